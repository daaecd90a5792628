"""Atomic file writes: write to a temporary name in the same folder, then ``os.replace``.

``os.replace`` within one file system is atomic: a reader (or a resumed run) sees either the old file,
no file, or the complete new file, never a partial one. The pipeline relies on this to record
per-frame completion by the mere existence of a frame's output file.

Temporary files are named ``.tmp-<random>-<final name>`` so that (a) they keep the final file's
extension (OpenCV and open3d choose the format from it) and (b) a run killed mid-write leaves
only names starting with :data:`TEMP_PREFIX`, which :func:`remove_temp_files` clears and output
listings skip. No fsync: this protects against killed processes, not against power loss.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterator
from pathlib import Path

#: Prefix of every temporary file this module creates.
TEMP_PREFIX = ".tmp-"


def temp_path_for(path: Path) -> Path:
    """A fresh temporary name next to ``path``, ending with ``path``'s own name."""
    return path.with_name(f"{TEMP_PREFIX}{os.getpid()}-{secrets.token_hex(4)}-{path.name}")


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
        if error.errno is None or error.filename is not None:
            raise
        # A write's error (a full disk) names no file: name the one being written (same errno, same type).
        raise OSError(error.errno, error.strerror, str(path)) from error
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Atomically write ``data`` to ``path``."""
    with atomic_output(path) as tmp:
        tmp.write_bytes(data)


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
