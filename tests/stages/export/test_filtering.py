import numpy as np
import pytest

from stages.export.filtering import lowpass

RATE = 30.0


def _signal(n: int, frequency_hz: float, amplitude: float = 0.1) -> np.ndarray:
    """(n, 1, 3) a sinusoid in x (metres) on a regular grid at RATE."""
    t = np.arange(n) / RATE
    x = np.zeros((n, 1, 3))
    x[:, 0, 0] = amplitude * np.sin(2 * np.pi * frequency_hz * t)
    return x


def test_slow_motion_passes_unchanged_in_amplitude_and_time():
    slow = _signal(150, 1.0)
    out = lowpass(slow, RATE, 8.0)
    middle = slice(30, 120)  # away from the ends' padding
    # within 2 mm of a 10 cm sinusoid: no lag (one frame's would be 21 mm) and no loss of amplitude
    np.testing.assert_allclose(out[middle], slow[middle], atol=0.002)


def test_jitter_above_the_cut_off_is_removed():
    rng = np.random.default_rng(0)
    jitter = np.zeros((200, 2, 3))
    jitter[:, :, :] = rng.normal(0.0, 0.005, jitter.shape)
    out = lowpass(jitter, RATE, 4.0)
    assert out[20:-20].std() < 0.6 * jitter.std()  # white noise keeps the share below the cut-off
    fast = _signal(200, 12.0)
    assert np.abs(lowpass(fast, RATE, 4.0)[20:-20]).max() < 0.01 * np.abs(fast).max()


def test_gaps_stay_gaps_and_the_runs_around_them_are_filtered_apart():
    x = _signal(60, 1.0) + 0.5
    x[20:25] = np.nan
    x[40] = np.nan
    x[41] = 9.0  # a run of one frame is kept as it is
    x[42] = np.nan
    out = lowpass(x, RATE, 6.0)
    assert np.isnan(out[20:25]).all() and np.isnan(out[[40, 42]]).all()
    np.testing.assert_array_equal(out[41], x[41])
    np.testing.assert_allclose(out[:20], lowpass(x[:20], RATE, 6.0), atol=1e-12)  # no data crosses a gap


def test_cut_off_must_be_below_half_the_rate():
    with pytest.raises(ValueError, match="half the frame rate"):
        lowpass(_signal(20, 1.0), RATE, 15.0)
