"""Each camera's background when no clean plate is given, with the subject left out even where he stands still.

The temporal median of a camera's frames is its background wherever the subject covers a pixel in fewer
than half of them. A subject who stays on one spot for a while (standing still before he starts, a stance
held between kicks) covers those pixels in more than half, and the median keeps a ghost of him: the
silhouettes then lose him wherever he stands as the ghost does, and gain a phantom wherever the ghost's
place is bare again.

If we knew which pixels the subject covers in every frame, the background would be the median of each
pixel's frames where it is *not* covered. One view cannot tell where its own background is wrong, but the
views together can: a view's errors are its own (a view's ghost is where the subject stood *as that view
sees it*; the blob where a ghost's place is bare again, or a passer-by, has no counterpart in most other
views), while the subject is where the views agree. So the estimate iterates (:func:`estimate_backgrounds`):

1. each camera's background is the plain median of frames sampled over the whole sequence;
2. each sampled frame's silhouettes are cut against it, at a reduced working resolution;
3. each sampled frame's visual hull is carved on a voxel grid of the working volume: a voxel is kept when
   it lies in the silhouette of every camera that sees it but ``tolerated`` ones (one, from four cameras
   on), so a view whose ghost hides the subject does not carve him away, while what one view alone sees
   is carved;
4. the hull, projected into each view, marks the pixels the subject covers in that frame (the first round
   the hull alone, since the views' own silhouettes may miss him where a ghost matches him; later rounds
   the view's own silhouette where the hull agrees, which is tighter; holes that a cover encloses are
   covered too); each pixel's background becomes the median of its samples that are not covered;
5. back to 2 with the new backgrounds, until the covered pixels settle.

A subject who stood still long enough to be a ghost in most views vanishes from the samples where he stands
as the ghost does: their hulls are empty while the others' are not. Those samples are told from samples in
which nobody was in view (a subject who walks in later) by the outlines of the two candidate backgrounds,
the median of all the samples and the median of the others (:func:`_outlines`): the one that shows the room
has no person's outline along the border where they differ. The estimate then starts again from that one,
or, when neither is clearly the room, leaves those samples out.

A pixel covered in (nearly) every sample is never seen bare: its background is inpainted from the pixels
around it (:func:`cv2.inpaint`), and its share of the image is reported
(:attr:`BackgroundEstimate.unresolved_share`); the subject then stays foreground there, which is right
as long as he stays there. A part of him that never changes colour in any view (he never moves at all)
looks to every sample like the room, and no estimate from the frames can tell it from the room.

Each estimate also measures how much the samples scatter about it (:func:`_scatter`): the silhouettes cut
against it take that as the lowest noise level a frame can have (``BackgroundModel.noise_floor``).

Memory stays flat in the sequence's length: at most ``MAX_SAMPLES`` frames per camera are sampled
(fewer for large images, ``SAMPLE_BYTES``). The working-resolution copies of every camera's samples are
kept; of the full-resolution frames, one camera's at a time (:func:`sample_camera`), and afterwards only
the pixels where the plain median is contested, where more than ``CONTESTED_SHARE`` of the samples differ
from it. Elsewhere the plain median is already the background: the subject covered the pixel too rarely to
move the median, or with a colour too close to the background's to matter; or he covered it in most
samples with one unchanging colour (standing still), and the working-resolution estimate, whose coverage
says so, is used there instead.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from calib.camera import Camera
from calib.errors import InputError
from stages.silhouettes import (
    NOISE_SIGMA_MAX,
    NOISE_SIGMA_MIN,
    SAMPLE_STRIDE,
    SilhouetteParams,
    background_model,
    extract_silhouette,
)

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
#: A covered share at or above this at a pixel that is not contested means an unchanging colour over most
#: samples there: the subject standing still, or the background itself.
MAJORITY_SHARE = 0.5
#: At least this many bare samples make a pixel's background; with fewer it is inpainted and reported.
MIN_UNCOVERED = 3
#: Radius (working pixels) of the inpainting's neighbourhood.
INPAINT_RADIUS_PX = 3
#: Voxel side of the hull (metres); larger in a large volume, so that the grid holds at most MAX_VOXELS.
VOXEL_M = 0.03
MAX_VOXELS = 2_000_000
#: The hull is carved first on cells of this many voxels a side.
COARSE_FACTOR = 4
#: A sample's own silhouette is widened by this many working pixels before it marks what the subject
#: covers: the outline's mixed pixels must not enter the median.
OWN_MARGIN_PX = 1
#: A sample whose hull holds fewer voxels than this share of the upper quartile of all the samples' hull
#: sizes is one in which nobody was found.
ABSENT_SHARE = 0.5
#: A hull smaller than this (cubic metres, a fist) is no subject.
MIN_SUBJECT_M3 = 0.002
#: Of two candidate backgrounds, one is the room when its outlines (:func:`_outlines`) are weaker than the
#: other's by this factor; a ghost's outline makes them several times stronger.
OUTLINE_RATIO = 0.7
#: Two candidate backgrounds differ where the sum of their channels' absolute differences exceeds this
#: (8-bit levels): far above two medians' noise, below a person's contrast with a room.
REGION_LEVELS = 30
#: Rounds of silhouettes, hulls and medians at most; fewer when the covered
#: pixels settle (fewer than SETTLED_SHARE of the covered working pixels change from one round to the next).
MAX_ROUNDS = 5
SETTLED_SHARE = 0.01
# The samples' scatter is measured on at most about this many of them (each gives thousands of pixels).
SCATTER_SAMPLES = 12
# The median of a χ² variable with 3 degrees of freedom: ‖I − B‖² / σ² of background pixels under Gaussian
# noise of σ per channel.
CHI2_3_MEDIAN = 2.366
# cv2.transform's matrix summing the three channels of each pixel.
_CHANNEL_SUM = np.ones((1, 3), np.float32)


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


@dataclass(frozen=True, eq=False)
class BackgroundEstimate:
    """One camera's estimated background and how well the subject could be left out of it.

    Attributes
    ----------
    image : (H, W, 3) uint8
    unresolved_share : float
        Share of the image covered by the subject in all but fewer than ``MIN_UNCOVERED`` samples: never
        seen bare, inpainted.
    covered_share : float
        Share of the image that the subject covers in at least one sample (his footprint over the sequence).
    samples : int
    found_samples : int
        Samples in which the cameras' hull found a subject (none: nobody in view, or a subject who never
        moved, whom no background estimate can tell from the room).
    ghost_samples : int
        Samples that showed nobody where the others showed the subject, because the first estimate held a
        ghost of him (he stood still in them): the estimate started again from the others' median. 0 when
        it did not.
    rounds : int
        Rounds of the iteration that ran.
    noise : float or None
        The samples' scatter about the background (σ, 8-bit levels, at the silhouette stage's working
        resolution; :func:`_scatter`): the noise floor of the silhouettes cut against it. None with a plate.
    """

    image: np.ndarray
    unresolved_share: float
    covered_share: float
    samples: int
    found_samples: int
    ghost_samples: int
    rounds: int
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
    median = _median(stack)
    # (K, H, W) uint8 each sample's L1 distance to the median, saturated at 255 (far above the thresholds).
    deviation = np.stack([cv2.transform(cv2.absdiff(frame, median), _CHANNEL_SUM) for frame in stack])
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


def _median(stack: np.ndarray) -> np.ndarray:
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


def working_camera(camera: Camera, size: tuple[int, int]) -> Camera:
    """``camera`` for its images resized to ``size`` (w, h): full-resolution pixel centres at integers map to
    ``(u + ½) s − ½`` with ``s`` the ratio of sizes, so the resized image's pixel centres stay at integers."""
    width, height = camera.size
    sx, sy = size[0] / width, size[1] / height
    scale = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
    return replace(camera, K=scale @ camera.K, size=size)


