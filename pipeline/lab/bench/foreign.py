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

Each scored run is also reconstructed and tracked again with the capture's true masks in place of its silhouettes
(:func:`true_masks_row`, in ``<out>/foreign/<name>-true-masks/``): the tracker's error on perfect silhouettes, apart
from what the silhouette stage costs. A tracker that degrades gracefully does no worse there; a capture that does
shows a weakness of the tracker itself (it showed a re-initialisation facing the subject backwards).

The tracker's own time is measured apart, after every run (:func:`~pipeline.lab.bench.speed.tracker_speed` over
each run's observations, in this process, in passes that take the runs in turn: :func:`tracker_ms`): the tracking
stage streams alongside the reconstruction, so its manifest time is mostly waiting. It is judged relative to
``data_samples/taekwondo`` (same motion, window and rig as foreign taekwondo, rendered by :mod:`pipeline.lab.synth`)
run through the same path into ``<out>/foreign-reference/taekwondo/``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from calib.errors import InputError
from pipeline.evaluate import evaluate_run
from pipeline.io import frames_io
from pipeline.io.capture import Capture
from pipeline.io.run_layout import RunLayout
from pipeline.lab.bench.runs import REPO, run_command, run_pipeline
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


#: Times the tracker runs over each capture's observations for its figure; the fastest pass counts.
TRACKER_PASSES = 3


@dataclass(frozen=True)
class TrackerTiming:
    """What timing the tracker on one run's observations needs: the run, its capture and the frames."""

    run_dir: Path
    capture: Capture
    frames: tuple[int, ...]


def tracker_ms(timings: Sequence[TrackerTiming]) -> list[float]:
    """The tracker's own milliseconds of CPU per frame over each run's observations, every frame (initialisations
    too), in the order of ``timings``.

    CPU rather than wall time, and the fastest of `TRACKER_PASSES` passes, each pass timing every run once in
    turn: the figures are compared with the reference capture's, and the tracker computes the same frames on every
    pass, so what differs between passes is the machine (its other work and its own speed, which drifts by a
    third within an hour here), and that only ever adds time. Taking the runs in turn within each pass puts a
    slow spell on all of them rather than on one.
    """
    passes = [[1000.0 / tracker_speed(t.run_dir, t.capture, list(t.frames))["fps_all_cpu"] for t in timings]
              for _ in range(TRACKER_PASSES)]
    return [min(column) for column in zip(*passes, strict=True)]


def image_sizes(capture: Capture) -> str:
    """The cameras' image sizes as "WxH", each distinct size once (a rig may mix cameras)."""
    return " ".join(sorted({f"{camera.size[0]}x{camera.size[1]}" for camera in capture.rig}))


def run_capture(name: str, capture: Path, run_dir: Path, *, workers: int) -> tuple[dict, TrackerTiming | None]:
    """One capture's row: what it is, the run's measure, its scores (or why it has none, in ``error``); and what
    timing its tracker needs, for a run that was scored (`tracker_ms` times them all together)."""
    try:
        opened = Capture.open(capture)
    except InputError as error:
        return {"capture": name, "error": str(error)}, None
    frames = opened.frame_numbers
    measure = run_pipeline(capture, run_dir, workers=workers, frames=len(frames), fresh=True)
    row = {"capture": name, "cameras": len(opened.rig), "size": image_sizes(opened), "frames": len(frames),
           "run": measure.to_dict(), "fps_end_to_end": len(frames) / measure.seconds if measure.ok else None}
    if not measure.ok:
        return row, None
    try:
        row |= foreign_scores(evaluate_run(run_dir, truth=capture / "groundtruth" / "joints.csv"))
        row |= true_masks_row(capture, run_dir, run_dir.parent / f"{run_dir.name}-true-masks", workers=workers)
    except (InputError, OSError) as error:
        return row | {"error": str(error)}, None
    return row, TrackerTiming(run_dir, opened, tuple(frames))


def true_masks_row(capture: Path, run_dir: Path, copy_dir: Path, *, workers: int) -> dict:
    """``mpjpe_true_masks_mm`` and ``worst_true_masks_mm`` of the run ``run_dir`` reconstructed and tracked again
    in ``copy_dir`` (made afresh) with ``<capture>/groundtruth/masks/<camera>/`` copied over its silhouettes; None
    each when the capture has no true masks for every silhouette, or the run fails (its log: ``<copy_dir>.log``).
    """
    masks = capture / "groundtruth" / "masks"
    silhouettes = RunLayout(run_dir).silhouettes_dir
    cameras = sorted(path for path in silhouettes.iterdir() if path.is_dir() and path.name != "background")
    pairs = [(masks / camera.name / image.name, image.relative_to(run_dir))
             for camera in cameras for image in sorted(camera.glob("*.png"))]
    none = {"mpjpe_true_masks_mm": None, "worst_true_masks_mm": None}
    if not pairs or not all(source.is_file() for source, _ in pairs):
        return none
    shutil.rmtree(copy_dir, ignore_errors=True)
    shutil.copytree(run_dir, copy_dir)
    for source, target in pairs:
        shutil.copyfile(source, copy_dir / target)
    with open(copy_dir.parent / f"{copy_dir.name}.log", "w") as log:
        done = subprocess.run([*run_command(capture, copy_dir, workers), "--from", "reconstruction", "--force"],
                              cwd=REPO, stdout=log, stderr=subprocess.STDOUT, check=False)
    if done.returncode != 0:
        return none
    scores = score_row(evaluate_run(copy_dir, truth=capture / "groundtruth" / "joints.csv"))
    return {"mpjpe_true_masks_mm": scores["mpjpe_mm"], "worst_true_masks_mm": scores["worst_frame_mm"]}


def with_tracking(rows: Sequence[dict], timings: Sequence[TrackerTiming | None]) -> list[dict]:
    """The rows with their tracks' statuses and tracker times (`tracking_row`), those with a timing timed together."""
    timed = [timing for timing in timings if timing is not None]
    milliseconds = iter(tracker_ms(timed))
    done = []
    for row, timing in zip(rows, timings, strict=True):
        if timing is not None:
            ms = next(milliseconds)
            try:
                row = row | tracking_row(timing.run_dir, timing.frames, ms)
            except (InputError, OSError) as error:
                row = row | {"error": str(error)}
        done.append(row)
    return done


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
    made = [run_capture(f"data_samples/{reference_name}", reference, out / "foreign-reference" / reference_name,
                        workers=workers)]
    for capture in found:
        name, path = selected(capture, out / "foreign", quick=quick)
        made.append(run_capture(name, path, out / "foreign" / name, workers=workers))
    reference_row, *rows = with_tracking([row for row, _ in made], [timing for _, timing in made])
    reference_ms = reference_row.get("tracker_ms_per_frame")
    return {"root": os.path.relpath(FOREIGN_ROOT, REPO), "rows": [with_reference(row, reference_ms) for row in rows],
            "reference": with_reference(reference_row, reference_ms)}
