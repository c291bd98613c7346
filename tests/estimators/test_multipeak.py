"""Noise-aware GCC-PHAT with the N best peaks (estimators.multipeak): synthetic truth, known delays."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

import beamform
from estimators import NoiseAwareGcc, pairs

FS = 16000
N_FFT = 1024
HOP = 256


def _two_sources(seed: int, *, n_devices: int = 5, seconds: float = 5.0, noise_gain: float = 1.0,
                 talker_gain: float = 0.5):
    """A continuous white 'noise' source and an intermittent 'talker' (on/off every 0.1 s), each reaching
    device ``i`` with an integer delay; returns the signals, the per-hop talker activity and both delay sets."""
    rng = np.random.default_rng(seed)
    n = int(seconds * FS)
    pad = 100
    noise = rng.standard_normal(n + 2 * pad)
    talker = rng.standard_normal(n + 2 * pad) * np.repeat(rng.random(n // 1600 + 2) > 0.5, 1600)[:n + 2 * pad]
    d_noise = rng.integers(-20, 21, n_devices)
    d_talk = rng.integers(-20, 21, n_devices)
    d_noise[0] = d_talk[0] = 0
    x = np.stack([noise_gain * noise[pad - dn:pad - dn + n] + talker_gain * talker[pad - dt:pad - dt + n]
                  for dn, dt in zip(d_noise, d_talk)], axis=1).astype(np.float32)
    x += 1e-3 * rng.standard_normal(x.shape).astype(np.float32)
    active = np.array([np.any(talker[pad + k * HOP:pad + (k + 1) * HOP] != 0) for k in range(n // HOP)])
    return x, active, d_noise, d_talk


def _run(x, active, weighting):
    m = x.shape[1]
    stft = beamform.StreamingStft(m, frame_samples=N_FFT, hop_samples=HOP)
    gcc = NoiseAwareGcc(m, n_fft=N_FFT, sample_rate_hz=FS, hop_s=HOP / FS, max_tdoa_s=0.004, weighting=weighting)
    out = []
    for k in range(len(active)):
        spectra = stft.process(x[k * HOP:(k + 1) * HOP])
        out.append(gcc.process(spectra, speech_probability=float(active[k])))
    return gcc, out


def _toa_to_tdoa_samples(d):
    p = pairs(len(d))
    return d[p[:, 0]] - d[p[:, 1]]


def test_plain_phat_follows_the_louder_noise_and_subtraction_finds_the_talker():
    x, active, d_noise, d_talk = _two_sources(1)
    y_noise, y_talk = _toa_to_tdoa_samples(d_noise), _toa_to_tdoa_samples(d_talk)
    frames = [k for k in range(40, len(active)) if active[k] and active[k - 4:k + 1].all()]
    for weighting, expect in (("phat", "noise"), ("subtract", "talker")):
        _, out = _run(x, active, weighting)
        top = np.array([out[k][0][:, 0] * FS for k in frames])
        near_talk = np.mean(np.abs(top - y_talk) < 0.6)
        near_noise = np.mean(np.abs(top - y_noise) < 0.6)
        if expect == "noise":
            assert near_noise > 0.9 and near_talk < 0.05, (near_noise, near_talk)
        else:
            assert near_talk > 0.6 and near_noise < 0.35, (near_noise, near_talk)


def test_both_sources_are_among_the_best_peaks_and_the_noise_spectra_give_the_noise():
    x, active, d_noise, d_talk = _two_sources(2, noise_gain=0.7, talker_gain=0.7)
    y_noise, y_talk = _toa_to_tdoa_samples(d_noise), _toa_to_tdoa_samples(d_talk)
    gcc, out = _run(x, active, "phat")
    frames = [k for k in range(20, len(active)) if active[k] and active[k - 4:k + 1].all()]
    found_t = np.mean([np.any(np.abs(out[k][0] * FS - y_talk[:, None]) < 0.6, axis=1).mean() for k in frames])
    found_n = np.mean([np.any(np.abs(out[k][0] * FS - y_noise[:, None]) < 0.6, axis=1).mean() for k in frames])
    assert found_t > 0.8 and found_n > 0.8
    tdoa, value, corr = gcc.noise_peaks()
    assert np.all(np.abs(tdoa[:, 0] * FS - y_noise) < 0.6)
    assert corr.shape == (gcc.n_pairs, N_FFT) and np.all(value[:, 0] > 0.3)
    # peaks come highest first
    assert np.all(np.diff(out[-1][1], axis=1) <= 0)


def test_swapping_channels_negates_the_delays_and_invalid_channels_give_nothing():
    x, active, _, _ = _two_sources(3, n_devices=3)
    stft = beamform.StreamingStft(3, frame_samples=N_FFT, hop_samples=HOP)
    stft2 = beamform.StreamingStft(3, frame_samples=N_FFT, hop_samples=HOP)
    a = NoiseAwareGcc(3, n_fft=N_FFT, sample_rate_hz=FS, hop_s=HOP / FS, max_tdoa_s=0.004, weighting="phat")
    b = NoiseAwareGcc(3, n_fft=N_FFT, sample_rate_hz=FS, hop_s=HOP / FS, max_tdoa_s=0.004, weighting="phat")
    for k in range(8):
        ta, va = a.process(stft.process(x[k * HOP:(k + 1) * HOP]), speech_probability=1.0)
        tb, vb = b.process(stft2.process(x[k * HOP:(k + 1) * HOP, ::-1].copy()), speech_probability=1.0)
    # reversed channel order [2, 1, 0]: new (0,1) = old (2,1), new (0,2) = old (2,0), new (1,2) = old (1,0)
    np.testing.assert_allclose(tb[:, 0], -ta[::-1, 0], atol=0.05 / FS)
    spectra = stft.process(x[:HOP])
    t, v = a.process(spectra, speech_probability=1.0, valid=np.array([True, False, True]))
    p = pairs(3)
    has1 = (p == 1).any(axis=1)
    assert np.all(v[has1] == 0) and np.all(v[~has1, 0] > 0)
    t, v = a.process(np.where(np.arange(3) == 2, np.nan, spectra), speech_probability=1.0)
    assert np.all(v[(p == 2).any(axis=1)] == 0)


def test_bad_arguments_raise_at_construction():
    with pytest.raises(ValueError, match="n_channels"):
        NoiseAwareGcc(1, n_fft=512, sample_rate_hz=FS, hop_s=0.01, max_tdoa_s=0.01)
    with pytest.raises(ValueError, match="weighting"):
        NoiseAwareGcc(2, n_fft=512, sample_rate_hz=FS, hop_s=0.01, max_tdoa_s=0.01, weighting="ml")
    with pytest.raises(ValueError, match="n_peaks"):
        NoiseAwareGcc(2, n_fft=512, sample_rate_hz=FS, hop_s=0.01, max_tdoa_s=0.01, n_peaks=0)
    for beta in (0.0, 1.5, float("nan")):
        with pytest.raises(ValueError, match="phat_beta"):
            NoiseAwareGcc(2, n_fft=512, sample_rate_hz=FS, hop_s=0.01, max_tdoa_s=0.01, phat_beta=beta)
    gcc = NoiseAwareGcc(2, n_fft=512, sample_rate_hz=FS, hop_s=0.01, max_tdoa_s=0.01)
    with pytest.raises(ValueError, match="spectra.shape"):
        gcc.process(np.zeros((10, 2), np.complex64), speech_probability=0.0)


def test_short_time_smoothing_finds_a_talker_10_db_below_the_noise():
    """A few frames of cross power averaged before the noise removal (``smoothing_time_constant_s``) give a
    far steadier talker peak than one frame; the noise average is corrected for its start from zero, so its
    removal works from the first second on."""
    x, active, d_noise, d_talk = _two_sources(1, talker_gain=0.3)     # talker 10.5 dB below the noise
    y_talk = _toa_to_tdoa_samples(d_talk)
    frames = [k for k in range(40, len(active)) if active[k] and active[k - 4:k + 1].all()]
    found = {}
    for tau in (0.0, 0.1):
        m = x.shape[1]
        stft = beamform.StreamingStft(m, frame_samples=N_FFT, hop_samples=HOP)
        gcc = NoiseAwareGcc(m, n_fft=N_FFT, sample_rate_hz=FS, hop_s=HOP / FS, max_tdoa_s=0.004,
                            smoothing_time_constant_s=tau)
        out = [gcc.process(stft.process(x[k * HOP:(k + 1) * HOP]), speech_probability=float(active[k]))
               for k in range(len(active))]
        top = np.array([out[k][0][:, 0] * FS for k in frames])
        found[tau] = np.mean(np.abs(top - y_talk) < 0.6)
    assert found[0.1] > 0.8 and found[0.1] > found[0.0] + 0.3, found
    with pytest.raises(ValueError, match="smoothing"):
        NoiseAwareGcc(3, n_fft=N_FFT, sample_rate_hz=FS, hop_s=HOP / FS, max_tdoa_s=0.004,
                      smoothing_time_constant_s=-1.0)


def test_a_late_speech_detector_leaks_the_talker_into_the_noise_average_unless_the_update_waits():
    """The speech detector fires 3 hops after each onset (with a hangover at the offsets): without a delay those first hops of the talker
    enter the noise cross-power average (the talker becomes a 'noise source' and is subtracted from itself);
    with the update 0.25 s late, gated by the speech heard since, they do not."""
    x, active, d_noise, d_talk = _two_sources(3, noise_gain=1.0, talker_gain=1.0)
    late = active.copy()
    for k in np.flatnonzero(~active[1:] & active[:-1]) + 1:
        late[k:k + 4] = True    # a hangover covers the frames that still hold the talker's last hop
    for k in np.flatnonzero(active[1:] & ~active[:-1]) + 1:
        late[k:k + 3] = False   # but the onsets are detected 3 hops late
    y_talk = _toa_to_tdoa_samples(d_talk)
    m = x.shape[1]
    leak = {}
    for delay in (0.0, 0.25):
        stft = beamform.StreamingStft(m, frame_samples=N_FFT, hop_samples=HOP)
        gcc = NoiseAwareGcc(m, n_fft=N_FFT, sample_rate_hz=FS, hop_s=HOP / FS, max_tdoa_s=0.004,
                            noise_delay_s=delay)
        for k in range(len(late)):
            gcc.process(stft.process(x[k * HOP:(k + 1) * HOP]), speech_probability=float(late[k]))
        _, _, corr = gcc.noise_peaks()
        lag = np.round(y_talk).astype(int) % N_FFT
        leak[delay] = float(np.mean(corr[np.arange(len(lag)), lag]))   # noise GCC at the talker's delays
    assert leak[0.0] > 0.05, leak   # printed on failure
    assert leak[0.25] < 0.3 * leak[0.0], leak
    with pytest.raises(ValueError, match="noise_delay_s"):
        NoiseAwareGcc(m, n_fft=N_FFT, sample_rate_hz=FS, hop_s=HOP / FS, max_tdoa_s=0.004, noise_delay_s=-1)


def _moving_talker(seed: int, *, noise_gain: float, samples_per_hop: float = 0.5, seconds: float = 4.0):
    """A talker (noise low-passed at 1 kHz, as voiced speech is mostly: a broad correlation peak; on/off every
    0.1 s) whose delay at device 1 grows by ``samples_per_hop`` every hop
    (about 2 ms/s at 0.5: a walking talker) and a stationary white noise source ``noise_gain`` below it, at
    devices 0, 1, 2 (the talker's delays 0, d(t), 5; the noise's 0, -7, 3). Returns the signals, the per-hop
    activity and the talker's pair (0, 1) TDOA per hop, in samples."""
    rng = np.random.default_rng(seed)
    n_hops = int(seconds * FS) // HOP
    n = n_hops * HOP
    pad = 400
    talker = scipy.signal.sosfilt(scipy.signal.butter(4, 1000, fs=FS, output="sos"), rng.standard_normal(n + 2 * pad))
    talker *= np.repeat(rng.random(n // 1600 + 2) > 0.4, 1600)[:n + 2 * pad] / np.std(talker)
    noise = rng.standard_normal(n + 2 * pad)
    x = np.zeros((n, 3), np.float32)
    d1 = np.floor(np.arange(n_hops) * samples_per_hop).astype(int)
    for k in range(n_hops):
        seg = slice(k * HOP, (k + 1) * HOP)
        for dev, dt, dn in ((0, 0, 0), (1, d1[k], -7), (2, 5, 3)):
            idx = np.arange(k * HOP, (k + 1) * HOP) + pad
            x[seg, dev] = talker[idx - dt] + noise_gain * noise[idx - dn]
    x += 1e-4 * rng.standard_normal(x.shape).astype(np.float32)
    active = np.array([np.any(talker[pad + k * HOP:pad + (k + 1) * HOP] != 0) for k in range(n_hops)])
    return x, active, -d1.astype(float)   # pair (0, 1): toa_0 - toa_1


@pytest.mark.parametrize("noise_gain, faster", [(0.01, True), (0.3, False)])
def test_fast_smoothing_follows_a_moving_talker_that_stands_clear_of_the_noise(noise_gain, faster):
    """The short-time average lags a moving talker's peak by about its time constant times the TDOA rate.
    ``fast_smoothing_time_constant_s`` shortens it where the frame's cross power is 15-30 dB above the noise's:
    a talker 40 dB above the noise is followed with less lag; one 10 dB above it gets the slow average,
    exactly as without the option."""
    x, active, tdoa01 = _moving_talker(5, noise_gain=noise_gain)
    lag, peaks = {}, {}
    for fast in (None, 0.02):
        stft = beamform.StreamingStft(3, frame_samples=N_FFT, hop_samples=HOP)
        gcc = NoiseAwareGcc(3, n_fft=N_FFT, sample_rate_hz=FS, hop_s=HOP / FS, max_tdoa_s=0.01,
                            smoothing_time_constant_s=0.1, fast_smoothing_time_constant_s=fast)
        top = []
        for k in range(len(active)):
            # the frame (4 hops) holds the talker if any of its hops does: the noise average takes only noise
            t, _ = gcc.process(stft.process(x[k * HOP:(k + 1) * HOP]),
                               speech_probability=float(active[max(k - 3, 0):k + 1].any()))
            top.append(t[0, 0] * FS)
        # frames of the talker, from 1 s on, where the frame (1024 samples, 4 hops) holds one delay at most
        # two samples old: the frame's centre is 2 hops back
        frames = [k for k in range(int(1.0 * FS / HOP), len(active)) if active[k - 3:k + 1].all()]
        err = np.array([top[k] - tdoa01[k - 2] for k in frames])
        lag[fast] = float(np.median(err))
        peaks[fast] = np.array(top)
    if faster:
        # the talker's delay falls: a lagging peak sits above it
        assert lag[None] > 0.6 and lag[0.02] < 0.4 * lag[None], lag
    else:   # the same peaks once a noise average exists (before it, the fast one) and the start is forgotten
        start = int(1.0 * FS / HOP)
        np.testing.assert_allclose(peaks[0.02][start:], peaks[None][start:], atol=1e-3)
    with pytest.raises(ValueError, match="fast_smoothing"):
        NoiseAwareGcc(3, n_fft=N_FFT, sample_rate_hz=FS, hop_s=HOP / FS, max_tdoa_s=0.004,
                      smoothing_time_constant_s=0.1, fast_smoothing_time_constant_s=0.2)


@pytest.mark.parametrize("beta, near_noise", [(1.0, False), (0.9, False), (0.7, False), (0.7, True)])
def test_the_compiled_frame_is_the_module_docs_formulas(beta, near_noise):
    """Frame by frame against numpy on the module doc's formulas (short-time average with the SNR-adaptive
    constant, noise removal and its update on non-speech frames, PHAT or PHAT-beta (``near_noise``: each
    pair's exponent moved towards 1 by its SNR share), irfft, the top peak)."""
    m, n_fft, hop = 4, 256, 64
    rng = np.random.default_rng(11)
    # near_noise: a talker 20-25 dB above the noise and an exact speech flag, so that the pairs' SNR shares
    # (and with them the exponents) also fall between 0 and 1
    x, active, _, _ = _two_sources(5, n_devices=m, seconds=1.5, noise_gain=0.15 if near_noise else 1.0,
                                   talker_gain=2.0)
    stft = beamform.StreamingStft(m, frame_samples=n_fft, hop_samples=hop)
    gcc = NoiseAwareGcc(m, n_fft=n_fft, sample_rate_hz=FS, hop_s=hop / FS, max_tdoa_s=0.004, n_peaks=1,
                        smoothing_time_constant_s=0.1, fast_smoothing_time_constant_s=0.02, phat_beta=beta,
                        phat_beta_near_noise=near_noise)
    shares = []
    p_idx = pairs(m)
    n_bins = n_fft // 2 + 1
    alpha = 1 - np.exp(-hop / FS / 1.0)
    b_slow, b_fast = 1 - np.exp(-hop / FS / 0.1), 1 - np.exp(-hop / FS / 0.02)
    sm = np.zeros((len(p_idx), n_bins), complex)
    phi = np.zeros((len(p_idx), n_bins), complex)
    weight = 0.0
    max_lag = int(0.004 * FS)
    lags = np.r_[np.arange(-max_lag, 0) + n_fft, np.arange(0, max_lag + 1)]
    for k in range(len(x) // hop):
        X = stft.process(x[k * hop:(k + 1) * hop]).T.astype(complex)
        speech = float(active[k // 4] if k // 4 < len(active) else 0.0) * float(rng.random() < 0.8 or near_noise)
        tdoa, value = gcc.process(np.asfortranarray(X.T.astype(np.complex64)), speech_probability=speech)
        scale = 1.0 / weight if weight > 1e-6 else 0.0
        a = alpha * (1 - speech)
        for p, (i, j) in enumerate(p_idx):
            c = X[i] * X[j].conj()
            noise = scale * np.abs(phi[p]).sum()
            share = 1.0 if noise == 0 else np.clip(
                (10 * np.log10(np.sum(np.abs(X[i]) * np.abs(X[j])) / noise) - 15.0) / 15.0, 0.0, 1.0)
            b = b_slow + share * (b_fast - b_slow)
            shares.append(share)
            beta_pair = beta + share * (1 - beta) if near_noise else beta
            q = round((1.0 - beta_pair) * 512)   # the kernel's exponent: (1 - beta) / 2 to ten binary digits
            beta_kernel = 1.0 - 2.0 * q / 1024
            sm[p] += b * (c - sm[p])
            g = sm[p] - scale * phi[p]
            phi[p] += a * (c - phi[p])
            eps = 1e-6 * np.abs(g).max()
            gw = g / (np.abs(g) ** 2 + eps ** 2) ** (beta_kernel / 2)
            if q > 0:   # the PHAT scale: sum_k |G_k| = n_bins
                gw *= n_bins / np.abs(gw).sum()
            r = np.fft.irfft(gw, n_fft)
            top = lags[np.argmax(r[lags])]
            lag = top - n_fft if top > n_fft // 2 else top
            assert value[p, 0] == pytest.approx(r[top], rel=1e-3, abs=1e-4)
            assert abs(tdoa[p, 0] * FS - lag) <= 0.5 + 1e-9
        weight += a * (1 - weight)
        np.testing.assert_allclose(gcc._smooth, sm, rtol=1e-4, atol=1e-4 * np.abs(sm).max())
        np.testing.assert_allclose(gcc._noise, phi, rtol=1e-4, atol=1e-4 * max(np.abs(phi).max(), 1e-12))
    assert 0 < sum(active) < len(active)
    if near_noise:   # both ends and the ramp between them were taken
        assert min(shares) == 0.0 and max(shares) == 1.0 and any(0.0 < s < 1.0 for s in shares)


@pytest.mark.parametrize("bad", ["nan_imag", "inf_real", "zeros"])
def test_a_channel_with_a_non_finite_or_no_value_gives_its_pairs_nothing(bad):
    m = 3
    rng = np.random.default_rng(2)
    spectra = np.asfortranarray((rng.standard_normal((N_FFT // 2 + 1, m))
                                 + 1j * rng.standard_normal((N_FFT // 2 + 1, m))).astype(np.complex64))
    col = spectra[:, 1]
    if bad == "nan_imag":
        col[7] = complex(1.0, np.nan)
    elif bad == "inf_real":
        col[N_FFT // 2] = complex(np.inf, 0.0)
    else:
        col[:] = 0.0
    gcc = NoiseAwareGcc(m, n_fft=N_FFT, sample_rate_hz=FS, hop_s=HOP / FS, max_tdoa_s=0.004)
    _, value = gcc.process(spectra, speech_probability=1.0)
    has1 = (pairs(m) == 1).any(axis=1)
    assert np.all(value[has1] == 0) and np.all(value[~has1, 0] > 0)
    assert gcc.usable.tolist() == [True, False, True]
    col[:] = 0.0
    col[3] = complex(0.0, 1e-30)   # one tiny value: usable
    gcc.process(spectra, speech_probability=1.0)
    assert gcc.usable.all()


@pytest.mark.parametrize("weighting", ["subtract", "subtract-snr", "phat"])
def test_frames_without_peaks_move_the_averages_exactly_as_frames_with_them(weighting):
    """``peaks=False`` (a tracker that measures every other hop): the frame still moves the short-time and the
    noise averages, so the next measured frame's peaks are the same to the bit as when every frame is searched."""
    x, active, _, _ = _two_sources(3, seconds=2.0)
    m = x.shape[1]
    stft = beamform.StreamingStft(m, frame_samples=N_FFT, hop_samples=HOP)
    every, other = (NoiseAwareGcc(m, n_fft=N_FFT, sample_rate_hz=FS, hop_s=HOP / FS, max_tdoa_s=0.004,
                                  weighting=weighting) for _ in range(2))
    n_compared = 0
    for k in range(len(active)):
        spectra = stft.process(x[k * HOP:(k + 1) * HOP])
        p = float(active[k])
        t_every, v_every = every.process(spectra, speech_probability=p, raw=not active[k])
        if k % 2:
            other.process(spectra, speech_probability=p, raw=not active[k], peaks=False)
            continue
        t_other, v_other = other.process(spectra, speech_probability=p, raw=not active[k])
        np.testing.assert_array_equal(t_other, t_every)
        np.testing.assert_array_equal(v_other, v_every)
        n_compared += 1
    assert n_compared > 50 and every.noise_mature and other.noise_mature
    np.testing.assert_array_equal(other.noise_peaks()[2], every.noise_peaks()[2])


@pytest.mark.parametrize("near_noise", [False, True])
def test_the_engine_option_reaches_the_tracker_gcc_and_a_bad_value_is_one_sentence(tmp_path, near_noise):
    from pathlib import Path

    from stream.config import EngineConfig
    from stream.errors import ConfigError
    from stream.run import run_replay
    with pytest.raises(ConfigError, match="gcc_phat_beta"):
        EngineConfig(gcc_phat_beta=1.5).resolved(16000.0)
    assert EngineConfig().gcc_phat_beta == 1.0   # PHAT by default (docs/tracking-log.md, "Tried 2026-11-30")
    fixture = Path(__file__).resolve().parents[2] / "replay_fixtures" / "two_talkers"
    assert EngineConfig().gcc_phat_beta_near_noise is False
    with pytest.raises(ConfigError, match="gcc_phat_beta_near_noise"):
        EngineConfig(gcc_phat_beta_near_noise="yes").resolved(16000.0)
    outcome = run_replay([fixture], tmp_path / "o", config=EngineConfig(
        gcc_phat_beta=0.9, gcc_phat_beta_near_noise=near_noise, plots=False, progress=False))
    assert outcome.pipeline.gcc.phat_beta == 0.9
    assert outcome.pipeline.gcc.phat_beta_near_noise is near_noise
    enh = outcome.report["metrics"]["enhancement"]
    assert enh["engine"]["si_sdr_db"] > enh["best_single_device"]["si_sdr_db"] + 2.0


@pytest.mark.parametrize("weighting, beta, near_noise, says", [
    ("subtract-snr", 0.9, False, "no effect with"),          # its SNR weight replaces PHAT-beta
    ("phat", 0.9, True, "needs"),                           # no noise cross power removed to measure against
    ("subtract-snr", 0.9, True, "no effect with"),
])
def test_a_weighting_that_would_ignore_the_beta_options_is_refused_in_one_sentence(weighting, beta, near_noise, says):
    from stream.config import EngineConfig
    from stream.errors import ConfigError
    with pytest.raises(ConfigError, match=says) as err:
        EngineConfig(gcc_weighting=weighting, gcc_phat_beta=beta, gcc_phat_beta_near_noise=near_noise).resolved(16000.0)
    assert str(err.value).count(". ") == 0 and "gcc_weighting" in str(err.value)
    with pytest.raises(ValueError, match=says):
        NoiseAwareGcc(4, n_fft=512, sample_rate_hz=16000.0, hop_s=0.008, max_tdoa_s=0.01, weighting=weighting,
                      phat_beta=beta, phat_beta_near_noise=near_noise)
    # the combinations that work as documented are taken
    EngineConfig(gcc_weighting="phat", gcc_phat_beta=0.9).resolved(16000.0)
    EngineConfig(gcc_weighting="subtract-snr").resolved(16000.0)
    EngineConfig(gcc_phat_beta=0.9, gcc_phat_beta_near_noise=True).resolved(16000.0)


def test_the_noise_spectra_moved_with_a_channel_keep_the_removal_on_the_noise():
    """A channel whose signals all arrive 6 samples later (clock drift over seconds, or the aligner moving it):
    the noise average still holds the old delays; moved by :meth:`shift_noise` it removes the noise again, and
    its peaks move by the pairs' change."""
    x, active, d_noise, d_talk = _two_sources(3, seconds=8.0)
    half = (len(active) // 2) * HOP
    later = x.copy()
    later[6:, 2] = x[:-6, 2]
    delta = np.zeros(x.shape[1])
    delta[2] = 6 / FS
    y_talk = _toa_to_tdoa_samples(d_talk + np.round(delta * FS).astype(int))
    shares = {}
    for move in (False, True):
        m = x.shape[1]
        stft = beamform.StreamingStft(m, frame_samples=N_FFT, hop_samples=HOP)
        gcc = NoiseAwareGcc(m, n_fft=N_FFT, sample_rate_hz=FS, hop_s=HOP / FS, max_tdoa_s=0.004,
                            weighting="subtract")
        top = []
        for k in range(len(active)):
            if k * HOP == half:
                before = gcc.noise_peaks()[0][:, 0].copy()
                if move:
                    gcc.shift_noise(delta)
                    after = gcc.noise_peaks()[0][:, 0]
                    assert np.allclose((after - before) * FS, _toa_to_tdoa_samples(delta * FS), atol=0.05)
            src = x if k * HOP < half else later
            # speech all through the second half: the noise average learns nothing new there
            p = float(active[k]) if k * HOP < half else 1.0
            peak_tdoa, _ = gcc.process(stft.process(src[k * HOP:(k + 1) * HOP]), speech_probability=p)
            if k * HOP >= half + N_FFT and active[k]:
                top.append(peak_tdoa[:, 0] * FS)
        shares[move] = float(np.mean(np.abs(np.array(top) - y_talk) < 0.6))
    assert shares[True] > 0.6 and shares[True] > shares[False] + 0.2, shares
    with pytest.raises(ValueError, match="delta_toa_s.shape"):
        gcc.shift_noise(np.zeros(2))


def test_the_noise_average_knows_how_old_its_frames_are():
    """The pipeline turns the noise average by a new drift measurement times the age of its frames: non-speech
    frames keep the age near the average's time constant (plus the frames' wait), speech frames let it grow."""
    m = 3
    rng = np.random.default_rng(5)
    stft = beamform.StreamingStft(m, frame_samples=N_FFT, hop_samples=HOP)
    gcc = NoiseAwareGcc(m, n_fft=N_FFT, sample_rate_hz=FS, hop_s=HOP / FS, max_tdoa_s=0.004,
                        noise_time_constant_s=1.0, noise_delay_s=0.25)
    assert gcc.noise_age_s == 0.0
    hops_s = int(FS / HOP)
    for k in range(8 * hops_s):   # 8 s of non-speech, then 2 s of speech
        spectra = stft.process(rng.standard_normal((HOP, m)).astype(np.float32))
        gcc.process(spectra, speech_probability=0.0 if k < 6 * hops_s else 1.0)
        if k == 6 * hops_s - 1:
            quiet_age = gcc.noise_age_s
    assert 1.0 < quiet_age < 1.5, quiet_age   # the time constant (1 s) and the wait (0.25 s)
    assert abs(gcc.noise_age_s - (quiet_age + 2.0)) < 0.1, gcc.noise_age_s
