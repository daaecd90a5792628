"""Reading a capture directory (layout and ``capture.yaml`` in CAPTURE_FORMAT.md).

:meth:`Capture.open` validates everything it can cheaply, before any heavy work: the YAML, the
calibration, that the cameras of the media and of the calibration are the same set, that every
camera has the same frames, that image sizes agree with the calibration, the frame range. Each
mistake is an :class:`InputError` naming the file and what was expected.

A :class:`Capture` holds paths and small metadata only (no open decoders, no pixels), so it is cheap
to pickle and send to worker processes; pixels are streamed one frame at a time by
:meth:`Capture.iter_images`, which keeps one decoder open per call, so memory does not grow with the
sequence length.

Media sources, in order of preference: ``images/<camera>/<frame:06d>.png|.jpg`` (exact frames, no
decoding state), ``videos/<camera>.<ext>``, else ``silhouettes/`` alone (a capture with masks only).
Images are BGR ``(H, W, 3) uint8`` (OpenCV's order), masks ``(H, W) uint8`` in {0, 255}.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import re
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import yaml

from calib.camera import Rig
from calib.errors import InputError
from calib.formats import load_rig
from calib.sanity import check_cameras_see_volume, check_intrinsics, check_rig_size
from calib.world import UNIT_SCALE, WorldTransform, fixed_transform, up_rotation
from pipeline.io import frames_io, plain_yaml
from stages.joints import SUBJECT_HEIGHT_RANGE_M

if TYPE_CHECKING:
    from pipeline.io.auto_frame import AutoFrame

log = logging.getLogger(__name__)

CALIBRATION_FORMATS = ("colmap", "opencv", "anipose", "projection", "qualisys")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
FRAME_FILE = re.compile(r"^(\d{6,})(\.[A-Za-z]+)$")

#: Height of the derived working volume, metres: a standing adult with raised arms fits.
DERIVED_VOLUME_HEIGHT_M = 2.3
#: How far the derived volume reaches below the floor, metres. Reconstructed points outside the volume are
#: dropped, and the soles' points lie at or a little below z = 0 (a visual hull's lowest points; a floor
#: found by ``up: auto`` within a few centimetres): a volume starting at z = 0 cut them off.
DERIVED_VOLUME_FLOOR_MARGIN_M = 0.15
#: Grid of floor positions tested when deriving the volume (cells per side).
DERIVED_VOLUME_GRID = 161
#: Heights (fractions of the volume height) at which a floor position must be in view: the feet and the
#: middle of the body. Requiring the top of the volume (raised arms) as well left out the rim of the floor
#: that the cameras, tilted down at the subject, see whole but for the space above 2 m, where the subject
#: still walks and kicks, and cut the subject off there.
DERIVED_VOLUME_HEIGHTS = (0.0, 0.5)
#: Seeking is slower than decoding a few frames; skip ahead by decoding up to this many frames.
MAX_FRAMES_DECODED_TO_SKIP = 8

_TOP_LEVEL_KEYS = ("fps", "calibration", "subject", "volume", "frames")
_CALIBRATION_KEYS = ("format", "path", "units", "up")


@dataclass(frozen=True)
class _CameraMedia:
    """Where one camera's frames live: a video file or an image folder with one suffix."""

    path: Path
    suffix: str = ""  # image files' suffix; "" for a video

    def frame_path(self, frame: int) -> Path:
        return self.path / frames_io.frame_name(frame, self.suffix)


