"""capture.yaml's frame_offsets: cameras whose media run frames behind or ahead of the others'."""

import logging

import numpy as np
import pytest
from conftest import make_capture, write_config

from calib.errors import InputError
from pipeline.graph import _write_sync_check
from pipeline.io import frames_io
from pipeline.io.capture import Capture
from pipeline.io.digest import canonical_json, text_digest
from pipeline.io.run_layout import sync_check_path
from stages.synchrony import SyncCheck


def _grey(image: np.ndarray) -> int:
    """The circle's grey level, which `tests.conftest.frame_image` makes 60 + 10 * frame."""
    height, width = image.shape[:2]
    return int(image[height // 2, width // 2, 0])


@pytest.mark.parametrize("media", ["images", "videos"])
def test_a_camera_behind_is_read_at_its_own_frames(tmp_path, media):
    root = make_capture(tmp_path / "capture", n_frames=6, media=media)
    write_config(root, frame_offsets={"cam1": 2})
    capture = Capture.open(root)
    assert capture.frame_numbers == (0, 1, 2, 3)  # cam1 has no frame 4 + 2
    (_, behind), = capture.iter_images("cam1", [1])
    (frame, other), = capture.iter_images("cam0", [1])
    assert frame == 1
    assert abs(_grey(behind) - 90) <= 3 and abs(_grey(other) - 70) <= 3  # cam1's media frame 3, cam0's frame 1


def test_a_camera_ahead_loses_the_first_frames(tmp_path):
    root = make_capture(tmp_path / "capture", n_frames=5, silhouettes=True)
    write_config(root, frame_offsets={"cam2": -1})
    capture = Capture.open(root)
    assert capture.frame_numbers == (1, 2, 3, 4)
    assert [frame for frame, _ in capture.iter_images("cam2", [1, 2])] == [1, 2]
    assert _grey(next(capture.iter_images("cam2", [1]))[1]) == 60  # its media frame 0
    (tmp_path / "capture" / "silhouettes" / "cam2" / "000003.png").unlink()  # its media frame 3, the frame 4
    with pytest.raises(InputError, match="no silhouette for frame 4"):
        Capture.open(root)


def test_the_run_records_the_offsets_it_read_with(tmp_path):
    from pipeline.io.capture import capture_summary

    root = make_capture(tmp_path / "capture", n_frames=6)
    assert capture_summary(Capture.open(root))["frame_offsets"] == {}
    write_config(root, frame_offsets={"cam1": 2})
    assert capture_summary(Capture.open(root))["frame_offsets"] == {"cam1": 2}


def test_frames_select_among_the_shared_ones(tmp_path):
    root = make_capture(tmp_path / "capture", n_frames=8)
    write_config(root, frame_offsets={"cam0": 1, "cam1": -2}, frames={"start": 3, "step": 2})
    assert Capture.open(root).frame_numbers == (3, 5)


@pytest.mark.parametrize("offsets, message", [
    ({"cam9": 1}, "frame_offsets names camera 'cam9', which is not among the cameras used"),
    ({"cam1": 1.5}, "frame_offsets.cam1 is 1.5 .expected a whole number of frames"),
    ({"cam1": True}, "frame_offsets.cam1 is True"),
    ([1, 2], "frame_offsets is \\[1, 2\\] .expected a mapping"),
    ({"cam1": 99}, "the cameras share no frame"),
])
def test_bad_frame_offsets_are_named(tmp_path, offsets, message):
    root = make_capture(tmp_path / "capture", n_frames=4)
    write_config(root, frame_offsets=offsets)
    with pytest.raises(InputError, match=message):
        Capture.open(root)


def test_the_offsets_are_part_of_the_captures_fingerprint(tmp_path):
    root = make_capture(tmp_path / "capture", n_frames=6)
    before = Capture.open(root).fingerprint("config")
    write_config(root, frame_offsets={"cam1": 0})
    assert Capture.open(root).fingerprint("config") == before  # a zero offset is no offset
    write_config(root, frame_offsets={"cam1": 1})
    assert Capture.open(root).fingerprint("config") != before


def test_another_offset_over_the_same_frames_makes_every_stage_stale(tmp_path):
    root = make_capture(tmp_path / "capture", n_frames=8)
    write_config(root, frame_offsets={"cam1": 1}, frames={"stop": 5})
    first = Capture.open(root)
    write_config(root, frame_offsets={"cam1": 2})
    second = Capture.open(root)
    assert first.frame_numbers == second.frame_numbers
    assert first.fingerprint("frames") != second.fingerprint("frames")  # the silhouettes' key: masks made again
    write_config(root, frame_offsets=None)  # without offsets, the key of the frames alone, as before they existed
    assert Capture.open(root).fingerprint("frames") == text_digest(canonical_json([0, 1, 2, 3, 4]))


def test_the_sync_check_names_the_camera_behind_and_its_offset(tmp_path, caplog):
    root = make_capture(tmp_path / "capture", n_frames=12)
    write_config(root, frame_offsets={"cam2": 1})
    capture = Capture.open(root)
    offsets = np.arange(-2, 3)
    agreement = np.full((3, 5, 4), 0.8)
    agreement[:, 2] = 0.95
    agreement[1, 3] = [0.99, 0.98, 0.99, 0.985]  # cam1 agrees best a frame later, on every frame
    part = SyncCheck([2, 4, 6, 8], offsets, agreement)
    with caplog.at_level(logging.INFO):
        _write_sync_check(capture, part, tmp_path)
    record = frames_io.read_json(sync_check_path(tmp_path))
    assert record["lag"] == {"cam0": 0, "cam1": 1, "cam2": 0}
    assert record["frame_offsets"] == {"cam1": 1, "cam2": 1}  # the one given is kept
    assert record["frames"] == [capture.frame_numbers[i] for i in (2, 4, 6, 8)]
    warning, = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert "cam1's silhouettes agree best with the other cameras' 1 frame(s) later" in warning
    assert "frame_offsets: {cam1: 1, cam2: 1} in capture.yaml" in warning


def test_an_offset_given_wrongly_is_undone(tmp_path, caplog):
    root = make_capture(tmp_path / "capture", n_frames=12)
    write_config(root, frame_offsets={"cam1": 1})
    agreement = np.full((3, 5, 4), 0.8)
    agreement[:, 2] = 0.95
    agreement[1, 1] = 0.99  # cam1, read a frame late, agrees best a frame earlier: it was on time
    with caplog.at_level(logging.INFO):
        _write_sync_check(Capture.open(root), SyncCheck([2, 4, 6, 8], np.arange(-2, 3), agreement), tmp_path)
    assert frames_io.read_json(sync_check_path(tmp_path))["frame_offsets"] == {}
    warning, = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert "no frame_offsets in capture.yaml makes up for it" in warning


def test_synchronised_cameras_get_an_info_line(tmp_path, caplog):
    capture = Capture.open(make_capture(tmp_path / "capture", n_frames=12))
    agreement = np.full((3, 5, 4), 0.8)
    agreement[:, 2] = 0.95
    with caplog.at_level(logging.INFO):
        _write_sync_check(capture, SyncCheck([2, 4, 6, 8], np.arange(-2, 3), agreement), tmp_path)
    assert frames_io.read_json(sync_check_path(tmp_path))["frame_offsets"] == {}
    assert any("every camera's silhouettes agree best" in r.getMessage() for r in caplog.records)
    assert not any(r.levelno == logging.WARNING for r in caplog.records)


def test_a_check_that_measured_nothing_says_so(tmp_path, caplog):
    capture = Capture.open(make_capture(tmp_path / "capture", n_frames=12))
    with caplog.at_level(logging.INFO):
        _write_sync_check(capture, SyncCheck([2, 4], np.arange(-2, 3), np.full((3, 5, 2), np.nan)), tmp_path)
    assert any("nothing moved in the silhouettes" in r.getMessage() for r in caplog.records)
    assert frames_io.read_json(sync_check_path(tmp_path))["lag"] == {"cam0": 0, "cam1": 0, "cam2": 0}


def test_the_report_notes_a_camera_behind():
    from pipeline.report.page import _lag

    record = {"lag": {"cam0": 0, "cam1": 2}, "frame_offsets": {"cam1": 3}}
    assert _lag(record, "cam0") == "" and _lag(None, "cam1") == ""
    note = _lag(record, "cam1")
    assert "2 frame(s) later" in note and "frame_offsets: {cam1: 3}" in note
    undone = _lag({"lag": {"cam1": -1}, "frame_offsets": {}}, "cam1")  # the offset given cancels out
    assert "1 frame(s) earlier" in undone and "should give it no frame offset" in undone


def test_the_sync_check_is_not_started_where_it_could_not_tell(tmp_path, caplog):
    from types import SimpleNamespace

    from pipeline.graph import _start_sync_check

    def context(root):
        return SimpleNamespace(capture=Capture.open(root), workers=None, input_dir=lambda stage: tmp_path / stage)

    short = make_capture(tmp_path / "short", n_frames=12)  # fewer frames than the offsets tried need
    gaps = make_capture(tmp_path / "gaps", n_frames=40)
    for camera in ("cam0", "cam1", "cam2"):
        (gaps / "images" / camera / "000003.png").unlink()
    joints = {frame: np.zeros((17, 3)) for frame in range(40)}
    with caplog.at_level(logging.INFO):
        assert _start_sync_check(context(short), joints) is None
        assert _start_sync_check(context(gaps), joints) is None
    messages = [r.getMessage() for r in caplog.records]
    assert any("too few frames with estimated joints" in m for m in messages)
    assert any("frames are not evenly spaced" in m for m in messages)
