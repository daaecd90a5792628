import json
import re
import shutil
import subprocess
from xml.etree import ElementTree

import numpy as np
import pytest
from conftest import stick_figure
from test_tracking_summary import record, write_records

from calib.camera import Camera, Rig
from pipeline.evaluate import evaluate_run, format_metrics
from pipeline.io import frames_io
from pipeline.io.export_io import write_angles_csv, write_joints_csv
from pipeline.io.overlay_video import write_overlay_video
from pipeline.io.run_layout import WARNINGS_FILE, overlay_video_name
from pipeline.report.figures import angle_groups, overlay_stills, viewer_data
from pipeline.report.page import build_report, warning_groups, write_report
from pipeline.report.run_data import JointSequence, read_angles_csv, stage_timings
from stages.joints import JOINT_NAMES

CHROMIUM_SECONDS = 60
FPS = 25.0
FRAMES = 12
LOST = 4


def _walk(n_frames: int) -> np.ndarray:
    """(n_frames, 17, 3) a stick figure swinging its limbs while walking along +y (metres, +z up)."""
    base = stick_figure()
    t = np.arange(n_frames)[:, None]
    swing = np.sin(0.3 * t) * np.array([[1.0 if name.startswith("l_") else -1.0 for name in JOINT_NAMES]])
    motion = np.zeros((n_frames, 17, 3))
    motion[:, :, 1] = 0.02 * t + 0.1 * swing * (base[None, :, 2] < 0.9)
    return base[None] + motion


def _rig() -> Rig:
    return Rig((Camera.look_at("front", (0.0, -4.0, 1.0), (0.0, 0.0, 1.0), f_px=150, size=(160, 120)),
                Camera.look_at("side", (4.0, 0.0, 1.0), (0.0, 0.0, 1.0), f_px=150, size=(160, 120))))


@pytest.fixture(scope="module")
def shared_run(tmp_path_factory):
    """A run as the pipeline leaves it: timings, tracking records (frame 4 lost, frame 7 doubtful), exported
    joints 20 mm off a truth, angles, silhouettes and backgrounds, warnings, and a stale eval/metrics.json.
    Shared by the tests that only read it; :func:`full_run` is a copy to change."""
    root = tmp_path_factory.mktemp("report")
    capture, out = root / "capture", root / "run"
    truth = _walk(FRAMES)
    write_joints_csv(capture / "groundtruth" / "joints.csv", np.arange(FRAMES), truth)
    kept = np.array([f for f in range(FRAMES) if f != LOST])
    write_joints_csv(out / "export" / "joints.csv", kept, truth[kept] + [0.02, 0.0, 0.0])
    write_angles_csv(out / "export" / "angles.csv", kept, truth[kept])
    frames_io.write_json(out / "calibration" / "capture.json",
                         {"fps": FPS, "frames": list(range(FRAMES)), "capture_dir": str(capture),
                          "cameras": ["front", "side"]})
    frames_io.write_json(out / "calibration" / "manifest.json", {"timing": {"seconds": 0.5, "frames": None}})
    write_records(out / "tracking", [record(0, "initialised")] + [
        record(f, "lost" if f == LOST else "initialised" if f == LOST + 1 else "tracked", doubtful=f == 7,
               outliers=0.7 if f == 7 else 0.05) for f in range(1, FRAMES)])
    frames_io.write_json(out / "tracking" / "manifest.json",
                         {"timing": {"seconds": 2.4, "frames": 11, "workers": "2 processes"},
                          "finished_at": "2026-01-01T00:00:00+00:00"})
    frames_io.write_json(out / "silhouettes" / "manifest.json", {"stage": "silhouettes"})  # no timing
    for camera in ("front", "side"):
        mask = np.zeros((120, 160), np.uint8)
        mask[30:90, 70:90] = 255
        frames_io.write_mask(out / "silhouettes" / camera / "000002.png", mask)
        background = np.full((120, 160, 3), 90, np.uint8)
        frames_io.write_image(out / "silhouettes" / "background" / f"{camera}.png", background)
    frames_io.write_json(out / WARNINGS_FILE, {"warnings": [
        {"stage": None, "logger": "pipeline.io.capture", "template": None, "message": "volume touched"},
        {"stage": "tracking", "logger": "pipeline.graph", "template": "frame %d: pose %s",
         "message": "frame 4: pose lost"},
        {"stage": "tracking", "logger": "pipeline.graph", "template": "frame %d: pose %s",
         "message": "frame 9: pose lost"}]})
    frames_io.write_json(out / "eval" / "metrics.json", {"mpjpe_mm": 1.5})  # an earlier run's, never shown
    return out


