"""Streaming STFT analysis and weighted-overlap-add (WOLA) synthesis.

Conventions (fixed here, used by :mod:`beamform.das`)
-----------------------------------------------------
- Audio is time-major, ``(n_samples, n_channels)``, float32.
- One call consumes exactly ``hop_samples`` new samples. The analysis buffer starts at zeros, so the
  frame produced after block ``k`` (0-based) covers input samples
  ``[(k + 1) * hop - frame, (k + 1) * hop)``.
- Spectra are ``scipy.fft.rfft(analysis_window * frame)`` without normalisation,
  ``n_bins = frame_samples // 2 + 1`` and bin ``b`` has angular frequency
  ``omega_b = 2 pi b sample_rate_hz / frame_samples`` (rad/s).
- Synthesis uses the canonical dual window of the analysis window,

  ``w_s[n] = w_a[n] / sum_k w_a[n + k hop]^2``  (sum over all integers ``k``, ``w_a = 0`` outside),

  so that ``sum_m w_s[n - m hop] w_a[n - m hop] = 1`` for every ``n`` and analysis followed by
  synthesis without modification is the identity delayed by
  ``latency_samples = frame_samples - hop_samples`` (Hann at 75 % overlap gives ``w_s = w_a / 1.5``).
  This holds for any ``hop_samples <= frame_samples`` for which the denominator never vanishes.

The pure functions :func:`stft` and :func:`istft` are the batch (vectorised) counterparts of
:class:`StreamingStft` and :class:`StreamingIstft` and produce the same frames and samples.
"""
from __future__ import annotations

import numpy as np
import scipy.fft
import scipy.signal

