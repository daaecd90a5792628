"""The cameras' synchrony from their silhouettes: a view whose frames run behind the others' is found."""

import numpy as np
import pytest

from stages.synchrony import check_synchrony, clearly_better, fastest_frames
from tests.stages.reconstruction.sphere_scene import VOLUME, render_spheres, ring_rig

FRAMES = 30
MAX_OFFSET = 3


def _scene(frame: int) -> tuple[np.ndarray, np.ndarray]:
    """A body-sized sphere walking along x and a limb-sized one swinging around it, at ``frame``."""
    body = np.array([-0.8 + 0.06 * frame, 0.0, 1.0])
    angle = 0.8 * frame
    limb = body + 0.5 * np.array([np.cos(angle), np.sin(angle), 0.4 * np.sin(angle)])
    return np.stack([body, limb]), np.array([0.22, 0.12])


@pytest.fixture(scope="module")
def rendered():
    rig = ring_rig(6, size=(260, 200), f_px=260.0)
    return rig, [[render_spheres(camera, *_scene(frame)) for camera in rig] for frame in range(FRAMES)]


def _check(rig, masks, lag: dict[int, int]):
    """The check on ``masks`` with camera c's frame f showing the scene of frame f - lag[c] (clamped)."""
    def mask_at(index, camera):
        return masks[min(max(index - lag.get(camera, 0), 0), FRAMES - 1)][camera]
    return check_synchrony(mask_at, list(rig), VOLUME, range(MAX_OFFSET + 1, FRAMES - MAX_OFFSET - 1, 3),
                           MAX_OFFSET, 1)


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


def test_a_still_subject_says_nothing_about_time(rendered):
    rig, masks = rendered
    check = check_synchrony(lambda index, camera: masks[0][camera], list(rig), VOLUME, [5, 10, 15], MAX_OFFSET, 1)
    assert np.isnan(check.agreement).all() and not check.lags().any()


def test_no_frame_no_check(rendered):
    rig, masks = rendered
    check = check_synchrony(lambda index, camera: masks[index][camera], list(rig), VOLUME, [], MAX_OFFSET, 1)
    assert check.frames == [] and not check.lags().any()


def test_the_fastest_frame_of_each_stretch_is_chosen():
    joints = np.zeros((40, 2, 3))
    joints[:, 0, 0] = np.cumsum(np.where(np.arange(40) % 10 == 7, 0.2, 0.01))  # a jump at frames 7, 17, 27, 37
    joints[20:23] = np.nan  # frames not estimated
    chosen = fastest_frames(joints, 4, 3)
    assert chosen == [6, 16, 26, 36]  # frames 6 and 7 both see the jump between their neighbours: the first is taken
    assert fastest_frames(joints[:6], 4, 3) == []


def test_clearly_better_needs_a_consistent_gain():
    rng = np.random.default_rng(0)
    base = rng.uniform(0.8, 0.9, 12)
    assert clearly_better(base + 0.05 + rng.normal(0, 0.01, 12), base)
    assert not clearly_better(base + rng.normal(0, 0.05, 12), base)
    assert not clearly_better(base[:2] + 0.1, base[:2])  # too few frames to tell
