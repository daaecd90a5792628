"""Synthetic captures: body surfaces, camera ring, and the written capture read back by the loaders."""

import csv
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest

from calib.errors import InputError
from calib.formats import load_rig
from calib.world import fixed_transform
from pipeline.cli import main as cli_main
from pipeline.io.capture import Capture
from pipeline.lab.mocap import load_clip
from pipeline.lab.synth import build_body, pose_body, posed_mesh, sample_body_surface
from pipeline.lab.synth.distractors import paint_distractors, random_distractors
from pipeline.lab.synth.render import (
    AMBIENT,
    AMBIENT_FROM_BELOW,
    irradiance,
    linear_to_srgb,
    srgb_to_linear,
    tone_curve,
)
from pipeline.lab.synth.rig import RingParams, check_rig_sees, ring_rig
from pipeline.lab.synth.writer import SynthParams, count_video_frames, standing_height, synthesise
from stages.joints import JOINT_NAMES, SCORED_JOINTS

CLIPS = Path(__file__).resolve().parents[2] / "pipeline" / "lab" / "data" / "clips"
KICKS = dict(clip=str(CLIPS / "135_07.amc"), skeleton=str(CLIPS / "martialwalk.asf"))


@pytest.fixture(scope="module")
def kick():
    """The first roundhouse kick at 28 fps (0.85-1.15 s)."""
    return load_clip(KICKS["clip"], skeleton=KICKS["skeleton"]).resample(28.0).slice_seconds(0.85, 1.15)


@pytest.fixture(scope="module", params=["mesh", "capsules"])
def posed(request, kick):
    body = build_body(kick, request.param)
    return pose_body(body, kick, 4)


def _scene(vertices, triangles):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
    return scene


def _rays(origins, directions):
    return o3d.core.Tensor(np.concatenate([origins, directions], axis=1).astype(np.float32))


def test_surface_samples_lie_on_the_rendered_mesh(posed):
    points, normals = sample_body_surface(posed, 3000, np.random.default_rng(0))
    assert points.shape == normals.shape == (3000, 3)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)
    vertices, triangles = posed_mesh(posed)
    centre = vertices.mean(axis=0)  # open3d works in float32: measure near the origin
    scene = _scene(vertices - centre, triangles)
    distance = scene.compute_distance(o3d.core.Tensor((points - centre).astype(np.float32))).numpy()
    assert distance.max() < 1e-5


def test_surface_normals_point_outwards(posed):
    """A ray leaving a closed surface outwards crosses it an even number of times (each closed part)."""
    points, normals = sample_body_surface(posed, 3000, np.random.default_rng(1))
    scene = _scene(*posed_mesh(posed))
    crossings = scene.count_intersections(_rays(points + 1e-4 * normals, normals)).numpy()
    assert np.mean(crossings % 2 == 0) > 0.97  # the mesh's eye sockets are open: a few rays slip through


def test_capsule_samples_are_on_the_outer_surface(kick):
    posed = pose_body(build_body(kick, "capsules"), kick, 4)
    points, normals = sample_body_surface(posed, 3000, np.random.default_rng(2))
    outside = points + 3e-3 * normals
    inside = points - 3e-3 * normals
    nowhere = np.full(len(points), -1)
    assert np.all(posed.parts.contains(inside, exclude=nowhere, margin=0.0))
    # stepping out 3 mm leaves every capsule, except within ~3 mm of a crease where two capsules meet
    assert np.mean(posed.parts.contains(outside, exclude=nowhere, margin=0.0)) < 0.01


def test_scored_joints_are_inside_the_mesh_body(kick):
    body = build_body(kick, "mesh")
    for frame in (0, 4, 8):
        scene = _scene(*posed_mesh(pose_body(body, kick, frame)))
        joints = kick.joints[frame, : len(SCORED_JOINTS)].astype(np.float32)
        occupied = scene.compute_occupancy(o3d.core.Tensor(joints), nsamples=5).numpy()
        assert occupied.all(), [name for name, inside in zip(SCORED_JOINTS, occupied, strict=True) if not inside]


