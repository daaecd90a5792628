"""Plausibility checks: rig size against the declared units, intrinsics, cameras that miss the volume."""

import numpy as np
import pytest
from calib_testing import ring_rig

from calib.camera import Camera, Rig
from calib.errors import InputError
from calib.sanity import check_cameras_see_volume, check_intrinsics, check_rig_size
from calib.world import fixed_transform

VOLUME = np.array([[-1.0, -1.0, 0.0], [1.0, 1.0, 2.0]])


def test_a_plausible_rig_passes():
    rig = ring_rig(6)
    check_rig_size(rig, units="m", where="calib.toml")
    check_intrinsics(rig, where="calib.toml")
    check_cameras_see_volume(rig, VOLUME, where="calib.toml")


def test_millimetres_declared_as_metres_name_the_unit_that_fits():
    in_mm = Rig(tuple(Camera(c.name, c.K, c.dist, c.R, c.t * 1000.0, c.size) for c in ring_rig(6)))
    with pytest.raises(InputError, match=r"calib.toml: with units: m the cameras span 8.09e\+03 m.*units: mm would "
                                         r"make it 8.09 m") as error:
        check_rig_size(fixed_transform(units="m", up="+z").apply(in_mm), units="m", where="calib.toml")
    assert "\n" not in str(error.value)


def test_metres_declared_as_millimetres_are_refused():
    with pytest.raises(InputError, match="span 0.00809 m.*units: m would make it 8.09 m"):
        check_rig_size(fixed_transform(units="mm", up="+z").apply(ring_rig(6)), units="mm", where="calib.toml")


@pytest.mark.parametrize(("entry", "value", "message"), [((0, 0), 1e308, "focal lengths"),
                                                         ((1, 1), 20.0, "focal lengths"),
                                                         ((0, 2), 1e5, "its principal point")])
def test_absurd_intrinsics_are_refused(entry, value, message):
    camera = ring_rig(1)[0]
    K = camera.K.copy()
    K[entry] = value
    with pytest.raises(InputError, match=f"calib.toml: camera 'cam_0' has {message}"):
        check_intrinsics(Rig((Camera(camera.name, K, camera.dist, camera.R, camera.t, camera.size),)),
                         where="calib.toml")


def test_a_camera_looking_away_from_the_volume_is_named():
    rig = ring_rig(3)
    away = Camera.look_at("away", (4.0, 0.0, 1.5), (8.0, 0.0, 1.5), f_px=800.0, size=(640, 480))
    with pytest.raises(InputError, match="camera 'away' does not see the working volume .*behind it"):
        check_cameras_see_volume(Rig((*rig.cameras, away)), VOLUME, where="calib.toml")
    with pytest.raises(InputError, match="camera 'cam_0' does not see .*(outside its image|behind it)"):
        check_cameras_see_volume(rig, VOLUME + [6.0, 6.0, 0.0], where="calib.toml")


def test_capture_in_millimetres_declared_as_metres_fails_to_open(tmp_path):
    from conftest import make_capture, write_config

    from pipeline.io.capture import Capture

    root = make_capture(tmp_path / "c", units="mm")
    write_config(root, calibration={"format": "anipose", "path": "calibration/calibration.toml", "units": "m"})
    with pytest.raises(InputError, match=r"calibration.toml: with units: m the cameras span .*units: mm would"):
        Capture.open(root)
