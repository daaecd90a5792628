"""Inside-the-silhouette tests and ray geometry shared by the visual hull and the visual shape.

A world point is *inside* a view when it lies in front of the camera, projects into the image and
lands on a foreground pixel. A point outside the image counts as outside the silhouette: the working
volume is meant to be seen by every camera, and a camera that misses part of the person is one of the
``tolerated_views`` that may disagree.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calib.camera import Camera

# Points closer than this to a camera's image plane (metres of depth) are treated as behind it.
MIN_DEPTH_M = 1e-3


def inside(camera: Camera, mask: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(N,) bool: which world points ``X`` (N, 3) project onto the foreground of ``mask`` (H, W)."""
    if len(X) == 0:
        return np.zeros(0, bool)
    uv = camera.project(X)
    height, width = mask.shape
    u = np.rint(uv[:, 0])
    v = np.rint(uv[:, 1])
    seen = (camera.depth(X) > MIN_DEPTH_M) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    result = np.zeros(len(X), bool)
    result[seen] = mask[v[seen].astype(np.intp), u[seen].astype(np.intp)] > 0
    return result


def outside_count(cameras: Sequence[Camera], masks: Sequence[np.ndarray], X: np.ndarray,
                  skip: np.ndarray | None = None) -> np.ndarray:
    """(N,) int: in how many views each world point ``X`` (N, 3) falls outside the silhouette.

    ``skip`` (N,) int, when given, names for each point one camera not to count (the camera whose
    viewing ray the point lies on: it is on that cone's boundary by construction).
    """
    count = np.zeros(len(X), np.int32)
    for index, (camera, mask) in enumerate(zip(cameras, masks, strict=True)):
        out = ~inside(camera, mask, X)
        if skip is not None:
            out &= skip != index
        count += out
    return count


def box_interval(
    origins: np.ndarray, directions: np.ndarray, volume: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameters ``(t_enter (M,), t_exit (M,))`` where rays ``origins + t directions`` cross the box
    ``volume`` (2, 3), restricted to ``t >= 0``; rays that miss it get ``t_enter > t_exit``.

    The slab method: the intersection of the three coordinate slabs.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = 1.0 / directions  # (M, 3), +-inf for axis-parallel rays
        t_low = (volume[0] - origins) * inverse
        t_high = (volume[1] - origins) * inverse
    t_near = np.minimum(t_low, t_high)
    t_far = np.maximum(t_low, t_high)
    # An axis-parallel ray gives nan (0 * inf) on that axis when it lies on a slab face: no constraint.
    t_near = np.where(np.isnan(t_near), -np.inf, t_near)
    t_far = np.where(np.isnan(t_far), np.inf, t_far)
    return np.maximum(t_near.max(axis=1), 0.0), t_far.min(axis=1)


def in_volume(X: np.ndarray, volume: np.ndarray) -> np.ndarray:
    """(N,) bool: which points ``X`` (N, 3) lie in the box ``volume`` (2, 3)."""
    return np.all((X >= volume[0]) & (X <= volume[1]), axis=1)
