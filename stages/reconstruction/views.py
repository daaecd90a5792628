"""Inside-the-silhouette tests and ray geometry shared by the visual hull and the visual shape.

A world point is *inside* a view when it lies in front of the camera, projects into the image and
lands on a foreground pixel. A point the camera does not see (behind it, or projecting outside the image)
counts as outside the silhouette only when the view frames the whole person (:func:`blind_beyond_image`): such a view
says where he is not, also beyond its image, while one that cuts him off (his feet below its image, a raised
arm beside it) or does not show him at all cannot veto what it does not see.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from calib.camera import MIN_VIEW_DEPTH_M, Camera


def blind_beyond_image(mask: np.ndarray) -> bool:
    """Whether a view with the silhouette ``mask`` (H, W) cannot tell where the person is not beyond its image:
    the silhouette reaches the image's border (he goes on beyond it) or is empty (he is wholly beyond it, or
    away).

    A body is one piece, so a silhouette that is not empty and does not reach the border shows all of it.
    """
    return not mask.any() or _reaches_border(mask)


def subject_cut_off(mask: np.ndarray) -> bool:
    """Whether the largest piece of the silhouette ``mask`` (H, W) reaches the image's border: the subject himself,
    rather than a speck or a stray blob, goes on beyond the image (which makes the view blind beyond it, as
    :func:`blind_beyond_image` says of any silhouette reaching the border)."""
    if not _reaches_border(mask):  # cheap: most silhouettes keep clear of the border
        return False
    _, _, stats, _ = cv2.connectedComponentsWithStats((mask > 0).astype(np.uint8))
    x, y, width, height, _ = stats[1 + np.argmax(stats[1:, cv2.CC_STAT_AREA])]
    return bool(x == 0 or y == 0 or x + width == mask.shape[1] or y + height == mask.shape[0])


def _reaches_border(mask: np.ndarray) -> bool:
    """Whether any pixel of the silhouette ``mask`` (H, W) lies on the image's border."""
    return bool(mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())


def inside_view(camera: Camera, mask: np.ndarray, X: np.ndarray, corner: tuple[int, int] = (0, 0),
                off_image: bool = False) -> np.ndarray:
    """(N,) bool: which world points ``X`` (3, N) float32 are inside the view of ``camera`` with ``mask``.

    ``mask`` (h, w) may be a box of the image starting at pixel ``corner`` (column, row), outside which the
    silhouette is background: a box around the person keeps the pixel lookups in cache. ``off_image`` is the
    answer for points the camera does not see (behind it, or projecting outside its image): True for a view that
    does not frame the whole person (:func:`blind_beyond_image`).

    Points are stored by coordinate (3, N) so that picking a subset gathers three contiguous rows, and
    in float32, which keeps millimetre precision at these distances while halving the memory traffic.
    The visual shape calls this some thirty times a frame on a few thousand points, so per-call overhead
    counts: the camera's float32 constants are converted once (``_float32_camera``), x and y are scaled
    together as the rows of one (2, N) array, and the arithmetic happens in place.
    """
    if X.shape[1] == 1:
        # BLAS multiplies a single column differently (gemv, not gemm), last bits included: tested as a pair,
        # a point gets the same answer whichever points it is tested with.
        return inside_view(camera, mask, np.repeat(X, 2, axis=1), corner, off_image)[:1]
    R, t, dist, focal, centre, skew = _float32_camera(camera)
    xyz = R @ X
    xyz += t[:, None]
    z, xy = xyz[2], xyz[:2]
    front = z > MIN_VIEW_DEPTH_M
    seen = front.copy()
    inverse_z = np.where(seen, z, np.float32(1.0))
    xy *= np.divide(np.float32(1.0), inverse_z, out=inverse_z)
    if dist is not None:
        k1, k2, p1, p2, k3 = dist
        x, y = xy
        r2 = np.add(*(xy * xy))  # x x + y y
        radial = r2 * k3  # 1 + r2 (k1 + r2 (k2 + r2 k3)), evaluated in place
        radial += k2
        radial *= r2
        radial += k1
        radial *= r2
        radial += 1.0
        if p1 or p2:
            xy = np.stack([x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                           y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y])
        else:  # radial distortion only, common after calibration: a third of the arithmetic
            xy *= radial
    # Pixel coordinates; the centre is shifted by half a pixel so that truncation rounds to the nearest
    # pixel centre: pixel (0, 0) covers [-0.5, 0.5). A skewed K adds s y to u: (s / fx) y before the scaling.
    if skew:
        xy[0] += skew * xy[1]
    xy *= focal
    xy += centre
    # In the box, which lies in the image: for u >= 0, u >= left exactly when the pixel column int(u) >= left.
    height, width = mask.shape
    left, top = corner
    box = np.array([[left, left + width], [top, top + height]], np.float32)
    in_box = (xy >= box[:, :1]) & (xy < box[:, 1:])
    seen &= in_box[0] & in_box[1]
    column, row = xy.astype(np.intp)
    row -= top
    row *= width
    row += column
    row -= left
    # Unseen points' indices are meaningless: clipped into the mask, their pixels are read and ignored.
    inside = seen & (mask.ravel().take(row, mode="clip") > 0)
    if off_image:
        in_image = (xy >= 0.0) & (xy < np.array([[camera.size[0]], [camera.size[1]]], np.float32))
        inside |= ~(front & in_image[0] & in_image[1])
    return inside


