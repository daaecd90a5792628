"""The visual shape: rim points and normals on viewing edges (Franco & Boyer's EPVH, as used by the paper).

For a point on camera i's silhouette outline, the viewing ray grazes the surface at one *rim point*,
where the surface normal is the normal ``n`` of the viewing-cone tangent plane. Which points of the ray
are possible is fixed by the other silhouettes: the *viewing edge* is the part of the ray inside every
other viewing cone (with ``tolerated_views`` allowed to disagree). We find it by

1. bounding the ray by the working volume and by each other silhouette's convex hull (exact and cheap:
   the projected ray is a line and the hull a convex polygon in normalised image coordinates);
2. sampling the bounded stretch and testing the masks, then bisecting every in/out transition.

Where on its edge the rim point lies is not fixed by camera i alone. The crude guess is the midpoint.
``rim_placement="osculating"`` uses the other views' cones instead: each edge end lies on another
view's cone, whose tangent plane there has normal ``m``. If the surface were locally a sphere or a
cylinder of radius r touching the ray at ``t*`` (any radius and axis), a plane with unit normal ``m``
tangent to it meets the ray at ``t = t* + r α``, ``α = (1 − m·n) / (m·d)`` (substitute the ray into the
plane ``m·(X − O) = r`` with ``X(t*) − O = r n``). Two edge ends give two such equations in the two
unknowns ``t*`` and r, so the rim point follows; it always lies on the edge because α ≤ 0 at the near
end and α ≥ 0 at the far end.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from calib.camera import Camera, Rig
from stages.rays import box_interval
from stages.reconstruction.contours import Outline, cone_normals, outline, row_norms
from stages.reconstruction.views import blind_beyond_image, in_volume, inside_view, ray_points

# The convex hull of a silhouette is widened by this many pixels before clipping rays, so that lens
# distortion (which bends the hull's straight edges slightly) never cuts off a true part of the cone.
HULL_MARGIN_PX = 2.0
HULL_SIMPLIFY_PX = 1.0
# The sampled stretch of each ray extends this far (metres) beyond the hull bounds, so that the first
# and last samples are outside and every edge end is bracketed.
RANGE_MARGIN_M = 0.01
# Bisection steps per edge end: each halves the bracket. The end is then snapped onto the exact cone
# face, so the bracket only has to be small enough to find the right face: 2 take a 3 cm sample spacing
# to 8 mm, about a pixel at 4 m (4 steps gave the same errors on the body benchmark).
BISECTION_STEPS = 2
# |α| is kept at least this large so that a nearly parallel or noisy end plane cannot push the rim
# point beyond the other end (it pulls the estimate towards that end instead).
MIN_ALPHA = 1e-3
# A ray crossing a cone face at a smaller angle than this (sine) has an ill-defined crossing point.
MIN_FACE_ANGLE_SIN = np.sin(np.radians(5.0))
# An edge end found on the pixel grid lies within about a pixel of the outline it crosses; a nearest
# outline point further away than MAX_SNAP_PX, or a move along the ray longer than MAX_SNAP_M (metres),
# means the face found is not the one crossed: the end keeps its grid position.
MAX_SNAP_PX = 3.0
MAX_SNAP_M = 0.15
OUTLINE_TOLERANCE_KERNEL = np.ones((3, 3), np.uint8)
# Sample this many more rays than observations wanted: a few rays have no edge (their rim point falls
# outside a view's tolerant mask or the working volume); each ray gives at most one point.
RAY_OVERSAMPLING = 1.1
# A phantom edge is scored by its rim point's mean distance to this many rim points of rays that have a
# single edge (which therefore carries their rim point): a few, so that one stray point cannot vouch.
SUPPORT_NEIGHBOURS = 3


@dataclass(frozen=True)
class ViewingEdges:
    """Segments of viewing rays inside all (but the tolerated) other cones.

    Attributes
    ----------
    ray : (E,) int
        Index of the ray each edge lies on.
    t_near, t_far : (E,) float
        Ends of the edge as distances from the camera centre along the ray (metres).
    camera_near, camera_far : (E,) int
        The view whose cone bounds each end, -1 where the end is the working volume's boundary.
    """

    ray: np.ndarray
    t_near: np.ndarray
    t_far: np.ndarray
    camera_near: np.ndarray
    camera_far: np.ndarray


def rim_points(
    masks: Sequence[np.ndarray],
    rig: Rig,
    volume: np.ndarray,
    *,
    n_observations: int,
    tolerated_views: int,
    rim_placement: str,
    samples_per_ray: int,
    contour_smoothing_px: float,
    hidden: Sequence[np.ndarray | None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Rim points (N, 3) and their unit outward normals (N, 3), at most ``n_observations`` of them.

    ``hidden`` holds, per view, None or an (H, W) uint8 map of the part of its image hidden behind something in
    front of the subject (:mod:`stages.reconstruction.occlusion`): a point there counts as inside the view's
    silhouette, and the outline along it casts no ray.
    """
    cameras = list(rig)
    hidden = [None] * len(masks) if hidden is None else list(hidden)
    outlines = [outline(mask, smoothing_px=contour_smoothing_px, hidden=part) for mask, part in zip(masks, hidden,
                                                                                                   strict=True)]
    # Every outline point undistorted once: the convex hulls need them all, and the rays, their cone faces
    # and the snapped edge ends look theirs up instead of undistorting them again.
    normalised = [camera.undistort_pixels(ours.pixels) for camera, ours in zip(cameras, outlines, strict=True)]
    rays = _sample_rays(outlines, round(n_observations * RAY_OVERSAMPLING))
    camera_of, pixels = rays
    if len(camera_of) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    # Rows are gathered with take throughout: indexing a 2-D array by an index array is several times slower.
    origins = np.stack([camera.centre for camera in cameras]).take(camera_of, axis=0)  # (M, 3)
    directions = np.zeros((len(camera_of), 3))
    for index, camera in enumerate(cameras):
        chosen = camera_of == index
        if chosen.any():
            directions[chosen] = camera.normalised_rays(normalised[index].take(pixels[chosen], axis=0))

    # Inside tests accept points up to a pixel outside a silhouette: a grazing ray that runs along another
    # view's outline would otherwise flicker in and out with the pixel grid and break into pieces.
    tolerant = [(*(_dilated(mask, ours.bounds) if part is None else _dilated(*_with_hidden(mask, part))),
                 blind_beyond_image(mask))
                for mask, ours, part in zip(masks, outlines, hidden, strict=True)]
    # The cones the rays are clipped to hold the hidden parts too.
    bounding = [points if part is None else np.concatenate([points, outline_points(camera, part)])
                for camera, points, part in zip(cameras, normalised, hidden, strict=True)]
    edges = _viewing_edges(cameras, tolerant, bounding, volume, origins, directions, camera_of,
                           tolerated_views=tolerated_views, samples_per_ray=samples_per_ray)
    o, d = origins.take(edges.ray, axis=0), directions.take(edges.ray, axis=0)
    count = len(edges.ray)
    # Both ends of every edge at once: (2E,).
    o_ends, d_ends = np.concatenate([o, o]), np.concatenate([d, d])
    t_ends = np.concatenate([edges.t_near, edges.t_far])
    nearest, pixel_distance, on = _nearest_outline_points(
        cameras, outlines, o_ends + t_ends[:, None] * d_ends, np.concatenate([edges.camera_near, edges.camera_far])
    )
    # The cone faces of the rays' own outline points and of the ends' nearest ones, in one pass per view.
    faces = _faces(cameras, outlines, normalised, np.concatenate([camera_of, on]), np.concatenate([pixels, nearest]))
    normals, m_ends = faces[:len(camera_of)], faces[len(camera_of):]
    t_ends = _snap_to_cones(cameras, o_ends, d_ends, t_ends, on, m_ends, pixel_distance)
    t_near, t_far, m_near, m_far = t_ends[:count], t_ends[count:], m_ends[:count], m_ends[count:]
    t_far = np.maximum(t_far, t_near)
    if rim_placement == "osculating":
        t_rim = _osculating_rim(t_near, t_far, m_near, m_far, d, normals.take(edges.ray, axis=0))
    else:
        t_rim = 0.5 * (t_near + t_far)
    points = o + t_rim[:, None] * d
    kept = _one_edge_per_ray(edges.ray, points, t_far - t_near)
    points, point_normals = points.take(kept, axis=0), normals.take(edges.ray[kept], axis=0)
    keep = in_volume(points, volume)
    points, point_normals = points.compress(keep, axis=0), point_normals.compress(keep, axis=0)
    if len(points) > n_observations:
        chosen = np.unique(np.linspace(0, len(points) - 1, n_observations).round().astype(int))
        points, point_normals = points[chosen], point_normals[chosen]
    return points, point_normals


