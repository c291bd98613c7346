"""Sinks that write as the stream goes, so that a failure mid-stream loses nothing already produced."""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import soundfile as sf


_SFC_RF64_AUTO_DOWNGRADE = 0x1210   # libsndfile: write RF64, rewrite as WAV at close if under 4 GiB


def open_wav(path: str | Path, *, sample_rate_hz: float, channels: int) -> sf.SoundFile:
    """A float32 WAV file for writing that may grow past 4 GiB (a long live session): RF64, which libsndfile
    turns back into an ordinary WAV (WAVE_FORMAT_EXTENSIBLE) at close when it stayed under 4 GiB."""
    f = sf.SoundFile(str(path), "w", samplerate=int(round(sample_rate_hz)), channels=channels, subtype="FLOAT",
                     format="RF64")
    sf._snd.sf_command(f._file, _SFC_RF64_AUTO_DOWNGRADE, sf._ffi.NULL, 1)
    return f


class WavSink:
    """Streams mono float32 audio into a WAV file; as a hop sink (``write(HopResult)``), the enhanced audio.

    Parameters
    ----------
    path : path
    sample_rate_hz : float
    skip_samples : int
        Samples dropped at the start (the beamformer's latency), so that the file lines up with
        the reference device.
    max_samples : int or None
        Samples written at most (the tail of the beamformer flush beyond the input is dropped).
    buffer_samples : int
        Samples gathered before each write to the file (few, larger writes; at most this much is lost on a
        hard kill; :meth:`flush` and :meth:`close` write the rest).
    """

    def __init__(self, path: str | Path, *, sample_rate_hz: float, skip_samples: int = 0,
                 max_samples: int | None = None, buffer_samples: int = 8192) -> None:
        self.path = Path(path)
        self._file = open_wav(self.path, sample_rate_hz=sample_rate_hz, channels=1)
        self._skip = int(skip_samples)
        self.max_samples = max_samples
        self.n_written = 0          # samples accepted (written or buffered)
        self._buf = np.zeros(max(1, int(buffer_samples)), np.float32)
        self._n_buf = 0

    def write(self, result) -> None:
        """Append one hop's enhanced audio (a :class:`~stream.messages.HopResult`)."""
        self.write_samples(result.enhanced)

    def write_samples(self, samples: np.ndarray) -> None:
        """Append mono samples."""
        x = np.asarray(samples, np.float32)
        if self._skip:
            k = min(self._skip, len(x))
            x, self._skip = x[k:], self._skip - k
        if self.max_samples is not None:
            x = x[: max(0, self.max_samples - self.n_written)]
        if not len(x):
            return
        self.n_written += len(x)
        if self._n_buf + len(x) > len(self._buf):
            self.flush()
            if len(x) > len(self._buf):
                self._file.write(x)
                return
        self._buf[self._n_buf:self._n_buf + len(x)] = x
        self._n_buf += len(x)

    def flush(self) -> None:
        if self._n_buf and not self._file.closed:
            self._file.write(self._buf[:self._n_buf])
            self._n_buf = 0
            self._file.flush()

    def close(self) -> None:
        if not self._file.closed:
            self.flush()
            self._file.close()


