"""The markdown of the results page, suite by suite: table cells (:func:`fmt`), tables (:func:`format_table`),
each suite's tables and the notes that explain them."""

from __future__ import annotations

import math
from collections.abc import Sequence

from pipeline.lab.bench.targets import judge_targets


def fmt(value, digits: int = 1) -> str:
    """A table cell: numbers rounded, NaN and None as "–", booleans as yes/no."""
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return "–" if not math.isfinite(value) else f"{value:.{digits}f}"
    return str(value)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def format_table(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    """A GitHub-flavoured markdown table; columns of numbers (missing values aside) right-aligned."""
    numeric = [any(_is_number(row[k]) for row in rows) and all(_is_number(row[k]) or row[k] is None for row in rows)
               for k in range(len(header))]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---:" if n else "---" for n in numeric) + "|"]
    lines += ["| " + " | ".join(fmt(value) for value in row) + " |" for row in rows]
    return "\n".join(lines)


def percent(fraction) -> str:
    return "–" if fraction is None else f"{100 * fraction:.0f} %"


def provenance(section: dict) -> str:
    made = section["made"]
    size = "quick (smoke-test size)" if section["quick"] else "full"
    machine = f"{made['cpus']} CPUs" + (f", {made['machine']}" if made.get("machine") else "")
    reference = made.get("reference_s")
    speed = ("" if not reference else
             f", reference workload {reference[0]:.2f} s before / {reference[1]:.2f} s after")
    return (f"{size}; {made['date']}, commit {made['commit']}, {made['seconds']:.0f} s, "
            f"load average {made['load_before']:.1f} before / {made['load_after']:.1f} after{speed} "
            f"({machine})\n\n```\n{section['command']}\n```")


def format_targets(results: dict) -> str:
    rows = [(t["suite"], t["target"], t["threshold"], fmt(t["value"], t["digits"]), "met" if t["met"] else "**MISSED**")
            for t in judge_targets(results)]
    return format_table(("suite", "target", "threshold", "measured", "verdict"), rows)


def format_speed(speed: dict) -> str:
    long, short, tracker = speed["long"], speed["short"], speed.get("tracker", {})
    recipe = speed["recipe"]
    lines = [f"Capture `{speed['capture']}`: clip {recipe['clip']}, {recipe['cameras']} cameras {recipe['size']}, "
             f"{recipe['media']}, {speed['fps_capture']:g} fps, {speed['frames']} frames; "
             f"`python -m pipeline run` on a fresh output directory, {speed['workers']} workers.", ""]
    lines.append(format_table(
        ("run", "frames", "ok", "wall s", "frames/s", "peak RSS MB", "load before"),
        [(name, run["frames"], run["ok"], run["seconds"], run["frames"] / run["seconds"] if run["ok"] else None,
          run["peak_rss_mb"], run["load"]) for name, run in (("long", long), ("short (memory check)", short))]))
    for name, run in (("long", long), ("short", short)):
        if not run["ok"]:
            lines += ["", f"The {name} run failed (exit status {run['returncode']}); the end of its log:", "",
                      "```", run.get("log_tail", ""), "```"]
    lines += ["", format_table(("stage", "ms/frame"), list(speed["stage_ms_per_frame"].items()) +
                               [("**total (stages)**", sum(speed["stage_ms_per_frame"].values()))])]
    if tracker:
        lines += ["", f"Tracker alone (`Tracker.track` in-process on the long run's {tracker['frames']} observation "
                      f"files, {tracker['observations_mean']:.0f} observations per frame on average): "
                      f"{tracker['fps_all']:.1f} frames/s over all frames ({fmt(tracker.get('fps_all_cpu'))} in the "
                      f"process's CPU time, which the machine's other work sways less), "
                      f"{tracker['fps_tracked']:.1f} over "
                      f"tracked frames (median {fmt(tracker.get('ms_tracked_median'), 0)} ms, 90th percentile "
                      f"{fmt(tracker.get('ms_tracked_p90'), 0)} ms per frame); an initialisation takes "
                      f"{tracker['ms_initialisation']:.0f} ms; loading the compiled code, once per process, "
                      f"{fmt(tracker.get('ms_first_call'), 0)} ms (first call, not counted); statuses "
                      f"{tracker['statuses']}."]
    bench = speed["made"]["bench_memory"]
    lines += ["", f"Peak memory long / short: {fmt(speed['memory_ratio'], 2)}. For the record, `getrusage` in the "
                  f"benchmark process after the suite: RUSAGE_SELF {bench['self_mb']:.0f} MB (includes the in-process "
                  f"tracker timing), RUSAGE_CHILDREN {bench['children_mb']:.0f} MB (largest child so far)."]
    return "\n".join(lines)


UNSEEN_COLUMNS = (("capture", "capture"), ("clip", "clip"), ("body", "body"), ("cams", "cameras"),
                  ("size", "size"), ("noise", "noise"), ("distr.", "distractors"), ("media", "media"),
                  ("calibration", "calibration"), ("height", "height_known"), ("frames", "frames"),
                  ("estimated", "fraction_estimated"), ("MPJPE mm", "mpjpe_mm"),
                  ("offset-free mm", "offset_free_mpjpe_mm"), ("worst mm", "worst_frame_mm"),
                  ("knee °", "knee_flexion_deg"), ("elbow °", "elbow_flexion_deg"), ("sil. IoU", "silhouette_iou"))


def format_unseen(unseen: dict) -> str:
    def cells(row: dict) -> tuple:
        return tuple(percent(row.get(key)) if key == "fraction_estimated"
                     else fmt(row.get(key), 3) if key == "silhouette_iou" else row.get(key)
                     for _, key in UNSEEN_COLUMNS)

    mean = unseen["mean"]
    rows = [cells(row) for row in unseen["rows"]] + [cells({**mean, "capture": f"**mean of {mean['captures']}**"})]
    lines = [format_table([header for header, _ in UNSEEN_COLUMNS], rows)]
    failed = [row for row in unseen["rows"] if "mpjpe_mm" not in row]
    for row in failed:
        reason = row.get("error") or row.get("run", {}).get("log_tail", "")
        lines += ["", f"`{row['capture']}` was not scored: {reason}"]
    return "\n".join(lines)


FOREIGN_COLUMNS = (("capture", "capture"), ("cams", "cameras"), ("size", "size"), ("frames", "frames"),
                   ("estimated", "fraction_estimated"), ("MPJPE mm", "mpjpe_mm"),
                   ("offset-free mm", "offset_free_mpjpe_mm"), ("worst mm", "worst_frame_mm"),
                   ("sil. IoU median", "silhouette_iou_median"), ("MPJPE true masks mm", "mpjpe_true_masks_mm"),
                   ("worst true masks mm", "worst_true_masks_mm"), ("end to end fps", "fps_end_to_end"),
                   ("tracker ms/frame", "tracker_ms_per_frame"),
                   ("× ref.", "tracker_vs_reference"), ("tracked", "tracked"), ("initialised", "initialised"),
                   ("predicted", "predicted"), ("lost", "lost"), ("doubtful", "doubtful"),
                   ("re-init. after 1st", "reinitialised_fraction"))


def format_foreign(foreign: dict) -> str:
    """One row per foreign capture, then the reference capture the tracker's time is compared with."""
    def cells(row: dict) -> tuple:
        values = row | row.get("statuses", {})
        return tuple(percent(values.get(key)) if key in ("fraction_estimated", "reinitialised_fraction")
                     else fmt(values.get(key), 3) if key == "silhouette_iou_median"
                     else fmt(values.get(key), 2) if key == "tracker_vs_reference"
                     else fmt(values.get(key), 1) if key == "fps_end_to_end" else values.get(key)
                     for _, key in FOREIGN_COLUMNS)

    reference = foreign["reference"]
    rows = [*foreign["rows"], {**reference, "capture": f"{reference['capture']} (reference)"}]
    lines = [f"Captures found in `{foreign['root']}`.", "",
             format_table([header for header, _ in FOREIGN_COLUMNS], [cells(row) for row in rows])]
    for row in rows:
        if "mpjpe_mm" not in row:
            lines += ["", f"`{row['capture']}` was not scored: {row.get('error') or row['run'].get('log_tail', '')}"]
    return "\n".join(lines)


def _robustness_cell(rows: Sequence[dict]) -> str:
    """"MPJPE (worst frame)" in mm, each the mean over the scored ``rows``, with the mean share of frames
    estimated when a run did not estimate all (an MPJPE over fewer frames reads better than it is); "–" when no
    row was scored."""
    scored = [row for row in rows if "mpjpe_mm" in row]
    if not scored:
        return "–"

    def mean(key: str) -> float:
        return sum(row[key] for row in scored) / len(scored)

    cell = f"{fmt(mean('mpjpe_mm'))} ({fmt(mean('worst_frame_mm'))})"
    return cell if mean("fraction_estimated") >= 1.0 else f"{cell}, {percent(mean('fraction_estimated'))} estimated"


def format_robustness(robustness: dict) -> str:
    """One row per capture and one column per variant, MPJPE (worst frame) in mm, then the mean over the captures
    per variant; the runs that were not scored are listed below with the reason."""
    rows = robustness["rows"]
    captures = list(dict.fromkeys(row["capture"] for row in rows))
    variants = list(dict.fromkeys(row["variant"] for row in rows))

    def matching(**match) -> list[dict]:
        return [row for row in rows if all(row[key] == value for key, value in match.items())]

    def cell(**match) -> str:
        return _robustness_cell(matching(**match))

    def reinitialised(**match) -> str:
        shares = [row["reinitialised_fraction"] for row in matching(**match) if "reinitialised_fraction" in row]
        return percent(sum(shares) / len(shares)) if shares else "–"

    def per_variant(cell_of) -> list[list[str]]:
        table = [[capture, *(cell_of(capture=capture, variant=variant) for variant in variants)]
                 for capture in captures]
        return table + [["**mean**", *(cell_of(variant=variant) for variant in variants)]]

    lines = [f"Copies of the captures in `{robustness['root']}`, one change each; a cell is MPJPE (worst frame) in mm, "
             "the last row their means over the captures scored.", "",
             format_table(["capture", *variants], per_variant(cell))]
    if any("reinitialised_fraction" in row for row in rows):
        lines += ["", "Share of each copy's frames initialised anew after the first (the fit failed the checks and a "
                  "fresh initialisation explained the data better: the tracker lost the body and searched again).", "",
                  format_table(["capture", *variants], per_variant(reinitialised))]
    for row in rows:
        if "mpjpe_mm" not in row:
            lines += ["", f"`{row['capture']}`, {row['variant']}: not scored: {row.get('error', '')}"]
    return "\n".join(lines)


def format_exports(exports: dict) -> str:
    """The agreement and confidence per capture, then MPJPE and wrist acceleration error per cut-off."""
    def mm(row: dict, file: str):
        return fmt(row.get("agreement_mm", {}).get(file), 5)

    files = ("motion.bvh", "joints.trc", "joints.c3d")
    scored = [row for row in exports["rows"] if "mpjpe_mm" in row]
    first = format_table(
        ["capture", *(f"{file} mm" for file in files), "unsupported pairs", "MPJPE unsupported mm",
         "MPJPE others mm", "errors > 50 mm flagged"],
        [(row["capture"], *(mm(row, file) for file in files), percent(row["confidence"]["unsupported_share"]),
          fmt(row["confidence"]["unsupported_mpjpe_mm"]), fmt(row["confidence"]["supported_mpjpe_mm"]),
          percent(row["confidence"]["large_errors_flagged"])) for row in scored])
    cutoffs = exports["cutoffs_hz"]
    second = format_table(
        ["capture", "unsmoothed MPJPE mm", "wrist accel. m/s²",
         *(f"{c:g} Hz: MPJPE mm / wrist accel." for c in cutoffs)],
        [(row["capture"], fmt(row["mpjpe_mm"]), fmt(row["wrist_acceleration_m_s2"], 2),
          *(f"{fmt(e['mpjpe_mm'])} / {fmt(e['wrist_acceleration_m_s2'], 2)}" for e in row["smoothed"]))
         for row in scored if "smoothed" in row])
    lines = [f"Captures found in `{exports['root']}`.", "", first, "", second]
    for row in exports["rows"]:
        if "error" in row or "mpjpe_mm" not in row:
            lines += ["", f"`{row['capture']}` was not scored: {row.get('error') or row['run'].get('log_tail', '')}"]
    return "\n".join(lines)


def format_sweep(rows: list[dict], x_name: str) -> str:
    """One row per swept value and distance (the paper's curves are the ``angle mean`` column)."""
    extra = "mask IoU" if x_name == "noise" else "reconstructed"
    order = {"normals": 0, "points": 1, "algebraic": 2}
    table = [(f"{row['x']:g}", row["distance"],
              f"{row['mask_iou']:.3f}" if x_name == "noise" else round(row["observations"]), row["frames"],
              row["angle_error_deg"], row.get("angle_error_median_deg"), row.get("angle_error_offset_free_deg"),
              row["mpjpe_mm"], percent(row.get("off_track")), percent(row["fraction_estimated"]))
             for row in sorted(rows, key=lambda r: (r["x"], order.get(r["distance"], 3)))]
    return format_table((x_name, "distance", extra, "frames", "angle mean °", "angle median °",
                         "angle offset-free °", "MPJPE mm", "off track", "estimated"), table)


def format_paper(paper: dict, figure: str | None) -> str:
    recipe = paper["recipe"]
    lines = [f"Capture `{paper['capture']}`: clip {recipe['clip']}, body {recipe['body']}, {recipe['cameras']} "
             f"cameras {recipe['size']}, true silhouettes; {100 * paper['outlier_fraction']:.0f} % outliers "
             "uniform in the working volume added to every frame's observations. Angle error = mean absolute "
             f"error of {', '.join(paper['limb_angles'])} (degrees), on exported frames; mean over frames (the "
             f"paper's average, plotted) and the median frame's; offset-free = the mean after removing each joint's "
             "constant offset in the body's frame (the paper's \"systematic offset\" between two skeletons' joint "
             "placements; `pipeline.lab.bench.paper.score`); off track = share of frames with MPJPE above "
             f"{paper['off_track_mm']:g} mm."]
    if figure:
        lines += ["", f"![Fig. 4 redone]({figure})"]
    base = paper["base"]
    lines += ["", "(a) 28 fps, 1000 observations, no silhouette noise:", "",
              format_table(("distance", "frames", "angle mean °", "angle median °", "angle offset-free °",
                            "hip angles °", "hips forward mm", "knees forward mm", "MPJPE mm", "off track",
                            "estimated", "tracking s"),
                           [(r["distance"], r["frames"], r["angle_error_deg"], r.get("angle_error_median_deg"),
                             r.get("angle_error_offset_free_deg"), r.get("hip_angle_error_deg"),
                             r.get("hips_forward_mm"), r.get("knees_forward_mm"), r["mpjpe_mm"],
                             percent(r.get("off_track")), percent(r["fraction_estimated"]), r["seconds"])
                            for r in base])]
    for key, title in (("noise", "(b) silhouette noise strength (boundary ± up to 4 px, up to 6 holes)"),
                       ("fps", "(c) frame rate (same 3.6 s of motion)"),
                       ("observations", "(d) observations per frame")):
        lines += ["", f"{title}:", "", format_sweep(paper[key], key)]
    return "\n".join(lines)


SPEED_NOTES = (
    "How: the wall time of `python -m pipeline run <capture> --out <fresh folder> --workers 2`, measured from "
    "outside (interpreter start, imports, video decoding, all five stages, every output written). Stage ms/frame "
    "= the seconds in the stage's manifest / the capture's frames; tracking runs alongside reconstruction (it "
    "streams: each frame is tracked as soon as its observations exist), so those two overlap and each is slowed by "
    "the other: their sum is more than their share of the wall time. Peak memory = `ru_maxrss` of the run's process "
    "tree (`os.wait4`: the largest single process, workers included). The machine is shared with other work; "
    "the load average before each run says how busy it was.")
UNSEEN_NOTES = (
    "How: each capture is synthetic (`pipeline.lab.synth`: a body driven by CMU motion capture, ray-cast into a "
    "textured room), rendered once and cached by recipe; `python -m pipeline run` processes it (2 workers) and "
    "`pipeline.evaluate.evaluate_run` scores `export/joints.csv` against `groundtruth/joints.csv`: MPJPE over the "
    "15 scored joints, the same offset-free (each joint's constant offset in the subject's frame taken off: where "
    "the tracker's body and the animation's skeleton put the joint in the same flesh), frames estimated / frames, "
    "the worst frame's MPJPE, mean absolute knee and elbow flexion "
    "errors, and the silhouette stage's IoU with the true masks. What is unseen: the tracker's ellipsoid sizes "
    "were measured on the MakeHuman mesh posed by md_walk and 135_04, and its initialisation pose library was "
    "sampled from 135_04, md_walk and 09_01, so for those clips the *poses* are not new (the spans, cameras, "
    "noise and the capsule body are); 135_07 and 131_05 and the capsule body were never used for tuning.")
FOREIGN_NOTES = (
    "How: the captures in the shared `foreign` folder were made by another program (its own renderer, body, "
    "room, lighting and noise; none of the project's code), so they show what the accuracy on `pipeline.lab.synth` "
    "captures owes to familiarity. Each is processed by `python -m pipeline run` (2 workers) and scored by "
    "`pipeline.evaluate.evaluate_run` against its `groundtruth/joints.csv`: frames estimated / frames, MPJPE over "
    "the 15 scored joints, the same offset-free (each joint's constant offset in the subject's frame taken off), "
    "the worst frame's MPJPE, and the median IoU of the silhouette stage's masks with "
    "`groundtruth/masks/` over all frames and cameras; then MPJPE and worst frame again with those true masks "
    "copied over the run's silhouettes and the run redone from the reconstruction (`--from reconstruction`): "
    "what the tracker makes of perfect silhouettes. Every run is fresh: fps is frames over the run's wall time, "
    "video decoding included. The tracker's milliseconds per frame are its own, every frame included, timed "
    "again in the bench's process on the run's observations after every run (in CPU time, the fastest of three "
    "passes, each taking every capture and the reference in turn, so that a slow spell of the machine falls on "
    "all of them; the tracking stage streams alongside the reconstruction, so its manifest time is mostly "
    "waiting), and as a multiple of `data_samples/taekwondo` "
    "(same motion, window and rig, rendered by `pipeline.lab.synth`) run the same way (× ref.); then how many frames "
    "ended in each status "
    "(doubtful: exported but flagged by the tracker's failure checks, overlapping tracked and initialised) and "
    "the share of frames initialised anew after the first.")
ROBUSTNESS_NOTES = (
    "How: each foreign capture is copied once per change by `pipeline.lab.bench.perturb` (seed 0; every video "
    "decoded, changed and encoded again): compression (every frame through JPEG at quality 20), noise (Gaussian "
    "sensor noise of 8 levels), flicker (each frame's exposure drawn in [0.9, 1.1]), darker before the gamma "
    "(every level I made 255 (I / 255)^1.25: the camera's automatic exposure lowered before its gamma, so that the "
    "frames' levels are a curve of the plates', not a multiple), no plates (the clean plates "
    "left out: the background estimated from the frames), 4 cameras (the first four by name), one camera zoomed "
    "1.8x (the first by name: the subject partly out of its view), calibration off 0.1° (each camera turned by "
    "0.1° about an axis of its own, about 1.7 pixels at a focal length of 1000), one plate 5 px off (the first "
    "camera's clean plate moved by 4 pixels across and 3 down, its frames unchanged: a camera knocked after its "
    "plate was taken), shutter open the whole frame (each frame half itself and half the frame before: a fast "
    "limb shows twice, the two images faint; the true joints those of the exposure's mean time, half-way between "
    "the two frames'), a desk before one camera (a grey panel in the first camera's plate and frames, from 70 % of "
    "the way down the subject's true masks to the image's bottom: his shins and feet hidden from that camera "
    "wherever he goes), a pillar before one camera (a grey post a twentieth of the image wide over its whole "
    "height, where the middle of the subject's true masks lies in the median frame: he passes behind it) and a box "
    "put down after the plates (a brown box 0.5 x 0.4 x 0.7 m on the floor, 1 m beside the subject's mean place "
    "across his travel, drawn from the calibration into every camera's frames and not into the plates), one "
    "camera 2 frames late (the first camera's frame t shows what the others show at t − 2, its first frame "
    "repeated before: a camera without a common clock; run as the others are, the sync check off by default) and "
    "2 frames late, frame_offsets from the sync check (the same copy run with `--set export.sync_check=true`, then "
    "again with capture.yaml's `frame_offsets` set to what the check named, which is the run scored: the last two "
    "frames, which the late camera lacks, are not estimated and not scored). The "
    "copies are made once into "
    "`<captures>/robustness/<capture>-<change>-<key>/`, the key a hash of the change's arguments and of the "
    "capture's capture.yaml. Each copy is processed by `python -m pipeline run` (2 workers) and scored by "
    "`pipeline.evaluate.evaluate_run` against its ground truth (the original's, or rewritten for the cameras kept "
    "or zoomed, for the shutter and for what an occluder or the box hides), as in the foreign suite, and its "
    "tracking records give the share of its "
    "frames initialised anew after the first (second table). Every copy's videos are encoded a second time "
    "(MPEG-4 Part 2), so the foreign suite's figures are not quite those without a change: that is a copy with "
    "`--change none` alone (not run by this suite). "
    "`python -m pipeline bench --out runs/bench --suite robustness` measures it; one copy by hand: "
    "`python -m pipeline.lab.bench.perturb ../shared/foreign/walk --change compression --out runs/walk-compression` "
    "(`--change gamma_dark`, or `--change none` with `--no-plates`, `--cameras cam00,cam01,cam02,cam03`, "
    "`--zoom cam00:1.8`, "
    "`--calibration-error 0.1`, `--plate-shift cam00:4:3`, `--shutter 0.5`, `--occluder cam00:desk`, "
    "`--occluder cam00:pillar`, `--box` or `--late cam00:2` for the others), then "
    "`python -m pipeline run runs/walk-compression --out "
    "runs/walk-compression-run` and `python -m pipeline eval runs/walk-compression-run --truth "
    "runs/walk-compression/groundtruth/joints.csv`.")
EXPORTS_NOTES = (
    "How: each foreign capture is run afresh with the default parameters (`python -m pipeline run`, 2 workers), "
    "then its export stage alone again with `--set export.filter_cutoff_hz=<Hz>` at each cut-off. First table "
    "(unsmoothed run): the largest distance over the estimated frames and joints between joints.csv and each "
    "export as an independent reader sees it (bvhio's forward kinematics of the BVH, trc-data-reader, the c3d "
    "package; `pipeline.lab.bench.exports.agreement_mm`), then the scored (frame, joint) pairs whose quality.csv "
    "confidence is below 0.5, the MPJPE of those and of the others, and the share of joint errors above 50 mm "
    "that are so flagged. Second table: MPJPE and the wrists' acceleration error (mean norm of the difference "
    "between estimated and true second differences, `pipeline eval`) unsmoothed and at each cut-off. The "
    "targets are judged at 6 Hz; the agreement target over every run, smoothed or not.")
PAPER_NOTES = (
    "How: in memory, calling the stage functions (`stages.reconstruction.reconstruct`, "
    "`stages.tracking.tracker.Tracker.track`) on the true silhouettes of a 56 fps rendering, perturbed "
    "(`pipeline.lab.bench.masks.perturb_mask`: random smooth erosion/dilation of the outline and holes, growing "
    "with the strength), then 20 % outliers added uniformly in the working volume. Every sequence starts from "
    "the data alone (automatic initialisation); the subject's height is given. The paper plots radians; this "
    "page degrees. Each point is one sequence (as in the paper), so one loss of track can decide its mean: read "
    "the off-track share and the median beside it. Raw and offset-free angles differ where the two skeletons "
    "put a joint at different places in the same flesh: table (a) gives each distance's constant offset of "
    "the hips and the knees along the body's forward axis (negative: behind the animation skeleton's) and "
    "its hip-angle error. Hips placed forward tilt the thighs and so change the hip angles, unless the knees "
    "are placed forward alike: a fit that places the knees right can have the larger raw hip-angle error.")
