"""Silhouette outlines with sub-pixel positions, tangents and the normals of their viewing cones.

Every viewing-cone face lies in the plane through the camera centre and a contour edge; at a rim
point the surface normal equals that plane's normal, oriented away from the silhouette's interior
(DESIGN.md, "Normals from silhouettes"). This module turns a mask into those planes.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import correlate1d, gaussian_filter1d

from calib.camera import Camera

# Contours with fewer points than this are specks (a few pixels), not body parts.
MIN_CONTOUR_POINTS = 12
# Contour points closer than this to the image edge (pixels) outline the frame, not the person.
BORDER_MARGIN_PX = 2.0
# OpenCV's contour runs through the centres of the outermost foreground pixels, while the outline of
# the silhouette lies between those and the first background pixels: half a pixel further out.
OUTLINE_OFFSET_PX = 0.5
# Offset (pixels) at which the two sides of a contour point are read to decide which side is inside.
SIDE_PROBE_PX = 1.5
# Outline points this close (pixels) to a part of the view hidden behind something in front of the subject lie
# on that thing's edge, not on a rim.
HIDDEN_MARGIN_PX = 2
# Where an outline is concave the surface behind its rim is saddle-shaped (Koenderink: the outline's
# curvature has the sign of the surface's Gaussian curvature), so the visual shape's rim placement, which
# assumes a locally convex surface, misplaces the point; at the junction of a limb and the body the
# outline also has a corner, whose tangent is ill-defined. Outline points bending outwards more sharply
# than a circle of CONCAVE_RADIUS_PX pixels, measured along CURVATURE_SCALE_PX contour points (well above
# the pixel staircase), cast no ray: on the synthetic captures this lowers the median normal error with
# segmented masks by a degree, and the outliers too.
CONCAVE_RADIUS_PX = 20.0
CURVATURE_SCALE_PX = 4.0


@dataclass(frozen=True)
class Outline:
    """The outline of one camera's silhouette, all contours concatenated.

    Attributes
    ----------
    pixels : (L, 2) float
        Sub-pixel outline positions ``(u, v)``.
    tangents : (L, 2) float
        Unit image tangents along the outline.
    outward : (L, 2) float
        Unit image normals pointing away from the silhouette's interior.
    contour : (L,) int
        Which contour each point belongs to (0, 1, ...).
    arc_length : (L,) float
        Cumulative outline length in pixels over the concatenated contours, for even sampling.
    usable : (L,) bool
        False near the image border, where the outline is the frame's edge rather than a rim, next to a part
        of the view hidden behind something in front of the subject, where it is that thing's edge, and where
        the outline is sharply concave (see ``CONCAVE_RADIUS_PX``).
    bounds : (x, y, width, height)
        The box around every foreground pixel, specks included (all zero for an empty mask).
    """

    pixels: np.ndarray
    tangents: np.ndarray
    outward: np.ndarray
    contour: np.ndarray
    arc_length: np.ndarray
    usable: np.ndarray
    bounds: tuple[int, int, int, int]

    def __len__(self) -> int:
        return len(self.pixels)


def outline(mask: np.ndarray, *, smoothing_px: float, hidden: np.ndarray | None = None) -> Outline:
    """The smoothed outline of ``mask`` (H, W) uint8, every contour (outer ones and holes).

    ``hidden`` (H, W) uint8, nonzero where something in front of the subject hides him
    (:mod:`stages.reconstruction.occlusion`), makes the outline within ``HIDDEN_MARGIN_PX`` of it unusable.

    Positions are smoothed along the contour without shrinking it (``_unshrunk``, a Gaussian of
    ``smoothing_px`` points; removing the pixel staircase) and moved half a pixel outwards onto the true
    outline. The contours are processed together, concatenated, each padded with its own wrapped ends
    (``_wrapped``) so that the filters along them see only their own contour: a mask then costs a few numpy
    calls however many contours it has.
    """
    contours, _ = cv2.findContours(mask, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    bounds = cv2.boundingRect(np.concatenate(contours)) if contours else (0, 0, 0, 0)
    pieces = [c for c in contours if len(c) >= MIN_CONTOUR_POINTS]
    if not pieces:
        empty = np.zeros((0, 2))
        return Outline(empty, empty, empty, np.zeros(0, int), np.zeros(0), np.zeros(0, bool), bounds)
    height, width = mask.shape
    raw = np.concatenate(pieces).reshape(-1, 2).astype(np.float64)
    lengths = np.array([len(c) for c in pieces])
    contour = np.repeat(np.arange(len(pieces)), lengths)
    # Twicing filters twice, so it reads twice its radius around a point.
    reach = max(2 * _radius(smoothing_px) if smoothing_px > 0 else 0, _radius(max(smoothing_px, 1.0)),
                _radius(CURVATURE_SCALE_PX))
    rows, interior = _wrapped(lengths, reach)
    padded = raw.take(rows, axis=0)
    pixels = _unshrunk(padded, smoothing_px).compress(interior, axis=0) if smoothing_px > 0 else raw
    derivative = _along_contour(padded, max(smoothing_px, 1.0), 1).compress(interior, axis=0)
    tangents = derivative / np.maximum(row_norms(derivative), 1e-12)
    outward = tangents[:, ::-1] * (1.0, -1.0)  # (ty, -tx)
    flipped = _mostly_inside(mask, pixels + SIDE_PROBE_PX * outward, contour, lengths).take(contour)
    outward[flipped] *= -1.0
    pixels = pixels + OUTLINE_OFFSET_PX * outward
    u, v = pixels[:, 0], pixels[:, 1]
    usable = (
        (u > BORDER_MARGIN_PX) & (v > BORDER_MARGIN_PX)
        & (u < width - 1 - BORDER_MARGIN_PX) & (v < height - 1 - BORDER_MARGIN_PX)
        & ~(_bending(padded, interior, outward) > 1.0 / CONCAVE_RADIUS_PX)
    )
    if hidden is not None:
        near = cv2.dilate(hidden, np.ones((2 * HIDDEN_MARGIN_PX + 1,) * 2, np.uint8))
        columns = np.clip(np.round(u).astype(np.intp), 0, width - 1)
        rows = np.clip(np.round(v).astype(np.intp), 0, height - 1)
        usable &= near[rows, columns] == 0
    # Each point's step from the previous point of its contour (the first point's from its contour's last).
    previous = np.arange(len(raw)) - 1
    previous[np.cumsum(lengths) - lengths] += lengths
    steps = row_norms(raw - raw.take(previous, axis=0))[:, 0]
    return Outline(pixels, tangents, outward, contour, np.cumsum(steps), usable, bounds)


def _wrapped(lengths: np.ndarray, reach: int) -> tuple[np.ndarray, np.ndarray]:
    """``(rows (P,), interior (P,) bool)``: closed contours of ``lengths`` (n,) points, concatenated, laid out
    each with ``reach`` more points at either end, those ``mode="wrap"`` reads beyond its ends: ``rows``
    indexes the concatenation, ``interior`` marks each contour's own points, in order.

    A filter reaching at most ``reach`` points along the padded contours gives each interior point the
    neighbours, hence the sum, it has when its contour alone is filtered with ``mode="wrap"``.
    """
    padded = lengths + 2 * reach
    # Each padded row's position in its contour, from -reach to length + reach - 1.
    offset = np.arange(padded.sum()) - np.repeat(np.cumsum(padded) - padded + reach, padded)
    length = np.repeat(lengths, padded)
    rows = np.repeat(np.cumsum(lengths) - lengths, padded) + offset % length
    return rows, (offset >= 0) & (offset < length)


def _unshrunk(raw: np.ndarray, sigma: float) -> np.ndarray:
    """A closed contour (L, 2) smoothed by Gaussian twicing (Tukey): G∗x + G∗(x − G∗x).

    A Gaussian alone pulls every point of a curved outline towards its centre of curvature by about
    σ²κ/2, which is a pixel or more at the end of a limb a few pixels wide: thin limbs came out thinner
    and shorter than their silhouettes, the more so the stronger the smoothing. Smoothing what the first
    pass removed and adding it back cancels that shrinkage to first order (the filter 2G − G∗G passes
    the outline's shape almost untouched) while the pixel staircase, at the highest frequencies, is
    still removed.
    """
    smooth = _along_contour(raw, sigma, 0)
    return smooth + _along_contour(raw - smooth, sigma, 0)


def _along_contour(raw: np.ndarray, sigma: float, order: int) -> np.ndarray:
    """``gaussian_filter1d(raw, sigma, axis=0, order=order, mode="wrap")`` of a closed contour (L, 2), with
    the weights computed once per (sigma, order): building them was half the cost of filtering a contour."""
    return correlate1d(raw, _gaussian_weights(sigma, order), axis=0, mode="wrap")


def _radius(sigma: float) -> int:
    """How many points either side ``gaussian_filter1d`` reads at ``sigma``: its default truncation at 4 sigma."""
    return int(4.0 * sigma + 0.5)


@functools.lru_cache(maxsize=16)
def _gaussian_weights(sigma: float, order: int) -> np.ndarray:
    """The correlation weights of ``gaussian_filter1d`` for ``sigma`` and derivative ``order``: its response
    to a unit impulse is its kernel, the weights reversed."""
    radius = _radius(sigma)
    impulse = np.zeros(2 * radius + 1)
    impulse[radius] = 1.0
    weights = gaussian_filter1d(impulse, sigma, order=order, mode="constant")[::-1].copy()
    weights.flags.writeable = False
    return weights


def _bending(padded: np.ndarray, interior: np.ndarray, outward: np.ndarray) -> np.ndarray:
    """(L,) signed curvature (1 / pixels) of the closed contours ``padded`` (P, 2) at their ``interior`` (P,)
    points (see ``_wrapped``), positive where they bend towards ``outward`` (L, 2), i.e. where the
    silhouette is concave: r''·n / |r'|² at CURVATURE_SCALE_PX."""
    first = _along_contour(padded, CURVATURE_SCALE_PX, 1).compress(interior, axis=0)
    second = _along_contour(padded, CURVATURE_SCALE_PX, 2).compress(interior, axis=0)
    return np.einsum("ij,ij->i", second, outward) / np.maximum(np.einsum("ij,ij->i", first, first), 1e-12)


def _mostly_inside(mask: np.ndarray, probes: np.ndarray, contour: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """(n,) bool: whether most ``probes`` (L, 2) of each contour fall on foreground pixels of ``mask``, given
    the contour of each probe ``contour`` (L,) and the contours' ``lengths`` (n,)."""
    height, width = mask.shape
    u, v = np.minimum(np.maximum(np.rint(probes).astype(int), 0), (width - 1, height - 1)).T  # np.clip's result
    return np.bincount(contour.compress(mask[v, u] > 0), minlength=len(lengths)) * 2 > lengths


def cone_normals(camera: Camera, normalised: np.ndarray, tangents: np.ndarray, outward: np.ndarray) -> np.ndarray:
    """(L, 3) unit normals of the viewing-cone tangent planes at outline points, oriented outwards.

    The plane through the camera centre containing the ray of an outline point, whose normalised image
    coordinates are ``normalised`` (L, 2) (``camera.undistort_pixels`` of its pixel), and the direction in
    which that ray moves as the point moves along the outline's tangent ``tangents`` (L, 2); its normal is
    the cross product of the two, turned to the side of ``outward`` (L, 2). Pixel steps are carried into the
    normalised image by the inverse of the distortion's derivative at the point (:func:`normalised_steps`):
    the tangent of the outline's image there, exactly, without undistorting further points.
    """
    if len(normalised) == 0:
        return np.zeros((0, 3))
    along, beside = normalised_steps(camera, normalised, tangents, outward)
    # Rays through the point and a step along (or beside) it: R^T (x, y, 1) and R^T (dx, dy, 0), unnormalised.
    ray = np.hstack([normalised, np.ones((len(normalised), 1))]) @ camera.R
    along = along @ camera.R[:2]
    # ray × along, as np.cross computes it (without its generic axis handling, which cost more than this).
    normals = (ray.take((1, 2, 0), axis=1) * along.take((2, 0, 1), axis=1)
               - ray.take((2, 0, 1), axis=1) * along.take((1, 2, 0), axis=1))  # take: faster than ray[:, (1, 2, 0)]
    flip = np.einsum("ij,ij->i", normals, beside @ camera.R[:2]) < 0
    normals[flip] *= -1.0
    return normals / np.maximum(row_norms(normals), 1e-15)


def normalised_steps(camera: Camera, normalised: np.ndarray, *steps: np.ndarray) -> list[np.ndarray]:
    """Each of the pixel ``steps`` (L, 2) at the points ``normalised`` (L, 2) as steps of normalised image
    coordinates, (L, 2) each: solved from the derivative of the projection there
    (:meth:`~calib.camera.Camera.pixel_derivative`), which undistorting the stepped pixels only
    approximates to first order."""
    derivative = camera.pixel_derivative(normalised)
    m00, m01, m10, m11 = derivative[:, 0, 0], derivative[:, 0, 1], derivative[:, 1, 0], derivative[:, 1, 1]
    determinant = m00 * m11 - m01 * m10
    inverse = np.stack([m11, -m01, -m10, m00], axis=1).reshape(-1, 2, 2) / determinant[:, None, None]
    return [np.einsum("nij,nj->ni", inverse, step) for step in steps]


def row_norms(vectors: np.ndarray) -> np.ndarray:
    """(L, 1) Euclidean lengths of ``vectors`` (L, k): the arithmetic of ``np.linalg.norm(vectors, axis=1,
    keepdims=True)`` (same bits: the squares summed from the first column on) without its argument handling,
    and column by column, because a numpy reduction over rows of two or three numbers is slower than adding
    the columns."""
    columns = vectors.T
    total = columns[0] * columns[0]
    for column in columns[1:]:
        total += column * column
    return np.sqrt(total)[:, None]
