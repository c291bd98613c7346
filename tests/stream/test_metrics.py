"""Metric sanity: SI-SDR, SDR/SAR, STOI, alignment, segmental SAR / SSARA, TOA RMSE."""
from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stream.scoring.metrics import (
    align_to_reference,
    sar_db,
    sdr_db,
    segmental_sar_db,
    si_sdr_db,
    speech_segments,
    ssara_db,
    stoi,
    toa_rmse_per_mic_s,
    toa_rmse_s,
)

FS_HZ = 16000


def _signal(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = np.convolve(rng.standard_normal(n + 16), np.hanning(7), mode="same")[:n]
    return x * (0.3 + np.abs(np.sin(np.pi * 3 * np.arange(n) / FS_HZ)))


def _noise_at_snr(x: np.ndarray, snr_db: float, seed: int = 1) -> np.ndarray:
    n = np.random.default_rng(seed).standard_normal(x.size)
    n -= x * np.dot(n, x) / np.dot(x, x)  # orthogonal to x: the SNR is then exactly snr_db
    return n * np.linalg.norm(x) / np.linalg.norm(n) * 10 ** (-snr_db / 20)


def test_si_sdr_of_the_reference_is_large():
    x = _signal(16000)
    assert si_sdr_db(x, x) > 60
    assert si_sdr_db(x + 1e-5 * _noise_at_snr(x, 0.0), x) > 60


@pytest.mark.parametrize("snr_db", [0.0, 10.0, -5.0])
def test_si_sdr_with_additive_noise_equals_the_snr(snr_db):
    x = _signal(16000)
    rng_noise = np.random.default_rng(3).standard_normal(x.size)
    rng_noise *= np.linalg.norm(x) / np.linalg.norm(rng_noise) * 10 ** (-snr_db / 20)
    assert si_sdr_db(x + rng_noise, x) == pytest.approx(snr_db, abs=0.5)  # random noise
    assert si_sdr_db(x + _noise_at_snr(x, snr_db), x) == pytest.approx(snr_db, abs=1e-6)  # orthogonal


@settings(max_examples=30, deadline=None)
@given(scale=st.floats(min_value=1e-3, max_value=1e3), seed=st.integers(0, 1000))
def test_si_sdr_is_scale_invariant(scale, seed):
    x = _signal(4000, seed)
    y = x + _noise_at_snr(x, 5.0, seed + 1)
    assert si_sdr_db(scale * y, x) == pytest.approx(si_sdr_db(y, x), abs=1e-6)
    assert si_sdr_db(-scale * y, x) == pytest.approx(si_sdr_db(y, x), abs=1e-6)  # alpha may be negative


def test_sdr_and_sar_agree_for_one_source_and_allow_a_filter():
    x = _signal(16000)
    noisy = x + _noise_at_snr(x, 10.0)
    assert sar_db(noisy, x) == sdr_db(noisy, x)
    assert sdr_db(noisy, x) == pytest.approx(10.0, abs=0.5)
    filtered = np.convolve(x, [0.2, -0.9, 0.0, 0.0, 0.6], mode="full")[: x.size]  # a short distortion filter
    assert sdr_db(filtered, x) > 40  # forgiven by the 512-tap filter
    assert si_sdr_db(filtered, x) < 5  # not by SI-SDR


def test_stoi_is_one_for_the_reference_and_lower_with_noise():
    x = _signal(3 * FS_HZ)
    assert stoi(x, x, sample_rate_hz=FS_HZ) == pytest.approx(1.0, abs=1e-6)
    noisy = x + _noise_at_snr(x, -5.0)
    assert stoi(noisy, x, sample_rate_hz=FS_HZ) < 0.95
    assert stoi(noisy, x, sample_rate_hz=FS_HZ, extended=True) < stoi(x, x, sample_rate_hz=FS_HZ, extended=True)


@settings(max_examples=30, deadline=None)
@given(lag=st.integers(min_value=-300, max_value=300), extra=st.integers(min_value=-50, max_value=200))
def test_align_to_reference_recovers_a_known_lag(lag, extra):
    x = _signal(4000, seed=5)
    # estimate[n] = x[n - lag] (late by lag), with a different length.
    est = np.zeros(x.size + extra)
    src = np.arange(est.size) - lag
    keep = (src >= 0) & (src < x.size)
    est[keep] = x[src[keep]]
    aligned, found = align_to_reference(est, x, max_lag_samples=400)
    assert found == lag
    assert aligned.shape == x.shape
    overlap = slice(max(0, -lag), min(x.size, est.size - lag))
    np.testing.assert_allclose(aligned[overlap], x[overlap])


def test_silent_inputs_give_nan_and_a_warning(caplog):
    x = _signal(8000)
    with caplog.at_level(logging.WARNING, logger="stream.scoring.metrics"):
        assert math.isnan(si_sdr_db(np.zeros_like(x), x))
        assert math.isnan(si_sdr_db(x, np.zeros_like(x)))
        assert math.isnan(sdr_db(np.zeros_like(x), x))
        assert math.isnan(stoi(x, np.zeros_like(x), sample_rate_hz=FS_HZ))
        assert math.isnan(si_sdr_db(np.full_like(x, np.nan), x))
    assert "silent" in caplog.text and "non-finite" in caplog.text
    assert align_to_reference(np.zeros(100), np.ones(100), max_lag_samples=10)[1] == 0


def test_length_mismatch_is_cropped():
    x = _signal(8000)
    y = x + _noise_at_snr(x, 3.0)
    assert si_sdr_db(np.concatenate([y, np.ones(500)]), x) == pytest.approx(si_sdr_db(y, x))
    assert si_sdr_db(y, np.concatenate([x, np.ones(500)])) == pytest.approx(si_sdr_db(y, x))


def test_speech_segments_label_by_energy():
    seg = FS_HZ // 2
    x = _signal(6 * seg)
    x[2 * seg : 3 * seg] *= 1e-3  # -60 dB: silence
    x[4 * seg : 5 * seg] *= 0.1  # -20 dB: still speech at the -30 dB default
    x = np.concatenate([x, x[: seg // 3]])  # a trailing partial segment is dropped
    labels = speech_segments(x, sample_rate_hz=FS_HZ)
    assert labels.tolist() == [True, True, False, True, True, True]
    assert speech_segments(x, sample_rate_hz=FS_HZ, threshold_db=-10).tolist() == [True, True, False, True, False, True]
    assert not speech_segments(np.zeros(4 * seg), sample_rate_hz=FS_HZ).any()


def test_ssara_equals_sar_when_all_segments_have_the_same_sar():
    seg = FS_HZ // 2
    r = _signal(seg, seed=7)
    e = r + _noise_at_snr(r, 6.0, seed=8)
    ref, est = np.tile(r, 5), np.tile(e, 5)
    starts, sar, is_speech = segmental_sar_db(est, ref, sample_rate_hz=FS_HZ)
    np.testing.assert_allclose(starts, np.arange(5) * 0.5)
    assert is_speech.all()
    np.testing.assert_allclose(sar, sar_db(e, r), atol=1e-6)
    assert ssara_db(est, ref, sample_rate_hz=FS_HZ) == pytest.approx(sar_db(e, r), abs=1e-6)


def test_ssara_is_the_arithmetic_mean_of_linear_sar_over_speech_segments():
    seg = FS_HZ // 2
    r = _signal(4 * seg, seed=9)
    e = r.copy()
    snrs = [0.0, 10.0, 20.0, 5.0]
    for k, snr in enumerate(snrs):
        sl = slice(k * seg, (k + 1) * seg)
        e[sl] += _noise_at_snr(r[sl], snr, seed=10 + k)
    r[3 * seg :] *= 1e-4  # last segment silent: not scored
    e[3 * seg :] = r[3 * seg :] + 1e-5
    _, sar, is_speech = segmental_sar_db(e, r, sample_rate_hz=FS_HZ)
    assert is_speech.tolist() == [True, True, True, False]
    expected = 10 * np.log10(np.mean(10 ** (sar[:3] / 10)))
    assert ssara_db(e, r, sample_rate_hz=FS_HZ) == pytest.approx(expected)
    assert sar[0] < sar[1] < sar[2]


def test_toa_rmse():
    true = np.array([[0.0, 1e-3, -2e-3], [0.0, 1.5e-3, -2e-3]])
    est = true.copy()
    est[:, 1] += 3e-4  # device 1 off by 0.3 ms, device 2 exact
    est[:, 0] = 123.0  # element 0 is ignored
    assert toa_rmse_s(est, true) == pytest.approx(3e-4)  # eq. (18): norm of the error vector
    np.testing.assert_allclose(toa_rmse_per_mic_s(est, true), [0.0, 3e-4, 0.0], atol=1e-15)
    est[:, 2] += 4e-4
    assert toa_rmse_s(est, true) == pytest.approx(5e-4)
    # a single truth row is broadcast: frame 1 then errs by (0.8, 0.4) ms
    assert toa_rmse_s(est, true[0]) == pytest.approx(np.sqrt((3e-4**2 + 4e-4**2 + 8e-4**2 + 4e-4**2) / 2))
    est[0, 1] = np.nan  # frames with a non-finite entry are skipped
    assert toa_rmse_s(est, true) == pytest.approx(5e-4)
    with pytest.raises(ValueError):
        toa_rmse_s(np.zeros((3, 2)), np.zeros((4, 2)))
