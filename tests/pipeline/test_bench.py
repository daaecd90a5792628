"""Benchmark helpers: recipes and their cache, mask noise, outliers, scoring, targets and tables (no timing)."""

import json
import math
import subprocess
import sys

import cv2
import numpy as np
import pytest
import yaml

from pipeline.lab.bench import paper, recipes, speed, suite, tables, targets, unseen
from pipeline.lab.bench.masks import perturb_mask
from pipeline.lab.bench.runs import LAUNCHER, run_command, stage_timings
from pipeline.lab.synth.writer import SynthParams
from stages.export.bvh import pelvis_frame
from stages.export.metrics import mask_iou
from stages.joints import JOINT_NAMES

# ---------------------------------------------------------------------------------------------
# Recipes


def test_recipe_hash_ignores_key_order_and_sees_every_value():
    spec = recipes.UNSEEN[1].spec()
    assert recipes.recipe_hash(spec) == recipes.recipe_hash(dict(reversed(list(spec.items()))))
    for key, value in spec.items():
        changed = {**spec, key: "something else" if value != "something else" else 0}
        assert recipes.recipe_hash(changed) != recipes.recipe_hash(spec), key


def test_recipes_are_valid_generator_parameters_with_unique_names():
    every = [recipes.SPEED, recipes.PAPER, *recipes.UNSEEN]
    names = [r.name for r in every] + [r.quick().name for r in every]
    assert len(set(names)) == len(names)
    assert set(recipes.QUICK_UNSEEN) <= {r.name for r in recipes.UNSEEN}
    for recipe in every:
        params = recipe.synth_params()
        assert isinstance(params, SynthParams) and params.clip.endswith(recipes.CLIPS[recipe.clip][0])
        assert recipe.spec()["clip"] == recipes.CLIPS[recipe.clip][0]  # relative: the hash is portable


def test_unseen_recipes_vary_what_the_brief_asks():
    described = [recipes.describe(r) for r in recipes.UNSEEN]
    assert {d["clip"] for d in described} == {"135_04", "135_07", "131_05", "md_walk", "09_01"}
    assert {d["cameras"] for d in described} >= {5, 6, 8}
    assert {d["body"] for d in described} == {"mesh", "capsules"}
    assert {d["media"] for d in described} == {"video", "images"}
    assert {d["height_known"] for d in described} == {True, False}
    assert {d["calibration"].split()[0] for d in described} == {"colmap", "opencv", "anipose"}
    assert len({d["size"] for d in described}) >= 3 and any(d["distractors"] for d in described)


def test_quick_recipe_is_a_separate_short_capture():
    quick = recipes.SPEED.quick()
    assert quick.name == "speed-135_07-quick" and quick.seconds == recipes.SPEED.quick_seconds
    assert recipes.recipe_hash(quick.spec()) != recipes.recipe_hash(recipes.SPEED.spec())


def test_capture_is_current_only_with_the_same_recipe_and_a_complete_folder(tmp_path):
    recipe = recipes.UNSEEN[0]
    assert not recipes.is_current(tmp_path, recipe)
    (tmp_path / recipe.name).mkdir()
    (tmp_path / recipe.name / "capture.yaml").write_text("fps: 28\n")
    stored = {"hash": recipes.recipe_hash(recipe.spec()), "recipe": recipe.spec()}
    recipes.recipe_file(tmp_path, recipe.name).write_text(json.dumps(stored, default=list))
    assert recipes.is_current(tmp_path, recipe)
    other = recipes.Recipe(recipe.name, recipe.clip, recipe.start_s + 0.5, recipe.seconds, recipe.options)
    assert not recipes.is_current(tmp_path, other)
    recipes.recipe_file(tmp_path, recipe.name).write_text("{not json")
    assert not recipes.is_current(tmp_path, recipe)


# ---------------------------------------------------------------------------------------------
# Silhouette noise


@pytest.fixture(scope="module")
def person_mask():
    mask = np.zeros((240, 200), np.uint8)
    cv2.ellipse(mask, (100, 120), (40, 90), 0, 0, 360, 255, -1)
    cv2.rectangle(mask, (40, 60), (160, 75), 255, -1)  # arms
    return mask


