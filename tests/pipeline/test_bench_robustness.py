"""Robustness suite on small synthetic folders: the copies' cache, error rows, the table, the targets (no run)."""

import dataclasses

import pytest

from calib.errors import InputError
from pipeline.lab.bench import robustness, suite, tables, targets
from pipeline.lab.bench.runs import RunMeasure

CAMERAS = ("cam00", "cam01", "cam02", "cam03", "cam04")


def _capture(root, name: str = "walk", cameras=CAMERAS, config: str = "fps: 30.0\n"):
    """A foreign capture as far as the suite looks before perturbing it: capture.yaml and videos/ by name."""
    capture = root / name
    (capture / "videos").mkdir(parents=True)
    (capture / "capture.yaml").write_text(config)
    for camera in cameras:
        (capture / "videos" / f"{camera}.mp4").write_bytes(b"")
    return capture


def _variant(name: str) -> robustness.Variant:
    return next(variant for variant in robustness.VARIANTS if variant.name == name)


def test_variants_spell_out_their_cameras_for_each_capture():
    assert _variant("4 cameras").arguments(CAMERAS)["cameras"] == CAMERAS[:4]
    assert _variant("one camera zoomed 1.8x").arguments(CAMERAS)["zoom"] == {"cam00": 1.8}
    assert _variant("compression").arguments(CAMERAS) == {"change": "compression", "seed": 0, "plates": True,
                                                          "cameras": (), "calibration_error_deg": 0.0, "zoom": None}
    assert _variant("one plate 5 px off").arguments(CAMERAS)["plate_shift"] == {"cam00": (4.0, 3.0)}
    assert "plate_shift" not in _variant("noise").arguments(CAMERAS)  # the other copies keep their cache keys
    assert _variant("calibration off 0.1°").slug == "calibration-off-0-1"
    assert len({variant.slug for variant in robustness.VARIANTS}) == len(robustness.VARIANTS)
    assert [variant.name for variant in robustness.variants(quick=True)] == list(robustness.QUICK_VARIANTS)


def test_copy_folders_change_with_a_parameter_and_are_stable_otherwise(tmp_path):
    capture, cache = _capture(tmp_path / "foreign"), tmp_path / "cache"
    folders = {variant.name: robustness.copy_folder(capture, variant, cache) for variant in robustness.VARIANTS}
    assert folders == {variant.name: robustness.copy_folder(capture, variant, cache)
                       for variant in robustness.VARIANTS}  # stable
    assert len(set(folders.values())) == len(folders) - 1  # the sync check's variant runs the late one's copy
    assert folders["no plates"].parent == cache and folders["no plates"].name.startswith("walk-no-plates-")
    off = _variant("calibration off 0.1°")
    assert robustness.copy_folder(capture, dataclasses.replace(off, calibration_error_deg=0.2), cache) \
        != folders[off.name]
    (capture / "capture.yaml").write_text("fps: 25.0\n")
    assert robustness.copy_folder(capture, off, cache) != folders[off.name]


def test_a_rig_whose_first_cameras_differ_gets_its_own_copy(tmp_path):
    cache, four = tmp_path / "cache", _variant("4 cameras")
    same_yaml = [_capture(tmp_path / folder, cameras=cameras)
                 for folder, cameras in (("a", CAMERAS), ("b", ("c1", "c2", "c3", "c4", "c5")))]
    first, second = (robustness.copy_folder(capture, four, cache) for capture in same_yaml)
    assert first != second


def test_an_existing_copy_is_reused_not_rebuilt(tmp_path, monkeypatch):
    made = []

    def fake_perturb(capture, out, change, **arguments):
        made.append((out.name, change))
        out.mkdir(parents=True)
        return out

    monkeypatch.setattr(robustness, "perturb_capture", fake_perturb)
    capture, cache = _capture(tmp_path / "foreign"), tmp_path / "cache"
    first = robustness.ensure_copy(capture, _variant("noise"), cache)
    assert robustness.ensure_copy(capture, _variant("noise"), cache) == first and first.is_dir()
    assert made == [(first.name, "noise")]


