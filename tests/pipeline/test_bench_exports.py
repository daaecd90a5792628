"""Exports suite helpers on a synthetic export (no pipeline run): the independent readers' agreement, the
confidence against truth, the table and the targets."""

import numpy as np
from conftest import stick_figure

from pipeline.io.export_io import read_joints_csv, write_exports, write_joints_csv
from pipeline.lab.bench import exports, suite, targets
from stages.export import ExportParams
from stages.export.quality import FrameQuality


def _export(folder, params=None):
    t = np.arange(12)
    joints = stick_figure()[None] + (0.02 * t)[:, None, None] * np.array([0.0, 1.0, 0.0])
    support = np.full((12, 17), 50.0)
    support[4, 7] = 5.0  # frame 9's left wrist: its forearm explains a tenth of its usual data
    quality = FrameQuality(frames=t + 5, statuses=np.array(["tracked"] * 12), doubtful=np.zeros(12, bool),
                           observations=np.full(12, 900), log_likelihood=np.full(12, 2000.0),
                           outlier_fraction=np.full(12, 0.05), support=support, fitted=np.ones(12, bool),
                           corrected=np.full(12, ""))
    write_exports(folder / "export", t + 5, joints, fps=30.0, params=params, quality=quality)
    return t + 5


def test_readers_agree_with_joints_csv_and_see_a_file_that_does_not(tmp_path):
    frames = _export(tmp_path)
    distances = exports.agreement_mm(tmp_path)
    assert set(distances) == {"motion.bvh", "joints.trc", "joints.c3d"} and max(distances.values()) < 1e-3
    _, _, joints = read_joints_csv(tmp_path / "export" / "joints.csv")
    joints[:, :, 2] += 0.001  # joints.csv 1 mm higher than the other files
    write_joints_csv(tmp_path / "export" / "joints.csv", frames, joints)
    assert min(exports.agreement_mm(tmp_path).values()) > 0.9


def test_readers_follow_the_exports_units_and_names_from_the_manifest(tmp_path):
    _export(tmp_path, ExportParams(bvh_units="mm", bvh_names="mixamo", trc_names="halpe26"))
    (tmp_path / "export" / "manifest.json").write_text(
        '{"params": {"bvh_units": "mm", "bvh_names": "mixamo", "trc_names": "halpe26"}}')
    assert max(exports.agreement_mm(tmp_path).values()) < 1e-3


def test_confidence_against_truth_separates_the_unsupported_joint(tmp_path):
    frames = _export(tmp_path)
    _, _, truth = read_joints_csv(tmp_path / "export" / "joints.csv")
    truth[4, 7, 0] += 0.1  # the unsupported wrist is 10 cm off
    write_joints_csv(tmp_path / "truth.csv", frames, truth)
    scores = exports.confidence_against_truth(tmp_path, tmp_path / "truth.csv")
    assert scores["unsupported_share"] == 1 / (12 * 15) and scores["large_errors_flagged"] == 1.0
    assert abs(scores["unsupported_mpjpe_mm"] - 100.0) < 1e-3 and scores["supported_mpjpe_mm"] < 1e-3


def _row(name, mpjpe, wrist, smoothed_mpjpe, smoothed_wrist, disagreement=0.0005):
    def entry(cutoff, m, w):
        return {"cutoff_hz": cutoff, "mpjpe_mm": m, "wrist_acceleration_m_s2": w, "largest_disagreement_mm": 0.0004,
                "agreement_mm": {}}
    return {"capture": name, "mpjpe_mm": mpjpe, "wrist_acceleration_m_s2": wrist,
            "largest_disagreement_mm": disagreement,
            "agreement_mm": {"motion.bvh": disagreement, "joints.trc": 0.0, "joints.c3d": 0.0002},
            "confidence": {"unsupported_share": 0.02, "unsupported_mpjpe_mm": 40.0, "supported_mpjpe_mm": 20.0,
                           "large_errors_flagged": 0.25},
            "smoothed": [entry(4.0, mpjpe + 1, 3.0), entry(6.0, smoothed_mpjpe, smoothed_wrist)]}


def test_targets_and_tables_of_the_exports_section():
    made = {"date": "2026-12-02T00:00:00+00:00", "commit": "abc", "seconds": 1.0, "load_before": 0.0,
            "load_after": 0.0, "cpus": 2, "machine": "x"}
    section = {"quick": False, "command": "python -m pipeline bench --suite exports", "made": made, "root": "/f",
               "cutoffs_hz": [4.0, 6.0], "judged_cutoff_hz": 6.0,
               "rows": [_row("walk", 22.3, 20.0, 21.6, 9.0), _row("kick", 17.3, 14.0, 17.9, 4.0, disagreement=0.2)]}
    verdicts = {v["target"]: v for v in targets.judge_targets({"exports": section})}
    agreement = verdicts["BVH, TRC, C3D vs joints.csv, largest distance in any frame (worst capture, smoothed or not)"]
    assert agreement["value"] == 0.2 and not agreement["met"]
    ratio = verdicts["smoothing at 6 Hz: wrist acceleration error, smoothed / unsmoothed (worst capture)"]
    assert abs(ratio["value"] - 0.45) < 1e-9 and ratio["met"]
    rise = verdicts["smoothing at 6 Hz: MPJPE rise (worst capture)"]
    assert abs(rise["value"] - 0.6) < 1e-9 and not rise["met"]
    text = suite.format_results({"exports": section})
    assert "## Exports: agreement, smoothing, confidence" in text
    assert "| walk | 0.00050 | 0.00000 | 0.00020 | 2 % | 40.0 | 20.0 | 25 % |" in text
    assert "| walk | 22.3 | 20.00 | 23.3 / 3.00 | 21.6 / 9.00 |" in text
