"""Joint angles from joint centres, in an ISB-like convention (docs/exports.md has the full definitions).

Segment frames (ISB, Wu et al. 2002 and 2005: X anterior, Y superior / proximal, Z to the right):

- pelvis: Z from the left to the right hip, Y the trunk direction (pelvis -> neck) made orthogonal to
  Z, X = Y x Z. joints.csv has no point that fixes the pelvis's tilt about the hip axis, so its Y is
  the trunk's: hip angles are measured against the trunk and include any lumbar flexion.
- thorax: Z from the left to the right shoulder, Y the trunk direction made orthogonal to it, X = Y x Z.
- thigh, upper arm: Y from the distal joint (knee, elbow) to the proximal one (hip, shoulder); X
  (anterior) from the plane of the limb's hinge, the knee's or elbow's (below).

A left limb is mirrored through its proximal frame's sagittal (X-Y) plane and then measured as a
right one, so every angle means the same on both sides: flexion, abduction and internal rotation
are positive on the left as on the right.

==================== ======================================================================================
angle                definition (degrees)
==================== ======================================================================================
hip_flexion          the thigh in the pelvis frame, split into swing and twist: the swing (the smallest rotation
hip_abduction        taking the pelvis's Y onto the thigh's) as its attitude vector's components, flexion about
hip_rotation         Z and abduction about -X (Woltring 1994), then internal rotation, the twist about the
                     thigh's own axis that remains. One plane at a time, these are the ISB's Cardan angles; unlike
                     a Cardan sequence they have no gimbal lock where a kick or a raised arm goes (abduction near
                     90 degrees), only with the limb pointing straight up along the trunk. Rotation needs the knee
                     bent by at least :data:`MIN_HINGE_FLEXION_DEG` (the knee's plane sets the thigh's X); else empty
knee_flexion         the angle between thigh and shank, negative when the knee is hyperextended: the ankle in
                     front of the thigh's line, seen in the thigh's swing frame, by less than
                     :data:`MAX_HYPEREXTENSION_DEG` (a larger bend is a flexion, whichever way it seems to go)
ankle_dorsiflexion   90 - the angle between the shank (ankle -> knee) and the foot (ankle -> toe): positive
                     when the toes come up towards the shin (needs the toes)
shoulder_flexion     the same for the upper arm in the thorax frame, the elbow's plane setting the arm's X
shoulder_abduction   (rotation empty when the elbow is straighter than :data:`MIN_HINGE_FLEXION_DEG`)
shoulder_rotation
elbow_flexion        the angle between upper arm and forearm, 0 = straight, never negative: the arm rotates by
                     more than 90 degrees, so the side the forearm bends to cannot tell a hyperextended elbow
                     from a rotated arm
hip_elevation        the angle between the trunk downwards (neck -> pelvis) and the thigh: how far the thigh
shoulder_elevation   (upper arm) is raised in whichever direction
trunk_inclination    the angle between the trunk (pelvis -> neck) and world +z: 0 = upright, 90 = lying
==================== ======================================================================================

Angles are NaN where undefined (written as empty cells in angles.csv).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from stages.joints import JOINT_NAMES

#: A limb's axial rotation is given only when its hinge (knee, elbow) is bent at least this much: a
#: straighter limb's plane, which sets the rotation, is lost in the joints' noise (2 cm of noise across
#: a 45 cm shank bent by 20 degrees is 7 degrees of rotation).
MIN_HINGE_FLEXION_DEG = 20.0

#: A knee bent "forwards" by less than this reads as hyperextended, by more as flexed: no knee hyperextends
#: that far (genu recurvatum is 5-15 degrees), while a thigh raised high or rotated far turns the frame the
#: bend is judged in (Codman's paradox), so a deep flexion can look forwards.
MAX_HYPEREXTENSION_DEG = 30.0

#: Decimal places of angles in angles.csv (a thousandth of a degree).
ANGLE_DECIMALS = 3

_SIDES = ("l", "r")
_UP = np.array([0.0, 0.0, 1.0])
#: Below this sine a limb counts as along its proximal frame's Y (no swing, so no flexion or abduction).
_PARALLEL = 1e-12


def angle_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angles in degrees between the vectors ``u (..., 3)`` and ``v (..., 3)``, in [0, 180].

    ``atan2(|u x v|, u . v)`` keeps full precision near 0 and 180 degrees, where ``arccos`` does not.
    """
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(u, v), axis=-1), np.einsum("...i,...i->...", u, v)))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _trunk_frame(P: dict[str, np.ndarray], left: str, right: str) -> np.ndarray:
    """(F, 3, 3) columns X (anterior), Y (up the trunk), Z (left -> right joint) of a pelvis or thorax frame."""
    z = _unit(P[right] - P[left])
    y = P["neck"] - P["pelvis"]
    y = _unit(y - np.einsum("fi,fi->f", y, z)[:, None] * z)
    return np.stack([np.cross(y, z), y, z], axis=-1)


