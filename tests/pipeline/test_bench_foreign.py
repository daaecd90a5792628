"""Foreign suite helpers on small synthetic folders: finding captures, the skip line, statuses, IoU (no run)."""

import numpy as np
import pytest

from pipeline.evaluate import evaluate_run
from pipeline.io import frames_io
from pipeline.io.export_io import write_joints_csv
from pipeline.io.run_layout import tracking_path
from pipeline.lab.bench import foreign, robustness, suite


def _result(status: str, doubtful: bool = False) -> dict:
    return {"status": status, "doubtful": doubtful}


def test_status_counts_every_status_and_doubtful_frames_beside_them():
    results = [_result("initialised", doubtful=True), _result("tracked"), _result("tracked", doubtful=True),
               _result("predicted"), _result("lost"), _result("initialised")]
    assert foreign.status_counts(results) == {"tracked": 2, "initialised": 2, "predicted": 1, "lost": 1,
                                              "doubtful": 2}
    assert foreign.status_counts([_result("tracked")])["initialised"] == 0  # absent statuses are counted as 0


def test_only_initialisations_after_the_first_frame_count_as_re_initialised():
    assert foreign.reinitialised_after_first([_result("initialised")] + [_result("tracked")] * 19) == 0.0
    results = [_result("initialised"), _result("tracked"), _result("lost"), _result("initialised")]
    assert foreign.reinitialised_after_first(results) == 0.25


def test_tracking_rows_read_the_stage_records_in_frame_order(tmp_path):
    for frame, status in ((3, "initialised"), (4, "tracked"), (5, "initialised")):
        frames_io.write_json(tracking_path(tmp_path / "tracking", frame),
                             {"frame": frame, "result": _result(status, doubtful=frame == 5), "state": {}})
    row = foreign.tracking_row(tmp_path, [3, 4, 5], tracker_ms=12.5)
    assert row == {"tracker_ms_per_frame": 12.5, "reinitialised_fraction": pytest.approx(1 / 3),
                   "statuses": {"tracked": 1, "initialised": 2, "predicted": 0, "lost": 0, "doubtful": 1}}


def test_captures_are_the_subfolders_with_a_capture_yaml(tmp_path):
    for name in ("walk", "frontkick", "notes"):
        (tmp_path / name).mkdir()
    for name in ("walk", "frontkick"):
        (tmp_path / name / "capture.yaml").write_text("fps: 30\n")
    assert foreign.find_captures(tmp_path) == [tmp_path / "frontkick", tmp_path / "walk"]
    with pytest.raises(suite.SuiteSkipped, match="holds no capture"):
        foreign.find_captures(tmp_path / "notes")


@pytest.mark.parametrize(("name", "module"), [("foreign", foreign), ("robustness", robustness)])
def test_absent_folder_skips_the_suite_with_one_line_and_keeps_the_results(tmp_path, monkeypatch, name, module):
    monkeypatch.setattr(module, "FOREIGN_ROOT", tmp_path / "shared" / "foreign")
    options = suite.BenchOptions(out=tmp_path / "bench", captures=tmp_path / "captures", quick=False, workers=1)
    lines = []
    assert suite.run_bench([name], options, log=lines.append) == {}
    assert lines[1:] == [f"bench: {name} suite skipped: no folder {tmp_path / 'shared' / 'foreign'} "
                         "(expected one capture folder with a capture.yaml per subfolder)"]
    assert not (tmp_path / "bench" / suite.RESULTS_JSON).exists()


@pytest.mark.parametrize("quick", [False, True])
def test_a_full_bench_warms_the_tracker_up_before_measuring(tmp_path, monkeypatch, quick):
    # A never set-up checkout compiled the tracker in its first timed run: that capture's fps was the compiler's.
    calls = []
    monkeypatch.setattr(suite, "ensure_compiled", lambda: calls.append("warm-up") or 1)
    monkeypatch.setattr(foreign, "FOREIGN_ROOT", tmp_path / "absent")
    options = suite.BenchOptions(out=tmp_path / "bench", captures=tmp_path / "captures", quick=quick, workers=1)
    lines = []
    suite.run_bench(["foreign"], options, log=lines.append)
    assert calls == ([] if quick else ["warm-up"])
    no_cache = "bench: the tracker's compiled code has no disk cache here: every run's figures include compiling it"
    assert (no_cache in lines) is not quick


