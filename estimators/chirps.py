"""Calibration chirps: synthesis, matched-filter detection in one device's stream, GCC-PHAT refinement, and
extraction of TDOA-S / TDOA-M for :mod:`estimators.hybrid_tdoa` (paper Sec. II-A.2, Fig. 2).

Every device records on its own clock; an onset ``onsets_s[j, i]`` is the arrival time of chirp ``j`` at device
``i`` read on device ``i``'s clock (sample index / sample rate, first sample = 0). Then (eqs. 5-6)

- TDOA-S ``tdoa_events_s[j, i] = onsets_s[j+1, i] - onsets_s[j, i]`` (same clock: no offset),
- TDOA-M ``tdoa_mics_s[j, i] = onsets_s[j, i] - onsets_s[j, 0]`` (device 0 is the reference; column 0 NaN),

each refined by GCC-PHAT between windows cut at the rough onsets (``T_rough + T_pre``, Fig. 2): adjacent
events of one device for TDOA-S, device ``i`` against device 0 at one event for TDOA-M. The rough onsets come
from a matched filter on the known chirp (more robust and more precise than the paper's energy threshold).
Missed chirps are NaN. Signals are 1-D float arrays (one channel per device); times in seconds.
"""
from __future__ import annotations

import collections
import dataclasses
import math

import numpy as np
import scipy.signal

__all__ = ["ChirpTdoas", "detect_chirps", "extract_tdoas", "gcc_phat_delays", "linear_chirp", "matched_filter"]


