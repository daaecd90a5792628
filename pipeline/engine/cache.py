"""Cache keys and manifests: the record a stage's manifest must hold to be up to date
(:func:`expected_record`), reading manifests, and the content hashes of a stage's output files.

The key is the hash of the stage's name, code version (:mod:`pipeline.engine.versions`), the canonical JSON
of its own parameters and its input hashes: each upstream's output digest and a fingerprint of each capture
part it reads.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.engine.params import params_to_dict
from pipeline.engine.stage import Stage
from pipeline.engine.versions import code_version
from pipeline.io import atomic
from pipeline.io.capture import Capture
from pipeline.io.digest import bytes_digest, canonical_json, text_digest
from pipeline.io.frames_io import DamagedFileError, problem_of
from pipeline.io.run_layout import MANIFEST, MARKER, read_manifest_file

log = logging.getLogger(__name__)

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
    for name, path in (params.input_files() if hasattr(params, "input_files") else {}).items():
        inputs[f"file:{name}"] = file_digest(path)
    record = {"stage": stage.name, "code_version": code_version(stage), "params": params_to_dict(params),
              "inputs": inputs}
    return Expected(record, text_digest(canonical_json(record)), tuple(missing))


def file_digest(path: Path) -> str | None:
    """SHA-256 of a file's bytes (None when it cannot be read: the stage's own check then says why)."""
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return None


def streamed_key(stage: Stage, capture: Capture, params: Any, output_root: Path, upstream_key: str) -> str:
    """The key a streaming stage's marker holds while it runs alongside its last input stage.

    Its cache key names that upstream's output digest, which is known only once the upstream has
    finished; the upstream's own cache key stands for it meanwhile (the same key makes the same files,
    which is what the cache rests on). A run killed while both ran then finds this key in the marker and
    keeps the frames already computed (:meth:`~pipeline.engine.runner.Runner.run_stage`), instead of a
    tracking folder emptied for want of a key to compare.
    """
    record = expected_record(stage, capture, params, output_root).record
    inputs = {**record["inputs"], f"stage:{stage.inputs[-1]}": f"key:{upstream_key}"}
    return text_digest(canonical_json({**record, "inputs": inputs}))


def read_manifest(folder: Path) -> dict | None:
    """The stage's manifest, or ``None`` when missing or unreadable (a logged cache miss)."""
    path = folder / MANIFEST
    try:
        manifest = read_manifest_file(folder)
        if manifest is None:
            return None
        if not all(key in manifest for key in ("cache_key", "params", "inputs", "code_version", "outputs")):
            raise DamagedFileError(path, "missing keys")
        outputs = manifest["outputs"]
        if not isinstance(manifest["inputs"], dict) or not isinstance(outputs, dict) or not isinstance(
                outputs.get("digest"), str) or not isinstance(outputs.get("contents"), dict):
            raise DamagedFileError(path, "malformed inputs or outputs")
    except (OSError, DamagedFileError) as error:
        log.warning("%s: unreadable manifest (%s); the stage will run again", path, problem_of(error))
        return None
    return manifest


def output_files(folder: Path) -> list[Path]:
    """The stage's result files, sorted, without the manifest, the marker and temporary files."""
    return sorted(path for path in folder.rglob("*") if path.is_file()
                  and path.relative_to(folder).as_posix() not in (MANIFEST, MARKER)
                  and not path.name.startswith(atomic.TEMP_PREFIX))


def unrecorded_files(folder: Path) -> list[str]:
    """The files (relative paths) of a finished stage folder that its manifest does not list: not the stage's
    results, but put there since (a user's notes); none for a folder without a manifest, whose files are those
    of a run that did not finish."""
    manifest = read_manifest(folder)
    if manifest is None:
        return []
    recorded = manifest["outputs"]["contents"]
    names = (path.relative_to(folder).as_posix() for path in output_files(folder))
    return [name for name in names if name not in recorded]


def output_contents(folder: Path) -> dict[str, str]:
    """Relative path -> content hash of each of the stage's result files.

    Reading and hashing every file is what makes a damaged file visible, whatever its format; the ~900
    files of a 112-frame, 6-camera capture (13 MB) take a small fraction of a second once they are in the
    page cache (tests/pipeline/test_runner.py checks 1000 files in under half a second).
    """
    return {path.relative_to(folder).as_posix(): bytes_digest(path.read_bytes()) for path in output_files(folder)}


def describe_outputs(folder: Path) -> dict:
    """Count, bytes, each file's content hash and their digest (for downstream keys) of the stage's files."""
    contents = output_contents(folder)
    return {"files": len(contents), "bytes": sum((folder / name).stat().st_size for name in contents),
            "digest": text_digest("".join(f"{name}\0{digest}\n" for name, digest in contents.items())),
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
        parts = [f"{len(names)} {what} ({listing(names)})" for what, names in
                 (("damaged", self.changed), ("missing", self.missing), ("added", self.added)) if names]
        return "output files changed on disk: " + ", ".join(parts)


def listing(names: Sequence[str], shown: int = 3) -> str:
    return ", ".join(names[:shown]) + (", ..." if len(names) > shown else "")


def output_changes(folder: Path, manifest: dict) -> OutputChanges:
    """Compare the stage's files with the content hashes its manifest recorded."""
    recorded, now = manifest["outputs"]["contents"], output_contents(folder)
    return OutputChanges(changed=tuple(name for name in recorded if name in now and now[name] != recorded[name]),
                         missing=tuple(name for name in recorded if name not in now),
                         added=tuple(name for name in now if name not in recorded))
