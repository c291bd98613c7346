"""GCC-PHAT time differences of arrival over all microphone pairs, batched.

Implements TOA paper eqs. (4)-(6) for every pair ``(i, j)`` of :func:`estimators.conventions.pairs`
at once:

- eq. (4), PHAT weighting. ``G_ij = X_i X_j^* / |X_i X_j^*|`` equals ``U_i U_j^*`` with the
  per-channel unit-magnitude spectrum ``U_i = X_i / (|X_i| + eps_i)``, so the division is done once
  per channel, not once per pair. ``eps_i = 1e-6 * max_k |X_i(k)|`` (plus the smallest positive
  float32) keeps empty bins at 0 instead of NaN.
- eq. (5), ``r_ij = irfft(G_ij)``: one batched inverse real FFT over all pairs (complex64 ->
  float32).
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
all zeros, contains a non-finite value or is marked invalid by the caller gives its pairs
``tdoa_s = 0`` and ``confidence = 0``.

Cost per frame: one compiled (numba) call does the PHAT weighting, the ``n_pairs`` cross spectra of
``n_fft // 2 + 1`` bins, the batched inverse FFT (DUCC through rocket-fft, the library behind
``scipy.fft``) into preallocated buffers, and the peak search over ``2 * max_lag_samples + 1``
lags per pair; the inverse FFT is the floor (about 60 % of the call at 8 channels x 512, 85 % at
16 x 4096). Pairs go through in cache-sized chunks. The Python side is a few checks and two output
allocations. Spectra laid out channel-major (``spectra.T`` C-contiguous complex64, as
:class:`beamform.StreamingStft` returns them) are used without a copy. :meth:`GccPhat.process_many`
runs the same kernel on many frames per call, and :func:`gcc_phat` adds the window and the forward
FFTs to it.
"""
from __future__ import annotations

import functools
import threading
from typing import Literal

import numba
from numba.core import types
from numba.extending import intrinsic
import numpy as np
import scipy.signal

from .numba_tools import borrowed

__all__ = ["GccPhat", "gcc_phat", "gcc_phat_spectra"]

Interpolation = Literal["sinc", "parabolic", "none"]

# Interpolation modes as the kernels take them.
_NONE, _SINC, _PARABOLIC = 0, 1, 2
_MODES = {"none": _NONE, "sinc": _SINC, "parabolic": _PARABOLIC}

_TINY_F32 = np.float32(np.finfo(np.float32).tiny)
# eq. (4): regulariser of the PHAT division, relative to the channel's largest bin magnitude.
_PHAT_REL_EPS = np.float32(1e-6)

# Pairs per chunk of _gcc_frame: a chunk's cross spectra and correlations take about this much
# memory (half of a 1 MiB L2 cache), and at least 16 pairs (rows the inverse FFT batches per SIMD
# pass). Measured: all 120 pairs at once at 16 channels x 512; chunks of 16 pairs at 4096, 3-6 %
# faster than one chunk.
_CHUNK_BYTES = 1 << 19

_C64 = np.dtype(np.complex64)
_F32 = np.dtype(np.float32)
_BOOL = np.dtype(np.bool_)


@functools.lru_cache(maxsize=16)
def _hann(n_samples: int) -> np.ndarray:
    # Kept writeable: numba types a read-only array differently (a second compiled specialisation).
    return scipy.signal.get_window("hann", n_samples, fftbins=True).astype(np.float32)


@functools.lru_cache(maxsize=16)
def _ones(n_samples: int) -> np.ndarray:
    """The rectangular window (``x * 1`` is exact, so ``window=False`` shares the windowed kernel)."""
    return np.ones(n_samples, np.float32)


def _max_lag_samples(n_fft: int, sample_rate_hz: float, max_tdoa_s: float | None) -> int:
    # Lags must stay strictly below n_fft/2 so that +lag and -lag are distinct and both have
    # neighbours for the interpolation.
    limit = n_fft // 2 - 1
    if max_tdoa_s is None:
        return limit
    return int(min(np.floor(max_tdoa_s * sample_rate_hz + 1e-9), limit))