@pytest.fixture(scope="module")
def shared_text(shared_run):
    """The report of :func:`shared_run`."""
    return build_report(shared_run)


@pytest.fixture
def full_run(shared_run, tmp_path):
    """A copy of :func:`shared_run` (same truth) that a test may change."""
    copy = tmp_path / "run"
    shutil.copytree(shared_run, copy)
    return copy


def _images():
    grey = np.full((120, 160, 3), 60, np.uint8)
    return {"front": (2, grey), "side": (2, grey)}


def _chromium_dom(html_text: str, folder, name: str = "page.html") -> str:
    """The DOM of ``html_text`` (written in ``folder``, beside the files it links) after its scripts and media
    loaded, from headless Chromium; skipped when there is no Chromium."""
    chromium = shutil.which("chromium")
    if chromium is None:
        pytest.skip("chromium not found: the report's check in a browser needs the Debian package 'chromium' "
                    "(scripts/bootstrap.sh --test installs it)")
    path = folder / name
    path.write_text(html_text)
    command = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
               "--disable-component-update", "--disable-sync", "--no-first-run", "--mute-audio",
               f"--user-data-dir={folder / 'chromium-profile'}", "--dump-dom", path.as_uri()]
    result = subprocess.run(command, capture_output=True, text=True, timeout=CHROMIUM_SECONDS, check=False)
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout


def _probe(script: str, html_text: str) -> str:
    """``html_text`` with ``script`` run once the page has loaded, its result as JSON in <pre id='probe'>."""
    return html_text.replace("</body>", "<pre id='probe'></pre><script>window.addEventListener('load', function () {"
                                        "document.getElementById('probe').textContent = JSON.stringify("
                                        f"(function () {{ {script} }})()); }});</script></body>")


def _probed(dom: str):
    return json.loads(re.search(r"<pre id=\"probe\">(.*?)</pre>", dom, re.S).group(1).replace("&quot;", '"'))


