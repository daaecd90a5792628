"""The stage graph's start-up: what the run command imports, and the export stage's warm-up."""

from __future__ import annotations

import subprocess
import sys

from pipeline.graph import REPORT_MODULE, warm_up_export
from stages.export import ExportParams


def test_the_run_command_does_not_import_the_report_at_start_up():
    code = "import sys, pipeline.commands.run; print(sorted({'matplotlib', 'pipeline.report'} & set(sys.modules)))"
    imported = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert imported.strip() == "[]"  # matplotlib costs a quarter of a second: imported only for a report


def test_warm_up_export_imports_the_report_only_for_a_report():
    code = ("import sys; from pipeline.graph import warm_up_export; from stages.export import ExportParams; "
            f"warm_up_export(None, ExportParams(report=False)); print({REPORT_MODULE!r} in sys.modules)")
    imported = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert imported.strip() == "False"
    warm_up_export(None, ExportParams(report=True))
    assert REPORT_MODULE in sys.modules
