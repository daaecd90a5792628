"""The silhouette and reconstruction stages' worker side: chunking of videos, the per-worker background cache, the
given masks."""

from __future__ import annotations

import os

import numpy as np
import pytest
from conftest import make_capture

from pipeline import frame_tasks
from pipeline.graph import MAX_VIDEO_CHUNK_FRAMES, video_chunk_size
from pipeline.io import frames_io
from pipeline.io.capture import Capture
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


def test_given_masks_marking_most_of_every_image_are_reported_as_maybe_inverted(tmp_path, caplog):
    root = make_capture(tmp_path / "c", media="none", silhouettes=True, n_frames=2)
    out = tmp_path / "out"
    params = SilhouetteParams(multiview_check=False)
    frame_tasks.silhouettes_task([0, 1], capture=Capture.open(root), params=params, out_dir=out)
    assert "inverted" not in caplog.text
    for path in (root / "silhouettes").rglob("*.png"):
        mask = frames_io.read_mask(path)
        frames_io.write_mask(path, 255 - mask)
    frame_tasks.silhouettes_task([1], capture=Capture.open(root), params=params, out_dir=out)
    assert "frame 1: the given silhouettes mark most of every camera's image as person" in caplog.text
