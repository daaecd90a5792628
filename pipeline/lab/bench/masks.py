"""Silhouette noise for the paper's noise experiment (Horaud et al. 2009, Sec. 4.1, Fig. 4, second graph).

Real silhouettes go wrong in two ways: their outline wanders (shadows, motion blur, colours close to the
background push it out or in by a few pixels, coherently along stretches of the contour) and they get holes
(clothing that matches the background). :func:`perturb_mask` applies both with one ``strength`` in [0, 1]:

- boundary: the mask is re-thresholded at ``signed_distance + amplitude * field``, where ``field`` is smooth
  unit-variance noise (correlated over :data:`FIELD_CORRELATION_PX`) and ``amplitude`` grows to
  :data:`MAX_BOUNDARY_PX` at strength 1: random erosion here, dilation there;
- holes: up to :data:`MAX_HOLES` discs of radius up to :data:`MAX_HOLE_RADIUS_PX` cleared inside the person.

Every random draw is made at full size whatever the (non-zero) strength, and the strength only scales them,
so for one seed a stronger perturbation changes a superset of what a weaker one changes (the boundary part
exactly; holes are cleared last): error curves over strength are not tangled with resampling noise.
"""

from __future__ import annotations

import cv2
import numpy as np

#: Largest outline displacement (pixels, one standard deviation of the field) at strength 1.
MAX_BOUNDARY_PX = 4.0
#: Correlation length of the boundary field (Gaussian sigma, pixels): a few pixels of contour move together.
FIELD_CORRELATION_PX = 6.0
#: Holes at strength 1, and their radius (pixels); both scale linearly with the strength.
MAX_HOLES = 6
MAX_HOLE_RADIUS_PX = 7.0


def signed_distance(mask: np.ndarray) -> np.ndarray:
    """(H, W) float32 distance to the outline, positive inside the person, negative outside (pixels)."""
    inside = (mask > 0).astype(np.uint8)
    into = cv2.distanceTransform(inside, cv2.DIST_L2, 5)
    out_of = cv2.distanceTransform(1 - inside, cv2.DIST_L2, 5)
    # A pixel on either side of the outline is half a pixel from it, so no pixel sits at exactly 0.
    return np.where(inside > 0, into - 0.5, 0.5 - out_of).astype(np.float32)


def smooth_field(shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """(H, W) float32 Gaussian-smoothed white noise rescaled to unit standard deviation."""
    white = rng.standard_normal(shape).astype(np.float32)
    field = cv2.GaussianBlur(white, (0, 0), FIELD_CORRELATION_PX)
    return field / max(float(field.std()), np.finfo(np.float32).tiny)


def perturb_mask(mask: np.ndarray, strength: float, rng: np.random.Generator) -> np.ndarray:
    """A noisy copy of a true silhouette.

    Parameters
    ----------
    mask : (H, W) uint8
        0 = background, 255 = person.
    strength : float in [0, 1]
        0 returns the mask unchanged; 1 moves the outline by :data:`MAX_BOUNDARY_PX` (one sigma) and
        clears :data:`MAX_HOLES` holes of radius :data:`MAX_HOLE_RADIUS_PX`.
    rng : numpy Generator
        Source of every random draw (the same number of draws for any strength).

    Returns
    -------
    (H, W) uint8, 0 or 255.
    """
    if not 0.0 <= strength <= 1.0:
        raise ValueError(f"strength: expected a value in [0, 1], got {strength}")
    if strength == 0.0:
        return mask.copy()
    field = smooth_field(mask.shape, rng)
    inside = np.flatnonzero(mask > 0)
    picks = rng.integers(0, max(len(inside), 1), MAX_HOLES)
    noisy = np.where(signed_distance(mask) + strength * MAX_BOUNDARY_PX * field > 0, 255, 0).astype(np.uint8)
    holes = int(np.ceil(strength * MAX_HOLES))
    radius = max(1, int(round(strength * MAX_HOLE_RADIUS_PX)))
    for pick in picks[:holes] if len(inside) else ():
        row, col = np.unravel_index(inside[pick], mask.shape)
        cv2.circle(noisy, (int(col), int(row)), radius, 0, thickness=-1)
    return noisy

