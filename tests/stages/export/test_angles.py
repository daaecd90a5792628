import numpy as np
import pytest
from motion_testing import random_motion

from stages.export.angles import ANGLE_NAMES, angle_between, format_angles_csv, joint_angles
from stages.joints import JOINT_NAMES, SCORED_JOINTS


def _standing() -> np.ndarray:
    """(1, 17, 3) an upright person, arms hanging, legs straight (metres, +z up, facing +y)."""
    p = {"pelvis": (0, 0, 1.0), "neck": (0, 0, 1.5), "head": (0, 0, 1.7),
         "l_shoulder": (-0.2, 0, 1.5), "r_shoulder": (0.2, 0, 1.5), "l_elbow": (-0.2, 0, 1.2),
         "r_elbow": (0.2, 0, 1.2), "l_wrist": (-0.2, 0, 0.95), "r_wrist": (0.2, 0, 0.95),
         "l_hip": (-0.1, 0, 1.0), "r_hip": (0.1, 0, 1.0), "l_knee": (-0.1, 0, 0.55), "r_knee": (0.1, 0, 0.55),
         "l_ankle": (-0.1, 0, 0.1), "r_ankle": (0.1, 0, 0.1), "l_toe": (-0.1, 0.15, 0.02),
         "r_toe": (0.1, 0.15, 0.02)}
    return np.array([[p[name] for name in JOINT_NAMES]], dtype=float)


def test_standing_pose_has_zero_angles():
    names, angles = joint_angles(_standing())
    assert names == ANGLE_NAMES
    np.testing.assert_allclose(angles, 0.0, atol=1e-9)


def test_known_angles_of_a_bent_pose():
    pose = _standing()
    index = JOINT_NAMES.index
    pose[0, index("l_ankle")] = pose[0, index("l_knee")] + [0, -0.45, 0]      # shank horizontal backwards
    pose[0, index("r_elbow")] = pose[0, index("r_shoulder")] + [0.3, 0, 0]    # arm abducted to the side
    pose[0, index("r_wrist")] = pose[0, index("r_elbow")] + [0, 0, 0.25]      # forearm up
    pose[0, index("neck")] = pose[0, index("pelvis")] + [0, 0.5 * np.sin(0.5), 0.5 * np.cos(0.5)]
    names, angles = joint_angles(pose)
    value = dict(zip(names, angles[0], strict=True))
    assert value["l_knee_flexion"] == pytest.approx(90.0)
    assert value["r_shoulder_angle"] == pytest.approx(90.0)  # arm along x, trunk leaning in the y-z plane
    assert value["r_elbow_flexion"] == pytest.approx(90.0)
    assert value["trunk_inclination"] == pytest.approx(np.degrees(0.5))
    assert value["l_hip_angle"] == pytest.approx(np.degrees(0.5))  # trunk leans, thigh stays vertical


def test_angle_between_is_exact_near_zero_and_straight():
    u = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    v = np.array([[1.0, 1e-9, 0.0], [-1.0, 1e-9, 0.0]])
    np.testing.assert_allclose(angle_between(u, v), [np.degrees(1e-9), 180 - np.degrees(1e-9)], rtol=1e-6)


def test_angles_without_toes_and_subset_of_joints():
    joints = random_motion(5, seed=1)
    names, angles = joint_angles(joints[:, :15], SCORED_JOINTS)
    assert names == ANGLE_NAMES and angles.shape == (5, len(ANGLE_NAMES))
    no_arms = [n for n in JOINT_NAMES if "wrist" not in n]
    names, _ = joint_angles(joints[:, [JOINT_NAMES.index(n) for n in no_arms]], no_arms)
    assert "l_elbow_flexion" not in names and "l_knee_flexion" in names


def test_angles_csv_text():
    text = format_angles_csv(np.array([3, 4]), ("a", "b"), np.array([[1.0, 2.5], [90.0, 180.0]]))
    assert text == "frame,a,b\n3,1.000,2.500\n4,90.000,180.000\n"
