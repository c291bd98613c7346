"""The network frame format and the aggregator's jitter buffer, on arrays (no network)."""
from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from stream import wire
from stream.messages import FrameFlag
from stream.net import JitterBuffer, Keys


def _frame(seq: int, *, instance: int = 7, n: int = 4, first: int | None = None, flags: int = 0) -> wire.WireFrame:
    x = np.full(n, seq / 100, np.float32)
    return wire.decode(wire.encode(x, seq=seq, first_sample=seq * n if first is None else first,
                                   sample_rate_hz=16000, instance=instance, flags=flags, sample_format="float32"))


@pytest.mark.parametrize("fmt", ["int16", "float32"])
def test_a_frame_round_trips_every_field(fmt):
    rng = np.random.default_rng(0)
    x = (0.5 * rng.standard_normal((300, 3))).astype(np.float32)
    payload = wire.encode(x, seq=41, first_sample=123456789012, sample_rate_hz=44100.0, instance=2**62 + 5,
                          capture_time_ns=1_700_000_000_123_456_789, flags=int(FrameFlag.CLIPPED),
                          sample_format=fmt)
    assert len(payload) == wire.HEADER.size + 300 * 3 * (2 if fmt == "int16" else 4)
    f = wire.decode(payload)
    assert (f.seq, f.first_sample, f.sample_rate_hz, f.instance, f.capture_time_ns) == \
        (41, 123456789012, 44100.0, 2**62 + 5, 1_700_000_000_123_456_789)
    assert f.flags == FrameFlag.CLIPPED and f.samples.shape == (300, 3) and f.samples.dtype == np.float32
    if fmt == "float32":
        np.testing.assert_array_equal(f.samples, x)
    else:   # int16: within half a step, and exact for values on the int16 grid
        assert np.abs(f.samples - np.clip(x, -1, 32767 / 32768)).max() <= 0.5 / 32768 + 1e-9
        grid = np.clip(np.round(x * 32768), -32768, 32767) / 32768
        np.testing.assert_array_equal(wire.decode(wire.encode(grid, seq=0, first_sample=0, sample_rate_hz=16000,
                                                              instance=1)).samples, grid)


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 2000), ch=st.integers(1, 8), seq=st.integers(0, 2**63 - 1),
       first=st.integers(0, 2**62), fmt=st.sampled_from(["int16", "float32"]))
def test_any_valid_frame_decodes_to_what_was_sent(n, ch, seq, first, fmt):
    x = np.linspace(-0.9, 0.9, n * ch, dtype=np.float32).reshape(n, ch)
    f = wire.decode(wire.encode(x, seq=seq, first_sample=first, sample_rate_hz=48000, instance=3,
                                sample_format=fmt))
    assert f.seq == seq and f.first_sample == first and f.samples.shape == (n, ch)


def _good() -> bytes:
    return wire.encode(np.zeros(64, np.float32), seq=1, first_sample=0, sample_rate_hz=16000, instance=9,
                       sample_format="float32")


def _patched(**fields) -> bytes:
    names = ["magic", "version", "fmt", "n_ch", "n", "seq", "first", "rate", "t_ns", "instance", "flags"]
    good = _good()
    values = dict(zip(names, wire.HEADER.unpack_from(good)))
    values.update(fields)
    return wire.HEADER.pack(*[values[k] for k in names]) + good[wire.HEADER.size:]


@pytest.mark.parametrize("payload, reason", [
    (b"", "shorter than the 56-byte header"),
    (b"hello world", "shorter than"),
    (_patched(magic=b"RIFF"), "bad magic"),
    (_patched(version=9), "version 9"),
    (_patched(fmt=7), "unknown sample format 7"),
    (_patched(n_ch=0), "0 channels"),
    (_patched(n_ch=500), "500 channels"),
    (_patched(n=0), "0 samples"),
    (_patched(rate=float("nan")), "sample rate nan"),
    (_patched(rate=5e9), "sample rate"),
    (_patched(first=-5), "negative first sample"),
    (_good()[:-4], "where the header announces"),
    (_good() + b"\0\0\0\0", "where the header announces"),
    (wire.encode(np.array([0.1, np.nan, np.inf], np.float32), seq=0, first_sample=0, sample_rate_hz=16000,
                 instance=1, sample_format="float32"), "2 non-finite samples"),
])
def test_a_malformed_payload_is_rejected_with_its_reason(payload, reason):
    with pytest.raises(wire.MalformedFrame, match=reason):
        wire.decode(payload)


