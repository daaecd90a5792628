"""Paper suite: the simulated experiments of Horaud et al. 2009 (Sec. 4.1, Fig. 4) on real motion.

The :data:`~pipeline.lab.bench.recipes.PAPER` capture (front kicks, seven cameras, rendered at 56 frames/s)
provides true silhouettes (``groundtruth/masks``) and true joints. Each *condition* (frame rate, silhouette
noise strength, number of observations) is computed in memory, calling the stage functions directly:

    true masks -> perturb_mask(strength) -> reconstruct(n_observations)
               -> + 20 % outliers uniform in the working volume -> Tracker(distance).track per frame

for the distances ``"normals"`` (the paper's points + normals), ``"points"`` and ``"algebraic"``
(Plänkers & Fua). The tracker starts from the data alone (no pose is given) and knows the subject's height,
as in the pipeline when capture.yaml states it. Scores, on the frames the tracker exported:

- the average joint-angle error: mean absolute error over the limb angles of :mod:`stages.export.angles`
  (knee and elbow flexion, hip and shoulder elevation), degrees (the paper plots radians); like the paper,
  the free motion (trunk orientation) is not in it;
- MPJPE over the 15 scored joints, millimetres, and the fraction of frames exported.

Experiments: (a) true and estimated left-knee and right-elbow flexion over 100 frames at 28 frames/s;
(b) error against silhouette noise; (c) error against frame rate (the 56 frames/s rendering subsampled, over
the same stretch of time); (d) error against the number of observations, points + normals against points.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.graph import EXPORTED_STATUSES
from pipeline.io import frames_io
from pipeline.io.capture import Capture
from pipeline.io.export_io import read_joints_csv
from pipeline.lab.bench.masks import perturb_mask
from pipeline.lab.bench.recipes import PAPER, describe, ensure_capture
from stages.export.angles import joint_angles
from stages.export.metrics import body_frames, constant_offsets, mask_iou, without_offsets
from stages.joints import JOINT_NAMES, SCORED_JOINTS
from stages.reconstruction import Observations, ReconstructionParams, reconstruct
from stages.tracking.params import TrackerParams
from stages.tracking.tracker import Tracker

DISTANCES = ("normals", "points", "algebraic")
#: Frame rate of the rendered capture, and the rate of experiments (a), (b) and (d).
CAPTURE_FPS = 56.0
BASE_FPS = 28.0
#: Observations per frame in (a), (b) and (c): the pipeline's default.
BASE_OBSERVATIONS = 1000
OUTLIER_FRACTION = 0.2
#: Angles averaged into the joint-angle error (the kinematic parameters, not the free motion).
LIMB_ANGLES = ("l_knee_flexion", "r_knee_flexion", "l_elbow_flexion", "r_elbow_flexion",
               "l_hip_elevation", "r_hip_elevation", "l_shoulder_elevation", "r_shoulder_elevation")
TRAJECTORY_ANGLES = ("l_knee_flexion", "r_elbow_flexion")
#: A frame whose MPJPE exceeds this is off track (the body lost, not merely imprecise), millimetres.
OFF_TRACK_MM = 100.0
SEED = 2009


@dataclass(frozen=True)
class PaperPlan:
    """Sizes of the experiments: frames at 28 frames/s per sequence, and the swept values."""

    frames: int
    noise_levels: tuple[float, ...]
    frame_rates: tuple[float, ...]
    observation_counts: tuple[int, ...]


FULL_PLAN = PaperPlan(frames=100, noise_levels=(0.0, 0.25, 0.5, 0.75, 1.0), frame_rates=(7.0, 14.0, 28.0, 56.0),
                      observation_counts=(50, 150, 250, 350, 450, 550))
QUICK_PLAN = PaperPlan(frames=10, noise_levels=(0.0, 1.0), frame_rates=(14.0, 28.0), observation_counts=(50, 550))


@dataclass(frozen=True)
class Condition:
    """One way of making the data: frame rate, silhouette noise strength, observations per frame."""

    fps: float
    strength: float
    n_observations: int

    def frames(self, plan: PaperPlan, available: int) -> list[int]:
        """Frame numbers of the 56 frames/s capture covering the time of ``plan.frames`` frames at 28/s."""
        step = int(round(CAPTURE_FPS / self.fps))
        count = int(round(plan.frames * self.fps / BASE_FPS))
        return [frame for frame in range(0, count * step, step) if frame < available]


BASE = Condition(BASE_FPS, 0.0, BASE_OBSERVATIONS)


def plan_conditions(plan: PaperPlan) -> dict[Condition, tuple[str, ...]]:
    """Every condition the experiments need, with the distances to track it with (shared ones once)."""
    needed: dict[Condition, set[str]] = {BASE: set(DISTANCES)}
    for strength in plan.noise_levels:
        needed.setdefault(Condition(BASE_FPS, strength, BASE_OBSERVATIONS), set()).update(DISTANCES)
    for fps in plan.frame_rates:
        needed.setdefault(Condition(fps, 0.0, BASE_OBSERVATIONS), set()).update(DISTANCES)
    for count in plan.observation_counts:
        needed.setdefault(Condition(BASE_FPS, 0.0, count), set()).update(("normals", "points"))
    return {condition: tuple(d for d in DISTANCES if d in distances) for condition, distances in needed.items()}


def add_outliers(points: np.ndarray, normals: np.ndarray, fraction: float, volume: np.ndarray,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Append uniform outliers so that they are ``fraction`` of the result (the paper's 20 %).

    Outlier points are uniform in the working volume (2, 3) and their normals uniform on the sphere.
    """
    count = int(round(len(points) * fraction / (1.0 - fraction)))
    extra = rng.uniform(volume[0], volume[1], (count, 3))
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return np.vstack([points, extra]), np.vstack([normals, directions])


