"""Online delay-and-sum: identity, steering sign, streaming equals batch, weighting, invalid channels."""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from beamform import DelayAndSum, StreamingIstft, StreamingStft, delay_and_sum

FS_HZ = 16000.0
DATA = Path("/work/shared/data/audio")


def _stream(das: DelayAndSum, x: np.ndarray, toa_s, valid=None) -> np.ndarray:
    hop = das.hop_samples
    n = x.shape[0] // hop
    toa = np.broadcast_to(np.asarray(toa_s, float), (n, x.shape[1]))
    ok = None if valid is None else np.broadcast_to(np.asarray(valid, bool), (n, x.shape[1]))
    return np.concatenate(
        [das.process(x[k * hop : (k + 1) * hop], toa[k], None if ok is None else ok[k]) for k in range(n)]
    )


def _frac_delay(x: np.ndarray, delay_samples: float) -> np.ndarray:
    """x(t - d) by an FFT phase ramp on a zero-padded copy (exact for band-limited x)."""
    n = 2 * len(x)
    X = np.fft.rfft(x, n)
    w = 2 * np.pi * np.arange(len(X)) / n
    return np.fft.irfft(X * np.exp(-1j * w * delay_samples), n)[: len(x)]


def _si_sdr_db(est, ref):
    a = np.dot(est, ref) / np.dot(ref, ref)
    return 10 * np.log10(np.sum((a * ref) ** 2) / np.sum((a * ref - est) ** 2))


def _speechlike(n: int, rng) -> np.ndarray:
    """Low-passed noise with a syllable-rate envelope, unit peak."""
    x = np.convolve(rng.standard_normal(n + 64), np.hanning(9), mode="same")[:n]
    env = 0.2 + np.abs(np.sin(np.pi * 4.0 * np.arange(n) / FS_HZ))
    x = x * env
    return (x / np.abs(x).max()).astype(np.float64)


