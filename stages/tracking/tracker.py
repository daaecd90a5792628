"""Tracking over time: one EM fit per frame from a constant-velocity prediction, with recovery.

Every frame starts from the previous pose plus the previous frame-to-frame change (constant
velocity), which is close enough for EM to converge in a few iterations (Horaud et al. 2009, Sec. 3:
"robust tracking"); each DOF's change is carried on in the share the track has found it predictive
(`velocity_gain`), and a limb's change by a search or an exchange not at all. What the paper leaves open
is handled here:

- first frame and after a loss: automatic initialisation from the data (`init.initialise`);
- the height, over the initialisations of the first `scale_frames` frames (averaged): with none stated,
  estimated by each (the cloud's top, then EM); with one stated, each searches at the current size and
  EM measures the size from its result (`measured_height`), weighed against the stated one
  (`stated_height_weight`, `subject_height`); the segment-length and girth factors named by
  `estimate_lengths` (groups of the body file's `lengths`) are estimated with the pose over those frames
  (prior towards the body file's proportions; each frame's EM from the mean so far and from those
  proportions, the likelier kept) and averaged, then frozen. The tracked frames do not refine the
  height: their EM, with the girth and lengths free as well, drifted it upward on stout bodies;
- a frame far worse than usual even after more EM iterations is also fitted from the last pose
  without velocity (`restart_drop`), the better fit kept;
- failure detection: an outlier fraction above `max_outlier_fraction`, or a Σ wider than both
  `failure_sigma_m` and what this capture's good fits usually are (`spread_limit`) in a fit less likely
  than usual (on the first frame after an initialisation, than that initialisation's fit), or held at the
  `max_sigma_m` ceiling, triggers a re-initialisation, and the better of the two fits (by likelihood) is
  kept; a frame that was fitted is never dropped:
  when both fail the checks, the better one is the estimate, flagged `doubtful`; after a doubtful
  initialisation the next frame tracks from it and weighs a fresh initialisation against that fit;
  a re-initialisation that turns the subject around (more than a quarter-turn from the track) must beat a
  search over the track's half-turn clearly: the data alone cannot tell which way a pose symmetric front
  to back faces;
- a limb that explains far fewer data than its mirror limb (an arm put on the wrong side of the
  body), or than it did over the recent tracked frames (a forearm folded onto its upper arm or
  turned away from its data, which may still explain as many data as its mirror), or that has folded
  onto itself since the last frame (`limbs.folded_limbs`), is re-initialised locally after every fit
  (`limbs.reinitialise_limb`, which never lands in a fold), and kept only on a clear likelihood gain;
  after an initialisation every limb is searched so, once; a fit worse than usual (`refit_drop` below the
  likelihood level) also tries the legs exchanged (`limbs.swap_limbs`: legs that passed each other and
  took each other's data, which no share test sees); a limb that the share tests suspect and its searches keep
  in place frame after frame is searched at doubling intervals while the fits stay as good as usual, and the
  legs' exchange at doubling intervals over a run of worse fits that it does not improve
  (`limbs.search_backoff`);
- frames with no or too few observations: the pose is predicted (velocity decaying) and flagged
  "predicted", then "lost" when the gap lasts; tracking re-initialises when data return.
Nothing here produces NaN: unusable rows of the input are dropped and every output is finite.

A `Tracker` is built once per run from the parameters and the working volume: it holds the body
(from the body file, with the length groups to estimate left free), its pose library and limbs, and
the body sized to the current height and length factors; `Tracker.track` takes one frame.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from stages.tracking.body import BodyModel
from stages.tracking.distances import distance_named
from stages.tracking.em import EMParams, FitResult, fit
from stages.tracking.init import initialise
from stages.tracking.library import load_pose_library
from stages.tracking.limbs import (
    body_limbs,
    checks_due,
    deserted_limbs,
    folded_limbs,
    misplaced_limbs,
    reinitialise_limb,
    search_backoff,
    segment_shares,
    swap_limbs,
)
from stages.tracking.mixture import Mixture, volume_size
from stages.tracking.params import TrackerParams, shipped_body
from stages.tracking.results import FrameResult, TrackerState, at_sigma_ceiling, sigma_spread, spread_limit

# Weight of a new frame in the running log-likelihood level (an exponential average over ~10 frames).
_LEVEL_RATE = 0.1
# Stopping rule of the extra EM iterations of a frame worse than usual: close to full convergence
# (1e-3 nats per observation, joints still by half a millimetre), since such frames are few.
_REFIT_TOLERANCE = 1e-3
_REFIT_DISPLACEMENT_M = 5e-4
# How many times as many library poses a failed initialisation refines when it searches again.
_WIDER_SEARCH = 5
# Normals shorter than this are not directions; such rows are dropped.
_MIN_NORMAL = 1e-6
# A joint this close to its segment's joint centre (metres) sits on it (`joint_support`).
_AT_JOINT_CENTRE_M = 1e-9


class Tracker:
    """The tracker of one run: its parameters, the working volume and the body model with what derives from it.

    Attributes
    ----------
    params : TrackerParams
    volume : (2, 3) float
        Working volume [min; max], metres (the outlier density's support).
    body : BodyModel
        The body with only the length groups `params.estimate_lengths` left free; its height
        is replaced by `params.height_m`, the data's estimate or the two weighed (`subject_height`).
    library : (M, D) float
        The body's pose library (`library.load_pose_library`), for initialisations and limb recovery.
    limbs : list of Limb
        The body's limbs and their mirrors (`limbs.body_limbs`).
    legs : list of Limb
        One of each pair of mirror limbs hanging from the root segment (the legs, from the pelvis), which
        a frame worse than usual tries exchanged (`limbs.swap_limbs`): legs pass each other at every stride,
        while the arms' exchange would cost an EM fit per such frame as well for no case found. None with a
        distance other than "normals": legs exchanged cover the same points, and without the normals'
        evidence the exchange wins on noise (its figures: docs/results_by_hand.md).
    """

    def __init__(self, params: TrackerParams, volume: np.ndarray, body: BodyModel | None = None):
        """`body` is the body `params.body` names, its length groups checked against the parameters: a shipped
        body is loaded here when it is not given (`TrackerParams` checked it); a body file's, which the pipeline
        reads and checks (`pipeline.io.body_io.tracking_body`), must be given."""
        self.params = params
        self.volume = np.asarray(volume, dtype=float)
        volume_size(self.volume)
        self.body = (shipped_body(params.body) if body is None else body).with_length_groups(params.estimate_lengths)
        self.library = load_pose_library(self.body)
        self.limbs = body_limbs(self.body)
        root = np.flatnonzero(self.body.parent < 0)
        legs = [limb for limb in self.limbs
                if self.body.parent[limb.segments[0]] in root and limb.segments[0] < limb.mirror_segments[0]]
        self.legs = legs if params.distance == "normals" else []
        self._sized: dict = {}

    def track(self, state: TrackerState | None, obs) -> tuple[FrameResult, TrackerState]:
        """Estimate one frame's pose from its observations and the tracker's state (None on the first frame).

        `obs` is any object with `points` (N, 3) and `normals` (N, 3) (metres, unit outward normals). The
        frame's EM starts from the constant-velocity prediction with Σ grown by σ² I; a fit that fails
        the checks (or a periodic or pending re-check) is weighed against a fresh initialisation.
        """
        params = self.params
        y, n = _usable(obs)
        if state is None:
            state = self._first_state()
        sized = self._sized_body(state)
        if len(y) < params.min_observations:
            return _predict(state, sized, params, len(y))
        if state.lost:
            return self._initialise(state, y, n, sized, alone=True)
        learning = state.height_weight < params.scale_frames
        em = replace(params.em, estimate_lengths=learning and bool(params.estimate_lengths))
        prediction = sized.clip(state.pose + velocity_gain(state) * state.velocity)
        mixture = Mixture(Sigma=state.Sigma + params.sigma_m**2 * np.eye(len(state.Sigma)), pi=state.pi)
        tracked = self._fit_from(prediction, state, y, n, sized, mixture, em)
        if em.estimate_lengths and np.any(state.length_factors != self.body.length_factors):
            tracked = self._likelier_fresh_lengths(prediction, state, y, n, mixture, em, tracked)
        # The searches move limbs at the lengths the frame's own fit has learnt: a search looks for a pose, and with
        # the lengths free each of its EM iterations costs several.
        searching = replace(em, estimate_lengths=False)
        tracked, moved, searches = self._search_limbs(y, n, tracked, state, searching)
        tracked, exchanged, exchanges = self._exchange_legs(y, n, tracked, state, searching)
        moved |= exchanged
        doubtful = _failed(tracked, params, spread_limit(state, params.failure_sigma_m),
                           usual=_as_likely_as_usual(tracked, len(y), state, params))
        tried = doubtful or 0 < params.reinit_every <= state.since_initialisation + 1 or state.recheck
        if tried:
            result, new_state = self._initialise(state, y, n, sized)
            # A fit that passed the checks from an estimate that did too is replaced only on clear evidence
            # (`reinit_margin`).
            margin = 0.0 if doubtful or state.recheck else params.reinit_margin * len(y)
            if result.log_likelihood > tracked.log_likelihood[-1] + margin:
                return result, new_state
        return self._tracked(state, tracked, len(y), learning, doubtful, tried, moved, searches, exchanges)

    def _likelier_fresh_lengths(self, prediction, state, y, n, mixture, em, tracked: FitResult) -> FitResult:
        """The likelier of `tracked` (a learning frame's fit whose lengths started from their running mean) and
        the same fit with the lengths started from the body file's proportions.

        Started from the running mean, a frame's EM settles near it, so an early wrong estimate confirms itself
        frame after frame (a forearm whose hand the data leave ambiguous comes out long or short by a mere
        re-encoding of the videos); started afresh, a frame whose pose misleads the lengths loses a good
        estimate the frames before had made. The data decide between the two starts.
        """
        fresh = self._fit_from(prediction, state, y, n, self._sized_body(state, self.body.length_factors), mixture,
                               em)
        return fresh if fresh.log_likelihood[-1] > tracked.log_likelihood[-1] else tracked

    def _sized_body(self, state: TrackerState, lengths: np.ndarray | None = None) -> BodyModel:
        """The body at the state's height and length factors (or `lengths`), remembered for the last two asked.

        They stop changing after `scale_frames` frames; remembering the body saves an eigen-decomposition
        per ellipsoid at every frame.
        """
        lengths = state.length_factors if lengths is None else lengths
        key = (state.height_m, lengths.tobytes())
        if key not in self._sized:
            if len(self._sized) > 1:  # the learning frames' two starts, then the learnt lengths alone
                self._sized.clear()
            self._sized[key] = self.body.scaled(state.height_m).with_lengths(lengths)
        return self._sized[key]

    def _first_state(self) -> TrackerState:
        """The state before any data: lost, standing at the volume's centre, the body's proportions."""
        body, params = self.body, self.params
        height = params.height_m if params.height_m is not None else body.height_m
        pose = body.scaled(height).zero_pose()
        pose[:2] = self.volume.mean(axis=0)[:2]  # a finite stand-in until data arrive
        mixture = Mixture.initial(body.n_ellipsoids, params.sigma_m, distance_named(params.distance).size)
        return TrackerState(pose=pose, velocity=np.zeros(body.pose_size), height_m=height,
                            length_factors=body.length_factors.copy(), height_weight=0, Sigma=mixture.Sigma,
                            pi=mixture.pi, likelihood_level=np.nan, frames_without_fit=0, lost=True)

    def _fit_from(self, prediction, state, y, n, sized, mixture, em) -> FitResult:
        """EM from the prediction; a fit worse than usual (`refit_drop`) gets more iterations and, when still
        far worse (`restart_drop`), is weighed against a fit from the last pose without velocity."""
        params = self.params
        tracked = fit(y, n, sized, prediction, self.volume, em, mixture=mixture)
        if not _worse_than_usual(tracked, len(y), state, params):
            return tracked
        # Worse than usual: fast motion, which the quick stopping rule can leave half-way. EM goes on.
        more = fit(y, n, tracked.body, tracked.pose, self.volume,
                   replace(em, max_iterations=params.refit_iterations, tolerance=_REFIT_TOLERANCE,
                           displacement_m=_REFIT_DISPLACEMENT_M), mixture=tracked.mixture, prior_pose=prediction,
                   start=tracked.estep)
        tracked = replace(more, iterations=tracked.iterations + more.iterations)
        per_obs = tracked.log_likelihood[-1] / len(y)
        if per_obs < state.likelihood_level - params.restart_drop and np.any(state.velocity):
            # Still far worse: the motion may have stopped or turned, and the constant-velocity prediction
            # overshot into another optimum (a kicking leg folded sideways). EM from the last pose as well.
            still = fit(y, n, sized, sized.clip(state.pose), self.volume, replace(
                em, max_iterations=params.max_iterations + params.refit_iterations,
                tolerance=_REFIT_TOLERANCE, displacement_m=_REFIT_DISPLACEMENT_M), mixture=mixture)
            if still.log_likelihood[-1] > tracked.log_likelihood[-1]:
                tracked = replace(still, iterations=tracked.iterations + still.iterations)
        return tracked

    def _search_limbs(self, y, n, tracked: FitResult, state: TrackerState,
                      em: EMParams) -> tuple[FitResult, dict[str, np.ndarray], tuple[np.ndarray, np.ndarray]]:
        """The tracked fit after the limb searches (`_recover_limbs`), the limbs they moved (name -> DOFs), and
        the limbs' searches in a row that kept the fit and their waits after this frame (`limbs.search_backoff`).

        A limb waits only while the fit is as good as usual: a fit worse than usual (`refit_drop`) is a change
        the wait did not foresee (a kick starting from a leg the search had kept in place).
        """
        misses, wait = _search_counts(state.search_misses, state.search_wait, len(self.limbs))
        usual = not _worse_than_usual(tracked, len(y), state, self.params)
        every = self.params.limb_check_every if self.params.limbs.share_ratio > 0 else 0  # 0: no limb recovery
        due = checks_due(state.since_initialisation + 1, len(self.limbs), every)
        tracked, searched, kept = self._recover_limbs(y, n, tracked, em, state.segment_shares, state.pose,
                                                      (wait > 0) & usual, due)
        moved = {limb.name: limb.dofs for limb, still in zip(self.limbs, kept, strict=True) if not still}
        return tracked, moved, search_backoff(misses, wait, searched, kept)

    def _exchange_legs(self, y, n, tracked: FitResult, state: TrackerState,
                       em: EMParams) -> tuple[FitResult, dict[str, np.ndarray], tuple[np.ndarray, np.ndarray]]:
        """The tracked fit after each pair of `legs` was tried exchanged (`limbs.swap_limbs`) if it is worse than
        usual (`refit_drop`) and the pair is not waiting, the exchanges kept ("l_thigh/r_thigh" -> both legs' DOFs),
        and the pairs' tries in a row that kept the fit and their waits after this frame (`limbs.search_backoff`)."""
        misses, wait = _search_counts(state.exchange_misses, state.exchange_wait, len(self.legs))
        tried = _worse_than_usual(tracked, len(y), state, self.params) & (wait == 0)
        kept = np.ones(len(self.legs), dtype=bool)
        moved = {}
        for index in np.flatnonzero(tried):
            legs = self.legs[index]
            exchanged = swap_limbs(y, n, tracked, legs, self.volume, em)
            kept[index] = exchanged is tracked
            if not kept[index]:
                mirror = self.body.segment_names[legs.mirror_segments[0]]
                moved[f"{legs.name}/{mirror}"] = np.concatenate([legs.dofs, legs.mirror_dofs])
            tracked = exchanged
        return tracked, moved, search_backoff(misses, wait, tried, kept)

    def _tracked(self, state: TrackerState, tracked: FitResult, observations: int, learning: bool, doubtful: bool,
                 tried: bool, moved: dict[str, np.ndarray], searches: tuple[np.ndarray, np.ndarray],
                 exchanges: tuple[np.ndarray, np.ndarray]) -> tuple[FrameResult, TrackerState]:
        """The estimate of a tracked frame and the state after it: the length factors' running mean (while
        `learning`), the likelihood level and segment shares (exponential averages), the velocity, the limbs'
        `searches` and the legs' `exchanges` in a row that kept the fit and their waits (`limbs.search_backoff`).

        The limbs a search or an exchange `moved` (name -> DOFs) are the estimate's `corrected`, and their DOFs
        get no velocity: their change over this frame is a correction, not motion, and carried on it would throw
        the limb as far again at the next frame. For the same reason no DOF gets any on the first frame after an
        initialisation: its change is mostly the EM's correction of the search's coarse pose."""
        per_obs = tracked.log_likelihood[-1] / observations
        height, lengths, weight = state.height_m, state.length_factors, state.height_weight
        if learning:  # running mean of the per-frame estimates of ln ℓ
            weight += 1
            lengths = lengths * (tracked.body.length_factors / lengths) ** (1.0 / weight)
        level = per_obs if not np.isfinite(state.likelihood_level) else (
            (1 - _LEVEL_RATE) * state.likelihood_level + _LEVEL_RATE * per_obs)
        shares = segment_shares(tracked.body, tracked.mixture)
        if doubtful:
            shares = state.segment_shares
        elif state.segment_shares is not None:
            shares = (1 - _LEVEL_RATE) * state.segment_shares + _LEVEL_RATE * shares
        # A doubtful fit's motion is not carried on: the next frame starts from it at rest.
        after_initialisation = not np.isfinite(state.likelihood_level) or state.recheck
        moving = state.frames_without_fit == 0 and not doubtful and not after_initialisation
        velocity = tracked.pose - state.pose if moving else np.zeros_like(state.velocity)
        for dofs in moved.values():
            velocity[dofs] = 0.0
        spread_level, spread_variance = state.spread_level, state.spread_variance
        if not doubtful:
            spread_level, spread_variance = running_spread(state, sigma_spread(tracked.mixture.Sigma))
        covariance, variance = state.velocity_covariance, state.velocity_variance
        if moving and np.any(state.velocity):
            if covariance is None:
                covariance, variance = np.zeros_like(velocity), np.zeros_like(velocity)
            covariance = (1 - _LEVEL_RATE) * covariance + _LEVEL_RATE * state.velocity * velocity
            variance = (1 - _LEVEL_RATE) * variance + _LEVEL_RATE * state.velocity**2
        new_state = TrackerState(pose=tracked.pose, velocity=velocity, height_m=height, length_factors=lengths,
                                 measured_height_m=state.measured_height_m, height_weight=weight,
                                 Sigma=tracked.mixture.Sigma, pi=tracked.mixture.pi,
                                 likelihood_level=level, frames_without_fit=0, lost=False,
                                 since_initialisation=0 if tried else state.since_initialisation + 1,
                                 segment_shares=shares, velocity_covariance=covariance,
                                 velocity_variance=variance, search_misses=searches[0], search_wait=searches[1],
                                 exchange_misses=exchanges[0], exchange_wait=exchanges[1],
                                 spread_level=spread_level, spread_variance=spread_variance)
        result = FrameResult(pose=tracked.pose, joints=tracked.joints,
                             log_likelihood=tracked.log_likelihood[-1], iterations=tracked.iterations,
                             outlier_fraction=tracked.outlier_fraction, status="tracked", height_m=tracked.height_m,
                             doubtful=doubtful, observations=observations,
                             joint_support=joint_support(tracked.body, tracked.mixture, observations),
                             corrected=tuple(moved))
        return result, new_state

    def _recover_limbs(self, y, n, result: FitResult, em: EMParams, usual_shares=None,
                       previous: np.ndarray | None = None, waiting: np.ndarray | None = None,
                       due: np.ndarray | None = None) -> tuple[FitResult, np.ndarray, np.ndarray]:
        """The fit with each limb that explains far fewer data than its mirror, or than it usually does
        (`usual_shares`, the running level of `limbs.segment_shares`; None: no history), or that has folded
        onto itself since the `previous` pose (`limbs.folded_limbs`; None: no previous pose), re-initialised
        locally; and which of `self.limbs` were searched and which of them kept their place (L,) bool each.
        The limbs `waiting` (L,) bool (`limbs.search_backoff`; None: none) are left to the fold test; the limbs
        `due` (L,) bool for their periodic search (`TrackerParams.limb_check_every`; None: none) are searched.

        A limb EM put on the wrong side of the body or folded away from its data gets almost no
        observations, and the local minimum holds it there for many frames; trying the library's angles
        for that limb alone (`limbs.reinitialise_limb`) finds it again, and the likelihood decides.
        """
        ready = self.limbs if waiting is None else [limb for limb, wait in zip(self.limbs, waiting, strict=True)
                                                    if not wait]
        limbs = misplaced_limbs(ready, result, len(y), self.params.limbs)
        if usual_shares is not None:
            limbs += deserted_limbs(ready, result, usual_shares, len(y), self.params.limbs)
        if self.params.limbs.share_ratio > 0:
            limbs += folded_limbs(self.limbs, result, previous)
        suspects = {limb.name for limb in limbs}
        suspected = np.array([limb.name in suspects for limb in self.limbs])
        checked = ~suspected & (due if due is not None else False)  # due, and suspected by no test
        searched = suspected | checked
        kept = np.ones(len(self.limbs), dtype=bool)
        for index in np.flatnonzero(searched):
            # A check refines only the likeliest hypothesis away from where the limb is: the fit is an optimum there.
            check = {"refine": 1, "elsewhere": True} if checked[index] else {}
            recovered = reinitialise_limb(y, n, result, self.limbs[index], self.volume, em, self.library,
                                          rng=np.random.default_rng(self.params.seed), **check)
            kept[index] = recovered is result
            result = recovered
        return result, searched, kept

    def _initialise(self, state: TrackerState, y, n, body: BodyModel, *,
                    alone: bool = False) -> tuple[FrameResult, TrackerState]:
        """Initialise from the data alone (`init.initialise`) and start a fresh track.

        `alone`: there is no track to weigh the result against (the first frame, data back after a gap). Then a
        search whose fit fails the checks is made again refining `_WIDER_SEARCH` times as many library poses,
        and the likelier kept: a subject walking into view mid-kick was otherwise exported far off until the next
        frame's re-check. A re-check is not widened: it has the tracked fit to fall back on, and widened there it
        traded captures against each other (both measured in docs/results_by_hand.md).

        A re-check whose search faces the subject more than a quarter-turn away from the track (`turned_around`,
        which says why) is weighed against a search over the track's half-turn (`init.initialise`'s `facing`),
        kept unless the turned one is likelier by `InitParams.finalist_margin` per observation.

        A doubtful initialisation is still the best pose the data gave: the next frame tracks from it (at
        rest) and tries a fresh initialisation against that fit, keeping the likelier (`recheck`). Starting
        every such frame from scratch threw the track away: on imperfect data the initialisations of
        consecutive frames landed in different poses, where tracking from the first would have explained
        the data far better. The likelihood level is left to the tracked frames: an initialisation's fit (a
        coarse search, sometimes with a limb still wrong) set it so low that the next frames' slips went
        unnoticed.

        Every limb of the initialisation's fit is then searched on its own (`limbs.reinitialise_limb`, kept
        on a clear gain only), not just the limbs the share tests find. The whole-body search ranks library
        poses, each with its own limbs: a pose whose trunk and legs fit can carry an arm from another pose
        that still explains some of the data (an arm hanging by a crouching subject's legs), so that no
        share test fires and tracking holds the arm there for tens of frames. It costs four limb searches per
        initialisation (their figures: docs/results_by_hand.md).
        """
        params = self.params
        stated = params.height_m is not None
        measure = (not stated or params.stated_height_weight < 1) and state.height_weight < params.scale_frames
        # A stated height sizes the search; the size is measured from its result (`measured_height`).
        search_size = measure and not stated

        def search(init_params=params.init, facing=None):  # each search from the same draw (`TrackerParams.seed`)
            return initialise(y, n, body, self.volume, self.library, estimate_height=search_size, em=params.em,
                              params=init_params, rng=np.random.default_rng(params.seed), facing=facing)

        init = search()
        if alone and _failed(init.fit, params):  # the coarse ranking can leave the pose that fits unrefined
            wider = search(replace(params.init, refine=params.init.refine * _WIDER_SEARCH))
            if wider.fit.log_likelihood[-1] > init.fit.log_likelihood[-1]:
                init = wider
        if not alone and turned_around(init.pose, state.pose):
            facing = search(facing=state.pose[3])
            if init.fit.log_likelihood[-1] < facing.fit.log_likelihood[-1] + params.init.finalist_margin * len(y):
                init = facing
        fitted = init.fit
        em = replace(params.em, estimate_scale=search_size)
        for limb in self.limbs:
            fitted = reinitialise_limb(y, n, fitted, limb, self.volume, em, self.library,
                                       rng=np.random.default_rng(params.seed))
        for _ in range(2):  # a limb moved by the first pass can leave its mirror (or itself) still misplaced
            recovered, _, _ = self._recover_limbs(y, n, fitted, em)
            if recovered is fitted:
                break
            fitted = recovered
        doubtful = _failed(fitted, params)
        height, measured, weight = state.height_m, state.measured_height_m, state.height_weight
        if measure:
            weight += 1
            now = measured_height(y, n, fitted, self.volume, params.em) if stated else init.height_m
            measured = now if measured is None else measured + (now - measured) / weight
            height = subject_height(params.height_m, measured, params.stated_height_weight)
        new_state = replace(state, pose=fitted.pose, velocity=np.zeros_like(fitted.pose), height_m=float(height),
                            measured_height_m=measured, height_weight=weight, Sigma=fitted.mixture.Sigma,
                            pi=fitted.mixture.pi,
                            likelihood_level=state.likelihood_level if doubtful else np.nan,
                            frames_without_fit=0, lost=False, since_initialisation=0, segment_shares=None,
                            recheck=doubtful, search_misses=None, search_wait=None,
                            exchange_misses=None, exchange_wait=None,
                            start_level=np.nan if doubtful else fitted.log_likelihood[-1] / len(y))
        result = FrameResult(pose=fitted.pose, joints=fitted.joints,
                             log_likelihood=fitted.log_likelihood[-1], iterations=fitted.iterations,
                             outlier_fraction=fitted.outlier_fraction, status="initialised", height_m=init.height_m,
                             doubtful=doubtful, observations=len(y),
                             joint_support=joint_support(fitted.body, fitted.mixture, len(y)))
        return result, new_state


def measured_height(y: np.ndarray, n: np.ndarray, result: FitResult, volume: np.ndarray, em: EMParams) -> float:
    """The height (metres) EM gives when it goes on from a fit of these data with the body's overall size free.

    With a stated height the initialisation searches at the current size (the stated one, then the weighed
    one) and the size is measured from its pose: a search for the size and the pose together cannot tell a
    crouching tall subject from a standing short one, and a subject crouching in the first frames started the
    track far off (docs/results_by_hand.md).
    """
    free_size = replace(em, estimate_scale=True)
    return fit(y, n, result.body, result.pose, volume, free_size, mixture=result.mixture).height_m


def subject_height(stated: float | None, measured: float, stated_weight: float) -> float:
    """The height to size the body at: the `measured` one (metres) weighed with a `stated` one (None: none) in log,
    stated^w × measured^(1 − w) with w = `stated_weight`.

    In log because heights err by a factor: a stature fixes the joints through the body's proportions, off by
    a few per cent from one body to the next, and the data's estimate errs by a few per cent on bodies of
    unusual proportions.
    """
    if stated is None:
        return float(measured)
    return float(np.exp(stated_weight * np.log(stated) + (1.0 - stated_weight) * np.log(measured)))


def joint_support(body: BodyModel, mixture: Mixture, n_observations: int) -> np.ndarray:
    """(17,) observations explained by the segment that places each joint of `JOINT_NAMES`.

    A joint at its segment's joint centre (an elbow at the forearm's) is placed by the parent segment
    (the upper arm: its direction sets where the elbow is); any other joint (a wrist) by the segment
    carrying it. The root's joint (the pelvis) by the root. The data a segment explains are I Σ π_p over
    its ellipsoids (`limbs.segment_shares`).
    """
    segment = body.joint_segment
    at_centre = np.all(np.abs(body.joint_offset) < _AT_JOINT_CENTRE_M, axis=1) & (body.parent[segment] >= 0)
    placing = np.where(at_centre, body.parent[segment], segment)
    return n_observations * segment_shares(body, mixture)[placing]


def turned_around(pose: np.ndarray, previous: np.ndarray) -> bool:
    """Whether `pose` faces more than a quarter-turn away from `previous` (their yaws, `pose[3]`).

    A subject does not turn that far between two frames, while a body turned around with left and right
    exchanged covers much the same space as the body facing the right way whenever the pose is close to
    symmetric front to back (a wide stance, arms by the sides): its fit can then score as well, or better
    than a tracked fit gone slightly astray.
    """
    return bool(abs(np.angle(np.exp(1j * (pose[3] - previous[3])))) > np.pi / 2)


def _below(level: float, result: FitResult, observations: int, params: TrackerParams) -> bool:
    """Whether a fit's log-likelihood per observation is `refit_drop` below ``level`` (nats; never when NaN)."""
    return bool(np.isfinite(level) and result.log_likelihood[-1] / observations < level - params.refit_drop)


def _worse_than_usual(result: FitResult, observations: int, state: TrackerState, params: TrackerParams) -> bool:
    """Whether a fit's log-likelihood per observation is `refit_drop` below the track's level (never while the
    level is unknown): what gets more EM iterations, the legs' exchange, and the limbs' searches at once."""
    return _below(state.likelihood_level, result, observations, params)


def _as_likely_as_usual(result: FitResult, observations: int, state: TrackerState, params: TrackerParams) -> bool:
    """Whether a fit's log-likelihood per observation is within `refit_drop` of the track's level or, on the first
    frame after an initialisation that passed the checks, of that initialisation's fit (`TrackerState.start_level`);
    never when neither is known.

    That first frame has no track's fits to be judged by, and its EM, started from the initialisation's Σ grown by
    the prediction error and stopped after a few iterations, often leaves Σ wider than `failure_sigma_m` on data
    whose good fits are wide: explaining its data about as well as the initialisation explained the frame before,
    it is no failure, and judged one it cost a second initialisation and a doubtful flag.
    """
    level = state.likelihood_level if np.isfinite(state.likelihood_level) else state.start_level
    return bool(np.isfinite(level)) and not _below(level, result, observations, params)


def _search_counts(misses: np.ndarray | None, wait: np.ndarray | None, count: int) -> tuple[np.ndarray, np.ndarray]:
    """A state's misses and waits of `limbs.search_backoff`, zeros (count,) when it has none yet."""
    if misses is None or wait is None:
        return np.zeros(count, dtype=int), np.zeros(count, dtype=int)
    return misses, wait


def velocity_gain(state: TrackerState) -> np.ndarray | float:
    """(D,) how much of each DOF's last frame-to-frame change the next frame's prediction carries on, in [0, 1]
    (1 until the track has measured it).

    The least-squares coefficient of a DOF's change on its change one frame earlier over the recent tracked
    frames, ⟨v_{t−1} v_t⟩ / ⟨v_{t−1}²⟩ (`TrackerState.velocity_covariance` over `velocity_variance`): close to 1
    where the motion is smooth from frame to frame (a run's legs, a walker's translation), towards 0 where the
    changes are mostly the fits' own jitter, which a full constant-velocity step would carry into the next
    frame's start doubled (a slow walk's or a crouch's joints).
    """
    if state.velocity_variance is None:
        return 1.0
    ratio = state.velocity_covariance / np.maximum(state.velocity_variance, np.finfo(float).tiny)
    return np.clip(np.where(state.velocity_variance > 0, ratio, 1.0), 0.0, 1.0)


def _failed(result: FitResult, params: TrackerParams, spread_limit_m: float | None = None,
            usual: bool = False) -> bool:
    """Whether a fit fails the checks: too many outliers, a Σ held at the `max_sigma_m` ceiling, or a Σ wider
    than `spread_limit_m` (default `failure_sigma_m`) in a fit not `usual` (`_as_likely_as_usual`).

    A Σ as wide as the data's spread around the wrong surface is what a torso or a pair of legs locked onto
    the wrong data looks like, while the outlier fraction stays small. A tracked fit is judged against what
    the track's good fits are (`spread_limit`); an initialisation, which has no track behind it, against
    `failure_sigma_m` alone: its fit is coarse by design, and one wider than that is checked again at the next
    frame (`TrackerState.recheck`), a cheap guard against starting a track in a wrong pose.

    A wide Σ fails only a fit that explains its data worse than the track's fits usually do. Locked onto the
    wrong data, a body explains them worse; a frame of worse data (a lossy frame, a flicker, a view that
    cut the subject off) widens Σ as much, while the fit explains them as well as the track's fits do theirs,
    and an initialisation there finds the same optimum or, barely likelier, a limb somewhere else.
    """
    wide = sigma_spread(result.mixture.Sigma)
    limit = params.failure_sigma_m if spread_limit_m is None else spread_limit_m
    return (result.outlier_fraction > params.max_outlier_fraction or (wide > limit and not usual)
            or at_sigma_ceiling(wide, params.max_sigma_m))


def running_spread(state: TrackerState, spread: float) -> tuple[float, float]:
    """`TrackerState.spread_level` and `spread_variance` after a fit of this Σ `spread` passed the checks
    (exponentially weighted mean and variance, at the likelihood level's rate)."""
    if not np.isfinite(state.spread_level):
        return spread, 0.0
    change = spread - state.spread_level
    return (state.spread_level + _LEVEL_RATE * change,
            (1 - _LEVEL_RATE) * (state.spread_variance + _LEVEL_RATE * change**2))


def _usable(obs) -> tuple[np.ndarray, np.ndarray]:
    """Finite points and unit normals (I, 3) each; rows with NaN/inf or null normals dropped."""
    y = np.asarray(obs.points, dtype=float).reshape(-1, 3)
    n = np.asarray(obs.normals, dtype=float).reshape(-1, 3)
    if len(y) != len(n):
        raise ValueError(f"observations: {len(y)} points but {len(n)} normals, expected as many")
    length = np.linalg.norm(n, axis=1)
    keep = np.all(np.isfinite(y), axis=1) & np.isfinite(length) & (length > _MIN_NORMAL)
    return y[keep], n[keep] / length[keep, None]


def _predict(state: TrackerState, body: BodyModel, params: TrackerParams,
             observations: int) -> tuple[FrameResult, TrackerState]:
    """A frame without a fit: continue the motion (slowing down), flag it, declare a loss when long."""
    gap = state.frames_without_fit + 1
    lost = state.lost or gap > params.max_predicted_frames
    velocity = state.velocity * params.velocity_decay if not lost else np.zeros_like(state.velocity)
    pose = body.clip(state.pose + velocity)
    new_state = TrackerState(pose=pose, velocity=velocity, height_m=state.height_m,
                             length_factors=state.length_factors, measured_height_m=state.measured_height_m,
                             height_weight=state.height_weight,
                             Sigma=state.Sigma, pi=state.pi, likelihood_level=state.likelihood_level,
                             frames_without_fit=gap, lost=lost, segment_shares=state.segment_shares,
                             spread_level=state.spread_level, spread_variance=state.spread_variance)
    result = FrameResult(pose=pose, joints=body.joint_positions(pose), log_likelihood=0.0, iterations=0,
                         outlier_fraction=1.0, status="lost" if lost else "predicted", height_m=state.height_m,
                         observations=observations)
    return result, new_state
