"""The real stage graph: one :class:`~pipeline.engine.stage.Stage` declaration per stage, in run order.

Adding a stage
--------------
1. Write its algorithm in ``stages/`` as pure functions over arrays, with a frozen parameter
   dataclass whose fields all have defaults (``SilhouetteParams``). ``--set <stage>.<field>=...``
   and ``--config`` sections then work without further code.
2. Write a run function here, ``run_<stage>(ctx: StageContext) -> int | None``, that reads its
   inputs (``ctx.capture``, ``ctx.input_dir("calibration")``, ...), writes its results under
   ``ctx.out_dir`` with the atomic writers of :mod:`pipeline.io.frames_io`, and returns the number of
   frames it computed (``None`` when the stage is not per-frame).
3. Append one declaration to :data:`STAGES`: name, run function, upstream stages, parameter class,
   the capture parts it reads directly, and the first-party modules, packages and data folders whose
   files define its results (its cache key; the helpers of this module it calls count by themselves)::

       Stage("silhouettes", run_silhouettes, inputs=("calibration",), params_type=SilhouetteParams,
             capture_parts=("frames", "images", "background", "silhouettes"),
             code=("stages.silhouettes", "pipeline.frame_tasks", "pipeline.io.capture", "calib", *FILES_CODE))

   tests/pipeline/test_graph.py runs each stage under a profiler and fails when it runs first-party
   code or reads first-party data that ``code`` leaves out. (A module of constants only, such as
   ``stages.joints``, runs no code the profiler could see: declare it where its values are used.)

Per-frame stages: the run function calls ``ctx.map_frames(task, outputs_of)``. ``task`` is a
module-level function bound with ``functools.partial`` to plain picklable arguments (the
:class:`~pipeline.io.capture.Capture`, which carries the rig and paths but no pixels, the params
dataclass, the output folder) and is called in a worker with a chunk of consecutive frame numbers.
**The worker writes each frame's outputs itself, atomically**, and returns nothing: images never
travel back to the parent, and a frame's file existing means the frame is done, which is how an
interrupted run resumes. ``outputs_of(frame)`` lists the files that make a frame complete.
Sequential stages (tracking: frame t needs frame t-1's state) loop in the run function instead,
writing each frame's file atomically and using ``ctx.pending_frames`` to resume.
"""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import functools
import logging
import math
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np

from calib.camera import Rig
from calib.formats import load_rig, save_rig
from pipeline.compiled_cache import load_cached
from pipeline.engine.context import StageContext
from pipeline.engine.executors import call_logged, relog, usable_cpus
from pipeline.engine.stage import Stage
from pipeline.frame_tasks import (
    FLOOR_SHIFT_FRAMES,
    SYNC_FRAMES,
    SYNC_MAX_OFFSET,
    camera_samples_task,
    floor_shifts_task,
    frame_images_task,
    frame_masks,
    occlusion_task,
    reconstruction_task,
    refinement_task,
    silhouettes_task,
    sync_check_task,
)
from pipeline.io import atomic, frames_io, run_layout
from pipeline.io.backgrounds import spread_frames
from pipeline.io.body_io import tracking_body
from pipeline.io.capture import Capture, capture_summary
from pipeline.io.export_io import write_exports, write_joints_csv, write_quality_csv
from pipeline.io.overlay_video import write_overlay_video
from pipeline.io.run_layout import (
    CAPTURE_FILE,
    JOINTS_FILE,
    QUALITY_FILE,
    RIG_FILE,
    ahead_masks_path,
    background_path,
    calibration_check_path,
    calibration_refinement_path,
    floor_shifts_path,
    hidden_part_path,
    noise_floors_path,
    observations_path,
    overlay_video_name,
    refined_rig_path,
    remaking_path,
    room_change_path,
    silhouette_path,
    sync_check_path,
)
from pipeline.io.tracking_io import read_tracking
from pipeline.report.page import write_report
from stages.background import BackgroundEstimate, estimate_backgrounds, sample_count
from stages.background.plates import MIN_PLATE_MATCH, PLATE_SHIFT_PX, PlateFit, plate_fit, shifted_plate
from stages.background.room import PATCH_FRAMES, patched_plate, static_parts
from stages.export import ExportParams
from stages.export.quality import FrameQuality
from stages.joints import JOINT_NAMES
from stages.reconstruction import Observations, ReconstructionParams
from stages.reconstruction.occlusion import parts_union
from stages.reconstruction.views import VOLUME_FACES, faces_reached
from stages.silhouettes import SilhouetteParams
from stages.synchrony import SyncCheck, fastest_frames
from stages.tangency import (
    camera_disagreement,
    cameras_at_fault,
    pair_disagreement,
    pair_medians,
)
from stages.tracking.params import TrackerParams
from stages.tracking.results import BodyHeight, FrameResult, frame_record
from stages.tracking.tracker import Tracker

log = logging.getLogger(__name__)

def run_calibration(ctx: StageContext) -> None:
    """Write the capture's cameras in the world frame (anipose TOML) and its metadata (JSON).

    The stages after it take the rig from the capture, opened once per run (:class:`Capture` already holds it
    in this frame: metres, +z up, image sizes taken from the media); they declare this stage as an input so
    that a change of the world frame (``up: auto`` finding another floor) reruns them. ``rig.toml`` is for the
    user and other tools; ``capture.json`` is what the report and ``pipeline eval`` read of the capture.
    """
    with atomic.atomic_output(ctx.out_dir / RIG_FILE) as tmp:
        save_rig(ctx.capture.rig, "anipose", tmp)
    frames_io.write_json(ctx.out_dir / CAPTURE_FILE, capture_summary(ctx.capture))


