"""Parts of a view hidden behind something that stands in front of the subject (a desk, a pillar, a tripod).

A static object between a camera and the subject is part of that camera's background: wherever it hides the subject,
the camera's silhouette shows background, and the visual hull, which keeps only what every view sees inside its
silhouette, carves away whatever goes behind it (a desk that hides the feet in one view takes the feet off the hull,
for every view). The other views still see the hidden part, and that is how it is found, in the manner of Guan,
Franco & Pollefeys (CVPR 2007), who learn such occluders from the silhouettes' disagreement over time: rays through
each view's silhouette are sampled where they lie inside the other silhouettes' convex hulls, and the points that
every camera sees and every other one sees inside its silhouette are projected into the camera; where that camera
shows background at them, it alone contradicts the others there. A camera's silhouette errs here and there, and
where the other views leave room (the visual hull's phantom volume, which moves with the subject) it contradicts
them rightly; but the same part of its image contradicting them on nearly every frame where they place the subject
there, while the subject moves, is something in front of him. The reconstruction then lets that camera decide
nothing there: a point that projects into the hidden part counts as inside its silhouette, and the outline along it,
the occluder's edge rather than the subject's, casts no ray (`stages.reconstruction`).

The votes are counted per frame on cells of the image (:func:`hidden_votes`) and weighed over frames spread over
the capture (:func:`hidden_parts`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from calib.camera import Camera
from stages.consistency import evenly_spread, pixels_seen
from stages.rays import box_interval
from stages.reconstruction.views import blind_beyond_image
from stages.reconstruction.visual_shape import hull_bounds, outline_points

#: Cells of this many across the image's width count the votes (8 pixels a side on a 780 x 580 image): finer than
#: a limb, coarse enough for the points of a hundred rays per view to reach most cells the subject covers.
CELLS_ACROSS = 100
#: Pixels of each view's silhouette whose rays are sampled per frame, spread evenly over it ...
RAYS_PER_VIEW = 100
#: ... chosen among every PIXEL_STRIDE-th pixel along both axes.
PIXEL_STRIDE = 4
#: Points sampled along each ray's stretch inside the other views' silhouettes' convex hulls (all of them but one,
#: which may be the camera at fault): a few centimetres apart.
POINTS_PER_RAY = 16
#: Fewest cameras for the search: the visual hull of three views leaves room beside the subject that they all see
#: inside their silhouettes, and a subject who lingers there leaves it on the same cells frame after frame.
MIN_CAMERAS = 5
#: A cell is hidden on a frame when at least this share of the points the other views place in it fall on the
#: camera's background.
HIDDEN_SHARE = 0.5
#: A cell is hidden behind something when it was hidden on at least this share of the frames where the other
#: views placed the subject in it, ...
PERSISTENT_SHARE = 0.8
#: ... and on at least this many frames, ...
MIN_HIDDEN_FRAMES = 2
#: ... and belongs to a connected part of such cells at least this share of the subject's mean image (in cells): the
#: subject's limbs sweep the whole of what hides them, while a silhouette's error that happens to repeat on a few
#: frames covers a cell or two.
MIN_PART_SHARE = 0.1
#: The subject's image must have moved by at least this many times its size (the square root of its area) over the
#: frames where the camera's large parts were hidden: what stays hidden while the subject's image moves across the
#: view stands still, as things in the room do, where the room that the other views leave open around him moves
#: with him (unless he keeps to the same part of the image, walking straight at the camera).
MIN_TRAVEL = 0.5


@dataclass(frozen=True)
class CellVotes:
    """Per camera, on its cells (:func:`cell_size`): on how many sampled frames the other views placed the subject
    in each cell (``placed``), on which of those frames the camera showed background there (``hidden``, a frame
    axis first), and where the camera's silhouette was on each frame (``centres``, (u, v) pixels of its centroid,
    NaN when empty)."""

    placed: tuple[np.ndarray, ...]  # (rows, cols) int per camera
    hidden: tuple[np.ndarray, ...]  # (frames, rows, cols) bool per camera
    centres: tuple[np.ndarray, ...]  # (frames, 2) float per camera

    @property
    def frames(self) -> int:
        """How many frames voted."""
        return len(self.centres[0]) if self.centres else 0

    def __add__(self, other: CellVotes) -> CellVotes:
        return CellVotes(tuple(a + b for a, b in zip(self.placed, other.placed, strict=True)),
                         tuple(np.concatenate([a, b]) for a, b in zip(self.hidden, other.hidden, strict=True)),
                         tuple(np.concatenate([a, b]) for a, b in zip(self.centres, other.centres, strict=True)))


def cell_size(camera: Camera) -> int:
    """Pixels per side of a camera's vote cells."""
    return max(1, round(camera.size[0] / CELLS_ACROSS))


