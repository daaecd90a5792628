"""Whether the cameras filmed the same instants: each camera's silhouettes against the others' a few frames apart.

Cameras that are not synchronised by hardware (webcams, phones, action cameras lined up by a clap) often start a
frame or more apart. Every stage then runs as usual, but a view that lags carves the moving limbs where they were
a frame before, and the reconstruction loses them: a kick at 5 m/s moves the foot 18 cm between two frames at 28
frames/s. This module measures, for each camera c and offset k, how much of c's silhouette at frame f + k the
visual hull of the other views at frame f explains (`stages.consistency.explained_rays`: Hernández, Schmitt &
Cipolla's silhouette coherence, 2007, across time), over frames where the subject moves. A synchronised camera
agrees best at k = 0 and less at every step away; a camera whose media run k frames behind agrees best at k.

The other views' hull tolerates one disagreeing view from four cameras on (`tolerated`), so that the lagging
camera does not spoil the hull against which the others are measured. Offsets are tried one step at a time
away from 0, and only while the farther one agrees better: for synchronised cameras, the usual case, the check
costs three offsets.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from calib.camera import Camera
from stages.consistency import explained_rays

#: Rays through each camera's silhouette that are tested per frame and offset: the share unexplained is a few
#: per cent, and 150 rays tell it to a few per cent, a dozen frames to about one.
SYNC_RAYS = 150
#: The frames compared are chosen among this many times as many, spread over the capture.
CANDIDATES_PER_FRAME = 2.0
#: A camera's offset is reported when its silhouettes agree better there than at 0 by this many standard errors
#: of the per-frame differences: clearly, not by the chance of which rays were drawn.
SYNC_CLEAR_STANDARD_ERRORS = 3.0


@dataclass(frozen=True)
class SyncCheck:
    """What :func:`check_synchrony` measured.

    Attributes
    ----------
    frames : list of int
        Indices (into the frames given) of the frames compared, those where the silhouettes change most.
    offsets : (K,) int
        The offsets tried, in frames, increasing; 0 among them.
    agreement : (C, K, F) float
        Per camera, offset and frame compared, the share of the rays through the camera's silhouette at frame
        f + offset that the other views' hull at frame f explains; NaN where not measured (an offset not tried
        for that camera, an empty silhouette).
    """

    frames: list[int]
    offsets: np.ndarray
    agreement: np.ndarray

    def mean_agreement(self) -> np.ndarray:
        """(C, K) each camera's agreement at each offset, averaged over the frames; NaN where not measured."""
        with np.errstate(invalid="ignore"):
            counted = np.isfinite(self.agreement).sum(axis=2)
            total = np.nansum(self.agreement, axis=2)
            return np.where(counted > 0, total / np.maximum(counted, 1), np.nan)

    def lags(self) -> np.ndarray:
        """(C,) int each camera's offset where its silhouettes agree clearly best (`clearly_better`), else 0."""
        zero = int(np.flatnonzero(self.offsets == 0)[0])
        mean = self.mean_agreement()
        lags = np.zeros(len(mean), dtype=int)
        for c, curve in enumerate(mean):
            if np.all(np.isnan(curve)):
                continue
            best = int(np.nanargmax(curve))
            if best != zero and clearly_better(self.agreement[c, best], self.agreement[c, zero]):
                lags[c] = int(self.offsets[best])
        return lags


def clearly_better(these: np.ndarray, those: np.ndarray) -> bool:
    """Whether the per-frame agreements ``these`` (F,) exceed ``those`` (F,) by more than
    `SYNC_CLEAR_STANDARD_ERRORS` standard errors of their paired differences (frames measured by both)."""
    differences = (these - those)[np.isfinite(these) & np.isfinite(those)]
    if len(differences) < 3:
        return False
    spread = differences.std(ddof=1) / np.sqrt(len(differences))
    return bool(differences.mean() > SYNC_CLEAR_STANDARD_ERRORS * max(spread, 1e-12))


