"""The multi-view iteration of :mod:`stages.background`: silhouettes, hulls and medians by rounds until the
covered pixels settle, the ghost check, and each camera's full-resolution background."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from calib.camera import Camera
from calib.errors import InputError
from stages.background.hull import VoxelGrid, hull_cover, tolerated_views, working_camera
from stages.background.samples import (
    CONTESTED_SHARE,
    MIN_SAMPLES,
    CameraSamples,
    masked_median,
    plain_median,
)
from stages.silhouettes import CHANNEL_SUM, SilhouetteParams, background_model, disk, extract_silhouette

#: A covered share at or above this at a pixel that is not contested means an unchanging colour over most
#: samples there: the subject standing still, or the background itself.
MAJORITY_SHARE = 0.5
#: At least this many bare samples make a pixel's background; with fewer it is inpainted and reported.
MIN_UNCOVERED = 3
#: Radius (working pixels) of the inpainting's neighbourhood.
INPAINT_RADIUS_PX = 3
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

#: How a round maps :func:`camera_silhouettes` over the cameras: :func:`map`, or an executor's.
Mapper = Callable[..., Iterable[np.ndarray]]


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


def _round(samples: Sequence[CameraSamples], backgrounds: Sequence[np.ndarray], grid: VoxelGrid, tolerated: int,
           params: SilhouetteParams, mapper: Mapper, *, fresh: bool) -> _Round:
    """Silhouettes, hulls and covers of every sample against the current working ``backgrounds``.

    A fresh start's backgrounds may hold ghosts, which hide the subject from a view's own silhouette: the
    hull alone says where he is. Later rounds' backgrounds are free of them, and the own silhouette, tighter
    than any hull, marks him, where the hull agrees (what the hull does not explain is not him).
    """
    views = list(mapper(camera_silhouettes, [s.small for s in samples], backgrounds, [params] * len(samples)))
    count = len(samples[0].small)
    covers = [np.zeros(s.small.shape[:3], bool) for s in samples]
    sizes = np.zeros(count, np.int64)
    for k in range(count):
        masks = [view[k] for view in views]
        hull, sizes[k] = hull_cover(masks, grid, tolerated)
        for c, (mask, cover) in enumerate(zip(masks, hull, strict=True)):
            if not fresh:
                cover &= _filled(cv2.dilate(mask, disk(OWN_MARGIN_PX)))
            covers[c][k] = _filled(cover.view(np.uint8))
    return _Round(covers, sizes)


def camera_silhouettes(small: np.ndarray, background: np.ndarray, params: SilhouetteParams) -> np.ndarray:
    """(K, h, w) uint8 the silhouettes of one camera's working-resolution samples ``small`` (K, h, w, 3) against
    its working ``background`` (h, w, 3): a round's work for that camera, which needs no other camera's."""
    model = background_model(background, params, tone_curve=False)
    return np.stack([extract_silhouette(sample, model, params) for sample in small])


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
                         params: SilhouetteParams, *, mapper: Mapper = map) -> list[BackgroundEstimate]:
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
    mapper : callable like :func:`map`
        How each round computes every camera's silhouettes (:func:`camera_silhouettes`, one call per camera):
        an executor's ``map`` spreads the cameras over processes, with the same result.

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
    grid = VoxelGrid(small, np.asarray(volume, dtype=float))
    tolerated = tolerated_views(len(cameras))
    working_params = replace(params, downsample=1, blur_kernel_px=1, shadows="none")
    first = [cv2.resize(s.median, camera.size, interpolation=cv2.INTER_AREA)
             for s, camera in zip(samples, small, strict=True)]
    backgrounds = list(first)
    minimum = MIN_SUBJECT_M3 / grid.voxel**3
    found = _round(samples, backgrounds, grid, tolerated, working_params, mapper, fresh=True)
    absent = _absent(found.sizes, minimum)
    ghost_samples, left_out = 0, np.zeros_like(absent)
    if absent.any():
        # Samples in which the hull finds nobody while the others find someone: either nobody was in view
        # then, or the subject stood still long enough to be a ghost in most views and vanishes where he
        # stands as it does; in the other samples he stands elsewhere, and their plain median shows the
        # ghost's place bare. Which of the two medians is the room is told by its outlines (_outlines);
        # when neither is clearly the room, the samples that found nobody cannot say where he is not.
        trial = [b if s.plate else plain_median(s.small[~absent]) for s, b in zip(samples, backgrounds, strict=True)]
        ratio = _outlines(trial, backgrounds) / max(_outlines(backgrounds, trial), 1e-6)
        if ratio < OUTLINE_RATIO:
            backgrounds, first, ghost_samples = trial, list(trial), int(absent.sum())
            found = _round(samples, backgrounds, grid, tolerated, working_params, mapper, fresh=True)
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
        found = _round(samples, backgrounds, grid, tolerated, working_params, mapper, fresh=False)
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
        difference = cv2.transform(cv2.absdiff(background, other), CHANNEL_SUM)
        region = cv2.morphologyEx((difference > REGION_LEVELS).astype(np.uint8), cv2.MORPH_OPEN, disk(1))
        border = cv2.morphologyEx(region, cv2.MORPH_GRADIENT, disk(1)) > 0
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
