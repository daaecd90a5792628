"""Export files: ``joints.csv``, ``motion.bvh``, ``angles.csv``, ``joints.c3d`` and overlay videos.

The converters live in :mod:`stages.export`; this module only puts their results on disk, each file
atomically (:mod:`pipeline.atomic`). Inputs are the estimated frames: frame numbers ``(F,)`` and joint
centres ``(F, J, 3)`` in metres (world frame, +z up), frames the tracker lost simply absent.

Formats with a fixed frame rate need every frame in between:

- ``motion.bvh`` runs from the first to the last estimated frame with the capture's frame step;
  lost frames are linearly interpolated (:func:`stages.export.joints_table.fill_gaps`), frame time
  ``step / fps``.
- ``joints.c3d`` covers the same frames; a lost frame's markers are written invalid (NaN coordinates,
  residual -1, as C3D readers expect), never interpolated. Points are in millimetres (``POINT:UNITS
  = mm``), in the world frame (+z up, as biomechanics tools use), rate ``fps / step``, one virtual
  marker per joint named as in ``JOINT_NAMES``.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import cv2
import ezc3d
import numpy as np

from calib.camera import Camera
from calib.errors import InputError
from pipeline import atomic
from stages.export.angles import format_angles_csv, joint_angles
from stages.export.bvh import bvh_from_joints
from stages.export.joints_table import fill_gaps, format_joints_csv, parse_joints_csv, regular_grid
from stages.export.overlay import draw_skeleton
from stages.joints import JOINT_NAMES

#: File names inside ``<out>/export/``.
JOINTS_FILE, BVH_FILE, ANGLES_FILE, C3D_FILE = "joints.csv", "motion.bvh", "angles.csv", "joints.c3d"

#: Millimetres per metre: C3D points are in millimetres.
MM_PER_M = 1000.0


def _frame_step(grid: np.ndarray) -> int:
    return int(grid[1] - grid[0]) if len(grid) > 1 else 1


def write_joints_csv(path: str | os.PathLike, frames: np.ndarray, joints: np.ndarray,
                     names: Sequence[str] = JOINT_NAMES) -> None:
    """Write ``joints.csv`` (CAPTURE_FORMAT.md): ``frames (F,)``, ``joints (F, J, 3)`` metres."""
    atomic.write_text(path, format_joints_csv(frames, joints, names))


def read_joints_csv(path: str | os.PathLike) -> tuple[np.ndarray, tuple[str, ...], np.ndarray]:
    """Read a ``joints.csv`` file with any subset and order of joints.

    Returns
    -------
    frames : (F,) int64, ascending;  names : J joint names;  joints : (F, J, 3) float64, metres

    Raises
    ------
    InputError
        Missing or unreadable file, or malformed content (the message names the file and line).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: file not found (expected a joints.csv: frame,joint,x,y,z)") from None
    except (UnicodeDecodeError, IsADirectoryError) as error:
        raise InputError(f"{path}: not a readable text file ({type(error).__name__}), "
                         "expected a joints.csv") from None
    return parse_joints_csv(text, source=str(path))


def write_bvh(path: str | os.PathLike, frames: np.ndarray, joints: np.ndarray, fps: float,
              names: Sequence[str] = JOINT_NAMES) -> None:
    """Write ``motion.bvh`` from the estimated frames (gaps interpolated; see the module docstring)."""
    grid, gridded = regular_grid(frames, joints)
    atomic.write_text(path, bvh_from_joints(fill_gaps(gridded), _frame_step(grid) / fps, names=names))


def write_angles_csv(path: str | os.PathLike, frames: np.ndarray, joints: np.ndarray,
                     names: Sequence[str] = JOINT_NAMES) -> None:
    """Write ``angles.csv``: one row per estimated frame, angles of :mod:`stages.export.angles` in degrees."""
    angle_names, angles = joint_angles(joints, names)
    order = np.argsort(frames)
    atomic.write_text(path, format_angles_csv(np.asarray(frames)[order], angle_names, angles[order]))


