import numpy as np
import pytest
from motion_testing import random_motion

from calib.camera import Camera
from stages.export.overlay import SIDE_COLOURS, draw_skeleton
from stages.joints import JOINT_NAMES


def _camera() -> Camera:
    return Camera.look_at("front", eye=(0.0, -4.0, 1.0), target=(0.0, 0.0, 1.0), f_px=250, size=(320, 400))


def test_skeleton_is_drawn_where_the_joints_project():
    joints = random_motion(1, seed=0, amplitude=0.2)[0]
    joints[:, :2] -= joints[0, :2]  # pelvis in front of the camera
    image = np.zeros((400, 320, 3), np.uint8)
    drawn = draw_skeleton(image, _camera(), joints)
    assert not image.any()  # the input is not modified
    u, v = np.round(_camera().project(joints[[JOINT_NAMES.index("head")]])[0]).astype(int)
    assert tuple(drawn[v, u]) == SIDE_COLOURS["centre"]
    u, v = np.round(_camera().project(joints[[JOINT_NAMES.index("l_ankle")]])[0]).astype(int)
    assert tuple(drawn[v, u]) == SIDE_COLOURS["l"]
    assert drawn.any(axis=2).mean() < 0.2


def test_joints_behind_the_camera_are_not_drawn():
    joints = np.tile([0.0, -5.0, 1.0], (17, 1))  # all behind the camera at y = -4 looking at +y
    drawn = draw_skeleton(np.zeros((400, 320, 3), np.uint8), _camera(), joints, colour=(1, 2, 3))
    assert not drawn.any()


def test_draw_skeleton_checks_shapes():
    with pytest.raises(ValueError, match="joints must have shape"):
        draw_skeleton(np.zeros((400, 320, 3), np.uint8), _camera(), np.zeros((3, 3)))
