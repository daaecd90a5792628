"""One self-contained HTML report per run: ``<out_dir>/export/report.html``.

It opens offline: images are inline base64 PNG, the 3-D viewer is inline JavaScript on a <canvas>,
and nothing is fetched. Each section appears when its inputs exist, so the report also works on a
run where only some stages finished:

- stage timings, from each ``<out_dir>/<stage>/manifest.json`` (``timing`` or ``timings``; missing
  keys shown as "-");
- accuracy, from ``<out_dir>/eval/metrics.json`` or, failing that, computed against the truth;
- plots (matplotlib, off-screen) of joint trajectories against the truth and of the error over time;
- overlay stills: the skeleton drawn on one frame of some cameras (the caller passes the images and
  the rig; this module never opens the capture's media);
- an animated 3-D skeleton (rotating orthographic view, play/pause, frame slider), with the truth in
  grey when known.
"""

from __future__ import annotations

import base64
import html
import io
import json
import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from matplotlib.figure import Figure

from calib.camera import Rig
from calib.errors import InputError
from pipeline import atomic, frames_io
from pipeline.evaluate import CAPTURE_JSON, EVAL_DIR, METRICS_FILE, default_truth, format_metrics
from pipeline.export_io import JOINTS_FILE, read_joints_csv
from stages.export.metrics import JointMetrics, evaluate_joints
from stages.export.overlay import draw_skeleton
from stages.export.skeleton import bones_among

log = logging.getLogger(__name__)

REPORT_FILE = "report.html"
ASSETS = Path(__file__).with_name("report_assets")

#: Stages in pipeline order; other stage folders with a manifest follow alphabetically.
STAGE_ORDER = ("calibration", "silhouettes", "reconstruction", "tracking", "export")

#: Joints whose trajectories are plotted: the root and the extremities, where errors show most.
TRAJECTORY_JOINTS = ("pelvis", "head", "l_wrist", "r_ankle")

#: Frame rate assumed when the run has no readable calibration/capture.json (viewer playback only).
DEFAULT_FPS = 25.0

#: Widest still image embedded (pixels); larger frames are shrunk to keep the report small.
STILL_MAX_WIDTH = 640


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


# ---------------------------------------------------------------------------------------------
# Pure pieces: figures, stills, viewer data


def png_data_uri(image_bgr: np.ndarray) -> str:
    """``data:image/png;base64,...`` of a ``(H, W, 3) uint8`` BGR image."""
    ok, encoded = cv2.imencode(".png", image_bgr)
    if not ok:
        raise ValueError("OpenCV could not encode the image as PNG")
    return "data:image/png;base64," + base64.b64encode(encoded.tobytes()).decode("ascii")


def _figure_uri(figure: Figure) -> str:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=90, bbox_inches="tight")
    return "data:image/png;base64," + base64.b64encode(buffer.getvalue()).decode("ascii")


def trajectory_figure(estimate: JointSequence, truth: JointSequence | None) -> Figure:
    """x, y, z of :data:`TRAJECTORY_JOINTS` over frames: estimate solid, truth dashed."""
    figure = Figure(figsize=(11, 6.5))
    axes = figure.subplots(3, 1, sharex=True)
    colours = ("tab:blue", "tab:orange", "tab:green", "tab:red")
    for joint, colour in zip(TRAJECTORY_JOINTS, colours, strict=True):
        for sequence, style, suffix in ((estimate, "-", ""), (truth, "--", " (truth)")):
            if sequence is None or joint not in sequence.names:
                continue
            j = sequence.names.index(joint)
            for k, ax in enumerate(axes):
                ax.plot(sequence.frames, sequence.joints[:, j, k], style, color=colour, lw=1.2,
                        label=f"{joint}{suffix}" if k == 0 else None)
    for ax, axis in zip(axes, "xyz", strict=True):
        ax.set_ylabel(f"{axis} (m)")
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("frame")
    axes[0].legend(ncol=4, fontsize=8, loc="upper left", bbox_to_anchor=(0, 1.35))
    return figure


