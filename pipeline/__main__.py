"""``python -m pipeline``: see :mod:`pipeline.cli`.

The process ends with ``os._exit`` once the subcommand has returned and the output is flushed: by then
every file is written and closed and every worker process has exited, and what a normal exit would
still do is tear down the interpreter's modules (numba's LLVM, OpenCV, matplotlib), about 0.2 s that the
user would wait for after a run. Exit handlers that a subcommand's own work needs (a worker pool's
shutdown, a thread's join) run when that work ends, not at exit.
"""

import logging
import os
import sys

from pipeline.cli import main

status = main()
logging.shutdown()
sys.stdout.flush()
sys.stderr.flush()
os._exit(status)
