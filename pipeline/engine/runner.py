"""Stage runner with a disk cache: run what is out of date, skip the rest, resume interrupted work.

A stage is a declaration (:class:`Stage`): a name, the upstream stages it reads, its parameter
dataclass, the parts of the capture it reads, and a run function. Each stage writes only under
``<out>/<stage>/``. When it finishes, the runner writes ``<out>/<stage>/manifest.json``::

    stage, cache_key, code_version, package_version, params, inputs, outputs, timing, finished_at

The **cache key** is the hash of: stage name, code version, the canonical JSON of the stage's own
parameters (only its section, so a tracker parameter does not invalidate silhouettes), and its
input hashes: each upstream stage's output digest (content hash of its files, so an upstream
rerun that produces identical files does not ripple down) and a fingerprint of each capture part
it reads (content for capture.yaml and the calibration, path + size + mtime for media files).
The code version is the package version plus a hash of the code and data the stage runs and reads
(:func:`code_inputs`): the run function with the helpers and constants of its module it uses, and
every file of the modules and packages listed in ``Stage.code`` (data files such as the tracker's
pose library included).

A stage is **up to date** when its manifest parses, its key equals the one computed now, and its
output files are still the ones it wrote: the manifest records each file's content hash, and the
check hashes them all again (cheap: :func:`output_contents`), so a damaged file is noticed whatever its
format. A corrupt manifest is a logged miss.

**Interruptions.** The manifest is written last, so a stage folder without one is incomplete.
Before any work, the runner deletes the old manifest and writes a ``params_hash`` marker holding
the key; per-frame outputs are written atomically (temp file + ``os.replace``), so an existing
frame file is a finished frame once it passes the content check its format carries
(:func:`pipeline.io.frames_io.file_problem`). On the next run, if the marker holds the same key, the
folder is kept and the stage only computes the frames whose files are missing or damaged (files that
differ from an old manifest's hashes are deleted first); otherwise the folder is emptied first. A
streaming stage running alongside its upstream (the tracking beside the reconstruction) cannot know its
key yet, since that names the upstream's output digest: its marker holds :func:`streamed_key`, made
with the upstream's cache key instead, and a run that finds it resumes there too. So a
run never trusts a stale, damaged or half-written result; and a damaged file a stage still comes to
read (:class:`~pipeline.io.frames_io.DamagedFileError`) is deleted and computed again (:meth:`Runner.run`).

**What the runner deletes.** Only what it can show it wrote: a stage folder is emptied only when it
holds the marker (written as the folder is made, before any result), and an output folder may not
overlap the capture (be it, lie inside it or contain it), so that ``--out`` pointed at the capture
cannot empty the capture's own ``calibration/`` or ``silhouettes/``. Anything else in the way is an
:class:`InputError` naming it.

A lock (``fcntl.flock`` on ``<out>/.lock``) refuses a second concurrent run on the same folder.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import errno
import fcntl
import hashlib
import importlib.metadata
import importlib.util
import inspect
import json
import logging
import math
import os
import re
import shutil
import sys
import time
import types
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from tqdm import tqdm

from calib.errors import InputError
from pipeline.engine import run_warnings
from pipeline.engine.executors import Workers, call_logged, relog
from pipeline.engine.params import params_to_dict
from pipeline.io import atomic, frames_io
from pipeline.io.capture import Capture
from pipeline.io.run_layout import LOCK, MANIFEST, MARKER, RUN_RECORD

log = logging.getLogger(__name__)

PACKAGE = "hnmocap"
#: Largest chunk of consecutive frames given to one worker call. Bigger chunks decode video with
#: fewer seeks; smaller ones balance load and update the progress bar more often.
MAX_CHUNK_FRAMES = 25
#: Chunks per worker to aim for, so that an uneven chunk does not leave workers idle at the end.
CHUNKS_PER_WORKER = 4

_STAGE_NAME = re.compile(r"^[a-z][a-z0-9_]*$")


# ---------------------------------------------------------------------------------------------
# Declarations


@dataclass(frozen=True)
class Stage:
    """One stage of the pipeline graph.

    Parameters
    ----------
    name : str
        Folder name under the output directory and section name in the configuration.
    run : callable
        ``run(ctx: StageContext) -> int | None``: does the work, writes files under ``ctx.out_dir``,
        returns the number of frames it computed (``None`` if the stage is not per-frame).
    inputs : tuple of str
        Upstream stages whose results it reads (through ``ctx.input_dir(name)``).
    params_type : type or None
        Frozen dataclass of its parameters (every field with a default), or ``None``.
    capture_parts : tuple of str
        Parts of the capture it reads directly (see :meth:`Capture.fingerprint`).
    code : tuple of str
        Modules, packages or resource folders (import names) whose files are part of its code version,
        in addition to the run function and the helpers of its module it uses, e.g.
        ``("stages.silhouettes",)``: every first-party module whose code the stage runs and every data
        file it reads, which tests/pipeline/test_graph.py checks (see :func:`code_inputs`).
    streams : bool
        The stage may run while its last input stage is still writing: it reads each input file
        through :meth:`StageContext.ready`, which waits for the file. A run then overlaps the two
        (see :meth:`Runner.run`).
    """

    name: str
    run: Callable[[StageContext], int | None]
    inputs: tuple[str, ...] = ()
    params_type: type | None = None
    capture_parts: tuple[str, ...] = ()
    code: tuple[str, ...] = ()
    streams: bool = False

    def __post_init__(self) -> None:
        if not _STAGE_NAME.match(self.name):
            raise ValueError(f"stage name {self.name!r}: expected lower_case letters, digits and _")


def check_graph(stages: Sequence[Stage]) -> None:
    """Raise ``ValueError`` unless names are unique and every input is declared before its user."""
    seen: set[str] = set()
    for stage in stages:
        if stage.name in seen:
            raise ValueError(f"stage {stage.name!r} is declared twice")
        unknown = [name for name in stage.inputs if name not in seen]
        if unknown:
            raise ValueError(f"stage {stage.name!r} reads {unknown}, which are not declared before it")
        seen.add(stage.name)


def select_stages(stages: Sequence[Stage], *, only: str | None = None, start: str | None = None,
                  end: str | None = None) -> list[str]:
    """Names of the stages to run for ``--only``, ``--from`` and ``--to`` (all when none is given).

    ``--from S`` selects S and every stage downstream of it; ``--to S`` selects S and every stage
    upstream of it; both together select the stages in between.
    """
    names = [stage.name for stage in stages]
    for option, value in (("--only", only), ("--from", start), ("--to", end)):
        if value is not None and value not in names:
            raise InputError(f"{option} {value}: unknown stage (expected one of {', '.join(names)})")
    if only is not None:
        return [only]
    by_name = {stage.name: stage for stage in stages}
    selected = set(names)
    if start is not None:
        downstream = {start}
        for stage in stages:
            if downstream.intersection(stage.inputs):
                downstream.add(stage.name)
        selected &= downstream
    if end is not None:
        upstream, todo = set(), [end]
        while todo:
            name = todo.pop()
            if name not in upstream:
                upstream.add(name)
                todo.extend(by_name[name].inputs)
        selected &= upstream
    if not selected:
        raise InputError(f"--from {start} --to {end}: no stage lies between them "
                         "(expected --from upstream of --to)")
    return [name for name in names if name in selected]


# ---------------------------------------------------------------------------------------------
# What a run function sees


@dataclass(frozen=True)
class StageContext:
    """Everything a stage's run function may use. Stages write only under ``out_dir``."""

    stage: str
    capture: Capture
    params: Any
    out_dir: Path
    output_root: Path
    workers: Workers
    show_progress: bool = False
    upstream: cf.Future | None = None

    def input_dir(self, stage: str) -> Path:
        """Folder of an upstream stage's results."""
        return self.output_root / stage

    def ready(self, path: Path) -> Path:
        """``path``, an input file, once it exists.

        While a streaming stage's upstream is still running (``upstream``, the future of its
        :meth:`Runner.run_stage`), files appear one by one, each complete (they are written
        atomically); waiting ends with the file, or with the upstream's own error if it failed.
        """
        while not path.exists():
            if self.upstream is None or self.upstream.done():
                if path.exists():
                    break
                if self.upstream is not None:
                    self.upstream.result()  # the upstream's error, if it failed
                raise InputError(f"{path}: input file missing (expected the {self.stage} stage's inputs complete)")
            time.sleep(STREAM_POLL_S)
        return path

    def progress(self, total: int, *, initial: int = 0) -> tqdm:
        """A progress bar over frames on stderr (disabled when not wanted or not a terminal)."""
        return tqdm(total=total, initial=initial, desc=self.stage, unit="frame", file=sys.stderr,
                    disable=not self.show_progress, leave=False, dynamic_ncols=True)

    def pending_frames(self, outputs_of: Callable[[int], Sequence[Path]],
                       frames: Sequence[int] | None = None) -> list[int]:
        """Frames (default: all of the capture's) for which some output file is missing or damaged.

        A file kept from an interrupted run counts only when it passes its content check
        (:func:`~pipeline.io.frames_io.file_problem`); one that fails is deleted here, with a warning, so
        that its frame is computed again and nothing reads the damaged file meanwhile.
        """
        frames = self.capture.frame_numbers if frames is None else frames
        return [frame for frame in frames if not all(_intact(path) for path in outputs_of(frame))]

    def map_frames(self, task: Callable[[tuple[int, ...]], Any],
                   outputs_of: Callable[[int], Sequence[Path]], *,
                   frames: Sequence[int] | None = None, chunk_size: int | None = None) -> int:
        """Run ``task(chunk)`` over chunks of consecutive pending frames with the executor.

        ``task`` runs in a worker (another process, or another machine with Dask): it must be
        picklable, e.g. ``functools.partial(module_level_function, capture=..., params=...,
        out_dir=...)``, and it **writes each frame's outputs itself**, atomically (``frames_io``
        writers), so that a frame's files exist only once complete and nothing large travels back
        to this process. Its return value is ignored. ``outputs_of(frame)`` lists the files that
        make a frame complete; frames whose files all exist are skipped (this is resuming).

        Returns
        -------
        int
            Number of frames computed now.
        """
        frames = self.capture.frame_numbers if frames is None else tuple(frames)
        pending = self.pending_frames(outputs_of, frames)
        if not pending:
            return 0
        size = chunk_size or min(MAX_CHUNK_FRAMES,
                                 max(1, math.ceil(len(pending) / (CHUNKS_PER_WORKER * self.workers.count))))
        chunks = consecutive_chunks(pending, frames, size)
        executor = self.workers.executor
        # Submitting a few chunks ahead keeps every worker busy without queueing the whole sequence;
        # with one in-process worker it means "one chunk at a time", so a failure stops at once.
        ahead = 1 if self.workers.count == 1 else 2 * self.workers.count
        remaining = iter(chunks)
        running: dict[cf.Future, tuple[int, ...]] = {}
        with self.progress(len(frames), initial=len(frames) - len(pending)) as bar:
            try:
                while True:
                    while len(running) < ahead and (chunk := next(remaining, None)) is not None:
                        future = executor.submit(task, chunk) if self.workers.in_process else \
                            executor.submit(call_logged, task, chunk)  # the worker's warnings come back
                        running[future] = chunk
                    if not running:
                        break
                    done, _ = cf.wait(running, return_when=cf.FIRST_COMPLETED)
                    for future in done:
                        chunk = running.pop(future)
                        result = future.result()
                        if not self.workers.in_process:
                            relog(result)
                        bar.update(len(chunk))
            finally:
                for future in running:
                    future.cancel()
        return len(pending)


