"""Devices that stream to an aggregator over Eclipse Zenoh.

Key expressions (``ARRAY`` is ``--array``, default ``default``)::

    adhoc/ARRAY/dev/NAME/audio      frames of device NAME (stream.wire format)
    adhoc/ARRAY/dev/NAME/info       queryable: JSON facts of the device (name, rate, channels, gain, version)
    adhoc/ARRAY/alive/NAME          liveliness token of device NAME (present while its agent runs)
    adhoc/ARRAY/out/enhanced        the aggregator's enhanced audio (stream.wire format, float32 mono)
    adhoc/ARRAY/out/toa             one JSON object per TOA frame: time_s, toa_s (per device), gated, devices
    adhoc/ARRAY/out/geometry        JSON of each calibrated geometry (positions, clock offsets, drift)
    adhoc/ARRAY/aggregator/alive    liveliness token of the aggregator

A device agent (:func:`run_device`) turns any :class:`~stream.messages.Source` (a sound card, a file replayed
at real time) into frames on its key. The aggregator's :class:`NetSource` is a Source of the one stream loop
(:func:`stream.run.run_stream`): it discovers devices by their liveliness tokens, keeps a bounded jitter buffer
per device, and places each device's samples on one continuous clock per device, concealing what is missing
(zeros flagged ``GAP``: the aligner leaves those blocks out of GCC-PHAT and the beamformer).

What is dropped when something is slow (backpressure):

* a device agent publishes RELIABLE with congestion control BLOCK: when the network cannot take its frames,
  ``put`` waits, and the card's 20 s ring absorbs the wait (beyond that the ring records a gap);
* the aggregator never blocks Zenoh: each device's jitter buffer holds at most ``buffer_s`` seconds; when
  the engine falls that far behind, the oldest frames are dropped (counted as ``n_overrun_frames``) and
  concealed as a gap.
"""
from __future__ import annotations

import collections
import itertools
import json
import logging
import re
import secrets
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from . import wire
from .errors import AdhocArrayError, ConfigError
from .messages import Frame, FrameFlag, HopResult
from .replay import DeviceInfo
from .stopping import install_stop_handlers as _install_stop_handlers

log = logging.getLogger(__name__)

PREFIX = "adhoc"
DEPARTURE_GRACE_S = 0.5  # a token gone without a LAST frame: a departure only if none comes this soon (lossy links
#                          retransmit the last frames after the token's DELETE has arrived)
CHORES_S = 0.02          # how often the aggregator checks presence, conceals silent devices and the end
DEFAULT_PORT = 7447


class NetworkError(AdhocArrayError, RuntimeError):
    """A Zenoh session cannot be opened or a network option is invalid."""


# keys ------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Keys:
    """The key expressions of one array."""

    array: str = "default"

    def __post_init__(self) -> None:
        if not self.array or any(c in self.array for c in "/*$?#"):
            raise ConfigError(f"--array '{self.array}' must be a non-empty name without '/', '*', '$', '?', '#'.")

    def _k(self, tail: str) -> str:
        return f"{PREFIX}/{self.array}/{tail}"

    def audio(self, name: str = "*") -> str:
        return self._k(f"dev/{name}/audio")

    def info(self, name: str = "*") -> str:
        return self._k(f"dev/{name}/info")

    def alive(self, name: str = "*") -> str:
        return self._k(f"alive/{name}")

    def out(self, what: str) -> str:
        return self._k(f"out/{what}")

    @property
    def aggregator_alive(self) -> str:
        return self._k("aggregator/alive")

    @staticmethod
    def device_of(key: str) -> str:
        """NAME of ``adhoc/ARRAY/dev/NAME/audio`` or ``adhoc/ARRAY/alive/NAME``."""
        parts = str(key).split("/")
        if len(parts) >= 5 and parts[2] == "dev":
            return parts[3]
        return parts[-1]


def check_name(name: str) -> str:
    if not name or any(c in name for c in "/*$?# "):
        raise ConfigError(f"Device name '{name}' must be non-empty, without '/', '*', '$', '?', '#' or spaces.")
    return name


# sessions --------------------------------------------------------------------------------------------------
@dataclass
class NetOptions:
    """How a command reaches the others: the ``--connect``, ``--listen``, ``--zenoh-config`` options.

    Attributes
    ----------
    mode : str
        "peer" (default; on a LAN the peers find each other by multicast scouting), "client" (through a
        router) or "router".
    connect, listen : sequence of str
        Zenoh endpoints (``tcp/HOST:PORT``, ``tls/HOST:PORT``, ``unixsock-stream/PATH``).
    config_file : path, optional
        A Zenoh JSON5 configuration passed to Zenoh unchanged (TLS, user/password, access control); the
        options above are applied on top only when given.
    scouting : bool
        Multicast scouting; off with ``--no-scouting`` (tests, networks without multicast).
    shared_memory : bool
        Zenoh's shared-memory transport; off unless asked (``../ENV.md``: no faster for audio, multi-ms tails).
    lease_ms : int, optional
        Link lease: how soon a frozen peer is declared gone (Zenoh's default is 10 s).
    """

    mode: str = "peer"
    connect: Sequence[str] = ()
    listen: Sequence[str] = ()
    config_file: str | None = None
    scouting: bool = True
    shared_memory: bool = False
    lease_ms: int | None = 2000

    def config(self):
        import zenoh
        if self.mode not in ("peer", "client", "router"):
            raise ConfigError(f"Zenoh mode '{self.mode}' must be peer, client or router.")
        if self.config_file:
            path = Path(self.config_file)
            if not path.is_file():
                raise ConfigError(f"--zenoh-config {path} does not exist.")
            try:
                cfg = zenoh.Config.from_file(str(path))
            except Exception as err:  # noqa: BLE001 - ZError: one sentence
                raise ConfigError(f"--zenoh-config {path} is not a valid Zenoh configuration ({err}).") from None
        else:
            cfg = zenoh.Config()
            cfg.insert_json5("transport/shared_memory/enabled", json.dumps(bool(self.shared_memory)))
            if self.lease_ms:
                cfg.insert_json5("transport/link/tx/lease", str(int(self.lease_ms)))
            # reconnect within a second (Zenoh's default backs off to 4 s: a device or router restart would
            # cost that much audio)
            cfg.insert_json5("connect/retry", '{"period_init_ms": 250, "period_max_ms": 1000, '
                                              '"period_increase_factor": 2}')
        if not self.config_file or self.mode != "peer":
            cfg.insert_json5("mode", json.dumps(self.mode))
        try:
            if self.connect:
                cfg.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
            if self.listen:
                cfg.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        except Exception as err:  # noqa: BLE001
            raise ConfigError(f"Invalid Zenoh endpoint in {list(self.connect) + list(self.listen)} ({err}).") from None
        if not self.scouting:
            cfg.insert_json5("scouting/multicast/enabled", "false")
        return cfg

    def open(self):
        """An open Zenoh session, or a one-sentence :class:`NetworkError`."""
        import zenoh
        cfg = self.config()
        try:
            return zenoh.open(cfg)
        except Exception as err:  # noqa: BLE001 - zenoh.ZError
            where = ", ".join(list(self.connect) + list(self.listen)) or "the default endpoints"
            hint = (" (with TLS: the device's certificate must be signed by the router's CA, and enable_mtls set "
                    "on both sides)" if "tls/" in where or self.config_file else "")
            raise NetworkError(f"Could not open a Zenoh {self.mode} session on {where} ({_zenoh_text(err)}){hint}.") \
                from None