# ---------------------------------------------------------------------------------------- kernels
# Every kernel is compiled with error_model="numpy": a float division by zero then follows IEEE
# instead of testing for ZeroDivisionError, whose branch stops LLVM from vectorising the loops.
_jit = numba.njit(cache=True, nogil=True, error_model="numpy")

# |X| is computed in float32 when the channel's largest |X(k)| lies in this range, otherwise again
# in float64: below 1e18 no float32 square overflows; above 1e-6, eps_i >= 1e-12 and the bins whose
# squares underflow (|X| < 1e-19) change U by < 1e-10.
_MAG_F32_MIN = np.float32(1e-6)
_MAG_F32_MAX = np.float32(1e18)


def _order_key_ir(context, builder, bits):
    """LLVM for ``b ^ ((b >> 31) & 0x7fffffff)`` on an i32 (arithmetic shift)."""
    i32 = context.get_value_type(types.int32)
    return builder.xor(bits, builder.and_(builder.ashr(bits, i32(31)), i32(0x7FFFFFFF)))


@intrinsic
def _order_key(typingctx, x):
    """Order key of a float32, an int32: ``b ^ ((b >> 31) & 0x7fffffff)`` of its bit pattern ``b``.

    Keys of non-NaN floats sort like the floats (-0 just below +0): a negative pattern gets its
    magnitude bits flipped. An integer max reduction over keys vectorises where a float max (with
    NaN semantics) does not. A NaN with the sign bit cleared sorts above +inf.
    """
    if x != types.float32:
        return None

    def codegen(context, builder, signature, args):
        return _order_key_ir(context, builder, builder.bitcast(args[0], context.get_value_type(types.int32)))

    return types.int32(types.float32), codegen


@intrinsic
def _key_value(typingctx, key):
    """The float32 whose :func:`_order_key` is ``key`` (the key map is its own inverse)."""
    if key != types.int32:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(_order_key_ir(context, builder, args[0]), context.get_value_type(types.float32))

    return types.float32(types.int32), codegen


_MIN_KEY = np.int32(-(2**31))


@_jit
def _magnitude_f32(x, mag):
    """``mag[k] = |x[k]|`` in float32; returns ``max_k |x[k]|``, NaN if any ``|x[k]|`` is NaN."""
    peak = _MIN_KEY
    for k in range(x.shape[0]):
        re = x[k].real
        im = x[k].imag
        m = np.sqrt(re * re + im * im)
        mag[k] = m
        peak = max(peak, _order_key(abs(m)))  # abs: a NaN's sign bit is arbitrary
    return _key_value(peak)


@_jit
def _magnitude_f64(x, mag):
    """:func:`_magnitude_f32` with the squares and their sum in float64 (exact squares, rounded once:
    hypot correctly rounded to float32), for magnitudes whose float32 squares over- or underflow."""
    peak = _MIN_KEY
    for k in range(x.shape[0]):
        re = np.float64(x[k].real)
        im = np.float64(x[k].imag)
        m = np.float32(np.sqrt(re * re + im * im))
        mag[k] = m
        peak = max(peak, _order_key(abs(m)))
    return _key_value(peak)


