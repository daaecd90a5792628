"""The report's pictures: inline SVG plots (quality, angles, trajectories, error), images as data URIs, the
skeleton drawn on each camera's still, and the 3-D viewer's data."""

from __future__ import annotations

import base64
from collections.abc import Mapping, Sequence

import cv2
import numpy as np

from calib.camera import Rig
from pipeline.report.run_data import AngleTable, JointSequence
from pipeline.report.svg_plot import LegendEntry, Panel, ReferenceLine, Series, Strip, line_chart, with_gaps
from pipeline.report.tracking_summary import (
    CATEGORIES,
    FrameStatus,
)
from stages.export.metrics import JointMetrics
from stages.export.overlay import draw_skeleton
from stages.export.skeleton import bones_among

#: Joints whose trajectories are plotted: the root and the extremities, where errors show most.
TRAJECTORY_JOINTS = ("pelvis", "head", "l_wrist", "r_ankle")

#: Widest overlay still embedded (pixels), and the width of the per-camera silhouette and background.
STILL_MAX_WIDTH = 520
THUMB_WIDTH = 260

#: JPEG quality of the embedded photographs (overlays, backgrounds): a sixth of PNG's size, no visible loss.
JPEG_QUALITY = 85

#: Matplotlib's "tab" colours, which the plots and report.css keep.
BLUE, ORANGE, GREEN, RED, GREY = "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#7f7f7f"

#: Colours of the tracking categories (:data:`pipeline.report.tracking_summary.CATEGORIES`), as report.css's swatches.
CATEGORY_COLOURS = {"tracked": GREEN, "initialised": BLUE, "doubtful": ORANGE, "predicted": GREY, "lost": RED}

#: Body-side colours of the plots: subject's left blue, right red, as the overlays draw them.
SIDE_COLOURS = {"l": BLUE, "r": RED, "c": GREEN}

#: Line colours of :data:`TRAJECTORY_JOINTS`.
TRAJECTORY_COLOURS = (BLUE, ORANGE, GREEN, RED)





def png_data_uri(image: np.ndarray) -> str:
    """``data:image/png;base64,...`` of a ``(H, W, 3)`` BGR or ``(H, W)`` grey ``uint8`` image."""
    return _data_uri(image, ".png", "image/png")


def jpeg_data_uri(image_bgr: np.ndarray) -> str:
    """``data:image/jpeg;base64,...`` of a ``(H, W, 3) uint8`` BGR image (:data:`JPEG_QUALITY`)."""
    return _data_uri(image_bgr, ".jpg", "image/jpeg", [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])


def _data_uri(image: np.ndarray, extension: str, mime: str, options: Sequence[int] = ()) -> str:
    ok, encoded = cv2.imencode(extension, image, list(options))
    if not ok:
        raise ValueError(f"OpenCV could not encode the image as {extension}")
    return f"data:{mime};base64," + base64.b64encode(encoded.tobytes()).decode("ascii")


def shrunk(image: np.ndarray, width: int) -> np.ndarray:
    if image.shape[1] <= width:
        return image
    factor = width / image.shape[1]
    return cv2.resize(image, None, fx=factor, fy=factor, interpolation=cv2.INTER_AREA)


def _side(name: str) -> str:
    return name[0] if name[:2] in ("l_", "r_") else "c"


def trajectory_figure(estimate: JointSequence, truth: JointSequence | None) -> str:
    """x, y, z of :data:`TRAJECTORY_JOINTS` over frames (SVG): estimate solid, truth dashed."""
    panels = [[] for _ in "xyz"]
    legend = []
    for joint, colour in zip(TRAJECTORY_JOINTS, TRAJECTORY_COLOURS, strict=True):
        for sequence, style, suffix in ((estimate, "solid", ""), (truth, "dashed", " (truth)")):
            if sequence is None or joint not in sequence.names:
                continue
            frames, positions = with_gaps(sequence.frames, sequence.joints[:, sequence.names.index(joint)])
            for k, series in enumerate(panels):
                series.append(Series(frames, positions[:, k], colour, style))
            legend.append(LegendEntry(f"{joint}{suffix}", colour, style))
    return line_chart([Panel(series, y_label=f"{axis} (m)", height=150) for series, axis in zip(panels, "xyz",
                                                                                              strict=True)],
                      x_label="frame", legend=legend, description="joint trajectories")


def error_figure(metrics: JointMetrics) -> str:
    """Per-frame MPJPE and the worst joint's error over frames (millimetres, SVG)."""
    frames, worst = with_gaps(metrics.frames, metrics.errors_mm.max(axis=1))
    series = (Series(*with_gaps(metrics.frames, metrics.per_frame_mm), BLUE, dots=True, width=1),
              Series(frames, worst, RED, "dotted", width=1.2))
    lines = [ReferenceLine(threshold, GREY, f"{threshold:g} mm") for threshold in metrics.pck_thresholds_mm]
    legend = (LegendEntry("MPJPE (scored joints)", BLUE), LegendEntry("worst joint", RED, "dotted"))
    return line_chart([Panel(series, y_label="error (mm)", reference_lines=lines, height=200, y_min=0.0)],
                      x_label="frame", legend=legend, description="error over time")