def _metrics(mpjpe_mm: float) -> dict:
    """What :func:`pipeline.evaluate.evaluate_run` returns, as far as the suite reads it."""
    angles = dict.fromkeys(("l_knee_flexion", "r_knee_flexion", "l_elbow_flexion", "r_elbow_flexion"), 3.0)
    return {"fraction_estimated": 1.0, "mpjpe_mm": mpjpe_mm, "worst_frame": {"mpjpe_mm": 2 * mpjpe_mm},
            "angle_errors_deg": angles, "pck": {"100mm": 1.0}, "silhouette_iou": {"mean": 0.9, "median": 0.95}}


def _measure(returncode: int = 0) -> RunMeasure:
    return RunMeasure(returncode=returncode, seconds=1.0, peak_rss_mb=100.0, frames=10, stage_seconds={}, load=0.5,
                      log_tail="reconstruction: out of memory" if returncode else "")


@pytest.fixture
def fake_runs(tmp_path, monkeypatch):
    """Two foreign captures; copies made as empty folders, every run scored from its run folder's name; the runs
    called, in order, kept in the returned list. ``walk`` with compression fails to run, ``leaning`` cannot be
    copied flickered."""
    root = tmp_path / "foreign"
    for name in ("walk", "leaning"):
        _capture(root, name, config="fps: 30.0\ncalibration: {format: colmap, path: calibration/colmap}\n")

    def fake_perturb(capture, out, change, **arguments):
        if (capture.name, change) == ("leaning", "flicker"):
            raise InputError(f"{capture}/videos/cam00.mp4: no frame could be decoded")
        (out / "calibration" / "colmap").mkdir(parents=True)
        (out / "capture.yaml").write_text((capture / "capture.yaml").read_text())
        return out

    runs = []

    def fake_run(capture, out, *, workers, frames, fresh, settings=()):
        runs.append((capture, out))
        if "export.sync_check=true" in settings and capture.parent.name != "foreign":  # the check names a lag
            (out / "export").mkdir(parents=True)
            (out / "export" / "sync_check.json").write_text('{"frame_offsets": {"cam00": 2}}')
        return _measure(1 if out.name.startswith("walk-compression") else 0)

    monkeypatch.setattr(robustness, "FOREIGN_ROOT", root)
    monkeypatch.setattr(robustness, "perturb_capture", fake_perturb)
    monkeypatch.setattr(robustness, "frame_numbers", lambda capture: list(range(10)))
    monkeypatch.setattr(robustness, "tracking_results", lambda run_dir, frames: [
        {"status": "initialised" if frame in (0, 4) else "tracked"} for frame in frames])
    monkeypatch.setattr(robustness, "run_pipeline", fake_run)
    monkeypatch.setattr(robustness, "evaluate_run", lambda run_dir, truth: _metrics(20.0 + len(run_dir.name)))
    return runs


def test_a_failing_run_or_copy_is_an_error_row_and_the_others_still_run(tmp_path, fake_runs):
    section = robustness.run_robustness(tmp_path / "bench", tmp_path / "captures", quick=False, workers=1)
    rows = {(row["capture"], row["variant"]): row for row in section["rows"]}
    # One copy fails; the sync check's variant runs each capture twice.
    assert len(section["rows"]) == 2 * len(robustness.VARIANTS) and len(fake_runs) == len(rows) - 1 + 2
    failed = rows[("walk", "compression")]
    assert failed["error"] == "the run failed (exit status 1): reconstruction: out of memory"
    assert failed["run"]["returncode"] == 1 and "mpjpe_mm" not in failed
    not_copied = f"{tmp_path / 'foreign' / 'leaning' / 'videos' / 'cam00.mp4'}: no frame could be decoded"
    assert rows[("leaning", "flicker")] == {"capture": "leaning", "variant": "flicker", "error": not_copied}
    scored = rows[("walk", "no plates")]
    assert scored["mpjpe_mm"] == 20.0 + len("walk-no-plates") and scored["silhouette_iou_median"] == 0.95
    assert set(scored) == {"capture", "variant", "copy", "frames", "run", "reinitialised_fraction", *robustness.SCORES}
    assert scored["reinitialised_fraction"] == pytest.approx(0.1)  # frame 4 of 10; the first does not count
    assert fake_runs[0][1] == tmp_path / "bench" / "robustness" / "leaning-compression"
    assert fake_runs[0][0].parent == tmp_path / "captures" / "robustness"


