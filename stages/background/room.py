"""Parts of a clean plate that the room no longer shows: something placed or moved after the plate was taken.

A plate is taken before the recording, and the room may change before the subject walks in: a box put down, a
chair moved, a bag left by the wall. Against the plate, such a thing is foreground in every frame of every camera
that sees it, and, being solid, the views agree on it: the multi-view check keeps it, the visual hull holds it, and
it takes its share of the reconstruction's points and outlines from the subject (merged with his silhouette where
he passes in front of it in a view). A background estimated from the frames has no such trouble: a thing that never
moves is part of their median.

Such a part shows in a camera's silhouettes over the capture (:func:`static_parts`): it is foreground in nearly
every frame, and the subject's moving silhouette is elsewhere in the image in most of the frames where he moves. A
subject who stands still while part of him moves (a stance held while the arms swing, a squat on one spot) is
foreground in every frame too, but the moving part of his silhouette belongs to the same connected silhouette as
the still part; a subject who never moves at all gives no frame with movement, and nothing is decided. The camera's
background there is then taken from frames where the subject is away from the part (:func:`patched_plate`),
brought to the plate's exposure, and the silhouettes are made again.

Decided on blocks of ``CELL_PX`` pixels, from the masks of frames spread over the capture: the masks say where
something differs from the plate, and a few frames' images what the room now looks like there.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import cv2
import numpy as np

#: Masks are compared on square blocks of this many pixels a side (a block is foreground where a pixel is).
CELL_PX = 4
#: A block foreground in at least this share of the frames checked is persistent.
PERSISTENT_SHARE = 0.9
#: A persistent part is the room's when the subject's moving silhouette is apart from it in at least this share of
#: the frames where he moves; passing in front of it in a view joins them for a while.
APART_SHARE = 0.5
#: Frames with movement needed to decide at all (a subject who stays still shows none).
MIN_MOVING_FRAMES = 4
#: A frame shows movement where at least this many blocks are foreground and not persistent (the subject's limbs
#: or more; a flickering block at the persistent parts' edges is not movement).
MIN_MOVING_CELLS = 8
#: Persistent parts smaller than this many blocks are left alone (a speck of the room that cost nothing).
MIN_PART_CELLS = 8
#: Frames whose images make the patch: the per-pixel median of this many frames where the subject is apart.
PATCH_FRAMES = 5


def static_parts(masks: Iterable[np.ndarray]) -> tuple[np.ndarray, list[int]]:
    """Where one camera's silhouettes hold a part of the room that changed since its plate, and the frames that show
    that part apart from the subject.

    Parameters
    ----------
    masks : iterable of (H, W) uint8
        The camera's silhouettes (0 = background) of frames spread over the capture (one at a time: only their blocks
        are kept).

    Returns
    -------
    region : (H, W) bool
        The pixels of the blocks of the room's parts (all False when there is none).
    apart : list of int
        Indices into ``masks`` of the frames in which every one of those parts is apart from the subject's moving
        silhouette (empty when there is no part).
    """
    shape, blocks = None, []
    for mask in masks:
        shape = mask.shape
        blocks.append(_cells(mask))
    if not blocks:
        raise ValueError("static_parts: expected the masks of at least one frame")
    cells = np.stack(blocks)  # (K, h, w) bool
    persistent = cells.sum(axis=0) >= np.ceil(PERSISTENT_SHARE * len(cells))
    nothing = np.zeros(shape, bool), []
    if persistent.sum() < MIN_PART_CELLS:
        return nothing
    count, parts = cv2.connectedComponents(persistent.view(np.uint8), connectivity=8)
    # The persistent parts' edges flicker in and out with the outline: not movement.
    edge = cv2.dilate(persistent.view(np.uint8), np.ones((3, 3), np.uint8)) > 0
    touched = np.zeros((len(cells), count), bool)  # frame, part: joined to moving blocks
    moving = np.zeros(len(cells), bool)
    for k, frame_cells in enumerate(cells):
        movement = frame_cells & ~edge
        if movement.sum() < MIN_MOVING_CELLS:
            continue
        moving[k] = True
        _, pieces = cv2.connectedComponents(frame_cells.view(np.uint8), connectivity=8)
        joined = np.unique(pieces[movement])  # the pieces of this frame's silhouette that move
        touched[k] = np.isin(np.arange(count), parts[persistent & np.isin(pieces, joined)])
    if moving.sum() < MIN_MOVING_FRAMES:
        return nothing
    sizes = np.bincount(parts.ravel(), minlength=count)
    apart_share = 1.0 - touched[moving].mean(axis=0)
    room = [part for part in range(1, count) if sizes[part] >= MIN_PART_CELLS and apart_share[part] >= APART_SHARE]
    if not room:
        return nothing
    apart = [int(k) for k in np.flatnonzero(moving & ~touched[:, room].any(axis=1))]
    if not apart:  # no frame shows every part bare at once (parts the subject takes turns before): nothing to take
        return nothing
    return _pixels(np.isin(parts, room), shape), apart


def patched_plate(plate: np.ndarray, region: np.ndarray, frames: Sequence[np.ndarray],
                  masks: Sequence[np.ndarray]) -> np.ndarray:
    """``plate`` (H, W, 3) uint8 with the pixels of ``region`` (H, W) bool taken from ``frames`` (their per-pixel
    median), each first brought to the plate's exposure by one ratio per channel measured on its background
    (outside its mask in ``masks`` and outside ``region``): the frames may be brighter or darker than the plate
    (flicker, automatic exposure), and the silhouettes fit the frames' exposure to the plate's everywhere else."""
    if not len(frames):
        raise ValueError("patched_plate: expected at least one frame")
    rows, cols = np.nonzero(region)
    plate_levels = plate.astype(np.float32)
    taken = []
    for frame, mask in zip(frames, masks, strict=True):
        background = (mask == 0) & ~region
        background[1::4] = False  # every fourth row and column is plenty for three ratios
        background[:, 1::4] = False
        ratio = _channel_ratios(frame[background].astype(np.float32), plate_levels[background])
        taken.append(frame[rows, cols].astype(np.float32) / ratio)
    patched = plate.copy()
    patched[rows, cols] = np.clip(np.round(np.median(np.stack(taken), axis=0)), 0, 255).astype(np.uint8)
    return patched


def _channel_ratios(frame: np.ndarray, plate: np.ndarray) -> np.ndarray:
    """(3,) the frame's level over the plate's per channel, over corresponding (n, 3) pixels: the ratio of their
    sums over the pixels neither too dark to measure nor saturated; 1 where none is."""
    usable = (plate > 16) & (plate < 240) & (frame < 250)
    ratios = np.ones(3, np.float32)
    for channel in range(3):
        chosen = usable[:, channel]
        if chosen.sum() >= 16:
            ratios[channel] = frame[chosen, channel].sum() / plate[chosen, channel].sum()
    return ratios


def _cells(mask: np.ndarray) -> np.ndarray:
    """(h, w) bool: the ``CELL_PX`` blocks of ``mask`` (H, W) that hold a foreground pixel (partial blocks at the far
    edges included)."""
    height, width = mask.shape
    rows, cols = -(-height // CELL_PX), -(-width // CELL_PX)
    padded = mask
    if (rows * CELL_PX, cols * CELL_PX) != mask.shape:
        padded = np.zeros((rows * CELL_PX, cols * CELL_PX), np.uint8)
        padded[:height, :width] = mask
    # Area averaging by a whole factor is the exact mean of each block: above 0 where a pixel is set.
    return cv2.resize(padded, (cols, rows), interpolation=cv2.INTER_AREA) > 0


def _pixels(cells: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: the pixels of the blocks ``cells`` (h, w) bool, grown by one block (the part's antialiased
    edge, half in a block the masks left out)."""
    grown = cv2.dilate(cells.view(np.uint8), np.ones((3, 3), np.uint8))
    full = cv2.resize(grown, (cells.shape[1] * CELL_PX, cells.shape[0] * CELL_PX), interpolation=cv2.INTER_NEAREST)
    return full[: shape[0], : shape[1]] > 0
