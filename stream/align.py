"""Coarse alignment of devices whose recordings start seconds apart, and the aligned block stream.

Devices are first aligned to the reference (device 0) to within a few samples by cross-correlating
their energy envelopes (as the TOA paper did for its smartphones), then refined by a PHAT-weighted
cross-correlation of the waveforms around the envelope lag. The remaining (fine) relative TOA is
left to the frame-based GCC-PHAT and the TOA estimator. Offsets are re-checked while streaming.

Convention: ``offsets_samples[i] = o`` means device ``i``'s sample ``n + o`` (at the working rate)
lines up with the reference's sample ``n``; ``o / working_rate_hz`` is the coarse relative TOA.
"""
from __future__ import annotations

import concurrent.futures
import logging
import math
import time
from typing import Iterator, Sequence
from dataclasses import dataclass

import numba
import numpy as np
import scipy.fft
import scipy.signal

from .condition import SILENCE_RMS
from .messages import Block, FrameFlag

log = logging.getLogger(__name__)


def energy_envelope(x: np.ndarray, *, sample_rate_hz: float, hop_s: float = 0.01) -> np.ndarray:
    """Log-energy envelope of a signal, zero mean and unit variance.

    Parameters
    ----------
    x : ndarray, shape (n_samples,), float
    sample_rate_hz : float
    hop_s : float
        Envelope resolution in seconds.

    Returns
    -------
    ndarray, shape (n_samples // hop,), float64
    """
    hop = max(1, int(round(hop_s * sample_rate_hz)))
    n = len(x) // hop
    if n == 0:
        return np.zeros(0)
    e = np.log10(np.mean(np.square(x[: n * hop].reshape(n, hop), dtype=np.float64), axis=1) + 1e-12)
    # the floor is taken over the frames that hold sound: digital silence (a card started before the room made
    # a sound, a stream's end) would pull it down, and its step to the first sound would then out-correlate
    # the sound itself
    sound = e > np.log10(SILENCE_RMS ** 2 + 1e-12) + 0.5
    floor = np.percentile(e[sound] if sound.any() else e, 10) + 0.6
    e = np.maximum(e, floor)  # ignore the noise floor (and 6 dB above it): only what rises above it aligns
    e -= e.mean()
    std = e.std()
    return e / std if std > 0 else e