@pytest.mark.parametrize("weighting", ["equal", "adaptive"])
@pytest.mark.parametrize("frame,hop", [(512, 128), (1024, 256), (4096, 1024)])
def test_identical_channels_zero_toa_return_input_delayed_by_latency(weighting, frame, hop):
    rng = np.random.default_rng(1)
    m = 4
    x = rng.standard_normal(hop * (2 * frame // hop + 12)).astype(np.float32)
    das = DelayAndSum(m, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, weighting=weighting)
    y = _stream(das, np.repeat(x[:, None], m, axis=1), np.zeros(m))
    assert y.dtype == np.float32 and y.shape == x.shape
    assert das.latency_samples == frame - hop
    assert das.latency_s == pytest.approx((frame - hop) / FS_HZ)
    lat = das.latency_samples
    np.testing.assert_allclose(y[lat:], x[: len(x) - lat], atol=2e-5)
    np.testing.assert_allclose(das.channel_weights.sum(), 1.0, rtol=1e-6)


@pytest.mark.parametrize("delay_samples", [23.0, -17.0, 7.5])
def test_steering_with_toa_aligns_a_delayed_channel(delay_samples):
    rng = np.random.default_rng(2)
    frame, hop = 1024, 256
    s = _speechlike(hop * 80, rng)
    x = np.stack([s, _frac_delay(s, delay_samples)], axis=1).astype(np.float32)  # device 1 hears later
    lat = frame - hop
    ref = s[: len(s) - lat]

    def score(toa):
        y = delay_and_sum(x, toa, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, weighting="equal")
        return np.corrcoef(y[lat + frame : len(s)], ref[frame:])[0, 1]

    steered = score([0.0, delay_samples / FS_HZ])
    unsteered = score([0.0, 0.0])
    wrong_sign = score([0.0, -delay_samples / FS_HZ])
    assert steered > 0.995
    assert steered > unsteered + 0.01
    assert steered > wrong_sign + 0.01


@settings(max_examples=20, deadline=None)
@given(
    weighting=st.sampled_from(["equal", "adaptive"]),
    frame_hop=st.sampled_from([(64, 16), (128, 32), (256, 64), (128, 64)]),
    n_blocks=st.integers(min_value=1, max_value=60),
    n_channels=st.integers(min_value=1, max_value=5),
    seed=st.integers(min_value=0, max_value=2**31 - 1),
)
def test_streaming_equals_batch(weighting, frame_hop, n_blocks, n_channels, seed):
    frame, hop = frame_hop
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((n_blocks * hop, n_channels)).astype(np.float32)
    x[:, 1:] += x[:, :1]  # a common component so the adaptive fit has something to find
    toa = rng.uniform(-2e-3, 2e-3, (n_blocks, n_channels))  # time-varying steering
    toa[:, 0] = 0.0
    valid = rng.random((n_blocks, n_channels)) > 0.15
    das = DelayAndSum(n_channels, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, weighting=weighting)
    y_stream = _stream(das, x, toa, valid)
    y_batch = delay_and_sum(
        x, toa, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, valid=valid, weighting=weighting
    )
    np.testing.assert_allclose(y_stream, y_batch, atol=1e-5)
    # Splitting the run (process the first part, then the rest) changes nothing either.
    das.reset()
    cut = int(rng.integers(0, n_blocks + 1))
    first = _stream(das, x[: cut * hop], toa[:cut], valid[:cut]) if cut else np.zeros(0, np.float32)
    rest = _stream(das, x[cut * hop :], toa[cut:], valid[cut:]) if cut < n_blocks else np.zeros(0, np.float32)
    np.testing.assert_array_equal(np.concatenate([first, rest]), y_stream)


def test_process_spectra_matches_process():
    rng = np.random.default_rng(3)
    m, frame, hop = 3, 256, 64
    x = rng.standard_normal((hop * 30, m)).astype(np.float32)
    toa = np.array([0.0, 1e-3, -5e-4])
    a = DelayAndSum(m, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ)
    b = DelayAndSum(m, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ)
    ana = StreamingStft(m, frame_samples=frame, hop_samples=hop)
    for k in range(30):
        blk = x[k * hop : (k + 1) * hop]
        np.testing.assert_array_equal(a.process(blk, toa), b.process_spectra(ana.process(blk), toa))


@pytest.mark.parametrize("weighting", ["equal", "adaptive"])
def test_nan_and_invalid_channels_are_excluded(weighting):
    rng = np.random.default_rng(4)
    m, frame, hop = 4, 256, 64
    s = rng.standard_normal(hop * 40).astype(np.float32)
    x = np.repeat(s[:, None], m, axis=1)
    x[:, 2] = np.nan  # a dead device
    x[hop * 5 : hop * 7, 3] = np.inf  # a glitch
    das = DelayAndSum(m, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, weighting=weighting)
    y = _stream(das, x, np.zeros(m))
    assert np.all(np.isfinite(y))
    lat = das.latency_samples
    np.testing.assert_allclose(y[lat:], s[: len(s) - lat], atol=2e-5)
    assert das.channel_weights[2] == 0.0
    np.testing.assert_allclose(das.channel_weights.sum(), 1.0, rtol=1e-6)

    # Flagged invalid: weight 0, the rest renormalised; with none valid the output is silent.
    das.reset()
    blk = rng.standard_normal((hop, m)).astype(np.float32)
    for _ in range(6):
        das.process(blk, np.zeros(m), valid=np.array([True, False, True, True]))
    assert das.channel_weights[1] == 0.0
    np.testing.assert_allclose(das.channel_weights.sum(), 1.0, rtol=1e-6)
    for _ in range(6):
        out = das.process(blk, np.zeros(m), valid=np.zeros(m, bool))
    np.testing.assert_array_equal(das.channel_weights, 0.0)
    np.testing.assert_array_equal(out, 0.0)


def test_nan_toa_excludes_that_device():
    m, frame, hop = 3, 128, 32
    rng = np.random.default_rng(5)
    s = rng.standard_normal(hop * 20).astype(np.float32)
    x = np.stack([s, s, rng.standard_normal(len(s)).astype(np.float32)], axis=1)
    das = DelayAndSum(m, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, weighting="equal")
    y = _stream(das, x, [0.0, 0.0, np.nan])
    lat = das.latency_samples
    np.testing.assert_allclose(y[lat:], s[: len(s) - lat], atol=2e-5)
    np.testing.assert_allclose(das.channel_weights, [0.5, 0.5, 0.0])


def test_adaptive_weights_follow_channel_snr_and_beat_the_best_channel():
    rng = np.random.default_rng(6)
    frame, hop = 512, 128
    s = _speechlike(int(4 * FS_HZ), rng)
    snr_db = np.array([10.0, 0.0, -5.0, -10.0, 3.0])
    p = np.mean(s**2)
    x = np.stack([s + rng.standard_normal(len(s)) * np.sqrt(p / 10 ** (d / 10)) for d in snr_db], axis=1)
    x = x.astype(np.float32)
    lat = frame - hop
    out = {}
    for weighting in ("equal", "adaptive"):
        das = DelayAndSum(len(snr_db), frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, weighting=weighting)
        y = _stream(das, x, np.zeros(len(snr_db)))
        out[weighting] = _si_sdr_db(y[lat + frame :], s[frame : len(y) - lat])
        if weighting == "adaptive":
            w = das.channel_weights
            assert np.all(w >= 0) and w.sum() == pytest.approx(1.0, rel=1e-6)
            assert list(np.argsort(-w)) == list(np.argsort(-snr_db))  # MRC ranks by SNR
    best_single = max(_si_sdr_db(x[:, i], s) for i in range(len(snr_db)))
    # MRC: output SNR ~ sum of channel SNRs = 10 log10(10 + 1 + .32 + .1 + 2) = 11.3 dB.
    assert out["adaptive"] > best_single + 0.8
    assert out["adaptive"] > out["equal"] + 3.0


@settings(max_examples=15, deadline=None)
@given(
    n_channels=st.integers(min_value=1, max_value=6),
    seed=st.integers(min_value=0, max_value=2**31 - 1),
)
def test_adaptive_weights_are_a_convex_combination(n_channels, seed):
    rng = np.random.default_rng(seed)
    hop = 32
    das = DelayAndSum(n_channels, frame_samples=128, hop_samples=hop, sample_rate_hz=FS_HZ)
    gains = rng.uniform(0.0, 2.0, n_channels)
    for _ in range(20):
        blk = rng.standard_normal((hop, 1)) * gains + 0.3 * rng.standard_normal((hop, n_channels))
        das.process(blk.astype(np.float32), rng.uniform(-1e-3, 1e-3, n_channels))
        w = das.channel_weights
        assert w.shape == (n_channels,) and np.all(np.isfinite(w)) and np.all(w >= 0)
        assert w.sum() == pytest.approx(1.0, rel=1e-5)


def test_construction_validation():
    kw = dict(frame_samples=512, hop_samples=128, sample_rate_hz=FS_HZ)
    with pytest.raises(ValueError, match="weighting"):
        DelayAndSum(2, weighting="mvdr", **kw)
    with pytest.raises(ValueError, match="sample_rate_hz"):
        DelayAndSum(2, frame_samples=512, hop_samples=128, sample_rate_hz=0.0)
    with pytest.raises(ValueError, match="hop_samples"):
        DelayAndSum(2, frame_samples=512, hop_samples=1024, sample_rate_hz=FS_HZ)
    with pytest.raises(ValueError, match="weight_time_constant_s"):
        DelayAndSum(2, weight_time_constant_s=-1.0, **kw)
    with pytest.raises(ValueError, match="weight_exponent"):
        DelayAndSum(2, weight_exponent=2.0, **kw)
    das = DelayAndSum(2, **kw)
    with pytest.raises(ValueError, match="shape"):
        das.process_spectra(np.zeros((100, 2), np.complex64), np.zeros(2))
    with pytest.raises(ValueError, match="shape"):
        das.process_spectra(np.zeros((2, 257), np.complex64), np.zeros(2))  # channel-major: transposed
    with pytest.raises(ValueError, match="toa.shape"):
        das.process_spectra(np.zeros((257, 2), np.complex64), np.zeros(3))
    with pytest.raises(ValueError, match="valid"):
        das.process_spectra(np.zeros((257, 2), np.complex64), np.zeros(2), valid=np.ones(3, bool))
    with pytest.raises(ValueError, match="toa.shape"):
        das.beamform_spectra(np.zeros((257, 2), np.complex64), np.zeros((2, 1)))
    # the kernels' own layout (channel-major transpose, float64, bool) is shape-checked inside them
    with pytest.raises(ValueError, match="spectra.shape"):
        das.process_spectra(np.zeros((2, 100), np.complex64).T, np.zeros(2))
    with pytest.raises(ValueError, match="toa.shape"):
        das.process_spectra(np.zeros((2, 257), np.complex64).T, np.zeros(3))
    with pytest.raises(ValueError, match="valid.shape"):
        das.beamform_spectra(np.zeros((2, 257), np.complex64).T, np.zeros(2), valid=np.ones(1, bool))
    # rejected calls changed nothing: the next output equals a fresh beamformer's
    X = np.ones((2, 257), np.complex64).T
    np.testing.assert_array_equal(das.process_spectra(X, np.zeros(2)),
                                  DelayAndSum(2, **kw).process_spectra(X, np.zeros(2)))


def _reverberant_scene():
    """6 devices 0.5-3 m from a talker in a 6 x 5 x 3 m room (RT60 0.4 s) with dish-washing noise."""
    pra = pytest.importorskip("pyroomacoustics")
    sf = pytest.importorskip("soundfile")
    speech_path = DATA / "cmu-arctic-16k" / "cmu_arctic_us_aew_a0001.wav"
    noise_path = DATA / "speechcommands-noise" / "doing_the_dishes.wav"
    if not (speech_path.exists() and noise_path.exists()):
        pytest.skip("shared audio data not available")
    speech, fs = sf.read(speech_path)
    noise, fs_n = sf.read(noise_path)
    assert fs == fs_n == FS_HZ
    noise = noise[: len(speech)] if noise.ndim == 1 else noise[: len(speech), 0]
    room_dim = [6.0, 5.0, 3.0]
    e_abs, max_order = pra.inverse_sabine(0.4, room_dim)
    room = pra.ShoeBox(room_dim, fs=fs, materials=pra.Material(e_abs), max_order=max_order)
    src = np.array([2.4, 2.5, 1.5])
    rng = np.random.default_rng(0)
    dist = np.array([2.0, 1.5, 3.0, 2.5, 0.5, 1.0])
    az = rng.uniform(0, 2 * np.pi, len(dist))
    mics = src + np.stack([dist * np.cos(az), dist * np.sin(az), np.zeros_like(dist)], axis=1)
    mics[:, :2] = np.clip(mics[:, :2], 0.2, np.array(room_dim[:2]) - 0.2)
    mics[:, 2] = rng.uniform(0.8, 1.3, len(dist))
    room.add_source(src, signal=speech)
    room.add_source([5.4, 0.6, 1.0], signal=noise)
    room.add_microphone_array(mics.T)
    premix = room.simulate(return_premix=True)
    n = len(speech)
    sp, nz = premix[0][:, :n], premix[1][:, :n]
    nz *= np.sqrt(np.mean(sp**2) / np.mean(nz**2))  # 0 dB average noise level
    x = (sp + nz).T.astype(np.float32)
    d = np.linalg.norm(mics - src, axis=1)
    toa_true_s = (d - d[0]) / 343.0
    # pyroomacoustics RIRs carry a fixed frac_delay_length // 2 sample delay (cancels in the TOA).
    offset = pra.constants.get("frac_delay_length") // 2
    refs = np.stack([_frac_delay(speech, di / 343.0 * fs + offset) for di in d], axis=1)
    return x, toa_true_s, refs


def test_adaptive_beats_best_device_on_a_reverberant_ad_hoc_scene():
    x, toa, refs = _reverberant_scene()
    frame, hop = 1024, 256
    lat = frame - hop
    scores = {}
    for weighting in ("equal", "adaptive"):
        y = delay_and_sum(x, toa, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, weighting=weighting)
        scores[weighting] = _si_sdr_db(y[lat:], refs[: len(y) - lat, 0])
    singles = [_si_sdr_db(x[:, i], refs[:, i]) for i in range(x.shape[1])]
    assert scores["adaptive"] >= max(singles) + 0.3, (scores, singles)
    assert scores["adaptive"] >= scores["equal"] + 0.3, (scores, singles)


class _ReferenceDas:
    """Plain numpy float64 restatement of DelayAndSum.beamform_spectra (eqs. 7-8 and the adaptive
    weights: exact exp(i omega toa) steering, complex128 sums, float64 statistics), time-major,
    without the compiled kernel's recurrences, float32 products or buffers, to check those against."""

    def __init__(self, das: DelayAndSum) -> None:
        self.das = das
        m = das.n_channels
        self.cov = np.zeros((m, m))
        self.mass = 0.0
        self.n_updates = 0
        self.gain = np.zeros(m)

    def beamform(self, X: np.ndarray, toa: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        das = self.das
        ok = np.isfinite(X).all(axis=0) & valid & np.isfinite(toa)
        toa = np.where(np.isfinite(toa), toa, 0.0)
        X = np.where(ok, X, 0)
        Z = X * np.exp(1j * das.omega_rad_s[:, None] * toa[None, :])  # complex128
        m = das.n_channels
        okf = ok.astype(float)
        n_ok = int(ok.sum())
        if das.weighting == "equal":
            w = okf / n_ok if n_ok else np.zeros(m)
        else:
            Zb = Z[das._stats_bins]
            F = (Zb.conj().T @ Zb).real
            self.mass = das._forget * self.mass + 1.0
            rate = 1.0 / self.mass
            both = ok[:, None] & ok[None, :]
            self.cov[both] += rate * (F[both] - self.cov[both])
            C, d = self.cov, self.cov.diagonal().copy()
            d_max = (d * okf).max() if n_ok else 0.0
            w = np.zeros(m)
            if d_max > 0:
                tiny = 1e-12 * d_max
                scale = np.sqrt(d)
                g = self.gain if self.gain.max() > 0 else 0.5 * scale
                self.n_updates += 1
                for _ in range(das._startup_iter if self.n_updates <= das._startup_frames else 1):
                    gm = g * okf
                    g2 = gm * gm
                    g_new = np.maximum(C @ gm - d * gm, 0.0) / (g2.sum() - g2 + tiny)
                    g = np.minimum(np.maximum(np.sqrt(g * g_new), 1e-6 * np.sqrt(d_max)), scale)
                self.gain = np.where(ok, g, self.gain)
                noise = np.maximum(d - g * g, d * das._inv_snr_max)
                w = g * okf / (noise + tiny)
                w /= w.sum()
        return Z @ w, w


@pytest.mark.parametrize("weighting", ["equal", "adaptive"])
@pytest.mark.parametrize("n_channels,frame,hop", [(3, 256, 64), (8, 512, 128), (6, 4096, 1024)])
@pytest.mark.parametrize("toa_max_s", [2e-3, 0.5])
def test_beamform_matches_reference_to_float32_precision(weighting, n_channels, frame, hop, toa_max_s):
    # Eqs. 7-8 (steering recurrence, validity, equal and adaptive weights, sum) against the float64
    # restatement, with small TOAs and with phases of up to ~1e4 rad (0.5 s).
    rng = np.random.default_rng(n_channels + frame)
    n_blocks = 40
    s = rng.standard_normal((n_blocks + 4) * hop)
    x = np.stack([_frac_delay(s, d) for d in rng.uniform(-20, 20, n_channels)], axis=1)
    x = (x + 0.3 * rng.standard_normal(x.shape)).astype(np.float32)
    toa = rng.uniform(-toa_max_s, toa_max_s, (n_blocks, n_channels))
    toa[:, 0] = 0.0
    toa[5, 1] = np.nan  # a device without a TOA for one frame
    valid = rng.random((n_blocks, n_channels)) > 0.1
    das = DelayAndSum(n_channels, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, weighting=weighting)
    ref = _ReferenceDas(das)
    ana = StreamingStft(n_channels, frame_samples=frame, hop_samples=hop)
    for k in range(n_blocks):
        X = ana.process(x[k * hop : (k + 1) * hop])
        Y = das.beamform_spectra(X, toa[k], valid[k])
        Y_ref, w_ref = ref.beamform(X.astype(np.complex128), toa[k], valid[k])
        # The kernel sums the band cross-power in float32 (as the BLAS sgemm before it) and forms
        # the steering and Z = a X in float32: measured here up to 6e-5 relative on the adaptive
        # weights (their fit amplifies the 1e-7 of the statistics; the numpy code before the
        # kernel: 9e-5) and 3e-6 of the peak on Y (equal weights: 2e-7).
        np.testing.assert_allclose(das.channel_weights, w_ref, rtol=5e-5, atol=1e-7)
        np.testing.assert_allclose(Y, Y_ref, rtol=0, atol=1e-5 * np.abs(Y_ref).max())


@pytest.mark.parametrize("frame,sample_rate_hz", [(16, 16_000.0), (100, 16_000.0), (512, 16_000.0),
                                                 (4096, 16_000.0), (4096, 48_000.0)])
def test_steering_is_exp_of_i_omega_toa_over_all_bins_for_large_toas(frame, sample_rate_hz):
    # eq. (7) through the public path: a unit spectrum on one valid channel gives Y = a_i(omega)
    # (weight 1). TOAs up to +-0.5 s: at 48 kHz / 4096 the last bin turns by 7.5e4 rad, where a
    # recurrence that was not reduced modulo 2 pi or not run in float64 would drift.
    toa = np.array([0.0, 0.5, -0.5, 0.4999999, -0.123456789, 0.012, -3.3e-5, 1.0 / sample_rate_hz])
    toa = np.concatenate([toa, np.random.default_rng(frame).uniform(-0.5, 0.5, 8)])
    m = len(toa)
    das = DelayAndSum(m, frame_samples=frame, hop_samples=frame // 4, sample_rate_hz=sample_rate_hz, weighting="equal")
    X = np.ones((das.n_bins, m), np.complex64)
    for i in range(m):
        Y = das.beamform_spectra(X, toa, np.arange(m) == i)
        exact = np.exp(1j * das.omega_rad_s * toa[i])  # complex128 reference
        assert Y.shape == (das.n_bins,) and Y.dtype == np.complex64
        # float32 output: ~6e-8 from the rounding of Y, ~2e-7 from the float32 product c_j f_k.
        assert np.abs(Y - exact).max() < 1e-6, (i, toa[i], np.abs(Y - exact).max())


def _reference_synthesis(Y: np.ndarray, frame: int, hop: int, window: np.ndarray) -> np.ndarray:
    """float64 numpy irfft of each frame, times the dual window, overlap-added; the first hop of
    the accumulator after frame k is output hop k (StreamingIstft's convention)."""
    w = window.astype(np.float64)
    n_folds = -(-frame // hop)
    w2 = np.zeros(n_folds * hop)
    w2[:frame] = w**2
    ws = w / np.tile(w2.reshape(n_folds, hop).sum(axis=0), n_folds)[:frame]
    acc = np.zeros(len(Y) * hop + frame)
    for k, spectrum in enumerate(Y):
        acc[k * hop : k * hop + frame] += np.fft.irfft(spectrum, frame) * ws
    return acc[: len(Y) * hop]


@pytest.mark.parametrize("weighting", ["equal", "adaptive"])
@pytest.mark.parametrize("n_channels,frame,hop", [(4, 512, 128), (5, 100, 25), (3, 64, 32), (8, 4096, 1024)])
def test_process_spectra_matches_numpy_reference_with_synthesis(weighting, n_channels, frame, hop):
    # The whole compiled hop (eqs. 7-8, irfft, overlap-add) against the float64 restatement of
    # eqs. 7-8 followed by a float64 numpy irfft and overlap-add.
    rng = np.random.default_rng(frame + n_channels)
    n_blocks = 30
    s = rng.standard_normal((n_blocks + 2) * hop)
    x = np.stack([_frac_delay(s, d) for d in rng.uniform(-10, 10, n_channels)], axis=1)
    x = (x + 0.2 * rng.standard_normal(x.shape)).astype(np.float32)
    x[hop * 7 : hop * 8, 1] = np.nan  # a glitch on one device
    toa = rng.uniform(-3e-3, 3e-3, (n_blocks, n_channels))
    valid = rng.random((n_blocks, n_channels)) > 0.1
    das = DelayAndSum(n_channels, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, weighting=weighting)
    ref = _ReferenceDas(das)
    ana = StreamingStft(n_channels, frame_samples=frame, hop_samples=hop)
    out, Y_ref = [], []
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # non-finite input is flagged, never warned about
        for k in range(n_blocks):
            X = ana.process(x[k * hop : (k + 1) * hop])
            out.append(das.process_spectra(X, toa[k], valid[k]))
            Y_ref.append(ref.beamform(X.astype(np.complex128), toa[k], valid[k])[0])
    y = np.concatenate(out)
    y_ref = _reference_synthesis(np.array(Y_ref), frame, hop, das.analysis_window)
    assert y.dtype == np.float32 and np.all(np.isfinite(y))
    # float32 spectra, weights and FFT: the equal-weight sum is within 2e-7 of the peak per bin
    # (see test_beamform_matches_reference_to_float32_precision); the irfft and the overlap-add
    # of up to frame / hop frames add a few float32 roundings.
    np.testing.assert_allclose(y, y_ref, rtol=0, atol=2e-5 * np.abs(y_ref).max())


def _twin_beamformers(seed: int, m: int = 4, frame: int = 256, hop: int = 64, n_frames: int = 20):
    """Two identical DelayAndSum instances and ``n_frames`` (spectra, toa_s) inputs from a StreamingStft
    (channel-major spectra of white noise, TOAs within +-1 ms)."""
    rng = np.random.default_rng(seed)
    a = DelayAndSum(m, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ)
    b = DelayAndSum(m, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ)
    ana = StreamingStft(m, frame_samples=frame, hop_samples=hop)
    frames = [(ana.process(rng.standard_normal((hop, m)).astype(np.float32)), rng.uniform(-1e-3, 1e-3, m))
              for _ in range(n_frames)]
    return a, b, frames


def test_process_spectra_is_beamform_spectra_then_synthesis():
    a, b, frames = _twin_beamformers(12)
    syn = StreamingIstft(frame_samples=a.frame_samples, hop_samples=a.hop_samples,
                         analysis_window=a.analysis_window)
    for X, toa in frames:
        np.testing.assert_array_equal(a.process_spectra(X, toa), syn.process(b.beamform_spectra(X, toa)))
        np.testing.assert_array_equal(a.channel_weights, b.channel_weights)


def test_input_types_and_layouts_do_not_change_the_output():
    # complex128 / strided / read-only spectra, float32 or list TOA, int mask or read-only arrays
    # are converted once; the results equal the canonical inputs' (same float32 values).
    rng = np.random.default_rng(13)
    m, frame, hop = 3, 128, 32
    dases = [DelayAndSum(m, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ) for _ in range(2)]
    ana = StreamingStft(m, frame_samples=frame, hop_samples=hop)
    for k in range(12):
        X = ana.process(rng.standard_normal((hop, m)).astype(np.float32))
        toa = rng.uniform(-1e-3, 1e-3, m).astype(np.float32).astype(np.float64)
        valid = np.array([True, k % 3 != 0, True])
        ro_X = X.copy()
        ro_X.flags.writeable = False
        ro_valid = valid.copy()
        ro_valid.flags.writeable = False
        odd = [X.astype(np.complex128), np.asfortranarray(X), ro_X][k % 3]
        odd_toa = [toa.astype(np.float32), list(toa), toa.copy()][k % 3]
        odd_valid = [valid.astype(int), list(valid), ro_valid][k % 3]
        np.testing.assert_array_equal(dases[0].process_spectra(X, toa, valid),
                                      dases[1].process_spectra(odd, odd_toa, odd_valid))
        np.testing.assert_array_equal(dases[0].channel_weights, dases[1].channel_weights)


def test_channel_weights_are_new_float32_arrays():
    das = DelayAndSum(3, frame_samples=64, hop_samples=16, sample_rate_hz=FS_HZ, weighting="equal")
    np.testing.assert_array_equal(das.channel_weights, np.float32(1) / np.float32(3))
    das.process(np.ones((16, 3), np.float32), np.zeros(3), valid=np.array([True, True, False]))
    first = das.channel_weights
    das.process(np.ones((16, 3), np.float32), np.zeros(3))
    second = das.channel_weights
    assert first.dtype == second.dtype == np.float32
    np.testing.assert_array_equal(first, [0.5, 0.5, 0.0])  # a kept array does not change later
    np.testing.assert_array_equal(second, np.float32(1) / np.float32(3))
    assert not np.shares_memory(first, second)


def test_overflowing_toa_excludes_that_device():
    # toa * omega overflows to inf: the device cannot be steered and must not bring NaN in.
    m, frame, hop = 3, 64, 16
    s = np.random.default_rng(14).standard_normal(hop * 12).astype(np.float32)
    das = DelayAndSum(m, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, weighting="adaptive")
    y = _stream(das, np.repeat(s[:, None], m, axis=1), [0.0, 1e308, 0.0])
    lat = das.latency_samples
    np.testing.assert_allclose(y[lat:], s[: len(s) - lat], atol=2e-5)
    assert das.channel_weights[1] == 0.0


def test_spectra_layout_does_not_change_the_output():
    a, b, frames = _twin_beamformers(11)
    for X, toa in frames:  # X channel-major
        np.testing.assert_array_equal(a.process_spectra(X, toa), b.process_spectra(np.ascontiguousarray(X), toa))


def _stream_quiet(das: DelayAndSum, x: np.ndarray, quiet: np.ndarray) -> np.ndarray:
    """``_stream`` at zero TOA, marking each hop a pause or not (as the pipeline does from its speech detector)."""
    hop = das.hop_samples
    stft = StreamingStft(x.shape[1], frame_samples=das.frame_samples, hop_samples=hop)
    out = []
    for k in range(x.shape[0] // hop):
        spectra = stft.process(x[k * hop : (k + 1) * hop])
        das.note_frame(spectra, pause=bool(quiet[k]))
        out.append(das.process_spectra(spectra, np.zeros(x.shape[1])))
    return np.concatenate(out)


def test_level_weights_undo_the_devices_gains_and_learn_only_in_pauses():
    # one talker heard alike by 4 devices, each with its own acoustic noise of one level, recorded at gains 12 dB
    # apart: equal weights let the loud device own the beam (its noise too); "level" brings every device to one
    # noise floor, which is delay-and-sum on equal-gain devices
    rng = np.random.default_rng(11)
    frame, hop = 512, 128
    n = int(6 * FS_HZ)
    talk = _speechlike(n, rng)
    talk[: n // 3] = 0.0                                  # 2 s of noise first: the pause the floors learn from
    gains = np.array([1.0, 0.25, 2.0, 1.0])
    noise = 0.1 * rng.standard_normal((n, 4))
    x = ((talk[:, None] + noise) * gains).astype(np.float32)
    quiet = np.arange(n // hop) * hop < n // 3
    lat = frame - hop
    out, weights = {}, {}
    for weighting in ("equal", "level"):
        das = DelayAndSum(4, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, weighting=weighting)
        assert das.weighting == weighting
        y = _stream_quiet(das, x, quiet)
        s0 = n // 3 + frame
        out[weighting] = _si_sdr_db(y[s0 + lat :], talk[s0 : len(y) - lat])
        weights[weighting] = das.channel_weights
    np.testing.assert_allclose(weights["level"], (1 / gains) / np.sum(1 / gains), rtol=0.02)
    equal_gain = (talk[:, None] + noise).mean(axis=1)     # the bound: the devices at one gain, averaged
    bound = _si_sdr_db(equal_gain[n // 3 + frame :], talk[n // 3 + frame :])
    assert out["level"] > out["equal"] + 1.0   # the gains cost equal weights 1.3 dB: (sum g)^2 / (M sum g^2) = 0.74
    assert out["level"] == pytest.approx(bound, abs=0.3)
    # the talker's frames (not quiet) leave the floors alone, however loud
    das = DelayAndSum(4, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, weighting="level")
    _stream_quiet(das, x[: n // 3], quiet[: n // 3 // hop])
    before = das.channel_weights
    loud = (np.stack([talk * 40, talk, talk, talk], axis=1)[n // 3 :] * gains).astype(np.float32)
    _stream_quiet(das, loud, np.zeros(len(loud) // hop, bool))
    np.testing.assert_array_equal(das.channel_weights, before)


def test_level_weights_are_held_within_their_ratio_and_survive_silence():
    frame, hop = 256, 64
    rng = np.random.default_rng(12)
    n = hop * 200
    x = rng.standard_normal((n, 3)).astype(np.float32) * np.array([1.0, 1e-4, 1.0], np.float32)
    x[:, 2] = 0.0                                             # digital silence: no floor, no division by zero
    das = DelayAndSum(3, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, weighting="level",
                      level_max_ratio=4.0)
    _stream_quiet(das, x, np.ones(n // hop, bool))
    w = das.channel_weights
    assert np.all(np.isfinite(w)) and w.sum() == pytest.approx(1.0, rel=1e-6)
    # the median of the two floors is their middle, 40 dB from each: both held to 4 times it; the silent channel
    # (no floor yet) counts as the median
    np.testing.assert_allclose(w, np.array([1 / 4, 4, 1]) / 5.25, rtol=1e-5)
    x[:, 2] = rng.standard_normal(n) * 1.0
    _stream_quiet(das, x, np.ones(n // hop, bool))
    w = das.channel_weights
    assert w[1] / np.median(w) == pytest.approx(4.0, rel=1e-5)   # 80 dB quieter, but held to 4 times the median
    assert w[0] == pytest.approx(w[2], rel=0.05)
    with pytest.raises(ValueError, match="level_max_ratio"):
        DelayAndSum(2, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, level_max_ratio=0.5)
    with pytest.raises(ValueError, match="level_min_pause_s"):   # a floor that could never count
        DelayAndSum(2, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, level_min_pause_s=3.0)


def test_a_floor_counts_after_half_a_second_of_pauses_and_quiet_electronics_are_not_boosted():
    frame, hop = 512, 128
    rng = np.random.default_rng(13)
    n = int(4 * FS_HZ)
    talk = _speechlike(n, rng)
    # devices 0-2: one talker and one room noise at gains 1, 1, 0.5 (device 2's floor 6 dB low: boosted); device 3
    # hears the talker 40 dB down over its own electronics 30 dB below the room: the lowest floor, and 10 dB less SNR
    room = 0.05 * rng.standard_normal((n, 4))
    gains = np.array([1.0, 1.0, 0.5, 0.01])
    x = (talk[:, None] + room) * gains
    x[:, 3] = 0.01 * talk + 0.0016 * rng.standard_normal(n)
    x = x.astype(np.float32)
    n_pause = int(0.25 * FS_HZ) // hop
    das = DelayAndSum(4, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, weighting="level")
    pauses = x.copy()
    pauses[:, :3] -= talk[:, None] * gains[None, :3]
    pauses[:, 3] -= 0.01 * talk
    _stream_quiet(das, pauses[: n_pause * hop], np.ones(n_pause, bool))
    np.testing.assert_array_equal(das.channel_weights, np.float32(0.25))   # 0.25 s of pauses: no floor counts yet
    _stream_quiet(das, pauses[n_pause * hop :], np.ones(len(pauses) // hop - n_pause, bool))
    _stream_quiet(das, x, np.zeros(n // hop, bool))                          # the talker: speech levels, SNRs
    w = das.channel_weights
    assert w[2] / w[0] == pytest.approx(2.0, rel=0.05)   # a lower gain, the same SNR: its floor brought up
    assert w[1] / w[0] == pytest.approx(1.0, rel=0.05)
    # a floor 30 dB low, but 10 dB less SNR: held at the median floor's weight (halfway between devices 1 and 2)
    assert w[3] == pytest.approx(np.sqrt(w[1] * w[2]), rel=1e-4)


def test_level_snr_exponent_gives_maximal_ratio_weights_on_the_floors():
    # three devices with one noise floor; the talker 6 dB louder at device 0 and 6 dB quieter at device 2 than at
    # device 1 (device 0 sits next to the talker). Exponent 1: weights ~ amplitude SNR (maximal-ratio combining on
    # devices of one floor), and the output beats "level" alone; exponent 0 is "level" exactly
    rng = np.random.default_rng(14)
    frame, hop = 512, 128
    n = int(6 * FS_HZ)
    talk = rng.standard_normal(n) * 0.1                  # stationary, so a frame's power is the talker's power
    talk[: n // 3] = 0.0
    amp = np.array([2.0, 1.0, 0.5])
    noise = 0.05 * rng.standard_normal((n, 3))
    x = (talk[:, None] * amp + noise).astype(np.float32)
    quiet = np.arange(n // hop) * hop < n // 3
    lat = frame - hop
    s0 = n // 3 + frame
    out, w = {}, {}
    for exponent in (0.0, 1.0):
        das = DelayAndSum(3, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, weighting="level",
                          level_snr_exponent=exponent)
        y = _stream_quiet(das, x, quiet)
        out[exponent] = _si_sdr_db(y[s0 + lat :], talk[s0 : len(y) - lat])
        w[exponent] = das.channel_weights
    np.testing.assert_allclose(w[0.0], 1 / 3, rtol=0.02)        # one floor: "level" is equal weighting
    snr = amp ** 2 * 0.1 ** 2 / 0.05 ** 2                       # 16, 4, 1
    np.testing.assert_allclose(w[1.0] / w[1.0][1], np.sqrt(snr / snr[1]), rtol=0.05)
    bound = 10 * np.log10(np.sum(snr))                          # MRC: the output SNR is the sum of the channels'
    assert out[1.0] == pytest.approx(bound, abs=0.3)
    assert out[1.0] > out[0.0] + 1.0
    with pytest.raises(ValueError, match="level_snr_exponent"):
        DelayAndSum(2, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, level_snr_exponent=-1)


def test_level_factors_multiply_the_level_weights_within_their_ratio():
    # three devices of one floor and one SNR: "level" is equal weighting; factors e^f multiply the weights (the
    # pipeline's per-device peak heights on the steered talker, level_height_exponent), held within
    # level_max_ratio of the median; None takes them away
    rng = np.random.default_rng(15)
    frame, hop = 512, 128
    n = int(4 * FS_HZ)
    talk = rng.standard_normal(n) * 0.1
    talk[: n // 2] = 0.0
    x = (talk[:, None] + 0.05 * rng.standard_normal((n, 3))).astype(np.float32)
    quiet = np.arange(n // hop) * hop < n // 2
    das = DelayAndSum(3, frame_samples=frame, hop_samples=hop, sample_rate_hz=FS_HZ, weighting="level")
    _stream_quiet(das, x, quiet)
    np.testing.assert_allclose(das.channel_weights, 1 / 3, rtol=0.02)
    das.set_level_factors(np.log([2.0, 1.0, 0.5]))
    _stream_quiet(das, x[-4 * hop:], np.zeros(4, bool))
    w = das.channel_weights
    np.testing.assert_allclose(w / w[1], [2.0, 1.0, 0.5], rtol=0.03)
    das.set_level_factors(np.log([100.0, 1.0, 1.0]))    # held within 4 times the median channel's
    _stream_quiet(das, x[-4 * hop:], np.zeros(4, bool))
    w = das.channel_weights
    assert w[0] / w[1] == pytest.approx(4.0, rel=0.03)
    das.set_level_factors(None)
    _stream_quiet(das, x[-4 * hop:], np.zeros(4, bool))
    np.testing.assert_allclose(das.channel_weights, 1 / 3, rtol=0.02)