@dataclass(frozen=True, eq=False)
class Capture:
    """A validated capture directory. Build it with :meth:`open`.

    Attributes
    ----------
    root : Path
        The capture directory.
    config : dict
        ``capture.yaml`` as parsed (plain data).
    fps : float
        Frames per second.
    rig : Rig
        Cameras in the world frame (metres, +z up), image sizes from the media.
    world : WorldTransform
        The map from the calibration's world to the rig's (``calibration.units`` and ``up``).
    auto_frame : AutoFrame or None
        What ``up: auto`` found (:mod:`pipeline.io.auto_frame`); None for a declared up axis.
    volume : (2, 3) float
        Working volume ``[min, max]``, metres, world frame; from ``capture.yaml`` or derived.
    volume_source : str
        ``"capture.yaml"`` or ``"derived"`` (see :func:`derive_volume`).
    height_m : float or None
        Subject's standing height, if given.
    frame_numbers : tuple of int
        The frames to process, after ``frames.start/stop/step``.
    media : str
        ``"images"``, ``"videos"`` or ``"silhouettes"`` (masks only).
    """

    root: Path
    config: dict
    fps: float
    rig: Rig
    volume: np.ndarray
    volume_source: str
    height_m: float | None
    frame_numbers: tuple[int, ...]
    media: str
    camera_media: Mapping[str, _CameraMedia]
    background_paths: Mapping[str, Path]
    silhouette_media: Mapping[str, _CameraMedia]
    world: WorldTransform
    auto_frame: AutoFrame | None = None

    @classmethod
    def open(cls, path: str | Path, *, allow_outside_paths: bool = False) -> Capture:
        """Validate the capture directory at ``path`` and return it (raises :class:`InputError`).

        ``calibration.path`` must lead inside the capture (CAPTURE_FORMAT.md: relative to the capture
        directory), so that a capture.yaml from elsewhere cannot make the pipeline open ``/etc/passwd``
        or ``../../secret``; ``allow_outside_paths`` (``run --allow-outside-paths``) lifts that.
        """
        root = Path(path)
        if not root.is_dir():
            raise InputError(f"{root}: no such capture directory (expected a folder with capture.yaml)")
        config = _read_config(root / "capture.yaml")
        calibration = config["calibration"]
        calibration_path = root / calibration["path"]
        if not allow_outside_paths and not _lies_in(calibration_path, root):
            raise InputError(f"{root / 'capture.yaml'}: calibration.path {calibration['path']!r} leads outside the "
                             f"capture (expected a path inside {root}, or run --allow-outside-paths)")
        if not calibration_path.exists():
            raise InputError(f"{root / 'capture.yaml'}: calibration.path {calibration['path']!r} does not "
                             f"exist (expected a path relative to {root})")

        camera_media, media = _find_media(root)
        silhouette_media = _find_image_folders(root / "silhouettes", what="silhouettes")
        background_paths = _find_backgrounds(root / "background")
        if media == "silhouettes":
            camera_media = silhouette_media
        media_names = set(camera_media)
        sizes = {name: _first_frame_size(source, name) for name, source in camera_media.items()}

        rig = _load_calibration(calibration["format"], calibration_path, sizes)
        _check_same_cameras(rig, media_names, where=root / media)
        for folder, names in (("silhouettes", silhouette_media), ("background", background_paths)):
            if names:
                _check_same_cameras(rig, set(names), where=root / folder)
        for camera in rig:
            if tuple(camera.size) != sizes[camera.name]:
                raise InputError(
                    f"{camera_media[camera.name].path}: image size {sizes[camera.name]} differs from the "
                    f"calibration's {tuple(camera.size)} for camera {camera.name!r} (expected equal sizes)")
        calibration_rig = Rig(tuple(camera.with_size(*sizes[camera.name]) for camera in rig))
        auto = calibration["up"] == "auto"  # then the vertical and floor come after the frames are known
        world = fixed_transform(units=calibration["units"], up="+z" if auto else calibration["up"])
        rig = world.apply(calibration_rig)
        check_rig_size(rig, units=calibration["units"], where=str(calibration_path))
        check_intrinsics(rig, where=str(calibration_path))

        available = _available_frames(camera_media, media, root)
        frame_numbers = _select_frames(config["frames"], available, root / "capture.yaml")
        for source in silhouette_media.values():
            missing = [f for f in frame_numbers if not source.frame_path(f).is_file()]
            if missing:
                raise InputError(f"{source.path}: no silhouette for frame {missing[0]} "
                                 f"({len(missing)} missing; expected one mask per processed frame)")
        for name, path in background_paths.items():
            size = _image_size(path)
            if size != sizes[name]:
                raise InputError(f"{path}: image size {size} differs from camera {name!r}'s {sizes[name]} "
                                 "(expected the clean plate of that camera)")
        subject = config["subject"] or {}
        capture = cls(root=root, config=config, fps=float(config["fps"]), rig=rig, volume=np.zeros((2, 3)),
                      volume_source="", height_m=subject.get("height_m"), frame_numbers=tuple(frame_numbers),
                      media=media, camera_media=camera_media, background_paths=background_paths,
                      silhouette_media=silhouette_media, world=world)
        if auto:
            from pipeline.io.auto_frame import find_world_frame  # here: it imports the silhouette stage

            found = find_world_frame(capture, world.scale)
            rig = found.transform.apply(calibration_rig)
            capture = dataclasses.replace(capture, rig=rig, world=found.transform, auto_frame=found)
            log.info("%s", found.describe())

        if config["volume"] is not None:
            volume = np.array([config["volume"]["min"], config["volume"]["max"]], dtype=np.float64)
            volume_source = "capture.yaml"
        else:
            try:
                volume, volume_source = derive_volume(rig), "derived"
            except ValueError as error:
                raise InputError(f"{calibration_path}: {error} (expected cameras looking at the capture "
                                 "area, or volume: in capture.yaml)") from None
            log.info("working volume derived from the calibration: min %s max %s",
                     np.round(volume[0], 2).tolist(), np.round(volume[1], 2).tolist())
        if volume_source == "capture.yaml":  # a derived volume is, by construction, what most cameras see
            check_cameras_see_volume(capture.rig, volume, where=str(calibration_path))
        return dataclasses.replace(capture, volume=volume, volume_source=volume_source)

    @property
    def has_images(self) -> bool:
        """Whether the capture has colour frames (videos or images), not only silhouettes."""
        return self.media != "silhouettes"

    @property
    def silhouettes_given(self) -> bool:
        """Whether precomputed silhouettes come with the capture."""
        return bool(self.silhouette_media)

    def iter_images(self, camera: str, frames: Iterable[int]) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(frame, image (H, W, 3) uint8 BGR)`` for increasing ``frames`` of ``camera``.

        One decoder stays open for the whole iteration; a video is read sequentially, seeking
        only when the next wanted frame is behind or far ahead. Close the generator (or exhaust
        it) to release the decoder.
        """
        if not self.has_images:
            raise ValueError("iter_images: this capture has silhouettes only (check has_images)")
        source = self.camera_media[camera]
        expected = tuple(self.rig[camera].size)
        images = (_iter_video(source.path, frames) if self.media == "videos"
                  else ((f, frames_io.read_image(source.frame_path(f))) for f in frames))
        for frame, image in images:
            size = (image.shape[1], image.shape[0])
            if size != expected:
                where = source.path if self.media == "videos" else source.frame_path(frame)
                raise InputError(f"{where}: frame {frame} is {size[0]}x{size[1]} pixels "
                                 f"(expected {expected[0]}x{expected[1]} like the camera's first frame)")
            yield frame, image

    def background(self, camera: str) -> np.ndarray | None:
        """The camera's clean plate ``(H, W, 3) uint8`` BGR, or ``None`` when not given."""
        path = self.background_paths.get(camera)
        return None if path is None else frames_io.read_image(path)

    def read_silhouette(self, camera: str, frame: int) -> np.ndarray:
        """The given mask ``(H, W) uint8`` in {0, 255} of ``camera`` at ``frame``."""
        path = self.silhouette_media[camera].frame_path(frame)
        mask = frames_io.read_mask(path)
        expected = tuple(self.rig[camera].size)
        if (mask.shape[1], mask.shape[0]) != expected:
            raise InputError(f"{path}: mask is {mask.shape[1]}x{mask.shape[0]} pixels "
                             f"(expected {expected[0]}x{expected[1]}, the camera's image size)")
        return mask

    def fingerprint(self, part: str) -> str:
        """A short hash of one part of the capture, for cache keys.

        Parts: ``"config"`` (parsed capture.yaml), ``"frames"`` (selected frame numbers),
        ``"calibration"`` (file contents), ``"image_sizes"``, and the media ``"images"``,
        ``"background"``, ``"silhouettes"`` (path + size + mtime of each file: cheap, and a changed
        file gets a new mtime).
        """
        if part == "config":
            return _hash_text(_canonical_json(self.config))
        if part == "frames":
            return _hash_text(_canonical_json(list(self.frame_numbers)))
        if part == "image_sizes":
            return _hash_text(_canonical_json({camera.name: list(camera.size) for camera in self.rig}))
        if part == "calibration":  # named within the calibration itself, which may lie anywhere
            path = self.root / self.config["calibration"]["path"]
            files = sorted(p for p in ([path] if path.is_file() else path.rglob("*")) if p.is_file())
            digest = hashlib.sha256()
            for file in files:
                name = file.name if file == path else file.relative_to(path).as_posix()
                digest.update(name.encode() + b"\0" + file.read_bytes() + b"\0")
            return digest.hexdigest()[:32]
        if part == "images":
            files = (self._media_files(self.camera_media) if self.has_images else [])
        elif part == "background":
            files = [self.background_paths[name] for name in sorted(self.background_paths)]
        elif part == "silhouettes":
            files = self._media_files(self.silhouette_media)
        else:
            raise ValueError(f"fingerprint: unknown part {part!r}")
        return _stat_digest(files, self.root)

    def _media_files(self, media: Mapping[str, _CameraMedia]) -> list[Path]:
        files = []
        for name in sorted(media):
            source = media[name]
            if source.suffix:
                files += [source.frame_path(frame) for frame in self.frame_numbers]
            else:
                files.append(source.path)
        return files


