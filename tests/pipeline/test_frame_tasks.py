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



@pytest.mark.parametrize(("pieces", "cut"), [
    ([(slice(10, 50), slice(20, 40))], False),  # the whole subject in view
    ([(slice(30, 60), slice(20, 40))], True),  # his feet below the image
    ([(slice(10, 50), slice(20, 40)), (slice(0, 2), slice(50, 53))], False),  # a speck on the border
    ([(slice(10, 50), slice(20, 40)), (slice(20, 30), slice(0, 5))], False),  # a stray blob on the border
    ([], False),  # nobody
])
def test_the_subject_is_cut_off_when_the_largest_piece_of_his_silhouette_reaches_the_border(pieces, cut):
    mask = np.zeros((60, 80), np.uint8)
    for rows, columns in pieces:
        mask[rows, columns] = 255
    assert frame_tasks.subject_cut_off(mask) is cut
