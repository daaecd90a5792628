"""Per-frame files: images and masks (PNG), oriented point clouds (PLY), results (JSON).

Every writer is atomic (:mod:`pipeline.io.atomic`), so a frame's output file either exists complete or
not at all; that is how stages record per-frame completion. Readers of user media raise
:class:`calib.errors.InputError` naming the file.

**Content checks.** A file can still be damaged after it was written (a disk, a copy, a hand), so each
per-frame format carries a check of its own content, made as it is written: PNG's chunk CRCs, a
``comment crc32`` line in the PLY header (over the vertex data), a ``crc32`` key in JSON records
(:func:`write_record`, over the rest of the record). :func:`file_problem` tests that check cheaply (a
resume trusts a frame's files only when it passes), and the readers test it too, along with what the
content must be (finite points, unit normals, the expected mask size). A file that fails raises
:class:`DamagedFileError`, an :class:`InputError` that names the file and that the runner turns into a
recompute when the file is one of its own outputs.

Conventions: images are ``(H, W, 3) uint8`` in OpenCV's BGR channel order, masks ``(H, W) uint8``
with 0 = background and 255 = person, point clouds two ``(N, 3) float64`` arrays (points in metres,
unit normals). File names of per-frame outputs are :func:`frame_name` (``<frame:06d><suffix>``).
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from calib.errors import InputError
from pipeline.io import atomic

#: Grey level above which a mask pixel counts as person (masks may be saved anti-aliased or as JPEG).
MASK_THRESHOLD = 127
#: The 8-byte signature that starts every PNG file.
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: Largest accepted departure of a normal's length from 1: float32 writers round to about 1e-7, while a
#: damaged normal is off by far more.
NORMAL_TOLERANCE = 1e-3
#: Key of a JSON record's content check (:func:`write_record`).
RECORD_CHECK = "crc32"


class DamagedFileError(InputError):
    """A file whose content check fails or whose content is implausible.

    ``path`` is the file: when it is one of the pipeline's own outputs, the runner deletes it and
    computes it again instead of stopping (:class:`pipeline.engine.runner.Runner`).
    """

    def __init__(self, path: str | os.PathLike, problem: str) -> None:
        self.path, self.problem = Path(path), problem
        super().__init__(f"{path}: {problem} (expected an intact file: the pipeline recomputes its own outputs, "
                         "a capture's file must be replaced)")

    def __reduce__(self) -> tuple:  # rebuilt from its two arguments when it comes back from a worker process
        return type(self), (self.path, self.problem)


def problem_of(error: OSError | DamagedFileError) -> str:
    """What is wrong with the file of ``error``, without its path: for a message that names the file itself."""
    return error.problem if isinstance(error, DamagedFileError) else (error.strerror or str(error))


_PLY_PROPERTIES = ("x", "y", "z", "nx", "ny", "nz")
_PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8"}


def frame_name(frame: int, suffix: str = ".png") -> str:
    """File name of a per-frame file: ``frame_name(7) == "000007.png"``."""
    return f"{frame:06d}{suffix}"


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read a colour image as ``(H, W, 3) uint8`` BGR; grey images are expanded to three channels."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise InputError(f"{path}: not a readable image (expected a PNG or JPEG file)")
    return image


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """``(width, height)`` of the image file at ``path``, which must be readable as :func:`read_image` reads it.

    A PNG is checked by its own CRCs (:func:`png_problem`) and measured from its header: the capture's opening
    measures every camera's clean plate, and decoding a colour plate costs many times that; any other image is
    decoded.
    """
    data = Path(path).read_bytes()
    if not data.startswith(PNG_SIGNATURE):
        image = read_image(path)
        return image.shape[1], image.shape[0]
    if (problem := png_problem(data)) or data[12:16] != b"IHDR":
        raise InputError(f"{path}: not a readable image ({problem or 'no PNG header'}; expected a PNG or JPEG file)")
    width, height = struct.unpack(">II", data[16:24])
    return width, height


def read_mask(path: str | os.PathLike, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read a silhouette mask as ``(H, W) uint8`` with values exactly 0 or 255.

    Person is what lies above :data:`MASK_THRESHOLD` (an anti-aliased or JPEG mask of 0 and 255), or, in a mask
    of exactly two grey levels whose brighter one is below it, that level (:func:`_person_threshold`): a mask
    saved as 0 and 1, as many tools write a boolean array, or a palette image whose person colour is dark.

    A PNG must pass its chunk CRCs (:func:`png_problem`), and with ``size`` ``(width, height)`` the mask
    must have that size; otherwise :class:`DamagedFileError`.
    """
    data = Path(path).read_bytes()
    if data.startswith(PNG_SIGNATURE) and (problem := png_problem(data)):
        raise DamagedFileError(path, problem)
    if not data:
        raise InputError(f"{path}: empty file (expected a PNG mask, 0 = background, 255 = person)")
    mask = _unfiltered_one_bit_png(data)
    if mask is None:
        grey = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
        if grey is None:
            raise InputError(f"{path}: not a readable mask image (expected a PNG, 0 = background, 255 = person)")
        mask = cv2.threshold(grey, _person_threshold(grey), 255, cv2.THRESH_BINARY)[1]
    if size is not None and (mask.shape[1], mask.shape[0]) != tuple(size):
        raise DamagedFileError(path, f"mask is {mask.shape[1]}x{mask.shape[0]} pixels, not the camera's "
                               f"{size[0]}x{size[1]}")
    return mask


