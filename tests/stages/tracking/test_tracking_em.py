"""EM fit (Horaud et al. 2009, Sec. 3) on data sampled from the model's own ellipsoids."""

import numpy as np
import pytest
from tracking_testing import VOLUME, data_near_a_pose, random_pose, sample_ellipsoids

from stages.tracking.body_file import load_body
from stages.tracking.distances import DISTANCES
from stages.tracking.em import (
    EMParams,
    Mixture,
    e_step,
    fit,
    hypothesis_scores,
    log_evidence,
    m_step,
)
from stages.tracking.geometry import normal_spread
from stages.tracking.mixture import NEGLIGIBLE_POSTERIOR, volume_size


@pytest.fixture(scope="module")
def body():
    return load_body("default")


@pytest.mark.parametrize("distance", ["normals", "points"])
def test_em_recovers_a_known_pose_despite_outliers(body, distance):
    rng = np.random.default_rng(10)
    truth = random_pose(body, rng)
    y, n = sample_ellipsoids(body, truth, 1000, rng, outlier_fraction=0.2)
    start = truth + rng.normal(0.0, 0.03, body.pose_size)
    result = fit(y, n, body, start, VOLUME, EMParams(distance=distance, max_iterations=40))
    error = np.linalg.norm(body.joint_positions(result.pose) - body.joint_positions(truth), axis=1)
    assert result.converged
    assert error.max() < 0.005  # metres
    assert result.outlier_fraction == pytest.approx(0.2, abs=0.03)


def test_log_likelihood_never_decreases(body):
    rng = np.random.default_rng(11)
    truth = random_pose(body, rng)
    y, n = sample_ellipsoids(body, truth, 600, rng, outlier_fraction=0.2)
    result = fit(y, n, body, truth + rng.normal(0.0, 0.05, body.pose_size), VOLUME)
    assert np.all(np.diff(result.log_likelihood) > -1e-6 * abs(result.log_likelihood[-1]))


def test_a_fit_continued_from_its_e_step_is_the_fit_run_on(body):
    rng = np.random.default_rng(21)
    truth = random_pose(body, rng)
    y, n = sample_ellipsoids(body, truth, 400, rng, outlier_fraction=0.1)
    params = EMParams(normal_noise_rad=np.radians(10.0), max_iterations=3, tolerance=0.0, displacement_m=0.0)
    first = fit(y, n, body, truth + rng.normal(0.0, 0.05, body.pose_size), VOLUME, params)
    again = fit(y, n, first.body, first.pose, VOLUME, params, mixture=first.mixture)
    resumed = fit(y, n, first.body, first.pose, VOLUME, params, mixture=first.mixture, start=first.estep)
    # equal up to the pruning, which depends on the order the ellipsoids are visited in (`EStep.best`)
    np.testing.assert_allclose(resumed.pose, again.pose, rtol=0, atol=1e-9)
    np.testing.assert_allclose(resumed.log_likelihood, again.log_likelihood, rtol=1e-9)


def test_e_step_posteriors_sum_to_one(body):
    rng = np.random.default_rng(12)
    pose = random_pose(body, rng)
    y, n = sample_ellipsoids(body, pose, 200, rng, outlier_fraction=0.2)
    mixture = Mixture.initial(body.n_ellipsoids, 0.02)
    estep = e_step(y, n, body.ellipsoids(pose), mixture, volume_size(VOLUME))
    np.testing.assert_allclose(estep.t.sum(axis=1) + estep.t_outlier, 1.0, atol=1e-12)
    # far-away data (the outliers are the last 50) are outliers
    assert np.median(estep.t_outlier[-50:]) > 0.99 and np.median(estep.t_outlier[:150]) < 0.01


def test_m_step_priors_sum_to_one_and_covariance_is_positive(body):
    rng = np.random.default_rng(13)
    pose = random_pose(body, rng)
    y, n = sample_ellipsoids(body, pose, 200, rng, outlier_fraction=0.2)
    mixture = Mixture.initial(body.n_ellipsoids, 0.02)
    estep = e_step(y, n, body.ellipsoids(pose), mixture, volume_size(VOLUME))
    mstep = m_step(y, n, body, body.fk(pose), pose, mixture, estep)
    assert mstep.mixture.pi.sum() == pytest.approx(1.0)
    assert np.all(np.linalg.eigvalsh(mstep.mixture.Sigma) > 0)


