"""Compile the tracker's inner loops into numba's on-disk cache, so that the first run does not.

Example:
  python -m pipeline warmup           # what scripts/bootstrap.sh runs; nothing to do when the stamp is fresh
  python -m pipeline warmup --force   # run the warm-up even so (loads from the cache what is there)

The tracker's loops (`stages.tracking.compiled`) are ``@njit(cache=True)``: numba compiles each one for
the argument types of its first call, 20-30 s for all of them on 2 cores, and saves the machine
code in its cache, here ``stages/tracking/__pycache__/compiled.*.nbi|nbc`` (or under NUMBA_CACHE_DIR
when that is set), keyed on the content of compiled.py, numba's version, the Python version and the CPU.
Later processes load it from there instead. This command makes those calls with the types
the tracking stage uses: it runs the tracker itself on a few frames of data sampled from the default
body's own ellipsoids (an initialisation, a tracked frame, a limb re-initialisation, and a fit with each
distance), then writes a stamp (:data:`STAMP`) next to numba's cache files. The next call does nothing
while the stamp is fresh (:func:`is_fresh`), so the set-up stays quick.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.metadata
import importlib.util
import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from pipeline.compiled_cache import dispatchers

#: The stamp's file name, in numba's cache directory of `stages.tracking.compiled`.
STAMP = "tracker-warmup.stamp"
#: Working volume of the warm-up's synthetic frames, metres.
VOLUME = np.array([[-2.0, -2.0, 0.0], [2.0, 2.0, 2.3]])
#: Observations per synthetic frame (types, not sizes, decide what numba compiles: a few hundred suffice).
OBSERVATIONS = 300


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--force", action="store_true", help="warm up even when the stamp is fresh")


def compiled_source() -> Path:
    """Path of `stages/tracking/compiled.py`, found without importing it (nor numba)."""
    return Path(importlib.util.find_spec("stages.tracking.compiled").origin)


def default_cache_dir() -> Path | None:
    """Where numba caches `compiled.py`'s functions by default: the ``__pycache__`` beside it (numba's
    in-tree locator, used when that folder is writable). None when NUMBA_CACHE_DIR sends the cache
    elsewhere: the stamp is then not checked and the warm-up always runs (a second or so when cached)."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return None
    return compiled_source().parent / "__pycache__"


def stamp_key(source: Path) -> str:
    """What numba's cache of `source` depends on: its content, numba's and Python's versions, the CPU."""
    cpu = ""
    try:
        cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                    if line.startswith("model name")), "")
    except OSError:
        pass
    return "\n".join([f"compiled.py sha256 {hashlib.sha256(source.read_bytes()).hexdigest()}",
                      f"numba {importlib.metadata.version('numba')}", f"python {platform.python_version()}",
                      f"machine {platform.machine()} {cpu}"]) + "\n"


def is_fresh(cache_dir: Path, key: str) -> bool:
    """Whether the stamp in `cache_dir` says the cache holds the warm-up's code for `key`.

    Fresh when the stamp holds `key` and no index file of numba's (``*.nbi``) is newer than it: numba
    rewrites a function's index when it compiles it, so a newer index means that something compiled
    since the warm-up, possibly for another version of compiled.py (an edit, then undone), which drops
    the cached code of the version the stamp names.
    """
    stamp = cache_dir / STAMP
    try:
        if stamp.read_text() != key:
            return False
        written = stamp.stat().st_mtime_ns
        indexes = list(cache_dir.glob("compiled.*.nbi"))
    except OSError:
        return False
    return bool(indexes) and all(index.stat().st_mtime_ns <= written for index in indexes)


