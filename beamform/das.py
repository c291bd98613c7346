"""Online weighted delay-and-sum beamformer in the STFT domain (TOA paper eqs. 7-8).

Conventions
-----------
- ``toa_s[i]`` is the relative time of arrival of the talker at device ``i`` in seconds,
  ``toa_s[0] = 0``; positive means device ``i`` hears it later (see ``estimators.conventions``).
- Channel ``i`` is advanced by ``toa_s[i]``: ``Z_i(w) = a_i(w) X_i(w)`` with the steering vector
  ``a_i(w) = exp(+i w toa_i)`` (eq. 7), and the output is ``Y(w) = sum_i w_i Z_i(w)`` (eq. 8 with
  weights ``w_i >= 0``, ``sum_i w_i = 1`` so that the output level is that of one device).
- Spectra come from :class:`beamform.stft.StreamingStft` with the same frame, hop and window; the
  output is synthesised by :class:`beamform.stft.StreamingIstft` and lags device 0's input by
  ``latency_samples = frame_samples - hop_samples``.

Weighting
---------
``"equal"``: ``w_i = 1 / M_valid`` on the valid channels.

``"adaptive"``: maximal-ratio combining (MRC) with online estimates of each aligned channel's target
gain and noise power. After alignment, channel ``i`` is modelled as ``Z_i = g_i S + N_i`` with the
noise (reverberation, other sources, sensor noise) uncorrelated across devices. The smoothed real
cross-power matrix of the aligned spectra, summed over the bins of ``weight_band_hz``,

    ``C_ij = E[ sum_b Re(Z_i(b) Z_j(b)^*) ]  ~  g_i g_j P_S + delta_ij sigma_i^2``

(bias-corrected exponential forgetting, time constant ``weight_time_constant_s``), gives the gains
from a rank-one fit to its off-diagonal part (a channel is never compared with itself, so it cannot
vote for itself) and the noise power from the rest of the diagonal:

    ``g = argmin_g sum_{i != j} (C_ij - g_i g_j)^2``,
    ``sigma_i^2 = max(C_ii - g_i^2, C_ii 10^(-max_channel_snr_db / 10))``.

The fit runs damped alternating least-squares steps warm-started from the previous frame: ten per
frame during the first second, then one (the statistics move slowly, so it tracks the fixed point).
MRC weights ``w_i ~ g_i / sigma_i^2`` maximise the output target-to-noise ratio under this model
(output SNR = sum of the channel SNRs); they are raised to ``weight_exponent``, floored at
``weight_floor / M_valid`` and normalised to sum to 1. ``sum_b Re(Z_i Z_j^*)`` is the zero-lag
cross-correlation of the band-passed aligned frames (as in BeamformIt), so misaligned or diffuse
components contribute little. With two valid channels the rank-one fit cannot separate gain from
noise; the gains then keep the ratio of their first estimate (``sqrt`` of the channel powers).

Evaluated on pyroomacoustics scenes (6 devices 0.5-3 m from the talker, RT60 0.4 s, dish-washing
noise, true TOA, frame 1024): SI-SDR +1.3 dB over the best single device and +1.4 dB over
equal-weight DAS on average, within ~0.5 dB of MRC with oracle weights. Known limits: per-band
weights lost 0.5-1.4 dB (noisier statistics, spectral colouring), so the weights are broadband; on
compact arrays (all devices within 1.5 m) devices share coherent reflections/noise, the rank-one
model over-credits neighbours and equal weights are 0.3-0.6 dB better (``weight_exponent=0.7``
halves that loss at ~0.1 dB cost on spread arrays).

``"level"``: equal weights on the channels brought to one noise floor, ``w_i ~ 1 / sigma_i`` with
``sigma_i^2`` the geometric mean of channel ``i``'s frame power over the pauses (frames the caller marks so
in :meth:`DelayAndSum.note_frame`; time constant ``level_time_constant_s``; counted after
``level_min_pause_s`` of pauses), held within ``level_max_ratio`` of the median channel's, and not raised
above it for a channel whose SNR is more than ``level_snr_margin_db`` below the median's. Devices of an
ad-hoc array differ in gain by more than in what they hear (a phone against a laptop: 10-20 dB), and equal
weights let the loudest-gain device own the beam; here every device counts by what it hears above its own
floor, and a device next to a noise source counts less. Unlike ``"adaptive"`` nothing is fitted to the
talker, so a wrong steering cannot move the weights. Measured on the generated scenes and the measured
office (README, "Channel weights").

With ``level_snr_exponent`` ``p > 0`` each "level" weight is also multiplied by ``(SNR_i / SNR_med)^(p / 2)``
(then held within ``level_max_ratio`` again), ``SNR_i = exp(S_i - L_i) - 1`` from channel ``i``'s average log
power over the speech frames ``S_i`` and over the pauses ``L_i`` (at least -20 dB): ``p = 1`` is maximal-ratio
combining on the channels brought to one floor (output SNR = sum of the channels' SNRs when their noises are
independent), so a device next to the talker counts more. Unlike ``"adaptive"`` it still fits nothing to the
talker: two averages of frame power per device, split by the speech detector. The engine uses ``p = 1``
(``EngineConfig.level_snr_exponent``); this class's default is 0. :meth:`DelayAndSum.set_level_factors` multiplies
each "level" weight by a factor the caller gives (held within ``level_max_ratio`` again): the pipeline's is each
device's matched GCC peak height on the steered talker track over the median device's, to the power
``EngineConfig.level_height_exponent``: the SNR is a power ratio and counts a far device's reverberation as signal.

Invalid channels (``valid[i] == False``, a non-finite ``toa_s[i]`` or any non-finite value in the
channel's spectrum) get weight 0 and are left out of the statistics for that frame; the others are
renormalised. NaN never reaches the output. With no valid channel the output frame is silent.

Implementation
--------------
One hop of :meth:`DelayAndSum.process_spectra` is one compiled numba call (``_das_process``):
validity, steering, weights, sum, then ``irfft`` (rocket-fft's ``np.fft`` inside numba) and the
weighted overlap-add of :mod:`beamform.stft`. The steering is not tabulated per TOA: per channel the
phase step ``omega_1 toa_i`` is reduced modulo ``2 pi`` (in turns, exactly), the exact phasor
``e_1 = exp(i omega_1 toa)`` seeds a float64 recurrence for ``exp(i omega_k toa)``, ``k <= K``, whose
last term ``e_K`` seeds a second one for every K-th bin, and each bin is a float32 product of the two
(error < 2e-7 relative for any TOA, all bins; two transcendental calls per channel and frame). The
statistics (``C``, the fit, the weights) are float64; the band cross-power of a frame is summed in
float32 SIMD lanes.

The pure function :func:`delay_and_sum` runs the same stage over a whole recording.
"""
from __future__ import annotations

