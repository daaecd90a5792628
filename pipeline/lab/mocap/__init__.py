"""Motion-capture clips (CMU ASF/AMC and BVH) as skeletons moving in the pipeline's world frame: :func:`load_clip`
returns a :class:`Motion` (see :mod:`pipeline.lab.mocap.motion` for the conventions)."""

from pipeline.lab.mocap.motion import Motion, load_clip

__all__ = ["Motion", "load_clip"]
