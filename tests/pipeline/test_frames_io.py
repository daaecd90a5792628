"""Atomic writes and the per-frame file formats (PNG masks, PLY clouds, JSON)."""

from __future__ import annotations

import errno
import json
import os
import pickle
import zlib

import cv2
import numpy as np
import open3d as o3d
import pytest

from calib.errors import InputError
from pipeline.io import atomic, frames_io


def test_atomic_output_replaces_only_on_success(tmp_path):
    path = tmp_path / "sub" / "result.txt"
    atomic.write_text(path, "first")
    with pytest.raises(RuntimeError):
        with atomic.atomic_output(path) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed mid-write")
    assert path.read_text() == "first"
    assert [p.name for p in path.parent.iterdir()] == ["result.txt"]  # no temporary file left


def test_write_bytes_makes_its_folder_and_leaves_nothing_behind_a_failed_write(tmp_path, monkeypatch):
    path = tmp_path / "new" / "folder" / "000001.png"
    atomic.write_bytes(path, b"first")
    assert path.read_bytes() == b"first"

    def full_disk(descriptor, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "write", full_disk)
    with pytest.raises(OSError, match="No space left") as raised:
        atomic.write_bytes(path, b"second")
    assert raised.value.errno == errno.ENOSPC and raised.value.filename == str(path)  # names the file
    assert path.read_bytes() == b"first"
    assert [p.name for p in path.parent.iterdir()] == ["000001.png"]  # no temporary file left


def test_temporary_names_differ_and_keep_the_suffix(tmp_path):
    names = {atomic.temp_path_for(tmp_path / "000001.ply").name for _ in range(1000)}
    assert len(names) == 1000
    assert all(name.startswith(atomic.TEMP_PREFIX) and name.endswith("-000001.ply") for name in names)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")
def test_a_forked_child_draws_its_own_temporary_names(tmp_path):
    """A forked batch worker draws a tag of its own: where pids repeat (containers sharing a folder), the
    tag is what keeps two writers' temporary names apart."""
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: report its tag and exit at once
        os.write(write_end, atomic.temp_path_for(tmp_path / "a.png").name.encode())
        os._exit(0)
    os.close(write_end)
    child_name = os.read(read_end, 1000).decode()
    os.close(read_end)
    os.waitpid(pid, 0)
    parent_name = atomic.temp_path_for(tmp_path / "a.png").name
    assert child_name.split("-")[2] != parent_name.split("-")[2]


def test_remove_temp_files(tmp_path):
    (tmp_path / "a").mkdir()
    leftover = atomic.temp_path_for(tmp_path / "a" / "000001.png")
    leftover.write_bytes(b"partial")
    (tmp_path / "a" / "000000.png").write_bytes(b"done")
    assert atomic.remove_temp_files(tmp_path) == 1
    assert [p.name for p in (tmp_path / "a").iterdir()] == ["000000.png"]


def test_mask_round_trip(tmp_path):
    mask = np.zeros((5, 7), np.uint8)
    mask[1:3, 2:6] = 1  # any nonzero value is "person"
    frames_io.write_mask(tmp_path / "m.png", mask)
    np.testing.assert_array_equal(frames_io.read_mask(tmp_path / "m.png"), np.where(mask > 0, 255, 0))


def test_masks_are_one_bit_pngs_as_opencv_writes_them(tmp_path):
    mask = np.zeros((580, 780), np.uint8)
    cv2.ellipse(mask, (390, 290), (80, 220), 0, 0, 360, 255, -1)
    frames_io.write_mask(tmp_path / "m.png", mask)
    data = (tmp_path / "m.png").read_bytes()
    flags = [cv2.IMWRITE_PNG_BILEVEL, 1, cv2.IMWRITE_PNG_COMPRESSION, 1,
             cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]
    assert len(data) <= len(cv2.imencode(".png", mask, flags)[1])  # the same bytes with the pinned zlib
    assert data[24] == 1  # IHDR bit depth
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "m.png"), cv2.IMREAD_UNCHANGED), mask)


