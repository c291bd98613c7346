"""Sound cards in and out: each ``--input`` card is a device of the ad-hoc array with its own clock.

The PortAudio callbacks only copy into preallocated ring buffers and count what went wrong (overflow,
underflow, a full ring): they never allocate arrays, log, or raise. The consumer loop (the stream
runner, in the main thread) reads the rings, stamps each frame with the index of its first sample in the
card's own clock, and flags the gaps. An exception raised in a callback is kept and re-raised in the
consumer loop as one sentence.

``import sounddevice`` fails where PortAudio is missing, so it is imported only here, on first use,
and the failure becomes one sentence that says what to install.

Input specs: ``NAME``, ``NAME:1,2`` (1-based channels of the card), or a PortAudio device index. A card
named by several specs (``system:1``, ``system:2``) is opened once, and each spec is a device with the
card's clock.
"""
from __future__ import annotations

import logging
import queue
import re
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Iterator, Sequence

import numpy as np

from .errors import AudioDeviceError
from .messages import Frame, FrameFlag
from .replay import DeviceInfo

log = logging.getLogger(__name__)

RING_S = 20.0        # seconds of audio each input ring holds (the consumer may fall this far behind)
MAX_GAPS = 4096      # gap records an input ring keeps before it counts them only


def import_sounddevice():
    """The ``sounddevice`` module, or an :class:`AudioDeviceError` that says what to install."""
    try:
        import sounddevice
    except OSError as err:   # PortAudio's shared library is missing
        raise AudioDeviceError(
            "Sound cards need the PortAudio library, which is not installed "
            f"({err}); install it with: sudo apt-get install libportaudio2") from None
    except ImportError as err:
        raise AudioDeviceError(f"Sound cards need the Python package sounddevice ({err}); "
                               "install it with: pip install sounddevice") from None
    return sounddevice


# device lookup ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class CardInfo:
    """One PortAudio device as the user sees it."""

    index: int
    name: str
    host_api: str
    max_input_channels: int
    max_output_channels: int
    default_rate_hz: float

    def describe(self) -> str:
        return (f"[{self.index}] {self.name} ({self.host_api}): {self.max_input_channels} in, "
                f"{self.max_output_channels} out, {self.default_rate_hz:g} Hz")


def list_cards() -> list[CardInfo]:
    """Every sound card PortAudio sees (empty when there is none)."""
    sd = import_sounddevice()
    apis = sd.query_hostapis()
    return [CardInfo(int(d["index"]), str(d["name"]), str(apis[d["hostapi"]]["name"]),
                     int(d["max_input_channels"]), int(d["max_output_channels"]),
                     float(d["default_samplerate"])) for d in sd.query_devices()]


def _available(cards: Sequence[CardInfo], kind: str) -> str:
    key = "max_input_channels" if kind == "input" else "max_output_channels"
    usable = [c.describe() for c in cards if getattr(c, key) > 0]
    return "; ".join(usable) if usable else "none (no sound card is visible to PortAudio)"


def find_card(name: str, cards: Sequence[CardInfo], *, kind: str = "input") -> CardInfo:
    """The card named by ``name``: an index, an exact name, or a unique part of a name (any case).

    Raises
    ------
    AudioDeviceError
        No card or several cards match; the message lists the cards that can do ``kind``.
    """
    key = "max_input_channels" if kind == "input" else "max_output_channels"
    usable = [c for c in cards if getattr(c, key) > 0]
    if name.strip().isdigit():
        for c in usable:
            if c.index == int(name):
                return c
    exact = [c for c in usable if c.name == name]
    if len(exact) == 1:
        return exact[0]
    part = [c for c in usable if name.lower() in c.name.lower()]
    if len(part) == 1:
        return part[0]
    if not part:
        raise AudioDeviceError(f"No {kind} sound card matches '{name}'; available: {_available(cards, kind)}.")
    raise AudioDeviceError(f"'{name}' matches several {kind} cards ({'; '.join(c.describe() for c in part)}); "
                           "give more of the name or the index.")


