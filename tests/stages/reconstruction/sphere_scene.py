"""Analytic test scenes: a ring of cameras looking at spheres, with exactly rendered silhouettes."""

import numpy as np

from calib.camera import Camera, Rig

CENTRE = np.array([0.1, -0.05, 1.0])
RADIUS = 0.25
VOLUME = np.array([[-1.5, -1.5, 0.0], [1.5, 1.5, 2.2]])


def ring_rig(n_cameras: int = 6, *, size=(390, 290), f_px: float = 380.0, distortion: bool = False,
             skew_px: float = 0.0) -> Rig:
    """Cameras on a 4 m ring at uneven angles and heights, all aimed near the sphere; ``skew_px`` is
    ``K[0, 1]`` of every other camera (its negative for the rest)."""
    cameras = []
    for i in range(n_cameras):
        angle = 2 * np.pi * i / n_cameras + 0.3 * np.sin(1.7 * i)
        eye = [4.0 * np.cos(angle), 4.0 * np.sin(angle), 1.2 + 0.6 * np.sin(i)]
        camera = Camera.look_at(f"cam_{i}", eye, [0.0, 0.0, 1.0], f_px=f_px, size=size)
        K = camera.K.copy()
        K[0, 1] = skew_px if i % 2 else -skew_px
        dist = [-0.12, 0.03, 0.0, 0.0, 0.0] if distortion else camera.dist
        camera = Camera(camera.name, K, dist, camera.R, camera.t, size)
        cameras.append(camera)
    return Rig(tuple(cameras))


def render_spheres(camera: Camera, centres, radii) -> np.ndarray:
    """(H, W) uint8 mask: 255 where the ray through the pixel centre hits one of the spheres."""
    width, height = camera.size
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    directions = camera.pixel_rays(np.column_stack([u.ravel(), v.ravel()]))  # (HW, 3)
    hit = np.zeros(len(directions), bool)
    for centre, radius in zip(np.atleast_2d(centres), np.atleast_1d(radii), strict=True):
        to_centre = centre - camera.centre
        along = directions @ to_centre
        miss2 = to_centre @ to_centre - along**2
        hit |= (along > 0) & (miss2 < radius**2)
    return np.where(hit, 255, 0).astype(np.uint8).reshape(height, width)
