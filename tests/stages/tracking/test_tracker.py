"""Tracking over time on data sampled from the body's own ellipsoids, and degenerate inputs."""

import json
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from tracking_testing import VOLUME, sample_ellipsoids

from stages.joints import JOINT_NAMES
from stages.tracking import tracker
from stages.tracking.body_file import load_body
from stages.tracking.limbs import exchanged
from stages.tracking.params import TrackerParams
from stages.tracking.results import STATUSES, FrameResult, TrackerState, sigma_spread, spread_limit
from stages.tracking.tracker import Tracker, velocity_gain

PARAMS = TrackerParams(height_m=1.75, init_headings=6, init_refine=2)


@pytest.fixture(scope="module")
def body():
    return load_body("default")


def _walk(body, frames):
    """A short motion: stepping forward while turning, knees and elbows bending."""
    poses = []
    for f in range(frames):
        pose = body.zero_pose()
        pose[1] = 0.02 * f
        pose[3] = 0.3 + 0.02 * f
        for name, amplitude in [("l_thigh.flex", 0.4), ("r_thigh.flex", -0.4), ("l_shank.flex", 0.5),
                                ("l_forearm.flex", 0.8), ("r_forearm.flex", 0.4)]:
            pose[body.dof_names.index(name)] = amplitude * np.sin(0.25 * f) + (0.5 if "shank" in name else 0.0)
        poses.append(body.clip(pose))
    return poses


def _obs(body, pose, rng, count=600):
    y, n = sample_ellipsoids(body, pose, count, rng, outlier_fraction=0.2)
    return SimpleNamespace(points=y, normals=n)


def test_tracks_a_sequence_from_an_automatic_start(body):
    rng = np.random.default_rng(20)
    truth = _walk(body.scaled(1.75), 6)
    tracker = Tracker(PARAMS, VOLUME)  # one tracker over the sequence, as the tracking stage runs it
    state, errors, statuses, doubtful = None, [], [], []
    for pose in truth:
        result, state = tracker.track(state, _obs(body, pose, rng))
        errors.append(np.linalg.norm(result.joints - body.joint_positions(pose), axis=1).mean())
        statuses.append(result.status)
        doubtful.append(result.doubtful)
    assert statuses[0] == "initialised" and set(statuses[1:]) == {"tracked"}
    assert not any(doubtful)
    assert max(errors) < 0.02  # metres, every frame


def test_empty_and_degenerate_frames_are_predicted_never_nan(body):
    rng = np.random.default_rng(21)
    pose = _walk(body, 1)[0]
    tracker = Tracker(PARAMS, VOLUME)
    _, state = tracker.track(None, _obs(body, pose, rng))
    empty = SimpleNamespace(points=np.zeros((0, 3)), normals=np.zeros((0, 3)))
    nan_rows = SimpleNamespace(points=np.full((50, 3), np.nan), normals=np.ones((50, 3)))
    for obs in [empty, nan_rows]:
        result, state = tracker.track(state, obs)
        assert result.status == "predicted"
        assert np.all(np.isfinite(result.joints)) and np.all(np.isfinite(result.pose))


def test_first_frame_without_data_is_lost_but_finite(body):
    empty = SimpleNamespace(points=np.zeros((0, 3)), normals=np.zeros((0, 3)))
    result, state = Tracker(PARAMS, VOLUME).track(None, empty)
    assert result.status == "lost" and state.lost
    assert np.all(np.isfinite(result.joints))


def test_all_outlier_frames_are_flagged_not_dropped_and_tracking_recovers(body):
    """A frame that was fitted is estimated (the better of the fit and a re-initialisation), flagged."""
    rng = np.random.default_rng(22)
    poses = _walk(body, 3)
    tracker = Tracker(PARAMS, VOLUME)
    _, state = tracker.track(None, _obs(body, poses[0], rng))
    noise = SimpleNamespace(points=rng.uniform(VOLUME[0], VOLUME[1], (600, 3)),
                            normals=np.tile([0.0, 0.0, 1.0], (600, 1)))
    result, state = tracker.track(state, noise)
    assert result.status in ("tracked", "initialised") and result.doubtful
    assert np.all(np.isfinite(result.joints))
    result, state = tracker.track(state, _obs(body, poses[2], rng))
    assert result.status in ("tracked", "initialised") and not result.doubtful
    assert np.linalg.norm(result.joints - body.joint_positions(poses[2]), axis=1).mean() < 0.02


def test_state_round_trips_through_json(body):
    rng = np.random.default_rng(23)
    result, state = Tracker(PARAMS, VOLUME).track(None, _obs(body, _walk(body, 1)[0], rng))
    again = TrackerState.from_dict(json.loads(json.dumps(state.to_dict())))
    np.testing.assert_array_equal(again.pose, state.pose)
    assert again.to_dict() == state.to_dict()
    assert result.status in STATUSES and json.loads(json.dumps(result.to_dict()))["status"] == result.status


