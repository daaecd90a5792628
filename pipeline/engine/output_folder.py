"""The output folder: refusing one that overlaps the capture, stage folders the runner made (and only
those emptied), the lock against a second concurrent run, the storage errors told in one line, and
``run.json`` (which capture and parameters the folder is for, and how the last run went)."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import shutil
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from calib.errors import InputError
from pipeline.engine.cache import unrecorded_files
from pipeline.engine.params import params_to_dict
from pipeline.io import atomic, frames_io
from pipeline.io.capture import Capture
from pipeline.io.run_layout import LOCK, MARKER, RUN_RECORD, WARNINGS_FILE


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
    runner's to delete; nor is a finished stage's folder holding files its manifest does not list.
    """
    if (folder.exists() or folder.is_symlink()) and not written_by_runner(folder):
        raise InputError(f"{folder}: not a stage folder written by the pipeline (no {MARKER} in it); "
                         "refusing to delete it (expected only the pipeline's own folders in --out; "
                         "move it away or choose another --out)")
    unrecorded = unrecorded_files(folder) if folder.exists() else []
    if unrecorded:
        raise InputError(f"{folder / unrecorded[0]}: not written by the pipeline ({len(unrecorded)} such file(s) in "
                         f"{folder.name}/), refusing to delete it with the stage's old results (expected only the "
                         "pipeline's files in its stage folders: move it out)")
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    atomic.write_text(folder / MARKER, key + "\n")


def check_own_files(output_root: Path) -> None:
    """Refuse an output folder whose ``run.json`` or ``warnings.json`` the pipeline did not write: a run rewrites
    both, and a user's files of those names would be lost."""
    for name, ours in ((RUN_RECORD, lambda data: isinstance(data, dict) and {"capture", "state"} <= data.keys()),
                       (WARNINGS_FILE, lambda data: isinstance(data, dict) and isinstance(data.get("warnings"), list))):
        path = output_root / name
        if not path.is_file():
            continue
        try:
            written = ours(frames_io.read_json(path))
        except (OSError, frames_io.DamagedFileError):
            written = False
        if not written:
            raise InputError(f"{path}: not written by the pipeline, which keeps its own record under this name "
                             "(expected an output folder without it: move it away or choose another --out)")


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
    where = os.fspath(error.filename) if error.filename else ""
    if not os.path.isabs(where):  # a name relative to a folder being emptied (shutil.rmtree's), or none
        where = f"{output_root}{f' ({where})' if where else ''}"
    return InputError(f"{where}: {error.strerror} (expected {expected})")


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
