"""A studio ring of cameras around the motion, each keeping the whole subject in view.

Cameras stand on a circle around the centre of the subject's footprint, evenly spread with a few
degrees of jitter, at heights drawn from 1.5-2.8 m, looking at the middle of the motion. Each camera's
focal length is the largest that keeps every body point of every frame inside the image with a margin
(after lens distortion), so the subject fills the view as a studio operator would frame it. Radial
distortion k1 is drawn from [-0.15, 0.05]; principal points sit within a few pixels of the centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.camera import Camera, Rig
from calib.errors import InputError


@dataclass(frozen=True)
class RingParams:
    """How the ring is laid out.

    Parameters
    ----------
    n_cameras : int
    size : (int, int)
        Image (width, height) in pixels (the paper's studio: 780 x 580).
    heights_m : (float, float)
        Range of camera heights.
    k1_range : (float, float)
        Range of the radial distortion coefficient k1.
    margin_fraction : float
        Fraction of the image width/height kept free on each side around the subject.
    clearance_m : float
        Distance from the edge of the subject's footprint to the ring.
    min_radius_m : float
        Smallest ring radius.
    """

    n_cameras: int = 6
    size: tuple[int, int] = (780, 580)
    heights_m: tuple[float, float] = (1.5, 2.8)
    k1_range: tuple[float, float] = (-0.15, 0.05)
    margin_fraction: float = 0.05
    clearance_m: float = 2.6
    min_radius_m: float = 3.4


# A focal length below this fraction of the image width means a field of view over ~110 degrees: the
# subject comes too close to the camera for an ordinary lens.
MIN_FOCAL_FRACTION = 0.35
# Points closer than this to a camera (metres) cannot be framed.
MIN_DEPTH_M = 0.5


def ring_centre_and_radius(points: np.ndarray, params: RingParams) -> tuple[np.ndarray, float]:
    """Footprint centre (2,) and ring radius (m) for body points (N, 3) of the whole motion."""
    low, high = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    centre = (low + high) / 2
    footprint_radius = np.linalg.norm(points[:, :2] - centre, axis=1).max()
    return centre, max(params.min_radius_m, footprint_radius + params.clearance_m)


def ring_rig(points: np.ndarray, params: RingParams, rng: np.random.Generator) -> Rig:
    """A ring of cameras framing body points (N, 3) (all frames' surface points, world metres).

    Raises
    ------
    InputError
        'rig cannot see the subject' when a camera would need an impossibly wide lens or the subject
        comes too close to it.
    """
    centre, radius = ring_centre_and_radius(points, params)
    z_low, z_high = points[:, 2].min(), points[:, 2].max()
    width, height = params.size
    first_angle = rng.uniform(0, 2 * np.pi)
    cameras = []
    for k in range(params.n_cameras):
        angle = first_angle + 2 * np.pi * k / params.n_cameras + np.radians(rng.uniform(-8, 8))
        eye = np.array([*(centre + radius * np.array([np.cos(angle), np.sin(angle)])), rng.uniform(*params.heights_m)])
        target = np.array([*(centre + rng.normal(0.0, 0.1, 2)), (z_low + z_high) / 2 + rng.normal(0.0, 0.05)])
        k1 = rng.uniform(*params.k1_range)
        dist = np.array([k1, 0.0, 0.0, 0.0, 0.0])
        name = f"cam{k + 1}"
        oriented = Camera.look_at(name, eye, target, f_px=1.0, size=params.size, dist=dist)
        f = _framing_focal_length(oriented, points, params)
        principal = np.array([(width - 1) / 2, (height - 1) / 2]) + rng.uniform(-0.01, 0.01, 2) * [width, height]
        K = np.array([[f, 0.0, principal[0]], [0.0, f, principal[1]], [0.0, 0.0, 1.0]])
        cameras.append(Camera(name, K, dist, oriented.R, oriented.t, params.size))
    return Rig(tuple(cameras))


def _framing_focal_length(camera: Camera, points: np.ndarray, params: RingParams) -> float:
    """The largest focal length (pixels) keeping ``points`` inside the image margins of ``camera``."""
    depth = camera.depth(points)
    if depth.min() < MIN_DEPTH_M:
        raise InputError(
            f"rig cannot see the subject: it comes within {max(depth.min(), 0):.2f} m of camera "
            f"{camera.name}; expected a shorter clip (--seconds) or a smaller motion"
        )
    x_cam = points @ camera.R.T + camera.t
    x, y = x_cam[:, 0] / x_cam[:, 2], x_cam[:, 1] / x_cam[:, 2]
    radial = 1.0 + camera.dist[0] * (x * x + y * y)
    width, height = params.size
    principal_slack = 0.01  # the principal point may move by 1 % of the size
    usable = (0.5 - params.margin_fraction - principal_slack) * np.array([width, height])
    f = min(usable[0] / np.abs(x * radial).max(), usable[1] / np.abs(y * radial).max())
    if f < MIN_FOCAL_FRACTION * width:
        raise InputError(
            f"rig cannot see the subject: camera {camera.name} would need a focal length of {f:.0f} px "
            f"(under {MIN_FOCAL_FRACTION} x image width); expected a shorter clip (--seconds)"
        )
    return f


def check_rig_sees(rig: Rig, joints: np.ndarray) -> None:
    """Raise InputError unless every joint (F, J, 3) of every frame projects inside every image."""
    points = joints.reshape(-1, 3)
    for camera in rig:
        visible = (camera.depth(points) > 0) & camera.in_image(camera.project(points))
        if not np.all(visible):
            frame = int(np.flatnonzero(~visible)[0] // joints.shape[1])
            raise InputError(
                f"rig cannot see the subject: camera {camera.name} loses joints at frame {frame} "
                f"({np.count_nonzero(~visible)} joint positions outside its {camera.size[0]}x{camera.size[1]} image)"
            )
