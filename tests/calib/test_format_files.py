"""Calibration files as other tools write them (hand-written text), and the corners of each format."""

import re
from pathlib import Path

import numpy as np
import pytest
from calib_testing import ring_rig, subject_points

from calib import _colmap
from calib.camera import Camera, Rig
from calib.errors import InputError
from calib.formats import load_rig, save_rig

# intri.yml / extri.yml as EasyMocap writes them (OpenCV 4 header, quoted numeric names, 5x1 dist,
# H_/W_ sizes), the second camera with an unquoted numeric name and only a Rodrigues rotation.
EASYMOCAP_INTRI = """%YAML:1.0
---
names:
   - "01"
   - 2
K_01: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 1000., 0., 511.5, 0., 1010., 383.5, 0., 0., 1. ]
dist_01: !!opencv-matrix
   rows: 5
   cols: 1
   dt: d
   data: [ -0.2, 0.05, 0.001, -0.002, 0.01 ]
H_01: 768
W_01: 1024
K_2: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 800., 0., 319.5, 0., 800., 239.5, 0., 0., 1. ]
dist_2: !!opencv-matrix
   rows: 1
   cols: 4
   dt: d
   data: [ -0.1, 0.0, 0.0, 0.0 ]
H_2: 480
W_2: 640
"""
EASYMOCAP_EXTRI = """%YAML:1.0
---
names:
   - "01"
   - 2
R_01: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ 0., 0., 1.5707963267948966 ]
Rot_01: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 0., -1., 0., 1., 0., 0., 0., 0., 1. ]
T_01: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ 0.1, -0.2, 3.0 ]
R_2: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ 3.141592653589793, 0., 0. ]
T_2: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ 0., 0., 4.0 ]
"""

# cameras.txt + images.txt as older COLMAP versions write them: no rigs, frames or points3D files.
CLASSIC_CAMERAS_TXT = """# Camera list with one line of data per camera:
1 SIMPLE_RADIAL 640 480 800 320.5 240.5 -0.1
2 PINHOLE 800 600 900 905 400 300
"""
CLASSIC_IMAGES_TXT = """# Image list with two lines of data per image:
2 1 0 0 0 0.5 0 4 2 right.jpg

1 0.7071067811865476 0 0.7071067811865476 0 -0.5 0 4 1 left.jpg

"""


def write_easymocap(directory: Path) -> None:
    (directory / "intri.yml").write_text(EASYMOCAP_INTRI)
    (directory / "extri.yml").write_text(EASYMOCAP_EXTRI)


