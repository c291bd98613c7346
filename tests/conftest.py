"""Shared test helpers: synthetic multi-device recordings with known delays."""
from __future__ import annotations

import numpy as np
import pytest
import soundfile as sf
import soxr

REPO_FIXTURES = __import__("pathlib").Path(__file__).resolve().parents[1] / "replay_fixtures"


def bursty_source(n_samples: int, *, sample_rate_hz: float, seed: int = 0) -> np.ndarray:
    """Speech-like test source: band-limited noise with a syllable-rate on/off envelope."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal(n_samples)
    spec = np.fft.rfft(x)
    f = np.fft.rfftfreq(n_samples, 1 / sample_rate_hz)
    spec[(f < 100) | (f > 0.45 * sample_rate_hz)] = 0
    x = np.fft.irfft(spec, n_samples)
    # syllables and pauses of random length (0.08-0.4 s on, 0.05-0.5 s off), random levels
    env = np.zeros(n_samples)
    pos = 0
    while pos < n_samples:
        on = int(rng.uniform(0.08, 0.4) * sample_rate_hz)
        env[pos:pos + on] = rng.uniform(0.3, 1.0)
        pos += on + int(rng.uniform(0.05, 0.5) * sample_rate_hz)
    env = np.convolve(env, np.hanning(int(0.02 * sample_rate_hz)) / (0.01 * sample_rate_hz), mode="same")
    x = x * env
    return (0.3 * x / np.max(np.abs(x))).astype(np.float32)


def delayed(x: np.ndarray, delay_samples: float, n_out: int) -> np.ndarray:
    """``x`` delayed by a fractional number of samples (FFT phase shift), cut to ``n_out``."""
    n = len(x) + int(abs(delay_samples)) + 16
    n_fft = 1 << (n - 1).bit_length()
    spec = np.fft.rfft(x, n_fft)
    k = np.arange(len(spec))
    y = np.fft.irfft(spec * np.exp(-2j * np.pi * k * delay_samples / n_fft), n_fft)
    return y[:n_out].astype(np.float32)


@pytest.fixture
def make_devices(tmp_path):
    """Write one WAV per device; device ``i`` hears the source ``toa_s[i]`` seconds after device 0.

    Returns (paths, source at rate_hz, toa_s).
    """

    def _make(toa_s, *, duration_s=6.0, rate_hz=16000, rates_hz=None, snr_db=30.0, seed=0, gains=None,
              subtype="FLOAT", fmt="wav"):
        toa_s = np.asarray(toa_s, float)
        n = int(duration_s * rate_hz)
        src = bursty_source(n + int(rate_hz * (toa_s.max() - toa_s.min() + 1)), sample_rate_hz=rate_hz, seed=seed)
        lead = int(rate_hz * max(0.0, -toa_s.min())) + rate_hz // 2
        rng = np.random.default_rng(seed + 1)
        paths = []
        for d, tau in enumerate(toa_s):
            x = delayed(src, lead + tau * rate_hz, n)
            x = x * (1.0 if gains is None else gains[d])
            x = x + rng.standard_normal(n).astype(np.float32) * 0.3 * 10 ** (-snr_db / 20) * 0.3
            r = rate_hz if rates_hz is None else rates_hz[d]
            if r != rate_hz:
                x = soxr.resample(x, rate_hz, r)
            p = tmp_path / f"dev{d}.{fmt}"
            sf.write(p, x, int(r), subtype=subtype)
            paths.append(p)
        return paths, src, toa_s

    return _make
