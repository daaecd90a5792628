import re
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
import tomli_w
import tomllib
from calib_testing import ring_rig, subject_points

from calib.camera import Camera, Rig
from calib.errors import InputError
from calib.formats import FORMATS, load_rig, save_rig

# COLMAP's pixel (0.5, 0.5) is the centre of the top-left pixel, ours is (0, 0).
COLMAP_PIXEL_OFFSET = 0.5


def assert_same_rig(loaded: Rig, expected: Rig) -> None:
    """Same names in the same order, same sizes, same parameters, same pixels to 1e-6 px."""
    assert loaded.names == expected.names
    for got, want in zip(loaded, expected, strict=True):
        assert got.size == want.size, got.name
        np.testing.assert_allclose(got.K, want.K, rtol=1e-12, atol=1e-9, err_msg=got.name)
        np.testing.assert_allclose(got.dist, want.dist, rtol=0, atol=1e-12, err_msg=got.name)
        np.testing.assert_allclose(got.R, want.R, rtol=0, atol=1e-9, err_msg=got.name)
        np.testing.assert_allclose(got.t, want.t, rtol=0, atol=1e-9, err_msg=got.name)
    X = subject_points(100)
    np.testing.assert_allclose(loaded.project(X), expected.project(X), rtol=0, atol=1e-6)


def write_opencv(directory: Path, cameras: list[Camera], *, rodrigues=True, rotation=True, sizes=True,
                 dist_shape=(1, 5), skip: str = "") -> None:
    """intri.yml / extri.yml written with cv2.FileStorage the way EasyMocap does, with variations."""
    directory.mkdir(parents=True, exist_ok=True)
    intri = cv2.FileStorage(str(directory / "intri.yml"), cv2.FILE_STORAGE_WRITE)
    extri = cv2.FileStorage(str(directory / "extri.yml"), cv2.FILE_STORAGE_WRITE)
    for storage in (intri, extri):
        storage.startWriteStruct("names", cv2.FileNode_SEQ)
        for camera in cameras:
            storage.write("", camera.name)
        storage.endWriteStruct()
    for camera in cameras:
        n = camera.name
        values = {
            (intri, f"K_{n}"): camera.K,
            (intri, f"dist_{n}"): camera.dist[: int(np.prod(dist_shape))].reshape(dist_shape),
            (extri, f"T_{n}"): camera.t.reshape(3, 1),
        }
        if sizes:
            values[(intri, f"W_{n}")] = camera.size[0]
            values[(intri, f"H_{n}")] = camera.size[1]
        if rodrigues:
            values[(extri, f"R_{n}")] = cv2.Rodrigues(camera.R)[0]
        if rotation:
            values[(extri, f"Rot_{n}")] = camera.R
        for (storage, key), value in values.items():
            if key != skip:
                storage.write(key, value)
    intri.release()
    extri.release()


def colmap_reconstruction(models: list[tuple[str, list[float]]], size=(640, 480)) -> pycolmap.Reconstruction:
    """A COLMAP model built with pycolmap's own API: one camera and one image per entry."""
    reconstruction = pycolmap.Reconstruction()
    rng = np.random.default_rng(7)
    for index, (model, params) in enumerate(models, start=1):
        camera = pycolmap.Camera.create_from_model_name(index, model, 1.0, *size)
        camera.params = params
        reconstruction.add_camera_with_trivial_rig(camera)
        quaternion_xyzw = rng.normal(size=4) * [0.2, 0.2, 0.2, 1.0]
        rotation = pycolmap.Rotation3d(quaternion_xyzw / np.linalg.norm(quaternion_xyzw))
        image = pycolmap.Image(name=f"view_{index}.jpg", camera_id=index, image_id=index)
        reconstruction.add_image_with_trivial_frame(image, pycolmap.Rigid3d(rotation, [0.1, -0.1, 4.0]))
    return reconstruction


def colmap_pixels(reconstruction: pycolmap.Reconstruction, X: np.ndarray) -> dict[str, np.ndarray]:
    """Pixels of ``X (N, 3)`` as COLMAP projects them, per image name stem."""
    pixels = {}
    for image in reconstruction.images.values():
        camera = reconstruction.camera(image.camera_id)
        cam_from_world = image.cam_from_world()
        pixels[Path(image.name).stem] = np.array([camera.img_from_cam(cam_from_world * x) for x in X])
    return pixels


def edit_toml(path: Path, edit) -> None:
    """Rewrite the TOML file at ``path`` with ``edit(document)`` applied to its parsed tables."""
    document = tomllib.loads(path.read_text())
    edit(document)
    path.write_text(tomli_w.dumps(document))


