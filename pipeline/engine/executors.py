"""Where per-frame work runs: in this process, in a local process pool, or on a Dask cluster.

All three are ``concurrent.futures.Executor`` objects, so a stage submits chunks of frames the same
way whatever runs them (see :func:`pipeline.engine.context.StageContext.map_frames`). A call in another process
(:func:`call_logged`) returns the warnings it logged, and :func:`relog` logs them again here, so that they
are shown and collected (:mod:`pipeline.engine.run_warnings`) like this process's own:

- ``workers=1``: :class:`InProcessExecutor`, calls run immediately in this process. No
  pickling, easiest to debug, and exceptions carry their full traceback. (``run``'s ``--workers`` defaults to
  :func:`usable_cpus` instead: a user's first run should keep every core busy.)
- ``workers=N > 1``: ``ProcessPoolExecutor`` whose processes are forks of multiprocessing's fork server
  (:func:`start_worker_server`), at a lower scheduling priority than this one, which runs the sequential
  tracker. The server is a clean process that imports the tasks' modules once, so every worker starts
  with them in memory; forking this process instead is not safe with the threads that progress bars and
  OpenCV start. Where there is no fork server (Windows), or it cannot start, ``spawn``: each worker
  imports them itself.
- ``scheduler="local:N"``: a Dask ``LocalCluster(n_workers=N, threads_per_worker=1, processes=True)``
  started for this run; ``scheduler="tcp://host:port"``: an existing Dask scheduler. Both go through
  ``Client.get_executor(pure=False)`` (``pure=False``: a chunk re-submitted after a failure must run
  again, not be served from Dask's memory of the failed key). Dask is imported only here, only when
  asked for, so it stays an optional dependency.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import importlib
import logging
import multiprocessing
import multiprocessing.forkserver
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from calib.errors import InputError

log = logging.getLogger(__name__)

#: Seconds to wait for a Dask scheduler to answer before giving up with a clear error.
DASK_CONNECT_TIMEOUT_S = 10


class InProcessExecutor(cf.Executor):
    """An executor that runs each call immediately, in the calling thread (``--workers 1``)."""

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> cf.Future:
        future: cf.Future = cf.Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except Exception as error:  # handed to the caller through the future, like a pool does
            future.set_exception(error)
        return future


class _Keep(logging.Handler):
    """Keeps the fields of each record it handles (message formatted: arguments need not pickle)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.records: list[dict] = []

    def emit(self, record: logging.LogRecord) -> None:
        fields = {key: value for key, value in vars(record).items()
                  if key in ("name", "levelno", "levelname", "pathname", "filename", "module", "lineno", "funcName",
                             "created", "msecs", "relativeCreated")}
        self.records.append({**fields, "msg": record.getMessage(), "args": None,
                             "template": record.msg if isinstance(record.msg, str) else None})


def call_logged(fn: Callable[[Any], Any], argument: Any) -> list[dict]:
    """``fn(argument)`` in a worker process, returning the WARNING records it logged (for :func:`relog`)
    instead of its result, which per-frame tasks do not have."""
    keep = _Keep()
    root = logging.getLogger()
    root.addHandler(keep)
    try:
        fn(argument)
    finally:
        root.removeHandler(keep)
    return keep.records


def relog(records: Sequence[dict]) -> None:
    """Log again, in this process and thread, the records a worker's :func:`call_logged` returned."""
    for fields in records:
        logging.getLogger(fields["name"]).handle(logging.makeLogRecord(fields))


@dataclass(frozen=True)
class Workers:
    """An executor and how many calls it runs at once (to size chunks of frames)."""

    executor: cf.Executor
    count: int
    description: str

    @property
    def in_process(self) -> bool:
        """Whether calls run in this process (their log records need no :func:`relog`)."""
        return isinstance(self.executor, InProcessExecutor)


