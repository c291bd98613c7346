"""Live sound cards through a real JACK dummy server (PortAudio's JACK host API), no mocks.

The server runs with an exact clock at 16 kHz with 128-sample periods; a patch bay client plays known signals
into the engine's capture ports and records its output. Skipped only where the server cannot start.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from stream.errors import StreamError
from stream.scoring.fixture import load_fixture

from tests.conftest import REPO_FIXTURES

RATE = 16000


def _feed(bay, signal_: np.ndarray, n_inputs: int, *, client: str = "PortAudio", output: bool = False,
          delay_s: float = 0.0) -> threading.Thread:
    """In a thread: wire bay:out_k to the engine's in_k once its ports exist, wait ``delay_s``, play, then wire
    its output. The ports exist once the engine opens its stream, a little before it starts capturing: a test
    that needs the whole signal in the recording waits (without it the capture started up to a period after the
    playback in about half the takes, and in every one of three takes of a run)."""
    def run():
        ins = bay.wait_ports(rf"{client}:in_", n_inputs, is_input=True)
        for k, port in enumerate(ins):
            bay.rewire(f"bay:out_{k + 1}", port)
        time.sleep(delay_s)
        bay.play(signal_)
        if output:
            out = bay.wait_ports(rf"{client}:out_", 1, is_output=True, timeout_s=30.0)
            bay.rewire(out[0], "bay:in_1")
    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


WHOLE_DELAY_S = 0.25   # _feed's wait before playing, where a test needs the whole signal in the recording


def _clean_take(bay, take, attempts: int = 3, whole=None):
    """Run ``take()`` until the JACK server has no xrun during it (and ``whole(result)``, if given, holds: the
    take caught the whole signal); returns (its result, whether it was clean).

    An xrun is a cycle the server ran late (a loaded machine without real-time scheduling): the server itself
    loses audio then, so a take with one cannot be compared sample for sample; the engine counts it.
    """
    for _ in range(attempts):
        x0 = bay.n_xruns
        result = take()
        time.sleep(0.5)                  # the xrun notice comes on the client's own thread, sometimes late
        if bay.n_xruns == x0 and (whole is None or whole(result)):
            return result, True
    warnings.warn(f"the JACK server had xruns, or the capture missed the start of the signal, in each of "
                  f"{attempts} takes (the machine is too loaded); the sample-exact comparisons were skipped")
    return result, False


def _lead(x: np.ndarray) -> int:
    nz = np.flatnonzero(np.any(x != 0, axis=1) if x.ndim == 2 else x != 0)
    return int(nz[0]) if len(nz) else len(x)


def test_devices_lists_the_jack_card(jack, capsys):
    from stream.cli import main
    assert main(["devices"]) == 0
    out = capsys.readouterr().out
    assert "system (JACK Audio Connection Kit): 8 in, 8 out, 16000 Hz" in out


def test_capture_of_a_multichannel_signal_is_bit_exact(jack, bay):
    """A 3-channel device and a device of channels 5,6 of the same card (opened once): every sample, in order."""
    from stream.cards import CardSource
    rng = np.random.default_rng(3)
    sig = (0.2 * rng.standard_normal((RATE, 6))).astype(np.float32)

    def take():
        frames: dict[int, list] = {0: [], 1: []}
        firsts: dict[int, list] = {0: [], 1: []}
        with CardSource(["system:1,2,3", "system:5,6"], max_duration_s=2.0) as src:
            assert len(src._cards) == 1 and src._cards[0].n_channels == 6
            _feed(bay, sig, 6, delay_s=WHOLE_DELAY_S)   # wired before it plays (once, the first periods were lost)
            for f in src:
                frames[f.device_id].append(f.samples)
                firsts[f.device_id].append(f.first_sample)
        return src, frames, firsts

    (src, frames, firsts), clean = _clean_take(bay, take, whole=lambda r: _lead(np.concatenate(r[1][0])) > 0)
    a, b = np.concatenate(frames[0]), np.concatenate(frames[1])
    assert a.shape[1] == 3 and b.shape[1] == 2 and len(a) == len(b) >= 2 * RATE
    starts = np.cumsum([0] + [len(x) for x in frames[0][:-1]])
    np.testing.assert_array_equal(firsts[0], starts)          # contiguous stamps, no gap
    assert all(d.n_gaps == 0 for d in src.active)
    if clean:
        lead = _lead(a)
        assert lead == _lead(b) and lead + RATE <= len(a)
        assert np.array_equal(a[lead:lead + RATE], sig[:, 0:3])
        assert np.array_equal(b[lead:lead + RATE], sig[:, 4:6])
        assert all(d.n_overflows == 0 for d in src.active)


def test_live_equals_replay_and_the_recording_replays_exactly(jack, bay, tmp_path):
    """meeting_table's six phones played into the card: the recording is bit-exact, and replaying it, or the
    fixture's files with the same lead of silence, gives the live output sample for sample."""
    from stream.live import LIVE_DEFAULTS, run_live
    from stream.run import run_replay
    fx = load_fixture(REPO_FIXTURES / "meeting_table")
    sig = np.stack([sf.read(d.path, dtype="float32")[0] for d in fx.devices], axis=1)

    def take():
        shutil.rmtree(tmp_path / "live", ignore_errors=True)
        shutil.rmtree(tmp_path / "take", ignore_errors=True)
        _feed(bay, sig, 6, output=True, delay_s=WHOLE_DELAY_S)
        return run_live([f"system:{k + 1}" for k in range(6)], tmp_path / "live", output="system",
                        record=tmp_path / "take", max_duration_s=8.5, status=False,
                        names=[d.name for d in fx.devices])

    def whole(_) -> bool:
        # the bay plays WHOLE_DELAY_S after the engine's input ports exist; on a very loaded machine the card's
        # stream may start capturing only after that (the recording then has no lead of silence and misses the
        # signal's start)
        return _lead(sf.read(tmp_path / "take" / f"dev00_{fx.devices[0].name}.wav", dtype="float32")[0]) > 0

    live, clean = _clean_take(bay, take, whole=whole)
    xruns_after = bay.n_xruns
    rep = live.report
    assert rep["status"] == "ok" and rep["live"] is True, rep.get("error")
    counts = [(c["name"], c["n_overflows"], c["n_gaps"]) for c in rep["cards"]["inputs"]]
    for c in rep["cards"]["inputs"]:   # when the overflows came (card time): none, or first <= latest in the take
        assert (c["overflows_s"] is None) == (c["n_overflows"] == 0), c
        assert c["overflows_s"] is None or 0 <= c["overflows_s"][0] <= c["overflows_s"][1] <= 9.0, c
    # the engine keeps up (no ring gaps) and, without a server xrun, nothing is lost on the way in (output
    # underflows, a hiccup of a loaded machine, are counted, not tested here: benchmarks/live_soak.py measures them)
    assert all(g == 0 for _, _, g in counts), counts
    # replaying the recorded folder gives the live output exactly (recording.toml carries the live options), even
    # after an xrun: the recording holds what the engine received
    again = run_replay([tmp_path / "take"], tmp_path / "again", overrides=[({"plots": False}, "test")])
    y_live = sf.read(tmp_path / "live" / "enhanced.wav", dtype="float32")[0]
    y_again = sf.read(tmp_path / "again" / "enhanced.wav", dtype="float32")[0]
    assert again.report["status"] == "ok"
    np.testing.assert_array_equal(y_live, y_again)
    # the enhanced stream was played on the output card
    assert bay.n_recorded > 0 and np.abs(bay.recorded[:bay.n_recorded]).max() > 0.01
    if not clean:
        return
    assert all(o == 0 for _, o, _ in counts), counts
    # the recording: each device's file is the fixture's, after the same lead of digital silence
    rec = [sf.read(tmp_path / "take" / f"dev{k:02d}_{d.name}.wav", dtype="float32")[0] for k, d in
           enumerate(fx.devices)]
    lead = _lead(rec[0])
    for x, d in zip(rec, sig.T):
        n = min(len(d), len(x) - lead)
        assert _lead(x) == lead and n > 6 * RATE, (lead, _lead(x), n, rep["cards"])
        if not np.array_equal(x[lead:lead + n], d[:n]) and bay.n_xruns > xruns_after:
            # the server's notice of an xrun in the take came after _clean_take looked: it lost audio
            warnings.warn("the JACK server reported an xrun of the take late; the sample-exact comparisons "
                          "were skipped")
            return
        assert np.array_equal(x[lead:lead + n], d[:n]), (int(np.flatnonzero(x[lead:lead + n] != d[:n])[0]),
                                                         bay.n_xruns, xruns_after, rep["cards"])
    # replaying the fixture's own files, with the lead of silence the card delivered before the playback started
    # and the same length, gives the live output exactly (the engine's result depends on where its hops fall
    # in the signal, so the lead must be the same: with 100 samples instead of 1408, SI-SDR moved by -4.7 dB)
    files = []
    for k, (x, d) in enumerate(zip(rec, sig.T)):
        files.append(tmp_path / f"fx{k}.wav")
        sf.write(files[-1], np.r_[np.zeros(lead, np.float32), d, np.zeros(len(x) - lead - len(d), np.float32)]
                 if len(x) >= lead + len(d) else np.r_[np.zeros(lead, np.float32), d][:len(x)], RATE, subtype="FLOAT")
    ref = run_replay(files, tmp_path / "replay", overrides=[(dict(LIVE_DEFAULTS, plots=False), "test")])
    np.testing.assert_array_equal(ref.pipeline.enhanced_signal(), y_live)


