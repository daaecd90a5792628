"""Calibrate the cameras from board recordings: each lens, the rig's poses and the floor.

Examples:
  python -m pipeline calibrate boards --board checkerboard:8x5:0.11 --out captures/session1
  python -m pipeline calibrate boards --board charuco:7x5:0.14:0.084:DICT_4X4_50 --floor floor --out captures/s1

BOARDS holds intrinsics/<camera>/ (images, or one video, of the board moved in front of that camera) and/or
extrinsics/<camera>/ (images or videos of the board seen by several cameras at once: the same file name, or
frame number of a video, is the same moment in every camera). A camera without intrinsics/ is calibrated from
its extrinsics/ views. BOARD is checkerboard:COLSxROWS:SQUARE_M (inner corners, as OpenCV counts them) or
charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT (squares; an OpenCV dictionary such as DICT_4X4_50). --floor names the
extrinsics view(s) in which the board lies flat on the floor: z = 0 there, +z up; without it the world is the
first camera's frame and capture.yaml gets `up: auto`.

Writes CAPTURE_DIR/calibration/calibration.toml (anipose layout), CAPTURE_DIR/calibration/report.json (per
camera K, dist, size, views, rms_px; the rig's RMS after bundle adjustment) and the calibration: block of
CAPTURE_DIR/capture.yaml (the rest of the file is kept). See docs/calibration.md.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import sys
from pathlib import Path

import yaml

from calib.board import Board, parse_board
from calib.calibrate import DISTORTION_MODELS, Intrinsics, RigCalibration, calibrate_intrinsics, calibrate_rig
from calib.errors import InputError
from calib.formats import natural_key, save_rig
from pipeline.commands.board_views import CameraViews, Source, detect_all, find_sources, spread
from pipeline.io import atomic, plain_yaml

PARTS = ("intrinsics", "extrinsics")
TOML_PATH = "calibration/calibration.toml"
REPORT_PATH = "calibration/report.json"
#: Default spacing of the video frames searched for the board (a board moved by hand barely changes in 1/3 s).
DEFAULT_VIDEO_STEP = 10
#: Default cap on the views per camera given to calibrateCamera (chosen evenly in time among the detections).
DEFAULT_MAX_VIEWS = 40


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("boards", type=Path, help="folder with intrinsics/<camera>/ and/or extrinsics/<camera>/")
    parser.add_argument("--board", required=True, metavar="BOARD",
                        help="checkerboard:COLSxROWS:SQUARE_M or charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT")
    parser.add_argument("--out", type=Path, required=True, metavar="CAPTURE_DIR",
                        help="capture directory to write calibration/ and capture.yaml's calibration block into")
    parser.add_argument("--floor", metavar="VIEW[,VIEW...]",
                        help="extrinsics view(s) (file stem or video frame number) showing the board flat on the floor")
    parser.add_argument("--distortion", choices=tuple(DISTORTION_MODELS), default="k1k2",
                        help="lens distortion coefficients to estimate (default k1k2)")
    parser.add_argument("--video-step", type=int, default=DEFAULT_VIDEO_STEP, metavar="N",
                        help=f"search every N-th frame of a video (default {DEFAULT_VIDEO_STEP})")
    parser.add_argument("--max-views", type=int, default=DEFAULT_MAX_VIEWS, metavar="N",
                        help=f"at most N views per camera for its intrinsics (default {DEFAULT_MAX_VIEWS})")
    parser.add_argument("--force", action="store_true",
                        help="replace a calibration/calibration.toml that this command did not write")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")


# ---------------------------------------------------------------------------------------------
# Calibrating (the board views are found by pipeline.commands.board_views)


def calibrate_cameras(board: Board, intrinsic_views: dict[str, CameraViews], extrinsic_views: dict[str, CameraViews],
                      *, distortion: str, max_views: int) -> dict[str, Intrinsics]:
    """Every camera's intrinsics, from its intrinsics/ views or, without them, its extrinsics/ views."""
    names = sorted(set(intrinsic_views) | set(extrinsic_views), key=natural_key)
    result = {}
    for name in names:
        views = intrinsic_views.get(name) or extrinsic_views[name]
        part = "intrinsics" if name in intrinsic_views else "extrinsics"
        if not views.detections:
            raise InputError(f"{views.source.describe()}: the board {board.describe()} was found in none of the "
                             f"{views.searched} views of camera {name!r} (expected it in most; check --board: a "
                             "checkerboard counts inner corners, a ChArUco board squares)")
        try:
            result[name] = calibrate_intrinsics(board.object_points, spread(views.detections, max_views), views.size,
                                                camera=name, distortion=distortion)
        except InputError as error:
            raise InputError(f"{views.source.describe()}: {error} ({len(views.detections)} of {views.searched} "
                             f"{part} views have the board)") from None
    return result


