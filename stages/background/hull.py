"""The visual hull of one sample's silhouettes on a voxel grid of the working volume, and the pixels it
covers in each view (steps 3 and 4 of :mod:`stages.background`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import cv2
import numpy as np

from calib.camera import Camera
from stages.silhouettes import disk

#: Voxel side of the hull (metres); larger in a large volume, so that the grid holds at most MAX_VOXELS.
VOXEL_M = 0.03
MAX_VOXELS = 2_000_000
#: The hull is carved first on cells of this many voxels a side.
COARSE_FACTOR = 4


def working_camera(camera: Camera, size: tuple[int, int]) -> Camera:
    """``camera`` for its images resized to ``size`` (w, h): full-resolution pixel centres at integers map to
    ``(u + ½) s − ½`` with ``s`` the ratio of sizes, so the resized image's pixel centres stay at integers."""
    width, height = camera.size
    sx, sy = size[0] / width, size[1] / height
    scale = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
    return replace(camera, K=scale @ camera.K, size=size)


class VoxelGrid:
    """Voxels of the working volume, coarse and fine, and where each camera sees their centres.

    The hull is carved coarse to fine: cells of ``COARSE_FACTOR`` fine voxels a side first, then the fine
    voxels of the cells that may hold the subject. Where the cameras see a fine voxel is worked out the
    first time its cell is needed and kept (the subject visits a small part of the volume), so the grid
    costs in proportion to the space the subject uses, not to the volume.
    """

    def __init__(self, cameras: Sequence[Camera], volume: np.ndarray):
        low, high = np.asarray(volume, dtype=float)
        self.cameras = list(cameras)
        self.voxel = max(VOXEL_M, float(np.prod(high - low) / MAX_VOXELS) ** (1 / 3))
        cell = COARSE_FACTOR * self.voxel
        self.cells = np.maximum(np.ceil((high - low) / cell).astype(int), 1)  # (3,) coarse cells per axis
        axes = [low[a] + np.arange(self.cells[a]) * cell for a in range(3)]
        self.cell_low = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)  # (M, 3) corners
        steps = (np.arange(COARSE_FACTOR) + 0.5) * self.voxel
        self.offsets = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), axis=-1).reshape(-1, 3)  # (F, 3)
        self.coarse_pixels, depths = self._pixels(self.cell_low + 0.5 * cell)
        # The fine voxels' pixels of the cells met so far: cell i's are store[:, slot[i]] (slot -1: not yet).
        self.slot = np.full(len(self.cell_low), -1, np.int64)
        self.store = np.zeros((len(self.cameras), 0, len(self.offsets)), np.int32)
        self.stored = 0
        focal = [0.5 * (camera.K[0, 0] + camera.K[1, 1]) for camera in self.cameras]
        typical = [float(np.median(d[p >= 0])) if (p >= 0).any() else 1.0
                   for d, p in zip(depths, self.coarse_pixels, strict=True)]
        # A voxel's half-diagonal, and a cell's, in working pixels at the camera's typical depth.
        self.fine_radius = [max(1, int(np.ceil(0.5 * np.sqrt(3.0) * self.voxel * f / z)))
                            for f, z in zip(focal, typical, strict=True)]
        self.coarse_radius = [max(1, int(np.ceil(0.5 * np.sqrt(3.0) * cell * f / z)))
                              for f, z in zip(focal, typical, strict=True)]

    def _pixels(self, X: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        """((C, N) int32 flat working pixel of each point ``X`` (N, 3) per camera, -1 where unseen; depths)."""
        pixels, depths = [], []
        for camera in self.cameras:
            depth = camera.depth(X)
            # Seen: in the image both without the distortion (which folds back far outside the image) and with it.
            seen = camera.sees(X)
            uv = np.full((len(X), 2), -1.0)
            uv[seen] = camera.project(X[seen])
            seen &= camera.in_image(uv)
            width, height = camera.size
            column = np.clip(np.floor(uv[:, 0] + 0.5), 0, width - 1)
            row = np.clip(np.floor(uv[:, 1] + 0.5), 0, height - 1)
            pixels.append(np.where(seen, row * width + column, -1).astype(np.int32))
            depths.append(depth)
        return np.stack(pixels), depths

    def fine(self, cells: np.ndarray) -> np.ndarray:
        """(C, len(cells), F) int32 working pixels of the fine voxels of coarse ``cells`` (M',) int."""
        new = cells[self.slot[cells] < 0]
        if len(new):
            X = (self.cell_low[new][:, None, :] + self.offsets[None]).reshape(-1, 3)
            pixels, _ = self._pixels(X)
            if self.stored + len(new) > self.store.shape[1]:  # grow by doubling: few copies
                grown = np.zeros((len(self.cameras), max(2 * self.store.shape[1], self.stored + len(new)),
                                  len(self.offsets)), np.int32)
                grown[:, : self.stored] = self.store[:, : self.stored]
                self.store = grown
            self.store[:, self.stored : self.stored + len(new)] = pixels.reshape(len(self.cameras), len(new), -1)
            self.slot[new] = np.arange(self.stored, self.stored + len(new))
            self.stored += len(new)
        return self.store[:, self.slot[cells]]


def tolerated_views(cameras: int) -> int:
    """How many cameras may disagree with a voxel of the hull: one from four cameras on (a view whose ghost
    hides the subject must not carve him), none with fewer (two or three views must all agree)."""
    return 1 if cameras >= 4 else 0


def _occupied(masks: Sequence[np.ndarray], pixels: np.ndarray, radius: Sequence[int], tolerated: int) -> np.ndarray:
    """(...) bool: which of the voxels whose centres the cameras see at ``pixels`` (C, ...) lie in the hull.

    A voxel is in it when at most ``tolerated`` of the cameras that see it see it outside their silhouette
    (each dilated by the voxel's footprint, ``radius`` per camera, so that a voxel the outline crosses
    counts as inside), and all but ``tolerated`` of the rig's cameras, and at least two, see it inside.
    """
    inside = np.zeros(pixels.shape[1:], np.int8)
    outside = np.zeros(pixels.shape[1:], np.int8)
    for c, mask in enumerate(masks):
        grown = cv2.dilate(mask, disk(radius[c]))
        flat = np.append(grown.ravel(), np.uint8(0))  # index -1 reads the appended 0
        hit = flat.take(pixels[c]) > 0
        inside += hit
        outside += (pixels[c] >= 0) & ~hit
    return (outside <= tolerated) & (inside >= max(2, len(masks) - 1 - tolerated))


def hull_cover(masks: Sequence[np.ndarray], grid: VoxelGrid, tolerated: int) -> tuple[list[np.ndarray], int]:
    """Per camera, (h, w) bool: the pixels onto which one sample's visual hull (see :func:`_occupied`)
    projects, each occupied fine voxel drawn as a disc of its footprint; and the hull's size in voxels."""
    cells = np.flatnonzero(_occupied(masks, grid.coarse_pixels, grid.coarse_radius, tolerated))
    pixels = grid.fine(cells)  # (C, M', F)
    occupied = _occupied(masks, pixels, grid.fine_radius, tolerated)
    covers = []
    for c, mask in enumerate(masks):
        cover = np.zeros(mask.size, np.uint8)
        where = pixels[c][occupied]
        cover[where[where >= 0]] = 255
        covers.append(cv2.dilate(cover.reshape(mask.shape), disk(grid.fine_radius[c])) > 0)
    return covers, int(occupied.sum())