def test_live_in_batches_wakes_once_a_batch_and_gives_what_its_recording_replays_to(jack, bay, tmp_path):
    """``batch_s``: the cards' audio is handed out once 32 ms are there (4 periods of 128 samples), not every
    period; nothing is lost (no ring gaps, the recording holds the whole signal) and the output is what replaying
    the recording gives, sample for sample."""
    from stream.live import run_live
    from stream.run import run_replay
    fx = load_fixture(REPO_FIXTURES / "meeting_table")
    sig = np.stack([sf.read(d.path, dtype="float32")[0] for d in fx.devices], axis=1)[: 5 * RATE]

    def take():
        shutil.rmtree(tmp_path / "live", ignore_errors=True)
        shutil.rmtree(tmp_path / "take", ignore_errors=True)
        _feed(bay, sig, 6, output=True, delay_s=WHOLE_DELAY_S)
        return run_live([f"system:{k + 1}" for k in range(6)], tmp_path / "live", output="system",
                        record=tmp_path / "take", max_duration_s=5.5, status=False, batch_s=0.032,
                        names=[d.name for d in fx.devices])

    def whole(_) -> bool:   # the capture started before the playback (as in the test above)
        return _lead(sf.read(tmp_path / "take" / f"dev00_{fx.devices[0].name}.wav", dtype="float32")[0]) > 0

    live, clean = _clean_take(bay, take, whole=whole)
    rep = live.report
    assert rep["status"] == "ok", rep.get("error")
    cards = rep["cards"]
    assert cards["batch_s"] == 0.032
    audio_s = rep["stream"]["audio_s"]
    # once a batch (a late card lets a batch go 20 ms after it was due), not once a period (8 ms: about 690)
    assert audio_s / 0.052 - 5 <= cards["n_handouts"] <= 1.1 * audio_s / 0.032 + 5, (cards["n_handouts"], audio_s)
    assert all(c["n_gaps"] == 0 for c in cards["inputs"]), cards
    assert bay.n_recorded > 0 and np.abs(bay.recorded[:bay.n_recorded]).max() > 0.01
    again = run_replay([tmp_path / "take"], tmp_path / "again", overrides=[({"plots": False}, "test")])
    np.testing.assert_array_equal(sf.read(tmp_path / "live" / "enhanced.wav", dtype="float32")[0],
                                  sf.read(tmp_path / "again" / "enhanced.wav", dtype="float32")[0])
    if clean:   # without a server xrun the recording is the whole signal, after the card's lead of silence
        rec = sf.read(tmp_path / "take" / f"dev00_{fx.devices[0].name}.wav", dtype="float32")[0]
        lead = _lead(rec)
        assert np.array_equal(rec[lead:lead + len(sig)], sig[: len(rec) - lead, 0])


