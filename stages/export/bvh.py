"""A BVH animation built from joint positions alone, independent of the tracker's body model.

Why from positions: a BVH viewer (Blender, MotionBuilder, bvhacker) then shows exactly the joints of
``joints.csv``, whatever body model produced them, and the file can be made for ground truth too.

Axes and units
    BVH viewers expect +Y up, so world points (x, y, z) (+z up, CAPTURE_FORMAT.md) are written as
    (x, z, -y), the proper rotation by -90 degrees about x. Lengths are in centimetres by default
    (:data:`UNITS`): MotionBuilder, Maya and most animation tools read BVH lengths as centimetres
    (a metre file shows a 1.7 cm character there); Blender asks for a scale on import (0.01 for cm).

Hierarchy
    The tree of :data:`stages.export.skeleton.BONES` with helper joints: ``spine`` (at the pelvis, aims
    the trunk pelvis -> neck), ``chest`` (at the trunk's top, the neck joint centre: the frame the
    neck and the shoulder girdle hang from), ``neck`` (at the same point, aims the head) and
    ``l_clavicle`` / ``r_clavicle`` (there too, aim the shoulders). They exist because a BVH joint
    has one rotation, which can aim one bone exactly; the pelvis aims both hips (they are opposite
    each other, the pelvis being their centre) and every other joint aims one bone. With the
    shoulders under the chest rather than the neck, a nod of the head moves no arm, as in animation
    rigs. The rest pose is a T-pose facing +Z: legs down (-Y), arms sideways (the subject's left is
    +X), trunk, neck and head up, feet forward (+Z). Offsets are the median bone lengths over the
    sequence along these rest directions. Every joint has ``Zrotation Xrotation Yrotation`` channels
    (intrinsic Z, X, Y). The root (pelvis), the chest and the head also have position channels: the
    trunk (pelvis -> neck) and the neck (neck -> head) are the bones whose straight length really
    changes (:data:`stages.export.skeleton.FLEXIBLE_BONES`; over the CMU clips in mocap/ the
    pelvis-neck distance varies by 5 to 55 mm, neck-head by up to 8 mm), and a rigid trunk would
    shift the whole upper body by that much. Their position channels give the exact distance along
    the bone; a viewer that ignores position channels below the root shows the median length instead.

Names
    The joints keep joints.csv's names (plus the helpers'), or take the Mixamo rig's names
    (:data:`MIXAMO_NAMES`: ``Hips``, ``LeftUpLeg``, ``LeftForeArm``...), which Blender's, Unity's
    and most retargeting tools map onto a character by name.

Rotations
    The pelvis frame is measured: x from the right to the left hip, y the trunk direction made
    orthogonal to x, z = x cross y. Every other joint's world rotation is the *swing* (the smallest
    rotation) that turns its bone's rest direction, as carried by the parent's world rotation, onto
    the observed bone direction. So no joint twists relative to its parent: the twist of every limb
    follows from the pelvis frame down the chain, which is smooth in time as long as no bone turns
    by 180 degrees from where its parent carries it (an arm reaching straight across the chest comes
    closest). Joints whose bone ends in an End Site (head, wrists, toes) get no rotation: joints.csv
    says nothing about hand or head orientation. Of the equivalent Euler angle triples, each frame
    keeps the one closest to the previous frame's.

Exactness: a joint's position is its parent's plus the rotated offset, i.e. the observed bone
direction times the median length, so positions are reproduced exactly for bones whose length is
constant (and for the trunk and neck whatever their length), and otherwise are off by the length's deviation
from the median. The pipeline's exports give every frame the same rigid bone lengths
(:func:`stages.export.skeleton.with_bone_lengths`), so their BVH reproduces joints.csv in every frame.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from stages.export.joints_table import select_joints
from stages.export.skeleton import FLEXIBLE_BONES
from stages.joints import JOINT_NAMES, SCORED_JOINTS

#: World (x, y, z), +z up  ->  BVH (x, z, -y), +Y up.
WORLD_TO_BVH = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

#: Length unit of the file -> its number per metre.
UNITS: dict[str, float] = {"cm": 100.0, "m": 1.0, "mm": 1000.0}

#: Length (metres) of the End Site segments (top of head, hands, tips of the feet): a display
#: aid only, no joint position depends on it.
END_SITE_LENGTH_M = 0.1

#: Decimal places written for positions and angles (degrees): a micrometre in a metre file, and
#: micro-degrees, keep a 1 m chain exact to far below a millimetre.
DECIMALS = 6

#: The BVH joints' names in the Mixamo rig (without its ``mixamorig:`` prefix). Mixamo's spine has
#: three joints; here the one trunk bone runs from ``Spine`` to ``Spine2``, the chest the neck and the
#: shoulders hang from in both rigs.
MIXAMO_NAMES: dict[str, str] = {
    "pelvis": "Hips", "spine": "Spine", "chest": "Spine2", "neck": "Neck", "head": "Head",
    "l_hip": "LeftUpLeg", "l_knee": "LeftLeg", "l_ankle": "LeftFoot", "l_toe": "LeftToeBase",
    "r_hip": "RightUpLeg", "r_knee": "RightLeg", "r_ankle": "RightFoot", "r_toe": "RightToeBase",
    "l_clavicle": "LeftShoulder", "l_shoulder": "LeftArm", "l_elbow": "LeftForeArm", "l_wrist": "LeftHand",
    "r_clavicle": "RightShoulder", "r_shoulder": "RightArm", "r_elbow": "RightForeArm", "r_wrist": "RightHand",
}

#: ``export.bvh_names`` value -> renaming of the BVH joints (an empty mapping keeps them).
BONE_NAMINGS: dict[str, dict[str, str]] = {"joints": {}, "mixamo": MIXAMO_NAMES}

#: Below this sine two directions count as parallel (or opposite) in :func:`_swing`.
_TINY = 1e-12

_LEFT, _RIGHT, _UP, _DOWN, _FORWARD = (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1)


@dataclass(frozen=True)
class _BvhJoint:
    """One BVH joint: where it sits (a joints.csv joint) and the rest direction from its parent."""

    name: str
    parent: str | None
    at: str                       # the joint of JOINT_NAMES this BVH joint sits on
    rest_from_parent: tuple       # unit direction of the bone parent -> this joint in the rest pose
    end_site: tuple               # direction of the End Site if no child joint is present


_JOINTS: tuple[_BvhJoint, ...] = (
    _BvhJoint("pelvis", None, "pelvis", (0, 0, 0), _UP),
    _BvhJoint("l_hip", "pelvis", "l_hip", _LEFT, _DOWN),
    _BvhJoint("l_knee", "l_hip", "l_knee", _DOWN, _DOWN),
    _BvhJoint("l_ankle", "l_knee", "l_ankle", _DOWN, _FORWARD),
    _BvhJoint("l_toe", "l_ankle", "l_toe", _FORWARD, _FORWARD),
    _BvhJoint("r_hip", "pelvis", "r_hip", _RIGHT, _DOWN),
    _BvhJoint("r_knee", "r_hip", "r_knee", _DOWN, _DOWN),
    _BvhJoint("r_ankle", "r_knee", "r_ankle", _DOWN, _FORWARD),
    _BvhJoint("r_toe", "r_ankle", "r_toe", _FORWARD, _FORWARD),
    _BvhJoint("spine", "pelvis", "pelvis", (0, 0, 0), _UP),
    _BvhJoint("chest", "spine", "neck", _UP, _UP),
    _BvhJoint("neck", "chest", "neck", (0, 0, 0), _UP),
    _BvhJoint("head", "neck", "head", _UP, _UP),
    _BvhJoint("l_clavicle", "chest", "neck", (0, 0, 0), _LEFT),
    _BvhJoint("l_shoulder", "l_clavicle", "l_shoulder", _LEFT, _LEFT),
    _BvhJoint("l_elbow", "l_shoulder", "l_elbow", _LEFT, _LEFT),
    _BvhJoint("l_wrist", "l_elbow", "l_wrist", _LEFT, _LEFT),
    _BvhJoint("r_clavicle", "chest", "neck", (0, 0, 0), _RIGHT),
    _BvhJoint("r_shoulder", "r_clavicle", "r_shoulder", _RIGHT, _RIGHT),
    _BvhJoint("r_elbow", "r_shoulder", "r_elbow", _RIGHT, _RIGHT),
    _BvhJoint("r_wrist", "r_elbow", "r_wrist", _RIGHT, _RIGHT),
)


def _swing(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(F, 3, 3) smallest rotations turning unit vectors ``a (F, 3)`` onto unit vectors ``b (F, 3)``.

    For opposite vectors every half turn about an axis perpendicular to ``a`` is smallest; one is chosen.
    """
    axis = np.cross(a, b)
    sin = np.linalg.norm(axis, axis=-1)
    angle = np.arctan2(sin, np.einsum("fi,fi->f", a, b))
    rotvec = axis * (angle / np.maximum(sin, _TINY))[:, None]
    opposite = (sin < _TINY) & (angle > np.pi / 2)
    if opposite.any():
        helper = np.where(np.abs(a[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        rotvec[opposite] = np.pi * _unit(np.cross(a, helper))[opposite]
    return Rotation.from_rotvec(rotvec).as_matrix()


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def pelvis_frame(P: dict[str, np.ndarray]) -> np.ndarray:
    """(F, 3, 3) pelvis world rotation: columns = left (r_hip -> l_hip), trunk up, forward.

    ``P`` maps at least l_hip, r_hip, pelvis and neck to their (F, 3) positions. Besides the BVH's root,
    this is the body frame in which the paper benchmark measures each joint's constant offset.
    """
    left = _unit(P["l_hip"] - P["r_hip"])
    up = P["neck"] - P["pelvis"]
    up = _unit(up - np.einsum("fi,fi->f", up, left)[:, None] * left)
    return np.stack([left, up, np.cross(left, up)], axis=-1)


def _bvh_joints(names: Sequence[str]) -> list[_BvhJoint]:
    """The BVH joints whose joints.csv joint is present (the toes are optional)."""
    return [j for j in _JOINTS if j.at in names]


def _children(joints: list[_BvhJoint], name: str) -> list[_BvhJoint]:
    return [j for j in joints if j.parent == name]


def _world_rotations(joints: list[_BvhJoint], P: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """(F, 3, 3) world rotation of every BVH joint (see the module docstring, "Rotations")."""
    G = {"pelvis": pelvis_frame(P)}
    for joint in joints[1:]:
        parent_G = G[joint.parent]
        aimed = [c for c in _children(joints, joint.name) if np.any(c.rest_from_parent)]
        if not aimed:
            G[joint.name] = parent_G
            continue
        child = aimed[0]
        rest = parent_G @ np.array(child.rest_from_parent, dtype=np.float64)
        observed = _unit(P[child.at] - P[joint.at])
        G[joint.name] = _swing(rest, observed) @ parent_G
    return G


def _euler_zxy_degrees(R: np.ndarray) -> np.ndarray:
    """(F, 3) angles (z, x, y) in degrees with ``R = Rz @ Rx @ Ry``, continuous over frames.

    Every rotation has two ZXY triples, (z, x, y) and (z + 180, 180 - x, y + 180), and each angle is
    defined modulo 360; frame by frame the triple closest to the previous frame's is kept, so a
    viewer interpolating between frames does not spin a joint round.
    """
    with warnings.catch_warnings():
        # Near x = +-90 degrees the split between z and y is arbitrary; the product is still exact.
        warnings.filterwarnings("ignore", message="Gimbal lock detected")
        first = np.degrees(Rotation.from_matrix(R).as_euler("ZXY"))
    second = np.column_stack([first[:, 0] + 180.0, 180.0 - first[:, 1], first[:, 2] + 180.0])
    # Python floats: the loop is sequential, and numpy's per-call cost on three values was most of a BVH export.
    # round() rounds halves to even as np.round does, so the angles are the same to the bit.
    previous = first[0].tolist()
    angles = []
    for triples in zip(first.tolist(), second.tolist(), strict=True):
        best, best_distance = None, 0.0
        for triple in triples:
            moved = [a - 360.0 * round((a - p) / 360.0) for a, p in zip(triple, previous, strict=True)]
            distance = abs(moved[0] - previous[0]) + abs(moved[1] - previous[1]) + abs(moved[2] - previous[2])
            if best is None or distance < best_distance:  # the first of equals, as np.argmin
                best, best_distance = moved, distance
        angles.append(best)
        previous = best
    return np.array(angles).reshape(-1, 3)


def _positioned(joints: list[_BvhJoint]) -> set[str]:
    """BVH joints with position channels: the root, and the ends of the flexible bones (trunk, neck)."""
    at = {joint.name: joint.at for joint in joints}
    return {joints[0].name} | {joint.name for joint in joints[1:]
                               if (at[joint.parent], joint.at) in FLEXIBLE_BONES and any(joint.rest_from_parent)}


def _hierarchy_text(joints: list[_BvhJoint], offsets: dict[str, np.ndarray], names: dict[str, str],
                    end_site_length: float) -> list[str]:
    lines = ["HIERARCHY"]
    positioned = _positioned(joints)

    def write(joint: _BvhJoint, depth: int) -> None:
        pad = "  " * depth
        keyword = "ROOT" if joint.parent is None else "JOINT"
        lines.append(f"{pad}{keyword} {names.get(joint.name, joint.name)}")
        lines.append(f"{pad}{{")
        x, y, z = offsets[joint.name]
        lines.append(f"{pad}  OFFSET {x:.{DECIMALS}f} {y:.{DECIMALS}f} {z:.{DECIMALS}f}")
        if joint.name in positioned:
            lines.append(f"{pad}  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation")
        else:
            lines.append(f"{pad}  CHANNELS 3 Zrotation Xrotation Yrotation")
        children = _children(joints, joint.name)
        for child in children:
            write(child, depth + 1)
        if not children:
            ex, ey, ez = np.array(joint.end_site) * end_site_length
            end_offset = f"OFFSET {ex:.{DECIMALS}f} {ey:.{DECIMALS}f} {ez:.{DECIMALS}f}"
            lines.extend([f"{pad}  End Site", f"{pad}  {{", f"{pad}    {end_offset}", f"{pad}  }}"])
        lines.append(f"{pad}}}")

    write(joints[0], 0)
    return lines


def bvh_from_joints(joints: np.ndarray, frame_time_s: float, *, names: Sequence[str] = JOINT_NAMES,
                    units: str = "cm", naming: str = "joints") -> str:
    """BVH text animating a skeleton through the given joint positions.

    Parameters
    ----------
    joints : (F, J, 3) float, metres, world frame (+z up)
        Joint centres of consecutive frames (fill gaps first: :func:`~stages.export.joints_table.fill_gaps`),
        in the order of ``names``.
    frame_time_s : float
        Seconds between frames (``step / fps``).
    names : sequence of J str
        Must include the 15 scored joints; ``l_toe`` / ``r_toe`` are used when present.
    units : {"cm", "m", "mm"}
        Length unit of the file (:data:`UNITS`).
    naming : {"joints", "mixamo"}
        The BVH joints' names (:data:`BONE_NAMINGS`).

    Returns
    -------
    str
        The BVH file's text (hierarchy and motion), see the module docstring for its conventions.
    """
    joints = np.asarray(joints, dtype=np.float64)
    if joints.ndim != 3 or joints.shape[1:] != (len(names), 3) or len(joints) == 0:
        raise ValueError(f"joints must have shape (F >= 1, {len(names)}, 3), got {joints.shape}")
    if not np.all(np.isfinite(joints)) or not frame_time_s > 0:
        raise ValueError("bvh_from_joints needs finite joints (fill gaps first) and a positive frame time")
    if units not in UNITS or naming not in BONE_NAMINGS:
        raise ValueError(f"units must be one of {list(UNITS)} and naming one of {list(BONE_NAMINGS)}, "
                         f"got {units!r} and {naming!r}")
    present = [n for n in JOINT_NAMES if n in names]
    wanted = list(SCORED_JOINTS) + [n for n in ("l_toe", "r_toe") if n in present]
    selected = select_joints(names, joints, wanted, source="bvh_from_joints joints") * UNITS[units]
    P = {name: selected[:, i] @ WORLD_TO_BVH.T for i, name in enumerate(wanted)}
    bvh_joints = _bvh_joints(wanted)

    at = {joint.name: joint.at for joint in bvh_joints}
    parent_at = {joint.name: at[joint.parent] for joint in bvh_joints[1:]}
    offsets = {"pelvis": np.zeros(3)}
    for joint in bvh_joints[1:]:
        length = np.median(np.linalg.norm(P[joint.at] - P[parent_at[joint.name]], axis=-1))
        offsets[joint.name] = np.array(joint.rest_from_parent, dtype=np.float64) * length

    G = _world_rotations(bvh_joints, P)
    positioned = _positioned(bvh_joints)
    columns = [P["pelvis"], _euler_zxy_degrees(G["pelvis"])]
    for joint in bvh_joints[1:]:
        if joint.name in positioned:  # the rest direction times the bone's current length
            length = np.linalg.norm(P[joint.at] - P[parent_at[joint.name]], axis=-1)
            columns.append(length[:, None] * np.array(joint.rest_from_parent, dtype=np.float64))
        local = np.swapaxes(G[joint.parent], -1, -2) @ G[joint.name]
        columns.append(_euler_zxy_degrees(local))
    motion = np.hstack(columns)

    lines = _hierarchy_text(bvh_joints, offsets, BONE_NAMINGS[naming], END_SITE_LENGTH_M * UNITS[units])
    lines += ["MOTION", f"Frames: {len(motion)}", f"Frame Time: {frame_time_s:.{DECIMALS + 2}f}"]
    lines += [" ".join(f"{v:.{DECIMALS}f}" for v in row) for row in motion]
    return "\n".join(lines) + "\n"