def quality_figure(statuses: Sequence[FrameStatus], limits: Mapping[str, float]) -> str:
    """The tracker's view of each frame (SVG): log-likelihood, outlier share and Σ spread of the kept fit, with
    the failure checks' limits (``limits["max_outlier_fraction"]``; the Σ spread's, each frame's own:
    ``FrameStatus.sigma_limit_m``, which follows the track's usual spread on data whose good fits are wide),
    and the frame's category as a coloured strip."""
    frames = np.array([status.frame for status in statuses])
    fitted = np.array([status.status in ("tracked", "initialised") for status in statuses])

    def fitted_only(values) -> np.ndarray:  # a frame without a fit has no value
        return np.where(fitted, np.asarray(values, dtype=float), np.nan)

    sigma_limit = Series(*with_gaps(frames, fitted_only([100 * status.sigma_limit_m for status in statuses])), RED,
                         "dotted", width=1.2)
    quantities = (("log-likelihood (nats)", [status.log_likelihood for status in statuses], [], []),
                  ("outliers (%)", [100 * status.outlier_fraction for status in statuses],
                   [ReferenceLine(100 * limits["max_outlier_fraction"], RED, "failure check")], []),
                  ("Σ spread (cm)", [100 * status.sigma_spread_m for status in statuses], [], [sigma_limit]))
    panels = []
    for label, values, lines, more in quantities:
        panels.append(Panel([Series(*with_gaps(frames, fitted_only(values)), BLUE, dots=True, width=1), *more],
                            y_label=label, reference_lines=lines, height=130))
    colours = [CATEGORY_COLOURS[status.category] for status in statuses]
    panels.append(Panel(strip=Strip(frames, colours, _frame_step(frames)), y_label="", height=36))
    legend = [LegendEntry(category, CATEGORY_COLOURS[category], "box") for category in CATEGORIES]
    legend.append(LegendEntry("failure check", RED, "dotted"))
    return line_chart(panels, x_label="frame", legend=legend, legend_below=True, description="tracking quality")


def _frame_step(frames: np.ndarray) -> float:
    return float(np.min(np.diff(frames))) if len(frames) > 1 else 1.0


def angle_groups(names: Sequence[str]) -> dict[str, list[str]]:
    """Angle names grouped by joint, left and right together: ``l_knee_flexion`` and ``r_knee_flexion`` under
    ``knee_flexion``; a name without a side is its own group. Order of first appearance."""
    groups: dict[str, list[str]] = {}
    for name in names:
        groups.setdefault(name[2:] if _side(name) != "c" else name, []).append(name)
    return groups


def angles_figure(angles: AngleTable, truth: AngleTable | None) -> str:
    """One small plot per joint of the angle table (SVG), left blue and right red, the truth dashed."""
    panels = []
    for group, names in angle_groups(angles.names).items():
        series = []
        for name in names:
            colour = SIDE_COLOURS[_side(name)]
            series.append(Series(*with_gaps(angles.frames, angles.degrees[:, angles.names.index(name)]), colour,
                                 width=1.1))
            if truth is not None and name in truth.names:
                series.append(Series(*with_gaps(truth.frames, truth.degrees[:, truth.names.index(name)]), colour,
                                     "dashed", width=1, opacity=0.7))
        panels.append(Panel(series, title=group.replace("_", " "), height=150))
    return line_chart(panels, columns=3, x_label="frame", y_label="degrees", description="joint angles")


def overlay_stills(images: Mapping[str, tuple[int, np.ndarray]], rig: Rig, estimate: JointSequence | None,
                   truth: JointSequence | None = None) -> list[tuple[str, int, np.ndarray]]:
    """Frames of some cameras with the estimated skeleton (and the truth in white) drawn on them.

    Parameters
    ----------
    images : mapping camera name -> (frame, (H, W, 3) uint8 BGR image)
    rig : the calibrated cameras (world frame)
    estimate, truth : joint sequences (or None); a frame missing from one is drawn without it

    Returns
    -------
    list of (camera, frame, image) with the skeletons drawn, shrunk to :data:`STILL_MAX_WIDTH`.
    """
    stills = []
    for camera_name, (frame, image) in images.items():
        camera = rig[camera_name]
        drawn = image
        true_pose = truth.at(frame) if truth is not None else None
        if true_pose is not None:
            drawn = draw_skeleton(drawn, camera, true_pose, truth.names, colour=(255, 255, 255))
        pose = estimate.at(frame) if estimate is not None else None
        if pose is not None:
            drawn = draw_skeleton(drawn, camera, pose, estimate.names)
        stills.append((camera_name, int(frame), shrunk(drawn, STILL_MAX_WIDTH)))
    return stills


def _viewer_series(sequence: JointSequence, frames: list[int]) -> dict:
    """One sequence for the viewer: its bones, body sides and per-frame poses (None where missing)."""
    row = {int(frame): k for k, frame in enumerate(sequence.frames)}
    poses = [np.round(sequence.joints[row[frame]], 3).tolist() if frame in row else None for frame in frames]
    return {"bones": bones_among(sequence.names), "sides": [_side(n) for n in sequence.names], "poses": poses}


def viewer_data(estimate: JointSequence, truth: JointSequence | None, fps: float,
                statuses: Sequence[FrameStatus] | None = None) -> dict:
    """The 3-D viewer's data (see assets/viewer.js): every frame of either sequence, mm-rounded, with
    the tracker's category of each (None where unknown)."""
    frames = sorted(set(estimate.frames.tolist()) | (set(truth.frames.tolist()) if truth else set()))
    category = {status.frame: status.category for status in statuses or ()}
    return {"frames": frames, "fps": float(fps), "estimate": _viewer_series(estimate, frames),
            "truth": _viewer_series(truth, frames) if truth is not None else None,
            "categories": [category.get(frame) for frame in frames]}