def test_zero_strength_keeps_the_mask(person_mask):
    assert np.array_equal(perturb_mask(person_mask, 0.0, np.random.default_rng(0)), person_mask)


def test_perturbation_grows_with_strength(person_mask):
    strengths = (0.0, 0.25, 0.5, 0.75, 1.0)
    for seed in range(3):
        noisy = [perturb_mask(person_mask, s, np.random.default_rng(seed)) for s in strengths]
        ious = [mask_iou(m, person_mask) for m in noisy]
        assert all(a > b for a, b in zip(ious, ious[1:], strict=False)), ious
        assert all(set(np.unique(m)) <= {0, 255} and m.dtype == np.uint8 for m in noisy)


def test_perturbation_is_reproducible_and_checks_strength(person_mask):
    a = perturb_mask(person_mask, 0.5, np.random.default_rng(7))
    assert np.array_equal(a, perturb_mask(person_mask, 0.5, np.random.default_rng(7)))
    with pytest.raises(ValueError, match="strength"):
        perturb_mask(person_mask, 1.5, np.random.default_rng(0))


# ---------------------------------------------------------------------------------------------
# Paper experiments


def test_outliers_are_the_requested_share_inside_the_volume():
    rng = np.random.default_rng(0)
    volume = np.array([[-1.0, -2.0, 0.0], [1.0, 2.0, 2.5]])
    points, normals = rng.normal(size=(800, 3)), np.tile([0.0, 0.0, 1.0], (800, 1))
    y, n = paper.add_outliers(points, normals, 0.2, volume, rng)
    assert len(y) == 1000 and np.array_equal(y[:800], points)
    assert np.all((y[800:] >= volume[0]) & (y[800:] <= volume[1]))
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)


def test_frame_rates_subsample_the_same_stretch_of_time():
    plan = paper.FULL_PLAN
    for fps, step, count in ((7.0, 8, 25), (14.0, 4, 50), (28.0, 2, 100), (56.0, 1, 200)):
        frames = paper.Condition(fps, 0.0, 1000).frames(plan, available=201)
        assert frames == list(range(0, count * step, step))
    assert paper.Condition(56.0, 0.0, 1000).frames(plan, available=150)[-1] == 149


def test_conditions_are_shared_between_experiments():
    conditions = paper.plan_conditions(paper.FULL_PLAN)
    assert conditions[paper.BASE] == paper.DISTANCES  # (a), (b) at 0 and (c) at 28 fps: computed once
    assert conditions[paper.Condition(28.0, 0.0, 50)] == ("normals", "points")
    assert len(conditions) == 1 + 4 + 3 + 6


def test_score_counts_only_exported_frames():
    truth = np.random.default_rng(1).normal(size=(4, len(JOINT_NAMES), 3))
    estimate = truth.copy()
    estimate[3] += 1.0  # a lost frame's prediction, far off
    result = paper.score(estimate, ["initialised", "tracked", "tracked", "lost"], truth)
    assert result == {"angle_error_deg": 0.0, "angle_error_median_deg": 0.0, "angle_error_offset_free_deg": 0.0,
                      "hip_angle_error_deg": 0.0, "hips_forward_mm": 0.0, "knees_forward_mm": 0.0,
                      "mpjpe_mm": 0.0, "off_track": 0.0, "fraction_estimated": 0.75}
    assert math.isnan(paper.score(estimate, ["lost"] * 4, truth)["mpjpe_mm"])


def test_offset_free_angles_ignore_a_joint_placed_elsewhere_in_the_body():
    """A skeleton that puts the knees 3 cm further forward (in the body's frame, whatever the pose) has
    other knee and hip angles, but the same motion."""
    truth = np.random.default_rng(2).normal(size=(20, len(JOINT_NAMES), 3))
    frames = pelvis_frame({name: truth[:, JOINT_NAMES.index(name)] for name in ("l_hip", "r_hip", "pelvis", "neck")})
    offset = np.zeros((len(JOINT_NAMES), 3))
    offset[[JOINT_NAMES.index("l_knee"), JOINT_NAMES.index("r_knee")], 2] = 0.03  # the frame's third axis: forward
    estimate = truth + np.einsum("fab,jb->fja", frames, offset)
    result = paper.score(estimate, ["tracked"] * 20, truth)
    assert result["angle_error_deg"] > 0.1  # degrees: the random joints are about a metre apart
    assert result["angle_error_offset_free_deg"] < 1e-6
    assert result["knees_forward_mm"] == pytest.approx(30.0) and result["hips_forward_mm"] == pytest.approx(0.0)


