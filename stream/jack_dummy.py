"""A JACK server on its dummy driver, and a patch bay that plays into and records from its ports: sound cards
where there are none (CI, a VM, trying ``adhoc-array live`` without hardware).

The dummy driver keeps an exact clock with ``-R`` and moves samples bit-exactly between clients; PortAudio
(and so sounddevice) sees it as the card ``system`` of the "JACK Audio Connection Kit" host API. The patch bay
is a JACK client (the ``JACK-Client`` package, a dev dependency) with its own output and input ports, whose
process callback plays preloaded arrays and records into preallocated ones.

Needs the ``jackd2`` package (``tools/setup_system.sh`` installs it).
"""
from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from .errors import AudioDeviceError


@dataclass(frozen=True)
class JackServer:
    name: str
    sample_rate_hz: int
    period_samples: int
    n_channels: int
    env: dict
    start_s: float


def _reinit_portaudio() -> None:
    """PortAudio lists devices when it initialises: re-scan so that it sees (or forgets) the server."""
    sd = sys.modules.get("sounddevice")
    if sd is not None:
        sd._terminate()
        sd._initialize()


@contextlib.contextmanager
def jack_dummy_server(*, sample_rate_hz: int = 16000, period_samples: int = 128, n_channels: int = 8,
                      name: str | None = None, timeout_s: float = 5.0) -> Iterator[JackServer]:
    """Start ``jackd -R -d dummy`` with a unique name, make it PortAudio's JACK server, stop it at the end.

    Raises
    ------
    AudioDeviceError
        jackd is not installed, or did not start (its last stderr lines are in the message).
    """
    if not shutil.which("jackd") or not shutil.which("jack_lsp"):
        raise AudioDeviceError("The JACK server is not installed; install it with: "
                               "sudo apt-get install jackd2 (tools/setup_system.sh does it).")
    name = name or f"adhoc{os.getpid()}_{int(time.monotonic() * 1e3) % 100000}"
    env = dict(os.environ, JACK_NO_AUDIO_RESERVATION="1", JACK_DEFAULT_SERVER=name)
    t0 = time.perf_counter()
    # jackd's messages go to a file, never a pipe: under load it prints a line per xrun, and a full pipe nobody
    # reads blocks the server (every client then hangs in its next server call)
    log = tempfile.TemporaryFile()
    proc = subprocess.Popen(["jackd", "-R", "-P", "70", "-n", name, "-d", "dummy", "-r", str(sample_rate_hz),
                             "-p", str(period_samples), "-C", str(n_channels), "-P", str(n_channels)],
                            env=env, stdout=subprocess.DEVNULL, stderr=log)
    while subprocess.run(["jack_lsp"], env=env, capture_output=True).returncode != 0:
        if proc.poll() is not None or time.perf_counter() - t0 > timeout_s:
            proc.kill()
            proc.wait()
            log.seek(0)
            err = log.read().decode(errors="replace")[-400:]
            log.close()
            raise AudioDeviceError(f"The JACK dummy server did not start ({err.strip() or 'no message'}).")
        time.sleep(0.02)
    old = os.environ.get("JACK_DEFAULT_SERVER")
    os.environ["JACK_DEFAULT_SERVER"] = name
    _reinit_portaudio()
    try:
        yield JackServer(name, sample_rate_hz, period_samples, n_channels, env, time.perf_counter() - t0)
    finally:
        sd = sys.modules.get("sounddevice")
        if sd is not None:
            sd._terminate()          # before jackd stops, or PortAudio aborts the process at exit
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()
        if old is None:
            os.environ.pop("JACK_DEFAULT_SERVER", None)
        else:
            os.environ["JACK_DEFAULT_SERVER"] = old
        if sd is not None:
            sd._initialize()


