"""Each camera's sampled frames: how many, at which resolution, their plain median, where it is contested,
and how much they scatter about it (the first step of :mod:`stages.background`)."""

from __future__ import annotations

import functools
from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from calib.errors import InputError
from stages.silhouettes import CHANNEL_SUM, NOISE_SIGMA_MAX, NOISE_SIGMA_MIN, SAMPLE_STRIDE

#: Frames sampled per camera, spread over the whole sequence: every pixel the subject leaves for a few
#: tenths of the sequence then has a handful of bare samples.
MAX_SAMPLES = 48
#: Upper bound on the bytes of one camera's full-resolution samples held at once (K x H x W x 3): a
#: 780 x 580 camera gets MAX_SAMPLES samples, a 1920 x 1080 one 32.
SAMPLE_BYTES = 200 * 2**20
#: Fewest samples taken whatever the image size: fewer make a noisy median.
MIN_SAMPLES = 9
#: The working resolution of the silhouettes and hulls has about this many pixels (about 280 x 210): the
#: subject is still a few dozen pixels wide, and a sample's silhouettes cost a millisecond or two.
WORKING_PIXELS = 60_000
#: The plain median gives the background at a pixel where at most this share of the samples differ from
#: it: a fifth of outliers, all on one side, move a median by a third of the noise.
CONTESTED_SHARE = 0.2
#: A sample differs from the median where the sum of its channels' absolute differences exceeds this
#: many times the camera's typical one (the median over all pixels and samples, which is noise: the subject
#: covers a small part of a frame): about five noise standard deviations.
DEVIATION_FACTOR = 4.0
# The samples' scatter is measured on at most about this many of them (each gives thousands of pixels).
SCATTER_SAMPLES = 12
# The median of a χ² variable with 3 degrees of freedom: ‖I − B‖² / σ² of background pixels under Gaussian
# noise of σ per channel.
CHI2_3_MEDIAN = 2.366


@dataclass(frozen=True, eq=False)
class CameraSamples:
    """What the estimate keeps of one camera's sampled frames (made by :func:`sample_camera`).

    Attributes
    ----------
    shape : (H, W, 3) of the full-resolution frames.
    median : (H, W, 3) uint8
        The samples' plain per-channel median, or the clean plate when one is given.
    small : (K, h, w, 3) uint8
        The samples at the working resolution.
    contested : (P,) int64
        Flat indices of the full-resolution pixels where the plain median is contested (empty with a plate).
    contested_values : (K, P, 3) uint8
        The samples at those pixels.
    plate : bool
        Whether ``median`` is a clean plate: the background is then given, not estimated.
    noise : float or None
        How much the samples scatter about the median (σ per channel, 8-bit levels) at the silhouette
        stage's working resolution (:func:`_scatter`); None with a plate.
    """

    shape: tuple[int, int, int]
    median: np.ndarray
    small: np.ndarray
    contested: np.ndarray
    contested_values: np.ndarray
    plate: bool
    noise: float | None


