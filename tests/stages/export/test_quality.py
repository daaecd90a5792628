import csv
import io

import numpy as np
import pytest

from stages.export.quality import UNSUPPORTED_CONFIDENCE, FrameQuality, format_quality_csv, joint_confidence
from stages.joints import JOINT_NAMES

J = len(JOINT_NAMES)


def _quality(support: np.ndarray, statuses: list[str]) -> FrameQuality:
    n = len(statuses)
    fitted = np.array([s in ("tracked", "initialised") for s in statuses])
    return FrameQuality(frames=np.arange(10, 10 + n), statuses=np.array(statuses), doubtful=np.zeros(n, bool),
                        observations=np.where(fitted, 1000, 5), log_likelihood=np.where(fitted, 2500.0, 0.0),
                        outlier_fraction=np.where(fitted, 0.05, 1.0), support=support, fitted=fitted,
                        corrected=np.full(n, ""))


def test_confidence_is_the_support_over_its_usual_level_carried_down_each_chain():
    support = np.full((5, J), 100.0)
    elbow, wrist, knee = (JOINT_NAMES.index(n) for n in ("l_elbow", "l_wrist", "l_knee"))
    support[2, elbow] = 20.0   # the upper arm explains a fifth of its usual data
    support[3, wrist] = 60.0   # the forearm a bit less than usual
    support[4, knee] = 250.0   # more than usual: still 1
    confidence = joint_confidence(support, np.ones(5, bool), JOINT_NAMES)
    assert confidence[2, elbow] == pytest.approx(0.2) and confidence[2, wrist] == pytest.approx(0.2)
    assert confidence[3, wrist] == pytest.approx(0.6) and confidence[3, elbow] == 1.0
    assert confidence[4, knee] == 1.0
    assert confidence[0].min() == 1.0


def test_frames_not_fitted_and_segments_never_seen_have_no_confidence():
    support = np.full((3, J), 50.0)
    support[1] = np.nan
    support[:, JOINT_NAMES.index("r_toe")] = 0.0
    confidence = joint_confidence(support, np.array([True, False, True]), JOINT_NAMES)
    assert (confidence[1] == 0).all() and (confidence[:, JOINT_NAMES.index("r_toe")] == 0).all()
    assert confidence[0, 0] == 1.0


def test_quality_csv_marks_a_tracked_frame_whose_forearm_is_unsupported():
    support = np.full((4, J), 80.0)
    support[1, JOINT_NAMES.index("r_wrist")] = 80.0 * (UNSUPPORTED_CONFIDENCE - 0.1)
    support[3] = np.nan
    text = format_quality_csv(_quality(support, ["initialised", "tracked", "tracked", "predicted"]), JOINT_NAMES)
    rows = list(csv.DictReader(io.StringIO(text)))
    assert [row["frame"] for row in rows] == ["10", "11", "12", "13"]
    assert rows[1]["status"] == "tracked" and rows[1]["unsupported"] == "r_wrist"
    assert float(rows[1]["r_wrist_confidence"]) == pytest.approx(UNSUPPORTED_CONFIDENCE - 0.1)
    assert rows[0]["unsupported"] == "" and float(rows[0]["log_likelihood_per_observation"]) == pytest.approx(2.5)
    assert rows[3]["status"] == "predicted" and rows[3]["log_likelihood_per_observation"] == ""
    assert rows[3]["observations"] == "5" and float(rows[3]["pelvis_confidence"]) == 0.0
    assert list(rows[0])[:7] == ["frame", "status", "doubtful", "observations", "log_likelihood_per_observation",
                                 "outlier_fraction", "unsupported"]
