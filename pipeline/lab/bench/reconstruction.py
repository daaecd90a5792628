"""Benchmark of the silhouette and reconstruction stages against the true body surface.

    python -m pipeline.lab.bench.reconstruction [--clips taekwondo leaning] [--frames 12] [--cameras 6]
        [--observations 1000] [--captures data_samples/taekwondo ...]

Reconstruction: for each clip, the synthetic body (MakeHuman mesh skinned to the clip, ``pipeline.lab.synth``)
is posed at ``--frames`` frames spread over the clip and its exact silhouettes are ray-cast into a ring of
``--cameras`` cameras at 780 x 580. Each method (visual shape with both rim placements, visual hull) then
reconstructs the frame, and its points are compared with the posed mesh: distance to the surface
(open3d ``RaycastingScene.compute_distance``; median and 95th percentile, mm), the angle between each
normal and the normal of the closest surface triangle (median, degrees), the fraction of outliers
(> 3 cm from the surface), the number of points and the CPU time per frame of the calling thread
(``time.thread_time``: the machine is shared, so wall time is not the stage's, and the renderer's worker
threads keep spinning after a frame is rendered, which process time would charge to the reconstruction).

Silhouettes (``--captures``): for each synthetic capture with ``groundtruth/masks``, every camera-frame
is segmented from its video or images (clean plate when present, else the temporal median) and compared
with the true mask: IoU per camera-frame (median, 5th percentile) and time per frame for all cameras.
The visual shape is then reconstructed at those frames from the segmented and from the true masks and
compared with the capture's body, posed again from ``groundtruth/synth.yaml`` (same columns as above).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import yaml

from calib.camera import Camera, Rig
from pipeline.io.backgrounds import background_image, spread_frames
from pipeline.io.capture import Capture
from pipeline.lab.bench.tracker import CLIPS
from pipeline.lab.mocap import load_clip
from pipeline.lab.poselib import clip_path
from pipeline.lab.synth import build_body, pose_body, posed_mesh
from pipeline.lab.synth.render import body_scene, pixel_grid_rays, render_body
from pipeline.lab.synth.writer import SynthParams, prepare_motion
from stages.export.metrics import mask_iou
from stages.reconstruction import Observations, ReconstructionParams, reconstruct
from stages.silhouettes import SilhouetteParams, background_model, extract_silhouettes, floor_geometry

OUTLIER_DISTANCE_M = 0.03
IMAGE_SIZE = (780, 580)
FOCAL_PX = 700.0
VOLUME = np.array([[-2.5, -2.5, 0.0], [2.5, 2.5, 2.3]])
VARIANTS = {
    "visual_shape/osculating": ReconstructionParams(method="visual_shape", rim_placement="osculating"),
    "visual_shape/midpoint": ReconstructionParams(method="visual_shape", rim_placement="midpoint"),
    "visual_hull": ReconstructionParams(method="visual_hull"),
}


def ring_rig(n_cameras: int, centre: np.ndarray) -> Rig:
    """``n_cameras`` cameras on a 4.5 m ring at 1.2 to 2.2 m height, aimed at ``centre`` (3,)."""
    cameras = []
    for i in range(n_cameras):
        angle = 2 * np.pi * i / n_cameras + 0.2
        eye = centre[:2].tolist() + [0.0]
        eye = [eye[0] + 4.5 * np.cos(angle), eye[1] + 4.5 * np.sin(angle), 1.2 + (i % 3) * 0.5]
        cameras.append(Camera.look_at(f"cam_{i}", eye, [centre[0], centre[1], 1.0], f_px=FOCAL_PX, size=IMAGE_SIZE))
    return Rig(tuple(cameras))


def surface_errors(observations: Observations, vertices: np.ndarray, triangles: np.ndarray,
                   vertex_normals: np.ndarray):
    """(distance (N,) metres, normal angle (N,) degrees) of observations to the mesh's closest points.

    The true normal is the smooth (vertex-interpolated) normal at the closest point, the one the
    renderer shades with: facet normals of the mesh jump by several degrees from triangle to triangle.
    """
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
    query = o3d.core.Tensor(observations.points.astype(np.float32))
    distance = scene.compute_distance(query).numpy().astype(np.float64)
    closest = scene.compute_closest_points(query)
    corners = triangles[closest["primitive_ids"].numpy()]  # (N, 3)
    uv = closest["primitive_uvs"].numpy().astype(np.float64)  # weights of corners 1 and 2
    weights = np.column_stack([1.0 - uv.sum(axis=1), uv])
    normals = np.einsum("nk,nkd->nd", weights, vertex_normals[corners])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-15)
    cosines = np.clip(np.einsum("ij,ij->i", normals, observations.normals), -1.0, 1.0)
    return distance, np.degrees(np.arccos(cosines))


def bench_reconstruction(clips: list[str], n_frames: int, n_cameras: int, n_observations: int) -> None:
    print(f"reconstruction: {n_cameras} cameras {IMAGE_SIZE[0]}x{IMAGE_SIZE[1]}, {n_observations} observations")
    print(f"{'clip':12s} {'method':24s} {'N':>6s} {'med mm':>7s} {'p95 mm':>7s} {'normal°':>8s} "
          f"{'out>3cm':>8s} {'ms/frame':>9s}")
    for clip in clips:
        amc, asf = CLIPS[clip]
        motion = load_clip(clip_path(amc), skeleton=None if asf is None else clip_path(asf))
        body = build_body(motion)
        frames = np.linspace(0, motion.n_frames - 1, n_frames).round().astype(int)
        results = {name: {"d": [], "a": [], "n": [], "t": []} for name in VARIANTS}
        for frame in frames:
            posed = pose_body(body, motion, int(frame))
            vertices, triangles = posed_mesh(posed)
            rig = ring_rig(n_cameras, vertices.mean(axis=0))
            scene = body_scene(posed)
            colours = np.ones((64, 3))
            masks = [
                np.where(render_body(camera, pixel_grid_rays(camera), scene, posed, colours).mask, 255, 0).astype(
                    np.uint8
                )
                for camera in rig
            ]
            for name, params in VARIANTS.items():
                params = ReconstructionParams(**{**params.__dict__, "n_observations": n_observations})
                start = time.thread_time()
                observations = reconstruct(masks, rig, VOLUME, params)
                _score(results[name], observations, time.thread_time() - start, posed, vertices, triangles)
        _print_rows(clip, results)


def bench_silhouettes(captures: list[Path], max_frames: int) -> None:
    print("silhouettes: IoU per camera-frame against groundtruth/masks")
    print(f"{'capture':12s} {'frames':>6s} {'IoU med':>8s} {'IoU p5':>7s} {'ms/frame (all cams)':>20s}")
    params = SilhouetteParams()
    for path in captures:
        capture = Capture.open(path)
        frames = spread_frames(capture.frame_numbers, max_frames)
        segmented, seconds = _segment(capture, frames, params)
        ious = [mask_iou(mask, _true_mask(Path(path), camera, frame))
                for frame in frames for camera, mask in zip(capture.rig.names, segmented[frame], strict=True)]
        print(f"{Path(path).name:12s} {len(frames):6d} {np.median(ious):8.3f} {np.percentile(ious, 5):7.3f} "
              f"{np.median(seconds) * 1e3:20.1f}")


def _segment(capture: Capture, frames: list[int], params: SilhouetteParams) -> tuple[dict[int, list], np.ndarray]:
    """Every camera's mask of each of ``frames`` as the silhouette stage makes them, and (F,) seconds per frame."""
    backgrounds = [background_model(background_image(capture, camera), params) for camera in capture.rig.names]
    floor = floor_geometry(list(capture.rig), capture.volume, params)
    images = [dict(capture.iter_images(camera, frames)) for camera in capture.rig.names]
    segmented, seconds = {}, np.zeros(len(frames))
    for k, frame in enumerate(frames):
        start = time.perf_counter()
        segmented[frame] = extract_silhouettes([views[frame] for views in images], backgrounds, floor, params)
        seconds[k] = time.perf_counter() - start
    return segmented, seconds


