"""Export files: ``joints.csv``, ``motion.bvh``, ``joints.trc``, ``angles.csv``, ``joints.c3d``, ``quality.csv``
(the overlay videos are :mod:`pipeline.io.overlay_video`'s).

The converters live in :mod:`stages.export`; this module only puts their results on disk, each file
atomically (:mod:`pipeline.io.atomic`). Inputs are the estimated frames: frame numbers ``(F,)`` and joint
centres ``(F, J, 3)`` in metres (world frame, +z up), frames the tracker lost simply absent.

Every export shows the same motion (:func:`export_trajectories`): one skeleton, whose rigid bones have
the settled lengths in every frame (:mod:`stages.export.skeleton`), optionally smoothed
(``export.filter_cutoff_hz``, :mod:`stages.export.filtering`); joints.csv, BVH, TRC and C3D then agree
to far below a millimetre in every frame. Formats with a fixed frame rate need every frame in between:

- ``motion.bvh`` runs from the first to the last estimated frame with the capture's frame step;
  lost frames are linearly interpolated (:func:`stages.export.joints_table.fill_gaps`), frame time
  ``step / fps``.
- ``joints.trc`` and ``joints.c3d`` cover the same frames; a lost frame's markers are written missing
  (TRC: empty cells; C3D: NaN coordinates, residual -1, as C3D readers expect), never interpolated.
  C3D points are in millimetres (``POINT:UNITS = mm``), in the world frame (+z up, as biomechanics
  tools use), rate ``fps / step``, one virtual marker per joint named as in ``JOINT_NAMES``; its
  header's first frame and ``TRIAL:ACTUAL_START_FIELD`` hold the capture's number of the first frame,
  1-based as C3D counts (capture frame 30 is C3D frame 31, which ezc3d, counting from 0, reports as
  30), and ``ACTUAL_END_FIELD`` the last sample's. C3D numbers its samples one by one, so with a frame
  step above 1 the samples after the first are numbered consecutively although they are ``step``
  capture frames apart (TRC's ``Frame#`` column holds the capture's own numbers).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Sequence
from pathlib import Path

import ezc3d
import numpy as np
from ezc3d import ezc3d as ezc3d_types

from calib.errors import InputError
from pipeline.io import atomic
from pipeline.io.run_layout import ANGLES_FILE, BVH_FILE, C3D_FILE, JOINTS_FILE, QUALITY_FILE, TRC_FILE
from stages.export import ExportParams
from stages.export.angles import format_angles_csv, joint_angles
from stages.export.bvh import bvh_from_joints
from stages.export.filtering import lowpass
from stages.export.joints_table import fill_gaps, format_joints_csv, parse_joints_csv, regular_grid
from stages.export.quality import FrameQuality, format_quality_csv
from stages.export.skeleton import settled_lengths, with_bone_lengths
from stages.export.trc import MARKER_NAMINGS, format_trc
from stages.joints import JOINT_NAMES

#: Millimetres per metre: C3D points are in millimetres.
MM_PER_M = 1000.0

#: C3D's 16-bit words hold frame numbers up to this; TRIAL's fields split larger ones in two words.
_WORD = 65536


def _frame_step(grid: np.ndarray) -> int:
    return int(grid[1] - grid[0]) if len(grid) > 1 else 1


def export_trajectories(frames: np.ndarray, joints: np.ndarray, fps: float, names: Sequence[str] = JOINT_NAMES,
                        *, cutoff_hz: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The motion every export shows, on the regular grid of the estimated frames.

    The rigid bones get the settled lengths of the last frame (:func:`stages.export.skeleton.with_bone_lengths`);
    with ``cutoff_hz`` the trajectories are then low-passed (:func:`stages.export.filtering.lowpass`)
    and the lengths restored, since smoothing each joint on its own changes them slightly.

    Returns
    -------
    grid : (G,) int64 frame numbers;  gridded : (G, J, 3) float64, metres, NaN at frames not estimated

    Raises
    ------
    InputError
        When ``cutoff_hz`` is not below half the grid's frame rate (the highest frequency it holds).
    """
    grid, gridded = regular_grid(frames, joints)
    lengths = settled_lengths(gridded, names)  # the grid's last frame is the last estimated one
    gridded = with_bone_lengths(gridded, names, lengths)
    if cutoff_hz is not None:
        rate = fps / _frame_step(grid)
        check_cutoff(cutoff_hz, rate)
        gridded = with_bone_lengths(lowpass(gridded, rate, cutoff_hz), names, lengths)
    return grid, gridded


def check_cutoff(cutoff_hz: float | None, rate: float) -> None:
    """Refuse a smoothing cut-off (``export.filter_cutoff_hz``) that is not below half the frame ``rate``.

    The run command calls it with the capture's rate before any work; :func:`export_trajectories` again with
    the rate of the frames estimated (lost frames can widen the step between them).
    """
    if cutoff_hz is not None and not cutoff_hz < rate / 2:
        raise InputError(f"export.filter_cutoff_hz: expected a cut-off below half the frame rate "
                         f"({rate / 2:g} Hz for {rate:g} frames/s), got {cutoff_hz:g}")


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
    frames, names, joints = _parsed(text, str(path))
    return frames.copy(), names, joints.copy()


@functools.lru_cache(maxsize=4)
def _parsed(text: str, source: str) -> tuple[np.ndarray, tuple[str, ...], np.ndarray]:
    """:func:`~stages.export.joints_table.parse_joints_csv` remembered for the last texts read: the end of a run
    reads its joints.csv and the truth's several times (the closing check, the report and its scores), and the
    parse costs far more than the read. Keyed by the text itself, so a file that changed is parsed anew."""
    return parse_joints_csv(text, source=source)


