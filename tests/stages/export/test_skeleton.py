import numpy as np
import pytest
from motion_testing import random_motion

from stages.export.skeleton import BONES, FLEXIBLE_BONES, bones_among, settled_lengths, with_bone_lengths
from stages.joints import JOINT_NAMES, SCORED_JOINTS


def _lengths(joints, names=JOINT_NAMES):
    return np.stack([np.linalg.norm(joints[:, b] - joints[:, a], axis=-1) for a, b in bones_among(names)], axis=-1)


def _growing(n_frames: int = 30, settle: int = 10) -> np.ndarray:
    """A motion whose body grows by up to 7 % over its first ``settle`` frames, as the tracker's does while it
    estimates the segment lengths, and then keeps its size."""
    joints = random_motion(n_frames, seed=11)
    pelvis = joints[:, :1]
    scale = np.minimum(1.0, 0.93 + 0.07 * np.arange(n_frames) / settle)
    return pelvis + (joints - pelvis) * scale[:, None, None]


def test_every_frame_gets_the_last_frames_rigid_lengths_along_its_own_directions():
    joints = _growing()
    rebuilt = with_bone_lengths(joints, JOINT_NAMES, settled_lengths(joints, JOINT_NAMES))
    before, after = _lengths(joints), _lengths(rebuilt)
    for k, bone in enumerate(BONES):
        if bone in FLEXIBLE_BONES:
            np.testing.assert_allclose(after[:, k], before[:, k], atol=1e-12)  # the spine and the neck bend
        else:
            np.testing.assert_allclose(after[:, k], before[-1, k], atol=1e-12)
        i, j = JOINT_NAMES.index(bone[0]), JOINT_NAMES.index(bone[1])
        directions = [(x[:, j] - x[:, i]) / np.linalg.norm(x[:, j] - x[:, i], axis=1, keepdims=True)
                      for x in (joints, rebuilt)]
        np.testing.assert_allclose(directions[1], directions[0], atol=1e-12)
    np.testing.assert_array_equal(rebuilt[:, 0], joints[:, 0])  # the pelvis stays
    np.testing.assert_allclose(rebuilt[10:], joints[10:], atol=1e-12)  # settled frames do not move
    assert np.abs(rebuilt[0] - joints[0]).max() > 0.02


def test_a_subset_of_joints_and_a_wrong_length_count():
    joints = _growing()[:, :15]
    lengths = settled_lengths(joints, SCORED_JOINTS)
    assert len(lengths) == len(BONES) - 2  # no toes
    np.testing.assert_allclose(with_bone_lengths(joints[-3:], SCORED_JOINTS, lengths), joints[-3:], atol=1e-12)
    with pytest.raises(ValueError, match="bone lengths"):
        with_bone_lengths(joints, SCORED_JOINTS, lengths[:-1])


def test_lost_frames_stay_lost():
    joints = _growing()
    joints[4] = np.nan
    rebuilt = with_bone_lengths(joints, JOINT_NAMES, settled_lengths(joints, JOINT_NAMES))
    assert np.isnan(rebuilt[4]).all() and np.isfinite(rebuilt[[3, 5]]).all()


def test_the_pelvis_is_put_on_the_line_between_the_hips():
    joints = random_motion(8, seed=12)
    pelvis, l_hip, r_hip = (JOINT_NAMES.index(n) for n in ("pelvis", "l_hip", "r_hip"))
    joints[:, l_hip, 2] += 0.01  # a hip 1 cm high: the pelvis is off the hip line
    rebuilt = with_bone_lengths(joints, JOINT_NAMES, settled_lengths(joints, JOINT_NAMES))
    across = rebuilt[:, l_hip] - rebuilt[:, r_hip]
    to_left = rebuilt[:, l_hip] - rebuilt[:, pelvis]
    np.testing.assert_allclose(np.cross(across, to_left), 0.0, atol=1e-12)
