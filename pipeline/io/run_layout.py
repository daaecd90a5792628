"""Where everything of a run lies under its output folder ``<out>/``: the one place that names those paths.

::

    <out>/run.json                           which capture and parameters the folder is for, the last run's state
    <out>/.lock                              held while a run uses the folder
    <out>/warnings.json                      every warning behind the results, by stage
    <out>/<stage>/manifest.json              written last: the stage finished (cache key, inputs, outputs)
    <out>/<stage>/params_hash                written first: the folder is the runner's, and for which key
    <out>/calibration/rig.toml               the cameras in the pipeline's world frame (anipose TOML), for the user
    <out>/calibration/capture.json           fps, frames, volume, world transform, ... (the report and eval read it)
    <out>/silhouettes/<camera>/<frame>.png   masks
    <out>/silhouettes/background/<camera>.png, noise_floors.json
    <out>/silhouettes/calibration_check.json the calibration checked against the silhouettes (per camera)
    <out>/silhouettes/floor_shifts.json      where the floor test of shadows compares the views, off the calibration
    <out>/reconstruction/<frame>.ply         points and normals
    <out>/tracking/frames/<frame>.json       estimate and tracker state
    <out>/export/joints.csv, quality.csv, joints.trc, motion.bvh, joints.c3d, angles.csv, overlay_<camera>.webm,
                 report.html
    <out>/export/sync_check.json             the cameras' synchrony checked on the silhouettes (per camera)
    <out>/eval/metrics.json                  ``python -m pipeline eval``

``<frame>`` is :func:`pipeline.io.frames_io.frame_name`'s six digits. A stage's run function and its worker
tasks see their own folder (``ctx.out_dir``) and upstream folders (``ctx.input_dir(name)``), so the per-stage
functions below take a stage folder; :class:`RunLayout` gives the same paths from the run folder, for what
reads a run from outside (the report, eval, the commands, the benchmarks).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pipeline.io.frames_io import DamagedFileError, frame_name, read_json

#: Files the runner keeps in the run folder and in each stage folder.
RUN_RECORD, LOCK, WARNINGS_FILE = "run.json", ".lock", "warnings.json"
MANIFEST, MARKER = "manifest.json", "params_hash"
#: The calibration stage's files.
RIG_FILE, CAPTURE_FILE = "rig.toml", "capture.json"
#: The export stage's files.
JOINTS_FILE, BVH_FILE, TRC_FILE, ANGLES_FILE = "joints.csv", "motion.bvh", "joints.trc", "angles.csv"
C3D_FILE, QUALITY_FILE = "joints.c3d", "quality.csv"
REPORT_FILE = "report.html"
OVERLAY_SUFFIX = ".webm"
#: ``python -m pipeline eval``'s folder and file.
EVAL_DIR, METRICS_FILE = "eval", "metrics.json"
#: The stage folders' names, in run order (the names of :data:`pipeline.graph.STAGES`).
STAGE_NAMES = ("calibration", "silhouettes", "reconstruction", "tracking", "export")


def read_manifest_file(stage_dir: Path) -> dict | None:
    """The JSON object of a stage folder's manifest, or None when it has none (the stage has not finished).

    Every reader of manifests goes through here (the cache, the report, the benchmarks) and decides for
    itself what an unreadable one means.

    Raises
    ------
    DamagedFileError
        If the manifest is not a JSON object (or not readable at all: ``OSError``).
    """
    path = stage_dir / MANIFEST
    if not path.is_file():
        return None
    manifest = read_json(path)
    if not isinstance(manifest, dict):
        raise DamagedFileError(path, f"expected a JSON object, got {type(manifest).__name__}")
    return manifest


def silhouette_path(stage_dir: Path, camera: str, frame: int) -> Path:
    """A mask in the silhouette stage's folder."""
    return stage_dir / camera / frame_name(frame, ".png")


def background_path(stage_dir: Path, camera: str) -> Path:
    """A camera's background image in the silhouette stage's folder."""
    return stage_dir / "background" / f"{camera}.png"


def noise_floors_path(stage_dir: Path) -> Path:
    """The noise floors of the estimated backgrounds (JSON: camera -> σ, 8-bit levels) in the silhouette stage's
    folder."""
    return stage_dir / "background" / "noise_floors.json"


def room_change_path(stage_dir: Path, camera: str) -> Path:
    """The part of a camera's view where the room changed since its clean plate (PNG, 255 there; written by the
    silhouette stage only for cameras with such a part, `pipeline.graph.mended_backgrounds`): its background is
    mended there, and the reconstruction does not let that camera carve there."""
    return stage_dir / "room_changes" / f"{camera}.png"


def remaking_path(stage_dir: Path) -> Path:
    """Present in the silhouette stage's folder while its silhouettes are made again against backgrounds mended for
    parts of the room changed since the plates (`pipeline.graph.run_silhouettes`): a run that stopped then left masks
    and backgrounds of two kinds, and the stage starts over."""
    return stage_dir / "remaking"


