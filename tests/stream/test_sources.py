"""Several sources end to end (estimator = "tracks"): speech presence, the steered talker, no speech at all."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from stream.config import EngineConfig
from stream.scoring.fixture import load_fixture
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
    assert sp.backend == "silero"
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
        # b gets the same samples in hops of varying size (decisions on the same 32 ms windows)
        pb, k = [], 0
        for n in [hop // 2, hop + hop // 2] * (len(y) // (2 * hop)):
            pb.append(b.process(y[k:k + n, None]).probability)
            k += n
        assert np.mean(pa) > 0.3
        assert a.backend == "silero"
        assert abs(np.mean(pa) - np.mean(pb[:len(pa)])) < 0.05


def test_the_engines_silero_model_gives_the_two_rate_models_decisions():
    """``silero_vad_8k.onnx`` (``tools/silero_8k.py``: the shipped two-rate model with its rate fixed at 8 kHz
    and its convolutions as matrix products) against ``silero_vad.onnx`` itself at 8 kHz, over 3 s of the
    fixture's five devices in one batched call per 32 ms window, the state carried from window to window (the
    tool's own check, :func:`compare`): every speech probability within 1e-5, every hysteresis decision the
    same."""
    import importlib.util

    import onnxruntime as ort
    import soxr
    from stream.speech import SILERO_MODEL

    spec = importlib.util.spec_from_file_location("silero_8k", FIXTURE.parents[1] / "tools" / "silero_8k.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    fx = load_fixture(FIXTURE)
    x = np.stack([soxr.resample(sf.read(d.path, dtype="float32", frames=3 * 16000)[0], 16000, 8000)
                  for d in fx.devices]).astype(np.float32)
    two_rate, fixed = (ort.InferenceSession(str(p), providers=["CPUExecutionProvider"])
                       for p in (SILERO_MODEL.parent / "silero_vad.onnx", SILERO_MODEL))
    p = tool.compare(two_rate, fixed, x)   # raises unless within 1e-5 with the same decisions
    assert p.shape == (x.shape[1] // 256, len(x))
    assert np.mean(p >= 0.5) > 0.3   # the comparison saw speech, not only silence


def test_silero_rejects_a_kitchen_noise_that_webrtc_takes_for_speech():
    """The reason Silero is the default: the real kitchen recording alone (kitchen_noise's first 2 s, before
    the talker) is no speech to Silero, while WebRTC fires on it."""
    fx = load_fixture(FIXTURE.parent / "kitchen_noise")
    x, fs = sf.read(fx.devices[0].path, dtype="float32", frames=int(1.9 * 16000))
    hop = 128
    rates = {}
    for backend in ("silero", "webrtc"):
        sp = SpeechPresence(1, sample_rate_hz=fs, hop_samples=hop, backend=backend)
        rates[backend] = np.mean([sp.process(x[k * hop:(k + 1) * hop, None]).probability
                                  for k in range(len(x) // hop)])
    assert rates["silero"] < 0.1 < rates["webrtc"], rates


def test_missing_onnxruntime_falls_back_to_webrtc_and_says_so(monkeypatch, caplog):
    monkeypatch.setitem(__import__("sys").modules, "onnxruntime", None)   # `import onnxruntime` raises ImportError
    with caplog.at_level("WARNING"):
        sp = make_speech_presence(2, sample_rate_hz=16000, hop_samples=160)
    assert sp.backend == "webrtc"
    assert "onnxruntime" in caplog.text and "falls back to WebRTC" in caplog.text


def test_energy_fallback_when_asked_and_bad_backend_raises():
    sp = make_speech_presence(2, sample_rate_hz=16000, hop_samples=160, backend="energy")
    assert sp.backend == "energy"
    rng = np.random.default_rng(0)
    quiet = [sp.process(1e-3 * rng.standard_normal((160, 2)).astype(np.float32)).probability for _ in range(200)]
    loud = [sp.process(0.3 * rng.standard_normal((160, 2)).astype(np.float32)).probability for _ in range(5)]
    assert np.mean(quiet[100:]) < 0.2 and loud[-1] == 1.0
    with pytest.raises(ValueError, match="backend"):
        make_speech_presence(2, sample_rate_hz=16000, hop_samples=160, backend="bogus")


def test_tracks_steer_at_the_talker_of_a_fixture(tmp_path):
    out = tmp_path / "o"
    outcome = run_replay([FIXTURE], out, config=EngineConfig(estimator="tracks", **FAST))
    report = json.loads((out / "report.json").read_text())
    sources = report["sources"]
    assert any(t["kind"] == "speech" for t in sources["tracks"]) and sources["switches"]
    assert sources["speech_presence"]["backend"] == "silero"
    assert sources["speech_presence"]["rate_hz"] == 8000      # the detector's rate, whatever the working rate
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


def test_two_talkers_taking_turns_the_beam_follows_each_turn(tmp_path):
    """The shipped two_talkers fixture (A, B, A, B around a table, a fan above it): both talkers get a track,
    the beam is on the active talker in most speech frames, every turn change moves it within 1 s, and the
    sources plot is written."""
    fixture = FIXTURE.parent / "two_talkers"
    out = tmp_path / "o"
    outcome = run_replay([fixture], out, config=EngineConfig(estimator="tracks", progress=False))
    assert (out / "sources.png").stat().st_size > 10_000
    report = json.loads((out / "report.json").read_text())
    steered = [t for t in report["sources"]["tracks"] if t["kind"] == "speech" and t["steered_s"] > 1.0]
    assert len(steered) >= 2
    fx = load_fixture(fixture)
    time_s, toa_s, _ = outcome.pipeline.toa_track()
    active, speaking = fx.activity_at(time_s)
    err = np.stack([np.abs((toa_s - toa_s[:, :1]) - (tr - tr[:, :1])).max(axis=1)
                    for tr in (fx.source_toa_at(s.name, time_s) for s in fx.sources if not s.is_noise)])
    on = err[active, np.arange(len(time_s))] <= 2.5e-4
    talking = speaking[np.arange(len(time_s)), active] & (time_s > 2.5)
    assert on[talking].mean() > 0.8, on[talking].mean()
    hop_s = time_s[1] - time_s[0]
    for c in np.flatnonzero(np.diff(active) != 0) + 1:
        run = np.convolve(on[c:].astype(int), np.ones(5, int), "valid")   # 5 frames on the new talker
        assert (run == 5).any() and np.argmax(run == 5) * hop_s < 1.0, (time_s[c], np.argmax(run == 5) * hop_s)
    # sources.png draws a track solid where it was heard and faint where it is only predicted: the per-frame
    # flag is in step with the track's times, and some track goes unheard for a while (a talker between turns)
    tracks = outcome.pipeline.state.source_tracks
    assert all(len(h["heard"]) == len(h["time_s"]) == len(h["toa_s"]) for h in tracks.values())
    assert any(not all(h["heard"]) for h in tracks.values()) and all(any(h["heard"]) for h in tracks.values())


def test_without_a_talker_or_a_noise_source_the_output_is_the_devices_average(tmp_path):
    """No talker and no point noise source (bursts of diffuse noise: the same rhythm at every device, unrelated
    waveforms): the output is the average of the aligned devices, so the noise heard is about 1 / M of one
    device's; where a tracked noise source would be beamed at, it is the reference device (the test above)."""
    fs, n_dev, dur = 16000, 4, 6.0
    rng = np.random.default_rng(11)
    t = np.arange(int(dur * fs)) / fs
    rhythm = (np.sin(2 * np.pi * 1.3 * t) > 0.2) * 0.9 + 0.1   # loud / quiet: the envelope the aligner uses
    paths = []
    for d, lead in enumerate((0, 900, 2500, 4100)):
        x = (0.05 * rhythm * rng.standard_normal(len(t)))[lead:].astype(np.float32)
        paths.append(tmp_path / f"d{d}.wav")
        sf.write(paths[-1], x, fs, subtype="FLOAT")
    out = tmp_path / "o"
    outcome = run_replay(paths, out, config=EngineConfig(estimator="tracks", **FAST))
    s = outcome.pipeline.state
    report = json.loads((out / "report.json").read_text())
    assert not any(t["kind"] in ("speech", "noise") for t in report["sources"]["tracks"])
    assert set(s.track_id) == {-1}
    assert all(report["stream"]["aligned"])
    w = np.vstack(s.weights)[np.vstack(s.valid).all(axis=1)]
    # the default "level" weights: the devices' floors are alike here, so the weights are nearly equal
    assert len(w) > 200 and np.allclose(w, 1.0 / n_dev, rtol=0.1)
    y, _ = sf.read(out / "enhanced.wav", dtype="float32")
    x0, _ = sf.read(paths[0], dtype="float32")
    quiet = np.mean(y[fs:-fs] ** 2) / np.mean(x0[fs:len(y) - fs] ** 2)
    assert 0.5 / n_dev < quiet < 2.0 / n_dev, quiet


