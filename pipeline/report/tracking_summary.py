"""What the tracker did on each frame, and why, from the tracking stage's per-frame records; and the height it
sized the body at (`read_body_height`), which a wrong stated height would show first.

The run's closing summary and the HTML report both say how many frames were tracked, initialised,
doubtful, predicted or lost. A frame's record holds its status and doubt flag but not the cause; the
cause follows from the record, the tracker's state before the frame (the previous record's) and the
tracker's parameters (the tracking stage's manifest), by the rules of :mod:`stages.tracking.tracker`:

- *initialised*: the first frame; data back after frames without a fit; the check that follows a
  doubtful initialisation (``recheck``); a periodic re-initialisation (``reinit_every``); otherwise the
  fit from the previous frame failed the failure checks and a fresh initialisation explained the data
  better;
- *doubtful* (tracked or initialised, exported but flagged): the kept fit failed the checks, an outlier
  share above ``max_outlier_fraction`` and/or a spread of Σ above the limit the tracker applied
  (``failure_sigma_m``, or for a tracked fit on data whose good fits are wider, the track's usual spread:
  :func:`stages.tracking.results.spread_limit`) or at the ``max_sigma_m`` ceiling;
- *predicted*: fewer than ``min_observations`` usable observations, the pose carried on;
- *lost*: too few observations for longer than ``max_predicted_frames`` frames, or before any fit;
- *tracked* frames on which a limb search put a limb elsewhere or the legs were exchanged (the record's
  ``corrected``): where the track changed its mind about a limb, and where to look first when it went wrong.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.io import frames_io
from pipeline.io.run_layout import read_manifest_file
from pipeline.io.tracking_io import read_tracking
from stages.tracking.params import TrackerParams
from stages.tracking.results import (
    BodyHeight,
    FrameResult,
    TrackerState,
    at_sigma_ceiling,
    sigma_spread,
    spread_limit,
)

#: The categories counted, in the order they are reported; a doubtful frame counts only as doubtful.
CATEGORIES = ("tracked", "initialised", "doubtful", "predicted", "lost")

#: Tracker parameters the causes depend on; the tracker's defaults stand in for a manifest that lacks them.
CAUSE_PARAMS = ("max_outlier_fraction", "failure_sigma_m", "max_sigma_m", "min_observations",
                "max_predicted_frames", "reinit_every")


@dataclass(frozen=True)
class FrameStatus:
    """One frame as the tracker left it.

    Attributes
    ----------
    frame : int
    category : one of :data:`CATEGORIES`
    status : the record's status ("tracked", "initialised", "predicted", "lost")
    log_likelihood : float, nats (0 when not fitted)
    outlier_fraction : float, mean outlier posterior (1 when not fitted)
    sigma_spread_m : float, square root of the largest eigenvalue of the kept fit's Σ, metres
    sigma_limit_m : float, the widest spread the failure check let that fit have, metres (NaN without a fit)
    causes : why the frame is not plainly tracked (empty for a tracked frame that passed the checks)
    """

    frame: int
    category: str
    status: str
    log_likelihood: float
    outlier_fraction: float
    sigma_spread_m: float
    sigma_limit_m: float
    causes: tuple[str, ...]


def _sigma_limit(status: str, previous: tuple[FrameResult, TrackerState] | None, params: Mapping) -> float:
    """The widest Σ spread the tracker let this frame's fit have: a tracked fit's from the state before it
    (`spread_limit`), an initialisation's `failure_sigma_m`."""
    if status == "tracked" and previous is not None:
        return spread_limit(previous[1], params["failure_sigma_m"])
    return params["failure_sigma_m"] if status in ("tracked", "initialised") else np.nan


def _doubt_causes(result: FrameResult, spread: float, limit: float, params: Mapping) -> tuple[str, ...]:
    causes = []
    if result.outlier_fraction > params["max_outlier_fraction"]:
        causes.append(f"outlier share above {100 * params['max_outlier_fraction']:.0f} %")
    if at_sigma_ceiling(spread, params["max_sigma_m"]):
        causes.append(f"Sigma spread at its ceiling of {100 * params['max_sigma_m']:.1f} cm")
    elif spread > limit:
        causes.append(f"Sigma spread above {100 * limit:.1f} cm")
    return tuple(causes) or ("failed the failure checks",)


def _initialisation_cause(previous: tuple[FrameResult, TrackerState] | None, params: Mapping) -> str:
    if previous is None:
        return "first frame"
    before, state = previous
    if before.status in ("predicted", "lost"):
        return "data back after frames without a fit"
    if state.recheck:
        return "re-check of a doubtful initialisation"
    if 0 < params["reinit_every"] <= state.since_initialisation + 1:
        return "periodic re-initialisation"
    return "the fit from the previous frame failed the checks"


