"""The tracker's compiled code (`stages.tracking.compiled`) made ready before its first call: built ahead of time, or
loaded from numba's on-disk cache.

**Built ahead of time.** numba costs a process about half a second of one core before the first call even when its
cache holds the machine code: its own import and the typing tables it sets up. :func:`build_ahead_of_time`, run by
the warm-up (`python -m pipeline warmup`, part of the set-up), compiles the tracker's entry points with numba's
``pycc`` into an extension module that needs no numba and imports in a millisecond, for the argument types the
warm-up called them with; :func:`install_built` puts it behind `stages.tracking.kernels` when it was built from the
current compiled.py (its name carries a hash of that file and of numpy's version). ``pycc`` is numba's own
ahead-of-time compiler (pending deprecation in numba, which is pinned here): should it fail (no C compiler, a
numba without it), the warm-up says so and runs load numba's cache as below.

**numba's cache.** numba loads a cached function the first time it is called, at the types of that call: for the
tracker's entry points about 0.3 s of one core, most of it holding the interpreter's lock. Called lazily, that
load falls on the first tracked frame, when the run's cores are busy reconstructing. :func:`load_cached` loads
every signature the cache holds for the current source at a moment of the caller's choosing. Nothing is compiled
there: a signature the cache does not hold (an edited compiled.py, another numba) is left to the first call, which
compiles it as before. numba has no public call for "load what the cache holds"; this reads the cache's index
through the dispatcher's cache object, which numba 0.68 (pinned) keeps at ``dispatcher._cache``. Should that
change, :func:`load_cached` loads nothing and the first call loads as before.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.machinery
import importlib.util
import json
import logging
import os
import platform
import shutil
import tempfile
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from pipeline.io import atomic
from stages.tracking import kernels

log = logging.getLogger(__name__)


def dispatchers() -> dict:
    """Name -> numba dispatcher of every compiled function of `stages.tracking.compiled`."""
    from numba.core.registry import CPUDispatcher

    from stages.tracking import compiled
    return {name: value for name, value in vars(compiled).items() if isinstance(value, CPUDispatcher)}


def load_cached() -> int:
    """Load from numba's disk cache every signature it holds for the tracker's compiled functions as they are now
    (the entry points: the helpers they call are compiled into them); how many were loaded.

    A signature is loaded only when the cache's index holds it under the key numba would look up now (this
    source, this machine) and its data file exists, so that the load cannot fall through to a compile.
    """
    loaded = 0
    try:
        for name, dispatcher in dispatchers().items():
            if name.startswith("_"):
                continue
            cache = dispatcher._cache
            codegen = dispatcher.targetctx.codegen()
            index = cache._cache_file._load_index()  # {} when the cache is of another source or numba
            for key, data_name in index.items():
                signature = key[0]
                if (key != cache._index_key(signature, codegen)
                        or not (Path(cache._cache_file._cache_path) / data_name).is_file()):
                    continue
                dispatcher.compile(signature)
                loaded += 1
    except (AttributeError, TypeError, IndexError, OSError) as error:  # numba's internals moved: the first call loads
        log.debug("compiled_cache: not loaded ahead (%s)", error)
    return loaded


#: The extension module's name (its file adds the build key and Python's extension suffix).
BUILT_MODULE = "tracker_kernels"


def build_folder() -> Path:
    """Where the build made ahead of time lives: numba's cache folder for compiled.py (NUMBA_CACHE_DIR when set,
    else the ``__pycache__`` beside it)."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return Path(os.environ["NUMBA_CACHE_DIR"])
    return Path(importlib.util.find_spec("stages.tracking.compiled").origin).parent / "__pycache__"


def build_key() -> str:
    """What a build depends on besides Python (whose extension suffix its file name carries): the content of
    compiled.py, the numpy it was built against (its arrays' layout in memory), and the CPU it was built for (its
    model and instruction sets, as Linux reports them: the build uses them all, as numba's own compilation does, and
    a folder shared by machines must not hand one's build to another)."""
    source = Path(importlib.util.find_spec("stages.tracking.compiled").origin).read_bytes()
    return hashlib.sha256(source + f"numpy {np.__version__}\n{_cpu()}".encode()).hexdigest()[:16]


def _cpu() -> str:
    """The machine, CPU model and instruction-set flags of this computer (``platform.machine()`` alone where
    /proc/cpuinfo is not to be read)."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        lines = []
    described = [next((line for line in lines if line.startswith(field)), "") for field in ("model name", "flags")]
    return "\n".join([platform.machine(), *described])


def built_paths(folder: Path, key: str, name: str = BUILT_MODULE) -> tuple[Path, Path]:
    """The build's extension module and its record of signatures (JSON) in ``folder``."""
    suffix = importlib.machinery.EXTENSION_SUFFIXES[0]
    return folder / f"{name}.{key}{suffix}", folder / f"{name}.{key}.json"