def normalised_xcorr(e: np.ndarray, e_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pearson correlation of ``e[n + lag]`` with ``e_ref[n]`` over their overlap, for every lag.

    Returns
    -------
    (score, lags) : ndarray, shape (len(e) + len(e_ref) - 1,)
    """
    n_e, n_r = len(e), len(e_ref)
    s_xy = scipy.signal.correlate(e, e_ref, mode="full", method="fft")
    lags = scipy.signal.correlation_lags(n_e, n_r, mode="full")
    lo_r = np.maximum(0, -lags)                 # overlap in e_ref: [lo_r, hi_r)
    hi_r = np.minimum(n_r, n_e - lags)
    n = np.clip(hi_r - lo_r, 1, None).astype(float)
    c_r, c_r2 = np.r_[0, np.cumsum(e_ref)], np.r_[0, np.cumsum(e_ref ** 2)]
    c_e, c_e2 = np.r_[0, np.cumsum(e)], np.r_[0, np.cumsum(e ** 2)]
    s_r, s_r2 = c_r[hi_r] - c_r[lo_r], c_r2[hi_r] - c_r2[lo_r]
    s_e, s_e2 = c_e[hi_r + lags] - c_e[lo_r + lags], c_e2[hi_r + lags] - c_e2[lo_r + lags]
    cov = s_xy - s_e * s_r / n
    var = np.clip(s_e2 - s_e ** 2 / n, 0, None) * np.clip(s_r2 - s_r ** 2 / n, 0, None)
    score = np.where(var > 1e-12, cov / np.sqrt(np.maximum(var, 1e-300)), 0.0)
    return score, lags


def coarse_offset(x_ref: np.ndarray, x: np.ndarray, *, sample_rate_hz: float, max_offset_s: float,
                  envelope_hop_s: float = 0.01, refine_s: float = 0.05) -> tuple[int, float]:
    """Offset of ``x`` relative to ``x_ref`` in samples, and a quality in [0, 1].

    ``x[n + offset]`` lines up with ``x_ref[n]``. The quality is the normalised envelope correlation
    at the chosen lag (about 0 for unrelated signals, up to 1).
    """
    hop = max(1, int(round(envelope_hop_s * sample_rate_hz)))
    e_ref = energy_envelope(x_ref, sample_rate_hz=sample_rate_hz, hop_s=envelope_hop_s)
    e = energy_envelope(x, sample_rate_hz=sample_rate_hz, hop_s=envelope_hop_s)
    if len(e_ref) < 4 or len(e) < 4 or not e_ref.any() or not e.any():
        return 0, 0.0
    score, lags = normalised_xcorr(e, e_ref)
    max_lag = int(max_offset_s / envelope_hop_s)
    overlap = np.minimum(len(e_ref), len(e) - lags) - np.maximum(0, -lags)
    min_overlap = max(4, int(0.25 * min(len(e), len(e_ref))))
    ok = (np.abs(lags) <= max_lag) & (overlap >= min_overlap)
    if not ok.any():
        return 0, 0.0
    # rank by correlation times the square root of the overlap share (full weight from FULL_OVERLAP_SHARE on),
    # so that a short overlap that happens to correlate does not beat the long one of the true offset, while
    # among long overlaps the best correlation wins (a repeated sentence correlates at the repetition's lag too)
    share = np.minimum(overlap / (FULL_OVERLAP_SHARE * min(len(e), len(e_ref))), 1.0)
    rank = np.where(ok, score * np.sqrt(share), -np.inf)
    k = int(np.argmax(rank))
    quality = float(np.clip(score[k], 0.0, 1.0))
    coarse = int(lags[k]) * hop
    # refine at sample resolution: PHAT cross-correlation of the waveforms around the envelope lag
    fine = refine_offset(x_ref, x, coarse_samples=coarse, search_samples=int(refine_s * sample_rate_hz))
    return fine, quality


def refine_offset(x_ref: np.ndarray, x: np.ndarray, *, coarse_samples: int, search_samples: int) -> int:
    """Sample-accurate offset near ``coarse_samples`` by PHAT-weighted cross-correlation."""
    start_ref = max(0, -coarse_samples)
    start = start_ref + coarse_samples
    n = min(len(x_ref) - start_ref, len(x) - start)
    if n <= 2 * search_samples:
        return coarse_samples
    a = x_ref[start_ref:start_ref + n].astype(np.float32)
    b = x[start:start + n].astype(np.float32)
    n_fft = scipy.fft.next_fast_len(n + search_samples)
    A = scipy.fft.rfft(a, n_fft)
    B = scipy.fft.rfft(b, n_fft)
    G = B * np.conj(A)
    G /= np.abs(G) + 1e-12
    r = scipy.fft.irfft(G, n_fft)
    lags = np.r_[np.arange(0, search_samples + 1), np.arange(-search_samples, 0)]
    vals = np.r_[r[: search_samples + 1], r[n_fft - search_samples:]]
    # if x[n + coarse + d] = x_ref[n] then b[m + d] = a[m]: the correlation peaks at lag d
    return coarse_samples + int(lags[int(np.argmax(vals))])


_EXECUTOR: concurrent.futures.ThreadPoolExecutor | None = None


def _executor() -> concurrent.futures.ThreadPoolExecutor:
    global _EXECUTOR
    if _EXECUTOR is None:
        _EXECUTOR = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="align-recheck")
    return _EXECUTOR


def _recheck_offsets(ref: np.ndarray, segments: dict[int, np.ndarray], *, sample_rate_hz: float,
                     max_offset_s: float) -> dict[int, tuple[int, float]]:
    """``{device: (offset change in samples, quality)}`` of each segment against the reference's."""
    return {d: coarse_offset(ref, x, sample_rate_hz=sample_rate_hz, max_offset_s=max_offset_s)
            for d, x in segments.items()}


_LAST = int(FrameFlag.LAST)
_NEW_CLOCK = int(FrameFlag.NEW_CLOCK)
_GAP = int(FrameFlag.GAP)
FULL_OVERLAP_SHARE = 0.75        # an envelope overlap this long (of the shorter window) counts in full
RECHECK_MIN_QUALITY = 0.5        # envelope correlation a re-check needs to move an aligned device
_TRIM_EVERY_BLOCKS = 8           # the buffers' fronts are dropped every few blocks (amortised)
RECHECK_MAX_SILENT_SHARE = 0.1   # a re-check skips windows with more digital silence than this (stream ends)


def _silent_share(x: np.ndarray, sample_rate_hz: float) -> float:
    """Share of the 10 ms frames of ``x`` that are digital silence (RMS below ``SILENCE_RMS``)."""
    hop = max(1, int(0.01 * sample_rate_hz))
    n = len(x) // hop
    if n == 0:
        return 1.0
    ms = np.mean(np.square(x[:n * hop].reshape(n, hop), dtype=np.float64), axis=1)
    return float(np.mean(ms < SILENCE_RMS ** 2))


@numba.njit(cache=True, nogil=True)
def _block_valid(samples, aligned, is_reference, covered, out):
    """``out[d]``: device ``d`` is usable in this block: aligned (or the reference), at least half the hop received
    (``covered``) and not digital silence (RMS of its samples at least ``SILENCE_RMS``). One compiled call per
    block instead of a few small numpy calls."""
    hop, n_dev = samples.shape
    for d in range(n_dev):
        e = 0.0
        for i in range(hop):
            v = float(samples[i, d])
            e += v * v
        out[d] = (aligned[d] or is_reference[d]) and covered[d] and math.sqrt(e / hop) >= SILENCE_RMS
    return out


class _SampleBuffer:
    """Growable float32 buffer: amortised O(1) appends, occasional compaction of the front."""

    def __init__(self) -> None:
        self._data = np.zeros(4096, np.float32)
        self._n = 0

    @property
    def data(self) -> np.ndarray:
        """View of the samples held (valid until the next append)."""
        return self._data[: self._n]

    def __len__(self) -> int:
        return self._n

    def append(self, x: np.ndarray) -> None:
        need = self._n + len(x)
        if need > len(self._data):
            grown = np.zeros(max(need, 2 * len(self._data)), np.float32)
            grown[: self._n] = self._data[: self._n]
            self._data = grown
        self._data[self._n:need] = x
        self._n = need

    def drop_front(self, n: int) -> None:
        keep = self._n - n
        self._data[:keep] = self._data[n:self._n]
        self._n = keep


@dataclass
class AlignmentEvent:
    """A change of a device's coarse offset while streaming."""

    time_s: float
    device_id: int
    old_offset_samples: int
    new_offset_samples: int
    reason: str


class Aligner:
    """Buffers each device at the working rate and emits time-aligned hop blocks.

    Parameters
    ----------
    n_devices : int
    sample_rate_hz : float
        Working rate.
    hop_samples : int
        Length of each emitted block.
    align_window_s : float
        Audio collected from every device before the first alignment (start-up latency of a live
        stream; a replay that ends sooner aligns on what it has).
    max_offset_s : float
        Largest start offset searched, in seconds.
    min_quality : float
        Devices whose envelope correlation with the reference stays below this are left out
        (valid = False) with a one-sentence message.
    recheck_s : float or None
        Re-check the offsets on the last ``align_window_s`` of audio every ``recheck_s`` seconds.
    recheck_tolerance_s : float
        A re-check moves a device only if its offset changed by more than this.
    deadline_s : float or None
        A device that delivered nothing for this long (wall clock) while the others did is late: the blocks it
        lacks go out without it (invalid, zeros; one sentence) and it is back as soon as its samples come in
        time. A replay as fast as possible is never late (any split of the input gives the same blocks). None:
        wait for every device (a stalled device then stalls the stream).
    recheck_delay_s : float
        A re-check runs in a worker thread (a long correlation must not stall the audio path) and its result
        is applied this many seconds of stream later, waiting for it only if it is not done by then: live,
        paced and as-fast-as-possible streams give the same output.
    clock_groups : sequence of int, optional
        ``clock_groups[d]``: the first device of ``d``'s clock group (the mics of one synchronous array,
        :mod:`stream.channels`), at or before ``d``. A group shares one coarse offset, measured on its first
        device and moved as one by re-checks and :meth:`shift_group`. Default: every device its own clock.
    """

    def __init__(self, n_devices: int, *, sample_rate_hz: float, hop_samples: int, align_window_s: float = 8.0,
                 max_offset_s: float = 4.0, min_quality: float = 0.15, recheck_s: float | None = 10.0,
                 recheck_tolerance_s: float = 0.01, recheck_delay_s: float = 0.5,
                 deadline_s: float | None = 2.0, clock_groups: Sequence[int] | None = None) -> None:
        if n_devices < 1:
            raise ValueError(f"{n_devices=} must be >= 1")
        if hop_samples < 1:
            raise ValueError(f"{hop_samples=} must be >= 1")
        if not align_window_s > 0 or not max_offset_s >= 0:
            raise ValueError(f"{align_window_s=} must be > 0 s and {max_offset_s=} >= 0 s")
        self.n_devices = n_devices
        groups = list(range(n_devices)) if clock_groups is None else [int(g) for g in clock_groups]
        if len(groups) != n_devices or any(not 0 <= g <= d or groups[g] != g for d, g in enumerate(groups)):
            raise ValueError(f"{clock_groups=} must give each of the {n_devices} devices the first device of its "
                             "group (itself or an earlier device that is its own first)")
        self.clock_groups = groups
        self._group_of = {g: [d for d in range(n_devices) if groups[d] == g] for g in set(groups)}
        self.sample_rate_hz = float(sample_rate_hz)
        self.hop_samples = int(hop_samples)
        self.window_samples = int(align_window_s * sample_rate_hz)
        self.max_offset_s = float(max_offset_s)
        self.min_quality = float(min_quality)
        self.recheck_blocks = None if not recheck_s else max(1, int(recheck_s * sample_rate_hz / hop_samples))
        self.recheck_tolerance_samples = int(recheck_tolerance_s * sample_rate_hz)
        self.recheck_delay_blocks = max(1, int(recheck_delay_s * sample_rate_hz / hop_samples))
        self._pending: tuple | None = None
        self._waiting_for: int | None = None   # the device the next block waits for (see push)
        self.deadline_s = deadline_s
        self._last_data_s = [time.monotonic()] * n_devices
        self._late = [False] * n_devices
        self.n_late_blocks = np.zeros(n_devices, dtype=np.int64)
        self._corrected = np.zeros(n_devices, bool)
        self._any_corrected = False
        self._new_clock_pending: set[int] = set()
        self._ref_start: int | None = None     # reference sample of its first frame that is not a gap
        self._bufs = [_SampleBuffer() for _ in range(n_devices)]
        self._buf_start = [0] * n_devices     # device sample index of _bufs[d][0]
        self._received = [0] * n_devices
        self._ended = [False] * n_devices
        self.offsets_samples = np.zeros(n_devices, dtype=np.int64)
        self.quality = np.ones(n_devices)
        self.aligned = np.ones(n_devices, dtype=bool)
        self._is_reference = np.arange(n_devices) == 0
        self.ready = False
        self.next_block = 0
        self.events: list[AlignmentEvent] = []
        self.messages: list[str] = []

    # input -----------------------------------------------------------------------------------
    def push(self, device_id: int, samples: np.ndarray, flags: FrameFlag = FrameFlag.NONE) -> Iterator[Block]:
        """Add working-rate samples of one device; iterate over the blocks that became complete.

        The blocks are cut one at a time as the caller takes them, so an offset change requested while the
        caller processes block ``k`` (:meth:`shift`) takes effect at block ``k + 1`` however the input was
        split into frames: streaming equals batch. Iterate to the end before the next call."""
        if device_id == 0 and self._ref_start is None and len(samples) and not int(flags) & _GAP:
            self._ref_start = self._received[0]     # the reference's first audio (not a network lead)
        if len(samples):
            self._bufs[device_id].append(samples)
            self._received[device_id] += len(samples)
            if self.deadline_s is not None:
                self._last_data_s[device_id] = time.monotonic()
        if int(flags) & _NEW_CLOCK:
            if self.ready:
                self._new_clock(device_id)
            else:       # the first alignment's window holds both clocks: the device waits for a re-check
                self._new_clock_pending.add(device_id)
        if int(flags) & _LAST:
            self._ended[device_id] = True
        elif self._waiting_for is not None and self._waiting_for != device_id and (
                self.deadline_s is None or time.monotonic() - self._last_data_s[self._waiting_for] < self.deadline_s):
            return iter(())   # the next block waits for a device that is not late: nothing new (most pushes)
        return self._emit()

    def finish(self) -> Iterator[Block]:
        """Mark every device as ended and iterate over the remaining blocks."""
        self._ended = [True] * self.n_devices
        return self._emit()

    # alignment -------------------------------------------------------------------------------
    def _late_devices(self) -> set[int]:
        """Devices (not ended) that delivered nothing for ``deadline_s`` (wall clock) while another did: the
        blocks they lack go out without them. A replay as fast as possible has none."""
        if self.deadline_s is None:
            return set()
        now = time.monotonic()
        live = [d for d in range(self.n_devices) if not self._ended[d]]
        if not live or max(self._last_data_s[d] for d in live) < now - self.deadline_s:
            return set()   # nobody delivers: nobody is late, the stream waits
        return {d for d in live if self._last_data_s[d] < now - self.deadline_s}

    def _overdue(self) -> bool:
        """Whether any device is late (:meth:`_late_devices`)."""
        return bool(self._late_devices()) if self.deadline_s is not None else False

    def _note_late(self, end: int, lacking: list[int]) -> None:
        """One sentence when a device falls behind the deadline, one when it has caught up; count its blocks.
        ``lacking``: the devices (not ended) without the samples of the block that ends at ``end``."""
        t_s = end / self.sample_rate_hz
        for d in range(self.n_devices):
            late = d in lacking
            if late:
                self.n_late_blocks[d] += 1
            if late and not self._late[d]:
                msg = (f"t={t_s:.2f} s: device {d} delivered nothing for {self.deadline_s:g} s while the others "
                       "did; the stream goes on without it until it catches up.")
                self.messages.append(msg)
                log.warning(msg)
            elif not late and self._late[d]:
                log.info("t=%.2f s: device %d has caught up and is back in the stream.", t_s, d)
            self._late[d] = late

    def _new_clock(self, device_id: int) -> None:
        """A device restarted (a new clock): its offset to the reference is unknown again, so it leaves the beam
        until a re-check finds it (the reference restarted: every other device)."""
        g = self.clock_groups[device_id]   # an array restarts as one clock
        for d in (self._group_of[g] if g else [d for d in range(self.n_devices) if self.clock_groups[d]]):
            if self.aligned[d]:
                self.aligned[d] = False
                msg = (f"Device {d} restarted with a new clock" if g else
                       f"The reference restarted with a new clock, so device {d}")
                msg += " is left out of the beamformer until the next re-check of the offsets aligns it again."
                self.messages.append(msg)
                log.warning(msg)

    def _initial_alignment(self) -> None:
        s0 = self._ref_start or 0     # a reference that joined the network late: its window starts at its audio
        ref = self._bufs[0].data[s0:s0 + self.window_samples].copy()
        for d in range(1, self.n_devices):
            g = self.clock_groups[d]
            if g != d:   # a mic of an array: its device's offset (the first mic's, measured before it)
                self.offsets_samples[d], self.quality[d], self.aligned[d] = (self.offsets_samples[g],
                                                                            self.quality[g], self.aligned[g])
                continue
            x = self._bufs[d].data[s0:s0 + self.window_samples + int(self.max_offset_s * self.sample_rate_hz)]
            off, q = coarse_offset(ref, x, sample_rate_hz=self.sample_rate_hz, max_offset_s=self.max_offset_s)
            self.offsets_samples[d], self.quality[d] = off, q
            if q < self.min_quality:
                self.aligned[d] = False
                msg = (f"Device {d} shares no clear sound with the reference within ±{self.max_offset_s:g} s "
                       f"(envelope correlation {q:.2f}); it is left out of the beamformer.")
                self.messages.append(msg)
                log.warning(msg)
        self.ready = True
        for d in sorted(self._new_clock_pending):
            self._new_clock(d)

    def _submit_recheck(self) -> None:
        """Snapshot the last ``align_window_s`` of every device and re-check the offsets in a worker thread;
        the result is applied ``recheck_delay_blocks`` later (:meth:`_apply_recheck`)."""
        ref_end = self.next_block * self.hop_samples
        ref_start = max(0, ref_end - self.window_samples)
        ref = self._slice(0, ref_start, ref_end)
        if ref is None or _silent_share(ref, self.sample_rate_hz) > RECHECK_MAX_SILENT_SHARE:
            return
        segments = {}
        for d in range(1, self.n_devices):
            if self.clock_groups[d] != d:
                continue
            o = int(self.offsets_samples[d])
            x = self._slice(d, ref_start + o, ref_end + o)
            if x is not None and _silent_share(x, self.sample_rate_hz) <= RECHECK_MAX_SILENT_SHARE:
                segments[d] = x
        max_offset_s = min(self.max_offset_s, 0.5 * len(ref) / self.sample_rate_hz)
        future = _executor().submit(_recheck_offsets, ref, segments, sample_rate_hz=self.sample_rate_hz,
                                    max_offset_s=max_offset_s)
        self._pending = (self.next_block + self.recheck_delay_blocks, self.offsets_samples.copy(), future)

    def _apply_recheck(self) -> None:
        """Apply a finished re-check (waiting for it if needed: the same result on any machine). A device
        whose offset moved since the snapshot is left alone."""
        _, snapshot, future = self._pending
        self._pending = None
        for d, (delta, q) in future.result().items():   # a worker's error is raised here, in the stream loop
            # moving an aligned device takes a clear correlation; joining a left-out one, the usual threshold
            need = self.min_quality if not self.aligned[d] else max(self.min_quality, RECHECK_MIN_QUALITY)
            if q < need or self.offsets_samples[d] != snapshot[d]:
                continue
            if not self.aligned[d]:
                for m in self._group_of[d]:
                    self.aligned[m] = True
                    self.quality[m] = q
                self.shift_group(d, delta, reason="device became audible with the reference; aligned now",
                                 correction=True)
            elif abs(delta) > self.recheck_tolerance_samples:
                self.shift_group(d, delta, reason="periodic re-check of the coarse offset", correction=True)

    def shift(self, device_id: int, delta_samples: int, *, reason: str, correction: bool = False) -> None:
        """Move a device's coarse offset by ``delta_samples`` from the next block on.

        ``correction``: the old offset was wrong (a re-check found the device elsewhere, a calibration repaired
        it), so the fine TOA tracked under it means nothing: the next block says so (``Block.corrected``) and
        the stream restarts its TOA estimator. Otherwise (re-centring, a clock-rate change) the total TOA is
        unchanged and the estimator moves with the offset."""
        if delta_samples == 0:
            return
        if correction:
            self._corrected[device_id] = True
            self._any_corrected = True
        old = int(self.offsets_samples[device_id])
        self.offsets_samples[device_id] = old + int(delta_samples)
        t_s = self.next_block * self.hop_samples / self.sample_rate_hz
        self.events.append(AlignmentEvent(t_s, device_id, old, old + int(delta_samples), reason))
        log.info("t=%.2f s: device %d coarse offset %d -> %d samples (%s).", t_s, device_id, old,
                 old + int(delta_samples), reason)

    def shift_group(self, device_id: int, delta_samples: int, *, reason: str, correction: bool = False) -> None:
        """:meth:`shift` every device of ``device_id``'s clock group (``clock_groups``) by the same amount."""
        for d in self._group_of[self.clock_groups[device_id]]:
            self.shift(d, delta_samples, reason=reason, correction=correction)

    # output ----------------------------------------------------------------------------------
    def _held_part(self, d: int, start: int, stop: int) -> tuple[int, np.ndarray] | None:
        """The part of device samples [start, stop) that was received: (its offset from ``start``, a view of the
        buffer), None if none is there."""
        b0 = self._buf_start[d]
        buf = self._bufs[d].data
        lo, hi = max(start, b0), min(stop, b0 + len(buf))
        return None if hi <= lo else (lo - start, buf[lo - b0:hi - b0])

    def _slice(self, d: int, start: int, stop: int) -> np.ndarray | None:
        """Device samples [start, stop) (zeros outside what was received), None if none is there."""
        part = self._held_part(d, start, stop)
        if part is None:
            return None
        out = np.zeros(stop - start, np.float32)
        out[part[0]:part[0] + len(part[1])] = part[1]
        return out

    def _end_block(self) -> int:
        """Number of blocks in the whole stream once every device has ended: the output covers the
        reference device's recording."""
        return int(np.ceil(self._received[0] / self.hop_samples))

    def _emit(self) -> Iterator[Block]:
        if not self.ready:
            if self._ref_start is None and not self._ended[0]:
                return                    # the reference has delivered no audio yet (only a network lead)
            s0 = self._ref_start or 0
            need = [s0 + self.window_samples + (int(self.max_offset_s * self.sample_rate_hz) if d else 0)
                    for d in range(self.n_devices)]
            have = all(self._ended[d] or self._received[d] >= need[d] for d in range(self.n_devices))
            if not have and not (self._received[0] >= need[0] and self._overdue()):
                return
            self._initial_alignment()
        hop = self.hop_samples
        n_dev = self.n_devices
        all_ended = all(self._ended)
        while True:
            k = self.next_block
            if self._ended[0] and k >= self._end_block():
                break
            offsets = self.offsets_samples.tolist()
            if not all_ended:
                end = (k + 1) * hop
                received, ended = self._received, self._ended
                lacking = [d for d in range(n_dev) if not ended[d] and received[d] < end + offsets[d]]
                if lacking:
                    late = self._late_devices()
                    # wait for the one furthest behind (the last to come, in a round of pushes): pushes from the
                    # others return at once (push)
                    waiting = max((d for d in lacking if d not in late), default=None,
                                  key=lambda d: (offsets[d] - received[d], d))
                    if waiting is not None or len(late) == n_dev - sum(ended):
                        self._waiting_for = lacking[0] if waiting is None else waiting
                        break
                if lacking or any(self._late):
                    self._note_late(end, lacking)
            self._waiting_for = None
            if self._pending is not None and k >= self._pending[0]:
                self._apply_recheck()
                offsets = self.offsets_samples.tolist()
            if self.recheck_blocks and k > 0 and k % self.recheck_blocks == 0 and self._pending is None:
                self._submit_recheck()
            samples = np.zeros((hop, n_dev), np.float32)
            covered = np.zeros(n_dev, np.bool_)   # at least half the hop was received
            for d in range(n_dev):   # written in place: zeros where a device has no samples
                start = k * hop + offsets[d]
                part = self._held_part(d, start, start + hop)
                if part is not None:
                    at, x = part
                    samples[at:at + len(x), d] = x
                    covered[d] = min(start + hop, self._received[d]) - max(start, self._buf_start[d], 0) >= hop // 2
            valid = _block_valid(samples, self.aligned, self._is_reference, covered, np.empty(n_dev, np.bool_))
            corrected = None
            if self._any_corrected:
                corrected, self._corrected = self._corrected, np.zeros(n_dev, bool)
                self._any_corrected = False
            self.next_block += 1
            if self.next_block % _TRIM_EVERY_BLOCKS == 0:
                self._trim()
            yield Block(seq=k, first_sample=k * hop, sample_rate_hz=self.sample_rate_hz, samples=samples,
                        valid=valid, offsets_samples=np.array(offsets, np.int64), corrected=corrected)

    def _trim(self) -> None:
        keep = self.window_samples + self.hop_samples
        for d in range(self.n_devices):
            pos = self.next_block * self.hop_samples + int(self.offsets_samples[d])
            cut = min(pos - keep - self._buf_start[d], len(self._bufs[d]))   # a late device has less
            if cut > 4 * keep:  # amortise the copy
                self._bufs[d].drop_front(cut)
                self._buf_start[d] += cut
