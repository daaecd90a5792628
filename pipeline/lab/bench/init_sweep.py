"""The tracker initialised from scratch on every few frames of a run, each result scored against the truth.

    python -m pipeline.lab.bench.init_sweep runs/bench/foreign/taekwondo --step 4

A track starts with an initialisation: on the first frame, when data come back after a gap, when a subject
walks into view mid-motion. On the bench's captures the track initialises once, on a first frame that is
often a calm pose, so the suites say little about how often the search fails elsewhere. This asks it on
every ``step``-th frame of a run's observations (``Tracker.track`` with no state, as on a first frame): each
frame's MPJPE over the 15 scored joints, and whether the failure checks flagged the result (``doubtful``).
A failure the checks flag is one the tracker can act on; one they miss is exported as it is.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib.errors import InputError
from pipeline.evaluate import default_truth
from pipeline.io import frames_io
from pipeline.io.capture import Capture
from pipeline.io.export_io import read_joints_csv
from pipeline.io.run_layout import RunLayout
from stages.export.joints_table import select_joints
from stages.export.metrics import joint_errors
from stages.joints import JOINT_NAMES, SCORED_JOINTS
from stages.reconstruction import Observations
from stages.tracking.params import TrackerParams
from stages.tracking.tracker import Tracker

#: A fresh initialisation further off than this (MPJPE, mm) is counted as failed.
FAILED_MM = 80.0


@dataclass(frozen=True)
class Initialisation:
    """One frame initialised from scratch: its MPJPE (mm) over the scored joints and the failure checks' verdict."""

    frame: int
    mpjpe_mm: float
    doubtful: bool


def sweep(tracker: Tracker, frames: Sequence[int], observations: Sequence[Observations],
          truth: np.ndarray) -> list[Initialisation]:
    """Initialise ``tracker`` from scratch on each of ``observations`` and score it against ``truth`` (F, 15, 3),
    metres, the ``SCORED_JOINTS`` in that order, one row per frame."""
    results = []
    for frame, frame_observations, joints in zip(frames, observations, truth, strict=True):
        result, _ = tracker.track(None, frame_observations)
        estimate = select_joints(JOINT_NAMES, result.joints[None], SCORED_JOINTS, source="the tracker's joints")
        error = joint_errors(estimate[0], joints).mean()
        results.append(Initialisation(frame, float(1000.0 * error), bool(result.doubtful)))
    return results


def summary(results: Sequence[Initialisation]) -> str:
    """One line: how many initialisations, their median error, and the failed ones, flagged and not."""
    errors = np.array([r.mpjpe_mm for r in results])
    failed = [r for r in results if r.mpjpe_mm > FAILED_MM]
    flagged = sum(r.doubtful for r in failed)
    return (f"{len(results)} initialisations: median {np.median(errors):.1f} mm; {len(failed)} over "
            f"{FAILED_MM:.0f} mm ({flagged} of them flagged doubtful); {sum(r.doubtful for r in results)} doubtful "
            "in all")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.lab.bench.init_sweep",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a run's output folder (its observations and capture are used)")
    parser.add_argument("--step", type=int, default=4, help="initialise on every STEP-th frame (default 4)")
    args = parser.parse_args(argv)
    try:
        if args.step < 1:
            raise InputError(f"--step: expected a whole number >= 1, got {args.step}")
        truth_path = default_truth(args.run)
        capture = Capture.open(truth_path.parents[1])
        truth_frames, names, truth = read_joints_csv(truth_path)
        frames = np.intersect1d(capture.frame_numbers[:: args.step], truth_frames).tolist()
        truth = select_joints(names, truth[np.searchsorted(truth_frames, frames)], SCORED_JOINTS,
                              source=str(truth_path))
        observations = [Observations(*frames_io.read_ply(RunLayout(args.run).observations(frame))) for frame in frames]
        tracker = Tracker(TrackerParams(height_m=capture.height_m), capture.volume)
        results = sweep(tracker, frames, observations, truth)
    except InputError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    for r in results:
        print(f"frame {r.frame}: {r.mpjpe_mm:.1f} mm{' (doubtful)' if r.doubtful else ''}")
    print(summary(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
