"""`python -m pipeline batch`: finding the captures of a study, a broken one among them, a rerun, and results the
same as `run`'s."""

from __future__ import annotations

import contextlib
import csv
import io
import logging
import os
import pickle
import shutil
import sys
from pathlib import Path

import cv2
import pytest
from conftest import frame_image, make_capture

from calib.errors import InputError
from pipeline.cli import main
from pipeline.commands.batch import BATCH_CSV, SOME_FAILED, find_captures, largest_first, make_jobs
from pipeline.commands.batch_workers import CaptureJob, CaptureReport, RenewedProcessPool, run_jobs
from pipeline.commands.run import read_params, stage_params
from pipeline.engine.cache import read_manifest
from pipeline.engine.executors import Workers
from pipeline.engine.params import read_overrides
from pipeline.graph import STAGES
from pipeline.io.capture import Capture
from pipeline.lab.bench.batch import BROKEN as BENCH_BROKEN
from pipeline.lab.bench.batch import BROKEN_IMAGE as BENCH_BROKEN_IMAGE
from pipeline.lab.bench.batch import broken_reported, excerpt_view

REPO = Path(__file__).resolve().parents[2]
TINY = REPO / "data_samples" / "tiny"
#: The export's report says when and how fast the run went: it is the one file of two runs that differs.
REPORT = "report.html"
#: The frame the broken capture's first camera cannot read.
BROKEN_IMAGE = Path("images") / "cam0" / "000002.png"


def touch_capture(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "capture.yaml").write_text("fps: 25\n")
    return folder


def test_find_captures_at_any_depth_but_not_inside_a_capture_a_hidden_folder_or_the_output(tmp_path):
    root = tmp_path / "study"
    expected = [touch_capture(root / "calibration-check"), touch_capture(root / "s1" / "p01" / "t1"),
                touch_capture(root / "s1" / "p01" / "t2"), touch_capture(root / "s1" / "p02" / "t1"),
                touch_capture(root / "s2" / "p01" / "t10")]
    touch_capture(root / "s1" / "p01" / "t1" / "videos" / "nested")  # inside a capture: its own folder
    touch_capture(root / ".trash" / "t1")
    touch_capture(root / "runs" / "s1" / "t1")  # the batch's output under the root
    (root / "s2" / "empty").mkdir()
    (root / "s2" / "loop").symlink_to(root / "s2")  # a link cycle ends

    assert find_captures(root, skip=root / "runs") == expected
    assert len(find_captures(root)) == len(expected) + 1  # without skip, the output's folders are searched


def test_find_captures_refuses_what_is_not_a_folder_of_captures(tmp_path):
    with pytest.raises(InputError, match="not a folder"):
        find_captures(tmp_path / "missing")
    with pytest.raises(InputError, match="no capture found"):
        find_captures(tmp_path)
    with pytest.raises(InputError, match="is itself a capture"):
        find_captures(touch_capture(tmp_path / "one"))


def test_an_output_folder_overlapping_a_capture_is_refused_before_any_run(tmp_path):
    root = tmp_path / "study"
    capture = touch_capture(root / "s1" / "t1")
    with pytest.raises(InputError, match="is the folder of captures"):
        make_jobs(root, [capture], root, (), allow_outside_paths=False, worker_log_level=None)
    with pytest.raises(InputError, match="overlaps the capture"):
        make_jobs(root, [capture], capture / "out", (), allow_outside_paths=False, worker_log_level=None)
    job, = make_jobs(root, [capture], root / "out", (), allow_outside_paths=False, worker_log_level=None)
    assert (job.name, job.out) == ("s1/t1", (root / "out" / "s1" / "t1").absolute())


def run_batch(*argv) -> tuple[int, str, list[dict]]:
    """Exit status, stdout and batch.csv's rows of ``python -m pipeline batch ARGV`` run in this process."""
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        status = main(["batch", *map(str, argv), "-q"])
    out = Path(argv[argv.index("--out") + 1])
    with open(out / BATCH_CSV, newline="") as table:
        return status, stdout.getvalue(), list(csv.DictReader(table))


@pytest.fixture(scope="module")
def study(tmp_path_factory) -> Path:
    """data_samples/tiny, a tiny disc capture, and a disc capture with an unreadable image, nested; the output
    under the root."""
    root = tmp_path_factory.mktemp("batch") / "study"
    shutil.copytree(TINY, root / "s1" / "p01" / "tiny")
    make_capture(root / "s1" / "p02" / "disc")
    broken = make_capture(root / "s2" / "p01" / "broken")
    (broken / BROKEN_IMAGE).write_bytes(b"\x89PNG\r\n")
    return root


@pytest.fixture(scope="module")
def first_batch(study) -> tuple[int, str, list[dict]]:
    """The study's first batch, two captures at a time in worker processes."""
    return run_batch(study, "--out", study / "out", "--scheduler", "local:2")


def test_a_broken_capture_is_reported_in_one_line_while_the_others_finish(first_batch, study):
    status, stdout, rows = first_batch
    assert status == SOME_FAILED
    by_name = {row["capture"]: row for row in rows}
    assert list(by_name) == ["s1/p01/tiny", "s1/p02/disc", "s2/p01/broken"]
    assert [by_name[name]["status"] for name in by_name] == ["ran", "ran", "failed"]
    error = by_name["s2/p01/broken"]["error"]
    assert "\n" not in error and error.startswith(str((study / "s2" / "p01" / "broken" / BROKEN_IMAGE).absolute()))
    assert "not a readable image" in error
    tiny = by_name["s1/p01/tiny"]
    assert tiny["frames"] == tiny["estimated"] == "8" and 0 < float(tiny["mpjpe_mm"]) < 100
    assert by_name["s1/p02/disc"]["mpjpe_mm"] == ""  # no ground truth, no score
    table = stdout.splitlines()
    assert table[0].split() == ["capture", "status", "frames", "estimated", "MPJPE", "mm", "seconds", "error"]
    assert table[3].startswith("s2/p01/broken") and table[3].endswith(error)