@dataclass(frozen=True)
class InputSpec:
    """One ``--input``: a card and the 1-based channels of it that make one device (empty: all)."""

    card: str
    channels: tuple[int, ...] = ()

    @classmethod
    def parse(cls, text: str, cards: Sequence[CardInfo] = ()) -> "InputSpec":
        """``NAME`` or ``NAME:1,2``. A name that itself contains ``:digits`` (ALSA's ``hw:1,0``) is taken
        whole when a card matches it whole."""
        m = re.fullmatch(r"(.+):(\d+(?:,\d+)*)", text.strip())
        if m is None:
            return cls(text.strip())
        whole = text.strip()
        if cards and any(whole.lower() in c.name.lower() for c in cards):
            return cls(whole)
        channels = tuple(int(v) for v in m.group(2).split(","))
        if any(c < 1 for c in channels):
            raise AudioDeviceError(f"--input '{text}': channels are numbered from 1.")
        return cls(m.group(1), channels)


# ring buffers ----------------------------------------------------------------------------------
class _Span:
    """When something went wrong on a card, in its own time: the sample clock of the first and the latest time
    (noted from the audio thread: two int stores)."""

    def __init__(self) -> None:
        self.first = -1     # -1: never
        self.last = -1

    def note(self, clock: int) -> None:
        if self.first < 0:
            self.first = clock
        self.last = clock

    def seconds(self, rate_hz: float) -> list[float] | None:
        """[first, latest] in seconds of the card's time (ms resolution), None if it never happened."""
        return None if self.first < 0 else [round(self.first / rate_hz, 3), round(self.last / rate_hz, 3)]


class _InputRing:
    """Single-producer (the PortAudio callback) single-consumer ring of frames of one card.

    The device clock ``n_clock`` counts every sample the card delivered, including those dropped because
    the ring was full; each drop is kept as a gap record ``(ring position, n_samples)`` so the consumer
    stamps the next frame with the right first sample and flags the gap.
    """

    def __init__(self, capacity_samples: int, n_channels: int) -> None:
        self.buf = np.zeros((capacity_samples, n_channels), np.float32)
        self.capacity = capacity_samples
        self.n_written = 0          # samples stored (ring position of the producer)
        self.n_read = 0             # samples consumed
        self.n_clock = 0            # samples the card delivered
        self.gap_at = np.zeros(MAX_GAPS, np.int64)
        self.gap_len = np.zeros(MAX_GAPS, np.int64)
        self.n_gaps = 0
        self.n_dropped = 0
        self.n_overflows = 0        # PortAudio's input-overflow flags (samples lost before us)
        self.overflows = _Span()    # n_clock at the first and the latest flag
        self.n_callbacks = 0
        self.last_callback_s = 0.0  # time.monotonic() of the newest callback

    def put(self, indata: np.ndarray, n: int) -> None:
        """Called in the audio thread: copy ``indata[:n]`` or, if the ring is full, record a gap."""
        w = self.n_written
        if w + n - self.n_read > self.capacity:
            if self.n_gaps < MAX_GAPS:
                self.gap_at[self.n_gaps] = w
                self.gap_len[self.n_gaps] = n
                self.n_gaps += 1
            self.n_dropped += n
        else:
            i = w % self.capacity
            k = min(n, self.capacity - i)
            self.buf[i:i + k] = indata[:k]
            if k < n:
                self.buf[:n - k] = indata[k:n]
            self.n_written = w + n
        self.n_clock += n


