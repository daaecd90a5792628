"""Robust fit of the articulated body to points and normals by EM (Horaud et al. 2009, Sec. 3).

The data are explained by a mixture of P Gaussian components, one per ellipsoid, centred on the
ellipsoid points x_ip(Λ) (eq. 4) with one covariance Σ shared by all (so that ellipsoids without data
cannot collapse), plus a uniform outlier component 1/V over the working volume (eqs. 9-11):

    P(y_i | n_i) = Σ_p π_p N(y_i | x_ip(Λ), Σ) + π_{P+1} / V.

`e_step` computes the posteriors t_ip (eq. 13) and the log-likelihood (eq. 12); `m_step` decreases the
expected complete-data negative log-likelihood (eq. 14) over the pose Λ by a damped Gauss-Newton
(Levenberg-Marquardt) step with the analytic Jacobians of `distances`, then updates Σ and π with the
paper's formulas (a generalised EM: one step per M-step is enough for the likelihood to grow). `fit`
owns the loop and stops when the likelihood gain or the joints' motion becomes negligible. Besides the
pose, an M-step may estimate the body's overall size and its segment-length factors (with a prior
towards the configured proportions). The names follow the paper: y, n, x, Σ (`Sigma`), π (`pi`),
t_ip (`t`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import logsumexp

from stages.tracking import compiled
from stages.tracking.body import BodyModel, Ellipsoids, Kinematics
from stages.tracking.distances import (
    DISTANCES,
    all_residuals,
    residual_lower_bound,
    residual_size,
    residuals,
)

# Σ is estimated from the residuals; with nearly exact data it would shrink towards 0 and the
# posteriors would turn into hard, brittle assignments. The floor is the model's own inexactness
# (ellipsoids are not a body surface): a few millimetres.
SIGMA_FLOOR_M = 0.004
# π_p of an ellipsoid that currently gets no data (occluded, or just out of reach) must not reach 0,
# or that ellipsoid could never attract data again.
PI_FLOOR = 1e-4
# EM updates of Σ per M-step under normal noise (`_noisy_covariance`).
NOISY_COVARIANCE_ITERATIONS = 5
# Posteriors below this do not change the weighted least squares measurably; dropping those pairs
# from the M-step is what makes it fast (each datum keeps a handful of ellipsoids).
PRUNE_POSTERIOR = 1e-3
# The E-step skips a pair whose joint density π_p N(y_i | x_ip, Σ_ip) is provably below this fraction of
# the largest term of the datum's evidence (`_e_step`): its posterior is below it too, every other
# posterior changes by less than P times it (relative), and ln P(Y | Λ) by less than I·P times it. An
# order below PRUNE_POSTERIOR: a skipped pair would not have entered the M-step anyway, and a smaller
# fraction only costs time (the joints do not change).
NEGLIGIBLE_POSTERIOR = 1e-4
# Prior strength: a DOF with prior weight 1 is held to its predicted value with this standard
# deviation (radians) when the data say nothing about it; data dominate it whenever they see it.
PRIOR_SIGMA_RAD = 0.25
# Length factors a segment may take (people, not caricatures).
LENGTH_RANGE = (0.75, 1.33)
# Forward-difference step on ln ℓ for de/d ln ℓ: the stretch acts on ellipsoid shapes, where an
# analytic derivative would be per distance; residuals are smooth in ℓ, so 1e-5 loses < 1e-5 relative.
LENGTH_STEP = 1e-5
# Levenberg-Marquardt: initial damping (relative to the diagonal), growth on a rejected step, and
# the number of tries before the M-step keeps the current pose (a GEM step never increases eq. 14).
LM_DAMPING = 1e-3
LM_GROWTH = 10.0
LM_TRIES = 4
# Heights (metres) an estimated body may take: people, not dolls or giants; keeps a scale step on
# poor data from running away.
HEIGHT_RANGE_M = (1.2, 2.2)
# A tiny ridge keeps the normal equations solvable when a DOF has no data and no prior.
RIDGE = 1e-9


@dataclass(frozen=True)
class EMParams:
    """Tunables of one EM fit.

    Attributes
    ----------
    distance : {"normals", "points", "algebraic"}
        Datum-to-ellipsoid distance (see `distances`).
    max_iterations : int
        EM iterations at most.
    tolerance : float
        Stop when the log-likelihood gain per observation falls below this (nats).
    displacement_m : float
        Stop when no joint centre moved more than this in the last iteration (metres).
    gauss_newton_steps : int
        Damped Gauss-Newton steps per M-step (1 is a generalised EM step).
    estimate_scale : bool
        Also estimate the body's overall size (standing height) with the pose.
    estimate_lengths : bool
        Also estimate the body's segment-length factors with the pose.
    normal_noise_rad : float
        Angular noise σ_n of the observed normals (radians), for the "normals" distance: each pair's
        covariance is Σ_ip = Σ + σ_n² A_ip A_ipᵀ with A_ip = ∂x_ip/∂n_i (`distances.normal_spread`);
        0 is the paper's model (Σ_ip = Σ).
    min_outlier_prior : float
        Lower bound on the outlier prior π_{P+1}. Without it the outlier class can die out (π_{P+1} → 0)
        and Σ then grows to absorb the visual hull's phantom volumes; robust point-set registration
        keeps a fixed outlier weight for the same reason. 0 is the paper's model.
    max_sigma_m : float
        Upper bound on the standard deviation along every axis of Σ, metres: Σ is the model's
        inexactness (ellipsoids are not a body surface), not the spread of phantom volumes.
    """

    distance: str = "normals"
    max_iterations: int = 20
    tolerance: float = 1e-3
    displacement_m: float = 0.0
    gauss_newton_steps: int = 1
    estimate_scale: bool = False
    estimate_lengths: bool = False
    normal_noise_rad: float = 0.0
    min_outlier_prior: float = 0.0
    max_sigma_m: float = np.inf


@dataclass(frozen=True)
class Mixture:
    """The mixture's non-kinematic parameters.

    Attributes
    ----------
    Sigma : (k, k) float
        Covariance Σ common to all Gaussian components, m².
    pi : (P + 1,) float
        Priors π_1..π_P of the ellipsoids and π_{P+1} of the outlier class; they sum to 1.
    """

    Sigma: np.ndarray
    pi: np.ndarray

    @staticmethod
    def initial(n_ellipsoids: int, sigma_m: float, k: int = 3) -> Mixture:
        """Σ = σ² I and equal priors 1/(P+1), the paper's initialisation (Sec. 3, step 1)."""
        return Mixture(Sigma=np.eye(k) * sigma_m**2, pi=np.full(n_ellipsoids + 1, 1.0 / (n_ellipsoids + 1)))


