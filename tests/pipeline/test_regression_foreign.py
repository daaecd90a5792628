"""End-to-end regression on a capture made by another program: the first 20 frames of the foreign ``walk``.

The bundled samples come from the project's own renderer; this cut of ``<repo>/../shared/foreign/walk`` (5
cameras 640x480, mp4, an independent body, room and noise) catches a change that only works on those. The
folder is shared, not bundled, so the test is skipped where it is absent. Accuracy on the whole foreign
captures is measured by ``python -m pipeline bench --suite foreign``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.cli import main
from pipeline.evaluate import evaluate_run
from pipeline.lab.bench.foreign import true_masks_row
from pipeline.lab.bench.speed import prefix_view

#: The tolerance of this regression test: MPJPE of the 20-frame cut, mm, a few mm above what it measures.
MPJPE_TOLERANCE_MM = 32.0
#: The foreign capture the cut is taken from, and the cut's length.
WALK = Path(__file__).resolve().parents[3] / "shared" / "foreign" / "walk"
FRAMES = 20


@pytest.fixture
def walk_cut(tmp_path) -> Path:
    """A capture folder showing the first :data:`FRAMES` frames of ``walk`` (the bench's prefix view: its
    media by symlink, its calibration copied, its capture.yaml with a ``frames`` range)."""
    if not (WALK / "capture.yaml").is_file():
        pytest.skip(f"no foreign capture {WALK} (the shared folder of captures made by another program)")
    return prefix_view(WALK, tmp_path / "walk20", FRAMES)


def test_foreign_walk_cut_is_tracked_with_its_silhouettes_and_with_the_true_masks(walk_cut, tmp_path):
    """The whole pipeline on 20 frames of 5 videos, then scored: about 5 s on 2 shared cores. Then the foreign
    suite's second look, the run redone from its reconstruction with the true masks as silhouettes, in a copy."""
    out = tmp_path / "out"
    assert main(["run", str(walk_cut), "--out", str(out), "--workers", "1", "-q"]) == 0
    metrics = evaluate_run(out, truth=walk_cut / "groundtruth" / "joints.csv")
    assert metrics["truth_frames"] == FRAMES and metrics["fraction_estimated"] == 1.0
    assert metrics["mpjpe_mm"] <= MPJPE_TOLERANCE_MM
    joints = (out / "export" / "joints.csv").read_bytes()
    row = true_masks_row(walk_cut, out, tmp_path / "true-masks", workers=1)
    assert row["mpjpe_true_masks_mm"] <= min(MPJPE_TOLERANCE_MM, row["worst_true_masks_mm"])
    copied = tmp_path / "true-masks" / "silhouettes" / "cam00" / "000000.png"
    assert copied.read_bytes() == (WALK / "groundtruth" / "masks" / "cam00" / "000000.png").read_bytes()
    assert (out / "export" / "joints.csv").read_bytes() == joints  # the run itself untouched