def _zenoh_text(err: BaseException) -> str:
    """Zenoh's error message without its Rust source location."""
    return re.sub(r"\s+at /\S+", "", str(err)).strip().rstrip(".")


def quiet_zenoh() -> None:
    """Zenoh's own log at error level unless RUST_LOG says otherwise (its info lines would flood stderr)."""
    import zenoh
    try:
        zenoh.init_log_from_env_or("error")
    except Exception:  # noqa: BLE001 - already initialised
        pass


# device agent ----------------------------------------------------------------------------------------------
@dataclass
class AgentCounters:
    n_frames: int = 0
    n_samples: int = 0
    n_bytes: int = 0
    n_put_errors: int = 0


def run_device(name: str, source, net: NetOptions, *, array: str = "default", sample_format: str = "int16",
               gain: float = 1.0, describe: str = "", on_frame: Callable[[Frame], None] | None = None,
               wait_aggregator_s: float = 0.0, handle_signals: bool = True) -> AgentCounters:
    """Stream one device to the array until its source ends or a signal stops it.

    Parameters
    ----------
    name : str
        The device's name (its key).
    source : Source
        Not yet opened; its first active device is sent (a card, or a file replayed at real time).
    sample_format : str
        "int16" (half the bytes) or "float32".
    gain : float
        Multiplies the samples before they are sent (reported in the device's facts).
    wait_aggregator_s : float
        Before the source starts, wait up to this long for an aggregator of the array (its liveliness token):
        a recording replayed as a live device then loses nothing. 0: start at once.
    """
    check_name(name)
    keys = Keys(array)
    if sample_format not in wire.FORMATS:
        raise ConfigError(f"--format '{sample_format}' must be int16 or float32.")
    counters = AgentCounters()
    instance = secrets.randbits(63)
    session = net.open()
    stopped: list[str] = []
    restore = _install_stop_handlers(source, stopped) if handle_signals else (lambda: None)
    facts: dict[str, Any] = {"name": name, "instance": instance, "software": f"adhoc-array {_version()}",
                             "gain": gain, "sample_format": sample_format, "input": describe}
    try:
        if wait_aggregator_s > 0 and not _wait_for_token(session, keys.aggregator_alive, wait_aggregator_s):
            log.warning("Device '%s': no aggregator of array '%s' appeared within %g s; streaming anyway.", name,
                        array, wait_aggregator_s)
        with source as src:
            if not src.active:
                raise AdhocArrayError(f"Device '{name}': its input could not be opened "
                                      f"({'; '.join(p for d in src.devices for p in d.problems) or 'no input'}).")
            dev = src.active[0]
            facts.update(sample_rate_hz=dev.sample_rate_hz, n_channels=getattr(dev, "n_file_channels", 0) or
                         len(getattr(dev, "channels", []) or [1]))

            def reply(query) -> None:
                query.reply(keys.info(name), json.dumps(facts))

            queryable = session.declare_queryable(keys.info(name), reply)
            import zenoh
            pub = session.declare_publisher(keys.audio(name), reliability=zenoh.Reliability.RELIABLE,
                                            congestion_control=zenoh.CongestionControl.BLOCK)
            token = session.liveliness().declare_token(keys.alive(name))
            seq = 0
            try:
                for frame in src:
                    if frame.device_id != 0:
                        continue
                    if on_frame is not None:
                        on_frame(frame)
                    x = frame.samples if gain == 1.0 else frame.samples * np.float32(gain)
                    if len(x) == 0 and not frame.flags & FrameFlag.LAST:
                        continue
                    payload = wire.encode(x, seq=seq, first_sample=frame.first_sample,
                                          sample_rate_hz=frame.sample_rate_hz, instance=instance,
                                          capture_time_ns=time.time_ns(), flags=int(frame.flags),
                                          sample_format=sample_format)
                    try:
                        pub.put(payload)
                    except Exception as err:  # noqa: BLE001 - counted; the next frame tries again
                        counters.n_put_errors += 1
                        if counters.n_put_errors == 1:
                            log.warning("Device '%s': a frame could not be sent (%s); the stream goes on.", name, err)
                    seq += 1
                    counters.n_frames += 1
                    counters.n_samples += len(x)
                    counters.n_bytes += len(payload)
                    if frame.flags & FrameFlag.LAST:
                        break
            finally:
                time.sleep(0.05)      # let the last frames leave before the token goes
                token.undeclare()
                pub.undeclare()
                queryable.undeclare()
    finally:
        restore()
        session.close()
    if stopped:
        log.info("Device '%s' stopped by %s after %d frames.", name, " and ".join(stopped), counters.n_frames)
    return counters


