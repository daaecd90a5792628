"""The per-frame work of the silhouette and reconstruction stages, and the refinement of the calibration between
them, as it runs in a worker.

A worker of ``--workers N`` is a fork of a server process that imported this module once
(:data:`pipeline.worker_modules.WORKER_MODULES`), started before the run's own imports: the workers have this
module and the reconstruction in memory before the first frame, and none imports the tracker (numba), which
lives in :mod:`pipeline.graph`.

Within a worker, frames are the unit of parallelism: OpenCV's own threads are switched off while a
chunk runs (on small images they mostly synchronise, a fifth more CPU for the same wall time), and
each camera's background model is built once per worker rather than once per chunk.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import logging
import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calib.camera import Camera, Rig
from pipeline.io import frames_io
from pipeline.io.backgrounds import spread_frames
from pipeline.io.capture import Capture
from pipeline.io.run_layout import background_path, observations_path, silhouette_path
from stages.background import CameraSamples, sample_camera, tolerated_views, working_size
from stages.consistency import consistent_silhouettes, explained_share
from stages.reconstruction import ReconstructionParams, reconstruct
from stages.reconstruction.occlusion import search_hidden_parts
from stages.reconstruction.views import subject_cut_off
from stages.silhouettes import (
    NOISE_SIGMA_MIN,
    BackgroundModel,
    FloorGeometry,
    SilhouetteParams,
    background_model,
    extract_silhouettes,
    floor_geometry,
    floor_shifts,
    measure_evidence,
    settled_silhouettes,
    shifted_floor,
)
from stages.synchrony import SyncCheck, check_synchrony
from stages.tangency import Refinement, refine_turns, turned

log = logging.getLogger(__name__)

#: Below this many observations a frame is reported: the tracker will only predict its pose.
FEW_OBSERVATIONS = 30
#: Background models a worker keeps (a few MB each): enough for every camera of a large rig.
CACHED_BACKGROUNDS = 32
#: Given masks marking more than this share of every camera's image as person are reported: a subject that a
#: studio's cameras frame whole covers far less, and masks saved the other way round (person 0) cover most.
MAX_GIVEN_COVERAGE = 0.5
#: The first frames of a capture, on which the floor test's shifts between the views are measured: decoded first
#: and cheaply, they show the subject's shadow at one place, and one shift per pair of views serves every frame.
FLOOR_SHIFT_FRAMES = 4
#: Frames, spread over the capture, whose silhouettes refine the cameras' orientations, ...
REFINEMENT_FRAMES = 30
#: ... and, among them, the frames and the rays per view on which the refined cameras must explain more of the
#: silhouettes than the given ones (`stages.consistency.explained_share`).
COHERENCE_FRAMES = 10
COHERENCE_RAYS = 100
#: Frames where the subject's joints move fastest, on which the cameras' synchrony is checked (`stages.synchrony`),
#: and the largest offset tried, in the capture's frames.
SYNC_FRAMES = 24
SYNC_MAX_OFFSET = 5
#: Frames, spread over the capture, whose silhouettes are searched for parts of a view hidden behind something in
#: front of the subject (`stages.reconstruction.occlusion`): enough for the subject's limbs to sweep what hides them.
OCCLUSION_FRAMES = 24


@contextlib.contextmanager
def single_threaded_opencv() -> Iterator[None]:
    """OpenCV without its worker threads inside the block, restored after it."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(threads)


def cached_background_model(path: Path, params: SilhouetteParams, noise_floor: float = NOISE_SIGMA_MIN,
                            tone_curve: bool = True) -> BackgroundModel:
    """The background model of the image at ``path`` (with its ``noise_floor`` and ``tone_curve``,
    :func:`~stages.silhouettes.background_model`), read and built once per worker.

    Reading a colour PNG and building the model cost as much as segmenting a few frames, per camera;
    the file's modification time and size are part of the key, so a rewritten background is read again.
    """
    status = os.stat(path)
    return _background_model(str(path), status.st_mtime_ns, status.st_size, params, noise_floor, tone_curve)