def test_a_stream_that_steers_at_no_talker_in_much_of_its_speech_says_so(tmp_path):
    """`kitchen_noise` (dishes from 2 s before the talker, five devices): the tracker steers at no talker in about
    1.2 s of the 2.9 s its speech detector calls speech (measured: 48 of the 136 frames of the talker's speech,
    at 5.5-6.2 s among them), so the output there is not steered at the talker, and one sentence says how much
    and what the output was instead; `meeting_table`, steered from its first words, says nothing."""
    from estimators.tracks import UNSTEERED_SHARE_MAX
    kitchen = run_replay([FIXTURE.parent / "kitchen_noise"], tmp_path / "k", config=EngineConfig(**FAST))
    src = kitchen.report["sources"]
    said = [m for m in kitchen.report["messages"] if m.startswith("No talker was tracked in")]
    assert len(said) == 1 and f"{src['unsteered_speech_s']:.1f} s of the {src['speech_s']:.1f} s" in said[0]
    assert src["unsteered_speech_s"] > UNSTEERED_SHARE_MAX * src["speech_s"]
    assert "the output is the average of the aligned devices" in said[0]
    # the per-frame record (toa.csv) agrees within the tracker's look-ahead (measured 1.09 s there against the
    # tracker's own 1.22 s: eight 16 ms frames, as long as the 0.128 s look-ahead)
    steered = np.asarray(kitchen.pipeline.state.track_id) >= 0
    speech = np.asarray(kitchen.pipeline.state.speech_probability) >= 0.5
    frame = kitchen.pipeline.tracker.frame_period_s
    assert np.sum(speech & ~steered) * frame == pytest.approx(
        src["unsteered_speech_s"], abs=kitchen.pipeline.config.tracker_lookahead_s + 2 * frame)
    table = run_replay([FIXTURE], tmp_path / "t", config=EngineConfig(**FAST))
    assert table.report["sources"]["unsteered_speech_s"] < 0.1
    assert not any(m.startswith("No talker") for m in table.report["messages"])


