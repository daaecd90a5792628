"""Calibrating a rig from board views: each camera's lens, then every camera's pose by a joint bundle adjustment.

1. **Intrinsics**, per camera (:func:`calibrate_intrinsics`): OpenCV's ``calibrateCamera`` (Zhang's method:
   homographies, then Levenberg-Marquardt on every view's reprojection) on that camera's board views; views
   whose reprojection error stands out (a corner detected on the wrong saddle, a blurred frame) are dropped and
   the camera calibrated again.
2. **Extrinsics** (:func:`calibrate_rig`): the board's pose in every camera that found it (``solvePnPGeneric``
   with IPPE, which returns both poses a planar target allows); for each pair of cameras sharing views, the
   relative pose that best transfers the board from one to the other over all their shared views; the overlap
   graph's maximum spanning tree (edges weighted by the shared views the relative pose explains) chains the
   cameras from the best-connected one; each board pose starts from the camera whose estimate reprojects best
   into all cameras that saw it. Then a joint bundle adjustment of every camera pose and board pose
   (``scipy.optimize.least_squares``, a sparse Jacobian: each corner depends on one camera and one board pose,
   a robust loss against stray corners), observations that still stand out dropped and the adjustment run
   again. Intrinsics stay fixed: the close views of step 1 determine them better than the far views of a rig.
3. **World**: the board lying on the floor, in one view or several (the board laid at several places), puts z = 0
   on the floor (the plane through all their corners) with +z up (out of the printed side), the origin below the
   first floor view's board origin and +x along its x axis; else the world is the first camera's frame.

Everything here works on arrays and :class:`calib.board.Detection` objects; reading images is the caller's.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.optimize
import scipy.sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation

from calib.board import Detection
from calib.camera import Camera, Rig
from calib.errors import InputError

#: Distortion models: name -> ``calibrateCamera`` flags. The names list the coefficients estimated.
DISTORTION_MODELS = {
    "none": cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "k1": cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "k1k2": cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "k1k2p1p2": cv2.CALIB_FIX_K3,
    "k1k2p1p2k3": 0,
}
#: Fewest views a camera's intrinsics are computed from (a focal length needs two tilted views; three leave
#: one to spare for a view dropped as an outlier).
MIN_INTRINSIC_VIEWS = 3
#: A view is an outlier when its reprojection RMS exceeds this multiple of the camera's median view ...
OUTLIER_RATIO = 3.0
#: ... and this many pixels (below it nothing is wrong, however the views compare).
OUTLIER_FLOOR_PX = 0.5
#: Rounds of dropping outliers and calibrating again.
OUTLIER_ROUNDS = 3
#: Robust loss scale of the bundle adjustment (pixels): corners off by more count less than quadratically.
BA_LOSS_SCALE_PX = 1.0
#: Shared views tried as the hypothesis of a pair's relative pose (each is scored on all shared views).
MAX_HYPOTHESES = 20
#: A camera's intrinsics are called weak when their focal length's standard deviation exceeds this share.
WEAK_FOCAL_SHARE = 0.01


@dataclass(frozen=True, eq=False)
class Intrinsics:
    """One camera's lens: what :func:`calibrate_intrinsics` found.

    Attributes
    ----------
    K : (3, 3) float
    dist : (5,) float
        OpenCV ``(k1, k2, p1, p2, k3)``.
    size : (int, int)
        Image (width, height).
    views : tuple of str
        The views used.
    dropped : tuple of str
        Views dropped as outliers.
    rms_px : float
        Reprojection RMS over the corners of the views used.
    view_rms_px : dict
        View -> its reprojection RMS (dropped views included, from the calibration that dropped them).
    focal_std_px : float
        Standard deviation of fx from ``calibrateCameraExtended``: large when the views do not tilt enough.
    """

    K: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]
    views: tuple[str, ...]
    dropped: tuple[str, ...]
    rms_px: float
    view_rms_px: dict[str, float]
    focal_std_px: float

    @property
    def weak(self) -> bool:
        """Whether the focal length is poorly determined by the views (they are too nearly parallel)."""
        return self.focal_std_px > WEAK_FOCAL_SHARE * self.K[0, 0]


def calibrate_intrinsics(object_points: np.ndarray, detections: Mapping[str, Detection], size: tuple[int, int], *,
                         camera: str, distortion: str = "k1k2") -> Intrinsics:
    """The lens of one camera from its board views.

    Parameters
    ----------
    object_points : (N, 3) float
        Board corners in the board frame (:attr:`calib.board.Board.object_points`).
    detections : mapping of view name -> Detection
        The views where the board was found.
    size : (int, int)
        Image (width, height).
    camera : str
        The camera's name, for messages.
    distortion : str
        A key of :data:`DISTORTION_MODELS`.

    Raises
    ------
    InputError
        Fewer than :data:`MIN_INTRINSIC_VIEWS` views, before or after dropping outliers.
    """
    if distortion not in DISTORTION_MODELS:
        raise InputError(f"--distortion {distortion!r}: expected one of {', '.join(DISTORTION_MODELS)}")
    views = list(detections)
    if len(views) < MIN_INTRINSIC_VIEWS:
        raise InputError(f"camera {camera!r}: the board was found in {len(views)} view(s), expected at least "
                         f"{MIN_INTRINSIC_VIEWS} for its intrinsics (more views, tilted differently, help)")
    dropped: list[str] = []
    view_rms: dict[str, float] = {}
    for _ in range(OUTLIER_ROUNDS):
        rms, K, dist, per_view, focal_std = _calibrate_camera(object_points, [detections[v] for v in views], size,
                                                              DISTORTION_MODELS[distortion])
        view_rms.update(zip(views, per_view, strict=True))
        limit = max(OUTLIER_RATIO * float(np.median(per_view)), OUTLIER_FLOOR_PX)
        outliers = [view for view, error in zip(views, per_view, strict=True) if error > limit]
        if not outliers or len(views) - len(outliers) < MIN_INTRINSIC_VIEWS:
            break
        dropped += outliers
        views = [view for view in views if view not in outliers]
    return Intrinsics(K, dist, tuple(size), tuple(views), tuple(dropped), rms, view_rms, focal_std)


def _calibrate_camera(object_points: np.ndarray, detections: list[Detection], size: tuple[int, int], flags: int):
    """``calibrateCameraExtended`` on the detections: (rms, K, dist (5,), per-view RMS (V,), std of fx)."""
    objects = [object_points[d.ids].astype(np.float32) for d in detections]
    images = [d.corners.astype(np.float32).reshape(-1, 1, 2) for d in detections]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    rms, K, dist, _, _, std_intrinsics, _, per_view = cv2.calibrateCameraExtended(
        objects, images, tuple(size), None, None, flags=flags, criteria=criteria)
    dist = np.zeros(5) if dist is None else np.concatenate([dist.ravel()[:5], np.zeros(5)])[:5]
    return float(rms), K, dist, per_view.ravel().astype(float), float(std_intrinsics.ravel()[0])


# ---------------------------------------------------------------------------------------------
# Poses


def _rt_matrix(rvec, tvec) -> np.ndarray:
    """(4, 4) homogeneous transform of a Rodrigues vector and a translation."""
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3))[0]
    T[:3, 3] = np.asarray(tvec, dtype=np.float64).reshape(3)
    return T


def _project(T: np.ndarray, points: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(N, 2) pixels of ``points`` (N, 3) moved by ``T`` (4, 4) into a camera (K, dist)."""
    rvec = cv2.Rodrigues(T[:3, :3])[0]
    uv, _ = cv2.projectPoints(points.reshape(-1, 1, 3), rvec, T[:3, 3], K, dist)
    return uv.reshape(-1, 2)