import math
from typing import Literal

import numba
import numpy as np

from estimators.numba_tools import all_finite, borrowed

from .stft import StreamingIstft, StreamingStft, _synthesise, istft, stft

__all__ = ["DelayAndSum", "delay_and_sum"]

Weighting = Literal["equal", "adaptive", "level"]

_F64 = np.dtype(np.float64)
_C64 = np.dtype(np.complex64)
_BOOL = np.dtype(np.bool_)

# Layout of the state, parameter and work arrays the kernels take (a few arrays instead of a dozen
# arguments: every argument of a compiled call costs ~40 ns to unbox).
# fstate, float64:
_MASS = 0         # bias-correction mass m_t of the exponential forgetting (state)
_BIN_HZ = 1       # sample_rate_hz / frame_samples: turns of phase per bin per second of TOA
_FORGET = 2       # forgetting factor lambda per frame
_INV_SNR_MAX = 3  # 10^(-max_channel_snr_db / 10)
_FLOOR = 4        # weight_floor
_EXPONENT = 5     # weight_exponent
_LEVEL_FORGET = 6  # "level": forgetting factor per frame of the noise-floor and speech-level averages
_LEVEL_MAX = 7    # largest weight ratio of a channel to the median channel's ("level")
_LEVEL_SNR_MARGIN = 8  # "level": a channel more than this (log power) below the median SNR is not boosted
_LEVEL_MIN_MASS = 9   # "level": a floor counts once its bias-correction mass (frames, forgetting) reaches this
_LEVEL_SNR_EXPONENT = 10  # "level": a channel's weight also scales as (its SNR over the median SNR)^(this / 2)
# istate, int64:
_N_UPDATES = 0    # frames that updated the rank-one fit (state)
_ADAPTIVE = 1     # the weighting: _EQUAL, _MRC or _LEVEL
_LO = 2           # statistics band: bins [lo, hi)
_HI = 3
_STARTUP_FRAMES = 4
_STARTUP_ITER = 5
_N_FINE = 6       # K: fine phasors per channel (see _steer)
_EQUAL, _MRC, _LEVEL = 0, 1, 2
_MODES = {"equal": _EQUAL, "adaptive": _MRC, "level": _LEVEL}
# f64, float64 (M + 1 + _N_WORK, M): the smoothed cross-power C (M rows), the gains g (1 row), then 14
# work rows: validity (0/1), e_1 = exp(i omega_1 toa), the running fine phasor, the rank-one fit's
# gains, its products, the float64 weights, and the state of "level": each channel's average log power
# over the pauses (its noise floor) and its bias-correction mass, then the same over speech frames, then the
# log factors the caller gives each channel's "level" weight (:meth:`DelayAndSum.set_level_factors`).
_N_WORK = 14
(_VALID, _E_RE, _E_IM, _F_RE, _F_IM, _G, _GM, _G_NEW, _W, _LOG_FLOOR, _FLOOR_MASS, _LOG_SPEECH, _SPEECH_MASS,
 _LOG_FACTOR) = range(_N_WORK)
# f32, float32: [channel weights (M) | fine phasors (M, 2, K) | steering row (2 J K)].
_TWO_PI = 2.0 * math.pi


@numba.njit(cache=True, nogil=True, fastmath={"reassoc"})
def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """``sum_t a[t] b[t]`` of two float32 rows, summed in float32 SIMD lanes (``reassoc``).

    On the interleaved (re, im) views of two aligned spectra this is ``sum_b Re(Z_i(b) Z_j(b)^*)``;
    relative error ~1e-7 of ``sum |a b|``, as a float32 BLAS product would give (a float64 sum
    took 1.7x as long).
    """
    s = np.float32(0.0)
    for t in range(a.shape[0]):
        s += a[t] * b[t]
    return s


@numba.njit(cache=True, nogil=True)
def _steer(x: np.ndarray, kr: float, ki: float, fine: np.ndarray, row: np.ndarray, weight: float, out: np.ndarray,
           accumulate: bool) -> None:
    """``out (+)= weight exp(+i 2 pi b turns) X(b)`` for every bin ``b`` (eqs. 7-8 for one channel).

    ``x`` and ``out`` are interleaved (re, im) float32 rows of ``n_bins`` values; ``turns`` is
    ``omega_1 toa / 2 pi`` reduced to [-1/2, 1/2] (whole turns drop out exactly); ``fine`` (2, K)
    holds ``f_k = exp(i 2 pi k turns)``, ``k < K``, and ``kr + i ki = e_K = exp(i 2 pi K turns)``,
    both from the float64 recurrence of :func:`_beamform` (error ~ K 1e-16). With ``b = j K + k``
    the steering is ``c_j f_k``, ``c_j = exp(i 2 pi j K turns)``: ``c`` follows the recurrence
    ``c_{j+1} = c_j e_K`` in float64 (error ~ (j + 1) K 1e-16), the weight is folded into ``c_j``,
    and each block of K bins is the float32 product ``c_j f_k`` (vectorised along k; steering
    error <= ~2e-7 relative). ``row`` is a float32 work row of ``2 J K`` values.
    """
    n_bins = x.shape[0] // 2
    n_fine = fine.shape[1]
    fr = fine[0]
    fi = fine[1]
    cr = weight
    ci = 0.0
    for base in range(0, n_bins, n_fine):
        a = np.float32(cr)
        b = np.float32(ci)
        seg = row[2 * base : 2 * base + 2 * n_fine]
        for k in range(n_fine):
            seg[2 * k] = a * fr[k] - b * fi[k]
            seg[2 * k + 1] = a * fi[k] + b * fr[k]
        cr, ci = cr * kr - ci * ki, cr * ki + ci * kr
    if accumulate:
        for t in range(n_bins):
            xr = x[2 * t]
            xi = x[2 * t + 1]
            sr = row[2 * t]
            si = row[2 * t + 1]
            out[2 * t] += xr * sr - xi * si
            out[2 * t + 1] += xr * si + xi * sr
    else:
        for t in range(n_bins):
            xr = x[2 * t]
            xi = x[2 * t + 1]
            sr = row[2 * t]
            si = row[2 * t + 1]
            out[2 * t] = xr * sr - xi * si
            out[2 * t + 1] = xr * si + xi * sr


