"""Atomic file writes: write to a temporary name in the same folder, then ``os.replace``.

``os.replace`` within one file system is atomic: a reader (or a resumed run) sees either the old file,
no file, or the complete new file, never a partial one. The pipeline relies on this to record
per-frame completion by the mere existence of a frame's output file.

Temporary files are named ``.tmp-<pid>-<tag>-<number>-<final name>`` (``tag`` drawn at random once per
process, ``number`` counting its files) so that (a) they keep the final file's extension (OpenCV and
open3d choose the format from it), (b) two processes never pick the same name, not even with the same
pid in two containers sharing a folder, and (c) a run killed mid-write leaves only names starting with
:data:`TEMP_PREFIX`, which :func:`remove_temp_files` clears and output listings skip.

No fsync: this protects against killed processes, not against power loss. Every per-frame output can be
computed again from the capture, and a resume trusts a kept file only when its content check passes
(:func:`pipeline.io.frames_io.file_problem`), so a file that a power loss left empty or torn is recomputed;
an fsync per file would instead make the disk's latency part of every frame's cost.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import secrets
from collections.abc import Iterator
from pathlib import Path

#: Prefix of every temporary file this module creates.
TEMP_PREFIX = ".tmp-"

#: How :func:`write_bytes` creates its temporary file: never one that exists already (O_EXCL), so that a
#: name clash fails instead of sharing a file, and not inherited by child processes.
_CREATE_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0)
#: This process's part of the temporary names, drawn once: a random draw per file would cost a system call.
_PROCESS_TAG = secrets.token_hex(4)
_temp_numbers = itertools.count()


def _draw_process_tag() -> None:
    """A new tag and count for this process: a forked child (a batch worker) must not share its parent's."""
    global _PROCESS_TAG, _temp_numbers
    _PROCESS_TAG = secrets.token_hex(4)
    _temp_numbers = itertools.count()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_draw_process_tag)


def temp_path_for(path: Path) -> Path:
    """A fresh temporary name next to ``path``, ending with ``path``'s own name."""
    return path.with_name(f"{TEMP_PREFIX}{os.getpid()}-{_PROCESS_TAG}-{next(_temp_numbers)}-{path.name}")


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path to write; move it to ``path`` when the block ends without error.

    On an exception the temporary file is removed and ``path`` is left as it was. The parent
    folder is created if needed.

    Examples
    --------
    >>> with atomic_output(out / "000001.png") as tmp:      # doctest: +SKIP
    ...     cv2.imwrite(str(tmp), mask)
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path_for(path)
    try:
        yield tmp
        if not tmp.exists():
            raise OSError(f"{path}: nothing was written to the temporary file {tmp.name}")
        os.replace(tmp, path)
    except OSError as error:
        if _names_no_file(error):
            raise _naming_the_file(error, path) from error
        raise
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Atomically write ``data`` to ``path``, creating its folder if needed.

    The writer of every per-frame file, so its way through is the fewest system calls: create the temporary
    file, write, close, replace. The folder is made only when creating the file finds it missing (once per
    folder rather than once per file), and the temporary file is removed only when something failed.
    """
    path = Path(path)
    tmp, descriptor = _create_temporary(path)
    try:
        try:
            remaining = memoryview(data)
            while remaining:  # os.write may write less than asked (a signal, a pipe): write the rest
                remaining = remaining[os.write(descriptor, remaining):]
        finally:
            os.close(descriptor)
        os.replace(tmp, path)
    except BaseException as error:  # a full disk, a kill signal's KeyboardInterrupt: no temporary file stays
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(error, OSError) and _names_no_file(error):
            raise _naming_the_file(error, path) from error
        raise


def _create_temporary(path: Path) -> tuple[Path, int]:
    """A new temporary file next to ``path``, open for writing: its name and descriptor."""
    tmp = temp_path_for(path)
    try:
        return tmp, os.open(tmp, _CREATE_FLAGS, 0o666)
    except FileNotFoundError:  # the folder's first file
        path.parent.mkdir(parents=True, exist_ok=True)
    return tmp, os.open(tmp, _CREATE_FLAGS, 0o666)


def _names_no_file(error: OSError) -> bool:
    """Whether ``error`` is a system error that names no file, as a write's (a full disk) does not."""
    return error.errno is not None and error.filename is None


def _naming_the_file(error: OSError, path: Path) -> OSError:
    """``error`` naming ``path``: the same errno and so the same type (OSError picks the subclass)."""
    return OSError(error.errno, error.strerror, str(path))


def write_text(path: str | os.PathLike, text: str) -> None:
    """Atomically write ``text`` (UTF-8) to ``path``."""
    write_bytes(path, text.encode("utf-8"))


def remove_temp_files(folder: str | os.PathLike) -> int:
    """Delete leftover temporary files under ``folder`` (recursively); return how many."""
    count = 0
    for leftover in Path(folder).rglob(f"{TEMP_PREFIX}*"):
        if leftover.is_file():
            leftover.unlink(missing_ok=True)
            count += 1
    return count