def write_bvh(path: str | os.PathLike, grid: np.ndarray, gridded: np.ndarray, fps: float,
              names: Sequence[str] = JOINT_NAMES, *, units: str = "cm", naming: str = "joints") -> None:
    """Write ``motion.bvh`` over a regular grid (gaps interpolated; see the module docstring)."""
    atomic.write_text(path, bvh_from_joints(fill_gaps(gridded), _frame_step(grid) / fps, names=names,
                                            units=units, naming=naming))


def write_trc(path: str | os.PathLike, grid: np.ndarray, gridded: np.ndarray, fps: float,
              names: Sequence[str] = JOINT_NAMES, *, naming: str = "joints") -> None:
    """Write ``joints.trc`` over a regular grid (OpenSim's +Y up, mm; lost frames empty)."""
    atomic.write_text(path, format_trc(grid, gridded, fps, names, marker_names=MARKER_NAMINGS[naming],
                                       file_name=Path(path).name))


def write_angles_csv(path: str | os.PathLike, frames: np.ndarray, joints: np.ndarray,
                     names: Sequence[str] = JOINT_NAMES) -> None:
    """Write ``angles.csv``: one row per estimated frame, angles of :mod:`stages.export.angles` in degrees."""
    angle_names, angles = joint_angles(joints, names)
    order = np.argsort(frames)
    atomic.write_text(path, format_angles_csv(np.asarray(frames)[order], angle_names, angles[order]))


def write_c3d(path: str | os.PathLike, grid: np.ndarray, gridded: np.ndarray, fps: float,
              names: Sequence[str] = JOINT_NAMES) -> None:
    """Write ``joints.c3d``: joints as virtual markers (mm, rate ``fps / step``, lost frames invalid, the
    capture's first and last frame numbers in the header and TRIAL group)."""
    points = np.ones((4, len(names), len(grid)))
    points[:3] = np.transpose(gridded, (2, 1, 0)) * MM_PER_M
    lost = np.isnan(gridded[:, :, 0]).T                      # (J, G)
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [fps / _frame_step(grid)]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = list(names)
    c3d.add_parameter("POINT", "UNITS", ["mm"])
    first = int(grid[0]) + 1                                 # C3D frames count from 1
    last = first + len(grid) - 1                             # and step by one sample (see the module docstring)
    for name, frame in (("ACTUAL_START_FIELD", first), ("ACTUAL_END_FIELD", last)):
        c3d.add_parameter("TRIAL", name, [frame % _WORD, frame // _WORD])
        # Two 16-bit integer words, as Vicon writes them and readers (the c3d package) decode them;
        # ezc3d's add_parameter stores numbers as floats, which such readers cannot decode.
        c3d["parameters"]["TRIAL"][name]["type"] = ezc3d_types.INT
    c3d["header"]["points"]["first_frame"] = int(grid[0])    # ezc3d counts from 0 and writes it + 1
    c3d["data"]["points"] = points
    c3d["data"]["meta_points"] = {"residuals": np.where(lost, -1.0, 0.0)[None]}
    with atomic.atomic_output(path) as tmp:
        c3d.write(str(tmp))


def write_quality_csv(path: str | os.PathLike, quality: FrameQuality, names: Sequence[str] = JOINT_NAMES) -> None:
    """Write ``quality.csv`` (:mod:`stages.export.quality`): one row per frame of the capture."""
    atomic.write_text(path, format_quality_csv(quality, names))


def write_exports(export_dir: str | os.PathLike, frames: np.ndarray, joints: np.ndarray, fps: float,
                  names: Sequence[str] = JOINT_NAMES, *, params: ExportParams | None = None,
                  quality: FrameQuality | None = None) -> dict[str, Path]:
    """Write every export file into ``export_dir``; return their paths by file name.

    Parameters
    ----------
    frames : (F,) int, the estimated frames (F >= 1)
    joints : (F, J, 3) float, metres, world frame, in the order of ``names`` (the tracker's estimates)
    fps : float, the capture's frame rate (frames per second of the media)
    params : ExportParams, optional, the filter and the BVH's and TRC's units and names (default: the defaults)
    quality : FrameQuality, optional, the tracker's record of every frame: quality.csv is written from it
    """
    if len(frames) == 0:
        raise InputError(f"{export_dir}: no frame was estimated, so there is nothing to export "
                         "(expected at least one tracked frame)")
    params = params or ExportParams()
    folder = Path(export_dir)
    files = (JOINTS_FILE, BVH_FILE, TRC_FILE, ANGLES_FILE, C3D_FILE) + ((QUALITY_FILE,) if quality else ())
    paths = {name: folder / name for name in files}
    grid, gridded = export_trajectories(frames, joints, fps, names, cutoff_hz=params.filter_cutoff_hz)
    estimated = ~np.isnan(gridded[:, 0, 0])
    write_joints_csv(paths[JOINTS_FILE], grid[estimated], gridded[estimated], names)
    write_bvh(paths[BVH_FILE], grid, gridded, fps, names, units=params.bvh_units, naming=params.bvh_names)
    write_trc(paths[TRC_FILE], grid, gridded, fps, names, naming=params.trc_names)
    write_angles_csv(paths[ANGLES_FILE], grid[estimated], gridded[estimated], names)
    write_c3d(paths[C3D_FILE], grid, gridded, fps, names)
    if quality is not None:
        write_quality_csv(paths[QUALITY_FILE], quality, names)
    return paths
