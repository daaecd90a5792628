"""Automatic initialisation from the data alone (what Horaud et al. 2009 leave open).

On the first frame, and whenever tracking is lost, the pose is found without any prior. Candidate
poses come from a library of joint-angle vectors for the body (real poses sampled from motion-capture
clips and retargeted offline by `pipeline/poselib.py`, plus generic standing, bending and crouching
poses); joint angles do not depend on the subject's size, so no inverse kinematics runs here. Every
candidate is placed on the point cloud and turned to several headings, all hypotheses are scored at
once by the mixture likelihood (eq. 12) on a subsample of the data, the best few get a short EM
refinement on that subsample, and the best of those is fitted to all the data by EM (with the body's
size as a further unknown when the height is not given). A capture may start mid-kick or bent over:
the library holds kicks, bends, crouches and walking poses, not only a T-pose.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from importlib import resources

import numpy as np
from scipy.spatial import cKDTree

from stages.joints import JOINT_NAMES
from stages.tracking.body import BodyModel, Ellipsoids
from stages.tracking.distances import distance_named
from stages.tracking.em import (
    EMParams,
    FitResult,
    Mixture,
    fit,
    hypothesis_scores,
    log_evidence,
    volume_size,
)
from stages.tracking.gauss_newton import HEIGHT_RANGE_M

_J = {name: k for k, name in enumerate(JOINT_NAMES)}
# IK weights per joint: toes are optional in the ground truth and loosely defined.
_IK_WEIGHTS = np.array([0.5 if name.endswith("_toe") else 1.0 for name in JOINT_NAMES])
# Damped least squares for IK: a small pull towards the previous iterate keeps the limb twists (which
# joint positions barely see when a limb is straight) from wandering.
_IK_DAMPING = 1e-4
_IK_ITERATIONS = 60
# The cloud's top (to guess a hypothesis' height when it is not given) is the highest point with a few
# neighbours this close: the body's surface is sampled densely, outliers in the volume are isolated.
_TOP_RADIUS_M = 0.06
_TOP_NEIGHBOURS = 2
# Σ while scoring and at the start of the refinement: hypotheses are off by several centimetres.
_SCORE_SIGMA_M = 0.06
# Each round of the refinement keeps the best quarter of its hypotheses (24 → 6 → 1 by default).
_KEEP_DIVISOR = 4


@dataclass(frozen=True)
class InitParams:
    """Tunables of the initialisation.

    Attributes
    ----------
    headings : int
        Headings tried per library pose, evenly spread over 360°.
    refine : int
        Best-scoring library poses (each at its best heading) refined by EM on the subsample, by
        successive halving: all get `refine_iterations` iterations, the best quarter as many more,
        and so on until one is left.
    score_points : int
        Observations used to score the hypotheses (the cloud's shape, not every point).
    refine_points : int
        Observations used to refine the best hypotheses (a superset of the scoring ones).
    refine_iterations : int
        EM iterations per round of the refinement.
    iterations : int
        EM iterations at most of the final fit to all observations.
    finalists : int
        Hypotheses the refinement keeps for a final fit each: the subsample's ranking can put a
        wrong optimum first. The first-ranked stays the result unless another's log-likelihood on all
        the observations is higher by `finalist_margin` nats per observation.
    finalist_margin : float
        Two fits in nearly the same place differ by hundredths of a nat per observation (a choice
        between them is noise), a fit in a better optimum by tenths: with this margin the runner-up
        wins only where the first-ranked is in a wrong optimum (an arm across the body).
    """

    headings: int = 12
    refine: int = 24
    score_points: int = 120
    refine_points: int = 400
    refine_iterations: int = 4
    iterations: int = 15
    finalists: int = 2
    finalist_margin: float = 0.05


@dataclass(frozen=True)
class InitResult:
    """The chosen initial pose (D,), the fitted body (its height, metres) and the final EM fit."""

    pose: np.ndarray
    height_m: float
    fit: FitResult


def load_pose_library(body: BodyModel) -> np.ndarray:
    """Library poses for `body` (M, D): root at x = y = 0, yaw 0, root height as a fraction of height.

    Read from `data/poses.npz` (built by `pipeline/poselib.py`) when it holds pose vectors for this
    body configuration; a body it does not know (an edited configuration) gets the library's joint
    positions retargeted by inverse kinematics (`library_poses`), which takes seconds.
    """
    path = resources.files("stages.tracking") / "data" / "poses.npz"
    with path.open("rb") as f, np.load(f, allow_pickle=False) as data:
        key = f"poses_{body.name}"
        if key in data and data[key].shape[1] == body.pose_size:
            return np.asarray(data[key], dtype=float)
        joints = np.asarray(data["joints"], dtype=float)
    return library_poses(body, joints)


def heading(joints: np.ndarray) -> float:
    """Yaw (radians) of a skeleton (17, 3): the angle of its right direction (l_hip → r_hip) from +x."""
    right = joints[_J["r_hip"]] - joints[_J["l_hip"]]
    return float(np.arctan2(right[1], right[0]))


def retarget(body: BodyModel, joints: np.ndarray, *, start: np.ndarray | None = None,
             estimate_scale: bool = False) -> tuple[np.ndarray, float]:
    """Pose (D,) (and height, metres) whose joint centres best match `joints` (17, 3): IK by LM.

    Minimises Σ_j w_j ||joint_j(Λ) − joints_j||² over Λ within the joint limits, and over the body's
    overall size with `estimate_scale` (d joint / d ln s = joint − root). Without `start`, it starts
    from the standing pose and from the arms-out pose placed on the pelvis and hip line, and keeps the
    better.
    """
    if start is not None:
        return _retarget_from(body, joints, body.clip(start.astype(float)), estimate_scale)[:2]
    best = None
    for pose in generic_poses(body)[:2]:
        pose[:3] = joints[_J["pelvis"]]
        pose[3] = heading(joints)
        result = _retarget_from(body, joints, pose, estimate_scale)
        if best is None or result[2] < best[2]:
            best = result
    return best[:2]


def _retarget_from(body, joints, pose, estimate_scale):
    """LM iterations of `retarget` from one start; returns (pose, height, cost)."""
    w = np.repeat(np.sqrt(_IK_WEIGHTS), 3)

    def cost_of(b, q):
        return float(np.sum(((joints - b.joint_positions(q)).reshape(-1) * w) ** 2))

    cost = cost_of(body, pose)
    damping = 1e-3
    for _ in range(_IK_ITERATIONS):
        kin = body.fk(pose)
        current = body.joint_positions(kin)
        J = body.point_jacobian(kin, current, body.joint_segment).reshape(-1, body.pose_size)
        if estimate_scale:
            J = np.column_stack([J, (current - kin.t[0]).reshape(-1)])
        Jw = J * w[:, None]
        H = Jw.T @ Jw
        g = Jw.T @ ((joints - current).reshape(-1) * w)
        while damping < 1e6:
            step = np.linalg.solve(H + damping * np.diag(np.diag(H)) + _IK_DAMPING * np.eye(len(H)), g)
            candidate = body.clip(pose + step[: body.pose_size])
            body_c = body
            if estimate_scale:
                body_c = body.scaled(float(np.clip(body.height_m * np.exp(step[-1]), *HEIGHT_RANGE_M)))
            cost_c = cost_of(body_c, candidate)
            if cost_c < cost:
                break
            damping *= 10.0
        else:
            break
        improvement = cost - cost_c
        pose, body, cost, damping = candidate, body_c, cost_c, max(damping / 10.0, 1e-6)
        if improvement < 1e-10:
            break
    return pose, body.height_m, cost


# Generic poses (degrees per DOF-name suffix; "thigh.flex" sets both thighs): standing with the arms
# down or out, bending forward at the hips and the lower back with the arms hanging or along the
# body, and squatting. The bends are split between the pelvis (root pitch, legs kept vertical) and
# the lumbar joint (where the body has one), as people bend; a body without a lumbar joint bends at
# the pelvis only.
_GENERIC = (
    {},
    {"upperarm.abduct": 80},
    {"upperarm.flex": 90},
    {"pitch": 20, "chest.flex": 20, "upperarm.flex": 40},
    {"pitch": 35, "chest.flex": 35},
    {"pitch": 35, "chest.flex": 35, "upperarm.flex": 70},
    {"pitch": 50, "chest.flex": 45, "upperarm.flex": 95},
    {"pitch": 50, "chest.flex": 45, "upperarm.flex": 40, "forearm.flex": 60},
    {"thigh.flex": 50, "shank.flex": 60, "pitch": 20, "upperarm.flex": 40},
    {"thigh.flex": 95, "shank.flex": 110, "pitch": 35, "chest.flex": 15, "upperarm.flex": 60},
)


def generic_poses(body: BodyModel) -> list[np.ndarray]:
    """The generic poses of `_GENERIC` for `body` (D,) each, standing on the floor at the origin.

    Root pitch is compensated at the hips so that the thighs keep their flexion relative to the
    vertical; the root height puts the lower ankle at its standing height.
    """
    poses = []
    standing_ankle = body.joint_positions(body.zero_pose())[_J["l_ankle"], 2]
    for spec in _GENERIC:
        pose = body.zero_pose()
        for key, degrees in {**spec, "thigh.flex": spec.get("thigh.flex", 0) + spec.get("pitch", 0)}.items():
            for d, name in enumerate(body.dof_names):
                if _matches(name, key):
                    pose[d] += np.radians(degrees)
        pose = body.clip(pose)
        ankles = body.joint_positions(pose)[[_J["l_ankle"], _J["r_ankle"]], 2]
        pose[2] += standing_ankle - ankles.min()
        poses.append(pose)
    return poses


def _matches(dof_name: str, key: str) -> bool:
    """Whether "<segment>.<dof>" is named by `key` ("<segment suffix>.<dof>" or "<dof>")."""
    segment, dof = dof_name.split(".")
    key_segment, key_dof = key.split(".") if "." in key else ("", key)
    return dof == key_dof and segment.endswith(key_segment)


def library_poses(body: BodyModel, library: np.ndarray) -> np.ndarray:
    """Pose vectors (M + G, D) for `body`: the generic poses, then library joints (M, 17, 3) retargeted.

    The library joints are at standing height 1 (`pipeline/poselib.py`). Rows have the root at
    x = y = 0, yaw 0, and the root height as a fraction of the body's height.
    """
    poses = generic_poses(body)
    for joints in library:
        pose, _ = retarget(body, joints * body.height_m)
        poses.append(pose)
    poses = np.array(poses)
    poses[:, :2] = 0.0
    poses[:, 3] = 0.0
    poses[:, 2] /= body.height_m
    return poses


def initialise(y: np.ndarray, n: np.ndarray, body: BodyModel, volume: np.ndarray, candidates: np.ndarray,
               *, estimate_height: bool, params: InitParams = InitParams(),
               em: EMParams | None = None, rng: np.random.Generator | None = None) -> InitResult:
    """Find the pose (and height) from one frame's points y (I, 3) and normals n (I, 3).

    Parameters
    ----------
    body : BodyModel
        The body at the known height, or at a first guess when `estimate_height`.
    volume : (2, 3) float
        Working volume (the outlier density's support).
    candidates : (M, D) float
        Library poses for this body (`load_pose_library`).
    estimate_height : bool
        Also estimate the body's height (from the cloud's top, then by EM).
    """
    rng = np.random.default_rng(0) if rng is None else rng
    em = EMParams() if em is None else em
    V = volume_size(volume)
    sample = rng.permutation(len(y))
    ys, ns = y[sample[: params.refine_points]], n[sample[: params.refine_points]]
    centre = np.median(y[:, :2], axis=0)
    top = _cloud_top(y)
    bodies, poses = [], []
    for base in candidates:
        height = body.height_m
        if estimate_height:
            height = float(np.clip(top / _top_ratio(body, base), *HEIGHT_RANGE_M))
        pose = base.copy()
        pose[2] *= height
        bodies.append(body.scaled(height))
        poses.append(pose)
    yaws = np.linspace(0.0, 2 * np.pi, params.headings, endpoint=False)
    mixture = Mixture.initial(body.n_ellipsoids, _SCORE_SIGMA_M, distance_named(em.distance).size)
    scored = sample[: params.score_points]
    scores = _score(y[scored], n[scored], centre, bodies, poses, yaws, mixture, V, em.distance)  # (M, H)
    short = replace(em, max_iterations=params.refine_iterations, displacement_m=0.0,
                    estimate_scale=estimate_height, estimate_lengths=False)
    order = np.argsort(-scores.max(axis=1))[: params.refine]  # distinct poses, each at its best heading
    fits = [fit(ys, ns, bodies[m], _placed(bodies[m], poses[m], yaws[np.argmax(scores[m])], centre), volume,
                short, sigma_m=_SCORE_SIGMA_M) for m in order]
    kept = max(1, params.finalists)
    while len(fits) > kept:  # successive halving: the better quarter gets more iterations
        fits = sorted(fits, key=lambda r: -r.log_likelihood[-1])[: max(kept, len(fits) // _KEEP_DIVISOR)]
        if len(fits) > kept:
            fits = [fit(ys, ns, r.body, r.pose, volume, short, mixture=r.mixture, start=r.estep) for r in fits]
    final = replace(em, max_iterations=params.iterations, estimate_scale=estimate_height)
    ranked = [fit(y, n, r.body, r.pose, volume, final, mixture=replace(r.mixture))
              for r in sorted(fits, key=lambda r: -r.log_likelihood[-1])]
    result = ranked[0]
    for other in ranked[1:]:
        if other.log_likelihood[-1] > result.log_likelihood[-1] + params.finalist_margin * len(y):
            result = other
    return InitResult(pose=result.pose, height_m=result.height_m, fit=result)


def _placed(body: BodyModel, pose: np.ndarray, yaw: float, centre: np.ndarray) -> np.ndarray:
    """The pose turned by `yaw` with the horizontal centroid of its ellipsoid centres on `centre` (2,)."""
    pose = pose.copy()
    pose[3] = yaw
    pose[:2] = 0.0
    pose[:2] = centre - body.ellipsoids(pose).t[:, :2].mean(axis=0)
    return pose


def _score(y, n, centre, bodies, poses, yaws, mixture, V, distance) -> np.ndarray:
    """Log-likelihood (eq. 12) (M, H) of every candidate pose at every heading.

    Turning a hypothesis by ψ about the vertical through `centre` is turning the data by −ψ, so the
    data are turned once per heading (H × I rows) and every candidate's ellipsoids (facing +y, centred
    on the origin) are compared with all of them at once.
    """
    c, s = np.cos(-yaws), np.sin(-yaws)
    Rz = np.zeros((len(yaws), 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
    offset = np.array([centre[0], centre[1], 0.0])
    y_turned = np.einsum("hab,ib->hia", Rz, y - offset).reshape(-1, 3)  # (H·I, 3)
    n_turned = np.einsum("hab,ib->hia", Rz, n).reshape(-1, 3)
    posed = [b.ellipsoids(_placed(b, q, 0.0, np.zeros(2))) for b, q in zip(bodies, poses, strict=True)]
    hypotheses = Ellipsoids(R=np.stack([e.R for e in posed]), t=np.stack([e.t for e in posed]),
                            semi_axes=np.stack([e.semi_axes for e in posed]))
    return hypothesis_scores(y_turned, n_turned, hypotheses, mixture, V, blocks=np.arange(len(yaws) + 1) * len(y),
                             distance=distance)


def _cloud_top(y: np.ndarray) -> float:
    """Height (metres) of the highest observation with `_TOP_NEIGHBOURS` others within `_TOP_RADIUS_M`."""
    neighbours = cKDTree(y).query_ball_point(y, _TOP_RADIUS_M, return_length=True) - 1
    dense = neighbours >= _TOP_NEIGHBOURS
    return float(y[dense, 2].max()) if np.any(dense) else float(y[:, 2].max())


def _top_ratio(body: BodyModel, pose: np.ndarray) -> float:
    """Highest point of the posed body (root height as a fraction of height) over the body's height."""
    pose = pose.copy()
    pose[2] *= body.height_m
    ell = body.ellipsoids(pose)
    z_extent = np.sqrt(np.sum((ell.R[:, 2, :] * ell.semi_axes) ** 2, axis=1))
    return float(np.max(ell.t[:, 2] + z_extent)) / body.height_m


