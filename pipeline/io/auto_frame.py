"""``up: auto``: find the vertical and the floor of a capture whose calibration world is arbitrary.

Calibration tools (anipose, FreeMoCap, most checkerboard tools) leave the world in camera 1's frame or
the board's: no floor at z = 0, no axis-aligned up. The pipeline's frame (+z up, floor at z = 0) is
found in two steps, once, as the capture is opened, before any stage runs (the silhouettes' shadow test
and the working volume use the floor):

1. **The vertical from the rig** (:func:`calib.world.rig_vertical`): the direction perpendicular to the
   cameras' image x axes, since studio cameras pitch but hardly roll.
2. **The floor from the images**: in a few frames spread over the capture, the subject's silhouettes
   (from the clean plates or a temporal median; shadows removed by colour, since a shadow on the floor
   carves into a cone below it as deep as its half-width times the tangent of the cameras' elevation)
   are carved into a visual hull around the point the cameras aim at, coarse to find the subject, then
   fine under its lowest part. The floor is the hull's lowest level that holds a few cells
   (:func:`floor_level`), the median over the frames, which ignores the frames where the subject jumps.
   It lies a little above the true floor: the soles' edges are thinner than what the silhouettes
   resolve.

The new frame has its origin on the floor below the cameras' aim point and +x along camera 1's image
x axis made horizontal; :class:`AutoFrame` records the transform and what was found.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from calib.camera import Rig
from calib.errors import InputError
from calib.world import WorldTransform, level_rotation, rig_vertical
from pipeline.io.backgrounds import background_image, spread_frames
from stages.rays import nearest_point
from stages.silhouettes import SilhouetteParams, extract_silhouette

if TYPE_CHECKING:
    from pipeline.io.capture import Capture

log = logging.getLogger(__name__)

#: Frames whose hulls are measured: the median over them ignores a few frames of a jump.
FLOOR_FRAMES = 5
#: The silhouettes of the floor search have no shadow test (there is no floor to test shadows on yet): a
#: shadow counts as the person, which errs towards a floor a little low, never one that cuts off the feet.
FLOOR_SILHOUETTES = SilhouetteParams(shadows="none")
#: The search box around the aim point: the subject stands at most this far below it (metres) ...
SEARCH_BELOW_M = 3.0
#: ... and its feet at most this far above it (cameras aimed at the subject's feet).
SEARCH_ABOVE_M = 1.0
#: Horizontal half-size of the search box: this fraction of the cameras' median horizontal distance
#: from the aim point, within the bounds below (metres).
SEARCH_RADIUS_FRACTION = 0.8
SEARCH_RADIUS_BOUNDS_M = (1.0, 4.0)
#: Voxel side of the coarse hull (metres) that locates the subject's lowest part (its centres may miss
#: the feet, which the fine hull's range below covers).
COARSE_VOXEL_M = 0.12
#: The fine hull under that part: cells of this width and height (metres) ...
FINE_CELL_M = (0.025, 0.005)
#: ... from this far below the coarse bottom to this far above it (metres), ...
FINE_RANGE_M = (0.25, 0.05)
#: ... over the coarse voxels up to this far above the bottom, widened by this much (a foot reaches
#: forward of the shin).
LOW_PART_M = (0.6, 0.2)
#: A level counts as occupied from this many fine cells on (specks of noise carve a few cells).
MIN_LEVEL_CELLS = 4
#: When the fine hull's lowest level is occupied (the coarse voxels missed the feet), its range moves
#: down by its height, at most this many times.
MAX_FINE_MOVES = 3


@dataclass(frozen=True)
class AutoFrame:
    """What ``up: auto`` found, in the calibration's world scaled to metres.

    Attributes
    ----------
    transform : WorldTransform
        Calibration world to the pipeline's world.
    vertical : (3,) float
        Up, unit, in the calibration's axes.
    vertical_method : str
        How the vertical was found (:func:`calib.world.rig_vertical`).
    floor_levels_m : tuple of float
        The floor height found in each measured frame, metres along ``vertical``.
    frames : tuple of int
        The frames measured.
    """

    transform: WorldTransform
    vertical: np.ndarray
    vertical_method: str
    floor_levels_m: tuple[float, ...]
    frames: tuple[int, ...]

    def to_dict(self) -> dict:
        """Plain data for ``capture.json``."""
        return {"vertical_in_calibration": self.vertical.tolist(), "vertical_method": self.vertical_method,
                "floor_levels_m": list(self.floor_levels_m), "frames": list(self.frames)}

    def describe(self) -> str:
        """One line for the log: the tilt found, the floor and how much the frames agree."""
        tilt = np.degrees(np.arccos(np.clip(abs(self.vertical).max(), -1.0, 1.0)))
        axis = "xyz"[int(np.argmax(abs(self.vertical)))]
        sign = "+" if self.vertical[int(np.argmax(abs(self.vertical)))] > 0 else "-"
        levels = np.array(self.floor_levels_m)
        return (f"up: auto: vertical {np.round(self.vertical, 4).tolist()} in the calibration's axes "
                f"({tilt:.1f} deg from its {sign}{axis}), {self.vertical_method}; floor at "
                f"{np.median(levels):.3f} m along it, from the subject's visual hull in {len(levels)} frames "
                f"(range {levels.min():.3f} to {levels.max():.3f} m)")


def aim_point(rig: Rig) -> np.ndarray:
    """(3,) the point nearest to all the cameras' optical axes (`stages.rays.nearest_point`): where they look.
    With one camera, or axes all parallel, the point 3 m in front of the first camera."""
    aim = nearest_point(rig.centres, np.array([camera.R[2] for camera in rig]))
    return rig[0].centre + 3.0 * rig[0].R[2] if aim is None else aim


def view_indices(rig: Rig, X: np.ndarray) -> np.ndarray:
    """(C, N) int64 flat pixel index of points ``X`` (N, 3) in each camera, -1 where not in view.

    A point is in view when it is in front of the camera and its pixel, with and without the lens
    distortion (the polynomial folds back far outside the image), lies inside the image.
    """
    indices = np.full((len(rig), len(X)), -1, dtype=np.int64)
    for c, camera in enumerate(rig):
        seen = camera.sees(X)
        uv = np.full((len(X), 2), np.inf)
        uv[seen] = camera.project(X[seen])
        seen &= camera.in_image(uv)
        pixels = np.floor(uv[seen] + 0.5).astype(np.int64)
        width = camera.size[0]
        where = np.flatnonzero(seen)
        indices[c, where] = np.clip(pixels[:, 1], 0, camera.size[1] - 1) * width + np.clip(pixels[:, 0], 0,
                                                                                             width - 1)
    return indices


def hull_occupancy(indices: np.ndarray, masks: Sequence[np.ndarray]) -> np.ndarray:
    """(N,) bool: points inside every silhouette that sees them, and seen by nearly all cameras.

    ``indices`` (C, N) from :func:`view_indices`; ``masks`` (H, W) uint8 per camera. One camera may miss
    a point (a close camera cuts off the feet) when there are more than three.
    """
    cameras = len(masks)
    needed = cameras if cameras <= 3 else cameras - 1
    seen = indices >= 0
    inside = np.ones(indices.shape[1], dtype=bool)
    for c, mask in enumerate(masks):
        inside &= ~seen[c] | (mask.ravel()[np.maximum(indices[c], 0)] > 0)
    return inside & (seen.sum(axis=0) >= needed)


def _grid(low: np.ndarray, high: np.ndarray, steps: np.ndarray) -> tuple[np.ndarray, tuple[int, int, int]]:
    """((N, 3) cell centres, (nx, ny, nz)) of the box ``low .. high`` cut into cells of ``steps`` (3,)."""
    counts = np.maximum(np.ceil((high - low) / steps).astype(int), 1)
    axes = [low[k] + (np.arange(counts[k]) + 0.5) * steps[k] for k in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3), tuple(counts)


def floor_level(levels_z: np.ndarray, cells: np.ndarray) -> float | None:
    """Height of the floor from a hull's cross-sections ``cells`` (Z,) at heights ``levels_z`` (Z,), or None.

    The lowest level holding ``MIN_LEVEL_CELLS`` cells, None when there is none.
    """
    occupied = np.flatnonzero(cells >= MIN_LEVEL_CELLS)
    return float(levels_z[occupied[0]]) if len(occupied) else None


def frame_floor(rig: Rig, masks: Sequence[np.ndarray], coarse: np.ndarray, coarse_indices: np.ndarray) -> float | None:
    """The floor height (levelled z, metres) under the subject in one frame, or None if not found.

    The coarse hull (``coarse`` (N, 3) voxel centres and their ``coarse_indices``) finds the subject's
    lowest voxels; a fine hull of ``FINE_CELL_M`` cells over and below them gives the cross-sections
    that :func:`floor_level` reads.
    """
    occupied = hull_occupancy(coarse_indices, masks)
    if not occupied.any():
        return None
    bottom = coarse[occupied, 2].min()
    low_part = coarse[occupied & (coarse[:, 2] <= bottom + LOW_PART_M[0])]
    low = np.array([*(low_part[:, :2].min(axis=0) - LOW_PART_M[1]), bottom - FINE_RANGE_M[0]])
    high = np.array([*(low_part[:, :2].max(axis=0) + LOW_PART_M[1]), bottom + FINE_RANGE_M[1]])
    width, height = FINE_CELL_M
    for _ in range(MAX_FINE_MOVES + 1):
        X, shape = _grid(low, high, np.array([width, width, height]))
        cells = hull_occupancy(view_indices(rig, X), masks).reshape(shape).sum(axis=(0, 1))  # (Z,)
        if cells[0] < MIN_LEVEL_CELLS:
            break
        low, high = low - [0.0, 0.0, high[2] - low[2]], high - [0.0, 0.0, high[2] - low[2]]
    return floor_level(X.reshape(*shape, 3)[0, 0, :, 2], cells)


def _masks(capture: Capture, frames: list[int]) -> dict[int, list[np.ndarray]]:
    """Silhouettes of ``frames`` in every camera: the given ones, else against the camera's background as
    the silhouette stage makes it (its clean plate, or the median of frames spread over the capture)."""
    masks: dict[int, list[np.ndarray]] = {frame: [] for frame in frames}
    for camera in capture.rig.names:
        if capture.silhouettes_given:
            masks_of_camera = [capture.read_silhouette(camera, frame) for frame in frames]
        else:
            background = background_image(capture, camera)
            masks_of_camera = [extract_silhouette(image, background, FLOOR_SILHOUETTES)
                               for _, image in capture.iter_images(camera, frames)]
        for frame, mask in zip(frames, masks_of_camera, strict=True):
            masks[frame].append(mask)
    return masks


def find_world_frame(capture: Capture, scale: float) -> AutoFrame:
    """The transform into a frame with +z up and the floor at z = 0 for ``capture``, whose rig is in the
    calibration's axes scaled to metres (``scale`` metres per calibration unit): ``transform.apply`` takes
    the calibration's rig in its own units."""
    rig = capture.rig
    vertical, method = rig_vertical(rig)
    A = level_rotation(vertical, rig[0].R[0])
    levelled = WorldTransform(A, np.zeros(3), 1.0).apply(rig)
    aim = A @ aim_point(rig)
    horizontal = np.median(np.linalg.norm(levelled.centres[:, :2] - aim[:2], axis=1))
    radius = float(np.clip(SEARCH_RADIUS_FRACTION * horizontal, *SEARCH_RADIUS_BOUNDS_M))
    low = np.array([aim[0] - radius, aim[1] - radius, aim[2] - SEARCH_BELOW_M])
    high = np.array([aim[0] + radius, aim[1] + radius, aim[2] + SEARCH_ABOVE_M])
    coarse, _ = _grid(low, high, np.full(3, COARSE_VOXEL_M))
    coarse_indices = view_indices(levelled, coarse)
    frames = spread_frames(capture.frame_numbers, FLOOR_FRAMES)
    masks = _masks(capture, frames)
    found = {frame: frame_floor(levelled, masks[frame], coarse, coarse_indices) for frame in frames}
    levels = {frame: level for frame, level in found.items() if level is not None}
    if not levels:
        raise InputError(f"{capture.root / 'capture.yaml'}: up: auto found no subject seen by the cameras in "
                         f"frames {frames} (expected a person in view of nearly all cameras, or a declared up "
                         "axis and a volume)")
    floor = float(np.median(list(levels.values())))
    transform = WorldTransform(A, np.array([-aim[0], -aim[1], -floor]), scale)
    return AutoFrame(transform, vertical, method, tuple(levels.values()), tuple(levels))
