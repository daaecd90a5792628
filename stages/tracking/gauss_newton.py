"""The M-step's pose update: a damped Gauss-Newton (Levenberg-Marquardt) step on eq. (14) for fixed t_ip.

The unknowns are the pose Λ (D), then, when asked for, ln s of the body's overall size and ln ℓ of its
segment-length factors (with a prior towards the configured proportions). The normal equations are
summed per ellipsoid in rigid-velocity coordinates (H_p = Σ_k t_k B_kᵀ Σ⁻¹ B_k, 6 × 6, by the distance:
`distances.Distance.normal_equations`) and mapped to the DOFs by the segment twists: H = Σ_p T_pᵀ H_p T_p.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.tracking import compiled
from stages.tracking.body import BodyModel, Kinematics
from stages.tracking.distances import Distance

# Prior strength: a DOF with prior weight 1 is held to its predicted value with this standard
# deviation (radians) when the data say nothing about it; data dominate it whenever they see it.
PRIOR_SIGMA_RAD = 0.25
# Length factors a segment may take (people, not caricatures).
LENGTH_RANGE = (0.75, 1.33)
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
class LeastSquares:
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
    distance: Distance
    prior_pose: np.ndarray
    prior: np.ndarray
    estimate_scale: bool
    estimate_lengths: bool

    def residuals(self, body: BodyModel, kin: Kinematics) -> np.ndarray:
        """The pairs' residuals e (K, k) on `body` posed by the kinematics `kin`."""
        return self.distance.pair_residuals(self.y, self.n, self.i, self.p, kin, body.ellipsoids(kin))

    def cost(self, body, pose, norm2):
        """Eq. (14) for fixed t_ip plus the priors on the weakly observed DOFs and the segment lengths, from its
        data term Σ |Wᵀ e|² (`norm2`: `compiled.whitened_norm2`, which the normal equations also sum on the way)."""
        total = norm2 + (self.prior * (pose - self.prior_pose) ** 2).sum()
        if self.estimate_lengths:
            total += ((np.log(body.length_factors) / body.length_prior_sd) ** 2).sum()
        return 0.5 * total


def gauss_newton_step(problem: LeastSquares, body: BodyModel, kin: Kinematics, pose: np.ndarray):
    """One Levenberg-Marquardt step on eq. (14) for fixed posteriors, from the pose's kinematics `kin`.

    Returns the accepted pose, body, their kinematics and the pairs' residuals there (the current ones
    when no damping within `LM_TRIES` lowers the cost).
    """
    H, g, e, norm2 = _normal_equations(problem, body, kin, pose)
    D = body.pose_size
    cost = problem.cost(body, pose, norm2)
    diag = np.diag(H) + RIDGE
    damping = LM_DAMPING
    for _ in range(LM_TRIES):
        step = np.linalg.solve(H + np.diag(damping * diag + RIDGE), -g)
        candidate = body.clip(pose + step[:D])
        body_c = _updated_body(problem, body, step[D:])
        kin_c = body_c.fk(candidate)
        e_c = problem.residuals(body_c, kin_c)
        if problem.cost(body_c, candidate, compiled.whitened_norm2(problem.W, e_c)) <= cost:
            return candidate, body_c, kin_c, e_c
        damping *= LM_GROWTH
    return pose, body, kin, e


def _normal_equations(problem: LeastSquares, body: BodyModel, kin: Kinematics, pose: np.ndarray):
    """H (D + X, D + X) and g (D + X,) of the linearised eq. (14) with its priors, the residuals e and Σ |Wᵀ e|².

    The pose block comes from the distance's per-ellipsoid blocks (`compiled.pose_normal_equations`);
    the X columns of the size and the length factors are summed per pair's ellipsoid like the pose's.
    """
    W, D = problem.W, body.pose_size
    e, r, Bw, H6, g6, J_scale, norm2 = problem.distance.normal_equations(
        problem.y, problem.n, problem.i, problem.p, W, kin, body.ellipsoids(kin), problem.estimate_scale)
    extra = _extra_columns(problem, body, kin, pose, e, J_scale)  # (K,k,X)
    X = extra.shape[2]
    H = np.zeros((D + X, D + X))
    g = np.zeros(D + X)
    H[:D, :D], g[:D] = compiled.pose_normal_equations(H6, g6, body.ellipsoid_segment, body.moves, kin.axis,
                                                      kin.origin, body.dof_revolute)
    if X:
        HX, H[D:, D:], g[D:] = compiled.extra_normal_equations(W, extra, Bw, r, problem.p, body.n_ellipsoids)
        T = body.segment_twists(kin)[body.ellipsoid_segment]  # (P,6,D); an ellipsoid without pairs adds zeros
        H[:D, D:] = np.einsum("pid,pix->dx", T, HX)
        H[D:, :D] = H[:D, D:].T
    prior = np.zeros(D + X)
    prior[:D] = problem.prior
    g[:D] += problem.prior * (pose - problem.prior_pose)
    if problem.estimate_lengths:
        G = len(body.length_groups)
        prior[-G:] = 1.0 / body.length_prior_sd**2
        g[-G:] += np.log(body.length_factors) / body.length_prior_sd**2
    H += np.diag(prior)
    return H, g, e, norm2


def _extra_columns(problem: LeastSquares, body: BodyModel, kin: Kinematics, pose: np.ndarray, e: np.ndarray,
                   J_scale: np.ndarray | None) -> np.ndarray:
    """de/d ln s (analytic, `J_scale`) and de/d ln ℓ (`Distance.length_jacobian`) as columns (K, k, X)."""
    columns = []
    if problem.estimate_scale:
        columns.append(J_scale[:, :, None])
    if problem.estimate_lengths:
        columns.append(problem.distance.length_jacobian(problem.y, problem.n, problem.i, problem.p, body, kin, pose,
                                                        e))
    return np.concatenate(columns, axis=2) if columns else np.zeros(e.shape + (0,))


def _updated_body(problem: LeastSquares, body: BodyModel, step: np.ndarray) -> BodyModel:
    """The body after a step on ln s (first, with `estimate_scale`) and ln ℓ (then, with `estimate_lengths`)."""
    if problem.estimate_scale:
        body = body.scaled(float(np.clip(body.height_m * np.exp(step[0]), *HEIGHT_RANGE_M)))
        step = step[1:]
    if problem.estimate_lengths:
        body = body.with_lengths(np.clip(body.length_factors * np.exp(step), *LENGTH_RANGE))
    return body
