"""The mixture model of the data (Horaud et al. 2009, eqs. 9-13): its parameters, its E-step and their bounds.

The data are explained by P Gaussian components, one per ellipsoid, centred on the ellipsoid points
x_ip(Λ) (eq. 4) with one covariance Σ shared by all (so that ellipsoids without data cannot collapse),
plus a uniform outlier component 1/V over the working volume:

    P(y_i | n_i) = Σ_p π_p N(y_i | x_ip(Λ), Σ) + π_{P+1} / V.

This module holds what every distance's E-step shares (`distances.Distance.e_step` computes it): the
mixture's parameters, the E-step's result, the pruning thresholds, and the bounds the M-step keeps Σ and
π within.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
# The E-step skips a pair whose joint density π_p N(y_i | x_ip, Σ_ip) is provably below this fraction of
# the largest term of the datum's evidence: its posterior is below it too, every other posterior changes
# by less than P times it (relative), and ln P(Y | Λ) by less than I·P times it. An order below
# PRUNE_POSTERIOR: a skipped pair would not have entered the M-step anyway, and a smaller fraction only
# costs time (the joints do not change).
NEGLIGIBLE_POSTERIOR = 1e-4


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
    explained : (P,) float
        Σ_i t_ip, the data each ellipsoid explains (the M-step's I π_p), as t.sum(axis=0) sums it.
    """

    t: np.ndarray
    t_outlier: np.ndarray
    log_likelihood: float
    pairs: np.ndarray
    weights: np.ndarray
    best: np.ndarray
    explained: np.ndarray

    @staticmethod
    def empty(P: int, k: int) -> EStep:
        """The E-step of no data: no posteriors, no pairs, ln P = 0."""
        return EStep(t=np.zeros((0, P)), t_outlier=np.zeros(0), log_likelihood=0.0,
                     pairs=np.zeros((2, 0), dtype=int), weights=np.zeros((0, k, k)), best=np.zeros(0, dtype=int),
                     explained=np.zeros(P))


def volume_size(volume: np.ndarray) -> float:
    """V of the uniform outlier density (eq. 10): the volume of the box (2, 3) [min; max], m³."""
    volume = np.asarray(volume, dtype=float)
    if volume.shape != (2, 3) or not np.all(np.isfinite(volume)) or np.any(volume[1] <= volume[0]):
        raise ValueError(f"volume must be a (2, 3) array [min; max] with max > min, got {volume.tolist()}")
    return float(np.prod(volume[1] - volume[0]))


def evidence_terms(I: int, P: int, mixture: Mixture, V: float, which: np.ndarray | None,
                   base: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The ellipsoids `which` (default all P) and the base terms b_i (default ln π_{P+1} / V) of an evidence."""
    which = np.arange(P) if which is None else np.asarray(which)
    base = np.full(I, np.log(mixture.pi[P]) - np.log(V)) if base is None else np.asarray(base, dtype=float)
    return which, base


def bound_covariance(Sigma: np.ndarray, max_sigma_m: float) -> np.ndarray:
    """Σ with its eigenvalues clipped to [SIGMA_FLOOR_M², max_sigma_m²] (symmetric positive definite)."""
    vals, vecs = np.linalg.eigh(0.5 * (Sigma + Sigma.T))
    return (vecs * np.clip(vals, SIGMA_FLOOR_M**2, max(max_sigma_m, SIGMA_FLOOR_M) ** 2)) @ vecs.T


def bound_priors(pi: np.ndarray, min_outlier_prior: float) -> np.ndarray:
    """π with every ellipsoid's prior at least PI_FLOOR and the outlier prior at least `min_outlier_prior`.

    The ellipsoids' share is rescaled to 1 − π_{P+1}, which maximises Σ_p (Σ_i t_ip) ln π_p under the bound.
    """
    pi = np.maximum(pi, PI_FLOOR)
    pi /= pi.sum()
    outlier = max(pi[-1], min_outlier_prior)
    bounded = pi * (1.0 - outlier) / pi[:-1].sum()
    bounded[-1] = outlier
    return bounded