def test_masks_from_other_writers_are_read_by_opencv_and_thresholded(tmp_path):
    mask = np.zeros((40, 60), np.uint8)
    mask[10:30, 15:45] = 200  # anti-aliased or scaled: above the threshold is person
    mask[10:30, 15] = 100
    for name, flags in (("grey.png", []), ("one_bit.png", [cv2.IMWRITE_PNG_BILEVEL, 1]), ("m.jpg", [])):
        source = np.where(mask > 127, 255, 0).astype(np.uint8) if name == "one_bit.png" else mask
        cv2.imwrite(str(tmp_path / name), source, flags)
        np.testing.assert_array_equal(frames_io.read_mask(tmp_path / name), np.where(mask > 127, 255, 0))


def test_two_level_masks_mark_the_person_with_their_brighter_level_however_dim(tmp_path):
    mask = np.zeros((40, 60), np.uint8)
    mask[10:30, 15:45] = 1
    cv2.imwrite(str(tmp_path / "ones.png"), mask)  # a boolean array saved as it is
    np.testing.assert_array_equal(frames_io.read_mask(tmp_path / "ones.png"), np.where(mask > 0, 255, 0))
    cv2.imwrite(str(tmp_path / "dark.png"), mask * 38)  # a palette's dark red, as OpenCV reads it in grey
    np.testing.assert_array_equal(frames_io.read_mask(tmp_path / "dark.png"), np.where(mask > 0, 255, 0))
    noise = np.zeros((40, 60), np.uint8)
    noise[5, 5], noise[20, 30], noise[30, 50] = 1, 2, 3  # an empty mask's JPEG noise: several dim levels
    cv2.imwrite(str(tmp_path / "noise.png"), noise)
    assert not frames_io.read_mask(tmp_path / "noise.png").any()


def test_ply_round_trip_and_open3d_reads_it(tmp_path):
    rng = np.random.default_rng(0)
    points = rng.normal(size=(50, 3))
    normals = rng.normal(size=(50, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    frames_io.write_ply(tmp_path / "c.ply", points, normals)
    read_points, read_normals = frames_io.read_ply(tmp_path / "c.ply")
    np.testing.assert_array_equal(read_points, points)
    np.testing.assert_array_equal(read_normals, normals)
    cloud = o3d.io.read_point_cloud(str(tmp_path / "c.ply"))
    np.testing.assert_allclose(np.asarray(cloud.points), points)
    np.testing.assert_allclose(np.asarray(cloud.normals), normals)


def test_empty_ply_round_trip(tmp_path):
    frames_io.write_ply(tmp_path / "empty.ply", np.empty((0, 3)), np.empty((0, 3)))
    points, normals = frames_io.read_ply(tmp_path / "empty.ply")
    assert points.shape == (0, 3) and normals.shape == (0, 3)


def test_truncated_ply_is_an_input_error(tmp_path):
    frames_io.write_ply(tmp_path / "c.ply", np.ones((4, 3)), np.ones((4, 3)))
    data = (tmp_path / "c.ply").read_bytes()
    (tmp_path / "c.ply").write_bytes(data[:-10])
    with pytest.raises(InputError, match="c.ply: PLY file is truncated"):
        frames_io.read_ply(tmp_path / "c.ply")


def test_json_round_trip_with_numpy_values(tmp_path):
    frames_io.write_json(tmp_path / "r.json", {"pose": np.arange(3.0), "iterations": np.int64(7)})
    assert frames_io.read_json(tmp_path / "r.json") == {"pose": [0.0, 1.0, 2.0], "iterations": 7}
    with pytest.raises(ValueError):
        frames_io.write_json(tmp_path / "nan.json", {"x": float("nan")})
    assert not (tmp_path / "nan.json").exists()


# ---------------------------------------------------------------------------------------------
# Content checks: a damaged or implausible file is noticed, not used


def flip_byte(path, offset: int) -> None:
    """Change one byte of ``path`` in place (same size: no size check can see it)."""
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x10
    path.write_bytes(bytes(data))


def unit_cloud(n: int = 20) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(1)
    normals = rng.normal(size=(n, 3))
    return rng.normal(size=(n, 3)), normals / np.linalg.norm(normals, axis=1, keepdims=True)


def plain_ply(points: np.ndarray, normals: np.ndarray) -> bytes:
    """A PLY file as other writers make it: no content check in the header."""
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(points)}",
              *(f"property float {name}" for name in ("x", "y", "z", "nx", "ny", "nz")), "end_header", ""]
    return "\n".join(header).encode() + np.hstack([points, normals]).astype("<f4").tobytes()


