"""DriftMeter: each device's relative TOA rate from the rotation of the pairs' cross-power spectra."""
import numpy as np
import pytest

from estimators import DriftMeter, pairs

FS = 16000.0
N_FFT = 512
HOP_S = 4 * 128 / FS   # every fourth 128-sample hop, as the pipeline feeds the meter


def _cross_frames(rates_s_per_s, seconds, *, seed=0, bursty=True, jump_at_s=None, jump_s=None):
    """Yield (time_s, cross (n_pairs, n_bins)) of a steady source and a bursty one (on about a third of the
    time, in 0.1-0.4 s bursts), both static, heard by devices whose clocks drift at ``rates_s_per_s``."""
    rng = np.random.default_rng(seed)
    m = len(rates_s_per_s)
    f = np.arange(N_FFT // 2 + 1) * FS / N_FFT
    toa_a = rng.uniform(-3e-3, 3e-3, m)
    toa_b = rng.uniform(-3e-3, 3e-3, m)
    p = pairs(m)
    on, left = False, 0
    smooth = np.zeros((len(p), len(f)), complex)
    for k in range(int(seconds / HOP_S)):
        t = k * HOP_S
        if left <= 0:
            on, left = (not on) if bursty else True, rng.integers(2, 8)
        left -= 1
        drift = np.asarray(rates_s_per_s) * t
        if jump_at_s is not None and t >= jump_at_s:
            if k * HOP_S < jump_at_s + HOP_S:   # the engine turns its short-time average with the move
                d = np.asarray(jump_s)
                smooth *= np.exp(-2j * np.pi * np.outer(d[p[:, 0]] - d[p[:, 1]], f))
            drift = drift + np.asarray(jump_s)
        sa = rng.standard_normal(len(f)) + 1j * rng.standard_normal(len(f))
        x = sa[None] * np.exp(-2j * np.pi * np.outer(toa_a + drift, f))
        if on:
            sb = 3 * (rng.standard_normal(len(f)) + 1j * rng.standard_normal(len(f)))
            x = x + sb[None] * np.exp(-2j * np.pi * np.outer(toa_b + drift, f))
        x = x + 0.3 * (rng.standard_normal(x.shape) + 1j * rng.standard_normal(x.shape))
        smooth += 0.35 * (x[p[:, 0]] * np.conj(x[p[:, 1]]) - smooth)
        yield t, smooth


@pytest.mark.parametrize("bursty", [False, True])
def test_the_rates_of_drifting_clocks_are_found_within_a_few_ppm(bursty):
    rates = np.array([0.0, 80e-6, -120e-6, 40e-6])
    meter = DriftMeter(4, n_fft=N_FFT, sample_rate_hz=FS)
    assert meter.rate_s_per_s is None
    for t, cross in _cross_frames(rates, 8.0, bursty=bursty):
        meter.add(cross, t, HOP_S)
    assert meter.rate_s_per_s is not None
    assert meter.rate_s_per_s[0] == 0.0
    assert np.max(np.abs(meter.rate_s_per_s - rates)) < 5e-6


def test_clocks_without_drift_give_zero_rates():
    meter = DriftMeter(3, n_fft=N_FFT, sample_rate_hz=FS)
    for t, cross in _cross_frames(np.zeros(3), 5.0, seed=1):
        meter.add(cross, t, HOP_S)
    assert np.max(np.abs(meter.rate_s_per_s)) < 3e-6


def test_a_known_re_alignment_is_not_read_as_drift():
    """Device 2's signals jump 0.4 ms earlier at 4 s (the aligner moved it) and the meter is told: the rates stay."""
    rates = np.array([0.0, 60e-6, -90e-6])
    meter = DriftMeter(3, n_fft=N_FFT, sample_rate_hz=FS)
    jump = np.array([0.0, 0.0, -4e-4])
    moved = False
    for t, cross in _cross_frames(rates, 10.0, seed=2, jump_at_s=4.0, jump_s=jump):
        if t >= 4.0 and not moved:
            meter.shift(jump)
            moved = True
        meter.add(cross, t, HOP_S)
        if t >= 4.5:   # every estimate from the move on
            assert np.max(np.abs(meter.rate_s_per_s - rates)) < 5e-6, (t, meter.rate_s_per_s)


def test_one_device_has_no_drift_to_measure():
    with pytest.raises(ValueError, match="n_devices=1 must be at least 2"):
        DriftMeter(1, n_fft=N_FFT, sample_rate_hz=FS)
