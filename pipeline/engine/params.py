"""Stage parameters from the command line: ``--config params.yaml`` and ``--set stage.param=value``.

Each stage's parameters are one frozen dataclass (``SilhouetteParams``, ``TrackerParams``, ...) whose
defaults are the defaults. The configuration mirrors them: one section per stage name, one key per
field, nested dataclasses as nested sections::

    silhouettes:
      strong_threshold: 10
    tracking:
      max_iterations: 20

Overrides are validated against the dataclass fields before any work starts: an unknown stage or
key, or a value of the wrong type, is an :class:`InputError` naming where it came from and listing
what is valid. Values are parsed as YAML without aliases (:mod:`pipeline.io.plain_yaml`; ``--set a.b=0.5`` gives a
float, ``=true`` a bool, ``=[1, 2]`` a list; ``1e-6``, a string in YAML 1.1, is accepted for a float).
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import yaml

from calib.errors import InputError
from pipeline.io import plain_yaml


def default_params(stages: Iterable[Any]) -> dict[str, Any]:
    """Stage name -> default parameters (an instance of its ``params_type``, or ``None``)."""
    return {stage.name: stage.params_type() if stage.params_type else None for stage in stages}


def read_config(path: str | Path) -> dict:
    """Read a ``--config`` YAML file: a mapping from stage name to that stage's parameters."""
    path = Path(path)
    try:
        config = plain_yaml.load(path.read_text(encoding="utf-8"), str(path))
    except OSError as error:
        raise InputError(f"{path}: cannot read ({error.strerror}) "
                         "(expected a YAML file of parameters)") from None
    except (yaml.YAMLError, UnicodeDecodeError) as error:
        raise InputError(f"{path}: not valid YAML ({plain_yaml.describe_error(error)}) "
                         "(expected stage: {param: value})") from None
    if config is None:
        return {}
    if not isinstance(config, dict) or not all(isinstance(section, dict) for section in config.values()):
        raise InputError(f"{path}: expected a mapping of stage names to mappings of parameters")
    return config


def parse_assignments(assignments: Iterable[str]) -> dict:
    """``["tracking.em.max_iterations=50", ...]`` -> ``{"tracking": {"em": {"max_iterations": 50}}}``."""
    nested: dict = {}
    for text in assignments:
        key, equals, value = text.partition("=")
        path = key.strip().split(".")
        if not equals or len(path) < 2 or not all(path):
            raise InputError(f"--set {text}: malformed "
                             "(expected stage.param=value, e.g. silhouettes.strong_threshold=10)")
        try:
            parsed = plain_yaml.load(value, f"--set {text}")
        except yaml.YAMLError:
            raise InputError(f"--set {text}: the value is not valid YAML (expected a number, "
                             "true/false, a string or a [list])") from None
        section = nested
        for name in path[:-1]:
            section = section.setdefault(name, {})
            if not isinstance(section, dict):
                raise InputError(f"--set {text}: {name} was already given a value "
                                 "(expected one value per key)")
        section[path[-1]] = parsed
    return nested


def apply_overrides(params: Mapping[str, Any], overrides: Mapping[str, Any], *,
                    source: str) -> dict[str, Any]:
    """``params`` with ``overrides`` (stage -> {field: value}) applied and validated.

    ``source`` names where the overrides come from (``"--set"``, a file path) for error messages.
    """
    result = dict(params)
    for stage_name, values in overrides.items():
        if stage_name not in result:
            raise InputError(f"{source} {stage_name}: unknown stage (expected one of {', '.join(result)})")
        if result[stage_name] is None:
            if values:
                raise InputError(f"{source} {stage_name}: this stage takes no parameters (expected none)")
            continue
        if not isinstance(values, Mapping):
            raise InputError(f"{source} {stage_name}: {values!r} (expected a mapping of parameters)")
        result[stage_name] = _replace(result[stage_name], values, f"{source} {stage_name}")
    return result