def test_fit_without_data_keeps_the_pose_and_stays_finite(body):
    pose = body.zero_pose()
    result = fit(np.zeros((0, 3)), np.zeros((0, 3)), body, pose, VOLUME)
    np.testing.assert_array_equal(result.pose, pose)
    assert result.iterations == 0 and np.isfinite(result.log_likelihood).all()


def test_fit_on_a_single_datum_stays_finite(body):
    result = fit(np.array([[0.0, 0.0, 1.0]]), np.array([[0.0, 1.0, 0.0]]), body, body.zero_pose(), VOLUME)
    assert np.all(np.isfinite(result.pose)) and np.all(np.isfinite(result.mixture.Sigma))


def test_bad_volume_is_rejected():
    with pytest.raises(ValueError, match="volume"):
        volume_size(np.array([[0.0, 0.0, 0.0], [1.0, -1.0, 1.0]]))


def test_em_estimates_the_body_height(body):
    rng = np.random.default_rng(14)
    truth = random_pose(body, rng, scale=0.2)
    tall = body.scaled(1.85)
    y, n = sample_ellipsoids(tall, truth, 1000, rng, outlier_fraction=0.2)
    result = fit(y, n, body.scaled(1.70), truth, VOLUME, EMParams(estimate_scale=True, max_iterations=40))
    assert result.height_m == pytest.approx(1.85, abs=0.01)


def test_em_estimates_segment_length_factors(body):
    rng = np.random.default_rng(15)
    truth = random_pose(body, rng, scale=0.3)
    factors = np.ones(len(body.length_groups))
    for name, value in [("thigh", 1.08), ("upperarm", 0.92), ("trunk", 1.05)]:
        factors[body.length_groups.index(name)] = value
    y, n = sample_ellipsoids(body.with_lengths(factors), truth, 1500, rng, outlier_fraction=0.2)
    result = fit(y, n, body, truth, VOLUME, EMParams(estimate_lengths=True, max_iterations=40))
    # the prior towards 1 (LENGTH_PRIOR_SD) shrinks the estimates only slightly with this much data
    np.testing.assert_allclose(result.body.length_factors, factors, atol=0.015)


def _tilted(n, degrees, rng):
    """Unit normals each tilted by |N(0, degrees)| about a random perpendicular axis."""
    axis = np.cross(n, rng.normal(size=n.shape))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.radians(np.abs(rng.normal(0.0, degrees, len(n))))[:, None]
    return n * np.cos(angle) + np.cross(axis, n) * np.sin(angle)


def test_normal_noise_covariance_beats_plain_eq4_on_noisy_normals(body):
    rng = np.random.default_rng(12)
    errors = {0.0: [], 15.0: []}
    for _ in range(3):
        truth = random_pose(body, rng)
        y, n = sample_ellipsoids(body, truth, 800, rng, outlier_fraction=0.1)
        n = _tilted(n, 15.0, rng)
        start = truth + rng.normal(0.0, 0.03, body.pose_size)
        for deg in errors:
            result = fit(y, n, body, start, VOLUME, EMParams(max_iterations=30, normal_noise_rad=np.radians(deg)))
            errors[deg].append(np.linalg.norm(body.joint_positions(result.pose) - body.joint_positions(truth),
                                              axis=1).mean())
    assert np.mean(errors[15.0]) < 0.8 * np.mean(errors[0.0])


def test_m_step_keeps_outlier_prior_and_bounds_sigma(body):
    rng = np.random.default_rng(13)
    pose = random_pose(body, rng)
    y, n = sample_ellipsoids(body, pose, 500, rng)  # no outliers: the plain M-step drives π_{P+1} to ~0
    mixture = Mixture.initial(body.n_ellipsoids, 0.2)
    estep = e_step(y, n, body.ellipsoids(pose), mixture, volume_size(VOLUME))
    mstep = m_step(y, n, body, body.fk(pose), pose, mixture, estep, EMParams(min_outlier_prior=0.05, max_sigma_m=0.03))
    assert mstep.mixture.pi[-1] == pytest.approx(0.05)
    assert mstep.mixture.pi.sum() == pytest.approx(1.0)
    assert np.linalg.eigvalsh(mstep.mixture.Sigma).max() <= 0.03**2 * (1 + 1e-9)