def floor_views(text: str | None, sources: dict[str, Source]) -> tuple[str, ...]:
    """The views named by ``--floor``, checked against the extrinsics image names (video frames are checked once
    the board has been searched for: :func:`calibrate_rig` names a floor view no camera found)."""
    if text is None:
        return ()
    if not sources:
        raise InputError(f"--floor {text}: needs extrinsics/ views (the board on the floor seen by the rig)")
    views = tuple(view.strip() for view in text.split(",") if view.strip())
    stems = {path.stem for source in sources.values() for path in source.images}
    videos = any(source.is_video for source in sources.values())
    for view in views:
        if view not in stems and not (videos and view.isdigit() and len(view) == 6):
            raise InputError(f"--floor {text}: view {view!r} is not one of the extrinsics views (expected the file "
                             "stem of a view with the board flat on the floor, or the 6-digit frame number in a video)")
    return views


# ---------------------------------------------------------------------------------------------
# Writing


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _check_overwrite(out: Path, force: bool) -> None:
    """Refuse to replace a calibration.toml that this command did not write (report.json holds its hash)."""
    toml = out / TOML_PATH
    if not toml.exists() or force:
        return
    try:
        ours = json.loads((out / REPORT_PATH).read_text()).get("calibration_toml_sha256")
    except (OSError, ValueError, AttributeError):
        ours = None
    if ours != _sha256(toml):
        raise InputError(f"{toml}: exists and was not written by `python -m pipeline calibrate` (or was edited since); "
                         "expected a capture without one, or --force to replace it")


def calibration_block(*, floor: bool) -> dict:
    return {"format": "anipose", "path": TOML_PATH, "units": "m", "up": "+z" if floor else "auto"}


def update_capture_yaml(path: Path, block: dict) -> str:
    """``capture.yaml``'s text with its top-level ``calibration:`` block replaced by ``block`` (added when absent);
    every other line, comments included, kept as it was. A new file gets the block alone."""
    lines = [f"  {key}: {value}" for key, value in block.items()]
    new_block = ["calibration:", *lines]
    if not path.exists():
        return "\n".join(["# fps: <frames per second of the media>   (required: add it)", *new_block]) + "\n"
    text = path.read_text(encoding="utf-8")
    try:
        parsed = plain_yaml.load(text, str(path))
    except yaml.YAMLError as error:
        raise InputError(f"{path}: not valid YAML ({plain_yaml.describe_error(error)}); "
                         "expected a capture.yaml") from None
    if parsed is not None and not isinstance(parsed, dict):
        raise InputError(f"{path}: top level is {type(parsed).__name__}, expected a mapping")
    old = text.splitlines()
    start = next((k for k, line in enumerate(old) if re.match(r"calibration\s*:", line)), None)
    if start is None:
        return text + ("" if text.endswith("\n") or not text else "\n") + "\n".join(new_block) + "\n"
    end = start + 1
    while end < len(old) and (not old[end].strip() or old[end][0] in " \t#"):
        end += 1
    while end > start + 1 and not old[end - 1].strip():  # keep the blank lines before the next key
        end -= 1
    return "\n".join(old[:start] + new_block + old[end:]) + "\n"


