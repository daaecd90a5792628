"""Whether each stage's results on disk are up to date (``python -m pipeline stages``), and why not."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.engine.cache import Expected, expected_record, output_changes, output_files, read_manifest
from pipeline.engine.stage import Stage
from pipeline.io.capture import Capture
from pipeline.io.run_layout import MANIFEST, MARKER


@dataclass(frozen=True)
class StageStatus:
    """``state`` is one of "up to date", "stale", "incomplete", "not run"; ``reason`` says why."""

    name: str
    state: str
    reason: str = ""


def _flatten(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, dict):
        flat = {}
        for key, item in value.items():
            flat.update(_flatten(item, f"{prefix}.{key}" if prefix else str(key)))
        return flat
    return {prefix: value}


def stale_reasons(manifest: dict, expected: Expected) -> list[str]:
    """Why a manifest does not match the expected record (empty when it does)."""
    reasons = []
    if manifest.get("code_version") != expected.record["code_version"]:
        reasons.append("code changed")
    old, new = _flatten(manifest.get("params")), _flatten(expected.record["params"])
    for key in sorted(set(old) | set(new)):
        if old.get(key) != new.get(key):
            reasons.append(f"parameter {key}: {old.get(key)!r} -> {new.get(key)!r}")
    for key, value in expected.record["inputs"].items():
        if manifest["inputs"].get(key) != value:
            kind, name = key.split(":", 1)
            reasons.append(f"upstream {name} changed" if kind == "stage" else f"capture {name} changed")
    if not reasons and manifest.get("cache_key") != expected.key:
        reasons.append("cache key differs")
    return reasons


def stage_status(stage: Stage, capture: Capture, params: Any, output_root: Path) -> StageStatus:
    """Whether ``stage``'s results on disk are up to date with the capture, parameters and code."""
    folder = output_root / stage.name
    manifest = read_manifest(folder)
    if manifest is None:
        if (folder / MARKER).exists():
            return StageStatus(stage.name, "incomplete",
                               f"{len(output_files(folder))} files kept; the next run resumes from them")
        if (folder / MANIFEST).exists():
            return StageStatus(stage.name, "stale", "manifest unreadable")
        return StageStatus(stage.name, "not run")
    expected = expected_record(stage, capture, params, output_root)
    if expected.missing:
        return StageStatus(stage.name, "stale",
                           f"upstream {', '.join(expected.missing)} has no complete result")
    reasons = stale_reasons(manifest, expected)
    changes = None if reasons else output_changes(folder, manifest)
    if changes:
        reasons.append(str(changes))
    return StageStatus(stage.name, "stale" if reasons else "up to date", "; ".join(reasons))


def graph_status(stages: Sequence[Stage], capture: Capture, params: Mapping[str, Any],
                 output_root: Path) -> list[StageStatus]:
    """Status of every stage; an up-to-date stage with a not-up-to-date upstream is reported stale."""
    statuses: dict[str, StageStatus] = {}
    for stage in stages:
        status = stage_status(stage, capture, params[stage.name], output_root)
        behind = [name for name in stage.inputs if statuses[name].state != "up to date"]
        if status.state == "up to date" and behind:
            status = StageStatus(stage.name, "stale", f"upstream {', '.join(behind)} not up to date")
        statuses[stage.name] = status
    return list(statuses.values())
