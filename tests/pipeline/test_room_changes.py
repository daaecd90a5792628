"""The silhouette stage's search for parts of the room changed since the clean plates were taken."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import still_scene as scene

from pipeline.cli import main
from pipeline.io import frames_io
from pipeline.io.run_layout import background_path, observations_path, room_change_path, silhouette_path

#: The subject walks a circle around the middle of the volume, ...
PATH = 0.6 * np.column_stack([np.cos(np.linspace(0, 2 * np.pi, 24, endpoint=False)),
                              np.sin(np.linspace(0, 2 * np.pi, 24, endpoint=False))])
#: ... and a box stands by the wall, put there after the plates were taken (centre and semi-axes, metres; colour).
BOX_CENTRE, BOX_AXES, BOX_COLOUR = np.array([-1.05, -0.9, 0.3]), np.array([0.2, 0.2, 0.3]), (150, 170, 60)


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    rig = scene.ring()
    rooms = scene.rooms(rig, seed=3)
    rng = np.random.default_rng(4)
    views = []
    for camera, room in zip(rig, rooms, strict=True):
        box = scene.ellipsoid_mask(camera, BOX_CENTRE, BOX_AXES) > 0
        box_nearer = np.linalg.norm(camera.centre - BOX_CENTRE)
        images = []
        for centre in PATH:
            image = room.astype(np.float32)
            person = scene.subject_mask(camera, centre) > 0
            in_front = np.linalg.norm(camera.centre[:2] - centre) < box_nearer
            for region, colour in ((box, BOX_COLOUR), (person, scene.COLOUR))[:: 1 if in_front else -1]:
                image[region] = colour
            image += rng.normal(0.0, scene.NOISE_SIGMA, image.shape)
            images.append(np.clip(image, 0, 255).round().astype(np.uint8))
        views.append(images)
    return scene.write_capture(tmp_path_factory.mktemp("box") / "capture", rig, views, rooms)


def _box_share(out: Path) -> float:
    """The share of the box's pixels that the silhouettes hold, over every camera and frame where the subject is
    apart from it."""
    held, total = 0, 0
    for camera in scene.ring():
        box = scene.ellipsoid_mask(camera, BOX_CENTRE, BOX_AXES) > 0
        for frame, centre in enumerate(PATH):
            if (scene.subject_mask(camera, centre) > 0)[box].any():
                continue
            mask = frames_io.read_mask(silhouette_path(out / "silhouettes", camera.name, frame)) > 0
            held += int(mask[box].sum())
            total += int(box.sum())
    return held / total


def test_a_box_put_down_after_the_plates_is_taken_into_the_backgrounds(capture, tmp_path, capfd):
    out = tmp_path / "out"
    assert main(["run", str(capture), "--out", str(out), "--to", "silhouettes", "-q", "--workers", "1"]) == 0
    err = capfd.readouterr().err
    mended = [camera.name for camera in scene.ring() if any(
        f"camera {camera.name}: " in line and "differs from its clean plate in nearly every frame" in line
        for line in err.splitlines())]
    assert len(mended) >= 3
    assert _box_share(out) < 0.05
    rig = scene.ring()
    for frame, centre in enumerate(PATH):  # the subject is all there
        for camera in rig:
            mask = frames_io.read_mask(silhouette_path(out / "silhouettes", camera.name, frame)) > 0
            person = scene.subject_mask(camera, centre) > 0
            assert (mask & person).sum() > 0.95 * person.sum()
    plate = frames_io.read_image(capture / "background" / f"{mended[0]}.png")
    assert not np.array_equal(frames_io.read_image(background_path(out / "silhouettes", mended[0])), plate)
    for camera in rig:  # where the box stands, that camera will not carve
        path = room_change_path(out / "silhouettes", camera.name)
        assert path.exists() == (camera.name in mended)
        if path.exists():
            box = scene.ellipsoid_mask(camera, BOX_CENTRE, BOX_AXES) > 0
            assert (frames_io.read_mask(path) > 0)[box].mean() > 0.95

    kept = tmp_path / "kept"
    assert main(["run", str(capture), "--out", str(kept), "--to", "silhouettes", "-q", "--workers", "1",
                 "--set", "silhouettes.find_room_changes=false"]) == 0
    assert "differs from its clean plate" not in capfd.readouterr().err
    assert _box_share(kept) > 0.9
    assert not (kept / "silhouettes" / "room_changes").exists()


def test_a_run_stopped_while_the_silhouettes_are_made_again_starts_the_stage_over(capture, tmp_path):
    out = tmp_path / "out"
    assert main(["run", str(capture), "--out", str(out), "--to", "silhouettes", "-q", "--workers", "1"]) == 0
    stage = out / "silhouettes"
    made = {path.relative_to(stage): path.read_bytes() for path in stage.rglob("*.png")}
    # As a stop would leave it: the backgrounds mended (one of them half written over), a few masks of the
    # second pass written and the others still the first pass's, no manifest.
    (stage / "manifest.json").unlink()
    (stage / "remaking").write_text("")
    first = scene.ring()[0].name
    background = frames_io.read_image(background_path(stage, first))
    frames_io.write_image(background_path(stage, first), background // 2)
    for frame in range(5):
        silhouette_path(stage, first, frame).unlink()
    assert main(["run", str(capture), "--out", str(out), "--to", "silhouettes", "-q", "--workers", "1"]) == 0
    assert not (stage / "remaking").exists()
    assert {path.relative_to(stage): path.read_bytes() for path in stage.rglob("*.png")} == made


def test_a_camera_does_not_carve_where_the_room_changed_since_its_plate(capture, tmp_path):
    # As if something put down before cam0 hid the subject's lower half from it in every frame: where the silhouette
    # stage says the room changed, the reconstruction lets cam0 carve nothing, and the other cameras reach his feet.
    out = tmp_path / "out"
    assert main(["run", str(capture), "--out", str(out), "--to", "silhouettes", "-q", "--workers", "1",
                 "--set", "silhouettes.find_room_changes=false"]) == 0
    stage, row = out / "silhouettes", 60
    for frame in range(len(PATH)):
        mask = frames_io.read_mask(silhouette_path(stage, "cam0", frame))
        mask[row:] = 0
        frames_io.write_mask(silhouette_path(stage, "cam0", frame), mask)
    assert main(["run", str(capture), "--out", str(out), "--from", "reconstruction", "--to", "reconstruction", "-q",
                 "--workers", "1", "--set", "silhouettes.find_room_changes=false",
                 "--set", "reconstruction.find_hidden_parts=false"]) == 0
    assert _lowest(out) > 0.3  # carved
    changed = np.zeros((scene.SIZE[1], scene.SIZE[0]), np.uint8)
    changed[row:] = 255
    frames_io.write_mask(room_change_path(stage, "cam0"), changed)
    shutil.rmtree(out / "reconstruction")  # the silhouettes' manifest does not know the file written here
    assert main(["run", str(capture), "--out", str(out), "--from", "reconstruction", "--to", "reconstruction", "-q",
                 "--workers", "1", "--set", "silhouettes.find_room_changes=false",
                 "--set", "reconstruction.find_hidden_parts=false"]) == 0
    assert _lowest(out) < 0.15


def _lowest(out: Path) -> float:
    """The median over frames of each frame's lowest observation's height, metres."""
    return float(np.median([frames_io.read_ply(observations_path(out / "reconstruction", frame))[0][:, 2].min()
                            for frame in range(len(PATH))]))