def _rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def board_poses(object_points: np.ndarray, detection: Detection, K: np.ndarray, dist: np.ndarray) -> list[np.ndarray]:
    """Candidate (4, 4) camera-from-board transforms of one view, best first.

    A planar board's pose is ambiguous when it is small in the image: IPPE returns both solutions (the board
    tilted either way); each is refined by Levenberg-Marquardt. The second is kept when it reprojects within
    twice the first's error, for the multi-camera steps to choose from.
    """
    objects = object_points[detection.ids]
    count, rvecs, tvecs, errors = cv2.solvePnPGeneric(objects, detection.corners, K, dist, flags=cv2.SOLVEPNP_IPPE)
    candidates = []
    for rvec, tvec in zip(rvecs[:count], tvecs[:count], strict=True):
        rvec, tvec = cv2.solvePnPRefineLM(objects, detection.corners, K, dist, rvec.copy(), tvec.copy())
        T = _rt_matrix(rvec, tvec)
        candidates.append((_rms(_project(T, objects, K, dist), detection.corners), T))
    candidates.sort(key=lambda pair: pair[0])
    best = candidates[0][0]
    return [T for error, T in candidates if error <= 2 * best + 1e-9]


@dataclass(frozen=True, eq=False)
class RigCalibration:
    """What :func:`calibrate_rig` found.

    Attributes
    ----------
    rig : Rig
        Cameras in the world frame (the floor board's, or the first camera's when ``floor`` is None).
    floor : tuple of str
        The views that set the floor; empty when the world is the first camera's frame.
    rms_px : float
        Reprojection RMS over every corner used by the bundle adjustment.
    camera_rms_px : dict
        Camera name -> its RMS after the adjustment.
    camera_views : dict
        Camera name -> views of it used.
    dropped : tuple of (camera, view)
        Observations dropped as outliers.
    views : int
        Board poses adjusted.
    chain : tuple of (camera, camera, int)
        The spanning tree's edges: cameras and the shared views behind each.
    """

    rig: Rig
    floor: tuple[str, ...]
    rms_px: float
    camera_rms_px: dict[str, float]
    camera_views: dict[str, int]
    dropped: tuple[tuple[str, str], ...]
    views: int
    chain: tuple[tuple[str, str, int], ...] = field(default=())