def background_models(out_dir: Path, cameras: Sequence[str], params: SilhouetteParams,
                      noise_floors: Mapping[str, float]) -> list[BackgroundModel]:
    """The background models of ``cameras`` from the silhouette stage's folder ``out_dir``: a ratio per channel for
    those with a noise floor (estimated from the frames), a tone curve for the plates (`cached_background_model`)."""
    return [cached_background_model(background_path(out_dir, camera), params,
                                    noise_floors.get(camera, NOISE_SIGMA_MIN), tone_curve=camera not in noise_floors)
            for camera in cameras]


@functools.lru_cache(maxsize=CACHED_BACKGROUNDS)
def _background_model(path: str, mtime_ns: int, size: int, params: SilhouetteParams,
                      noise_floor: float, tone_curve: bool) -> BackgroundModel:
    return background_model(frames_io.read_image(path), params, noise_floor=noise_floor, tone_curve=tone_curve)


def cached_floor_geometry(rig: Rig, volume: np.ndarray, params: SilhouetteParams,
                          shifts: np.ndarray | None = None) -> FloorGeometry:
    """The rig's floor geometry for the shadow test, made once per worker (tens of ms per camera), with the views'
    ``shifts`` (:func:`~stages.silhouettes.floor_shifts`; None: none).

    Keyed by the cameras' numbers, the volume and the working resolution: a worker that meets another
    capture, or a recalibrated one, makes it again.
    """
    key = hashlib.sha256(repr(params.downsample).encode())
    for camera in rig:
        key.update(camera.name.encode())
        for values in (camera.K, camera.dist, camera.R, camera.t, np.asarray(camera.size)):
            key.update(np.ascontiguousarray(values, dtype=np.float64).tobytes())
    key.update(np.ascontiguousarray(volume, dtype=np.float64).tobytes())
    digest = key.hexdigest()
    if digest not in _FLOOR_GEOMETRIES:
        _FLOOR_GEOMETRIES.clear()  # one rig at a time: a worker serves one capture
        _FLOOR_GEOMETRIES[digest] = floor_geometry(list(rig), volume, params)
    floor = _FLOOR_GEOMETRIES[digest]
    return floor if shifts is None or not np.any(shifts) else shifted_floor(floor, shifts)  # a millisecond or two


_FLOOR_GEOMETRIES: dict[str, FloorGeometry] = {}


def silhouettes_task(chunk: Sequence[int], *, capture: Capture, params: SilhouetteParams, out_dir: Path,
                     noise_floors: Mapping[str, float] | None = None, floor_shifts: np.ndarray | None = None) -> None:
    """Worker: masks of every camera for a chunk of consecutive frames (one decoder per camera).

    The cameras of a frame are segmented together: whether a darker patch is the person's shadow on the
    floor is settled across the views (:func:`stages.silhouettes.extract_silhouettes`), where ``floor_shifts``
    says they see the floor (`pipeline.graph.masks_with_floor_shifts`; None: where the calibration says).
    ``noise_floors`` holds the noise floor of each camera whose background was estimated from the frames; their
    frames' exposure is fitted as one ratio per channel, not as a tone curve
    (:func:`~stages.silhouettes.background_model`).
    """
    floors = noise_floors or {}
    names = capture.rig.names
    with single_threaded_opencv():
        if capture.silhouettes_given:
            for frame in chunk:
                masks = [capture.read_silhouette(camera, frame) for camera in names]
                if all(cv2.countNonZero(mask) > MAX_GIVEN_COVERAGE * mask.size for mask in masks):
                    log.warning("frame %d: the given silhouettes mark most of every camera's image as person "
                                "(expected 0 = background, 255 = person: are they inverted?)", frame)
                _write_masks(out_dir, names, frame, _checked(masks, capture, params))
            return
        backgrounds = background_models(out_dir, names, params, floors)
        floor = cached_floor_geometry(capture.rig, capture.volume, params, floor_shifts)
        # A frame's images are done with once its masks are written, before the next frame is decoded.
        streams = [capture.iter_images(camera, chunk, reuse=True) for camera in names]
        for frame, views in zip(chunk, zip(*streams, strict=True), strict=True):
            masks = extract_silhouettes([image for _, image in views], backgrounds, floor, params)
            _write_masks(out_dir, names, frame, _checked(masks, capture, params))


