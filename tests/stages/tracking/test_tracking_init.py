"""Initialisation from the data alone: the pose-vector library and finding unusual starting poses."""

import numpy as np
import pytest
from tracking_testing import VOLUME, sample_ellipsoids

from stages.tracking.body import load_body
from stages.tracking.init import InitParams, generic_poses, initialise, load_pose_library


@pytest.mark.parametrize("name", ["default", "paper"])
def test_library_holds_pose_vectors_of_the_body(name):
    body = load_body(name)
    library = load_pose_library(body)
    assert library.ndim == 2 and library.shape[1] == body.pose_size and len(library) > 100
    np.testing.assert_array_equal(library[:, [0, 1, 3]], 0.0)  # at the origin, facing +y
    assert np.all((library[:, 2] > 0.2) & (library[:, 2] < 0.7))  # root height, fraction of height
    np.testing.assert_allclose(body.clip(library), library)  # inside the joint limits
    generic = np.array(generic_poses(body))
    generic[:, 2] /= body.height_m
    np.testing.assert_allclose(library[: len(generic)], generic, atol=1e-12)


def _pose(body, yaw, degrees):
    pose = body.zero_pose()
    pose[:2] = [0.3, -0.2]
    pose[3] = yaw
    for name, value in degrees.items():
        pose[body.dof_names.index(name)] = np.radians(value)
    pose = body.clip(pose)
    lowest = body.joint_positions(pose)[13:15, 2].min()  # ankles on the floor
    pose[2] += body.joint_positions(body.zero_pose())[13, 2] - lowest
    return pose


@pytest.mark.parametrize("degrees", [
    {"pelvis.pitch": 40, "l_thigh.flex": 40, "r_thigh.flex": 40, "chest.flex": 40, "l_upperarm.flex": 80,
     "r_upperarm.flex": 80},  # deep forward bend, arms hanging
    {"l_thigh.flex": 100, "l_shank.flex": 30, "r_upperarm.abduct": 60},  # high front kick
])
def test_initialisation_finds_bends_and_kicks(degrees):
    body = load_body("default")
    rng = np.random.default_rng(30)
    truth = _pose(body, 2.0, degrees)
    y, n = sample_ellipsoids(body, truth, 1000, rng, outlier_fraction=0.2)
    result = initialise(y, n, body, VOLUME, load_pose_library(body), estimate_height=False,
                        params=InitParams(headings=8))
    error = np.linalg.norm(body.joint_positions(result.pose) - body.joint_positions(truth), axis=1)
    assert error.mean() < 0.02  # metres