def calibrate_rig(intrinsics: Mapping[str, Intrinsics], observations: Mapping[str, Mapping[str, Detection]],
                  object_points: np.ndarray, *, floor: Sequence[str] = ()) -> RigCalibration:
    """Every camera's pose from synchronised board views, by chaining and a joint bundle adjustment.

    Parameters
    ----------
    intrinsics : mapping of camera name -> Intrinsics
        The rig's cameras, in rig order.
    observations : mapping of camera name -> (mapping of view name -> Detection)
        The views in which each camera found the board; views with the same name show the same board pose.
    object_points : (N, 3) float
        Board corners in the board frame.
    floor : sequence of str
        Views in which the board lies flat on the floor: they set the world frame.

    Raises
    ------
    InputError
        A camera that found the board in no view, cameras that share no view with the others (naming them), a
        floor view that no camera found.
    """
    names = list(intrinsics)
    missing = [name for name in names if not observations.get(name)]
    if missing:
        raise InputError(f"camera {missing[0]!r}: the board was found in none of its extrinsics views, expected it "
                         "in views shared with other cameras")
    found = tuple(view for view in floor if any(view in observations[name] for name in names))
    if floor and not found:
        raise InputError(f"--floor {','.join(floor)}: no camera found the board in these views, expected it in at "
                         "least one camera (a board on the floor is seen at a grazing angle: larger squares help)")
    floor = found  # a floor view no camera found is left out (RigCalibration.floor lists those used)
    candidates = {(name, view): board_poses(object_points, detection, intrinsics[name].K, intrinsics[name].dist)
                  for name in names for view, detection in observations[name].items()}
    support, relative = _pairwise(names, intrinsics, observations, candidates, object_points)
    _check_connected(names, support)
    root, chain, camera_from_root = _chain(names, support, relative)
    views = sorted({view for name in names for view in observations[name]
                    if view in floor or sum(view in observations[other] for other in names) >= 2})
    root_from_board = {view: _initial_board_pose(view, names, intrinsics, observations, candidates,
                                                 camera_from_root, object_points) for view in views}
    problem = _Problem(names, root, intrinsics, observations, object_points, views)
    camera_from_root, root_from_board, dropped = problem.solve(camera_from_root, root_from_board)
    residuals = problem.residuals_by_observation(camera_from_root, root_from_board, exclude=dropped)
    lost = [name for name in names if not any(camera == name for camera, _ in residuals)]
    if lost:
        raise InputError(f"camera {lost[0]!r}: none of its board views agrees with the rest of the rig (all dropped "
                         "as outliers); expected views of the same board poses as the other cameras")
    world = (_floor_frame([root_from_board[view] for view in floor], object_points) if floor
             else camera_from_root[names[0]])
    cameras = []
    for name in names:
        T = camera_from_root[name] @ np.linalg.inv(world)  # camera from world
        lens = intrinsics[name]
        cameras.append(Camera(name, lens.K, lens.dist, _orthonormal(T[:3, :3]), T[:3, 3], lens.size))
    all_errors = np.concatenate([errors for errors in residuals.values()])
    camera_rms = {name: float(np.sqrt(np.mean(np.concatenate(
        [errors for (camera, _), errors in residuals.items() if camera == name]) ** 2))) for name in names}
    camera_views = {name: sum(camera == name for camera, _ in residuals) for name in names}
    return RigCalibration(Rig(tuple(cameras)), floor, float(np.sqrt(np.mean(all_errors**2))), camera_rms,
                          camera_views, tuple(sorted(dropped)), len(views), chain)