@dataclass
class _EventStop:
    """What a signal stops when the loop is a wait on an event (``listen``, ``router``)."""

    event: threading.Event

    def stop(self) -> None:
        self.event.set()


def _wait_for_token(session, key: str, timeout_s: float) -> bool:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        try:
            if any(r.ok is not None for r in session.liveliness().get(key, timeout=0.5)):
                return True
        except Exception:  # noqa: BLE001 - no route yet
            pass
        time.sleep(0.05)
    return False


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("adhoc-array")
    except PackageNotFoundError:
        return "unknown"


# jitter buffer ---------------------------------------------------------------------------------------------
@dataclass
class NetCounters:
    """What the network did to one device's frames (in report.json under ``network``)."""

    n_frames: int = 0
    n_reordered: int = 0
    n_duplicates: int = 0
    n_lost_frames: int = 0            # sequence numbers never received (their samples are concealed)
    n_late_frames: int = 0            # arrived after their place was concealed: dropped
    n_overrun_frames: int = 0         # dropped because the engine fell buffer_s behind
    n_concealed_samples: int = 0
    n_restarts: int = 0               # the sender came back with a new instance (sequence from 0)
    n_malformed: int = 0
    n_departures: int = 0
    start_sample: int = -1            # where the device's first sample was placed on its engine-side clock


class _Reservoir:
    """A uniform sample of at most ``size`` values of a whole run (Vitter's algorithm R)."""

    def __init__(self, size: int = 20000, seed: int = 0) -> None:
        self._v = np.empty(size)
        self.n = 0
        self.recent = float("nan")     # exponential average of the latest values (a status line's figure)
        self._rng = np.random.default_rng(seed)

    def add(self, value: float) -> None:
        self.recent = value if self.n == 0 else 0.9 * self.recent + 0.1 * value
        if self.n < len(self._v):
            self._v[self.n] = value
        else:
            j = int(self._rng.integers(0, self.n + 1))
            if j < len(self._v):
                self._v[j] = value
        self.n += 1

    def values(self) -> np.ndarray:
        return self._v[:min(self.n, len(self._v))].copy()


class JitterBuffer:
    """Reorders one device's frames by sequence number and releases them after at most ``latency_s``.

    A missing sequence number is waited for until the frame after it has waited ``latency_s``; then it is
    declared lost (its samples are concealed downstream from the jump in ``first_sample``). A new sender
    instance (the device restarted: sequence numbers from 0, a new clock) is released after everything of the
    old one. At most ``capacity`` frames wait; beyond that the oldest are released at once.
    """

    def __init__(self, *, latency_s: float = 0.1, capacity: int = 1000) -> None:
        self.latency_s = float(latency_s)
        self.capacity = int(capacity)
        self.counters = NetCounters()
        self._waiting: dict[tuple[int, int], tuple[float, wire.WireFrame]] = {}
        self._instances: list[int] = []      # in order of appearance; [0] is being released
        self._next_seq: dict[int, int] = {}

    def __len__(self) -> int:
        return len(self._waiting)

    def push(self, frame: wire.WireFrame, arrival_s: float) -> None:
        c = self.counters
        c.n_frames += 1
        inst = frame.instance
        if inst not in self._next_seq:
            if self._instances:
                c.n_restarts += 1
            self._instances.append(inst)
            self._next_seq[inst] = frame.seq   # the first frame heard of an instance starts it
        key = (inst, frame.seq)
        if frame.seq < self._next_seq[inst] or key in self._waiting:
            c.n_duplicates += 1          # received twice, or after it was released or declared lost
            return
        if any(i == inst and s > frame.seq for (i, s) in self._waiting):
            c.n_reordered += 1
        self._waiting[key] = (arrival_s, frame)

    def pop_ready(self, now_s: float) -> list[wire.WireFrame]:
        """Frames to hand on, in order: the next expected ones, and past a hole that waited too long."""
        out: list[wire.WireFrame] = []
        c = self.counters
        while self._instances:
            inst = self._instances[0]
            nxt = self._next_seq[inst]
            item = self._waiting.pop((inst, nxt), None)
            if item is not None:
                out.append(item[1])
                self._next_seq[inst] = nxt + 1
                continue
            mine = [s for (i, s) in self._waiting if i == inst]
            if mine:
                first = min(mine)
                arrival = self._waiting[(inst, first)][0]
                if now_s - arrival >= self.latency_s or len(self._waiting) > self.capacity:
                    c.n_lost_frames += first - nxt
                    self._next_seq[inst] = first
                    continue
                break
            if len(self._instances) > 1:        # the old instance is done: the next one is released
                self._instances.pop(0)
                continue
            break
        return out


# the aggregator's source -----------------------------------------------------------------------------------
@dataclass
class NetDevice(DeviceInfo):
    """A device of the array, as the aggregator sees it."""

    key: str = ""
    instance: int = 0
    present: bool = False
    facts: dict = field(default_factory=dict)
    spare: bool = False          # a free slot (``--spare``) that no late device has taken yet
    joined_late: bool = False    # a device that took a spare slot


@dataclass
class _Lane:
    """One device's state in the aggregator: jitter buffer, its position on the device clock the engine sees."""

    buffer: JitterBuffer
    pos: int = 0                       # next sample index handed to the engine (engine-side device clock)
    base: dict = field(default_factory=dict)      # instance -> engine-side index of its first_sample 0
    started: bool = False
    ended: bool = False
    last_arrival_s: float = 0.0
    gone_since_s: float | None = None  # monotonic time its liveliness token went (None: present)
    said_last: bool = False            # its sender ended its stream cleanly (a LAST frame)
    seq: int = 0
    leaving_since_s: float | None = None   # its token went without a LAST frame yet (see DEPARTURE_GRACE_S)