@numba.njit(cache=True, nogil=True)
def _learn_floors(X: np.ndarray, valid: np.ndarray, work: np.ndarray, fstate: np.ndarray, pause: bool) -> None:
    """``"level"``: one frame's power ``p_i = sum_b |X_i(b)|^2`` of each valid channel into its noise floor
    (a ``pause``: nobody speaks) or its speech level (otherwise), each the bias-corrected exponential average
    of ``log p_i`` (``L_i += (log p_i - L_i) / m_i``, ``m_i = lambda m_i + 1``). A frame of digital silence
    or with a non-finite value leaves both alone."""
    floor = work[_LOG_FLOOR] if pause else work[_LOG_SPEECH]
    mass = work[_FLOOR_MASS] if pause else work[_SPEECH_MASS]
    lam = fstate[_LEVEL_FORGET]
    for i in range(X.shape[0]):
        if valid[i]:
            p = 0.0
            for b in range(X.shape[1]):
                v = X[i, b]
                p += v.real * v.real + v.imag * v.imag
            if p > 1e-30 and math.isfinite(p):
                mass[i] = lam * mass[i] + 1.0
                floor[i] += (math.log(p) - floor[i]) / mass[i]


@numba.njit(cache=True, nogil=True)
def _log_snr(log_ratio: float) -> float:
    """``log SNR`` from ``log((S + N) / N)``, a speech level over a floor; the SNR at least -20 dB."""
    return math.log(max(math.exp(min(log_ratio, 700.0)) - 1.0, 0.01))


@numba.njit(cache=True, nogil=True)
def _level_weights(work: np.ndarray, fstate: np.ndarray, n_ok: int, weights: np.ndarray) -> bool:
    """``"level"``: equal weights on the channels brought to one noise floor (:func:`_learn_floors`),
    ``w_i = exp(-L_i / 2)``, held within ``[1 / r, r]`` times the median valid channel's
    (``r = fstate[_LEVEL_MAX]``), normalised to sum to 1 over the valid channels. A floor counts once
    ``fstate[_LEVEL_MIN_MASS]`` frames of pauses made it (a few frames at a talker's onset or in a
    reverberant tail are not a floor); a channel without one counts as the median channel. With none, it
    returns False and leaves ``weights`` alone (the caller gives equal ones).

    A channel whose floor is below the median but whose SNR (speech level over floor) is more than
    ``fstate[_LEVEL_SNR_MARGIN]`` below the median SNR is not raised above the median: its floor is low
    because its own electronics are quiet, not because its gain is (``async_8dev``'s device 5: 15 dB of gain
    down, a floor 15 dB down, 8 dB less SNR). With ``fstate[_LEVEL_SNR_EXPONENT]`` ``p > 0``, a channel with a
    floor and a speech level is then also weighted by ``(SNR_i / SNR_med)^(p / 2)`` (:func:`_log_snr`) and
    held within ``[1 / r, r]`` again."""
    m = work.shape[1]
    ok = work[_VALID]
    floor = work[_LOG_FLOOR]
    mass = work[_FLOOR_MASS]
    min_mass = fstate[_LEVEL_MIN_MASS]
    floors = np.empty(n_ok)   # the valid channels' floors, then their SNRs
    k = 0
    for i in range(m):
        if ok[i] and mass[i] >= min_mass:
            floors[k] = floor[i]
            k += 1
    if k == 0:
        return False
    middle = np.median(floors[:k])
    # each channel's SNR (log speech-frame power over its floor) against the median channel's
    speech = work[_LOG_SPEECH]
    smass = work[_SPEECH_MASS]
    k2 = 0
    for i in range(m):
        if ok[i] and mass[i] >= min_mass and smass[i] > 0.0:
            floors[k2] = speech[i] - floor[i]
            k2 += 1
    snr_mid = np.median(floors[:k2]) if k2 > 0 else 0.0
    snr_mid_log = _log_snr(snr_mid)
    snr_margin = fstate[_LEVEL_SNR_MARGIN]
    snr_exp = fstate[_LEVEL_SNR_EXPONENT]
    limit = math.log(fstate[_LEVEL_MAX])
    w64 = work[_W]
    total = 0.0
    for i in range(m):
        if ok[i]:
            e = -0.5 * (floor[i] - middle) if mass[i] >= min_mass else 0.0
            e = min(max(e, -limit), limit)
            if e > 0.0 and k2 > 0 and smass[i] > 0.0 and speech[i] - floor[i] < snr_mid - snr_margin:
                e = 0.0   # a low floor but a low SNR too: its own quiet electronics, not a low gain
            if snr_exp > 0.0 and k2 > 0 and mass[i] >= min_mass and smass[i] > 0.0:
                # maximal-ratio combining on the channels brought to one floor: amplitude SNR ^ exponent
                e = min(max(e + 0.5 * snr_exp * (_log_snr(speech[i] - floor[i]) - snr_mid_log), -limit), limit)
            if work[_LOG_FACTOR, i] != 0.0:
                e = min(max(e + work[_LOG_FACTOR, i], -limit), limit)
            w64[i] = math.exp(e)
            total += w64[i]
    for i in range(m):
        weights[i] = np.float32(w64[i] / total) if ok[i] else np.float32(0.0)
    return True


