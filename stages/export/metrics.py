"""Accuracy of estimated joints against ground truth, and of silhouettes against true masks.

Definitions (the usual ones of the human-pose literature):

- joint error: Euclidean distance between an estimated and a true joint centre of the same frame;
- MPJPE (mean per-joint position error): the mean joint error over scored joints and matched frames,
  reported in millimetres, overall, per joint and per frame;
- PCK@t: the fraction of (frame, joint) pairs whose error is at most t;
- angle error: mean absolute difference (wrapped to +-180 degrees) of an angle of :mod:`stages.export.angles`
  over the matched frames where both define it;
- constant offset: a joint's mean error expressed in the true body's frame (``bvh.pelvis_frame``: left, up,
  forward), over the matched frames. Two skeletons can put a joint at different places in the same flesh
  (a shoulder at the top of the humerus or inside the deltoid, a hip centre nearer or farther from the
  midline); that difference moves with the body and shows here rather than as scatter. The offset-free
  MPJPE is the MPJPE after each joint's constant offset is subtracted (in that frame, frame by frame): what
  is left of the error once the two skeletons' conventions are set aside. The offsets are measured on the
  frames it scores, so it is what the best fixed correction of each joint would leave, a lower bound rather
  than an accuracy any tracker could claim. It needs the pelvis, neck and hips among the scored joints;
- acceleration error: the mean norm of the difference between estimated and true accelerations (second
  differences over three consecutive matched frames, m/s²), per joint: the jitter of a trajectory, which
  MPJPE barely sees, and which smoothing (``export.filter_cutoff_hz``) lowers;
- fraction estimated: matched frames / ground-truth frames (a frame the tracker lost has no row and
  counts as not estimated; it does not enter MPJPE);
- silhouette IoU: |estimate AND truth| / |estimate OR truth| of binary masks.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from calib.errors import InputError
from stages.export.angles import joint_angles
from stages.export.bvh import pelvis_frame
from stages.joints import SCORED_JOINTS

#: PCK thresholds reported by default, millimetres.
PCK_THRESHOLDS_MM: tuple[float, ...] = (50.0, 100.0)


@dataclass(frozen=True)
class JointMetrics:
    """Accuracy of one estimated sequence against ground truth (units in the field names).

    ``frames``, ``per_frame_mm`` and ``errors_mm`` keep the per-frame detail for plots; :meth:`summary`
    is the JSON-ready digest written to ``metrics.json``.
    """

    joints: tuple[str, ...]                 # scored joints present in both sequences
    frames: np.ndarray                      # (M,) matched frame numbers
    errors_mm: np.ndarray                   # (M, J) joint errors
    truth_frame_count: int
    pck_thresholds_mm: tuple[float, ...]
    angle_errors_deg: dict[str, float]      # mean absolute error per angle
    acceleration_errors_m_s2: dict[str, float] = field(default_factory=dict)  # per joint; {} without a frame time
    offsets_mm: np.ndarray | None = None    # (J, 3) constant offsets (left, up, forward); None: no body frame
    offset_free_errors_mm: np.ndarray | None = None  # (M, J) joint errors after the constant offsets

    @property
    def per_frame_mm(self) -> np.ndarray:
        """(M,) MPJPE of each matched frame."""
        return self.errors_mm.mean(axis=1)

    @property
    def per_joint_mm(self) -> dict[str, float]:
        return {name: float(e) for name, e in zip(self.joints, self.errors_mm.mean(axis=0), strict=True)}

    @property
    def mpjpe_mm(self) -> float:
        return float(self.errors_mm.mean())

    @property
    def offset_free_mpjpe_mm(self) -> float | None:
        return None if self.offset_free_errors_mm is None else float(self.offset_free_errors_mm.mean())

    def pck(self, threshold_mm: float) -> float:
        """Fraction of (frame, joint) errors at most ``threshold_mm``."""
        return float(np.mean(self.errors_mm <= threshold_mm))

    @property
    def fraction_estimated(self) -> float:
        return len(self.frames) / self.truth_frame_count

    def summary(self) -> dict:
        """Plain-data digest: numbers, names and the worst frame."""
        worst = int(np.argmax(self.per_frame_mm))
        return {
            "scored_joints": list(self.joints),
            "frames_scored": len(self.frames),
            "truth_frames": self.truth_frame_count,
            "fraction_estimated": self.fraction_estimated,
            "mpjpe_mm": self.mpjpe_mm,
            "per_joint_mpjpe_mm": self.per_joint_mm,
            "pck": {f"{threshold:g}mm": self.pck(threshold) for threshold in self.pck_thresholds_mm},
            "worst_frame": {"frame": int(self.frames[worst]), "mpjpe_mm": float(self.per_frame_mm[worst])},
            "angle_errors_deg": dict(self.angle_errors_deg),
            "acceleration_error_m_s2": (float(np.mean(list(self.acceleration_errors_m_s2.values())))
                                        if self.acceleration_errors_m_s2 else None),
            "per_joint_acceleration_error_m_s2": dict(self.acceleration_errors_m_s2),
            "offset_free_mpjpe_mm": self.offset_free_mpjpe_mm,
            "per_joint_offset_mm": (None if self.offsets_mm is None else
                                    {name: [float(v) for v in offset]
                                     for name, offset in zip(self.joints, self.offsets_mm, strict=True)}),
        }


def joint_errors(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(F, J) Euclidean distances between ``estimate (F, J, 3)`` and ``truth (F, J, 3)`` (same units)."""
    difference = np.asarray(estimate, dtype=np.float64) - np.asarray(truth, dtype=np.float64)
    return np.linalg.norm(difference, axis=-1)