def _dilated(mask: np.ndarray, bounds: tuple[int, int, int, int]) -> tuple[np.ndarray, tuple[int, int]]:
    """``mask`` (H, W) grown by one pixel, as ``(box (h, w), corner (column, row))``: the grown mask in the
    box ``bounds`` around its foreground widened by a pixel, outside which it is background (a person fills
    a small part of the frame; dilating the whole image cost as much as a third of the ray tests, and
    lookups in the small box stay in cache)."""
    left, top, width, height = bounds
    if width == 0:
        return mask, (0, 0)
    top, left = max(top - 1, 0), max(left - 1, 0)
    box = mask[top:top + height + 2, left:left + width + 2]  # clipped at the image's far edges
    return cv2.dilate(box, OUTLINE_TOLERANCE_KERNEL), (left, top)


def _with_hidden(mask: np.ndarray, hidden: np.ndarray) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """``(union (H, W) uint8, bounds)``: the silhouette ``mask`` with the ``hidden`` part of the view, and the box
    around both."""
    union = cv2.bitwise_or(mask, hidden)
    return union, cv2.boundingRect(union)


def outline_points(camera: Camera, mask: np.ndarray) -> np.ndarray:
    """(n, 2) the vertices of the outer outlines of ``mask`` (H, W) uint8 in normalised image coordinates: enough for
    its convex hull (`hull_bounds`)."""
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return np.zeros((0, 2))
    return camera.undistort_pixels(np.concatenate(contours).reshape(-1, 2).astype(np.float64))


