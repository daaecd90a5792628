"""Robustness suite: the whole pipeline on perturbed copies of the foreign captures, one perturbation per copy.

The foreign suite (:mod:`pipeline.lab.bench.foreign`) measures four captures as another program made them; a real
studio differs from them in ways that each stage meets on its own: a codec that blocks, a noisy sensor, mains
flicker, an automatic exposure acting before the camera's gamma, no clean plate, fewer cameras, a camera that does
not frame the whole volume, a calibration slightly off, a camera knocked after its clean plate was taken, something
standing between a camera and the subject, a camera that was not synchronised with the others. Each of
:data:`VARIANTS` makes one such change to every foreign capture with
:func:`~pipeline.lab.bench.perturb.perturb_capture` (seed 0), so that what it costs is read against the foreign
suite's figures for the same capture (roughly: every copy's videos are also encoded a second time, which a copy
with ``change="none"`` alone measures). The folder of foreign captures lives outside the
repository, so the suite is skipped with one line when it is absent.

A copy takes a while to write (every frame of every video decoded, changed and encoded again) and depends only
on its source and its perturbation, so copies are cached in ``<captures>/robustness/`` (the bench's cache of
rendered captures) and made once (:func:`ensure_copy`). Each copy ``<capture>-<variant slug>-<key>/`` is named
after a hash of what it is made from (:func:`cache_key`), so a changed perturbation or capture.yaml makes a new
copy instead of reusing a stale one (older copies are left for the user to delete).

Each copy is run afresh by :func:`~pipeline.lab.bench.runs.run_pipeline` into ``<out>/robustness/<capture>-<variant
slug>/`` and scored by :func:`pipeline.evaluate.evaluate_run` against the copy's ground truth (the original's, or
rewritten by the perturbation for the cameras it keeps or zooms). A variant with ``sync_offsets`` runs with the
cameras' sync check, then again, into ``<...>-offsets/``, on a view of the copy with the ``frame_offsets`` the check
named (:func:`~pipeline.lab.bench.speed.capture_view`), which is the run scored. A failed copy, run or scoring is a
row with an ``error``, never an exception that stops the bench.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import subprocess
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from calib.errors import InputError
from pipeline.evaluate import evaluate_run
from pipeline.io import frames_io
from pipeline.io.capture import Capture
from pipeline.io.run_layout import RunLayout
from pipeline.lab.bench.foreign import (
    FOREIGN_ROOT,
    QUICK_FRAMES,
    find_captures,
    foreign_scores,
    reinitialised_after_first,
    tracking_results,
)
from pipeline.lab.bench.perturb import capture_videos, perturb_capture
from pipeline.lab.bench.runs import REPO, run_pipeline
from pipeline.lab.bench.speed import capture_view, prefix_view

#: The random draws of every copy (flicker, noise, the calibration's turns): fixed, so that a copy is reproducible.
SEED = 0
#: Characters of the hash in a copy's folder name: enough to tell apart the few versions a cache ever holds.
KEY_LENGTH = 8
#: The scores kept in a row (of :func:`~pipeline.lab.bench.foreign.foreign_scores`).
SCORES = ("mpjpe_mm", "worst_frame_mm", "fraction_estimated", "silhouette_iou_median")


@dataclass(frozen=True)
class Variant:
    """One perturbation of the suite: its name and :func:`perturb_capture`'s keyword arguments.

    The arguments that name cameras cannot be written once for four rigs, so they are given relative to the
    capture's cameras sorted by name: ``first_cameras`` keeps that many of the first (None: all of them),
    ``first_camera_zoom`` zooms the first by that factor (None: no zoom), ``first_plate_shift`` moves the first's
    clean plate by those (x, y) pixels (None: no shift), ``first_occluder`` puts that kind of occluder before the
    first (None: none) and ``first_late`` makes the first run that many frames behind the others (None: on time).
    :meth:`arguments` spells them out. ``sync_offsets``: the run checks the cameras' synchrony
    (``export.sync_check``) and the copy is run again with the ``frame_offsets`` the check names. ``copy_as``: the
    variant whose copy this one runs (None: its own).
    """

    name: str
    change: str = "none"
    plates: bool = True
    first_cameras: int | None = None
    first_camera_zoom: float | None = None
    calibration_error_deg: float = 0.0
    position_error_m: float = 0.0
    first_plate_shift: tuple[float, float] | None = None
    shutter: float = 0.0
    first_occluder: str | None = None
    box: bool = False
    first_late: int | None = None
    sync_offsets: bool = False
    copy_as: str | None = None

    @property
    def slug(self) -> str:
        """The name as a folder name: lower case, each run of other characters than letters and digits a "-"."""
        return _slug(self.name)

    @property
    def copy_slug(self) -> str:
        """The slug of the variant whose copy this one runs."""
        return _slug(self.copy_as or self.name)

    def arguments(self, cameras: Sequence[str]) -> dict:
        """:func:`perturb_capture`'s keyword arguments for a capture whose cameras are ``cameras`` (sorted); a position
        error, a plate shift, a shutter, an occluder and a box only when there are, so that the other copies keep their
        cache keys (:func:`cache_key`)."""
        arguments = {"change": self.change, "seed": SEED, "plates": self.plates,
                     "cameras": tuple(cameras[:self.first_cameras]) if self.first_cameras is not None else (),
                     "calibration_error_deg": self.calibration_error_deg,
                     "zoom": {cameras[0]: self.first_camera_zoom} if self.first_camera_zoom is not None else None}
        if self.position_error_m:
            arguments["position_error_m"] = self.position_error_m
        if self.first_plate_shift is not None:
            arguments["plate_shift"] = {cameras[0]: self.first_plate_shift}
        if self.shutter:
            arguments["shutter"] = self.shutter
        if self.first_occluder is not None:
            arguments["occluder"] = {cameras[0]: self.first_occluder}
        if self.box:
            arguments["box"] = True
        if self.first_late is not None:
            arguments["late"] = {cameras[0]: self.first_late}
        return arguments


def _slug(name: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")


VARIANTS = (
    Variant("compression", change="compression"),
    Variant("noise", change="noise"),
    Variant("flicker", change="flicker"),
    Variant("darker before the gamma", change="gamma_dark"),
    Variant("no plates", plates=False),
    Variant("4 cameras", first_cameras=4),
    Variant("one camera zoomed 1.8x", first_camera_zoom=1.8),
    Variant("calibration off 0.1°", calibration_error_deg=0.1),
    Variant("calibration off 0.3°", calibration_error_deg=0.3),
    Variant("cameras moved 2 cm", position_error_m=0.02),
    Variant("one plate 5 px off", first_plate_shift=(4.0, 3.0)),
    Variant("shutter open the whole frame", shutter=0.5),
    Variant("a desk before one camera", first_occluder="desk"),
    Variant("a pillar before one camera", first_occluder="pillar"),
    Variant("a box put down after the plates", box=True),
    Variant("one camera 2 frames late", first_late=2),
    Variant("2 frames late, frame_offsets from the sync check", first_late=2, sync_offsets=True,
            copy_as="one camera 2 frames late"),
)
#: The variants of a quick run (a smoke test): one that changes the frames, one that changes the rig and the truth.
QUICK_VARIANTS = ("compression", "4 cameras")


def variants(*, quick: bool) -> tuple[Variant, ...]:
    """The variants to run: all of them, or in a quick run those named in :data:`QUICK_VARIANTS`."""
    return tuple(variant for variant in VARIANTS if not quick or variant.name in QUICK_VARIANTS)


def camera_names(capture: Path) -> list[str]:
    """The capture's cameras by name, as :func:`perturb_capture` knows them (:func:`capture_videos`' names without
    extension); InputError when it has no videos."""
    return [video.stem for video in capture_videos(capture)]


def cache_key(arguments: dict, capture_yaml: bytes) -> str:
    """A short hash of a copy's perturbation (``arguments``, the camera names spelled out) and of its source's
    capture.yaml: a copy made from other arguments or another capture.yaml has another key.

    The videos themselves are not hashed (reading them would cost about what copying them does): a foreign capture
    whose videos are redone without a change to its capture.yaml keeps its old copies, which are then to be deleted.
    """
    digest = hashlib.sha256(json.dumps(arguments, sort_keys=True).encode())
    digest.update(capture_yaml)
    return digest.hexdigest()[:KEY_LENGTH]


def copy_folder(capture: Path, variant: Variant, cache: Path) -> Path:
    """Where the ``variant`` copy of ``capture`` is cached: ``<cache>/<capture>-<variant's copy slug>-<key>``."""
    key = cache_key(variant.arguments(camera_names(capture)), (capture / "capture.yaml").read_bytes())
    return cache / f"{capture.name}-{variant.copy_slug}-{key}"


