"""What the report reads of a run folder, each piece optional: joints, truth and its score, tracking
statuses, angles, warnings, stage timings (:func:`load_run`)."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib.errors import InputError
from pipeline.engine.run_warnings import read_warnings
from pipeline.evaluate import default_truth, score_joints
from pipeline.io import frames_io
from pipeline.io.export_io import read_joints_csv
from pipeline.io.run_layout import ANGLES_FILE, MANIFEST, STAGE_NAMES, RunLayout, read_manifest_file
from pipeline.report.tracking_summary import (
    FrameStatus,
    read_body_height,
    read_frame_statuses,
    tracker_params,
)
from stages.export.metrics import JointMetrics
from stages.tracking.results import BodyHeight

log = logging.getLogger(__name__)

#: Frame rate assumed when the run has no readable calibration/capture.json (viewer playback only).
DEFAULT_FPS = 25.0


@dataclass(frozen=True)
class JointSequence:
    """Joint centres of one sequence: ``frames (F,)``, ``names`` (J), ``joints (F, J, 3)`` metres."""

    frames: np.ndarray
    names: tuple[str, ...]
    joints: np.ndarray

    def at(self, frame: int) -> np.ndarray | None:
        """(J, 3) joints of ``frame``, or None when it was not estimated."""
        hits = np.flatnonzero(self.frames == frame)
        return self.joints[hits[0]] if len(hits) else None


@dataclass(frozen=True)
class AngleTable:
    """Joint angles: ``frames (F,)``, ``names`` (K), ``degrees (F, K)``."""

    frames: np.ndarray
    names: tuple[str, ...]
    degrees: np.ndarray



def stage_timings(out_dir: Path) -> list[dict]:
    """One row per stage folder with a readable manifest: stage, seconds, frames, finished_at (the stages in
    pipeline order; other stage folders with a manifest follow alphabetically)."""
    folders = [p for p in out_dir.iterdir() if (p / MANIFEST).is_file()] if out_dir.is_dir() else []
    rank = {name: i for i, name in enumerate(STAGE_NAMES)}
    folders.sort(key=lambda p: (rank.get(p.name, len(STAGE_NAMES)), p.name))
    rows = []
    for folder in folders:
        try:
            manifest = read_manifest_file(folder) or {}
        except (OSError, frames_io.DamagedFileError) as error:
            log.warning("%s: unreadable manifest (%s); left out of the report", folder, frames_io.problem_of(error))
            continue
        timing = manifest.get("timing") or {}
        timing = timing if isinstance(timing, dict) else {}
        rows.append({"stage": folder.name, "seconds": timing.get("seconds"), "frames": timing.get("frames"),
                     "workers": timing.get("workers"), "finished_at": manifest.get("finished_at")})
    return rows


def read_angles_csv(path: Path) -> AngleTable:
    """An angles.csv (header ``frame,<angle>,...``, one row per frame, degrees; an empty cell is NaN).

    Raises
    ------
    InputError
        The file is not such a table (the message names the file and line).
    """
    lines = [line for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]
    header = lines[0].split(",") if lines else []
    if header[:1] != ["frame"] or len(header) < 2:
        raise InputError(f"{path}:1: expected a header 'frame,<angle>,...', got {lines[:1]}")
    rows = []
    for number, line in enumerate(lines[1:], start=2):
        cells = line.split(",")
        try:
            if len(cells) != len(header):
                raise ValueError(f"{len(cells)} cells for {len(header)} columns")
            rows.append([float(cell) if cell.strip() else np.nan for cell in cells])
        except ValueError as error:
            raise InputError(f"{path}:{number}: not a row of numbers ({error})") from None
    table = np.array(rows, dtype=float).reshape(-1, len(header))
    return AngleTable(table[:, 0].astype(int), tuple(header[1:]), table[:, 1:])


def _read_sequence(path: Path) -> JointSequence | None:
    if not path.is_file():
        return None
    frames, names, joints = read_joints_csv(path)
    return JointSequence(frames, names, joints)


def _find_truth(out_dir: Path, truth_path: str | os.PathLike | None) -> Path | None:
    if truth_path is not None:
        return Path(truth_path)
    try:
        return default_truth(out_dir)
    except InputError:
        return None


@dataclass(frozen=True)
class LoadedRun:
    """What the report shows of one run; every field but ``fps``, ``capture`` and ``warnings`` may be missing."""

    out_dir: Path
    fps: float
    capture: dict
    estimate: JointSequence | None
    estimate_problem: str | None
    truth: JointSequence | None
    truth_path: Path | None
    metrics: JointMetrics | None
    scoring_problem: str | None
    statuses: list[FrameStatus] | None
    limits: dict
    angles: AngleTable | None
    angles_problem: str | None
    warnings: list[dict]
    body_height: BodyHeight | None = None


def load_run(out_dir: Path, truth_path: str | os.PathLike | None) -> LoadedRun:
    layout = RunLayout(out_dir)
    summary_path = layout.capture_summary
    capture = frames_io.read_json(summary_path) if summary_path.is_file() else {}
    capture = capture if isinstance(capture, dict) else {}
    fps = capture.get("fps")
    fps = float(fps) if isinstance(fps, (int, float)) and fps > 0 else DEFAULT_FPS
    estimate, estimate_problem = None, None
    try:
        estimate = _read_sequence(layout.joints)
    except InputError as error:  # e.g. no rows: no frame was estimated, which the report is to explain
        estimate_problem = str(error)
    found_truth = _find_truth(out_dir, truth_path)
    truth = _read_sequence(found_truth) if found_truth is not None else None
    metrics, problem = None, None
    if estimate is not None and truth is not None:
        try:
            metrics = score_joints(out_dir, found_truth)
        except InputError as error:
            problem = str(error)
    frames = capture.get("frames")
    statuses = read_frame_statuses(layout.tracking_dir, frames) if isinstance(frames, list) else None
    angles, angles_problem = None, None
    if layout.export_file(ANGLES_FILE).is_file():
        try:
            angles = read_angles_csv(layout.export_file(ANGLES_FILE))
        except (InputError, UnicodeDecodeError) as error:
            angles_problem = str(error)
    stated = capture.get("height_m")
    body_height = read_body_height(layout.tracking_dir, frames, stated if isinstance(stated, (int, float)) else None
                                   ) if statuses is not None else None
    return LoadedRun(out_dir, fps, capture, estimate, estimate_problem, truth,
                     found_truth if truth is not None else None, metrics, problem, statuses,
                     tracker_params(layout.tracking_dir), angles, angles_problem, read_warnings(out_dir), body_height)
