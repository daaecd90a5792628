"""Choosing and posing the synthetic body: the skinned MakeHuman mesh (default) or tapered capsules.

Usage (frame ``k`` of a clip)::

    motion = load_clip("pipeline/lab/data/clips/135_07.amc", skeleton="pipeline/lab/data/clips/martialwalk.asf")
    body = build_body(motion)                      # once per clip: "mesh" (default) or "capsules"
    posed = pose_body(body, motion, k)             # PosedBody: triangles in world metres
    points, normals = sample_body_surface(posed, 5000, np.random.default_rng(0))
    vertices, triangles = posed_mesh(posed)
"""

from __future__ import annotations

from calib.errors import InputError
from pipeline.lab.mocap import Motion
from pipeline.lab.synth.capsules import CapsuleBody, JointCapsuleBody, build_capsule_body
from pipeline.lab.synth.makehuman import MeshBody, build_mesh_body
from pipeline.lab.synth.posed import PosedBody

BODY_KINDS = ("mesh", "capsules")

Body = MeshBody | CapsuleBody | JointCapsuleBody


def build_body(motion: Motion, kind: str = "mesh") -> Body:
    """The body surface of ``kind`` bound to ``motion``'s skeleton.

    The mesh is skinned to CMU bones; the capsules fit any skeleton the mocap reader maps to the 17
    joints, so a mesh that cannot be bound points the user to them.

    Raises
    ------
    InputError
        ``kind`` is "mesh" and the skeleton lacks a CMU bone the mesh needs.
    """
    if kind == "mesh":
        try:
            return build_mesh_body(motion)
        except InputError as error:
            raise InputError(f"{error}; --body capsules renders any clip the mocap reader reads") from error
    if kind == "capsules":
        return build_capsule_body(motion)
    raise ValueError(f"body kind: expected one of {', '.join(BODY_KINDS)}, got {kind!r}")


def pose_body(body: Body, motion: Motion, frame: int) -> PosedBody:
    """``body`` posed at ``frame`` (0-based) of ``motion``, the clip it was built for."""
    if not 0 <= frame < motion.n_frames:
        raise IndexError(f"frame {frame} outside the clip's {motion.n_frames} frames")
    return body.pose(motion, frame)
