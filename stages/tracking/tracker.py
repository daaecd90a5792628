"""Tracking over time: one EM fit per frame from a constant-velocity prediction, with recovery.

Every frame starts from the previous pose plus the previous frame-to-frame change (constant
velocity), which is close enough for EM to converge in a few iterations (Horaud et al. 2009, Sec. 3:
"robust tracking"). What the paper leaves open is handled here:

- first frame and after a loss: automatic initialisation from the data (`init.initialise`);
- unknown height: estimated by the initialisation (the cloud's top, then EM; averaged over the
  initialisations of the first `scale_frames` frames); the segment-length and girth factors named by
  `estimate_lengths` (groups of the body file's `lengths`) are estimated with the pose over those frames
  (prior towards the body file's proportions), then frozen. The tracked frames do not refine the
  height: their EM, with the girth and lengths free as well, drifted it upward on stout bodies;
- a frame far worse than usual even after more EM iterations is also fitted from the last pose
  without velocity (`restart_drop`), the better fit kept;
- failure detection, by absolute checks that a bad start cannot make the norm: an outlier fraction
  above `max_outlier_fraction` or a Σ wider than `failure_sigma_m` triggers a re-initialisation,
  and the better of the two fits (by likelihood) is kept; a frame that was fitted is never dropped:
  when both fail the checks, the better one is the estimate, flagged `doubtful`; after a doubtful
  initialisation the next frame tracks from it and weighs a fresh initialisation against that fit;
- a limb that explains far fewer data than its mirror limb (an arm put on the wrong side of the
  body), or than it did over the recent tracked frames (a forearm folded onto its upper arm or
  turned away from its data, which may still explain as many data as its mirror), is re-initialised
  locally after every fit (`init.reinitialise_limb`), and kept only on a clear likelihood gain;
- frames with no or too few observations: the pose is predicted (velocity decaying) and flagged
  "predicted", then "lost" when the gap lasts; tracking re-initialises when data return.
Nothing here produces NaN: unusable rows of the input are dropped and every output is finite.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from calib.errors import InputError
from stages.checks import check_choice, check_int, check_number
from stages.joints import SUBJECT_HEIGHT_RANGE_M
from stages.tracking.body import BodyModel, shipped_length_groups
from stages.tracking.distances import DISTANCES, distance_named
from stages.tracking.em import EMParams, FitResult, Mixture, fit, volume_size
from stages.tracking.init import (
    LIMB_MIN_OBSERVATIONS,
    LIMB_SHARE_RATIO,
    InitParams,
    deserted_limbs,
    initialise,
    load_pose_library,
    misplaced_limbs,
    reinitialise_limb,
    segment_shares,
)

STATUSES = ("tracked", "initialised", "predicted", "lost")


@dataclass(frozen=True)
class TrackerParams:
    """Tunables of the tracker (defaults are generic, not tuned to one sequence).

    Attributes
    ----------
    height_m : float or None
        Subject's standing height in metres; None = estimate it from the data.
    distance : {"normals", "points", "algebraic"}
        Datum-to-ellipsoid distance (the paper's is "normals").
    max_iterations : int
        EM iterations per frame at most.
    tolerance : float
        EM stops when the log-likelihood gain per observation is below this (nats).
    displacement_m : float
        EM stops when no joint centre moved more than this in an iteration (metres).
    estimate_lengths : tuple of str
        Length groups of the body (its file's `lengths`) whose factors are estimated over the first
        `scale_frames` frames; the others stay at the file's proportions; () estimates none. The
        defaults are the groups the data pin down: the bending elbow and knee bound the upper arm and the
        shank, a fixed forearm's error would be absorbed by the upper arm (the elbows then sit high), the
        shoulder width follows narrow-shouldered subjects, and the girth keeps stout bodies from coming
        out taller. The thigh trades off against the shank, the trunk against the pelvis and head
        ellipsoids, and the hip width is pushed out by stout thighs, so these stay at the file's values.
    sigma_m : float
        Prediction error (metres, > 0): every frame's EM starts from the previous frame's Σ + σ² I, the
        first from σ² I.
    min_observations : int
        Fewer observations than this: the frame is predicted, not fitted.
    max_outlier_fraction : float
        A fit explaining more than this fraction of the data as outliers is a failure.
    reinit_every : int
        Every this many tracked frames a re-initialisation is tried as well, and the better fit (by
        likelihood) kept: EM can settle in a wrong local optimum (a knee bent the wrong way, legs
        swapped) that passes every check, and a fresh look bounds how long it lasts; 0 never.
    reinit_margin : float
        Such a periodic re-initialisation replaces a fit that passed the checks only when its
        log-likelihood per observation is higher by this much (nats): two fits in nearly the same
        place differ by hundredths, a fit in a different, better optimum by tenths.
    failure_sigma_m : float
        A fit whose Σ has a standard deviation above this (metres) is a failure: the ellipsoids are
        off the body surface by a few centimetres, not by a spread close to the `max_sigma_m` ceiling
        (which it must be below: Σ never grows past that ceiling, so the check would never fail).
    refit_drop, refit_iterations : float, int
        A fit whose log-likelihood per observation is `refit_drop` nats below the running level gets up
        to `refit_iterations` (at least 1) more EM iterations with a strict stopping rule before it is
        judged; inf never refits.
    restart_drop : float
        When such a fit is still `restart_drop` nats below the level, EM also runs from the last pose
        (no velocity) and the better fit is kept (inf never restarts): a motion that stops or turns
        makes the constant-velocity prediction overshoot into another optimum (a chambered kick's knee
        folded sideways).
    velocity_decay : float
        Factor on the velocity for each predicted frame (a gap's motion slows down).
    max_predicted_frames : int
        After this many frames without a fit, the subject is lost and the next data re-initialise.
    scale_frames : int
        Frames over which the height (when unknown: by the initialisations among them) and the length
        factors keep being estimated.
    init_headings, init_refine : int
        Initialisation: headings per library pose, hypotheses refined by EM.
    normal_noise_deg : float
        Angular noise of the observed normals (degrees; silhouette normals are off by ~10°): with the
        "normals" distance each pair's covariance grows by how far that tilt slides the ellipsoid point
        of eq. (4) (`EMParams.normal_noise_rad`); 0 is the paper's model.
    min_outlier_prior : float
        Lower bound on the outlier class's prior π_{P+1} (`EMParams.min_outlier_prior`); 0 is the paper's,
        0.5 the most (the outlier class may not own most of the data).
    max_sigma_m : float
        Upper bound on Σ's standard deviations, metres (`EMParams.max_sigma_m`).
    limb_share_ratio, limb_min_observations : float, int
        After every fit, a limb with a segment explaining fewer data than `limb_share_ratio` times
        what its mirror segment explains, or than its running level over the tracked frames (when
        that reference is at least `limb_min_observations`), is re-initialised locally
        (`init.misplaced_limbs`, `init.deserted_limbs`, `init.reinitialise_limb`); 0 disables it.
    """

    height_m: float | None = None
    distance: str = "normals"
    max_iterations: int = 10
    tolerance: float = 0.01
    displacement_m: float = 0.002
    estimate_lengths: tuple[str, ...] = ("upperarm", "shank", "girth", "forearm", "shoulders")
    sigma_m: float = 0.02
    min_observations: int = 30
    max_outlier_fraction: float = 0.6
    failure_sigma_m: float = 0.05
    reinit_every: int = 0
    reinit_margin: float = 0.05
    refit_drop: float = 0.1
    refit_iterations: int = 20
    restart_drop: float = 0.3
    velocity_decay: float = 0.7
    max_predicted_frames: int = 10
    scale_frames: int = 10
    init_headings: int = 12
    init_refine: int = 24
    normal_noise_deg: float = 10.0
    min_outlier_prior: float = 0.05
    max_sigma_m: float = 0.06
    limb_share_ratio: float = LIMB_SHARE_RATIO
    limb_min_observations: int = LIMB_MIN_OBSERVATIONS

    def __post_init__(self) -> None:
        """Refuse, before any work, a value the tracker would fail on or silently misuse.

        Every field is checked for its type (an integer count, a finite number), its range and its
        relations to the others: a negative iteration count or prediction error ran and exported poses
        up to a metre off, a NaN width or zero headings ended in a traceback, an unknown distance
        stopped the run in its middle.
        """
        if self.height_m is not None:
            check_number("tracking.height_m", self.height_m, *SUBJECT_HEIGHT_RANGE_M, above=True)
        check_choice("tracking.distance", self.distance, tuple(DISTANCES))
        for name, minimum in _INTEGER_MINIMA.items():
            check_int(f"tracking.{name}", getattr(self, name), minimum)
        for name, (minimum, maximum, above) in _NUMBER_RANGES.items():
            check_number(f"tracking.{name}", getattr(self, name), minimum, maximum, above=above,
                         infinite=name in _MAY_BE_INFINITE)
        _check_length_groups(self.estimate_lengths)
        if not self.failure_sigma_m < self.max_sigma_m:
            raise InputError(f"tracking.failure_sigma_m: expected a value below max_sigma_m ({self.max_sigma_m}), "
                             f"since Σ never grows past that ceiling, got {self.failure_sigma_m}")


# Smallest valid value of each integer field of TrackerParams.
_INTEGER_MINIMA = {"max_iterations": 1, "min_observations": 1, "reinit_every": 0, "refit_iterations": 1,
                   "max_predicted_frames": 0, "scale_frames": 0, "init_headings": 1, "init_refine": 1,
                   "limb_min_observations": 0}
# (minimum, maximum, strictly above the minimum) of each float field of TrackerParams. Σ starts from
# sigma_m² I, so a zero sigma_m is a singular covariance; a fraction or a prior are at most 1 (the
# outlier prior at most one half: the outlier class may not own most of the data).
_NUMBER_RANGES = {"tolerance": (0.0, np.inf, False), "displacement_m": (0.0, np.inf, False),
                  "sigma_m": (0.0, np.inf, True), "max_outlier_fraction": (0.0, 1.0, True),
                  "failure_sigma_m": (0.0, np.inf, True), "reinit_margin": (0.0, np.inf, False),
                  "refit_drop": (0.0, np.inf, False), "restart_drop": (0.0, np.inf, False),
                  "velocity_decay": (0.0, 1.0, False), "normal_noise_deg": (0.0, 90.0, False),
                  "min_outlier_prior": (0.0, 0.5, False), "max_sigma_m": (0.0, np.inf, True),
                  "limb_share_ratio": (0.0, 1.0, False)}
# Thresholds that inf turns off (never refit, never restart).
_MAY_BE_INFINITE = ("refit_drop", "restart_drop")


def _check_length_groups(names) -> None:
    """`estimate_lengths`: a tuple of distinct names of the shipped bodies' length groups."""
    known = sorted(shipped_length_groups())
    if not (isinstance(names, tuple) and all(isinstance(name, str) and name in known for name in names)
            and len(set(names)) == len(names)):
        raise InputError(f"tracking.estimate_lengths: expected a list of distinct length groups among "
                         f"{', '.join(known)}, got {list(names) if isinstance(names, tuple) else names!r}")


@dataclass(frozen=True)
class FrameResult:
    """One frame's estimate.

    Attributes
    ----------
    pose : (D,) float
        Pose vector Λ of the body (see `body`).
    joints : (17, 3) float
        Joint centres in `JOINT_NAMES` order, metres, world.
    log_likelihood : float
        ln P(Y | Λ) of the frame's data (eq. 12), nats; 0 when not fitted.
    iterations : int
        EM iterations (of the refinement, for an initialisation).
    outlier_fraction : float
        Mean outlier posterior; 1 when not fitted.
    status : {"tracked", "initialised", "predicted", "lost"}
        "predicted" and "lost" frames are not exported.
    height_m : float
        Body height used for this frame, metres.
    doubtful : bool
        The fit failed the failure checks (`TrackerParams.max_outlier_fraction`, `failure_sigma_m`)
        and so did a re-initialisation: the better of the two is the estimate, exported but flagged.
    observations : int
        Usable observations of the frame (the data the likelihood sums over).
    joint_support : (17,) float or None
        Per joint of `JOINT_NAMES`, the observations explained by the segment that places it relative
        to the joint before it in the skeleton (`joint_support`); None when the frame was not fitted.
        The export's per-joint confidence comes from it: a limb EM keeps where the data say nothing
        is still "tracked", and only this says that its data are missing.
    """

    pose: np.ndarray
    joints: np.ndarray
    log_likelihood: float
    iterations: int
    outlier_fraction: float
    status: str
    height_m: float
    doubtful: bool = False
    observations: int = 0
    joint_support: np.ndarray | None = None

    def to_dict(self) -> dict:
        """JSON-ready dictionary (lists of floats)."""
        support = None if self.joint_support is None else np.asarray(self.joint_support).tolist()
        return {**asdict(self), "pose": self.pose.tolist(), "joints": self.joints.tolist(), "joint_support": support}


@dataclass(frozen=True)
class TrackerState:
    """What the next frame needs from the past; JSON-serialisable so that a run can resume.

    Attributes
    ----------
    pose, velocity : (D,) float
        Last estimated pose and its last frame-to-frame change.
    height_m : float
        Current body height, metres.
    length_factors : (G,) float
        Current segment-length factors of the groups named by `TrackerParams.estimate_lengths`.
    height_weight : int
        Frames that contributed to the height and length estimates (frozen at `scale_frames`).
    Sigma : (k, k) float
        Covariance Σ of the last fit, m² (the next frame's EM starts from it).
    pi : (P + 1,) float
        Mixture priors π of the last fit.
    likelihood_level : float
        Running level of the log-likelihood per observation of good fits (nats).
    frames_without_fit : int
        Consecutive frames predicted instead of fitted.
    lost : bool
        The next frame with data must re-initialise.
    since_initialisation : int
        Frames tracked since a re-initialisation was last tried (`TrackerParams.reinit_every`).
    segment_shares : (S,) float or None
        Running level of each segment's share of the data over the tracked frames (`init.segment_shares`,
        the same exponential average as the likelihood level); None until a tracked frame sets it.
    recheck : bool
        The last frame was an initialisation that failed the checks: the next frame tracks from it but
        also weighs a fresh initialisation against that fit, whether or not the fit passes the checks (a
        pose fitted to clutter can hold the next frame's data in a wrong optimum that passes them).
    """

    pose: np.ndarray
    velocity: np.ndarray
    height_m: float
    length_factors: np.ndarray
    height_weight: int
    Sigma: np.ndarray
    pi: np.ndarray
    likelihood_level: float
    frames_without_fit: int
    lost: bool
    since_initialisation: int = 0
    segment_shares: np.ndarray | None = None
    recheck: bool = False

    def to_dict(self) -> dict:
        """JSON-ready dictionary (strict JSON: an unknown likelihood level is null, not NaN)."""
        level = self.likelihood_level if np.isfinite(self.likelihood_level) else None
        return {**asdict(self), "pose": self.pose.tolist(), "velocity": self.velocity.tolist(),
                "length_factors": self.length_factors.tolist(), "Sigma": self.Sigma.tolist(),
                "pi": self.pi.tolist(), "likelihood_level": level,
                "segment_shares": None if self.segment_shares is None else self.segment_shares.tolist()}

    @staticmethod
    def from_dict(data: dict) -> TrackerState:
        return TrackerState(pose=np.asarray(data["pose"], dtype=float),
                            velocity=np.asarray(data["velocity"], dtype=float),
                            height_m=float(data["height_m"]),
                            length_factors=np.asarray(data["length_factors"], dtype=float),
                            height_weight=int(data["height_weight"]),
                            Sigma=np.asarray(data["Sigma"], dtype=float), pi=np.asarray(data["pi"], dtype=float),
                            likelihood_level=np.nan if data["likelihood_level"] is None
                            else float(data["likelihood_level"]),
                            frames_without_fit=int(data["frames_without_fit"]), lost=bool(data["lost"]),
                            since_initialisation=int(data.get("since_initialisation", 0)),
                            segment_shares=None if data.get("segment_shares") is None
                            else np.asarray(data["segment_shares"], dtype=float),
                            recheck=bool(data.get("recheck", False)))


# Weight of a new frame in the running log-likelihood level (an exponential average over ~10 frames).
_LEVEL_RATE = 0.1
# Stopping rule of the extra EM iterations of a frame worse than usual: close to full convergence
# (1e-3 nats per observation, joints still by half a millimetre), since such frames are few.
_REFIT_TOLERANCE = 1e-3
_REFIT_DISPLACEMENT_M = 5e-4
# Normals shorter than this are not directions; such rows are dropped.
_MIN_NORMAL = 1e-6
# A joint this close to its segment's joint centre (metres) sits on it (`joint_support`).
_AT_JOINT_CENTRE_M = 1e-9


def track_frame(state: TrackerState | None, obs, body: BodyModel, params: TrackerParams,
                volume: np.ndarray) -> tuple[FrameResult, TrackerState]:
    """Estimate one frame's pose from its observations and the tracker's state.

    Parameters
    ----------
    state : TrackerState or None
        None on the first frame.
    obs
        Any object with `points` (N, 3) and `normals` (N, 3) (metres, unit outward normals).
    body : BodyModel
        The body (its height is replaced by `params.height_m` or by the estimate).
    params : TrackerParams
    volume : (2, 3) float
        Working volume [min; max], metres.
    """
    volume = np.asarray(volume, dtype=float)
    volume_size(volume)
    y, n = _usable(obs)
    body = _remembered("free", body, params.estimate_lengths, lambda: body.with_length_groups(params.estimate_lengths))
    if state is None:
        state = _first_state(body, params, volume)
    sized = _remembered("sized", body, (state.height_m, state.length_factors.tobytes()),
                        lambda: body.scaled(state.height_m).with_lengths(state.length_factors))
    if len(y) < params.min_observations:
        return _predict(state, sized, params, len(y))
    em = EMParams(distance=params.distance, max_iterations=params.max_iterations, tolerance=params.tolerance,
                  displacement_m=params.displacement_m, normal_noise_rad=np.radians(params.normal_noise_deg),
                  min_outlier_prior=params.min_outlier_prior, max_sigma_m=params.max_sigma_m)
    if state.lost:
        return _initialise(state, y, n, sized, params, volume, em)
    prediction = sized.clip(state.pose + state.velocity)
    learning = state.height_weight < params.scale_frames
    mixture = Mixture(Sigma=state.Sigma + params.sigma_m**2 * np.eye(len(state.Sigma)), pi=state.pi)
    frame_em = replace(em, estimate_lengths=learning and bool(params.estimate_lengths))
    tracked = fit(y, n, sized, prediction, volume, frame_em, mixture=mixture)
    per_obs = tracked.log_likelihood[-1] / len(y)
    if np.isfinite(state.likelihood_level) and per_obs < state.likelihood_level - params.refit_drop:
        # Worse than usual: fast motion, which the quick stopping rule can leave half-way. EM goes on.
        more = fit(y, n, tracked.body, tracked.pose, volume,
                   replace(frame_em, max_iterations=params.refit_iterations, tolerance=_REFIT_TOLERANCE,
                           displacement_m=_REFIT_DISPLACEMENT_M), mixture=tracked.mixture, prior_pose=prediction,
                   start=tracked.estep)
        tracked = replace(more, iterations=tracked.iterations + more.iterations)
        per_obs = tracked.log_likelihood[-1] / len(y)
        if per_obs < state.likelihood_level - params.restart_drop and np.any(state.velocity):
            # Still far worse: the motion may have stopped or turned, and the constant-velocity prediction
            # overshot into another optimum (a kicking leg folded sideways). EM from the last pose as well.
            still = fit(y, n, sized, sized.clip(state.pose), volume, replace(
                frame_em, max_iterations=params.max_iterations + params.refit_iterations,
                tolerance=_REFIT_TOLERANCE, displacement_m=_REFIT_DISPLACEMENT_M), mixture=mixture)
            if still.log_likelihood[-1] > tracked.log_likelihood[-1]:
                tracked = replace(still, iterations=tracked.iterations + still.iterations)
            per_obs = tracked.log_likelihood[-1] / len(y)
    tracked = _recover_limbs(y, n, tracked, volume, frame_em, params, state.segment_shares)
    per_obs = tracked.log_likelihood[-1] / len(y)
    doubtful = _failed(tracked, params)
    periodic = 0 < params.reinit_every <= state.since_initialisation + 1
    tried = doubtful or periodic or state.recheck
    if tried:
        result, new_state = _initialise(state, y, n, sized, params, volume, em)
        # A fit that passed the checks from an estimate that did too is replaced only on clear evidence
        # (`reinit_margin`).
        margin = 0.0 if doubtful or state.recheck else params.reinit_margin * len(y)
        if result.log_likelihood > tracked.log_likelihood[-1] + margin:
            return result, new_state
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
    moving = state.frames_without_fit == 0 and not doubtful
    velocity = tracked.pose - state.pose if moving else np.zeros_like(state.velocity)
    new_state = TrackerState(pose=tracked.pose, velocity=velocity, height_m=height, length_factors=lengths,
                             height_weight=weight, Sigma=tracked.mixture.Sigma, pi=tracked.mixture.pi,
                             likelihood_level=level, frames_without_fit=0, lost=False,
                             since_initialisation=0 if tried else state.since_initialisation + 1,
                             segment_shares=shares)
    result = FrameResult(pose=tracked.pose, joints=tracked.body.joint_positions(tracked.pose),
                         log_likelihood=tracked.log_likelihood[-1], iterations=tracked.iterations,
                         outlier_fraction=tracked.outlier_fraction, status="tracked", height_m=tracked.height_m,
                         doubtful=doubtful, observations=len(y),
                         joint_support=joint_support(tracked.body, tracked.mixture, len(y)))
    return result, new_state


def joint_support(body: BodyModel, mixture: Mixture, n_observations: int) -> np.ndarray:
    """(17,) observations explained by the segment that places each joint of `JOINT_NAMES`.

    A joint at its segment's joint centre (an elbow at the forearm's) is placed by the parent segment
    (the upper arm: its direction sets where the elbow is); any other joint (a wrist) by the segment
    carrying it. The root's joint (the pelvis) by the root. The data a segment explains are I Σ π_p over
    its ellipsoids (`init.segment_shares`).
    """
    segment = body.joint_segment
    at_centre = np.all(np.abs(body.joint_offset) < _AT_JOINT_CENTRE_M, axis=1) & (body.parent[segment] >= 0)
    placing = np.where(at_centre, body.parent[segment], segment)
    return n_observations * segment_shares(body, mixture)[placing]


def _remembered(slot: str, body: BodyModel, key, make):
    """`make()`, a body derived from `body` and `key`, remembered in `slot` for the last (body, key) asked.

    Every frame derives the same bodies (the free length groups, then the current height and length
    factors, which stop changing after `scale_frames` frames); remembering them saves an eigen-decomposition
    per ellipsoid at every frame.
    """
    last = _REMEMBERED.get(slot)
    if last is None or last[0] is not body or last[1] != key:
        last = _REMEMBERED[slot] = (body, key, make())
    return last[2]


_REMEMBERED: dict[str, tuple] = {}


def _failed(result: FitResult, params: TrackerParams) -> bool:
    """Whether a fit fails the absolute checks: too many outliers, or Σ spread beyond `failure_sigma_m`.

    Absolute rather than relative to a running level, so that a bad start cannot make itself the
    norm. A Σ as wide as the data's spread around the wrong surface is what a torso or a pair of legs
    locked onto the wrong data looks like, while the outlier fraction stays small.
    """
    spread = float(np.sqrt(np.linalg.eigvalsh(result.mixture.Sigma).max()))
    return result.outlier_fraction > params.max_outlier_fraction or spread > params.failure_sigma_m


def _first_state(body: BodyModel, params: TrackerParams, volume: np.ndarray) -> TrackerState:
    """The state before any data: lost, standing at the volume's centre, the body's proportions."""
    height = params.height_m if params.height_m is not None else body.height_m
    pose = body.scaled(height).zero_pose()
    pose[:2] = volume.mean(axis=0)[:2]  # a finite stand-in until data arrive
    mixture = Mixture.initial(body.n_ellipsoids, params.sigma_m, distance_named(params.distance).size)
    return TrackerState(pose=pose, velocity=np.zeros(body.pose_size), height_m=height,
                        length_factors=body.length_factors.copy(), height_weight=0, Sigma=mixture.Sigma,
                        pi=mixture.pi, likelihood_level=np.nan, frames_without_fit=0, lost=True)


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
                             length_factors=state.length_factors, height_weight=state.height_weight,
                             Sigma=state.Sigma, pi=state.pi, likelihood_level=state.likelihood_level,
                             frames_without_fit=gap, lost=lost, segment_shares=state.segment_shares)
    result = FrameResult(pose=pose, joints=body.joint_positions(pose), log_likelihood=0.0, iterations=0,
                         outlier_fraction=1.0, status="lost" if lost else "predicted", height_m=state.height_m,
                         observations=observations)
    return result, new_state


def _recover_limbs(y, n, result, volume, em, params, usual_shares=None) -> FitResult:
    """The fit with each limb that explains far fewer data than its mirror, or than it usually does
    (`usual_shares`, the running level of `init.segment_shares`; None: no history), re-initialised locally.

    A limb EM put on the wrong side of the body or folded away from its data gets almost no
    observations, and the local minimum holds it there for many frames; trying the library's angles
    for that limb alone (`init.reinitialise_limb`) finds it again, and the likelihood decides.
    """
    limbs = misplaced_limbs(result.body, result, len(y), share_ratio=params.limb_share_ratio,
                            min_observations=params.limb_min_observations)
    if usual_shares is not None:
        names = {limb.name for limb in limbs}
        limbs += [limb for limb in deserted_limbs(result.body, result, usual_shares, len(y),
                                                  share_ratio=params.limb_share_ratio,
                                                  min_observations=params.limb_min_observations)
                  if limb.name not in names]
    for limb in limbs:
        result = reinitialise_limb(y, n, result, limb, volume, em, load_pose_library(result.body))
    return result


def _initialise(state, y, n, body, params, volume, em) -> tuple[FrameResult, TrackerState]:
    """Initialise from the data alone (`init.initialise`) and start a fresh track."""
    estimate = params.height_m is None and state.height_weight < params.scale_frames
    init = initialise(y, n, body, volume, load_pose_library(body), estimate_height=estimate, em=em,
                      params=InitParams(headings=params.init_headings, refine=params.init_refine))
    fitted = init.fit
    for _ in range(2):  # a limb moved by the first pass can leave its mirror (or itself) still misplaced
        recovered = _recover_limbs(y, n, fitted, volume, replace(em, estimate_scale=estimate), params)
        if recovered is fitted:
            break
        fitted = recovered
    joints = fitted.body.joint_positions(fitted.pose)
    doubtful = _failed(fitted, params)
    height, weight = state.height_m, state.height_weight
    if estimate:
        weight += 1
        height = init.height_m if weight == 1 else height + (init.height_m - height) / weight
    # A doubtful initialisation is still the best pose the data gave: the next frame tracks from it (at
    # rest) and tries a fresh initialisation against that fit, keeping the likelier (`recheck`). Starting
    # every such frame from scratch threw the track away: on imperfect data the initialisations of
    # consecutive frames landed in different poses, where tracking from the first would have explained the
    # data far better. The likelihood level is left to the tracked frames: an initialisation's fit (a
    # coarse search, sometimes with a limb still wrong) set it so low that the next frames' slips went
    # unnoticed.
    new_state = replace(state, pose=fitted.pose, velocity=np.zeros_like(fitted.pose), height_m=float(height),
                        height_weight=weight, Sigma=fitted.mixture.Sigma, pi=fitted.mixture.pi,
                        likelihood_level=state.likelihood_level if doubtful else np.nan,
                        frames_without_fit=0, lost=False, since_initialisation=0, segment_shares=None,
                        recheck=doubtful)
    result = FrameResult(pose=fitted.pose, joints=joints, log_likelihood=fitted.log_likelihood[-1],
                         iterations=fitted.iterations, outlier_fraction=fitted.outlier_fraction,
                         status="initialised", height_m=init.height_m, doubtful=doubtful, observations=len(y),
                         joint_support=joint_support(fitted.body, fitted.mixture, len(y)))
    return result, new_state
