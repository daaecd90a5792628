"""Random but valid articulated motions for the export tests: every bone keeps its length."""

import numpy as np
from scipy.spatial.transform import Rotation

from stages.joints import JOINT_NAMES

# (parent, child, length in metres, rest direction in the body frame: x = right, y = forward, z = up)
_BONES = (
    ("pelvis", "neck", 0.52, (0, 0, 1)), ("neck", "head", 0.22, (0, 0, 1)),
    ("neck", "l_shoulder", 0.19, (-1, 0, 0)), ("neck", "r_shoulder", 0.19, (1, 0, 0)),
    ("l_shoulder", "l_elbow", 0.29, (-0.3, 0, -1)), ("r_shoulder", "r_elbow", 0.29, (0.3, 0, -1)),
    ("l_elbow", "l_wrist", 0.26, (-0.1, 0.5, -1)), ("r_elbow", "r_wrist", 0.26, (0.1, 0.5, -1)),
    ("l_hip", "l_knee", 0.43, (0, 0, -1)), ("r_hip", "r_knee", 0.43, (0, 0, -1)),
    ("l_knee", "l_ankle", 0.41, (0, -0.2, -1)), ("r_knee", "r_ankle", 0.41, (0, -0.2, -1)),
    ("l_ankle", "l_toe", 0.14, (0, 1, -0.3)), ("r_ankle", "r_toe", 0.14, (0, 1, -0.3)),
)
HALF_HIP_WIDTH_M = 0.09


def _smooth_noise(rng: np.random.Generator, n_frames: int, dims: int, amplitude: float) -> np.ndarray:
    """(n_frames, dims) sums of three random sinusoids: smooth random curves."""
    t = np.arange(n_frames)[:, None, None]
    freq = rng.uniform(0.005, 0.03, (1, dims, 3))  # cycles per frame
    phase = rng.uniform(0, 2 * np.pi, (1, dims, 3))
    return amplitude * np.sin(2 * np.pi * freq * t + phase).sum(axis=-1) / 3


def random_motion(n_frames: int = 60, *, seed: int = 0, amplitude: float = 1.0) -> np.ndarray:
    """(n_frames, 17, 3) joint centres in JOINT_NAMES order (metres, +z up) with constant bone lengths.

    The pelvis wanders and turns about the vertical; every bone direction wobbles smoothly around a
    standing pose by up to about ``amplitude`` radians (1.0 gives large, varied poses).
    """
    rng = np.random.default_rng(seed)
    position = {}
    heading = _smooth_noise(rng, n_frames, 1, 1.5)[:, 0] + rng.uniform(0, 2 * np.pi)
    tilt = _smooth_noise(rng, n_frames, 2, 0.3 * amplitude)
    body = Rotation.from_euler("zxy", np.column_stack([heading, tilt]))
    position["pelvis"] = np.array([0.0, 0.0, 1.0]) + _smooth_noise(rng, n_frames, 3, 0.3)
    position["l_hip"] = position["pelvis"] - body.apply([HALF_HIP_WIDTH_M, 0, 0])
    position["r_hip"] = position["pelvis"] + body.apply([HALF_HIP_WIDTH_M, 0, 0])
    for parent, child, length, rest in _BONES:
        direction = np.asarray(rest, dtype=float) / np.linalg.norm(rest)
        direction = direction + _smooth_noise(rng, n_frames, 3, 1.2 * amplitude)
        direction = body.apply(direction / np.linalg.norm(direction, axis=1, keepdims=True))
        position[child] = position[parent] + length * direction
    return np.stack([position[name] for name in JOINT_NAMES], axis=1)
