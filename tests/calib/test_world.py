import numpy as np
import pytest
from calib_testing import subject_points

from calib.camera import Camera, Rig
from calib.errors import InputError
from calib.world import UNIT_SCALE, fixed_transform, from_world, up_rotation

AXES = {
    "+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1),
}


@pytest.mark.parametrize("up", AXES)
def test_up_rotation_is_proper_and_takes_up_to_z(up):
    A = up_rotation(up)
    np.testing.assert_array_equal(A @ A.T, np.eye(3))
    assert np.linalg.det(A) == pytest.approx(1.0)
    np.testing.assert_array_equal(A @ AXES[up], [0.0, 0.0, 1.0])


def test_up_rotation_matches_capture_format_table():
    x, y, z = 1.0, 2.0, 3.0
    expected = {
        "+z": (x, y, z), "-z": (x, -y, -z), "+y": (x, -z, y),
        "-y": (x, z, -y), "+x": (-z, y, x), "-x": (z, y, -x),
    }
    for up, mapped in expected.items():
        np.testing.assert_array_equal(up_rotation(up) @ (x, y, z), mapped)


def test_point_in_y_up_centimetre_calibration_lands_at_z_up_metres():
    """A head 170 cm above a +y-up floor, 10 cm along x and 30 cm along z, seen by one camera."""
    head_cm = np.array([10.0, 170.0, 30.0])
    camera = Camera.look_at("c", (0.0, 150.0, -400.0), head_cm, up=(0.0, 1.0, 0.0), f_px=900.0,
                            size=(800, 600))
    pixel = camera.project(head_cm[None])
    converted = fixed_transform(units="cm", up="+y").apply(Rig((camera,)))["c"]
    head_m = np.array([0.1, -0.3, 1.7])  # (x, -z, y) / 100
    np.testing.assert_allclose(converted.project(head_m[None]), pixel, atol=1e-9)
    np.testing.assert_allclose(converted.centre, [0.0, 4.0, 1.5], atol=1e-12)
    # the world's up is still the image's up: a point 10 cm higher appears higher in the image
    assert converted.project((head_m + [0.0, 0.0, 0.1])[None])[0, 1] < pixel[0, 1]


@pytest.mark.parametrize("units", UNIT_SCALE)
@pytest.mark.parametrize("up", AXES)
def test_projections_unchanged_when_points_are_converted_too(rig12, units, up):
    X_old = subject_points(40) / UNIT_SCALE[units]
    X_new = (UNIT_SCALE[units] * X_old) @ up_rotation(up).T
    converted = fixed_transform(units=units, up=up).apply(rig12)
    np.testing.assert_allclose(converted.project(X_new), rig12.project(X_old), atol=1e-9)
    np.testing.assert_allclose(converted.centres, (UNIT_SCALE[units] * rig12.centres) @ up_rotation(up).T,
                               atol=1e-9)


@pytest.mark.parametrize("up", AXES)
def test_from_world_inverts_the_fixed_transform(rig12, up):
    back = fixed_transform(units="mm", up=up).apply(from_world(rig12, units="mm", up=up))
    assert back.names == rig12.names
    for original, restored in zip(rig12, back, strict=True):
        np.testing.assert_allclose(restored.R, original.R, atol=1e-12)
        np.testing.assert_allclose(restored.t, original.t, atol=1e-12)
        np.testing.assert_array_equal(restored.K, original.K)
        assert restored.size == original.size


def test_bad_units_is_an_input_error(rig12):
    with pytest.raises(InputError, match="units: unknown unit 'inch'; expected one of m, cm, mm"):
        fixed_transform(units="inch", up="+z").apply(rig12)


def test_bad_up_axis_is_an_input_error(rig12):
    with pytest.raises(InputError, match="up: unknown axis 'z'"):
        fixed_transform(units="m", up="z").apply(rig12)