def _orthonormal(R: np.ndarray) -> np.ndarray:
    """The rotation nearest to ``R`` (removes the rounding a chain of products leaves)."""
    U, _, Vt = np.linalg.svd(R)
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


def _pairwise(names, intrinsics, observations, candidates, object_points):
    """For every pair of cameras sharing views: the relative pose (b from a) that best transfers the board from
    a to b over their shared views, and how many shared views it explains (transfer RMS within
    :func:`_transfer_limit`)."""
    support: dict[tuple[str, str], int] = {}
    relative: dict[tuple[str, str], np.ndarray] = {}
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            shared = sorted(set(observations[a]) & set(observations[b]))
            if not shared:
                continue
            best = None
            for view in shared[:: max(1, len(shared) // MAX_HYPOTHESES)]:
                for T_a in candidates[(a, view)]:
                    for T_b in candidates[(b, view)]:
                        T_ba = T_b @ np.linalg.inv(T_a)
                        errors = [_rms(_project(T_ba @ candidates[(a, w)][0], object_points[observations[b][w].ids],
                                                intrinsics[b].K, intrinsics[b].dist), observations[b][w].corners)
                                  for w in shared]
                        explained = sum(error < _transfer_limit(observations[b][w]) for error, w in
                                        zip(errors, shared, strict=True))
                        score = (explained, -float(np.median(errors)))
                        if best is None or score > best[0]:
                            best = (score, T_ba)
            if best[0][0] > 0:
                support[(a, b)] = support[(b, a)] = best[0][0]
                relative[(a, b)], relative[(b, a)] = best[1], np.linalg.inv(best[1])
    return support, relative


def _transfer_limit(detection: Detection) -> float:
    """Pixels within which a board transferred from another camera counts as explained: 5 % of the board's
    extent in this image (a fixed number of pixels would be too strict for a large board, too lax for a small)."""
    extent = np.ptp(detection.corners, axis=0).max()
    return max(2.0, 0.05 * float(extent))


def _check_connected(names: list[str], support: dict) -> None:
    """InputError naming the cameras cut off from the others: the board must link every camera to the rig."""
    index = {name: k for k, name in enumerate(names)}
    rows = [index[a] for a, _ in support]
    cols = [index[b] for _, b in support]
    graph = scipy.sparse.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(names), len(names)))
    count, labels = connected_components(graph, directed=False)
    if count == 1:
        return
    groups = [[name for name in names if labels[index[name]] == label] for label in range(count)]
    groups.sort(key=len, reverse=True)
    lonely = [group for group in groups[1:] if len(group) == 1]
    if len(groups) == 2 and lonely:
        raise InputError(f"camera {lonely[0][0]!r} shares no board view with the other cameras (a view counts when "
                         "the board is found in both images, same file name or frame); expected views of the board "
                         f"seen by {lonely[0][0]} together with one of {', '.join(groups[0])}")
    described = "; ".join(", ".join(group) for group in groups)
    raise InputError(f"the cameras fall into {count} groups that share no board view: {described} (a view counts when "
                     "the board is found in both images); expected views linking every group to the others")


def _chain(names: list[str], support: dict, relative: dict):
    """Root camera, spanning-tree edges and every camera's pose relative to the root, by Prim's algorithm on
    the overlap graph (the edge explaining the most shared views first)."""
    totals = {name: sum(count for (a, _), count in support.items() if a == name) for name in names}
    root = max(names, key=lambda name: (totals[name], -names.index(name)))
    camera_from_root = {root: np.eye(4)}
    chain = []
    while len(camera_from_root) < len(names):
        a, b = max(((a, b) for (a, b) in support if a in camera_from_root and b not in camera_from_root),
                   key=lambda edge: (support[edge], -names.index(edge[1])))
        camera_from_root[b] = relative[(a, b)] @ camera_from_root[a]
        chain.append((a, b, support[(a, b)]))
    return root, tuple(chain), camera_from_root