#: Longest chunk of the silhouette stage on videos (frames). Each chunk seeks its videos, and a seek
#: decodes from the last keyframe (per camera, as much work as segmenting a few frames), so chunks are as
#: long as this allows; it bounds how unevenly the last chunks load the workers.
MAX_VIDEO_CHUNK_FRAMES = 200


#: An estimated background whose unresolved share (never seen without the subject) reaches this is a warning.
UNRESOLVED_WARNING_SHARE = 0.001


def estimated_backgrounds(capture: Capture, params: SilhouetteParams, plates: Mapping[str, PlateFit],
                          executor: cf.Executor | None = None) -> dict[str, BackgroundEstimate]:
    """Every camera's background, estimated from frames sampled over the whole capture when a camera has no
    clean plate in ``plates`` (:func:`checked_plates`; :func:`stages.background.estimate_backgrounds`; the cameras
    with one keep it).

    The work that is one camera's (its samples, :func:`~pipeline.frame_tasks.camera_samples_task`, its video
    decoded once; each round's silhouettes of them, ``estimate_backgrounds``' ``mapper``) is mapped over the
    cameras on ``executor`` when given, side by side: a worker holds one camera's full-resolution samples at a
    time. Logs what was done, and warns for each camera where part of the image was never seen without the
    subject.
    """
    frames = capture.frame_numbers
    picks = spread_frames(frames, min(sample_count(len(frames), (height, width, 3))
                                      for width, height in (camera.size for camera in capture.rig)))
    mapper = executor.map if executor is not None else map
    given = [plate_image(capture, name, plates[name]) if name in plates else None for name in capture.rig.names]
    samples = list(mapper(functools.partial(camera_samples_task, capture, frames=picks, downsample=params.downsample),
                          capture.rig.names, given))
    estimates = estimate_backgrounds(samples, list(capture.rig), capture.volume, params, mapper=mapper)
    found = dict(zip(capture.rig.names, estimates, strict=True))
    missing = [name for name, s in zip(capture.rig.names, samples, strict=True) if not s.plate]
    first = estimates[0]
    log.info("silhouettes: no usable clean plate for camera(s) %s; backgrounds from %d frames spread over the capture, "
             "the subject left out where the cameras' visual hull puts him (%d rounds)", ", ".join(missing), len(picks),
             first.rounds)
    if first.ghost_samples:
        log.info("silhouettes: the subject stood still in %d of the sampled frames, where a plain median kept a "
                 "ghost of him; the backgrounds started again from the other frames", first.ghost_samples)
    if first.found_samples == 0 and len(capture.rig) >= 2:  # one camera makes no hull: its plain median stays
        log.warning("silhouettes: no subject found in any of the %d sampled frames: nobody is in view, or the subject "
                    "never moves, and then no background estimate can tell him from the room (a clean plate in "
                    "background/ can)", len(picks))
    for name in missing:
        estimate = found[name]
        if estimate.unresolved_share >= UNRESOLVED_WARNING_SHARE:
            log.warning("silhouettes: camera %s: %.1f %% of the image could not be separated from the subject "
                        "(covered in nearly every sampled frame); its background there is inpainted from around "
                        "it, and the silhouettes may be wrong there (a clean plate in background/ avoids this)",
                        name, 100 * estimate.unresolved_share)
    return found


def _backgrounds(ctx: StageContext) -> dict[str, float]:
    """Write one background image per camera: its clean plate (:func:`checked_plates`), else
    :func:`estimated_backgrounds`; and the estimated ones' noise floors (JSON). Returns the noise floors.

    Computed once in this process, before the per-frame work, so every worker reads the same model.
    A clean plate that is a PNG already and needs no shift is copied byte for byte: decoding and encoding it
    again would only cost time, once per camera.
    """
    capture = ctx.capture
    plates = checked_plates(capture)
    estimated = [camera for camera in capture.rig.names if camera not in plates]
    floors_path = noise_floors_path(ctx.out_dir)
    pending = [camera for camera in capture.rig.names if not _intact(background_path(ctx.out_dir, camera))]
    if estimated and not _intact(floors_path):
        pending = list(capture.rig.names)  # the floors come with the estimate (which is deterministic)
    if not pending:  # all kept from an interrupted run, intact
        return frames_io.read_json(floors_path) if estimated else {}
    estimates = (estimated_backgrounds(capture, ctx.params, plates, ctx.workers.executor)  # every camera votes
                 if estimated else {})
    for camera in pending:
        path = background_path(ctx.out_dir, camera)
        given = capture.background_paths.get(camera)
        if camera in estimates:
            frames_io.write_image(path, estimates[camera].image)
        elif given.suffix.lower() == ".png" and plates[camera].distance_px < PLATE_SHIFT_PX:
            atomic.write_bytes(path, given.read_bytes())
        else:
            frames_io.write_image(path, plate_image(capture, camera, plates[camera]))
    floors = {camera: estimates[camera].noise for camera in estimated}
    if estimated:
        frames_io.write_json(floors_path, floors)
    return floors