def test_mesh_body_keeps_its_shape_in_motion(kick):
    """Skinning does not tear or blow up the mesh, and the standing height is an adult's.

    Linear blend skinning pinches and stretches skin at strongly bent joints (the groin in a high kick
    stretches some edges to 2-4x their rest length); a binding error would stretch them 10x or more.
    """
    body = build_body(kick, "mesh")
    rest = pose_body(body, kick.rest_pose(), 0)
    edges = np.concatenate([rest.triangles[:, [0, 1]], rest.triangles[:, [1, 2]], rest.triangles[:, [2, 0]]])
    rest_lengths = np.linalg.norm(np.diff(rest.vertices[edges], axis=1)[:, 0], axis=1)
    for frame in range(kick.n_frames):
        vertices = pose_body(body, kick, frame).vertices
        ratio = np.linalg.norm(np.diff(vertices[edges], axis=1)[:, 0], axis=1) / np.maximum(rest_lengths, 1e-9)
        assert np.percentile(ratio, 99.9) < 2.5 and ratio.max() < 5.0
    assert len(rest.vertices) == 13380
    assert 1.6 < standing_height(body, kick) < 1.9


def test_non_cmu_skeleton_is_an_input_error_for_the_mesh_pointing_to_capsules():
    run = load_clip(CLIPS / "09_01.bvh")
    with pytest.raises(InputError, match="needs CMU bone names.*--body capsules"):
        build_body(run, "mesh")


# ------------------------------------------------------------------------------------------------ rig


def _body_points(motion, kind="capsules"):
    body = build_body(motion, kind)
    return np.concatenate([pose_body(body, motion, k).vertices[::5] for k in range(motion.n_frames)])


def test_ring_frames_every_body_point(kick):
    points = _body_points(kick)
    params = RingParams(n_cameras=5, size=(320, 240))
    rig = ring_rig(points, params, np.random.default_rng(3))
    assert len(rig) == 5
    for camera in rig:
        uv = camera.project(points)
        assert np.all(uv >= [0.04 * 320, 0.04 * 240]) and np.all(uv <= [0.96 * 320, 0.96 * 240])
        assert 1.5 <= camera.centre[2] <= 2.8
        assert -0.15 <= camera.dist[0] <= 0.05
    again = ring_rig(points, params, np.random.default_rng(3))
    np.testing.assert_array_equal(again[2].K, rig[2].K)
    check_rig_sees(rig, kick.joints)


def test_rig_too_close_to_the_subject_is_an_input_error(kick):
    points = _body_points(kick)
    crowded = RingParams(clearance_m=0.1, min_radius_m=0.5)
    with pytest.raises(InputError, match="rig cannot see the subject"):
        ring_rig(points, crowded, np.random.default_rng(0))


def test_joints_outside_the_images_are_an_input_error(kick):
    rig = ring_rig(_body_points(kick), RingParams(n_cameras=3, size=(160, 120)), np.random.default_rng(0))
    walked_away = kick.joints + [6.0, 0.0, 0.0]
    with pytest.raises(InputError, match="rig cannot see the subject: camera cam"):
        check_rig_sees(rig, walked_away)


# ------------------------------------------------------------------------------------- written captures


def _render(out, **options):
    params = SynthParams(**KICKS, start_s=0.9, seconds=4 / 28 - 1e-6, n_cameras=3, size=(200, 150), **options)
    synthesise(params, out)
    return params


def _read_joints(path):
    with open(path, newline="") as table:
        rows = list(csv.DictReader(table))
    frames = sorted({int(row["frame"]) for row in rows})
    joints = np.zeros((len(frames), len(JOINT_NAMES), 3))
    for row in rows:
        joints[int(row["frame"]), JOINT_NAMES.index(row["joint"])] = [float(row[a]) for a in "xyz"]
    return joints