def _true_mask(capture_dir: Path, camera: str, frame: int) -> np.ndarray:
    return cv2.imread(str(capture_dir / "groundtruth" / "masks" / camera / f"{frame:06d}.png"), cv2.IMREAD_GRAYSCALE)


def _score(record: dict, observations: Observations, seconds: float, posed, vertices, triangles) -> None:
    """Append one frame's surface errors, count and CPU time to ``record`` (lists "d", "a", "n", "t")."""
    distance, angle = surface_errors(observations, vertices, triangles, posed.vertex_normals)
    record["d"].append(distance)
    record["a"].append(angle)
    record["n"].append(len(observations))
    record["t"].append(seconds)


def _print_rows(label: str, results: dict[str, dict]) -> None:
    """One table row per method/mask kind: count, median and p95 distance, normal error, outliers, CPU time."""
    for name, r in results.items():
        d, a = np.concatenate(r["d"]), np.concatenate(r["a"])
        print(f"{label:12s} {name:24s} {np.mean(r['n']):6.0f} {np.median(d) * 1e3:7.1f} "
              f"{np.percentile(d, 95) * 1e3:7.1f} {np.median(a):8.1f} {np.mean(d > OUTLIER_DISTANCE_M):8.3f} "
              f"{np.median(r['t']) * 1e3:9.1f}")


