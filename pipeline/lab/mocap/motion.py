"""Motion-capture clips (CMU ASF/AMC and BVH) as skeletons moving in the pipeline's world frame.

The synthetic captures (``pipeline/lab/synth``) are driven by real human motion, and the tracker's pose
library samples real poses; both read clips through ``load_clip``, which returns a ``Motion``: every
bone's world rotation, start and end per frame, and the 17 joints of ``stages.joints.JOINT_NAMES``.

World frame
-----------
Metres, right-handed, +z up (CAPTURE_FORMAT.md). Both formats are Y-up; a clip's points are rotated by
``calib.world.up_rotation("+y")``, ``(x, y, z) -> (x, -z, y)``. The floor: the whole clip is shifted
vertically so that the lowest *foot point* over the clip sits at z = 0, a foot point being the start or
end of a foot or toe bone (ankle, ball of the foot, toe tip). Slicing and resampling keep that frame (no
second shift), so a slice's ground truth agrees with the whole clip's.

Units
-----
ASF: ``:units length L`` means one file unit is ``1 / L`` inch (CMU: ``length 0.45``, 0.05644 m).
BVH stores no unit; ``length_unit_m`` gives it, or it is inferred from the rest pose: of metres,
centimetres, millimetres, inches and CMU's ASF unit, the one that makes the rest skeleton's height closest
to 1.7 m (the CMU conversions in ASF units and the Daz-style 09_01.bvh in centimetres are both found).

Forward kinematics
------------------
ASF/AMC (CMU's convention, README of the clips): ``R_bone = R_parent C M Cᵀ`` with ``C`` the bone's
``axis`` rotation and ``M`` the product of the frame's dof rotations, the later-listed on the left
(``dof rx ry rz`` gives ``Rz Ry Rx``); ``bone_end = bone_start + length R_bone direction``; a bone starts
where its parent ends. The root is a zero-length bone at the AMC root translation.
BVH: ``W_joint = W_parent L`` with ``L`` the product of the rotation channels in the order listed
(``Zrotation Yrotation Xrotation`` gives ``Rz Ry Rx``), ``p_joint = p_parent + W_parent offset``. A BVH
joint is a bone starting at the joint; it ends at its End Site, at its child, or (several children) at
the mean of its children's starts.
In both formats ``bone_rotations`` is the rotation of the bone from the skeleton's rest pose (every
channel zero) to the frame's pose, in world axes: identity at rest.

Mapping to JOINT_NAMES
----------------------
CMU names (the ASF and the BVH conversions in ``mocap/bvh``): pelvis = midpoint of the starts of lfemur
and rfemur (the hip joints); l_hip / r_hip = start of lfemur / rfemur; l_knee = start of ltibia;
l_ankle = start of lfoot; l_toe = start of ltoes (ball of the foot); neck = start of lowerneck (top of the
thorax); head = midpoint of the head bone; l_shoulder = start of lhumerus; l_elbow = start of lradius;
l_wrist = start of lwrist; ``r_`` likewise with the ``r`` bones.
Daz-style names (the CMU 09_01 retarget): pelvis = midpoint of lThigh and rThigh; l_hip = lThigh;
l_knee = lShin; l_ankle = lFoot; l_toe = end of lFoot (its End Site, the ball of the foot); neck = neck;
head = midpoint of the head joint and the midpoint of leftEye and rightEye; l_shoulder = lShldr;
l_elbow = lForeArm; l_wrist = lHand (all "start of" the named joint).
CMU's ``l`` and Daz's ``l`` are the subject's anatomical left, as in joints.csv.

Resampling
----------
``Motion.resample`` interpolates each bone's world rotation by spherical linear interpolation
(``scipy.spatial.transform.Slerp``) and the root translation linearly, then recomputes every position by
forward kinematics, so bone lengths stay exact at the new frames.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from calib.errors import InputError
from calib.world import up_rotation
from pipeline.lab.mocap.asf_amc import read_asf_amc
from pipeline.lab.mocap.bvh import read_bvh
from pipeline.lab.mocap.raw import RawClip
from stages.joints import JOINT_NAMES

# How each joints.csv joint is read off a skeleton: a list of (bone, "start" | "end", weight).
_CMU_JOINTS = {
    "pelvis": [("lfemur", "start", 0.5), ("rfemur", "start", 0.5)],
    "neck": [("lowerneck", "start", 1.0)],
    "head": [("head", "start", 0.5), ("head", "end", 0.5)],
    "l_shoulder": [("lhumerus", "start", 1.0)],
    "r_shoulder": [("rhumerus", "start", 1.0)],
    "l_elbow": [("lradius", "start", 1.0)],
    "r_elbow": [("rradius", "start", 1.0)],
    "l_wrist": [("lwrist", "start", 1.0)],
    "r_wrist": [("rwrist", "start", 1.0)],
    "l_hip": [("lfemur", "start", 1.0)],
    "r_hip": [("rfemur", "start", 1.0)],
    "l_knee": [("ltibia", "start", 1.0)],
    "r_knee": [("rtibia", "start", 1.0)],
    "l_ankle": [("lfoot", "start", 1.0)],
    "r_ankle": [("rfoot", "start", 1.0)],
    "l_toe": [("ltoes", "start", 1.0)],
    "r_toe": [("rtoes", "start", 1.0)],
}
_CMU_FOOT_BONES = ("lfoot", "ltoes", "rfoot", "rtoes")

_DAZ_JOINTS = {
    "pelvis": [("lThigh", "start", 0.5), ("rThigh", "start", 0.5)],
    "neck": [("neck", "start", 1.0)],
    "head": [("head", "start", 0.5), ("leftEye", "start", 0.25), ("rightEye", "start", 0.25)],
    "l_shoulder": [("lShldr", "start", 1.0)],
    "r_shoulder": [("rShldr", "start", 1.0)],
    "l_elbow": [("lForeArm", "start", 1.0)],
    "r_elbow": [("rForeArm", "start", 1.0)],
    "l_wrist": [("lHand", "start", 1.0)],
    "r_wrist": [("rHand", "start", 1.0)],
    "l_hip": [("lThigh", "start", 1.0)],
    "r_hip": [("rThigh", "start", 1.0)],
    "l_knee": [("lShin", "start", 1.0)],
    "r_knee": [("rShin", "start", 1.0)],
    "l_ankle": [("lFoot", "start", 1.0)],
    "r_ankle": [("rFoot", "start", 1.0)],
    "l_toe": [("lFoot", "end", 1.0)],
    "r_toe": [("rFoot", "end", 1.0)],
}
_DAZ_FOOT_BONES = ("lFoot", "rFoot")

_SKELETON_CONVENTIONS = (("CMU", _CMU_JOINTS, _CMU_FOOT_BONES), ("Daz", _DAZ_JOINTS, _DAZ_FOOT_BONES))


@dataclass(frozen=True, eq=False)
class Motion:
    """A skeleton moving in the world frame (metres, +z up, floor z = 0), sampled at ``fps``.

    Parameters
    ----------
    fps : float
        Frames per second.
    bone_names : tuple of str, length B
        Bone names as in the file; bone 0 is the root, parents come before their children.
    parents : (B,) int
        Index of each bone's parent, -1 for the root.
    bone_rotations : (F, B, 3, 3) float
        World rotation of each bone from the rest pose (identity at rest).
    bone_origins : (F, B, 3) float, metres
        World position of each bone's start (``bone_origins[:, 0]`` is the root translation).
    bone_ends : (F, B, 3) float, metres
        World position of each bone's end.
    joints : (F, 17, 3) float, metres
        The joints of ``JOINT_NAMES``, in that order.
    rest_origins, rest_ends : (B, 3) float, metres
        Bone starts and ends in the rest pose with the root at the world origin, world axes; forward
        kinematics moves these, so resampling can rebuild exact positions.
    joint_weights : (17, 2B) float
        ``joints[f] = joint_weights @ concatenate([bone_origins[f], bone_ends[f]])``.
    """

    fps: float
    bone_names: tuple[str, ...]
    parents: np.ndarray
    bone_rotations: np.ndarray
    bone_origins: np.ndarray
    bone_ends: np.ndarray
    joints: np.ndarray
    rest_origins: np.ndarray
    rest_ends: np.ndarray
    joint_weights: np.ndarray

    def __post_init__(self) -> None:
        n_frames, n_bones = self.bone_rotations.shape[:2]
        expected = {
            "parents": (self.parents, (n_bones,)),
            "bone_rotations": (self.bone_rotations, (n_frames, n_bones, 3, 3)),
            "bone_origins": (self.bone_origins, (n_frames, n_bones, 3)),
            "bone_ends": (self.bone_ends, (n_frames, n_bones, 3)),
            "joints": (self.joints, (n_frames, len(JOINT_NAMES), 3)),
            "rest_origins": (self.rest_origins, (n_bones, 3)),
            "rest_ends": (self.rest_ends, (n_bones, 3)),
            "joint_weights": (self.joint_weights, (len(JOINT_NAMES), 2 * n_bones)),
        }
        for name, (array, shape) in expected.items():
            if array.shape != shape:
                raise ValueError(f"Motion.{name}: expected shape {shape}, got {array.shape}")
        if len(self.bone_names) != n_bones:
            raise ValueError(f"Motion.bone_names: expected {n_bones} names, got {len(self.bone_names)}")

    @property
    def n_frames(self) -> int:
        return self.bone_rotations.shape[0]

    @property
    def duration(self) -> float:
        """Seconds from the first to the last frame."""
        return (self.n_frames - 1) / self.fps

    def bone_index(self, name: str) -> int:
        """Position of the bone called ``name``; ``KeyError`` naming the known bones otherwise."""
        try:
            return self.bone_names.index(name)
        except ValueError:
            raise KeyError(f"no bone named '{name}'; known bones: {', '.join(self.bone_names)}") from None

    def resample(self, fps: float) -> Motion:
        """The motion sampled at ``fps`` frames per second over the same time span (from t = 0).

        Rotations are slerped per bone, the root translation interpolated linearly, positions recomputed
        by forward kinematics. The last frame is the last multiple of ``1 / fps`` within the clip.
        """
        if not (fps > 0 and math.isfinite(fps)):
            raise InputError(f"fps: expected a positive frame rate, got {fps}")
        old_times = np.arange(self.n_frames) / self.fps
        n_new = int(math.floor(self.duration * fps + 1e-9)) + 1
        new_times = np.minimum(np.arange(n_new) / fps, old_times[-1])
        n_bones = len(self.bone_names)
        rotations = np.empty((n_new, n_bones, 3, 3))
        for bone in range(n_bones):
            if self.n_frames == 1:
                rotations[:, bone] = self.bone_rotations[0, bone]
                continue
            slerp = Slerp(old_times, Rotation.from_matrix(self.bone_rotations[:, bone]))
            rotations[:, bone] = slerp(new_times).as_matrix()
        root = np.stack(
            [np.interp(new_times, old_times, self.bone_origins[:, 0, k]) for k in range(3)], axis=1
        )
        return self._with_pose(float(fps), rotations, root)

    def slice_seconds(self, t0: float, t1: float) -> Motion:
        """Frames with ``t0 <= time < t1`` (time 0 = first frame), renumbered from 0; same world frame."""
        first = max(0, int(math.ceil(t0 * self.fps - 1e-9)))
        stop = min(self.n_frames, int(math.ceil(t1 * self.fps - 1e-9)))
        if stop <= first:
            raise InputError(
                f"time span: [{t0}, {t1}) s holds no frame of a {self.duration:.2f} s clip; "
                f"expected 0 <= start < end within the clip"
            )
        return self._frames(slice(first, stop))

    def held(self, seconds: float) -> Motion:
        """The motion with its first pose held still for ``seconds`` before it starts (a subject standing
        still, then moving): that many frames at ``fps`` are prepended."""
        if not (seconds >= 0 and math.isfinite(seconds)):
            raise InputError(f"hold: expected a duration >= 0 seconds, got {seconds}")
        count = round(seconds * self.fps)
        return self._frames(np.concatenate([np.zeros(count, int), np.arange(self.n_frames)]))

    def _frames(self, keep: slice | np.ndarray) -> Motion:
        """The frames ``keep`` (a slice or indices), renumbered from 0; same skeleton and world frame."""
        return Motion(
            self.fps,
            self.bone_names,
            self.parents,
            self.bone_rotations[keep],
            self.bone_origins[keep],
            self.bone_ends[keep],
            self.joints[keep],
            self.rest_origins,
            self.rest_ends,
            self.joint_weights,
        )

    def rest_pose(self) -> Motion:
        """One frame of the skeleton's rest pose (every rotation the identity), root at its first position."""
        n_bones = len(self.bone_names)
        rotations = np.broadcast_to(np.eye(3), (1, n_bones, 3, 3)).copy()
        return self._with_pose(self.fps, rotations, self.bone_origins[:1, 0])

    def _with_pose(self, fps: float, rotations: np.ndarray, root_positions: np.ndarray) -> Motion:
        origins, ends = _forward_kinematics(
            self.parents, self.rest_origins, self.rest_ends, rotations, root_positions
        )
        joints = _joints_from_bones(self.joint_weights, origins, ends)
        return Motion(
            fps,
            self.bone_names,
            self.parents,
            rotations,
            origins,
            ends,
            joints,
            self.rest_origins,
            self.rest_ends,
            self.joint_weights,
        )


