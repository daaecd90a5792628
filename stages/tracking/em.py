"""Robust fit of the articulated body to points and normals by EM (Horaud et al. 2009, Sec. 3).

The data are explained by a mixture of P Gaussian components, one per ellipsoid, centred on the
ellipsoid points x_ip(Λ) (eq. 4) with one covariance Σ shared by all (so that ellipsoids without data
cannot collapse), plus a uniform outlier component 1/V over the working volume (eqs. 9-11):

    P(y_i | n_i) = Σ_p π_p N(y_i | x_ip(Λ), Σ) + π_{P+1} / V.

`e_step` computes the posteriors t_ip (eq. 13) and the log-likelihood (eq. 12); `m_step` decreases the
expected complete-data negative log-likelihood (eq. 14) over the pose Λ by a damped Gauss-Newton
(Levenberg-Marquardt) step with the analytic Jacobians of `distances`, then updates Σ and π with the
paper's formulas. `fit` owns the loop. The names follow the paper: y, n, x, Σ (`Sigma`), π (`pi`),
t_ip (`t`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.tracking.body import BodyModel
from stages.tracking.distances import DISTANCES, all_residuals, residual_size, residuals

# Σ is estimated from the residuals; with nearly exact data it would shrink towards 0 and the
# posteriors would turn into hard, brittle assignments. The floor is the model's own inexactness
# (ellipsoids are not a body surface): a few millimetres.
SIGMA_FLOOR_M = 0.004
# π_p of an ellipsoid that currently gets no data (occluded, or just out of reach) must not reach 0,
# or that ellipsoid could never attract data again.
PI_FLOOR = 1e-4
# Posteriors below this do not change the weighted least squares measurably; dropping those pairs
# from the M-step is what makes it fast (each datum keeps a handful of ellipsoids).
PRUNE_POSTERIOR = 1e-3
# Prior strength: a DOF with prior weight 1 is held to its predicted value with this standard
# deviation (radians) when the data say nothing about it; data dominate it whenever they see it.
PRIOR_SIGMA_RAD = 0.25
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
    gauss_newton_steps : int
        Damped Gauss-Newton steps per M-step (1 is a generalised EM step).
    estimate_scale : bool
        Also estimate the body's overall size (standing height) with the pose.
    """

    distance: str = "normals"
    max_iterations: int = 20
    tolerance: float = 1e-3
    gauss_newton_steps: int = 1
    estimate_scale: bool = False


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
    """

    t: np.ndarray
    t_outlier: np.ndarray
    log_likelihood: float


@dataclass(frozen=True)
class MStep:
    """New parameters from one M-step: pose Λ (D,), mixture (Σ, π) and the body's height (metres)."""

    pose: np.ndarray
    mixture: Mixture
    height_m: float


@dataclass(frozen=True)
class FitResult:
    """Outcome of `fit`.

    Attributes
    ----------
    pose : (D,) float
        Estimated pose Λ.
    height_m : float
        Standing height of the fitted body (the starting body's unless the scale was estimated).
    mixture : Mixture
        Final Σ and π.
    iterations : int
        EM iterations run.
    converged : bool
        The log-likelihood gain fell below the tolerance.
    log_likelihood : tuple of float
        ln P(Y | Λ) before each iteration and after the last one (length iterations + 1).
    outlier_fraction : float
        Mean posterior of the outlier class at the final pose.
    """

    pose: np.ndarray
    height_m: float
    mixture: Mixture
    iterations: int
    converged: bool
    log_likelihood: tuple[float, ...]
    outlier_fraction: float


def volume_size(volume: np.ndarray) -> float:
    """V of the uniform outlier density (eq. 10): the volume of the box (2, 3) [min; max], m³."""
    volume = np.asarray(volume, dtype=float)
    if volume.shape != (2, 3) or not np.all(np.isfinite(volume)) or np.any(volume[1] <= volume[0]):
        raise ValueError(f"volume must be a (2, 3) array [min; max] with max > min, got {volume.tolist()}")
    return float(np.prod(volume[1] - volume[0]))


