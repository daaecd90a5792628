"""The reconstruction stage's search for parts of a view hidden behind something in front of the subject."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import still_scene as scene

from pipeline.cli import main
from pipeline.io import frames_io
from pipeline.io.run_layout import hidden_part_path, observations_path

#: The subject walks a circle around the middle of the volume, ...
PATH = 0.7 * np.column_stack([np.cos(np.linspace(0, 2 * np.pi, 24, endpoint=False)),
                              np.sin(np.linspace(0, 2 * np.pi, 24, endpoint=False))])
#: ... and the first camera sees the lowest rows of its image behind a desk (grey, in its plate and its frames).
DESK_ROW = 75
DESK = (110, 120, 130)


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    rig = scene.ring()
    rooms = scene.rooms(rig, seed=2)
    views = scene.frames(rig, rooms, PATH)
    for image in (rooms[0], *views[0]):  # the desk, in camera 0's plate and frames
        image[DESK_ROW:] = DESK
    return scene.write_capture(tmp_path_factory.mktemp("desk") / "capture", rig, views, rooms)


def _lowest_points(out: Path) -> float:
    """The median over frames of each frame's lowest observation's height, metres."""
    return float(np.median([frames_io.read_ply(observations_path(out / "reconstruction", frame))[0][:, 2].min()
                            for frame in range(len(PATH))]))


def test_what_a_desk_hides_from_one_camera_is_found_and_no_longer_carved(capture, tmp_path, capfd):
    out = tmp_path / "out"
    assert main(["run", str(capture), "--out", str(out), "--to", "reconstruction", "-q", "--workers", "1"]) == 0
    err = capfd.readouterr().err
    assert "WARNING" in err and "cam0: something in front of the subject hides part of him from this camera" in err
    rig = scene.ring()
    hidden = frames_io.read_mask(hidden_part_path(out / "reconstruction", "cam0")) > 0
    behind = np.maximum.reduce([scene.subject_mask(rig[0], centre) for centre in PATH]) > 0
    behind[:DESK_ROW] = False
    assert (hidden & behind).sum() > 0.8 * behind.sum()
    assert not any(hidden_part_path(out / "reconstruction", camera.name).exists() for camera in rig[1:])
    # The desk hides the subject's lower part from cam0 only: the other cameras put observations down to his feet.
    assert _lowest_points(out) < 0.15

    carved = tmp_path / "carved"
    assert main(["run", str(capture), "--out", str(carved), "--to", "reconstruction", "-q", "--workers", "1",
                 "--set", "reconstruction.find_hidden_parts=false"]) == 0
    assert not (carved / "reconstruction" / "hidden").exists()
    assert _lowest_points(carved) > 0.3
