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

#: Pixels of a part whose rays are tested (spread evenly over the part), ...
RAYS_PER_PART = 16
#: ... points sampled along each ray's stretch in the working volume (a few centimetres apart: a limb is
#: thicker), ...
POINTS_PER_RAY = 64
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
        count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        if count <= 2 or len(cameras) < 2:
            kept.append(mask)
            continue
        others = [(camera, masks[o]) for o, camera in enumerate(cameras) if o != c]
        parts = range(1, count)
        pixels = [_spread_pixels(labels, stats[part], part) for part in parts]
        explained = _explained(camera, np.concatenate(pixels), others, volume, tolerated)  # (rays,) bool
        cleaned = mask.copy()
        start = 0
        for part, part_pixels in zip(parts, pixels, strict=True):
            share = explained[start : start + len(part_pixels)].mean()
            start += len(part_pixels)
            if share < EXPLAINED_SHARE:
                x, y, w, h = stats[part, :4]
                box = cleaned[y : y + h, x : x + w]
                box[labels[y : y + h, x : x + w] == part] = 0
        kept.append(cleaned)
    return kept


def _spread_pixels(labels: np.ndarray, stats: np.ndarray, part: int) -> np.ndarray:
    """(n, 2) float (u, v) of at most RAYS_PER_PART pixels of ``part``, evenly spread in its raster order."""
    x, y, w, h = stats[:4]
    rows, cols = np.nonzero(labels[y : y + h, x : x + w] == part)
    chosen = np.unique(np.linspace(0, len(rows) - 1, min(RAYS_PER_PART, len(rows))).round().astype(int))
    return np.column_stack([cols[chosen] + x, rows[chosen] + y]).astype(float)


def _explained(camera: Camera, uv: np.ndarray, others: Sequence[tuple[Camera, np.ndarray]], volume: np.ndarray,
               tolerated: int) -> np.ndarray:
    """(n,) bool: which rays of ``camera`` through pixels ``uv`` (n, 2) meet a point that the ``others``
    (camera, mask) see inside their silhouettes (see the module's docstring)."""
    directions = camera.pixel_rays(uv)  # (n, 3)
    # Every ray's stretch in the volume lies between the camera's nearest and farthest distance to its corners.
    corners = np.array(np.meshgrid(*volume.T, indexing="ij")).reshape(3, -1).T  # (8, 3)
    reach = np.linalg.norm(corners - camera.centre, axis=1)
    near = 0.0 if np.all((camera.centre >= volume[0]) & (camera.centre <= volume[1])) else reach.min()
    t = near + (reach.max() - near) * (np.arange(POINTS_PER_RAY) + 0.5) / POINTS_PER_RAY  # (S,)
    X = (camera.centre + t[None, :, None] * directions[:, None, :]).reshape(-1, 3)  # (n S, 3)
    in_volume = np.all((X >= volume[0]) & (X <= volume[1]), axis=1)
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
