"""Chirp detection and TDOA-S / TDOA-M extraction (estimators.chirps), synthetic signals with known onsets."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimators import chirps
from estimators import hybrid_tdoa as ht

FS = 16000.0
C = 343.0


def template() -> np.ndarray:
    return chirps.linear_chirp(duration_s=0.1, f0_hz=300.0, f1_hz=6000.0, sample_rate_hz=FS)


def fractional_delay(x: np.ndarray, delay_samples: float, n_out: int) -> np.ndarray:
    """``x`` delayed by a (fractional) number of samples via the FFT, length ``n_out``."""
    n = int(2 ** np.ceil(np.log2(n_out + len(x))))
    spec = np.fft.rfft(x, n) * np.exp(-2j * np.pi * np.fft.rfftfreq(n) * delay_samples)
    return np.fft.irfft(spec, n)[:n_out]


def render(onsets_s: np.ndarray, n_samples: int, rng: np.random.Generator, *, noise_std: float = 0.2,
           gains=None, echo: bool = True) -> np.ndarray:
    """A stream with the template at ``onsets_s`` (seconds), an echo 12 ms later and white noise."""
    tpl = template()
    x = rng.normal(0.0, noise_std, n_samples)
    for j, t in enumerate(onsets_s):
        g = 1.0 if gains is None else gains[j]
        n0 = int(np.floor(t * FS))
        seg = fractional_delay(tpl, t * FS - n0, len(tpl) + 400)
        if echo:
            seg[192:] += 0.4 * seg[:-192]
        x[n0:n0 + len(seg)] += g * seg[:max(0, min(len(seg), n_samples - n0))]
    return x


def test_linear_chirp_shape_and_validation():
    tpl = template()
    assert tpl.shape == (1600,)
    assert np.max(np.abs(tpl)) <= 1.0 and abs(tpl[0]) < 1e-3 and abs(tpl[-1]) < 1e-3
    with pytest.raises(ValueError, match="f1_hz"):
        chirps.linear_chirp(duration_s=0.1, f0_hz=100.0, f1_hz=9000.0, sample_rate_hz=FS)


def test_detects_known_onsets_within_one_sample():
    rng = np.random.default_rng(0)
    onsets = np.array([0.31, 1.2037, 2.05, 3.3331, 4.0])
    x = render(onsets, int(4.5 * FS), rng, noise_std=0.3)
    found = chirps.detect_chirps(x, template(), sample_rate_hz=FS, min_separation_s=0.4)
    assert found.shape == onsets.shape
    assert np.max(np.abs(found - onsets)) * FS < 1.0


def test_detection_ignores_noise_only_stream():
    rng = np.random.default_rng(1)
    x = rng.normal(0.0, 1.0, int(2 * FS))
    assert len(chirps.detect_chirps(x, template(), sample_rate_hz=FS, min_separation_s=0.4)) == 0


@settings(max_examples=20, deadline=None)
@given(delay=st.floats(-40.0, 40.0))
def test_gcc_phat_follows_a_shift(delay):
    rng = np.random.default_rng(2)
    base = rng.normal(0.0, 1.0, 1024)
    shifted = fractional_delay(np.concatenate([np.zeros(64), base]), delay, 1024 + 128)
    ref = np.concatenate([np.zeros(64), base, np.zeros(64)])
    d = chirps.gcc_phat_delays(ref, shifted[None, :], sample_rate_hz=FS)[0]
    assert abs(d * FS - delay) < 0.2  # samples (parabolic interpolation of the PHAT peak)
    back = chirps.gcc_phat_delays(shifted, ref[None, :], sample_rate_hz=FS)[0]
    assert abs(back + d) * FS < 0.1  # tdoa(x, y) == -tdoa(y, x)


def test_extract_tdoas_with_a_missed_chirp():
    rng = np.random.default_rng(3)
    n_dev, k = 4, 6
    interval = rng.uniform(0.8, 1.2, k - 1)
    sched = np.concatenate([[0.0], np.cumsum(interval)])
    offsets = rng.uniform(0.05, 0.15, n_dev)
    prop = rng.uniform(0.0, 0.015, (k, n_dev))
    truth = 0.2 + sched[:, None] + offsets[None, :] + prop  # arrival times on each device's clock
    n = int((truth.max() + 0.5) * FS)
    streams = []
    for i in range(n_dev):
        gains = np.ones(k)
        if i == 2:
            gains[3] = 0.0  # device 2 missed event 3
        streams.append(render(truth[:, i], n, rng, gains=gains))
    out = chirps.extract_tdoas(streams, template(), sample_rate_hz=FS, interval_s=interval)
    assert np.isnan(out.onsets_s[3, 2]) and np.isfinite(np.delete(out.onsets_s.ravel(), 3 * n_dev + 2)).all()
    exp_s = np.diff(truth, axis=0)
    exp_m = truth - truth[:, :1]
    assert np.isnan(out.tdoa_events_s[2, 2]) and np.isnan(out.tdoa_events_s[3, 2])
    assert np.isnan(out.tdoa_mics_s[3, 2]) and np.all(np.isnan(out.tdoa_mics_s[:, 0]))
    ok_s, ok_m = np.isfinite(out.tdoa_events_s), np.isfinite(out.tdoa_mics_s)
    assert np.max(np.abs(out.tdoa_events_s[ok_s] - exp_s[ok_s])) < 2e-5  # seconds (< 1/3 sample)
    assert np.max(np.abs(out.tdoa_mics_s[ok_m] - exp_m[ok_m])) < 2e-5


def test_audio_to_calibration_end_to_end():
    """Free-field rendering of 8 chirps at 5 asynchronous devices -> TDOAs -> hybrid calibration."""
    rng = np.random.default_rng(4)
    n_dev = 5
    events = np.array([[0, 0, 0], [2, 0, 0], [2, 2, 0], [0, 2, 0], [0, 2, 1.2], [0, 0, 1.2], [2, 0, 1.2],
                       [2, 2, 1.2]], float)
    mics = rng.uniform([-0.5, -0.5, -0.3], [2.5, 2.5, 1.5], (n_dev, 3))
    interval = rng.uniform(0.6, 0.9, len(events) - 1)
    t_emit = np.concatenate([[0.0], np.cumsum(interval)])
    offsets = rng.uniform(0.0, 0.1, n_dev)
    dist = np.linalg.norm(mics[None, :, :] - events[:, None, :], axis=2)
    arrivals = 0.2 + t_emit[:, None] + offsets[None, :] + dist / C  # no drift: same nominal rate
    n = int((arrivals.max() + 0.4) * FS)
    streams = [render(arrivals[:, i], n, rng, gains=1.0 / np.maximum(dist[:, i], 0.3), echo=False,
                      noise_std=0.05) for i in range(n_dev)]
    ext = chirps.extract_tdoas(streams, template(), sample_rate_hz=FS, interval_s=interval)
    odo = np.diff(events, axis=0) + rng.normal(0.0, 0.01, (len(events) - 1, 3))
    problem = ht.HybridTdoaProblem(tdoa_events_s=ext.tdoa_events_s, tdoa_mics_s=ext.tdoa_mics_s, odometry_m=odo,
                                   interval_s=interval, sigma_tdoa_s=2e-5, sigma_odo_m=0.01,
                                   speed_of_sound_m_s=C)
    res = ht.solve(problem, rng=0)
    assert res.verdict == "converged"
    assert ht.mic_frame_error(res, ht.Scene(mics, events))["location_m"] < 0.05


@settings(max_examples=6, deadline=None)
@given(split=st.lists(st.integers(1, 5000), min_size=1, max_size=20), seed=st.integers(0, 1000))
def test_streaming_and_batch_chirp_detectors_agree(split, seed):
    """The streaming ChirpDetector (any block split) and detect_chirps find the same onsets, to 0.05 sample,
    on a one-path scene (the streaming one also looks for an earlier first arrival, which needs an echo)."""
    fs = 16000
    rng = np.random.default_rng(seed)
    tmpl = chirps.linear_chirp(duration_s=0.05, f0_hz=500.0, f1_hz=6000.0, sample_rate_hz=fs)
    n = 5 * fs
    onsets = np.sort(rng.uniform(0.3, 4.5, 4))
    onsets[1:] = onsets[0] + np.cumsum(np.maximum(np.diff(onsets), 0.4))[: 3]
    onsets = onsets[onsets < 4.7] * fs
    f = np.fft.rfftfreq(n, 1 / fs)
    t_spec = np.fft.rfft(tmpl, n)
    x = np.fft.irfft(sum(t_spec * np.exp(-2j * np.pi * f * o / fs) for o in onsets), n)
    x += 0.02 * rng.standard_normal(n)
    batch = chirps.detect_chirps(x, tmpl, sample_rate_hz=fs, min_separation_s=0.3) * fs
    det = chirps.ChirpDetector(tmpl, sample_rate_hz=fs, min_separation_s=0.3)
    found, pos, k = [], 0, 0
    while pos < n:
        step = split[k % len(split)]
        found += det.process(x[pos:pos + step], last=pos + step >= n)
        pos, k = pos + step, k + 1
    streaming = np.array([onset for onset, _ in found])
    assert len(batch) == len(streaming) == len(onsets)
    np.testing.assert_allclose(streaming, batch, atol=0.05)
    np.testing.assert_allclose(streaming, onsets, atol=0.1)