def test_full_report_renders_in_chromium_without_js_errors_and_plays_its_videos(full_run, tmp_path):
    for camera in _rig():
        images = ((frame, np.full((120, 160, 3), 40 + 10 * frame, np.uint8)) for frame in range(FRAMES))
        write_overlay_video(images, camera, {}, full_run / "export" / overlay_video_name(camera.name), FPS)
    path = write_report(full_run, rig=_rig(), images=_images())
    assert path == full_run / "export" / "report.html"
    text = path.read_text()
    for heading in ("What happened", "Warnings (3)", "Accuracy", "3-D skeleton", "Tracking quality", "Joint angles",
                    "Joint trajectories", "Error over time", "Cameras", "Stage timings"):
        assert re.search(rf"<h2[^>]*>{re.escape(heading)}", text), heading
    assert not re.search(r"(src|href)=['\"]?(https?:)?//", text)  # nothing fetched from the network
    assert text.count("data:image/png;base64,") == 2 and text.count("<svg ") == 4   # two silhouettes, four plots
    assert text.count("data:image/jpeg;base64,") == 2 + 2            # two overlay stills, two backgrounds
    assert "<video controls muted loop preload='metadata' src='overlay_front.webm'>" in text
    probe = ("return {errors: document.getElementById('js-errors').textContent, "
             "status: document.getElementById('skeleton-status').textContent, "
             "videos: Array.from(document.querySelectorAll('video')).map(v => [v.readyState, v.videoWidth, "
             "v.error ? v.error.code : 0, Math.round(v.duration * 1000)]), "
             "plots: Array.from(document.querySelectorAll('svg.plot')).map(svg => {"
             "const box = svg.getBoundingClientRect(); return [Math.round(box.width), Math.round(box.height), "
             "svg.querySelectorAll('polyline').length]; })};")
    # A media element delays the page's load event until it has its metadata or has failed: at load, each
    # video knows its size and length, or why it cannot play (an mp4v MP4 fails here: error code 4).
    result = _probed(_chromium_dom(_probe(probe, text), full_run / "export", "probed.html"))
    assert result["errors"] == "" and result["status"] == f"rendered {FRAMES} frames"
    assert [video[1:] for video in result["videos"]] == [[160, 0, 1000 * FRAMES / FPS]] * 2, result["videos"]
    assert all(video[0] >= 1 for video in result["videos"])       # HAVE_METADATA or more
    assert len(result["plots"]) == 4 and all(width > 500 and 100 < height < width and lines
                                             for width, height, lines in result["plots"]), result["plots"]


def test_the_viewer_plays_at_the_capture_frame_rate_whatever_the_refresh_rate_and_orbits(shared_text, tmp_path):
    """Animation frames at 60 Hz and at 144 Hz for the same time show the same capture frame: number
    first + seconds * fps (the frames run 0..11 at 25 frames/s, so 0.48 s a loop)."""
    drive = ("const v = window.skeletonViewer; v.detach(); const out = {};"
             "for (const hz of [60, 144]) { for (const seconds of [0.25, 5 / 12, 0.5]) {"
             "  v.seek(0); v.play(); let t = 1000; v.tick(t);"
             "  for (let k = 0; k < Math.round(seconds * hz); k++) { t += 1000 / hz; v.tick(t); }"
             "  const s = v.state(); out[hz + '@' + seconds] = [s.frame, Math.round(s.clock * 1e6) / 1e6];"
             "} }"
             "v.pause(); v.seek(0.17); out.label = document.getElementById('skeleton-label').textContent;"
             "out.slider = document.getElementById('skeleton-frame').value;"
             "const c = document.getElementById('skeleton-canvas'), home = v.state().view;"
             "c.dispatchEvent(new WheelEvent('wheel', {deltaY: -200, cancelable: true}));"
             "c.dispatchEvent(new PointerEvent('pointerdown', {clientX: 10, clientY: 10, bubbles: true}));"
             "window.dispatchEvent(new PointerEvent('pointermove', {clientX: 60, clientY: 30}));"
             "window.dispatchEvent(new PointerEvent('pointerup', {}));"
             "window.dispatchEvent(new PointerEvent('pointermove', {clientX: 300, clientY: 300}));"
             "out.turned = [home, v.state().view];"
             "c.dispatchEvent(new MouseEvent('dblclick', {})); out.reset = v.state().view; return out;")
    result = _probed(_chromium_dom(_probe(drive, shared_text), tmp_path))
    for hz in (60, 144):  # whole numbers of animation frames at both rates
        assert result[f"{hz}@0.25"] == [6, 0.25]                          # 0.25 s * 25 frames/s
        assert result[f"{hz}@0.4166666666666667"] == [10, 0.416667]
        assert result[f"{hz}@0.5"] == [0, 0.02]                           # looped after 0.48 s
    assert result["label"] == "frame 4 (0.16 s), not estimated" and result["slider"] == "4"
    home, turned = result["turned"]  # a wheel turn zooms in, a drag of (50, 20) px orbits; released, it stops
    assert turned["zoom"] == pytest.approx(home["zoom"] * np.exp(0.3))
    assert turned["azimuth"] == pytest.approx(home["azimuth"] + 0.5)
    assert turned["elevation"] == pytest.approx(home["elevation"] + 0.2)
    assert result["reset"] == home