def _with_noise_device(tmp_path: Path, device: int) -> Path:
    """A copy of the meeting_table fixture in which one device records only white noise (a covered or broken mic,
    a phone in a pocket next to a fan)."""
    import shutil
    folder = tmp_path / "fx"
    shutil.copytree(FIXTURE, folder)
    path = folder / f"dev{device:02d}.flac"
    x, fs = sf.read(path, dtype="float32")
    sf.write(path, 0.05 * np.random.default_rng(3).standard_normal(len(x)).astype(np.float32), fs, subtype="PCM_16")
    return folder


def test_a_device_that_hears_only_noise_leaves_the_talker_tracked_on_the_others(tmp_path):
    folder = _with_noise_device(tmp_path, 3)
    outcome = run_replay([folder], tmp_path / "o", config=EngineConfig(**FAST))
    time_s, toa_s, _ = outcome.pipeline.toa_track()
    truth = load_fixture(folder).truth_toa_at(time_s)
    truth -= truth[:, :1]
    steered = np.asarray(outcome.pipeline.state.track_id) >= 0
    late = time_s > 2.0
    assert steered[late].mean() > 0.9
    others = [0, 1, 2, 4, 5]
    err = np.abs(toa_s[:, others] - truth[:, others]).max(axis=1)
    assert np.mean(err[late & steered] <= 2.5e-4) > 0.9
    enh = outcome.report["metrics"]["enhancement"]
    assert enh["engine"]["si_sdr_db"] > enh["best_single_device"]["si_sdr_db"] + 3.0
    # the report shows which device the talker's track does not measure: device 3 is never usable, every other
    # device takes part in nearly every hit, and the reference is not said to hear the talker poorly
    share = outcome.report["sources"]["device_matched_share"]
    assert share[3] is None and min(share[d] for d in others) > 0.9
    assert not any("took part in only" in m for m in outcome.report["messages"])


