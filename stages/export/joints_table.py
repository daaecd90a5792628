"""``joints.csv`` text (CAPTURE_FORMAT.md) and regular frame grids.

The table has the header ``frame,joint,x,y,z`` and one row per frame and joint, in metres in the
world frame (+z up). A frame that could not be estimated has no rows: the table never holds NaN.
Reading accepts any subset and order of joints and rows (a ground-truth file written by another tool),
but every frame must list the same joints.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence

import numpy as np

from calib.errors import InputError
from stages.joints import JOINT_NAMES

HEADER = ("frame", "joint", "x", "y", "z")

#: Decimal places of the coordinates: 0.1 micrometre, far below any capture's accuracy, and
#: enough for a round trip of synthetic ground truth at the precision the metrics report.
COORDINATE_DECIMALS = 7


def _check_table(frames: np.ndarray, joints: np.ndarray,
                 names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    frames = np.asarray(frames)
    joints = np.asarray(joints, dtype=np.float64)
    if frames.ndim != 1 or not np.issubdtype(frames.dtype, np.integer):
        raise ValueError(f"frames must be a 1-D integer array, got {frames.dtype} {frames.shape}")
    if joints.shape != (len(frames), len(names), 3):
        raise ValueError(f"joints must have shape (F, J, 3) = ({len(frames)}, {len(names)}, 3), "
                         f"got {joints.shape}")
    if not np.all(np.isfinite(joints)):
        raise ValueError("joints contain NaN or infinity; leave frames that were not estimated out instead")
    if len(np.unique(frames)) != len(frames):
        raise ValueError("frames contain duplicates")
    return frames.astype(np.int64), joints


def format_joints_csv(frames: np.ndarray, joints: np.ndarray, names: Sequence[str] = JOINT_NAMES) -> str:
    """The text of a ``joints.csv`` file.

    Parameters
    ----------
    frames : (F,) int
        Frame numbers of the estimated frames (frames not estimated are simply absent).
    joints : (F, J, 3) float, metres
        Joint centres in the order of ``names``; must be finite.
    names : sequence of J str
        Joint names, by default all of ``JOINT_NAMES``.
    """
    frames, joints = _check_table(frames, joints, names)
    order = np.argsort(frames, kind="stable")
    out = io.StringIO()
    out.write(",".join(HEADER) + "\n")
    for f in order:
        for j, name in enumerate(names):
            x, y, z = joints[f, j]
            out.write(f"{frames[f]},{name},{x:.{COORDINATE_DECIMALS}f},{y:.{COORDINATE_DECIMALS}f},"
                      f"{z:.{COORDINATE_DECIMALS}f}\n")
    return out.getvalue()


def parse_joints_csv(text: str, *,
                     source: str = "joints.csv") -> tuple[np.ndarray, tuple[str, ...], np.ndarray]:
    """Parse ``joints.csv`` text.

    Parameters
    ----------
    text : str
        The file's content.
    source : str
        The file name, for error messages.

    Returns
    -------
    frames : (F,) int64, sorted ascending
    names : tuple of J str
        The file's joints: those of ``JOINT_NAMES`` in that order, then any others in order of appearance.
    joints : (F, J, 3) float64, metres

    Raises
    ------
    InputError
        For a wrong header, a malformed row, a non-finite coordinate, a repeated (frame, joint) or
        frames that do not all list the same joints.
    """
    reader = csv.reader(io.StringIO(text))
    header = next(reader, None)
    if header is None or tuple(cell.strip() for cell in header) != HEADER:
        raise InputError(f"{source}: header is {header!r}, expected '{','.join(HEADER)}'")
    values: dict[int, dict[str, tuple[float, float, float]]] = {}
    seen_names: list[str] = []
    for line_number, row in enumerate(reader, start=2):
        if not row or all(not cell.strip() for cell in row):
            continue
        if len(row) != 5:
            raise InputError(f"{source}:{line_number}: {len(row)} fields, expected 5 (frame,joint,x,y,z)")
        try:
            frame = int(row[0])
            xyz = tuple(float(cell) for cell in row[2:])
        except ValueError:
            raise InputError(f"{source}:{line_number}: {','.join(row)!r} is not an integer frame and three "
                             "numbers") from None
        name = row[1].strip()
        if frame < 0 or not name:
            raise InputError(f"{source}:{line_number}: expected a frame number >= 0 and a joint name")
        if not all(math.isfinite(v) for v in xyz):
            raise InputError(f"{source}:{line_number}: coordinates {xyz} are not finite (a frame that was "
                             "not estimated must have no rows)")
        rows = values.setdefault(frame, {})
        if name in rows:
            raise InputError(f"{source}:{line_number}: joint {name!r} appears twice in frame {frame}")
        rows[name] = xyz
        if name not in seen_names:
            seen_names.append(name)
    if not values:
        raise InputError(f"{source}: no data rows (expected one row per frame and joint)")
    known = [name for name in JOINT_NAMES if name in seen_names]
    names = tuple(known + [name for name in seen_names if name not in JOINT_NAMES])
    frames = np.array(sorted(values), dtype=np.int64)
    joints = np.empty((len(frames), len(names), 3))
    for f, frame in enumerate(frames):
        rows = values[int(frame)]
        if len(rows) != len(names):
            missing = [n for n in names if n not in rows]
            raise InputError(f"{source}: frame {frame} lacks joints {', '.join(missing)} "
                             "(expected every frame to list the same joints)")
        joints[f] = [rows[n] for n in names]
    return frames, names, joints


def select_joints(names: Sequence[str], joints: np.ndarray, wanted: Sequence[str], *,
                  source: str) -> np.ndarray:
    """The ``(F, len(wanted), 3)`` columns of ``joints`` for the ``wanted`` names, in that order.

    An :class:`InputError` naming ``source`` lists the wanted joints that are missing.
    """
    missing = [name for name in wanted if name not in names]
    if missing:
        raise InputError(f"{source}: joints {', '.join(missing)} are missing (expected {', '.join(wanted)})")
    return joints[:, [list(names).index(name) for name in wanted]]


def regular_grid(frames: np.ndarray, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Place estimated frames on a regular grid of frame numbers, NaN where a frame is missing.

    Formats with a fixed frame rate (BVH, C3D) need every frame. The grid runs from the first to the
    last estimated frame with a step equal to the greatest common divisor of the gaps between
    estimated frames (the capture's ``frames.step`` when the tracker lost nothing).

    Parameters
    ----------
    frames : (F,) int, distinct
    joints : (F, J, 3) float

    Returns
    -------
    grid : (G,) int64 frame numbers
    gridded : (G, J, 3) float64, NaN at grid frames that were not estimated
    """
    frames = np.asarray(frames, dtype=np.int64)
    if len(frames) == 0:
        raise ValueError("regular_grid needs at least one frame")
    order = np.argsort(frames)
    frames, joints = frames[order], np.asarray(joints, dtype=np.float64)[order]
    step = int(np.gcd.reduce(np.diff(frames))) if len(frames) > 1 else 1
    grid = np.arange(frames[0], frames[-1] + 1, step, dtype=np.int64)
    gridded = np.full((len(grid),) + joints.shape[1:], np.nan)
    gridded[(frames - frames[0]) // step] = joints
    return grid, gridded


def fill_gaps(gridded: np.ndarray) -> np.ndarray:
    """Linearly interpolate NaN frames of ``gridded (G, J, 3)`` from the estimated frames around them.

    Used for the BVH, where every frame needs a pose; a gap's frames move at constant speed between
    the poses on either side. The first and last frames of a grid from :func:`regular_grid` are
    always estimated, so there is no extrapolation.
    """
    known = ~np.isnan(gridded[:, 0, 0])
    if not known.any():
        raise ValueError("fill_gaps needs at least one estimated frame")
    t = np.arange(len(gridded))
    filled = gridded.copy()
    flat = filled.reshape(len(gridded), -1)
    for column in range(flat.shape[1]):
        flat[:, column] = np.interp(t, t[known], flat[known, column])
    return filled
