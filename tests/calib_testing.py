"""Rigs and points shared by the calib tests: realistic, varied cameras so that mix-ups show."""

import numpy as np

from calib.camera import Camera, Rig


def ring_rig(n_cameras: int = 12, *, seed: int = 0, with_k3: bool = True) -> Rig:
    """``n_cameras`` cameras on a ring of radius ~4 m looking at a subject 1 m above the floor.

    Every camera has its own focal lengths, principal point, distortion and image size, so a reader
    that swaps cameras or fields cannot go unnoticed. Names ``cam_0 .. cam_<n-1>`` make numeric versus
    text ordering bugs visible from 11 cameras on.
    """
    rng = np.random.default_rng(seed)
    cameras = []
    for i in range(n_cameras):
        angle = 2 * np.pi * i / n_cameras
        eye = np.array([4.0 * np.cos(angle), 4.0 * np.sin(angle), rng.uniform(1.2, 2.6)])
        target = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), 1.0])
        size = (int(rng.choice([640, 800, 1280])), int(rng.choice([480, 600, 720])))
        base = Camera.look_at(f"cam_{i}", eye, target, f_px=rng.uniform(700, 1100), size=size)
        K = base.K.copy()
        K[1, 1] *= rng.uniform(0.98, 1.02)
        K[:2, 2] += rng.uniform(-10, 10, 2)
        dist = np.array(
            [
                rng.uniform(-0.3, -0.1),
                rng.uniform(0.0, 0.1),
                rng.uniform(-1e-3, 1e-3),
                rng.uniform(-1e-3, 1e-3),
                rng.uniform(-0.02, 0.02) if with_k3 else 0.0,
            ]
        )
        cameras.append(Camera(base.name, K, dist, base.R, base.t, size))
    return Rig(tuple(cameras))


def subject_points(n_points: int = 200, *, seed: int = 1) -> np.ndarray:
    """(N, 3) world points in a person-sized box around (0, 0, 1), seen by every ring camera."""
    rng = np.random.default_rng(seed)
    return rng.uniform([-0.5, -0.5, 0.0], [0.5, 0.5, 2.0], (n_points, 3))