def test_a_tracked_fit_is_judged_against_the_spread_this_tracks_good_fits_have(body):
    """Data 1.6 cm off the surface (σ along the normals) give fits a little wider than a `failure_sigma_m` of 1.2 cm:
    alone, such a fit fails the checks and costs an initialisation; after good fits about as wide (the running
    level and variance in the state), it is tracked as usual, and a frame without data keeps that level. An
    initialisation is still held to the limit."""
    rng = np.random.default_rng(30)
    poses = _walk(body.scaled(1.75), 2)
    tracker = Tracker(replace(PARAMS, failure_sigma_m=0.012), VOLUME)

    def noisy(pose):
        y, n = sample_ellipsoids(body, pose, 600, rng, outlier_fraction=0.1)
        return SimpleNamespace(points=y + rng.normal(0.0, 0.016, (len(y), 1)) * n, normals=n)

    first, state = tracker.track(None, noisy(poses[0]))
    assert first.status == "initialised" and first.doubtful  # wider than 1.2 cm, and no track to judge it by
    data = noisy(poses[1])
    alone, _ = tracker.track(replace(state, recheck=False), data)
    assert alone.doubtful
    usual = replace(state, recheck=False, spread_level=0.0115, spread_variance=0.001**2)
    assert spread_limit(usual, 0.012) == pytest.approx(0.0145)
    tracked, after = tracker.track(usual, data)
    assert tracked.status == "tracked" and not tracked.doubtful
    assert 0.012 < sigma_spread(after.Sigma) < 0.0145 and after.spread_level > usual.spread_level
    empty = SimpleNamespace(points=np.zeros((0, 3)), normals=np.zeros((0, 3)))
    _, gap = tracker.track(after, empty)  # the data's quality outlives frames without data
    assert (gap.spread_level, gap.spread_variance) == (after.spread_level, after.spread_variance)
    assert np.linalg.norm(tracked.joints - body.joint_positions(poses[1]), axis=1).mean() < 0.02


def test_a_fit_wider_than_usual_that_explains_the_data_as_well_as_usual_is_not_a_failure(body):
    """A tracked fit whose Σ is wider than the track's good fits have been, but whose likelihood per observation is
    at the track's level, is what a frame of worse data looks like (a lossy frame, a flicker), not a lost track: it
    passes, and costs no initialisation. The same fit when the track's fits have explained the data clearly better
    (`refit_drop` above it) fails, as it does while the level is unknown."""
    rng = np.random.default_rng(31)
    poses = _walk(body.scaled(1.75), 2)
    the_tracker = Tracker(replace(PARAMS, failure_sigma_m=0.012), VOLUME)
    y, n = sample_ellipsoids(body, poses[1], 600, rng, outlier_fraction=0.1)
    data = SimpleNamespace(points=y + rng.normal(0.0, 0.015, (len(y), 1)) * n, normals=n)
    _, state = the_tracker.track(None, SimpleNamespace(points=y, normals=n))
    narrow = replace(state, recheck=False, spread_level=0.005, spread_variance=0.0)  # good fits 5 mm wide
    unknown, _ = the_tracker.track(narrow, data)
    assert unknown.doubtful  # wider than 1.2 cm, and no likelihood level to weigh it by
    level = unknown.log_likelihood / unknown.observations
    usual, after = the_tracker.track(replace(narrow, likelihood_level=level), data)
    assert usual.status == "tracked" and not usual.doubtful and sigma_spread(after.Sigma) > 0.012
    worse, _ = the_tracker.track(replace(narrow, likelihood_level=level + 2 * PARAMS.refit_drop), data)
    assert worse.doubtful


def test_the_usual_spread_is_a_running_mean_and_variance_of_the_fits_that_passed():
    start = SimpleNamespace(spread_level=np.nan, spread_variance=np.nan)
    assert tracker.running_spread(start, 0.04) == (0.04, 0.0)
    level, variance = tracker.running_spread(SimpleNamespace(spread_level=0.04, spread_variance=0.0), 0.05)
    assert level == pytest.approx(0.041) and variance == pytest.approx(0.9 * 0.1 * 0.01**2)
    assert spread_limit(SimpleNamespace(spread_level=np.nan, spread_variance=np.nan), 0.05) == 0.05
    assert spread_limit(SimpleNamespace(spread_level=0.03, spread_variance=0.002**2), 0.05) == 0.05  # narrow data


