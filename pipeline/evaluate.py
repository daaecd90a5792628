"""Score a run against ground truth: MPJPE (also without each joint's constant offset), PCK, angle errors,
silhouette IoU -> <out>/eval/metrics.json.

Usage: ``python -m pipeline eval <out_dir> [--truth <capture>/groundtruth/joints.csv]``.

The estimate is ``<out_dir>/export/joints.csv``. The truth defaults to
``<capture_dir>/groundtruth/joints.csv`` of the capture named by ``capture_dir`` in
``<out_dir>/calibration/capture.json``. Silhouettes are scored when both ``<out_dir>/silhouettes/`` and
true masks (``masks/<camera>/<frame:06d>.png`` next to the truth joints.csv) exist. The metric
definitions are in :mod:`stages.export.metrics`; the scored joints are ``SCORED_JOINTS``.
"""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path

import numpy as np

from calib.errors import InputError
from pipeline.io import frames_io
from pipeline.io.export_io import read_joints_csv
from pipeline.io.run_layout import MARKER, RunLayout
from pipeline.terminal import printable
from stages.export.metrics import JointMetrics, evaluate_joints, mask_iou
from stages.joints import JOINT_NAMES

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out_dir", type=Path, help="output directory of a run (holds export/joints.csv)")
    parser.add_argument("--truth", type=Path, default=None,
                        help="ground-truth joints.csv (default: groundtruth/joints.csv of the run's capture)")


def main(args: argparse.Namespace) -> int:
    summary = evaluate_run(args.out_dir, truth=args.truth)
    print("\n".join(printable(line) for line in format_metrics(summary).splitlines()))  # camera names from files
    print(printable(f"written: {RunLayout(args.out_dir).metrics}"))
    return 0


#: Where a capture keeps its ground-truth joints (CAPTURE_FORMAT.md), scored when present.
TRUTH_FILE = Path("groundtruth") / "joints.csv"


def default_truth(out_dir: str | os.PathLike) -> Path:
    """The ground-truth joints.csv of the capture a run was made from (``capture_dir`` in capture.json)."""
    summary_path = RunLayout(out_dir).capture_summary
    summary = frames_io.read_json(summary_path) if summary_path.is_file() else {}
    capture_dir = summary.get("capture_dir") if isinstance(summary, dict) else None
    if not capture_dir:
        raise InputError(f"{summary_path}: no capture_dir recorded, so the ground truth is unknown "
                         "(expected --truth <capture>/groundtruth/joints.csv)")
    truth = Path(capture_dir) / TRUTH_FILE
    if not truth.is_file():
        raise InputError(f"{truth}: the run's capture has no ground truth (expected --truth <joints.csv>)")
    return truth


def silhouette_iou(estimated_dir: str | os.PathLike, truth_dir: str | os.PathLike) -> dict | None:
    """IoU of estimated silhouettes against true masks, for every (camera, frame) present in both.

    Parameters
    ----------
    estimated_dir : folder ``<camera>/<frame:06d>.png`` of the silhouette stage
    truth_dir : folder ``<camera>/<frame:06d>.png`` of true masks

    Returns
    -------
    dict or None
        ``{"mean": mean IoU over all compared masks, "median": their median, "per_camera": {camera: mean IoU},
        "masks_compared": count}``, or None when no mask pair exists. The median is there because a few
        masks a distractor or a shadow ruined pull the mean down: it says how good a typical mask is.
    """
    estimated_dir, truth_dir = Path(estimated_dir), Path(truth_dir)
    if not estimated_dir.is_dir() or not truth_dir.is_dir():
        return None
    per_camera: dict[str, list[float]] = {}
    for camera_dir in sorted(p for p in truth_dir.iterdir() if p.is_dir()):
        for truth_file in sorted(camera_dir.glob("*.png")):
            estimated_file = estimated_dir / camera_dir.name / truth_file.name
            if estimated_file.is_file():
                estimate, truth = frames_io.read_mask(estimated_file), frames_io.read_mask(truth_file)
                if estimate.shape != truth.shape:
                    raise InputError(f"{estimated_file}: size {estimate.shape[::-1]} differs from the true "
                                     f"mask {truth_file} {truth.shape[::-1]} (expected the same image size)")
                per_camera.setdefault(camera_dir.name, []).append(mask_iou(estimate, truth))
    if not per_camera:
        return None
    every = [value for values in per_camera.values() for value in values]
    return {"mean": float(np.mean(every)), "median": float(np.median(every)), "masks_compared": len(every),
            "per_camera": {camera: float(np.mean(values)) for camera, values in per_camera.items()}}


def score_joints(out_dir: str | os.PathLike, truth: str | os.PathLike) -> JointMetrics:
    """The joint metrics of a run's ``export/joints.csv`` against the ``truth`` joints.csv.

    Only the frames the run was asked to process (capture.yaml's frames range, in capture.json) are
    scored, so that a run on an excerpt is not charged with the frames it never saw. The report scores
    with this too, so that its figures are always those of ``pipeline eval`` on the same files.
    """
    layout = RunLayout(out_dir)
    estimate = read_joints_csv(layout.joints)
    true_frames, true_names, true_joints = read_joints_csv(truth)
    check_truth(truth, true_names, true_joints)
    summary_path = layout.capture_summary
    capture = frames_io.read_json(summary_path) if summary_path.is_file() else {}
    processed = capture.get("frames")
    if processed is not None:
        kept = np.isin(true_frames, processed)
        if len(true_frames) and not kept.any():
            raise InputError(f"{truth}: frames {true_frames.min()}..{true_frames.max()}, none of them processed by "
                             f"the run (frames {min(processed)}..{max(processed)}; expected the capture's numbering)")
        true_frames, true_joints = true_frames[kept], true_joints[kept]
    fps = capture.get("fps")
    return evaluate_joints(*estimate, true_frames, true_names, true_joints, frame_time_s=1.0 / fps if fps else None)