def test_the_accuracy_is_this_runs_as_eval_scores_it_never_a_stale_file(full_run):
    text = build_report(full_run)
    assert "MPJPE 1.5" not in text
    summary = evaluate_run(full_run)  # overwrites the stale metrics.json
    expected = format_metrics({**summary, "silhouette_iou": None})
    assert expected.splitlines()[0].startswith("MPJPE 20.0 mm over 15 joints and 11 frames")
    assert expected.replace("'", "&#x27;") in text
    assert "MPJPE 20.0 mm against the truth" in text


def test_what_happened_counts_the_trackers_categories_with_their_causes(shared_text):
    text = shared_text
    rows = re.findall(r"<tr><td><span class='swatch (\w+)'></span>\w+</td><td>(\d+)</td><td>([^<]*)</td></tr>", text)
    assert rows == [("tracked", "8", "-"),
                    ("initialised", "2", "first frame (1); data back after frames without a fit (1)"),
                    ("doubtful", "1", "outlier share above 60 % (1)"), ("predicted", "0", "-"),
                    ("lost", "1", "fewer than 30 observations for more than 10 frames (1)")]
    assert f"11 frames estimated of {FRAMES} capture frames" in text
    assert "Body sized for a subject 1.700 m tall (as the data measure it)." in text
    data = json.loads(re.search(r"id='skeleton-data'>(.*?)</script>", text).group(1))
    assert data["categories"][LOST] == "lost" and data["categories"][7] == "doubtful"


def test_warnings_are_listed_by_stage_with_repeats_folded(shared_text):
    text = shared_text
    assert "<li><b>run</b>: volume touched</li>" in text
    assert "<li><b>tracking</b>: frames 4, 9 (2 frames): pose lost</li>" in text
    assert warning_groups([{"stage": "a", "template": "x %d", "message": "x 1"},
                           {"stage": "b", "template": "x %d", "message": "x 2"},
                           {"stage": "a", "template": "x %d", "message": "x 3"}]) == [("a", ["x 1", "x 3"]),
                                                                                      ("b", ["x 2"])]


def test_without_truth_nothing_speaks_of_a_truth(full_run):
    (full_run / "calibration" / "capture.json").unlink()
    text = build_report(full_run, rig=_rig(), images=_images())
    assert "<h2>Accuracy" not in text and "Error over time" not in text and "<canvas" in text
    assert not re.search(r"truth (in|dashed)", text) and "Estimate in colour" in text


def test_a_run_without_export_or_without_any_estimated_frame_says_so(tmp_path, full_run):
    out = tmp_path / "bare"
    frames_io.write_json(out / "calibration" / "manifest.json", {"timing": {"seconds": 0.25, "frames": 1}})
    text = build_report(out)
    assert "the export stage has not run" in text and "<h2>Stage timings" in text
    assert "<canvas" not in text and "Error over time" not in text and "the tracking stage has not finished" in text
    (full_run / "export" / "joints.csv").write_text("frame,joint,x,y,z\n")
    text = build_report(full_run)
    assert "No motion: " in text and "no data rows" in text and "<canvas" not in text


def test_joint_angles_are_plotted_by_joint_and_a_broken_table_is_named(full_run):
    angles = read_angles_csv(full_run / "export" / "angles.csv")
    assert len(angles.frames) == FRAMES - 1 and "l_knee_flexion" in angles.names
    groups = angle_groups(angles.names)
    assert groups["knee_flexion"] == ["l_knee_flexion", "r_knee_flexion"]
    assert groups["trunk_inclination"] == ["trunk_inclination"]
    (full_run / "export" / "angles.csv").write_text("frame,l_knee_flexion\n0,12.5\n1,oops\n")
    text = build_report(full_run)
    assert "Joint angles</h2><p class='note'>Not shown: " in text and "angles.csv:3: not a row of numbers" in text