class NetSource:
    """The aggregator's :class:`~stream.messages.Source`: every device of the array, over Zenoh.

    Parameters
    ----------
    net : NetOptions
    array : str
    expect : sequence of str, optional
        Device names that form the array, in order (the first is the reference); the stream starts once
        they are all present or ``discover_s`` has passed. Without it: every device present after
        ``discover_s`` (at least one), by name. When the first is not present at the start, the first expected
        device that is becomes the reference (one sentence in the log and the report), so that the outputs never
        wait for it.
    discover_s : float
        Longest wait for devices before the stream starts.
    jitter_s : float
        How long a missing frame is waited for before its samples are concealed.
    hold_s : float
        A device that delivers nothing for this long (it left, or has not joined yet) is concealed with
        flagged zeros so that it never stalls the others.
    buffer_s : float
        Bound of each device's frames waiting for the engine, in seconds of audio (backpressure: the oldest are
        dropped).
    until_done : bool
        End when every device has ended its stream (a LAST frame) or has been gone for ``gone_done_s`` (a router
        restart makes every device leave for a moment); otherwise only ``stop()`` ends.
    max_duration_s : float, optional
        End after the reference has delivered this much audio.
    spare : int
        Free slots (``spare1``, ...) for devices that join after the stream started without being in ``expect``:
        the first such device at the slot's rate takes it (renamed, one sentence) and joins like any late
        device (concealed until then, aligned by the next re-check of the offsets). Each slot costs what a
        device costs. Without one, such a device is left out, with one sentence.
    """

    live = True
    paced = True

    def __init__(self, net: NetOptions, *, array: str = "default", expect: Sequence[str] = (),
                 discover_s: float = 5.0, jitter_s: float = 0.1, hold_s: float = 0.5, buffer_s: float = 10.0,
                 until_done: bool = False, max_duration_s: float | None = None, session=None,
                 spare: int = 0) -> None:
        if int(spare) != spare or spare < 0:
            raise ConfigError(f"{spare=} must be a whole number of slots >= 0")
        self.spare = int(spare)
        self.net = net
        self.keys = Keys(array)
        self.expect = [check_name(n) for n in expect]
        self.discover_s = float(discover_s)
        self.jitter_s = float(jitter_s)
        self.hold_s = float(hold_s)
        self.buffer_s = float(buffer_s)
        self.until_done = until_done
        self.gone_done_s = 5.0
        self.max_duration_s = max_duration_s
        self.devices: list[NetDevice] = []
        self.active: list[NetDevice] = []
        self._session = session
        self._own_session = session is None
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._inbox: dict[str, collections.deque] = {}
        self._inbox_samples: dict[str, int] = {}
        self._overrun: dict[str, int] = {}
        self._latencies: dict[str, _Reservoir] = {}
        self._present: dict[str, bool] = {}
        self._presence_changed = True
        self._malformed: dict[str, int] = {}
        self._malformed_said: set[str] = set()
        self._strangers: set[str] = set()
        self._lanes: list[_Lane] = []
        self._stop = False
        self._subs: list = []
        self.t_start_s = 0.0
        self.network_report: dict[str, Any] = {}

    # Source protocol ---------------------------------------------------------------------------------------
    @property
    def sample_rates_hz(self) -> list[float]:
        return [d.sample_rate_hz for d in self.active]

    @property
    def duration_s(self) -> None:
        return None

    def stop(self) -> None:
        self._stop = True
        self._wake.set()

    def __enter__(self) -> "NetSource":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def open(self) -> None:
        if self._session is None:
            self._session = self.net.open()
        s = self._session
        self._subs.append(s.liveliness().declare_subscriber(self.keys.alive(), self._on_alive, history=True))
        self._subs.append(s.declare_subscriber(self.keys.audio(), self._on_audio))
        self._subs.append(s.liveliness().declare_token(self.keys.aggregator_alive))
        self._discover()

    def close(self) -> None:
        for sub in self._subs:
            try:
                sub.undeclare()
            except Exception:  # noqa: BLE001 - closing: the session goes anyway
                pass
        self._subs = []
        if self._session is not None and self._own_session:
            self._session.close()
        self._session = None

    def _latency(self, name: str) -> "_Reservoir":
        r = self._latencies.get(name)
        if r is None:
            r = self._latencies[name] = _Reservoir()
        return r

    # zenoh callbacks (zenoh's threads: record and wake only) ---------------------------------------------
    def _on_alive(self, sample) -> None:
        import zenoh
        name = Keys.device_of(str(sample.key_expr))
        with self._lock:
            self._present[name] = sample.kind == zenoh.SampleKind.PUT
            self._presence_changed = True
        self._wake.set()

    def _on_audio(self, sample) -> None:
        key = str(sample.key_expr)
        name = Keys.device_of(key)
        try:
            frame = wire.decode(sample.payload.to_bytes())
        except wire.MalformedFrame as err:
            with self._lock:
                self._malformed[key] = self._malformed.get(key, 0) + 1
                first = key not in self._malformed_said
                self._malformed_said.add(key)
            if first:
                log.warning("A malformed frame from '%s' was rejected (%s); further ones from it are counted.",
                            key, err)
            return
        now_ns = time.time_ns()
        with self._lock:
            if frame.capture_time_ns:
                self._latency(name).add((now_ns - frame.capture_time_ns) / 1e6)
            box = self._inbox.get(name)
            if box is None:
                box = self._inbox[name] = collections.deque()
                self._inbox_samples[name] = 0
            box.append((time.monotonic(), frame))
            self._inbox_samples[name] += frame.n_samples
            # backpressure: an engine buffer_s behind loses the oldest frames of the device (concealed as a gap)
            while self._inbox_samples[name] > self.buffer_s * frame.sample_rate_hz and len(box) > 1:
                _, old = box.popleft()
                self._inbox_samples[name] -= old.n_samples
                self._overrun[name] = self._overrun.get(name, 0) + 1
        self._wake.set()

    # discovery ----------------------------------------------------------------------------------------------
    def _discover(self) -> None:
        t_end = time.monotonic() + self.discover_s
        present: list[str] = []
        while not self._stop:
            with self._lock:
                present = sorted(n for n, p in self._present.items() if p)
            if self.expect and all(n in present for n in self.expect):
                break
            if time.monotonic() >= t_end:
                break
            self._wake.wait(0.05)
            self._wake.clear()
        names = list(self.expect) if self.expect else present
        log.info("Discovery ended after %.1f s: %s present.", time.monotonic() - t_end + self.discover_s,
                 ", ".join(present) or "no device")
        if self.expect and names[0] not in present and any(n in present for n in names):
            # the reference is the clock every output is on: one that is not there would hold every output back
            # until it comes; the first expected device that is there takes its place
            first = next(n for n in names if n in present)
            names.remove(first)
            names.insert(0, first)
            log.warning("The reference device '%s' was not present when the stream started; '%s' is the reference "
                        "instead, and '%s' joins like any late device.", self.expect[0], first, self.expect[0])
        for name in names:
            dev = NetDevice(name=name, path=f"zenoh:{self.keys.audio(name)}", key=self.keys.audio(name))
            self.devices.append(dev)
        for k in range(self.spare):
            name = next(f"spare{j}" for j in itertools.count(k + 1) if f"spare{j}" not in names)
            self.devices.append(NetDevice(name=name, path="zenoh:(a free slot)", spare=True))
        facts = self._query_facts(names)
        for dev in self.devices:
            f = facts.get(dev.name)
            if dev.spare:
                log.info("Slot '%s' is free for a device that joins late.", dev.name)
            elif f is None:
                # not there yet: its rate comes from the expected devices that are, or its first frame
                dev.problem(f"Device '{dev.name}' is not present yet; it is concealed until it joins.")
            else:
                dev.facts = f
                dev.sample_rate_hz = float(f.get("sample_rate_hz", float("nan")))
                dev.n_file_channels = int(f.get("n_channels", 1))
                dev.present = True
        known = [d.sample_rate_hz for d in self.devices if np.isfinite(d.sample_rate_hz)]
        if not known:
            where = ", ".join(list(self.net.connect) + list(self.net.listen)) or "the local network (scouting)"
            raise NetworkError(f"No device of array '{self.keys.array}' was found on {where} within "
                               f"{self.discover_s:g} s; start one with: adhoc-array device --name NAME --input ...")
        for dev in self.devices:
            if not np.isfinite(dev.sample_rate_hz):
                if known:
                    dev.sample_rate_hz = known[0]
                else:
                    dev.usable = False
        self.active = [d for d in self.devices if d.usable]
        for dev in self.active:
            cap = max(8, int(self.buffer_s * dev.sample_rate_hz / 256))
            self._lanes.append(_Lane(JitterBuffer(latency_s=self.jitter_s, capacity=cap)))

    def _query_facts(self, names: Sequence[str]) -> dict[str, dict]:
        facts: dict[str, dict] = {}
        if not names:
            return facts
        try:
            for reply in self._session.get(self.keys.info(), timeout=2.0):
                if reply.ok is None:
                    continue
                try:
                    f = json.loads(reply.ok.payload.to_bytes())
                except ValueError:
                    continue
                name = Keys.device_of(str(reply.ok.key_expr))
                if name in names:
                    facts[name] = f
        except Exception as err:  # noqa: BLE001 - the facts also come with the frames
            log.warning("The device facts could not be queried (%s); rates are taken from the frames.", err)
        return facts

    # iteration ----------------------------------------------------------------------------------------------
    def __iter__(self) -> Iterator[Frame]:
        self.t_start_s = time.monotonic()
        index = {d.name: k for k, d in enumerate(self.active)}
        next_chores = 0.0            # presence, concealment and the end are checked every CHORES_S
        while True:
            if self._stop:
                break
            now = time.monotonic()
            with self._lock:
                inbox = {n: list(q) for n, q in self._inbox.items() if q}
                for n in inbox:
                    self._inbox[n].clear()
                    self._inbox_samples[n] = 0
                present = dict(self._present) if self._presence_changed or now >= next_chores else None
                self._presence_changed = False
            for name, items in inbox.items():
                k = index.get(name)
                if k is None and name not in self._strangers:
                    k = self._claim(name, items[0][1], index)
                if k is None:
                    if name not in self._strangers:
                        self._strangers.add(name)
                        log.warning("Device '%s' streams to array '%s' but joined after the stream started; it "
                                    "is not part of this run (name it in --expect, or keep a free slot with --spare, "
                                    "to include it).", name, self.keys.array)
                    continue
                lane = self._lanes[k]
                for arrival, frame in items:
                    lane.buffer.push(frame, arrival)
                    lane.last_arrival_s = arrival
                    lane.said_last |= bool(frame.flags & FrameFlag.LAST)   # before its token's DELETE is read
            for name, k in (index.items() if present is not None else ()):
                dev, lane = self.active[k], self._lanes[k]
                was = dev.present
                dev.present = present.get(name, False)
                if dev.present:
                    lane.gone_since_s = None
                elif lane.gone_since_s is None:
                    lane.gone_since_s = now
                if was and not dev.present:
                    lane.leaving_since_s = now     # ended cleanly or left: its LAST frame decides (below)
                if lane.leaving_since_s is not None:
                    if lane.said_last:
                        lane.leaving_since_s = None
                        log.info("Device '%s' ended its stream after %.1f s.", name, lane.pos / dev.sample_rate_hz)
                    elif dev.present or now - lane.leaving_since_s >= DEPARTURE_GRACE_S:
                        lane.leaving_since_s = None
                        lane.buffer.counters.n_departures += 1
                        dev.problem(f"Device '{name}' left the array after {lane.pos / dev.sample_rate_hz:.1f} s; "
                                    "it is concealed until it comes back.")
                if dev.present and not was and lane.started:
                    lane.said_last = False
                    log.info("Device '%s' is back.", name)
            # frames released by the jitter buffers, placed on each device's engine-side clock
            progress = max((ln.pos / d.sample_rate_hz for ln, d in zip(self._lanes, self.active)), default=0.0)
            for k, (dev, lane) in enumerate(zip(self.active, self._lanes)):
                if len(lane.buffer):
                    for f in lane.buffer.pop_ready(now):
                        yield from self._place(k, dev, lane, f, progress)
            if now < next_chores:
                self._wake.wait(CHORES_S)
                self._wake.clear()
                continue
            next_chores = now + CHORES_S
            # devices that deliver nothing for hold_s: flagged zeros keep them in step with the others
            progress = max((ln.pos / d.sample_rate_hz for ln, d in zip(self._lanes, self.active)), default=0.0)
            for k, (dev, lane) in enumerate(zip(self.active, self._lanes)):
                lag_s = progress - lane.pos / dev.sample_rate_hz
                quiet_s = now - lane.last_arrival_s if lane.started else now - self.t_start_s
                if lane.ended or len(lane.buffer) or lag_s <= self.hold_s or quiet_s <= self.hold_s:
                    continue
                n = int((lag_s - self.hold_s / 2) * dev.sample_rate_hz)
                lane.buffer.counters.n_concealed_samples += max(n, 0)
                yield from self._zeros(k, dev, lane, n)
            if self.max_duration_s is not None and self.active and \
                    self._lanes[0].pos / self.active[0].sample_rate_hz >= self.max_duration_s:
                break
            if self.until_done and all(ln.ended or (not len(ln.buffer) and ln.gone_since_s is not None and
                                                    now - ln.gone_since_s > self.gone_done_s)
                                       for ln in self._lanes):
                break
            self._wake.wait(CHORES_S)
            self._wake.clear()
        for k, (dev, lane) in enumerate(zip(self.active, self._lanes)):
            if not lane.ended:
                lane.ended = True
                yield Frame(k, lane.seq, lane.pos, dev.sample_rate_hz, np.zeros(0, np.float32), FrameFlag.LAST)
        self.network_report = self.report()

    def _claim(self, name: str, frame: wire.WireFrame, index: dict[str, int]) -> int | None:
        """A free spare slot at the frame's rate for the late device ``name`` (renamed to it), or None."""
        free = [k for k, d in enumerate(self.active) if d.spare]
        if not free:
            return None
        k = next((k for k in free if abs(self.active[k].sample_rate_hz - frame.sample_rate_hz) < 1e-6), None)
        if k is None:
            self._strangers.add(name)
            log.warning("Device '%s' joined after the stream started at %g Hz; the free slots run at %g Hz, so it is "
                        "not part of this run.", name, frame.sample_rate_hz, self.active[free[0]].sample_rate_hz)
            return None
        dev = self.active[k]
        slot = dev.name
        del index[slot]
        index[name] = k
        dev.name, dev.key, dev.path = name, self.keys.audio(name), f"zenoh:{self.keys.audio(name)}"
        dev.spare, dev.joined_late = False, True
        dev.n_file_channels = int(frame.samples.shape[1])
        with self._lock:
            self._presence_changed = True
        dev.problem(f"Device '{name}' joined after the stream started; it streams in the free slot '{slot}' (its "
                    "column in toa.csv) from its first frame.")
        return k

    def _place(self, k: int, dev: NetDevice, lane: _Lane, f: wire.WireFrame, progress_s: float) -> Iterator[Frame]:
        c = lane.buffer.counters
        if lane.ended:
            return
        if f.sample_rate_hz != dev.sample_rate_hz:
            c.n_malformed += 1
            if c.n_malformed == 1:
                dev.problem(f"Device '{dev.name}' sent {f.sample_rate_hz:g} Hz frames where the stream runs it at "
                            f"{dev.sample_rate_hz:g} Hz; they are dropped.")
            return
        if f.instance not in lane.base:
            # a device's first frame, or its first after a restart (a new clock): placed where the others are
            # now (the arrival; the aligner then finds the exact offset on the audio)
            others = any(ln.started for j, ln in enumerate(self._lanes) if j != k)
            start = max(lane.pos, int(round(progress_s * dev.sample_rate_hz))) if others else lane.pos
            lane.base[f.instance] = start - f.first_sample
            if not lane.started:
                c.start_sample = start
            lane.started = True
        first = lane.base[f.instance] + f.first_sample
        restarted = f.instance != dev.instance
        if restarted:
            dev.instance = f.instance
        if first > lane.pos and c.start_sample == first:
            # the lead before a device's first sample (it started, or was first heard, after the others): flagged
            # zeros, not a loss
            yield from self._zeros(k, dev, lane, first - lane.pos)
        x = f.samples
        if first < lane.pos:                      # its place was concealed already: the late part is dropped
            cut = min(lane.pos - first, len(x))
            c.n_late_frames += cut == len(x)
            x = x[cut:]
            first += cut
        last = bool(f.flags & FrameFlag.LAST)
        if len(x) or last:
            flags = FrameFlag(f.flags) & ~FrameFlag.LAST
            if last and not self.until_done:   # a device that ends cleanly may come back: it stays, concealed
                last = False
            if first > lane.pos:
                c.n_concealed_samples += first - lane.pos
            if restarted and c.start_sample != first:       # not its first clock: a new one
                flags |= FrameFlag.NEW_CLOCK
            yield Frame(k, lane.seq, first, dev.sample_rate_hz, x, flags | (FrameFlag.LAST if last else 0))
            lane.seq += 1
            lane.pos = first + len(x)
            if last:
                lane.ended = True

    @staticmethod
    def _zeros(k: int, dev: NetDevice, lane: _Lane, n: int) -> Iterator[Frame]:
        """``n`` flagged zeros for device ``k`` (at most 0.1 s per frame)."""
        while n > 0:
            m = min(n, int(0.1 * dev.sample_rate_hz))
            yield Frame(k, lane.seq, lane.pos, dev.sample_rate_hz, np.zeros(m, np.float32), FrameFlag.GAP)
            lane.seq += 1
            lane.pos += m
            n -= m

    def report(self) -> dict[str, Any]:
        """Per-device network counters and one-way latency (capture to arrival) percentiles."""
        out: dict[str, Any] = {"array": self.keys.array, "devices": {}, "malformed": dict(self._malformed),
                               "strangers": sorted(self._strangers)}
        for dev, lane in zip(self.active, self._lanes):
            c = lane.buffer.counters
            c.n_overrun_frames = self._overrun.get(dev.name, 0)
            with self._lock:
                lat = self._latency(dev.name).values()
            d = dict(vars(c))
            if len(lat):     # capture (the sender's clock) to arrival: the network's one-way latency
                d["latency_ms"] = {"p50": float(np.percentile(lat, 50)), "p99": float(np.percentile(lat, 99)),
                                   "max": float(lat.max())}
            if dev.joined_late or dev.spare:
                d["slot"] = "taken by a device that joined late" if dev.joined_late else "free"
            out["devices"][dev.name] = d
        return out


