import numpy as np
import pytest

from pipeline.io import frames_io
from pipeline.report.tracking_summary import (
    category_totals,
    frame_status,
    read_body_height,
    read_frame_statuses,
    summary_line,
    tracker_params,
)
from stages.joints import JOINT_NAMES
from stages.tracking.results import BodyHeight, FrameResult, TrackerState, frame_record, read_frame_record

PARAMS = {"max_outlier_fraction": 0.6, "failure_sigma_m": 0.05, "max_sigma_m": 0.06, "min_observations": 30,
          "max_predicted_frames": 10, "reinit_every": 0}


def record(frame, status, *, doubtful=False, outliers=0.05, spread_m=0.02, recheck=False, since=0, height_m=1.7,
           measured_m=None, spread_level=np.nan, spread_variance=np.nan, corrected=()):
    """A tracking record as the tracker writes it (`frame_record`), with the fields the summary reads set."""
    fitted = status in ("tracked", "initialised")
    result = FrameResult(pose=np.zeros(6), joints=np.zeros((len(JOINT_NAMES), 3)),
                         log_likelihood=3000.0 + frame if fitted else 0.0, iterations=3,
                         outlier_fraction=outliers if fitted else 1.0, status=status, height_m=1.7, doubtful=doubtful,
                         corrected=corrected)
    state = TrackerState(pose=np.zeros(6), velocity=np.zeros(6), height_m=height_m, length_factors=np.ones(0),
                         height_weight=1, Sigma=np.diag([spread_m**2, (spread_m / 2) ** 2, 1e-6]), pi=np.ones(1),
                         likelihood_level=np.nan, frames_without_fit=0 if fitted else 1, lost=False,
                         since_initialisation=since, recheck=recheck, measured_height_m=measured_m,
                         spread_level=spread_level, spread_variance=spread_variance)
    return frame_record(frame, result, state)


def causes(current, previous=None, params=PARAMS, fitted_before=True):
    def read(entry):
        return None if entry is None else read_frame_record(entry, entry["frame"])

    status = frame_status(current["frame"], read(current), read(previous), params, fitted_before=fitted_before)
    return status.category, status.causes


def test_initialisations_say_why_they_happened():
    assert causes(record(0, "initialised"), fitted_before=False) == ("initialised", ("first frame",))
    assert causes(record(5, "initialised"), record(4, "lost")) == (
        "initialised", ("data back after frames without a fit",))
    assert causes(record(5, "initialised"), record(4, "initialised", doubtful=True, recheck=True)) == (
        "initialised", ("re-check of a doubtful initialisation",))
    assert causes(record(5, "initialised"), record(4, "tracked", since=3), {**PARAMS, "reinit_every": 4}) == (
        "initialised", ("periodic re-initialisation",))
    assert causes(record(5, "initialised"), record(4, "tracked", since=3)) == (
        "initialised", ("the fit from the previous frame failed the checks",))


def test_a_tracked_frame_names_the_limbs_the_tracker_put_elsewhere():
    assert causes(record(3, "tracked"), record(2, "tracked")) == ("tracked", ())
    assert causes(record(3, "tracked", corrected=("l_upperarm", "l_thigh/r_thigh")), record(2, "tracked")) == (
        "tracked", ("l_upperarm put elsewhere by a search", "legs exchanged (l_thigh/r_thigh)"))
    category, why = causes(record(3, "tracked", doubtful=True, outliers=0.7, corrected=("r_upperarm",)),
                           record(2, "tracked"))
    assert category == "doubtful" and why == ("outlier share above 60 %", "r_upperarm put elsewhere by a search")


def test_a_doubtful_frame_names_the_checks_it_failed():
    category, why = causes(record(3, "tracked", doubtful=True, outliers=0.7, spread_m=0.055), record(2, "tracked"))
    assert category == "doubtful" and why == ("outlier share above 60 %", "Sigma spread above 5.0 cm")
    category, why = causes(record(0, "initialised", doubtful=True, spread_m=0.055), fitted_before=False)
    assert why == ("Sigma spread above 5.0 cm", "initialised: first frame")
    category, why = causes(record(3, "tracked", doubtful=True, spread_m=0.06), record(2, "tracked"))
    assert why == ("Sigma spread at its ceiling of 6.0 cm",)
    current = record(3, "tracked", spread_m=0.055)
    status = frame_status(3, read_frame_record(current, 3), None, PARAMS, fitted_before=True)
    assert status.category == "tracked" and status.causes == () and status.sigma_spread_m == pytest.approx(0.055)


