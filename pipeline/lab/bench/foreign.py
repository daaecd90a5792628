"""Foreign suite: the whole pipeline on captures made by another program, found in ``<repo>/../shared/foreign``.

Every other suite scores the pipeline on captures rendered by :mod:`pipeline.lab.synth`, whose body, room, lighting
and noise the silhouette stage and the tracker were developed against; a capture from an independent renderer
shows what of the accuracy is owed to that familiarity. The folder lives outside the repository (it is shared,
not bundled), so the suite is skipped with one line when it is absent.

Each capture ``<root>/<name>/`` (a subfolder with a capture.yaml) is run afresh by
:func:`~pipeline.lab.bench.runs.run_pipeline` into ``<out>/foreign/<name>/`` and scored by
:func:`pipeline.evaluate.evaluate_run` against ``<capture>/groundtruth/joints.csv``, which
also scores the silhouettes against ``groundtruth/masks/``. From the tracking stage it adds what says *how* the
track went, not only how far off it ended: the count of each frame status and the share of frames
re-initialised after the first (a track that keeps restarting can still score a fair MPJPE). Every run is
fresh, so its wall time gives the end-to-end frame rate, video decoding included.

The tracker's own time is measured apart (:func:`~pipeline.lab.bench.speed.tracker_speed` over the run's
observations, in this process): the tracking stage streams alongside the reconstruction, so its manifest time
is mostly waiting. It is judged relative to ``data_samples/taekwondo`` (same motion, window and rig as foreign
taekwondo, rendered by :mod:`pipeline.lab.synth`) run through the same path into
``<out>/foreign-reference/taekwondo/``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from calib.errors import InputError
from pipeline.evaluate import evaluate_run
from pipeline.io import frames_io
from pipeline.io.capture import Capture
from pipeline.io.run_layout import RunLayout
from pipeline.lab.bench.runs import REPO, run_pipeline
from pipeline.lab.bench.speed import prefix_view, tracker_speed
from pipeline.lab.bench.suite import SuiteSkipped
from pipeline.lab.bench.unseen import score_row
from stages.tracking.results import STATUSES

#: Where the foreign captures are: beside the repository, shared by every checkout.
FOREIGN_ROOT = REPO.parent / "shared" / "foreign"
#: The bundled capture whose tracker time is the reference (same motion, window and rig as foreign taekwondo).
REFERENCE = REPO / "data_samples" / "taekwondo"
#: Frames of each capture in a quick run (a smoke test of the suite, not a measurement).
QUICK_FRAMES = 20


def find_captures(root: Path) -> list[Path]:
    """The capture folders under ``root`` (subfolders holding a capture.yaml), by name.

    Raises
    ------
    SuiteSkipped
        When ``root`` is absent or holds no capture: the suite has nothing to measure, which is not an error.
    """
    root = Path(root)
    if not root.is_dir():
        raise SuiteSkipped(f"no folder {root} (expected one capture folder with a capture.yaml per subfolder)")
    captures = sorted(path for path in root.iterdir() if (path / "capture.yaml").is_file())
    if not captures:
        raise SuiteSkipped(f"{root} holds no capture (expected subfolders with a capture.yaml)")
    return captures


def foreign_scores(metrics: dict) -> dict:
    """The unseen suite's row fields of an evaluated run, plus the silhouettes' median IoU with the true masks.

    The median, not the mean: a few masks ruined by a shadow or a distractor pull the mean down, the median
    says how good a typical mask is. None when the capture has no true masks.
    """
    return score_row(metrics) | {"silhouette_iou_median": (metrics["silhouette_iou"] or {}).get("median")}


def tracking_results(run_dir: Path, frames: Sequence[int]) -> list[dict]:
    """The tracking stage's per-frame ``result`` records of a run, in frame order."""
    return [frames_io.read_json(RunLayout(run_dir).tracking_record(frame))["result"] for frame in frames]


def status_counts(results: Sequence[dict]) -> dict[str, int]:
    """How many frames ended in each status, plus ``doubtful``: frames exported but flagged by the tracker.

    ``doubtful`` is a flag on a tracked or initialised frame, not a status of its own, so it overlaps them.
    """
    counts = {status: sum(result["status"] == status for result in results) for status in STATUSES}
    return counts | {"doubtful": sum(bool(result.get("doubtful")) for result in results)}


