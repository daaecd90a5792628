"""``up: auto``: the vertical from the rig, the floor from the subject, on captures in camera 1's frame."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from calib_testing import ring_rig

from calib.camera import Camera, Rig
from calib.formats import load_rig, save_rig
from calib.world import WorldTransform, level_rotation, rig_vertical
from pipeline.cli import main
from pipeline.evaluate import evaluate_run
from pipeline.io import frames_io
from pipeline.io.auto_frame import aim_point
from pipeline.io.capture import Capture
from pipeline.io.capture.volume import DERIVED_VOLUME_FLOOR_MARGIN_M
from pipeline.io.export_io import read_joints_csv, write_joints_csv

TAEKWONDO = Path(__file__).resolve().parents[2] / "data_samples" / "taekwondo"
#: Frames of the end-to-end comparison: short, the whole suite must stay within minutes.
FRAMES = 15


def camera_frame_transform(camera: Camera, scale: float) -> WorldTransform:
    """The map from the pipeline's world (metres) to ``camera``'s frame in units of 1/``scale`` m."""
    return WorldTransform(camera.R, camera.t / scale, 1.0 / scale)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0))))


def test_vertical_of_a_ring_in_camera_1_frame_is_its_true_up():
    rig = ring_rig(8)
    moved = camera_frame_transform(rig[0], 1.0).apply(rig)
    vertical, how = rig_vertical(moved)
    np.testing.assert_allclose(vertical, rig[0].R @ [0.0, 0.0, 1.0], atol=1e-9)
    assert "x axes" in how


def test_vertical_tolerates_cameras_that_roll_a_little():
    rig = ring_rig(6)
    rng = np.random.default_rng(5)
    rolled = []
    for camera in rig:  # rolled by up to 1.5 degrees about the optical axis
        roll = cv2.Rodrigues(np.array([0.0, 0.0, np.radians(rng.uniform(-1.5, 1.5))]))[0]
        rolled.append(Camera(camera.name, camera.K, camera.dist, roll @ camera.R, roll @ camera.t, camera.size))
    vertical, _ = rig_vertical(Rig(tuple(rolled)))
    error = angle_deg(vertical, np.array([0.0, 0.0, 1.0]))
    mean_up = -np.sum([camera.R[1] for camera in rolled], axis=0)
    assert error < 1.5 and error < angle_deg(mean_up, np.array([0.0, 0.0, 1.0])), error  # measured 1.1


def test_vertical_of_cameras_facing_one_way_comes_from_their_up_axes():
    cameras = tuple(Camera.look_at(f"c{i}", (x, -4.0, 1.6), (x, 0.0, 1.0), f_px=800.0, size=(640, 480))
                    for i, x in enumerate((-1.0, 0.0, 1.0)))
    vertical, how = rig_vertical(Rig(cameras))
    assert "mean image up" in how
    assert angle_deg(vertical, np.array([0.0, 0.0, 1.0])) < 10.0  # the cameras pitch down by 8.5 degrees


def test_level_rotation_takes_the_vertical_to_z_and_the_heading_to_x():
    vertical, heading = np.array([0.1, -0.9, -0.3]), np.array([1.0, 0.2, 0.0])
    A = level_rotation(vertical, heading)
    np.testing.assert_allclose(A @ A.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(A) == pytest.approx(1.0)
    np.testing.assert_allclose(A @ vertical / np.linalg.norm(vertical), [0.0, 0.0, 1.0], atol=1e-12)
    assert (A @ heading)[1] == pytest.approx(0.0, abs=1e-12) and (A @ heading)[0] > 0


def test_aim_point_is_where_the_cameras_look():
    np.testing.assert_allclose(aim_point(ring_rig(8)), [0.0, 0.0, 1.0], atol=0.2)  # targets within 0.2 m


def _link(capture: Path, *names: str) -> None:
    for name in names:
        shutil.copytree(TAEKWONDO / name, capture / name)


@pytest.fixture(scope="module")
def floor_and_camera_captures(tmp_path_factory) -> tuple[Path, Path]:
    """The first frames of data_samples/taekwondo twice: as shipped (floor frame, +z up, a volume), and
    with its calibration in camera 1's frame in millimetres (anipose), ``up: auto`` and no volume."""
    root = tmp_path_factory.mktemp("auto_frame")
    config = yaml.safe_load((TAEKWONDO / "capture.yaml").read_text())
    config["frames"] = {"start": 0, "stop": FRAMES, "step": 1}
    floor = root / "floor"
    floor.mkdir()
    _link(floor, "videos", "background", "calibration")
    (floor / "capture.yaml").write_text(yaml.safe_dump(config))
    camera = root / "camera1"
    camera.mkdir()
    _link(camera, "videos", "background")
    rig = load_rig("colmap", TAEKWONDO / "calibration" / "colmap")
    save_rig(camera_frame_transform(rig[0], 0.001).apply(rig), "anipose", camera / "calibration")
    config["calibration"] = {"format": "anipose", "path": "calibration/calibration.toml", "units": "mm",
                             "up": "auto"}
    del config["volume"]
    (camera / "capture.yaml").write_text(yaml.safe_dump(config))
    return floor, camera