def _initial_board_pose(view, names, intrinsics, observations, candidates, camera_from_root, object_points):
    """(4, 4) root-from-board pose of ``view``: of every camera's candidate poses, the one reprojecting best
    (summed RMS) into all the cameras that found the board in this view."""
    seen = [name for name in names if view in observations[name]]
    best = None
    for name in seen:
        for T_cb in candidates[(name, view)]:
            root_from_board = np.linalg.inv(camera_from_root[name]) @ T_cb
            error = sum(_rms(_project(camera_from_root[other] @ root_from_board,
                                      object_points[observations[other][view].ids], intrinsics[other].K,
                                      intrinsics[other].dist), observations[other][view].corners) for other in seen)
            if best is None or error < best[0]:
                best = (error, root_from_board)
    return best[1]


def _floor_frame(root_from_floors: list[np.ndarray], object_points: np.ndarray) -> np.ndarray:
    """(4, 4) world-from-root of the floor: z = 0 on the least-squares plane through the corners of every floor
    view (each (4, 4) root-from-board), +z out of the printed side, the origin below the first view's board origin,
    +x along its x axis. For one view this is the board's own frame turned up (its y and z negated)."""
    corners = np.concatenate([object_points @ T[:3, :3].T + T[:3, 3] for T in root_from_floors])
    centroid = corners.mean(axis=0)
    normal = np.linalg.svd(corners - centroid)[2][2]
    first = root_from_floors[0]
    if normal @ first[:3, 2] > 0:  # board z points into the floor: up is the other way
        normal = -normal
    x_axis = first[:3, 0] - (first[:3, 0] @ normal) * normal
    x_axis /= np.linalg.norm(x_axis)
    A = np.stack([x_axis, np.cross(normal, x_axis), normal])
    origin = first[:3, 3] - ((first[:3, 3] - centroid) @ normal) * normal
    world_from_root = np.eye(4)
    world_from_root[:3, :3], world_from_root[:3, 3] = A, -A @ origin
    return world_from_root