def e_step(y: np.ndarray, n: np.ndarray, body: BodyModel, pose: np.ndarray, mixture: Mixture,
           V: float, *, distance: str = "normals") -> EStep:
    """Posteriors t_ip (Horaud et al. 2009 eq. 13) and log-likelihood (eq. 12), by log-sum-exp.

    Parameters
    ----------
    y, n : (I, 3) float
        Points (metres) and unit outward normals.
    body, pose : BodyModel, (D,) float
    mixture : Mixture
    V : float
        Volume of the working space, m³ (outlier density 1/V).
    """
    I, P = len(y), body.n_ellipsoids
    if I == 0:
        return EStep(t=np.zeros((0, P)), t_outlier=np.zeros(0), log_likelihood=0.0)
    e = all_residuals(y, n, body.ellipsoids(pose), distance=distance)  # (I,P,k)
    log_joint = np.empty((I, P + 1))
    log_joint[:, :P] = np.log(mixture.pi[:P]) + _log_gaussian(e, mixture.Sigma)  # ln π_p N(y_i | x_ip, Σ)
    log_joint[:, P] = np.log(mixture.pi[P]) - np.log(V)  # ln π_{P+1} / V
    peak = log_joint.max(axis=1, keepdims=True)
    log_evidence = peak[:, 0] + np.log(np.exp(log_joint - peak).sum(axis=1))  # ln P(y_i | n_i)
    posterior = np.exp(log_joint - log_evidence[:, None])
    return EStep(t=posterior[:, :P], t_outlier=posterior[:, P], log_likelihood=float(log_evidence.sum()))


def m_step(y: np.ndarray, n: np.ndarray, body: BodyModel, pose: np.ndarray, mixture: Mixture,
           estep: EStep, *, distance: str = "normals", prior_pose: np.ndarray | None = None,
           gauss_newton_steps: int = 1, estimate_scale: bool = False) -> MStep:
    """M-step of Horaud et al. 2009 (Sec. 3, step 3): pose by damped Gauss-Newton, then Σ and π.

    The pose minimises ½ Σ_i Σ_p t_ip (y_i − x_ip(Λ))ᵀ Σ⁻¹ (y_i − x_ip(Λ)) (eq. 14 for fixed t_ip)
    plus, for DOFs with a prior weight, ½ w_d ((Λ_d − Λ̂_d) / PRIOR_SIGMA_RAD)² towards `prior_pose`;
    joint limits are enforced by clipping each step. Then Σ = Σ t_ip e_ip e_ipᵀ / Σ t_ip at the new
    pose and π_p = (1/I) Σ_i t_ip. With `estimate_scale` the body's height is a further unknown of the
    least squares.
    """
    I, P = estep.t.shape
    if I == 0:
        return MStep(pose=pose, mixture=mixture, height_m=body.height_m)
    i, p = np.nonzero(estep.t > PRUNE_POSTERIOR)
    t = estep.t[i, p]  # (K,)
    W = np.linalg.inv(mixture.Sigma)  # Σ⁻¹
    prior_pose = pose if prior_pose is None else prior_pose
    prior = body.prior_weight / PRIOR_SIGMA_RAD**2  # (D,)
    for _ in range(gauss_newton_steps):
        pose, body = _gauss_newton_step(y, n, i, p, t, W, body, pose, prior, prior_pose, distance,
                                        estimate_scale)
    kin = body.fk(pose)
    e = residuals(y, n, i, p, body, kin, body.ellipsoids(kin), distance=distance).e
    Sigma = np.einsum("k,ka,kb->ab", t, e, e) / max(t.sum(), np.finfo(float).tiny)
    pi = np.empty(P + 1)
    pi[:P] = estep.t.sum(axis=0) / I
    pi[P] = estep.t_outlier.sum() / I
    return MStep(pose=pose, mixture=Mixture(Sigma=_floor_covariance(Sigma), pi=_floor_priors(pi)),
                 height_m=body.height_m)


