"""The tracker's compiled loops (`stages.tracking.compiled`) as the rest of the tracker calls them.

Each function here is one of `compiled`'s entry points: numba's just-in-time version unless a build of the same
functions made ahead of time is installed (:func:`install`). numba costs a process about half a second of one core
before its first call even when its disk cache holds the machine code (its import and its typing tables, once per
process), where an extension module built ahead of time imports in a millisecond; the pipeline builds one during
the set-up and installs it before tracking (`pipeline.compiled_cache`). Without one, `compiled` (and numba) is
imported at the first call, not when this module is.

A built function accepts only the argument types it was built for and does not check them: a float32 array would
be read as float64 bytes. So each call to an installed function is first checked against the signatures it was
built for (:class:`ArrayType` and scalar names, :func:`checker`), and a call that none fits goes to numba's version
instead, which compiles for the new types as it always has.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

#: The functions of `compiled` that the tracker calls from Python (the others are compiled into them).
ENTRY_POINTS = ("e_step", "log_evidence", "hypothesis_scores", "shapes", "residuals", "length_columns",
                "normal_equations", "whitened_norm2", "extra_normal_equations", "pose_normal_equations",
                "noisy_covariance", "posed_body", "posed_ellipsoids")
#: Scalar argument types a build may take, each with the Python and numpy types that convert to it exactly.
SCALARS = {"float64": (float, int, np.floating, np.integer), "int64": (int, np.integer), "bool": (bool, np.bool_)}


@dataclass(frozen=True)
class ArrayType:
    """An array argument of a built function: its dtype, dimensions, and whether it must be C-contiguous (numba's
    layout 'C'; otherwise 'A', any strides). Aligned, as numba's arrays are; writeable or not alike (no entry point
    writes into its arguments)."""

    dtype: np.dtype
    ndim: int
    contiguous: bool

    def __post_init__(self):
        object.__setattr__(self, "dtype", np.dtype(self.dtype))


#: A built function's argument types, in order: arrays and names of :data:`SCALARS`.
Signature = Sequence[ArrayType | str]


def checker(signature: Signature) -> Callable[..., bool]:
    """A function of ``len(signature)`` arguments telling whether they are of the types of ``signature``, with no
    conversion that could change a value: an ndarray itself (no subclass) of that dtype (numpy's dtypes of the
    native byte order are shared objects, compared by identity first) and dimension, aligned and, for a 'C'
    layout, C-contiguous; a scalar of one of its name's :data:`SCALARS` types.

    It runs before every call of a built function, where a loop over the signature cost more than most of the calls
    themselves; so it is generated as one expression, as `dataclasses` generates the methods it adds.
    """
    names = [f"a{k}" for k in range(len(signature))]
    scope: dict = {"ndarray": np.ndarray}
    terms = []
    for k, (kind, name) in enumerate(zip(signature, names, strict=True)):
        if isinstance(kind, str):
            scope[f"scalar{k}"] = SCALARS[kind]
            terms.append(f"isinstance({name}, scalar{k})")
        else:
            scope[f"dtype{k}"] = kind.dtype
            layout = " and flags.c_contiguous" if kind.contiguous else ""
            terms.append(f"{name}.__class__ is ndarray and {name}.ndim == {kind.ndim} and ({name}.dtype is dtype{k} "
                         f"or {name}.dtype == dtype{k}) and (flags := {name}.flags).aligned{layout}")
    exec(f"def check({', '.join(names)}):\n    return {' and '.join(terms) or 'True'}\n", scope)  # noqa: S102
    return scope["check"]


def _just_in_time(name: str) -> Callable:
    """numba's version of `compiled`'s function ``name`` (importing numba at the first such call)."""
    from stages.tracking import compiled

    return getattr(compiled, name)


def _numba_on_first_call(name: str) -> Callable:
    """A stand-in for ``name`` that, at its first call, puts numba's version in its place and calls it."""
    def call(*args):
        function = _just_in_time(name)
        globals()[name] = function
        return function(*args)

    call.__name__ = call.__qualname__ = name
    return call


def _checked(name: str, variants: Sequence[tuple[Signature, Callable]]) -> Callable:
    """``name`` calling the first built variant whose signature fits the arguments (:func:`checker`), else numba's
    version."""
    checked = [(len(signature), checker(signature), function) for signature, function in variants]

    def call(*args):
        for arity, fits, function in checked:
            if len(args) == arity and fits(*args):
                return function(*args)
        return _just_in_time(name)(*args)

    call.__name__ = call.__qualname__ = name
    return call


def install(built: Mapping[str, Sequence[tuple[Signature, Callable]]]) -> None:
    """Call the built variants of each entry point in ``built`` from now on (each with its signature, tried in
    order); the entry points it does not name keep numba's version."""
    unknown = set(built) - set(ENTRY_POINTS)
    if unknown:
        raise ValueError(f"not entry points of stages.tracking.compiled: {sorted(unknown)}")
    for name in ENTRY_POINTS:
        globals()[name] = _checked(name, built[name]) if built.get(name) else _numba_on_first_call(name)
    _built.clear()
    _built.update({name: variants for name, variants in built.items() if variants})


def uninstall() -> None:
    """Back to numba's versions of every entry point."""
    install({})


def installed() -> bool:
    """Whether a build made ahead of time is installed (for at least one entry point)."""
    return bool(_built)


#: The installed build's variants by entry point (empty: numba's versions throughout).
_built: dict[str, Sequence[tuple[Signature, Callable]]] = {}
uninstall()
