"""Run the pipeline on a capture directory; stages already up to date are skipped.

Examples:
  python -m pipeline run data_samples/tiny --out runs/tiny
  python -m pipeline run data_samples/tiny --out runs/tiny --only silhouettes --set silhouettes.strong_threshold=10
  python -m pipeline run data_samples/tiny --out runs/tiny --from tracking --workers 2
  python -m pipeline run data_samples/tiny --out runs/tiny --scheduler local:2
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from calib.errors import InputError
from pipeline import graph
from pipeline.engine import run_warnings
from pipeline.engine.executors import Workers, make_executor, usable_cpus
from pipeline.engine.output_folder import check_own_files, output_lock, storage_error
from pipeline.engine.params import apply_all, default_params, read_overrides
from pipeline.engine.runner import Runner, StageOutcome, format_summary
from pipeline.engine.stage import select_stages
from pipeline.io.body_io import tracking_body
from pipeline.io.capture import Capture
from pipeline.io.export_io import check_cutoff, read_joints_csv
from pipeline.io.run_layout import BVH_FILE, C3D_FILE, JOINTS_FILE, RunLayout
from pipeline.report.tracking_summary import read_frame_statuses, summary_line
from pipeline.terminal import printable
from pipeline.worker_modules import WORKER_MODULES
from stages.reconstruction import check_tolerated_views


def add_arguments(parser: argparse.ArgumentParser) -> None:
    names = ", ".join(stage.name for stage in graph.STAGES)
    parser.add_argument("capture", type=Path, help="capture directory (with capture.yaml)")
    parser.add_argument("--out", type=Path, required=True, help="output directory (results and cache)")
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--only", metavar="STAGE", help=f"run only this stage ({names})")
    which.add_argument("--from", dest="start", metavar="STAGE", help="run this stage and everything after it")
    parser.add_argument("--to", dest="end", metavar="STAGE", help="run this stage and everything before it")
    parser.add_argument("--force", action="store_true", help="rerun the selected stages even if up to date")
    parser.add_argument("--config", type=Path, help="YAML file of parameters: {stage: {param: value}}")
    parser.add_argument("--set", dest="assignments", action="append", default=[], metavar="STAGE.PARAM=VALUE",
                        help="set one parameter (repeatable; applied after --config)")
    parser.add_argument("--workers", type=int, default=usable_cpus(),
                        help=f"local worker processes (1 = in this process; default: the CPUs this process may use, "
                             f"{usable_cpus()} here)")
    parser.add_argument("--scheduler", metavar="ADDRESS",
                        help="run per-frame work on Dask: a scheduler address, or local:N "
                             "for a local cluster of N processes")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    parser.add_argument("--allow-outside-paths", action="store_true",
                        help="let capture.yaml's calibration.path lead outside the capture directory "
                             "(refused by default: a capture.yaml from elsewhere could name any file)")


#: Exit status of a run that finished but whose result is not usable (:func:`unusable_result`); a user
#: mistake is 2.
UNUSABLE_RESULT = 3
#: What the line after Ctrl-C adds (:mod:`pipeline.cli`): every finished frame is kept, and the cache resumes it.
INTERRUPTED_HINT = "; the same command resumes from the frames already written"
#: A run estimating fewer than this share of the capture's frames has no usable result.
MIN_ESTIMATED_FRACTION = 0.5
#: What the export stage must have written for the run to count as usable.
EXPORTED_FILES = (JOINTS_FILE, BVH_FILE, C3D_FILE)


def unusable_result(export_dir: Path, frames: int) -> str | None:
    """Why a finished run's export in ``export_dir`` is not usable, in one line, or None when it is.

    Usable: every file of :data:`EXPORTED_FILES` written, and at least :data:`MIN_ESTIMATED_FRACTION` of
    the capture's ``frames`` estimated. A motion with most frames missing says "success" while it has
    lost the subject (out of view, silhouettes that disagree, a working volume that cuts them off).
    """
    joints = export_dir / JOINTS_FILE
    if joints.is_file() and len(joints.read_text(encoding="utf-8").strip().splitlines()) <= 1:
        # Its header alone, and no motion file beside it: the cause, not the missing files, is what to say.
        return (f"{joints}: no frame estimated (the subject was lost on every frame: the warnings above and "
                "the report say why)")
    missing = [name for name in EXPORTED_FILES if not (export_dir / name).is_file()]
    if missing:
        return f"{export_dir}: no {', '.join(missing)} written (expected every export of a finished run)"
    estimated = len(read_joints_csv(joints)[0])
    if estimated < MIN_ESTIMATED_FRACTION * frames:
        return (f"{export_dir / JOINTS_FILE}: only {estimated} of {frames} frames estimated (expected at least "
                f"half; `python -m pipeline stages` and the report say where the subject was lost)")
    return None


def closing_lines(out: Path, frames: Sequence[int], outcomes: Sequence[StageOutcome], warned: int) -> list[str]:
    """What the run's results amount to, below the table of stages: what the tracker did on the frames
    and why (:mod:`pipeline.report.tracking_summary`), how many warnings this run logged, and where the report is;
    the tracker's and the report's lines only when their stage was part of the run."""
    selected = {outcome.name for outcome in outcomes if outcome.action != "not selected"}
    lines = []
    layout = RunLayout(out)
    statuses = read_frame_statuses(layout.tracking_dir, frames) if "tracking" in selected else None
    if statuses is not None:
        lines.append(summary_line(statuses))
    if warned:
        lines.append(f"{warned} warning{'s' if warned > 1 else ''} in this run "
                     f"(above, a message repeated on consecutive frames once; every warning behind the results: "
                     f"{layout.warnings} and the report)")
    report = layout.report
    if "export" in selected and report.is_file():
        lines.append(f"report: {report}")
    return lines


def read_params(config: Path | None, assignments: Sequence[str]) -> dict[str, Any]:
    """Every stage's parameters: the defaults, then the ``--config`` file's, then each ``--set`` assignment."""
    return stage_params(read_overrides(config, assignments))


def stage_params(overrides: Iterable[tuple[str, Mapping[str, Any]]]) -> dict[str, Any]:
    """Every stage's parameters: the defaults with ``overrides`` (:func:`~pipeline.engine.params.read_overrides`)
    applied in turn, and checked before any work, a body file given to the tracker included."""
    params = apply_all(default_params(graph.STAGES), overrides)
    tracking_body(params["tracking"])
    return params


@dataclass(frozen=True)
class RunResult:
    """What one run of a capture did: each stage's outcome, the capture's frame numbers, how many warnings it
    logged, and ``problem``, why the result is not usable in one line (:func:`unusable_result`; None when it
    is, or no export was asked for)."""

    outcomes: list[StageOutcome]
    frame_numbers: list[int]
    warnings: int
    problem: str | None

    @property
    def frames(self) -> int:
        return len(self.frame_numbers)


def run_capture(capture_dir: Path, out: Path, params: Mapping[str, Any], workers: Workers, *,
                selected: Collection[str] | None = None, force: bool = False, show_progress: bool = False,
                allow_outside_paths: bool = False) -> RunResult:
    """Run the ``selected`` stages (default all) of ``capture_dir`` into ``out``, holding its lock.

    Raises
    ------
    InputError
        For a mistake in the capture or the output folder, and for a full, read-only or forbidden disk
        (:func:`~pipeline.engine.output_folder.storage_error`), from this process or a worker.
    """
    try:
        with run_warnings.collecting() as warnings:
            capture = Capture.open(capture_dir, allow_outside_paths=allow_outside_paths)
            step = capture.frame_numbers[1] - capture.frame_numbers[0] if len(capture.frame_numbers) > 1 else 1
            check_cutoff(params["export"].filter_cutoff_hz, capture.fps / step)  # before any work
            check_tolerated_views(params["reconstruction"].tolerated_views, len(capture.rig))
            runner = Runner(graph.STAGES, capture, params, out, workers, show_progress,  # refuses --out in the capture
                            record_facts={"allow_outside_paths": allow_outside_paths})
            with output_lock(out):
                check_own_files(out)
                warnings.attach(out)
                outcomes = runner.run(selected, force=force)
    except OSError as error:  # a full or read-only disk, from this process or a worker: the user's to fix
        problem = storage_error(error, out)
        if problem is None:
            raise
        raise problem from None
    frames = list(capture.frame_numbers)
    exported = any(outcome.name == "export" and outcome.action != "not selected" for outcome in outcomes)
    problem = unusable_result(RunLayout(out).export_dir, len(frames)) if exported else None
    return RunResult(outcomes, frames, len(warnings.records), problem)


def main(args: argparse.Namespace) -> int:
    if args.only and args.end:
        raise InputError(f"--only {args.only} --to {args.end}: cannot be combined "
                         "(expected --only, or --from and/or --to)")
    params = read_params(args.config, args.assignments)
    selected = select_stages(graph.STAGES, only=args.only, start=args.start, end=args.end)
    # The workers start first: their start-up overlaps the checks of the capture.
    with make_executor(args.workers, args.scheduler, preload=WORKER_MODULES) as workers:
        result = run_capture(args.capture, args.out, params, workers, selected=selected, force=args.force,
                             show_progress=not args.quiet and sys.stderr.isatty(),
                             allow_outside_paths=args.allow_outside_paths)
    print(format_summary(result.outcomes))
    for line in closing_lines(Path(args.out), result.frame_numbers, result.outcomes, result.warnings):
        print(printable(line))  # the report's path is the user's, which may hold anything
    if result.problem is not None:
        print(f"error: {result.problem}", file=sys.stderr)
        return UNUSABLE_RESULT
    return 0
