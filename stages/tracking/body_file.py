"""Body files: the YAML description of an articulated body (`bodies/default.yaml` documents the layout).

A body file lists the segments (name, parent, joint centre, DOFs with their axes and limits), the
ellipsoids each segment carries (Horaud et al. 2009, Sec. 2.2: a long-axis chord and two radii), where
the 17 joints of `stages.joints` sit, and the length groups whose factors the tracker may estimate, all
as fractions of the standing height `height_m`. Bodies shipped with the tracker are named by their file
stem ("default", "paper"); any other body file is named by its path.
"""

from __future__ import annotations

from importlib import resources

import numpy as np
import yaml

from calib.errors import InputError
from stages.joints import JOINT_NAMES
from stages.tracking.body import BodyModel, lineage

ROOT_DOF_NAMES = ("tx", "ty", "tz", "yaw", "pitch", "roll")
# Segment-length factors vary between adults by a few per cent of the population's proportions; this
# is the standard deviation of the prior on ln ℓ towards 0 (the body file's proportions) of a length
# group whose entry gives no `prior_sd`.
LENGTH_PRIOR_SD = 0.06
# Root rotation order: yaw about world z, then pitch about the body's (negative) right axis so that a
# positive pitch leans forward, then roll about the forward axis. Its gimbal lock (pitch = ±90°, body
# lying face down) is far from the upright motions tracked here.
_ROOT_AXES = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1], [-1, 0, 0], [0, 1, 0]], dtype=float)
_AXIS_WORDS = {"x": (1, 0, 0), "y": (0, 1, 0), "z": (0, 0, 1),
               "-x": (-1, 0, 0), "-y": (0, -1, 0), "-z": (0, 0, -1)}



def load_body(name: str = "default", *, height_m: float | None = None) -> BodyModel:
    """A body shipped with the tracker, by name (`bodies/<name>.yaml`), scaled to `height_m` if given.

    A body file of the user's, named by its path, is read by the pipeline (`pipeline.io.body_io`), which
    owns the disk, and parsed by `body_from_text`.

    Raises
    ------
    InputError
        If no body of that name is shipped (one line listing those that are).
    """
    files = resources.files("stages.tracking") / "bodies"
    shipped = files / f"{name}.yaml"
    if is_body_path(name) or not shipped.is_file():
        known = sorted(p.name[:-5] for p in files.iterdir() if p.name.endswith(".yaml"))
        raise InputError(f"body {name!r}: no such body configuration, expected one of {known} "
                         "(a body file given by its path is read by pipeline.io.body_io.tracking_body)")
    body = body_from_text(shipped.read_text(), source=f"bodies/{name}.yaml")
    return body if height_m is None else body.scaled(height_m)


def body_from_text(text: str, *, source: str) -> BodyModel:
    """The body described by the text of a body file (YAML, safe-loaded); `source` names it in errors.

    Raises
    ------
    InputError
        If the text is not YAML or not a body description (one line naming `source`).
    """
    try:
        spec = yaml.load(text, Loader=_SAFE_LOADER)
    except yaml.YAMLError as error:
        first_line = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise InputError(f"{source}: not valid YAML ({first_line}), expected a body description") from None
    return body_from_dict(spec, source=source)


def is_body_path(name: str) -> bool:
    """Whether a body is named by a file path rather than by a shipped body's name."""
    return "/" in name or "\\" in name or name.endswith((".yaml", ".yml"))


# libyaml's safe loader when PyYAML has it (a body file parses several times faster), else PyYAML's own;
# both build the same values.
_SAFE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def body_from_dict(spec: dict, *, source: str = "body") -> BodyModel:
    """Build a BodyModel from the YAML structure described in `bodies/default.yaml`."""
    try:
        return _body_from_dict(spec)
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as err:
        if isinstance(err, InputError):
            raise
        raise InputError(f"{source}: malformed body description ({err!r}), expected the layout of "
                         "bodies/default.yaml") from err


