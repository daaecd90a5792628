"""Export converters: joint tables, BVH and TRC text, joint angles, quality, accuracy metrics, overlays.

Pure functions over arrays of joint centres ``(F, J, 3)`` in metres (world frame, +z up); they return
text or arrays and never open files. ``pipeline.io.export_io`` writes what they produce.

- :mod:`stages.export.skeleton`: the bones between the joints of ``JOINT_NAMES``; one body size for a sequence.
- :mod:`stages.export.joints_table`: ``joints.csv`` text (CAPTURE_FORMAT.md), gap filling.
- :mod:`stages.export.filtering`: optional zero-phase Butterworth smoothing of the trajectories.
- :mod:`stages.export.bvh`: a BVH animation built from joint positions alone.
- :mod:`stages.export.trc`: TRC text for OpenSim and Pose2Sim.
- :mod:`stages.export.angles`: joint angles (ISB-like hip and shoulder, signed knee, ankle, elbow, trunk).
- :mod:`stages.export.quality`: ``quality.csv``, per-frame fit quality and per-joint confidence.
- :mod:`stages.export.metrics`: MPJPE, PCK, angle and acceleration errors, silhouette IoU.
- :mod:`stages.export.overlay`: a skeleton drawn on a camera image.
"""

from dataclasses import dataclass

from stages.checks import check_bool, check_choice, check_number
from stages.export.bvh import BONE_NAMINGS, UNITS
from stages.export.trc import MARKER_NAMINGS


@dataclass(frozen=True)
class ExportParams:
    """What the export stage writes and how (joints.csv, BVH, TRC, angles, C3D and quality.csv are always written).

    Attributes
    ----------
    report : bool
        Write the self-contained HTML report (``export/report.html``).
    overlay_videos : bool
        Write one WebM (VP8) video per camera with the fitted skeleton drawn on the frames, linked from the
        report (costs a full decode and encode of every video, so it is off by default).
    filter_cutoff_hz : float or None
        Smooth every export's trajectories with a zero-phase Butterworth low-pass of this cut-off (Hz,
        below half the frame rate; ``stages.export.filtering``), as Pose2Sim and FreeMoCap do; None
        (the default) exports the tracker's estimates unsmoothed. The tracker's own records are never
        smoothed. Human movement has little power above 6-10 Hz (Winter); a fast kick or punch needs
        the upper end.
    bvh_units : {"cm", "m", "mm"}
        Length unit of ``motion.bvh``: centimetres for MotionBuilder, Maya and most animation tools
        (Blender: import with scale 0.01), metres for tools that expect SI.
    bvh_names : {"joints", "mixamo"}
        Names of the BVH's joints: joints.csv's (and helpers'), or the Mixamo rig's (``Hips``,
        ``LeftUpLeg``, ...), which retargeting tools map onto a character by name.
    trc_names : {"joints", "halpe26"}
        Marker names of ``joints.trc``: joints.csv's, or the HALPE_26 keypoint names of Pose2Sim's
        OpenSim models (``Hip``, ``LHip``, ``LBigToe``...; docs/exports.md says where they differ).
    sync_check : bool
        Check whether the cameras filmed the same instants (``stages.synchrony``: each camera's silhouettes
        against the others' a few frames apart), write ``export/sync_check.json`` and name each camera whose
        media run frames behind or ahead, with the ``frame_offsets`` for capture.yaml that make up for it. For
        rigs without hardware synchronisation (webcams, phones); off by default, as it lengthens the export stage
        (docs/results_by_hand.md, "Cameras not synchronised"). ``--from export --set export.sync_check=true`` checks a
        finished run.
    """

    report: bool = True
    overlay_videos: bool = False
    filter_cutoff_hz: float | None = None
    bvh_units: str = "cm"
    bvh_names: str = "joints"
    trc_names: str = "joints"
    sync_check: bool = False

    def __post_init__(self) -> None:
        for name in ("report", "overlay_videos", "sync_check"):
            check_bool(f"export.{name}", getattr(self, name))
        if self.filter_cutoff_hz is not None:
            check_number("export.filter_cutoff_hz", self.filter_cutoff_hz, 0.0, above=True)
        check_choice("export.bvh_units", self.bvh_units, UNITS)
        check_choice("export.bvh_names", self.bvh_names, BONE_NAMINGS)
        check_choice("export.trc_names", self.trc_names, MARKER_NAMINGS)
