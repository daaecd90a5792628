"""Benchmark the pipeline: speed, accuracy (unseen, paper, foreign captures and perturbed copies), exports, calibration,
batch.

Examples:
  python -m pipeline bench --out runs/bench                      # every suite (make bench)
  python -m pipeline bench --out runs/bench --suite speed --quick  # smoke run, a few frames
  python -m pipeline bench --out runs/bench --report-only --docs docs   # redraw docs/results.md, docs/figures

Writes <out>/results.json (one section per suite; running a suite replaces only its own), <out>/results.md
(tables, targets met or missed) and <out>/figures/*.png; with --docs DIR also DIR/results.md,
DIR/figures/*.png and DIR/results.json, the measurements the page is drawn from, kept with the page: a bench in a
fresh checkout (no <out>/results.json yet) starts from them, so that running one suite there replaces that
suite's section and keeps the others'. Synthetic captures are rendered
once into <out>/captures/<name>/ with their recipe beside them (<name>.recipe.json) and rendered again only
when the recipe changes. Suites:
  speed   the paper's studio (6 cameras 780x580 28 fps): end-to-end frames/s of `python -m pipeline run`,
          ms/frame per stage, the tracker alone, peak memory of a short and a long capture
  unseen  the whole pipeline on captures varying clip, body, cameras, resolution, noise, distractors,
          media, calibration format/units/up axis and known height, scored against ground truth
  paper   Horaud et al. 2009 Fig. 4: flexion trajectories, error vs silhouette noise, frame rate and
          number of observations, points+normals vs points vs the algebraic distance (20 % outliers)
  foreign the whole pipeline on the captures in <repo>/../shared/foreign (made by another renderer), scored
          against their ground truth, with the tracker's statuses and speed (skipped when the folder is absent)
  robustness  the whole pipeline on copies of the foreign captures changed one way each (JPEG at quality 20,
          sensor noise, flicker, no clean plates, 4 cameras, one camera zoomed 1.8x, calibration off 0.1°),
          made once into <captures>/robustness/ (skipped when the foreign folder is absent)
  exports the foreign captures' exports read back by independent readers against joints.csv, smoothing's
          effect on wrist acceleration and MPJPE, the per-joint confidence against the error
  calibration  `python -m pipeline calibrate` on rendered board recordings (checkerboard, ChArUco, a phone),
          scored against the true rig; taekwondo run on the self-calibrated rig against the true one
  batch   `python -m pipeline batch` on a study of 4 excerpts of the bundled samples and a broken capture:
          local:N against one capture after the other, the broken one reported while the others finish
"""

from __future__ import annotations

import argparse
from pathlib import Path

from calib.errors import InputError
from pipeline.io import atomic
from pipeline.lab.bench.suite import (
    RESULTS_JSON,
    RESULTS_MD,
    SUITES,
    BenchOptions,
    load_results,
    run_bench,
    write_report,
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("runs/bench"), help="results folder (default runs/bench)")
    parser.add_argument("--suite", choices=(*SUITES, "all"), default="all", help="which suite to run (default all)")
    parser.add_argument("--quick", action="store_true", help="few frames per capture: a smoke run of a few minutes")
    parser.add_argument("--workers", type=int, default=2, help="worker processes (pipeline runs, rendering, sweeps)")
    parser.add_argument("--captures", type=Path, help="cache of synthetic captures (default <out>/captures)")
    parser.add_argument("--docs", type=Path, metavar="DIR",
                        help="also write DIR/results.md, DIR/figures/ and DIR/results.json (and start from that "
                             "JSON when <out> has none)")
    parser.add_argument("--report-only", action="store_true",
                        help="measure nothing: redraw the tables and figures from <out>/results.json")


def main(args: argparse.Namespace) -> int:
    if args.workers < 1:
        raise InputError(f"--workers {args.workers}: expected at least 1")
    source = args.out / RESULTS_JSON
    if args.docs is not None:
        seed_results(source, args.docs / RESULTS_JSON)
    if args.report_only:
        results = load_results(source)
        if not results:
            raise InputError(f"{source}: no results to report (expected a previous `python -m pipeline bench` run)")
        write_report(results, args.out / RESULTS_MD, source=source)
    else:
        options = BenchOptions(out=args.out, captures=args.captures or args.out / "captures", quick=args.quick,
                               workers=args.workers)
        results = run_bench(SUITES if args.suite == "all" else (args.suite,), options)
    written = [source, args.out / RESULTS_MD]
    if args.docs is not None:
        write_report(results, args.docs / RESULTS_MD, source=source)
        atomic.write_text(args.docs / RESULTS_JSON, source.read_text())
        written += [args.docs / RESULTS_MD, args.docs / RESULTS_JSON]
    print("written: " + ", ".join(str(path) for path in written))
    return 0


def seed_results(results: Path, published: Path) -> None:
    """Copy the ``published`` measurements (the docs' results.json) to ``results`` when there are none there yet.

    Results stay on the machine that measured them; the docs page and its JSON travel with the repository. A
    suite run in a fresh checkout merges into the published sections instead of drawing a page of one suite.
    """
    if results.exists() or not load_results(published):
        return
    results.parent.mkdir(parents=True, exist_ok=True)
    atomic.write_text(results, published.read_text())
    print(f"bench: {results} started from {published} (the published measurements)")