def _share_of_joints_in_masks(out, rig, joints):
    """Share of the ground-truth joints (F, 17, 3) that project into their camera's true mask."""
    inside, total = 0, 0
    kernel = np.ones((5, 5), np.uint8)  # dilate by 2 px
    for camera in rig:
        for frame in range(len(joints)):
            mask = cv2.imread(str(out / "groundtruth" / "masks" / camera.name / f"{frame:06d}.png"), 0)
            mask = cv2.dilate(mask, kernel)
            uv = np.rint(camera.project(joints[frame])).astype(int)
            inside += int(np.count_nonzero(mask[uv[:, 1], uv[:, 0]]))
            total += len(uv)
    return inside / total


@pytest.fixture(scope="module")
def small_capture(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "small"
    _render(out, media="images", calib_format="anipose", distractors=2)
    return out


@pytest.mark.parametrize(
    ("calib_format", "units", "up"), [("colmap", "m", "+z"), ("opencv", "cm", "+y"), ("anipose", "mm", "-x")]
)
def test_ground_truth_joints_fall_inside_the_true_masks(tmp_path, calib_format, units, up):
    out = tmp_path / "capture"
    params = _render(out, media="images", calib_format=calib_format, units=units, up=up)
    config = Capture.open(out)  # the pipeline's own reader accepts the capture
    assert config.rig.names == ("cam1", "cam2", "cam3")
    sizes = {name: params.size for name in config.rig.names}
    stored = load_rig(calib_format, out / {"colmap": "calibration/colmap", "opencv": "calibration/opencv",
                                            "anipose": "calibration/calibration.toml"}[calib_format],
                      image_sizes=sizes)  # fmt: skip
    rig = fixed_transform(units=units, up=up).apply(stored)
    joints = _read_joints(out / "groundtruth" / "joints.csv")
    assert joints.shape == (4, 17, 3)
    assert _share_of_joints_in_masks(out, rig, joints) >= 0.98


def test_capture_layout_and_contents(small_capture):
    capture = Capture.open(small_capture)
    assert capture.fps == 28.0
    assert capture.height_m is not None and 1.6 < capture.height_m < 1.9
    assert list(capture.frame_numbers) == [0, 1, 2, 3]
    for camera in capture.rig.names:
        background = capture.background(camera)
        frame, image = next(iter(capture.iter_images(camera, [2])))
        mask = cv2.imread(str(small_capture / "groundtruth" / "masks" / camera / "000002.png"), 0)
        assert background.shape == image.shape == (150, 200, 3)
        assert set(np.unique(mask)) == {0, 255}
        difference = np.abs(image.astype(int) - background.astype(int)).max(axis=2)
        assert np.median(difference[mask == 255]) > np.median(difference[mask == 0]) + 10
    assert (small_capture / "groundtruth" / "synth.yaml").is_file()


def test_images_are_exposed_mid_grey_with_a_lit_body_and_few_clipped_pixels(small_capture):
    capture = Capture.open(small_capture)
    for camera in capture.rig.names:
        _, image = next(iter(capture.iter_images(camera, [2])))
        mask = cv2.imread(str(small_capture / "groundtruth" / "masks" / camera / "000002.png"), 0)
        assert 100 < image.mean() < 150  # metered on the room: near the middle of the 8-bit range
        assert (image >= 250).mean() < 0.002 and (image <= 5).mean() < 0.002
        assert np.percentile(image[mask == 255].max(axis=1), 10) > 25  # shadowed side lit by fill and ambient


def test_every_surface_receives_at_least_the_ambient_light():
    directions = np.random.default_rng(0).normal(size=(2000, 3))
    normals = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    received = irradiance(normals)
    assert received.min() >= AMBIENT * AMBIENT_FROM_BELOW - 1e-12
    assert irradiance(np.array([[0.0, 0.0, 1.0]]))[0] > irradiance(np.array([[0.0, 0.0, -1.0]]))[0]


def test_tone_curve_is_srgb_below_the_shoulder_and_never_clips_highlights():
    values = np.linspace(0.0, 0.5, 51)
    np.testing.assert_allclose(tone_curve(values), linear_to_srgb(values), atol=1e-12)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(values)), values, atol=1e-12)
    bright = tone_curve(np.array([0.9, 1.5, 3.0]))
    assert np.all(np.diff(bright) > 0) and bright[-1] < 1.0


