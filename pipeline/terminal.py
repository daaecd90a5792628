"""What the pipeline echoes to the terminal, made harmless.

Messages and logs repeat names read from files: camera names from a calibration, folder and file names
of a capture. A terminal acts on some characters instead of showing them: ESC starts sequences that can
retitle the window, clear it, move the cursor or rewrite what was printed; a line break splits a one-line
error; a bidirectional override reverses the text after it. :func:`printable` writes each such character
as its Python escape (``\\x1b``, ``\\n``, ``\\u202e``), so the user sees what the file holds.

Per-frame warnings that repeat (a recording that starts before the subject walks in has no silhouette, no
observations and no pose on each of its first frames) are written once per run of frames rather than once a
frame (:class:`FoldingStreamHandler`); ``warnings.json`` and the report keep every one.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Hashable, Iterable, Sequence

#: A per-frame message: ``frame <number>: <what happened>``.
_FRAME_MESSAGE = re.compile(r"frame (\d+): (.+)", re.DOTALL)
#: Longest time a per-frame message is held back, waiting for the same message on other frames (seconds).
FOLD_WINDOW_S = 5.0


def printable(text: str) -> str:
    """``text`` with every non-printable character (``str.isprintable``: control and format characters,
    line and paragraph separators, unusual spaces) written as its backslash escape."""
    if text.isprintable():
        return text
    return "".join(character if character.isprintable() else character.encode("unicode_escape").decode("ascii")
                   for character in text)


class PrintableFormatter(logging.Formatter):
    """A log formatter whose messages are :func:`printable` (a traceback after one keeps its lines)."""

    def formatMessage(self, record: logging.LogRecord) -> str:
        return printable(super().formatMessage(record))


def frame_ranges(frames: Sequence[int]) -> str:
    """Increasing frame numbers as runs of consecutive ones: ``[0, 1, 2, 5, 7, 8]`` -> ``"0-2, 5, 7-8"``."""
    runs: list[list[int]] = []
    for frame in frames:
        if runs and frame == runs[-1][1] + 1:
            runs[-1][1] = frame
        else:
            runs.append([frame, frame])
    return ", ".join(str(first) if first == last else f"{first}-{last}" for first, last in runs)


def frame_message(frames: Sequence[int], text: str) -> str:
    """``frame 3: <text>`` for one frame, ``frames 0-19, 25 (21 frames): <text>`` for several (increasing)."""
    if len(frames) == 1:
        return f"frame {frames[0]}: {text}"
    return f"frames {frame_ranges(frames)} ({len(frames)} frames): {text}"


def fold_frame_messages(messages: Sequence[str]) -> list[str]:
    """``messages`` with those that differ only in their frame (``frame N: <text>``) made one
    (:func:`frame_message`), at the place of the first of them; the others as they are."""
    return [message for _, message in _folded((None, message) for message in messages)]


def _folded(items: Iterable[tuple[Hashable, str]]) -> list[tuple[int, str]]:
    """``(key, message)`` items folded as :func:`fold_frame_messages` folds messages, per-frame ones only with
    others of the same key: ``(index of the item the line stands for, line)``, in the order of those items."""
    lines: list[tuple[int, str | list[int], str]] = []  # (item, message or the frames of a text, text)
    texts: dict[tuple[Hashable, str], list[int]] = {}  # (key, text) -> its frames, filled in place
    for index, (key, message) in enumerate(items):
        match = _FRAME_MESSAGE.fullmatch(message)
        if match is None:
            lines.append((index, message, ""))
        else:
            if (key, match[2]) not in texts:
                texts[key, match[2]] = []
                lines.append((index, texts[key, match[2]], match[2]))
            texts[key, match[2]].append(int(match[1]))
    return [(index, line if isinstance(line, str) else frame_message(sorted(set(line)), text))
            for index, line, text in lines]


class FoldingStreamHandler(logging.StreamHandler):
    """A stream handler that writes the same per-frame message of several frames as one line naming them.

    A record whose message is ``frame N: <text>`` is held, with the frames of the records of the same logger,
    level and text, until a record of another kind is written, :meth:`flush` is called (the runner does at the
    end of every stage) or the first held one is :data:`FOLD_WINDOW_S` old; then each held text is written once,
    in the order they first came: ``frames 0-19 (20 frames): <text>``. Every other record is written at once,
    after the held ones, so that the order of events is kept.
    """

    def __init__(self, stream=None) -> None:
        super().__init__(stream)
        self._held: list[logging.LogRecord] = []  # per-frame records not written yet
        self._held_since = 0.0

    def emit(self, record: logging.LogRecord) -> None:
        try:
            match = _FRAME_MESSAGE.fullmatch(record.getMessage())
        except Exception:  # a malformed call: logging reports it as usual
            self.handleError(record)
            return
        if match is None:
            self._release()
            super().emit(record)
            return
        if not self._held:
            self._held_since = time.monotonic()
        self._held.append(record)
        if time.monotonic() - self._held_since >= FOLD_WINDOW_S:
            self._release()

    def flush(self) -> None:
        with self.lock:
            self._release()
        super().flush()

    def _release(self) -> None:
        """Write the held messages, one line each."""
        held, self._held = self._held, []
        for index, message in _folded(((r.name, r.levelno), r.getMessage()) for r in held):
            super().emit(logging.makeLogRecord({**vars(held[index]), "msg": message, "args": None}))
