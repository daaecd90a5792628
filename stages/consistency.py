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
(the test costs a few milliseconds per tested part, so it runs only where there is a choice to make). Nor is a
view emptied of every part while the other views confirm some of one: there the subject is merged, in this view,
with something they do not see (he passes before a bystander, or before a thing the other views have in their
backgrounds), and an empty view would carve him away; the best confirmed part stays.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from calib.camera import Camera
from calib.errors import InputError
from stages.rays import box_interval

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
        cells, corner = _cells(mask, cell)
        count, labels, stats, _ = cv2.connectedComponentsWithStats(cells, connectivity=8)
        if count <= 2 or len(cameras) < 2:
            kept.append(mask)
            continue
        # The parts' boxes and pixels from here on are of the full image, in cells and in pixels.
        stats[:, :2] += corner
        others = [(camera, masks[o]) for o, camera in enumerate(cameras) if o != c]
        pixels = [_spread_pixels(mask, labels, stats[part], corner, part, cell) for part in range(1, count)]
        explained = explained_pixels(camera, np.concatenate(pixels), others, volume, tolerated)  # (rays,) bool
        starts = np.cumsum([0] + [len(part) for part in pixels[:-1]])
        shares = np.add.reduceat(explained, starts) / np.array([len(part) for part in pixels])
        dropped = np.flatnonzero(shares < EXPLAINED_SHARE) + 1  # labels of the parts to drop
        if len(dropped) == count - 1 and shares.max() > 0:
            # Every part would go, yet the others confirm some of one: the subject merged in this view with
            # something they do not see (he passes before it). Emptied, the view would carve all of him away.
            dropped = dropped[dropped != np.argmax(shares) + 1]
        if not len(dropped):
            kept.append(mask)
            continue
        kept.append(_without_parts(mask, labels, corner, dropped, cell))
    return kept


def explained_share(masks: Sequence[np.ndarray], cameras: Sequence[Camera], volume: np.ndarray, *, tolerated: int,
                    rays_per_view: int) -> float:
    """The share of rays through the views' silhouettes that meet a point the other views see inside theirs (all
    that see it but ``tolerated``, and at least two): how much of the silhouettes the visual hull explains, which is
    what the reconstruction carves (Hernández, Schmitt & Cipolla's silhouette coherence, 2007). ``rays_per_view``
    pixels of each silhouette are tested, spread evenly in raster order; NaN when every silhouette is empty."""
    volume = np.asarray(volume, dtype=float)
    explained, tested = 0, 0
    for c, (mask, camera) in enumerate(zip(masks, cameras, strict=True)):
        uv = silhouette_pixels(mask, rays_per_view)
        if not len(uv):
            continue
        others = [(other, masks[o]) for o, other in enumerate(cameras) if o != c]
        explained += int(explained_pixels(camera, uv, others, volume, tolerated).sum())
        tested += len(uv)
    return explained / tested if tested else np.nan


def silhouette_pixels(mask: np.ndarray, count: int) -> np.ndarray:
    """(n, 2) float (u, v): at most ``count`` pixels of the silhouette ``mask``, evenly spread in raster order."""
    points = cv2.findNonZero(np.ascontiguousarray(mask, dtype=np.uint8))
    if points is None:
        return np.zeros((0, 2))
    points = points.reshape(-1, 2)
    return points[evenly_spread(len(points), count)].astype(float)


