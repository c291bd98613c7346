"""Array devices in the stream (``arrays`` option, :mod:`stream.channels`): two asynchronous 4-mic arrays and a
phone in a simulated room (pyroomacoustics, RT60 0.3 s, the talker of ``meeting_table``, sensor noise at
15 dB); every mic of an array is a channel of its own, the mics of one array share one coarse offset, and each
is steered at its own TOA."""
from __future__ import annotations

import importlib.util
import io
import re
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from stream.scoring import metrics
from stream.align import Aligner
from stream.channels import ChannelLayout
from stream.cli import main
from stream.config import EngineConfig
from stream.messages import Frame, FrameFlag
from stream.replay import DeviceInfo
from stream.run import run_replay

REPO = Path(__file__).resolve().parents[2]


def _bench():
    """``benchmarks/array_devices.py``: the scene is built once, there."""
    name = "array_devices_bench"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, REPO / "benchmarks" / "array_devices.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
    return sys.modules[name]


_B = _bench()
FS, SQUARE, OFFSET_S, _toml_rows = _B.FS, _B.SQUARE, _B.OFFSET_S, _B.toml_rows


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Files A.wav (4 ch), B.wav (4 ch, turned 90 degrees), phone.wav; arrays.toml; the clean talker and every
    channel's true relative TOA (direct path, in the device clocks)."""
    pytest.importorskip("pyroomacoustics")
    folder = tmp_path_factory.mktemp("arrays")
    clean, toa = _B.simulate(folder, snr_db=15.0, seed=5)
    return folder, clean, toa


def _run(folder: Path, out: Path, **options):
    cfg = EngineConfig(plots=False, progress=False, **options)
    outcome = run_replay([folder / "A.wav", folder / "B.wav", folder / "phone.wav"], out, config=cfg)
    y, _ = sf.read(out / "enhanced.wav", dtype="float32")
    return outcome, y


def _si_sdr(y: np.ndarray, clean: np.ndarray) -> float:
    n = min(len(y), len(clean))
    est, _ = metrics.align_to_reference(y[:n], clean[:n], max_lag_samples=800)
    return metrics.si_sdr_db(est, clean[:n])


def test_every_mic_of_an_array_is_a_channel_steered_at_its_own_toa(scene, tmp_path):
    folder, clean, toa_true = scene
    outcome, y = _run(folder, tmp_path / "arrays", arrays=str(folder / "arrays.toml"))
    rep = outcome.report
    assert rep["status"] == "ok" and not rep["messages"], rep["messages"]
    assert rep["stream"]["channels"] == ["A.1", "A.2", "A.3", "A.4", "B.1", "B.2", "B.3", "B.4", "phone"]
    assert rep["arrays"]["B"]["channels"] == ["B.1", "B.2", "B.3", "B.4"]
    assert [len(d.get("mics", [])) for d in rep["devices"]] == [4, 4, 0]
    header = (tmp_path / "arrays" / "toa.csv").read_text().splitlines()[0]
    assert "A.4" in header and "phone" in header
    # one clock per array: one coarse offset, the recording's start (within a hop)
    off = np.asarray(rep["stream"]["coarse_offsets_s"])
    assert np.all(off[:4] == off[0]) and np.all(off[4:8] == off[4])
    assert abs(off[4] + OFFSET_S["B"]) < 2e-3 and abs(off[8] + OFFSET_S["phone"]) < 2e-3
    # each mic steered at its own arrival (an array's mics differ by up to 0.4 ms here, 6 samples)
    t, toa, _ = outcome.pipeline.toa_track()
    err_s = np.median(np.abs(toa[t > 2.0] - toa_true), axis=0)
    assert np.all(err_s < 1e-4), 1e3 * err_s
    # and it sounds better than the arrays mixed down to one channel each
    mixed, y_mixed = _run(folder, tmp_path / "mixed")
    assert mixed.report["stream"]["channels"] == ["A", "B", "phone"]
    gain_db = _si_sdr(y, clean) - _si_sdr(y_mixed, clean)
    assert gain_db > 1.5, gain_db   # 2.2 dB when written


