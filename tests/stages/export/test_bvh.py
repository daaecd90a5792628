import bvhio
import numpy as np
import pytest
from motion_testing import random_motion

from calib.errors import InputError
from stages.export.bvh import WORLD_TO_BVH, bvh_from_joints
from stages.joints import JOINT_NAMES, SCORED_JOINTS


def _read_back(path, n_frames: int) -> tuple[dict[str, np.ndarray], float]:
    """Joint world positions (metres, +z up) per name from a BVH file, read by bvhio."""
    root = bvhio.readAsHierarchy(str(path))
    joints = {joint.Name: joint for joint, _, _ in root.layout()}
    positions = {name: np.empty((n_frames, 3)) for name in joints}
    for frame in range(n_frames):
        root.loadPose(frame)
        for name, joint in joints.items():
            positions[name][frame] = np.array(joint.PositionWorld) @ WORLD_TO_BVH  # BVH -> world
    return positions, bvhio.readAsBvh(str(path)).FrameTime


def test_bvh_read_by_bvhio_reproduces_joint_positions(tmp_path):
    joints = random_motion(40, seed=3)
    path = tmp_path / "motion.bvh"
    path.write_text(bvh_from_joints(joints, 1 / 25))
    positions, frame_time = _read_back(path, len(joints))
    assert frame_time == pytest.approx(0.04)
    for j, name in enumerate(JOINT_NAMES):
        error = np.linalg.norm(positions[name] - joints[:, j], axis=1)
        assert error.max() < 1e-3, f"{name}: {error.max() * 1000:.3f} mm"


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
    positions, _ = _read_back(path, len(joints))
    for j, name in enumerate(JOINT_NAMES):
        assert np.abs(positions[name] - joints[:, j]).max() < 1e-3, name


def test_bvh_without_toes_ends_ankles_in_end_sites(tmp_path):
    joints = random_motion(10, seed=4)[:, :15]
    text = bvh_from_joints(joints, 0.04, names=SCORED_JOINTS)
    assert "l_toe" not in text and text.count("End Site") == 5
    path = tmp_path / "motion.bvh"
    path.write_text(text)
    positions, _ = _read_back(path, len(joints))
    assert np.abs(positions["r_ankle"] - joints[:, SCORED_JOINTS.index("r_ankle")]).max() < 1e-3


def test_bvh_offsets_are_median_bone_lengths_in_a_y_up_t_pose():
    joints = random_motion(30, seed=5)
    text = bvh_from_joints(joints, 0.04)
    lines = text.splitlines()
    knee_offset = lines[lines.index("    JOINT l_knee") + 2].split()[1:]
    hip, knee = joints[:, JOINT_NAMES.index("l_hip")], joints[:, JOINT_NAMES.index("l_knee")]
    thigh = np.median(np.linalg.norm(knee - hip, axis=1))
    np.testing.assert_allclose([float(v) for v in knee_offset], [0.0, -thigh, 0.0], atol=1e-6)


def test_bvh_angles_are_smooth_for_smooth_motion():
    joints = random_motion(80, seed=6, amplitude=0.3)
    lines = bvh_from_joints(joints, 0.04).splitlines()
    motion = np.array([[float(v) for v in line.split()] for line in lines[lines.index("MOTION") + 3:]])
    angle_steps = np.abs(np.diff(motion[:, 3:], axis=0))
    assert angle_steps.max() < 30.0


def test_bvh_needs_the_scored_joints():
    joints = random_motion(5, seed=7)[:, 1:]
    with pytest.raises(InputError, match="pelvis"):
        bvh_from_joints(joints, 0.04, names=JOINT_NAMES[1:])
