"""The one stream loop: sample-index checks, bounded history, recordings, drift, the re-check worker, signals."""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import soundfile as sf
import soxr

from stream.condition import FrameChecker
from stream.config import EngineConfig
from stream.messages import Frame, FrameFlag
from stream.pipeline import History, HopTimes
from stream.replay import ReplaySource
from stream.run import run_replay, run_stream
from stream.sinks import RecordingSink
from tests.conftest import REPO_FIXTURES, bursty_source, delayed

FS = 16000


def test_history_is_bounded_spans_the_stream_and_keeps_lists_in_step():
    a, b = History(1000), History(1000)
    for k in range(100_000):
        a.append(k)
        b.append(-k)
    assert 500 <= len(a) <= 1000 and list(b) == [-v for v in a]
    steps = np.diff(np.asarray(a))
    # the whole stream, at one resolution (or two, while the older part is being thinned)
    assert a[0] == 0 and a[-1] > 99_000 - steps.max() and set(steps) <= {steps.max(), steps.max() // 2}
    # thinned a chunk per append: once done, the same records as dropping every other one at once
    c = History(1000)
    for k in range(1001):
        c.append(k)
    while c._thin_at < c._thin_end:
        c.append(c.n_appended)
    n_new = len(c) - 501
    assert list(c[:501]) == list(range(0, 1001, 2)) and list(c[501:]) == [1002 + 2 * i for i in range(n_new)]
    full, none = History(None), History(0)
    for k in range(10):
        full.append(k)
        none.append(k)
    assert list(full) == list(range(10)) and len(none) == 0


def test_hop_times_percentiles_match_numpy_to_the_bin():
    rng = np.random.default_rng(0)
    ms = rng.lognormal(-2.0, 0.8, 20_000)
    h = HopTimes()
    for v in ms:
        h.add(float(v))
    for q in (50, 99, 99.9):
        assert abs(h.percentile(q) - np.percentile(ms, q)) <= 2 * HopTimes.BIN_MS
    assert h.max_ms == pytest.approx(ms.max()) and h.n == len(ms)


def test_frame_checker_fills_gaps_drops_repeats_and_mixes_channels():
    c = FrameChecker()
    x = np.arange(20, dtype=np.float32).reshape(10, 2)
    f = c.process(Frame(0, 0, 0, FS, x))
    np.testing.assert_array_equal(f.samples, x.mean(axis=1))
    g = c.process(Frame(0, 1, 15, FS, np.ones(4, np.float32)))          # 5 samples lost
    assert g.flags & FrameFlag.GAP and g.first_sample == 10
    np.testing.assert_array_equal(g.samples, np.r_[np.zeros(5), np.ones(4)])
    h = c.process(Frame(0, 2, 17, FS, np.full(4, 2.0, np.float32)))     # 2 samples repeated
    assert h.first_sample == 19 and len(h.samples) == 2
    assert (c.counters.n_gaps, c.counters.n_gap_samples, c.counters.n_overlap_samples) == (1, 5, 2)


class _Withholding(ReplaySource):
    """Replays files but never delivers the frames of one device that start in ``[start_s, stop_s)`` of its
    clock (samples lost, as by a full ring, or held back, as by a stalled card or a lost network link): the
    device resumes with the index of its next sample, so the gap is in its clock."""

    def __init__(self, paths, *, device: int, start_s: float, stop_s: float, **kwargs) -> None:
        super().__init__(paths, **kwargs)
        self.withheld = (device, start_s * FS, stop_s * FS)

    def __iter__(self):
        device, start, stop = self.withheld
        for frame in super().__iter__():
            if frame.device_id == device and start <= frame.first_sample < stop:
                continue
            yield frame


def test_lost_samples_are_a_flagged_gap_left_out_of_the_beam(make_devices, tmp_path):
    paths, _, _ = make_devices([0.0, 0.0004, -0.0003], duration_s=8.0)
    cfg = EngineConfig(plots=False, progress=False, align_window_s=2.0, max_offset_s=0.5)
    ref = run_replay(paths, tmp_path / "ref", config=cfg)
    src = _Withholding(paths, device=1, start_s=3.0, stop_s=3.5, block_s=0.05)
    out = run_stream(src, tmp_path / "gap", config=cfg,
                     handle_signals=False)
    dev = out.report["devices"][1]
    assert dev["n_gaps"] == 1 and dev["n_gap_samples"] == FS // 2
    assert any("lost in 1 gaps" in p for p in dev["problems"])
    assert out.report["stream"]["n_blocks"] == ref.report["stream"]["n_blocks"]       # nothing shifted
    lost = out.report["stream"]["n_invalid_device_blocks"] - ref.report["stream"]["n_invalid_device_blocks"]
    hop = out.pipeline.config.hop_samples
    assert 0.5 * FS / hop - 2 <= lost <= 0.5 * FS / hop + 2
    y = sf.read(tmp_path / "gap" / "enhanced.wav")[0]
    assert len(y) == len(sf.read(tmp_path / "ref" / "enhanced.wav")[0]) and np.isfinite(y).all()


def test_a_recording_folder_replays_as_its_files(make_devices, tmp_path):
    """RecordingSink writes what a source delivered (a 2-channel device, gaps as zeros); replaying the folder
    equals replaying the same files named one by one."""
    paths, _, _ = make_devices([0.0, 0.0005], duration_s=5.0)
    stereo = np.stack([sf.read(paths[1], dtype="float32")[0]] * 2, axis=1)
    stereo[:, 1] *= 0.5
    sf.write(tmp_path / "st.wav", stereo, FS, subtype="FLOAT")
    files = [paths[0], tmp_path / "st.wav"]
    src = ReplaySource(files, block_s=0.03)
    with src:
        rec = RecordingSink(tmp_path / "take", src.active, description="test")
        for frame in src:
            rec.write(frame)
        rec.close()
    info = sf.info(str(tmp_path / "take" / "dev01_st.wav"))
    assert info.channels == 2 and info.frames == len(stereo)
    cfg = EngineConfig(plots=False, progress=False)
    a = run_replay([tmp_path / "take"], tmp_path / "a", config=cfg)
    b = run_replay(files, tmp_path / "b", config=cfg)
    assert [d["name"] for d in a.report["devices"]] == ["dev0", "st"]
    np.testing.assert_array_equal(a.pipeline.enhanced_signal(), b.pipeline.enhanced_signal())


def test_the_report_states_each_devices_clock_drift(tmp_path):
    """60 s; device 1's clock runs 100 ppm fast: the stream observes 100 ± 5 ppm, device 2 (none) 0 ± 5 (the
    Kalman TOA: the source is noise bursts, which the default speech-aware tracker rightly does not steer at)."""
    n = 60 * FS
    src = bursty_source(n + FS, sample_rate_hz=FS, seed=3)
    rng = np.random.default_rng(0)
    noise = lambda: 1e-3 * rng.standard_normal(n).astype(np.float32)  # noqa: E731
    x1 = soxr.resample(delayed(src, 5.3, n + FS), FS, FS * (1 + 100e-6))[:n].astype(np.float32)
    xs = [src[:n] + noise(), x1 + noise(), delayed(src, -3.1, n) + noise()]
    paths = []
    for k, x in enumerate(xs):
        paths.append(tmp_path / f"d{k}.wav")
        sf.write(paths[-1], x, FS, subtype="FLOAT")
    out = run_replay(paths, tmp_path / "out", config=EngineConfig(plots=False, progress=False, estimator="kalman"))
    drift = out.report["stream"]["observed_drift_ppm"]
    assert drift[0] == 0.0 and abs(drift[1] - 100.0) < 5.0 and abs(drift[2]) < 5.0


def test_the_offset_re_check_runs_in_a_worker_and_is_reproducible(tmp_path):
    """Device 1 loses 0.2 s mid-stream (a dropout that shortened its recording): the periodic re-check finds
    the new offset; its result is applied a fixed stream time later, so block sizes do not change the output."""
    n = 20 * FS
    src = bursty_source(n + FS, sample_rate_hz=FS, seed=8)
    rng = np.random.default_rng(1)
    x0 = src[:n] + 1e-3 * rng.standard_normal(n).astype(np.float32)
    x1 = delayed(src, 40.0, n + FS)
    x1 = np.r_[x1[:8 * FS], x1[int(8.2 * FS):]][:n] + 1e-3 * rng.standard_normal(n).astype(np.float32)
    paths = [tmp_path / "a.wav", tmp_path / "b.wav"]
    sf.write(paths[0], x0, FS, subtype="FLOAT")
    sf.write(paths[1], x1, FS, subtype="FLOAT")
    cfg = dict(plots=False, progress=False, align_window_s=3.0, max_offset_s=1.0, align_recheck_s=2.0)
    a = run_replay(paths, tmp_path / "a", config=EngineConfig(**cfg, block_s=0.05))
    b = run_replay(paths, tmp_path / "b", config=EngineConfig(**cfg, block_s=0.013))
    moves = [e for e in a.report["stream"]["alignment_events"] if "re-check" in e["reason"]]
    assert moves and abs(moves[0]["new_offset_samples"] - moves[0]["old_offset_samples"] + 0.2 * FS) < 2
    assert 8.2 < moves[0]["time_s"] < 12.5
    np.testing.assert_array_equal(a.pipeline.enhanced_signal(), b.pipeline.enhanced_signal())


def test_sigterm_interrupts_a_paced_replay_and_writes_everything(tmp_path):
    cmd = [sys.executable, "-m", "stream.cli", "replay", "replay_fixtures/meeting_table", "--out", str(tmp_path),
           "--speed", "1.0", "--no-plots"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t_end = time.monotonic() + 60
    while time.monotonic() < t_end and not (tmp_path / "toa.csv").exists():
        time.sleep(0.05)
    time.sleep(1.0)
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 1, stderr
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["status"] == "interrupted" and report["stopped_by"] == "SIGTERM"
    assert "Stopped by SIGTERM" in report["error"] and "stopped by SIGTERM" in stdout
    info = sf.info(str(tmp_path / "enhanced.wav"))
    assert 0 < info.duration < 8.0
    rows = (tmp_path / "toa.csv").read_text().splitlines()
    assert len(rows) > 10


def test_the_smoothers_lag_is_honoured(tmp_path):
    """The fixed-lag smoother's TOA is `lag` frames old: the stream steers that frame's audio with it and stamps
    it with that frame's time, so its output lines up with the filter's and its rows carry the same times."""
    from tests.conftest import REPO_FIXTURES
    fx = REPO_FIXTURES / "meeting_table"
    base = dict(plots=False, progress=False)
    k = run_replay([fx], tmp_path / "k", config=EngineConfig(**base, estimator="kalman"))
    s = run_replay([fx], tmp_path / "s", config=EngineConfig(**base, estimator="smoother", smoother_lag_frames=6))
    assert s.pipeline.latency_samples == k.pipeline.latency_samples + 6 * s.pipeline.config.hop_samples
    tk, ts = (np.loadtxt(tmp_path / d / "toa.csv", delimiter=",", skiprows=1)[:, 0] for d in ("k", "s"))
    np.testing.assert_array_equal(tk, ts)
    yk, ys = k.pipeline.enhanced_signal(), s.pipeline.enhanced_signal()
    assert len(yk) == len(ys) == len(sf.read(tmp_path / "s" / "enhanced.wav")[0])
    from stream.scoring import metrics
    _, lag = metrics.align_to_reference(ys, yk, max_lag_samples=2000)
    assert lag == 0
    assert metrics.si_sdr_db(ys, yk) > 10.0
    assert s.report["metrics"]["enhancement"]["engine"]["si_sdr_db"] >= \
        k.report["metrics"]["enhancement"]["engine"]["si_sdr_db"] - 0.5


def test_a_re_check_over_the_silence_after_the_end_does_not_move_devices(tmp_path):
    """meeting_table followed by 4 s of digital silence (a live recording that went on after the talk), with the
    live settings: the re-check over a window that is half silence moves nothing, and the talker is tracked."""
    from stream.scoring.fixture import load_fixture
    from tests.conftest import REPO_FIXTURES
    fx = load_fixture(REPO_FIXTURES / "meeting_table")
    paths = []
    for d in fx.devices:
        x, rate = sf.read(d.path, dtype="float32")
        paths.append(tmp_path / f"{d.name}.wav")
        sf.write(paths[-1], np.r_[x, np.zeros(4 * rate, np.float32)], rate, subtype="FLOAT")
    cfg = EngineConfig(plots=False, progress=False, estimator="tracks", align_window_s=4.0, max_offset_s=0.5,
                       align_recheck_s=5.0)
    out = run_replay(paths, tmp_path / "out", config=cfg)
    assert out.report["stream"]["alignment_events"] == []
    ref = run_replay([REPO_FIXTURES / "meeting_table"], tmp_path / "ref", config=cfg)   # without the silence
    assert out.report["stream"]["coarse_offsets_s"] == ref.report["stream"]["coarse_offsets_s"]
    assert out.report["sources"]["n_speech_frames"] > 100
    assert any(t["kind"] == "speech" for t in out.report["sources"]["tracks"])


def test_tracks_on_plain_files_draw_every_plot(tmp_path):
    """A fixture's recordings named one by one (no fixture: no names, no truth): the sources plot is drawn
    too, and nothing warns."""
    from tests.conftest import REPO_FIXTURES
    paths = sorted((REPO_FIXTURES / "meeting_table").glob("dev*.flac"))
    out = run_replay(paths, tmp_path / "o", config=EngineConfig(estimator="tracks", progress=False))
    assert not [m for m in out.report["messages"] if "could not be drawn" in m]
    assert out.pipeline.state.source_tracks
    assert (tmp_path / "o" / "sources.png").is_file() and (tmp_path / "o" / "toa_tracks.png").is_file()


def test_output_wavs_may_outgrow_4_gib_and_stay_plain_wav_when_small(tmp_path):
    """enhanced.wav and recordings are opened as RF64 (no 4 GiB limit over a long session); a file that stayed
    small is an ordinary RIFF/WAVE file after closing."""
    from stream.sinks import WavSink
    w = WavSink(tmp_path / "e.wav", sample_rate_hz=FS)
    w.write_samples(np.ones(1000, np.float32))
    w.close()
    assert (tmp_path / "e.wav").read_bytes()[:4] == b"RIFF"
    x, rate = sf.read(tmp_path / "e.wav", dtype="float32")
    assert rate == FS and len(x) == 1000 and x.min() == 1.0


def test_a_late_device_does_not_stall_the_others(make_devices, tmp_path):
    """Paced at 4x real time, device 2 delivers nothing from 4 s to 7 s of the stream (0.75 s of wall time)."""
    paths, _, _ = make_devices([0.0, 0.0004, -0.0003], duration_s=10.0)
    cfg = EngineConfig(plots=False, progress=False, align_window_s=2.0, max_offset_s=0.5, device_deadline_s=0.25)
    src = _Withholding(paths, device=2, start_s=4.0, stop_s=7.0, block_s=0.05, speed=4.0)
    out = run_stream(src, tmp_path / "o", config=cfg,
                     handle_signals=False)
    st = out.report["stream"]
    hop = out.pipeline.config.hop_samples
    assert st["n_blocks"] == 10 * FS // hop
    # device 2 is left out of the blocks of its stall (3 s of stream; those waiting when the 0.25 s deadline
    # passed included); the others went on, and it was back right after
    assert 2.5 * FS / hop <= st["late_blocks"][2] <= 3.3 * FS / hop and st["late_blocks"][:2] == [0, 0]
    assert any("device 2 delivered nothing for 0.25 s while the others did" in m for m in out.report["messages"])
    valid = np.asarray(out.pipeline.state.valid)
    t = np.asarray(out.pipeline.state.time_s)
    assert valid[(t > 6.0) & (t < 6.8), 2].sum() == 0 and valid[t > 8.0, 2].mean() > 0.9


def test_leading_digital_silence_does_not_mislead_the_first_alignment(tmp_path):
    """Cards started 0.56 s before the room made a sound (every device's stream starts with digital silence):
    the first alignment finds the same offsets as without it, and no re-check has to repair them."""
    from stream.scoring.fixture import load_fixture
    from tests.conftest import REPO_FIXTURES
    fx = load_fixture(REPO_FIXTURES / "meeting_table")
    paths = []
    for d in fx.devices:
        x, rate = sf.read(d.path, dtype="float32")
        paths.append(tmp_path / f"{d.name}.wav")
        sf.write(paths[-1], np.r_[np.zeros(9000, np.float32), x], rate, subtype="FLOAT")
    cfg = EngineConfig(plots=False, progress=False, align_window_s=4.0, max_offset_s=0.5, align_recheck_s=5.0)
    out = run_replay(paths, tmp_path / "out", config=cfg)
    ref = run_replay([REPO_FIXTURES / "meeting_table"], tmp_path / "ref", config=cfg)
    assert out.report["stream"]["alignment_events"] == []
    np.testing.assert_allclose(out.report["stream"]["coarse_offsets_s"], ref.report["stream"]["coarse_offsets_s"],
                               atol=3 / FS)


def test_the_report_times_the_running_stream_apart_from_its_start(tmp_path):
    """``timing.running_cpu_share``: CPU over wall time from the first hop out to the end of the input, without
    the start-up (the first alignment's wait, the kernels) and the report; as fast as possible it is about one
    core on an idle machine (every thread counts: at most two here). The window is a few tens of milliseconds
    here, so another job on the machine can take most of it: only the bounds are tested."""
    rep = run_replay([REPO_FIXTURES / "walking_talker"], tmp_path, config=EngineConfig(plots=False, progress=False)).report
    t = rep["timing"]
    assert 0 < t["running_wall_s"] < t["wall_s"]
    assert 0 < t["running_cpu_share"] < 2.1, t
    assert t["running_cpu_share"] * t["running_wall_s"] <= t["cpu_s"], t


def test_scorings_true_toa_baselines_run_through_the_pipeline(tmp_path):
    """The baselines of the report (delay-and-sum at the true TOA) go through the engine's own stages:
    steering the run's aligned input by the TOA track the run itself used gives back its output, the smoother's
    lag included (to float rounding: the track is stored as coarse offset + fine TOA and split again here)."""
    from stream.pipeline import steer_aligned
    run = run_replay([REPO_FIXTURES / "meeting_table"], tmp_path,
                     config=EngineConfig(plots=False, progress=False, estimator="smoother", smoother_lag_frames=6))
    p = run.pipeline
    fs = p.config.working_rate_hz
    _, toa, _ = p.toa_track()
    fine = toa - np.vstack(p.state.offsets) / fs
    y = steer_aligned(p.config, np.vstack(p.state.aligned_input), fine, weighting=p.config.weighting,
                      valid=np.vstack(p.state.valid))
    np.testing.assert_allclose(y, p.enhanced_signal(), rtol=0, atol=1e-7)
    baselines = run.report["metrics"]["enhancement"]
    assert baselines["true_toa_sync_equal"]["si_sdr_db"] > baselines["engine"]["si_sdr_db"] - 1.0


def test_the_tracker_follows_a_drifting_clock_on_speech_and_the_report_states_it(tmp_path):
    """The tracker (replay's and live's default) on real speech: async_8dev's talker in its room, said six
    times (40 s), three of its devices; device 1's clock runs 100 ppm fast, device 2 started 0.7 s late. The
    stream observes 100 ± 5 ppm and 0 ± 5 ppm (measured: 99.9 and 0.0; over the frames it steered by: the
    frames without a talker hold the last TOA, and with them it said 91 ppm; kalman says 117 and 7.5 here)."""
    x, fs = sf.read(REPO_FIXTURES / "async_8dev" / "truth" / "sync.flac", dtype="float32", always_2d=True)
    x = soxr.resample(x[:, :3], fs, FS).astype(np.float32)
    x = np.concatenate([x] * 6)
    n = len(x) - FS
    rng = np.random.default_rng(4)
    noise = lambda: 1e-4 * rng.standard_normal(n).astype(np.float32)  # noqa: E731
    x1 = soxr.resample(x[:, 1], FS, FS * (1 + 100e-6))[:n].astype(np.float32)
    x2 = np.r_[np.zeros(int(0.7 * FS), np.float32), x[:, 2]][:n]
    paths = []
    for k, y in enumerate([x[:n, 0], x1, x2]):
        paths.append(tmp_path / f"d{k}.wav")
        sf.write(paths[-1], y + noise(), FS, subtype="FLOAT")
    out = run_replay(paths, tmp_path / "out", config=EngineConfig(plots=False, progress=False))
    assert out.report["settings"]["estimator"] == "tracks"
    drift = out.report["stream"]["observed_drift_ppm"]
    assert drift[0] == 0.0 and abs(drift[1] - 100.0) < 5.0 and abs(drift[2]) < 5.0, drift
    # the drift the noise spectra follow, measured from the cross-power spectra's rotation, without the tracks
    spectra = out.report["stream"]["spectra_drift_ppm"]
    print(spectra)
    assert spectra[0] == 0.0 and abs(spectra[1] - 100.0) < 5.0 and abs(spectra[2]) < 5.0, spectra


def test_level_weights_learn_from_the_speech_detectors_pauses_only(tmp_path):
    """``weighting="level"`` learns each device's floor in the pauses the speech detector finds: with the tracker on
    `kitchen_noise` (dishes from 2 s before the talker) the devices get unequal weights, each within 4 times the
    median's; an estimator without a detector has no pauses to learn from, and its output is equal weighting's to
    the bit."""
    fx = REPO_FIXTURES / "kitchen_noise"
    base = dict(plots=False, progress=False)
    t = run_replay([fx], tmp_path / "t", config=EngineConfig(**base, weighting="level"))
    w = np.asarray(t.report["stream"]["final_channel_weights"])
    assert w.sum() == pytest.approx(1.0, rel=1e-5)
    assert np.ptp(w) > 0.02 and np.all(w <= 4 * np.median(w) + 1e-6) and np.all(w >= np.median(w) / 4 - 1e-6)
    k = {wt: run_replay([fx], tmp_path / wt, config=EngineConfig(**base, estimator="kalman", weighting=wt))
         for wt in ("equal", "level")}
    np.testing.assert_array_equal(k["equal"].pipeline.enhanced_signal(), k["level"].pipeline.enhanced_signal())
