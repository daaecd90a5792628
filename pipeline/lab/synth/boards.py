"""Board recordings for calibration: a printed board moved through a studio, as the rig's cameras see it.

What ``python -m pipeline calibrate`` reads (docs/calibration.md)::

    <boards>/intrinsics/<camera>/<view:03d>.png   the board moved in front of one camera
    <boards>/extrinsics/<camera>/<view:03d>.png   one board pose per view, seen at once by every camera
    <boards>/extrinsics/<camera>/floor.png        the board laid flat on the floor (optional; floor1.png ... more)
    <boards>/groundtruth/calibration.toml         the true rig (anipose), for scoring only
    <boards>/groundtruth/boards.json              the board, its poses, how the recording was made

Every view is ray-traced through the lens (``pipeline.lab.synth.render``'s studio: room, lights, exposure,
vignetting, blur, tone curve, sensor noise): each pixel averages :data:`SUPERSAMPLING` ² rays, whose
normalised image coordinates are interpolated from the camera's per-pixel undistortion, so the board's edges
are anti-aliased and bent by the lens distortion exactly as the camera model says. The board is the printed
pattern of :func:`calib.board.board_image` on a white card; its back is grey card.

Poses: for the intrinsics, the board fills 35-75 % of the image width at positions spread over the image,
tilted by up to 50 degrees, so that every camera's focal length, principal point and distortion are seen.
For the extrinsics the board stands in the middle of the ring at 0.5-1.9 m and faces a point between two
neighbouring cameras (the ring sorted by azimuth), so each pose is seen by two or three cameras and only
the chain of overlaps links the far side of the ring; the far cameras see it small.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from calib.board import Board, board_image
from calib.camera import Camera, Rig
from calib.formats import save_rig
from pipeline.lab.synth.render import Room, finish_image, irradiance, meter_exposure, render_room, srgb_to_linear

#: Rays per pixel along each axis on the board.
SUPERSAMPLING = 4
#: Texture resolution of the printed pattern.
TEXTURE_PX_PER_SQUARE = 96
#: White card around the pattern, in squares (OpenCV's detectors need a light border).
CARD_MARGIN_SQUARES = 0.75
#: sRGB albedo of the ink, the paper and the card's back.
INK, PAPER, BACK = 0.05, 0.85, 0.45
#: A camera sees a pose of the extrinsics only at incidence angles below this (degrees from the board's normal).
MAX_INCIDENCE_DEG = 72.0
#: Board corners must lie this far inside the image (pixels) for a checkerboard view to count.
IMAGE_MARGIN_PX = 4.0
FLOOR_VIEW = "floor"


@dataclass(frozen=True)
class BoardPose:
    """Where the board is: ``X_world = R @ X_board + t`` (board frame of :mod:`calib.board`)."""

    R: np.ndarray
    t: np.ndarray

    def to_dict(self) -> dict:
        return {"R": self.R.tolist(), "t": self.t.tolist()}


@dataclass(frozen=True, eq=False)
class CameraView:
    """Per-camera data reused for every view: normalised coordinates of each pixel, clean plate, exposure."""

    camera: Camera
    xy: np.ndarray  # (H, W, 2) float32 undistorted normalised coordinates of the pixel centres
    plate: np.ndarray  # (H, W, 3) linear radiance of the empty room
    exposure: object


def camera_view(camera: Camera, room: Room) -> CameraView:
    """The camera's per-pixel geometry, its clean plate and its metered exposure."""
    width, height = camera.size
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    xy = camera.undistort_pixels(np.column_stack([u.ravel(), v.ravel()])).reshape(height, width, 2)
    rays = np.concatenate([xy, np.ones((height, width, 1))], axis=2) @ camera.R  # rows of R^T d
    rays /= np.linalg.norm(rays, axis=2, keepdims=True)
    plate = render_room(camera, rays.astype(np.float32), room)
    return CameraView(camera, xy.astype(np.float32), plate, meter_exposure(camera, plate))



def _card_geometry(board: Board) -> tuple[np.ndarray, np.ndarray]:
    """(origin (2,), size (2,)) of the white card in the board frame, metres: the pattern and its margin."""
    margin = CARD_MARGIN_SQUARES * board.square_m
    return board.pattern_origin_m - margin, np.asarray(board.extent_m) + 2 * margin


def board_texture(board: Board) -> np.ndarray:
    """(H, W) float32 linear albedo of the card: the printed pattern (ink on paper) with its margin."""
    printed = board_image(board, TEXTURE_PX_PER_SQUARE, margin_squares=CARD_MARGIN_SQUARES).astype(np.float32) / 255
    return srgb_to_linear(INK + (PAPER - INK) * printed).astype(np.float32)


