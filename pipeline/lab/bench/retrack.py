"""Track the bench's runs again from their observations with other tracker settings, and score every one.

    python -m pipeline.lab.bench.retrack --out runs/retrack/no_shoulders \\
        --set 'tracking.estimate_lengths=[upperarm,shank,girth,forearm]'

An ablation of the tracker alone. Every scored run of the foreign and unseen suites under ``--bench`` (and the
foreign suite's reference run) keeps the silhouettes and observations the bench made; only tracking and export
run again, ``python -m pipeline run <capture> --from tracking`` with the ``--set`` and ``--config`` given, a few
runs at a time. The table puts each capture's MPJPE, worst frame, share of frames re-initialised after the
first and count of frames flagged doubtful (as the foreign suite reports them) in the bench's run beside the
new ones, and the figures the
targets judge beside them: the unseen suite's mean and the foreign suite's worst capture.
A change that helps one capture and hurts the others shows at once, in about half a minute for fifteen
captures, where the suites take minutes to make again silhouettes and points the change leaves alone.

Some captures are chaotic: a setting that changes nothing of substance can still move one of them by several
millimetres, through one limb re-initialisation or fresh initialisation that goes another way (foreign leaning
moved 43.2 → 38.7 mm with only the pose library's angle vectors changed). ``--seeds N`` tracks every run N times,
with ``tracking.seed`` 0 to N − 1 (the random subsamples the initialisation and the limb recovery score their
hypotheses on), and gives each capture's mean over the seeds and its range: a difference between two settings
that the seeds' own range covers is the draw, not the setting. Compare two settings each with the same seeds
(the bench's own run is one draw, seed 0).

The new runs are made in ``--out``, one folder per run (``<name>.seed<k>`` with ``--seeds``): the bench's stage
folders up to the reconstruction hard-linked (copied where the file system cannot link), so that nothing of the
bench's runs is written to.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib.errors import InputError
from pipeline.evaluate import default_truth, score_joints
from pipeline.io import frames_io
from pipeline.io.run_layout import MANIFEST, RunLayout
from pipeline.lab.bench.foreign import reinitialised_after_first, status_counts, tracking_results
from pipeline.lab.bench.runs import REPO
from pipeline.lab.bench.tables import format_table, percent
from pipeline.terminal import printable

#: The bench's folders of runs scored against a ground truth, in the order of the table.
SUITE_FOLDERS = ("foreign", "foreign-reference", "unseen")
#: Stage folders a new run takes from the bench's run (what tracking reads).
UPSTREAM_STAGES = ("calibration", "silhouettes", "reconstruction")
#: The file that marks a folder as made by this tool, holding the settings of its last use.
SETTINGS_FILE = "retrack.json"


@dataclass(frozen=True)
class BenchRun:
    """One scored run of the bench: its suite folder, name and directory."""

    suite: str
    name: str
    path: Path


def bench_runs(bench: Path) -> list[BenchRun]:
    """The runs under ``bench`` (its :data:`SUITE_FOLDERS`) that exported joints and whose capture has a ground
    truth."""
    runs = []
    for suite in SUITE_FOLDERS:
        folder = bench / suite
        for path in sorted(folder.iterdir()) if folder.is_dir() else []:
            if (path / "reconstruction" / MANIFEST).is_file() and RunLayout(path).joints.is_file() and _has_truth(path):
                runs.append(BenchRun(suite, path.name, path))
    return runs


def _has_truth(run_dir: Path) -> bool:
    try:
        default_truth(run_dir)
    except (InputError, OSError):
        return False
    return True


def linked_copy(run: Path, dest: Path) -> None:
    """``dest`` made afresh with the :data:`UPSTREAM_STAGES` folders of ``run``, hard-linked where possible.

    The pipeline writes every file by renaming a new one into place, so a linked file is never written
    through: the bench's run stays as it was.
    """
    shutil.rmtree(dest, ignore_errors=True)
    dest.mkdir(parents=True)
    for stage in UPSTREAM_STAGES:
        try:
            shutil.copytree(run / stage, dest / stage, copy_function=os.link)
        except OSError:  # another file system, or one without hard links
            shutil.rmtree(dest / stage, ignore_errors=True)
            shutil.copytree(run / stage, dest / stage)


def retrack(run: BenchRun, out: Path, options: list[str], seed: int | None = None) -> dict:
    """Track ``run`` again in ``out/<suite>/<name>`` (``<name>.seed<seed>`` with a ``seed``, given as
    ``tracking.seed``) with the ``options`` of ``pipeline run``; its scores then and now (``problem`` says why a
    run has no new score)."""
    truth = default_truth(run.path)
    summary = frames_io.read_json(RunLayout(run.path).capture_summary)
    dest = out / run.suite / (run.name if seed is None else f"{run.name}.seed{seed}")
    linked_copy(run.path, dest)
    seeded = [] if seed is None else ["--set", f"tracking.seed={seed}"]
    command = [sys.executable, "-m", "pipeline", "run", summary["capture_dir"], "--out", str(dest),
               "--from", "tracking", "--workers", "1", "-q", *options, *seeded]
    finished = subprocess.run(command, cwd=REPO, capture_output=True, text=True)
    row = {"suite": run.suite, "capture": run.name} | scores(run.path, truth, summary["frames"], "before")
    if finished.returncode != 0:
        lines = (finished.stderr or finished.stdout).strip().splitlines()
        return row | {"problem": lines[-1] if lines else f"exit status {finished.returncode}"}
    return row | scores(dest, truth, summary["frames"], "after")


def scores(run_dir: Path, truth: Path, frames: list[int], when: str) -> dict:
    """A run's MPJPE, worst frame, share of frames re-initialised after the first and count of doubtful frames
    (as the foreign suite counts them), keyed ``<figure>_<when>``: a change that keeps the error but restarts
    more often costs time, each restart being a fresh search."""
    joints = score_joints(run_dir, truth).summary()
    results = tracking_results(run_dir, frames)
    return {f"mpjpe_{when}": joints["mpjpe_mm"], f"worst_{when}": joints["worst_frame"]["mpjpe_mm"],
            f"reinitialised_{when}": reinitialised_after_first(results),
            f"doubtful_{when}": status_counts(results)["doubtful"]}


def over_seeds(rows: list[dict]) -> dict:
    """One capture's rows of several seeds as one row: the new figures' means over the seeds, the MPJPE's range
    (``mpjpe_range``), and the first problem met (a row with a problem has no new figures)."""
    scored = [row for row in rows if "problem" not in row]
    merged = {key: value for key, value in rows[0].items() if not key.endswith("_after") and key != "problem"}
    if len(scored) < len(rows):
        return merged | {"problem": next(row["problem"] for row in rows if "problem" in row)}
    merged |= {key: float(np.mean([row[key] for row in scored]))
               for key in ("mpjpe_after", "worst_after", "reinitialised_after", "doubtful_after")}
    return merged | {"mpjpe_range": (min(row["mpjpe_after"] for row in scored),
                                     max(row["mpjpe_after"] for row in scored))}


def summary_rows(rows: list[dict]) -> list[tuple]:
    """The figures the targets judge, before and after: the unseen mean, the foreign worst capture and mean."""
    def figure(label, suite, reduce):
        scored = [row for row in rows if row["suite"] == suite and "mpjpe_after" in row]
        if not scored:
            return None
        return (label, reduce([row["mpjpe_before"] for row in scored]), reduce([row["mpjpe_after"] for row in scored]))

    figures = [figure("unseen, mean MPJPE", "unseen", np.mean), figure("foreign, worst capture", "foreign", np.max),
               figure("foreign, mean MPJPE", "foreign", np.mean)]
    return [row for row in figures if row is not None]


def check_out(out: Path, bench: Path) -> None:
    """Refuse an ``out`` inside the bench's folder, or an existing folder this tool did not make."""
    if out.resolve() == bench.resolve() or bench.resolve() in out.resolve().parents:
        raise InputError(f"--out {out}: inside the bench's folder {bench} (expected a folder of its own)")
    if out.exists() and any(out.iterdir()) and not (out / SETTINGS_FILE).is_file():
        raise InputError(f"--out {out}: a folder this tool did not make (no {SETTINGS_FILE}); "
                         "expected a new or empty folder, or one of an earlier retrack")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bench", type=Path, default=REPO / "runs" / "bench", help="the bench's --out folder")
    parser.add_argument("--out", type=Path, required=True, help="folder for the new runs")
    parser.add_argument("--set", dest="assignments", action="append", default=[], metavar="STAGE.PARAM=VALUE",
                        help="as for python -m pipeline run (repeatable)")
    parser.add_argument("--config", type=Path, help="as for python -m pipeline run")
    parser.add_argument("--workers", type=int, default=2, help="runs tracked at a time")
    parser.add_argument("--seeds", type=int, default=0, metavar="N",
                        help="track every run with tracking.seed 0 to N-1 and give the means and ranges (default: "
                             "once, with the settings as given)")
    args = parser.parse_args(argv)
    options = [word for assignment in args.assignments for word in ("--set", assignment)]
    seeded = any(assignment.replace(" ", "").startswith("tracking.seed=") for assignment in args.assignments)
    if args.seeds < 0 or (args.seeds and seeded):
        parser.exit(2, "error: --seeds: expected a count >= 0, and no --set tracking.seed beside it\n")
    if args.config is not None:
        options += ["--config", str(args.config.resolve())]
    try:
        check_out(args.out, args.bench)
        runs = bench_runs(args.bench)
        if not runs:
            raise InputError(f"{args.bench}: no scored run of the {', '.join(SUITE_FOLDERS)} suites "
                             "(expected the --out folder of python -m pipeline bench)")
    except InputError as error:
        parser.exit(2, f"error: {printable(str(error))}\n")
    args.out.mkdir(parents=True, exist_ok=True)
    frames_io.write_json(args.out / SETTINGS_FILE, {"bench": str(args.bench.resolve()), "options": options,
                                                    "seeds": args.seeds})
    seeds = list(range(args.seeds)) or [None]
    with cf.ThreadPoolExecutor(max(1, args.workers)) as pool:
        tracked = list(pool.map(lambda job: retrack(job[0], args.out, options, job[1]),
                                [(run, seed) for run in runs for seed in seeds]))
    rows = [over_seeds(tracked[k * len(seeds):(k + 1) * len(seeds)]) for k in range(len(runs))]
    ranges = "MPJPE range over the seeds" if args.seeds else None
    print(format_table(("suite", "capture", "MPJPE mm before", "after", *([ranges] if ranges else []),
                        "worst mm before", "after", "re-init. after 1st before", "after", "doubtful before", "after",
                        "problem"),
                       [(row["suite"], row["capture"], row["mpjpe_before"], row.get("mpjpe_after"),
                         *([_span(row.get("mpjpe_range"))] if ranges else []),
                         row["worst_before"], row.get("worst_after"), percent(row["reinitialised_before"]),
                         percent(row.get("reinitialised_after")), row["doubtful_before"],
                         row.get("doubtful_after"), printable(row.get("problem", "")))
                        for row in rows]))
    if args.seeds:
        print(f"\nafter: the mean over tracking.seed 0-{args.seeds - 1}; before: the bench's run (seed 0)")
    print()
    print(format_table(("figure", "before", "after"), summary_rows(rows)))
    return 1 if any("problem" in row for row in rows) else 0


def _span(bounds: tuple[float, float] | None) -> str:
    return "" if bounds is None else f"{bounds[0]:.1f}-{bounds[1]:.1f}"


if __name__ == "__main__":
    sys.exit(main())
