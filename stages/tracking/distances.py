"""Datum-to-ellipsoid distances, one object each, and what EM computes on them.

Three ways to measure how far datum i (point y_i, unit outward normal n_i) is from ellipsoid p:

- ``"normals"`` (the paper's, Horaud et al. 2009 eq. 4): the ellipsoid point whose outward normal is
  parallel to n_i, x_ip = λ R_p D⁻¹ R_pᵀ n_i + t_p with λ = (n_iᵀ R_p D⁻¹ R_pᵀ n_i)^(-1/2); the residual
  is y_i − x_ip (3-D, metres).
- ``"points"`` (no normals): the ellipsoid point whose normal is parallel to the ellipsoid's own
  gradient at y_i, which is the radial projection x_ip = t_p + (y_i − t_p) / sqrt(q_p(y_i)) (the
  pseudo-Euclidean point of Dewaele et al.); residual y_i − x_ip.
- ``"algebraic"`` (Plänkers & Fua 2003): the scalar q_p(y) = Yᵀ Q_p Y = (y − t)ᵀ R D Rᵀ (y − t) − 1
  (eq. 1), times ρ_p / 2 with ρ_p the ellipsoid's smallest semi-axis, so that it is about the distance
  to the surface near a limb's side; residual 1-D, metres.

The pose derivatives come from one identity: moving ellipsoid p rigidly is the same as moving the
datum the opposite way in the ellipsoid's frame. For a rigid velocity (ω, v) of the ellipsoid (a point
x of it moves by ω × x + v),

    dx = ω × x + v − (∂x/∂y) (ω × y + v) − (∂x/∂n) (ω × n),

which is linear in (ω, v): de = B (ω, v) with B (k, 6) per pair. The pose Jacobian is then
de/dΛ = B T_s with T_s (6, D) the rigid velocities of the ellipsoid's segment per DOF
(`BodyModel.segment_twists`), so a least-squares solver can sum 6 × 6 blocks per ellipsoid instead
of forming (K, k, D) Jacobians.

Each distance is a `Distance` object, chosen once by name (`distance_named`): its geometry (residuals
and their derivatives, in numpy) and the EM's work on it, the E-step (eqs. 12-13), the evidence of
hypotheses and the M-step's normal equations (eq. 14), which `Distance` computes in numpy from the
geometry. The paper's distance, which the tracker runs by default, is `CompiledNormals`: the same maths
in the compiled loops of `compiled` (`NormalsDistance`, its numpy twin, is the reference the tests check
them against).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy.special import logsumexp

from stages.tracking import compiled
from stages.tracking.body import BodyModel, Ellipsoids, Kinematics
from stages.tracking.geometry import (
    Q_MIN,
    entries,
    normal_point,
    radial_point,
    rigid_derivative,
    shape_matrices,
)
from stages.tracking.mixture import (
    NEGLIGIBLE_POSTERIOR,
    PRUNE_POSTERIOR,
    EStep,
    Mixture,
    bound_covariance,
)

# EM updates of Σ per M-step under normal noise (`CompiledNormals.covariance`).
NOISY_COVARIANCE_ITERATIONS = 5
# Forward-difference step on ln ℓ for de/d ln ℓ where a distance has no closed form (`Distance.length_jacobian`):
# residuals are smooth in ℓ, so 1e-5 loses < 1e-5 relative.
LENGTH_STEP = 1e-5


@dataclass(frozen=True)
class Residuals:
    """Residuals of observation-ellipsoid pairs.

    Attributes
    ----------
    e : (K, k) float
        Residual of each pair (k = 3 for point distances, 1 for the algebraic one), metres.
    B : (K, k, 6) float or None
        de/d(ω, v) for a rigid velocity of each pair's ellipsoid (module docstring), or None when not
        asked for; de/dΛ = B T_s (`pose_jacobian`).
    J_scale : (K, k) float or None
        de/d(ln s) for a uniform scaling s of the whole body about its root joint, when asked for.
    """

    e: np.ndarray
    B: np.ndarray | None
    J_scale: np.ndarray | None = None


def pose_jacobian(B: np.ndarray, twists: np.ndarray) -> np.ndarray:
    """de/dΛ (K, k, D) from the rigid derivatives B (K, k, 6) and each pair's segment twists (K, 6, D)."""
    return B @ twists


