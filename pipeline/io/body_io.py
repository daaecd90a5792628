"""The tracker's body when ``tracking.body`` names a body file: read here, where the pipeline owns the disk.

A shipped body ("default", "paper") is part of the tracker's code and loads from its package
(``stages.tracking.body_file.load_body``); a body file of the user's is read from its path, parsed by
``stages.tracking.body_file.body_from_text`` and checked against the parameters that depend on it (the
length groups to estimate) before any work, every error one line naming the file.
"""

from __future__ import annotations

from pathlib import Path

from calib.errors import InputError
from stages.tracking.body import BodyModel
from stages.tracking.body_file import body_from_text, is_body_path
from stages.tracking.params import TrackerParams, check_length_groups, shipped_body


def read_body_file(path: Path) -> BodyModel:
    """The body described by the body file at ``path``.

    Raises
    ------
    InputError
        If the file cannot be read or is not a body description (one line naming the file).
    """
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        reason = error.strerror if isinstance(error, OSError) else "not UTF-8 text"
        raise InputError(f"{path}: cannot read the body file ({reason}), expected a body description "
                         "in the layout of bodies/default.yaml") from None
    return body_from_text(text, source=str(path))


def tracking_body(params: TrackerParams) -> BodyModel:
    """The body ``params.body`` names, read and checked (``tracking.estimate_lengths`` among its length
    groups); errors are one line under ``tracking.body`` (or ``tracking.estimate_lengths``)."""
    if not is_body_path(params.body):
        return shipped_body(params.body)
    try:
        body = read_body_file(Path(params.body))
    except InputError as error:
        raise InputError(f"tracking.body: {error}") from None
    check_length_groups(params.estimate_lengths, body)
    return body
