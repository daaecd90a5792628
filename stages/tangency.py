"""Whether the silhouettes agree with the calibration: epipolar tangency, camera pair by camera pair.

A plane through the centres of two cameras (an epipolar plane) either cuts the person or misses him, whichever
of the two cameras looks. So the planes that meet one view's silhouette are the planes that meet the other's, and
the two extreme ones, tangent to the person, are the same from both views: they touch him at the frontier points
(Cipolla & Giblin; Boyer, "On using silhouettes for camera calibration", ACCV 2006, calibrates cameras from them).
Where the calibration is wrong the two views disagree about those planes. Two cameras' names swapped, or a camera
moved after it was calibrated, leave the reconstruction nothing to carve but fragments, and nothing else says which
camera is at fault.

The disagreement of a pair is the angle between the extreme planes each view gives, averaged over the two
extremes, times the subject's distance from the baseline: a length at the subject, a few millimetres with a sound
calibration (segmentation noise included), centimetres with cameras turned by a fraction of a degree,
decimetres with two names swapped. A camera's disagreement is the median over its pairs, so that one bad camera
does not implicate the others, and cameras are set aside worst first until the rest agree
(:func:`cameras_at_fault`). A view whose silhouette is empty or touches the image's border gives no extreme
(the border cuts the person there), and a pair whose baseline passes through the person has no extreme planes
(its planes cut him all round).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from calib.camera import Camera
from stages.rays import nearest_point
from stages.reconstruction.views import blind_beyond_image

#: A pair whose planes through the silhouette span more than this has its baseline through the person.
MAX_SPAN_RAD = np.radians(150.0)


def pair_disagreement(masks: Sequence[np.ndarray], cameras: Sequence[Camera], centre: np.ndarray) -> np.ndarray:
    """(C, C) float: each camera pair's disagreement (metres at the subject) on one frame, NaN where not measured.

    Parameters
    ----------
    masks, cameras : sequences of (H, W) uint8 and of Camera
        As in `stages.consistency.consistent_silhouettes`: a silhouette per camera, cameras in metres.
    centre : (3,) float
        Where the subject is when the silhouettes cannot say (fewer than two views see him): the working
        volume's centre. It sets the side of each baseline the angles are measured from and the distance that
        turns them into lengths; the point nearest to the rays through the silhouettes' centroids is used
        instead when there is one, since a subject far from the volume's centre would scale the lengths wrong.
    """
    centre = _nearest_point(masks, cameras, centre)
    outlines = [_outline(mask) for mask in masks]
    rays = [camera.pixel_rays(points) if points is not None else None
            for camera, points in zip(cameras, outlines, strict=True)]
    count = len(cameras)
    disagreement = np.full((count, count), np.nan)
    for i, j, (_, _, distance), (low_i, high_i), (low_j, high_j) in _measured_pairs(rays, cameras, centre):
        disagreement[i, j] = disagreement[j, i] = 0.5 * (abs(low_i - low_j) + abs(high_i - high_j)) * distance
    return disagreement


def _measured_pairs(rays: Sequence[np.ndarray | None], cameras: Sequence[Camera], centre: np.ndarray):
    """``(i, j, frame, extremes_i, extremes_j)`` of each camera pair i < j whose two views' ``rays`` (N, 3) (world
    directions through the outline; None: not measured) give extreme planes: the pair's `_pair_frame` and the
    smallest and largest angle of each view's planes in it (`_plane_angles`). A pair whose baseline meets the
    subject's ``centre``, or whose planes span more than `MAX_SPAN_RAD` (the baseline passes through the person),
    has none."""
    for i in range(len(cameras)):
        for j in range(i + 1, len(cameras)):
            if rays[i] is None or rays[j] is None:
                continue
            frame = _pair_frame(cameras[i], cameras[j], centre)
            if frame is None:
                continue
            baseline, towards, _ = frame
            extremes = [_plane_angles(baseline, towards, rays[k]) for k in (i, j)]
            if max(high - low for low, high in extremes) <= MAX_SPAN_RAD:
                yield i, j, frame, *extremes


def _pair_frame(first: Camera, second: Camera, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray, float] | None:
    """``(baseline, towards, distance)`` of a camera pair: the unit baseline from ``first`` to ``second``, the unit
    direction across it towards the subject's ``centre``, and the centre's distance from it; None when the centre
    lies on the baseline (no plane through it is the subject's)."""
    baseline = second.centre - first.centre
    baseline /= np.linalg.norm(baseline)
    towards = centre - first.centre
    towards = towards - (towards @ baseline) * baseline
    distance = float(np.linalg.norm(towards))
    if distance == 0.0:
        return None
    return baseline, towards / distance, distance


def pair_medians(per_frame: np.ndarray) -> np.ndarray:
    """(C, C) float: each pair's median disagreement over the frames (``per_frame`` (F, C, C) from
    :func:`pair_disagreement`), NaN for a pair never measured."""
    return np.apply_along_axis(_median_measured, 0, np.asarray(per_frame, dtype=float))


def camera_disagreement(pairs: np.ndarray, among: np.ndarray | None = None) -> np.ndarray:
    """(C,) float: each camera's disagreement, the median over its pairs with the cameras ``among`` (a (C,) bool
    mask, default all) of :func:`pair_medians`; NaN for a camera with no such pair measured."""
    among = np.ones(len(pairs), dtype=bool) if among is None else np.asarray(among, dtype=bool)
    return np.array([_median_measured(row[among & (np.arange(len(row)) != camera)])
                     for camera, row in enumerate(pairs)])


def cameras_at_fault(pairs: np.ndarray, limit: float) -> np.ndarray:
    """(C,) bool: the cameras whose calibration disagrees with the others' by more than ``limit`` (metres).

    While some camera's disagreement with the cameras still trusted exceeds ``limit``, the camera that disagrees
    most on average with them is set aside, and the others are judged again without it. A median over each
    camera's pairs alone would blame every camera of a four-camera rig with two cameras swapped: each sound
    camera disagrees with two of its three partners, while a swapped one disagrees with all three. Two cameras
    that disagree cannot say which of them is off: both are at fault.
    """
    trusted = np.ones(len(pairs), dtype=bool)
    while True:
        beyond = trusted & (camera_disagreement(pairs, trusted) > limit)  # NaN (not measured) is not beyond
        if not beyond.any():
            return ~trusted
        if trusted.sum() <= 2:
            return ~trusted | beyond
        others = trusted[None, :] & ~np.eye(len(pairs), dtype=bool)
        mean = [np.nanmean(row[keep]) if trusted[camera] and np.any(~np.isnan(row[keep])) else -np.inf
                for camera, (row, keep) in enumerate(zip(pairs, others, strict=True))]
        trusted[int(np.argmax(mean))] = False


def _median_measured(values: np.ndarray) -> float:
    """The median of the values that are not NaN; NaN when there are none."""
    measured = values[~np.isnan(values)]
    return float(np.median(measured)) if len(measured) else np.nan


def _nearest_point(masks: Sequence[np.ndarray], cameras: Sequence[Camera], fallback: np.ndarray) -> np.ndarray:
    """(3,) the point nearest to the rays through the centroids of the silhouettes that are not empty, or
    ``fallback`` when fewer than two are (or their rays are parallel)."""
    origins, directions = [], []
    for camera, mask in zip(cameras, masks, strict=True):
        mask = np.ascontiguousarray(mask, dtype=np.uint8)
        x, y, w, h = cv2.boundingRect(mask)  # the moments of the person's box alone: a fraction of the image
        moments = cv2.moments(mask[y : y + h, x : x + w], binaryImage=True)
        if moments["m00"] > 0:
            centroid = [x + moments["m10"] / moments["m00"], y + moments["m01"] / moments["m00"]]
            origins.append(camera.centre)
            directions.append(camera.pixel_rays([centroid])[0])
    nearest = nearest_point(np.array(origins), np.array(directions)) if len(origins) >= 2 else None
    return np.asarray(fallback, dtype=float) if nearest is None else nearest


def _outline(mask: np.ndarray) -> np.ndarray | None:
    """(N, 2) float pixels of the silhouette's outer outlines, or None when it is empty or reaches the border
    (`blind_beyond_image`: the border, not the person, bounds it there)."""
    if blind_beyond_image(mask):
        return None
    contours, _ = cv2.findContours(np.ascontiguousarray(mask, dtype=np.uint8), cv2.RETR_EXTERNAL,
                                   cv2.CHAIN_APPROX_SIMPLE)
    return np.concatenate(contours).reshape(-1, 2).astype(float)


def _plane_angles(baseline: np.ndarray, towards: np.ndarray, directions: np.ndarray) -> tuple[float, float]:
    """The smallest and largest angle, about the ``baseline``, of the planes through it and the rays
    ``directions`` (N, 3), measured from the half-plane ``towards`` the subject (so the subject's lie near 0)."""
    # The plane's normal n = b × d, with b the baseline and t towards the subject (t ⟂ b): n · (b × t) = d · t
    # and n · t = −d · (b × t), so each angle takes two dot products.
    angles = np.arctan2(directions @ towards, -(directions @ np.cross(baseline, towards)))
    return float(angles.min()), float(angles.max())


# Refinement of the cameras' orientations from the tangencies (Boyer 2006 calibrates whole cameras this way).
#: A camera's turn is penalised like one disagreement of this many metres per degree. The tangencies of frames
#: a few tenths of a second apart repeat each other's errors, and they leave some directions of a turn loose
#: (cameras at one height see their extreme planes at the head and the feet, which a turn about the vertical
#: moves little): held this firmly, a camera turns only as far as hundreds of tangencies agree it should.
TURN_PRIOR_M_PER_DEGREE = 1.0
#: Disagreements beyond this (metres at the subject) count less and less (a soft L1 loss): a silhouette that
#: lost a hand or gained a shadow on one frame moves its extreme planes by its own error, not the calibration's.
TANGENCY_LOSS_SCALE_M = 0.01
#: Turns are proposed only when the median disagreement falls to this share or less: a sound calibration's
#: disagreement is the silhouettes' noise, which no turn removes, and a refinement there would chase the noise.
AGREEMENT_SHARE = 2.0 / 3.0
_TURN_PRIOR = TURN_PRIOR_M_PER_DEGREE * np.degrees(1.0)  # metres per radian


@dataclass(frozen=True)
class Refinement:
    """Each camera's turn about its centre that makes the silhouettes' extreme planes agree (`refine_turns`).

    Attributes
    ----------
    turns : (C, 3) float
        Rotation vectors (radians, world frame) turning each camera's rays about its centre.
    before_m, after_m : float
        Median disagreement of the tangencies (metres at the subject) with the cameras as given and turned.
    tangencies : int
        Extreme planes compared (two per camera pair and frame where both views show the whole subject).
    """

    turns: np.ndarray
    before_m: float
    after_m: float
    tangencies: int

    @property
    def tangencies_agree(self) -> bool:
        """Whether the turns make the tangencies agree clearly better than the calibration as given
        (`AGREEMENT_SHARE`)."""
        return self.tangencies > 0 and self.after_m <= AGREEMENT_SHARE * self.before_m


def refine_turns(masks_by_frame: Iterable[Sequence[np.ndarray]], cameras: Sequence[Camera],
                 centre: np.ndarray) -> Refinement:
    """The turn of each camera about its centre that best makes its silhouettes' extreme epipolar planes agree with
    the other cameras', over several frames (robust least squares, each turn held by `TURN_PRIOR_M_PER_DEGREE`).

    A camera turned by a fraction of a degree after calibration (knocked, a loose mount, a calibration from a board
    seen at a few angles) moves each of its rays by centimetres at the subject, and the visual hull then carves
    limbs away: the positions of the cameras are usually known to millimetres, their orientations less well. The
    same tangencies as :func:`pair_disagreement` are compared, signed, with each pair's extreme rays found again
    at every step; only the outlines' convex hulls matter (a plane through the camera's centre touches the
    silhouette on its hull).

    Parameters
    ----------
    masks_by_frame : iterable of sequences of (H, W) uint8
        Per frame, a silhouette per camera; read once, one frame at a time (a generator keeps one frame's masks in
        memory, not all of them).
    cameras : sequence of Camera
    centre : (3,) float
        The working volume's centre (see :func:`pair_disagreement`).
    """
    from scipy.optimize import least_squares  # here: every command imports this module, few refine a rig

    problem = _TangencyProblem.build(masks_by_frame, cameras, centre)
    count = len(cameras)
    if problem is None:
        return Refinement(np.zeros((count, 3)), np.nan, np.nan, 0)

    last: dict = {}

    def evaluated(turns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # least_squares asks for both at each point
        if last.get("turns") is None or not np.array_equal(last["turns"], turns):
            last.update(turns=turns.copy(), values=problem.disagreements(turns.reshape(count, 3)))
        return last["values"]

    def residuals(turns: np.ndarray) -> np.ndarray:
        return np.concatenate([evaluated(turns)[0], _TURN_PRIOR * turns])

    def jacobian(turns: np.ndarray) -> np.ndarray:
        return np.vstack([evaluated(turns)[1], _TURN_PRIOR * np.eye(3 * count)])

    start = np.zeros(3 * count)
    solution = least_squares(residuals, start, jac=jacobian, loss="soft_l1", f_scale=TANGENCY_LOSS_SCALE_M).x
    turns = solution.reshape(count, 3)
    before = np.abs(problem.disagreements(np.zeros((count, 3)))[0])
    after = np.abs(problem.disagreements(turns)[0])
    return Refinement(turns, float(np.median(before)), float(np.median(after)), len(before))


def turned(camera: Camera, turn: np.ndarray) -> Camera:
    """``camera`` with its rays turned about its centre by the rotation vector ``turn`` (radians, world frame)."""
    R = camera.R @ _rotation(turn).T  # rays R^T d turned: (Exp(turn) R^T)^T = R Exp(turn)^T
    return dataclasses.replace(camera, R=R, t=-R @ camera.centre)


def _rotation(turn: np.ndarray) -> np.ndarray:
    """(3, 3) the rotation of the rotation vector ``turn`` (Rodrigues)."""
    return cv2.Rodrigues(np.asarray(turn, dtype=np.float64).reshape(3, 1))[0]


def _left_jacobian(turn: np.ndarray) -> np.ndarray:
    """(3, 3) J with Exp(turn + ε) ≈ Exp(J ε) Exp(turn) (the left Jacobian of the rotation group)."""
    angle = float(np.linalg.norm(turn))
    cross = np.array([[0.0, -turn[2], turn[1]], [turn[2], 0.0, -turn[0]], [-turn[1], turn[0], 0.0]])
    if angle < 1e-8:
        return np.eye(3) + 0.5 * cross
    return (np.eye(3) + (1.0 - np.cos(angle)) / angle**2 * cross
            + (angle - np.sin(angle)) / angle**3 * cross @ cross)


@dataclass(frozen=True)
class _TangencyProblem:
    """The extreme planes of every measured camera pair and frame, as flat arrays for :meth:`disagreements`.

    The convex-hull rays of each view (camera frame) are stacked in ``rays``; each pair and frame has two groups of
    them, one per camera, gathered by ``gather`` in group order (``starts`` where each group begins), with the pair's
    half-plane directions ``towards`` and ``sideways`` per gathered ray.
    """

    rays: np.ndarray  # (N, 3) unit ray directions in their camera's frame
    camera_of_ray: np.ndarray  # (N,) int
    gather: np.ndarray  # (G,) int indices into rays, group after group
    starts: np.ndarray  # (2 P,) int where each group begins in gather; groups 2p and 2p + 1 are pair p's cameras
    towards: np.ndarray  # (G, 3) the pair's direction towards the subject, across the baseline
    sideways: np.ndarray  # (G, 3) towards × baseline
    distance: np.ndarray  # (P,) the subject's distance from the pair's baseline
    pair_cameras: np.ndarray  # (P, 2) int
    rotations: np.ndarray  # (C, 3, 3) the cameras' world-to-camera rotations as given

    @classmethod
    def build(cls, masks_by_frame, cameras, centre) -> _TangencyProblem | None:
        rays, camera_of_ray, groups, towards, sideways, distance, pairs = [], [], [], [], [], [], []
        offset = 0
        for masks in masks_by_frame:
            middle = _nearest_point(masks, cameras, centre)
            indices, world = [], []  # per view, its hull rays' indices in ``rays`` and their world directions
            for index, (camera, mask) in enumerate(zip(cameras, masks, strict=True)):
                outline = _outline(mask)
                if outline is None:
                    indices.append(None)
                    world.append(None)
                    continue
                xy = cv2.convexHull(camera.undistort_pixels(outline).astype(np.float32)).reshape(-1, 2)
                directions = np.hstack([xy, np.ones((len(xy), 1))])
                rays.append(directions / np.linalg.norm(directions, axis=1, keepdims=True))
                camera_of_ray.append(np.full(len(xy), index))
                indices.append(np.arange(offset, offset + len(xy)))
                world.append(rays[-1] @ camera.R)
                offset += len(xy)
            for i, j, (baseline, across, length), _, _ in _measured_pairs(world, cameras, middle):
                groups += [indices[i], indices[j]]
                towards.append(across)
                sideways.append(np.cross(across, baseline))
                distance.append(length)
                pairs.append((i, j))
        if not pairs:
            return None
        sizes = np.array([len(group) for group in groups])
        per_ray = np.repeat(np.arange(len(pairs)), sizes.reshape(-1, 2).sum(axis=1))
        return cls(np.concatenate(rays), np.concatenate(camera_of_ray), np.concatenate(groups),
                   np.cumsum(sizes) - sizes, np.array(towards)[per_ray], np.array(sideways)[per_ray],
                   np.array(distance), np.array(pairs), np.array([camera.R for camera in cameras]))

    def disagreements(self, turns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(2 P,) signed disagreements (metres at the subject) of each pair's two extreme planes with the cameras
        turned by ``turns`` (C, 3), and their derivatives (2 P, 3 C) with respect to the turns."""
        to_world = np.array([_rotation(turn) for turn in turns]) @ self.rotations.transpose(0, 2, 1)  # Exp(ω) Rᵀ
        jacobians = np.array([_left_jacobian(turn) for turn in turns])  # Exp(ω + ε) = Exp(J ε) Exp(ω)
        world = np.einsum("nij,nj->ni", to_world[self.camera_of_ray], self.rays)[self.gather]  # (G, 3)
        y = np.einsum("gi,gi->g", world, self.towards)
        x = np.einsum("gi,gi->g", world, self.sideways)
        angles = np.arctan2(y, x)
        sizes = np.diff(np.append(self.starts, len(angles)))
        pairs, count = len(self.distance), len(turns)
        residuals, rows = [], []
        for extreme in (np.minimum, np.maximum):  # each group's lowest plane, then its highest
            hits = np.flatnonzero(angles == np.repeat(extreme.reduceat(angles, self.starts), sizes))
            picked = hits[np.searchsorted(hits, self.starts)]  # (2 P,) each group's first ray at its extreme
            d, t, s = world[picked], self.towards[picked], self.sideways[picked]
            xp, yp = x[picked, None], y[picked, None]
            # θ = atan2(d·t, d·s); a turn δ moves d by δ × d: dθ/dδ = (x (d × t) − y (d × s)) / (x² + y²)
            gradient = (xp * np.cross(d, t) - yp * np.cross(d, s)) / (xp**2 + yp**2)
            gradient *= np.repeat(self.distance, 2)[:, None]  # metres at the subject
            residuals.append((angles[picked[0::2]] - angles[picked[1::2]]) * self.distance)
            row = np.zeros((pairs, count, 3))
            row[np.arange(pairs), self.pair_cameras[:, 0]] = gradient[0::2]
            row[np.arange(pairs), self.pair_cameras[:, 1]] = -gradient[1::2]
            rows.append(np.einsum("pci,cij->pcj", row, jacobians).reshape(pairs, 3 * count))
        return np.concatenate(residuals), np.vstack(rows)