def test_segment_shares_are_learnt_over_tracked_frames_and_round_trip(body):
    """An initialisation leaves no usual shares (its fit may hold a limb still wrong); tracked frames set
    and average them, and they survive the JSON state of a resumed run."""
    rng = np.random.default_rng(24)
    poses = _walk(body, 3)
    tracker = Tracker(PARAMS, VOLUME)
    result, state = tracker.track(None, _obs(body, poses[0], rng))
    assert result.status == "initialised" and state.segment_shares is None
    for pose in poses[1:]:
        result, state = tracker.track(state, _obs(body, pose, rng))
        assert result.status == "tracked"
    shares = state.segment_shares
    assert shares.shape == (len(body.segment_names),) and np.all(shares > 0) and shares.sum() < 1.0
    again = TrackerState.from_dict(json.loads(json.dumps(state.to_dict(), allow_nan=False)))
    np.testing.assert_array_equal(again.segment_shares, shares)


def test_mismatched_points_and_normals_are_rejected(body):
    obs = SimpleNamespace(points=np.zeros((5, 3)), normals=np.zeros((4, 3)))
    with pytest.raises(ValueError, match="normals"):
        Tracker(PARAMS, VOLUME).track(None, obs)


def test_state_before_any_fit_is_strict_json(body):
    empty = SimpleNamespace(points=np.zeros((0, 3)), normals=np.zeros((0, 3)))
    _, state = Tracker(PARAMS, VOLUME).track(None, empty)
    text = json.dumps(state.to_dict(), allow_nan=False)
    assert np.isnan(TrackerState.from_dict(json.loads(text)).likelihood_level)


@pytest.mark.parametrize("distance", ["points", "algebraic"])
def test_variant_distances_run_end_to_end(body, distance):
    rng = np.random.default_rng(24)
    params = TrackerParams(height_m=1.75, init_headings=4, init_refine=1, distance=distance)
    result, _ = Tracker(params, VOLUME).track(None, _obs(body, _walk(body, 1)[0], rng))
    assert result.status in STATUSES and np.all(np.isfinite(result.joints))


def test_only_the_named_length_groups_are_estimated(body):
    rng = np.random.default_rng(23)
    truth = _walk(body.scaled(1.75), 3)
    params = TrackerParams(height_m=1.75, init_headings=6, init_refine=2, estimate_lengths=("shank",))
    tracker = Tracker(params, VOLUME)  # its sized body must follow the length factors as they are learnt
    state = None
    for pose in truth:
        result, state = tracker.track(state, _obs(body, pose, rng))
    assert state.length_factors.shape == (1,)
    assert abs(np.log(state.length_factors[0])) < 0.05  # the data are the file's proportions
    fixed = TrackerParams(height_m=1.75, init_headings=6, init_refine=2, estimate_lengths=())
    _, none = Tracker(fixed, VOLUME).track(None, _obs(body, truth[0], rng))
    assert none.length_factors.shape == (0,)


def test_a_learning_frame_fits_from_the_mean_so_far_and_from_the_files_proportions(body, monkeypatch):
    # Shanks 12 % longer than the file's. Each learning frame's EM runs from the mean of the frames before and
    # afresh from the file's proportions (the likelier kept); the frames after it track with the learnt mean.
    rng = np.random.default_rng(25)
    long_shanks = body.with_length_groups(("shank",)).with_lengths(np.array([1.12]))
    truth = _walk(long_shanks.scaled(1.75), 5)
    params = TrackerParams(height_m=1.75, init_headings=6, init_refine=2, estimate_lengths=("shank",), scale_frames=4)
    started = []
    fit_from = Tracker._fit_from

    def spy(self, prediction, state, y, n, sized, mixture, em):
        started.append((len(frames), sized.length_factors[0], state.length_factors[0]))
        return fit_from(self, prediction, state, y, n, sized, mixture, em)

    monkeypatch.setattr(Tracker, "_fit_from", spy)
    tracker, state, frames = Tracker(params, VOLUME), None, []
    for pose in truth:
        result, state = tracker.track(state, _obs(long_shanks, pose, rng))
        frames.append(result)
    for frame in (2, 3):  # learning, the mean so far moved off the file's proportions by frame 1's estimate
        starts = sorted(start for index, start, _ in started if index == frame)
        mean = next(mean for index, _, mean in started if index == frame)
        assert abs(mean - 1.0) > 0.03
        np.testing.assert_allclose(starts, sorted([1.0, mean]))
    assert [start for index, start, _ in started if index == 4] == [state.length_factors[0]]  # learnt: one fit
    assert abs(np.log(state.length_factors[0] / 1.12)) < 0.05


def test_unknown_height_comes_from_the_initialisation_and_tracked_frames_keep_it(body):
    rng = np.random.default_rng(24)
    truth = _walk(body.scaled(1.62), 4)
    params = TrackerParams(height_m=None, init_headings=6, init_refine=2)
    heights, statuses = [], []
    tracker = Tracker(params, VOLUME)  # its sized body must follow the height once it is estimated
    state = None
    for pose in truth:
        result, state = tracker.track(state, _obs(body.scaled(1.62), pose, rng))
        heights.append(state.height_m)
        statuses.append(result.status)
    assert statuses[0] == "initialised" and set(statuses[1:]) == {"tracked"}
    assert abs(heights[0] - 1.62) < 0.05
    assert heights[1:] == [heights[0]] * 3


