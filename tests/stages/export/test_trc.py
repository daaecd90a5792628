import numpy as np
import pytest
from motion_testing import random_motion
from trc import TRCData  # trc-data-reader: an independent TRC parser

from stages.export.joints_table import regular_grid
from stages.export.trc import HALPE26_NAMES, format_trc
from stages.joints import JOINT_NAMES


def _read(path) -> TRCData:
    data = TRCData()
    data.load(str(path))
    return data


def _world(data: TRCData, marker: str) -> np.ndarray:
    """(F, 3) a marker's positions back in the world frame (metres, +z up) from TRC's +Y up millimetres."""
    xyz = np.array(data[marker], dtype=float) / 1000.0
    return np.column_stack([xyz[:, 0], -xyz[:, 2], xyz[:, 1]])


def test_trc_read_by_an_independent_parser_gives_back_the_joints(tmp_path):
    joints = random_motion(12, seed=2)
    frames = 30 + 2 * np.arange(12)
    kept = np.arange(12) != 5  # frame 40 lost
    grid, gridded = regular_grid(frames[kept], joints[kept])
    path = tmp_path / "joints.trc"
    path.write_text(format_trc(grid, gridded, 50.0, JOINT_NAMES))
    data = _read(path)
    assert data["DataRate"] == pytest.approx(25.0) and data["CameraRate"] == pytest.approx(25.0)
    assert data["NumFrames"] == 12 and data["NumMarkers"] == 17 and data["Units"] == "mm"
    assert data["OrigDataStartFrame"] == 30 and data["FileName"] == "joints.trc"
    assert data["Markers"] == list(JOINT_NAMES)
    assert data["Frame#"] == frames.tolist()
    np.testing.assert_allclose(data["Time"], frames / 50.0)
    for j, name in enumerate(JOINT_NAMES):
        read = _world(data, name)
        np.testing.assert_allclose(read[kept], joints[kept, j], atol=1e-7)
        assert np.isnan(read[5]).all()  # the lost frame's cells are empty


def test_trc_is_y_up_and_can_take_pose2sim_names(tmp_path):
    joints = random_motion(3, seed=4)
    grid, gridded = regular_grid(np.arange(3), joints)
    text = format_trc(grid, gridded, 30.0, JOINT_NAMES, marker_names=HALPE26_NAMES)
    path = tmp_path / "joints.trc"
    path.write_text(text)
    data = _read(path)
    assert data["Markers"][:3] == ["Hip", "Neck", "Head"] and "LBigToe" in data["Markers"]
    head_height = np.array(data["Head"])[:, 1] / 1000.0  # TRC Y is the world's height
    np.testing.assert_allclose(head_height, joints[:, JOINT_NAMES.index("head"), 2], atol=1e-7)
    assert text.splitlines()[0] == "PathFileType\t4\t(X/Y/Z)\tjoints.trc" and text.splitlines()[5] == ""
