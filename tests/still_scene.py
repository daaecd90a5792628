"""A test scene for background estimation: a ring of cameras, textured rooms, and a subject who stands still.

The subject is an upright ellipsoid (a body without limbs) of a colour unlike the rooms'. Its silhouette in a
view is the convex hull of its projected surface points, which is exact for an ellipsoid's outline up to
the sampling. Each frame adds Gaussian sensor noise.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml

from calib.camera import Camera, Rig
from calib.formats import save_rig

SIZE = (160, 120)
VOLUME = np.array([[-1.5, -1.5, 0.0], [1.5, 1.5, 2.2]])
#: Semi-axes of the subject (metres) and its colour (BGR).
SEMI_AXES = np.array([0.22, 0.16, 0.85])
COLOUR = (60, 80, 200)
NOISE_SIGMA = 2.0


def ring(n_cameras: int = 5) -> Rig:
    """Cameras 4 m from the centre at uneven angles and heights, all aimed at (0, 0, 0.9)."""
    cameras = []
    for i in range(n_cameras):
        angle = 2 * np.pi * i / n_cameras + 0.2 * np.sin(1.3 * i)
        eye = [4.0 * np.cos(angle), 4.0 * np.sin(angle), 1.4 + 0.4 * np.sin(i)]
        cameras.append(Camera.look_at(f"cam{i}", eye, [0.0, 0.0, 0.9], f_px=150.0, size=SIZE))
    return Rig(tuple(cameras))


def rooms(rig: Rig, seed: int = 0) -> list[np.ndarray]:
    """Per camera, (H, W, 3) uint8 smooth random colours: a cluttered room out of focus."""
    rng = np.random.default_rng(seed)
    width, height = SIZE
    return [cv2.resize(rng.uniform(90, 230, (height // 10 + 1, width // 10 + 1, 3)).astype(np.uint8),
                       SIZE, interpolation=cv2.INTER_LINEAR) for _ in rig]


def subject_mask(camera: Camera, centre) -> np.ndarray:
    """(H, W) uint8 255 inside the silhouette of the subject standing with its middle at ``centre`` (x, y)."""
    return ellipsoid_mask(camera, [centre[0], centre[1], SEMI_AXES[2]], SEMI_AXES)


def ellipsoid_mask(camera: Camera, centre, semi_axes) -> np.ndarray:
    """(H, W) uint8 255 inside the silhouette of an axis-aligned ellipsoid (world ``centre`` (3,) and
    ``semi_axes`` (3,), metres)."""
    theta, phi = np.meshgrid(np.linspace(0, np.pi, 24), np.linspace(0, 2 * np.pi, 48))
    unit = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1).reshape(-1, 3)
    uv = camera.project(unit * np.asarray(semi_axes) + centre).astype(np.float32)
    width, height = camera.size
    mask = np.zeros((height, width), np.uint8)
    cv2.fillConvexPoly(mask, np.round(cv2.convexHull(uv)).astype(np.int32), 255)
    return mask


def frames(rig: Rig, backgrounds: list[np.ndarray], path: np.ndarray, seed: int = 1) -> list[list[np.ndarray]]:
    """Per camera, the frames of the subject standing at each (x, y) of ``path`` (F, 2), with sensor noise."""
    rng = np.random.default_rng(seed)
    views = []
    for camera, background in zip(rig, backgrounds, strict=True):
        images = []
        for centre in path:
            image = background.astype(np.float32)
            image[subject_mask(camera, centre) > 0] = COLOUR
            image += rng.normal(0.0, NOISE_SIGMA, image.shape)
            images.append(np.clip(image, 0, 255).round().astype(np.uint8))
        views.append(images)
    return views


def still_then_moving(n_frames: int = 30, still: int = 18) -> np.ndarray:
    """(F, 2) the subject's positions: at (0, 0) for the first ``still`` frames, then walking a circle of
    0.8 m radius around it (more than his width away, so every pixel he covered is seen bare again)."""
    angles = np.linspace(0.0, 2 * np.pi, n_frames - still, endpoint=False)
    walk = 0.8 * np.column_stack([np.cos(angles), np.sin(angles)])
    return np.vstack([np.zeros((still, 2)), walk])


def write_capture(root: Path, rig: Rig, views: list[list[np.ndarray]], plates: list[np.ndarray] | None = None) -> Path:
    """A capture folder at ``root`` of each camera's frames ``views`` (image folders), with clean ``plates`` (one
    per camera) if given; returns ``root``."""
    save_rig(rig, "anipose", root / "calibration" / "calibration.toml")
    config = {"fps": 25.0, "calibration": {"format": "anipose", "path": "calibration/calibration.toml"},
              "volume": {"min": VOLUME[0].tolist(), "max": VOLUME[1].tolist()}}
    (root / "capture.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    for index, (camera, images) in enumerate(zip(rig, views, strict=True)):
        folder = root / "images" / camera.name
        folder.mkdir(parents=True)
        for frame, image in enumerate(images):
            cv2.imwrite(str(folder / f"{frame:06d}.png"), image)
        if plates is not None:
            (root / "background").mkdir(exist_ok=True)
            cv2.imwrite(str(root / "background" / f"{camera.name}.png"), plates[index])
    return root