def test_a_reference_that_hears_only_noise_is_left_out_and_the_others_are_aligned_on_each_other(tmp_path):
    """Device 0 (the reference the offsets are measured against) hears only noise: every other device used to be
    left out for sharing no sound with it, and the output was that noise. Now the offsets are measured against the
    device that shares its sound with the most others, device 0 is left out, and the output equals the run without
    device 0 at all (whose reference is device 1), with one sentence saying why."""
    folder = _with_noise_device(tmp_path, 0)
    files = sorted(folder.glob("dev*.flac"))
    a = run_replay(files, tmp_path / "a", config=EngineConfig(**FAST))
    b = run_replay(files[1:], tmp_path / "b", config=EngineConfig(**FAST))
    report = json.loads((tmp_path / "a" / "report.json").read_text())
    assert report["stream"]["aligned"] == [False, True, True, True, True, True]
    assert any("reference device 0 shares no clear sound" in m and "measured against device 1" in m
               for m in report["messages"])
    assert not any("No speech" in m for m in report["messages"])
    # left out, it is in none of the talker track's measurements: not a reference that hears poorly
    assert report["sources"]["device_matched_share"][0] is None
    assert not any("took part in only" in m for m in report["messages"])
    without = json.loads((tmp_path / "b" / "report.json").read_text())["stream"]["coarse_offsets_s"]
    assert report["stream"]["coarse_offsets_s"][1:] == without
    assert np.mean(np.asarray(a.pipeline.state.track_id) >= 0) > 0.9
    ya, fs = sf.read(tmp_path / "a" / "enhanced.wav", dtype="float32")
    yb, _ = sf.read(tmp_path / "b" / "enhanced.wav", dtype="float32")
    n = min(len(ya), len(yb))
    mid = slice(2 * fs, n - fs)
    # measured 0.99993 with one 0.1 s cross-power average, 0.99714 since its time constant follows the pair's SNR:
    # the speech detector's batch of 6 devices rounds differently from a batch of 5, the noise averages differ in
    # the last digits, and the tracker's discrete steps (gates, births) carry that to TOAs up to 0.2 ms apart in
    # some frames. Device 0's noise itself would not correlate at all.
    assert np.corrcoef(ya[mid], yb[mid])[0, 1] > 0.995


