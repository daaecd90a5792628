"""Exports suite: do the exported files show joints.csv's motion, does smoothing help, does the confidence mean much?

On each foreign capture (``pipeline.lab.bench.foreign``: made by another program, with ground truth) one fresh run
with the default parameters, then the export stage alone again with smoothing at each cut-off of
:data:`CUTOFFS_HZ` (``--set export.filter_cutoff_hz=...``: the upstream stages are up to date, so only the
export reruns). For each:

- agreement: the largest distance, over the estimated frames and joints, between joints.csv and each other
  export as a reader that shares no code with the pipeline sees it: ``motion.bvh`` by bvhio (forward
  kinematics of the file's offsets and channels), ``joints.trc`` by trc-data-reader, ``joints.c3d`` by the
  c3d package (:func:`agreement_mm`);
- accuracy: ``pipeline.evaluate.evaluate_run``'s MPJPE and acceleration errors (the wrists': the fastest and
  noisiest joints);
- confidence (unsmoothed run): the share of scored (frame, joint) pairs quality.csv calls unsupported, the
  MPJPE of those and of the others, and the share of joint errors above 50 mm that it flags
  (:func:`confidence_against_truth`).

The readers come with the dev extra (``pip install -e .[dev]``); without them the suite is skipped.
"""

from __future__ import annotations

import csv
import os
import subprocess
import warnings
from pathlib import Path

import numpy as np

from calib.errors import InputError
from pipeline.evaluate import evaluate_run
from pipeline.io import frames_io
from pipeline.io.capture import Capture
from pipeline.io.export_io import read_joints_csv
from pipeline.io.run_layout import BVH_FILE, C3D_FILE, QUALITY_FILE, TRC_FILE, RunLayout
from pipeline.lab.bench.foreign import FOREIGN_ROOT, find_captures, selected
from pipeline.lab.bench.runs import REPO, run_command, run_pipeline
from pipeline.lab.bench.suite import SuiteSkipped
from stages.export.bvh import BONE_NAMINGS, UNITS, WORLD_TO_BVH
from stages.export.quality import UNSUPPORTED_CONFIDENCE
from stages.export.trc import MARKER_NAMINGS
from stages.joints import SCORED_JOINTS

#: Cut-offs (Hz) of the smoothed exports; the targets are judged at :data:`JUDGED_CUTOFF_HZ`.
CUTOFFS_HZ = (4.0, 6.0, 8.0, 10.0)
#: Winter's usual cut-off for walking, a middle choice for the sport motions as well.
JUDGED_CUTOFF_HZ = 6.0
#: Joint errors above this (mm) count as large for the confidence's hit rate.
LARGE_ERROR_MM = 50.0


def _grid_index(frames: np.ndarray) -> np.ndarray:
    """Positions of the estimated ``frames`` on the regular grid the fixed-rate formats use."""
    step = int(np.gcd.reduce(np.diff(frames))) if len(frames) > 1 else 1
    return (frames - frames[0]) // step


def bvh_positions(path: Path, names: tuple[str, ...], units: str, naming: str) -> np.ndarray:
    """(G, J, 3) world positions (metres, +z up) of the joints.csv joints in every BVH frame, by bvhio."""
    import bvhio

    root = bvhio.readAsHierarchy(str(path))
    joints = {joint.Name: joint for joint, _, _ in root.layout()}
    bvh_name = {name: BONE_NAMINGS[naming].get(name, name) for name in names}
    positions = np.empty((bvhio.readAsBvh(str(path)).FrameCount, len(names), 3))
    for frame in range(len(positions)):
        root.loadPose(frame)
        positions[frame] = [np.array(joints[bvh_name[name]].PositionWorld) @ WORLD_TO_BVH for name in names]
    return positions / UNITS[units]


def trc_positions(path: Path, names: tuple[str, ...], naming: str) -> np.ndarray:
    """(G, J, 3) world positions (metres, +z up) from the TRC (+Y up, mm), by trc-data-reader."""
    from trc import TRCData

    data = TRCData()
    data.load(str(path))
    marker = {name: MARKER_NAMINGS[naming].get(name, name) for name in names}
    xyz = np.stack([np.array(data[marker[name]], dtype=float) for name in names], axis=1) / 1000.0
    return np.stack([xyz[..., 0], -xyz[..., 2], xyz[..., 1]], axis=-1)


def c3d_positions(path: Path, names: tuple[str, ...]) -> np.ndarray:
    """(G, J, 3) world positions (metres, +z up) from the C3D (mm), by the c3d package."""
    import c3d

    with open(path, "rb") as handle, warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="No analog data found")
        reader = c3d.Reader(handle)
        labels = [label.strip() for label in reader.point_labels]
        frames = [points[:, :3].copy() for _, points, _ in reader.read_frames()]
    return np.stack(frames)[:, [labels.index(name) for name in names]] / 1000.0


def agreement_mm(run_dir: Path) -> dict[str, float]:
    """Largest distance (mm) over the estimated frames and joints between joints.csv and each other export."""
    layout = RunLayout(run_dir)
    export = layout.export_dir
    frames, names, joints = read_joints_csv(layout.joints)
    manifest = layout.manifest("export")  # the run's export parameters: the BVH's units and names
    params = frames_io.read_json(manifest).get("params", {}) if manifest.is_file() else {}
    index = _grid_index(frames)
    readings = {
        BVH_FILE: bvh_positions(export / BVH_FILE, names, params.get("bvh_units", "cm"),
                                params.get("bvh_names", "joints")),
        TRC_FILE: trc_positions(export / TRC_FILE, names, params.get("trc_names", "joints")),
        C3D_FILE: c3d_positions(export / C3D_FILE, names),
    }
    return {file: float(1000.0 * np.linalg.norm(read[index] - joints, axis=-1).max())
            for file, read in readings.items()}


