"""A copy of a capture whose videos differ from its clean plates the way a real camera's or codec's do.

    python -m pipeline.lab.bench.perturb ../shared/foreign/walk --change gamma --out runs/perturbed/walk-gamma
    python -m pipeline run runs/perturbed/walk-gamma --out runs/walk-gamma
    python -m pipeline eval runs/walk-gamma --truth ../shared/foreign/walk/groundtruth/joints.csv

The foreign captures are a validation set of four, and the project is judged on captures it has not seen, from
other cameras and rooms. A perturbed copy asks what one such difference does to the silhouettes and the track,
one at a time: the change applies to every frame of every video, the clean plates stay as they were (a plate
shot before the camera's automatic exposure, white balance or the codec moved), and the copy holds the
original's calibration and plates and links its ground truth, so that it is run and scored as the original is.
Every video is decoded and encoded again (``none`` does only that: the codec's second generation, the control
every other change is compared with). With ``--no-plates`` the copy has no clean plates at all, as a recording
made without one: the pipeline then estimates each camera's background from the frames.

    python -m pipeline.lab.bench.perturb ../shared/foreign/walk --change none --no-plates --out runs/walk-noplate

With ``--absent FIRST:STOP`` the subject is away on frames FIRST to STOP - 1 (a recording that starts before he
walks in, ``0:20``, or one he leaves and comes back to, ``50:70``): each camera shows its clean plate there, with
sensor noise, and the copy's ground truth has no joints and empty masks on those frames, so that ``eval``
scores only the frames he is in view.

    python -m pipeline.lab.bench.perturb ../shared/foreign/taekwondo --change none --absent 0:20 --out runs/late

With ``--cameras NAME,NAME,...`` the copy keeps only those cameras (a smaller rig: the calibration rewritten in
its own format, units and up axis with the others left out; their videos, plates and true masks left out too).

    python -m pipeline.lab.bench.perturb ../shared/foreign/frontkick --change none --cameras cam00,cam02,cam04,cam05 \
        --out runs/frontkick-4cams

With ``--calibration-error DEGREES`` the copy's calibration is off the way a real one is: each camera turned by
that angle about an axis of its own (drawn with ``--seed``) about its centre, the images unchanged. At a focal
length of f pixels the angle moves the image of the subject by up to f tan(angle) pixels: 0.1° is about 1.7
pixels at f = 1000, the reprojection error of a mediocre calibration.

    python -m pipeline.lab.bench.perturb ../shared/foreign/walk --change none --calibration-error 0.1 \
        --out runs/walk-off

With ``--zoom NAME:FACTOR,...`` those cameras see the scene through a longer lens: each frame's middle 1 / FACTOR
enlarged to the whole image about its centre, the camera's intrinsics multiplied to match (K' = Z K, distortion
unchanged, which is exact for a zoom of the distorted image), its plate and true masks zoomed alike. The
subject then leaves those views in part (feet, a raised arm or the head cut off by the image's border), as in a
studio whose cameras do not all frame the whole volume.

    python -m pipeline.lab.bench.perturb ../shared/foreign/taekwondo --change none --zoom cam00:1.8 --out runs/cut

With ``--late NAME:FRAMES,...`` those cameras run that many frames behind the others (cameras without a common
clock: webcams, action cameras): their frame t shows what the others showed at t - FRAMES (the first frame
repeated before it), and their true masks move alike. The pipeline takes the frames as simultaneous unless
capture.yaml's ``frame_offsets`` says otherwise (``--set export.sync_check=true`` names the offsets).

    python -m pipeline.lab.bench.perturb ../shared/foreign/frontkick --change none --late cam02:1 --out runs/late

With ``--monochrome`` every camera records grey levels only (machine-vision and infrared studio cameras): the
frames and the plates are turned to grey (OpenCV's luma), the frames still written in three equal channels.

    python -m pipeline.lab.bench.perturb ../shared/foreign/walk --change none --monochrome --out runs/walk-grey

With ``--plate-shift NAME:DX:DY,...`` those cameras' clean plates are moved by (DX, DY) pixels (their frames
unchanged): a plate taken before the camera was knocked or re-aimed a little.

    python -m pipeline.lab.bench.perturb ../shared/foreign/taekwondo --change none --plate-shift cam00:4:3 \
        --out runs/knocked

With ``--shutter SHARE`` every camera's shutter stays open longer: each frame is (1 − SHARE) of itself and SHARE
of the frame before (the first frame unchanged), what an exposure over the whole frame interval records of a
moving subject, sampled at its two ends: a limb that moves fast shows twice, the earlier image faint (a kick's
foot crosses several of its widths from one frame to the next). The copy's true joints are those of the exposure's
mean time, (1 − SHARE) of the frame's and SHARE of the frame before's (the pose such a frame shows, to which its two
images are equally near when SHARE is 0.5); its true masks stay the frame's own.

    python -m pipeline.lab.bench.perturb ../shared/foreign/frontkick --change none --shutter 0.5 --out runs/smear

With ``--occluder NAME:KIND,...`` something stands between those cameras and the subject, in their plates and in
every frame (painted before the change, which it undergoes like the room): ``desk``, a grey panel across the image
from the row 70 % of the way down from the top of the subject's true masks to their bottom (medians over the
frames), hiding his shins and feet wherever he goes; ``pillar``, a grey post over the whole image's height, a
twentieth of its width wide, where the middle of his true masks lies in the median frame, which he passes behind.
Their true masks lose what it hides. The subject's joints are unchanged: the other cameras see him whole.

    python -m pipeline.lab.bench.perturb ../shared/foreign/taekwondo --change none --occluder cam00:desk --out runs/desk

With ``--box`` a box stands on the floor beside where the subject moves, in every frame and not in the plates:
something put down after the plates were taken (:mod:`pipeline.lab.bench.box`). The true masks lose what it hides.

    python -m pipeline.lab.bench.perturb ../shared/foreign/walk --change none --box --out runs/walk-box
"""