def no_votes(cameras: Sequence[Camera]) -> CellVotes:
    """Votes of no frame."""
    shapes = [_cells_shape(camera) for camera in cameras]
    return CellVotes(tuple(np.zeros(shape, int) for shape in shapes),
                     tuple(np.zeros((0, *shape), bool) for shape in shapes), tuple(np.zeros((0, 2)) for _ in shapes))


def hidden_votes(masks: Sequence[np.ndarray], cameras: Sequence[Camera], volume: np.ndarray,
                 found: Sequence[np.ndarray | None] | None = None) -> CellVotes:
    """One frame's votes: for each camera, the cells where the other views place the subject (points that every
    camera sees and every other one sees inside its silhouette), those of them where the camera shows background
    at ``HIDDEN_SHARE`` of the points or more, and where the camera's silhouette lies.

    Parameters
    ----------
    masks : sequence of (H, W) uint8
        One silhouette per camera (0 = background).
    cameras : sequence of Camera
    volume : (2, 3) float
        Working volume [min; max], metres: the rays are sampled within it.
    found : sequence of (H, W) uint8 or None, optional
        Parts of the views already found hidden (:func:`search_hidden_parts`): as one of the others, a camera
        counts a point there as inside its silhouette, as the reconstruction does; its own votes are its
        silhouette's.
    """
    found = [None] * len(cameras) if found is None else list(found)
    shapes = [_cells_shape(camera) for camera in cameras]
    placed = [np.zeros(shape, int) for shape in shapes]
    hidden = [np.zeros((1, *shape), bool) for shape in shapes]
    pixels = [_silhouette_pixels(mask) for mask in masks]
    centres = tuple(ours.mean(axis=0, keepdims=True) if len(ours) else np.full((1, 2), np.nan) for ours in pixels)
    if len(cameras) < MIN_CAMERAS:
        return CellVotes(tuple(placed), tuple(hidden), centres)
    X = _ray_points([mask if part is None else cv2.bitwise_or(mask, part) for mask, part in zip(masks, found,
                                                                                                 strict=True)],
                    pixels, cameras, np.asarray(volume, dtype=float))
    if len(X) == 0:
        return CellVotes(tuple(placed), tuple(hidden), centres)
    # The cameras are asked one after the other about the points still in the running: a point that a camera does
    # not see, or that two see outside their silhouettes, is placed for none of them.
    inside = np.zeros((len(cameras), len(X)), bool)  # as one of the others: with the part found hidden, if any
    own = np.zeros((len(cameras), len(X)), bool)  # in the camera's silhouette
    cells = np.zeros((len(cameras), len(X)), np.intp)
    misses = np.zeros(len(X), np.int8)
    running = np.arange(len(X))
    for index, (camera, mask, part, shape) in enumerate(zip(cameras, masks, found, shapes, strict=True)):
        seen, at = pixels_seen(camera, X.take(running, axis=0), mask.shape)
        running = running.compress(seen)
        rows, cols = np.divmod(at, mask.shape[1])
        hit = mask.ravel().take(at) > 0
        own[index, running] = hit
        if part is not None:
            hit |= part.ravel().take(at) > 0
        inside[index, running] = hit
        cells[index, running] = (rows // cell_size(camera)) * shape[1] + cols // cell_size(camera)
        misses[running] += ~hit
        running = running.compress(misses.take(running) < 2)
    for index, shape in enumerate(shapes):
        # Placed by the others: seen by every camera and inside every other one's silhouette.
        others_agree = running.compress(misses.take(running) == (~inside[index]).take(running))
        at = cells[index].take(others_agree)
        count = np.bincount(at, minlength=shape[0] * shape[1]).reshape(shape)
        background = np.bincount(at.compress(~own[index].take(others_agree)),
                                 minlength=shape[0] * shape[1]).reshape(shape)
        placed[index] = (count > 0).astype(int)
        hidden[index][0] = (count > 0) & (background >= HIDDEN_SHARE * count)
    return CellVotes(tuple(placed), tuple(hidden), centres)


def search_hidden_parts(frames: Callable[[], Iterable[Sequence[np.ndarray]]], cameras: Sequence[Camera],
                        volume: np.ndarray) -> list[np.ndarray | None]:
    """Each camera's (H, W) uint8 part of the view hidden behind something in front of the subject, or None, from
    the silhouettes of the frames that ``frames()`` yields (one sequence of masks per frame, every call the same).

    The search goes in rounds: a part found is counted inside its camera's silhouette when that camera is one of the
    others in the next round (:func:`hidden_votes`), so that a thing that hides the subject from two cameras at once
    (a desk before two of them) is found in the second once it is found in the first, where it hides less; the
    rounds end when one finds nothing new. Without anything hidden that is one round.
    """
    found: list[np.ndarray | None] = [None] * len(cameras)
    if len(cameras) < MIN_CAMERAS:
        return found
    for _ in range(len(cameras)):
        votes = no_votes(cameras)
        for masks in frames():
            votes = votes + hidden_votes(masks, cameras, volume, found)
        merged = [parts_union(before, now) for before, now in zip(found, hidden_parts(votes, cameras), strict=True)]
        if all(_same(before, after) for before, after in zip(found, merged, strict=True)):
            break
        found = merged
    return found


def parts_union(a: np.ndarray | None, b: np.ndarray | None) -> np.ndarray | None:
    """The union of two (H, W) uint8 parts of a view, either of them None (no part)."""
    return b if a is None else a if b is None else cv2.bitwise_or(a, b)


def _same(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    return (a is None) == (b is None) and (a is None or np.array_equal(a, b))


def hidden_parts(votes: CellVotes, cameras: Sequence[Camera]) -> list[np.ndarray | None]:
    """Each camera's (H, W) uint8 map (255: hidden behind something in front of the subject) from the votes of
    frames spread over the capture, or None where nothing is hidden.

    A cell is hidden when the camera showed background there on ``PERSISTENT_SHARE`` of the frames where the
    others placed the subject in it and on at least ``MIN_HIDDEN_FRAMES``, and its connected part of such cells is
    large (``MIN_PART_SHARE``); the camera's large parts count when they were hidden while the subject's image
    moved (``MIN_TRAVEL``). The parts found are filled (a cell inside one that the sampled frames missed is hidden
    too) and grown by a cell, so that the band between the subject's visible part and the first cell found is
    covered too.
    """
    maps = []
    for camera, placed, hidden, centres in zip(cameras, votes.placed, votes.hidden, votes.centres, strict=True):
        times = hidden.sum(axis=0)
        found = ((times >= MIN_HIDDEN_FRAMES) & (times >= PERSISTENT_SHARE * placed)).astype(np.uint8)
        contours, _ = cv2.findContours(found, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        filled = cv2.drawContours(found, contours, -1, 1, thickness=cv2.FILLED)
        count, labels, stats, _ = cv2.connectedComponentsWithStats(filled, connectivity=8)
        subject_cells = placed.sum() / max(votes.frames, 1)
        size = np.sqrt(subject_cells) * cell_size(camera)  # of the subject's image, pixels
        large = np.isin(labels, np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= MIN_PART_SHARE * subject_cells) + 1)
        if not large.any() or _travel(centres[hidden[:, large].any(axis=1)]) < MIN_TRAVEL * size:
            maps.append(None)
            continue
        cells = cv2.dilate(large.astype(np.uint8) * np.uint8(255), np.ones((3, 3), np.uint8))
        cell = cell_size(camera)
        width, height = camera.size
        maps.append(cv2.resize(cells, (cells.shape[1] * cell, cells.shape[0] * cell),
                               interpolation=cv2.INTER_NEAREST)[:height, :width])
    return maps


def _cells_shape(camera: Camera) -> tuple[int, int]:
    """(rows, columns) of a camera's vote cells."""
    cell = cell_size(camera)
    return -(-camera.size[1] // cell), -(-camera.size[0] // cell)


def _silhouette_pixels(mask: np.ndarray) -> np.ndarray:
    """(n, 2) float (u, v) every ``PIXEL_STRIDE``-th pixel of a silhouette (H, W) uint8 along both axes: the rays
    are cast through some of them, and their mean is where the silhouette is."""
    pixels = cv2.findNonZero(np.ascontiguousarray(mask[::PIXEL_STRIDE, ::PIXEL_STRIDE]))
    return np.zeros((0, 2)) if pixels is None else pixels.reshape(-1, 2).astype(float) * PIXEL_STRIDE


def _travel(centres: np.ndarray) -> float:
    """How far apart (pixels) the subject's image was over frames whose silhouette centroids are ``centres``
    (n, 2): the diagonal of their box (0 for fewer than two)."""
    centres = centres[np.isfinite(centres).all(axis=1)]
    return float(np.hypot(*np.ptp(centres, axis=0))) if len(centres) > 1 else 0.0


def _ray_points(masks: Sequence[np.ndarray], pixels: Sequence[np.ndarray], cameras: Sequence[Camera],
                volume: np.ndarray) -> np.ndarray:
    """(N, 3) points along rays through ``RAYS_PER_VIEW`` of each view's silhouette ``pixels`` (n, 2), spread evenly,
    ``POINTS_PER_RAY`` per ray, evenly over the ray's stretch in the working volume that lies inside the convex
    hulls of the other views' silhouettes ``masks``, all of them but one (`hull_bounds`)."""
    origins, directions, camera_of, outlines = [], [], [], []
    for index, (camera, mask, ours) in enumerate(zip(cameras, masks, pixels, strict=True)):
        outlines.append(outline_points(camera, mask))
        if not len(ours):
            continue
        chosen = evenly_spread(len(ours), RAYS_PER_VIEW)
        directions.append(camera.pixel_rays(ours[chosen]))
        origins.append(np.repeat(camera.centre[None], len(chosen), axis=0))
        camera_of.append(np.full(len(chosen), index))
    if not origins:
        return np.zeros((0, 3))
    origins, directions, camera_of = np.concatenate(origins), np.concatenate(directions), np.concatenate(camera_of)
    enter, leave = box_interval(origins, directions, volume)
    low, high = hull_bounds(list(cameras), outlines, origins, directions, camera_of, 1,
                            [blind_beyond_image(mask) for mask in masks])
    enter, leave = np.maximum(enter, low), np.minimum(leave, high)
    crossing = np.flatnonzero(enter < leave)
    enter, leave = enter[crossing], leave[crossing]
    t = enter[:, None] + (leave - enter)[:, None] * (np.arange(POINTS_PER_RAY) + 0.5) / POINTS_PER_RAY
    return (origins[crossing, None, :] + t[..., None] * directions[crossing, None, :]).reshape(-1, 3)
