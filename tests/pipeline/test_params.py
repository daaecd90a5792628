"""Stage parameters from --config and --set, validated against the stages' dataclasses."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import pytest

from calib.errors import InputError
from pipeline.engine.params import apply_overrides, params_to_dict, parse_assignments, read_config


@dataclass(frozen=True)
class EMParams:
    max_iterations: int = 30
    tolerance: float = 1e-4


@dataclass(frozen=True)
class FakeParams:
    threshold: float = 25.0
    method: Literal["visual_shape", "visual_hull"] = "visual_shape"
    body: str | None = None
    enabled: bool = True
    volume_margin: tuple[float, float, float] = (0.1, 0.1, 0.0)
    em: EMParams = field(default_factory=EMParams)

    def __post_init__(self) -> None:
        if self.threshold < 0:
            raise ValueError(f"threshold {self.threshold}: expected >= 0")


DEFAULTS = {"fake": FakeParams(), "plain": None}


def test_parse_assignments_uses_yaml_values():
    assert parse_assignments(["fake.threshold=30", "fake.em.tolerance=1e-6", "fake.enabled=false",
                              "fake.volume_margin=[0, 0.2, 0]", "fake.body=paper"]) == {
        "fake": {"threshold": 30, "em": {"tolerance": "1e-6"}, "enabled": False,
                 "volume_margin": [0, 0.2, 0], "body": "paper"}}


def test_overrides_are_converted_to_the_field_types():
    params = apply_overrides(DEFAULTS, parse_assignments(
        ["fake.threshold=30", "fake.volume_margin=[0, 0.2, 0]", "fake.em.max_iterations=5",
         "fake.method=visual_hull", "fake.em.tolerance=1e-6"]), source="--set")["fake"]
    assert params.threshold == 30.0 and isinstance(params.threshold, float)
    assert params.volume_margin == (0.0, 0.2, 0.0)
    assert params.em == EMParams(max_iterations=5, tolerance=1e-6)
    assert params.method == "visual_hull"
    assert params_to_dict(params)["volume_margin"] == [0.0, 0.2, 0.0]


def test_unknown_key_lists_the_valid_ones():
    expected = r"--set fake.treshold: unknown parameter \(expected one of threshold, method, body, enabled, "
    with pytest.raises(InputError, match=expected + r"volume_margin, em\)"):
        apply_overrides(DEFAULTS, {"fake": {"treshold": 3}}, source="--set")


def test_unknown_nested_key():
    with pytest.raises(InputError, match="fake.em.iterations: unknown parameter"):
        apply_overrides(DEFAULTS, {"fake": {"em": {"iterations": 3}}}, source="--set")


@pytest.mark.parametrize(("values", "message"), [
    ({"threshold": "high"}, "fake.threshold: 'high' is not valid (expected a number)"),
    ({"enabled": 1}, "fake.enabled: 1 is not valid (expected true or false)"),
    ({"method": "voxels"}, "expected one of 'visual_shape', 'visual_hull'"),
    ({"volume_margin": [1, 2]}, "fake.volume_margin: [1, 2] is not valid"),
    ({"em": {"max_iterations": 2.5}}, "fake.em.max_iterations: 2.5 is not valid (expected an integer)"),
    ({"threshold": -1}, "fake: threshold -1.0: expected >= 0"),
])
def test_wrong_values_are_input_errors(values, message):
    with pytest.raises(InputError, match=message.replace("[", r"\[").replace("(", r"\(").replace(")", r"\)")):
        apply_overrides(DEFAULTS, {"fake": values}, source="--set")


def test_read_config_file(tmp_path):
    path = tmp_path / "params.yaml"
    path.write_text("fake:\n  threshold: 12\n  em: {max_iterations: 3}\n")
    params = apply_overrides(DEFAULTS, read_config(path), source=f"{path}:")["fake"]
    assert (params.threshold, params.em.max_iterations) == (12.0, 3)


def test_read_config_file_of_the_wrong_shape(tmp_path):
    path = tmp_path / "params.yaml"
    path.write_text("- fake\n")
    with pytest.raises(InputError, match="params.yaml: expected a mapping of stage names"):
        read_config(path)
