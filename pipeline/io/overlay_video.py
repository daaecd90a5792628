"""Overlay videos a browser plays: one camera's frames with the fitted skeleton, as WebM (VP8).

The report links them (``export/overlay_<camera>.webm`` beside ``report.html``), so they must play in a
browser. The pinned opencv-python-headless (5.0) carries an FFmpeg without an H.264 encoder (fourcc
``avc1``/``H264`` fail to open; only a hardware V4L2 encoder is built in), and its MPEG-4 Part 2
(``mp4v``) is a codec no browser plays. It does write VP8 in WebM, which Chromium, Firefox, Edge and
Safari (14.1 on) play; VP9 too, but about fifteen times slower. So: VP8, no further dependency.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np

from calib.camera import Camera
from calib.errors import InputError
from pipeline.io import atomic
from stages.export.overlay import draw_skeleton
from stages.joints import JOINT_NAMES

#: Codec of the overlay videos, in the container that :data:`pipeline.io.run_layout.OVERLAY_SUFFIX` names (see the
#: module docstring).
FOURCC = "VP80"


def write_overlay_video(images: Iterable[tuple[int, np.ndarray]], camera: Camera,
                        joints_by_frame: Mapping[int, np.ndarray], path: str | os.PathLike, fps: float,
                        names: Sequence[str] = JOINT_NAMES) -> int:
    """Write a WebM (VP8) of one camera's frames with the fitted skeleton drawn on them.

    Parameters
    ----------
    images : iterable of (frame, (H, W, 3) uint8 BGR image)
        The camera's frames in order (e.g. ``Capture.iter_images(camera, frames)``); streamed, so
        only one image is in memory at a time.
    camera : the calibrated camera the images come from
    joints_by_frame : mapping frame -> (J, 3) float, metres
        Frames without an entry (lost) are written without a skeleton.
    path : output path, ending in :data:`~pipeline.io.run_layout.OVERLAY_SUFFIX`
    fps : frames per second of the video

    Returns
    -------
    int
        Number of frames written.
    """
    path = Path(path)
    writer = None
    count = 0
    with atomic.atomic_output(path) as tmp:
        try:
            for frame, image in images:
                if writer is None:
                    height, width = image.shape[:2]
                    # The temporary name must keep the suffix: FFmpeg picks the container from it.
                    writer = cv2.VideoWriter(str(tmp), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*FOURCC),
                                             float(fps), (width, height))
                    if not writer.isOpened():
                        raise OSError(f"{path}: OpenCV cannot write a {FOURCC} video here")
                if frame in joints_by_frame:
                    image = draw_skeleton(image, camera, joints_by_frame[frame], names)
                writer.write(image)
                count += 1
        finally:
            if writer is not None:
                writer.release()
        if writer is None:
            raise InputError(f"{path}: no images to write for camera {camera.name!r} (expected frames)")
    return count