def _hash_text(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:32]


def _canonical_json(value: Any) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=False)


def _stat_digest(files: Iterable[Path], root: Path) -> str:
    digest = hashlib.sha256()
    for file in files:
        stat = file.stat()
        digest.update(f"{file.relative_to(root)}\0{stat.st_size}\0{stat.st_mtime_ns}\n".encode())
    return digest.hexdigest()[:32]


# ---------------------------------------------------------------------------------------------
# capture.yaml


def _read_config(path: Path) -> dict:
    """Parse and validate ``capture.yaml``; return it with defaults filled in."""
    if not path.is_file():
        raise InputError(f"{path}: missing (expected a capture.yaml describing the capture, "
                         "see CAPTURE_FORMAT.md)")
    try:
        raw = plain_yaml.load(path.read_text(encoding="utf-8"), str(path))
    except (yaml.YAMLError, UnicodeDecodeError) as error:
        first_line = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise InputError(f"{path}: not valid YAML ({first_line}) (expected a mapping of keys)") from None
    if raw is None:
        raise InputError(f"{path}: empty (expected a mapping with at least fps and calibration: {{format, path}}, "
                         "see CAPTURE_FORMAT.md)")
    if not isinstance(raw, dict):
        raise InputError(f"{path}: top level is {type(raw).__name__} "
                         "(expected a mapping with fps and calibration)")
    _reject_unknown(raw, _TOP_LEVEL_KEYS, path, "")

    fps = raw.get("fps")
    if not _is_number(fps) or not fps > 0:
        raise InputError(f"{path}: fps is {fps!r} (expected a positive number of frames per second)")

    calibration = raw.get("calibration")
    if not isinstance(calibration, dict):
        raise InputError(f"{path}: calibration is {calibration!r} (expected a mapping with format and path)")
    _reject_unknown(calibration, _CALIBRATION_KEYS, path, "calibration.")
    calibration = {"units": "m", "up": "+z", **calibration}
    if calibration.get("format") not in CALIBRATION_FORMATS:
        raise InputError(f"{path}: calibration.format {calibration.get('format')!r} is unknown "
                         f"(expected one of {', '.join(CALIBRATION_FORMATS)})")
    if not isinstance(calibration.get("path"), str) or not calibration["path"]:
        raise InputError(f"{path}: calibration.path is {calibration.get('path')!r} "
                         "(expected a path relative to the capture directory)")
    if calibration["units"] not in UNIT_SCALE:
        raise InputError(f"{path}: calibration.units {calibration['units']!r} is unknown "
                         f"(expected one of {', '.join(UNIT_SCALE)})")
    try:
        if calibration["up"] != "auto":
            up_rotation(calibration["up"])
    except InputError:
        raise InputError(f"{path}: calibration.up {calibration['up']!r} is unknown "
                         "(expected one of +z, -z, +y, -y, +x, -x, auto)") from None

    subject = raw.get("subject")
    if subject is not None:
        if not isinstance(subject, dict):
            raise InputError(f"{path}: subject is {subject!r} (expected a mapping like {{height_m: 1.75}})")
        _reject_unknown(subject, ("height_m",), path, "subject.")
        height = subject.get("height_m")
        low, high = SUBJECT_HEIGHT_RANGE_M
        if height is not None and (not _is_number(height) or not low < height <= high):
            raise InputError(f"{path}: subject.height_m is {height!r} "
                             f"(expected a height in metres, above {low:g} and at most {high:g})")

    volume = raw.get("volume")
    if volume is not None:
        volume = _check_volume(volume, path)

    frames = raw.get("frames") or {}
    if not isinstance(frames, dict):
        raise InputError(f"{path}: frames is {frames!r} "
                         "(expected a mapping like {start: 0, stop: null, step: 1})")
    _reject_unknown(frames, ("start", "stop", "step"), path, "frames.")
    frames = {"start": 0, "stop": None, "step": 1, **frames}
    for key, minimum in (("start", 0), ("step", 1), ("stop", 1)):
        value = frames[key]
        if key == "stop" and value is None:
            continue
        if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
            raise InputError(f"{path}: frames.{key} is {value!r} (expected an integer >= {minimum})")
    if frames["stop"] is not None and frames["stop"] <= frames["start"]:
        raise InputError(f"{path}: frames.stop {frames['stop']} is not after frames.start {frames['start']} "
                         "(expected start < stop)")
    return {"fps": float(fps), "calibration": calibration, "subject": subject, "volume": volume,
            "frames": frames}


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _reject_unknown(section: dict, known: tuple[str, ...], path: Path, prefix: str) -> None:
    """Refuse keys we do not read: a typo (``volum:``) would otherwise be silently ignored."""
    for key in section:
        if key not in known:
            raise InputError(f"{path}: unknown key {prefix + str(key)!r} "
                             f"(expected one of {', '.join(prefix + name for name in known)})")


