"""The reconstruction stage's refinement of the cameras' orientations from the silhouettes
(`pipeline.graph.refined_rig`)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import yaml

from calib.camera import Rig
from calib.formats import load_rig, save_rig
from pipeline import frame_tasks, graph
from pipeline.cli import main
from pipeline.io.capture import Capture
from pipeline.report.page import _refinement_note
from stages.tangency import turned

TINY = Path(__file__).resolve().parents[2] / "data_samples" / "tiny"


def _with_turned_calibration(tmp_path: Path, degrees: float) -> Path:
    """A copy of tiny whose calibration has every camera turned by ``degrees`` about an axis of its own."""
    capture = tmp_path / "tiny"
    shutil.copytree(TINY, capture)
    rig = Capture.open(TINY).rig
    axes = np.random.default_rng(0).normal(size=(len(rig), 3))
    cameras = [turned(camera, np.radians(degrees) * axis / np.linalg.norm(axis))
               for camera, axis in zip(rig, axes, strict=True)]
    path = capture / yaml.safe_load((capture / "capture.yaml").read_text())["calibration"]["path"]
    path.unlink()
    save_rig(Rig(tuple(cameras)), "anipose", path)
    return capture


def test_cameras_turned_since_their_calibration_are_refined_and_written(tmp_path, capfd):
    capture = _with_turned_calibration(tmp_path, 0.5)
    out = tmp_path / "out"
    # Two workers: the refinement is measured in one of them (`pipeline.frame_tasks.refinement_task`).
    assert main(["run", str(capture), "--out", str(out), "--workers", "2"]) == 0
    assert "calibration refined from the silhouettes: cameras turned by cam1 " in capfd.readouterr().err
    refinement = json.loads((out / "reconstruction" / "calibration_refinement.json").read_text())
    assert refinement["kept"] and refinement["disagreement_after_m"] < 0.7 * refinement["disagreement_before_m"]
    assert refinement["explained_after"] > refinement["explained_before"]
    assert all(0.0 < turn < 1.0 for turn in refinement["turns_deg"].values())
    refined = load_rig("anipose", out / "reconstruction" / "rig_refined.toml")
    given = Capture.open(capture).rig
    assert refined.names == given.names
    assert all(np.allclose(new.centre, old.centre) and not np.allclose(new.R, old.R)
               for new, old in zip(refined, given, strict=True))
    # The report's stills are drawn with the cameras the reconstruction used, and say so.
    report = (out / "export" / "report.html").read_text()
    assert report.count("Calibration refined from the silhouettes: turned by") == len(given)
    assert report.count("Calibration refined from the silhouettes: each camera turned about its centre") == 1
    assert report.count("reconstruction/rig_refined.toml") == 1  # named once, above the cameras


def test_a_sound_calibration_is_used_as_it_is(tmp_path):
    out = tmp_path / "out"
    assert main(["run", str(TINY), "--out", str(out), "--to", "reconstruction", "-q"]) == 0
    refinement = json.loads((out / "reconstruction" / "calibration_refinement.json").read_text())
    assert not refinement["kept"] and refinement["tangencies"] > 0
    assert not (out / "reconstruction" / "rig_refined.toml").exists()


def test_the_refinement_can_be_turned_off(tmp_path):
    capture = _with_turned_calibration(tmp_path, 0.5)
    out = tmp_path / "out"
    assert main(["run", str(capture), "--out", str(out), "--to", "reconstruction", "-q",
                 "--set", "reconstruction.refine_calibration=false"]) == 0
    assert not (out / "reconstruction" / "calibration_refinement.json").exists()
    assert not (out / "reconstruction" / "rig_refined.toml").exists()


def test_turns_that_leave_the_silhouettes_less_explained_are_not_kept(tmp_path, monkeypatch, capfd):
    # Cameras moved rather than turned: the tangencies can agree better after turns while the rays through the
    # silhouettes meet less well. The visual hull's share of the silhouettes decides (here made to fall).
    capture = _with_turned_calibration(tmp_path, 0.5)
    out = tmp_path / "out"
    assert main(["run", str(capture), "--out", str(out), "--to", "silhouettes", "-q"]) == 0
    opened = Capture.open(capture)
    given = opened.rig["cam1"].R
    monkeypatch.setattr(frame_tasks, "explained_share",  # the rig as given explains 90 %, turned 80 %
                        lambda masks, cameras, *args, **kwargs: 0.9 if np.array_equal(cameras[0].R, given) else 0.8)
    (out / "reconstruction").mkdir()
    assert graph.refined_rig(opened, out / "silhouettes", out / "reconstruction", 0) is opened.rig
    refinement = json.loads((out / "reconstruction" / "calibration_refinement.json").read_text())
    assert refinement["tangencies_agree"] and not refinement["kept"]
    assert refinement["explained_before"] > refinement["explained_after"]
    assert not (out / "reconstruction" / "rig_refined.toml").exists()
    assert "calibration not refined: turning the cameras by cam1 " in capfd.readouterr().err
    # The report says so too (its camera sections note no turn: none was kept).
    note = _refinement_note(refinement, "reconstruction/rig_refined.toml")
    assert "Calibration <strong>not refined</strong>" in note and "90.0 → 80.0 %" in note
