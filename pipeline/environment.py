"""The environment every process of a run starts with, set before OpenCV and numpy load (they read it once).

Worker processes inherit it, so a run's pool and a batch's captures side by side start the same way. A user's own
setting of any of these variables wins.
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping

#: Variable -> value unless the user set it.
DEFAULTS = {
    # OpenCV's and FFmpeg's own messages (a PNG header they cannot parse, "moov atom not found") would reach the
    # terminal before the pipeline's one-line error that says which file is wrong and why.
    "OPENCV_LOG_LEVEL": "OFF",
    "OPENCV_FFMPEG_LOGLEVEL": "-8",
    # The run's parallelism is its own: frames in worker processes beside the tracker, captures side by side in a
    # batch. OpenBLAS's threads (numpy's and scipy's products and solvers) find no free core there and only take
    # turns with those processes: two captures at a time in a batch ran each about a tenth slower with them.
    "OPENBLAS_NUM_THREADS": "1",
}


def set_defaults(environ: MutableMapping[str, str] = os.environ) -> None:
    """Give each variable of :data:`DEFAULTS` its value in ``environ`` where it is not set."""
    for name, value in DEFAULTS.items():
        environ.setdefault(name, value)
