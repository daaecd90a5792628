"""One self-contained HTML report per run: ``<out_dir>/export/report.html``.

It opens offline: images are inline (SVG plots, PNG masks, JPEG photographs), the 3-D viewer is inline
JavaScript on a <canvas>, and nothing is fetched but the overlay videos, which sit beside the report
(``overlay_<camera>.webm``, written when ``export.overlay_videos`` is on) and are linked. Each section
appears when its inputs exist, so the report also works on a run where only some stages finished:

- what happened: frames tracked, initialised, doubtful, predicted or lost, and why
  (:mod:`pipeline.report.tracking_summary`, from the tracking stage's per-frame records);
- the warnings behind the results (:mod:`pipeline.engine.run_warnings`, ``<out_dir>/warnings.json``);
- accuracy against the truth, when the capture has one: scored now, from this run's joints.csv, by the
  same function as ``python -m pipeline eval`` (:func:`pipeline.evaluate.score_joints`), so it can never
  be an earlier run's;
- an animated 3-D skeleton: played at the capture's frame rate (a clock in seconds, whatever the
  screen's refresh rate), orbited by dragging, zoomed with the wheel; the truth in grey when known;
- plots (inline SVG, :mod:`pipeline.report.svg_plot`): tracking quality per frame, joint angles (the export's
  angles.csv), joint trajectories and the error over time (when there is a truth);
- per camera: the skeleton drawn on one frame, that frame's silhouette, the background, and the overlay
  video (the caller passes the images and the rig; this module never opens the capture's media);
- stage timings, from each ``<out_dir>/<stage>/manifest.json``.
"""

from __future__ import annotations

import base64
import html
import json
import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calib.camera import Rig
from calib.errors import InputError
from pipeline.engine.run_warnings import WARNINGS_FILE, read_warnings
from pipeline.evaluate import default_truth, format_metrics, score_joints
from pipeline.io import atomic, frames_io
from pipeline.io.export_io import read_joints_csv
from pipeline.io.run_layout import ANGLES_FILE, MANIFEST, STAGE_NAMES, RunLayout, overlay_video_name
from pipeline.report.svg_plot import LegendEntry, Panel, ReferenceLine, Series, Strip, line_chart, with_gaps
from pipeline.report.tracking_summary import (
    CATEGORIES,
    FrameStatus,
    category_counts,
    category_totals,
    read_frame_statuses,
    tracker_params,
)
from stages.export.angles import joint_angles
from stages.export.metrics import JointMetrics
from stages.export.overlay import draw_skeleton
from stages.export.skeleton import bones_among

log = logging.getLogger(__name__)

ASSETS = Path(__file__).with_name("assets")

#: Joints whose trajectories are plotted: the root and the extremities, where errors show most.
TRAJECTORY_JOINTS = ("pelvis", "head", "l_wrist", "r_ankle")

#: Frame rate assumed when the run has no readable calibration/capture.json (viewer playback only).
DEFAULT_FPS = 25.0

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


# ---------------------------------------------------------------------------------------------
# Pure pieces: figures, stills, viewer data


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


def _shrunk(image: np.ndarray, width: int) -> np.ndarray:
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
    """The tracker's view of each frame (SVG): log-likelihood, outlier share and Σ spread of the kept fit (with
    the failure checks' limits, ``limits["max_outlier_fraction"]`` and ``limits["failure_sigma_m"]``),
    and the frame's category as a coloured strip."""
    frames = np.array([status.frame for status in statuses])
    fitted = np.array([status.status in ("tracked", "initialised") for status in statuses])
    quantities = (("log-likelihood (nats)", [status.log_likelihood for status in statuses], None),
                  ("outliers (%)", [100 * status.outlier_fraction for status in statuses],
                   100 * limits["max_outlier_fraction"]),
                  ("Σ spread (cm)", [100 * status.sigma_spread_m for status in statuses],
                   100 * limits["failure_sigma_m"]))
    panels = []
    for label, values, limit in quantities:
        values = np.where(fitted, np.asarray(values, dtype=float), np.nan)  # a frame without a fit has no value
        lines = [ReferenceLine(limit, RED, "failure check")] if limit is not None else []
        panels.append(Panel([Series(*with_gaps(frames, values), BLUE, dots=True, width=1)], y_label=label,
                            reference_lines=lines, height=130))
    colours = [CATEGORY_COLOURS[status.category] for status in statuses]
    panels.append(Panel(strip=Strip(frames, colours, _frame_step(frames)), y_label="", height=36))
    legend = [LegendEntry(category, CATEGORY_COLOURS[category], "box") for category in CATEGORIES]
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
        stills.append((camera_name, int(frame), _shrunk(drawn, STILL_MAX_WIDTH)))
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