def frame_status(frame: int, record: tuple[FrameResult, TrackerState],
                 previous: tuple[FrameResult, TrackerState] | None, params: Mapping, *,
                 fitted_before: bool) -> FrameStatus:
    """The :class:`FrameStatus` of one frame's tracking record (its estimate and the tracker's state after it,
    :func:`~pipeline.io.tracking_io.read_tracking`), given the record of the frame before (None at the first
    frame), the tracker's parameters (:data:`CAUSE_PARAMS` keys) and whether an earlier frame was fitted
    (tracked or initialised)."""
    result, state = record
    status = result.status
    spread = sigma_spread(state.Sigma) if status in ("tracked", "initialised") else 0.0
    limit = _sigma_limit(status, previous, params)
    causes: tuple[str, ...] = ()
    if status == "initialised":
        causes = (_initialisation_cause(previous, params),)
    elif status == "predicted":
        causes = (f"fewer than {params['min_observations']} observations",)
    elif status == "lost":
        causes = (f"fewer than {params['min_observations']} observations for more than "
                  f"{params['max_predicted_frames']} frames" if fitted_before
                  else f"fewer than {params['min_observations']} observations before any fit",)
    doubtful = result.doubtful and status in ("tracked", "initialised")
    if doubtful:
        causes = _doubt_causes(result, spread, limit, params) + tuple(f"initialised: {cause}" for cause in causes)
    causes += tuple(_correction(name) for name in result.corrected)
    return FrameStatus(frame=frame, category="doubtful" if doubtful else status, status=status,
                       log_likelihood=float(result.log_likelihood), outlier_fraction=float(result.outlier_fraction),
                       sigma_spread_m=spread, sigma_limit_m=limit, causes=causes)


def _correction(name: str) -> str:
    """How the report names a limb the tracker put elsewhere on a tracked frame (`FrameResult.corrected`)."""
    return f"legs exchanged ({name})" if "/" in name else f"{name} put elsewhere by a search"


def tracker_params(tracking_dir: Path) -> dict:
    """The :data:`CAUSE_PARAMS` the tracking stage ran with (its manifest), defaults where unreadable."""
    params = {field.name: field.default for field in dataclasses.fields(TrackerParams) if field.name in CAUSE_PARAMS}
    try:
        recorded = (read_manifest_file(tracking_dir) or {}).get("params")
    except (OSError, frames_io.DamagedFileError):
        return params
    recorded = recorded if isinstance(recorded, dict) else {}
    params.update({key: recorded[key] for key in CAUSE_PARAMS if isinstance(recorded.get(key), (int, float))})
    return params


def read_frame_statuses(tracking_dir: str | Path, frames: Sequence[int]) -> list[FrameStatus] | None:
    """The status of each of ``frames`` (the capture's, in order) from the tracking stage's records.

    Returns None when a record is missing or unreadable (the tracking stage has not finished): a count
    over part of the frames would read as the whole story.
    """
    tracking_dir = Path(tracking_dir)
    params = tracker_params(tracking_dir)
    statuses, previous, fitted = [], None, False
    for frame in frames:
        try:
            record = read_tracking(tracking_dir, frame)
        except (OSError, frames_io.DamagedFileError):
            return None
        statuses.append(frame_status(frame, record, previous, params, fitted_before=fitted))
        previous, fitted = record, fitted or statuses[-1].status in ("tracked", "initialised")
    return statuses


def read_body_height(tracking_dir: str | Path, frames: Sequence[int], stated_m: float | None) -> BodyHeight | None:
    """The :class:`BodyHeight` after the last of ``frames`` (the size stops changing after the first frames), from
    its tracking record; ``stated_m`` as the capture states it. A height set by ``--set tracking.height_m`` (the
    tracking stage's manifest) takes its place, as in the tracking stage. None without a readable record."""
    tracking_dir = Path(tracking_dir)
    if not len(frames):
        return None
    try:
        _, state = read_tracking(tracking_dir, frames[-1])
        recorded = (read_manifest_file(tracking_dir) or {}).get("params")
    except (OSError, frames_io.DamagedFileError):
        return None
    override = recorded.get("height_m") if isinstance(recorded, dict) else None
    stated = override if isinstance(override, (int, float)) else stated_m
    return BodyHeight(tracked_m=float(state.height_m), stated_m=None if stated is None else float(stated),
                      measured_m=state.measured_height_m)


def category_counts(statuses: Sequence[FrameStatus]) -> dict[str, Counter]:
    """Per category of :data:`CATEGORIES`, how many frames each cause accounts for (``Counter``; a frame
    with two causes counts under both, so use :func:`category_totals` for frame counts)."""
    counts: dict[str, Counter] = {category: Counter() for category in CATEGORIES}
    for status in statuses:
        counts[status.category].update(status.causes)
    return counts


def category_totals(statuses: Sequence[FrameStatus]) -> dict[str, int]:
    totals = Counter(status.category for status in statuses)
    return {category: totals.get(category, 0) for category in CATEGORIES}


def summary_line(statuses: Sequence[FrameStatus]) -> str:
    """``"tracking, 112 frames: 104 tracked, 2 initialised (first frame; ...), 6 doubtful (...), 0 ..."``."""
    totals, counts = category_totals(statuses), category_counts(statuses)
    parts = []
    for category in CATEGORIES:
        causes = "; ".join(f"{cause} x{n}" if n > 1 else cause for cause, n in counts[category].most_common())
        parts.append(f"{totals[category]} {category}" + (f" ({causes})" if causes else ""))
    return f"tracking, {len(statuses)} frames: " + ", ".join(parts)
