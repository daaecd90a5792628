"""CMU ASF skeletons and AMC motions (the FK convention: :mod:`pipeline.lab.mocap.motion`'s docstring)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib.errors import InputError
from pipeline.lab.mocap.raw import INCH_M, RawClip, euler_rotations

# CMU captured at 120 Hz and AMC files do not store a rate.
AMC_FPS = 120.0


@dataclass(frozen=True)
class _AsfBone:
    name: str
    direction: np.ndarray  # (3,) unit, ASF frame
    length: float  # file units
    axis_rotation: np.ndarray  # (3, 3) C
    dofs: tuple[str, ...]  # e.g. ("rx", "ry", "rz")


def _numbers(tokens: Sequence[str], count: int, path: Path, line_number: int, what: str) -> list[float]:
    """``count`` floats from ``tokens``, or an InputError naming the file, line and field."""
    if len(tokens) < count:
        raise InputError(f"{path}:{line_number}: {what}: expected {count} numbers, got {len(tokens)}")
    try:
        return [float(token) for token in tokens[:count]]
    except ValueError:
        raise InputError(f"{path}:{line_number}: {what}: expected numbers, got {' '.join(tokens)}") from None


def _asf_axis_rotation(tokens: Sequence[str], path: Path, line_number: int, degrees: bool) -> np.ndarray:
    """The rotation ``C`` of an ASF ``axis a b c XYZ`` line (later-listed axis on the left)."""
    angles = _numbers(tokens, 3, path, line_number, "axis")
    order = tokens[3].lower() if len(tokens) > 3 else "xyz"
    if sorted(order) != ["x", "y", "z"]:
        raise InputError(f"{path}:{line_number}: axis order '{tokens[3]}': expected a permutation of XYZ")
    radians = np.radians(angles) if degrees else np.array(angles)
    by_axis = dict(zip("xyz", radians, strict=True))
    return euler_rotations(order, np.array([[by_axis[a] for a in order]]))[0]


def _parse_asf(path: Path):
    """Bones (root first, then file order), hierarchy, metres per unit, degrees flag, root channel order."""
    lines = path.read_text(errors="replace").splitlines()
    section = None
    metres_per_unit = INCH_M  # ASF default: length 1.0 means inches
    degrees = True
    root_order = ("tx", "ty", "tz", "rx", "ry", "rz")
    root_axis = np.eye(3)
    root_axis_order = "XYZ"
    bones: dict[str, _AsfBone] = {}
    parents: dict[str, str] = {}
    current: dict | None = None
    current_line = 0
    for line_number, line in enumerate(lines, start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        head = tokens[0].lower()
        if head.startswith(":"):
            section = head[1:]
            continue
        if section == "units":
            if head == "length":
                scale = _numbers(tokens[1:], 1, path, line_number, "length unit")[0]
                if scale <= 0:
                    raise InputError(f"{path}:{line_number}: length unit {scale}: expected a positive number")
                metres_per_unit = INCH_M / scale
            elif head == "angle":
                if len(tokens) < 2 or tokens[1].lower() not in ("deg", "rad"):
                    raise InputError(f"{path}:{line_number}: angle unit: expected 'deg' or 'rad'")
                degrees = tokens[1].lower() == "deg"
        elif section == "root":
            if head == "order":
                root_order = tuple(token.lower() for token in tokens[1:])
                if sorted(root_order) != sorted(("tx", "ty", "tz", "rx", "ry", "rz")):
                    raise InputError(
                        f"{path}:{line_number}: root order: expected TX TY TZ RX RY RZ in some order, got "
                        f"{' '.join(tokens[1:])}"
                    )
            elif head == "axis" and len(tokens) >= 2:
                root_axis_order = tokens[1]
            elif head == "orientation":
                root_axis = _asf_axis_rotation(tokens[1:4] + [root_axis_order], path, line_number, degrees)
        elif section == "bonedata":
            if head == "begin":
                current, current_line = {"dofs": ()}, line_number
            elif head == "end":
                if current is None:
                    raise InputError(f"{path}:{line_number}: 'end' without 'begin' in :bonedata")
                for field, key in (
                    ("name", "name"),
                    ("direction", "direction"),
                    ("length", "length"),
                    ("axis", "axis_rotation"),
                ):
                    if key not in current:
                        raise InputError(
                            f"{path}:{current_line}: bone block has no '{field}'; expected name, direction, "
                            f"length and axis"
                        )
                bones[current["name"]] = _AsfBone(**current)
                current = None
            elif current is not None:
                if head == "name" and len(tokens) >= 2:
                    current["name"] = tokens[1]
                elif head == "direction":
                    direction = np.array(_numbers(tokens[1:], 3, path, line_number, "direction"))
                    norm = np.linalg.norm(direction)
                    if norm == 0:
                        raise InputError(f"{path}:{line_number}: direction is zero; expected a unit vector")
                    current["direction"] = direction / norm
                elif head == "length":
                    current["length"] = _numbers(tokens[1:], 1, path, line_number, "length")[0]
                elif head == "axis":
                    current["axis_rotation"] = _asf_axis_rotation(tokens[1:], path, line_number, degrees)
                elif head == "dof":
                    dofs = tuple(token.lower() for token in tokens[1:])
                    unknown = [d for d in dofs if d not in ("rx", "ry", "rz")]
                    if unknown:
                        raise InputError(
                            f"{path}:{line_number}: dof {' '.join(unknown)}: expected rx, ry and/or rz"
                        )
                    current["dofs"] = dofs
        elif section == "hierarchy":
            if head in ("begin", "end"):
                continue
            for child in tokens[1:]:
                parents[child] = tokens[0]
    if not bones:
        raise InputError(f"{path}: no bones found; expected an ASF file with a :bonedata section")
    for child, parent in parents.items():
        for name in (child, parent):
            if name != "root" and name not in bones:
                raise InputError(f"{path}: hierarchy names bone '{name}' that :bonedata does not define")
    orphans = sorted(set(bones) - set(parents))
    if orphans:
        raise InputError(f"{path}: bones {', '.join(orphans)} are missing from :hierarchy")
    return bones, parents, metres_per_unit, degrees, root_order, root_axis


def _topological_order(parents: dict[str, str]) -> list[str]:
    """Bone names with every parent before its children, root first, children in hierarchy order."""
    children: dict[str, list[str]] = {}
    for child, parent in parents.items():
        children.setdefault(parent, []).append(child)
    order, stack = [], ["root"]
    while stack:
        name = stack.pop(0)
        order.append(name)
        stack[0:0] = children.get(name, [])
    return order


def read_asf_amc(asf_path: Path, amc_path: Path) -> RawClip:
    bones, parents, metres_per_unit, degrees, root_order, root_axis = _parse_asf(asf_path)
    names = _topological_order(parents)
    if len(names) != len(bones) + 1:
        raise InputError(f"{asf_path}: :hierarchy does not connect every bone to the root (a cycle?)")
    index = {name: k for k, name in enumerate(names)}
    parent_index = np.array([-1] + [index[parents[name]] for name in names[1:]])

    rest_origins = np.zeros((len(names), 3))
    rest_ends = np.zeros((len(names), 3))
    for k, name in enumerate(names[1:], start=1):
        bone = bones[name]
        rest_origins[k] = rest_ends[parent_index[k]]
        rest_ends[k] = rest_origins[k] + bone.length * metres_per_unit * bone.direction

    frames = _parse_amc(amc_path, bones, root_order)
    n_frames = len(frames)
    to_radians = math.pi / 180 if degrees else 1.0
    rotations = np.empty((n_frames, len(names), 3, 3))
    root_values = np.array([frame["root"] for frame in frames])  # (F, 6)
    translation_columns = [root_order.index(axis) for axis in ("tx", "ty", "tz")]
    root_positions = root_values[:, translation_columns] * metres_per_unit
    rotation_axes = "".join(channel[1] for channel in root_order if channel.startswith("r"))
    rotation_columns = [k for k, channel in enumerate(root_order) if channel.startswith("r")]
    M = euler_rotations(rotation_axes, root_values[:, rotation_columns] * to_radians)
    rotations[:, 0] = root_axis @ M @ root_axis.T
    for k, name in enumerate(names[1:], start=1):
        bone = bones[name]
        parent_rotation = rotations[:, parent_index[k]]
        if not bone.dofs:
            rotations[:, k] = parent_rotation
            continue
        values = np.array([frame[name] for frame in frames]) * to_radians  # (F, dofs)
        M = euler_rotations("".join(d[1] for d in bone.dofs), values)
        C = bone.axis_rotation
        rotations[:, k] = parent_rotation @ C @ M @ C.T
    return RawClip(AMC_FPS, tuple(names), parent_index, rest_origins, rest_ends, rotations, root_positions)


def _parse_amc(
    path: Path, bones: dict[str, _AsfBone], root_order: Sequence[str]
) -> list[dict[str, list[float]]]:
    """Per frame, each bone's dof values (root: its 6 channels in ``root_order``)."""
    expected_counts = {name: len(bone.dofs) for name, bone in bones.items() if bone.dofs}
    expected_counts["root"] = len(root_order)
    frames: list[dict[str, list[float]]] = []
    current: dict[str, list[float]] | None = None
    frame_line = 0

    def finish(frame: dict[str, list[float]], line_number: int) -> None:
        missing = sorted(set(expected_counts) - frame.keys())
        if missing:
            raise InputError(
                f"{path}:{line_number}: frame {len(frames) + 1} has no values for {', '.join(missing[:5])}; "
                f"expected a line per bone with dofs"
            )
        frames.append(frame)

    with path.open(errors="replace") as lines:
        for line_number, line in enumerate(lines, start=1):
            tokens = line.split()
            if not tokens or tokens[0].startswith(("#", ":")):
                continue
            if len(tokens) == 1 and tokens[0].isdigit():
                if current is not None:
                    finish(current, frame_line)
                current, frame_line = {}, line_number
                continue
            if current is None:
                raise InputError(f"{path}:{line_number}: bone values before the first frame number")
            name = tokens[0]
            if name not in expected_counts:
                if name in bones:  # a bone without dofs written with no values is harmless
                    continue
                raise InputError(
                    f"{path}:{line_number}: unknown bone '{name}'; expected a bone of the ASF skeleton"
                )
            count = expected_counts[name]
            if len(tokens) - 1 != count:
                raise InputError(
                    f"{path}:{line_number}: bone '{name}' has {len(tokens) - 1} values; expected {count}"
                )
            current[name] = _numbers(tokens[1:], count, path, line_number, f"bone '{name}'")
    if current is not None:
        finish(current, frame_line)
    if not frames:
        raise InputError(f"{path}: no frames found; expected an AMC file with numbered frames")
    return frames
