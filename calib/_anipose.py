"""anipose / aniposelib / FreeMoCap ``calibration.toml``: one ``[cam_N]`` table per camera.

Each table holds ``name``, ``size = [width, height]``, ``matrix`` (3x3), ``distortions`` (OpenCV
k1 k2 p1 p2 k3), ``rotation`` (Rodrigues vector, world to camera) and ``translation``. Tables are
ordered by the number N (aniposelib sorts them as text, which puts ``cam_10`` before ``cam_2``);
other tables such as ``[metadata]`` are ignored.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import tomli_w
import tomllib

from calib import _parse
from calib.camera import Camera, Rig
from calib.errors import InputError

FILE_NAME = "calibration.toml"
_CAMERA_TABLE = re.compile(r"cam_(\d+)")


def _toml_path(path: Path) -> Path:
    """The TOML file itself when ``path`` is a directory holding ``calibration.toml``."""
    return path / FILE_NAME if path.is_dir() else path


def load(path: Path) -> Rig:
    """The rig stored in ``path`` (``calibration.toml`` or the directory holding it)."""
    toml_path = _toml_path(path)
    if not toml_path.is_file():
        raise InputError(f"{toml_path}: no such file, expected an anipose {FILE_NAME}")
    try:
        document = tomllib.loads(toml_path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
        raise InputError(f"{toml_path}: not valid TOML ({error})") from None
    tables = sorted(
        (int(match[1]), key)
        for key in document
        if (match := _CAMERA_TABLE.fullmatch(key)) and isinstance(document[key], dict)
    )
    if not tables:
        raise InputError(f"{toml_path}: no [cam_N] camera tables, expected one per camera")
    return _parse.rig(str(toml_path), [_camera(document[key], f"{toml_path} [{key}]") for _, key in tables])


def _camera(table: dict, where: str) -> Camera:
    """One ``[cam_N]`` table as a Camera; ``where`` names the file and table in errors."""
    missing = [key for key in ("name", "size", "matrix", "rotation", "translation") if key not in table]
    if missing:
        raise InputError(f"{where}: missing key {missing[0]!r}")
    name = table["name"]
    if isinstance(name, int) and not isinstance(name, bool):
        name = str(name)  # a bare number in TOML is still a camera name
    if not isinstance(name, str):
        raise InputError(f"{where} name: expected a string, got {name!r}")
    rotation = _parse.numbers(table["rotation"], (3,), f"{where} rotation")
    R, _ = cv2.Rodrigues(rotation)
    return _parse.camera(
        where,
        name=name,
        K=_parse.numbers(table["matrix"], (3, 3), f"{where} matrix"),
        dist=_parse.distortion(table.get("distortions", [0.0]), f"{where} distortions"),
        R=R,
        t=_parse.numbers(table["translation"], (3,), f"{where} translation"),
        size=_parse.image_size(table["size"], f"{where} size"),
    )


def save(rig: Rig, path: Path) -> None:
    """Write ``rig`` to ``path`` (a ``.toml`` file, or a directory that gets ``calibration.toml``).

    The layout is aniposelib's, one line per key and one table per camera, so a calibration diffs
    line by line (tomli_w would spread every array over one line per number).
    """
    toml_path = path if path.suffix == ".toml" else path / FILE_NAME
    toml_path.parent.mkdir(parents=True, exist_ok=True)
    tables = [_table(f"cam_{index}", camera) for index, camera in enumerate(rig)]
    toml_path.write_text("\n".join(tables), encoding="utf-8")


def _array(values) -> str:
    """A TOML array literal on one line; ``repr`` of a finite float or int is valid TOML."""
    items = (_array(value) if isinstance(value, list) else repr(value) for value in values)
    return "[" + ", ".join(items) + "]"


def _table(key: str, camera: Camera) -> str:
    rotation, _ = cv2.Rodrigues(camera.R)
    return (
        f"[{key}]\n"
        + tomli_w.dumps({"name": camera.name})  # string quoting and escapes
        + f"size = {_array(list(camera.size))}\n"
        + f"matrix = {_array(camera.K.tolist())}\n"
        + f"distortions = {_array(camera.dist.tolist())}\n"
        + f"rotation = {_array(rotation.reshape(3).tolist())}\n"
        + f"translation = {_array(camera.t.tolist())}\n"
    )
