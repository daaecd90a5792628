"""Unseen suite: the whole pipeline on synthetic captures the tracker was never tuned on, scored on truth.

Each capture of :data:`~pipeline.lab.bench.recipes.UNSEEN` is rendered once (cached by recipe), then
``python -m pipeline run`` processes it into ``<out>/unseen/<name>/`` (the runner's own cache skips stages
whose code, parameters and inputs did not change) and :func:`pipeline.evaluate.evaluate_run` scores the
exported joints against ``groundtruth/joints.csv``: MPJPE over the 15 scored joints, fraction of frames
estimated, worst frame, knee and elbow flexion errors.
"""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from calib.errors import InputError
from pipeline.evaluate import evaluate_run
from pipeline.io.capture import Capture
from pipeline.lab.bench.recipes import QUICK_UNSEEN, UNSEEN, Recipe, describe, ensure_capture
from pipeline.lab.bench.runs import run_pipeline

#: Row fields averaged into the "mean" row.
MEAN_FIELDS = ("fraction_estimated", "mpjpe_mm", "offset_free_mpjpe_mm", "worst_frame_mm", "knee_flexion_deg",
               "elbow_flexion_deg", "silhouette_iou")


def unseen_recipes(quick: bool) -> list[Recipe]:
    return [recipe.quick() for recipe in UNSEEN if recipe.name in QUICK_UNSEEN] if quick else list(UNSEEN)


def render(captures: Path, recipe: Recipe) -> Path | str:
    """The capture's directory, or why the generator refused the recipe (the row then reports it)."""
    try:
        return ensure_capture(captures, recipe)
    except (InputError, RuntimeError) as error:
        return f"capture not rendered: {error}"


def ensure_captures(captures: Path, recipes: list[Recipe], workers: int) -> list[Path | str]:
    """Render the missing captures, ``workers`` at a time (each rendering is single-threaded)."""
    if workers <= 1:
        return [render(captures, recipe) for recipe in recipes]
    with ProcessPoolExecutor(workers) as pool:
        return list(pool.map(render, [captures] * len(recipes), recipes))


def score_row(metrics: dict) -> dict:
    """The row fields of one evaluated run (see :func:`pipeline.evaluate.evaluate_run`)."""
    angles = metrics["angle_errors_deg"]
    return {
        "fraction_estimated": metrics["fraction_estimated"],
        "mpjpe_mm": metrics["mpjpe_mm"],
        "offset_free_mpjpe_mm": metrics.get("offset_free_mpjpe_mm"),  # None without the body frame's joints
        "worst_frame_mm": metrics["worst_frame"]["mpjpe_mm"],
        "knee_flexion_deg": float(np.mean([angles["l_knee_flexion"], angles["r_knee_flexion"]])),
        "elbow_flexion_deg": float(np.mean([angles["l_elbow_flexion"], angles["r_elbow_flexion"]])),
        "pck_100mm": metrics["pck"].get("100mm"),
        "silhouette_iou": (metrics.get("silhouette_iou") or {}).get("mean"),
    }


def mean_row(rows: list[dict]) -> dict:
    """Mean of :data:`MEAN_FIELDS` over the rows that were scored (a failed run has no score)."""
    scored = [row for row in rows if "mpjpe_mm" in row]
    return {field: float(np.mean([row[field] for row in scored if row.get(field) is not None] or [np.nan]))
            for field in MEAN_FIELDS} | {"captures": len(scored), "failed": len(rows) - len(scored)}


def run_unseen(out: Path, captures: Path, *, quick: bool, workers: int) -> dict:
    """Rows per capture and their mean (see the module docstring)."""
    recipes = unseen_recipes(quick)
    paths = ensure_captures(captures, recipes, workers)
    rows = []
    for recipe, path in zip(recipes, paths, strict=True):
        if isinstance(path, str):
            rows.append({"capture": recipe.name, **describe(recipe), "error": path})
            continue
        frames = len(Capture.open(path).frame_numbers)
        measure = run_pipeline(path, out / "unseen" / recipe.name, workers=workers, frames=frames, fresh=False)
        row = {"capture": recipe.name, **describe(recipe), "frames": frames, "run": measure.to_dict()}
        if measure.ok:
            try:
                row |= score_row(evaluate_run(out / "unseen" / recipe.name))
            except InputError as error:
                row["error"] = str(error)
        rows.append(row)
    return {"rows": rows, "mean": mean_row(rows)}
