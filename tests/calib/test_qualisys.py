"""The Qualisys (QTM) reader on a file written here from the format's description, not by our writer."""

import numpy as np
import pytest

from calib.errors import InputError
from calib.formats import load_rig

# Camera 26580 (a video camera): 1920 x 1088 sensor, 64 sub-pixel units per pixel, the video window starting at
# pixel (16, 8); at x, y, z = (0, -5000, 1000) mm, looking along +y (QTM camera axes: x right = +x, y up = +z,
# z backwards = -y). fx = 1000 px, fy = 1002 px, principal point (950, 540) in sensor pixels.
# Camera 26581 records no video (marker-only) and camera 26582 is inactive.
QCA = """<?xml version="1.0" encoding="UTF-8"?>
<calibration source="test.qca" created="2024-01-01" qtm-version="2024.1" type="regular" wandLength="601.1">
  <results std-dev="0.5" min-max-diff="1.2"/>
  <cameras>
    <camera active="1" calibrated="true" point-count="2241" avg-residual="0.5" serial="26580" model="Miqus Video"
            viewrotation="0" video_resolution="1080p">
      <fov_marker left="0" top="0" right="1919" bottom="1087"/>
      <fov_marker_max left="0" top="0" right="1919" bottom="1087"/>
      <fov_video left="16" top="8" right="1615" bottom="907"/>
      <fov_video_max left="0" top="0" right="1919" bottom="1087"/>
      <transform x="0" y="-5000" z="1000" r11="1" r12="0" r13="0" r21="0" r22="0" r23="1" r31="0" r32="-1" r33="0"/>
      <intrinsic focallength="9.27" sensorMinU="0.000000" sensorMaxU="122879.000000" sensorMinV="0.000000"
                 sensorMaxV="69631.000000" focalLengthU="64000" focalLengthV="64128" centerPointU="60800"
                 centerPointV="34560" skew="0" radialDistortion1="-0.05" radialDistortion2="0.1"
                 radialDistortion3="0.01" tangentalDistortion1="0.001" tangentalDistortion2="-0.002"/>
    </camera>
    <camera active="1" serial="26581" model="Miqus M3" viewrotation="0">
      <fov_video left="0" top="0" right="1823" bottom="1087"/>
      <transform x="5000" y="0" z="1000" r11="0" r12="1" r13="0" r21="0" r22="0" r23="1" r31="1" r32="0" r33="0"/>
      <intrinsic sensorMinU="0" sensorMaxU="116735" sensorMinV="0" sensorMaxV="69631" focalLengthU="64000"
                 focalLengthV="64000" centerPointU="58368" centerPointV="34816" skew="0"/>
    </camera>
    <camera active="0" serial="26582" viewrotation="0"/>
  </cameras>
</calibration>
"""


@pytest.fixture
def qca(tmp_path):
    path = tmp_path / "calibration.qca.txt"
    path.write_text(QCA)
    return path


def test_a_video_camera_is_read_in_pixels_and_metres(qca):
    rig = load_rig("qualisys", qca, image_sizes={"26580": (1600, 900)})
    assert rig.names == ("26580",)  # the marker-only camera has no media, the inactive one is skipped
    camera = rig["26580"]
    assert camera.size == (1600, 900)
    np.testing.assert_allclose(camera.K, [[1000, 0, 950 - 16], [0, 1002, 540 - 8], [0, 0, 1]])
    np.testing.assert_allclose(camera.dist, [-0.05, 0.1, 0.001, -0.002, 0.01])
    np.testing.assert_allclose(camera.centre, [0, -5, 1], atol=1e-12)
    # 5 m in front of the camera, 0.5 m to its right and 0.25 m above it
    x, y = 0.1, -0.05
    r2 = x * x + y * y
    radial = 1 - 0.05 * r2 + 0.1 * r2**2 + 0.01 * r2**3
    xd = x * radial + 2 * 0.001 * x * y - 0.002 * (r2 + 2 * x * x)
    yd = y * radial + 0.001 * (r2 + 2 * y * y) + 2 * -0.002 * x * y
    np.testing.assert_allclose(camera.project(np.array([[0.5, 0.0, 1.25]])),
                               [[1000 * xd + 934, 1002 * yd + 532]], atol=1e-9)


def test_every_active_camera_without_media_sizes(qca):
    rig = load_rig("qualisys", qca.parent)
    assert rig.names == ("26580", "26581")
    assert rig["26581"].size == (1824, 1088)
    np.testing.assert_allclose(rig["26581"].K[:2, 2], [912, 544])
    # camera 26581 at (5, 0, 1) m looks along -x: the origin's column is straight ahead
    assert rig["26581"].depth(np.array([[0.0, 0.0, 1.0]]))[0] == pytest.approx(5.0)


def test_video_recorded_at_half_resolution_halves_the_intrinsics(qca):
    camera = load_rig("qualisys", qca, image_sizes={"26580": (800, 450)})["26580"]
    np.testing.assert_allclose(camera.K, [[500, 0, (934 + 0.5) / 2 - 0.5], [0, 501, (532 + 0.5) / 2 - 0.5], [0, 0, 1]])


def test_a_turned_video_is_refused(qca):
    qca.write_text(QCA.replace('viewrotation="0" video_resolution', 'viewrotation="90" video_resolution'))
    with pytest.raises(InputError, match="viewrotation=90.*unrotated"):
        load_rig("qualisys", qca, image_sizes={"26580": (900, 1600)})


def test_media_named_otherwise_are_refused_with_the_serials(qca):
    with pytest.raises(InputError, match="videos named by serial number: 26580, 26581, 26582"):
        load_rig("qualisys", qca, image_sizes={"cam1": (1600, 900)})


@pytest.mark.parametrize(("change", "message"), [
    (('focalLengthV="64128"', 'focalLengthV="wide"'), "focalLengthV='wide' is not a number"),
    (('<transform x="0" y="-5000"', '<transform y="-5000"'), "has no attribute 'x'"),
    (('sensorMaxU="122879.000000"', 'sensorMaxU="100800"'), "whole number of sub-pixel units"),
    (('<calibration ', '<!DOCTYPE x [<!ENTITY a "b">]>\n<calibration '), "DOCTYPE or ENTITY"),
    (('</calibration>', ''), "not valid XML"),
])
def test_malformed_files_are_named(qca, change, message):
    qca.write_text(QCA.replace(*change))
    with pytest.raises(InputError, match=message):
        load_rig("qualisys", qca, image_sizes={"26580": (1600, 900)})
