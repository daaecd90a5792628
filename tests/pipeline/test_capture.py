"""Capture reading: layout discovery, streaming frames, world conversion, derived volume, fingerprints."""

from __future__ import annotations

import os
import pickle
import re
import shutil
import types

import numpy as np
import pytest
from conftest import BACKGROUND_GREY, TINY_SIZE, frame_image, make_capture, tiny_rig, write_config

from calib.errors import InputError
from pipeline.io.capture import Capture, derive_volume
from pipeline.io.capture.volume import DERIVED_VOLUME_FLOOR_MARGIN_M
from stages.tracking.params import TrackerParams


def test_image_capture_metadata(tiny_capture):
    capture = Capture.open(tiny_capture)
    assert capture.media == "images"
    assert capture.fps == 25.0
    assert capture.rig.names == ("cam0", "cam1", "cam2")
    assert all(camera.size == TINY_SIZE for camera in capture.rig)
    assert capture.frame_numbers == (0, 1, 2, 3)
    assert capture.height_m is None
    assert not capture.silhouettes_given
    assert capture.background("cam0") is None


def test_iter_images_streams_the_requested_frames(tiny_capture):
    capture = Capture.open(tiny_capture)
    frames = capture.iter_images("cam1", [1, 3])
    assert isinstance(frames, types.GeneratorType)  # one frame at a time, nothing preloaded
    received = list(frames)
    assert [frame for frame, _ in received] == [1, 3]
    np.testing.assert_array_equal(received[1][1], frame_image(3))