# A limb's segment is taken for misplaced when it explains fewer data than this fraction of what its
# mirror segment explains: left and right limbs have the same surface, and even a limb held against
# the body or turned away from most cameras keeps a good part of its mirror's share, while a forearm put
# on the wrong side of the body by the initialisation explains a small fraction of it.
LIMB_SHARE_RATIO = 0.3
# The comparison only means something when the mirror segment itself explains this many observations
# (a foot or a forearm seen by few cameras is too noisy a reference).
LIMB_MIN_OBSERVATIONS = 20
# Observations used to score the joint-angle hypotheses of a limb (the rest of the body fixed).
_LIMB_SCORE_POINTS = 400
# Hypotheses closer than this (radians, every DOF of the chain) are one: the library repeats itself.
_LIMB_HYPOTHESIS_STEP = 0.1
# Best-scoring limb hypotheses refined by EM on all the data.
_LIMB_REFINE = 3
# A re-initialised limb replaces the fit only when the likelihood gains this much per observation (nats):
# a limb really misplaced gains tenths, while gains of hundredths come from ambiguous data, where taking
# them flips a forearm back and forth from frame to frame.
LIMB_MARGIN = 0.02
# Values per DOF of the grid over the limb's two first joints (shoulder and elbow, hip and knee): the
# library holds whole-body poses, and an arm reaching out from a leaning torso may be in none of them.
_LIMB_GRID_LEVELS = 5


