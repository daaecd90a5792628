"""Checks of parameter values at the door: one-line :class:`InputError` messages, ``<where>: expected ..., got ...``.

A parameter dataclass calls these from ``__post_init__``, so that a wrong value (a negative iteration
count, a NaN width, an unknown choice) is refused before any work starts, not met as a traceback or a
silently wrong result in the middle of a run. ``bool`` is refused where a number is expected (Python
counts ``True`` as 1, a user writing ``true`` meant something else).
"""

from __future__ import annotations

import math
from collections.abc import Collection
from typing import Any

from calib.errors import InputError


def check_int(where: str, value: Any, minimum: int, maximum: int | None = None) -> None:
    """An integer (not a bool) from ``minimum`` to ``maximum`` (None: no upper bound)."""
    if not (isinstance(value, int) and not isinstance(value, bool)
            and minimum <= value and (maximum is None or value <= maximum)):
        bound = f">= {minimum}" if maximum is None else f"from {minimum} to {maximum}"
        raise InputError(f"{where}: expected an integer {bound}, got {value!r}")


def check_number(where: str, value: Any, minimum: float = -math.inf, maximum: float = math.inf, *,
                 above: bool = False, infinite: bool = False) -> None:
    """A finite number (int or float, not a bool) from ``minimum`` to ``maximum``; ``above``: strictly
    greater than ``minimum``; ``infinite``: +inf is valid too (a threshold that inf turns off).

    NaN is always refused and infinities unless ``infinite``: NaN passes every comparison-based range
    check unnoticed, and an infinite width or count is no value a computation can use.
    """
    number = isinstance(value, (int, float)) and not isinstance(value, bool) and not math.isnan(value)
    finite = number and (math.isfinite(value) or (infinite and value == math.inf))
    if not (finite and (value > minimum if above else value >= minimum) and value <= maximum):
        described = _range(minimum, maximum, above) + (" (or inf)" if infinite else "")
        raise InputError(f"{where}: expected {described}, got {value!r}")


def check_choice(where: str, value: Any, choices: Collection[str]) -> None:
    """One of ``choices``."""
    if value not in choices:
        raise InputError(f"{where}: expected one of {', '.join(choices)}, got {value!r}")


def check_bool(where: str, value: Any) -> None:
    """``True`` or ``False`` (not 0/1, not a string)."""
    if not isinstance(value, bool):
        raise InputError(f"{where}: expected true or false, got {value!r}")


def _range(minimum: float, maximum: float, above: bool) -> str:
    low = f"{'>' if above else '>='} {minimum:g}" if minimum > -math.inf else ""
    if maximum == math.inf:
        return f"a finite number {low}".rstrip()
    if not low:
        return f"a finite number <= {maximum:g}"
    return f"a number {low} and <= {maximum:g}"