def checked_plates(capture: Capture) -> dict[str, PlateFit]:
    """How the clean plates of ``capture`` that are pictures of their cameras' views lie against their frames
    (:mod:`stages.background.plates`, against the capture's first frame), by camera. One warning per plate that
    lies :data:`~stages.background.plates.PLATE_SHIFT_PX` or more off (:func:`plate_image` shifts it onto them) or
    that is left out (another view's, or a colour view's without its colour: the camera's background is then
    estimated from the frames, as without a plate)."""
    first = capture.frame_numbers[0]

    def fitted(camera: str) -> PlateFit:
        return plate_fit(capture.background(camera), next(capture.iter_images(camera, [first]))[1])

    with cf.ThreadPoolExecutor(usable_cpus()) as pool:  # OpenCV's decoding and transforms let go of the GIL
        fits = dict(zip(capture.background_paths, pool.map(fitted, capture.background_paths), strict=True))
    for camera, fit in list(fits.items()):
        path = capture.background_paths[camera]
        if fit.match < MIN_PLATE_MATCH:
            log.warning("%s: the clean plate does not show camera %s's view (its phase correlation with frame %d "
                        "peaks at %.2f, expected above %.2f: another camera's plate, or another room's?); that "
                        "camera's background is estimated from the frames instead", path, camera, first, fit.match,
                        MIN_PLATE_MATCH)
            del fits[camera]
        elif fit.colourless:
            log.warning("%s: the clean plate has no colour while camera %s's frames have (a grey-level copy?); that "
                        "camera's background is estimated from the frames instead", path, camera)
            del fits[camera]
        elif fit.distance_px >= PLATE_SHIFT_PX:
            log.warning("%s: the clean plate lies %.1f pixels off camera %s's frames (x %+.1f, y %+.1f: the camera "
                        "moved after it was taken?); it is used shifted onto them", path, fit.distance_px, camera,
                        *fit.shift)
    return fits


def plate_image(capture: Capture, camera: str, fit: PlateFit) -> np.ndarray:
    """The camera's clean plate (H, W, 3) uint8, shifted onto its frames when ``fit`` (:func:`checked_plates`) says
    it lies :data:`~stages.background.plates.PLATE_SHIFT_PX` or more off them. Read when needed, one camera at a
    time: a large rig's plates would not all fit in memory at once."""
    plate = capture.background(camera)
    return shifted_plate(plate, fit.shift) if fit.distance_px >= PLATE_SHIFT_PX else plate


def _intact(path: Path) -> bool:
    return path.exists() and frames_io.file_problem(path) is None


def run_silhouettes(ctx: StageContext) -> int:
    """Per frame and camera, the person's mask: given ones as they are, else background subtraction (made again,
    every camera's, when a camera's clean plate is found out of date: :func:`mended_backgrounds`)."""
    given = ctx.capture.silhouettes_given
    names = ctx.capture.rig.names
    plated = [] if given else [camera for camera in names if camera in ctx.capture.background_paths]

    def outputs_of(frame: int) -> list[Path]:
        return [silhouette_path(ctx.out_dir, camera, frame) for camera in names]

    def remove(paths: Iterable[Path]) -> None:
        for path in paths:
            path.unlink(missing_ok=True)

    every_mask = [path for frame in ctx.capture.frame_numbers for path in outputs_of(frame)]
    remaking = remaking_path(ctx.out_dir)
    if remaking.exists():  # stopped while remaking: masks and backgrounds of two kinds, so start over
        remove(every_mask)
        remove(path for camera in plated for path in (background_path(ctx.out_dir, camera),
                                                      room_change_path(ctx.out_dir, camera)))
        remaking.unlink()
    ahead = ahead_masks_path(ctx.out_dir)
    if ahead.exists():  # stopped before the floor shifts were decided: masks made as if none were needed
        remove(path for frame in frames_io.read_json(ahead)["frames"] for path in outputs_of(frame))
        ahead.unlink()
    floors = {} if given else _backgrounds(ctx)

    def make_masks() -> int:
        if given or ctx.params.shadows != "floor" or len(names) < 2:
            return _map_masks(ctx, floors, outputs_of, None)
        return masks_with_floor_shifts(ctx, floors, outputs_of)

    count = make_masks()
    plated = [camera for camera in plated if camera not in floors]  # a plate left out has an estimate instead
    mended = mended_backgrounds(ctx.capture, ctx.out_dir, plated) if ctx.params.find_room_changes and plated else {}
    if mended:
        atomic.write_text(remaking, "")
        for camera, (image, region) in mended.items():
            frames_io.write_image(background_path(ctx.out_dir, camera), image)
            frames_io.write_mask(room_change_path(ctx.out_dir, camera), region.view(np.uint8) * np.uint8(255))
        remove(every_mask)  # every view's, since the views settle shadows and parts together
        count = make_masks()
        remaking.unlink()
    _check_calibration(ctx.capture, ctx.out_dir)
    return count


def _masks_task(ctx: StageContext, noise_floors: Mapping[str, float], shifts: np.ndarray | None) -> Callable:
    """The silhouette stage's per-chunk task (`frame_tasks.silhouettes_task`) with the floor test's ``shifts``."""
    return functools.partial(silhouettes_task, capture=ctx.capture, params=ctx.params, out_dir=ctx.out_dir,
                             noise_floors=noise_floors, floor_shifts=shifts)


def _map_masks(ctx: StageContext, noise_floors: Mapping[str, float], outputs_of: Callable[[int], list[Path]],
               shifts: np.ndarray | None, frames: Sequence[int] | None = None) -> int:
    """Make the masks of the pending frames among ``frames`` (default: all) on the workers; how many were made."""
    chunk_size = None
    if ctx.capture.media == "videos" and not ctx.capture.silhouettes_given:
        chunk_size = video_chunk_size(len(ctx.pending_frames(outputs_of, frames)), ctx.workers.count)
    return ctx.map_frames(_masks_task(ctx, noise_floors, shifts), outputs_of, frames=frames, chunk_size=chunk_size)


