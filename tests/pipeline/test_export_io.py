import bvhio
import cv2
import ezc3d
import numpy as np
import pytest
from conftest import stick_figure

from calib.camera import Camera
from calib.errors import InputError
from pipeline.export_io import (
    read_joints_csv,
    write_exports,
    write_joints_csv,
    write_overlay_video,
)
from stages.export.angles import ANGLE_NAMES
from stages.joints import JOINT_NAMES


def _walk(n_frames: int) -> np.ndarray:
    """(n_frames, 17, 3) a stick figure walking along +y (metres, +z up); constant bone lengths."""
    base = stick_figure()
    return base[None] + np.arange(n_frames)[:, None, None] * np.array([0.0, 0.03, 0.0])


def test_joints_csv_file_round_trip(tmp_path):
    joints = _walk(4)
    write_joints_csv(tmp_path / "joints.csv", np.arange(4), joints)
    frames, names, read = read_joints_csv(tmp_path / "joints.csv")
    assert names == JOINT_NAMES
    np.testing.assert_allclose(read, joints, atol=1e-7)


def test_read_joints_csv_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match="missing.csv: file not found"):
        read_joints_csv(tmp_path / "missing.csv")
    (tmp_path / "bad.csv").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(InputError, match="bad.csv: not a readable text file"):
        read_joints_csv(tmp_path / "bad.csv")
    (tmp_path / "short.csv").write_text("frame,joint,x,y,z\n0,pelvis,1\n")
    with pytest.raises(InputError, match="short.csv:2: 3 fields"):
        read_joints_csv(tmp_path / "short.csv")


def test_write_exports_with_a_lost_frame(tmp_path):
    joints = _walk(6)
    frames = np.array([10, 12, 14, 18, 20])  # step 2, frame 16 lost
    paths = write_exports(tmp_path / "export", frames, joints[[0, 1, 2, 4, 5]], fps=50.0)
    assert sorted(p.name for p in paths.values()) == ["angles.csv", "joints.c3d", "joints.csv", "motion.bvh"]

    read_frames, _, _ = read_joints_csv(paths["joints.csv"])
    np.testing.assert_array_equal(read_frames, frames)

    angles = paths["angles.csv"].read_text().splitlines()
    assert angles[0] == "frame," + ",".join(ANGLE_NAMES) and len(angles) == 6

    bvh = bvhio.readAsBvh(str(paths["motion.bvh"]))
    assert bvh.FrameCount == 6 and bvh.FrameTime == pytest.approx(2 / 50)
    root = bvhio.readAsHierarchy(str(paths["motion.bvh"]))
    root.loadPose(3)  # the interpolated frame 16: halfway between frames 14 and 18
    pelvis_bvh = np.array(root.PositionWorld)
    np.testing.assert_allclose(pelvis_bvh, [0.0, 1.0, -(joints[3, 0, 1])], atol=1e-6)

    c3d = ezc3d.c3d(str(paths["joints.c3d"]))
    assert c3d["parameters"]["POINT"]["RATE"]["value"][0] == pytest.approx(25.0)
    assert list(c3d["parameters"]["POINT"]["LABELS"]["value"]) == list(JOINT_NAMES)
    assert c3d["parameters"]["POINT"]["UNITS"]["value"] == ["mm"]
    points = c3d["data"]["points"]
    assert points.shape == (4, 17, 6)
    np.testing.assert_allclose(points[:3, :, 0].T, joints[0] * 1000, atol=1e-3)
    np.testing.assert_allclose(points[:3, :, 5].T, joints[5] * 1000, atol=1e-3)
    assert np.isnan(points[:3, :, 3]).all()  # frame 16 lost: markers invalid


def test_write_exports_refuses_an_empty_sequence(tmp_path):
    with pytest.raises(InputError, match="no frame was estimated"):
        write_exports(tmp_path, np.zeros(0, int), np.zeros((0, 17, 3)), fps=25.0)


def test_overlay_video_has_every_frame(tmp_path):
    camera = Camera.look_at("cam", eye=(0.0, -4.0, 1.0), target=(0.0, 0.0, 1.0), f_px=150, size=(160, 120))
    joints = _walk(5)
    images = ((frame, np.full((120, 160, 3), 40, np.uint8)) for frame in range(5))
    tracked = {f: joints[f] for f in (0, 1, 3, 4)}
    count = write_overlay_video(images, camera, tracked, tmp_path / "cam.mp4", 25.0)
    assert count == 5
    video = cv2.VideoCapture(str(tmp_path / "cam.mp4"))
    frames = []
    while True:
        ok, image = video.read()
        if not ok:
            break
        frames.append(image)
    assert len(frames) == 5
    assert np.abs(frames[0].astype(int) - 40).max() > 100   # skeleton drawn
    assert np.abs(frames[2].astype(int) - 40).max() < 30    # lost frame: plain image (codec noise only)
