"""Read and write a rig in the calibration formats of CAPTURE_FORMAT.md: colmap, opencv, anipose, projection,
qualisys.

Readers return the rig exactly as the file states it (file units, file up axis); ``calib.world``
converts it to the pipeline's world frame. Every problem with a file raises ``InputError`` naming
the file and the key.
"""

from __future__ import annotations

import importlib
import re
from collections.abc import Collection, Mapping
from pathlib import Path
from types import ModuleType

from calib.camera import Rig
from calib.errors import InputError

FORMATS = ("colmap", "opencv", "anipose", "projection", "qualisys")
#: Formats whose readers take the image sizes of the media: opencv and projection store none, qualisys the
#: sensor's (the videos may be recorded smaller, and marker-only cameras have none).
SIZELESS_FORMATS = ("opencv", "projection", "qualisys")


_DIGITS = re.compile(r"(\d+)")


def natural_key(text: str) -> list:
    """Sort key putting ``cam2`` before ``cam10``: digit runs compare as numbers (file names of cameras and
    views are ordered this way wherever a folder is listed)."""
    return [int(part) if part.isdigit() else part for part in _DIGITS.split(text)]


def _reader(fmt: str) -> ModuleType:
    """The private module of a format, imported when first needed: pycolmap alone takes a twentieth of a
    second, which every worker process of a pipeline run would otherwise pay without reading a model."""
    return importlib.import_module(f"calib._{fmt}")


def _check_format(fmt: str) -> None:
    if fmt not in FORMATS:
        raise InputError(f"calibration format {fmt!r} is unknown, expected one of {', '.join(FORMATS)}")


def load_rig(fmt: str, path: str | Path, *, image_sizes: Mapping[str, tuple[int, int]] | None = None,
             cameras: Collection[str] | None = None) -> Rig:
    """The rig stored at ``path`` in format ``fmt``, cameras in the file's order.

    Parameters
    ----------
    fmt : {"colmap", "opencv", "anipose", "projection", "qualisys"}
    path : str or Path
        colmap: the model directory; opencv: the directory holding ``intri.yml`` and ``extri.yml``
        (or ``intri.yml`` itself); anipose: ``calibration.toml`` or the directory holding it;
        projection: the directory of one 3x4 matrix file per camera; qualisys: the ``.qca.txt`` file or the
        directory holding it.
    image_sizes : mapping of camera name to (width, height), optional
        Sizes read from the media. opencv files (EasyMocap's ``W_``/``H_`` keys aside) and projection
        matrices do not store sizes, so they come from here. Formats that store sizes must agree with the given ones:
        intrinsics calibrated at another resolution would silently misproject.
    cameras : collection of str, optional
        The cameras to keep (default all), each of which must be in the file; the others are not read further (a
        camera left out needs no image size).
    """
    _check_format(fmt)
    path = Path(path)
    sizes = dict(image_sizes or {})
    keep = None if cameras is None else set(cameras)
    if fmt in SIZELESS_FORMATS:
        rig = _reader(fmt).load(path, sizes, keep)
    else:
        rig = _reader(fmt).load(path)
        if keep is not None:
            rig = Rig(tuple(camera for camera in rig if camera.name in keep))
        for camera in rig:
            if camera.name in sizes and tuple(sizes[camera.name]) != camera.size:
                raise InputError(
                    f"{path}: camera {camera.name!r} is calibrated for {camera.size[0]}x{camera.size[1]} images,"
                    f" but its media are {sizes[camera.name][0]}x{sizes[camera.name][1]}; expected the same size"
                )
    absent = sorted((keep or set()) - set(rig.names))
    if absent:
        raise InputError(f"{path}: no camera {absent[0]!r} in this calibration (expected the names of its cameras)")
    return rig


def save_rig(rig: Rig, fmt: str, path: str | Path) -> None:
    """Write ``rig`` to ``path`` in format ``fmt`` (COLMAP as text); ``load_rig`` reads it back.

    ``path`` is a directory (created if needed); for anipose it may also be the ``.toml`` file. projection
    holds no distortion and colmap no skew: a camera with them is refused (``InputError``).
    """
    _check_format(fmt)
    path = Path(path)
    _reader(fmt).save(rig, path)
