"""The cached stage runner on a small fake graph: skip, rerun what depends on a change, resume.

Fake graph: ``source`` (whole-stage, writes one JSON) -> ``per_frame`` (one JSON per frame, through
``map_frames``) -> ``summary`` (sums the per-frame values). Every frame computed is appended to a log
file, so tests can count exactly which work was done.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from calib.errors import InputError
from pipeline.engine.cache import describe_outputs, expected_record, output_changes
from pipeline.engine.context import consecutive_chunks
from pipeline.engine.executors import make_executor
from pipeline.engine.output_folder import output_lock
from pipeline.engine.params import apply_overrides, default_params
from pipeline.engine.runner import Runner
from pipeline.engine.stage import Stage, select_stages
from pipeline.engine.status import graph_status
from pipeline.engine.versions import code_inputs, code_version
from pipeline.io import frames_io
from pipeline.io.capture import Capture
from pipeline.io.run_layout import LOCK, MANIFEST, MARKER, RUN_RECORD

WORK_LOG = "FAKE_STAGE_WORK_LOG"  # environment: file where fake stages log their work
FAIL_AT = "FAKE_STAGE_FAIL_AT"  # environment: frame at which the per-frame stage raises


@dataclass(frozen=True)
class SourceParams:
    value: float = 1.0
    comment: str = ""  # does not change the output: downstream must not rerun when only this changes


@dataclass(frozen=True)
class PerFrameParams:
    scale: float = 2.0


@dataclass(frozen=True)
class SummaryParams:
    rounding: int = 3


def _log(entry: str) -> None:
    with open(os.environ[WORK_LOG], "a") as handle:
        handle.write(entry + "\n")


def run_source(ctx) -> None:
    _log("source")
    frames_io.write_json(ctx.out_dir / "value.json", {"value": ctx.params.value})


def per_frame_task(chunk: tuple[int, ...], *, value: float, scale: float, out_dir: Path) -> None:
    for frame in chunk:
        if str(frame) == os.environ.get(FAIL_AT):
            raise RuntimeError(f"simulated crash at frame {frame}")
        _log(f"per_frame {frame}")
        frames_io.write_record(out_dir / frames_io.frame_name(frame, ".json"), {"v": value * scale * frame})


def run_per_frame(ctx) -> int:
    value = frames_io.read_json(ctx.input_dir("source") / "value.json")["value"]
    task = functools.partial(per_frame_task, value=value, scale=ctx.params.scale, out_dir=ctx.out_dir)
    return ctx.map_frames(task, lambda frame: [ctx.out_dir / frames_io.frame_name(frame, ".json")],
                          chunk_size=1)


def run_summary(ctx) -> None:
    _log("summary")
    frame_files = sorted(ctx.input_dir("per_frame").glob("[0-9]*.json"))
    total = sum(frames_io.read_record(path)["v"] for path in frame_files)
    frames_io.write_json(ctx.out_dir / "total.json", {"total": round(total, ctx.params.rounding)})


STAGES = (
    Stage("source", run_source, params_type=SourceParams, capture_parts=("config",)),
    Stage("per_frame", run_per_frame, inputs=("source",), params_type=PerFrameParams,
          capture_parts=("frames",)),
    Stage("summary", run_summary, inputs=("per_frame",), params_type=SummaryParams),
)


@pytest.fixture
def setup(tmp_path, tiny_capture, monkeypatch):
    """(capture, output folder, run(params overrides, **options) -> outcomes, read work log)."""
    monkeypatch.setenv(WORK_LOG, str(tmp_path / "work.log"))
    capture = Capture.open(tiny_capture)
    out = tmp_path / "out"

    def run(overrides=None, selected=None, force=False, stages=STAGES):
        params = apply_overrides(default_params(stages), overrides or {}, source="test")
        (tmp_path / "work.log").write_text("")
        with output_lock(out), make_executor(1) as workers:
            outcomes = Runner(stages, capture, params, out, workers).run(selected, force=force)
        return {outcome.name: outcome.action for outcome in outcomes}

    def work():
        return (tmp_path / "work.log").read_text().split("\n")[:-1]

    return capture, out, run, work


def test_first_run_runs_everything_and_writes_manifests(setup):
    capture, out, run, work = setup
    assert run() == {"source": "ran", "per_frame": "ran", "summary": "ran"}
    assert work() == ["source", "per_frame 0", "per_frame 1", "per_frame 2", "per_frame 3", "summary"]
    manifest = json.loads((out / "per_frame" / MANIFEST).read_text())
    assert manifest["params"] == {"scale": 2.0}
    assert manifest["timing"]["frames"] == len(capture.frame_numbers)
    assert set(manifest["inputs"]) == {"stage:source", "capture:frames"}
    assert frames_io.read_json(out / "summary" / "total.json") == {"total": 12.0}  # 2 * (0+1+2+3)


def test_second_run_skips_everything(setup):
    _, _, run, work = setup
    run()
    assert run() == {"source": "up to date", "per_frame": "up to date", "summary": "up to date"}
    assert work() == []


def test_changing_a_parameter_reruns_that_stage_and_downstream_only(setup):
    _, out, run, work = setup
    run()
    assert run({"per_frame": {"scale": 3.0}}) == {
        "source": "up to date", "per_frame": "ran", "summary": "ran"}
    assert frames_io.read_json(out / "summary" / "total.json") == {"total": 18.0}
    assert run({"per_frame": {"scale": 3.0}, "summary": {"rounding": 1}}) == {
        "source": "up to date", "per_frame": "up to date", "summary": "ran"}
    assert work() == ["summary"]


def test_upstream_rerun_with_identical_outputs_does_not_ripple_down(setup):
    _, _, run, work = setup
    run()
    assert run({"source": {"comment": "same numbers"}}) == {
        "source": "ran", "per_frame": "up to date", "summary": "up to date"}
    assert work() == ["source"]


def test_killed_run_resumes_with_the_remaining_frames(setup, monkeypatch):
    _, out, run, work = setup
    monkeypatch.setenv(FAIL_AT, "2")
    with pytest.raises(RuntimeError, match="simulated crash at frame 2"):
        run()
    assert work() == ["source", "per_frame 0", "per_frame 1"]
    assert not (out / "per_frame" / MANIFEST).exists()  # incomplete stage: no manifest to trust
    assert (out / "per_frame" / MARKER).exists()

    monkeypatch.delenv(FAIL_AT)
    assert run() == {"source": "up to date", "per_frame": "ran", "summary": "ran"}
    assert work() == ["per_frame 2", "per_frame 3", "summary"]
    assert frames_io.read_json(out / "summary" / "total.json") == {"total": 12.0}


def test_interrupted_run_with_other_parameters_starts_over(setup, monkeypatch):
    _, out, run, work = setup
    monkeypatch.setenv(FAIL_AT, "2")
    with pytest.raises(RuntimeError):
        run()
    monkeypatch.delenv(FAIL_AT)
    run({"per_frame": {"scale": 5.0}})
    per_frame_work = [entry for entry in work() if entry.startswith("per_frame")]
    assert per_frame_work == [f"per_frame {f}" for f in range(4)]
    assert frames_io.read_record(out / "per_frame" / "000001.json") == {"v": 5.0}


def test_leftover_temporary_files_are_removed_on_resume(setup, monkeypatch):
    _, out, run, _ = setup
    monkeypatch.setenv(FAIL_AT, "1")
    with pytest.raises(RuntimeError):
        run()
    leftover = out / "per_frame" / ".tmp-123-abcd-000001.json"
    leftover.write_text("{half")
    monkeypatch.delenv(FAIL_AT)
    run()
    assert not leftover.exists()


def test_corrupt_manifest_is_a_logged_miss(setup, caplog):
    _, out, run, work = setup
    run()
    (out / "summary" / MANIFEST).write_text("{not json")
    assert run()["summary"] == "ran"
    assert "unreadable manifest" in caplog.text
    assert work() == ["summary"]


def test_deleted_output_file_is_recomputed_alone(setup):
    _, out, run, work = setup
    run()
    (out / "per_frame" / "000002.json").unlink()
    assert run() == {"source": "up to date", "per_frame": "ran", "summary": "up to date"}
    assert work() == ["per_frame 2"]  # identical content again, so summary stays valid


@pytest.mark.parametrize("kind", ["folder", "file", "link"])
def test_a_stage_folder_the_runner_did_not_write_is_never_deleted(setup, tmp_path, kind):
    _, out, run, work = setup
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("my data")
    out.mkdir()
    if kind == "folder":
        (out / "source").mkdir()
        (out / "source" / "notes.txt").write_text("my data")
    elif kind == "file":
        (out / "source").write_text("my data")
    else:
        (out / "source").symlink_to(mine, target_is_directory=True)
    with pytest.raises(InputError, match=f"{out / 'source'}: not a stage folder written by the pipeline"):
        run()
    assert work() == []
    assert (mine / "notes.txt").read_text() == "my data"
    assert (out / "source" if kind == "file" else out / "source" / "notes.txt").read_text() == "my data"


def test_a_stage_folder_the_runner_wrote_is_emptied_for_a_fresh_start(setup):
    _, out, run, _ = setup
    run()
    (out / "per_frame" / MANIFEST).unlink()  # a run that did not finish: its files are the runner's
    (out / "per_frame" / "extra.txt").write_text("left over")
    run({"per_frame": {"scale": 3.0}})
    assert not (out / "per_frame" / "extra.txt").exists()


def test_a_file_a_finished_stage_did_not_write_is_not_deleted(setup):
    _, out, run, _ = setup
    run()
    (out / "per_frame" / "extra.txt").write_text("the user's")
    with pytest.raises(InputError, match=r"per_frame/extra.txt: not written by the pipeline"):
        run({"per_frame": {"scale": 3.0}})
    assert (out / "per_frame" / "extra.txt").read_text() == "the user's"


def test_the_runner_refuses_an_output_folder_in_the_capture(setup):
    capture, _, _, _ = setup
    with pytest.raises(InputError, match="overlaps the capture"):
        Runner(STAGES, capture, default_params(STAGES), capture.root / "out", None)


def change_value(path: Path, old: str, new: str) -> None:
    """Replace one value in a file by another of the same length: a size check cannot see it."""
    text = path.read_text()
    assert len(old) == len(new) and old in text
    path.write_text(text.replace(old, new))


def test_a_damaged_file_of_a_finished_stage_is_recomputed_alone(setup):
    capture, out, run, work = setup
    run()
    original = (out / "per_frame" / "000002.json").read_text()
    change_value(out / "per_frame" / "000002.json", "4.0", "5.0")
    statuses = {s.name: s for s in graph_status(STAGES, capture, default_params(STAGES), out)}
    assert statuses["per_frame"].reason == "output files changed on disk: 1 damaged (000002.json)"
    assert run() == {"source": "up to date", "per_frame": "ran", "summary": "up to date"}
    assert work() == ["per_frame 2"]
    assert (out / "per_frame" / "000002.json").read_text() == original


def test_a_damaged_frame_kept_from_an_interrupted_run_is_recomputed(setup, monkeypatch, caplog):
    _, out, run, work = setup
    monkeypatch.setenv(FAIL_AT, "3")
    with pytest.raises(RuntimeError):
        run()
    change_value(out / "per_frame" / "000001.json", "2.0", "7.0")  # no manifest yet: only the file's own check
    monkeypatch.delenv(FAIL_AT)
    assert run() == {"source": "up to date", "per_frame": "ran", "summary": "ran"}
    assert work() == ["per_frame 1", "per_frame 3", "summary"]
    assert "000001.json: JSON record fails its crc32 check; deleted, computed again" in caplog.text
    assert frames_io.read_json(out / "summary" / "total.json") == {"total": 12.0}


def test_a_damaged_file_a_stage_reads_is_recomputed_not_used(setup, caplog):
    """A damaged file blessed into its stage's manifest (as runs before the content hashes did) is
    found by the reader of the next stage; the runner computes it again instead of stopping."""
    _, out, run, work = setup
    run()
    change_value(out / "per_frame" / "000001.json", "2.0", "7.0")
    manifest = json.loads((out / "per_frame" / MANIFEST).read_text())
    manifest["outputs"] = describe_outputs(out / "per_frame")
    (out / "per_frame" / MANIFEST).write_text(json.dumps(manifest))
    assert run() == {"source": "up to date", "per_frame": "ran", "summary": "ran"}
    assert work() == ["summary", "per_frame 1", "summary"]
    assert "000001.json: JSON record fails its crc32 check; deleted, the per_frame stage computes it again" in (
        caplog.text)
    assert frames_io.read_json(out / "summary" / "total.json") == {"total": 12.0}


def test_checking_a_thousand_output_files_takes_well_under_a_second(tmp_path):
    folder = tmp_path / "stage"
    rng = np.random.default_rng(0)
    for index in range(1000):  # about the files of a 112-frame, 6-camera capture, and their 13 MB
        frames_io.write_ply(folder / frames_io.frame_name(index, ".ply"), rng.normal(size=(270, 3)),
                            np.tile([0.0, 0.0, 1.0], (270, 1)))
    manifest = {"outputs": describe_outputs(folder)}
    started = time.perf_counter()
    assert not output_changes(folder, manifest)
    seconds = time.perf_counter() - started
    print(f"up-to-date check of 1000 files: {1000 * seconds:.0f} ms")
    assert seconds < 0.5


def test_a_code_version_follows_every_file_of_a_declared_package(tmp_path, monkeypatch):
    package = tmp_path / "keyed_package"
    (package / "data").mkdir(parents=True)
    (package / "__init__.py").write_text("SCALE = 2\n")
    (package / "data" / "table.npz").write_bytes(b"first table")
    monkeypatch.syspath_prepend(str(tmp_path))
    stage = Stage("keyed", run_source, code=("keyed_package",))
    first = code_version(stage)
    (package / "data" / "table.npz").write_bytes(b"other table")  # data, not source: part of the key
    second = code_version(stage)
    (package / "__pycache__").mkdir()
    (package / "__pycache__" / "cache.nbi").write_bytes(b"compiled")  # a cache is not
    assert first != second == code_version(stage)


def test_a_run_function_counts_with_the_helpers_and_constants_of_its_module_it_uses():
    from pipeline import graph

    silhouettes, tracking = (code_inputs(stage) for stage in graph.STAGES if stage.name in ("silhouettes", "tracking"))
    assert {function.__name__ for function in silhouettes.functions} >= {
        "run_silhouettes", "_backgrounds", "estimated_backgrounds", "video_chunk_size"}
    assert ("UNRESOLVED_WARNING_SHARE", repr(graph.UNRESOLVED_WARNING_SHARE)) in silhouettes.constants
    assert "estimated_backgrounds" not in {function.__name__ for function in tracking.functions}
    assert {"run_tracking", "_warn_volume_contact"} <= {function.__name__ for function in tracking.functions}
    assert any(name == "stages.tracking/data/poses.npz" for name, _ in tracking.files)


def test_a_failed_rerun_leaves_nothing_that_looks_finished(setup, monkeypatch, caplog):
    caplog.set_level(logging.DEBUG, logger="pipeline.engine.runner")  # the terminal shows only the run's error
    capture, out, run, work = setup
    run()
    assert frames_io.read_json(out / RUN_RECORD)["state"] == "finished"
    monkeypatch.setenv(FAIL_AT, "2")
    with pytest.raises(RuntimeError, match="simulated crash at frame 2"):
        run({"per_frame": {"scale": 3.0}})
    assert not (out / "per_frame" / MANIFEST).exists()
    assert not (out / "summary").exists()  # made from the per_frame files the run replaced
    assert (out / "source" / MANIFEST).exists()
    record = frames_io.read_json(out / RUN_RECORD)
    assert record["state"] == "failed" and record["params"]["per_frame"] == {"scale": 3.0}
    assert record["failure"] == {"error": "simulated crash at frame 2", "incomplete": ["per_frame"]}
    assert "the run failed; per_frame left incomplete" in caplog.text
    statuses = {s.name: s.state for s in graph_status(STAGES, capture, default_params(STAGES), out)}
    assert statuses == {"source": "up to date", "per_frame": "incomplete", "summary": "not run"}
    monkeypatch.delenv(FAIL_AT)
    assert run({"per_frame": {"scale": 3.0}}) == {"source": "up to date", "per_frame": "ran", "summary": "ran"}
    assert work() == ["per_frame 2", "per_frame 3", "summary"]
    assert frames_io.read_json(out / RUN_RECORD)["state"] == "finished"


def test_a_run_refused_before_any_change_leaves_no_trace(setup):
    _, out, run, _ = setup
    with pytest.raises(InputError, match="needs the results of source"):
        run(selected=["per_frame"])
    assert not out.exists()  # no folder, no lock file, no run.json


def test_the_lock_file_goes_with_the_run(tmp_path):
    out = tmp_path / "out"
    (out / "kept").mkdir(parents=True)
    with output_lock(out):
        assert (out / LOCK).exists()
    assert not (out / LOCK).exists() and (out / "kept").is_dir()
    with output_lock(out):  # and the folder can be locked again
        pass


def test_force_reruns_selected_stages(setup):
    _, _, run, work = setup
    run()
    assert run(selected=["per_frame"], force=True) == {
        "source": "not selected", "per_frame": "ran", "summary": "not selected"}
    assert work() == [f"per_frame {f}" for f in range(4)]


def test_selected_stage_needs_completed_upstream(setup):
    _, _, run, _ = setup
    with pytest.raises(InputError, match="needs the results of source"):
        run(selected=["per_frame"])


def test_status_reports_why_a_stage_is_stale(setup):
    capture, out, run, _ = setup
    params = default_params(STAGES)
    assert [s.state for s in graph_status(STAGES, capture, params, out)] == ["not run"] * 3
    run()
    assert {s.state for s in graph_status(STAGES, capture, params, out)} == {"up to date"}
    changed = apply_overrides(params, {"per_frame": {"scale": 4.0}}, source="test")
    statuses = {s.name: s for s in graph_status(STAGES, capture, changed, out)}
    assert statuses["source"].state == "up to date"
    assert statuses["per_frame"].reason == "parameter scale: 2.0 -> 4.0"
    assert statuses["summary"].reason == "upstream per_frame not up to date"


def test_status_of_an_interrupted_stage_is_incomplete(setup, monkeypatch):
    capture, out, run, _ = setup
    monkeypatch.setenv(FAIL_AT, "3")
    with pytest.raises(RuntimeError):
        run()
    statuses = {s.name: s for s in graph_status(STAGES, capture, default_params(STAGES), out)}
    assert statuses["per_frame"].state == "incomplete"
    assert statuses["per_frame"].reason.startswith("3 files kept")


def test_second_concurrent_run_is_refused(tmp_path):
    with output_lock(tmp_path / "out"):
        with pytest.raises(InputError, match="another run is using this output directory"):
            with output_lock(tmp_path / "out"):
                pass
    with output_lock(tmp_path / "out"):  # released: usable again
        pass


@pytest.mark.parametrize(("options", "expected"), [
    ({}, ["source", "per_frame", "summary"]),
    ({"only": "per_frame"}, ["per_frame"]),
    ({"start": "per_frame"}, ["per_frame", "summary"]),
    ({"end": "per_frame"}, ["source", "per_frame"]),
    ({"start": "per_frame", "end": "per_frame"}, ["per_frame"]),
])
def test_select_stages(options, expected):
    assert select_stages(STAGES, **options) == expected


def test_select_unknown_stage_lists_the_valid_ones():
    with pytest.raises(InputError, match="--only nope: unknown stage .*source, per_frame, summary"):
        select_stages(STAGES, only="nope")


def test_consecutive_chunks_break_at_gaps_and_size():
    frames = (0, 2, 4, 6, 8, 10, 12)  # a step-2 selection: consecutive means adjacent in this list
    assert consecutive_chunks([0, 2, 4, 8, 10, 12], frames, 2) == [(0, 2), (4,), (8, 10), (12,)]


def test_graph_declaration_errors():
    with pytest.raises(ValueError, match="not declared before it"):
        Runner((STAGES[1], STAGES[0]), None, {}, Path("."), None)
    with pytest.raises(ValueError, match="stage name"):
        Stage("Bad Name", run_source)


# ---------------------------------------------------------------------------------------------
# Streaming: a stage that reads its upstream's frames as they appear runs alongside it


def run_follower(ctx) -> int:
    """Reads every per-frame file through ``ctx.ready`` (waiting for it while the upstream runs)."""
    frames = ctx.capture.frame_numbers
    for frame in frames:
        value = frames_io.read_record(ctx.ready(ctx.input_dir("per_frame") / frames_io.frame_name(frame, ".json")))
        _log(f"follower {frame}")
        frames_io.write_json(ctx.out_dir / frames_io.frame_name(frame, ".json"), {"twice": 2 * value["v"]})
    return len(frames)


STREAMING = (*STAGES[:2], Stage("follower", run_follower, inputs=("per_frame",), streams=True))


def test_a_streaming_stage_runs_alongside_its_upstream_and_ends_up_to_date(setup):
    capture, out, run, work = setup
    assert run(stages=STREAMING) == {"source": "ran", "per_frame": "ran", "follower": "ran"}
    assert sorted(work()) == sorted(["source"] + [f"{stage} {frame}" for frame in capture.frame_numbers
                                                  for stage in ("per_frame", "follower")])
    assert [frames_io.read_json(out / "follower" / frames_io.frame_name(frame, ".json"))["twice"]
            for frame in capture.frame_numbers] == [4.0 * frame for frame in capture.frame_numbers]
    manifest = json.loads((out / "follower" / MANIFEST).read_text())
    assert manifest["inputs"]["stage:per_frame"] == json.loads((out / "per_frame" / MANIFEST).read_text())[
        "outputs"]["digest"]
    assert run(stages=STREAMING) == {"source": "up to date", "per_frame": "up to date", "follower": "up to date"}


def test_an_upstream_failure_stops_the_streaming_stage_without_a_record(setup, monkeypatch):
    capture, out, run, work = setup
    monkeypatch.setenv(FAIL_AT, str(capture.frame_numbers[2]))
    with pytest.raises(RuntimeError, match="simulated crash"):
        run(stages=STREAMING)
    assert not (out / "per_frame" / MANIFEST).exists() and not (out / "follower" / MANIFEST).exists()
    monkeypatch.delenv(FAIL_AT)
    assert run(stages=STREAMING) == {"source": "up to date", "per_frame": "ran", "follower": "ran"}


FOLLOWER_FAIL_AT = "FAKE_FOLLOWER_FAIL_AT"  # environment: frame at which the resuming follower raises


def run_resuming_follower(ctx) -> int:
    """A follower that, like the tracker, resumes after the last frame it finished."""
    outputs_of = lambda frame: [ctx.out_dir / frames_io.frame_name(frame, ".json")]  # noqa: E731
    pending = ctx.pending_frames(outputs_of)
    for frame in pending:
        value = frames_io.read_record(ctx.ready(ctx.input_dir("per_frame") / frames_io.frame_name(frame, ".json")))
        if str(frame) == os.environ.get(FOLLOWER_FAIL_AT):
            raise KeyboardInterrupt
        _log(f"follower {frame}")
        frames_io.write_record(outputs_of(frame)[0], {"twice": 2 * value["v"]})
    return len(pending)


RESUMING = (*STAGES[:2], Stage("follower", run_resuming_follower, inputs=("per_frame",), streams=True))


def test_a_streaming_stage_killed_with_its_upstream_resumes_alongside_it(setup, monkeypatch):
    """Issue #13 item 8: both stopped at frame 2 (the upstream's crash); the rerun streams again and
    keeps the follower's frames 0 and 1 instead of emptying its folder."""
    capture, out, run, work = setup
    frames = capture.frame_numbers
    monkeypatch.setenv(FAIL_AT, str(frames[2]))
    with pytest.raises(RuntimeError, match="simulated crash"):
        run(stages=RESUMING)
    assert [entry for entry in work() if entry.startswith("follower")] == [f"follower {f}" for f in frames[:2]]
    monkeypatch.delenv(FAIL_AT)
    assert run(stages=RESUMING) == {"source": "up to date", "per_frame": "ran", "follower": "ran"}
    assert sorted(work()) == sorted(f"{stage} {f}" for f in frames[2:] for stage in ("per_frame", "follower"))
    assert run(stages=RESUMING) == {"source": "up to date", "per_frame": "up to date", "follower": "up to date"}