def log_gaussian(e, Sigma):
    """ln N(e | 0, Σ) for residuals e (..., k), Σ (k, k) or one (..., k, k) per residual, by LAPACK."""
    Sigma = np.broadcast_to(Sigma, e.shape + e.shape[-1:])
    mahalanobis = (e * np.linalg.solve(Sigma, e[..., None])[..., 0]).sum(-1)
    return -0.5 * (mahalanobis + np.linalg.slogdet(Sigma)[1] + e.shape[-1] * np.log(2.0 * np.pi))


@pytest.mark.parametrize(("distance", "noise_deg", "sigma_m"), [
    ("normals", 10.0, 0.03), ("normals", 10.0, 0.01), ("normals", 0.0, 0.02), ("points", 0.0, 0.02)])
def test_pruned_e_step_equals_the_dense_one(body, distance, noise_deg, sigma_m):
    rng = np.random.default_rng(16)
    truth = random_pose(body, rng)
    y, n = sample_ellipsoids(body, truth, 600, rng, outlier_fraction=0.2)
    pose = truth + rng.normal(0.0, 0.03, body.pose_size)  # data a little off the model, as between iterations
    mixture = Mixture(Sigma=np.diag([1.0, 1.5, 0.7]) * sigma_m**2, pi=rng.dirichlet(np.ones(body.n_ellipsoids + 1)))
    V, sigma_n = volume_size(VOLUME), np.radians(noise_deg)
    ell = body.ellipsoids(pose)
    Sigma = mixture.Sigma + (sigma_n**2 * normal_spread(n, ell) if distance == "normals" else 0.0)
    log_joint = np.c_[np.log(mixture.pi[:-1]) + log_gaussian(DISTANCES[distance].all_residuals(y, n, ell), Sigma),
                      np.full(len(y), np.log(mixture.pi[-1] / V))]  # eq. (13) on every pair
    evidence = np.logaddexp.reduce(log_joint, axis=1)
    dense = np.exp(log_joint - evidence[:, None])
    estep = e_step(y, n, body.ellipsoids(pose), mixture, V, EMParams(distance=distance, normal_noise_rad=sigma_n))
    bound = body.n_ellipsoids * NEGLIGIBLE_POSTERIOR  # what skipping may change, relative
    np.testing.assert_allclose(estep.t, dense[:, :-1], rtol=0, atol=bound)
    np.testing.assert_allclose(estep.t_outlier, dense[:, -1], rtol=0, atol=bound)
    assert estep.log_likelihood == pytest.approx(evidence.sum(), abs=len(y) * bound)
    assert np.mean(estep.t == 0.0) > 0.5  # most pairs were skipped




@pytest.mark.parametrize("distance", ["normals", "points"])
def test_log_evidence_adds_up_over_ellipsoids(body, distance):
    y, n, pose, rng = data_near_a_pose(body, 18, 300, spread=0.03)
    mixture = Mixture(Sigma=np.diag([1.0, 1.5, 0.7]) * 0.02**2, pi=rng.dirichlet(np.ones(body.n_ellipsoids + 1)))
    V, sigma_n, ell = volume_size(VOLUME), np.radians(10.0), body.ellipsoids(pose)
    whole = log_evidence(y, n, ell, mixture, V, distance=distance, normal_noise_rad=sigma_n)
    estep = e_step(y, n, body.ellipsoids(pose), mixture, V, EMParams(distance=distance, normal_noise_rad=sigma_n))
    assert whole.sum() == pytest.approx(estep.log_likelihood, rel=1e-12)
    limb = np.flatnonzero(np.isin(body.ellipsoid_segment, [1, 2, 3]))
    rest = log_evidence(y, n, ell, mixture, V, which=np.setdiff1d(np.arange(body.n_ellipsoids), limb),
                        distance=distance, normal_noise_rad=sigma_n)
    added = log_evidence(y, n, ell, mixture, V, which=limb, base=rest, distance=distance, normal_noise_rad=sigma_n)
    np.testing.assert_allclose(added, whole, rtol=0, atol=body.n_ellipsoids * NEGLIGIBLE_POSTERIOR)


