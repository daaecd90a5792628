"""Where rays cross the working volume: geometry that both the silhouette and the reconstruction stages use.

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