def load_clip(path, *, skeleton=None, length_unit_m: float | None = None) -> Motion:
    """Read a motion clip: CMU ``.amc`` (with its ``.asf`` given as ``skeleton``) or ``.bvh``.

    Parameters
    ----------
    path : path-like
        The ``.amc`` or ``.bvh`` file.
    skeleton : path-like, optional
        The ``.asf`` skeleton an ``.amc`` file needs; not used for BVH.
    length_unit_m : float, optional
        Metres per BVH length unit; inferred from the rest skeleton's height when not given.

    Returns
    -------
    Motion
        In the world frame (metres, +z up, lowest foot point of the clip at z = 0); AMC clips at 120 fps,
        BVH at their ``Frame Time``.

    Raises
    ------
    InputError
        Missing or malformed files (naming file and line), an AMC without skeleton, bones the joint
        mapping does not know.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: clip file not found; expected an .amc or .bvh file")
    suffix = path.suffix.lower()
    if suffix == ".amc":
        if skeleton is None:
            raise InputError(
                f"{path}: an AMC clip needs its ASF skeleton; pass skeleton=<file.asf> (--skeleton)"
            )
        skeleton = Path(skeleton)
        if not skeleton.is_file():
            raise InputError(f"{skeleton}: skeleton file not found; expected the clip's .asf file")
        raw = read_asf_amc(skeleton, path)
    elif suffix == ".bvh":
        raw = read_bvh(path, length_unit_m)
    else:
        raise InputError(
            f"{path}: unknown clip type '{path.suffix}'; expected .amc (with --skeleton) or .bvh"
        )
    return _motion_in_world(raw, path)



def _forward_kinematics(parents, rest_origins, rest_ends, rotations, root_positions):
    """Bone starts and ends (F, B, 3) from world rotations from rest (F, B, 3, 3) and root positions (F, 3).

    ``start_b = start_parent + R_parent (rest_start_b - rest_start_parent)``,
    ``end_b = start_b + R_b (rest_end_b - rest_start_b)``.
    """
    n_frames, n_bones = rotations.shape[:2]
    origins = np.empty((n_frames, n_bones, 3))
    for bone in range(n_bones):
        parent = parents[bone]
        if parent < 0:
            origins[:, bone] = root_positions + (rest_origins[bone] - rest_origins[0])
        else:
            offset = rest_origins[bone] - rest_origins[parent]
            origins[:, bone] = origins[:, parent] + rotations[:, parent] @ offset
    ends = origins + np.einsum("fbij,bj->fbi", rotations, rest_ends - rest_origins)
    return origins, ends


def _joints_from_bones(joint_weights, origins, ends):
    """(F, 17, 3) joints as weighted sums of bone starts and ends."""
    return np.einsum("jk,fkd->fjd", joint_weights, np.concatenate([origins, ends], axis=1))


def _joint_weights(bone_names: Sequence[str], path: Path) -> tuple[np.ndarray, tuple[str, ...]]:
    """The (17, 2B) joint weights and the foot bones, from whichever naming convention the file uses."""
    index = {name: k for k, name in enumerate(bone_names)}
    n_bones = len(bone_names)
    missing_by_convention = []
    for convention, spec, foot_bones in _SKELETON_CONVENTIONS:
        needed = {bone for parts in spec.values() for bone, _, _ in parts} | set(foot_bones)
        missing = sorted(needed - index.keys())
        if missing:
            missing_by_convention.append(f"{convention} names lack {', '.join(missing[:4])}")
            continue
        weights = np.zeros((len(JOINT_NAMES), 2 * n_bones))
        for row, joint in enumerate(JOINT_NAMES):
            for bone, where, weight in spec[joint]:
                weights[row, index[bone] + (n_bones if where == "end" else 0)] += weight
        return weights, foot_bones
    raise InputError(
        f"{path}: unknown joint names, cannot map the skeleton to joints.csv "
        f"({'; '.join(missing_by_convention)}); "
        f"expected CMU names (lfemur, ltibia, lhumerus, ...) or Daz names (lThigh, lShin, lShldr, ...)"
    )


def _motion_in_world(raw: RawClip, path: Path) -> Motion:
    """Rotate a Y-up clip to +z up, put its lowest foot point on the floor and compute the joints."""
    weights, foot_bones = _joint_weights(raw.bone_names, path)
    A = up_rotation("+y")  # (x, y, z) -> (x, -z, y)
    rotations = A @ raw.rotations @ A.T
    rest_origins = raw.rest_origins @ A.T
    rest_ends = raw.rest_ends @ A.T
    root = raw.root_positions @ A.T
    origins, ends = _forward_kinematics(raw.parents, rest_origins, rest_ends, rotations, root)
    feet = [raw.bone_names.index(name) for name in foot_bones]
    floor = min(origins[:, feet, 2].min(), ends[:, feet, 2].min())
    shift = np.array([0.0, 0.0, -floor])
    origins, ends, root = origins + shift, ends + shift, root + shift
    joints = _joints_from_bones(weights, origins, ends)
    return Motion(
        raw.fps,
        raw.bone_names,
        raw.parents,
        rotations,
        origins,
        ends,
        joints,
        rest_origins,
        rest_ends,
        weights,
    )
