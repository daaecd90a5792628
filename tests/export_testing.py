"""Shared helpers for the export tests: the BVH as an independent reader (bvhio) sees it."""

import bvhio
import numpy as np

from stages.export.bvh import UNITS, WORLD_TO_BVH


def read_bvh_positions(path, n_frames: int, units: str = "cm") -> tuple[dict[str, np.ndarray], float]:
    """Joint world positions (metres, +z up) per BVH joint name, read by bvhio, and the frame time."""
    root = bvhio.readAsHierarchy(str(path))
    joints = {joint.Name: joint for joint, _, _ in root.layout()}
    positions = {name: np.empty((n_frames, 3)) for name in joints}
    for frame in range(n_frames):
        root.loadPose(frame)
        for name, joint in joints.items():
            positions[name][frame] = np.array(joint.PositionWorld) @ WORLD_TO_BVH / UNITS[units]  # BVH -> world
    return positions, bvhio.readAsBvh(str(path)).FrameTime
