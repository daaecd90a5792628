"""Shared test helpers: a tiny capture directory built from scratch in a temporary folder.

``make_capture(root, ...)`` writes a few cameras on a ring looking at a disc-shaped "person" at the
origin (``Camera.look_at`` + ``save_rig``), and per camera a few frames (a filled circle on a plain
background, the circle's grey level encoding the frame number) as images or an MJPG video, with
optional clean plates and silhouettes. Tests change one thing and check what the pipeline says.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from calib_testing import ring_rig

from calib.camera import Camera, Rig
from calib.formats import save_rig
from calib.world import from_world

#: Image size of the tiny captures (width, height): small, so tests stay fast.
TINY_SIZE = (64, 48)
BACKGROUND_GREY = 40


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "dask: starts a Dask LocalCluster (a few seconds)")


def tiny_rig(n_cameras: int = 3, *, size: tuple[int, int] = TINY_SIZE, radius_m: float = 4.0) -> Rig:
    """Cameras on a ring of ``radius_m`` at 1.5 m height, all looking at (0, 0, 1)."""
    cameras = []
    for index in range(n_cameras):
        angle = 2 * np.pi * index / n_cameras
        eye = (radius_m * np.cos(angle), radius_m * np.sin(angle), 1.5)
        cameras.append(Camera.look_at(f"cam{index}", eye, (0.0, 0.0, 1.0), f_px=0.9 * size[0], size=size))
    return Rig(tuple(cameras))


def frame_image(frame: int, size: tuple[int, int] = TINY_SIZE) -> np.ndarray:
    """A grey background with a filled circle whose grey level is ``60 + 10 * frame``."""
    width, height = size
    image = np.full((height, width, 3), BACKGROUND_GREY, np.uint8)
    cv2.circle(image, (width // 2, height // 2), min(size) // 4, (60 + 10 * frame,) * 3, thickness=-1)
    return image


def frame_mask(size: tuple[int, int] = TINY_SIZE) -> np.ndarray:
    width, height = size
    mask = np.zeros((height, width), np.uint8)
    cv2.circle(mask, (width // 2, height // 2), min(size) // 4, 255, thickness=-1)
    return mask


def write_config(root: Path, **changes) -> Path:
    """Rewrite ``capture.yaml`` with top-level keys replaced by ``changes`` (None deletes a key)."""
    path = root / "capture.yaml"
    config = yaml.safe_load(path.read_text()) if path.exists() else {}
    for key, value in changes.items():
        if value is None:
            config.pop(key, None)
        else:
            config[key] = value
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def make_capture(root: Path, *, n_cameras: int = 3, n_frames: int = 4, media: str = "images",
                 fmt: str = "anipose", units: str = "m", up: str = "+z", backgrounds: bool = False,
                 silhouettes: bool = False, volume: dict | None = None,
                 size: tuple[int, int] = TINY_SIZE) -> Path:
    """Write a tiny capture under ``root`` and return ``root``.

    ``media`` is "images", "videos" (MJPG .avi) or "none" (then pass ``silhouettes=True``).
    The calibration is written in ``units`` with up axis ``up`` (converted from the world frame).
    """
    root.mkdir(parents=True, exist_ok=True)
    rig = tiny_rig(n_cameras, size=size)
    calibration_dir = {"anipose": "calibration/calibration.toml", "opencv": "calibration",
                       "colmap": "calibration/colmap", "projection": "calibration/projection"}[fmt]
    save_rig(from_world(rig, units=units, up=up), fmt, root / calibration_dir)
    config = {"fps": 25.0, "calibration": {"format": fmt, "path": calibration_dir, "units": units, "up": up}}
    if volume is not None:
        config["volume"] = volume
    (root / "capture.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    for camera in rig:
        if media == "images":
            folder = root / "images" / camera.name
            folder.mkdir(parents=True)
            for frame in range(n_frames):
                cv2.imwrite(str(folder / f"{frame:06d}.png"), frame_image(frame, size))
        elif media == "videos":
            write_video(root / "videos" / f"{camera.name}.avi", n_frames, size)
        if backgrounds:
            (root / "background").mkdir(exist_ok=True)
            cv2.imwrite(str(root / "background" / f"{camera.name}.png"),
                        np.full((size[1], size[0], 3), BACKGROUND_GREY, np.uint8))
        if silhouettes:
            folder = root / "silhouettes" / camera.name
            folder.mkdir(parents=True)
            for frame in range(n_frames):
                cv2.imwrite(str(folder / f"{frame:06d}.png"), frame_mask(size))
    return root


def write_video(path: Path, n_frames: int, size: tuple[int, int] = TINY_SIZE) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, size)
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV cannot write MJPG video {path}")
    for frame in range(n_frames):
        writer.write(frame_image(frame, size))
    writer.release()


@pytest.fixture
def tiny_capture(tmp_path: Path) -> Path:
    """A valid 3-camera, 4-frame image capture with an anipose calibration."""
    return make_capture(tmp_path / "capture")


@pytest.fixture
def rig12() -> Rig:
    """Twelve varied cameras named cam_0 .. cam_11 (numeric and text order differ)."""
    return ring_rig(12)


def stick_figure() -> np.ndarray:
    """(17, 3) a standing stick figure in ``JOINT_NAMES`` order (metres, +z up, facing +y)."""
    from stages.joints import JOINT_NAMES

    template = {"pelvis": (0, 0, 1.0), "neck": (0, 0, 1.5), "head": (0, 0, 1.7),
                "l_shoulder": (-0.2, 0, 1.5), "r_shoulder": (0.2, 0, 1.5), "l_elbow": (-0.25, 0, 1.2),
                "r_elbow": (0.25, 0, 1.2), "l_wrist": (-0.25, 0.1, 0.95), "r_wrist": (0.25, 0.1, 0.95),
                "l_hip": (-0.1, 0, 1.0), "r_hip": (0.1, 0, 1.0), "l_knee": (-0.1, 0, 0.55),
                "r_knee": (0.1, 0, 0.55), "l_ankle": (-0.1, 0, 0.1), "r_ankle": (0.1, 0, 0.1),
                "l_toe": (-0.1, 0.15, 0.02), "r_toe": (0.1, 0.15, 0.02)}
    return np.array([template[name] for name in JOINT_NAMES], dtype=float)
