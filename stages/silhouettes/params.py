"""The silhouette stage's parameters (:class:`SilhouetteParams`).
"""

from __future__ import annotations

from dataclasses import dataclass

from calib.errors import InputError
from stages.checks import check_bool, check_choice, check_int, check_number

#: Choices of ``SilhouetteParams.shadows``.
SHADOW_TESTS = ("floor", "colour", "none")


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
        Evidence ‖I − T(B)‖ / σ (in noise standard deviations) above which a pixel seeds the person: high
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
    find_room_changes : bool
        Look for parts of the room that changed since a camera's clean plate was taken (a box put down, a chair
        moved): foreground in nearly every frame and apart from the subject's moving silhouette in most, see
        :mod:`stages.background.room`. That camera's background there is taken from the frames, and the
        silhouettes are made again. The pipeline does it (it needs many frames' silhouettes).
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
    find_room_changes: bool = True

    def __post_init__(self) -> None:
        check_bool("silhouettes.multiview_check", self.multiview_check)
        check_bool("silhouettes.find_room_changes", self.find_room_changes)
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
        check_choice("silhouettes.shadows", self.shadows, SHADOW_TESTS)
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
