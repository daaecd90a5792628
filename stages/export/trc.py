"""TRC text: the joints as virtual markers for OpenSim and Pose2Sim.

TRC ("track row column", from Motion Analysis Corp.) is what OpenSim's scaling and inverse-kinematics
tools and Pose2Sim read. Layout (tab-separated)::

    PathFileType  4  (X/Y/Z)  joints.trc
    DataRate  CameraRate  NumFrames  NumMarkers  Units  OrigDataRate  OrigDataStartFrame  OrigNumFrames
    30.0  30.0  120  17  mm  30.0  0  120
    Frame#  Time  pelvis      neck  ...
                  X1  Y1  Z1  X2  Y2  Z2  ...
    <blank line>
    0  0.000000  x  y  z  x  y  z  ...

Conventions
    OpenSim's: +Y up, millimetres. World points (x, y, z) (+z up, CAPTURE_FORMAT.md) are written as
    (x, z, -y), the proper rotation by -90 degrees about x that the BVH uses too. ``Frame#`` holds the
    capture's own frame numbers and ``Time`` is frame / fps seconds, so a run on an excerpt keeps its
    place in the capture; ``OrigDataStartFrame`` is the first frame's number. The rows run over a
    regular grid (``DataRate`` = fps / frame step) from the first to the last estimated frame; a frame
    that was not estimated has empty marker cells (OpenSim reads them as missing), never made-up values.

Marker names
    ``joints.csv``'s joint names, or the HALPE_26 keypoint names of Pose2Sim's OpenSim models
    (:data:`HALPE26_NAMES`); docs/exports.md says where the joint centres and those keypoints differ.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

#: World (x, y, z), +z up  ->  TRC (x, z, -y), +Y up (the same rotation as the BVH's).
WORLD_TO_TRC = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

#: Decimal places of the coordinates (millimetres): 0.1 micrometre, as joints.csv.
DECIMALS = 4

#: joints.csv name -> HALPE_26 keypoint name (Pose2Sim's ``HALPE_26`` skeleton and its OpenSim marker set).
HALPE26_NAMES: dict[str, str] = {
    "pelvis": "Hip", "neck": "Neck", "head": "Head",
    "l_shoulder": "LShoulder", "r_shoulder": "RShoulder", "l_elbow": "LElbow", "r_elbow": "RElbow",
    "l_wrist": "LWrist", "r_wrist": "RWrist", "l_hip": "LHip", "r_hip": "RHip",
    "l_knee": "LKnee", "r_knee": "RKnee", "l_ankle": "LAnkle", "r_ankle": "RAnkle",
    "l_toe": "LBigToe", "r_toe": "RBigToe",
}

#: ``export.trc_names`` value -> renaming of joints.csv names (an empty mapping keeps them).
MARKER_NAMINGS: dict[str, Mapping[str, str]] = {"joints": {}, "halpe26": HALPE26_NAMES}


def format_trc(frames: np.ndarray, gridded: np.ndarray, fps: float, names: Sequence[str], *,
               marker_names: Mapping[str, str] | None = None, file_name: str = "joints.trc") -> str:
    """The text of a TRC file.

    Parameters
    ----------
    frames : (G,) int
        A regular grid of the capture's frame numbers (``joints_table.regular_grid``).
    gridded : (G, J, 3) float, metres, world frame (+z up)
        Joint centres in the order of ``names``; NaN in frames that were not estimated.
    fps : float
        The capture's frame rate; the file's rate is ``fps`` / the grid's step.
    names : J str
    marker_names : mapping, optional
        joints.csv name -> marker name (e.g. :data:`HALPE26_NAMES`); names it lacks are kept.
    file_name : str
        Written in the first line, as TRC writers do.
    """
    frames = np.asarray(frames, dtype=np.int64)
    gridded = np.asarray(gridded, dtype=np.float64)
    if gridded.shape != (len(frames), len(names), 3) or len(frames) == 0:
        raise ValueError(f"gridded must have shape ({len(frames)} >= 1, {len(names)}, 3), got {gridded.shape}")
    step = int(frames[1] - frames[0]) if len(frames) > 1 else 1
    rate = fps / step
    markers = [(marker_names or {}).get(name, name) for name in names]
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{file_name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{rate:g}\t{rate:g}\t{len(frames)}\t{len(names)}\tmm\t{rate:g}\t{frames[0]}\t{len(frames)}",
        "\t".join(["Frame#", "Time"] + [cell for marker in markers for cell in (marker, "", "")]),
        "\t".join(["", ""] + [f"{axis}{k}" for k in range(1, len(names) + 1) for axis in "XYZ"]),
        "",
    ]
    points = gridded @ WORLD_TO_TRC.T * 1000.0
    for frame, row in zip(frames, points.reshape(len(frames), -1), strict=True):
        cells = ["" if np.isnan(value) else f"{value:.{DECIMALS}f}" for value in row]
        lines.append("\t".join([str(int(frame)), f"{frame / fps:.6f}"] + cells))
    return "\n".join(lines) + "\n"
