"""Automatic initialisation from the data alone (what Horaud et al. 2009 leave open).

On the first frame, and whenever tracking is lost, the pose is found without any prior. Candidate
poses come from the pose library (`library`: joint-angle vectors for the body). Every candidate is
placed on the point cloud and turned to several headings, all hypotheses are scored at once by the
mixture likelihood (eq. 12) on a subsample of the data, the best few get a short EM refinement on that
subsample (successive halving), and the best of those is fitted to all the data by EM (with the body's
size as a further unknown when the height is not given).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from stages.tracking.body import BodyModel, Ellipsoids
from stages.tracking.distances import distance_named
from stages.tracking.em import EMParams, FitResult, fit, hypothesis_scores, screened_scores
from stages.tracking.gauss_newton import HEIGHT_RANGE_M
from stages.tracking.mixture import Mixture, volume_size

# The cloud's top (to guess a hypothesis' height when it is not given) is the highest point with a few
# neighbours this close: the body's surface is sampled densely, outliers in the volume are isolated.
_TOP_RADIUS_M = 0.06
_TOP_NEIGHBOURS = 2
# Σ while scoring and at the start of the refinement: hypotheses are off by several centimetres (also
# the limbs' re-initialisation's, `limbs.reinitialise_limb`).
SCORE_SIGMA_M = 0.06
# The candidate poses are screened on this many of the scoring observations, and this many times as many as
# the refinement takes are scored on all of them (`_screened_scores`).
_SCREEN_POINTS = 30
_SCREEN_KEEP_FACTOR = 6
# Each round of the refinement keeps the best quarter of its hypotheses (12 → 3 → 2 by default).
_KEEP_DIVISOR = 4


@dataclass(frozen=True)
class InitParams:
    """Tunables of the initialisation.

    Attributes
    ----------
    headings : int
        Headings tried per library pose, evenly spread over 360°.
    refine : int
        Best-scoring library poses (each at its best heading) refined by EM, by successive halving: all
        get `refine_iterations` iterations, the best quarter as many more, and so on until `finalists`
        are left.
    score_points : int
        Observations used to score the hypotheses (the cloud's shape, not every point).
    refine_points : int or None
        Observations used to refine the best hypotheses (a superset of the scoring ones); None: all. On a
        random subsample the halving's ranking, and with it the pose chosen, depends on the draw
        (`TrackerParams.seed`; measured in docs/results_by_hand.md).
    refine_iterations : int
        EM iterations per round of the refinement.
    iterations : int
        EM iterations at most of the final fit to all observations.
    finalists : int
        Hypotheses the refinement keeps for a final fit each: the subsample's ranking can put a
        wrong optimum first. The first-ranked stays the result unless another's log-likelihood on all
        the observations is higher by `finalist_margin` nats per observation.
    finalist_margin : float
        Two fits in nearly the same place differ by hundredths of a nat per observation (a choice
        between them is noise), a fit in a better optimum by tenths: with this margin the runner-up
        wins only where the first-ranked is in a wrong optimum (an arm across the body).
    """

    headings: int = 12
    refine: int = 12
    score_points: int = 120
    refine_points: int | None = None
    refine_iterations: int = 4
    iterations: int = 15
    finalists: int = 2
    finalist_margin: float = 0.05


@dataclass(frozen=True)
class InitResult:
    """The chosen initial pose (D,), the fitted body (its height, metres) and the final EM fit."""

    pose: np.ndarray
    height_m: float
    fit: FitResult

def initialise(y: np.ndarray, n: np.ndarray, body: BodyModel, volume: np.ndarray, candidates: np.ndarray,
               *, estimate_height: bool, params: InitParams = InitParams(),
               em: EMParams | None = None, rng: np.random.Generator | None = None,
               facing: float | None = None) -> InitResult:
    """Find the pose (and height) from one frame's points y (I, 3) and normals n (I, 3).

    Parameters
    ----------
    body : BodyModel
        The body at the known height, or at a first guess when `estimate_height`.
    volume : (2, 3) float
        Working volume (the outlier density's support).
    candidates : (M, D) float
        Library poses for this body (`load_pose_library`).
    estimate_height : bool
        Also estimate the body's height (from the cloud's top, then by EM).
    facing : float, optional
        A heading (yaw, radians) the subject is known to face roughly: the headings tried are then spread
        over the half-turn centred on it instead of the whole turn.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    em = EMParams() if em is None else em
    V = volume_size(volume)
    sample = rng.permutation(len(y))
    ys, ns = y[sample[: params.refine_points]], n[sample[: params.refine_points]]
    centre = np.median(y[:, :2], axis=0)
    top = _cloud_top(y)
    bodies, poses = [], []
    for base in candidates:
        height = body.height_m
        if estimate_height:
            height = float(np.clip(top / _top_ratio(body, base), *HEIGHT_RANGE_M))
        pose = base.copy()
        pose[2] *= height
        bodies.append(body.scaled(height))
        poses.append(pose)
    yaws = np.linspace(0.0, 2 * np.pi, params.headings, endpoint=False) if facing is None else \
        facing + np.linspace(-np.pi / 2, np.pi / 2, params.headings // 2 + 1)
    mixture = Mixture.initial(body.n_ellipsoids, SCORE_SIGMA_M, distance_named(em.distance).size)
    scored = sample[: params.score_points]
    scores = _screened_scores(y[scored], n[scored], centre, bodies, poses, yaws, mixture, V, em.distance,
                              keep=_SCREEN_KEEP_FACTOR * params.refine)  # (M, H)
    short = replace(em, max_iterations=params.refine_iterations, displacement_m=0.0,
                    estimate_scale=estimate_height, estimate_lengths=False)
    order = np.argsort(-scores.max(axis=1))[: params.refine]  # distinct poses, each at its best heading
    fits = [fit(ys, ns, bodies[m], _placed(bodies[m], poses[m], yaws[np.argmax(scores[m])], centre), volume,
                short, sigma_m=SCORE_SIGMA_M) for m in order]
    kept = max(1, params.finalists)
    while len(fits) > kept:  # successive halving: the better quarter gets more iterations
        fits = sorted(fits, key=lambda r: -r.log_likelihood[-1])[: max(kept, len(fits) // _KEEP_DIVISOR)]
        if len(fits) > kept:
            fits = [fit(ys, ns, r.body, r.pose, volume, short, mixture=r.mixture, start=r.estep) for r in fits]
    final = replace(em, max_iterations=params.iterations, estimate_scale=estimate_height)
    ranked = [fit(y, n, r.body, r.pose, volume, final, mixture=replace(r.mixture))
              for r in sorted(fits, key=lambda r: -r.log_likelihood[-1])]
    result = ranked[0]
    for other in ranked[1:]:
        if other.log_likelihood[-1] > result.log_likelihood[-1] + params.finalist_margin * len(y):
            result = other
    return InitResult(pose=result.pose, height_m=result.height_m, fit=result)


def _placed(body: BodyModel, pose: np.ndarray, yaw: float, centre: np.ndarray) -> np.ndarray:
    """The pose turned by `yaw` with the horizontal centroid of its ellipsoid centres on `centre` (2,)."""
    pose = pose.copy()
    pose[3] = yaw
    pose[:2] = 0.0
    pose[:2] = centre - body.ellipsoids(pose).t[:, :2].mean(axis=0)
    return pose


def _score(y, n, centre, bodies, poses, yaws, mixture, V, distance) -> np.ndarray:
    """Log-likelihood (eq. 12) (M, H) of every candidate pose at every heading.

    Turning a hypothesis by ψ about the vertical through `centre` is turning the data by −ψ, so the
    data are turned once per heading (H × I rows) and every candidate's ellipsoids (facing +y, centred
    on the origin) are compared with all of them at once.
    """
    c, s = np.cos(-yaws), np.sin(-yaws)
    Rz = np.zeros((len(yaws), 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
    offset = np.array([centre[0], centre[1], 0.0])
    y_turned = np.einsum("hab,ib->hia", Rz, y - offset).reshape(-1, 3)  # (H·I, 3)
    n_turned = np.einsum("hab,ib->hia", Rz, n).reshape(-1, 3)
    posed = [b.ellipsoids(_placed(b, q, 0.0, np.zeros(2))) for b, q in zip(bodies, poses, strict=True)]
    hypotheses = Ellipsoids(R=np.stack([e.R for e in posed]), t=np.stack([e.t for e in posed]),
                            semi_axes=np.stack([e.semi_axes for e in posed]))
    return hypothesis_scores(y_turned, n_turned, hypotheses, mixture, V, blocks=np.arange(len(yaws) + 1) * len(y),
                             distance=distance)


def _screened_scores(y, n, centre, bodies, poses, yaws, mixture, V, distance, *, keep: int) -> np.ndarray:
    """`_score` (M, H) of the `keep` candidate poses best at their best heading on the first `_SCREEN_POINTS`
    rows, −inf for the others (`em.screened_scores`)."""

    def score(chosen: np.ndarray, rows: slice) -> np.ndarray:
        return _score(y[rows], n[rows], centre, [bodies[m] for m in chosen], [poses[m] for m in chosen], yaws,
                      mixture, V, distance)

    return screened_scores(score, len(bodies), len(y), _SCREEN_POINTS, keep)


def _cloud_top(y: np.ndarray) -> float:
    """Height (metres) of the highest observation with `_TOP_NEIGHBOURS` others within `_TOP_RADIUS_M`."""
    neighbours = cKDTree(y).query_ball_point(y, _TOP_RADIUS_M, return_length=True) - 1
    dense = neighbours >= _TOP_NEIGHBOURS
    return float(y[dense, 2].max()) if np.any(dense) else float(y[:, 2].max())


def _top_ratio(body: BodyModel, pose: np.ndarray) -> float:
    """Highest point of the posed body (root height as a fraction of height) over the body's height."""
    pose = pose.copy()
    pose[2] *= body.height_m
    ell = body.ellipsoids(pose)
    z_extent = np.sqrt(np.sum((ell.R[:, 2, :] * ell.semi_axes) ** 2, axis=1))
    return float(np.max(ell.t[:, 2] + z_extent)) / body.height_m
