"""Replay end to end on synthetic devices with known delays, and every kind of bad input."""
import json
import logging
import os
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from stream.cli import main
from stream.config import EngineConfig
from stream.errors import ConfigError, InputFileError, StreamError
from stream.replay import DecoderMessages, ReplaySource, open_device_file
from stream.run import run_replay

FAST = dict(plots=False, progress=False, align_window_s=4.0, max_offset_s=2.5)


def _cfg(**kw):
    return EngineConfig(**{**FAST, **kw})


def _toa_after(outcome, t_min_s=2.0):
    time_s, toa_s, _ = outcome.pipeline.toa_track()
    return toa_s[time_s > t_min_s]


def test_known_delays_and_offsets_are_recovered(make_devices, tmp_path):
    # device 1 hears 2.5 ms later, device 2 starts 1.3 s earlier (so hears it 1.3 s "later" on its clock)
    toa = [0.0, 0.0025, 1.3 - 0.001, -0.7]
    paths, _, _ = make_devices(toa, duration_s=6.0)
    outcome = run_replay(paths, tmp_path / "out", config=_cfg())
    est = _toa_after(outcome)
    np.testing.assert_allclose(np.median(est, axis=0), toa, atol=1.5 / 16000)
    for name in ("enhanced.wav", "toa.csv", "report.json"):
        assert (tmp_path / "out" / name).exists()
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["status"] == "ok" and report["stream"]["n_devices"] == 4
    y, fs = sf.read(tmp_path / "out" / "enhanced.wav")
    assert fs == 16000 and abs(len(y) - 6 * 16000) <= 2 * outcome.pipeline.config.hop_samples


def test_device_at_44k1_among_48k(make_devices, tmp_path):
    toa = [0.0, 0.001, -0.002]
    paths, _, _ = make_devices(toa, duration_s=5.0, rate_hz=48000, rates_hz=[48000, 44100, 48000])
    outcome = run_replay(paths, tmp_path / "o", config=_cfg())
    est = _toa_after(outcome)
    np.testing.assert_allclose(np.median(est, axis=0), toa, atol=3 / 48000)


@pytest.mark.parametrize("estimator", ["subset", "pinv", "kalman", "smoother"])
def test_every_estimator_runs(make_devices, tmp_path, estimator):
    paths, _, _ = make_devices([0.0, 0.002, -0.001], duration_s=4.0)
    outcome = run_replay(paths, tmp_path / estimator, config=_cfg(estimator=estimator))
    assert np.isfinite(outcome.pipeline.toa_track()[1]).all()


def test_streaming_equals_batch_for_any_block_split(make_devices, tmp_path):
    paths, _, _ = make_devices([0.0, 0.0031, -0.4], duration_s=5.0, rates_hz=[16000, 16000, 22050])
    a = run_replay(paths, tmp_path / "a", config=_cfg(block_s=0.013))
    b = run_replay(paths, tmp_path / "b", config=_cfg(block_s=0.5))
    ya, yb = a.pipeline.enhanced_signal(), b.pipeline.enhanced_signal()
    assert len(ya) == len(yb)
    np.testing.assert_allclose(ya, yb, atol=1e-5)
    np.testing.assert_allclose(a.pipeline.toa_track()[1], b.pipeline.toa_track()[1], atol=1e-9)


def test_low_latency_settings(make_devices, tmp_path):
    paths, _, _ = make_devices([0.0, 0.0015, 0.0005], duration_s=4.0)
    outcome = run_replay(paths, tmp_path / "o", config=_cfg(frame_samples=512, hop_samples=128,
                                                            tracker_lookahead_s=0.0))   # causal, as live
    assert outcome.report["stream"]["output_latency_samples"] == 384
    np.testing.assert_allclose(np.median(_toa_after(outcome), axis=0), [0, 0.0015, 0.0005], atol=2 / 16000)


# -- bad input ------------------------------------------------------------------------------------

