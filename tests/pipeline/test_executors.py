"""Executors: in-process, local process pool and Dask all run ``map_frames`` to the same files."""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path

import pytest

from calib.errors import InputError
from pipeline.engine.context import StageContext
from pipeline.engine.executors import WORKER_NICENESS, InProcessExecutor, make_executor, usable_cpus
from pipeline.io import frames_io
from pipeline.io.capture import Capture


def write_frames(chunk: tuple[int, ...], *, out_dir: Path) -> None:
    """A per-frame task: one JSON per frame, recording which process computed it."""
    for frame in chunk:
        frames_io.write_json(out_dir / frames_io.frame_name(frame, ".json"),
                             {"frame": frame, "square": frame * frame, "pid": os.getpid()})


def fail_on_odd(chunk: tuple[int, ...]) -> None:
    if any(frame % 2 for frame in chunk):
        raise RuntimeError(f"odd chunk {chunk}")


def map_over_capture(capture: Capture, out_dir: Path, workers, chunk_size=None) -> int:
    out_dir.mkdir(parents=True, exist_ok=True)
    ctx = StageContext("test", capture, None, out_dir, out_dir.parent, workers)
    return ctx.map_frames(functools.partial(write_frames, out_dir=out_dir),
                          lambda frame: [out_dir / frames_io.frame_name(frame, ".json")],
                          chunk_size=chunk_size)


def results(out_dir: Path) -> dict[int, int]:
    written = [frames_io.read_json(path) for path in sorted(out_dir.glob("*.json"))]
    return {data["frame"]: data["square"] for data in written}


def test_in_process_executor_returns_results_and_exceptions():
    executor = InProcessExecutor()
    assert executor.submit(pow, 2, 10).result() == 1024
    with pytest.raises(ZeroDivisionError):
        executor.submit(divmod, 1, 0).result()


def test_in_process_map_frames(tiny_capture, tmp_path):
    capture = Capture.open(tiny_capture)
    with make_executor(1) as workers:
        assert map_over_capture(capture, tmp_path / "out", workers) == 4
        assert map_over_capture(capture, tmp_path / "out", workers) == 0  # all frames already there
    assert results(tmp_path / "out") == {0: 0, 1: 1, 2: 4, 3: 9}


def test_process_pool_map_frames(tiny_capture, tmp_path):
    capture = Capture.open(tiny_capture)
    with make_executor(2) as workers:
        assert workers.count == 2
        assert map_over_capture(capture, tmp_path / "out", workers, chunk_size=1) == 4
    assert results(tmp_path / "out") == {0: 0, 1: 1, 2: 4, 3: 9}
    assert os.getpid() not in {frames_io.read_json(p)["pid"] for p in (tmp_path / "out").glob("*.json")}


def test_worker_exception_reaches_the_caller(tiny_capture, tmp_path):
    capture = Capture.open(tiny_capture)
    ctx_dir = tmp_path / "out"
    with make_executor(2) as workers:
        ctx = StageContext("test", capture, None, ctx_dir, tmp_path, workers)
        with pytest.raises(RuntimeError, match="odd chunk"):
            ctx.map_frames(fail_on_odd, lambda frame: [ctx_dir / f"{frame}"], chunk_size=1)


@pytest.mark.parametrize(("workers", "scheduler", "message"), [
    (0, None, "--workers 0: expected a positive whole number"),
    (1, "local:zero", "--scheduler local:zero: expected local:N"),
])
def test_bad_executor_options(workers, scheduler, message):
    with pytest.raises(InputError, match=message):
        with make_executor(workers, scheduler):
            pass


@pytest.mark.dask
def test_dask_local_cluster_map_frames(tiny_capture, tmp_path):
    pytest.importorskip("distributed")
    import cloudpickle

    # Dask workers cannot import this test module by name: ship its functions by value.
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    try:
        capture = Capture.open(tiny_capture)
        with make_executor(1, "local:2") as workers:
            assert workers.count == 2 and workers.description.startswith("Dask at ")
            assert map_over_capture(capture, tmp_path / "out", workers, chunk_size=1) == 4
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    assert results(tmp_path / "out") == {0: 0, 1: 1, 2: 4, 3: 9}


def test_a_failed_preload_does_not_stop_the_pool():
    with make_executor(2, preload=("json", "no_such_module_here")) as workers:
        pids = {workers.executor.submit(os.getpid).result() for _ in range(4)}
    assert pids and os.getpid() not in pids  # real tasks still run, in the pool's own processes


def test_pool_processes_yield_to_the_parent():
    with make_executor(2) as workers:
        niceness = {workers.executor.submit(os.nice, 0).result() for _ in range(4)}
    assert niceness == {min(os.nice(0) + WORKER_NICENESS, 19)}


@pytest.mark.parametrize(("argv", "started"), [
    (["run", "capture", "--out", "o", "--workers", "2"], True),
    (["run", "capture", "--out", "o", "--workers=3", "-q"], True),
    (["run", "capture", "--out", "o", "--workers", "1"], False),  # one worker: in this process
    (["run", "capture", "--out", "o"], usable_cpus() > 1),  # by default one worker per CPU this process may use
    (["run", "capture", "--out", "o", "--workers", "2", "--scheduler", "local:2"], False),  # Dask's workers
    (["run", "capture", "--out", "o", "--workers", "two"], False),  # the parser proper reports it
])
def test_a_run_with_local_workers_starts_their_server_before_its_imports(monkeypatch, argv, started):
    import pipeline.engine.executors as executors
    from pipeline.cli import start_workers_early
    from pipeline.worker_modules import WORKER_MODULES

    calls = []
    monkeypatch.setattr(executors, "start_worker_server", calls.append)
    start_workers_early(argv)
    assert calls == ([WORKER_MODULES] if started else [])


def test_without_a_fork_server_the_workers_are_spawned(monkeypatch, caplog):
    import multiprocessing.forkserver

    def no_room():
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(multiprocessing.forkserver, "ensure_running", no_room)
    with make_executor(2) as workers:
        assert workers.executor.submit(sum, [1, 2]).result() == 3
    assert "spawned instead" in caplog.text and "No space left" in caplog.text


def test_the_cpus_a_run_may_use_are_its_affinity(monkeypatch):
    """A container or `taskset` narrows the CPUs a process may use below the machine's count; the default number of
    workers follows the narrower figure."""
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 3}, raising=False)
    assert usable_cpus() == 2
    monkeypatch.delattr(os, "sched_getaffinity", raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: None)
    assert usable_cpus() == 1
