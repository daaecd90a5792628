"""Benchmark the pipeline: speed, accuracy on unseen synthetic captures, the paper's experiments.

Examples:
  python -m pipeline bench --out runs/bench                      # every suite (make bench)
  python -m pipeline bench --out runs/bench --suite speed --quick  # smoke run, a few frames
  python -m pipeline bench --out runs/bench --suite paper --figures docs/figures

Writes <out>/results.json (one section per suite; running a suite replaces only its own), <out>/results.md
(tables, targets met or missed) and PNG figures (default <out>/figures). Synthetic captures are rendered
once into <out>/captures/<name>/ with their recipe beside them (<name>.recipe.json) and rendered again only
when the recipe changes. Suites:
  speed   the paper's studio (6 cameras 780x580 28 fps): end-to-end frames/s of `python -m pipeline run`,
          ms/frame per stage, the tracker alone, peak memory of a short and a long capture
  unseen  the whole pipeline on captures varying clip, body, cameras, resolution, noise, distractors,
          media, calibration format/units/up axis and known height, scored against ground truth
  paper   Horaud et al. 2009 Fig. 4: flexion trajectories, error vs silhouette noise, frame rate and
          number of observations, points+normals vs points vs the algebraic distance (20 % outliers)
"""

from __future__ import annotations

import argparse
from pathlib import Path

from calib.errors import InputError
from pipeline.bench.suite import SUITES, BenchOptions, run_bench


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("runs/bench"), help="results folder (default runs/bench)")
    parser.add_argument("--suite", choices=(*SUITES, "all"), default="all", help="which suite to run (default all)")
    parser.add_argument("--quick", action="store_true", help="few frames per capture: a smoke run of a few minutes")
    parser.add_argument("--workers", type=int, default=2, help="worker processes (pipeline runs, rendering, sweeps)")
    parser.add_argument("--captures", type=Path, help="cache of synthetic captures (default <out>/captures)")
    parser.add_argument("--figures", type=Path, help="where the PNG figures go (default <out>/figures)")


def main(args: argparse.Namespace) -> int:
    if args.workers < 1:
        raise InputError(f"--workers {args.workers}: expected at least 1")
    options = BenchOptions(out=args.out, captures=args.captures or args.out / "captures",
                           figures=args.figures or args.out / "figures", quick=args.quick, workers=args.workers)
    suites = SUITES if args.suite == "all" else (args.suite,)
    run_bench(suites, options)
    print(f"written: {args.out / 'results.json'}, {args.out / 'results.md'}")
    return 0
