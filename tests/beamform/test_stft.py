"""Streaming STFT / WOLA synthesis: identity, framing convention, streaming equals batch."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import scipy.fft
import scipy.signal
from hypothesis import given, settings
from hypothesis import strategies as st

from beamform.stft import StreamingIstft, StreamingStft, analysis_window, dual_window, istft, stft

PAIRS = [(4096, 1024), (512, 128), (1024, 256), (512, 256), (256, 64), (64, 16), (100, 25), (48, 16)]


def _stream(x: np.ndarray, frame: int, hop: int, window="hann"):
    """Run analysis + synthesis hop by hop; return (spectra, output)."""
    ana = StreamingStft(x.shape[1], frame_samples=frame, hop_samples=hop, window=window)
    syn = [StreamingIstft(frame_samples=frame, hop_samples=hop, analysis_window=ana.analysis_window) for _ in range(x.shape[1])]
    specs, outs = [], []
    for k in range(x.shape[0] // hop):
        S = ana.process(x[k * hop : (k + 1) * hop])
        specs.append(S)
        outs.append(np.stack([syn[c].process(S[:, c]) for c in range(x.shape[1])], axis=1))
    return np.array(specs), np.concatenate(outs)


@pytest.mark.parametrize("frame,hop", PAIRS)
def test_analysis_synthesis_is_identity_delayed_by_latency(frame, hop):
    rng = np.random.default_rng(frame + hop)
    x = rng.standard_normal((hop * (3 * frame // hop + 5), 2)).astype(np.float32)
    _, y = _stream(x, frame, hop)
    latency = frame - hop
    assert StreamingIstft(frame_samples=frame, hop_samples=hop, analysis_window=np.hanning(frame + 1)[:-1]).latency_samples == latency
    np.testing.assert_allclose(y[latency:], x[: len(x) - latency], atol=1e-5)
    np.testing.assert_allclose(y[:latency], 0.0, atol=1e-5)


def test_spectra_shape_dtype_and_frame_convention():
    frame, hop = 16, 4
    ana = StreamingStft(3, frame_samples=frame, hop_samples=hop)
    assert ana.analysis_window.dtype == np.float32
    np.testing.assert_allclose(ana.analysis_window, scipy.signal.get_window("hann", frame, fftbins=True), atol=1e-7)
    # An impulse at input sample n0 appears in frame k iff (k+1)*hop - frame <= n0 < (k+1)*hop.
    n0 = 9
    x = np.zeros((40, 3), np.float32)
    x[n0] = 1.0
    for k in range(10):
        S = ana.process(x[k * hop : (k + 1) * hop])
        assert S.shape == (frame // 2 + 1, 3) and S.dtype == np.complex64
        start = (k + 1) * hop - frame
        expected = np.zeros(frame, np.float32)
        if start <= n0 < start + frame:
            expected[n0 - start] = ana.analysis_window[n0 - start]
        np.testing.assert_allclose(np.fft.irfft(S[:, 0], frame), expected, atol=1e-7)


def test_dual_window_of_hann_at_75_percent_is_hann_over_1p5():
    w = scipy.signal.get_window("hann", 512, fftbins=True)
    np.testing.assert_allclose(dual_window(w, hop_samples=128), w / 1.5, rtol=1e-6, atol=1e-7)


def test_validation():
    with pytest.raises(ValueError, match="hop_samples"):
        StreamingStft(1, frame_samples=256, hop_samples=512)
    with pytest.raises(ValueError, match="hop_samples"):  # periodic Hann at 0 % overlap has a zero
        StreamingIstft(frame_samples=256, hop_samples=256, analysis_window=np.hanning(257)[:-1])
    with pytest.raises(ValueError, match="n_channels"):
        StreamingStft(0, frame_samples=256, hop_samples=64)
    ana = StreamingStft(2, frame_samples=256, hop_samples=64)
    for bad in (np.zeros((63, 2), np.float32), np.zeros((64, 3)), np.zeros(64, np.float32), [[0.0, 0.0]] * 65):
        with pytest.raises(ValueError, match="block.shape"):
            ana.process(bad)
    assert ana.n_frames == 0  # a rejected block changes nothing
    with pytest.raises(ValueError, match="window"):
        StreamingStft(2, frame_samples=256, hop_samples=64, window=np.ones(255))


def test_reset_restores_initial_state():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((256, 1)).astype(np.float32)
    ana = StreamingStft(1, frame_samples=128, hop_samples=32)
    first = [ana.process(x[k * 32 : (k + 1) * 32]) for k in range(8)]
    ana.reset()
    again = [ana.process(x[k * 32 : (k + 1) * 32]) for k in range(8)]
    np.testing.assert_array_equal(np.array(first), np.array(again))


@settings(max_examples=25, deadline=None)
@given(
    frame_pow=st.integers(min_value=4, max_value=9),
    overlap=st.sampled_from([2, 4, 8]),
    n_blocks=st.integers(min_value=1, max_value=40),
    n_channels=st.integers(min_value=1, max_value=3),
    seed=st.integers(min_value=0, max_value=2**31 - 1),
)
def test_streaming_equals_batch_and_identity_for_any_block_count(frame_pow, overlap, n_blocks, n_channels, seed):
    frame = 2**frame_pow
    hop = frame // overlap
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((n_blocks * hop, n_channels)).astype(np.float32)
    specs, y = _stream(x, frame, hop)
    S = stft(x, frame_samples=frame, hop_samples=hop)
    np.testing.assert_array_equal(specs, S)  # the same compiled per-frame code: bit for bit
    yb = istft(S, frame_samples=frame, hop_samples=hop)
    np.testing.assert_array_equal(y, yb)
    latency = frame - hop
    if len(x) > latency:
        np.testing.assert_allclose(y[latency:], x[: len(x) - latency], atol=2e-5)


def _naive_frames(x: np.ndarray, frame: int, hop: int, window: np.ndarray) -> np.ndarray:
    """Reference analysis: zero-pad the past, slice frame k = [(k+1) hop - frame, (k+1) hop)."""
    padded = np.concatenate([np.zeros((frame - hop, x.shape[1]), np.float32), x])
    n = x.shape[0] // hop
    frames = np.stack([padded[k * hop : k * hop + frame] for k in range(n)])
    return scipy.fft.rfft(frames * window[None, :, None], axis=1, workers=1)


@pytest.mark.parametrize("frame,hop", [(64, 16), (64, 64), (100, 25), (512, 128)])
def test_ring_buffer_wraps_without_changing_the_frames(frame, hop):
    # many more hops than the 2 * frame history holds: every wrap must keep the last frame
    rng = np.random.default_rng(frame + hop)
    x = rng.standard_normal((hop * (6 * frame // hop + 7), 3)).astype(np.float32)
    ana = StreamingStft(3, frame_samples=frame, hop_samples=hop)
    specs = np.array([ana.process(x[k * hop : (k + 1) * hop]) for k in range(x.shape[0] // hop)])
    ref = _naive_frames(x, frame, hop, ana.analysis_window)
    # rocket-fft (DUCC0) inside the kernel against scipy's pocketfft on the same float32 frames:
    # equal here, but only float32 FFT rounding (~log2(frame) 6e-8 of the peak) is promised.
    np.testing.assert_allclose(specs, ref, rtol=0, atol=1e-6 * np.abs(ref).max())


def test_spectra_are_channel_major_new_arrays():
    ana = StreamingStft(4, frame_samples=256, hop_samples=64)
    blk = np.ones((64, 4), np.float32)
    a = ana.process(blk)
    b = ana.process(blk)
    assert a.shape == (129, 4) and a.T.flags.c_contiguous  # the layout GccPhat / DelayAndSum use
    assert not np.shares_memory(a, b)


@settings(max_examples=25, deadline=None)
@given(
    frame_pow=st.integers(min_value=3, max_value=9),
    overlap=st.sampled_from([1, 2, 4]),
    n_channels=st.integers(min_value=1, max_value=4),
    splits=st.lists(st.integers(min_value=0, max_value=9), min_size=1, max_size=6),
    seed=st.integers(min_value=0, max_value=2**31 - 1),
)
def test_process_many_equals_process_hop_by_hop(frame_pow, overlap, n_channels, splits, seed):
    frame = 2**frame_pow
    hop = frame // overlap
    rng = np.random.default_rng(seed)
    n_hops = sum(splits)
    x = rng.standard_normal((n_hops * hop, n_channels)).astype(np.float32)
    one = StreamingStft(n_channels, frame_samples=frame, hop_samples=hop)
    streamed = [one.process(x[k * hop : (k + 1) * hop]) for k in range(n_hops)]
    many = StreamingStft(n_channels, frame_samples=frame, hop_samples=hop)
    batched, start = [], 0
    for i, n in enumerate(splits):  # batches of any size, mixed with single hops
        chunk = x[start * hop : (start + n) * hop]
        if i % 2 and n:
            batched.extend(many.process(chunk[k * hop : (k + 1) * hop]) for k in range(n))
        else:
            out = many.process_many(chunk)
            assert out.shape == (n, frame // 2 + 1, n_channels) and out.dtype == np.complex64
            assert all(o.T.flags.c_contiguous for o in out)
            batched.extend(out)
        start += n
    np.testing.assert_array_equal(np.array(batched).reshape(-1), np.array(streamed).reshape(-1))
    assert many.n_frames == one.n_frames == n_hops
    # the state after the batches is the streaming state
    tail = rng.standard_normal((hop, n_channels)).astype(np.float32)
    np.testing.assert_array_equal(many.process(tail), one.process(tail))


def test_process_many_validation():
    ana = StreamingStft(2, frame_samples=64, hop_samples=16)
    with pytest.raises(ValueError, match="blocks.shape"):
        ana.process_many(np.zeros((40, 2), np.float32))
    with pytest.raises(ValueError, match="blocks.shape"):
        ana.process_many(np.zeros((32, 3), np.float32))
    assert ana.process_many(np.zeros((0, 2), np.float32)).shape == (0, 33, 2)


def test_non_finite_input_passes_through_without_warnings():
    rng = np.random.default_rng(7)
    frame, hop = 64, 16
    x = rng.standard_normal((hop * 12, 3)).astype(np.float32)
    bad = x.copy()
    bad[hop * 4 + 3, 1] = np.nan
    bad[hop * 6 : hop * 7, 2] = np.inf
    clean = StreamingStft(3, frame_samples=frame, hop_samples=hop)
    ana = StreamingStft(3, frame_samples=frame, hop_samples=hop)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for k in range(12):
            S = ana.process(bad[k * hop : (k + 1) * hop])
            S_clean = clean.process(x[k * hop : (k + 1) * hop])
            np.testing.assert_array_equal(S[:, 0], S_clean[:, 0])  # other channels untouched
            assert np.all(np.isfinite(S[:, 1])) == (k < 4 or k >= 4 + frame // hop)
            assert np.all(np.isfinite(S[:, 2])) == (k < 6 or k >= 7 + frame // hop - 1)


@pytest.mark.parametrize("frame,hop,window", [(64, 48, "hann"), (64, 64, "boxcar"), (60, 20, "hamming")])
def test_synthesis_identity_for_long_hops_and_other_windows(frame, hop, window):
    # hop > frame / 2 (fresh samples reach the output directly) and hop == frame (no overlap)
    rng = np.random.default_rng(frame + hop)
    x = rng.standard_normal((hop * 20, 2)).astype(np.float32)
    _, y = _stream(x, frame, hop, window)
    latency = frame - hop
    np.testing.assert_allclose(y[latency:], x[: len(x) - latency], atol=2e-5)
    S = stft(x, frame_samples=frame, hop_samples=hop, window=window)
    np.testing.assert_array_equal(istft(S, frame_samples=frame, hop_samples=hop, window=window), y)


def test_synthesis_input_types_and_reset():
    rng = np.random.default_rng(8)
    frame, hop = 32, 8
    S = (rng.standard_normal((10, 17)) + 1j * rng.standard_normal((10, 17))).astype(np.complex64)
    S[:, 0] = S[:, 0].real  # DC and Nyquist of a real frame are real
    S[:, -1] = S[:, -1].real
    w = analysis_window("hann", frame)  # float32, as istft() makes it
    syn = StreamingIstft(frame_samples=frame, hop_samples=hop, analysis_window=w)
    ref = [syn.process(s) for s in S]
    syn.reset()
    read_only = S.copy()
    read_only.flags.writeable = False
    # complex128, strided and read-only spectra give the same float32 samples after reset
    odd = [S[0].astype(np.complex128), np.stack([S[1], S[1]], axis=1)[:, 0], read_only[2]]
    odd += list(S[3:])
    out = [syn.process(s) for s in odd]
    np.testing.assert_array_equal(np.array(out), np.array(ref))
    assert out[0].dtype == np.float32 and not np.shares_memory(out[0], out[1])
    np.testing.assert_array_equal(istft(S, frame_samples=frame, hop_samples=hop), np.concatenate(ref))
    with pytest.raises(ValueError, match="spectrum.shape"):
        syn.process(S[0, :-1])
