"""Initialisation from the data alone: the pose-vector library and finding unusual starting poses."""

import numpy as np
import pytest
from tracking_testing import VOLUME, sample_ellipsoids

from stages.joints import JOINT_NAMES
from stages.tracking.body_file import load_body
from stages.tracking.em import EMParams, fit
from stages.tracking.init import InitParams, initialise
from stages.tracking.library import generic_poses, load_pose_library
from stages.tracking.limbs import (
    body_limbs,
    deserted_limbs,
    exchanged,
    folded,
    misplaced_limbs,
    reinitialise_limb,
    segment_shares,
    swap_limbs,
)


@pytest.mark.parametrize("name", ["default", "paper"])
def test_library_holds_pose_vectors_of_the_body(name):
    body = load_body(name)
    library = load_pose_library(body)
    assert library.ndim == 2 and library.shape[1] == body.pose_size and len(library) > 100
    np.testing.assert_array_equal(library[:, [0, 1, 3]], 0.0)  # at the origin, facing +y
    assert np.all((library[:, 2] > 0.2) & (library[:, 2] < 0.7))  # root height, fraction of height
    np.testing.assert_allclose(body.clip(library), library)  # inside the joint limits
    generic = np.array(generic_poses(body))
    generic[:, 2] /= body.height_m
    np.testing.assert_allclose(library[: len(generic)], generic, atol=1e-12)


def test_a_body_edited_from_a_shipped_one_gets_its_library_only_while_it_moves_alike(monkeypatch):
    from importlib import resources

    from stages.tracking import library
    from stages.tracking.body_file import body_from_text

    text = (resources.files("stages.tracking") / "bodies" / "default.yaml").read_text()
    retargeted = []
    monkeypatch.setattr(library, "library_poses", lambda body, joints: retargeted.append(body) or joints[:, 0])
    wider = body_from_text(text.replace("radii: [0.088, 0.060]", "radii: [0.100, 0.070]"), source="wider.yaml")
    np.testing.assert_array_equal(load_pose_library(wider), load_pose_library(load_body("default")))
    assert not retargeted  # other ellipsoids, the same joints: the stored angle vectors hold
    old_knee = "    dofs:\n      - {name: flex, axis: -x, min: 0, max: 165}\n  - name: r_shank"
    assert old_knee in text
    bent_other_way = text.replace(old_knee, old_knee.replace("axis: -x", "axis: x"))
    turned = body_from_text(bent_other_way, source="turned.yaml")
    assert turned.name == "default" and turned.pose_size == wider.pose_size
    load_pose_library(turned)
    assert len(retargeted) == 1 and retargeted[0] is turned  # same name and size, another joint: retargeted


def _pose(body, yaw, degrees):
    pose = body.zero_pose()
    pose[:2] = [0.3, -0.2]
    pose[3] = yaw
    for name, value in degrees.items():
        pose[body.dof_names.index(name)] = np.radians(value)
    pose = body.clip(pose)
    lowest = body.joint_positions(pose)[13:15, 2].min()  # ankles on the floor
    pose[2] += body.joint_positions(body.zero_pose())[13, 2] - lowest
    return pose


@pytest.mark.parametrize("degrees", [
    {"pelvis.pitch": 40, "l_thigh.flex": 40, "r_thigh.flex": 40, "chest.flex": 40, "l_upperarm.flex": 80,
     "r_upperarm.flex": 80},  # deep forward bend, arms hanging
    {"l_thigh.flex": 100, "l_shank.flex": 30, "r_upperarm.abduct": 60},  # high front kick
])
def test_initialisation_finds_bends_and_kicks(degrees):
    body = load_body("default")
    rng = np.random.default_rng(30)
    truth = _pose(body, 2.0, degrees)
    y, n = sample_ellipsoids(body, truth, 1000, rng, outlier_fraction=0.2)
    result = initialise(y, n, body, VOLUME, load_pose_library(body), estimate_height=False,
                        params=InitParams(headings=8))
    error = np.linalg.norm(body.joint_positions(result.pose) - body.joint_positions(truth), axis=1)
    assert error.mean() < 0.02  # metres


def test_limbs_and_their_mirrors():
    body = load_body("default")
    limbs = {limb.name: limb for limb in body_limbs(body)}
    assert set(limbs) == {"l_upperarm", "r_upperarm", "l_thigh", "r_thigh"}
    arm = limbs["l_upperarm"]
    assert [body.segment_names[s] for s in arm.mirror_segments] == ["r_upperarm", "r_forearm"]
    twist = [body.dof_names[d] for d in arm.dofs].index("l_upperarm.twist")
    assert arm.mirror_sign[twist] == -1 and np.sum(arm.mirror_sign == 1) == len(arm.dofs) - 1


