"""A body file given to the tracker by its path is read by the pipeline, checked at the door, one-line errors."""

from __future__ import annotations

from importlib import resources

import numpy as np
import pytest
from conftest import make_capture

from calib.errors import InputError
from pipeline.cli import main
from pipeline.io.body_io import tracking_body
from pipeline.io.run_layout import MANIFEST
from stages.tracking.body_file import load_body
from stages.tracking.params import TrackerParams
from stages.tracking.tracker import Tracker

VOLUME = np.array([[-2.0, -2.0, 0.0], [2.0, 2.0, 2.3]])


def shipped_text(name: str) -> str:
    return (resources.files("stages.tracking") / "bodies" / f"{name}.yaml").read_text()


@pytest.mark.parametrize("text", ["segments: [unclosed", "- a list\n- not a body\n", "name: half\nheight_m: 1.7\n"])
def test_a_bad_body_file_is_a_one_line_input_error_naming_it(tmp_path, text):
    path = tmp_path / "mine.yaml"
    path.write_text(text)
    params = TrackerParams(body=str(path))  # a path is only a name until the pipeline reads it
    with pytest.raises(InputError) as error:
        tracking_body(params)
    message = str(error.value)
    assert "\n" not in message and message.startswith(f"tracking.body: {path}:") and "expected" in message, message


def test_a_missing_body_file_is_a_one_line_input_error_naming_it(tmp_path):
    path = tmp_path / "nowhere.yaml"
    with pytest.raises(InputError, match=f"^tracking.body: {path}: cannot read the body file"):
        tracking_body(TrackerParams(body=str(path)))


def test_a_body_file_given_by_its_path_is_the_body_it_describes(tmp_path):
    path = tmp_path / "mine.yaml"
    path.write_text(shipped_text("paper"))
    body = tracking_body(TrackerParams(body=str(path), estimate_lengths=()))
    assert body.pose_size == load_body("paper").pose_size
    with pytest.raises(InputError, match="tracking.estimate_lengths: .* of body 'paper'"):
        tracking_body(TrackerParams(body=str(path)))  # the paper's body has no length groups


def test_a_shipped_body_is_checked_when_the_parameters_are_made():
    with pytest.raises(InputError, match="tracking.estimate_lengths: .* of body 'paper'"):
        TrackerParams(body="paper")
    with pytest.raises(InputError, match="^tracking.body: body 'centaur': no such body configuration"):
        TrackerParams(body="centaur")


def test_the_tracker_of_a_body_file_takes_the_body_the_pipeline_read(tmp_path):
    path = tmp_path / "mine.yaml"
    path.write_text(shipped_text("default"))
    params = TrackerParams(body=str(path))
    with pytest.raises(InputError, match="read by pipeline.io.body_io"):
        Tracker(params, VOLUME)  # the tracker never opens a file
    tracker = Tracker(params, VOLUME, tracking_body(params))
    assert tracker.body.pose_size == Tracker(TrackerParams(), VOLUME).body.pose_size


def test_the_cli_refuses_a_bad_body_file_in_one_line_before_any_work(tmp_path, capsys):
    capture, out = make_capture(tmp_path / "capture"), tmp_path / "out"
    body = tmp_path / "mine.yaml"
    body.write_text("segments: [unclosed")
    assert main(["run", str(capture), "--out", str(out), "-q", "--set", f"tracking.body={body}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: tracking.body: {body}:"), err
    assert not list(out.rglob(MANIFEST))
