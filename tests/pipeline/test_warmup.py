"""`python -m pipeline warmup`: afterwards numba's cache holds every signature the tracker uses, so that a new
process (the first run) loads the compiled code instead of compiling it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

from pipeline.commands import warmup

REPO = Path(__file__).resolve().parents[2]

# Run in a fresh process after the warm-up: the cache loaded ahead (`compiled_cache.load_cached`), the warm-up
# again, then the tracker on other data (a walk, as in the tracker's tests, with each distance), as the tracking
# stage would call it. Prints, per compiled function, the signatures it compiled (cache misses) and loaded (cache
# hits) and the size of its fresh on-disk index, and how many signatures were loaded ahead.
_AFTER = textwrap.dedent("""
    import json, sys
    from types import SimpleNamespace
    import numpy as np
    sys.path.insert(0, "tests/stages/tracking")
    from tracking_testing import VOLUME, sample_ellipsoids
    from pipeline import compiled_cache
    from pipeline.commands import warmup
    from stages.tracking.body_file import load_body
    from stages.tracking.params import TrackerParams
    from stages.tracking.tracker import Tracker

    ahead = compiled_cache.load_cached()
    warmup.warm_up()
    body = load_body()
    rng = np.random.default_rng(5)
    for params, frames in [(TrackerParams(), 3), (TrackerParams(distance="points", init_headings=2, init_refine=2), 2),
                           (TrackerParams(distance="algebraic", init_headings=2, init_refine=2), 2)]:
        state, tracker = None, Tracker(params, VOLUME)
        for f in range(frames):
            pose = body.scaled(1.7).zero_pose()
            pose[1], pose[3] = 0.03 * f, -0.4 + 0.05 * f
            pose[body.dof_names.index("l_thigh.flex")] = 0.3 * f
            y, n = sample_ellipsoids(body.scaled(1.7), body.clip(pose), 500, rng, outlier_fraction=0.2)
            _, state = tracker.track(state, SimpleNamespace(points=y, normals=n))
    print(json.dumps({name: {"misses": [str(s) for s in d.stats.cache_misses],
                             "hits": [str(s) for s in d.stats.cache_hits],
                             "indexed": len(d._cache._cache_file._load_index())}
                      for name, d in compiled_cache.dispatchers().items()}))
    print(ahead)
""")


def _env() -> dict:
    """This environment without NUMBA_CACHE_DIR: the cache is numba's default, the one a run uses."""
    return {key: value for key, value in os.environ.items() if key != "NUMBA_CACHE_DIR"}


#: Entry points of `stages.tracking.compiled` that the tracker calls from Python; the others are helpers
#: compiled into them (and cached on their own when they are compiled).
ENTRY_POINTS = ("e_step", "log_evidence", "hypothesis_scores", "shapes", "residuals", "normal_equations",
                "whitened_norm2", "pose_normal_equations", "noisy_covariance",
                "posed_body", "posed_ellipsoids")


def test_after_the_warmup_a_new_process_compiles_nothing():
    command = [sys.executable, "-m", "pipeline", "warmup", "--force"]
    done = subprocess.run(command, cwd=REPO, env=_env(), capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr
    assert "loaded from the cache" in done.stdout
    cache_dir = warmup.default_cache_dir()
    assert warmup.is_fresh(cache_dir, warmup.stamp_key(warmup.compiled_source()))
    again = subprocess.run(command[:-1], cwd=REPO, env=_env(), capture_output=True, text=True, timeout=60)
    assert again.returncode == 0 and again.stdout == ""  # the stamp is fresh: nothing to do

    after = subprocess.run([sys.executable, "-c", _AFTER], cwd=REPO, env=_env(), capture_output=True, text=True,
                           timeout=600)
    assert after.returncode == 0, after.stderr
    *_, line, ahead = after.stdout.strip().splitlines()
    stats = json.loads(line)
    assert set(ENTRY_POINTS) <= set(stats)
    assert {name: s["misses"] for name, s in stats.items() if s["misses"]} == {}  # nothing compiled
    for name in ENTRY_POINTS:  # each loaded from the disk cache, ahead of its first call and only then
        assert len(stats[name]["hits"]) == 1, name
    assert int(ahead) == sum(len(s["hits"]) for s in stats.values())
    for name, s in stats.items():  # helpers too are cached (they are compiled into the entry points)
        assert s["indexed"] >= 1, name
    assert stats["_mixture"]["indexed"] == 2  # with and without posteriors (a literal bool)


def _stamped(folder: Path, key: str, *indexes: str) -> None:
    for name in indexes:
        (folder / name).write_bytes(b"index")
    (folder / warmup.STAMP).write_text(key)


def test_the_stamp_is_fresh_only_for_its_key_and_while_no_index_was_rewritten(tmp_path):
    key = warmup.stamp_key(warmup.compiled_source())
    assert "compiled.py sha256" in key and "numba" in key
    assert not warmup.is_fresh(tmp_path, key)  # no stamp
    _stamped(tmp_path, key)
    assert not warmup.is_fresh(tmp_path, key)  # a stamp but no cache
    _stamped(tmp_path, key, "compiled.e_step-77.py311.nbi", "compiled.shapes-283.py311.nbi")
    assert warmup.is_fresh(tmp_path, key)
    assert not warmup.is_fresh(tmp_path, key.replace("numba", "numba 0.1 not"))
    stamp = tmp_path / warmup.STAMP
    later = stamp.stat().st_mtime_ns + 1_000_000
    os.utime(tmp_path / "compiled.shapes-283.py311.nbi", ns=(later, later))  # numba compiled something since
    assert not warmup.is_fresh(tmp_path, key)