@dataclass(frozen=True)
class Limb:
    """A chain of segments hanging from the torso (arm, leg) and its mirror image.

    Attributes
    ----------
    name : str
        Name of the chain's first segment ("l_upperarm").
    segments, mirror_segments : (S,) int
        Segments of the chain (from the torso outwards) and the mirror chain's same segments.
    dofs, mirror_dofs : (K,) int
        DOFs of the chain and the mirror chain's corresponding DOFs.
    mirror_sign : (K,) float
        A pose mirrored left-right has mirror_dofs = mirror_sign × dofs (twists change sign).
    """

    name: str
    segments: np.ndarray
    mirror_segments: np.ndarray
    dofs: np.ndarray
    mirror_dofs: np.ndarray
    mirror_sign: np.ndarray


_MIRROR_PREFIXES = ("l_", "r_")


def body_limbs(body: BodyModel) -> list[Limb]:
    """The limbs of `body` (`_limbs`), found once per kinematic structure: every frame asks."""
    key = (body.segment_names, body.dof_names, body.parent.tobytes(), body.dof_segment.tobytes(),
           body.dof_axis.tobytes())
    if key not in _LIMBS:
        _LIMBS[key] = _limbs(body)
    return _LIMBS[key]


_LIMBS: dict[tuple, list[Limb]] = {}


