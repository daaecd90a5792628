"""Bring a calibration into the pipeline's world frame: metres, right-handed, +z up.

Calibration files come in other units and with other up axes (a floor-plane calibration with +y up in
centimetres is common). ``fixed_transform(units=..., up=...).apply`` converts a rig once on load;
``from_world`` does the reverse for writers of captures in another convention. Both follow the capture
format (docs/capture_format.md) exactly: translations are scaled to metres first, then world points are
rotated by the proper rotation ``A`` that takes the declared up axis to +z, ``X_new = A @ X_old``.

With ``up: auto`` the calibration's world is arbitrary (camera 1's frame, a checkerboard's): the vertical
comes from the rig (:func:`rig_vertical`), :func:`level_rotation` turns it to +z, and the floor height,
which the rig alone cannot tell, comes from the images (``pipeline.io.auto_frame``). The whole map is a
:class:`WorldTransform`, ``X_new = A @ (scale X_old) + b``.
"""

from __future__ import annotations

from dataclasses import dataclass

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


def nearest_up_axis(direction) -> str:
    """The declared up axis (``"+z"``, ``"-y"``, ...) nearest the ``direction`` (3,), in the calibration's frame."""
    direction = np.asarray(direction, dtype=np.float64)
    return max(_UP_ROTATIONS, key=lambda up: float(up_rotation(up)[2] @ direction))


def _unit_scale(units: str) -> float:
    if units not in UNIT_SCALE:
        raise InputError(f"units: unknown unit {units!r}; expected one of {', '.join(UNIT_SCALE)}")
    return UNIT_SCALE[units]


def _transform(rig: Rig, A: np.ndarray, scale: float, b=(0.0, 0.0, 0.0)) -> Rig:
    """The rig in a world where ``X_new = A @ (scale * X_old) + b``: ``R_new = R A^T``,
    ``t_new = scale t - R_new b``.

    Scaling the camera frame along with the world leaves every projection unchanged.
    """
    b = np.asarray(b, dtype=np.float64)
    return Rig(tuple(Camera(cam.name, cam.K, cam.dist, cam.R @ A.T, cam.t * scale - cam.R @ A.T @ b, cam.size)
                     for cam in rig))


@dataclass(frozen=True)
class WorldTransform:
    """The map from the calibration's world to the pipeline's: ``X_new = A @ (scale * X_old) + b``.

    Attributes
    ----------
    A : (3, 3) float
        Proper rotation.
    b : (3,) float
        Translation, metres (zero for a declared up axis: the calibration's origin is kept).
    scale : float
        Metres per calibration unit.
    """

    A: np.ndarray
    b: np.ndarray
    scale: float

    def apply(self, rig: Rig) -> Rig:
        """The calibration-frame ``rig`` in the pipeline's world frame."""
        return _transform(rig, self.A, self.scale, self.b)

    def to_dict(self) -> dict:
        """Plain data for ``capture.json``: ``rotation`` (3 rows), ``translation_m``, ``scale``."""
        return {"rotation": self.A.tolist(), "translation_m": self.b.tolist(), "scale": self.scale}


def fixed_transform(*, units: str, up: str) -> WorldTransform:
    """The transform of a declared up axis: the table's rotation, the unit's scale, no translation."""
    return WorldTransform(up_rotation(up), np.zeros(3), _unit_scale(units))


# Cameras whose image x axes (rows 0 of R) span less than this (smallest but one eigenvalue of
# sum x x^T, per camera; about sin^2 of half their spread of headings, here ~11 degrees) all face the
# same way: the x axes then leave the vertical free about their common direction.
MIN_HEADING_SPREAD = 0.01


def rig_vertical(rig: Rig) -> tuple[np.ndarray, str]:
    """(3,) unit world "up" of the rig's world, and how it was found (for the log).

    Studio cameras are mounted level: they pitch down at the subject, by anything up to 45 degrees,
    but hardly roll (a degree or two), so each image's x axis (row 0 of R, in world coordinates) is
    horizontal. The vertical is the direction most nearly perpendicular to them all, the eigenvector of
    the smallest eigenvalue of ``sum x_i x_i^T``, signed so that it agrees with the images' up axes
    ``-R[1]``. It does not depend on how far the cameras pitch; the mean of the images' up axes does
    (it tilts towards the side with more, or more steeply pitched, cameras), and so does the normal of
    the plane through the camera centres (cameras at different heights). When the
    cameras all face the same way the x axes fix the vertical only up to a turn about their common
    direction; the mean up axis, made perpendicular to that direction, fixes it then.
    """
    if len(rig) == 0:
        raise InputError("up: auto needs at least one camera")
    x_axes = np.array([camera.R[0] for camera in rig])  # (C, 3)
    up_axes = -np.array([camera.R[1] for camera in rig])  # (C, 3)
    eigenvalues, eigenvectors = np.linalg.eigh(x_axes.T @ x_axes)  # ascending
    if eigenvalues[1] >= MIN_HEADING_SPREAD * len(rig):
        vertical, how = eigenvectors[:, 0], "perpendicular to the cameras' image x axes"
    else:
        common = eigenvectors[:, 2]
        vertical = up_axes.sum(axis=0) - (up_axes.sum(axis=0) @ common) * common
        how = "the cameras' mean image up axis (they all face the same way)"
    vertical = vertical / np.linalg.norm(vertical)
    return (vertical if vertical @ up_axes.sum(axis=0) >= 0 else -vertical), how


def level_rotation(vertical, heading) -> np.ndarray:
    """(3, 3) proper rotation ``A`` with ``A @ vertical = +z`` and ``heading``, made horizontal, along +x.

    ``heading`` must not be parallel to ``vertical`` (the caller passes camera 1's image x axis, which
    is close to horizontal).
    """
    z = np.asarray(vertical, dtype=np.float64) / np.linalg.norm(vertical)
    x = np.asarray(heading, dtype=np.float64) - (np.asarray(heading) @ z) * z
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def from_world(rig: Rig, *, units: str, up: str) -> Rig:
    """The inverse of ``fixed_transform(units=units, up=up).apply``: a pipeline-frame rig expressed in
    ``units`` with up axis ``up``."""
    return _transform(rig, up_rotation(up).T, 1.0 / _unit_scale(units))
