"""Per-pair quantities of `distances` against their dense definitions."""

import numpy as np
import pytest
from tracking_testing import random_pose, sample_ellipsoids

from stages.tracking.body import load_body
from stages.tracking.distances import (
    all_residuals,
    normal_spread,
    normal_spread_entries,
    residual_bounds,
    symmetric_matrices,
)


@pytest.fixture(scope="module")
def data():
    body = load_body("default")
    rng = np.random.default_rng(20)
    truth = random_pose(body, rng)
    y, n = sample_ellipsoids(body, truth, 300, rng, outlier_fraction=0.2)
    return y, n, body.ellipsoids(truth + rng.normal(0.0, 0.05, body.pose_size))


def test_residual_bounds_are_exact_for_the_normals_distance(data):
    y, n, ell = data
    e = all_residuals(y, n, ell).transpose(1, 0, 2)  # (P,I,3)
    norm, along, spread = residual_bounds(y, n, ell)
    np.testing.assert_allclose(norm, np.linalg.norm(e, axis=2), atol=1e-12)
    np.testing.assert_allclose(along, np.abs(np.einsum("pia,ia->pi", e, n)), atol=1e-12)
    np.testing.assert_allclose(spread, np.linalg.eigvalsh(normal_spread(n, ell))[..., -1].T, rtol=1e-9, atol=1e-12)


def test_residual_bounds_bound_the_points_distance(data):
    y, n, ell = data
    norm, along, spread = residual_bounds(y, n, ell, distance="points")
    assert np.all(norm <= np.linalg.norm(all_residuals(y, n, ell, distance="points"), axis=2).T + 1e-12)
    assert not along.any() and not spread.any()


def test_pair_spread_matches_the_dense_one(data):
    y, n, ell = data
    rng = np.random.default_rng(21)
    i, p = rng.integers(0, len(y), 200), rng.integers(0, len(ell.t), 200)
    dense = normal_spread(n, ell)[i, p]
    np.testing.assert_allclose(normal_spread(n[i], ell, p), dense, atol=1e-14)
    np.testing.assert_allclose(symmetric_matrices(normal_spread_entries(n[i], ell, p)), dense, atol=1e-14)
