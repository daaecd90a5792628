"""The silhouette stage's check of the calibration against the silhouettes (`pipeline.graph._check_calibration`)."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np

from calib.camera import Rig
from pipeline.cli import main
from pipeline.graph import _check_calibration
from pipeline.io.capture import Capture

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


def test_with_two_cameras_a_disagreement_names_both(tmp_path, capfd):
    # Two cameras cannot say which of them is off: a disagreement names both, rather than passing.
    out = tmp_path / "out"
    assert main(["run", str(TINY), "--out", str(out), "--to", "silhouettes", "-q"]) == 0
    capture = Capture.open(TINY)
    first, second = capture.rig["cam1"], capture.rig["cam3"]
    turn, _ = cv2.Rodrigues(np.radians(3.0) * np.array([0.0, 0.6, 0.8]))
    turned = replace(second, R=turn @ second.R, t=-(turn @ second.R) @ second.centre)
    pair = SimpleNamespace(rig=Rig((first, turned)), frame_numbers=capture.frame_numbers, volume=capture.volume)
    capfd.readouterr()
    _check_calibration(pair, out / "silhouettes")  # the run's terminal handler prints the log
    err = capfd.readouterr().err
    assert "WARNING pipeline.graph: calibration check: the silhouettes of cam1 (" in err and "), cam3 (" in err


def test_a_camera_whose_silhouettes_reach_the_border_is_named_as_not_checked(tmp_path, capfd):
    out = tmp_path / "out"
    assert main(["run", str(TINY), "--out", str(out), "--to", "silhouettes", "-q"]) == 0
    for path in sorted((out / "silhouettes" / "cam2").glob("*.png")):
        mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        mask[-1] = 255  # the subject cut off by the image's bottom edge
        cv2.imwrite(str(path), mask)
    capfd.readouterr()
    _check_calibration(Capture.open(TINY), out / "silhouettes")
    err = capfd.readouterr().err
    assert "not checked: cam2, whose silhouettes were empty or reached the image's border" in err
    assert json.loads((out / "silhouettes" / "calibration_check.json").read_text())["disagreement_m"]["cam2"] is None
    assert main(["run", str(TINY), "--out", str(out), "--from", "reconstruction", "-q"]) == 0
    report = (out / "export" / "report.html").read_text()
    assert report.count("Calibration check: not checked") == 1
