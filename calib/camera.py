"""Calibrated pinhole cameras with OpenCV distortion, and rigs of named cameras.

Conventions (CAPTURE_FORMAT.md): a world point X (metres) maps to the camera frame as
``x_cam = R @ X + t``; the image point is ``K @ distort(x_cam / z_cam)`` with OpenCV's
distortion ``(k1, k2, p1, p2, k3)``; pixel ``(0, 0)`` is the *centre* of the top-left pixel,
so the image covers ``[-0.5, w - 0.5) x [-0.5, h - 0.5)``; image size is ``(width, height)``.

``K`` may carry skew ``s = K[0, 1]`` (``u = fx x_d + s y_d + cx``), as projection matrices decomposed
into K, R, t usually do. OpenCV's ``projectPoints`` and ``undistortPoints`` have no skew, so it is
applied as the affine map K after the distortion (the camera model of Bouguet's toolbox, where
``s = fx alpha_c``) and removed before OpenCV undistorts: with ``y_d = (v - cy) / fy`` the skew shifts
each row of pixels sideways by ``s y_d``, which :func:`_unskew` takes back exactly.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from calib.errors import InputError

# A stored rotation is accepted when R^T R and det(R) are this close to I and +1: loose enough for
# rotations written with double precision by any tool, tight enough to catch a transposed
# camera-to-world matrix or a reflection.
ROTATION_TOLERANCE = 1e-6

# cv2.undistortPoints stops iterating once the re-distorted point lies this close (pixels) to the
# observed one; the default (5 iterations) leaves errors of a tenth of a pixel at the corners of
# lenses with k1 = -0.2.
#: Points nearer than this to the camera's plane (metres) are not in its view (`Camera.sees`).
MIN_VIEW_DEPTH_M = 1e-3
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-10)


def _readonly(values, shape: tuple[int, ...], what: str) -> np.ndarray:
    """A read-only float64 copy of ``values``, which must have ``shape`` and be finite."""
    array = np.array(values, dtype=np.float64)
    if array.shape != shape:
        raise InputError(f"{what}: got shape {array.shape}, expected shape {shape}")
    if not np.all(np.isfinite(array)):
        raise InputError(f"{what}: contains NaN or infinity, expected finite numbers")
    array.flags.writeable = False
    return array


def _as_rows(values, width: int, what: str) -> np.ndarray:
    """``values`` as an ``(N, width)`` float64 array; a programming error if the shape differs."""
    array = np.asarray(values, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != width:
        raise ValueError(f"{what} must have shape (N, {width}), got {array.shape}")
    return array


def _is_positive_int(value) -> bool:
    """An integer (Python or numpy, not bool) above zero."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value > 0