def warning_groups(warnings: Sequence[Mapping]) -> list[tuple[str | None, list[str]]]:
    """Warnings grouped by stage and message template, in order of first appearance: ``(stage, messages)``
    per group, so that a warning repeated on a hundred frames is one line with a count."""
    groups: dict[tuple, tuple[str | None, list[str]]] = {}
    for warning in warnings:
        stage = warning.get("stage")
        key = (stage, warning.get("logger"), warning.get("template") or warning["message"])
        groups.setdefault(key, (stage, []))[1].append(warning["message"])
    return list(groups.values())


# ---------------------------------------------------------------------------------------------
# Reading what the run left on disk (each piece optional)


def stage_timings(out_dir: Path) -> list[dict]:
    """One row per stage folder with a readable manifest: stage, seconds, frames, finished_at (the stages in
    pipeline order; other stage folders with a manifest follow alphabetically)."""
    folders = [p for p in out_dir.iterdir() if (p / MANIFEST).is_file()] if out_dir.is_dir() else []
    rank = {name: i for i, name in enumerate(STAGE_NAMES)}
    folders.sort(key=lambda p: (rank.get(p.name, len(STAGE_NAMES)), p.name))
    rows = []
    for folder in folders:
        try:
            manifest = json.loads((folder / MANIFEST).read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
            log.warning("%s: unreadable manifest (%s); left out of the report", folder, error)
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
class _Run:
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


def _load_run(out_dir: Path, truth_path: str | os.PathLike | None) -> _Run:
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
    return _Run(out_dir, fps, capture, estimate, estimate_problem, truth, found_truth if truth is not None else None,
                metrics, problem, statuses, tracker_params(layout.tracking_dir), angles, angles_problem,
                read_warnings(out_dir))


# ---------------------------------------------------------------------------------------------
# HTML


def _table(header: Sequence[str], rows: Sequence[Sequence], *, raw_columns: Sequence[int] = (),
           css_class: str = "") -> str:
    """An HTML table; cells are escaped except those of ``raw_columns`` (HTML the caller built)."""
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{c if k in raw_columns else html.escape(str(c))}</td>"
                                    for k, c in enumerate(row)) + "</tr>" for row in rows)
    attribute = f" class='{css_class}'" if css_class else ""
    return f"<table{attribute}><tr>{head}</tr>{body}</table>"


def _number(value, digits: int) -> str:
    return f"{value:.{digits}f}" if isinstance(value, (int, float)) and not isinstance(value, bool) else "-"


def _summary_section(run: _Run) -> str:
    """What happened: frames estimated, the tracker's categories with their causes, warnings, MPJPE."""
    frames = run.capture.get("frames")
    facts = []
    if run.estimate is not None:
        of_capture = f" of {len(frames)} capture frames" if isinstance(frames, list) else ""
        facts.append(f"{len(run.estimate.frames)} frames estimated{of_capture}, {len(run.estimate.names)} joints, "
                     f"{run.fps:g} frames/s.")
    elif run.estimate_problem is not None:
        facts.append(f"No motion: {html.escape(run.estimate_problem)}.")
    else:
        facts.append("No export/joints.csv: the export stage has not run.")
    if run.metrics is not None:
        facts.append(f"MPJPE {run.metrics.mpjpe_mm:.1f} mm against the truth (see Accuracy).")
    facts.append(f"<a href='#warnings'>{len(run.warnings)} warning{'' if len(run.warnings) == 1 else 's'}</a>."
                 if run.warnings else "No warnings.")
    text = "<h2>What happened</h2><p>" + " ".join(facts) + "</p>"
    if run.statuses is None:
        return text + "<p class='note'>No complete tracking records: the tracking stage has not finished.</p>"
    totals, counts = category_totals(run.statuses), category_counts(run.statuses)
    rows = [(f"<span class='swatch {category}'></span>{category}", totals[category],
             "; ".join(f"{cause} ({n})" for cause, n in counts[category].most_common()) or "-")
            for category in CATEGORIES]
    return text + _table(("tracker", "frames", "why"), rows, raw_columns=(0,), css_class="story")