def _lies_in(path: Path, root: Path) -> bool:
    """Whether ``path`` (``..`` and links followed) is ``root`` or lies under it."""
    path, root = path.resolve(), root.resolve()
    return path == root or root in path.parents


def _check_volume(volume: Any, path: Path) -> dict:
    if not isinstance(volume, dict) or set(volume) != {"min", "max"}:
        raise InputError(f"{path}: volume is {volume!r} "
                         "(expected a mapping with min: [x, y, z] and max: [x, y, z])")
    corners = []
    for key in ("min", "max"):
        corner = volume[key]
        if not isinstance(corner, list) or len(corner) != 3 or not all(_is_number(v) for v in corner):
            raise InputError(f"{path}: volume.{key} is {corner!r} (expected three numbers in metres)")
        corners.append([float(v) for v in corner])
    if not all(lo < hi for lo, hi in zip(*corners, strict=True)):
        raise InputError(f"{path}: volume.min {corners[0]} is not below volume.max {corners[1]} "
                         "(expected min < max on every axis)")
    return {"min": corners[0], "max": corners[1]}


# ---------------------------------------------------------------------------------------------
# Layout


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


def _image_size(path: Path) -> tuple[int, int]:
    image = frames_io.read_image(path)
    return image.shape[1], image.shape[0]