def _distort(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """OpenCV's lens distortion of normalised image coordinates ``xy (N, 2)``.

    The model of ``cv2.projectPoints`` restricted to ``(k1, k2, p1, p2, k3)``:
    radial ``1 + k1 r^2 + k2 r^4 + k3 r^6`` plus tangential ``(p1, p2)`` terms.
    """
    # Python floats: on the few thousand points of a call, numpy's scalars cost more than the arithmetic
    # (the same double-precision products either way).
    k1, k2, p1, p2, k3 = dist.tolist()
    x, y = xy.T.copy()  # contiguous rows: the passes below run faster on them than on strided columns
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    distorted = np.empty_like(xy)  # filled column by column: np.stack's overhead is a tenth of the call
    distorted[:, 0] = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    distorted[:, 1] = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return distorted


def _distortion_derivative(xy: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The derivative of :func:`_distort` at ``xy (N, 2)``: the entries ``a, b, d`` (N,) each of the
    symmetric [[a, b], [b, d]] (the tangential terms keep it symmetric)."""
    k1, k2, p1, p2, k3 = dist
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    slope = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3))  # d radial / d(r2), twice
    a = radial + slope * x * x + 2.0 * p1 * y + 6.0 * p2 * x
    b = slope * x * y + 2.0 * p1 * x + 2.0 * p2 * y
    d = radial + slope * y * y + 6.0 * p1 * y + 2.0 * p2 * x
    return a, b, d


def _unskew(uv: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(uv' (N, 2), K' (3, 3))``: pixels ``uv`` of a camera with skew as the same camera without it sees them.

    ``u = fx x_d + s y_d + cx`` and ``v = fy y_d + cy``: the row ``v`` gives ``y_d`` alone, so
    ``u' = u - s (v - cy) / fy`` is the pixel of ``(x_d, y_d)`` under ``K'`` = ``K`` with ``s = 0``, exactly.
    """
    fy, cy = K[1, 1], K[1, 2]
    unskewed = uv.copy()
    unskewed[:, 0] -= K[0, 1] * (uv[:, 1] - cy) / fy
    K_plain = K.copy()
    K_plain[0, 1] = 0.0
    return unskewed, K_plain


@dataclass(frozen=True, eq=False)
class Camera:
    """One calibrated camera: ``x_cam = R @ X + t``, ``x_img ~ K @ distort(x_cam / z_cam)``.

    Parameters
    ----------
    name : str
        Camera name (COLMAP image stem, YAML/TOML camera name, video file stem).
    K : (3, 3) float
        Intrinsics ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` in pixels, pixel centres at integers;
        the skew ``s`` is usually 0.
    dist : (5,) float
        OpenCV distortion ``(k1, k2, p1, p2, k3)``.
    R : (3, 3) float
        World-to-camera rotation (proper: orthonormal, det +1).
    t : (3,) float
        World-to-camera translation, metres.
    size : (int, int)
        Image ``(width, height)`` in pixels.

    Arrays are stored as read-only float64 copies, so a camera can be shared safely. Equality is
    identity (arrays have no single truth value); compare fields with numpy when needed.
    """

    name: str
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    size: tuple[int, int]

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise InputError(f"camera name {self.name!r}: expected a non-empty string")
        what = f"camera {self.name!r}"
        K = _readonly(self.K, (3, 3), f"{what} K")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise InputError(f"{what} K: focal lengths must be positive, got ({K[0, 0]}, {K[1, 1]})")
        if K[1, 0] != 0 or np.any(K[2] != (0.0, 0.0, 1.0)):
            raise InputError(
                f"{what} K: expected upper triangular [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}"
            )
        dist = _readonly(self.dist, (5,), f"{what} dist (k1, k2, p1, p2, k3)")
        R = _readonly(self.R, (3, 3), f"{what} R")
        orthogonality = np.abs(R.T @ R - np.eye(3)).max()
        if orthogonality > ROTATION_TOLERANCE or abs(np.linalg.det(R) - 1.0) > ROTATION_TOLERANCE:
            raise InputError(
                f"{what} R: not a rotation matrix (|R^T R - I| = {orthogonality:.2g},"
                f" det = {np.linalg.det(R):.6g}), expected orthonormal with det +1"
            )
        t = _readonly(self.t, (3,), f"{what} t")
        size = tuple(self.size) if isinstance(self.size, (tuple, list, np.ndarray)) else ()
        if len(size) != 2 or not all(_is_positive_int(n) for n in size):
            raise InputError(f"{what} size {self.size!r}: expected (width, height) as two positive integers")
        size = (int(size[0]), int(size[1]))
        for field, value in (("K", K), ("dist", dist), ("R", R), ("t", t), ("size", size)):
            object.__setattr__(self, field, value)

    @classmethod
    def look_at(
        cls,
        name: str,
        eye,
        target,
        *,
        up=(0.0, 0.0, 1.0),
        f_px: float,
        size: tuple[int, int],
        dist=None,
    ) -> Camera:
        """A camera at ``eye (3,)`` whose optical axis passes through ``target (3,)``.

        The image's "up" (−y in pixels) points along the world ``up`` vector as seen by the camera,
        and the principal point is the image centre ``((w - 1) / 2, (h - 1) / 2)``, so ``target``
        projects there (distortion leaves the principal point in place). ``f_px`` is the focal
        length in pixels; ``dist`` defaults to no distortion.
        """
        eye = np.asarray(eye, dtype=np.float64)
        forward = np.asarray(target, dtype=np.float64) - eye
        if np.linalg.norm(forward) == 0:
            raise InputError(f"Camera.look_at({name!r}): eye and target are the same point")
        forward /= np.linalg.norm(forward)
        up = np.asarray(up, dtype=np.float64)
        down = -(up - (up @ forward) * forward)
        if np.linalg.norm(down) < 1e-9 * np.linalg.norm(up):  # up (anti)parallel to the view: roll undefined
            raise InputError(f"Camera.look_at({name!r}): up {up.tolist()} is parallel to the view direction")
        down /= np.linalg.norm(down)
        right = np.cross(down, forward)
        R = np.stack([right, down, forward])
        width, height = size
        K = np.array([[f_px, 0.0, (width - 1) / 2.0], [0.0, f_px, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
        return cls(name, K, np.zeros(5) if dist is None else dist, R, -R @ eye, size)

    @property
    def centre(self) -> np.ndarray:
        """(3,) camera centre in world coordinates, ``-R^T t``."""
        return -self.R.T @ self.t

    @property
    def P(self) -> np.ndarray:
        """(3, 4) undistorted projection matrix ``K [R | t]``."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    @functools.cached_property
    def _read_only_P(self) -> np.ndarray:
        """:attr:`P`, made once and read-only, for :meth:`sees`: the silhouette stage asks every frame."""
        P = self.P
        P.flags.writeable = False
        return P

    def depth(self, X) -> np.ndarray:
        """(N,) depth (z in the camera frame, metres) of world points ``X (N, 3)``; negative behind."""
        return _as_rows(X, 3, "X") @ self.R[2] + self.t[2]

    def project(self, X) -> np.ndarray:
        """(N, 2) pixel coordinates of world points ``X (N, 3)``, lens distortion included.

        Same numbers as ``cv2.projectPoints``; points behind the camera get mirrored (meaningless)
        pixels, so check ``depth(X) > 0`` where that matters.
        """
        x_cam = _as_rows(X, 3, "X") @ self.R.T + self.t
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = x_cam[:, :2] / x_cam[:, 2:3]
        return _distort(xy, self.dist) @ self.K[:2, :2].T + self.K[:2, 2]

    def pixel_derivative(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2, 2) derivative of the pixel with respect to the normalised image coordinates ``xy (N, 2)``
        there (pixel = K D(xy), D the lens distortion as :meth:`project` applies it): how a small step in
        the normalised image moves in the image, which undistorting a stepped pixel only approximates."""
        a, b, d = _distortion_derivative(xy, self.dist)
        (fx, skew), (_, fy) = self.K[0, :2], self.K[1, :2]
        return np.stack([fx * a + skew * b, fx * b + skew * d, fy * b, fy * d], axis=1).reshape(-1, 2, 2)

    def undistort_pixels(self, uv) -> np.ndarray:
        """(N, 2) normalised image coordinates ``(x/z, y/z)`` of pixels ``uv (N, 2)``.

        Inverts the distortion iteratively (``cv2.undistortPoints`` with a tight criterion), so
        ``project`` of the corresponding ray returns ``uv`` to about 1e-9 px inside the image. A skewed
        camera's pixels are first mapped to those of the same camera without skew (:func:`_unskew`).
        """
        uv = _as_rows(uv, 2, "uv")
        if len(uv) == 0:
            return np.empty((0, 2))
        K = self.K
        if K[0, 1] != 0:
            uv, K = _unskew(uv, K)
        xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, self.dist, criteria=UNDISTORT_CRITERIA)
        return xy.reshape(-1, 2).astype(np.float64, copy=False)

    def pixel_rays(self, uv) -> np.ndarray:
        """(N, 3) unit world directions of the rays from ``centre`` through pixels ``uv (N, 2)``."""
        return self.normalised_rays(self.undistort_pixels(uv))

    def normalised_rays(self, xy: np.ndarray) -> np.ndarray:
        """(N, 3) unit world directions of the rays through normalised image points ``xy (N, 2)``.

        ``pixel_rays`` without the undistortion, for callers that already hold ``undistort_pixels`` of
        their pixels (the undistortion is the expensive part, and it is the same for a pixel every time).
        """
        d_cam = np.hstack([xy, np.ones((len(xy), 1))])
        d_world = d_cam @ self.R  # rows of R^T d
        # np.linalg.norm(d_world, axis=1, keepdims=True)'s arithmetic, without its overhead per call.
        return d_world / np.sqrt(np.add.reduce(d_world * d_world, axis=1, keepdims=True))

    def backproject(self, uv, depth) -> np.ndarray:
        """(N, 3) world points seen at pixels ``uv (N, 2)`` at camera-frame ``depth (N,)`` (z, metres)."""
        xy = self.undistort_pixels(uv)
        depth = np.asarray(depth, dtype=np.float64).reshape(-1)
        if depth.shape != (len(xy),):
            raise ValueError(f"depth must have shape ({len(xy)},), got {depth.shape}")
        x_cam = np.hstack([xy, np.ones((len(xy), 1))]) * depth[:, None]
        return (x_cam - self.t) @ self.R  # rows of R^T (x_cam - t)

    def with_size(self, width: int, height: int) -> Camera:
        """This camera with image size ``(width, height)`` (intrinsics unchanged)."""
        return dataclasses.replace(self, size=(width, height))

    def in_image(self, uv) -> np.ndarray:
        """(N,) bool: pixel ``uv (N, 2)`` lies inside the image ``[-0.5, w - 0.5) x [-0.5, h - 0.5)``."""
        uv = _as_rows(uv, 2, "uv")
        width, height = self.size
        with np.errstate(invalid="ignore"):
            inside_u = (uv[:, 0] >= -0.5) & (uv[:, 0] < width - 0.5)
            return inside_u & (uv[:, 1] >= -0.5) & (uv[:, 1] < height - 0.5)

    def sees(self, X) -> np.ndarray:
        """(N,) bool: world points ``X (N, 3)`` in front of the camera whose pinhole image is in the image.

        The undistorted projection, because the distortion polynomial folds back far outside the image and
        can put a point well out of view on the image: this is the test that holds for points anywhere.
        Near the border it differs from ``in_image(project(X))`` by the distortion.
        """
        P = self._read_only_P
        x = _as_rows(X, 3, "X") @ P[:, :3].T + P[:, 3]
        ahead = x[:, 2] > MIN_VIEW_DEPTH_M
        seen = np.zeros(len(x), dtype=bool)
        front = x[ahead]
        seen[ahead] = self.in_image(front[:, :2] / front[:, 2:])
        return seen


@dataclass(frozen=True, eq=False)
class Rig:
    """Cameras in a stable order (the calibration file's order) with unique names.

    Index by position or by name; batched operations return arrays with the camera axis first.
    """

    cameras: tuple[Camera, ...]

    def __post_init__(self) -> None:
        cameras = tuple(self.cameras)
        for camera in cameras:
            if not isinstance(camera, Camera):
                raise TypeError(f"Rig takes Camera objects, got {type(camera).__name__}")
        names = [camera.name for camera in cameras]
        duplicates = sorted({name for name in names if names.count(name) > 1})
        if duplicates:
            raise InputError(f"duplicate camera names {', '.join(duplicates)}: expected each name once")
        object.__setattr__(self, "cameras", cameras)

    @property
    def names(self) -> tuple[str, ...]:
        """Camera names in rig order."""
        return tuple(camera.name for camera in self.cameras)

    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self) -> Iterator[Camera]:
        return iter(self.cameras)

    def __getitem__(self, key: int | str) -> Camera:
        """The camera at position ``key`` (int) or named ``key`` (str)."""
        if isinstance(key, str):
            for camera in self.cameras:
                if camera.name == key:
                    return camera
            raise KeyError(f"no camera named {key!r}; known cameras: {', '.join(self.names)}")
        return self.cameras[key]

    def project(self, X) -> np.ndarray:
        """(C, N, 2) pixels of world points ``X (N, 3)`` in every camera, in rig order."""
        X = _as_rows(X, 3, "X")
        if not self.cameras:
            return np.empty((0, len(X), 2))
        return np.stack([camera.project(X) for camera in self.cameras])

    def subset(self, names: Sequence[str] | Iterable[str]) -> Rig:
        """The rig restricted to ``names``, keeping the rig's order; unknown names raise ``KeyError``."""
        wanted = set(names)
        unknown = sorted(wanted - set(self.names))
        if unknown:
            raise KeyError(f"no cameras named {', '.join(unknown)}; known cameras: {', '.join(self.names)}")
        return Rig(tuple(camera for camera in self.cameras if camera.name in wanted))

    @property
    def centres(self) -> np.ndarray:
        """(C, 3) camera centres in world coordinates, in rig order."""
        return np.array([camera.centre for camera in self.cameras]).reshape(-1, 3)
