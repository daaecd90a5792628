"""scripts/reliability.py replays issue #13's battery; its quick subset must pass on today's pipeline.

The full replay takes a minute or two, too long for the suite; the quick one (3 bad inputs, 1 damaged
result) checks that the script itself still works against the CLI it drives.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_the_quick_replay_reports_all_passed(tmp_path):
    result = subprocess.run([sys.executable, str(REPO / "scripts" / "reliability.py"), "--quick", "--out",
                             str(tmp_path / "work")], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    rows = {line.split()[0]: line.split()[1:] for line in result.stdout.splitlines()[1:3]}
    assert rows == {"bad": ["input", "3", "3", "0", "0", "0", "0"], "corruption": ["1", "1", "0", "0", "0", "0"]}
    assert "all passed (4 cases" in result.stdout
