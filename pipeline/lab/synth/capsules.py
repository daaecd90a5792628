"""A body of tapered capsules along the bones of a skeleton, with anthropometric radii.

CMU skeletons (ASF/AMC and their BVH conversions) get capsules bound to their bones
(``CapsuleBody``); any other skeleton the mocap reader maps to the 17 joints of ``JOINT_NAMES`` gets
capsules between those joints (``JointCapsuleBody``), so that every readable clip can be rendered.

Each capsule is the convex hull of two spheres whose centres are *anchors*: points fixed in a bone's
frame (a fraction of the way along the bone plus an offset), so they move rigidly with that bone, or
(joint-bound) weighted means of joints plus an offset in the torso's axes. The
torso is built from side-by-side capsules (a round capsule cannot be wide and shallow at once); the
head is a short, nearly spherical capsule. Radii are for an adult of about 1.75 m (thigh circumference
about 55 cm, calf 37 cm, upper arm 30 cm, chest 100 cm, head 57 cm).

Offsets are in the rest pose's world axes (bone anchors) or in the torso's own axes (joint anchors):
+x the subject's left, -y forward, +z up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.lab.mocap import Motion
from pipeline.lab.synth.posed import MATERIALS, PosedBody, RoundCones
from stages.joints import JOINT_NAMES

# (name, material, (bone, fraction along it, offset (3,) m), start radius m, (bone, ...), end radius m).
# Left-side entries (bone names starting with "l") are mirrored to the right (x -> -x).
_CENTRE_CAPSULES = (
    ("pelvis", "trousers", ("root", 0.0, (0.065, 0.0, 0.0)), 0.115, ("root", 0.0, (-0.065, 0.0, 0.0)), 0.115),
    ("neck", "skin", ("lowerneck", 0.0, (0.0, 0.0, 0.0)), 0.055, ("head", 0.0, (0.0, 0.0, 0.0)), 0.05),
    ("head", "skin", ("head", 0.1, (0.0, -0.01, 0.0)), 0.085, ("head", 0.85, (0.0, -0.005, 0.0)), 0.09),
)
_LEFT_CAPSULES = (
    ("l_abdomen", "shirt", ("root", 0.0, (0.055, 0.0, 0.07)), 0.11, ("thorax", 0.0, (0.06, 0.0, 0.0)), 0.115),
    ("l_chest", "shirt", ("thorax", 0.0, (0.07, 0.0, 0.0)), 0.12, ("lowerneck", 0.0, (0.06, 0.0, -0.08)), 0.1),
    ("l_shoulder", "shirt", ("lclavicle", 0.3, (0.0, 0.0, -0.02)), 0.065, ("lhumerus", 0.0, (0, 0, 0)), 0.058),
    ("l_upper_arm", "shirt", ("lhumerus", 0.0, (0, 0, 0)), 0.05, ("lhumerus", 1.0, (0, 0, 0)), 0.042),
    ("l_forearm", "skin", ("lradius", 0.0, (0, 0, 0)), 0.042, ("lradius", 1.0, (0, 0, 0)), 0.03),
    ("l_hand", "skin", ("lwrist", 0.0, (0, 0, 0)), 0.032, ("lhand", 1.0, (0, 0, 0)), 0.028),
    ("l_thigh", "trousers", ("lfemur", 0.0, (0, 0, 0)), 0.088, ("lfemur", 1.0, (0, 0, 0)), 0.058),
    ("l_shin", "trousers", ("ltibia", 0.0, (0, 0, 0)), 0.056, ("ltibia", 1.0, (0, 0, 0)), 0.038),
    ("l_foot", "shoes", ("lfoot", 0.0, (0.0, 0.035, -0.035)), 0.038, ("ltoes", 1.0, (0.0, 0.03, 0.025)), 0.028),
)

# Tessellation: points around each ring, rings on each spherical cap (pole included).
RING_POINTS = 24
CAP_RINGS = 7


@dataclass(frozen=True, eq=False)
class CapsuleBody:
    """Capsules bound to a skeleton's bones (built by ``build_capsule_body``).

    Parameters
    ----------
    names : tuple of str, length K
    anchor_bones : (K, 2) int
        Bone index of each capsule's start and end anchor.
    anchor_offsets : (K, 2, 3) float, metres
        Anchor positions relative to their bone's start, in rest-pose world axes.
    radii : (K, 2) float, metres
    materials : (K,) int
        Index into ``MATERIALS``.
    """

    names: tuple[str, ...]
    anchor_bones: np.ndarray
    anchor_offsets: np.ndarray
    radii: np.ndarray
    materials: np.ndarray

    def pose(self, motion: Motion, frame: int) -> PosedBody:
        """The capsules at ``frame`` of ``motion`` as one triangle mesh with its parts."""
        origins = motion.bone_origins[frame][self.anchor_bones]  # (K, 2, 3)
        rotations = motion.bone_rotations[frame][self.anchor_bones]  # (K, 2, 3, 3)
        anchors = origins + np.einsum("kaij,kaj->kai", rotations, self.anchor_offsets)
        cones = RoundCones(anchors[:, 0], anchors[:, 1], self.radii[:, 0], self.radii[:, 1])
        vertices, normals, triangles, vertex_parts = _tessellate(cones)
        return PosedBody(
            vertices=vertices,
            triangles=triangles,
            vertex_normals=normals,
            vertex_materials=self.materials[vertex_parts],
            parts=cones,
            triangle_parts=vertex_parts[triangles[:, 0]],
        )


def _mirrored(entry):
    name, material, (bone0, fraction0, offset0), r0, (bone1, fraction1, offset1), r1 = entry

    def side(bone, fraction, offset):
        right_bone = "r" + bone[1:] if bone.startswith("l") and bone != "lowerneck" else bone
        return right_bone, fraction, (-offset[0], offset[1], offset[2])

    return "r" + name[1:], material, side(bone0, fraction0, offset0), r0, side(bone1, fraction1, offset1), r1


def capsule_table() -> tuple:
    """All capsule entries, centre ones first, then left and right pairs."""
    return _CENTRE_CAPSULES + _LEFT_CAPSULES + tuple(_mirrored(entry) for entry in _LEFT_CAPSULES)


def build_capsule_body(motion: Motion) -> CapsuleBody | JointCapsuleBody:
    """Capsules for ``motion``: on its bones if it has CMU bone names, else between its 17 joints.

    The bone-bound capsules follow CMU's clavicles, spine and toes more closely than the joints alone
    can; the joint-bound ones work for any skeleton the mocap reader maps to ``JOINT_NAMES``.
    """
    table = capsule_table()
    needed = {anchor[0] for entry in table for anchor in (entry[2], entry[4])}
    if not needed.issubset(motion.bone_names):
        return build_joint_capsule_body(motion)
    bones, offsets, radii, materials = [], [], [], []
    for _, material, start, r0, end, r1 in table:
        pair_bones, pair_offsets = [], []
        for bone, fraction, offset in (start, end):
            index = motion.bone_index(bone)
            along = motion.rest_ends[index] - motion.rest_origins[index]
            pair_bones.append(index)
            pair_offsets.append(fraction * along + np.asarray(offset, dtype=float))
        bones.append(pair_bones)
        offsets.append(pair_offsets)
        radii.append((r0, r1))
        materials.append(MATERIALS.index(material))
    return CapsuleBody(
        names=tuple(entry[0] for entry in table),
        anchor_bones=np.array(bones),
        anchor_offsets=np.array(offsets),
        radii=np.array(radii, dtype=float),
        materials=np.array(materials),
    )


# Joint-bound capsules, for skeletons without CMU bone names. An anchor is (joints with weights summing
# to 1, torso axes or "" for world axes, offset (3,) m at the reference height); a weight above 1 reaches
# beyond a joint along a limb. The radii and the torso's offsets are those of the bone-bound table, so
# both bodies have the same girths; "hips" and "shoulders" axes have +x along the hip or shoulder line,
# +z from the pelvis towards the neck, so the torso keeps its width however the joints are spaced.
def _at(joint, axes="", offset=(0.0, 0.0, 0.0)):
    return ((joint, 1.0),), axes, offset


def _between(joint0, joint1, fraction, axes="", offset=(0.0, 0.0, 0.0)):
    return ((joint0, 1.0 - fraction), (joint1, fraction)), axes, offset


# Where the head capsule's sphere centres sit along the neck -> head line, as fractions of it either side
# of the head joint (the head's centre): a nearly round head, lengthened along the neck's direction.
_HEAD_SPAN = 0.25
# How far the hand reaches beyond the wrist, as a fraction of the forearm (hand length ~0.108 of the
# height, forearm ~0.146, Winter's segment table; this is the fingertip sphere's centre, not the tip).
_HAND_REACH = 0.55
# How far the foot's end sphere lies beyond the toe joint (the ball of the foot) along the foot, as a
# fraction of ankle -> ball, so the foot ends near the toe tips.
_TOE_REACH = 0.3
# Fraction of the way from the pelvis to the neck where the abdomen capsules meet the chest capsules.
_WAIST = 0.55

_JOINT_CENTRE_CAPSULES = (
    ("pelvis", "trousers", _at("pelvis", "hips", (0.065, 0.0, 0.04)), 0.115,
     _at("pelvis", "hips", (-0.065, 0.0, 0.04)), 0.115),
    ("neck", "skin", _at("neck"), 0.055, _between("neck", "head", 1.0 - _HEAD_SPAN), 0.05),
    ("head", "skin", _between("neck", "head", 1.0 - _HEAD_SPAN), 0.085,
     _between("neck", "head", 1.0 + _HEAD_SPAN), 0.09),
)  # fmt: skip
_JOINT_LEFT_CAPSULES = (
    ("l_abdomen", "shirt", _at("pelvis", "hips", (0.055, 0.0, 0.1)), 0.11,
     _between("pelvis", "neck", _WAIST, "shoulders", (0.06, 0.0, 0.0)), 0.115),
    ("l_chest", "shirt", _between("pelvis", "neck", _WAIST, "shoulders", (0.07, 0.0, 0.0)), 0.12,
     _at("neck", "shoulders", (0.06, 0.0, -0.08)), 0.1),
    ("l_shoulder", "shirt", _at("neck", "shoulders", (0.07, 0.0, -0.04)), 0.065, _at("l_shoulder"), 0.058),
    ("l_upper_arm", "shirt", _at("l_shoulder"), 0.05, _at("l_elbow"), 0.042),
    ("l_forearm", "skin", _at("l_elbow"), 0.042, _at("l_wrist"), 0.03),
    ("l_hand", "skin", _at("l_wrist"), 0.032, _between("l_elbow", "l_wrist", 1.0 + _HAND_REACH), 0.028),
    ("l_thigh", "trousers", _at("l_hip"), 0.088, _at("l_knee"), 0.058),
    ("l_shin", "trousers", _at("l_knee"), 0.056, _at("l_ankle"), 0.038),
    ("l_foot", "shoes", _at("l_ankle"), 0.038, _between("l_ankle", "l_toe", 1.0 + _TOE_REACH), 0.028),
)  # fmt: skip

# Anthropometric height of the radii and offsets above (module docstring), and the share of the height
# from the hip joint to the ankle (0.530 - 0.039 of the height, Winter's segment table), from which the
# body's own height is estimated: the leg is measured by the clip's joints in every convention.
REFERENCE_HEIGHT_M = 1.75
HIP_TO_ANKLE_OF_HEIGHT = 0.491
_TORSO_AXES = ("", "hips", "shoulders")


@dataclass(frozen=True, eq=False)
class JointCapsuleBody:
    """Capsules bound to the 17 joints of ``Motion.joints`` (built by ``build_joint_capsule_body``).

    Parameters
    ----------
    names : tuple of str, length K
    anchor_weights : (K, 2, 17) float
        Each anchor as an affine combination of the joints (weights sum to 1).
    anchor_axes : (K, 2) int
        Index into ``_TORSO_AXES`` of the axes the anchor's offset is in (0: world).
    anchor_offsets : (K, 2, 3) float, metres
    radii : (K, 2) float, metres
    materials : (K,) int
        Index into ``MATERIALS``.
    """

    names: tuple[str, ...]
    anchor_weights: np.ndarray
    anchor_axes: np.ndarray
    anchor_offsets: np.ndarray
    radii: np.ndarray
    materials: np.ndarray

    def pose(self, motion: Motion, frame: int) -> PosedBody:
        """The capsules at ``frame`` of ``motion`` as one triangle mesh with its parts."""
        joints = motion.joints[frame]
        anchors = np.einsum("kaj,jd->kad", self.anchor_weights, joints)
        axes = np.stack([np.eye(3), *(_torso_axes(joints, side) for side in ("hip", "shoulder"))])
        anchors += np.einsum("kaij,kaj->kai", axes[self.anchor_axes], self.anchor_offsets)
        cones = RoundCones(anchors[:, 0], anchors[:, 1], self.radii[:, 0], self.radii[:, 1])
        vertices, normals, triangles, vertex_parts = _tessellate(cones)
        return PosedBody(
            vertices=vertices,
            triangles=triangles,
            vertex_normals=normals,
            vertex_materials=self.materials[vertex_parts],
            parts=cones,
            triangle_parts=vertex_parts[triangles[:, 0]],
        )


def _torso_axes(joints: np.ndarray, side: str) -> np.ndarray:
    """(3, 3) columns: the subject's left along the ``side`` joints, backwards, and up the spine."""
    left = joints[JOINT_NAMES.index(f"l_{side}")] - joints[JOINT_NAMES.index(f"r_{side}")]
    left /= np.linalg.norm(left)
    up = joints[JOINT_NAMES.index("neck")] - joints[JOINT_NAMES.index("pelvis")]
    up -= (up @ left) * left
    up /= np.linalg.norm(up)
    return np.stack([left, np.cross(up, left), up], axis=1)


