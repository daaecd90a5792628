"""Distractors: small blobs that appear in one camera for a while (an insect, a reflection, a ball).

They are absent from the clean plate and from the true masks, so background subtraction finds
foreground that is not the person, in one view only: after carving, what survives of them is outlier
data for the tracker's uniform class.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Distractor:
    """A soft elliptical blob drifting across one camera's image.

    Parameters
    ----------
    camera : int
        Index of the camera (rig order) that sees it.
    first_frame, last_frame : int
        Frames (inclusive) in which it is visible.
    start : (2,) float
        Pixel position of its centre at ``first_frame``.
    velocity : (2,) float
        Pixels per frame.
    radii : (2,) float
        Semi-axes in pixels.
    angle : float
        Orientation of the first semi-axis, radians.
    colour : (3,) float
        RGB in [0, 1].
    """

    camera: int
    first_frame: int
    last_frame: int
    start: tuple[float, float]
    velocity: tuple[float, float]
    radii: tuple[float, float]
    angle: float
    colour: tuple[float, float, float]


def random_distractors(
    count: int, n_cameras: int, n_frames: int, size: tuple[int, int], rng: np.random.Generator
) -> list[Distractor]:
    """``count`` distractors in random cameras, each visible for a random third to all of the frames."""
    width, height = size
    scale = min(width, height)
    distractors = []
    for _ in range(count):
        duration = int(rng.integers(max(1, n_frames // 3), n_frames + 1))
        first = int(rng.integers(0, n_frames - duration + 1))
        distractors.append(
            Distractor(
                camera=int(rng.integers(0, n_cameras)),
                first_frame=first,
                last_frame=first + duration - 1,
                start=(float(rng.uniform(0.1, 0.9) * width), float(rng.uniform(0.1, 0.9) * height)),
                velocity=tuple(float(v) for v in rng.normal(0.0, 0.004 * scale, 2)),
                radii=tuple(float(r) for r in rng.uniform(0.012, 0.04, 2) * scale),
                angle=float(rng.uniform(0, np.pi)),
                colour=tuple(float(c) for c in rng.uniform(0.05, 0.95, 3)),
            )
        )
    return distractors


def paint_distractors(image: np.ndarray, distractors: list[Distractor], camera: int, frame: int) -> np.ndarray:
    """Paint the distractors of ``camera`` visible at ``frame`` over ``image`` (H, W, 3) RGB, in place."""
    height, width = image.shape[:2]
    for blob in distractors:
        if blob.camera != camera or not blob.first_frame <= frame <= blob.last_frame:
            continue
        elapsed = frame - blob.first_frame
        cx = blob.start[0] + blob.velocity[0] * elapsed
        cy = blob.start[1] + blob.velocity[1] * elapsed
        reach = int(np.ceil(max(blob.radii))) + 2
        u0, u1 = max(int(cx) - reach, 0), min(int(cx) + reach + 1, width)
        v0, v1 = max(int(cy) - reach, 0), min(int(cy) + reach + 1, height)
        if u1 <= u0 or v1 <= v0:
            continue
        u, v = np.meshgrid(np.arange(u0, u1) - cx, np.arange(v0, v1) - cy)
        c, s = np.cos(blob.angle), np.sin(blob.angle)
        along, across = (c * u + s * v) / blob.radii[0], (-s * u + c * v) / blob.radii[1]
        distance = np.sqrt(along**2 + across**2)  # 1 on the rim
        coverage = np.clip((1.0 - distance) * min(blob.radii) + 0.5, 0.0, 1.0)[:, :, None]  # 1 px soft edge
        patch = image[v0:v1, u0:u1]
        image[v0:v1, u0:u1] = patch * (1 - coverage) + np.asarray(blob.colour) * coverage
    return image