def reinitialised_after_first(results: Sequence[dict]) -> float:
    """Share of frames initialised anew after the first frame: the tracker lost the body and searched again.

    The first frame has no track to lose (it is initialised from the data alone), so it is not counted; the
    denominator is all frames.
    """
    return sum(result["status"] == "initialised" for result in results[1:]) / len(results)


def tracking_row(run_dir: Path, frames: Sequence[int], tracker_ms: float) -> dict:
    """The row fields that describe the track: statuses, re-initialisations, the tracker's ms per frame."""
    results = tracking_results(run_dir, frames)
    return {"tracker_ms_per_frame": tracker_ms, "statuses": status_counts(results),
            "reinitialised_fraction": reinitialised_after_first(results)}


#: Times the tracker runs over a capture's observations for its figure; the fastest pass counts.
TRACKER_PASSES = 3


def tracker_ms(run_dir: Path, capture: Capture, frames: Sequence[int]) -> float:
    """The tracker's own milliseconds of CPU per frame over a run's observations, every frame (initialisations too).

    CPU rather than wall time, and the fastest of `TRACKER_PASSES` passes: the figure is compared with the
    reference capture's, timed minutes apart; the tracker computes the same frames on every pass, so what
    differs between passes is the machine (its other work and its own speed, which moved a single pass's CPU
    time by up to a tenth between two runs of the suite), and that only ever adds time.
    """
    return min(1000.0 / tracker_speed(run_dir, capture, list(frames))["fps_all_cpu"] for _ in range(TRACKER_PASSES))


def image_sizes(capture: Capture) -> str:
    """The cameras' image sizes as "WxH", each distinct size once (a rig may mix cameras)."""
    return " ".join(sorted({f"{camera.size[0]}x{camera.size[1]}" for camera in capture.rig}))


def run_capture(name: str, capture: Path, run_dir: Path, *, workers: int) -> dict:
    """One capture's row: what it is, the run's measure, its scores (or why it has none, in ``error``)."""
    try:
        opened = Capture.open(capture)
    except InputError as error:
        return {"capture": name, "error": str(error)}
    frames = opened.frame_numbers
    measure = run_pipeline(capture, run_dir, workers=workers, frames=len(frames), fresh=True)
    row = {"capture": name, "cameras": len(opened.rig), "size": image_sizes(opened), "frames": len(frames),
           "run": measure.to_dict(), "fps_end_to_end": len(frames) / measure.seconds if measure.ok else None}
    if measure.ok:
        try:
            row |= foreign_scores(evaluate_run(run_dir, truth=capture / "groundtruth" / "joints.csv"))
            row |= tracking_row(run_dir, frames, tracker_ms(run_dir, opened, frames))
        except (InputError, OSError) as error:
            row["error"] = str(error)
    return row


def selected(capture: Path, folder: Path, *, quick: bool) -> tuple[str, Path]:
    """The run's name and the capture it processes: the capture itself, or in a quick run a view of its
    first :data:`QUICK_FRAMES` frames (named apart, so that its rows and run folders are not taken for the
    full run's)."""
    if not quick:
        return capture.name, capture
    name = f"{capture.name}-quick"
    return name, prefix_view(capture, folder / f"{name}-capture", QUICK_FRAMES)


def with_reference(row: dict, reference_ms: float | None) -> dict:
    """``row`` with its tracker ms/frame as a multiple of the reference's (None when either is unknown)."""
    ms = row.get("tracker_ms_per_frame")
    return row | {"tracker_vs_reference": ms / reference_ms if ms is not None and reference_ms else None}


def run_foreign(out: Path, captures: Path, *, quick: bool, workers: int) -> dict:
    """Rows per capture of :data:`FOREIGN_ROOT` and the reference row (see the module docstring).

    ``captures`` (the cache of synthetic renderings) is not used: these captures are made elsewhere.
    """
    found = find_captures(FOREIGN_ROOT)
    reference_name, reference = selected(REFERENCE, out / "foreign-reference", quick=quick)
    reference_row = run_capture(f"data_samples/{reference_name}", reference,
                                out / "foreign-reference" / reference_name, workers=workers)
    reference_ms = reference_row.get("tracker_ms_per_frame")
    rows = []
    for capture in found:
        name, path = selected(capture, out / "foreign", quick=quick)
        rows.append(with_reference(run_capture(name, path, out / "foreign" / name, workers=workers), reference_ms))
    return {"root": os.path.relpath(FOREIGN_ROOT, REPO), "rows": rows,
            "reference": with_reference(reference_row, reference_ms)}
