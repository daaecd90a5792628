"""Render a synthetic capture of real motion (mocap clip, skinned body, ring of cameras), or a montage.

Examples::

    python -m pipeline synth --clip pipeline/lab/data/clips/135_07.amc --start 0.3 --seconds 4 --out runs/kicks
    python -m pipeline synth --montage 40 runs/kicks            # writes runs/kicks/montage_000040.png

An AMC clip needs its ASF skeleton (--skeleton); for the bundled clips it is found automatically.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import cv2

from calib.errors import InputError
from calib.world import UNIT_SCALE
from pipeline.lab.synth.body import BODY_KINDS
from pipeline.lab.synth.writer import CALIBRATION_PATHS, SynthParams, synthesise

log = logging.getLogger(__name__)

CLIPS_DIR = Path(__file__).resolve().parents[1] / "data" / "clips"
#: The ASF skeleton of each bundled AMC clip.
BUNDLED_SKELETONS = {"135_07.amc": "martialwalk.asf", "131_05.amc": "mjackson.asf", "md_walk.amc": "moderndance.asf"}
UP_AXES = ("+z", "-z", "+y", "-y", "+x", "-x")


def _size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 780x580, got {text!r}") from None
    return width, height


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", nargs="?", type=Path, help="capture directory (with --montage)")
    parser.add_argument("--montage", type=int, metavar="FRAME", help="write a PNG of all cameras at FRAME")
    parser.add_argument("--masks", action="store_true", help="with --montage: outline the true masks")
    parser.add_argument("--clip", type=Path, default=CLIPS_DIR / "135_07.amc", help="AMC or BVH clip")
    parser.add_argument("--skeleton", type=Path, help="ASF skeleton of an AMC clip")
    parser.add_argument("--start", type=float, default=0.0, help="start of the span in the clip, seconds")
    parser.add_argument("--seconds", type=float, help="length of the span (default: to the end of the clip)")
    parser.add_argument("--hold", type=float, default=0.0, metavar="SECONDS",
                        help="hold the span's first pose still for this long before the motion starts")
    parser.add_argument("--fps", type=float, default=28.0, help="frame rate of the capture")
    parser.add_argument("--body", choices=BODY_KINDS, default="mesh", help="rendered body surface")
    parser.add_argument("--cameras", type=int, default=6, help="number of cameras in the ring")
    parser.add_argument("--size", type=_size, default=(780, 580), help="image size WxH")
    parser.add_argument("--calib-format", choices=tuple(CALIBRATION_PATHS), default="colmap")
    parser.add_argument("--units", choices=tuple(UNIT_SCALE), default="m", help="units of the calibration")
    parser.add_argument("--up", choices=UP_AXES, default="+z", help="up axis of the calibration's world")
    parser.add_argument("--noise", type=float, default=2.0, help="sensor noise sigma, grey levels")
    parser.add_argument("--distractors", type=int, default=0, help="number of distractor blobs")
    media = parser.add_mutually_exclusive_group()
    media.add_argument("--video", dest="media", action="store_const", const="video", help="mp4 videos (default)")
    media.add_argument("--images", dest="media", action="store_const", const="images", help="PNG image folders")
    parser.set_defaults(media="video")
    height = parser.add_mutually_exclusive_group()
    height.add_argument("--height-known", dest="height_known", action="store_true", help="write subject.height_m")
    height.add_argument("--no-height", dest="height_known", action="store_false", help="leave the height out")
    parser.set_defaults(height_known=True)
    parser.add_argument("--seed", type=int, default=0, help="seed of every random choice")
    parser.add_argument("--out", type=Path, help="capture directory to create")


def _skeleton_for(clip: Path, skeleton: Path | None) -> Path | None:
    if skeleton is not None or clip.suffix.lower() != ".amc":
        return skeleton
    bundled = BUNDLED_SKELETONS.get(clip.name)
    if bundled is None or not (clip.parent / bundled).is_file():
        raise InputError(f"--clip {clip}: an AMC clip needs its ASF skeleton; pass --skeleton <file.asf>")
    return clip.parent / bundled


def main(args: argparse.Namespace) -> int:
    if args.montage is not None:
        from pipeline.lab.synth.montage import montage

        if args.capture is None:
            raise InputError("--montage FRAME: expected the capture directory, e.g. --montage 10 runs/kicks")
        path = (args.out or args.capture) / f"montage_{args.montage:06d}.png"
        cv2.imwrite(str(path), montage(args.capture, args.montage, masks=args.masks))
        print(path)
        return 0
    if args.out is None:
        raise InputError("--out: expected the directory of the capture to create")
    if args.capture is not None:
        raise InputError(f"unexpected argument {args.capture}; a capture directory is only taken with --montage")
    params = SynthParams(
        clip=str(args.clip),
        skeleton=None if (skeleton := _skeleton_for(args.clip, args.skeleton)) is None else str(skeleton),
        start_s=args.start,
        seconds=args.seconds,
        hold_s=args.hold,
        fps=args.fps,
        body=args.body,
        n_cameras=args.cameras,
        size=args.size,
        calib_format=args.calib_format,
        units=args.units,
        up=args.up,
        noise_sigma=args.noise,
        distractors=args.distractors,
        media=args.media,
        height_known=args.height_known,
        seed=args.seed,
    )
    started = time.perf_counter()
    synthesise(params, args.out)
    log.info("wrote %s in %.1f s", args.out, time.perf_counter() - started)
    return 0
