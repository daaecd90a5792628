import numpy as np
import pytest
from motion_testing import random_motion
from scipy.spatial.transform import Rotation

from stages.export.angles import (
    ANGLE_NAMES,
    MIN_HINGE_FLEXION_DEG,
    angle_between,
    format_angles_csv,
    joint_angles,
)
from stages.joints import JOINT_NAMES, SCORED_JOINTS

THIGH, SHANK, UPPER_ARM, FOREARM, FOOT = 0.45, 0.43, 0.30, 0.26, 0.14


def _pose(heading_deg: float = 30.0, **angles: float) -> np.ndarray:
    """(1, 17, 3) a person built from anatomical angles (degrees, keyword ``<side>_<angle>``, default 0).

    The pelvis and thorax frames are one (X anterior, Y up, Z right), turned by ``heading_deg`` about the
    vertical; each limb is the swing of attitude vector (-abduction, 0, flexion) after the twist ``Ry(rotation)``
    from that frame, then its hinge, built for a right limb and mirrored through the sagittal plane for a left one.
    """
    turn = Rotation.from_euler("z", heading_deg, degrees=True).as_matrix()
    trunk = turn @ np.column_stack([[0, 1, 0], [0, 0, 1], [1, 0, 0]])  # columns X, Y, Z in the world
    centre = np.array([0.3, -0.2, 1.0])
    p = {"pelvis": centre, "neck": centre + trunk @ [0, 0.5, 0], "head": centre + trunk @ [0, 0.7, 0]}

    def limb(side, root, hinge, distal, forward, lengths):
        get = {name: np.radians(angles.get(f"{side}_{name}", 0.0)) for name in (hinge[1], "flexion", "abduction",
                                                                              "rotation")}
        frame = (Rotation.from_rotvec([-get["abduction"], 0.0, get["flexion"]])
                 * Rotation.from_euler("y", get["rotation"])).as_matrix()
        k = get[hinge[1]]
        bend = np.array([np.sin(k) if forward else -np.sin(k), -np.cos(k), 0.0])
        mirror = np.diag([1.0, 1.0, -1.0 if side == "l" else 1.0])
        start = p[f"{side}_{root}"]
        middle = start + trunk @ mirror @ frame @ [0, -lengths[0], 0]
        p[f"{side}_{hinge[0]}"] = middle
        p[f"{side}_{distal}"] = middle + trunk @ mirror @ frame @ (lengths[1] * bend)

    for side, sign in (("l", -1.0), ("r", 1.0)):
        p[f"{side}_hip"] = centre + trunk @ [0, 0, 0.1 * sign]
        p[f"{side}_shoulder"] = p["neck"] + trunk @ [0, 0, 0.2 * sign]
        limb(side, "hip", ("knee", "knee_flexion"), "ankle", False, (THIGH, SHANK))
        limb(side, "shoulder", ("elbow", "elbow_flexion"), "wrist", True, (UPPER_ARM, FOREARM))
        dorsi = np.radians(angles.get(f"{side}_ankle_dorsiflexion", 0.0))
        shank_up = p[f"{side}_knee"] - p[f"{side}_ankle"]
        shank_up /= np.linalg.norm(shank_up)
        forward = trunk[:, 0] - (trunk[:, 0] @ shank_up) * shank_up
        forward /= np.linalg.norm(forward)
        p[f"{side}_toe"] = p[f"{side}_ankle"] + FOOT * (np.cos(dorsi) * forward + np.sin(dorsi) * shank_up)
    return np.array([[p[name] for name in JOINT_NAMES]])


def _angles(pose: np.ndarray) -> dict[str, float]:
    names, values = joint_angles(pose)
    return dict(zip(names, values[0], strict=True))


def test_standing_reads_zero_and_leaves_the_rotation_of_straight_limbs_empty():
    value = _angles(_pose())
    for name in ANGLE_NAMES:
        if name.endswith("_rotation"):
            assert np.isnan(value[name]), name
        else:
            assert value[name] == pytest.approx(0.0, abs=1e-9), name


@pytest.mark.parametrize("side", ["l", "r"])
def test_hip_and_knee_angles_are_recovered_on_both_sides(side):
    set_ = {f"{side}_flexion": 35.0, f"{side}_abduction": 12.0, f"{side}_rotation": -25.0,
            f"{side}_knee_flexion": 60.0}
    value = _angles(_pose(**set_))
    # the same keywords drive the hip and the shoulder in _pose: both limbs of the side carry the angles
    assert value[f"{side}_hip_flexion"] == pytest.approx(35.0)
    assert value[f"{side}_hip_abduction"] == pytest.approx(12.0)
    assert value[f"{side}_hip_rotation"] == pytest.approx(-25.0)
    assert value[f"{side}_knee_flexion"] == pytest.approx(60.0)
    assert value[f"{side}_shoulder_flexion"] == pytest.approx(35.0)
    assert value[f"{side}_shoulder_abduction"] == pytest.approx(12.0)
    assert np.isnan(value[f"{side}_shoulder_rotation"])  # the elbow is straight
    other = "r" if side == "l" else "l"
    assert value[f"{other}_hip_flexion"] == pytest.approx(0.0, abs=1e-9)


