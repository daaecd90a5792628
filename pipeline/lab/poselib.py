"""Build the tracker's pose library (stages/tracking/data/poses.npz) from motion-capture clips.

    python -m pipeline.lab.poselib [--out stages/tracking/data/poses.npz] [--count 120]

Poses come from clips that are NOT evaluation samples (135_07 taekwondo and 131_05 leaning are kept
out): 135_04 (front kicks), md_walk (walking) and 09_01 (running). Each frame's 17 joints are made
body-independent: turned to face +y (hip line along +x), pelvis above the origin, floor at z = 0,
divided by the subject's standing height (estimated by fitting the default body with its size free).
Farthest-point sampling then keeps `count` poses that differ most from each other (mean joint
distance), so that rare poses (the top of a kick) are as present as common ones (standing).

The file holds these joints (`joints` (M, 17, 3), `source`) and, for every body configuration in
BODIES, the same poses retargeted to it by inverse kinematics as pose vectors, after the generic
standing, bending and squatting poses of `stages.tracking.library.generic_poses` (`poses_<body>` (G + M, D):
joint angles, root at x = y = 0, yaw 0, root height as a fraction of standing height). Joint angles do
not depend on the subject's size, so the tracker's initialisation uses them as they are.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pipeline.lab.mocap import load_clip
from stages.tracking.body_file import load_body
from stages.tracking.library import heading, library_poses, retarget

MOCAP = Path(__file__).resolve().parent / "data"
CLIPS = (
    ("clips/135_04.amc", "clips/martialwalk.asf"),
    ("clips/md_walk.amc", "clips/moderndance.asf"),
    ("clips/09_01.bvh", None),
)
SHARED_MOCAP = Path("/work/shared/mocap")
BODIES = ("default", "paper")
DEFAULT_OUT = Path(__file__).resolve().parents[2] / "stages" / "tracking" / "data" / "poses.npz"
SAMPLE_FPS = 20.0  # consecutive poses at 120 Hz are near-duplicates
HEIGHT_FRAMES = 12  # frames used to estimate a subject's height


def normalised_joints(joints: np.ndarray) -> np.ndarray:
    """Joints (F, 17, 3) turned to face +y with the pelvis above the origin (floor kept)."""
    out = np.empty_like(joints)
    for f, frame in enumerate(joints):
        yaw = heading(frame)
        c, s = np.cos(-yaw), np.sin(-yaw)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        centred = frame - [frame[0, 0], frame[0, 1], 0.0]  # joint 0 is the pelvis
        out[f] = centred @ R.T
    return out


def subject_height(joints: np.ndarray) -> float:
    """Standing height (metres) of the default body that best fits these frames' joints (median)."""
    body = load_body("default")
    picks = np.linspace(0, len(joints) - 1, HEIGHT_FRAMES).astype(int)
    return float(np.median([retarget(body, joints[f], estimate_scale=True)[1] for f in picks]))


def farthest_poses(joints: np.ndarray, count: int) -> np.ndarray:
    """Indices of `count` poses (F, 17, 3) chosen by farthest-point sampling on mean joint distance."""
    chosen = [0]
    distance = np.full(len(joints), np.inf)
    for _ in range(min(count, len(joints)) - 1):
        distance = np.minimum(distance, np.linalg.norm(joints - joints[chosen[-1]], axis=2).mean(axis=1))
        chosen.append(int(np.argmax(distance)))
    return np.array(chosen)


def clip_path(relative: str) -> Path:
    """A clip shipped in pipeline/lab/data, or else in the shared mocap folder."""
    local = MOCAP / relative
    return local if local.exists() else SHARED_MOCAP / relative


def build(count: int) -> dict[str, np.ndarray]:
    all_joints, sources = [], []
    for clip, skeleton in CLIPS:
        motion = load_clip(clip_path(clip), skeleton=None if skeleton is None else clip_path(skeleton))
        motion = motion.resample(SAMPLE_FPS)
        joints = motion.joints
        height = subject_height(joints)
        all_joints.append(normalised_joints(joints) / height)
        sources += [f"{Path(clip).stem}@{f / SAMPLE_FPS:.1f}s" for f in range(len(joints))]
        print(f"{clip}: {len(joints)} frames at {SAMPLE_FPS} fps, subject height {height:.3f} m")
    joints = np.concatenate(all_joints)
    keep = farthest_poses(joints, count)
    library = {"joints": joints[keep].astype(np.float64), "source": np.array(sources)[keep]}
    for name in BODIES:
        library[f"poses_{name}"] = library_poses(load_body(name), library["joints"])
        print(f"retargeted {len(keep)} poses to the {name!r} body")
    return library


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--count", type=int, default=120)
    args = parser.parse_args(argv)
    library = build(args.count)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out, **library)
    print(f"wrote {len(library['joints'])} poses to {args.out}")


if __name__ == "__main__":
    main()