def ensure_copy(capture: Path, variant: Variant, cache: Path) -> Path:
    """The ``variant`` copy of ``capture`` in ``cache``, made unless it is there.

    A folder that is there is complete: :func:`perturb_capture` writes ``<copy>.partial`` and renames it when done.
    """
    copy = copy_folder(capture, variant, cache)
    if not copy.is_dir():
        perturb_capture(capture, copy, **variant.arguments(camera_names(capture)))
    return copy


def frame_numbers(capture: Path) -> list[int]:
    """The frames a run of ``capture`` processes (its capture.yaml's selection)."""
    return list(Capture.open(capture).frame_numbers)


def run_variant(capture: Path, variant: Variant, cache: Path, out: Path, *, quick: bool, workers: int) -> dict:
    """The row of ``capture`` perturbed by ``variant``: its scores and the share of its frames initialised anew
    after the first (``reinitialised_fraction``: how gracefully the tracker met the change), or why it has none
    (``error``).

    The copy is cached in ``cache``; the run goes to ``<out>/<capture>-<variant slug>`` (``-quick`` added in a
    quick run, which processes a view of the copy's first :data:`~pipeline.lab.bench.foreign.QUICK_FRAMES` frames
    beside it, so that its folders are not taken for a full run's).
    """
    row = {"capture": capture.name, "variant": variant.name}
    name = f"{capture.name}-{variant.slug}" + ("-quick" if quick else "")
    try:
        copy = ensure_copy(capture, variant, cache)
        source = prefix_view(copy, out / f"{name}-capture", QUICK_FRAMES) if quick else copy
        numbers = frame_numbers(source)
        settings = ("export.sync_check=true",) if variant.sync_offsets else ()
        measure = run_pipeline(source, out / name, workers=workers, frames=len(numbers), fresh=True,
                               settings=settings)
        if variant.sync_offsets and measure.ok:
            offsets = named_offsets(out / name)
            row["offsets_named"] = offsets
            if offsets:
                name += "-offsets"
                source = capture_view(source, out / f"{name}-capture", frame_offsets=offsets)
                numbers = frame_numbers(source)
                measure = run_pipeline(source, out / name, workers=workers, frames=len(numbers), fresh=True)
        frames = len(numbers)
    except (InputError, OSError, subprocess.CalledProcessError) as error:
        return row | {"error": str(error)}
    row |= {"copy": str(copy), "frames": frames, "run": measure.to_dict()}
    if not measure.ok:
        last_line = measure.log_tail.splitlines()[-1:] or [""]
        return row | {"error": f"the run failed (exit status {measure.returncode}): {last_line[0]}"}
    try:
        scores = foreign_scores(evaluate_run(out / name, truth=source / "groundtruth" / "joints.csv"))
        reinitialised = reinitialised_after_first(tracking_results(out / name, numbers))
    except (InputError, OSError) as error:
        return row | {"error": str(error)}
    return row | {key: scores[key] for key in SCORES} | {"reinitialised_fraction": reinitialised}


def named_offsets(run_dir: Path) -> dict[str, int]:
    """The ``frame_offsets`` that a run's sync check named (``export/sync_check.json``), {} when it named none or did
    not write its file."""
    path = RunLayout(run_dir).sync_check
    return dict(frames_io.read_json(path).get("frame_offsets") or {}) if path.is_file() else {}


def run_robustness(out: Path, captures: Path, *, quick: bool, workers: int) -> dict:
    """One row per foreign capture and variant, capture by capture (see the module docstring)."""
    found = find_captures(FOREIGN_ROOT)
    rows = [run_variant(capture, variant, captures / "robustness", out / "robustness", quick=quick, workers=workers)
            for capture in found for variant in variants(quick=quick)]
    return {"root": os.path.relpath(FOREIGN_ROOT, REPO), "rows": rows}