def test_a_tracked_fit_is_judged_against_the_tracks_usual_spread():
    """On data whose good fits are wide (the level and variance in the state before the frame), the limit is
    their level plus three standard deviations (5.2 cm here); an initialisation's stays `failure_sigma_m`."""
    wide = record(2, "tracked", spread_m=0.046, spread_level=0.046, spread_variance=0.002**2)
    status = frame_status(3, read_frame_record(record(3, "tracked", doubtful=True, spread_m=0.053), 3),
                          read_frame_record(wide, 2), PARAMS, fitted_before=True)
    assert status.sigma_limit_m == pytest.approx(0.052) and status.causes == ("Sigma spread above 5.2 cm",)
    status = frame_status(3, read_frame_record(record(3, "initialised", spread_m=0.045), 3),
                          read_frame_record(wide, 2), PARAMS, fitted_before=True)
    assert status.sigma_limit_m == pytest.approx(0.05)
    status = frame_status(3, read_frame_record(record(3, "predicted"), 3), read_frame_record(wide, 2), PARAMS,
                          fitted_before=True)
    assert np.isnan(status.sigma_limit_m)


def test_frames_without_a_fit_say_whether_the_subject_was_ever_found():
    assert causes(record(3, "predicted"), record(2, "tracked")) == ("predicted", ("fewer than 30 observations",))
    assert causes(record(0, "lost"), fitted_before=False) == (
        "lost", ("fewer than 30 observations before any fit",))
    assert causes(record(20, "lost"), record(19, "lost")) == (
        "lost", ("fewer than 30 observations for more than 10 frames",))


def write_records(folder, records, params=None):
    for entry in records:
        frames_io.write_record(folder / "frames" / frames_io.frame_name(entry["frame"], ".json"), entry)
    if params is not None:
        frames_io.write_json(folder / "manifest.json", {"params": params})


def test_read_frame_statuses_follows_the_sequence_and_its_manifest(tmp_path):
    folder = tmp_path / "tracking"
    write_records(folder, [record(0, "lost"), record(1, "initialised"), record(2, "tracked", spread_m=0.045),
                           record(3, "tracked", doubtful=True, spread_m=0.045), record(4, "predicted")],
                  {**PARAMS, "failure_sigma_m": 0.04, "min_observations": 50})
    statuses = read_frame_statuses(folder, range(5))
    assert [status.category for status in statuses] == ["lost", "initialised", "tracked", "doubtful", "predicted"]
    assert statuses[0].causes == ("fewer than 50 observations before any fit",)
    assert statuses[1].causes == ("data back after frames without a fit",)
    assert statuses[3].causes == ("Sigma spread above 4.0 cm",)
    assert category_totals(statuses) == {"tracked": 1, "initialised": 1, "doubtful": 1, "predicted": 1, "lost": 1}
    assert summary_line(statuses) == (
        "tracking, 5 frames: 1 tracked, 1 initialised (data back after frames without a fit), "
        "1 doubtful (Sigma spread above 4.0 cm), 1 predicted (fewer than 50 observations), "
        "1 lost (fewer than 50 observations before any fit)")


def test_an_unfinished_tracking_stage_has_no_summary(tmp_path):
    folder = tmp_path / "tracking"
    write_records(folder, [record(0, "initialised"), record(1, "tracked")])
    assert read_frame_statuses(folder, range(3)) is None       # frame 2 not written yet
    (folder / "frames" / "000001.json").write_text("{broken")
    assert read_frame_statuses(folder, range(2)) is None


def test_tracker_params_default_where_the_manifest_is_silent(tmp_path):
    assert tracker_params(tmp_path) == PARAMS                  # no manifest: the tracker's defaults
    frames_io.write_json(tmp_path / "manifest.json", {"params": {"max_outlier_fraction": 0.5, "distance": "normals"}})
    assert tracker_params(tmp_path) == {**PARAMS, "max_outlier_fraction": 0.5}


def test_the_body_height_is_read_from_the_last_record_with_what_it_weighed(tmp_path):
    folder = tmp_path / "tracking"
    write_records(folder, [record(0, "initialised", height_m=1.75, measured_m=1.76),
                           record(1, "tracked", height_m=1.709, measured_m=1.736)], {**PARAMS, "height_m": None})
    height = read_body_height(folder, range(2), 1.683)
    assert height == BodyHeight(tracked_m=1.709, stated_m=1.683, measured_m=1.736)
    assert height.sentence() == ("Body sized for a subject 1.709 m tall "
                                 "(stated 1.683 m, measured from the data 1.736 m, +3.1 %).")
    write_records(folder, [], {**PARAMS, "height_m": 1.8})  # --set tracking.height_m overrides the capture's
    assert read_body_height(folder, range(2), 1.683).stated_m == 1.8
    assert BodyHeight(1.709, None, 1.709).sentence().endswith("1.709 m tall (as the data measure it).")
    assert BodyHeight(1.683, 1.683, None).sentence().endswith("1.683 m tall (as stated).")
    assert read_body_height(folder, range(3), 1.683) is None  # frame 2 not written yet
