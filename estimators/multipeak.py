"""Noise-aware GCC-PHAT with the N best peaks of every pair (several sources at once).

:class:`NoiseAwareGcc` extends the TOA paper's eqs. (4)-(6) in two ways, for rooms with a persistent
point noise source and with more than one talker:

1. **Noise cross-power spectrum removal.** Every pair's noise cross-power spectrum is tracked on
   non-speech frames, recursively and weighted by the frame's speech presence ``p`` in ``[0, 1]``::

       Phi_ij <- Phi_ij + a (1 - p) (X_i X_j^* - Phi_ij),    a = 1 - exp(-hop / noise_time_constant)

   (with ``noise_delay_s``, each frame joins the average that long after it was heard and only as far as no
   speech was detected since: ``p`` is then the largest speech presence from that frame to now, so a talker's
   first words, heard before the detector fires, stay out of the noise) and removed from the frame's cross
   spectrum before the PHAT weighting::

       G_ij = X_i X_j^* - Phi_ij                       (weighting "subtract")
       G_ij = (X_i X_j^* - Phi_ij) * max(0, 1 - |Phi_ij| / |X_i X_j^*|)   ("subtract-snr")
       r_ij = irfft(G_ij / |G_ij|)

   A coherent noise source contributes ``|N|^2 H_i H_j^*`` to ``X_i X_j^*``; after the removal only
   its fluctuation ``(|N|^2 - E|N|^2) H_i H_j^*`` is left, whose sign is random from bin to bin, so
   the PHAT correlation no longer has a peak at the noise source's delay. ``"subtract-snr"``
   further down-weights bins in which the frame's cross power is not above the noise cross power
   (a per-bin SNR weight, in the spirit of the maximum-likelihood GCC weighting). ``"phat"`` is the
   plain eq. (4) on ``X_i X_j^*`` (no removal) for comparison.

   The removal works on a short-time average of ``X_i X_j^*`` (``smoothing_time_constant_s``), which makes a
   talker's peak far steadier under the noise but lags a moving talker; with
   ``fast_smoothing_time_constant_s`` the average is shorter in the frames where a pair's cross power stands
   well above the noise's (``FAST_SNR_DB``).

   With ``phat_beta`` < 1 ("subtract" and "phat"), the weighting is PHAT-β: ``r_ij = irfft(c G_ij /
   |G_ij|^beta)``, ``c`` such that ``sum_k |c G_ij / |G_ij|^beta| = n_bins`` as with PHAT (the peaks stay on
   PHAT's scale). The louder bins (after the removal: the talker's harmonics) then count for more than those
   left with the noise's residue and the late reverberation. ``|G|^(1 - beta)`` is computed as a product of
   repeated square roots, to 2^-10 in ``(1 - beta) / 2``. With ``phat_beta_near_noise`` each pair's exponent
   moves from ``phat_beta`` to 1 by the same SNR share as the time constant (``FAST_SNR_DB``): PHAT-β where
   the pair is near the noise, PHAT where it stands clear of it.
2. **The N best peaks** of every pair's correlation within ``|lag| <= max_lag_samples`` (local maxima,
   highest first, refined to a fraction of a sample with the three-point parabola) instead of the
   single maximum of eq. (6), as BeamformIt keeps the N best delays per channel pair.

:meth:`NoiseAwareGcc.noise_peaks` gives the N best peaks of the PHAT-weighted noise cross-power
spectrum itself: the delays of the persistent noise sources.

All of it is one compiled (numba) call per frame, FFTs included (rocket-fft's ``np.fft`` inside numba).
Conventions as in :mod:`estimators.conventions`: ``tdoa_s[p] = toa_i - toa_j`` for ``p = (i, j)``.
"""
from __future__ import annotations

import math
from typing import Literal

import numba
import numpy as np

from .conventions import delay_phasors, pairs
from .numba_tools import all_finite, borrowed

__all__ = ["NoiseAwareGcc", "Weighting"]

Weighting = Literal["phat", "subtract", "subtract-snr"]
_WEIGHTINGS = {"phat": 0, "subtract": 1, "subtract-snr": 2}

_jit = numba.njit(cache=True, nogil=True, error_model="numpy")

# Parameter slots of the compiled call (one float64 array instead of many arguments).
(_P_MAX_LAG, _P_RATE_HZ, _P_ALPHA, _P_MODE, _P_SPEECH, _P_N_PEAKS, _P_UPDATE, _P_SMOOTH, _P_NOISE_SCALE,
 _P_SMOOTH_FAST, _P_FAST_LO_DB, _P_FAST_HI_DB, _P_PEAKS, _P_BETA, _P_BETA_NEAR_NOISE) = range(15)
_N_PARAMS = 15

# The short-time average moves from its slow to its fast time constant as a pair's frame cross power (sum of
# |X_i X_j^*| over the bins) rises from FAST_SNR_DB[0] to FAST_SNR_DB[1] above the noise cross power's.
FAST_SNR_DB = (15.0, 30.0)