def render_view(view: CameraView, board: Board, texture: np.ndarray, pose: BoardPose | None, *,
                noise_sigma: float, rng: np.random.Generator) -> np.ndarray:
    """(H, W, 3) uint8 BGR image of the studio with the board at ``pose`` (None: the empty studio)."""
    radiance = view.plate.copy()
    if pose is not None:
        _paint_board(radiance, view, board, texture, pose)
    return finish_image(radiance, view.exposure, noise_sigma, rng)


def _paint_board(radiance: np.ndarray, view: CameraView, board: Board, texture: np.ndarray, pose: BoardPose) -> None:
    """Replace the pixels of ``radiance`` (H, W, 3) covered by the board card with its shaded, anti-aliased image."""
    camera = view.camera
    R_cb, t_cb = camera.R @ pose.R, camera.R @ pose.t + camera.t  # board -> camera
    origin, size = _card_geometry(board)
    edge, zeros, ones = np.linspace(0.0, 1.0, 17), np.zeros(17), np.ones(17)
    outline = np.concatenate([np.column_stack(pair) for pair in ((edge, zeros), (edge, ones), (zeros, edge),
                                                                  (ones, edge))])  # the card's four sides, unit square
    outline = np.column_stack([origin + outline * size, np.zeros(len(outline))]) @ pose.R.T + pose.t
    if np.any(camera.depth(outline) < 0.05):  # the card reaches behind the camera: not a view anyone records
        return
    uv = camera.project(outline)
    width, height = camera.size
    u0, v0 = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 2, 0)
    u1, v1 = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 2, [width - 1, height - 1])
    if u1 < u0 or v1 < v0:
        return
    s = SUPERSAMPLING
    offsets = (np.arange(s) + 0.5) / s - 0.5
    map_u = (np.arange(u0, u1 + 1)[:, None] + offsets).ravel().astype(np.float32)
    map_v = (np.arange(v0, v1 + 1)[:, None] + offsets).ravel().astype(np.float32)
    map_u, map_v = np.meshgrid(map_u, map_v)
    xy = cv2.remap(view.xy, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)  # (h s, w s, 2)
    d = np.concatenate([xy, np.ones(xy.shape[:2] + (1,), np.float32)], axis=2).astype(np.float64)
    normal = R_cb[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = (normal @ t_cb) / (d @ normal)  # ray parameter to the board's plane
    X_b = (depth[..., None] * d - t_cb) @ R_cb  # board-frame hit points
    card = X_b[..., :2] - origin
    inside = (depth > 0) & np.all((card >= 0) & (card < size), axis=2)
    front = (-R_cb.T @ t_cb)[2] < 0  # the camera is on the printed side
    if front:
        scale = TEXTURE_PX_PER_SQUARE / board.square_m
        albedo = cv2.remap(texture, (card[..., 0] * scale - 0.5).astype(np.float32),
                           (card[..., 1] * scale - 0.5).astype(np.float32), cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REPLICATE)
    else:
        albedo = np.full(inside.shape, srgb_to_linear(BACK), np.float32)
    facing_normal = -pose.R[:, 2] if front else pose.R[:, 2]
    light = float(irradiance(facing_normal[None])[0])
    background = np.repeat(np.repeat(radiance[v0 : v1 + 1, u0 : u1 + 1], s, axis=0), s, axis=1)
    samples = np.where(inside[..., None], (albedo * light)[..., None], background)
    h, w = v1 - v0 + 1, u1 - u0 + 1
    radiance[v0 : v1 + 1, u0 : u1 + 1] = samples.reshape(h, s, w, s, 3).mean(axis=(1, 3))


def _corners_in_image(camera: Camera, board: Board, pose: BoardPose) -> bool:
    """Whether every board corner is in front of ``camera`` and at least :data:`IMAGE_MARGIN_PX` inside its image."""
    corners = board.object_points @ pose.R.T + pose.t
    if np.any(camera.depth(corners) <= 0):
        return False
    uv = camera.project(corners)
    width, height = camera.size
    return bool(np.all((uv >= IMAGE_MARGIN_PX) & (uv <= np.array([width, height]) - 1 - IMAGE_MARGIN_PX)))


def _board_centre(board: Board) -> np.ndarray:
    return board.object_points.mean(axis=0)


def intrinsic_poses(camera: Camera, board: Board, count: int, rng: np.random.Generator) -> list[BoardPose]:
    """``count`` poses of the board in front of ``camera``, all corners in view, spread over a 3 x 3 grid of
    image positions, 35-75 % of the image wide, tilted by 10-50 degrees about a random axis, rolled by up to
    25 degrees."""
    width, height = camera.size
    cells = [(cx, cy) for cy in (0.25, 0.5, 0.75) for cx in (0.25, 0.5, 0.75)]
    rng.shuffle(cells)
    centre = _board_centre(board)
    poses: list[BoardPose] = []
    for _attempt in range(200 * count):
        if len(poses) == count:
            break
        cx, cy = cells[len(poses) % len(cells)]
        target = np.array([cx * width, cy * height]) + rng.uniform(-0.12, 0.12, 2) * [width, height]
        depth = camera.K[0, 0] * board.extent_m[0] / (rng.uniform(0.35, 0.75) * width)
        xy = camera.undistort_pixels(target[None])[0]
        axis_angle = rng.uniform(0, 2 * np.pi)
        tilt = np.radians(rng.uniform(10, 50)) * np.array([np.cos(axis_angle), np.sin(axis_angle), 0.0])
        R_cb = Rotation.from_rotvec(tilt).as_matrix() @ Rotation.from_euler("z", rng.uniform(-25, 25),
                                                                            degrees=True).as_matrix()
        t_cb = depth * np.array([xy[0], xy[1], 1.0]) - R_cb @ centre
        pose = BoardPose(camera.R.T @ R_cb, camera.R.T @ (t_cb - camera.t))
        if _corners_in_image(camera, board, pose):
            poses.append(pose)
    if len(poses) < count:
        raise ValueError(f"camera {camera.name}: could not place {count} board poses in view "
                         f"(board {board.describe()} too large for the lens?)")
    return poses


def rig_centre(rig: Rig) -> np.ndarray:
    """(3,) the point closest (least squares) to every camera's optical axis: where the ring looks."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for camera in rig:
        axis = camera.R[2]
        projector = np.eye(3) - np.outer(axis, axis)
        A += projector
        b += projector @ camera.centre
    return np.linalg.solve(A, b)


def sees(camera: Camera, board: Board, pose: BoardPose) -> bool:
    """Whether ``camera`` sees the printed side of the board at ``pose`` at an incidence below
    :data:`MAX_INCIDENCE_DEG`, every corner in its image."""
    centre = pose.R @ _board_centre(board) + pose.t
    towards = camera.centre - centre
    cosine = (-pose.R[:, 2]) @ towards / np.linalg.norm(towards)
    return cosine > np.cos(np.radians(MAX_INCIDENCE_DEG)) and _corners_in_image(camera, board, pose)


def extrinsic_poses(rig: Rig, board: Board, count: int, rng: np.random.Generator, *,
                    radius_m: float = 1.0) -> list[BoardPose]:
    """``count`` board poses in the middle of the ring, each seen (:func:`sees`) by at least two cameras.

    The board stands within ``radius_m`` of the point below :func:`rig_centre`, 0.5-1.9 m high, and faces a
    point between two neighbouring cameras of the ring (sorted by azimuth), rolled by up to 30 degrees.
    """
    middle = rig_centre(rig)
    azimuths = np.arctan2(*(rig.centres[:, :2] - middle[:2]).T[::-1])
    ring = [rig[int(k)] for k in np.argsort(azimuths)]
    centre = _board_centre(board)
    up = np.array([0.0, 0.0, 1.0])
    poses: list[BoardPose] = []
    for _attempt in range(500 * count):
        if len(poses) == count:
            break
        angle, distance = rng.uniform(0, 2 * np.pi), radius_m * np.sqrt(rng.uniform())
        position = np.array([*(middle[:2] + distance * np.array([np.cos(angle), np.sin(angle)])),
                             rng.uniform(0.5, 1.9)])
        k = int(rng.integers(len(ring)))
        first, second = ring[k].centre - position, ring[(k + 1) % len(ring)].centre - position
        blend = rng.uniform(-0.25, 1.25)
        facing = (1 - blend) * first / np.linalg.norm(first) + blend * second / np.linalg.norm(second)
        facing /= np.linalg.norm(facing)
        z_axis = -facing
        x_axis = np.cross(z_axis, up)
        x_axis /= np.linalg.norm(x_axis)
        upright = np.column_stack([x_axis, np.cross(z_axis, x_axis), z_axis])
        R = upright @ Rotation.from_euler("z", rng.uniform(-30, 30), degrees=True).as_matrix()
        pose = BoardPose(R, position - R @ centre)
        if sum(sees(camera, board, pose) for camera in rig) >= 2:
            poses.append(pose)
    if len(poses) < count:
        raise ValueError(f"could not place {count} board poses seen by two cameras of the rig")
    return poses


#: The board laid on the floor with its frame on the world's: origin at the world origin, x along +x, the
#: printed side up (board y along -y, board z down into the floor). Calibrated from it, the world is the true one.
FLOOR_POSE = BoardPose(np.diag([1.0, -1.0, -1.0]), np.zeros(3))


def floor_poses(rig: Rig, count: int) -> dict[str, BoardPose]:
    """``count`` views of the board flat on the floor: ``floor`` is :data:`FLOOR_POSE`; ``floor1``, ``floor2``, ...
    lie turned on a circle of 1.2 m around the point below :func:`rig_centre` (more of the floor, seen by more
    cameras, pins its plane down better)."""
    middle = rig_centre(rig)
    poses = {FLOOR_VIEW: FLOOR_POSE}
    for k in range(1, count):
        angle = 2 * np.pi * (k - 1) / max(count - 1, 1)
        turn = Rotation.from_euler("z", np.degrees(angle) + 30, degrees=True).as_matrix()
        position = np.array([*(middle[:2] + 1.2 * np.array([np.cos(angle), np.sin(angle)])), 0.0])
        poses[f"{FLOOR_VIEW}{k}"] = BoardPose(turn @ FLOOR_POSE.R, position)
    return poses


def studio_room(rig: Rig, seed: int) -> Room:
    """A room around the rig: the cameras 0.8 m inside its walls, the ceiling above the highest."""
    centres = rig.centres
    middle = (centres[:, :2].min(axis=0) + centres[:, :2].max(axis=0)) / 2
    half = np.abs(centres[:, :2] - middle).max(axis=0) + 0.8
    return Room(centre=(float(middle[0]), float(middle[1])), half_size=(float(half[0]), float(half[1])),
                height=max(3.2, float(centres[:, 2].max()) + 0.5), seed=seed)


def write_board_recording(rig: Rig, board: Board, out: Path, *, intrinsic_views: int, extrinsic_views: int,
                          floor_views: int = 1, noise_sigma: float = 2.0, seed: int = 0,
                          cameras_for_intrinsics: list[str] | None = None) -> None:
    """Render a ``BOARDS`` folder (module docstring) for ``rig`` into ``out`` (created; must not exist).

    ``floor_views``: views of the board on the floor (:func:`floor_poses`; 0 for none);
    ``cameras_for_intrinsics``: the cameras that get an ``intrinsics/`` folder (default all).
    """
    out = Path(out)
    out.mkdir(parents=True)
    pose_rng, noise_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2))
    room = studio_room(rig, seed)
    texture = board_texture(board)
    views = {camera.name: camera_view(camera, room) for camera in rig}
    record: dict = {"board": board.describe(), "seed": seed, "noise_sigma": noise_sigma, "intrinsics": {}}
    for name in cameras_for_intrinsics if cameras_for_intrinsics is not None else rig.names:
        poses = intrinsic_poses(rig[name], board, intrinsic_views, pose_rng)
        folder = out / "intrinsics" / name
        folder.mkdir(parents=True)
        for index, pose in enumerate(poses):
            image = render_view(views[name], board, texture, pose, noise_sigma=noise_sigma, rng=noise_rng)
            cv2.imwrite(str(folder / f"{index:03d}.png"), image)
        record["intrinsics"][name] = [pose.to_dict() for pose in poses]
    shared = extrinsic_poses(rig, board, extrinsic_views, pose_rng) if extrinsic_views else []
    poses = {f"{index:03d}": pose for index, pose in enumerate(shared)}
    poses |= floor_poses(rig, floor_views) if floor_views else {}
    for camera in rig if poses else ():
        folder = out / "extrinsics" / camera.name
        folder.mkdir(parents=True)
        for key, pose in poses.items():
            image = render_view(views[camera.name], board, texture, pose, noise_sigma=noise_sigma, rng=noise_rng)
            cv2.imwrite(str(folder / f"{key}.png"), image)
    record["extrinsics"] = {key: pose.to_dict() for key, pose in poses.items()}
    record["seen_by"] = {key: [camera.name for camera in rig if sees(camera, board, pose)]
                         for key, pose in poses.items()}
    (out / "groundtruth").mkdir()
    save_rig(rig, "anipose", out / "groundtruth" / "calibration.toml")
    (out / "groundtruth" / "boards.json").write_text(json.dumps(record, indent=1) + "\n")