def _intact(path: Path) -> bool:
    """Whether the output file ``path`` exists and passes its content check (else it is deleted)."""
    if not path.exists():
        return False
    problem = frames_io.file_problem(path)
    if problem:
        log.warning("%s: %s; deleted, computed again", path, problem)
        path.unlink()
    return problem is None


#: How often a streaming stage looks for its next input file, seconds.
STREAM_POLL_S = 0.002


def consecutive_chunks(pending: Sequence[int], frames: Sequence[int], size: int) -> list[tuple[int, ...]]:
    """Split ``pending`` into chunks of at most ``size`` frames that are consecutive in ``frames``.

    Consecutive (in the capture's frame order) so that a worker decodes a video sequentially.
    """
    position = {frame: index for index, frame in enumerate(frames)}
    chunks: list[list[int]] = []
    for frame in pending:
        if chunks and len(chunks[-1]) < size and position[frame] == position[chunks[-1][-1]] + 1:
            chunks[-1].append(frame)
        else:
            chunks.append([frame])
    return [tuple(chunk) for chunk in chunks]


# ---------------------------------------------------------------------------------------------
# Cache keys and manifests


def canonical_json(value: Any) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=False)


def _hash(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:32]


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


@dataclass(frozen=True)
class Expected:
    """What a stage's manifest must say for it to be up to date (``missing``: upstreams not done)."""

    record: dict
    key: str
    missing: tuple[str, ...] = ()


