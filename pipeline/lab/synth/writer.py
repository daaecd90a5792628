"""Writing a synthetic capture: a clip performed by the rendered body, seen by a ring of cameras.

Layout (CAPTURE_FORMAT.md) under ``out``::

    capture.yaml
    calibration/...                    colmap/ | opencv/ | calibration.toml, in --units / --up
    videos/<camera>.mp4                or images/<camera>/<frame:06d>.png
    background/<camera>.png            clean plate (the empty room, mean of 16 noisy empty frames)
    groundtruth/joints.csv             frame,joint,x,y,z in metres, world frame, the 17 JOINT_NAMES
    groundtruth/masks/<camera>/<frame:06d>.png   true masks (pixel centre ray hits the body)
    groundtruth/synth.yaml             how the capture was made (clip, span, seed, body, options)

The pipeline does not read ``groundtruth/`` as input. Random choices (rig, room, clothes, distractors,
noise) come from separate streams of one seed, so changing the noise does not move the cameras.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from calib.errors import InputError
from calib.formats import save_rig
from calib.world import from_world
from pipeline.lab.mocap import Motion, load_clip
from pipeline.lab.synth.body import Body, build_body, pose_body
from pipeline.lab.synth.distractors import paint_distractors, random_distractors
from pipeline.lab.synth.render import (
    Room,
    body_scene,
    clothing_colours,
    finish_image,
    meter_exposure,
    pixel_grid_rays,
    render_body,
    render_room,
)
from pipeline.lab.synth.rig import RingParams, check_rig_sees, ring_centre_and_radius, ring_rig
from stages.joints import JOINT_NAMES

log = logging.getLogger(__name__)

CALIBRATION_PATHS = {
    "colmap": "calibration/colmap",
    "opencv": "calibration/opencv",
    "anipose": "calibration/calibration.toml",
}
# Room: cameras stand this far inside the walls; ceiling height.
WALL_CLEARANCE_M = 0.8
CEILING_M = 3.2
# Posed vertices kept (every n-th) when framing the cameras: enough to bound the body.
FRAMING_VERTEX_STEP = 7
VIDEO_FOURCC = "mp4v"
#: The clean plate is written as the mean of this many empty frames (noise sigma / sqrt of it).
CLEAN_PLATE_FRAMES = 16


@dataclass(frozen=True)
class SynthParams:
    """Everything that decides a synthetic capture (written to groundtruth/synth.yaml).

    Parameters
    ----------
    clip, skeleton : str
        The motion (``.amc`` with its ``.asf``, or ``.bvh`` with skeleton None).
    start_s : float
        Start of the rendered span in the clip, seconds.
    seconds : float or None
        Length of the span; None for the rest of the clip.
    hold_s : float
        The span's first pose is held still for this long before the motion starts (a subject who stands
        still, then moves: a temporal median of the frames keeps a ghost of him).
    fps : float
        Frame rate of the capture (the clip is resampled).
    body : str
        "mesh" or "capsules".
    n_cameras : int
    size : (int, int)
        Image (width, height).
    calib_format : str
        colmap | opencv | anipose.
    units, up : str
        Convention of the written calibration (``calib.world.from_world``).
    noise_sigma : float
        Sensor noise, grey levels (0-255).
    distractors : int
        Number of distractor blobs.
    media : str
        "video" (mp4, lossy) or "images" (PNG, exact).
    height_known : bool
        Whether capture.yaml states subject.height_m.
    seed : int
    """

    clip: str
    skeleton: str | None = None
    start_s: float = 0.0
    seconds: float | None = None
    hold_s: float = 0.0
    fps: float = 28.0
    body: str = "mesh"
    n_cameras: int = 6
    size: tuple[int, int] = (780, 580)
    calib_format: str = "colmap"
    units: str = "m"
    up: str = "+z"
    noise_sigma: float = 2.0
    distractors: int = 0
    media: str = "video"
    height_known: bool = True
    seed: int = 0


def prepare_motion(params: SynthParams) -> Motion:
    """The clip resampled to the capture's frame rate and cut to the requested span."""
    motion = load_clip(params.clip, skeleton=params.skeleton).resample(params.fps)
    end = motion.duration + 1.0 / params.fps if params.seconds is None else params.start_s + params.seconds
    motion = motion.slice_seconds(params.start_s, end)
    return motion.held(params.hold_s) if params.hold_s else motion