@pytest.mark.parametrize(("limb", "dof", "bent", "degrees"), [
    ("l_upperarm", "l_forearm.flex", False, [0, 60, 120]), ("l_upperarm", "l_forearm.flex", True, [150, 155]),
    ("r_thigh", "r_shank.flex", False, [0, 90, 140]), ("r_thigh", "r_shank.flex", True, [160, 165])])
def test_a_limb_is_folded_when_its_lower_segment_lies_inside_the_upper_one(limb, dof, bent, degrees):
    body = load_body("default", height_m=1.75)
    chain = {item.name: item for item in body_limbs(body)}[limb]
    for angle in degrees:
        pose = body.zero_pose()
        pose[list(body.dof_names).index(dof)] = np.radians(angle)
        assert folded(body, pose, chain) is bent


def test_a_limb_placed_wrong_is_found_and_recovered_locally():
    """An arm stuck behind the back while the data show it reaching forward: EM alone stays there; the
    limb gets far fewer data than its mirror, and the local re-initialisation brings it back."""
    body = load_body("default", height_m=1.75)
    rng = np.random.default_rng(40)
    truth = _pose(body, 0.5, {"l_upperarm.flex": 90, "l_upperarm.abduct": 20, "l_forearm.flex": 40,
                              "r_upperarm.flex": 10, "r_forearm.flex": 20})
    y, n = sample_ellipsoids(body, truth, 1000, rng, outlier_fraction=0.1)
    wrong = truth.copy()
    wrong[body.dof_names.index("l_upperarm.flex")] = np.radians(-60)
    wrong[body.dof_names.index("l_upperarm.abduct")] = 0.0
    wrong[body.dof_names.index("l_forearm.flex")] = np.radians(100)
    em = EMParams(max_iterations=15, normal_noise_rad=np.radians(10), min_outlier_prior=0.05)
    stuck = fit(y, n, body, wrong, VOLUME, em)
    wrist = JOINT_NAMES.index("l_wrist")
    assert np.linalg.norm(body.joint_positions(stuck.pose)[wrist] - body.joint_positions(truth)[wrist]) > 0.2
    suspects = misplaced_limbs(body_limbs(body), stuck, len(y))
    assert [limb.name for limb in suspects] == ["l_upperarm"]
    recovered = reinitialise_limb(y, n, stuck, suspects[0], VOLUME, em, load_pose_library(body))
    assert recovered.log_likelihood[-1] > stuck.log_likelihood[-1]
    error = np.linalg.norm(recovered.body.joint_positions(recovered.pose) - body.joint_positions(truth), axis=1)
    assert error.max() < 0.03  # metres, every joint
    assert misplaced_limbs(body_limbs(body), recovered, len(y)) == []
    # A periodic check, which refines the likeliest hypothesis away from the current angles only, finds it too,
    # and keeps a fit that is where the data are.
    checked = reinitialise_limb(y, n, stuck, suspects[0], VOLUME, em, load_pose_library(body), refine=1,
                                elsewhere=True)
    error = np.linalg.norm(checked.body.joint_positions(checked.pose) - body.joint_positions(truth), axis=1)
    assert error.max() < 0.03
    assert reinitialise_limb(y, n, recovered, suspects[0], VOLUME, em, load_pose_library(body), refine=1,
                             elsewhere=True) is recovered


@pytest.mark.parametrize("arm", [
    {"l_upperarm.flex": 100, "l_upperarm.abduct": 70, "l_forearm.flex": 60},  # reaching forward and out
    {"l_upperarm.flex": 30, "l_upperarm.abduct": 100, "l_forearm.flex": 110},  # raised sideways, bent
])
def test_a_limb_is_recovered_from_noisy_data_at_angles_off_the_hypothesis_grid(arm):
    """Hypotheses are tens of millimetres off the truth: scored under the fit's narrow Σ they lose to the
    arm left hanging at the side, scored under the initialisation's coarse Σ one of them wins."""
    body = load_body("default", height_m=1.75)
    rng = np.random.default_rng(42)
    truth = _pose(body, 0.5, {**arm, "r_upperarm.flex": 10, "r_forearm.flex": 20})
    y, n = sample_ellipsoids(body, truth, 1000, rng, outlier_fraction=0.1)
    y = y + rng.normal(0.0, 0.015, y.shape)
    n = n + rng.normal(0.0, 0.15, n.shape)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    hanging = truth.copy()
    hanging[[body.dof_names.index(name) for name in arm]] = 0.0
    em = EMParams(max_iterations=15, normal_noise_rad=np.radians(10), min_outlier_prior=0.05)
    stuck = fit(y, n, body, hanging, VOLUME, em)
    suspects = misplaced_limbs(body_limbs(body), stuck, len(y))
    assert [limb.name for limb in suspects] == ["l_upperarm"]
    recovered = reinitialise_limb(y, n, stuck, suspects[0], VOLUME, em, load_pose_library(body))
    error = np.linalg.norm(recovered.body.joint_positions(recovered.pose) - body.joint_positions(truth), axis=1)
    assert error.max() < 0.03  # metres, every joint