def frame_observations(capture: Capture, frame: int, condition: Condition) -> tuple[Observations, int, float]:
    """One frame's observations under ``condition`` (outliers included), how many were reconstructed, and
    the noisy masks' mean IoU with the true ones.

    The random draws depend on the frame and camera only, so every condition with the same noise strength
    sees the same noise, and every distance the same data.
    """
    masks, ious = [], []
    for index, camera in enumerate(capture.rig.names):
        true = frames_io.read_mask(capture.root / "groundtruth" / "masks" / camera / frames_io.frame_name(frame))
        noisy = perturb_mask(true, condition.strength, np.random.default_rng([SEED, frame, index]))
        masks.append(noisy)
        ious.append(mask_iou(noisy, true))
    observations = reconstruct(masks, capture.rig, capture.volume,
                               ReconstructionParams(n_observations=condition.n_observations))
    points, normals = add_outliers(observations.points, observations.normals, OUTLIER_FRACTION, capture.volume,
                                   np.random.default_rng([SEED, frame, len(masks)]))
    return Observations(points, normals), len(observations), float(np.mean(ious))


def track_sequence(frames: Sequence[Observations], distance: str, capture: Capture) -> tuple[np.ndarray, list[str]]:
    """Joints (F, 17, 3) and statuses of the tracker run over ``frames`` with one distance."""
    # The height as stated, not weighed against a measured one: the paper's body has known dimensions, and a size
    # each distance measured for itself would compare the distances on the body's size as well as on the pose.
    params = TrackerParams(distance=distance, height_m=capture.height_m, stated_height_weight=1.0)
    tracker = Tracker(params, capture.volume)
    state, joints, statuses = None, [], []
    for observations in frames:
        result, state = tracker.track(state, observations)
        joints.append(result.joints)
        statuses.append(result.status)
    return np.array(joints), statuses


