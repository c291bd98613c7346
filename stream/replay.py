"""Replay recorded files as fake live input: one file per device, each in its own clock.

A :class:`ReplaySource` yields :class:`~stream.messages.Frame` blocks device by device in time order,
exactly as a live source would, optionally paced at real time (``speed=1.0``).
"""
from __future__ import annotations

import logging
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
import soundfile as sf

from .errors import InputFileError, why_unreadable
from .messages import Frame, FrameFlag

log = logging.getLogger(__name__)


@dataclass
class DeviceInfo:
    """Facts about one device's input, filled in while streaming (reported at the end)."""

    name: str
    path: str
    sample_rate_hz: float = float("nan")
    n_file_channels: int = 0
    n_file_samples: int = 0
    duration_s: float = 0.0
    n_read_samples: int = 0
    usable: bool = True
    problems: list[str] = field(default_factory=list)

    def problem(self, message: str) -> None:
        """Record (and log) a one-sentence problem with this device."""
        self.problems.append(message)
        log.warning("%s", message)


def open_device_file(path: str | Path, *, name: str | None = None) -> tuple[sf.SoundFile | None, DeviceInfo]:
    """Open one device's recording, or explain in one sentence why it cannot be used.

    Returns
    -------
    (SoundFile or None, DeviceInfo)
        The open file (None when it cannot be used; ``info.problems`` says why).
    """
    path = Path(path)
    info = DeviceInfo(name=name or path.stem, path=str(path))
    if not path.exists():
        info.usable = False
        info.problem(f"Device '{info.name}': file {path} does not exist; it is left out.")
        return None, info
    try:
        handle = sf.SoundFile(str(path))
    except (sf.LibsndfileError, RuntimeError, OSError) as err:
        info.usable = False
        info.problem(f"Device '{info.name}': {path} is not a readable audio file ({why_unreadable(path, err)}); "
                     "it is left out.")
        return None, info
    info.sample_rate_hz = float(handle.samplerate)
    info.n_file_channels = int(handle.channels)
    info.n_file_samples = int(handle.frames) if handle.frames >= 0 else 0
    info.duration_s = info.n_file_samples / info.sample_rate_hz
    if info.n_file_samples == 0:
        handle.close()
        info.usable = False
        info.problem(f"Device '{info.name}': {path} holds no samples; it is left out.")
        return None, info
    if info.n_file_channels > 1:
        log.info("Device '%s': %d channels (mixed down to mono by the stream).", info.name, info.n_file_channels)
    return handle, info


READ_AHEAD_S = 1.0   # each file is read this much at a time: a libsndfile call per block (50 ms by default) cost
#                      more than converting its samples


DECODER_TAG = b"libmpg123"   # the lines libsndfile's MP3 decoder prints on stderr carry its source path


class DecoderMessages:
    """Keeps what C code prints on the process's stderr (file descriptor 2) during a call, and counts the lines of
    libsndfile's MP3 decoder (libmpg123) among them; other lines are written back to stderr.

    libmpg123 prints an "error: part2_3_length (...) too large for available bit count" line at some boundaries of
    the blocks libsndfile is asked for: the 9 shared locaR recordings print 6 to 604 such lines between them, read in
    100,000- to 1152-sample blocks, none read whole, and give the same samples (to 1e-8) either way. Printed amid the
    stream's own messages they read as a damaged file, so they are counted and logged instead.
    Where file descriptor 2 cannot be redirected, the call runs as it is.
    """

    def __init__(self) -> None:
        self.n_lines = 0
        self.first = ""
        self._tmp = None

    def run(self, call, *args, **kwargs):
        """``call(*args, **kwargs)`` with stderr kept."""
        try:
            if self._tmp is None:
                self._tmp = tempfile.TemporaryFile()
            sys.stderr.flush()
            saved = os.dup(2)
        except (OSError, ValueError, AttributeError):
            return call(*args, **kwargs)
        try:
            os.dup2(self._tmp.fileno(), 2)
            try:
                return call(*args, **kwargs)
            finally:
                os.dup2(saved, 2)
        finally:
            os.close(saved)
            self._sort()

    def _sort(self) -> None:
        self._tmp.seek(0)
        text = self._tmp.read()
        self._tmp.seek(0)
        self._tmp.truncate()
        other = []
        for line in text.splitlines(keepends=True):
            if DECODER_TAG in line:
                if not self.n_lines:
                    self.first = line.decode(errors="replace").split("]", 1)[-1].strip()
                self.n_lines += 1
            else:
                other.append(line)
        if other:
            os.write(2, b"".join(other))

    def close(self) -> None:
        if self._tmp is not None:
            self._tmp.close()
            self._tmp = None