@_jit
def _phat_channel(x, usable, mag, unit):
    """eq. (4) for one channel: ``U = X / (|X| + eps)`` with ``eps = 1e-6 max_k |X(k)| + tiny``.

    ``x`` is the channel's spectrum and ``unit`` receives ``U``, both shape (n_bins,), complex64;
    ``mag`` is a float32 work array of the same length. Returns whether the channel is usable:
    ``usable`` (the caller's flag), every ``|X(k)|`` finite and ``max_k |X(k)| > 0``; otherwise
    ``U = 0``. float32 arithmetic, as the former numpy code (``np.abs``, ``+ eps``, ``1 / ...``,
    product).
    """
    if usable:
        peak = _magnitude_f32(x, mag)
        if not (_MAG_F32_MIN <= peak <= _MAG_F32_MAX):  # also NaN and inf: tell them from overflow
            peak = _magnitude_f64(x, mag)
        usable = 0.0 < peak < np.inf
    if not usable:
        unit[:] = 0.0
        return False
    eps = _PHAT_REL_EPS * peak + _TINY_F32
    one = np.float32(1.0)
    for k in range(x.shape[0]):
        w = one / (mag[k] + eps)
        unit[k] = complex(x[k].real * w, x[k].imag * w)
    return True


@_jit
def _max_key(values):
    """``max_k _order_key(values[k])`` (vectorises; see :func:`_order_key`)."""
    best = _MIN_KEY
    for k in range(values.shape[0]):
        best = max(best, _order_key(values[k]))
    return best


@_jit
def _first_equal(values, target):
    """First index ``k`` with ``values[k] == target``, else ``len(values)`` (a min reduction: vectorises)."""
    n = values.shape[0]
    first = n
    for k in range(n):
        first = min(first, k if values[k] == target else n)
    return first


@_jit
def _first_max(row, max_lag):
    """eq. (6): integer lag in ``-max_lag..max_lag`` of the first maximum of the correlation ``row``.

    Lags ``-L..-1`` (the end of the row) come before ``0..L``, as ``argmax`` over the concatenated
    window orders them; float equality, so +0 and -0 tie. ``row`` is finite (eq. 4 zeroes unusable
    channels).
    """
    n_fft = row.shape[0]
    neg = row[n_fft - max_lag :]  # lags -L..-1
    pos = row[: max_lag + 1]  # lags 0..L
    key_pos = _max_key(pos)
    key_neg = _max_key(neg) if max_lag > 0 else _MIN_KEY
    key = max(key_pos, key_neg)
    peak = _key_value(key)
    # A non-zero peak is in neg only if its key is; a zero one may be -0 there and +0 in pos.
    if key_neg == key or peak == 0.0:
        k = _first_equal(neg, peak)
        if k < max_lag:
            return k - max_lag
    return _first_equal(pos, peak)


@_jit
def _refine(row, lag_int, max_lag, mode, sample_rate_hz):
    """eq. (6): sub-sample lag from ``r[k-1], r[k], r[k+1]`` (float64), clipped to ``+-L``, in seconds;
    and the peak height ``r[k]``.

    ``"sinc"``: ``d = s / (r[k] + s)`` with ``s = max(r[k-1], r[k+1])``, 0 where ``r[k] + s <= 0``,
    clipped to ``[0, 0.5]``, signed towards the larger neighbour (``+`` on a tie: the sign of
    ``r[k+1] - r[k-1]``). ``"parabolic"``: ``d = (r[k-1] - r[k+1]) / (2 (r[k-1] - 2 r[k] + r[k+1]))``
    where the denominator is < 0, else 0, clipped to ``[-0.5, 0.5]``. ``"none"``: ``d = 0``.
    """
    n_fft = row.shape[0]
    k = lag_int + n_fft if lag_int < 0 else lag_int  # |lag| + 1 <= n_fft / 2: neighbours in range
    r0 = np.float64(row[k])
    rm = np.float64(row[k - 1 if k > 0 else n_fft - 1])
    rp = np.float64(row[k + 1 if k < n_fft - 1 else 0])
    d = 0.0
    if mode == _SINC:
        side = max(rp, rm)
        den = r0 + side
        if den > 0.0:
            d = side / den
        d = min(max(d, 0.0), 0.5)
        d = np.copysign(d, rp - rm)
    elif mode == _PARABOLIC:
        den = rm - 2.0 * r0 + rp
        if den < 0.0:
            d = 0.5 * (rm - rp) / den
        d = min(max(d, -0.5), 0.5)
    lag = min(max(d + lag_int, -max_lag), max_lag)
    return lag / sample_rate_hz, r0