def _mirrored_joints(entry):
    name, material, start, r0, end, r1 = entry

    def side(anchor):
        weights, axes, offset = anchor
        right = tuple(("r" + joint[1:] if joint.startswith("l_") else joint, w) for joint, w in weights)
        return right, axes, (-offset[0], offset[1], offset[2])

    return "r" + name[1:], material, side(start), r0, side(end), r1


def joint_capsule_table() -> tuple:
    """All joint-bound capsule entries, centre ones first, then left and right pairs."""
    left = _JOINT_LEFT_CAPSULES
    return _JOINT_CENTRE_CAPSULES + left + tuple(_mirrored_joints(entry) for entry in left)


def build_joint_capsule_body(motion: Motion) -> JointCapsuleBody:
    """Capsules between the joints of ``motion``, sized for the height its legs imply."""
    rest = motion.rest_pose().joints[0]
    joint = {name: rest[index] for index, name in enumerate(JOINT_NAMES)}
    leg = np.mean(
        [
            np.linalg.norm(joint[f"{side}_knee"] - joint[f"{side}_hip"])
            + np.linalg.norm(joint[f"{side}_ankle"] - joint[f"{side}_knee"])
            for side in "lr"
        ]
    )
    scale = leg / HIP_TO_ANKLE_OF_HEIGHT / REFERENCE_HEIGHT_M
    table = joint_capsule_table()
    weights = np.zeros((len(table), 2, len(JOINT_NAMES)))
    axes = np.zeros((len(table), 2), dtype=int)
    offsets = np.zeros((len(table), 2, 3))
    for k, (_, _, start, _, end, _) in enumerate(table):
        for a, (pairs, frame, offset) in enumerate((start, end)):
            for joint, weight in pairs:
                weights[k, a, JOINT_NAMES.index(joint)] += weight
            axes[k, a] = _TORSO_AXES.index(frame)
            offsets[k, a] = offset
    return JointCapsuleBody(
        names=tuple(entry[0] for entry in table),
        anchor_weights=weights,
        anchor_axes=axes,
        anchor_offsets=scale * offsets,
        radii=scale * np.array([(entry[3], entry[5]) for entry in table]),
        materials=np.array([MATERIALS.index(entry[1]) for entry in table]),
    )