class _ReadAhead:
    """A file read in chunks of ``chunk`` samples and handed out block by block (fewer, larger libsndfile
    calls). A read error ends the file after the samples read before it; :meth:`read` reports it once those are
    handed out. An MP3 file's decoder messages are kept off the terminal (:class:`DecoderMessages`)."""

    def __init__(self, handle: sf.SoundFile, *, chunk: int) -> None:
        self.handle = handle
        self.chunk = max(1, int(chunk))
        self._buf = np.zeros((0, max(1, handle.channels)), np.float32)
        self._eof = False
        self._error: Exception | None = None
        self.decoder = DecoderMessages() if handle.format == "MP3" else None

    def read(self, want: int) -> tuple[np.ndarray, Exception | None]:
        """Up to ``want`` samples, shape (n, channels), float32; and the read error, once the samples before it
        are all handed out (fewer than ``want`` samples: the file ended)."""
        if len(self._buf) < want and not self._eof:
            n = max(want - len(self._buf), self.chunk)
            try:
                if self.decoder is None:
                    data = self.handle.read(n, dtype="float32", always_2d=True)
                else:
                    data = self.decoder.run(self.handle.read, n, dtype="float32", always_2d=True)
            except (sf.LibsndfileError, RuntimeError) as err:
                data, self._error = self._buf[:0], err
            self._eof = len(data) < n
            self._buf = np.concatenate([self._buf, data]) if len(self._buf) else data
        out, self._buf = self._buf[:want], self._buf[want:]
        err = None
        if len(out) < want and self._error is not None:
            err, self._error = self._error, None
        return out, err

    def close(self) -> None:
        self.handle.close()
        if self.decoder is not None:
            self.decoder.close()


