"""What the pipeline echoes to the terminal, made harmless.

Messages and logs repeat names read from files: camera names from a calibration, folder and file names
of a capture. A terminal acts on some characters instead of showing them: ESC starts sequences that can
retitle the window, clear it, move the cursor or rewrite what was printed; a line break splits a one-line
error; a bidirectional override reverses the text after it. :func:`printable` writes each such character
as its Python escape (``\\x1b``, ``\\n``, ``\\u202e``), so the user sees what the file holds.
"""

from __future__ import annotations

import logging


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
