"""Fit the tracking body's ellipsoid shapes to a body surface, and print them as body-YAML entries.

    python -m pipeline.lab.bench.body_shape [--body default] [--frames 24]

Why: the ellipsoids' centres and semi-axes in `stages/tracking/bodies/*.yaml` started from rounded
anthropometric girths; the joint centres follow mocap skeletons. This tool measures how ellipsoids
sit on a human surface: the MakeHuman mesh of `pipeline.lab.synth` posed by clips that are NOT evaluation
samples (md_walk and 135_04; never 135_07 or 131_05). Per frame the body is put in the clip's pose by
IK on the ground-truth joints, surface points are drawn, each point is assigned to the ellipsoid with
the smallest datum distance (eq. 4), and every ellipsoid's centre and semi-axes (in its segment frame,
axes kept) are refitted by least squares on the residuals y − x(n); three rounds. The output replaces
the `ellipsoids:` list of a body file (as fractions of height); it is a measurement to review, not
applied automatically.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.optimize import least_squares

from pipeline.lab.bench.tracker import CLIPS
from pipeline.lab.mocap import load_clip
from pipeline.lab.poselib import clip_path
from pipeline.lab.synth import build_body, pose_body, sample_body_surface
from stages.tracking.body_file import load_body
from stages.tracking.distances import DISTANCES
from stages.tracking.geometry import ellipsoid_point
from stages.tracking.library import retarget

CALIBRATION_CLIPS = ("walk", "front_kick")
ROUNDS = 3
MAX_DISTANCE_M = 0.08  # points farther than this from every ellipsoid (hands' fingers, hair) are ignored


def collect(body_name: str, frames_per_clip: int, points: int, seed: int):
    """Per frame: body at the IK pose and height, and surface points/normals in each segment's frame."""
    rng = np.random.default_rng(seed)
    base = load_body(body_name)
    samples = []
    for name in CALIBRATION_CLIPS:
        clip, skeleton = CLIPS[name]
        motion = load_clip(clip_path(clip), skeleton=None if skeleton is None else clip_path(skeleton))
        synth = build_body(motion)
        for f in np.linspace(0, motion.n_frames - 1, frames_per_clip).astype(int):
            pose, height = retarget(base, motion.joints[f], estimate_scale=True)
            y, n = sample_body_surface(pose_body(synth, motion, f), points, rng)
            samples.append((pose, height, y, n))
    return base, samples


def fit_shapes(base, samples):
    """Centres (E, 3) and semi-axes (E, 3), fractions of height, in each ellipsoid's segment frame."""
    centre = base.ellipsoid_centre / base.height_m
    semi = base.semi_axes / base.height_m
    for _ in range(ROUNDS):
        local_y = [[] for _ in range(base.n_ellipsoids)]
        local_n = [[] for _ in range(base.n_ellipsoids)]
        for pose, height, y, n in samples:
            body = base.scaled(height)
            body = type(body)(**{**body.__dict__, "ellipsoid_centre": centre * height, "semi_axes": semi * height})
            kin = body.fk(pose)
            e = np.linalg.norm(DISTANCES["normals"].all_residuals(y, n, body.ellipsoids(kin)), axis=2)  # (I,P)
            best = e.argmin(axis=1)
            near = e[np.arange(len(y)), best] < MAX_DISTANCE_M
            for p in range(body.n_ellipsoids):
                pick = near & (best == p)
                R_s = kin.R[body.ellipsoid_segment[p]]
                t_s = kin.t[body.ellipsoid_segment[p]]
                local_y[p].append((y[pick] - t_s) @ R_s / height)  # R_sᵀ (y − t_s), fractions of height
                local_n[p].append(n[pick] @ R_s)
        for p in range(base.n_ellipsoids):
            yl, nl = np.concatenate(local_y[p]), np.concatenate(local_n[p])
            if len(yl) < 20:
                continue
            R = np.repeat(base.ellipsoid_rotation[p][None], len(yl), axis=0)

            def residual(params, yl=yl, nl=nl, R=R):
                c, a = params[:3], np.abs(params[3:])
                return (yl - ellipsoid_point(nl, R, np.broadcast_to(c, yl.shape), np.broadcast_to(a, yl.shape))).ravel()

            solution = least_squares(residual, np.concatenate([centre[p], semi[p]]), loss="soft_l1", f_scale=0.01)
            centre[p], semi[p] = solution.x[:3], np.abs(solution.x[3:])
    return centre, semi


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--body", default="default")
    parser.add_argument("--frames", type=int, default=12, help="frames per calibration clip")
    parser.add_argument("--points", type=int, default=3000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    base, samples = collect(args.body, args.frames, args.points, args.seed)
    centre, semi = fit_shapes(base, samples)
    joint = base.standing_root / base.height_m  # segment joint centres, zero pose, fractions of height
    joints = [joint]
    for s in range(1, len(base.segment_names)):
        joints.append(joints[base.parent[s]] + base.offset[s] / base.height_m)
    print("ellipsoids:")
    for p in range(base.n_ellipsoids):
        s = base.ellipsoid_segment[p]
        middle = joints[s] + centre[p]
        axis = base.ellipsoid_rotation[p][:, 0]
        start, end = middle - semi[p, 0] * axis, middle + semi[p, 0] * axis
        fmt = ", ".join
        print(f"  - {{segment: {base.segment_names[s]}, from: [{fmt(f'{v:.3f}' for v in start)}], "
              f"to: [{fmt(f'{v:.3f}' for v in end)}], radii: [{semi[p, 1]:.3f}, {semi[p, 2]:.3f}]}}")


if __name__ == "__main__":
    main()