# the aggregator's outputs on the network -------------------------------------------------------------------
class NetPublisher:
    """A hop sink publishing the enhanced audio (wire frames of ``frame_hops`` hops) and the TOA estimates."""

    def __init__(self, session, keys: Keys, *, sample_rate_hz: float, device_names: Sequence[str],
                 frame_hops: int = 4) -> None:
        import zenoh
        self.keys = keys
        self.rate = float(sample_rate_hz)
        self.names = list(device_names)
        self.frame_hops = frame_hops
        self._audio = session.declare_publisher(keys.out("enhanced"), congestion_control=zenoh.CongestionControl.DROP)
        self._toa = session.declare_publisher(keys.out("toa"), congestion_control=zenoh.CongestionControl.DROP)
        self._geometry = session.declare_publisher(keys.out("geometry"))
        self._pending: list[np.ndarray] = []
        self._first = 0
        self._seq = 0
        self._instance = secrets.randbits(63)

    def write(self, result: HopResult) -> None:
        self._pending.append(result.enhanced)
        if len(self._pending) >= self.frame_hops:
            self._flush()
        t = result.toa
        if t is not None:
            self._toa.put(json.dumps({"time_s": round(t.time_s, 6), "toa_s": [float(v) for v in t.toa_s],
                                      "gated": bool(t.gated), "track_id": t.track_id, "devices": self.names}))

    def geometry(self, geometry) -> None:
        """Publish a calibrated geometry (:meth:`estimators.geometry.Geometry.to_json`)."""
        try:
            self._geometry.put(geometry.to_json())
        except Exception as err:  # noqa: BLE001 - publishing must not stop the stream
            log.warning("The geometry could not be published (%s).", err)

    def _flush(self, last: bool = False) -> None:
        x = np.concatenate(self._pending) if self._pending else np.zeros(1 if last else 0, np.float32)
        self._pending = []
        if len(x) == 0:
            return
        self._audio.put(wire.encode(x, seq=self._seq, first_sample=self._first, sample_rate_hz=self.rate,
                                    instance=self._instance, capture_time_ns=time.time_ns(),
                                    flags=int(FrameFlag.LAST) if last else 0, sample_format="float32"))
        self._seq += 1
        self._first += len(x)

    def close(self) -> None:
        self._flush(last=True)
        for p in (self._audio, self._toa, self._geometry):
            p.undeclare()