def _local(frame: np.ndarray, v: np.ndarray, side: str) -> np.ndarray:
    """``v (F, 3)`` in ``frame``'s coordinates, mirrored through its X-Y plane for a left limb."""
    local = np.einsum("fij,fi->fj", frame, v)
    if side == "l":
        local = local * np.array([1.0, 1.0, -1.0])
    return local


def _swing(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Swing of a right limb whose proximal axis is ``axis (F, 3)`` (unit, in its proximal frame), radians.

    The swing is the smallest rotation taking the frame's Y onto ``axis``: an angle (the elevation) about
    an axis in the X-Z plane; flexion and abduction are its attitude-vector components about Z and about
    -X (Woltring 1994), so that elevation² = flexion² + abduction². Returns (flexion, abduction, elevation).
    """
    elevation = np.arctan2(np.hypot(axis[:, 0], axis[:, 2]), axis[:, 1])
    across = np.hypot(axis[:, 0], axis[:, 2])
    scale = np.divide(elevation, across, out=np.zeros_like(across), where=across > _PARALLEL)
    return -scale * axis[:, 0], -scale * axis[:, 2], elevation


def _unswung(local: np.ndarray, flexion: np.ndarray, abduction: np.ndarray) -> np.ndarray:
    """``local (F, 3)`` with the swing of attitude vector (-abduction, 0, flexion) undone."""
    return Rotation.from_rotvec(np.column_stack([abduction, np.zeros_like(flexion), -flexion])).apply(local)


def _limb(P: dict[str, np.ndarray], side: str, proximal: str, hinge: str, distal: str,
          frame: np.ndarray, bends_forward: bool) -> dict[str, np.ndarray]:
    """Flexion, abduction, rotation of the proximal joint and the hinge's flexion, degrees (module docstring).

    ``bends_forward``: the distal segment swings anterior when the hinge flexes (elbow), else posterior (knee).
    """
    p, h, d = (f"{side}_{name}" for name in (proximal, hinge, distal))
    flexion, abduction, _ = _swing(_local(frame, _unit(P[p] - P[h]), side))
    distal_dir = _unswung(_local(frame, _unit(P[d] - P[h]), side), flexion, abduction)
    # distal_dir = (±sin k cos r, -cos k, ∓sin k sin r) for hinge flexion k and rotation r (+ elbow, - knee)
    forward = distal_dir[:, 0] if bends_forward else -distal_dir[:, 0]
    sideways = -distal_dir[:, 2] if bends_forward else distal_dir[:, 2]
    bend = np.hypot(forward, sideways)
    if bends_forward:  # unsigned flexion, rotation over the full turn
        hinge_flexion, rotation = np.arctan2(bend, -distal_dir[:, 1]), np.arctan2(sideways, forward)
    else:  # signed flexion: a shank bent forwards, by no more than a knee can hyperextend
        magnitude = np.arctan2(bend, -distal_dir[:, 1])
        sign = np.where((forward < 0) & (magnitude < np.radians(MAX_HYPEREXTENSION_DEG)), -1.0, 1.0)
        hinge_flexion, rotation = sign * magnitude, np.arctan2(sign * sideways, sign * forward)
    rotation = np.where(np.abs(np.degrees(hinge_flexion)) >= MIN_HINGE_FLEXION_DEG, rotation, np.nan)
    return {"flexion": np.degrees(flexion), "abduction": np.degrees(abduction), "rotation": np.degrees(rotation),
            "hinge": np.degrees(hinge_flexion)}


def _hip(part: str, side: str) -> Callable:
    return lambda P: _limb(P, side, "hip", "knee", "ankle", _trunk_frame(P, "l_hip", "r_hip"), False)[part]


def _shoulder(part: str, side: str) -> Callable:
    return lambda P: _limb(P, side, "shoulder", "elbow", "wrist", _trunk_frame(P, "l_shoulder", "r_shoulder"),
                           True)[part]


def _ankle(side: str) -> Callable:
    return lambda P: 90.0 - angle_between(P[f"{side}_knee"] - P[f"{side}_ankle"], P[f"{side}_toe"] - P[f"{side}_ankle"])


def _elevation(proximal: str, distal: str) -> Callable:
    return lambda P: angle_between(P["pelvis"] - P["neck"], P[distal] - P[proximal])


def _trunk_inclination(P: dict[str, np.ndarray]) -> np.ndarray:
    return angle_between(P["neck"] - P["pelvis"], np.broadcast_to(_UP, P["neck"].shape))


_PELVIS = ("pelvis", "neck", "l_hip", "r_hip")
_THORAX = ("pelvis", "neck", "l_shoulder", "r_shoulder")

#: name -> (joints it needs, function of {joint: (F, 3) positions} -> (F,) degrees), in angles.csv order.
ANGLE_DEFINITIONS: dict[str, tuple[tuple[str, ...], Callable]] = {}
_SWING_TWIST = ("flexion", "abduction", "rotation")
for _s in _SIDES:
    ANGLE_DEFINITIONS.update({f"{_s}_hip_{part}": ((*_PELVIS, f"{_s}_knee", f"{_s}_ankle"), _hip(part, _s))
                              for part in _SWING_TWIST})
for _s in _SIDES:
    ANGLE_DEFINITIONS[f"{_s}_knee_flexion"] = ((*_PELVIS, f"{_s}_knee", f"{_s}_ankle"), _hip("hinge", _s))
for _s in _SIDES:
    ANGLE_DEFINITIONS[f"{_s}_ankle_dorsiflexion"] = ((f"{_s}_knee", f"{_s}_ankle", f"{_s}_toe"), _ankle(_s))
for _s in _SIDES:
    ANGLE_DEFINITIONS.update({f"{_s}_shoulder_{part}": ((*_THORAX, f"{_s}_elbow", f"{_s}_wrist"), _shoulder(part, _s))
                              for part in _SWING_TWIST})
for _s in _SIDES:
    ANGLE_DEFINITIONS[f"{_s}_elbow_flexion"] = ((*_THORAX, f"{_s}_elbow", f"{_s}_wrist"), _shoulder("hinge", _s))
for _s in _SIDES:
    ANGLE_DEFINITIONS[f"{_s}_hip_elevation"] = (("pelvis", "neck", f"{_s}_hip", f"{_s}_knee"),
                                                _elevation(f"{_s}_hip", f"{_s}_knee"))
for _s in _SIDES:
    ANGLE_DEFINITIONS[f"{_s}_shoulder_elevation"] = (("pelvis", "neck", f"{_s}_shoulder", f"{_s}_elbow"),
                                                     _elevation(f"{_s}_shoulder", f"{_s}_elbow"))
ANGLE_DEFINITIONS["trunk_inclination"] = (("pelvis", "neck"), _trunk_inclination)
del _s

ANGLE_NAMES: tuple[str, ...] = tuple(ANGLE_DEFINITIONS)


def available_angles(names: Sequence[str]) -> tuple[str, ...]:
    """The angles of :data:`ANGLE_NAMES` whose joints are all in ``names``."""
    present = set(names)
    return tuple(name for name, (needed, _) in ANGLE_DEFINITIONS.items() if set(needed) <= present)


def joint_angles(joints: np.ndarray,
                 names: Sequence[str] = JOINT_NAMES) -> tuple[tuple[str, ...], np.ndarray]:
    """The angles of the module docstring for every frame.

    Parameters
    ----------
    joints : (F, J, 3) float, metres, world frame (+z up), in the order of ``names``
    names : sequence of J str

    Returns
    -------
    angle_names : tuple of K str
        The angles computable from ``names`` (:func:`available_angles`), in :data:`ANGLE_NAMES` order.
    angles : (F, K) float, degrees; NaN where an angle is undefined (a rotation of a straight limb)
    """
    joints = np.asarray(joints, dtype=np.float64)
    if joints.ndim != 3 or joints.shape[1:] != (len(names), 3):
        raise ValueError(f"joints must have shape (F, {len(names)}, 3), got {joints.shape}")
    P = {name: joints[:, i] for i, name in enumerate(names)}
    angle_names = available_angles(names)
    angles = np.empty((len(joints), len(angle_names)))
    with np.errstate(invalid="ignore", divide="ignore"):  # a zero-length direction gives NaN, as it should
        for k, name in enumerate(angle_names):
            angles[:, k] = ANGLE_DEFINITIONS[name][1](P)
    return angle_names, angles


def format_angles_csv(frames: np.ndarray, angle_names: Sequence[str], angles: np.ndarray) -> str:
    """The text of ``angles.csv``: header ``frame,<angle names>``, one row per frame, degrees, empty if undefined.

    Parameters
    ----------
    frames : (F,) int
    angle_names : sequence of K str
    angles : (F, K) float, degrees (NaN = undefined)
    """
    angles = np.asarray(angles, dtype=np.float64)
    if angles.shape != (len(frames), len(angle_names)):
        raise ValueError(f"angles must have shape ({len(frames)}, {len(angle_names)}), got {angles.shape}")
    lines = [",".join(("frame", *angle_names))]
    lines += [",".join([str(int(frame))] + ["" if np.isnan(value) else f"{value:.{ANGLE_DECIMALS}f}" for value in row])
              for frame, row in zip(frames, angles, strict=True)]
    return "\n".join(lines) + "\n"