__all__ = [
    "StreamingStft",
    "StreamingIstft",
    "analysis_window",
    "dual_window",
    "stft",
    "istft",
]


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
    return np.ascontiguousarray(w, dtype=np.float32)


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
        # the previous ones and the frame is the last frame_samples columns before self._end, so
        # a hop writes hop_samples columns instead of shifting the whole frame; the last
        # frame - hop samples are moved back to the start only when the buffer is full (once
        # every ~frame / hop hops): at 4096 x 8 the shift cost ~7 us. Channel-major rows also let
        # the window product run along contiguous rows: on the time-major (frame, n_channels)
        # layout it looped over rows of n_channels values (16 instead of 7.5 us at 4096 x 8).
        # The rfft costs the same along either axis and gives the same values.
        self._history = np.zeros((self.n_channels, 2 * self.frame_samples), dtype=np.float32)
        self._end = self.frame_samples
        self._windowed = np.empty((self.n_channels, self.frame_samples), dtype=np.float32)
        self.n_frames = 0

    def reset(self) -> None:
        """Clear the analysis buffer (back to zeros) and the frame counter."""
        self._history.fill(0.0)
        self._end = self.frame_samples
        self.n_frames = 0

    def process(self, block: np.ndarray) -> np.ndarray:
        """Push one hop of new samples and return the spectrum of the latest frame.

        Parameters
        ----------
        block : ndarray, shape (hop_samples, n_channels), float32
            Exactly ``hop_samples`` new samples per channel (a 1-D block is accepted when
            ``n_channels == 1``).

        Returns
        -------
        ndarray, shape (n_bins, n_channels), complex64
            ``rfft(analysis_window * x[(k+1) hop - frame : (k+1) hop])`` for block ``k``. A new
            array, returned as the transpose of a C-contiguous ``(n_channels, n_bins)`` array:
            ``spectra.T`` is the channel-major layout in which :class:`estimators.GccPhat` and
            :class:`beamform.DelayAndSum` work without a copy.
        """
        block = np.asarray(block)
        if block.ndim == 1 and self.n_channels == 1:
            block = block[:, None]
        if block.shape != (self.hop_samples, self.n_channels):
            raise ValueError(
                f"{block.shape=} must be ({self.hop_samples}, {self.n_channels}) = "
                "(hop_samples, n_channels)"
            )
        hop, frame = self.hop_samples, self.frame_samples
        history = self._history
        end = self._end
        if end + hop > history.shape[1]:  # full: keep the last frame - hop samples at the start
            keep = frame - hop
            history[:, :keep] = history[:, end - keep : end]
            end = keep
        history[:, end : end + hop] = block.T
        end += hop
        self._end = end
        with np.errstate(invalid="ignore", over="ignore"):  # inf/NaN input is flagged downstream
            np.multiply(history[:, end - frame : end], self.analysis_window, out=self._windowed)
        self.n_frames += 1
        return scipy.fft.rfft(self._windowed, axis=-1, workers=1).T

    def process_many(self, blocks: np.ndarray) -> np.ndarray:
        """Push ``n_frames`` hops at once; equal to ``n_frames`` calls of :meth:`process`.

        One window product and one ``rfft`` for all the frames instead of one per hop, for
        replay, where many hops are available at once. The results are bit-identical to the
        streaming calls and the state afterwards is the same, so both can be mixed. It holds the
        windowed frames and the spectra of all hops at once (about ``12 * n_frames * n_channels *
        frame_samples`` bytes): feed long recordings in chunks (e.g. one second of hops).

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
        x = np.asarray(blocks)
        if x.ndim == 1 and self.n_channels == 1:
            x = x[:, None]
        hop, frame = self.hop_samples, self.frame_samples
        if x.ndim != 2 or x.shape[1] != self.n_channels or x.shape[0] % hop:
            raise ValueError(
                f"blocks.shape={x.shape} must be (n_frames * {hop}, {self.n_channels}) = "
                "(n_frames * hop_samples, n_channels)"
            )
        n_frames = x.shape[0] // hop
        if n_frames == 0:
            return np.empty((0, self.n_bins, self.n_channels), np.complex64)
        keep = frame - hop
        end = self._end
        # The last frame - hop samples of the history, then the new ones: every frame is a window
        # of this sequence, frame k starting at k * hop.
        sequence = np.empty((self.n_channels, keep + x.shape[0]), np.float32)
        sequence[:, :keep] = self._history[:, end - keep : end]
        sequence[:, keep:] = x.T
        frames = np.lib.stride_tricks.sliding_window_view(sequence, frame, axis=1)[:, ::hop]  # (M, K, frame)
        windowed = np.empty((n_frames, self.n_channels, frame), np.float32)
        with np.errstate(invalid="ignore", over="ignore"):  # inf/NaN input is flagged downstream
            np.multiply(frames.transpose(1, 0, 2), self.analysis_window, out=windowed)
        spectra = scipy.fft.rfft(windowed, axis=-1, workers=1)  # (K, M, n_bins)
        self._history[:, :frame] = sequence[:, -frame:]
        self._end = frame
        self.n_frames += n_frames
        return spectra.transpose(0, 2, 1)


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
        self.synthesis_window = dual_window(w, hop_samples=self.hop_samples)
        self.latency_samples = self.frame_samples - self.hop_samples
        self._accumulator = np.zeros(self.frame_samples, dtype=np.float32)

    def reset(self) -> None:
        """Clear the overlap-add accumulator."""
        self._accumulator.fill(0.0)

    def process(self, spectrum: np.ndarray) -> np.ndarray:
        """Overlap-add one frame and return the next ``hop_samples`` finished output samples.

        Parameters
        ----------
        spectrum : ndarray, shape (n_bins,), complex
            One-sided spectrum of one frame (``n_bins = frame_samples // 2 + 1``).

        Returns
        -------
        ndarray, shape (hop_samples,), float32
        """
        if spectrum.shape != (self.n_bins,):
            raise ValueError(f"{spectrum.shape=} must be ({self.n_bins},) = (n_bins,)")
        frame = scipy.fft.irfft(spectrum, n=self.frame_samples, workers=1)
        acc = self._accumulator
        acc += np.multiply(frame, self.synthesis_window, out=frame)  # in place: frame is ours
        hop = self.hop_samples
        out = acc[:hop].copy()
        acc[:-hop] = acc[hop:]
        acc[-hop:] = 0.0
        return out


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
    frame_samples, hop_samples : int
    window : str or ndarray, shape (frame_samples,), optional
        The analysis window; synthesis uses its dual.

    Returns
    -------
    ndarray, shape (n_frames * hop_samples,) or (n_frames * hop_samples, n_channels), float32
        The same samples :class:`StreamingIstft` emits, i.e. delayed by
        ``frame_samples - hop_samples`` with respect to the analysed input.
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
    frames = scipy.fft.irfft(S, n=frame_samples, axis=1, workers=1) * ws[None, :, None]
    n_out = n_frames * hop_samples
    # Output hop k is the first hop of the accumulator after frame k; frame k starts at k * hop.
    y = np.zeros((n_out + frame_samples, n_ch), dtype=np.float64)
    for m in range(-(-frame_samples // hop_samples)):
        seg = frames[:, m * hop_samples : (m + 1) * hop_samples]
        L = seg.shape[1]
        # frame k sample m*hop + j lands at output index (k + m) * hop + j.
        tgt = y[m * hop_samples : m * hop_samples + n_frames * hop_samples].reshape(n_frames, hop_samples, n_ch)
        tgt[:, :L] += seg
    y = y[:n_out].astype(np.float32)
    return y[:, 0] if squeeze else y