@functools.lru_cache(maxsize=64)
def _float32_camera(camera: Camera) -> tuple:
    """``(R (3, 3), t (3,), dist (5,) or None without distortion, (fx, fy) (2, 1), (cx + ½, cy + ½) (2, 1),
    s / fx)`` of ``camera`` in float32, as :func:`inside_view` uses them: converted once per camera rather
    than on every call (cameras are immutable and hash by identity)."""
    K = camera.K
    fx, fy, cx, cy = (np.float32(value) for value in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    dist = camera.dist.astype(np.float32) if np.any(camera.dist) else None
    return (
        camera.R.astype(np.float32),
        camera.t.astype(np.float32),
        dist,
        np.array([[fx], [fy]], np.float32),
        np.array([[cx + np.float32(0.5)], [cy + np.float32(0.5)]], np.float32),
        np.float32(K[0, 1] / K[0, 0]),
    )


def ray_points(origins: np.ndarray, directions: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(3, M S) float32 world points ``origins + t directions`` of rays (M, 3) at ``t`` (M, S) or (M,), ray-major."""
    t = t.reshape(len(t), -1).astype(np.float32)
    o = origins.T.astype(np.float32)[:, :, None]  # (3, M, 1)
    d = directions.T.astype(np.float32)[:, :, None]
    return (o + t[None] * d).reshape(3, -1)


def in_volume(X: np.ndarray, volume: np.ndarray) -> np.ndarray:
    """(N,) bool: which points ``X`` (N, 3) lie in the box ``volume`` (2, 3)."""
    return np.all((X >= volume[0]) & (X <= volume[1]), axis=1)


#: The working volume's faces in the order of :func:`faces_reached`'s columns: (axis, which bound, name).
VOLUME_FACES = ((0, 0, "-x"), (0, 1, "+x"), (1, 0, "-y"), (1, 1, "+y"), (2, 0, "floor side (-z)"), (2, 1, "top (+z)"))


def faces_reached(X: np.ndarray, volume: np.ndarray, margin_m: float) -> np.ndarray:
    """(6,) bool: which faces of the box ``volume`` (2, 3) the points ``X`` (N, 3) come within ``margin_m`` of.

    The volume bounds the carving: a subject who reaches beyond a face is cut flat there, and his
    surface points then lie on that face. The bottom face counts only when it is above the floor
    (z = 0), where feet standing on the floor are expected to reach it.
    """
    if not len(X):
        return np.zeros(len(VOLUME_FACES), dtype=bool)
    low, high = X.min(axis=0), X.max(axis=0)
    reached = np.array([low[axis] <= volume[0, axis] + margin_m if bound == 0 else
                        high[axis] >= volume[1, axis] - margin_m for axis, bound, _ in VOLUME_FACES])
    reached[4] &= volume[0, 2] > 0.0
    return reached