@dataclass(frozen=True)
class EStep:
    """Posteriors and likelihood at one pose.

    Attributes
    ----------
    t : (I, P) float
        Posterior t_ip that datum i belongs to ellipsoid p (eq. 13).
    t_outlier : (I,) float
        Posterior of the outlier class, t_{i,P+1}.
    log_likelihood : float
        ln P(Y | Λ) of eq. (12), nats.
    pairs : (2, K) int
        Datum i and ellipsoid p of the pairs with t_ip > PRUNE_POSTERIOR (those the M-step uses),
        sorted by ellipsoid.
    weights : (K, k, k) float
        Lower-triangular W_ip with t_ip Σ_ip⁻¹ = W Wᵀ at the E-step's pose and Σ: the whitening of those
        pairs in the M-step of the same iteration (eq. 14's term is ½ |Wᵀ e|²).
    best : (I,) int
        Each datum's ellipsoid of largest posterior (where the next iteration's E-step starts).
    """

    t: np.ndarray
    t_outlier: np.ndarray
    log_likelihood: float
    pairs: np.ndarray
    weights: np.ndarray
    best: np.ndarray


@dataclass(frozen=True)
class MStep:
    """New parameters from one M-step: pose Λ (D,), mixture (Σ, π) and the body (its size and lengths)."""

    pose: np.ndarray
    mixture: Mixture
    body: BodyModel


@dataclass(frozen=True)
class FitResult:
    """Outcome of `fit`.

    Attributes
    ----------
    pose : (D,) float
        Estimated pose Λ.
    body : BodyModel
        The fitted body (the starting body unless its size or segment lengths were estimated).
    mixture : Mixture
        Final Σ and π.
    iterations : int
        EM iterations run.
    converged : bool
        The log-likelihood gain or the joints' motion fell below its tolerance.
    log_likelihood : tuple of float
        ln P(Y | Λ) before each iteration and after the last one (length iterations + 1).
    outlier_fraction : float
        Mean posterior of the outlier class at the final pose.
    estep : EStep or None
        The E-step at the final pose and mixture: a fit continued from this one starts from it.
    """

    pose: np.ndarray
    body: BodyModel
    mixture: Mixture
    iterations: int
    converged: bool
    log_likelihood: tuple[float, ...]
    outlier_fraction: float
    estep: EStep | None = None

    @property
    def height_m(self) -> float:
        """Standing height of the fitted body, metres."""
        return self.body.height_m