def _limbs(body: BodyModel) -> list[Limb]:
    """The limbs of `body`: chains starting at an "l_"/"r_" segment whose parent is neither, with mirrors.

    Mirror segments and DOFs are found by swapping the "l_"/"r_" prefix; the sign of a mirrored DOF is
    that of its axis against the left-right reflection (x → −x) of the original axis (a rotation axis
    is a pseudo-vector: (w_x, −w_y, −w_z)).
    """
    names = list(body.segment_names)

    def mirror(name):
        side = name[:2]
        return ("r_" if side == "l_" else "l_") + name[2:] if side in _MIRROR_PREFIXES else None

    limbs = []
    for s, name in enumerate(names):
        parent = body.parent[s]
        if mirror(name) not in names or (parent >= 0 and mirror(names[parent]) is not None):
            continue
        chain = [s]
        for child in range(s + 1, len(names)):
            if body.parent[child] in chain:
                chain.append(child)
        mirrored = [names.index(mirror(names[c])) for c in chain]
        dofs = [d for d in range(body.pose_size) if body.dof_segment[d] in chain]
        dof_names = list(body.dof_names)
        mirror_dofs = [dof_names.index(mirror(dof_names[d])) for d in dofs]
        reflected = body.dof_axis[dofs] * np.array([1.0, -1.0, -1.0])
        sign = np.sign(np.einsum("ka,ka->k", body.dof_axis[mirror_dofs], reflected))
        limbs.append(Limb(name=name, segments=np.array(chain), mirror_segments=np.array(mirrored),
                          dofs=np.array(dofs), mirror_dofs=np.array(mirror_dofs), mirror_sign=sign))
    return limbs