# listen ----------------------------------------------------------------------------------------------------
def listen(key: str, out: str | Path, net: NetOptions, *, max_duration_s: float | None = None,
           until_last: bool = True, wait_s: float | None = None) -> dict[str, Any]:
    """Record what is published on ``key``: wire frames into a WAV (gaps as zeros), anything else as lines.

    Returns a summary (frames, samples, gaps, malformed). Ends on a signal, after ``max_duration_s`` of
    audio, once a frame flagged LAST has come (``until_last``), or after ``wait_s`` with nothing received.
    """
    import soundfile as sf
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    session = net.open()
    q: collections.deque = collections.deque(maxlen=100_000)
    wake = threading.Event()

    def cb(sample) -> None:
        q.append(sample.payload.to_bytes())
        wake.set()

    stop: list[str] = []
    restore = _install_stop_handlers(_EventStop(wake), stop)
    summary = {"key": key, "out": str(out), "n_frames": 0, "n_samples": 0, "n_gaps": 0, "n_malformed": 0,
               "n_lines": 0}
    wav = None
    text = None
    pos = 0
    instance = None
    t_last = time.monotonic()
    sub = session.declare_subscriber(key, cb)
    try:
        while not stop:
            wake.wait(0.05)
            wake.clear()
            done = False
            while q:
                payload = q.popleft()
                t_last = time.monotonic()
                if payload[:4] == wire.MAGIC:
                    try:
                        f = wire.decode(payload)
                    except wire.MalformedFrame:
                        summary["n_malformed"] += 1
                        continue
                    if wav is None:
                        wav = sf.SoundFile(str(out), "w", samplerate=int(round(f.sample_rate_hz)),
                                           channels=f.samples.shape[1], subtype="FLOAT")
                        summary["sample_rate_hz"] = f.sample_rate_hz
                        instance, pos = f.instance, f.first_sample
                    if f.instance != instance:     # the publisher restarted: its clock restarts too
                        instance, pos = f.instance, f.first_sample
                    if f.first_sample > pos:
                        summary["n_gaps"] += 1
                        wav.write(np.zeros((f.first_sample - pos, wav.channels), np.float32))
                        pos = f.first_sample
                    x = f.samples[max(0, pos - f.first_sample):]
                    wav.write(x)
                    pos += len(x)
                    summary["n_frames"] += 1
                    summary["n_samples"] = pos
                    done = until_last and bool(f.flags & FrameFlag.LAST)
                else:
                    if text is None:
                        text = open(out, "w")
                    text.write(payload.decode(errors="replace").rstrip("\n") + "\n")
                    summary["n_lines"] += 1
                if max_duration_s is not None and wav is not None and pos >= max_duration_s * wav.samplerate:
                    done = True
            if done:
                break
            if wait_s is not None and time.monotonic() - t_last > wait_s:
                break
    finally:
        restore()
        sub.undeclare()
        session.close()
        if wav is not None:
            wav.close()
        if text is not None:
            text.close()
    return summary


