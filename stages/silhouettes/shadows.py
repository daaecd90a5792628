"""The floor test of shadows: a shadow-like pixel is a shadow when the other views see its floor point
darkened too (:func:`floor_shadows`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from calib.camera import Camera
from calib.errors import InputError
from stages.silhouettes.evidence import Evidence, _working_shape
from stages.silhouettes.outline import flat_nonzero
from stages.silhouettes.params import SilhouetteParams

# The floor test looks at the floor behind blocks of FLOOR_BLOCK x FLOOR_BLOCK working pixels at once
# (a shadow's darkening changes over many pixels; a quarter of the look-up tables' size and making).
FLOOR_BLOCK = 2
# The floor test compares a shadow-like pixel's darkening 1 − α/g with that of its floor point in another
# view: a shadow darkens a matt floor alike from every side, so the other view must see at least this share
# of it. The fifth left over allows for noise and for a soft rim, where the darkening fades out over a few
# pixels that a calibration error can shift; the lower legs, whose floor points lie in the lighter outer
# part of the shadow, see less than that.
SHADOW_AGREEMENT = 0.8


@dataclass(frozen=True, eq=False)
class FloorGeometry:
    """Where each camera sees the floor behind its pixels, and where the other cameras see those points.

    Built once per rig by :func:`floor_geometry`: the undistortions and projections cost tens of
    milliseconds per camera, the look-ups a frame makes in them almost nothing. Pixels are grouped in
    blocks of FLOOR_BLOCK x FLOOR_BLOCK working pixels (a shadow's darkening changes over many pixels).
    """

    working_shapes: tuple[tuple[int, int], ...]  # (h, w) of each camera's working-resolution frame
    # seen_at[c][b] (blocks of c,) int32: the flat working pixel of camera b that sees the floor point
    # behind each block of camera c; -1 where that ray misses the floor or the footprint, or b does not
    # see the point. None for b = c.
    seen_at: tuple[tuple[np.ndarray | None, ...], ...]


def floor_geometry(cameras: Sequence[Camera], volume: np.ndarray, params: SilhouetteParams) -> FloorGeometry:
    """The :class:`FloorGeometry` of a rig, for :func:`floor_shadows`.

    Parameters
    ----------
    cameras : sequence of Camera
        The views' cameras at the images' resolution, world frame with the floor at z = 0.
    volume : (2, 3) float
        Working volume [min; max], metres: shadows are looked for on the floor within its footprint.
    params : SilhouetteParams
        Its ``downsample`` sets the working resolution.
    """
    footprint = np.asarray(volume, dtype=float)[:, :2]
    ds = params.downsample
    shapes = tuple(_working_shape(camera.size, ds) for camera in cameras)
    seen_at = []
    for index, (camera, (height, width)) in enumerate(zip(cameras, shapes, strict=True)):
        block_rows, block_cols = np.divmod(np.arange(_blocks(height) * _blocks(width)), _blocks(width))
        centre = (FLOOR_BLOCK - 1) / 2
        uv = np.column_stack([(block_cols * FLOOR_BLOCK + centre + 0.5) * ds - 0.5,
                              (block_rows * FLOOR_BLOCK + centre + 0.5) * ds - 0.5])
        X, on_floor = _floor_points(camera, uv)
        on_floor &= np.all((X[:, :2] >= footprint[0]) & (X[:, :2] <= footprint[1]), axis=1)
        X = X[on_floor]
        seen = []
        for other, (other_camera, other_shape) in enumerate(zip(cameras, shapes, strict=True)):
            if other == index:
                seen.append(None)
                continue
            pixels = np.full(len(uv), -1, np.int32)
            pixels[on_floor] = _working_pixel(other_camera, other_shape, ds, X)
            seen.append(pixels)
        seen_at.append(tuple(seen))
    return FloorGeometry(shapes, tuple(seen_at))


def _blocks(length: int) -> int:
    """How many FLOOR_BLOCK-pixel blocks cover ``length`` working pixels (a partial last block counts)."""
    return -(-length // FLOOR_BLOCK)


def _floor_points(camera: Camera, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) points where the rays through pixels ``uv`` meet the floor z = 0, and (n,) whether they do."""
    rays = camera.pixel_rays(uv)
    centre = camera.centre
    with np.errstate(divide="ignore", invalid="ignore"):
        distance = -centre[2] / rays[:, 2]
    meets = np.isfinite(distance) & (distance > 0)
    return centre + np.where(meets, distance, 0.0)[:, None] * rays, meets


def _working_pixel(camera: Camera, shape: tuple[int, int], downsample: int, X: np.ndarray) -> np.ndarray:
    """(n,) int32 flat index of the working pixel (of a frame of ``shape``) where ``camera`` sees ``X``
    (n, 3); -1 where it does not (outside its field of view, where the distortion would fold a point back
    into the image, or outside the image)."""
    uv = camera.project(X)
    seen = camera.sees(X) & camera.in_image(uv)
    height, width = shape
    cols = np.clip(np.floor((uv[:, 0] + 0.5) / downsample), 0, width - 1)
    rows = np.clip(np.floor((uv[:, 1] + 0.5) / downsample), 0, height - 1)
    return np.where(seen, rows * width + cols, -1).astype(np.int32)


def floor_shadows(views: Sequence[Evidence], floor: FloorGeometry, params: SilhouetteParams) -> list[np.ndarray]:
    """Per view, which of its shadow-like pixels are the person's shadow on the floor, (h', w') bool each.

    A shadow-like pixel's ray meets the floor (z = 0, the world's convention) at a point X within the
    working volume's footprint. If the pixel is a shadow, X is darkened, and every other camera that sees
    X unoccluded sees it darkened alike (a matt floor looks the same from every side). If the pixel is
    clothing darker than the background behind it, X is bare floor somewhere behind the person, and the
    other cameras see it undarkened. Each other camera votes: no vote where X is outside its image or
    hidden by foreground that is not shadow-like (a limb in front of it); a vote for a shadow where X is
    darkened by at least ``SHADOW_AGREEMENT`` of the pixel's darkening; against otherwise. A pixel is a
    shadow when it has a vote for and at least as many for as against. Rays that never reach the floor
    (above the horizon) are never shadows.

    ``floor`` is the rig's :func:`floor_geometry`, its cameras in the order of ``views``; ``params`` gives
    the weak threshold, above which a pixel that is not shadow-like hides the floor.
    """
    shapes = tuple(view.I_sharp.shape[:2] for view in views)
    if shapes != floor.working_shapes:
        raise InputError(f"floor_shadows: views of working sizes {shapes}, but a floor geometry made for "
                         f"{floor.working_shapes}; expected the same cameras in the same order")
    darkenings = [view.darkening() for view in views]
    looks = [_floor_look(view, darkening, params) for view, darkening in zip(views, darkenings, strict=True)]
    shadows = []
    for index, (view, darkening) in enumerate(zip(views, darkenings, strict=True)):
        shadow = np.zeros(view.shadow_like.shape, bool)
        at = flat_nonzero(view.shadow_like.view(np.uint8)) if shadow.size else np.zeros(0, np.int32)
        if len(at) == 0:
            shadows.append(shadow)
            continue
        rows, cols = np.divmod(at, np.int32(shadow.shape[1]))  # (n,) in the region
        blocks = (((rows + view.region[0].start) // FLOOR_BLOCK) * _blocks(view.I_sharp.shape[1])
                  + (cols + view.region[1].start) // FLOOR_BLOCK)
        needed = SHADOW_AGREEMENT * darkening.ravel().take(at)  # (n,)
        votes_for = np.zeros(len(rows), np.int32)
        votes_against = np.zeros(len(rows), np.int32)
        for other, look in enumerate(looks):
            if other == index:
                continue
            pixels = floor.seen_at[index][other].take(blocks)  # (n,) -1 where there is no floor point to see
            seen_darkening = look.take(pixels)  # NaN where the floor point is not seen: no vote either way
            votes_for += seen_darkening >= needed
            votes_against += seen_darkening < needed
        shadow.ravel()[at] = (votes_for > 0) & (votes_for >= votes_against)
        shadows.append(shadow)
    return shadows


def _floor_look(view: Evidence, darkening: np.ndarray, params: SilhouetteParams) -> np.ndarray:
    """What a view says of the floor points it sees: (h w + 1,) float32 indexed by flat working pixel, its
    darkening 1 − α (:meth:`Evidence.darkening`, ``darkening``) smoothed over 3 x 3 pixels (noise), NaN where
    the floor is not seen: behind foreground that is not shadow-like, and in the last entry, which index -1 (no
    floor point there) reads. A NaN compares false with any darkening, so it gives no vote. Outside its region
    nothing differs from the background: the floor is seen there, undarkened (0)."""
    height, width = view.I_sharp.shape[:2]
    look = np.zeros(height * width + 1, np.float32)
    look[-1] = np.nan
    if view.region is not None:
        hidden = (view.difference2 > np.float32(params.weak_threshold**2)) & ~view.shadow_like
        smoothed = cv2.blur(darkening, (3, 3))
        smoothed[hidden] = np.nan
        look[:-1].reshape(height, width)[view.region] = smoothed
    return look
