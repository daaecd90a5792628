"""The benchmark suite behind ``python -m pipeline bench``: run suites, keep results, judge targets, write tables.

``<out>/results.json`` holds one section per suite (:data:`SUITES`: ``speed``, ``unseen``, ``paper``, ``foreign``,
...); running one suite replaces its own section and keeps the others (a suite skipped for want of its data keeps
its old one), so the file always shows the latest measurement of each, and every section says how it was made
(``command``, ``quick``, and ``made``: date, commit, seconds, machine load).
``<out>/results.md`` is drawn from results.json by :func:`format_results` alone, with the targets the project
is judged by (:data:`~pipeline.lab.bench.targets.TARGETS`) marked met or missed: the tables are drawn
by :mod:`pipeline.lab.bench.tables`.
"""

from __future__ import annotations

import json
import math
import os
import platform
import resource
import subprocess
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from pipeline.commands.warmup import ensure_compiled
from pipeline.io import atomic
from pipeline.lab.bench import figures
from pipeline.lab.bench.tables import (
    EXPORTS_NOTES,
    FOREIGN_NOTES,
    PAPER_NOTES,
    ROBUSTNESS_NOTES,
    SPEED_NOTES,
    UNSEEN_NOTES,
    format_exports,
    format_foreign,
    format_paper,
    format_robustness,
    format_speed,
    format_targets,
    format_unseen,
    provenance,
)
from pipeline.lab.bench.targets import MPJPE_MM, WORST_FRAME_MM, scored_rows

SUITES = ("speed", "unseen", "paper", "foreign", "robustness", "exports", "calibration", "batch")
RESULTS_JSON, RESULTS_MD = "results.json", "results.md"


class SuiteSkipped(Exception):
    """A suite has nothing to measure on this machine (e.g. its captures are absent); the message says why."""


@dataclass(frozen=True)
class BenchOptions:
    """Where the benchmark writes and how big it is.

    ``captures``: cache of rendered synthetic captures; ``workers``: processes for the pipeline runs,
    renderings and paper sweeps.
    """

    out: Path
    captures: Path
    quick: bool
    workers: int

    def command(self, suite: str) -> str:
        """The command line that reproduces one suite's section."""
        parts = ["python -m pipeline bench", f"--out {self.out}", f"--suite {suite}"]
        if self.captures != self.out / "captures":
            parts.append(f"--captures {self.captures}")
        if self.workers != 2:
            parts.append(f"--workers {self.workers}")
        if self.quick:
            parts.append("--quick")
        return " ".join(parts)



def format_results(results: dict, figure_links: dict[str, str] | None = None, *, source: Path | None = None) -> str:
    """The whole results page from a results.json dictionary (``figure_links``: suite -> image path)."""
    from pipeline.lab.bench.batch import BATCH_NOTES, format_batch  # here, like the suites in suite_runners

    links = figure_links or {}
    origin = f" from `{source}`" if source is not None else ""
    lines = ["# Benchmark results", "",
             f"Drawn by `python -m pipeline bench`{origin}; each section names the command that measured it. "
             "`make bench` runs every suite (`ARGS=\"--suite NAME\"` for one of "
             f"{', '.join(SUITES)}, `--quick` for a smoke run); `python -m pipeline bench --report-only --docs "
             "docs` redraws docs/results.md and docs/figures/ from the stored results without measuring again. "
             "Comparisons measured by hand, each with its command, are in docs/results_by_hand.md (not redrawn). "
             "Each section's first line gives the time this machine took, before and after the suite, for a fixed "
             "workload of interpreted Python and small numpy operations (`suite.reference_seconds`): the machine's "
             "speed drifts, and speed figures from different runs compare after scaling by it.",
             "", "## Targets", "", format_targets(results)]
    from pipeline.lab.bench.calibration import CALIBRATION_NOTES, format_calibration

    sections = (("speed", "Speed", SPEED_NOTES, format_speed),
                ("unseen", "Accuracy on unseen captures", UNSEEN_NOTES, format_unseen),
                ("paper", "The paper's experiments (Horaud et al. 2009, Sec. 4.1, Fig. 4)", PAPER_NOTES, None),
                ("foreign", "Accuracy on captures made by another program", FOREIGN_NOTES, format_foreign),
                ("robustness", "Robustness: the foreign captures perturbed, one change at a time", ROBUSTNESS_NOTES,
                 format_robustness),
                ("exports", "Exports: agreement, smoothing, confidence", EXPORTS_NOTES, format_exports),
                ("calibration", "Calibrating a studio from board recordings", CALIBRATION_NOTES, format_calibration),
                ("batch", "A study in one command: whole captures in parallel", BATCH_NOTES, format_batch))
    for suite, title, notes, body in sections:
        if suite not in results:
            continue
        lines += ["", f"## {title}", "", provenance(results[suite]), "", notes, ""]
        if body is None:
            lines.append(format_paper(results[suite], links.get(suite)))
            continue
        if suite in links:
            lines += [f"![{suite}]({links[suite]})", ""]
        lines.append(body(results[suite]))
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------
# Running