def expected_record(stage: Stage, capture: Capture, params: Any, output_root: Path) -> Expected:
    """The cache record and key of ``stage`` given the current inputs on disk."""
    inputs: dict[str, str | None] = {}
    missing = []
    for upstream in stage.inputs:
        manifest = read_manifest(output_root / upstream)
        inputs[f"stage:{upstream}"] = manifest["outputs"]["digest"] if manifest else None
        if manifest is None:
            missing.append(upstream)
    for part in stage.capture_parts:
        inputs[f"capture:{part}"] = capture.fingerprint(part)
    record = {"stage": stage.name, "code_version": code_version(stage), "params": params_to_dict(params),
              "inputs": inputs}
    return Expected(record, _hash(canonical_json(record)), tuple(missing))


def streamed_key(stage: Stage, capture: Capture, params: Any, output_root: Path, upstream_key: str) -> str:
    """The key a streaming stage's marker holds while it runs alongside its last input stage.

    Its cache key names that upstream's output digest, which is known only once the upstream has
    finished; the upstream's own cache key stands for it meanwhile (the same key makes the same files,
    which is what the cache rests on). A run killed while both ran then finds this key in the marker and
    keeps the frames already computed (:meth:`Runner.run_stage`), instead of a tracking folder emptied
    for want of a key to compare.
    """
    record = expected_record(stage, capture, params, output_root).record
    inputs = {**record["inputs"], f"stage:{stage.inputs[-1]}": f"key:{upstream_key}"}
    return _hash(canonical_json({**record, "inputs": inputs}))


def read_manifest(folder: Path) -> dict | None:
    """The stage's manifest, or ``None`` when missing or unreadable (a logged cache miss)."""
    path = folder / MANIFEST
    if not path.exists():
        return None
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(manifest, dict) or not all(
                key in manifest for key in ("cache_key", "params", "inputs", "code_version", "outputs")):
            raise ValueError("missing keys")
        outputs = manifest["outputs"]
        if not isinstance(manifest["inputs"], dict) or not isinstance(outputs, dict) or not isinstance(
                outputs.get("digest"), str) or not isinstance(outputs.get("contents"), dict):
            raise ValueError("malformed inputs or outputs")
    except (OSError, ValueError, KeyError, TypeError) as error:
        log.warning("%s: unreadable manifest (%s); the stage will run again", path, error)
        return None
    return manifest