def test_video_capture_decodes_with_matching_frame_counts(tmp_path):
    out = tmp_path / "video"
    _render(out, media="video", noise_sigma=1.0, height_known=False)
    for camera in ("cam1", "cam2", "cam3"):
        assert count_video_frames(out / "videos" / f"{camera}.mp4", (200, 150)) == 4
    capture = Capture.open(out)
    assert capture.height_m is None
    assert list(capture.frame_numbers) == [0, 1, 2, 3]


def test_montage_command_writes_a_png(small_capture, tmp_path):
    assert cli_main(["synth", "--montage", "1", str(small_capture), "--masks", "--out", str(tmp_path)]) == 0
    sheet = cv2.imread(str(tmp_path / "montage_000001.png"))
    assert sheet is not None and sheet.shape[1] == 2 * 390


def test_synth_into_a_non_empty_directory_is_refused(small_capture, capsys):
    assert cli_main(["synth", "--out", str(small_capture), "--size", "64x48"]) == 2
    assert "directory is not empty" in capsys.readouterr().err


def test_distractors_paint_blobs_in_their_own_camera_and_frames():
    blobs = random_distractors(4, 3, 10, (200, 150), np.random.default_rng(0))
    assert all(0 <= blob.first_frame <= blob.last_frame < 10 for blob in blobs)
    blob = blobs[0]
    grey = np.full((150, 200, 3), 0.5)
    painted = paint_distractors(grey.copy(), [blob], blob.camera, blob.first_frame)
    u, v = (int(round(c)) for c in blob.start)
    np.testing.assert_allclose(painted[v, u], blob.colour, atol=1e-6)
    untouched = paint_distractors(grey.copy(), [blob], (blob.camera + 1) % 3, blob.first_frame)
    np.testing.assert_array_equal(untouched, grey)


# ------------------------------------------------------------------------------ non-CMU skeletons


def test_capsules_of_a_non_cmu_clip_hold_its_joints_and_have_an_adults_height():
    """The Daz-style 09_01 run gets joint-bound capsules around its scored joints, sized for an adult."""
    run = load_clip(CLIPS / "09_01.bvh").slice_seconds(0.0, 0.3)
    body = build_body(run, "capsules")
    for frame in (0, run.n_frames - 1):
        posed = pose_body(body, run, frame)
        points, normals = sample_body_surface(posed, 2000, np.random.default_rng(frame))
        nowhere = np.full(len(points), -1)
        assert np.all(posed.parts.contains(points - 3e-3 * normals, exclude=nowhere, margin=0.0))
        # capsules overlap at the joints, so ask them (a ray's crossings of their union are not a parity)
        joints = run.joints[frame, : len(SCORED_JOINTS)]
        inside = posed.parts.contains(joints, exclude=np.full(len(joints), -1), margin=0.01)
        assert inside.all(), [name for name, held in zip(SCORED_JOINTS, inside, strict=True) if not held]
    assert 1.55 < standing_height(body, run) < 1.95


def test_non_cmu_clip_renders_with_joints_inside_the_true_masks(tmp_path):
    out = tmp_path / "run"
    params = SynthParams(
        clip=str(CLIPS / "09_01.bvh"), seconds=3 / 28 - 1e-6, body="capsules", n_cameras=3, size=(160, 120),
        media="images",
    )  # fmt: skip
    synthesise(params, out)
    sizes = dict.fromkeys(("cam1", "cam2", "cam3"), params.size)
    stored = load_rig("colmap", out / "calibration" / "colmap", image_sizes=sizes)
    rig = fixed_transform(units="m", up="+z").apply(stored)
    joints = _read_joints(out / "groundtruth" / "joints.csv")
    assert joints.shape == (3, 17, 3)
    assert _share_of_joints_in_masks(out, rig, joints) >= 0.98
