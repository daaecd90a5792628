"""The laboratory around the pipeline: mocap readers, synthetic captures, benchmarks, the pose library builder
and the bundled data they use (``data/``).

It may import any part of the pipeline; the run path (``python -m pipeline run``) never imports it.
"""
