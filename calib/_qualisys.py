"""Qualisys Track Manager (QTM) calibrations exported as XML (``*.qca.txt``, as Pose2Sim's demos ship them).

Layout: ``<calibration><cameras><camera ...>`` (possibly inside QTM's ``<QTM_Parameters_Ver_...>``), one element
per camera with attributes ``serial`` (the camera's name here), ``active`` (cameras with ``0`` are skipped) and
``viewrotation``, and children:

- ``<transform x y z r11 ... r33>``: the camera's *position* in the lab, millimetres, and the rotation matrix
  ``M = [[r11, r12, r13], [r21, ...], ...]`` whose rows are the camera's axes in the lab frame, QTM's camera
  frame having x right, y *up* and the camera looking along -z. OpenCV's camera has y down and looks along +z,
  so ``R = diag(1, -1, -1) M`` and ``t = -R position``; positions are converted to metres here, so the rig is
  in metres whatever ``calibration.units`` says (leave it at ``m``).
- ``<intrinsic focalLengthU focalLengthV centerPointU centerPointV skew sensorMinU sensorMaxU sensorMinV
  sensorMaxV radialDistortion1..3 tangentalDistortion1..2>``: lengths in *sub-pixel units* of the sensor. The
  sub-pixel factor is the sensor's extent ``sensorMaxU - sensorMinU`` over the width of the full video field of
  view ``fov_video_max`` (64 for Miqus and Oqus cameras, 1 in files written in pixels); the principal point is
  then shifted by the video window's corner (``fov_video`` ``left``, ``top``). The distortion coefficients act
  on normalised image coordinates, as OpenCV's ``(k1, k2, p1, p2, k3)`` = (radial1, radial2, tangental1,
  tangental2, radial3), and are not scaled.
- ``<fov_video left top right bottom>``: the recorded image, pixels, inclusive; its size is the camera's.

Videos are matched to cameras by serial number; cameras without media (marker-only cameras) are left out when
the media are known. A video recorded at a lower resolution than ``fov_video`` (QTM's 540p, 720p options) scales
the intrinsics by the common factor. The calibration refers to the sensor's orientation: ``viewrotation`` only
turns QTM's display, and a video turned by 90 degrees is refused.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import numpy as np

from calib import _parse
from calib.camera import Camera, Rig
from calib.errors import InputError

FILE_SUFFIX = ".qca.txt"
#: The writer's sub-pixel factor (QTM's).
SUBPIXELS = 64
#: QTM camera frame (y up, looking along -z) to OpenCV's (y down, looking along +z).
_FLIP = np.diag([1.0, -1.0, -1.0])
_MM = 1000.0
_INTRINSIC_KEYS = ("focalLengthU", "focalLengthV", "centerPointU", "centerPointV", "sensorMinU", "sensorMaxU")


def _file(path: Path) -> Path:
    """The ``.qca.txt`` file itself, or the only one in the directory ``path``."""
    if path.is_dir():
        files = sorted(path.glob(f"*{FILE_SUFFIX}"))
        if len(files) != 1:
            raise InputError(f"{path}: {len(files)} *{FILE_SUFFIX} files, expected one Qualisys calibration "
                             "(or name the file in calibration.path)")
        return files[0]
    if not path.is_file():
        raise InputError(f"{path}: no such file, expected a Qualisys {FILE_SUFFIX} calibration")
    return path


def _number(element: ElementTree.Element, key: str, where: str, default: float | None = None) -> float:
    value = element.get(key)
    if value is None:
        if default is not None:
            return default
        raise InputError(f"{where}: <{element.tag}> has no attribute {key!r}")
    try:
        number = float(value)
    except ValueError:
        raise InputError(f"{where}: <{element.tag}> {key}={value!r} is not a number") from None
    if not np.isfinite(number):
        raise InputError(f"{where}: <{element.tag}> {key}={value!r}, expected a finite number")
    return number


def _child(camera: ElementTree.Element, tag: str, where: str) -> ElementTree.Element:
    element = camera.find(tag)
    if element is None:
        raise InputError(f"{where}: no <{tag}> element")
    return element


def _window(element: ElementTree.Element, where: str) -> tuple[float, float, int, int]:
    """(left, top, width, height) of a ``fov_*`` element (its right and bottom are inclusive)."""
    left, top = _number(element, "left", where), _number(element, "top", where)
    width = _number(element, "right", where) - left + 1
    height = _number(element, "bottom", where) - top + 1
    if width < 1 or height < 1 or width != round(width) or height != round(height):
        raise InputError(f"{where}: <{element.tag}> spans {width:g} x {height:g} pixels, expected a whole size")
    return left, top, int(width), int(height)


def _subpixels(intrinsic: ElementTree.Element, full_width: int, where: str) -> float:
    """Sub-pixel units per pixel: the sensor's extent over the full video width, a whole number."""
    extent = _number(intrinsic, "sensorMaxU", where) - _number(intrinsic, "sensorMinU", where)
    ratio = extent / full_width
    factor = round(ratio)
    if factor < 1 or abs(ratio - factor) > 0.05:  # max - min is factor * width, or one unit less
        raise InputError(f"{where}: sensorMinU..sensorMaxU spans {extent:g} units over a {full_width}-pixel field of "
                         "view, expected a whole number of sub-pixel units per pixel (64 for QTM)")
    return float(factor)


