"""Run the pipeline on every capture under a folder (a study), whole captures in parallel; a table of how each went.

Examples:
  python -m pipeline batch study --out runs/study                       # one capture after the other
  python -m pipeline batch study --out runs/study --scheduler local:2   # two at a time on this machine
  python -m pipeline batch study --out runs/study --scheduler tcp://10.0.0.5:8786 --set tracking.distance=points

A capture is any folder under ROOT holding a capture.yaml, at any depth (session/participant/trial...); the
folders inside a capture, hidden folders and --out are not searched. Each capture runs as `python -m pipeline
run` would, with the same cache and parameters, into OUT/<its path under ROOT>: what is up to date is skipped,
what a failed or interrupted batch left is resumed. A capture that fails does not stop the others; the batch
ends with a table on stdout and OUT/batch.csv (capture, status, frames, estimated, mpjpe_mm where the capture
has groundtruth/joints.csv, seconds, error), and exits with status 3 if any capture failed.

--scheduler local:N runs N captures at a time in N processes of this machine (default local:1: one after the
other, in this process); an address runs each capture as one task on that Dask cluster, whose workers must
see ROOT and OUT at the same paths and have this package installed (`pip install 'hnmocap[dask]'`). A
capture's own per-frame stages run in its task's process, one frame after the other.
"""

from __future__ import annotations

import argparse
import csv
import io
import logging
import math
import os
import sys
from collections.abc import Mapping, Sequence
from dataclasses import fields
from pathlib import Path
from typing import Any

# This module imports only light modules at its top, so that a local pool's processes start (in main()) before
# this process loads the heavier ones it needs itself (OpenCV, through the output folder's checks; tqdm): those are
# imported where they are used, and their loading overlaps the workers' start-up.
from calib.errors import InputError
from pipeline.commands.batch_workers import (
    CaptureJob,
    CaptureReport,
    capture_workers,
    check_params,
    run_jobs,
)
from pipeline.engine.params import read_overrides
from pipeline.io import atomic
from pipeline.terminal import printable

log = logging.getLogger(__name__)

#: What makes a folder a capture.
CAPTURE_YAML = "capture.yaml"
#: The batch's table of captures, in OUT.
BATCH_CSV = "batch.csv"
#: Exit status when some capture failed: the batch finished, not every result is usable (as `run`'s 3).
SOME_FAILED = 3
#: What the line after Ctrl-C adds (:mod:`pipeline.cli`): each capture resumes as a `run` does.
INTERRUPTED_HINT = "; the same command resumes each capture from the frames already written"
#: A capture's folders of media (see docs/capture_format.md), whose size says how long it takes.
MEDIA_FOLDERS = ("images", "videos", "silhouettes")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("root", type=Path, help="folder of captures (each a folder with capture.yaml), at any depth")
    parser.add_argument("--out", type=Path, required=True,
                        help="output folder: one run folder per capture at its path under ROOT, and batch.csv")
    parser.add_argument("--scheduler", default="local:1", metavar="ADDRESS",
                        help="local:N for N captures at a time on this machine (default local:1), or the address "
                             "of a Dask scheduler (tcp://host:port) for one task per capture on its workers")
    parser.add_argument("--config", type=Path, help="YAML file of parameters: {stage: {param: value}}")
    parser.add_argument("--set", dest="assignments", action="append", default=[], metavar="STAGE.PARAM=VALUE",
                        help="set one parameter for every capture (repeatable; applied after --config)")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--allow-outside-paths", action="store_true",
                        help="let a capture.yaml's calibration.path lead outside its capture folder "
                             "(a calibration shared by a session's trials, say)")


# ---------------------------------------------------------------------------------------------
# Finding the captures


def find_captures(root: Path, *, skip: Path | None = None) -> list[Path]:
    """Every folder under ``root`` holding a capture.yaml, in order of their paths.

    The search does not enter a capture (its videos and calibration are not captures of their own), a
    hidden folder (``.git``), or ``skip`` (the batch's output folder when it lies under ``root``: its run
    folders hold no capture.yaml, but a study can be large). Links to folders are followed, each real
    folder visited once, so that a study assembled from links works and a link cycle ends.

    Raises
    ------
    InputError
        When ``root`` is not a folder, is itself a capture (``python -m pipeline run`` is for one), or holds none.
    """
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root}: not a folder (expected a folder of captures, each a folder holding a "
                         f"{CAPTURE_YAML})")
    if (root / CAPTURE_YAML).is_file():
        raise InputError(f"{root}: is itself a capture (expected a folder of captures; "
                         "`python -m pipeline run` processes one capture)")
    skipped = Path(skip).resolve() if skip is not None else None
    found, visited = [], set()
    for folder, subfolders, files in os.walk(root, followlinks=True):
        real = Path(folder).resolve()
        if real in visited or real == skipped:
            subfolders.clear()
            continue
        visited.add(real)
        if CAPTURE_YAML in files:
            found.append(Path(folder))
            subfolders.clear()
        else:
            subfolders[:] = sorted(name for name in subfolders if not name.startswith("."))
    if not found:
        raise InputError(f"{root}: no capture found (expected folders holding a {CAPTURE_YAML}, at any depth)")
    return sorted(found, key=lambda path: path.relative_to(root).parts)


# ---------------------------------------------------------------------------------------------
# The table


def _cell(value: Any, digits: int = 1) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return "" if not math.isfinite(value) else f"{value:.{digits}f}"
    return str(value)


