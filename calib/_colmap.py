"""COLMAP sparse models (``cameras`` + ``images``, text or binary), read and written with pycolmap.

Camera name = image name stem. COLMAP puts the centre of the top-left pixel at (0.5, 0.5) where
we put it at (0, 0), so ``cx_ours = cx_colmap - 0.5`` (same for cy). COLMAP's OPENCV-family
distortion is OpenCV's, so the lens models below map onto ``(k1, k2, p1, p2, k3)`` exactly.
"""

from __future__ import annotations

import math
import re
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pycolmap

from calib import _parse
from calib.camera import Camera, Rig
from calib.errors import InputError

# COLMAP's pixel-centre convention minus ours (pixels).
PIXEL_CENTRE_SHIFT = 0.5

# Image file extension the writer appends to a camera name, so names containing dots keep their stem.
IMAGE_SUFFIX = ".png"

# Parameter layout of each supported COLMAP model: which entries are fx, fy, cx, cy and which are
# the distortion terms k1, k2, p1, p2, k3 (None = not in the model, zero).
_MODELS = {
    "SIMPLE_PINHOLE": ((0, 0, 1, 2), (None, None, None, None, None)),
    "PINHOLE": ((0, 1, 2, 3), (None, None, None, None, None)),
    "SIMPLE_RADIAL": ((0, 0, 1, 2), (3, None, None, None, None)),
    "RADIAL": ((0, 0, 1, 2), (3, 4, None, None, None)),
    "OPENCV": ((0, 1, 2, 3), (4, 5, 6, 7, None)),
    "FULL_OPENCV": ((0, 1, 2, 3), (4, 5, 6, 7, 8)),
}
# FULL_OPENCV's rational terms k4, k5, k6 (parameters 9..11) must be zero for OpenCV's 5-term model.
_FULL_OPENCV_RATIONAL = slice(9, 12)
# Number of parameters of each supported model in COLMAP's files, as pycolmap counts them.
_PARAMETER_COUNTS = {model: len(pycolmap.Camera.create_from_model_name(1, model, 1.0, 1, 1).params)
                     for model in _MODELS}
# What a line of cameras.txt and the first line of an image in images.txt hold.
_CAMERA_LINE = "CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]"
_IMAGE_LINE = "IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then a line of POINTS2D[] as (X, Y, POINT3D_ID)"


def _intrinsics(model: str, params: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray]:
    """``(K (3,3), dist (5,))`` in our pixel convention from a COLMAP camera model and its parameters."""
    if model not in _MODELS:
        supported = ", ".join(_MODELS)
        raise InputError(f"{where}: camera model {model} is not supported, expected one of {supported}")
    if model == "FULL_OPENCV" and np.any(params[_FULL_OPENCV_RATIONAL] != 0):
        raise InputError(f"{where}: FULL_OPENCV with nonzero k4, k5, k6 is not supported, expected them zero")
    (fx, fy, cx, cy), distortion = _MODELS[model]
    K = np.array(
        [
            [params[fx], 0.0, params[cx] - PIXEL_CENTRE_SHIFT],
            [0.0, params[fy], params[cy] - PIXEL_CENTRE_SHIFT],
            [0.0, 0.0, 1.0],
        ]
    )
    dist = np.array([0.0 if index is None else params[index] for index in distortion])
    return K, dist


def _model_files(path: Path) -> tuple[str, list[str]]:
    """``("bin" | "txt", names of the model files present)``; binary wins when both are complete."""
    for extension in ("bin", "txt"):
        if (path / f"cameras.{extension}").is_file() and (path / f"images.{extension}").is_file():
            present = [
                f"{stem}.{extension}"
                for stem in ("cameras", "images", "points3D", "rigs", "frames")
                if (path / f"{stem}.{extension}").is_file()
            ]
            return extension, present
    raise InputError(f"{path}: no COLMAP model, expected cameras + images .txt (or .bin) files")


def _read_reconstruction(path: Path) -> pycolmap.Reconstruction:
    """pycolmap's model at ``path``; a calibration often comes without ``points3D``, which pycolmap requires,
    so such a model is read from a temporary copy with an empty point list."""
    extension, present = _model_files(path)
    reconstruction = pycolmap.Reconstruction()
    read = reconstruction.read_binary if extension == "bin" else reconstruction.read_text
    try:
        if f"points3D.{extension}" in present:
            read(str(path))
        else:
            with tempfile.TemporaryDirectory() as copy:
                for name in present:
                    shutil.copyfile(path / name, Path(copy) / name)
                empty_points = np.zeros(1, np.uint64).tobytes() if extension == "bin" else b""
                (Path(copy) / f"points3D.{extension}").write_bytes(empty_points)
                read(copy)
    except (ValueError, RuntimeError, IndexError, MemoryError) as error:
        problem = _text_model_problem(path) if extension == "txt" else None
        if problem:
            raise InputError(problem) from None
        raise InputError(f"{path}: not a readable COLMAP {extension} model (pycolmap refused it: "
                         f"{_pycolmap_reason(error)}; expected a model as COLMAP writes it)") from None
    return reconstruction


def _pycolmap_reason(error: Exception) -> str:
    """pycolmap's message without the C++ source location and check expression it starts with."""
    message = str(error).strip().splitlines()[-1] if str(error).strip() else type(error).__name__
    message = re.sub(r"^\[[^\]]*\]\s*", "", message)
    if message.startswith("Check failed:"):
        return "a check of its reader failed"
    return message