class _Grid:
    """Voxels of the working volume, coarse and fine, and where each camera sees their centres.

    The hull is carved coarse to fine: cells of ``COARSE_FACTOR`` fine voxels a side first, then the fine
    voxels of the cells that may hold the subject. Where the cameras see a fine voxel is worked out the
    first time its cell is needed and kept (the subject visits a small part of the volume), so the grid
    costs in proportion to the space the subject uses, not to the volume.
    """

    def __init__(self, cameras: Sequence[Camera], volume: np.ndarray):
        low, high = np.asarray(volume, dtype=float)
        self.cameras = list(cameras)
        self.voxel = max(VOXEL_M, float(np.prod(high - low) / MAX_VOXELS) ** (1 / 3))
        cell = COARSE_FACTOR * self.voxel
        self.cells = np.maximum(np.ceil((high - low) / cell).astype(int), 1)  # (3,) coarse cells per axis
        axes = [low[a] + np.arange(self.cells[a]) * cell for a in range(3)]
        self.cell_low = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)  # (M, 3) corners
        steps = (np.arange(COARSE_FACTOR) + 0.5) * self.voxel
        self.offsets = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), axis=-1).reshape(-1, 3)  # (F, 3)
        self.coarse_pixels, depths = self._pixels(self.cell_low + 0.5 * cell)
        # The fine voxels' pixels of the cells met so far: cell i's are store[:, slot[i]] (slot -1: not yet).
        self.slot = np.full(len(self.cell_low), -1, np.int64)
        self.store = np.zeros((len(self.cameras), 0, len(self.offsets)), np.int32)
        self.stored = 0
        focal = [0.5 * (camera.K[0, 0] + camera.K[1, 1]) for camera in self.cameras]
        typical = [float(np.median(d[p >= 0])) if (p >= 0).any() else 1.0
                   for d, p in zip(depths, self.coarse_pixels, strict=True)]
        # A voxel's half-diagonal, and a cell's, in working pixels at the camera's typical depth.
        self.fine_radius = [max(1, int(np.ceil(0.5 * np.sqrt(3.0) * self.voxel * f / z)))
                            for f, z in zip(focal, typical, strict=True)]
        self.coarse_radius = [max(1, int(np.ceil(0.5 * np.sqrt(3.0) * cell * f / z)))
                              for f, z in zip(focal, typical, strict=True)]

    def _pixels(self, X: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        """((C, N) int32 flat working pixel of each point ``X`` (N, 3) per camera, -1 where unseen; depths)."""
        pixels, depths = [], []
        for camera in self.cameras:
            depth = camera.depth(X)
            # Seen: in the image both without the distortion (which folds back far outside the image) and with it.
            seen = camera.sees(X)
            uv = np.full((len(X), 2), -1.0)
            uv[seen] = camera.project(X[seen])
            seen &= camera.in_image(uv)
            width, height = camera.size
            column = np.clip(np.floor(uv[:, 0] + 0.5), 0, width - 1)
            row = np.clip(np.floor(uv[:, 1] + 0.5), 0, height - 1)
            pixels.append(np.where(seen, row * width + column, -1).astype(np.int32))
            depths.append(depth)
        return np.stack(pixels), depths

    def fine(self, cells: np.ndarray) -> np.ndarray:
        """(C, len(cells), F) int32 working pixels of the fine voxels of coarse ``cells`` (M',) int."""
        new = cells[self.slot[cells] < 0]
        if len(new):
            X = (self.cell_low[new][:, None, :] + self.offsets[None]).reshape(-1, 3)
            pixels, _ = self._pixels(X)
            if self.stored + len(new) > self.store.shape[1]:  # grow by doubling: few copies
                grown = np.zeros((len(self.cameras), max(2 * self.store.shape[1], self.stored + len(new)),
                                  len(self.offsets)), np.int32)
                grown[:, : self.stored] = self.store[:, : self.stored]
                self.store = grown
            self.store[:, self.stored : self.stored + len(new)] = pixels.reshape(len(self.cameras), len(new), -1)
            self.slot[new] = np.arange(self.stored, self.stored + len(new))
            self.stored += len(new)
        return self.store[:, self.slot[cells]]


def tolerated_views(cameras: int) -> int:
    """How many cameras may disagree with a voxel of the hull: one from four cameras on (a view whose ghost
    hides the subject must not carve him), none with fewer (two or three views must all agree)."""
    return 1 if cameras >= 4 else 0


def _occupied(masks: Sequence[np.ndarray], pixels: np.ndarray, radius: Sequence[int], tolerated: int) -> np.ndarray:
    """(...) bool: which of the voxels whose centres the cameras see at ``pixels`` (C, ...) lie in the hull.

    A voxel is in it when at most ``tolerated`` of the cameras that see it see it outside their silhouette
    (each dilated by the voxel's footprint, ``radius`` per camera, so that a voxel the outline crosses
    counts as inside), and all but ``tolerated`` of the rig's cameras, and at least two, see it inside.
    """
    inside = np.zeros(pixels.shape[1:], np.int8)
    outside = np.zeros(pixels.shape[1:], np.int8)
    for c, mask in enumerate(masks):
        grown = cv2.dilate(mask, _disk(radius[c]))
        flat = np.append(grown.ravel(), np.uint8(0))  # index -1 reads the appended 0
        hit = flat.take(pixels[c]) > 0
        inside += hit
        outside += (pixels[c] >= 0) & ~hit
    return (outside <= tolerated) & (inside >= max(2, len(masks) - 1 - tolerated))


def _hull_cover(masks: Sequence[np.ndarray], grid: _Grid, tolerated: int) -> tuple[list[np.ndarray], int]:
    """Per camera, (h, w) bool: the pixels onto which one sample's visual hull (see :func:`_occupied`)
    projects, each occupied fine voxel drawn as a disc of its footprint; and the hull's size in voxels."""
    cells = np.flatnonzero(_occupied(masks, grid.coarse_pixels, grid.coarse_radius, tolerated))
    pixels = grid.fine(cells)  # (C, M', F)
    occupied = _occupied(masks, pixels, grid.fine_radius, tolerated)
    covers = []
    for c, mask in enumerate(masks):
        cover = np.zeros(mask.size, np.uint8)
        where = pixels[c][occupied]
        cover[where[where >= 0]] = 255
        covers.append(cv2.dilate(cover.reshape(mask.shape), _disk(grid.fine_radius[c])) > 0)
    return covers, int(occupied.sum())


@functools.cache
def _disk(radius: int) -> np.ndarray:
    """Disk-shaped structuring element of ``radius`` pixels, made once per radius."""
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _working_background(samples: CameraSamples, cover: np.ndarray, first: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A camera's background at the working resolution from its samples' ``cover`` (K, h, w) bool, and
    where it is unresolved ((h, w) bool: fewer than MIN_UNCOVERED bare samples, inpainted).

    ``first`` (h, w, 3) uint8 is the plain median there, kept where the subject covers too few samples to
    move it.
    """
    shares = cover.mean(axis=0)  # (h, w)
    background = first.copy()
    redo = np.flatnonzero(shares > CONTESTED_SHARE)
    flat = background.reshape(-1, 3)
    small = samples.small.reshape(len(samples.small), -1, 3)
    median, count = masked_median(small[:, redo], cover.reshape(len(cover), -1)[:, redo])
    flat[redo] = median
    unresolved = np.zeros(shares.size, bool)
    unresolved[redo[count < MIN_UNCOVERED]] = True
    unresolved = unresolved.reshape(shares.shape)
    if unresolved.any():
        background = cv2.inpaint(background, unresolved.astype(np.uint8), INPAINT_RADIUS_PX, cv2.INPAINT_TELEA)
    return background, unresolved


@dataclass(frozen=True, eq=False)
class _Round:
    """What one round of the iteration found in every sample."""

    covers: list[np.ndarray]  # per camera (K, h, w) bool: the pixels the subject covers in each sample
    sizes: np.ndarray  # (K,) int each sample's hull size, voxels

    def left_out(self, samples: np.ndarray) -> list[np.ndarray]:
        """The covers with ``samples`` (K,) bool covered everywhere: left out of every pixel's median."""
        return [cover | samples[:, None, None] for cover in self.covers]


def _round(samples: Sequence[CameraSamples], backgrounds: Sequence[np.ndarray], grid: _Grid, tolerated: int,
           params: SilhouetteParams, *, fresh: bool) -> _Round:
    """Silhouettes, hulls and covers of every sample against the current working ``backgrounds``.

    A fresh start's backgrounds may hold ghosts, which hide the subject from a view's own silhouette: the
    hull alone says where he is. Later rounds' backgrounds are free of them, and the own silhouette, tighter
    than any hull, marks him, where the hull agrees (what the hull does not explain is not him).
    """
    models = [background_model(b, params) for b in backgrounds]
    count = len(samples[0].small)
    covers = [np.zeros(s.small.shape[:3], bool) for s in samples]
    sizes = np.zeros(count, np.int64)
    for k in range(count):
        masks = [extract_silhouette(s.small[k], model, params) for s, model in zip(samples, models, strict=True)]
        hull, sizes[k] = _hull_cover(masks, grid, tolerated)
        for c, (mask, cover) in enumerate(zip(masks, hull, strict=True)):
            if not fresh:
                cover &= _filled(cv2.dilate(mask, _disk(OWN_MARGIN_PX)))
            covers[c][k] = _filled(cover.view(np.uint8))
    return _Round(covers, sizes)


def _filled(mask: np.ndarray) -> np.ndarray:
    """(h, w) bool the (h, w) uint8 or bool-as-uint8 ``mask`` with the holes it encloses filled.

    What the subject encloses is covered too: a part of him that matches a ghost in the background shows
    as a hole in his silhouette (and a cavity in the hull), and the gap between an arm and the body, which
    this covers as well, is seen bare in other samples.
    """
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    filled = np.zeros(mask.shape, np.uint8)
    cv2.drawContours(filled, contours, -1, 1, cv2.FILLED)
    return filled > 0


def _absent(sizes: np.ndarray, minimum: float) -> np.ndarray:
    """(K,) bool the samples whose hull is much smaller than the others' (below ``ABSENT_SHARE`` of their
    upper quartile, and below ``minimum`` voxels): nobody was found there; none when fewer than
    MIN_SAMPLES others remain."""
    absent = sizes < max(ABSENT_SHARE * np.quantile(sizes, 0.75), minimum)
    return absent if (~absent).sum() >= MIN_SAMPLES else np.zeros_like(absent)


def estimate_backgrounds(samples: Sequence[CameraSamples], cameras: Sequence[Camera], volume: np.ndarray,
                         params: SilhouetteParams) -> list[BackgroundEstimate]:
    """Every camera's background, the subject left out by the multi-view iteration of the module's docstring.

    Parameters
    ----------
    samples : sequence of CameraSamples
        One per camera, in rig order, the same frames sampled in each (:func:`sample_camera`).
    cameras : sequence of Camera
        The rig's cameras at full resolution, world frame.
    volume : (2, 3) float
        Working volume [min; max], metres: the hulls are carved in it.
    params : SilhouetteParams
        The silhouette stage's parameters; the samples' silhouettes use them at the working resolution
        (``downsample`` 1, no blur), with no shadow test: a shadow counts as the subject, so it stays out of
        the median too.

    Returns
    -------
    list of BackgroundEstimate, one per camera (a camera with a clean plate gets its plate).
    """
    if not len(samples) == len(cameras):
        raise InputError(f"estimate_backgrounds: {len(samples)} cameras' samples for {len(cameras)} cameras")
    counts = {len(s.small) for s in samples}
    if len(counts) != 1:
        raise InputError(f"estimate_backgrounds: cameras sampled {sorted(counts)} frames; expected the same frames")
    for s, camera in zip(samples, cameras, strict=True):
        if s.shape[1::-1] != tuple(camera.size):
            raise InputError(f"estimate_backgrounds: camera {camera.name!r} is {camera.size[0]}x{camera.size[1]}, "
                             f"its samples {s.shape[1]}x{s.shape[0]}")
    small = [working_camera(camera, s.small.shape[2:0:-1]) for s, camera in zip(samples, cameras, strict=True)]
    grid = _Grid(small, np.asarray(volume, dtype=float))
    tolerated = tolerated_views(len(cameras))
    working_params = replace(params, downsample=1, blur_kernel_px=1, shadows="none")
    first = [cv2.resize(s.median, camera.size, interpolation=cv2.INTER_AREA)
             for s, camera in zip(samples, small, strict=True)]
    backgrounds = list(first)
    minimum = MIN_SUBJECT_M3 / grid.voxel**3
    found = _round(samples, backgrounds, grid, tolerated, working_params, fresh=True)
    absent = _absent(found.sizes, minimum)
    ghost_samples, left_out = 0, np.zeros_like(absent)
    if absent.any():
        # Samples in which the hull finds nobody while the others find someone: either nobody was in view
        # then, or the subject stood still long enough to be a ghost in most views and vanishes where he
        # stands as it does; in the other samples he stands elsewhere, and their plain median shows the
        # ghost's place bare. Which of the two medians is the room is told by its outlines (_outlines);
        # when neither is clearly the room, the samples that found nobody cannot say where he is not.
        trial = [b if s.plate else _median(s.small[~absent]) for s, b in zip(samples, backgrounds, strict=True)]
        ratio = _outlines(trial, backgrounds) / max(_outlines(backgrounds, trial), 1e-6)
        if ratio < OUTLINE_RATIO:
            backgrounds, first, ghost_samples = trial, list(trial), int(absent.sum())
            found = _round(samples, backgrounds, grid, tolerated, working_params, fresh=True)
        elif ratio <= 1 / OUTLINE_RATIO:
            left_out = absent
    rounds = 1
    covers = found.left_out(left_out)
    unresolved = [np.zeros(s.small.shape[1:3], bool) for s in samples]
    settled = False
    while True:
        for c, s in enumerate(samples):
            if not s.plate:
                backgrounds[c], unresolved[c] = _working_background(s, covers[c], first[c])
        if settled or rounds >= MAX_ROUNDS:
            break
        rounds += 1
        found = _round(samples, backgrounds, grid, tolerated, working_params, fresh=False)
        previous, covers = covers, found.left_out(left_out)
        changed = sum(int((new ^ old).sum()) for new, old in zip(covers, previous, strict=True))
        settled = changed <= SETTLED_SHARE * max(sum(int(cover.sum()) for cover in covers), 1)
    found_samples = int((found.sizes >= minimum).sum())
    return [_full_background(s, cover, left_out, background, gaps, rounds, found_samples, ghost_samples)
            for s, cover, background, gaps in zip(samples, covers, backgrounds, unresolved, strict=True)]


def _outlines(backgrounds: Sequence[np.ndarray], others: Sequence[np.ndarray]) -> float:
    """How strongly ``backgrounds`` (working resolution, one per camera) show an outline along the border of
    the region where they differ from ``others``: the mean gradient magnitude there, over all cameras.

    Of two candidate backgrounds that differ where a person stood, the one that shows him has his outline
    all along that border (a person is not the colour of the room), the one that shows the room has only
    the room's own texture there, which goes on across the border.
    """
    total, count = 0.0, 0
    for background, other in zip(backgrounds, others, strict=True):
        difference = cv2.transform(cv2.absdiff(background, other), _CHANNEL_SUM)
        region = cv2.morphologyEx((difference > REGION_LEVELS).astype(np.uint8), cv2.MORPH_OPEN, _disk(1))
        border = cv2.morphologyEx(region, cv2.MORPH_GRADIENT, _disk(1)) > 0
        if not border.any():
            continue
        grey = cv2.cvtColor(background, cv2.COLOR_BGR2GRAY).astype(np.float32)
        magnitude = np.abs(cv2.Sobel(grey, cv2.CV_32F, 1, 0)) + np.abs(cv2.Sobel(grey, cv2.CV_32F, 0, 1))
        total += float(magnitude[border].sum())
        count += int(border.sum())
    return total / max(count, 1)


def _full_background(samples: CameraSamples, cover: np.ndarray, left_out: np.ndarray, working: np.ndarray,
                     unresolved: np.ndarray, rounds: int, found: int, ghost_samples: int) -> BackgroundEstimate:
    """The full-resolution background of one camera from its working-resolution cover (K, h, w) bool (the
    ``left_out`` (K,) bool samples covered everywhere), its working background (h, w, 3) and unresolved pixels
    (h, w) bool (see the module's docstring)."""
    height, width = samples.shape[:2]
    seen = cover[~left_out]  # (K', h, w) the samples that say where the subject is
    covered_share = float(cv2.resize(seen.any(axis=0).astype(np.uint8), (width, height),
                                     interpolation=cv2.INTER_NEAREST).mean())
    if samples.plate:
        return BackgroundEstimate(samples.median, 0.0, covered_share, len(cover), found, ghost_samples, rounds, None)
    h, w = cover.shape[1:]
    # The working pixel of each full-resolution pixel (nearest), as flat indices.
    rows = np.minimum((np.arange(height) + 0.5) * h / height, h - 1).astype(np.int64)
    cols = np.minimum((np.arange(width) + 0.5) * w / width, w - 1).astype(np.int64)
    image = samples.median.copy()
    flat = image.reshape(-1, 3)
    majority = cv2.resize((seen.mean(axis=0) >= MAJORITY_SHARE).astype(np.uint8), (width, height),
                          interpolation=cv2.INTER_NEAREST) > 0
    if majority.any():
        upsampled = cv2.resize(working, (width, height), interpolation=cv2.INTER_LINEAR)
        image[majority] = upsampled[majority]
    # The contested pixels that the subject covers often enough to move their median.
    at = rows[samples.contested // width] * w + cols[samples.contested % width]  # (P,) their working pixels
    redo = np.flatnonzero(cover.reshape(len(cover), -1)[:, at].mean(axis=0) > CONTESTED_SHARE)
    if len(redo):
        median, count = masked_median(samples.contested_values[:, redo], cover.reshape(len(cover), -1)[:, at[redo]])
        kept = count >= MIN_UNCOVERED
        flat[samples.contested[redo[kept]]] = median[kept]
    gaps = unresolved[rows[:, None], cols[None, :]]  # (H, W) bool
    if gaps.any():
        radius = max(INPAINT_RADIUS_PX, round(INPAINT_RADIUS_PX * width / w))
        image = cv2.inpaint(image, gaps.astype(np.uint8), radius, cv2.INPAINT_TELEA)
    return BackgroundEstimate(image, float(gaps.mean()), covered_share, len(cover), found, ghost_samples, rounds,
                              samples.noise)
