import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.board import Detection, parse_board
from calib.calibrate import calibrate_intrinsics, calibrate_rig
from calib.camera import Camera, Rig
from calib.errors import InputError

BOARD = parse_board("checkerboard:8x5:0.11")
NOISE_PX = 0.05


def seen(camera: Camera, R: np.ndarray, t: np.ndarray, rng) -> Detection:
    """The board at ``X = R X_board + t`` as ``camera`` detects it: projected corners plus noise."""
    corners = camera.project(BOARD.object_points @ R.T + t) + rng.normal(0, NOISE_PX, (BOARD.n_corners, 2))
    return Detection(np.arange(BOARD.n_corners), corners)


def camera_poses_in_front(camera: Camera, count: int, rng) -> list[tuple[np.ndarray, np.ndarray]]:
    """Board poses 1.5-2.5 m in front of ``camera``, tilted 20-45 degrees, spread over the image."""
    poses = []
    centre = BOARD.object_points.mean(axis=0)
    while len(poses) < count:
        axis = rng.uniform(0, 2 * np.pi)
        R_cb = Rotation.from_rotvec(np.radians(rng.uniform(20, 45)) * np.array([np.cos(axis), np.sin(axis), 0]))
        R_cb = R_cb.as_matrix()
        t_cb = np.array([rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3), rng.uniform(1.5, 2.5)]) - R_cb @ centre
        R, t = camera.R.T @ R_cb, camera.R.T @ (t_cb - camera.t)
        uv = camera.project(BOARD.object_points @ R.T + t)
        if np.all((uv > 5) & (uv < np.array(camera.size) - 5)):
            poses.append((R, t))
    return poses


@pytest.fixture(scope="module")
def ring() -> Rig:
    """Five cameras on a 4 m ring around the origin, 2 m up, each with its own lens."""
    cameras = []
    for k in range(5):
        angle = 2 * np.pi * k / 5
        base = Camera.look_at(f"cam{k + 1}", [4 * np.cos(angle), 4 * np.sin(angle), 2.0], [0, 0, 1.0],
                              f_px=700 + 40 * k, size=(800, 600), dist=[-0.12 + 0.03 * k, 0.01, 0, 0, 0])
        K = base.K.copy()
        K[:2, 2] += [5 - 2 * k, 3 * k - 4]
        cameras.append(Camera(base.name, K, base.dist, base.R, base.t, base.size))
    return Rig(tuple(cameras))


def test_intrinsics_come_back_and_a_wrong_view_is_dropped(ring):
    rng = np.random.default_rng(0)
    camera = ring[0]
    detections = {f"{k:02d}": seen(camera, R, t, rng) for k, (R, t) in enumerate(camera_poses_in_front(camera, 8, rng))}
    shifted = detections["03"].corners.copy()
    shifted[::3] += 4.0  # a third of the corners on the wrong saddle
    detections["03"] = Detection(detections["03"].ids, shifted)
    lens = calibrate_intrinsics(BOARD.object_points, detections, camera.size, camera=camera.name)
    assert lens.dropped == ("03",) and len(lens.views) == 7
    np.testing.assert_allclose(lens.K, camera.K, rtol=2e-3, atol=0.5)
    assert lens.dist[0] == pytest.approx(camera.dist[0], abs=5e-3)
    assert lens.rms_px == pytest.approx(NOISE_PX * np.sqrt(2), rel=0.3)
    assert not lens.weak


def test_too_few_views_name_the_camera(ring):
    rng = np.random.default_rng(1)
    camera = ring[1]
    detections = {str(k): seen(camera, R, t, rng) for k, (R, t) in enumerate(camera_poses_in_front(camera, 2, rng))}
    with pytest.raises(InputError, match="camera 'cam2': the board was found in 2 view"):
        calibrate_intrinsics(BOARD.object_points, detections, camera.size, camera=camera.name)


def lenses_of(rig: Rig, rng) -> dict:
    """Each camera's intrinsics calibrated from its own views (as the command does)."""
    result = {}
    for camera in rig:
        views = {str(k): seen(camera, R, t, rng) for k, (R, t) in enumerate(camera_poses_in_front(camera, 6, rng))}
        result[camera.name] = calibrate_intrinsics(BOARD.object_points, views, camera.size, camera=camera.name)
    return result