def _output_files(folder: Path) -> list[Path]:
    """The stage's result files, sorted, without the manifest, the marker and temporary files."""
    return sorted(path for path in folder.rglob("*") if path.is_file()
                  and path.relative_to(folder).as_posix() not in (MANIFEST, MARKER)
                  and not path.name.startswith(atomic.TEMP_PREFIX))


def output_contents(folder: Path) -> dict[str, str]:
    """Relative path -> content hash of each of the stage's result files.

    Reading and hashing every file is what makes a damaged file visible, whatever its format; the ~900
    files of a 112-frame, 6-camera capture (13 MB) take a small fraction of a second once they are in the
    page cache (tests/pipeline/test_runner.py checks 1000 files in under half a second).
    """
    return {path.relative_to(folder).as_posix(): hashlib.sha256(path.read_bytes()).hexdigest()[:32]
            for path in _output_files(folder)}


def describe_outputs(folder: Path) -> dict:
    """Count, bytes, each file's content hash and their digest (for downstream keys) of the stage's files."""
    contents = output_contents(folder)
    return {"files": len(contents), "bytes": sum((folder / name).stat().st_size for name in contents),
            "digest": _hash("".join(f"{name}\0{digest}\n" for name, digest in contents.items())),
            "contents": contents}


@dataclass(frozen=True)
class OutputChanges:
    """How a stage's files differ from its manifest: files ``changed`` (damaged), ``missing``, ``added``."""

    changed: tuple[str, ...] = ()
    missing: tuple[str, ...] = ()
    added: tuple[str, ...] = ()

    def __bool__(self) -> bool:
        return bool(self.changed or self.missing or self.added)

    def __str__(self) -> str:
        """``"output files changed on disk: 2 damaged (000003.ply, 000007.ply), 1 missing (000009.ply)"``."""
        parts = [f"{len(names)} {what} ({_listing(names)})" for what, names in
                 (("damaged", self.changed), ("missing", self.missing), ("added", self.added)) if names]
        return "output files changed on disk: " + ", ".join(parts)


def _listing(names: Sequence[str], shown: int = 3) -> str:
    return ", ".join(names[:shown]) + (", ..." if len(names) > shown else "")


def output_changes(folder: Path, manifest: dict) -> OutputChanges:
    """Compare the stage's files with the content hashes its manifest recorded."""
    recorded, now = manifest["outputs"]["contents"], output_contents(folder)
    return OutputChanges(changed=tuple(name for name in recorded if name in now and now[name] != recorded[name]),
                         missing=tuple(name for name in recorded if name not in now),
                         added=tuple(name for name in now if name not in recorded))


# ---------------------------------------------------------------------------------------------
# Status


@dataclass(frozen=True)
class StageStatus:
    """``state`` is one of "up to date", "stale", "incomplete", "not run"; ``reason`` says why."""

    name: str
    state: str
    reason: str = ""


def _flatten(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, dict):
        flat = {}
        for key, item in value.items():
            flat.update(_flatten(item, f"{prefix}.{key}" if prefix else str(key)))
        return flat
    return {prefix: value}


def stale_reasons(manifest: dict, expected: Expected) -> list[str]:
    """Why a manifest does not match the expected record (empty when it does)."""
    reasons = []
    if manifest.get("code_version") != expected.record["code_version"]:
        reasons.append("code changed")
    old, new = _flatten(manifest.get("params")), _flatten(expected.record["params"])
    for key in sorted(set(old) | set(new)):
        if old.get(key) != new.get(key):
            reasons.append(f"parameter {key}: {old.get(key)!r} -> {new.get(key)!r}")
    for key, value in expected.record["inputs"].items():
        if manifest["inputs"].get(key) != value:
            kind, name = key.split(":", 1)
            reasons.append(f"upstream {name} changed" if kind == "stage" else f"capture {name} changed")
    if not reasons and manifest.get("cache_key") != expected.key:
        reasons.append("cache key differs")
    return reasons


def stage_status(stage: Stage, capture: Capture, params: Any, output_root: Path) -> StageStatus:
    """Whether ``stage``'s results on disk are up to date with the capture, parameters and code."""
    folder = output_root / stage.name
    manifest = read_manifest(folder)
    if manifest is None:
        if (folder / MARKER).exists():
            return StageStatus(stage.name, "incomplete",
                               f"{len(_output_files(folder))} files kept; the next run resumes from them")
        if (folder / MANIFEST).exists():
            return StageStatus(stage.name, "stale", "manifest unreadable")
        return StageStatus(stage.name, "not run")
    expected = expected_record(stage, capture, params, output_root)
    if expected.missing:
        return StageStatus(stage.name, "stale",
                           f"upstream {', '.join(expected.missing)} has no complete result")
    reasons = stale_reasons(manifest, expected)
    changes = None if reasons else output_changes(folder, manifest)
    if changes:
        reasons.append(str(changes))
    return StageStatus(stage.name, "stale" if reasons else "up to date", "; ".join(reasons))


