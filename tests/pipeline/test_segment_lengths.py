"""The segment-length table of `pipeline.lab.bench.segment_lengths`."""

import numpy as np
import pytest

from pipeline.io.export_io import write_joints_csv
from pipeline.lab.bench.segment_lengths import main, median_lengths
from stages.joints import JOINT_NAMES


def test_a_longer_forearm_shows_in_its_group_and_nowhere_else(tmp_path):
    truth = np.random.default_rng(0).normal(size=(5, len(JOINT_NAMES), 3))
    estimate = truth.copy()
    for side in ("l", "r"):
        elbow, wrist = JOINT_NAMES.index(f"{side}_elbow"), JOINT_NAMES.index(f"{side}_wrist")
        estimate[:, wrist] = truth[:, elbow] + 1.2 * (truth[:, wrist] - truth[:, elbow])
    estimate[0] += 10.0 * np.arange(len(JOINT_NAMES))[:, None]  # a frame the comparison leaves out
    write_joints_csv(tmp_path / "truth.csv", np.arange(5), truth)
    write_joints_csv(tmp_path / "estimate.csv", np.arange(5), estimate)
    frames, true_lengths = median_lengths(tmp_path / "truth.csv", np.arange(1, 5))
    _, estimated = median_lengths(tmp_path / "estimate.csv", frames)
    assert list(frames) == [1, 2, 3, 4]
    ratios = {group: estimated[group] / true_lengths[group] for group in true_lengths}
    assert ratios.pop("elbow-wrist") == pytest.approx(1.2)
    assert ratios == pytest.approx(dict.fromkeys(ratios, 1.0)) and "shoulder-elbow" in ratios


def test_a_folder_that_is_no_run_is_one_line_and_exit_status_2(tmp_path, capsys):
    (tmp_path / "notes.log").write_text("not a run")
    with pytest.raises(SystemExit) as stopped:
        main([str(tmp_path / "notes.log")])
    assert stopped.value.code == 2
    error = capsys.readouterr().err
    assert error.startswith("error: ") and "notes.log" in error and error.count("\n") == 1
