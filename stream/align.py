"""Coarse alignment of devices whose recordings start seconds apart, and the aligned block stream.

Devices are first aligned to the reference (device 0) to within a few samples by cross-correlating
their energy envelopes (as the TOA paper did for its smartphones), then refined by a PHAT-weighted
cross-correlation of the waveforms around the envelope lag (:mod:`stream.offsets`). The remaining (fine)
relative TOA is left to the frame-based GCC-PHAT and the TOA estimator. Offsets are re-checked while
streaming, in a child process (:class:`stream.offsets.OffsetWorker`) so that the correlation does not share
the GIL with the stream loop.

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

from .messages import Block, FrameFlag
from .offsets import SILENCE_RMS, coarse_offset, joint_offsets, worker

log = logging.getLogger(__name__)


_EXECUTOR: concurrent.futures.ThreadPoolExecutor | None = None


def _executor() -> concurrent.futures.ThreadPoolExecutor:
    global _EXECUTOR
    if _EXECUTOR is None:
        _EXECUTOR = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="align-recheck")
    return _EXECUTOR


_LAST = int(FrameFlag.LAST)
_NEW_CLOCK = int(FrameFlag.NEW_CLOCK)
_GAP = int(FrameFlag.GAP)
RECHECK_MIN_QUALITY = 0.5        # envelope correlation a re-check needs to move an aligned device
_TRIM_EVERY_BLOCKS = 8           # the buffers' fronts are dropped every few blocks (amortised)
RECHECK_MAX_SILENT_SHARE = 0.1   # a re-check skips windows with more digital silence than this (stream ends)


@numba.njit(cache=True, nogil=True)
def _cut_block(datas, buf_start, received, offsets, first, aligned, is_reference, samples, valid):
    """Cut one block: ``samples[:, d]`` = device ``d``'s samples ``[first + offsets[d], + hop)`` from its buffer
    ``datas[d]`` (holding device samples ``[buf_start[d], received[d])``; zeros where it holds none), and
    ``valid[d]``: the device is usable in this block: aligned (or the reference), at least half the hop received
    and not digital silence (RMS of its samples at least ``SILENCE_RMS``). One compiled call per block instead of
    a Python loop over the devices and a few small numpy calls."""
    hop, n_dev = samples.shape
    for d in range(n_dev):
        start = first + offsets[d]
        b0 = buf_start[d]
        lo, hi = max(start, b0), min(start + hop, received[d])
        buf = datas[d]
        e = 0.0
        for i in range(hop):
            j = start + i
            v = buf[j - b0] if lo <= j < hi else np.float32(0.0)
            samples[i, d] = v
            e += float(v) * float(v)
        covered = hi > lo and hi - max(start, b0, 0) >= hop // 2
        valid[d] = (aligned[d] or is_reference[d]) and covered and math.sqrt(e / hop) >= SILENCE_RMS
    return valid


def compile_kernels(hop_samples: int, n_devices: int) -> None:
    """Compile (or load from numba's cache) this module's per-block kernel before a stream starts."""
    zeros = np.zeros(n_devices, np.int64)
    _cut_block(tuple(np.zeros(hop_samples, np.float32) for _ in range(n_devices)), zeros, zeros + hop_samples,
               zeros, 0, np.ones(n_devices, bool), np.zeros(n_devices, bool),
               np.zeros((hop_samples, n_devices), np.float32), np.empty(n_devices, np.bool_))


class _SampleBuffer:
    """Growable float32 buffer: amortised O(1) appends, occasional compaction of the front.

    ``capacity``: what the stream holds at most, allocated at once (untouched pages cost no memory until
    written): growing copies the whole buffer into new pages, several ms per device at 48 kHz, once in the
    stream's first seconds, where it made one hop late."""

    def __init__(self, capacity: int = 4096) -> None:
        self._data = np.zeros(max(int(capacity), 1), np.float32)
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
        time. A replay as fast as possible passes None (its output must not depend on the machine's load). None:
        wait for every device (a stalled device then stalls the stream).
    recheck_delay_s : float
        A re-check runs in a child process (a long correlation must not stall the audio path; a thread
        waits for it) and its result is applied this many seconds of stream later, waiting for it only if it is not done by then: live,
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
        if self.recheck_blocks:
            worker().start()   # it imports while the stream starts: ready by the first re-check
        self._pending: tuple | None = None
        self._snapshots = (np.full((n_devices, self.window_samples), 0.0, np.float32)   # the re-check's copies
                           if self.recheck_blocks else None)
        self._waiting_for: int | None = None   # the device the next block waits for (see push)
        self.deadline_s = deadline_s
        self._last_data_s = [time.monotonic()] * n_devices
        self._late = [False] * n_devices
        self.n_late_blocks = np.zeros(n_devices, dtype=np.int64)
        self._corrected = np.zeros(n_devices, bool)
        self._any_corrected = False
        self._new_clock_pending: set[int] = set()
        self._ref_start: int | None = None     # reference sample of its first frame that is not a gap
        # held at most: the first alignment's window and search, then the kept window and up to 4 more before
        # _trim drops them (every _TRIM_EVERY_BLOCKS blocks), and a device's lead of up to max_offset_s
        keep = self.window_samples + self.hop_samples
        capacity = 5 * keep + 2 * int(max_offset_s * sample_rate_hz) + 2 * _TRIM_EVERY_BLOCKS * self.hop_samples
        self._bufs = [_SampleBuffer(capacity) for _ in range(n_devices)]
        self._buf_start = [0] * n_devices     # device sample index of _bufs[d][0]
        self._received = [0] * n_devices
        self._ended = [False] * n_devices
        self.offsets_samples = np.zeros(n_devices, dtype=np.int64)
        self._block_offsets: np.ndarray | None = None   # the last blocks' offsets (shared while equal)
        self._block_offsets_list: list[int] = []
        self.quality = np.ones(n_devices)
        self.aligned = np.ones(n_devices, dtype=bool)
        self._is_reference = np.arange(n_devices) == 0
        # the device whose audio the offsets are measured against: the reference (device 0), unless it shares no
        # clear sound with most of the others (it hears only noise, or nothing) and another device does
        self.pivot = 0
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

    def _windows(self, p: int, s0: int) -> tuple[np.ndarray, dict[int, np.ndarray]]:
        """Device ``p``'s first alignment window, and the first device of every other clock group's window with
        the search beyond it (views of the buffers)."""
        extra = int(self.max_offset_s * self.sample_rate_hz)
        return (self._bufs[p].data[s0:s0 + self.window_samples],
                {d: self._bufs[d].data[s0:s0 + self.window_samples + extra] for d in range(self.n_devices)
                 if self.clock_groups[d] == d and d != p})   # p is the first device of its group

    def _offsets_against(self, p: int, s0: int) -> dict[int, tuple[int, float]]:
        """``{device: (offset, quality)}`` of the first device of every other clock group against device ``p``'s
        first alignment window (offsets of ``p``'s own clock: ``p`` at 0)."""
        ref, windows = self._windows(p, s0)
        return {d: coarse_offset(ref, x, sample_rate_hz=self.sample_rate_hz, max_offset_s=self.max_offset_s)
                for d, x in windows.items()}

    def _joint(self, s0: int, found: dict[int, tuple[int, float]]) -> dict[int, tuple[int, float]]:
        """``found``, or its offsets refined over every pair together when the pairwise ones disagree grossly
        (:func:`~stream.offsets.joint_offsets`)."""
        ref, windows = self._windows(self.pivot, s0)
        joint = joint_offsets(ref, {d: (x, *found[d]) for d, x in windows.items()},
                              sample_rate_hz=self.sample_rate_hz, min_quality=self.min_quality)
        return {d: ((joint[d], q) if d in joint else (o, q)) for d, (o, q) in found.items()}

    @property
    def time_reference(self) -> int:
        """The device whose time the beam keeps: device 0, or :attr:`pivot` while device 0 is left out (its TOA is
        then only the convention ``toa[0] = 0``, and a moving one)."""
        return 0 if self.aligned[0] else self.pivot

    def _n_clear(self, offsets: dict[int, tuple[int, float]]) -> int:
        """How many of ``{device: (offset, quality)}`` share a clear sound (quality >= ``min_quality``)."""
        return sum(q >= self.min_quality for _, q in offsets.values())

    def _choose_pivot(self, s0: int, found: dict[int, tuple[int, float]]) -> dict[int, tuple[int, float]]:
        """The reference shares no clear sound with most devices (it hears only noise, a mic covered or broken):
        measure against the device that shares it with the most others, so that they are aligned with each other
        and beamformed, and leave the reference out. Returns the offsets of every other group's first device,
        device 0's included, against the pivot (``found`` when no device does better)."""
        n_bad = len(found) - self._n_clear(found)
        best_n, best = self._n_clear(found), found
        for p in found:
            other = self._offsets_against(p, s0)
            n = self._n_clear(other)
            if n > best_n:
                best_n, best, self.pivot = n, other, p
        if not self.pivot:
            return found
        q0 = best[0][1]
        best[self.pivot] = (0, 1.0)
        self._is_reference = np.arange(self.n_devices) == self.pivot
        msg = (f"The reference device 0 shares no clear sound with the other devices (envelope correlation below "
               f"{self.min_quality:g} with {n_bad} of {len(found)}: it may hear only noise, or nothing); the offsets "
               f"are measured against device {self.pivot}"
               + (", and device 0 is left out of the beamformer until it shares their sound."
                  if q0 < self.min_quality else "."))
        self.messages.append(msg)
        log.warning(msg)
        return best

    def _initial_alignment(self) -> None:
        s0 = self._ref_start or 0     # a reference that joined the network late: its window starts at its audio
        found = self._offsets_against(0, s0)
        if len(found) >= 2 and 2 * self._n_clear(found) < len(found):
            found = self._choose_pivot(s0, found)
        found = self._joint(s0, found)
        if self.pivot:   # device 0 is measured like any other device, against the pivot
            self.quality[0] = found[0][1]
            for m in self._group_of[0]:
                self.aligned[m] = self.quality[0] >= self.min_quality
        for d in range(1, self.n_devices):
            g = self.clock_groups[d]
            if g != d:   # a mic of an array: its device's offset (the first mic's, measured before it)
                self.offsets_samples[d], self.quality[d], self.aligned[d] = (self.offsets_samples[g],
                                                                            self.quality[g], self.aligned[g])
                continue
            off, q = found[d]
            self.offsets_samples[d], self.quality[d] = off, q
            if q < self.min_quality:
                self.aligned[d] = False
                what = "the reference" if not self.pivot else f"device {self.pivot}"
                msg = (f"Device {d} shares no clear sound with {what} within ±{self.max_offset_s:g} s "
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
        # copied into arrays kept from one re-check to the next (the worker is done with them before the next
        # is submitted), written once when the aligner was made: fresh arrays cost page faults, 2-3 ms per
        # device at 48 kHz on this VM
        n = ref_end - ref_start
        p = self.pivot
        o = int(self.offsets_samples[p])
        ref = self._slice(p, ref_start + o, ref_end + o, self._snapshots[p, :n])
        if ref is None:
            return
        segments = {}
        for d in range(self.n_devices):
            if self.clock_groups[d] != d or d == p:   # p is the first device of its group
                continue
            o = int(self.offsets_samples[d])
            x = self._slice(d, ref_start + o, ref_end + o, self._snapshots[d, :n])
            if x is not None:
                segments[d] = x
        max_offset_s = min(self.max_offset_s, 0.5 * len(ref) / self.sample_rate_hz)
        # the worker skips windows of digital silence (its check, too, costs ms per device at 48 kHz)
        future = _executor().submit(worker().compute, ref, segments, sample_rate_hz=self.sample_rate_hz,
                                    max_offset_s=max_offset_s, max_silent_share=RECHECK_MAX_SILENT_SHARE)
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

    def _slice(self, d: int, start: int, stop: int, out: np.ndarray | None = None) -> np.ndarray | None:
        """Device samples [start, stop) (zeros outside what was received; written into ``out`` if given), None if
        none is there."""
        part = self._held_part(d, start, stop)
        if part is None:
            return None
        if out is None:
            out = np.zeros(stop - start, np.float32)
        else:
            out[:part[0]] = 0.0
            out[part[0] + len(part[1]):] = 0.0
        out[part[0]:part[0] + len(part[1])] = part[1]
        return out

    def _end_block(self) -> int:
        """Number of blocks in the whole stream once every device has ended: the output covers the
        reference device's recording."""
        return int(np.ceil(self._received[0] / self.hop_samples))

    def _offsets_now(self) -> tuple[np.ndarray, list[int]]:
        """The next block's offsets: a copy of ``offsets_samples`` (a shift moves them later), the same array
        as the last block's while they have not changed (so the pipeline can tell at once), and as a list."""
        offsets = self.offsets_samples.tolist()
        if self._block_offsets is None or offsets != self._block_offsets_list:
            self._block_offsets = self.offsets_samples.copy()   # not to be written to: blocks share it
            self._block_offsets_list = offsets
        return self._block_offsets, offsets

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
            offsets_now, offsets = self._offsets_now()
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
                offsets_now, offsets = self._offsets_now()
            if self.recheck_blocks and k > 0 and k % self.recheck_blocks == 0 and self._pending is None:
                self._submit_recheck()
            samples = np.empty((hop, n_dev), np.float32)
            # each buffer holds device samples [_buf_start[d], _received[d])
            valid = _cut_block(tuple([b._data for b in self._bufs]), np.array(self._buf_start),
                               np.array(self._received), offsets_now, k * hop, self.aligned, self._is_reference,
                               samples, np.empty(n_dev, np.bool_))
            corrected = None
            if self._any_corrected:
                corrected, self._corrected = self._corrected, np.zeros(n_dev, bool)
                self._any_corrected = False
            self.next_block += 1
            if self.next_block % _TRIM_EVERY_BLOCKS == 0:
                self._trim()
            yield Block(seq=k, first_sample=k * hop, sample_rate_hz=self.sample_rate_hz, samples=samples,
                        valid=valid, offsets_samples=offsets_now, corrected=corrected)

    def _trim(self) -> None:
        keep = self.window_samples + self.hop_samples
        for d in range(self.n_devices):
            pos = self.next_block * self.hop_samples + int(self.offsets_samples[d])
            cut = min(pos - keep - self._buf_start[d], len(self._bufs[d]))   # a late device has less
            if cut > 4 * keep:  # amortise the copy
                self._bufs[d].drop_front(cut)
                self._buf_start[d] += cut
