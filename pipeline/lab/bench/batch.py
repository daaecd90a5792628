"""Batch suite: a small study by ``python -m pipeline batch``, whole captures in parallel against one after the other.

The study (``<out>/batch/study/``) holds four captures, the halves of ``data_samples/taekwondo`` (2 × 56
frames) and of ``data_samples/leaning`` (2 × 42 frames), as views of the same files (:func:`excerpt_view`), and
one broken capture: ``data_samples/tiny`` copied with one image cut short, which fails in its silhouette stage,
after it has started, as a capture damaged on its way to the lab would.

Fresh runs of it, each timed from outside (interpreter start and everything else included):

1. ``batch --scheduler local:N`` (``--workers``, 2 by default): N captures at a time;
2. ``batch --scheduler local:1``: the same captures one after the other in one process, 1 worker each;
3. ``run --workers 1`` once per capture, one after the other: what a user without ``batch`` would do.

(1) and (2) run :data:`TRIALS` times each, alternated, and the fastest of each counts: the machine is shared,
and another program's busy spell only ever slows a run down. The speed-up is (2) / (1), the stricter of the two
baselines: (3) also pays an interpreter start and the tracker's code loading per capture. The suite checks that
the broken capture is reported failed with its one-line error while every other capture finished, and that each
capture's exported joints are the same in all runs.
"""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import yaml

from pipeline.commands.batch import BATCH_CSV, SOME_FAILED
from pipeline.io.run_layout import RunLayout
from pipeline.lab.bench.runs import REPO, run_pipeline
from pipeline.lab.bench.speed import prefix_view
from pipeline.lab.bench.tables import fmt, format_table

SAMPLES = REPO / "data_samples"
#: The study's good captures: name -> (sample, first frame, end frame); quick: :data:`QUICK_FRAMES` of each.
EXCERPTS = {"taekwondo/first": ("taekwondo", 0, 56), "taekwondo/second": ("taekwondo", 56, 112),
            "leaning/first": ("leaning", 0, 42), "leaning/second": ("leaning", 42, 84)}
QUICK_FRAMES = 8
#: The broken capture, and the image of it that is cut short.
BROKEN = "tiny/broken"
BROKEN_IMAGE = Path("images") / "cam2" / "000004.png"
#: Runs of each batch way (alternated); the fastest counts, the machine being shared.
TRIALS = 2


