"""Where a capture's frames are: ``images/<camera>/<frame:06d>.png|.jpg``, ``videos/<camera>.<ext>``,
``silhouettes/`` and ``background/``; the frames every camera has, the ``frames:`` selection, and video
decoding (one ``cv2.VideoCapture`` per pass, sequential reads)."""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calib.errors import InputError
from pipeline.io import frames_io

log = logging.getLogger(__name__)


VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
FRAME_FILE = re.compile(r"^(\d{6,})(\.[A-Za-z]+)$")

#: Seeking is slower than decoding a few frames; skip ahead by decoding up to this many frames.
MAX_FRAMES_DECODED_TO_SKIP = 8
#: A video whose stated frame rate departs from capture.yaml's fps by more than this share is reported.
VIDEO_RATE_TOLERANCE = 0.01


@dataclass(frozen=True)
class _CameraMedia:
    """Where one camera's frames live: a video file or an image folder with one suffix."""

    path: Path
    suffix: str = ""  # image files' suffix; "" for a video

    def frame_path(self, frame: int) -> Path:
        return self.path / frames_io.frame_name(frame, self.suffix)


def _visible_entries(folder: Path) -> list[Path]:
    """Entries of ``folder`` in name order, hidden files (``.DS_Store``, ...) skipped."""
    return sorted(p for p in folder.iterdir() if not p.name.startswith("."))


def _find_media(root: Path) -> tuple[dict[str, _CameraMedia], str]:
    """Camera name -> media source, and which kind of media the capture has."""
    images = _find_image_folders(root / "images", what="images")
    videos = _find_videos(root / "videos")
    if images and videos:
        log.info("%s: both images/ and videos/ present; reading images/", root)
    if images:
        return images, "images"
    if videos:
        return videos, "videos"
    if (root / "silhouettes").is_dir():
        return {}, "silhouettes"
    raise InputError(f"{root}: no media found (expected videos/<camera>.mp4, images/<camera>/<frame:06d>.png "
                     "or silhouettes/<camera>/<frame:06d>.png)")


def _find_videos(folder: Path) -> dict[str, _CameraMedia]:
    if not folder.is_dir():
        return {}
    videos = {}
    for entry in _visible_entries(folder):
        if not entry.is_file() or entry.suffix.lower() not in VIDEO_SUFFIXES:
            raise InputError(f"{entry}: not a video file (expected <camera>{{{','.join(VIDEO_SUFFIXES)}}})")
        if entry.stem in videos:
            raise InputError(f"{entry}: a second video for camera {entry.stem!r} (expected one per camera)")
        videos[entry.stem] = _CameraMedia(entry)
    return videos


def _find_image_folders(folder: Path, *, what: str) -> dict[str, _CameraMedia]:
    """Camera name -> its folder of ``<frame:06d>.<suffix>`` files (one suffix per camera)."""
    if not folder.is_dir():
        return {}
    cameras = {}
    for entry in _visible_entries(folder):
        if not entry.is_dir():
            raise InputError(f"{entry}: not a folder (expected {what}/<camera>/<frame:06d>.png)")
        suffixes = set()
        for file in _visible_entries(entry):
            match = FRAME_FILE.match(file.name)
            if not match or match.group(2).lower() not in IMAGE_SUFFIXES or not file.is_file():
                raise InputError(f"{file}: not a frame image (expected files named <frame:06d>.png or .jpg)")
            suffixes.add(match.group(2))
        if not suffixes:
            raise InputError(f"{entry}: no frames (expected {what}/{entry.name}/<frame:06d>.png files)")
        if len(suffixes) > 1:
            raise InputError(f"{entry}: frames with mixed suffixes {sorted(suffixes)} "
                             "(expected one image format)")
        cameras[entry.name] = _CameraMedia(entry, suffixes.pop())
    return cameras