def graph_status(stages: Sequence[Stage], capture: Capture, params: Mapping[str, Any],
                 output_root: Path) -> list[StageStatus]:
    """Status of every stage; an up-to-date stage with a not-up-to-date upstream is reported stale."""
    statuses: dict[str, StageStatus] = {}
    for stage in stages:
        status = stage_status(stage, capture, params[stage.name], output_root)
        behind = [name for name in stage.inputs if statuses[name].state != "up to date"]
        if status.state == "up to date" and behind:
            status = StageStatus(stage.name, "stale", f"upstream {', '.join(behind)} not up to date")
        statuses[stage.name] = status
    return list(statuses.values())


# ---------------------------------------------------------------------------------------------
# Running


@dataclass(frozen=True)
class StageOutcome:
    """What happened to one stage in a run: ``action`` is "ran", "up to date" or "not selected"."""

    name: str
    action: str
    seconds: float = 0.0
    frames: int | None = None
    reason: str = ""


def check_output_folder(output_root: Path, capture_root: Path) -> None:
    """Refuse an output folder that is the capture, lies inside it or contains it.

    The runner empties ``<out>/<stage>`` folders; with ``--out`` at the capture, those would be the
    capture's own ``calibration/`` or ``silhouettes/``, and with the capture inside ``--out`` a stage
    folder could hold it.
    """
    out, capture = output_root.resolve(), capture_root.resolve()
    if out == capture or capture in out.parents or out in capture.parents:
        raise InputError(f"--out {output_root}: overlaps the capture {capture_root} "
                         "(expected an output folder outside the capture, and not containing it)")


def written_by_runner(folder: Path) -> bool:
    """Whether ``folder`` is a stage folder the runner made: a real folder (not a link) with a marker."""
    return not folder.is_symlink() and (folder / MARKER).is_file()


def fresh_stage_folder(folder: Path, key: str) -> None:
    """Make ``folder`` empty but for the marker holding ``key``.

    An existing folder is deleted only when it holds a marker: the runner writes one in every stage
    folder it makes, before any result, so a folder without one (or a file, or a link) is not the
    runner's to delete.
    """
    if (folder.exists() or folder.is_symlink()) and not written_by_runner(folder):
        raise InputError(f"{folder}: not a stage folder written by the pipeline (no {MARKER} in it); "
                         "refusing to delete it (expected only the pipeline's own folders in --out; "
                         "move it away or choose another --out)")
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    atomic.write_text(folder / MARKER, key + "\n")


