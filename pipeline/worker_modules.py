"""The modules a run's local worker processes have imported before their first task.

A worker of ``--workers N`` is a fork of a server process that imported these once
(:func:`pipeline.engine.executors.start_worker_server`). The command line starts that server before its own
imports (:func:`pipeline.cli.start_workers_early`), so this module imports nothing: the server's imports
begin as soon as the interpreter is up, and run beside the command's own.
"""

#: The per-frame tasks (:mod:`pipeline.frame_tasks`, which bring the silhouettes and the reconstruction) and
#: scipy.optimize, which the calibration's refinement (`stages.tangency.refine_turns`) imports when it runs: a
#: tenth of a second a worker would otherwise spend on its first refinement.
WORKER_MODULES = ("pipeline.frame_tasks", "scipy.optimize")