def test_limbs_that_lost_their_data_are_found_by_their_usual_share_when_the_mirror_is_no_reference():
    """Both forearms folded onto their upper arms: each explains as little as its mirror, so the mirror
    test sees nothing, but each explains far less than it did at the right pose (its usual share);
    re-initialising those limbs brings them back, and a fit at its usual shares flags nothing."""
    body = load_body("default", height_m=1.75)
    rng = np.random.default_rng(44)
    truth = _pose(body, 0.5, {"l_upperarm.flex": 70, "l_forearm.flex": 30, "r_upperarm.flex": 70,
                              "r_forearm.flex": 30})
    y, n = sample_ellipsoids(body, truth, 1000, rng, outlier_fraction=0.1)
    em = EMParams(max_iterations=15, normal_noise_rad=np.radians(10), min_outlier_prior=0.05)
    good = fit(y, n, body, truth, VOLUME, em)
    usual = segment_shares(body, good.mixture)
    assert usual.sum() == pytest.approx(1.0 - good.mixture.pi[-1])
    assert deserted_limbs(body_limbs(body), good, usual, len(y)) == []
    folded = truth.copy()
    folded[[body.dof_names.index("l_forearm.flex"), body.dof_names.index("r_forearm.flex")]] = np.radians(150)
    stuck = fit(y, n, body, folded, VOLUME, em)
    assert misplaced_limbs(body_limbs(body), stuck, len(y)) == []
    suspects = deserted_limbs(body_limbs(body), stuck, usual, len(y))
    assert [limb.name for limb in suspects] == ["l_upperarm", "r_upperarm"]
    recovered = stuck
    for limb in suspects:
        recovered = reinitialise_limb(y, n, recovered, limb, VOLUME, em, load_pose_library(body))
    error = np.linalg.norm(recovered.body.joint_positions(recovered.pose) - body.joint_positions(truth), axis=1)
    assert error.max() < 0.03  # metres, every joint
    assert deserted_limbs(body_limbs(body), recovered, usual, len(y)) == []


def test_screened_limb_scores_are_the_full_scores_of_the_hypotheses_that_survive():
    """The screening scores every limb hypothesis on the first rows only; the survivors' scores are then their
    scores on all the rows, the others −inf, and the best of the full ranking survive it."""
    from dataclasses import replace

    from stages.tracking.em import hypothesis_scores, log_evidence
    from stages.tracking.init import SCORE_SIGMA_M
    from stages.tracking.limbs import _LIMB_REFINE, _LIMB_SCREEN_KEEP, _limb_grid, _screened_scores
    from stages.tracking.mixture import Mixture, volume_size

    body = load_body("default", height_m=1.75)
    rng = np.random.default_rng(41)
    truth = _pose(body, 0.5, {"l_upperarm.flex": 70, "l_forearm.flex": 50})
    y, n = sample_ellipsoids(body, truth, 400, rng, outlier_fraction=0.1)
    arm = next(limb for limb in body_limbs(body) if limb.name == "l_upperarm")
    hypotheses = np.repeat(truth[None], 125, axis=0)
    hypotheses[:, arm.dofs] = _limb_grid(body, truth, arm)
    mine = np.isin(body.ellipsoid_segment, arm.segments)
    mixture = replace(Mixture.initial(body.n_ellipsoids, SCORE_SIGMA_M, 3), Sigma=np.eye(3) * SCORE_SIGMA_M**2)
    V = volume_size(VOLUME)
    em = EMParams(normal_noise_rad=np.radians(10))
    rest = log_evidence(y, n, body.ellipsoids(truth), mixture, V, which=np.flatnonzero(~mine),
                        normal_noise_rad=em.normal_noise_rad)
    posed = body.posed_ellipsoids(hypotheses)
    full = hypothesis_scores(y, n, posed, mixture, V, which=np.flatnonzero(mine), base=rest,
                             normal_noise_rad=em.normal_noise_rad)[:, 0]
    screened = _screened_scores(y, n, posed, mixture, V, np.flatnonzero(mine), rest, em)
    survived = np.isfinite(screened)
    assert survived.sum() == _LIMB_SCREEN_KEEP
    np.testing.assert_allclose(screened[survived], full[survived], rtol=1e-12)
    assert np.all(screened[~survived] == -np.inf)
    assert survived[np.argsort(full)[::-1][:_LIMB_REFINE]].all()


