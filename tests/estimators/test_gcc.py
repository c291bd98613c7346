"""GCC-PHAT against synthetic delays: known shifts in, TDOA in seconds out (tolerances in samples)."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import scipy.fft
import scipy.signal
from hypothesis import given, settings
from hypothesis import strategies as st

from estimators import GccPhat, gcc_phat, gcc_phat_spectra, pair_matrix, pairs
from estimators import gcc as gcc_module

FS_HZ = 16_000.0
N = 1024


def noise(seed: int, n_samples: int = 4 * N) -> np.ndarray:
    return np.random.default_rng(seed).standard_normal(n_samples)


def speech_like(seed: int, n_samples: int = 4 * N) -> np.ndarray:
    """AR(2) resonance (formant near 500 Hz) with a syllabic 4 Hz envelope."""
    rng = np.random.default_rng(seed)
    r, f_hz = 0.97, 500.0
    a = [1.0, -2 * r * np.cos(2 * np.pi * f_hz / FS_HZ), r * r]
    x = scipy.signal.lfilter([1.0], a, rng.standard_normal(n_samples))
    t_s = np.arange(n_samples) / FS_HZ
    return x * (1.2 + np.sin(2 * np.pi * 4.0 * t_s))


def delayed(x: np.ndarray, delay_samples: float) -> np.ndarray:
    """``x(t - delay)`` by an FFT phase shift (circular over the whole signal)."""
    k = np.arange(len(x) // 2 + 1)
    return np.fft.irfft(np.fft.rfft(x) * np.exp(-2j * np.pi * k * delay_samples / len(x)), n=len(x))


def frame_of(*channels: np.ndarray) -> np.ndarray:
    """Middle ``N`` samples of each channel, time-major; the delay is not circular in the frame."""
    return np.stack([c[N : 2 * N] for c in channels], axis=1)


@pytest.mark.parametrize("d", [-37, -5, -1, 0, 1, 7, 100])
@pytest.mark.parametrize("source", [noise, speech_like])
def test_integer_delay_sign_and_value(d, source):
    s = source(d + 1000)
    x1 = np.roll(s, d)  # channel 1 delayed by d samples: x1(t) = s(t - d)
    tdoa_s, conf = gcc_phat(frame_of(s, x1), sample_rate_hz=FS_HZ)
    # pair (0, 1): toa_0 - toa_1 = -d
    assert tdoa_s.shape == (1,) and tdoa_s.dtype == np.float64
    assert abs(tdoa_s[0] * FS_HZ - (-d)) <= 0.1
    assert 0.5 < conf[0] <= 1.0


@pytest.mark.parametrize("d", [-12.5, -3.25, -0.4, 0.3, 2.75, 9.9])
@pytest.mark.parametrize("interpolation", ["sinc", "parabolic"])
@pytest.mark.parametrize("source", [noise, speech_like])
def test_fractional_delay(d, interpolation, source):
    s = source(7)
    tdoa_s, _ = gcc_phat(frame_of(s, delayed(s, d)), sample_rate_hz=FS_HZ, interpolation=interpolation)
    assert abs(tdoa_s[0] * FS_HZ + d) <= 0.25


def test_sinc_interpolation_is_nearly_unbiased():
    s = noise(3)
    for d in np.linspace(-2, 2, 17):
        tdoa_s, _ = gcc_phat(frame_of(s, delayed(s, d)), sample_rate_hz=FS_HZ)
        assert abs(tdoa_s[0] * FS_HZ + d) <= 0.02


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), d=st.floats(-50, 50, allow_nan=False))
def test_follows_a_shift(seed, d):
    s = noise(seed)
    tdoa_s, _ = gcc_phat(frame_of(s, delayed(s, d)), sample_rate_hz=FS_HZ)
    assert abs(tdoa_s[0] * FS_HZ + d) <= 0.25


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    d=st.floats(-50, 50, allow_nan=False),
    noise_std=st.floats(0.0, 1.0),
)
def test_antisymmetric(seed, d, noise_std):
    rng = np.random.default_rng(seed)
    s = noise(seed)
    x = s + noise_std * rng.standard_normal(len(s))
    y = delayed(s, d) + noise_std * rng.standard_normal(len(s))
    t_xy, c_xy = gcc_phat(frame_of(x, y), sample_rate_hz=FS_HZ)
    t_yx, c_yx = gcc_phat(frame_of(y, x), sample_rate_hz=FS_HZ)
    assert abs(t_xy[0] + t_yx[0]) * FS_HZ <= 1e-3
    assert abs(c_xy[0] - c_yx[0]) <= 1e-4


def test_multichannel_matches_pair_matrix():
    toa_samples = np.array([0.0, 3.5, -7.25, 12.0, 0.6])
    s = speech_like(11)
    frame = frame_of(*[delayed(s, t) for t in toa_samples])
    tdoa_s, conf = gcc_phat(frame, sample_rate_hz=FS_HZ)
    expected_samples = pair_matrix(5) @ toa_samples
    assert tdoa_s.shape == (10,)
    np.testing.assert_allclose(tdoa_s * FS_HZ, expected_samples, atol=0.25)
    # pair order is pairs(): (0,1) first, (3,4) last
    assert pairs(5)[0].tolist() == [0, 1] and pairs(5)[-1].tolist() == [3, 4]
    assert np.all((conf > 0.3) & (conf <= 1.0))


def test_max_tdoa_bound_respected():
    s = noise(5)
    frame = frame_of(s, np.roll(s, 40), np.roll(s, -25))
    max_tdoa_s = 10 / FS_HZ
    tdoa_s, _ = gcc_phat(frame, sample_rate_hz=FS_HZ, max_tdoa_s=max_tdoa_s)
    assert np.all(np.abs(tdoa_s) <= max_tdoa_s + 1e-12)
    # a delay inside the bound is still found
    tdoa_s, _ = gcc_phat(frame_of(s, np.roll(s, 6)), sample_rate_hz=FS_HZ, max_tdoa_s=max_tdoa_s)
    assert abs(tdoa_s[0] * FS_HZ + 6) <= 0.1


def test_search_stays_below_half_frame():
    gcc = GccPhat(2, n_fft=64, sample_rate_hz=FS_HZ, max_tdoa_s=1.0)
    assert gcc.max_lag_samples == 31


@pytest.mark.parametrize("bad", ["zeros", "nan", "inf"])
def test_silent_or_invalid_channel(bad):
    s = noise(9)
    frame = frame_of(s, np.roll(s, 3), np.zeros_like(s), np.roll(s, -2))
    if bad == "nan":
        frame[100, 2] = np.nan
    elif bad == "inf":
        frame[:, 2] = np.inf
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tdoa_s, conf = gcc_phat(frame, sample_rate_hz=FS_HZ)
    assert np.all(np.isfinite(tdoa_s)) and np.all(np.isfinite(conf))
    touches_2 = (pairs(4) == 2).any(axis=1)
    assert np.all(conf[touches_2] == 0) and np.all(tdoa_s[touches_2] == 0)
    assert np.all(conf[~touches_2] > 0.5)
    np.testing.assert_allclose(tdoa_s[~touches_2] * FS_HZ, [-3, 2, 5], atol=0.1)


@pytest.mark.parametrize("bad_value", [np.nan, np.inf, 0.0])
def test_invalid_spectra_handled(bad_value):
    s = noise(2)
    spec = scipy.fft.rfft(frame_of(s, np.roll(s, 4), s), axis=0)
    if bad_value == 0.0:
        spec[:, 2] = 0.0
    else:
        spec[5, 2] = bad_value
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tdoa_s, conf = gcc_phat_spectra(spec, n_fft=N, sample_rate_hz=FS_HZ)
    np.testing.assert_array_equal(conf[1:], 0.0)
    np.testing.assert_array_equal(tdoa_s[1:], 0.0)
    assert abs(tdoa_s[0] * FS_HZ + 4) <= 0.1


def test_pure_circular_delay_has_confidence_one():
    s = noise(4, N)
    tdoa_s, conf = gcc_phat(np.stack([s, np.roll(s, 9)], axis=1), sample_rate_hz=FS_HZ, window=False)
    assert abs(tdoa_s[0] * FS_HZ + 9) <= 1e-3
    assert conf[0] == pytest.approx(1.0, abs=1e-3)


@pytest.mark.parametrize("max_tdoa_s", [None, 20 / FS_HZ])
def test_frame_and_spectra_paths_agree(max_tdoa_s):
    s = speech_like(8)
    frame = frame_of(s, delayed(s, 2.5), delayed(s, -6.0), np.roll(s, 1))
    window = scipy.signal.get_window("hann", N, fftbins=True)
    spectra = scipy.fft.rfft((frame * window[:, None]).astype(np.float32), axis=0)
    t_frame, c_frame = gcc_phat(frame, sample_rate_hz=FS_HZ, max_tdoa_s=max_tdoa_s)
    t_spec, c_spec = gcc_phat_spectra(spectra, n_fft=N, sample_rate_hz=FS_HZ, max_tdoa_s=max_tdoa_s)
    gcc = GccPhat(4, n_fft=N, sample_rate_hz=FS_HZ, max_tdoa_s=max_tdoa_s)
    t_cls, c_cls = gcc.process(spectra)
    np.testing.assert_allclose(t_spec * FS_HZ, t_frame * FS_HZ, atol=1e-3)
    np.testing.assert_allclose(c_spec, c_frame, atol=1e-4)
    np.testing.assert_array_equal(t_cls, t_spec)
    np.testing.assert_array_equal(c_cls, c_spec)


def test_outputs_are_not_reused_buffers():
    gcc = GccPhat(3, n_fft=N, sample_rate_hz=FS_HZ)
    a, b = noise(1), noise(2)
    spec_a = scipy.fft.rfft(frame_of(a, np.roll(a, 3), np.roll(a, -8)), axis=0)
    spec_b = scipy.fft.rfft(frame_of(b, np.roll(b, 1), np.roll(b, 5)), axis=0)
    t_a, c_a = gcc.process(spec_a)
    t_a_copy, c_a_copy = t_a.copy(), c_a.copy()
    gcc.process(spec_b)
    np.testing.assert_array_equal(t_a, t_a_copy)
    np.testing.assert_array_equal(c_a, c_a_copy)


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(n_channels=1, n_fft=N, sample_rate_hz=FS_HZ),
        dict(n_channels=2, n_fft=2, sample_rate_hz=FS_HZ),
        dict(n_channels=2, n_fft=N, sample_rate_hz=0.0),
        dict(n_channels=2, n_fft=N, sample_rate_hz=FS_HZ, max_tdoa_s=-1e-3),
        dict(n_channels=2, n_fft=N, sample_rate_hz=FS_HZ, interpolation="cubic"),
    ],
)
def test_bad_arguments_raise_at_construction(kwargs):
    n_channels = kwargs.pop("n_channels")
    with pytest.raises(ValueError):
        GccPhat(n_channels, **kwargs)


def test_bad_shapes_raise():
    gcc = GccPhat(3, n_fft=N, sample_rate_hz=FS_HZ)
    for bad in (np.zeros((N // 2 + 1, 2), np.complex64), np.zeros((2, N // 2 + 1), np.complex64).T,
                np.zeros((N // 2 + 1, 3, 1)), np.zeros(N // 2 + 1, np.complex64),
                np.zeros((N // 2 + 1, 1), np.complex64)):
        with pytest.raises(ValueError, match="spectra.shape"):
            gcc.process(bad)
    with pytest.raises(ValueError, match="frame.shape"):
        gcc_phat(np.zeros(N), sample_rate_hz=FS_HZ)


# Correlation values closer than this may be ordered either way: the kernel's |X| (float32 sqrt) and
# products round differently from numpy's hypot and complex product by ~1e-7 relative.
TIE = 1e-5


def reference_gcc(spectra: np.ndarray, n_fft: int, max_lag: int, fs: float, interpolation: str = "sinc"):
    """The former numpy implementation, restated plainly (np.where/np.clip, one gather per neighbour).

    Returns ``(tdoa_s, confidence, ambiguous)``: ``ambiguous`` marks the pairs whose result hangs on
    a near-tie that float rounding may legitimately break either way (see ``TIE``).
    """
    spec = np.ascontiguousarray(np.asarray(spectra).T, dtype=np.complex64)
    m = spec.shape[0]
    mag = np.abs(spec)
    peak = mag.max(axis=1)
    valid = np.isfinite(peak) & (peak > 0)
    eps = (1e-6 * np.where(valid, peak, 0) + float(np.finfo(np.float32).tiny)).astype(np.float32)
    with np.errstate(invalid="ignore"):
        unit = spec * (1.0 / (mag + eps[:, None]))
    unit[~valid] = 0
    p = pairs(m)
    cross = unit[p[:, 0]] * np.conj(unit[p[:, 1]])
    corr = scipy.fft.irfft(cross, n=n_fft, axis=-1, workers=1)
    L = max_lag
    window = np.concatenate((corr[:, n_fft - L :], corr[:, : L + 1]), axis=1)
    lag_int = np.argmax(window, axis=1) - L
    rows = np.arange(len(p))
    idx = np.mod(lag_int, n_fft)
    r0 = corr[rows, idx].astype(np.float64)
    rm = corr[rows, np.mod(idx - 1, n_fft)].astype(np.float64)
    rp = corr[rows, np.mod(idx + 1, n_fft)].astype(np.float64)
    lag = lag_int.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        if interpolation == "sinc":
            plus = rp >= rm
            side = np.where(plus, rp, rm)
            den = r0 + side
            d = np.clip(np.where(den > 0, side / den, 0.0), 0.0, 0.5)
            lag += np.where(plus, d, -d)
        elif interpolation == "parabolic":
            den = rm - 2.0 * r0 + rp
            lag += np.clip(np.where(den < 0, 0.5 * (rm - rp) / den, 0.0), -0.5, 0.5)
    lag = np.clip(lag, -L, L)
    conf = np.clip(r0, 0.0, 1.0)
    ok = valid[p[:, 0]] & valid[p[:, 1]]
    lag[~ok] = 0.0
    conf[~ok] = 0.0
    # Near-ties: the two highest lags of the window (the integer peak may flip), and for "sinc" the
    # two neighbours (the side of the offset may flip).
    top2 = np.sort(window, axis=1)[:, -2:]
    ambiguous = ok & (top2[:, -1] - top2[:, 0] < TIE) if L > 0 else np.zeros(len(p), bool)
    if interpolation == "sinc":
        ambiguous |= ok & (np.abs(rp - rm) < TIE)
    return lag / fs, conf, ambiguous


def random_spectra(rng: np.random.Generator, n_frames: int, n_channels: int, n_fft: int) -> np.ndarray:
    """Windowed frames of a common source with per-channel delays, noise and occasional bad channels."""
    s = rng.standard_normal(n_fft * (n_frames + 2))
    delays = rng.uniform(-20, 20, n_channels)
    x = np.stack([delayed(s, d) for d in delays], axis=1) + 0.3 * rng.standard_normal((len(s), n_channels))
    window = scipy.signal.get_window("hann", n_fft, fftbins=True)
    frames = np.stack([x[k * n_fft // 2 : k * n_fft // 2 + n_fft] for k in range(n_frames)]) * window[None, :, None]
    spec = scipy.fft.rfft(frames.astype(np.float32), axis=1)
    for k in range(n_frames):  # a silent, a NaN or an inf channel now and then
        kind = rng.integers(0, 6)
        c = rng.integers(0, n_channels)
        if kind == 0:
            spec[k, :, c] = 0
        elif kind == 1:
            spec[k, rng.integers(0, spec.shape[1]), c] = np.nan
        elif kind == 2:
            spec[k, rng.integers(0, spec.shape[1]), c] = np.inf
    return spec


@pytest.mark.parametrize(
    "n_channels,n_fft,max_tdoa_s",
    [(2, 64, None), (5, 256, 30 / FS_HZ), (8, 512, None), (4, 1024, 3 / FS_HZ), (8, 4096, None)],
)
@pytest.mark.parametrize("interpolation", ["sinc", "parabolic", "none"])
def test_process_matches_reference(n_channels, n_fft, max_tdoa_s, interpolation):
    # The compiled kernel rounds |X|, the products and the inverse FFT differently from numpy and
    # scipy (~1 float32 ulp; seen: 3e-7 sample, 1.2e-7 in confidence), so it matches the former
    # arithmetic to 1e-5 sample and 1e-6 in confidence, not bit for bit. Pairs on a near-tie (TIE)
    # are left out of the TDOA comparison, and must be rare (none in these inputs).
    rng = np.random.default_rng(n_channels * n_fft)
    spec = random_spectra(rng, 12, n_channels, n_fft)
    gcc = GccPhat(n_channels, n_fft=n_fft, sample_rate_hz=FS_HZ, max_tdoa_s=max_tdoa_s, interpolation=interpolation)
    n_ambiguous = 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for k in range(len(spec)):
            t, c = gcc.process(spec[k])
            t_ref, c_ref, ambiguous = reference_gcc(spec[k], n_fft, gcc.max_lag_samples, FS_HZ, interpolation)
            n_ambiguous += int(ambiguous.sum())
            np.testing.assert_allclose(t[~ambiguous] * FS_HZ, t_ref[~ambiguous] * FS_HZ, rtol=0, atol=1e-5)
            np.testing.assert_allclose(c, c_ref, rtol=0, atol=1e-6)
            # any memory layout and dtype of the input gives the same result
            t2, c2 = gcc.process(np.ascontiguousarray(spec[k]).astype(np.complex128))
            np.testing.assert_array_equal(t2, t)
            np.testing.assert_array_equal(c2, c)
    assert n_ambiguous <= 0.02 * len(spec) * gcc.n_pairs


def test_pairs_in_chunks_equal_all_at_once(monkeypatch):
    # 8 channels x 4096 bins go through in chunks of 16 pairs; one chunk of all 28 pairs gives the
    # same result (here bit for bit; to float32 rounding if the FFT batches rows differently).
    rng = np.random.default_rng(3)
    spec = random_spectra(rng, 3, 8, 4096)
    chunked = GccPhat(8, n_fft=4096, sample_rate_hz=FS_HZ)
    assert chunked._cross.shape[0] < chunked.n_pairs
    monkeypatch.setattr(gcc_module, "_CHUNK_BYTES", 1 << 30)
    whole = GccPhat(8, n_fft=4096, sample_rate_hz=FS_HZ)
    assert whole._cross.shape[0] == whole.n_pairs
    for s in spec:
        t_c, c_c = chunked.process(s)
        t_w, c_w = whole.process(s)
        np.testing.assert_allclose(t_c * FS_HZ, t_w * FS_HZ, rtol=0, atol=1e-5)
        np.testing.assert_allclose(c_c, c_w, rtol=0, atol=1e-6)


@pytest.mark.parametrize("scale", [1e-30, 1e-8, 1e21, 1e30])
def test_extreme_but_finite_magnitudes(scale):
    # A channel whose largest |X| is outside 1e-6..1e18 gets |X| again in float64 (its float32
    # squares could over- or underflow): it stays usable, and PHAT is scale invariant (to float32
    # rounding).
    s = noise(6)
    window = scipy.signal.get_window("hann", N)[:, None]
    spec = scipy.fft.rfft(frame_of(s, np.roll(s, 4), np.roll(s, -3)) * window, axis=0)
    scaled = spec.copy()
    scaled[:, 1] *= scale
    gcc = GccPhat(3, n_fft=N, sample_rate_hz=FS_HZ)
    t_ref, c_ref = gcc.process(spec.astype(np.complex64))
    t, c = gcc.process(scaled.astype(np.complex64))
    assert np.all(c > 0.5)
    np.testing.assert_allclose(t * FS_HZ, t_ref * FS_HZ, rtol=0, atol=1e-5)
    np.testing.assert_allclose(c, c_ref, rtol=0, atol=1e-6)


@settings(max_examples=200, deadline=None)
@given(
    values=st.lists(st.sampled_from([-1.0, -0.0, 0.0, 0.25, 1.0]), min_size=4, max_size=24),
    max_lag=st.integers(0, 11),
)
def test_peak_search_takes_the_first_maximum(values, max_lag):
    # Lags -L..-1 before 0..L, first maximum wins, +0 ties with -0: np.argmax over the window.
    row = np.array(values[: len(values) // 2 * 2], np.float32)
    n = len(row)
    L = min(max_lag, n // 2 - 1)
    window = np.concatenate((row[n - L :], row[: L + 1]))
    assert gcc_module._first_max(row, L) == int(np.argmax(window)) - L


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), mask=st.lists(st.booleans(), min_size=5, max_size=5))
def test_valid_keyword_silences_exactly_the_pairs_of_invalid_channels(seed, mask):
    gcc = GccPhat(5, n_fft=256, sample_rate_hz=FS_HZ, max_tdoa_s=30 / FS_HZ)
    spec = random_spectra(np.random.default_rng(seed), 1, 5, 256)[0]
    t_all, c_all = gcc.process(spec)
    valid = np.array(mask)
    t, c = gcc.process(spec, valid=valid)
    p = pairs(5)
    ok = valid[p[:, 0]] & valid[p[:, 1]]
    np.testing.assert_array_equal(t[~ok], 0.0)
    np.testing.assert_array_equal(c[~ok], 0.0)
    np.testing.assert_array_equal(t[ok], t_all[ok])  # the other channels' pairs are untouched
    np.testing.assert_array_equal(c[ok], c_all[ok])
    # the same as the caller's former masking of the confidence, and any array-like works
    np.testing.assert_array_equal(c, np.where(ok, c_all, 0.0))
    t_list, c_list = gcc.process(spec, valid=[int(v) for v in mask])
    np.testing.assert_array_equal(t_list, t)
    np.testing.assert_array_equal(c_list, c)


def test_valid_keyword_shape_is_checked():
    gcc = GccPhat(3, n_fft=64, sample_rate_hz=FS_HZ)
    spec = np.ones((33, 3), np.complex64)
    with pytest.raises(ValueError, match="valid.shape"):
        gcc.process(spec, valid=np.ones(4, bool))
    with pytest.raises(ValueError, match="valid.shape"):  # the kernel's own layout: checked inside it
        gcc.process(np.ones((3, 33), np.complex64).T, valid=np.ones(4, bool))
    with pytest.raises(ValueError, match="valid.shape"):
        gcc.process(spec, valid=np.ones((1, 3), bool))
    with pytest.raises(ValueError, match="valid.shape"):
        gcc.process_many(spec[None], valid=np.ones(3, bool))


def test_read_only_and_strided_inputs():
    rng = np.random.default_rng(5)
    spec = random_spectra(rng, 2, 4, 256)
    gcc = GccPhat(4, n_fft=256, sample_rate_hz=FS_HZ)
    t, c = gcc.process(spec[0])
    frozen = spec[0].copy()
    frozen.flags.writeable = False
    valid = np.ones(4, bool)
    valid.flags.writeable = False
    t2, c2 = gcc.process(frozen, valid=valid)
    np.testing.assert_array_equal(t2, t)
    np.testing.assert_array_equal(c2, c)
    # other dtypes and layouts of the spectra and the mask are converted; same values, same result
    for s, v in ((spec[0].astype(np.complex128), [True] * 4), (np.ascontiguousarray(spec[0]), np.ones(4, int)),
                 (spec[0].tolist(), None)):
        t2, c2 = gcc.process(s, valid=v)
        np.testing.assert_array_equal(t2, t)
        np.testing.assert_array_equal(c2, c)
    frame = noise(1)[: 2 * N].reshape(N, 2)
    wide = np.zeros((N, 4))
    wide[:, ::2] = frame
    t_ref, c_ref = gcc_phat(frame.astype(np.float32), sample_rate_hz=FS_HZ)
    for f in (frame, wide[:, ::2], np.asfortranarray(frame)):  # float64, strided, Fortran order
        t_f, c_f = gcc_phat(f, sample_rate_hz=FS_HZ)
        np.testing.assert_array_equal(t_f, t_ref)
        np.testing.assert_array_equal(c_f, c_ref)


@pytest.mark.parametrize("n_channels,n_fft", [(3, 64), (8, 512), (16, 256)])
def test_process_many_equals_process(n_channels, n_fft):
    rng = np.random.default_rng(n_channels)
    gcc = GccPhat(n_channels, n_fft=n_fft, sample_rate_hz=FS_HZ, max_tdoa_s=10 / FS_HZ)
    n_frames = 7
    spec = random_spectra(rng, n_frames, n_channels, n_fft)
    single = [gcc.process(s) for s in spec]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        t, c = gcc.process_many(spec)
    assert t.shape == c.shape == (n_frames, gcc.n_pairs)
    np.testing.assert_array_equal(t, np.array([s[0] for s in single]))
    np.testing.assert_array_equal(c, np.array([s[1] for s in single]))
    # the channel-major layout of StreamingStft.process_many (a transposed view) gives the same
    cm = np.ascontiguousarray(spec.transpose(0, 2, 1)).transpose(0, 2, 1)
    t2, c2 = gcc.process_many(cm)
    np.testing.assert_array_equal(t2, t)
    np.testing.assert_array_equal(c2, c)
    # per-frame channel flags equal per-frame calls with valid=
    valid = rng.random((n_frames, n_channels)) > 0.3
    t3, c3 = gcc.process_many(spec, valid=valid)
    single = [gcc.process(s, valid=v) for s, v in zip(spec, valid)]
    np.testing.assert_array_equal(t3, np.array([s[0] for s in single]))
    np.testing.assert_array_equal(c3, np.array([s[1] for s in single]))
    t0, c0 = gcc.process_many(spec[:0])
    assert t0.shape == c0.shape == (0, gcc.n_pairs)
    with pytest.raises(ValueError, match="spectra.shape"):
        gcc.process_many(spec[0])