def usable_cpus() -> int:
    """The CPUs this process may run on (its affinity, which a container or ``taskset`` narrows), at least 1:
    the default of ``--workers``, as the per-frame stages keep every core busy."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # no affinity on this platform (macOS, Windows)
        return max(1, os.cpu_count() or 1)


@contextlib.contextmanager
def make_executor(workers: int = 1, scheduler: str | None = None, *,
                  preload: Sequence[str] = ()) -> Iterator[Workers]:
    """Start the executor asked for on the command line; shut it down when the block ends.

    Parameters
    ----------
    workers : int
        ``--workers``: 1 runs in this process, N > 1 in a pool of N processes. Ignored with a scheduler.
    scheduler : str or None
        ``--scheduler``: ``"local:N"`` for a Dask LocalCluster of N single-threaded worker processes,
        or the address of a running Dask scheduler (``"tcp://10.0.0.5:8786"``).
    preload : sequence of str
        Modules a local pool's processes need (those of the per-frame tasks), imported by the fork server
        before the first process starts (unless :func:`start_worker_server` started it already), or by
        each spawned process as soon as it starts.
    """
    if scheduler:
        with _dask_executor(scheduler) as dask_workers:
            yield dask_workers
        return
    if not isinstance(workers, int) or workers < 1:
        raise InputError(f"--workers {workers!r}: expected a positive whole number of processes")
    if workers == 1:
        yield Workers(InProcessExecutor(), 1, "in-process")
        return
    context = multiprocessing.get_context("forkserver" if start_worker_server(preload) else "spawn")
    pool = cf.ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=_yield_to_parent)
    for _ in range(workers):  # starts the processes now; a failed import shows again in the first real task
        pool.submit(_import, tuple(preload))
    try:
        yield Workers(pool, workers, f"{workers} local processes")
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def start_worker_server(preload: Sequence[str]) -> bool:
    """Start the fork server that a local pool's processes are forked from, importing ``preload``; whether
    this platform has one.

    A server started already (by an earlier call) keeps its modules, and a pool's processes import any
    other themselves. The server's imports take about half a second; started before this process's own
    imports, they overlap them (see :func:`pipeline.cli.start_workers_early`).
    """
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return False
    multiprocessing.get_context("forkserver").set_forkserver_preload(list(preload))
    try:
        multiprocessing.forkserver.ensure_running()
    except OSError as error:  # its socket lives in the temporary folder, which may be full or read-only
        log.warning("no fork server for the worker processes (%s); they are spawned instead", error)
        return False
    return True


#: Niceness a local pool's processes add to their own (see :func:`_yield_to_parent`).
WORKER_NICENESS = 10


def _yield_to_parent() -> None:
    """Lower this worker process's scheduling priority below the parent's.

    The parent runs the sequential stage (the tracker) alongside the per-frame stage whose frames it
    reads, so N workers and the parent compete for the cores. The tracker is what the run waits for;
    at equal priority it gets 2/3 of a core on two cores, and it finishes alone after the workers are
    done. Behind it, the workers take whatever CPU it leaves and all of it when the parent is idle.
    """
    os.nice(WORKER_NICENESS)


def _import(modules: tuple[str, ...]) -> None:
    for module in modules:
        importlib.import_module(module)


def local_count(scheduler: str) -> int:
    """N of a ``--scheduler local:N``, checked."""
    count = scheduler.removeprefix("local:")
    if not count.isdigit() or int(count) < 1:
        raise InputError(f"--scheduler {scheduler}: expected local:N with N a positive whole number")
    return int(count)


@contextlib.contextmanager
def _dask_executor(scheduler: str) -> Iterator[Workers]:
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise InputError(f"--scheduler {scheduler}: Dask is not installed "
                         "(expected `pip install 'hnmocap[dask]'`)") from None
    with contextlib.ExitStack() as stack:
        if scheduler.startswith("local:"):
            cluster = stack.enter_context(LocalCluster(n_workers=local_count(scheduler), threads_per_worker=1,
                                                       processes=True, dashboard_address=None))
            client = stack.enter_context(Client(cluster))
        else:
            try:
                client = stack.enter_context(Client(scheduler, timeout=f"{DASK_CONNECT_TIMEOUT_S}s"))
            except (OSError, ValueError, TypeError) as error:
                raise InputError(f"--scheduler {scheduler}: cannot connect ({error}) "
                                 "(expected the address of a running Dask scheduler, or local:N)") from None
        threads = sum(worker["nthreads"] for worker in client.scheduler_info()["workers"].values())
        executor = client.get_executor(pure=False)
        yield Workers(executor, max(threads, 1), f"Dask at {client.scheduler.address} ({threads} threads)")
