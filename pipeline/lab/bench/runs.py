"""Running the whole pipeline as a user does (``python -m pipeline run``) and measuring it.

The run is a child process, waited for with ``os.wait4``: its wall time is everything a user waits for
(interpreter start, imports, video decoding, all five stages, writing), and its resource usage is that of
the child and of every worker process it reaped, so ``ru_maxrss`` is the peak resident memory of the
largest process of that run alone (Linux reports it in kilobytes) — not of the benchmark's other runs.

One Linux subtlety decides how the child is started: a process's ``ru_maxrss`` starts at the resident size
of the process it was forked from (the forked memory's high-water mark is carried through ``exec``). Forked
straight from the benchmark, which holds hundreds of megabytes, every run would report at least that. So a
tiny launcher interpreter (:data:`LAUNCHER`) starts the run and reports the wait4 numbers; its own size, a
few megabytes, is the floor of the measurement.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from pipeline import graph
from pipeline.io.run_layout import RunLayout, read_manifest_file

#: The repository root: the child runs there so that ``python -m pipeline`` imports this checkout.
REPO = Path(__file__).resolve().parents[3]
#: Lines of a failed run's log kept in the results.
LOG_TAIL_LINES = 8
#: ``python -c LAUNCHER <report.json> <command...>``: run the command, write its exit status, wall seconds
#: and peak resident memory (kB) as JSON. Kept to the standard library so that the launcher stays small.
LAUNCHER = """
import json, os, subprocess, sys, time
started = time.perf_counter()
child = subprocess.Popen(sys.argv[2:])
_, status, usage = os.wait4(child.pid, 0)
seconds = time.perf_counter() - started
with open(sys.argv[1], "w") as report:
    json.dump({"returncode": os.waitstatus_to_exitcode(status), "seconds": seconds, "maxrss_kb": usage.ru_maxrss},
              report)
"""


@dataclass(frozen=True)
class RunMeasure:
    """One ``python -m pipeline run``: outcome, wall time, peak memory and the stages' own timings.

    ``stage_seconds`` maps stage name to the seconds its manifest records (0 for a stage skipped as up to
    date); ``frames`` is the number of frames the capture selects; ``load`` the 1-minute load average just
    before the run (other programs on the machine slow it down).
    """

    returncode: int
    seconds: float
    peak_rss_mb: float
    frames: int
    stage_seconds: dict[str, float]
    load: float
    log_tail: str

    @property
    def ok(self) -> bool:
        return self.returncode == 0

    def to_dict(self) -> dict:
        return {"ok": self.ok, "returncode": self.returncode, "seconds": self.seconds,
                "peak_rss_mb": self.peak_rss_mb, "frames": self.frames, "stage_seconds": self.stage_seconds,
                "load": self.load, **({} if self.ok else {"log_tail": self.log_tail})}


def run_command(capture: Path, out: Path, workers: int, settings: Sequence[str] = ()) -> list[str]:
    """The command line that runs the pipeline on ``capture`` into ``out``, with ``settings`` (``stage.name=value``
    each, as ``--set`` takes them)."""
    return [sys.executable, "-m", "pipeline", "run", str(capture), "--out", str(out), "--workers", str(workers),
            "--quiet", *(argument for setting in settings for argument in ("--set", setting))]


def stage_timings(out: Path) -> dict[str, float]:
    """Seconds each stage took according to its manifest (0 when a stage has no readable manifest)."""
    seconds = {}
    for stage in graph.STAGES:
        try:
            seconds[stage.name] = float(read_manifest_file(RunLayout(out).stage_dir(stage.name))["timing"]["seconds"])
        except (OSError, ValueError, KeyError, TypeError):  # DamagedFileError is a ValueError; None has no keys
            seconds[stage.name] = 0.0
    return seconds


def run_pipeline(capture: Path, out: Path, *, workers: int, frames: int, fresh: bool,
                 settings: Sequence[str] = ()) -> RunMeasure:
    """Run the pipeline on ``capture`` into ``out`` with ``settings`` (`run_command`) and measure it (``fresh``: delete
    ``out`` first).

    The run's output goes to ``<out>.log``; a failure is reported in the result, not raised, so one bad
    capture does not stop a benchmark.
    """
    out = Path(out)
    if fresh:
        shutil.rmtree(out, ignore_errors=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    log_path = out.parent / f"{out.name}.log"
    report_path = out.parent / f"{out.name}.measure.json"
    report_path.unlink(missing_ok=True)
    load = os.getloadavg()[0]
    with open(log_path, "w") as log:
        subprocess.run([sys.executable, "-c", LAUNCHER, str(report_path),
                        *run_command(capture, out, workers, settings)],
                       cwd=REPO, stdout=log, stderr=subprocess.STDOUT, check=True)
    report = json.loads(report_path.read_text())
    tail = "\n".join(log_path.read_text(errors="replace").splitlines()[-LOG_TAIL_LINES:])
    return RunMeasure(returncode=report["returncode"], seconds=report["seconds"],
                      peak_rss_mb=report["maxrss_kb"] / 1024.0, frames=frames, stage_seconds=stage_timings(out),
                      load=load, log_tail=tail)
