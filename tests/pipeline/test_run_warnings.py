import json
import logging
import shutil
import threading

from conftest import make_capture

from pipeline.cli import main
from pipeline.engine.executors import call_logged, relog
from pipeline.engine.run_warnings import collecting, read_warnings, stage_scope
from pipeline.io import frames_io
from pipeline.io.run_layout import WARNINGS_FILE

log = logging.getLogger("tests.run_warnings")


def messages(out, stage=...):
    return [w["message"] for w in read_warnings(out) if stage is ... or w["stage"] == stage]


def test_warnings_are_filed_under_the_stage_whose_thread_logged_them(tmp_path):
    with collecting() as warnings:
        log.warning("before the lock: %s", "capture")
        warnings.attach(tmp_path)
        with stage_scope("silhouettes"):
            log.warning("frame %d: empty", 3)
            log.info("not a warning")
            other = threading.Thread(target=lambda: log.warning("from elsewhere"))
            other.start()
            other.join()
    entries = json.loads((tmp_path / WARNINGS_FILE).read_text())["warnings"]
    assert [(entry["stage"], entry["message"]) for entry in entries] == [
        (None, "before the lock: capture"), ("silhouettes", "frame 3: empty"), (None, "from elsewhere")]
    assert entries[1]["template"] == "frame %d: empty" and entries[1]["logger"] == "tests.run_warnings"


def test_a_stage_that_runs_again_replaces_its_warnings_and_the_others_stay(tmp_path):
    for run, stages in enumerate((("silhouettes", "tracking"), ("tracking",))):
        with collecting() as warnings:
            warnings.attach(tmp_path)
            log.warning("run %d opened the capture", run)
            for stage in stages:
                with stage_scope(stage):
                    log.warning("%s in run %d", stage, run)
    assert messages(tmp_path) == ["silhouettes in run 0", "run 1 opened the capture", "tracking in run 1"]


def test_nothing_is_written_into_a_fresh_folder_before_a_stage_runs(tmp_path):
    with collecting() as warnings:
        warnings.attach(tmp_path)
        log.warning("refused at once")
    assert not (tmp_path / WARNINGS_FILE).exists()          # the run's lock then removes the folder it made


def test_read_warnings_sees_what_was_just_logged_and_tolerates_a_damaged_file(tmp_path):
    with collecting() as warnings:
        warnings.attach(tmp_path)
        with stage_scope("export"):
            for frame in range(50):  # faster than the file is rewritten
                log.warning("frame %d: lost", frame)
            assert len(messages(tmp_path, "export")) == 50
    (tmp_path / WARNINGS_FILE).write_text("{not json")
    assert read_warnings(tmp_path) == []


def test_a_workers_warnings_come_back_with_their_template(tmp_path):
    def task(chunk):
        logging.getLogger("pipeline.frame_tasks").warning("frame %d: only %d observations", chunk[0], 3)
        logging.getLogger("pipeline.frame_tasks").info("quiet")

    records = call_logged(task, (7,))
    assert [(r["name"], r["msg"], r["template"]) for r in records] == [
        ("pipeline.frame_tasks", "frame 7: only 3 observations", "frame %d: only %d observations")]
    json.dumps(records)  # plain data: it travels back from another process
    with collecting() as warnings:
        warnings.attach(tmp_path)
        with stage_scope("reconstruction"):
            relog(records)
    assert read_warnings(tmp_path)[0] == {"stage": "reconstruction", "logger": "pipeline.frame_tasks",
                                          "template": "frame %d: only %d observations",
                                          "message": "frame 7: only 3 observations"}


def test_a_run_with_worker_processes_lists_their_warnings_and_says_what_happened(tmp_path, capsys):
    """An empty frame in every camera: the reconstruction's workers warn; the closing lines count it."""
    capture = make_capture(tmp_path / "capture", backgrounds=True)
    for camera in ("cam0", "cam1", "cam2"):
        shutil.copy(capture / "background" / f"{camera}.png", capture / "images" / camera / "000002.png")
    out = tmp_path / "out"
    assert main(["run", str(capture), "--out", str(out), "-q", "--workers", "2"]) == 0
    printed = capsys.readouterr().out
    by_stage = {(w["stage"], w["message"]) for w in frames_io.read_json(out / WARNINGS_FILE)["warnings"]}
    assert ("reconstruction", "frame 2: empty silhouette in camera(s) cam0, cam1, cam2") in by_stage
    assert ("tracking", "frame 2: pose predicted, not exported (0 observations)") in by_stage
    assert "1 predicted (fewer than 30 observations)" in printed.splitlines()[-3]
    assert (f"in this run (above, a message repeated on consecutive frames once; every warning behind the results: "
            f"{out / WARNINGS_FILE} and the report)") in printed
    assert printed.splitlines()[-1] == f"report: {out / 'export' / 'report.html'}"
    report = (out / "export" / "report.html").read_text()
    assert "frame 2: empty silhouette in camera(s) cam0, cam1, cam2" in report
