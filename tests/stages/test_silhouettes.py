import dataclasses

import cv2
import numpy as np
import pytest
import shadow_studio as studio

from calib.errors import InputError
from stages.silhouettes import (
    SilhouetteParams,
    background_model,
    extract_silhouette,
    extract_silhouettes,
    floor_geometry,
    floor_shifts,
    measure_evidence,
    median_background,
    shifted_floor,
)

HEIGHT, WIDTH = 290, 390


def _textured_background(rng: np.random.Generator) -> np.ndarray:
    """(H, W, 3) uint8 smooth random colours, like a cluttered room out of focus."""
    coarse = rng.uniform(40, 210, (HEIGHT // 15 + 1, WIDTH // 15 + 1, 3)).astype(np.uint8)
    return cv2.resize(coarse, (WIDTH, HEIGHT), interpolation=cv2.INTER_LINEAR)


def _person_mask() -> np.ndarray:
    """(H, W) uint8 a body, an outstretched arm, and an arm with the hand on the hip enclosing a gap."""
    mask = np.zeros((HEIGHT, WIDTH), np.uint8)
    cv2.ellipse(mask, (190, 150), (32, 105), 0, 0, 360, 255, -1)
    cv2.ellipse(mask, (140, 110), (45, 8), -25, 0, 360, 255, -1)
    cv2.ellipse(mask, (215, 150), (40, 45), 0, -90, 90, 255, 12)
    return mask


def _scene(rng, *, shadow_factor=0.6, noise_sigma=6.0, jpeg_quality=60):
    """(image, background, true mask, shadow region): a person with a cast shadow, noise and JPEG loss."""
    background = _textured_background(rng)
    truth = _person_mask()
    image = background.copy()
    image[truth > 0] = (60, 80, 200)  # clothing: a colour unlike the shadowed background
    shadow = np.zeros((HEIGHT, WIDTH), bool)
    shadow[250:280, 120:300] = True
    shadow &= truth == 0
    image[shadow] = (image[shadow] * shadow_factor).astype(np.uint8)
    image = np.clip(image + rng.normal(0.0, noise_sigma, image.shape), 0, 255).astype(np.uint8)
    _, encoded = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
    return cv2.imdecode(encoded, cv2.IMREAD_COLOR), background, truth, shadow


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return ((a > 0) & (b > 0)).sum() / max(((a > 0) | (b > 0)).sum(), 1)


@pytest.mark.parametrize("downsample", [1, 2])
def test_silhouette_of_noisy_compressed_frame_with_shadow_matches_truth(downsample):
    image, background, truth, shadow = _scene(np.random.default_rng(1))
    mask = extract_silhouette(image, background, SilhouetteParams(downsample=downsample, shadows="colour"))
    assert mask.dtype == np.uint8 and mask.shape == truth.shape
    assert set(np.unique(mask)) <= {0, 255}
    assert _iou(mask, truth) > 0.96  # thin limbs on a small image: a 1 px rim is 2 % of the area
    assert (mask[shadow] > 0).mean() < 0.01  # the shadow is not the person


def test_gap_between_arm_and_body_stays_open_but_noise_holes_are_filled():
    image, background, truth, _ = _scene(np.random.default_rng(2), noise_sigma=2.0)
    holes = np.zeros_like(truth)
    cv2.circle(holes, (190, 60), 3, 255, -1)
    image[holes > 0] = background[holes > 0]  # clothing that matches the background
    mask = extract_silhouette(image, background, SilhouetteParams(downsample=1))
    assert (mask[holes > 0] > 0).all()
    _, labels = cv2.connectedComponents(255 - truth, connectivity=4)
    gap = (labels > 0) & (labels != labels[0, 0])  # the background enclosed by arm and body
    assert gap.sum() > 50 and (mask[gap] == 0).mean() > 0.8


def test_speckle_noise_far_from_person_is_removed():
    image, background, truth, _ = _scene(np.random.default_rng(3))
    image[20:23, 20:23] = (255, 255, 255)
    mask = extract_silhouette(image, background, SilhouetteParams())
    assert (mask[10:35, 10:35] == 0).all()


def test_frame_equal_to_background_gives_empty_mask():
    background = _textured_background(np.random.default_rng(4))
    mask = extract_silhouette(background, background, SilhouetteParams())
    assert mask.shape == (HEIGHT, WIDTH) and not mask.any()


def test_frame_entirely_different_from_background_gives_full_mask():
    background = np.full((HEIGHT, WIDTH, 3), 200, np.uint8)
    image = np.zeros_like(background)
    image[:] = (200, 20, 20)
    mask = extract_silhouette(image, background, SilhouetteParams())
    assert (mask == 255).all()


def test_a_faint_person_in_a_noiseless_frame_is_found():
    # Every background pixel is an exact copy (a render, a still scene): what differs is the person, whose
    # own contrast must not be taken for the noise level.
    background = _textured_background(np.random.default_rng(7))
    truth = _person_mask()
    image = background.astype(int)
    image[truth > 0] += 20
    mask = extract_silhouette(np.clip(image, 0, 255).astype(np.uint8), background, SilhouetteParams())
    assert _iou(mask, truth) > 0.9


def test_clothing_a_few_noise_levels_from_a_plain_wall_is_found():
    rng = np.random.default_rng(6)
    stains = rng.uniform(-8, 8, (HEIGHT // 60 + 1, WIDTH // 60 + 1, 1))
    background = np.clip(np.array([170.0, 180.0, 185.0]) + cv2.resize(stains, (WIDTH, HEIGHT))[:, :, None], 0, 255)
    background = background.astype(np.uint8)
    truth = _person_mask()
    image = background.astype(float)
    image[truth > 0] += (9.0, -6.0, 7.0)  # camouflage: about 13 levels away, far below a fixed threshold
    image = np.clip(image + rng.normal(0.0, 2.0, image.shape), 0, 255).astype(np.uint8)
    mask = extract_silhouette(image, background, SilhouetteParams())
    assert _iou(mask, truth) > 0.9


def test_a_change_of_exposure_is_not_a_person():
    background = _textured_background(np.random.default_rng(7))
    darker = np.clip(background * 0.9 + np.random.default_rng(8).normal(0.0, 2.0, background.shape), 0, 255)
    mask = extract_silhouette(darker.astype(np.uint8), background, SilhouetteParams())
    assert not mask.any()


def test_background_model_gives_the_same_mask_as_the_background_image():
    image, background, _, _ = _scene(np.random.default_rng(9))
    params = SilhouetteParams()
    model = background_model(background, params)
    from_model, from_image = (extract_silhouette(image, b, params) for b in (model, background))
    np.testing.assert_array_equal(from_model, from_image)
    with pytest.raises(InputError, match="downsample"):
        extract_silhouette(image, model, SilhouetteParams(downsample=1))
    with pytest.raises(InputError, match="model of"):
        extract_silhouette(image[:100], model, params)


def test_median_background_removes_a_moving_person():
    rng = np.random.default_rng(5)
    background = _textured_background(rng)
    frames = []
    for shift in range(0, 200, 20):
        frame = background.copy()
        frame[100:200, shift:shift + 30] = (0, 0, 255)
        frames.append(frame)
    estimate = median_background(frames)
    assert estimate.dtype == np.uint8 and np.abs(estimate.astype(int) - background).max() <= 1


def test_median_background_rejects_no_images_and_mixed_sizes():
    with pytest.raises(InputError, match="at least one"):
        median_background([])
    with pytest.raises(InputError, match="different shapes"):
        median_background([np.zeros((4, 4, 3), np.uint8), np.zeros((5, 4, 3), np.uint8)])


def test_extract_silhouette_rejects_mismatched_background():
    image = np.zeros((10, 10, 3), np.uint8)
    with pytest.raises(InputError, match="background"):
        extract_silhouette(image, np.zeros((10, 12, 3), np.uint8), SilhouetteParams())
    with pytest.raises(InputError, match="image"):
        extract_silhouette(image[..., 0], image, SilhouetteParams())


def test_params_reject_inverted_shadow_band():
    with pytest.raises(InputError, match="shadow_min"):
        SilhouetteParams(shadow_min=0.9, shadow_max=0.8)


def test_params_reject_an_unknown_shadow_test():
    with pytest.raises(InputError, match="shadows"):
        SilhouetteParams(shadows="sun")


@pytest.mark.parametrize("clothing", [np.array([40.0, 40.0, 160.0]), 0.55 * studio.FLOOR], ids=["red", "floor-like"])
def test_floor_shadows_are_removed_and_dark_clothing_of_the_floor_s_hue_is_kept(clothing):
    rng = np.random.default_rng(10)
    cameras = studio.ring(5)
    backgrounds = [studio.render(camera, None, rng)[0] for camera in cameras]
    frames, truths = zip(*(studio.render(camera, clothing, rng) for camera in cameras), strict=True)
    floor = floor_geometry(cameras, studio.VOLUME, SilhouetteParams())
    masks = extract_silhouettes(frames, backgrounds, floor, SilhouetteParams())
    for mask, truth in zip(masks, truths, strict=True):
        assert _iou(mask, truth) > 0.9
    # Without a shadow test the shadow is taken for the person; the single-view colour rule also takes
    # the clothing of the floor's hue, darker than the floor, for a shadow.
    unshadowed = extract_silhouettes(frames, backgrounds, floor, SilhouetteParams(shadows="none"))
    assert np.mean([_iou(mask, truth) for mask, truth in zip(unshadowed, truths, strict=True)]) < 0.8
    if np.allclose(clothing, 0.55 * studio.FLOOR):
        by_colour = extract_silhouettes(frames, backgrounds, floor, SilhouetteParams(shadows="colour"))
        assert np.mean([_iou(mask, truth) for mask, truth in zip(by_colour, truths, strict=True)]) < 0.5


def test_floor_shifts_find_where_the_views_see_the_floor_under_a_calibration_off_by_centimetres():
    # Clothing of the floor's hue, darker than it, makes the floor test decide: the cameras are calibrated 6 cm off
    # where they stand, each in a direction of its own, so that their floor points land off the shadow in the other
    # views, which then vote against it. The shadows' darkening says where the views see them.
    rng = np.random.default_rng(11)
    cameras = studio.ring(5)
    backgrounds = [studio.render(camera, None, rng)[0] for camera in cameras]
    params, volume = SilhouetteParams(), studio.VOLUME
    views = []  # two frames, their noise drawn anew
    for _ in range(2):
        frames, truths = zip(*(studio.render(camera, 0.55 * studio.FLOOR, rng) for camera in cameras), strict=True)
        views.append([measure_evidence(frame, background, params)
                      for frame, background in zip(frames, backgrounds, strict=True)])
    sound = floor_geometry(cameras, volume, params)
    assert not np.any(floor_shifts(views, sound, params))  # the calibration's own mapping is left as it is
    directions = rng.normal(size=(len(cameras), 3))
    moved = [dataclasses.replace(camera, t=-camera.R @ (camera.centre + 0.06 * d / np.linalg.norm(d)))
             for camera, d in zip(cameras, directions, strict=True)]
    off = floor_geometry(moved, volume, params)
    shifts = floor_shifts(views, off, params)
    assert shifts.shape == (5, 5, 2) and np.count_nonzero(np.abs(shifts).sum(axis=2)) >= 10

    def mean_iou(floor):
        masks = extract_silhouettes(frames, backgrounds, floor, params)
        return np.mean([_iou(mask, truth) for mask, truth in zip(masks, truths, strict=True)])

    truly, as_calibrated, shifted = mean_iou(sound), mean_iou(off), mean_iou(shifted_floor(off, shifts))
    assert as_calibrated < truly - 0.05  # the shadows kept as the person's feet
    assert shifted > truly - 0.03  # most of it mended


def test_a_shifted_floor_is_also_looked_at_shifted_and_not_where_the_shift_leaves_the_view():
    params = SilhouetteParams()
    floor = floor_geometry(studio.ring(3), studio.VOLUME, params)
    shifts = np.zeros((3, 3, 2), int)
    shifts[0, 1] = (0, WIDTH)  # a whole frame across: nothing of camera 0's floor is where camera 1 sees
    shifts[0, 2] = (1, -2)
    moved = shifted_floor(floor, shifts)
    assert moved.seen_at is floor.seen_at  # the calibration's own places are still looked at
    assert np.all(moved.shifted_at[0][1] == -1) and np.any(floor.seen_at[0][1] >= 0)
    width = floor.working_shapes[2][1]
    kept = (floor.seen_at[0][2] >= 0) & (moved.shifted_at[0][2] >= 0)
    assert kept.any() and np.all(moved.shifted_at[0][2][kept] - floor.seen_at[0][2][kept] == width - 2)
    assert all(pixels is None for pixels in moved.shifted_at[1])  # no shift: nowhere else to look


def test_extract_silhouettes_rejects_mismatched_views():
    image = np.zeros((HEIGHT, WIDTH, 3), np.uint8)
    params = SilhouetteParams()
    floor = floor_geometry(studio.ring(2), np.array([[-1, -1, 0], [1, 1, 2.0]]), params)
    with pytest.raises(InputError, match="as many"):
        extract_silhouettes([image, image], [image], floor, params)
    with pytest.raises(InputError, match="floor geometry"):
        extract_silhouettes([image[:100], image[:100]], [image[:100], image[:100]], floor, params)



def test_clothing_close_to_the_wall_is_found_after_a_change_of_white_balance():
    rng = np.random.default_rng(11)
    background = np.full((HEIGHT, WIDTH, 3), (170.0, 180.0, 185.0))
    truth = _person_mask()
    image = background.copy()
    image[truth > 0] += (12.0, -9.0, 10.0)  # about 18 levels from the wall
    image = image * np.array([1.06, 1.0, 0.94])  # the camera's automatic white balance moved since the plate
    image = np.clip(image + rng.normal(0.0, 2.0, image.shape), 0, 255).astype(np.uint8)
    mask = extract_silhouette(image, background.astype(np.uint8), SilhouetteParams())
    assert _iou(mask, truth) > 0.9


def _wall_and_floor(rng: np.random.Generator, wall: tuple[float, float, float], rows: int) -> np.ndarray:
    """(H, W, 3) float a wall of colour ``wall`` over the first ``rows`` rows and a dark wooden floor below,
    both slightly mottled."""
    background = np.empty((HEIGHT, WIDTH, 3))
    background[:rows] = wall
    background[rows:] = (60.0, 75.0, 95.0)
    return background + cv2.resize(rng.uniform(-6, 6, (HEIGHT // 20, WIDTH // 20, 3)), (WIDTH, HEIGHT))


def _person_after_a_tone_change(background: np.ndarray, tone: str, rng: np.random.Generator):
    """The person painted over ``background`` (H, W, 3) float, the frame's levels then changed by ``tone``
    ("gamma": the exposure lowered before the camera's gamma; "black level": the blacks lifted) and sensor noise
    added: (image (H, W, 3) uint8, the person's mask)."""
    truth = _person_mask()
    image = background.copy()
    image[truth > 0] = (120.0, 110.0, 150.0)
    image = 255.0 * (image / 255.0) ** 1.25 if tone == "gamma" else image * 0.85 + 20.0
    return np.clip(image + rng.normal(0.0, 2.0, image.shape), 0, 255).astype(np.uint8), truth


@pytest.mark.parametrize("tone", ["gamma", "black level"])
def test_a_change_of_tone_curve_over_a_bright_wall_and_a_dark_floor_is_not_a_person(tone):
    # The camera's automatic exposure acts before its gamma (or a grabber lifts the black level): the frame's
    # levels are no longer the plate's times one ratio per channel, and a ratio fitted to the floor, most of
    # the image, would put the whole wall in the mask.
    rng = np.random.default_rng(12)
    background = _wall_and_floor(rng, (200.0, 205.0, 190.0), HEIGHT // 3)  # a bright wall
    image, truth = _person_after_a_tone_change(background, tone, rng)
    mask = extract_silhouette(image, np.clip(background, 0, 255).astype(np.uint8), SilhouetteParams())
    assert _iou(mask, truth) > 0.9


@pytest.mark.parametrize("tone", ["gamma", "black level"])
def test_a_bright_strip_few_pixels_have_is_not_a_person_after_a_change_of_tone_curve(tone):
    # A white skirting board: its levels are too rare in the image for the tone curve to be measured there, so
    # the curve is extrapolated from the wall's and the floor's levels, and a gain through black alone misses it
    # by more than the noise after the exposure moved before the camera's gamma (or a black level was lifted).
    rng = np.random.default_rng(13)
    background = _wall_and_floor(rng, (150.0, 155.0, 140.0), HEIGHT // 2)
    strip = np.zeros((HEIGHT, WIDTH), bool)
    strip[HEIGHT // 2 - 12 : HEIGHT // 2, :200] = True
    background[strip] = np.repeat(np.linspace(196.0, 244.0, 200)[None, :, None], 12, axis=0).reshape(-1, 1)
    image, truth = _person_after_a_tone_change(background, tone, rng)
    mask = extract_silhouette(image, np.clip(background, 0, 255).astype(np.uint8), SilhouetteParams())
    away = strip & (cv2.dilate(truth, np.ones((9, 9), np.uint8)) == 0)
    assert (mask[away] > 0).mean() < 0.02
    assert _iou(mask, truth) > 0.9
