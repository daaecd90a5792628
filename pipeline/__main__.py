"""``python -m pipeline``: see :mod:`pipeline.cli`.

The process ends with ``os._exit`` once the subcommand has returned and the output is flushed: by then
every file is written and closed and every worker process has exited, and what a normal exit would
still do is tear down the interpreter's modules (numba's LLVM, OpenCV, matplotlib), a wait that the
user would notice after every run. Exit handlers that a subcommand's own work needs (a worker pool's
shutdown, a thread's join) run when that work ends, not at exit.
"""

import logging
import os
import sys

# OpenCV's and FFmpeg's own messages (a PNG header they cannot parse, "moov atom not found") would reach the
# terminal before the pipeline's one-line error that says which file is wrong and why; set before cv2 loads,
# so that the worker processes, which inherit the environment, are quiet too. A user's own setting wins.
os.environ.setdefault("OPENCV_LOG_LEVEL", "OFF")
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")

from pipeline.cli import main  # noqa: E402  (after the environment it must see)

status = main()
logging.shutdown()
sys.stdout.flush()
sys.stderr.flush()
os._exit(status)
