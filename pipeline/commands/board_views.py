"""The board views of a calibration: which camera's images or video each folder holds, their frames, and where
the board was found in them (the input side of :mod:`pipeline.commands.calibrate`)."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from calib.board import Board, Detection, detect
from calib.errors import InputError
from calib.formats import natural_key
from pipeline.io.capture.media import VIDEO_SUFFIXES

#: Board views may also be still images of formats a capture's frames are not ("bmp", "tif").
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")

@dataclass(frozen=True)
class Source:
    """Where one camera's board views of one part come from: image files, or a video."""

    path: Path
    images: tuple[Path, ...] = ()

    @property
    def is_video(self) -> bool:
        return not self.images

    def describe(self) -> str:
        return f"{self.path} ({len(self.images)} images)" if self.images else str(self.path)


def _visible(folder: Path) -> list[Path]:
    return sorted((p for p in folder.iterdir() if not p.name.startswith(".")), key=lambda p: natural_key(p.name))


def find_sources(boards: Path, part: str) -> dict[str, Source]:
    """Camera name -> its :class:`Source` in ``boards/part``: ``<camera>/`` holding images or one video, or a video
    file ``<camera>.<ext>``."""
    folder = boards / part
    if not folder.is_dir():
        return {}
    sources = {}
    for entry in _visible(folder):
        if entry.is_file() and entry.suffix.lower() in VIDEO_SUFFIXES:
            sources[entry.stem] = Source(entry)
            continue
        if not entry.is_dir():
            raise InputError(f"{entry}: not a camera folder or video (expected {part}/<camera>/ with images or one "
                             f"video, or {part}/<camera>.mp4)")
        files = [p for p in _visible(entry) if p.is_file()]
        images = tuple(p for p in files if p.suffix.lower() in IMAGE_SUFFIXES)
        videos = [p for p in files if p.suffix.lower() in VIDEO_SUFFIXES]
        if images and videos or len(videos) > 1:
            raise InputError(f"{entry}: holds {len(images)} images and {len(videos)} videos, expected images or one "
                             "video")
        if not images and not videos:
            raise InputError(f"{entry}: no images or video (expected .png/.jpg files or one .mp4)")
        stems = [p.stem for p in images]
        if len(set(stems)) < len(stems):
            twin = next(stem for stem in stems if stems.count(stem) > 1)
            raise InputError(f"{entry}: two images named {twin!r}, expected one file per view")
        if entry.name in sources:
            raise InputError(f"{entry}: camera {entry.name!r} has both a folder and a video in {folder}")
        sources[entry.name] = Source(videos[0]) if videos else Source(entry, images)
    return sources


def iter_views(source: Source, video_step: int) -> Iterator[tuple[str, np.ndarray]]:
    """Yield ``(view name, BGR image)``: image file stems, or ``<frame:06d>`` for every ``video_step``-th frame."""
    if not source.is_video:
        for path in source.images:
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if image is None:
                raise InputError(f"{path}: not a readable image")
            yield path.stem, image
        return
    capture = cv2.VideoCapture(str(source.path))
    if not capture.isOpened():
        raise InputError(f"{source.path}: OpenCV cannot open this video")
    try:
        frame = 0
        while True:
            if not capture.grab():
                break
            if frame % video_step == 0:
                ok, image = capture.retrieve()
                if not ok:
                    raise InputError(f"{source.path}: frame {frame} does not decode")
                yield f"{frame:06d}", image
            frame += 1
    finally:
        capture.release()


def _frame_count(source: Source, video_step: int) -> int:
    if not source.is_video:
        return len(source.images)
    capture = cv2.VideoCapture(str(source.path))
    count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    capture.release()
    return -(-max(count, 0) // video_step)


@dataclass
class CameraViews:
    """What one camera's folder of one part gave: detections by view, how many views were searched, the size."""

    source: Source
    detections: dict[str, Detection]
    searched: int
    size: tuple[int, int] | None


def detect_all(board: Board, sources: dict[str, Source], part: str, *, video_step: int,
               progress: bool) -> dict[str, CameraViews]:
    """Search every view of every camera for the board (a progress bar over all views of the part)."""
    total = sum(_frame_count(source, video_step) for source in sources.values())
    found: dict[str, CameraViews] = {}
    with tqdm(total=total, desc=f"{part}", unit="view", file=sys.stderr, disable=not progress) as bar:
        for camera, source in sources.items():
            views = CameraViews(source, {}, 0, None)
            bar.set_postfix_str(camera)
            for view, image in iter_views(source, video_step):
                size = (image.shape[1], image.shape[0])
                if views.size is None:
                    views.size = size
                elif size != views.size:
                    raise InputError(f"{source.path}: view {view} is {size[0]}x{size[1]} pixels, expected "
                                     f"{views.size[0]}x{views.size[1]} like the camera's first view")
                detection = detect(board, image)
                if detection is not None:
                    views.detections[view] = detection
                views.searched += 1
                bar.update()
            found[camera] = views
    return found


def spread(views: dict[str, Detection], count: int) -> dict[str, Detection]:
    """At most ``count`` of ``views``, evenly spaced in their order (a video's detections come in runs of
    nearly equal frames: taking every k-th keeps the variety)."""
    if len(views) <= count:
        return views
    keys = list(views)
    picks = np.unique(np.linspace(0, len(keys) - 1, count).round().astype(int))
    return {keys[k]: views[keys[k]] for k in picks}