# ---------------------------------------------------------------------------------------------
# Runs, speed and unseen helpers


def test_prefix_view_shows_the_first_frames_of_the_same_files(tmp_path):
    capture = tmp_path / "capture"
    (capture / "videos").mkdir(parents=True)
    (capture / "calib" / "colmap").mkdir(parents=True)
    (capture / "calib" / "colmap" / "cameras.txt").write_text("# cameras\n")
    (capture / "capture.yaml").write_text(yaml.safe_dump({"fps": 28.0, "frames": {"start": 0, "step": 1},
                                                          "calibration": {"path": "calib/colmap"}}))
    view = speed.prefix_view(capture, tmp_path / "view", 56)
    assert (view / "videos").is_symlink() and (view / "videos").resolve() == (capture / "videos").resolve()
    # The calibration is a copy: a run refuses a calibration reached through a link out of the capture.
    assert not (view / "calib").is_symlink()
    assert (view / "calib" / "colmap" / "cameras.txt").read_text() == "# cameras\n"
    assert yaml.safe_load((view / "capture.yaml").read_text())["frames"] == {"start": 0, "step": 1, "stop": 56}
    assert speed.prefix_view(capture, tmp_path / "view", 10).is_dir()  # rebuilt, not refused


def test_stage_timings_read_the_manifests(tmp_path):
    (tmp_path / "tracking").mkdir()
    (tmp_path / "tracking" / "manifest.json").write_text(json.dumps({"timing": {"seconds": 2.5, "frames": 10}}))
    (tmp_path / "export").mkdir()
    (tmp_path / "export" / "manifest.json").write_text("{broken")
    timings = stage_timings(tmp_path)
    assert timings["tracking"] == 2.5 and timings["export"] == 0.0 and timings["silhouettes"] == 0.0
    command = run_command(tmp_path, tmp_path / "out", 2)
    assert command[1:5] == ["-m", "pipeline", "run", str(tmp_path)]
    assert command[command.index("--out") + 1] == str(tmp_path / "out")
    assert command[command.index("--workers") + 1] == "2"


def _launched_peak_mb(tmp_path, code: str) -> float:
    report = tmp_path / "measure.json"
    subprocess.run([sys.executable, "-c", LAUNCHER, str(report), sys.executable, "-c", code], check=True)
    measured = json.loads(report.read_text())
    assert measured["returncode"] == 0 and measured["seconds"] > 0
    return measured["maxrss_kb"] / 1024


def test_peak_memory_is_the_runs_own_not_the_benchmarks(tmp_path):
    ballast = np.ones(40_000_000)  # 320 MB in this process: must not show in a child's peak
    assert _launched_peak_mb(tmp_path, "pass") < 100 < ballast.nbytes / 2**20
    assert _launched_peak_mb(tmp_path, "x = bytearray(300 * 2**20); x[::4096] = bytes(len(x[::4096]))") > 290


def test_mean_row_skips_runs_that_were_not_scored():
    rows = [{"mpjpe_mm": 10.0, "fraction_estimated": 1.0, "worst_frame_mm": 30.0, "knee_flexion_deg": 2.0,
             "elbow_flexion_deg": 4.0, "silhouette_iou": None},
            {"mpjpe_mm": 30.0, "fraction_estimated": 0.5, "worst_frame_mm": 90.0, "knee_flexion_deg": 4.0,
             "elbow_flexion_deg": 6.0, "silhouette_iou": 0.9},
            {"capture": "failed", "run": {"ok": False}}]
    mean = unseen.mean_row(rows)
    assert mean["mpjpe_mm"] == 20.0 and mean["fraction_estimated"] == 0.75 and mean["silhouette_iou"] == 0.9
    assert mean["captures"] == 2 and mean["failed"] == 1


