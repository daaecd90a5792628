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

import html
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np

from calib.camera import Rig
from calib.errors import InputError
from pipeline.engine.run_warnings import WARNINGS_FILE
from pipeline.evaluate import format_metrics
from pipeline.io import atomic, frames_io
from pipeline.io.run_layout import ANGLES_FILE, RunLayout, overlay_video_name
from pipeline.report.figures import (
    THUMB_WIDTH,
    angles_figure,
    error_figure,
    jpeg_data_uri,
    overlay_stills,
    png_data_uri,
    quality_figure,
    shrunk,
    trajectory_figure,
    viewer_data,
)
from pipeline.report.run_data import AngleTable, LoadedRun, load_run, stage_timings
from pipeline.report.tracking_summary import (
    CATEGORIES,
    category_counts,
    category_totals,
)
from pipeline.terminal import fold_frame_messages
from stages.export.angles import joint_angles

ASSETS = Path(__file__).with_name("assets")


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


def _summary_section(run: LoadedRun) -> str:
    """What happened: frames estimated, the tracker's categories with their causes, warnings, MPJPE."""
    frames = run.capture.get("frames")
    facts = []
    if run.estimate is not None:
        of_capture = f" of {len(frames)} capture frames" if isinstance(frames, list) else ""
        facts.append(f"{len(run.estimate.frames)} frames estimated{of_capture}, {len(run.estimate.names)} joints, "
                     f"{run.fps:g} frames/s.")
        if run.body_height is not None:
            facts.append(run.body_height.sentence())
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


def _warnings_section(run: LoadedRun) -> str:
    if not run.warnings:
        return ""
    items = []
    for stage, messages in warning_groups(run.warnings):
        where = html.escape(stage) if stage else "run"
        messages = fold_frame_messages(messages)  # the same text on many frames: one line naming them
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


def _accuracy_section(run: LoadedRun) -> str:
    if run.metrics is not None:
        text = format_metrics({**run.metrics.summary(), "silhouette_iou": None})
        return (f"<h2>Accuracy</h2><p class='note'>This run's joints.csv against {html.escape(str(run.truth_path))}"
                " (as <code>python -m pipeline eval</code> scores it; eval also scores the silhouettes).</p>"
                f"<pre>{html.escape(text)}</pre>")
    if run.scoring_problem is not None:
        return f"<h2>Accuracy</h2><p class='note'>Not scored: {html.escape(run.scoring_problem)}</p>"
    return ""


def _quality_section(run: LoadedRun) -> str:
    if not run.statuses:
        return ""
    return ("<h2>Tracking quality</h2><p class='note'>Per frame, from the tracker's records: the kept fit's "
            "log-likelihood, the share of data it explains as outliers and the spread of its Σ (a fit beyond a "
            "dashed limit fails the checks and is re-initialised or flagged doubtful); below, each frame's "
            "category.</p>"
            + quality_figure(run.statuses, run.limits))


def _angles_section(run: LoadedRun) -> str:
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


def _plots_section(run: LoadedRun) -> str:
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
    image = shrunk(image, THUMB_WIDTH)
    return png_data_uri(image) if image.ndim == 2 else jpeg_data_uri(image)