def whitened(W: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Wᵀ X of every pair for lower-triangular W (K, k, k) and X (K, k) or (K, k, m), term by term."""
    k = W.shape[1]
    w = W if X.ndim == 2 else W[..., None]
    return np.stack([sum(w[:, a, b] * X[:, a] for a in range(b, k)) for b in range(k)], axis=1)


class Distance:
    """A datum-to-ellipsoid distance: its residuals (the subclasses) and EM's work on them, in numpy.

    The numpy E-step and M-step model no noise on the normals (Σ_ip = Σ, the paper's model): the
    normals' noise (`EMParams.normal_noise_rad`) is `CompiledNormals`'.
    """

    name: ClassVar[str]
    size: ClassVar[int] = 3  # dimension k of one residual

    def residuals(self, y: np.ndarray, n: np.ndarray, i: np.ndarray, p: np.ndarray, kin: Kinematics,
                  ellipsoids: Ellipsoids, *, jacobian: bool = False, scale: bool = False) -> Residuals:
        """Residuals (and optionally their pose Jacobians) of the pairs (i[k], p[k]).

        Parameters
        ----------
        y, n : (I, 3) float
            Observed points (metres) and unit outward normals.
        i, p : (K,) int
            Observation and ellipsoid index of every pair.
        kin, ellipsoids
            The body's kinematics and posed ellipsoids at the current pose.
        jacobian : bool
            Also return the rigid derivatives B (K, k, 6) (see `Residuals`).
        scale : bool
            Also return de/d(ln s) (K, k) for the body's height: scaling every ellipsoid by s about the
            root c is scaling the datum by 1/s about c, so dx/d(ln s) = (x − c) − (∂x/∂y)(y − c).
        """
        raise NotImplementedError

    def all_residuals(self, y: np.ndarray, n: np.ndarray, ellipsoids: Ellipsoids) -> np.ndarray:
        """Residuals (I, P, k) of every observation against every ellipsoid (the E-step's dense case).

        Same values as `residuals` on all pairs, computed by broadcasting instead of gathering.
        """
        raise NotImplementedError

    def lower_bound(self, y: np.ndarray, ellipsoids: Ellipsoids) -> np.ndarray:
        """A lower bound on every pair's |e_ip|² (P, I), from the centres' distances alone.

        For the point distances x_ip lies on ellipsoid p, within its largest semi-axis a_p of t_p, so
        |e| ≥ |y − t_p| − a_p. Ellipsoid-major (P, I), the order of the pairs everywhere else.
        """
        t = ellipsoids.t
        centre = (t * t).sum(1)[:, None] - 2.0 * t @ y.T + (y * y).sum(1)  # |y − t|²
        gap = np.maximum(np.sqrt(np.maximum(centre, 0.0)) - ellipsoids.semi_axes.max(axis=1)[:, None], 0.0)
        return gap * gap

    def e_step(self, y: np.ndarray, n: np.ndarray, ellipsoids: Ellipsoids, mixture: Mixture, log_outlier: float,
               normal_noise_rad: float, previous: EStep | None) -> EStep:
        """Posteriors (eq. 13) and ln P(Y | Λ) (eq. 12) of I > 0 data, pairs skipped as `em.e_step` says.

        `log_outlier` is ln π_{P+1} / V; `previous` (the last iteration's E-step) only guides the
        compiled search.
        """
        I, P, k = len(y), len(ellipsoids.t), self.size
        # Squared Mahalanobis distance (P,) beyond which ln π_p N_ip is below ln(NEGLIGIBLE_POSTERIOR π_{P+1} / V)
        # (the Gaussian's peak is at most N₀ = N(0 | 0, Σ)), and eᵀ Σ⁻¹ e ≥ |e|² / c, c Σ's largest eigenvalue.
        log_peak = -0.5 * (np.linalg.slogdet(mixture.Sigma)[1] + k * np.log(2.0 * np.pi))
        reach = -2.0 * (log_outlier + np.log(NEGLIGIBLE_POSTERIOR) - np.log(mixture.pi[:P]) - log_peak)
        bound = self.lower_bound(y, ellipsoids) / np.linalg.eigvalsh(mixture.Sigma)[-1]
        p, i = np.nonzero(bound <= reach[:, None])
        e = self.residuals(y, n, i, p, None, ellipsoids).e
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
                     pairs=np.stack([i[used], p[used]]), weights=weights, best=t.argmax(axis=1),
                     explained=t.sum(axis=0))

    def log_evidence(self, y: np.ndarray, n: np.ndarray, chosen: Ellipsoids, mixture: Mixture, log_pi: np.ndarray,
                     base: np.ndarray, normal_noise_rad: float) -> np.ndarray:
        """Per datum ln(exp(b_i) + Σ_p π_p N(y_i | x_ip, Σ)) (I,) over the `chosen` ellipsoids, I > 0."""
        log_norm = -0.5 * (np.linalg.slogdet(mixture.Sigma)[1] + len(mixture.Sigma) * np.log(2.0 * np.pi))
        e = self.all_residuals(y, n, chosen)  # (I, P', k)
        log_joint = log_pi + log_norm - 0.5 * np.einsum("ipa,ab,ipb->ip", e, np.linalg.inv(mixture.Sigma), e)
        return np.logaddexp(base, logsumexp(log_joint, axis=1))

    def hypothesis_scores(self, y: np.ndarray, n: np.ndarray, hypotheses: Ellipsoids, mixture: Mixture,
                          which: np.ndarray, base: np.ndarray, blocks: np.ndarray,
                          normal_noise_rad: float) -> np.ndarray:
        """`log_evidence` over the ellipsoids `which` of each of H posed bodies, summed per block (H, B)."""
        H = len(hypotheses.t)
        log_pi = np.log(mixture.pi[which])
        terms = (self.log_evidence(y, n, Ellipsoids(R=hypotheses.R[h][which], t=hypotheses.t[h][which],
                                                    semi_axes=hypotheses.semi_axes[h][which]),
                                   mixture, log_pi, base, 0.0) for h in range(H))
        return np.array([[column[a:b].sum() for a, b in zip(blocks[:-1], blocks[1:], strict=True)]
                         for column in terms]).reshape(H, len(blocks) - 1)

    def pair_residuals(self, y: np.ndarray, n: np.ndarray, i: np.ndarray, p: np.ndarray, kin: Kinematics,
                       ellipsoids: Ellipsoids) -> np.ndarray:
        """The M-step's residuals e (K, k) of the pairs (i, p) at the posed `ellipsoids`."""
        return self.residuals(y, n, i, p, kin, ellipsoids).e

    def length_jacobian(self, y: np.ndarray, n: np.ndarray, i: np.ndarray, p: np.ndarray, body: BodyModel,
                        kin: Kinematics, pose: np.ndarray, e: np.ndarray) -> np.ndarray:
        """de/d ln ℓ (K, k, G) of the pairs (i, p), whose residuals on `body` at `pose` (kinematics `kin`) are e
        (K, k), for each of the body's length factors: forward differences, one stretched body per factor
        (`BodyModel.with_each_lengths`).
        """
        one_step = np.where(np.eye(len(body.length_groups), dtype=bool), np.exp(LENGTH_STEP), 1.0)
        columns = []
        for stretched in body.with_each_lengths(body.length_factors * one_step):  # row g: factor g stepped
            kin = stretched.fk(pose)
            columns.append((self.pair_residuals(y, n, i, p, kin, stretched.ellipsoids(kin)) - e) / LENGTH_STEP)
        return np.stack(columns, axis=2) if columns else np.zeros(e.shape + (0,))

    def normal_equations(self, y: np.ndarray, n: np.ndarray, i: np.ndarray, p: np.ndarray, W: np.ndarray,
                         kin: Kinematics, ellipsoids: Ellipsoids, scale: bool):
        """The pairs' residuals e and, whitened, r = Wᵀ e and Bw = Wᵀ B (B = de/d(ω, v)); per ellipsoid
        H_p = Σ Bwᵀ Bw (P, 6, 6) and g_p = Σ Bwᵀ r (P, 6); de/d(ln s) (or None without `scale`); and Σ |Wᵀ e|²
        (twice eq. 14's data term, summed as `compiled.whitened_norm2` sums it).

        The pairs (i, p) are sorted by ellipsoid, W (K, k, k) whitens them (t_ip Σ_ip⁻¹ = W Wᵀ).
        """
        P = len(ellipsoids.t)
        res = self.residuals(y, n, i, p, kin, ellipsoids, jacobian=True, scale=scale)
        r = whitened(W, res.e)  # (K,k) Wᵀ e
        Bw = whitened(W, res.B)  # (K,k,6) Wᵀ B
        H6, g6 = np.zeros((P, 6, 6)), np.zeros((P, 6))
        starts = np.flatnonzero(np.diff(p, prepend=-1))
        for a, b in zip(starts, np.append(starts, len(r))[1:], strict=True):
            block = Bw[a:b].reshape(-1, 6)
            H6[p[a]] = block.T @ block
        g6[p[starts]] = np.add.reduceat(np.einsum("kai,ka->ki", Bw, r), starts)
        return res.e, r, Bw, H6, g6, res.J_scale, compiled.whitened_norm2(W, res.e)

    def covariance(self, n: np.ndarray, i: np.ndarray, p: np.ndarray, e: np.ndarray, t: np.ndarray,
                   ellipsoids: Ellipsoids, Sigma: np.ndarray, normal_noise_rad: float,
                   max_sigma_m: float) -> np.ndarray:
        """The M-step's Σ = Σ t_ip e_ip e_ipᵀ / Σ t_ip from the pairs' residuals e and posteriors t, bounded
        (`mixture.bound_covariance`)."""
        return bound_covariance((e * t[:, None]).T @ e / max(t.sum(), np.finfo(float).tiny), max_sigma_m)


class _PointDistance(Distance):
    """A distance whose residual is y_i − x_ip for a point x_ip of ellipsoid p chosen by the datum."""

    def point(self, y_k, n_k, ellipsoids: Ellipsoids, p, t, jacobian):
        """x_ip (K, 3) of the pairs, ∂x/∂y and ∂x/∂n (K, 3, 3) each or None (zero, or not asked for)."""
        raise NotImplementedError

    def residuals(self, y, n, i, p, kin, ellipsoids, *, jacobian=False, scale=False) -> Residuals:
        y_k, n_k, t = y[i], n[i], ellipsoids.t[p]
        x, A_y, A_n = self.point(y_k, n_k, ellipsoids, p, t, jacobian)
        e = y_k - x
        if not jacobian:
            return Residuals(e=e, B=None)
        J_scale = None
        if scale:
            c = kin.t[0]
            J_scale = -(x - c) if A_y is None else -(x - c) + np.einsum("kab,kb->ka", A_y, y_k - c)
        return Residuals(e=e, B=-rigid_derivative(x, y_k, n_k, A_y, A_n), J_scale=J_scale)


class NormalsDistance(_PointDistance):
    """The paper's distance (eq. 4): to the ellipsoid point whose outward normal is parallel to n_i (numpy)."""

    name = "normals"

    def point(self, y_k, n_k, ellipsoids, p, t, jacobian):
        return normal_point(n_k, entries(shape_matrices(ellipsoids, 2.0), p), t, jacobian)

    def length_jacobian(self, y, n, i, p, body, kin, pose, e):
        """de/d ln ℓ (K, 3, G) in closed form: x = t + λ M n moves by dx = dt + λ dM n − ½ λ³ (nᵀ dM n) M n
        (λ = (nᵀ M n)^(-1/2)) as the ellipsoids' centres and shapes change (`BodyModel.length_derivatives`)."""
        dt, dM = body.length_derivatives(kin)
        n_k = n[i]
        m = np.einsum("kab,kb->ka", shape_matrices(kin.ellipsoids, 2.0)[p], n_k)  # M n
        lam = 1.0 / np.sqrt(np.einsum("ka,ka->k", n_k, m))
        dMn = np.einsum("gkab,kb->gka", dM[:, p], n_k)
        dx = dt[:, p] + lam[:, None] * dMn - (0.5 * lam**3 * np.einsum("gka,ka->gk", dMn, n_k))[:, :, None] * m
        return -dx.transpose(1, 2, 0)

    def all_residuals(self, y, n, ellipsoids):
        P = len(ellipsoids.t)
        M = shape_matrices(ellipsoids, 2.0)  # (P,3,3) symmetric, so (nᵀ M)ᵀ = M n
        u = (n @ M.transpose(1, 0, 2).reshape(3, 3 * P)).reshape(-1, P, 3)  # (I,P,3): one matrix product
        lam = 1.0 / np.sqrt(np.einsum("ipa,ia->ip", u, n))  # eq. (4)
        return y[:, None, :] - ellipsoids.t[None] - lam[:, :, None] * u


class PointsDistance(_PointDistance):
    """To the radial projection of y_i on the ellipsoid (no normals; Dewaele et al.'s pseudo-Euclidean point)."""

    name = "points"

    def point(self, y_k, n_k, ellipsoids, p, t, jacobian):
        return radial_point(y_k, shape_matrices(ellipsoids, -2.0)[p], t)

    def all_residuals(self, y, n, ellipsoids):
        v = y[:, None, :] - ellipsoids.t[None]  # (I,P,3)
        q = np.einsum("ipa,ipa->ip", v, np.einsum("ipa,pab->ipb", v, shape_matrices(ellipsoids, -2.0)))
        return v * (1.0 - 1.0 / np.sqrt(np.maximum(q, Q_MIN)))[:, :, None]  # y − (t + v/√q)


class AlgebraicDistance(Distance):
    """Plänkers & Fua's algebraic distance q(Y) = YᵀQY (eq. 1) in metres: r = (ρ/2) q, Q = R D Rᵀ."""

    name = "algebraic"
    size = 1

    def residuals(self, y, n, i, p, kin, ellipsoids, *, jacobian=False, scale=False) -> Residuals:
        y, Q, t, semi = y[i], shape_matrices(ellipsoids, -2.0)[p], ellipsoids.t[p], ellipsoids.semi_axes[p]
        v = y - t
        g = np.einsum("kab,kb->ka", Q, v)
        rho = semi.min(axis=1)
        r = 0.5 * rho * (np.einsum("ka,ka->k", v, g) - 1.0)
        if not jacobian:
            return Residuals(e=r[:, None], B=None)
        # Moving the ellipsoid by (ω, v) is moving y by −(ω × y + v) in its frame: dr = −ρ gᵀ(ω × y + v).
        B = -rho[:, None] * np.concatenate([np.cross(y, g), g], axis=1)  # ω·(y × g) = gᵀ(ω × y)
        J_scale = (r - rho * np.einsum("ka,ka->k", g, y - kin.t[0]))[:, None] if scale else None
        return Residuals(e=r[:, None], B=B[:, None, :], J_scale=J_scale)

    def all_residuals(self, y, n, ellipsoids):
        v = y[:, None, :] - ellipsoids.t[None]  # (I,P,3)
        q = np.einsum("ipa,ipa->ip", v, np.einsum("ipa,pab->ipb", v, shape_matrices(ellipsoids, -2.0)))
        return (0.5 * ellipsoids.semi_axes.min(axis=1)[None, :] * (q - 1.0))[:, :, None]

    def lower_bound(self, y, ellipsoids):
        """0 (P, I): the algebraic distance has no point on the ellipsoid to bound it with."""
        return np.zeros((len(ellipsoids.t), len(y)))


class CompiledNormals(NormalsDistance):
    """The paper's distance with the EM's work in the compiled loops of `compiled` (the tracker's default).

    It also models noise on the normals: with σ_n = `normal_noise_rad` > 0 each pair's covariance is
    Σ_ip = Σ + σ_n² A_ip A_ipᵀ, A_ip = ∂x_ip/∂n_i (`geometry.normal_spread`).
    """

    def e_step(self, y, n, ellipsoids, mixture, log_outlier, normal_noise_rad, previous):
        P = len(ellipsoids.t)
        first = np.zeros(len(y), dtype=int) if previous is None else previous.best
        t, t_outlier, log_likelihood, pairs, weights, best, explained = compiled.e_step(
            y, n, ellipsoids.t, *ellipsoids.shapes, ellipsoids.semi_axes,
            mixture.Sigma, np.log(mixture.pi[:P]), log_outlier, normal_noise_rad**2, np.log(NEGLIGIBLE_POSTERIOR),
            PRUNE_POSTERIOR, first)
        return EStep(t=t, t_outlier=t_outlier, log_likelihood=log_likelihood, pairs=pairs, weights=weights, best=best,
                     explained=explained)

    def log_evidence(self, y, n, chosen, mixture, log_pi, base, normal_noise_rad):
        return compiled.log_evidence(y, n, chosen.t, *chosen.shapes, chosen.semi_axes,
                                     mixture.Sigma, log_pi, base, normal_noise_rad**2, np.log(NEGLIGIBLE_POSTERIOR))

    def hypothesis_scores(self, y, n, hypotheses, mixture, which, base, blocks, normal_noise_rad):
        H = len(hypotheses.t)
        R, t, semi_axes = hypotheses.R[:, which], hypotheses.t[:, which], hypotheses.semi_axes[:, which]
        M, M2 = compiled.shapes(R.reshape(-1, 3, 3), np.ascontiguousarray(semi_axes).reshape(-1, 3))
        stack = (H, len(which))
        return compiled.hypothesis_scores(
            y, n, blocks, np.ascontiguousarray(t), M.reshape(*stack, 3, 3), M2.reshape(*stack, 3, 3),
            np.ascontiguousarray(semi_axes), mixture.Sigma, np.log(mixture.pi[which]), base, normal_noise_rad**2,
            np.log(NEGLIGIBLE_POSTERIOR))

    def pair_residuals(self, y, n, i, p, kin, ellipsoids):
        return compiled.residuals(y, n, i, p, ellipsoids.t, ellipsoids.shapes[0])

    def length_jacobian(self, y, n, i, p, body, kin, pose, e):
        dt, dM = body.length_derivatives(kin)
        return compiled.length_columns(n, i, p, kin.ellipsoids.shapes[0], dt, dM)

    def normal_equations(self, y, n, i, p, W, kin, ellipsoids, scale):
        e, r, Bw, H6, g6, J_scale, norm2 = compiled.normal_equations(
            y, n, i, p, W, ellipsoids.t, ellipsoids.shapes[0], kin.t[0])
        return e, r, Bw, H6, g6, J_scale if scale else None, norm2

    def covariance(self, n, i, p, e, t, ellipsoids, Sigma, normal_noise_rad, max_sigma_m):
        """Without normal noise, `Distance.covariance`. With it, each pair's residual is e_k = z_k + w_k with
        z ~ N(0, Σ) and w ~ N(0, σ_n² A_k²), so that e_k ~ N(0, Σ_k), Σ_k = Σ + σ_n² A_k².

        The maximiser of Q(Σ) = Σ_k t_k ln N(e_k | 0, Σ_k) has no closed form. EM on the hidden z_k,
        Σ' = (1/T) Σ_k t_k E[z zᵀ | e_k] = Σ − Σ (S₁/T) Σ + Σ (S₂/T) Σ (S₁ = Σ_k t_k Σ_k⁻¹,
        S₂ = Σ_k t_k Σ_k⁻¹ e_k e_kᵀ Σ_k⁻¹, T = Σ_k t_k), never lowers Q; it moves slowly where σ_n² A_k²
        dominates Σ_k (flat, wide surfaces), so it is iterated `NOISY_COVARIANCE_ITERATIONS` times
        (`compiled.noisy_covariance`). The moment estimate (1/T) Σ_k t_k (e_k e_kᵀ − σ_n² A_k²) does not
        maximise Q: it shrinks Σ's narrow axis iteration after iteration while ln P(Y | Λ) falls.
        """
        if not normal_noise_rad > 0.0:
            return super().covariance(n, i, p, e, t, ellipsoids, Sigma, normal_noise_rad, max_sigma_m)
        M, M2 = ellipsoids.shapes
        return bound_covariance(compiled.noisy_covariance(n, i, p, e, t, M, M2, normal_noise_rad**2, Sigma,
                                                          NOISY_COVARIANCE_ITERATIONS), max_sigma_m)


# The distance each name runs as: the paper's in compiled code, the others in numpy.
DISTANCES: dict[str, Distance] = {"normals": CompiledNormals(), "points": PointsDistance(),
                                  "algebraic": AlgebraicDistance()}


def distance_named(name: str) -> Distance:
    """The distance called `name` (one of `DISTANCES`)."""
    if name not in DISTANCES:
        raise ValueError(f"distance={name!r}, expected one of {tuple(DISTANCES)}")
    return DISTANCES[name]
