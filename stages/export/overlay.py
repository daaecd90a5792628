"""A skeleton drawn on a camera image: the joints projected through the calibrated camera.

Used for the report's overlay stills and the per-camera overlay videos; it takes arrays and a
:class:`calib.camera.Camera`, never paths.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from calib.camera import Camera
from stages.export.skeleton import bones_among
from stages.joints import JOINT_NAMES

#: BGR colours by side of the body, so a left-right swap is visible at a glance.
SIDE_COLOURS = {"l": (255, 128, 0), "r": (0, 0, 255), "centre": (0, 200, 0)}


def _side(name: str) -> str:
    return name[0] if name[:2] in ("l_", "r_") else "centre"


def draw_skeleton(image: np.ndarray, camera: Camera, joints: np.ndarray, names: Sequence[str] = JOINT_NAMES,
                  *, colour: tuple[int, int, int] | None = None, thickness: int | None = None) -> np.ndarray:
    """A copy of ``image`` with the skeleton's bones and joints drawn on it.

    Parameters
    ----------
    image : (H, W, 3) uint8, BGR
        A frame of ``camera`` (its size should be ``camera.size``).
    camera : Camera
        Projects world points with distortion (``Camera.project``).
    joints : (J, 3) float, metres, world frame, in the order of ``names``
    colour : BGR, optional
        One colour for everything (e.g. ground truth); by default left / right / centre colours.
    thickness : int, optional
        Line thickness in pixels; by default about 1/250 of the image diagonal.

    Joints behind the camera are left out with their bones.
    """
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"image must be (H, W, 3) uint8, got {image.dtype} {image.shape}")
    joints = np.asarray(joints, dtype=np.float64)
    if joints.shape != (len(names), 3):
        raise ValueError(f"joints must have shape ({len(names)}, 3), got {joints.shape}")
    out = image.copy()
    if thickness is None:
        thickness = max(1, round(np.hypot(*image.shape[:2]) / 250))
    in_front = camera.depth(joints) > 0
    pixels = camera.project(joints)
    # Drawn with 4 fractional bits (sub-pixel positions keep thin lines straight); points far outside
    # the image are clipped so that OpenCV's integer coordinates cannot overflow.
    limit = 10 * max(image.shape[:2])
    points = np.round(np.clip(np.nan_to_num(pixels), -limit, limit) * 16).astype(np.int64)
    for i, j in bones_among(names):
        if in_front[i] and in_front[j]:
            bone_colour = colour or SIDE_COLOURS[_side(names[j])]
            cv2.line(out, tuple(map(int, points[i])), tuple(map(int, points[j])), bone_colour, thickness,
                     cv2.LINE_AA, shift=4)
    for k, name in enumerate(names):
        if in_front[k]:
            joint_colour = colour or SIDE_COLOURS[_side(name)]
            radius = 16 * (thickness + 1)
            cv2.circle(out, tuple(map(int, points[k])), radius, joint_colour, -1, cv2.LINE_AA, shift=4)
    return out