def _body_from_dict(spec: dict) -> BodyModel:
    """The body of a parsed body file: the tree, its DOFs, the ellipsoids, the length groups and the joints."""
    H = float(spec["height_m"])
    segments = spec["segments"]
    names = tuple(s["name"] for s in segments)
    index = {n: i for i, n in enumerate(names)}
    parent = np.array([-1 if s["parent"] is None else index[s["parent"]] for s in segments])
    if parent[0] != -1 or np.any(parent[1:] < 0) or np.any(parent[1:] >= np.arange(1, len(names))):
        raise ValueError("segments must start with the root and list every parent before its children")
    joint = np.array([s["joint"] for s in segments], dtype=float) * H  # zero-pose world positions
    offset = joint - np.where(parent[:, None] >= 0, joint[np.maximum(parent, 0)], joint)
    offset[0] = 0.0
    dofs = _dofs(segments, parent)

    e_seg, e_rot, e_centre, e_axes = [], [], [], []
    for e in spec["ellipsoids"]:
        s = index[e["segment"]]
        start, end = np.array(e["from"], float) * H, np.array(e["to"], float) * H
        R, semi = _ellipsoid_frame(end - start, np.array(e["radii"], float) * H)
        e_seg.append(s)
        e_rot.append(R)
        e_centre.append(0.5 * (start + end) - joint[s])
        e_axes.append(semi)

    groups = spec.get("lengths", {})
    j_seg, j_off = [], []
    for name in JOINT_NAMES:
        j = spec["joints"][name]
        s = index[j["segment"]]
        j_seg.append(s)
        j_off.append(np.array(j["at"], float) * H - joint[s])

    return BodyModel(
        name=str(spec["name"]), height_m=H, segment_names=names, parent=parent, offset=offset, **dofs,
        ellipsoid_segment=np.array(e_seg), ellipsoid_rotation=np.array(e_rot), ellipsoid_centre=np.array(e_centre),
        semi_axes=np.array(e_axes), standing_root=joint[0], joint_segment=np.array(j_seg),
        joint_offset=np.array(j_off), length_groups=tuple(groups), length_factors=np.ones(len(groups)),
        **_length_groups(groups, index, np.array(e_seg), len(names)),
        length_prior_sd=np.array([float(entry.get("prior_sd", LENGTH_PRIOR_SD)) for entry in groups.values()]))


def _dofs(segments: list, parent: np.ndarray) -> dict:
    """The DOF fields of `BodyModel` (names, segments, axes, limits, priors, `moves`) from the segments' entries."""
    dof_names, dof_seg, axes, revolute, lo, hi, prior = [], [], [], [], [], [], []
    for s, seg in enumerate(segments):
        if seg["dofs"] == "root":
            for k, dof in enumerate(ROOT_DOF_NAMES):
                dof_names.append(f"{seg['name']}.{dof}")
                dof_seg.append(s)
                axes.append(_ROOT_AXES[k])
                revolute.append(k >= 3)
                lo.append(-np.inf)
                hi.append(np.inf)
                prior.append(0.0)
            continue
        for dof in seg["dofs"]:
            dof_names.append(f"{seg['name']}.{dof['name']}")
            dof_seg.append(s)
            axes.append(_AXIS_WORDS[dof["axis"]])
            revolute.append(True)
            lo.append(np.radians(float(dof["min"])))
            hi.append(np.radians(float(dof["max"])))
            prior.append(float(dof.get("prior", 0.0)))
    dof_seg = np.array(dof_seg, dtype=int)
    moves = lineage(parent)[dof_seg]  # every DOF of a segment and of its ancestors moves it
    return dict(dof_names=tuple(dof_names), dof_segment=dof_seg, dof_axis=np.array(axes, dtype=float),
                dof_revolute=np.array(revolute), lower=np.array(lo), upper=np.array(hi),
                prior_weight=np.array(prior), moves=moves)


def _length_groups(groups: dict, index: dict, e_seg: np.ndarray, S: int) -> dict:
    """The length-group fields of `BodyModel` (which of the S segments, the ellipsoids and joints each group
    scales)."""
    length_group, length_axis = np.full(S, -1), np.zeros((S, 3))
    girth_group = np.full(len(e_seg), -1)
    joint_group, joint_axis = np.full(S, -1), np.zeros((S, 3))
    for g, entry in enumerate(groups.values()):
        for seg in entry["segments"]:
            if entry["axis"] == "girth":
                girth_group[e_seg == index[seg]] = g
                continue
            if entry.get("scales", "segment") == "joint":
                joint_group[index[seg]] = g
                joint_axis[index[seg]] = _AXIS_WORDS[entry["axis"]]
                continue
            length_group[index[seg]] = g
            length_axis[index[seg]] = _AXIS_WORDS[entry["axis"]]
    return dict(length_group=length_group, length_axis=length_axis, girth_group=girth_group,
                joint_group=joint_group, joint_axis=joint_axis)


def _ellipsoid_frame(long_axis: np.ndarray, radii: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axes (3, 3) (columns a, b, c) and semi-axes (3,) of an ellipsoid given by its long-axis chord."""
    length = np.linalg.norm(long_axis)
    if length <= 0 or np.any(radii <= 0):
        raise ValueError("an ellipsoid needs distinct tips and positive radii")
    a_dir = long_axis / length
    ref = np.array([0.0, 1.0, 0.0]) if abs(a_dir[0]) > 0.9 else np.array([1.0, 0.0, 0.0])
    b_dir = ref - a_dir * (ref @ a_dir)
    b_dir /= np.linalg.norm(b_dir)
    c_dir = np.cross(a_dir, b_dir)
    return np.column_stack([a_dir, b_dir, c_dir]), np.array([0.5 * length, radii[0], radii[1]])