def standing_height(body: Body, motion: Motion) -> float:
    """The rendered body's standing height (m): rest-pose extent with the legs counted straight.

    The CMU rest pose spreads the legs by about 20 degrees, so the vertical extent at rest is corrected
    by the difference between the leg length (hip-knee-ankle) and the hip's height above the ankle.
    """
    rest = motion.rest_pose()
    vertices = pose_body(body, rest, 0).vertices
    hip, knee, ankle = (rest.joints[0, JOINT_NAMES.index(name)] for name in ("l_hip", "l_knee", "l_ankle"))
    leg = np.linalg.norm(knee - hip) + np.linalg.norm(ankle - knee)
    return float(np.ptp(vertices[:, 2]) + leg - (hip[2] - ankle[2]))


def synthesise(params: SynthParams, out: Path) -> None:
    """Render the capture described by ``params`` into the directory ``out`` (created, must be empty)."""
    _check_params(params)
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise InputError(f"--out {out}: directory is not empty; expected a new or empty directory")
    motion = prepare_motion(params)
    body = build_body(motion, params.body)
    seeds = np.random.SeedSequence(params.seed).spawn(5)
    rig_rng, room_rng, clothes_rng, distractor_rng, noise_rng = (np.random.default_rng(s) for s in seeds)

    framing_points = np.concatenate(
        [pose_body(body, motion, k).vertices[::FRAMING_VERTEX_STEP] for k in range(motion.n_frames)]
    )
    ring = RingParams(n_cameras=params.n_cameras, size=params.size)
    rig = ring_rig(framing_points, ring, rig_rng)
    check_rig_sees(rig, motion.joints)
    centre, radius = ring_centre_and_radius(framing_points, ring)
    room = Room(
        centre=(float(centre[0]), float(centre[1])),
        half_size=(radius + WALL_CLEARANCE_M, radius + WALL_CLEARANCE_M + float(room_rng.uniform(0, 1.0))),
        height=CEILING_M,
        seed=int(room_rng.integers(2**31)),
    )
    colours = clothing_colours(clothes_rng)
    distractors = random_distractors(params.distractors, len(rig), motion.n_frames, params.size, distractor_rng)

    out.mkdir(parents=True, exist_ok=True)
    rays = {camera.name: pixel_grid_rays(camera) for camera in rig}
    plates = {camera.name: render_room(camera, rays[camera.name], room) for camera in rig}
    exposures = {camera.name: meter_exposure(camera, plates[camera.name]) for camera in rig}
    (out / "background").mkdir()
    for camera in rig:
        # a studio's clean plate is the mean of many empty frames: less noise than one frame
        noise = params.noise_sigma / CLEAN_PLATE_FRAMES**0.5
        background = finish_image(plates[camera.name], exposures[camera.name], noise, noise_rng)
        cv2.imwrite(str(out / "background" / f"{camera.name}.png"), background)

    sinks = {camera.name: _FrameSink(out, camera.name, params) for camera in rig}
    for frame in range(motion.n_frames):
        posed = pose_body(body, motion, frame)
        scene = body_scene(posed)
        for index, camera in enumerate(rig):
            layer = render_body(camera, rays[camera.name], scene, posed, colours)
            image = np.where(layer.mask[:, :, None], layer.colour, plates[camera.name])
            paint_distractors(image, distractors, index, frame)
            recorded = finish_image(image, exposures[camera.name], params.noise_sigma, noise_rng)
            sinks[camera.name].write(frame, recorded, layer.mask)
        if frame % 20 == 0:
            log.info("rendered frame %d / %d", frame + 1, motion.n_frames)
    for sink in sinks.values():
        sink.close(motion.n_frames)

    _write_calibration(rig, params, out)
    _write_joints(motion, out / "groundtruth" / "joints.csv")
    _write_capture_yaml(params, framing_points, standing_height(body, motion), out)
    provenance = asdict(params) | {"size": list(params.size), "frames": motion.n_frames}
    (out / "groundtruth" / "synth.yaml").write_text(yaml.safe_dump(provenance, sort_keys=False))