def _person_threshold(grey: np.ndarray) -> int:
    """The grey level of ``grey`` (H, W) uint8 above which a pixel is person: :data:`MASK_THRESHOLD`, unless the
    mask holds exactly two levels, 0 and a dimmer one, which then marks him.

    Only a two-level mask is read so: an empty mask saved as JPEG carries a few dim levels of compression noise,
    which must stay background.
    """
    brightest = int(grey.max())
    if 0 < brightest <= MASK_THRESHOLD and cv2.countNonZero(grey) == np.count_nonzero(grey == brightest):
        return brightest - 1
    return MASK_THRESHOLD


def png_problem(data: bytes) -> str | None:
    """What is wrong with the PNG file ``data`` by its own checks (signature, chunk CRCs, an IEND
    chunk at the end), or None. A CRC-32 per chunk is cheap to test, far cheaper than decoding the image."""
    if not data.startswith(PNG_SIGNATURE):
        return "not a PNG file"
    position = len(PNG_SIGNATURE)
    while position + 12 <= len(data):
        length, kind = struct.unpack(">I4s", data[position : position + 8])
        end = position + 12 + length
        if end > len(data):
            break
        if zlib.crc32(data[position + 4 : end - 4]) != struct.unpack(">I", data[end - 4 : end])[0]:
            return f"PNG chunk {kind.decode('ascii', 'backslashreplace')} fails its CRC check"
        if kind == b"IEND":
            return None
        position = end
    return "PNG file is truncated (no IEND chunk)"