@_jit
def _gcc_frame(spec, valid, mag, unit, cross, corr, max_lag, mode, sample_rate_hz, tdoa_s, confidence):
    """Eqs. (4)-(6) for one frame: PHAT, the cross spectra, batched ``irfft``, peak, refinement.

    The pairs go through in chunks of ``len(cross)`` rows (all at once for small frames), so
    that a chunk's cross spectra and correlations stay in cache between the steps.

    Parameters
    ----------
    spec : ndarray, shape (n_channels, n_bins), complex64, C-contiguous
        Channel-major spectra.
    valid : ndarray, shape (n_channels,), bool
        The caller's channel flags; a False channel is treated as silent.
    mag : ndarray, shape (n_bins,), float32
        Work array: ``|X_i|``.
    unit : ndarray, shape (n_channels, n_bins), complex64
        Work array: ``U_i``.
    cross : ndarray, shape (n_chunk, n_bins), complex64
        Work array: ``G_ij = U_i U_j^*`` of a chunk of pairs in the order of
        :func:`~estimators.conventions.pairs`.
    corr : ndarray, shape (n_chunk, n_fft), float32
        Work array: ``r_ij = irfft(G_ij)`` (eq. 5) of the chunk.
    max_lag, mode, sample_rate_hz
        ``L`` in samples, interpolation (``_NONE``, ``_SINC``, ``_PARABOLIC``), rate in Hz.
    tdoa_s, confidence : ndarray, shape (n_pairs,), float64
        Outputs; ``0, 0`` for a pair with an unusable channel.
    """
    n_channels, n_bins = spec.shape
    n_fft = corr.shape[1]
    n_chunk = cross.shape[0]
    n_pairs = n_channels * (n_channels - 1) // 2
    usable = np.empty(n_channels, np.bool_)
    for i in range(n_channels):
        usable[i] = _phat_channel(spec[i], valid[i], mag, unit[i])
    i0, j0 = 0, 1  # first pair of the chunk
    for start in range(0, n_pairs, n_chunk):
        n_rows = min(n_chunk, n_pairs - start)
        i, j = i0, j0
        for row in range(n_rows):
            a = unit[i]
            b = unit[j]
            g = cross[row]
            for k in range(n_bins):
                g[k] = a[k] * b[k].conjugate()
            j += 1
            if j == n_channels:
                i += 1
                j = i + 1
        np.fft.irfft(cross[:n_rows], n_fft, -1, None, corr[:n_rows])  # eq. (5)
        i, j = i0, j0
        for row in range(n_rows):
            p = start + row
            if usable[i] and usable[j]:
                lag_int = _first_max(corr[row], max_lag)
                t, r0 = _refine(corr[row], lag_int, max_lag, mode, sample_rate_hz)
                tdoa_s[p] = t
                confidence[p] = min(max(r0, 0.0), 1.0)
            else:
                tdoa_s[p] = 0.0
                confidence[p] = 0.0
            j += 1
            if j == n_channels:
                i += 1
                j = i + 1
        i0, j0 = i, j


# Layout of GccPhat's float32 work array (mag | unit | cross | corr, each starting at an even float
# so the complex views are 8-byte aligned) and of its float64 parameter array, as _gcc_process takes them:
# two arrays instead of seven arguments (every argument of a compiled call costs ~40 ns to unbox).
_L_MAX_LAG, _L_MODE, _L_RATE_HZ, _L_CHANNELS, _L_BINS, _L_FFT, _L_CHUNK = range(7)
_L_OFFSETS = 7  # then the start of mag, unit, cross and corr in the work array
_N_LAYOUT = _L_OFFSETS + 4

# Return codes of _gcc_process.
_OK, _BAD_SPECTRA_SHAPE, _BAD_VALID_SHAPE = 0, 1, 2


