"""The frame format devices send over the network (Zenoh payloads), and its validation.

One payload is one frame: a fixed 56-byte little-endian header, then the samples, interleaved
(``n_samples`` rows of ``n_channels``), as int16 (full scale 32768) or float32.

======  ======  ==================  ==========================================================================
offset  bytes   field               meaning
======  ======  ==================  ==========================================================================
0       4       magic               ``b"ADHA"``
4       1       version             1
5       1       sample_format       0 = int16, 1 = float32
6       2       n_channels          1..64
8       4       n_samples           1..1,048,576 per channel (0 in a LAST frame)
12      8       seq                 the sender's frame counter (restarts at 0 when the sender restarts)
20      8       first_sample        index of the first sample in the sender's own clock (int64, >= 0)
28      8       sample_rate_hz      nominal rate (float64, 1,000..384,000)
36      8       capture_time_ns     sender's wall clock when the frame was captured (for latency figures only)
44      8       instance            random id of the sender's run (a new one after a restart)
52      4       flags               :class:`~stream.messages.FrameFlag` bits (LAST: the sender ends cleanly)
======  ======  ==================  ==========================================================================

The engine never aligns devices on ``capture_time_ns``: it aligns on the audio; the capture time only gives
the network latency in reports.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from .messages import FrameFlag

MAGIC = b"ADHA"
VERSION = 1
INT16, FLOAT32 = 0, 1
FORMATS = {"int16": INT16, "float32": FLOAT32}
_DTYPES = {INT16: np.dtype("<i2"), FLOAT32: np.dtype("<f4")}
HEADER = struct.Struct("<4sBBHIQqdqQI")
MAX_CHANNELS = 64
MAX_SAMPLES = 1 << 20
MIN_RATE_HZ, MAX_RATE_HZ = 1000.0, 384000.0


class MalformedFrame(ValueError):
    """A payload that is not a valid frame; the message says what is wrong in a few words."""


@dataclass(frozen=True)
class WireFrame:
    """One decoded frame. ``samples`` is float32, shape (n_samples, n_channels), full scale 1.0."""

    instance: int
    seq: int
    first_sample: int
    sample_rate_hz: float
    capture_time_ns: int
    flags: FrameFlag
    samples: np.ndarray
    sample_format: int = FLOAT32

    @property
    def n_samples(self) -> int:
        return int(self.samples.shape[0])


def encode(samples: np.ndarray, *, seq: int, first_sample: int, sample_rate_hz: float, instance: int,
           capture_time_ns: int = 0, flags: int = 0, sample_format: str | int = "int16") -> bytes:
    """One frame's payload. ``samples``: (n,) or (n, channels), float (full scale 1.0; int16 clips there)."""
    fmt = FORMATS[sample_format] if isinstance(sample_format, str) else int(sample_format)
    x = np.asarray(samples, np.float32)
    if x.ndim == 1:
        x = x[:, None]
    if fmt == INT16:
        data = np.clip(np.rint(x * 32768.0), -32768, 32767).astype("<i2")
    else:
        data = x.astype("<f4", copy=False)
    head = HEADER.pack(MAGIC, VERSION, fmt, x.shape[1], x.shape[0], int(seq), int(first_sample),
                       float(sample_rate_hz), int(capture_time_ns), int(instance) & (2**64 - 1), int(flags))
    return head + np.ascontiguousarray(data).tobytes()


def decode(payload: bytes | bytearray | memoryview) -> WireFrame:
    """The frame in ``payload``.

    Raises
    ------
    MalformedFrame
        Too short, bad magic or version, unknown sample format, absurd channel count, length or rate, a length
        that does not match the header, a negative index, or non-finite float samples.
    """
    buf = memoryview(payload)
    if len(buf) < HEADER.size:
        raise MalformedFrame(f"{len(buf)} bytes, shorter than the {HEADER.size}-byte header")
    magic, version, fmt, n_ch, n, seq, first, rate, t_ns, instance, flags = HEADER.unpack_from(buf)
    if magic != MAGIC:
        raise MalformedFrame(f"bad magic {bytes(magic)!r} (expected {MAGIC!r})")
    if version != VERSION:
        raise MalformedFrame(f"frame format version {version} (this engine reads {VERSION})")
    if fmt not in _DTYPES:
        raise MalformedFrame(f"unknown sample format {fmt}")
    if not 1 <= n_ch <= MAX_CHANNELS:
        raise MalformedFrame(f"{n_ch} channels (1..{MAX_CHANNELS})")
    if not (1 if not flags & FrameFlag.LAST else 0) <= n <= MAX_SAMPLES:   # only a LAST frame may be empty
        raise MalformedFrame(f"{n} samples per channel (1..{MAX_SAMPLES})")
    if not MIN_RATE_HZ <= rate <= MAX_RATE_HZ:      # NaN fails too
        raise MalformedFrame(f"sample rate {rate!r} Hz ({MIN_RATE_HZ:g}..{MAX_RATE_HZ:g})")
    if first < 0:
        raise MalformedFrame(f"negative first sample {first}")
    dtype = _DTYPES[fmt]
    want = HEADER.size + n * n_ch * dtype.itemsize
    if len(buf) != want:
        raise MalformedFrame(f"{len(buf)} bytes where the header announces {want}")
    raw = np.frombuffer(buf, dtype, count=n * n_ch, offset=HEADER.size).reshape(n, n_ch)
    if fmt == INT16:
        x = raw.astype(np.float32) * np.float32(1.0 / 32768.0)
    else:
        x = raw.astype(np.float32)    # a copy: the payload's buffer is not ours to keep
        if not np.isfinite(x).all():
            raise MalformedFrame(f"{int(np.count_nonzero(~np.isfinite(x)))} non-finite samples")
    return WireFrame(instance, seq, first, rate, t_ns, FrameFlag(flags & int(_ALL_FLAGS)), x, fmt)


_ALL_FLAGS = FrameFlag(0)
for _f in FrameFlag:
    _ALL_FLAGS |= _f
