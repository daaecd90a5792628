"""Projection-matrix calibrations: decomposition of P into K, R, t, the directory reader and writer."""

from pathlib import Path

import cv2
import numpy as np
import pytest
from calib_testing import ring_rig, subject_points

from calib._projection import decompose
from calib.camera import Camera
from calib.errors import InputError
from calib.formats import load_rig

SIZE = (1000, 800)


def known_camera() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K with skew and unequal focal lengths, a rotation with all three angles, a translation."""
    K = np.array([[1100.0, 0.7, 501.3], [0.0, 1092.0, 388.9], [0.0, 0.0, 1.0]])
    R = cv2.Rodrigues(np.array([0.4, -1.9, 0.3]))[0]
    return K, R, np.array([0.3, -1.2, 4.5])


def write_matrix(path: Path, P: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(" ".join(f"{value:.17g}" for value in row) for row in P) + "\n")
    return path


@pytest.mark.parametrize("scale", [1.0, 3.7e-4, -2.5])
def test_decompose_recovers_known_k_r_t_whatever_the_scale_and_sign_of_p(scale):
    K, R, t = known_camera()
    got_K, got_R, got_t = decompose(scale * K @ np.column_stack([R, t]))
    np.testing.assert_allclose(got_K, K, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got_R, R, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got_t, t, rtol=0, atol=1e-12)
    assert np.linalg.det(got_R) == pytest.approx(1.0)


def test_reader_names_cameras_by_file_name_up_to_the_first_dot_in_natural_order(tmp_path):
    rig = ring_rig(12)
    for camera in reversed(rig.cameras):
        index = int(camera.name.split("_")[1])
        write_matrix(tmp_path / f"Camera{index + 1}.Pmat.cal", -0.01 * camera.P)
    loaded = load_rig("projection", tmp_path, image_sizes={f"Camera{i + 1}": SIZE for i in range(12)})
    assert loaded.names == tuple(f"Camera{i + 1}" for i in range(12))  # Camera10 after Camera9
    X = subject_points(100)
    for got, want in zip(loaded, rig, strict=True):
        undistorted = Camera(want.name, want.K, np.zeros(5), want.R, want.t, want.size)
        np.testing.assert_allclose(got.project(X), undistorted.project(X), rtol=0, atol=1e-6)
        np.testing.assert_allclose(got.centre, want.centre, atol=1e-9)
        assert np.all(got.depth(X) > 0)  # looking at the subject, not away from it
        assert got.size == SIZE and not np.any(got.dist)


def test_hidden_files_are_ignored(tmp_path):
    K, R, t = known_camera()
    write_matrix(tmp_path / "a.txt", K @ np.column_stack([R, t]))
    (tmp_path / ".DS_Store").write_bytes(b"\0\1")
    assert load_rig("projection", tmp_path, image_sizes={"a": SIZE}).names == ("a",)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("1 2 3 4 5 6 7 8 9 10 11", "11 numbers, expected 12"),
        ("1 2 3 4 5 6 7 8 9 10 11 12 13", "13 numbers, expected 12"),
        ("1 2 3 4 5 6 7 8 9 10 11 twelve", "'twelve' is not a number"),
        ("1 0 0 0 0 1 0 0 0 0 nan 1", "NaN or infinity"),
        ("1 0 0 0 0 1 0 0 1 1 0 1", "rank-deficient .*rank 2"),
        ("0 0 0 0 0 0 0 0 0 0 0 0", "rank-deficient .*rank 0"),
    ],
)
def test_malformed_matrix_file_is_a_one_line_error_naming_it(tmp_path, text, message):
    (tmp_path / "cam.P.txt").write_text(text)
    with pytest.raises(InputError, match=message) as error:
        load_rig("projection", tmp_path, image_sizes={"cam": SIZE})
    assert str(tmp_path / "cam.P.txt") in str(error.value) and "\n" not in str(error.value)


def test_missing_sizes_files_and_folder_are_errors(tmp_path):
    with pytest.raises(InputError, match="no such directory"):
        load_rig("projection", tmp_path / "absent", image_sizes={})
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no projection matrix files"):
        load_rig("projection", tmp_path / "empty", image_sizes={})
    K, R, t = known_camera()
    write_matrix(tmp_path / "p" / "cam.P.txt", K @ np.column_stack([R, t]))
    with pytest.raises(InputError, match="cam.P.txt: no image size for camera 'cam'"):
        load_rig("projection", tmp_path / "p", image_sizes={})


def test_writer_refuses_what_a_projection_matrix_cannot_hold(tmp_path):
    from calib.camera import Rig
    from calib.formats import save_rig

    camera = ring_rig(1)[0]
    with pytest.raises(InputError, match="distortion"):
        save_rig(Rig((camera,)), "projection", tmp_path)
    dotted = Camera("a.b", camera.K, np.zeros(5), camera.R, camera.t, camera.size)
    with pytest.raises(InputError, match="without '.'"):
        save_rig(Rig((dotted,)), "projection", tmp_path)