def test_a_sync_variant_runs_the_late_copy_again_with_the_offsets_the_check_named(tmp_path, fake_runs):
    late, checked = _variant("one camera 2 frames late"), _variant("2 frames late, frame_offsets from the sync check")
    assert late.arguments(CAMERAS)["late"] == {"cam00": 2} and checked.arguments(CAMERAS) == late.arguments(CAMERAS)
    captures = tmp_path / "captures" / "robustness"
    walk = tmp_path / "foreign" / "walk"
    assert robustness.copy_folder(walk, checked, captures) == robustness.copy_folder(walk, late, captures)
    row = robustness.run_variant(walk, checked, captures, tmp_path / "bench", quick=False, workers=1)
    assert row["offsets_named"] == {"cam00": 2}
    (first, first_run), (view, run_dir) = fake_runs
    assert first_run.name == "walk-2-frames-late-frame-offsets-from-the-sync-check"
    assert run_dir.name == first_run.name + "-offsets" and view.name == first_run.name + "-offsets-capture"
    assert "cam00: 2" in (view / "capture.yaml").read_text() and (view / "calibration").is_dir()
    assert row["mpjpe_mm"] == 20.0 + len(run_dir.name)  # the second run is the one scored


def test_a_quick_run_takes_two_variants_on_the_copies_first_frames(tmp_path, fake_runs):
    section = robustness.run_robustness(tmp_path / "bench", tmp_path / "captures", quick=True, workers=1)
    assert [row["variant"] for row in section["rows"]] == list(robustness.QUICK_VARIANTS) * 2
    view, run_dir = fake_runs[0]
    assert run_dir == tmp_path / "bench" / "robustness" / "leaning-compression-quick"
    assert view == tmp_path / "bench" / "robustness" / "leaning-compression-quick-capture"
    assert f"stop: {robustness.QUICK_FRAMES}" in (view / "capture.yaml").read_text()


def _row(capture: str, variant: str, mpjpe_mm: float, estimated: float = 1.0, reinitialised: float = 0.0) -> dict:
    return {"capture": capture, "variant": variant, "mpjpe_mm": mpjpe_mm, "worst_frame_mm": 2 * mpjpe_mm,
            "fraction_estimated": estimated, "silhouette_iou_median": 0.9, "reinitialised_fraction": reinitialised,
            "run": {"ok": True}}


SECTION = {"root": "../shared/foreign", "quick": False, "rows": [
    _row("walk", "noise", 20.0, reinitialised=0.12), _row("walk", "4 cameras", 30.0, estimated=0.9),
    _row("leaning", "noise", 24.0), {"capture": "leaning", "variant": "4 cameras", "error": "boom"}]}


def test_the_table_has_a_column_per_variant_and_their_means_below():
    lines = tables.format_robustness(SECTION).splitlines()
    assert lines[2:7] == ["| capture | noise | 4 cameras |", "|---|---|---|",
                          "| walk | 20.0 (40.0) | 30.0 (60.0), 90 % estimated |", "| leaning | 24.0 (48.0) | – |",
                          "| **mean** | 22.0 (44.0) | 30.0 (60.0), 90 % estimated |"]
    assert lines[10:15] == ["| capture | noise | 4 cameras |", "|---|---|---|", "| walk | 12 % | 0 % |",
                            "| leaning | 0 % | – |", "| **mean** | 6 % | 0 % |"]
    assert lines[-1] == "`leaning`, 4 cameras: not scored: boom"


def test_the_targets_read_the_section():
    verdicts = {t["target"]: t for t in targets.judge_targets({"robustness": SECTION})}
    assert verdicts["mean MPJPE over every capture and variant"]["value"] == pytest.approx(74 / 3)
    assert verdicts["mean MPJPE over every capture and variant"]["met"]
    estimated = verdicts["frames estimated, worst run"]
    assert estimated["value"] == 0.0 and not estimated["met"]  # the run that failed estimated nothing


def test_the_results_page_has_the_section():
    made = {"date": "2025-01-01T00:00:00+00:00", "commit": "abc", "seconds": 10.0, "load_before": 0.5,
            "load_after": 0.6, "cpus": 2}
    page = suite.format_results({"robustness": {**SECTION, "made": made, "command": "python -m pipeline bench"}})
    assert "## Robustness: the foreign captures perturbed, one change at a time" in page
    assert "| robustness | frames estimated, worst run | ≥ 100 % | 0.0 | **MISSED** |" in page

