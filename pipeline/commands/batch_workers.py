"""The tasks of ``python -m pipeline batch`` and where they run: one capture as a picklable job, the task that
runs it in a worker (``run``'s own code, then its count and score), and the pools of processes or Dask workers that
run several at once, each a failure of its own.

Like :mod:`pipeline.commands.batch`, this module imports only light modules at its top: the stages and the scoring
(:data:`TASK_MODULES`) are imported where a capture runs, which with a local pool is its fork server, once.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import importlib
import logging
import multiprocessing
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from calib.errors import InputError
from pipeline.engine.executors import InProcessExecutor, Workers, local_count, make_executor, start_worker_server
from pipeline.terminal import PrintableFormatter

log = logging.getLogger(__name__)

#: What a capture's task runs, and what checks the parameters: the stages and the scoring. Imported only where a
#: capture runs or the parameters are checked: with a local pool, only the pool's fork server loads it, once for
#: all its processes (:class:`RenewedProcessPool`).
TASK_MODULES = ("pipeline.commands.run", "pipeline.evaluate")
#: Top-level packages whose log lines a worker process shows (see :func:`_log_in_worker`).
LOGGED_PACKAGES = ("calib", "stages", "pipeline")


# ---------------------------------------------------------------------------------------------
# One capture: the task a worker runs


@dataclass(frozen=True)
class CaptureJob:
    """One capture to run: everything its task needs, picklable (it may travel to a Dask worker).

    ``name`` is its path under the batch's root (the row's name); ``capture`` and ``out`` are absolute, so
    that a worker started elsewhere finds them; ``overrides`` are the parameters asked for as plain data
    (:func:`~pipeline.engine.params.read_overrides`), which the task makes into the stages' parameters: the
    batch's process need not import the stages to hold them; ``worker_log_level`` is None when the task runs in
    the batch's own process, whose logging is set already.
    """

    name: str
    capture: Path
    out: Path
    overrides: Sequence[tuple[str, Mapping[str, Any]]]
    allow_outside_paths: bool = False
    worker_log_level: int | None = None


@dataclass(frozen=True)
class CaptureReport:
    """How one capture went: a row of the batch's table.

    ``status`` is "ran" (some stage ran), "up to date" (every stage was), "failed" (``error`` says why, in one
    line) or "not run" (the batch ended before it). ``frames``: the frames the capture selects; ``estimated``:
    those exported; ``mpjpe_mm``: the mean joint error against the capture's ground truth, when it has one.
    """

    capture: str
    status: str
    frames: int | None = None
    estimated: int | None = None
    mpjpe_mm: float | None = None
    seconds: float | None = None
    error: str = ""

    @property
    def ok(self) -> bool:
        return self.status in ("ran", "up to date")


def one_line(error: BaseException) -> str:
    """An error as the one line the table shows: an InputError's message, else its type and first line."""
    text = str(error).strip()
    first = text.splitlines()[0] if text else ""
    if isinstance(error, InputError):
        return first
    return f"{type(error).__name__}: {first}" if first else type(error).__name__


def process_capture(job: CaptureJob) -> CaptureReport:
    """Run one capture as ``python -m pipeline run`` does (1 worker), then count and score its export.

    Never raises for the capture's own failure: a user mistake, an unusable result or a bug is reported
    in the row (a bug's traceback in the log), so that the captures beside it carry on.
    """
    from pipeline.commands.run import run_capture, stage_params  # see TASK_MODULES
    from pipeline.evaluate import TRUTH_FILE, evaluate_run
    from pipeline.io.export_io import read_joints_csv
    from pipeline.io.run_layout import RunLayout

    started = time.perf_counter()
    if job.worker_log_level is not None:
        _log_in_worker(job.name, job.worker_log_level)
    try:
        params = stage_params(job.overrides)
        with make_executor(1) as workers:
            result = run_capture(job.capture, job.out, params, workers,
                                 allow_outside_paths=job.allow_outside_paths)
        if result.problem is not None:
            raise InputError(result.problem)
        estimated = len(read_joints_csv(RunLayout(job.out).joints)[0])
        truth = job.capture / TRUTH_FILE
        mpjpe = float(evaluate_run(job.out, truth=truth)["mpjpe_mm"]) if truth.is_file() else None
    except Exception as error:  # this capture's failure, whatever it is, must not end the batch
        if not isinstance(error, InputError):
            log.error("%s: failed with a bug", job.name, exc_info=error)
        return CaptureReport(job.name, "failed", seconds=time.perf_counter() - started, error=one_line(error))
    status = "up to date" if all(outcome.action == "up to date" for outcome in result.outcomes) else "ran"
    return CaptureReport(job.name, status, result.frames, estimated, mpjpe, time.perf_counter() - started)


class _CaptureName(logging.Filter):
    """Puts the name of the capture a worker process runs now into its log records (``%(capture)s``)."""

    current = ""

    def filter(self, record: logging.LogRecord) -> bool:
        record.capture = self.current
        return True


_capture_name = _CaptureName()


def _log_in_worker(name: str, level: int) -> None:
    """In a worker process: log the project's lines at ``level`` to stderr, each naming the capture ``name``.

    A process pool's worker starts with no logging set up, and a Dask worker's is Dask's own: the handler goes
    on the project's packages (:data:`LOGGED_PACKAGES`), not on the root logger, so that Dask's lines are not
    shown twice. Set up once per process; later captures only change the name.
    """
    _capture_name.current = name
    for package in LOGGED_PACKAGES:
        logger = logging.getLogger(package)
        if not any(_capture_name in handler.filters for handler in logger.handlers):
            handler = logging.StreamHandler(sys.stderr)
            handler.addFilter(_capture_name)
            handler.setFormatter(PrintableFormatter("%(levelname)s %(name)s: %(capture)s: %(message)s"))
            logger.addHandler(handler)
            logger.propagate = False
        logger.setLevel(level)