def test_video_capture_reads_and_seeks(tmp_path):
    capture = Capture.open(make_capture(tmp_path / "c", media="videos", n_frames=20))
    assert capture.media == "videos"
    assert capture.frame_numbers == tuple(range(20))
    centre = (TINY_SIZE[1] // 2, TINY_SIZE[0] // 2)
    wanted = [0, 2, 3, 15, 19]  # small skip (decoded), large skip (seek)
    for frame, image in capture.iter_images("cam2", wanted):
        assert image.shape == (TINY_SIZE[1], TINY_SIZE[0], 3)
        assert abs(int(image[centre][1]) - (60 + 10 * frame)) <= 4, frame  # MJPG is lossy
    assert [frame for frame, _ in capture.iter_images("cam2", wanted)] == wanted


def test_video_frames_decoded_into_one_array_on_request(tmp_path):
    capture = Capture.open(make_capture(tmp_path / "c", media="videos", n_frames=6))
    wanted = [0, 1, 4]
    fresh = [image for _, image in capture.iter_images("cam1", wanted)]
    reused = []
    for frame, image in capture.iter_images("cam1", wanted, reuse=True):
        np.testing.assert_array_equal(image, fresh[wanted.index(frame)])
        reused.append(image)
    assert reused[0] is reused[1] is reused[2]  # each frame overwrote the one before


def test_frame_range_selects_on_frame_numbers(tiny_capture):
    write_config(tiny_capture, frames={"start": 1, "stop": 4, "step": 2})
    assert Capture.open(tiny_capture).frame_numbers == (1, 3)


def test_silhouettes_only_capture(tmp_path):
    capture = Capture.open(make_capture(tmp_path / "c", media="none", silhouettes=True))
    assert capture.media == "silhouettes" and not capture.has_images and capture.silhouettes_given
    mask = capture.read_silhouette("cam0", 2)
    assert mask.dtype == np.uint8 and set(np.unique(mask)) == {0, 255}
    with pytest.raises(ValueError, match="silhouettes only"):
        next(capture.iter_images("cam0", [0]))


def test_backgrounds_are_read(tmp_path):
    capture = Capture.open(make_capture(tmp_path / "c", backgrounds=True))
    assert capture.background("cam1").shape == (TINY_SIZE[1], TINY_SIZE[0], 3)
    assert capture.background("cam1").max() == BACKGROUND_GREY


@pytest.mark.parametrize(("fmt", "units", "up"), [("anipose", "m", "+z"), ("opencv", "cm", "+y"),
                                                  ("colmap", "mm", "-x")])
def test_calibration_is_converted_to_the_world_frame(tmp_path, fmt, units, up):
    capture = Capture.open(make_capture(tmp_path / "c", fmt=fmt, units=units, up=up))
    np.testing.assert_allclose(capture.rig.centres, tiny_rig().centres, atol=1e-9)


def test_projection_matrix_capture_matches_the_same_capture_in_another_format(tmp_path):
    projection = Capture.open(make_capture(tmp_path / "p", fmt="projection", units="mm", up="+y"))
    anipose = Capture.open(make_capture(tmp_path / "a", fmt="anipose"))
    assert projection.rig.names == anipose.rig.names
    for got, want in zip(projection.rig, anipose.rig, strict=True):
        assert got.size == want.size
        for field in ("K", "R", "t"):
            np.testing.assert_allclose(getattr(got, field), getattr(want, field), rtol=0, atol=1e-9)
    np.testing.assert_allclose(projection.volume, anipose.volume, atol=1e-9)


def test_volume_from_capture_yaml(tmp_path):
    volume = {"min": [-1.0, -1.5, 0.0], "max": [1.0, 1.5, 2.0]}
    capture = Capture.open(make_capture(tmp_path / "c", volume=volume))
    np.testing.assert_array_equal(capture.volume, [volume["min"], volume["max"]])
    assert capture.volume_source == "capture.yaml"


def test_derived_volume_covers_what_most_cameras_see():
    rig = tiny_rig(8, radius_m=4.0)  # a ring of 8 cameras looking at (0, 0, 1)
    volume = derive_volume(rig)
    assert volume[0, 2] == -DERIVED_VOLUME_FLOOR_MARGIN_M < 0.0 and volume[1, 2] == 2.3  # the soles are in it
    assert np.all(volume[0, :2] < -0.5) and np.all(volume[1, :2] > 0.5)  # the centre is inside
    assert np.all(volume[0, :2] > -4.0) and np.all(volume[1, :2] < 4.0)  # the cameras are outside
    np.testing.assert_allclose(volume[0, :2], -volume[1, :2], atol=0.1)  # symmetric ring, symmetric box


def test_derived_volume_needs_a_camera_seeing_the_floor():
    from calib.camera import Camera, Rig
    sky = Rig((Camera.look_at("up", (0, 0, 1), (0, 0, 10), up=(0, 1, 0), f_px=50, size=TINY_SIZE),))
    with pytest.raises(ValueError, match="no camera sees the floor"):
        derive_volume(sky)


def test_capture_pickles_for_workers(tiny_capture):
    capture = pickle.loads(pickle.dumps(Capture.open(tiny_capture)))
    assert [frame for frame, _ in capture.iter_images("cam0", [0])] == [0]


def test_fingerprints_follow_the_files(tiny_capture):
    capture = Capture.open(tiny_capture)
    before = {part: capture.fingerprint(part) for part in ("config", "calibration", "images", "frames")}
    image = tiny_capture / "images" / "cam0" / "000001.png"
    os.utime(image, ns=(1, 1))
    after = Capture.open(tiny_capture)
    assert after.fingerprint("images") != before["images"]
    assert {part: after.fingerprint(part) for part in ("config", "calibration", "frames")} == {
        part: before[part] for part in ("config", "calibration", "frames")}


@pytest.mark.parametrize(("changes", "key"), [
    ({"volum": {"min": [0, 0, 0], "max": [1, 1, 1]}}, "'volum' (expected one of fps, calibration"),
    ({"calibration": {"format": "anipose", "path": "calibration/calibration.toml", "unit": "mm"}},
     "'calibration.unit' (expected one of calibration.format, calibration.path"),
    ({"subject": {"height": 1.8}}, "'subject.height' (expected one of subject.height_m)"),
    ({"frames": {"begin": 1}}, "'frames.begin' (expected one of frames.start, frames.stop, frames.step)"),
])
def test_unknown_keys_are_refused(tiny_capture, changes, key):
    write_config(tiny_capture, **changes)  # a typo would otherwise be silently ignored
    with pytest.raises(InputError, match=re.escape(f"capture.yaml: unknown key {key}")):
        Capture.open(tiny_capture)


@pytest.mark.parametrize(("height", "accepted"), [(2.6, True), (2.61, False), (0.5, False), (175, False)])
def test_the_capture_and_the_tracker_accept_the_same_subject_heights(tiny_capture, height, accepted):
    write_config(tiny_capture, subject={"height_m": height})
    if accepted:
        assert Capture.open(tiny_capture).height_m == height
        TrackerParams(height_m=height)
        return
    with pytest.raises(InputError, match="subject.height_m"):
        Capture.open(tiny_capture)
    with pytest.raises(InputError, match="tracking.height_m"):
        TrackerParams(height_m=height)


@pytest.mark.parametrize("fmt", ["anipose", "opencv", "projection"])
def test_cameras_selects_calibrated_cameras_and_the_others_need_no_media(tmp_path, fmt):
    root = make_capture(tmp_path / "c", fmt=fmt, backgrounds=True, silhouettes=True)
    whole = Capture.open(root)
    shutil.rmtree(root / "images" / "cam1")  # a camera whose recording failed
    (root / "background" / "cam1.png").unlink()
    with pytest.raises(InputError, match="'cam1'.*`cameras:` in capture.yaml lists the ones to use"):
        Capture.open(root)
    write_config(root, cameras=["cam2", "cam0"])
    capture = Capture.open(root)
    assert capture.rig.names == ("cam0", "cam2")  # in the calibration's order
    kept = {"cam0", "cam2"}
    assert set(capture.camera_media) == set(capture.background_paths) == set(capture.silhouette_media) == kept
    for name in capture.rig.names:
        np.testing.assert_allclose(capture.rig[name].P, whole.rig[name].P, atol=1e-9)
    assert capture.fingerprint("config") != whole.fingerprint("config")


@pytest.mark.parametrize(("cameras", "message"), [
    (["cam0", "cam9"], "no camera 'cam9' in this calibration"),
    (["cam0", "cam0"], "cameras names 'cam0' twice"),
    ([], "cameras is []"),
    ("cam0", "expected a list of camera names"),
])
def test_cameras_naming_an_unknown_or_repeated_camera_is_refused(tiny_capture, cameras, message):
    write_config(tiny_capture, cameras=cameras)
    with pytest.raises(InputError, match=re.escape(message)):
        Capture.open(tiny_capture)


def test_videos_stating_another_frame_rate_than_capture_yaml_are_reported(tmp_path, caplog):
    root = make_capture(tmp_path / "c", media="videos")  # written at 25 frames/s, as capture.yaml says
    Capture.open(root)
    assert "the videos say otherwise" not in caplog.text
    write_config(root, fps=30.0)
    Capture.open(root)
    assert "capture.yaml: fps is 30, but the videos say otherwise (frames/s: cam0 25, cam1 25, cam2 25)" in caplog.text


def test_a_declared_up_axis_the_cameras_contradict_is_reported_with_the_likely_one(tmp_path, caplog):
    root = make_capture(tmp_path / "c", up="-y")  # the calibration's world has its up along -y
    Capture.open(root)
    assert "calibration.up" not in caplog.text
    write_config(root, calibration={"format": "anipose", "path": "calibration/calibration.toml", "up": "+z"})
    Capture.open(root)
    assert "calibration.up is +z, but the cameras, which studios mount level, make the world's up about -y" in (
        caplog.text)


def test_one_camera_is_refused_and_two_are_reported(tiny_capture, caplog):
    write_config(tiny_capture, cameras=["cam1"])
    with pytest.raises(InputError, match=re.escape("1 camera (expected at least 2")):
        Capture.open(tiny_capture)
    write_config(tiny_capture, cameras=["cam0", "cam2"])
    Capture.open(tiny_capture)
    assert "2 cameras: two views bound the body from two sides only" in caplog.text


def test_a_camera_without_a_clean_plate_is_reported_and_keeps_the_others(tmp_path, caplog):
    root = make_capture(tmp_path / "c", backgrounds=True)
    (root / "background" / "cam1.png").unlink()
    capture = Capture.open(root)
    assert set(capture.background_paths) == {"cam0", "cam2"} and capture.background("cam1") is None
    assert "no clean plate for camera cam1; its background is estimated from the frames" in caplog.text