def load(path: Path, image_sizes: dict[str, tuple[int, int]] | None, keep: set[str] | None = None) -> Rig:
    """The rig of the Qualisys calibration at ``path``; ``image_sizes`` (from the media) select and size cameras,
    of those named in ``keep`` (None: all)."""
    file = _file(path)
    text = file.read_text(encoding="utf-8", errors="replace")
    if re.search(r"<!(DOCTYPE|ENTITY)", text):  # a calibration needs no entities; they can expand without bound
        raise InputError(f"{file}: holds a DOCTYPE or ENTITY declaration, expected plain QTM calibration XML")
    try:
        root = ElementTree.fromstring(text)
    except ElementTree.ParseError as error:
        raise InputError(f"{file}: not valid XML ({error})") from None
    elements = root.findall(".//cameras/camera")
    if not elements:
        raise InputError(f"{file}: no <cameras><camera> elements, expected a QTM calibration")
    sizes = dict(image_sizes or {})
    cameras, skipped = [], []
    for index, element in enumerate(elements):
        where = f"{file} camera {index + 1}"
        name = element.get("serial")
        if not name:
            raise InputError(f"{where}: no serial attribute, expected the camera's serial number (its name)")
        if element.get("active", "1").strip() == "0" or (keep is not None and name not in keep):
            continue
        if sizes and name not in sizes:
            skipped.append(name)
            continue
        cameras.append(_camera(element, name, f"{file} camera {name}", sizes.get(name)))
    if not cameras:
        expected = ", ".join(element.get("serial", "?") for element in elements)
        raise InputError(f"{file}: none of its cameras has media here (expected videos named by serial number: "
                         f"{expected})")
    return _parse.rig(str(file), cameras)


def _camera(element: ElementTree.Element, name: str, where: str, media_size: tuple[int, int] | None) -> Camera:
    transform, intrinsic = _child(element, "transform", where), _child(element, "intrinsic", where)
    video = _child(element, "fov_video", where)
    full = element.find("fov_video_max")
    left, top, width, height = _window(video, where)
    full_width = _window(full, where)[2] if full is not None else width
    subpixels = _subpixels(intrinsic, full_width, where)
    values = {key: _number(intrinsic, key, where) for key in _INTRINSIC_KEYS}
    skew = _number(intrinsic, "skew", where, default=0.0)
    K = np.array([[values["focalLengthU"], skew, values["centerPointU"]], [0.0, values["focalLengthV"],
                                                                          values["centerPointV"]], [0, 0, subpixels]])
    K = K / subpixels
    K[0, 2] -= left
    K[1, 2] -= top
    size = (width, height)
    if media_size is not None and tuple(media_size) != size:
        K, size = _scaled(K, size, tuple(media_size), element.get("viewrotation", "0"), where)
    dist = np.array([_number(intrinsic, key, where, default=0.0) for key in
                     ("radialDistortion1", "radialDistortion2", "tangentalDistortion1", "tangentalDistortion2",
                      "radialDistortion3")])
    M = np.array([[_number(transform, f"r{i}{j}", where) for j in (1, 2, 3)] for i in (1, 2, 3)])
    position = np.array([_number(transform, axis, where) for axis in "xyz"]) / _MM
    R = _FLIP @ M
    return _parse.camera(where, name=name, K=K, dist=dist, R=R, t=-R @ position, size=size)


