"""The floor test of shadows: a shadow-like pixel is a shadow when the other views see its floor point
darkened too (:func:`floor_shadows`), where the calibration says they see it, or where the shadows themselves
say they do (:func:`floor_shifts`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from calib.camera import Camera
from calib.errors import InputError
from stages.consistency import evenly_spread
from stages.silhouettes.evidence import Evidence, _working_shape
from stages.silhouettes.outline import flat_nonzero
from stages.silhouettes.params import SilhouetteParams

# The floor test looks at the floor behind blocks of FLOOR_BLOCK x FLOOR_BLOCK working pixels at once
# (a shadow's darkening changes over many pixels; a quarter of the look-up tables' size and making).
FLOOR_BLOCK = 2
# The floor test compares a shadow-like pixel's darkening 1 − α/g with that of its floor point in another
# view: a shadow darkens a matt floor alike from every side, so the other view must see at least this share
# of it. The fifth left over allows for noise and for a soft rim, where the darkening fades out over a few
# pixels that a calibration error can shift; the lower legs, whose floor points lie in the lighter outer
# part of the shadow, see less than that.
SHADOW_AGREEMENT = 0.8
# The shifts of the floor test (:func:`floor_shifts`): the largest tried, as a share of the working image's width
# (16 pixels at a width of 390: the foreign captures' copies with every camera turned by 0.3° or moved by 2 cm took
# shifts of up to that), ...
MAX_FLOOR_SHIFT = 0.04
# ... the share by which a shift must lower the mean difference of the darkenings compared: with a sound
# calibration the best shift is the one the calibration gives or a pixel away, within a few hundredths of it
# (the shadow's noise and the blocks' quantisation), and the test is left as the calibration has it ...
FLOOR_SHIFT_GAIN = 0.1
# ... the shadow-like pixels compared per view, frame and other view, spread over the view's (the darkening
# changes over many pixels: a few hundred of them say as much as all), ...
FLOOR_SHIFT_SAMPLES = 300
# ... the floor points that must be compared over all frames for a shift to be decided (fewer: none taken), ...
FLOOR_SHIFT_MIN_SAMPLES = 200
# ... and how well the darkening at the shifted place must match: its mean difference from c's below this share of
# c's mean darkening. A shadow seen where it lies matches within about half (the soft rim, noise); shadow-like
# pixels that are clothing, not a shadow (a room lit without cast shadows), differ by three quarters or more of
# their darkening at any shift, a shift merely landing them on the next clothes.
FLOOR_SHIFT_MATCH = 2.0 / 3.0


@dataclass(frozen=True, eq=False)
class FloorGeometry:
    """Where each camera sees the floor behind its pixels, and where the other cameras see those points.

    Built once per rig by :func:`floor_geometry`: the undistortions and projections cost tens of
    milliseconds per camera, the look-ups a frame makes in them almost nothing. Pixels are grouped in
    blocks of FLOOR_BLOCK x FLOOR_BLOCK working pixels (a shadow's darkening changes over many pixels).
    """

    working_shapes: tuple[tuple[int, int], ...]  # (h, w) of each camera's working-resolution frame
    # seen_at[c][b] (blocks of c,) int32: the flat working pixel of camera b that sees the floor point
    # behind each block of camera c; -1 where that ray misses the floor or the footprint, or b does not
    # see the point. None for b = c.
    seen_at: tuple[tuple[np.ndarray | None, ...], ...]
    # shifted_at[c][b]: as seen_at, where the shadows say b sees c's floor points (:func:`floor_shifts`); None
    # (all of it, or a pair's) where they say nothing else than the calibration.
    shifted_at: tuple[tuple[np.ndarray | None, ...], ...] | None = None


def floor_geometry(cameras: Sequence[Camera], volume: np.ndarray, params: SilhouetteParams) -> FloorGeometry:
    """The :class:`FloorGeometry` of a rig, for :func:`floor_shadows`.

    Parameters
    ----------
    cameras : sequence of Camera
        The views' cameras at the images' resolution, world frame with the floor at z = 0.
    volume : (2, 3) float
        Working volume [min; max], metres: shadows are looked for on the floor within its footprint.
    params : SilhouetteParams
        Its ``downsample`` sets the working resolution.
    """
    footprint = np.asarray(volume, dtype=float)[:, :2]
    ds = params.downsample
    shapes = tuple(_working_shape(camera.size, ds) for camera in cameras)
    seen_at = []
    for index, (camera, (height, width)) in enumerate(zip(cameras, shapes, strict=True)):
        block_rows, block_cols = np.divmod(np.arange(_blocks(height) * _blocks(width)), _blocks(width))
        centre = (FLOOR_BLOCK - 1) / 2
        uv = np.column_stack([(block_cols * FLOOR_BLOCK + centre + 0.5) * ds - 0.5,
                              (block_rows * FLOOR_BLOCK + centre + 0.5) * ds - 0.5])
        X, on_floor = _floor_points(camera, uv)
        on_floor &= np.all((X[:, :2] >= footprint[0]) & (X[:, :2] <= footprint[1]), axis=1)
        X = X[on_floor]
        seen = []
        for other, (other_camera, other_shape) in enumerate(zip(cameras, shapes, strict=True)):
            if other == index:
                seen.append(None)
                continue
            pixels = np.full(len(uv), -1, np.int32)
            pixels[on_floor] = _working_pixel(other_camera, other_shape, ds, X)
            seen.append(pixels)
        seen_at.append(tuple(seen))
    return FloorGeometry(shapes, tuple(seen_at))


def _blocks(length: int) -> int:
    """How many FLOOR_BLOCK-pixel blocks cover ``length`` working pixels (a partial last block counts)."""
    return -(-length // FLOOR_BLOCK)


def _floor_points(camera: Camera, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) points where the rays through pixels ``uv`` meet the floor z = 0, and (n,) whether they do."""
    rays = camera.pixel_rays(uv)
    centre = camera.centre
    with np.errstate(divide="ignore", invalid="ignore"):
        distance = -centre[2] / rays[:, 2]
    meets = np.isfinite(distance) & (distance > 0)
    return centre + np.where(meets, distance, 0.0)[:, None] * rays, meets


def _working_pixel(camera: Camera, shape: tuple[int, int], downsample: int, X: np.ndarray) -> np.ndarray:
    """(n,) int32 flat index of the working pixel (of a frame of ``shape``) where ``camera`` sees ``X``
    (n, 3); -1 where it does not (outside its field of view, where the distortion would fold a point back
    into the image, or outside the image)."""
    uv = camera.project(X)
    seen = camera.sees(X) & camera.in_image(uv)
    height, width = shape
    cols = np.clip(np.floor((uv[:, 0] + 0.5) / downsample), 0, width - 1)
    rows = np.clip(np.floor((uv[:, 1] + 0.5) / downsample), 0, height - 1)
    return np.where(seen, rows * width + cols, -1).astype(np.int32)


def floor_shadows(views: Sequence[Evidence], floor: FloorGeometry, params: SilhouetteParams) -> list[np.ndarray]:
    """Per view, which of its shadow-like pixels are the person's shadow on the floor, (h', w') bool each.

    A shadow-like pixel's ray meets the floor (z = 0, the world's convention) at a point X within the
    working volume's footprint. If the pixel is a shadow, X is darkened, and every other camera that sees
    X unoccluded sees it darkened alike (a matt floor looks the same from every side). If the pixel is
    clothing darker than the background behind it, X is bare floor somewhere behind the person, and the
    other cameras see it undarkened. Each other camera votes: no vote where X is outside its image or
    hidden by foreground that is not shadow-like (a limb in front of it); a vote for a shadow where X is
    darkened by at least ``SHADOW_AGREEMENT`` of the pixel's darkening; against otherwise. A pixel is a
    shadow when it has a vote for and at least as many for as against. Rays that never reach the floor
    (above the horizon) are never shadows.

    ``floor`` is the rig's :func:`floor_geometry`, its cameras in the order of ``views``; ``params`` gives
    the weak threshold, above which a pixel that is not shadow-like hides the floor.
    """
    shapes = tuple(view.I_sharp.shape[:2] for view in views)
    if shapes != floor.working_shapes:
        raise InputError(f"floor_shadows: views of working sizes {shapes}, but a floor geometry made for "
                         f"{floor.working_shapes}; expected the same cameras in the same order")
    darkenings = [view.darkening() for view in views]
    looks = [_floor_look(view, darkening, params) for view, darkening in zip(views, darkenings, strict=True)]
    shadows = []
    for index, (view, darkening) in enumerate(zip(views, darkenings, strict=True)):
        shadow = np.zeros(view.shadow_like.shape, bool)
        at, blocks = _shadow_like_blocks(view)
        if len(at) == 0:
            shadows.append(shadow)
            continue
        needed = SHADOW_AGREEMENT * darkening.ravel().take(at)  # (n,)
        votes_for = np.zeros(len(at), np.int32)
        votes_against = np.zeros(len(at), np.int32)
        for other, look in enumerate(looks):
            if other == index:
                continue
            pixels = floor.seen_at[index][other].take(blocks)  # (n,) -1 where there is no floor point to see
            seen_darkening = look.take(pixels)  # NaN where the floor point is not seen: no vote either way
            shifted = floor.shifted_at[index][other] if floor.shifted_at is not None else None
            if shifted is not None:  # the darker of the two places counts (fmax: NaN where neither is seen)
                seen_darkening = np.fmax(seen_darkening, look.take(shifted.take(blocks)))
            votes_for += seen_darkening >= needed
            votes_against += seen_darkening < needed
        shadow.ravel()[at] = (votes_for > 0) & (votes_for >= votes_against)
        shadows.append(shadow)
    return shadows


def floor_shifts(frames: Iterable[Sequence[Evidence]], floor: FloorGeometry, params: SilhouetteParams) -> np.ndarray:
    """(C, C, 2) int: for each camera c and other camera o, the shift (rows, columns, working pixels of o) that
    makes o's darkening of the floor agree with c's where c's shadow-like pixels see the floor; 0 where the
    calibration's own mapping (``floor``) agrees about as well (`FLOOR_SHIFT_GAIN`), where no shift matches c's
    darkening (`FLOOR_SHIFT_MATCH`: not a shadow) or where too few points are compared.

    A shadow darkens a matt floor alike from every side, so where o sees c's floor point it sees c's darkening;
    the floor test (:func:`floor_shadows`) looks there. A calibration off by a fraction of a degree or by a
    couple of centimetres maps c's floor points several pixels away from where o sees them, onto the shadow's
    lighter rim or the bare floor beyond: o votes against, and c's shadow is kept as the person's feet. The
    shadows say where o sees the points: the shift whose darkenings differ least from c's, on average over the
    ``frames`` (each a sequence of every view's :class:`Evidence`, cameras in ``floor``'s order), found coarse to
    fine within `MAX_FLOOR_SHIFT` of the calibration's mapping. Over the few metres of floor a subject's shadow
    covers, a calibration's error moves the mapping about alike, so one shift per pair of views serves every
    frame.
    """
    count = len(floor.working_shapes)
    # Per pair (c, o): o's flat look index base (its frame's place in the looks laid end to end), the rows and
    # columns of o where c's floor points are seen, and c's darkening there; then the looks end to end.
    pairs: dict[tuple[int, int], list[tuple[np.ndarray, ...]]] = {}
    looks, base = [[] for _ in range(count)], np.zeros(count, np.int64)
    for views in frames:
        if len(views) != count:
            raise InputError(f"floor_shifts: a frame of {len(views)} views for a floor geometry of {count} cameras")
        darkenings = [view.darkening() for view in views]
        for index, (view, darkening) in enumerate(zip(views, darkenings, strict=True)):
            looks[index].append(_floor_look(view, darkening, params))
            at, blocks = _shadow_like_blocks(view)
            if len(at) == 0:
                continue
            chosen = evenly_spread(len(at), FLOOR_SHIFT_SAMPLES)
            at, blocks = at[chosen], blocks[chosen]
            for other in range(count):
                if other == index:
                    continue
                pixels = floor.seen_at[index][other].take(blocks)
                seen = pixels >= 0
                rows, cols = np.divmod(pixels[seen], floor.working_shapes[other][1])
                pairs.setdefault((index, other), []).append(
                    (np.full(len(rows), base[other]), rows, cols, darkening.ravel().take(at[seen])))
        base += [len(look[-1]) for look in looks]
    shifts = np.zeros((count, count, 2), int)
    if not pairs:
        return shifts
    flat_looks = [np.concatenate(look) for look in looks]
    for (index, other), parts in pairs.items():
        starts, rows, cols, darkening = (np.concatenate(column) for column in zip(*parts, strict=True))
        if len(rows) < FLOOR_SHIFT_MIN_SAMPLES:
            continue
        shape = floor.working_shapes[other]
        differences = functools.partial(_darkening_differences, flat_looks[other], shape, starts, rows, cols,
                                        darkening)
        shift, least = _coarse_to_fine(differences, round(MAX_FLOOR_SHIFT * shape[1]))
        if (shift is not None and least <= (1.0 - FLOOR_SHIFT_GAIN) * differences(np.zeros((1, 2), int))[0]
                and least < FLOOR_SHIFT_MATCH * darkening.mean()):
            shifts[index, other] = shift
    return shifts


def _darkening_differences(look: np.ndarray, shape: tuple[int, int], starts: np.ndarray, rows: np.ndarray,
                           cols: np.ndarray, darkening: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """(K,) for each of ``shifts`` (K, 2), the mean |o's darkening ``look`` at the points (``rows``, ``cols``) of o's
    frames beginning at ``starts`` in it, shifted − c's ``darkening`` there|, over the points o sees; inf where it
    sees none. A point shifted out of o's frame (of ``shape``) reads its frame's last entry, NaN: not seen."""
    height, width = shape
    r = rows[None, :] + shifts[:, :1]
    c = cols[None, :] + shifts[:, 1:]
    inside = (r >= 0) & (r < height) & (c >= 0) & (c < width)
    seen = look.take(starts[None, :] + np.where(inside, r * width + c, height * width))
    compared = ~np.isnan(seen)
    total = np.where(compared, np.abs(seen - darkening[None, :]), 0.0).sum(axis=1)
    counts = compared.sum(axis=1)
    return np.where(counts > 0, total / np.maximum(counts, 1), np.inf)


def _coarse_to_fine(cost: Callable[[np.ndarray], np.ndarray], reach: int) -> tuple[np.ndarray | None, float]:
    """The integer shift within ``reach`` (both ways, both axes) of least ``cost`` (a function of (K, 2) int shifts
    returning (K,) costs) and that cost: a grid of a quarter of ``reach`` apart, then its best's neighbours at
    half the spacing, down to one pixel; (None, inf) when no shift has a finite cost."""
    spacing = max(1, reach // 4)
    grid = np.arange(-(reach // spacing), reach // spacing + 1) * spacing
    candidates = np.stack(np.meshgrid(grid, grid, indexing="ij"), axis=-1).reshape(-1, 2)
    costs = cost(candidates)
    best = int(np.argmin(costs))
    shift, least = candidates[best], float(costs[best])
    while spacing > 1:
        spacing = max(1, spacing // 2)
        around = shift + spacing * np.array([(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx])
        around = around[np.all(np.abs(around) <= reach, axis=1)]
        costs = cost(around)
        if len(costs) and costs.min() < least:
            shift, least = around[int(np.argmin(costs))], float(costs.min())
    return (shift, least) if np.isfinite(least) else (None, np.inf)


def shifted_floor(floor: FloorGeometry, shifts: np.ndarray) -> FloorGeometry:
    """``floor`` where the floor test also looks at each camera c's floor points shifted by ``shifts[c, o]`` (rows,
    columns) in each other camera o (:func:`floor_shifts`), and takes the darker of the two places; points shifted
    out of o's frame are not seen there.

    Both places, not the shifted one alone: one shift serves the floor around the subject's first place, and a
    calibration's error moves the mapping differently where he walks to, while the calibration's own mapping may
    hold there.
    """
    shifted_at = []
    for index, row in enumerate(floor.seen_at):
        shifted = []
        for other, pixels in enumerate(row):
            if pixels is None or not np.any(shifts[index, other]):
                shifted.append(None)
                continue
            height, width = floor.working_shapes[other]
            rows, cols = np.divmod(pixels, width)
            rows, cols = rows + shifts[index, other, 0], cols + shifts[index, other, 1]
            inside = (pixels >= 0) & (rows >= 0) & (rows < height) & (cols >= 0) & (cols < width)
            shifted.append(np.where(inside, rows * width + cols, -1).astype(np.int32))
        shifted_at.append(tuple(shifted))
    return replace(floor, shifted_at=tuple(shifted_at))


def _shadow_like_blocks(view: Evidence) -> tuple[np.ndarray, np.ndarray]:
    """The view's shadow-like pixels, (n,) int32 flat in its region, and (n,) the floor block of each."""
    if view.region is None or not view.shadow_like.size:
        return np.zeros(0, np.int32), np.zeros(0, np.int32)
    at = flat_nonzero(view.shadow_like.view(np.uint8))
    rows, cols = np.divmod(at, np.int32(view.shadow_like.shape[1]))
    blocks = (((rows + view.region[0].start) // FLOOR_BLOCK) * _blocks(view.I_sharp.shape[1])
              + (cols + view.region[1].start) // FLOOR_BLOCK)
    return at, blocks


def _floor_look(view: Evidence, darkening: np.ndarray, params: SilhouetteParams) -> np.ndarray:
    """What a view says of the floor points it sees: (h w + 1,) float32 indexed by flat working pixel, its
    darkening 1 − α (:meth:`Evidence.darkening`, ``darkening``) smoothed over 3 x 3 pixels (noise), NaN where
    the floor is not seen: behind foreground that is not shadow-like, and in the last entry, which index -1 (no
    floor point there) reads. A NaN compares false with any darkening, so it gives no vote. Outside its region
    nothing differs from the background: the floor is seen there, undarkened (0)."""
    height, width = view.I_sharp.shape[:2]
    look = np.zeros(height * width + 1, np.float32)
    look[-1] = np.nan
    if view.region is not None:
        hidden = (view.difference2 > np.float32(params.weak_threshold**2)) & ~view.shadow_like
        smoothed = cv2.blur(darkening, (3, 3))
        smoothed[hidden] = np.nan
        look[:-1].reshape(height, width)[view.region] = smoothed
    return look