def segment_shares(body: BodyModel, mixture: Mixture) -> np.ndarray:
    """Fraction of the data each segment of `body` explains (S,): the sum of its ellipsoids' priors π_p.

    After a fit the priors are the mean posteriors (the M-step's π_p = (1/I) Σ_i t_ip), so I times a
    share is the number of observations the segment explains.
    """
    return np.bincount(body.ellipsoid_segment, weights=mixture.pi[:-1], minlength=len(body.segment_names))


def misplaced_limbs(body: BodyModel, result: FitResult, n_observations: int, *,
                    share_ratio: float = LIMB_SHARE_RATIO,
                    min_observations: float = LIMB_MIN_OBSERVATIONS) -> list[Limb]:
    """Limbs of a fit with a segment explaining far fewer data than its mirror segment.

    The data a segment explains are I Σ π_p over its ellipsoids (`segment_shares`). The test is
    absolute (a share against the mirror's share in the same frame), so a bad start cannot make
    itself the norm.
    """
    per_segment = n_observations * segment_shares(body, result.mixture)
    return [limb for limb in body_limbs(body)
            if _starved(per_segment[limb.segments], per_segment[limb.mirror_segments], share_ratio, min_observations)]


def deserted_limbs(body: BodyModel, result: FitResult, usual_shares: np.ndarray, n_observations: int, *,
                   share_ratio: float = LIMB_SHARE_RATIO,
                   min_observations: float = LIMB_MIN_OBSERVATIONS) -> list[Limb]:
    """Limbs of a fit with a segment explaining far fewer data than it usually does.

    `usual_shares` (S,) are the segments' shares of the data over the recent tracked frames (a running
    mean of `segment_shares`). A forearm that EM folded onto its upper arm, or turned away from its data,
    still explains some data, often as many as its mirror (which `misplaced_limbs` compares with), but
    far fewer than it did a few frames before; so does a limb that has just become hidden, for which
    the re-initialisation finds nothing better and the fit stays. A share that stays low becomes the
    usual share within a few tens of frames, which bounds how long a limb is tried again.
    """
    per_segment = n_observations * segment_shares(body, result.mixture)
    usual = n_observations * np.asarray(usual_shares)
    return [limb for limb in body_limbs(body)
            if _starved(per_segment[limb.segments], usual[limb.segments], share_ratio, min_observations)]