def shared_views(rig: Rig, rng, *, pairs=None, floor=True) -> dict:
    """Board poses between neighbouring cameras (each seen by two of them) and, with ``floor``, the board flat
    on the floor at the origin seen by every camera; camera -> view -> detection."""
    observations = {camera.name: {} for camera in rig}
    centre = BOARD.object_points.mean(axis=0)
    count = len(rig)
    for k, (a, b) in enumerate(pairs or [(i, (i + 1) % count) for i in range(count)] * 3):
        middle = (rig[a].centre + rig[b].centre) / 2
        middle /= np.linalg.norm(middle[:2])
        facing = np.array([middle[0], middle[1], 0.3])
        z_axis = -facing / np.linalg.norm(facing)
        x_axis = np.cross(z_axis, [0, 0, 1.0])
        x_axis /= np.linalg.norm(x_axis)
        R = np.column_stack([x_axis, np.cross(z_axis, x_axis), z_axis])
        R = R @ Rotation.from_euler("z", rng.uniform(-20, 20), degrees=True).as_matrix()
        t = np.array([*rng.uniform(-0.4, 0.4, 2), rng.uniform(0.8, 1.4)]) - R @ centre
        for index in (a, b):
            observations[rig[index].name][f"{k:03d}"] = seen(rig[index], R, t, rng)
    if floor:
        for camera in rig:
            observations[camera.name]["floor"] = seen(camera, np.diag([1.0, -1, -1]), np.array([-0.4, 0.3, 0]), rng)
    return observations


def test_rig_comes_back_in_the_floor_frame(ring):
    rng = np.random.default_rng(2)
    result = calibrate_rig(lenses_of(ring, rng), shared_views(ring, rng), BOARD.object_points, floor=["floor"])
    assert result.floor == ("floor",) and result.rms_px < 0.2 and not result.dropped
    # the floor board's corner 0 lies at (-0.4, 0.3, 0) of the true world, its x axis along +x: the origin moves
    for got, want in zip(result.rig, ring, strict=True):
        np.testing.assert_allclose(got.centre, want.centre - [-0.4, 0.3, 0], atol=5e-3)
        angle = np.degrees(np.linalg.norm(cv2.Rodrigues(got.R @ want.R.T)[0]))
        assert angle < 0.15, got.name  # the principal points, from six views each, are off by a few tenths
    assert len(result.chain) == len(ring) - 1


def test_without_a_floor_the_world_is_the_first_cameras_frame(ring):
    rng = np.random.default_rng(3)
    result = calibrate_rig(lenses_of(ring, rng), shared_views(ring, rng, floor=False), BOARD.object_points)
    np.testing.assert_allclose(result.rig[0].R, np.eye(3), atol=1e-9)
    np.testing.assert_allclose(result.rig[0].t, 0, atol=1e-9)
    # distances between the cameras are metric (the board's squares set the scale), to the 10 mm of the target:
    # without the floor board, seen by all, only pairs of neighbours link the ring
    got = np.linalg.norm(result.rig.centres[1:] - result.rig.centres[:1], axis=1)
    want = np.linalg.norm(ring.centres[1:] - ring.centres[:1], axis=1)
    np.testing.assert_allclose(got, want, atol=0.01)


def test_a_camera_sharing_no_view_is_named(ring):
    rng = np.random.default_rng(4)
    pairs = [(0, 1), (1, 2), (2, 3), (0, 3)] * 2  # cam5 sees none of these
    observations = shared_views(ring, rng, pairs=pairs, floor=False)
    observations["cam5"] = {"lonely": seen(ring[4], *camera_poses_in_front(ring[4], 1, rng)[0], rng)}
    with pytest.raises(InputError, match="camera 'cam5' shares no board view with the other cameras"):
        calibrate_rig(lenses_of(ring, rng), observations, BOARD.object_points)


def test_two_groups_of_cameras_are_named(ring):
    rng = np.random.default_rng(5)
    observations = shared_views(ring, rng, pairs=[(0, 1), (2, 3), (3, 4)] * 2, floor=False)
    with pytest.raises(InputError, match="2 groups that share no board view: cam3, cam4, cam5; cam1, cam2"):
        calibrate_rig(lenses_of(ring, rng), observations, BOARD.object_points)


def test_a_camera_without_any_view_is_named(ring):
    rng = np.random.default_rng(6)
    observations = shared_views(ring, rng, floor=False)
    observations["cam3"] = {}
    with pytest.raises(InputError, match="camera 'cam3': the board was found in none of its extrinsics views"):
        calibrate_rig(lenses_of(ring, rng), observations, BOARD.object_points)


def test_floor_from_several_boards_is_their_common_plane(ring):
    rng = np.random.default_rng(7)
    observations = shared_views(ring, rng, floor=False)
    for k, (x, y, turn) in enumerate([(-0.4, 0.3, 0.0), (1.0, -0.8, 40.0), (-1.2, -1.0, 100.0)]):
        R = Rotation.from_euler("z", turn, degrees=True).as_matrix() @ np.diag([1.0, -1, -1])
        for camera in ring:
            observations[camera.name][f"floor{k}"] = seen(camera, R, np.array([x, y, 0.0]), rng)
    result = calibrate_rig(lenses_of(ring, rng), observations, BOARD.object_points,
                           floor=["floor0", "floor1", "floor2"])
    for got, want in zip(result.rig, ring, strict=True):
        np.testing.assert_allclose(got.centre, want.centre - [-0.4, 0.3, 0], atol=5e-3)
