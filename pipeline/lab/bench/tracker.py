"""Benchmark of the articulated tracker on exact body-surface samples of real motion.

    python -m pipeline.lab.bench.tracker [--clips taekwondo leaning ...] [--frames 90] [--fps 30]
        [--distance normals|points|algebraic] [--body default|paper] [--surface mesh|capsules]
        [--known-height] [--normal-noise DEG]

For each clip, the synthetic body (MakeHuman mesh skinned to the clip's skeleton, `pipeline.lab.synth`, or
with --surface capsules its tapered-capsule body, which the tracking body's shapes were not fitted to) is
posed at every frame, 1000 points with their normals are drawn on its surface and 20 % uniform outliers
are added over the working volume (as in Horaud et al. 2009, Sec. 4.1); the tracker runs on these
observations and its joints are compared with the clip's ground-truth joints. Reported per clip: MPJPE
over the 15 scored joints (mm), the worst frame's, knee and elbow flexion errors (degrees), frames per
second of CPU time (tracking frames, and everything including initialisations), and the count of each
status. --normal-noise tilts the sampled normals (the pipeline's silhouette normals are off by ~10-20°).
The subject's height is NOT given to the tracker unless --known-height.
"""

from __future__ import annotations

import argparse
import time
from types import SimpleNamespace

import numpy as np

from calib.errors import InputError
from pipeline.io.body_io import tracking_body
from pipeline.lab.mocap import load_clip
from pipeline.lab.poselib import clip_path
from pipeline.lab.synth import build_body, pose_body, sample_body_surface
from stages.joints import JOINT_NAMES
from stages.tracking.params import TrackerParams
from stages.tracking.tracker import Tracker

CLIPS = {
    "taekwondo": ("clips/135_07.amc", "clips/martialwalk.asf"),
    "leaning": ("clips/131_05.amc", "clips/mjackson.asf"),
    "front_kick": ("clips/135_04.amc", "clips/martialwalk.asf"),
    "walk": ("clips/md_walk.amc", "clips/moderndance.asf"),
    "run": ("clips/09_01.bvh", None),
}
SCORED = 15
_J = {name: k for k, name in enumerate(JOINT_NAMES)}
FLEXION = {"l_knee": ("l_hip", "l_knee", "l_ankle"), "r_knee": ("r_hip", "r_knee", "r_ankle"),
           "l_elbow": ("l_shoulder", "l_elbow", "l_wrist"), "r_elbow": ("r_shoulder", "r_elbow", "r_wrist")}


def flexion_degrees(joints: np.ndarray) -> np.ndarray:
    """Flexion (F, 4) of knees and elbows: angle between the proximal and distal segment, degrees."""
    out = []
    for a, b, c in FLEXION.values():
        u = joints[:, _J[b]] - joints[:, _J[a]]
        v = joints[:, _J[c]] - joints[:, _J[b]]
        cos = np.sum(u * v, axis=1) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1))
        out.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return np.stack(out, axis=1)


def perturb_normals(normals: np.ndarray, degrees: float, rng: np.random.Generator) -> np.ndarray:
    """Unit normals (N, 3) each tilted by an angle |N(0, degrees)| about a random perpendicular axis."""
    if degrees <= 0:
        return normals
    axis = np.cross(normals, rng.normal(size=normals.shape))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.radians(np.abs(rng.normal(0.0, degrees, len(normals))))[:, None]
    tilted = normals * np.cos(angle) + np.cross(axis, normals) * np.sin(angle)
    return tilted / np.linalg.norm(tilted, axis=1, keepdims=True)


def synthetic_observations(motion, count: int, outlier_fraction: float, volume: np.ndarray, seed: int,
                           surface: str = "mesh", normal_noise_deg: float = 0.0):
    """Per frame: exact surface samples of the synthetic body (normals tilted by `normal_noise_deg`, the
    standard deviation of the tilt) plus uniform outliers in the volume."""
    rng = np.random.default_rng(seed)
    body = build_body(motion, kind=surface)
    frames = []
    n_out = int(round(count * outlier_fraction / (1.0 - outlier_fraction)))
    for f in range(motion.n_frames):
        points, normals = sample_body_surface(pose_body(body, motion, f), count, rng)
        normals = perturb_normals(normals, normal_noise_deg, rng)
        out = rng.uniform(volume[0], volume[1], (n_out, 3))
        out_n = rng.normal(size=(n_out, 3))
        out_n /= np.linalg.norm(out_n, axis=1, keepdims=True)
        frames.append(SimpleNamespace(points=np.vstack([points, out]), normals=np.vstack([normals, out_n])))
    return frames