@numba.njit(cache=True, nogil=True)
def _adaptive_weights(stats: np.ndarray, fstate: np.ndarray, istate: np.ndarray, work: np.ndarray, n_ok: int,
                      w: np.ndarray) -> None:
    """MRC weights from the smoothed cross-power ``C = stats[:M]`` (already updated with this
    frame) and the rank-one gains ``g = stats[M]`` (module docstring), into ``w`` (float64).

    Damped ALS steps of ``g = argmin sum_{i != j} (C_ij - g_i g_j)^2`` over the valid channels
    (``n_iter`` per frame: the start-up count during the first second, then 1),
    ``g_i <- sqrt(g_i max(sum_{j != i} C_ij g_j, 0) / sum_{j != i} g_j^2)`` clipped to
    ``[1e-6 sqrt(max C_ii), sqrt(C_ii)]``; ``sigma_i^2 = max(C_ii - g_i^2, C_ii 10^(-snr_max / 10))``;
    ``w_i ~ (g_i / sigma_i^2)^p``, floored at ``floor / M_valid``, normalised to sum 1. The gains
    of invalid channels are kept for later frames.
    """
    m = w.shape[0]
    ok = work[_VALID]
    g = work[_G]
    gm = work[_GM]
    g_new = work[_G_NEW]
    gain = stats[m]
    d_max = 0.0
    for i in range(m):
        d_max = max(d_max, stats[i, i] * ok[i])
    if not d_max > 0.0:
        for i in range(m):
            w[i] = ok[i] / n_ok
        return
    tiny = 1e-12 * d_max
    g_max = gain[0]
    for i in range(1, m):
        g_max = max(g_max, gain[i])
    for i in range(m):  # warm start from the last fit, else half the channel amplitude
        g[i] = gain[i] if g_max > 0.0 else 0.5 * math.sqrt(stats[i, i])
    istate[_N_UPDATES] += 1
    n_iter = istate[_STARTUP_ITER] if istate[_N_UPDATES] <= istate[_STARTUP_FRAMES] else 1
    g_floor = 1e-6 * math.sqrt(d_max)
    for _ in range(n_iter):
        g2_sum = 0.0
        for i in range(m):
            gm[i] = g[i] * ok[i]
            g2_sum += gm[i] * gm[i]
        for i in range(m):
            cg = 0.0
            for j in range(m):
                cg += stats[i, j] * gm[j]
            # g_i <- sum_{j != i} C_ij g_j / sum_{j != i} g_j^2
            g_new[i] = max(cg - stats[i, i] * gm[i], 0.0) / (g2_sum - gm[i] * gm[i] + tiny)
        for i in range(m):  # damped (geometric mean with the last step), g_i^2 <= C_ii
            g[i] = min(max(math.sqrt(g[i] * g_new[i]), g_floor), math.sqrt(stats[i, i]))
    total = 0.0
    for i in range(m):
        if ok[i]:
            gain[i] = g[i]
        d = stats[i, i]
        noise = max(d - g[i] * g[i], d * fstate[_INV_SNR_MAX])  # sigma_i^2 with the SNR cap
        w[i] = g[i] * ok[i] / (noise + tiny)  # MRC: g_i / sigma_i^2
        total += w[i]
    if not total > 0.0:
        for i in range(m):
            w[i] = ok[i] / n_ok
        return
    for i in range(m):
        w[i] /= total
    p = fstate[_EXPONENT]
    if p != 1.0:  # w_i ~ (g_i / sigma_i^2)^p, between equal (0) and MRC (1)
        total = 0.0
        for i in range(m):
            w[i] = w[i] ** p * ok[i]
            total += w[i]
        for i in range(m):
            w[i] /= total
    floor = fstate[_FLOOR]
    if floor > 0.0:
        total = 0.0
        for i in range(m):
            w[i] = max(w[i], floor / n_ok) * ok[i]
            total += w[i]
        for i in range(m):
            w[i] /= total


@numba.njit(cache=True, nogil=True)
def _beamform(X: np.ndarray, toa: np.ndarray, valid: np.ndarray, f64: np.ndarray, fstate: np.ndarray,
              istate: np.ndarray, f32: np.ndarray, Z: np.ndarray) -> None:
    """Eqs. 7-8 for one frame: ``Y = Z[M] = sum_i w_i exp(+i omega toa_i) X_i``, weights ``w``
    (float32) into ``f32[:M]``; array layouts at the top of the module.

    ``X`` (M, n_bins) complex64 channel-major. Channel ``i`` is valid if ``valid[i]``, ``toa[i]``
    is finite and ``X_i`` has no inf/NaN; equal weights are ``1 / M_valid``; adaptive ones come from
    the statistics of the aligned ``Z_i`` (rows of ``Z``) over bins ``[lo, hi)``, updated with
    ``C_ij += (F_ij - C_ij) / m_t``, ``m_t = lambda m_{t-1} + 1`` on valid pairs,
    ``F_ij = sum_b Re(Z_i Z_j^*)``. No valid channel: ``Y = 0``, ``weights = 0``.
    """
    m, n_bins = X.shape
    n_fine = istate[_N_FINE]
    stats = f64[: m + 1]
    work = f64[m + 1 :]
    weights = f32[:m]
    fine = f32[m : m + 2 * m * n_fine].reshape((m, 2, n_fine))
    row = f32[m + 2 * m * n_fine :]
    xf = X.view(np.float32)  # (M, 2 n_bins): interleaved (re, im)
    xbits = X.view(np.uint32)
    zf = Z.view(np.float32)
    y = zf[m]
    ok = work[_VALID]
    er = work[_E_RE]
    ei = work[_E_IM]
    n_ok = 0
    for i in range(m):
        # eq. (7) phase step per bin in turns, omega_1 toa / 2 pi (a non-finite one, also from an
        # overflowing toa, cannot be steered), then reduced exactly to [-1/2, 1/2]
        u = toa[i] * fstate[_BIN_HZ]
        good = valid[i] and math.isfinite(u) and all_finite(xbits[i])
        ok[i] = 1.0 if good else 0.0
        n_ok += good
        if not good:
            u = 0.0
        u -= np.rint(u)
        er[i] = math.cos(_TWO_PI * u)
        ei[i] = math.sin(_TWO_PI * u)
    if n_ok == 0:
        y[:] = 0.0
        weights[:] = 0.0
        return
    # fine[i, :, k] = exp(i 2 pi k turns_i) by the recurrence f_{k+1} = f_k e_1 in float64, all
    # channels in step (error ~ k 1e-16); it ends at f_K = e_K, the coarse step of _steer.
    fr = work[_F_RE]
    fi = work[_F_IM]
    fr[:] = 1.0
    fi[:] = 0.0
    for k in range(n_fine):
        for i in range(m):
            fine[i, 0, k] = fr[i]
            fine[i, 1, k] = fi[i]
            fr[i], fi[i] = fr[i] * er[i] - fi[i] * ei[i], fr[i] * ei[i] + fi[i] * er[i]
    mode = istate[_ADAPTIVE]
    if mode != _MRC:   # equal weights, or "level" ones (equal until a channel has a noise floor)
        if mode == _EQUAL or not _level_weights(f64[m + 1 :], fstate, n_ok, weights):
            w = np.float32(1.0) / np.float32(n_ok)
            for i in range(m):
                weights[i] = w if ok[i] else np.float32(0.0)
        y[:] = 0.0
        for i in range(m):
            if ok[i]:
                _steer(xf[i], fr[i], fi[i], fine[i], row, np.float64(weights[i]), y, True)
        return
    for i in range(m):
        if ok[i]:
            _steer(xf[i], fr[i], fi[i], fine[i], row, 1.0, zf[i], False)
    # Band cross-power of this frame into the smoothed statistics, valid pairs only.
    fstate[_MASS] = fstate[_FORGET] * fstate[_MASS] + 1.0
    rate = 1.0 / fstate[_MASS]
    lo = 2 * istate[_LO]  # interleaved (re, im) floats of the band's bins
    hi = 2 * istate[_HI]
    for i in range(m):
        if ok[i]:
            band_i = zf[i, lo:hi]  # (row, slice) indexing keeps the contiguous layout for _dot
            for j in range(i + 1):
                if ok[j]:
                    c = stats[i, j] + rate * (np.float64(_dot(band_i, zf[j, lo:hi])) - stats[i, j])
                    stats[i, j] = c
                    stats[j, i] = c
    w64 = work[_W]
    _adaptive_weights(stats, fstate, istate, work, n_ok, w64)
    first = True
    for i in range(m):
        wi = np.float32(w64[i])
        weights[i] = wi
        if ok[i]:
            zi = zf[i]
            if first:
                for t in range(2 * n_bins):
                    y[t] = wi * zi[t]
                first = False
            else:
                for t in range(2 * n_bins):
                    y[t] += wi * zi[t]


