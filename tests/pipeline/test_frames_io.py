"""Atomic writes and the per-frame file formats (PNG masks, PLY clouds, JSON)."""

from __future__ import annotations

import cv2
import numpy as np
import open3d as o3d
import pytest

from calib.errors import InputError
from pipeline import atomic, frames_io


def test_atomic_output_replaces_only_on_success(tmp_path):
    path = tmp_path / "sub" / "result.txt"
    atomic.write_text(path, "first")
    with pytest.raises(RuntimeError):
        with atomic.atomic_output(path) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed mid-write")
    assert path.read_text() == "first"
    assert [p.name for p in path.parent.iterdir()] == ["result.txt"]  # no temporary file left


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