def git_commit() -> str:
    """Short hash of HEAD, with "+dirty" when tracked files differ from it (or "unknown")."""
    root = Path(__file__).resolve().parents[3]
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The processor's model name ("AMD EPYC"), from `cpuinfo` where Linux has it, else what `platform` knows.

    Figures measured in different sessions may come from different machines behind the same core count:
    the model says whether two speeds can be compared.
    """
    try:
        lines = cpuinfo.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        lines = []
    names = [line.split(":", 1)[1].strip() for line in lines if line.startswith("model name") and ":" in line]
    return next((name for name in names if name), None) or platform.processor() or platform.machine() or "unknown"


def reference_seconds(repeats: int = 5) -> float:
    """Seconds this process takes for a fixed mix of interpreted Python and small numpy operations (the
    fastest of ``repeats``).

    The per-frame code spends most of its time in such small operations, and this machine's speed drifts by
    tens of percent within an hour and by twice that between days at the same load average (docs/results_by_hand.md),
    so a speed figure is read beside the time of this workload measured with it: two figures compare after
    scaling by their reference times. The fastest repeat is kept, a momentary stall of the machine being noise.
    """
    best = math.inf
    for _ in range(repeats):
        started = time.perf_counter()
        total = 0
        for i in range(300_000):
            total += i * i % 7
        a = np.linspace(0.0, 1.0, 64)
        b = a[::-1].copy()
        for _ in range(20_000):
            a = np.sqrt(a * b + 1.0) - 0.5
        best = min(best, time.perf_counter() - started)
    return best


def load_results(path: Path) -> dict:
    """A previous results.json, or an empty dict when there is none or it is unreadable."""
    try:
        results = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return {}
    return results if isinstance(results, dict) else {}


def peak_memory_mb() -> dict:
    """Peak resident memory of this process and of its largest reaped child (MB; Linux reports kB)."""
    return {"self_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "children_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0}


def suite_runners() -> dict[str, Callable[..., dict]]:
    """Suite name -> ``run(out, captures, *, quick, workers) -> section`` (imported when needed)."""
    from pipeline.lab.bench.batch import run_batch_suite
    from pipeline.lab.bench.calibration import run_calibration
    from pipeline.lab.bench.exports import run_exports
    from pipeline.lab.bench.foreign import run_foreign
    from pipeline.lab.bench.paper import run_paper
    from pipeline.lab.bench.robustness import run_robustness
    from pipeline.lab.bench.speed import run_speed
    from pipeline.lab.bench.unseen import run_unseen

    return {"speed": run_speed, "unseen": run_unseen, "paper": run_paper, "foreign": run_foreign,
            "robustness": run_robustness, "exports": run_exports, "calibration": run_calibration,
            "batch": run_batch_suite}


def draw_figures(results: dict, folder: Path) -> dict[str, Path]:
    """The PNGs of the suites present in ``results``, drawn into ``folder`` (suite -> path)."""
    drawn = {}
    if "speed" in results and results["speed"].get("long", {}).get("ok"):
        drawn["speed"] = figures.speed_figure(results["speed"], folder / "speed_stages.png")
    if "unseen" in results and scored_rows(results["unseen"]):
        drawn["unseen"] = figures.unseen_figure(results["unseen"], folder / "unseen_mpjpe.png",
                                                target_mm=MPJPE_MM, worst_target_mm=WORST_FRAME_MM)
    if "paper" in results:
        drawn["paper"] = figures.paper_figure(results["paper"], folder / "paper_fig4.png")
    return drawn


def write_report(results: dict, markdown: Path, *, source: Path) -> None:
    """``markdown`` from ``results`` (read from ``source``), figures in ``figures/`` beside it."""
    markdown = Path(markdown)
    drawn = draw_figures(results, markdown.parent / "figures")
    links = {suite: os.path.relpath(path, markdown.parent) for suite, path in drawn.items()}
    atomic.write_text(markdown, format_results(results, links, source=source))


def json_safe(value):
    """Plain JSON data: tuples as lists, numpy scalars as numbers, NaN and infinities as None (null)."""
    if isinstance(value, dict):
        return {str(key): json_safe(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(item) for item in value]
    if hasattr(value, "tolist"):
        return json_safe(value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_outputs(results: dict, options: BenchOptions) -> None:
    """``<out>/results.json``, ``<out>/results.md`` and ``<out>/figures/``."""
    atomic.write_text(options.out / RESULTS_JSON, json.dumps(results, indent=1, allow_nan=False) + "\n")
    write_report(results, options.out / RESULTS_MD, source=options.out / RESULTS_JSON)


def run_bench(suites: Sequence[str], options: BenchOptions, *, log: Callable[[str], None] = print) -> dict:
    """Run ``suites`` in order; after each, merge its section into results.json and rewrite the outputs.

    A suite that raises :class:`SuiteSkipped` is reported in one line and leaves results.json as it was: its
    data is missing here, which says nothing about the code, so its last measurement stays the latest one.
    Before the first suite of a full run, the tracker's compiled code is put in numba's disk cache when it is
    not there yet (:func:`pipeline.commands.warmup.ensure_compiled`), so that no timed run compiles it.
    """
    runners = suite_runners()
    if not options.quick and ensure_compiled() != 0:
        log("bench: the tracker's compiled code has no disk cache here: every run's figures include compiling it")
    options.out.mkdir(parents=True, exist_ok=True)
    results = load_results(options.out / RESULTS_JSON)
    for suite in suites:
        log(f"bench: {suite} suite{' (quick)' if options.quick else ''} ...")
        commit, load_before, reference_before = git_commit(), os.getloadavg()[0], reference_seconds()
        started = time.perf_counter()
        try:
            section = runners[suite](options.out, options.captures, quick=options.quick, workers=options.workers)
        except SuiteSkipped as skipped:
            log(f"bench: {suite} suite skipped: {skipped}")
            continue
        section |= {"quick": options.quick, "command": options.command(suite),
                    "made": {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "commit": commit,
                             "seconds": time.perf_counter() - started, "load_before": load_before,
                             "load_after": os.getloadavg()[0], "cpus": os.cpu_count(),
                             "reference_s": [reference_before, reference_seconds()],
                             "machine": cpu_model(),
                             "bench_memory": peak_memory_mb()}}
        results[suite] = json_safe(section)
        write_outputs(results, options)
        log(f"bench: {suite} done in {section['made']['seconds']:.0f} s")
    return results