def sample_count(frames: int, shape: tuple[int, ...]) -> int:
    """How many of a sequence's ``frames`` to sample for images of ``shape`` (H, W, 3)."""
    frame_bytes = int(np.prod(shape))
    return max(min(frames, MIN_SAMPLES), min(frames, MAX_SAMPLES, SAMPLE_BYTES // max(frame_bytes, 1)))


def working_size(size: tuple[int, int]) -> tuple[int, int]:
    """(w, h) of the working resolution for images of ``size`` (W, H): about WORKING_PIXELS pixels,
    reduced by a whole factor (never enlarged)."""
    width, height = size
    factor = max(1, int(np.ceil(np.sqrt(width * height / WORKING_PIXELS))))
    return max(1, round(width / factor)), max(1, round(height / factor))


def sample_camera(frames: Iterable[np.ndarray], size: tuple[int, int], *, plate: np.ndarray | None = None,
                  downsample: int = 2) -> CameraSamples:
    """One camera's :class:`CameraSamples` from its sampled ``frames`` ((H, W, 3) uint8 each).

    Parameters
    ----------
    frames : iterable of (H, W, 3) uint8
        The samples, all of one size; held together (one camera at a time).
    size : (w, h)
        The working resolution (:func:`working_size`).
    plate : (H, W, 3) uint8 or None
        The camera's clean plate, if any: its background is then the plate, and only the working copies of
        the samples are kept (its silhouettes still vote in every sample's hull).
    downsample : int
        The silhouette stage's working resolution (``SilhouetteParams.downsample``), at which the samples'
        scatter is measured.
    """
    stack = _stack(frames)
    small = np.stack([cv2.resize(frame, size, interpolation=cv2.INTER_AREA) for frame in stack])
    if plate is not None:
        plate = np.asarray(plate)
        if plate.shape != stack.shape[1:] or plate.dtype != np.uint8:
            raise InputError(f"clean plate: expected a uint8 image of the frames' shape {stack.shape[1:]}, "
                             f"got {plate.dtype} {plate.shape}")
        return CameraSamples(stack.shape[1:], plate, small, np.zeros(0, np.int64),
                             np.zeros((len(stack), 0, 3), np.uint8), True, None)
    median = plain_median(stack)
    # (K, H, W) uint8 each sample's L1 distance to the median, saturated at 255 (far above the thresholds).
    deviation = np.stack([cv2.transform(cv2.absdiff(frame, median), CHANNEL_SUM) for frame in stack])
    typical = float(np.median(deviation[:, ::4, ::4]))
    differing = (deviation > DEVIATION_FACTOR * max(typical, 1.0)).mean(axis=0)  # (H, W) share of samples
    contested = np.flatnonzero(differing > CONTESTED_SHARE)
    values = stack.reshape(len(stack), -1, 3)[:, contested]  # (K, P, 3)
    return CameraSamples(stack.shape[1:], median, small, contested, values, False,
                         _scatter(stack, median, downsample))


def _scatter(stack: np.ndarray, median: np.ndarray, downsample: int) -> float:
    """σ per channel (8-bit levels) of the samples about their median at the silhouette stage's working
    resolution, within [NOISE_SIGMA_MIN, NOISE_SIGMA_MAX].

    Each sample is reduced as the silhouette stage reduces a frame, scaled by its exposure ratio to the
    median (the median of I·B / B·B: flicker), and compared with it on every SAMPLE_STRIDE-th pixel that it
    does not copy exactly (a codec repeats static blocks, which tell nothing of the noise; when copies are
    most of the pixels, the samples are noiseless and what differs is the subject). The median of
    ‖I − gB‖² over them, divided by that of a χ²₃ variable, is σ²: the subject covers a small part of the
    samples, and the median, unlike the lower quartile a single frame's estimate uses, also counts the
    heavier tail that a codec leaves where it encodes a block again.
    """
    height, width = median.shape[:2]
    shape = (max(1, round(width / downsample)), max(1, round(height / downsample)))
    B = cv2.resize(median, shape, interpolation=cv2.INTER_AREA)[::SAMPLE_STRIDE, ::SAMPLE_STRIDE].reshape(-1, 3)
    B = B.astype(np.float32)
    distances, sampled = [], 0
    for frame in stack[:: max(1, len(stack) // SCATTER_SAMPLES)]:
        I = cv2.resize(frame, shape, interpolation=cv2.INTER_AREA)[::SAMPLE_STRIDE, ::SAMPLE_STRIDE].reshape(-1, 3)
        I = I.astype(np.float32)
        measured = (I != B).any(axis=1)
        gain = np.median((I * B).sum(axis=1) / ((B * B).sum(axis=1) + 1.0))
        distances.append(((I - gain * B) ** 2).sum(axis=1)[measured])
        sampled += len(I)
    distances = np.concatenate(distances)
    if len(distances) < sampled / 2:  # mostly exact copies (a noiseless render): what differs is the subject
        return NOISE_SIGMA_MIN
    sigma = float(np.sqrt(np.median(distances) / CHI2_3_MEDIAN))
    return min(max(sigma, NOISE_SIGMA_MIN), NOISE_SIGMA_MAX)


def _stack(frames: Iterable[np.ndarray]) -> np.ndarray:
    """(K, H, W, 3) uint8 of the frames, checked to be colour images of one size."""
    frames = [np.asarray(frame) for frame in frames]
    if not frames:
        raise InputError("background samples: expected at least one frame, got none")
    shapes = {frame.shape for frame in frames}
    if len(shapes) != 1:
        raise InputError(f"background samples: frames of different shapes {sorted(shapes)}; expected one size")
    shape = shapes.pop()
    if len(shape) != 3 or shape[2] != 3 or any(frame.dtype != np.uint8 for frame in frames):
        raise InputError(f"background samples: expected (H, W, 3) uint8 colour frames, got shape {shape}")
    return np.stack(frames)


def plain_median(stack: np.ndarray) -> np.ndarray:
    """(...) uint8 per-element median of the samples ``stack`` (K, ...) uint8; of an even count, the upper of
    the two middle values (half a rank off; the mean of two would need one more pass)."""
    return _sorted(stack)[len(stack) // 2]


def _sorted(stack: np.ndarray) -> list[np.ndarray]:
    """The samples ``stack`` (K, ...) uint8 sorted element by element, as K arrays (smallest first).

    Batcher's odd-even merge sort (Knuth, TAOCP vol. 3, 5.3.4) as a fixed sequence of element-wise minima and
    maxima over whole images: vectorised, it sorts a few dozen 780 x 580 images several times faster than
    numpy's sorting or partitioning along the sample axis, which works pixel by pixel.
    """
    layers = [np.array(layer) for layer in stack]  # copies, sorted in place
    spare = np.empty_like(layers[0])
    for a, b in _batcher_pairs(len(layers)):
        np.minimum(layers[a], layers[b], out=spare)
        np.maximum(layers[a], layers[b], out=layers[b])
        layers[a], spare = spare, layers[a]
    return layers


@functools.cache
def _batcher_pairs(count: int) -> tuple[tuple[int, int], ...]:
    """The compare-exchange pairs (i, j), i < j, of Batcher's odd-even merge sort of ``count`` elements."""
    pairs = []
    p = 1
    while p < count:
        k = p
        while k >= 1:
            for j in range(k % p, count - k, 2 * k):
                for i in range(min(k, count - j - k)):
                    if (i + j) // (2 * p) == (i + j + k) // (2 * p):
                        pairs.append((i + j, i + j + k))
            k //= 2
        p *= 2
    return tuple(pairs)


def masked_median(values: np.ndarray, covered: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel median of each pixel's samples that are not covered, and how many there are.

    Parameters
    ----------
    values : (K, P, 3) uint8
        K samples of P pixels.
    covered : (K, P) bool
        Which samples to leave out.

    Returns
    -------
    median : (P, 3) uint8
        Meaningless where no sample is left (count 0).
    count : (P,) int
    """
    count = len(values) - covered.sum(axis=0)  # (P,)
    ordered = values.copy()
    ordered[covered] = 255  # after every kept sample in the order (a kept 255 ties, which is the same value)
    ordered = np.stack(_sorted(ordered))
    lower = np.clip((count - 1) // 2, 0, len(values) - 1)[None, :, None]  # ranks of the two middle samples
    upper = np.clip(count // 2, 0, len(values) - 1)[None, :, None]
    middle = (np.take_along_axis(ordered, lower, axis=0).astype(np.uint16)
              + np.take_along_axis(ordered, upper, axis=0) + 1) // 2
    return middle[0].astype(np.uint8), count
