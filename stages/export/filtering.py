"""Optional temporal smoothing of exported joint trajectories: a zero-phase Butterworth low-pass.

The tracker fits every frame on its own data (from the previous frame's pose), so its joints carry
frame-to-frame jitter, which differentiation amplifies: a millimetre of white jitter (standard
deviation) at 30 frames/s is √6 mm / (1/30 s)² ≈ 2 m/s² of acceleration noise. Biomechanics smooths
marker and joint trajectories with a low-pass Butterworth filter run forwards and backwards (Winter,
"Biomechanics and Motor Control of Human Movement", ch. 3; Pose2Sim and FreeMoCap do the same): the
two passes cancel each other's phase lag, so no event moves in time, and square the magnitude
response (a second-order filter passed twice is fourth order, 6 dB down at the cut-off).

Only the exports are smoothed, never the tracker's state: the next frame's fit still starts from
the unfiltered estimate.
"""

from __future__ import annotations

import numpy as np

#: Order of each pass; forwards and backwards together make a fourth-order zero-phase filter.
FILTER_ORDER = 2


def lowpass(gridded: np.ndarray, rate_hz: float, cutoff_hz: float) -> np.ndarray:
    """Joint trajectories on a regular frame grid, each run of estimated frames low-passed on its own.

    Parameters
    ----------
    gridded : (G, J, 3) float
        Positions on consecutive grid frames (``joints_table.regular_grid``), NaN in frames that were
        not estimated. Each run of estimated frames between such gaps is filtered separately: a gap
        has no data to smooth across, and interpolating it first would put invented motion into the
        frames around it.
    rate_hz : float
        Frames per second of the grid (the capture's rate divided by its frame step).
    cutoff_hz : float
        Cut-off of each pass, 0 < cutoff < rate / 2.

    Returns
    -------
    (G, J, 3) float, NaN where ``gridded`` is. A run too short for the filter's edge padding is padded
    as far as it allows; a single frame stays as it is.
    """
    if not 0 < cutoff_hz < rate_hz / 2:
        raise ValueError(f"cut-off {cutoff_hz} Hz must be above 0 and below half the frame rate ({rate_hz / 2} Hz)")
    # Imported here, not at the top: scipy.signal takes about half a second to import, a wait that
    # every run would pay before its first frame although smoothing is off unless asked for.
    from scipy.signal import butter, sosfiltfilt

    gridded = np.asarray(gridded, dtype=np.float64)
    sos = butter(FILTER_ORDER, cutoff_hz, btype="low", fs=rate_hz, output="sos")
    default_padding = 3 * (2 * len(sos) + 1)  # sosfiltfilt's own default
    smoothed = gridded.copy()
    for start, stop in _runs(~np.isnan(gridded[:, 0, 0])):
        if stop - start > 1:
            smoothed[start:stop] = sosfiltfilt(sos, gridded[start:stop], axis=0,
                                               padlen=min(default_padding, stop - start - 1))
    return smoothed


def _runs(known: np.ndarray) -> list[tuple[int, int]]:
    """``[start, stop)`` of every run of True in the boolean vector ``known``."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], known.astype(np.int8), [0]])))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))