def volume_size(volume: np.ndarray) -> float:
    """V of the uniform outlier density (eq. 10): the volume of the box (2, 3) [min; max], m³."""
    volume = np.asarray(volume, dtype=float)
    if volume.shape != (2, 3) or not np.all(np.isfinite(volume)) or np.any(volume[1] <= volume[0]):
        raise ValueError(f"volume must be a (2, 3) array [min; max] with max > min, got {volume.tolist()}")
    return float(np.prod(volume[1] - volume[0]))


def e_step(y: np.ndarray, n: np.ndarray, body: BodyModel, pose: np.ndarray, mixture: Mixture,
           V: float, *, distance: str = "normals", normal_noise_rad: float = 0.0) -> EStep:
    """Posteriors t_ip (Horaud et al. 2009 eq. 13) and log-likelihood (eq. 12), by log-sum-exp.

    With `normal_noise_rad` σ_n > 0 (and the "normals" distance), component p's Gaussian for datum i
    has the covariance Σ_ip = Σ + σ_n² A_ip A_ipᵀ (`distances.normal_spread`) instead of Σ. Pairs whose
    joint density is provably below NEGLIGIBLE_POSTERIOR times the outlier term are skipped (t_ip = 0),
    which leaves a few ellipsoids per datum; the result equals the dense computation to that precision.

    Parameters
    ----------
    y, n : (I, 3) float
        Points (metres) and unit outward normals.
    body, pose : BodyModel, (D,) float
    mixture : Mixture
    V : float
        Volume of the working space, m³ (outlier density 1/V).
    """
    return _e_step(y, n, body.ellipsoids(pose), mixture, V, distance, normal_noise_rad)


def _e_step(y: np.ndarray, n: np.ndarray, ellipsoids: Ellipsoids, mixture: Mixture, V: float, distance: str,
            normal_noise_rad: float, previous: EStep | None = None) -> EStep:
    """`e_step` on the posed ellipsoids: compiled for the paper's distance, numpy for the others.

    `previous`, the E-step of the previous iteration, only says which ellipsoid to try first for each datum.
    """
    I, P = len(y), len(ellipsoids.t)
    k = residual_size(distance)
    if I == 0:
        return EStep(t=np.zeros((0, P)), t_outlier=np.zeros(0), log_likelihood=0.0,
                     pairs=np.zeros((2, 0), dtype=int), weights=np.zeros((0, k, k)), best=np.zeros(0, dtype=int))
    log_outlier = np.log(mixture.pi[P]) - np.log(V)  # ln π_{P+1} / V
    if distance == "normals":
        first = np.zeros(I, dtype=int) if previous is None else previous.best
        t, t_outlier, log_likelihood, pairs, weights, best = compiled.e_step(
            y, n, ellipsoids.t, *compiled.shapes(ellipsoids.R, ellipsoids.semi_axes), ellipsoids.semi_axes,
            mixture.Sigma, np.log(mixture.pi[:P]), log_outlier, normal_noise_rad**2, np.log(NEGLIGIBLE_POSTERIOR),
            PRUNE_POSTERIOR, first)
        return EStep(t=t, t_outlier=t_outlier, log_likelihood=log_likelihood, pairs=pairs, weights=weights, best=best)
    # Squared Mahalanobis distance (P,) beyond which ln π_p N_ip is below ln(NEGLIGIBLE_POSTERIOR π_{P+1} / V)
    # (the Gaussian's peak is at most N₀ = N(0 | 0, Σ)), and eᵀ Σ⁻¹ e ≥ |e|² / c, c Σ's largest eigenvalue.
    log_peak = -0.5 * (np.linalg.slogdet(mixture.Sigma)[1] + k * np.log(2.0 * np.pi))
    reach = -2.0 * (log_outlier + np.log(NEGLIGIBLE_POSTERIOR) - np.log(mixture.pi[:P]) - log_peak)
    bound = residual_lower_bound(y, ellipsoids, distance=distance) / np.linalg.eigvalsh(mixture.Sigma)[-1]
    p, i = np.nonzero(bound <= reach[:, None])
    e = residuals(y, n, i, p, None, ellipsoids, distance=distance).e
    W = np.linalg.inv(mixture.Sigma)
    log_joint = np.log(mixture.pi[p]) + log_peak - 0.5 * ((e @ W) * e).sum(1)  # ln π_p N_ip
    dense = np.full((P, I), -np.inf)  # ln π_p N_ip, −∞ for the skipped pairs
    dense[p, i] = log_joint
    peak = np.maximum(dense.max(axis=0), log_outlier)
    joint = np.exp(log_joint - peak[i])
    evidence = np.exp(log_outlier - peak) + np.bincount(i, joint, minlength=I)
    posterior = joint / evidence[i]  # eq. (13)
    t = np.zeros((I, P))
    t[i, p] = posterior
    log_likelihood = float(np.sum(peak + np.log(evidence)))  # Σ_i ln P(y_i | n_i), eq. (12)
    used = posterior > PRUNE_POSTERIOR
    weights = np.linalg.cholesky(W) * np.sqrt(posterior[used])[:, None, None]  # t_ip Σ⁻¹ = W Wᵀ, Σ shared
    return EStep(t=t, t_outlier=np.exp(log_outlier - peak) / evidence, log_likelihood=log_likelihood,
                 pairs=np.stack([i[used], p[used]]), weights=weights, best=t.argmax(axis=1))