def confidence_against_truth(run_dir: Path, truth: Path) -> dict[str, float]:
    """How the joints quality.csv calls unsupported compare in error with the others (see the module docstring)."""
    layout = RunLayout(run_dir)
    frames, names, joints = read_joints_csv(layout.joints)
    true_frames, true_names, true_joints = read_joints_csv(truth)
    with open(layout.export_file(QUALITY_FILE), newline="") as handle:
        rows = {int(row["frame"]): row for row in csv.DictReader(handle)}
    common = np.intersect1d(frames, true_frames)
    scored = [name for name in SCORED_JOINTS if name in names and name in true_names]
    estimate = joints[np.isin(frames, common)][:, [names.index(n) for n in scored]]
    true = true_joints[np.isin(true_frames, common)][:, [true_names.index(n) for n in scored]]
    error = 1000.0 * np.linalg.norm(estimate - true, axis=-1)
    confidence = np.array([[float(rows[int(f)][f"{name}_confidence"]) for name in scored] for f in common])
    weak, large = confidence < UNSUPPORTED_CONFIDENCE, error > LARGE_ERROR_MM
    return {"unsupported_share": float(weak.mean()),
            "unsupported_mpjpe_mm": float(error[weak].mean()) if weak.any() else None,
            "supported_mpjpe_mm": float(error[~weak].mean()) if (~weak).any() else None,
            "large_errors_flagged": float(weak[large].mean()) if large.any() else None}


def _scores(run_dir: Path, truth: Path) -> dict:
    """MPJPE, acceleration errors (mean, wrists) and the exports' agreement of one exported run."""
    metrics = evaluate_run(run_dir, truth=truth)
    acceleration = metrics["per_joint_acceleration_error_m_s2"]
    wrists = [acceleration[name] for name in ("l_wrist", "r_wrist") if name in acceleration]
    agreement = agreement_mm(run_dir)
    return {"mpjpe_mm": metrics["mpjpe_mm"], "acceleration_m_s2": metrics["acceleration_error_m_s2"],
            "wrist_acceleration_m_s2": float(np.mean(wrists)) if wrists else None,
            "agreement_mm": agreement, "largest_disagreement_mm": max(agreement.values())}


def reexport(capture: Path, run_dir: Path, cutoff_hz: float | None, workers: int) -> None:
    """Run the export stage again on a finished run, smoothed at ``cutoff_hz`` (None: unsmoothed)."""
    value = "null" if cutoff_hz is None else f"{cutoff_hz:g}"
    subprocess.run([*run_command(capture, run_dir, workers), "--set", f"export.filter_cutoff_hz={value}"],
                   cwd=REPO, check=True, capture_output=True)


def run_capture(name: str, capture: Path, run_dir: Path, *, workers: int) -> dict:
    """One capture's row: the unsmoothed run's scores and confidence, then one entry per cut-off."""
    try:
        frames = Capture.open(capture).frame_numbers
    except InputError as error:
        return {"capture": name, "error": str(error)}
    truth = capture / "groundtruth" / "joints.csv"
    measure = run_pipeline(capture, run_dir, workers=workers, frames=len(frames), fresh=True)
    row = {"capture": name, "frames": len(frames), "run": measure.to_dict()}
    if not measure.ok:
        return row
    try:
        row |= _scores(run_dir, truth) | {"confidence": confidence_against_truth(run_dir, truth)}
        smoothed = []
        for cutoff in CUTOFFS_HZ:
            reexport(capture, run_dir, cutoff, workers)
            smoothed.append({"cutoff_hz": cutoff, **_scores(run_dir, truth)})
        row["smoothed"] = smoothed
        reexport(capture, run_dir, None, workers)  # the folder ends as a default run
    except (InputError, OSError, subprocess.CalledProcessError) as error:
        row["error"] = str(error)
    return row


def run_exports(out: Path, captures: Path, *, quick: bool, workers: int) -> dict:
    """Rows per capture of the foreign folder (see the module docstring); ``captures`` is not used."""
    try:
        import bvhio  # noqa: F401
        import c3d  # noqa: F401
        import trc  # noqa: F401
    except ImportError as error:
        raise SuiteSkipped(f"{error.name} is missing (the independent readers come with `pip install -e .[dev]`)") \
            from None
    rows = []
    for capture in find_captures(FOREIGN_ROOT):
        name, path = selected(capture, out / "exports", quick=quick)
        rows.append(run_capture(name, path, out / "exports" / name, workers=workers))
    return {"root": os.path.relpath(FOREIGN_ROOT, REPO), "rows": rows, "cutoffs_hz": list(CUTOFFS_HZ),
            "judged_cutoff_hz": JUDGED_CUTOFF_HZ}


def smoothed_row(row: dict, cutoff_hz: float = JUDGED_CUTOFF_HZ) -> dict:
    """The entry of ``row["smoothed"]`` at ``cutoff_hz``; KeyError when the capture has none."""
    for entry in row.get("smoothed", []):
        if entry["cutoff_hz"] == cutoff_hz:
            return entry
    raise KeyError(cutoff_hz)