def run_condition(capture_dir: Path, plan: PaperPlan, condition: Condition, distances: tuple[str, ...]) -> dict:
    """Worker: make the condition's data once, track it with each distance; plain results for the parent."""
    capture = Capture.open(capture_dir)
    frames = condition.frames(plan, len(capture.frame_numbers))
    observations, counts, ious = zip(*(frame_observations(capture, frame, condition) for frame in frames),
                                     strict=True)
    tracks = {}
    for distance in distances:
        started = time.perf_counter()
        joints, statuses = track_sequence(observations, distance, capture)
        tracks[distance] = {"joints": joints, "statuses": statuses, "seconds": time.perf_counter() - started}
    return {"frames": frames, "iou": float(np.mean(ious)), "observations": float(np.mean(counts)), "tracks": tracks}


def score(joints: np.ndarray, statuses: Sequence[str], truth: np.ndarray) -> dict:
    """Accuracy of one tracked sequence on its exported frames.

    ``joints`` and ``truth`` are (F, 17, 3) in :data:`JOINT_NAMES` order, the same frames. A mean is
    dominated by the frames where the tracker has lost the body, so the median frame's angle error and the
    share of frames off track (MPJPE above :data:`OFF_TRACK_MM`) are reported beside it: they tell accuracy
    while tracking from robustness.

    The paper explains its own "relatively large error" by "a systematic offset between the
    ground-truth kinematic parameters and the estimated parameters": the animation's skeleton and the
    tracker's body put the joints at different places in the same flesh. Such an offset turns into an
    angle error that changes with the pose, and it can add to a tracker's own errors or happen to cancel
    them: hips placed forward (or behind) of the animation skeleton's tilt the thighs, and so change the
    hip angles, unless the knees are placed alike (``hips_forward_mm``, ``knees_forward_mm`` and
    ``hip_angle_error_deg`` show it).
    ``angle_error_offset_free_deg`` removes it: each joint's mean error in the true body's frame
    (`stages.export.metrics.constant_offsets`), taken over the sequence, is subtracted before the angles are
    measured.

    Returns
    -------
    dict
        ``angle_error_deg`` (the paper's average: mean over frames and limb angles), ``angle_error_median_deg``
        (median over frames of each frame's mean limb-angle error), ``angle_error_offset_free_deg``,
        ``hip_angle_error_deg`` (the two hip angles' mean error), ``hips_forward_mm`` and
        ``knees_forward_mm`` (the mean constant offset of each pair of joints along the body's forward
        axis, millimetres), ``mpjpe_mm``, ``off_track`` and ``fraction_estimated`` (exported frames /
        frames).
    """
    exported = np.isin(statuses, EXPORTED_STATUSES)
    if not exported.any():
        return {"angle_error_deg": float("nan"), "angle_error_median_deg": float("nan"),
                "angle_error_offset_free_deg": float("nan"), "hip_angle_error_deg": float("nan"),
                "hips_forward_mm": float("nan"), "knees_forward_mm": float("nan"), "mpjpe_mm": float("nan"),
                "off_track": float("nan"), "fraction_estimated": 0.0}
    joints, truth = joints[exported], truth[exported]
    names, estimated = joint_angles(joints)
    _, true = joint_angles(truth)
    limbs = [names.index(name) for name in LIMB_ANGLES]
    angle_error = np.abs(estimated[:, limbs] - true[:, limbs]).mean(axis=1)  # (F,) per frame
    frames = body_frames(truth, JOINT_NAMES)
    offset = constant_offsets(joints, truth, frames)  # (17, 3) in the body's frame
    _, offset_free = joint_angles(without_offsets(joints, frames, offset))
    hips = [names.index(name) for name in ("l_hip_elevation", "r_hip_elevation")]
    forward = 1000.0 * offset[:, 2]  # the pelvis frame's third axis, millimetres
    scored = [JOINT_NAMES.index(name) for name in SCORED_JOINTS]
    frame_mpjpe = 1000.0 * np.linalg.norm(joints[:, scored] - truth[:, scored], axis=2).mean(axis=1)
    return {"angle_error_deg": float(angle_error.mean()), "angle_error_median_deg": float(np.median(angle_error)),
            "angle_error_offset_free_deg": float(np.abs(offset_free[:, limbs] - true[:, limbs]).mean()),
            "hip_angle_error_deg": float(np.abs(estimated[:, hips] - true[:, hips]).mean()),
            "hips_forward_mm": float(forward[[JOINT_NAMES.index("l_hip"), JOINT_NAMES.index("r_hip")]].mean()),
            "knees_forward_mm": float(forward[[JOINT_NAMES.index("l_knee"), JOINT_NAMES.index("r_knee")]].mean()),
            "mpjpe_mm": float(frame_mpjpe.mean()), "off_track": float(np.mean(frame_mpjpe > OFF_TRACK_MM)),
            "fraction_estimated": float(exported.mean())}


