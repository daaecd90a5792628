import numpy as np
import pytest
from motion_testing import random_motion

from calib.errors import InputError
from stages.export.metrics import evaluate_joints, joint_errors, mask_iou
from stages.joints import JOINT_NAMES, SCORED_JOINTS


def test_constant_offset_of_10_mm_gives_mpjpe_10_and_full_pck():
    truth = random_motion(20, seed=0)
    frames = np.arange(20)
    offset = np.array([0.006, 0.0, -0.008])  # 10 mm
    metrics = evaluate_joints(frames, JOINT_NAMES, truth + offset, frames, JOINT_NAMES, truth)
    assert metrics.joints == SCORED_JOINTS
    assert metrics.mpjpe_mm == pytest.approx(10.0)
    assert all(value == pytest.approx(10.0) for value in metrics.per_joint_mm.values())
    assert metrics.pck(50) == 1.0 and metrics.pck(5) == 0.0
    assert all(error == pytest.approx(0.0, abs=1e-9) for error in metrics.angle_errors_deg.values())
    summary = metrics.summary()
    assert summary["pck"] == {"50mm": 1.0, "100mm": 1.0} and summary["fraction_estimated"] == 1.0


def test_an_offset_that_turns_with_the_body_is_measured_in_its_frame_and_taken_off_the_offset_free_mpjpe():
    """A skeleton that puts each shoulder 20 mm further out and the head 15 mm further forward, in the subject's own
    frame (so that in the world the offset turns as he turns), plus 3 mm of noise: MPJPE counts the offsets, the
    offset-free MPJPE only the noise, and the offsets come out in the body's (left, up, forward) axes."""
    from stages.export.metrics import body_frames

    truth = random_motion(40, seed=3)
    frames = np.arange(40)
    axes = body_frames(truth, JOINT_NAMES)  # (F, 3, 3) columns left, up, forward
    offsets = np.zeros((len(JOINT_NAMES), 3))
    offsets[JOINT_NAMES.index("l_shoulder")] = [0.020, 0.0, 0.0]
    offsets[JOINT_NAMES.index("r_shoulder")] = [-0.020, 0.0, 0.0]
    offsets[JOINT_NAMES.index("head")] = [0.0, 0.0, 0.015]
    noise = np.random.default_rng(3).normal(0.0, 0.003 / np.sqrt(3), truth.shape)
    estimate = truth + np.einsum("fab,jb->fja", axes, offsets) + noise
    metrics = evaluate_joints(frames, JOINT_NAMES, estimate, frames, JOINT_NAMES, truth)
    summary = metrics.summary()
    assert summary["offset_free_mpjpe_mm"] == pytest.approx(2.8, abs=0.4)  # the noise's mean norm
    assert summary["mpjpe_mm"] > summary["offset_free_mpjpe_mm"] + 2.5  # (20 + 20 + 15) / 15 joints, about
    np.testing.assert_allclose(summary["per_joint_offset_mm"]["l_shoulder"], [20.0, 0.0, 0.0], atol=1.0)
    np.testing.assert_allclose(summary["per_joint_offset_mm"]["r_shoulder"], [-20.0, 0.0, 0.0], atol=1.0)
    np.testing.assert_allclose(summary["per_joint_offset_mm"]["head"], [0.0, 0.0, 15.0], atol=1.0)
    without_hips = [name for name in JOINT_NAMES if name not in ("l_hip", "r_hip")]
    partial = evaluate_joints(frames, without_hips, estimate[:, [JOINT_NAMES.index(n) for n in without_hips]],
                              frames, JOINT_NAMES, truth).summary()
    assert partial["offset_free_mpjpe_mm"] is None and partial["per_joint_offset_mm"] is None  # no body frame


def test_missing_frames_lower_the_fraction_and_the_worst_frame_is_found():
    truth = random_motion(10, seed=1)
    estimate = truth.copy()
    estimate[6, JOINT_NAMES.index("l_wrist")] += [0.0, 0.3, 0.0]   # one joint 300 mm off in frame 6
    kept = np.array([0, 1, 2, 3, 6, 7, 8, 9])                     # frames 4 and 5 lost
    metrics = evaluate_joints(kept, JOINT_NAMES, estimate[kept], np.arange(10), JOINT_NAMES, truth)
    summary = metrics.summary()
    assert summary["fraction_estimated"] == pytest.approx(0.8)
    assert summary["worst_frame"] == {"frame": 6, "mpjpe_mm": pytest.approx(300.0 / 15)}
    assert summary["mpjpe_mm"] == pytest.approx(300.0 / 15 / 8)
    assert summary["pck"]["100mm"] == pytest.approx(1 - 1 / (15 * 8))
    assert summary["per_joint_mpjpe_mm"]["l_wrist"] == pytest.approx(300.0 / 8)
    assert summary["angle_errors_deg"]["l_elbow_flexion"] > 1.0
    assert summary["angle_errors_deg"]["r_knee_flexion"] == pytest.approx(0.0, abs=1e-9)


def test_truth_with_a_joint_subset_in_another_order_scores_the_common_joints():
    truth = random_motion(4, seed=2)
    names = ("r_knee", "pelvis", "l_knee")
    subset = truth[:, [JOINT_NAMES.index(n) for n in names]]
    metrics = evaluate_joints(np.arange(4), JOINT_NAMES, truth, np.arange(4), names, subset)
    assert metrics.joints == ("pelvis", "l_knee", "r_knee")  # SCORED_JOINTS order
    assert metrics.mpjpe_mm == 0.0 and metrics.angle_errors_deg == {}


def test_no_common_frames_is_an_input_error():
    truth = random_motion(3, seed=3)
    with pytest.raises(InputError, match="do not overlap"):
        evaluate_joints(np.arange(3), JOINT_NAMES, truth, np.arange(10, 13), JOINT_NAMES, truth)


def test_no_common_joints_is_an_input_error():
    truth = random_motion(3, seed=3)
    with pytest.raises(InputError, match="share no scored joint"):
        evaluate_joints(np.arange(3), JOINT_NAMES[:2], truth[:, :2],
                        np.arange(3), ("l_toe",), truth[:, 15:16])


def test_joint_errors_are_euclidean():
    np.testing.assert_allclose(joint_errors(np.zeros((1, 1, 3)), [[[3.0, 4.0, 0.0]]]), [[5.0]])


def test_mask_iou_known_answers():
    a = np.zeros((4, 4), np.uint8)
    b = np.zeros((4, 4), np.uint8)
    assert mask_iou(a, b) == 1.0
    a[:2] = 255       # 8 pixels
    b[1:3] = 255      # 8 pixels, 4 shared
    assert mask_iou(a, b) == pytest.approx(4 / 12)