def _cameras_section(run: LoadedRun, rig: Rig | None, images: Mapping[str, tuple[int, np.ndarray]] | None) -> str:
    """Per camera: the skeleton on one frame, that frame's silhouette, the background, the overlay video."""
    stills = {camera: (frame, image) for camera, frame, image in
              (overlay_stills(images, rig, run.estimate, run.truth) if rig is not None and images else [])}
    cameras = list(stills) or [str(name) for name in run.capture.get("cameras", []) or []]
    layout = RunLayout(run.out_dir)
    check = _record(layout.calibration_check, "disagreement_m")
    shifts = _record(layout.floor_shifts, "shifts_px")
    sync = _record(layout.sync_check, "lag")
    decided = _record(layout.calibration_refinement, "turns_deg")
    refinement = decided if decided and decided.get("kept") is True else None
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
        if hidden := _mask_thumb(layout.hidden_part(camera)):
            cells.append((hidden, "hidden behind something, not carved"))
        if changed := _mask_thumb(layout.room_change(camera)):
            cells.append((changed, "changed since the plate, not carved"))
        figures = "".join(f"<figure><img alt='{html.escape(camera)} {html.escape(caption)}' src='{uri}'>"
                          f"<figcaption>{html.escape(caption)}</figcaption></figure>" for uri, caption in cells)
        video = overlay_video_name(camera)
        if layout.overlay_video(camera).is_file():
            figures += (f"<figure><video controls muted loop preload='metadata' src='{html.escape(video)}'></video>"
                        f"<figcaption><a href='{html.escape(video)}'>{html.escape(video)}</a></figcaption></figure>")
        if figures:
            rows.append(f"<h3>{html.escape(camera)}</h3>{_agreement(check, camera)}{_floor_shift(shifts, camera)}"
                        f"{_lag(sync, camera)}"
                        f"{_turn(refinement, camera)}"
                        f"{_part_note(layout.hidden_part(camera), HIDDEN_NOTE)}"
                        f"{_part_note(layout.room_change(camera), ROOM_NOTE)}"
                        f"<div class='stills'>{figures}</div>")
    if not rows:
        return ""
    drawn = [what for what, sequence in (("estimate in colour (subject's left blue, right red)", run.estimate),
                                         ("truth in white", run.truth))
             if sequence is not None and any(sequence.at(frame) is not None for frame, _ in stills.values())]
    legend = (", ".join(drawn) + ". ").capitalize() if drawn else ""
    rig_file = layout.refined_rig.relative_to(layout.root).as_posix()
    return (f"<h2>Cameras</h2><p class='note'>{legend}Silhouettes white on black.</p>"
            f"{_refinement_note(decided, rig_file)}"
            + "".join(rows))


def _record(path: Path, key: str) -> dict | None:
    """A stage's JSON record holding a mapping under ``key`` (the calibration check,
    `pipeline.graph._check_calibration`; the floor test's shifts, `pipeline.graph.masks_with_floor_shifts`; the
    calibration refinement, `pipeline.graph.refined_rig`; the sync check, `pipeline.graph._write_sync_check`), or None
    when absent or unreadable (a report never fails on it)."""
    try:
        record = frames_io.read_json(path)
    except (OSError, InputError):
        return None
    return record if isinstance(record, dict) and isinstance(record.get(key), dict) else None


def _refinement_note(record: dict | None, rig_file: str) -> str:
    """What the refinement of the cameras' orientations decided, when turns were proposed: kept (the cameras used
    then in ``rig_file``, relative to the run folder) or refused."""
    if not record or record.get("tangencies_agree") is not True:
        return ""
    figures = [record.get(key) for key in ("disagreement_before_m", "disagreement_after_m", "explained_before",
                                           "explained_after")]
    if not all(isinstance(value, (int, float)) for value in figures):
        return ""
    before, after, explained_before, explained_after = figures
    measured = (f"the tangencies' median disagreement {1000 * before:.1f} → {1000 * after:.1f} mm, the share of the "
                f"silhouettes the visual hull explains {100 * explained_before:.1f} → {100 * explained_after:.1f} %")
    if record.get("kept") is True:
        return (f"<p class='note'>Calibration refined from the silhouettes: each camera turned about its centre "
                f"({measured}); the cameras the reconstruction and these stills used are in "
                f"{html.escape(rig_file)}.</p>")
    return (f"<p class='note'>Calibration <strong>not refined</strong>: turning the cameras made the tangencies agree "
            f"but the silhouettes less consistent ({measured}): the calibration is off in a way turns cannot mend "
            "(the cameras' positions?).</p>")


