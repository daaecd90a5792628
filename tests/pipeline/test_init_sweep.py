"""``pipeline.lab.bench.init_sweep``: the tracker initialised from scratch on frames of a run, scored."""

from __future__ import annotations

import numpy as np

from pipeline.lab.bench.init_sweep import FAILED_MM, Initialisation, summary, sweep
from stages.joints import JOINT_NAMES, SCORED_JOINTS
from stages.reconstruction import Observations
from stages.tracking.body import sample_surface
from stages.tracking.body_file import load_body
from stages.tracking.params import TrackerParams
from stages.tracking.tracker import Tracker

VOLUME = np.array([[-2.0, -2.0, 0.0], [2.0, 2.0, 2.3]])


def test_each_frame_is_initialised_afresh_and_scored_against_its_truth():
    body = load_body("default").scaled(1.75)
    rng = np.random.default_rng(3)
    poses = []
    for x in (0.0, 0.6):  # two frames, far apart: the second cannot be tracked from the first
        pose = body.zero_pose()
        pose[0], pose[3] = x, 0.4
        poses.append(pose)
    observations = [Observations(*sample_surface(body, pose, 600, rng)) for pose in poses]
    truth = np.stack([body.joint_positions(pose) for pose in poses])[:, [JOINT_NAMES.index(j) for j in SCORED_JOINTS]]
    tracker = Tracker(TrackerParams(height_m=1.75, init_headings=6, init_refine=2), VOLUME)
    results = sweep(tracker, [10, 20], observations, truth)
    assert [r.frame for r in results] == [10, 20]
    assert all(r.mpjpe_mm < 20 and not r.doubtful for r in results)
    off = truth.copy()
    off[1] += 0.1  # every joint 0.17 m from where the search puts it: that frame failed, unflagged
    assert sweep(tracker, [10, 20], observations, off)[1].mpjpe_mm > FAILED_MM


def test_the_summary_counts_the_failures_and_those_the_checks_flagged():
    results = [Initialisation(0, 20.0, False), Initialisation(4, 150.0, True), Initialisation(8, 90.0, False),
               Initialisation(12, 25.0, True)]
    assert summary(results) == ("4 initialisations: median 57.5 mm; 2 over 80 mm (1 of them flagged doubtful); "
                                "2 doubtful in all")
