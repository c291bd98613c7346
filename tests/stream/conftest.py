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
    from stream.jack_dummy import PatchBay
    b = PatchBay(jack, n_outputs=8, n_inputs=1, record_s=30.0)
    yield b
    b.close()