def test_screened_initialisation_scores_are_the_full_scores_of_the_poses_that_survive():
    """Every library pose is scored at every heading on a few rows; the best `keep` poses are then scored on all
    the rows (the same scores as without screening), the others are −inf, and the poses the refinement takes
    from the full ranking survive."""
    from stages.tracking import init
    from stages.tracking.init import SCORE_SIGMA_M
    from stages.tracking.mixture import Mixture, volume_size

    body = load_body("default", height_m=1.75)
    rng = np.random.default_rng(42)
    truth = _pose(body, 1.0, {"l_thigh.flex": 80, "l_shank.flex": 40, "r_upperarm.abduct": 50})
    y, n = sample_ellipsoids(body, truth, 120, rng, outlier_fraction=0.2)
    library = load_pose_library(body)
    poses = [pose * np.r_[1.0, 1.0, body.height_m, np.ones(body.pose_size - 3)] for pose in library]
    bodies = [body] * len(poses)
    yaws = np.linspace(0.0, 2 * np.pi, 8, endpoint=False)
    mixture = Mixture.initial(body.n_ellipsoids, SCORE_SIGMA_M, 3)
    centre = np.median(y[:, :2], axis=0)
    arguments = (y, n, centre, bodies, poses, yaws, mixture, volume_size(VOLUME), "normals")
    full = init._score(*arguments)
    keep = init._SCREEN_KEEP_FACTOR * InitParams().refine
    screened = init._screened_scores(*arguments, keep=keep)
    survived = np.isfinite(screened).all(axis=1)
    assert survived.sum() == keep and np.all(np.isinf(screened[~survived]))
    np.testing.assert_allclose(screened[survived], full[survived], rtol=1e-12)
    assert survived[np.argsort(-full.max(axis=1))[:InitParams().refine]].all()


def test_legs_that_took_each_other_s_data_are_exchanged_back():
    """Mid-stride, legs swapped (each given the other's angles) explain the data well enough for EM to stay; the
    exchange puts each thigh back on its own data (the knees where they belong; a shank and foot may then settle in
    an optimum of their own, which a limb search is for), and a fit whose legs are right is left as it is."""
    body = load_body("default").scaled(1.75)
    truth = body.zero_pose()
    truth[3] = 0.3
    for name, degrees in [("l_thigh.flex", 30), ("r_thigh.flex", -30), ("l_shank.flex", 20), ("r_shank.flex", 20)]:
        truth[body.dof_names.index(name)] = np.radians(degrees)
    truth = body.clip(truth)
    y, n = sample_ellipsoids(body, truth, 600, np.random.default_rng(3), outlier_fraction=0.2)
    legs = next(limb for limb in body_limbs(body) if limb.name == "l_thigh")
    crossed = fit(y, n, body, body.clip(exchanged(truth, legs)), VOLUME, EMParams(max_iterations=1))

    def error(result, joints=slice(None)):  # metres, the worst joint
        return np.linalg.norm(result.body.joint_positions(result.pose)[joints] - body.joint_positions(truth)[joints],
                              axis=1).max()

    thighs = [JOINT_NAMES.index(name) for name in ("l_hip", "r_hip", "l_knee", "r_knee")]
    assert error(crossed, thighs) > 0.1
    back = swap_limbs(y, n, crossed, legs, VOLUME, EMParams())
    assert error(back, thighs) < 0.01 and error(back) < error(crossed) / 4
    assert swap_limbs(y, n, back, legs, VOLUME, EMParams()) is back


def test_a_pose_symmetric_front_to_back_is_found_turned_around_as_well_and_a_facing_keeps_it_the_right_way():
    """Arms and legs spread sideways: the body turned around with left and right exchanged covers the same space,
    so the data alone cannot say which way the subject faces; told a facing, the search keeps within its
    half-turn."""
    body = load_body("default")
    rng = np.random.default_rng(31)
    truth = _pose(body, 2.0, {"l_upperarm.abduct": 80, "r_upperarm.abduct": 80, "l_thigh.abduct": 20,
                              "r_thigh.abduct": 20})
    y, n = sample_ellipsoids(body, truth, 1000, rng, outlier_fraction=0.2)
    joints = body.joint_positions(truth)
    exchanged_sides = joints[[JOINT_NAMES.index(name.replace("l_", "#").replace("r_", "l_").replace("#", "r_"))
                              for name in JOINT_NAMES]]
    for facing, expected in ((2.0, joints), (2.0 + np.pi, exchanged_sides)):
        result = initialise(y, n, body, VOLUME, load_pose_library(body), estimate_height=False,
                            params=InitParams(headings=8), facing=facing)
        assert abs(np.angle(np.exp(1j * (result.pose[3] - facing)))) < np.pi / 2
        error = np.linalg.norm(body.joint_positions(result.pose) - expected, axis=1)
        assert np.median(error) < 0.04  # metres