def test_a_flipped_byte_in_a_ply_is_noticed(tmp_path):
    path = tmp_path / "c.ply"
    frames_io.write_ply(path, *unit_cloud())
    assert frames_io.file_problem(path) is None
    flip_byte(path, -30)  # inside a coordinate: still a finite number, the cloud looks fine
    assert frames_io.file_problem(path) == "PLY vertex data fails its crc32 check"
    with pytest.raises(frames_io.DamagedFileError, match="c.ply: PLY vertex data fails its crc32 check"):
        frames_io.read_ply(path)


def test_plys_without_a_check_are_read_when_plausible(tmp_path):
    points, normals = unit_cloud()
    (tmp_path / "c.ply").write_bytes(plain_ply(points, normals))
    read_points, read_normals = frames_io.read_ply(tmp_path / "c.ply")
    np.testing.assert_allclose(read_normals, normals, atol=1e-6)
    points[3, 1] = np.nan
    (tmp_path / "nan.ply").write_bytes(plain_ply(points, normals))
    with pytest.raises(frames_io.DamagedFileError, match="nan.ply: PLY holds a coordinate that is not a finite"):
        frames_io.read_ply(tmp_path / "nan.ply")
    points[3, 1], normals[5] = 0.0, [3.0, 0.0, 0.0]
    (tmp_path / "long.ply").write_bytes(plain_ply(points, normals))
    with pytest.raises(frames_io.DamagedFileError, match="long.ply: PLY normal 5 has length 3, not 1"):
        frames_io.read_ply(tmp_path / "long.ply")


def test_a_damaged_mask_is_noticed(tmp_path):
    mask = np.zeros((48, 64), np.uint8)
    mask[10:30, 20:40] = 255
    path = tmp_path / "m.png"
    frames_io.write_mask(path, mask)
    good = path.read_bytes()
    assert frames_io.file_problem(path) is None
    flip_byte(path, len(good) - 20)  # in the pixel data (IDAT)
    assert frames_io.file_problem(path) == "PNG chunk IDAT fails its CRC check"
    with pytest.raises(frames_io.DamagedFileError, match="m.png: PNG chunk IDAT fails its CRC check"):
        frames_io.read_mask(path)
    path.write_bytes(good[:-6])
    with pytest.raises(frames_io.DamagedFileError, match="PNG file is truncated"):
        frames_io.read_mask(path)


def test_an_empty_or_unreadable_mask_file_is_one_line_not_an_opencv_error(tmp_path):
    path = tmp_path / "m.png"
    path.write_bytes(b"")
    with pytest.raises(InputError, match="m.png: empty file"):
        frames_io.read_mask(path)
    path.write_bytes(b"not an image")
    with pytest.raises(InputError, match="m.png: not a readable mask image"):
        frames_io.read_mask(path)


def test_a_mask_of_the_wrong_size_is_refused(tmp_path):
    frames_io.write_mask(tmp_path / "m.png", np.zeros((48, 64), np.uint8))
    assert frames_io.read_mask(tmp_path / "m.png", (64, 48)).shape == (48, 64)
    with pytest.raises(frames_io.DamagedFileError, match="mask is 64x48 pixels, not the camera's 80x60"):
        frames_io.read_mask(tmp_path / "m.png", (80, 60))


