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


def test_residual_bounds_are_exact_or_bounds_for_the_normals_distance(data):
    y, n, ell = data
    e = all_residuals(y, n, ell).transpose(1, 0, 2)  # (P,I,3)
    norm2, along2, spread = residual_bounds(y, n, ell)
    np.testing.assert_allclose(norm2, (e * e).sum(2), atol=1e-12)
    np.testing.assert_allclose(along2, np.einsum("pia,ia->pi", e, n) ** 2, atol=1e-12)
    largest = np.linalg.eigvalsh(normal_spread(n, ell))[..., -1].T  # ‖A‖²
    assert np.all(spread >= largest * (1 - 1e-9)) and np.all(spread <= 2.0 * largest * (1 + 1e-9))


def test_residual_bounds_bound_the_points_distance(data):
    y, n, ell = data
    norm2, along2, spread = residual_bounds(y, n, ell, distance="points")
    assert np.all(norm2 <= (all_residuals(y, n, ell, distance="points") ** 2).sum(2).T + 1e-12)
    assert not along2.any() and not spread.any()


def test_pair_spread_matches_the_dense_one(data):
    y, n, ell = data
    rng = np.random.default_rng(21)
    i, p = rng.integers(0, len(y), 200), rng.integers(0, len(ell.t), 200)
    dense = normal_spread(n, ell)[i, p]
    np.testing.assert_allclose(normal_spread(n[i], ell, p), dense, atol=1e-14)
    np.testing.assert_allclose(symmetric_matrices(normal_spread_entries(n[i], ell, p)), dense, atol=1e-14)
