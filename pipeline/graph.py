"""The real stage graph: one :class:`~pipeline.runner.Stage` declaration per stage, in run order.

Adding a stage
--------------
1. Write its algorithm in ``stages/`` as pure functions over arrays, with a frozen parameter
   dataclass whose fields all have defaults (``SilhouetteParams``). ``--set <stage>.<field>=...``
   and ``--config`` sections then work without further code.
2. Write a run function here, ``run_<stage>(ctx: StageContext) -> int | None``, that reads its
   inputs (``ctx.capture``, ``ctx.input_dir("calibration")``, ...), writes its results under
   ``ctx.out_dir`` with the atomic writers of :mod:`pipeline.frames_io`, and returns the number of
   frames it computed (``None`` when the stage is not per-frame).
3. Append one declaration to :data:`STAGES`: name, run function, upstream stages, parameter class,
   the capture parts it reads directly, and the modules whose source defines its results::

       Stage("silhouettes", run_silhouettes, inputs=("calibration",), params_type=SilhouetteParams,
             capture_parts=("frames", "images", "background", "silhouettes"),
             code=("stages.silhouettes",))

Per-frame stages: the run function calls ``ctx.map_frames(task, outputs_of)``. ``task`` is a
module-level function bound with ``functools.partial`` to plain picklable arguments (the
:class:`~pipeline.capture.Capture`, which carries the rig and paths but no pixels, the params
dataclass, the output folder) and is called in a worker with a chunk of consecutive frame numbers.
**The worker writes each frame's outputs itself, atomically**, and returns nothing: images never
travel back to the parent, and a frame's file existing means the frame is done, which is how an
interrupted run resumes. ``outputs_of(frame)`` lists the files that make a frame complete.
Sequential stages (tracking: frame t needs frame t-1's state) loop in the run function instead,
writing each frame's file atomically and using ``ctx.pending_frames`` to resume.
"""

from __future__ import annotations

from pathlib import Path

from calib.camera import Rig
from calib.formats import load_rig, save_rig
from pipeline import atomic, frames_io
from pipeline.capture import capture_summary
from pipeline.runner import Stage, StageContext

#: File names of the calibration stage's results.
RIG_FILE = "rig.toml"
CAPTURE_FILE = "capture.json"


def run_calibration(ctx: StageContext) -> None:
    """Write the capture's cameras in the world frame (anipose TOML) and its metadata (JSON).

    Downstream stages read these instead of the capture's own calibration, so they always see
    metres, +z up, and image sizes taken from the media.
    """
    with atomic.atomic_output(ctx.out_dir / RIG_FILE) as tmp:
        save_rig(ctx.capture.rig, "anipose", tmp)
    frames_io.write_json(ctx.out_dir / CAPTURE_FILE, capture_summary(ctx.capture))


def read_calibration(folder: Path) -> tuple[Rig, dict]:
    """The calibration stage's results: the world-frame rig and the capture summary.

    ``summary`` has ``fps``, ``cameras``, ``image_sizes``, ``frames``, ``volume`` ((2, 3) as nested
    lists, metres), ``volume_source``, ``height_m``, ``media``, ``silhouettes_given``, ``backgrounds``.
    """
    return load_rig("anipose", folder / RIG_FILE), frames_io.read_json(folder / CAPTURE_FILE)


STAGES: tuple[Stage, ...] = (
    Stage("calibration", run_calibration,
          capture_parts=("config", "calibration", "image_sizes", "frames"),
          code=("calib", "pipeline.capture")),
)