@_jit
def _work_views(work, layout):
    """The work arrays of :func:`_gcc_frame` as views of ``work`` (layout above): ``mag`` (n_bins,)
    float32, ``unit`` (n_channels, n_bins) and ``cross`` (n_chunk, n_bins) complex64, ``corr``
    (n_chunk, n_fft) float32."""
    m = int(layout[_L_CHANNELS])
    n_bins = int(layout[_L_BINS])
    n_chunk = int(layout[_L_CHUNK])
    o_mag = int(layout[_L_OFFSETS])
    o_unit = int(layout[_L_OFFSETS + 1])
    o_cross = int(layout[_L_OFFSETS + 2])
    o_corr = int(layout[_L_OFFSETS + 3])
    mag = work[o_mag : o_mag + n_bins]
    unit = work[o_unit : o_unit + 2 * m * n_bins].view(np.complex64).reshape((m, n_bins))
    cross = work[o_cross : o_cross + 2 * n_chunk * n_bins].view(np.complex64).reshape((n_chunk, n_bins))
    n_fft = int(layout[_L_FFT])
    corr = work[o_corr : o_corr + n_chunk * n_fft].reshape((n_chunk, n_fft))
    return mag, unit, cross, corr


@numba.njit(
    numba.int64(numba.types.Array(numba.complex64, 2, "F"),  # spectra (n_bins, M), a C-contiguous transpose
                numba.types.Array(numba.bool_, 1, "A", readonly=True),  # valid: any 1-D bool array
                numba.float32[::1], numba.float64[::1], numba.float64[::1], numba.float64[::1]),
    cache=True, nogil=True, error_model="numpy",
)
def _gcc_process(spectra, valid, work, layout, tdoa_s, confidence):
    """:meth:`GccPhat.process` in one compiled call: shape checks, then :func:`_gcc_frame`.

    ``spectra`` (n_bins, n_channels) complex64 with a C-contiguous transpose (the layout of
    :meth:`beamform.StreamingStft.process`); compiled for exactly these types (anything else is a
    ``TypeError`` at the call: the caller converts first). Returns ``_OK`` or which shape is wrong
    (nothing written then).
    """
    m = int(layout[_L_CHANNELS])
    if spectra.shape[0] != int(layout[_L_BINS]) or spectra.shape[1] != m:
        return _BAD_SPECTRA_SHAPE
    if valid.shape[0] != m:
        return _BAD_VALID_SHAPE
    # borrowed (estimators.numba_tools): no reference-count updates for the views and calls below
    spectra, valid, work = borrowed(spectra), borrowed(valid), borrowed(work)
    tdoa_s, confidence = borrowed(tdoa_s), borrowed(confidence)
    mag, unit, cross, corr = _work_views(work, layout)
    _gcc_frame(spectra.T, valid, mag, unit, cross, corr, int(layout[_L_MAX_LAG]), int(layout[_L_MODE]),
               layout[_L_RATE_HZ], tdoa_s, confidence)
    return _OK


@_jit
def _gcc_frames(spec, valid, mag, unit, cross, corr, max_lag, mode, sample_rate_hz, tdoa_s, confidence):
    """:func:`_gcc_frame` for each of ``n_frames`` frames: ``spec`` (n_frames, n_channels, n_bins),
    ``valid`` (n_frames, n_channels), outputs (n_frames, n_pairs)."""
    for f in range(spec.shape[0]):
        _gcc_frame(spec[f], valid[f], mag, unit, cross, corr, max_lag, mode, sample_rate_hz, tdoa_s[f],
                   confidence[f])