def _scaled(K: np.ndarray, size: tuple[int, int], media: tuple[int, int], rotation: str,
            where: str) -> tuple[np.ndarray, tuple[int, int]]:
    """``K`` for media recorded at ``media`` instead of the calibration's ``size``: one common factor only."""
    if media == size[::-1] and rotation.strip() in ("90", "270"):
        raise InputError(f"{where}: the media are {media[0]}x{media[1]}, the calibration's {size[0]}x{size[1]} turned "
                         f"by viewrotation={rotation}; expected videos in the sensor's orientation (unrotated)")
    factor = media[0] / size[0]
    if abs(media[1] - size[1] * factor) > 1.0:
        raise InputError(f"{where}: the media are {media[0]}x{media[1]}, the calibration's fov_video "
                         f"{size[0]}x{size[1]}; expected the same size or the same size scaled")
    scaled = K.copy()
    scaled[:2, :2] *= factor
    scaled[:2, 2] = (K[:2, 2] + 0.5) * factor - 0.5  # pixel centres at integers in both images
    return scaled, media


def save(rig: Rig, path: Path) -> None:
    """Write ``rig`` (metres) as a QTM calibration: ``path`` is the ``.qca.txt`` file or a directory for
    ``calibration.qca.txt``; sub-pixel factor :data:`SUBPIXELS`, positions in millimetres."""
    file = path if path.name.endswith(FILE_SUFFIX) else path / f"calibration{FILE_SUFFIX}"
    file.parent.mkdir(parents=True, exist_ok=True)
    root = ElementTree.Element("calibration", {"source": file.name, "type": "regular"})
    cameras = ElementTree.SubElement(root, "cameras")
    for camera in rig:
        element = ElementTree.SubElement(cameras, "camera", {"active": "1", "serial": camera.name,
                                                             "viewrotation": "0"})
        width, height = camera.size
        window = {"left": "0", "top": "0", "right": str(width - 1), "bottom": str(height - 1)}
        for tag in ("fov_marker", "fov_marker_max", "fov_video", "fov_video_max"):
            ElementTree.SubElement(element, tag, window)
        M = _FLIP @ camera.R
        attributes = {axis: repr(float(value)) for axis, value in zip("xyz", camera.centre * _MM, strict=True)}
        attributes |= {f"r{i + 1}{j + 1}": repr(float(M[i, j])) for i in range(3) for j in range(3)}
        ElementTree.SubElement(element, "transform", attributes)
        K = camera.K * SUBPIXELS
        k1, k2, p1, p2, k3 = camera.dist
        ElementTree.SubElement(element, "intrinsic", {
            "sensorMinU": "0", "sensorMaxU": str(width * SUBPIXELS - 1), "sensorMinV": "0",
            "sensorMaxV": str(height * SUBPIXELS - 1), "focalLengthU": repr(float(K[0, 0])),
            "focalLengthV": repr(float(K[1, 1])), "centerPointU": repr(float(K[0, 2])),
            "centerPointV": repr(float(K[1, 2])), "skew": repr(float(K[0, 1])), "radialDistortion1": repr(float(k1)),
            "radialDistortion2": repr(float(k2)), "radialDistortion3": repr(float(k3)),
            "tangentalDistortion1": repr(float(p1)), "tangentalDistortion2": repr(float(p2))})
    ElementTree.indent(root)
    file.write_text('<?xml version="1.0" encoding="UTF-8"?>\n' + ElementTree.tostring(root, encoding="unicode") + "\n",
                    encoding="utf-8")