def masks_with_floor_shifts(ctx: StageContext, noise_floors: Mapping[str, float],
                            outputs_of: Callable[[int], list[Path]]) -> int:
    """Make the pending masks with the floor test's shifts between the views (`frame_tasks.floor_shifts_task`, on a
    worker, which makes the masks of the frames it measures them on); how many frames' masks were made. The shifts
    are written down (`_write_floor_shifts`).

    The other workers do not wait for them: each makes its share of the pending frames at once, as if no shift were
    needed (so it is with a sound calibration), while the measuring worker goes on with its own share; when a shift
    is taken, their masks are made again with it. Their frames are listed in `ahead_masks_path` until that is
    decided: a run stopped before removes them when it starts again (`run_silhouettes`).
    """
    capture, out_dir, workers = ctx.capture, ctx.out_dir, ctx.workers
    first = list(capture.frame_numbers[:FLOOR_SHIFT_FRAMES])
    rest = [frame for frame in ctx.pending_frames(outputs_of) if frame not in first]
    own = len(rest) // workers.count  # the measuring worker's share; with one worker, all of them
    mine, ahead = rest[:own], rest[own:]
    frames_io.write_json(ahead_masks_path(out_dir), {"frames": ahead})  # before any of them is made
    measured = workers.executor.submit(floor_shifts_task, capture, ctx.params, out_dir, noise_floors)
    share = max(1, math.ceil(len(ahead) / max(1, workers.count - 1)))  # frames per other worker
    unshifted = _masks_task(ctx, noise_floors, None)
    running = [workers.executor.submit(call_logged, unshifted, tuple(ahead[start:start + share]))
               for start in range(0, len(ahead), share)]  # none with one worker, in this process
    shifts = measured.result()
    made = len(first) + _map_masks(ctx, noise_floors, outputs_of, shifts, mine)
    for future in running:
        relog(future.result())
    if np.any(shifts):
        for frame in ahead:
            for path in outputs_of(frame):
                path.unlink(missing_ok=True)
        made += _map_masks(ctx, noise_floors, outputs_of, shifts, ahead)
    else:
        made += len(ahead)
    ahead_masks_path(out_dir).unlink()
    _write_floor_shifts(out_dir, capture.rig.names, first, shifts * ctx.params.downsample)
    return made


def _write_floor_shifts(out_dir: Path, names: Sequence[str], frames: Sequence[int], pixels: np.ndarray) -> None:
    """Write the floor test's shifts ``pixels`` (C, C, 2), image pixels, measured on ``frames``, to
    `floor_shifts_path`, and name the largest in a line when any is taken: the calibration then maps the floor that
    far off where the views see it."""
    frames_io.write_json(floor_shifts_path(out_dir), {
        "method": "shadows' darkening compared between the views", "frames": list(frames),
        "shifts_px": {camera: {other: pixels[index, column].tolist() for column, other in enumerate(names)
                               if column != index} for index, camera in enumerate(names)}})
    lengths = np.linalg.norm(pixels, axis=2)
    if lengths.max() > 0:
        index, other = np.unravel_index(np.argmax(lengths), lengths.shape)
        log.info("silhouettes: the floor test compares %d of the %d pairs of views shifted off the calibration's "
                 "mapping, by up to %.0f pixels (%s's floor points in %s's view): the calibration is off by about "
                 "that at the floor (shifts: %s)", np.count_nonzero(lengths), len(names) * (len(names) - 1),
                 lengths.max(), names[index], names[other], floor_shifts_path(out_dir))


#: Frames, spread over the capture, whose silhouettes are searched for parts of the room changed since the plates.
ROOM_CHECK_FRAMES = 24