def test_a_changed_value_in_a_json_record_is_noticed(tmp_path):
    path = tmp_path / "r.json"
    record = {"frame": 3, "result": {"log_likelihood": -1234.5678, "joints": [[0.1, 0.2, 0.3]]}}
    frames_io.write_record(path, record)
    assert frames_io.read_record(path) == record and frames_io.file_problem(path) is None
    path.write_text(path.read_text().replace("-1234.5678", "-1234.5679"))  # same size, still valid JSON
    assert frames_io.file_problem(path) == "JSON record fails its crc32 check"
    with pytest.raises(frames_io.DamagedFileError, match="r.json: JSON record fails its crc32 check"):
        frames_io.read_record(path)
    path.write_text(path.read_text()[:-8])
    assert frames_io.file_problem(path).startswith("not valid JSON")


@pytest.mark.parametrize("record", [
    {"frame": 3, "result": {"crc32": [1.5, np.float64(2.25)], "frame": np.arange(3)}},  # the check sorts first
    {"a": "x\ny", "b": {"a": 1}, "d": [{"crc32": "no"}]},  # in the middle, and a nested key of the same name
    {"a": 1, "b": [0.1, 0.2]},  # last
    {},
    {"é": 1, "z\"": None},  # keys the encoder escapes
])
def test_a_record_is_the_json_of_the_record_and_its_check(tmp_path, record):
    path = tmp_path / "r.json"
    frames_io.write_record(path, record)
    check = f"{zlib.crc32(frames_io.to_json(record).encode('utf-8')):08x}"
    assert path.read_text(encoding="utf-8") == frames_io.to_json({**record, "crc32": check})
    assert frames_io.file_problem(path) is None
    assert frames_io.to_json(frames_io.read_record(path)) == frames_io.to_json(record)


def test_a_reformatted_record_with_the_same_values_passes_its_check(tmp_path):
    path = tmp_path / "r.json"
    frames_io.write_record(path, {"frame": 3, "joints": [[0.1, 0.2, 0.3]]})
    path.write_text(json.dumps(json.loads(path.read_text()), indent=4))
    assert frames_io.file_problem(path) is None
    assert frames_io.read_record(path) == {"frame": 3, "joints": [[0.1, 0.2, 0.3]]}


def test_plain_json_has_no_check_to_fail(tmp_path):
    frames_io.write_json(tmp_path / "plain.json", {"a": 1})
    assert frames_io.file_problem(tmp_path / "plain.json") is None
    with pytest.raises(frames_io.DamagedFileError, match="not a JSON record with a crc32 content check"):
        frames_io.read_record(tmp_path / "plain.json")


def test_a_damaged_file_error_comes_back_whole_from_a_worker_process():
    error = pickle.loads(pickle.dumps(frames_io.DamagedFileError("out/reconstruction/000001.ply", "truncated")))
    assert isinstance(error, InputError) and str(error).startswith("out/reconstruction/000001.ply: truncated")
    assert error.path.name == "000001.ply" and error.problem == "truncated"


def test_the_png_check_is_the_formats_own_crc(tmp_path):
    """A PNG from any writer passes: the check is the chunk CRC every PNG carries."""
    cv2.imwrite(str(tmp_path / "photo.png"), np.full((8, 8, 3), 7, np.uint8))
    assert frames_io.png_problem((tmp_path / "photo.png").read_bytes()) is None


def test_an_images_size_is_read_from_a_png_header_and_checked_like_a_decoded_image(tmp_path):
    cv2.imwrite(str(tmp_path / "plate.png"), np.full((6, 9, 3), 7, np.uint8))
    cv2.imwrite(str(tmp_path / "plate.jpg"), np.full((6, 9, 3), 7, np.uint8))
    assert frames_io.image_size(tmp_path / "plate.png") == frames_io.image_size(tmp_path / "plate.jpg") == (9, 6)
    data = (tmp_path / "plate.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[:-20])
    with pytest.raises(InputError, match=r"cut.png: not a readable image \(PNG file is truncated"):
        frames_io.image_size(tmp_path / "cut.png")
    (tmp_path / "text.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match="text.png: not a readable image"):
        frames_io.image_size(tmp_path / "text.png")