# ---------------------------------------------------------------------------------------------
# Targets and tables


def _sweep(errors: dict[float, dict[str, float]]) -> list[dict]:
    return [{"x": x, "distance": d, "angle_error_deg": e, "mpjpe_mm": 10 * e, "fraction_estimated": 1.0,
             "off_track": 0.0, "mask_iou": 1.0 - x / 10, "observations": 1000.0, "frames": 100, "seconds": 1.0}
            for x, by_distance in errors.items() for d, e in by_distance.items()]


@pytest.fixture()
def results():
    made = {"date": "2026-01-01T00:00:00+00:00", "commit": "abc1234", "seconds": 60.0, "load_before": 1.0,
            "load_after": 1.5, "cpus": 2, "bench_memory": {"self_mb": 900.0, "children_mb": 850.0}}
    run = {"ok": True, "frames": 168, "seconds": 8.0, "peak_rss_mb": 500.0, "load": 1.0,
           "stage_seconds": {"silhouettes": 3.0, "tracking": 4.0}}
    row = {"capture": "walk", "clip": "md_walk", "body": "mesh", "cameras": 6, "size": "780x580", "noise": 2.0,
           "distractors": 0, "media": "video", "calibration": "colmap m +z", "height_known": True, "frames": 84,
           "fraction_estimated": 1.0, "mpjpe_mm": 20.0, "worst_frame_mm": 95.0, "knee_flexion_deg": 3.0,
           "elbow_flexion_deg": 6.0, "silhouette_iou": 0.95, "run": run}
    statuses = {"tracked": 114, "initialised": 6, "predicted": 0, "lost": 0, "doubtful": 2}
    walk = {"capture": "walk", "cameras": 5, "size": "640x480", "frames": 120, "run": run, "fraction_estimated": 1.0,
            "mpjpe_mm": 22.0, "offset_free_mpjpe_mm": 12.5, "worst_frame_mm": 60.0, "silhouette_iou_median": 0.95,
            "tracker_ms_per_frame": 30.0,
            "mpjpe_true_masks_mm": 17.5, "worst_true_masks_mm": 30.0, "fps_end_to_end": 15.0,
            "tracker_vs_reference": 1.2, "statuses": statuses, "reinitialised_fraction": 0.05}
    sweep = _sweep({0.0: {"normals": 2.0, "points": 3.0, "algebraic": 4.0},
                    0.75: {"normals": 3.0, "points": 3.5, "algebraic": 5.0},
                    1.0: {"normals": 5.0, "points": 4.0, "algebraic": 6.0}})
    return {
        "speed": {"quick": False, "command": "python -m pipeline bench --suite speed", "made": made,
                  "capture": "speed", "recipe": recipes.describe(recipes.SPEED), "fps_capture": 28.0, "workers": 2,
                  "frames": 168, "short_frames": 56, "long": run, "short": {**run, "frames": 56},
                  "fps_end_to_end": 21.0, "stage_ms_per_frame": {"silhouettes": 17.9, "tracking": 23.8},
                  "memory_ratio": 1.0, "tracker": {"frames": 100, "observations_mean": 990.0, "fps_tracked": 90.0,
                                                   "fps_all": 120.0, "ms_initialisation": 900.0,
                                                   "statuses": {"tracked": 99, "initialised": 1}}},
        "unseen": {"quick": True, "command": "python -m pipeline bench --suite unseen --quick", "made": made,
                   "rows": [row, {"capture": "broken", "run": {**run, "ok": False, "log_tail": "boom"}},
                            {"capture": "unrendered", "error": "capture not rendered: no camera sees it"}],
                   "mean": unseen.mean_row([row])},
        "paper": {"quick": False, "command": "python -m pipeline bench --suite paper", "made": made,
                  "capture": "paper", "recipe": recipes.describe(recipes.PAPER), "frames": 100,
                  "outlier_fraction": 0.2, "limb_angles": list(paper.LIMB_ANGLES), "off_track_mm": 100.0,
                  "trajectories": {"time_s": [0.0, 0.1], **{name: {"truth": [1.0, 2.0], "estimate": [1.5, 2.5]}
                                                            for name in paper.TRAJECTORY_ANGLES}},
                  "base": [r for r in sweep if r["x"] == 0.0], "noise": sweep, "fps": sweep,
                  "observations": [r for r in sweep if r["distance"] != "algebraic"]},
        "foreign": {"quick": False, "command": "python -m pipeline bench --suite foreign", "made": made,
                    "root": "/shared/foreign", "rows": [walk, {"capture": "odd", "error": "odd/capture.yaml: no fps"}],
                    "reference": {**walk, "capture": "data_samples/taekwondo", "tracker_vs_reference": 1.0}},
        "calibration": {"quick": True, "command": "python -m pipeline bench --suite calibration --quick", "made": made,
                        "rows": [{"scenario": name, "board": name, "returncode": 0, "focal_percent": 0.1,
                                  "principal_px": 0.4, "aligned_centre_mm": centre, "aligned_rotation_deg": 0.05,
                                  "rms_px": 0.07}
                                 for name, centre in (("checkerboard", 2.0), ("charuco", 12.0))]
                        + [{"scenario": "phone", "board": "checkerboard:4x7:0.025", "returncode": 0,
                            "focal_percent": 0.3},
                           {"scenario": "taekwondo", "true_mpjpe_mm": 16.6, "self_mpjpe_mm": 16.9,
                            "mpjpe_difference_mm": 0.3}]},
        "batch": {"quick": False, "command": "python -m pipeline bench --suite batch", "made": made, "workers": 2,
                  "captures": [{"capture": "walk/first", "frames": 56}],
                  "parallel": {"seconds": 20.0, "returncode": 3, "load": 0.5, "rows": [
                      {"capture": "walk/first", "frames": 56, "status": "ran", "estimated": 56, "mpjpe_mm": 18.0,
                       "seconds": 9.5, "error": ""},
                      {"capture": "tiny/broken", "frames": None, "status": "failed", "estimated": None,
                       "mpjpe_mm": None, "seconds": 0.2, "error": "tiny/broken/images/cam2/000004.png: unreadable"}]},
                  "sequential": {"seconds": 36.0, "returncode": 3, "load": 0.6, "rows": []},
                  "trial_seconds": {"parallel": [20.0, 21.0], "sequential": [36.0, 37.5]},
                  "runs": {"seconds": 40.0, "load": 0.7, "ok": ["walk/first"]},
                  "speedup": 1.8, "speedup_vs_runs": 2.0, "broken_reported": True, "same_joints": True},
    }