def log_evidence(y: np.ndarray, n: np.ndarray, ellipsoids: Ellipsoids, mixture: Mixture, V: float, *,
                 which: np.ndarray | None = None, base: np.ndarray | None = None, distance: str = "normals",
                 normal_noise_rad: float = 0.0) -> np.ndarray:
    """Per datum ln(exp(b_i) + Σ_{p ∈ which} π_p N(y_i | x_ip, Σ_ip)) (I,), pairs skipped as in `e_step`.

    With every ellipsoid and b_i = ln(π_{P+1} / V) (the defaults) these are the terms of ln P(Y | Λ)
    (eq. 12). Evidence is additive over the classes, so hypotheses that move only a few ellipsoids are
    scored by computing the others' evidence once (`which` = the others) and passing it as `base`.
    """
    which, base = _evidence_terms(len(y), len(ellipsoids.t), mixture, V, which, base)
    chosen = Ellipsoids(R=ellipsoids.R[which], t=ellipsoids.t[which], semi_axes=ellipsoids.semi_axes[which])
    log_pi = np.log(mixture.pi[which])
    if len(y) == 0:
        return np.zeros(0)
    if distance == "normals":
        return compiled.log_evidence(y, n, chosen.t, *compiled.shapes(chosen.R, chosen.semi_axes), chosen.semi_axes,
                                     mixture.Sigma, log_pi, base, normal_noise_rad**2, np.log(NEGLIGIBLE_POSTERIOR))
    log_norm = -0.5 * (np.linalg.slogdet(mixture.Sigma)[1] + len(mixture.Sigma) * np.log(2.0 * np.pi))
    e = all_residuals(y, n, chosen, distance=distance)  # (I, P', k)
    log_joint = log_pi + log_norm - 0.5 * np.einsum("ipa,ab,ipb->ip", e, np.linalg.inv(mixture.Sigma), e)
    return np.logaddexp(base, logsumexp(log_joint, axis=1))


def hypothesis_scores(y: np.ndarray, n: np.ndarray, hypotheses: Ellipsoids, mixture: Mixture, V: float,
                      *, which: np.ndarray | None = None, base: np.ndarray | None = None,
                      blocks: np.ndarray | None = None, distance: str = "normals",
                      normal_noise_rad: float = 0.0) -> np.ndarray:
    """`log_evidence` summed over blocks of data (default one block: ln P(Y | Λ), eq. 12) for many posed
    bodies at once, (H, B): initialisation and limb re-initialisation score hundreds of hypotheses.

    `hypotheses` holds the H posed bodies' ellipsoids with a leading hypothesis axis (H, P, ...)
    (`BodyModel.posed_ellipsoids`); `blocks` (B + 1,) are the rows where each block starts, then the
    number of data.
    """
    blocks = np.array([0, len(y)]) if blocks is None else np.asarray(blocks)
    H, P = hypotheses.t.shape[:2]
    which, base = _evidence_terms(len(y), P, mixture, V, which, base)
    if distance != "normals" or len(y) == 0:
        terms = (log_evidence(y, n, Ellipsoids(R=hypotheses.R[h], t=hypotheses.t[h], semi_axes=hypotheses.semi_axes[h]),
                              mixture, V, which=which, base=base, distance=distance) for h in range(H))
        return np.array([[column[a:b].sum() for a, b in zip(blocks[:-1], blocks[1:], strict=True)]
                         for column in terms]).reshape(H, len(blocks) - 1)
    R, t, semi_axes = hypotheses.R[:, which], hypotheses.t[:, which], hypotheses.semi_axes[:, which]
    M, M2 = compiled.shapes(R.reshape(-1, 3, 3), np.ascontiguousarray(semi_axes).reshape(-1, 3))
    stack = (H, len(which))
    return compiled.hypothesis_scores(
        y, n, blocks, np.ascontiguousarray(t), M.reshape(*stack, 3, 3), M2.reshape(*stack, 3, 3),
        np.ascontiguousarray(semi_axes), mixture.Sigma, np.log(mixture.pi[which]), base, normal_noise_rad**2,
        np.log(NEGLIGIBLE_POSTERIOR))