#: The joints that define the body's frame in which constant offsets are measured (``bvh.pelvis_frame``).
BODY_FRAME_JOINTS = ("l_hip", "r_hip", "pelvis", "neck")


def body_frames(truth: np.ndarray, names: Sequence[str]) -> np.ndarray | None:
    """(F, 3, 3) the true body's frame in each frame (columns: left, up, forward), or None when ``names`` lack
    one of :data:`BODY_FRAME_JOINTS`."""
    if not all(name in names for name in BODY_FRAME_JOINTS):
        return None
    return pelvis_frame({name: np.asarray(truth)[:, list(names).index(name)] for name in BODY_FRAME_JOINTS})


def constant_offsets(estimate: np.ndarray, truth: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """(J, 3) each joint's mean error (estimate − truth, same units) in the body's ``frames`` (F, 3, 3)."""
    return np.einsum("fba,fjb->fja", frames, np.asarray(estimate) - np.asarray(truth)).mean(axis=0)


def without_offsets(estimate: np.ndarray, frames: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(F, J, 3) ``estimate`` with the constant ``offsets`` (J, 3), given in the body's ``frames``, taken off."""
    return np.asarray(estimate) - np.einsum("fab,jb->fja", frames, offsets)


def angle_errors(estimate: np.ndarray, truth: np.ndarray, names: Sequence[str]) -> dict[str, float]:
    """Mean absolute angle error (degrees) per angle of :mod:`stages.export.angles` computable from ``names``.

    Parameters
    ----------
    estimate, truth : (F, J, 3) float, matched frames, joints in the order of ``names``
    """
    angle_names, estimated = joint_angles(estimate, names)
    _, true = joint_angles(truth, names)
    difference = np.abs((estimated - true + 180.0) % 360.0 - 180.0)  # NaN where either is undefined
    defined = ~np.isnan(difference)
    return {name: float(difference[defined[:, k], k].mean()) for k, name in enumerate(angle_names)
            if defined[:, k].any()}


def acceleration_errors(frames: np.ndarray, estimate: np.ndarray, truth: np.ndarray, names: Sequence[str],
                        frame_time_s: float) -> dict[str, float]:
    """Mean acceleration error (m/s²) per joint over the matched frames' consecutive triples.

    Parameters
    ----------
    frames : (F,) int, ascending matched frame numbers
    estimate, truth : (F, J, 3) float, metres
    frame_time_s : float, seconds per capture frame (1 / fps)

    A triple (f - s, f, f + s) counts when both gaps equal the smallest gap s between matched frames
    (the capture's frame step); none: {}.
    """
    frames = np.asarray(frames, dtype=np.int64)
    if len(frames) < 3:
        return {}
    gaps = np.diff(frames)
    step = int(gaps.min())
    middle = np.flatnonzero((gaps[:-1] == step) & (gaps[1:] == step)) + 1
    if not len(middle):
        return {}

    def acceleration(x: np.ndarray) -> np.ndarray:
        return (x[middle + 1] - 2.0 * x[middle] + x[middle - 1]) / (step * frame_time_s) ** 2

    error = np.linalg.norm(acceleration(np.asarray(estimate, dtype=np.float64))
                           - acceleration(np.asarray(truth, dtype=np.float64)), axis=-1)
    return {name: float(e) for name, e in zip(names, error.mean(axis=0), strict=True)}


def evaluate_joints(
    estimate_frames: np.ndarray, estimate_names: Sequence[str], estimate: np.ndarray,
    truth_frames: np.ndarray, truth_names: Sequence[str], truth: np.ndarray,
    *, scored: Sequence[str] = SCORED_JOINTS, pck_thresholds_mm: Sequence[float] = PCK_THRESHOLDS_MM,
    frame_time_s: float | None = None,
) -> JointMetrics:
    """Score an estimated joint sequence against ground truth on their common frames.

    Parameters
    ----------
    estimate_frames : (F,) int;  estimate_names : J names;  estimate : (F, J, 3) float, metres
    truth_frames : (T,) int;  truth_names : K names;  truth : (T, K, 3) float, metres
    scored : joint names to score (those present in both sequences are used)
    frame_time_s : seconds per capture frame (1 / fps), for the acceleration errors; None: not computed

    Raises
    ------
    InputError
        When the two sequences share no scored joint or no frame.
    """
    joints = tuple(name for name in scored if name in estimate_names and name in truth_names)
    if not joints:
        raise InputError(f"estimate joints {list(estimate_names)} and truth joints {list(truth_names)} share "
                         f"no scored joint (expected some of {', '.join(scored)})")
    common, in_estimate, in_truth = np.intersect1d(estimate_frames, truth_frames, return_indices=True)
    if len(common) == 0:
        raise InputError(f"estimate frames {_span(estimate_frames)} and truth frames {_span(truth_frames)} "
                         "do not overlap (expected the same frame numbering)")
    est = np.asarray(estimate)[in_estimate][:, [list(estimate_names).index(n) for n in joints]]
    tru = np.asarray(truth)[in_truth][:, [list(truth_names).index(n) for n in joints]]
    frames = body_frames(tru, joints)
    offsets = None if frames is None else constant_offsets(est, tru, frames)
    return JointMetrics(
        joints=joints,
        frames=common.astype(np.int64),
        errors_mm=1000.0 * joint_errors(est, tru),
        truth_frame_count=len(truth_frames),
        pck_thresholds_mm=tuple(float(t) for t in pck_thresholds_mm),
        angle_errors_deg=angle_errors(est, tru, joints),
        acceleration_errors_m_s2={} if frame_time_s is None else acceleration_errors(common, est, tru, joints,
                                                                                      frame_time_s),
        offsets_mm=None if offsets is None else 1000.0 * offsets,
        offset_free_errors_mm=None if offsets is None else 1000.0 * joint_errors(without_offsets(est, frames, offsets),
                                                                                 tru),
    )


def _span(frames: np.ndarray) -> str:
    return f"{int(np.min(frames))}..{int(np.max(frames))}" if len(frames) else "(none)"


def mask_iou(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Intersection over union of two ``(H, W)`` masks (nonzero = person); 1.0 when both are empty."""
    if estimate.shape != truth.shape:
        raise ValueError(f"masks differ in shape: {estimate.shape} and {truth.shape}")
    a, b = estimate > 0, truth > 0
    union = np.count_nonzero(a | b)
    return 1.0 if union == 0 else np.count_nonzero(a & b) / union