def stage_files(out: Path, stage: str) -> dict[str, str]:
    """The content hash of each file a stage wrote, but the report's."""
    return {name: digest for name, digest in read_manifest(out / stage)["outputs"]["contents"].items()
            if name != REPORT}


def test_a_capture_of_a_batch_gives_what_run_gives(first_batch, study, tmp_path):
    alone = tmp_path / "alone"
    assert main(["run", str(study / "s1" / "p01" / "tiny"), "--out", str(alone), "-q"]) == 0
    batched = study / "out" / "s1" / "p01" / "tiny"
    for stage in STAGES:
        assert stage_files(batched, stage.name) == stage_files(alone, stage.name) != {}


def test_a_rerun_skips_what_is_up_to_date_and_retries_what_failed(first_batch, study):
    broken = study / "s2" / "p01" / "broken"
    cv2.imwrite(str(broken / BROKEN_IMAGE), frame_image(2))
    status, stdout, rows = run_batch(study, "--out", study / "out")
    assert status == 0
    assert [row["status"] for row in rows] == ["up to date", "up to date", "ran"]
    assert rows[2]["error"] == "" and rows[2]["estimated"] == rows[2]["frames"] == "4"
    assert rows[0]["mpjpe_mm"] == first_batch[2][0]["mpjpe_mm"]
    assert stdout.splitlines()[-1] == f"written: {study / 'out' / BATCH_CSV}"


def test_a_mistake_in_the_parameters_is_refused_by_the_pool_before_any_run(study, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["batch", str(study), "--out", str(out), "--scheduler", "local:2", "--set", "tracking.no_such=1", "-q"]
    assert main(argv) == 2
    assert capsys.readouterr().err.startswith("error: --set tracking.no_such: unknown parameter")
    assert not out.exists()


def test_a_job_holds_the_parameters_as_plain_data_which_its_task_makes_into_the_stages_own(tmp_path):
    overrides = read_overrides(None, ["tracking.distance=points"])
    job, = make_jobs(tmp_path, [touch_capture(tmp_path / "t1")], tmp_path / "out", overrides,
                     allow_outside_paths=False, worker_log_level=logging.WARNING)
    assert b"stages" not in pickle.dumps(job)  # the batch's process holds it without importing the stages
    assert stage_params(job.overrides) == read_params(None, ["tracking.distance=points"])


def test_without_dask_an_address_says_how_to_install_it(study, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed now fails
    out = tmp_path / "out"
    assert main(["batch", str(study), "--out", str(out), "--scheduler", "tcp://127.0.0.1:8786", "-q"]) == 2
    assert "Dask is not installed" in capsys.readouterr().err
    assert not out.exists()  # refused before anything was written


def report_or_exit(job: CaptureJob) -> CaptureReport:
    """A task that ends its worker process for the job named "dies", as a crash in compiled code would."""
    if job.name == "dies":
        os._exit(1)
    return CaptureReport(job.name, "ran")


def test_a_capture_that_ends_its_worker_process_fails_alone_once_the_pool_is_renewed():
    jobs = [CaptureJob(name, Path(name), Path(name), ()) for name in ("dies", "a", "b", "c")]
    reports = []
    with RenewedProcessPool(1) as pool:
        run_jobs(jobs, Workers(pool, 1, "test"), reports.append, task=report_or_exit)
    assert [(report.capture, report.status) for report in reports] == [
        ("dies", "failed"), ("a", "ran"), ("b", "ran"), ("c", "ran")]
    assert "worker process was lost" in reports[0].error


def test_the_bench_study_views_a_stretch_of_a_sample_and_judges_the_broken_capture(tmp_path):
    view = excerpt_view(TINY, tmp_path / "view", 2, 6)
    assert Capture.open(view).frame_numbers == (2, 3, 4, 5)
    good = {"capture": "walk/first", "status": "ran"}
    broken = {"capture": BENCH_BROKEN, "status": "failed", "error": f"x/{BENCH_BROKEN_IMAGE}: not a readable image"}
    assert broken_reported({"returncode": SOME_FAILED, "rows": [good, broken]}, ["walk/first"])
    assert not broken_reported({"returncode": 0, "rows": [good, broken]}, ["walk/first"])
    assert not broken_reported({"returncode": SOME_FAILED, "rows": [{**good, "status": "failed"}, broken]},
                               ["walk/first"])


def test_the_captures_with_the_most_media_start_first(tmp_path):
    sizes = {"short": 10, "long": 1000, "middle": 100, "none": 0}
    jobs = []
    for name, size in sizes.items():
        capture = touch_capture(tmp_path / name)
        if size:
            (capture / "videos").mkdir()
            (capture / "videos" / "cam1.mp4").write_bytes(b"x" * size)
            (capture / "calibration.toml").write_bytes(b"x" * 5000)  # not media
        jobs.append(CaptureJob(name, capture, tmp_path / "out" / name, ()))
    assert [job.name for job in largest_first(jobs)] == ["long", "middle", "short", "none"]