def test_a_streaming_stage_killed_after_its_upstream_finished_resumes_on_its_own(setup, monkeypatch):
    capture, out, run, work = setup
    frames = capture.frame_numbers
    monkeypatch.setenv(FOLLOWER_FAIL_AT, str(frames[2]))
    with pytest.raises(KeyboardInterrupt):
        run(stages=RESUMING)
    assert (out / "per_frame" / MANIFEST).exists() and not (out / "follower" / MANIFEST).exists()
    assert frames_io.read_json(out / RUN_RECORD)["failure"]["error"] == "interrupted (Ctrl-C)"
    monkeypatch.delenv(FOLLOWER_FAIL_AT)
    assert run(stages=RESUMING) == {"source": "up to date", "per_frame": "up to date", "follower": "ran"}
    assert work() == [f"follower {f}" for f in frames[2:]]
    assert [frames_io.read_record(out / "follower" / frames_io.frame_name(f, ".json"))["twice"]
            for f in frames] == [4.0 * f for f in frames]


@pytest.mark.parametrize("change", [{"per_frame": {"scale": 3.0}}, {"source": {"value": 2.0}}])
def test_a_streaming_stage_killed_starts_over_when_its_upstream_changed(setup, monkeypatch, change):
    capture, out, run, work = setup
    monkeypatch.setenv(FOLLOWER_FAIL_AT, str(capture.frame_numbers[2]))
    with pytest.raises(KeyboardInterrupt):
        run(stages=RESUMING)
    monkeypatch.delenv(FOLLOWER_FAIL_AT)
    run(change, stages=RESUMING)
    assert [entry for entry in work() if entry.startswith("follower")] == [
        f"follower {f}" for f in capture.frame_numbers]


