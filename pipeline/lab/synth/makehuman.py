"""The MakeHuman base mesh skinned to a CMU skeleton by linear blend skinning (LBS).

Data (``pipeline/lab/data/mesh``, CC0): ``base.obj`` (hm08; its group ``body`` is the skin, 13380 vertices,
13378 quads; decimetres, Y up, facing +Z, left +X, A-pose), ``default.mhskel`` (163 bones whose joints
are means of listed ``base.obj`` vertices) and ``default_weights.mhw`` (per-bone vertex weights).

Binding to a clip
-----------------
1. The mesh is moved to the clip's world axes (the ASF's Y-up -> +z up rotation; both face the same
   way) and scaled uniformly so that its leg + trunk + neck length matches the clip's skeleton.
2. Each MakeHuman bone is assigned a CMU bone: limbs by name (upperleg -> femur, lowerarm -> radius,
   fingers and metacarpals -> wrist, toes -> toes, ...), face bones -> head. The spine and neck chains
   have different numbers of bones in the two skeletons; there, points are matched by arc length along
   the chain (hip centre ... base of the neck, base of the neck ... head centre), and each MakeHuman
   spine/neck bone goes to the CMU bone holding its midpoint. Weights are summed per CMU bone.
3. For each CMU bone ``b`` the mesh's corresponding segment, from ``P0_b`` to ``P1_b``, is mapped onto
   the clip's rest bone by ``F_b``: a stretch along the segment by the length ratio, then a rotation
   ``Q_b`` taking the segment's direction to the clip's rest direction. ``Q_b`` is the parent's ``Q``
   followed by the smallest extra rotation needed, so twist stays continuous along a chain. The pelvis
   (the zero-length root) gets the affine map taking the mesh's hip joints and root point to the clip's.
4. Posing at frame ``t``: ``v' = sum_b w_b [R_b(t) F_b (v - P0_b) + C0_b(t)]``, with ``R_b(t)`` the bone's
   world rotation from rest and ``C0_b(t)`` the bone's posed start, which ``P0_b`` is matched to. Neighbouring bones
   map their shared joint to the same posed point, so blending causes no tearing however much the
   mesh's proportions differ from the clip's.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from calib.errors import InputError
from calib.world import up_rotation
from pipeline.lab.mocap import Motion
from pipeline.lab.synth.posed import MATERIALS, PosedBody, vertex_normals

MESH_DIR = Path(__file__).resolve().parents[1] / "data" / "mesh"
MESH_UNIT_M = 0.1  # MakeHuman meshes are in decimetres

# MakeHuman bone -> CMU bone (without side letter; sides come from the .L / .R suffix).
_LIMB_BONES = {
    "pelvis": "root",
    "upperleg01": "femur",
    "upperleg02": "femur",
    "lowerleg01": "tibia",
    "lowerleg02": "tibia",
    "foot": "foot",
    "clavicle": "clavicle",
    "shoulder01": "clavicle",
    "upperarm01": "humerus",
    "upperarm02": "humerus",
    "lowerarm01": "radius",
    "lowerarm02": "radius",
    "wrist": "wrist",
}
_TORSO_CHAIN_MH = ("spine05", "spine04", "spine03", "spine02", "spine01")
_NECK_CHAIN_MH = ("neck01", "neck02", "neck03")
_TORSO_CHAIN_CMU = ("lowerback", "upperback", "thorax")
_NECK_CHAIN_CMU = ("lowerneck", "upperneck", "head")

# Dominant CMU bone -> clothing. Hair is decided separately, on the head.
_CLOTHING = {
    "root": "trousers", "femur": "trousers", "tibia": "trousers",
    "lowerback": "shirt", "upperback": "shirt", "thorax": "shirt", "clavicle": "shirt", "humerus": "shirt",
    "foot": "shoes", "toes": "shoes",
}  # fmt: skip
# Head vertices this far above the eyes, or this far behind them, wear hair (decimetres, mesh frame).
HAIR_ABOVE_EYES_DM = 0.3
HAIR_BEHIND_EYES_DM = 1.1


@dataclass(frozen=True)
class MakeHumanMesh:
    """The raw mesh in its own frame (decimetres, Y up): body vertices, triangles, joints, weights."""

    vertices: np.ndarray  # (V, 3)
    triangles: np.ndarray  # (T, 3) int32, counter-clockwise seen from outside
    joints: dict  # joint name ("<bone>____head" / "____tail") -> (3,)
    parents: dict  # bone -> parent bone or None
    weights: dict  # bone -> (indices (n,), weights (n,))


@lru_cache(maxsize=1)
def load_makehuman(mesh_dir: Path = MESH_DIR) -> MakeHumanMesh:
    """Read ``base.obj`` (group ``body``), ``default.mhskel`` and ``default_weights.mhw``."""
    all_vertices, body_faces, group = [], [], None
    with (mesh_dir / "base.obj").open() as lines:
        for line in lines:
            if line.startswith("v "):
                all_vertices.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("g "):
                group = line.split()[1]
            elif line.startswith("f ") and group == "body":
                body_faces.append([int(token.split("/")[0]) - 1 for token in line.split()[1:]])
    all_vertices = np.array(all_vertices)
    n_body = 1 + max(max(face) for face in body_faces)
    triangles = []
    for face in body_faces:
        triangles.extend([face[0], face[k], face[k + 1]] for k in range(1, len(face) - 1))
    triangles = np.array(triangles, dtype=np.int32)
    skeleton = json.loads((mesh_dir / "default.mhskel").read_text())
    joints = {name: all_vertices[indices].mean(axis=0) for name, indices in skeleton["joints"].items()}
    parents = {name: bone["parent"] for name, bone in skeleton["bones"].items()}
    weights = {}
    for bone, pairs in json.loads((mesh_dir / "default_weights.mhw").read_text())["weights"].items():
        pairs = np.array(pairs)
        on_body = pairs[:, 0] < n_body
        weights[bone] = (pairs[on_body, 0].astype(int), pairs[on_body, 1])
    vertices = all_vertices[:n_body]
    if _signed_volume(vertices, triangles) < 0:
        triangles = triangles[:, ::-1].copy()
    return MakeHumanMesh(vertices, triangles, joints, parents, weights)


def _signed_volume(vertices: np.ndarray, triangles: np.ndarray) -> float:
    corners = vertices[triangles]
    return float(np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum() / 6)


@dataclass(frozen=True, eq=False)
class MeshBody:
    """The MakeHuman mesh bound to a clip's skeleton (built by ``build_mesh_body``).

    Parameters
    ----------
    rest_vertices : (V, 3) float, metres
        The scaled mesh in world axes (A-pose, not yet fitted to the clip).
    triangles : (T, 3) int32
    weights : (V, B) float
        Skin weights per clip bone (rows sum to 1).
    fit_matrices : (B, 3, 3) float
        ``F_b``: stretch along the segment, then rotation to the clip's rest bone.
    mesh_points : (B, 3) float, metres
        ``P0_b``, the mesh point matched to the start of clip bone ``b``.
    vertex_materials : (V,) int
    """

    rest_vertices: np.ndarray
    triangles: np.ndarray
    weights: np.ndarray
    fit_matrices: np.ndarray
    mesh_points: np.ndarray
    vertex_materials: np.ndarray

    def pose(self, motion: Motion, frame: int) -> PosedBody:
        """The skinned mesh at ``frame`` of ``motion``."""
        R = motion.bone_rotations[frame]  # (B, 3, 3)
        linear = R @ self.fit_matrices  # (B, 3, 3)
        translation = motion.bone_origins[frame] - np.einsum("bij,bj->bi", linear, self.mesh_points)  # (B, 3)
        blended = self.weights @ np.concatenate([linear.reshape(-1, 9), translation], axis=1)  # (V, 12)
        vertices = np.einsum("vij,vj->vi", blended[:, :9].reshape(-1, 3, 3), self.rest_vertices) + blended[:, 9:]
        return PosedBody(
            vertices=vertices,
            triangles=self.triangles,
            vertex_normals=vertex_normals(vertices, self.triangles),
            vertex_materials=self.vertex_materials,
        )


def _side_and_stem(mh_bone: str) -> tuple[str, str]:
    if mh_bone.endswith((".L", ".R")):
        return mh_bone[-1].lower(), mh_bone[:-2]
    return "", mh_bone


def _cmu_bone_of(mh_bone: str, parents: dict, chain_bones: dict) -> str:
    """The CMU bone a MakeHuman bone's weights go to: by name, by chain, else its parent's."""
    bone = mh_bone
    while bone is not None:
        side, stem = _side_and_stem(bone)
        if stem.startswith("toe"):
            return side + "toes"
        if stem in _LIMB_BONES:
            target = _LIMB_BONES[stem]
            return target if target == "root" else side + target
        if bone in chain_bones:
            return chain_bones[bone]
        if bone == "root":
            return "root"
        if bone == "head":
            return "head"
        bone = parents[bone]
    raise ValueError(f"MakeHuman bone {mh_bone} has no mapped ancestor")


def _arc_fractions(points: np.ndarray) -> np.ndarray:
    """(N,) Cumulative arc length along a polyline (N, 3), as fractions of its total length."""
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    cumulative = np.concatenate([[0.0], np.cumsum(steps)])
    return cumulative / cumulative[-1]


def _point_at_fraction(points: np.ndarray, fraction: float) -> np.ndarray:
    """The point at ``fraction`` of the arc length along the polyline ``points`` (N, 3)."""
    fractions = _arc_fractions(points)
    return np.array([np.interp(fraction, fractions, points[:, k]) for k in range(3)])


def _smallest_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) The rotation by the smallest angle taking direction ``a`` to direction ``b``."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    sin, cos = np.linalg.norm(axis), float(np.dot(a, b))
    if sin < 1e-12:
        if cos > 0:
            return np.eye(3)
        perpendicular = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        axis, sin, cos = perpendicular / np.linalg.norm(perpendicular), 0.0, -1.0
    else:
        axis = axis / sin
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + sin * K + (1 - cos) * K @ K


def _affine_from_points(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(3, 3) The linear part of the affine map taking 3 points (3, 3) onto 3 others, and their normals.

    The 4th correspondence is each triangle's centroid plus its unit normal times its mean edge length, so
    the map also scales the out-of-plane direction like the in-plane ones.
    """

    def frame(points):
        edges = points[1:] - points[0]
        normal = np.cross(edges[0], edges[1])
        size = np.mean(np.linalg.norm(edges, axis=1))
        return np.column_stack([edges[0], edges[1], normal / np.linalg.norm(normal) * size])

    return frame(target) @ np.linalg.inv(frame(source))


