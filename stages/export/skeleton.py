"""The bones between the joints of ``JOINT_NAMES``: one tree rooted at the pelvis, and one body size for a sequence.

Every exporter and drawing uses this one list, so the BVH hierarchy, the overlays and the report's
3-D view show the same skeleton. The trunk is one bone pelvis -> neck (joints.csv has no spine joints).

One skeleton for every exported frame
    The tracker estimates the body's segment lengths over its first frames and then freezes them
    (``TrackerParams.scale_frames``), so in those first frames the joints belong to a body that is
    still changing size (a shank 2-3 cm longer than later). A BVH has one set of bone lengths, so it
    could not reproduce those frames, and a body that shrinks is no real motion. The exports
    therefore give every frame the *settled* lengths, those of the sequence's last frame (the tracker
    never changes them after they froze, and before that the last frame holds the estimate from the
    most frames), along each frame's own bone directions (:func:`with_bone_lengths`). The two
    flexible bones keep their own length in every frame: the trunk (pelvis -> neck: the spine bends)
    and the neck (neck -> head: the head nods about a joint between the two).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: (parent, child) joint names, parents before children (a breadth-first order of the tree).
BONES: tuple[tuple[str, str], ...] = (
    ("pelvis", "l_hip"), ("pelvis", "r_hip"), ("pelvis", "neck"),
    ("neck", "head"), ("neck", "l_shoulder"), ("neck", "r_shoulder"),
    ("l_hip", "l_knee"), ("r_hip", "r_knee"),
    ("l_shoulder", "l_elbow"), ("r_shoulder", "r_elbow"),
    ("l_knee", "l_ankle"), ("r_knee", "r_ankle"),
    ("l_elbow", "l_wrist"), ("r_elbow", "r_wrist"),
    ("l_ankle", "l_toe"), ("r_ankle", "r_toe"),
)

#: Bones whose length changes with the pose: the trunk, whose spine bends, and the neck, whose head nods
#: about a joint between the neck and head centres. Every other bone is one rigid segment of the body.
FLEXIBLE_BONES: tuple[tuple[str, str], ...] = (("pelvis", "neck"), ("neck", "head"))

def bones_among(names: Sequence[str]) -> list[tuple[int, int]]:
    """Index pairs ``(parent, child)`` into ``names`` of the :data:`BONES` whose two joints are present."""
    index = {name: i for i, name in enumerate(names)}
    return [(index[a], index[b]) for a, b in BONES if a in index and b in index]


def settled_lengths(joints: np.ndarray, names: Sequence[str]) -> np.ndarray:
    """Length of every bone of :func:`bones_among` in the sequence's last frame, metres.

    Parameters
    ----------
    joints : (F, J, 3) float, F >= 1, in frame order, in the order of ``names``

    Returns
    -------
    (B,) float, in the order of ``bones_among(names)`` (flexible bones included, though unused).
    """
    last = np.asarray(joints, dtype=np.float64)[-1]
    return np.array([np.linalg.norm(last[child] - last[parent]) for parent, child in bones_among(names)])


def with_bone_lengths(joints: np.ndarray, names: Sequence[str], lengths: np.ndarray) -> np.ndarray:
    """The joints rebuilt from the root outwards with the given bone lengths along each frame's bone directions.

    The pelvis stays; every rigid bone's child is placed at its (already rebuilt) parent plus the
    frame's direction of that bone times its length; a flexible bone (:data:`FLEXIBLE_BONES`) keeps the
    frame's own vector. The hips take the direction of the line between them, so that the pelvis lies
    on it as in the tracker's body and in the BVH, whose pelvis aims both hips with one rotation
    (smoothing keeps that, but noisy joints from elsewhere need not). A joint outside :data:`BONES` is
    left where it is. When the lengths already are the frame's and the pelvis is on the hip line,
    nothing moves.

    Parameters
    ----------
    joints : (F, J, 3) float, metres (NaN frames stay NaN)
    names : J str
    lengths : (B,) float, metres, in the order of ``bones_among(names)`` (:func:`settled_lengths`)
    """
    joints = np.asarray(joints, dtype=np.float64)
    bones = bones_among(names)
    if len(lengths) != len(bones):
        raise ValueError(f"expected {len(bones)} bone lengths, got {len(lengths)}")
    index = {name: i for i, name in enumerate(names)}
    flexible = {(index[a], index[b]) for a, b in FLEXIBLE_BONES if a in index and b in index}
    directions = {}
    if {"pelvis", "l_hip", "r_hip"} <= set(index):
        across = joints[:, index["l_hip"]] - joints[:, index["r_hip"]]
        directions = {(index["pelvis"], index["l_hip"]): across, (index["pelvis"], index["r_hip"]): -across}
    rebuilt = joints.copy()
    for (parent, child), length in zip(bones, lengths, strict=True):
        bone = joints[:, child] - joints[:, parent]
        if (parent, child) not in flexible:
            direction = directions.get((parent, child), bone)
            bone = direction * (length / np.linalg.norm(direction, axis=-1, keepdims=True))
        rebuilt[:, child] = rebuilt[:, parent] + bone
    return rebuilt
