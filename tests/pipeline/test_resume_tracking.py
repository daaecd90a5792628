"""A run killed while the tracking streams alongside the reconstruction keeps its tracked frames (issue #13
item 8): the next run resumes the tracking from the state in its last good frame's record, and the result
is identical to that of a run never interrupted."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline.cli import INTERRUPTED, main
from pipeline.io.run_layout import JOINTS_FILE, MANIFEST
from stages.tracking.tracker import Tracker

TINY = Path(__file__).resolve().parents[2] / "data_samples" / "tiny"
TRACKED_BEFORE_THE_KILL = 3


def run(out: Path) -> int:
    return main(["run", str(TINY), "--out", str(out), "-q", "--workers", "1", "--set", "export.report=false"])


def kill_after(monkeypatch, calls: int) -> None:
    """Make the tracker raise KeyboardInterrupt (a Ctrl-C; a SIGKILL leaves the same files) on call ``calls + 1``."""
    track, done = Tracker.track, []

    def counting(*args, **kwargs):
        if len(done) == calls:
            raise KeyboardInterrupt
        done.append(None)
        return track(*args, **kwargs)

    monkeypatch.setattr(Tracker, "track", counting)


def tracked_frames(out: Path) -> int:
    return json.loads((out / "tracking" / MANIFEST).read_text())["timing"]["frames"]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> bytes:
    out = tmp_path_factory.mktemp("uninterrupted") / "out"
    assert run(out) == 0
    return (out / "export" / JOINTS_FILE).read_bytes()


@pytest.mark.parametrize("reconstruction_finished", [True, False])
def test_a_killed_tracking_resumes_from_its_last_frame_with_the_same_result(
        tmp_path, monkeypatch, uninterrupted, reconstruction_finished):
    out = tmp_path / "out"
    kill_after(monkeypatch, TRACKED_BEFORE_THE_KILL)
    assert run(out) == INTERRUPTED  # one line, no traceback (tests/pipeline/test_cli.py)
    kept = sorted((out / "tracking" / "frames").glob("*.json"))
    assert len(kept) == TRACKED_BEFORE_THE_KILL and not (out / "tracking" / MANIFEST).exists()
    observations = sorted((out / "reconstruction").glob("*.ply"))
    if not reconstruction_finished:  # the kill hit both: the reconstruction's later frames are missing too
        (out / "reconstruction" / MANIFEST).unlink()
        for path in observations[TRACKED_BEFORE_THE_KILL + 1:]:
            path.unlink()
    monkeypatch.undo()
    assert run(out) == 0
    assert tracked_frames(out) == len(observations) - TRACKED_BEFORE_THE_KILL
    assert all(path.exists() for path in kept)
    assert (out / "export" / JOINTS_FILE).read_bytes() == uninterrupted