def test_an_array_with_the_wrong_channel_count_or_no_device_is_one_sentence_and_the_stream_goes_on(scene, tmp_path):
    folder, _, _ = scene
    arrays = tmp_path / "arrays.toml"
    arrays.write_text(f'[[array]]\nname = "A"\nmics_m = {_toml_rows(SQUARE[:3])}\n\n'
                      f'[[array]]\nname = "kitchen"\nmics_m = {_toml_rows(SQUARE)}\n')
    outcome, y = _run(folder, tmp_path / "out", arrays=str(arrays), estimator="pinv")
    rep = outcome.report
    assert rep["status"] == "ok" and len(y) > FS
    assert rep["stream"]["channels"] == ["A", "B", "phone"]
    assert any("'A' delivers 4 channels but the arrays file gives it 3 mics" in m for m in rep["messages"])
    assert any("array 'kitchen' that is not one of the stream's devices" in m for m in rep["messages"])


@pytest.mark.parametrize("text, message", [
    ('[[array]]\nmics_m = [[0, 0, 0], [0.1, 0, 0]]\n', "needs name and mics_m"),
    ('[[array]]\nname = "A"\nmics_m = [[0, 0, 0]]\n', "at least 2 mics"),
    ('[[array]]\nname = "A"\nmics_m = [[0, 0], [1, 0]]\n', "at least 2 mics"),
    ('[[array]]\nname = "A"\nmics_m = [[0, 0, 0], [0.1, 0, 0]]\n[[array]]\nname = "A"\nmics_m = [[0, 0, 0], [0.1, 0, 0]]\n',
     "two arrays are named 'A'"),
    ('name = "A"\n', "at least one [[array]] table"),
])
def test_a_bad_arrays_file_is_one_sentence_from_the_cli(scene, tmp_path, capsys, text, message):
    folder, _, _ = scene
    arrays = tmp_path / "arrays.toml"
    arrays.write_text(text)
    code = main(["replay", str(folder / "A.wav"), str(folder / "B.wav"), "--arrays", str(arrays),
                 "--out", str(tmp_path / "out"), "--no-plots", "--no-progress"])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1, err


def test_split_frames_keep_the_device_clock_and_flags():
    devices = [DeviceInfo("ref", "-", 16000.0, n_file_channels=1), DeviceInfo("arr", "-", 48000.0, n_file_channels=3)]
    spec = type("Spec", (), {"name": "arr", "mics_m": np.zeros((3, 3))})()
    layout = ChannelLayout(devices, [spec])
    assert layout.names == ["ref", "arr.1", "arr.2", "arr.3"] and layout.clock_groups == [0, 1, 1, 1]
    assert layout.sample_rates_hz == [16000.0, 48000.0, 48000.0, 48000.0]
    x = np.arange(12, dtype=np.float32).reshape(4, 3)
    parts = layout.split(Frame(1, 7, 4096, 48000.0, x, FrameFlag.GAP))
    assert [p.device_id for p in parts] == [1, 2, 3]
    assert all(p.seq == 7 and p.first_sample == 4096 and p.flags == FrameFlag.GAP for p in parts)
    assert np.array_equal(np.stack([p.samples for p in parts], axis=1), x)
    last = layout.split(Frame(1, 8, 4100, 48000.0, np.zeros(0, np.float32), FrameFlag.LAST))
    assert len(last) == 3 and all(len(p.samples) == 0 and p.flags == FrameFlag.LAST for p in last)
    assert not layout.messages
    (ref,) = layout.split(Frame(0, 0, 0, 16000.0, np.ones(4, np.float32)))
    assert ref.device_id == 0