def test_targets_are_judged_on_the_measured_numbers(results):
    verdicts = {(t["suite"], t["target"]): t for t in targets.judge_targets(results)}
    assert len(verdicts) == len([t for t in targets.TARGETS if t.suite in results])  # exports: test_bench_exports
    centre = verdicts[("calibration", "camera centre error, worst camera (rigidly aligned)")]
    assert not centre["met"] and centre["value"] == 12.0  # the worst of the board scenarios
    assert verdicts[("calibration", "taekwondo MPJPE, self-calibrated minus true rig")]["met"]
    assert not verdicts[("speed", "end-to-end frames/s (6 cameras 780x580, video, 2 workers)")]["met"]
    tracker = verdicts[("speed", "tracker alone, frames/s at ~1000 observations")]
    assert tracker["met"] and tracker["value"] == 120.0  # over all frames, not the tracked ones only
    assert verdicts[("unseen", "mean MPJPE over captures")]["met"]
    assert not verdicts[("unseen", "fraction of frames estimated (worst capture run)")]["met"]  # the failed run
    assert not verdicts[("unseen", "worst frame (worst capture)")]["met"]
    share = verdicts[("paper", "points+normals beat points alone (share of noise levels)")]
    assert share["value"] == 2 / 3 and not share["met"]
    noisy = verdicts[("paper", "points+normals MPJPE at silhouette noise 0.75 (mask IoU about 0.8)")]
    assert noisy["value"] == 30.0 and noisy["met"]
    assert verdicts[("paper", "points+normals frames off track at silhouette noise 0.75")]["met"]
    real_time = verdicts[("foreign", "end-to-end frames/s on taekwondo (6 cameras 780x580, video, 2 workers)")]
    assert math.isnan(real_time["value"]) and not real_time["met"]  # no taekwondo among the foreign rows
    assert verdicts[("foreign", "MPJPE (worst capture)")]["met"]  # over the scored captures
    assert not verdicts[("foreign", "frames estimated (worst capture run)")]["met"]  # "odd" was never run
    reinitialised = verdicts[("foreign", "frames re-initialised after the first (worst capture)")]
    assert reinitialised["value"] == 5.0 and reinitialised["threshold"] == "< 5 %" and not reinitialised["met"]
    assert verdicts[("foreign", "tracker ms/frame, worst capture / data_samples/taekwondo")]["met"]
    iou = verdicts[("foreign", "silhouette IoU, median over frames and cameras (worst capture)")]
    assert iou["met"] and iou["digits"] == 2  # shown as 0.95, not rounded to 0.9 or 1.0 against 0.93
    assert verdicts[("batch", "4 captures, local:2 vs one after the other (1 worker each), times faster")]["met"]


