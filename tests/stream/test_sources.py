"""Several sources end to end (estimator = "tracks"): speech presence, the steered talker, no speech at all."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from stream.config import EngineConfig
from stream.fixture import load_fixture
from stream.run import run_replay
from stream.speech import SpeechPresence, make_speech_presence

FIXTURE = Path(__file__).resolve().parents[2] / "replay_fixtures" / "meeting_table"
FAST = dict(plots=False, progress=False)


def _speech_truth(clean: np.ndarray, hop: int) -> np.ndarray:
    e = np.array([np.mean(clean[k * hop:(k + 1) * hop] ** 2) for k in range(len(clean) // hop)])
    return e > e.max() * 10 ** (-3.5)


def test_speech_presence_finds_the_talker_and_not_silence():
    fx = load_fixture(FIXTURE)
    x, fs = sf.read(fx.devices[0].path, dtype="float32")
    clean, _ = fx.load_clean()
    hop = 128
    sp = SpeechPresence(1, sample_rate_hz=fs, hop_samples=hop)
    p = np.array([sp.process(x[k * hop:(k + 1) * hop, None]).probability for k in range(len(x) // hop)])
    truth = _speech_truth(clean, hop)[:len(p)]
    assert np.mean(p[truth] >= 0.5) > 0.7                     # recall on the talker's frames
    assert sp.backend == "webrtc"
    silent = SpeechPresence(2, sample_rate_hz=fs, hop_samples=hop)
    for _ in range(50):
        f = silent.process(np.zeros((hop, 2), np.float32))
    assert f.probability == 0.0
    nan = np.full((hop, 2), np.nan, np.float32)
    assert SpeechPresence(2, sample_rate_hz=fs, hop_samples=hop).process(nan).probability == 0.0


def test_speech_presence_streaming_equals_batch_and_other_rates():
    fx = load_fixture(FIXTURE)
    x, fs = sf.read(fx.devices[1].path, dtype="float32", frames=3 * 16000)
    for rate, hop in ((fs, 128), (fs, 256), (44100, 441)):
        y = x if rate == fs else __import__("soxr").resample(x, fs, rate).astype(np.float32)
        a = SpeechPresence(1, sample_rate_hz=rate, hop_samples=hop)
        b = SpeechPresence(1, sample_rate_hz=rate, hop_samples=hop)
        pa = [a.process(y[k * hop:(k + 1) * hop, None]).probability for k in range(len(y) // hop)]
        # b gets the same samples in hops of varying size (decisions on the same 10 ms frames)
        pb, k = [], 0
        for n in [hop // 2, hop + hop // 2] * (len(y) // (2 * hop)):
            pb.append(b.process(y[k:k + n, None]).probability)
            k += n
        assert np.mean(pa) > 0.3
        assert abs(np.mean(pa) - np.mean(pb[:len(pa)])) < 0.05


def test_energy_fallback_when_asked_and_bad_backend_raises():
    sp = make_speech_presence(2, sample_rate_hz=16000, hop_samples=160, backend="energy")
    assert sp.backend == "energy"
    rng = np.random.default_rng(0)
    quiet = [sp.process(1e-3 * rng.standard_normal((160, 2)).astype(np.float32)).probability for _ in range(200)]
    loud = [sp.process(0.3 * rng.standard_normal((160, 2)).astype(np.float32)).probability for _ in range(5)]
    assert np.mean(quiet[100:]) < 0.2 and loud[-1] == 1.0
    with pytest.raises(ValueError, match="backend"):
        make_speech_presence(2, sample_rate_hz=16000, hop_samples=160, backend="silero")


def test_tracks_steer_at_the_talker_of_a_fixture(tmp_path):
    out = tmp_path / "o"
    outcome = run_replay([FIXTURE], out, config=EngineConfig(estimator="tracks", **FAST))
    report = json.loads((out / "report.json").read_text())
    sources = report["sources"]
    assert any(t["kind"] == "speech" for t in sources["tracks"]) and sources["switches"]
    assert sources["speech_presence"]["backend"] == "webrtc"
    with open(out / "toa.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert "steered_track" in rows[0] and "speech_probability" in rows[0]
    time_s, toa_s, _ = outcome.pipeline.toa_track()
    steered = np.array([int(r["steered_track"]) for r in rows])
    fx = load_fixture(FIXTURE)
    truth = fx.truth_toa_at(time_s)
    truth -= truth[:, :1]
    sel = (steered >= 0) & (time_s > 2.0)
    assert sel.mean() > 0.7
    err = np.abs(toa_s[sel] - truth[sel]).max(axis=1)
    assert np.mean(err <= 2.5e-4) > 0.9
    enh = report["metrics"]["enhancement"]
    assert enh["engine"]["si_sdr_db"] > enh["best_single_device"]["si_sdr_db"] + 3.0


def test_no_speech_outputs_the_reference_device_and_says_so(tmp_path):
    fs = 16000
    rng = np.random.default_rng(5)
    noise = rng.standard_normal(6 * fs + 100).astype(np.float32) * 0.1
    paths = []
    for d, lag in enumerate((0, 7, 19)):
        x = noise[50 - lag:50 - lag + 6 * fs] + 1e-3 * rng.standard_normal(6 * fs).astype(np.float32)
        p = tmp_path / f"n{d}.wav"
        sf.write(p, x, fs, subtype="FLOAT")
        paths.append(p)
    out = tmp_path / "o"
    outcome = run_replay(paths, out, config=EngineConfig(estimator="tracks", **FAST))
    report = json.loads((out / "report.json").read_text())
    assert not any(t["kind"] == "speech" for t in report["sources"]["tracks"])
    assert any("No speech" in m or "no talker" in m for m in report["messages"])
    assert set(outcome.pipeline.state.track_id) == {-1}
    y, _ = sf.read(out / "enhanced.wav", dtype="float32")
    x0, _ = sf.read(paths[0], dtype="float32")
    n = min(len(y), len(x0)) - fs
    c = np.corrcoef(y[fs // 2:n], x0[fs // 2:n])[0, 1]
    assert c > 0.99          # the reference device, not a beam (at the noise or anywhere)
