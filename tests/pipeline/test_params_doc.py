"""docs/parameters.md is generated from the parameter dataclasses and must not drift from them."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from pipeline.commands.params import attribute_docs, parameters_markdown
from pipeline.graph import STAGES

DOC = Path(__file__).resolve().parents[2] / "docs" / "parameters.md"


def test_parameters_doc_is_current():
    assert DOC.read_text() == parameters_markdown(), (
        "docs/parameters.md is stale: regenerate it with `python -m pipeline params > docs/parameters.md`")


def test_every_parameter_is_documented():
    for stage in STAGES:
        if stage.params_type is None:
            continue
        docs = attribute_docs(stage.params_type.__doc__)
        missing = [f.name for f in dataclasses.fields(stage.params_type) if f.name not in docs]
        assert not missing, f"{stage.params_type.__name__} docstring lacks Attributes entries for {missing}"


def test_attribute_docs_reads_shared_entries():
    doc = """Thresholds.

    Attributes
    ----------
    low, high : float
        Band limits,
        in metres.
    mode : {"a", "b"}
    """
    assert attribute_docs(doc) == {"low": ("float", "Band limits, in metres."),
                                   "high": ("float", "Band limits, in metres."),
                                   "mode": ('{"a", "b"}', "")}
