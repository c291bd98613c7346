"""Streaming STFT analysis and weighted-overlap-add (WOLA) synthesis.

Conventions (fixed here, used by :mod:`beamform.das`)
-----------------------------------------------------
- Audio is time-major, ``(n_samples, n_channels)``, float32.
- One call consumes exactly ``hop_samples`` new samples. The analysis buffer starts at zeros, so the
  frame produced after block ``k`` (0-based) covers input samples
  ``[(k + 1) * hop - frame, (k + 1) * hop)``.
- Spectra are ``rfft(analysis_window * frame)`` (numpy convention) without normalisation,
  ``n_bins = frame_samples // 2 + 1`` and bin ``b`` has angular frequency
  ``omega_b = 2 pi b sample_rate_hz / frame_samples`` (rad/s).
- Synthesis uses the canonical dual window of the analysis window,

  ``w_s[n] = w_a[n] / sum_k w_a[n + k hop]^2``  (sum over all integers ``k``, ``w_a = 0`` outside),

  so that ``sum_m w_s[n - m hop] w_a[n - m hop] = 1`` for every ``n`` and analysis followed by
  synthesis without modification is the identity delayed by
  ``latency_samples = frame_samples - hop_samples`` (Hann at 75 % overlap gives ``w_s = w_a / 1.5``).
  This holds for any ``hop_samples <= frame_samples`` for which the denominator never vanishes.

The pure functions :func:`stft` and :func:`istft` are the batch counterparts of
:class:`StreamingStft` and :class:`StreamingIstft` and produce the same frames and samples, bit for
bit: each public call runs one compiled numba kernel (``_stft_process``, ``_istft_process``, ...)
that also does the FFT (rocket-fft's ``np.fft`` inside numba), and the batch kernels run the same
per-frame code over all frames.
"""
from __future__ import annotations

import numba
import numpy as np
import scipy.signal

from estimators.numba_tools import borrowed

__all__ = [
    "StreamingStft",
    "StreamingIstft",
    "analysis_window",
    "dual_window",
    "stft",
    "istft",
]

_F32 = np.dtype(np.float32)
_C64 = np.dtype(np.complex64)


def analysis_window(window: str | np.ndarray, frame_samples: int) -> np.ndarray:
    """Analysis window for the STFT.

    Parameters
    ----------
    window : str or ndarray, shape (frame_samples,)
        A name understood by :func:`scipy.signal.get_window` (periodic, i.e. ``fftbins=True``;
        ``"hann"`` is the periodic Hann window) or the window samples themselves.
    frame_samples : int
        Frame length in samples.

    Returns
    -------
    ndarray, shape (frame_samples,), float32
    """
    if isinstance(window, str):
        w = scipy.signal.get_window(window, frame_samples, fftbins=True)
    else:
        w = np.asarray(window, dtype=np.float64)
        if w.shape != (frame_samples,):
            raise ValueError(f"{w.shape=} of the window must be ({frame_samples},) = (frame_samples,)")
    if not np.all(np.isfinite(w)):
        raise ValueError("the analysis window must be finite")
    return np.array(w, dtype=np.float32, order="C")  # a writeable copy (the kernels take it)


