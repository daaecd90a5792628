"""The working volume: given in ``capture.yaml``, or derived from the calibration when it gives none
(:func:`derive_volume`)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from calib.camera import Rig
from calib.errors import InputError
from calib.sanity import check_cameras_see_volume

log = logging.getLogger(__name__)

#: Height of the derived working volume, metres: a standing adult with raised arms fits.
DERIVED_VOLUME_HEIGHT_M = 2.3
#: How far the derived volume reaches below the floor, metres. Reconstructed points outside the volume are
#: dropped, and the soles' points lie at or a little below z = 0 (a visual hull's lowest points; a floor
#: found by ``up: auto`` within a few centimetres): a volume starting at z = 0 cut them off.
DERIVED_VOLUME_FLOOR_MARGIN_M = 0.15
#: Grid of floor positions tested when deriving the volume (cells per side).
DERIVED_VOLUME_GRID = 161
#: Heights (fractions of the volume height) at which a floor position must be in view: the feet and the
#: middle of the body. Requiring the top of the volume (raised arms) as well left out the rim of the floor
#: that the cameras, tilted down at the subject, see whole but for the space above 2 m, where the subject
#: still walks and kicks, and cut the subject off there.
DERIVED_VOLUME_HEIGHTS = (0.0, 0.5)


def derive_volume(rig: Rig, *, height_m: float = DERIVED_VOLUME_HEIGHT_M) -> np.ndarray:
    """Working volume seen by most cameras, when ``capture.yaml`` gives none.

    Rule: lay a square grid of floor positions (x, y) over the cameras' surroundings (centred on
    the mean camera position, half-size the largest camera distance from it plus 1 m, or 3 m if the
    cameras are close together). A position counts as seen by a camera when the vertical segment
    above it, sampled at :data:`DERIVED_VOLUME_HEIGHTS` (the feet and the body's middle), is in front of
    the camera and inside its image (`Camera.sees`: the undistorted pinhole model, safe far outside the
    image where the distortion polynomial is not). Keep the positions seen by a majority of the cameras (at least
    two), or, if none, by the largest number seen anywhere; the volume is their bounding box,
    ``-DERIVED_VOLUME_FLOOR_MARGIN_M <= z <= height_m``.

    Returns
    -------
    (2, 3) float
        ``[[x_min, y_min, -margin], [x_max, y_max, height_m]]`` in metres.

    Raises
    ------
    ValueError
        When no camera sees any floor position of the grid.
    """
    centres = rig.centres  # (C, 3)
    middle = centres[:, :2].mean(axis=0)
    half = max(np.linalg.norm(centres[:, :2] - middle, axis=1).max() + 1.0, 3.0)
    axis = np.linspace(-half, half, DERIVED_VOLUME_GRID)
    gx, gy = np.meshgrid(middle[0] + axis, middle[1] + axis, indexing="ij")
    floor = np.stack([gx.ravel(), gy.ravel()], axis=1)  # (G, 2)
    seen = np.ones((len(rig), len(floor)), dtype=bool)  # (C, G)
    for fraction in DERIVED_VOLUME_HEIGHTS:
        X = np.hstack([floor, np.full((len(floor), 1), fraction * height_m)])  # (G, 3)
        for c, camera in enumerate(rig):
            seen[c] &= camera.sees(X)
    counts = seen.sum(axis=0)  # (G,)
    needed = max(2, len(rig) // 2 + 1)
    if counts.max() < needed:
        needed = counts.max()
    if needed == 0:
        raise ValueError("no camera sees the floor near the cameras")
    kept = floor[counts >= needed]
    step = axis[1] - axis[0]  # grow by one grid cell so the box covers the kept cells, not their centres
    return np.array([[*(kept.min(axis=0) - step), -DERIVED_VOLUME_FLOOR_MARGIN_M],
                     [*(kept.max(axis=0) + step), height_m]])


def working_volume(given: dict | None, rig: Rig, calibration_path: Path) -> tuple[np.ndarray, str]:
    """The working volume ``(2, 3)`` and where it comes from: ``"capture.yaml"`` (``given``, the validated
    ``volume:`` section, which most cameras must see) or ``"derived"`` (:func:`derive_volume`)."""
    if given is not None:
        volume = np.array([given["min"], given["max"]], dtype=np.float64)
        check_cameras_see_volume(rig, volume, where=str(calibration_path))
        return volume, "capture.yaml"
    try:
        volume = derive_volume(rig)
    except ValueError as error:
        raise InputError(f"{calibration_path}: {error} (expected cameras looking at the capture "
                         "area, or volume: in capture.yaml)") from None
    log.info("working volume derived from the calibration: min %s max %s",
             np.round(volume[0], 2).tolist(), np.round(volume[1], 2).tolist())
    return volume, "derived"
