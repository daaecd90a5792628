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
from stages.joints import JOINT_NAMES

INCH_M = 0.0254
# CMU captured at 120 Hz and AMC files do not store a rate.
AMC_FPS = 120.0
# A rest skeleton's height (lowest to highest point, in metres) expected when inferring a BVH file's unit.
TYPICAL_REST_HEIGHT_M = 1.7
BVH_CANDIDATE_UNITS_M = {
    "m": 1.0,
    "cm": 0.01,
    "mm": 0.001,
    "inch": INCH_M,
    "CMU ASF unit": INCH_M / 0.45,
}

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
        raw = _read_asf_amc(skeleton, path)
    elif suffix == ".bvh":
        raw = _read_bvh(path, length_unit_m)
    else:
        raise InputError(
            f"{path}: unknown clip type '{path.suffix}'; expected .amc (with --skeleton) or .bvh"
        )
    return _motion_in_world(raw, path)


@dataclass(frozen=True)
class _RawClip:
    """A clip as read, in the file's Y-up frame but already in metres."""

    fps: float
    bone_names: tuple[str, ...]
    parents: np.ndarray  # (B,)
    rest_origins: np.ndarray  # (B, 3)
    rest_ends: np.ndarray  # (B, 3)
    rotations: np.ndarray  # (F, B, 3, 3), from rest
    root_positions: np.ndarray  # (F, 3)


def _axis_rotations(axis: str, angles: np.ndarray) -> np.ndarray:
    """(N, 3, 3) Rotations by ``angles`` (N,) radians about the coordinate axis ``axis`` in 'xyz'."""
    c, s = np.cos(angles), np.sin(angles)
    one, zero = np.ones_like(angles), np.zeros_like(angles)
    if axis == "x":
        rows = [[one, zero, zero], [zero, c, -s], [zero, s, c]]
    elif axis == "y":
        rows = [[c, zero, s], [zero, one, zero], [-s, zero, c]]
    else:
        rows = [[c, -s, zero], [s, c, zero], [zero, zero, one]]
    return np.moveaxis(np.array(rows), (0, 1), (-2, -1))


def _euler_rotations(axes: str, angles: np.ndarray) -> np.ndarray:
    """(N, 3, 3) ``R_axes[-1] ... R_axes[0]``: the later-listed axis on the left, ``angles`` (N, len) rad."""
    result = np.broadcast_to(np.eye(3), (len(angles), 3, 3)).copy()
    for k, axis in enumerate(axes):
        result = _axis_rotations(axis, angles[:, k]) @ result
    return result


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


def _motion_in_world(raw: _RawClip, path: Path) -> Motion:
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


# ---------------------------------------------------------------------------------------------- ASF / AMC


@dataclass(frozen=True)
class _AsfBone:
    name: str
    direction: np.ndarray  # (3,) unit, ASF frame
    length: float  # file units
    axis_rotation: np.ndarray  # (3, 3) C
    dofs: tuple[str, ...]  # e.g. ("rx", "ry", "rz")


def _numbers(tokens: Sequence[str], count: int, path: Path, line_number: int, what: str) -> list[float]:
    """``count`` floats from ``tokens``, or an InputError naming the file, line and field."""
    if len(tokens) < count:
        raise InputError(f"{path}:{line_number}: {what}: expected {count} numbers, got {len(tokens)}")
    try:
        return [float(token) for token in tokens[:count]]
    except ValueError:
        raise InputError(f"{path}:{line_number}: {what}: expected numbers, got {' '.join(tokens)}") from None


def _asf_axis_rotation(tokens: Sequence[str], path: Path, line_number: int, degrees: bool) -> np.ndarray:
    """The rotation ``C`` of an ASF ``axis a b c XYZ`` line (later-listed axis on the left)."""
    angles = _numbers(tokens, 3, path, line_number, "axis")
    order = tokens[3].lower() if len(tokens) > 3 else "xyz"
    if sorted(order) != ["x", "y", "z"]:
        raise InputError(f"{path}:{line_number}: axis order '{tokens[3]}': expected a permutation of XYZ")
    radians = np.radians(angles) if degrees else np.array(angles)
    by_axis = dict(zip("xyz", radians, strict=True))
    return _euler_rotations(order, np.array([[by_axis[a] for a in order]]))[0]