def build_mesh_body(motion: Motion) -> MeshBody:
    """Bind the MakeHuman mesh to ``motion``'s skeleton (CMU bone names).

    Raises
    ------
    InputError
        The skeleton lacks a CMU bone the mesh needs.
    """
    needed = ("root", "lowerback", "upperback", "thorax", "lowerneck", "upperneck", "head") + tuple(
        side + bone
        for side in "lr"
        for bone in ("clavicle", "humerus", "radius", "wrist", "hand", "femur", "tibia", "foot", "toes")
    )
    missing = [bone for bone in needed if bone not in motion.bone_names]
    if missing:
        raise InputError(
            f"clip skeleton: the mesh body needs CMU bone names, missing {', '.join(missing[:5])}; "
            f"expected a CMU ASF/AMC clip or its BVH conversion"
        )
    mh = load_makehuman()
    A = up_rotation("+y")
    b = motion.bone_index
    rest_o, rest_e = motion.rest_origins, motion.rest_ends

    def mh_joint(name: str) -> np.ndarray:
        return A @ mh.joints[name] * MESH_UNIT_M

    def head(bone: str) -> np.ndarray:
        return mh_joint(f"{bone}____head")

    # Matching points of the two skeletons, in world axes (mesh unscaled, clip at rest).
    mesh_hips = {side: head(f"upperleg01.{side.upper()}") for side in "lr"}
    mesh_hip_centre = (mesh_hips["l"] + mesh_hips["r"]) / 2
    mesh_neck = head("neck01")
    mesh_head_centre = (head("head") + mh_joint("head____tail")) / 2
    mesh_torso = np.array([mesh_hip_centre] + [head(bone) for bone in _TORSO_CHAIN_MH] + [mesh_neck])
    mesh_neck_chain = np.array([head(bone) for bone in _NECK_CHAIN_MH] + [head("head"), mesh_head_centre])

    clip_hip_centre = (rest_o[b("lfemur")] + rest_o[b("rfemur")]) / 2
    clip_torso = np.array([clip_hip_centre] + [rest_o[b(bone)] for bone in _TORSO_CHAIN_CMU] + [rest_e[b("thorax")]])
    clip_neck_chain = np.array(
        [rest_o[b(bone)] for bone in _NECK_CHAIN_CMU] + [(rest_o[b("head")] + rest_e[b("head")]) / 2]
    )

    def leg_and_trunk(hips, knee, ankle, torso, neck_chain):
        return np.linalg.norm(knee - hips) + np.linalg.norm(ankle - knee) + _arc_length(torso) + _arc_length(neck_chain)

    scale = leg_and_trunk(
        rest_o[b("lfemur")], rest_o[b("ltibia")], rest_o[b("lfoot")], clip_torso, clip_neck_chain
    ) / leg_and_trunk(mesh_hips["l"], head("lowerleg01.L"), head("foot.L"), mesh_torso, mesh_neck_chain)

    def mesh_point(name: str) -> np.ndarray:
        return scale * head(name)

    mesh_torso, mesh_neck_chain = scale * mesh_torso, scale * mesh_neck_chain
    mesh_hip_centre = scale * mesh_hip_centre

    # Start and end of each clip bone's segment on the mesh (P0, P1).
    segments = _chain_segments(clip_torso, mesh_torso, _TORSO_CHAIN_CMU, first_point=1)
    segments.update(_chain_segments(clip_neck_chain, mesh_neck_chain, _NECK_CHAIN_CMU[:2], first_point=0))
    head_start = _point_at_fraction(mesh_neck_chain, _arc_fractions(clip_neck_chain)[2])
    segments["head"] = (head_start, head_start + 2 * (mesh_neck_chain[-1] - head_start))  # centre halfway
    toe_balls = {side: np.mean([mesh_point(f"toe{k}-1.{side.upper()}") for k in range(1, 6)], axis=0) for side in "lr"}
    for side in "lr":
        S = side.upper()
        segments[side + "clavicle"] = (mesh_point(f"clavicle.{S}"), mesh_point(f"upperarm01.{S}"))
        segments[side + "humerus"] = (mesh_point(f"upperarm01.{S}"), mesh_point(f"lowerarm01.{S}"))
        segments[side + "radius"] = (mesh_point(f"lowerarm01.{S}"), mesh_point(f"wrist.{S}"))
        segments[side + "wrist"] = (mesh_point(f"wrist.{S}"), mesh_point(f"finger3-1.{S}"))
        segments[side + "femur"] = (mesh_point(f"upperleg01.{S}"), mesh_point(f"lowerleg01.{S}"))
        segments[side + "tibia"] = (mesh_point(f"lowerleg01.{S}"), mesh_point(f"foot.{S}"))
        segments[side + "foot"] = (mesh_point(f"foot.{S}"), toe_balls[side])
        toe_tip = scale * mh_joint(f"toe3-3.{S}____tail")
        segments[side + "toes"] = (toe_balls[side], toe_tip)

    # The clip's rest segment for each bone: its start and end, except the wrist segment, which runs to
    # the end of the hand (the mesh's hand moves with the wrist bone), and the head's, which ends at the
    # clip's head bone end.
    def clip_segment(bone: str) -> tuple[np.ndarray, np.ndarray]:
        if bone.endswith("wrist"):
            return rest_o[b(bone)], rest_e[b(bone[0] + "hand")]
        return rest_o[b(bone)], rest_e[b(bone)]

    n_bones = len(motion.bone_names)
    fit = np.broadcast_to(np.eye(3), (n_bones, 3, 3)).copy()
    mesh_points = np.zeros((n_bones, 3))
    Q = np.broadcast_to(np.eye(3), (n_bones, 3, 3)).copy()
    # The pelvis: affine from the mesh's (hips, root point) to the clip's.
    mesh_root_point = _point_at_fraction(mesh_torso, _arc_fractions(clip_torso)[1])
    root = b("root")
    fit[root] = _affine_from_points(
        np.array([scale * mesh_hips["l"], scale * mesh_hips["r"], mesh_root_point]),
        np.array([rest_o[b("lfemur")], rest_o[b("rfemur")], rest_o[root]]),
    )
    mesh_points[root] = mesh_root_point
    for bone in range(1, n_bones):  # parents come first
        name = motion.bone_names[bone]
        Q[bone] = Q[motion.parents[bone]]
        if name not in segments:
            continue
        p0, p1 = segments[name]
        c0, c1 = clip_segment(name)
        mesh_direction, clip_direction = p1 - p0, c1 - c0
        Q[bone] = _smallest_rotation(Q[bone] @ mesh_direction, clip_direction) @ Q[bone]
        d = mesh_direction / np.linalg.norm(mesh_direction)
        stretch = np.linalg.norm(clip_direction) / np.linalg.norm(mesh_direction)
        fit[bone] = Q[bone] @ (np.eye(3) + (stretch - 1) * np.outer(d, d))
        mesh_points[bone] = p0

    weights, dominant = _clip_weights(mh, motion, mesh_torso, clip_torso, mesh_neck_chain, clip_neck_chain)
    rest_vertices = scale * mh.vertices @ (A * MESH_UNIT_M).T
    materials = _materials(mh, motion, dominant)
    return MeshBody(rest_vertices, mh.triangles, weights, fit, mesh_points, materials)