def test_a_missing_number_is_a_miss_not_a_crash(results):
    del results["speed"]["tracker"]
    verdict = next(t for t in targets.judge_targets(results) if "tracker" in t["target"])
    assert math.isnan(verdict["value"]) and not verdict["met"]


def test_format_table_aligns_numbers_and_shows_missing_values():
    table = tables.format_table(("name", "value"), [("a", 1.25), ("b", float("nan")), ("c", None)])
    assert table.splitlines() == ["| name | value |", "|---|---:|", "| a | 1.2 |", "| b | – |", "| c | – |"]
    assert tables.fmt(True) == "yes" and tables.fmt(3) == "3" and tables.fmt(0.12345, 3) == "0.123"


def test_results_markdown_has_every_section_command_and_verdict(results):
    text = suite.format_results(results, {"paper": "figures/paper_fig4.png"})
    for heading in ("## Targets", "## Speed", "## Accuracy on unseen captures", "## The paper's experiments",
                    "## Accuracy on captures made by another program", "## A study in one command"):
        assert heading in text
    for section in results.values():
        assert section["command"] in text
    assert "**MISSED**" in text and "| met |" in text
    assert "`broken` was not scored: boom" in text and "`unrendered` was not scored: capture not" in text
    assert "![Fig. 4 redone](figures/paper_fig4.png)" in text
    walk = ("| walk | 5 | 640x480 | 120 | 100 % | 22.0 | 12.5 | 60.0 | 0.950 | 17.5 | 30.0 | 15.0 | 30.0 | 1.20 | 114 |"
            " 6 | 0 | 0 | 2 | 5 % |")
    assert walk in text
    assert "| data_samples/taekwondo (reference) |" in text and "`odd` was not scored: odd/capture.yaml" in text
    assert "| walk/first | 56 | ran | 56 | 18.0 | 9.5 | – | – |" in text
    assert "| `batch --scheduler local:1` | 36.0 | 1.80 | 0.6 |" in text
    assert "Every batch run: parallel 20.0, 21.0 s; sequential 36.0, 37.5 s." in text


def test_results_round_trip_through_strict_json(results, tmp_path):
    results["unseen"]["mean"]["elbow_flexion_deg"] = float("nan")
    safe = suite.json_safe({**results, "extra": (np.float64(1.5), np.array([1, 2]))})
    assert safe["unseen"]["mean"]["elbow_flexion_deg"] is None and safe["extra"] == [1.5, [1, 2]]
    path = tmp_path / "results.json"
    path.write_text(json.dumps(safe, allow_nan=False))
    assert suite.load_results(path) == safe
    assert suite.format_results(suite.load_results(path))
    path.write_text("[1, 2]")
    assert suite.load_results(path) == {} and suite.load_results(tmp_path / "missing.json") == {}


def test_command_names_only_options_that_differ_from_the_defaults(tmp_path):
    options = suite.BenchOptions(out=tmp_path, captures=tmp_path / "captures", quick=False, workers=2)
    assert options.command("speed") == f"python -m pipeline bench --out {tmp_path} --suite speed"
    quick = suite.BenchOptions(out=tmp_path, captures=tmp_path / "cache", quick=True, workers=1)
    assert quick.command("paper").endswith(f"--suite paper --captures {tmp_path / 'cache'} --workers 1 --quick")


