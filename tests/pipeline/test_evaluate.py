import json

import numpy as np
import pytest

from pipeline import cli
from pipeline.evaluate import evaluate_run, silhouette_iou
from pipeline.io import frames_io
from pipeline.io.export_io import write_joints_csv
from stages.joints import JOINT_NAMES


def _truth(n_frames: int) -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.uniform([-0.3, -0.3, 0.0], [0.3, 0.3, 1.8], (n_frames, 17, 3))


@pytest.fixture
def run(tmp_path):
    """A run directory whose estimate is the truth shifted by 10 mm, frame 3 of 0..9 lost."""
    capture, out = tmp_path / "capture", tmp_path / "out"
    truth = _truth(10)
    write_joints_csv(capture / "groundtruth" / "joints.csv", np.arange(10), truth)
    kept = np.array([0, 1, 2, 4, 5, 6, 7, 8, 9])
    write_joints_csv(out / "export" / "joints.csv", kept, truth[kept] + [0.0, 0.01, 0.0])
    frames_io.write_json(out / "calibration" / "capture.json", {"fps": 25.0, "capture_dir": str(capture)})
    return out, capture


def test_eval_subcommand_writes_metrics_and_prints_a_table(run, capsys):
    out, _ = run
    assert cli.main(["eval", str(out)]) == 0
    metrics = json.loads((out / "eval" / "metrics.json").read_text())
    assert metrics["mpjpe_mm"] == pytest.approx(10.0, abs=1e-3)
    assert metrics["pck"] == {"50mm": 1.0, "100mm": 1.0}
    assert metrics["fraction_estimated"] == pytest.approx(0.9)
    assert metrics["frames_scored"] == 9 and metrics["silhouette_iou"] is None
    assert set(metrics["per_joint_mpjpe_mm"]) == set(JOINT_NAMES[:15])
    printed = capsys.readouterr().out
    assert "MPJPE 10.0 mm" in printed and "l_knee_flexion" in printed and "90.0% of 10" in printed


def test_explicit_truth_and_silhouette_iou(run, tmp_path):
    out, capture = run
    (out / "calibration" / "capture.json").unlink()
    mask = np.zeros((20, 30), np.uint8)
    mask[5:15, 10:20] = 255
    shifted = np.roll(mask, 5, axis=1)       # overlaps half: IoU 50 / 150
    for frame, estimate in ((0, mask), (1, shifted)):
        frames_io.write_mask(capture / "groundtruth" / "masks" / "cam_a" / f"{frame:06d}.png", mask)
        frames_io.write_mask(out / "silhouettes" / "cam_a" / f"{frame:06d}.png", estimate)
    metrics = evaluate_run(out, truth=capture / "groundtruth" / "joints.csv")
    assert metrics["silhouette_iou"] == {"mean": pytest.approx((1 + 1 / 3) / 2),
                                         "median": pytest.approx((1 + 1 / 3) / 2), "masks_compared": 2,
                                         "per_camera": {"cam_a": pytest.approx((1 + 1 / 3) / 2)}}


def test_eval_without_a_known_truth_is_a_usage_error(run, capsys):
    out, _ = run
    frames_io.write_json(out / "calibration" / "capture.json", {"fps": 25.0})
    assert cli.main(["eval", str(out)]) == 2
    assert "no capture_dir recorded" in capsys.readouterr().err


def test_eval_without_export_is_a_usage_error(tmp_path, capsys):
    assert cli.main(["eval", str(tmp_path)]) == 2
    assert "export stage has finished" in capsys.readouterr().err


def test_silhouette_iou_is_none_without_masks(tmp_path):
    assert silhouette_iou(tmp_path / "a", tmp_path / "b") is None


def test_a_truth_in_millimetres_or_of_other_frames_is_refused(run, tmp_path, capsys):
    out, capture = run
    truth = _truth(10)
    write_joints_csv(tmp_path / "mm.csv", np.arange(10), 1000.0 * truth)
    assert cli.main(["eval", str(out), "--truth", str(tmp_path / "mm.csv")]) == 2
    assert "mm.csv: the joints of a frame spread over" in capsys.readouterr().err
    frames_io.write_json(out / "calibration" / "capture.json", {"fps": 25.0, "frames": list(range(10))})
    write_joints_csv(tmp_path / "late.csv", np.arange(100, 110), truth)
    assert cli.main(["eval", str(out), "--truth", str(tmp_path / "late.csv")]) == 2
    assert "late.csv: frames 100..109, none of them processed by the run (frames 0..9" in capsys.readouterr().err


def test_truth_joints_of_unknown_names_are_reported(run, tmp_path, caplog):
    out, capture = run
    names = ("hips",) + JOINT_NAMES[1:]
    write_joints_csv(tmp_path / "named.csv", np.arange(10), _truth(10), names=names)
    metrics = evaluate_run(out, truth=tmp_path / "named.csv")
    assert "named.csv: joints hips are none of the 17 the contract names" in caplog.text
    assert "pelvis" not in metrics["per_joint_mpjpe_mm"] and len(metrics["per_joint_mpjpe_mm"]) == 14