@pytest.mark.parametrize("weight", [0.5, 1.0])
def test_a_stated_height_is_weighed_against_the_measured_one(body, weight, monkeypatch):
    """The capture states 1.65 m for a body of 1.75 m: by default the body is sized half-way (in log) between
    the stated and the measured height; with the stated height's weight at 1 it is the stated one, unmeasured.
    Either way the initialisation searches at the stated size, not for a size."""
    rng = np.random.default_rng(25)
    truth = _walk(body.scaled(1.75), 3)
    searched = []
    original = tracker.initialise
    monkeypatch.setattr(tracker, "initialise",
                        lambda *a, **k: searched.append(k["estimate_height"]) or original(*a, **k))
    params = TrackerParams(height_m=1.65, stated_height_weight=weight, init_headings=6, init_refine=2)
    the_tracker, state, heights = Tracker(params, VOLUME), None, []
    for pose in truth:
        _, state = the_tracker.track(state, _obs(body.scaled(1.75), pose, rng))
        heights.append(state.height_m)
    assert searched == [False]
    if weight == 1.0:
        assert state.measured_height_m is None and heights == [1.65] * 3
    else:
        assert abs(state.measured_height_m - 1.75) < 0.04
        assert heights == [pytest.approx(np.sqrt(1.65 * state.measured_height_m))] * 3
    again = TrackerState.from_dict(json.loads(json.dumps(state.to_dict())))
    assert again.measured_height_m == state.measured_height_m


def test_subject_height_weighs_in_log():
    assert tracker.subject_height(None, 1.7, 0.5) == 1.7
    assert tracker.subject_height(1.6, 1.8, 1.0) == pytest.approx(1.6)
    assert tracker.subject_height(1.6, 1.8, 0.0) == pytest.approx(1.8)
    assert tracker.subject_height(1.6, 1.8, 0.5) == pytest.approx(np.sqrt(1.6 * 1.8))


@pytest.mark.parametrize("restart_drop", [0.3, np.inf])
def test_a_stop_after_fast_motion_is_tracked_from_the_last_pose(body, restart_drop):
    """The subject stops dead: the constant-velocity prediction lands far off (here 0.8 m away, turned by
    86°, the knee folded back), EM from it settles elsewhere, and EM from the last pose finds the subject."""
    rng = np.random.default_rng(24)
    params = TrackerParams(height_m=1.75, init_headings=6, init_refine=2, restart_drop=restart_drop)
    pose = _walk(body.scaled(1.75), 1)[0]
    tracker = Tracker(params, VOLUME)
    _, state = tracker.track(None, _obs(body, pose, rng))
    _, state = tracker.track(state, _obs(body, pose, rng))  # a tracked frame sets the level
    jump = np.zeros(body.pose_size)
    jump[0], jump[3], jump[body.dof_names.index("r_shank.flex")] = 0.8, 1.5, 1.5
    state = TrackerState(**{**vars(state), "velocity": jump})
    result, _ = tracker.track(state, _obs(body, pose, rng))
    error = np.linalg.norm(result.joints - body.joint_positions(pose), axis=1).mean()
    if np.isfinite(restart_drop):
        assert result.status == "tracked" and error < 0.02
    else:  # without the restart, only a full re-initialisation (or nothing) rescues such a frame
        assert result.status == "initialised" or error > 0.02


def test_a_doubtful_initialisation_is_tracked_from_and_weighed_against_a_fresh_one(body, monkeypatch):
    """After an initialisation that failed the checks, the next frame fits from it and also tries a fresh
    initialisation, keeping the likelier, even when its own fit passes the checks (where a track in good
    standing would keep its fit without looking further)."""
    rng = np.random.default_rng(25)
    poses = _walk(body.scaled(1.75), 2)
    failing = [True]  # the checks fail on the first frame only
    monkeypatch.setattr(tracker, "_failed", lambda result, params, spread_limit_m=None, usual=False: failing[0])
    the_tracker = Tracker(PARAMS, VOLUME)
    first, state = the_tracker.track(None, _obs(body, poses[0], rng))
    assert first.status == "initialised" and first.doubtful and state.recheck and not state.lost
    failing[0] = False
    fits, initialisations, fits_before = [], [], []
    for owner, name, calls in ((tracker, "fit", fits), (the_tracker, "_initialise", initialisations)):
        original = getattr(owner, name)
        monkeypatch.setattr(owner, name, lambda *a, original=original, calls=calls, **k: (
            fits_before.append(len(fits)) if calls is initialisations else None) or calls.append(
            original(*a, **k)) or calls[-1])
    result, after = the_tracker.track(state, _obs(body, poses[1], rng))
    assert fits_before[0] and len(initialisations) == 1  # tracked from the estimate, and a fresh look as well
    # the tracked fit is the last before the initialisation (which fits again to measure the height)
    tracked_ll, fresh_ll = fits[fits_before[0] - 1].log_likelihood[-1], initialisations[0][0].log_likelihood
    assert result.log_likelihood == max(tracked_ll, fresh_ll) and not after.recheck
    assert np.linalg.norm(result.joints - body.joint_positions(poses[1]), axis=1).mean() < 0.02


