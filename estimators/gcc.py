"""GCC-PHAT time differences of arrival over all microphone pairs, batched.

Implements TOA paper eqs. (4)-(6) for every pair ``(i, j)`` of :func:`estimators.conventions.pairs`
at once:

- eq. (4), PHAT weighting. ``G_ij = X_i X_j^* / |X_i X_j^*|`` equals ``U_i U_j^*`` with the
  per-channel unit-magnitude spectrum ``U_i = X_i / (|X_i| + eps_i)``, so the division is done once
  per channel, not once per pair. ``eps_i = 1e-6 * max_k |X_i(k)|`` (plus the smallest positive
  float32) keeps empty bins at 0 instead of NaN.
- eq. (5), ``r_ij = irfft(G_ij)``: one batched inverse real FFT over all pairs (complex64 ->
  float32, ``scipy.fft``, ``workers=1``).
- eq. (6), ``tdoa_ij = argmax r_ij``, searched only over ``|lag| <= max_lag_samples`` with
  ``max_lag_samples = min(floor(max_tdoa_s * sample_rate_hz), n_fft // 2 - 1)``, then refined to a
  fraction of a sample with a three-point interpolator (see :class:`GccPhat`). No zero padding:
  the sinc interpolator is already unbiased to ~0.005 sample on a clean delay, and padding would
  multiply the inverse-FFT cost.

Sign: with ``x_i(t) = s(t - toa_i)`` the cross-spectrum is ``|S|^2 exp(-1j w (toa_i - toa_j))``,
whose inverse transform peaks at ``+(toa_i - toa_j)``. So ``tdoa_s[p] = toa_i - toa_j`` for
``p = (i, j)``, positive when channel ``i`` is delayed relative to channel ``j``, as fixed in
:mod:`estimators.conventions`.

Confidence is the height of the PHAT correlation peak, clipped to ``[0, 1]``: 1 for a pure circular
integer delay, lower with noise, reverberation, windowing and fractional delays. A channel that is
all zeros or contains a non-finite value gives its pairs ``tdoa_s = 0`` and ``confidence = 0``.

Cost per frame: ``n_pairs`` products of ``n_fft // 2 + 1`` complex64 bins, one batched ``irfft``
of ``n_pairs`` rows (the floor), and a copy of ``2 * max_lag_samples + 1`` lags per pair. Every
per-frame work array except the ``irfft`` output is preallocated, and the rest is a fixed number of
numpy calls (about 40 plus one per channel), whatever the number of pairs. Spectra laid out
channel-major (``spectra.T`` C-contiguous, as :class:`beamform.StreamingStft` returns them) are used
without a copy. :meth:`GccPhat.process_many` runs the same computation on many frames per call.
"""
from __future__ import annotations

import functools
import threading
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.fft
import scipy.signal

from .conventions import pairs

__all__ = ["GccPhat", "gcc_phat", "gcc_phat_spectra"]

Interpolation = Literal["sinc", "parabolic", "none"]

_TINY_F32 = float(np.finfo(np.float32).tiny)
# eq. (4): regulariser of the PHAT division, relative to the channel's largest bin magnitude.
_PHAT_REL_EPS = 1e-6


@dataclass(frozen=True)
class _Plan:
    """Read-only index arrays shared by every :class:`GccPhat` with the same configuration."""

    n_channels: int
    n_fft: int
    max_lag_samples: int
    pair_i: np.ndarray  # shape (n_pairs,), first channel of each pair
    pair_j: np.ndarray  # shape (n_pairs,), second channel of each pair
    # Row blocks: pairs (i, i+1..M-1) are rows block_start[i]:block_start[i+1].
    block_start: np.ndarray  # shape (n_channels,)


@functools.lru_cache(maxsize=64)
def _plan(n_channels: int, n_fft: int, max_lag_samples: int) -> _Plan:
    p = pairs(n_channels)
    counts = np.arange(n_channels - 1, -1, -1)  # pairs whose first channel is i
    block_start = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.intp)
    pair_i, pair_j = p[:, 0].copy(), p[:, 1].copy()
    for a in (pair_i, pair_j, block_start):
        a.flags.writeable = False
    return _Plan(n_channels, n_fft, max_lag_samples, pair_i, pair_j, block_start)


