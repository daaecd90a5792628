"""Robust fit of the articulated body to points and normals by EM (Horaud et al. 2009, Sec. 3).

The data are explained by a mixture of one Gaussian per ellipsoid and a uniform outlier class
(eqs. 9-11, `mixture`). `e_step` computes the posteriors t_ip (eq. 13) and the log-likelihood (eq. 12);
`m_step` decreases the expected complete-data negative log-likelihood (eq. 14) over the pose Λ by a
damped Gauss-Newton (Levenberg-Marquardt) step (`gauss_newton`) with the analytic Jacobians of the
distance (`distances`), then updates Σ and π with the paper's formulas (a generalised EM: one step per
M-step is enough for the likelihood to grow). `fit` owns the loop and stops when the likelihood gain or
the joints' motion becomes negligible. Besides the pose, an M-step may estimate the body's overall size
and its segment-length factors (with a prior towards the configured proportions). The names follow the
paper: y, n, x, Σ (`Sigma`), π (`pi`), t_ip (`t`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.tracking.body import BodyModel, Ellipsoids, Kinematics
from stages.tracking.distances import distance_named
from stages.tracking.gauss_newton import PRIOR_SIGMA_RAD, LeastSquares, gauss_newton_step
from stages.tracking.mixture import EStep, Mixture, bound_priors, evidence_terms, volume_size


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
        covariance is Σ_ip = Σ + σ_n² A_ip A_ipᵀ with A_ip = ∂x_ip/∂n_i (`geometry.normal_spread`);
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
class MStep:
    """New parameters from one M-step: pose Λ (D,), mixture (Σ, π), the body (its size and lengths) and
    the kinematics of the new pose on that body (the next E-step poses the ellipsoids from them)."""

    pose: np.ndarray
    mixture: Mixture
    body: BodyModel
    kin: Kinematics


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
    kin : Kinematics
        The kinematics of `pose` on `body` (`BodyModel.fk`), for what is computed at the fitted pose next.
    joints : (17, 3) float
        Joint centres of `pose` on `body` (`BodyModel.joint_positions`), which the stopping rule computed.
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
    kin: Kinematics
    joints: np.ndarray
    estep: EStep | None = None

    @property
    def height_m(self) -> float:
        """Standing height of the fitted body, metres."""
        return self.body.height_m


def e_step(y: np.ndarray, n: np.ndarray, ellipsoids: Ellipsoids, mixture: Mixture, V: float,
           params: EMParams = EMParams(), previous: EStep | None = None) -> EStep:
    """Posteriors t_ip (Horaud et al. 2009 eq. 13) and log-likelihood (eq. 12), by log-sum-exp.

    With `params.normal_noise_rad` σ_n > 0 (and the "normals" distance), component p's Gaussian for datum
    i has the covariance Σ_ip = Σ + σ_n² A_ip A_ipᵀ (`geometry.normal_spread`) instead of Σ. Pairs whose
    joint density is provably below `mixture.NEGLIGIBLE_POSTERIOR` times the largest term of the datum's
    evidence are skipped (t_ip = 0), which leaves a few ellipsoids per datum; the result equals the dense
    computation to that precision.

    Parameters
    ----------
    y, n : (I, 3) float
        Points (metres) and unit outward normals.
    ellipsoids : Ellipsoids
        The body's posed ellipsoids (`BodyModel.ellipsoids`).
    mixture : Mixture
    V : float
        Volume of the working space, m³ (outlier density 1/V).
    previous : EStep, optional
        The E-step of the previous iteration: it only says which ellipsoid to try first for each datum.
    """
    distance = distance_named(params.distance)
    if len(y) == 0:
        return EStep.empty(len(ellipsoids.t), distance.size)
    log_outlier = np.log(mixture.pi[len(ellipsoids.t)]) - np.log(V)  # ln π_{P+1} / V
    return distance.e_step(y, n, ellipsoids, mixture, log_outlier, params.normal_noise_rad, previous)


def log_evidence(y: np.ndarray, n: np.ndarray, ellipsoids: Ellipsoids, mixture: Mixture, V: float, *,
                 which: np.ndarray | None = None, base: np.ndarray | None = None, distance: str = "normals",
                 normal_noise_rad: float = 0.0) -> np.ndarray:
    """Per datum ln(exp(b_i) + Σ_{p ∈ which} π_p N(y_i | x_ip, Σ_ip)) (I,), pairs skipped as in `e_step`.

    With every ellipsoid and b_i = ln(π_{P+1} / V) (the defaults) these are the terms of ln P(Y | Λ)
    (eq. 12). Evidence is additive over the classes, so hypotheses that move only a few ellipsoids are
    scored by computing the others' evidence once (`which` = the others) and passing it as `base`.
    """
    which, base = evidence_terms(len(y), len(ellipsoids.t), mixture, V, which, base)
    chosen = Ellipsoids(R=ellipsoids.R[which], t=ellipsoids.t[which], semi_axes=ellipsoids.semi_axes[which])
    log_pi = np.log(mixture.pi[which])
    if len(y) == 0:
        return np.zeros(0)
    return distance_named(distance).log_evidence(y, n, chosen, mixture, log_pi, base, normal_noise_rad)


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
    which, base = evidence_terms(len(y), P, mixture, V, which, base)
    if len(y) == 0:
        return np.zeros((H, len(blocks) - 1))
    return distance_named(distance).hypothesis_scores(y, n, hypotheses, mixture, which, base, blocks,
                                                      normal_noise_rad)


def screened_scores(score, count: int, rows: int, screen: int, keep: int) -> np.ndarray:
    """The scores of `count` hypotheses on `rows` data rows, computed in full only for the `keep` best on the
    first `screen` rows; −inf for the others.

    `score(chosen, rows)` gives the chosen hypotheses' summed log-evidence (`hypothesis_scores`) on a slice of
    the data rows, (len(chosen), ...) with any further axes (the headings of the initialisation); a hypothesis is
    ranked by its best entry. Initialisation and limb recovery refine only a few of hundreds of hypotheses, and
    one far down the ranking on a few random rows stays far down on all of them: scoring every one on those
    rows and only the survivors on the others costs a fraction of the work, and the two block sums add up to
    the survivors' full scores.
    """
    everyone = np.arange(count)
    if screen >= rows or keep >= count:
        return score(everyone, slice(0, rows))
    first = score(everyone, slice(0, screen))
    survivors = np.sort(np.argsort(-first.reshape(count, -1).max(axis=1), kind="stable")[:keep])
    scores = np.full_like(first, -np.inf)
    scores[survivors] = first[survivors] + score(survivors, slice(screen, rows))
    return scores


def m_step(y: np.ndarray, n: np.ndarray, body: BodyModel, kin: Kinematics, pose: np.ndarray, mixture: Mixture,
           estep: EStep, params: EMParams = EMParams(), prior_pose: np.ndarray | None = None) -> MStep:
    """M-step of Horaud et al. 2009 (Sec. 3, step 3): pose by damped Gauss-Newton, then Σ and π.

    The pose minimises ½ Σ_i Σ_p t_ip (y_i − x_ip(Λ))ᵀ Σ⁻¹ (y_i − x_ip(Λ)) (eq. 14 for fixed t_ip)
    plus, for DOFs with a prior weight, ½ w_d ((Λ_d − Λ̂_d) / PRIOR_SIGMA_RAD)² towards `prior_pose`
    (default: `pose`); joint limits are enforced by clipping each step. Then Σ = Σ t_ip e_ip e_ipᵀ / Σ t_ip
    at the new pose and π_p = (1/I) Σ_i t_ip. With `params.estimate_scale` the body's height, with
    `estimate_lengths` its segment-length factors ln ℓ (prior ½ Σ (ln ℓ_g / body.length_prior_sd_g)²)
    are further unknowns. `kin` is the kinematics of `pose` on `body`; the pairs' weights t_ip Σ_ip⁻¹
    are the E-step's (same pose, same Σ).

    With normal noise σ_n, Σ⁻¹ becomes each pair's Σ_ip⁻¹, frozen at the starting pose during the
    Gauss-Newton steps (Σ_ip varies slowly with Λ: only through the ellipsoid's orientation relative to
    n_i). Σ then has no closed-form maximiser; it comes from EM on the residuals' two parts
    (`distances.CompiledNormals.covariance`). Σ's eigenvalues are bounded above by `max_sigma_m`²,
    π_{P+1} below by `min_outlier_prior` (the maximisers of eq. 14 under these bounds).
    """
    if len(estep.t) == 0:
        return MStep(pose=pose, mixture=mixture, body=body, kin=kin)
    distance = distance_named(params.distance)
    I, P = estep.t.shape
    i, p = estep.pairs
    t = estep.t[i, p]  # (K,)
    problem = LeastSquares(y, n, i, p, estep.weights, distance, prior_pose if prior_pose is not None else pose,
                           body.prior_weight / PRIOR_SIGMA_RAD**2, params.estimate_scale,
                           params.estimate_lengths and len(body.length_groups) > 0)
    e = None
    for _ in range(params.gauss_newton_steps):
        pose, body, kin, e = gauss_newton_step(problem, body, kin, pose)
    Sigma = distance.covariance(n, i, p, e, t, body.ellipsoids(kin), mixture.Sigma, params.normal_noise_rad,
                                params.max_sigma_m)
    pi = np.empty(P + 1)
    pi[:P] = estep.explained / I
    pi[P] = estep.t_outlier.sum() / I
    return MStep(pose=pose, mixture=Mixture(Sigma=Sigma, pi=bound_priors(pi, params.min_outlier_prior)), body=body,
                 kin=kin)


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
    size = distance_named(params.distance).size
    V = volume_size(volume)
    pose = body.clip(np.asarray(pose, dtype=float))
    prior_pose = pose.copy() if prior_pose is None else prior_pose
    if mixture is None:
        mixture = Mixture.initial(body.n_ellipsoids, sigma_m, size)
    kin = body.fk(pose)
    estep = start if start is not None else e_step(y, n, body.ellipsoids(kin), mixture, V, params)
    history = [estep.log_likelihood]
    converged = len(y) == 0
    iterations = 0
    joints = body.joint_positions(kin)
    while not converged and iterations < params.max_iterations:
        mstep = m_step(y, n, body, kin, pose, mixture, estep, params, prior_pose)
        pose, mixture, body, kin = mstep.pose, mstep.mixture, mstep.body, mstep.kin
        estep = e_step(y, n, body.ellipsoids(kin), mixture, V, params, estep)
        iterations += 1
        history.append(estep.log_likelihood)
        moved = joints
        joints = body.joint_positions(kin)
        displacement = np.sqrt(((joints - moved) ** 2).sum(axis=1)).max()
        converged = abs(history[-1] - history[-2]) < params.tolerance * len(y) or displacement < params.displacement_m
    outliers = float(estep.t_outlier.mean()) if len(y) else 1.0
    return FitResult(pose=pose, body=body, mixture=mixture, iterations=iterations, converged=converged,
                     log_likelihood=tuple(history), outlier_fraction=outliers, kin=kin, joints=joints,
                     estep=estep)