def test_a_forced_streaming_stage_starts_over(setup, monkeypatch):
    capture, out, run, work = setup
    monkeypatch.setenv(FOLLOWER_FAIL_AT, str(capture.frame_numbers[2]))
    with pytest.raises(KeyboardInterrupt):
        run(stages=RESUMING)
    monkeypatch.delenv(FOLLOWER_FAIL_AT)
    (out / "per_frame" / MANIFEST).unlink()  # so that the forced rerun streams
    run(stages=RESUMING, force=True)
    assert [entry for entry in work() if entry.startswith("follower")] == [
        f"follower {f}" for f in capture.frame_numbers]


def test_a_body_file_given_by_its_path_is_part_of_the_tracking_key(tiny_capture, tmp_path):
    from importlib import resources

    from pipeline.graph import STAGES
    from stages.tracking.params import TrackerParams

    tracking = next(stage for stage in STAGES if stage.name == "tracking")
    capture = Capture.open(tiny_capture)
    body = tmp_path / "mine.yaml"
    body.write_text((resources.files("stages.tracking") / "bodies" / "default.yaml").read_text())
    params = TrackerParams(body=str(body))
    before = expected_record(tracking, capture, params, tmp_path / "out")
    body.write_text(body.read_text() + "# edited in place\n")
    after = expected_record(tracking, capture, params, tmp_path / "out")
    assert before.record["inputs"]["file:body"] != after.record["inputs"]["file:body"]
    assert before.key != after.key
    assert "file:body" not in expected_record(tracking, capture, TrackerParams(), tmp_path / "out").record["inputs"]