def excerpt_view(capture: Path, view: Path, start: int, stop: int) -> Path:
    """A capture ``view`` showing frames ``start`` to ``stop`` (excluded) of ``capture``: a prefix view
    (:func:`~pipeline.lab.bench.speed.prefix_view`) starting later."""
    prefix_view(capture, view, stop)
    config = yaml.safe_load((view / "capture.yaml").read_text())
    config["frames"]["start"] = int(start)
    (view / "capture.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    return view


def make_study(study: Path, *, quick: bool) -> dict[str, int]:
    """The suite's study, made afresh under ``study``; its good captures' names -> frames."""
    shutil.rmtree(study, ignore_errors=True)
    frames = {}
    for name, (sample, start, stop) in EXCERPTS.items():
        if quick:
            start, stop = start, start + QUICK_FRAMES
        excerpt_view(SAMPLES / sample, study / name, start, stop)
        frames[name] = stop - start
    broken = study / BROKEN
    shutil.copytree(SAMPLES / "tiny", broken)
    image = broken / BROKEN_IMAGE
    image.write_bytes(image.read_bytes()[:100])
    return frames


def read_table(out: Path) -> list[dict]:
    """batch.csv's rows, numbers as numbers (empty cells as None)."""
    try:
        with open(out / BATCH_CSV, newline="") as table:
            rows = list(csv.DictReader(table))
    except OSError:
        return []
    for row in rows:
        for key in ("frames", "estimated"):
            row[key] = int(row[key]) if row[key] else None
        for key in ("mpjpe_mm", "seconds"):
            row[key] = float(row[key]) if row[key] else None
    return rows


def run_batch(study: Path, out: Path, scheduler: str) -> dict:
    """``python -m pipeline batch`` on ``study`` into a fresh ``out``: exit status, wall seconds, load, rows."""
    shutil.rmtree(out, ignore_errors=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "pipeline", "batch", str(study), "--out", str(out), "--scheduler", scheduler,
               "-q"]
    load = os.getloadavg()[0]
    with open(out.parent / f"{out.name}.log", "w") as log:
        started = time.perf_counter()
        returncode = subprocess.run(command, cwd=REPO, stdout=log, stderr=subprocess.STDOUT, check=False).returncode
        seconds = time.perf_counter() - started
    return {"scheduler": scheduler, "returncode": returncode, "seconds": seconds, "load": load,
            "rows": read_table(out)}


def same_joints(names: list[str], *folders: Path) -> bool:
    """Whether every capture of ``names`` exported the same joints.csv in each of ``folders``."""
    for name in names:
        contents = {RunLayout(folder / name).joints.read_bytes()
                    if RunLayout(folder / name).joints.is_file() else None for folder in folders}
        if len(contents) != 1 or None in contents:
            return False
    return True


def broken_reported(result: dict, good: list[str]) -> bool:
    """Whether a batch exited with :data:`SOME_FAILED`, the broken capture failed with its image named in one
    line, and every good capture finished."""
    rows = {row["capture"]: row for row in result["rows"]}
    broken = rows.get(BROKEN, {})
    return (result["returncode"] == SOME_FAILED and broken.get("status") == "failed"
            and str(BROKEN_IMAGE) in broken.get("error", "")
            and all(rows.get(name, {}).get("status") == "ran" for name in good))


def run_batch_suite(out: Path, captures: Path, *, quick: bool, workers: int) -> dict:
    """The batch suite's results (see the module docstring); everything under ``<out>/batch/``.

    ``captures`` (the cache of synthetic renderings) is not used: the study is made of the bundled samples.
    """
    folder = out / "batch"
    study = folder / "study"
    frames = make_study(study, quick=quick)
    good = list(frames)
    trials: dict[str, list[dict]] = {"parallel": [], "sequential": []}
    for trial in range(1 if quick else TRIALS):  # alternated, so that a busy spell of the machine slows both
        trials["parallel"].append(run_batch(study, folder / f"parallel-{trial}", f"local:{workers}"))
        trials["sequential"].append(run_batch(study, folder / f"sequential-{trial}", "local:1"))
    parallel, sequential = (min(results, key=lambda result: result["seconds"]) for results in trials.values())
    runs = {name: run_pipeline(study / name, folder / "runs" / name, workers=1, frames=count, fresh=True).to_dict()
            for name, count in {**frames, BROKEN: 0}.items()}
    separate = sum(run["seconds"] for run in runs.values())
    first_load = next(iter(runs.values()))["load"]
    every = [folder / f"{mode}-{trial}" for mode, results in trials.items() for trial in range(len(results))]
    return {
        "workers": workers, "captures": [{"capture": name, "frames": count} for name, count in frames.items()],
        "broken": {"capture": BROKEN, "damage": f"{BROKEN_IMAGE} cut to 100 bytes"},
        "parallel": parallel, "sequential": sequential,
        "trial_seconds": {mode: [result["seconds"] for result in results] for mode, results in trials.items()},
        "runs": {"seconds": separate, "load": first_load, "ok": [name for name, run in runs.items() if run["ok"]]},
        "speedup": sequential["seconds"] / parallel["seconds"], "speedup_vs_runs": separate / parallel["seconds"],
        "broken_reported": all(broken_reported(result, good) for results in trials.values() for result in results),
        "same_joints": same_joints(good, *every, folder / "runs"),
    }


BATCH_NOTES = (
    "How: a study of five captures, the halves of `data_samples/taekwondo` and of `data_samples/leaning` (6 cameras "
    "780×580 video; a quick run takes their first frames only) and a copy of `data_samples/tiny` with one image cut "
    "short (it fails in its silhouette stage), run afresh three ways and timed from outside: `python -m pipeline batch "
    "--scheduler local:N` (N captures at a time), `batch --scheduler local:1` (one after the other in one process) "
    "and `python -m pipeline run --workers 1` once per capture; the two batch ways twice each, alternated, the faster "
    "of each shown (all times under the table). Every capture's per-frame stages run with 1 worker. "
    "The speed-up judged is local:1 / local:N; the separate runs also pay an interpreter start and the tracker's "
    "code loading per capture. The machine is shared with other work: the load average before each run says how "
    "busy it was.")


def format_batch(section: dict) -> str:
    """The suite's tables: how the study's runs went and how long each way took."""
    parallel, sequential = section["parallel"], section["sequential"]
    frames = {row["capture"]: row["frames"] for row in section["captures"]}
    by_name = {row["capture"]: row for row in sequential["rows"]}
    rows = [(row["capture"], frames.get(row["capture"], row["frames"]), row["status"], row["estimated"],
             row["mpjpe_mm"], row["seconds"], by_name.get(row["capture"], {}).get("seconds"), row["error"] or "–")
            for row in parallel["rows"]]
    lines = [format_table(("capture", "frames", "status", "estimated", "MPJPE mm",
                           f"s (local:{section['workers']})", "s (local:1)", "error"), rows), ""]
    lines.append(format_table(
        ("how", "wall s", f"local:{section['workers']} faster by ×", "load before"),
        [(f"`batch --scheduler local:{section['workers']}`", parallel["seconds"], "1.00", parallel["load"]),
         ("`batch --scheduler local:1`", sequential["seconds"], f"{section['speedup']:.2f}", sequential["load"]),
         ("`run --workers 1` per capture, one after the other", section["runs"]["seconds"],
          f"{section['speedup_vs_runs']:.2f}", section["runs"]["load"])]))
    tries = "; ".join(f"{mode} {', '.join(f'{seconds:.1f}' for seconds in times)} s"
                      for mode, times in section["trial_seconds"].items())
    lines += ["", f"Every batch run: {tries}. Broken capture reported failed "
                  f"(exit status {parallel['returncode']}) while the others finished: "
                  f"{fmt(section['broken_reported'])}; the same joints in every run: {fmt(section['same_joints'])}."]
    return "\n".join(lines)
