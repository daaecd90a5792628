"""The silhouette stage's check of the calibration against the silhouettes (`pipeline.graph._check_calibration`)."""

from __future__ import annotations

import shutil
from pathlib import Path

from pipeline.cli import main

TINY = Path(__file__).resolve().parents[2] / "data_samples" / "tiny"


def _swap(capture: Path, first: str, second: str) -> None:
    """Exchange two cameras' images and plates: the calibration then has their names swapped."""
    for folder, suffix in (("images", ""), ("background", ".png")):
        a, b, spare = (capture / folder / f"{name}{suffix}" for name in (first, second, "spare"))
        a.rename(spare)
        b.rename(a)
        spare.rename(b)


def test_two_cameras_with_their_names_swapped_are_named(tmp_path, capfd):
    capture = tmp_path / "tiny"
    shutil.copytree(TINY, capture)
    _swap(capture, "cam1", "cam3")
    assert main(["run", str(capture), "--out", str(tmp_path / "out"), "--to", "silhouettes", "-q"]) == 0
    err = capfd.readouterr().err
    assert "calibration check: the silhouettes of cam1 (" in err and "), cam3 (" in err
    assert "cam2 (" not in err and "cam4 (" not in err


def test_a_sound_calibration_passes_the_check_quietly(tmp_path, capfd):
    assert main(["run", str(TINY), "--out", str(tmp_path / "out"), "--to", "silhouettes"]) == 0
    err = capfd.readouterr().err
    assert "calibration check: every camera's silhouettes agree with the others' at the subject within" in err
    assert "cm per camera: cam1 " in err
    assert "disagree" not in err