def _find_backgrounds(folder: Path) -> dict[str, Path]:
    if not folder.is_dir():
        return {}
    backgrounds = {}
    for entry in _visible_entries(folder):
        if not entry.is_file() or entry.suffix.lower() not in IMAGE_SUFFIXES:
            raise InputError(f"{entry}: not a background image (expected background/<camera>.png or .jpg)")
        backgrounds[entry.stem] = entry
    return backgrounds


def _frame_numbers_in(source: _CameraMedia) -> list[int]:
    return sorted(int(FRAME_FILE.match(p.name).group(1)) for p in _visible_entries(source.path))


def _first_frame_size(source: _CameraMedia) -> tuple[int, int]:
    """``(width, height)`` of the camera's first frame, checked readable (`frames_io.image_size`; a video's
    decoded)."""
    if source.suffix:
        return frames_io.image_size(source.frame_path(_frame_numbers_in(source)[0]))
    for _, image in _iter_video(source.path, [0]):
        return image.shape[1], image.shape[0]
    raise AssertionError("unreachable: _iter_video yields or raises")


def _video_property(path: Path, prop: int) -> float:
    """A property (``cv2.CAP_PROP_...``) of the video at ``path``, as its container states it."""
    video = cv2.VideoCapture(str(path))
    try:
        if not video.isOpened():
            raise InputError(f"{path}: not a readable video (expected a file OpenCV can decode)")
        return float(video.get(prop))
    finally:
        video.release()


def _video_frame_count(path: Path) -> int:
    return int(_video_property(path, cv2.CAP_PROP_FRAME_COUNT))


def _video_rate(path: Path) -> float:
    """Frames per second a video's container states (0 when it states none)."""
    rate = _video_property(path, cv2.CAP_PROP_FPS)
    return rate if math.isfinite(rate) and rate > 0 else 0.0


def _warn_other_rates(camera_media: Mapping[str, _CameraMedia], fps: float, config_path: Path) -> None:
    """One warning for the videos whose stated frame rate is not capture.yaml's ``fps`` (to a part in a hundred):
    the exports' times and rates follow capture.yaml, so a wrong ``fps`` would stretch the motion unnoticed. A
    rate a container does not state, or states loosely (a phone's variable rate), is not a mistake to report."""
    rates = {name: _video_rate(source.path) for name, source in camera_media.items()}
    other = {name: rate for name, rate in rates.items() if rate and abs(rate - fps) > VIDEO_RATE_TOLERANCE * fps}
    if other:
        stated = ", ".join(f"{name} {rate:.4g}" for name, rate in sorted(other.items()))
        log.warning("%s: fps is %.4g, but the videos say otherwise (frames/s: %s): the exports' times follow "
                    "capture.yaml", config_path, fps, stated)


def _iter_video(path: Path, frames: Iterable[int], *, reuse: bool = False) -> Iterator[tuple[int, np.ndarray]]:
    """Decode the increasing ``frames`` of a video with one ``cv2.VideoCapture``.

    The decoder gets OpenCV's thread count: one in a worker's single-threaded block, where frames are the
    unit of parallelism and a decoder's own threads only add a tenth of CPU time for their synchronisation.
    With ``reuse``, every frame is decoded into the array of the one before (which the caller must be done
    with): a new array per frame costs more than the copy it holds, as the memory of large arrays comes
    fresh from the system and each of its pages faults in on the first write.
    """
    video = cv2.VideoCapture(str(path), cv2.CAP_ANY, [cv2.CAP_PROP_N_THREADS, cv2.getNumThreads()])
    try:
        if not video.isOpened():
            raise InputError(f"{path}: not a readable video (expected a file OpenCV can decode)")
        position = 0  # index of the frame the next read() returns
        image = None
        for frame in frames:
            if frame < position or frame - position > MAX_FRAMES_DECODED_TO_SKIP:
                video.set(cv2.CAP_PROP_POS_FRAMES, frame)
                position = frame
            while position < frame:
                video.grab()
                position += 1
            ok, image = video.read(image if reuse else None)
            position += 1
            if not ok:
                raise InputError(f"{path}: could not decode frame {frame} (expected a readable frame)")
            yield frame, image
    finally:
        video.release()


