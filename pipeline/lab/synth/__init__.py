"""Synthetic captures of real motion: a body surface driven by mocap, rendered by virtual cameras.

Public API for other stages' evaluations: ``build_body``, ``pose_body``, ``posed_mesh``,
``sample_body_surface`` (see ``pipeline.lab.synth.body`` for a usage example).
"""

from pipeline.lab.synth.body import BODY_KINDS, build_body, pose_body
from pipeline.lab.synth.posed import MATERIALS, PosedBody, posed_mesh, sample_body_surface

__all__ = [
    "BODY_KINDS",
    "MATERIALS",
    "PosedBody",
    "build_body",
    "pose_body",
    "posed_mesh",
    "sample_body_surface",
]
