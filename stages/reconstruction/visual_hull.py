"""The visual hull by coarse-to-fine voxel carving and marching cubes.

Rather than a binary occupancy, every voxel centre X gets a signed distance to the hull,

    φ(X) = the (k+1)-th smallest over views c of  s_c(π_c(X)) · depth_c(X) / f_c,

where s_c is the signed distance (pixels, positive inside) of the projection to silhouette c's outline
(off the image: far outside, or far inside for a view that does not frame the whole person, which cannot veto
what it does not see: `views.blind_beyond_image`), scaled to metres at the point's depth, and k is the number
of tolerated disagreeing views (k = 0 gives the plain hull, the minimum over views). Marching cubes on φ then
places the surface between voxel centres, and the gradient of φ gives outward normals.

Coarse to fine: φ is first evaluated on coarse voxels; a voxel whose |φ| exceeds twice its half
diagonal cannot contain the surface (φ changes by little more than the distance moved), so only the
children of the others are evaluated at the next, twice finer level.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from skimage.measure import marching_cubes

from calib.camera import MIN_VIEW_DEPTH_M, Camera, Rig
from stages.reconstruction.views import blind_beyond_image

# A voxel is refined when |φ| at its centre is below this many half diagonals: φ measures distance in
# the image plane at the point's depth, which grows a little faster than 3-D distance off the optical axis.
BAND_FACTOR = 2.0
# |φ| (metres) of points outside an image or behind a camera: far outside any silhouette (inside, for a view
# that does not frame the whole person), and the bound of any φ.
FAR_OUTSIDE_M = 10.0
# Signed distance (pixels) reported off the image: further than any real outline distance (outside, or inside
# for a view that does not frame the whole person).
OFF_IMAGE_PX = 1e5
REMAP_ROW = 1024


def hull_surface_points(
    masks: Sequence[np.ndarray],
    rig: Rig,
    volume: np.ndarray,
    *,
    n_observations: int,
    tolerated_views: int,
    voxel_size_m: float,
    coarse_voxel_size_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) on the visual hull's surface and unit outward normals (N, 3), N <= ``n_observations``."""
    cameras = list(rig)
    distance_maps = [_signed_distance_px(mask) for mask in masks]
    blind = [blind_beyond_image(mask) for mask in masks]
    levels = max(0, int(np.ceil(np.log2(coarse_voxel_size_m / voxel_size_m))))
    block = 2**levels
    cells = np.ceil((volume[1] - volume[0]) / (voxel_size_m * block)).astype(int)  # coarse cells per axis

    def phi(X: np.ndarray) -> np.ndarray:
        return _hull_distance(cameras, distance_maps, X, tolerated_views, blind)

    size = voxel_size_m * block
    centres = _grid_centres(volume[0], size, (0, 0, 0), cells)
    field = phi(centres.reshape(-1, 3)).reshape(cells)
    candidate = field > -BAND_FACTOR * _half_diagonal(size)
    if not candidate.any():
        return np.zeros((0, 3)), np.zeros((0, 3))
    # Crop to the candidates' bounding box (plus one coarse cell), so the fine grid stays small.
    found = np.argwhere(candidate)
    low = np.maximum(found.min(axis=0) - 1, 0)
    high = np.minimum(found.max(axis=0) + 2, cells)
    field = field[low[0]:high[0], low[1]:high[1], low[2]:high[2]]
    origin = volume[0] + low * size

    for _ in range(levels):
        band = np.abs(field) < BAND_FACTOR * _half_diagonal(size)
        size /= 2.0
        field = _upsample(field)
        refine = np.argwhere(_upsample(band))
        field[tuple(refine.T)] = phi(origin + (refine + 0.5) * size)

    # Pad with "outside" so that a body touching the crop's edge still gets a closed surface.
    padded = np.pad(field, 1, constant_values=-FAR_OUTSIDE_M).astype(np.float32)
    if padded.max() <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    vertices, _, normals, _ = marching_cubes(padded, 0.0, spacing=(size, size, size))
    points = origin + vertices - 0.5 * size  # voxel centre (i + 0.5) h in the unpadded grid is index i + 1
    # φ grows inwards; skimage's default 'descent' normals point down the gradient, i.e. outwards.
    normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-15)
    inside_volume = np.all((points >= volume[0]) & (points <= volume[1]), axis=1)
    points, normals = points[inside_volume], normals[inside_volume]
    if len(points) > n_observations:
        chosen = np.unique(np.linspace(0, len(points) - 1, n_observations).round().astype(int))
        points, normals = points[chosen], normals[chosen]
    return points.astype(np.float64), normals.astype(np.float64)


