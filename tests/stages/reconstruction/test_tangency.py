"""`stages.tangency`: whether the silhouettes agree with the calibration, by epipolar tangency."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from sphere_scene import CENTRE, VOLUME, render_spheres, ring_rig

from calib.camera import Camera
from stages.rays import nearest_point
from stages.tangency import (
    _TangencyProblem,
    camera_disagreement,
    cameras_at_fault,
    pair_disagreement,
    pair_medians,
    refine_turns,
    turned,
)

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


def _moving_scene(frames: int = 8):
    """A ring of six cameras and, per frame, their silhouettes of a trunk, a head and an arm that swings round."""
    rig = list(ring_rig(6, distortion=True))
    per_frame = []
    for frame in range(frames):
        angle = 2 * np.pi * frame / frames
        arm = CENTRE + [0.35 * np.cos(angle), 0.35 * np.sin(angle), 0.2 + 0.15 * np.sin(2 * angle)]
        spheres = (np.array([CENTRE, CENTRE + [0.0, 0.05, 0.4], arm]), np.array([0.25, 0.12, 0.09]))
        per_frame.append([render_spheres(camera, *spheres) for camera in rig])
    return rig, per_frame


def _rays_miss_m(cameras: list[Camera], truth: list[Camera], points: np.ndarray) -> float:
    """How far, on average, the rays of ``cameras`` through the pixels where the ``truth`` cameras see each point
    pass from the point nearest to them all (metres): 0 for a consistent rig, whatever its orientation."""
    misses = []
    for point in points:
        directions = np.array([camera.pixel_rays(true.project(point[None]))[0]
                               for camera, true in zip(cameras, truth, strict=True)])
        centres = np.array([camera.centre for camera in cameras])
        offsets = nearest_point(centres, directions) - centres
        misses.append(np.linalg.norm(offsets - (offsets * directions).sum(axis=1)[:, None] * directions, axis=1))
    return float(np.mean(misses))


@pytest.fixture(scope="module")
def moving():
    return _moving_scene()


def test_cameras_turned_since_their_calibration_are_turned_back(moving):
    truth, masks = moving
    axes = np.random.default_rng(1).normal(size=(len(truth), 3))
    calibrated = [turned(camera, np.radians(0.3) * axis / np.linalg.norm(axis))
                  for camera, axis in zip(truth, axes, strict=True)]
    refinement = refine_turns(masks, calibrated, VOLUME.mean(axis=0))
    assert refinement.tangencies_agree and refinement.after_m < 0.5 * refinement.before_m
    refined = [turned(camera, turn) for camera, turn in zip(calibrated, refinement.turns, strict=True)]
    # The rays meet again: spheres' silhouettes cannot tell every turn of the rig as a whole, but they tell how the
    # cameras' rays disagree. The refined cameras keep their centres: only their orientations were in doubt.
    points = np.array([CENTRE, CENTRE + [0.0, 0.05, 0.4], CENTRE + [0.3, 0.2, 0.3]])
    assert _rays_miss_m(refined, truth, points) < 0.6 * _rays_miss_m(calibrated, truth, points)
    assert all(np.allclose(new.centre, old.centre) for new, old in zip(refined, calibrated, strict=True))


def test_a_sound_calibration_is_left_as_it_is(moving):
    truth, masks = moving
    refinement = refine_turns(masks, truth, VOLUME.mean(axis=0))
    assert refinement.tangencies > 0 and not refinement.tangencies_agree
    assert refinement.before_m < 0.005  # metres: the silhouettes' pixel staircase, which no turn removes


def test_the_disagreements_derivatives_are_those_of_small_turns(moving):
    truth, masks = moving
    problem = _TangencyProblem.build(masks, truth, VOLUME.mean(axis=0))
    turns = np.radians(0.2) * np.random.default_rng(2).normal(size=(len(truth), 3))
    values, jacobian = problem.disagreements(turns)
    step = 1e-7
    for column in range(0, 3 * len(truth), 4):
        stepped = turns.ravel().copy()
        stepped[column] += step
        numeric = (problem.disagreements(stepped.reshape(-1, 3))[0] - values) / step
        assert np.allclose(jacobian[:, column], numeric, rtol=1e-3, atol=1e-5)


def test_without_two_views_of_the_whole_subject_nothing_is_refined(moving):
    truth, masks = moving
    empty = [[np.zeros_like(mask) for mask in frame[:5]] + [frame[5]] for frame in masks]
    refinement = refine_turns(empty, truth, VOLUME.mean(axis=0))
    assert refinement.tangencies == 0 and not refinement.tangencies_agree and not np.any(refinement.turns)
