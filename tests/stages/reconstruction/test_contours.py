import cv2
import numpy as np
import pytest

from stages.reconstruction.contours import outline


def _disk(radius: int, size: int = 64) -> np.ndarray:
    mask = np.zeros((size, size), np.uint8)
    cv2.circle(mask, (size // 2, size // 2), radius, 255, cv2.FILLED)
    return mask


@pytest.mark.parametrize("radius", [6, 12])
def test_smoothing_removes_the_staircase_without_shrinking_the_outline(radius):
    # A limb a dozen pixels across: a Gaussian alone pulled its outline in by σ²κ/2, 0.4 px at radius 6.
    centre = np.array([32.0, 32.0])
    raw = np.linalg.norm(outline(_disk(radius), smoothing_px=0).pixels - centre, axis=1)
    smooth = np.linalg.norm(outline(_disk(radius), smoothing_px=2.0).pixels - centre, axis=1)
    assert abs(smooth.mean() - raw.mean()) < 0.05
    assert smooth.std() < raw.std() / 5


def test_smoothing_keeps_the_length_of_a_thin_limb():
    # Four pixels wide: the Gaussian alone shortened it by a pixel, and thinned it.
    mask = np.zeros((40, 80), np.uint8)
    mask[18:22, 10:70] = 255
    raw, smooth = (outline(mask, smoothing_px=s).pixels for s in (0, 2.0))
    assert np.ptp(smooth[:, 0]) == pytest.approx(np.ptp(raw[:, 0]), abs=0.1)
    assert np.ptp(smooth[:, 1]) >= np.ptp(raw[:, 1])