def test_sources_plot_draws_a_track_in_the_label_it_had_at_each_time(tmp_path):
    """A noise source of the pauses that turned talker at 2 s, then noise again at 3.5 s: the plot draws it as
    noise, then as a talker, then as noise (``label_over_time``), with the changes marked; a track never
    relabelled keeps its one label."""
    from stream.scoring.plots import label_over_time, plot_source_tracks

    t = np.arange(0.0, 5.0, 0.016)
    relabels = [(2.0, "noise", "speech", "louder when somebody speaks"), (3.5, "speech", "noise", "in the pauses")]
    label = label_over_time(t, "noise", relabels)
    assert set(label[t < 2.0]) == {"noise"} and set(label[(t >= 2.0) & (t < 3.5)]) == {"speech"}
    assert set(label[t >= 3.5]) == {"noise"}
    assert set(label_over_time(t, "speech")) == {"speech"}
    toa = [np.array([0.0, 1e-3, -2e-3])] * len(t)
    tracks = {4: {"kind": "noise", "time_s": list(t), "toa_s": toa, "heard": [True] * len(t), "relabels": relabels},
              5: {"kind": "speech", "time_s": list(t), "toa_s": [x + np.array([0.0, 5e-4, 5e-4]) for x in toa],
                  "heard": [True] * len(t)}}
    path = plot_source_tracks(tmp_path / "sources.png", tracks=tracks, time_s=t,
                              steered_id=np.where((t >= 2.0) & (t < 3.5), 4, 5))
    assert path.stat().st_size > 10_000


def test_toa_plot_says_where_an_estimate_is_beyond_the_truths_view(tmp_path):
    """The TOA panel's view is the truth's (fractions of a millisecond); an estimate 12 ms off (a coarse
    alignment on the wrong peak) is drawn at the view's edge and the panel says in how many frames and how far,
    instead of showing only the truth."""
    from stream.scoring.plots import outside_view_note, plot_toa_tracks

    t = np.arange(0.0, 4.0, 0.016)
    true = np.array([0.0, -0.518, 0.295])
    est = np.tile(true, (len(t), 1))
    est[t >= 1.0, 1] -= 0.0127                   # device 1: 12.7 ms early from 1 s on (75 % of the frames)
    est[:, 2] += 1e-4                            # device 2: within the view
    assert outside_view_note(1e3 * (est[:, 2] - true[2]), 0.5) == ""
    note = outside_view_note(1e3 * (est[:, 1] - true[1]), 0.5)
    assert note == "estimate beyond this view in 75 % of frames (-12.7 to -12.7 ms)"
    assert outside_view_note(np.array([np.nan, 0.1]), 0.5) == ""
    path = plot_toa_tracks(tmp_path / "toa.png", time_s=t, toa_s=est, true_toa_s=true,
                           device_names=["a", "b", "c"])
    assert path.stat().st_size > 10_000


def test_the_beam_weighs_each_device_by_how_well_it_hears_the_steered_talker(tmp_path):
    """``level_height_exponent``: every talker track keeps each device's mean matched GCC peak height over its
    pairs (``report.json`` ``device_peak``); the beam multiplies each device's `level` weight by its height on the
    steered track over the median device's, to that power. On the two_talkers fixture (a fan above the table)
    the device the steered talker's peaks show least gets less weight than without it, the one they show most
    more, and the output is no worse."""
    fixture = FIXTURE.parent / "two_talkers"
    runs = {}
    for q in (0.0, 1.0):
        outcome = run_replay([fixture], tmp_path / f"q{q}",
                             config=EngineConfig(estimator="tracks", level_height_exponent=q, **FAST))
        runs[q] = (outcome, json.loads((tmp_path / f"q{q}" / "report.json").read_text()))
    outcome, report = runs[1.0]
    tracker = outcome.pipeline.tracker
    h = tracker.steered.device_height
    assert h is not None and np.isfinite(h).all()
    summary = next(t for t in report["sources"]["tracks"] if t["id"] == tracker.steered.track_id)
    np.testing.assert_allclose(summary["device_peak"], h, atol=1e-4)
    w0 = np.asarray(runs[0.0][1]["stream"]["final_channel_weights"])
    w1 = np.asarray(report["stream"]["final_channel_weights"])
    change = (w1 / np.median(w1)) / (w0 / np.median(w0))
    assert change[np.argmin(h)] < 1.0 < change[np.argmax(h)], (h, change)
    enh = {q: r["metrics"]["enhancement"]["engine"]["si_sdr_db"] for q, (_, r) in runs.items()}
    assert enh[1.0] > enh[0.0] - 0.1, enh
