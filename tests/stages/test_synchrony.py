"""The cameras' synchrony from their silhouettes: a view whose frames run behind the others' is found."""

import numpy as np
import pytest

from stages.synchrony import check_synchrony, clearly_better
from tests.stages.reconstruction.sphere_scene import VOLUME, render_spheres, ring_rig

FRAMES = 24


def _scene(frame: int) -> tuple[np.ndarray, np.ndarray]:
    """A body-sized sphere walking along x and a limb-sized one swinging around it, at ``frame``."""
    body = np.array([-0.8 + 0.07 * frame, 0.0, 1.0])
    angle = 0.8 * frame
    limb = body + 0.5 * np.array([np.cos(angle), np.sin(angle), 0.4 * np.sin(angle)])
    return np.stack([body, limb]), np.array([0.22, 0.12])


@pytest.fixture(scope="module")
def rendered():
    rig = ring_rig(6, size=(260, 200), f_px=260.0)
    return rig, [[render_spheres(camera, *_scene(frame)) for camera in rig] for frame in range(FRAMES)]


def _check(rig, masks, lag: dict[int, int]):
    """The check on ``masks`` with camera c's frame f showing the scene of frame f - lag[c] (clamped)."""
    def masks_at(index):
        return [masks[min(max(index - lag.get(c, 0), 0), FRAMES - 1)][c] for c in range(len(rig))]
    return check_synchrony(masks_at, list(rig), VOLUME, FRAMES, 8, 3, 1)


def test_synchronised_cameras_agree_best_at_the_same_frame(rendered):
    rig, masks = rendered
    check = _check(rig, masks, {})
    assert len(check.frames) == 8
    assert not check.lags().any()
    mean = check.mean_agreement()
    zero = int(np.flatnonzero(check.offsets == 0)[0])
    assert np.all(mean[:, zero] >= np.nanmax(mean, axis=1))


@pytest.mark.parametrize("lag", [2, -1])
def test_a_camera_behind_or_ahead_is_found_with_its_lag(rendered, lag):
    rig, masks = rendered
    check = _check(rig, masks, {4: lag})
    expected = np.zeros(len(rig), dtype=int)
    expected[4] = lag
    np.testing.assert_array_equal(check.lags(), expected)


def test_only_the_cameras_asked_are_measured(rendered):
    rig, masks = rendered
    masks_at = lambda index: masks[index]  # noqa: E731
    check = check_synchrony(masks_at, list(rig), VOLUME, FRAMES, 8, 3, 1, measured=[1, 2])
    measured = np.isfinite(check.agreement).any(axis=(1, 2))
    np.testing.assert_array_equal(measured, [False, True, True, False, False, False])


def test_too_short_a_capture_is_not_checked(rendered):
    rig, masks = rendered
    check = check_synchrony(lambda index: masks[index], list(rig), VOLUME, 8, 8, 3, 1)
    assert check.frames == [] and not check.lags().any()


def test_clearly_better_needs_a_consistent_gain():
    rng = np.random.default_rng(0)
    base = rng.uniform(0.8, 0.9, 12)
    assert clearly_better(base + 0.05 + rng.normal(0, 0.01, 12), base)
    assert not clearly_better(base + rng.normal(0, 0.05, 12), base)
    assert not clearly_better(base[:2] + 0.1, base[:2])  # too few frames to tell