from __future__ import annotations

import argparse
import csv
import shutil
import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from calib.camera import Camera, Rig
from calib.errors import InputError
from calib.formats import load_rig, save_rig
from calib.world import UNIT_SCALE
from pipeline.io.capture import Capture
from pipeline.io.export_io import read_joints_csv, write_joints_csv
from pipeline.lab.bench.box import BoxCamera, box_cameras, with_box
from stages.background.plates import shifted_plate

# What each change does to a frame (float32 8-bit levels, BGR), given a random generator and the camera's index.
Change = Callable[[np.ndarray, np.random.Generator, int], np.ndarray]

#: Sensor noise on the frames where the subject is away (8-bit levels): a plate repeated as it is would be a
#: still image, which no camera records.
ABSENT_NOISE = 2.0

#: The colour of an occluder (``--occluder``, BGR 8-bit levels), with a fixed texture of OCCLUDER_TEXTURE levels.
OCCLUDER_COLOUR = np.array([105.0, 115.0, 125.0], np.float32)
OCCLUDER_TEXTURE = 6.0
#: Where a desk starts, from the top of the subject's true masks (0) to their bottom (1), and a pillar's width as a
#: share of the image's.
DESK_FROM = 0.7
PILLAR_WIDTH = 0.05
OCCLUDERS = ("desk", "pillar")

#: Cameras whose automatic white balance moved since the plates: blue and red gains, alternating by camera.
_WHITE_BALANCE = (np.array([1.08, 1.0, 0.93], np.float32), np.array([0.92, 1.0, 1.08], np.float32))


def _tone(exponent: float) -> Change:
    return lambda frame, rng, camera: 255.0 * (frame / 255.0) ** exponent


