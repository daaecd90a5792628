"""Estimated segment lengths of runs against their captures' true ones, as a table.

    python -m pipeline.lab.bench.segment_lengths runs/bench/foreign/leaning runs/bench/unseen/walk_capsules ...

For each run folder and each bone of :data:`stages.export.skeleton.BONES` (left and right taken together),
the median over frames of the exported joints' distance divided by the median of the ground truth's (the
truth of the capture the run was made from, :func:`pipeline.evaluate.default_truth`). A ratio above 1 is a
segment estimated too long. What it shows: which proportions the tracker gets wrong, and whether the errors
of neighbouring segments trade off (a long upper arm beside a short forearm: the elbow misplaced along an arm
whose total length is right).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from calib.errors import InputError
from pipeline.evaluate import default_truth
from pipeline.io.export_io import read_joints_csv
from pipeline.io.run_layout import RunLayout
from pipeline.terminal import printable
from stages.export.skeleton import BONES


def _side_free(name: str) -> str:
    return name.removeprefix("l_").removeprefix("r_")


def bone_groups() -> dict[str, list[tuple[str, str]]]:
    """The bones of the table, left and right as one: "shoulder-elbow" stands for both upper arms (the toes left
    out: the truth may not have them)."""
    groups: dict[str, list[tuple[str, str]]] = {}
    for parent, child in BONES:
        if not child.endswith("toe"):
            groups.setdefault(f"{_side_free(parent)}-{_side_free(child)}", []).append((parent, child))
    return groups


def median_lengths(path: Path, frames: np.ndarray | None = None) -> tuple[np.ndarray, dict[str, float]]:
    """The frames of a joints.csv (or those of ``frames`` it has) and each bone group's median length (metres)."""
    numbers, names, joints = read_joints_csv(path)
    if frames is not None:
        keep = np.isin(numbers, frames)
        numbers, joints = numbers[keep], joints[keep]
    index = {name: k for k, name in enumerate(names)}
    lengths = {}
    for group, pairs in bone_groups().items():
        present = [(index[a], index[b]) for a, b in pairs if a in index and b in index]
        if present:
            lengths[group] = float(np.median(np.concatenate(
                [np.linalg.norm(joints[:, a] - joints[:, b], axis=1) for a, b in present])))
    return numbers, lengths


def length_ratios(run_dir: Path) -> dict[str, float]:
    """Each bone group's estimated over true median length, over the frames both have.

    Raises
    ------
    InputError
        When `run_dir` is not a finished run (no export/joints.csv) or its capture has no ground truth.
    """
    joints = RunLayout(run_dir).joints
    if not joints.is_file():
        raise InputError(f"{run_dir}: no {joints.relative_to(run_dir)} (expected the folder of a finished run)")
    estimated_frames, _ = median_lengths(joints)
    truth_frames, truth = median_lengths(default_truth(run_dir), estimated_frames)
    _, estimate = median_lengths(joints, truth_frames)
    return {group: estimate[group] / truth[group] for group in estimate if group in truth}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+", help="run folders (each holds export/joints.csv)")
    args = parser.parse_args(argv)
    groups = list(bone_groups())
    try:
        table = [(run, length_ratios(run)) for run in args.runs]
    except InputError as error:
        parser.exit(2, f"error: {printable(str(error))}\n")
    print("| run | " + " | ".join(groups) + " |")
    print("|---|" + "---:|" * len(groups))
    for run, ratios in table:
        cells = [f"{ratios[group]:.2f}" if group in ratios else "" for group in groups]
        print(f"| {run.parent.name}/{run.name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
