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

from pipeline.environment import set_defaults

set_defaults()  # before OpenCV and numpy load, for this process and the workers it starts

from pipeline.cli import main  # noqa: E402  (after the environment it must see)

status = main()
logging.shutdown()
sys.stdout.flush()
sys.stderr.flush()
os._exit(status)
