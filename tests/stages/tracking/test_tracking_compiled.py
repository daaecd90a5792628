"""The compiled inner loops of EM against the numpy reference of `distances`."""

import numpy as np
import pytest
from tracking_testing import data_near_a_pose, random_pose

from stages.tracking import compiled
from stages.tracking.body_file import load_body
from stages.tracking.distances import NormalsDistance
from stages.tracking.geometry import normal_spread, shape_matrices


@pytest.fixture(scope="module")
def pairs():
    body = load_body("default")
    y, n, pose, rng = data_near_a_pose(body, 30, 200)
    kin = body.fk(pose)
    p = np.sort(rng.integers(0, body.n_ellipsoids, 500))  # sorted by ellipsoid, as EM keeps them
    i = rng.integers(0, len(y), 500)
    return y, n, i, p, kin, body.ellipsoids(kin), rng


def test_residuals_match_the_reference(pairs):
    y, n, i, p, kin, ell, _ = pairs
    expected = NormalsDistance().residuals(y, n, i, p, kin, ell).e
    np.testing.assert_allclose(compiled.residuals(y, n, i, p, ell.t, shape_matrices(ell, 2.0)), expected, atol=1e-14)


def test_normal_equations_match_the_reference(pairs):
    y, n, i, p, kin, ell, rng = pairs
    L = np.tril(rng.normal(size=(len(i), 3, 3))) + 3.0 * np.eye(3)  # any lower-triangular weights
    e, r, Bw, H, g, e_scale, norm2 = compiled.normal_equations(y, n, i, p, L, ell.t, shape_matrices(ell, 2.0),
                                                               kin.t[0])
    assert norm2 == compiled.whitened_norm2(L, e)  # the same sum in the same order: the step's cost is unchanged
    ref = NormalsDistance().residuals(y, n, i, p, kin, ell, jacobian=True, scale=True)
    Lt = L.transpose(0, 2, 1)
    np.testing.assert_allclose(e, ref.e, atol=1e-14)
    np.testing.assert_allclose(e_scale, ref.J_scale, atol=1e-14)
    np.testing.assert_allclose(r, (Lt @ ref.e[:, :, None])[:, :, 0], atol=1e-12)
    np.testing.assert_allclose(Bw, Lt @ ref.B, atol=1e-12)
    for q in range(len(ell.t)):
        block = Bw[p == q].reshape(-1, 6)
        np.testing.assert_allclose(H[q], block.T @ block, atol=1e-10)
        np.testing.assert_allclose(g[q], block.T @ r[p == q].reshape(-1), atol=1e-10)


@pytest.mark.parametrize("k", [1, 3])
def test_extra_normal_equations_match_the_products_they_sum(pairs, k):
    _, _, i, p, _, ell, rng = pairs
    L = np.tril(rng.normal(size=(len(i), k, k))) + 3.0 * np.eye(k)
    X = rng.normal(size=(len(i), k, 4))  # four further unknowns' columns de/dx
    Bw, r = rng.normal(size=(len(i), k, 6)), rng.normal(size=(len(i), k))
    HX, XX, gX = compiled.extra_normal_equations(L, X, Bw, r, p, len(ell.t))
    Xw = L.transpose(0, 2, 1) @ X  # Wᵀ X
    for q in range(len(ell.t)):
        np.testing.assert_allclose(HX[q], np.einsum("kai,kax->ix", Bw[p == q], Xw[p == q]), atol=1e-10)
    np.testing.assert_allclose(XX, np.einsum("kax,kay->xy", Xw, Xw), rtol=1e-12)
    np.testing.assert_allclose(gX, np.einsum("kax,ka->x", Xw, r), rtol=1e-12)


def _noisy_covariance_terms(pairs):
    _, n, i, p, _, ell, rng = pairs
    sigma_n = np.radians(10.0)
    e = rng.normal(0.0, 0.015, (len(i), 3))  # residuals of a few centimetres
    w = rng.uniform(0.05, 1.0, len(i))
    spread = sigma_n**2 * normal_spread(n[i], ell, p)  # σ_n² A_k² (K, 3, 3)
    return n, i, p, ell, e, w, sigma_n**2, spread


def _Q(Sigma, e, w, spread):
    """Σ_k w_k ln N(e_k | 0, Σ + σ_n² A_k²), the objective the noisy covariance maximises."""
    C = Sigma + spread
    quadratic = np.einsum("ka,ka->k", e, np.linalg.solve(C, e[:, :, None])[:, :, 0])
    return float(np.sum(-0.5 * w * (quadratic + np.linalg.slogdet(C)[1] + 3.0 * np.log(2.0 * np.pi))))