def _check_params(params: SynthParams) -> None:
    if params.calib_format not in CALIBRATION_PATHS:
        raise InputError(f"--calib-format {params.calib_format}: expected one of {', '.join(CALIBRATION_PATHS)}")
    if params.media not in ("video", "images"):
        raise InputError(f"media {params.media!r}: expected 'video' or 'images'")
    if params.n_cameras < 2:
        raise InputError(f"--cameras {params.n_cameras}: expected at least 2 cameras")
    if min(params.size) < 16:
        raise InputError(f"--size {params.size[0]}x{params.size[1]}: expected at least 16x16 pixels")
    if not params.fps > 0:
        raise InputError(f"--fps {params.fps}: expected a positive frame rate")
    if params.noise_sigma < 0:
        raise InputError(f"--noise {params.noise_sigma}: expected a non-negative sigma (grey levels)")
    if params.distractors < 0:
        raise InputError(f"--distractors {params.distractors}: expected a non-negative count")
    if not params.hold_s >= 0:
        raise InputError(f"--hold {params.hold_s}: expected a duration >= 0 seconds")
    if params.seconds is not None and not params.seconds > 0:
        raise InputError(f"--seconds {params.seconds}: expected a positive duration")


class _FrameSink:
    """Where one camera's frames and true masks go: an mp4 video or a PNG folder."""

    def __init__(self, out: Path, camera: str, params: SynthParams):
        self.out, self.camera, self.params = out, camera, params
        self.mask_dir = out / "groundtruth" / "masks" / camera
        self.mask_dir.mkdir(parents=True)
        self.writer = None
        if params.media == "video":
            (out / "videos").mkdir(exist_ok=True)
            self.video_path = out / "videos" / f"{camera}.mp4"
            self.writer = cv2.VideoWriter(
                str(self.video_path), cv2.VideoWriter_fourcc(*VIDEO_FOURCC), params.fps, params.size
            )
            if not self.writer.isOpened():
                raise RuntimeError(f"OpenCV cannot write {VIDEO_FOURCC} video to {self.video_path}")
        else:
            self.image_dir = out / "images" / camera
            self.image_dir.mkdir(parents=True)

    def write(self, frame: int, image: np.ndarray, mask: np.ndarray) -> None:
        if self.writer is not None:
            self.writer.write(image)
        else:
            cv2.imwrite(str(self.image_dir / f"{frame:06d}.png"), image)
        cv2.imwrite(str(self.mask_dir / f"{frame:06d}.png"), mask.astype(np.uint8) * 255)

    def close(self, n_frames: int) -> None:
        """Finish the video and check that it decodes back to ``n_frames`` frames of the right size."""
        if self.writer is None:
            return
        self.writer.release()
        decoded = count_video_frames(self.video_path, self.params.size)
        if decoded != n_frames:
            raise RuntimeError(f"{self.video_path}: wrote {n_frames} frames but {decoded} decode back")


def count_video_frames(path: Path, size: tuple[int, int]) -> int:
    """Number of frames of ``size`` that OpenCV decodes from the video at ``path``."""
    capture = cv2.VideoCapture(str(path))
    count = 0
    try:
        while True:
            ok, image = capture.read()
            if not ok:
                break
            if (image.shape[1], image.shape[0]) != tuple(size):
                raise RuntimeError(f"{path}: decoded a {image.shape[1]}x{image.shape[0]} frame, expected {size}")
            count += 1
    finally:
        capture.release()
    return count


def _write_calibration(rig, params: SynthParams, out: Path) -> None:
    path = out / CALIBRATION_PATHS[params.calib_format]
    path.parent.mkdir(parents=True, exist_ok=True)
    save_rig(from_world(rig, units=params.units, up=params.up), params.calib_format, path)


def _write_joints(motion: Motion, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["frame,joint,x,y,z"]
    for frame in range(motion.n_frames):
        for name, (x, y, z) in zip(JOINT_NAMES, motion.joints[frame], strict=True):
            lines.append(f"{frame},{name},{x:.6f},{y:.6f},{z:.6f}")
    path.write_text("\n".join(lines) + "\n")


def _write_capture_yaml(params: SynthParams, body_points: np.ndarray, height_m: float, out: Path) -> None:
    """capture.yaml; the volume is the space the body used, 0.5 m wider, rounded out to 10 cm."""
    low = np.floor((body_points.min(axis=0) - 0.5) * 10) / 10
    high = np.ceil((body_points.max(axis=0) + 0.5) * 10) / 10
    config = {
        "fps": float(params.fps),
        "calibration": {
            "format": params.calib_format,
            "path": CALIBRATION_PATHS[params.calib_format],
            "units": params.units,
            "up": params.up,
        },
    }
    if params.height_known:
        config["subject"] = {"height_m": round(height_m, 3)}
    config["volume"] = {
        "min": [round(float(low[0]), 1), round(float(low[1]), 1), 0.0],
        "max": [round(float(high[0]), 1), round(float(high[1]), 1), round(max(2.3, float(high[2])), 1)],
    }
    config["frames"] = {"start": 0, "stop": None, "step": 1}
    (out / "capture.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