def _first_frame_size(source: _CameraMedia, camera: str) -> tuple[int, int]:
    """``(width, height)`` of the camera's first frame (decoding it checks the file is readable)."""
    if source.suffix:
        return _image_size(source.frame_path(_frame_numbers_in(source)[0]))
    for _, image in _iter_video(source.path, [0]):
        return image.shape[1], image.shape[0]
    raise AssertionError("unreachable: _iter_video yields or raises")


def _video_frame_count(path: Path) -> int:
    video = cv2.VideoCapture(str(path))
    try:
        if not video.isOpened():
            raise InputError(f"{path}: not a readable video (expected a file OpenCV can decode)")
        return int(video.get(cv2.CAP_PROP_FRAME_COUNT))
    finally:
        video.release()


def _iter_video(path: Path, frames: Iterable[int]) -> Iterator[tuple[int, np.ndarray]]:
    """Decode the increasing ``frames`` of a video with one ``cv2.VideoCapture``."""
    video = cv2.VideoCapture(str(path))
    try:
        if not video.isOpened():
            raise InputError(f"{path}: not a readable video (expected a file OpenCV can decode)")
        position = 0  # index of the frame the next read() returns
        for frame in frames:
            if frame < position or frame - position > MAX_FRAMES_DECODED_TO_SKIP:
                video.set(cv2.CAP_PROP_POS_FRAMES, frame)
                position = frame
            while position < frame:
                video.grab()
                position += 1
            ok, image = video.read()
            position += 1
            if not ok:
                raise InputError(f"{path}: could not decode frame {frame} (expected a readable frame)")
            yield frame, image
    finally:
        video.release()