CHANGES: dict[str, tuple[str, Change]] = {
    "none": ("decoded and encoded again only", lambda frame, rng, camera: frame),
    "gamma": ("exposure raised before the camera's gamma: I' = 255 (I / 255)^0.8", _tone(0.8)),
    "gamma_dark": ("exposure lowered before the camera's gamma: I' = 255 (I / 255)^1.25", _tone(1.25)),
    "black_level": ("black level lifted, contrast lowered (a grabber, haze): I' = 0.85 I + 20",
                    lambda frame, rng, camera: 0.85 * frame + 20.0),
    "exposure": ("exposure 0.8 of the plates'", lambda frame, rng, camera: 0.8 * frame),
    "flicker": ("each frame's exposure drawn in [0.9, 1.1] (mains flicker)",
                lambda frame, rng, camera: frame * rng.uniform(0.9, 1.1)),
    "white_balance": ("each camera's blue and red gains moved by 7-8 %",
                      lambda frame, rng, camera: frame * _WHITE_BALANCE[camera % 2]),
    "noise": ("Gaussian sensor noise of 8 levels added",
              lambda frame, rng, camera: frame + rng.normal(0.0, 8.0, frame.shape)),
    "compression": ("every frame through JPEG at quality 20 (blocking, ringing)",
                    lambda frame, rng, camera: _jpeg(frame, 20)),
    "blur": ("the frames blurred (a Gaussian of 1.5 px) against sharp plates",
             lambda frame, rng, camera: cv2.GaussianBlur(frame, (0, 0), 1.5)),
}


def _jpeg(frame: np.ndarray, quality: int) -> np.ndarray:
    _, encoded = cv2.imencode(".jpg", _to_uint8(frame), [cv2.IMWRITE_JPEG_QUALITY, quality])
    return cv2.imdecode(encoded, cv2.IMREAD_COLOR).astype(np.float32)


def _grey(frame: np.ndarray) -> np.ndarray:
    """A float32 BGR frame as a monochrome camera records it: its luma in all three channels."""
    return cv2.cvtColor(cv2.cvtColor(np.clip(frame, 0.0, 255.0).astype(np.float32), cv2.COLOR_BGR2GRAY),
                        cv2.COLOR_GRAY2BGR)


def _to_uint8(frame: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(frame), 0, 255).astype(np.uint8)


