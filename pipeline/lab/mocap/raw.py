"""A clip as a reader returns it (:class:`RawClip`), and the Euler rotations both formats are made of."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Metres per inch (ASF's default length unit).
INCH_M = 0.0254


@dataclass(frozen=True)
class RawClip:
    """A clip as read, in the file's Y-up frame but already in metres: what :mod:`~pipeline.lab.mocap.motion` turns
    into a :class:`~pipeline.lab.mocap.motion.Motion`."""

    fps: float
    bone_names: tuple[str, ...]
    parents: np.ndarray  # (B,)
    rest_origins: np.ndarray  # (B, 3)
    rest_ends: np.ndarray  # (B, 3)
    rotations: np.ndarray  # (F, B, 3, 3), from rest
    root_positions: np.ndarray  # (F, 3)


def axis_rotations(axis: str, angles: np.ndarray) -> np.ndarray:
    """(N, 3, 3) Rotations by ``angles`` (N,) radians about the coordinate axis ``axis`` in 'xyz'."""
    c, s = np.cos(angles), np.sin(angles)
    one, zero = np.ones_like(angles), np.zeros_like(angles)
    if axis == "x":
        rows = [[one, zero, zero], [zero, c, -s], [zero, s, c]]
    elif axis == "y":
        rows = [[c, zero, s], [zero, one, zero], [-s, zero, c]]
    else:
        rows = [[c, -s, zero], [s, c, zero], [zero, zero, one]]
    return np.moveaxis(np.array(rows), (0, 1), (-2, -1))


def euler_rotations(axes: str, angles: np.ndarray) -> np.ndarray:
    """(N, 3, 3) ``R_axes[-1] ... R_axes[0]``: the later-listed axis on the left, ``angles`` (N, len) rad."""
    result = np.broadcast_to(np.eye(3), (len(angles), 3, 3)).copy()
    for k, axis in enumerate(axes):
        result = axis_rotations(axis, angles[:, k]) @ result
    return result
