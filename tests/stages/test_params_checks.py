"""Every stage parameter is checked at the door (issue #13 item 2): a bad value is a one-line InputError
naming ``<stage>.<field>``, and through the CLI exit status 2 before any work, never a traceback or a
silently wrong run."""

from __future__ import annotations

import dataclasses
import math

import pytest
from conftest import make_capture

from calib.errors import InputError
from pipeline.cli import main
from pipeline.graph import STAGES
from pipeline.io.run_layout import MANIFEST
from stages.export import ExportParams
from stages.reconstruction import ReconstructionParams
from stages.silhouettes import SilhouetteParams
from stages.tracking.params import TrackerParams

NAN, INF = math.nan, math.inf
# Field -> values it must refuse (wrong type, NaN/inf, out of range, unknown choice).
BAD = {
    TrackerParams: {
        "height_m": [0.0, -1.75, 3.0, NAN, INF, True, "1.75"],
        "distance": ["foo", "", None],
        "max_iterations": [-5, 0, 2.5, True, NAN],
        "tolerance": [-0.01, NAN, INF, True],
        "displacement_m": [-0.002, NAN, INF],
        "estimate_lengths": [("foo",), ("shank", "shank"), "shank", ("shank", 3), ["shank"]],
        "sigma_m": [-0.02, 0.0, NAN, INF, False],
        "min_observations": [0, -1, 30.0, True],
        "max_outlier_fraction": [0.0, -0.1, 1.5, NAN],
        "failure_sigma_m": [0.0, -0.05, NAN, INF, 0.06, 0.2],  # 0.06 = max_sigma_m: Σ never exceeds it
        "reinit_every": [-1, 1.0, True],
        "reinit_margin": [-0.05, NAN, INF],
        "refit_drop": [-0.1, NAN, -INF],
        "refit_iterations": [0, -20, 20.0],
        "restart_drop": [-0.3, NAN, -INF],
        "velocity_decay": [-0.1, 1.5, NAN],
        "max_predicted_frames": [-1, 10.0],
        "scale_frames": [-1, NAN],
        "init_headings": [0, -12, 12.0, True],
        "init_refine": [0, -24, 24.5],
        "normal_noise_deg": [-10.0, 91.0, NAN, INF],
        "min_outlier_prior": [-0.05, 0.6, 1.0, NAN],
        "max_sigma_m": [0.0, -0.06, NAN, INF],
        "limb_share_ratio": [-0.1, 1.5, NAN],
        "stated_height_weight": [-0.5, 1.5, NAN, INF],
        "limb_min_observations": [-1, 2.5, True],
        "limb_check_every": [-1, 2.5, True],
        "seed": [-1, 0.5, True],
        "body": ["centaur", "", 3, None],  # a missing body file: tests/pipeline/test_body_io.py
    },
    SilhouetteParams: {
        "downsample": [0, 2.0, True], "blur_kernel_px": [2, 0, True], "strong_threshold": [NAN, INF, 1.0],
        "weak_threshold": [-1.0, NAN], "shadow_min": [NAN, 0.0], "shadow_max": [NAN, 1.5], "shadows": ["foo"],
        "background_jitter_px": [-0.2, NAN, INF], "opening_px": [-1, 1.5], "closing_px": [-2, NAN],
        "min_component_fraction": [-0.05, NAN], "min_component_area_fraction": [NAN, -1.0],
        "max_hole_fraction": [INF, -0.01], "multiview_check": [1, "yes", None], "find_room_changes": [1, "yes", None],
    },
    ReconstructionParams: {
        "method": ["foo"], "n_observations": [49, 5001, 1000.0, True], "tolerated_views": [-1, 0.5],
        "rim_placement": ["foo"], "samples_per_ray": [1, NAN], "contour_smoothing_px": [-1.0, NAN, INF],
        "voxel_size_m": [0.0, NAN, 0.1], "coarse_voxel_size_m": [NAN, INF, 0.005],
        "refine_calibration": [1, "yes", None],
        "find_hidden_parts": [1, "yes", None],
    },
    ExportParams: {"report": [1, "yes", None], "overlay_videos": [0, "true"], "sync_check": [1, "no"],
                   "filter_cutoff_hz": [0.0, -6.0, NAN, INF, True, "6"], "bvh_units": ["inch", None],
                   "bvh_names": ["cmu", None], "trc_names": ["openpose", None]},
}
CASES = [(params_type, name, value) for params_type, fields in BAD.items()
         for name, values in fields.items() for value in values]
PREFIX = {TrackerParams: "tracking", SilhouetteParams: "silhouettes", ReconstructionParams: "reconstruction",
          ExportParams: "export"}


def test_every_field_of_every_stage_has_bad_values_here():
    for stage in STAGES:
        if stage.params_type is not None:
            assert {field.name for field in dataclasses.fields(stage.params_type)} == set(BAD[stage.params_type])


@pytest.mark.parametrize("params_type", list(BAD))
def test_the_defaults_pass(params_type):
    params_type()


@pytest.mark.parametrize(("params_type", "name", "value"), CASES,
                         ids=[f"{PREFIX[t]}.{name}={value!r}" for t, name, value in CASES])
def test_a_bad_value_is_a_one_line_input_error_naming_the_field(params_type, name, value):
    with pytest.raises(InputError) as error:
        params_type(**{name: value})
    message = str(error.value)
    assert "\n" not in message and "expected" in message
    assert message.startswith(f"{PREFIX[params_type]}.") and name in message.split(":")[0], message


@pytest.mark.parametrize("values", [{"refit_drop": INF, "restart_drop": INF}, {"height_m": 1.75},
                                    {"estimate_lengths": ()}, {"estimate_lengths": ["thigh", "trunk"]},
                                    {"reinit_every": 0, "scale_frames": 0, "max_predicted_frames": 0}])
def test_edge_values_that_mean_something_pass(values):
    TrackerParams(**{key: tuple(value) if isinstance(value, list) else value for key, value in values.items()})


@pytest.mark.parametrize(("assignment", "fragment"), [
    ("tracking.max_iterations=-5", "tracking.max_iterations: expected an integer >= 1, got -5"),
    ("tracking.sigma_m=-0.02", "tracking.sigma_m: expected a finite number > 0, got -0.02"),
    ("tracking.init_headings=0", "tracking.init_headings: expected an integer >= 1, got 0"),
    ("tracking.sigma_m=nan", "tracking.sigma_m: expected a finite number > 0, got nan"),
    ("tracking.max_sigma_m=.inf", "tracking.max_sigma_m: expected a finite number > 0, got inf"),
    ("tracking.distance=foo", "tracking.distance: expected one of normals, points, algebraic, got 'foo'"),
    ("tracking.estimate_lengths=[shank, foo]", "tracking.estimate_lengths: expected a list of distinct"),
    ("silhouettes.weak_threshold=.nan", "silhouettes.weak_threshold: expected a finite number, got nan"),
])
def test_the_cli_refuses_a_bad_value_in_one_line_before_any_work(tmp_path, capsys, assignment, fragment):
    capture, out = make_capture(tmp_path / "capture"), tmp_path / "out"
    assert main(["run", str(capture), "--out", str(out), "-q", "--set", assignment]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and fragment in err[0], err
    assert not list(out.rglob(MANIFEST))