def test_a_hyperextended_knee_reads_negative():
    value = _angles(_pose(l_knee_flexion=-8.0, r_knee_flexion=8.0, l_rotation=30.0))
    assert value["l_knee_flexion"] == pytest.approx(-8.0)
    assert value["r_knee_flexion"] == pytest.approx(8.0)


def test_shoulder_rotation_spans_the_full_turn_and_the_elbow_never_reads_negative():
    value = _angles(_pose(r_flexion=20.0, r_abduction=30.0, r_rotation=120.0, r_elbow_flexion=90.0,
                          l_rotation=-70.0, l_elbow_flexion=45.0))
    assert value["r_shoulder_rotation"] == pytest.approx(120.0)
    assert value["r_elbow_flexion"] == pytest.approx(90.0)
    assert value["l_shoulder_rotation"] == pytest.approx(-70.0)
    assert value["l_elbow_flexion"] == pytest.approx(45.0)


def test_rotation_needs_a_bent_hinge():
    below = _angles(_pose(r_rotation=30.0, r_knee_flexion=MIN_HINGE_FLEXION_DEG - 1))
    above = _angles(_pose(r_rotation=30.0, r_knee_flexion=MIN_HINGE_FLEXION_DEG + 1))
    assert np.isnan(below["r_hip_rotation"]) and above["r_hip_rotation"] == pytest.approx(30.0)


@pytest.mark.parametrize(("flexion", "abduction"), [(135.0, 0.0), (0.0, 135.0), (100.0, 10.0), (-30.0, 20.0),
                                                   (0.0, 90.0), (60.0, 80.0)])
def test_raised_limbs_read_without_gimbal_lock(flexion, abduction):
    """Overhead forwards or sideways, horizontal to the side (a Cardan sequence's gimbal lock), a side kick."""
    value = _angles(_pose(r_flexion=flexion, r_abduction=abduction, r_rotation=40.0, r_elbow_flexion=70.0,
                          r_knee_flexion=70.0))
    for limb in ("shoulder", "hip"):
        assert value[f"r_{limb}_flexion"] == pytest.approx(flexion)
        assert value[f"r_{limb}_abduction"] == pytest.approx(abduction)
        assert value[f"r_{limb}_rotation"] == pytest.approx(40.0)
    assert value["r_knee_flexion"] == pytest.approx(70.0) and value["r_elbow_flexion"] == pytest.approx(70.0)
    assert value["r_shoulder_elevation"] == pytest.approx(np.hypot(flexion, abduction))


def test_a_high_chambered_kick_keeps_its_knee_flexed_and_its_hip_rotation():
    """A thigh raised high and out to the side, turned beyond 90 degrees from the frame its swing carries: the
    bend looks forwards there, but a deep one is a flexion (no knee hyperextends 130 degrees)."""
    value = _angles(_pose(l_flexion=60.0, l_abduction=130.0, l_rotation=-115.0, l_knee_flexion=130.0))
    assert value["l_knee_flexion"] == pytest.approx(130.0) and value["l_hip_rotation"] == pytest.approx(-115.0)
    assert value["l_hip_abduction"] == pytest.approx(130.0)


def test_ankle_dorsiflexion_and_elevations():
    value = _angles(_pose(l_ankle_dorsiflexion=15.0, r_ankle_dorsiflexion=-30.0, l_abduction=40.0))
    assert value["l_ankle_dorsiflexion"] == pytest.approx(15.0)
    assert value["r_ankle_dorsiflexion"] == pytest.approx(-30.0)
    assert value["l_hip_elevation"] == pytest.approx(40.0)  # raised sideways: elevation = abduction
    assert value["l_shoulder_elevation"] == pytest.approx(40.0)


def test_trunk_inclination_and_a_lean_measured_against_the_trunk():
    pose = _pose()
    index = JOINT_NAMES.index
    pose[0, index("neck")] = pose[0, index("pelvis")] + [0, 0.5 * np.sin(0.5), 0.5 * np.cos(0.5)]
    value = _angles(pose)
    assert value["trunk_inclination"] == pytest.approx(np.degrees(0.5))
    assert value["l_hip_elevation"] == pytest.approx(np.degrees(0.5))  # trunk leans, thigh stays vertical


def test_angle_between_is_exact_near_zero_and_straight():
    u = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    v = np.array([[1.0, 1e-9, 0.0], [-1.0, 1e-9, 0.0]])
    np.testing.assert_allclose(angle_between(u, v), [np.degrees(1e-9), 180 - np.degrees(1e-9)], rtol=1e-6)


def test_angles_without_toes_and_subset_of_joints():
    joints = random_motion(5, seed=1)
    names, angles = joint_angles(joints[:, :15], SCORED_JOINTS)
    assert "l_ankle_dorsiflexion" not in names and angles.shape == (5, len(names))
    assert names == tuple(name for name in ANGLE_NAMES if "ankle" not in name)
    no_arms = [n for n in JOINT_NAMES if "wrist" not in n]
    names, _ = joint_angles(joints[:, [JOINT_NAMES.index(n) for n in no_arms]], no_arms)
    assert "l_elbow_flexion" not in names and "l_knee_flexion" in names and "l_shoulder_elevation" in names


def test_angles_csv_text_leaves_undefined_angles_empty():
    text = format_angles_csv(np.array([3, 4]), ("a", "b"), np.array([[1.0, np.nan], [90.0, 180.0]]))
    assert text == "frame,a,b\n3,1.000,\n4,90.000,180.000\n"