def test_stage_timings_tolerate_missing_keys_and_bad_manifests(full_run):
    (full_run / "reconstruction").mkdir()
    (full_run / "reconstruction" / "manifest.json").write_text("{not json")
    (full_run / "export").mkdir(exist_ok=True)
    (full_run / "export" / "manifest.json").write_text("[1, 2]")  # JSON, not a manifest
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
    assert data["frames"] == [0, 1, 2, 3] and data["fps"] == 30.0 and data["categories"] == [None] * 4
    assert [pose is None for pose in data["estimate"]["poses"]] == [False, False, True, False]
    assert [pose is None for pose in data["truth"]["poses"]] == [True, False, False, False]
    assert len(data["truth"]["bones"]) == 14 and len(data["estimate"]["bones"]) == 16
    assert data["estimate"]["sides"][:4] == ["c", "c", "c", "l"]


def test_every_plot_is_well_formed_svg_and_no_png_figure_is_left(shared_text):
    plots = re.findall(r"<svg .*?</svg>", shared_text, re.S)
    assert len(plots) == 4                     # quality, angles, trajectories, error
    for plot in plots:
        ElementTree.fromstring(plot)
    assert "data:image/png" not in shared_text.split("<h2>Cameras")[0]   # PNGs are only the silhouettes below
    assert "failure check" in plots[0] and "knee flexion" in plots[1] and "l_wrist (truth)" in plots[2]


def test_a_part_of_a_view_found_hidden_behind_something_is_shown_in_its_camera_section(full_run):
    assert "hidden behind something" not in build_report(full_run, rig=_rig(), images=_images())
    part = np.zeros((120, 160), np.uint8)
    part[80:] = 255
    frames_io.write_mask(full_run / "reconstruction" / "hidden" / "side.png", part)
    text = build_report(full_run, rig=_rig(), images=_images())
    side = text[text.index("<h3>side</h3>"):]
    assert "Part of its view is <strong>hidden behind something</strong>" in side
    assert "alt='side hidden behind something, not carved'" in side
    assert "hidden behind something" not in text[text.index("<h3>front</h3>"):text.index("<h3>side</h3>")]


def test_a_part_of_a_view_changed_since_its_plate_is_shown_in_its_camera_section(full_run):
    assert "changed since its clean plate" not in build_report(full_run, rig=_rig(), images=_images())
    part = np.zeros((120, 160), np.uint8)
    part[70:100, 10:40] = 255
    frames_io.write_mask(full_run / "silhouettes" / "room_changes" / "front.png", part)
    text = build_report(full_run, rig=_rig(), images=_images())
    front = text[text.index("<h3>front</h3>"):text.index("<h3>side</h3>")]
    assert "Part of its view <strong>changed since its clean plate</strong>" in front
    assert "alt='front changed since the plate, not carved'" in front
    assert "changed since its clean plate" not in text[text.index("<h3>side</h3>"):]


def test_the_floor_tests_shifts_are_noted_in_the_cameras_they_concern(full_run):
    assert "Floor test of shadows" not in build_report(full_run, rig=_rig(), images=_images())
    frames_io.write_json(full_run / "silhouettes" / "floor_shifts.json", {
        "method": "shadows' darkening compared between the views", "frames": [0, 1, 2, 3],
        "shifts_px": {"front": {"side": [6, 8]}, "side": {"front": [0, 0]}}})
    text = build_report(full_run, rig=_rig(), images=_images())
    front = text[text.index("<h3>front</h3>"):text.index("<h3>side</h3>")]
    assert "Floor test of shadows: the other views see its floor points off where the calibration puts them, by " \
           "side 10 pixels" in front
    assert "Floor test of shadows" not in text[text.index("<h3>side</h3>"):]
