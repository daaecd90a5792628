"""Limbs that EM put in the wrong place, found by the data they explain, and their local re-initialisation.

A limb EM put on the wrong side of the body or folded away from its data gets almost no
observations, and the local minimum holds it there for many frames. A limb's segments are compared
with its mirror limb's (`misplaced_limbs`) and with their own running level (`deserted_limbs`); a limb
found either way, and every limb after an initialisation, gets the library's angles for that limb alone
(`reinitialise_limb`), and the likelihood decides (eq. 12); a limb and its mirror that took each other's data
are exchanged back (`swap_limbs`). What Horaud et al. 2009 leave open, like the initialisation.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from stages.tracking.body import BodyModel, Ellipsoids
from stages.tracking.em import EMParams, FitResult, fit, hypothesis_scores, log_evidence, screened_scores
from stages.tracking.init import SCORE_SIGMA_M
from stages.tracking.mixture import Mixture, volume_size

# A limb's segment is taken for misplaced when it explains fewer data than this fraction of what its
# mirror segment explains: left and right limbs have the same surface, and even a limb held against
# the body or turned away from most cameras keeps a good part of its mirror's share, while a forearm put
# on the wrong side of the body by the initialisation explains a small fraction of it.
LIMB_SHARE_RATIO = 0.3
# The comparison only means something when the mirror segment itself explains this many observations
# (a foot or a forearm seen by few cameras is too noisy a reference).
LIMB_MIN_OBSERVATIONS = 20
# Hypotheses closer than this (radians, every DOF of the chain) are one: the library repeats itself.
_LIMB_HYPOTHESIS_STEP = 0.1
# Limb hypotheses are scored on this many random observations first, and the best this many on all of them
# (`_screened_scores`).
_LIMB_SCREEN_POINTS = 100
_LIMB_SCREEN_KEEP = 48
# Best-scoring limb hypotheses refined by EM on all the data.
_LIMB_REFINE = 3
# A re-initialised limb replaces the fit only when the likelihood gains this much per observation (nats):
# a limb really misplaced gains tenths, while gains of hundredths come from ambiguous data, where taking
# them flips a forearm back and forth from frame to frame.
LIMB_MARGIN = 0.02
# Values per DOF of the grid over the limb's two first joints (shoulder and elbow, hip and knee): the
# library holds whole-body poses, and an arm reaching out from a leaning torso may be in none of them.
_LIMB_GRID_LEVELS = 5


@dataclass(frozen=True)
class LimbParams:
    """When a limb is taken for misplaced (`misplaced_limbs`, `deserted_limbs`).

    Attributes
    ----------
    share_ratio : float
        A limb with a segment explaining fewer data than this fraction of its reference (its mirror
        segment's data, or its own running level) is misplaced; 0 never.
    min_observations : float
        The reference must explain at least this many observations to mean something.
    """

    share_ratio: float = LIMB_SHARE_RATIO
    min_observations: float = LIMB_MIN_OBSERVATIONS


@dataclass(frozen=True)
class Limb:
    """A chain of segments hanging from the torso (arm, leg) and its mirror image.

    Attributes
    ----------
    name : str
        Name of the chain's first segment ("l_upperarm").
    segments, mirror_segments : (S,) int
        Segments of the chain (from the torso outwards) and the mirror chain's same segments.
    dofs, mirror_dofs : (K,) int
        DOFs of the chain and the mirror chain's corresponding DOFs.
    mirror_sign : (K,) float
        A pose mirrored left-right has mirror_dofs = mirror_sign × dofs (twists change sign).
    nested : (2, N) int
        Every pair (ellipsoid of a segment past the chain's first, ellipsoid of that segment's parent):
        where `folded` looks for a centre inside its parent, per frame and limb, so found once.
    """

    name: str
    segments: np.ndarray
    mirror_segments: np.ndarray
    dofs: np.ndarray
    mirror_dofs: np.ndarray
    mirror_sign: np.ndarray
    nested: np.ndarray


_MIRROR_PREFIXES = ("l_", "r_")


def body_limbs(body: BodyModel) -> list[Limb]:
    """The limbs of `body`: chains starting at an "l_"/"r_" segment whose parent is neither, with mirrors.

    Mirror segments and DOFs are found by swapping the "l_"/"r_" prefix; the sign of a mirrored DOF is
    that of its axis against the left-right reflection (x → −x) of the original axis (a rotation axis
    is a pseudo-vector: (w_x, −w_y, −w_z)).
    """
    names = list(body.segment_names)

    def mirror(name):
        side = name[:2]
        return ("r_" if side == "l_" else "l_") + name[2:] if side in _MIRROR_PREFIXES else None

    limbs = []
    for s, name in enumerate(names):
        parent = body.parent[s]
        if mirror(name) not in names or (parent >= 0 and mirror(names[parent]) is not None):
            continue
        chain = [s]
        for child in range(s + 1, len(names)):
            if body.parent[child] in chain:
                chain.append(child)
        mirrored = [names.index(mirror(names[c])) for c in chain]
        dofs = [d for d in range(body.pose_size) if body.dof_segment[d] in chain]
        dof_names = list(body.dof_names)
        mirror_dofs = [dof_names.index(mirror(dof_names[d])) for d in dofs]
        reflected = body.dof_axis[dofs] * np.array([1.0, -1.0, -1.0])
        sign = np.sign(np.einsum("ka,ka->k", body.dof_axis[mirror_dofs], reflected))
        limbs.append(Limb(name=name, segments=np.array(chain), mirror_segments=np.array(mirrored),
                          dofs=np.array(dofs), mirror_dofs=np.array(mirror_dofs), mirror_sign=sign,
                          nested=_nested_ellipsoids(body, chain[1:])))
    return limbs


def segment_shares(body: BodyModel, mixture: Mixture) -> np.ndarray:
    """Fraction of the data each segment of `body` explains (S,): the sum of its ellipsoids' priors π_p.

    After a fit the priors are the mean posteriors (the M-step's π_p = (1/I) Σ_i t_ip), so I times a
    share is the number of observations the segment explains.
    """
    return np.bincount(body.ellipsoid_segment, weights=mixture.pi[:-1], minlength=len(body.segment_names))


def misplaced_limbs(limbs: list[Limb], result: FitResult, n_observations: int,
                    params: LimbParams = LimbParams()) -> list[Limb]:
    """The `limbs` (`body_limbs` of the fitted body) with a segment explaining far fewer data than its mirror
    segment.

    The data a segment explains are I Σ π_p over its ellipsoids (`segment_shares`). The test is
    absolute (a share against the mirror's share in the same frame), so a bad start cannot make
    itself the norm.
    """
    per_segment = n_observations * segment_shares(result.body, result.mixture)
    return _starved(limbs, per_segment, per_segment, [limb.mirror_segments for limb in limbs], params)


def deserted_limbs(limbs: list[Limb], result: FitResult, usual_shares: np.ndarray, n_observations: int,
                   params: LimbParams = LimbParams()) -> list[Limb]:
    """The `limbs` (`body_limbs` of the fitted body) with a segment explaining far fewer data than it usually
    does.

    `usual_shares` (S,) are the segments' shares of the data over the recent tracked frames (a running
    mean of `segment_shares`). A forearm that EM folded onto its upper arm, or turned away from its data,
    still explains some data, often as many as its mirror (which `misplaced_limbs` compares with), but
    far fewer than it did a few frames before; so does a limb that has just become hidden, for which
    the re-initialisation finds nothing better and the fit stays. A share that stays low becomes the
    usual share within a few tens of frames, which bounds how long a limb is tried again.
    """
    per_segment = n_observations * segment_shares(result.body, result.mixture)
    usual = n_observations * np.asarray(usual_shares)
    return _starved(limbs, per_segment, usual, [limb.segments for limb in limbs], params)


def folded_limbs(limbs: list[Limb], result: FitResult, previous: np.ndarray | None = None) -> list[Limb]:
    """The `limbs` (`body_limbs` of the fitted body) that lie `folded` onto themselves in the fit and did not in
    the `previous` pose (None: no previous pose, every folded limb).

    A forearm EM folded onto its upper arm keeps a fair share of the data (its upper arm's, a second time), so
    neither share test finds it; the fold itself makes it a suspect, once, when it appears: where the data
    show the fold (a chambered kick's knee), no hypothesis beats it, and trying again at every frame it lasts
    would cost a limb re-initialisation each.
    """
    now = _folded_each(result.kin.ellipsoids, limbs)
    suspects = [limb for limb, bent in zip(limbs, now, strict=True) if bent]
    if previous is None or not suspects:
        return suspects
    before = _folded_each(result.body.ellipsoids(previous), suspects)
    return [limb for limb, bent in zip(suspects, before, strict=True) if not bent]


def checks_due(count: int, limbs: int, every: int) -> np.ndarray:
    """(limbs,) bool the limbs whose periodic search falls on the `count`-th tracked frame since an initialisation:
    each every `every` frames, the limbs spread over that interval in turn (limb i when count ≡ i·every / limbs),
    so that a frame pays for one search at most; none with `every` 0."""
    if every <= 0:
        return np.zeros(limbs, dtype=bool)
    return (count - (np.arange(limbs) * every) // limbs) % every == 0


def search_backoff(misses: np.ndarray, wait: np.ndarray, searched: np.ndarray,
                   kept: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each limb's searches in a row that kept the fit and the frames it now waits before a share test may
    search it again (L,) int each, after a frame in which the limbs `searched` were searched and those `kept`
    stayed where EM had put them (L,) bool each. Also for the legs' exchange (`swap_limbs`).

    A limb that the search keeps where it is, frame after frame, has few data because the data are few there
    (an arm held against a ducking subject's body explains a fraction of its mirror's data), not because it
    is misplaced: the search found nothing better and, the data changing little from one frame to the next,
    will not at the next. Such a limb is searched at doubling intervals (after k searches in a row that kept
    it, the next 2^(k−1) − 1 frames are skipped: none after one, as a limb slipping off its data over two
    frames is common, then 1, 3, 7...), so that its cost grows with the log of the time its data stay few
    rather than with the time; a search that moves it, or a frame where no test suspects it, starts the
    count again.
    """
    misses = np.where(searched, np.where(kept, misses + 1, 0), np.where(wait > 0, misses, 0))
    return misses, np.where(searched, 2 ** np.maximum(misses - 1, 0) - 1, np.maximum(wait - 1, 0))


def _starved(limbs: list[Limb], own: np.ndarray, reference: np.ndarray, compared: list[np.ndarray],
             params: LimbParams) -> list[Limb]:
    """The `limbs` with a segment s explaining fewer data `own[s]` than `share_ratio` times a reference of at least
    `min_observations`, `reference[c]` with c the segment that `compared` (one array per limb, aligned with its
    segments) puts against s. `own` and `reference` are per segment (S,); the limbs are tested together, at
    every frame."""
    if not limbs:
        return []
    references = reference[np.concatenate(compared)]
    short = (references >= params.min_observations) & (
        own[np.concatenate([limb.segments for limb in limbs])] < params.share_ratio * references)
    starved = _any_of_each(short, [len(limb.segments) for limb in limbs])
    return [limb for limb, hit in zip(limbs, starved, strict=True) if hit]


def reinitialise_limb(y: np.ndarray, n: np.ndarray, result: FitResult, limb: Limb, volume: np.ndarray,
                      em: EMParams, candidates: np.ndarray, *, rng: np.random.Generator | None = None,
                      refine: int = _LIMB_REFINE, elsewhere: bool = False) -> FitResult:
    """Re-initialise one limb of a fit locally; returns the better (by likelihood) of the two fits.

    Joint-angle hypotheses for the limb's DOFs come from the pose library (`candidates`, the limb's
    own values and its mirror's, mirrored), from a grid over its first two joints (`_limb_grid`),
    from the mirror limb's current angles (people often hold both arms alike) and from the current
    angles. Each is scored by the likelihood (eq. 12) with the rest of the body fixed, on all the data
    (screened on a random few first, `_screened_scores`: scored on a random subsample, the limb's fate
    depended on the draw), with the limb's priors π set to its mirror's (a limb that explained nothing
    would otherwise be handicapped by its small prior) and under the initialisation's coarse Σ
    (`SCORE_SIGMA_M`), not the fit's: grid and library angles are tens of millimetres off at best, and
    under a Σ of 2-3 cm they lost to the misplaced limb itself (the test with arms off the grid shows it).
    The best `refine` are refined by EM on all the data (the whole body free); the best of them
    that does not leave the limb `folded` replaces the fit when it is better by `LIMB_MARGIN` nats per
    observation. `elsewhere` leaves out the hypotheses at the current angles: a check of a limb that no test
    suspects looks for another optimum only (the fit is one already, and refined there it stays there).
    """
    rng = np.random.default_rng(0) if rng is None else rng
    body, pose = result.body, result.pose
    values = np.vstack([candidates[:, limb.dofs], candidates[:, limb.mirror_dofs] * limb.mirror_sign,
                        pose[limb.mirror_dofs] * limb.mirror_sign, pose[limb.dofs], _limb_grid(body, pose, limb)])
    values = np.clip(values, body.lower[limb.dofs], body.upper[limb.dofs])
    cells = np.round(values / _LIMB_HYPOTHESIS_STEP)
    _, first = np.unique(cells, axis=0, return_index=True)
    first = np.sort(first)
    if elsewhere:
        here = np.round(np.clip(pose[limb.dofs], body.lower[limb.dofs], body.upper[limb.dofs]) / _LIMB_HYPOTHESIS_STEP)
        first = first[np.any(cells[first] != here, axis=1)]
    hypotheses = np.repeat(pose[None], len(first), axis=0)
    hypotheses[:, limb.dofs] = values[first]
    pi = result.mixture.pi.copy()
    mine = np.isin(body.ellipsoid_segment, limb.segments)
    theirs = np.isin(body.ellipsoid_segment, limb.mirror_segments)
    pi[np.flatnonzero(mine)] = np.maximum(pi[np.flatnonzero(mine)], pi[np.flatnonzero(theirs)])
    mixture = replace(result.mixture, pi=pi / pi.sum())
    coarse = replace(mixture, Sigma=np.eye(len(mixture.Sigma)) * SCORE_SIGMA_M**2)
    V = volume_size(volume)
    order = rng.permutation(len(y))  # the screening's rows a random sample
    ys, ns = y[order], n[order]
    # The rest of the body does not move: its evidence is computed once, the limb's added per hypothesis.
    rest = log_evidence(ys, ns, body.ellipsoids(pose), coarse, V, which=np.flatnonzero(~mine),
                        distance=em.distance, normal_noise_rad=em.normal_noise_rad)
    scores = _screened_scores(ys, ns, body.posed_ellipsoids(hypotheses), coarse, V, np.flatnonzero(mine), rest, em)
    best = result
    for q in hypotheses[np.argsort(scores)[::-1][:refine]]:
        refined = fit(y, n, body, q, volume, em, mixture=mixture)
        if refined.log_likelihood[-1] > best.log_likelihood[-1] and not folded(refined.body, refined.pose, limb):
            best = refined
    return _clearly_better(best, result, len(y))


def exchanged(pose: np.ndarray, limb: Limb) -> np.ndarray:
    """A copy of `pose` (D,) with `limb` and its mirror limb each given the other's angles, mirrored."""
    swapped = pose.copy()
    swapped[limb.dofs] = pose[limb.mirror_dofs] * limb.mirror_sign
    swapped[limb.mirror_dofs] = pose[limb.dofs] * limb.mirror_sign
    return swapped


def swap_limbs(y: np.ndarray, n: np.ndarray, result: FitResult, limb: Limb, volume: np.ndarray,
               em: EMParams) -> FitResult:
    """The fit with `limb` and its mirror limb exchanged, each given the other's angles (mirrored) and refitted
    by EM, when that gains `LIMB_MARGIN` per observation; else `result`.

    Left and right legs look alike in silhouettes: where they pass each other (a walk's stride), EM can follow
    each onto the other's data, and from then on each explains the other's observations as well as its own
    would, so that neither share test fires; only the hips' and knees' directions are wrong, and the
    likelihood sinks a little more at every frame. Re-initialising one limb cannot undo it (its data are
    taken by the other); exchanging both can.
    """
    pose = result.body.clip(exchanged(result.pose, limb))
    return _clearly_better(fit(y, n, result.body, pose, volume, em, mixture=result.mixture), result, len(y))


def _clearly_better(candidate: FitResult, result: FitResult, observations: int) -> FitResult:
    """`candidate` when its likelihood beats `result`'s by `LIMB_MARGIN` nats per observation, else `result`."""
    if candidate.log_likelihood[-1] < result.log_likelihood[-1] + LIMB_MARGIN * observations:
        return result
    return candidate


def folded(body: BodyModel, pose: np.ndarray, limb: Limb) -> bool:
    """Whether a segment of `limb` lies folded onto its parent: the centre of one of its ellipsoids inside one
    of the parent segment's ellipsoids (with the default body, an elbow bent past about 135°, a knee past 150°).

    Such a pose is a degenerate optimum of the mixture: the folded segment explains its parent's data a
    second time, which can outweigh the few data of a thin forearm, so a limb re-initialisation could jump
    there from a pose that was right, the wrist then put back at the shoulder. Tracking still follows a
    limb that bends that far from frame to frame; only a jump there is refused.
    """
    return bool(_folded_each(body.ellipsoids(pose), [limb])[0])


def _folded_each(ellipsoids: Ellipsoids, limbs: list[Limb]) -> np.ndarray:
    """`folded` (L,) bool of each of `limbs` on the posed `ellipsoids`: the tracker tests every limb at every
    frame, and one pass over all their ellipsoid pairs costs what one limb's did."""
    outer, inner = np.concatenate([limb.nested for limb in limbs], axis=1)
    # centre offsets in the parent ellipsoids' axes, over their semi-axes: inside when of norm < 1
    scaled = np.einsum("ka,kab->kb", ellipsoids.t[outer] - ellipsoids.t[inner], ellipsoids.R[inner])
    inside = ((scaled / ellipsoids.semi_axes[inner]) ** 2).sum(axis=-1) < 1.0
    return _any_of_each(inside, [limb.nested.shape[1] for limb in limbs])


def _any_of_each(flags: np.ndarray, sizes: list[int]) -> np.ndarray:
    """(L,) bool whether any of each limb's `flags` is set, the flags (N,) of the L limbs one after the other,
    `sizes[l]` of them for limb l."""
    owner = np.repeat(np.arange(len(sizes)), sizes)
    return np.bincount(owner, weights=flags, minlength=len(sizes)) > 0


def _nested_ellipsoids(body: BodyModel, segments: list[int]) -> np.ndarray:
    """`Limb.nested` of the `segments`: (2, N) pairs of an ellipsoid of one of them and one of its parent's."""
    pairs = [(outer, inner) for segment in segments
             for outer in np.flatnonzero(body.ellipsoid_segment == segment)
             for inner in np.flatnonzero(body.ellipsoid_segment == body.parent[segment])]
    return np.array(pairs, dtype=int).reshape(-1, 2).T


def _screened_scores(y: np.ndarray, n: np.ndarray, hypotheses: Ellipsoids, mixture: Mixture, V: float,
                     which: np.ndarray, base: np.ndarray, em: EMParams) -> np.ndarray:
    """(H,) the limb hypotheses' scores (`hypothesis_scores` of the limb's ellipsoids `which` over the rest's
    evidence `base`) on all of y for the `_LIMB_SCREEN_KEEP` best on its first `_LIMB_SCREEN_POINTS` rows, −inf
    for the others (`em.screened_scores`)."""

    def score(chosen: np.ndarray, rows: slice) -> np.ndarray:
        posed = Ellipsoids(R=hypotheses.R[chosen], t=hypotheses.t[chosen], semi_axes=hypotheses.semi_axes[chosen])
        return hypothesis_scores(y[rows], n[rows], posed, mixture, V, which=which, base=base[rows],
                                 distance=em.distance, normal_noise_rad=em.normal_noise_rad)[:, 0]

    return screened_scores(score, len(hypotheses.t), len(y), _LIMB_SCREEN_POINTS, _LIMB_SCREEN_KEEP)


def _limb_grid(body: BodyModel, pose: np.ndarray, limb: Limb) -> np.ndarray:
    """Limb angles (M, K): every combination of `_LIMB_GRID_LEVELS` values across the joint range of each
    DOF of the limb's first two segments that the data see (twists, which have a prior, keep their
    current value, as do the DOFs further down the chain)."""
    first = np.isin(body.dof_segment[limb.dofs], limb.segments[:2]) & (body.prior_weight[limb.dofs] == 0)
    axes = [np.linspace(body.lower[d], body.upper[d], _LIMB_GRID_LEVELS) for d in limb.dofs[first]]
    grid = np.repeat(pose[limb.dofs][None], _LIMB_GRID_LEVELS ** len(axes), axis=0)
    grid[:, first] = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(axes))
    return grid
