"""Compiled inner loops of EM for the paper's distance (points and normals, Horaud et al. 2009 eq. 4).

Each EM iteration visits every datum-ellipsoid pair a few times (posteriors, normal equations, step
acceptance); as numpy expressions that is dozens of passes over (I × P) temporaries and hundreds of small
calls per iteration, which is what bounded the tracker's frame rate. Here each pass is one loop over the
pairs with the pair's 3 × 3 algebra written out, compiled by numba (cached on disk, so only the first run
on a machine pays for compilation). The maths is the same as the numpy reference in `distances` and `em`,
against which the tests check these functions:

- x_ip = t_p + λ M_p n_i with M_p = R_p diag(a_p²) R_pᵀ and λ = (n_iᵀ M_p n_i)^(-1/2) (eq. 4);
- A_ip = ∂x_ip/∂n_i = λ (M_p − λ² u uᵀ), u = M_p n_i (symmetric; `geometry.normal_spread`);
- Σ_ip = Σ + σ_n² A_ip² and the component density π_p N(y_i | x_ip, Σ_ip) (eqs. 11-13);
- the rigid derivative de/d(ω, v) = [x]× − A_ip [n_i]×, −I (`distances` module docstring).

Ellipsoid shapes enter as M (P, 3, 3) and M² (P, 3, 3) (`shapes`); a symmetric 3 × 3 sum is returned as its
six distinct entries in `geometry.SYMMETRIC_ENTRIES` order (00, 11, 22, 01, 02, 12). Every loop runs on one
core: numba's threads were tried, and on a machine shared with other work they made the tracker several
times slower. The loops stay in this one module although it is long: numba's disk cache of a function is
invalidated only when its own file changes, not when a helper compiled into it from another file does,
and the warm-up (`python -m pipeline warmup`) stamps this one file.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_LOG_2PI = math.log(2.0 * math.pi)


# The pair helpers take whole arrays and indices, never row views: a view costs reference counting.


@njit(cache=True, error_model="numpy")
def _normal_direction(n, i, M, p):
    """u = M_p n_i and λ = (n_iᵀ M_p n_i)^(-1/2) of eq. (4)."""
    n0, n1, n2 = n[i, 0], n[i, 1], n[i, 2]
    u0 = M[p, 0, 0] * n0 + M[p, 0, 1] * n1 + M[p, 0, 2] * n2
    u1 = M[p, 1, 0] * n0 + M[p, 1, 1] * n1 + M[p, 1, 2] * n2
    u2 = M[p, 2, 0] * n0 + M[p, 2, 1] * n1 + M[p, 2, 2] * n2
    return u0, u1, u2, 1.0 / math.sqrt(n0 * u0 + n1 * u1 + n2 * u2)


@njit(cache=True, error_model="numpy")
def _normal_point(n, i, M, t, p):
    """u = M_p n_i, λ and x_ip = t_p + λ u of eq. (4)."""
    u0, u1, u2, lam = _normal_direction(n, i, M, p)
    return u0, u1, u2, lam, t[p, 0] + lam * u0, t[p, 1] + lam * u1, t[p, 2] + lam * u2


@njit(cache=True, error_model="numpy")
def _spread(M, M2, p, u0, u1, u2, lam):
    """A² = λ² (M² − λ² (w uᵀ + u wᵀ) + λ⁴ |u|² u uᵀ), w = M u, as six entries (`geometry.normal_spread`)."""
    w0 = M[p, 0, 0] * u0 + M[p, 0, 1] * u1 + M[p, 0, 2] * u2
    w1 = M[p, 1, 0] * u0 + M[p, 1, 1] * u1 + M[p, 1, 2] * u2
    w2 = M[p, 2, 0] * u0 + M[p, 2, 1] * u1 + M[p, 2, 2] * u2
    lam2 = lam * lam
    quartic = lam2 * lam2 * (u0 * u0 + u1 * u1 + u2 * u2)
    s00 = lam2 * (M2[p, 0, 0] - lam2 * 2.0 * w0 * u0 + quartic * u0 * u0)
    s11 = lam2 * (M2[p, 1, 1] - lam2 * 2.0 * w1 * u1 + quartic * u1 * u1)
    s22 = lam2 * (M2[p, 2, 2] - lam2 * 2.0 * w2 * u2 + quartic * u2 * u2)
    s01 = lam2 * (M2[p, 0, 1] - lam2 * (w0 * u1 + u0 * w1) + quartic * u0 * u1)
    s02 = lam2 * (M2[p, 0, 2] - lam2 * (w0 * u2 + u0 * w2) + quartic * u0 * u2)
    s12 = lam2 * (M2[p, 1, 2] - lam2 * (w1 * u2 + u1 * w2) + quartic * u1 * u2)
    return s00, s11, s22, s01, s02, s12


@njit(cache=True, error_model="numpy")
def _adjugate(a, d, g, b, c, f):
    """Cofactors (c00, c01, c02, c11, c12, c22) and determinant of the symmetric 3 × 3 matrix
    [[a, b, c], [b, d, f], [c, f, g]]: its inverse is the cofactor matrix over the determinant."""
    c00, c01, c02 = d * g - f * f, c * f - b * g, b * f - c * d
    c11, c12, c22 = a * g - c * c, b * c - a * f, a * d - b * b
    return c00, c01, c02, c11, c12, c22, a * c00 + b * c01 + c * c02


@njit(cache=True, error_model="numpy")
def e_step(y, n, t, M, M2, semi_axes, Sigma, log_pi, log_outlier, noise2, log_negligible, prune, first):
    """Posteriors t_ip (eq. 13), ln P(Y | Λ) (eq. 12) and the M-step's pairs, for Σ_ip = Σ + σ_n² A_ip².

    A pair is skipped (t_ip = 0) when a lower bound on its Mahalanobis distance shows its joint density
    below `mixture.NEGLIGIBLE_POSTERIOR` times the largest term of the datum's evidence met so far, the outlier
    term or a pair's (det Σ_ip ≥ det Σ bounds the rest); the skipped pairs then change the evidence by
    less than P times that fraction. Visiting first the ellipsoid that explained the datum best in the
    previous iteration (`first`) makes that largest term a real pair's at once. Σ_ip ⪯
    C = c I + σ_n² A², c Σ's largest eigenvalue, of which n_i is an eigenvector with eigenvalue c (A n = 0)
    and whose other eigenvalues are at most c + σ_n² r_p², r_p the ellipsoid's largest radius of
    curvature (‖A‖ ≤ r_p: A is the inverse of the shape operator on the tangent plane), so that
    eᵀ Σ_ip⁻¹ e ≥ (nᵀ e)² / c + (|e|² − (nᵀ e)²) / (c + σ_n² r_p²). Before even e is computed, x_ip lies
    within the largest semi-axis a_p of t_p, so |e| ≥ |y − t_p| − a_p; after it, the pair's own
    ‖A‖² ≤ tr A² = λ² (tr M² − 2 λ² nᵀ M³ n + λ⁴ (nᵀ M² n)²) replaces r_p² at a third of Σ_ip's cost.

    Parameters
    ----------
    y, n : (I, 3) float
        Points and unit normals.
    t, M, M2, semi_axes : (P, 3), (P, 3, 3), (P, 3, 3), (P, 3) float
        Ellipsoid centres, M_p, M_p² (`shapes`) and semi-axes.
    Sigma : (3, 3) float
    log_pi : (P,) float
        ln π_p of the ellipsoids.
    log_outlier : float
        ln (π_{P+1} / V).
    noise2 : float
        σ_n² (rad²).
    log_negligible : float
        ln of that fraction (`mixture.NEGLIGIBLE_POSTERIOR`).
    prune : float
        Pairs with t_ip above this are returned for the M-step.
    first : (I,) int
        Ellipsoid to visit first for each datum (any, when there is no better guess).

    Returns
    -------
    t_ip : (I, P); t_outlier : (I,); log_likelihood : float;
    pairs : (2, K) int (datum, ellipsoid), sorted by ellipsoid;
    weights : (K, 3, 3) lower-triangular W with t_ip Σ_ip⁻¹ = W Wᵀ (the M-step's whitening, eq. 14);
    best : (I,) int, each datum's ellipsoid of largest posterior (the next E-step's `first`);
    explained : (P,) Σ_i t_ip, summed in datum order (the bits of numpy's t_ip.sum(axis=0)).
    """
    I = y.shape[0]
    reach, largest = _bounds(semi_axes, Sigma, log_pi, log_negligible, noise2)
    log_evidence, posterior, pairs, weights, best, explained = _mixture(
        y, n, t, M, M2, reach, Sigma, largest, log_pi, np.full(I, log_outlier), noise2, prune, True, first)
    return posterior, np.exp(log_outlier - log_evidence), log_evidence.sum(), pairs, weights, best, explained


@njit(cache=True, error_model="numpy")
def log_evidence(y, n, t, M, M2, semi_axes, Sigma, log_pi, log_base, noise2, log_negligible):
    """ln(exp(b_i) + Σ_p π_p N(y_i | x_ip, Σ_ip)) per datum (I,), pairs skipped as in `e_step`.

    With b_i = ln(π_{P+1} / V) these are the terms of ln P(Y | Λ) (eq. 12); with b_i the evidence of the
    other ellipsoids (this function on them), they add a few ellipsoids to an evidence computed once,
    which is how limb hypotheses are scored with the rest of the body fixed.
    """
    first = np.zeros(y.shape[0], np.int64)
    reach, largest = _bounds(semi_axes, Sigma, log_pi, log_negligible, noise2)
    return _mixture(y, n, t, M, M2, reach, Sigma, largest, log_pi, log_base, noise2, 1.0, False, first)[0]


@njit(cache=True, error_model="numpy")
def hypothesis_scores(y, n, blocks, t, M, M2, semi_axes, Sigma, log_pi, log_base, noise2, log_negligible):
    """Σ over each block of data of `log_evidence`, for H posed sets of ellipsoids at once: (H, B).

    `t`, `M`, `M2` and `semi_axes` are `log_evidence`'s with a leading hypothesis axis (H, P, ...); data
    block b is rows blocks[b]:blocks[b + 1] of y and n (the data turned to one heading, say).
    """
    H, B = t.shape[0], blocks.shape[0] - 1
    first = np.zeros(y.shape[0], np.int64)
    sums = np.zeros((H, B))
    for h in range(H):
        reach, largest = _bounds(semi_axes[h], Sigma, log_pi, log_negligible, noise2)
        terms = _mixture(y, n, t[h], M[h], M2[h], reach, Sigma, largest, log_pi, log_base, noise2, 1.0, False,
                         first)[0]
        for b in range(B):
            sums[h, b] = terms[blocks[b]:blocks[b + 1]].sum()
    return sums


@njit(cache=True, error_model="numpy")
def _mixture(y, n, t, M, M2, reach, Sigma, largest, log_pi, log_base, noise2, prune, posteriors, first):
    """Per datum ln(exp(b_i) + Σ_p π_p N_ip) and, with `posteriors`, t_ip, the pairs above `prune` and
    Σ_i t_ip per ellipsoid.

    The pair's algebra is written out in this one loop rather than in a helper: a helper taking arrays
    that LLVM does not inline costs more than the arithmetic.
    """
    I, P = y.shape[0], t.shape[0]
    evidence_log = np.empty(I)
    posterior = np.zeros((I, P) if posteriors else (0, P))
    # One datum's pairs: ln π_p N_ip and Σ_ip⁻¹ by ellipsoid; the ellipsoids not skipped, in visiting order,
    # and their π_p N_ip / e^peak.
    log_joint, inverse = np.empty(P), np.empty((P, 6))
    passed, scaled = np.empty(P, np.int64), np.empty(P)
    # Pairs above `prune` in datum order; only the first K rows of these buffers are ever touched.
    room = I * P if posteriors else 0
    kept_i, kept_p, kept_precision = np.empty(room, np.int64), np.empty(room, np.int64), np.empty((room, 6))
    per_ellipsoid = np.zeros(P + 1, np.int64)
    explained = np.zeros(P)
    best = first.copy()
    K = 0
    inverse_largest = 1.0 / largest
    inverse_across = np.empty(P)  # 1 / (c + σ_n² r_p²), r_p the largest radius of curvature
    for p in range(P):
        inverse_across[p] = 1.0 / reach[p, 2]
    for i in range(I):
        peak = log_base[i]  # the largest term of the evidence met so far
        m = 0  # pairs of this datum not skipped: passed[:m]
        p = first[i] - 1  # the ellipsoids from first[i] on, wrapping round (no integer division per pair)
        for _ in range(P):
            p = p + 1 if p + 1 < P else 0
            limit = reach[p, 1] - 2.0 * peak  # squared Mahalanobis distance of a negligible pair
            d0, d1, d2 = y[i, 0] - t[p, 0], y[i, 1] - t[p, 1], y[i, 2] - t[p, 2]
            gap = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) - reach[p, 0]
            if gap > 0.0 and gap * gap > limit * reach[p, 2]:
                continue
            u0, u1, u2, lam, x0, x1, x2 = _normal_point(n, i, M, t, p)
            e0, e1, e2 = y[i, 0] - x0, y[i, 1] - x1, y[i, 2] - x2
            along = n[i, 0] * e0 + n[i, 1] * e1 + n[i, 2] * e2  # n is an eigenvector of Σ_ip ⪯ c I + σ_n² A²
            across = e0 * e0 + e1 * e1 + e2 * e2 - along * along
            if along * along * inverse_largest + across * inverse_across[p] > limit:
                continue
            s00 = s11 = s22 = s01 = s02 = s12 = 0.0  # A² (needed only with normal noise)
            if noise2 > 0.0:
                w0 = M[p, 0, 0] * u0 + M[p, 0, 1] * u1 + M[p, 0, 2] * u2  # ‖A‖² ≤ tr A² (A has rank 2)
                w1 = M[p, 1, 0] * u0 + M[p, 1, 1] * u1 + M[p, 1, 2] * u2
                w2 = M[p, 2, 0] * u0 + M[p, 2, 1] * u1 + M[p, 2, 2] * u2
                lam2 = lam * lam
                u_u = u0 * u0 + u1 * u1 + u2 * u2
                trace = lam2 * (reach[p, 3] - 2.0 * lam2 * (u0 * w0 + u1 * w1 + u2 * w2) + lam2 * lam2 * u_u * u_u)
                if along * along * inverse_largest + across / (largest + noise2 * trace) > limit:
                    continue
                s00, s11, s22, s01, s02, s12 = _spread(M, M2, p, u0, u1, u2, lam)
            a, d, g = Sigma[0, 0] + noise2 * s00, Sigma[1, 1] + noise2 * s11, Sigma[2, 2] + noise2 * s22
            b, c, f = Sigma[0, 1] + noise2 * s01, Sigma[0, 2] + noise2 * s02, Sigma[1, 2] + noise2 * s12
            c00, c01, c02, c11, c12, c22, det = _adjugate(a, d, g, b, c, f)
            h = 1.0 / det
            quadratic = (c00 * e0 * e0 + c11 * e1 * e1 + c22 * e2 * e2
                         + 2.0 * (c01 * e0 * e1 + c02 * e0 * e2 + c12 * e1 * e2)) * h
            log_joint[p] = log_pi[p] - 0.5 * (quadratic + math.log(det) + 3.0 * _LOG_2PI)
            if log_joint[p] > peak:
                peak, best[i] = log_joint[p], p
            inverse[p, 0], inverse[p, 1], inverse[p, 2] = c00 * h, c11 * h, c22 * h
            inverse[p, 3], inverse[p, 4], inverse[p, 5] = c01 * h, c02 * h, c12 * h
            passed[m] = p
            m += 1
        evidence = math.exp(log_base[i] - peak)  # log-sum-exp over the classes, eqs. (12)-(13)
        for k in range(m):
            scaled[k] = math.exp(log_joint[passed[k]] - peak)
            evidence += scaled[k]
        evidence_log[i] = peak + math.log(evidence)
        if not posteriors:
            continue
        for k in range(m):
            p = passed[k]
            posterior[i, p] = scaled[k] / evidence
            explained[p] += posterior[i, p]
            if posterior[i, p] > prune:
                kept_i[K], kept_p[K] = i, p
                for j in range(6):
                    kept_precision[K, j] = inverse[p, j]
                per_ellipsoid[p + 1] += 1
                K += 1
    start = np.cumsum(per_ellipsoid)  # counting sort of the kept pairs by ellipsoid (stable in i)
    pairs = np.empty((2, K), dtype=np.int64)
    weights = np.zeros((K, 3, 3))
    for k in range(K):
        slot = start[kept_p[k]]
        start[kept_p[k]] += 1
        pairs[0, slot], pairs[1, slot] = kept_i[k], kept_p[k]
        _cholesky(kept_precision[k], posterior[kept_i[k], kept_p[k]], weights, slot)
    return evidence_log, posterior, pairs, weights, best, explained


@njit(cache=True, error_model="numpy")
def _bounds(semi_axes, Sigma, log_pi, log_negligible, noise2):
    """The pruning bounds of `e_step` per ellipsoid (P, 4) and c, Σ's largest eigenvalue.

    Columns: a_p; ρ_p = −2 (ln negligible − ln π_p − ln N₀), N₀ = (2π)^(−3/2) det Σ^(−1/2) the Gaussian's
    peak at Σ, so that a pair whose squared Mahalanobis distance exceeds ρ_p − 2 m is negligible against
    a term m; c + σ_n² r_p² with r_p = a_max² / a_min the largest radius of curvature; tr M_p² = Σ a⁴.
    """
    a, d, g, b, c, f = Sigma[0, 0], Sigma[1, 1], Sigma[2, 2], Sigma[0, 1], Sigma[0, 2], Sigma[1, 2]
    det = a * (d * g - f * f) + b * (c * f - b * g) + c * (b * f - c * d)
    log_peak = -0.5 * (math.log(det) + 3.0 * _LOG_2PI)
    # largest eigenvalue of a symmetric 3 × 3 matrix, closed form (trigonometric solution of the cubic)
    mean = (a + d + g) / 3.0
    off = b * b + c * c + f * f
    spread = math.sqrt(((a - mean) ** 2 + (d - mean) ** 2 + (g - mean) ** 2 + 2.0 * off) / 6.0)
    largest = mean
    if spread > 0.0:
        ba, bd, bg = (a - mean) / spread, (d - mean) / spread, (g - mean) / spread
        bb, bc, bf = b / spread, c / spread, f / spread
        half_det = 0.5 * (ba * (bd * bg - bf * bf) - bb * (bb * bg - bf * bc) + bc * (bb * bf - bd * bc))
        largest = mean + 2.0 * spread * math.cos(math.acos(min(1.0, max(-1.0, half_det))) / 3.0)
    P = semi_axes.shape[0]
    reach = np.empty((P, 4))
    for p in range(P):
        a_max = max(semi_axes[p, 0], semi_axes[p, 1], semi_axes[p, 2])
        a_min = min(semi_axes[p, 0], semi_axes[p, 1], semi_axes[p, 2])
        reach[p, 0] = a_max
        reach[p, 1] = -2.0 * (log_negligible - log_pi[p] - log_peak)
        reach[p, 2] = largest + noise2 * (a_max * a_max / a_min) ** 2
        reach[p, 3] = semi_axes[p, 0] ** 4 + semi_axes[p, 1] ** 4 + semi_axes[p, 2] ** 4
    return reach, largest


@njit(cache=True, error_model="numpy")
def shapes(R, semi_axes):
    """M = R diag(a²) Rᵀ and M² = R diag(a⁴) Rᵀ (E, 3, 3) each of posed ellipsoids (M of eq. 4)."""
    E = R.shape[0]
    M, M2 = np.empty((E, 3, 3)), np.empty((E, 3, 3))
    for e in range(E):
        for a in range(3):
            for b in range(a, 3):
                m = m2 = 0.0
                for k in range(3):
                    s2 = semi_axes[e, k] * semi_axes[e, k]
                    m += R[e, a, k] * s2 * R[e, b, k]
                    m2 += R[e, a, k] * s2 * s2 * R[e, b, k]
                M[e, a, b] = M[e, b, a] = m
                M2[e, a, b] = M2[e, b, a] = m2
    return M, M2


@njit(cache=True, error_model="numpy")
def _cholesky(entries, scale, L, k):
    """L[k] = the lower-triangular Cholesky factor of `scale` times the symmetric matrix of six `entries`
    (the Cholesky–Banachiewicz recurrences written out for 3 × 3)."""
    a00, a11, a22 = scale * entries[0], scale * entries[1], scale * entries[2]
    a01, a02, a12 = scale * entries[3], scale * entries[4], scale * entries[5]
    l00 = math.sqrt(a00)
    l10, l20 = a01 / l00, a02 / l00
    l11 = math.sqrt(a11 - l10 * l10)
    l21 = (a12 - l20 * l10) / l11
    L[k, 0, 0], L[k, 1, 0], L[k, 2, 0], L[k, 1, 1], L[k, 2, 1] = l00, l10, l20, l11, l21
    L[k, 2, 2] = math.sqrt(a22 - l20 * l20 - l21 * l21)


@njit(cache=True, error_model="numpy")
def residuals(y, n, i, p, t, M):
    """e_ip = y_i − x_ip (K, 3) of the pairs (i[k], p[k]) (eq. 4)."""
    K = i.shape[0]
    e = np.empty((K, 3))
    for k in range(K):
        _, _, _, _, x0, x1, x2 = _normal_point(n, i[k], M, t, p[k])
        e[k, 0], e[k, 1], e[k, 2] = y[i[k], 0] - x0, y[i[k], 1] - x1, y[i[k], 2] - x2
    return e


@njit(cache=True, error_model="numpy")
def length_columns(n, i, p, M, dt, dM):
    """de/d ln ℓ (K, 3, G) of the pairs (i[k], p[k]) for each length factor g,
    −(dt_gp + λ dM_gp n − ½ λ³ (nᵀ dM_gp n) M_p n) with λ = (nᵀ M_p n)^(-1/2), from the ellipsoids' dt (G, P, 3)
    and dM (G, P, 3, 3) (`distances.NormalsDistance.length_jacobian`, `BodyModel.length_derivatives`)."""
    K, G = i.shape[0], dt.shape[0]
    out = np.empty((K, 3, G))
    for k in range(K):
        d, e = i[k], p[k]
        u0, u1, u2, lam = _normal_direction(n, d, M, e)
        n0, n1, n2 = n[d, 0], n[d, 1], n[d, 2]
        for g in range(G):
            a0 = dM[g, e, 0, 0] * n0 + dM[g, e, 0, 1] * n1 + dM[g, e, 0, 2] * n2
            a1 = dM[g, e, 1, 0] * n0 + dM[g, e, 1, 1] * n1 + dM[g, e, 1, 2] * n2
            a2 = dM[g, e, 2, 0] * n0 + dM[g, e, 2, 1] * n1 + dM[g, e, 2, 2] * n2
            c = 0.5 * lam * lam * lam * (n0 * a0 + n1 * a1 + n2 * a2)
            out[k, 0, g] = -(dt[g, e, 0] + lam * a0 - c * u0)
            out[k, 1, g] = -(dt[g, e, 1] + lam * a1 - c * u1)
            out[k, 2, g] = -(dt[g, e, 2] + lam * a2 - c * u2)
    return out


@njit(cache=True, error_model="numpy")
def normal_equations(y, n, i, p, W, t, M, root):
    """Whitened residuals and rigid derivatives of the pairs, and their normal equations per ellipsoid.

    For pair k with lower-triangular weight W_k (t_ip Σ_ip⁻¹ = W Wᵀ): r_k = W_kᵀ e_k, Bw_k = W_kᵀ B_k with
    B_k = de/d(ω, v) = [[x]× − A [n]×, −I] (3 × 6), and per ellipsoid H_p = Σ Bwᵀ Bw (6 × 6),
    g_p = Σ Bwᵀ r (6,). Also de/d(ln s) = −(x − c) for a scaling of the body about its root c
    (`Distance.residuals`, ∂x/∂y = 0 for this distance).

    Returns
    -------
    e : (K, 3); r : (K, 3); Bw : (K, 3, 6); H : (P, 6, 6); g : (P, 6); e_scale : (K, 3);
    norm2 : float, Σ_k |r_k|² summed as `whitened_norm2` sums it (the same bits).
    """
    K, P = i.shape[0], t.shape[0]
    e = np.empty((K, 3))
    r = np.empty((K, 3))
    Bw = np.empty((K, 3, 6))
    H = np.zeros((P, 6, 6))
    g = np.zeros((P, 6))
    e_scale = np.empty((K, 3))
    B = np.empty((3, 6))
    norm2 = 0.0
    for k in range(K):
        q, d = p[k], i[k]
        u0, u1, u2, lam, x0, x1, x2 = _normal_point(n, d, M, t, q)
        e[k, 0], e[k, 1], e[k, 2] = y[d, 0] - x0, y[d, 1] - x1, y[d, 2] - x2
        e_scale[k, 0], e_scale[k, 1], e_scale[k, 2] = root[0] - x0, root[1] - x1, root[2] - x2
        lam3 = lam * lam * lam
        # A = λ M − λ³ u uᵀ, then A [n]× column by column: [n]× e_j = n × e_j
        a00, a11 = lam * M[q, 0, 0] - lam3 * u0 * u0, lam * M[q, 1, 1] - lam3 * u1 * u1
        a22, a01 = lam * M[q, 2, 2] - lam3 * u2 * u2, lam * M[q, 0, 1] - lam3 * u0 * u1
        a02, a12 = lam * M[q, 0, 2] - lam3 * u0 * u2, lam * M[q, 1, 2] - lam3 * u1 * u2
        n0, n1, n2 = n[d, 0], n[d, 1], n[d, 2]
        # [n]× = [[0, −n2, n1], [n2, 0, −n0], [−n1, n0, 0]]; (A [n]×)_{aj} = Σ_b A_ab [n]×_bj
        an00, an01, an02 = a01 * n2 - a02 * n1, -a00 * n2 + a02 * n0, a00 * n1 - a01 * n0
        an10, an11, an12 = a11 * n2 - a12 * n1, -a01 * n2 + a12 * n0, a01 * n1 - a11 * n0
        an20, an21, an22 = a12 * n2 - a22 * n1, -a02 * n2 + a22 * n0, a02 * n1 - a12 * n0
        # B = [[x]× − A [n]×, −I]; [x]× = [[0, −x2, x1], [x2, 0, −x0], [−x1, x0, 0]]
        B[0, 0], B[0, 1], B[0, 2] = -an00, -x2 - an01, x1 - an02
        B[1, 0], B[1, 1], B[1, 2] = x2 - an10, -an11, -x0 - an12
        B[2, 0], B[2, 1], B[2, 2] = -x1 - an20, x0 - an21, -an22
        for a in range(3):
            for j in range(3):
                B[a, 3 + j] = -1.0 if a == j else 0.0
        for b in range(3):  # (Wᵀ X)_b = Σ_{a ≥ b} W_ab X_a (W lower-triangular)
            acc = 0.0
            for a in range(b, 3):
                acc += W[k, a, b] * e[k, a]
            r[k, b] = acc
            norm2 += acc * acc
            for j in range(6):
                acc = 0.0
                for a in range(b, 3):
                    acc += W[k, a, b] * B[a, j]
                Bw[k, b, j] = acc
        for j in range(6):
            for l in range(j, 6):
                H[q, j, l] += Bw[k, 0, j] * Bw[k, 0, l] + Bw[k, 1, j] * Bw[k, 1, l] + Bw[k, 2, j] * Bw[k, 2, l]
            g[q, j] += Bw[k, 0, j] * r[k, 0] + Bw[k, 1, j] * r[k, 1] + Bw[k, 2, j] * r[k, 2]
    for q in range(P):
        for j in range(6):
            for l in range(j):
                H[q, j, l] = H[q, l, j]
    return e, r, Bw, H, g, e_scale, norm2


@njit(cache=True, error_model="numpy")
def whitened_norm2(W, e):
    """Σ_k |W_kᵀ e_k|² for lower-triangular W (K, k, k) and residuals e (K, k): twice eq. (14)'s data term."""
    total = 0.0
    for k in range(e.shape[0]):
        for b in range(e.shape[1]):
            acc = 0.0
            for a in range(b, e.shape[1]):
                acc += W[k, a, b] * e[k, a]
            total += acc * acc
    return total


@njit(cache=True, error_model="numpy")
def extra_normal_equations(W, X, Bw, r, p, P):
    """The normal equations' blocks of further unknowns (the body's size, its length factors) with columns
    X = de/dx (K, k, m): per ellipsoid Σ Bwᵀ Wᵀ X (P, 6, m), and Σ (Wᵀ X)ᵀ Wᵀ X (m, m) and Σ (Wᵀ X)ᵀ r (m,)
    over the pairs, for lower-triangular W (K, k, k), Bw = Wᵀ B (K, k, 6), r = Wᵀ e (K, k), the pairs'
    ellipsoids p (K,) among P.

    Whitened pair by pair and summed in one pass, as the pose block is (`normal_equations`): numpy would
    build (K, k, m) temporaries and sum their products without BLAS, at every M-step of a learning frame.
    """
    K, k, m = X.shape
    HX = np.zeros((P, 6, m))
    XX = np.zeros((m, m))
    gX = np.zeros(m)
    xw = np.empty((k, m))
    for q in range(K):
        for b in range(k):  # (Wᵀ X)_b = Σ_{a ≥ b} W_ab X_a
            for c in range(m):
                acc = 0.0
                for a in range(b, k):
                    acc += W[q, a, b] * X[q, a, c]
                xw[b, c] = acc
        e = p[q]
        for b in range(k):
            rb = r[q, b]
            for c in range(m):
                x = xw[b, c]
                gX[c] += x * rb
                for d in range(c, m):
                    XX[c, d] += x * xw[b, d]
                for j in range(6):
                    HX[e, j, c] += Bw[q, b, j] * x
    for c in range(m):
        for d in range(c):
            XX[c, d] = XX[d, c]
    return HX, XX, gX


@njit(cache=True, error_model="numpy")
def pose_normal_equations(H6, g6, ellipsoid_segment, moves, axis, origin, revolute):
    """H = Σ_p T_pᵀ H_p T_p (D, D) and g = Σ_p T_pᵀ g_p (D,) from the per-ellipsoid blocks (P, 6, 6), (P, 6).

    T_p (6, D) holds the rigid velocity (ω, v) of ellipsoid p's segment per unit change of each DOF
    (`body.BodyModel.segment_twists`): (w_d, o_d × w_d) for a revolute DOF with world axis w_d through
    o_d, (0, w_d) for a translation, zero for a DOF that does not move the segment (`moves` (D, S)).
    """
    D, P = axis.shape[0], H6.shape[0]
    twist = np.zeros((D, 6))
    for d in range(D):
        w0, w1, w2 = axis[d, 0], axis[d, 1], axis[d, 2]
        if revolute[d]:
            o0, o1, o2 = origin[d, 0], origin[d, 1], origin[d, 2]
            twist[d, 0], twist[d, 1], twist[d, 2] = w0, w1, w2
            twist[d, 3], twist[d, 4], twist[d, 5] = o1 * w2 - o2 * w1, o2 * w0 - o0 * w2, o0 * w1 - o1 * w0
        else:
            twist[d, 3], twist[d, 4], twist[d, 5] = w0, w1, w2
    H, g = np.zeros((D, D)), np.zeros(D)
    dofs = np.empty(D, np.int64)
    HT = np.empty((6, D))
    for p in range(P):
        s = ellipsoid_segment[p]
        m = 0
        for d in range(D):
            if moves[d, s]:
                dofs[m] = d
                m += 1
        for a in range(m):  # H_p T_p on the DOFs that move the segment, then T_pᵀ (H_p T_p)
            for j in range(6):
                acc = 0.0
                for l in range(6):
                    acc += H6[p, j, l] * twist[dofs[a], l]
                HT[j, a] = acc
        for a in range(m):
            da = dofs[a]
            for b in range(a, m):
                acc = 0.0
                for j in range(6):
                    acc += twist[da, j] * HT[j, b]
                H[da, dofs[b]] += acc
            acc = 0.0
            for j in range(6):
                acc += twist[da, j] * g6[p, j]
            g[da] += acc
    for a in range(D):  # only one triangle was summed (DOFs of a chain are in increasing order)
        for b in range(a):
            H[a, b] = H[b, a]
    return H, g


@njit(cache=True, error_model="numpy")
def noisy_covariance(n, i, p, e, weight, M, M2, noise2, Sigma, iterations):
    """EM for Σ in e_k = z_k + w_k, z ~ N(0, Σ), w ~ N(0, σ_n² A_k²) (`distances.CompiledNormals.covariance`):
    `iterations` updates Σ ← Σ − Σ (S₁/T) Σ + Σ (S₂/T) Σ from `Sigma`, with S₁ = Σ_k t_k Σ_k⁻¹,
    S₂ = Σ_k t_k Σ_k⁻¹ e_k e_kᵀ Σ_k⁻¹, Σ_k = Σ + σ_n² A_k² and T = Σ_k t_k (t = `weight`)."""
    K = i.shape[0]
    spread = np.empty((K, 6))
    total = 0.0
    for k in range(K):
        u0, u1, u2, lam = _normal_direction(n, i[k], M, p[k])
        s = _spread(M, M2, p[k], u0, u1, u2, lam)
        for j in range(6):
            spread[k, j] = noise2 * s[j]
        total += weight[k]
    S = Sigma.copy()
    S1, S2 = np.empty((3, 3)), np.empty((3, 3))
    for _ in range(iterations):
        # the sums in scalars (kept in registers), added in the same order as into arrays
        p00 = p11 = p22 = p01 = p02 = p12 = 0.0  # S₁
        q00 = q11 = q22 = q01 = q02 = q12 = 0.0  # S₂
        for k in range(K):
            a, d, g = S[0, 0] + spread[k, 0], S[1, 1] + spread[k, 1], S[2, 2] + spread[k, 2]
            b, c, f = S[0, 1] + spread[k, 3], S[0, 2] + spread[k, 4], S[1, 2] + spread[k, 5]
            c00, c01, c02, c11, c12, c22, det = _adjugate(a, d, g, b, c, f)
            h = 1.0 / det  # Σ_k⁻¹ = h adj Σ_k
            v0 = h * (c00 * e[k, 0] + c01 * e[k, 1] + c02 * e[k, 2])  # Σ_k⁻¹ e_k
            v1 = h * (c01 * e[k, 0] + c11 * e[k, 1] + c12 * e[k, 2])
            v2 = h * (c02 * e[k, 0] + c12 * e[k, 1] + c22 * e[k, 2])
            w, wh = weight[k], weight[k] * h
            p00 += wh * c00
            p11 += wh * c11
            p22 += wh * c22
            p01 += wh * c01
            p02 += wh * c02
            p12 += wh * c12
            q00 += w * v0 * v0
            q11 += w * v1 * v1
            q22 += w * v2 * v2
            q01 += w * v0 * v1
            q02 += w * v0 * v2
            q12 += w * v1 * v2
        S1[0, 0], S1[1, 1], S1[2, 2], S1[0, 1], S1[0, 2], S1[1, 2] = p00, p11, p22, p01, p02, p12
        S2[0, 0], S2[1, 1], S2[2, 2], S2[0, 1], S2[0, 2], S2[1, 2] = q00, q11, q22, q01, q02, q12
        for a_ in range(3):
            for b_ in range(a_):
                S1[a_, b_], S2[a_, b_] = S1[b_, a_], S2[b_, a_]
        S = S + S @ ((S2 - S1) / max(total, 1e-300)) @ S
        S = 0.5 * (S + S.T)
    return S


@njit(cache=True, error_model="numpy")
def forward_kinematics(parent, offset, dof_start, dof_axis, dof_revolute, pose):
    """Segment frames and world DOF axes of a pose (`body.BodyModel.fk`), down the tree in segment order.

    A segment's frame is its parent's moved by the segment's offset, then turned or shifted by each of
    its DOFs in turn (Rodrigues' formula about the DOF's axis in the current frame).

    Returns
    -------
    R : (S, 3, 3); t : (S, 3); axis : (D, 3); origin : (D, 3)
    """
    S, D = parent.shape[0], pose.shape[0]
    R, t = np.empty((S, 3, 3)), np.empty((S, 3))
    axis, origin = np.empty((D, 3)), np.empty((D, 3))
    frame, position, turned, local = np.empty((3, 3)), np.empty(3), np.empty((3, 3)), np.empty((3, 3))
    for s in range(S):
        q = parent[s]
        for a in range(3):
            position[a] = 0.0
            for b in range(3):
                frame[a, b] = (1.0 if a == b else 0.0) if q < 0 else R[q, a, b]
            if q >= 0:
                position[a] = t[q, a] + (R[q, a, 0] * offset[s, 0] + R[q, a, 1] * offset[s, 1]
                                         + R[q, a, 2] * offset[s, 2])
        for d in range(dof_start[s], dof_start[s + 1]):
            w0, w1, w2 = dof_axis[d, 0], dof_axis[d, 1], dof_axis[d, 2]
            for a in range(3):
                axis[d, a] = frame[a, 0] * w0 + frame[a, 1] * w1 + frame[a, 2] * w2
            if dof_revolute[d]:
                for a in range(3):
                    origin[d, a] = position[a]
                sin, cos = math.sin(pose[d]), 1.0 - math.cos(pose[d])
                # local = I + sin K + (1 − cos) K², K = [w]×, K² = w wᵀ − I
                local[0, 0], local[0, 1], local[0, 2] = 1.0 + cos * (w0 * w0 - 1.0), -sin * w2 + cos * w0 * w1, \
                    sin * w1 + cos * w0 * w2
                local[1, 0], local[1, 1], local[1, 2] = sin * w2 + cos * w0 * w1, 1.0 + cos * (w1 * w1 - 1.0), \
                    -sin * w0 + cos * w1 * w2
                local[2, 0], local[2, 1], local[2, 2] = -sin * w1 + cos * w0 * w2, sin * w0 + cos * w1 * w2, \
                    1.0 + cos * (w2 * w2 - 1.0)
                for a in range(3):
                    for b in range(3):
                        turned[a, b] = frame[a, 0] * local[0, b] + frame[a, 1] * local[1, b] + frame[a, 2] * local[2, b]
                frame[:, :] = turned
            else:
                for a in range(3):
                    position[a] += axis[d, a] * pose[d]
                    origin[d, a] = position[a]
        R[s] = frame
        t[s] = position
    return R, t, axis, origin


@njit(cache=True, error_model="numpy")
def place_ellipsoids(R_segment, t_segment, segment, rotation, centre):
    """World axes R (E, 3, 3) and centres t (E, 3) of ellipsoids riding on posed segments (`posed_body`).

    Ellipsoid e is fixed in its segment's frame (axes `rotation[e]`, centre `centre[e]`): R = R_s rotation,
    t = t_s + R_s centre with s = segment[e].
    """
    E = segment.shape[0]
    R, t = np.empty((E, 3, 3)), np.empty((E, 3))
    for e in range(E):
        s = segment[e]
        for a in range(3):
            r0, r1, r2 = R_segment[s, a, 0], R_segment[s, a, 1], R_segment[s, a, 2]
            t[e, a] = t_segment[s, a] + r0 * centre[e, 0] + r1 * centre[e, 1] + r2 * centre[e, 2]
            for b in range(3):
                R[e, a, b] = r0 * rotation[e, 0, b] + r1 * rotation[e, 1, b] + r2 * rotation[e, 2, b]
    return R, t


@njit(cache=True, error_model="numpy")
def posed_body(parent, offset, dof_start, dof_axis, dof_revolute, pose, segment, rotation, centre):
    """`forward_kinematics` then `place_ellipsoids` of one pose (`body.BodyModel.fk`): segment frames R (S, 3, 3)
    and t (S, 3), DOF axes (D, 3) and origins (D, 3), ellipsoid axes (E, 3, 3) and centres (E, 3)."""
    R_segment, t_segment, axis, origin = forward_kinematics(parent, offset, dof_start, dof_axis, dof_revolute, pose)
    R, t = place_ellipsoids(R_segment, t_segment, segment, rotation, centre)
    return R_segment, t_segment, axis, origin, R, t


@njit(cache=True, error_model="numpy")
def posed_ellipsoids(parent, offset, dof_start, dof_axis, dof_revolute, poses, segment, rotation, centre):
    """`place_ellipsoids` after `forward_kinematics` for many poses (H, D) of one body: (H, E, 3, 3), (H, E, 3).

    Limb re-initialisation scores hundreds of poses; one call instead of one per pose.
    """
    H, E = poses.shape[0], segment.shape[0]
    R, t = np.empty((H, E, 3, 3)), np.empty((H, E, 3))
    for h in range(H):
        R_segment, t_segment, _, _ = forward_kinematics(parent, offset, dof_start, dof_axis, dof_revolute, poses[h])
        R[h], t[h] = place_ellipsoids(R_segment, t_segment, segment, rotation, centre)
    return R, t
