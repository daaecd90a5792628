"""Ellipsoid geometry shared by the distances: shape matrices, the point of eq. (4) and its derivatives.

An ellipsoid p is posed by its rotation R_p, centre t_p and semi-axes (`body.Ellipsoids`); its shape
enters the distances as R diag(semi_axes**power) Rᵀ (`shape_matrices`): M = R D⁻¹ Rᵀ for the point whose
outward normal is parallel to n (Horaud et al. 2009 eq. 4), Q = R D Rᵀ for the quadric of eq. (1). Symmetric
3 × 3 matrices of many pairs are handled as their six distinct entries, (K,) each, which keeps the pairs'
elementwise work on contiguous memory.
"""

from __future__ import annotations

import numpy as np

from stages.tracking.body import Ellipsoids, skew

# Order of the six distinct entries of a symmetric 3 × 3 matrix when it is kept as separate arrays.
SYMMETRIC_ENTRIES = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
# q_p(y) is the squared "ellipsoidal radius" of y; at the ellipsoid's centre the radial projection is
# undefined. Data that deep inside a limb are noise; clamping keeps x finite and lets EM push them out.
Q_MIN = 1e-6


def shape_matrices(ellipsoids: Ellipsoids, power: float) -> np.ndarray:
    """R diag(semi_axes**power) Rᵀ (E, 3, 3): D⁻¹ for power 2 (M of eq. 4), D for power −2 (Q of eq. 1)."""
    R = ellipsoids.R
    return np.einsum("eab,eb,ecb->eac", R, ellipsoids.semi_axes**power, R)


def ellipsoid_point(n: np.ndarray, R: np.ndarray, t: np.ndarray, semi_axes: np.ndarray) -> np.ndarray:
    """The ellipsoid point whose outward normal is parallel to n, Horaud et al. 2009 eq. (4).

    Parameters
    ----------
    n : (K, 3) float
        Unit directions.
    R, t, semi_axes : (K, 3, 3), (K, 3), (K, 3) float
        Ellipsoid of each row.
    """
    return normal_point(n, entries(shape_matrices(Ellipsoids(R=R, t=t, semi_axes=semi_axes), 2.0)), t, False)[0]


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

    In `SYMMETRIC_ENTRIES` order. A² = λ² (M² − λ² (w uᵀ + u wᵀ) + λ⁴ |u|² u uᵀ) with u = M n, w = M u,
    since A = λ (M − λ² u uᵀ) is symmetric.
    """
    M, M2 = entries(shape_matrices(ellipsoids, 2.0), p), entries(shape_matrices(ellipsoids, 4.0), p)
    n = (n[:, 0], n[:, 1], n[:, 2])
    u = symmetric_times(M, n)
    w = symmetric_times(M, u)
    lam2 = 1.0 / (n[0] * u[0] + n[1] * u[1] + n[2] * u[2])  # λ² of eq. (4)
    quartic = lam2**2 * (u[0] * u[0] + u[1] * u[1] + u[2] * u[2])  # λ⁴ |u|²
    return tuple(lam2 * (m2 - lam2 * (w[a] * u[b] + u[a] * w[b]) + quartic * u[a] * u[b])
                 for m2, (a, b) in zip(M2, SYMMETRIC_ENTRIES, strict=True))


def symmetric_matrices(entries: tuple[np.ndarray, ...]) -> np.ndarray:
    """Symmetric matrices (K, 3, 3) from their six distinct entries (K,) in `SYMMETRIC_ENTRIES` order."""
    m00, m11, m22, m01, m02, m12 = entries
    return np.stack([m00, m01, m02, m01, m11, m12, m02, m12, m22], axis=1).reshape(-1, 3, 3)


def entries(A: np.ndarray, p: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """The six distinct entries of symmetric matrices A (P, 3, 3), each gathered at p (K,) when given."""
    return tuple(A[:, a, b] if p is None else A[:, a, b][p] for a, b in SYMMETRIC_ENTRIES)


def symmetric_times(M: tuple[np.ndarray, ...], v) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """M v for symmetric M given by its six distinct entries and v by its three components."""
    m00, m11, m22, m01, m02, m12 = M
    return (m00 * v[0] + m01 * v[1] + m02 * v[2], m01 * v[0] + m11 * v[1] + m12 * v[2],
            m02 * v[0] + m12 * v[1] + m22 * v[2])


def normal_point(n, M, t, jacobian):
    """x = λ M n + t with M = R D⁻¹ Rᵀ (eq. 4), and ∂x/∂y = 0, ∂x/∂n = λ (M − λ² (Mn)(Mn)ᵀ) if `jacobian`.

    M is given by its six distinct entries (K,) each (`entries`).
    """
    u = symmetric_times(M, (n[:, 0], n[:, 1], n[:, 2]))
    lam = 1.0 / np.sqrt(n[:, 0] * u[0] + n[:, 1] * u[1] + n[:, 2] * u[2])  # eq. (4); n·Mn >= min(semi)² > 0
    x = np.stack([lam * u[0], lam * u[1], lam * u[2]], axis=1) + t
    if not jacobian:
        return x, None, None
    lam3 = lam * lam * lam
    return x, None, symmetric_matrices(tuple(lam * m - lam3 * u[a] * u[b]
                                             for m, (a, b) in zip(M, SYMMETRIC_ENTRIES, strict=True)))


def radial_point(y, Q, t):
    """x = t + v / sqrt(q), v = y − t, q = vᵀ Q v with Q = R D Rᵀ, and ∂x/∂y = (I − v (Qv)ᵀ / q) / sqrt(q)."""
    v = y - t
    g = np.einsum("kab,kb->ka", Q, v)  # half the gradient of q
    q = np.maximum(np.einsum("ka,ka->k", v, g), Q_MIN)
    s = 1.0 / np.sqrt(q)
    x = t + s[:, None] * v
    A_y = s[:, None, None] * (np.eye(3) - v[:, :, None] * g[:, None, :] / q[:, None, None])
    return x, A_y, None


def rigid_derivative(x, y, n, A_y, A_n):
    """dx/d(ω, v) (K, 3, 6) of a point x that depends on the datum (y, n) (`distances` module docstring).

    dx = −[x]× ω + v − A_y (−[y]× ω + v) − A_n (−[n]× ω), with A_y = ∂x/∂y and A_n = ∂x/∂n (None: zero).
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
