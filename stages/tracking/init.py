"""Automatic initialisation from the data alone (what Horaud et al. 2009 leave open).

On the first frame, and whenever tracking is lost, the pose is found without any prior: a library of
real poses (sampled from motion-capture clips and stored as body-independent joint positions) is
retargeted to the body by inverse kinematics, every library pose is placed on the point cloud and
turned to several headings, the hypotheses are scored by the mixture likelihood (eq. 12), and the
best few are refined by EM (with the body's size as a further unknown when the height is not given).
A capture may start mid-kick: the library holds kicks, bends and walking poses, not only a T-pose.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources

import numpy as np

from stages.joints import JOINT_NAMES
from stages.tracking.body import BodyModel
from stages.tracking.distances import residual_size
from stages.tracking.em import HEIGHT_RANGE_M, EMParams, FitResult, Mixture, e_step, fit, volume_size

_J = {name: k for k, name in enumerate(JOINT_NAMES)}
# IK weights per joint: toes are optional in the ground truth and loosely defined.
_IK_WEIGHTS = np.array([0.5 if name.endswith("_toe") else 1.0 for name in JOINT_NAMES])
# Damped least squares for IK: a small pull towards the previous iterate keeps the limb twists (which
# joint positions barely see when a limb is straight) from wandering.
_IK_DAMPING = 1e-4
_IK_ITERATIONS = 60
# The cloud's top (to guess a hypothesis' height when it is not given) as a high quantile of the
# points' heights rather than the maximum, which one outlier would set.
_CLOUD_TOP_QUANTILE = 0.99
# Points used to score hypotheses: the likelihood ranking needs the cloud's shape, not every point.
_SCORE_POINTS = 300
# Σ while scoring and at the start of the refinement: hypotheses are off by several centimetres.
_SCORE_SIGMA_M = 0.06


@dataclass(frozen=True)
class InitParams:
    """Tunables of the initialisation.

    Attributes
    ----------
    headings : int
        Headings tried per library pose, evenly spread over 360°.
    refine : int
        Best-scoring hypotheses refined by EM.
    iterations : int
        EM iterations per refinement.
    """

    headings: int = 12
    refine: int = 4
    iterations: int = 40


@dataclass(frozen=True)
class InitResult:
    """The chosen initial pose (D,), the body height (metres) and the refining EM fit."""

    pose: np.ndarray
    height_m: float
    fit: FitResult


def load_pose_library() -> np.ndarray:
    """Library poses (M, 17, 3): joints at standing height 1, facing +y, pelvis above the origin.

    Built by `pipeline/poselib.py` from motion-capture clips; stored as `data/poses.npz`.
    """
    path = resources.files("stages.tracking") / "data" / "poses.npz"
    with path.open("rb") as f, np.load(f, allow_pickle=False) as data:
        return np.asarray(data["joints"], dtype=float)


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
    for pose in _generic_poses(body):
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


def _generic_poses(body: BodyModel) -> list[np.ndarray]:
    """Standing with the arms down (the zero pose) and with the arms out, (D,) each."""
    arms_out = body.zero_pose()
    for k, name in enumerate(body.dof_names):
        if name.endswith("upperarm.abduct"):
            arms_out[k] = np.radians(80.0)
    return [body.zero_pose(), arms_out]


def library_poses(body: BodyModel, library: np.ndarray) -> np.ndarray:
    """Retarget every library pose (M, 17, 3) (height 1) to `body`: joint angles (M + 2, D).

    Two generic poses are added: standing with the arms down (the zero pose) and with the arms out.
    Rows have the root at x = y = 0, yaw 0, and the root height of the pose at the body's height.
    """
    poses = _generic_poses(body)
    for joints in library:
        pose, _ = retarget(body, joints * body.height_m)
        poses.append(pose)
    poses = np.array(poses)
    poses[:, :2] = 0.0
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
        Library poses for this body (`library_poses`), root at x = y = 0, any heading.
    estimate_height : bool
        Also estimate the body's height (from the cloud's top, then by EM).
    """
    rng = np.random.default_rng(0) if rng is None else rng
    em = EMParams() if em is None else em
    V = volume_size(volume)
    centre = np.median(y[:, :2], axis=0)
    top = np.quantile(y[:, 2], _CLOUD_TOP_QUANTILE)
    sample = rng.choice(len(y), min(len(y), _SCORE_POINTS), replace=False)
    mixture = Mixture.initial(body.n_ellipsoids, _SCORE_SIGMA_M, residual_size(em.distance))
    scored = []
    for base in candidates:
        base_yaw = base[3]
        height = body.height_m
        if estimate_height:
            height = float(np.clip(top / _top_ratio(body, base), *HEIGHT_RANGE_M))
        sized = body.scaled(height)
        for yaw in np.linspace(0.0, 2 * np.pi, params.headings, endpoint=False):
            pose = base.copy()
            pose[2] *= height / body.height_m
            pose[3] = base_yaw + yaw
            pose[:2] = centre - _pelvis_offset(sized, pose)
            score = e_step(y[sample], n[sample], sized, pose, mixture, V, distance=em.distance)
            scored.append((score.log_likelihood, height, pose))
    scored.sort(key=lambda s: -s[0])
    best = None
    refine = EMParams(distance=em.distance, max_iterations=params.iterations, tolerance=em.tolerance,
                      estimate_scale=estimate_height)
    for _, height, pose in scored[: params.refine]:
        result = fit(y, n, body.scaled(height), pose, volume, refine, sigma_m=_SCORE_SIGMA_M)
        if best is None or result.log_likelihood[-1] > best.log_likelihood[-1]:
            best = result
    return InitResult(pose=best.pose, height_m=best.height_m, fit=best)


def _top_ratio(body: BodyModel, pose: np.ndarray) -> float:
    """Highest point of the posed body (with its root at the pose's height) over the body's height."""
    ell = body.ellipsoids(pose)
    z_extent = np.sqrt(np.sum((ell.R[:, 2, :] * ell.semi_axes) ** 2, axis=1))
    return float(np.max(ell.t[:, 2] + z_extent)) / body.height_m


def _pelvis_offset(body: BodyModel, pose: np.ndarray) -> np.ndarray:
    """Horizontal offset (2,) from the root to the centroid of the posed ellipsoid centres."""
    return body.ellipsoids(pose).t[:, :2].mean(axis=0) - pose[:2]
