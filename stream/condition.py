"""Per-device conditioning: check the frame's sample index (fill gaps), mix channels down, sanitise samples,
flag data-quality events, resample to the working rate; each device's clock map (working-rate sample index ->
the device's own clock) and glitch-free rate changes when a calibration corrects a device's drift."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import soxr

from .messages import Frame, FrameFlag
from .offsets import SILENCE_RMS

_LAST = int(FrameFlag.LAST)
_F32 = np.dtype(np.float32)
CLIP_LEVEL = 0.999          # |x| at or above this counts as clipped (full scale is 1.0)


@numba.njit(cache=True, nogil=True)
def _frame_stats(x):
    """One pass over a frame: the sum of its squares (float64, NaN or inf if any sample is not finite) and its
    largest magnitude. Every frame of every device goes through it, so it is one compiled call."""
    energy, peak = 0.0, 0.0
    for v in x:
        e = float(v)
        energy += e * e
        a = abs(e)
        if a > peak:
            peak = a
    return energy, peak


def compile_kernels(hop_samples: int) -> None:
    """Compile (or load from numba's cache) this module's per-frame kernel before a stream starts."""
    _frame_stats(np.zeros(hop_samples, np.float32))


@dataclass
class DeviceCounters:
    """Data-quality counters of one device (samples at the device's own rate)."""

    n_samples: int = 0
    n_nan_samples: int = 0
    n_clipped_samples: int = 0
    n_silent_blocks: int = 0
    n_blocks: int = 0


@dataclass
class GapCounters:
    """Sample-index checks of one device (samples at the device's own rate)."""

    n_gaps: int = 0
    n_gap_samples: int = 0
    n_overlaps: int = 0
    n_overlap_samples: int = 0


class FrameChecker:
    """The one stage that reads ``Frame.first_sample``: it checks it against the next expected index of the
    device, fills a gap with zeros (flagged :attr:`FrameFlag.GAP`: the aligner then leaves the device out of
    those blocks, so GCC-PHAT and the beamformer skip it) and drops samples that repeat ones already seen.
    Several channels are mixed down to mono (their mean).
    """

    def __init__(self) -> None:
        self.next_sample = 0
        self.counters = GapCounters()

    def process(self, frame: Frame) -> Frame:
        """The frame, mono, starting exactly at the next expected sample."""
        x = frame.samples
        jump = int(frame.first_sample) - self.next_sample
        if jump == 0 and x.ndim == 1:   # the usual case: nothing to do
            self.next_sample += len(x)
            return frame
        if x.ndim == 2:
            x = x[:, 0] if x.shape[1] == 1 else x.mean(axis=1, dtype=np.float32)
        flags = frame.flags
        c = self.counters
        if jump > 0:
            c.n_gaps += 1
            c.n_gap_samples += jump
            x = np.concatenate([np.zeros(jump, np.float32), np.asarray(x, np.float32)])
            flags |= FrameFlag.GAP
        elif jump < 0:
            k = min(-jump, len(x))
            c.n_overlaps += 1
            c.n_overlap_samples += k
            x = x[k:]
        self.next_sample += len(x)
        return Frame(frame.device_id, frame.seq, self.next_sample - len(x), frame.sample_rate_hz, x, flags)


class DeviceConditioner:
    """Sanitises one device's frames and resamples them to the working rate.

    Parameters
    ----------
    sample_rate_hz : float
        The device's nominal rate.
    working_rate_hz : float
        The engine's rate; devices at other rates are resampled with a streaming polyphase
        resampler (soxr), so the output of any block split is the same as of the whole file.
    rate_ratio : float
        Extra clock correction: the device's true rate is ``sample_rate_hz * rate_ratio``
        (``1 + drift_ppm * 1e-6``, from calibration). 1.0 means no correction.
    """

    def __init__(self, sample_rate_hz: float, *, working_rate_hz: float, rate_ratio: float = 1.0,
                 quality: str = "HQ") -> None:
        if not sample_rate_hz > 0 or not working_rate_hz > 0:
            raise ValueError(f"{sample_rate_hz=} and {working_rate_hz=} must be > 0 Hz")
        self.sample_rate_hz = float(sample_rate_hz)
        self.working_rate_hz = float(working_rate_hz)
        self.rate_ratio = float(rate_ratio)
        self.counters = DeviceCounters()
        in_rate = self.sample_rate_hz * self.rate_ratio
        self._resampler = None
        if abs(in_rate - self.working_rate_hz) > 1e-9 * self.working_rate_hz:
            self._resampler = soxr.ResampleStream(in_rate, self.working_rate_hz, 1, dtype="float32",
                                                  quality=quality)

    def process(self, frame: Frame) -> tuple[np.ndarray, FrameFlag]:
        """Return the frame's samples at the working rate (float32, 1-D) and its quality flags."""
        x = frame.samples
        flags = frame.flags
        c = self.counters
        n = len(x)
        c.n_blocks += 1
        c.n_samples += n
        if n:
            energy, peak = _frame_stats(x if x.ndim == 1 else x.ravel())
            if not math.isfinite(energy):
                finite = np.isfinite(x)
                n_bad = int(n - finite.sum())
                if n_bad:
                    c.n_nan_samples += n_bad
                    x = np.where(finite, x, np.float32(0.0))
                    flags |= FrameFlag.NAN_REPLACED
                energy = float(np.dot(x.astype(np.float64), x.astype(np.float64)))
                peak = float(np.abs(x).max())
            if peak >= CLIP_LEVEL:
                c.n_clipped_samples += int(np.count_nonzero(np.abs(x) >= CLIP_LEVEL))
                flags |= FrameFlag.CLIPPED
            if math.sqrt(energy / n) < SILENCE_RMS:
                c.n_silent_blocks += 1
                flags |= FrameFlag.SILENT
        if self._resampler is not None:
            last = bool(int(flags) & _LAST)
            x = self._resampler.resample_chunk(np.ascontiguousarray(x, np.float32), last=last)
        return (x if x.dtype is _F32 else np.asarray(x, np.float32)), flags


HISTORY_S = 0.25   # input kept per device to prime a resampler after a rate change


class ClockMap:
    """Working-rate sample index ``m`` of one device's conditioned stream -> that device's clock ``c`` (s).

    Piecewise linear, one segment per rate ratio: ``c = c_k + (m - m_k) * ratio_k / working_rate_hz`` for
    ``m_k <= m < m_{k+1}``; the last segment extends to +inf (and the first to -inf).
    """

    def __init__(self, working_rate_hz: float) -> None:
        self.working_rate_hz = float(working_rate_hz)
        self.start_index = [0]
        self.start_clock_s = [0.0]
        self.ratio = [1.0]

    def append(self, start_index: int, start_clock_s: float, ratio: float) -> None:
        if start_index < self.start_index[-1]:
            raise ValueError(f"{start_index=} must not precede the last segment ({self.start_index[-1]})")
        if start_index == self.start_index[-1]:
            self.start_index.pop(), self.start_clock_s.pop(), self.ratio.pop()
        self.start_index.append(int(start_index))
        self.start_clock_s.append(float(start_clock_s))
        self.ratio.append(float(ratio))

    def clock_s(self, index):
        """Clock (seconds) of working-rate sample index (scalar or array, fractional allowed)."""
        m = np.asarray(index, float)
        k = np.clip(np.searchsorted(self.start_index, m, side="right") - 1, 0, None)
        m0 = np.asarray(self.start_index, float)[k]
        out = np.asarray(self.start_clock_s)[k] + (m - m0) * np.asarray(self.ratio)[k] / self.working_rate_hz
        return float(out) if out.ndim == 0 else out

    def index_of(self, clock_s):
        """Inverse of :meth:`clock_s` (clock increases with the index)."""
        c = np.asarray(clock_s, float)
        k = np.clip(np.searchsorted(self.start_clock_s, c, side="right") - 1, 0, None)
        out = (np.asarray(self.start_index, float)[k] + (c - np.asarray(self.start_clock_s)[k])
               * self.working_rate_hz / np.asarray(self.ratio)[k])
        return float(out) if out.ndim == 0 else out


class RetunableConditioner:
    """A :class:`DeviceConditioner` whose ``rate_ratio`` can change mid-stream without a glitch.

    A rate change builds a new conditioner with the new ratio, primes it with the last ``HISTORY_S`` of input
    and drops its outputs up to the clock of the next sample the old one would have produced: the output is
    continuous to within the resampler's accuracy (about -95 dB) and the :class:`ClockMap` gets an exact new
    segment (the phase jump is under half a sample and is in the map). Without rate changes it is exactly the
    wrapped conditioner.
    """

    def __init__(self, sample_rate_hz: float, *, working_rate_hz: float, rate_ratio: float = 1.0,
                 keep_history: bool = False) -> None:
        self.sample_rate_hz = float(sample_rate_hz)
        self.working_rate_hz = float(working_rate_hz)
        self.inner = DeviceConditioner(sample_rate_hz, working_rate_hz=working_rate_hz, rate_ratio=rate_ratio)
        self.clock = ClockMap(working_rate_hz)
        if rate_ratio != 1.0:
            self.clock.ratio[0] = float(rate_ratio)
        self.n_in = 0
        self.n_out = 0
        self.ended = False
        self.n_retunes = 0
        self._history_len = max(4096, int(HISTORY_S * sample_rate_hz)) if keep_history else 0
        self._history = np.zeros(0, np.float32)
        self._carry = np.zeros(0, np.float32)
        self._skip = 0

    @property
    def counters(self) -> DeviceCounters:
        return self.inner.counters

    @property
    def rate_ratio(self) -> float:
        return self.inner.rate_ratio

    def process(self, frame: Frame) -> tuple[np.ndarray, FrameFlag]:
        """Samples at the working rate (float32) and flags, as :meth:`DeviceConditioner.process`."""
        if self._history_len:
            x = np.where(np.isfinite(frame.samples), frame.samples, np.float32(0.0)).astype(np.float32)
            self._history = np.concatenate([self._history, x])[-self._history_len:]
        self.n_in += len(frame.samples)
        y, flags = self.inner.process(frame)
        if self._skip:
            k = min(self._skip, len(y))
            y, self._skip = y[k:], self._skip - k
        if len(self._carry):
            y, self._carry = np.concatenate([self._carry, y]), np.zeros(0, np.float32)
        self.n_out += len(y)
        if int(flags) & _LAST:
            self.ended = True
        return y, flags

    def retune(self, rate_ratio: float) -> None:
        """Use ``rate_ratio`` from the next output sample on (effective with the next :meth:`process`)."""
        if not self._history_len:
            raise RuntimeError("this conditioner keeps no input history (keep_history=False); it cannot retune")
        q = float(rate_ratio)
        if not (np.isfinite(q) and 0.5 < q < 2.0):
            raise ValueError(f"{rate_ratio=} must be a clock rate ratio near 1")
        if self.ended or q == self.rate_ratio:
            return
        fs, fd = self.working_rate_hz, self.sample_rate_hz
        c_target = self.clock.clock_s(self.n_out)             # clock of the next output under the old ratio
        n_p = self.n_in - len(self._history)                   # input index of the first primed sample
        j0 = max(0, int(math.ceil((c_target - n_p / fd) * fs / q - 0.5)))
        new = DeviceConditioner(fd, working_rate_hz=fs, rate_ratio=q)
        counters = self.inner.counters
        y, _ = new.process(Frame(0, 0, n_p, fd, self._history.copy()))
        new.counters = counters                                # priming is not new input
        self.inner = new
        self.clock.append(self.n_out, n_p / fd + j0 * q / fs, q)
        k = min(j0, len(y))
        self._carry, self._skip = y[k:].astype(np.float32), j0 - k
        self.n_retunes += 1