# Return codes of the entry kernels (nothing is computed or changed unless _OK).
_OK, _BAD_SPECTRA_SHAPE, _BAD_TOA_SHAPE, _BAD_VALID_SHAPE = 0, 1, 2, 3
# Entry kernels are compiled for exactly these types (eagerly, from the cache): the common inputs
# pass without a conversion, anything else is a TypeError at the call and the caller converts.
_ENTRY_ARGS = (
    numba.complex64[:, ::1],  # X = spectra.T (M, n_bins), channel-major
    numba.types.Array(numba.float64, 1, "A", readonly=True),  # toa: any 1-D float64 array
    numba.types.Array(numba.bool_, 1, "A", readonly=True),  # valid: any 1-D bool array
    numba.float64[:, ::1], numba.float64[::1], numba.int64[::1], numba.float32[::1],  # f64, fstate, istate, f32
    numba.complex64[:, ::1],  # Z
)


@numba.njit(cache=True, nogil=True)
def _check_inputs(X: np.ndarray, toa: np.ndarray, valid: np.ndarray, Z: np.ndarray) -> int:
    """``_OK`` or which of the inputs has the wrong shape (``X`` must be (M, n_bins) like ``Z[:M]``)."""
    m = Z.shape[0] - 1
    if X.shape[0] != m or X.shape[1] != Z.shape[1]:
        return _BAD_SPECTRA_SHAPE
    if toa.shape[0] != m:
        return _BAD_TOA_SHAPE
    if valid.shape[0] != m:
        return _BAD_VALID_SHAPE
    return _OK


@numba.njit(numba.int64(*_ENTRY_ARGS, numba.complex64[::1]), cache=True, nogil=True)
def _das_beamform(X: np.ndarray, toa: np.ndarray, valid: np.ndarray, f64: np.ndarray, fstate: np.ndarray,
                  istate: np.ndarray, f32: np.ndarray, Z: np.ndarray, out: np.ndarray) -> int:
    """:func:`_beamform`, ``Y`` copied into ``out`` (n_bins,) complex64; a return code."""
    # borrowed (estimators.numba_tools): no reference-count updates for the views and calls below
    X, toa, valid, Z = borrowed(X), borrowed(toa), borrowed(valid), borrowed(Z)
    f64, fstate, istate, f32 = borrowed(f64), borrowed(fstate), borrowed(istate), borrowed(f32)
    code = _check_inputs(X, toa, valid, Z)
    if code == _OK:
        _beamform(X, toa, valid, f64, fstate, istate, f32, Z)
        out[:] = Z[Z.shape[0] - 1]
    return code


@numba.njit(numba.int64(*_ENTRY_ARGS, numba.float32[::1], numba.int64[::1], numba.float32[::1]),
            cache=True, nogil=True)
def _das_process(X: np.ndarray, toa: np.ndarray, valid: np.ndarray, f64: np.ndarray, fstate: np.ndarray,
                 istate: np.ndarray, f32: np.ndarray, Z: np.ndarray, ola: np.ndarray, ola_state: np.ndarray,
                 out: np.ndarray) -> int:
    """:func:`_beamform`, then the synthesis of ``Y`` (``irfft`` and the weighted
    overlap-add of ``beamform.stft``) into ``out``, the next ``hop`` samples; a return code."""
    # borrowed (estimators.numba_tools): no reference-count updates for the views and calls below
    X, toa, valid, Z = borrowed(X), borrowed(toa), borrowed(valid), borrowed(Z)
    f64, fstate, istate, f32 = borrowed(f64), borrowed(fstate), borrowed(istate), borrowed(f32)
    ola, ola_state, out = borrowed(ola), borrowed(ola_state), borrowed(out)
    code = _check_inputs(X, toa, valid, Z)
    if code == _OK:
        _beamform(X, toa, valid, f64, fstate, istate, f32, Z)
        _synthesise(Z[Z.shape[0] - 1], ola, ola_state, out)
    return code


