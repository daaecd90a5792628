"""Per-pair quantities of `distances` against their dense definitions."""

import numpy as np
import pytest
from tracking_testing import data_near_a_pose

from stages.tracking.body_file import load_body
from stages.tracking.distances import DISTANCES
from stages.tracking.geometry import normal_spread, normal_spread_entries, symmetric_matrices


@pytest.fixture(scope="module")
def data():
    body = load_body("default")
    y, n, pose, _ = data_near_a_pose(body, 20, 300)
    return y, n, body.ellipsoids(pose)


@pytest.mark.parametrize("distance", ["normals", "points"])
def test_residual_lower_bound_bounds_the_point_distances(data, distance):
    y, n, ell = data
    bound = DISTANCES[distance].lower_bound(y, ell)
    exact = (DISTANCES[distance].all_residuals(y, n, ell) ** 2).sum(2).T
    assert np.all(bound <= exact + 1e-12) and bound.any()


def test_normal_spread_is_bounded_by_the_largest_radius_of_curvature(data):
    _, n, ell = data
    largest = np.linalg.eigvalsh(normal_spread(n, ell))[..., -1]  # ‖A‖² (I, P)
    radius = ell.semi_axes.max(axis=1) ** 2 / ell.semi_axes.min(axis=1)
    assert np.all(largest <= radius**2 * (1 + 1e-9))
    assert np.any(largest >= 0.5 * radius**2)  # and the bound is not loose everywhere


def test_pair_spread_matches_the_dense_one(data):
    y, n, ell = data
    rng = np.random.default_rng(21)
    i, p = rng.integers(0, len(y), 200), rng.integers(0, len(ell.t), 200)
    dense = normal_spread(n, ell)[i, p]
    np.testing.assert_allclose(normal_spread(n[i], ell, p), dense, atol=1e-14)
    np.testing.assert_allclose(symmetric_matrices(normal_spread_entries(n[i], ell, p)), dense, atol=1e-14)