def error_figure(metrics: JointMetrics) -> Figure:
    """Per-frame MPJPE and the worst joint's error over frames (millimetres)."""
    figure = Figure(figsize=(11, 3.2))
    ax = figure.subplots()
    ax.plot(metrics.frames, metrics.per_frame_mm, ".-", lw=1, ms=3, label="MPJPE (scored joints)")
    ax.plot(metrics.frames, metrics.errors_mm.max(axis=1), ":", lw=1, color="tab:red", label="worst joint")
    for threshold in metrics.pck_thresholds_mm:
        ax.axhline(threshold, color="grey", lw=0.8, ls="--")
    ax.set_xlabel("frame")
    ax.set_ylabel("error (mm)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return figure


def overlay_stills(images: Mapping[str, tuple[int, np.ndarray]], rig: Rig, estimate: JointSequence,
                   truth: JointSequence | None = None) -> list[tuple[str, int, np.ndarray]]:
    """Frames of some cameras with the estimated skeleton (and the truth in white) drawn on them.

    Parameters
    ----------
    images : mapping camera name -> (frame, (H, W, 3) uint8 BGR image)
    rig : the calibrated cameras (world frame)
    estimate, truth : joint sequences; a frame missing from one is drawn without it

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
        pose = estimate.at(frame)
        if pose is not None:
            drawn = draw_skeleton(drawn, camera, pose, estimate.names)
        if drawn.shape[1] > STILL_MAX_WIDTH:
            factor = STILL_MAX_WIDTH / drawn.shape[1]
            drawn = cv2.resize(drawn, None, fx=factor, fy=factor, interpolation=cv2.INTER_AREA)
        stills.append((camera_name, int(frame), drawn))
    return stills


def _viewer_series(sequence: JointSequence, frames: list[int]) -> dict:
    """One sequence for the viewer: its bones, body sides and per-frame poses (None where missing)."""
    row = {int(frame): k for k, frame in enumerate(sequence.frames)}
    poses = [np.round(sequence.joints[row[frame]], 3).tolist() if frame in row else None for frame in frames]
    sides = ["l" if n.startswith("l_") else "r" if n.startswith("r_") else "c" for n in sequence.names]
    return {"bones": bones_among(sequence.names), "sides": sides, "poses": poses}


def viewer_data(estimate: JointSequence, truth: JointSequence | None, fps: float) -> dict:
    """The 3-D viewer's data (see report_assets/viewer.js): every frame of either sequence, mm-rounded."""
    frames = sorted(set(estimate.frames.tolist()) | (set(truth.frames.tolist()) if truth else set()))
    return {"frames": frames, "fps": float(fps), "estimate": _viewer_series(estimate, frames),
            "truth": _viewer_series(truth, frames) if truth is not None else None}


# ---------------------------------------------------------------------------------------------
# Reading what the run left on disk (each piece optional)


def stage_timings(out_dir: Path) -> list[dict]:
    """One row per stage folder with a readable manifest: stage, seconds, frames, finished_at."""
    folders = [p for p in out_dir.iterdir() if (p / "manifest.json").is_file()] if out_dir.is_dir() else []
    rank = {name: i for i, name in enumerate(STAGE_ORDER)}
    folders.sort(key=lambda p: (rank.get(p.name, len(STAGE_ORDER)), p.name))
    rows = []
    for folder in folders:
        try:
            manifest = json.loads((folder / "manifest.json").read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
            log.warning("%s: unreadable manifest (%s); left out of the report", folder, error)
            continue
        timing = manifest.get("timing") or {}
        timing = timing if isinstance(timing, dict) else {}
        rows.append({"stage": folder.name, "seconds": timing.get("seconds"), "frames": timing.get("frames"),
                     "workers": timing.get("workers"), "finished_at": manifest.get("finished_at")})
    return rows


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


# ---------------------------------------------------------------------------------------------
# HTML


def _table(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _number(value, digits: int) -> str:
    return f"{value:.{digits}f}" if isinstance(value, (int, float)) and not isinstance(value, bool) else "-"


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


@dataclass(frozen=True)
class _Run:
    """What the report shows of one run; every field but ``fps`` may be missing."""

    fps: float
    capture: dict
    estimate: JointSequence | None
    truth: JointSequence | None
    metrics: JointMetrics | None
    scoring_problem: str | None
    saved_metrics: dict | None


def _load_run(out_dir: Path, truth_path: str | os.PathLike | None) -> _Run:
    summary_path = out_dir / CAPTURE_JSON
    capture = frames_io.read_json(summary_path) if summary_path.is_file() else {}
    capture = capture if isinstance(capture, dict) else {}
    fps = capture.get("fps")
    fps = float(fps) if isinstance(fps, (int, float)) and fps > 0 else DEFAULT_FPS
    estimate = _read_sequence(out_dir / "export" / JOINTS_FILE)
    found_truth = _find_truth(out_dir, truth_path)
    truth = _read_sequence(found_truth) if found_truth is not None else None
    metrics, problem = None, None
    if estimate is not None and truth is not None:
        try:
            metrics = evaluate_joints(estimate.frames, estimate.names, estimate.joints,
                                      truth.frames, truth.names, truth.joints)
        except InputError as error:
            problem = str(error)
    metrics_path = out_dir / EVAL_DIR / METRICS_FILE
    saved = frames_io.read_json(metrics_path) if metrics_path.is_file() else None
    return _Run(fps, capture, estimate, truth, metrics, problem, saved)


def _motion_section(run: _Run) -> str:
    if run.estimate is None:
        return "<h2>Motion</h2><p class='note'>No export/joints.csv: the export stage has not run.</p>"
    frames = run.capture.get("frames")
    of_capture = f" of {len(frames)} capture frames" if isinstance(frames, list) else ""
    return (f"<h2>Motion</h2><p>{len(run.estimate.frames)} frames estimated{of_capture}, "
            f"{len(run.estimate.names)} joints, {run.fps:g} frames/s.</p>")


def _accuracy_section(run: _Run) -> str:
    if run.saved_metrics is not None:
        title, summary = "Accuracy (eval/metrics.json)", run.saved_metrics
    elif run.metrics is not None:
        title, summary = "Accuracy", {"silhouette_iou": None, **run.metrics.summary()}
    elif run.scoring_problem is not None:
        return f"<h2>Accuracy</h2><p class='note'>Not scored: {html.escape(run.scoring_problem)}</p>"
    else:
        return ""
    try:
        text = format_metrics(summary)
    except (KeyError, TypeError, AttributeError):
        return f"<h2>{title}</h2><p class='note'>metrics.json is not in the expected layout.</p>"
    return f"<h2>{title}</h2><pre>{html.escape(text)}</pre>"


def _plots_section(run: _Run) -> str:
    if run.estimate is None:
        return ""
    parts = ["<h2>Joint trajectories</h2>",
             f"<img alt='trajectories' src='{_figure_uri(trajectory_figure(run.estimate, run.truth))}'>"]
    if run.metrics is not None:
        parts += ["<h2>Error over time</h2>",
                  f"<img alt='error over time' src='{_figure_uri(error_figure(run.metrics))}'>"]
    return "".join(parts)


def _stills_section(run: _Run, rig: Rig | None, images: Mapping[str, tuple[int, np.ndarray]] | None) -> str:
    if run.estimate is None or rig is None or not images:
        return ""
    figures = "".join(
        f"<figure><img alt='{html.escape(camera)}' src='{png_data_uri(image)}'>"
        f"<figcaption>{html.escape(camera)}, frame {frame}</figcaption></figure>"
        for camera, frame, image in overlay_stills(images, rig, run.estimate, run.truth))
    return ("<h2>Overlays</h2><p class='note'>Estimate in colour (subject's left blue, right red), "
            f"truth in white.</p><div class='stills'>{figures}</div>")


def _viewer_section(run: _Run) -> str:
    if run.estimate is None:
        return ""
    # "</" inside a <script> would end it early; JSON allows the escaped form.
    data = json.dumps(viewer_data(run.estimate, run.truth, run.fps), separators=(",", ":"))
    data = data.replace("</", "<\\/")
    script = (ASSETS / "viewer.js").read_text(encoding="utf-8")
    return ("<h2>3-D skeleton</h2><p class='note'>Orthographic view turning about the vertical; "
            "truth in grey.</p><canvas id='skeleton-canvas' width='640' height='480'></canvas><div>"
            "<button id='skeleton-play' type='button'>pause</button> "
            "<input id='skeleton-frame' type='range' min='0' max='0' value='0'> "
            "<span id='skeleton-label'></span></div>"
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
        stills; without them that section is left out
    """
    out_dir = Path(out_dir)
    run = _load_run(out_dir, truth_path)
    sections = [_timings_section(stage_timings(out_dir)), _motion_section(run), _accuracy_section(run),
                _plots_section(run), _stills_section(run, rig, images), _viewer_section(run)]
    css = (ASSETS / "report.css").read_text(encoding="utf-8")
    title = f"Motion capture report: {html.escape(out_dir.resolve().name)}"
    return (f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{title}</title>"
            f"<style>{css}</style><script>{_ERROR_HOOK}</script></head><body><h1>{title}</h1>"
            "<div id='js-errors'></div><p class='note'>Viewer: <span id='skeleton-status'>no data</span></p>"
            + "\n".join(section for section in sections if section) + "</body></html>\n")


def write_report(out_dir: str | os.PathLike, *, truth_path: str | os.PathLike | None = None,
                 rig: Rig | None = None, images: Mapping[str, tuple[int, np.ndarray]] | None = None) -> Path:
    """Write ``<out_dir>/export/report.html`` (see :func:`build_report`) and return its path."""
    path = Path(out_dir) / "export" / REPORT_FILE
    atomic.write_text(path, build_report(out_dir, truth_path=truth_path, rig=rig, images=images))
    return path
