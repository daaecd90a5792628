"""The tracker's compiled code (`stages.tracking.compiled`) in numba's on-disk cache, loaded ahead of its first call.

numba loads a cached function the first time it is called, at the types of that call: for the tracker's fourteen
entry points about 0.3 s of one core, most of it holding the interpreter's lock. Called lazily, that load falls on
the first tracked frame, when the run's cores are busy reconstructing. :func:`load_cached` loads every signature the
cache holds for the current source at a moment of the caller's choosing (the tracking stage: while the calibration
refinement runs in a worker process, when a core is otherwise idle). Nothing is compiled here: a signature the cache
does not hold (an edited compiled.py, another numba) is left to the first call, which compiles it as before.

numba has no public call for "load what the cache holds"; this reads the cache's index through the dispatcher's
cache object, which numba 0.68 (pinned) keeps at ``dispatcher._cache``. Should that change, :func:`load_cached`
loads nothing and the first call loads as before.
"""

from __future__ import annotations

import logging
from pathlib import Path

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