def _evidence_terms(I: int, P: int, mixture: Mixture, V: float, which: np.ndarray | None,
                    base: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The ellipsoids `which` (default all P) and the base terms b_i (default ln π_{P+1} / V) of `log_evidence`."""
    which = np.arange(P) if which is None else np.asarray(which)
    base = np.full(I, np.log(mixture.pi[P]) - np.log(V)) if base is None else np.asarray(base, dtype=float)
    return which, base


def m_step(y: np.ndarray, n: np.ndarray, body: BodyModel, pose: np.ndarray, mixture: Mixture,
           estep: EStep, *, distance: str = "normals", prior_pose: np.ndarray | None = None,
           gauss_newton_steps: int = 1, estimate_scale: bool = False, estimate_lengths: bool = False,
           normal_noise_rad: float = 0.0, min_outlier_prior: float = 0.0,
           max_sigma_m: float = np.inf) -> MStep:
    """M-step of Horaud et al. 2009 (Sec. 3, step 3): pose by damped Gauss-Newton, then Σ and π.

    The pose minimises ½ Σ_i Σ_p t_ip (y_i − x_ip(Λ))ᵀ Σ⁻¹ (y_i − x_ip(Λ)) (eq. 14 for fixed t_ip)
    plus, for DOFs with a prior weight, ½ w_d ((Λ_d − Λ̂_d) / PRIOR_SIGMA_RAD)² towards `prior_pose`;
    joint limits are enforced by clipping each step. Then Σ = Σ t_ip e_ip e_ipᵀ / Σ t_ip at the new
    pose and π_p = (1/I) Σ_i t_ip. With `estimate_scale` the body's height, with `estimate_lengths`
    its segment-length factors ln ℓ (prior ½ Σ (ln ℓ_g / body.length_prior_sd_g)²) are further unknowns.

    With normal noise σ_n, Σ⁻¹ becomes each pair's Σ_ip⁻¹, frozen at the starting pose during the
    Gauss-Newton steps (Σ_ip varies slowly with Λ: only through the ellipsoid's orientation relative to
    n_i). Σ then has no closed-form maximiser; it comes from EM on the residuals' two parts
    (`_noisy_covariance`). Σ's eigenvalues are bounded above by `max_sigma_m`², π_{P+1} below by
    `min_outlier_prior` (the maximisers of eq. 14 under these bounds).
    """
    if len(estep.t) == 0:
        return MStep(pose=pose, mixture=mixture, body=body)
    return _m_step(y, n, body, body.fk(pose), pose, mixture, estep, distance, prior_pose, gauss_newton_steps,
                   estimate_scale, estimate_lengths, normal_noise_rad, min_outlier_prior, max_sigma_m)[0]


def _m_step(y, n, body, kin, pose, mixture, estep, distance, prior_pose, gauss_newton_steps, estimate_scale,
            estimate_lengths, normal_noise_rad, min_outlier_prior, max_sigma_m) -> tuple[MStep, Kinematics]:
    """`m_step` from the pose's kinematics `kin`; also returns the kinematics of the new pose.

    The pairs' weights t_ip Σ_ip⁻¹ are the E-step's (same pose, same Σ).
    """
    I, P = estep.t.shape
    i, p = estep.pairs
    t = estep.t[i, p]  # (K,)
    problem = _Problem(y, n, i, p, estep.weights, distance, prior_pose if prior_pose is not None else pose,
                       body.prior_weight / PRIOR_SIGMA_RAD**2, estimate_scale,
                       estimate_lengths and len(body.length_groups) > 0)
    e = None
    for _ in range(gauss_newton_steps):
        pose, body, kin, e = _gauss_newton_step(problem, body, kin, pose)
    if distance == "normals" and normal_noise_rad > 0.0:
        Sigma = _noisy_covariance(n, i, p, e, t, body.ellipsoids(kin), mixture.Sigma, normal_noise_rad**2,
                                  max_sigma_m)
    else:
        Sigma = _bound_covariance((e * t[:, None]).T @ e / max(t.sum(), np.finfo(float).tiny), max_sigma_m)
    pi = np.empty(P + 1)
    pi[:P] = estep.t.sum(axis=0) / I
    pi[P] = estep.t_outlier.sum() / I
    mstep = MStep(pose=pose, mixture=Mixture(Sigma=Sigma, pi=_bound_priors(pi, min_outlier_prior)), body=body)
    return mstep, kin


def _noisy_covariance(n, i, p, e, t, ellipsoids, Sigma, noise2, max_sigma_m) -> np.ndarray:
    """The M-step's Σ when each pair's residual also carries the normals' noise: e_k = z_k + w_k with
    z ~ N(0, Σ) and w ~ N(0, σ_n² A_k²), so that e_k ~ N(0, Σ_k), Σ_k = Σ + σ_n² A_k².

    The maximiser of Q(Σ) = Σ_k t_k ln N(e_k | 0, Σ_k) has no closed form. EM on the hidden z_k,
    Σ' = (1/T) Σ_k t_k E[z zᵀ | e_k] = Σ − Σ (S₁/T) Σ + Σ (S₂/T) Σ (S₁ = Σ_k t_k Σ_k⁻¹,
    S₂ = Σ_k t_k Σ_k⁻¹ e_k e_kᵀ Σ_k⁻¹, T = Σ_k t_k), never lowers Q; it moves slowly where σ_n² A_k²
    dominates Σ_k (flat, wide surfaces), so it is iterated `NOISY_COVARIANCE_ITERATIONS` times
    (`compiled.noisy_covariance`). The moment estimate (1/T) Σ_k t_k (e_k e_kᵀ − σ_n² A_k²) does not
    maximise Q: it shrinks Σ's narrow axis iteration after iteration while ln P(Y | Λ) falls.
    """
    M, M2 = compiled.shapes(ellipsoids.R, ellipsoids.semi_axes)
    return _bound_covariance(compiled.noisy_covariance(n, i, p, e, t, M, M2, noise2, Sigma,
                                                       NOISY_COVARIANCE_ITERATIONS), max_sigma_m)


def fit(y: np.ndarray, n: np.ndarray, body: BodyModel, pose: np.ndarray, volume: np.ndarray,
        params: EMParams = EMParams(), *, mixture: Mixture | None = None,
        prior_pose: np.ndarray | None = None, sigma_m: float = 0.03, start: EStep | None = None) -> FitResult:
    """Fit the body to points y (I, 3) and normals n (I, 3) by EM, starting at `pose` (D,).

    Parameters
    ----------
    volume : (2, 3) float
        Working volume [min; max], metres (its size is V of the outlier density).
    mixture : Mixture, optional
        Starting Σ and π; default Σ = sigma_m² I and equal priors (the paper's initialisation).
    prior_pose : (D,) float, optional
        Values the weakly observed DOFs are pulled towards (default: the starting pose).
    start : EStep, optional
        The E-step of these data at `pose` under `mixture` (`FitResult.estep` of a fit being
        continued), which is then not computed again.
    """
    if params.distance not in DISTANCES:
        raise ValueError(f"distance={params.distance!r}, expected one of {DISTANCES}")
    V = volume_size(volume)
    pose = body.clip(np.asarray(pose, dtype=float))
    prior_pose = pose.copy() if prior_pose is None else prior_pose
    if mixture is None:
        mixture = Mixture.initial(body.n_ellipsoids, sigma_m, residual_size(params.distance))
    kin = body.fk(pose)
    estep = start if start is not None else _e_step(y, n, body.ellipsoids(kin), mixture, V, params.distance,
                                                     params.normal_noise_rad)
    history = [estep.log_likelihood]
    converged = len(y) == 0
    iterations = 0
    joints = body.joint_positions(kin)
    while not converged and iterations < params.max_iterations:
        mstep, kin = _m_step(y, n, body, kin, pose, mixture, estep, params.distance, prior_pose,
                             params.gauss_newton_steps, params.estimate_scale, params.estimate_lengths,
                             params.normal_noise_rad, params.min_outlier_prior, params.max_sigma_m)
        pose, mixture, body = mstep.pose, mstep.mixture, mstep.body
        estep = _e_step(y, n, body.ellipsoids(kin), mixture, V, params.distance, params.normal_noise_rad, estep)
        iterations += 1
        history.append(estep.log_likelihood)
        moved = joints
        joints = body.joint_positions(kin)
        displacement = np.linalg.norm(joints - moved, axis=1).max()
        converged = abs(history[-1] - history[-2]) < params.tolerance * len(y) or displacement < params.displacement_m
    outliers = float(estep.t_outlier.mean()) if len(y) else 1.0
    return FitResult(pose=pose, body=body, mixture=mixture, iterations=iterations, converged=converged,
                     log_likelihood=tuple(history), outlier_fraction=outliers, estep=estep)


@dataclass(frozen=True)
class _Problem:
    """The weighted least squares of one M-step (eq. 14 for fixed t_ip): data, pairs and priors.

    Pairs (i[k], p[k]) are sorted by ellipsoid p; W (K, k, k), lower-triangular, weighs and whitens
    each pair (t_ip Σ_ip⁻¹ = W Wᵀ: the pair's term of eq. 14 is ½ |Wᵀ e|²), `prior` (D,) holds the prior
    precisions of the DOFs towards `prior_pose`.
    """

    y: np.ndarray
    n: np.ndarray
    i: np.ndarray
    p: np.ndarray
    W: np.ndarray
    distance: str
    prior_pose: np.ndarray
    prior: np.ndarray
    estimate_scale: bool
    estimate_lengths: bool

    @property
    def starts(self) -> np.ndarray:
        """Index of each present ellipsoid's first pair (the pairs are sorted by ellipsoid); empty without pairs."""
        return np.flatnonzero(np.diff(self.p, prepend=-1))

    def residuals(self, body: BodyModel, kin: Kinematics) -> np.ndarray:
        """The pairs' residuals e (K, k) on `body` posed by the kinematics `kin`."""
        ellipsoids = body.ellipsoids(kin)
        if self.distance == "normals":
            M = compiled.shapes(ellipsoids.R, ellipsoids.semi_axes)[0]
            return compiled.residuals(self.y, self.n, self.i, self.p, ellipsoids.t, M)
        return residuals(self.y, self.n, self.i, self.p, kin, ellipsoids, distance=self.distance).e

    def cost(self, body, pose, e):
        """Eq. (14) for fixed t_ip plus the priors on the weakly observed DOFs and the segment lengths."""
        z = np.log(body.length_factors) / body.length_prior_sd if self.estimate_lengths else np.zeros(0)
        return 0.5 * (compiled.whitened_norm2(self.W, e) + (self.prior * (pose - self.prior_pose) ** 2).sum()
                      + (z**2).sum())


def _gauss_newton_step(problem: _Problem, body: BodyModel, kin: Kinematics, pose: np.ndarray):
    """One Levenberg-Marquardt step on eq. (14) for fixed posteriors, from the pose's kinematics `kin`.

    Returns the accepted pose, body, their kinematics and the pairs' residuals there. The unknowns are Λ (D), then
    ln s of the body's size with `estimate_scale`, then ln ℓ of the length factors with
    `estimate_lengths`. The normal equations are summed per ellipsoid in rigid-velocity coordinates
    (H_p = Σ_k t_k B_kᵀ Σ⁻¹ B_k, 6 × 6) and mapped to the DOFs by the segment twists: H = Σ_p T_pᵀ H_p T_p.
    """
    W, D = problem.W, body.pose_size
    e, r, Bw, H6, g6, J_scale = _linearised(problem, body, kin)
    extra = _extra_columns(problem, body, pose, e, J_scale)  # (K,k,X)
    X = extra.shape[2]
    H = np.zeros((D + X, D + X))
    g = np.zeros(D + X)
    H[:D, :D], g[:D] = compiled.pose_normal_equations(H6, g6, body.ellipsoid_segment, body.moves, kin.axis,
                                                      kin.origin, body.dof_revolute)
    if X:  # the size and length columns are summed per pair's ellipsoid like the pose's
        starts = problem.starts
        T = body.segment_twists(kin)[body.ellipsoid_segment[problem.p[starts]]]  # (P',6,D)
        Xw = _whitened(W, extra)
        H[:D, D:] = np.einsum("pid,pix->dx", T, np.add.reduceat(np.einsum("kai,kax->kix", Bw, Xw), starts))
        H[D:, :D] = H[:D, D:].T
        H[D:, D:] = np.einsum("kax,kay->xy", Xw, Xw)
        g[D:] = np.einsum("kax,ka->x", Xw, r)
    prior = np.zeros(D + X)
    prior[:D] = problem.prior
    g[:D] += problem.prior * (pose - problem.prior_pose)
    if problem.estimate_lengths:
        G = len(body.length_groups)
        prior[-G:] = 1.0 / body.length_prior_sd**2
        g[-G:] += np.log(body.length_factors) / body.length_prior_sd**2
    H += np.diag(prior)
    cost = problem.cost(body, pose, e)
    diag = np.diag(H) + RIDGE
    damping = LM_DAMPING
    for _ in range(LM_TRIES):
        step = np.linalg.solve(H + np.diag(damping * diag + RIDGE), -g)
        candidate = body.clip(pose + step[:D])
        body_c = _updated_body(problem, body, step[D:])
        kin_c = body_c.fk(candidate)
        e_c = problem.residuals(body_c, kin_c)
        if problem.cost(body_c, candidate, e_c) <= cost:
            return candidate, body_c, kin_c, e_c
        damping *= LM_GROWTH
    return pose, body, kin, e


def _linearised(problem: _Problem, body: BodyModel, kin: Kinematics):
    """The pairs' residuals e and, whitened, r = Wᵀ e and Bw = Wᵀ B (B = de/d(ω, v)); per ellipsoid
    H_p = Σ Bwᵀ Bw (P, 6, 6) and g_p = Σ Bwᵀ r (P, 6); and de/d(ln s) (or None without `estimate_scale`).

    Compiled for the paper's distance (`compiled.normal_equations`), numpy for the others.
    """
    P = body.n_ellipsoids
    if problem.distance == "normals":
        ellipsoids = body.ellipsoids(kin)
        e, r, Bw, H6, g6, J_scale = compiled.normal_equations(
            problem.y, problem.n, problem.i, problem.p, problem.W, ellipsoids.t,
            compiled.shapes(ellipsoids.R, ellipsoids.semi_axes)[0],
            kin.t[0])
        return e, r, Bw, H6, g6, J_scale if problem.estimate_scale else None
    res = residuals(problem.y, problem.n, problem.i, problem.p, kin, body.ellipsoids(kin), distance=problem.distance,
                    jacobian=True, scale=problem.estimate_scale)
    r = _whitened(problem.W, res.e)  # (K,k) Wᵀ e
    Bw = _whitened(problem.W, res.B)  # (K,k,6) Wᵀ B
    H6, g6 = np.zeros((P, 6, 6)), np.zeros((P, 6))
    starts = problem.starts
    for a, b in zip(starts, np.append(starts, len(r))[1:], strict=True):
        block = Bw[a:b].reshape(-1, 6)
        H6[problem.p[a]] = block.T @ block
    g6[problem.p[starts]] = np.add.reduceat(np.einsum("kai,ka->ki", Bw, r), starts)
    return res.e, r, Bw, H6, g6, res.J_scale


def _whitened(W: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Wᵀ X of every pair for lower-triangular W (K, k, k) and X (K, k) or (K, k, m), term by term."""
    k = W.shape[1]
    w = W if X.ndim == 2 else W[..., None]
    return np.stack([sum(w[:, a, b] * X[:, a] for a in range(b, k)) for b in range(k)], axis=1)


def _extra_columns(problem: _Problem, body: BodyModel, pose: np.ndarray, e: np.ndarray,
                   J_scale: np.ndarray | None) -> np.ndarray:
    """de/d ln s (analytic, `J_scale`) and de/d ln ℓ (forward differences from `e`) as columns (K, k, X)."""
    columns = []
    if problem.estimate_scale:
        columns.append(J_scale[:, :, None])
    if problem.estimate_lengths:
        for g in range(len(body.length_groups)):
            factors = body.length_factors.copy()
            factors[g] *= np.exp(LENGTH_STEP)
            stretched = body.with_lengths(factors)
            e_g = problem.residuals(stretched, stretched.fk(pose))
            columns.append(((e_g - e) / LENGTH_STEP)[:, :, None])
    return np.concatenate(columns, axis=2) if columns else np.zeros(e.shape + (0,))


def _updated_body(problem: _Problem, body: BodyModel, step: np.ndarray) -> BodyModel:
    """The body after a step on ln s (first, with `estimate_scale`) and ln ℓ (then, with `estimate_lengths`)."""
    if problem.estimate_scale:
        body = body.scaled(float(np.clip(body.height_m * np.exp(step[0]), *HEIGHT_RANGE_M)))
        step = step[1:]
    if problem.estimate_lengths:
        body = body.with_lengths(np.clip(body.length_factors * np.exp(step), *LENGTH_RANGE))
    return body


def _bound_covariance(Sigma: np.ndarray, max_sigma_m: float) -> np.ndarray:
    """Σ with its eigenvalues clipped to [SIGMA_FLOOR_M², max_sigma_m²] (symmetric positive definite)."""
    vals, vecs = np.linalg.eigh(0.5 * (Sigma + Sigma.T))
    return (vecs * np.clip(vals, SIGMA_FLOOR_M**2, max(max_sigma_m, SIGMA_FLOOR_M) ** 2)) @ vecs.T


def _bound_priors(pi: np.ndarray, min_outlier_prior: float) -> np.ndarray:
    """π with every ellipsoid's prior at least PI_FLOOR and the outlier prior at least `min_outlier_prior`.

    The ellipsoids' share is rescaled to 1 − π_{P+1}, which maximises Σ_p (Σ_i t_ip) ln π_p under the bound.
    """
    pi = np.maximum(pi, PI_FLOOR)
    pi /= pi.sum()
    outlier = max(pi[-1], min_outlier_prior)
    bounded = pi * (1.0 - outlier) / pi[:-1].sum()
    bounded[-1] = outlier
    return bounded
