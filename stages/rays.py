"""Where rays cross the working volume, and the point nearest to a set of rays: geometry that the silhouette and
the reconstruction stages and the pipeline's reading of a capture share.

It has a module of its own, outside :mod:`stages.reconstruction`, because the silhouette workers' multi-view
check (:mod:`stages.consistency`) needs it too, and importing the reconstruction package brings scipy along.
"""

from __future__ import annotations

import numpy as np


def box_interval(
    origins: np.ndarray, directions: np.ndarray, volume: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameters ``(t_enter (M,), t_exit (M,))`` where rays ``origins + t directions`` cross the box
    ``volume`` (2, 3), restricted to ``t >= 0``; rays that miss it get ``t_enter > t_exit``.

    ``origins`` is (M, 3), or (3,) for rays from one point. The slab method: the intersection of the
    three coordinate slabs.
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
    # The three slabs column by column: max/min over rows of three are slow reductions, same result.
    return (np.maximum(np.maximum(np.maximum(t_near[:, 0], t_near[:, 1]), t_near[:, 2]), 0.0),
            np.minimum(np.minimum(t_far[:, 0], t_far[:, 1]), t_far[:, 2]))


def nearest_point(origins: np.ndarray, directions: np.ndarray) -> np.ndarray | None:
    """(3,) the point nearest to the lines ``origins + t directions`` (N, 3) in least squares, or None when the
    lines are (nearly) parallel and no one point is nearest.

    Minimises ``sum_i |(I - d_i d_i^T)(p - o_i)|^2`` over p, with ``d_i`` the unit directions.
    """
    directions = np.asarray(directions, dtype=float)
    directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    projectors = np.eye(3) - directions[:, :, None] * directions[:, None, :]  # (N, 3, 3)
    normal = projectors.sum(axis=0)
    if np.linalg.cond(normal) > 1e8:
        return None
    return np.linalg.solve(normal, np.einsum("nij,nj->i", projectors, np.asarray(origins, dtype=float)))