def format_csv(reports: Sequence[CaptureReport]) -> str:
    """batch.csv: one row per capture, the fields of :class:`CaptureReport`; empty cells for unknown values."""
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow([field.name for field in fields(CaptureReport)])
    writer.writerows([_cell(getattr(report, field.name)) for field in fields(CaptureReport)] for report in reports)
    return text.getvalue()


def format_table(reports: Sequence[CaptureReport]) -> str:
    """The table the batch prints: the rows of batch.csv, aligned, "-" for unknown values."""
    from pipeline.engine.runner import format_columns  # see the imports at the top

    header = ("capture", "status", "frames", "estimated", "MPJPE mm", "seconds", "error")
    rows = [header] + [tuple(printable(_cell(getattr(report, field.name))) or "-" for field in fields(CaptureReport))
                       for report in reports]
    return format_columns(rows, right=range(2, 6))


def describe(report: CaptureReport) -> str:
    """One capture's log line: ``"s1/p01/t2: ran in 12.3 s, 56 of 56 frames estimated, MPJPE 21.4 mm"``."""
    if not report.ok:
        return f"{report.capture}: failed: {report.error}"
    scored = f", MPJPE {report.mpjpe_mm:.1f} mm" if report.mpjpe_mm is not None else ""
    return (f"{report.capture}: {report.status} in {report.seconds:.1f} s, {report.estimated} of {report.frames} "
            f"frames estimated{scored}")


# ---------------------------------------------------------------------------------------------
# The command


def make_jobs(root: Path, captures: Sequence[Path], out: Path, overrides: Sequence[tuple[str, Mapping[str, Any]]], *,
              allow_outside_paths: bool, worker_log_level: int | None) -> list[CaptureJob]:
    """One job per capture, into ``out/<its path under root>``; refuses, before any run, an ``out`` that
    overlaps a capture (see :func:`~pipeline.engine.output_folder.check_output_folder`)."""
    from pipeline.engine.output_folder import check_output_folder  # see the imports at the top

    if Path(out).resolve() == Path(root).resolve():
        raise InputError(f"--out {out}: is the folder of captures (expected a separate output folder)")
    jobs = []
    for capture in captures:
        relative = capture.relative_to(root)
        check_output_folder(out / relative, capture)
        jobs.append(CaptureJob(relative.as_posix(), capture.absolute(), (out / relative).absolute(), overrides,
                               allow_outside_paths, worker_log_level))
    return jobs


def media_bytes(capture: Path) -> int:
    """Bytes of a capture's media (:data:`MEDIA_FOLDERS`), links followed: roughly how much work it is."""
    return sum(os.stat(Path(parent) / name).st_size for folder in MEDIA_FOLDERS
               for parent, _, files in os.walk(capture / folder, followlinks=True)
               for name in files if os.path.exists(Path(parent) / name))


def largest_first(jobs: Sequence[CaptureJob]) -> list[CaptureJob]:
    """``jobs`` in the order to start them: the captures with the most media first (ties in their order).

    Started last, a long capture would run alone at the end while the other workers idle; largest first, the
    short ones fill in around the long ones. A capture's time grows with its frames, cameras and pixels, and so
    do its media's bytes, roughly (a capture.yaml that selects a part of its frames is not looked at).
    """
    return sorted(jobs, key=lambda job: media_bytes(job.capture), reverse=True)


def main(args: argparse.Namespace) -> int:
    # The workers start first: their start-up overlaps this process's imports and checks.
    with capture_workers(args.scheduler) as workers:
        from tqdm import tqdm  # see the imports at the top
        from tqdm.contrib.logging import logging_redirect_tqdm

        from pipeline.engine.output_folder import output_lock

        overrides = read_overrides(args.config, args.assignments)
        # Workers show warnings only (-v: everything): the lines of several captures at once would bury the bar.
        worker_level = logging.DEBUG if log.isEnabledFor(logging.DEBUG) else logging.WARNING
        in_process = workers.in_process
        jobs = make_jobs(args.root, find_captures(args.root, skip=args.out), args.out, overrides,
                         allow_outside_paths=args.allow_outside_paths,
                         worker_log_level=None if in_process else worker_level)
        check_params(workers, overrides)  # waits for the pool's first process: this process's checks come first
        reports = {job.name: CaptureReport(job.name, "not run") for job in jobs}
        table_path = args.out / BATCH_CSV
        show_progress = not args.quiet and sys.stderr.isatty()
        with output_lock(args.out), logging_redirect_tqdm(), tqdm(
                total=len(jobs), desc="batch", unit="capture", file=sys.stderr, disable=not show_progress,
                dynamic_ncols=True) as bar:
            log.info("%d captures, %s", len(jobs), workers.description)
            atomic.write_text(table_path, format_csv(list(reports.values())))  # no row of an earlier batch stays

            def record(report: CaptureReport) -> None:
                reports[report.capture] = report
                atomic.write_text(table_path, format_csv(list(reports.values())))
                (log.info if report.ok else log.warning)(describe(report))
                bar.update(1)

            run_jobs(largest_first(jobs), workers, record)
    print(format_table(list(reports.values())))
    failed = [report for report in reports.values() if not report.ok]
    if failed:
        print(f"error: {len(failed)} of {len(reports)} captures failed (the error column says why; "
              f"rerunning the batch retries them): {table_path}", file=sys.stderr)
        return SOME_FAILED
    print(f"written: {table_path}")
    return 0
