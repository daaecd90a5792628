"""OpenCV FileStorage ``intri.yml`` + ``extri.yml`` (the EasyMocap / ZJU-MoCap layout).

``intri.yml``: ``names`` (list of camera names), ``K_<name>`` (3x3), ``dist_<name>`` (1x5, 5x1 or 4
values) and, as EasyMocap writes them, optional ``H_<name>`` / ``W_<name>`` image sizes.
``extri.yml``: ``Rot_<name>`` (3x3) and/or ``R_<name>`` (3x1 Rodrigues), ``T_<name>`` (3x1); all
world to camera. The image size is otherwise not stored: the caller passes it from the media.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from calib import _parse
from calib.camera import Rig
from calib.errors import InputError, NoImageSize

INTRINSICS = "intri.yml"
EXTRINSICS = "extri.yml"

# Rot_<name> and the Rodrigues R_<name> of the same file describe one rotation; EasyMocap writes
# both from one matrix in double precision, so a larger difference means an edited, inconsistent file.
ROTATION_AGREEMENT = 1e-6

# FileStorage keys are K_<name> etc.; OpenCV accepts only these characters in a key.
_KEY_SAFE_NAME = re.compile(r"[A-Za-z0-9_-]+")


def _file_paths(path: Path) -> tuple[Path, Path]:
    """``(intri.yml, extri.yml)`` for a directory holding both, or for ``intri.yml`` itself."""
    intri = path / INTRINSICS if path.is_dir() else path
    return intri, intri.with_name(EXTRINSICS)


class _YamlFile:
    """An open ``cv2.FileStorage`` that turns every read problem into an InputError naming file and key."""

    def __init__(self, path: Path):
        if not path.is_file():
            raise InputError(f"{path}: no such file, expected OpenCV YAML ({INTRINSICS} and {EXTRINSICS})")
        self.path = path
        try:
            self._storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        except (cv2.error, SystemError) as error:  # the binding wraps parse errors in SystemError
            raise InputError(f"{path}: not readable OpenCV YAML ({_opencv_message(error)})") from None
        if not self._storage.isOpened():
            raise InputError(f"{path}: could not be opened as OpenCV YAML")

    def _get(self, key: str) -> cv2.FileNode:
        try:
            return self._storage.getNode(key)
        except cv2.error:  # the top level is not a mapping
            raise InputError(f"{self.path}: expected a mapping of keys (names, K_<name>, ...)") from None

    def has(self, key: str) -> bool:
        return not self._get(key).empty()

    def node(self, key: str) -> cv2.FileNode:
        node = self._get(key)
        if node.empty():
            raise InputError(f"{self.path}: missing key {key!r}")
        return node

    def matrix(self, key: str, shape: tuple[int, ...] | None) -> np.ndarray:
        """The !!opencv-matrix ``key`` reshaped to ``shape`` (``None``: flattened, any length)."""
        try:
            value = self.node(key).mat()
        except cv2.error:
            value = None
        if value is None:
            raise InputError(f"{self.path} {key}: expected an !!opencv-matrix")
        if shape is None:
            return np.asarray(value, dtype=np.float64).reshape(-1)
        return _parse.numbers(value, shape, f"{self.path} {key}")

    def integer(self, key: str) -> int:
        node = self.node(key)
        if not (node.isInt() or node.isReal()) or node.real() != round(node.real()):
            raise InputError(f"{self.path} {key}: expected an integer")
        return int(node.real())

    def names(self) -> list[str]:
        node = self.node("names")
        if not node.isSeq():
            raise InputError(f"{self.path} names: expected a list of camera names")
        return [_name(node.at(index), f"{self.path} names[{index}]") for index in range(node.size())]


def _opencv_message(error: Exception) -> str:
    """The last line of OpenCV's message (the parse error itself), from the cv2.error behind ``error``."""
    lines = str(error.__cause__ or error).strip().splitlines()
    return lines[-1] if lines else type(error).__name__


def _name(node: cv2.FileNode, where: str) -> str:
    """A camera name; unquoted numeric names (``- 1``) are integers in YAML but still names."""
    if node.isString():
        return node.string()
    if node.isInt():
        return str(int(node.real()))
    raise InputError(f"{where}: expected a camera name (string)")