def write_c3d(path: str | os.PathLike, frames: np.ndarray, joints: np.ndarray, fps: float,
              names: Sequence[str] = JOINT_NAMES) -> None:
    """Write ``joints.c3d``: joints as virtual markers (mm, rate ``fps / step``, lost frames invalid)."""

    grid, gridded = regular_grid(frames, joints)
    points = np.ones((4, len(names), len(grid)))
    points[:3] = np.transpose(gridded, (2, 1, 0)) * MM_PER_M
    lost = np.isnan(gridded[:, :, 0]).T                      # (J, G)
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [fps / _frame_step(grid)]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = list(names)
    c3d.add_parameter("POINT", "UNITS", ["mm"])
    c3d["data"]["points"] = points
    c3d["data"]["meta_points"] = {"residuals": np.where(lost, -1.0, 0.0)[None]}
    with atomic.atomic_output(path) as tmp:
        c3d.write(str(tmp))


def write_exports(export_dir: str | os.PathLike, frames: np.ndarray, joints: np.ndarray, fps: float,
                  names: Sequence[str] = JOINT_NAMES) -> dict[str, Path]:
    """Write all four export files into ``export_dir``; return their paths by file name.

    Parameters
    ----------
    frames : (F,) int, the estimated frames (F >= 1)
    joints : (F, J, 3) float, metres, world frame, in the order of ``names``
    fps : float, the capture's frame rate (frames per second of the media)
    """
    if len(frames) == 0:
        raise InputError(f"{export_dir}: no frame was estimated, so there is nothing to export "
                         "(expected at least one tracked frame)")
    folder = Path(export_dir)
    paths = {name: folder / name for name in (JOINTS_FILE, BVH_FILE, ANGLES_FILE, C3D_FILE)}
    write_joints_csv(paths[JOINTS_FILE], frames, joints, names)
    write_bvh(paths[BVH_FILE], frames, joints, fps, names)
    write_angles_csv(paths[ANGLES_FILE], frames, joints, names)
    write_c3d(paths[C3D_FILE], frames, joints, fps, names)
    return paths


def write_overlay_video(images_iter: Iterable[tuple[int, np.ndarray]], rig_camera: Camera,
                        joints_by_frame: Mapping[int, np.ndarray], path: str | os.PathLike, fps: float,
                        names: Sequence[str] = JOINT_NAMES) -> int:
    """Write an MP4 of one camera's frames with the fitted skeleton drawn on them.

    Parameters
    ----------
    images_iter : iterable of (frame, (H, W, 3) uint8 BGR image)
        The camera's frames in order (e.g. ``Capture.iter_images(camera, frames)``); streamed, so
        only one image is in memory at a time.
    rig_camera : Camera
        The calibrated camera the images come from.
    joints_by_frame : mapping frame -> (J, 3) float, metres
        Frames without an entry (lost) are written without a skeleton.
    path : output ``.mp4`` path
    fps : frames per second of the video

    Returns
    -------
    int
        Number of frames written.
    """
    path = Path(path)
    writer = None
    count = 0
    with atomic.atomic_output(path) as tmp:
        try:
            for frame, image in images_iter:
                if writer is None:
                    height, width = image.shape[:2]
                    fourcc = cv2.VideoWriter_fourcc(*"mp4v")
                    writer = cv2.VideoWriter(str(tmp), fourcc, float(fps), (width, height))
                    if not writer.isOpened():
                        raise OSError(f"{path}: OpenCV cannot write an mp4v video here")
                if frame in joints_by_frame:
                    image = draw_skeleton(image, rig_camera, joints_by_frame[frame], names)
                writer.write(image)
                count += 1
        finally:
            if writer is not None:
                writer.release()
        if writer is None:
            raise InputError(f"{path}: no images to write for camera {rig_camera.name!r} (expected frames)")
    return count
