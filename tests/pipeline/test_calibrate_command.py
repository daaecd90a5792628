"""``python -m pipeline calibrate`` on a small rendered board recording: outputs, accuracy, and its one-line errors."""

import json
import shutil

import cv2
import numpy as np
import pytest

from calib.board import parse_board
from calib.camera import Camera, Rig
from calib.formats import load_rig
from pipeline.cli import main
from pipeline.commands.calibrate import update_capture_yaml
from pipeline.lab.synth.boards import write_board_recording

BOARD = "checkerboard:6x5:0.1"


@pytest.fixture(scope="module")
def boards(tmp_path_factory):
    """Three 400x300 cameras on a 2.6 m ring, 2.4 m up; a rendered recording: 5 intrinsic views each, 8 shared
    poses, the board on the floor at the world's origin."""
    cameras = []
    for k in range(3):
        angle = 2 * np.pi / 3 * k + 0.3
        cameras.append(Camera.look_at(f"cam{k + 1}", [2.6 * np.cos(angle), 2.6 * np.sin(angle), 2.4], [0, 0, 0.6],
                                      f_px=400 + 20 * k, size=(400, 300), dist=[-0.08 + 0.04 * k, 0, 0, 0, 0]))
    rig = Rig(tuple(cameras))
    out = tmp_path_factory.mktemp("boards") / "recording"
    write_board_recording(rig, parse_board(BOARD), out, intrinsic_views=5, extrinsic_views=8, seed=1)
    return out, rig


def calibrate(capsys, *arguments) -> tuple[int, str, str]:
    status = main(["calibrate", *map(str, arguments)])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


@pytest.fixture(scope="module")
def calibrated(boards, tmp_path_factory):
    """The command run once on the whole recording, with the floor, into a capture that has a capture.yaml."""
    capture = tmp_path_factory.mktemp("capture")
    (capture / "capture.yaml").write_text("fps: 25  # the media's\nsubject: {height_m: 1.7}\n")
    status = main(["calibrate", str(boards[0]), "--board", BOARD, "--floor", "floor", "--out", str(capture), "-q"])
    return status, capture


def test_rig_calibrated_from_the_recording(boards, calibrated):
    _, truth = boards
    status, capture = calibrated
    assert status == 0
    rig = load_rig("anipose", capture / "calibration" / "calibration.toml")
    assert rig.names == truth.names
    for got, want in zip(rig, truth, strict=True):  # the floor board lies at the world's origin, along its axes
        assert got.K[0, 0] == pytest.approx(want.K[0, 0], rel=0.01)
        np.testing.assert_allclose(got.centre, want.centre, atol=0.03)
        assert np.degrees(np.linalg.norm(cv2.Rodrigues(got.R @ want.R.T)[0])) < 0.5
    report = json.loads((capture / "calibration" / "report.json").read_text())
    assert set(report["cameras"]["cam1"]) >= {"K", "dist", "size", "views", "rms_px"}
    assert report["cameras"]["cam1"]["size"] == [400, 300] and report["cameras"]["cam1"]["views"] == 5
    assert report["rig"]["rms_px"] < 0.5 and report["rig"]["floor"] == ["floor"]
    text = (capture / "capture.yaml").read_text()
    assert text.startswith("fps: 25  # the media's\n") and "subject: {height_m: 1.7}" in text
    assert "  format: anipose\n  path: calibration/calibration.toml\n  units: m\n  up: +z" in text


def test_a_second_run_without_a_floor_replaces_the_first(boards, calibrated, tmp_path, capsys):
    recording, _ = boards
    capture = tmp_path / "capture"
    shutil.copytree(calibrated[1], capture)
    fewer = tmp_path / "fewer"  # views 004-007 and the floor left out
    shutil.copytree(recording, fewer, ignore=lambda folder, names: [n for n in names if n[:3] in ("004", "005", "006",
                                                                                                   "007", "flo")])
    status, out, _ = calibrate(capsys, fewer, "--board", BOARD, "--out", capture)
    assert status == 0 and "world = the first camera's frame, up: auto" in out
    rig = load_rig("anipose", capture / "calibration")
    np.testing.assert_allclose(rig[0].R, np.eye(3), atol=1e-9)
    assert "up: auto" in (capture / "capture.yaml").read_text()


