"""Sinks that write as the stream goes, so that a failure mid-stream loses nothing already produced."""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import soundfile as sf


class WavSink:
    """Streams mono float32 audio into a WAV file.

    Parameters
    ----------
    path : path
    sample_rate_hz : float
    skip_samples : int
        Samples dropped at the start (the beamformer's latency), so that the file lines up with
        the reference device.
    max_samples : int or None
        Samples written at most (the tail of the beamformer flush beyond the input is dropped).
    """

    def __init__(self, path: str | Path, *, sample_rate_hz: float, skip_samples: int = 0,
                 max_samples: int | None = None) -> None:
        self.path = Path(path)
        self._file = sf.SoundFile(str(self.path), "w", samplerate=int(round(sample_rate_hz)), channels=1,
                                  subtype="FLOAT")
        self._skip = int(skip_samples)
        self.max_samples = max_samples
        self.n_written = 0

    def write(self, samples: np.ndarray) -> None:
        x = np.asarray(samples, np.float32)
        if self._skip:
            k = min(self._skip, len(x))
            x, self._skip = x[k:], self._skip - k
        if self.max_samples is not None:
            x = x[: max(0, self.max_samples - self.n_written)]
        if len(x):
            self._file.write(x)
            self.n_written += len(x)

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()


class ToaCsvSink:
    """Streams the TOA track: frame centre time (reference clock, s), relative TOA of every device (s), gated."""

    def __init__(self, path: str | Path, device_names: Sequence[str], *, tracks: bool = False) -> None:
        self.path = Path(path)
        self._fh = open(self.path, "w", newline="")
        self._writer = csv.writer(self._fh)
        self.tracks = tracks
        extra = ["steered_track", "speech_probability"] if tracks else []
        self._writer.writerow(["time_s", *[f"toa_s_{k}_{n}" for k, n in enumerate(device_names)], "gated", *extra])
        self.n_rows = 0

    def write(self, time_s: float, toa_s: np.ndarray, gated: bool, track_id: int = -1,
              speech_probability: float = float("nan")) -> None:
        extra = [int(track_id), f"{speech_probability:.3f}"] if self.tracks else []
        self._writer.writerow([f"{time_s:.6f}", *[f"{v:.9f}" for v in toa_s], int(gated), *extra])
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