def run_router(net: NetOptions, *, ready: Callable[[list[str]], None] | None = None) -> None:
    """A Zenoh router (zenoh-python's router mode) until SIGINT/SIGTERM; ``ready`` gets its locators."""
    import zenoh
    net = NetOptions(**{**vars(net), "mode": "router"})
    cfg = net.config()
    cfg.insert_json5("adminspace/enabled", "true")
    try:
        session = zenoh.open(cfg)
    except Exception as err:  # noqa: BLE001
        raise NetworkError(f"The router could not listen on {', '.join(net.listen) or 'the default port'} "
                           f"({_zenoh_text(err)}).") from None
    stopped: list[str] = []
    event = threading.Event()
    restore = _install_stop_handlers(_EventStop(event), stopped)
    try:
        locators = router_locators(session)
        if ready is not None:
            ready(locators)
        while not event.wait(0.2):
            pass
    finally:
        restore()
        session.close()


def router_locators(session) -> list[str]:
    """The endpoints a router (or peer) session actually listens on (port 0 resolved)."""
    for kind in ("router", "peer"):
        try:
            for reply in session.get(f"@/{session.zid()}/{kind}", timeout=1.0):
                if reply.ok is not None:
                    return list(json.loads(reply.ok.payload.to_bytes()).get("locators", []))
        except Exception:  # noqa: BLE001
            continue
    return []