class PatchBay:
    """A JACK client that plays arrays on its outputs and records its inputs, sample-exact per cycle.

    Parameters
    ----------
    server : JackServer
    n_outputs, n_inputs : int
        Ports ``bay:out_1..`` and ``bay:in_1..``.
    record_s : float
        Capacity of the input recording, seconds.
    """

    def __init__(self, server: JackServer, *, n_outputs: int = 8, n_inputs: int = 2, record_s: float = 60.0,
                 name: str = "bay") -> None:
        import jack
        self._jack = jack
        self.client = jack.Client(name, servername=server.name, no_start_server=True)
        self.outs = [self.client.outports.register(f"out_{k + 1}") for k in range(n_outputs)]
        self.ins = [self.client.inports.register(f"in_{k + 1}") for k in range(n_inputs)]
        self.recorded = np.zeros((int(record_s * server.sample_rate_hz), n_inputs), np.float32)
        self.n_recorded = 0
        self.frame = 0              # JACK cycles' sample count since activation
        self.play_start_frame = -1  # frame at which the current signal's first sample was played
        self.record_start_frame = 0
        self._signal = np.zeros((0, n_outputs), np.float32)
        self._pos = 0
        self._go = False
        self._lock = threading.Lock()
        self.n_xruns = 0            # the server's xruns (a cycle ran late: on a loaded machine audio is lost)
        self.client.set_process_callback(self._process)
        self.client.set_xrun_callback(self._xrun)
        self.client.activate()

    def _process(self, n: int) -> None:
        sig, pos = self._signal, self._pos
        for k, port in enumerate(self.outs):
            buf = port.get_array()
            if self._go and pos < len(sig):
                m = min(n, len(sig) - pos)
                buf[:m] = sig[pos:pos + m, k] if k < sig.shape[1] else 0.0
                buf[m:] = 0.0
            else:
                buf[:] = 0.0
        if self._go:
            if pos == 0:
                self.play_start_frame = self.frame
            self._pos = pos + n
        r = self.n_recorded
        m = min(n, len(self.recorded) - r)
        if m > 0:
            if r == 0:
                self.record_start_frame = self.frame
            for k, port in enumerate(self.ins):
                self.recorded[r:r + m, k] = port.get_array()[:m]
            self.n_recorded = r + m
        self.frame += n

    def _xrun(self, delay_usecs: float) -> None:
        self.n_xruns += 1

    def play(self, signal: np.ndarray) -> None:
        """Start playing ``signal`` (n_samples, n_channels) on out_1.. from the next cycle."""
        x = np.asarray(signal, np.float32)
        self._signal = x[:, None] if x.ndim == 1 else x
        self._pos = 0
        self.play_start_frame = -1
        self._go = True

    @property
    def playing(self) -> bool:
        return self._go and self._pos < len(self._signal)

    def wait_played(self, timeout_s: float) -> bool:
        t_end = time.monotonic() + timeout_s
        while self.playing and time.monotonic() < t_end:
            time.sleep(0.01)
        return not self.playing

    def wait_ports(self, pattern: str, n: int, timeout_s: float = 10.0, **kind) -> list[str]:
        """Names of the first ``n`` ports matching ``pattern`` (waits until they exist)."""
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            names = sorted((p.name for p in self.client.get_ports(pattern, **kind)), key=_port_key)
            if len(names) >= n:
                return names[:n]
            time.sleep(0.01)
        raise TimeoutError(f"no {n} JACK ports match {pattern!r} after {timeout_s} s")

    def rewire(self, source: str, destination: str) -> None:
        """Connect ``source`` to ``destination`` alone: every other connection of ``destination`` is removed."""
        dest = self.client.get_port_by_name(destination)
        for other in self.client.get_all_connections(dest):
            if other.name != source:
                self.client.disconnect(other.name, destination)
        if source not in [p.name for p in self.client.get_all_connections(dest)]:
            self.client.connect(source, destination)

    def close(self) -> None:
        self.client.deactivate()
        self.client.close()


def _port_key(name: str):
    head, _, tail = name.rpartition("_")
    return (head, int(tail)) if tail.isdigit() else (name, 0)