def bench_capture_reconstruction(captures: list[Path], max_frames: int, n_observations: int) -> None:
    """Visual shape from each capture's segmented and true masks against its re-posed synthetic body."""
    print("visual shape on captures: segmented vs true masks, against the rendered body")
    print(f"{'capture':12s} {'masks':24s} {'N':>6s} {'med mm':>7s} {'p95 mm':>7s} {'normal°':>8s} "
          f"{'out>3cm':>8s} {'ms/frame':>9s}")
    params = ReconstructionParams(n_observations=n_observations)
    silhouette_params = SilhouetteParams()
    for path in captures:
        capture = Capture.open(path)
        provenance = yaml.safe_load((Path(path) / "groundtruth" / "synth.yaml").read_text())
        provenance.pop("frames", None)
        synth = SynthParams(**{**provenance, "size": tuple(provenance["size"])})
        motion = prepare_motion(synth)
        body = build_body(motion, synth.body)
        frames = spread_frames(capture.frame_numbers, max_frames)
        segmented, _ = _segment(capture, frames, silhouette_params)
        results = {kind: {"d": [], "a": [], "n": [], "t": []} for kind in ("segmented", "true")}
        for frame in frames:
            posed = pose_body(body, motion, frame)
            vertices, triangles = posed_mesh(posed)
            truth = [_true_mask(Path(path), camera, frame) for camera in capture.rig.names]
            for kind, masks in (("segmented", segmented[frame]), ("true", truth)):
                start = time.thread_time()
                observations = reconstruct(masks, capture.rig, capture.volume, params)
                _score(results[kind], observations, time.thread_time() - start, posed, vertices, triangles)
        _print_rows(Path(path).name, results)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clips", nargs="*", default=["taekwondo", "leaning"], choices=sorted(CLIPS))
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--cameras", type=int, default=6)
    parser.add_argument("--observations", type=int, default=1000)
    parser.add_argument("--captures", nargs="*", default=[], type=Path)
    args = parser.parse_args()
    if args.captures:
        bench_silhouettes(args.captures, args.frames)
        bench_capture_reconstruction(args.captures, args.frames, args.observations)
    if args.clips:
        bench_reconstruction(args.clips, args.frames, args.cameras, args.observations)


if __name__ == "__main__":
    main()
