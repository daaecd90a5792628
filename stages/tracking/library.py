"""The pose library: joint-angle vectors the initialisation starts from, and retargeting joints to them.

Candidate poses come from real poses sampled from motion-capture clips and retargeted offline by
`pipeline/lab/poselib.py` (stored in `data/poses.npz`), plus generic standing, bending and crouching poses;
joint angles do not depend on the subject's size, so no inverse kinematics runs while tracking. A
capture may start mid-kick or bent over: the library holds kicks, bends, crouches and walking poses,
not only a T-pose.
"""

from __future__ import annotations

from importlib import resources

import numpy as np

from stages.joints import JOINT_NAMES
from stages.tracking.body import BodyModel
from stages.tracking.body_file import load_body
from stages.tracking.gauss_newton import HEIGHT_RANGE_M

_J = {name: k for k, name in enumerate(JOINT_NAMES)}
# IK weights per joint: toes are optional in the ground truth and loosely defined.
_IK_WEIGHTS = np.array([0.5 if name.endswith("_toe") else 1.0 for name in JOINT_NAMES])
# Damped least squares for IK: a small pull towards the previous iterate keeps the limb twists (which
# joint positions barely see when a limb is straight) from wandering.
_IK_DAMPING = 1e-4
_IK_ITERATIONS = 60


def load_pose_library(body: BodyModel) -> np.ndarray:
    """Library poses for `body` (M, D): root at x = y = 0, yaw 0, root height as a fraction of height.

    Read from `data/poses.npz` (built by `pipeline/lab/poselib.py`) when it holds pose vectors for this
    body configuration; a body it does not know (an edited configuration) gets the library's joint
    positions retargeted by inverse kinematics (`library_poses`), which takes seconds.
    """
    path = resources.files("stages.tracking") / "data" / "poses.npz"
    with path.open("rb") as f, np.load(f, allow_pickle=False) as data:
        key = f"poses_{body.name}"
        if key in data and data[key].shape[1] == body.pose_size and _moves_as_shipped(body):
            return np.asarray(data[key], dtype=float)
        joints = np.asarray(data["joints"], dtype=float)
    return library_poses(body, joints)


def _moves_as_shipped(body: BodyModel) -> bool:
    """Whether `body` moves as the shipped body of its name does: the same segments, parents and DOFs (names,
    axes, kinds), so that the library's angle vectors for that body mean the same for it. A body file
    edited from a shipped one keeps its name; its ellipsoids and proportions may change, its joints not."""
    shipped = load_body(body.name)
    return (body.segment_names == shipped.segment_names and body.dof_names == shipped.dof_names
            and np.array_equal(body.parent, shipped.parent) and np.array_equal(body.dof_segment, shipped.dof_segment)
            and np.array_equal(body.dof_axis, shipped.dof_axis)
            and np.array_equal(body.dof_revolute, shipped.dof_revolute))


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

    The library joints are at standing height 1 (`pipeline/lab/poselib.py`). Rows have the root at
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
