import bvhio
import numpy as np
import pytest
from export_testing import read_bvh_positions
from motion_testing import random_motion

from calib.errors import InputError
from stages.export.bvh import MIXAMO_NAMES, bvh_from_joints
from stages.joints import JOINT_NAMES, SCORED_JOINTS


@pytest.mark.parametrize("units", ["cm", "m", "mm"])
def test_bvh_read_by_bvhio_reproduces_joint_positions(tmp_path, units):
    joints = random_motion(40, seed=3)
    path = tmp_path / "motion.bvh"
    path.write_text(bvh_from_joints(joints, 1 / 25, units=units))
    positions, frame_time = read_bvh_positions(path, len(joints), units)
    assert frame_time == pytest.approx(0.04)
    for j, name in enumerate(JOINT_NAMES):
        error = np.linalg.norm(positions[name] - joints[:, j], axis=1)
        assert error.max() < 1e-4, f"{name}: {error.max() * 1000:.4f} mm"


def test_bvh_with_mixamo_names(tmp_path):
    joints = random_motion(10, seed=9)
    text = bvh_from_joints(joints, 1 / 30, naming="mixamo")
    assert "ROOT Hips" in text and "JOINT LeftForeArm" in text and "l_elbow" not in text
    path = tmp_path / "motion.bvh"
    path.write_text(text)
    positions, _ = read_bvh_positions(path, len(joints))
    assert set(positions) == set(MIXAMO_NAMES.values())
    for name in ("l_elbow", "r_toe", "head", "neck"):
        assert np.abs(positions[MIXAMO_NAMES[name]] - joints[:, JOINT_NAMES.index(name)]).max() < 1e-4, name
    hierarchy = bvhio.readAsHierarchy(str(path))
    chest = hierarchy.filter("Spine2")[0]
    assert {child.Name for child in chest.Children} == {"Neck", "LeftShoulder", "RightShoulder"}


def test_bvh_follows_a_stretching_trunk_exactly(tmp_path):
    joints = random_motion(30, seed=8)
    pelvis, neck = JOINT_NAMES.index("pelvis"), JOINT_NAMES.index("neck")
    upper = [JOINT_NAMES.index(n) for n in ("neck", "head", "l_shoulder", "r_shoulder", "l_elbow", "r_elbow",
                                            "l_wrist", "r_wrist")]
    trunk = joints[:, neck] - joints[:, pelvis]
    stretch = 0.05 * np.sin(np.arange(30) / 3)[:, None] * trunk / np.linalg.norm(trunk, axis=1, keepdims=True)
    joints[:, upper] += stretch[:, None]   # the spine bends: pelvis-neck distance varies by +-5 cm
    path = tmp_path / "motion.bvh"
    path.write_text(bvh_from_joints(joints, 1 / 25))
    positions, _ = read_bvh_positions(path, len(joints))
    for j, name in enumerate(JOINT_NAMES):
        assert np.abs(positions[name] - joints[:, j]).max() < 1e-4, name


def test_bvh_without_toes_ends_ankles_in_end_sites(tmp_path):
    joints = random_motion(10, seed=4)[:, :15]
    text = bvh_from_joints(joints, 0.04, names=SCORED_JOINTS)
    assert "l_toe" not in text and text.count("End Site") == 5
    path = tmp_path / "motion.bvh"
    path.write_text(text)
    positions, _ = read_bvh_positions(path, len(joints))
    assert np.abs(positions["r_ankle"] - joints[:, SCORED_JOINTS.index("r_ankle")]).max() < 1e-4


def test_bvh_offsets_are_median_bone_lengths_in_a_y_up_t_pose():
    joints = random_motion(30, seed=5)
    lines = bvh_from_joints(joints, 0.04, units="m").splitlines()
    knee_offset = lines[lines.index("    JOINT l_knee") + 2].split()[1:]
    hip, knee = joints[:, JOINT_NAMES.index("l_hip")], joints[:, JOINT_NAMES.index("l_knee")]
    thigh = np.median(np.linalg.norm(knee - hip, axis=1))
    np.testing.assert_allclose([float(v) for v in knee_offset], [0.0, -thigh, 0.0], atol=1e-6)
    in_cm = bvh_from_joints(joints, 0.04).splitlines()
    np.testing.assert_allclose(float(in_cm[in_cm.index("    JOINT l_knee") + 2].split()[2]), -100 * thigh, atol=1e-5)


def test_bvh_angles_are_smooth_for_smooth_motion():
    joints = random_motion(80, seed=6, amplitude=0.3)
    lines = bvh_from_joints(joints, 0.04).splitlines()
    motion = np.array([[float(v) for v in line.split()] for line in lines[lines.index("MOTION") + 3:]])
    steps = np.abs(np.diff(motion[:, 3:], axis=0))  # angles, and the chest's and head's bone lengths (cm)
    assert steps.max() < 30.0


def test_bvh_needs_the_scored_joints_and_known_options():
    joints = random_motion(5, seed=7)
    with pytest.raises(InputError, match="pelvis"):
        bvh_from_joints(joints[:, 1:], 0.04, names=JOINT_NAMES[1:])
    with pytest.raises(ValueError, match="units"):
        bvh_from_joints(joints, 0.04, units="inch")