class ReplaySource:
    """Replays one recording per device as a live stream.

    Parameters
    ----------
    paths : sequence of path
        One audio file per device (any format libsndfile reads); the first usable one is the reference.
    block_s : float
        Duration of each block in seconds, on each device's own clock.
    speed : float or None
        ``None`` replays as fast as possible; ``1.0`` paces blocks at real time, ``2.0`` at twice that.
    names : sequence of str, optional
        Device names; default: file stems.
    start_s : float
        Start this far into every file (a device that joins a running array mid-recording); the device's clock
        still starts at sample 0.

    Usage: ``with ReplaySource(paths) as src: for frame in src: ...``. Devices whose files cannot be
    opened are left out with a one-sentence message in ``src.devices[k].problems``; ``src.active``
    lists the devices that stream, in order (their ``device_id`` is their index in ``active``).
    """

    def __init__(self, paths: Sequence[str | Path], *, block_s: float = 0.02, speed: float | None = None,
                 names: Sequence[str] | None = None, start_s: float = 0.0) -> None:
        if len(paths) == 0:
            raise InputFileError("No input files were given; pass one audio file per device.")
        if not block_s > 0:
            raise ValueError(f"{block_s=} must be > 0 seconds")
        if speed is not None and not speed > 0:
            raise ValueError(f"{speed=} must be > 0 (or None for as fast as possible)")
        if names is not None and len(names) != len(paths):
            raise ValueError(f"{len(names)=} must equal {len(paths)=}")
        if not start_s >= 0:
            raise ValueError(f"{start_s=} must be >= 0 seconds")
        self.block_s = float(block_s)
        self.start_s = float(start_s)
        self.speed = speed
        self._paths = [Path(p) for p in paths]
        self._names = list(names) if names is not None else None
        self.devices: list[DeviceInfo] = []
        self._handles: list[_ReadAhead] = []
        self.active: list[DeviceInfo] = []
        self._stop = False

    live = False   # a replay ends when its files do; a stop() before that interrupts it

    @property
    def paced(self) -> bool:
        """Whether blocks come at a given speed (else as fast as possible)."""
        return self.speed is not None

    # context manager -------------------------------------------------------------------------
    def __enter__(self) -> "ReplaySource":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def open(self) -> None:
        """Open every file; unusable ones are left out and reported."""
        seen: dict[str, int] = {}
        for k, path in enumerate(self._paths):
            name = self._names[k] if self._names else path.stem
            if name in seen:  # two files with the same stem in different folders
                seen[name] += 1
                name = f"{name}#{seen[name]}"
            else:
                seen[name] = 0
            handle, info = open_device_file(path, name=name)
            self.devices.append(info)
            if handle is not None and self.start_s:
                skip = int(round(self.start_s * info.sample_rate_hz))
                if skip >= info.n_file_samples:
                    info.usable = False
                    info.problem(f"Device '{name}': {path} lasts {info.duration_s:.2f} s, less than the start "
                                 f"{self.start_s:g} s; it is left out.")
                    handle.close()
                    handle = None
                else:
                    handle.seek(skip)
                    info.n_file_samples -= skip
                    info.duration_s = info.n_file_samples / info.sample_rate_hz
            if handle is not None:
                self._handles.append(_ReadAhead(handle, chunk=int(READ_AHEAD_S * info.sample_rate_hz)))
                self.active.append(info)

    def close(self) -> None:
        for info, h in zip(self.active, self._handles):
            if h.decoder is not None and h.decoder.n_lines:
                log.info("Device '%s': the MP3 decoder printed %d messages while %s was read in blocks (the first: "
                         "%s); they are logged here instead of on the terminal.", info.name, h.decoder.n_lines,
                         info.path, h.decoder.first)
            h.close()
        self._handles = []

    def stop(self) -> None:
        """End the replay after the current block (safe from a signal handler): every device's stream ends."""
        self._stop = True

    @property
    def sample_rates_hz(self) -> list[float]:
        return [d.sample_rate_hz for d in self.active]

    @property
    def duration_s(self) -> float:
        """Longest file duration in seconds (for progress reporting)."""
        return max((d.duration_s for d in self.active), default=0.0)

    # iteration -------------------------------------------------------------------------------
    def __iter__(self) -> Iterator[Frame]:
        if not self._handles and not self.devices:
            self.open()
        n_dev = len(self._handles)
        ended = [False] * n_dev
        seq = [0] * n_dev
        pos = [0] * n_dev
        tick = 0
        t0 = time.monotonic()
        while not all(ended):
            if self._stop:
                for d in range(n_dev):
                    if not ended[d]:
                        ended[d] = True
                        yield Frame(device_id=d, seq=seq[d], first_sample=pos[d],
                                    sample_rate_hz=self.active[d].sample_rate_hz,
                                    samples=np.zeros(0, np.float32), flags=FrameFlag.LAST)
                return
            if self.speed is not None:
                due = t0 + tick * self.block_s / self.speed
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            for d in range(n_dev):
                if ended[d]:
                    continue
                info, handle = self.active[d], self._handles[d]
                rate = info.sample_rate_hz
                # cumulative boundaries so that block lengths never drift from the clock
                stop = int(round((tick + 1) * self.block_s * rate))
                want = stop - pos[d]
                flags = FrameFlag.NONE
                data, err = handle.read(want)
                if err is not None:
                    flags |= FrameFlag.TRUNCATED
                    info.problem(f"Device '{info.name}': read error after {(pos[d] + len(data)) / rate:.2f} s "
                                 f"({err}); its stream ends there.")
                samples = data if data.shape[1] > 1 else data[:, 0]   # channels are mixed by the stream
                last = len(samples) < want or pos[d] + len(samples) >= info.n_file_samples
                if len(samples) < want and pos[d] + len(samples) < info.n_file_samples and not flags:
                    flags |= FrameFlag.TRUNCATED
                    info.problem(f"Device '{info.name}': file ends after {(pos[d] + len(samples)) / rate:.2f} s, "
                                 f"before the {info.duration_s:.2f} s its header states (truncated).")
                if last:
                    flags |= FrameFlag.LAST
                    ended[d] = True
                info.n_read_samples += len(samples)
                yield Frame(device_id=d, seq=seq[d], first_sample=pos[d], sample_rate_hz=rate,
                            samples=np.ascontiguousarray(samples, dtype=np.float32), flags=flags)
                seq[d] += 1
                pos[d] += len(samples)
            tick += 1
