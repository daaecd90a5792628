"""Per-pair quantities of `distances` against their dense definitions."""

import numpy as np
import pytest
from tracking_testing import data_near_a_pose, random_pose

from stages.tracking.body_file import load_body
from stages.tracking.distances import DISTANCES, CompiledNormals, Distance, NormalsDistance
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


def test_closed_form_length_jacobian_is_the_differenced_one(data):
    """The paper's distance differentiates its residuals by the length factors in closed form; every distance
    can difference them (`Distance.length_jacobian`), and the two agree to the differences' own error."""
    y, n, *_ = data
    rng = np.random.default_rng(8)
    body = load_body("default")
    body = body.with_lengths(np.exp(rng.normal(0.0, 0.1, len(body.length_groups))))
    pose = random_pose(body, rng)
    kin = body.fk(pose)
    p = np.sort(rng.integers(0, body.n_ellipsoids, 400))
    i = rng.integers(0, len(y), 400)
    for distance in (NormalsDistance(), CompiledNormals()):
        e = distance.pair_residuals(y, n, i, p, kin, kin.ellipsoids)
        closed = distance.length_jacobian(y, n, i, p, body, kin, pose, e)
        differenced = Distance.length_jacobian(distance, y, n, i, p, body, kin, pose, e)
        assert closed.shape == (len(i), 3, len(body.length_groups))
        np.testing.assert_allclose(closed, differenced, atol=1e-5 * np.abs(differenced).max())