def test_only_a_last_frame_may_be_empty():
    f = wire.decode(wire.encode(np.zeros(0, np.float32), seq=3, first_sample=99, sample_rate_hz=16000, instance=1,
                                flags=int(FrameFlag.LAST)))
    assert f.n_samples == 0 and f.flags & FrameFlag.LAST
    assert struct.unpack_from("<4s", _good())[0] == wire.MAGIC


def test_keys_of_an_array():
    k = Keys("lab")
    assert k.audio("pi3") == "adhoc/lab/dev/pi3/audio" and k.alive() == "adhoc/lab/alive/*"
    assert Keys.device_of("adhoc/lab/dev/pi3/audio") == "pi3" and Keys.device_of("adhoc/lab/alive/pi3") == "pi3"
    with pytest.raises(ValueError, match="without '/'"):
        Keys("a/b")


# jitter buffer -------------------------------------------------------------------------------------------------
def test_frames_out_of_order_come_out_in_order():
    jb = JitterBuffer(latency_s=0.1)
    for seq in [0, 2, 1, 4, 3, 5]:
        jb.push(_frame(seq), 0.0)
    assert [f.seq for f in jb.pop_ready(0.0)] == [0, 1, 2, 3, 4, 5]
    assert jb.counters.n_reordered == 2 and jb.counters.n_lost_frames == 0


def test_a_missing_frame_is_waited_for_then_declared_lost():
    jb = JitterBuffer(latency_s=0.1)
    jb.push(_frame(0), 0.0)
    jb.push(_frame(2), 1.0)
    jb.push(_frame(3), 1.0)
    assert [f.seq for f in jb.pop_ready(1.05)] == [0]          # 1 may still come
    assert [f.seq for f in jb.pop_ready(1.1)] == [2, 3]        # it waited latency_s: lost
    assert jb.counters.n_lost_frames == 1
    jb.push(_frame(1), 1.2)                                     # too late now: dropped, not reordered into the past
    assert jb.pop_ready(1.2) == [] and jb.counters.n_duplicates == 1


def test_duplicates_are_dropped():
    jb = JitterBuffer()
    for seq in [0, 1, 1, 2, 0]:
        jb.push(_frame(seq), 0.0)
    assert [f.seq for f in jb.pop_ready(0.0)] == [0, 1, 2] and jb.counters.n_duplicates == 2


def test_a_restarted_sender_follows_the_old_one():
    """Sequence numbers from 0 again with a new instance: the old instance's frames go first, then the new."""
    jb = JitterBuffer(latency_s=0.1)
    for seq in range(3):
        jb.push(_frame(seq, instance=1), 0.0)
    jb.push(_frame(0, instance=2), 0.0)
    jb.push(_frame(1, instance=2), 0.0)
    out = jb.pop_ready(0.0)
    assert [(f.instance, f.seq) for f in out] == [(1, 0), (1, 1), (1, 2), (2, 0), (2, 1)]
    assert jb.counters.n_restarts == 1


def test_the_buffer_is_bounded():
    """More waiting frames than the capacity (a hole that never fills, an engine far behind): released at once."""
    jb = JitterBuffer(latency_s=100.0, capacity=10)
    jb.push(_frame(0), 0.0)
    for seq in range(2, 30):
        jb.push(_frame(seq), 0.0)
    out = jb.pop_ready(0.0)
    assert [f.seq for f in out] == [0] + list(range(2, 30)) and len(jb) == 0 and jb.counters.n_lost_frames == 1
