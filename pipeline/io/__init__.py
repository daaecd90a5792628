"""Files in and out: the capture reader, per-frame files, atomic writes, export files, plain YAML, videos.

It may import ``calib`` and ``stages``, never :mod:`pipeline.engine`, :mod:`pipeline.graph` or
:mod:`pipeline.lab`.
"""