def _one_edge_per_ray(ray: np.ndarray, points: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Indices of the one edge kept per ray, given edges' rays (E,), rim points (E, 3) and lengths (E,).

    A ray through a contour point touches the body only at its rim point, so of a ray's several edges
    one holds the rim and the others are phantom parts of the visual hull. Which one is not fixed by the
    ray alone (the rim edge is not always the first along the ray: a phantom in front of the body is not
    opaque). A ray with a single edge holds its rim point; the real surface is covered by such points from
    every view, while a phantom, lying in free space, is not: each ray keeps the edge whose rim point is
    closest to them (mean distance to ``SUPPORT_NEIGHBOURS`` of them). Without any single-edge ray, the
    longest edge is kept (phantoms are mostly thin slivers between cones).
    """
    single = np.bincount(ray)[ray] == 1
    score = np.zeros(len(ray))
    if single.any() and not single.all():
        neighbours = min(SUPPORT_NEIGHBOURS, int(single.sum()))
        # Unbalanced, uncompacted: quicker to build for one query, with the same distances.
        tree = cKDTree(points.compress(single, axis=0), balanced_tree=False, compact_nodes=False)
        distance, _ = tree.query(points.compress(~single, axis=0), k=neighbours)
        score[~single] = distance.reshape(len(distance), -1).mean(axis=1)
    elif not single.any():
        score = -length
    ranked = _lexsort_mostly_distinct(ray, score)  # by ray, best score first
    ray_sorted = ray[ranked]
    return ranked[np.diff(ray_sorted, prepend=-1) != 0]


def _sample_rays(outlines: list[Outline], n_rays: int) -> tuple[np.ndarray, np.ndarray]:
    """``(camera (M,), outline index (M,))``: usable outline points spread evenly by arc length.

    Every camera with a usable outline gets an equal share, so that no view dominates the data.
    """
    usable_cameras = [index for index, ours in enumerate(outlines) if ours.usable.any()]
    camera_of, picked = [], []
    for index in usable_cameras:
        ours = outlines[index]
        candidates = np.flatnonzero(ours.usable)
        share = max(1, round(n_rays / len(usable_cameras)))
        arc = ours.arc_length[candidates]
        targets = np.linspace(arc[0], arc[-1], min(share, len(candidates)), endpoint=False)
        # Increasing targets pick non-decreasing candidates: repeats are neighbours (np.unique without a sort).
        chosen = candidates[np.minimum(np.searchsorted(arc, targets), len(candidates) - 1)]
        chosen = chosen[np.diff(chosen, prepend=-1) != 0]
        camera_of.append(np.full(len(chosen), index))
        picked.append(chosen)
    if not camera_of:
        return np.zeros(0, int), np.zeros(0, int)
    return np.concatenate(camera_of), np.concatenate(picked)


def _viewing_edges(
    cameras: list[Camera],
    masks: Sequence[tuple[np.ndarray, tuple[int, int]]],
    normalised: list[np.ndarray],
    volume: np.ndarray,
    origins: np.ndarray,
    directions: np.ndarray,
    camera_of: np.ndarray,
    *,
    tolerated_views: int,
    samples_per_ray: int,
) -> ViewingEdges:
    """The viewing edges of rays ``origins + t directions`` (M, 3) cast from cameras ``camera_of`` (M,), given
    each view's mask as ``(box, corner, blind)`` (see ``_dilated``; ``blind``: the view does not frame the whole
    person, :func:`~stages.reconstruction.views.blind_beyond_image`) and the points whose convex hull bounds its
    cone, in normalised image coordinates ``normalised``."""
    t_low, t_high = box_interval(origins, directions, volume)
    hull_low, hull_high = hull_bounds(cameras, normalised, origins, directions, camera_of, tolerated_views,
                                       [blind for _, _, blind in masks])
    t_low = np.maximum(t_low, hull_low - RANGE_MARGIN_M)
    t_high = np.minimum(t_high, hull_high + RANGE_MARGIN_M)
    alive = np.flatnonzero(t_high > t_low)
    if len(alive) == 0:
        return ViewingEdges(*(np.zeros(0, int),) * 5)
    fractions = np.linspace(0.0, 1.0, samples_per_ray)  # (S,)
    t = t_low[alive, None] + (t_high - t_low)[alive, None] * fractions  # (A, S)
    ray_of_sample = np.repeat(alive, samples_per_ray)
    X = ray_points(origins.take(alive, axis=0), directions.take(alive, axis=0), t)
    ok, known = _inside_enough(cameras, masks, camera_of[ray_of_sample], X, tolerated_views)
    ok = ok.reshape(t.shape)
    # A single outside sample between inside ones is a grazing ray flickering along another view's
    # outline, not a gap in the body: close it.
    ok[:, 1:-1] |= ok[:, :-2] & ok[:, 2:]

    # Runs of consecutive inside samples; a run touching the stretch's end is bounded by the volume.
    padded = np.zeros((len(ok), ok.shape[1] + 2), bool)
    padded[:, 1:-1] = ok
    rows, starts = np.nonzero(padded[:, 1:-1] & ~padded[:, :-2])
    _, ends = np.nonzero(padded[:, 1:-1] & ~padded[:, 2:])  # same row order as starts (row-major)
    # Both ends of every edge are refined together: (2E,) inside sample and its outside neighbour.
    rows2 = np.concatenate([rows, rows])
    inner = np.concatenate([starts, ends])
    outer = np.concatenate([starts - 1, ends + 1])
    t_end, camera_end = _refine_ends(cameras, masks, origins, directions, camera_of, alive[rows2], t, rows2,
                                     inner, outer, known, tolerated_views)
    count = len(rows)
    return ViewingEdges(alive[rows], t_end[:count], t_end[count:], camera_end[:count], camera_end[count:])


def _inside_enough(
    cameras, masks, camera_of: np.ndarray, X: np.ndarray, tolerated_views: int
) -> tuple[np.ndarray, np.ndarray]:
    """``(ok (N,) bool, known (C, N) int8)``: whether points ``X`` (3, N), each on a ray cast from
    ``camera_of`` (N,), are outside at most ``tolerated_views`` views (a ray's own view counts it as
    inside), and the answers of the views that were asked (1 inside, 0 outside, -1 not asked).

    Views are tested one after the other on the points still in the running: with the exact hull a
    point leaves at its first outside view, so later views test only a fraction of the points.
    """
    misses = np.zeros(X.shape[1], np.int16)
    known = np.full((len(cameras), X.shape[1]), -1, np.int8)
    running = np.arange(X.shape[1])
    for index, (camera, (mask, corner, blind)) in enumerate(zip(cameras, masks, strict=True)):
        tested = running[camera_of[running] != index]
        inside = inside_view(camera, mask, X.take(tested, axis=1), corner, blind)  # take: X[:, tested], faster
        known[index, tested] = inside
        misses[tested] += ~inside  # tested holds each point once
        running = running[misses[running] <= tolerated_views]
    return misses <= tolerated_views, known


def _inside_each(cameras, masks, camera_of: np.ndarray, X: np.ndarray, known: np.ndarray) -> np.ndarray:
    """(C, N) bool: whether points ``X`` (3, N) are inside view c; the view a point's ray came from says yes.

    Only the views whose answer ``known`` (C, N) (from :func:`_inside_enough`: 1, 0, or -1 not asked) lacks
    are asked: the edge ends' samples were all tested there, most of them by every view.
    """
    result = known == 1
    result[camera_of, np.arange(X.shape[1])] = True
    for index, (camera, (mask, corner, blind)) in enumerate(zip(cameras, masks, strict=True)):
        asked = np.flatnonzero((known[index] < 0) & (camera_of != index))
        result[index, asked] = inside_view(camera, mask, X.take(asked, axis=1), corner, blind)
    return result


def _refine_ends(cameras, masks, origins, directions, camera_of, ray, t, rows, inner, outer, known, tolerated_views):
    """Each edge end between the inside sample ``inner`` (E,) and its outside neighbour ``outer`` (E,) of
    rows ``rows`` (E,) of the samples ``t``, whose views' answers so far are ``known`` (C, samples).

    The views that are inside at ``inner`` but outside at ``outer`` are the cones the ray leaves in
    between; each such crossing is bisected against that one view alone (a fifth of the work of testing
    every view), and the end is the crossing that brings the number of outside views above
    ``tolerated_views``, counted from the inner side. Returns the end's ray parameter (E,) and the camera
    whose cone it crosses (E,), -1 when the end is the sampled stretch's boundary (the volume).
    """
    samples = t.shape[1]
    bounded = (outer >= 0) & (outer < samples)
    t_end = t[rows, inner]
    camera = np.full(len(rows), -1)
    idx = np.flatnonzero(bounded)
    if len(idx) == 0:
        return t_end, camera
    ray, own = ray[idx], camera_of[ray[idx]]
    t_in, t_out = t_end[idx], t[rows[idx], outer[idx]]
    # Both samples of every end at once, (C, 2E'): inner ones first.
    sample = rows[idx] * samples
    X = ray_points(np.concatenate([origins.take(ray, axis=0)] * 2), np.concatenate([directions.take(ray, axis=0)] * 2),
                   np.concatenate([t_in, t_out]))
    inside = _inside_each(cameras, masks, np.concatenate([own, own]), X,
                          known.take(np.concatenate([sample + inner[idx], sample + outer[idx]]), axis=1))
    inside_in = inside[:, :len(idx)]  # (C, E')
    flips = inside_in & ~inside[:, len(idx):]
    view, end = np.nonzero(flips)  # one crossing per (view, end), grouped by view
    lo, hi = t_in[end], t_out[end]  # lo inside, hi outside that view
    o, d = origins.take(ray[end], axis=0), directions.take(ray[end], axis=0)
    groups = np.searchsorted(view, np.arange(len(cameras) + 1))
    for _ in range(BISECTION_STEPS):
        mid = 0.5 * (lo + hi)
        X = ray_points(o, d, mid)
        inside = np.zeros(len(mid), bool)
        for index, (camera_c, (mask, corner, blind)) in enumerate(zip(cameras, masks, strict=True)):
            part = slice(groups[index], groups[index + 1])
            inside[part] = inside_view(camera_c, mask, X[:, part], corner, blind)
        lo = np.where(inside, mid, lo)
        hi = np.where(inside, hi, mid)
    crossing = 0.5 * (lo + hi)
    # The end is the k-th crossing from the inner side, k = the views still allowed to disagree there.
    needed = tolerated_views + 1 - (~inside_in).sum(axis=0)  # (E',)
    order = _lexsort_mostly_distinct(end, np.abs(crossing - t_in[end]))
    sorted_end = end[order]
    rank = np.arange(len(order)) - np.searchsorted(sorted_end, sorted_end)
    available = np.bincount(end, minlength=len(idx))
    wanted = np.minimum(needed, available) - 1
    picked = order[rank == wanted[sorted_end]]
    t_end[idx[end[picked]]] = crossing[picked]
    camera[idx[end[picked]]] = view[picked]
    return t_end, camera


def _lexsort_mostly_distinct(key: np.ndarray, then: np.ndarray) -> np.ndarray:
    """``np.lexsort((then, key))``, faster when most ``key`` (n,) values occur once: a stable sort by ``key``,
    then by ``then`` (n,) only among the repeated keys (sorting every element by ``then`` was most of the
    cost: edge ends crossed by several views, rays with several edges)."""
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    repeated = sorted_key[1:] == sorted_key[:-1]
    if repeated.any():
        shared = np.zeros(len(order), bool)
        shared[1:] |= repeated
        shared[:-1] |= repeated
        some = np.flatnonzero(shared)
        order[some] = order[some][np.lexsort((then[order[some]], sorted_key[some]))]
    return order


def hull_bounds(cameras, normalised, origins, directions, camera_of, tolerated_views, blind):
    """Ray parameters ``(low (M,), high (M,))`` outside which a ray leaves more than ``tolerated_views``
    silhouettes' convex hulls, given each view's outline in normalised image coordinates ``normalised``; the
    views ``blind`` (C,) bool beyond their images (:func:`~stages.reconstruction.views.blind_beyond_image`) bound
    nothing.

    For camera j the hull is a convex polygon ``e_k · x <= c_k`` in normalised image coordinates x, and
    the ray projects to ``x(t) = (A_xy + t B_xy) / (A_z + t B_z)`` with ``A = R_j o + t_j``, ``B = R_j d``;
    multiplying by the positive depth makes every edge a linear inequality ``p t <= q`` in t.
    """
    n_rays = len(origins)
    lows = np.full((len(cameras), n_rays), -np.inf)
    highs = np.full((len(cameras), n_rays), np.inf)
    for index, (camera, ours) in enumerate(zip(cameras, normalised, strict=True)):
        others = np.flatnonzero(camera_of != index)  # indices: used four times
        if blind[index]:
            continue
        if len(ours) == 0:
            lows[index, others], highs[index, others] = np.inf, -np.inf
            continue
        e, c = _hull_halfplanes(camera, ours)
        A = origins.take(others, axis=0) @ camera.R.T + camera.t  # (M', 3)
        B = directions.take(others, axis=0) @ camera.R.T
        # Depth A_z + t B_z > 0 is one more half-line. Stored edge-major, (K + 1, M'): the reductions over
        # a ray's half-lines then run across contiguous rows, ten times faster than along each ray's row.
        p = _edge_major(B[:, :2] @ e.T - B[:, 2:] * c, -B[:, 2])
        q = _edge_major(A[:, 2:] * c - A[:, :2] @ e.T, A[:, 2])
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = q / p
        # Reductions over the half-lines that bound each side, without a masked copy of ``bound`` per side.
        low = np.max(bound, axis=0, where=p < 0, initial=-np.inf)
        high = np.min(bound, axis=0, where=p > 0, initial=np.inf)
        parallel = p == 0  # a ray parallel to an edge: outside for good if it starts outside
        if parallel.any():
            never = np.any(parallel & (q < 0), axis=0)
            low[never], high[never] = np.inf, -np.inf
        lows[index, others], highs[index, others] = low, high
    order = tolerated_views  # the (k+1)-th most restrictive bound may be violated by k views
    if order == 0:  # the exact hull: the tightest bound, without sorting
        return lows.max(axis=0), highs.min(axis=0)
    low = -np.sort(-lows, axis=0)[min(order, len(cameras) - 1)]
    high = np.sort(highs, axis=0)[min(order, len(cameras) - 1)]
    return low, high


def _edge_major(per_edge: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(K + 1, M) C-ordered: the rows of ``per_edge`` (M, K) transposed, then ``depth`` (M,)."""
    stacked = np.empty((per_edge.shape[1] + 1, per_edge.shape[0]))
    stacked[:-1] = per_edge.T
    stacked[-1] = depth
    return stacked


