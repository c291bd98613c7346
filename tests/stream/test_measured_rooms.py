"""Scenes in a measured room (``benchmarks/scenes.py --rooms measured``): the responses are put on the timing truth,
and the clean reference carries the direct path's own filter.

The measured set itself (polimi eStick, GPL-3.0) stays in ``../shared/data``; these tests build a small set of the
same layout from known responses."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.io
import scipy.signal
import soundfile as sf

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "replay_fixtures"))
sys.path.insert(0, str(ROOT / "benchmarks"))
import build_fixtures as bf  # noqa: E402
from scenes import _separation_s  # noqa: E402

RATE = 48000
C = 343.0
Z = 1.5
SOURCES = [(0.40, 0.20), (0.70, 0.60)]
LATENCY_S = 4e-5      # the measurement's own delay, common to every channel


def _wavelet(n: int, at: float) -> np.ndarray:
    """A loudspeaker-like direct path: a band-pass pulse (1-6 kHz, not a delay) whose envelope peaks at ``at``."""
    t = (np.arange(n) - at) / RATE
    return np.exp(-(t / 2.5e-4) ** 2) * np.sin(2 * np.pi * 3000 * t + 0.9)


def _measured_set(folder: Path, jitter_s: np.ndarray) -> None:
    """Two sources to 32 microphones 3 cm apart, each response a wavelet at the arrival (plus ``jitter_s`` per
    microphone, as the inferred positions are off by a centimetre or two) and a weaker echo 4 ms later."""
    folder.mkdir(parents=True)
    scipy.io.savemat(folder / "source_location.mat", {"sourceLocation": np.array(SOURCES)})
    for k, (x, y) in enumerate(SOURCES, start=1):
        h = np.zeros((RATE // 2, 32))
        for m in range(32):
            at = (math.hypot(x, y - 0.03 * m) / C + LATENCY_S + jitter_s[m]) * RATE
            h[:, m] = _wavelet(len(h), at) + 0.3 * _wavelet(len(h), at + 0.004 * RATE)
        sf.write(folder / f"rir_source_{k}.wav", 0.5 * h, RATE, subtype="FLOAT")


def _scene(devices_y, noise: bool = False) -> bf.Scene:
    devs = tuple(bf.DeviceSpec(f"dev{i}", 16000, 0.1 * i, 0.0, 0.0, (0.0, y, Z), -90.0)
                 for i, y in enumerate(devices_y))
    return bf.Scene(name="m_test", description="", sim_rate_hz=16000, duration_s=2.0, room_dims_m=(0.0, 0.0, 0.0),
                    sabine_rt60_s=0.04, max_order_cap=0, speech_files=("audio/talk.wav",), speech_start_s=0.5,
                    speech_gap_s=0.3, path=bf.StaticPath((*SOURCES[0], Z)), devices=devs,
                    noise=bf.NoiseSpec("generated:white", 0.0, (*SOURCES[1], Z), 30.0) if noise else None,
                    block_hop_s=None, seed=3, speech_credit="", noise_credit="", source_truth=True,
                    measured_rirs="audio/rirs")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    _measured_set(root / "audio" / "rirs", np.random.default_rng(1).uniform(-6e-5, 6e-5, 32))
    rng = np.random.default_rng(2)    # a talker stand-in: bursts of coloured noise
    x = scipy.signal.lfilter([1.0], [1.0, -0.9], rng.standard_normal(16000))
    x *= np.repeat(rng.uniform(0.2, 1.0, 16), 1000)
    sf.write(root / "audio" / "talk.wav", 0.1 * x / np.abs(x).max(), 16000)
    return root


def test_each_measured_response_arrives_at_the_geometric_arrival_plus_the_time_models_delay(data):
    ys = (0.0, 0.27, 0.63, 0.93)
    scene = _scene(ys)
    delay = bf.pra.constants.get("frac_delay_length") // 2
    for h, y in zip(bf._measured_rirs(scene, data, scene.path(0.0)[0]), ys):
        env = np.abs(scipy.signal.hilbert(h))
        i = int(np.argmax(env[:400]))
        peak = i + 0.5 * (env[i - 1] - env[i + 1]) / (env[i - 1] - 2 * env[i] + env[i + 1])
        # the latency and each microphone's jitter are gone: the truth, computed from positions, holds
        assert peak == pytest.approx(math.hypot(SOURCES[0][0], SOURCES[0][1] - y) / C * 16000 + delay, abs=0.05)


def test_a_source_or_device_off_the_measured_positions_is_refused(data):
    scene = _scene((0.0, 0.3))
    with pytest.raises(ValueError, match="no measured response"):
        bf._measured_rirs(scene, data, (0.5, 0.5, Z))
    with pytest.raises(ValueError, match="not a measured microphone"):
        bf._measured_rirs(_scene((0.0, 0.315)), data, scene.path(0.0)[0])


def test_the_clean_reference_is_the_talker_through_the_direct_paths_filter(data, tmp_path):
    scene = _scene((0.0, 0.3, 0.6, 0.9))
    bf.build(scene, data, tmp_path)
    sync, fs = sf.read(tmp_path / "m_test" / "truth" / "sync.flac", always_2d=True)
    clean, _ = sf.read(tmp_path / "m_test" / "truth" / "clean_sync.flac")
    n = min(len(clean), len(sync))
    x, ref = sync[:n, 0], clean[:n]
    # device 0's own (noise-free) signal against the reference: only the echo 4 ms later differs (-10.5 dB)
    a = np.dot(x, ref) / np.dot(ref, ref)
    si_sdr = 10 * np.log10(np.sum((a * ref) ** 2) / np.sum((x - a * ref) ** 2))
    assert si_sdr > 8.0
    # against the dry talker the band-pass direct path alone would score below 0 dB
    dry = bf._dry_speech(scene, data, n)
    k = int(round(math.hypot(*SOURCES[0]) / C * fs))
    d = np.roll(dry, k)[:n]
    b = np.dot(x, d) / np.dot(d, d)
    assert 10 * np.log10(np.sum((b * d) ** 2) / np.sum((x - b * d) ** 2)) < 0.0


def test_sources_in_line_with_a_row_of_microphones_are_apart_only_by_the_wavefronts_curvature():
    row = [(0.0, 0.03 * m, Z) for m in range(0, 32, 4)]
    same_y = _separation_s(row, (0.33, 0.09, Z), (0.90, 0.10, Z))
    across = _separation_s(row, (0.33, 0.09, Z), (0.32, 0.78, Z))
    assert 0.3e-3 < same_y < 1e-3 < across
    assert _separation_s(row, (0.33, 0.09, Z), (0.33, 0.09, Z)) == 0.0