def test_frames_record_the_data_supporting_each_joint_and_a_hidden_forearm_has_little(body):
    """`joint_support`: the elbow is placed by the upper arm, the wrist by the forearm; a forearm whose data
    are gone (hidden) explains almost nothing though the frame is still tracked."""
    rng = np.random.default_rng(25)
    poses = _walk(body, 3)
    tracker = Tracker(PARAMS, VOLUME)
    result, state = tracker.track(None, _obs(body, poses[0], rng))
    assert result.observations > 0 and result.joint_support.shape == (17,)
    result, state = tracker.track(state, _obs(body, poses[1], rng))
    seen = dict(zip(JOINT_NAMES, result.joint_support, strict=True))
    explained = result.observations * np.bincount(body.ellipsoid_segment, weights=state.pi[:-1])  # per segment
    for joint, segment in [("l_elbow", "l_upperarm"), ("l_wrist", "l_forearm"), ("pelvis", "pelvis"),
                           ("l_hip", "pelvis"), ("l_knee", "l_thigh"), ("l_toe", "l_foot")]:
        assert seen[joint] == pytest.approx(explained[body.segment_names.index(segment)]), joint
    obs = _obs(body, poses[2], rng)
    ellipsoids = body.ellipsoids(poses[2])
    forearm = np.flatnonzero(body.ellipsoid_segment == body.segment_names.index("l_forearm"))
    inside = np.zeros(len(obs.points), bool)
    for e in forearm:  # drop every datum within 1.5 semi-axes of the left forearm's ellipsoids
        local = (obs.points - ellipsoids.t[e]) @ ellipsoids.R[e] / ellipsoids.semi_axes[e]
        inside |= np.linalg.norm(local, axis=1) < 1.5
    hidden = SimpleNamespace(points=obs.points[~inside], normals=obs.normals[~inside])
    result, state = tracker.track(state, hidden)
    assert result.status == "tracked" and result.observations == len(hidden.points)
    support = dict(zip(JOINT_NAMES, result.joint_support, strict=True))
    assert support["l_wrist"] < 0.3 * seen["l_wrist"] and support["r_wrist"] > 0.5 * seen["r_wrist"]
    assert json.loads(json.dumps(result.to_dict()))["joint_support"] == result.joint_support.tolist()


def test_an_initialisation_searches_every_limb_and_keeps_what_gains_nothing(body, monkeypatch):
    """After the whole-body search each limb gets a search of its own, whether or not a share test finds it;
    on data where the search's limbs are right, none of them moves."""
    rng = np.random.default_rng(27)
    pose = _walk(body.scaled(1.75), 1)[0]
    tried = []
    recover = tracker.reinitialise_limb
    monkeypatch.setattr(tracker, "reinitialise_limb",
                        lambda y, n, result, limb, *args, **kwargs: tried.append(limb.name)
                        or recover(y, n, result, limb, *args, **kwargs))
    the_tracker = Tracker(PARAMS, VOLUME)
    result, _ = the_tracker.track(None, _obs(body, pose, rng))
    assert result.status == "initialised"
    assert sorted(tried) == sorted(limb.name for limb in the_tracker.limbs)
    assert np.linalg.norm(result.joints - body.joint_positions(pose), axis=1).max() < 0.02  # metres


def test_a_folded_limb_is_tried_again_and_kept_where_the_data_fold_it(body, monkeypatch):
    """A forearm folded onto its upper arm explains a fair share of the data (the upper arm's, a second time),
    so the fold alone makes the limb recovery try it again when it appears; here the arm really bends that
    far, tracking follows it there, and the fit stays where the data are."""
    rng = np.random.default_rng(26)
    tried = []
    recover = tracker.reinitialise_limb
    monkeypatch.setattr(tracker, "reinitialise_limb",
                        lambda y, n, result, limb, *args, **kwargs: tried.append(limb.name)
                        or recover(y, n, result, limb, *args, **kwargs))
    # Without the periodic checks of every limb (`limb_check_every`): only the searches the tests ask for count.
    bending, state, tried_by_frame = Tracker(replace(PARAMS, limb_check_every=0), VOLUME), None, []
    for elbow in (60, 80, 100, 120, 135, 150, 150):
        pose = body.zero_pose()
        pose[3] = 0.3
        for name, degrees in [("l_upperarm.flex", 40), ("l_forearm.flex", elbow), ("r_upperarm.flex", 40)]:
            pose[body.dof_names.index(name)] = np.radians(degrees)
        tried.clear()
        result, state = bending.track(state, _obs(body, body.clip(pose), rng))
        tried_by_frame.append(list(tried))
    assert tried_by_frame[1:] == [[], [], [], ["l_upperarm"], [], []]  # once, when the fold appears
    assert np.linalg.norm(result.joints - body.joint_positions(body.clip(pose)), axis=1).max() < 0.01  # metres


