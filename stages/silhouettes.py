"""Person silhouettes from colour images and a background model.

A pixel is foreground when it differs from the background in a way that lighting cannot explain. We
follow Horprasert, Harwood & Davis (ICCV Frame-Rate Workshop 1999): write the pixel colour I (3,) as
a brightness-scaled copy of the background colour B (3,) plus a remainder,

    I = α B + r,   α = (I · B) / (B · B)   (brightness distortion),   ‖r‖ (chromaticity distortion),

so a shadow or a change of exposure moves α (0.5 to 1.2, say) but leaves ‖r‖ small, while a person in
front of the background changes the colour direction and makes ‖r‖ large. Pixels are foreground when
‖r‖ is large, or when α is far outside the band a shadow or a highlight can produce and the colour
difference is well above the noise. Sensor noise and compression are handled by a small blur first and
by morphology and connected-component filtering after.

Everything is done with OpenCV's vectorised operations, at a reduced resolution when asked: the
per-pixel score is computed on a downsampled image (averaging also cancels noise), interpolated back
to full resolution and thresholded there, so the outline stays sub-pixel smooth.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from calib.errors import InputError

# Added to B·B before dividing, so a pure black background pixel gives α = 0 rather than a division
# by zero (8-bit squared units: far below the B·B = 3 of the darkest non-black pixel).
BACKGROUND_ENERGY_FLOOR = 1e-3
# Radius (working-resolution pixels) of the neighbourhood whose largest distortion sets the half-contrast
# threshold: wide enough to reach across a blurred edge, narrow enough not to erase faint detail nearby.
CONTRAST_WINDOW = 2
# Magnitude given to the score where the clean-up overruled the foreground test (a tenth of a threshold).
SCORE_FLOOR = 0.1


@dataclass(frozen=True)
class SilhouetteParams:
    """Thresholds of the foreground test and of the clean-up, in 8-bit intensity units and pixels.

    Attributes
    ----------
    downsample : int
        The per-pixel score is computed on an image this many times smaller in each direction (1 = full
        resolution), then interpolated back; 2 halves the cost four times over and averages noise away.
    blur_kernel_px : int
        Size of the Gaussian blur kernel (odd; at the working resolution) against sensor noise and
        compression blocks; 1 = none.
    chroma_threshold : float
        Chromaticity distortion ‖I − αB‖ above which a pixel is foreground, in 8-bit levels.
    brightness_min, brightness_max : float
        Brightness distortions α outside [min, max] are foreground (darker than any shadow, brighter
        than any highlight) provided the colour difference also exceeds ``difference_threshold``.
    difference_threshold : float
        ‖I − B‖ below which a pixel is never foreground by brightness alone (dark background pixels make
        α noisy), in 8-bit levels.
    opening_px, closing_px : int
        Radii of the morphological opening (removes specks) and closing (bridges thin gaps), at full
        resolution; 0 = skip.
    min_component_fraction : float
        Connected components smaller than this fraction of the largest one are dropped (a person is
        one large blob plus, at most, a few limbs separated by a thin gap).
    min_component_area_fraction : float
        Components smaller than this fraction of the image are dropped, so that noise alone never
        survives as a tiny "person".
    max_hole_fraction : float
        Background holes smaller than this fraction of the foreground area are filled (holes from
        clothing that matches the background); larger ones (the gap between an arm and the body) stay.
    """

    downsample: int = 2
    blur_kernel_px: int = 3
    chroma_threshold: float = 20.0
    brightness_min: float = 0.5
    brightness_max: float = 1.3
    difference_threshold: float = 30.0
    opening_px: int = 1
    closing_px: int = 2
    min_component_fraction: float = 0.05
    min_component_area_fraction: float = 2e-4
    max_hole_fraction: float = 0.01

    def __post_init__(self) -> None:
        if not (isinstance(self.downsample, int) and self.downsample >= 1):
            raise InputError(f"silhouettes.downsample: expected an integer >= 1, got {self.downsample!r}")
        if not 0 < self.brightness_min < 1 < self.brightness_max:
            raise InputError(
                "silhouettes.brightness_min/brightness_max: expected 0 < brightness_min < 1 < "
                f"brightness_max, got {self.brightness_min} and {self.brightness_max}"
            )
        kernel = self.blur_kernel_px
        if not (isinstance(kernel, int) and kernel >= 1 and kernel % 2):
            raise InputError(f"silhouettes.blur_kernel_px: expected an odd integer >= 1, got {kernel!r}")
        for name in ("chroma_threshold", "difference_threshold", "min_component_fraction",
                     "min_component_area_fraction", "max_hole_fraction", "opening_px", "closing_px"):
            if getattr(self, name) < 0:
                raise InputError(f"silhouettes.{name}: expected a value >= 0, got {getattr(self, name)}")


def median_background(images: Iterable[np.ndarray], *, max_frames: int = 31) -> np.ndarray:
    """(H, W, 3) uint8 background estimated as the per-pixel temporal median of a sequence.

    A person who moves covers any given pixel in fewer than half of the frames, so the median is the
    background there. Only ``max_frames`` frames, evenly spread over the sequence, are used: the
    median of a few dozen is as good as that of thousands and much cheaper.

    Parameters
    ----------
    images : iterable of (H, W, 3) uint8
        Frames of one camera, all the same size (a sample of the sequence is fine).
    max_frames : int
        At most this many frames enter the median.
    """
    frames = list(images)
    if not frames:
        raise InputError("median_background: expected at least one image, got none")
    shapes = {np.shape(frame) for frame in frames}
    if len(shapes) != 1:
        raise InputError(f"median_background: images of different shapes {sorted(shapes)}; expected one size")
    shape = shapes.pop()
    if len(shape) != 3 or shape[2] != 3:
        raise InputError(f"median_background: expected (H, W, 3) colour images, got shape {shape}")
    chosen = np.unique(np.linspace(0, len(frames) - 1, min(max_frames, len(frames))).round().astype(int))
    stack = np.stack([np.asarray(frames[i], dtype=np.uint8) for i in chosen])  # (F, H, W, 3)
    return np.median(stack, axis=0).round().astype(np.uint8)


def extract_silhouette(image: np.ndarray, background: np.ndarray, params: SilhouetteParams) -> np.ndarray:
    """(H, W) uint8 mask of the person, 0 = background, 255 = person.

    The foreground test, morphology and component filtering run at the working resolution
    (``params.downsample``); the cleaned mask then decides the sign of the continuous foreground score,
    which is interpolated to full resolution and thresholded there, so the outline keeps sub-pixel
    detail while the costly steps run on a quarter of the pixels.

    Parameters
    ----------
    image, background : (H, W, 3) uint8
        The frame and the background model of the same camera (colour order does not matter as long as
        both use the same one).
    params : SilhouetteParams
    """
    image = np.asarray(image)
    background = np.asarray(background)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise InputError(f"image: expected an (H, W, 3) uint8 array, got {image.dtype} {image.shape}")
    if background.shape != image.shape or background.dtype != np.uint8:
        raise InputError(
            f"background: expected a uint8 array of the image's shape {image.shape}, "
            f"got {background.dtype} {background.shape}"
        )
    height, width = image.shape[:2]
    I = _prepare(image, params.downsample, params.blur_kernel_px)
    B = _prepare(background, params.downsample, params.blur_kernel_px)
    score = _foreground_score(I, B, params)
    raw = cv2.compare(score, 0.0, cv2.CMP_GT)
    cleaned = _clean_mask(raw, params, params.downsample)
    # Where cleaning overruled the test the score takes the cleaned sign, with a small magnitude so that
    # interpolation still places the outline between pixels.
    changed = cleaned != raw
    score[changed] = np.where(cleaned[changed] > 0, SCORE_FLOOR, -SCORE_FLOOR)
    if params.downsample > 1:
        score = cv2.resize(score, (width, height), interpolation=cv2.INTER_LINEAR)
    return cv2.compare(score, 0.0, cv2.CMP_GT)


def _prepare(image: np.ndarray, factor: int, blur_kernel: int) -> np.ndarray:
    """The image averaged over factor x factor blocks and blurred, as float32.

    Both steps run on uint8, where OpenCV's fixed-point code is several times faster than on floats.
    """
    if factor > 1:
        height, width = image.shape[:2]
        size = (max(1, round(width / factor)), max(1, round(height / factor)))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    if blur_kernel > 1:
        image = cv2.GaussianBlur(image, (blur_kernel, blur_kernel), 0)
    return image.astype(np.float32)


def _foreground_score(I: np.ndarray, B: np.ndarray, params: SilhouetteParams) -> np.ndarray:
    """(h, w) float32 score, > 0 for foreground: the largest margin by which a foreground test passes.

    Each test is scaled so that 0 is its threshold. A blurred edge between the person and the
    background passes a fixed threshold well before the half-way point when the contrast is high, which
    would grow every silhouette by a pixel or two; so each threshold is also raised to half the largest
    distortion nearby (``CONTRAST_WINDOW``), which puts the outline at the half-contrast point.
    """
    channel_sum = np.ones((1, 3), np.float32)
    II = cv2.transform(cv2.multiply(I, I), channel_sum)  # (h, w) I·I
    IB = cv2.transform(cv2.multiply(I, B), channel_sum)  # (h, w) I·B
    BB = cv2.transform(cv2.multiply(B, B), channel_sum) + np.float32(BACKGROUND_ENERGY_FLOOR)  # (h, w) B·B
    difference = cv2.sqrt(np.maximum(II - 2.0 * IB + BB, np.float32(0.0)))  # (h, w) ‖I − B‖
    alpha = IB / BB  # brightness distortion α
    # ‖I − αB‖² = I·I − (I·B)² / B·B, the remainder being orthogonal to B.
    chroma = cv2.sqrt(np.maximum(II - IB * alpha, np.float32(0.0)))
    window = _disk(CONTRAST_WINDOW)
    chroma_threshold = np.maximum(np.float32(params.chroma_threshold), 0.5 * cv2.dilate(chroma, window))
    difference_threshold = np.maximum(
        np.float32(max(params.difference_threshold, 1e-6)), 0.5 * cv2.dilate(difference, window)
    )
    chroma_margin = chroma / chroma_threshold - 1.0
    brightness_margin = np.maximum(params.brightness_min - alpha, alpha - params.brightness_max)
    difference_margin = difference / difference_threshold - 1.0
    return np.maximum(chroma_margin, np.minimum(brightness_margin, difference_margin))


def _disk(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _clean_mask(mask: np.ndarray, params: SilhouetteParams, scale: int) -> np.ndarray:
    """Morphology, then keep the large components, then fill the small holes.

    ``mask`` is at 1/``scale`` of the full resolution; the radii in ``params`` are full-resolution pixels.
    """
    opening, closing = round(params.opening_px / scale), round(params.closing_px / scale)
    if opening > 0:
        mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, _disk(opening))
    if closing > 0:
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, _disk(closing))
    contours, hierarchy = cv2.findContours(mask, cv2.RETR_TREE, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return mask
    return _redraw(mask.shape, contours, hierarchy[0], params)


def _redraw(shape: tuple[int, int], contours, hierarchy: np.ndarray, params: SilhouetteParams) -> np.ndarray:
    """The mask redrawn from its contour tree without the small components and the small holes.

    Working on contours rather than on labelled pixels costs a fraction of a millisecond. Contours are
    processed parents first, so each nested island or hole overwrites its parent's interior: even depths
    are components (drawn when large enough), odd depths are holes (erased when large enough; the hole's
    border pixels belong to the component around it and are drawn back).
    """
    parents = hierarchy[:, 3]  # (K,) index of the enclosing contour, -1 at the top
    depth = np.zeros(len(contours), int)
    for index in range(len(contours)):
        parent = parents[index]
        while parent >= 0:
            depth[index] += 1
            parent = parents[parent]
    areas = np.array([cv2.contourArea(contour) for contour in contours])  # (K,) pixels
    is_component = depth % 2 == 0
    min_component = max(
        params.min_component_fraction * areas[is_component].max(),
        params.min_component_area_fraction * shape[0] * shape[1],
    )
    max_hole = params.max_hole_fraction * areas[is_component & (areas >= min_component)].sum()
    mask = np.zeros(shape, np.uint8)
    inside = np.zeros(len(contours), np.uint8)  # (K,) value of the redrawn mask inside each contour
    for index in np.argsort(depth, kind="stable"):
        around = inside[parents[index]] if parents[index] >= 0 else 0
        inside[index] = around
        if is_component[index] and around == 0 and areas[index] >= min_component:
            cv2.drawContours(mask, contours, index, 255, cv2.FILLED)
            inside[index] = 255
        elif not is_component[index] and around == 255 and areas[index] >= max_hole:
            cv2.drawContours(mask, contours, index, 0, cv2.FILLED)
            cv2.drawContours(mask, contours, index, 255, 1)
            inside[index] = 0
    return mask
