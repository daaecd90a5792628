"""Residuals between observations and posed ellipsoids, with their derivatives w.r.t. the pose.

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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.tracking.body import Ellipsoids, Kinematics, skew

DISTANCES = ("normals", "points", "algebraic")
# Order of the six distinct entries of a symmetric 3 × 3 matrix when it is kept as separate arrays.
SYMMETRIC_ENTRIES = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
# q_p(y) is the squared "ellipsoidal radius" of y; at the ellipsoid's centre the radial projection is
# undefined. Data that deep inside a limb are noise; clamping keeps x finite and lets EM push them out.
_Q_MIN = 1e-6


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


def residual_size(distance: str) -> int:
    """Dimension k of one residual for a distance name."""
    return 1 if distance == "algebraic" else 3


def residuals(y: np.ndarray, n: np.ndarray, i: np.ndarray, p: np.ndarray, kin: Kinematics,
              ellipsoids: Ellipsoids, *, distance: str = "normals",
              jacobian: bool = False, scale: bool = False) -> Residuals:
    """Residuals (and optionally their pose Jacobians) of the pairs (i[k], p[k]).

    Parameters
    ----------
    y, n : (I, 3) float
        Observed points (metres) and unit outward normals.
    i, p : (K,) int
        Observation and ellipsoid index of every pair.
    kin, ellipsoids
        The body's kinematics and posed ellipsoids at the current pose.
    distance : {"normals", "points", "algebraic"}
    jacobian : bool
        Also return the rigid derivatives B (K, k, 6) (see `Residuals`).
    scale : bool
        Also return de/d(ln s) (K, k) for the body's height: scaling every ellipsoid by s about the
        root c is scaling the datum by 1/s about c, so dx/d(ln s) = (x − c) − (∂x/∂y)(y − c).
    """
    if distance not in DISTANCES:
        raise ValueError(f"distance={distance!r}, expected one of {DISTANCES}")
    y_k, n_k, t = y[i], n[i], ellipsoids.t[p]
    if distance == "algebraic":
        Q = shape_matrices(ellipsoids, -2.0)[p]
        return _algebraic(y_k, Q, t, ellipsoids.semi_axes[p], kin, jacobian, scale)
    if distance == "normals":
        x, A_y, A_n = _normal_point(n_k, _entries(shape_matrices(ellipsoids, 2.0), p), t, jacobian)
    else:
        x, A_y, A_n = _radial_point(y_k, shape_matrices(ellipsoids, -2.0)[p], t)
    e = y_k - x
    if not jacobian:
        return Residuals(e=e, B=None)
    J_scale = None
    if scale:
        c = kin.t[0]
        J_scale = -(x - c) if A_y is None else -(x - c) + np.einsum("kab,kb->ka", A_y, y_k - c)
    return Residuals(e=e, B=-_rigid_derivative(x, y_k, n_k, A_y, A_n), J_scale=J_scale)


def all_residuals(y: np.ndarray, n: np.ndarray, ellipsoids: Ellipsoids, *,
                  distance: str = "normals") -> np.ndarray:
    """Residuals (I, P, k) of every observation against every ellipsoid (the E-step's dense case).

    Same values as `residuals` on all pairs, computed by broadcasting instead of gathering.
    """
    if distance not in DISTANCES:
        raise ValueError(f"distance={distance!r}, expected one of {DISTANCES}")
    P = len(ellipsoids.t)
    if distance == "normals":
        M = shape_matrices(ellipsoids, 2.0)  # (P,3,3) symmetric, so (nᵀ M)ᵀ = M n
        u = (n @ M.transpose(1, 0, 2).reshape(3, 3 * P)).reshape(-1, P, 3)  # (I,P,3): one matrix product
        lam = 1.0 / np.sqrt(np.einsum("ipa,ia->ip", u, n))  # eq. (4)
        return y[:, None, :] - ellipsoids.t[None] - lam[:, :, None] * u
    v = y[:, None, :] - ellipsoids.t[None]  # (I,P,3)
    q = np.einsum("ipa,ipa->ip", v, np.einsum("ipa,pab->ipb", v, shape_matrices(ellipsoids, -2.0)))
    if distance == "points":
        return v * (1.0 - 1.0 / np.sqrt(np.maximum(q, _Q_MIN)))[:, :, None]  # y − (t + v/√q)
    return (0.5 * ellipsoids.semi_axes.min(axis=1)[None, :] * (q - 1.0))[:, :, None]


def normal_spread(n: np.ndarray, ellipsoids: Ellipsoids, p: np.ndarray | None = None) -> np.ndarray:
    """A Aᵀ with A = ∂x_ip/∂n_i of eq. (4): how a tilt of the normal moves the ellipsoid point.

    A tilt of the unit normal by a small angle θ about an axis perpendicular to n moves n by θ w, w a
    unit tangent; with θ ~ N(0, σ_n²) about either tangent axis, cov(dn) = σ_n² (I − n nᵀ) and
    cov(x_ip) = σ_n² A (I − n nᵀ) Aᵀ = σ_n² A Aᵀ, since A n = 0 (x depends on n's direction only).
    On an elongated ellipsoid x slides along the long axis by about a²/b per radian.

    Parameters
    ----------
    n : (I, 3) float
        Unit normals.
    ellipsoids : Ellipsoids
        The P posed ellipsoids.
    p : (I,) int, optional
        One ellipsoid per normal (pairs); default every normal against every ellipsoid.

    Returns
    -------
    (I, 3, 3) float for pairs, (I, P, 3, 3) otherwise; symmetric positive semi-definite, m² per rad².
    """
    if p is not None:
        return symmetric_matrices(normal_spread_entries(n, ellipsoids, p))
    M, M2 = shape_matrices(ellipsoids, 2.0), shape_matrices(ellipsoids, 4.0)  # M² = R diag(semi_axes⁴) Rᵀ
    u = np.einsum("pab,ib->ipa", M, n)  # (I,P,3)
    w = np.einsum("pab,ib->ipa", M2, n)  # M u = M² n
    lam2 = (1.0 / np.einsum("ipa,ia->ip", u, n))[..., None, None]  # λ² of eq. (4)
    wu = w[..., :, None] * u[..., None, :]
    uu = u[..., :, None] * u[..., None, :]
    # A = λ (M − λ² u uᵀ) is symmetric, so A Aᵀ = A² = λ² (M² − λ² (w uᵀ + u wᵀ) + λ⁴ |u|² u uᵀ)
    return lam2 * (M2[None] - lam2 * (wu + wu.swapaxes(-1, -2)) + lam2**2 * (u * u).sum(-1)[..., None, None] * uu)


def normal_spread_entries(n: np.ndarray, ellipsoids: Ellipsoids, p: np.ndarray) -> tuple[np.ndarray, ...]:
    """`normal_spread` of the pairs (n_k, ellipsoid p_k) as its six distinct entries (K,) each.

    In `SYMMETRIC_ENTRIES` order; separate (K,) arrays keep the pairs' elementwise work on contiguous
    memory. A² = λ² (M² − λ² (w uᵀ + u wᵀ) + λ⁴ |u|² u uᵀ) with u = M n, w = M u, since A = λ (M − λ² u uᵀ)
    is symmetric.
    """
    M, M2 = _entries(shape_matrices(ellipsoids, 2.0), p), _entries(shape_matrices(ellipsoids, 4.0), p)
    n = (n[:, 0], n[:, 1], n[:, 2])
    u = _symmetric_times(M, n)
    w = _symmetric_times(M, u)
    lam2 = 1.0 / (n[0] * u[0] + n[1] * u[1] + n[2] * u[2])  # λ² of eq. (4)
    quartic = lam2**2 * (u[0] * u[0] + u[1] * u[1] + u[2] * u[2])  # λ⁴ |u|²
    return tuple(lam2 * (m2 - lam2 * (w[a] * u[b] + u[a] * w[b]) + quartic * u[a] * u[b])
                 for m2, (a, b) in zip(M2, SYMMETRIC_ENTRIES, strict=True))


def symmetric_matrices(entries: tuple[np.ndarray, ...]) -> np.ndarray:
    """Symmetric matrices (K, 3, 3) from their six distinct entries (K,) in `SYMMETRIC_ENTRIES` order."""
    m00, m11, m22, m01, m02, m12 = entries
    return np.stack([m00, m01, m02, m01, m11, m12, m02, m12, m22], axis=1).reshape(-1, 3, 3)


def residual_lower_bound(y: np.ndarray, ellipsoids: Ellipsoids, *, distance: str = "normals") -> np.ndarray:
    """A lower bound on every pair's |e_ip|² (P, I), from the centres' distances alone.

    For the point distances x_ip lies on ellipsoid p, within its largest semi-axis a_p of t_p, so
    |e| ≥ |y − t_p| − a_p; the algebraic distance has no such point, and its bound is 0. Ellipsoid-major
    (P, I), the order of the pairs everywhere else.
    """
    t = ellipsoids.t
    if distance == "algebraic":
        return np.zeros((len(t), len(y)))
    centre = (t * t).sum(1)[:, None] - 2.0 * t @ y.T + (y * y).sum(1)  # |y − t|²
    gap = np.maximum(np.sqrt(np.maximum(centre, 0.0)) - ellipsoids.semi_axes.max(axis=1)[:, None], 0.0)
    return gap * gap


def ellipsoid_point(n: np.ndarray, R: np.ndarray, t: np.ndarray, semi_axes: np.ndarray) -> np.ndarray:
    """The ellipsoid point whose outward normal is parallel to n, Horaud et al. 2009 eq. (4).

    Parameters
    ----------
    n : (K, 3) float
        Unit directions.
    R, t, semi_axes : (K, 3, 3), (K, 3), (K, 3) float
        Ellipsoid of each row.
    """
    return _normal_point(n, _entries(shape_matrices(Ellipsoids(R=R, t=t, semi_axes=semi_axes), 2.0)), t, False)[0]


def shape_matrices(ellipsoids: Ellipsoids, power: float) -> np.ndarray:
    """R diag(semi_axes**power) Rᵀ (E, 3, 3): D⁻¹ for power 2 (M of eq. 4), D for power −2 (Q of eq. 1)."""
    R = ellipsoids.R
    return np.einsum("eab,eb,ecb->eac", R, ellipsoids.semi_axes**power, R)


def _normal_point(n, M, t, jacobian):
    """x = λ M n + t with M = R D⁻¹ Rᵀ, and ∂x/∂y = 0, ∂x/∂n = λ (M − λ² (Mn)(Mn)ᵀ) if `jacobian`.

    M is given by its six distinct entries (K,) each (`_entries`).
    """
    u = _symmetric_times(M, (n[:, 0], n[:, 1], n[:, 2]))
    lam = 1.0 / np.sqrt(n[:, 0] * u[0] + n[:, 1] * u[1] + n[:, 2] * u[2])  # eq. (4); n·Mn >= min(semi)² > 0
    x = np.stack([lam * u[0], lam * u[1], lam * u[2]], axis=1) + t
    if not jacobian:
        return x, None, None
    lam3 = lam * lam * lam
    return x, None, symmetric_matrices(tuple(lam * m - lam3 * u[a] * u[b]
                                             for m, (a, b) in zip(M, SYMMETRIC_ENTRIES, strict=True)))


def _entries(A: np.ndarray, p: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """The six distinct entries of symmetric matrices A (P, 3, 3), each gathered at p (K,) when given."""
    return tuple(A[:, a, b] if p is None else A[:, a, b][p] for a, b in SYMMETRIC_ENTRIES)


def _symmetric_times(M: tuple[np.ndarray, ...], v) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """M v for symmetric M given by its six distinct entries and v by its three components."""
    m00, m11, m22, m01, m02, m12 = M
    return (m00 * v[0] + m01 * v[1] + m02 * v[2], m01 * v[0] + m11 * v[1] + m12 * v[2],
            m02 * v[0] + m12 * v[1] + m22 * v[2])


def _radial_point(y, Q, t):
    """x = t + v / sqrt(q), v = y − t, q = vᵀ Q v with Q = R D Rᵀ, and ∂x/∂y = (I − v (Qv)ᵀ / q) / sqrt(q)."""
    v = y - t
    g = np.einsum("kab,kb->ka", Q, v)  # half the gradient of q
    q = np.maximum(np.einsum("ka,ka->k", v, g), _Q_MIN)
    s = 1.0 / np.sqrt(q)
    x = t + s[:, None] * v
    A_y = s[:, None, None] * (np.eye(3) - v[:, :, None] * g[:, None, :] / q[:, None, None])
    return x, A_y, None


def _rigid_derivative(x, y, n, A_y, A_n):
    """dx/d(ω, v) (K, 3, 6) from the rigid-motion identity in the module docstring.

    dx = −[x]× ω + v − A_y (−[y]× ω + v) − A_n (−[n]× ω).
    """
    D = np.empty(x.shape + (6,))
    D[:, :, :3] = -skew(x)
    D[:, :, 3:] = np.eye(3)
    if A_y is not None:
        D[:, :, :3] += A_y @ skew(y)
        D[:, :, 3:] -= A_y
    if A_n is not None:
        D[:, :, :3] += A_n @ skew(n)
    return D


def _algebraic(y, Q, t, semi, kin, jacobian, scale):
    """Plänkers & Fua's algebraic distance q(Y) = YᵀQY (eq. 1) in metres: r = (ρ/2) q, Q = R D Rᵀ."""
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