class _OutputRing:
    """Single-producer (the stream runner) single-consumer (the PortAudio callback) mono ring."""

    def __init__(self, capacity_samples: int) -> None:
        self.buf = np.zeros(capacity_samples, np.float32)
        self.capacity = capacity_samples
        self.n_written = 0
        self.n_read = 0
        self.n_underflows = 0        # callbacks that found too little audio (after the first sample arrived)
        self.n_underflow_samples = 0
        self.n_port_underflows = 0   # PortAudio's output-underflow flags
        self.n_clock = 0             # samples the card took (its time since the stream started)
        self.underflows = _Span()    # n_clock at the first and the latest underflow
        self.n_callbacks = 0
        self.draining = False        # the stream has ended: running dry is no longer an underflow
        self.margin_samples = 0      # the margin asked for (CardPlayback's queue_s)
        self.prime_samples = 0       # the margin used: whole callbacks of the card
        self.block = 0               # samples the card takes per callback (its period), once it has called
        self.priming = True

    def take(self, out: np.ndarray, n: int) -> None:
        """Called in the audio thread: fill ``out[:n]`` (every channel) from the ring, zeros if short.

        Playing starts (and starts again after running dry, so that one late hop costs one gap and not a gap
        per callback) once this callback's ``n`` samples and the margin are queued, so that the margin is
        still there after the callback. The margin is whole callbacks: the card takes ``n`` samples at a time,
        so a margin of less than ``n`` would only add latency (a late hop finds too little either way)."""
        if n != self.block:
            self.block = n
            self.prime_samples = self.margin_samples // n * n
        self.n_clock += n
        r = self.n_read
        avail = self.n_written - r
        if self.priming:
            if avail < n + self.prime_samples and not self.draining:
                out[:n] = 0.0
                return
            self.priming = False
        k = min(n, avail)
        if k > 0:
            i = r % self.capacity
            a = min(k, self.capacity - i)
            out[:a] = self.buf[i:i + a, None]
            if a < k:
                out[a:k] = self.buf[:k - a, None]
            self.n_read = r + k
        if k < n:
            out[k:n] = 0.0
            if not self.draining:
                self.n_underflows += 1
                self.n_underflow_samples += n - k
                self.priming = True
                self.underflows.note(self.n_clock)


# the source ------------------------------------------------------------------------------------
@dataclass
class CardDevice(DeviceInfo):
    """A device of a live stream: one input spec (a card and some of its channels)."""

    card: str = ""
    channels: list[int] = field(default_factory=list)   # 1-based channels of the card mixed into this device
    n_gaps: int = 0
    n_gap_samples: int = 0
    n_overflows: int = 0
    overflows_s: list[float] | None = None   # card time of the first and the latest overflow flag


BATCH_LATE_S = 0.02   # a batch (CardSource batch_s) goes out this much after it was due even if a card lags


class _Wake:
    """Wakes the stream loop from the audio callbacks: ``set`` is one C-level queue put (``threading.Event.set``
    runs a condition variable's Python code in the audio thread, every callback), and only when the loop has
    not been woken already since it last waited."""

    def __init__(self) -> None:
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._pending = False

    def set(self) -> None:
        if not self._pending:
            self._pending = True
            self._q.put(None)

    def wait(self, timeout_s: float) -> None:
        """Until :meth:`set` or ``timeout_s``; everything stored before that ``set`` is then visible."""
        try:
            self._q.get(timeout=timeout_s)
        except queue.Empty:
            pass
        self._pending = False


class _Card:
    """One opened input card: its PortAudio stream, ring, and the devices that read from it."""

    def __init__(self, info: CardInfo, n_channels: int, rate_hz: float, block_samples: int) -> None:
        self.info = info
        self.n_channels = n_channels
        self.rate_hz = rate_hz
        self.block_samples = block_samples
        self.ring = _InputRing(int(RING_S * rate_hz), n_channels)
        self.devices: list[int] = []          # indices into CardSource.active
        self.columns: list[np.ndarray] = []   # 0-based ring columns of each of those devices
        self.stream = None
        self.latency_s = 0.0                  # PortAudio's input latency, seconds
        self.error: BaseException | None = None
        self.ended = False
        self.n_consumed_clock = 0             # device-clock index of the next sample handed out
        self.next_gap = 0
        self.n_last_sent = False


