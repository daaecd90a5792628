"""Small checks shared by the calibration readers: turn raw file values into arrays or InputError."""

from __future__ import annotations

import numpy as np

from calib.camera import Camera, Rig
from calib.errors import InputError


def numbers(value, shape: tuple[int, ...], where: str) -> np.ndarray:
    """``value`` as a float64 array of ``shape``; ``where`` names the file and key for the error."""
    try:
        array = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{where}: expected numbers of shape {shape}, got {value!r}") from None
    if array.size != int(np.prod(shape)):
        count = int(np.prod(shape))
        raise InputError(f"{where}: expected {count} numbers (shape {shape}), got shape {array.shape}")
    return array.reshape(shape)


def distortion(value, where: str) -> np.ndarray:
    """(5,) OpenCV distortion ``(k1, k2, p1, p2, k3)`` from 1, 4 or 5 numbers (missing terms are zero).

    Files store one value (radial k1 only), four (no k3) or five; a longer vector would be a
    rational or thin-prism model that ``Camera`` does not represent, so it is rejected.
    """
    try:
        array = np.array(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(f"{where}: expected 1, 4 or 5 distortion coefficients, got {value!r}") from None
    if array.size not in (1, 4, 5):
        raise InputError(f"{where}: expected 1, 4 or 5 distortion coefficients got {array.size}")
    return np.concatenate([array, np.zeros(5 - array.size)])


def image_size(value, where: str) -> tuple[int, int]:
    """``(width, height)`` from two integral numbers."""
    array = numbers(value, (2,), where)
    if np.any(array != np.round(array)) or np.any(array <= 0):
        raise InputError(f"{where}: expected two positive integers (width, height), got {array.tolist()}")
    return int(array[0]), int(array[1])


def camera(where: str, **fields) -> Camera:
    """``Camera(**fields)``, with a validation error prefixed by ``where`` (the file and key it came from)."""
    try:
        return Camera(**fields)
    except InputError as error:
        raise InputError(f"{where}: {error}") from None


def rig(where: str, cameras: list[Camera]) -> Rig:
    """``Rig(cameras)``, with a validation error (duplicate names) prefixed by ``where`` (the file)."""
    try:
        return Rig(tuple(cameras))
    except InputError as error:
        raise InputError(f"{where}: {error}") from None
