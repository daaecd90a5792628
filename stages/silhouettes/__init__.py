"""Person silhouettes from colour images and a background model.

A pixel is foreground when it differs from the background by more than the noise, in a way that lighting
cannot explain. We follow Horprasert, Harwood & Davis (ICCV Frame-Rate Workshop 1999): write the pixel
colour I (3,) as a brightness-scaled copy of the background colour B (3,) plus a remainder,

    I = α B + r,   α = (I · B) / (B · B)   (brightness distortion),   ‖r‖ (chromaticity distortion),

so a shadow lowers α but leaves ‖r‖ small, while a person in front of the background changes the colour
direction or the brightness. As in that paper, distortions are measured in units of the noise; with a
clean plate instead of a training sequence, the noise is estimated from each frame:

- the camera's exposure, tone and white balance may drift from the plate's (flicker, automatic exposure
  acting before the camera's gamma, automatic white balance, a codec or a grabber shifting the black
  level): each channel k has its tone curve T_k, the frame's level where the plate's is b, fitted on the
  background itself (medians per plate level, then means on the half of the image that is surely
  background; see :func:`_noise`), and the background model is T(B); α and the distortions below are taken
  against T(B). A single ratio per channel fits the room's most common tone and misses the others (a bright
  wall above a dark floor) by more than the noise wherever the tone curve changed. Bright levels too rare in
  the image to be fitted (a white skirting board) are extrapolated, and how uncertain that is counts as noise
  (τ_p below; :func:`_tone_curve`);
- the noise level σ comes from the lower quartile of ‖I − T(B)‖ over the image, and grows where the
  background is textured, because a sub-pixel shift or compression changes a textured pixel by about its
  gradient times the shift, and where T(B) is extrapolated: σ_p² = σ² + (κ ‖∇B‖)² / 3 + τ_p².

The evidence is ‖I − T(B)‖ / σ_p, except on shadows, where only the chromaticity distortion counts. A
pixel looks like a shadow when it is darker than the background by as much as a shadow darkens
(α between ``shadow_min`` and ``shadow_max``) with its colour direction unchanged. Colour alone cannot
tell a shadow from dark clothing in front of a background of the same hue (navy trousers on a blue mat, a
grey shirt on a lighter grey wall), and taking every such pixel for a shadow cuts the person away there.
Geometry can: a person's shadow lies on the floor and darkens it alike from every side, so a
shadow-like pixel is a shadow only when the other cameras see the floor point behind it darkened too
(:func:`floor_shadows`; all the views of a frame are segmented together, :func:`extract_silhouettes`).
Where the calibration maps a view's floor points a few pixels off where the others see them, the shadows
themselves say where they do (:func:`floor_shifts`, :func:`shifted_floor`).
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

from collections.abc import Sequence

import numpy as np

from calib.errors import InputError
from stages.silhouettes.evidence import (
    CHANNEL_SUM,
    NOISE_SIGMA_MAX,
    NOISE_SIGMA_MIN,
    SAMPLE_STRIDE,
    BackgroundModel,
    Evidence,
    background_model,
    measure_evidence,
    median_background,
)
from stages.silhouettes.outline import disk, silhouette_from_evidence
from stages.silhouettes.params import SHADOW_TESTS, SilhouetteParams
from stages.silhouettes.shadows import FloorGeometry, floor_geometry, floor_shadows, floor_shifts, shifted_floor

__all__ = [
    "CHANNEL_SUM",
    "NOISE_SIGMA_MAX",
    "NOISE_SIGMA_MIN",
    "SAMPLE_STRIDE",
    "SHADOW_TESTS",
    "BackgroundModel",
    "Evidence",
    "FloorGeometry",
    "SilhouetteParams",
    "background_model",
    "disk",
    "extract_silhouette",
    "extract_silhouettes",
    "floor_geometry",
    "floor_shadows",
    "floor_shifts",
    "measure_evidence",
    "median_background",
    "settled_silhouettes",
    "shifted_floor",
    "silhouette_from_evidence",
]


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
    return settled_silhouettes([measure_evidence(image, background, params)
                                for image, background in zip(images, backgrounds, strict=True)], floor, params)


def settled_silhouettes(views: Sequence[Evidence], floor: FloorGeometry, params: SilhouetteParams) -> list[np.ndarray]:
    """The masks of :func:`extract_silhouettes` from every view's :func:`measure_evidence` of one frame (for a caller
    that reads the evidence for something else as well: :func:`floor_shifts`)."""
    if params.shadows == "floor":
        shadows = floor_shadows(views, floor, params)
    elif params.shadows == "colour":
        shadows = [view.shadow_like for view in views]
    else:
        shadows = [None] * len(views)
    return [silhouette_from_evidence(view, shadow, params) for view, shadow in zip(views, shadows, strict=True)]