def _selected_frames(camera_media: Mapping[str, _CameraMedia], media: str, root: Path, frames: dict,
                     config_path: Path, offsets: Mapping[str, int] | None = None) -> list[int]:
    """The frames a run processes: capture.yaml's ``frames`` (start, stop, step on frame numbers) applied to the
    cameras' frames, which must be the same for every camera unless ``frames.stop`` keeps the selection within
    the frames they share.

    Real recordings often end a frame or two apart from camera to camera. Using the frames they share without
    being told would hide a camera that dropped frames midway or belongs to another take (its views then
    disagree with the others' on every later frame), so a mismatch is refused, saying how to select the shared
    frames; a ``frames.stop`` within every camera's frames is that choice made. With ``offsets`` (capture.yaml's
    ``frame_offsets``: camera -> frames its media run behind) the frames are numbered as the cameras without an
    offset number them, and those that every camera has are used: cameras started at different times end apart.
    """
    per_camera = {}
    offsets = offsets or {}
    for name, source in camera_media.items():
        numbers = list(range(_video_frame_count(source.path))) if media == "videos" else _frame_numbers_in(source)
        per_camera[name] = [number - offsets.get(name, 0) for number in numbers]
    reference_name = min(per_camera)
    reference = per_camera[reference_name]
    if not reference:
        raise InputError(f"{root / media}: the media have no frames (expected at least one)")
    if offsets:
        shared = sorted(set.intersection(*(set(frames_of) for frames_of in per_camera.values())))
        if not shared:
            raise InputError(f"{config_path}: with frame_offsets {dict(offsets)} the cameras share no frame "
                             "(expected offsets smaller than the recordings)")
        return _select_frames(frames, shared, config_path)
    differing = sorted(name for name, frames_of in per_camera.items() if frames_of != reference)
    if not differing:
        return _select_frames(frames, reference, config_path)
    shared = sorted(set.intersection(*(set(frames_of) for frames_of in per_camera.values())))
    if frames["stop"] is not None and shared:
        selected = _select_frames(frames, reference, config_path)
        if set(selected) <= set(shared):
            return selected
    name = differing[0]
    where, reference_file = camera_media[name].path, camera_media[reference_name].path.name
    if media == "videos":
        hint = (f"; if they start together and only their ends differ, frames: {{stop: {len(shared)}}} in "
                f"{config_path.name} uses the {len(shared)} frames every camera has; cameras that did not start "
                "together need frame_offsets as well, which a run with --set export.sync_check=true measures"
                if shared else "")
        raise InputError(f"{where}: {len(per_camera[name])} frames but {reference_file} has {len(reference)} "
                         f"(expected the same frame count for every camera{hint})")
    extra = sorted(set(per_camera[name]) ^ set(reference))
    raise InputError(f"{where}: frame {extra[0]} is in one of {name!r} and {reference_name!r} but not the other "
                     "(expected the same frame numbers for every camera, or frames.start and frames.stop in "
                     f"{config_path.name} selecting frames that every camera has)")


def _select_frames(frames: dict, available: list[int], config_path: Path) -> list[int]:
    """Apply ``frames.start/stop/step`` (on frame numbers) to the frames available."""
    start, stop, step = frames["start"], frames["stop"], frames["step"]
    last = available[-1]
    if start > last:
        raise InputError(f"{config_path}: frames.start {start} is out of range "
                         f"(expected at most {last}, the last frame of the media)")
    if stop is not None and stop > last + 1:
        raise InputError(f"{config_path}: frames.stop {stop} is out of range "
                         f"(expected at most {last + 1}, one past the last frame of the media)")
    stop = last + 1 if stop is None else stop
    selected = [f for f in available if start <= f < stop and (f - start) % step == 0]
    if not selected:
        raise InputError(f"{config_path}: frames {start}:{stop}:{step} select no frame of the media "
                         f"(expected a range overlapping frames {available[0]}..{last})")
    return selected
