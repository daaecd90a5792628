import struct

import bvhio
import c3d
import ezc3d
import numpy as np
import pytest
from conftest import make_capture, stick_figure
from export_testing import read_bvh_positions
from trc import TRCData

from calib.errors import InputError
from pipeline.cli import main
from pipeline.io.export_io import (
    read_joints_csv,
    write_exports,
    write_joints_csv,
)
from pipeline.io.run_layout import MANIFEST
from stages.export import ExportParams
from stages.export.angles import ANGLE_NAMES
from stages.export.quality import FrameQuality
from stages.joints import JOINT_NAMES


def _walk(n_frames: int) -> np.ndarray:
    """(n_frames, 17, 3) a stick figure walking along +y (metres, +z up); constant bone lengths."""
    base = stick_figure()
    return base[None] + np.arange(n_frames)[:, None, None] * np.array([0.0, 0.03, 0.0])


def test_joints_csv_file_round_trip(tmp_path):
    joints = _walk(4)
    write_joints_csv(tmp_path / "joints.csv", np.arange(4), joints)
    frames, names, read = read_joints_csv(tmp_path / "joints.csv")
    assert names == JOINT_NAMES
    np.testing.assert_allclose(read, joints, atol=1e-7)


def test_a_joints_csv_read_again_is_the_files_content_whatever_the_last_reader_did(tmp_path):
    path = tmp_path / "joints.csv"
    write_joints_csv(path, np.arange(4), _walk(4))
    frames, _, joints = read_joints_csv(path)
    frames[:], joints[:] = -1, np.nan  # a reader's own arrays: the next read does not see this
    np.testing.assert_allclose(read_joints_csv(path)[2], _walk(4), atol=1e-7)
    write_joints_csv(path, np.arange(3), _walk(3) + 1.0)  # the file rewritten: read anew
    frames, _, joints = read_joints_csv(path)
    assert frames.tolist() == [0, 1, 2]
    np.testing.assert_allclose(joints, _walk(3) + 1.0, atol=1e-7)


def test_read_joints_csv_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match="missing.csv: file not found"):
        read_joints_csv(tmp_path / "missing.csv")
    (tmp_path / "bad.csv").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(InputError, match="bad.csv: not a readable text file"):
        read_joints_csv(tmp_path / "bad.csv")
    (tmp_path / "short.csv").write_text("frame,joint,x,y,z\n0,pelvis,1\n")
    with pytest.raises(InputError, match="short.csv:2: 3 fields"):
        read_joints_csv(tmp_path / "short.csv")


def _tracked_like(n_frames: int) -> np.ndarray:
    """A walk whose body grows by 6 % over its first ten frames and then keeps its size, as the tracker's
    joints do while it estimates the segment lengths, with the arms swinging (bones change direction)."""
    joints = _walk(n_frames)
    pelvis = joints[:, :1]
    t = np.arange(n_frames)
    swing = 0.15 * np.sin(t / 3.0)
    for side in ("l", "r"):
        for name in (f"{side}_elbow", f"{side}_wrist"):
            joints[:, JOINT_NAMES.index(name), 1] += swing * (1 if name.endswith("wrist") else 0.5)
    scale = np.minimum(1.0, 0.94 + 0.06 * t / 10)
    return pelvis + (joints - pelvis) * scale[:, None, None]


