"""Bring a calibration into the pipeline's world frame: metres, right-handed, +z up.

Calibration files come in other units and with other up axes (a floor-plane calibration with +y up in
centimetres is common). ``to_world`` converts a rig once on load; ``from_world`` does the reverse for
writers of captures in another convention. Both follow CAPTURE_FORMAT.md exactly: translations are
scaled to metres first, then world points are rotated by the proper rotation ``A`` that takes the
declared up axis to +z, ``X_new = A @ X_old``.
"""

from __future__ import annotations

import numpy as np

from calib.camera import Camera, Rig
from calib.errors import InputError

UNIT_SCALE = {"m": 1.0, "cm": 0.01, "mm": 0.001}

# A for each declared up axis, written as the map of CAPTURE_FORMAT.md, (x, y, z) -> A (x, y, z).
_UP_ROTATIONS = {
    "+z": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),  # (x, y, z)
    "-z": ((1, 0, 0), (0, -1, 0), (0, 0, -1)),  # (x, -y, -z)
    "+y": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),  # (x, -z, y)
    "-y": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),  # (x, z, -y)
    "+x": ((0, 0, -1), (0, 1, 0), (1, 0, 0)),  # (-z, y, x)
    "-x": ((0, 0, 1), (0, 1, 0), (-1, 0, 0)),  # (z, y, -x)
}


def up_rotation(up: str) -> np.ndarray:
    """(3, 3) The proper rotation ``A`` taking the axis ``up`` (``"+z"``, ``"-y"``, ...) to +z."""
    if up not in _UP_ROTATIONS:
        raise InputError(f"up: unknown axis {up!r}; expected one of {', '.join(_UP_ROTATIONS)}")
    return np.array(_UP_ROTATIONS[up], dtype=np.float64)


def _unit_scale(units: str) -> float:
    if units not in UNIT_SCALE:
        raise InputError(f"units: unknown unit {units!r}; expected one of {', '.join(UNIT_SCALE)}")
    return UNIT_SCALE[units]


def _transform(rig: Rig, A: np.ndarray, scale: float) -> Rig:
    """The rig in a world where ``X_new = A @ (scale * X_old)``: ``R_new = R A^T``, ``t_new = scale t``.

    Scaling the camera frame along with the world leaves every projection unchanged.
    """
    return Rig(
        tuple(Camera(cam.name, cam.K, cam.dist, cam.R @ A.T, cam.t * scale, cam.size) for cam in rig)
    )


def to_world(rig: Rig, *, units: str, up: str) -> Rig:
    """The rig in the pipeline's world frame, from a calibration in ``units`` with up axis ``up``."""
    return _transform(rig, up_rotation(up), _unit_scale(units))


def from_world(rig: Rig, *, units: str, up: str) -> Rig:
    """The inverse of ``to_world``: a pipeline-frame rig expressed in ``units`` with up axis ``up``."""
    return _transform(rig, up_rotation(up).T, 1.0 / _unit_scale(units))
