"""The stage graph: what the run command imports, and each stage's cache key covering the code and data it
really runs and reads."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
from conftest import make_capture

from pipeline.cli import main
from pipeline.graph import STAGES, _report_height
from pipeline.io.run_layout import STAGE_NAMES
from stages.tracking.results import BodyHeight

REPO = Path(__file__).resolve().parents[2]


def test_the_run_command_never_imports_matplotlib():
    code = "import sys, pipeline.commands.run, pipeline.report.page; print('matplotlib' in sys.modules)"
    imported = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert imported.strip() == "False"  # a quarter of a second to import: the report's plots are SVG instead


def test_the_run_command_never_imports_the_lab():
    code = ("import sys, pipeline.commands.run, pipeline.report.page; "
            "print(sorted(m for m in sys.modules if m.startswith('pipeline.lab')))")
    imported = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert imported.strip() == "[]"  # benchmarks and synthetic captures are not part of a run


def test_the_worker_server_starts_before_any_heavy_import():
    heavy = ("numpy", "cv2", "scipy", "numba", "pipeline.frame_tasks")
    code = ("import sys, pipeline.cli, pipeline.worker_modules, pipeline.engine.executors; "
            f"print(sorted(m for m in {heavy!r} if m in sys.modules))")
    imported = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert imported.strip() == "[]"  # what the command line imports before it starts the worker server


def test_the_workers_never_import_the_tracker():
    code = ("import sys, importlib, pipeline.worker_modules as w; [importlib.import_module(m) for m in "
            "w.WORKER_MODULES]; print(sorted(m for m in ('numba', 'stages.tracking') if m in sys.modules))")
    imported = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert imported.strip() == "[]"  # numba's import and cache are the tracker's, in the main process


def test_the_run_layout_names_the_graph_stages():
    assert STAGE_NAMES == tuple(stage.name for stage in STAGES)  # a copy: the report cannot import the graph


def test_the_run_command_imports_scipy_signal_only_to_smooth():
    code = "import sys, pipeline.commands.run; print('scipy.signal' in sys.modules)"
    imported = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert imported.strip() == "False"  # half a second to import, for a filter that is off by default


#: Run in a fresh interpreter: each stage of pipeline.graph, run again on a finished output folder, in a
#: child forked before any stage ran (so no cache a stage fills hides code from another), under a
#: profiler (every Python function called) and an audit hook (every file opened). Prints, per stage,
#: the first-party functions and data files that ran or were read and that its code version does not
#: cover. The runner, the executors and the log of warnings are left out: they decide which frames run where
#: and keep the log, never what a result holds.
UNCOVERED = """
import json, os, sys
from pathlib import Path
from pipeline import graph
from pipeline.engine import runner, versions
from pipeline.io.capture import Capture
from pipeline.engine.executors import make_executor
from pipeline.engine.params import default_params

repo = Path(runner.__file__).resolve().parents[2]
roots = tuple(repo / name for name in ("calib", "stages", "pipeline"))
orchestration = {repo / "pipeline" / "engine" / name for name in ("runner.py", "context.py", "executors.py",
                                                                          "run_warnings.py")}
capture, out = Capture.open(sys.argv[1]), Path(sys.argv[2])


def first_party(path):
    return any(root in path.parents for root in roots)


def nested(code):
    yield code
    for constant in code.co_consts:
        if hasattr(constant, "co_consts"):
            yield from nested(constant)


def uncovered(stage):
    called, opened, tracing = set(), set(), []
    sys.addaudithook(lambda event, args: opened.add(Path(os.fsdecode(args[0])).resolve()) if tracing
                     and event == "open" and isinstance(args[0], (str, bytes, os.PathLike)) else None)
    execute = runner.Runner._execute

    def traced(self, *args):  # the stage's own work, not the runner's bookkeeping around it
        tracing.append(True)
        sys.setprofile(lambda frame, event, arg: called.add(frame.f_code) if event == "call" else None)
        try:
            return execute(self, *args)
        finally:
            sys.setprofile(None)
            tracing.clear()

    runner.Runner._execute = traced
    with make_executor(1) as workers:
        runner.Runner(graph.STAGES, capture, default_params(graph.STAGES), out, workers).run_stage(stage, force=True)
    inputs = versions.code_inputs(stage)
    files = {path.resolve() for _, path in inputs.files}
    functions = {code for function in inputs.functions for code in nested(function.__code__)}
    misses = set()
    for code in called - functions:
        path = Path(code.co_filename).resolve()
        if first_party(path) and path not in files | orchestration:
            misses.add(f"{path.relative_to(repo)}: {code.co_qualname}")
    for path in opened - files:
        if first_party(path) and "__pycache__" not in path.parts and path.suffix not in (".py", ".pyc"):
            misses.add(f"{path.relative_to(repo)} (data)")
    return sorted(misses)


report = {}
for stage in graph.STAGES:
    read, write = os.pipe()
    if os.fork() == 0:
        os.close(read)
        os.write(write, json.dumps(uncovered(stage)).encode())
        os._exit(0)
    os.close(write)
    with os.fdopen(read) as answer:
        report[stage.name] = json.loads(answer.read() or '["the child failed"]')
    os.wait()
print(json.dumps(report))
"""


def test_every_stage_key_covers_the_code_and_data_it_runs(tmp_path):
    capture = make_capture(tmp_path / "capture", backgrounds=True)
    assert main(["run", str(capture), "--out", str(tmp_path / "out"), "-q"]) == 0
    traced = subprocess.run([sys.executable, "-c", UNCOVERED, str(capture), str(tmp_path / "out")], cwd=REPO,
                            capture_output=True, text=True, timeout=600)
    assert traced.returncode == 0, traced.stderr[-3000:]
    report = json.loads(traced.stdout.strip().splitlines()[-1])
    assert set(report) == {stage.name for stage in STAGES}
    outside = {name: misses for name, misses in report.items() if misses}
    assert not outside, f"code or data a stage uses but its key (Stage.code) misses: {json.dumps(outside, indent=1)}"


def test_a_stated_height_far_from_the_measured_one_is_a_warning(caplog):
    def height(measured):
        return BodyHeight(tracked_m=float(np.sqrt(1.60 * measured)), stated_m=1.60, measured_m=measured)

    with caplog.at_level(logging.INFO, logger="pipeline.graph"):
        _report_height(height(1.65))
        _report_height(height(1.85))
        _report_height(BodyHeight(tracked_m=1.7, stated_m=None, measured_m=1.7))  # nothing to weigh: no line
    (near, far) = [(record.levelno, record.getMessage()) for record in caplog.records]
    assert near == (logging.INFO, "tracking: Body sized for a subject 1.625 m tall "
                                  "(stated 1.600 m, measured from the data 1.650 m, +3.1 %).")
    assert far[0] == logging.WARNING and far[1].endswith("+15.6 %). Check subject.height_m in capture.yaml.")