def floor_shifts_task(capture: Capture, params: SilhouetteParams, out_dir: Path,
                      noise_floors: Mapping[str, float]) -> np.ndarray:
    """Worker: the floor test's shifts between the views (:func:`stages.silhouettes.floor_shifts`) on the capture's
    first `FLOOR_SHIFT_FRAMES` frames, against the backgrounds in the silhouette stage's folder ``out_dir``, and
    those frames' masks made with them from the same evidence (written as :func:`silhouettes_task` writes them).
    The worker keeps the rig's floor geometry for the masks it makes next."""
    names = capture.rig.names
    frames = capture.frame_numbers[:FLOOR_SHIFT_FRAMES]
    with single_threaded_opencv():
        models = background_models(out_dir, names, params, noise_floors)
        streams = [capture.iter_images(camera, frames) for camera in names]
        views = [[measure_evidence(image, model, params) for (_, image), model in zip(images, models, strict=True)]
                 for images in zip(*streams, strict=True)]
        floor = cached_floor_geometry(capture.rig, capture.volume, params)
        shifts = floor_shifts(views, floor, params)
        shifted = shifted_floor(floor, shifts) if np.any(shifts) else floor
        for frame, frame_views in zip(frames, views, strict=True):
            _write_masks(out_dir, names, frame, _checked(settled_silhouettes(frame_views, shifted, params), capture,
                                                         params))
        return shifts


def _checked(masks: list[np.ndarray], capture: Capture, params: SilhouetteParams) -> list[np.ndarray]:
    """The masks of one frame without the parts the other views do not confirm (``params.multiview_check``)."""
    if not params.multiview_check:
        return masks
    return consistent_silhouettes(masks, list(capture.rig), capture.volume, tolerated=tolerated_views(len(masks)))


def _write_masks(out_dir: Path, names: Sequence[str], frame: int, masks: Sequence[np.ndarray]) -> None:
    for camera, mask in zip(names, masks, strict=True):
        frames_io.write_mask(silhouette_path(out_dir, camera, frame), mask)


def reconstruction_task(chunk: Sequence[int], *, capture: Capture, rig: Rig, params: ReconstructionParams,
                        masks_dir: Path, out_dir: Path, hidden: Sequence[np.ndarray | None] | None = None) -> None:
    """Worker: points and normals of a chunk of frames from the silhouette stage's masks, seen by ``rig`` (the
    capture's cameras, or as the silhouettes refined them: `pipeline.graph.refined_rig`), with the parts of the
    views ``hidden`` behind something in front of the subject (`occlusion_task`)."""
    with single_threaded_opencv():
        for frame in chunk:
            masks = [frames_io.read_mask(silhouette_path(masks_dir, camera.name, frame), camera.size)
                     for camera in rig]
            empty = [camera for camera, mask in zip(rig.names, masks, strict=True) if not mask.any()]
            if empty:
                log.warning("frame %d: empty silhouette in camera(s) %s", frame, ", ".join(empty))
            for camera, mask in zip(rig.names, masks, strict=True):
                if subject_cut_off(mask):  # one message per camera: each folds over its frames
                    log.warning("frame %d: the subject reaches the image's border in camera %s (partly out of its "
                                "view: that part comes from the other cameras)", frame, camera)
            observations = reconstruct(masks, rig, capture.volume, params, hidden)
            if len(observations) < FEW_OBSERVATIONS:
                log.warning("frame %d: only %d observations (person out of view or silhouettes disagree)",
                            frame, len(observations))
            frames_io.write_ply(observations_path(out_dir, frame), observations.points, observations.normals)


def occlusion_task(capture: Capture, masks_dir: Path, rig: Rig) -> list[np.ndarray | None]:
    """Worker: per camera of ``rig``, the part of its image hidden behind something in front of the subject, or None
    (`stages.reconstruction.occlusion.search_hidden_parts`), from the silhouettes of ``OCCLUSION_FRAMES`` frames
    spread over the capture."""
    cameras = list(rig)
    frames = spread_frames(capture.frame_numbers, OCCLUSION_FRAMES)
    return search_hidden_parts(lambda: (frame_masks(masks_dir, cameras, frame) for frame in frames), cameras,
                               capture.volume)