def fit(y: np.ndarray, n: np.ndarray, body: BodyModel, pose: np.ndarray, volume: np.ndarray,
        params: EMParams = EMParams(), *, mixture: Mixture | None = None,
        prior_pose: np.ndarray | None = None, sigma_m: float = 0.03) -> FitResult:
    """Fit the body to points y (I, 3) and normals n (I, 3) by EM, starting at `pose` (D,).

    Parameters
    ----------
    volume : (2, 3) float
        Working volume [min; max], metres (its size is V of the outlier density).
    mixture : Mixture, optional
        Starting Σ and π; default Σ = sigma_m² I and equal priors (the paper's initialisation).
    prior_pose : (D,) float, optional
        Values the weakly observed DOFs are pulled towards (default: the starting pose).
    """
    if params.distance not in DISTANCES:
        raise ValueError(f"distance={params.distance!r}, expected one of {DISTANCES}")
    V = volume_size(volume)
    pose = body.clip(np.asarray(pose, dtype=float))
    prior_pose = pose.copy() if prior_pose is None else prior_pose
    if mixture is None:
        mixture = Mixture.initial(body.n_ellipsoids, sigma_m, residual_size(params.distance))
    estep = e_step(y, n, body, pose, mixture, V, distance=params.distance)
    history = [estep.log_likelihood]
    converged = len(y) == 0
    iterations = 0
    while not converged and iterations < params.max_iterations:
        mstep = m_step(y, n, body, pose, mixture, estep, distance=params.distance, prior_pose=prior_pose,
                       gauss_newton_steps=params.gauss_newton_steps, estimate_scale=params.estimate_scale)
        pose, mixture = mstep.pose, mstep.mixture
        if mstep.height_m != body.height_m:
            body = body.scaled(mstep.height_m)
        estep = e_step(y, n, body, pose, mixture, V, distance=params.distance)
        iterations += 1
        history.append(estep.log_likelihood)
        converged = abs(history[-1] - history[-2]) < params.tolerance * len(y)
    outliers = float(estep.t_outlier.mean()) if len(y) else 1.0
    return FitResult(pose=pose, height_m=body.height_m, mixture=mixture, iterations=iterations,
                     converged=converged, log_likelihood=tuple(history), outlier_fraction=outliers)


def _log_gaussian(e: np.ndarray, Sigma: np.ndarray) -> np.ndarray:
    """ln N(e | 0, Σ) for residuals e (..., k)."""
    k = Sigma.shape[0]
    L = np.linalg.cholesky(Sigma)
    z = e @ np.linalg.inv(L).T  # L⁻¹ e, row by row
    log_det = 2.0 * np.log(np.diag(L)).sum()
    return -0.5 * (np.einsum("...a,...a->...", z, z) + log_det + k * np.log(2.0 * np.pi))


def _gauss_newton_step(y, n, i, p, t, W, body, pose, prior, prior_pose, distance, estimate_scale):
    """One Levenberg-Marquardt step on eq. (14) for fixed posteriors; returns the accepted pose, body.

    The unknowns are Λ and, with `estimate_scale`, ln s of the body's size (an extra last column).
    """
    kin = body.fk(pose)
    res = residuals(y, n, i, p, body, kin, body.ellipsoids(kin), distance=distance, jacobian=True,
                    scale=estimate_scale)
    J = res.J if not estimate_scale else np.concatenate([res.J, res.J_scale[:, :, None]], axis=2)
    L = np.linalg.cholesky(W)  # W = L Lᵀ: whitened residual Lᵀ e
    sqrt_t = np.sqrt(t)[:, None]
    r = (res.e @ L) * sqrt_t  # (K,k)
    Jw = (np.einsum("ba,kbd->kad", L, J) * sqrt_t[:, :, None]).reshape(-1, J.shape[2])  # Lᵀ J
    prior = np.append(prior, 0.0) if estimate_scale else prior
    offset = np.append(pose - prior_pose, 0.0) if estimate_scale else pose - prior_pose
    H = Jw.T @ Jw + np.diag(prior)
    g = Jw.T @ r.reshape(-1) + prior * offset
    cost = 0.5 * (r**2).sum() + 0.5 * (prior * offset**2).sum()
    diag = np.diag(H) + RIDGE
    damping = LM_DAMPING
    for _ in range(LM_TRIES):
        step = np.linalg.solve(H + np.diag(damping * diag + RIDGE), -g)
        candidate = body.clip(pose + step[: body.pose_size])
        body_c = body
        if estimate_scale:
            body_c = body.scaled(float(np.clip(body.height_m * np.exp(step[-1]), *HEIGHT_RANGE_M)))
        kin_c = body_c.fk(candidate)
        e_c = residuals(y, n, i, p, body_c, kin_c, body_c.ellipsoids(kin_c), distance=distance).e
        r_c = (e_c @ L) * sqrt_t
        cost_c = 0.5 * (r_c**2).sum() + 0.5 * (prior[: body.pose_size] * (candidate - prior_pose) ** 2).sum()
        if cost_c <= cost:
            return candidate, body_c
        damping *= LM_GROWTH
    return pose, body


def _floor_covariance(Sigma: np.ndarray) -> np.ndarray:
    """Σ with every eigenvalue at least SIGMA_FLOOR_M² (symmetric positive definite)."""
    vals, vecs = np.linalg.eigh(0.5 * (Sigma + Sigma.T))
    return (vecs * np.maximum(vals, SIGMA_FLOOR_M**2)) @ vecs.T


def _floor_priors(pi: np.ndarray) -> np.ndarray:
    pi = np.maximum(pi, PI_FLOOR)
    return pi / pi.sum()