def test_auto_frame_finds_the_floor_and_the_vertical(floor_and_camera_captures, caplog):
    floor, camera = floor_and_camera_captures
    with caplog.at_level(logging.INFO, logger="pipeline.io.capture"):
        auto = Capture.open(camera)
    assert any("up: auto: vertical" in record.getMessage() for record in caplog.records)
    truth = Capture.open(floor).rig
    for found, true in zip(auto.rig, truth, strict=True):
        # Up is up (the rig's own axes, exact for these level cameras); the floor within 4 cm (measured +2.3).
        assert angle_deg(found.R @ [0, 0, 1], true.R @ [0, 0, 1]) < 0.01
    heights = auto.rig.centres[:, 2] - truth.centres[:, 2]
    assert np.ptp(heights) < 1e-6 and abs(heights[0]) < 0.04
    assert auto.volume_source == "derived" and auto.volume[0, 2] == -DERIVED_VOLUME_FLOOR_MARGIN_M


def _mpjpe(out: Path, truth_csv: Path, to_run_frame) -> float:
    frames, _, joints = read_joints_csv(TAEKWONDO / "groundtruth" / "joints.csv")
    write_joints_csv(truth_csv, frames, to_run_frame(joints))
    return evaluate_run(out, truth=truth_csv)["mpjpe_mm"]


def test_camera_frame_capture_with_up_auto_scores_like_the_floor_frame(floor_and_camera_captures, tmp_path):
    floor, camera = floor_and_camera_captures
    scores = {}
    for name, capture in (("floor", floor), ("camera", camera)):
        out = tmp_path / name
        assert main(["run", str(capture), "--out", str(out), "--workers", "1", "-q"]) == 0
        world = frames_io.read_json(out / "calibration" / "capture.json")["world_transform"]
        recorded = WorldTransform(np.array(world["rotation"]), np.array(world["translation_m"]), world["scale"])
        to_camera = camera_frame_transform(load_rig("colmap", TAEKWONDO / "calibration" / "colmap")[0], 0.001)

        def to_run_frame(joints, name=name, recorded=recorded, to_camera=to_camera):
            if name == "floor":
                return joints
            in_camera = (joints @ to_camera.A.T * to_camera.scale + to_camera.b)  # millimetres
            return (in_camera * recorded.scale) @ recorded.A.T + recorded.b

        scores[name] = _mpjpe(out, tmp_path / f"truth_{name}.csv", to_run_frame)
        assert world["up"] == ("auto" if name == "camera" else "+z")
    # Measured 14.4 mm (floor frame, its volume) and 14.5 mm (camera 1's frame, up: auto, derived volume).
    assert abs(scores["camera"] - scores["floor"]) < 3.0, scores
