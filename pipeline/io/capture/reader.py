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

This module puts together what the others of the package check: ``capture.yaml``
(:mod:`~pipeline.io.capture.config`), the media and their frames (:mod:`~pipeline.io.capture.media`) and the
working volume (:mod:`~pipeline.io.capture.volume`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from calib.camera import Rig
from calib.errors import InputError, NoImageSize
from calib.formats import load_rig
from calib.sanity import check_intrinsics, check_rig_size
from calib.world import WorldTransform, fixed_transform, nearest_up_axis, rig_vertical
from pipeline.io import frames_io
from pipeline.io.capture.config import _read_config
from pipeline.io.capture.media import (
    _CameraMedia,
    _find_backgrounds,
    _find_image_folders,
    _find_media,
    _first_frame_size,
    _iter_video,
    _selected_frames,
    _warn_other_rates,
)
from pipeline.io.capture.volume import working_volume
from pipeline.io.digest import DIGEST_HEX, canonical_json, text_digest

if TYPE_CHECKING:
    from pipeline.io.auto_frame import AutoFrame

log = logging.getLogger(__name__)


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
        ``"capture.yaml"`` or ``"derived"`` (see :func:`pipeline.io.capture.volume.derive_volume`).
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
        calibration_path = _calibration_path(root, calibration["path"], allow_outside_paths)

        camera_media, media = _find_media(root)
        silhouette_media = _find_image_folders(root / "silhouettes", what="silhouettes")
        background_paths = _find_backgrounds(root / "background")
        if media == "silhouettes":
            camera_media = silhouette_media
        chosen = config.get("cameras")
        if chosen is not None:  # the other cameras' media are left alone, as if they were not there
            camera_media, silhouette_media, background_paths = (
                {name: source for name, source in found.items() if name in chosen}
                for found in (camera_media, silhouette_media, background_paths))
        sizes = {name: _first_frame_size(source) for name, source in camera_media.items()}

        rig = _load_calibration(calibration["format"], calibration_path, sizes, chosen)
        _check_camera_count(rig, root / "capture.yaml" if chosen is not None else calibration_path)
        _check_media_cameras(rig, root, media, camera_media, {"silhouettes": silhouette_media,
                                                              "background": background_paths}, sizes)
        calibration_rig = Rig(tuple(camera.with_size(*sizes[camera.name]) for camera in rig))
        auto = calibration["up"] == "auto"  # then the vertical and floor come after the frames are known
        world = fixed_transform(units=calibration["units"], up="+z" if auto else calibration["up"])
        rig = world.apply(calibration_rig)
        if not auto:
            _warn_other_up(rig, world, calibration["up"], root / "capture.yaml")
        check_rig_size(rig, units=calibration["units"], where=str(calibration_path))
        check_intrinsics(rig, where=str(calibration_path))

        offsets = config.get("frame_offsets", {})
        unknown = sorted(set(offsets) - set(rig.names))
        if unknown:
            raise InputError(f"{root / 'capture.yaml'}: frame_offsets names camera {unknown[0]!r}, which is not "
                             f"among the cameras used (expected some of {', '.join(rig.names)})")
        frame_numbers = _selected_frames(camera_media, media, root, config["frames"], root / "capture.yaml", offsets)
        if media == "videos":
            _warn_other_rates(camera_media, float(config["fps"]), root / "capture.yaml")
        _check_given_files(frame_numbers, silhouette_media, background_paths, sizes, offsets)
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

        volume, volume_source = working_volume(config["volume"], capture.rig, calibration_path)
        return dataclasses.replace(capture, volume=volume, volume_source=volume_source)

    @property
    def has_images(self) -> bool:
        """Whether the capture has colour frames (videos or images), not only silhouettes."""
        return self.media != "silhouettes"

    @property
    def silhouettes_given(self) -> bool:
        """Whether precomputed silhouettes come with the capture."""
        return bool(self.silhouette_media)

    @property
    def frame_offsets(self) -> Mapping[str, int]:
        """capture.yaml's ``frame_offsets``: per camera listed, how many frames its media run behind the others'."""
        return self.config.get("frame_offsets", {})

    def media_frame(self, camera: str, frame: int) -> int:
        """The number, in ``camera``'s own media, of the capture's ``frame`` (`frame_offsets`)."""
        return frame + self.frame_offsets.get(camera, 0)

    def iter_images(self, camera: str, frames: Iterable[int], *,
                    reuse: bool = False) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(frame, image (H, W, 3) uint8 BGR)`` for increasing ``frames`` of ``camera``.

        One decoder stays open for the whole iteration; a video is read sequentially, seeking
        only when the next wanted frame is behind or far ahead. Close the generator (or exhaust
        it) to release the decoder. ``reuse``: a video's frames may all be decoded into one array,
        overwritten by the next frame, for a caller done with each frame before it asks for the next.
        ``frames`` are the capture's; a camera with a frame offset is read at its own (`media_frame`).
        """
        if not self.has_images:
            raise ValueError("iter_images: this capture has silhouettes only (check has_images)")
        source = self.camera_media[camera]
        expected = tuple(self.rig[camera].size)
        offset = self.frame_offsets.get(camera, 0)
        wanted = (f + offset for f in frames)
        images = (_iter_video(source.path, wanted, reuse=reuse) if self.media == "videos"
                  else ((f, frames_io.read_image(source.frame_path(f))) for f in wanted))
        for frame, image in images:
            size = (image.shape[1], image.shape[0])
            if size != expected:
                where = source.path if self.media == "videos" else source.frame_path(frame)
                raise InputError(f"{where}: frame {frame} is {size[0]}x{size[1]} pixels "
                                 f"(expected {expected[0]}x{expected[1]} like the camera's first frame)")
            yield frame - offset, image

    def background(self, camera: str) -> np.ndarray | None:
        """The camera's clean plate ``(H, W, 3) uint8`` BGR, or ``None`` when not given."""
        path = self.background_paths.get(camera)
        return None if path is None else frames_io.read_image(path)

    def read_silhouette(self, camera: str, frame: int) -> np.ndarray:
        """The given mask ``(H, W) uint8`` in {0, 255} of ``camera`` at ``frame``."""
        path = self.silhouette_media[camera].frame_path(self.media_frame(camera, frame))
        mask = frames_io.read_mask(path)
        expected = tuple(self.rig[camera].size)
        if (mask.shape[1], mask.shape[0]) != expected:
            raise InputError(f"{path}: mask is {mask.shape[1]}x{mask.shape[0]} pixels "
                             f"(expected {expected[0]}x{expected[1]}, the camera's image size)")
        return mask

    def fingerprint(self, part: str) -> str:
        """A short hash of one part of the capture, for cache keys.

        Parts: ``"config"`` (parsed capture.yaml), ``"frames"`` (selected frame numbers, and the cameras'
        ``frame_offsets``),
        ``"calibration"`` (file contents), ``"image_sizes"``, and the media ``"images"``,
        ``"background"``, ``"silhouettes"`` (path + size + mtime of each file: cheap, and a changed
        file gets a new mtime).
        """
        if part == "config":
            return text_digest(canonical_json(self.config))
        if part == "frames":  # which media frame each camera reads too, when frame_offsets says (else as before)
            frames = list(self.frame_numbers)
            return text_digest(canonical_json({"frames": frames, "frame_offsets": dict(self.frame_offsets)}
                                              if self.frame_offsets else frames))
        if part == "image_sizes":
            return text_digest(canonical_json({camera.name: list(camera.size) for camera in self.rig}))
        if part == "calibration":  # named within the calibration itself, which may lie anywhere
            path = self.root / self.config["calibration"]["path"]
            files = sorted(p for p in ([path] if path.is_file() else path.rglob("*")) if p.is_file())
            digest = hashlib.sha256()
            for file in files:
                name = file.name if file == path else file.relative_to(path).as_posix()
                digest.update(name.encode() + b"\0" + file.read_bytes() + b"\0")
            return digest.hexdigest()[:DIGEST_HEX]
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
                files += [source.frame_path(self.media_frame(name, frame)) for frame in self.frame_numbers]
            else:
                files.append(source.path)
        return files


def _stat_digest(files: Iterable[Path], root: Path) -> str:
    digest = hashlib.sha256()
    for file in files:
        stat = file.stat()
        digest.update(f"{file.relative_to(root)}\0{stat.st_size}\0{stat.st_mtime_ns}\n".encode())
    return digest.hexdigest()[:DIGEST_HEX]


def _calibration_path(root: Path, relative: str, allow_outside_paths: bool) -> Path:
    """``calibration.path`` resolved against the capture, which it must exist in (or, allowed, outside it)."""
    calibration_path = root / relative
    if not allow_outside_paths and not _lies_in(calibration_path, root):
        raise InputError(f"{root / 'capture.yaml'}: calibration.path {relative!r} leads outside the "
                         f"capture (expected a path inside {root}, or run --allow-outside-paths)")
    if not calibration_path.exists():
        raise InputError(f"{root / 'capture.yaml'}: calibration.path {relative!r} does not "
                         f"exist (expected a path relative to {root})")
    return calibration_path


def _check_media_cameras(rig: Rig, root: Path, media: str, camera_media: Mapping[str, _CameraMedia],
                         folders: Mapping[str, Mapping], sizes: Mapping[str, tuple[int, int]]) -> None:
    """The media's cameras, and those of the given ``folders`` (silhouettes/, background/), are the
    calibration's, and the media's image sizes are those it calibrated. Clean plates are optional per camera
    (CAPTURE_FORMAT.md): a camera without one is reported, its background estimated from the frames."""
    _check_same_cameras(rig, set(camera_media), where=root / media)
    for folder, names in folders.items():
        if names:
            _check_same_cameras(rig, set(names), where=root / folder, every=folder != "background")
    unplated = [name for name in rig.names if name not in folders["background"]]
    if folders["background"] and unplated:
        log.warning("%s: no clean plate for camera %s; %s background is estimated from the frames",
                    root / "background", ", ".join(unplated), "its" if len(unplated) == 1 else "their")
    for camera in rig:
        if tuple(camera.size) != sizes[camera.name]:
            raise InputError(
                f"{camera_media[camera.name].path}: image size {sizes[camera.name]} differs from the "
                f"calibration's {tuple(camera.size)} for camera {camera.name!r} (expected equal sizes)")


def _check_given_files(frame_numbers: Sequence[int], silhouette_media: Mapping[str, _CameraMedia],
                       background_paths: Mapping[str, Path], sizes: Mapping[str, tuple[int, int]],
                       offsets: Mapping[str, int]) -> None:
    """Given silhouettes cover every processed frame (at the cameras' `offsets`); given clean plates have their
    camera's size."""
    for name, source in silhouette_media.items():
        missing = [f for f in frame_numbers if not source.frame_path(f + offsets.get(name, 0)).is_file()]
        if missing:
            raise InputError(f"{source.path}: no silhouette for frame {missing[0]} "
                             f"({len(missing)} missing; expected one mask per processed frame)")
    for name, path in background_paths.items():
        size = frames_io.image_size(path)
        if size != sizes[name]:
            raise InputError(f"{path}: image size {size} differs from camera {name!r}'s {sizes[name]} "
                             "(expected the clean plate of that camera)")


def _lies_in(path: Path, root: Path) -> bool:
    """Whether ``path`` (``..`` and links followed) is ``root`` or lies under it."""
    path, root = path.resolve(), root.resolve()
    return path == root or root in path.parents


def _load_calibration(fmt: str, path: Path, sizes: Mapping[str, tuple[int, int]],
                      cameras: Sequence[str] | None = None) -> Rig:
    """Load the calibration, only its ``cameras`` when given (capture.yaml's ``cameras:``); ``sizes`` (from the media)
    fill in formats that do not store them and must agree with those that do."""
    try:
        return load_rig(fmt, path, image_sizes=dict(sizes), cameras=cameras)
    except InputError as error:
        message = str(error)
        if isinstance(error, NoImageSize):  # a calibrated camera without media
            message += "; `cameras:` in capture.yaml lists the ones to use"
        raise InputError(message if str(path) in message else f"{path}: {message}") from None
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise InputError(f"{path}: cannot read the {fmt} calibration ({type(error).__name__}: {error}) "
                         f"(expected a valid {fmt} calibration, see CAPTURE_FORMAT.md)") from None


def _check_camera_count(rig: Rig, where: Path) -> None:
    """Refuse a rig of one camera and warn about one of two: the visual shape is where every view's silhouette
    agrees, and two views bound the body from two sides only (measured in docs/results_by_hand.md, "A user's bad
    input, swept")."""
    if len(rig) < 2:
        raise InputError(f"{where}: {len(rig)} camera (expected at least 2, better 3 or more around the subject: "
                         "one view gives a silhouette, not a 3-D shape)")
    if len(rig) == 2:
        log.warning("%s: 2 cameras: two views bound the body from two sides only; expect joints several "
                    "centimetres off and many doubtful frames (3 or more cameras around the subject do far better)",
                    where)


#: A declared up axis further than this (degrees) from the vertical the cameras' horizon gives is reported: a
#: level studio rig agrees within a few degrees, a wrong axis is a quarter or half turn away.
UP_DISAGREEMENT_DEG = 45.0


def _warn_other_up(rig: Rig, world: WorldTransform, declared: str, config_path: Path) -> None:
    """One warning when the cameras of ``rig`` (in the pipeline's world, converted with ``declared`` as up) make
    the vertical another axis of the calibration (:func:`calib.world.rig_vertical`: studio cameras do not roll):
    with a wrong ``calibration.up`` the floor, the working volume and the shadows' test are all askew, and what
    the run shows is a cascade of lost frames. A rig of cameras turned on their side would disagree as well,
    hence a warning, not an error."""
    vertical, _ = rig_vertical(rig)
    angle = float(np.degrees(np.arccos(np.clip(vertical[2], -1.0, 1.0))))
    if angle <= UP_DISAGREEMENT_DEG:
        return
    likely = nearest_up_axis(world.A.T @ vertical)  # the same direction in the calibration's own axes
    log.warning("%s: calibration.up is %s, but the cameras, which studios mount level, make the world's up about %s "
                "(%.0f degrees away): expected the calibration's up axis there (or up: auto)", config_path,
                declared, likely, angle)


def _check_same_cameras(rig: Rig, names: set[str], *, where: Path, every: bool = True) -> None:
    """Refuse ``names`` (of the cameras found ``where``) not in the calibration and, when ``every``, calibrated
    cameras missing from them."""
    calibrated = set(rig.names)
    if names - calibrated:
        raise InputError(f"{where}: camera {sorted(names - calibrated)[0]!r} is not in the calibration "
                         f"(expected one of {', '.join(rig.names)})")
    if every and calibrated - names:
        raise InputError(f"{where}: calibrated camera {sorted(calibrated - names)[0]!r} has no media here "
                         f"(expected a file or folder for each of {', '.join(rig.names)}; `cameras:` in capture.yaml "
                         "lists the ones to use)")


def capture_summary(capture: Capture) -> dict:
    """Plain-data description of the capture for ``calibration/capture.json``."""
    return {
        "capture_dir": str(capture.root.resolve()),
        "fps": capture.fps,
        "cameras": list(capture.rig.names),
        "image_sizes": {camera.name: list(camera.size) for camera in capture.rig},
        "frames": list(capture.frame_numbers),
        "frame_offsets": dict(capture.frame_offsets),
        "volume": capture.volume.tolist(),
        "volume_source": capture.volume_source,
        "world_transform": {"up": capture.config["calibration"]["up"], **capture.world.to_dict(),
                            **(capture.auto_frame.to_dict() if capture.auto_frame else {})},
        "height_m": capture.height_m,
        "media": capture.media,
        "silhouettes_given": capture.silhouettes_given,
        "backgrounds": sorted(capture.background_paths),
    }