_OK, _BAD_SPECTRA_SHAPE, _BAD_VALID_SHAPE = 0, 1, 2
_EPS_REL = np.float32(1e-6)
_TINY = np.float32(np.finfo(np.float32).tiny)
_MAGNITUDE_MASK = np.uint32(0x7FFFFFFF)  # every bit but the sign: none set <=> +-0


@_jit
def _top_peaks(row, max_lag, rate_hz, out_tdoa, out_value):
    """The ``len(out_tdoa)`` highest local maxima of the correlation ``row`` (n_fft,) over lags
    ``-max_lag..max_lag`` (circular indices), highest first, each refined by the three-point parabola
    (clipped to half a sample) and returned in seconds; unfilled slots get value 0 and tdoa 0."""
    n_fft = row.shape[0]
    k_best = out_tdoa.shape[0]
    for q in range(k_best):
        out_tdoa[q] = 0.0
        out_value[q] = 0.0
    n_found = 0
    thr = 0.0   # a lag must be above this to enter: 0, then the lowest value kept once the list is full
    for lag in range(-max_lag, max_lag + 1):
        k = lag + n_fft if lag < 0 else lag
        r0 = np.float64(row[k])
        if r0 <= thr:
            continue
        rm = np.float64(row[k - 1 if k > 0 else n_fft - 1])
        rp = np.float64(row[k + 1 if k < n_fft - 1 else 0])
        if not (r0 >= rm and r0 > rp):
            continue
        den = rm - 2.0 * r0 + rp
        d = 0.0
        if den < 0.0:
            d = min(max(0.5 * (rm - rp) / den, -0.5), 0.5)
        t = min(max(lag + d, -max_lag), max_lag) / rate_hz
        # insert, keeping the list sorted by value (descending)
        q = n_found if n_found < k_best else k_best - 1
        while q > 0 and out_value[q - 1] < r0:
            if q < k_best:
                out_value[q] = out_value[q - 1]
                out_tdoa[q] = out_tdoa[q - 1]
            q -= 1
        out_value[q] = r0
        out_tdoa[q] = t
        if n_found < k_best:
            n_found += 1
        if n_found == k_best:
            thr = out_value[k_best - 1]


@_jit
def _channel_ok(x, valid):
    """Whether a channel's spectrum is usable: flagged valid, finite and not all zero (integer reductions over
    the float32 bits, which vectorise: a zero has none set but the sign)."""
    if not valid:
        return False
    bits = x.view(np.uint32)
    if not all_finite(bits):
        return False
    nonzero = np.uint32(0)
    for k in range(bits.shape[0]):
        nonzero |= bits[k] & _MAGNITUDE_MASK
    return nonzero != 0


@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath={"reassoc"})
def _dot(a, b):
    """``sum_k a[k] b[k]`` of two float32 rows, in float64 SIMD lanes (``reassoc``: the order of the sum is
    free; it feeds a dB figure, so a different rounding in the last bit changes nothing downstream)."""
    s = 0.0
    for k in range(a.shape[0]):
        s += np.float64(a[k] * b[k])
    return s