class CardSource:
    """Live input from sound cards, one device per ``--input`` spec.

    Parameters
    ----------
    specs : sequence of str
        ``NAME``, ``NAME:1,2`` or an index (see the module docstring). The first usable one is the reference.
    sample_rate_hz : float, optional
        Rate to open every card at (default: each card's default rate).
    block_samples : int
        PortAudio block size (0: the host's choice).
    stall_s : float
        A card that delivers nothing for this long while the others do is ended (unplugged, or its
        driver stopped) with a one-sentence message; the stream goes on with the rest.
    names : sequence of str, optional
        Device names (default: the spec's text).
    max_duration_s : float, optional
        Stop by itself once the reference device's card has delivered this much audio (its own clock).
    batch_s : float
        Hand out audio only once every card holds this much that was not handed out yet (or ``batch_s`` plus
        ``BATCH_LATE_S`` after the last time): the stream loop then wakes once per batch instead of once per card
        period, and processes its hops back to back. Fewer, warmer wake-ups cost less CPU (8 devices at 16 kHz,
        hop 128, JACK period 128: 13.2 % of a core woken every period, 9.9 % in 32 ms batches, the medians of three
        60 s runs each, benchmarks/README.md); the latency grows by about the batch less a period (50 -> 72 ms at
        32 ms). 0 (the default): every period, the lowest latency.

    Usage: ``with CardSource(["USB", "ReSpeaker:1,2"]) as src: for frame in src: ...``; ``src.stop()``
    (from a signal handler or another thread) ends the iteration after the audio captured so far. The cards
    start recording when the iteration starts.
    Frames carry ``samples`` of shape ``(n_samples, n_channels)`` (the spec's channels; ``(n_samples,)`` for a
    spec of one channel, so that the stream's per-frame path does no mix-down), the index of their
    first sample in the card's clock, and ``FrameFlag.GAP`` when samples before them were lost.
    """

    def __init__(self, specs: Sequence[str], *, sample_rate_hz: float | None = None, block_samples: int = 0,
                 stall_s: float = 1.0, names: Sequence[str] | None = None, max_duration_s: float | None = None,
                 batch_s: float = 0.0) -> None:
        if not specs:
            raise AudioDeviceError("No --input was given; name at least one sound card (see: adhoc-array devices).")
        if sample_rate_hz is not None and not sample_rate_hz > 0:
            raise ValueError(f"{sample_rate_hz=} must be > 0 Hz")
        if block_samples < 0:
            raise ValueError(f"{block_samples=} must be >= 0 (0: the host's choice)")
        if names is not None and len(names) != len(specs):
            raise ValueError(f"{len(names)=} must equal {len(specs)=}")
        if not 0 <= batch_s <= 1.0:
            raise ValueError(f"{batch_s=} must be in 0..1 s")
        self.specs = list(specs)
        self.batch_s = float(batch_s)
        self._last_batch_s = 0.0
        self.n_handouts = 0   # times the cards' audio was handed out (the stream loop's wake-ups with work)
        self.sample_rate_hz = sample_rate_hz
        self.block_samples = int(block_samples)
        self.stall_s = float(stall_s)
        self.max_duration_s = max_duration_s
        self._names = list(names) if names is not None else None
        self.devices: list[CardDevice] = []
        self.active: list[CardDevice] = []
        self._cards: list[_Card] = []
        self._stop = threading.Event()
        self._wake = _Wake()
        self._sd = None
        self.t_start_s = 0.0

    # context manager -------------------------------------------------------------------------
    def __enter__(self) -> "CardSource":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    live = True
    paced = True

    @property
    def sample_rates_hz(self) -> list[float]:
        return [d.sample_rate_hz for d in self.active]

    @property
    def duration_s(self) -> float | None:
        return None   # live: unknown

    @property
    def input_latency_s(self) -> float:
        """The largest PortAudio input latency of the open cards, seconds."""
        return max((c.latency_s for c in self._cards), default=0.0)

    def stop(self) -> None:
        """End the stream after what was captured so far (safe from a signal handler or any thread)."""
        self._stop.set()
        self._wake.set()

    def open(self) -> None:
        """Find and open every card; a spec that cannot be used is left out with one sentence."""
        self._sd = import_sounddevice()
        cards = list_cards()
        if not any(c.max_input_channels > 0 for c in cards):
            raise AudioDeviceError("No input sound card is visible to PortAudio; connect one (or start a JACK or "
                                   "PulseAudio server) and see: adhoc-array devices.")
        by_index: dict[int, tuple[CardInfo, list[tuple[int, tuple[int, ...]]]]] = {}
        for k, text in enumerate(self.specs):
            name = self._names[k] if self._names else text
            dev = CardDevice(name=name, path=f"card:{text}", card=text)
            self.devices.append(dev)
            try:
                spec = InputSpec.parse(text, cards)
                info = find_card(spec.card, cards, kind="input")
                if spec.channels and max(spec.channels) > info.max_input_channels:
                    raise AudioDeviceError(f"--input '{text}': card '{info.name}' has {info.max_input_channels} "
                                           f"input channels; channel {max(spec.channels)} does not exist.")
            except AudioDeviceError as err:
                dev.usable = False
                dev.problem(f"Device '{name}': {err}")
                continue
            chans = spec.channels or tuple(range(1, info.max_input_channels + 1))
            dev.card, dev.channels = info.name, list(chans)
            by_index.setdefault(info.index, (info, []))[1].append((k, chans))
        for info, members in by_index.values():
            n_ch = max(max(ch) for _, ch in members)
            rate = float(self.sample_rate_hz or info.default_rate_hz)
            card = _Card(info, n_ch, rate, self.block_samples)
            try:
                card.stream = self._open_stream(card)
                card.latency_s = float(card.stream.latency)
            except AudioDeviceError as err:
                for k, _ in members:
                    self.devices[k].usable = False
                    self.devices[k].problem(f"Device '{self.devices[k].name}': {err}")
                continue
            for k, ch in members:
                dev = self.devices[k]
                dev.sample_rate_hz = rate
                card.devices.append(k)
                card.columns.append(np.asarray(ch, np.intp) - 1)
            self._cards.append(card)
        # active devices in spec order; device_id = index in active
        order = {k: i for i, k in enumerate(k for k in range(len(self.devices)) if self.devices[k].usable)}
        self.active = [d for d in self.devices if d.usable]
        for card in self._cards:
            card.devices = [order[k] for k in card.devices]

    def start(self) -> None:
        """Start every card (the first iteration does it: the consumer is ready, so nothing piles up)."""
        if self.t_start_s:
            return
        self.t_start_s = time.monotonic()
        for card in self._cards:
            card.stream.start()

    def _open_stream(self, card: _Card):
        sd = self._sd
        try:
            sd.check_input_settings(device=card.info.index, channels=card.n_channels, samplerate=card.rate_hz,
                                    dtype="float32")
        except Exception as err:  # noqa: BLE001 - PortAudioError or ValueError: one sentence, the rest go on
            raise AudioDeviceError(
                f"card '{card.info.name}' cannot record {card.n_channels} channels at {card.rate_hz:g} Hz "
                f"({err}); it offers {card.info.max_input_channels} channels, default rate "
                f"{card.info.default_rate_hz:g} Hz") from None
        ring = card.ring

        def callback(indata, frames, time_info, status) -> None:   # audio thread: copy and count only
            try:
                if status.input_overflow:
                    ring.n_overflows += 1
                    ring.overflows.note(ring.n_clock)
                ring.put(indata, frames)
                ring.n_callbacks += 1
                ring.last_callback_s = time.monotonic()
                self._wake.set()
            except BaseException as err:  # noqa: BLE001 - handed to the consumer loop
                card.error = err
                self._wake.set()
                raise sd.CallbackAbort from None

        try:
            return sd.InputStream(device=card.info.index, channels=card.n_channels, samplerate=card.rate_hz,
                                  dtype="float32", blocksize=card.block_samples, callback=callback,
                                  finished_callback=self._wake.set)
        except Exception as err:  # noqa: BLE001
            raise AudioDeviceError(f"card '{card.info.name}' could not be opened ({err})") from None

    def close(self) -> None:
        for card in self._cards:
            if card.stream is not None:
                try:
                    card.stream.abort()
                    card.stream.close()
                except Exception as err:  # noqa: BLE001 - closing a vanished card must not lose the outputs
                    log.info("Card '%s' did not close cleanly (%s).", card.info.name, err)
                card.stream = None

    # iteration -------------------------------------------------------------------------------
    def __iter__(self) -> Iterator[Frame]:
        self.start()
        self._last_batch_s = time.monotonic()
        seq = [0] * len(self.active)
        limit = None
        if self.max_duration_s is not None and self._cards:
            ref = next(c for c in self._cards if 0 in c.devices)
            limit = (ref, int(round(self.max_duration_s * ref.rate_hz)))
        while True:
            if limit is not None and limit[0].n_consumed_clock >= limit[1]:
                self._stop.set()
            stopping = self._stop.is_set()
            got = False
            if not self.batch_s or stopping or self._batch_due():   # else: nothing handed out this round
                self._last_batch_s = time.monotonic()
                for card in self._cards:
                    if not card.ended:
                        for frame in self._drain(card, seq):
                            got = True
                            yield frame
                self.n_handouts += got
            if stopping:   # every device's stream ends with what it has
                for card in self._cards:
                    yield from self._end(card, seq)
                return
            if not got:
                for card in self._stalled_cards():
                    yield from self._end(card, seq)
                if all(c.ended for c in self._cards):
                    return
                self._wake.wait(0.05)

    def _batch_due(self) -> bool:
        """Whether every card holds ``batch_s`` of audio not handed out yet, or the last batch is that long ago
        plus ``BATCH_LATE_S`` (a card that lags does not hold the others back)."""
        if time.monotonic() - self._last_batch_s >= self.batch_s + BATCH_LATE_S:
            return True
        return all(c.ended or c.ring.n_written - c.ring.n_read >= self.batch_s * c.rate_hz for c in self._cards)

    def _end(self, card: _Card, seq: list[int]) -> Iterator[Frame]:
        """The empty last frame of each device of ``card``."""
        if card.n_last_sent:
            return
        card.ended = card.n_last_sent = True
        for j, d in enumerate(card.devices):
            cols = card.columns[j]
            empty = np.zeros((0, len(cols)) if len(cols) > 1 else 0, np.float32)
            yield self._frame(card, d, seq, empty, card.n_consumed_clock, FrameFlag.LAST)

    def _frame(self, card: _Card, d: int, seq: list[int], x: np.ndarray, first: int, flags: FrameFlag) -> Frame:
        f = Frame(device_id=d, seq=seq[d], first_sample=first, sample_rate_hz=card.rate_hz, samples=x, flags=flags)
        seq[d] += 1
        self.active[d].n_read_samples += len(x)
        return f

    def _drain(self, card: _Card, seq: list[int]) -> Iterator[Frame]:
        """Frames of everything the card's ring holds (one per device, split at gaps)."""
        if card.error is not None:
            err, card.error = card.error, None
            from .errors import StreamError
            raise StreamError(f"Card '{card.info.name}': its audio callback failed "
                              f"({type(err).__name__}: {err}).")
        ring = card.ring
        end = ring.n_written
        flags = FrameFlag.NONE
        while ring.n_read < end:
            stop = end
            if card.next_gap < min(ring.n_gaps, MAX_GAPS):
                at = int(ring.gap_at[card.next_gap])
                if at <= ring.n_read:     # the gap lies before the next stored sample
                    n_gap = int(ring.gap_len[card.next_gap])
                    card.next_gap += 1
                    card.n_consumed_clock += n_gap
                    flags = FrameFlag.GAP
                    for d in card.devices:
                        self.active[d].n_gaps += 1
                        self.active[d].n_gap_samples += n_gap
                    continue
                stop = min(stop, at)
            r0 = ring.n_read
            i = r0 % ring.capacity
            n = min(stop - r0, ring.capacity - i)
            chunk = ring.buf[i:i + n]
            first = card.n_consumed_clock
            # a gap is flagged on the frame after it: its first_sample jumps
            for j, d in enumerate(card.devices):
                cols = card.columns[j]   # a copy either way: the ring may be overwritten
                x = chunk[:, cols[0]].copy() if len(cols) == 1 else chunk[:, cols]
                yield self._frame(card, d, seq, x, first, flags)
            ring.n_read = r0 + n
            card.n_consumed_clock += n
            flags = FrameFlag.NONE
        for j, d in enumerate(card.devices):
            self.active[d].n_overflows = ring.n_overflows
            self.active[d].overflows_s = ring.overflows.seconds(card.rate_hz)

    def _stalled_cards(self) -> list[_Card]:
        """Cards whose stream stopped, or that stalled while another card still delivers (or, alone,
        delivered nothing for ``stall_s``): each is ended with one sentence."""
        now = time.monotonic()
        live = [c for c in self._cards if not c.ended]
        newest = max((c.ring.last_callback_s for c in live), default=now)
        out = []
        for card in live:
            if not card.ring.n_callbacks:   # not started yet: a card may take a while to deliver its first block
                stalled = now - self.t_start_s > max(2.0, 2 * self.stall_s)
            else:
                last = card.ring.last_callback_s
                stalled = last < newest - self.stall_s or (len(live) == 1 and now - last > self.stall_s)
            inactive = card.stream is not None and not card.stream.active
            if stalled or inactive:
                t = card.n_consumed_clock / card.rate_hz
                why = "its stream stopped" if inactive else f"it delivered nothing for {self.stall_s:g} s"
                for d in card.devices:
                    self.active[d].problem(f"Device '{self.active[d].name}': card '{card.info.name}' stopped "
                                           f"delivering audio after {t:.2f} s ({why}; unplugged?); the stream "
                                           "goes on without it.")
                out.append(card)
        return out

    def counters(self) -> dict[str, Any]:
        """Overflow and gap counts per device (for the status line and the report)."""
        return {d.name: {"n_overflows": d.n_overflows, "n_gaps": d.n_gaps, "n_gap_samples": d.n_gap_samples}
                for d in self.active}


