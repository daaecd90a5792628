"""Export converters: joint tables, BVH text, joint angles, accuracy metrics, skeleton overlays.

Pure functions over arrays of joint centres ``(F, J, 3)`` in metres (world frame, +z up); they return
text or arrays and never open files. ``pipeline.export_io`` writes what they produce.

- :mod:`stages.export.skeleton`: the bones between the joints of ``JOINT_NAMES``.
- :mod:`stages.export.joints_table`: ``joints.csv`` text (CAPTURE_FORMAT.md), gap filling.
- :mod:`stages.export.bvh`: a BVH animation built from joint positions alone.
- :mod:`stages.export.angles`: joint angles (knee/elbow flexion, hip/shoulder, trunk inclination).
- :mod:`stages.export.metrics`: MPJPE, PCK, angle errors, silhouette IoU.
- :mod:`stages.export.overlay`: a skeleton drawn on a camera image.
"""

from dataclasses import dataclass

from stages.checks import check_bool


@dataclass(frozen=True)
class ExportParams:
    """What the export stage writes besides joints.csv, BVH, angles and C3D (always written).

    Attributes
    ----------
    report : bool
        Write the self-contained HTML report (``export/report.html``).
    overlay_videos : bool
        Write one MP4 per camera with the fitted skeleton drawn on the frames (costs a full decode and
        encode of every video, so it is off by default).
    """

    report: bool = True
    overlay_videos: bool = False

    def __post_init__(self) -> None:
        for name in ("report", "overlay_videos"):
            check_bool(f"export.{name}", getattr(self, name))