def _cells(mask: np.ndarray, cell: int) -> tuple[np.ndarray, tuple[int, int]]:
    """``(cells (h, w) uint8, corner (column, row))``: nonzero for the ``cell`` x ``cell`` blocks of ``mask`` that hold
    a foreground pixel (the last, partial blocks included), in the box of blocks around the foreground, whose
    first block is ``corner`` (in blocks). Parts less than a block apart merge, and are kept or dropped together.

    Only the box is reduced: a person covers a small part of the frame, and the empty rest cost most of the
    reduction.
    """
    x, y, w, h = cv2.boundingRect(mask)
    if w == 0:
        return np.zeros((1, 1), np.uint8), (0, 0)
    left, top = x // cell, y // cell
    cols, rows = -(-(x + w) // cell) - left, -(-(y + h) // cell) - top
    box = mask[top * cell : (top + rows) * cell, left * cell : (left + cols) * cell]
    if box.shape != (rows * cell, cols * cell):  # partial blocks at the image's far edges: pad them
        padded = np.zeros((rows * cell, cols * cell), np.uint8)
        padded[: box.shape[0], : box.shape[1]] = box
        box = padded
    # Area averaging by a whole factor is the exact mean of each block: above 0 where a pixel is set.
    return cv2.compare(cv2.resize(box, (cols, rows), interpolation=cv2.INTER_AREA), 0, cv2.CMP_GT), (left, top)


def _part_blocks(labels: np.ndarray, part_labels: int | np.ndarray, cell: int) -> np.ndarray:
    """(h cell, w cell) uint8 255 on the pixels of the blocks ``labels`` (h, w) gives one of ``part_labels``
    (one label, or an array of them)."""
    # One part: a comparison, a fraction of np.isin's cost.
    chosen = (labels == part_labels) if np.ndim(part_labels) == 0 else np.isin(labels, part_labels)
    chosen = chosen.view(np.uint8) * np.uint8(255)
    return cv2.resize(chosen, (labels.shape[1] * cell, labels.shape[0] * cell), interpolation=cv2.INTER_NEAREST)


def _spread_pixels(mask: np.ndarray, labels: np.ndarray, stats: np.ndarray, corner: tuple[int, int], part: int,
                   cell: int) -> np.ndarray:
    """(n, 2) float (u, v): at most RAYS_PER_PART foreground pixels of ``mask`` in the blocks (``cell`` pixels
    a side) of ``part``, evenly spread in their raster order. ``stats`` gives the part's box of blocks in the
    image, ``labels`` the parts of the blocks from block ``corner`` on."""
    x, y, w, h = stats[:4]
    blocks = _part_blocks(labels[y - corner[1] : y - corner[1] + h, x - corner[0] : x - corner[0] + w], part, cell)
    box = mask[y * cell : (y + h) * cell, x * cell : (x + w) * cell]
    points = cv2.findNonZero(cv2.bitwise_and(blocks[: box.shape[0], : box.shape[1]], box))  # (n, 1, 2) raster order
    cols, rows = points.reshape(-1, 2).T
    chosen = evenly_spread(len(rows), RAYS_PER_PART)
    return np.column_stack([cols[chosen] + x * cell, rows[chosen] + y * cell]).astype(float)


def pixels_seen(camera: Camera, X: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``(visible (N,) bool, at (M,) intp)``: which world points ``X`` (N, 3) the camera sees in its image (in view
    without the distortion's fold-back and with it), and the flat index, in an image of ``shape`` (H, W), of the
    pixel each of those M points falls on."""
    uv = camera.project(X)
    visible = camera.sees(X) & camera.in_image(uv)
    pixel = np.floor(uv.compress(visible, axis=0) + 0.5).astype(np.intp)
    height, width = shape
    # Clipped by np.maximum and np.minimum: np.clip's wrapper costs several times the arithmetic here.
    rows = np.minimum(np.maximum(pixel[:, 1], 0), height - 1)
    cols = np.minimum(np.maximum(pixel[:, 0], 0), width - 1)
    return visible, rows * width + cols


def evenly_spread(count: int, wanted: int) -> np.ndarray:
    """At most ``wanted`` indices of ``count`` items (count > 0), evenly spread from the first to the last."""
    return np.unique(np.linspace(0, count - 1, min(wanted, count)).round().astype(int))


def _without_parts(mask: np.ndarray, labels: np.ndarray, corner: tuple[int, int], dropped: np.ndarray,
                   cell: int) -> np.ndarray:
    """A copy of ``mask`` without the pixels of the blocks labelled ``dropped`` (from block ``corner`` on)."""
    gone = _part_blocks(labels, dropped, cell)
    top, left = corner[1] * cell, corner[0] * cell
    kept = mask.copy()
    box = kept[top : top + gone.shape[0], left : left + gone.shape[1]]  # clipped at the image's far edges
    box[gone[: box.shape[0], : box.shape[1]] > 0] = 0
    return kept


def explained_pixels(camera: Camera, uv: np.ndarray, others: Sequence[tuple[Camera, np.ndarray]],
                     volume: np.ndarray, tolerated: int) -> np.ndarray:
    """(n,) bool: which rays of ``camera`` through pixels ``uv`` (n, 2) meet a point that the ``others``
    (camera, mask) see inside their silhouettes (see the module's docstring). The masks need not be of the instant
    the pixels are: `stages.synchrony` compares them across time."""
    directions = camera.pixel_rays(uv)  # (n, 3)
    enter, leave = box_interval(camera.centre, directions, volume)
    t = enter[:, None] + (leave - enter)[:, None] * (np.arange(POINTS_PER_RAY) + 0.5) / POINTS_PER_RAY  # (n, S)
    X = (camera.centre + t[..., None] * directions[:, None, :]).reshape(-1, 3)  # (n S, 3)
    # The other views are asked one after the other, each about the points still in the running: a point the
    # others see outside more than ``tolerated`` times is out (most of a ray's stretch lies in free room).
    running = np.flatnonzero(np.repeat(enter < leave, POINTS_PER_RAY))
    inside = np.zeros(len(X), np.int32)
    misses = np.zeros(len(X), np.int32)
    for other, mask in others:
        # Only the points in view are counted, by flat indices (gathers and scatters of the points in view rather
        # than masks over all the running ones).
        visible, at = pixels_seen(other, X.take(running, axis=0), mask.shape)
        hit = mask.ravel().take(at) > 0
        seen = running.take(np.flatnonzero(visible))  # (m,) indices in X of the points in view, each once
        inside[seen[hit]] += 1
        misses[seen[~hit]] += 1
        running = running[misses.take(running) <= tolerated]
    # Inside at least two others (the only other of a two-camera rig), outside at most ``tolerated`` of those
    # that see it: inside >= max(min(2, others), seen - tolerated).
    explained = np.zeros(len(X), bool)
    explained[running] = inside.take(running) >= min(2, len(others))
    return explained.reshape(len(uv), POINTS_PER_RAY).any(axis=1)