def _tessellate(cones: RoundCones):
    """Triangle meshes of all capsules: vertices (V, 3), normals (V, 3), triangles (T, 3), part (V,).

    Each capsule is a surface of revolution: the end sphere's cap for normals at angles
    ``psi in [0, pi/2 - alpha]`` from the axis, then the start sphere's cap for ``psi in [pi/2 - alpha,
    pi]``; the straight flank joins the two caps' rims.
    """
    K = len(cones.starts)
    axis = cones.ends - cones.starts
    lengths = np.maximum(np.linalg.norm(axis, axis=1), 1e-12)
    u = axis / lengths[:, None]  # (K, 3)
    helper = np.where(np.abs(u[:, [0]]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(u, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(u, e1)
    sin_alpha = np.clip((cones.start_radii - cones.end_radii) / lengths, -0.99, 0.99)
    flank = np.pi / 2 - np.arcsin(sin_alpha)  # (K,) normal angle of the flank

    steps = np.linspace(0.0, 1.0, CAP_RINGS)
    ring_psi = np.concatenate(
        [steps[None, :] * flank[:, None], flank[:, None] + steps[None, :] * (np.pi - flank[:, None])], axis=1
    )  # (K, 2 * CAP_RINGS)
    on_end_sphere = np.arange(2 * CAP_RINGS) < CAP_RINGS
    centres = np.where(on_end_sphere[None, :, None], cones.ends[:, None], cones.starts[:, None])  # (K, R, 3)
    radii = np.where(on_end_sphere[None, :], cones.end_radii[:, None], cones.start_radii[:, None])  # (K, R)
    phi = np.linspace(0.0, 2 * np.pi, RING_POINTS, endpoint=False)
    radial = np.cos(phi)[None, :, None] * e1[:, None] + np.sin(phi)[None, :, None] * e2[:, None]  # (K, P, 3)
    normals = (
        np.cos(ring_psi)[:, :, None, None] * u[:, None, None, :]
        + np.sin(ring_psi)[:, :, None, None] * radial[:, None, :, :]
    )  # (K, R, P, 3)
    vertices = centres[:, :, None, :] + radii[:, :, None, None] * normals

    n_rings = 2 * CAP_RINGS
    grid = np.arange(n_rings * RING_POINTS).reshape(n_rings, RING_POINTS)
    nxt = np.roll(grid, -1, axis=1)
    # rings go from the end pole (+u) to the start pole (-u); with phi turning from e1 to e2 = u x e1,
    # (ring r, p), (ring r+1, p), (ring r+1, p+1) is counter-clockwise seen from outside.
    quads_a = np.stack([grid[:-1], grid[1:], nxt[1:]], axis=-1).reshape(-1, 3)
    quads_b = np.stack([grid[:-1], nxt[1:], nxt[:-1]], axis=-1).reshape(-1, 3)
    template = np.concatenate([quads_a, quads_b])
    # drop the triangles collapsed at the poles (two corners on the pole ring)
    pole = (template < RING_POINTS) | (template >= (n_rings - 1) * RING_POINTS)
    template = template[pole.sum(axis=1) < 2]
    per_capsule = n_rings * RING_POINTS
    triangles = (template[None] + per_capsule * np.arange(K)[:, None, None]).reshape(-1, 3)
    parts = np.repeat(np.arange(K), per_capsule)
    return vertices.reshape(-1, 3), normals.reshape(-1, 3), triangles.astype(np.int32), parts
