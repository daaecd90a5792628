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

from collections.abc import Sequence

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
    for i in range(count):
        for j in range(i + 1, count):
            if rays[i] is None or rays[j] is None:
                continue
            baseline = cameras[j].centre - cameras[i].centre
            baseline /= np.linalg.norm(baseline)
            towards = centre - cameras[i].centre
            towards = towards - (towards @ baseline) * baseline
            distance = float(np.linalg.norm(towards))
            if distance == 0.0:
                continue
            towards /= distance
            extremes = [_plane_angles(baseline, towards, directions) for directions in (rays[i], rays[j])]
            if max(high - low for low, high in extremes) > MAX_SPAN_RAD:
                continue
            (low_i, high_i), (low_j, high_j) = extremes
            disagreement[i, j] = disagreement[j, i] = 0.5 * (abs(low_i - low_j) + abs(high_i - high_j)) * distance
    return disagreement


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
        moments = cv2.moments(np.ascontiguousarray(mask, dtype=np.uint8), binaryImage=True)
        if moments["m00"] > 0:
            centroid = [moments["m10"] / moments["m00"], moments["m01"] / moments["m00"]]
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
