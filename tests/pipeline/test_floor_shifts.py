"""The silhouette stage's shifts of the floor test, measured on the shadows when the calibration maps the floor off
where the views see it (`pipeline.graph.masks_with_floor_shifts`)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import shadow_studio as studio
import still_scene

from calib.camera import Rig
from pipeline import frame_tasks
from pipeline.cli import main
from pipeline.io import frames_io
from pipeline.io.run_layout import silhouette_path

FRAMES = 5


@pytest.fixture(scope="module")
def studio_views(tmp_path_factory):
    """The studio's cameras, their plates, frames and true masks: a person in clothing of the floor's hue, darker
    than it, so that the floor test decides what is shadow."""
    rng = np.random.default_rng(21)
    cameras = studio.ring(5)
    # Each view's walls and floor stained alike in its plate and frames (a plain room gives the plates' check nothing
    # to match): the stains scale the levels, not the darkening a shadow brings.
    stains = [cv2.resize(rng.uniform(0.6, 1.4, (29, 39, 1)), (studio.WIDTH, studio.HEIGHT))[:, :, None]
              for _ in cameras]

    def stained(image, stain):
        return np.clip(image * stain, 0, 255).astype(np.uint8)

    plates = [stained(studio.render(camera, None, rng)[0], stain) for camera, stain in zip(cameras, stains,
                                                                                          strict=True)]
    rendered = [[(stained(image, stain), truth) for image, truth in
                 (studio.render(camera, 0.55 * studio.FLOOR, rng) for _ in range(FRAMES))]
                for camera, stain in zip(cameras, stains, strict=True)]
    return cameras, plates, rendered


def _capture(root: Path, cameras, plates, rendered) -> Path:
    return still_scene.write_capture(root, Rig(tuple(cameras)), [[image for image, _ in views] for views in rendered],
                                     plates)


def _held_outside(out: Path, cameras, rendered) -> float:
    """The share of the masks' pixels outside the person (his shadow, kept as his feet), over every view and frame."""
    outside, held = 0, 0
    for camera, views in zip(cameras, rendered, strict=True):
        for frame, (_, truth) in enumerate(views):
            mask = frames_io.read_mask(silhouette_path(out / "silhouettes", camera.name, frame)) > 0
            outside += int((mask & (truth == 0)).sum())
            held += int(mask.sum())
    return outside / held


def test_a_calibration_off_by_centimetres_has_the_floor_test_shifted(studio_views, tmp_path, capfd, monkeypatch):
    cameras, plates, rendered = studio_views
    sound = _capture(tmp_path / "sound", cameras, plates, rendered)
    assert main(["run", str(sound), "--out", str(tmp_path / "sound-out"), "--to", "silhouettes", "--workers", "1"]) == 0
    assert "floor test compares" not in capfd.readouterr().err
    shifts = json.loads((tmp_path / "sound-out" / "silhouettes" / "floor_shifts.json").read_text())
    assert shifts["frames"] == list(range(4)) and len(shifts["shifts_px"]) == 5
    assert all(shift == [0, 0] for row in shifts["shifts_px"].values() for shift in row.values())
    assert _held_outside(tmp_path / "sound-out", cameras, rendered) < 0.005

    # Every camera calibrated 10 cm off where it stands, each in a direction of its own; the images are the same.
    directions = np.random.default_rng(5).normal(size=(len(cameras), 3))
    moved = [dataclasses.replace(camera, t=-camera.R @ (camera.centre + 0.1 * d / np.linalg.norm(d)))
             for camera, d in zip(cameras, directions, strict=True)]
    off = _capture(tmp_path / "off", moved, plates, rendered)
    assert main(["run", str(off), "--out", str(tmp_path / "off-out"), "--to", "silhouettes", "--workers", "1"]) == 0
    assert "INFO pipeline.graph: silhouettes: the floor test compares " in capfd.readouterr().err
    shifts = json.loads((tmp_path / "off-out" / "silhouettes" / "floor_shifts.json").read_text())["shifts_px"]
    assert sum(shift != [0, 0] for row in shifts.values() for shift in row.values()) >= 8
    assert _held_outside(tmp_path / "off-out", cameras, rendered) < 0.005

    # The same run with the shifts left out (in this process: one worker): the shadows stay with the feet.
    monkeypatch.setattr(frame_tasks, "floor_shifts", lambda frames, floor, params: np.zeros((5, 5, 2), int))
    assert main(["run", str(off), "--out", str(tmp_path / "unshifted"), "--to", "silhouettes", "--workers", "1"]) == 0
    assert _held_outside(tmp_path / "unshifted", cameras, rendered) > 0.02


def _masks(out: Path) -> dict:
    return {path.relative_to(out): path.read_bytes() for path in sorted((out / "silhouettes").rglob("*.png"))}


def _moved_capture(root: Path, studio_views) -> Path:
    cameras, plates, rendered = studio_views
    directions = np.random.default_rng(5).normal(size=(len(cameras), 3))
    moved = [dataclasses.replace(camera, t=-camera.R @ (camera.centre + 0.1 * d / np.linalg.norm(d)))
             for camera, d in zip(cameras, directions, strict=True)]
    return _capture(root, moved, plates, rendered)


@pytest.mark.parametrize("calibration", ["sound", "off"])
def test_masks_made_ahead_of_the_shifts_are_the_masks_made_after_them(studio_views, tmp_path, calibration):
    # Two workers: the second makes its share of the frames before the shifts are known, as if none were needed,
    # and makes them again when one is taken. The masks are those one worker makes after the shifts.
    cameras, plates, rendered = studio_views
    capture = (_capture(tmp_path / "capture", cameras, plates, rendered) if calibration == "sound"
               else _moved_capture(tmp_path / "capture", studio_views))
    for workers in ("1", "2"):
        assert main(["run", str(capture), "--out", str(tmp_path / workers), "--to", "silhouettes", "-q",
                     "--workers", workers]) == 0
    assert _masks(tmp_path / "1") == _masks(tmp_path / "2")
    assert not (tmp_path / "2" / "silhouettes" / "masks_ahead_of_floor_shifts.json").exists()


def test_a_run_stopped_before_the_shifts_were_decided_makes_the_masks_ahead_of_them_again(studio_views, tmp_path):
    capture = _moved_capture(tmp_path / "capture", studio_views)
    out = tmp_path / "out"
    assert main(["run", str(capture), "--out", str(out), "--to", "silhouettes", "-q", "--workers", "1"]) == 0
    made = _masks(out)
    # As a stop would leave it: frames 3 and 4 made as if no shift were needed, listed, the stage unfinished.
    stage = out / "silhouettes"
    (stage / "manifest.json").unlink()
    (stage / "masks_ahead_of_floor_shifts.json").write_text(json.dumps({"frames": [3, 4]}))
    for frame in (3, 4):
        for camera in studio_views[0]:
            frames_io.write_mask(silhouette_path(stage, camera.name, frame),
                                 np.zeros((studio.HEIGHT, studio.WIDTH), np.uint8))
    assert main(["run", str(capture), "--out", str(out), "--to", "silhouettes", "-q", "--workers", "1"]) == 0
    assert _masks(out) == made
    assert not (stage / "masks_ahead_of_floor_shifts.json").exists()