def _warnings_section(run: _Run) -> str:
    if not run.warnings:
        return ""
    items = []
    for stage, messages in warning_groups(run.warnings):
        where = html.escape(stage) if stage else "run"
        first = html.escape(messages[0])
        if len(messages) == 1:
            items.append(f"<li><b>{where}</b>: {first}</li>")
        else:
            rest = "".join(f"<li>{html.escape(message)}</li>" for message in messages[1:])
            items.append(f"<li><b>{where}</b>: {first} <details><summary>and {len(messages) - 1} more like it"
                         f"</summary><ul>{rest}</ul></details></li>")
    return (f"<h2 id='warnings'>Warnings ({len(run.warnings)})</h2><p class='note'>Every warning behind these "
            f"results, by the stage that logged it ({WARNINGS_FILE} in the run folder).</p>"
            f"<ul class='warnings'>{''.join(items)}</ul>")


def _accuracy_section(run: _Run) -> str:
    if run.metrics is not None:
        text = format_metrics({**run.metrics.summary(), "silhouette_iou": None})
        return (f"<h2>Accuracy</h2><p class='note'>This run's joints.csv against {html.escape(str(run.truth_path))}"
                " (as <code>python -m pipeline eval</code> scores it; eval also scores the silhouettes).</p>"
                f"<pre>{html.escape(text)}</pre>")
    if run.scoring_problem is not None:
        return f"<h2>Accuracy</h2><p class='note'>Not scored: {html.escape(run.scoring_problem)}</p>"
    return ""


def _quality_section(run: _Run) -> str:
    if not run.statuses:
        return ""
    return ("<h2>Tracking quality</h2><p class='note'>Per frame, from the tracker's records: the kept fit's "
            "log-likelihood, the share of data it explains as outliers and the spread of its Σ (a fit beyond a "
            "dashed limit fails the checks and is re-initialised or flagged doubtful); below, each frame's "
            "category.</p>"
            + quality_figure(run.statuses, run.limits))


def _angles_section(run: _Run) -> str:
    if run.angles_problem is not None:
        return f"<h2>Joint angles</h2><p class='note'>Not shown: {html.escape(run.angles_problem)}</p>"
    if run.angles is None or not len(run.angles.frames):
        return ""
    truth = None
    if run.truth is not None:
        names, degrees = joint_angles(run.truth.joints, run.truth.names)
        truth = AngleTable(run.truth.frames, names, degrees)
    caption = "Left blue, right red" + (", truth dashed" if truth is not None else "")
    return (f"<h2>Joint angles</h2><p class='note'>From export/{ANGLES_FILE}. {caption}.</p>"
            + angles_figure(run.angles, truth))


def _plots_section(run: _Run) -> str:
    if run.estimate is None:
        return ""
    note = "Estimate solid, truth dashed." if run.truth is not None else ""
    parts = [f"<h2>Joint trajectories</h2><p class='note'>{note}</p>", trajectory_figure(run.estimate, run.truth)]
    if run.metrics is not None:
        parts += ["<h2>Error over time</h2>", error_figure(run.metrics)]
    return "".join(parts)


def _mask_thumb(path: Path) -> str | None:
    """A silhouette or background file as an inline thumbnail, or None when absent or unreadable."""
    if not path.is_file():
        return None
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        return None
    image = _shrunk(image, THUMB_WIDTH)
    return png_data_uri(image) if image.ndim == 2 else jpeg_data_uri(image)


def _cameras_section(run: _Run, rig: Rig | None, images: Mapping[str, tuple[int, np.ndarray]] | None) -> str:
    """Per camera: the skeleton on one frame, that frame's silhouette, the background, the overlay video."""
    stills = {camera: (frame, image) for camera, frame, image in
              (overlay_stills(images, rig, run.estimate, run.truth) if rig is not None and images else [])}
    cameras = list(stills) or [str(name) for name in run.capture.get("cameras", []) or []]
    layout = RunLayout(run.out_dir)
    rows = []
    for camera in cameras:
        frame = stills[camera][0] if camera in stills else None
        cells = []
        if camera in stills:
            cells.append((jpeg_data_uri(stills[camera][1]), f"frame {frame}"))
        if frame is not None and (mask := _mask_thumb(layout.silhouette(camera, frame))):
            cells.append((mask, f"silhouette, frame {frame}"))
        if background := _mask_thumb(layout.background(camera)):
            cells.append((background, "background"))
        figures = "".join(f"<figure><img alt='{html.escape(camera)} {html.escape(caption)}' src='{uri}'>"
                          f"<figcaption>{html.escape(caption)}</figcaption></figure>" for uri, caption in cells)
        video = overlay_video_name(camera)
        if layout.overlay_video(camera).is_file():
            figures += (f"<figure><video controls muted loop preload='metadata' src='{html.escape(video)}'></video>"
                        f"<figcaption><a href='{html.escape(video)}'>{html.escape(video)}</a></figcaption></figure>")
        if figures:
            rows.append(f"<h3>{html.escape(camera)}</h3><div class='stills'>{figures}</div>")
    if not rows:
        return ""
    drawn = [what for what, sequence in (("estimate in colour (subject's left blue, right red)", run.estimate),
                                         ("truth in white", run.truth))
             if sequence is not None and any(sequence.at(frame) is not None for frame, _ in stills.values())]
    legend = (", ".join(drawn) + ". ").capitalize() if drawn else ""
    return f"<h2>Cameras</h2><p class='note'>{legend}Silhouettes white on black.</p>" + "".join(rows)