def build_report(board: Board, args: argparse.Namespace, intrinsics: dict[str, Intrinsics],
                 sources: dict[str, str], searched: dict[str, int], rig: RigCalibration | None) -> dict:
    cameras = {}
    for name, lens in intrinsics.items():
        cameras[name] = {"K": lens.K.tolist(), "dist": lens.dist.tolist(), "size": list(lens.size),
                         "views": len(lens.views), "rms_px": lens.rms_px, "focal_px": [lens.K[0, 0], lens.K[1, 1]],
                         "focal_std_px": lens.focal_std_px, "dropped_views": list(lens.dropped),
                         "source": sources[name], "views_searched": searched[name]}
    report = {"board": board.describe(), "distortion": args.distortion, "cameras": cameras}
    if rig is not None:
        report["rig"] = {"rms_px": rig.rms_px, "board_poses": rig.views, "floor": list(rig.floor),
                         "world": "floor board: z = 0 on the floor, +z up" if rig.floor else "the first camera's frame",
                         "cameras": {name: {"rms_px": rig.camera_rms_px[name], "views": rig.camera_views[name]}
                                     for name in intrinsics},
                         "chain": [list(edge) for edge in rig.chain],
                         "dropped_observations": [list(pair) for pair in rig.dropped]}
    return report


