"""The capture reader: :meth:`Capture.open` validates a capture directory (CAPTURE_FORMAT.md) and returns a
:class:`Capture` (see :mod:`pipeline.io.capture.reader`)."""

from pipeline.io.capture.reader import Capture, capture_summary
from pipeline.io.capture.volume import derive_volume

__all__ = ["Capture", "capture_summary", "derive_volume"]
