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