def sync_check_task(capture: Capture, masks_dir: Path, frames: Sequence[int]) -> SyncCheck:
    """Worker: each camera checked against the others for frame offsets (`stages.synchrony.check_synchrony`) on the
    silhouette stage's masks of the capture's ``frames`` (indices, at least ``SYNC_MAX_OFFSET + 1`` from either
    end)."""
    cameras = list(capture.rig)
    numbers = capture.frame_numbers

    def mask_at(index: int, camera: int) -> np.ndarray:
        return frames_io.read_mask(silhouette_path(masks_dir, cameras[camera].name, numbers[index]))

    return check_synchrony(mask_at, cameras, capture.volume, frames, SYNC_MAX_OFFSET, tolerated_views(len(cameras)))


def camera_samples_task(capture: Capture, camera: str, plate: np.ndarray | None, *, frames: Sequence[int],
                        downsample: int) -> CameraSamples:
    """Worker: one camera's sampled ``frames`` summed up for the background estimate
    (`stages.background.sample_camera`, its clean ``plate`` if it has one, else None), its video decoded once."""
    return sample_camera((image for _, image in capture.iter_images(camera, frames)),
                         working_size(capture.rig[camera].size), plate=plate, downsample=downsample)


def frame_images_task(capture: Capture, frame: int) -> dict[str, tuple[int, np.ndarray]]:
    """Worker: each camera's ``(frame, image)`` of one frame (the report's photographs): a seek per camera into
    its video, made beside the main process's writing of the exports."""
    return {camera: next(capture.iter_images(camera, [frame])) for camera in capture.rig.names}


def frame_masks(masks_dir: Path, cameras: Sequence[Camera], frame: int) -> list[np.ndarray]:
    """The silhouette stage's masks of one frame, one per camera."""
    return [frames_io.read_mask(silhouette_path(masks_dir, camera.name, frame)) for camera in cameras]


@dataclass(frozen=True)
class RigRefinement:
    """What :func:`refinement_task` measured of the capture's cameras, and whether the turns are kept
    (`pipeline.graph.refined_rig` writes and logs it)."""

    frames: list[int]  # the frames whose tangencies were compared
    refinement: Refinement
    rig: Rig  # the capture's cameras turned by ``refinement.turns``
    explained: tuple[float, float]  # share of the silhouettes the hull explains, given and turned (nan: untested)

    @property
    def kept(self) -> bool:
        """Whether the turned cameras replace the given ones: the tangencies agree clearly better and the hull
        explains more."""
        return self.refinement.tangencies_agree and self.explained[1] > self.explained[0]


def refinement_task(capture: Capture, masks_dir: Path, tolerated: int) -> RigRefinement:
    """Worker: each camera's turn from the tangencies of the silhouettes of ``REFINEMENT_FRAMES`` frames spread
    over the capture (`stages.tangency.refine_turns`) and, when they agree clearly better turned, the share of
    the silhouettes of ``COHERENCE_FRAMES`` of them the visual hull explains (at most ``tolerated`` views outside)
    with the cameras given and turned (`stages.consistency.explained_share`)."""
    rig = capture.rig
    frames = spread_frames(capture.frame_numbers, REFINEMENT_FRAMES)
    # Read frame by frame (a generator): thirty frames' masks at once are tens of megabytes.
    masks = functools.partial(frame_masks, masks_dir, list(rig))
    refinement = refine_turns(map(masks, frames), list(rig), capture.volume.mean(axis=0))
    refined = Rig(tuple(turned(camera, turn) for camera, turn in zip(rig, refinement.turns, strict=True)))
    explained = (np.nan, np.nan)
    if refinement.tangencies_agree:
        shares = np.array([[explained_share(views, list(cameras), capture.volume, tolerated=tolerated,
                                            rays_per_view=COHERENCE_RAYS) for cameras in (rig, refined)]
                           for views in map(masks, spread_frames(frames, COHERENCE_FRAMES))])
        explained = tuple(float(value) for value in np.nanmean(shares, axis=0))
    return RigRefinement(frames, refinement, refined, explained)