def run_clip(name: str, args) -> dict:
    clip, skeleton = CLIPS[name]
    motion = load_clip(clip_path(clip), skeleton=None if skeleton is None else clip_path(skeleton))
    motion = motion.resample(args.fps)
    if args.start > 0 or args.frames:
        stop = motion.duration + 1 if not args.frames else args.start + args.frames / args.fps
        motion = motion.slice_seconds(args.start, stop)
    lo = motion.joints.reshape(-1, 3).min(axis=0) - 1.0
    hi = motion.joints.reshape(-1, 3).max(axis=0) + 1.0
    volume = np.array([[lo[0], lo[1], 0.0], [hi[0], hi[1], max(hi[2], 2.3)]])
    observations = synthetic_observations(motion, args.observations, args.outliers, volume, args.seed, args.surface,
                                         args.normal_noise)
    truth_height = None
    params = TrackerParams(distance=args.distance, height_m=truth_height, body=args.body)
    body = tracking_body(params)
    if args.known_height:
        from stages.tracking.library import retarget

        truth_height = retarget(body, motion.joints[0], estimate_scale=True)[1]
        params = TrackerParams(distance=args.distance, height_m=truth_height, body=args.body)
    tracker = Tracker(params, volume, body)
    state, estimates, statuses, seconds = None, [], [], []
    for obs in observations:
        start = time.process_time()  # CPU time: the machine is shared, wall time is noisy
        result, state = tracker.track(state, obs)
        seconds.append(time.process_time() - start)
        estimates.append(result.joints)
        statuses.append(result.status)
    estimates = np.array(estimates)
    statuses = np.array(statuses)
    seconds = np.array(seconds)
    error = np.linalg.norm(estimates[:, :SCORED] - motion.joints[:, :SCORED], axis=2) * 1000.0
    exported = np.isin(statuses, ["tracked", "initialised"])
    flex = np.abs(flexion_degrees(estimates) - flexion_degrees(motion.joints))
    tracked = statuses == "tracked"
    return {
        "clip": name, "frames": len(statuses), "exported": int(exported.sum()),
        "mpjpe_mm": float(error[exported].mean()), "worst_frame_mm": float(error[exported].mean(axis=1).max()),
        "per_joint_mm": dict(zip(JOINT_NAMES[:SCORED], error[exported].mean(axis=0).round(1).tolist(), strict=True)),
        "knee_flexion_deg": float(flex[exported][:, :2].mean()),
        "elbow_flexion_deg": float(flex[exported][:, 2:].mean()),
        "fps_tracking": float(tracked.sum() / seconds[tracked].sum()) if tracked.any() else 0.0,
        "fps_all": float(len(seconds) / seconds.sum()),
        "statuses": {s: int((statuses == s).sum()) for s in np.unique(statuses)},
        "final_height_m": float(result.height_m),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clips", nargs="+", default=list(CLIPS), choices=list(CLIPS))
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--start", type=float, default=0.0, help="seconds into the clip")
    parser.add_argument("--frames", type=int, default=0, help="frames per clip (0 = all)")
    parser.add_argument("--observations", type=int, default=1000)
    parser.add_argument("--outliers", type=float, default=0.2)
    parser.add_argument("--distance", default="normals", choices=["normals", "points", "algebraic"])
    parser.add_argument("--body", default="default")
    parser.add_argument("--surface", default="mesh", choices=["mesh", "capsules"])
    parser.add_argument("--known-height", action="store_true")
    parser.add_argument("--normal-noise", type=float, default=0.0,
                        help="standard deviation of the tilt of the sampled normals, degrees")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--per-joint", action="store_true")
    args = parser.parse_args(argv)
    print(f"{'clip':<11} {'frames':>6} {'MPJPE':>7} {'worst':>7} {'knee°':>6} {'elbow°':>6} "
          f"{'cpu fps trk':>8} {'all':>8} {'height':>7}  statuses")
    for name in args.clips:
        try:
            r = run_clip(name, args)
        except InputError as err:  # e.g. the synthetic mesh body needs a CMU skeleton
            print(f"{name:<11} skipped: {err}", flush=True)
            continue
        print(f"{r['clip']:<11} {r['frames']:>6} {r['mpjpe_mm']:>7.1f} {r['worst_frame_mm']:>7.1f} "
              f"{r['knee_flexion_deg']:>6.1f} {r['elbow_flexion_deg']:>6.1f} {r['fps_tracking']:>8.1f} "
              f"{r['fps_all']:>8.1f} {r['final_height_m']:>7.3f}  {r['statuses']}", flush=True)
        if args.per_joint:
            print("   ", r["per_joint_mm"])


if __name__ == "__main__":
    main()
