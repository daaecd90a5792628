import numpy as np
import pytest
from motion_testing import random_motion

from calib.errors import InputError
from stages.export.joints_table import (
    fill_gaps,
    format_joints_csv,
    parse_joints_csv,
    regular_grid,
    select_joints,
)
from stages.joints import JOINT_NAMES


def test_joints_csv_round_trip_with_missing_frames():
    joints = random_motion(6, seed=0)
    frames = np.array([5, 0, 1, 2, 3, 9])  # unordered, with gaps
    text = format_joints_csv(frames, joints)
    lines = text.splitlines()
    assert lines[0] == "frame,joint,x,y,z" and len(lines) == 1 + 6 * 17
    assert lines[1].startswith("0,pelvis,") and "nan" not in text.lower()
    read_frames, names, read = parse_joints_csv(text)
    order = np.argsort(frames)
    np.testing.assert_array_equal(read_frames, frames[order])
    assert names == JOINT_NAMES
    np.testing.assert_allclose(read, joints[order], atol=1e-7)


def test_reader_accepts_any_joint_subset_and_row_order():
    text = "frame,joint,x,y,z\n1,r_knee,1,2,3\n0,l_knee,0,0,0\n0,r_knee,4,5,6\n1,l_knee,7,8,9\n"
    frames, names, joints = parse_joints_csv(text)
    assert names == ("l_knee", "r_knee")
    np.testing.assert_array_equal(frames, [0, 1])
    np.testing.assert_array_equal(joints, [[[0, 0, 0], [4, 5, 6]], [[7, 8, 9], [1, 2, 3]]])


@pytest.mark.parametrize(("text", "message"), [
    ("", "header"),
    ("frame,joint,x,y\n0,pelvis,1,2\n", "header"),
    ("frame,joint,x,y,z\n", "no data rows"),
    ("frame,joint,x,y,z\n0,pelvis,1,2\n", "joints.csv:2: 4 fields"),
    ("frame,joint,x,y,z\n0,pelvis,1,two,3\n", "not an integer frame"),
    ("frame,joint,x,y,z\n0,pelvis,1,nan,3\n", "not finite"),
    ("frame,joint,x,y,z\n0,pelvis,1,2,3\n0,pelvis,1,2,3\n", "appears twice"),
    ("frame,joint,x,y,z\n0,pelvis,1,2,3\n0,neck,1,2,3\n1,pelvis,1,2,3\n", "frame 1 lacks joints neck"),
    ("frame,joint,x,y,z\n-1,pelvis,1,2,3\n", "frame number >= 0"),
])
def test_malformed_joints_csv_is_an_input_error(text, message):
    with pytest.raises(InputError, match=message):
        parse_joints_csv(text, source="joints.csv")


def test_writer_refuses_nan():
    joints = random_motion(2, seed=1)
    joints[1, 3, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        format_joints_csv(np.arange(2), joints)


def test_select_joints_names_the_missing_ones():
    joints = random_motion(2, seed=2)
    np.testing.assert_array_equal(select_joints(JOINT_NAMES, joints, ["neck", "pelvis"], source="x"),
                                  joints[:, [1, 0]])
    with pytest.raises(InputError, match="x: joints spine are missing"):
        select_joints(JOINT_NAMES, joints, ["pelvis", "spine"], source="x")


def test_regular_grid_uses_the_frame_step_and_fill_gaps_interpolates():
    joints = np.arange(4 * 1 * 3, dtype=float).reshape(4, 1, 3)
    grid, gridded = regular_grid(np.array([10, 12, 18, 14]), joints)   # step 2, frame 16 lost
    np.testing.assert_array_equal(grid, [10, 12, 14, 16, 18])
    assert np.isnan(gridded[3]).all()
    np.testing.assert_array_equal(gridded[2], joints[3])
    filled = fill_gaps(gridded)
    np.testing.assert_allclose(filled[3], (joints[3] + joints[2]) / 2)