def _unfiltered_one_bit_png(data: bytes) -> np.ndarray | None:
    """The (H, W) uint8 0/255 pixels of a 1-bit grey PNG without row filters (as :func:`mask_png` writes
    them), else None (left to OpenCV).

    Inflating and unpacking the rows directly takes about a quarter of OpenCV's time for a 780 x 580 mask,
    and the reconstruction reads every camera's mask.
    """
    if not data.startswith(PNG_SIGNATURE + b"\x00\x00\x00\x0dIHDR") or len(data) < 33:
        return None
    width, height, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", data[16:29])
    if (depth, colour, interlace) != (1, 0, 0):
        return None
    pixels, position = [], 8
    while position + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[position : position + 8])
        if kind == b"IDAT":
            pixels.append(data[position + 8 : position + 8 + length])
        elif kind == b"IEND":
            break
        position += length + 12
    size = height * ((width + 7) // 8 + 1)
    try:
        rows = np.frombuffer(zlib.decompress(b"".join(pixels), zlib.MAX_WBITS, size), np.uint8)  # one buffer
    except zlib.error:
        return None
    if rows.size != size:
        return None
    rows = rows.reshape(height, -1)
    if rows[:, 0].any():  # a row filter: rare for 1-bit images, and OpenCV knows them all
        return None
    mask = np.unpackbits(rows[:, 1:], axis=1, count=width)
    return np.multiply(mask, np.uint8(255), out=mask)


def write_image(path: str | os.PathLike, image: np.ndarray) -> None:
    """Atomically write an image (``(H, W)`` or ``(H, W, 3)`` uint8; PNG is lossless)."""
    if image.dtype != np.uint8 or image.ndim not in (2, 3):
        raise ValueError(f"write_image: expected a (H, W[, 3]) uint8 array, got {image.dtype} {image.shape}")
    ok, encoded = cv2.imencode(Path(path).suffix, image)
    if not ok:
        raise ValueError(f"write_image: OpenCV cannot encode {Path(path).suffix!r} images ({path})")
    atomic.write_bytes(path, encoded.tobytes())  # a full disk is an OSError with its errno, as for any file


def write_mask(path: str | os.PathLike, mask: np.ndarray) -> None:
    """Atomically write a ``(H, W) uint8`` mask as PNG (nonzero pixels are saved as 255)."""
    if mask.dtype not in (np.uint8, np.bool_) or mask.ndim != 2:
        raise ValueError(f"write_mask: expected a (H, W) uint8 or bool array, got {mask.dtype} {mask.shape}")
    atomic.write_bytes(path, mask_png(mask))


def mask_png(mask: np.ndarray) -> bytes:
    """The PNG file of a mask (H, W) uint8 or bool: 1 bit per pixel, grey, nonzero pixels white (255).

    Every reader expands 1-bit grey to 0 and 255; an eighth of the bytes of an 8-bit PNG makes writing
    and reading several times faster. The rows (filter type 0) are deflated at level 1 with run-length
    matches only, as runs are all a mask has: the same bytes as OpenCV's ``IMWRITE_PNG_BILEVEL`` with that
    strategy, in about a third of its time.
    """
    height, width = mask.shape
    rows = np.zeros((height, (width + 7) // 8 + 1), np.uint8)  # a leading 0 per row: no filter
    rows[:, 1:] = np.packbits(mask.view(np.uint8), axis=1)
    deflate = zlib.compressobj(1, zlib.DEFLATED, 15, 8, zlib.Z_RLE)
    pixels = deflate.compress(rows.tobytes()) + deflate.flush()
    header = struct.pack(">IIBBBBB", width, height, 1, 0, 0, 0, 0)  # 1 bit, grey, deflate, no filter, no interlace
    return PNG_SIGNATURE + _png_chunk(b"IHDR", header) + _png_chunk(b"IDAT", pixels) + _png_chunk(b"IEND", b"")


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def write_ply(path: str | os.PathLike, points: np.ndarray, normals: np.ndarray) -> None:
    """Atomically write an oriented point cloud as binary little-endian PLY with double coordinates.

    Written by hand rather than through open3d so that an empty cloud (N = 0, a legal reconstruction
    result) is a valid file; open3d reads these files (``o3d.io.read_point_cloud``).

    Parameters
    ----------
    points : (N, 3) float array, metres
    normals : (N, 3) float array, unit vectors
    """
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(f"write_ply: expected points and normals of shape (N, 3), got {points.shape} "
                         f"and {normals.shape}")
    body = np.hstack([points, normals]).astype("<f8").tobytes()
    header = ["ply", "format binary_little_endian 1.0", f"comment crc32 {zlib.crc32(body):08x}",
              f"element vertex {len(points)}"]
    header += [f"property double {name}" for name in _PLY_PROPERTIES]
    header += ["end_header", ""]
    atomic.write_bytes(path, "\n".join(header).encode("ascii") + body)


@dataclass(frozen=True)
class _PlyLayout:
    """What a PLY header says: the vertex count and dtype, the header's length, its crc32 (or None)."""

    count: int
    dtype: np.dtype
    body_start: int
    crc32: int | None


def _ply_layout(data: bytes) -> _PlyLayout | str:
    """The layout of the PLY file ``data``, or what is wrong with its header."""
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        return "not a PLY file (no 'ply' header ending in 'end_header')"
    lines = data[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        return "unsupported PLY encoding (not binary_little_endian 1.0)"
    count, fields, in_vertex, crc = 0, [], False, None
    for line in lines:
        words = line.split()
        if words[:2] == ["comment", "crc32"] and len(words) == 3:
            try:
                crc = int(words[2], 16)
            except ValueError:
                return f"unreadable PLY content check {line!r}"
        elif words[:1] == ["element"] and len(words) == 3:
            in_vertex = words[1] == "vertex"
            if in_vertex:
                if not words[2].isdigit():
                    return f"unreadable PLY vertex count {line!r}"
                count = int(words[2])
            elif count:
                break  # vertex data comes first; later elements are not read
        elif words[:1] == ["property"] and in_vertex:
            if len(words) != 3 or words[1] not in _PLY_TYPES:
                return f"unsupported vertex property {line!r} (not float or double)"
            fields.append((words[2], _PLY_TYPES[words[1]]))
    names = [name for name, _ in fields]
    if any(name not in names for name in _PLY_PROPERTIES):
        return f"PLY vertices lack {sorted(set(_PLY_PROPERTIES) - set(names))} (not x y z nx ny nz)"
    return _PlyLayout(count, np.dtype(fields), end + len(b"end_header\n"), crc)


def ply_problem(data: bytes) -> str | None:
    """What is wrong with the PLY file ``data`` by its header, length and content check, or None."""
    checked = _checked_ply_layout(data)
    return checked if isinstance(checked, str) else None


def _checked_ply_layout(data: bytes) -> _PlyLayout | str:
    """The layout of the PLY file ``data`` once its length and content check pass, or what is wrong."""
    layout = _ply_layout(data)
    if isinstance(layout, str):
        return layout
    body = memoryview(data)[layout.body_start:]
    if len(body) < layout.count * layout.dtype.itemsize:
        return f"PLY file is truncated ({len(body)} bytes for {layout.count} vertices)"
    if layout.crc32 is not None and zlib.crc32(body) != layout.crc32:
        return "PLY vertex data fails its crc32 check"
    return layout


def read_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a binary little-endian PLY point cloud with normals.

    The file must pass :func:`ply_problem`, its points and normals be finite and its normals of unit
    length (within :data:`NORMAL_TOLERANCE`); otherwise :class:`DamagedFileError`.

    Returns
    -------
    points, normals : (N, 3) float64 arrays
    """
    data = Path(path).read_bytes()
    layout = _checked_ply_layout(data)
    if isinstance(layout, str):
        raise DamagedFileError(path, layout)
    vertices = np.frombuffer(data, dtype=layout.dtype, count=layout.count, offset=layout.body_start)
    points = np.stack([vertices[name] for name in _PLY_PROPERTIES[:3]], axis=1).astype(np.float64)
    normals = np.stack([vertices[name] for name in _PLY_PROPERTIES[3:]], axis=1).astype(np.float64)
    if not (np.isfinite(points).all() and np.isfinite(normals).all()):
        raise DamagedFileError(path, "PLY holds a coordinate that is not a finite number")
    lengths = np.sqrt(np.einsum("ij,ij->i", normals, normals))
    if len(lengths) and np.abs(lengths - 1).max() > NORMAL_TOLERANCE:
        worst = int(np.abs(lengths - 1).argmax())
        raise DamagedFileError(path, f"PLY normal {worst} has length {lengths[worst]:.6g}, not 1")
    return points, normals


def _to_json_value(value: Any) -> Any:
    """``json.dumps`` hook for numpy arrays and scalars."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot write {type(value).__name__} as JSON")


def to_json(obj: Any) -> str:
    """Deterministic JSON text (sorted keys, no NaN) of plain data with numpy values."""
    return json.dumps(obj, indent=1, sort_keys=True, allow_nan=False, default=_to_json_value) + "\n"


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Atomically write ``obj`` as JSON (see :func:`to_json`)."""
    atomic.write_text(path, to_json(obj))


def read_json(path: str | os.PathLike) -> Any:
    """Read a JSON file; a malformed one is a :class:`DamagedFileError` naming it."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DamagedFileError(path, f"not valid JSON ({error})") from None


def write_record(path: str | os.PathLike, record: dict) -> None:
    """Atomically write the JSON object ``record`` with its content check (key :data:`RECORD_CHECK`):
    the CRC-32 of :func:`to_json` of the rest, so that a changed value is noticed (:func:`read_record`)."""
    if RECORD_CHECK in record:
        raise ValueError(f"write_record: {RECORD_CHECK!r} is the content check's key")
    text = to_json(record)
    atomic.write_text(path, _with_check_line(text, record, f"{zlib.crc32(text.encode('utf-8')):08x}"))


def read_record(path: str | os.PathLike) -> dict:
    """A JSON record written by :func:`write_record`, without its check; :class:`DamagedFileError` when
    the file is not valid JSON or fails its check."""
    try:
        text = Path(path).read_text(encoding="utf-8")
        record = json.loads(text)
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DamagedFileError(path, f"not valid JSON ({error})") from None
    problem = _record_text_problem(text, record)
    if problem:
        raise DamagedFileError(path, problem)
    return {key: value for key, value in record.items() if key != RECORD_CHECK}


def _with_check_line(text: str, record: dict, check: str) -> str:
    """:func:`to_json` of ``record`` with its ``check`` added, from ``text``, :func:`to_json` of ``record``.

    The records hold long lists of floats, which the indented encoder (Python's, not C's) is slow to
    write; the check is one line at its sorted place among the top-level keys, the lines indented by
    exactly one space (JSON strings hold no raw newline, deeper lines are indented further).
    """
    line = f' "{RECORD_CHECK}": "{check}"'
    keys = list(record)
    later = sorted(key for key in keys if key > RECORD_CHECK) if all(isinstance(key, str) for key in keys) else None
    following = f"\n {json.dumps(later[0])}: " if later else None
    if following is not None and following in text:
        return text.replace(following, f"\n{line},{following}", 1)
    if later == [] and text.endswith("\n}\n"):  # the check sorts last
        return f"{text[:-3]},\n{line}\n}}\n"
    return to_json({**record, RECORD_CHECK: check})  # no line to add it to (an empty record), or odd keys


def _record_text_problem(text: str, record: Any) -> str | None:
    """What is wrong with the record file ``text`` (parsed: ``record``) by its check, or None.

    A file as :func:`write_record` wrote it is :func:`to_json` of the rest plus the check's line: its
    check is tested on the text without that line, without encoding the record again. Any other text
    (reformatted by a hand, say) is judged by its values (:func:`_record_problem`).
    """
    if isinstance(record, dict) and isinstance(check := record.get(RECORD_CHECK), str):
        rest = _without_check_line(text, check)
        if rest is not None and f"{zlib.crc32(rest.encode('utf-8')):08x}" == check:
            return None
    return _record_problem(record)


def _without_check_line(text: str, check: str) -> str | None:
    """``text`` without the top-level line of the record check ``check`` (and its comma), or None."""
    line = f'\n "{RECORD_CHECK}": "{check}"'
    start = text.find(line)
    if start < 0:
        return None
    end = start + len(line)
    if text.startswith(",", end):  # a later key follows
        return text[:start] + text[end + 1:]
    if text.endswith(",", 0, start):  # the check was the last key
        return text[:start - 1] + text[end:]
    return None


def _record_problem(record: Any) -> str | None:
    if not isinstance(record, dict) or not isinstance(record.get(RECORD_CHECK), str):
        return f"not a JSON record with a {RECORD_CHECK} content check"
    rest = {key: value for key, value in record.items() if key != RECORD_CHECK}
    try:
        text = to_json(rest)
    except ValueError:  # NaN or infinity: written by no one but a hand
        return "JSON record holds a number that is not finite"
    if f"{zlib.crc32(text.encode('utf-8')):08x}" != record[RECORD_CHECK]:
        return f"JSON record fails its {RECORD_CHECK} check"
    return None


def file_problem(path: str | os.PathLike) -> str | None:
    """What is wrong with a per-frame output file by the content check its format carries, or None.

    PNG: chunk CRCs; PLY: header, length and crc32; JSON: valid JSON, and a record's check when it has
    one. Reads the file but decodes nothing, a small fraction of the cost of decoding, so a resume can
    afford it for every frame it keeps. Other suffixes carry no check (None).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".png", ".ply", ".json"):
        return None
    data = path.read_bytes()
    if suffix == ".png":
        return png_problem(data)
    if suffix == ".ply":
        return ply_problem(data)
    try:
        text = data.decode("utf-8")
        document = json.loads(text)
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        return f"not valid JSON ({error})"
    return _record_text_problem(text, document) if isinstance(document, dict) and RECORD_CHECK in document else None