class RecordingSink:
    """Writes every device's raw input (its own rate, its channels, its own clock) into a folder that
    ``adhoc-array replay DIR`` accepts unchanged: one float WAV per device and ``recording.toml`` naming them
    in device order, with an ``[engine]`` table of the options the stream ran with (a replay applies them, so
    it gives the same output). A gap in a device's stream (lost samples) is written as zeros, so each file stays on
    the device's clock.
    """

    MANIFEST = "recording.toml"

    def __init__(self, folder: str | Path, devices: Sequence[Any], *, description: str = "",
                 engine: dict[str, Any] | None = None) -> None:
        self.folder = Path(folder)
        self.engine = {k: v for k, v in (engine or {}).items() if v is not None}
        self.folder.mkdir(parents=True, exist_ok=True)
        self.devices = list(devices)
        self.description = description
        self._files: list[sf.SoundFile | None] = [None] * len(self.devices)
        self._next = [0] * len(self.devices)
        self.n_gap_samples = [0] * len(self.devices)
        self.file_names = [f"dev{k:02d}_{_safe(getattr(d, 'name', str(k)))}.wav" for k, d in enumerate(self.devices)]
        self._write_manifest()

    def write(self, frame) -> None:
        """Append one frame (``Frame.samples`` of shape (n,) or (n, n_channels))."""
        d = frame.device_id
        x = np.asarray(frame.samples, np.float32)
        x2 = x[:, None] if x.ndim == 1 else x
        f = self._files[d]
        if f is None:
            f = self._files[d] = open_wav(self.folder / self.file_names[d], sample_rate_hz=frame.sample_rate_hz,
                                          channels=max(1, x2.shape[1]))
        gap = int(frame.first_sample) - self._next[d]
        if gap > 0:
            f.write(np.zeros((gap, f.channels), np.float32))
            self.n_gap_samples[d] += gap
        elif gap < 0:
            x2 = x2[-gap:]
        if len(x2):
            f.write(x2)
        self._next[d] = max(self._next[d], int(frame.first_sample) + len(x))

    def _write_manifest(self) -> None:
        lines = ["# adhoc-array recording: one raw file per device, each in its own clock.",
                 "# Replay it with: adhoc-array replay " + str(self.folder), "",
                 f"description = {json.dumps(self.description)}", ""]
        for k, d in enumerate(self.devices):
            lines += ["[[device]]", f"name = {json.dumps(str(getattr(d, 'name', k)))}",
                      f"file = {json.dumps(self.file_names[k])}"]
            rate = getattr(d, "sample_rate_hz", float("nan"))
            if rate == rate:
                lines.append(f"sample_rate_hz = {float(rate)!r}")
            for key in ("card", "channels"):
                if getattr(d, key, None):
                    lines.append(f"{key} = {json.dumps(getattr(d, key))}")
            lines.append("")
        if self.engine:   # the options the stream ran with: a replay of the folder applies them (as a fixture's)
            lines += ["[engine]", *[f"{k} = {json.dumps(v)}" for k, v in sorted(self.engine.items())], ""]
        (self.folder / self.MANIFEST).write_text("\n".join(lines), encoding="utf-8")

    def close(self) -> None:
        for k, f in enumerate(self._files):
            if f is not None and not f.closed:
                f.close()
            elif f is None:   # a device that delivered nothing still gets a (valid, empty) file
                rate = getattr(self.devices[k], "sample_rate_hz", 16000.0)
                rate = rate if rate == rate else 16000.0
                sf.SoundFile(str(self.folder / self.file_names[k]), "w", samplerate=int(round(rate)), channels=1,
                             subtype="FLOAT").close()


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name)[:40] or "device"


class ToaCsvSink:
    """Streams the TOA track: frame centre time (reference clock, s), relative TOA of every device (s), gated;
    with the tracker, the steered track and the speech presence. A hop sink: one row per hop with a frame."""

    def __init__(self, path: str | Path, device_names: Sequence[str], *, tracks: bool = False) -> None:
        self.path = Path(path)
        self._fh = open(self.path, "w", newline="")
        self._writer = csv.writer(self._fh)
        self.tracks = tracks
        extra = ["steered_track", "speech_probability"] if tracks else []
        self._writer.writerow(["time_s", *[f"toa_s_{k}_{n}" for k, n in enumerate(device_names)], "gated", *extra])
        self.n_rows = 0
        self.n_devices = len(device_names)
        # one %-format per row (a csv row of f-strings took 2.7 times as long)
        self._row_format = ",".join(["%.6f", *["%.9f"] * self.n_devices, "%d",
                                     *(["%d", "%.3f"] if tracks else [])]) + self._writer.dialect.lineterminator

    def write(self, result) -> None:
        """One row from a :class:`~stream.messages.HopResult` (none for hops without a frame)."""
        toa = result.toa
        if toa is not None:
            self.write_row(toa.time_s, toa.toa_s, toa.gated, toa.track_id, toa.speech_probability)

    def write_row(self, time_s: float, toa_s: np.ndarray, gated: bool, track_id: int = -1,
                  speech_probability: float = float("nan")) -> None:
        if len(toa_s) != self.n_devices:
            raise ValueError(f"{self.path.name} has {self.n_devices} device columns; a row with {len(toa_s)} TOAs "
                             "would not line up with them.")
        toa = np.asarray(toa_s, np.float64).tolist()
        values = (time_s, *toa, gated, track_id, speech_probability) if self.tracks else \
            (time_s, *toa, gated)
        self._fh.write(self._row_format % values)
        self.n_rows += 1
        if self.n_rows % 256 == 0:
            self._fh.flush()

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.close()


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (np.floating, float)):
        v = float(value)
        return None if math.isnan(v) or math.isinf(v) else v
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.bool_,)):
        return bool(value)
    if isinstance(value, Path):
        return str(value)
    return value


def write_json(path: str | Path, data: dict) -> None:
    """Write a report as JSON (NaN and inf become null, arrays become lists)."""
    with open(path, "w") as fh:
        json.dump(_jsonable(data), fh, indent=2)
        fh.write("\n")
