import cv2
import numpy as np
import pytest
import still_scene as scene

from calib.errors import InputError
from stages.background import (
    MIN_UNCOVERED,
    estimate_backgrounds,
    masked_median,
    sample_camera,
    sample_count,
    working_camera,
    working_size,
)
from stages.background.plates import MIN_PLATE_MATCH, plate_fit, shifted_plate
from stages.silhouettes import SilhouetteParams, median_background


def _estimate(rig, views):
    samples = [sample_camera(images, working_size(camera.size)) for camera, images in zip(rig, views, strict=True)]
    return estimate_backgrounds(samples, list(rig), scene.VOLUME, SilhouetteParams())


def _error(image: np.ndarray, truth: np.ndarray, where: np.ndarray) -> float:
    """Mean over the pixels ``where`` of the largest channel difference (grey levels)."""
    return float(np.abs(image.astype(int) - truth)[where].max(axis=1).mean())


@pytest.fixture(scope="module")
def still_then_moving():
    rig = scene.ring()
    backgrounds = scene.rooms(rig)
    views = scene.frames(rig, backgrounds, scene.still_then_moving())
    return rig, backgrounds, views, _estimate(rig, views)


def test_the_median_keeps_a_ghost_of_a_subject_who_stood_still_and_the_estimate_does_not(still_then_moving):
    rig, backgrounds, views, estimates = still_then_moving
    for camera, truth, images, estimate in zip(rig, backgrounds, views, estimates, strict=True):
        ghost = scene.subject_mask(camera, (0.0, 0.0)) > 0  # where he stood for 18 of the 30 frames
        assert _error(median_background(images, max_frames=len(images)), truth, ghost) > 40  # the test's premise
        assert _error(estimate.image, truth, ghost) < 4  # sensor noise 2: the median of a dozen bare samples
        assert _error(estimate.image, truth, ~ghost) < 4
        assert estimate.unresolved_share == 0.0
        assert estimate.samples == len(images) and estimate.ghost_samples == 18


def test_a_subject_who_never_leaves_his_spot_is_reported():
    rig = scene.ring()
    backgrounds = scene.rooms(rig, seed=3)
    swaying = np.column_stack([0.15 * np.sin(np.arange(24)), np.zeros(24)])  # never more than 15 cm away
    estimates = _estimate(rig, scene.frames(rig, backgrounds, swaying))
    for camera, estimate in zip(rig, estimates, strict=True):
        core = np.ones((scene.SIZE[1], scene.SIZE[0]), bool)
        for offset in swaying[:, 0]:  # the pixels he covers in every frame
            core &= scene.subject_mask(camera, (offset, 0.0)) > 0
        # The hull finds him around his core, part of which is reported (inpainted); the rest, one colour
        # in every sample, the samples cannot tell from the room.
        assert core.any() and estimate.found_samples == 24
        assert estimate.unresolved_share >= 0.1 * core.mean()


def test_a_subject_who_never_moves_is_not_found_and_says_so():
    rig = scene.ring(4)
    estimates = _estimate(rig, scene.frames(rig, scene.rooms(rig, seed=4), np.zeros((12, 2))))
    assert all(estimate.found_samples == 0 for estimate in estimates)


def test_frames_before_a_subject_walks_in_and_stands_still_make_the_background():
    rig = scene.ring()
    backgrounds = scene.rooms(rig, seed=6)
    path = np.vstack([np.full((10, 2), 9.0), np.zeros((14, 2))])  # out of view, then still for 14 of 24 frames
    estimates = _estimate(rig, scene.frames(rig, backgrounds, path))
    for camera, truth, estimate in zip(rig, backgrounds, estimates, strict=True):
        assert _error(estimate.image, truth, scene.subject_mask(camera, (0.0, 0.0)) > 0) < 4
        assert estimate.ghost_samples == 14 and estimate.found_samples == 14


def test_frames_before_the_subject_walks_in_are_kept():
    rig = scene.ring()
    backgrounds = scene.rooms(rig, seed=5)
    path = np.vstack([np.full((20, 2), 9.0), scene.still_then_moving(12, 4)])  # 20 frames far out of view
    estimates = _estimate(rig, scene.frames(rig, backgrounds, path))
    for camera, truth, estimate in zip(rig, backgrounds, estimates, strict=True):
        assert estimate.ghost_samples == 0 and estimate.found_samples == 12
        assert _error(estimate.image, truth, scene.subject_mask(camera, (0.0, 0.0)) > 0) < 4


def test_a_blob_that_one_camera_alone_sees_does_not_hide_the_background_from_the_others(still_then_moving):
    rig, backgrounds, views, _ = still_then_moving
    views = [list(images) for images in views]
    for k in range(len(views[0])):  # a reflection in camera 0 only, in every frame: part of its background
        views[0][k][5:25, 5:30] = (250, 250, 250)
    estimates = _estimate(rig, views)
    assert np.abs(estimates[0].image[5:25, 5:30].astype(int) - 250).max() <= 2 * scene.NOISE_SIGMA + 1
    for camera, truth, estimate in zip(rig, backgrounds, estimates, strict=True):
        ghost = scene.subject_mask(camera, (0.0, 0.0)) > 0
        assert _error(estimate.image, truth, ghost) < 4


