"""``capture.yaml``: parsed as plain YAML and validated key by key, defaults filled in; each mistake is one
:class:`InputError` naming the file, the key and what was expected (CAPTURE_FORMAT.md)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import yaml

from calib.errors import InputError
from calib.world import UNIT_SCALE, up_rotation
from pipeline.io import plain_yaml
from stages.joints import SUBJECT_HEIGHT_RANGE_M

CALIBRATION_FORMATS = ("colmap", "opencv", "anipose", "projection", "qualisys")

_TOP_LEVEL_KEYS = ("fps", "calibration", "cameras", "subject", "volume", "frames", "frame_offsets")
_CALIBRATION_KEYS = ("format", "path", "units", "up")


def _read_config(path: Path) -> dict:
    """Parse and validate ``capture.yaml``; return it with defaults filled in."""
    raw = _read_mapping(path)
    _reject_unknown(raw, _TOP_LEVEL_KEYS, path, "")
    fps = raw.get("fps")
    if not _is_number(fps) or not fps > 0:
        raise InputError(f"{path}: fps is {fps!r} (expected a positive number of frames per second)")
    calibration = _check_calibration(raw.get("calibration"), path)
    subject = raw.get("subject")
    if subject is not None:
        _check_subject(subject, path)
    volume = raw.get("volume")
    if volume is not None:
        volume = _check_volume(volume, path)
    frames = _check_frames(raw.get("frames") or {}, path)
    config = {"fps": float(fps), "calibration": calibration, "subject": subject, "volume": volume, "frames": frames}
    if "cameras" in raw:  # only when given: the config's fingerprint (cache keys) stays that of a capture without it
        config["cameras"] = _check_cameras(raw["cameras"], path)
    offsets = _check_frame_offsets(raw["frame_offsets"], path) if "frame_offsets" in raw else {}
    if offsets:  # likewise, and zero offsets are none
        config["frame_offsets"] = offsets
    return config


def _read_mapping(path: Path) -> dict:
    """The top level of ``capture.yaml``, which must be a mapping."""
    if not path.is_file():
        raise InputError(f"{path}: missing (expected a capture.yaml describing the capture, "
                         "see CAPTURE_FORMAT.md)")
    try:
        raw = plain_yaml.load(path.read_text(encoding="utf-8"), str(path))
    except (yaml.YAMLError, UnicodeDecodeError) as error:
        raise InputError(f"{path}: not valid YAML ({plain_yaml.describe_error(error)}) "
                         "(expected a mapping of keys)") from None
    if raw is None:
        raise InputError(f"{path}: empty (expected a mapping with at least fps and calibration: {{format, path}}, "
                         "see CAPTURE_FORMAT.md)")
    if not isinstance(raw, dict):
        raise InputError(f"{path}: top level is {type(raw).__name__} "
                         "(expected a mapping with fps and calibration)")
    return raw


def _check_calibration(calibration: Any, path: Path) -> dict:
    """The ``calibration:`` section with its defaults (``units: m``, ``up: +z``)."""
    if not isinstance(calibration, dict):
        raise InputError(f"{path}: calibration is {calibration!r} (expected a mapping with format and path)")
    _reject_unknown(calibration, _CALIBRATION_KEYS, path, "calibration.")
    calibration = {"units": "m", "up": "+z", **calibration}
    if calibration.get("format") not in CALIBRATION_FORMATS:
        raise InputError(f"{path}: calibration.format {calibration.get('format')!r} is unknown "
                         f"(expected one of {', '.join(CALIBRATION_FORMATS)})")
    if not isinstance(calibration.get("path"), str) or not calibration["path"]:
        raise InputError(f"{path}: calibration.path is {calibration.get('path')!r} "
                         "(expected a path relative to the capture directory)")
    if calibration["units"] not in UNIT_SCALE:
        raise InputError(f"{path}: calibration.units {calibration['units']!r} is unknown "
                         f"(expected one of {', '.join(UNIT_SCALE)})")
    try:
        if calibration["up"] != "auto":
            up_rotation(calibration["up"])
    except InputError:
        raise InputError(f"{path}: calibration.up {calibration['up']!r} is unknown "
                         "(expected one of +z, -z, +y, -y, +x, -x, auto)") from None
    return calibration


def _check_subject(subject: Any, path: Path) -> None:
    if not isinstance(subject, dict):
        raise InputError(f"{path}: subject is {subject!r} (expected a mapping like {{height_m: 1.75}})")
    _reject_unknown(subject, ("height_m",), path, "subject.")
    height = subject.get("height_m")
    low, high = SUBJECT_HEIGHT_RANGE_M
    if height is not None and (not _is_number(height) or not low < height <= high):
        raise InputError(f"{path}: subject.height_m is {height!r} "
                         f"(expected a height in metres, above {low:g} and at most {high:g})")


def _check_frames(frames: Any, path: Path) -> dict:
    """The ``frames:`` section with its defaults (``start: 0, stop: null, step: 1``)."""
    if not isinstance(frames, dict):
        raise InputError(f"{path}: frames is {frames!r} "
                         "(expected a mapping like {start: 0, stop: null, step: 1})")
    _reject_unknown(frames, ("start", "stop", "step"), path, "frames.")
    frames = {"start": 0, "stop": None, "step": 1, **frames}
    for key, minimum in (("start", 0), ("step", 1), ("stop", 1)):
        value = frames[key]
        if key == "stop" and value is None:
            continue
        if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
            raise InputError(f"{path}: frames.{key} is {value!r} (expected an integer >= {minimum})")
    if frames["stop"] is not None and frames["stop"] <= frames["start"]:
        raise InputError(f"{path}: frames.stop {frames['stop']} is not after frames.start {frames['start']} "
                         "(expected start < stop)")
    return frames


def _check_cameras(cameras: Any, path: Path) -> list[str]:
    """The ``cameras:`` list: the calibrated cameras to use, by name, at least one and each once."""
    if (not isinstance(cameras, list) or not cameras
            or not all(isinstance(name, str) and name.strip() for name in cameras)):
        raise InputError(f"{path}: cameras is {cameras!r} (expected a list of camera names, such as [cam1, cam2])")
    repeated = sorted({name for name in cameras if cameras.count(name) > 1})
    if repeated:
        raise InputError(f"{path}: cameras names {repeated[0]!r} twice (expected each camera once)")
    return list(cameras)


def _check_frame_offsets(offsets: Any, path: Path) -> dict[str, int]:
    """The ``frame_offsets:`` mapping: per camera named, the whole number of frames its media run behind the
    others' (its frame f + offset shows what the others' frame f shows; negative: ahead)."""
    if (not isinstance(offsets, dict) or not offsets
            or not all(isinstance(name, str) and name.strip() for name in offsets)):
        raise InputError(f"{path}: frame_offsets is {offsets!r} (expected a mapping of camera names to whole "
                         "numbers of frames, such as {cam2: 1})")
    for name, offset in offsets.items():
        if not isinstance(offset, int) or isinstance(offset, bool):
            raise InputError(f"{path}: frame_offsets.{name} is {offset!r} (expected a whole number of frames, "
                             "positive when the camera's media run behind the others')")
    return {name: int(offset) for name, offset in offsets.items() if offset != 0}


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _reject_unknown(section: dict, known: tuple[str, ...], path: Path, prefix: str) -> None:
    """Refuse keys we do not read: a typo (``volum:``) would otherwise be silently ignored."""
    for key in section:
        if key not in known:
            raise InputError(f"{path}: unknown key {prefix + str(key)!r} "
                             f"(expected one of {', '.join(prefix + name for name in known)})")


def _check_volume(volume: Any, path: Path) -> dict:
    if not isinstance(volume, dict) or set(volume) != {"min", "max"}:
        raise InputError(f"{path}: volume is {volume!r} "
                         "(expected a mapping with min: [x, y, z] and max: [x, y, z])")
    corners = []
    for key in ("min", "max"):
        corner = volume[key]
        if not isinstance(corner, list) or len(corner) != 3 or not all(_is_number(v) for v in corner):
            raise InputError(f"{path}: volume.{key} is {corner!r} (expected three numbers in metres)")
        corners.append([float(v) for v in corner])
    if not all(lo < hi for lo, hi in zip(*corners, strict=True)):
        raise InputError(f"{path}: volume.min {corners[0]} is not below volume.max {corners[1]} "
                         "(expected min < max on every axis)")
    return {"min": corners[0], "max": corners[1]}