@functools.lru_cache(maxsize=16)
def _hann(n_samples: int) -> np.ndarray:
    w = scipy.signal.get_window("hann", n_samples, fftbins=True).astype(np.float32)
    w.flags.writeable = False
    return w


def _max_lag_samples(n_fft: int, sample_rate_hz: float, max_tdoa_s: float | None) -> int:
    # Lags must stay strictly below n_fft/2 so that +lag and -lag are distinct and both have
    # neighbours for the interpolation.
    limit = n_fft // 2 - 1
    if max_tdoa_s is None:
        return limit
    return int(min(np.floor(max_tdoa_s * sample_rate_hz + 1e-9), limit))


class _Work:
    """Preallocated work arrays for ``n_frames`` frames (one set per frame count in use).

    Reusing them saves the allocation and, for the large ones, the page faults of first touch:
    at 16 channels x 4096 one fresh ``(n_pairs, n_bins)`` buffer per call tripled the cost.
    """

    def __init__(self, plan: _Plan, n_frames: int, n_bins: int) -> None:
        m = plan.n_channels
        n_pairs = len(plan.pair_i)
        self.n_frames = n_frames
        self.mag = np.empty((n_frames, m, n_bins), np.float32)
        self.unit = np.empty((n_frames, m, n_bins), np.complex64)
        self.unit_conj = np.empty_like(self.unit)
        self.cross = np.empty((n_frames, n_pairs, n_bins), np.complex64)
        self.window = np.empty((n_frames * n_pairs, 2 * plan.max_lag_samples + 1), np.float32)
        self.rows = np.arange(n_frames * n_pairs)[:, None]  # row index of each correlation
        # Operands of G_ij = U_i U_j^*, one broadcast product per first channel i: pairs
        # (i, i+1..M-1) are rows block_start[i]:block_start[i + 1] of the cross spectra. The views
        # are made once (slicing three 3-D arrays per product cost ~0.5 us each time).
        self.cross_products = [
            (self.unit[:, i : i + 1], self.unit_conj[:, i + 1 :], self.cross[:, s : s + m - 1 - i])
            for i, s in enumerate(plan.block_start[: m - 1])
        ]


# Offsets of r[k-1], r[k], r[k+1] around the peak k, gathered in one indexing call.
_NEIGHBOURS = np.array([-1, 0, 1])
# Frames per process_many chunk: bounded so that the chunk's work arrays stay near 4 MiB.
_CHUNK_BYTES = 1 << 22


