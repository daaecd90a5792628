"""What the tracker writes for each frame: its estimate (`FrameResult`) and its state after it (`TrackerState`).

Both go to JSON and come back from it (`frame_record`, `read_frame_record`): a run resumes from the
state after the last frame written, and the export reads the estimates.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from stages.joints import JOINT_NAMES

STATUSES = ("tracked", "initialised", "predicted", "lost")


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
    corrected : tuple of str
        The limbs a search put elsewhere on this tracked frame (`Limb.name`, "l_upperarm") and the legs an
        exchange swapped ("l_thigh/r_thigh"): where the track changed its mind about a limb rather than
        following it, which the likelihood decides and can decide wrong on ambiguous data (a rig of few
        cameras, motion blur). An initialisation's own searches are not listed (its status says it).
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
    corrected: tuple[str, ...] = ()

    def to_dict(self) -> dict:
        """JSON-ready dictionary (lists of floats)."""
        support = None if self.joint_support is None else np.asarray(self.joint_support).tolist()
        return {**asdict(self), "pose": self.pose.tolist(), "joints": self.joints.tolist(), "joint_support": support,
                "corrected": list(self.corrected)}

    @staticmethod
    def from_dict(data: dict) -> FrameResult:
        """The estimate `to_dict` wrote (records written before `joint_support` or `corrected` were saved have
        neither)."""
        support = data.get("joint_support")
        return FrameResult(**{**data, "pose": np.asarray(data["pose"], dtype=float),
                              "joints": np.asarray(data["joints"], dtype=float),
                              "joint_support": None if support is None else np.asarray(support, dtype=float),
                              "corrected": tuple(data.get("corrected", ()))})


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
    measured_height_m : float or None
        The data's estimate of the height (the running mean of the initialisations' over those frames), which
        `height_m` is or weighs against a stated height; None until an initialisation measured it.
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
        Running level of each segment's share of the data over the tracked frames (`limbs.segment_shares`,
        the same exponential average as the likelihood level); None until a tracked frame sets it.
    recheck : bool
        The last frame was an initialisation that failed the checks: the next frame tracks from it but
        also weighs a fresh initialisation against that fit, whether or not the fit passes the checks (a
        pose fitted to clutter can hold the next frame's data in a wrong optimum that passes them).
    velocity_covariance, velocity_variance : (D,) float or None
        Running levels (the likelihood level's exponential average) of each DOF's product of consecutive
        frame-to-frame changes v_{t−1} v_t and of its square v_{t−1}² over the tracked frames, from which the
        prediction weighs the velocity (`tracker.velocity_gain`); None until two tracked frames in a row.
    search_misses, search_wait : (L,) int or None
        Per limb of `Tracker.limbs`, its searches in a row that kept the fit and the frames it waits before a
        share test may search it again (`limbs.search_backoff`); None until a tracked frame sets them.
    exchange_misses, exchange_wait : (X,) int or None
        The same for the exchange of each pair of `Tracker.legs` (`limbs.swap_limbs`), tried on a fit worse
        than usual.
    spread_level, spread_variance : float
        Running level (the likelihood level's exponential average) of the largest standard deviation of the
        fitted Σ (metres) over the tracked frames that passed the checks, and its running variance (m²): how
        wide a good fit of this capture's data is (`spread_limit`); NaN until such a frame sets them.
    start_level : float
        Log-likelihood per observation of the fit of the initialisation that started the track (nats); NaN when
        it failed the checks, and after the first tracked frame (`tracker._as_likely_as_usual`).
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
    measured_height_m: float | None = None
    velocity_covariance: np.ndarray | None = None
    velocity_variance: np.ndarray | None = None
    search_misses: np.ndarray | None = None
    search_wait: np.ndarray | None = None
    exchange_misses: np.ndarray | None = None
    exchange_wait: np.ndarray | None = None
    spread_level: float = np.nan
    spread_variance: float = np.nan
    start_level: float = np.nan

    def to_dict(self) -> dict:
        """JSON-ready dictionary (strict JSON: an unknown likelihood level is null, not NaN)."""
        return {**asdict(self), "pose": self.pose.tolist(), "velocity": self.velocity.tolist(),
                "length_factors": self.length_factors.tolist(), "Sigma": self.Sigma.tolist(),
                "pi": self.pi.tolist(), "likelihood_level": _finite(self.likelihood_level),
                "segment_shares": _listed(self.segment_shares),
                "velocity_covariance": _listed(self.velocity_covariance),
                "velocity_variance": _listed(self.velocity_variance),
                "search_misses": _listed(self.search_misses), "search_wait": _listed(self.search_wait),
                "exchange_misses": _listed(self.exchange_misses), "exchange_wait": _listed(self.exchange_wait),
                "spread_level": _finite(self.spread_level), "spread_variance": _finite(self.spread_variance),
                "start_level": _finite(self.start_level)}

    @staticmethod
    def from_dict(data: dict) -> TrackerState:
        return TrackerState(pose=np.asarray(data["pose"], dtype=float),
                            velocity=np.asarray(data["velocity"], dtype=float),
                            height_m=float(data["height_m"]),
                            length_factors=np.asarray(data["length_factors"], dtype=float),
                            height_weight=int(data["height_weight"]),
                            Sigma=np.asarray(data["Sigma"], dtype=float), pi=np.asarray(data["pi"], dtype=float),
                            likelihood_level=_unknown_nan(data["likelihood_level"]),
                            frames_without_fit=int(data["frames_without_fit"]), lost=bool(data["lost"]),
                            since_initialisation=int(data.get("since_initialisation", 0)),
                            segment_shares=_array(data.get("segment_shares")),
                            recheck=bool(data.get("recheck", False)),
                            velocity_covariance=_array(data.get("velocity_covariance")),
                            velocity_variance=_array(data.get("velocity_variance")),
                            search_misses=_array(data.get("search_misses"), int),
                            search_wait=_array(data.get("search_wait"), int),
                            exchange_misses=_array(data.get("exchange_misses"), int),
                            exchange_wait=_array(data.get("exchange_wait"), int),
                            measured_height_m=None if data.get("measured_height_m") is None
                            else float(data["measured_height_m"]),
                            spread_level=_unknown_nan(data.get("spread_level")),
                            spread_variance=_unknown_nan(data.get("spread_variance")),
                            start_level=_unknown_nan(data.get("start_level")))


#: A tracked fit's Σ is as wide as usual within this many standard deviations of the track's usual spread.
SPREAD_DEVIATIONS = 3.0


def sigma_spread(Sigma: np.ndarray) -> float:
    """The largest standard deviation of a covariance Σ (metres; 0 for an empty one)."""
    return float(np.sqrt(max(np.linalg.eigvalsh(Sigma).max(), 0.0))) if Sigma.size else 0.0


def at_sigma_ceiling(spread: float, max_sigma_m: float) -> bool:
    """Whether a Σ spread (metres) is held at the `max_sigma_m` ceiling that bounds Σ's eigenvalues (to rounding):
    the data want a wider Σ than any fit may have, which the failure checks always count as a failure."""
    return spread >= max_sigma_m * (1.0 - 1e-6)


def spread_limit(state: TrackerState, failure_sigma_m: float) -> float:
    """The widest Σ spread (metres) the next tracked fit may have and pass the failure checks: `failure_sigma_m`,
    or on data whose good fits are wider, their running level plus `SPREAD_DEVIATIONS` standard deviations
    (`TrackerState.spread_level`, `spread_variance`).

    Σ measures how far the data lie from the fitted surface, and that is the data's own quality as much as
    the fit's: lossy video, sensor noise or few cameras leave rims centimetres off the body in every frame,
    and a fixed limit then fails fit after fit that is as good as these data allow, each failure costing an
    initialisation. The level comes only from fits that passed, under `failure_sigma_m` at first, so that a
    bad start cannot make itself the norm.
    """
    if not np.isfinite(state.spread_level):
        return failure_sigma_m
    return max(failure_sigma_m, state.spread_level + SPREAD_DEVIATIONS * float(np.sqrt(state.spread_variance)))


def _finite(value: float) -> float | None:
    """A float for strict JSON: None for NaN (unknown)."""
    return float(value) if np.isfinite(value) else None


def _unknown_nan(value: float | None) -> float:
    """A float from strict JSON: NaN (unknown) for None."""
    return np.nan if value is None else float(value)


def _listed(values: np.ndarray | None) -> list | None:
    return None if values is None else values.tolist()


def _array(values: list | None, dtype=float) -> np.ndarray | None:
    return None if values is None else np.asarray(values, dtype=dtype)


@dataclass(frozen=True)
class BodyHeight:
    """The height (metres) the tracker sized the body at, `tracked_m`, and the two it weighed: the `stated_m` one
    (`TrackerParams.height_m`; None: none) and the one the data measured over the first frames, `measured_m`
    (`TrackerState.measured_height_m`; None where it was not measured). The run's log and report say it."""

    tracked_m: float
    stated_m: float | None
    measured_m: float | None

    @property
    def disagreement(self) -> float | None:
        """How far the measured height is from the stated one, as a fraction of it (None without both)."""
        if self.stated_m is None or self.measured_m is None:
            return None
        return self.measured_m / self.stated_m - 1.0

    def sentence(self) -> str:
        """``"Body sized for a subject 1.709 m tall (stated 1.683 m, measured from the data 1.736 m, +3.1 %)."``"""
        if self.stated_m is None:
            source = "as the data measure it"
        elif self.measured_m is None:
            source = "as stated"
        else:
            source = (f"stated {self.stated_m:.3f} m, measured from the data {self.measured_m:.3f} m, "
                      f"{100 * self.disagreement:+.1f} %")
        return f"Body sized for a subject {self.tracked_m:.3f} m tall ({source})."


def frame_record(frame: int, result: FrameResult, state: TrackerState) -> dict:
    """The JSON-ready record of one tracked frame: its number, its estimate and the tracker's state after it."""
    return {"frame": frame, "result": result.to_dict(), "state": state.to_dict()}


def read_frame_record(record: dict, frame: int) -> tuple[FrameResult, TrackerState]:
    """The estimate and state of a `frame_record` of frame `frame`.

    Raises
    ------
    ValueError
        If it is not such a record: fields missing or of the wrong kind, another frame's record, joints
        or joint support of the wrong shape, an unknown status.
    """
    try:
        estimate, state = FrameResult.from_dict(record["result"]), TrackerState.from_dict(record["state"])
    except (KeyError, TypeError, ValueError, AttributeError) as error:
        raise ValueError(f"not a tracking record ({type(error).__name__}: {error})") from None
    support_shape = None if estimate.joint_support is None else estimate.joint_support.shape
    if (record.get("frame") != frame or estimate.joints.shape != (len(JOINT_NAMES), 3)
            or estimate.status not in STATUSES or support_shape not in (None, (len(JOINT_NAMES),))):
        raise ValueError(f"not the tracking record of frame {frame} "
                         "(its frame number, joints, joint support or status differ)")
    return estimate, state
