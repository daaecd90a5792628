"""The silhouette stage without clean plates, on captures the tests write: a subject who stands still."""

from __future__ import annotations

import logging
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import still_scene as scene

from pipeline import graph
from pipeline.engine.executors import make_executor
from pipeline.io import frames_io
from pipeline.io.capture import Capture
from pipeline.io.run_layout import background_path, noise_floors_path
from stages.background.plates import shifted_plate
from stages.silhouettes import SilhouetteParams


def _write_capture(root: Path, path: np.ndarray, *, plates: bool = False) -> tuple[Path, list[np.ndarray]]:
    """A capture of the still scene's subject walking ``path`` (F, 2); returns it and the true rooms."""
    rig = scene.ring()
    rooms = scene.rooms(rig, seed=2)
    return scene.write_capture(root, rig, scene.frames(rig, rooms, path), rooms if plates else None), rooms


def test_a_subject_who_stood_still_leaves_no_ghost_and_the_log_says_how(tmp_path, caplog):
    root, rooms = _write_capture(tmp_path / "capture", scene.still_then_moving())
    capture = Capture.open(root)
    with caplog.at_level(logging.INFO, logger="pipeline.graph"):
        estimates = graph.estimated_backgrounds(capture, SilhouetteParams(), {})
    for camera, room in zip(capture.rig, rooms, strict=True):
        ghost = scene.subject_mask(camera, (0.0, 0.0)) > 0
        assert np.abs(estimates[camera.name].image.astype(int) - room)[ghost].max(axis=1).mean() < 4
    assert "the subject left out" in caplog.text and "WARNING" not in caplog.text


def test_the_estimate_spread_over_worker_processes_is_the_estimate_made_here(tmp_path):
    capture = Capture.open(_write_capture(tmp_path / "capture", scene.still_then_moving())[0])
    here = graph.estimated_backgrounds(capture, SilhouetteParams(), {})
    with make_executor(2) as workers:  # the cameras' samples and each round's silhouettes in two processes
        there = graph.estimated_backgrounds(capture, SilhouetteParams(), {}, workers.executor)
    for camera in capture.rig.names:
        np.testing.assert_array_equal(there[camera].image, here[camera].image)
        assert (there[camera].noise, there[camera].rounds) == (here[camera].noise, here[camera].rounds)


def test_a_subject_who_never_leaves_his_spot_is_a_warning_naming_each_camera(tmp_path, caplog):
    swaying = np.column_stack([0.15 * np.sin(np.arange(24)), np.zeros(24)])
    capture = Capture.open(_write_capture(tmp_path / "capture", swaying)[0])
    with caplog.at_level(logging.WARNING, logger="pipeline.graph"):
        graph.estimated_backgrounds(capture, SilhouetteParams(), {})
    warned = [record.getMessage() for record in caplog.records if "could not be separated" in record.getMessage()]
    assert {message.split(":")[1].strip().split()[1] for message in warned} == set(capture.rig.names)


def test_a_subject_who_never_moves_is_a_warning(tmp_path, caplog):
    capture = Capture.open(_write_capture(tmp_path / "capture", np.zeros((12, 2)))[0])
    with caplog.at_level(logging.WARNING, logger="pipeline.graph"):
        graph.estimated_backgrounds(capture, SilhouetteParams(), {})
    assert "no subject found in any of the 12 sampled frames" in caplog.text


@pytest.mark.parametrize("plates", [False, True])
def test_the_stage_writes_backgrounds_and_the_noise_floors_of_estimated_ones(tmp_path, monkeypatch, plates):
    root, rooms = _write_capture(tmp_path / "capture", scene.still_then_moving(16, 6), plates=plates)
    out = tmp_path / "run"

    context = SimpleNamespace(capture=Capture.open(root), out_dir=out, params=SilhouetteParams(),  # what it reads
                              workers=SimpleNamespace(executor=None))
    floors = graph._backgrounds(context)
    names = context.capture.rig.names
    assert all(frames_io.file_problem(background_path(out, camera)) is None for camera in names)
    if plates:
        assert floors == {} and not noise_floors_path(out).exists()
        assert all(np.array_equal(frames_io.read_image(background_path(out, c)), room)
                   for c, room in zip(names, rooms, strict=True))
        return
    assert frames_io.read_json(noise_floors_path(out)) == floors and set(floors) == set(names)
    assert all(0.5 <= floor <= 6.0 for floor in floors.values())
    monkeypatch.setattr(graph, "estimated_backgrounds", None)  # a resumed run reads what is there
    assert graph._backgrounds(context) == floors


def test_a_plate_off_its_frames_is_shifted_onto_them_and_another_views_plate_is_left_out(tmp_path, caplog):
    root, rooms = _write_capture(tmp_path / "capture", scene.still_then_moving(16, 6), plates=True)
    names = Capture.open(root).rig.names
    moved = root / "background" / f"{names[0]}.png"  # taken before the camera was knocked 3 pixels aside
    cv2.imwrite(str(moved), shifted_plate(rooms[0], (3.0, -2.0)))
    (root / "background" / f"{names[1]}.png").write_bytes((root / "background" / f"{names[2]}.png").read_bytes())
    out = tmp_path / "run"
    context = SimpleNamespace(capture=Capture.open(root), out_dir=out, params=SilhouetteParams(),
                              workers=SimpleNamespace(executor=None))
    with caplog.at_level(logging.WARNING, logger="pipeline.graph"):
        floors = graph._backgrounds(context)
    assert f"the clean plate lies 3.6 pixels off camera {names[0]}'s frames (x -3.1, y +1.8" in caplog.text
    inner = (slice(4, -4), slice(4, -4))  # the strip the shift uncovered holds the plate's edge pixels
    background = frames_io.read_image(background_path(out, names[0])).astype(int)
    assert np.abs(background - rooms[0])[inner].mean() < 1.0
    assert f"the clean plate does not show camera {names[1]}'s view" in caplog.text
    assert set(floors) == {names[1]}  # estimated from the frames, as without a plate
    assert frames_io.read_image(background_path(out, names[2])).tobytes() == rooms[2].tobytes()
