"""The bones between the joints of ``JOINT_NAMES``: one tree rooted at the pelvis.

Every exporter and drawing uses this one list, so the BVH hierarchy, the overlays and the report's
3-D view show the same skeleton. The trunk is one bone pelvis -> neck (joints.csv has no spine joints).
"""

from __future__ import annotations

from collections.abc import Sequence

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


def bones_among(names: Sequence[str]) -> list[tuple[int, int]]:
    """Index pairs ``(parent, child)`` into ``names`` of the :data:`BONES` whose two joints are present."""
    index = {name: i for i, name in enumerate(names)}
    return [(index[a], index[b]) for a, b in BONES if a in index and b in index]
