"""From evidence to mask: hysteresis, morphology and components at the working resolution, then the
outline placed by matting, measured again at full resolution where a working pixel is mixed.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from stages.silhouettes.evidence import Evidence, _dot, _Noise
from stages.silhouettes.params import SilhouetteParams

# Matting (full-resolution pixels): the person's colour next to the outline is the mean of the mask's
# pixels at least CORE_DEPTH_PX inside it (lens blur and compression mix the outermost ones) within
# MATTE_RADIUS_PX, and the outline is measured on pixels up to MATTE_RADIUS_PX from it, on both sides.
CORE_DEPTH_PX = 2
MATTE_RADIUS_PX = 4
# The person's share of a pixel is measured only where the person's colour differs from the background by
# more than this (8-bit levels); closer colours make it too noisy, and the mask decides.
MIN_MATTE_CONTRAST = 8.0
# Magnitude (a share of the pixel) given to the outline score where the mask decides.
SCORE_FLOOR = 0.1


def silhouette_from_evidence(view: Evidence, shadow: np.ndarray | None, params: SilhouetteParams) -> np.ndarray:
    """(H, W) uint8 mask of the person, 0 = background, 255 = person, from one view's evidence.

    ``shadow`` (h', w') bool marks the pixels of the region known to be shadow (only their change of
    colour direction counts there); None: none. At the working resolution (``params.downsample``),
    hysteresis, morphology and component filtering give the mask, and in the mask's box the matting
    places the outline, measured again at full resolution where a working pixel is mixed. The costly
    steps thus run on a fraction of the pixels.
    """
    image, background, ds = view.image, view.model, params.downsample
    silhouette = np.zeros(image.shape[:2], np.uint8)
    if view.region is None:
        return silhouette
    evidence2 = view.difference2
    if shadow is not None and shadow.any():
        evidence2 = cv2.copyTo(view.chroma2, shadow.view(np.uint8), evidence2.copy())  # np.where at a third of its cost
    mask = _clean_mask(_hysteresis(evidence2, params), params, ds, image.shape[0] * image.shape[1] / ds**2)
    x, y, w, h = cv2.boundingRect(mask)
    if w == 0:
        return silhouette
    # The outline is worked out in the person's bounding box only, with a margin of background wider
    # than the matting band, so that interpolation at the box's edges sees background as it would.
    margin = max(1, round(MATTE_RADIUS_PX / ds)) + 2
    x0, y0 = max(x - margin, 0), max(y - margin, 0)
    x1, y1 = min(x + w + margin, mask.shape[1]), min(y + h + margin, mask.shape[0])
    box = (slice(y0, y1), slice(x0, x1))  # in the region
    region = view.region
    y0, y1, x0, x1 = y0 + region[0].start, y1 + region[0].start, x0 + region[1].start, x1 + region[1].start
    frame_box = (slice(y0, y1), slice(x0, x1))  # the same in the working-resolution frame
    matte = _matte(mask[box], view.I_sharp[frame_box], background.B_sharp[frame_box], view.noise,
                   view.alpha[box], ds)
    if ds > 1:
        score = _full_resolution_score(matte, image, background.image, view.noise, (y0 * ds, x0 * ds), ds)
    else:
        score = matte.score
    inside = silhouette[y0 * ds : y1 * ds, x0 * ds : x1 * ds]  # a view, clipped at the image's edges
    cv2.compare(score[: inside.shape[0], : inside.shape[1]], 0.0, cv2.CMP_GT, dst=inside)
    return silhouette


def _hysteresis(evidence2: np.ndarray, params: SilhouetteParams) -> np.ndarray:
    """(h, w) uint8 mask: the regions above the weak threshold that hold a pixel above the strong one.

    Weak regions are opened first (lines one or two pixels wide, such as the rim of a hard shadow,
    vanish) and strong pixels are kept as they are (a thin limb is strong).
    """
    strong = cv2.compare(evidence2, float(params.strong_threshold**2), cv2.CMP_GT)
    weak = cv2.compare(evidence2, float(params.weak_threshold**2), cv2.CMP_GT)
    weak = cv2.bitwise_or(cv2.morphologyEx(weak, cv2.MORPH_OPEN, disk(1)), strong)
    count, labels = cv2.connectedComponents(weak, connectivity=8)
    seeded = np.zeros(count, np.uint8)  # (count,) 255 for the regions holding a strong pixel
    seeded[labels[strong > 0]] = 255
    seeded[0] = 0
    if seeded[1:].all():  # every region holds one (about half of the frames): the mask is the weak one
        return weak
    return np.take(seeded, labels)


@dataclass(frozen=True, eq=False)
class _Matte:
    score: np.ndarray  # (h, w) float32 > 0 for the person: φ − 1/2 where measured, else the mask's ±SCORE_FLOOR
    # The pixels that full resolution measures again: φ measured and mixed (0 < φ < 1).
    rows: np.ndarray  # (m,) int working-resolution pixels
    cols: np.ndarray  # (m,) int
    F: np.ndarray  # (3, m) float32 the person's colour next to each
    lam: np.ndarray  # (m,) float32 the exposed background's brightness factor λ next to each


# The matte's score where the mask decides, by mask value: a table lookup costs a third of np.where.
_MASK_SCORE = np.where(np.arange(256) > 0, np.float32(SCORE_FLOOR), np.float32(-SCORE_FLOOR))


def _matte(mask: np.ndarray, I: np.ndarray, B: np.ndarray, noise: _Noise, alpha: np.ndarray,
           downsample: int) -> _Matte:
    """The person's share φ of the pixels near the outline, and what it was measured against.

    A pixel on a blurred edge mixes the person's colour F and the background's, λB:
    I = φ F + (1 − φ) λB, so φ = (I − λB)·(F − λB) / ‖F − λB‖². F is the mean colour of the mask's core
    nearby (pixels ``CORE_DEPTH_PX`` inside it) and λ the mean brightness distortion of the pixels just
    outside (1, or less in the person's shadow). The true outline runs where φ = 1/2; a fixed threshold
    would keep the whole blurred edge of a high-contrast outline and grow the silhouette. ``I`` (h, w, 3)
    uint8 and the background ``B`` (h, w, 3) uint8, exposed by the frame's tone curve T (``noise``), are not
    blurred, so the edge is as sharp as the camera made it. φ is measured within ``MATTE_RADIUS_PX`` of the
    outline, on both sides; elsewhere (and where F is too close to the background to measure it) the mask
    decides, with a small magnitude so that interpolation still places the outline between pixels.
    """
    depth = disk(max(1, round(CORE_DEPTH_PX / downsample)))
    radius = max(1, round(MATTE_RADIUS_PX / downsample))
    size = (2 * radius + 1, 2 * radius + 1)
    width = mask.shape[1]
    score = cv2.LUT(mask, _MASK_SCORE)
    core = cv2.erode(mask, depth, borderType=cv2.BORDER_REPLICATE)
    outside = cv2.compare(cv2.dilate(mask, depth), 0, cv2.CMP_EQ)
    band = cv2.compare(cv2.dilate(mask, disk(radius)), cv2.erode(mask, disk(radius), borderType=cv2.BORDER_REPLICATE),
                       cv2.CMP_GT)
    index = flat_nonzero(band)  # (n,) flat indices of the pixels near the outline: np.take is the fastest gather
    I, B = np.ascontiguousarray(I), np.ascontiguousarray(B)
    # The core's colour sum and both pixel counts in one pass: sums of 8-bit integers, exact in float32.
    sums = cv2.boxFilter(cv2.merge([cv2.bitwise_and(I, I, mask=core), core, outside]), cv2.CV_32F, size,
                         normalize=False)  # (h, w, 5)
    sums = sums.ravel().take(_channel_index(index, 5))  # (5, n)
    n_core, n_outside = sums[3:] / 255.0  # (n,) pixels nearby
    # α outside, 0 elsewhere (the box of α is a strided view: a contiguous copy is faster to mask).
    alpha_outside = cv2.copyTo(np.ascontiguousarray(alpha), outside, np.zeros(alpha.shape, np.float32))
    alpha_sum = cv2.boxFilter(alpha_outside, -1, size, normalize=False)
    lam = np.where(n_outside > 0, alpha_sum.ravel().take(index) / np.maximum(n_outside, 1.0), np.float32(1.0))  # λ
    F = sums[:3] / np.maximum(n_core, 1.0)  # (3, n)
    at = _channel_index(index, 3)
    exposed = noise.expose(B.ravel().take(at))  # (3, n) T(B) at those pixels only
    phi, EE = _share(I.ravel().take(at), F, lam * exposed)
    measured = np.flatnonzero((n_core > 0) & (EE > MIN_MATTE_CONTRAST**2))
    share = phi.take(measured) - 0.5
    score.ravel()[index.take(measured)] = share
    # A block all person, or all background, needs no new measurement at full resolution.
    mixed = measured.take(np.flatnonzero(np.abs(share) < 0.5))  # (m,)
    rows, cols = np.divmod(index.take(mixed), width)
    return _Matte(score, rows, cols, F.take(mixed, axis=1), lam.take(mixed))


def _channel_index(index: np.ndarray, channels: int) -> np.ndarray:
    """(channels, ...) flat positions of the values of the pixels at flat indices ``index`` (...) of a
    contiguous (h, w, channels) image.

    Gathering single values by them (``image.ravel().take``) is several times faster than taking rows of
    ``channels`` values, and gives the channels-first layout of :func:`_dot` without a copy.
    """
    return channels * index + np.arange(channels).reshape(-1, *[1] * index.ndim)


def flat_nonzero(mask: np.ndarray) -> np.ndarray:
    """(n,) int32 flat indices of the nonzero pixels of the (h, w) uint8 ``mask``, in order: as
    ``np.flatnonzero`` at half the cost (OpenCV's scan, then the indices from its (x, y) points)."""
    points = cv2.findNonZero(mask)  # (n, 2) or (n, 1, 2) x, y by OpenCV version; None when there are none
    if points is None:
        return np.zeros(0, np.int32)
    x, y = points.reshape(-1, 2).T
    return y * np.int32(mask.shape[1]) + x


def _share(I: np.ndarray, F: np.ndarray, background: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """φ (...) of colours I (3, ...) between the person's F and the background's (both broadcast to I's
    shape), and ‖F − bg‖²; channels come first (see :func:`_dot`)."""
    E = F - background  # (3, ...)
    D = I - background
    EE = _dot(E, E)
    return _dot(D, E) / np.maximum(EE, 1e-6), EE


def _full_resolution_score(
    matte: _Matte, image: np.ndarray, background: np.ndarray, noise: _Noise, origin: tuple[int, int],
    downsample: int,
) -> np.ndarray:
    """(h ds, w ds) float32 outline score of the box at full resolution, from its working-resolution matte.

    The score is interpolated, then φ is measured again on the full-resolution pixels of every mixed
    working pixel (0 < φ < 1; ``matte.rows`` and ``matte.cols``), against that pixel's F and λ: the
    outline then follows the full-resolution edge rather than its average over ``downsample`` x
    ``downsample`` blocks. ``image`` and ``background`` (H, W, 3) uint8 are whole (flat
    gathers from them are the fastest), the box starting at full-resolution pixel ``origin`` (row, column);
    the background is exposed by the frame's tone curve (``noise``), as in the matte.
    """
    height, width = matte.score.shape
    ds = downsample
    score = cv2.resize(matte.score, (width * ds, height * ds), interpolation=cv2.INTER_LINEAR)
    dy, dx = np.divmod(np.arange(ds * ds), ds)  # (ds²,) offsets in a block
    rows = matte.rows[:, None] * ds + dy  # (m, ds²) box rows and columns of their pixels
    cols = matte.cols[:, None] * ds + dx
    # A box passing the image's far edges reads the edge pixels there; those scores are cut off with the box.
    index = (np.minimum(rows + origin[0], image.shape[0] - 1) * image.shape[1]
             + np.minimum(cols + origin[1], image.shape[1] - 1))  # (m, ds²) flat indices in the image
    at = _channel_index(index, 3)
    # Each λ repeated for its ds² pixels: broadcast along the last axis, numpy's loops would run ds² at a time.
    lam = np.repeat(matte.lam, ds * ds).reshape(-1, ds * ds)  # (m, ds²)
    lam_B = noise.expose(background.ravel().take(at)) * lam  # (3, m, ds²) λT(B)
    phi, _ = _share(image.ravel().take(at), matte.F[:, :, None], lam_B)
    score.ravel()[rows * (width * ds) + cols] = phi - 0.5
    return score


@functools.cache
def disk(radius: int) -> np.ndarray:
    """Read-only disk-shaped structuring element, built once per radius (several are used per frame)."""
    element = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    element.flags.writeable = False
    return element


def _clean_mask(mask: np.ndarray, params: SilhouetteParams, scale: int, frame_area: float) -> np.ndarray:
    """Morphology, then keep the large components, then fill the small holes.

    ``mask`` is at 1/``scale`` of the full resolution, part of a frame of ``frame_area`` pixels at that
    resolution; the radii in ``params`` are full-resolution pixels.
    """
    opening, closing = round(params.opening_px / scale), round(params.closing_px / scale)
    if opening > 0:
        mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, disk(opening))
    if closing > 0:
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, disk(closing))
    contours, hierarchy = cv2.findContours(mask, cv2.RETR_TREE, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return mask
    return _redraw(mask.shape, contours, hierarchy[0], params, frame_area)


def _redraw(
    shape: tuple[int, int], contours, hierarchy: np.ndarray, params: SilhouetteParams, frame_area: float
) -> np.ndarray:
    """The mask redrawn from its contour tree without the small components and the small holes.

    Working on contours rather than on labelled pixels costs a fraction of a millisecond. Contours are
    processed parents first, so each nested island or hole overwrites its parent's interior: even depths
    are components (drawn when large enough), odd depths are holes (erased when large enough; the hole's
    border pixels belong to the component around it and are drawn back).
    """
    # Python lists for the loops over contours (a numpy scalar costs several times a list item to read).
    parents = hierarchy[:, 3].tolist()  # (K,) index of the enclosing contour, -1 at the top
    depths = [0] * len(contours)
    for index, parent in enumerate(parents):
        while parent >= 0:
            depths[index] += 1
            parent = parents[parent]
    depth = np.array(depths)
    areas = np.array([cv2.contourArea(contour) for contour in contours])  # (K,) pixels
    is_component = depth % 2 == 0
    min_component = max(
        params.min_component_fraction * areas[is_component].max(),
        params.min_component_area_fraction * frame_area,
    )
    max_hole = params.max_hole_fraction * areas[is_component & (areas >= min_component)].sum()
    mask = np.zeros(shape, np.uint8)
    inside = [0] * len(contours)  # (K,) value of the redrawn mask inside each contour
    component, area = is_component.tolist(), areas.tolist()
    for index in np.argsort(depth, kind="stable").tolist():
        around = inside[parents[index]] if parents[index] >= 0 else 0
        inside[index] = around
        # Each contour is drawn alone: given them all, OpenCV's binding would convert every one at each call.
        contour = (contours[index],)
        if component[index] and around == 0 and area[index] >= min_component:
            cv2.drawContours(mask, contour, 0, 255, cv2.FILLED)
            inside[index] = 255
        elif not component[index] and around == 255 and area[index] >= max_hole:
            cv2.drawContours(mask, contour, 0, 0, cv2.FILLED)
            cv2.drawContours(mask, contour, 0, 255, 1)
            inside[index] = 0
    return mask
