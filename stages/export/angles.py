"""Joint angles from joint centres: flexion of knees and elbows, hip and shoulder angles, trunk lean.

Every angle is the angle in degrees (0..180) between two directions, so it needs no body-fixed
axes and means the same for a tracker's output and for ground truth:

==================== ================================================ ===============================
name                 between                                          reading
==================== ================================================ ===============================
l/r_knee_flexion     thigh (hip -> knee) and shank (knee -> ankle)    0 = straight leg
l/r_elbow_flexion    upper arm (shoulder -> elbow), forearm (-> wrist) 0 = straight arm
l/r_hip_angle        trunk downwards (neck -> pelvis) and the thigh    0 = standing, 90 = thigh level
l/r_shoulder_angle   trunk downwards (neck -> pelvis), the upper arm   0 = arm hanging, 180 = overhead
trunk_inclination    trunk upwards (pelvis -> neck) and world +z       0 = upright, 90 = lying
==================== ================================================ ===============================

Hip and shoulder angles are the total elevation of the segment from the trunk axis, whatever its
direction (flexion, abduction or a mix): a joint centre alone does not separate the planes.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from stages.joints import JOINT_NAMES

#: name -> ((from, to) of the first direction, (from, to) of the second); "+z" is world up.
ANGLE_DEFINITIONS: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {
    "l_knee_flexion": (("l_hip", "l_knee"), ("l_knee", "l_ankle")),
    "r_knee_flexion": (("r_hip", "r_knee"), ("r_knee", "r_ankle")),
    "l_elbow_flexion": (("l_shoulder", "l_elbow"), ("l_elbow", "l_wrist")),
    "r_elbow_flexion": (("r_shoulder", "r_elbow"), ("r_elbow", "r_wrist")),
    "l_hip_angle": (("neck", "pelvis"), ("l_hip", "l_knee")),
    "r_hip_angle": (("neck", "pelvis"), ("r_hip", "r_knee")),
    "l_shoulder_angle": (("neck", "pelvis"), ("l_shoulder", "l_elbow")),
    "r_shoulder_angle": (("neck", "pelvis"), ("r_shoulder", "r_elbow")),
    "trunk_inclination": (("pelvis", "neck"), ("+z", "+z")),
}
ANGLE_NAMES: tuple[str, ...] = tuple(ANGLE_DEFINITIONS)

#: Decimal places of angles in angles.csv (a thousandth of a degree).
ANGLE_DECIMALS = 3


def angle_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angles in degrees between the vectors ``u (..., 3)`` and ``v (..., 3)``, in [0, 180].

    ``atan2(|u x v|, u . v)`` keeps full precision near 0 and 180 degrees, where ``arccos`` does not.
    """
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(u, v), axis=-1), np.einsum("...i,...i->...", u, v)))


def _direction(joints: np.ndarray, index: dict[str, int], segment: tuple[str, str]) -> np.ndarray:
    start, end = segment
    if start == "+z":
        return np.broadcast_to([0.0, 0.0, 1.0], joints.shape[:1] + (3,))
    return joints[:, index[end]] - joints[:, index[start]]


def available_angles(names: Sequence[str]) -> tuple[str, ...]:
    """The angles of :data:`ANGLE_NAMES` whose joints are all in ``names``."""
    present = set(names) | {"+z"}
    return tuple(name for name, (a, b) in ANGLE_DEFINITIONS.items() if set(a + b) <= present)


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
    angles : (F, K) float, degrees
    """
    joints = np.asarray(joints, dtype=np.float64)
    if joints.ndim != 3 or joints.shape[1:] != (len(names), 3):
        raise ValueError(f"joints must have shape (F, {len(names)}, 3), got {joints.shape}")
    index = {name: i for i, name in enumerate(names)}
    angle_names = available_angles(names)
    angles = np.empty((len(joints), len(angle_names)))
    for k, name in enumerate(angle_names):
        first, second = ANGLE_DEFINITIONS[name]
        angles[:, k] = angle_between(_direction(joints, index, first), _direction(joints, index, second))
    return angle_names, angles


def format_angles_csv(frames: np.ndarray, angle_names: Sequence[str], angles: np.ndarray) -> str:
    """The text of ``angles.csv``: header ``frame,<angle names>``, one row per frame, degrees.

    Parameters
    ----------
    frames : (F,) int
    angle_names : sequence of K str
    angles : (F, K) float, degrees
    """
    angles = np.asarray(angles, dtype=np.float64)
    if angles.shape != (len(frames), len(angle_names)):
        raise ValueError(f"angles must have shape ({len(frames)}, {len(angle_names)}), got {angles.shape}")
    lines = [",".join(("frame", *angle_names))]
    lines += [",".join([str(int(frame))] + [f"{value:.{ANGLE_DECIMALS}f}" for value in row])
              for frame, row in zip(frames, angles, strict=True)]
    return "\n".join(lines) + "\n"
