"""Messages passed between pipeline stages: frozen dataclasses carrying their own indices.

Streams are aligned on sample indices in each device's own clock, never on wall-clock time.
Data-quality events (NaN samples replaced, clipping, silence, missing device) travel as flags.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Iterator, Protocol, Sequence

import numpy as np


class FrameFlag(enum.IntFlag):
    """Data-quality flags of one block of one device."""

    NONE = 0
    NAN_REPLACED = enum.auto()   # non-finite samples were replaced by zeros
    CLIPPED = enum.auto()        # samples at or beyond full scale
    SILENT = enum.auto()         # the block is digital silence
    LAST = enum.auto()           # the device's stream ends with this block
    TRUNCATED = enum.auto()      # the device's file ended early (read error)
    GAP = enum.auto()            # samples before this block were lost (filled with zeros, left out of the beam)
    NEW_CLOCK = enum.auto()      # the device restarted: its clock, so its offset to the others, is a new one


@dataclass(frozen=True)
class Frame:
    """One block of audio from one device, in that device's clock.

    Attributes
    ----------
    device_id : int
        Index of the device (0 = reference).
    seq : int
        Sequence number of the block within the device's stream.
    first_sample : int
        Index of the first sample in the device's own clock, at ``sample_rate_hz``.
    sample_rate_hz : float
        Nominal sample rate of the device.
    samples : ndarray, shape (n_samples,) or (n_samples, n_channels), float32
        The device's microphones; several channels are mixed down to mono when the stream conditions them.
    flags : FrameFlag
        Data-quality flags.
    """

    device_id: int
    seq: int
    first_sample: int
    sample_rate_hz: float
    samples: np.ndarray
    flags: FrameFlag = FrameFlag.NONE


@dataclass(frozen=True)
class Block:
    """One hop of time-aligned audio of all devices at the working rate.

    Attributes
    ----------
    seq : int
        Block index; block ``k`` covers reference samples ``[k*hop, (k+1)*hop)``.
    first_sample : int
        First sample in the reference device's clock at the working rate.
    sample_rate_hz : float
        Working rate.
    samples : ndarray, shape (hop_samples, n_devices), float32
    valid : ndarray, shape (n_devices,), bool
        False where a device had no usable audio for this block (not started, ended, silent, NaN).
    offsets_samples : ndarray, shape (n_devices,), int
        Coarse offset applied to each device: device ``i``'s sample ``n + offsets[i]`` was placed at
        reference sample ``n``.
    corrected : ndarray, shape (n_devices,), bool, or None
        Devices whose offset changed at this block because the old one was wrong (a re-check, a repair):
        their fine TOA restarts. None when there is none.
    """

    seq: int
    first_sample: int
    sample_rate_hz: float
    samples: np.ndarray
    valid: np.ndarray
    offsets_samples: np.ndarray
    corrected: np.ndarray | None = None


@dataclass(frozen=True)
class TdoaFrame:
    """Pairwise delays of one analysis frame.

    ``tdoa_s[p] = toa[i] - toa[j]`` for pair ``p = (i, j)`` in :func:`estimators.pairs` order.
    """

    seq: int
    time_s: float
    tdoa_s: np.ndarray
    confidence: np.ndarray


@dataclass(frozen=True)
class ToaEstimate:
    """Relative TOA of every device at one frame; ``toa_s[0] = 0``.

    ``toa_s`` is the total relative TOA in the device clocks (coarse offset plus fine estimate).
    With several tracked sources (``estimator = "tracks"``) it is the steered track's; ``track_id`` names
    that track (-1: none is steered and the output is the reference device), ``speech_probability`` is
    the frame's speech presence (NaN when not measured).
    """

    seq: int
    time_s: float
    toa_s: np.ndarray
    gated: bool
    track_id: int = -1
    speech_probability: float = float("nan")


@dataclass(frozen=True)
class HopResult:
    """What the pipeline produced for one hop, as the sinks consume it (``write(result)``, then ``close()``).

    Attributes
    ----------
    enhanced : ndarray, shape (hop_samples,), float32
        The beamformer's output hop (the first ``Pipeline.latency_samples`` of the stream are its delay).
    toa : ToaEstimate or None
        The steering of the frame this hop belongs to; None for hops that carry no frame: the start-up of a
        lagging estimator and the beamformer's tail after the input ended.
    """

    enhanced: np.ndarray
    toa: ToaEstimate | None = None


class HopSink(Protocol):
    """Consumes the pipeline's hops as they are produced (enhanced.wav, toa.csv, a sound card)."""

    def write(self, result: HopResult) -> None: ...

    def close(self) -> None: ...


class Source(Protocol):
    """What the stream runner reads: replayed files, sound cards, later the network.

    A context manager and an iterator of :class:`Frame` (``with src: for frame in src: ...``), possibly
    delivering devices at different times and rates. ``active`` lists the devices that stream (their
    ``device_id`` is their index there), ``devices`` every one asked for (with the problems of those left
    out). ``stop()`` may be called from a signal handler: the iteration then ends each device's stream with
    a ``LAST`` frame. ``live`` sources end only by ``stop()``; ``duration_s`` is None for them. ``paced``:
    frames come at the pace of the audio (live, or a replay at a given speed), so a device that delivers nothing
    for a while is late; False: as fast as possible, every device's audio at hand (no wall-clock deadline).
    """

    live: bool
    paced: bool
    devices: Sequence
    active: Sequence

    @property
    def sample_rates_hz(self) -> list[float]: ...

    @property
    def duration_s(self) -> float | None: ...

    def __enter__(self) -> "Source": ...

    def __exit__(self, *exc) -> None: ...

    def __iter__(self) -> Iterator[Frame]: ...

    def stop(self) -> None: ...