@pytest.mark.filterwarnings("ignore:No analog data found")
def test_every_export_reproduces_joints_csv_in_every_frame(tmp_path):
    """joints.csv, BVH (bvhio), TRC (trc-data-reader) and C3D (ezc3d and the c3d package) agree within
    0.1 mm in every frame, the first frames of a body still changing size included."""
    joints = _tracked_like(24)
    frames = 30 + 2 * np.arange(24)
    kept = np.ones(24, bool)
    kept[[3, 15]] = False  # two lost frames
    paths = write_exports(tmp_path, frames[kept], joints[kept], fps=50.0)
    csv_frames, names, exported = read_joints_csv(paths["joints.csv"])
    np.testing.assert_array_equal(csv_frames, frames[kept])
    assert np.abs(exported[0] - joints[0]).max() > 0.01  # the first frame took the settled size

    grid_index = (csv_frames - 30) // 2
    bvh, _ = read_bvh_positions(paths["motion.bvh"], 24)  # centimetres by default
    trc = TRCData()
    trc.load(str(paths["joints.trc"]))
    assert trc["Frame#"] == frames.tolist() and trc["OrigDataStartFrame"] == 30
    c3d_points = ezc3d.c3d(str(paths["joints.c3d"]))["data"]["points"]
    with open(paths["joints.c3d"], "rb") as handle:
        c3d_reader = c3d.Reader(handle)
        c3d_frames = [points[:, :3].copy() for _, points, _ in c3d_reader.read_frames()]
    for j, name in enumerate(names):
        trc_mm = np.array(trc[name], dtype=float)
        readings = {
            "bvh": bvh[name][grid_index],
            "trc": np.column_stack([trc_mm[:, 0], -trc_mm[:, 2], trc_mm[:, 1]])[grid_index] / 1000,
            "c3d (ezc3d)": c3d_points[:3, j, grid_index].T / 1000,
            "c3d (c3d)": np.array([frame[j] for frame in c3d_frames])[grid_index] / 1000,
        }
        for reader, read in readings.items():
            error = np.linalg.norm(read - exported[:, j], axis=1).max()
            assert error < 1e-4, f"{reader} {name}: {error * 1000:.4f} mm"
        assert np.isnan(trc_mm[3]).all() and np.isnan(c3d_points[:3, j, 3]).all()  # lost: missing, not invented


@pytest.mark.filterwarnings("ignore:No analog data found")
def test_c3d_keeps_the_captures_frame_numbers(tmp_path):
    paths = write_exports(tmp_path, np.arange(30, 40), _walk(10), fps=50.0)
    read = ezc3d.c3d(str(paths["joints.c3d"]))
    assert read["header"]["points"]["first_frame"] == 30 and read["header"]["points"]["last_frame"] == 39
    np.testing.assert_array_equal(read["parameters"]["TRIAL"]["ACTUAL_START_FIELD"]["value"], [31, 0])
    np.testing.assert_array_equal(read["parameters"]["TRIAL"]["ACTUAL_END_FIELD"]["value"], [40, 0])
    header_words = struct.unpack("<4H", paths["joints.c3d"].read_bytes()[:8])
    assert header_words[3] == 31  # the header's own first frame counts from 1
    with open(paths["joints.c3d"], "rb") as handle:
        reader = c3d.Reader(handle)
        assert (reader.first_frame, reader.last_frame) == (31, 40)


def test_write_exports_with_a_lost_frame_and_the_export_options(tmp_path):
    joints = _walk(6)
    frames = np.array([10, 12, 14, 18, 20])  # step 2, frame 16 lost
    params = ExportParams(bvh_units="m", bvh_names="mixamo", trc_names="halpe26")
    paths = write_exports(tmp_path / "export", frames, joints[[0, 1, 2, 4, 5]], fps=50.0, params=params)
    assert sorted(p.name for p in paths.values()) == ["angles.csv", "joints.c3d", "joints.csv", "joints.trc",
                                                      "motion.bvh"]
    angles = paths["angles.csv"].read_text().splitlines()
    assert angles[0] == "frame," + ",".join(ANGLE_NAMES) and len(angles) == 6

    bvh = bvhio.readAsBvh(str(paths["motion.bvh"]))
    assert bvh.FrameCount == 6 and bvh.FrameTime == pytest.approx(2 / 50)
    root = bvhio.readAsHierarchy(str(paths["motion.bvh"]))
    assert root.Name == "Hips"
    root.loadPose(3)  # the interpolated frame 16: halfway between frames 14 and 18
    np.testing.assert_allclose(np.array(root.PositionWorld), [0.0, 1.0, -(joints[3, 0, 1])], atol=1e-6)
    assert "\tLHip\t" in paths["joints.trc"].read_text().splitlines()[3]

    c3d_file = ezc3d.c3d(str(paths["joints.c3d"]))
    assert c3d_file["parameters"]["POINT"]["RATE"]["value"][0] == pytest.approx(25.0)
    assert list(c3d_file["parameters"]["POINT"]["LABELS"]["value"]) == list(JOINT_NAMES)
    assert c3d_file["parameters"]["POINT"]["UNITS"]["value"] == ["mm"]
    assert c3d_file["data"]["points"].shape == (4, 17, 6)