@_jit
def _gcc_time(frame, window, valid, windowed, spec, mag, unit, cross, corr, max_lag, mode, sample_rate_hz,
              tdoa_s, confidence):
    """``rfft(window * x_i)`` of every channel of a time-major ``frame`` (n_samples, n_channels),
    float32, into ``spec`` (n_channels, n_bins), then :func:`_gcc_frame`.

    No separate finiteness test: a non-finite sample makes its channel's spectrum non-finite (at
    least bin 0, the sum of all samples; ``inf * 0`` is NaN), which eq. (4) rejects.
    """
    n_samples, n_channels = frame.shape
    for t in range(n_samples):
        w = window[t]
        for c in range(n_channels):
            windowed[c, t] = frame[t, c] * w
    np.fft.rfft(windowed, n_samples, -1, None, spec)
    _gcc_frame(spec, valid, mag, unit, cross, corr, max_lag, mode, sample_rate_hz, tdoa_s, confidence)


# ---------------------------------------------------------------------------------------- class
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
        ``r[k-1], r[k], r[k+1]`` (computed in float64):

        - ``"sinc"`` (default): the PHAT correlation of a pure delay ``k + d`` is
          ``sinc(n - k - d)``, whose neighbour ratio is ``r[k+1] / r[k] = d / (1 - d)``; hence
          ``d = r[k+1] / (r[k] + r[k+1])`` (or ``-r[k-1] / (r[k] + r[k-1])`` on the other side),
          clipped to ``[-0.5, 0.5]``. Unbiased for a full-band delay.
        - ``"parabolic"``: vertex of the parabola through the three points,
          ``d = (r[k-1] - r[k+1]) / (2 (r[k-1] - 2 r[k] + r[k+1]))``; biased towards integers by up
          to about 0.1 sample for PHAT peaks.
        - ``"none"``: integer lags.

        The integer peak is the first maximum over lags ``-L..-1`` then ``0..L``.

    Notes
    -----
    The per-frame work uses preallocated buffers, so one instance must not be used from two threads
    at once; the module functions :func:`gcc_phat` and :func:`gcc_phat_spectra` keep one instance
    per thread and configuration and are thread-safe. The compiled kernels release the GIL.
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
        if interpolation not in _MODES:
            raise ValueError(f"{interpolation=} must be 'sinc', 'parabolic' or 'none'")
        self.n_channels = int(n_channels)
        self.n_fft = int(n_fft)
        self.n_bins = self.n_fft // 2 + 1
        self.n_pairs = self.n_channels * (self.n_channels - 1) // 2
        self.sample_rate_hz = float(sample_rate_hz)
        self.max_tdoa_s = max_tdoa_s
        self.interpolation: Interpolation = interpolation
        self.max_lag_samples = _max_lag_samples(self.n_fft, self.sample_rate_hz, max_tdoa_s)
        self._mode = _MODES[interpolation]
        self._shape = (self.n_bins, self.n_channels)
        self._all_valid = np.ones(self.n_channels, np.bool_)
        # Work arrays of _gcc_frame, reused by every call (a fresh (n_pairs, n_fft) buffer per call
        # costs its page faults at 16 channels x 4096).
        n_chunk = min(self.n_pairs, max(16, _CHUNK_BYTES // (8 * self.n_bins + 4 * self.n_fft)))
        sizes = (self.n_bins, 2 * self.n_channels * self.n_bins, 2 * n_chunk * self.n_bins, n_chunk * self.n_fft)
        offsets = np.cumsum((0,) + tuple(n + n % 2 for n in sizes))
        self._work = np.zeros(int(offsets[-1]), np.float32)
        self._layout = np.zeros(_N_LAYOUT)
        self._layout[:_L_OFFSETS] = (self.max_lag_samples, self._mode, self.sample_rate_hz, self.n_channels,
                                     self.n_bins, self.n_fft, n_chunk)
        self._layout[_L_OFFSETS:] = offsets[:4]
        self._mag, self._unit, self._cross, self._corr = _work_views(self._work, self._layout)
        self._time_work: tuple[np.ndarray, np.ndarray] | None = None  # for gcc_phat, made on first use

    def reset(self) -> None:
        """No state is carried between frames; present for the common stage interface."""

    def process(self, spectra: np.ndarray, *, valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """TDOA and confidence of every pair from one frame's spectra.

        Parameters
        ----------
        spectra : ndarray, shape (n_bins, n_channels), complex
            ``rfft`` of each channel's windowed frame along axis 0, ``n_bins = n_fft // 2 + 1``.
            Fastest as a writeable complex64 array with ``spectra.T`` C-contiguous (the layout of
            :meth:`beamform.StreamingStft.process`); any other layout or dtype is copied first.
        valid : ndarray, shape (n_channels,), bool, optional
            Channels to use. A channel with ``valid[i] == False`` is treated like a silent one: its
            pairs get ``tdoa_s = 0`` and ``confidence = 0``, and the other pairs are unchanged.
            ``None`` (default): all channels.

        Returns
        -------
        tdoa_s : ndarray, shape (n_pairs,), float64
            ``toa_i - toa_j`` in seconds for pair ``(i, j)``.
        confidence : ndarray, shape (n_pairs,), float64
            PHAT peak height in ``[0, 1]``; 0 for pairs with a silent, non-finite or invalid channel.
        """
        tdoa_s = np.empty(self.n_pairs)
        confidence = np.empty(self.n_pairs)
        if valid is None:
            valid = self._all_valid
        # The kernel is compiled for one dtype and layout of the spectra (and the dtype of the mask);
        # other inputs are converted first, here: a failed call costs ~70 us (numba words its TypeError).
        try:
            usual = spectra.dtype is _C64 and spectra.flags.farray and valid.dtype is _BOOL
        except AttributeError:  # not arrays
            usual = False
        if usual:
            try:
                code = _gcc_process(spectra, valid, self._work, self._layout, tdoa_s, confidence)
            except TypeError:  # the usual dtypes with other dimensions
                usual = False
        if not usual:
            code = _gcc_process(*self._as_kernel_inputs(spectra, valid), self._work, self._layout, tdoa_s,
                                confidence)
        if code != _OK:
            self._raise_shape(code, spectra, valid)
        return tdoa_s, confidence

    def _as_kernel_inputs(self, spectra, valid) -> tuple[np.ndarray, np.ndarray]:
        """``spectra`` as complex64 with a writeable C-contiguous transpose (numba types read-only or
        strided arrays differently), ``valid`` as a 1-D bool array; wrong shapes raise."""
        spectra = np.asarray(spectra)
        if spectra.shape != self._shape:
            self._raise_shape(_BAD_SPECTRA_SHAPE, spectra, valid)
        valid = np.asarray(valid, dtype=np.bool_)
        if valid.ndim != 1:
            self._raise_shape(_BAD_VALID_SHAPE, spectra, valid)
        return _kernel_array(spectra.T, _C64).T, valid

    def _raise_shape(self, code: int, spectra, valid) -> None:
        if code == _BAD_SPECTRA_SHAPE:
            raise ValueError(
                f"spectra.shape={np.shape(spectra)} must be (n_bins, n_channels)="
                f"{(self.n_bins, self.n_channels)}"
            )
        raise ValueError(f"valid.shape={np.shape(valid)} must be {self._all_valid.shape}")

    def process_many(
        self, spectra: np.ndarray, *, valid: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`process` on many frames at once (e.g. a replay with several hops available).

        The result equals ``n_frames`` calls of :meth:`process` (no state is carried between
        frames), computed in one compiled call.

        Parameters
        ----------
        spectra : ndarray, shape (n_frames, n_bins, n_channels), complex
            One frame's spectra per row, as :meth:`process` takes them. Used without a copy when
            the per-frame transposes are C-contiguous complex64 (the output of
            :meth:`beamform.StreamingStft.process_many`).
        valid : ndarray, shape (n_frames, n_channels), bool, optional
            Channels to use in each frame, as in :meth:`process`. ``None`` (default): all channels.

        Returns
        -------
        tdoa_s : ndarray, shape (n_frames, n_pairs), float64
        confidence : ndarray, shape (n_frames, n_pairs), float64
        """
        spectra = np.asarray(spectra)
        if spectra.ndim != 3 or spectra.shape[1:] != self._shape:
            raise ValueError(
                f"spectra.shape={spectra.shape} must be (n_frames, n_bins, n_channels)="
                f"(n_frames, {self.n_bins}, {self.n_channels})"
            )
        n_frames = spectra.shape[0]
        spec = spectra.transpose(0, 2, 1)
        if spec.dtype != _C64 or not spec.flags.c_contiguous or not spec.flags.writeable:
            spec = np.array(spec, dtype=np.complex64, order="C")
        if valid is None:
            valid = np.ones((n_frames, self.n_channels), np.bool_)
        else:
            valid = _channel_flags(valid, (n_frames, self.n_channels))
        tdoa_s = np.empty((n_frames, self.n_pairs))
        confidence = np.empty((n_frames, self.n_pairs))
        _gcc_frames(spec, valid, self._mag, self._unit, self._cross, self._corr, self.max_lag_samples, self._mode,
                    self.sample_rate_hz, tdoa_s, confidence)
        return tdoa_s, confidence

    def _process_frame(self, frame: np.ndarray, window: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`process` of ``rfft(window * frame)``, the FFTs inside the same compiled call.

        ``frame`` is (n_fft, n_channels) float32, writeable and C-contiguous; ``window`` (n_fft,)
        float32.
        """
        work = self._time_work
        if work is None:  # only gcc_phat needs these
            work = self._time_work = (
                np.zeros((self.n_channels, self.n_fft), np.float32),
                np.zeros((self.n_channels, self.n_bins), np.complex64),
            )
        tdoa_s = np.empty(self.n_pairs)
        confidence = np.empty(self.n_pairs)
        _gcc_time(frame, window, self._all_valid, work[0], work[1], self._mag, self._unit, self._cross, self._corr,
                  self.max_lag_samples, self._mode, self.sample_rate_hz, tdoa_s, confidence)
        return tdoa_s, confidence


def _kernel_array(a, dtype: np.dtype) -> np.ndarray:
    """``a`` as a writeable C-contiguous array of ``dtype``, the one layout the kernels are compiled for (numba
    types read-only or strided arrays differently); no copy when it already is one."""
    if type(a) is not np.ndarray or a.dtype != dtype or not a.flags.c_contiguous or not a.flags.writeable:
        a = np.array(a, dtype=dtype, order="C")
    return a


def _channel_flags(valid: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``valid`` as a writeable C-contiguous bool array of ``shape`` (no copy when it already is one)."""
    valid = _kernel_array(valid, _BOOL)
    if valid.shape != shape:
        raise ValueError(f"valid.shape={valid.shape} must be {shape}")
    return valid


_local = threading.local()


def _instance(
    n_channels: int,
    n_fft: int,
    sample_rate_hz: float,
    max_tdoa_s: float | None,
    interpolation: Interpolation,
) -> GccPhat:
    """A :class:`GccPhat` cached per thread and configuration (its work arrays stay warm)."""
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
        Time-major audio frame, ``n_samples >= 4``, ``n_channels >= 2``, converted to float32 (no
        copy for a C-contiguous float32 frame). A channel containing a non-finite value is treated
        as silent.
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
    frame = _kernel_array(frame, _F32)
    if frame.ndim != 2 or frame.shape[0] < 4 or frame.shape[1] < 2:
        raise ValueError(f"frame.shape={frame.shape} must be (n_samples >= 4, n_channels >= 2)")
    n_samples, n_channels = frame.shape
    gcc = _instance(n_channels, n_samples, sample_rate_hz, max_tdoa_s, interpolation)
    return gcc._process_frame(frame, _hann(n_samples) if window else _ones(n_samples))