def test_a_frame_worse_than_usual_tries_the_legs_exchanged(body, monkeypatch):
    """Exchanging the legs costs an EM fit, so it is tried only where legs that took each other's data would
    show: a fit `refit_drop` below the track's usual likelihood."""
    rng = np.random.default_rng(31)
    tried = []
    exchange = tracker.swap_limbs
    monkeypatch.setattr(tracker, "swap_limbs", lambda y, n, result, limb, *args: tried.append(limb.name)
                        or exchange(y, n, result, limb, *args))
    the_tracker, state = Tracker(PARAMS, VOLUME), None
    poses = _walk(body.scaled(1.75), 4)
    for pose in poses[:3]:
        _, state = the_tracker.track(state, _obs(body, pose, rng))
    assert tried == []
    usual = replace(state, likelihood_level=state.likelihood_level + 2 * PARAMS.refit_drop + 1.0)
    result, _ = the_tracker.track(usual, _obs(body, poses[3], rng))
    assert tried == ["l_thigh"]
    assert np.linalg.norm(result.joints - body.joint_positions(poses[3]), axis=1).max() < 0.02  # metres


def test_a_limb_a_search_moved_carries_no_velocity_into_the_next_frame(body, monkeypatch):
    """A limb search's jump is a correction, not motion: carried on as velocity, the next frame's prediction would
    throw the limb as far again. The other DOFs keep their motion."""
    rng = np.random.default_rng(32)
    the_tracker, state = Tracker(PARAMS, VOLUME), None
    poses = _walk(body.scaled(1.75), 4)
    for pose in poses[:3]:
        _, state = the_tracker.track(state, _obs(body, pose, rng))
    arm = next(limb for limb in the_tracker.limbs if limb.name == "l_upperarm")

    def search(y, n, result, limb, *args, **kwargs):
        if limb is not arm:
            return result
        moved = result.pose.copy()
        moved[arm.dofs] += 0.5
        return _moved_fit(result, result.body.clip(moved))

    monkeypatch.setattr(tracker, "misplaced_limbs", lambda limbs, *args: [arm])
    monkeypatch.setattr(tracker, "reinitialise_limb", search)
    result, after = the_tracker.track(state, _obs(body, poses[3], rng))
    assert result.status == "tracked"
    assert result.corrected == ("l_upperarm",)  # quality.csv names the frame where the track changed its mind
    assert FrameResult.from_dict(json.loads(json.dumps(result.to_dict()))).corrected == ("l_upperarm",)
    assert not after.velocity[arm.dofs].any()
    others = np.setdiff1d(np.arange(body.pose_size), arm.dofs)
    assert np.abs(after.velocity[others]).max() > 0.01  # the walk goes on


def test_legs_an_exchange_swapped_are_named_with_the_frame(body, monkeypatch):
    """The legs' exchange is a correction like a limb search's: its frame lists both legs, and an exchange that
    gained nothing lists none."""
    rng = np.random.default_rng(33)
    the_tracker, state = Tracker(PARAMS, VOLUME), None
    poses = _walk(body.scaled(1.75), 4)
    for pose in poses[:3]:
        _, state = the_tracker.track(state, _obs(body, pose, rng))
    worse = replace(state, likelihood_level=state.likelihood_level + 2 * PARAMS.refit_drop + 1.0)
    corrected = {}
    for kept in (True, False):
        monkeypatch.setattr(tracker, "swap_limbs", lambda y, n, result, limb, *args, kept=kept: result if kept
                            else _moved_fit(result, result.body.clip(exchanged(result.pose, limb))))
        corrected[kept] = the_tracker.track(worse, _obs(body, poses[3], rng))[0].corrected
    assert corrected == {True: (), False: ("l_thigh/r_thigh",)}


def test_the_prediction_carries_on_the_changes_the_track_found_smooth(body):
    """Each DOF's last change is carried into the next frame's start as far as such changes predicted the next
    one on this track: a walk's driven DOFs (smooth from frame to frame) keep it whole, a subject standing
    still, whose changes are the fits' jitter, keeps none of it."""
    rng = np.random.default_rng(5)
    walking = _walk(body.scaled(1.75), 12)
    driven = [body.dof_names.index(name) for name in ("l_thigh.flex", "r_thigh.flex", "l_forearm.flex")] + [1]
    gains, moved = {}, {}
    for name, poses in (("walk", walking), ("still", [walking[0]] * 20)):
        the_tracker, state = Tracker(PARAMS, VOLUME), None
        for pose in poses:
            _, state = the_tracker.track(state, _obs(body, pose, rng))
        gains[name] = np.broadcast_to(velocity_gain(state), state.pose.shape)
        moved[name] = state.velocity_variance > 0  # a DOF held at a limit never changes: nothing to carry on
        assert TrackerState.from_dict(json.loads(json.dumps(state.to_dict()))).velocity_variance.tolist() == \
            state.velocity_variance.tolist()
    assert gains["walk"][driven].min() > 0.9
    assert moved["still"].sum() > len(moved["still"]) // 2 and gains["still"][moved["still"]].max() < 0.3
    first_frame = the_tracker.track(None, _obs(body, walking[0], rng))[1]
    assert velocity_gain(first_frame) == 1.0  # nothing measured yet: the whole change, as the paper's prediction