def summary(report: dict) -> str:
    """The per-camera table and the rig's line, as printed at the end."""
    rows = [("camera", "views", "dropped", "rms px", "fx px", "fy px", "cx px", "cy px", "from")]
    for name, camera in report["cameras"].items():
        K = camera["K"]
        rows.append((name, str(camera["views"]), str(len(camera["dropped_views"])), f"{camera['rms_px']:.3f}",
                     f"{K[0][0]:.1f}", f"{K[1][1]:.1f}", f"{K[0][2]:.1f}", f"{K[1][2]:.1f}", camera["source"]))
    widths = [max(len(row[k]) for row in rows) for k in range(len(rows[0]))]
    lines = ["  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True)).rstrip() for row in rows]
    rig = report.get("rig")
    if rig is None:
        lines.append("extrinsics: none (no extrinsics/ folder): only the intrinsics were calibrated; the cameras' "
                     "poses need extrinsics/<camera>/ views of the board seen by several cameras at once")
    else:
        floor = (f"floor from view {', '.join(rig['floor'])} (z = 0, +z up)" if rig["floor"]
                 else "no floor view: world = the first camera's frame, up: auto")
        lines.append(f"rig: {len(report['cameras'])} cameras, {rig['board_poses']} board poses, RMS "
                     f"{rig['rms_px']:.3f} px after bundle adjustment; {floor}")
        if rig["dropped_observations"]:
            lines.append(f"dropped as outliers: {', '.join(f'{c} view {v}' for c, v in rig['dropped_observations'])}")
    return "\n".join(lines)


def checked_sources(args: argparse.Namespace, board: Board) -> tuple[dict[str, Source], dict[str, Source]]:
    """The intrinsics and extrinsics recordings under BOARDS, by camera, once the arguments and the folders'
    layout are checked (one-line errors before any detection)."""
    if args.video_step < 1 or args.max_views < 3:
        raise InputError("--video-step must be at least 1 and --max-views at least 3")
    if not args.boards.is_dir():
        raise InputError(f"{args.boards}: no such folder, expected BOARDS with intrinsics/<camera>/ and/or "
                         "extrinsics/<camera>/")
    intrinsic_sources, extrinsic_sources = (find_sources(args.boards, part) for part in PARTS)
    if not intrinsic_sources and not extrinsic_sources:
        raise InputError(f"{args.boards}: no intrinsics/<camera>/ or extrinsics/<camera>/ folders, expected board "
                         "recordings there")
    if extrinsic_sources and board.symmetric:
        raise InputError(f"--board {board.describe()}: {board.columns}x{board.rows} inner corners look the same turned "
                         "by 180 degrees, so two cameras may disagree which corner is which; expected one odd and one "
                         "even count (e.g. 8x5) or a ChArUco board for extrinsics")
    only_intrinsics = sorted(set(intrinsic_sources) - set(extrinsic_sources), key=natural_key)
    if extrinsic_sources and only_intrinsics:
        raise InputError(f"{args.boards / 'extrinsics'}: no views of camera {only_intrinsics[0]!r}, expected "
                         f"extrinsics/{only_intrinsics[0]}/ like the other cameras' (or leave out its intrinsics/)")
    return intrinsic_sources, extrinsic_sources


def main(args: argparse.Namespace) -> int:
    board = parse_board(args.board)
    intrinsic_sources, extrinsic_sources = checked_sources(args, board)
    floor = floor_views(args.floor, extrinsic_sources)
    args.out.mkdir(parents=True, exist_ok=True)
    _check_overwrite(args.out, args.force)
    progress = not args.quiet and sys.stderr.isatty()
    # Intrinsics first, so that a board never found or too few views stop the command before the (longer) search
    # of the extrinsics; cameras without intrinsics/ wait for their extrinsics views.
    intrinsic_views = detect_all(board, intrinsic_sources, "intrinsics", video_step=args.video_step, progress=progress)
    intrinsics = calibrate_cameras(board, intrinsic_views, {}, distortion=args.distortion, max_views=args.max_views)
    extrinsic_views = detect_all(board, extrinsic_sources, "extrinsics", video_step=args.video_step, progress=progress)
    for name, views in intrinsic_views.items():
        if name in extrinsic_views and views.size != extrinsic_views[name].size:
            raise InputError(f"{extrinsic_views[name].source.path}: {extrinsic_views[name].size[0]}x"
                             f"{extrinsic_views[name].size[1]} views, but intrinsics/{name} has {views.size[0]}x"
                             f"{views.size[1]}: expected the same camera settings for both")
    intrinsics |= calibrate_cameras(board, {}, {name: views for name, views in extrinsic_views.items()
                                                if name not in intrinsic_views},
                                    distortion=args.distortion, max_views=args.max_views)
    intrinsics = {name: intrinsics[name] for name in sorted(intrinsics, key=natural_key)}
    sources = {name: ("intrinsics" if name in intrinsic_views else "extrinsics") + f"/{name}" for name in intrinsics}
    searched = {name: (intrinsic_views.get(name) or extrinsic_views[name]).searched for name in intrinsics}
    rig = None
    if extrinsic_views:
        rig = calibrate_rig(intrinsics, {name: extrinsic_views[name].detections for name in intrinsics},
                            board.object_points, floor=floor)
    if rig is not None and set(rig.floor) != set(floor):
        missing = ", ".join(sorted(set(floor) - set(rig.floor)))
        print(f"warning: --floor: no camera found the board in view(s) {missing}; the floor is set by "
              f"{', '.join(rig.floor)}", file=sys.stderr)
    report = build_report(board, args, intrinsics, sources, searched, rig)
    for name, lens in intrinsics.items():
        if lens.weak:
            share = 100 * lens.focal_std_px / lens.K[0, 0]
            print(f"warning: camera {name!r}: its views leave the focal length uncertain by ±{lens.focal_std_px:.1f} "
                  f"px ({share:.1f} %); tilt the board more in front of it", file=sys.stderr)
    written = []
    if rig is not None:
        toml = args.out / TOML_PATH
        with atomic.atomic_output(toml) as temporary:
            save_rig(rig.rig, "anipose", temporary)
        report["calibration_toml_sha256"] = _sha256(toml)
        capture_yaml = args.out / "capture.yaml"
        atomic.write_text(capture_yaml, update_capture_yaml(capture_yaml, calibration_block(floor=bool(floor))))
        written += [toml, capture_yaml]
    atomic.write_text(args.out / REPORT_PATH, json.dumps(report, indent=1) + "\n")
    written.insert(1 if rig is not None else 0, args.out / REPORT_PATH)
    print(summary(report))
    print("written: " + ", ".join(str(path) for path in written))
    return 0