def _signed_distance_px(mask: np.ndarray) -> np.ndarray:
    """(H, W) float32 signed distance (pixels) from each pixel centre to the silhouette's outline,
    positive inside; the outline lies half-way between foreground and background pixel centres."""
    foreground = (mask > 0).astype(np.uint8)
    inside = cv2.distanceTransform(foreground, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    outside = cv2.distanceTransform(1 - foreground, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.where(foreground > 0, inside - 0.5, 0.5 - outside).astype(np.float32)


def _hull_distance(cameras: list[Camera], distance_maps: list[np.ndarray], X: np.ndarray,
                   tolerated_views: int, blind: list[bool]) -> np.ndarray:
    """(N,) φ(X) for world points ``X`` (N, 3): the (k+1)-th smallest per-view signed distance (metres); where a
    view does not see a point, far outside, or far inside for the views ``blind`` beyond their images."""
    per_view = np.empty((len(cameras), len(X)), np.float32)
    for index, (camera, distance) in enumerate(zip(cameras, distance_maps, strict=True)):
        sign = 1.0 if blind[index] else -1.0
        sampled = _bilinear(distance, camera.project(X), sign * OFF_IMAGE_PX)
        depth = camera.depth(X)
        focal = 0.5 * (camera.K[0, 0] + camera.K[1, 1])
        metres = sampled * np.maximum(depth, MIN_VIEW_DEPTH_M) / focal
        per_view[index] = np.where(depth > MIN_VIEW_DEPTH_M, np.clip(metres, -FAR_OUTSIDE_M, FAR_OUTSIDE_M),
                                   sign * FAR_OUTSIDE_M)
    order = min(tolerated_views, len(cameras) - 1)
    return np.partition(per_view, order, axis=0)[order]


def _bilinear(image: np.ndarray, uv: np.ndarray, off_image: float) -> np.ndarray:
    """(N,) float32 ``image`` (H, W) float32 interpolated at pixels ``uv`` (N, 2); ``off_image`` off the image.

    cv2.remap wants maps with fewer than 32767 columns, so the points are laid out in rows of 1024.
    """
    count = len(uv)
    rows = max(1, -(-count // REMAP_ROW))
    maps = np.zeros((rows * REMAP_ROW, 2), np.float32)
    maps[:count] = uv
    maps[count:] = -1e6  # padding, off the image
    sampled = cv2.remap(
        image, maps[:, 0].reshape(rows, REMAP_ROW), maps[:, 1].reshape(rows, REMAP_ROW), cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT, borderValue=off_image,
    )
    return sampled.ravel()[:count]


def _grid_centres(origin: np.ndarray, size: float, low, cells) -> np.ndarray:
    """(I, J, K, 3) centres of voxels ``low .. low + cells`` of side ``size`` from ``origin``."""
    axes = [origin[a] + (low[a] + np.arange(cells[a]) + 0.5) * size for a in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


def _half_diagonal(size: float) -> float:
    return 0.5 * np.sqrt(3.0) * size


def _upsample(grid: np.ndarray) -> np.ndarray:
    """Each voxel split into its 2 x 2 x 2 children, which inherit its value."""
    return grid.repeat(2, axis=0).repeat(2, axis=1).repeat(2, axis=2)