def floor_shifts_path(stage_dir: Path) -> Path:
    """The floor test's shifts between the views (JSON, `pipeline.graph.masks_with_floor_shifts`) in the silhouette
    stage's folder: where each camera's floor points are compared in each other camera, off the calibration's
    mapping."""
    return stage_dir / "floor_shifts.json"


def ahead_masks_path(stage_dir: Path) -> Path:
    """The frames whose masks are being made before the floor test's shifts are decided (JSON, present only
    meanwhile: `pipeline.graph.masks_with_floor_shifts`), in the silhouette stage's folder."""
    return stage_dir / "masks_ahead_of_floor_shifts.json"


def calibration_check_path(stage_dir: Path) -> Path:
    """The silhouette stage's check of the calibration (JSON, `pipeline.graph._check_calibration`)."""
    return stage_dir / "calibration_check.json"


def sync_check_path(stage_dir: Path) -> Path:
    """The export stage's check of the cameras' synchrony (JSON, `pipeline.graph._write_sync_check`)."""
    return stage_dir / "sync_check.json"


def calibration_refinement_path(stage_dir: Path) -> Path:
    """The reconstruction stage's refinement of the cameras' orientations (JSON, `pipeline.graph.refined_rig`)."""
    return stage_dir / "calibration_refinement.json"


def hidden_part_path(stage_dir: Path, camera: str) -> Path:
    """The part of a camera's image that the reconstruction found hidden behind something in front of the subject
    (PNG, 255 hidden; `pipeline.frame_tasks.occlusion_task`), written only for cameras with such a part."""
    return stage_dir / "hidden" / f"{camera}.png"


def refined_rig_path(stage_dir: Path) -> Path:
    """The cameras as the reconstruction used them, when the refinement was kept (anipose TOML)."""
    return stage_dir / "rig_refined.toml"


def observations_path(stage_dir: Path, frame: int) -> Path:
    """A frame's points and normals in the reconstruction stage's folder."""
    return stage_dir / frame_name(frame, ".ply")


def tracking_path(stage_dir: Path, frame: int) -> Path:
    """A frame's record in the tracking stage's folder."""
    return stage_dir / "frames" / frame_name(frame, ".json")


def overlay_video_name(camera: str) -> str:
    """File name of a camera's overlay video inside ``export/``."""
    return f"overlay_{camera}{OVERLAY_SUFFIX}"


@dataclass(frozen=True)
class RunLayout:
    """The paths of one run folder, ``root`` (see the module docstring)."""

    root: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))

    def stage_dir(self, stage: str) -> Path:
        return self.root / stage

    def manifest(self, stage: str) -> Path:
        return self.stage_dir(stage) / MANIFEST

    @property
    def run_record(self) -> Path:
        return self.root / RUN_RECORD

    @property
    def warnings(self) -> Path:
        return self.root / WARNINGS_FILE

    @property
    def capture_summary(self) -> Path:
        return self.stage_dir("calibration") / CAPTURE_FILE

    @property
    def silhouettes_dir(self) -> Path:
        return self.stage_dir("silhouettes")

    def silhouette(self, camera: str, frame: int) -> Path:
        return silhouette_path(self.silhouettes_dir, camera, frame)

    def background(self, camera: str) -> Path:
        return background_path(self.silhouettes_dir, camera)

    def room_change(self, camera: str) -> Path:
        return room_change_path(self.silhouettes_dir, camera)

    @property
    def calibration_check(self) -> Path:
        return calibration_check_path(self.silhouettes_dir)

    @property
    def floor_shifts(self) -> Path:
        return floor_shifts_path(self.silhouettes_dir)

    @property
    def sync_check(self) -> Path:
        return sync_check_path(self.export_dir)

    def observations(self, frame: int) -> Path:
        return observations_path(self.stage_dir("reconstruction"), frame)

    @property
    def calibration_refinement(self) -> Path:
        return calibration_refinement_path(self.stage_dir("reconstruction"))

    @property
    def refined_rig(self) -> Path:
        return refined_rig_path(self.stage_dir("reconstruction"))

    def hidden_part(self, camera: str) -> Path:
        return hidden_part_path(self.stage_dir("reconstruction"), camera)

    @property
    def tracking_dir(self) -> Path:
        return self.stage_dir("tracking")

    def tracking_record(self, frame: int) -> Path:
        return tracking_path(self.tracking_dir, frame)

    @property
    def export_dir(self) -> Path:
        return self.stage_dir("export")

    def export_file(self, name: str) -> Path:
        """One of the export stage's files, by name (:data:`JOINTS_FILE`, ...)."""
        return self.export_dir / name

    @property
    def joints(self) -> Path:
        return self.export_file(JOINTS_FILE)

    @property
    def report(self) -> Path:
        return self.export_file(REPORT_FILE)

    def overlay_video(self, camera: str) -> Path:
        return self.export_file(overlay_video_name(camera))

    @property
    def metrics(self) -> Path:
        return self.root / EVAL_DIR / METRICS_FILE