def trajectories(joints: np.ndarray, truth: np.ndarray, frames: Sequence[int]) -> dict:
    """Experiment (a): true and estimated :data:`TRAJECTORY_ANGLES` per frame (degrees), time in seconds."""
    names, estimated = joint_angles(joints)
    _, true = joint_angles(truth)
    return {"time_s": [frame / CAPTURE_FPS for frame in frames],
            **{name: {"truth": true[:, names.index(name)].tolist(),
                      "estimate": estimated[:, names.index(name)].tolist()} for name in TRAJECTORY_ANGLES}}


def condition_rows(x: float, result: dict, truth: np.ndarray) -> list[dict]:
    """One row per distance of a computed condition; ``truth`` (T, 17, 3) is indexed by frame number."""
    return [{"x": x, "distance": distance, "mask_iou": result["iou"], "observations": result["observations"],
             "frames": len(result["frames"]), "seconds": track["seconds"],
             **score(track["joints"], track["statuses"], truth[result["frames"]])}
            for distance, track in result["tracks"].items()]


def sweep_rows(results: dict[Condition, dict], truth: np.ndarray, sweep: str, plan: PaperPlan) -> list[dict]:
    """Rows ``{x, distance, angle_error_deg, mpjpe_mm, fraction_estimated, ...}`` of one experiment."""
    conditions = {
        "noise": [(s, Condition(BASE_FPS, s, BASE_OBSERVATIONS)) for s in plan.noise_levels],
        "fps": [(fps, Condition(fps, 0.0, BASE_OBSERVATIONS)) for fps in plan.frame_rates],
        "observations": [(n, Condition(BASE_FPS, 0.0, n)) for n in plan.observation_counts],
    }[sweep]
    return [row for x, condition in conditions for row in condition_rows(x, results[condition], truth)]


def run_paper(out: Path, captures: Path, *, quick: bool, workers: int) -> dict:
    """All four experiments (see the module docstring)."""
    recipe = PAPER.quick() if quick else PAPER
    plan = QUICK_PLAN if quick else FULL_PLAN
    path = ensure_capture(captures, recipe)
    frames, names, truth = read_joints_csv(path / "groundtruth" / "joints.csv")
    if not np.array_equal(frames, np.arange(len(frames))):
        raise RuntimeError(f"{path}: expected ground truth for frames 0..{len(frames) - 1}, one row each")
    truth = truth[:, [names.index(name) for name in JOINT_NAMES]]
    conditions = plan_conditions(plan)
    # Longest conditions first, so that the pool does not end waiting on one big task.
    order = sorted(conditions, key=lambda c: -len(c.frames(plan, len(frames))) * len(conditions[c]))
    with ProcessPoolExecutor(max(1, workers)) as pool:
        futures = {c: pool.submit(run_condition, path, plan, c, conditions[c]) for c in order}
        results = {c: future.result() for c, future in futures.items()}
    base = results[BASE]
    return {
        "capture": recipe.name, "recipe": describe(recipe), "frames": plan.frames,
        "outlier_fraction": OUTLIER_FRACTION, "limb_angles": list(LIMB_ANGLES), "off_track_mm": OFF_TRACK_MM,
        "trajectories": trajectories(base["tracks"]["normals"]["joints"], truth[base["frames"]], base["frames"]),
        "base": condition_rows(BASE_FPS, base, truth),
        "noise": sweep_rows(results, truth, "noise", plan),
        "fps": sweep_rows(results, truth, "fps", plan),
        "observations": sweep_rows(results, truth, "observations", plan),
    }
