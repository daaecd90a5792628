"""The silhouette and reconstruction stages' worker side: chunking of videos, the per-worker background cache."""

from __future__ import annotations

import os

import numpy as np
import pytest

from pipeline import frame_tasks
from pipeline.graph import MAX_VIDEO_CHUNK_FRAMES, video_chunk_size
from pipeline.io import frames_io
from stages.silhouettes import SilhouetteParams


@pytest.mark.parametrize(("pending", "workers", "size"), [
    (112, 1, 112),  # one chunk: no seek at all
    (112, 2, 56),  # one chunk per worker
    (1000, 2, 167),  # six chunks of at most MAX_VIDEO_CHUNK_FRAMES, three per worker
    (401, 1, 134),
    (3, 4, 1),  # fewer frames than workers
])
def test_video_chunks_are_few_even_and_bounded(pending, workers, size):
    assert video_chunk_size(pending, workers) == size <= MAX_VIDEO_CHUNK_FRAMES


def test_background_model_is_read_again_when_the_file_changes(tmp_path):
    params = SilhouetteParams()
    path = tmp_path / "background.png"
    frames_io.write_image(path, np.full((40, 60, 3), 50, np.uint8))
    first = frame_tasks.cached_background_model(path, params)
    assert frame_tasks.cached_background_model(path, params) is first  # built once
    frames_io.write_image(path, np.full((40, 60, 3), 200, np.uint8))
    os.utime(path, ns=(os.stat(path).st_atime_ns, os.stat(path).st_mtime_ns + 10**9))  # a later write
    second = frame_tasks.cached_background_model(path, params)
    assert second is not first
    assert int(second.image[0, 0, 0]) == 200
