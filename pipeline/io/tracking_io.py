"""The tracking stage's per-frame records, read back: by the stage itself when it resumes, by the export,
and by the run's summary and report. One reader, so that all of them refuse the same damaged records."""

from __future__ import annotations

from pathlib import Path

from pipeline.io import frames_io
from pipeline.io.run_layout import tracking_path
from stages.tracking.results import FrameResult, TrackerState, read_frame_record


def read_tracking(folder: Path, frame: int) -> tuple[FrameResult, TrackerState]:
    """One frame's tracking record in the tracking stage's ``folder``: its estimate and the tracker's state
    after it.

    Raises :class:`~pipeline.io.frames_io.DamagedFileError` when the record fails its content check or is
    not a record of this frame with a (17, 3) array of joints and a known status.
    """
    path = tracking_path(folder, frame)
    record = frames_io.read_record(path)
    try:
        return read_frame_record(record, frame)
    except ValueError as error:
        raise frames_io.DamagedFileError(path, str(error)) from None