def test_filtering_smooths_every_export_alike_and_keeps_the_skeleton(tmp_path):
    rng = np.random.default_rng(5)
    joints = _tracked_like(60)
    noisy = joints + rng.normal(0.0, 0.004, joints.shape)  # 4 mm of jitter
    raw = tmp_path / "raw"
    smooth = tmp_path / "smooth"
    write_exports(raw, np.arange(60), noisy, fps=30.0)
    paths = write_exports(smooth, np.arange(60), noisy, fps=30.0, params=ExportParams(filter_cutoff_hz=4.0))
    _, names, unfiltered = read_joints_csv(raw / "joints.csv")
    _, _, filtered = read_joints_csv(paths["joints.csv"])

    def acceleration(x):
        return np.linalg.norm(x[2:] - 2 * x[1:-1] + x[:-2], axis=-1).mean()

    assert acceleration(filtered) < 0.3 * acceleration(unfiltered)
    bones = [(names.index(a), names.index(b)) for a, b in (("l_hip", "l_knee"), ("l_elbow", "l_wrist"))]
    for a, b in bones:  # rigid bones keep one length through the smoothing
        lengths = np.linalg.norm(filtered[:, b] - filtered[:, a], axis=1)
        assert np.ptp(lengths) < 1e-6  # joints.csv's 0.1 micrometre rounding
    bvh, _ = read_bvh_positions(paths["motion.bvh"], 60)
    for j, name in enumerate(names):
        assert np.abs(bvh[name] - filtered[:, j]).max() < 1e-4, name


def test_filter_cut_off_above_the_nyquist_rate_is_refused(tmp_path):
    with pytest.raises(InputError, match="filter_cutoff_hz"):
        write_exports(tmp_path, np.arange(0, 20, 2), _walk(10), fps=30.0, params=ExportParams(filter_cutoff_hz=8.0))
    assert not (tmp_path / "joints.csv").exists()


def test_the_run_command_refuses_a_cut_off_above_the_captures_nyquist_rate_before_any_work(tmp_path, capsys):
    capture, out = make_capture(tmp_path / "capture"), tmp_path / "out"
    assert main(["run", str(capture), "--out", str(out), "-q", "--set", "export.filter_cutoff_hz=12.5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == ("error: export.filter_cutoff_hz: expected a cut-off below half the frame rate "
                       "(12.5 Hz for 25 frames/s), got 12.5")
    assert not list(out.rglob(MANIFEST))


def test_quality_csv_is_written_beside_joints_csv(tmp_path):
    frames = np.arange(5)
    support = np.full((5, 17), 40.0)
    quality = FrameQuality(frames=frames, statuses=np.array(["initialised"] + ["tracked"] * 4),
                           doubtful=np.zeros(5, bool), observations=np.full(5, 900),
                           log_likelihood=np.full(5, 1800.0), outlier_fraction=np.full(5, 0.1), support=support,
                           fitted=np.ones(5, bool), corrected=np.array(["", "", "l_upperarm", "", "l_thigh/r_thigh"]))
    paths = write_exports(tmp_path, frames, _walk(5), fps=25.0, quality=quality)
    lines = paths["quality.csv"].read_text().splitlines()
    assert len(lines) == 6 and lines[1].startswith("0,initialised,0,900,2.0000,0.1000,,,1.0000")
    assert lines[0].split(",")[6:8] == ["unsupported", "corrected"]
    assert [line.split(",")[7] for line in lines[1:]] == ["", "", "l_upperarm", "", "l_thigh/r_thigh"]


def test_write_exports_refuses_an_empty_sequence(tmp_path):
    with pytest.raises(InputError, match="no frame was estimated"):
        write_exports(tmp_path, np.zeros(0, int), np.zeros((0, 17, 3)), fps=25.0)