def _parse_asf(path: Path):
    """Bones (root first, then file order), hierarchy, metres per unit, degrees flag, root channel order."""
    lines = path.read_text(errors="replace").splitlines()
    section = None
    metres_per_unit = INCH_M  # ASF default: length 1.0 means inches
    degrees = True
    root_order = ("tx", "ty", "tz", "rx", "ry", "rz")
    root_axis = np.eye(3)
    root_axis_order = "XYZ"
    bones: dict[str, _AsfBone] = {}
    parents: dict[str, str] = {}
    current: dict | None = None
    current_line = 0
    for line_number, line in enumerate(lines, start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        head = tokens[0].lower()
        if head.startswith(":"):
            section = head[1:]
            continue
        if section == "units":
            if head == "length":
                scale = _numbers(tokens[1:], 1, path, line_number, "length unit")[0]
                if scale <= 0:
                    raise InputError(f"{path}:{line_number}: length unit {scale}: expected a positive number")
                metres_per_unit = INCH_M / scale
            elif head == "angle":
                if len(tokens) < 2 or tokens[1].lower() not in ("deg", "rad"):
                    raise InputError(f"{path}:{line_number}: angle unit: expected 'deg' or 'rad'")
                degrees = tokens[1].lower() == "deg"
        elif section == "root":
            if head == "order":
                root_order = tuple(token.lower() for token in tokens[1:])
                if sorted(root_order) != sorted(("tx", "ty", "tz", "rx", "ry", "rz")):
                    raise InputError(
                        f"{path}:{line_number}: root order: expected TX TY TZ RX RY RZ in some order, got "
                        f"{' '.join(tokens[1:])}"
                    )
            elif head == "axis" and len(tokens) >= 2:
                root_axis_order = tokens[1]
            elif head == "orientation":
                root_axis = _asf_axis_rotation(tokens[1:4] + [root_axis_order], path, line_number, degrees)
        elif section == "bonedata":
            if head == "begin":
                current, current_line = {"dofs": ()}, line_number
            elif head == "end":
                if current is None:
                    raise InputError(f"{path}:{line_number}: 'end' without 'begin' in :bonedata")
                for field, key in (
                    ("name", "name"),
                    ("direction", "direction"),
                    ("length", "length"),
                    ("axis", "axis_rotation"),
                ):
                    if key not in current:
                        raise InputError(
                            f"{path}:{current_line}: bone block has no '{field}'; expected name, direction, "
                            f"length and axis"
                        )
                bones[current["name"]] = _AsfBone(**current)
                current = None
            elif current is not None:
                if head == "name" and len(tokens) >= 2:
                    current["name"] = tokens[1]
                elif head == "direction":
                    direction = np.array(_numbers(tokens[1:], 3, path, line_number, "direction"))
                    norm = np.linalg.norm(direction)
                    if norm == 0:
                        raise InputError(f"{path}:{line_number}: direction is zero; expected a unit vector")
                    current["direction"] = direction / norm
                elif head == "length":
                    current["length"] = _numbers(tokens[1:], 1, path, line_number, "length")[0]
                elif head == "axis":
                    current["axis_rotation"] = _asf_axis_rotation(tokens[1:], path, line_number, degrees)
                elif head == "dof":
                    dofs = tuple(token.lower() for token in tokens[1:])
                    unknown = [d for d in dofs if d not in ("rx", "ry", "rz")]
                    if unknown:
                        raise InputError(
                            f"{path}:{line_number}: dof {' '.join(unknown)}: expected rx, ry and/or rz"
                        )
                    current["dofs"] = dofs
        elif section == "hierarchy":
            if head in ("begin", "end"):
                continue
            for child in tokens[1:]:
                parents[child] = tokens[0]
    if not bones:
        raise InputError(f"{path}: no bones found; expected an ASF file with a :bonedata section")
    for child, parent in parents.items():
        for name in (child, parent):
            if name != "root" and name not in bones:
                raise InputError(f"{path}: hierarchy names bone '{name}' that :bonedata does not define")
    orphans = sorted(set(bones) - set(parents))
    if orphans:
        raise InputError(f"{path}: bones {', '.join(orphans)} are missing from :hierarchy")
    return bones, parents, metres_per_unit, degrees, root_order, root_axis


def _topological_order(parents: dict[str, str]) -> list[str]:
    """Bone names with every parent before its children, root first, children in hierarchy order."""
    children: dict[str, list[str]] = {}
    for child, parent in parents.items():
        children.setdefault(parent, []).append(child)
    order, stack = [], ["root"]
    while stack:
        name = stack.pop(0)
        order.append(name)
        stack[0:0] = children.get(name, [])
    return order


def _read_asf_amc(asf_path: Path, amc_path: Path) -> _RawClip:
    bones, parents, metres_per_unit, degrees, root_order, root_axis = _parse_asf(asf_path)
    names = _topological_order(parents)
    if len(names) != len(bones) + 1:
        raise InputError(f"{asf_path}: :hierarchy does not connect every bone to the root (a cycle?)")
    index = {name: k for k, name in enumerate(names)}
    parent_index = np.array([-1] + [index[parents[name]] for name in names[1:]])

    rest_origins = np.zeros((len(names), 3))
    rest_ends = np.zeros((len(names), 3))
    for k, name in enumerate(names[1:], start=1):
        bone = bones[name]
        rest_origins[k] = rest_ends[parent_index[k]]
        rest_ends[k] = rest_origins[k] + bone.length * metres_per_unit * bone.direction

    frames = _parse_amc(amc_path, bones, root_order)
    n_frames = len(frames)
    to_radians = math.pi / 180 if degrees else 1.0
    rotations = np.empty((n_frames, len(names), 3, 3))
    root_values = np.array([frame["root"] for frame in frames])  # (F, 6)
    translation_columns = [root_order.index(axis) for axis in ("tx", "ty", "tz")]
    root_positions = root_values[:, translation_columns] * metres_per_unit
    rotation_axes = "".join(channel[1] for channel in root_order if channel.startswith("r"))
    rotation_columns = [k for k, channel in enumerate(root_order) if channel.startswith("r")]
    M = _euler_rotations(rotation_axes, root_values[:, rotation_columns] * to_radians)
    rotations[:, 0] = root_axis @ M @ root_axis.T
    for k, name in enumerate(names[1:], start=1):
        bone = bones[name]
        parent_rotation = rotations[:, parent_index[k]]
        if not bone.dofs:
            rotations[:, k] = parent_rotation
            continue
        values = np.array([frame[name] for frame in frames]) * to_radians  # (F, dofs)
        M = _euler_rotations("".join(d[1] for d in bone.dofs), values)
        C = bone.axis_rotation
        rotations[:, k] = parent_rotation @ C @ M @ C.T
    return _RawClip(AMC_FPS, tuple(names), parent_index, rest_origins, rest_ends, rotations, root_positions)


def _parse_amc(
    path: Path, bones: dict[str, _AsfBone], root_order: Sequence[str]
) -> list[dict[str, list[float]]]:
    """Per frame, each bone's dof values (root: its 6 channels in ``root_order``)."""
    expected_counts = {name: len(bone.dofs) for name, bone in bones.items() if bone.dofs}
    expected_counts["root"] = len(root_order)
    frames: list[dict[str, list[float]]] = []
    current: dict[str, list[float]] | None = None
    frame_line = 0

    def finish(frame: dict[str, list[float]], line_number: int) -> None:
        missing = sorted(set(expected_counts) - frame.keys())
        if missing:
            raise InputError(
                f"{path}:{line_number}: frame {len(frames) + 1} has no values for {', '.join(missing[:5])}; "
                f"expected a line per bone with dofs"
            )
        frames.append(frame)

    with path.open(errors="replace") as lines:
        for line_number, line in enumerate(lines, start=1):
            tokens = line.split()
            if not tokens or tokens[0].startswith(("#", ":")):
                continue
            if len(tokens) == 1 and tokens[0].isdigit():
                if current is not None:
                    finish(current, frame_line)
                current, frame_line = {}, line_number
                continue
            if current is None:
                raise InputError(f"{path}:{line_number}: bone values before the first frame number")
            name = tokens[0]
            if name not in expected_counts:
                if name in bones:  # a bone without dofs written with no values is harmless
                    continue
                raise InputError(
                    f"{path}:{line_number}: unknown bone '{name}'; expected a bone of the ASF skeleton"
                )
            count = expected_counts[name]
            if len(tokens) - 1 != count:
                raise InputError(
                    f"{path}:{line_number}: bone '{name}' has {len(tokens) - 1} values; expected {count}"
                )
            current[name] = _numbers(tokens[1:], count, path, line_number, f"bone '{name}'")
    if current is not None:
        finish(current, frame_line)
    if not frames:
        raise InputError(f"{path}: no frames found; expected an AMC file with numbered frames")
    return frames


# ---------------------------------------------------------------------------------------------------- BVH

_BVH_CHANNELS = ("xposition", "yposition", "zposition", "xrotation", "yrotation", "zrotation")


@dataclass
class _BvhJoint:
    name: str
    parent: int
    offset: np.ndarray  # (3,) file units
    channels: tuple[str, ...]
    end_site: np.ndarray | None = None  # (3,) offset of the End Site, if any


class _Tokens:
    """Whitespace tokens of a BVH hierarchy with their line numbers, for error messages."""

    def __init__(self, path: Path, lines: Sequence[str]):
        self.path = path
        self.items = [(token, number) for number, line in enumerate(lines, start=1) for token in line.split()]
        self.position = 0

    def next(self, what: str) -> tuple[str, int]:
        if self.position >= len(self.items):
            raise InputError(f"{self.path}: file ends inside the HIERARCHY; expected {what}")
        item = self.items[self.position]
        self.position += 1
        return item

    def expect(self, word: str) -> int:
        token, line = self.next(f"'{word}'")
        if token.upper() != word.upper():
            raise InputError(f"{self.path}:{line}: expected '{word}', got '{token}'")
        return line

    def numbers(self, count: int, what: str) -> np.ndarray:
        values = []
        for _ in range(count):
            token, line = self.next(what)
            try:
                values.append(float(token))
            except ValueError:
                raise InputError(f"{self.path}:{line}: {what}: expected a number, got '{token}'") from None
        return np.array(values)


def _parse_bvh_joint(tokens: _Tokens, joints: list[_BvhJoint], parent: int) -> None:
    """Parse ``name { OFFSET ... CHANNELS ... (JOINT ... | End Site {...})* }`` after ROOT/JOINT."""
    name, _ = tokens.next("a joint name")
    tokens.expect("{")
    tokens.expect("OFFSET")
    offset = tokens.numbers(3, f"OFFSET of joint '{name}'")
    tokens.expect("CHANNELS")
    count_token, line = tokens.next("a channel count")
    if not count_token.isdigit():
        raise InputError(
            f"{tokens.path}:{line}: CHANNELS of joint '{name}': expected a count, got '{count_token}'"
        )
    channels = []
    for _ in range(int(count_token)):
        channel, line = tokens.next("a channel name")
        if channel.lower() not in _BVH_CHANNELS:
            raise InputError(
                f"{tokens.path}:{line}: unknown channel '{channel}' of joint '{name}'; "
                f"expected X/Y/Z position or rotation"
            )
        channels.append(channel.lower())
    joint = _BvhJoint(name, parent, offset, tuple(channels))
    joints.append(joint)
    me = len(joints) - 1
    while True:
        token, line = tokens.next("JOINT, End Site or '}'")
        keyword = token.upper()
        if keyword == "}":
            return
        if keyword == "JOINT":
            _parse_bvh_joint(tokens, joints, me)
        elif keyword == "END":
            tokens.expect("Site")
            tokens.expect("{")
            tokens.expect("OFFSET")
            joint.end_site = tokens.numbers(3, f"End Site OFFSET of joint '{name}'")
            tokens.expect("}")
        else:
            raise InputError(
                f"{tokens.path}:{line}: unexpected '{token}' in joint '{name}'; "
                f"expected JOINT, End Site or '}}'"
            )


def _infer_bvh_unit(rest_points: np.ndarray, path: Path) -> float:
    """Metres per unit making the rest skeleton (Y-up, file units) closest to a typical human height."""
    height = float(np.ptp(rest_points[:, 1]))
    if height <= 0:
        raise InputError(
            f"{path}: the rest skeleton has no height; pass length_unit_m to give the file's unit"
        )
    return min(
        BVH_CANDIDATE_UNITS_M.values(),
        key=lambda unit: abs(math.log(height * unit / TYPICAL_REST_HEIGHT_M)),
    )


def _read_bvh(path: Path, length_unit_m: float | None) -> _RawClip:
    lines = path.read_text(errors="replace").splitlines()
    motion_line = next((k for k, line in enumerate(lines) if line.strip().upper() == "MOTION"), None)
    if motion_line is None:
        raise InputError(f"{path}: no MOTION section; expected a BVH file (HIERARCHY ... MOTION ...)")
    tokens = _Tokens(path, lines[:motion_line])
    tokens.expect("HIERARCHY")
    tokens.expect("ROOT")
    joints: list[_BvhJoint] = []
    _parse_bvh_joint(tokens, joints, -1)
    if tokens.position != len(tokens.items):
        _, line = tokens.items[tokens.position]
        raise InputError(f"{path}:{line}: text after the root joint; expected MOTION (one ROOT only)")
    names = [joint.name for joint in joints]
    duplicates = sorted({name for name in names if names.count(name) > 1})
    if duplicates:
        raise InputError(f"{path}: duplicate joint names {', '.join(duplicates)}; expected unique names")

    n_frames, frame_time, values = _parse_bvh_motion(
        path, lines, motion_line, sum(len(j.channels) for j in joints)
    )

    parents = np.array([joint.parent for joint in joints])
    rest_origins = np.zeros((len(joints), 3))
    for k, joint in enumerate(joints):
        rest_origins[k] = joint.offset + (rest_origins[joint.parent] if joint.parent >= 0 else 0.0)
    rest_ends = rest_origins.copy()
    for k, joint in enumerate(joints):
        children = np.flatnonzero(parents == k)
        if joint.end_site is not None and len(children) == 0:
            rest_ends[k] = rest_origins[k] + joint.end_site
        elif len(children):
            rest_ends[k] = rest_origins[children].mean(axis=0)
    unit = (
        length_unit_m
        if length_unit_m is not None
        else _infer_bvh_unit(np.vstack([rest_origins, rest_ends]), path)
    )
    rest_origins, rest_ends = rest_origins * unit, rest_ends * unit

    rotations = np.empty((n_frames, len(joints), 3, 3))
    root_positions = np.zeros((n_frames, 3))
    column = 0
    for k, joint in enumerate(joints):
        columns = {channel: column + i for i, channel in enumerate(joint.channels)}
        column += len(joint.channels)
        if k == 0:
            for axis_index, axis in enumerate("xyz"):
                if f"{axis}position" in columns:
                    root_positions[:, axis_index] = values[:, columns[f"{axis}position"]] * unit
        rotation_channels = [c for c in joint.channels if c.endswith("rotation")]
        # BVH lists rotations outermost first, so the first listed is leftmost: reverse for _euler_rotations.
        axes = "".join(c[0] for c in reversed(rotation_channels))
        angles = np.radians(values[:, [columns[c] for c in reversed(rotation_channels)]])
        local = _euler_rotations(axes, angles) if axes else np.broadcast_to(np.eye(3), (n_frames, 3, 3))
        rotations[:, k] = local if joint.parent < 0 else rotations[:, joint.parent] @ local
    return _RawClip(
        1.0 / frame_time, tuple(names), parents, rest_origins, rest_ends, rotations, root_positions
    )


def _parse_bvh_motion(path: Path, lines: Sequence[str], motion_line: int, n_channels: int):
    """Frame count, frame time (s) and the (F, channels) values of the MOTION section."""
    header = {}
    body_start = motion_line + 1
    for key in ("frames", "frame time"):
        while body_start < len(lines) and not lines[body_start].strip():
            body_start += 1
        line_number = body_start + 1
        text = lines[body_start] if body_start < len(lines) else ""
        label, _, value = text.partition(":")
        if label.strip().lower() != key:
            raise InputError(
                f"{path}:{line_number}: expected '{key.capitalize()}: <number>', got '{text.strip()}'"
            )
        try:
            header[key] = float(value)
        except ValueError:
            raise InputError(
                f"{path}:{line_number}: {key}: expected a number, got '{value.strip()}'"
            ) from None
        body_start += 1
    n_frames = int(header["frames"])
    if n_frames < 1 or header["frames"] != n_frames:
        raise InputError(
            f"{path}:{motion_line + 2}: Frames: expected a positive whole number, got {header['frames']}"
        )
    if header["frame time"] <= 0:
        raise InputError(f"{path}:{motion_line + 3}: Frame Time: expected a positive number of seconds")
    rows = []
    for line_number, line in enumerate(lines[body_start:], start=body_start + 1):
        tokens = line.split()
        if not tokens:
            continue
        if len(tokens) != n_channels:
            raise InputError(
                f"{path}:{line_number}: {len(tokens)} values; expected {n_channels} (one per channel)"
            )
        try:
            rows.append([float(token) for token in tokens])
        except ValueError:
            raise InputError(f"{path}:{line_number}: expected numbers in the MOTION data") from None
    if len(rows) != n_frames:
        raise InputError(f"{path}: MOTION has {len(rows)} frames; the header says Frames: {n_frames}")
    return n_frames, header["frame time"], np.array(rows)
