"""Keep, in each view's silhouette, the parts that the other views confirm: the person the cameras agree on.

A silhouette can hold more than the subject: a bystander or a passer-by that one or two cameras see, a
reflection, an insect, the phantom of a badly estimated background. The visual hull already carves away
what the other views do not see, but such a part still costs: its outline takes a share of the
reconstruction's samples, and with ``tolerated_views`` a part seen by all cameras but that many would add
volume. So each connected part of a view's silhouette is tested before the reconstruction:
rays through a few of its pixels are sampled across the working volume, and the part is the subject's when
enough of the rays pass through a point that the other views see inside their silhouettes (all of those
that see the point, but ``tolerated`` ones, and at least two, or the only other view of a two-camera rig).
A bystander seen by two cameras fails: at his place, the other cameras see bare room.

A view whose silhouette is a single part is left as it is: that part is the subject or nothing can be said
(the test costs a few milliseconds per tested part, so it runs only where there is a choice to make).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from calib.camera import Camera
from calib.errors import InputError

#: Parts are told apart on square blocks of pixels, about this many across the image's width (4 pixels a
#: side on a 780 x 580 image): a sixteenth of the pixels to label.
CELLS_ACROSS = 200
#: Pixels of a part whose rays are tested (spread evenly over the part), ...
RAYS_PER_PART = 16
#: ... points sampled along each ray's stretch in the working volume (a few centimetres apart: a limb is
#: thicker), ...
POINTS_PER_RAY = 48
#: ... and the share of the rays that must meet the other views' silhouettes for the part to be kept: parts of
#: the subject meet them with nearly all their rays, a part no other view sees with none.
EXPLAINED_SHARE = 0.25


def consistent_silhouettes(masks: Sequence[np.ndarray], cameras: Sequence[Camera], volume: np.ndarray, *,
                           tolerated: int) -> list[np.ndarray]:
    """Each view's (H, W) uint8 mask without the connected parts that the other views do not confirm.

    Parameters
    ----------
    masks : sequence of (H, W) uint8
        One silhouette per camera (0 = background), the cameras' image sizes.
    cameras : sequence of Camera
        World frame, metres.
    volume : (2, 3) float
        Working volume [min; max]: the rays are sampled within it.
    tolerated : int
        How many of the other views that see a ray's point may see it outside their silhouette.
    """
    if len(masks) != len(cameras):
        raise InputError(f"consistent_silhouettes: {len(masks)} masks for {len(cameras)} cameras")
    volume = np.asarray(volume, dtype=float)
    kept = []
    for c, (mask, camera) in enumerate(zip(masks, cameras, strict=True)):
        cell = max(1, round(mask.shape[1] / CELLS_ACROSS))
        count, labels, stats, _ = cv2.connectedComponentsWithStats(_cells(mask, cell), connectivity=8)
        if count <= 2 or len(cameras) < 2:
            kept.append(mask)
            continue
        others = [(camera, masks[o]) for o, camera in enumerate(cameras) if o != c]
        pixels = [_spread_pixels(mask, labels, stats[part], part, cell) for part in range(1, count)]
        explained = _explained(camera, np.concatenate(pixels), others, volume, tolerated)  # (rays,) bool
        starts = np.cumsum([0] + [len(part) for part in pixels[:-1]])
        shares = np.add.reduceat(explained, starts) / np.array([len(part) for part in pixels])
        dropped = np.flatnonzero(shares < EXPLAINED_SHARE) + 1  # labels of the parts to drop
        if not len(dropped):
            kept.append(mask)
            continue
        gone = np.isin(labels, dropped).repeat(cell, axis=0).repeat(cell, axis=1)
        kept.append(np.where(gone[: mask.shape[0], : mask.shape[1]], np.uint8(0), mask))
    return kept


def _cells(mask: np.ndarray, cell: int) -> np.ndarray:
    """(h, w) uint8 1 for the ``cell`` x ``cell`` blocks of ``mask`` that hold a foreground pixel (the last,
    partial blocks included). Parts less than a block apart merge, and are kept or dropped together."""
    height, width = mask.shape
    rows, cols = -(-height // cell), -(-width // cell)
    padded = np.zeros((rows * cell, cols * cell), np.uint8)
    padded[:height, :width] = mask
    # Area averaging by a whole factor is the exact mean of each block: above 0 where a pixel is set.
    return (cv2.resize(padded, (cols, rows), interpolation=cv2.INTER_AREA) > 0).astype(np.uint8)


def _spread_pixels(mask: np.ndarray, labels: np.ndarray, stats: np.ndarray, part: int, cell: int) -> np.ndarray:
    """(n, 2) float (u, v): at most RAYS_PER_PART foreground pixels of ``mask`` in the blocks (``cell`` pixels
    a side) of ``part``, evenly spread in their raster order."""
    x, y, w, h = stats[:4]
    blocks = (labels[y : y + h, x : x + w] == part).repeat(cell, axis=0).repeat(cell, axis=1)
    box = mask[y * cell : (y + h) * cell, x * cell : (x + w) * cell]
    rows, cols = np.nonzero(blocks[: box.shape[0], : box.shape[1]] & (box > 0))
    chosen = np.unique(np.linspace(0, len(rows) - 1, min(RAYS_PER_PART, len(rows))).round().astype(int))
    return np.column_stack([cols[chosen] + x * cell, rows[chosen] + y * cell]).astype(float)


def _stretch(origin: np.ndarray, directions: np.ndarray, volume: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameters (enter (n,), leave (n,)) where rays ``origin + t directions`` (n, 3) cross the box
    ``volume`` (2, 3), t >= 0; enter >= leave for a ray that misses it (the slab method, as
    ``stages.reconstruction.views.box_interval``, which the silhouette workers do not import: the
    reconstruction package brings scipy along)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        low = (volume[0] - origin) / directions
        high = (volume[1] - origin) / directions
    near = np.nan_to_num(np.minimum(low, high), nan=-np.inf)
    far = np.nan_to_num(np.maximum(low, high), nan=np.inf)
    return np.maximum(near.max(axis=1), 0.0), far.min(axis=1)


def _explained(camera: Camera, uv: np.ndarray, others: Sequence[tuple[Camera, np.ndarray]], volume: np.ndarray,
               tolerated: int) -> np.ndarray:
    """(n,) bool: which rays of ``camera`` through pixels ``uv`` (n, 2) meet a point that the ``others``
    (camera, mask) see inside their silhouettes (see the module's docstring)."""
    directions = camera.pixel_rays(uv)  # (n, 3)
    enter, leave = _stretch(camera.centre, directions, volume)
    t = enter[:, None] + (leave - enter)[:, None] * (np.arange(POINTS_PER_RAY) + 0.5) / POINTS_PER_RAY  # (n, S)
    X = (camera.centre + t[..., None] * directions[:, None, :]).reshape(-1, 3)  # (n S, 3)
    in_volume = np.repeat(enter < leave, POINTS_PER_RAY)
    inside = np.zeros(len(X), np.int32)
    seen = np.zeros(len(X), np.int32)
    for other, mask in others:
        uv_other = other.project(X)
        visible = (other.depth(X) > 0) & other.in_image(uv_other)
        pixel = np.floor(uv_other[visible] + 0.5).astype(int)
        hit = np.zeros(len(X), bool)
        hit[visible] = mask[np.clip(pixel[:, 1], 0, mask.shape[0] - 1), np.clip(pixel[:, 0], 0, mask.shape[1] - 1)] > 0
        seen += visible
        inside += hit
    needed = np.maximum(np.minimum(2, len(others)), seen - tolerated)
    return (in_volume & (inside >= needed)).reshape(len(uv), POINTS_PER_RAY).any(axis=1)
