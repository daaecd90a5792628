"""Person silhouettes from colour images and a background model.

A pixel is foreground when it differs from the background by more than the noise, in a way that lighting
cannot explain. We follow Horprasert, Harwood & Davis (ICCV Frame-Rate Workshop 1999): write the pixel
colour I (3,) as a brightness-scaled copy of the background colour B (3,) plus a remainder,

    I = α B + r,   α = (I · B) / (B · B)   (brightness distortion),   ‖r‖ (chromaticity distortion),

so a shadow lowers α but leaves ‖r‖ small, while a person in front of the background changes the colour
direction or the brightness. As in that paper, distortions are measured in units of the noise; with a
clean plate instead of a training sequence, the noise is estimated from each frame:

- the camera's exposure and white balance may drift from the plate's (flicker, automatic white balance,
  a codec shifting levels): each channel has its exposure ratio g_k, fitted on the half of the image
  that is surely background (see :func:`_noise`), and the background model is G B with G = diag(g); α and
  the distortions below are taken against G B;
- the noise level σ comes from the lower quartile of ‖I − GB‖ over the image, and grows where the
  background is textured, because a sub-pixel shift or compression changes a textured pixel by about its
  gradient times the shift: σ_p² = σ² + (κ ‖∇B‖)² / 3.

The evidence is ‖I − GB‖ / σ_p, except on shadows, where only the chromaticity distortion counts. A
pixel looks like a shadow when it is darker than the background by as much as a shadow darkens
(α between ``shadow_min`` and ``shadow_max``) with its colour direction unchanged. Colour alone cannot
tell a shadow from dark clothing in front of a background of the same hue (navy trousers on a blue mat, a
grey shirt on a lighter grey wall), and taking every such pixel for a shadow cuts the person away there.
Geometry can: a person's shadow lies on the floor and darkens it alike from every side, so a
shadow-like pixel is a shadow only when the other cameras see the floor point behind it darkened too
(:func:`floor_shadows`; all the views of a frame are segmented together, :func:`extract_silhouettes`).
Pixels above ``strong_threshold`` seed the person; connected regions above
``weak_threshold`` join them (hysteresis, as in Canny's edge detector), so clothing close to the
background is kept without letting isolated noise in; a weak region must be more than a line, so that
the rim of a shadow does not grow out of the feet. Morphology, connected components and hole filling
clean the mask. Its outline is then placed where each pixel is half person: near the outline every pixel
is a mix of the person's colour nearby and the (possibly shadowed) background, and its share of person
is measured (a matting step). Everything runs with OpenCV's vectorised operations at a reduced working
resolution (``downsample``; averaging also cancels noise); the person's share is interpolated back to
full resolution, so the outline stays sub-pixel smooth. The per-camera part of the work can be done once
with :func:`background_model`.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from calib.camera import Camera
from calib.errors import InputError
from stages.checks import check_int, check_number

# Added to B·B before dividing, so a pure black background pixel gives α = 0 rather than a division
# by zero (8-bit squared units: far below the B·B = 3 of the darkest non-black pixel).
BACKGROUND_ENERGY_FLOOR = 1e-3
# Every SAMPLE_STRIDE-th pixel along both axes enters the exposure and noise estimates: a few thousand
# pixels fix a median or a quartile to well under a percent, at a sixteenth of the cost.
SAMPLE_STRIDE = 4
# The 25th percentile of a χ² variable with 3 degrees of freedom: ‖I − GB‖² / σ² of background pixels
# under Gaussian noise of σ per channel, so σ² = (lower quartile of ‖I − GB‖²) / this.
CHI2_3_LOWER_QUARTILE = 1.2125
# Bounds on the per-channel noise σ (8-bit levels). Below: 8-bit quantisation, after blur and averaging,
# is still about this much. Above: heavier than any usable camera's noise; a larger lower quartile means
# the person (or a change of lighting) covers most of the image, and the quartile is no longer noise.
NOISE_SIGMA_MIN = 0.5
NOISE_SIGMA_MAX = 6.0
# Fewest sampled pixels that differ from the background for a noise estimate; with fewer, or fewer than half
# of the sample, the frame is mostly an exact copy of the background (a still scene from a video codec, a
# noiseless render) and its noise is the lower bound: what differs is then mostly the person, not noise.
MIN_NOISE_SAMPLES = 100
# The search for the person looks at blocks of COARSE_FACTOR x COARSE_FACTOR working pixels (a sixteenth of
# the cost), then works on the box around what it found plus COARSE_MARGIN blocks (parts of the person too
# faint to show on blocks lie next to parts that do).
COARSE_FACTOR = 4
COARSE_MARGIN = 3
# Bounds on each channel's exposure ratio g_k between frame and background: drift, white balance and codec
# level shifts stay well inside; outside, the median is not the background's (a person filling the view)
# and is not trusted.
EXPOSURE_RATIO_RANGE = (0.7, 1.4)
# Matting (full-resolution pixels): the person's colour next to the outline is the mean of the mask's
# pixels at least CORE_DEPTH_PX inside it (lens blur and compression mix the outermost ones) within
# MATTE_RADIUS_PX, and the outline is measured on pixels up to MATTE_RADIUS_PX from it, on both sides.
CORE_DEPTH_PX = 2
MATTE_RADIUS_PX = 4
# The person's share of a pixel is measured only where the person's colour differs from the background by
# more than this (8-bit levels); closer colours make it too noisy, and the mask decides.
MIN_MATTE_CONTRAST = 8.0
# Magnitude (a share of the pixel) given to the outline score where the mask decides.
SCORE_FLOOR = 0.1
# The floor test looks at the floor behind blocks of FLOOR_BLOCK x FLOOR_BLOCK working pixels at once
# (a shadow's darkening changes over many pixels; a quarter of the look-up tables' size and making).
FLOOR_BLOCK = 2
#: Choices of ``SilhouetteParams.shadows``.
SHADOW_TESTS = ("floor", "colour", "none")
# The floor test compares a shadow-like pixel's darkening 1 − α/g with that of its floor point in another
# view: a shadow darkens a matt floor alike from every side, so the other view must see at least this share
# of it. The fifth left over allows for noise and for a soft rim, where the darkening fades out over a few
# pixels that a calibration error can shift; the lower legs, whose floor points lie in the lighter outer
# part of the shadow, see less than that.
SHADOW_AGREEMENT = 0.8
# cv2.transform's matrix summing the three channels of each pixel.
_CHANNEL_SUM = np.ones((1, 3), np.float32)


@dataclass(frozen=True)
class SilhouetteParams:
    """Thresholds of the foreground test and of the clean-up, in units of the noise and in pixels.

    Attributes
    ----------
    downsample : int
        The per-pixel test runs on an image this many times smaller in each direction (1 = full
        resolution), then the outline is interpolated back; 2 halves the cost four times over and averages
        noise away.
    blur_kernel_px : int
        Size of a Gaussian blur kernel (odd; at the working resolution) applied before the foreground test
        only, for very noisy input; 1 = none (the thresholds already follow the noise, and a blur widens
        the person's edges, which the weak threshold then takes in).
    strong_threshold : float
        Evidence ‖I − GB‖ / σ (in noise standard deviations) above which a pixel seeds the person: high
        enough that noise alone practically never reaches it.
    weak_threshold : float
        Evidence above which a pixel is person when its region holds a seed: low enough to keep clothing
        close to the background colour, high enough that the noise does not grow a halo.
    shadow_min, shadow_max : float
        Pixels whose brightness relative to the background, α, lies in [min, max] and whose colour
        direction has not changed (chromaticity distortion below ``weak_threshold``) look like a shadow
        (at darkest ``shadow_min``, at faintest ``shadow_max``). Darker or brighter changes are never
        shadows.
    shadows : {"floor", "colour", "none"}
        Which shadow-like pixels are shadows. "floor": those whose floor point (z = 0, behind the pixel)
        looks darkened alike from the other cameras that see it (:func:`floor_shadows`): a shadow lies on
        the floor and darkens it the same from every side, while darker clothing in front of a
        background of the same hue hides a floor point that the other cameras see undarkened. Needs the
        cameras (:func:`extract_silhouettes`); a single view (:func:`extract_silhouette`) then has no
        shadow test. "colour": every shadow-like pixel (the single-view rule of Horprasert et al.; it
        also drops dark clothing in front of a similar background). "none": no shadow test.
    background_jitter_px : float
        How far (pixels) the background may seem to move between the clean plate and a frame (camera
        vibration, compression of fine texture): a textured pixel's noise grows by its gradient times this.
    opening_px, closing_px : int
        Radii of the morphological opening (removes specks) and closing (bridges thin gaps), at full
        resolution; 0 = skip.
    min_component_fraction : float
        Connected components smaller than this fraction of the largest one are dropped (a person is
        one large blob plus, at most, a few limbs separated by a thin gap).
    min_component_area_fraction : float
        Components smaller than this fraction of the image are dropped, so that noise alone never
        survives as a tiny "person".
    max_hole_fraction : float
        Background holes smaller than this fraction of the foreground area are filled (holes from
        clothing that matches the background); larger ones (the gap between an arm and the body) stay.
    multiview_check : bool
        Drop the connected parts of a view's silhouette that the other views do not confirm (a bystander
        seen by one or two cameras, a reflection, a phantom): see :mod:`stages.consistency`. Applies to
        given silhouettes too (a person segmenter marks every person).
    """

    downsample: int = 2
    blur_kernel_px: int = 1
    strong_threshold: float = 8.0
    weak_threshold: float = 4.0
    shadow_min: float = 0.5
    shadow_max: float = 1.0
    shadows: str = "floor"
    background_jitter_px: float = 0.2
    opening_px: int = 1
    closing_px: int = 2
    min_component_fraction: float = 0.05
    min_component_area_fraction: float = 2e-4
    max_hole_fraction: float = 0.01
    multiview_check: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.multiview_check, bool):
            raise InputError(f"silhouettes.multiview_check: expected true or false, got {self.multiview_check!r}")
        check_int("silhouettes.downsample", self.downsample, 1)
        for name in ("opening_px", "closing_px"):
            check_int(f"silhouettes.{name}", getattr(self, name), 0)
        for name in ("strong_threshold", "weak_threshold", "shadow_min", "shadow_max", "background_jitter_px",
                     "min_component_fraction", "min_component_area_fraction", "max_hole_fraction"):
            check_number(f"silhouettes.{name}", getattr(self, name))  # finite: NaN passes the checks below
        if not 0 < self.shadow_min < self.shadow_max <= 1:
            raise InputError(
                "silhouettes.shadow_min/shadow_max: expected 0 < shadow_min < shadow_max <= 1, "
                f"got {self.shadow_min} and {self.shadow_max}"
            )
        if self.shadows not in SHADOW_TESTS:
            raise InputError(f"silhouettes.shadows: expected one of {', '.join(SHADOW_TESTS)}, got {self.shadows!r}")
        kernel = self.blur_kernel_px
        if not (isinstance(kernel, int) and not isinstance(kernel, bool) and kernel >= 1 and kernel % 2):
            raise InputError(f"silhouettes.blur_kernel_px: expected an odd integer >= 1, got {kernel!r}")
        for name in ("weak_threshold", "background_jitter_px", "min_component_fraction",
                     "min_component_area_fraction", "max_hole_fraction"):
            if getattr(self, name) < 0:
                raise InputError(f"silhouettes.{name}: expected a value >= 0, got {getattr(self, name)}")
        if not self.strong_threshold >= self.weak_threshold:
            raise InputError(
                f"silhouettes.strong_threshold: expected a value >= weak_threshold ({self.weak_threshold}), "
                f"got {self.strong_threshold}"
            )


@dataclass(frozen=True, eq=False)
class BackgroundModel:
    """One camera's background at the working resolution, with what every frame needs from it.

    Built by :func:`background_model`; pass it to :func:`extract_silhouette` instead of the background
    image to do this work once per camera rather than once per frame.
    """

    shape: tuple[int, int, int]  # (H, W, 3) of the full-resolution images
    downsample: int
    blur_kernel_px: int
    image: np.ndarray  # (H, W, 3) uint8 the background itself
    B: np.ndarray  # (h, w, 3) uint8 background colours at the working resolution, blurred
    B_sharp: np.ndarray  # (h, w, 3) uint8 the same before the blur
    B2: np.ndarray  # (h, w, 3) float32 the squares B_k² (a frame's G B · G B is their sum weighted by g_k²)
    texture_variance: np.ndarray  # (h, w) float32 (κ ‖∇B‖)² / 3, per-channel noise variance from texture
    # Colours below are stored channels first, as :func:`_dot` wants them (a copy saved per frame).
    sample_B: np.ndarray  # (3, m) float32 every SAMPLE_STRIDE-th pixel of B_sharp along both axes, flattened
    sample_B2: np.ndarray  # (3, m) float32 their squares B_k²
    sample_divisor: np.ndarray  # (m,) float32 B·B + BACKGROUND_ENERGY_FLOOR there
    coarse_B: np.ndarray  # (3, h / COARSE_FACTOR, w / COARSE_FACTOR) float32 B_sharp averaged over blocks
    coarse_texture_variance: np.ndarray  # (h / COARSE_FACTOR, w / COARSE_FACTOR) float32 the same for the texture
    noise_floor: float  # σ (8-bit levels) below which a frame's noise estimate is not believed


def background_model(background: np.ndarray, params: SilhouetteParams, *,
                     noise_floor: float = NOISE_SIGMA_MIN) -> BackgroundModel:
    """The per-camera part of :func:`extract_silhouette`, for a background (H, W, 3) uint8.

    ``noise_floor`` is the lowest noise σ (8-bit levels, at the working resolution) a frame's estimate may
    give: by default the quantisation's; a background estimated from the frames themselves knows how much
    they scatter about it (:func:`stages.background.sample_camera`), where a single frame's estimate, made
    on the pixels that match the background best, may see less than the frames' codec leaves near the person.
    """
    background = np.asarray(background)
    if background.ndim != 3 or background.shape[2] != 3 or background.dtype != np.uint8:
        raise InputError(f"background: expected an (H, W, 3) uint8 array, got {background.dtype} {background.shape}")
    check_number("background noise floor", noise_floor, NOISE_SIGMA_MIN, NOISE_SIGMA_MAX)
    B_sharp = _downsample(background, params.downsample)
    B = _blur(B_sharp, params.blur_kernel_px)  # (h, w, 3) uint8
    # A shift of the background by κ pixels changes a pixel by about κ times the gradient, which the
    # range of each channel over the 3x3 neighbourhood (two pixels across) measures twice over.
    spread = cv2.morphologyEx(B, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8))  # (h, w, 3) uint8
    squared_gradient = cv2.transform(cv2.multiply(spread, spread, dtype=cv2.CV_32F), _CHANNEL_SUM) / 4.0
    jitter = params.background_jitter_px
    texture_variance = squared_gradient * np.float32(jitter * jitter / 3.0)
    sample_B = _channels_first(B_sharp[::SAMPLE_STRIDE, ::SAMPLE_STRIDE]).reshape(3, -1)  # the frame's is unblurred
    return BackgroundModel(
        shape=background.shape,
        downsample=params.downsample,
        blur_kernel_px=params.blur_kernel_px,
        image=background,
        B=B,
        B_sharp=B_sharp,
        B2=cv2.multiply(B, B, dtype=cv2.CV_32F),
        texture_variance=texture_variance,
        sample_B=sample_B,
        sample_B2=sample_B * sample_B,
        sample_divisor=_dot(sample_B, sample_B) + np.float32(BACKGROUND_ENERGY_FLOOR),
        coarse_B=_channels_first(_block_mean(B_sharp, COARSE_FACTOR)),
        coarse_texture_variance=_block_mean(texture_variance, COARSE_FACTOR),
        noise_floor=float(noise_floor),
    )


def median_background(images: Iterable[np.ndarray], *, max_frames: int = 31) -> np.ndarray:
    """(H, W, 3) uint8 background estimated as the per-pixel temporal median of a sequence.

    A person who moves covers any given pixel in fewer than half of the frames, so the median is the
    background there. Only ``max_frames`` frames, evenly spread over the sequence, are used: the
    median of a few dozen is as good as that of thousands and much cheaper.

    Parameters
    ----------
    images : iterable of (H, W, 3) uint8
        Frames of one camera, all the same size (a sample of the sequence is fine).
    max_frames : int
        At most this many frames enter the median.
    """
    frames = list(images)
    if not frames:
        raise InputError("median_background: expected at least one image, got none")
    shapes = {np.shape(frame) for frame in frames}
    if len(shapes) != 1:
        raise InputError(f"median_background: images of different shapes {sorted(shapes)}; expected one size")
    shape = shapes.pop()
    if len(shape) != 3 or shape[2] != 3:
        raise InputError(f"median_background: expected (H, W, 3) colour images, got shape {shape}")
    chosen = np.unique(np.linspace(0, len(frames) - 1, min(max_frames, len(frames))).round().astype(int))
    stack = np.stack([np.asarray(frames[i], dtype=np.uint8) for i in chosen])  # (F, H, W, 3)
    return np.median(stack, axis=0).round().astype(np.uint8)


@dataclass(frozen=True, eq=False)
class Evidence:
    """One view's frame after the per-pixel test, before its shadows are settled.

    Made by :func:`measure_evidence`; :func:`floor_shadows` reads every view's to decide which shadow-like
    pixels are shadows, and :func:`silhouette_from_evidence` then makes the mask. Maps cover ``region``
    of the working-resolution frame only (None: nothing differs from the background anywhere).
    """

    image: np.ndarray  # (H, W, 3) uint8 the frame
    model: BackgroundModel
    I_sharp: np.ndarray  # (h, w, 3) uint8 the frame at the working resolution
    noise: _Noise
    region: tuple[slice, slice] | None
    difference2: np.ndarray  # (h', w') float32 ‖I − GB‖² in noise variances
    chroma2: np.ndarray  # (h', w') float32 ‖I − αGB‖² in noise variances (the colour direction's change)
    alpha: np.ndarray  # (h', w') float32 α = I·GB / GB·GB, 1 on the background
    shadow_like: np.ndarray  # (h', w') bool above the weak threshold, but as a shadow would be

    def darkening(self) -> np.ndarray:
        """(h', w') float32 1 − α, how much darker than the background each pixel is (< 0: brighter)."""
        return 1.0 - self.alpha


def measure_evidence(image: np.ndarray, background: np.ndarray | BackgroundModel, params: SilhouetteParams) -> Evidence:
    """The per-pixel foreground test of one view (see the module's docstring), shadows not yet settled.

    The exposure ratio and the noise level come from a sparse sample of the frame; blocks of
    ``COARSE_FACTOR`` x ``COARSE_FACTOR`` working pixels show where the person may be, and the evidence
    is measured there only.

    Parameters
    ----------
    image : (H, W, 3) uint8
        The frame.
    background : (H, W, 3) uint8 or BackgroundModel
        The background of the same camera (colour order does not matter as long as both use the same
        one), or its :func:`background_model` built with the same ``params``.
    params : SilhouetteParams
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise InputError(f"image: expected an (H, W, 3) uint8 array, got {image.dtype} {image.shape}")
    if not isinstance(background, BackgroundModel):
        background = np.asarray(background)
        if background.shape != image.shape or background.dtype != np.uint8:
            raise InputError(
                f"background: expected a uint8 array of the image's shape {image.shape}, "
                f"got {background.dtype} {background.shape}"
            )
        background = background_model(background, params)
    elif background.shape != image.shape:
        raise InputError(f"background: model of {background.shape} images, expected the image's {image.shape}")
    elif (background.downsample, background.blur_kernel_px) != (params.downsample, params.blur_kernel_px):
        raise InputError("background: model built with another downsample/blur_kernel_px than params")
    I_sharp = _downsample(image, params.downsample)
    noise = _noise(I_sharp[::SAMPLE_STRIDE, ::SAMPLE_STRIDE], background)
    region = _person_region(I_sharp, background, noise, params)
    if region is None:
        empty = np.zeros((0, 0), np.float32)
        return Evidence(image, background, I_sharp, noise, None, empty, empty, empty, empty.astype(bool))
    difference2, chroma2, alpha = _evidence(_blur(I_sharp[region], params.blur_kernel_px), background, region, noise)
    weak2 = np.float32(params.weak_threshold**2)
    shadow_like = ((difference2 > weak2) & (chroma2 <= weak2)
                   & (alpha >= np.float32(params.shadow_min)) & (alpha <= np.float32(params.shadow_max)))
    return Evidence(image, background, I_sharp, noise, region, difference2, chroma2, alpha, shadow_like)


@dataclass(frozen=True, eq=False)
class FloorGeometry:
    """Where each camera sees the floor behind its pixels, and where the other cameras see those points.

    Built once per rig by :func:`floor_geometry`: the undistortions and projections cost tens of
    milliseconds per camera, the look-ups a frame makes in them almost nothing. Pixels are grouped in
    blocks of FLOOR_BLOCK x FLOOR_BLOCK working pixels (a shadow's darkening changes over many pixels).
    """

    working_shapes: tuple[tuple[int, int], ...]  # (h, w) of each camera's working-resolution frame
    # seen_at[c][b] (blocks of c,) int32: the flat working pixel of camera b that sees the floor point
    # behind each block of camera c; -1 where that ray misses the floor or the footprint, or b does not
    # see the point. None for b = c.
    seen_at: tuple[tuple[np.ndarray | None, ...], ...]


def floor_geometry(cameras: Sequence[Camera], volume: np.ndarray, params: SilhouetteParams) -> FloorGeometry:
    """The :class:`FloorGeometry` of a rig, for :func:`floor_shadows`.

    Parameters
    ----------
    cameras : sequence of Camera
        The views' cameras at the images' resolution, world frame with the floor at z = 0.
    volume : (2, 3) float
        Working volume [min; max], metres: shadows are looked for on the floor within its footprint.
    params : SilhouetteParams
        Its ``downsample`` sets the working resolution.
    """
    footprint = np.asarray(volume, dtype=float)[:, :2]
    ds = params.downsample
    shapes = tuple(_working_shape(camera.size, ds) for camera in cameras)
    seen_at = []
    for index, (camera, (height, width)) in enumerate(zip(cameras, shapes, strict=True)):
        block_rows, block_cols = np.divmod(np.arange(_blocks(height) * _blocks(width)), _blocks(width))
        centre = (FLOOR_BLOCK - 1) / 2
        uv = np.column_stack([(block_cols * FLOOR_BLOCK + centre + 0.5) * ds - 0.5,
                              (block_rows * FLOOR_BLOCK + centre + 0.5) * ds - 0.5])
        X, on_floor = _floor_points(camera, uv)
        on_floor &= np.all((X[:, :2] >= footprint[0]) & (X[:, :2] <= footprint[1]), axis=1)
        X = X[on_floor]
        seen = []
        for other, (other_camera, other_shape) in enumerate(zip(cameras, shapes, strict=True)):
            if other == index:
                seen.append(None)
                continue
            pixels = np.full(len(uv), -1, np.int32)
            pixels[on_floor] = _working_pixel(other_camera, other_shape, ds, X)
            seen.append(pixels)
        seen_at.append(tuple(seen))
    return FloorGeometry(shapes, tuple(seen_at))


def _blocks(length: int) -> int:
    """How many FLOOR_BLOCK-pixel blocks cover ``length`` working pixels (a partial last block counts)."""
    return -(-length // FLOOR_BLOCK)


def _floor_points(camera: Camera, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) points where the rays through pixels ``uv`` meet the floor z = 0, and (n,) whether they do."""
    rays = camera.pixel_rays(uv)
    centre = camera.centre
    with np.errstate(divide="ignore", invalid="ignore"):
        distance = -centre[2] / rays[:, 2]
    meets = np.isfinite(distance) & (distance > 0)
    return centre + np.where(meets, distance, 0.0)[:, None] * rays, meets


def _working_pixel(camera: Camera, shape: tuple[int, int], downsample: int, X: np.ndarray) -> np.ndarray:
    """(n,) int32 flat index of the working pixel (of a frame of ``shape``) where ``camera`` sees ``X``
    (n, 3); -1 where it does not (behind it, outside the image)."""
    uv = camera.project(X)
    seen = (camera.depth(X) > 0) & camera.in_image(uv)
    height, width = shape
    cols = np.clip(np.floor((uv[:, 0] + 0.5) / downsample), 0, width - 1)
    rows = np.clip(np.floor((uv[:, 1] + 0.5) / downsample), 0, height - 1)
    return np.where(seen, rows * width + cols, -1).astype(np.int32)


def floor_shadows(views: Sequence[Evidence], floor: FloorGeometry, params: SilhouetteParams) -> list[np.ndarray]:
    """Per view, which of its shadow-like pixels are the person's shadow on the floor, (h', w') bool each.

    A shadow-like pixel's ray meets the floor (z = 0, the world's convention) at a point X within the
    working volume's footprint. If the pixel is a shadow, X is darkened, and every other camera that sees
    X unoccluded sees it darkened alike (a matt floor looks the same from every side). If the pixel is
    clothing darker than the background behind it, X is bare floor somewhere behind the person, and the
    other cameras see it undarkened. Each other camera votes: no vote where X is outside its image or
    hidden by foreground that is not shadow-like (a limb in front of it); a vote for a shadow where X is
    darkened by at least ``SHADOW_AGREEMENT`` of the pixel's darkening; against otherwise. A pixel is a
    shadow when it has a vote for and at least as many for as against. Rays that never reach the floor
    (above the horizon) are never shadows.

    ``floor`` is the rig's :func:`floor_geometry`, its cameras in the order of ``views``; ``params`` gives
    the weak threshold, above which a pixel that is not shadow-like hides the floor.
    """
    shapes = tuple(view.I_sharp.shape[:2] for view in views)
    if shapes != floor.working_shapes:
        raise InputError(f"floor_shadows: views of working sizes {shapes}, but a floor geometry made for "
                         f"{floor.working_shapes}; expected the same cameras in the same order")
    darkenings = [view.darkening() for view in views]
    looks = [_floor_look(view, darkening, params) for view, darkening in zip(views, darkenings, strict=True)]
    shadows = []
    for index, (view, darkening) in enumerate(zip(views, darkenings, strict=True)):
        shadow = np.zeros(view.shadow_like.shape, bool)
        rows, cols = np.nonzero(view.shadow_like)
        if len(rows) == 0:
            shadows.append(shadow)
            continue
        blocks = (((rows + view.region[0].start) // FLOOR_BLOCK) * _blocks(view.I_sharp.shape[1])
                  + (cols + view.region[1].start) // FLOOR_BLOCK)
        needed = SHADOW_AGREEMENT * darkening[rows, cols]  # (n,)
        votes_for = np.zeros(len(rows), np.int32)
        votes_against = np.zeros(len(rows), np.int32)
        for other, look in enumerate(looks):
            if other == index:
                continue
            pixels = floor.seen_at[index][other].take(blocks)  # (n,) -1 where there is no floor point to see
            darkening, visible = look.darkening.take(pixels), look.visible.take(pixels)
            votes_for += visible & (darkening >= needed)
            votes_against += visible & (darkening < needed)
        shadow[rows, cols] = (votes_for > 0) & (votes_for >= votes_against)
        shadows.append(shadow)
    return shadows


@dataclass(frozen=True, eq=False)
class _FloorLook:
    """What a view says of the floor points it sees, indexed by flat working pixel, plus one last entry
    that index -1 (no floor point there) reads."""

    darkening: np.ndarray  # (h w + 1,) float32 1 − α smoothed over 3 x 3 pixels (noise); 0 outside the region
    visible: np.ndarray  # (h w + 1,) bool the floor is seen: not behind foreground that is not shadow-like


def _floor_look(view: Evidence, darkening: np.ndarray, params: SilhouetteParams) -> _FloorLook:
    """The view's :class:`_FloorLook`, from its ``darkening`` (:meth:`Evidence.darkening`). Outside its
    region nothing differs from the background: the floor is seen there, undarkened."""
    height, width = view.I_sharp.shape[:2]
    seen_darkening = np.zeros(height * width + 1, np.float32)
    visible = np.ones(height * width + 1, bool)
    visible[-1] = False
    if view.region is not None:
        hidden = (view.difference2 > np.float32(params.weak_threshold**2)) & ~view.shadow_like
        seen_darkening[:-1].reshape(height, width)[view.region] = cv2.blur(darkening, (3, 3))
        visible[:-1].reshape(height, width)[view.region] = ~hidden
    return _FloorLook(seen_darkening, visible)


def silhouette_from_evidence(view: Evidence, shadow: np.ndarray | None, params: SilhouetteParams) -> np.ndarray:
    """(H, W) uint8 mask of the person, 0 = background, 255 = person, from one view's evidence.

    ``shadow`` (h', w') bool marks the pixels of the region known to be shadow (only their change of
    colour direction counts there); None: none. At the working resolution (``params.downsample``),
    hysteresis, morphology and component filtering give the mask, and in the mask's box the matting
    places the outline, measured again at full resolution where a working pixel is mixed. The costly
    steps thus run on a fraction of the pixels.
    """
    image, background, ds = view.image, view.model, params.downsample
    silhouette = np.zeros(image.shape[:2], np.uint8)
    if view.region is None:
        return silhouette
    evidence2 = view.difference2
    if shadow is not None and shadow.any():
        evidence2 = np.where(shadow, view.chroma2, evidence2)
    mask = _clean_mask(_hysteresis(evidence2, params), params, ds, image.shape[0] * image.shape[1] / ds**2)
    x, y, w, h = cv2.boundingRect(mask)
    if w == 0:
        return silhouette
    # The outline is worked out in the person's bounding box only, with a margin of background wider
    # than the matting band, so that interpolation at the box's edges sees background as it would.
    margin = max(1, round(MATTE_RADIUS_PX / ds)) + 2
    x0, y0 = max(x - margin, 0), max(y - margin, 0)
    x1, y1 = min(x + w + margin, mask.shape[1]), min(y + h + margin, mask.shape[0])
    box = (slice(y0, y1), slice(x0, x1))  # in the region
    region = view.region
    y0, y1, x0, x1 = y0 + region[0].start, y1 + region[0].start, x0 + region[1].start, x1 + region[1].start
    frame_box = (slice(y0, y1), slice(x0, x1))  # the same in the working-resolution frame
    exposed = cv2.multiply(background.B_sharp[frame_box], view.noise.gains, dtype=cv2.CV_32F)  # G B in the box
    matte = _matte(mask[box], view.I_sharp[frame_box], exposed, view.alpha[box], ds)
    if ds > 1:
        score = _full_resolution_score(matte, image, background.image, view.noise, (y0 * ds, x0 * ds), ds)
    else:
        score = matte.score
    inside = silhouette[y0 * ds : y1 * ds, x0 * ds : x1 * ds]  # a view, clipped at the image's edges
    cv2.compare(score[: inside.shape[0], : inside.shape[1]], 0.0, cv2.CMP_GT, dst=inside)
    return silhouette


def extract_silhouette(
    image: np.ndarray, background: np.ndarray | BackgroundModel, params: SilhouetteParams
) -> np.ndarray:
    """(H, W) uint8 mask of the person in a single view, 0 = background, 255 = person.

    Without the other cameras the floor test of shadows (``params.shadows == "floor"``) cannot be made,
    and no pixel is taken for a shadow; "colour" takes every shadow-like pixel for one. See
    :func:`measure_evidence` for ``image`` and ``background``; :func:`extract_silhouettes` for the
    multi-view version.
    """
    view = measure_evidence(image, background, params)
    return silhouette_from_evidence(view, view.shadow_like if params.shadows == "colour" else None, params)


def extract_silhouettes(
    images: Sequence[np.ndarray], backgrounds: Sequence[np.ndarray | BackgroundModel], floor: FloorGeometry,
    params: SilhouetteParams,
) -> list[np.ndarray]:
    """(H, W) uint8 masks of the person in every view of one frame, shadows settled across the views.

    Parameters
    ----------
    images, backgrounds : sequences of (H, W, 3) uint8 (backgrounds may be :class:`BackgroundModel`)
        The frame and background of each camera, as in :func:`measure_evidence`.
    floor : FloorGeometry
        The rig's :func:`floor_geometry`, its cameras in the order of ``images`` (used when
        ``params.shadows`` is "floor").
    params : SilhouetteParams
    """
    if not len(images) == len(backgrounds) == len(floor.working_shapes):
        raise InputError(f"extract_silhouettes: {len(images)} images, {len(backgrounds)} backgrounds and "
                         f"{len(floor.working_shapes)} cameras; expected as many of each")
    views = [measure_evidence(image, background, params)
             for image, background in zip(images, backgrounds, strict=True)]
    if params.shadows == "floor":
        shadows = floor_shadows(views, floor, params)
    elif params.shadows == "colour":
        shadows = [view.shadow_like for view in views]
    else:
        shadows = [None] * len(views)
    return [silhouette_from_evidence(view, shadow, params) for view, shadow in zip(views, shadows, strict=True)]


def _downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """The uint8 image averaged over factor x factor blocks (OpenCV's fixed-point code: fast on uint8)."""
    if factor == 1:
        return image
    height, width = _working_shape(image.shape[1::-1], factor)
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


def _working_shape(size: tuple[int, int], factor: int) -> tuple[int, int]:
    """(h, w) of the working-resolution frame of a ``size`` (width, height) image downsampled by ``factor``."""
    return max(1, round(size[1] / factor)), max(1, round(size[0] / factor))


def _block_mean(image: np.ndarray, factor: int) -> np.ndarray:
    """``image`` averaged over factor x factor blocks, a partial block at the far edges left out.

    A power of two is reached by halving again and again: OpenCV's area averaging has a fast path for
    halving only, and three halvings of a 780 x 580 frame cost a third of one reduction by 8.
    """
    while factor > 1:
        step = 2 if factor % 2 == 0 else factor
        rows, cols = image.shape[0] // step, image.shape[1] // step
        image = cv2.resize(image[: rows * step, : cols * step], (cols, rows), interpolation=cv2.INTER_AREA)
        factor //= step
    return image


def _blur(image: np.ndarray, blur_kernel: int) -> np.ndarray:
    """The uint8 image blurred against noise (on uint8, where OpenCV's fixed-point code is fast)."""
    if blur_kernel > 1:
        return cv2.GaussianBlur(image, (blur_kernel, blur_kernel), 0)
    return image


@dataclass(frozen=True, eq=False)
class _Noise:
    gains: tuple[float, float, float]  # g_k, each channel's exposure ratio of the frame to the background
    sigma2: float  # σ², the per-channel noise variance (8-bit levels squared)

    def exposure(self) -> np.ndarray:
        """(3, 1, 1) float32 G's diagonal, shaped to scale channels-first colours."""
        return np.array(self.gains, np.float32).reshape(3, 1, 1)


def _noise(I: np.ndarray, model: BackgroundModel) -> _Noise:
    """The frame's exposure ratios and noise level, from a sample ``I`` (every SAMPLE_STRIDE-th pixel).

    First one ratio for all channels, g = the median of α = I·B / B·B (the person covers less than half of
    the image); the half of the sample closest to gB is then surely background, and on it each channel's
    ratio is the least-squares g_k = Σ I_k B_k / Σ B_k². Medians of per-channel ratios would be pulled by the
    person's colour, each channel its own way, and tint the model. σ² is the lower quartile of ‖I − GB‖²
    over χ²₃'s, on the pixels that are not exact copies of the background. Both are clipped to plausible
    ranges (see the constants; σ from below by the model's ``noise_floor``).
    """
    I = _channels_first(I).reshape(3, -1)  # (3, m)
    B = model.sample_B
    products = I * B  # (3, m) I_k B_k
    alpha = (products[0] + products[1] + products[2]) / model.sample_divisor
    g = np.float32(_clip_ratio(_quantile(alpha, 0.5)))
    D = I - g * B
    distance2 = _dot(D, D)
    background = (distance2 <= np.float32(_quantile(distance2, 0.5))).astype(np.float32)  # (m,) 1 or 0
    # Sums over the background half as products with its 0/1 indicator: a fraction of boolean indexing's cost.
    gains = tuple(_clip_ratio(float(IB / BB)) if BB > 0 else float(g)
                  for IB, BB in zip(products @ background, model.sample_B2 @ background, strict=True))
    D = I - np.array(gains, np.float32)[:, None] * B
    distance2 = _dot(D, D)
    # A pixel equal to the background in every channel is a copy, not a noisy measurement of it: a video
    # codec repeats static blocks from frame to frame, so a background taken from the same video (a
    # temporal median, or a plate cut from it) matches them exactly, while the blocks it encodes again,
    # around the moving person, carry the codec's noise. Only the others tell the noise level.
    measured = np.flatnonzero((I != B).any(axis=0))
    if len(measured) < max(MIN_NOISE_SAMPLES, len(distance2) // 2):
        return _Noise(gains, model.noise_floor**2)
    quartile = _quantile(distance2.take(measured), 0.25)
    return _Noise(gains, min(max(quartile / CHI2_3_LOWER_QUARTILE, model.noise_floor**2), NOISE_SIGMA_MAX**2))


def _clip_ratio(ratio: float) -> float:
    """An exposure ratio within :data:`EXPOSURE_RATIO_RANGE`."""
    return min(max(ratio, EXPOSURE_RATIO_RANGE[0]), EXPOSURE_RATIO_RANGE[1])


def _person_region(
    I: np.ndarray, model: BackgroundModel, noise: _Noise, params: SilhouetteParams
) -> tuple[slice, slice] | None:
    """The part of the working-resolution frame ``I`` (h, w, 3) uint8 worth a close look, or None.

    On blocks of COARSE_FACTOR x COARSE_FACTOR working pixels, ‖I − GB‖² is compared with the weak
    threshold at the working resolution's noise (averaging only lowers the noise, so this errs towards
    looking); the answer is the box around every block that passes, with a margin of COARSE_MARGIN
    blocks for the parts of the person too faint to show on blocks.
    """
    D = _channels_first(_block_mean(I, COARSE_FACTOR)) - noise.exposure() * model.coarse_B
    difference2 = _dot(D, D)
    passing = cv2.compare(difference2, params.weak_threshold**2 * (model.coarse_texture_variance + noise.sigma2),
                          cv2.CMP_GT)
    x, y, w, h = cv2.boundingRect(passing)
    if w == 0:
        return None
    return _span(y, h, I.shape[0]), _span(x, w, I.shape[1])


def _span(start: int, length: int, size: int) -> slice:
    """Blocks [start, start + length) grown by COARSE_MARGIN, as working pixels of an axis of ``size``
    (a margin reaching the last, partial block takes it in)."""
    return slice(max((start - COARSE_MARGIN) * COARSE_FACTOR, 0),
                 min((start + length + COARSE_MARGIN) * COARSE_FACTOR, size))


def _evidence(
    I: np.ndarray, model: BackgroundModel, region: tuple[slice, slice], noise: _Noise
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """‖I − GB‖² and ‖I − αGB‖² per pixel of ``region``, in noise variances, and the brightness distortion α.

    ``I`` (h', w', 3) uint8 is the region. With α = I·GB / GB·GB, the chromaticity distortion is
    ‖I − αGB‖² = I·I − α I·GB (the remainder orthogonal to GB) and ‖I − GB‖² = I·I − 2 I·GB + GB·GB.
    The products are taken straight from uint8 into float32; I·GB and GB·GB are channel sums weighted by
    g_k and g_k².
    """
    gains = np.array([noise.gains], np.float32)  # (1, 3)
    II = cv2.transform(cv2.multiply(I, I, dtype=cv2.CV_32F), _CHANNEL_SUM)  # (h', w') I·I
    IB = cv2.transform(cv2.multiply(I, model.B[region], dtype=cv2.CV_32F), gains)  # (h', w') I·GB
    BB = cv2.transform(model.B2[region], gains * gains)  # (h', w') GB·GB
    alpha = cv2.divide(IB, BB + np.float32(BACKGROUND_ENERGY_FLOOR))  # (h', w') α
    chroma2 = cv2.subtract(II, cv2.multiply(IB, alpha))  # (h', w') ‖I − αGB‖² (≥ 0 up to rounding)
    difference2 = cv2.add(cv2.addWeighted(II, 1.0, IB, -2.0, 0.0), BB)  # ‖I − GB‖²
    variance = model.texture_variance[region] + np.float32(noise.sigma2)
    return cv2.divide(difference2, variance), cv2.divide(chroma2, variance), alpha


def _quantile(values: np.ndarray, q: float) -> float:
    """The ``q`` quantile of ``values`` by partial sorting (a few times faster than ``np.median``)."""
    flat = values.ravel()
    k = min(int(q * flat.size), flat.size - 1)
    return float(np.partition(flat, k)[k])


def _hysteresis(evidence2: np.ndarray, params: SilhouetteParams) -> np.ndarray:
    """(h, w) uint8 mask: the regions above the weak threshold that hold a pixel above the strong one.

    Weak regions are opened first (lines one or two pixels wide, such as the rim of a hard shadow,
    vanish) and strong pixels are kept as they are (a thin limb is strong).
    """
    strong = cv2.compare(evidence2, float(params.strong_threshold**2), cv2.CMP_GT)
    weak = cv2.compare(evidence2, float(params.weak_threshold**2), cv2.CMP_GT)
    weak = cv2.bitwise_or(cv2.morphologyEx(weak, cv2.MORPH_OPEN, _disk(1)), strong)
    count, labels = cv2.connectedComponents(weak, connectivity=8)
    seeded = np.zeros(count, np.uint8)  # (count,) 255 for the regions holding a strong pixel
    seeded[labels[strong > 0]] = 255
    seeded[0] = 0
    return np.take(seeded, labels)


@dataclass(frozen=True, eq=False)
class _Matte:
    score: np.ndarray  # (h, w) float32 > 0 for the person: φ − 1/2 where measured, else the mask's ±SCORE_FLOOR
    # The pixels that full resolution measures again: φ measured and mixed (0 < φ < 1).
    rows: np.ndarray  # (m,) int working-resolution pixels
    cols: np.ndarray  # (m,) int
    F: np.ndarray  # (3, m) float32 the person's colour next to each
    lam: np.ndarray  # (m,) float32 the exposed background's brightness factor λ next to each


# The matte's score where the mask decides, by mask value: a table lookup costs a third of np.where.
_MASK_SCORE = np.where(np.arange(256) > 0, np.float32(SCORE_FLOOR), np.float32(-SCORE_FLOOR))


def _matte(mask: np.ndarray, I: np.ndarray, B: np.ndarray, alpha: np.ndarray, downsample: int) -> _Matte:
    """The person's share φ of the pixels near the outline, and what it was measured against.

    A pixel on a blurred edge mixes the person's colour F and the background's, λB:
    I = φ F + (1 − φ) λB, so φ = (I − λB)·(F − λB) / ‖F − λB‖². F is the mean colour of the mask's core
    nearby (pixels ``CORE_DEPTH_PX`` inside it) and λ the mean brightness distortion of the pixels just
    outside (1, or less in the person's shadow). The true outline runs where φ = 1/2; a fixed threshold
    would keep the whole blurred edge of a high-contrast outline and grow the silhouette. ``I`` (h, w, 3)
    uint8 and the exposed background ``B`` = GB (h, w, 3) float32 are not blurred, so the edge is as sharp
    as the camera made it. φ is measured within ``MATTE_RADIUS_PX`` of the outline, on both sides;
    elsewhere (and where F is too close to the background to measure it) the mask decides, with a small
    magnitude so that interpolation still places the outline between pixels.
    """
    depth = _disk(max(1, round(CORE_DEPTH_PX / downsample)))
    radius = max(1, round(MATTE_RADIUS_PX / downsample))
    size = (2 * radius + 1, 2 * radius + 1)
    width = mask.shape[1]
    score = cv2.LUT(mask, _MASK_SCORE)
    core = cv2.erode(mask, depth, borderType=cv2.BORDER_REPLICATE)
    outside = cv2.compare(cv2.dilate(mask, depth), 0, cv2.CMP_EQ)
    band = cv2.compare(cv2.dilate(mask, _disk(radius)), cv2.erode(mask, _disk(radius), borderType=cv2.BORDER_REPLICATE),
                       cv2.CMP_GT)
    index = _flat_nonzero(band)  # (n,) flat indices of the pixels near the outline: np.take is the fastest gather
    I, B = np.ascontiguousarray(I), np.ascontiguousarray(B)
    # The core's colour sum and both pixel counts in one pass: sums of 8-bit integers, exact in float32.
    sums = cv2.boxFilter(cv2.merge([cv2.bitwise_and(I, I, mask=core), core, outside]), cv2.CV_32F, size,
                         normalize=False)  # (h, w, 5)
    sums = sums.ravel().take(_channel_index(index, 5))  # (5, n)
    n_core, n_outside = sums[3:] / 255.0  # (n,) pixels nearby
    alpha_sum = cv2.boxFilter(cv2.bitwise_and(alpha, alpha, mask=outside), -1, size, normalize=False)
    lam = np.where(n_outside > 0, alpha_sum.ravel().take(index) / np.maximum(n_outside, 1.0), np.float32(1.0))  # λ
    F = sums[:3] / np.maximum(n_core, 1.0)  # (3, n)
    at = _channel_index(index, 3)
    phi, EE = _share(I.ravel().take(at), F, lam * B.ravel().take(at))
    measured = np.flatnonzero((n_core > 0) & (EE > MIN_MATTE_CONTRAST**2))
    share = phi.take(measured) - 0.5
    score.ravel()[index.take(measured)] = share
    # A block all person, or all background, needs no new measurement at full resolution.
    mixed = measured.take(np.flatnonzero(np.abs(share) < 0.5))  # (m,)
    rows, cols = np.divmod(index.take(mixed), width)
    return _Matte(score, rows, cols, F.take(mixed, axis=1), lam.take(mixed))


def _channel_index(index: np.ndarray, channels: int) -> np.ndarray:
    """(channels, ...) flat positions of the values of the pixels at flat indices ``index`` (...) of a
    contiguous (h, w, channels) image.

    Gathering single values by them (``image.ravel().take``) is several times faster than taking rows of
    ``channels`` values, and gives the channels-first layout of :func:`_dot` without a copy.
    """
    return channels * index + np.arange(channels).reshape(-1, *[1] * index.ndim)


def _flat_nonzero(mask: np.ndarray) -> np.ndarray:
    """(n,) int32 flat indices of the nonzero pixels of the (h, w) uint8 ``mask``, in order: as
    ``np.flatnonzero`` at half the cost (OpenCV's scan, then the indices from its (x, y) points)."""
    points = cv2.findNonZero(mask)  # (n, 2) or (n, 1, 2) x, y by OpenCV version; None when there are none
    if points is None:
        return np.zeros(0, np.int32)
    x, y = points.reshape(-1, 2).T
    return y * np.int32(mask.shape[1]) + x


def _share(I: np.ndarray, F: np.ndarray, background: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """φ (...) of colours I (3, ...) between the person's F and the background's (both broadcast to I's
    shape), and ‖F − bg‖²; channels come first (see :func:`_dot`)."""
    E = F - background  # (3, ...)
    D = I - background
    EE = _dot(E, E)
    return _dot(D, E) / np.maximum(EE, 1e-6), EE


def _channels_first(image: np.ndarray) -> np.ndarray:
    """(3, h, w) float32 copy of an (h, w, 3) image, in one pass (the layout :func:`_dot` is fastest on)."""
    return np.ascontiguousarray(image.transpose(2, 0, 1), dtype=np.float32)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a · b (...) over the first axis of a and b (3, ...), summed channel by channel.

    On a few thousand pixels this is a few times faster than ``np.einsum`` over a last axis of 3, which
    calls its inner loop once per pixel; it adds the products in the same order, so the result is the same
    to the bit.
    """
    dot = a[0] * b[0]
    dot += a[1] * b[1]
    dot += a[2] * b[2]
    return dot


def _full_resolution_score(
    matte: _Matte, image: np.ndarray, background: np.ndarray, noise: _Noise, origin: tuple[int, int],
    downsample: int,
) -> np.ndarray:
    """(h ds, w ds) float32 outline score of the box at full resolution, from its working-resolution matte.

    The score is interpolated, then φ is measured again on the full-resolution pixels of every mixed
    working pixel (0 < φ < 1; ``matte.rows`` and ``matte.cols``), against that pixel's F and λ: the
    outline then follows the full-resolution edge rather than its average over ``downsample`` x
    ``downsample`` blocks. ``image`` and ``background`` (H, W, 3) uint8 are whole (flat
    gathers from them are the fastest), the box starting at full-resolution pixel ``origin`` (row, column);
    the background is exposed by the frame's ``noise`` gains, as in the matte.
    """
    height, width = matte.score.shape
    ds = downsample
    score = cv2.resize(matte.score, (width * ds, height * ds), interpolation=cv2.INTER_LINEAR)
    dy, dx = np.divmod(np.arange(ds * ds), ds)  # (ds²,) offsets in a block
    rows = matte.rows[:, None] * ds + dy  # (m, ds²) box rows and columns of their pixels
    cols = matte.cols[:, None] * ds + dx
    # A box passing the image's far edges reads the edge pixels there; those scores are cut off with the box.
    index = (np.minimum(rows + origin[0], image.shape[0] - 1) * image.shape[1]
             + np.minimum(cols + origin[1], image.shape[1] - 1))  # (m, ds²) flat indices in the image
    at = _channel_index(index, 3)
    lam_B = background.ravel().take(at) * (noise.exposure() * matte.lam[:, None])  # (3, m, ds²) λGB
    phi, _ = _share(image.ravel().take(at), matte.F[:, :, None], lam_B)
    score.ravel()[rows * (width * ds) + cols] = phi - 0.5
    return score


@functools.cache
def _disk(radius: int) -> np.ndarray:
    """Read-only disk-shaped structuring element, built once per radius (several are used per frame)."""
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    disk.flags.writeable = False
    return disk


def _clean_mask(mask: np.ndarray, params: SilhouetteParams, scale: int, frame_area: float) -> np.ndarray:
    """Morphology, then keep the large components, then fill the small holes.

    ``mask`` is at 1/``scale`` of the full resolution, part of a frame of ``frame_area`` pixels at that
    resolution; the radii in ``params`` are full-resolution pixels.
    """
    opening, closing = round(params.opening_px / scale), round(params.closing_px / scale)
    if opening > 0:
        mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, _disk(opening))
    if closing > 0:
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, _disk(closing))
    contours, hierarchy = cv2.findContours(mask, cv2.RETR_TREE, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return mask
    return _redraw(mask.shape, contours, hierarchy[0], params, frame_area)


def _redraw(
    shape: tuple[int, int], contours, hierarchy: np.ndarray, params: SilhouetteParams, frame_area: float
) -> np.ndarray:
    """The mask redrawn from its contour tree without the small components and the small holes.

    Working on contours rather than on labelled pixels costs a fraction of a millisecond. Contours are
    processed parents first, so each nested island or hole overwrites its parent's interior: even depths
    are components (drawn when large enough), odd depths are holes (erased when large enough; the hole's
    border pixels belong to the component around it and are drawn back).
    """
    parents = hierarchy[:, 3]  # (K,) index of the enclosing contour, -1 at the top
    depth = np.zeros(len(contours), int)
    for index in range(len(contours)):
        parent = parents[index]
        while parent >= 0:
            depth[index] += 1
            parent = parents[parent]
    areas = np.array([cv2.contourArea(contour) for contour in contours])  # (K,) pixels
    is_component = depth % 2 == 0
    min_component = max(
        params.min_component_fraction * areas[is_component].max(),
        params.min_component_area_fraction * frame_area,
    )
    max_hole = params.max_hole_fraction * areas[is_component & (areas >= min_component)].sum()
    mask = np.zeros(shape, np.uint8)
    inside = np.zeros(len(contours), np.uint8)  # (K,) value of the redrawn mask inside each contour
    for index in np.argsort(depth, kind="stable"):
        around = inside[parents[index]] if parents[index] >= 0 else 0
        inside[index] = around
        if is_component[index] and around == 0 and areas[index] >= min_component:
            cv2.drawContours(mask, contours, index, 255, cv2.FILLED)
            inside[index] = 255
        elif not is_component[index] and around == 255 and areas[index] >= max_hole:
            cv2.drawContours(mask, contours, index, 0, cv2.FILLED)
            cv2.drawContours(mask, contours, index, 255, 1)
            inside[index] = 0
    return mask