class DelayAndSum:
    """Online weighted delay-and-sum beamformer, one hop per call.

    Parameters
    ----------
    n_channels : int
        Number of devices ``M``.
    frame_samples : int
        STFT frame length in samples (the TOA paper uses 4096 at 75 % overlap).
    hop_samples : int
        Hop in samples, ``1 <= hop_samples <= frame_samples``.
    sample_rate_hz : float
        Common (nominal) sample rate in hertz, used to turn ``toa_s`` into phase.
    weighting : {"equal", "adaptive", "level"}, optional
        Channel weighting (see the module docstring). Default ``"adaptive"``.
    window : str or ndarray, shape (frame_samples,), optional
        Analysis window (periodic Hann by default); it must be the one used for the spectra.
    weight_time_constant_s : float, optional
        Time constant of the exponential smoothing of the cross-power statistics in seconds
        (forgetting factor ``exp(-hop_samples / (sample_rate_hz * tau))``). Default 2 s.
    weight_band_hz : tuple of float, optional
        ``(low_hz, high_hz)`` range whose bins feed the statistics. Default 100-6000 Hz.
    max_channel_snr_db : float, optional
        Cap on a channel's estimated target-to-noise ratio in dB (a floor on its noise power), so
        that a fit error cannot hand one channel all the weight. Default 20 dB.
    weight_floor : float, optional
        Each valid channel keeps at least ``weight_floor / M_valid`` before normalisation,
        in ``[0, 1]``. Default 0.
    weight_exponent : float, optional
        ``p`` in ``w_i ~ (g_i / sigma_i^2)^p``, in ``[0, 1]``: 1 is MRC (default), 0 equal weights.
        Values around 0.7 hedge for compact arrays where devices share coherent reflections or noise
        (the rank-one model then over-credits neighbouring devices) at a small cost on spread arrays.
    level_time_constant_s : float, optional
        ``"level"``: time constant of each channel's noise-floor and speech-level averages, in seconds of
        pauses and of speech (:meth:`note_frame`). Default 3 s.
    level_max_ratio : float, optional
        ``"level"``: a channel's weight stays within this factor of the median channel's
        (default 4: 12 dB either way), so that a dead-quiet or a swamped channel cannot take or lose
        the beam alone.
    level_snr_margin_db : float, optional
        ``"level"``: a channel whose SNR is more than this below the median channel's is not raised above
        the median's weight, however low its floor. Default 3 dB.
    level_min_pause_s : float, optional
        ``"level"``: a channel's floor counts after this much of pauses. Default 0.5 s.
    level_snr_exponent : float, optional
        ``"level"``: each weight also times ``(SNR_i / SNR_med)^(p / 2)``, ``p`` in [0, 2] (module docstring):
        1 is maximal-ratio combining, 0 (default) the floors alone.

    Attributes
    ----------
    channel_weights : ndarray, shape (n_channels,), float32
        Weights applied to the latest frame (non-negative, summing to 1 unless no channel was
        valid, then all 0); a new array (a copy) each time it is read.
    latency_samples : int
        Output delay with respect to device 0's input, ``frame_samples - hop_samples``.
    latency_s : float
        The same in seconds.
    omega_rad_s : ndarray, shape (n_bins,), rad/s
        Angular frequency of each bin, ``2 pi b sample_rate_hz / frame_samples``.
    """

    def __init__(
        self,
        n_channels: int,
        *,
        frame_samples: int,
        hop_samples: int,
        sample_rate_hz: float,
        weighting: Weighting = "adaptive",
        window: str | np.ndarray = "hann",
        weight_time_constant_s: float = 2.0,
        weight_band_hz: tuple[float, float] = (100.0, 6000.0),
        max_channel_snr_db: float = 20.0,
        weight_floor: float = 0.0,
        weight_exponent: float = 1.0,
        level_time_constant_s: float = 3.0,
        level_max_ratio: float = 4.0,
        level_snr_margin_db: float = 3.0,
        level_min_pause_s: float = 0.5,
        level_snr_exponent: float = 0.0,
    ) -> None:
        if int(n_channels) != n_channels or n_channels < 1:
            raise ValueError(f"{n_channels=} must be an integer >= 1")
        if not (np.isfinite(sample_rate_hz) and sample_rate_hz > 0):
            raise ValueError(f"{sample_rate_hz=} must be a positive number of hertz")
        if weighting not in _MODES:
            raise ValueError(f"{weighting=} must be 'equal', 'adaptive' or 'level'")
        if not (np.isfinite(level_time_constant_s) and level_time_constant_s > 0):
            raise ValueError(f"{level_time_constant_s=} must be a positive number of seconds")
        if not (np.isfinite(level_max_ratio) and level_max_ratio >= 1):
            raise ValueError(f"{level_max_ratio=} must be a number >= 1")
        if not (np.isfinite(level_snr_margin_db) and level_snr_margin_db >= 0):
            raise ValueError(f"{level_snr_margin_db=} must be a number of dB >= 0")
        if not (np.isfinite(level_min_pause_s) and 0 <= level_min_pause_s < level_time_constant_s):
            raise ValueError(f"{level_min_pause_s=} must be a number of seconds >= 0 and below "
                             f"{level_time_constant_s=} (the averages' mass never reaches more)")
        if not (np.isfinite(level_snr_exponent) and 0 <= level_snr_exponent <= 2):
            raise ValueError(f"{level_snr_exponent=} must be in [0, 2] (0: every channel to one floor, 1: MRC)")
        if not (np.isfinite(weight_time_constant_s) and weight_time_constant_s > 0):
            raise ValueError(f"{weight_time_constant_s=} must be a positive number of seconds")
        low_hz, high_hz = (float(f) for f in weight_band_hz)
        if not 0.0 <= low_hz < high_hz:
            raise ValueError(f"{weight_band_hz=} must be (low_hz, high_hz) in hertz with 0 <= low_hz < high_hz")
        if not np.isfinite(max_channel_snr_db):
            raise ValueError(f"{max_channel_snr_db=} must be a finite number of dB")
        if not 0.0 <= weight_floor <= 1.0:
            raise ValueError(f"{weight_floor=} must be in [0, 1]")
        if not 0.0 <= weight_exponent <= 1.0:
            raise ValueError(f"{weight_exponent=} must be in [0, 1] (0: equal weights, 1: MRC)")

        self.n_channels = int(n_channels)
        self.sample_rate_hz = float(sample_rate_hz)
        self._stft = StreamingStft(self.n_channels, frame_samples=frame_samples, hop_samples=hop_samples, window=window)
        self.frame_samples = self._stft.frame_samples
        self.hop_samples = self._stft.hop_samples
        self.n_bins = self._stft.n_bins
        self.analysis_window = self._stft.analysis_window
        # The synthesis runs inside _das_process on this object's buffers, so that
        # beamform_spectra followed by self._istft.process is the same as process_spectra.
        self._istft = StreamingIstft(
            frame_samples=self.frame_samples, hop_samples=self.hop_samples, analysis_window=self.analysis_window
        )
        self.latency_samples = self._istft.latency_samples
        self.latency_s = self.latency_samples / self.sample_rate_hz
        self.omega_rad_s = 2.0 * np.pi * np.arange(self.n_bins) * self.sample_rate_hz / self.frame_samples

        m = self.n_channels
        bin_hz = self.sample_rate_hz / self.frame_samples
        # Bins [lo, hi) feed the weighting statistics.
        lo = min(int(np.ceil(low_hz / bin_hz)), self.n_bins - 1)
        hi = min(int(np.floor(high_hz / bin_hz)) + 1, self.n_bins)
        self._stats_bins = slice(lo, max(hi, lo + 1))
        self._forget = float(np.exp(-self.hop_samples / (self.sample_rate_hz * weight_time_constant_s)))
        self._inv_snr_max = float(10.0 ** (-max_channel_snr_db / 10.0))
        # The rank-one fit takes 10 ALS steps per frame during the first second (the statistics
        # move fast), then one step per frame warm-started from the last.
        self._startup_frames = int(np.ceil(self.sample_rate_hz / self.hop_samples))
        self._startup_iter = 10

        # Kernel parameters and state (layouts at the top of the module).
        self._fstate = np.array([0.0, bin_hz, self._forget, self._inv_snr_max, float(weight_floor),
                                 float(weight_exponent),
                                 float(np.exp(-self.hop_samples / (self.sample_rate_hz * level_time_constant_s))),
                                 float(level_max_ratio),
                                 float(level_snr_margin_db) * math.log(10.0) / 10.0,
                                 float(level_min_pause_s) * self.sample_rate_hz / self.hop_samples,
                                 float(level_snr_exponent)])
        # Steering blocks: K fine phasors per channel, K a power of two >= sqrt(n_bins) so that
        # the K-long product rows and the n_bins / K coarse steps balance.
        n_fine = max(2, 1 << int(np.ceil(np.log2(np.sqrt(self.n_bins)))))
        n_blocks = -(-self.n_bins // n_fine)
        self._istate = np.array([0, _MODES[weighting], self._stats_bins.start, self._stats_bins.stop,
                                 self._startup_frames, self._startup_iter, n_fine], dtype=np.int64)
        self._f64 = np.zeros((m + 1 + _N_WORK, m))
        self._stats = self._f64[: m + 1]  # C, then the gains g
        self._level_work = self._f64[m + 1 :]
        self._f32 = np.zeros(m + 2 * m * n_fine + 2 * n_blocks * n_fine, dtype=np.float32)
        self._weights = self._f32[:m]
        self._aligned = np.zeros((m + 1, self.n_bins), dtype=np.complex64)  # Z_i, then Y
        self._all_valid = np.ones(m, dtype=bool)
        self._x_shape = (self.n_bins, m)
        self._m_shape = (m,)
        # The kernels' state and work arrays after the inputs, in one tuple each (fewer attribute
        # loads per call); reset() clears them in place.
        self._beamform_args = (self._f64, self._fstate, self._istate, self._f32, self._aligned)
        self._process_args = self._beamform_args + (self._istft._ola, self._istft._state)
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget the STFT/overlap-add buffers and the weighting statistics."""
        self._stft.reset()
        self._istft.reset()
        self._stats.fill(0.0)
        self._level_work[_LOG_FLOOR:].fill(0.0)   # the floors, the speech levels and their masses
        self._fstate[_MASS] = 0.0
        self._istate[_N_UPDATES] = 0
        self._weights.fill(np.float32(1.0 / self.n_channels))

    @property
    def weighting(self) -> Weighting:
        """``"equal"``, ``"adaptive"`` or ``"level"``, as constructed (the kernels read it from their state)."""
        return next(k for k, v in _MODES.items() if v == self._istate[_ADAPTIVE])

    def note_frame(self, spectra: np.ndarray, valid: np.ndarray | None = None, *, pause: bool) -> None:
        """``"level"``: the frame ``spectra`` (n_bins, n_channels) updates every ``valid`` channel's noise
        floor if it is a ``pause`` (no talker: the pipeline asks its speech detector), its speech level
        otherwise. Call it before the frame's :meth:`process_spectra`, with every device the stream has (not
        only those the frame's beam takes). Nothing happens with another weighting; without a call, "level"
        is equal weighting."""
        if self._istate[_ADAPTIVE] != _LEVEL:
            return
        if valid is None:
            valid = self._all_valid
        if getattr(spectra, "dtype", None) is _C64 and spectra.shape == self._x_shape \
                and getattr(valid, "dtype", None) is _BOOL and valid.shape == self._m_shape:
            _learn_floors(spectra.T, valid, self._level_work, self._fstate, pause)   # the usual inputs as they are
        else:   # converted, shapes checked (the kernel does not check them)
            X, _, ok = self._converted(spectra, np.zeros(self.n_channels), valid)
            _learn_floors(X, ok, self._level_work, self._fstate, pause)

    def set_level_factors(self, log_factors: np.ndarray | None) -> None:
        """``"level"``: multiply each channel's weight by ``exp(log_factors[i])`` (then held within
        ``level_max_ratio`` of the median channel's, as the rest); None: no factors. The pipeline gives the
        steered talker track's per-device peak heights here (``EngineConfig.level_height_exponent``)."""
        if log_factors is None:
            self._level_work[_LOG_FACTOR] = 0.0
        else:
            self._level_work[_LOG_FACTOR] = log_factors

    @property
    def channel_weights(self) -> np.ndarray:
        """Weights applied to the latest frame, shape (n_channels,), float32: a copy, so a kept
        array does not change with later frames."""
        return self._weights.copy()

    # ------------------------------------------------------------------ stages
    def process(self, block: np.ndarray, toa_s: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Analyse one hop of multichannel audio and beamform it.

        Parameters
        ----------
        block : ndarray, shape (hop_samples, n_channels), float32
            Exactly ``hop_samples`` new samples per device.
        toa_s : ndarray, shape (n_channels,), seconds
            Relative TOA used to steer this frame.
        valid : ndarray, shape (n_channels,), bool, optional
            ``False`` excludes a device (silent, clipped, missing). Default all valid.

        Returns
        -------
        ndarray, shape (hop_samples,), float32
            Beamformed samples, delayed by :attr:`latency_samples`.
        """
        return self.process_spectra(self._stft.process(block), toa_s, valid)

    def process_spectra(self, spectra: np.ndarray, toa_s: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Beamform one STFT frame (eq. 8) and return the next hop of output samples.

        One compiled call: validity, steering (eq. 7), weights, sum (eq. 8), ``irfft`` and the
        weighted overlap-add.

        Parameters
        ----------
        spectra : ndarray, shape (n_bins, n_channels), complex64
            Spectra of the latest frame from a :class:`~beamform.stft.StreamingStft` with the
            same frame, hop and window.
        toa_s : ndarray, shape (n_channels,), seconds
            Relative TOA used to steer this frame.
        valid : ndarray, shape (n_channels,), bool, optional
            ``False`` excludes a device for this frame. Channels with a non-finite value in
            ``spectra`` or a non-finite ``toa_s`` are excluded as well.

        Returns
        -------
        ndarray, shape (hop_samples,), float32
            Beamformed samples, delayed by :attr:`latency_samples`.
        """
        return self._run(_das_process, self._process_args, spectra, toa_s, valid,
                         np.empty(self.hop_samples, np.float32))

    def beamform_spectra(self, spectra: np.ndarray, toa_s: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Steer, weight and sum one STFT frame (eqs. 7-8) without synthesis.

        :meth:`process_spectra` is this followed by the overlap-add synthesis; the weighting
        statistics are updated here.

        Parameters
        ----------
        spectra : ndarray, shape (n_bins, n_channels), complex64
        toa_s : ndarray, shape (n_channels,), seconds
        valid : ndarray, shape (n_channels,), bool, optional

        Returns
        -------
        ndarray, shape (n_bins,), complex64
            ``Y(w) = sum_i w_i exp(+i w toa_i) X_i(w)``, a new array.
        """
        return self._run(_das_beamform, self._beamform_args, spectra, toa_s, valid,
                         np.empty(self.n_bins, np.complex64))

    # ------------------------------------------------------------------ input checks
    def _run(self, kernel, state: tuple, spectra, toa_s, valid, out: np.ndarray) -> np.ndarray:
        """``kernel(spectra.T, toa_s, valid, *state, out)``, an entry kernel compiled for exactly the
        types of ``_ENTRY_ARGS``; returns ``out``. The usual inputs (StreamingStft spectra, a float64
        TOA, a bool mask or None) pass as they are after a cheap check; others are converted first
        (:meth:`_converted`), not by a failed call (numba takes ~70 us to word its TypeError). The
        kernel checks the shapes and changes nothing when one is wrong.
        """
        if valid is None:
            valid = self._all_valid
        try:
            X = spectra.T
            usual = X.dtype is _C64 and X.flags.carray and toa_s.dtype is _F64 and valid.dtype is _BOOL
        except AttributeError:  # not arrays
            usual = False
        if usual:
            try:
                code = kernel(X, toa_s, valid, *state, out)
            except TypeError:  # the usual dtypes with other dimensions
                usual = False
        if not usual:
            code = kernel(*self._converted(spectra, toa_s, valid), *state, out)
        if code != _OK:
            self._raise_shape(code, spectra, toa_s, valid)
        return out

    def _converted(self, spectra, toa_s, valid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``spectra.T`` C-contiguous writeable complex64, ``toa_s`` float64, ``valid`` bool, shapes checked."""
        X = np.asarray(spectra)
        if X.shape != self._x_shape:
            self._raise_shape(_BAD_SPECTRA_SHAPE, X, toa_s, valid)
        toa = np.asarray(toa_s, dtype=np.float64)
        if toa.shape != self._m_shape:
            self._raise_shape(_BAD_TOA_SHAPE, X, toa, valid)
        ok = np.asarray(valid, dtype=np.bool_)
        if ok.shape != self._m_shape:
            self._raise_shape(_BAD_VALID_SHAPE, X, toa, ok)
        return np.array(X.T, dtype=np.complex64, order="C"), toa, ok

    def _raise_shape(self, code: int, spectra, toa_s, valid) -> None:
        if code == _BAD_SPECTRA_SHAPE:
            raise ValueError(f"spectra.shape={np.shape(spectra)} must be ({self.n_bins}, {self.n_channels}) = "
                             "(n_bins, n_channels)")
        if code == _BAD_TOA_SHAPE:
            raise ValueError(f"toa.shape={np.shape(toa_s)} must be ({self.n_channels},) = (n_channels,)")
        raise ValueError(f"valid.shape={np.shape(valid)} must be ({self.n_channels},) = (n_channels,)")


def delay_and_sum(
    audio: np.ndarray,
    toa_s: np.ndarray,
    *,
    frame_samples: int,
    hop_samples: int,
    sample_rate_hz: float,
    valid: np.ndarray | None = None,
    **options,
) -> np.ndarray:
    """Delay-and-sum a whole recording with the same stage as :class:`DelayAndSum`.

    The STFT and the overlap-add are computed in batch; the per-frame steering and weighting run
    through :meth:`DelayAndSum.beamform_spectra`, so the result equals streaming the recording hop
    by hop.

    Parameters
    ----------
    audio : ndarray, shape (n_samples, n_channels), float32
        Time-major input; ``n_samples`` is truncated to a multiple of ``hop_samples``.
    toa_s : ndarray, shape (n_channels,) or (n_frames, n_channels), seconds
        Relative TOA, fixed or one row per frame (``n_frames = n_samples // hop_samples``).
    frame_samples, hop_samples : int
        STFT frame and hop in samples.
    sample_rate_hz : float
        Sample rate in hertz.
    valid : ndarray, shape (n_channels,) or (n_frames, n_channels), bool, optional
        Per-channel (per-frame) validity mask.
    **options
        Keyword options of :class:`DelayAndSum` (``weighting``, ``window``, ...).

    Returns
    -------
    ndarray, shape (n_frames * hop_samples,), float32
        Beamformed signal, delayed by ``frame_samples - hop_samples`` samples.
    """
    x = np.asarray(audio, dtype=np.float32)
    if x.ndim != 2:
        raise ValueError(f"{x.shape=} must be (n_samples, n_channels)")
    das = DelayAndSum(
        x.shape[1], frame_samples=frame_samples, hop_samples=hop_samples, sample_rate_hz=sample_rate_hz, **options
    )
    S = stft(x, frame_samples=frame_samples, hop_samples=hop_samples, window=das.analysis_window)
    n_frames = S.shape[0]
    # Writeable C-contiguous rows (broadcast_to gives read-only views): no per-frame copies.
    toa = np.array(np.broadcast_to(np.asarray(toa_s, dtype=np.float64), (n_frames, x.shape[1])), order="C")
    ok = None if valid is None else np.array(np.broadcast_to(np.asarray(valid, dtype=bool), (n_frames, x.shape[1])))
    Y = np.empty((n_frames, das.n_bins), dtype=np.complex64)
    for k in range(n_frames):
        Y[k] = das.beamform_spectra(S[k], toa[k], None if ok is None else ok[k])
    return istft(Y, frame_samples=frame_samples, hop_samples=hop_samples, window=das.analysis_window)
