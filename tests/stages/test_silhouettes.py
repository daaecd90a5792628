import cv2
import numpy as np
import pytest

from calib.camera import Camera
from calib.errors import InputError
from stages.silhouettes import (
    SilhouetteParams,
    background_model,
    extract_silhouette,
    extract_silhouettes,
    floor_geometry,
    median_background,
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


# A studio seen by a ring of cameras: a plain floor (z = 0) under a grey wall, a person standing at the
# origin as a vertical cylinder, and the person's soft contact shadow on the floor around the feet.
FLOOR, WALL = np.array([80.0, 110.0, 140.0]), np.array([150.0, 150.0, 150.0])  # BGR
PERSON_RADIUS_M, PERSON_HEIGHT_M, SHADOW_RADIUS_M = 0.2, 1.7, 0.6


def _ring(count: int) -> list[Camera]:
    angles = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    return [Camera.look_at(f"cam{i}", (3.0 * np.cos(a), 3.0 * np.sin(a), 1.6), (0.0, 0.0, 0.8), f_px=300.0,
                           size=(WIDTH, HEIGHT)) for i, a in enumerate(angles)]


def _render(camera: Camera, clothing: np.ndarray | None, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(image, true mask) of the studio by ray casting; ``clothing`` None: the empty studio (the clean plate)."""
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH]
    rays = camera.pixel_rays(np.column_stack([u.ravel(), v.ravel()]).astype(float))
    centre = camera.centre
    with np.errstate(divide="ignore", invalid="ignore"):
        to_floor = -centre[2] / rays[:, 2]
    floor = np.isfinite(to_floor) & (to_floor > 0)
    ground = centre[:2] + np.where(floor, to_floor, 0.0)[:, None] * rays[:, :2]
    image = np.where(floor[:, None], FLOOR, WALL)
    if clothing is None:
        return _noisy(image, rng), np.zeros((HEIGHT, WIDTH), np.uint8)
    radius = np.linalg.norm(ground, axis=1)
    darkening = 0.45 * np.clip(1.0 - radius / SHADOW_RADIUS_M, 0.0, 1.0) ** 0.5  # soft, darkest at the feet
    image = image * (1.0 - np.where(floor, darkening, 0.0))[:, None]
    # Ray and cylinder x² + y² = r²: a s² + b s + c = 0 along the ray, the nearer root, within the height.
    a = (rays[:, :2] ** 2).sum(axis=1)
    b = 2.0 * rays[:, :2] @ centre[:2]
    c = centre[:2] @ centre[:2] - PERSON_RADIUS_M**2
    with np.errstate(invalid="ignore"):
        s = (-b - np.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)
    z = centre[2] + s * rays[:, 2]
    person = np.isfinite(s) & (s > 0) & (z >= 0) & (z <= PERSON_HEIGHT_M)
    image[person] = clothing
    return _noisy(image, rng), (person.reshape(HEIGHT, WIDTH) * 255).astype(np.uint8)


def _noisy(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    noisy = image.reshape(HEIGHT, WIDTH, 3) + rng.normal(0.0, 2.0, (HEIGHT, WIDTH, 3))
    return np.clip(noisy, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("clothing", [np.array([40.0, 40.0, 160.0]), 0.55 * FLOOR], ids=["red", "floor-like"])
def test_floor_shadows_are_removed_and_dark_clothing_of_the_floor_s_hue_is_kept(clothing):
    rng = np.random.default_rng(10)
    cameras = _ring(5)
    backgrounds = [_render(camera, None, rng)[0] for camera in cameras]
    frames, truths = zip(*(_render(camera, clothing, rng) for camera in cameras), strict=True)
    floor = floor_geometry(cameras, np.array([[-2.0, -2.0, 0.0], [2.0, 2.0, 2.0]]), SilhouetteParams())
    masks = extract_silhouettes(frames, backgrounds, floor, SilhouetteParams())
    for mask, truth in zip(masks, truths, strict=True):
        assert _iou(mask, truth) > 0.9
    # Without a shadow test the shadow is taken for the person; the single-view colour rule also takes
    # the clothing of the floor's hue, darker than the floor, for a shadow.
    unshadowed = extract_silhouettes(frames, backgrounds, floor, SilhouetteParams(shadows="none"))
    assert np.mean([_iou(mask, truth) for mask, truth in zip(unshadowed, truths, strict=True)]) < 0.8
    if np.allclose(clothing, 0.55 * FLOOR):
        by_colour = extract_silhouettes(frames, backgrounds, floor, SilhouetteParams(shadows="colour"))
        assert np.mean([_iou(mask, truth) for mask, truth in zip(by_colour, truths, strict=True)]) < 0.5


def test_extract_silhouettes_rejects_mismatched_views():
    image = np.zeros((HEIGHT, WIDTH, 3), np.uint8)
    params = SilhouetteParams()
    floor = floor_geometry(_ring(2), np.array([[-1, -1, 0], [1, 1, 2.0]]), params)
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
