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
from pathlib import Path

from calib.errors import InputError
from pipeline import graph
from pipeline.capture import Capture
from pipeline.executors import make_executor
from pipeline.params import apply_overrides, default_params, parse_assignments, read_config
from pipeline.runner import Runner, format_summary, output_lock, select_stages, storage_error


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
    parser.add_argument("--workers", type=int, default=1, help="local worker processes (1 = in this process)")
    parser.add_argument("--scheduler", metavar="ADDRESS",
                        help="run per-frame work on Dask: a scheduler address, or local:N "
                             "for a local cluster of N processes")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    parser.add_argument("--allow-outside-paths", action="store_true",
                        help="let capture.yaml's calibration.path lead outside the capture directory "
                             "(refused by default: a capture.yaml from elsewhere could name any file)")


def main(args: argparse.Namespace) -> int:
    if args.only and args.end:
        raise InputError(f"--only {args.only} --to {args.end}: cannot be combined "
                         "(expected --only, or --from and/or --to)")
    stages = graph.STAGES
    params = default_params(stages)
    if args.config is not None:
        params = apply_overrides(params, read_config(args.config), source=f"{args.config}:")
    params = apply_overrides(params, parse_assignments(args.assignments), source="--set")
    selected = select_stages(stages, only=args.only, start=args.start, end=args.end)

    show_progress = not args.quiet and sys.stderr.isatty()
    try:
        # The workers start first: their start-up overlaps the checks of the capture.
        with make_executor(args.workers, args.scheduler, preload=graph.WORKER_MODULES) as workers:
            capture = Capture.open(args.capture, allow_outside_paths=args.allow_outside_paths)
            runner = Runner(stages, capture, params, args.out, workers, show_progress,  # refuses --out in the capture
                            record_facts={"allow_outside_paths": args.allow_outside_paths})
            with output_lock(args.out):
                outcomes = runner.run(selected, force=args.force)
    except OSError as error:  # a full or read-only disk, from this process or a worker: the user's to fix
        problem = storage_error(error, args.out)
        if problem is None:
            raise
        raise problem from None
    print(format_summary(outcomes))
    return 0