def _starved(own: np.ndarray, reference: np.ndarray, share_ratio: float, min_observations: float) -> bool:
    """Whether a segment explains fewer data than `share_ratio` times a reference of at least `min_observations`."""
    return bool(np.any((reference >= min_observations) & (own < share_ratio * reference)))


def reinitialise_limb(y: np.ndarray, n: np.ndarray, result: FitResult, limb: Limb, volume: np.ndarray,
                      em: EMParams, candidates: np.ndarray, *,
                      rng: np.random.Generator | None = None) -> FitResult:
    """Re-initialise one limb of a fit locally; returns the better (by likelihood) of the two fits.

    Joint-angle hypotheses for the limb's DOFs come from the pose library (`candidates`, the limb's
    own values and its mirror's, mirrored), from a grid over its first two joints (`_limb_grid`),
    from the mirror limb's current angles (people often hold both arms alike) and from the current
    angles. Each is scored by the likelihood (eq. 12) with the rest of the body fixed, on a
    subsample, with the limb's priors π set to its mirror's (a limb that explained nothing would
    otherwise be handicapped by its small prior) and under the initialisation's coarse Σ
    (`_SCORE_SIGMA_M`), not the fit's: grid and library angles are tens of millimetres off at best,
    and under a Σ of 2-3 cm they lost to the misplaced limb itself (the test with arms off the grid
    shows it). The best `_LIMB_REFINE` are refined by EM on all the data (the whole body free); the
    best of them replaces the fit when it is better by `LIMB_MARGIN` nats per observation.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    body, pose = result.body, result.pose
    values = np.vstack([candidates[:, limb.dofs], candidates[:, limb.mirror_dofs] * limb.mirror_sign,
                        pose[limb.mirror_dofs] * limb.mirror_sign, pose[limb.dofs], _limb_grid(body, pose, limb)])
    values = np.clip(values, body.lower[limb.dofs], body.upper[limb.dofs])
    _, first = np.unique(np.round(values / _LIMB_HYPOTHESIS_STEP), axis=0, return_index=True)
    hypotheses = np.repeat(pose[None], len(first), axis=0)
    hypotheses[:, limb.dofs] = values[np.sort(first)]
    pi = result.mixture.pi.copy()
    mine = np.isin(body.ellipsoid_segment, limb.segments)
    theirs = np.isin(body.ellipsoid_segment, limb.mirror_segments)
    pi[np.flatnonzero(mine)] = np.maximum(pi[np.flatnonzero(mine)], pi[np.flatnonzero(theirs)])
    mixture = replace(result.mixture, pi=pi / pi.sum())
    coarse = replace(mixture, Sigma=np.eye(len(mixture.Sigma)) * _SCORE_SIGMA_M**2)
    V = volume_size(volume)
    subset = rng.permutation(len(y))[:_LIMB_SCORE_POINTS]
    ys, ns = y[subset], n[subset]
    # The rest of the body does not move: its evidence is computed once, the limb's added per hypothesis.
    rest = log_evidence(ys, ns, body.ellipsoids(pose), coarse, V, which=np.flatnonzero(~mine),
                        distance=em.distance, normal_noise_rad=em.normal_noise_rad)
    scores = hypothesis_scores(ys, ns, body.posed_ellipsoids(hypotheses), coarse, V,
                               which=np.flatnonzero(mine), base=rest, distance=em.distance,
                               normal_noise_rad=em.normal_noise_rad)[:, 0]
    best = result
    for q in hypotheses[np.argsort(scores)[::-1][:_LIMB_REFINE]]:
        refined = fit(y, n, body, q, volume, em, mixture=mixture)
        if refined.log_likelihood[-1] > best.log_likelihood[-1]:
            best = refined
    if best.log_likelihood[-1] < result.log_likelihood[-1] + LIMB_MARGIN * len(y):
        return result
    return best


def _limb_grid(body: BodyModel, pose: np.ndarray, limb: Limb) -> np.ndarray:
    """Limb angles (M, K): every combination of `_LIMB_GRID_LEVELS` values across the joint range of each
    DOF of the limb's first two segments that the data see (twists, which have a prior, keep their
    current value, as do the DOFs further down the chain)."""
    first = np.isin(body.dof_segment[limb.dofs], limb.segments[:2]) & (body.prior_weight[limb.dofs] == 0)
    axes = [np.linspace(body.lower[d], body.upper[d], _LIMB_GRID_LEVELS) for d in limb.dofs[first]]
    grid = np.repeat(pose[limb.dofs][None], _LIMB_GRID_LEVELS ** len(axes), axis=0)
    grid[:, first] = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(axes))
    return grid