def test_a_limb_the_search_keeps_in_place_is_searched_at_doubling_intervals(body, monkeypatch):
    """A limb a share test suspects at every frame while its search keeps finding nothing better (an arm held
    against a ducking body, whose data are few) is searched twice, then after skipping 1, 3, 7... frames; a
    search that moves it starts the count again, and the count is part of the state a run resumes from."""
    rng = np.random.default_rng(33)
    the_tracker, state = Tracker(PARAMS, VOLUME), None
    arm = next(limb for limb in the_tracker.limbs if limb.name == "l_upperarm")
    now, searched, moving = [0], [], set()  # now[0]: the frame being tracked

    def search(y, n, result, limb, *args, **kwargs):
        if limb is not arm or now[0] == 0:
            return result
        searched.append(now[0])
        return _moved_fit(result, result.pose + 1e-3) if now[0] in moving else result

    monkeypatch.setattr(tracker, "misplaced_limbs", lambda limbs, *args: [limb for limb in limbs if limb is arm])
    monkeypatch.setattr(tracker, "reinitialise_limb", search)
    poses = _walk(body.scaled(1.75), 18)
    for now[0], pose in enumerate(poses[:12]):
        _, state = the_tracker.track(state, _obs(body, pose, rng))
    assert searched == [1, 2, 4, 8]
    state = TrackerState.from_dict(json.loads(json.dumps(state.to_dict())))
    moving.add(16)
    for now[0], pose in enumerate(poses[12:], start=12):
        _, state = the_tracker.track(state, _obs(body, pose, rng))
    assert searched == [1, 2, 4, 8, 16, 17]  # 17: after the move at 16, as at 1 (else not before 32)


def test_every_limb_is_searched_in_turn_even_when_no_test_suspects_it(body, monkeypatch):
    """A limb settled a few centimetres off where it explains about its usual share of the data passes every
    test; each limb is searched every `limb_check_every` tracked frames anyway, the limbs in turn, so that a
    frame pays for one search at most and a limb stuck so is found within that many frames."""
    rng = np.random.default_rng(35)
    the_tracker, state = Tracker(replace(PARAMS, limb_check_every=8), VOLUME), None
    names = [limb.name for limb in the_tracker.limbs]
    now, searched = [0], []

    def search(y, n, result, limb, *args, **kwargs):
        if now[0] > 0:
            searched.append((now[0], names.index(limb.name)))
        return result

    for suspicion in ("misplaced_limbs", "deserted_limbs", "folded_limbs"):
        monkeypatch.setattr(tracker, suspicion, lambda *args: [])
    monkeypatch.setattr(tracker, "reinitialise_limb", search)
    for now[0], pose in enumerate(_walk(body.scaled(1.75), 18)):
        _, state = the_tracker.track(state, _obs(body, pose, rng))
    assert searched == [(2, 1), (4, 2), (6, 3), (8, 0), (10, 1), (12, 2), (14, 3), (16, 0)]
    assert not tracker.checks_due(8, 4, 0).any()


def test_a_learning_frame_searches_its_limbs_at_the_lengths_its_own_fit_learnt(body, monkeypatch):
    """While the lengths are learnt (`scale_frames`), a frame's own fit has them free, and its limb searches keep
    them: a search looks for a pose, and with the lengths free each of its EM iterations costs several."""
    rng = np.random.default_rng(36)
    the_tracker, state = Tracker(replace(PARAMS, scale_frames=6, limb_check_every=2), VOLUME), None
    fits, searches, tracking = [], [], [False]
    original_fit, original_search = tracker.fit, tracker.reinitialise_limb

    def fit(y, n, body_, pose, volume, em, **kwargs):
        if tracking[0]:
            fits.append(em.estimate_lengths)
        return original_fit(y, n, body_, pose, volume, em, **kwargs)

    def search(y, n, result, limb, volume, em, *args, **kwargs):
        if tracking[0]:
            searches.append(em.estimate_lengths)
        return original_search(y, n, result, limb, volume, em, *args, **kwargs)

    monkeypatch.setattr(tracker, "fit", fit)
    monkeypatch.setattr(tracker, "reinitialise_limb", search)
    for frame, pose in enumerate(_walk(body.scaled(1.75), 5)):
        tracking[0] = frame > 0  # the first frame is an initialisation
        _, state = the_tracker.track(state, _obs(body, pose, rng))
    assert 0 < state.height_weight < 6  # every frame so far a learning frame
    assert fits and all(fits)  # the frames' own fits learn the lengths
    assert searches and not any(searches)  # their searches keep them