def test_missing_and_corrupt_files_are_left_out_with_a_sentence(make_devices, tmp_path):
    paths, _, _ = make_devices([0.0, 0.002, 0.001], duration_s=4.0)
    corrupt = tmp_path / "corrupt.wav"
    corrupt.write_bytes(b"RIFF\x00\x00\x00\x00WAVEfmt garbage" * 10)
    outcome = run_replay([*paths, tmp_path / "nope.wav", corrupt], tmp_path / "o", config=_cfg())
    problems = [p for d in outcome.report["devices"] for p in d["problems"]]
    assert any("does not exist" in p for p in problems)
    assert any("not a readable audio file" in p for p in problems)
    assert outcome.report["stream"]["n_devices"] == 3


def test_a_phone_recording_libsndfile_cannot_read_says_how_to_convert_it(tmp_path):
    phone = tmp_path / "meeting phone.m4a"
    phone.write_bytes(b"\x00\x00\x00\x20ftypM4A " + bytes(200))
    handle, info = open_device_file(phone)
    assert handle is None and not info.usable
    (sentence,) = info.problems
    assert "not a readable audio file" in sentence and "but not M4A: convert it first" in sentence
    assert "ffmpeg -i 'meeting phone.m4a' 'meeting phone.flac'" in sentence and sentence.endswith("it is left out.")
    assert sentence.replace("e.g. ", "").count(". ") == 0   # one sentence
    corrupt = tmp_path / "corrupt.wav"
    corrupt.write_bytes(b"RIFF" + bytes(40))
    _, info = open_device_file(corrupt)
    assert "ffmpeg" not in info.problems[0]                 # a format libsndfile reads: no advice to convert


def test_the_mp3_decoders_stderr_lines_are_counted_not_printed(capfd):
    """libmpg123 prints lines on file descriptor 2 from C; they are counted, other lines go through."""
    kept = DecoderMessages()

    def decode(n):
        os.write(2, b"[src/libmpg123/layer3.c:INT123_do_layer3():1774] error: part2_3_length (2464) too large\n")
        os.write(2, b"somebody else's line\n")
        os.write(2, b"[src/libmpg123/layer3.c:INT123_do_layer3():1774] error: part2_3_length (2208) too large\n")
        return n * 2

    assert kept.run(decode, 21) == 42
    assert kept.run(decode, 1) == 2
    kept.close()
    assert kept.n_lines == 4 and kept.first == "error: part2_3_length (2464) too large"
    assert capfd.readouterr().err == "somebody else's line\n" * 2


def test_an_mp3_file_replays_sample_for_sample_with_its_decoder_quiet(tmp_path, capfd, caplog):
    """White noise as a constant-bitrate MP3 at 24 kHz makes libmpg123 print its "part2_3_length" lines when read
    a second at a time (as a replay reads), none when read whole, with the same samples: the replay keeps them
    off stderr and logs their count in one line when it closes."""
    caplog.set_level(logging.INFO, logger="stream.replay")
    rng = np.random.default_rng(1)
    x = (0.3 * rng.standard_normal(5 * 24000)).astype(np.float32)
    sf.write(tmp_path / "a.mp3", x, 24000, format="MP3", subtype="MPEG_LAYER_III", bitrate_mode="CONSTANT",
             compression_level=0.0)
    whole, _ = sf.read(tmp_path / "a.mp3", dtype="float32")
    capfd.readouterr()
    with ReplaySource([tmp_path / "a.mp3"], block_s=0.02) as src:
        frames = list(src)
    np.testing.assert_allclose(np.concatenate([f.samples for f in frames]), whole, atol=1e-6)
    assert "libmpg123" not in capfd.readouterr().err
    (line,) = [r.getMessage() for r in caplog.records if "MP3 decoder" in r.getMessage()]
    assert "Device 'a': the MP3 decoder printed" in line and "part2_3_length" in line