#: Largest extent of one frame's joints (metres) a person can have, arms spread: a truth whose joints spread
#: wider in most frames is not in metres.
MAX_BODY_EXTENT_M = 3.0


def check_truth(path: str | os.PathLike, names: tuple[str, ...], joints: np.ndarray) -> None:
    """Refuse a truth that is not in metres; warn about joints of no known name, which are not scored.

    A truth in millimetres scored as metres gives an MPJPE of kilometres without a word of the cause; a joint
    named otherwise than the contract's (``hips`` for ``pelvis``) silently drops out of the scores.
    """
    widest = np.nanmedian(np.nanmax(np.nanmax(joints, axis=1) - np.nanmin(joints, axis=1), axis=1))
    if widest > MAX_BODY_EXTENT_M:  # read_joints_csv refuses a file without rows: every frame has some joint
        raise InputError(f"{path}: the joints of a frame spread over {widest:.4g} units (median), "
                         f"expected metres (a person spans at most {MAX_BODY_EXTENT_M:g} m; millimetres?)")
    unknown = [name for name in names if name not in JOINT_NAMES]
    if unknown:
        log.warning("%s: joints %s are none of the 17 the contract names (%s), left out of the scores",
                    path, ", ".join(unknown), ", ".join(JOINT_NAMES))


def evaluate_run(out_dir: str | os.PathLike, *, truth: str | os.PathLike | None = None) -> dict:
    """Score a run's exported joints (and silhouettes) and write ``<out_dir>/eval/metrics.json``.

    Returns
    -------
    dict
        The content of metrics.json: the fields of :meth:`JointMetrics.summary` plus ``estimate`` and
        ``truth`` (paths) and ``silhouette_iou`` (see :func:`silhouette_iou`, or None).
    """
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise InputError(f"{out_dir}: not a directory (expected the output directory of a run)")
    layout = RunLayout(out_dir)
    estimate_path = layout.joints
    if not estimate_path.is_file():
        raise InputError(f"{estimate_path}: not found (expected a run whose export stage has finished)")
    if (layout.stage_dir("export") / MARKER).is_file() and not layout.manifest("export").is_file():
        # A run began the export and did not finish it: these joints need not be the run's.
        raise InputError(f"{layout.manifest('export')}: missing, the last run did not finish its export "
                         "(expected a finished run: run the pipeline again on this output folder)")
    truth_path = Path(truth) if truth is not None else default_truth(out_dir)
    metrics = score_joints(out_dir, truth_path)
    summary = {"estimate": str(estimate_path), "truth": str(truth_path), **metrics.summary(),
               "silhouette_iou": silhouette_iou(layout.silhouettes_dir, truth_path.parent / "masks")}
    frames_io.write_json(layout.metrics, summary)
    return summary


def format_metrics(summary: dict) -> str:
    """A readable table of a metrics.json summary."""
    pck = "   ".join(f"PCK@{threshold} {value:.3f}" for threshold, value in summary["pck"].items())
    worst = summary["worst_frame"]
    lines = [
        f"MPJPE {summary['mpjpe_mm']:.1f} mm over {len(summary['scored_joints'])} joints and "
        f"{summary['frames_scored']} frames; {100 * summary['fraction_estimated']:.1f}% of "
        f"{summary['truth_frames']} truth frames estimated",
        pck,
        f"worst frame {worst['frame']}: {worst['mpjpe_mm']:.1f} mm",
    ]
    acceleration = summary.get("per_joint_acceleration_error_m_s2") or {}
    if acceleration:
        wrists = "  ".join(f"{name} {acceleration[name]:.2f}" for name in ("l_wrist", "r_wrist")
                           if name in acceleration)
        lines.append(f"acceleration error {summary['acceleration_error_m_s2']:.2f} m/s² (mean over joints; {wrists})")
    offsets = summary.get("per_joint_offset_mm") or {}  # none without the joints of the subject's frame
    if offsets:
        lines.append(f"offset-free MPJPE {summary['offset_free_mpjpe_mm']:.1f} mm (each joint's constant offset in the "
                     "subject's frame taken off: where the two skeletons put the joint in the same flesh)")
    lines += ["", f"{'joint':<20}{'MPJPE mm':>10}" + ("   constant offset mm (left, up, forward)" if offsets else "")]
    lines += [f"{name:<20}{value:>10.1f}" + ("   " + " ".join(f"{v:+6.0f}" for v in offsets[name]) if offsets else "")
              for name, value in summary["per_joint_mpjpe_mm"].items()]
    if summary["angle_errors_deg"]:
        lines += ["", f"{'angle':<20}{'error deg':>10}"]
        lines += [f"{name:<20}{value:>10.1f}" for name, value in summary["angle_errors_deg"].items()]
    iou = summary.get("silhouette_iou")
    if iou:
        cameras = ", ".join(f"{camera} {value:.3f}" for camera, value in iou["per_camera"].items())
        lines += ["", f"silhouette IoU {iou['mean']:.3f} over {iou['masks_compared']} masks ({cameras})"]
    return "\n".join(lines)