# ---------------------------------------------------------------------------------------------
# Running the captures


def _start_worker(modules: Sequence[str]) -> None:
    """A worker process's start: import ``modules``, which its fork server has imported already (nothing to do)
    unless that failed (the fork server ignores a failed import; here it shows, with its traceback)."""
    for module in modules:
        importlib.import_module(module)


class RenewedProcessPool(cf.Executor):
    """A process pool that starts afresh when one of its processes dies, its processes forked from a server
    process that has imported what a capture needs.

    A ``ProcessPoolExecutor`` that loses a process (killed, out of memory, a crash in compiled code) is
    broken for good: the calls running in it fail, and so would every later one. Here only those running
    fail; the next call starts a new pool, so that one capture that ends its process does not fail the
    rest of the study. Unlike :func:`~pipeline.engine.executors.make_executor`'s pool, its processes keep the
    parent's priority: the parent only waits.

    The processes come from multiprocessing's ``forkserver`` (spawned where it cannot start:
    :func:`~pipeline.engine.executors.start_worker_server`), which imports :data:`TASK_MODULES` once as it
    starts (1.3-1.6 s of CPU: numpy, OpenCV, scipy, numba and the stages); each process is a fork of it, with
    those modules in memory already, the pages shared. With ``spawn`` every process imported them itself, all at
    once on a machine of few cores, and so did each process of a renewed pool. The server is a clean process
    (imports only, no work done), so forking it is safe where forking the batch's own process would not be;
    its processes end with ``os._exit``, without the interpreter's teardown (unloading numba's LLVM, OpenCV
    and the rest), which the batch would wait for as its pool shuts down.
    """

    def __init__(self, count: int) -> None:
        self.count = count
        self._pool = self._start()

    def _start(self) -> cf.ProcessPoolExecutor:
        """A pool of the fork server, which starts importing :data:`TASK_MODULES` now (unless it runs already).

        Its processes are forked on demand, a call starting one while none is idle, up to ``count``: the first
        call waits until the server has its modules, and this process's own work before it overlaps theirs.
        """
        context = multiprocessing.get_context("forkserver" if start_worker_server(TASK_MODULES) else "spawn")
        return cf.ProcessPoolExecutor(max_workers=self.count, mp_context=context, initializer=_start_worker,
                                      initargs=(TASK_MODULES,))

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> cf.Future:
        try:
            return self._pool.submit(fn, *args, **kwargs)
        except BrokenProcessPool:
            log.warning("a worker process was lost; starting %d new ones", self.count)
            self._pool.shutdown(wait=True)
            self._pool = self._start()
            return self._pool.submit(fn, *args, **kwargs)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self._pool.shutdown(wait=wait, cancel_futures=cancel_futures)


@contextlib.contextmanager
def capture_workers(scheduler: str) -> Iterator[Workers]:
    """Where whole captures run, and how many at once.

    ``local:1``: one after the other in this process; ``local:N``: N processes (:class:`RenewedProcessPool`);
    anything else: the Dask scheduler at that address (:func:`~pipeline.engine.executors.make_executor`).
    """
    if not scheduler.startswith("local:"):
        with make_executor(scheduler=scheduler) as workers:
            yield workers
        return
    count = local_count(scheduler)
    if count == 1:
        yield Workers(InProcessExecutor(), 1, "one at a time, in this process")
        return
    with RenewedProcessPool(count) as pool:
        yield Workers(pool, count, f"{count} at a time, in {count} local processes")


def run_jobs(jobs: Sequence[CaptureJob], workers: Workers, on_done: Callable[[CaptureReport], None], *,
             task: Callable[[CaptureJob], CaptureReport] = process_capture) -> None:
    """Run ``task`` on ``jobs`` with ``workers``, ``workers.count`` at a time, calling ``on_done`` with each
    report as it comes, in this thread.

    A job whose worker is lost (its process died, a Dask worker went away) is reported failed: its
    task's own failures are reports already. Starting no more than ``workers.count`` at once keeps the
    rest waiting in order (and gives the in-process executor one at a time).
    """
    waiting = iter(jobs)
    running: dict[cf.Future, CaptureJob] = {}
    while True:
        while len(running) < workers.count and (job := next(waiting, None)) is not None:
            log.info("%s: started", job.name)
            running[workers.executor.submit(task, job)] = job
        if not running:
            return
        done, _ = cf.wait(running, return_when=cf.FIRST_COMPLETED)
        for future in done:
            job = running.pop(future)
            try:
                report = future.result()
            except Exception as error:  # the worker went, not the task (whose failures are reports)
                report = CaptureReport(job.name, "failed", error=f"its worker process was lost ({one_line(error)}; "
                                                                 "this capture or one beside it ended it)")
            on_done(report)


def _check_params(overrides: Sequence[tuple[str, Mapping[str, Any]]]) -> None:
    from pipeline.commands.run import stage_params  # see TASK_MODULES

    stage_params(overrides)


def check_params(workers: Workers, overrides: Sequence[tuple[str, Mapping[str, Any]]]) -> None:
    """Check ``overrides`` against the stages' parameters, as ``run`` does before any work.

    A local pool's process checks them: it has the stages for its captures anyway, and this process, which then
    only waits, need not import them (1.3 s of CPU, which the pool's start-up would share on a machine of few
    cores). Otherwise this process does.

    Raises
    ------
    InputError
        Naming the mistake.
    """
    checker = workers.executor if isinstance(workers.executor, RenewedProcessPool) else InProcessExecutor()
    checker.submit(_check_params, overrides).result()
