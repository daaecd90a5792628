"""``pipeline.lab.bench.perturb``: a copy of a capture whose videos differ from its plates as a camera's would."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from calib.camera import Camera, Rig
from calib.errors import InputError
from calib.formats import load_rig, save_rig
from pipeline.io.export_io import read_joints_csv, write_joints_csv
from pipeline.lab.bench.perturb import main, perturb_capture

FRAMES, HEIGHT, WIDTH = 4, 48, 64


def _frames(video: Path) -> list[np.ndarray]:
    reader = cv2.VideoCapture(str(video))
    frames = []
    while (read := reader.read())[0]:
        frames.append(read[1])
    reader.release()
    return frames


def _write_flat_video(path: Path, levels: tuple[int, ...]) -> None:
    """A video of uniform frames, one grey level each: what a change did to a frame shows in its mean."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 25, (WIDTH, HEIGHT))
    for level in levels:
        writer.write(np.full((HEIGHT, WIDTH, 3), level, np.uint8))
    writer.release()


@pytest.fixture
def capture(tmp_path) -> Path:
    """A capture folder with two short videos of smooth colours, a plate per camera, a calibration and truth."""
    root = tmp_path / "capture"
    for folder in ("videos", "background", "calibration", "groundtruth"):
        (root / folder).mkdir(parents=True)
    (root / "capture.yaml").write_text("fps: 25\n")
    (root / "calibration" / "rig.toml").write_text("# a calibration\n")
    (root / "groundtruth" / "joints.csv").write_text("frame,joint,x,y,z\n")
    rng = np.random.default_rng(0)
    for camera in ("cam0", "cam1"):
        plate = cv2.resize(rng.uniform(60, 200, (4, 5, 3)), (WIDTH, HEIGHT)).astype(np.uint8)
        cv2.imwrite(str(root / "background" / f"{camera}.png"), plate)
        writer = cv2.VideoWriter(str(root / "videos" / f"{camera}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 25,
                                 (WIDTH, HEIGHT))
        for _ in range(FRAMES):
            writer.write(plate)
        writer.release()
    return root


def test_a_black_level_change_is_applied_to_every_frame_and_the_rest_is_kept(capture, tmp_path):
    out = perturb_capture(capture, tmp_path / "lifted", "black_level")
    assert (out / "capture.yaml").read_text() == "fps: 25\n"
    assert (out / "calibration" / "rig.toml").is_file() and (out / "background" / "cam1.png").is_file()
    assert (out / "groundtruth").is_symlink() and (out / "groundtruth" / "joints.csv").is_file()
    for camera in ("cam0", "cam1"):
        before, after = _frames(capture / "videos" / f"{camera}.mp4"), _frames(out / "videos" / f"{camera}.mp4")
        assert len(after) == len(before) == FRAMES
        for original, changed in zip(before, after, strict=True):
            # the codec's second generation adds a level or two; the change itself is 0.85 I + 20
            assert np.abs(changed.astype(float) - (0.85 * original + 20.0)).mean() < 3.0
    assert not (tmp_path / "lifted.partial").exists()


def test_a_copy_without_plates_is_a_recording_made_without_a_clean_plate(capture, tmp_path):
    assert main([str(capture), "--change", "none", "--no-plates", "--out", str(tmp_path / "bare")]) == 0
    out = tmp_path / "bare"
    assert not (out / "background").exists()
    assert (out / "calibration" / "rig.toml").is_file() and (out / "groundtruth" / "joints.csv").is_file()
    assert len(_frames(out / "videos" / "cam0.mp4")) == FRAMES


def test_nothing_is_overwritten_and_an_unknown_change_is_refused(capture, tmp_path, capsys):
    (tmp_path / "taken").mkdir()
    with pytest.raises(InputError, match="already exists"):
        perturb_capture(capture, tmp_path / "taken", "gamma")
    with pytest.raises(InputError, match="unknown change 'sepia'"):
        perturb_capture(capture, tmp_path / "new", "sepia")
    (capture / "videos" / "cam0.mp4").unlink()
    (capture / "videos" / "cam1.mp4").unlink()
    assert main([str(capture), "--change", "noise", "--out", str(tmp_path / "new")]) == 2
    assert "no videos/ folder with videos" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()


def test_an_absent_subject_shows_the_plates_there_and_the_truth_leaves_those_frames_out(capture, tmp_path):
    # A subject who walks out of view for frames 1-2 and comes back: a white square on the plate elsewhere.
    for camera in ("cam0", "cam1"):
        plate = cv2.imread(str(capture / "background" / f"{camera}.png"))
        person = plate.copy()
        person[10:30, 20:40] = 255
        writer = cv2.VideoWriter(str(capture / "videos" / f"{camera}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 25,
                                 (WIDTH, HEIGHT))
        for _ in range(FRAMES):
            writer.write(person)
        writer.release()
        (capture / "groundtruth" / "masks" / camera).mkdir(parents=True)
        for frame in range(FRAMES):
            mask = np.zeros((HEIGHT, WIDTH), np.uint8)
            mask[10:30, 20:40] = 255
            cv2.imwrite(str(capture / "groundtruth" / "masks" / camera / f"{frame:06d}.png"), mask)
    rows = "".join(f"{frame},pelvis,0,0,1\n" for frame in range(FRAMES))
    (capture / "groundtruth" / "joints.csv").write_text("frame,joint,x,y,z\n" + rows)
    assert main([str(capture), "--change", "none", "--absent", "1:3", "--out", str(tmp_path / "away")]) == 0
    out = tmp_path / "away"
    plate = cv2.imread(str(capture / "background" / "cam1.png")).astype(float)
    square = (slice(10, 30), slice(20, 40))
    for frame, image in enumerate(_frames(out / "videos" / "cam1.mp4")):
        away = frame in (1, 2)
        assert bool(np.abs(image[square] - plate[square]).mean() < 6) == away  # the plate, with noise, where away
        assert bool(cv2.imread(str(out / "groundtruth" / "masks" / "cam1" / f"{frame:06d}.png"), 0).any()) != away
    assert (out / "groundtruth" / "joints.csv").read_text() == "frame,joint,x,y,z\n0,pelvis,0,0,1\n3,pelvis,0,0,1\n"
    assert (capture / "groundtruth" / "joints.csv").read_text().count("pelvis") == FRAMES  # the original untouched


def test_absent_frames_need_a_plate_for_every_camera_and_a_span(capture, tmp_path, capsys):
    (capture / "background" / "cam1.png").unlink()
    with pytest.raises(InputError, match="no readable clean plate for camera 'cam1'"):
        perturb_capture(capture, tmp_path / "away", "none", absent=range(0, 2))
    assert not (tmp_path / "away").exists() and not (tmp_path / "away.partial").exists()
    with pytest.raises(SystemExit):
        main([str(capture), "--change", "none", "--absent", "5:2", "--out", str(tmp_path / "away")])
    assert "expected 0 <= FIRST < STOP" in capsys.readouterr().err


@pytest.mark.parametrize("fmt", ["opencv", "anipose"])
def test_a_smaller_rig_keeps_the_named_cameras_in_the_calibrations_own_format_and_units(capture, tmp_path, fmt):
    (capture / "videos" / "cam0.mp4").rename(capture / "videos" / "cam2.mp4")  # cam1 and cam2: not the first ones
    (capture / "background" / "cam0.png").rename(capture / "background" / "cam2.png")
    for camera in ("cam1", "cam2"):
        (capture / "groundtruth" / "masks" / camera).mkdir(parents=True)
        cv2.imwrite(str(capture / "groundtruth" / "masks" / camera / "000000.png"), np.zeros((HEIGHT, WIDTH), np.uint8))
    cameras = [Camera.look_at(f"cam{index}", (4000.0 * np.cos(index), 4000.0 * np.sin(index), 1500.0),
                              (0.0, 0.0, 1000.0), f_px=60.0, size=(WIDTH, HEIGHT)) for index in (1, 2)]
    save_rig(Rig(tuple(cameras)), fmt, capture / "calibration" / fmt)  # in millimetres, as the file states them
    (capture / "capture.yaml").write_text(f"fps: 25\ncalibration: {{format: {fmt}, path: calibration/{fmt}, "
                                          "units: mm, up: +z}\n")
    assert main([str(capture), "--change", "none", "--cameras", "cam2", "--out", str(tmp_path / "one")]) == 0
    out = tmp_path / "one"
    kept = load_rig(fmt, out / "calibration" / fmt, image_sizes={"cam2": (WIDTH, HEIGHT)})
    assert kept.names == ("cam2",)
    np.testing.assert_allclose(kept["cam2"].t, cameras[1].t)
    assert [path.name for path in (out / "videos").iterdir()] == ["cam2.mp4"]
    assert [path.name for path in (out / "background").iterdir()] == ["cam2.png"]
    assert [path.name for path in (out / "groundtruth" / "masks").iterdir()] == ["cam2"]
    assert (out / "groundtruth" / "joints.csv").is_file()
    with pytest.raises(InputError, match="no video of camera\\(s\\) cam7"):
        perturb_capture(capture, tmp_path / "other", "none", cameras=("cam2", "cam7"))


def _colmap_calibration(capture: Path) -> list[Camera]:
    """The capture's two cameras looking at the origin, written as its COLMAP calibration (capture.yaml too)."""
    cameras = [Camera.look_at(f"cam{index}", (4.0 * np.cos(index), 4.0 * np.sin(index), 1.5), (0.0, 0.0, 1.0),
                              f_px=60.0, size=(WIDTH, HEIGHT)) for index in (0, 1)]
    save_rig(Rig(tuple(cameras)), "colmap", capture / "calibration" / "colmap")
    (capture / "capture.yaml").write_text("fps: 25\ncalibration: {format: colmap, path: calibration/colmap, units: m, "
                                          "up: +z}\n")
    return cameras


def test_a_calibration_error_turns_each_camera_about_its_centre_by_the_angle_asked(capture, tmp_path):
    cameras = _colmap_calibration(capture)
    out = perturb_capture(capture, tmp_path / "off", "none", calibration_error_deg=0.2)
    turned = load_rig("colmap", out / "calibration" / "colmap")
    for before, after in zip(cameras, turned, strict=True):
        np.testing.assert_allclose(after.centre, before.centre, atol=1e-9)
        angle = np.degrees(np.arccos(np.clip((np.trace(after.R @ before.R.T) - 1.0) / 2.0, -1.0, 1.0)))
        assert angle == pytest.approx(0.2, abs=1e-6)
    assert not np.allclose(turned[0].R @ cameras[0].R.T, turned[1].R @ cameras[1].R.T)  # an axis of its own
    with pytest.raises(InputError, match="expected a finite angle"):
        perturb_capture(capture, tmp_path / "nan", "none", calibration_error_deg=float("nan"))


def test_a_position_error_moves_each_camera_by_the_distance_asked_in_the_files_units(capture, tmp_path):
    cameras = [Camera.look_at(f"cam{index}", (4000.0 * np.cos(index), 4000.0 * np.sin(index), 1500.0),
                              (0.0, 0.0, 1000.0), f_px=60.0, size=(WIDTH, HEIGHT)) for index in (0, 1)]
    save_rig(Rig(tuple(cameras)), "anipose", capture / "calibration" / "anipose")  # millimetres
    (capture / "capture.yaml").write_text("fps: 25\ncalibration: {format: anipose, path: calibration/anipose, "
                                          "units: mm, up: +z}\n")
    out = perturb_capture(capture, tmp_path / "moved", "none", position_error_m=0.02)
    moved = load_rig("anipose", out / "calibration" / "anipose", image_sizes={c.name: c.size for c in cameras})
    for before, after in zip(cameras, moved, strict=True):
        np.testing.assert_allclose(after.R, before.R, atol=1e-12)  # the orientation kept
        assert np.linalg.norm(after.centre - before.centre) == pytest.approx(20.0)  # 2 cm in millimetres
    with pytest.raises(InputError, match="expected a finite distance"):
        perturb_capture(capture, tmp_path / "inf", "none", position_error_m=float("inf"))


def test_a_zoomed_camera_sees_the_middle_of_its_image_enlarged_and_its_calibration_and_truth_agree(capture, tmp_path):
    cameras = _colmap_calibration(capture)
    mask = np.zeros((HEIGHT, WIDTH), np.uint8)
    mask[20:28, 28:36] = 255  # 8 x 8 about the centre (31.5, 23.5)
    (capture / "groundtruth" / "masks" / "cam1").mkdir(parents=True)
    cv2.imwrite(str(capture / "groundtruth" / "masks" / "cam1" / "000000.png"), mask)
    out = perturb_capture(capture, tmp_path / "zoomed", "none", zoom={"cam1": 2.0})
    zoomed = load_rig("colmap", out / "calibration" / "colmap")
    np.testing.assert_allclose(zoomed[0].K, cameras[0].K)
    X = np.array([[0.1, -0.2, 1.2], [0.0, 0.1, 0.9]])
    centre = np.array([(WIDTH - 1) / 2, (HEIGHT - 1) / 2])
    np.testing.assert_allclose(zoomed[1].project(X) - centre, 2.0 * (cameras[1].project(X) - centre), atol=1e-9)
    np.testing.assert_allclose(zoomed[1].R, cameras[1].R, atol=1e-12)
    grown = cv2.imread(str(out / "groundtruth" / "masks" / "cam1" / "000000.png"), cv2.IMREAD_GRAYSCALE)
    assert set(np.unique(grown)) == {0, 255} and (grown > 0).sum() == 4 * (mask > 0).sum()
    plate, before = (cv2.imread(str(root / "background" / "cam1.png")) for root in (out, capture))
    np.testing.assert_allclose(plate[HEIGHT // 2, WIDTH // 2], before[HEIGHT // 2, WIDTH // 2], atol=2)
    assert (out / "background" / "cam0.png").read_bytes() == (capture / "background" / "cam0.png").read_bytes()
    with pytest.raises(InputError, match="at least 1"):
        perturb_capture(capture, tmp_path / "wide", "none", zoom={"cam1": 0.5})
    with pytest.raises(InputError, match="no video of camera"):
        perturb_capture(capture, tmp_path / "nobody", "none", zoom={"cam7": 2.0})
    with pytest.raises(SystemExit):
        main([str(capture), "--change", "none", "--zoom", "cam1:oops", "--out", str(tmp_path / "x")])


def test_a_late_camera_shows_the_others_earlier_frames_and_its_true_masks_follow(capture, tmp_path):
    _write_flat_video(capture / "videos" / "cam1.mp4", (40, 90, 140, 190))
    for camera in ("cam0", "cam1"):
        (capture / "groundtruth" / "masks" / camera).mkdir(parents=True)
        for frame in range(FRAMES):
            mask = np.zeros((HEIGHT, WIDTH), np.uint8)
            mask[frame * 10:frame * 10 + 5] = 255
            cv2.imwrite(str(capture / "groundtruth" / "masks" / camera / f"{frame:06d}.png"), mask)
    out = perturb_capture(capture, tmp_path / "late", "none", late={"cam1": 1})
    source = [float(frame.mean()) for frame in _frames(capture / "videos" / "cam1.mp4")]
    shown = [float(frame.mean()) for frame in _frames(out / "videos" / "cam1.mp4")]
    np.testing.assert_allclose(shown, [source[0], *source[:3]], atol=3)  # frame t is the source's t - 1
    masks = [cv2.imread(str(out / "groundtruth" / "masks" / "cam1" / f"{frame:06d}.png"), cv2.IMREAD_GRAYSCALE)
             for frame in range(FRAMES)]
    assert [int(np.flatnonzero(mask.any(axis=1))[0]) for mask in masks] == [0, 0, 10, 20]
    steady = cv2.imread(str(out / "groundtruth" / "masks" / "cam0" / "000002.png"), cv2.IMREAD_GRAYSCALE)
    assert np.flatnonzero(steady.any(axis=1))[0] == 20  # the others keep their own
    with pytest.raises(InputError, match="whole number of frames"):
        perturb_capture(capture, tmp_path / "early", "none", late={"cam1": 0})


def test_a_shifted_plate_is_moved_and_its_frames_are_not(capture, tmp_path):
    out = perturb_capture(capture, tmp_path / "knocked", "none", plate_shift={"cam1": (2.0, 1.0)})
    plate, before = (cv2.imread(str(root / "background" / "cam1.png")).astype(int) for root in (out, capture))
    np.testing.assert_allclose(plate[10:40, 10:50], before[9:39, 8:48], atol=2)  # content moved 2 right, 1 down
    assert (out / "background" / "cam0.png").read_bytes() == (capture / "background" / "cam0.png").read_bytes()
    np.testing.assert_allclose(_frames(out / "videos" / "cam1.mp4")[0], _frames(capture / "videos" / "cam1.mp4")[0],
                               atol=3)
    with pytest.raises(InputError, match="two finite numbers"):
        perturb_capture(capture, tmp_path / "bad", "none", plate_shift={"cam1": (float("nan"), 1.0)})
    with pytest.raises(SystemExit):
        main([str(capture), "--change", "none", "--plate-shift", "cam1:2", "--out", str(tmp_path / "x")])


def test_a_monochrome_copy_has_grey_frames_and_plates(capture, tmp_path):
    out = perturb_capture(capture, tmp_path / "grey", "none", monochrome=True)
    frame = _frames(out / "videos" / "cam0.mp4")[0].astype(int)
    assert np.abs(frame[:, :, 0] - frame[:, :, 2]).max() <= 3  # the codec's rounding only
    plate = cv2.imread(str(out / "background" / "cam0.png"), cv2.IMREAD_UNCHANGED)
    colour = cv2.imread(str(capture / "background" / "cam0.png"))
    assert plate.ndim == 2 and np.array_equal(plate, cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY))
    _colmap_calibration(capture)  # a smaller rig rewrites the calibration
    smaller = perturb_capture(capture, tmp_path / "grey-one", "none", monochrome=True, cameras=("cam0",))
    assert [path.name for path in (smaller / "background").iterdir()] == ["cam0.png"]  # no plate of a camera left out


def test_a_longer_shutter_blends_each_frame_with_the_one_before(capture, tmp_path):
    _write_flat_video(capture / "videos" / "cam1.mp4", (40, 120, 200, 80))
    write_joints_csv(capture / "groundtruth" / "joints.csv", np.arange(FRAMES), np.zeros((FRAMES, 17, 3)))
    out = perturb_capture(capture, tmp_path / "smear", "none", shutter=0.25)
    control = perturb_capture(capture, tmp_path / "control", "none")  # the codec's second generation alone
    plain = [float(frame.mean()) for frame in _frames(control / "videos" / "cam1.mp4")]
    shown = [float(frame.mean()) for frame in _frames(out / "videos" / "cam1.mp4")]
    expected = [plain[0]] + [0.75 * now + 0.25 * before for before, now in zip(plain[:-1], plain[1:], strict=True)]
    np.testing.assert_allclose(shown, expected, atol=2)
    with pytest.raises(InputError, match="shutter 1.0"):
        perturb_capture(capture, tmp_path / "bad", "none", shutter=1.0)


def test_a_longer_shutter_times_the_true_joints_at_the_exposures_mean(capture, tmp_path):
    truth = np.arange(3 * 17 * 3, dtype=float).reshape(3, 17, 3) / 100.0
    write_joints_csv(capture / "groundtruth" / "joints.csv", np.array([0, 1, 3]), truth)  # frame 2 missing
    out = perturb_capture(capture, tmp_path / "smear", "none", shutter=0.25)
    frames, _, joints = read_joints_csv(out / "groundtruth" / "joints.csv")
    assert frames.tolist() == [0, 1, 3] and not (out / "groundtruth").is_symlink()
    np.testing.assert_allclose(joints[[0, 2]], truth[[0, 2]], atol=1e-6)  # no frame before them
    np.testing.assert_allclose(joints[1], 0.75 * truth[1] + 0.25 * truth[0], atol=1e-6)


def _true_masks(capture: Path, rows: slice, columns: slice) -> None:
    """Every camera's true masks: the subject over ``rows`` and ``columns`` of the image, on every frame."""
    for camera in ("cam0", "cam1"):
        (capture / "groundtruth" / "masks" / camera).mkdir(parents=True)
        for frame in range(FRAMES):
            mask = np.zeros((HEIGHT, WIDTH), np.uint8)
            mask[rows, columns] = 255
            cv2.imwrite(str(capture / "groundtruth" / "masks" / camera / f"{frame:06d}.png"), mask)


@pytest.mark.parametrize(("kind", "hidden"), [("desk", np.s_[30:, :]), ("pillar", np.s_[:, 28:32])])
def test_an_occluder_stands_in_one_cameras_plate_and_frames_and_hides_the_subject_from_its_truth(
        capture, tmp_path, kind, hidden):
    # Rows 10-39: a desk from row 10 + 0.7 (39 - 10), 30, on; columns 20-39: a pillar 2 x 2 wide about 29.5, rounded.
    _true_masks(capture, slice(10, 40), slice(20, 40))
    out = perturb_capture(capture, tmp_path / kind, "none", occluder={"cam1": kind})
    region = np.zeros((HEIGHT, WIDTH), bool)
    region[hidden] = True
    plate = cv2.imread(str(out / "background" / "cam1.png")).astype(float)
    frame = _frames(out / "videos" / "cam1.mp4")[2].astype(float)
    source = _frames(capture / "videos" / "cam1.mp4")[2].astype(float)
    # The occluder's grey, in the plate and the frames alike (medians: the codec bleeds colour across its edges).
    assert np.abs(np.median(plate[region], axis=0) - [105, 115, 125]).max() < 4
    assert np.abs(np.median(frame[region], axis=0) - [105, 115, 125]).max() < 6
    assert np.abs(frame[~region] - source[~region]).mean() < 6
    mask = cv2.imread(str(out / "groundtruth" / "masks" / "cam1" / "000002.png"), cv2.IMREAD_GRAYSCALE)
    assert not mask[region].any() and mask[~region].sum() == 255 * (30 * 20 - (region[10:40, 20:40]).sum())
    assert (out / "background" / "cam0.png").read_bytes() == (capture / "background" / "cam0.png").read_bytes()
    with pytest.raises(InputError, match="expected one of desk, pillar"):
        perturb_capture(capture, tmp_path / "bad", "none", occluder={"cam1": "wall"})


def test_an_occluder_is_placed_by_the_true_masks(capture, tmp_path):
    with pytest.raises(InputError, match="no true masks"):
        perturb_capture(capture, tmp_path / "none", "none", occluder={"cam1": "desk"})


def test_a_box_put_down_after_the_plates_stands_in_every_frame_and_not_in_the_plates(tmp_path):
    import still_scene as scene

    from calib.formats import save_rig as save
    from pipeline.lab.bench.box import box_corners, box_view

    rig = scene.ring(4)  # one of whose cameras sees the subject behind the box
    rooms = scene.rooms(rig, seed=5)
    path = 0.3 * np.column_stack([np.cos(np.linspace(0, 2 * np.pi, 6)), np.zeros(6)])  # to and fro along x
    views = scene.frames(rig, rooms, path)
    root = tmp_path / "capture"
    for folder in ("videos", "background", "groundtruth/masks"):
        (root / folder).mkdir(parents=True)
    save(rig, "anipose", root / "calibration" / "calibration.toml")
    (root / "capture.yaml").write_text(
        "fps: 25\ncalibration: {format: anipose, path: calibration/calibration.toml}\n"
        f"volume: {{min: {scene.VOLUME[0].tolist()}, max: {scene.VOLUME[1].tolist()}}}\n")
    pelvis = np.column_stack([path, np.full(len(path), 0.85)])[:, None, :]
    write_joints_csv(root / "groundtruth" / "joints.csv", np.arange(len(path)), pelvis, ("pelvis",))
    for camera, room, images in zip(rig, rooms, views, strict=True):
        cv2.imwrite(str(root / "background" / f"{camera.name}.png"), room)
        writer = cv2.VideoWriter(str(root / "videos" / f"{camera.name}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 25,
                                 scene.SIZE)
        (root / "groundtruth" / "masks" / camera.name).mkdir()
        for frame, (image, centre) in enumerate(zip(images, path, strict=True)):
            writer.write(image)
            cv2.imwrite(str(root / "groundtruth" / "masks" / camera.name / f"{frame:06d}.png"),
                        scene.subject_mask(camera, centre))
        writer.release()

    out = perturb_capture(root, tmp_path / "box", "none", box=True)
    corners = box_corners(pelvis[:, 0], scene.VOLUME)
    cuts, checked = 0, 0  # frames of a camera where the box hides part of the subject, where it is seen
    for camera in rig:
        assert (out / "background" / f"{camera.name}.png").read_bytes() == \
            (root / "background" / f"{camera.name}.png").read_bytes()
        view = box_view(camera, corners)
        assert view.region.sum() > 200
        inner = cv2.erode(view.region.view(np.uint8), np.ones((5, 5), np.uint8)) > 0  # away from the codec's edges
        seen = checked
        for index, frame in enumerate(_frames(out / "videos" / f"{camera.name}.mp4")):
            given = cv2.imread(str(root / "groundtruth" / "masks" / camera.name / f"{index:06d}.png"), 0) > 0
            kept = cv2.imread(str(out / "groundtruth" / "masks" / camera.name / f"{index:06d}.png"), 0) > 0
            shown = inner & ~cv2.dilate(kept.view(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
            if shown.sum() > 50:  # the box, where he is not seen
                assert np.abs(frame[shown].astype(float) - view.image[shown]).mean() < 6
                checked += 1
            # The true masks lose the subject where the box hides him, and only there.
            behind = view.depth < float(camera.depth(pelvis[index])[0])
            assert np.array_equal(kept, given & ~view.region if behind else given)
            cuts += int((given & ~kept).any())
        assert checked > seen  # every camera shows the box
    assert checked >= len(rig) * len(path) // 2 and cuts > 0
    with pytest.raises(InputError, match="no true joints and masks"):
        perturb_capture(_bare(tmp_path / "bare", root), tmp_path / "nobox", "none", box=True)


def _bare(folder: Path, root: Path) -> Path:
    """A copy of the capture at ``root`` without its ground truth."""
    import shutil

    shutil.copytree(root, folder, ignore=shutil.ignore_patterns("groundtruth"))
    return folder
