"""Messages passed between pipeline stages: frozen dataclasses carrying their own indices.

Streams are aligned on sample indices in each device's own clock, never on wall-clock time.
Data-quality events (NaN samples replaced, clipping, silence, missing device) travel as flags.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np


class FrameFlag(enum.IntFlag):
    """Data-quality flags of one block of one device."""

    NONE = 0
    NAN_REPLACED = enum.auto()   # non-finite samples were replaced by zeros
    CLIPPED = enum.auto()        # samples at or beyond full scale
    SILENT = enum.auto()         # the block is digital silence
    LAST = enum.auto()           # the device's stream ends with this block
    TRUNCATED = enum.auto()      # the device's file ended early (read error)


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
    samples : ndarray, shape (n_samples,), float32
        Mono samples (multi-channel devices are mixed down by the source).
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
    """

    seq: int
    first_sample: int
    sample_rate_hz: float
    samples: np.ndarray
    valid: np.ndarray
    offsets_samples: np.ndarray


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
