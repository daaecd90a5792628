"""Speed suite: is the whole pipeline faster than real time in the paper's studio, and is its memory flat?

On the :data:`~pipeline.lab.bench.recipes.SPEED` capture (6 cameras, 780 x 580, 28 frames/s, mp4 video):

1. end to end: ``python -m pipeline run`` on a fresh output directory with 2 workers, timed from the
   outside (interpreter start and video decoding included): frames per second, and each stage's
   milliseconds per frame from its manifest;
2. memory: the same run on the first third of the capture (a view of the same files whose capture.yaml
   stops early): peak resident memory of the short and the long run; streaming stages keep it flat;
3. the tracker alone: ``Tracker.track`` in this process over the long run's observation files (about 1000
   observations a frame), frames per second over all frames (initialisation and recoveries included) and
   over tracked frames only, after one uncounted call that loads the compiled code.
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
import yaml

from pipeline.io import frames_io
from pipeline.io.capture import Capture
from pipeline.io.run_layout import RunLayout
from pipeline.lab.bench.recipes import SPEED, describe, ensure_capture
from pipeline.lab.bench.runs import RunMeasure, run_pipeline
from stages.reconstruction import Observations
from stages.tracking.params import TrackerParams
from stages.tracking.tracker import Tracker

#: Length of the short run for the memory check, as a fraction of the capture (2 s of 6 s).
SHORT_FRACTION = 1.0 / 3.0
#: At most this many frames are tracked again in-process for the tracker's own speed.
TRACKER_FRAMES = 100


def prefix_view(capture: Path, view: Path, stop: int) -> Path:
    """A capture directory ``view`` showing the first ``stop`` frames of ``capture`` (`capture_view` with
    ``frames.stop`` set)."""
    frames = yaml.safe_load((Path(capture) / "capture.yaml").read_text()).get("frames") or {}
    return capture_view(capture, view, frames={**frames, "start": 0, "stop": int(stop), "step": 1})


def capture_view(capture: Path, view: Path, **changes) -> Path:
    """A capture directory ``view`` showing ``capture`` with capture.yaml's top-level keys ``changes`` replaced: the
    same media (symlinks), a copy of its calibration (a calibration reached through a link leads outside the
    capture, which a run refuses). Rebuilt on every call (cheap), so it always follows ``capture``."""
    shutil.rmtree(view, ignore_errors=True)
    view.mkdir(parents=True)
    config = yaml.safe_load((Path(capture) / "capture.yaml").read_text())
    calibration = Path(config["calibration"]["path"]).parts[0]  # the capture's entry that holds it
    for entry in Path(capture).iterdir():
        if entry.name == calibration:
            (shutil.copytree if entry.is_dir() else shutil.copy2)(entry, view / entry.name)
        elif entry.name != "capture.yaml":
            (view / entry.name).symlink_to(entry.resolve())
    (view / "capture.yaml").write_text(yaml.safe_dump(config | changes, sort_keys=False))
    return view


def ms_per_frame(measure: RunMeasure) -> dict[str, float]:
    """Each stage's milliseconds per frame of the capture (setup stages spread over the frames too)."""
    return {stage: 1000.0 * seconds / measure.frames for stage, seconds in measure.stage_seconds.items()}


def tracker_speed(run_dir: Path, capture: Capture, frames: list[int]) -> dict:
    """Time ``Tracker.track`` over a run's observations, as the tracking stage calls it (height as given).

    A first call, on the first frame and not counted, builds the tracker and loads the compiled inner
    loops (numba's runtime and on-disk cache: a fixed cost per process, reported as ``ms_first_call``);
    the frames are then tracked from scratch, initialisation included.
    """
    params = TrackerParams(height_m=capture.height_m)
    observations = [frames_io.read_ply(RunLayout(run_dir).observations(frame)) for frame in frames]
    started = time.perf_counter()
    tracker = Tracker(params, capture.volume)
    tracker.track(None, Observations(*observations[0]))
    first_call = time.perf_counter() - started
    state, seconds, statuses, counts = None, [], [], []
    cpu_started = time.process_time()
    for points, normals in observations:
        started = time.perf_counter()
        result, state = tracker.track(state, Observations(points, normals))
        seconds.append(time.perf_counter() - started)
        statuses.append(result.status)
        counts.append(len(points))
    cpu_seconds = time.process_time() - cpu_started
    seconds, statuses = np.array(seconds), np.array(statuses)
    tracked = statuses == "tracked"
    return {
        "frames": len(frames),
        "observations_mean": float(np.mean(counts)),
        "fps_tracked": float(tracked.sum() / seconds[tracked].sum()) if tracked.any() else 0.0,
        "fps_all": float(len(seconds) / seconds.sum()),
        "fps_all_cpu": float(len(seconds) / cpu_seconds),
        "ms_tracked_median": float(1000.0 * np.median(seconds[tracked])) if tracked.any() else float("nan"),
        "ms_tracked_p90": float(1000.0 * np.percentile(seconds[tracked], 90)) if tracked.any() else float("nan"),
        "ms_initialisation": float(1000.0 * seconds[~tracked].mean()) if (~tracked).any() else 0.0,
        "ms_first_call": 1000.0 * first_call,
        "statuses": {str(s): int((statuses == s).sum()) for s in np.unique(statuses)},
    }


def run_speed(out: Path, captures: Path, *, quick: bool, workers: int) -> dict:
    """The speed suite's results (see the module docstring); runs go to ``<out>/speed/``."""
    recipe = SPEED.quick() if quick else SPEED
    path = ensure_capture(captures, recipe)
    capture = Capture.open(path)
    n_frames = len(capture.frame_numbers)
    n_short = max(2, int(round(n_frames * SHORT_FRACTION)))
    short_view = prefix_view(path, out / "speed" / "short-capture", n_short)
    short = run_pipeline(short_view, out / "speed" / "short", workers=workers, frames=n_short, fresh=True)
    long = run_pipeline(path, out / "speed" / "long", workers=workers, frames=n_frames, fresh=True)
    result = {
        "capture": recipe.name, "recipe": describe(recipe), "fps_capture": capture.fps, "workers": workers,
        "frames": n_frames, "short_frames": n_short, "long": long.to_dict(), "short": short.to_dict(),
        "fps_end_to_end": n_frames / long.seconds if long.ok else float("nan"),
        "stage_ms_per_frame": ms_per_frame(long),
        "memory_ratio": long.peak_rss_mb / short.peak_rss_mb if short.peak_rss_mb else float("nan"),
    }
    if long.ok:
        result["tracker"] = tracker_speed(out / "speed" / "long", capture,
                                          list(capture.frame_numbers[:TRACKER_FRAMES]))
    return result
