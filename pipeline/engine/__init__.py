"""The stage engine: stage declarations, cache keys and manifests, the runner, executors, parameters.

Generic: it knows stages, folders and files, not what a silhouette or a pose is. It may import
:mod:`pipeline.io`, ``calib`` and ``stages``' errors, never :mod:`pipeline.lab`.
"""