def colmap_models(directory: Path) -> dict[str, str]:
    """COLMAP camera model name per image name stem."""
    reconstruction = pycolmap.Reconstruction(str(directory))
    return {
        Path(image.name).stem: reconstruction.camera(image.camera_id).model.name
        for image in reconstruction.images.values()
    }


def undistorted(rig: Rig) -> Rig:
    """``rig`` without lens distortion, as projection matrices hold it."""
    return Rig(tuple(Camera(camera.name, camera.K, np.zeros(5), camera.R, camera.t, camera.size) for camera in rig))


def sizes_of(rig: Rig) -> dict[str, tuple[int, int]]:
    return {camera.name: camera.size for camera in rig}


@pytest.mark.parametrize("fmt", FORMATS)
def test_round_trip_twelve_cameras(rig12, tmp_path, fmt):
    rig = undistorted(rig12) if fmt == "projection" else rig12
    save_rig(rig, fmt, tmp_path / fmt)
    assert_same_rig(load_rig(fmt, tmp_path / fmt, image_sizes=sizes_of(rig)), rig)


def skewed(rig: Rig, skew_px: float = 0.8) -> Rig:
    """``rig`` with skew ``K[0, 1]`` alternating in sign from camera to camera."""
    cameras = []
    for index, camera in enumerate(rig):
        K = camera.K.copy()
        K[0, 1] = skew_px * (-1) ** index
        cameras.append(Camera(camera.name, K, camera.dist, camera.R, camera.t, camera.size))
    return Rig(tuple(cameras))


@pytest.mark.parametrize("fmt", ["opencv", "anipose", "projection"])
def test_skewed_intrinsics_round_trip(rig12, tmp_path, fmt):
    rig = skewed(undistorted(rig12) if fmt == "projection" else rig12)
    save_rig(rig, fmt, tmp_path / fmt)
    assert_same_rig(load_rig(fmt, tmp_path / fmt, image_sizes=sizes_of(rig)), rig)


def test_colmap_writer_refuses_skew(rig12, tmp_path):
    with pytest.raises(InputError, match="cam_0.*skew K\\[0, 1\\] = 0.8 px has no COLMAP camera model"):
        save_rig(skewed(rig12), "colmap", tmp_path)


def test_colmap_binary_model_loads_like_text(rig12, tmp_path):
    save_rig(rig12, "colmap", tmp_path / "text")
    (tmp_path / "binary").mkdir()
    pycolmap.Reconstruction(str(tmp_path / "text")).write_binary(str(tmp_path / "binary"))
    assert not list((tmp_path / "binary").glob("*.txt"))
    assert_same_rig(load_rig("colmap", tmp_path / "binary"), rig12)


def test_cross_format_equivalence(rig12, tmp_path):
    X = subject_points(300)
    rig = undistorted(rig12)
    expected = rig.project(X)
    for fmt in FORMATS:
        save_rig(rig, fmt, tmp_path / fmt)
        loaded = load_rig(fmt, tmp_path / fmt, image_sizes=sizes_of(rig))
        np.testing.assert_allclose(loaded.project(X), expected, rtol=0, atol=1e-6)


def test_colmap_writer_picks_the_simplest_model_that_holds_the_distortion(tmp_path):
    rig = ring_rig(3)
    pinhole, opencv, full = (
        Camera(c.name, c.K, dist, c.R, c.t, c.size)
        for c, dist in zip(rig, [np.zeros(5), [-0.2, 0.05, 1e-3, 0.0, 0.0], [-0.2, 0.05, 0.0, 0.0, 0.01]],
                           strict=True)
    )
    save_rig(Rig((pinhole, opencv, full)), "colmap", tmp_path)
    expected = {pinhole.name: "PINHOLE", opencv.name: "OPENCV", full.name: "FULL_OPENCV"}
    assert colmap_models(tmp_path) == expected


@pytest.mark.parametrize(
    ("model", "params"),
    [
        ("SIMPLE_PINHOLE", [800.0, 320.5, 240.5]),
        ("PINHOLE", [800.0, 790.0, 315.2, 250.7]),
        ("SIMPLE_RADIAL", [800.0, 320.5, 240.5, -0.15]),
        ("RADIAL", [800.0, 320.5, 240.5, -0.2, 0.05]),
        ("OPENCV", [800.0, 810.0, 322.0, 238.0, -0.2, 0.05, 1e-3, -2e-3]),
        ("FULL_OPENCV", [800.0, 810.0, 322.0, 238.0, -0.2, 0.05, 1e-3, -2e-3, 0.01, 0.0, 0.0, 0.0]),
    ],
)
@pytest.mark.parametrize("binary", [False, True])
def test_colmap_reader_projects_like_pycolmap(tmp_path, model, params, binary):
    reconstruction = colmap_reconstruction([(model, params), ("PINHOLE", [700.0, 700.0, 320.0, 240.0])])
    (reconstruction.write_binary if binary else reconstruction.write_text)(str(tmp_path))
    rig = load_rig("colmap", tmp_path)
    assert rig.names == ("view_1", "view_2")
    X = subject_points(50) * [0.3, 0.3, 0.5]
    for name, expected in colmap_pixels(reconstruction, X).items():
        np.testing.assert_allclose(rig[name].project(X), expected - COLMAP_PIXEL_OFFSET, rtol=0, atol=1e-6)
        assert rig[name].size == (640, 480)