def test_report_draws_every_figure_and_links_it_from_the_page(results, tmp_path):
    suite.write_report(results, tmp_path / "docs" / "results.md", source=tmp_path / "results.json")
    text = (tmp_path / "docs" / "results.md").read_text()
    for name in ("speed_stages.png", "unseen_mpjpe.png", "paper_fig4.png"):
        assert (tmp_path / "docs" / "figures" / name).stat().st_size > 0
        assert f"(figures/{name})" in text


def test_cpu_model_is_read_from_cpuinfo_and_shown_beside_the_core_count(tmp_path, results, monkeypatch):
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor\t: 0\nmodel name\t: AMD EPYC 7B13\nprocessor\t: 1\nmodel name\t: AMD EPYC 7B13\n")
    assert suite.cpu_model(cpuinfo) == "AMD EPYC 7B13"
    monkeypatch.setattr(suite.platform, "processor", lambda: "")  # Linux often knows no processor name here
    monkeypatch.setattr(suite.platform, "machine", lambda: "x86_64")
    assert suite.cpu_model(tmp_path / "absent") == "x86_64"
    monkeypatch.setattr(suite.platform, "machine", lambda: "")
    assert suite.cpu_model(tmp_path / "absent") == "unknown"
    section = results["speed"] | {"made": results["speed"]["made"] | {"cpus": 2, "machine": "AMD EPYC 7B13"}}
    assert "(2 CPUs, AMD EPYC 7B13)" in tables.provenance(section)


def test_the_reference_workload_is_timed_and_shown_beside_the_load(results, monkeypatch):
    assert 0 < suite.reference_seconds(repeats=1) < 60
    section = results["speed"] | {"made": results["speed"]["made"] | {"reference_s": [0.213, 0.251]}}
    assert "reference workload 0.21 s before / 0.25 s after" in tables.provenance(section)
    old = results["speed"] | {"made": {k: v for k, v in results["speed"]["made"].items() if k != "reference_s"}}
    assert "reference workload" not in tables.provenance(old)  # results.json written before it was measured


def test_a_suite_records_the_reference_workload_before_and_after_it(tmp_path, monkeypatch):
    times = iter([0.2, 0.3])
    monkeypatch.setattr(suite, "reference_seconds", lambda: next(times))
    monkeypatch.setattr(suite, "ensure_compiled", lambda: 0)
    monkeypatch.setattr(suite, "suite_runners", lambda: {"speed": lambda *args, **kwargs: {}})
    monkeypatch.setattr(suite, "write_outputs", lambda results, options: None)
    options = suite.BenchOptions(out=tmp_path / "bench", captures=tmp_path / "captures", quick=True, workers=1)
    results = suite.run_bench(["speed"], options, log=lambda line: None)
    assert results["speed"]["made"]["reference_s"] == [0.2, 0.3]


def test_docs_keep_the_measurements_and_a_fresh_checkout_starts_from_them(results, tmp_path, capsys):
    import argparse

    from pipeline.commands import bench

    out, docs = tmp_path / "runs" / "bench", tmp_path / "docs"
    docs.mkdir()
    (docs / "results.json").write_text(json.dumps(suite.json_safe(results), allow_nan=False))
    args = argparse.Namespace(out=out, suite="all", quick=False, workers=2, captures=None, docs=docs, report_only=True)
    assert bench.main(args) == 0  # a fresh checkout: nothing measured here yet, the published page redrawn
    assert suite.load_results(out / "results.json") == suite.load_results(docs / "results.json")
    assert "started from" in capsys.readouterr().out
    kept = suite.load_results(out / "results.json")
    (out / "results.json").write_text(json.dumps({"speed": kept["speed"]}))  # this machine's own measurements
    assert bench.main(args) == 0
    assert set(suite.load_results(docs / "results.json")) == {"speed"}  # the docs follow <out>, never the reverse
    assert "## Speed" in (docs / "results.md").read_text()