def _observations(body, pose: np.ndarray, rng: np.random.Generator, count: int = OBSERVATIONS) -> SimpleNamespace:
    """Points and outward unit normals on the posed body (`sample_surface`), plus a quarter as many outliers
    uniform in the volume: what a reconstruction of the body would give, as float64 (I, 3) arrays."""
    from stages.tracking.body import sample_surface

    y, n = sample_surface(body, pose, count, rng)
    outliers = count // 4
    y_out = rng.uniform(VOLUME[0], VOLUME[1], (outliers, 3))
    n_out = rng.normal(size=(outliers, 3))
    return SimpleNamespace(points=np.vstack([y, y_out]), normals=np.vstack([n, n_out]))


def warm_up() -> None:
    """Call every compiled function of the tracker with the argument types the tracking stage uses.

    The tracker runs as the tracking stage runs it (`Tracker.track` with the default parameters and the
    default body, height unknown) on two synthetic frames: the first initialises (pose library scoring,
    EM refinement with the height free, limb recovery), the second is tracked (the segment lengths free).
    A limb re-initialisation is then forced (the data decide whether the tracker needs one), and each
    other distance fits once (its own code is numpy; what it shares with the paper's is compiled).
    """
    from stages.tracking.em import fit
    from stages.tracking.limbs import reinitialise_limb
    from stages.tracking.params import TrackerParams
    from stages.tracking.tracker import Tracker

    rng = np.random.default_rng(0)
    params = TrackerParams()
    tracker = Tracker(params, VOLUME)
    body = tracker.body
    poses = []
    for step in range(2):  # standing at the volume's centre, turning, one knee and one elbow bending
        pose = body.zero_pose()
        pose[3] = 0.3 + 0.05 * step
        pose[body.dof_names.index("l_shank.flex")] = 0.4 + 0.1 * step
        pose[body.dof_names.index("r_forearm.flex")] = 0.6 + 0.1 * step
        poses.append(body.clip(pose))
    frames = [_observations(body, pose, rng) for pose in poses]
    state = None
    for obs in frames:
        _, state = tracker.track(state, obs)
    y, n = frames[-1].points, frames[-1].normals / np.linalg.norm(frames[-1].normals, axis=1, keepdims=True)
    sized = body.scaled(state.height_m)
    em = replace(params.em, max_iterations=2)
    fitted = fit(y, n, sized, state.pose, VOLUME, em)
    reinitialise_limb(y, n, fitted, tracker.limbs[0], VOLUME, em, tracker.library)
    for distance in ("points", "algebraic"):
        fit(y, n, sized, state.pose, VOLUME, replace(em, distance=distance, normal_noise_rad=0.0))


def main(args: argparse.Namespace) -> int:
    return ensure_compiled(force=args.force)


def ensure_compiled(*, force: bool = False) -> int:
    """Warm up unless the stamp is fresh (or ``force``); 0 when numba's disk cache now holds the tracker's code.

    Also what the bench calls before it measures anything: a checkout that was never set up (a new
    worktree, a clone run without ``make``) would otherwise compile during its first timed run, and that
    capture's frame rate would be the compiler's.
    """
    source, cache_dir = compiled_source(), default_cache_dir()
    key = stamp_key(source)
    if not force and cache_dir is not None and is_fresh(cache_dir, key):
        return 0
    print("warmup: loading the tracker's compiled code from numba's cache, or compiling it (20-30 s, once)", flush=True)
    started = time.perf_counter()
    warm_up()
    seconds = time.perf_counter() - started
    functions = dispatchers()
    compiled_now = sum(len(d.stats.cache_misses) for d in functions.values())
    loaded = sum(len(d.stats.cache_hits) for d in functions.values())
    cache = getattr(functions["e_step"], "_cache", None)
    where = Path(cache.cache_path) if cache is not None and hasattr(cache, "cache_path") else None
    if where is None:
        print("warmup: numba has no on-disk cache for the tracker's code (is stages/tracking writable?); "
              "each run will compile it", file=sys.stderr)
        return 1
    print(f"warmup: {compiled_now} signatures compiled, {loaded} loaded from the cache, in {seconds:.1f} s ({where})")
    if cache_dir is not None and where.resolve() == cache_dir.resolve():
        (cache_dir / STAMP).write_text(key)
    return 0
