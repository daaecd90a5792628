"""Plots of the benchmark results (matplotlib, Agg backend: no display needed).

Each function takes a section of results.json and a PNG path, so a figure can be redrawn from a stored
results file without recomputing anything.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (the backend must be chosen first)

DISTANCE_STYLES = {
    "normals": {"label": "points + normals (paper)", "color": "tab:blue", "marker": "o"},
    "points": {"label": "points alone", "color": "tab:orange", "marker": "s"},
    "algebraic": {"label": "algebraic distance", "color": "tab:green", "marker": "^"},
}
ANGLE_LABELS = {"l_knee_flexion": "left knee flexion", "r_elbow_flexion": "right elbow flexion"}
DPI = 110


def _save(figure, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.tight_layout()
    figure.savefig(path, dpi=DPI)
    plt.close(figure)
    return path


def _sweep(axes, rows: list[dict], xlabel: str, title: str) -> None:
    for distance, style in DISTANCE_STYLES.items():
        points = sorted((row["x"], row["angle_error_deg"]) for row in rows if row["distance"] == distance)
        if points:
            xs, ys = zip(*points, strict=True)
            axes.plot(xs, ys, marker=style["marker"], color=style["color"], label=style["label"])
    axes.set_xlabel(xlabel)
    axes.set_ylabel("mean joint-angle error (deg)")
    axes.set_title(title)
    axes.grid(alpha=0.3)
    axes.legend(fontsize=8)


def paper_figure(paper: dict, path: Path) -> Path:
    """Horaud et al. 2009 Fig. 4 redone: trajectories, error vs silhouette noise, frame rate, observations."""
    figure, axes = plt.subplots(2, 2, figsize=(11, 8))
    trajectory = paper["trajectories"]
    for name, color in zip(ANGLE_LABELS, ("tab:red", "tab:purple"), strict=True):
        axes[0, 0].plot(trajectory["time_s"], trajectory[name]["truth"], "--", color=color,
                        label=f"{ANGLE_LABELS[name]}, truth")
        axes[0, 0].plot(trajectory["time_s"], trajectory[name]["estimate"], "-", color=color,
                        label=f"{ANGLE_LABELS[name]}, estimate")
    axes[0, 0].set_xlabel("time (s)")
    axes[0, 0].set_ylabel("flexion (deg)")
    axes[0, 0].set_title(f"(a) {len(trajectory['time_s'])} frames at 28 fps, points + normals")
    axes[0, 0].grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    _sweep(axes[0, 1], paper["noise"], "silhouette noise strength", "(b) silhouette noise")
    ious = {row["x"]: row["mask_iou"] for row in paper["noise"]}
    top = axes[0, 1].secondary_xaxis("top")
    top.set_xticks(list(ious), [f"{iou:.2f}" for iou in ious.values()], fontsize=7)
    top.set_xlabel("mean IoU of the noisy masks", fontsize=8)
    _sweep(axes[1, 0], paper["fps"], "frames per second", "(c) frame rate")
    axes[1, 0].set_xscale("log", base=2)
    rates = sorted({row["x"] for row in paper["fps"]})
    axes[1, 0].set_xticks(rates, [f"{rate:g}" for rate in rates])
    _sweep(axes[1, 1], paper["observations"], "observations per frame", "(d) number of observations")
    figure.suptitle(f"{paper['capture']}: {paper['recipe']['cameras']} cameras, "
                    f"{100 * paper['outlier_fraction']:.0f} % outliers", fontsize=10)
    return _save(figure, path)


def unseen_figure(unseen: dict, path: Path, *, target_mm: float, worst_target_mm: float) -> Path:
    """MPJPE and worst frame per capture, with the targets."""
    rows = [row for row in unseen["rows"] if "mpjpe_mm" in row]
    figure, axes = plt.subplots(figsize=(10, 4.5))
    names = [row["capture"] for row in rows]
    bars = axes.bar(names, [row["mpjpe_mm"] for row in rows], color="tab:blue", label="MPJPE")
    axes.bar_label(bars, fmt="%.0f", fontsize=8)
    axes.plot(names, [row["worst_frame_mm"] for row in rows], "v", color="tab:red", label="worst frame")
    axes.axhline(target_mm, color="tab:blue", ls="--", lw=1, label=f"target MPJPE {target_mm:g} mm")
    axes.axhline(worst_target_mm, color="tab:red", ls=":", lw=1, label=f"target worst {worst_target_mm:g} mm")
    axes.set_ylabel("mm")
    axes.set_title("Unseen captures: joint position error over the 15 scored joints")
    axes.tick_params(axis="x", labelrotation=30)
    axes.legend(fontsize=8)
    return _save(figure, path)


def speed_figure(speed: dict, path: Path) -> Path:
    """Milliseconds per frame of each stage and of all of them (the stages run one after another) against
    the real-time budget of the capture's frame rate."""
    stages = speed["stage_ms_per_frame"]
    wall = 1000.0 / speed["fps_end_to_end"]
    figure, axes = plt.subplots(figsize=(7, 4))
    bars = axes.barh([*stages, "all stages", "end to end (wall)"], [*stages.values(), sum(stages.values()), wall],
                     color=["tab:gray"] * len(stages) + ["tab:blue", "tab:purple"])
    axes.bar_label(bars, fmt="%.0f", fontsize=8, padding=2)
    budget = 1000.0 / speed["fps_capture"]
    axes.axvline(budget, color="tab:red", ls="--",
                 label=f"real-time budget at {speed['fps_capture']:g} fps: {budget:.1f} ms")
    axes.invert_yaxis()
    axes.set_xlabel("ms per frame (2 workers)")
    axes.set_title(f"{speed['capture']}: {speed['frames']} frames, end to end {speed['fps_end_to_end']:.1f} fps")
    axes.legend(fontsize=8)
    return _save(figure, path)
