"""The JACK dummy server and patch bay of the sound-card tests (one server per test module)."""
from __future__ import annotations

import pytest

from stream.errors import AudioDeviceError

RATE = 16000


@pytest.fixture(scope="module")
def jack():
    from stream.jack_dummy import jack_dummy_server
    try:
        with jack_dummy_server(sample_rate_hz=RATE, period_samples=128, n_channels=8) as server:
            yield server
    except AudioDeviceError as err:
        pytest.skip(f"no JACK dummy server here: {err}")


@pytest.fixture
def bay(jack):
    """The patch bay's process callback is Python in this process: it needs the GIL once per JACK period (8 ms),
    while the engine under test holds it in stretches. Python hands the GIL over only every switch interval
    (5 ms by default), which with the callback's own work overran the period (a server xrun in every take
    when the whole module ran); 0.1 ms keeps the callback on time."""
    import sys
    from stream.jack_dummy import PatchBay
    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-4)
    b = PatchBay(jack, n_outputs=8, n_inputs=1, record_s=30.0)
    try:
        yield b
    finally:
        b.close()
        sys.setswitchinterval(old)