def mended_backgrounds(capture: Capture, masks_dir: Path,
                       cameras: Sequence[str]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The background of each of ``cameras`` (those with a clean plate) whose silhouettes hold a part of the room
    that changed since its plate (`stages.background.room`), mended from frames of the capture where the subject is
    apart from it, with that part (H, W) bool, by camera; each camera mended is named in a warning. Their
    silhouettes are then out of date."""
    frames = spread_frames(capture.frame_numbers, ROOM_CHECK_FRAMES)

    def masks(camera: str, chosen: Sequence[int]) -> Iterator[np.ndarray]:
        return (frames_io.read_mask(silhouette_path(masks_dir, camera, frame)) for frame in chosen)

    with cf.ThreadPoolExecutor(usable_cpus()) as pool:  # the decoding and OpenCV's work let go of the GIL
        found = dict(zip(cameras, pool.map(lambda camera: static_parts(masks(camera, frames)), cameras), strict=True))
    mended = {}
    for camera, (region, apart) in found.items():
        if not region.any():
            continue
        chosen = spread_frames([frames[k] for k in apart], PATCH_FRAMES)
        images = [image for _, image in capture.iter_images(camera, chosen)]
        background = frames_io.read_image(background_path(masks_dir, camera))
        mended[camera] = patched_plate(background, region, images, list(masks(camera, chosen))), region
        log.warning("silhouettes: camera %s: %.1f %% of its view differs from its clean plate in nearly every frame "
                    "and not with the subject (something put down or moved after the plate was taken?); its "
                    "background there is taken from the frames, the silhouettes are made again, and the "
                    "reconstruction does not let this camera carve there (the thing may hide the subject)", camera,
                    100 * region.mean())
    return mended


#: Frames, spread over the capture, on which the silhouettes are checked against the calibration.
CALIBRATION_CHECK_FRAMES = 10
#: A camera whose silhouettes disagree with the other cameras' by more than this (metres at the subject,
#: `stages.tangency`) is named in a warning: a sound calibration gives millimetres, cameras turned by 0.2° one to
#: three centimetres, two cameras' names swapped decimetres.
CALIBRATION_DISAGREEMENT_M = 0.05


def _check_calibration(capture: Capture, masks_dir: Path) -> None:
    """Log how far each camera's silhouettes agree with the other cameras' through the calibration (epipolar
    tangency, `stages.tangency`), warning about the cameras beyond `CALIBRATION_DISAGREEMENT_M`, and write the
    figures for the report (`calibration_check.json` in the stage's folder).

    A calibration that does not fit the videos (two cameras' names swapped, a camera moved since it was
    calibrated) loads and runs like a sound one; the reconstruction then has little to carve and the track is
    lost, with nothing to say which camera is at fault.
    """
    cameras = list(capture.rig)
    if len(cameras) < 2:
        return
    frames = spread_frames(capture.frame_numbers, CALIBRATION_CHECK_FRAMES)
    per_frame = [pair_disagreement(frame_masks(masks_dir, cameras, frame), cameras, capture.volume.mean(axis=0))
                 for frame in frames]
    pairs = pair_medians(np.array(per_frame))
    off = cameras_at_fault(pairs, CALIBRATION_DISAGREEMENT_M)
    per_camera = camera_disagreement(pairs, ~off if (~off).any() else None)  # all at fault: against each other
    frames_io.write_json(calibration_check_path(masks_dir), {
        "method": "epipolar tangency", "frames": frames, "limit_m": CALIBRATION_DISAGREEMENT_M,
        "disagreement_m": {camera.name: float(value) if np.isfinite(value) else None
                           for camera, value in zip(cameras, per_camera, strict=True)},
        "at_fault": [camera.name for camera, bad in zip(cameras, off, strict=True) if bad]})
    if np.all(np.isnan(per_camera)):
        log.info("calibration check: no camera pair sees the whole subject on the %d frames checked", len(frames))
        return
    figures = ", ".join(f"{camera.name} {100 * value:.1f}" for camera, value in zip(cameras, per_camera, strict=True)
                        if np.isfinite(value))
    unchecked = [camera.name for camera, value in zip(cameras, per_camera, strict=True) if np.isnan(value)]
    if unchecked:  # a view whose silhouette is empty or cut by the image's border gives no tangent plane
        figures += (f"; not checked: {', '.join(unchecked)}, whose silhouettes were empty or reached the image's "
                    "border on the frames checked")
    if not off.any():
        log.info("calibration check: every camera's silhouettes agree with the others' at the subject within "
                 "%.1f cm (epipolar tangency, median over %d frames; cm per camera: %s)",
                 100 * np.nanmax(per_camera), len(frames), figures)
        return
    named = ", ".join(camera.name + (f" ({100 * value:.0f} cm)" if np.isfinite(value) else "")
                      for camera, value, bad in zip(cameras, per_camera, off, strict=True) if bad)
    others = per_camera[~off & ~np.isnan(per_camera)]
    agree = f"; the others agree within {100 * others.max():.1f} cm" if len(others) else ""
    log.warning("calibration check: the silhouettes of %s disagree with the other cameras' at the subject "
                "(epipolar tangency, median over %d frames%s): check their calibration (two cameras' names "
                "swapped, a camera moved since it was calibrated), then their silhouettes (something that only "
                "they see, in every frame, or something in front of the subject that hides part of him from them: "
                "the reconstruction looks for that)", named, len(frames), agree)


def video_chunk_size(pending: int, workers: int) -> int:
    """Frames per chunk of ``pending`` video frames: the fewest chunks that are a multiple of ``workers``
    (so that they share the chunks evenly) and no longer than ``MAX_VIDEO_CHUNK_FRAMES``."""
    chunks = workers * max(1, math.ceil(pending / (workers * MAX_VIDEO_CHUNK_FRAMES)))
    return max(1, math.ceil(pending / chunks))


def run_reconstruction(ctx: StageContext) -> int:
    """Per frame, sparse surface points with outward normals from all cameras' silhouettes, with the cameras'
    orientations refined from the silhouettes first (``refine_calibration``, `refined_rig`) and the parts of their
    views hidden behind something in front of the subject found (`frame_tasks.occlusion_task`)."""
    masks_dir = ctx.input_dir("silhouettes")
    executor = ctx.workers.executor
    searching = ctx.params.find_hidden_parts
    # The search runs on a worker beside the refinement, with the cameras as given; turned, they are searched again.
    search = (executor.submit(occlusion_task, ctx.capture, masks_dir, ctx.capture.rig)
              if executor is not None and searching else None)
    rig = (refined_rig(ctx.capture, masks_dir, ctx.out_dir, ctx.params.tolerated_views, executor)
           if ctx.params.refine_calibration else ctx.capture.rig)
    hidden = None
    if searching:
        hidden = (search.result() if search is not None and rig is ctx.capture.rig
                  else occlusion_task(ctx.capture, masks_dir, rig))
        _write_hidden_parts(rig, hidden, ctx.out_dir)
    # Where the room changed since a plate, something solid stands that may hide the subject: not carved either.
    changed = [room_change_path(masks_dir, camera.name) for camera in rig]
    if any(path.exists() for path in changed):
        hidden = [parts_union(part, frames_io.read_mask(path) if path.exists() else None)
                  for part, path in zip(hidden or [None] * len(rig), changed, strict=True)]
    task = functools.partial(reconstruction_task, capture=ctx.capture, rig=rig, params=ctx.params,
                             masks_dir=masks_dir, out_dir=ctx.out_dir, hidden=hidden)
    return ctx.map_frames(task, lambda frame: [observations_path(ctx.out_dir, frame)])


def _write_hidden_parts(rig: Rig, hidden: Sequence[np.ndarray | None], out_dir: Path) -> None:
    """Save each camera's part of the view hidden behind something in front of the subject
    (`stages.reconstruction.occlusion`) and say which cameras have one."""
    for camera, part in zip(rig, hidden, strict=True):
        if part is None:
            continue
        path = hidden_part_path(out_dir, camera.name)
        frames_io.write_mask(path, part)
        log.warning("%s: something in front of the subject hides part of him from this camera on most frames checked "
                    "(%.0f %% of its image, where the other cameras place him and this one shows the background): it "
                    "does not carve there, the other cameras do (the part: %s)", camera.name,
                    100 * np.count_nonzero(part) / part.size, path)


def refined_rig(capture: Capture, masks_dir: Path, out_dir: Path, tolerated: int,
                executor: cf.Executor | None = None) -> Rig:
    """The capture's rig with each camera turned about its centre as the silhouettes' tangencies say
    (`stages.tangency.refine_turns`), when that makes them agree clearly better and the visual hull (at most
    ``tolerated`` views outside, as the reconstruction carves) explains more of the silhouettes; else as given.

    The second test guards against an error that turns cannot mend: cameras whose positions are off by centimetres
    give tangencies that turns bring closer while the rays through the silhouettes meet less well (foreign taekwondo
    with every camera moved by 2 cm: docs/results_by_hand.md). The measuring runs on ``executor`` when given
    (:func:`~pipeline.frame_tasks.refinement_task`: a worker process, while this one readies the tracker), else
    here. Writes what was measured and decided (`calibration_refinement_path`) and, when the turns are kept, the
    cameras as the reconstruction uses them (`refined_rig_path`, anipose TOML: for the user's next run or other
    tools).
    """
    rig = capture.rig
    if len(rig) < 3:  # two views' tangencies say nothing the calibration could be wrong about
        return rig
    measured = (executor.submit(refinement_task, capture, masks_dir, tolerated).result() if executor is not None
                else refinement_task(capture, masks_dir, tolerated))
    refinement, explained, kept = measured.refinement, measured.explained, measured.kept
    degrees = np.degrees(np.linalg.norm(refinement.turns, axis=1))
    frames_io.write_json(calibration_refinement_path(out_dir), {
        "method": "epipolar tangency", "frames": measured.frames, "tangencies": refinement.tangencies,
        "disagreement_before_m": _finite_or_none(refinement.before_m),
        "disagreement_after_m": _finite_or_none(refinement.after_m), "tangencies_agree": refinement.tangencies_agree,
        "explained_before": _finite_or_none(explained[0]), "explained_after": _finite_or_none(explained[1]),
        "kept": kept, "turns_deg": {camera.name: float(turn) for camera, turn in zip(rig, degrees, strict=True)}})
    turns = ", ".join(f"{camera.name} {turn:.2f}" for camera, turn in zip(rig, degrees, strict=True))
    if refinement.tangencies_agree and not kept:
        log.info("calibration not refined: turning the cameras by %s degrees made the tangencies agree (%.1f -> "
                 "%.1f mm) but the visual hull explain less of the silhouettes (%.1f -> %.1f %%): the calibration is "
                 "off in a way turns cannot mend (the cameras' positions?)", turns, 1000 * refinement.before_m,
                 1000 * refinement.after_m, 100 * explained[0], 100 * explained[1])
    if not kept:
        return rig
    with atomic.atomic_output(refined_rig_path(out_dir)) as tmp:
        save_rig(measured.rig, "anipose", tmp)
    log.info("calibration refined from the silhouettes: cameras turned by %s degrees about their centres (the "
             "tangencies' median disagreement %.1f -> %.1f mm over %d frames, the silhouettes the visual hull explains "
             "%.1f -> %.1f %%; the cameras used: %s)", turns, 1000 * refinement.before_m, 1000 * refinement.after_m,
             len(measured.frames), 100 * explained[0], 100 * explained[1], refined_rig_path(out_dir))
    return measured.rig


def used_rig(capture: Capture, reconstruction_dir: Path) -> Rig:
    """The cameras the reconstruction used: as the silhouettes refined them (`refined_rig`), or as given."""
    path = refined_rig_path(reconstruction_dir)
    return load_rig("anipose", path) if path.is_file() else capture.rig


def _finite_or_none(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


#: Statuses of tracked frames that are exported (the others were only predicted).
EXPORTED_STATUSES = ("tracked", "initialised")


def run_tracking(ctx: StageContext) -> int:
    """Fit the articulated body to each frame's observations, in order (frame t starts from t-1).

    Sequential by nature, so it runs in this process, alongside the reconstruction when both have
    to run (it streams: each frame's observations are read as soon as they exist); each frame's
    record (estimate + tracker state) is written atomically, and a resumed run restarts from the
    state after the last complete frame.
    """
    params: TrackerParams = ctx.params
    if params.height_m is None and ctx.capture.height_m is not None:
        params = dataclasses.replace(params, height_m=ctx.capture.height_m)
    tracker = Tracker(params, ctx.capture.volume, tracking_body(params))
    # Now rather than at the first frame: alongside the reconstruction, this runs while the calibration is refined
    # in a worker, and the first frame comes when every core has frames to reconstruct.
    load_cached()
    frames = ctx.capture.frame_numbers
    pending = ctx.pending_frames(lambda frame: [run_layout.tracking_path(ctx.out_dir, frame)])
    done = frames.index(pending[0]) if pending else len(frames)  # frames after a missing one are redone
    state = read_tracking(ctx.out_dir, frames[done - 1])[1] if done else None
    observations_dir = ctx.input_dir("reconstruction")
    faces = np.zeros((len(frames), len(VOLUME_FACES)), dtype=bool)
    with ctx.progress(len(frames), initial=done) as bar:
        for index, frame in enumerate(frames[done:], start=done):
            points, normals = frames_io.read_ply(ctx.ready(observations_path(observations_dir, frame)))
            faces[index] = faces_reached(points, ctx.capture.volume, VOLUME_CONTACT_M)
            result, state = tracker.track(state, Observations(points, normals))
            if result.status in ("predicted", "lost"):
                log.warning("frame %d: pose %s, not exported (%d observations)", frame, result.status, len(points))
            frames_io.write_record(run_layout.tracking_path(ctx.out_dir, frame), frame_record(frame, result, state))
            bar.update(1)
    _warn_volume_contact(faces[done:], frames[done:], ctx.capture.volume)
    if state is not None:
        _report_height(BodyHeight(tracked_m=state.height_m, stated_m=params.height_m,
                                  measured_m=state.measured_height_m))
    return len(frames) - done


#: A stated and a measured height further apart than this fraction: one of them is wrong, not a few per cent off
#: as each can be (a typo, another subject's height, silhouettes that miss part of the body).
HEIGHT_DISAGREEMENT = 0.1


def _report_height(height: BodyHeight) -> None:
    """The height the body was sized at and the stated and measured ones it weighed, as the report gives them;
    a warning when those two disagree by far. Nothing when no height was stated (the data's is the only one)."""
    change = height.disagreement
    if change is None:
        return
    line = f"tracking: {height.sentence()}"
    if abs(change) > HEIGHT_DISAGREEMENT:
        log.warning("%s Check subject.height_m in capture.yaml.", line)
    else:
        log.info("%s", line)


#: Observations this close to a face of the working volume (metres) mean the subject was cut there: a
#: clipped hull's points lie on the face itself, within a voxel and the rim placement.
VOLUME_CONTACT_M = 0.02


def _warn_volume_contact(faces: np.ndarray, frames: Sequence[int], volume: np.ndarray) -> None:
    """One warning per face of the volume that the subject reached, with how often and where first."""
    for column, (axis, bound, name) in enumerate(VOLUME_FACES):
        hits = np.flatnonzero(faces[:, column])
        if len(hits):
            log.warning("the subject reaches the working volume's %s face (%s = %.2f m) in %d of %d frames "
                        "(first: frame %d): what lies beyond it is cut off; widen `volume:` in capture.yaml",
                        name, "xyz"[axis], volume[bound, axis], len(hits), len(frames), frames[hits[0]])


def frame_quality(results: dict[int, FrameResult]) -> FrameQuality:
    """The tracker's per-frame records as the arrays of ``quality.csv`` (``stages.export.quality``)."""
    frames = sorted(results)
    unrecorded = np.full(len(JOINT_NAMES), np.nan)
    return FrameQuality(
        frames=np.array(frames, dtype=int), statuses=np.array([results[f].status for f in frames]),
        doubtful=np.array([results[f].doubtful for f in frames]),
        observations=np.array([results[f].observations for f in frames], dtype=int),
        log_likelihood=np.array([results[f].log_likelihood for f in frames], dtype=float),
        outlier_fraction=np.array([results[f].outlier_fraction for f in frames], dtype=float),
        support=np.array([unrecorded if results[f].joint_support is None else results[f].joint_support
                          for f in frames]),
        fitted=np.array([results[f].status in EXPORTED_STATUSES for f in frames]),
        corrected=np.array([" ".join(results[f].corrected) for f in frames]))


def run_export(ctx: StageContext) -> None:
    """joints.csv, BVH, TRC, angles, C3D and quality.csv of the estimated frames, then the overlay videos and
    the report.

    Frames the tracker only predicted are left out, as CAPTURE_FORMAT.md asks (no rows, never NaN).
    """
    params: ExportParams = ctx.params
    capture = ctx.capture
    rig = used_rig(capture, ctx.input_dir("reconstruction"))
    results = {frame: read_tracking(ctx.input_dir("tracking"), frame)[0] for frame in capture.frame_numbers}
    estimated = {frame: r.joints for frame, r in results.items() if r.status in EXPORTED_STATUSES}
    if len(estimated) < len(results):
        log.warning("export: %d of %d frames were not estimated and have no rows in joints.csv",
                    len(results) - len(estimated), len(results))
    frames = np.array(sorted(estimated), dtype=int)
    quality = frame_quality(results)
    shown = None
    if params.report and capture.has_images:  # the report's photographs, decoded while the exports are written
        pictured = frames if len(frames) else np.asarray(capture.frame_numbers)
        shown = ctx.workers.executor.submit(frame_images_task, capture, int(pictured[len(pictured) // 2]))
    sync = _start_sync_check(ctx, estimated) if params.sync_check else None
    if len(frames):
        write_exports(ctx.out_dir, frames, np.stack([estimated[frame] for frame in frames]), capture.fps,
                      params=params, quality=quality)
    else:
        # Nothing to animate: joints.csv keeps its header so that readers see "no frame", not a failure.
        log.warning("export: no frame was estimated; joints.csv has no rows and no BVH/TRC/C3D is written")
        write_joints_csv(ctx.out_dir / JOINTS_FILE, frames, np.zeros((0, len(JOINT_NAMES), 3)))
        write_quality_csv(ctx.out_dir / QUALITY_FILE, quality)
    if params.overlay_videos and capture.has_images and len(frames):  # before the report, which links them
        for camera in rig:
            write_overlay_video(capture.iter_images(camera.name, capture.frame_numbers), camera, estimated,
                                ctx.out_dir / overlay_video_name(camera.name), capture.fps)
    if sync is not None:
        _write_sync_check(capture, sync.result(), ctx.out_dir)
    if params.report:  # also when no frame was estimated: it says what happened
        write_report(ctx.output_root, rig=rig, images=shown.result() if shown is not None else None)


def _start_sync_check(ctx: StageContext, estimated: Mapping[int, np.ndarray]) -> cf.Future | None:
    """The cameras' synchrony check (`frame_tasks.sync_check_task`) started on a worker, to run while this process
    writes the exports on the core the workers leave; None, with a line saying why, when it cannot tell anything:
    frames not evenly spaced (offsets are whole steps of the capture's frames), or too few frames with joints."""
    frames = ctx.capture.frame_numbers
    if len(set(np.diff(frames).tolist())) > 1:
        log.info("sync check: not run, the capture's frames are not evenly spaced")
        return None
    joints = np.stack([estimated[frame] if frame in estimated else np.full((len(JOINT_NAMES), 3), np.nan)
                       for frame in frames])
    checked = fastest_frames(joints, SYNC_FRAMES, SYNC_MAX_OFFSET + 1)
    if not checked:
        log.info("sync check: not run, too few frames with estimated joints (%d frames; offsets up to %d are tried)",
                 len(frames), SYNC_MAX_OFFSET)
        return None
    return ctx.workers.executor.submit(sync_check_task, ctx.capture, ctx.input_dir("silhouettes"), checked)


def _write_sync_check(capture: Capture, check: SyncCheck, out_dir: Path) -> None:
    """Write the cameras' synchrony check (`sync_check_path`, measured by `frame_tasks.sync_check_task` on evenly
    spaced frames) and warn about each camera whose silhouettes agree clearly better with the others' at a frame
    offset, with the ``frame_offsets`` for capture.yaml that make up for it (those given counted in)."""
    frames = capture.frame_numbers
    step = int(frames[1] - frames[0])  # a capture frame is `step` frames of the media
    lags, mean = check.lags(), check.mean_agreement()
    names = capture.rig.names
    given = capture.frame_offsets
    totals = {name: given.get(name, 0) + int(lag) * step for name, lag in zip(names, lags, strict=True)}
    needed = {name: offset for name, offset in totals.items() if offset}  # the given ones may cancel out
    frames_io.write_json(sync_check_path(out_dir), {
        "method": "silhouette coherence across time", "frames": [int(frames[i]) for i in check.frames],
        "offsets": [int(k) * step for k in check.offsets],
        "agreement": {name: [_finite_or_none(value) for value in row] for name, row in zip(names, mean, strict=True)},
        "lag": {name: int(lag) * step for name, lag in zip(names, lags, strict=True)},
        "frame_offsets": needed})
    zero = int(np.flatnonzero(check.offsets == 0)[0])
    if np.isnan(mean[:, zero]).all():
        log.info("sync check: nothing moved in the silhouettes of the %d frames checked, which says nothing about "
                 "the cameras' synchrony", len(check.frames))
    elif not lags.any():
        log.info("sync check: every camera's silhouettes agree best with the other cameras' at the same frame (%d "
                 "frames where the subject moves)", len(check.frames))
    advice = ("frame_offsets: {" + ", ".join(f"{camera}: {offset}" for camera, offset in needed.items()) + "}"
              if needed else "no frame_offsets")
    for name, lag, row in zip(names, lags, mean, strict=True):
        if lag:
            log.warning("cameras not synchronised? %s's silhouettes agree best with the other cameras' %d frame(s) "
                        "%s (%.1f %% of its silhouette explained by their visual hull, against %.1f %% at the same "
                        "frame; %d frames where the subject moves): its media seem to run %d frame(s) %s theirs. "
                        "%s in capture.yaml makes up for it (then run again)", name, abs(lag) * step,
                        "later" if lag > 0 else "earlier", 100 * row[zero + lag], 100 * row[zero],
                        len(check.frames), abs(lag) * step, "behind" if lag > 0 else "ahead of", advice)


#: Modules every stage runs to write (and read) its files.
FILES_CODE = ("pipeline.io.frames_io", "pipeline.io.atomic", "pipeline.io.run_layout")

STAGES: tuple[Stage, ...] = (
    Stage("calibration", run_calibration,  # up: auto finds the floor in the media (pipeline.io.auto_frame)
          capture_parts=("config", "calibration", "image_sizes", "frames", "images", "background", "silhouettes"),
          code=("calib", "pipeline.io.capture", "pipeline.io.auto_frame", "pipeline.io.backgrounds",
                "stages.silhouettes", *FILES_CODE)),
    Stage("silhouettes", run_silhouettes, inputs=("calibration",), params_type=SilhouetteParams,
          capture_parts=("frames", "images", "background", "silhouettes"),
          code=("stages.silhouettes", "stages.background", "stages.consistency", "stages.rays", "stages.checks",
                "stages.tangency", "stages.reconstruction.views", "pipeline.frame_tasks", "pipeline.io.backgrounds",
                "pipeline.io.capture", "calib", *FILES_CODE)),
    Stage("reconstruction", run_reconstruction, inputs=("calibration", "silhouettes"),
          params_type=ReconstructionParams, capture_parts=("config", "frames"),
          code=("stages.reconstruction", "stages.rays", "stages.checks", "stages.tangency", "stages.consistency",
                "pipeline.frame_tasks", "pipeline.io.capture", "pipeline.io.backgrounds", "calib", *FILES_CODE)),
    Stage("tracking", run_tracking, inputs=("calibration", "reconstruction"), params_type=TrackerParams,
          capture_parts=("config", "frames"),
          code=("stages.tracking", "stages.checks", "stages.joints", "stages.reconstruction", "pipeline.frame_tasks",
                "pipeline.compiled_cache", "pipeline.io.body_io", "pipeline.io.tracking_io", *FILES_CODE),
          streams=True),
    Stage("export", run_export, inputs=("calibration", "silhouettes", "reconstruction", "tracking"),
          params_type=ExportParams,
          capture_parts=("config", "frames", "images"),
          code=("stages.export", "stages.checks", "stages.joints", "stages.tracking.results", "stages.synchrony",
                "stages.consistency", "stages.rays", "pipeline.io.export_io",
                "pipeline.io.tracking_io", "pipeline.io.overlay_video", "pipeline.report",
                "pipeline.engine.run_warnings", "pipeline.evaluate", "pipeline.terminal", "pipeline.io.capture",
                "pipeline.frame_tasks", "calib", *FILES_CODE)),
)