def test_colmap_writer_output_projects_like_pycolmap(rig12, tmp_path):
    save_rig(rig12, "colmap", tmp_path)
    X = subject_points(50)
    pixels = colmap_pixels(pycolmap.Reconstruction(str(tmp_path)), X)
    assert set(pixels) == set(rig12.names)
    for camera in rig12:
        np.testing.assert_allclose(pixels[camera.name] - COLMAP_PIXEL_OFFSET, camera.project(X), atol=1e-6)


def test_colmap_unsupported_model_is_named(tmp_path):
    colmap_reconstruction([("OPENCV_FISHEYE", [800.0, 800.0, 320.0, 240.0, 0.1, 0.0, 0.0, 0.0])]).write_text(
        str(tmp_path)
    )
    with pytest.raises(InputError, match="OPENCV_FISHEYE"):
        load_rig("colmap", tmp_path)


def test_colmap_full_opencv_with_rational_terms_is_rejected(tmp_path):
    params = [800.0, 810.0, 322.0, 238.0, -0.2, 0.05, 0.0, 0.0, 0.0, 0.1, 0.0, 0.0]
    colmap_reconstruction([("FULL_OPENCV", params)]).write_text(str(tmp_path))
    with pytest.raises(InputError, match="FULL_OPENCV"):
        load_rig("colmap", tmp_path)


def test_opencv_accepts_the_intri_file_as_path(rig12, tmp_path):
    save_rig(rig12, "opencv", tmp_path)
    assert_same_rig(load_rig("opencv", tmp_path / "intri.yml"), rig12)


@pytest.mark.parametrize(
    ("rodrigues", "rotation", "dist_shape"),
    [(True, False, (1, 5)), (False, True, (5, 1)), (True, True, (1, 4))],
    ids=["rodrigues-only", "matrix-only", "both-four-coefficients"],
)
def test_opencv_easymocap_variants(tmp_path, rodrigues, rotation, dist_shape):
    rig = ring_rig(12, with_k3=np.prod(dist_shape) == 5)
    write_opencv(tmp_path, list(rig), rodrigues=rodrigues, rotation=rotation, dist_shape=dist_shape)
    assert_same_rig(load_rig("opencv", tmp_path), rig)


def test_opencv_sizes_come_from_the_caller_when_the_file_has_none(rig12, tmp_path):
    write_opencv(tmp_path, list(rig12), sizes=False)
    with pytest.raises(InputError, match="cam_0"):
        load_rig("opencv", tmp_path)
    sizes = {camera.name: camera.size for camera in rig12}
    assert_same_rig(load_rig("opencv", tmp_path, image_sizes=sizes), rig12)


def test_opencv_disagreeing_rotations_are_an_error(tmp_path):
    camera = ring_rig(1)[0]
    turn = cv2.Rodrigues(np.array([0.0, 0.0, 0.1]))[0]
    turned = Camera(camera.name, camera.K, camera.dist, turn @ camera.R, camera.t, camera.size)
    write_opencv(tmp_path, [camera], rotation=False)
    rodrigues_only = (tmp_path / "extri.yml").read_text()
    write_opencv(tmp_path, [turned], rodrigues=False)
    matrix_only = (tmp_path / "extri.yml").read_text()
    rodrigues_entry = rodrigues_only[rodrigues_only.index("R_cam_0"):]
    (tmp_path / "extri.yml").write_text(matrix_only + rodrigues_entry)
    with pytest.raises(InputError, match="extri.yml.*cam_0"):
        load_rig("opencv", tmp_path)


def test_anipose_orders_tables_numerically_and_ignores_metadata(tmp_path):
    rig = ring_rig(12)
    save_rig(rig, "anipose", tmp_path)
    text = (tmp_path / "calibration.toml").read_text()
    tables = re.split(r"(?m)^(?=\[)", text)
    shuffled = "[metadata]\nadjusted = true\nerror = 0.5\n\n" + "".join(sorted(tables))  # cam_10 before cam_2
    assert shuffled.index("[cam_10]") < shuffled.index("[cam_2]")
    (tmp_path / "calibration.toml").write_text(shuffled)
    assert_same_rig(load_rig("anipose", tmp_path / "calibration.toml"), rig)


