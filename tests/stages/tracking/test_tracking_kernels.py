"""`stages.tracking.kernels`: a built function is called only with the types it was built for, numba's otherwise."""

import numpy as np
import pytest

from stages.tracking import compiled, kernels
from stages.tracking.kernels import ArrayType

#: whitened_norm2(W (K, 3, 3), e (K, 3)) as a build records it.
NORM_SIGNATURE = (ArrayType("float64", 3, True), ArrayType("float64", 2, True))
#: The same built for float32 arrays: the tests' stand-in, so that the calls it does not take (float64, as the
#: tracker makes) reach numba at a signature its cache holds, and no test compiles another into it.
STAND_IN_SIGNATURE = (ArrayType("float32", 3, True), ArrayType("float32", 2, True))


@pytest.fixture
def stand_in():
    """whitened_norm2 "built" as a Python function that records its calls; numba's versions again afterwards."""
    calls = []

    def built(W, e):
        calls.append((W, e))
        return -1.0

    kernels.install({"whitened_norm2": [(STAND_IN_SIGNATURE, built)]})
    yield calls
    kernels.uninstall()


def _arguments(rng):
    return rng.normal(size=(6, 3, 3)), rng.normal(size=(6, 3))


def _fits(signature, args) -> bool:
    return kernels.checker(signature)(*args)


def test_a_checker_passes_only_the_exact_types():
    rng = np.random.default_rng(0)
    W, e = _arguments(rng)
    assert _fits(NORM_SIGNATURE, (W, e))
    assert not _fits(NORM_SIGNATURE, (W.astype(np.float32), e))  # dtype: would be read as float64 bytes
    assert not _fits(NORM_SIGNATURE, (W[..., 0], e))  # dimensions
    assert not _fits(NORM_SIGNATURE, (np.asfortranarray(W), e))  # layout
    assert not _fits(NORM_SIGNATURE, (W, e[::2]))  # strides
    assert not _fits(NORM_SIGNATURE, (W, e.tolist()))
    readonly = e.copy()
    readonly.flags.writeable = False
    assert _fits(NORM_SIGNATURE, (W, readonly))  # read only, as every entry point reads its arguments
    unaligned = np.frombuffer(bytearray(6 * 3 * 8 + 1), np.uint8)[1:].view(np.float64).reshape(6, 3)
    assert not unaligned.flags.aligned and not _fits(NORM_SIGNATURE, (W, unaligned))
    assert not _fits(NORM_SIGNATURE, (W, e.astype(">f8")))  # the other byte order
    assert _fits((ArrayType("float64", 2, False),), (e[::2],))  # layout 'A': any strides
    assert _fits(("float64", "int64", "bool"), (1.5, np.int64(3), True))
    assert _fits(("float64",), (2,))  # an int converts to a double exactly
    assert not _fits(("int64",), (2.0,))
    assert not _fits(("int64",), ("2",))


def test_an_installed_build_takes_the_calls_it_fits_and_numba_the_others(stand_in):
    assert kernels.installed()
    rng = np.random.default_rng(1)
    W, e = _arguments(rng)
    assert kernels.whitened_norm2(W.astype(np.float32), e.astype(np.float32)) == -1.0 and len(stand_in) == 1
    assert kernels.whitened_norm2(W, e) == compiled.whitened_norm2(W, e)
    assert len(stand_in) == 1  # the float64 call went to numba
    with pytest.raises(TypeError):  # numba's answer to a call of the wrong arity
        kernels.whitened_norm2(W)
    assert len(stand_in) == 1
    body_shapes = kernels.shapes(np.eye(3)[None].copy(), np.ones((1, 3)))  # not built: numba's
    np.testing.assert_allclose(body_shapes[0], compiled.shapes(np.eye(3)[None].copy(), np.ones((1, 3)))[0])


def test_uninstalling_returns_to_numba():
    kernels.install({"whitened_norm2": [(STAND_IN_SIGNATURE, lambda W, e: -1.0)]})
    kernels.uninstall()
    assert not kernels.installed()
    W, e = _arguments(np.random.default_rng(2))
    assert kernels.whitened_norm2(W, e) == compiled.whitened_norm2(W, e)
    assert kernels.whitened_norm2 is compiled.whitened_norm2  # the first call put numba's version in place


def test_only_entry_points_can_be_installed():
    with pytest.raises(ValueError, match="_mixture"):
        kernels.install({"_mixture": [((), lambda: None)]})
    assert not kernels.installed()