class _Problem:
    """The bundle adjustment: parameters, residuals and the Jacobian's sparsity.

    Parameters: a rotation vector and translation (camera from root) for each camera but the root, then a
    rotation vector and translation (root from board) for each view. Residuals: pixel differences of every
    observed corner, two per corner. An observation is one camera's detection in one view.
    """

    def __init__(self, names, root, intrinsics, observations, object_points, views):
        self.names, self.root, self.views = names, root, views
        self.free = [name for name in names if name != root]
        view_position = {view: k for k, view in enumerate(views)}
        self.keys: list[tuple[str, str]] = []
        camera_index, view_index, points, pixels, observation = [], [], [], [], []
        for c, name in enumerate(names):
            for view, detection in observations[name].items():
                if view not in view_position:
                    continue
                n = len(detection.ids)
                camera_index.append(np.full(n, c))
                view_index.append(np.full(n, view_position[view]))
                observation.append(np.full(n, len(self.keys)))
                points.append(object_points[detection.ids])
                pixels.append(detection.corners)
                self.keys.append((name, view))
        self.camera_index = np.concatenate(camera_index)  # (M,) per corner
        self.view_index = np.concatenate(view_index)
        self.observation = np.concatenate(observation)
        self.points = np.concatenate(points)  # (M, 3) board frame
        self.pixels = np.concatenate(pixels)  # (M, 2)
        self.K = np.array([intrinsics[name].K for name in names])
        self.dist = np.array([intrinsics[name].dist for name in names])
        self.free_position = np.full(len(names), -1)
        for k, name in enumerate(self.free):
            self.free_position[names.index(name)] = k

    def pack(self, camera_from_root: dict, root_from_board: dict) -> np.ndarray:
        transforms = [camera_from_root[name] for name in self.free] + [root_from_board[view] for view in self.views]
        return np.concatenate([np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])
                               for T in transforms])

    def unpack(self, x: np.ndarray) -> tuple[dict, dict]:
        transforms = []
        for block in x.reshape(-1, 6):
            T = np.eye(4)
            T[:3, :3] = Rotation.from_rotvec(block[:3]).as_matrix()
            T[:3, 3] = block[3:]
            transforms.append(T)
        camera_from_root = {self.root: np.eye(4)} | dict(zip(self.free, transforms[: len(self.free)], strict=True))
        return camera_from_root, dict(zip(self.views, transforms[len(self.free) :], strict=True))

    def _residual_vector(self, x: np.ndarray, keep: np.ndarray) -> np.ndarray:
        """(2 m,) pixel residuals of the kept corners (``keep`` (M,) bool), u and v alternating."""
        blocks = x.reshape(-1, 6)
        n_free = len(self.free)
        R_cam = np.repeat(np.eye(3)[None], len(self.names), axis=0)
        t_cam = np.zeros((len(self.names), 3))
        free = self.free_position >= 0
        if n_free:
            R_cam[free] = Rotation.from_rotvec(blocks[self.free_position[free], :3]).as_matrix()
            t_cam[free] = blocks[self.free_position[free], 3:]
        R_view = Rotation.from_rotvec(blocks[n_free:, :3]).as_matrix()
        t_view = blocks[n_free:, 3:]
        c, v = self.camera_index[keep], self.view_index[keep]
        X = np.einsum("nij,nj->ni", R_view[v], self.points[keep]) + t_view[v]
        X = np.einsum("nij,nj->ni", R_cam[c], X) + t_cam[c]
        x_n, y_n = X[:, 0] / X[:, 2], X[:, 1] / X[:, 2]
        k1, k2, p1, p2, k3 = self.dist[c].T
        r2 = x_n * x_n + y_n * y_n
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x_n * radial + 2.0 * p1 * x_n * y_n + p2 * (r2 + 2.0 * x_n * x_n)
        yd = y_n * radial + p1 * (r2 + 2.0 * y_n * y_n) + 2.0 * p2 * x_n * y_n
        K = self.K[c]
        u = K[:, 0, 0] * xd + K[:, 0, 1] * yd + K[:, 0, 2]
        w = K[:, 1, 1] * yd + K[:, 1, 2]
        return (np.column_stack([u, w]) - self.pixels[keep]).ravel()

    def _sparsity(self, keep: np.ndarray) -> scipy.sparse.csr_matrix:
        """Which parameters each residual depends on: its view's six and, unless it is the root, its camera's."""
        n_free = len(self.free)
        c, v = self.camera_index[keep], self.view_index[keep]
        free = self.free_position[c]
        rows, cols = [], []
        for axis in range(2):
            residual_rows = 2 * np.arange(len(c)) + axis
            for j in range(6):
                rows += [residual_rows, residual_rows[free >= 0]]
                cols += [6 * (n_free + v) + j, 6 * free[free >= 0] + j]
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        shape = (2 * len(c), 6 * (n_free + len(self.views)))
        return scipy.sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=shape)

    def solve(self, camera_from_root: dict, root_from_board: dict):
        """Adjust; drop the observations that still stand out (:data:`OUTLIER_RATIO`); adjust again."""
        x = self.pack(camera_from_root, root_from_board)
        dropped: set[int] = set()
        for _ in range(OUTLIER_ROUNDS):
            keep = ~np.isin(self.observation, list(dropped))
            result = scipy.optimize.least_squares(self._residual_vector, x, jac_sparsity=self._sparsity(keep),
                                                  args=(keep,), loss="soft_l1", f_scale=BA_LOSS_SCALE_PX,
                                                  x_scale="jac", method="trf", max_nfev=200)
            x = result.x
            rms = {k: float(np.sqrt(np.mean(errors**2)))
                   for k, errors in self._errors(x, dropped).items()}
            limit = max(OUTLIER_RATIO * float(np.median(list(rms.values()))), OUTLIER_FLOOR_PX)
            outliers = {k for k, error in rms.items() if error > limit}
            if not outliers:
                break
            dropped |= outliers
        camera_from_root, root_from_board = self.unpack(x)
        return camera_from_root, root_from_board, {self.keys[k] for k in dropped}

    def _errors(self, x: np.ndarray, dropped: set[int]) -> dict[int, np.ndarray]:
        """Observation index -> (n,) reprojection error of each of its corners, pixels (dropped ones left out)."""
        norms = np.linalg.norm(self._residual_vector(x, np.ones(len(self.observation), bool)).reshape(-1, 2), axis=1)
        order = np.argsort(self.observation, kind="stable")
        groups = np.split(norms[order], np.flatnonzero(np.diff(self.observation[order])) + 1)
        return {k: errors for k, errors in enumerate(groups) if k not in dropped}

    def residuals_by_observation(self, camera_from_root: dict, root_from_board: dict, *,
                                 exclude: set) -> dict[tuple[str, str], np.ndarray]:
        """(camera, view) -> (n,) reprojection error of each corner, pixels; ``exclude``d observations left out."""
        errors = self._errors(self.pack(camera_from_root, root_from_board), set())
        return {self.keys[k]: e for k, e in errors.items() if self.keys[k] not in exclude}
