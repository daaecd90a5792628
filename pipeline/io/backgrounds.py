"""Frames spread over a capture, and a quick background image of a camera from them.

What looks at a few frames before (or outside) the silhouette stage uses these: ``up: auto``'s floor
search (:mod:`pipeline.io.auto_frame`, which the capture reader calls), the silhouette stage's own
background sampling and the benchmarks. They live here rather than in :mod:`pipeline.graph`, which
imports the capture reader: the reader's side can use them without importing the stage graph.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from stages.silhouettes import median_background

if TYPE_CHECKING:
    from pipeline.io.capture import Capture

log = logging.getLogger(__name__)

#: Frames sampled per camera for a temporal-median background when no clean plate is given.
MEDIAN_BACKGROUND_FRAMES = 25


def spread_frames(frames: Sequence[int], count: int) -> list[int]:
    """At most ``count`` of ``frames``, evenly spread from the first to the last (sorted, no repeats)."""
    picks = np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int)
    return sorted({frames[int(i)] for i in picks})


def background_image(capture: Capture, camera: str) -> np.ndarray:
    """The camera's clean plate, else the temporal median of frames spread over the capture.

    A quick background for a look at a few frames (``up: auto``'s floor search, benchmarks); the silhouette
    stage estimates backgrounds without plates from every camera together
    (:func:`pipeline.graph.estimated_backgrounds`), which leaves out a subject who stands still.
    """
    plate = capture.background(camera)
    if plate is not None:
        return plate
    picks = spread_frames(capture.frame_numbers, MEDIAN_BACKGROUND_FRAMES)
    log.info("silhouettes: no clean plate for camera %s; using the median of %d frames", camera, len(picks))
    return median_background(image for _, image in capture.iter_images(camera, picks))
