"""Every WARNING a run logs, kept in ``<out>/warnings.json`` for the report and for the user.

A run prints warnings as they happen, and they scroll away behind progress bars and the closing table;
the report lists them (issue: a run that says "success" while it lost frames). Each warning is filed
under the stage that was running when it was logged (``None``: the run itself, e.g. opening the capture
or deciding what is stale)::

    {"warnings": [{"stage": "tracking", "logger": "pipeline.graph", "template": "frame %d: pose %s, ...",
                   "message": "frame 41: pose lost, not exported (12 observations)"}, ...]}

The file is the story of the results the folder holds, not only of the last command: a stage that is up
to date keeps the warnings of the run that computed it, a stage that runs replaces its own, and the run's
own warnings are this run's. (A stage resumed after an interruption keeps only what it logged since.)

Which stage a warning belongs to: the runner marks the thread that runs a stage (:func:`stage_scope`); a
worker process's warnings are logged again in that thread when its chunk of frames is done
(:func:`pipeline.engine.executors.relog`). The file is rewritten atomically, at most every :data:`WRITE_INTERVAL_S`
while warnings arrive, and whenever a stage starts or ends, the log closes, or :func:`read_warnings` asks.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from pipeline.io import frames_io
from pipeline.io.run_layout import WARNINGS_FILE

#: Shortest time between two rewrites of the file while warnings arrive (a run that loses every frame
#: logs one warning per frame; rewriting the whole file for each would cost quadratic time).
WRITE_INTERVAL_S = 0.5

_lock = threading.RLock()
_thread_stage: dict[int, str] = {}      # thread ident -> stage it runs
_logs: list[WarningLog] = []            # the open logs, told when a stage starts


class WarningLog(logging.Handler):
    """A logging handler that keeps the run's WARNING records and writes them to ``<out>/warnings.json``.

    It collects from the moment it is installed (warnings while the capture is opened count too) and
    writes once :meth:`attach` names the output folder (inside the run's lock, so that two runs never
    write the same file). Records of earlier runs for stages that do not run again are kept.
    """

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.path: Path | None = None
        self.records: list[dict] = []       # this run's
        self.kept: list[dict] = []          # earlier runs', of stages that have not run again
        self._written_at = 0.0
        self._dirty = False
        self._stage_ran = False

    def attach(self, output_root: str | os.PathLike) -> None:
        """Start writing to ``<output_root>/warnings.json``, keeping its stage warnings from earlier runs."""
        with _lock:
            self.path = Path(output_root) / WARNINGS_FILE
            self.kept = [record for record in _read(self.path) if record.get("stage") is not None]
            _logs.append(self)
            self._write()

    def stage_started(self, stage: str) -> None:
        """Forget what ``stage`` logged before: it computes its results again."""
        with _lock:
            self.kept = [record for record in self.kept if record.get("stage") != stage]
            self.records = [record for record in self.records if record.get("stage") != stage]
            self._stage_ran = True
            self._write()

    def emit(self, record: logging.LogRecord) -> None:
        try:
            template = getattr(record, "template", record.msg)  # a worker's record carries it (relog)
            entry = {"stage": _thread_stage.get(record.thread), "logger": record.name,
                     "template": template if isinstance(template, str) else None, "message": record.getMessage()}
        except Exception:  # a malformed call must not end the run; logging reports it as usual
            self.handleError(record)
            return
        with _lock:
            self.records.append(entry)
            self._dirty = True
            if time.monotonic() - self._written_at >= WRITE_INTERVAL_S:
                with contextlib.suppress(OSError):  # a full disk, say: written again at the stage's end,
                    self._write()                        # where the error is the run's to report

    def flush(self) -> None:
        with _lock:
            if self._dirty:
                self._write()

    def close(self) -> None:
        with _lock:
            self.flush()
            if self in _logs:
                _logs.remove(self)
        super().close()

    def _write(self) -> None:
        # Nothing is written before a stage runs into a folder that has no such file yet: a run refused at
        # once leaves no trace (``output_folder.output_lock`` removes the folder it made when it stays empty).
        if self.path is None or not (self._stage_ran or self.path.exists()):
            return
        frames_io.write_json(self.path, {"warnings": self.kept + self.records})
        self._written_at, self._dirty = time.monotonic(), False


def _read(path: Path) -> list[dict]:
    """The warnings of ``path``; none when it is missing or not a warnings file (it is rewritten whole)."""
    try:
        content = frames_io.read_json(path) if path.is_file() else {}
    except (OSError, frames_io.DamagedFileError):
        return []
    entries = content.get("warnings") if isinstance(content, dict) else None
    return [entry for entry in entries if isinstance(entry, dict) and isinstance(entry.get("message"), str)
            ] if isinstance(entries, list) else []


@contextlib.contextmanager
def stage_scope(stage: str) -> Iterator[None]:
    """Warnings logged by this thread during the block belong to ``stage``, which runs afresh."""
    ident = threading.get_ident()
    with _lock:
        _thread_stage[ident] = stage
        for log in _logs:
            log.stage_started(stage)
    try:
        yield
    finally:
        with _lock:
            _thread_stage.pop(ident, None)
            for log in _logs:
                log.flush()


def read_warnings(output_root: str | os.PathLike) -> list[dict]:
    """The warnings recorded for ``output_root`` (see the module docstring), up to this moment."""
    path = Path(output_root) / WARNINGS_FILE
    with _lock:
        for log in _logs:
            if log.path == path:
                log.flush()
    return _read(path)


@contextlib.contextmanager
def collecting() -> Iterator[WarningLog]:
    """Collect the warnings logged during the block (see :class:`WarningLog`); the caller attaches it."""
    log = WarningLog()
    root = logging.getLogger()
    root.addHandler(log)
    try:
        yield log
    finally:
        root.removeHandler(log)
        log.close()
