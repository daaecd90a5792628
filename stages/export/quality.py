"""``quality.csv``: how far each frame and each joint of the exports can be trusted.

joints.csv says where the joints are, not how well the data pinned them down; a fit can be "tracked"
with a forearm that no observation supports (hidden, or folded away from its data, while EM keeps it
where the prediction put it). This table gives, for every frame of the capture:

==================================== ==========================================================================
column                               meaning
==================================== ==========================================================================
frame                                the capture's frame number (joints.csv has rows only for exported frames)
status                               the tracker's: tracked, initialised (exported); predicted, lost (not)
doubtful                             1 when the fit failed the tracker's failure checks even after a fresh
                                     initialisation (too many outliers or a Σ too wide); exported, but suspect
observations                         usable observations of the frame
log_likelihood_per_observation       ln P(Y | Λ) / observations, nats (higher = data closer to the surface);
                                     compare frames of one capture, not captures
outlier_fraction                     mean posterior of the outlier class: the share of data the body leaves
                                     unexplained
unsupported                          in a fitted frame, the joints whose confidence is below
                                     :data:`UNSUPPORTED_CONFIDENCE`, space-separated (empty when none)
corrected                            the limbs the tracker put elsewhere on this tracked frame rather than
                                     following them (``FrameResult.corrected``), space-separated: the frames
                                     to look at first where a limb went wrong
<joint>_confidence                   per joint, from 0 to 1 (below)
==================================== ==========================================================================

Per-joint confidence
    Each joint is placed, relative to the joint before it, by one segment of the body (the elbow by
    the upper arm, the wrist by the forearm; the tracker records how many observations that segment
    explains, ``FrameResult.joint_support``). Its support ratio is that count over the segment's
    typical count in this capture (its median over the fitted frames, :data:`TYPICAL_PERCENTILE`),
    capped at 1; a joint's confidence is the smallest
    ratio along its chain from the pelvis, since a wrist is no better placed than the elbow it hangs
    from. A frame that was not fitted has confidence 0, and so does a joint whose segment never
    explained any data. The ratio is relative to the capture itself, so it does not depend on how
    many observations the reconstruction makes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from stages.export.skeleton import bones_among

#: Percentile of a joint's support over the fitted frames taken as its typical support: the median. A
#: high one (the 90th) took the ordinary frame-to-frame variation of the well-seen pelvis's share for a
#: lack of data, and capped every joint below it.
TYPICAL_PERCENTILE = 50.0

#: Below this confidence a joint is listed as unsupported: its segment explains less than half the data
#: it explains when well seen.
UNSUPPORTED_CONFIDENCE = 0.5

#: Decimal places of the real-valued columns.
DECIMALS = 4


@dataclass(frozen=True)
class FrameQuality:
    """The tracker's per-frame record of every frame of the capture, as arrays (F frames, J joints).

    Attributes
    ----------
    frames : (F,) int
    statuses : (F,) str
    doubtful : (F,) bool
    observations : (F,) int
    log_likelihood : (F,) float, nats (0 when not fitted)
    outlier_fraction : (F,) float
    support : (F, J) float
        Observations supporting each joint (``FrameResult.joint_support``), NaN where not recorded
        (frames not fitted).
    fitted : (F,) bool
        The frames fitted to data (the exported statuses).
    corrected : (F,) str
        The limbs corrected on each frame (``FrameResult.corrected``), space-separated.
    """

    frames: np.ndarray
    statuses: np.ndarray
    doubtful: np.ndarray
    observations: np.ndarray
    log_likelihood: np.ndarray
    outlier_fraction: np.ndarray
    support: np.ndarray
    fitted: np.ndarray
    corrected: np.ndarray


def joint_confidence(support: np.ndarray, fitted: np.ndarray, names: Sequence[str]) -> np.ndarray:
    """(F, J) confidence in [0, 1] of every joint in every frame (the module docstring).

    Parameters
    ----------
    support : (F, J) float, observations supporting each joint (NaN where not fitted)
    fitted : (F,) bool
    names : J joint names (their chains are :data:`stages.export.skeleton.BONES`)
    """
    support = np.asarray(support, dtype=np.float64)
    fitted = np.asarray(fitted, dtype=bool)
    confidence = np.zeros_like(support)
    if not fitted.any():
        return confidence
    typical = np.percentile(support[fitted], TYPICAL_PERCENTILE, axis=0)  # (J,)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(typical > 0, support / typical, 0.0)
    confidence[fitted] = np.clip(np.nan_to_num(ratio[fitted]), 0.0, 1.0)
    for parent, child in bones_among(names):  # parents first, so each chain is carried down whole
        confidence[:, child] = np.minimum(confidence[:, child], confidence[:, parent])
    return confidence


def format_quality_csv(quality: FrameQuality, names: Sequence[str]) -> str:
    """The text of ``quality.csv`` (columns in the module docstring), one row per frame in frame order."""
    confidence = joint_confidence(quality.support, quality.fitted, names)
    header = ["frame", "status", "doubtful", "observations", "log_likelihood_per_observation", "outlier_fraction",
              "unsupported", "corrected"] + [f"{name}_confidence" for name in names]
    lines = [",".join(header)]
    for f in np.argsort(quality.frames, kind="stable"):
        fitted = bool(quality.fitted[f]) and quality.observations[f] > 0
        per_observation = f"{quality.log_likelihood[f] / quality.observations[f]:.{DECIMALS}f}" if fitted else ""
        outliers = f"{quality.outlier_fraction[f]:.{DECIMALS}f}" if fitted else ""
        weak = " ".join(name for name, c in zip(names, confidence[f], strict=True) if c < UNSUPPORTED_CONFIDENCE)
        lines.append(",".join([str(int(quality.frames[f])), str(quality.statuses[f]), str(int(quality.doubtful[f])),
                               str(int(quality.observations[f])), per_observation, outliers, weak if fitted else "",
                               str(quality.corrected[f])]
                              + [f"{c:.{DECIMALS}f}" for c in confidence[f]]))
    return "\n".join(lines) + "\n"
