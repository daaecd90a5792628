"""What the pipeline echoes is shown, not obeyed, by the terminal."""

from __future__ import annotations

import io
import logging

import pytest

from pipeline import terminal
from pipeline.terminal import FoldingStreamHandler, PrintableFormatter, fold_frame_messages, frame_ranges, printable


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


def test_frame_ranges_are_runs_of_consecutive_frames():
    assert frame_ranges([0, 1, 2, 5, 7, 8]) == "0-2, 5, 7-8"
    assert frame_ranges([4]) == "4"


def test_messages_that_differ_only_in_their_frame_are_folded_where_the_first_stood():
    messages = ["frame 56: empty", "frame 57: empty", "frame 56: only 0 observations", "volume touched",
                "frame 50: empty", "frame 57: only 12 observations"]
    assert fold_frame_messages(messages) == [
        "frames 50, 56-57 (3 frames): empty", "frame 56: only 0 observations", "volume touched",
        "frame 57: only 12 observations"]


def _logged(handler: FoldingStreamHandler, *messages: str, logger: str = "pipeline.graph") -> None:
    for message in messages:
        handler.handle(logging.LogRecord(logger, logging.WARNING, __file__, 1, message, None, None))


@pytest.fixture
def folding():
    stream = io.StringIO()
    handler = FoldingStreamHandler(stream)
    handler.setFormatter(logging.Formatter("%(name)s: %(message)s"))
    return handler, stream


def test_a_message_repeated_on_consecutive_frames_is_written_once_with_its_frames(folding):
    # A recording that starts before the subject walks in: three warnings on each of its first frames.
    handler, stream = folding
    for frame in range(20):
        _logged(handler, f"frame {frame}: empty silhouette in camera(s) cam0, cam1", f"frame {frame}: pose lost")
    _logged(handler, "frame 25: pose lost", "frame 30: only 3 observations")
    assert stream.getvalue() == ""  # held until a message of another kind, or a flush
    _logged(handler, "export: 21 of 40 frames were not estimated")
    assert stream.getvalue().splitlines() == [
        "pipeline.graph: frames 0-19 (20 frames): empty silhouette in camera(s) cam0, cam1",
        "pipeline.graph: frames 0-19, 25 (21 frames): pose lost",
        "pipeline.graph: frame 30: only 3 observations",
        "pipeline.graph: export: 21 of 40 frames were not estimated"]


def test_held_frames_are_written_on_a_flush_and_after_the_fold_window(folding, monkeypatch):
    handler, stream = folding
    _logged(handler, "frame 3: pose lost")
    _logged(handler, "frame 3: pose lost", logger="other")  # another logger's message stays its own line
    handler.flush()  # the runner flushes at the end of every stage
    assert stream.getvalue().splitlines() == ["pipeline.graph: frame 3: pose lost", "other: frame 3: pose lost"]
    clock = iter([100.0, 100.0, 100.0 + terminal.FOLD_WINDOW_S])  # held since, its age, the next one's age
    monkeypatch.setattr(terminal.time, "monotonic", lambda: next(clock))
    _logged(handler, "frame 4: pose lost", "frame 5: pose lost")  # the second comes a fold window after the first
    assert stream.getvalue().splitlines()[-1] == "pipeline.graph: frames 4-5 (2 frames): pose lost"