def test_truncated_file_keeps_streaming(make_devices, tmp_path):
    paths, _, _ = make_devices([0.0, 0.002, 0.001], duration_s=5.0, subtype="PCM_16")
    data = paths[1].read_bytes()
    paths[1].write_bytes(data[: len(data) // 2])           # header still claims the full length
    outcome = run_replay(paths, tmp_path / "o", config=_cfg())
    assert outcome.report["status"] == "ok"
    y, _ = sf.read(tmp_path / "o" / "enhanced.wav")
    assert len(y) > 4.5 * 16000


def test_silent_nan_and_clipped_channels(make_devices, tmp_path):
    paths, _, _ = make_devices([0.0, 0.002, 0.001, -0.001], duration_s=4.0)
    x, fs = sf.read(paths[1], dtype="float32")
    sf.write(paths[1], np.zeros_like(x), fs, subtype="FLOAT")          # silent
    x, fs = sf.read(paths[2], dtype="float32")
    x[fs:2 * fs] = np.nan
    sf.write(paths[2], x, fs, subtype="FLOAT")                           # NaN for 1 s
    x, fs = sf.read(paths[3], dtype="float32")
    sf.write(paths[3], np.clip(20 * x, -1, 1), fs, subtype="FLOAT")     # clipped
    outcome = run_replay(paths, tmp_path / "o", config=_cfg())
    devs = outcome.report["devices"]
    assert devs[1]["n_silent_blocks"] == devs[1]["n_blocks"]
    assert devs[2]["n_nan_samples"] == fs
    assert devs[3]["n_clipped_samples"] > 0
    y = outcome.pipeline.enhanced_signal()
    assert np.isfinite(y).all() and np.abs(y).max() > 0.01
    assert any("silent throughout" in p for p in devs[1]["problems"])


def test_single_device_passes_through(make_devices, tmp_path):
    paths, src, _ = make_devices([0.0], duration_s=3.0)
    outcome = run_replay(paths[:1], tmp_path / "o", config=_cfg())
    x, _ = sf.read(paths[0], dtype="float32")
    y = outcome.pipeline.enhanced_signal()
    np.testing.assert_allclose(y[: len(x)], x[: len(y)], atol=1e-5)


def test_device_that_starts_after_the_others_ended(make_devices, tmp_path):
    paths, _, _ = make_devices([0.0, 0.002], duration_s=4.0)
    late = tmp_path / "late.wav"
    rng = np.random.default_rng(3)
    sf.write(late, (0.05 * rng.standard_normal(4 * 16000)).astype(np.float32), 16000)  # shares nothing
    outcome = run_replay([*paths, late], tmp_path / "o", config=_cfg())
    assert outcome.report["stream"]["aligned"] == [True, True, False]
    assert any("left out of the beamformer" in m for m in outcome.report["messages"])


def test_different_lengths_and_channel_counts(make_devices, tmp_path):
    paths, _, _ = make_devices([0.0, 0.002, 0.001], duration_s=5.0)
    x, fs = sf.read(paths[1], dtype="float32")
    sf.write(paths[1], np.stack([x[: 3 * fs], x[: 3 * fs]], axis=1), fs)   # stereo, 3 s
    outcome = run_replay(paths, tmp_path / "o", config=_cfg())
    assert outcome.report["devices"][1]["n_file_channels"] == 2
    assert outcome.report["status"] == "ok"


def test_no_readable_input_is_one_sentence(tmp_path, capsys):
    with pytest.raises(StreamError, match="None of the 2 input files could be read"):
        run_replay([tmp_path / "a.wav", tmp_path / "b.wav"], tmp_path / "o", config=_cfg())
    assert main(["replay", str(tmp_path / "a.wav"), "--out", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "None of the 1 input files could be read" in err
    assert (tmp_path / "o" / "report.json").exists()


def test_bad_options_are_one_sentence(make_devices, tmp_path, capsys):
    paths, _, _ = make_devices([0.0, 0.001], duration_s=2.0)
    with pytest.raises(ConfigError, match="hop_samples=300 must divide frame_samples=1024"):
        run_replay(paths, tmp_path / "o", config=_cfg(frame_samples=1024, hop_samples=300))
    assert main(["replay", *map(str, paths), "--out", str(tmp_path / "o"), "--level-snr-exponent", "3"]) == 2
    assert "level_snr_exponent=3.0 must be in 0..2" in capsys.readouterr().err
    assert main(["replay", *map(str, paths), "--out", str(tmp_path / "o"), "--level-height-exponent", "5"]) == 2
    assert "level_height_exponent=5.0 must be in 0..4" in capsys.readouterr().err
    cfg = tmp_path / "c.toml"
    cfg.write_text("estimatr = 'kalman'\n")
    assert main(["replay", *map(str, paths), "--out", str(tmp_path / "o"), "--config", str(cfg)]) == 2
    assert "unknown option 'estimatr'" in capsys.readouterr().err
    with pytest.raises(InputFileError):
        ReplaySource([])


def test_cli_replay_with_config_file(make_devices, tmp_path, capsys):
    paths, _, _ = make_devices([0.0, 0.002, 0.001], duration_s=3.0)
    cfg = tmp_path / "c.toml"
    cfg.write_text("estimator = 'pinv'\nframe_samples = 512\nhop_samples = 128\nplots = false\n")
    rc = main(["replay", *map(str, paths), "--out", str(tmp_path / "o"), "--config", str(cfg),
               "--estimator", "kalman", "--no-progress", "--align-window-s", "2"])
    assert rc == 0
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    assert report["settings"]["estimator"] == "kalman"     # the CLI wins over the config file
    assert report["settings"]["frame_samples"] == 512
    assert "adhoc-array replay: ok" in capsys.readouterr().out


def test_broken_fixture_is_one_sentence(tmp_path, capsys):
    (tmp_path / "fx").mkdir()
    (tmp_path / "fx" / "fixture.toml").write_text("name = 'x'\n[[device]]\nname='a'\n")
    assert main(["replay", str(tmp_path / "fx"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("adhoc-array: ") and err.count("\n") == 1


def test_speed_paces_the_replay(make_devices, tmp_path):
    import time
    paths, _, _ = make_devices([0.0, 0.001], duration_s=2.0)
    t0 = time.monotonic()
    run_replay(paths, tmp_path / "o", config=_cfg(speed=4.0))
    assert time.monotonic() - t0 >= 2.0 / 4.0 * 0.9


@pytest.mark.parametrize("block_s", [0.02, 0.37, 2.5])
def test_frames_hold_every_sample_of_the_file_once(tmp_path, block_s):
    """The files are read a second at a time and handed out block by block: whatever the block length, the
    frames of each device put together are its file, and a truncated file gives every sample libsndfile reads
    before it ends (libsndfile counts the samples there are, not the header's claim)."""
    from stream.messages import FrameFlag
    rng = np.random.default_rng(3)
    whole = (0.1 * rng.standard_normal((int(3.3 * 16000), 2))).astype(np.float32)
    sf.write(tmp_path / "a.wav", whole, 16000, subtype="FLOAT")
    sf.write(tmp_path / "b.wav", whole[:, 0], 16000, subtype="PCM_16")
    data = (tmp_path / "b.wav").read_bytes()
    (tmp_path / "c.wav").write_bytes(data[: len(data) // 2])   # the header still claims the full length
    with ReplaySource([tmp_path / "a.wav", tmp_path / "b.wav", tmp_path / "c.wav"], block_s=block_s) as src:
        frames = list(src)
    got = {d: [f for f in frames if f.device_id == d] for d in range(3)}
    assert all(f.first_sample == sum(len(g.samples) for g in got[f.device_id][:k])
               for d in got for k, f in enumerate(got[d]))
    np.testing.assert_array_equal(np.concatenate([f.samples for f in got[0]]), whole)
    expected_b, _ = sf.read(tmp_path / "b.wav", dtype="float32")
    np.testing.assert_array_equal(np.concatenate([f.samples for f in got[1]]), expected_b)
    readable, _ = sf.read(tmp_path / "c.wav", dtype="float32")
    np.testing.assert_array_equal(np.concatenate([f.samples for f in got[2]]), readable)
    assert all(f.flags == FrameFlag.LAST for f in (got[0][-1], got[1][-1], got[2][-1]))
    assert not any(f.flags for d in got for f in got[d][:-1])


def test_a_replay_as_fast_as_possible_does_not_depend_on_how_loaded_the_machine_is(tmp_path, monkeypatch):
    """The device deadline is wall-clock time: on a loaded machine a first alignment (or a re-check waited for)
    that took longer than it once left devices out of blocks, and the same replay gave another output. A replay
    as fast as possible has every device's audio at hand and has no deadline; here the first alignment takes
    2.5 s, longer than the 2 s deadline, and the output is the same to the bit."""
    import time as _time

    import stream.align
    from tests.conftest import REPO_FIXTURES

    folder = REPO_FIXTURES / "meeting_table"
    # a 2 s window: the first alignment comes mid-stream, with every device still delivering
    cfg = EngineConfig(plots=False, progress=False, align_window_s=2.0, max_offset_s=1.0)
    run_replay([folder], tmp_path / "a", config=cfg)
    real = stream.align.joint_offsets

    def slow(*args, **kwargs):
        _time.sleep(2.5)
        return real(*args, **kwargs)

    monkeypatch.setattr(stream.align, "joint_offsets", slow)
    outcome = run_replay([folder], tmp_path / "b", config=cfg)
    a, _ = sf.read(tmp_path / "a" / "enhanced.wav", dtype="float32")
    b, _ = sf.read(tmp_path / "b" / "enhanced.wav", dtype="float32")
    assert np.array_equal(a, b)
    assert not outcome.pipeline.aligner.n_late_blocks.any()


def test_the_trackers_kernels_are_compiled_before_the_stream_not_at_its_first_talker():
    """numba compiles a kernel at its first call with each argument type (or loads it from its cache): the
    tracker's kernels, first called when the first talker is heard, stalled that hop for ~0.5 s on a first run
    after an install or an update (live: input overflows); a noise source from the mature noise spectra (then
    fit on a column view of the peak array: another layout) for 0.26 s (an output underflow); the checker's and
    the aligner's, in the stream's first block. The pipeline calls them once when it is built; then a talker, a
    pause and a noise source compile nothing. Checked in a fresh interpreter, where no other test has called
    them."""
    import subprocess
    import sys
    import textwrap
    code = textwrap.dedent("""
        import numba, numpy as np
        import estimators, estimators.tracks as T, estimators.toa as K, stream.align as A, stream.condition as C
        from stream.config import EngineConfig
        from stream.pipeline import Pipeline
        def signatures():
            return {(m.__name__, k): len(v.signatures) for m in (T, K, A, C) for k, v in vars(m).items()
                    if isinstance(v, numba.core.registry.CPUDispatcher)}
        p = Pipeline(EngineConfig(estimator="tracks").resolved(16000.0), [16000.0] * 4)
        before = signatures()
        h = estimators.pair_matrix(4)
        tdoa, value = np.zeros((6, 5)), np.full((6, 5), 0.05)
        value[:, 0] = 0.5
        for k in range(80):   # a talker 0.6 s, a pause, then a noise source from the noise spectra
            tdoa[:, 0] = h @ np.array([0.0, 1e-3, 2e-3, -1e-3])
            noise = (np.where(np.arange(5) == 0, (h @ np.array([0.0, -2e-3, 1e-3, 3e-3]))[:, None], 0.0),
                     value.copy(), np.zeros((6, 1024), np.float32))
            p.tracker.update(tdoa, value, speech_probability=float(k < 40), usable=np.ones(4, bool),
                             time_s=k * 0.016, noise_peaks=lambda: noise)
        after = signatures()
        used = [(T, "_anchor_vote"), (T, "_predict_gate"), (T, "_pick_peaks"), (T, "_solve_pairs"),
                (T, "_note_heights"), (T, "_height_factors"),
                (K, "_kalman_step"), (A, "_cut_block"), (C, "_frame_stats")]
        print(all(before[m.__name__, k] > 0 for m, k in used), [k for k in after if after[k] > before[k]],
              sorted(t.kind for t in p.tracker.tracks))
        """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         cwd=Path(__file__).resolve().parents[2])
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "True [] ['noise', 'speech']", out.stdout