# the aggregator --------------------------------------------------------------------------------------------
def _status_line():
    from .live import StatusLine

    class NetStatus(StatusLine):
        """The aggregator's status line: per device presence, frames lost and network latency; TOA, gating, CPU."""

        def text(self, pipeline) -> str:
            wall, cpu = time.perf_counter(), time.process_time()
            load = (cpu - self._t[1]) / max(wall - self._t[0], 1e-9)
            self._t = (wall, cpu)
            src = self.source
            ref = src._lanes[0] if src._lanes else None
            parts = [f"{(ref.pos if ref else 0) / src.active[0].sample_rate_hz:7.1f} s"]
            if not pipeline.aligner.ready:
                parts[0] += " (aligning the devices)"
            for dev, lane in zip(src.active, src._lanes):
                c = lane.buffer.counters
                state = "" if dev.present else " GONE"
                lat = src._latency(dev.name).recent
                parts.append(f"{dev.name}{state} {lat:.1f} ms" + (f" lost {c.n_lost_frames}" if c.n_lost_frames
                                                                   else ""))
            line = " | ".join(parts)
            bad = sum(src._malformed.values())
            if bad:
                line += f" | malformed {bad}"
            st = pipeline.state
            if len(st.toa_s):
                line += " | TOA ms " + " ".join(f"{1e3 * v:+.2f}" for v in st.toa_s[-1][1:])
            return line + f" | gated {pipeline.counters.n_gated} | CPU {100 * load:.0f}%"

    return NetStatus


def run_aggregate(out_dir: str | Path, net: NetOptions, *, array: str = "default", expect: Sequence[str] = (),
                  discover_s: float = 5.0, jitter_s: float = 0.1, hold_s: float = 0.5, until_done: bool = False,
                  max_duration_s: float | None = None, config=None,
                  overrides: Sequence[tuple[dict[str, Any], str]] = (), status: bool = True,
                  handle_signals: bool = True, spare: int = 0):
    """Run the engine on every device of ``array`` until stopped (or, with ``until_done``, until they end).

    Writes what ``replay`` writes into ``out_dir`` (report.json gains a ``network`` section), and publishes the
    enhanced audio, the TOA estimates and each calibrated geometry under ``adhoc/ARRAY/out/``.
    """
    from .config import EngineConfig, merge
    from .live import LIVE_DEFAULTS
    from .run import run_stream
    cfg = merge(config or EngineConfig(), LIVE_DEFAULTS, source="live defaults")
    for values, src in overrides:
        cfg = merge(cfg, values, source=src)
    keys = Keys(array)
    session = net.open()
    source = NetSource(net, array=array, expect=expect, discover_s=discover_s, jitter_s=jitter_s, hold_s=hold_s,
                       until_done=until_done, max_duration_s=max_duration_s, session=session, spare=spare)
    state: dict[str, Any] = {}

    class Publish:   # opened on the first hop, when the working rate is known
        def write(self, result: HopResult) -> None:
            if "pub" not in state:
                fs = cfg.working_rate_hz or source.active[0].sample_rate_hz
                state["pub"] = NetPublisher(session, keys, sample_rate_hz=fs,
                                            device_names=[d.name for d in source.active])
            state["pub"].write(result)

        def close(self) -> None:
            pass

    def on_geometry(geometry) -> None:
        if "pub" in state:
            state["pub"].geometry(geometry)

    def extra(report: dict) -> None:
        if "pub" in state:
            try:
                state["pub"].close()
            except Exception as err:  # noqa: BLE001 - closing must not lose the report
                log.warning("Closing the network outputs failed (%s).", err)
        report["network"] = source.network_report or source.report()
        if line is not None:
            line.close()

    line = _status_line()(source) if status else None
    try:
        outcome = run_stream(source, out_dir, config=cfg, extra_sinks=[Publish()], on_geometry=on_geometry,
                             extra_report=extra, handle_signals=handle_signals, status=line)
    finally:
        session.close()
    return outcome