def test_a_camera_with_a_clean_plate_keeps_it_and_its_silhouettes_still_vote(still_then_moving):
    rig, backgrounds, views, _ = still_then_moving
    samples = [sample_camera(images, working_size(camera.size), plate=backgrounds[0] if index == 0 else None)
               for index, (camera, images) in enumerate(zip(rig, views, strict=True))]
    estimates = estimate_backgrounds(samples, list(rig), scene.VOLUME, SilhouetteParams())
    assert estimates[0].image is backgrounds[0]
    camera, truth = rig[1], backgrounds[1]
    assert _error(estimates[1].image, truth, scene.subject_mask(camera, (0.0, 0.0)) > 0) < 4


def test_masked_median_is_the_median_of_the_samples_left():
    rng = np.random.default_rng(0)
    values = rng.integers(0, 256, (9, 50, 3), dtype=np.uint8)
    values[0, :5] = 255  # kept samples equal to the value the covered ones sort as
    covered = rng.random((9, 50)) < 0.4
    median, count = masked_median(values, covered)
    assert np.array_equal(count, (~covered).sum(axis=0))
    for pixel in np.flatnonzero(count):
        kept = values[~covered[:, pixel], pixel].astype(float)
        assert np.all(np.abs(median[pixel] - np.median(kept, axis=0)) <= 0.5)


def test_working_camera_sees_points_where_the_resized_image_shows_them():
    camera = scene.ring()[2]
    small = working_camera(camera, (40, 30))  # a quarter of 160 x 120
    X = np.array([[0.1, 0.2, 1.0], [-0.5, 0.3, 0.2], [0.4, -0.4, 1.8]])
    # A 4 x 4 block of full-resolution pixels, centres 0..3, is working pixel 0 with its centre at 1.5.
    assert np.allclose(small.project(X), (camera.project(X) - 1.5) / 4, atol=1e-9)


def test_sample_counts_and_working_sizes():
    assert sample_count(1000, (580, 780, 3)) == 48
    assert sample_count(5, (580, 780, 3)) == 5  # a short capture: all its frames
    assert 9 <= sample_count(1000, (1920, 1080 * 4, 3)) < 48  # a large image: fewer, within the memory bound
    assert working_size((160, 120)) == (160, 120)
    assert working_size((780, 580)) == (260, 193)
    assert MIN_UNCOVERED >= 1


def test_samples_of_different_sizes_or_counts_are_refused():
    rig = scene.ring(4)
    image = np.zeros((120, 160, 3), np.uint8)
    with pytest.raises(InputError, match="different shapes"):
        sample_camera([image, np.zeros((60, 80, 3), np.uint8)], (160, 120))
    with pytest.raises(InputError, match="at least one frame"):
        sample_camera([], (160, 120))
    samples = [sample_camera([image] * (3 if index else 2), (160, 120)) for index in range(4)]
    with pytest.raises(InputError, match="same frames"):
        estimate_backgrounds(samples, list(rig), scene.VOLUME, SilhouetteParams())


def test_a_plate_fit_finds_the_shift_between_plate_and_frame_and_tells_another_view():
    rng = np.random.default_rng(3)
    room = cv2.GaussianBlur(rng.uniform(0, 255, (290, 390, 3)).astype(np.uint8), (0, 0), 1.0)
    room = cv2.resize(room, (780, 580), interpolation=cv2.INTER_CUBIC)  # texture a few pixels across
    frame = shifted_plate(room, (2.5, -1.25))
    cv2.rectangle(frame, (300, 150), (420, 520), (40, 60, 200), -1)  # the person, in the frame only
    fit = plate_fit(room, frame)
    assert fit.shift == pytest.approx((2.5, -1.25), abs=0.1) and fit.match > 0.3
    assert plate_fit(room, room).distance_px < 0.01
    aligned = shifted_plate(room, fit.shift).astype(int)
    assert np.abs(aligned - frame)[10:140, 10:-10].mean() < 2.0  # the room above the person agrees
    elsewhere = cv2.GaussianBlur(rng.uniform(0, 255, (580, 780, 3)).astype(np.uint8), (0, 0), 4.0)
    assert plate_fit(elsewhere, frame).match < MIN_PLATE_MATCH


def test_a_plate_without_the_colour_of_its_frames_is_told():
    rng = np.random.default_rng(4)
    room = cv2.GaussianBlur(rng.uniform(0, 255, (580, 780, 3)).astype(np.uint8), (0, 0), 2.0)
    grey = cv2.cvtColor(cv2.cvtColor(room, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)
    assert plate_fit(grey, room).colourless and not plate_fit(room, room).colourless
    assert not plate_fit(grey, grey).colourless  # a monochrome camera's plate and frames
    offset = np.clip(grey.astype(int) + [0, 2, 5], 0, 255).astype(np.uint8)  # its video's channels a step apart
    assert not plate_fit(grey, offset).colourless
