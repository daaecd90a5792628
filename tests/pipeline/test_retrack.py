"""`pipeline.lab.bench.retrack`: the bench's runs tracked again with other settings, the bench's own untouched."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.cli import main as pipeline_main
from pipeline.evaluate import score_joints
from pipeline.lab.bench import retrack

TINY = Path(__file__).resolve().parents[2] / "data_samples" / "tiny"


@pytest.fixture(scope="module")
def bench(tmp_path_factory) -> Path:
    """A bench folder holding one finished unseen run of the tiny sample."""
    root = tmp_path_factory.mktemp("bench")
    out = root / "unseen" / "tiny"
    assert pipeline_main(["run", str(TINY), "--out", str(out), "-q", "--workers", "1",
                          "--set", "export.report=false"]) == 0
    return root


def files_of(folder: Path) -> dict[Path, tuple[int, int]]:
    return {path: (path.stat().st_mtime_ns, path.stat().st_size) for path in folder.rglob("*") if path.is_file()}


def test_the_runs_are_tracked_again_with_the_settings_and_scored_beside_the_benchs(bench, tmp_path, capsys):
    before = files_of(bench)
    out = tmp_path / "fewer_iterations"
    assert retrack.main(["--bench", str(bench), "--out", str(out), "--workers", "1",
                         "--set", "tracking.max_iterations=1"]) == 0
    table = capsys.readouterr().out
    benchs = score_joints(bench / "unseen" / "tiny", TINY / "groundtruth" / "joints.csv").summary()["mpjpe_mm"]
    again = score_joints(out / "unseen" / "tiny", TINY / "groundtruth" / "joints.csv").summary()["mpjpe_mm"]
    assert f"| unseen | tiny | {benchs:.1f} | {again:.1f} |" in table
    assert "| unseen, mean MPJPE |" in table
    assert "| re-init. after 1st before | after | doubtful before | after |" in table
    assert '"tracking.max_iterations=1"' in (out / retrack.SETTINGS_FILE).read_text()
    assert "max_iterations: 1" in (out / "unseen" / "tiny" / "tracking" / "manifest.json").read_text().replace('"', "")
    assert files_of(bench) == before  # linked, never written through
    assert retrack.main(["--bench", str(bench), "--out", str(out), "--workers", "1"]) == 0  # its own folder again


@pytest.mark.parametrize("where", ["foreign folder", "inside the bench"])
def test_an_out_folder_it_did_not_make_is_refused_and_left_alone(bench, tmp_path, capsys, where):
    out = tmp_path / "mine" if where == "foreign folder" else bench / "retrack"
    if where == "foreign folder":
        out.mkdir()
        (out / "notes.txt").write_text("the user's")
    with pytest.raises(SystemExit) as stopped:
        retrack.main(["--bench", str(bench), "--out", str(out)])
    assert stopped.value.code == 2 and capsys.readouterr().err.startswith("error: --out ")
    assert (out / "notes.txt").read_text() == "the user's" if where == "foreign folder" else not out.exists()


def test_seeds_track_every_run_once_per_seed_and_give_the_mean_and_the_range(bench, tmp_path, capsys):
    out = tmp_path / "seeded"
    assert retrack.main(["--bench", str(bench), "--out", str(out), "--workers", "2", "--seeds", "2"]) == 0
    table = capsys.readouterr().out
    truth = TINY / "groundtruth" / "joints.csv"
    errors = [score_joints(out / "unseen" / f"tiny.seed{seed}", truth).summary()["mpjpe_mm"] for seed in (0, 1)]
    assert f"| {sum(errors) / 2:.1f} | {min(errors):.1f}-{max(errors):.1f} |" in table
    assert "seed: 1" in (out / "unseen" / "tiny.seed1" / "tracking" / "manifest.json").read_text().replace('"', "")
    assert "the mean over tracking.seed 0-1" in table


def test_seeds_beside_a_seed_of_ones_own_are_refused(bench, tmp_path, capsys):
    with pytest.raises(SystemExit) as stopped:
        retrack.main(["--bench", str(bench), "--out", str(tmp_path / "x"), "--seeds", "2", "--set", "tracking.seed=3"])
    assert stopped.value.code == 2 and "--seeds" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