def read_overrides(config: str | Path | None, assignments: Iterable[str]) -> list[tuple[str, dict]]:
    """What ``--config`` and ``--set`` ask for, in the order they apply: ``(source, {stage: {param: value}})``
    pairs for :func:`apply_all`, read and parsed but not yet checked against the stages' parameters.

    Plain data, so that a process that only hands them on (a batch's, to its worker processes) need not import
    the stages whose parameter classes they become.
    """
    overrides = [(f"{config}:", read_config(config))] if config is not None else []
    return overrides + [("--set", parse_assignments(assignments))]


def apply_all(params: Mapping[str, Any], overrides: Iterable[tuple[str, Mapping[str, Any]]]) -> dict[str, Any]:
    """``params`` with each of ``overrides`` (source, values) applied in turn (:func:`apply_overrides`)."""
    result = dict(params)
    for source, values in overrides:
        result = apply_overrides(result, values, source=source)
    return result


def params_to_dict(params: Any) -> dict | None:
    """Plain-data form of a parameter dataclass (tuples become lists), for JSON and cache keys."""
    if params is None:
        return None
    return _plain(dataclasses.asdict(params))


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    return value


def _replace(params: Any, values: Mapping[str, Any], where: str) -> Any:
    """``dataclasses.replace(params, **values)`` with each value checked against its field's type."""
    fields = {field.name: field for field in dataclasses.fields(params) if field.init}
    hints = typing.get_type_hints(type(params))
    changes = {}
    for key, value in values.items():
        if key not in fields:
            raise InputError(f"{where}.{key}: unknown parameter (expected one of {', '.join(fields)})")
        current = getattr(params, key)
        if dataclasses.is_dataclass(current) and isinstance(value, Mapping):
            changes[key] = _replace(current, value, f"{where}.{key}")
        else:
            changes[key] = _coerce(value, hints[key], f"{where}.{key}")
    try:
        return dataclasses.replace(params, **changes)
    except (ValueError, TypeError) as error:  # the dataclass's own validation (__post_init__)
        raise InputError(f"{where}: {error}") from None


_NO_MATCH = object()


def _coerce(value: Any, hint: Any, where: str) -> Any:
    """``value`` converted to the annotated type ``hint``, or an :class:`InputError`."""
    converted = _convert(value, hint)
    if converted is _NO_MATCH:
        raise InputError(f"{where}: {value!r} is not valid (expected {_describe(hint)})")
    return converted


def _convert(value: Any, hint: Any) -> Any:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any:
        return value
    if hint is type(None):
        return None if value is None else _NO_MATCH
    if origin in (typing.Union, types.UnionType):
        for arm in args:
            converted = _convert(value, arm)
            if converted is not _NO_MATCH:
                return converted
        return _NO_MATCH
    if origin is typing.Literal:
        return value if value in args else _NO_MATCH
    if hint is bool:
        return value if isinstance(value, bool) else _NO_MATCH
    if hint is int:
        return value if isinstance(value, int) and not isinstance(value, bool) else _NO_MATCH
    if hint is float:
        if isinstance(value, str):  # YAML 1.1 reads 1e-6 (no dot) as a string
            try:
                return float(value)
            except ValueError:
                return _NO_MATCH
        return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else _NO_MATCH
    if hint is str:
        return value if isinstance(value, str) else _NO_MATCH
    if hint is tuple or origin is tuple:
        if not isinstance(value, (list, tuple)):
            return _NO_MATCH
        if not args:
            return tuple(value)
        arms = [args[0]] * len(value) if len(args) == 2 and args[1] is Ellipsis else list(args)
        if len(arms) != len(value):
            return _NO_MATCH
        items = [_convert(item, arm) for item, arm in zip(value, arms, strict=True)]
        return _NO_MATCH if any(item is _NO_MATCH for item in items) else tuple(items)
    return value  # a type we do not check (the dataclass's __post_init__ may)


def _describe(hint: Any) -> str:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_describe(arm) for arm in args)
    if origin is typing.Literal:
        return "one of " + ", ".join(repr(arg) for arg in args)
    if hint is type(None):
        return "null"
    if origin is tuple:
        return f"a list like {hint}".replace("typing.", "")
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(
        hint, getattr(hint, "__name__", str(hint)))