def load(path: Path, image_sizes: dict[str, tuple[int, int]] | None, keep: set[str] | None = None) -> Rig:
    """The rig in ``intri.yml`` / ``extri.yml`` at ``path``, only the cameras named in ``keep`` (None: all).

    Image sizes come from ``image_sizes`` (name -> (w, h)), else from ``W_``/``H_`` keys.
    """
    intri_path, extri_path = _file_paths(path)
    intri, extri = _YamlFile(intri_path), _YamlFile(extri_path)
    sizes = image_sizes or {}
    cameras = []
    for name in intri.names():
        if keep is not None and name not in keep:
            continue
        if name in sizes:
            size = sizes[name]
        elif intri.has(f"W_{name}") and intri.has(f"H_{name}"):
            size = (intri.integer(f"W_{name}"), intri.integer(f"H_{name}"))
        else:
            raise NoImageSize(
                f"{intri_path}: no image size for camera {name!r} (no W_{name}/H_{name} keys),"
                " expected it from the camera's video or images"
            )
        cameras.append(
            _parse.camera(
                f"{intri_path} + {extri_path.name}",
                name=name,
                K=intri.matrix(f"K_{name}", (3, 3)),
                dist=_parse.distortion(intri.matrix(f"dist_{name}", None), f"{intri_path} dist_{name}"),
                R=_rotation(extri, name),
                t=extri.matrix(f"T_{name}", (3,)),
                size=size,
            )
        )
    return _parse.rig(str(intri_path), cameras)


def _rotation(extri: _YamlFile, name: str) -> np.ndarray:
    """(3, 3) ``Rot_<name>``, checked against ``R_<name>`` when both are present; else from ``R_<name>``."""
    rodrigues = extri.matrix(f"R_{name}", (3,)) if extri.has(f"R_{name}") else None
    if not extri.has(f"Rot_{name}"):
        if rodrigues is None:
            raise InputError(f"{extri.path}: missing key 'Rot_{name}' or 'R_{name}'")
        return cv2.Rodrigues(rodrigues)[0]
    R = extri.matrix(f"Rot_{name}", (3, 3))
    if rodrigues is not None:
        difference = np.abs(cv2.Rodrigues(rodrigues)[0] - R).max()
        if difference > ROTATION_AGREEMENT:
            raise InputError(
                f"{extri.path}: Rot_{name} and R_{name} describe different rotations"
                f" (max difference {difference:.2g}), expected the same rotation"
            )
    return R


def save(rig: Rig, path: Path) -> None:
    """Write ``rig`` as ``intri.yml`` + ``extri.yml`` in the directory ``path`` (or ``path`` = intri.yml)."""
    for camera in rig:
        if not _KEY_SAFE_NAME.fullmatch(camera.name):
            raise InputError(
                f"camera name {camera.name!r}: cannot be part of an OpenCV YAML key,"
                " expected letters, digits, '_' or '-'"
            )
    intri_path = path if path.suffix in (".yml", ".yaml") else path / INTRINSICS
    extri_path = intri_path.with_name(EXTRINSICS)
    intri_path.parent.mkdir(parents=True, exist_ok=True)
    intri = cv2.FileStorage(str(intri_path), cv2.FILE_STORAGE_WRITE)
    intri.startWriteStruct("names", cv2.FileNode_SEQ)
    for camera in rig:
        intri.write("", camera.name)
    intri.endWriteStruct()
    for camera in rig:
        intri.write(f"K_{camera.name}", camera.K)
        intri.write(f"dist_{camera.name}", camera.dist.reshape(1, 5))
        intri.write(f"H_{camera.name}", camera.size[1])
        intri.write(f"W_{camera.name}", camera.size[0])
    intri.release()
    extri = cv2.FileStorage(str(extri_path), cv2.FILE_STORAGE_WRITE)
    for camera in rig:
        extri.write(f"R_{camera.name}", cv2.Rodrigues(camera.R)[0])
        extri.write(f"Rot_{camera.name}", camera.R)
        extri.write(f"T_{camera.name}", camera.t.reshape(3, 1))
    extri.release()