@contextlib.contextmanager
def output_lock(output_root: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``<out>/.lock`` for the duration of a run.

    Afterwards the lock file is removed, and so is the output folder when the block made it and left
    nothing in it (a run refused at once leaves no trace). The file is removed while still locked: a
    run that opened it meanwhile finds, once it gets the lock, that the path is no longer its file, and
    is refused like any second run.
    """
    made = not output_root.exists()
    try:
        output_root.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        in_the_way = next(path for path in (output_root, *output_root.parents) if path.exists())
        raise InputError(f"--out {output_root}: {in_the_way} is a file, not a folder (expected a folder for the "
                         "results, or a path where one can be made)") from None
    path = output_root / LOCK
    busy = InputError(f"{output_root}: another run is using this output directory "
                      "(expected one run at a time; wait for it or pick another --out)")
    try:
        with open(path, "a") as handle:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise busy from None
            if not _same_file(handle.fileno(), path):
                raise busy
            try:
                yield
            finally:
                path.unlink(missing_ok=True)
                fcntl.flock(handle, fcntl.LOCK_UN)
    finally:
        if made and output_root.is_dir() and not any(output_root.iterdir()):
            output_root.rmdir()


def _same_file(descriptor: int, path: Path) -> bool:
    """Whether ``path`` still names the file open as ``descriptor``."""
    try:
        named = path.stat()
    except FileNotFoundError:
        return False
    opened = os.fstat(descriptor)
    return (named.st_dev, named.st_ino) == (opened.st_dev, opened.st_ino)


#: errno of the OSErrors that are about the storage a run reads and writes, not about the pipeline, with
#: what the user is expected to provide.
STORAGE_ERRORS = {
    errno.ENOSPC: "free space on the output's disk; the frames already written are kept and the next run "
                  "resumes from them",
    errno.EDQUOT: "disk quota left for the output; the frames already written are kept and the next run "
                  "resumes from them",
    errno.EFBIG: "files allowed to grow that large (see ulimit -f)",
    errno.EROFS: "an output folder on a file system that can be written",
    errno.EACCES: "permission to read the capture and to write the output folder",
    errno.EPERM: "permission to read the capture and to write the output folder",
}


def storage_error(error: OSError, output_root: Path) -> InputError | None:
    """The one-line error for an ``OSError`` about the storage (full, read-only, not permitted), wherever
    it was raised (a worker process's comes back whole), or None for any other (a bug, which keeps its
    traceback)."""
    expected = STORAGE_ERRORS.get(error.errno)
    if expected is None:
        return None
    return InputError(f"{error.filename or output_root}: {error.strerror} (expected {expected})")


def write_run_record(output_root: Path, capture: Capture, params: Mapping[str, Any], state: str, *,
                     facts: Mapping[str, Any] | None = None, failure: Mapping[str, Any] | None = None) -> None:
    """Record which capture and parameters this output folder is for (``stages <out>`` reads it), and
    how the last run that changed it went.

    ``state`` is "running" (a run is changing the folder, or was killed doing so), "finished" or
    "failed", the last with ``failure``: ``{"error": the one-line error, "incomplete": [stages]}``.
    ``facts`` are what else reopening the capture needs (``{"allow_outside_paths": true}``).
    """
    frames_io.write_json(output_root / RUN_RECORD, {
        "capture": str(capture.root.resolve()), **(facts or {}),
        "params": {name: params_to_dict(value) for name, value in params.items() if value is not None},
        "state": state, **({"failure": dict(failure)} if failure else {}),
    })


def read_run_record(output_root: Path) -> dict:
    path = output_root / RUN_RECORD
    if not path.is_file():
        raise InputError(f"{path}: missing "
                         "(expected an output directory written by `python -m pipeline run`)")
    record = frames_io.read_json(path)
    if not isinstance(record, dict) or not isinstance(record.get("capture"), str):
        raise InputError(f"{path}: no capture path recorded "
                         "(expected a file written by `python -m pipeline run`)")
    return record


@dataclass
class Runner:
    """Runs a stage graph on one capture into one output folder (hold :func:`output_lock` around it)."""

    stages: Sequence[Stage]
    capture: Capture
    params: Mapping[str, Any]
    output_root: Path
    workers: Workers
    show_progress: bool = False
    record_facts: Mapping[str, Any] = field(default_factory=dict)
    outcomes: list[StageOutcome] = field(default_factory=list)
    _changing: bool = field(default=False, init=False, repr=False)

    def __post_init__(self) -> None:
        check_graph(self.stages)
        check_output_folder(self.output_root, self.capture.root)

    def run(self, selected: Collection[str] | None = None, *, force: bool = False) -> list[StageOutcome]:
        """Run the ``selected`` stages (default all) in declaration order; return what happened.

        A streaming stage that has no finished result yet runs alongside its upstream when that one
        has work to do: the upstream in a background thread (its workers compute the frames), the
        streaming stage here, reading each frame as it appears. The tracker, sequential by nature,
        then uses the core the per-frame stage's workers leave idle between chunks.

        A stage that reads a damaged output of a stage (:class:`~pipeline.io.frames_io.DamagedFileError`)
        does not end the run: the file is deleted, its stage loses its manifest, and the run starts
        again with that stage selected too, which computes the file again as it resumes (each file is
        repaired once; a second failure is raised).

        A run that fails after it began to change the folder leaves nothing that looks finished: every
        stage downstream of one left incomplete loses its manifest too (:meth:`_invalidate`), and
        ``run.json`` records the failure; a warning names those stages. Their files stay, so that the
        next run resumes from them.
        """
        selected = set(selected) if selected is not None else {stage.name for stage in self.stages}
        forced = set(selected) if force else set()
        ran: dict[str, StageOutcome] = {}
        repaired: set[Path] = set()
        self._changing = False
        try:
            while True:
                try:
                    self._run_once(selected, forced)
                    break
                except frames_io.DamagedFileError as error:
                    selected.add(self._repair(error, repaired))
                    ran.update({outcome.name: outcome for outcome in self.outcomes if outcome.action == "ran"})
                    forced -= set(ran)
        except BaseException as error:  # Ctrl-C too: what the run left must not look finished
            if self._changing:
                self._record_failure(error)
            raise
        if self._changing:
            write_run_record(self.output_root, self.capture, self.params, "finished", facts=self.record_facts)
        self.outcomes = [ran.get(outcome.name, outcome) if outcome.action == "up to date" else outcome
                         for outcome in self.outcomes]
        return self.outcomes

    def _begin_change(self) -> None:
        """Called before the run first changes a stage folder: ``run.json`` says it is for this run now."""
        if not self._changing:
            write_run_record(self.output_root, self.capture, self.params, "running", facts=self.record_facts)
            self._changing = True

    def _record_failure(self, error: BaseException) -> None:
        """Mark what a failed run left incomplete (:meth:`_invalidate`), in ``run.json`` and the debug log: the
        run's own one-line error is what the terminal shows, ``pipeline stages`` reports the rest."""
        incomplete = self._invalidate()
        message = str(error).splitlines()[0] if str(error).strip() else type(error).__name__
        log.debug("the run failed; %s left incomplete (no manifest; their files are kept and the next run "
                    "resumes from them; `python -m pipeline stages %s` lists them)",
                    ", ".join(incomplete) or "no stage", self.output_root)
        try:
            write_run_record(self.output_root, self.capture, self.params, "failed", facts=self.record_facts,
                             failure={"error": message, "incomplete": incomplete})
        except OSError as failure:  # a full disk, say: the run's own error is the one to show
            log.warning("%s: could not record the failure (%s)", self.output_root / RUN_RECORD, failure)

    def _invalidate(self) -> list[str]:
        """Take the manifest from every stage that has one while one of its upstreams has none (its result
        was made from files the failed run replaced or left unfinished); return the stages of the folder
        that are incomplete (a marker, no manifest), in order."""
        complete: dict[str, bool] = {}
        incomplete = []
        for stage in self.stages:
            folder = self.output_root / stage.name
            has_manifest = (folder / MANIFEST).is_file()
            if has_manifest and not all(complete.get(name, False) for name in stage.inputs):
                (folder / MANIFEST).unlink()
                has_manifest = False
            complete[stage.name] = has_manifest
            if not has_manifest and written_by_runner(folder):
                incomplete.append(stage.name)
        return incomplete

    def _run_once(self, selected: Collection[str], forced: Collection[str]) -> None:
        """One pass of :meth:`run` over the stages, the ``forced`` ones rerun even if up to date."""
        self.outcomes = []
        stages = list(self.stages)
        while stages:
            stage = stages.pop(0)
            if stage.name not in selected:
                self.outcomes.append(StageOutcome(stage.name, "not selected"))
            elif stages and stages[0].name in selected and self._streams_after(stage, stages[0], forced):
                self.outcomes.extend(self._run_streaming(stage, stages.pop(0), forced))
            else:
                self.outcomes.append(self.run_stage(stage, force=stage.name in forced))

    def _repair(self, error: frames_io.DamagedFileError, repaired: set[Path]) -> str:
        """Delete the damaged file of ``error`` and its stage's manifest; return that stage's name.

        Raises ``error`` again when the file is not in a stage folder the runner wrote (a capture's
        file is the user's to replace) or was repaired before in this run.
        """
        path = error.path.resolve()
        owner = next((stage.name for stage in self.stages
                      if (self.output_root / stage.name).resolve() in path.parents), None)
        if owner is None or not written_by_runner(self.output_root / owner) or path in repaired:
            raise error
        self._begin_change()
        repaired.add(path)
        log.warning("%s: %s; deleted, the %s stage computes it again", error.path, error.problem, owner)
        path.unlink(missing_ok=True)
        (self.output_root / owner / MANIFEST).unlink(missing_ok=True)
        return owner

    def _streams_after(self, upstream: Stage, stage: Stage, forced: Collection[str]) -> bool:
        """Whether ``stage`` should run alongside ``upstream``: it streams from it, will run anyway (no
        finished result of its own), and ``upstream`` has work to do."""
        if not stage.streams or stage.inputs[-1:] != (upstream.name,):
            return False
        if read_manifest(self.output_root / stage.name) is not None and stage.name not in forced:
            return False  # it may still be up to date after the upstream reruns: wait and see
        status = stage_status(upstream, self.capture, self.params[upstream.name], self.output_root)
        return upstream.name in forced or status.state != "up to date"

    def _run_streaming(self, upstream: Stage, stage: Stage, forced: Collection[str]) -> list[StageOutcome]:
        upstream_key = expected_record(upstream, self.capture, self.params[upstream.name], self.output_root).key
        key = streamed_key(stage, self.capture, self.params[stage.name], self.output_root, upstream_key)
        prepared = self._prepare(upstream, force=upstream.name in forced)  # before the follower looks at its folder
        with cf.ThreadPoolExecutor(1, thread_name_prefix=upstream.name) as background:
            if isinstance(prepared, StageOutcome):
                running = cf.Future()
                running.set_result(prepared)
            else:
                running = background.submit(self._run_prepared, upstream, prepared)
            outcome = self._run_streaming_stage(stage, running, key, force=stage.name in forced)
        return [running.result(), outcome]

    def run_stage(self, stage: Stage, *, force: bool = False) -> StageOutcome:
        """Run one stage unless up to date, resuming from the frames an interrupted run left when its
        marker holds the key computed now (or, for a streaming stage, the key it ran under alongside
        its upstream, :func:`streamed_key`, when that upstream has finished since)."""
        prepared = self._prepare(stage, force=force)
        return prepared if isinstance(prepared, StageOutcome) else self._run_prepared(stage, prepared)

    def _prepare(self, stage: Stage, *, force: bool) -> StageOutcome | Expected:
        """The outcome of a stage that is up to date; else its folder made ready to run in (resumed or
        emptied) and the record it is to run under.

        A streaming follower starts only after this, so it never reads the files of an earlier run
        that its upstream is about to delete."""
        folder = self.output_root / stage.name
        expected = expected_record(stage, self.capture, self.params[stage.name], self.output_root)
        if expected.missing:
            upstream = expected.missing[0]
            raise InputError(f"{self.output_root / upstream}: stage {stage.name} needs the results of "
                             f"{upstream}, which are not complete (expected a finished {upstream} stage; "
                             "run it first)")
        manifest = read_manifest(folder)
        changes = None
        if manifest is not None and not force:
            reasons = stale_reasons(manifest, expected)
            changes = None if reasons else output_changes(folder, manifest)
            if not reasons and not changes:
                log.info("%s: up to date", stage.name)
                return StageOutcome(stage.name, "up to date", reason="")
            log.info("%s: stale (%s)", stage.name, "; ".join(reasons) or str(changes))
        self._begin_change()
        if changes and changes.changed:  # deleted, so that the resume below computes them again
            log.warning("%s: %d files differ from what the stage wrote (%s); deleted, computed again",
                        stage.name, len(changes.changed), _listing(changes.changed))
            for name in changes.changed:
                (folder / name).unlink()

        self._resume_or_start_afresh(stage, (expected.key, *self._streamed_keys(stage)), expected.key, force)
        return expected

    def _run_prepared(self, stage: Stage, expected: Expected) -> StageOutcome:
        """Run a stage whose folder :meth:`_prepare` made ready, and record it under ``expected``."""
        frames, seconds = self._execute(stage)
        return self._finish(stage, expected, frames, seconds)

    def _streamed_keys(self, stage: Stage) -> tuple[str, ...]:
        """The key a streaming ``stage`` ran under alongside its finished upstream (:func:`streamed_key`)."""
        manifest = read_manifest(self.output_root / stage.inputs[-1]) if stage.streams else None
        if manifest is None:
            return ()
        return (streamed_key(stage, self.capture, self.params[stage.name], self.output_root, manifest["cache_key"]),)

    def _resume_or_start_afresh(self, stage: Stage, resumable_keys: Sequence[str], key: str, force: bool) -> None:
        """Keep the stage folder's finished frames when its marker holds one of ``resumable_keys`` (and the
        run is not forced); else empty it, with a marker holding ``key``."""
        folder = self.output_root / stage.name
        if not force and written_by_runner(folder) and (
                folder / MARKER).read_text(encoding="utf-8").strip() in resumable_keys:
            (folder / MANIFEST).unlink(missing_ok=True)
            removed = atomic.remove_temp_files(folder)
            log.info("%s: resuming (%d leftover temporary files removed)", stage.name, removed)
        else:
            fresh_stage_folder(folder, key)

    def _run_streaming_stage(self, stage: Stage, upstream: cf.Future, key: str, *, force: bool) -> StageOutcome:
        """Run ``stage`` alongside ``upstream``, the future of its running input stage: under ``key`` (its
        :func:`streamed_key`), resuming what a run under the same key left; its record is made when both
        have finished."""
        folder = self.output_root / stage.name
        self._begin_change()
        self._resume_or_start_afresh(stage, (key,), key, force)
        frames, seconds = self._execute(stage, upstream)
        upstream.result()  # its manifest is written: this stage's inputs are known now
        expected = expected_record(stage, self.capture, self.params[stage.name], self.output_root)
        atomic.write_text(folder / MARKER, expected.key + "\n")
        return self._finish(stage, expected, frames, seconds)

    def _execute(self, stage: Stage, upstream: cf.Future | None = None) -> tuple[int | None, float]:
        """Call the stage's run function in its folder: the frames it computed and the seconds it took."""
        context = StageContext(stage.name, self.capture, self.params[stage.name], self.output_root / stage.name,
                               self.output_root, self.workers, self.show_progress, upstream)
        started = time.perf_counter()
        with run_warnings.stage_scope(stage.name):
            frames = stage.run(context)
        return frames, time.perf_counter() - started

    def _finish(self, stage: Stage, expected: Expected, frames: int | None, seconds: float) -> StageOutcome:
        """Write the manifest of a stage that ran: from now on it is up to date."""
        folder = self.output_root / stage.name
        manifest = {
            **expected.record,
            "cache_key": expected.key,
            "package_version": package_version(),
            "outputs": describe_outputs(folder),
            "timing": {"seconds": round(seconds, 6), "frames": frames, "workers": self.workers.description},
            "finished_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        }
        frames_io.write_json(folder / MANIFEST, manifest)
        return StageOutcome(stage.name, "ran", seconds, frames)


def format_summary(outcomes: Sequence[StageOutcome]) -> str:
    """Table of what each stage did, with its time per frame and frames per second."""
    rows = [("stage", "action", "seconds", "frames", "ms/frame", "frames/s")]
    for outcome in outcomes:
        timed = outcome.action == "ran"
        per_frame = timed and outcome.frames
        rows.append((
            outcome.name, outcome.action,
            f"{outcome.seconds:.2f}" if timed else "-",
            str(outcome.frames) if timed and outcome.frames is not None else "-",
            f"{1000 * outcome.seconds / outcome.frames:.1f}" if per_frame else "-",
            f"{outcome.frames / outcome.seconds:.2f}" if per_frame and outcome.seconds > 0 else "-",
        ))
    return format_columns(rows, right=range(2, len(rows[0])))


def format_columns(rows: Sequence[Sequence[str]], *, right: Collection[int]) -> str:
    """Rows of text cells as aligned columns: those numbered in ``right`` (numbers) to the right, the others
    (names, words) to the left."""
    widths = [max(len(row[column]) for row in rows) for column in range(len(rows[0]))]
    return "\n".join("  ".join(cell.rjust(width) if column in right else cell.ljust(width)
                               for column, (cell, width) in enumerate(zip(row, widths, strict=True))).rstrip()
                     for row in rows)