@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath={"reassoc"})
def _abs_sum(f):
    """``sum_k |z_k|`` of complex values given as their interleaved (re, im) float32 view, ``|.|`` as a float32
    ``sqrt``, summed in float64 SIMD lanes (``reassoc``, as :func:`_dot`)."""
    s = 0.0
    for k in range(f.shape[0] // 2):
        s += np.float64(np.sqrt(f[2 * k] * f[2 * k] + f[2 * k + 1] * f[2 * k + 1]))
    return s


@_jit
def _max_nonneg(v):
    """The largest of the non-negative float32 values ``v`` (their uint32 views order as the values do, and an
    integer max-reduction vectorises where a float one, with its NaN rules, does not)."""
    bits = v.view(np.uint32)
    top = np.uint32(0)
    for k in range(bits.shape[0]):
        top = max(top, bits[k])
    out = np.empty(1, np.uint32)
    out[0] = top
    return out.view(np.float32)[0]


@_jit
def _pair_spectrum(xi, xj, oi, oj, phi, sm, g, scratch, a, b, mode, update, phi_scale, adapt, fast, phi_l1, mi, mj,
                   weigh, beta, beta_near_noise):
    """One pair's weighted cross spectrum into ``g`` (module doc): the short-time average ``sm`` of
    ``X_i X_j^*`` (moved by ``b``; ``b = 1``: this frame only) minus the noise cross power ``phi`` (for
    "phat": this frame's ``X_i X_j^*`` alone), optional per-bin weight, PHAT normalisation; then the noise
    average moves towards the delayed frame's ``O_i O_j^*`` (``oi``, ``oj``) by ``a``. ``phi_scale`` undoes the
    average's start-up bias (it starts at 0). ``scratch`` (>= n_bins floats) holds |G|^2.

    ``adapt``: ``b`` moves towards ``fast = (b_fast, lo_db, hi_db)``'s ``b_fast`` as the frame's cross
    power ``sum_k |X_i X_j^*|`` rises from ``lo_db`` to ``hi_db`` above the noise's (``phi_scale * phi_l1[0]``,
    ``phi_l1[0] = sum_k |phi_k|``, kept up to date here when the noise average moves; ``mi``, ``mj``: the
    channels' magnitudes ``|X_i|``, ``|X_j|``).

    The complex arithmetic runs on the interleaved (re, im) float32 views, one operation per component as
    numba's complex64 operations do it (the cross spectra, both averages and the PHAT weights are the same to
    the bit), in loops without a reduction, which vectorise (with complex64 elements, ``abs`` as ``hypot`` and
    a running maximum in the loop they did not: the frame took 1.4-2 times as long). The two sums that only
    feed the SNR share in dB, ``sum |X_i| |X_j|`` and ``sum |phi|``, are summed in SIMD lanes, with ``|.|`` as a
    float32 ``sqrt``: they may differ in the last bits (the 52 scenes' SI-SDR moved by < 1e-8 dB).

    ``weigh`` False: the averages only (``g`` is left unweighted: a frame whose peaks are not searched).

    ``beta`` < 1 (not for "subtract-snr"): PHAT-beta, ``G / |G|^beta``, then scaled so that ``sum_k |G_k|`` is
    ``n_bins`` as with PHAT (the peaks' heights stay on the PHAT scale the thresholds are set for);
    ``beta_near_noise``: ``beta`` moves to 1 by the pair's SNR share (computed as for ``adapt``)."""
    n_bins = xi.shape[0]
    if adapt or beta_near_noise:
        sc = _dot(mi, mj)
        noise = phi_scale * phi_l1[0]
        share = 1.0
        if noise > 0.0:
            snr_db = 10.0 * np.log10(max(sc, 1e-30) / noise)
            share = min(max((snr_db - fast[1]) / (fast[2] - fast[1]), 0.0), 1.0)
        if adapt:
            b = np.float32(b + share * (fast[0] - b))
        if beta_near_noise:   # PHAT where the pair stands clear of the noise
            beta = beta + share * (1.0 - beta)
    xf, yf, smf, phf, gf = xi.view(np.float32), xj.view(np.float32), sm.view(np.float32), phi.view(np.float32), \
        g.view(np.float32)
    m2 = scratch[:n_bins]
    for k in range(n_bins):
        ar, ai, br, bi = xf[2 * k], xf[2 * k + 1], yf[2 * k], yf[2 * k + 1]
        cr = ar * br + ai * bi        # X_i X_j^*
        ci = ai * br - ar * bi
        sr = smf[2 * k] + b * (cr - smf[2 * k])
        si = smf[2 * k + 1] + b * (ci - smf[2 * k + 1])
        smf[2 * k] = sr
        smf[2 * k + 1] = si
        if mode != 0:
            cr = sr - phi_scale * phf[2 * k]
            ci = si - phi_scale * phf[2 * k + 1]
        gf[2 * k] = cr
        gf[2 * k + 1] = ci
        m2[k] = cr * cr + ci * ci
    if update and a != 0.0:   # a = 0 on speech frames: the average stays as it is
        of, pf = oi.view(np.float32), oj.view(np.float32)
        for k in range(n_bins):
            ar, ai, br, bi = of[2 * k], of[2 * k + 1], pf[2 * k], pf[2 * k + 1]
            phf[2 * k] += a * ((ar * br + ai * bi) - phf[2 * k])
            phf[2 * k + 1] += a * ((ai * br - ar * bi) - phf[2 * k + 1])
        phi_l1[0] = _abs_sum(phf)
    if not weigh:
        return
    peak2 = _max_nonneg(m2)
    eps = _EPS_REL * np.sqrt(peak2) + _TINY
    eps2 = eps * eps
    one = np.float32(1.0)
    if mode == 2:
        for k in range(n_bins):
            c = sm[k]
            ac = np.sqrt(c.real * c.real + c.imag * c.imag)
            an = phi_scale * abs(phi[k])
            w = one - an / (ac + _TINY)
            w = w if w > 0 else np.float32(0.0)
            g[k] = g[k] * (w / np.sqrt(scratch[k] + eps2))
    else:
        for k in range(n_bins):
            w = one / np.sqrt(m2[k] + eps2)
            gf[2 * k] *= w
            gf[2 * k + 1] *= w
        if beta != 1.0:
            _phat_beta(gf, m2, eps2, beta)


@_jit
def _phat_beta(gf, m2, eps2, beta):
    """PHAT-weighted ``G`` (interleaved ``gf``) to ``c G / |G|^beta`` with ``sum_k |.| = n_bins``: times
    ``|G|^(1 - beta)``, a product of the powers ``|G|^(2^-j)`` of the set binary digits of ``(1 - beta) / 2`` to
    2^-10 (ten passes of square roots of ``m2 + eps2 = |G|^2 + eps^2`` vectorise; a pow per bin does not).
    ``m2`` is overwritten."""
    n_bins = m2.shape[0]
    q = int(round((1.0 - beta) * 512.0))
    if q == 0:
        return
    for k in range(n_bins):
        m2[k] = m2[k] + eps2
    for j in range(1, 11):
        if (q >> (10 - j)) & 1:
            for k in range(n_bins):
                m2[k] = np.sqrt(m2[k])
                gf[2 * k] *= m2[k]
                gf[2 * k + 1] *= m2[k]
        else:
            for k in range(n_bins):
                m2[k] = np.sqrt(m2[k])
    total = _abs_sum(gf)
    if total > 0.0:
        scale = np.float32(n_bins / total)
        for k in range(2 * n_bins):
            gf[k] *= scale


@numba.njit(
    numba.int64(numba.types.Array(numba.complex64, 2, "F"),  # spectra (n_bins, M), a C-contiguous transpose
                numba.types.Array(numba.bool_, 1, "A", readonly=True),
                numba.complex64[:, ::1],  # the delayed frame that updates the noise average (M, n_bins)
                numba.bool_[::1],         # its usable channels (M,)
                numba.complex64[:, ::1],  # noise cross-power spectra (n_pairs, n_bins), state
                numba.complex64[:, ::1],  # short-time cross-power spectra (n_pairs, n_bins), state
                numba.float64[::1],       # sum over bins of |noise cross power| per pair (n_pairs,), state
                numba.complex64[:, ::1],  # cross work (n_pairs, n_bins)
                numba.float32[:, ::1],    # correlation work (n_pairs, n_fft)
                numba.float32[:, ::1],    # magnitude work (M, n_bins)
                numba.float64[::1],       # parameters
                numba.float64[:, ::1], numba.float64[:, ::1],  # peak tdoa, value (n_pairs, n_peaks)
                numba.bool_[::1]),        # usable channels (M,), output
    cache=True, nogil=True, error_model="numpy",
)
def _frame(spectra, valid, old, old_usable, noise, smooth, noise_l1, cross, corr, mag, params, peak_tdoa,
           peak_value, usable):
    """One frame: noise cross-power removal and update (from the delayed frame ``old``), PHAT, batched irfft,
    N best peaks per pair."""
    n_bins, m = spectra.shape
    if noise.shape[1] != n_bins or noise.shape[0] != m * (m - 1) // 2:
        return _BAD_SPECTRA_SHAPE
    if valid.shape[0] != m:
        return _BAD_VALID_SHAPE
    if old.shape[0] != m or old.shape[1] != n_bins or old_usable.shape[0] != m:
        return _BAD_SPECTRA_SHAPE
    if mag.shape[0] != m or mag.shape[1] != n_bins:
        return _BAD_SPECTRA_SHAPE
    spectra, valid, noise, cross = borrowed(spectra), borrowed(valid), borrowed(noise), borrowed(cross)
    smooth, old, old_usable, noise_l1 = borrowed(smooth), borrowed(old), borrowed(old_usable), borrowed(noise_l1)
    corr, peak_tdoa, peak_value, usable = borrowed(corr), borrowed(peak_tdoa), borrowed(peak_value), borrowed(usable)
    mag = borrowed(mag)
    spec = spectra.T
    max_lag = int(params[_P_MAX_LAG])
    rate_hz = params[_P_RATE_HZ]
    mode = int(params[_P_MODE])
    a = np.float32(params[_P_ALPHA] * (1.0 - min(max(params[_P_SPEECH], 0.0), 1.0)))
    update = params[_P_UPDATE] != 0.0
    b = np.float32(params[_P_SMOOTH])
    phi_scale = np.float32(params[_P_NOISE_SCALE])
    fast = (np.float32(params[_P_SMOOTH_FAST]), params[_P_FAST_LO_DB], params[_P_FAST_HI_DB])
    peaks = params[_P_PEAKS] != 0.0   # False: the averages only, no weighting, correlation or peaks
    beta = params[_P_BETA]
    # the exponent only weighs a frame whose peaks are searched: no SNR share (nor |X_i|) for the others
    beta_near_noise = params[_P_BETA_NEAR_NOISE] != 0.0 and beta != 1.0 and mode != 0 and peaks
    for i in range(m):
        usable[i] = _channel_ok(spec[i], valid[i])
    adapt = fast[0] > b and mode != 0   # the average's time constant follows each pair's SNR this frame
    if adapt or beta_near_noise:
        for i in range(m):
            if usable[i]:
                xf = spec[i].view(np.float32)
                for k in range(n_bins):   # |X_i| for the pairs' cross power (a dB figure: sqrt, not hypot)
                    mag[i, k] = np.sqrt(xf[2 * k] * xf[2 * k] + xf[2 * k + 1] * xf[2 * k + 1])
    p = 0
    for i in range(m - 1):
        xi = spec[i]
        for j in range(i + 1, m):
            g = cross[p]
            if usable[i] and usable[j]:
                _pair_spectrum(xi, spec[j], old[i], old[j], noise[p], smooth[p], g, corr[p], a, b, mode,
                               update and old_usable[i] and old_usable[j], phi_scale, adapt, fast, noise_l1[p:p + 1],
                               mag[i], mag[j], peaks, beta, beta_near_noise)
            else:
                g[:] = 0.0
            p += 1
    if not peaks:
        return _OK
    np.fft.irfft(cross, corr.shape[1], -1, None, corr)
    p = 0
    for i in range(m - 1):
        for j in range(i + 1, m):
            if usable[i] and usable[j]:
                _top_peaks(corr[p], max_lag, rate_hz, peak_tdoa[p], peak_value[p])
            else:
                peak_tdoa[p, :] = 0.0
                peak_value[p, :] = 0.0
            p += 1
    return _OK


@_jit
def _noise_frame(noise, cross, corr, max_lag, rate_hz, peak_tdoa, peak_value):
    """PHAT of the noise cross-power spectra themselves, irfft, N best peaks per pair."""
    n_pairs, n_bins = noise.shape
    for p in range(n_pairs):
        g = cross[p]
        phi = noise[p]
        peak = np.float32(0.0)
        for k in range(n_bins):
            peak = max(peak, abs(phi[k]))
        eps = _EPS_REL * peak + _TINY
        for k in range(n_bins):
            g[k] = phi[k] / (abs(phi[k]) + eps)
    np.fft.irfft(cross, corr.shape[1], -1, None, corr)
    for p in range(n_pairs):
        _top_peaks(corr[p], max_lag, rate_hz, peak_tdoa[p], peak_value[p])


class NoiseAwareGcc:
    """GCC-PHAT of every pair with noise cross-power removal and the N best peaks (see module doc).

    Parameters
    ----------
    n_channels : int
        Number of channels ``M >= 2``.
    n_fft : int
        FFT length in samples; spectra have ``n_fft // 2 + 1`` bins.
    sample_rate_hz : float
        Sample rate in Hz.
    hop_s : float
        Time between frames in seconds (sets the noise update's smoothing constant).
    max_tdoa_s : float
        Largest ``|tdoa|`` searched in seconds (capped at ``n_fft // 2 - 1`` samples).
    n_peaks : int
        Peaks kept per pair (``N``), >= 1.
    weighting : {"subtract", "subtract-snr", "phat"}
        How the noise cross-power spectrum is used before the PHAT weighting (module doc).
    noise_time_constant_s : float
        Time constant of the recursive noise cross-power average over non-speech frames, seconds.
    smoothing_time_constant_s : float
        Time constant of the short-time average of every pair's cross-power spectrum that the noise is removed
        from (0: each frame alone, the paper's eq. 4). A few frames of the same talker give a much steadier
        peak than one in reverberation and noise; it must stay short against a moving talker and a turn.
    fast_smoothing_time_constant_s : float, optional
        A shorter time constant for frames whose cross power stands well above the noise's: the average moves
        from ``smoothing_time_constant_s`` to this one as a pair's frame cross power rises from
        ``FAST_SNR_DB[0]`` to ``FAST_SNR_DB[1]`` above the noise cross power (and while no noise was averaged
        yet). A smoothed peak lags a moving talker by about the time constant times its TDOA rate, and the
        track's rate then lags too; where the talker stands clear of the noise it does not need the average.
        None (default): one time constant.
    noise_delay_s : float
        The noise average takes each frame this long after it was heard, weighted by ``1 - max p`` over the
        frames since: a talker's onset, heard before the speech detector fires, then never enters it (0: each
        frame at once, weighted by its own ``p``).
    phat_beta : float
        The PHAT weighting's exponent ``beta`` in ``G / |G|^beta``, in (0, 1] (1: PHAT). Below 1 the louder
        bins (in a room with a point noise source: the talker's harmonics, once the noise's cross power is
        removed) count for more; "subtract-snr" ignores it.
    phat_beta_near_noise : bool
        With ``phat_beta`` < 1: each pair's exponent moves from ``phat_beta`` to 1 (PHAT) as its frame's cross
        power rises from ``FAST_SNR_DB[0]`` to ``FAST_SNR_DB[1]`` above the noise cross power: the weighting
        where the noise is, PHAT where the pair stands clear of it (a real room's coherent low-frequency
        reflections are louder bins too). Only with "subtract" (other weightings raise ValueError).
    """

    def __init__(self, n_channels: int, *, n_fft: int, sample_rate_hz: float, hop_s: float,
                 max_tdoa_s: float, n_peaks: int = 3, weighting: Weighting = "subtract",
                 noise_time_constant_s: float = 1.0, smoothing_time_constant_s: float = 0.0,
                 fast_smoothing_time_constant_s: float | None = None, noise_delay_s: float = 0.0,
                 phat_beta: float = 1.0, phat_beta_near_noise: bool = False) -> None:
        if int(n_channels) != n_channels or n_channels < 2:
            raise ValueError(f"{n_channels=} must be an integer >= 2")
        if int(n_fft) != n_fft or n_fft < 8:
            raise ValueError(f"{n_fft=} must be an integer number of samples >= 8")
        for name, value in (("sample_rate_hz", sample_rate_hz), ("hop_s", hop_s), ("max_tdoa_s", max_tdoa_s),
                            ("noise_time_constant_s", noise_time_constant_s)):
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name}={value!r} must be finite and > 0")
        if int(n_peaks) != n_peaks or n_peaks < 1:
            raise ValueError(f"{n_peaks=} must be an integer >= 1")
        if weighting not in _WEIGHTINGS:
            raise ValueError(f"{weighting=} must be one of {', '.join(_WEIGHTINGS)}")
        if not (np.isfinite(phat_beta) and 0 < phat_beta <= 1):
            raise ValueError(f"{phat_beta=} must be in (0, 1]")
        if phat_beta != 1 and weighting == "subtract-snr":
            raise ValueError(f"{phat_beta=} has no effect with weighting='subtract-snr' (its per-bin SNR weight "
                             "takes the place of PHAT-beta): use 'subtract' or 'phat', or phat_beta=1")
        if phat_beta_near_noise and weighting != "subtract":
            raise ValueError(f"phat_beta_near_noise needs weighting='subtract', not {weighting!r}: it measures "
                             "each pair against the noise cross power that 'subtract' removes")
        self.n_channels = int(n_channels)
        self.n_fft = int(n_fft)
        self.n_bins = self.n_fft // 2 + 1
        self.n_pairs = self.n_channels * (self.n_channels - 1) // 2
        self.sample_rate_hz = float(sample_rate_hz)
        self.n_peaks = int(n_peaks)
        self.weighting = weighting
        self.max_lag_samples = int(min(math.floor(max_tdoa_s * sample_rate_hz + 1e-9), self.n_fft // 2 - 1))
        self.max_tdoa_s = self.max_lag_samples / self.sample_rate_hz
        self.noise_time_constant_s = float(noise_time_constant_s)
        self._params = np.zeros(_N_PARAMS)
        self._params[_P_MAX_LAG] = self.max_lag_samples
        self._params[_P_RATE_HZ] = self.sample_rate_hz
        self._params[_P_ALPHA] = 1.0 - math.exp(-hop_s / noise_time_constant_s)
        self._params[_P_MODE] = _WEIGHTINGS[weighting]
        self._params[_P_N_PEAKS] = self.n_peaks
        self._params[_P_UPDATE] = 1.0
        self._params[_P_PEAKS] = 1.0
        self.phat_beta = float(phat_beta)
        self._params[_P_BETA] = self.phat_beta
        self.phat_beta_near_noise = bool(phat_beta_near_noise)
        self._params[_P_BETA_NEAR_NOISE] = float(self.phat_beta_near_noise)
        if not (np.isfinite(smoothing_time_constant_s) and smoothing_time_constant_s >= 0):
            raise ValueError(f"{smoothing_time_constant_s=} must be finite and >= 0")
        self.smoothing_time_constant_s = float(smoothing_time_constant_s)
        self._params[_P_SMOOTH] = (1.0 if smoothing_time_constant_s == 0
                                   else 1.0 - math.exp(-hop_s / smoothing_time_constant_s))
        fast = fast_smoothing_time_constant_s
        if fast is not None and not (np.isfinite(fast) and 0 <= fast <= smoothing_time_constant_s):
            raise ValueError(f"fast_smoothing_time_constant_s={fast} must be in 0..smoothing_time_constant_s")
        self.fast_smoothing_time_constant_s = None if fast is None else float(fast)
        # off (fast = slow): the kernel skips the test
        self._params[_P_SMOOTH_FAST] = (self._params[_P_SMOOTH] if fast is None
                                        else 1.0 if fast == 0 else 1.0 - math.exp(-hop_s / fast))
        self._params[_P_FAST_LO_DB], self._params[_P_FAST_HI_DB] = FAST_SNR_DB
        if not (np.isfinite(noise_delay_s) and noise_delay_s >= 0):
            raise ValueError(f"{noise_delay_s=} must be finite and >= 0")
        self.noise_delay_frames = int(round(noise_delay_s / hop_s))
        d = self.noise_delay_frames
        # the last d frames (channel-major spectra, usable channels, speech presence); slot _ring_pos is the oldest
        self._ring = np.zeros((max(d, 1), self.n_channels, self.n_bins), np.complex64)
        self._ring_usable = np.zeros((max(d, 1), self.n_channels), np.bool_)
        self._ring_p = [1.0] * max(d, 1)
        self._ring_pos = 0
        self._noise = np.zeros((self.n_pairs, self.n_bins), np.complex64)
        self._smooth = np.zeros((self.n_pairs, self.n_bins), np.complex64)
        self._noise_l1 = np.zeros(self.n_pairs)   # sum over bins of |noise cross power|, per pair
        self._cross = np.zeros((self.n_pairs, self.n_bins), np.complex64)
        self._corr = np.zeros((self.n_pairs, self.n_fft), np.float32)
        self._mag = np.zeros((self.n_channels, self.n_bins), np.float32)
        self._usable = np.zeros(self.n_channels, np.bool_)
        self._all_valid = np.ones(self.n_channels, np.bool_)
        self.n_noise_frames = 0.0   # effective number of non-speech frames averaged so far
        self._noise_weight = 0.0    # 1 - prod(1 - a_k): the weight the average has gathered (bias correction)
        self._hops = 0              # frames processed
        self._noise_hop = 0.0       # the noise average's time: the weighted mean of its frames' (hops)
        self._hop_s = float(hop_s)
        self._omega = np.arange(self.n_bins) * (2.0 * np.pi * self.sample_rate_hz / self.n_fft)   # rad/s per bin
        self._pair_idx = pairs(self.n_channels)
        self._params[_P_NOISE_SCALE] = 0.0

    def reset(self) -> None:
        """Forget the noise and short-time cross-power spectra."""
        self._noise[:] = 0.0
        self._smooth[:] = 0.0
        self._noise_l1[:] = 0.0
        self._ring_usable[:] = False
        self._ring_p = [1.0] * len(self._ring_p)
        self.n_noise_frames = 0.0
        self._noise_weight = 0.0
        self._params[_P_NOISE_SCALE] = 0.0

    @property
    def noise_cross_power(self) -> np.ndarray:
        """Copy of the tracked noise cross-power spectra, shape (n_pairs, n_bins), complex64."""
        return self._noise.copy()

    @property
    def noise_mature(self) -> bool:
        """Whether the noise average holds at least ``0.7 noise_time_constant_s`` worth of non-speech frames
        (before that it is mostly the first frames of whatever sounded, a talker's onset included)."""
        return self.n_noise_frames >= 0.5 / self._params[_P_ALPHA]

    @property
    def usable(self) -> np.ndarray:
        """Channels usable in the last frame (valid, finite, not silent), shape (n_channels,), bool."""
        return self._usable.copy()

    def process(self, spectra: np.ndarray, *, speech_probability: float, valid: np.ndarray | None = None,
                update_noise: bool = True, raw: bool = False, peaks: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """N best peaks of every pair for one frame; updates the noise cross-power spectra.

        Parameters
        ----------
        spectra : ndarray, shape (n_bins, n_channels), complex64
            One frame's channel spectra (the layout of :meth:`beamform.StreamingStft.process`; other
            layouts are copied first).
        speech_probability : float
            Speech presence of the frame in ``[0, 1]``: the noise average moves by ``a (1 - p)``.
        valid : ndarray, shape (n_channels,), bool, optional
            Channels to use; pairs with an unusable channel get value 0.
        update_noise : bool
            False: use the noise cross-power spectra without updating them.
        raw : bool
            True: plain PHAT (no removal) for this frame, e.g. on non-speech frames, whose peaks show the
            sources that keep sounding when nobody speaks.
        peaks : bool
            False: update the averages only (no correlation, no peaks: the returned arrays are not filled), for
            the frames between two measurements of a tracker that measures every few frames.

        Returns
        -------
        peak_tdoa_s : ndarray, shape (n_pairs, n_peaks), float64
            Delays of the peaks, highest first, in seconds (``toa_i - toa_j``).
        peak_value : ndarray, shape (n_pairs, n_peaks), float64
            Their heights (PHAT correlation, at most 1); 0 for missing peaks and unusable pairs.
        """
        peak_tdoa = np.empty((self.n_pairs, self.n_peaks))
        peak_value = np.empty((self.n_pairs, self.n_peaks))
        if valid is None:
            valid = self._all_valid
        p = float(speech_probability) if np.isfinite(speech_probability) else 1.0
        d = self.noise_delay_frames
        if d:   # the oldest frame kept updates the noise, unless speech was heard since
            p_update = max(p, max(self._ring_p))
        else:
            p_update = p
        self._params[_P_SPEECH] = p_update
        self._params[_P_UPDATE] = 1.0 if update_noise else 0.0
        self._params[_P_MODE] = 0 if raw else _WEIGHTINGS[self.weighting]
        self._params[_P_PEAKS] = 1.0 if peaks else 0.0
        if not (type(spectra) is np.ndarray and spectra.dtype == np.complex64 and spectra.flags.f_contiguous
                and spectra.flags.writeable):
            spectra = np.asarray(spectra)
            if spectra.shape != (self.n_bins, self.n_channels):
                raise ValueError(f"spectra.shape={spectra.shape} must be (n_bins, n_channels)="
                                 f"{(self.n_bins, self.n_channels)}")
            spectra = np.array(spectra.T, dtype=np.complex64, order="C").T
        if not (type(valid) is np.ndarray and valid.dtype == np.bool_):
            valid = np.asarray(valid, dtype=np.bool_)
        if d:
            slot = self._ring_pos
            old, old_usable = self._ring[slot], self._ring_usable[slot]
            if not old_usable.any():
                p_update = 1.0   # the oldest slot holds no usable channel (not yet filled): nothing to add
                self._params[_P_SPEECH] = 1.0
        else:
            old, old_usable = spectra.T, self._usable   # the kernel sets usable before it uses it
        code = _frame(spectra, valid, old, old_usable, self._noise, self._smooth, self._noise_l1, self._cross,
                      self._corr, self._mag, self._params, peak_tdoa, peak_value, self._usable)
        if code == _BAD_SPECTRA_SHAPE:
            raise ValueError(f"spectra.shape={spectra.shape} must be (n_bins, n_channels)="
                             f"{(self.n_bins, self.n_channels)}")
        if code == _BAD_VALID_SHAPE:
            raise ValueError(f"valid.shape={np.shape(valid)} must be ({self.n_channels},)")
        if d:
            self._ring[slot] = spectra.T
            self._ring_usable[slot] = self._usable
            self._ring_p[slot] = p
            self._ring_pos = (slot + 1) % d
        self._hops += 1
        if update_noise:
            a = self._params[_P_ALPHA] * (1.0 - min(max(p_update, 0.0), 1.0))
            if a > 0.0:   # the average's time: the weighted mean of its frames' (the one joining is d hops old)
                w = (1.0 - a) * self._noise_weight
                self._noise_hop = (w * self._noise_hop + a * (self._hops - d)) / (w + a)
            self.n_noise_frames = (1.0 - a) * self.n_noise_frames + a / self._params[_P_ALPHA]
            self._noise_weight += a * (1.0 - self._noise_weight)
            self._params[_P_NOISE_SCALE] = 1.0 / self._noise_weight if self._noise_weight > 1e-6 else 0.0
        return peak_tdoa, peak_value

    @property
    def noise_age_s(self) -> float:
        """How long ago, on average, the frames of the noise average were taken (seconds; 0 before any)."""
        return (self._hops - self._noise_hop) * self._hop_s if self._noise_weight > 0 else 0.0

    @property
    def short_time_cross_power(self) -> np.ndarray:
        """The short-time average of every pair's cross power ``X_i X_j^*`` (``smoothing_time_constant_s``;
        the last frame's when 0), shape (n_pairs, n_bins), complex64: a view, valid until the next frame."""
        return self._smooth

    def shift_noise(self, delta_toa_s: np.ndarray, *, short_time: bool = True) -> None:
        """Move the noise cross-power spectra by a known change of the channels' relative TOAs.

        The noise average holds the noise's delays of the frames it averaged: when clock drift moves them (at
        100 ppm, 0.5 ms in 5 s of speech, while the average only takes non-speech frames) or the aligner moves a
        channel, the removal would subtract the noise where it was, and leave it where it is. Each pair's
        spectra are turned by the pair's change, ``exp(-2 pi j f (d_i - d_j))``, as that of a source moved by it.

        Parameters
        ----------
        delta_toa_s : ndarray, shape (n_channels,)
            Change of each channel's TOA (seconds); a common part changes nothing.
        short_time : bool
            Turn the short-time average (:attr:`short_time_cross_power`) too (a re-alignment); False for clock
            drift, whose rotation a :class:`~estimators.DriftMeter` measures there.
        """
        d = np.asarray(delta_toa_s, dtype=np.float64)
        if d.shape != (self.n_channels,):
            raise ValueError(f"delta_toa_s.shape={d.shape} must be ({self.n_channels},)")
        if not np.isfinite(d).all() or not np.any(d != d[0]):
            return
        i, j = self._pair_idx.T
        chan = delay_phasors(d, self._omega)   # per channel, then per pair: 8 channels' trig, not 28 pairs'
        rot = chan[i] * np.conj(chan[j])
        self._noise *= rot
        if short_time:
            self._smooth *= rot
        if self.noise_delay_frames:   # the frames still to join the noise average
            self._ring *= chan[None]

    def noise_peaks(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """N best peaks of the PHAT-weighted noise cross-power spectra: the persistent noise sources.

        Returns
        -------
        peak_tdoa_s, peak_value : ndarray, shape (n_pairs, n_peaks), float64
            As :meth:`process`; all values 0 before any non-speech frame was seen.
        correlation : ndarray, shape (n_pairs, n_fft), float32
            The whole noise GCC-PHAT correlation of every pair (lag ``k`` at index ``k mod n_fft``).
        """
        peak_tdoa = np.empty((self.n_pairs, self.n_peaks))
        peak_value = np.empty((self.n_pairs, self.n_peaks))
        _noise_frame(self._noise, self._cross, self._corr, self.max_lag_samples, self.sample_rate_hz, peak_tdoa,
                     peak_value)
        return peak_tdoa, peak_value, self._corr.copy()