def test_noisy_covariance_is_the_em_update_of_the_reference(pairs):
    n, i, p, ell, e, w, noise2, spread = _noisy_covariance_terms(pairs)
    Sigma = np.diag([0.02, 0.03, 0.025]) ** 2
    inverse = np.linalg.inv(Sigma + spread)  # Σ_k⁻¹
    S1 = np.einsum("k,kab->ab", w, inverse)
    v = np.einsum("kab,kb->ka", inverse, e)
    S2 = np.einsum("k,ka,kb->ab", w, v, v)
    expected = Sigma + Sigma @ ((S2 - S1) / w.sum()) @ Sigma
    once = compiled.noisy_covariance(n, i, p, e, w, shape_matrices(ell, 2.0), shape_matrices(ell, 4.0), noise2,
                                     Sigma, 1)
    np.testing.assert_allclose(once, expected, rtol=1e-10, atol=1e-16)


def test_noisy_covariance_never_lowers_its_objective(pairs):
    n, i, p, ell, e, w, noise2, spread = _noisy_covariance_terms(pairs)
    M, M2 = shape_matrices(ell, 2.0), shape_matrices(ell, 4.0)
    Sigma = np.diag([0.06, 0.05, 0.04]) ** 2  # far too wide, as at an initialisation
    scores = [_Q(Sigma, e, w, spread)]
    for _ in range(6):
        Sigma = compiled.noisy_covariance(n, i, p, e, w, M, M2, noise2, Sigma, 1)
        scores.append(_Q(Sigma, e, w, spread))
    assert np.all(np.diff(scores) >= -1e-9 * abs(scores[0]))
    assert np.all(np.linalg.eigvalsh(Sigma) > 0.0)
    # the moment estimate, which EM replaced, does worse by this objective on such data
    moment = (np.einsum("k,ka,kb->ab", w, e, e) - np.einsum("k,kab->ab", w, spread)) / w.sum()
    values, vectors = np.linalg.eigh(moment)
    moment = (vectors * np.maximum(values, 0.004**2)) @ vectors.T  # floored, as the M-step bounds Σ
    assert _Q(Sigma, e, w, spread) > _Q(moment, e, w, spread)


def test_pose_normal_equations_match_the_segment_twists():
    body = load_body("default")
    rng = np.random.default_rng(31)
    kin = body.fk(random_pose(body, rng))
    A = rng.normal(size=(body.n_ellipsoids, 6, 6))
    H6, g6 = A @ A.transpose(0, 2, 1), rng.normal(size=(body.n_ellipsoids, 6))
    H, g = compiled.pose_normal_equations(H6, g6, body.ellipsoid_segment, body.moves, kin.axis, kin.origin,
                                          body.dof_revolute)
    T = body.segment_twists(kin)[body.ellipsoid_segment]  # (P, 6, D)
    np.testing.assert_allclose(H, np.einsum("pjd,pjk,pke->de", T, H6, T), atol=1e-10)
    np.testing.assert_allclose(g, np.einsum("pjd,pj->d", T, g6), atol=1e-12)


def test_whitened_norm_is_the_weighted_sum_of_squares(pairs):
    *_, rng = pairs
    W, e = np.tril(rng.normal(size=(50, 3, 3))), rng.normal(size=(50, 3))
    assert compiled.whitened_norm2(W, e) == pytest.approx(np.einsum("ka,kab,kcb,kc->", e, W, W, e), rel=1e-12)


def test_shapes_match_the_reference(pairs):
    *_, ell, _ = pairs
    M, M2 = compiled.shapes(ell.R, ell.semi_axes)
    np.testing.assert_allclose(M, shape_matrices(ell, 2.0), atol=1e-15)
    np.testing.assert_allclose(M2, shape_matrices(ell, 4.0), atol=1e-15)


@pytest.mark.parametrize("seed", range(5))
def test_pruning_bounds_use_sigmas_largest_eigenvalue(seed):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(3, 3)) * 0.02
    Sigma = A @ A.T + (np.eye(3) * 1e-4 if seed else 0.0)  # the first one singular-ish, others generic
    Sigma = np.diag([4e-4, 4e-4, 4e-4]) if seed == 4 else Sigma  # and an isotropic one
    semi = rng.uniform(0.05, 0.3, (4, 3))
    reach, largest = compiled._bounds(semi, Sigma, np.log(np.full(4, 0.2)), np.log(1e-9), 0.03)
    assert largest == pytest.approx(np.linalg.eigvalsh(Sigma)[-1], rel=1e-9)
    np.testing.assert_allclose(reach[:, 2], largest + 0.03 * (semi.max(1) ** 2 / semi.min(1)) ** 2, rtol=1e-12)


def test_length_columns_match_the_reference(pairs):
    y, n, i, p, kin, ell, rng = pairs
    body = load_body("default")
    body = body.with_lengths(np.exp(rng.normal(0.0, 0.1, len(body.length_groups))))
    pose = random_pose(body, rng)
    kin = body.fk(pose)
    e = NormalsDistance().pair_residuals(y, n, i, p, kin, kin.ellipsoids)
    expected = NormalsDistance().length_jacobian(y, n, i, p, body, kin, pose, e)
    dt, dM = body.length_derivatives(kin)
    np.testing.assert_allclose(compiled.length_columns(n, i, p, shape_matrices(kin.ellipsoids, 2.0), dt, dM),
                               expected, atol=1e-12)