def test_a_batch_out_of_range_is_one_sentence_before_any_card_opens(tmp_path, capsys):
    from stream.cli import main
    assert main(["live", "--input", "system", "--out", str(tmp_path / "o"), "--batch-s", "2"]) == 2
    assert "--batch-s 2.0 must be in 0..1 seconds" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def _valid_outputs(out: Path, rec: Path | None = None) -> dict:
    report = json.loads((out / "report.json").read_text())
    info = sf.info(str(out / "enhanced.wav"))
    assert info.frames >= 0 and info.samplerate == RATE
    rows = (out / "toa.csv").read_text().splitlines()
    assert rows[0].startswith("time_s,")
    if rec is not None:
        for f in sorted(rec.glob("*.wav")):
            assert sf.info(str(f)).frames > 0
    return report


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_ends_the_live_stream_with_valid_files(jack, tmp_path, sig):
    """adhoc-array live in its own process: Ctrl-C or SIGTERM once it streams; exit 0, every file valid."""
    out, rec = tmp_path / "out", tmp_path / "rec"
    env = dict(os.environ, JACK_DEFAULT_SERVER=jack.name)
    proc = subprocess.Popen([sys.executable, "-X", "faulthandler", "-m", "stream.cli", "live", "--input", "system:1",
                             "--input",
                             "system:2", "--out", str(out), "--record", str(rec), "--no-status", "--no-plots"],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t_end = time.monotonic() + 60
    while time.monotonic() < t_end and proc.poll() is None:
        files = list(rec.glob("*.wav")) if rec.exists() else []
        if files and all(f.stat().st_size > 44 + 4 * RATE for f in files):   # > 1 s recorded
            break
        time.sleep(0.1)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(sig)
    try:
        stdout, stderr = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:   # show where it hangs: faulthandler dumps every thread on SIGABRT
        proc.send_signal(signal.SIGABRT)
        stdout, stderr = proc.communicate(timeout=30)
        pytest.fail(f"live did not stop within 60 s of {sig.name}:\n{stderr[-4000:]}")
    assert proc.returncode == 0, stderr
    report = _valid_outputs(out, rec)
    assert report["status"] == "ok" and report["stopped_by"] == sig.name
    assert f"stopped by {sig.name}" in stdout
    assert sf.info(str(sorted(rec.glob("*.wav"))[0])).duration >= 0.9


def test_a_source_that_raises_mid_stream_leaves_valid_files_and_says_why(jack, bay, tmp_path):
    from stream.cards import CardSource
    from stream.config import EngineConfig
    from stream.live import LIVE_DEFAULTS
    from stream.run import run_stream

    class Failing(CardSource):
        def __iter__(self):
            for k, frame in enumerate(super().__iter__()):
                if frame.first_sample > 6 * RATE:
                    raise OSError("the USB cable was pulled")
                yield frame

    rng = np.random.default_rng(5)
    sig = (0.1 * rng.standard_normal((10 * RATE, 2))).astype(np.float32)
    _feed(bay, sig, 2)
    cfg = EngineConfig(**LIVE_DEFAULTS, plots=False)
    with pytest.raises(OSError, match="cable"):
        run_stream(Failing(["system:1", "system:2"]), tmp_path / "out", config=cfg, handle_signals=False)
    report = _valid_outputs(tmp_path / "out")
    assert report["status"] == "failed" and "the USB cable was pulled" in report["error"]
    assert sf.info(str(tmp_path / "out" / "enhanced.wav")).duration > 1.0


def test_a_card_that_stops_is_ended_in_one_sentence(jack, bay, tmp_path):
    """The card's stream really stops mid-run (as when it is unplugged): the source ends that device with a
    message and the outputs are written."""
    from stream.cards import CardSource
    from stream.config import EngineConfig
    from stream.live import LIVE_DEFAULTS
    from stream.run import run_stream
    rng = np.random.default_rng(6)
    _feed(bay, (0.1 * rng.standard_normal((20 * RATE, 2))).astype(np.float32), 2)

    class Unplugged(CardSource):
        def _drain(self, card, seq):   # once 6 s are captured, the card's stream stops for real
            if card.n_consumed_clock >= 6 * RATE and card.stream.active:
                card.stream.stop()
            yield from super()._drain(card, seq)

    src = Unplugged(["system:1", "system:2"], stall_s=0.5)
    outcome = run_stream(src, tmp_path / "out", config=EngineConfig(**LIVE_DEFAULTS, plots=False),
                         handle_signals=False)
    problems = [p for d in outcome.report["devices"] for p in d["problems"]]
    assert any("stopped delivering audio after" in p and "the stream goes on without it" in p for p in problems)
    assert outcome.report["stream"]["audio_s"] >= 6.0
    _valid_outputs(tmp_path / "out")


def test_a_card_that_stops_while_another_delivers_is_ended_in_one_sentence(jack, bay, tmp_path):
    """Two cards (two PortAudio streams on the server: each --input opened as a card of its own), and one stops
    for real after 4 s while the other goes on delivering: that card is ended with its sentence within about
    ``stall_s``, and the stream goes on with the other."""
    from stream.cards import CardSource
    from stream.config import EngineConfig
    from stream.live import LIVE_DEFAULTS
    from stream.run import run_stream
    rng = np.random.default_rng(7)
    _feed(bay, (0.1 * rng.standard_normal((20 * RATE, 2))).astype(np.float32), 2)

    class TwoCards(CardSource):
        def open(self):   # the server's one card opened once per --input: two streams, two clocks to the engine
            super().open()
            card = self._cards[0]
            if len(card.devices) == 2:
                from stream.cards import _Card
                other = _Card(card.info, card.n_channels, card.rate_hz, card.block_samples)
                other.devices, other.columns = [card.devices.pop()], [card.columns.pop()]
                other.stream = self._open_stream(other)
                self._cards.append(other)

        def _drain(self, card, seq):   # once 4 s are captured, the second card's stream stops for real
            if card is self._cards[1] and card.n_consumed_clock >= 4 * RATE and card.stream.active:
                card.stream.stop()
            yield from super()._drain(card, seq)

    src = TwoCards(["system:1", "system:2"], stall_s=0.5, max_duration_s=9.0)
    outcome = run_stream(src, tmp_path / "out", config=EngineConfig(**LIVE_DEFAULTS, plots=False),
                         handle_signals=False)
    assert len(src._cards) == 2
    problems = outcome.report["devices"][1]["problems"]
    assert any(re.search(r"card 'system' stopped delivering audio after 4\.\d\d s \(its stream stopped",
                         p) and "the stream goes on without it" in p for p in problems), problems
    assert not outcome.report["devices"][0]["problems"]
    assert outcome.report["stream"]["audio_s"] >= 8.5
    _valid_outputs(tmp_path / "out")


def test_bad_cards_are_one_sentence_each_and_the_rest_streams(jack, bay, tmp_path):
    from stream.cards import CardSource
    from stream.config import EngineConfig
    from stream.live import LIVE_DEFAULTS
    from stream.run import run_stream
    with pytest.raises(StreamError, match="None of the 1 inputs could be read"):
        run_stream(CardSource(["no such card"]), tmp_path / "a", config=EngineConfig(plots=False),
                   handle_signals=False)
    rep = json.loads((tmp_path / "a" / "report.json").read_text())
    assert "No input sound card matches 'no such card'; available: [0] system" in rep["devices"][0]["problems"][0]
    with pytest.raises(StreamError):
        run_stream(CardSource(["system"], sample_rate_hz=44100), tmp_path / "b", config=EngineConfig(plots=False),
                   handle_signals=False)
    rep = json.loads((tmp_path / "b" / "report.json").read_text())
    assert "cannot record 8 channels at 44100 Hz" in rep["devices"][0]["problems"][0]
    # a bad channel next to a good card: one sentence, and the good one streams
    rng = np.random.default_rng(7)
    _feed(bay, (0.1 * rng.standard_normal((8 * RATE, 1))).astype(np.float32), 1)
    src = CardSource(["system:1", "system:9"], max_duration_s=5.0)
    out = run_stream(src, tmp_path / "c", config=EngineConfig(**LIVE_DEFAULTS, plots=False), handle_signals=False)
    assert out.report["status"] == "ok" and out.pipeline.n_devices == 1
    assert "channel 9 does not exist" in out.report["devices"][1]["problems"][0]


def test_missing_portaudio_is_one_sentence_with_the_fix():
    """Where the PortAudio library cannot be found, the live commands say what to install."""
    code = ("import ctypes.util, sys\n"
            "real = ctypes.util.find_library\n"
            "ctypes.util.find_library = lambda n: None if 'portaudio' in n else real(n)\n"
            "from stream.cli import main\n"
            "sys.exit(main(['devices']))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert r.stderr.strip().startswith("adhoc-array: Sound cards need the PortAudio library")
    assert "apt-get install libportaudio2" in r.stderr and "Traceback" not in r.stderr


def test_no_sound_card_is_one_sentence(tmp_path):
    """No card visible (no JACK server of that name, no ALSA card here): devices and live each say so."""
    env = dict(os.environ, JACK_DEFAULT_SERVER="adhoc-no-such-server")
    r = subprocess.run([sys.executable, "-m", "stream.cli", "devices"], env=env, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 1 and "no sound card is visible to PortAudio" in r.stderr
    r = subprocess.run([sys.executable, "-m", "stream.cli", "live", "--input", "USB", "--out", str(tmp_path)],
                       env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().startswith("adhoc-array: No input sound card is visible to PortAudio")


@pytest.mark.parametrize("period, margin, used", [(128, 160, 128), (256, 160, 0), (1024, 480, 0), (1024, 1200, 1024)])
def test_the_output_margin_is_whole_card_periods_and_covers_a_loop_that_is_late(period, margin, used):
    """The card takes a period per callback and the stream loop answers each capture callback with one hop:
    it has one period, plus the margin. A margin shorter than a period protects nothing (the late hop's
    callback finds too little either way) and would only add latency, so the margin is whole periods: a loop
    late by less than margin + period loses nothing, and the queue then holds the margin, not more."""
    from stream.cards import _OutputRing
    ring = _OutputRing(16 * period)
    ring.margin_samples = ring.prime_samples = margin
    out = np.zeros((period, 1), np.float32)
    hop = np.arange(period, dtype=np.float32)

    def cycle(n_hops: int = 1) -> None:   # one server cycle: the playback callback, then the loop's hops
        ring.take(out, period)
        for _ in range(n_hops):
            ring.buf[ring.n_written % ring.capacity:][:period] = hop
            ring.n_written += period

    for _ in range(2 + used // period):   # the first hops: playing starts with a period and the margin queued
        cycle()
    assert ring.prime_samples == used and ring.n_underflows == 0
    assert ring.n_written - ring.n_read == used + period          # after this cycle's hop: the margin and a hop
    for _ in range(10):
        cycle()
    assert ring.n_written - ring.n_read == used + period and ring.n_underflows == 0
    cycle(0)                                                      # one hop a period late: it comes with the next
    cycle(2)
    cycle()
    assert ring.n_underflows == (0 if used else 1)
    if used:
        assert ring.n_written - ring.n_read == used + period
    else:   # when it happened, in the card's time: the callback of the late cycle
        n_cycles = 2 + used // period + 10 + 2
        assert ring.underflows.first == ring.underflows.last == n_cycles * period


def test_the_summary_says_when_a_card_overflowed(tmp_path):
    """The closing summary names each card's overflows and the output's underflows and, when there were some,
    when they came (card time),
    so that a user can tell a start-up hiccup from a machine that cannot keep up."""
    from stream.cli import summary
    inputs = [{"name": "phone", "card": "system", "channels": [1], "sample_rate_hz": 16000, "n_overflows": 3,
               "overflows_s": [1.25, 7.5], "n_gaps": 0},
              {"name": "laptop", "card": "system", "channels": [2], "sample_rate_hz": 16000, "n_overflows": 0,
               "overflows_s": None, "n_gaps": 0}]
    output = {"card": "system", "n_underflows": 2, "underflows_s": [61.25, 300.5], "n_dropped_samples": 0}
    text = summary({"cards": {"inputs": inputs, "output": output}}, tmp_path)
    assert "phone (system ch 1, 16000 Hz, 3 overflows (1.2-7.5 s), 0 gaps)" in text
    assert "laptop (system ch 2, 16000 Hz, 0 overflows, 0 gaps)" in text
    assert "output system: 2 underflows (61.2-300.5 s);" in text
