"""Plausibility checks of a rig in metres: units, intrinsics, and whether the cameras see the volume.

A calibration in millimetres declared ``units: m`` is a 4.5 km rig; a focal length of 1e308 projects
everything onto the principal point. Both load without complaint and produce nothing useful, so they are
refused here with one line naming the file, what looks wrong and what would fit.
"""

from __future__ import annotations

import numpy as np

from calib.camera import Rig
from calib.errors import InputError
from calib.world import UNIT_SCALE

#: Largest distance between two camera centres of a capture rig, metres: from a desk-top pair to a
#: stadium-sized studio.
RIG_SIZE_M = (0.2, 60.0)
#: A focal length between these multiples of the image width: a 140-degree wide angle to a 2-degree
#: telephoto.
FOCAL_WIDTHS = (0.18, 30.0)
#: The principal point within this fraction of the image size outside the image (shifted lenses).
PRINCIPAL_MARGIN = 0.5


def check_rig_size(rig: Rig, *, units: str, where: str) -> None:
    """Refuse a rig whose extent, read in ``units``, is implausible; name the unit that would fit."""
    if len(rig) < 2:
        return
    centres = rig.centres
    size = float(np.max(np.linalg.norm(centres[:, None] - centres[None], axis=2)))
    low, high = RIG_SIZE_M
    if low <= size <= high:
        return
    in_file = size / UNIT_SCALE[units]
    fitting = [unit for unit, scale in UNIT_SCALE.items() if low <= in_file * scale <= high]
    hint = f"; units: {fitting[0]} would make it {in_file * UNIT_SCALE[fitting[0]]:.3g} m" if fitting else ""
    raise InputError(f"{where}: with units: {units} the cameras span {size:.3g} m, expected "
                     f"{low} to {high} m for a capture rig{hint}")


def check_intrinsics(rig: Rig, *, where: str) -> None:
    """Refuse focal lengths or principal points absurd for the image size."""
    for camera in rig:
        width, height = camera.size
        fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
        low, high = FOCAL_WIDTHS[0] * width, FOCAL_WIDTHS[1] * width
        if not (low <= fx <= high and low <= fy <= high):
            raise InputError(f"{where}: camera {camera.name!r} has focal lengths ({fx:.4g}, {fy:.4g}) px for "
                             f"{width}x{height} images, expected {low:.0f} to {high:.0f} px")
        margin_x, margin_y = PRINCIPAL_MARGIN * width, PRINCIPAL_MARGIN * height
        if not (-margin_x <= cx <= width + margin_x and -margin_y <= cy <= height + margin_y):
            raise InputError(f"{where}: camera {camera.name!r} has its principal point at ({cx:.4g}, {cy:.4g}) "
                             f"px, expected near the {width}x{height} image (about ({width / 2:.0f}, "
                             f"{height / 2:.0f}))")


def check_cameras_see_volume(rig: Rig, volume: np.ndarray, *, where: str) -> None:
    """Refuse a camera that sees none of the working volume's central column.

    The column through the volume's centre, from its floor to its top, is where the subject stands; a
    camera that has it neither in front nor in its image looks elsewhere (a camera-to-world pose read as
    world-to-camera, a wrong up axis, a volume somewhere else).
    """
    centre = volume.mean(axis=0)
    column = np.column_stack([np.full(9, centre[0]), np.full(9, centre[1]), np.linspace(*volume[:, 2], 9)])
    for camera in rig:
        if not camera.sees(column).any():
            behind = not (camera.depth(column) > 0).any()
            raise InputError(f"{where}: camera {camera.name!r} does not see the working volume (its central "
                             f"column at x, y = {centre[0]:.2f}, {centre[1]:.2f} m is "
                             f"{'behind it' if behind else 'outside its image'}), expected every "
                             "camera to look at the volume")