def perturb_capture(capture: Path, out: Path, change: str, *, seed: int = 0, plates: bool = True,
                    absent: range = range(0), cameras: tuple[str, ...] = (),
                    calibration_error_deg: float = 0.0, position_error_m: float = 0.0,
                    zoom: dict[str, float] | None = None,
                    late: dict[str, int] | None = None,
                    plate_shift: dict[str, tuple[float, float]] | None = None, monochrome: bool = False,
                    shutter: float = 0.0, occluder: dict[str, str] | None = None, box: bool = False) -> Path:
    """Write to ``out`` (which must not exist) a copy of ``capture`` with ``change`` (a key of ``CHANGES``) applied
    to every frame of its videos, and the subject away on the frames ``absent``, seen by the ``cameras`` named
    (default: all) through a calibration whose cameras are each turned by ``calibration_error_deg`` and moved by
    ``position_error_m``, the cameras of ``zoom`` zoomed by its factors (:func:`zoomed`), those of ``late`` that
    many frames behind the others, the clean plates of those of ``plate_shift`` moved by its (x, y) pixels, every
    frame and plate in grey levels with ``monochrome``, each frame blended with the one before in the share
    ``shutter``, the cameras of ``occluder`` seeing the subject behind a desk or a pillar (:func:`occluder_region`), and
    with ``box`` a box put down beside him after the plates were taken (:mod:`pipeline.lab.bench.box`); returns ``out``.

    capture.yaml, the calibration and the background plates (unless ``plates`` is False) are copied, the ground
    truth (when there is one) linked, or rewritten without the ``absent`` frames and the cameras left out
    (:func:`_truth_without`).
    The videos are written as MPEG-4 Part 2 (the codec OpenCV's wheels can write) at the originals' frame
    rate; only captures whose frames are videos (``videos/<camera>.<ext>``) can be changed.

    Raises
    ------
    InputError
        An unknown change, ``out`` already there, a capture without videos, ``absent`` frames in a capture
        without a clean plate for every camera, a camera named that has no video, an angle or a distance that is
        not finite, a zoom factor that is not a finite number of at least 1, a delay that is not a whole number of
        frames of at least 1, a plate shift that is not two finite numbers, a shutter share outside [0, 1), or an
        occluder of another kind or for a camera without true masks, or a box in a capture without true joints.
    """
    capture, out = Path(capture), Path(out)
    if change not in CHANGES:
        raise InputError(f"unknown change {change!r} (expected one of {', '.join(CHANGES)})")
    if out.exists():
        raise InputError(f"{out}: already exists (give a new folder; nothing is overwritten)")
    if not 0.0 <= shutter < 1.0:
        raise InputError(f"shutter {shutter}: expected the share of the frame before, at least 0 and below 1")
    if not np.isfinite(calibration_error_deg):
        raise InputError(f"calibration error {calibration_error_deg}: expected a finite angle in degrees")
    if not np.isfinite(position_error_m):
        raise InputError(f"position error {position_error_m}: expected a finite distance in metres")
    zoom = dict(zoom or {})
    for name, factor in zoom.items():
        if not (np.isfinite(factor) and factor >= 1.0):
            raise InputError(f"zoom of camera {name!r}: {factor} (expected a finite factor of at least 1)")
    videos = capture_videos(capture)
    late = dict(late or {})
    for name, frames in late.items():
        if not (isinstance(frames, int) and frames >= 1):
            raise InputError(f"delay of camera {name!r}: {frames} (expected a whole number of frames, at least 1)")
    plate_shift = dict(plate_shift or {})
    for name, shift in plate_shift.items():
        if len(shift) != 2 or not np.all(np.isfinite(shift)):
            raise InputError(f"plate shift of camera {name!r}: {shift} (expected two finite numbers of pixels)")
    occluder = dict(occluder or {})
    for name, kind in occluder.items():
        if kind not in OCCLUDERS:
            raise InputError(f"occluder of camera {name!r}: {kind!r} (expected one of {', '.join(OCCLUDERS)})")
    unknown = sorted((set(cameras) | set(zoom) | set(late) | set(plate_shift) | set(occluder))
                     - {video.stem for video in videos})
    if unknown:
        raise InputError(f"{capture / 'videos'}: no video of camera(s) {', '.join(unknown)}")
    if cameras:
        videos = [video for video in videos if video.stem in cameras]
    empty_room = [_plate(capture, video.stem) for video in videos] if absent else [None] * len(videos)
    regions = {name: occluder_region(capture / "groundtruth" / "masks" / name, kind) for name, kind in occluder.items()}
    boxes = box_cameras(capture, {video.stem for video in videos}) if box else {}
    apply = CHANGES[change][1]
    rng = np.random.default_rng(seed)
    partial = out.with_name(out.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    (partial / "videos").mkdir(parents=True)
    shutil.copy2(capture / "capture.yaml", partial / "capture.yaml")
    if cameras or calibration_error_deg or position_error_m or zoom:
        _rewrite_calibration(Capture.open(capture), partial, {video.stem for video in videos}, calibration_error_deg,
                             position_error_m, np.random.default_rng([seed, 1]),  # its own draws: the frames' stay
                             zoom)
    elif (capture / "calibration").is_dir():
        shutil.copytree(capture / "calibration", partial / "calibration")
    if plates and (capture / "background").is_dir():
        (partial / "background").mkdir()
        kept = {video.stem for video in videos}
        for plate in (capture / "background").iterdir():
            if plate.stem not in kept:
                continue
            if plate.stem in zoom or plate.stem in plate_shift or monochrome or plate.stem in regions:
                image = zoomed(cv2.imread(str(plate), cv2.IMREAD_UNCHANGED), zoom.get(plate.stem, 1.0))
                if plate.stem in plate_shift:
                    image = shifted_plate(image, plate_shift[plate.stem])
                if plate.stem in regions:
                    image = _to_uint8(_occluded(image.astype(np.float32), regions[plate.stem]))
                if monochrome and image.ndim == 3:
                    image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
                cv2.imwrite(str(partial / "background" / plate.name), image)
            else:
                shutil.copy2(plate, partial / "background" / plate.name)
    if (capture / "groundtruth").is_dir():
        if absent or cameras or zoom or late or shutter or regions or boxes:
            _truth_without(capture / "groundtruth", partial / "groundtruth", absent, {video.stem for video in videos},
                           zoom, late, shutter, regions, boxes)
        else:
            (partial / "groundtruth").symlink_to((capture / "groundtruth").resolve(), target_is_directory=True)
    for camera, (video, plate) in enumerate(zip(videos, empty_room, strict=True)):
        region = regions.get(video.stem)

        def changed(frame: np.ndarray, index: int, camera: int = camera, plate: np.ndarray | None = plate,
                    factor: float = zoom.get(video.stem, 1.0), region: np.ndarray | None = region,
                    name: str = video.stem):
            if index in absent:
                frame = plate + rng.normal(0.0, ABSENT_NOISE, plate.shape)
            if name in boxes:
                shown = max(0, index - late.get(name, 0))
                frame = with_box(frame, boxes[name].view, *boxes[name].subject(shown))
            frame = zoomed(frame, factor)
            frame = apply(frame if region is None else _occluded(frame, region), rng, camera)
            return _grey(frame) if monochrome else frame

        _rewrite(video, partial / "videos" / (video.stem + ".mp4"), changed, late.get(video.stem, 0), shutter)
    partial.rename(out)
    return out


def capture_videos(capture: Path) -> list[Path]:
    """The capture's videos (``videos/<camera>.<ext>``), by name: what a copy can change, one per camera.

    Raises
    ------
    InputError
        When the capture has none (only captures of videos can be perturbed).
    """
    folder = Path(capture) / "videos"
    videos = sorted(path for path in folder.iterdir() if path.is_file()) if folder.is_dir() else []
    if not videos:
        raise InputError(f"{capture}: no videos/ folder with videos (only captures of videos can be perturbed)")
    return videos


def _rewrite_calibration(source: Capture, copy: Path, kept: set[str], error_deg: float, position_error_m: float,
                         rng: np.random.Generator, zoom: dict[str, float]) -> None:
    """The ``source`` capture's calibration written into ``copy`` with only the ``kept`` cameras, each turned by
    ``error_deg`` (:func:`_turned`), then moved by ``position_error_m`` (:func:`_moved`), and those of ``zoom``
    zoomed (:func:`zoom_matrix`): read as the file states it (image sizes from the media) and saved in the same
    format at the same place, so that its units and up axis stay as capture.yaml says."""
    calibration = source.config["calibration"]
    rig = load_rig(calibration["format"], source.root / calibration["path"],
                   image_sizes={camera.name: camera.size for camera in source.rig})
    cameras = [_turned(camera, error_deg, rng) for camera in rig if camera.name in kept]
    in_file_units = position_error_m / UNIT_SCALE[calibration["units"]]
    cameras = [_moved(camera, in_file_units, rng) for camera in cameras]
    cameras = [replace(camera, K=zoom_matrix(camera.size, zoom[camera.name]) @ camera.K) if camera.name in zoom
               else camera for camera in cameras]
    save_rig(Rig(tuple(cameras)), calibration["format"], copy / calibration["path"])


def zoom_matrix(size: tuple[int, int], factor: float) -> np.ndarray:
    """(3, 3) Z mapping a pixel to where a zoom by ``factor`` about the centre of an image of ``size`` (width,
    height) puts it: u' = factor (u − c) + c, with c the image's centre (pixel centres at integers)."""
    centre = (np.asarray(size, float) - 1.0) / 2.0
    return np.array([[factor, 0.0, (1.0 - factor) * centre[0]], [0.0, factor, (1.0 - factor) * centre[1]],
                     [0.0, 0.0, 1.0]])


def zoomed(image: np.ndarray, factor: float) -> np.ndarray:
    """``image`` zoomed by ``factor`` about its centre (:func:`zoom_matrix`), the same size: linear interpolation
    for pictures, nearest for a mask (uint8 with one channel), so that a mask stays two-valued."""
    if factor == 1.0:
        return image
    height, width = image.shape[:2]
    nearest = image.ndim == 2 and image.dtype == np.uint8
    return cv2.warpAffine(image, zoom_matrix((width, height), factor)[:2], (width, height),
                          flags=cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _turned(camera: Camera, angle_deg: float, rng: np.random.Generator) -> Camera:
    """``camera`` turned by ``angle_deg`` about a random axis through its centre (the centre kept)."""
    if not angle_deg:
        return camera
    axis = rng.normal(size=3)
    turn, _ = cv2.Rodrigues(axis / np.linalg.norm(axis) * np.radians(angle_deg))
    R = turn @ camera.R
    return replace(camera, R=R, t=-R @ camera.centre)


def _moved(camera: Camera, distance: float, rng: np.random.Generator) -> Camera:
    """``camera`` moved by ``distance`` (the calibration's units) in a random direction, its orientation kept."""
    if not distance:
        return camera
    step = rng.normal(size=3)
    return replace(camera, t=-camera.R @ (camera.centre + distance * step / np.linalg.norm(step)))


def _plate(capture: Path, camera: str) -> np.ndarray:
    """The camera's clean plate (float32, BGR), from ``background/<camera>.<ext>``."""
    paths = sorted((capture / "background").glob(f"{camera}.*")) if (capture / "background").is_dir() else []
    plate = cv2.imread(str(paths[0]), cv2.IMREAD_COLOR) if paths else None
    if plate is None:
        raise InputError(f"{capture / 'background'}: no readable clean plate for camera {camera!r} "
                         "(--absent shows each camera's plate where the subject is away)")
    return plate.astype(np.float32)


def _truth_without(truth: Path, target: Path, absent: range, cameras: set[str], zoom: dict[str, float],
                   late: dict[str, int], shutter: float = 0.0, regions: dict[str, np.ndarray] | None = None,
                   boxes: dict[str, BoxCamera] | None = None) -> None:
    """``target``, the ground truth at ``truth`` without the ``absent`` frames, seen by ``cameras``: the absent
    frames' joints.csv rows left out and their masks empty, the other cameras' masks left out, the masks of the
    cameras of ``zoom`` zoomed (:func:`zoomed`), those of the cameras of ``late`` the earlier frame's, those of the
    cameras of ``regions`` without what their occluder hides there, those of ``boxes`` without what the box hides
    (the other masks and files linked); with a
    ``shutter``, each frame's joints moved that share of the way back to the frame before's (the exposure's mean
    time)."""
    regions, boxes = regions or {}, boxes or {}
    target.mkdir()
    for path in sorted(truth.iterdir()):
        if path.name == "joints.csv" and shutter:
            frames, names, joints = read_joints_csv(path)
            follows = np.flatnonzero(np.diff(frames) == 1) + 1  # frames whose frame before is in the truth
            exposed = joints.copy()
            exposed[follows] = _exposure(joints[follows], joints[follows - 1], shutter)
            kept = ~np.isin(frames, list(absent))
            write_joints_csv(target / path.name, frames[kept], exposed[kept], names)
        elif path.name == "joints.csv":
            with path.open(newline="") as source, (target / path.name).open("w", newline="") as copy:
                rows = csv.reader(source)
                writer = csv.writer(copy)
                writer.writerow(next(rows))
                writer.writerows(row for row in rows if int(row[0]) not in absent)
        elif path.name == "masks" and path.is_dir():
            for camera in sorted(p for p in path.iterdir() if p.is_dir() and p.name in cameras):
                (target / "masks" / camera.name).mkdir(parents=True)
                masks = sorted(camera.iterdir())
                behind = late.get(camera.name, 0)
                for index, mask in enumerate(masks):
                    shown = masks[max(0, index - behind)]  # the frame this camera shows there (late: an earlier one)
                    written = target / "masks" / camera.name / mask.name
                    if mask.stem.isdigit() and int(mask.stem) in absent:
                        image = cv2.imread(str(mask), cv2.IMREAD_GRAYSCALE)
                        cv2.imwrite(str(written), np.zeros_like(image))
                    elif camera.name in zoom or camera.name in regions or camera.name in boxes:
                        image = cv2.imread(str(shown), cv2.IMREAD_GRAYSCALE)
                        if camera.name in boxes and shown.stem.isdigit() and not boxes[camera.name].nearer(
                                int(shown.stem)):
                            image[boxes[camera.name].view.region] = 0
                        image = zoomed(image, zoom.get(camera.name, 1.0))
                        if camera.name in regions:
                            image[regions[camera.name]] = 0
                        cv2.imwrite(str(written), image)
                    else:
                        written.symlink_to(shown.resolve())
        else:
            (target / path.name).symlink_to(path.resolve(), target_is_directory=path.is_dir())


def _rewrite(source: Path, target: Path, change: Callable[[np.ndarray, int], np.ndarray], late: int = 0,
             shutter: float = 0.0) -> None:
    """Decode ``source``, change every frame (as float32, with its index) and encode the result to ``target``;
    ``late``: each frame t is the source's t - late (its first frame before that), as many frames as the source;
    ``shutter``: each frame, before the change, is (1 - shutter) of itself and ``shutter`` of the one before."""
    reader = cv2.VideoCapture(str(source))
    fps = reader.get(cv2.CAP_PROP_FPS)
    writer = None
    index = 0
    recent: list[np.ndarray] = []  # the source's last late + 1 frames
    previous = None  # the last frame taken, for the shutter
    try:
        while True:
            ok, frame = reader.read()
            if not ok:
                break
            if late:
                recent = ((recent or [frame] * late) + [frame])[-(late + 1):]  # the first stands in for earlier ones
                frame = recent[0]
            if writer is None:
                writer = cv2.VideoWriter(str(target), cv2.VideoWriter_fourcc(*"mp4v"), fps,
                                         (frame.shape[1], frame.shape[0]))
                if not writer.isOpened():
                    raise InputError(f"{target}: OpenCV cannot write an MPEG-4 video here")
            taken = frame.astype(np.float32)
            exposed = taken if previous is None else _exposure(taken, previous, shutter)
            previous = taken
            writer.write(_to_uint8(change(exposed, index)))
            index += 1
    finally:
        reader.release()
        if writer is not None:
            writer.release()
    if writer is None:
        raise InputError(f"{source}: no frame could be decoded")


def occluder_region(masks: Path, kind: str) -> np.ndarray:
    """(H, W) bool: where a ``kind`` of occluder (``OCCLUDERS``) stands in the view whose true masks are in the
    folder ``masks``, placed by where those masks lie (see the module's docstring)."""
    paths = sorted(masks.glob("*.png"))
    if not paths:
        raise InputError(f"{masks}: no true masks to place the occluder by")
    tops, bottoms, middles, shape = [], [], [], None
    for path in paths:
        mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        shape = mask.shape
        rows, columns = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        if len(rows):
            tops.append(rows[0])
            bottoms.append(rows[-1])
            middles.append(0.5 * (columns[0] + columns[-1]))
    if not tops:
        raise InputError(f"{masks}: every true mask is empty; no place for the occluder")
    region = np.zeros(shape, bool)
    if kind == "desk":
        top, bottom = np.median(tops), np.median(bottoms)
        region[round(top + DESK_FROM * (bottom - top)):] = True
    else:
        half = max(1, round(PILLAR_WIDTH * shape[1] / 2))
        middle = round(np.median(middles))
        region[:, max(0, middle - half):middle + half] = True
    return region


def _occluded(image: np.ndarray, region: np.ndarray) -> np.ndarray:
    """``image`` (float32, BGR) with the occluder painted over ``region`` (its texture the same in every image)."""
    texture = np.random.default_rng(0).normal(0.0, OCCLUDER_TEXTURE, image.shape[:2]).astype(np.float32)
    painted = image.copy()
    painted[region] = OCCLUDER_COLOUR + texture[region][:, None]
    return painted


def _exposure(now: np.ndarray, before: np.ndarray, shutter: float) -> np.ndarray:
    """What a shutter open over ``shutter`` of the frame before as well records, of frames or of joints alike: the
    blend (1 − shutter) now + shutter before."""
    return (1.0 - shutter) * now + shutter * before


def _frame_span(text: str) -> range:
    """``FIRST:STOP`` (0 <= FIRST < STOP) as the frames it names."""
    first, _, stop = text.partition(":")
    try:
        span = range(int(first), int(stop))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected FIRST:STOP, two frame numbers, got {text!r}") from None
    if span.start < 0 or not span:
        raise argparse.ArgumentTypeError(f"expected 0 <= FIRST < STOP, got {text!r}")
    return span


def _per_camera(text: str, kind: Callable[[str], object], what: str) -> dict:
    """``NAME:VALUE,...`` as {camera: kind(value)}; ``what`` spells the value out in the error."""
    values = {}
    for item in (part for part in text.split(",") if part):
        name, _, value = item.partition(":")
        try:
            values[name] = kind(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected NAME:{what}, a camera and its numbers, got {item!r}") from None
    return values


def _zooms(text: str) -> dict[str, float]:
    """``NAME:FACTOR,...`` as {camera: factor}."""
    return _per_camera(text, float, "FACTOR")


def _plate_shifts(text: str) -> dict[str, tuple[float, float]]:
    """``NAME:DX:DY,...`` as {camera: (dx, dy)}."""
    return _per_camera(text, _pair, "DX:DY")


def _pair(text: str) -> tuple[float, float]:
    """``DX:DY`` as two numbers (ValueError otherwise)."""
    dx, dy = (float(value) for value in text.split(":"))
    return dx, dy


def _occluders(text: str) -> dict[str, str]:
    """``NAME:KIND,...`` as {camera: kind}."""
    return _per_camera(text, str, "KIND")


def _delays(text: str) -> dict[str, int]:
    """``NAME:FRAMES,...`` as {camera: frames}."""
    return _per_camera(text, int, "FRAMES")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m pipeline.lab.bench.perturb", formatter_class=argparse.RawDescriptionHelpFormatter,
        description=__doc__.split("\n\n")[0],
        epilog="changes:\n" + "\n".join(f"  {name:14s}{text}" for name, (text, _) in CHANGES.items()))
    parser.add_argument("capture", type=Path, help="capture directory (with capture.yaml and videos/)")
    parser.add_argument("--change", required=True, choices=sorted(CHANGES))
    parser.add_argument("--out", required=True, type=Path, help="new capture directory (must not exist)")
    parser.add_argument("--seed", type=int, default=0, help="random draws of flicker and noise")
    parser.add_argument("--no-plates", action="store_true",
                        help="leave the clean plates out (the background is then estimated from the frames)")
    parser.add_argument("--absent", type=_frame_span, default=range(0), metavar="FIRST:STOP",
                        help="the subject away on frames FIRST to STOP - 1: the clean plates shown there")
    parser.add_argument("--cameras", type=lambda text: tuple(name for name in text.split(",") if name), default=(),
                        metavar="NAME,NAME,...", help="keep only these cameras (a smaller rig)")
    parser.add_argument("--calibration-error", type=float, default=0.0, metavar="DEGREES",
                        help="each camera of the calibration turned by this angle about an axis of its own")
    parser.add_argument("--position-error", type=float, default=0.0, metavar="METRES",
                        help="each camera of the calibration moved by this distance in a direction of its own")
    parser.add_argument("--zoom", type=_zooms, default={}, metavar="NAME:FACTOR,...",
                        help="these cameras zoomed in by these factors about their images' centres (the subject "
                             "then partly out of their view)")
    parser.add_argument("--late", type=_delays, default={}, metavar="NAME:FRAMES,...",
                        help="these cameras that many frames behind the others (no common clock)")
    parser.add_argument("--monochrome", action="store_true",
                        help="every frame and plate in grey levels (monochrome cameras)")
    parser.add_argument("--plate-shift", type=_plate_shifts, default={}, metavar="NAME:DX:DY,...",
                        help="these cameras' clean plates moved by (DX, DY) pixels (a camera knocked after its plate)")
    parser.add_argument("--shutter", type=float, default=0.0, metavar="SHARE",
                        help="each frame blended with the one before in this share (a longer exposure: moving "
                             "limbs smeared)")
    parser.add_argument("--occluder", type=_occluders, default={}, metavar="NAME:KIND,...",
                        help=f"something between these cameras and the subject, in their plates and frames: one of "
                             f"{', '.join(OCCLUDERS)}")
    parser.add_argument("--box", action="store_true",
                        help="a box put down beside the subject after the plates were taken: in every frame, not in "
                             "the plates")
    args = parser.parse_args(argv)
    try:
        perturb_capture(args.capture, args.out, args.change, seed=args.seed, plates=not args.no_plates,
                        absent=args.absent, cameras=args.cameras, calibration_error_deg=args.calibration_error,
                        position_error_m=args.position_error,
                        zoom=args.zoom, late=args.late, plate_shift=args.plate_shift, monochrome=args.monochrome,
                        shutter=args.shutter, occluder=args.occluder, box=args.box)
    except InputError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