def _available_frames(camera_media: Mapping[str, _CameraMedia], media: str, root: Path) -> list[int]:
    """Frame numbers present for every camera; all cameras must have the same ones."""
    per_camera = {}
    for name, source in camera_media.items():
        if media == "videos":
            count = _video_frame_count(source.path)
            per_camera[name] = list(range(count))
        else:
            per_camera[name] = _frame_numbers_in(source)
    reference_name = min(per_camera)
    reference = per_camera[reference_name]
    for name, frames in sorted(per_camera.items()):
        if frames != reference:
            where, reference_file = camera_media[name].path, camera_media[reference_name].path.name
            if media == "videos":
                raise InputError(f"{where}: {len(frames)} frames but {reference_file} has {len(reference)} "
                                 "(expected the same frame count for every camera)")
            extra = sorted(set(frames) ^ set(reference))
            raise InputError(f"{where}: frame {extra[0]} is in one of {name!r} and {reference_name!r} but "
                             "not the other (expected the same frame numbers for every camera)")
    if not reference:
        raise InputError(f"{root / media}: the media have no frames (expected at least one)")
    return reference


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


def _load_calibration(fmt: str, path: Path, sizes: Mapping[str, tuple[int, int]]) -> Rig:
    """Load the calibration; ``sizes`` (from the media) fill in formats that do not store them and
    must agree with those that do."""
    try:
        return load_rig(fmt, path, image_sizes=dict(sizes))
    except InputError as error:
        message = str(error)
        raise InputError(message if str(path) in message else f"{path}: {message}") from None
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise InputError(f"{path}: cannot read the {fmt} calibration ({type(error).__name__}: {error}) "
                         f"(expected a valid {fmt} calibration, see CAPTURE_FORMAT.md)") from None


