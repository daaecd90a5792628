"""The silhouette stage's check of the calibration against the silhouettes (`pipeline.graph._check_calibration`)."""

from __future__ import annotations

import json
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
    out = tmp_path / "out"
    main(["run", str(capture), "--out", str(out), "-q"])  # the track may be lost: not what is tested here
    err = capfd.readouterr().err
    assert "calibration check: the silhouettes of cam1 (" in err and "), cam3 (" in err
    assert "cam2 (" not in err and "cam4 (" not in err
    check = json.loads((out / "silhouettes" / "calibration_check.json").read_text())
    assert check["at_fault"] == ["cam1", "cam3"] and check["disagreement_m"]["cam1"] > 0.05
    report = (out / "export" / "report.html").read_text()
    assert report.count("its silhouettes <strong>disagree</strong> with the other cameras'") == 2


def test_a_sound_calibration_passes_the_check_quietly(tmp_path, capfd):
    assert main(["run", str(TINY), "--out", str(tmp_path / "out"), "--to", "silhouettes"]) == 0
    err = capfd.readouterr().err
    assert "calibration check: every camera's silhouettes agree with the others' at the subject within" in err
    assert "cm per camera: cam1 " in err
    assert "disagree" not in err
    check = json.loads((tmp_path / "out" / "silhouettes" / "calibration_check.json").read_text())
    assert check["at_fault"] == [] and all(value < 0.05 for value in check["disagreement_m"].values())
