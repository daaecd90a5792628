"""`stages.tangency`: whether the silhouettes agree with the calibration, by epipolar tangency."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from sphere_scene import CENTRE, VOLUME, render_spheres, ring_rig

from calib.camera import Camera
from stages.tangency import camera_disagreement, cameras_at_fault, pair_disagreement, pair_medians

# Two spheres, so that the silhouettes differ from view to view.
SPHERES = (np.array([CENTRE, CENTRE + [0.25, 0.1, 0.35]]), np.array([0.25, 0.12]))


@pytest.fixture(scope="module")
def scene():
    rig = ring_rig(6, distortion=True)
    return list(rig), [render_spheres(camera, *SPHERES) for camera in rig]


def _turned(camera: Camera, degrees: float) -> Camera:
    turn, _ = cv2.Rodrigues(np.radians(degrees) * np.array([0.6, 0.0, 0.8]))
    R = turn @ camera.R
    return replace(camera, R=R, t=-R @ camera.centre)


def test_a_sound_calibration_agrees_within_millimetres(scene):
    cameras, masks = scene
    pairs = pair_medians([pair_disagreement(masks, cameras, VOLUME.mean(axis=0))])
    assert np.all(camera_disagreement(pairs) < 0.005)  # metres: a pixel's staircase at 4 m
    assert not cameras_at_fault(pairs, 0.05).any()


def test_a_camera_turned_since_its_calibration_is_the_one_at_fault(scene):
    cameras, masks = scene
    calibrated = [*cameras[:2], _turned(cameras[2], 2.0), *cameras[3:]]  # the masks are the true cameras'
    pairs = pair_medians([pair_disagreement(masks, calibrated, VOLUME.mean(axis=0))])
    at_fault = cameras_at_fault(pairs, 0.05)
    assert at_fault.tolist() == [False, False, True, False, False, False]
    disagreement = camera_disagreement(pairs, ~at_fault)
    assert disagreement[2] > 0.05 and np.all(np.delete(disagreement, 2) < 0.01)


def test_a_view_cut_by_its_border_or_empty_is_not_measured(scene):
    cameras, masks = scene
    cut, empty = masks[0].copy(), np.zeros_like(masks[1])
    cut[cut.any(axis=1), : cut.any(axis=0).argmax() + 1] = 255  # the silhouette stretched to the left border
    disagreement = pair_disagreement([cut, empty, *masks[2:]], cameras, VOLUME.mean(axis=0))
    assert np.all(np.isnan(disagreement[:2])) and np.all(np.isnan(disagreement[:, :2]))
    assert not np.isnan(disagreement[2:, 2:][~np.eye(4, dtype=bool)]).any()


def test_the_worst_cameras_are_set_aside_until_the_others_agree():
    # Four cameras, 1 and 3 swapped: every pair with either is off, so the sound cameras 0 and 2 disagree with two
    # of their three partners; setting the worst aside first leaves them agreeing.
    pairs = np.full((4, 4), 0.003)
    pairs[[1, 3], :] = pairs[:, [1, 3]] = 0.2
    pairs[1, 3] = pairs[3, 1] = 0.3
    np.fill_diagonal(pairs, np.nan)
    assert np.all(camera_disagreement(pairs)[[0, 2]] > 0.05)  # the plain median blames every camera
    assert cameras_at_fault(pairs, 0.05).tolist() == [False, True, False, True]
    # Two cameras that disagree cannot say which of them is off; two that agree are both sound.
    two = np.array([[np.nan, 0.2], [0.2, np.nan]])
    assert cameras_at_fault(two, 0.05).tolist() == [True, True]
    assert cameras_at_fault(two / 100, 0.05).tolist() == [False, False]