class CardPlayback:
    """Plays the enhanced stream on a sound card in real time (mono, on every channel opened).

    The stream runner :meth:`write`\\ s each hop; the PortAudio callback plays what is queued once ``queue_s``
    of audio is (a margin against the jitter of the stream loop), and zeros, counted as an underflow, when the
    queue runs dry (it then waits for ``queue_s`` again). So that the output stays live, a hop that finds more
    than that is queued is dropped (counted): the burst of blocks released when the stream first
    aligns its devices is skipped this way (``queue_s`` doubled, plus 50 ms).

    Parameters
    ----------
    name : str
        Card name (part of it, or an index; ``default``: PortAudio's default output).
    sample_rate_hz : float
    block_samples : int
        PortAudio block size (0: the host's choice).
    queue_s : float
        Audio queued before playing, seconds: the output's margin against the jitter of the stream loop, paid
        in latency. It is rounded down to whole periods of the card (the samples it takes per callback): a
        loop that is late by less than the margin plus one period loses nothing; a margin shorter than a
        period would protect nothing. 0: play as soon as a hop is there.
    """

    def __init__(self, name: str, *, sample_rate_hz: float, block_samples: int = 0, queue_s: float = 0.01) -> None:
        if not sample_rate_hz > 0:
            raise ValueError(f"{sample_rate_hz=} must be > 0 Hz")
        if not queue_s >= 0:
            raise ValueError(f"{queue_s=} must be >= 0 s")
        sd = import_sounddevice()
        cards = list_cards()
        if name == "default":
            idx = sd.default.device[1]
            if idx is None or idx < 0:
                raise AudioDeviceError(f"There is no default output card; available: {_available(cards, 'output')}.")
            info = next(c for c in cards if c.index == idx)
        else:
            info = find_card(name, cards, kind="output")
        self.info = info
        self.sample_rate_hz = float(sample_rate_hz)
        self.ring = _OutputRing(int(max(4 * queue_s, 1.0) * sample_rate_hz))
        self.ring.margin_samples = self.ring.prime_samples = int(queue_s * sample_rate_hz)
        self.max_queue = 2 * self.ring.margin_samples + int(0.05 * sample_rate_hz)
        self._told_margin = False
        self.n_dropped_samples = 0
        try:
            sd.check_output_settings(device=info.index, channels=1, samplerate=self.sample_rate_hz, dtype="float32")
        except Exception as err:  # noqa: BLE001 - PortAudioError or ValueError, as one sentence
            raise AudioDeviceError(f"Output card '{info.name}' cannot play at {self.sample_rate_hz:g} Hz ({err}); "
                                   f"its default rate is {info.default_rate_hz:g} Hz.") from None
        ring = self.ring
        self.error: BaseException | None = None

        def callback(outdata, frames, time_info, status) -> None:   # audio thread: copy and count only
            try:
                if status.output_underflow:
                    ring.n_port_underflows += 1
                ring.take(outdata, frames)
                ring.n_callbacks += 1
            except BaseException as err:  # noqa: BLE001 - handed to the stream runner
                self.error = err
                raise sd.CallbackAbort from None

        self._stream = sd.OutputStream(device=info.index, channels=1, samplerate=self.sample_rate_hz,
                                       dtype="float32", blocksize=block_samples, callback=callback)
        self._started = False
        self._min_level = 1 << 62
        self._window_end = 0
        self._excess = 0
        self.latency_s = float(self._stream.latency)   # PortAudio's output latency, seconds

    @property
    def queued_samples(self) -> int:
        return self.ring.n_written - self.ring.n_read

    def write(self, result) -> None:
        """Queue one hop of enhanced audio (a :class:`~stream.messages.HopResult`: the hop sink protocol)."""
        self.write_samples(result.enhanced)

    def write_samples(self, samples: np.ndarray) -> None:
        """Queue one hop of enhanced audio.

        The queue level is kept near ``queue_s``: a hop that finds the queue over ``max_queue`` is dropped
        (the burst at the start), and every half second the minimum of the level over that half second, less
        ``queue_s``, is latency nobody needs (the card and the stream share a clock, so it would stay
        forever): that many samples are dropped from the next hops. Every dropped sample is counted.
        """
        if self.error is not None:
            err, self.error = self.error, None
            from .errors import StreamError
            raise StreamError(f"Output card '{self.info.name}': its audio callback failed "
                              f"({type(err).__name__}: {err}).")
        ring = self.ring
        if not self._told_margin and ring.block:
            self._told_margin = True
            if ring.prime_samples < ring.margin_samples:
                fs = self.sample_rate_hz
                log.info("Output margin: %.1f ms (%d whole periods of %.1f ms of the output card; %.1f ms asked: "
                         "less than a period only adds latency).", 1e3 * ring.prime_samples / fs,
                         ring.prime_samples // ring.block, 1e3 * ring.block / fs, 1e3 * ring.margin_samples / fs)
        level = ring.n_written - ring.n_read
        if level > self.max_queue:
            self.n_dropped_samples += len(samples)
            return
        if self._started:
            self._min_level = min(self._min_level, level)
            if ring.n_written >= self._window_end:
                self._excess = max(0, self._min_level - ring.prime_samples)
                self._min_level = 1 << 62
                self._window_end = ring.n_written + int(0.5 * self.sample_rate_hz)
            if self._excess:
                k = min(self._excess, len(samples))
                samples = samples[k:]
                self._excess -= k
                self.n_dropped_samples += k
        n = len(samples)
        w = ring.n_written
        i = w % ring.capacity
        k = min(n, ring.capacity - i)
        ring.buf[i:i + k] = samples[:k]
        if k < n:
            ring.buf[:n - k] = samples[k:]
        ring.n_written = w + n
        if not self._started:
            self._stream.start()
            self._started = True
            self._window_end = ring.n_written + int(0.5 * self.sample_rate_hz)

    def counters(self) -> dict[str, int]:
        r = self.ring
        return {"n_underflows": r.n_underflows, "n_underflow_samples": r.n_underflow_samples,
                "underflows_s": r.underflows.seconds(self.sample_rate_hz),
                "n_port_underflows": r.n_port_underflows, "n_dropped_samples": self.n_dropped_samples,
                "period_samples": r.block, "margin_samples": r.prime_samples}

    def close(self) -> None:
        if self._stream is not None:
            try:
                self.ring.draining = True
                if self._started:   # let the queued audio play out (bounded: the queue is short)
                    deadline = time.monotonic() + 2 * self.max_queue / self.sample_rate_hz + 0.1
                    while self.queued_samples > 0 and time.monotonic() < deadline and self._stream.active:
                        time.sleep(0.005)
                self._stream.abort()
                self._stream.close()
            except Exception as err:  # noqa: BLE001
                log.info("Output card '%s' did not close cleanly (%s).", self.info.name, err)
            self._stream = None