def _chain_segments(clip_chain, mesh_chain, bones, *, first_point):
    """Mesh segments (P0, P1) of the clip bones along a chain, matched by arc length.

    Clip bone ``k`` runs from point ``first_point + k`` to the next of ``clip_chain`` (N, 3); its mesh
    segment joins the points at the same arc-length fractions of ``mesh_chain`` (M, 3).
    """
    fractions = _arc_fractions(clip_chain)
    return {
        bone: (
            _point_at_fraction(mesh_chain, fractions[first_point + k]),
            _point_at_fraction(mesh_chain, fractions[first_point + k + 1]),
        )
        for k, bone in enumerate(bones)
    }


def _arc_length(points: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


def _clip_weights(mh, motion, mesh_torso, clip_torso, mesh_neck_chain, clip_neck_chain):
    """(V, B) weights per clip bone (rows sum to 1), and each vertex's dominant clip bone (V,)."""
    chain_bones = {}
    # MakeHuman chain bone k spans points k+1..k+2 of the torso polyline (which starts at the hip centre)
    # and k..k+1 of the neck polyline; clip segment j of the torso is root, lowerback, ... .
    for mh_chain, mesh_chain, clip_chain, clip_bones, first_point in (
        (_TORSO_CHAIN_MH, mesh_torso, clip_torso, ("root",) + _TORSO_CHAIN_CMU, 1),
        (_NECK_CHAIN_MH, mesh_neck_chain, clip_neck_chain, _NECK_CHAIN_CMU, 0),
    ):
        mesh_fractions = _arc_fractions(mesh_chain)
        clip_fractions = _arc_fractions(clip_chain)
        for k, bone in enumerate(mh_chain):
            middle = (mesh_fractions[first_point + k] + mesh_fractions[first_point + k + 1]) / 2
            segment = int(np.searchsorted(clip_fractions, middle, side="right")) - 1
            chain_bones[bone] = clip_bones[min(segment, len(clip_bones) - 1)]
    n_vertices = len(mh.vertices)
    weights = np.zeros((n_vertices, len(motion.bone_names)))
    for mh_bone, (indices, values) in mh.weights.items():
        target = motion.bone_index(_cmu_bone_of(mh_bone, mh.parents, chain_bones))
        np.add.at(weights[:, target], indices, values)
    totals = weights.sum(axis=1, keepdims=True)
    unweighted = totals[:, 0] <= 0
    if np.any(unweighted):  # none in hm08; kept safe by riding on the root
        weights[unweighted, 0], totals[unweighted] = 1.0, 1.0
    return weights / totals, np.argmax(weights, axis=1)


def _materials(mh: MakeHumanMesh, motion: Motion, dominant: np.ndarray) -> np.ndarray:
    """(V,) Clothing per vertex from its dominant bone; hair on the top and back of the head."""
    stems = [name[1:] if name[:1] in "lr" and name[1:] in _CLOTHING else name for name in motion.bone_names]
    materials = np.array([MATERIALS.index(_CLOTHING.get(stem, "skin")) for stem in stems])[dominant]
    eyes = (mh.joints["eye.L____head"] + mh.joints["eye.R____head"]) / 2
    neck_top = mh.joints["head____head"]
    on_head = dominant == motion.bone_index("head")
    above = mh.vertices[:, 1] > eyes[1] + HAIR_ABOVE_EYES_DM
    behind = (mh.vertices[:, 2] < eyes[2] - HAIR_BEHIND_EYES_DM) & (mh.vertices[:, 1] > neck_top[1])
    materials[on_head & (above | behind)] = MATERIALS.index("hair")
    return materials