def linear_chirp(*, duration_s: float, f0_hz: float, f1_hz: float, sample_rate_hz: float,
                 fade_s: float = 0.005) -> np.ndarray:
    """Linear sweep ``sin(2 pi (f0 t + (f1 - f0) t^2 / (2 T)))`` with raised-cosine fades.

    Returns
    -------
    ndarray, shape (round(duration_s * sample_rate_hz),), float64, peak 1
    """
    if not (duration_s > 0 and sample_rate_hz > 0):
        raise ValueError(f"{duration_s=} s and {sample_rate_hz=} Hz must be > 0")
    if not (0 <= f0_hz < sample_rate_hz / 2 and 0 <= f1_hz < sample_rate_hz / 2):
        raise ValueError(f"{f0_hz=}, {f1_hz=} must be in [0, {sample_rate_hz / 2}) Hz")
    n = int(round(duration_s * sample_rate_hz))
    t = np.arange(n) / sample_rate_hz
    x = np.sin(2 * np.pi * (f0_hz * t + 0.5 * (f1_hz - f0_hz) / duration_s * t * t))
    nf = min(int(round(fade_s * sample_rate_hz)), n // 2)
    if nf > 0:
        ramp = 0.5 - 0.5 * np.cos(np.pi * np.arange(nf) / nf)
        x[:nf] *= ramp
        x[n - nf:] *= ramp[::-1]
    return x


def matched_filter(signal: np.ndarray, template: np.ndarray) -> np.ndarray:
    """Cross-correlation of ``signal`` with ``template`` at every start lag (FFT), ``out[n] = sum_k
    signal[n + k] template[k]``.

    Returns
    -------
    ndarray, shape (len(signal),), float64 (lags past the end use zero padding)
    """
    x = np.asarray(signal, float)
    h = np.asarray(template, float)
    return scipy.signal.fftconvolve(x, h[::-1], mode="full")[len(h) - 1:len(h) - 1 + len(x)]


def parabolic_offset(y: np.ndarray, k: int) -> float:
    """Sub-sample peak offset of ``y`` around index ``k`` (parabola through three points), in samples."""
    if k <= 0 or k >= len(y) - 1:
        return 0.0
    a, b, c = y[k - 1], y[k], y[k + 1]
    den = a - 2 * b + c
    return float(0.5 * (a - c) / den) if den < 0 else 0.0


def detect_chirps(signal: np.ndarray, template: np.ndarray, *, sample_rate_hz: float, min_separation_s: float,
                  n_events: int | None = None, threshold: float = 10.0) -> np.ndarray:
    """Onsets of the calibration chirp in one device's stream by matched filtering.

    Peaks of the correlation envelope above ``threshold`` times its robust noise level
    (``1.4826 * median``), at least ``min_separation_s`` apart; the onset is the sub-sample maximum of
    the correlation itself near the envelope peak.

    Parameters
    ----------
    signal : ndarray, shape (n_samples,), float
    template : ndarray, shape (n_template,), float
        The emitted chirp.
    sample_rate_hz : float
    min_separation_s : float
        Shortest time between two chirps.
    n_events : int, optional
        Keep at most the ``n_events`` strongest detections.
    threshold : float
        Detection threshold in robust noise units.

    Returns
    -------
    ndarray, shape (n_detected,), float64
        Onset times in seconds on this device's clock, ascending.
    """
    if min_separation_s <= 0:
        raise ValueError(f"{min_separation_s=} must be > 0 s")
    corr = matched_filter(signal, template)
    env = np.abs(scipy.signal.hilbert(corr))
    noise = 1.4826 * np.median(env) + 1e-300
    dist = max(1, int(min_separation_s * sample_rate_hz))
    peaks, props = scipy.signal.find_peaks(env, height=threshold * noise, distance=dist)
    if n_events is not None and len(peaks) > n_events:
        keep = np.argsort(props["peak_heights"])[::-1][:n_events]
        peaks = np.sort(peaks[keep])
    half = max(2, int(0.001 * sample_rate_hz))  # the carrier peak lies within ~1 ms of the envelope peak
    onsets = []
    for p in peaks:
        lo, hi = max(0, p - half), min(len(corr), p + half + 1)
        k = lo + int(np.argmax(corr[lo:hi]))
        onsets.append((k + parabolic_offset(corr, k)) / sample_rate_hz)
    return np.asarray(onsets, float)


def gcc_phat_delays(ref: np.ndarray, others: np.ndarray, *, sample_rate_hz: float,
                    max_delay_s: float | None = None) -> np.ndarray:
    """GCC-PHAT delay of each row of ``others`` relative to ``ref`` (positive = later), batched over rows.

    Parameters
    ----------
    ref : ndarray, shape (n,) or (m, n)
        One reference window, or one per row of ``others``.
    others : ndarray, shape (m, n)
    max_delay_s : float, optional
        Search the peak only within +/- this delay.

    Returns
    -------
    ndarray, shape (m,), seconds (sub-sample by parabolic interpolation)
    """
    others = np.atleast_2d(np.asarray(others, float))
    ref = np.asarray(ref, float)
    n = others.shape[1]
    nfft = int(2 ** np.ceil(np.log2(2 * n)))
    a = np.fft.rfft(ref, nfft, axis=-1)
    b = np.fft.rfft(others, nfft, axis=-1)
    cross = b * np.conj(a)
    cross /= np.abs(cross) + 1e-12 * np.max(np.abs(cross))
    cc = np.fft.irfft(cross, nfft, axis=-1)
    cc = np.concatenate([cc[:, -(nfft // 2):], cc[:, :nfft // 2]], axis=1)  # lags -nfft/2 .. nfft/2-1
    lags = np.arange(-(nfft // 2), nfft // 2)
    if max_delay_s is not None:
        cc = np.where(np.abs(lags) <= max_delay_s * sample_rate_hz, cc, -np.inf)
    out = np.empty(len(cc))
    for r, row in enumerate(cc):
        k = int(np.argmax(row))
        fin = np.where(np.isfinite(row), row, np.min(row[np.isfinite(row)]))
        out[r] = (lags[k] + parabolic_offset(fin, k)) / sample_rate_hz
    return out


@dataclasses.dataclass(frozen=True)
class ChirpTdoas:
    """TDOAs extracted from multi-device audio (inputs of :class:`estimators.hybrid_tdoa.HybridTdoaProblem`).

    Attributes
    ----------
    tdoa_events_s : ndarray, shape (K-1, N)
        TDOA-S, seconds; NaN where a chirp was missed.
    tdoa_mics_s : ndarray, shape (K, N)
        TDOA-M against device 0, seconds; column 0 NaN.
    onsets_s : ndarray, shape (K, N)
        Matched-filter onsets on each device's clock, seconds; NaN where missed.
    """

    tdoa_events_s: np.ndarray
    tdoa_mics_s: np.ndarray
    onsets_s: np.ndarray


def _assign_events(onsets: np.ndarray, schedule_s: np.ndarray, tolerance_s: float) -> np.ndarray:
    """Match detections to scheduled emissions ``schedule_s`` (K,) up to an unknown clock offset: the offset
    that matches most detections within ``tolerance_s`` wins. Returns (K,) onsets with NaN for misses."""
    k = len(schedule_s)
    out = np.full(k, np.nan)
    if len(onsets) == 0:
        return out
    best, best_off = -1, 0.0
    for d in onsets:
        for s in schedule_s:
            off = d - s
            err = np.abs(onsets[:, None] - (schedule_s[None, :] + off))
            n_match = int(np.sum(np.min(err, axis=1) < tolerance_s))
            if n_match > best:
                best, best_off = n_match, off
    err = np.abs(onsets[:, None] - (schedule_s[None, :] + best_off))
    for j in range(k):
        i = int(np.argmin(err[:, j]))
        if err[i, j] < tolerance_s:
            out[j] = onsets[i]
    return out


def extract_tdoas(streams: list[np.ndarray], template: np.ndarray, *, sample_rate_hz: float,
                  interval_s: np.ndarray, tolerance_s: float = 0.25, window_s: float | None = None,
                  max_refine_s: float = 0.002, threshold: float = 10.0) -> ChirpTdoas:
    """TDOA-S and TDOA-M of K scheduled chirps from N asynchronous devices.

    Parameters
    ----------
    streams : list of ndarray, each shape (n_samples_i,)
        One channel per device, each on its own clock (same nominal sample rate).
    template : ndarray, shape (n_template,)
        The emitted chirp.
    interval_s : ndarray, shape (K-1,)
        Emission intervals; detections are assigned to events by this schedule up to a per-device offset
        (and ``tolerance_s`` for drift, propagation and offsets between devices).
    window_s : float, optional
        GCC-PHAT window length starting a little before each onset; default template length + 50 ms.
    max_refine_s : float
        GCC-PHAT refinement searched within +/- this delay around the matched-filter estimate.

    Returns
    -------
    ChirpTdoas
    """
    interval_s = np.asarray(interval_s, float)
    k = len(interval_s) + 1
    n = len(streams)
    schedule = np.concatenate([[0.0], np.cumsum(interval_s)])
    min_sep = 0.5 * float(np.min(interval_s)) if len(interval_s) else 1.0
    onsets = np.full((k, n), np.nan)
    for i, x in enumerate(streams):
        det = detect_chirps(x, template, sample_rate_hz=sample_rate_hz, min_separation_s=min_sep,
                            threshold=threshold)
        onsets[:, i] = _assign_events(det, schedule, tolerance_s)
    wl = int(round((window_s if window_s is not None else len(template) / sample_rate_hz + 0.05)
                   * sample_rate_hz))
    pre = int(round(0.01 * sample_rate_hz))

    def cut(x, t_s):
        start = int(np.floor(t_s * sample_rate_hz)) - pre
        seg = np.zeros(wl)
        lo, hi = max(start, 0), min(start + wl, len(x))
        if hi > lo:
            seg[lo - start:hi - start] = x[lo:hi]
        return start, seg

    # TDOA-S: adjacent events of one device (Fig. 2): T_rough (window starts) + T_pre (GCC-PHAT)
    tdoa_s = np.full((k - 1, n), np.nan)
    for i, x in enumerate(streams):
        ok = np.isfinite(onsets[:, i])
        cuts = [cut(x, t) if ok[j] else (0, np.zeros(wl)) for j, t in enumerate(onsets[:, i])]
        starts = np.array([c[0] for c in cuts], float)
        segs = np.stack([c[1] for c in cuts])
        pairs = np.nonzero(ok[:-1] & ok[1:])[0]
        if len(pairs):
            d = gcc_phat_delays(segs[pairs], segs[pairs + 1], sample_rate_hz=sample_rate_hz, max_delay_s=None)
            rough = (starts[pairs + 1] - starts[pairs]) / sample_rate_hz
            mf = onsets[pairs + 1, i] - onsets[pairs, i]
            refined = rough + d
            tdoa_s[pairs, i] = np.where(np.abs(refined - mf) <= max_refine_s, refined, mf)
    # TDOA-M: device i against device 0 at one event
    tdoa_m = np.full((k, n), np.nan)
    for j in range(k):
        if not np.isfinite(onsets[j, 0]):
            continue
        s0, ref = cut(streams[0], onsets[j, 0])
        devs = [i for i in range(1, n) if np.isfinite(onsets[j, i])]
        if not devs:
            continue
        cuts = [cut(streams[i], onsets[j, i]) for i in devs]
        d = gcc_phat_delays(ref, np.stack([c[1] for c in cuts]), sample_rate_hz=sample_rate_hz)
        for q, i in enumerate(devs):
            rough = (cuts[q][0] - s0) / sample_rate_hz
            mf = onsets[j, i] - onsets[j, 0]
            refined = rough + d[q]
            tdoa_m[j, i] = refined if abs(refined - mf) <= max_refine_s else mf
    return ChirpTdoas(tdoa_events_s=tdoa_s, tdoa_mics_s=tdoa_m, onsets_s=onsets)


class ChirpDetector:
    """Matched filter for a known chirp on one device's conditioned stream, in fixed blocks (overlap-save).

    Any split of the input gives the same detections (the FFT blocks do not depend on it). Per block of
    ``block_samples`` (about 3 template lengths): one real FFT, one complex inverse FFT of the analytic
    correlation (its magnitude is the envelope, its real part the exact correlation), a median for the noise
    level (the median of the last ``noise_blocks`` block medians), and peak picking: envelope peaks above
    ``threshold`` x ``1.4826`` x noise, the largest within ``min_separation_s``; then the first arrival: the
    earliest envelope peak at most ``first_arrival_s`` before it and at least ``first_arrival_ratio`` of it (a
    reflection off a nearby surface can beat the direct path); the onset is the sub-sample maximum of the
    correlation within 1 ms of that peak (as :func:`estimators.detect_chirps`). Memory is bounded: one FFT
    block of input, two blocks (plus the look-back) of correlation, ``noise_blocks`` medians.
    """

    def __init__(self, template: np.ndarray, *, sample_rate_hz: float, min_separation_s: float,
                 threshold: float = 10.0, noise_blocks: int = 8, first_arrival_s: float = 0.02,
                 first_arrival_ratio: float = 0.5) -> None:
        h = np.asarray(template, float)
        if h.ndim != 1 or len(h) < 8:
            raise ValueError(f"template shape {h.shape} must be 1-D with >= 8 samples")
        if not min_separation_s > 0:
            raise ValueError(f"{min_separation_s=} must be > 0 s")
        self.sample_rate_hz = float(sample_rate_hz)
        self.template_samples = len(h)
        self.nfft = max(1024, 1 << int(math.ceil(math.log2(4 * len(h)))))
        self.block_samples = self.nfft - len(h) + 1
        u = np.zeros(self.nfft)
        u[0] = 1.0
        u[1:self.nfft // 2] = 2.0
        u[self.nfft // 2] = 1.0
        self._filter = np.conj(np.fft.fft(h, self.nfft)) * u     # analytic correlation in one inverse FFT
        self.threshold = float(threshold)
        self.separation_samples = max(1, int(min_separation_s * sample_rate_hz))
        self._half = max(2, int(0.001 * sample_rate_hz))
        self._lookback = int(first_arrival_s * sample_rate_hz)
        self.first_arrival_ratio = float(first_arrival_ratio)
        self._floor = 1e-9 * float(np.sqrt(np.sum(h * h)))
        self._medians: collections.deque = collections.deque(maxlen=noise_blocks)
        self._buf = np.zeros(0, np.float64)   # input from index self._buf_start on
        self._buf_start = 0
        self._corr = np.zeros(0)              # real correlation of the last two blocks (+ the look-back)
        self._env = np.zeros(0)               # its envelope
        self._corr_start = 0
        self.processed = 0                    # correlation computed for onsets < processed
        self._pending: list | None = None     # [index, envelope, onset or None, snr]
        self.ended = False

    @property
    def final_before(self) -> float:
        """Onsets below this index are final: a later detection cannot replace them."""
        return math.inf if self.ended else float(self.processed - self.separation_samples - self._half)

    def process(self, samples: np.ndarray, *, last: bool = False) -> list[tuple[float, float]]:
        """Feed conditioned samples (the next ones of the device's stream); return ``(onset_samples, snr)`` of
        the chirps that became final."""
        out: list[tuple[float, float]] = []
        if len(samples):
            self._buf = np.concatenate([self._buf, np.asarray(samples, np.float64)])
        while len(self._buf) >= self.nfft:
            self._block(self._buf[:self.nfft], out, self.block_samples)
        if last and not self.ended:
            n_valid = len(self._buf)
            self._buf = np.concatenate([self._buf, np.zeros(self.nfft)])
            while n_valid > 0:
                self._block(self._buf[:self.nfft], out, min(n_valid, self.block_samples))
                n_valid -= self.block_samples
            self._buf = np.zeros(0)
            self.ended = True
            self._finalise(out, force=True)
        return out

    def _block(self, seg: np.ndarray, out: list, n_onsets: int) -> None:
        """Correlation for the onsets ``[start, start + n_onsets)`` from ``seg`` (nfft samples from start)."""
        half = np.fft.rfft(seg, self.nfft)
        spec = np.zeros(self.nfft, complex)
        spec[:len(half)] = half
        z = np.fft.ifft(spec * self._filter)[:n_onsets]
        env = np.abs(z)
        start = self._buf_start
        self._buf = self._buf[self.block_samples:]
        self._buf_start += self.block_samples
        self._medians.append(float(np.median(env)))
        noise = max(1.4826 * float(np.median(self._medians)), self._floor)
        keep = self.block_samples + self._lookback
        self._corr = np.concatenate([self._corr[-keep:], z.real])
        self._env = np.concatenate([self._env[-keep:], env])
        self._corr_start = start + n_onsets - len(self._corr)
        above = np.flatnonzero(env > self.threshold * noise)
        if len(above):
            left = np.r_[-np.inf, env[:-1]][above]
            right = np.r_[env[1:], -np.inf][above]
            for i in above[(env[above] >= left) & (env[above] >= right)]:
                n = start + int(i)
                p = self._pending
                if p is not None and n - p[0] > self.separation_samples:
                    self._emit(out)
                    p = None
                if p is None or env[i] > p[1]:
                    self._pending = [n, float(env[i]), None, float(env[i] / noise)]
        self.processed = start + n_onsets
        self._finalise(out)

    def _finalise(self, out: list, *, force: bool = False) -> None:
        p = self._pending
        if p is None:
            return
        if p[2] is None and (p[0] + self._half < self.processed or force):
            self._refine(p)
        if force or p[0] + self.separation_samples < self.processed:
            self._emit(out)

    def _emit(self, out: list) -> None:
        p, self._pending = self._pending, None
        if p[2] is None:
            self._refine(p)
        out.append((float(p[2]), float(p[3])))

    def _refine(self, p: list) -> None:
        """First arrival before the envelope peak, then the sub-sample maximum of the correlation near it."""
        b0 = self._corr_start
        lo = max(p[0] - self._lookback - b0, 1)
        hi = min(p[0] - b0, len(self._env) - 1)
        peak = p[0]
        if hi > lo:
            e = self._env
            w = np.arange(lo, hi)
            cand = w[(e[w] >= e[w - 1]) & (e[w] >= e[w + 1]) & (e[w] >= self.first_arrival_ratio * p[1])]
            if len(cand):
                peak = b0 + int(cand[0])
        lo = max(peak - self._half - b0, 0)
        hi = min(peak + self._half + 1 - b0, len(self._corr))
        if hi > lo:
            seg = self._corr[lo:hi]
            k = int(np.argmax(seg))
            p[2] = b0 + lo + k + parabolic_offset(seg, k)
        else:  # pragma: no cover - the correlation buffer always covers a pending peak
            p[2] = float(peak)