def test_intrinsics_alone_are_calibrated_and_the_extrinsics_asked_for(boards, tmp_path, capsys):
    recording, truth = boards
    shutil.copytree(recording / "intrinsics", tmp_path / "only" / "intrinsics")
    status, out, _ = calibrate(capsys, tmp_path / "only", "--board", BOARD, "--out", tmp_path / "capture")
    assert status == 0 and "need extrinsics/<camera>/" in out
    assert not (tmp_path / "capture" / "calibration" / "calibration.toml").exists()
    report = json.loads((tmp_path / "capture" / "calibration" / "report.json").read_text())
    assert "rig" not in report
    assert report["cameras"]["cam3"]["K"][0][0] == pytest.approx(truth["cam3"].K[0, 0], rel=0.01)


def test_a_board_never_found_is_named(boards, tmp_path, capsys):
    recording, _ = boards
    status, _, err = calibrate(capsys, recording, "--board", "checkerboard:9x6:0.08", "--out", tmp_path)
    assert status == 2
    assert "intrinsics/cam1" in err and "was found in none of the 5 views of camera 'cam1'" in err


def test_a_camera_that_shares_no_view_is_named(boards, tmp_path, capsys):
    recording, _ = boards
    copy = tmp_path / "boards"
    shutil.copytree(recording, copy, ignore=lambda folder, names: [n for n in names if n[:3] in ("004", "005", "006")])
    for image in (copy / "extrinsics" / "cam3").glob("0*.png"):  # cam3 keeps only the floor view, the others lose it
        image.unlink()
    for camera in ("cam1", "cam2"):
        (copy / "extrinsics" / camera / "floor.png").unlink()
    status, _, err = calibrate(capsys, copy, "--board", BOARD, "--out", tmp_path / "capture")
    assert status == 2 and "camera 'cam3' shares no board view with the other cameras" in err


def test_a_symmetric_checkerboard_is_refused_for_extrinsics(boards, tmp_path, capsys):
    recording, _ = boards
    status, _, err = calibrate(capsys, recording, "--board", "checkerboard:6x6:0.08", "--out", tmp_path)
    assert status == 2 and "look the same turned by 180 degrees" in err


def test_a_calibration_written_by_someone_else_is_kept(boards, tmp_path, capsys):
    recording, _ = boards
    theirs = tmp_path / "calibration" / "calibration.toml"
    theirs.parent.mkdir()
    theirs.write_text("[cam_0]\n")
    status, _, err = calibrate(capsys, recording, "--board", BOARD, "--out", tmp_path)
    assert status == 2 and "was not written by `python -m pipeline calibrate`" in err
    assert theirs.read_text() == "[cam_0]\n"


def test_an_unknown_floor_view_is_named(boards, tmp_path, capsys):
    recording, _ = boards
    status, _, err = calibrate(capsys, recording, "--board", BOARD, "--floor", "ground", "--out", tmp_path)
    assert status == 2 and "view 'ground' is not one of the extrinsics views" in err


def test_capture_yaml_keeps_everything_but_its_calibration_block(tmp_path):
    path = tmp_path / "capture.yaml"
    path.write_text("fps: 28\n# our studio\ncalibration:\n  format: colmap  # old\n  path: calibration/colmap\n\n"
                    "volume: {min: [-2, -2, 0], max: [2, 2, 2.3]}\n")
    block = {"format": "anipose", "path": "calibration/calibration.toml", "units": "m", "up": "+z"}
    assert update_capture_yaml(path, block) == (
        "fps: 28\n# our studio\ncalibration:\n  format: anipose\n  path: calibration/calibration.toml\n  units: m\n"
        "  up: +z\n\nvolume: {min: [-2, -2, 0], max: [2, 2, 2.3]}\n")
    path.write_text("fps: 28\n")
    assert update_capture_yaml(path, block).startswith("fps: 28\ncalibration:\n  format: anipose\n")