def test_easymocap_files_load(tmp_path):
    write_easymocap(tmp_path)
    rig = load_rig("opencv", tmp_path)
    assert rig.names == ("01", "2")
    first, second = rig
    assert first.size == (1024, 768) and second.size == (640, 480)
    np.testing.assert_array_equal(first.K, [[1000.0, 0.0, 511.5], [0.0, 1010.0, 383.5], [0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(first.dist, [-0.2, 0.05, 0.001, -0.002, 0.01])
    np.testing.assert_array_equal(second.dist, [-0.1, 0.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(first.R, [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(second.R, np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    np.testing.assert_allclose(second.centre, [0.0, 0.0, 4.0], atol=1e-12)


def test_opencv_caller_sizes_override_the_file_sizes(tmp_path):
    write_easymocap(tmp_path)
    rig = load_rig("opencv", tmp_path, image_sizes={"2": (1280, 960)})
    assert rig["2"].size == (1280, 960)
    assert rig["01"].size == (1024, 768)


def test_classic_colmap_text_model_without_points_loads(tmp_path):
    (tmp_path / "cameras.txt").write_text(CLASSIC_CAMERAS_TXT)
    (tmp_path / "images.txt").write_text(CLASSIC_IMAGES_TXT)
    rig = load_rig("colmap", tmp_path)
    assert rig.names == ("left", "right")  # image id order, not file order
    left, right = rig
    np.testing.assert_allclose(left.K, [[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(left.dist, [-0.1, 0.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(left.R, [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(right.R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(right.centre, [-0.5, 0.0, -4.0], atol=1e-12)
    assert right.size == (800, 600)
    assert not (tmp_path / "points3D.txt").exists()  # the reader never writes into the user's model


def test_colmap_binary_writer_round_trip_without_points(rig12, tmp_path):
    _colmap.save(rig12, tmp_path, binary=True)
    assert not list(tmp_path.glob("*.txt"))
    (tmp_path / "points3D.bin").unlink()
    X = subject_points(100)
    loaded = load_rig("colmap", tmp_path)
    assert loaded.names == rig12.names
    np.testing.assert_allclose(loaded.project(X), rig12.project(X), rtol=0, atol=1e-6)


def renamed(rig: Rig, names: list[str]) -> Rig:
    return Rig(tuple(Camera(name, c.K, c.dist, c.R, c.t, c.size) for name, c in zip(names, rig, strict=True)))


@pytest.mark.parametrize(
    ("fmt", "names"),
    [
        ("colmap", ["cam.01", "2", "side-left", "Cam_B"]),
        ("anipose", ["cam.01", "2", "side-left", "Cam_B"]),
        ("opencv", ["01", "2", "side-left", "Cam_B"]),  # OpenCV keys cannot hold dots
    ],
)
def test_names_with_dots_dashes_and_digits_round_trip(tmp_path, fmt, names):
    save_rig(renamed(ring_rig(4), names), fmt, tmp_path)
    assert load_rig(fmt, tmp_path).names == tuple(names)


def test_anipose_name_needing_toml_escapes_round_trips(tmp_path):
    save_rig(renamed(ring_rig(1), ['front "A" \\ left']), "anipose", tmp_path / "calib.toml")
    assert load_rig("anipose", tmp_path / "calib.toml").names == ('front "A" \\ left',)


def test_opencv_writer_rejects_names_that_cannot_be_keys(tmp_path):
    with pytest.raises(InputError, match="'cam.01': cannot be part of an OpenCV YAML key"):
        save_rig(renamed(ring_rig(1), ["cam.01"]), "opencv", tmp_path)


@pytest.mark.parametrize("fmt", ["colmap", "anipose"])
def test_stored_size_disagreeing_with_the_media_is_an_error(rig12, tmp_path, fmt):
    save_rig(rig12, fmt, tmp_path)
    width, height = rig12["cam_4"].size
    assert load_rig(fmt, tmp_path, image_sizes={"cam_4": (width, height)}).names == rig12.names
    with pytest.raises(InputError, match=f"cam_4.*{width}x{height}.*{width // 2}x{height // 2}"):
        load_rig(fmt, tmp_path, image_sizes={"cam_4": (width // 2, height // 2)})


@pytest.mark.parametrize(("cameras", "images", "where", "problem"), [
    ("1 PINHOLE 640 480 800 800\n", "1 1 0 0 0 0 0 4 1 a.jpg\n\n", "cameras.txt: line 1",
     "PINHOLE takes 4 numeric parameters, got ['800', '800']"),  # cx, cy missing
    ("# a comment\n1 PINHOLE 640 480 800 800 320 240\n", "\n1 1 0 0 0 0 0 4 7 a.jpg\n\n", "images.txt: line 2",
     "camera 7 is not in cameras.txt"),
    ("1 PINHOLE 640 480 800 800 320 240\n", "1 1 0 0 0 0 0 4 1 a.jpg\n1 2\n", "images.txt: line 2",
     "not (X, Y, POINT3D_ID) triples"),
])
def test_colmap_text_errors_name_the_file_and_line(tmp_path, cameras, images, where, problem):
    """Not pycolmap's C++ check ("[reconstruction_io_text.cc:148] Check failed: camera.VerifyParams()")."""
    (tmp_path / "cameras.txt").write_text(cameras)
    (tmp_path / "images.txt").write_text(images)
    with pytest.raises(InputError, match=re.escape(f"{tmp_path / where}: {problem}")) as error:
        load_rig("colmap", tmp_path)
    assert "Check failed" not in str(error.value) and ".cc:" not in str(error.value)


def test_a_damaged_binary_colmap_model_is_named_without_pycolmaps_check(rig12, tmp_path):
    save_rig(rig12, "colmap", tmp_path / "text")
    binary = tmp_path / "binary"
    binary.mkdir()
    _colmap._read_reconstruction(tmp_path / "text").write_binary(str(binary))
    (binary / "cameras.bin").write_bytes((binary / "cameras.bin").read_bytes()[:20])
    with pytest.raises(InputError, match=f"{binary}: not a readable COLMAP bin model") as error:
        load_rig("colmap", binary)
    assert "Check failed" not in str(error.value) and ".cc:" not in str(error.value)


def test_anipose_file_without_camera_tables_is_an_error(tmp_path):
    (tmp_path / "calibration.toml").write_text("[metadata]\nadjusted = false\n")
    with pytest.raises(InputError, match=r"calibration.toml: no \[cam_N\] camera tables"):
        load_rig("anipose", tmp_path)


def test_anipose_non_numeric_matrix_names_table_and_key(tmp_path):
    save_rig(ring_rig(2), "anipose", tmp_path)
    text = (tmp_path / "calibration.toml").read_text()
    second = text.index("[cam_1]")
    broken = text[:second] + text[second:].replace("matrix = [", 'matrix = ["fx", ', 1)
    (tmp_path / "calibration.toml").write_text(broken)
    with pytest.raises(InputError, match=r"calibration.toml \[cam_1\] matrix"):
        load_rig("anipose", tmp_path)


def test_opencv_yaml_that_is_not_a_mapping_names_the_file(tmp_path):
    for name in ("intri.yml", "extri.yml"):
        (tmp_path / name).write_text("%YAML:1.0\n---\n- K_01\n- dist_01\n")
    with pytest.raises(InputError, match="intri.yml: expected a mapping of keys"):
        load_rig("opencv", tmp_path)