def check_synchrony(masks_at: Callable[[int], Sequence[np.ndarray]], cameras: Sequence[Camera], volume: np.ndarray,
                    count: int, frames: int, max_offset: int, tolerated: int, *,
                    measured: Sequence[int] | None = None, rays: int = SYNC_RAYS) -> SyncCheck:
    """Each camera's silhouettes against the other views' hull at offsets up to ``max_offset`` frames.

    Parameters
    ----------
    masks_at : callable
        ``masks_at(index)``: the silhouettes (one (H, W) uint8 per camera, 0 = background) of the frame at
        ``index`` among the capture's ``count`` frames, which are consecutive.
    cameras : sequence of Camera
    volume : (2, 3) float
        Working volume [min; max], metres.
    count : int
        How many frames the capture has.
    frames : int
        How many frames to compare: those where the silhouettes change most between the frames before and
        after, among `CANDIDATES_PER_FRAME` times as many spread over the capture.
    max_offset : int
        The largest offset tried, either way.
    tolerated : int
        How many of the other views may see a ray's point outside their silhouette
        (`stages.background.tolerated_views`).
    measured : sequence of int, optional
        The cameras (indices) to check, the others' rows left NaN (default: all): processes sharing the cameras
        between them choose the same frames.
    """
    offsets = np.arange(-max_offset, max_offset + 1)
    zero = max_offset
    if count < 2 * max_offset + 3 or len(cameras) < 3:
        return SyncCheck([], offsets, np.full((len(cameras), len(offsets), 0), np.nan))
    chosen = _moving_frames(masks_at, count, frames, max_offset)
    agreement = np.full((len(cameras), len(offsets), len(chosen)), np.nan)

    def measure(tried: dict[int, list[int]]) -> None:
        """Fill ``agreement`` for each camera's offsets ``tried`` (camera -> offsets), frame after frame: a few
        frames' masks in memory at a time."""
        wanted = sorted({k for ks in tried.values() for k in ks})
        for j, index in enumerate(chosen):
            views = masks_at(index)
            shifted = {k: views if k == 0 else masks_at(index + k) for k in wanted}
            for c, ks in tried.items():
                others = [(camera, views[o]) for o, camera in enumerate(cameras) if o != c]
                for k in ks:
                    agreement[c, zero + k, j] = explained_rays(cameras[c], shifted[k][c], others, volume,
                                                                tolerated=tolerated, rays=rays)

    def curve(c: int) -> np.ndarray:
        return SyncCheck(chosen, offsets, agreement[c : c + 1]).mean_agreement()[0]

    checked = list(range(len(cameras))) if measured is None else list(measured)
    measure({c: [-1, 0, 1] for c in checked})
    reached = {}  # camera -> the offset reached so far, for the cameras that agree better one step away
    for c in checked:
        near = curve(c)[zero - 1 : zero + 2]
        if not np.isnan(near).any() and near[1] < near.max():
            reached[c] = 1 if near[2] > near[0] else -1
    while reached:  # on, one step at a time, while the farther offset agrees better
        reached = {c: k for c, k in reached.items() if abs(k) < max_offset}
        measure({c: [k + int(np.sign(k))] for c, k in reached.items()})
        reached = {c: k + int(np.sign(k)) for c, k in reached.items()
                   if curve(c)[zero + k + int(np.sign(k))] > curve(c)[zero + k]}
    return SyncCheck(chosen, offsets, agreement)


def _moving_frames(masks_at: Callable[[int], Sequence[np.ndarray]], count: int, frames: int,
                   max_offset: int) -> list[int]:
    """Indices of up to ``frames`` frames, at least ``max_offset`` from either end, where the silhouettes change
    most between the frames before and after (pixels that differ over pixels set, summed over the cameras),
    among `CANDIDATES_PER_FRAME` times as many spread evenly."""
    first, last = max_offset, count - 1 - max_offset
    wanted = min(round(CANDIDATES_PER_FRAME * frames), last - first + 1)
    candidates = np.unique(np.linspace(first, last, wanted).round().astype(int))
    change = []
    for index in candidates:
        before, now, after = masks_at(index - 1), masks_at(index), masks_at(index + 1)
        differing = sum(np.count_nonzero((b > 0) != (a > 0)) for b, a in zip(before, after, strict=True))
        change.append(differing / max(1, sum(np.count_nonzero(m) for m in now)))
    keep = np.sort(np.argsort(change, kind="stable")[::-1][:frames])
    return [int(index) for index in candidates[keep]]
