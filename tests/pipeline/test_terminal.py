"""What the pipeline echoes is shown, not obeyed, by the terminal."""

from __future__ import annotations

import logging

from pipeline.terminal import PrintableFormatter, printable


def test_printable_escapes_what_a_terminal_would_act_on():
    assert printable("cam01 000002.png (expected 64x48)") == "cam01 000002.png (expected 64x48)"
    assert printable("cam\x1b]0;owned\x07\x1b[2J") == "cam\\x1b]0;owned\\x07\\x1b[2J"  # retitle, clear
    assert printable("two\nlines\r") == "two\\nlines\\r"  # a one-line error stays one line
    assert printable("abc\u202edcba") == "abc\\u202edcba"  # a right-to-left override
    assert printable("caméra 3") == "caméra 3"  # printable non-ASCII stays as it is


def test_log_messages_are_printable_and_tracebacks_keep_their_lines():
    formatter = PrintableFormatter("%(levelname)s %(message)s")
    record = logging.LogRecord("x", logging.WARNING, __file__, 1, "camera %s: no plate", ("c\x1b[2J",), None)
    assert formatter.format(record) == "WARNING camera c\\x1b[2J: no plate"
    try:
        raise RuntimeError("bug")
    except RuntimeError:
        import sys
        record.exc_info = sys.exc_info()
    assert formatter.format(record).count("\n") >= 2
