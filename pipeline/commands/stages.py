"""List the stages of an output directory with their status: up to date, stale (and why), not run.

Example:
  python -m pipeline stages runs/tiny
"""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline import graph
from pipeline.engine.output_folder import read_run_record
from pipeline.engine.params import apply_overrides, default_params
from pipeline.engine.status import graph_status
from pipeline.io.capture import Capture
from pipeline.io.run_layout import RunLayout
from pipeline.terminal import printable


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out", type=Path, help="output directory of a previous `run`")


def main(args: argparse.Namespace) -> int:
    record = read_run_record(args.out)
    capture = Capture.open(record["capture"], allow_outside_paths=record.get("allow_outside_paths") is True)
    params = apply_overrides(default_params(graph.STAGES), record.get("params", {}),
                             source=f"{RunLayout(args.out).run_record}:")
    statuses = graph_status(graph.STAGES, capture, params, args.out)
    width = max(len(status.name) for status in statuses)
    for status in statuses:
        line = f"{status.name.ljust(width)}  {status.state}"
        print(printable(f"{line}: {status.reason}") if status.reason else line)  # reasons name files
    failure = record.get("failure")
    if record.get("state") == "failed" and isinstance(failure, dict):
        print(printable(f"the last run failed: {failure.get('error')}"))
    elif record.get("state") == "running":
        print("the last run has not finished (it is running, or it was interrupted: the next run resumes)")
    return 0