def _turn(refinement: dict | None, camera: str) -> str:
    """A note on how far the camera was turned from its calibration to agree with the others' silhouettes."""
    turn = refinement["turns_deg"].get(camera) if refinement else None
    if not isinstance(turn, (int, float)):
        return ""
    return f"<p class='note'>Calibration refined from the silhouettes: turned by {turn:.2f}° about its centre.</p>"


#: The notes on the parts of a camera's view that it does not carve (each shown when its file exists).
HIDDEN_NOTE = ("Part of its view is <strong>hidden behind something</strong> in front of the subject on most "
               "frames (the other cameras place him there, this one shows the background): it does not carve there "
               "(white in the figure).")
ROOM_NOTE = ("Part of its view <strong>changed since its clean plate</strong> (something put down or moved after it "
             "was taken, in nearly every frame and apart from the subject): the background there is taken from the "
             "frames, and it does not carve there (white in the figure).")


def _part_note(path: Path, note: str) -> str:
    """``note`` as a paragraph when the part of the camera's view at ``path`` exists, else nothing."""
    return f"<p class='note'>{note}</p>" if path.is_file() else ""


def _agreement(check: dict | None, camera: str) -> str:
    """A note on how far the camera's silhouettes agree with the other cameras' through the calibration."""
    value = check["disagreement_m"].get(camera) if check else None
    if check and camera in check["disagreement_m"] and value is None:
        return ("<p class='note'>Calibration check: not checked, its silhouettes were empty or reached the image's "
                "border on the frames checked.</p>")
    if not isinstance(value, (int, float)):
        return ""
    if camera in (check.get("at_fault") or []):
        return (f"<p class='note'>Calibration check: its silhouettes <strong>disagree</strong> with the other "
                f"cameras' by {100 * value:.0f} cm at the subject: check this camera's calibration (names swapped "
                "with another camera's, moved since it was calibrated), then its silhouettes (something only it "
                "sees, in every frame).</p>")
    return (f"<p class='note'>Calibration check: its silhouettes agree with the other cameras' within "
            f"{100 * value:.1f} cm at the subject (epipolar tangency).</p>")


def _floor_shift(record: dict | None, camera: str) -> str:
    """A note on where the floor test of shadows compares the camera's floor points in the other views, when the
    shadows put them off the calibration's mapping (`silhouettes/floor_shifts.json`); else nothing."""
    shifted = {other: shift for other, shift in ((record or {}).get("shifts_px", {}).get(camera) or {}).items()
               if isinstance(shift, list) and any(shift)}
    if not shifted:
        return ""
    views = ", ".join(f"{html.escape(str(other))} {float(np.hypot(*shift)):.0f}" for other, shift in shifted.items())
    return (f"<p class='note'>Floor test of shadows: the other views see its floor points off where the calibration "
            f"puts them, by {views} pixels, and the test also looks there (the calibration is off by about that at "
            "the floor).</p>")


def _lag(record: dict | None, camera: str) -> str:
    """A note on a camera whose silhouettes agree best with the other cameras' some frames apart
    (`export/sync_check.json`, ``export.sync_check``); else nothing."""
    lag = (record or {}).get("lag", {}).get(camera)
    if not isinstance(lag, int) or not lag:
        return ""
    offset = (record.get("frame_offsets") or {}).get(camera, 0)  # 0: the offset given for it cancels out
    remedy = (f"<code>frame_offsets: {{{html.escape(camera)}: {offset}}}</code> in capture.yaml makes up for it"
              if offset else "capture.yaml should give it no frame offset")
    return (f"<p class='note'>Sync check: its silhouettes agree best with the other cameras' {abs(lag)} frame(s) "
            f"{'later' if lag > 0 else 'earlier'}: its media seem to run {'behind' if lag > 0 else 'ahead of'} "
            f"theirs (not synchronised?); {remedy}.</p>")


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


def _viewer_section(run: LoadedRun) -> str:
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
    run = load_run(out_dir, truth_path)
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