def _hull_halfplanes(camera: Camera, normalised: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(e (K, 2), c (K,))``: the convex hull of outline points ``normalised`` (L, 2) (normalised image
    coordinates) as ``e · x <= c``."""
    hull = cv2.convexHull(normalised.astype(np.float32))
    # Fewer hull edges make clipping cheaper; the simplified polygon cuts at most this far inside the
    # hull, so the margin below grows by as much.
    simplify = HULL_SIMPLIFY_PX / min(camera.K[0, 0], camera.K[1, 1])
    hull = cv2.approxPolyDP(hull, simplify, closed=True).reshape(-1, 2).astype(np.float64)
    if len(hull) < 3:
        # A degenerate outline (a line of pixels): bound it by its box.
        low, high = hull.min(axis=0), hull.max(axis=0)
        hull = np.array([[low[0], low[1]], [high[0], low[1]], [high[0], high[1]], [low[0], high[1]]])
    edge = np.concatenate([hull[1:], hull[:1]]) - hull
    e = edge[:, ::-1] * (1.0, -1.0)  # (dy, -dx)
    e /= np.maximum(row_norms(e), 1e-15)
    centroid = np.add.reduce(hull, axis=0) / len(hull)  # hull.mean(axis=0)
    flip = np.einsum("ij,ij->i", e, centroid - hull) > 0
    e[flip] *= -1.0
    margin = (HULL_MARGIN_PX + HULL_SIMPLIFY_PX) / min(camera.K[0, 0], camera.K[1, 1])
    return e, np.einsum("ij,ij->i", e, hull) + margin


def _faces(cameras, outlines, normalised, view: np.ndarray, index: np.ndarray) -> np.ndarray:
    """(n, 3) outward unit normals of the viewing-cone faces at outline points ``index`` (n,) of the views
    ``view`` (n,), whose outlines undistorted are ``normalised``; zero where ``view`` is -1.

    Computed for the points asked for only (the rays and the edge ends use about half of the outline), each
    distinct point once: a fifth of the edge ends share their nearest outline point with another end, and
    some with a ray.
    """
    normals = np.zeros((len(index), 3))
    for camera_index, (camera, ours) in enumerate(zip(cameras, outlines, strict=True)):
        chosen = np.flatnonzero(view == camera_index)
        if len(chosen):
            points, which = _distinct(index[chosen], len(ours))
            normals[chosen] = cone_normals(camera, normalised[camera_index].take(points, axis=0),
                                           ours.tangents.take(points, axis=0),
                                           ours.outward.take(points, axis=0)).take(which, axis=0)
    return normals


def _distinct(index: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(index, return_inverse=True)`` for indices ``index`` (n,) into ``size`` elements, by marking
    them rather than sorting."""
    present = np.zeros(size, bool)
    present[index] = True
    return np.flatnonzero(present), np.cumsum(present)[index] - 1


def _nearest_outline_points(cameras, outlines, X: np.ndarray, view: np.ndarray):
    """``(nearest (E,), pixel_distance (E,), view (E,))`` for edge ends ``X`` (E, 3) found on the cones of the
    views ``view`` (E,) (-1: on the working volume): the index of the outline point of that view nearest
    to the end's image, and its distance in pixels; ``view`` becomes -1 where the view has no outline."""
    nearest = np.zeros(len(X), int)
    pixel_distance = np.full(len(X), np.inf)
    view = view.copy()
    for index, (camera, ours) in enumerate(zip(cameras, outlines, strict=True)):
        chosen = np.flatnonzero(view == index)
        if len(chosen) == 0:
            continue
        if len(ours) == 0:
            view[chosen] = -1
            continue
        tree = cKDTree(ours.pixels, balanced_tree=False, compact_nodes=False)  # built once, queried once
        pixel_distance[chosen], nearest[chosen] = tree.query(camera.project(X.take(chosen, axis=0)))
    return nearest, pixel_distance, view


def _snap_to_cones(cameras, o, d, t_end, view, m, pixel_distance) -> np.ndarray:
    """(E,) edge ends ``o + t_end d`` (E, 3) moved onto the exact cone faces.

    An end found on the pixel grid lies on the cone of ``view`` (E,); the outline point of that view
    nearest to its image, ``pixel_distance`` (E,) away, gives the face (the plane through the camera centre
    and the outline's tangent line, with outward normal ``m`` (E, 3) from :func:`_faces`), and the end
    moves to where the ray meets that plane. A ray nearly parallel to the face (or a move longer than
    ``MAX_SNAP_M``, or a nearest point further than ``MAX_SNAP_PX``) keeps the grid position, and so do
    ends on the working volume (``view`` -1, zero normal).
    """
    centres = np.stack([camera.centre for camera in cameras])
    facing = np.einsum("ij,ij->i", m, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_plane = np.einsum("ij,ij->i", m, centres.take(view, axis=0) - o) / facing
    good = (
        (view >= 0)
        & (np.abs(facing) > MIN_FACE_ANGLE_SIN)
        & (pixel_distance < MAX_SNAP_PX)
        & (np.abs(t_plane - t_end) < MAX_SNAP_M)
    )
    return np.where(good, t_plane, t_end)


def _osculating_rim(t_near, t_far, m_near, m_far, d, n) -> np.ndarray:
    """(E,) ray parameter of each edge's rim point from the cone faces ``m`` (E, 3) at its two ends.

    Solves ``t_near = t* + r α_near``, ``t_far = t* + r α_far`` (module docstring). Falls back to the
    midpoint where an end is not on a cone (the working volume) or the ray grazes the end's face, which
    makes α meaningless.
    """
    facing_near = np.einsum("ij,ij->i", m_near, d)
    facing_far = np.einsum("ij,ij->i", m_far, d)
    informative = (facing_near < -MIN_FACE_ANGLE_SIN) & (facing_far > MIN_FACE_ANGLE_SIN)
    with np.errstate(divide="ignore", invalid="ignore"):
        alpha_near = np.minimum((1.0 - np.einsum("ij,ij->i", m_near, n)) / facing_near, -MIN_ALPHA)
        alpha_far = np.maximum((1.0 - np.einsum("ij,ij->i", m_far, n)) / facing_far, MIN_ALPHA)
        t_rim = (alpha_far * t_near - alpha_near * t_far) / (alpha_far - alpha_near)
    return np.where(informative, t_rim, 0.5 * (t_near + t_far))
