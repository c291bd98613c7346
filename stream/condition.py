"""Per-device conditioning: check the frame's sample index (fill gaps), mix channels down, sanitise samples,
flag data-quality events, resample to the working rate."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import soxr

from .messages import Frame, FrameFlag

_LAST = int(FrameFlag.LAST)
CLIP_LEVEL = 0.999          # |x| at or above this counts as clipped (full scale is 1.0)
SILENCE_RMS = 1e-7          # a block quieter than this (about -140 dBFS) is digital silence


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
        c.n_blocks += 1
        c.n_samples += len(x)
        energy = float(np.dot(x, x)) if len(x) else 0.0   # one BLAS call: finite iff every sample is
        if not np.isfinite(energy):
            finite = np.isfinite(x)
            n_bad = int(len(x) - finite.sum())
            if n_bad:
                c.n_nan_samples += n_bad
                x = np.where(finite, x, np.float32(0.0))
                flags |= FrameFlag.NAN_REPLACED
            energy = float(np.dot(x.astype(np.float64), x.astype(np.float64)))
        if len(x):
            if x.max() >= CLIP_LEVEL or x.min() <= -CLIP_LEVEL:
                c.n_clipped_samples += int(np.count_nonzero(np.abs(x) >= CLIP_LEVEL))
                flags |= FrameFlag.CLIPPED
            if np.sqrt(energy / len(x)) < SILENCE_RMS:
                c.n_silent_blocks += 1
                flags |= FrameFlag.SILENT
        if self._resampler is not None:
            last = bool(int(flags) & _LAST)
            x = self._resampler.resample_chunk(np.ascontiguousarray(x, np.float32), last=last)
        return np.asarray(x, np.float32), flags
