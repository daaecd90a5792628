"""Per-view evidence: the background model, the frame's exposure and noise, and how far each pixel
differs from the background in units of the noise (the colour model of the package's docstring).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from calib.errors import InputError
from stages.checks import check_number
from stages.silhouettes.params import SilhouetteParams

# Added to B·B before dividing, so a pure black background pixel gives α = 0 rather than a division
# by zero (8-bit squared units: far below the B·B = 3 of the darkest non-black pixel).
BACKGROUND_ENERGY_FLOOR = 1e-3
# Every SAMPLE_STRIDE-th pixel along both axes enters the exposure and noise estimates: a few thousand
# pixels fix a median or a quartile to well under a percent, at a sixteenth of the cost.
SAMPLE_STRIDE = 4
# The 25th percentile of a χ² variable with 3 degrees of freedom: ‖I − T(B)‖² / σ² of background pixels
# under Gaussian noise of σ per channel, so σ² = (lower quartile of ‖I − T(B)‖²) / this.
CHI2_3_LOWER_QUARTILE = 1.2125
# Bounds on the per-channel noise σ (8-bit levels). Below: 8-bit quantisation, after blur and averaging,
# is still about this much. Above: heavier than any usable camera's noise; a larger lower quartile means
# the person (or a change of lighting) covers most of the image, and the quartile is no longer noise.
NOISE_SIGMA_MIN = 0.5
NOISE_SIGMA_MAX = 6.0
# Fewest sampled pixels that differ from the background for a noise estimate; with fewer, or fewer than half
# of the sample, the frame is mostly an exact copy of the background (a still scene from a video codec, a
# noiseless render) and its noise is the lower bound: what differs is then mostly the person, not noise.
MIN_NOISE_SAMPLES = 100
# The search for the person looks at blocks of COARSE_FACTOR x COARSE_FACTOR working pixels (a sixteenth of
# the cost), then works on the box around what it found plus COARSE_MARGIN blocks (parts of the person too
# faint to show on blocks lie next to parts that do).
COARSE_FACTOR = 4
COARSE_MARGIN = 3
# Bounds on each channel's exposure ratio between frame and background: drift, white balance and codec
# level shifts stay well inside; outside, the median is not the background's (a person filling the view)
# and is not trusted.
EXPOSURE_RATIO_RANGE = (0.7, 1.4)
# The tone curve T_k may also shift a level by this much (8-bit levels) beyond those ratios: a black level
# or haze adds an offset, which a ratio alone would bound tightly in the darkest levels.
TONE_SHIFT_MAX = 24.0
# The tone curve is fitted on background levels binned this wide (8-bit levels): 16 bins, across which a
# camera's tone curve is close to linear, each with hundreds of samples where the room has that colour.
TONE_BIN_LEVELS = 16
# Fewest sampled pixels in a bin for its median or mean to enter the tone curve; sparser bins are
# interpolated from their neighbours.
MIN_TONE_SAMPLES = 20
# cv2.transform's matrix summing the three channels of each pixel.
CHANNEL_SUM = np.ones((1, 3), np.float32)
# A tone curve with no variance of its own (one ratio per channel, :func:`_ratio_tone`; :class:`_Noise`).
_NO_TONE_VARIANCE = np.zeros((256, 1, 3), np.float32)


@dataclass(frozen=True, eq=False)
class BackgroundModel:
    """One camera's background at the working resolution, with what every frame needs from it.

    Built by :func:`background_model`; pass it to :func:`extract_silhouette` instead of the background
    image to do this work once per camera rather than once per frame.
    """

    shape: tuple[int, int, int]  # (H, W, 3) of the full-resolution images
    downsample: int
    blur_kernel_px: int
    image: np.ndarray  # (H, W, 3) uint8 the background itself
    B: np.ndarray  # (h, w, 3) uint8 background colours at the working resolution, blurred
    B_sharp: np.ndarray  # (h, w, 3) uint8 the same before the blur
    texture_variance: np.ndarray  # (h, w) float32 (κ ‖∇B‖)² / 3, per-channel noise variance from texture
    # Colours below are stored channels first, as :func:`_dot` wants them (a copy saved per frame).
    sample_B: np.ndarray  # (3, m) float32 every SAMPLE_STRIDE-th pixel of B_sharp along both axes, flattened
    sample_B2: np.ndarray  # (3, m) float32 their squares B_k²
    sample_divisor: np.ndarray  # (m,) float32 B·B + BACKGROUND_ENERGY_FLOOR there
    sample_levels: np.ndarray  # (3, m) intp their 8-bit levels, channel k's numbered from k × 256
    sample_keys: np.ndarray  # (3, m) intp 256 × their tone-curve bins (channel k's from k × the bins per channel)
    sample_bins: tuple[np.ndarray, np.ndarray]  # :func:`_bin_levels` of the whole sample, the same every frame
    # (3, h / COARSE_FACTOR, w / COARSE_FACTOR) intp B_sharp averaged over blocks and rounded to 8-bit levels,
    # channel k's numbered from k × 256 (as sample_levels)
    coarse_levels: np.ndarray
    coarse_texture_variance: np.ndarray  # (h / COARSE_FACTOR, w / COARSE_FACTOR) float32 the same for the texture
    noise_floor: float  # σ (8-bit levels) below which a frame's noise estimate is not believed
    tone_curve: bool  # whether a frame's tone curve is fitted (else one exposure ratio per channel)


def background_model(background: np.ndarray, params: SilhouetteParams, *,
                     noise_floor: float = NOISE_SIGMA_MIN, tone_curve: bool = True) -> BackgroundModel:
    """The per-camera part of :func:`extract_silhouette`, for a background (H, W, 3) uint8.

    ``noise_floor`` is the lowest noise σ (8-bit levels, at the working resolution) a frame's estimate may
    give: by default the quantisation's; a background estimated from the frames themselves knows how much
    they scatter about it (:func:`stages.background.sample_camera`), where a single frame's estimate, made
    on the pixels that match the background best, may see less than the frames' codec leaves near the person.

    ``tone_curve`` False keeps each frame's exposure to one ratio per channel (see :func:`_noise`): for a
    background estimated from the frames themselves, whose tone is theirs by construction and whose levels
    may hold what remains of a subject who stood still, which a tone curve would learn as the room's.
    """
    background = np.asarray(background)
    if background.ndim != 3 or background.shape[2] != 3 or background.dtype != np.uint8:
        raise InputError(f"background: expected an (H, W, 3) uint8 array, got {background.dtype} {background.shape}")
    check_number("background noise floor", noise_floor, NOISE_SIGMA_MIN, NOISE_SIGMA_MAX)
    B_sharp = _downsample(background, params.downsample)
    B = _blur(B_sharp, params.blur_kernel_px)  # (h, w, 3) uint8
    # A shift of the background by κ pixels changes a pixel by about κ times the gradient, which the
    # range of each channel over the 3x3 neighbourhood (two pixels across) measures twice over.
    spread = cv2.morphologyEx(B, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8))  # (h, w, 3) uint8
    squared_gradient = cv2.transform(cv2.multiply(spread, spread, dtype=cv2.CV_32F), CHANNEL_SUM) / 4.0
    jitter = params.background_jitter_px
    texture_variance = squared_gradient * np.float32(jitter * jitter / 3.0)
    sample_B = _channels_first(B_sharp[::SAMPLE_STRIDE, ::SAMPLE_STRIDE]).reshape(3, -1)  # the frame's is unblurred
    sample_levels = _flat_levels(sample_B)
    return BackgroundModel(
        shape=background.shape,
        downsample=params.downsample,
        blur_kernel_px=params.blur_kernel_px,
        image=background,
        B=B,
        B_sharp=B_sharp,
        texture_variance=texture_variance,
        sample_B=sample_B,
        sample_B2=sample_B * sample_B,
        sample_divisor=_dot(sample_B, sample_B) + np.float32(BACKGROUND_ENERGY_FLOOR),
        sample_levels=sample_levels,
        sample_keys=256 * (sample_levels // TONE_BIN_LEVELS),
        sample_bins=_bin_levels(sample_levels),
        coarse_levels=_flat_levels(_channels_first(_block_mean(B_sharp, COARSE_FACTOR)).round()),
        coarse_texture_variance=_block_mean(texture_variance, COARSE_FACTOR),
        noise_floor=float(noise_floor),
        tone_curve=bool(tone_curve),
    )


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


@dataclass(frozen=True, eq=False)
class Evidence:
    """One view's frame after the per-pixel test, before its shadows are settled.

    Made by :func:`measure_evidence`; :func:`floor_shadows` reads every view's to decide which shadow-like
    pixels are shadows, and :func:`silhouette_from_evidence` then makes the mask. Maps cover ``region``
    of the working-resolution frame only (None: nothing differs from the background anywhere).
    """

    image: np.ndarray  # (H, W, 3) uint8 the frame
    model: BackgroundModel
    I_sharp: np.ndarray  # (h, w, 3) uint8 the frame at the working resolution
    noise: _Noise
    region: tuple[slice, slice] | None
    difference2: np.ndarray  # (h', w') float32 ‖I − T(B)‖² in noise variances
    chroma2: np.ndarray  # (h', w') float32 ‖I − αT(B)‖² in noise variances (the colour direction's change)
    alpha: np.ndarray  # (h', w') float32 α = I·T(B) / T(B)·T(B), 1 on the background
    shadow_like: np.ndarray  # (h', w') bool above the weak threshold, but as a shadow would be

    def darkening(self) -> np.ndarray:
        """(h', w') float32 1 − α, how much darker than the background each pixel is (< 0: brighter)."""
        return 1.0 - self.alpha


def measure_evidence(image: np.ndarray, background: np.ndarray | BackgroundModel, params: SilhouetteParams) -> Evidence:
    """The per-pixel foreground test of one view (see the module's docstring), shadows not yet settled.

    The exposure ratio and the noise level come from a sparse sample of the frame; blocks of
    ``COARSE_FACTOR`` x ``COARSE_FACTOR`` working pixels show where the person may be, and the evidence
    is measured there only.

    Parameters
    ----------
    image : (H, W, 3) uint8
        The frame.
    background : (H, W, 3) uint8 or BackgroundModel
        The background of the same camera (colour order does not matter as long as both use the same
        one), or its :func:`background_model` built with the same ``params``.
    params : SilhouetteParams
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise InputError(f"image: expected an (H, W, 3) uint8 array, got {image.dtype} {image.shape}")
    if not isinstance(background, BackgroundModel):
        background = np.asarray(background)
        if background.shape != image.shape or background.dtype != np.uint8:
            raise InputError(
                f"background: expected a uint8 array of the image's shape {image.shape}, "
                f"got {background.dtype} {background.shape}"
            )
        background = background_model(background, params)
    elif background.shape != image.shape:
        raise InputError(f"background: model of {background.shape} images, expected the image's {image.shape}")
    elif (background.downsample, background.blur_kernel_px) != (params.downsample, params.blur_kernel_px):
        raise InputError("background: model built with another downsample/blur_kernel_px than params")
    I_sharp = _downsample(image, params.downsample)
    noise = _noise(I_sharp[::SAMPLE_STRIDE, ::SAMPLE_STRIDE], background)
    region = _person_region(I_sharp, background, noise, params)
    if region is None:
        empty = np.zeros((0, 0), np.float32)
        return Evidence(image, background, I_sharp, noise, None, empty, empty, empty, empty.astype(bool))
    difference2, chroma2, alpha = _evidence(_blur(I_sharp[region], params.blur_kernel_px), background, region, noise)
    weak2 = np.float32(params.weak_threshold**2)
    shadow_like = ((difference2 > weak2) & (chroma2 <= weak2)
                   & (alpha >= np.float32(params.shadow_min)) & (alpha <= np.float32(params.shadow_max)))
    return Evidence(image, background, I_sharp, noise, region, difference2, chroma2, alpha, shadow_like)


def _downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """The uint8 image averaged over factor x factor blocks (OpenCV's fixed-point code: fast on uint8)."""
    if factor == 1:
        return image
    height, width = _working_shape(image.shape[1::-1], factor)
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


def _working_shape(size: tuple[int, int], factor: int) -> tuple[int, int]:
    """(h, w) of the working-resolution frame of a ``size`` (width, height) image downsampled by ``factor``."""
    return max(1, round(size[1] / factor)), max(1, round(size[0] / factor))


def _block_mean(image: np.ndarray, factor: int) -> np.ndarray:
    """``image`` averaged over factor x factor blocks, a partial block at the far edges left out.

    A power of two is reached by halving again and again: OpenCV's area averaging has a fast path for
    halving only, and three halvings of a 780 x 580 frame cost a third of one reduction by 8.
    """
    while factor > 1:
        step = 2 if factor % 2 == 0 else factor
        rows, cols = image.shape[0] // step, image.shape[1] // step
        image = cv2.resize(image[: rows * step, : cols * step], (cols, rows), interpolation=cv2.INTER_AREA)
        factor //= step
    return image


def _blur(image: np.ndarray, blur_kernel: int) -> np.ndarray:
    """The uint8 image blurred against noise (on uint8, where OpenCV's fixed-point code is fast)."""
    if blur_kernel > 1:
        return cv2.GaussianBlur(image, (blur_kernel, blur_kernel), 0)
    return image


@dataclass(frozen=True, eq=False)
class _Noise:
    tone: np.ndarray  # (3, 256) float32 T_k(b), the frame's expected level of channel k where the background's is b
    sigma2: float  # σ², the per-channel noise variance (8-bit levels squared)
    # (256, 1, 3) float32 the variance of T_k(b) itself, a table for cv2.LUT: 0 where the frame's background has
    # level b, growing where T_k is extrapolated (:func:`_tone_curve`)
    tone_variance: np.ndarray

    def expose(self, B: np.ndarray) -> np.ndarray:
        """(3, ...) float32 T(B) of 8-bit background levels B (3, ...), channels first (see :func:`_dot`)."""
        return _look_up(self.tone, B)

    def expose_levels(self, levels: np.ndarray) -> np.ndarray:
        """(3, ...) float32 T(B) of background levels already numbered by :func:`_flat_levels` (the model's)."""
        return _toned(self.tone, levels)

    def expose_image(self, B: np.ndarray) -> np.ndarray:
        """(h, w, 3) float32 T(B) of a background image (h, w, 3) uint8 (OpenCV's table look-up)."""
        return cv2.LUT(B, self.tone.T.reshape(256, 1, 3))


def _noise(I: np.ndarray, model: BackgroundModel) -> _Noise:
    """The frame's tone curve and noise level, from a sample ``I`` (every SAMPLE_STRIDE-th pixel).

    Each channel's tone curve T_k is first the median frame level per background level (binned,
    :func:`_tone_curve`): the person covers less than half of the pixels of each background level, so the
    median is the background's. The half of the sample closest to T(B) is then surely background, and T_k
    is fitted again on it by means, which scatter less than medians of 8-bit levels. A tone curve, not a
    ratio per channel: a camera's automatic exposure acts before its gamma, a codec or a grabber may lift the
    black level, and a ratio that fits the room's most common tone (a floor) misses the others (a bright
    wall) by more than the noise, all over the image. σ² is the lower quartile of ‖I − T(B)‖² over χ²₃'s, on
    the pixels that are not exact copies of the background, clipped to a plausible range (see the
    constants; from below by the model's ``noise_floor``).
    """
    levels = np.ascontiguousarray(I.transpose(2, 0, 1)).reshape(3, -1)  # (3, m) uint8
    I = levels.astype(np.float32)
    B = model.sample_B
    tone_variance = _NO_TONE_VARIANCE
    if model.tone_curve:
        keys = model.sample_keys + levels  # (3, m) each pixel's bin and frame level, as one index of the histogram
        first, _ = _tone_curve(keys, model, median=True)
        tone, spread = _tone_curve(keys, model, np.flatnonzero(_closest_half(I, _toned(first, model.sample_levels))),
                                   median=False)
        tone_variance = np.ascontiguousarray((spread * spread).T.reshape(256, 1, 3))
    else:
        tone = _ratio_tone(I, model)
    D = I - _toned(tone, model.sample_levels)
    distance2 = _dot(D, D)
    # A pixel equal to the background in every channel is a copy, not a noisy measurement of it: a video
    # codec repeats static blocks from frame to frame, so a background taken from the same video (a
    # temporal median, or a plate cut from it) matches them exactly, while the blocks it encodes again,
    # around the moving person, carry the codec's noise. Only the others tell the noise level.
    measured = np.flatnonzero((I != B).any(axis=0))
    if len(measured) < max(MIN_NOISE_SAMPLES, len(distance2) // 2):
        return _Noise(tone, model.noise_floor**2, tone_variance)
    quartile = _quantile(distance2.take(measured), 0.25)
    return _Noise(tone, min(max(quartile / CHI2_3_LOWER_QUARTILE, model.noise_floor**2), NOISE_SIGMA_MAX**2),
                  tone_variance)


# Offsets of each channel's 256 levels in a flattened (3, 256) tone curve.
_CHANNEL_OFFSETS = np.arange(3) * 256
_LEVELS = np.arange(256, dtype=np.float64)
_BINS_PER_CHANNEL = 256 // TONE_BIN_LEVELS
# Each tone-curve bin's background levels, one row per bin of the three channels: (3 × bins, TONE_BIN_LEVELS).
_BINNED_LEVELS = np.tile(_LEVELS.reshape(_BINS_PER_CHANNEL, TONE_BIN_LEVELS), (3, 1))
# Bounds on T_k(b) (256,): EXPOSURE_RATIO_RANGE times b, widened by TONE_SHIFT_MAX levels either way.
_LOWEST_TONE = EXPOSURE_RATIO_RANGE[0] * _LEVELS - TONE_SHIFT_MAX
_HIGHEST_TONE = EXPOSURE_RATIO_RANGE[1] * _LEVELS + TONE_SHIFT_MAX


def _bin_levels(levels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(count, level)`` (3 × bins,) of background levels ``levels`` (3, m) intp (channel k's numbered from
    k × 256): how many fall in each tone-curve bin (int) and their mean there (float; 0 in an empty bin)."""
    background = np.bincount(levels.ravel(), minlength=3 * 256).reshape(-1, TONE_BIN_LEVELS)
    count = background.sum(axis=1)
    return count, (background * _BINNED_LEVELS).sum(axis=1) / np.maximum(count, 1.0)


def _tone_curve(keys: np.ndarray, model: BackgroundModel, chosen: np.ndarray | None = None, *,
                median: bool) -> tuple[np.ndarray, np.ndarray]:
    """(3, 256) float32 each channel's tone curve T_k(b) and its uncertainty (a standard deviation, 8-bit levels).

    T_k is the frame's median (``median``) or mean level I_k over the ``chosen`` pixels (indices into the
    sample; None: all) whose background level B_k falls in each bin, joined linearly between the bins' mean
    background levels and made non-decreasing; it is known there (uncertainty 0).

    ``keys`` (3, m) intp holds the sample's 8-bit levels plus ``model.sample_keys`` (made once for both fits
    of a frame), ``model`` the background's levels at the same pixels. Both are counted into histograms of
    integer levels per bin, from which the medians, means and counts follow exactly (sums of 8-bit levels
    are exact in floating point).

    Below the first bin with ``MIN_TONE_SAMPLES``, T_k(b) is b times the ratio there: a change of exposure keeps
    black black. Above the last lie bright levels that few pixels of the room have (a white skirting board, a
    window frame), where two readings of the bins fit: a gain (b times the ratio at the last bin: exposure,
    white balance) and the curve's own course (its slope between the last two bins: exposure moved before the
    camera's gamma, a lifted black level). T_k(b) is their mean there and their difference its uncertainty,
    which the evidence adds to the noise (:func:`_evidence`): where they agree nothing changes, and where they
    part, a level that either explains, or that lies a little beyond both (the course is a secant, and a bending
    curve runs past it), is not taken for the person. The gain alone misses a skirting board by more than the
    noise after such a change of exposure, and puts it in the mask with the person it touches. (At the dark end
    the two readings part on unchanged frames too, where the first bins are few and far apart, and an
    uncertainty there would cost the contrast of dark clothing in front of a dark poster.) A channel with one such
    bin has the gain alone, one with none T_k(b) = b. T_k(b) stays within ``EXPOSURE_RATIO_RANGE`` of b widened by
    ``TONE_SHIFT_MAX`` levels either way.
    """
    if chosen is None:
        count, level = model.sample_bins
    else:
        # Flat gathers of the three channels at once (faster than takes along an axis).
        at = chosen + (np.arange(3) * keys.shape[1])[:, None]
        keys = keys.ravel().take(at)
        count, level = _bin_levels(model.sample_levels.ravel().take(at))
    histogram = np.bincount(keys.ravel(), minlength=len(count) * 256)  # the frame's levels, bin after bin
    if median:
        frame = _bin_medians(histogram, count)
    else:
        frame = (histogram.reshape(-1, 256) @ _LEVELS) / np.maximum(count, 1.0)
    filled = (count >= MIN_TONE_SAMPLES).reshape(3, -1)
    level, frame = level.reshape(3, -1), frame.reshape(3, -1)
    tone = np.repeat(_LEVELS[None], 3, axis=0)
    spread = np.zeros_like(tone)
    for k in np.flatnonzero(filled.any(axis=1)).tolist():
        levels, means = level[k, filled[k]], np.maximum.accumulate(frame[k, filled[k]])
        tone[k] = np.interp(_LEVELS, levels, means)
        # The levels below the first bin's mean and above the last's: ends of the ascending _LEVELS.
        low, high = math.ceil(levels[0]), math.floor(levels[-1]) + 1
        tone[k, :low] = _LEVELS[:low] * (means[0] / max(levels[0], 1.0))
        gain = _LEVELS[high:] * (means[-1] / max(levels[-1], 1.0))
        if len(levels) < 2:
            tone[k, high:] = gain
            continue
        slope = (means[-1] - means[-2]) / (levels[-1] - levels[-2])
        course = means[-1] + np.clip(slope, *EXPOSURE_RATIO_RANGE) * (_LEVELS[high:] - levels[-1])
        tone[k, high:] = 0.5 * (gain + course)
        spread[k, high:] = np.abs(gain - course)
    return np.clip(tone, _LOWEST_TONE, _HIGHEST_TONE).astype(np.float32), spread.astype(np.float32)


def _bin_medians(histogram: np.ndarray, count: np.ndarray) -> np.ndarray:
    """(bins,) float64 the median level of each bin's ``histogram`` (bins × 256,) int of 8-bit levels, whose
    rows hold ``count`` (bins,) int levels: the number of levels whose running count stays below half the bin's.

    One running count over all the bins, searched for each bin's half: a search per bin rather than a
    comparison per level. A level's running count stays below half of its bin's exactly when it is below
    the counts of the bins before plus the half rounded up (counts are integers); an empty bin gives 0.
    """
    running = np.cumsum(histogram)
    before = running[255::256] - count  # (bins,) levels in the bins before each
    first = np.arange(len(count)) * 256
    below = np.searchsorted(running, before + (count + 1) // 2, side="left") - first
    return np.clip(below, 0, 255).astype(np.float64)


def _ratio_tone(I: np.ndarray, model: BackgroundModel) -> np.ndarray:
    """(3, 256) float32 the tone curve T_k(b) = g_k b of one exposure ratio per channel, from the sample ``I`` (3, m).

    First one ratio for all channels, g = the median of α = I·B / B·B (the person covers less than half of
    the image); the half of the sample closest to gB is then surely background, and on it each channel's
    ratio is the least-squares g_k = Σ I_k B_k / Σ B_k², within ``EXPOSURE_RATIO_RANGE``. Medians of
    per-channel ratios would be pulled by the person's colour, each channel its own way, and tint the model.
    """
    B = model.sample_B
    products = I * B  # (3, m) I_k B_k
    alpha = (products[0] + products[1] + products[2]) / model.sample_divisor
    g = np.float32(np.clip(_quantile(alpha, 0.5), *EXPOSURE_RATIO_RANGE))
    background = _closest_half(I, g * B).astype(np.float32)
    # Sums over the background half as products with its 0/1 indicator: a fraction of boolean indexing's cost.
    IB, BB = products @ background, model.sample_B2 @ background
    gains = np.where(BB > 0, np.clip(IB / np.maximum(BB, 1e-12), *EXPOSURE_RATIO_RANGE), g)
    return (gains[:, None] * _LEVELS).astype(np.float32)


def _closest_half(I: np.ndarray, expected: np.ndarray) -> np.ndarray:
    """(m,) bool True for the half of the sample ``I`` (3, m) closest to its ``expected`` background colours (3, m):
    the person covers less than half of the image, so that half is surely background."""
    D = I - expected
    distance2 = _dot(D, D)
    return distance2 <= np.float32(_quantile(distance2, 0.5))


def _look_up(tone: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(3, ...) float32 T(B) of 8-bit background levels B (3, ...), channels first (see :func:`_dot`)."""
    return _toned(tone, _flat_levels(B))


def _toned(tone: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """(3, ...) float32 the tone curve ``tone`` (3, 256) read at background ``levels`` (3, ...) numbered by
    :func:`_flat_levels`."""
    return tone.ravel().take(levels)


def _flat_levels(B: np.ndarray) -> np.ndarray:
    """(3, ...) intp the 8-bit levels B (3, ...) as positions in a flattened (3, 256) tone curve, channel k's
    numbered from k × 256: a background's are made once, and each frame's tone curve is read at them."""
    return B.astype(np.intp) + _CHANNEL_OFFSETS.reshape(3, *[1] * (B.ndim - 1))


def _person_region(
    I: np.ndarray, model: BackgroundModel, noise: _Noise, params: SilhouetteParams
) -> tuple[slice, slice] | None:
    """The part of the working-resolution frame ``I`` (h, w, 3) uint8 worth a close look, or None.

    On blocks of COARSE_FACTOR x COARSE_FACTOR working pixels, ‖I − T(B)‖² is compared with the weak
    threshold at the working resolution's noise (averaging only lowers the noise, so this errs towards
    looking); the answer is the box around every block that passes, with a margin of COARSE_MARGIN
    blocks for the parts of the person too faint to show on blocks.
    """
    D = _channels_first(_block_mean(I, COARSE_FACTOR)) - noise.expose_levels(model.coarse_levels)
    difference2 = _dot(D, D)
    passing = cv2.compare(difference2, params.weak_threshold**2 * (model.coarse_texture_variance + noise.sigma2),
                          cv2.CMP_GT)
    x, y, w, h = cv2.boundingRect(passing)
    if w == 0:
        return None
    return _span(y, h, I.shape[0]), _span(x, w, I.shape[1])


def _span(start: int, length: int, size: int) -> slice:
    """Blocks [start, start + length) grown by COARSE_MARGIN, as working pixels of an axis of ``size``
    (a margin reaching the last, partial block takes it in)."""
    return slice(max((start - COARSE_MARGIN) * COARSE_FACTOR, 0),
                 min((start + length + COARSE_MARGIN) * COARSE_FACTOR, size))


def _evidence(
    I: np.ndarray, model: BackgroundModel, region: tuple[slice, slice], noise: _Noise
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """‖I − T(B)‖² and ‖I − αT(B)‖² per pixel of ``region``, in noise variances, and the brightness distortion α.

    ``I`` (h', w', 3) uint8 is the region. With α = I·T(B) / T(B)·T(B), the chromaticity distortion is
    ‖I − αT(B)‖² = I·I − α I·T(B) (the remainder orthogonal to T(B)) and ‖I − T(B)‖² = I·I − 2 I·T(B) + T(B)·T(B).
    """
    exposed = noise.expose_image(model.B[region])  # (h', w', 3) float32 T(B)
    # Converted once: OpenCV's products of uint8 and float32 convert on every call, at three times the
    # cost of float32 products. The products are the same to the bit: an 8-bit level times a float32 is
    # exact in double precision, so either way it is rounded to float32 once.
    I = I.astype(np.float32)
    II = cv2.transform(cv2.multiply(I, I), CHANNEL_SUM)  # (h', w') I·I
    IB = cv2.transform(cv2.multiply(I, exposed), CHANNEL_SUM)  # (h', w') I·T(B)
    BB = cv2.transform(cv2.multiply(exposed, exposed), CHANNEL_SUM)  # (h', w') T(B)·T(B)
    alpha = cv2.divide(IB, BB + np.float32(BACKGROUND_ENERGY_FLOOR))  # (h', w') α
    chroma2 = cv2.subtract(II, cv2.multiply(IB, alpha))  # (h', w') ‖I − αT(B)‖² (≥ 0 up to rounding)
    difference2 = cv2.add(cv2.addWeighted(II, 1.0, IB, -2.0, 0.0), BB)  # ‖I − T(B)‖²
    # T(B)'s own variance, the mean of the channels' (the evidence counts per-channel noise variances)
    tone_variance = cv2.transform(cv2.LUT(model.B[region], noise.tone_variance), CHANNEL_SUM / 3.0)
    variance = cv2.add(model.texture_variance[region], tone_variance) + np.float32(noise.sigma2)
    return cv2.divide(difference2, variance), cv2.divide(chroma2, variance), alpha


def _quantile(values: np.ndarray, q: float) -> float:
    """The ``q`` quantile of ``values`` by partial sorting (a few times faster than ``np.median``)."""
    flat = values.ravel()
    k = min(int(q * flat.size), flat.size - 1)
    return float(np.partition(flat, k)[k])


def _channels_first(image: np.ndarray) -> np.ndarray:
    """(3, h, w) float32 copy of an (h, w, 3) image, in one pass (the layout :func:`_dot` is fastest on)."""
    return np.ascontiguousarray(image.transpose(2, 0, 1), dtype=np.float32)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a · b (...) over the first axis of a and b (3, ...), summed channel by channel.

    On a few thousand pixels this is a few times faster than ``np.einsum`` over a last axis of 3, which
    calls its inner loop once per pixel; it adds the products in the same order, so the result is the same
    to the bit.
    """
    dot = a[0] * b[0]
    dot += a[1] * b[1]
    dot += a[2] * b[2]
    return dot