def _timings_section(rows: list[dict]) -> str:
    if not rows:
        return "<h2>Stage timings</h2><p class='note'>No stage manifest found.</p>"
    table_rows = []
    for row in rows:
        seconds, frames = row["seconds"], row["frames"]
        timed = isinstance(seconds, (int, float)) and isinstance(frames, int) and frames > 0
        table_rows.append((row["stage"], _number(seconds, 2), frames if frames is not None else "-",
                           _number(1000 * seconds / frames if timed else None, 1), row["workers"] or "-",
                           row["finished_at"] or "-"))
    header = ("stage", "seconds", "frames", "ms/frame", "workers", "finished")
    return "<h2>Stage timings</h2>" + _table(header, table_rows)


def _viewer_section(run: _Run) -> str:
    if run.estimate is None:
        return ""
    # "</" inside a <script> would end it early; JSON allows the escaped form.
    data = json.dumps(viewer_data(run.estimate, run.truth, run.fps, run.statuses), separators=(",", ":"))
    data = data.replace("</", "<\\/")
    script = (ASSETS / "viewer.js").read_text(encoding="utf-8")
    truth = "; truth in grey" if run.truth is not None else ""
    return ("<h2>3-D skeleton</h2><p class='note'>Drag to orbit, wheel to zoom, double-click to reset; played at "
            f"the capture's {run.fps:g} frames/s (or slower){truth}.</p>"
            "<canvas id='skeleton-canvas' width='720' height='540'></canvas><div class='controls'>"
            "<button id='skeleton-play' type='button'>pause</button> "
            "<input id='skeleton-frame' type='range' min='0' max='0' value='0'> "
            "<select id='skeleton-speed'><option value='1'>1×</option><option value='0.5'>½×</option>"
            "<option value='0.25'>¼×</option></select> <span id='skeleton-label'></span></div>"
            f"<script type='application/json' id='skeleton-data'>{data}</script><script>{script}</script>")


#: Reports JavaScript errors on the page itself, so a headless browser's DOM dump shows them.
_ERROR_HOOK = ("window.onerror = function (message, source, line) { document.getElementById('js-errors')"
               ".textContent += message + ' (line ' + line + ')\\n'; };")


def build_report(out_dir: str | os.PathLike, *, truth_path: str | os.PathLike | None = None,
                 rig: Rig | None = None, images: Mapping[str, tuple[int, np.ndarray]] | None = None) -> str:
    """The report's HTML text for the run in ``out_dir``.

    Parameters
    ----------
    out_dir : the run's output directory
    truth_path : ground-truth joints.csv; by default the capture's (``capture_dir`` in capture.json), if any
    rig, images : the calibrated rig and, per camera name, one ``(frame, BGR image)`` for the overlay
        stills; without them the cameras section shows only the silhouette stage's backgrounds
    """
    out_dir = Path(out_dir)
    run = _load_run(out_dir, truth_path)
    sections = [_summary_section(run), _warnings_section(run), _accuracy_section(run), _viewer_section(run),
                _quality_section(run), _angles_section(run), _plots_section(run),
                _cameras_section(run, rig, images), _timings_section(stage_timings(out_dir))]
    css = (ASSETS / "report.css").read_text(encoding="utf-8")
    title = f"Motion capture report: {html.escape(out_dir.resolve().name)}"
    return (f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{title}</title>"
            f"<style>{css}</style><script>{_ERROR_HOOK}</script></head><body><h1>{title}</h1>"
            "<div id='js-errors'></div><p class='note'>Viewer: <span id='skeleton-status'>no data</span></p>"
            + "\n".join(section for section in sections if section) + "</body></html>\n")


def write_report(out_dir: str | os.PathLike, *, truth_path: str | os.PathLike | None = None,
                 rig: Rig | None = None, images: Mapping[str, tuple[int, np.ndarray]] | None = None) -> Path:
    """Write ``<out_dir>/export/report.html`` (see :func:`build_report`) and return its path."""
    path = RunLayout(out_dir).report
    atomic.write_text(path, build_report(out_dir, truth_path=truth_path, rig=rig, images=images))
    return path