def test_an_array_is_aligned_and_moved_as_one_clock():
    """The group's first mic is correlated with the reference; its other mics take its offset, and a shift of
    the group moves them all."""
    rng = np.random.default_rng(0)
    fs, n = 8000, 8000 * 6
    s = np.repeat(rng.standard_normal(n // 80), 80) * rng.standard_normal(n)   # bursty noise: a clear envelope
    lag = 1234
    al = Aligner(4, sample_rate_hz=fs, hop_samples=64, align_window_s=2.0, max_offset_s=0.5, recheck_s=None,
                 clock_groups=[0, 1, 1, 1])
    blocks = []
    blocks += list(al.push(0, s[lag:].astype(np.float32)))
    for d in (1, 2, 3):   # the array's mics: the same clock, tiny acoustic differences
        blocks += list(al.push(d, np.roll(s, d).astype(np.float32)))
    assert al.ready
    assert list(al.offsets_samples[1:]) == [al.offsets_samples[1]] * 3 and abs(al.offsets_samples[1] - lag) <= 2
    al.shift_group(2, 10, reason="test")
    assert list(al.offsets_samples[1:]) == [al.offsets_samples[1]] * 3
    with pytest.raises(ValueError, match="clock_groups"):
        Aligner(3, sample_rate_hz=fs, hop_samples=64, clock_groups=[0, 2, 2])


def test_a_live_card_whose_channels_are_an_array(scene, jack, bay, tmp_path):
    """Through the JACK dummy card: array A on channels 1-4 and the phone on channel 5 of one card (one clock
    here). A's four mics are channels of their own with one coarse offset, the status line counts the array's
    clipping as one device, and the recording (A as one 4-channel file) replays to the same output."""
    from stream.live import run_live
    folder, _, _ = scene
    a = sf.read(folder / "A.wav", dtype="float32")[0]
    phone = sf.read(folder / "phone.wav", dtype="float32")[0]
    n = min(len(a), len(phone), int(6.0 * FS))
    sig = np.column_stack([a[:n], phone[:n]])
    arrays = tmp_path / "arrays.toml"
    arrays.write_text(f'[[array]]\nname = "A"\nmics_m = {_toml_rows(SQUARE)}\n')

    def run():
        ins = bay.wait_ports(r"PortAudio:in_", 5, is_input=True)
        for k, port in enumerate(ins):
            bay.rewire(f"bay:out_{k + 1}", port)
        bay.play(sig)
    threading.Thread(target=run, daemon=True).start()
    status = io.StringIO()
    live = run_live(["system:1,2,3,4", "system:5"], tmp_path / "live", record=tmp_path / "take", names=["A", "phone"],
                    max_duration_s=6.5, status=status, overrides=[({"arrays": str(arrays)}, "test")])
    rep = live.report
    assert "| A " in status.getvalue() and "| phone " in status.getvalue(), status.getvalue()[-300:]
    # the tracker's sources, and how much of the speech so far had no talker steered (the report's sentence)
    assert re.search(r"\| sources \S+ steered -?\d+ \(no talker in \d+\.\d of \d+\.\d s of speech\)",
                     status.getvalue()), status.getvalue()[-300:]
    assert rep["status"] == "ok", rep.get("error")
    assert rep["stream"]["channels"] == ["A.1", "A.2", "A.3", "A.4", "phone"]
    assert len(set(rep["stream"]["coarse_offsets_s"][:4])) == 1
    assert sf.info(str(next((tmp_path / "take").glob("dev00_*.wav")))).channels == 4
    again = run_replay([tmp_path / "take"], tmp_path / "again", overrides=[({"plots": False}, "test")])
    assert again.report["stream"]["channels"] == rep["stream"]["channels"]
    np.testing.assert_array_equal(sf.read(tmp_path / "live" / "enhanced.wav", dtype="float32")[0],
                                  sf.read(tmp_path / "again" / "enhanced.wav", dtype="float32")[0])
