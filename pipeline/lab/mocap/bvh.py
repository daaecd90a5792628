"""BVH files: the joint hierarchy, the motion channels and the length unit inferred from the rest pose."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib.errors import InputError
from pipeline.lab.mocap.raw import INCH_M, RawClip, euler_rotations

# A rest skeleton's height (lowest to highest point, in metres) expected when inferring a BVH file's unit.
TYPICAL_REST_HEIGHT_M = 1.7
BVH_CANDIDATE_UNITS_M = {
    "m": 1.0,
    "cm": 0.01,
    "mm": 0.001,
    "inch": INCH_M,
    "CMU ASF unit": INCH_M / 0.45,
}


_BVH_CHANNELS = ("xposition", "yposition", "zposition", "xrotation", "yrotation", "zrotation")


@dataclass
class _BvhJoint:
    name: str
    parent: int
    offset: np.ndarray  # (3,) file units
    channels: tuple[str, ...]
    end_site: np.ndarray | None = None  # (3,) offset of the End Site, if any


class _Tokens:
    """Whitespace tokens of a BVH hierarchy with their line numbers, for error messages."""

    def __init__(self, path: Path, lines: Sequence[str]):
        self.path = path
        self.items = [(token, number) for number, line in enumerate(lines, start=1) for token in line.split()]
        self.position = 0

    def next(self, what: str) -> tuple[str, int]:
        if self.position >= len(self.items):
            raise InputError(f"{self.path}: file ends inside the HIERARCHY; expected {what}")
        item = self.items[self.position]
        self.position += 1
        return item

    def expect(self, word: str) -> int:
        token, line = self.next(f"'{word}'")
        if token.upper() != word.upper():
            raise InputError(f"{self.path}:{line}: expected '{word}', got '{token}'")
        return line

    def numbers(self, count: int, what: str) -> np.ndarray:
        values = []
        for _ in range(count):
            token, line = self.next(what)
            try:
                values.append(float(token))
            except ValueError:
                raise InputError(f"{self.path}:{line}: {what}: expected a number, got '{token}'") from None
        return np.array(values)


def _parse_bvh_joint(tokens: _Tokens, joints: list[_BvhJoint], parent: int) -> None:
    """Parse ``name { OFFSET ... CHANNELS ... (JOINT ... | End Site {...})* }`` after ROOT/JOINT."""
    name, _ = tokens.next("a joint name")
    tokens.expect("{")
    tokens.expect("OFFSET")
    offset = tokens.numbers(3, f"OFFSET of joint '{name}'")
    tokens.expect("CHANNELS")
    count_token, line = tokens.next("a channel count")
    if not count_token.isdigit():
        raise InputError(
            f"{tokens.path}:{line}: CHANNELS of joint '{name}': expected a count, got '{count_token}'"
        )
    channels = []
    for _ in range(int(count_token)):
        channel, line = tokens.next("a channel name")
        if channel.lower() not in _BVH_CHANNELS:
            raise InputError(
                f"{tokens.path}:{line}: unknown channel '{channel}' of joint '{name}'; "
                f"expected X/Y/Z position or rotation"
            )
        channels.append(channel.lower())
    joint = _BvhJoint(name, parent, offset, tuple(channels))
    joints.append(joint)
    me = len(joints) - 1
    while True:
        token, line = tokens.next("JOINT, End Site or '}'")
        keyword = token.upper()
        if keyword == "}":
            return
        if keyword == "JOINT":
            _parse_bvh_joint(tokens, joints, me)
        elif keyword == "END":
            tokens.expect("Site")
            tokens.expect("{")
            tokens.expect("OFFSET")
            joint.end_site = tokens.numbers(3, f"End Site OFFSET of joint '{name}'")
            tokens.expect("}")
        else:
            raise InputError(
                f"{tokens.path}:{line}: unexpected '{token}' in joint '{name}'; "
                f"expected JOINT, End Site or '}}'"
            )


def _infer_bvh_unit(rest_points: np.ndarray, path: Path) -> float:
    """Metres per unit making the rest skeleton (Y-up, file units) closest to a typical human height."""
    height = float(np.ptp(rest_points[:, 1]))
    if height <= 0:
        raise InputError(
            f"{path}: the rest skeleton has no height; pass length_unit_m to give the file's unit"
        )
    return min(
        BVH_CANDIDATE_UNITS_M.values(),
        key=lambda unit: abs(math.log(height * unit / TYPICAL_REST_HEIGHT_M)),
    )


def read_bvh(path: Path, length_unit_m: float | None) -> RawClip:
    lines = path.read_text(errors="replace").splitlines()
    motion_line = next((k for k, line in enumerate(lines) if line.strip().upper() == "MOTION"), None)
    if motion_line is None:
        raise InputError(f"{path}: no MOTION section; expected a BVH file (HIERARCHY ... MOTION ...)")
    tokens = _Tokens(path, lines[:motion_line])
    tokens.expect("HIERARCHY")
    tokens.expect("ROOT")
    joints: list[_BvhJoint] = []
    _parse_bvh_joint(tokens, joints, -1)
    if tokens.position != len(tokens.items):
        _, line = tokens.items[tokens.position]
        raise InputError(f"{path}:{line}: text after the root joint; expected MOTION (one ROOT only)")
    names = [joint.name for joint in joints]
    duplicates = sorted({name for name in names if names.count(name) > 1})
    if duplicates:
        raise InputError(f"{path}: duplicate joint names {', '.join(duplicates)}; expected unique names")

    n_frames, frame_time, values = _parse_bvh_motion(
        path, lines, motion_line, sum(len(j.channels) for j in joints)
    )

    parents = np.array([joint.parent for joint in joints])
    rest_origins = np.zeros((len(joints), 3))
    for k, joint in enumerate(joints):
        rest_origins[k] = joint.offset + (rest_origins[joint.parent] if joint.parent >= 0 else 0.0)
    rest_ends = rest_origins.copy()
    for k, joint in enumerate(joints):
        children = np.flatnonzero(parents == k)
        if joint.end_site is not None and len(children) == 0:
            rest_ends[k] = rest_origins[k] + joint.end_site
        elif len(children):
            rest_ends[k] = rest_origins[children].mean(axis=0)
    unit = (
        length_unit_m
        if length_unit_m is not None
        else _infer_bvh_unit(np.vstack([rest_origins, rest_ends]), path)
    )
    rest_origins, rest_ends = rest_origins * unit, rest_ends * unit

    rotations = np.empty((n_frames, len(joints), 3, 3))
    root_positions = np.zeros((n_frames, 3))
    column = 0
    for k, joint in enumerate(joints):
        columns = {channel: column + i for i, channel in enumerate(joint.channels)}
        column += len(joint.channels)
        if k == 0:
            for axis_index, axis in enumerate("xyz"):
                if f"{axis}position" in columns:
                    root_positions[:, axis_index] = values[:, columns[f"{axis}position"]] * unit
        rotation_channels = [c for c in joint.channels if c.endswith("rotation")]
        # BVH lists rotations outermost first, so the first listed is leftmost: reverse for euler_rotations.
        axes = "".join(c[0] for c in reversed(rotation_channels))
        angles = np.radians(values[:, [columns[c] for c in reversed(rotation_channels)]])
        local = euler_rotations(axes, angles) if axes else np.broadcast_to(np.eye(3), (n_frames, 3, 3))
        rotations[:, k] = local if joint.parent < 0 else rotations[:, joint.parent] @ local
    return RawClip(
        1.0 / frame_time, tuple(names), parents, rest_origins, rest_ends, rotations, root_positions
    )


def _parse_bvh_motion(path: Path, lines: Sequence[str], motion_line: int, n_channels: int):
    """Frame count, frame time (s) and the (F, channels) values of the MOTION section."""
    header = {}
    body_start = motion_line + 1
    for key in ("frames", "frame time"):
        while body_start < len(lines) and not lines[body_start].strip():
            body_start += 1
        line_number = body_start + 1
        text = lines[body_start] if body_start < len(lines) else ""
        label, _, value = text.partition(":")
        if label.strip().lower() != key:
            raise InputError(
                f"{path}:{line_number}: expected '{key.capitalize()}: <number>', got '{text.strip()}'"
            )
        try:
            header[key] = float(value)
        except ValueError:
            raise InputError(
                f"{path}:{line_number}: {key}: expected a number, got '{value.strip()}'"
            ) from None
        body_start += 1
    n_frames = int(header["frames"])
    if n_frames < 1 or header["frames"] != n_frames:
        raise InputError(
            f"{path}:{motion_line + 2}: Frames: expected a positive whole number, got {header['frames']}"
        )
    if header["frame time"] <= 0:
        raise InputError(f"{path}:{motion_line + 3}: Frame Time: expected a positive number of seconds")
    rows = []
    for line_number, line in enumerate(lines[body_start:], start=body_start + 1):
        tokens = line.split()
        if not tokens:
            continue
        if len(tokens) != n_channels:
            raise InputError(
                f"{path}:{line_number}: {len(tokens)} values; expected {n_channels} (one per channel)"
            )
        try:
            rows.append([float(token) for token in tokens])
        except ValueError:
            raise InputError(f"{path}:{line_number}: expected numbers in the MOTION data") from None
    if len(rows) != n_frames:
        raise InputError(f"{path}: MOTION has {len(rows)} frames; the header says Frames: {n_frames}")
    return n_frames, header["frame time"], np.array(rows)
