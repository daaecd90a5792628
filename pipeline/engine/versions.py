"""A stage's code version: the package version plus a hash of the code and data its results depend on
(:func:`code_inputs`): the run function with the helpers and constants of its module it uses, and every file
of the modules and packages listed in ``Stage.code`` (data files such as the tracker's pose library
included)."""

from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
import inspect
import types
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.engine.stage import Stage

PACKAGE = "hnmocap"


def package_version() -> str:
    try:
        return importlib.metadata.version(PACKAGE)
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def declared_files(module: str) -> list[tuple[str, Path]]:
    """``(name, path)`` of the files a :attr:`Stage.code` entry stands for, names independent of where
    the repository lies.

    A module is its file; a package, or a folder of resources inside one (``pipeline.report.assets``),
    is every file under it, data as well as source: the pose library ``stages/tracking/data/poses.npz``
    defines the tracker's results as much as its code does. Caches (``__pycache__``) and hidden files
    are left out.
    """
    spec = importlib.util.find_spec(module)
    if spec is None:
        raise ValueError(f"Stage.code: no module named {module!r}")
    if not spec.submodule_search_locations:
        return [(module, Path(spec.origin))]
    return sorted((f"{module}/{path.relative_to(folder).as_posix()}", path)
                  for folder in map(Path, spec.submodule_search_locations) for path in folder.rglob("*")
                  if path.is_file() and not any(part == "__pycache__" or part.startswith(".")
                                                for part in path.relative_to(folder).parts))


@dataclass(frozen=True)
class CodeInputs:
    """What a stage's code version is made of (:func:`code_inputs`).

    Attributes
    ----------
    functions : tuple of function
        The run function and every function of its module that it uses, directly or through another.
    constants : tuple of (str, str)
        Name and ``repr`` of the plain values (numbers, strings, tuples of them) of that module they read.
    files : tuple of (str, Path)
        The files of the :attr:`Stage.code` entries (:func:`declared_files`).
    """

    functions: tuple[Callable, ...]
    constants: tuple[tuple[str, str], ...]
    files: tuple[tuple[str, Path], ...]


def code_inputs(stage: Stage) -> CodeInputs:
    """The code and data ``stage``'s results depend on.

    Run functions share a module (``pipeline/graph.py``) with other stages' run functions, so that module
    counts function by function: the run function, the functions of the module it names (found in the
    names its code, nested functions included, reads), theirs, and so on, with the plain constants
    they read. Everything else comes from :attr:`Stage.code`; tests/pipeline/test_graph.py runs each
    real stage under a profiler and fails when first-party code or data outside these runs.
    """
    namespace = stage.run.__globals__
    functions: dict[str, Callable] = {}
    constants: dict[str, str] = {}
    todo = [stage.run]
    while todo:
        function = todo.pop()
        if function.__qualname__ in functions:
            continue
        functions[function.__qualname__] = function
        for name in sorted(_names_read(function.__code__)):
            value = namespace.get(name)
            if inspect.isfunction(value) and value.__module__ == stage.run.__module__:
                todo.append(value)
            elif _is_plain(value):
                constants[name] = repr(value)
    files = tuple(entry for module in stage.code for entry in declared_files(module))
    return CodeInputs(tuple(functions[name] for name in sorted(functions)), tuple(sorted(constants.items())), files)


def _names_read(code: types.CodeType) -> set[str]:
    """Global (and attribute) names the code object and the code objects nested in it read."""
    names = set(code.co_names)
    for constant in code.co_consts:
        if isinstance(constant, types.CodeType):
            names |= _names_read(constant)
    return names


def _is_plain(value: Any) -> bool:
    """Whether ``value`` is data whose ``repr`` is the same in every process (no object addresses)."""
    if isinstance(value, (tuple, frozenset)):
        return all(_is_plain(item) for item in value)
    return value is not None and isinstance(value, (bool, int, float, str, bytes))


def code_version(stage: Stage) -> str:
    """Package version + hash of what :func:`code_inputs` finds: sources, constants, declared files."""
    inputs = code_inputs(stage)
    digest = hashlib.sha256()
    for function in inputs.functions:
        digest.update(f"{function.__qualname__}\0{inspect.getsource(function)}\0".encode())
    for name, value in inputs.constants:
        digest.update(f"{name}={value}\0".encode())
    for name, path in inputs.files:
        digest.update(name.encode() + b"\0" + path.read_bytes() + b"\0")
    return f"{package_version()}+{digest.hexdigest()[:16]}"
