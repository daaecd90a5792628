"""The reconstruction stage's search for parts of a view hidden behind something in front of the subject."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import still_scene as scene
import yaml

from calib.formats import save_rig
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
    root = tmp_path_factory.mktemp("desk") / "capture"
    rig = scene.ring()
    rooms = scene.rooms(rig, seed=2)
    save_rig(rig, "anipose", root / "calibration" / "calibration.toml")
    config = {"fps": 25.0, "calibration": {"format": "anipose", "path": "calibration/calibration.toml"},
              "volume": {"min": scene.VOLUME[0].tolist(), "max": scene.VOLUME[1].tolist()}}
    (root / "capture.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    (root / "background").mkdir()
    for index, (camera, room, images) in enumerate(zip(rig, rooms, scene.frames(rig, rooms, PATH), strict=True)):
        if index == 0:
            room, images = room.copy(), [image.copy() for image in images]
            for image in (room, *images):
                image[DESK_ROW:] = DESK
        cv2.imwrite(str(root / "background" / f"{camera.name}.png"), room)
        folder = root / "images" / camera.name
        folder.mkdir(parents=True)
        for frame, image in enumerate(images):
            cv2.imwrite(str(folder / f"{frame:06d}.png"), image)
    return root


def _lowest_points(out: Path) -> float:
    """The median over frames of each frame's lowest observation's height, metres."""
    return float(np.median([frames_io.read_ply(observations_path(out / "reconstruction", frame))[0][:, 2].min()
                            for frame in range(len(PATH))]))


def test_what_a_desk_hides_from_one_camera_is_found_and_no_longer_carved(capture, tmp_path, capfd):
    out = tmp_path / "out"
    assert main(["run", str(capture), "--out", str(out), "--to", "reconstruction", "-q", "--workers", "1"]) == 0
    err = capfd.readouterr().err
    assert "WARNING" in err and "cam0: " in err and "hides the subject behind something in front of him" in err
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