def dual_window(window: np.ndarray, *, hop_samples: int) -> np.ndarray:
    """Canonical dual (synthesis) window for weighted overlap-add.

    ``w_s[n] = w_a[n] / sum_k w_a[n + k hop]^2`` with ``w_a = 0`` outside the frame, which makes
    ``sum_m w_s[n - m hop] w_a[n - m hop] = 1`` (perfect reconstruction).

    Parameters
    ----------
    window : ndarray, shape (frame_samples,)
        Analysis window.
    hop_samples : int
        Hop between frames in samples, ``1 <= hop_samples <= frame_samples``.

    Returns
    -------
    ndarray, shape (frame_samples,), float32

    Raises
    ------
    ValueError
        If the hop is out of range or the overlap-added squared window vanishes somewhere
        (the window/hop pair does not allow reconstruction).
    """
    w = np.asarray(window, dtype=np.float64)
    frame_samples = w.shape[0]
    if not 1 <= hop_samples <= frame_samples:
        raise ValueError(f"{hop_samples=} must be in 1..{frame_samples} (frame_samples)")
    # Denominator is periodic with period hop: fold w^2 onto one hop.
    n_folds = -(-frame_samples // hop_samples)
    w2 = np.zeros(n_folds * hop_samples)
    w2[:frame_samples] = w**2
    folded = w2.reshape(n_folds, hop_samples).sum(axis=0)
    if np.min(folded) <= 1e-8 * max(np.max(folded), np.finfo(float).tiny):
        raise ValueError(
            f"the squared analysis window overlap-added at {hop_samples=} has a zero; "
            f"choose a smaller hop (e.g. frame_samples // 4 for Hann)"
        )
    denom = np.tile(folded, n_folds)[:frame_samples]
    return (w / denom).astype(np.float32)


def _check_frame_hop(frame_samples: int, hop_samples: int) -> None:
    if int(frame_samples) != frame_samples or frame_samples < 2:
        raise ValueError(f"{frame_samples=} must be an integer >= 2 (samples)")
    if int(hop_samples) != hop_samples or not 1 <= hop_samples <= frame_samples:
        raise ValueError(f"{hop_samples=} must be an integer in 1..{frame_samples} (samples)")


# Compiled per-hop kernels. Each public call below makes one of these calls; the FFTs run inside
# them through rocket-fft's numba overloads of np.fft (float32 in -> complex64 out and back).


@numba.njit(cache=True, nogil=True)
def _push_hop(samples: np.ndarray, first: int, history: np.ndarray, state: np.ndarray, window: np.ndarray,
              windowed: np.ndarray) -> None:
    """Append one hop to the channel-major history and window the newest frame.

    ``history[c, end : end + hop] = samples[first : first + hop, c]`` (after moving the last
    ``frame - hop`` columns to the start when the history is full), then
    ``windowed[c, t] = window[t] history[c, end - frame + t]``. ``state = [end, n_frames, hop]``.
    """
    n_channels, n_columns = history.shape
    frame = windowed.shape[1]
    end, hop = state[0], state[2]
    if end + hop > n_columns:  # full: keep the last frame - hop samples (source and target disjoint)
        keep = frame - hop
        for c in range(n_channels):
            src = history[c, end - keep : end]
            dst = history[c, :keep]
            for t in range(keep):  # loops start at 0 on sliced rows: no negative-index checks
                dst[t] = src[t]
        end = keep
    # Transpose in tiles of 128 samples: one pass per channel over a tile that stays in L1
    # (a whole-block pass per channel at 16 x 1024 ran 2x slower).
    flat = samples.reshape(samples.size)
    for t0 in range(0, hop, 128):
        n_t = min(128, hop - t0)
        for c in range(n_channels):
            row = history[c, end + t0 : end + t0 + n_t]
            src = flat[(first + t0) * n_channels + c :]
            for t in range(n_t):
                row[t] = src[t * n_channels]
    end += hop
    state[0] = end
    state[1] += 1
    for c in range(n_channels):
        seg = history[c, end - frame : end]
        out = windowed[c]
        for t in range(frame):
            out[t] = seg[t] * window[t]


@numba.njit(numba.boolean(numba.float32[:, ::1], numba.float32[:, ::1], numba.int64[::1], numba.float32[::1],
                          numba.float32[:, ::1], numba.complex64[:, ::1]), cache=True, nogil=True)
def _stft_process(block: np.ndarray, history: np.ndarray, state: np.ndarray, window: np.ndarray,
                  windowed: np.ndarray, out: np.ndarray) -> bool:
    """One hop: :func:`_push_hop` then ``out = rfft(windowed)`` (n_channels, n_bins), complex64.

    Compiled for exactly these types (the caller converts anything else). Returns False, changing
    nothing, when ``block`` is not (hop, n_channels).
    """
    if block.shape[0] != state[2] or block.shape[1] != history.shape[0]:
        return False
    # borrowed (estimators.numba_tools): no reference-count updates for the views and calls below
    block, history, state, window = borrowed(block), borrowed(history), borrowed(state), borrowed(window)
    windowed, out = borrowed(windowed), borrowed(out)
    _push_hop(block, 0, history, state, window, windowed)
    np.fft.rfft(windowed, windowed.shape[1], -1, None, out)
    return True


@numba.njit(cache=True, nogil=True)
def _stft_process_many(blocks: np.ndarray, history: np.ndarray, state: np.ndarray, window: np.ndarray,
                       windowed: np.ndarray) -> np.ndarray:
    """``n_frames`` hops of :func:`_stft_process`, shape (n_frames, n_channels, n_bins), complex64.

    Each frame goes through the same window product and the same ``(n_channels, frame)`` rfft as
    the single hop, so the spectra are bit-identical to hop-by-hop calls.
    """
    hop = state[2]
    n_frames = blocks.shape[0] // hop
    out = np.empty((n_frames, windowed.shape[0], windowed.shape[1] // 2 + 1), np.complex64)
    for k in range(n_frames):
        _push_hop(blocks, k * hop, history, state, window, windowed)
        out[k] = np.fft.rfft(windowed)
    return out


@numba.njit(cache=True, nogil=True)
def _scale(x: np.ndarray, w: np.ndarray, out: np.ndarray) -> None:
    """``out[t] = x[t] w[t]`` for ``t < len(x)``."""
    for t in range(x.shape[0]):
        out[t] = x[t] * w[t]


@numba.njit(cache=True, nogil=True)
def _multiply_add(x: np.ndarray, w: np.ndarray, acc: np.ndarray) -> None:
    """``acc[t] += x[t] w[t]`` for ``t < len(x)``."""
    for t in range(x.shape[0]):
        acc[t] = acc[t] + x[t] * w[t]


@numba.njit(cache=True, nogil=True)
def _overlap_add(frame: np.ndarray, ola: np.ndarray, state: np.ndarray, out: np.ndarray) -> None:
    """Weighted overlap-add of one frame, ``out`` = the next ``hop`` finished samples.

    ``ola = [w_s (n) | accumulator (2 n)]`` and ``state[0] = p``: the frame lands on accumulator
    samples ``[p, p + n)``, of which the first ``n - hop`` hold the overlap-added earlier frames
    and the rest are fresh (no earlier frame reaches them); ``acc[p + t] += w_s[t] frame[t]``,
    ``out = acc[p : p + hop]``, then ``p += hop``. The live part moves back to the start once
    ``p > n`` (every ``n / hop`` frames) instead of shifting the accumulator every frame.
    """
    n = frame.shape[0]
    hop = out.shape[0]
    live = n - hop
    window = ola[:n]
    acc = ola[n:]
    p = state[0]
    if p + n > acc.shape[0]:  # p > n >= live: source and target disjoint
        src = acc[p : p + live]
        for t in range(live):
            acc[t] = src[t]
        p = 0
    a = acc[p : p + n]
    # Four ranges of t, each loop over a slice from 0 (no negative-index checks, vectorised):
    # [0, min(hop, live)) and [min(hop, live), hop) finish, [hop, live) accumulates, the rest is fresh.
    n_done_live = min(hop, live)
    for t in range(n_done_live):
        out[t] = a[t] + frame[t] * window[t]
    _scale(frame[n_done_live:hop], window[n_done_live:hop], out[n_done_live:])
    if live > hop:
        _multiply_add(frame[hop:live], window[hop:live], a[hop:live])
    start = max(hop, live)
    _scale(frame[start:], window[start:], a[start:])
    state[0] = p + hop


@numba.njit(cache=True, nogil=True)
def _synthesise(spectrum: np.ndarray, ola: np.ndarray, state: np.ndarray, out: np.ndarray) -> None:
    """``irfft`` of one frame then :func:`_overlap_add`: the next ``hop = state[1]`` samples into ``out``."""
    n = ola.shape[0] // 3
    _overlap_add(np.fft.irfft(spectrum, n), ola, state, out)


@numba.njit(cache=True, nogil=True)
def _istft_process(spectrum: np.ndarray, ola: np.ndarray, state: np.ndarray) -> np.ndarray:
    """:func:`_synthesise` into a new array of ``hop = state[1]`` samples, float32."""
    out = np.empty(state[1], np.float32)
    _synthesise(spectrum, ola, state, out)
    return out


@numba.njit(cache=True, nogil=True)
def _istft_many(spectra: np.ndarray, window: np.ndarray, hop: int) -> np.ndarray:
    """:func:`_istft_process` over ``spectra`` (n_channels, n_frames, n_bins) from a cleared state,
    per channel; returns (n_channels, n_frames * hop), float32, bit-identical to the streaming calls."""
    n_channels, n_frames, _ = spectra.shape
    n = window.shape[0]
    ola = np.zeros(3 * n, np.float32)
    ola[:n] = window
    state = np.zeros(2, np.int64)
    out = np.empty((n_channels, n_frames * hop), np.float32)
    for c in range(n_channels):
        ola[n:] = 0.0
        state[0] = 0
        for k in range(n_frames):
            _synthesise(spectra[c, k], ola, state, out[c, k * hop : (k + 1) * hop])
    return out


class StreamingStft:
    """Streaming short-time Fourier analysis, one hop at a time.

    Parameters
    ----------
    n_channels : int
        Number of channels.
    frame_samples : int
        Frame (FFT) length in samples.
    hop_samples : int
        Hop in samples, ``1 <= hop_samples <= frame_samples``.
    window : str or ndarray, shape (frame_samples,), optional
        Analysis window (see :func:`analysis_window`), periodic Hann by default.

    Attributes
    ----------
    analysis_window : ndarray, shape (frame_samples,), float32
    frame_samples, hop_samples, n_channels, n_bins : int
    n_frames : int
        Frames produced since construction or the last :meth:`reset`.
    """

    def __init__(
        self,
        n_channels: int,
        *,
        frame_samples: int,
        hop_samples: int,
        window: str | np.ndarray = "hann",
    ) -> None:
        if int(n_channels) != n_channels or n_channels < 1:
            raise ValueError(f"{n_channels=} must be an integer >= 1")
        _check_frame_hop(frame_samples, hop_samples)
        self.n_channels = int(n_channels)
        self.frame_samples = int(frame_samples)
        self.hop_samples = int(hop_samples)
        self.n_bins = self.frame_samples // 2 + 1
        self.analysis_window = analysis_window(window, self.frame_samples)
        # Channel-major history (n_channels, 2 * frame_samples): a hop appends its samples after
        # the previous ones and the frame is the last frame_samples columns before `end`, so a hop
        # writes hop_samples columns instead of shifting the whole frame; the last frame - hop
        # samples move back to the start only when the buffer is full (once every ~frame / hop
        # hops). Channel-major rows let the window product and the rfft run along contiguous rows.
        self._history = np.zeros((self.n_channels, 2 * self.frame_samples), dtype=np.float32)
        self._windowed = np.empty((self.n_channels, self.frame_samples), dtype=np.float32)
        self._state = np.array([self.frame_samples, 0, self.hop_samples], dtype=np.int64)  # end, n_frames, hop
        self._block_shape = (self.hop_samples, self.n_channels)
        self._spectra_shape = (self.n_channels, self.n_bins)
        self._kernel_args = (self._history, self._state, self.analysis_window, self._windowed)  # reset() keeps them

    @property
    def n_frames(self) -> int:
        """Frames produced since construction or the last :meth:`reset`."""
        return int(self._state[1])

    def reset(self) -> None:
        """Clear the analysis buffer (back to zeros) and the frame counter."""
        self._history.fill(0.0)
        self._state[:2] = (self.frame_samples, 0)

    def process(self, block: np.ndarray) -> np.ndarray:
        """Push one hop of new samples and return the spectrum of the latest frame.

        Parameters
        ----------
        block : ndarray, shape (hop_samples, n_channels), float32
            Exactly ``hop_samples`` new samples per channel (a 1-D block is accepted when
            ``n_channels == 1``). Non-finite samples pass through (they are flagged downstream).

        Returns
        -------
        ndarray, shape (n_bins, n_channels), complex64
            ``rfft(analysis_window * x[(k+1) hop - frame : (k+1) hop])`` for block ``k``. A new
            array, returned as the transpose of a C-contiguous ``(n_channels, n_bins)`` array:
            ``spectra.T`` is the channel-major layout in which :class:`estimators.GccPhat` and
            :class:`beamform.DelayAndSum` work without a copy.
        """
        out = np.empty(self._spectra_shape, np.complex64)
        # The kernel is compiled for 2-D C-contiguous writeable float32 blocks (flags.carray); anything
        # else is converted (and shape-checked) first, here rather than by a failed call (numba takes
        # ~70 us to word its TypeError). The kernel checks the shape.
        try:
            usual = block.dtype is _F32 and block.ndim == 2 and block.flags.carray
        except AttributeError:  # not an array
            usual = False
        if not usual:
            block = self._as_samples(block, single_hop=True)
        ok = _stft_process(block, *self._kernel_args, out)
        if not ok:
            self._as_samples(block, single_hop=True)  # raises the shape error
            raise AssertionError("_stft_process rejected a block that _as_samples accepts")
        return out.T

    def process_many(self, blocks: np.ndarray) -> np.ndarray:
        """Push ``n_frames`` hops at once; equal to ``n_frames`` calls of :meth:`process`.

        One compiled call for all the hops, for replay, where many hops are available at once. Each
        frame goes through the same window product and rfft as in :meth:`process`, so the results
        are bit-identical to the streaming calls and the state afterwards is the same (both can be
        mixed). The spectra of all hops are returned at once (``8 * n_frames * n_channels *
        n_bins`` bytes): feed long recordings in chunks (e.g. one second of hops).

        Parameters
        ----------
        blocks : ndarray, shape (n_frames * hop_samples, n_channels), float32
            Consecutive new samples (1-D when ``n_channels == 1``); the length must be a multiple
            of ``hop_samples``.

        Returns
        -------
        ndarray, shape (n_frames, n_bins, n_channels), complex64
            Row ``k`` is what :meth:`process` returns for the ``k``-th hop; each row's transpose
            is C-contiguous, the layout :meth:`estimators.GccPhat.process_many` takes.
        """
        x = self._as_samples(blocks, single_hop=False)
        if x.shape[0] == 0:
            return np.empty((0, self.n_bins, self.n_channels), np.complex64)
        spectra = _stft_process_many(x, self._history, self._state, self.analysis_window, self._windowed)
        return spectra.transpose(0, 2, 1)

    def _as_samples(self, samples: np.ndarray, *, single_hop: bool) -> np.ndarray:
        """``samples`` as a C-contiguous writeable float32 (n_samples, n_channels) array, shape checked."""
        x = np.asarray(samples)
        if x.ndim == 1 and self.n_channels == 1:
            x = x[:, None]
        hop = self.hop_samples
        if single_hop:
            if x.shape != self._block_shape:
                raise ValueError(
                    f"block.shape={x.shape} must be ({hop}, {self.n_channels}) = (hop_samples, n_channels)"
                )
        elif x.ndim != 2 or x.shape[1] != self.n_channels or x.shape[0] % hop:
            raise ValueError(
                f"blocks.shape={x.shape} must be (n_frames * {hop}, {self.n_channels}) = "
                "(n_frames * hop_samples, n_channels)"
            )
        if x.dtype == _F32 and x.flags.carray:
            return x
        return np.array(x, dtype=np.float32, order="C")


class StreamingIstft:
    """Streaming weighted overlap-add synthesis, one frame in, one hop out.

    Parameters
    ----------
    frame_samples : int
        Frame (FFT) length in samples.
    hop_samples : int
        Hop in samples, ``1 <= hop_samples <= frame_samples``.
    analysis_window : ndarray, shape (frame_samples,)
        The window used by the analysis (:attr:`StreamingStft.analysis_window`); the synthesis
        window is its canonical dual (:func:`dual_window`).

    Attributes
    ----------
    synthesis_window : ndarray, shape (frame_samples,), float32
    latency_samples : int
        ``frame_samples - hop_samples``: analysis then synthesis returns the input delayed by this.
    """

    def __init__(self, *, frame_samples: int, hop_samples: int, analysis_window: np.ndarray) -> None:
        _check_frame_hop(frame_samples, hop_samples)
        w = np.asarray(analysis_window)
        if w.shape != (frame_samples,):
            raise ValueError(f"{w.shape=} of analysis_window must be ({frame_samples},) = (frame_samples,)")
        self.frame_samples = int(frame_samples)
        self.hop_samples = int(hop_samples)
        self.n_bins = self.frame_samples // 2 + 1
        self.latency_samples = self.frame_samples - self.hop_samples
        # [synthesis window (frame) | accumulator (2 frame)] and [accumulator position, hop]: see
        # _overlap_add. One array each, as the kernels take them.
        n = self.frame_samples
        self._ola = np.zeros(3 * n, dtype=np.float32)
        self._ola[:n] = dual_window(w, hop_samples=self.hop_samples)
        self.synthesis_window = self._ola[:n]
        self._state = np.array([0, self.hop_samples], dtype=np.int64)
        self._spectrum_shape = (self.n_bins,)

    def reset(self) -> None:
        """Clear the overlap-add accumulator."""
        self._ola[self.frame_samples :] = 0.0
        self._state[0] = 0

    def process(self, spectrum: np.ndarray) -> np.ndarray:
        """Overlap-add one frame and return the next ``hop_samples`` finished output samples.

        Parameters
        ----------
        spectrum : ndarray, shape (n_bins,), complex
            One-sided spectrum of one frame (``n_bins = frame_samples // 2 + 1``), computed in
            complex64.

        Returns
        -------
        ndarray, shape (hop_samples,), float32
            A new array.
        """
        if not (type(spectrum) is np.ndarray and spectrum.dtype == _C64 and spectrum.flags.carray):
            spectrum = np.array(spectrum, dtype=np.complex64, order="C")
        if spectrum.shape != self._spectrum_shape:
            raise ValueError(f"{spectrum.shape=} must be ({self.n_bins},) = (n_bins,)")
        return _istft_process(spectrum, self._ola, self._state)


def stft(
    audio: np.ndarray,
    *,
    frame_samples: int,
    hop_samples: int,
    window: str | np.ndarray = "hann",
) -> np.ndarray:
    """Batch STFT with the streaming conventions of :class:`StreamingStft`.

    Parameters
    ----------
    audio : ndarray, shape (n_samples, n_channels)
        Input; ``n_samples`` is truncated to a multiple of ``hop_samples``.
    frame_samples, hop_samples : int
        Frame and hop in samples.
    window : str or ndarray, shape (frame_samples,), optional

    Returns
    -------
    ndarray, shape (n_frames, n_bins, n_channels), complex64
        Frame ``k`` covers samples ``[(k + 1) hop - frame, (k + 1) hop)`` (zeros before 0),
        ``n_frames = n_samples // hop_samples``; equal to :class:`StreamingStft` run hop by hop
        (it is :meth:`StreamingStft.process_many`), in the same layout.
    """
    _check_frame_hop(frame_samples, hop_samples)
    x = np.asarray(audio, dtype=np.float32)
    if x.ndim == 1:
        x = x[:, None]
    n_frames = x.shape[0] // hop_samples
    # The streaming analysis run on all hops at once: the same frames, bit for bit.
    analysis = StreamingStft(x.shape[1], frame_samples=frame_samples, hop_samples=hop_samples, window=window)
    return analysis.process_many(x[: n_frames * hop_samples])


def istft(
    spectra: np.ndarray,
    *,
    frame_samples: int,
    hop_samples: int,
    window: str | np.ndarray = "hann",
) -> np.ndarray:
    """Batch WOLA synthesis with the streaming conventions of :class:`StreamingIstft`.

    Parameters
    ----------
    spectra : ndarray, shape (n_frames, n_bins) or (n_frames, n_bins, n_channels)
        Computed in complex64.
    frame_samples, hop_samples : int
    window : str or ndarray, shape (frame_samples,), optional
        The analysis window; synthesis uses its dual.

    Returns
    -------
    ndarray, shape (n_frames * hop_samples,) or (n_frames * hop_samples, n_channels), float32
        The same samples :class:`StreamingIstft` emits (the same compiled frame by frame
        synthesis, bit for bit), i.e. delayed by ``frame_samples - hop_samples`` with respect to
        the analysed input.
    """
    _check_frame_hop(frame_samples, hop_samples)
    S = np.asarray(spectra)
    squeeze = S.ndim == 2
    if squeeze:
        S = S[:, :, None]
    n_frames, n_bins, n_ch = S.shape
    if n_bins != frame_samples // 2 + 1:
        raise ValueError(f"{n_bins=} must be frame_samples // 2 + 1 = {frame_samples // 2 + 1}")
    ws = dual_window(analysis_window(window, frame_samples), hop_samples=hop_samples)
    channel_major = np.array(S.transpose(2, 0, 1), dtype=np.complex64, order="C")  # (n_ch, n_frames, n_bins)
    y = _istft_many(channel_major, ws, int(hop_samples))  # (n_ch, n_frames * hop)
    return y[0] if squeeze else np.ascontiguousarray(y.T)