def _text_model_problem(path: Path) -> str | None:
    """The first line of ``cameras.txt`` or ``images.txt`` that is not what COLMAP writes, as the
    one-line error naming the file and line, or None when both files look right (pycolmap's reason is
    then all there is)."""
    cameras: set[int] = set()
    for number, words in _data_lines(path / "cameras.txt"):
        where = f"{path / 'cameras.txt'}: line {number}"
        if len(words) < 4 or not _integers(words[0], words[2], words[3]):
            return f"{where}: {' '.join(words)!r}: no whole CAMERA_ID, WIDTH and HEIGHT (expected {_CAMERA_LINE})"
        if words[1] not in _PARAMETER_COUNTS:
            return (f"{where}: camera model {words[1]!r} is not supported "
                    f"(expected one of {', '.join(_PARAMETER_COUNTS)})")
        count = _PARAMETER_COUNTS[words[1]]
        if len(words) - 4 != count or not _floats(*words[4:]):
            return f"{where}: {words[1]} takes {count} numeric parameters, got {words[4:]} (expected {_CAMERA_LINE})"
        cameras.add(int(words[0]))
    lines = iter(_raw_lines(path / "images.txt"))
    for number, line in lines:
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        where = f"{path / 'images.txt'}: line {number}"
        if len(words) < 10 or not (_integers(words[0], words[8]) and _floats(*words[1:8])):
            return f"{where}: {line.strip()!r}: not ten fields with a numeric pose (expected {_IMAGE_LINE})"
        if int(words[8]) not in cameras:
            return f"{where}: camera {words[8]} is not in cameras.txt (expected one of {sorted(cameras)})"
        points = next(lines, (number + 1, ""))
        values = points[1].split()
        if len(values) % 3 or not _floats(*values):
            return f"{path / 'images.txt'}: line {points[0]}: not (X, Y, POINT3D_ID) triples (expected {_IMAGE_LINE})"
    return None


def _raw_lines(path: Path) -> list[tuple[int, str]]:
    """``(line number, text)`` of every line of ``path`` (none when it cannot be read as text)."""
    try:
        return list(enumerate(path.read_text(encoding="utf-8").splitlines(), start=1))
    except (OSError, UnicodeDecodeError):
        return []


def _data_lines(path: Path) -> list[tuple[int, list[str]]]:
    """``(line number, words)`` of the lines of ``path`` that are neither empty nor comments."""
    return [(number, line.split()) for number, line in _raw_lines(path)
            if line.split() and not line.lstrip().startswith("#")]


def _integers(*words: str) -> bool:
    return all(re.fullmatch(r"[+-]?\d+", word) for word in words)


def _floats(*words: str) -> bool:
    try:
        return all(math.isfinite(float(word)) for word in words)
    except ValueError:
        return False


def load(path: Path) -> Rig:
    """The rig in the COLMAP model directory ``path``, cameras in image-id order."""
    if not path.is_dir():
        raise InputError(f"{path}: no such directory, expected a COLMAP model directory")
    reconstruction = _read_reconstruction(path)
    cameras = []
    for image_id in sorted(reconstruction.images):
        image = reconstruction.images[image_id]
        where = f"{path} image {image.name!r}"
        if not image.has_pose:
            raise InputError(f"{where}: has no pose (not registered), expected every camera posed")
        colmap_camera = reconstruction.cameras[image.camera_id]
        K, dist = _intrinsics(colmap_camera.model_name, np.asarray(colmap_camera.params, np.float64), where)
        cam_from_world = image.cam_from_world()
        cameras.append(
            _parse.camera(
                where,
                name=Path(image.name).stem,
                K=K,
                dist=dist,
                R=cam_from_world.rotation.matrix(),
                t=np.asarray(cam_from_world.translation).reshape(3),
                size=(int(colmap_camera.width), int(colmap_camera.height)),
            )
        )
    if not cameras:
        raise InputError(f"{path}: the COLMAP model has no images, expected one image per camera")
    return _parse.rig(str(path), cameras)


def _colmap_camera(camera: Camera, camera_id: int) -> pycolmap.Camera:
    """The smallest COLMAP model holding ``camera``'s lens: PINHOLE, OPENCV, or FULL_OPENCV when k3 != 0.

    COLMAP's models have no skew, so a skewed camera is refused rather than written as another camera.
    """
    if camera.K[0, 1] != 0:
        raise InputError(f"camera {camera.name!r}: skew K[0, 1] = {camera.K[0, 1]:g} px has no COLMAP camera "
                         "model, expected K[0, 1] = 0 (write it as opencv, anipose or projection instead)")
    fx, fy = camera.K[0, 0], camera.K[1, 1]
    cx, cy = camera.K[:2, 2] + PIXEL_CENTRE_SHIFT
    k1, k2, p1, p2, k3 = camera.dist
    if not np.any(camera.dist):
        model, params = "PINHOLE", [fx, fy, cx, cy]
    elif k3 == 0:
        model, params = "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
    else:
        model, params = "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]
    width, height = camera.size
    return pycolmap.Camera(model=model, width=width, height=height, params=params, camera_id=camera_id)


def save(rig: Rig, path: Path, *, binary: bool = False) -> None:
    """Write ``rig`` as a COLMAP model (text, or binary) into the directory ``path``; ids follow rig order."""
    reconstruction = pycolmap.Reconstruction()
    for index, camera in enumerate(rig, start=1):
        reconstruction.add_camera_with_trivial_rig(_colmap_camera(camera, index))
        image = pycolmap.Image(name=f"{camera.name}{IMAGE_SUFFIX}", camera_id=index, image_id=index)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(camera.R), camera.t)
        reconstruction.add_image_with_trivial_frame(image, pose)
    path.mkdir(parents=True, exist_ok=True)
    if binary:
        reconstruction.write_binary(str(path))
    else:
        reconstruction.write_text(str(path))
