import subprocess
import sys
from pathlib import Path

from pipeline.environment import DEFAULTS, set_defaults


def test_each_default_is_set_where_the_user_set_nothing_and_the_users_setting_wins():
    environ = {"OPENBLAS_NUM_THREADS": "4"}
    set_defaults(environ)
    assert environ["OPENBLAS_NUM_THREADS"] == "4"
    assert {name: environ[name] for name in DEFAULTS if name != "OPENBLAS_NUM_THREADS"} == {
        name: value for name, value in DEFAULTS.items() if name != "OPENBLAS_NUM_THREADS"}


def test_the_entry_point_sets_them_before_numpy_loads():
    # numpy reads OPENBLAS_NUM_THREADS once, when it loads: the entry point must not import it first.
    code = ("import sys, runpy; sys.argv = ['pipeline', '--help']\n"
            "import pipeline.environment as e; real = e.set_defaults\n"
            "def checked(*a, **k):\n    assert 'numpy' not in sys.modules and 'cv2' not in sys.modules; real(*a, **k)\n"
            "e.set_defaults = checked\n"
            "runpy.run_module('pipeline', run_name='__main__')\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env={"PATH": ""},
                          cwd=Path(__file__).resolve().parents[2])
    assert done.returncode == 0, done.stderr