@pytest.mark.parametrize("n_coefficients", [1, 4])
def test_anipose_short_distortion_vectors_are_padded(tmp_path, n_coefficients):
    camera = ring_rig(1)[0]
    save_rig(Rig((camera,)), "anipose", tmp_path)
    edit_toml(tmp_path / "calibration.toml",
              lambda document: document["cam_0"].update(distortions=camera.dist[:n_coefficients].tolist()))
    expected = np.concatenate([camera.dist[:n_coefficients], np.zeros(5 - n_coefficients)])
    np.testing.assert_array_equal(load_rig("anipose", tmp_path)[0].dist, expected)


# --- bad input: every mistake is an InputError naming the file (or argument) and what is wrong ---


def test_unknown_format_lists_the_known_ones(rig12, tmp_path):
    with pytest.raises(InputError, match="colmap, opencv, anipose"):
        load_rig("bundler", tmp_path)
    with pytest.raises(InputError, match="bundler"):
        save_rig(rig12, "bundler", tmp_path)


@pytest.mark.parametrize("fmt", FORMATS)
def test_missing_calibration_names_the_path(tmp_path, fmt):
    missing = tmp_path / "nowhere"
    with pytest.raises(InputError, match="nowhere"):
        load_rig(fmt, missing)


def test_malformed_yaml_names_the_file(rig12, tmp_path):
    save_rig(rig12, "opencv", tmp_path)
    (tmp_path / "intri.yml").write_text("%YAML:1.0\n---\nnames: [cam_0\nK_cam_0: {{{\n")
    with pytest.raises(InputError, match="intri.yml"):
        load_rig("opencv", tmp_path)


def test_missing_opencv_key_is_named(rig12, tmp_path):
    write_opencv(tmp_path, list(rig12), skip="K_cam_7")
    with pytest.raises(InputError, match="intri.yml.*K_cam_7"):
        load_rig("opencv", tmp_path)


def test_missing_extri_file_is_named(rig12, tmp_path):
    save_rig(rig12, "opencv", tmp_path)
    (tmp_path / "extri.yml").unlink()
    with pytest.raises(InputError, match="extri.yml"):
        load_rig("opencv", tmp_path)


def test_non_rotation_in_opencv_file_names_the_file(tmp_path):
    camera = ring_rig(1)[0]
    write_opencv(tmp_path, [Camera(camera.name, camera.K, camera.dist, np.eye(3), camera.t, camera.size)],
                 rodrigues=False)
    identity = "data: [ 1., 0., 0., 0., 1., 0., 0., 0., 1. ]"
    extri = (tmp_path / "extri.yml").read_text()
    assert identity in extri
    reflection = "data: [ 1., 0., 0., 0., 1., 0., 0., 0., -1. ]"
    (tmp_path / "extri.yml").write_text(extri.replace(identity, reflection))
    with pytest.raises(InputError, match="extri.yml.*not a rotation"):
        load_rig("opencv", tmp_path)


def test_malformed_toml_names_the_file(tmp_path):
    (tmp_path / "calibration.toml").write_text("[cam_0]\nname = 'a'\nsize = [640, 480\n")
    with pytest.raises(InputError, match="calibration.toml"):
        load_rig("anipose", tmp_path)


def test_missing_anipose_key_is_named(rig12, tmp_path):
    save_rig(rig12, "anipose", tmp_path)
    edit_toml(tmp_path / "calibration.toml", lambda document: document["cam_5"].pop("translation"))
    with pytest.raises(InputError, match=r"calibration.toml.*cam_5.*translation"):
        load_rig("anipose", tmp_path)


def test_duplicate_camera_names_in_a_file_are_an_error(tmp_path):
    camera = ring_rig(1)[0]
    save_rig(Rig((camera,)), "anipose", tmp_path)
    text = (tmp_path / "calibration.toml").read_text()
    (tmp_path / "calibration.toml").write_text(text + "\n" + text.replace("[cam_0]", "[cam_1]"))
    with pytest.raises(InputError, match="duplicate camera names cam_0"):
        load_rig("anipose", tmp_path)


def test_colmap_directory_without_a_model_is_named(tmp_path):
    (tmp_path / "cameras.txt").write_text("# nothing else here\n")
    with pytest.raises(InputError, match=str(tmp_path.name)):
        load_rig("colmap", tmp_path)