SQUARE = np.zeros((20, 30), np.uint8)
SQUARE[5:15, 10:20] = 255


def _evaluated_run(root, estimates: tuple[np.ndarray, ...] = ()) -> dict:
    """A run whose joints are the truth and whose camera ``cam_a`` has ``estimates`` as silhouettes of a
    true mask (a 10 x 10 square), evaluated against ``<capture>/groundtruth/``."""
    capture, out = root / "capture", root / "out"
    truth = np.random.default_rng(0).uniform([-0.3, -0.3, 0.0], [0.3, 0.3, 1.8], (3, 17, 3))
    write_joints_csv(capture / "groundtruth" / "joints.csv", np.arange(3), truth)
    write_joints_csv(out / "export" / "joints.csv", np.arange(3), truth)
    for frame, estimate in enumerate(estimates):
        frames_io.write_mask(capture / "groundtruth" / "masks" / "cam_a" / f"{frame:06d}.png", SQUARE)
        frames_io.write_mask(out / "silhouettes" / "cam_a" / f"{frame:06d}.png", estimate)
    return evaluate_run(out, truth=capture / "groundtruth" / "joints.csv")


def test_silhouettes_are_scored_against_the_groundtruth_masks_by_their_median(tmp_path):
    # IoU 1, 1/3 (half overlap: 50 / 150) and 0 (no overlap): the median is the middle one, the mean lower.
    metrics = _evaluated_run(tmp_path, (SQUARE, np.roll(SQUARE, 5, axis=1), np.roll(SQUARE, 10, axis=1)))
    scores = foreign.foreign_scores(metrics)
    assert scores["silhouette_iou_median"] == pytest.approx(1 / 3)
    assert scores["silhouette_iou"] == pytest.approx(4 / 9) and scores["mpjpe_mm"] == 0.0


def test_without_true_masks_the_median_is_unknown_not_zero(tmp_path):
    assert foreign.foreign_scores(_evaluated_run(tmp_path))["silhouette_iou_median"] is None


def test_tracker_time_is_a_multiple_of_the_references():
    assert foreign.with_reference({"tracker_ms_per_frame": 30.0}, 20.0)["tracker_vs_reference"] == 1.5
    assert foreign.with_reference({"capture": "broken"}, 20.0)["tracker_vs_reference"] is None
    assert foreign.with_reference({"tracker_ms_per_frame": 30.0}, None)["tracker_vs_reference"] is None


def test_tracker_passes_take_the_runs_in_turn_and_keep_each_ones_fastest(monkeypatch, tmp_path):
    calls = []
    speeds = {"a": iter([50.0, 100.0, 80.0]), "b": iter([20.0, 25.0, 10.0])}  # frames/s of CPU, pass by pass

    def fake_speed(run_dir, capture, frames):
        calls.append(run_dir.name)
        return {"fps_all_cpu": next(speeds[run_dir.name])}

    monkeypatch.setattr(foreign, "tracker_speed", fake_speed)
    timings = [foreign.TrackerTiming(tmp_path / name, None, (0, 1)) for name in ("a", "b")]
    assert foreign.tracker_ms(timings) == [pytest.approx(10.0), pytest.approx(40.0)]
    assert calls == ["a", "b"] * foreign.TRACKER_PASSES


def test_rows_without_a_timing_keep_their_error_and_get_no_tracker_time(monkeypatch, tmp_path):
    monkeypatch.setattr(foreign, "tracker_ms", lambda timings: [12.0] * len(timings))
    monkeypatch.setattr(foreign, "tracking_row", lambda run_dir, frames, ms: {"tracker_ms_per_frame": ms})
    rows = foreign.with_tracking([{"capture": "ok"}, {"capture": "broken", "error": "boom"}],
                                 [foreign.TrackerTiming(tmp_path, None, (0,)), None])
    assert rows == [{"capture": "ok", "tracker_ms_per_frame": 12.0}, {"capture": "broken", "error": "boom"}]


def test_without_true_masks_there_is_no_second_look_with_them(tmp_path):
    _evaluated_run(tmp_path)  # a run with no silhouettes, a capture with no masks
    (tmp_path / "out" / "silhouettes" / "cam_a").mkdir(parents=True)
    row = foreign.true_masks_row(tmp_path / "capture", tmp_path / "out", tmp_path / "copy", workers=1)
    assert row == {"mpjpe_true_masks_mm": None, "worst_true_masks_mm": None} and not (tmp_path / "copy").exists()
