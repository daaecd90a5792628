"""Whether the cameras filmed the same instants: each camera's silhouettes against the others' a few frames apart.

Cameras that are not synchronised by hardware (webcams, phones, action cameras lined up by a clap) often start a
frame or more apart. Every stage then runs as usual, but a view that lags carves the moving limbs where they were
a frame before, and the reconstruction loses them: a kick at 5 m/s moves the foot 18 cm between two frames at 28
frames/s. This module measures, for each camera c and offset k, how much of the *moving part* of c's silhouette at
frame f + k the visual hull of the other views at frame f explains (`stages.consistency.explained_pixels`:
Hernández, Schmitt & Cipolla's silhouette coherence, 2007, across time), over frames where the subject moves. The
moving part is what the silhouette holds at f + k and only one of its neighbours f + k ± 1 holds: where a limb
is on its way. The still rest (a torso, a standing leg) is explained at every offset and would only dilute the
comparison. A synchronised camera agrees best at k = 0 and less at every step away; a camera whose media run k
frames behind agrees best at k.

The other views' hull tolerates one disagreeing view from four cameras on (`tolerated`), so that the lagging
camera does not spoil the hull against which the others are measured. Offsets are tried one step at a time
away from 0, and only while the farther one agrees better: for synchronised cameras, the usual case, the check
costs three offsets.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from calib.camera import Camera
from stages.consistency import explained_pixels, silhouette_pixels

#: Rays through the moving part of each camera's silhouette tested per frame and offset: at the right offset most
#: of them are explained, a frame away clearly fewer, so a few dozen tell the two apart on each frame.
SYNC_RAYS = 40
#: A camera's offset is reported when its silhouettes agree better there than at 0 by this many standard errors
#: of the per-frame differences: clearly, not by the chance of which rays were drawn.
SYNC_CLEAR_STANDARD_ERRORS = 3.0


@dataclass(frozen=True)
class SyncCheck:
    """What :func:`check_synchrony` measured.

    Attributes
    ----------
    frames : list of int
        Indices (into the capture's frames) of the frames compared.
    offsets : (K,) int
        The offsets tried, in frames, increasing; 0 among them.
    agreement : (C, K, F) float
        Per camera, offset and frame compared, the share of the rays through the moving part of the camera's
        silhouette at frame f + offset that the other views' hull at frame f explains; NaN where not measured (an
        offset not tried for that camera, nothing moving).
    """

    frames: list[int]
    offsets: np.ndarray
    agreement: np.ndarray

    def mean_agreement(self) -> np.ndarray:
        """(C, K) each camera's agreement at each offset, averaged over the frames; NaN where not measured."""
        return _frame_mean(self.agreement)

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


def fastest_frames(joints: np.ndarray, count: int, margin: int) -> list[int]:
    """Indices of ``count`` frames spread over the capture, at least ``margin`` from either end: in each of ``count``
    equal stretches, the frame whose joints move most between the frames before and after (the largest joint
    displacement; frames without joints, NaN, are passed over). Spread, so that the frames tell apart as many
    moments of the motion as they can; the fastest of each stretch, as a still subject says nothing about time.

    Parameters
    ----------
    joints : (N, J, 3) float
        The estimated joints of the capture's N frames, NaN where a frame has none.
    """
    inner = np.arange(margin, len(joints) - margin)
    if not len(inner):
        return []
    with np.errstate(invalid="ignore"):
        step = np.linalg.norm(joints[inner + 1] - joints[inner - 1], axis=2).max(axis=1)
    chosen = []
    for stretch in np.array_split(np.arange(len(inner)), min(count, len(inner))):
        moving = stretch[np.isfinite(step[stretch])]
        if len(moving):
            chosen.append(int(inner[moving[np.argmax(step[moving])]]))
    return chosen


def check_synchrony(mask_at: Callable[[int, int], np.ndarray], cameras: Sequence[Camera], volume: np.ndarray,
                    frames: Sequence[int], max_offset: int, tolerated: int, *, rays: int = SYNC_RAYS) -> SyncCheck:
    """Each camera's silhouettes against the other views' hull at offsets up to ``max_offset`` frames.

    Parameters
    ----------
    mask_at : callable
        ``mask_at(index, camera)``: the silhouette ((H, W) uint8, 0 = background) of camera ``camera`` (an index
        into ``cameras``) at the capture's frame ``index``; the frames are consecutive, and asked for up to
        ``max_offset + 1`` from each of ``frames``.
    cameras : sequence of Camera
    volume : (2, 3) float
        Working volume [min; max], metres.
    frames : sequence of int
        The indices of the frames to compare, where the subject moves (`fastest_frames`).
    max_offset : int
        The largest offset tried, either way.
    tolerated : int
        How many of the other views may see a ray's point outside their silhouette
        (`stages.background.tolerated_views`).
    """
    offsets = np.arange(-max_offset, max_offset + 1)
    zero = max_offset
    frames = [int(index) for index in frames]
    agreement = np.full((len(cameras), len(offsets), len(frames)), np.nan)
    if len(cameras) < 3 or not frames:
        return SyncCheck(frames, offsets, agreement)

    def measure(tried: dict[int, list[int]]) -> None:
        """Fill ``agreement`` for each camera's offsets ``tried`` (camera -> offsets), frame after frame: one frame's
        views and a camera's own neighbouring masks in memory at a time, one ray test per camera and frame for all
        its offsets."""
        for j, index in enumerate(frames):
            views = [mask_at(index, o) for o in range(len(cameras))]
            for c, ks in tried.items():
                own = {k: views[c] if k == 0 else mask_at(index + k, c)
                       for k in sorted({k + step for k in ks for step in (-1, 0, 1)})}
                parts = [silhouette_pixels(_moving_part(own[k], own[k - 1], own[k + 1]), rays) for k in ks]
                others = [(camera, views[o]) for o, camera in enumerate(cameras) if o != c]
                explained = explained_pixels(cameras[c], np.concatenate(parts), others, volume, tolerated)
                for k, part in zip(ks, np.split(explained, np.cumsum([len(p) for p in parts])[:-1]), strict=True):
                    agreement[c, zero + k, j] = part.mean() if len(part) else np.nan

    measure({c: [-1, 0, 1] for c in range(len(cameras))})
    reached = {}  # camera -> the offset reached so far, for the cameras that agree better one step away
    for c in range(len(cameras)):
        near = _frame_mean(agreement[c])[zero - 1 : zero + 2]
        if not np.isnan(near).any() and near[1] < near.max():
            reached[c] = 1 if near[2] > near[0] else -1
    while reached:  # on, one step at a time, while the farther offset agrees better
        reached = {c: k for c, k in reached.items() if abs(k) < max_offset}
        if not reached:
            break
        measure({c: [k + int(np.sign(k))] for c, k in reached.items()})
        reached = {c: k + int(np.sign(k)) for c, k in reached.items()
                   if _frame_mean(agreement[c, zero + k + int(np.sign(k))]) > _frame_mean(agreement[c, zero + k])}
    return SyncCheck(frames, offsets, agreement)


def _frame_mean(agreement: np.ndarray) -> np.ndarray:
    """``agreement`` (..., F) averaged over its last axis, the frames, leaving out NaN; NaN where every frame is."""
    counted = np.isfinite(agreement).sum(axis=-1)
    return np.where(counted > 0, np.nansum(agreement, axis=-1) / np.maximum(counted, 1), np.nan)


def _moving_part(mask: np.ndarray, before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """The pixels of ``mask`` that only one of the masks ``before`` and ``after`` it holds: where it moves."""
    return cv2.bitwise_and(mask, cv2.bitwise_xor(before, after))
