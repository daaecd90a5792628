import re
import shutil
import subprocess

import numpy as np
import pytest
from conftest import stick_figure

from calib.camera import Camera, Rig
from pipeline import frames_io
from pipeline.export_io import write_joints_csv
from pipeline.report import (
    JointSequence,
    build_report,
    overlay_stills,
    stage_timings,
    viewer_data,
    write_report,
)
from stages.joints import JOINT_NAMES

CHROMIUM_SECONDS = 60


def _walk(n_frames: int) -> np.ndarray:
    """(n_frames, 17, 3) a stick figure swinging its limbs while walking along +y (metres, +z up)."""
    base = stick_figure()
    t = np.arange(n_frames)[:, None]
    swing = np.sin(0.3 * t) * np.array([[1.0 if name.startswith("l_") else -1.0 for name in JOINT_NAMES]])
    motion = np.zeros((n_frames, 17, 3))
    motion[:, :, 1] = 0.02 * t + 0.1 * swing * (base[None, :, 2] < 0.9)
    return base[None] + motion


@pytest.fixture
def full_run(tmp_path):
    """A run with timings, exported joints (frame 4 lost), a truth 20 mm away and eval metrics absent."""
    capture, out = tmp_path / "capture", tmp_path / "run"
    truth = _walk(12)
    write_joints_csv(capture / "groundtruth" / "joints.csv", np.arange(12), truth)
    kept = np.array([f for f in range(12) if f != 4])
    write_joints_csv(out / "export" / "joints.csv", kept, truth[kept] + [0.02, 0.0, 0.0])
    frames_io.write_json(out / "calibration" / "capture.json",
                         {"fps": 25.0, "frames": list(range(12)), "capture_dir": str(capture)})
    frames_io.write_json(out / "calibration" / "manifest.json", {"timing": {"seconds": 0.5, "frames": None}})
    frames_io.write_json(out / "tracking" / "manifest.json",
                         {"timing": {"seconds": 2.4, "frames": 11, "workers": "2 processes"},
                          "finished_at": "2026-01-01T00:00:00+00:00"})
    frames_io.write_json(out / "silhouettes" / "manifest.json", {"stage": "silhouettes"})  # no timing
    return out


def _rig() -> Rig:
    return Rig((Camera.look_at("front", (0.0, -4.0, 1.0), (0.0, 0.0, 1.0), f_px=150, size=(160, 120)),
                Camera.look_at("side", (4.0, 0.0, 1.0), (0.0, 0.0, 1.0), f_px=150, size=(160, 120))))


def _render_dom(path, tmp_path) -> str:
    """The DOM of ``path`` after its scripts ran, from headless Chromium."""
    chromium = shutil.which("chromium")
    if chromium is None:
        pytest.fail("chromium not found: install the Debian package 'chromium' (apt-get install -y chromium) "
                    "to test that the report renders")
    command = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
               "--disable-component-update", "--disable-sync", "--no-first-run",
               f"--user-data-dir={tmp_path / 'chromium-profile'}", "--dump-dom", path.as_uri()]
    result = subprocess.run(command, capture_output=True, text=True, timeout=CHROMIUM_SECONDS, check=False)
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout


def test_full_report_renders_in_headless_chromium_without_js_errors(full_run, tmp_path):
    grey = np.full((120, 160, 3), 60, np.uint8)
    images = {"front": (2, grey), "side": (4, grey)}
    path = write_report(full_run, rig=_rig(), images=images)
    assert path == full_run / "export" / "report.html"
    text = path.read_text()
    for heading in ("Stage timings", "Motion", "Accuracy", "Joint trajectories", "Error over time", "Overlays",
                    "3-D skeleton"):
        assert f"<h2>{heading}" in text
    assert "MPJPE 20.0 mm" in text and "11 frames estimated of 12 capture frames" in text
    assert not re.search(r"(src|href)=['\"]?(https?:)?//", text)  # nothing fetched from the network
    assert len(re.findall(r"data:image/png;base64,", text)) == 4    # two plots, two stills
    dom = _render_dom(path, tmp_path)
    assert "rendered 12 frames" in dom
    assert re.search(r"<div id=\"js-errors\"></div>", dom), dom[:3000]


def test_report_of_a_run_without_export_has_graceful_sections(tmp_path):
    out = tmp_path / "run"
    frames_io.write_json(out / "calibration" / "manifest.json", {"timing": {"seconds": 0.25, "frames": 1}})
    text = build_report(out)
    assert "the export stage has not run" in text and "<h2>Stage timings" in text
    assert "<canvas" not in text and "Error over time" not in text


def test_report_without_truth_has_no_accuracy_but_a_viewer(full_run, tmp_path):
    (full_run / "calibration" / "capture.json").unlink()
    text = build_report(full_run)
    assert "Accuracy" not in text and "<canvas" in text and "Joint trajectories" in text


def test_stage_timings_tolerate_missing_keys_and_bad_manifests(full_run):
    (full_run / "reconstruction").mkdir()
    (full_run / "reconstruction" / "manifest.json").write_text("{not json")
    rows = stage_timings(full_run)
    assert [row["stage"] for row in rows] == ["calibration", "silhouettes", "tracking"]
    assert rows[1]["seconds"] is None and rows[2]["frames"] == 11


def test_overlay_stills_draw_estimate_and_truth():
    joints = _walk(3)
    estimate = JointSequence(np.arange(3), JOINT_NAMES, joints)
    truth = JointSequence(np.arange(3), JOINT_NAMES, joints + [0.1, 0.0, 0.0])
    blank = np.zeros((120, 160, 3), np.uint8)
    stills = overlay_stills({"front": (1, blank), "side": (7, blank)}, _rig(), estimate, truth)
    assert [(camera, frame) for camera, frame, _ in stills] == [("front", 1), ("side", 7)]
    front = stills[0][2]
    assert (front == 255).all(axis=2).any() and (front[:, :, 2] > 200).any()   # white truth, red right side
    assert not stills[1][2].any()  # frame 7 is in neither sequence


def test_viewer_data_aligns_frames_and_keeps_each_sequence_joints():
    joints = _walk(4)
    estimate = JointSequence(np.array([0, 1, 3]), JOINT_NAMES, joints[[0, 1, 3]])
    truth = JointSequence(np.array([1, 2, 3]), JOINT_NAMES[:15], joints[1:, :15])   # no toes
    data = viewer_data(estimate, truth, 30.0)
    assert data["frames"] == [0, 1, 2, 3] and data["fps"] == 30.0
    assert [pose is None for pose in data["estimate"]["poses"]] == [False, False, True, False]
    assert [pose is None for pose in data["truth"]["poses"]] == [True, False, False, False]
    assert len(data["truth"]["bones"]) == 14 and len(data["estimate"]["bones"]) == 16
    assert data["estimate"]["sides"][:4] == ["c", "c", "c", "l"]