def _argument_type(numba_type) -> dict | str | None:
    """A numba argument type as the build's record keeps it (`kernels.ArrayType` fields, or a scalar's name), or
    None for a type that `kernels.fits` could not check (the function is then left to numba)."""
    from numba.core import types

    if isinstance(numba_type, types.Array):
        if numba_type.layout not in ("C", "A") or not numba_type.aligned or not numba_type.mutable:
            return None
        return {"dtype": str(numba_type.dtype), "ndim": numba_type.ndim, "contiguous": numba_type.layout == "C"}
    name = "bool" if isinstance(numba_type, types.Boolean) else str(numba_type)
    return name if name in kernels.SCALARS else None


@contextlib.contextmanager
def _numpy_error_model() -> Iterator[None]:
    """pycc compiles with numba's default error model ('python': a division by zero raises); compiled.py's functions
    are written for 'numpy' (IEEE results, as their ``@njit(error_model="numpy")`` says). pycc takes no flags, so
    its compiler is given flags of that model for the duration of the build."""
    from numba.core.compiler import Flags
    from numba.pycc import compiler

    class NumpyErrorFlags(Flags):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.error_model = "numpy"

    compiler.Flags = NumpyErrorFlags
    try:
        yield
    finally:
        compiler.Flags = Flags


def build_ahead_of_time(folder: Path | None = None, names: tuple[str, ...] = kernels.ENTRY_POINTS,
                        module: str = BUILT_MODULE) -> Path:
    """Compile the entry points ``names`` of `stages.tracking.compiled`, at every signature they have been called
    with in this process (the warm-up's calls), into an extension module in ``folder`` (default
    :func:`build_folder`); its path. The module is written first and its record last, each atomically, so that
    :func:`install_built` never finds half a build. Raises what pycc raises when it cannot build.
    """
    folder = build_folder() if folder is None else folder
    functions = dispatchers()
    record: dict[str, list] = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pycc's notice of its pending deprecation
        from numba.pycc import CC
    compiler = CC(module)
    compiler.verbose = False
    compiler.target_cpu = "host"  # this CPU's instruction sets, as numba's own compilation uses (and build_key names)
    exported = 0
    for name in names:
        dispatcher = functions[name]
        for signature in dispatcher.signatures:
            full = dispatcher.overloads[signature].signature
            arguments = [_argument_type(t) for t in full.args]
            if any(a is None for a in arguments):
                continue
            symbol = f"{name}_{len(record.get(name, []))}"
            compiler.export(symbol, full)(dispatcher.py_func)
            record.setdefault(name, []).append({"symbol": symbol, "arguments": arguments})
            exported += 1
    if not exported:
        raise RuntimeError("no compiled function has been called in this process: nothing to build")
    key = build_key()
    library, signatures = built_paths(folder, key, module)
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="tracker-build-") as scratch:
        compiler.output_dir = scratch
        compiler.output_file = library.name
        with _numpy_error_model():
            compiler.compile()
        temporary = atomic.temp_path_for(library)
        shutil.move(Path(scratch) / library.name, temporary)
        os.replace(temporary, library)
    atomic.write_text(signatures, json.dumps({"module": module, "key": key, "functions": record}, indent=1))
    return library


def install_built(folder: Path | None = None) -> bool:
    """Install in `stages.tracking.kernels` the build in ``folder`` (default :func:`build_folder`) made from the
    current compiled.py, when there is one; whether one is installed now."""
    folder = build_folder() if folder is None else folder
    key = build_key()
    library, signatures = built_paths(folder, key)
    try:
        record = json.loads(signatures.read_text())
        if record.get("key") != key or not library.is_file():
            return kernels.installed()
        spec = importlib.util.spec_from_file_location(record["module"], library)
        built = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(built)
        variants = {name: [(tuple(a if isinstance(a, str) else kernels.ArrayType(**a) for a in entry["arguments"]),
                            getattr(built, entry["symbol"])) for entry in entries]
                    for name, entries in record["functions"].items()}
        kernels.install(variants)
    except (OSError, ValueError, KeyError, TypeError, AttributeError, ImportError) as error:
        log.debug("compiled_cache: no build installed (%s)", error)
    return kernels.installed()


def make_ready() -> None:
    """Ready the tracker's compiled code before its first call: the build made ahead of time when one matches
    compiled.py, else numba's disk cache loaded ahead (:func:`load_cached`). Nothing to do once a build is installed."""
    if not kernels.installed() and not install_built():
        load_cached()