@pytest.mark.parametrize("distance", ["normals", "points"])
def test_hypothesis_scores_sum_log_evidence_per_block(body, distance):
    y, n, pose, rng = data_near_a_pose(body, 19, 200)
    mixture = Mixture.initial(body.n_ellipsoids, 0.03)
    V, sigma_n = volume_size(VOLUME), np.radians(10.0)
    poses = pose + rng.normal(0.0, 0.05, (4, body.pose_size))
    blocks = np.array([0, 50, 120, len(y)])
    scores = hypothesis_scores(y, n, body.posed_ellipsoids(poses), mixture, V, blocks=blocks, distance=distance,
                               normal_noise_rad=sigma_n)
    expected = [[log_evidence(y, n, body.ellipsoids(q), mixture, V, distance=distance,
                              normal_noise_rad=sigma_n)[a:b].sum()
                 for a, b in zip(blocks[:-1], blocks[1:], strict=True)] for q in poses]
    np.testing.assert_allclose(scores, expected, rtol=1e-12)


def test_e_step_weights_whiten_each_pair_by_its_posterior_and_covariance(body):
    y, n, pose, rng = data_near_a_pose(body, 20, 300, spread=0.03)
    mixture = Mixture(Sigma=np.diag([1.0, 1.5, 0.7]) * 0.02**2, pi=rng.dirichlet(np.ones(body.n_ellipsoids + 1)))
    sigma_n = np.radians(10.0)
    estep = e_step(y, n, body.ellipsoids(pose), mixture, volume_size(VOLUME), EMParams(normal_noise_rad=sigma_n))
    i, p = estep.pairs
    assert np.all(np.diff(p) >= 0) and np.all(estep.t[i, p] > 1e-3)
    covariance = mixture.Sigma + sigma_n**2 * normal_spread(n[i], body.ellipsoids(pose), p)
    expected = estep.t[i, p][:, None, None] * np.linalg.inv(covariance)
    np.testing.assert_allclose(estep.weights @ estep.weights.transpose(0, 2, 1), expected, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("distance", ["normals", "points", "algebraic"])
def test_a_fit_with_no_datum_near_the_body_keeps_going_while_estimating_lengths(body, distance):
    """Every datum an outlier (the prediction far from the subject): no pair enters the M-step, and the
    normal equations and the size and length columns, summed per ellipsoid over the pairs, must not
    fail on none."""
    rng = np.random.default_rng(25)
    pose = random_pose(body, rng)
    y, n = sample_ellipsoids(body, pose, 300, rng)
    free = body.with_length_groups(("upperarm", "shank"))
    far = pose.copy()
    far[0] += 1.5  # metres
    result = fit(y, n, free, far, VOLUME, EMParams(distance=distance, normal_noise_rad=np.radians(10.0),
                                                   estimate_scale=True, estimate_lengths=True, max_iterations=3))
    assert np.all(np.isfinite(result.pose)) and np.all(np.isfinite(result.mixture.Sigma))
    assert result.outlier_fraction > 0.9


def test_screened_scores_score_in_full_only_the_hypotheses_best_on_the_first_rows():
    """Survivors get their sums over every row, the others −inf; with nothing to screen out, every score is full."""
    from stages.tracking.em import screened_scores

    rng = np.random.default_rng(5)
    terms = rng.normal(size=(20, 3, 50))  # hypotheses x headings x rows
    calls = []

    def score(chosen, rows):
        calls.append((len(chosen), rows.stop - rows.start))
        return terms[chosen][:, :, rows].sum(axis=2)

    screened = screened_scores(score, 20, 50, 10, 4)
    survivors = np.argsort(-terms[:, :, :10].sum(axis=2).max(axis=1))[:4]
    assert calls == [(20, 10), (4, 40)]
    np.testing.assert_allclose(screened[np.sort(survivors)], terms[np.sort(survivors)].sum(axis=2))
    assert np.isinf(np.delete(screened, survivors, axis=0)).all()
    calls.clear()
    np.testing.assert_allclose(screened_scores(score, 20, 50, 10, 20), terms.sum(axis=2))
    assert calls == [(20, 50)]