def test_an_exchange_of_the_legs_that_gains_nothing_is_tried_at_doubling_intervals(body, monkeypatch):
    """Fits worse than usual frame after frame (data noisier than the track's start) try the legs exchanged
    twice, then after skipping 1, 3, 7... frames rather than at every frame, each try costing an EM fit."""
    rng = np.random.default_rng(34)
    now, tried = [0], []
    monkeypatch.setattr(tracker, "swap_limbs", lambda y, n, result, *args: tried.append(now[0]) or result)
    the_tracker, state = Tracker(PARAMS, VOLUME), None
    for now[0], pose in enumerate(_walk(body.scaled(1.75), 10)):
        if state is not None and np.isfinite(state.likelihood_level):  # every fit worse than the level
            state = replace(state, likelihood_level=state.likelihood_level + 1.0)
        _, state = the_tracker.track(state, _obs(body, pose, rng))
    assert tried == [2, 3, 5, 9]


def _moved_fit(result, pose):
    """A fit `result` moved to `pose`, as a limb search that found it would return it."""
    return replace(result, pose=pose, kin=result.body.fk(pose), joints=result.body.joint_positions(pose))


def test_a_failed_initialisation_searches_again_refining_more_library_poses(body, monkeypatch):
    """The coarse ranking can leave the library pose that fits out of the few refined: a search whose fit fails
    the checks is made again, wider, and the likelier of the two kept; a search that passes is not repeated."""
    refined = []
    original = tracker.initialise

    def recorded(*args, **kwargs):
        refined.append(kwargs["params"].refine)
        return original(*args, **kwargs)

    monkeypatch.setattr(tracker, "initialise", recorded)
    rng = np.random.default_rng(26)
    the_tracker = Tracker(PARAMS, VOLUME)
    result, state = the_tracker.track(None, _obs(body, _walk(body.scaled(1.75), 1)[0], rng))
    assert refined == [PARAMS.init_refine] and not result.doubtful
    clutter = SimpleNamespace(points=rng.uniform(VOLUME[0], VOLUME[1], (600, 3)),
                              normals=rng.normal(size=(600, 3)))  # no body in it: every fit fails the checks
    refined.clear()
    result, _ = the_tracker.track(state, clutter)  # a re-check of a failing tracked fit: not widened
    assert set(refined) == {PARAMS.init_refine} and result.doubtful  # (searched again facing the track if turned)
    refined.clear()
    result, _ = Tracker(PARAMS, VOLUME).track(None, clutter)  # alone: widened
    assert refined == [PARAMS.init_refine, PARAMS.init_refine * tracker._WIDER_SEARCH] and result.doubtful


def test_a_re_check_that_turns_the_subject_around_is_weighed_against_a_search_facing_the_track(body, monkeypatch):
    """A re-check's initialisation that faces more than a quarter-turn away from the track (a body turned around
    with left and right exchanged, which covers the same space in a pose symmetric front to back) is weighed
    against a search over the track's half-turn, and loses unless it is clearly likelier."""
    rng = np.random.default_rng(27)
    poses = _walk(body.scaled(1.75), 2)
    the_tracker = Tracker(PARAMS, VOLUME)
    _, state = the_tracker.track(None, _obs(body, poses[0], rng))
    facings = []
    original = tracker.initialise

    def turned_unless_told(*args, facing=None, **kwargs):  # the whole turn's search comes back turned around
        facings.append(facing)
        return original(*args, facing=poses[1][3] + np.pi if facing is None else facing, **kwargs)

    monkeypatch.setattr(tracker, "initialise", turned_unless_told)
    # the tracked fit fails: a re-check
    monkeypatch.setattr(tracker, "_failed", lambda result, params, spread_limit_m=None, usual=False: True)
    result, _ = the_tracker.track(state, _obs(body, poses[1], rng))
    assert facings[0] is None and facings[1] == pytest.approx(state.pose[3])
    assert not tracker.turned_around(result.pose, poses[1])
    assert np.linalg.norm(result.joints - body.joint_positions(poses[1]), axis=1).mean() < 0.02


@pytest.mark.parametrize(("turn", "turned"), [(0.1, False), (1.5, False), (1.7, True), (np.pi, True), (-1.7, True),
                                             (2 * np.pi - 0.1, False)])
def test_turned_around_compares_yaws_over_the_circle(body, turn, turned):
    pose = body.zero_pose()
    pose[3] = 3.0
    other = pose.copy()
    other[3] += turn
    assert tracker.turned_around(other, pose) is turned