def _check_same_cameras(rig: Rig, names: set[str], *, where: Path) -> None:
    calibrated = set(rig.names)
    if names - calibrated:
        raise InputError(f"{where}: camera {sorted(names - calibrated)[0]!r} is not in the calibration "
                         f"(expected one of {', '.join(rig.names)})")
    if calibrated - names:
        raise InputError(f"{where}: calibrated camera {sorted(calibrated - names)[0]!r} has no media here "
                         f"(expected a file or folder for each of {', '.join(rig.names)})")


# ---------------------------------------------------------------------------------------------
# Working volume


def derive_volume(rig: Rig, *, height_m: float = DERIVED_VOLUME_HEIGHT_M) -> np.ndarray:
    """Working volume seen by most cameras, when ``capture.yaml`` gives none.

    Rule: lay a square grid of floor positions (x, y) over the cameras' surroundings (centred on
    the mean camera position, half-size the largest camera distance from it plus 1 m, or 3 m if the
    cameras are close together). A position counts as seen by a camera when the vertical segment
    above it, sampled at :data:`DERIVED_VOLUME_HEIGHTS` (the feet and the body's middle), is in front of
    the camera and inside its image (`Camera.sees`: the undistorted pinhole model, safe far outside the
    image where the distortion polynomial is not). Keep the positions seen by a majority of the cameras (at least
    two), or, if none, by the largest number seen anywhere; the volume is their bounding box,
    ``-DERIVED_VOLUME_FLOOR_MARGIN_M <= z <= height_m``.

    Returns
    -------
    (2, 3) float
        ``[[x_min, y_min, -margin], [x_max, y_max, height_m]]`` in metres.

    Raises
    ------
    ValueError
        When no camera sees any floor position of the grid.
    """
    centres = rig.centres  # (C, 3)
    middle = centres[:, :2].mean(axis=0)
    half = max(np.linalg.norm(centres[:, :2] - middle, axis=1).max() + 1.0, 3.0)
    axis = np.linspace(-half, half, DERIVED_VOLUME_GRID)
    gx, gy = np.meshgrid(middle[0] + axis, middle[1] + axis, indexing="ij")
    floor = np.stack([gx.ravel(), gy.ravel()], axis=1)  # (G, 2)
    seen = np.ones((len(rig), len(floor)), dtype=bool)  # (C, G)
    for fraction in DERIVED_VOLUME_HEIGHTS:
        X = np.hstack([floor, np.full((len(floor), 1), fraction * height_m)])  # (G, 3)
        for c, camera in enumerate(rig):
            seen[c] &= camera.sees(X)
    counts = seen.sum(axis=0)  # (G,)
    needed = max(2, len(rig) // 2 + 1)
    if counts.max() < needed:
        needed = counts.max()
    if needed == 0:
        raise ValueError("no camera sees the floor near the cameras")
    kept = floor[counts >= needed]
    step = axis[1] - axis[0]  # grow by one grid cell so the box covers the kept cells, not their centres
    return np.array([[*(kept.min(axis=0) - step), -DERIVED_VOLUME_FLOOR_MARGIN_M],
                     [*(kept.max(axis=0) + step), height_m]])


def capture_summary(capture: Capture) -> dict:
    """Plain-data description of the capture for ``calibration/capture.json``."""
    return {
        "capture_dir": str(capture.root.resolve()),
        "fps": capture.fps,
        "cameras": list(capture.rig.names),
        "image_sizes": {camera.name: list(camera.size) for camera in capture.rig},
        "frames": list(capture.frame_numbers),
        "volume": capture.volume.tolist(),
        "volume_source": capture.volume_source,
        "world_transform": {"up": capture.config["calibration"]["up"], **capture.world.to_dict(),
                            **(capture.auto_frame.to_dict() if capture.auto_frame else {})},
        "height_m": capture.height_m,
        "media": capture.media,
        "silhouettes_given": capture.silhouettes_given,
        "backgrounds": sorted(capture.background_paths),
    }

