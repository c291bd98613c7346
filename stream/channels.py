"""Array devices in the stream: the stream's channels, and the frames of a source split into them.

A device can be a synchronous multichannel array with a known internal geometry (a ReSpeaker on a Pi, a
6-mic circular board): the ``arrays`` engine option names an arrays file (the TOML of
``adhoc-array calibrate --method multi-array``; in a stream ``file`` is optional) whose ``[[array]]``
tables are matched to the stream's devices by ``name``. Each mic of an array is then a channel of its own:
GCC-PHAT, the TOA estimator and the beamformer see every mic. The mics share their device's clock, so the
channels of one device form a clock group: one coarse offset, found on the group's first channel (the
aligner, :class:`stream.align.Aligner` ``clock_groups``). Every other device is one channel (several
channels of a card not named as an array are mixed down, as before).

Channel ``c`` is mic ``channels[c].mic`` of the source's active device ``channels[c].device_id``; the
channels of one device are consecutive and named ``DEVICE.k`` (``k`` = 1-based mic) for an array, the
device's own name otherwise.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .messages import Frame

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Channel:
    """One channel of the stream.

    Attributes
    ----------
    name : str
        ``DEVICE.k`` for mic ``k`` (1-based) of an array, else the device's name.
    device_id : int
        The source's active device it comes from.
    mic : int
        The array's mic (0-based, its row in ``mics_m``); -1 for a device that is one channel.
    group : int
        The clock group: index of the first channel of the same device.
    """

    name: str
    device_id: int
    mic: int
    group: int


def _n_channels(info) -> int:
    """The channels a device delivers, as far as it is known before its first frame (0: not known)."""
    return int(getattr(info, "n_file_channels", 0) or len(getattr(info, "channels", ()) or ()))


class ChannelLayout:
    """The stream's channels from the source's active devices and the arrays of the ``arrays`` option.

    Parameters
    ----------
    devices : sequence
        The source's active devices (``name``; ``n_file_channels`` or ``channels`` when known).
    arrays : sequence of stream.arrays.ArraySpec
        The arrays file's arrays. An array whose device delivers another number of channels than it has mics
        is left a single channel (its mics mixed) with one sentence; an array no device is named after is
        said once and ignored.
    """

    def __init__(self, devices: Sequence, arrays: Sequence = ()) -> None:
        by_name = {a.name: a for a in arrays}
        self.arrays: dict[int, object] = {}     # device_id -> ArraySpec
        self.messages: list[str] = []
        self._misshapen: set[int] = set()
        channels: list[Channel] = []
        for d, info in enumerate(devices):
            spec = by_name.pop(info.name, None)
            n_file = _n_channels(info)
            if spec is not None and n_file and n_file != len(spec.mics_m):
                self._say(f"Device '{info.name}' delivers {n_file} channel{'s' * (n_file != 1)} but the arrays file "
                          f"gives it {len(spec.mics_m)} mics; it is streamed as one channel (its channels mixed).")
                spec = None
            if spec is None:
                channels.append(Channel(info.name, d, -1, len(channels)))
                continue
            self.arrays[d] = spec
            first = len(channels)
            channels.extend(Channel(f"{info.name}.{k + 1}", d, k, first) for k in range(len(spec.mics_m)))
        for name in by_name:
            self._say(f"The arrays file names an array '{name}' that is not one of the stream's devices "
                      f"({', '.join(i.name for i in devices)}); it is ignored.")
        self.channels = channels
        self.n_devices = len(devices)
        self.device_names = [i.name for i in devices]
        self._first = [0] * self.n_devices    # first channel of each device
        for c in reversed(range(len(channels))):
            self._first[channels[c].device_id] = c
        self._rates = [float(getattr(devices[ch.device_id], "sample_rate_hz", float("nan"))) for ch in channels]

    def _say(self, message: str) -> None:
        self.messages.append(message)
        log.warning("%s", message)

    @property
    def identity(self) -> bool:
        """Every device is one channel (no array): frames pass through unchanged."""
        return not self.arrays

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.channels]

    @property
    def clock_groups(self) -> list[int]:
        """``clock_groups[c]``: the first channel of channel ``c``'s device (channels of one clock)."""
        return [c.group for c in self.channels]

    @property
    def sample_rates_hz(self) -> list[float]:
        return list(self._rates)

    def split(self, frame: Frame) -> list[Frame]:
        """The frame of one device as the frames of its channels (the same indices, flags and clock). A frame
        of an array with another number of channels (a card re-opened otherwise) is zeros on every mic: they
        leave the beam as silent, said once."""
        d = frame.device_id
        c0 = self._first[d]
        spec = self.arrays.get(d)
        if spec is None:
            return [frame if c0 == d else Frame(c0, frame.seq, frame.first_sample, frame.sample_rate_hz,
                                                frame.samples, frame.flags)]
        x = frame.samples
        n_mics = len(spec.mics_m)
        if x.ndim != 2 or x.shape[1] != n_mics:
            if len(x) and d not in self._misshapen:
                self._misshapen.add(d)
                self._say(f"Device '{spec.name}' sent a frame of shape {x.shape} instead of {n_mics} "
                          "channels; its mics are zeros in such frames.")
            x = np.zeros((len(x), n_mics), np.float32)
        return [Frame(c0 + k, frame.seq, frame.first_sample, frame.sample_rate_hz,
                      np.ascontiguousarray(x[:, k]), frame.flags) for k in range(n_mics)]

    def source_index(self, names) -> list[int]:
        """Each channel's device as an index into ``names`` (a fixture's device names; None: the source's own
        order). An array's mics share their device's index: they are scored against its truth."""
        return ([list(names).index(self.device_names[c.device_id]) for c in self.channels] if names else
                [c.device_id for c in self.channels])

    def placements(self) -> list[tuple[str, list[int], np.ndarray]]:
        """``(name, channels, mics_m)`` of every array, for :meth:`estimators.geometry.Geometry.with_arrays`."""
        return [(spec.name, [c for c, ch in enumerate(self.channels) if ch.device_id == d],
                 np.asarray(spec.mics_m, float)) for d, spec in self.arrays.items()]

    def report(self) -> dict:
        """The arrays of the stream and their channels (for report.json)."""
        return {spec.name: {
                    "device_id": d, "channels": [c.name for c in self.channels if c.device_id == d],
                    "mics_m": np.asarray(spec.mics_m, float).tolist()}
                for d, spec in self.arrays.items()}