class GccPhat:
    """Batched GCC-PHAT for a fixed channel count and FFT size (TOA paper eqs. 4-6).

    Parameters
    ----------
    n_channels : int
        Number of channels ``M >= 2``; outputs have ``n_pairs = M * (M - 1) / 2`` entries in the order
        of :func:`estimators.conventions.pairs`.
    n_fft : int
        FFT length in samples (>= 4); spectra have ``n_fft // 2 + 1`` bins.
    sample_rate_hz : float
        Sample rate in hertz, > 0.
    max_tdoa_s : float or None
        Largest ``|tdoa|`` searched, in seconds (>= 0). ``None`` searches all lags below
        ``n_fft / 2``. The bound is rounded down to whole samples and also capped at
        ``n_fft // 2 - 1`` samples; interpolated outputs are clipped to it.
    interpolation : {"sinc", "parabolic", "none"}
        Sub-sample refinement of the integer peak ``k`` from its neighbours
        ``r[k-1], r[k], r[k+1]``:

        - ``"sinc"`` (default): the PHAT correlation of a pure delay ``k + d`` is
          ``sinc(n - k - d)``, whose neighbour ratio is ``r[k+1] / r[k] = d / (1 - d)``; hence
          ``d = r[k+1] / (r[k] + r[k+1])`` (or ``-r[k-1] / (r[k] + r[k-1])`` on the other side),
          clipped to ``[-0.5, 0.5]``. Unbiased for a full-band delay.
        - ``"parabolic"``: vertex of the parabola through the three points,
          ``d = (r[k-1] - r[k+1]) / (2 (r[k-1] - 2 r[k] + r[k+1]))``; biased towards integers by up
          to about 0.1 sample for PHAT peaks.
        - ``"none"``: integer lags.

    Notes
    -----
    The per-frame work uses preallocated buffers, so one instance must not be used from two threads
    at once; the module functions :func:`gcc_phat` and :func:`gcc_phat_spectra` keep one instance
    per thread and configuration and are thread-safe.
    """

    def __init__(
        self,
        n_channels: int,
        *,
        n_fft: int,
        sample_rate_hz: float,
        max_tdoa_s: float | None = None,
        interpolation: Interpolation = "sinc",
    ) -> None:
        if int(n_channels) != n_channels or n_channels < 2:
            raise ValueError(f"{n_channels=} must be an integer >= 2")
        if int(n_fft) != n_fft or n_fft < 4:
            raise ValueError(f"{n_fft=} must be an integer number of samples >= 4")
        if not np.isfinite(sample_rate_hz) or sample_rate_hz <= 0:
            raise ValueError(f"{sample_rate_hz=} must be a finite rate in Hz > 0")
        if max_tdoa_s is not None and (not np.isfinite(max_tdoa_s) or max_tdoa_s < 0):
            raise ValueError(f"{max_tdoa_s=} must be None or a finite time in s >= 0")
        if interpolation not in ("sinc", "parabolic", "none"):
            raise ValueError(f"{interpolation=} must be 'sinc', 'parabolic' or 'none'")
        self.n_channels = int(n_channels)
        self.n_fft = int(n_fft)
        self.n_bins = self.n_fft // 2 + 1
        self.n_pairs = self.n_channels * (self.n_channels - 1) // 2
        self.sample_rate_hz = float(sample_rate_hz)
        self.max_tdoa_s = max_tdoa_s
        self.interpolation: Interpolation = interpolation
        self.max_lag_samples = _max_lag_samples(self.n_fft, self.sample_rate_hz, max_tdoa_s)
        self._plan = _plan(self.n_channels, self.n_fft, self.max_lag_samples)
        self._work = {1: self._new_work(1)}
        per_frame = self.n_pairs * (8 * self.n_bins + 4 * self.n_fft)  # cross spectra + correlations
        self._chunk_frames = int(max(1, min(64, _CHUNK_BYTES // per_frame)))

    def _new_work(self, n_frames: int) -> _Work:
        return _Work(self._plan, n_frames, self.n_bins)

    def reset(self) -> None:
        """No state is carried between frames; present for the common stage interface."""

    def process(self, spectra: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """TDOA and confidence of every pair from one frame's spectra.

        Parameters
        ----------
        spectra : ndarray, shape (n_bins, n_channels), complex
            ``rfft`` of each channel's windowed frame along axis 0, ``n_bins = n_fft // 2 + 1``.
            Fastest as complex64 with ``spectra.T`` C-contiguous (the layout of
            :meth:`beamform.StreamingStft.process`); any other layout is copied first.

        Returns
        -------
        tdoa_s : ndarray, shape (n_pairs,), float64
            ``toa_i - toa_j`` in seconds for pair ``(i, j)``.
        confidence : ndarray, shape (n_pairs,), float64
            PHAT peak height in ``[0, 1]``; 0 for pairs with a silent or non-finite channel.
        """
        spectra = np.asarray(spectra)
        if spectra.shape != (self.n_bins, self.n_channels):
            raise ValueError(
                f"spectra.shape={spectra.shape} must be (n_bins, n_channels)="
                f"{(self.n_bins, self.n_channels)}"
            )
        return self._process_channel_major(spectra.T)

    def process_many(self, spectra: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`process` on many frames at once (e.g. a replay with several hops available).

        The result equals ``n_frames`` calls of :meth:`process` (no state is carried between
        frames); the numpy and FFT call overhead is paid once per chunk of frames instead of once
        per frame.

        Parameters
        ----------
        spectra : ndarray, shape (n_frames, n_bins, n_channels), complex
            One frame's spectra per row, as :meth:`process` takes them (e.g. the output of
            :meth:`beamform.StreamingStft.process_many`, whose per-frame transposes are
            C-contiguous).

        Returns
        -------
        tdoa_s : ndarray, shape (n_frames, n_pairs), float64
        confidence : ndarray, shape (n_frames, n_pairs), float64
        """
        spectra = np.asarray(spectra)
        if spectra.ndim != 3 or spectra.shape[1:] != (self.n_bins, self.n_channels):
            raise ValueError(
                f"spectra.shape={spectra.shape} must be (n_frames, n_bins, n_channels)="
                f"(n_frames, {self.n_bins}, {self.n_channels})"
            )
        n_frames = spectra.shape[0]
        tdoa_s = np.empty((n_frames, self.n_pairs))
        confidence = np.empty((n_frames, self.n_pairs))
        chunk = self._chunk_frames
        for start in range(0, n_frames, chunk):
            stop = min(n_frames, start + chunk)
            k = stop - start
            work = self._work.get(k)
            if work is None:  # keep the full-chunk arrays; a shorter last chunk gets temporary ones
                work = self._new_work(k)
                if k == chunk:
                    self._work[k] = work
            tdoa_s[start:stop], confidence[start:stop] = self._run(spectra[start:stop].transpose(0, 2, 1), work)
        return tdoa_s, confidence

    def _process_channel_major(self, spec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`process` on spectra laid out ``(n_channels, n_bins)``."""
        tdoa_s, confidence = self._run(spec[None], self._work[1])
        return tdoa_s[0], confidence[0]

    def _run(self, spec: np.ndarray, work: _Work) -> tuple[np.ndarray, np.ndarray]:
        """Eqs. (4)-(6) for ``K`` frames of spectra laid out ``(K, n_channels, n_bins)``.

        Returns ``(tdoa_s, confidence)``, each of shape ``(K, n_pairs)``, float64.
        """
        plan = self._plan
        n_fft = self.n_fft
        L = self.max_lag_samples
        n_frames = spec.shape[0]
        spec = np.ascontiguousarray(spec, dtype=np.complex64)  # no copy for StreamingStft's layout
        mag = np.abs(spec, out=work.mag)  # (K, M, n_bins) float32
        peak_mag = mag.max(axis=2)  # a NaN propagates (max does not warn on NaN)
        # Fast path: every channel finite and not silent. NaN-safe: a NaN peak makes the minimum
        # NaN (the comparison is False), an inf one the maximum. Two reductions instead of four
        # numpy calls; the exact per-channel test only runs when this fails.
        all_valid = bool(peak_mag.min() > 0.0) and bool(peak_mag.max() < np.inf)
        if all_valid:
            valid = None
            eps = _PHAT_REL_EPS * peak_mag + _TINY_F32  # float32 (Python scalars are weak)
        else:
            valid = np.isfinite(peak_mag) & (peak_mag > 0)
            eps = (_PHAT_REL_EPS * np.where(valid, peak_mag, 0) + _TINY_F32).astype(np.float32)
        # eq. (4), PHAT per channel: U_i = X_i / (|X_i| + eps_i); reciprocal then product is ~4x
        # faster than a complex-by-real division.
        np.add(mag, eps[:, :, None], out=mag)
        np.reciprocal(mag, out=mag)
        unit = work.unit
        if valid is None:  # finite spectra times finite weights: nothing to silence
            np.multiply(spec, mag, out=unit)
        else:
            with np.errstate(invalid="ignore"):
                np.multiply(spec, mag, out=unit)
            unit[~valid] = 0
        np.conjugate(unit, out=work.unit_conj)
        # G_ij = U_i U_j^* for all pairs. One broadcast product per first channel i (M-1 calls, not
        # one per pair) into a preallocated buffer: measured 2-16x faster than gathering
        # U[pair_i] * conj(U[pair_j]) through (n_pairs, n_bins) index arrays at 16 ch x 4096.
        for first, others, out in work.cross_products:
            np.multiply(first, others, out=out)
        # eq. (5): one batched inverse FFT; float32 out for complex64 in. This is the floor of the
        # per-frame cost (n_pairs inverse FFTs of n_fft points).
        corr = scipy.fft.irfft(work.cross, n=n_fft, axis=-1, workers=1).reshape(n_frames * self.n_pairs, n_fft)
        # eq. (6): peak over lags -L..L. Two contiguous slices copied into a buffer (lags -L..-1
        # then 0..L) beat a fancy-index gather by ~20x; argmax then runs on contiguous rows
        # (numpy's argmax would copy a strided view anyway).
        window = work.window
        np.concatenate((corr[:, n_fft - L :], corr[:, : L + 1]), axis=1, out=window)
        lag_int = np.argmax(window, axis=1)
        lag_int -= L
        # r[k-1], r[k], r[k+1] of every row in one gather; a negative lag indexes from the end of
        # its row, which is lag mod n_fft (|lag| <= L + 1 <= n_fft / 2).
        r = corr[work.rows, lag_int[:, None] + _NEIGHBOURS].astype(np.float64)
        rm, r0, rp = r[:, 0], r[:, 1], r[:, 2]
        if self.interpolation == "sinc":
            lag = _sinc_offset(rm, r0, rp)
        elif self.interpolation == "parabolic":
            lag = _parabolic_offset(rm, r0, rp)
        else:
            lag = np.zeros(len(r))
        lag += lag_int
        # np.minimum/np.maximum with out= instead of np.clip: same values, ~3 us less per call.
        np.maximum(lag, -L, out=lag)
        np.minimum(lag, L, out=lag)
        confidence = np.maximum(r0, 0.0)
        np.minimum(confidence, 1.0, out=confidence)
        if valid is not None:
            pair_ok = (valid[:, plan.pair_i] & valid[:, plan.pair_j]).reshape(-1)
            lag[~pair_ok] = 0.0
            confidence[~pair_ok] = 0.0
        lag /= self.sample_rate_hz
        return lag.reshape(n_frames, self.n_pairs), confidence.reshape(n_frames, self.n_pairs)


_local = threading.local()


def _instance(
    n_channels: int,
    n_fft: int,
    sample_rate_hz: float,
    max_tdoa_s: float | None,
    interpolation: Interpolation,
) -> GccPhat:
    """A :class:`GccPhat` cached per thread and configuration.

    Reusing the instance keeps its buffers warm: a fresh ``(n_pairs, n_bins)`` buffer per call
    tripled the cost at 16 channels x 4096 (page faults on first touch).
    """
    cache = getattr(_local, "cache", None)
    if cache is None:
        cache = _local.cache = {}
    key = (n_channels, n_fft, sample_rate_hz, max_tdoa_s, interpolation)
    gcc = cache.get(key)
    if gcc is None:
        if len(cache) >= 8:
            cache.pop(next(iter(cache)))
        gcc = cache[key] = GccPhat(
            n_channels,
            n_fft=n_fft,
            sample_rate_hz=sample_rate_hz,
            max_tdoa_s=max_tdoa_s,
            interpolation=interpolation,
        )
    return gcc


def _sinc_offset(rm: np.ndarray, r0: np.ndarray, rp: np.ndarray) -> np.ndarray:
    """Fractional peak offset in samples for a sinc-shaped peak, in ``[-0.5, 0.5]`` (a new array).

    For ``r[n] = sinc(n - d)``, ``r[1] / r[0] = d / (1 - d)`` so ``d = r[1] / (r[0] + r[1])``,
    taken on the side of the larger neighbour (the right one on a tie); 0 where ``r[0] + r[1] <= 0``.
    """
    # Written with out=/where= instead of np.where/np.clip (each a few us on small arrays):
    # max(rp, rm) is the side chosen by rp >= rm, and copysign by rp - rm (+0 on a tie) puts it
    # on that side.
    side = np.maximum(rp, rm)
    den = r0 + side
    d = np.zeros(den.shape)
    np.divide(side, den, out=d, where=den > 0)
    np.maximum(d, 0.0, out=d)
    np.minimum(d, 0.5, out=d)
    return np.copysign(d, rp - rm, out=d)


def _parabolic_offset(rm: np.ndarray, r0: np.ndarray, rp: np.ndarray) -> np.ndarray:
    """Vertex offset in samples of the parabola through ``(-1, rm), (0, r0), (1, rp)`` (a new array)."""
    den = rm - 2.0 * r0 + rp
    d = np.zeros(den.shape)
    np.divide(0.5 * (rm - rp), den, out=d, where=den < 0)
    np.maximum(d, -0.5, out=d)
    return np.minimum(d, 0.5, out=d)


def gcc_phat_spectra(
    spectra: np.ndarray,
    *,
    n_fft: int,
    sample_rate_hz: float,
    max_tdoa_s: float | None = None,
    interpolation: Interpolation = "sinc",
) -> tuple[np.ndarray, np.ndarray]:
    """GCC-PHAT of all pairs from precomputed per-channel spectra (TOA paper eqs. 4-6).

    Parameters
    ----------
    spectra : ndarray, shape (n_fft // 2 + 1, n_channels), complex
        ``rfft`` of each channel's windowed frame along axis 0.
    n_fft : int
        FFT length in samples used to compute ``spectra``.
    sample_rate_hz : float
        Sample rate in hertz.
    max_tdoa_s : float or None
        Largest ``|tdoa|`` searched, in seconds; see :class:`GccPhat`.
    interpolation : {"sinc", "parabolic", "none"}
        Sub-sample peak refinement; see :class:`GccPhat`.

    Returns
    -------
    tdoa_s : ndarray, shape (n_pairs,), float64
        ``toa_i - toa_j`` in seconds for each pair ``(i, j)`` of :func:`~estimators.conventions.pairs`.
    confidence : ndarray, shape (n_pairs,), float64
        PHAT peak height in ``[0, 1]``.
    """
    spectra = np.asarray(spectra)
    if spectra.ndim != 2:
        raise ValueError(f"spectra.shape={spectra.shape} must be (n_bins, n_channels)")
    gcc = _instance(spectra.shape[1], n_fft, sample_rate_hz, max_tdoa_s, interpolation)
    return gcc.process(spectra)


def gcc_phat(
    frame: np.ndarray,
    *,
    sample_rate_hz: float,
    max_tdoa_s: float | None = None,
    window: bool = True,
    interpolation: Interpolation = "sinc",
) -> tuple[np.ndarray, np.ndarray]:
    """GCC-PHAT of all channel pairs of one frame (TOA paper eqs. 4-6).

    Parameters
    ----------
    frame : ndarray, shape (n_samples, n_channels), float
        Time-major audio frame, ``n_samples >= 4``, ``n_channels >= 2``. A channel containing a
        non-finite value is treated as silent.
    sample_rate_hz : float
        Sample rate in hertz.
    max_tdoa_s : float or None
        Largest ``|tdoa|`` searched, in seconds; see :class:`GccPhat`.
    window : bool
        Apply a periodic Hann window before the FFT (``n_fft = n_samples``, no zero padding).
    interpolation : {"sinc", "parabolic", "none"}
        Sub-sample peak refinement; see :class:`GccPhat`.

    Returns
    -------
    tdoa_s : ndarray, shape (n_pairs,), float64
        ``toa_i - toa_j`` in seconds for each pair ``(i, j)``: positive when channel ``i`` is
        delayed relative to channel ``j``.
    confidence : ndarray, shape (n_pairs,), float64
        PHAT peak height in ``[0, 1]``.
    """
    frame = np.asarray(frame)
    if frame.ndim != 2 or frame.shape[0] < 4 or frame.shape[1] < 2:
        raise ValueError(f"frame.shape={frame.shape} must be (n_samples >= 4, n_channels >= 2)")
    n_samples, n_channels = frame.shape
    gcc = _instance(n_channels, n_samples, sample_rate_hz, max_tdoa_s, interpolation)
    x = np.array(frame.T, dtype=np.float32, order="C")  # (n_channels, n_samples)
    bad = ~np.isfinite(x).all(axis=1)
    if bad.any():
        x[bad] = 0.0
    if window:
        x *= _hann(n_samples)
    spec = scipy.fft.rfft(x, axis=-1, workers=1)  # (n_channels, n_bins) complex64
    return gcc._process_channel_major(spec)
