"""The tracker's measurement interval (``track_interval_s``): with hops shorter than it, the GCC peaks and the
track bank's update run every ``track_stride`` hops (the tracker's frame period is that span; the GCC's averages
still take every hop) and the hops between are steered by the last decision; the output, ``toa.csv`` and the
beamformer keep the hop. The default (16 ms) measures every hop at the default 1024/256 at 16 kHz and every other
hop at 512/128 (``benchmarks/throughput.py``: the whole engine's CPU about 12 % lower there)."""
from pathlib import Path

import numpy as np
import pytest

from stream.config import EngineConfig
from stream.errors import ConfigError
from stream.run import run_replay

FIXTURE = Path(__file__).resolve().parents[2] / "replay_fixtures" / "two_talkers"
LOW_LATENCY = dict(frame_samples=512, hop_samples=128, plots=False, progress=False)


@pytest.mark.parametrize("hop, interval, stride", [(256, 0.016, 1), (128, 0.016, 2), (64, 0.016, 4),
                                                   (160, 0.016, 1), (128, 0.0, 1), (128, 0.031, 3)])
def test_the_stride_is_the_most_whole_hops_within_the_interval(hop, interval, stride):
    cfg = EngineConfig(frame_samples=max(512, 4 * hop), hop_samples=hop, track_interval_s=interval).resolved(16000.0)
    assert cfg.track_stride == stride


@pytest.mark.parametrize("bad", [-0.01, float("nan"), 0.5])
def test_a_bad_interval_is_one_sentence(bad):
    with pytest.raises(ConfigError, match="track_interval_s"):
        EngineConfig(track_interval_s=bad).resolved(16000.0)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    out = tmp_path_factory.mktemp("interval")
    every = run_replay([FIXTURE], out / "every", config=EngineConfig(track_interval_s=0.0, **LOW_LATENCY))
    other = run_replay([FIXTURE], out / "other", config=EngineConfig(**LOW_LATENCY))
    causal = run_replay([FIXTURE], out / "causal", config=EngineConfig(tracker_lookahead_s=0.0, **LOW_LATENCY))
    return every, other, causal


def test_the_tracker_measures_every_other_hop_and_the_stream_keeps_its_hop(runs):
    every, other, _ = runs
    for run, stride in ((every, 1), (other, 2)):
        p = run.pipeline
        assert run.report["stream"]["tracker_every_hops"] == stride == p.track_stride
        assert p.tracker.frame_period_s == pytest.approx(stride * 128 / 16000)
        n_blocks = p.counters.n_blocks
        assert abs(p.tracker.n_frames - n_blocks / stride) <= 1
        assert len(p.state.time_s) == n_blocks and len(p.enhanced_signal()) == n_blocks * 128
    assert every.pipeline.counters.n_blocks == other.pipeline.counters.n_blocks
    assert (every.report["stream"]["output_latency_samples"] == other.report["stream"]["output_latency_samples"])


def test_between_measurements_the_last_decision_holds(runs):
    p = runs[2].pipeline   # causal: the hop after a measurement is steered exactly as the measurement's
    ids = np.asarray(p.state.track_id)
    toa = p.toa_track()[1]
    offsets = np.asarray(p.state.offsets)
    same_offsets = (offsets[1::2] == offsets[0:-1:2][:len(offsets[1::2])]).all(axis=1)
    n = len(same_offsets)
    assert (ids[1::2][:n] == ids[0::2][:n]).all()
    assert (ids >= 0).mean() > 0.5
    np.testing.assert_array_equal(toa[1::2][:n][same_offsets], toa[0::2][:n][same_offsets])


def test_measuring_every_other_hop_keeps_the_enhancement(runs):
    every, other, _ = runs
    sdr = [r.report["metrics"]["enhancement"]["engine"]["si_sdr_db"] for r in (every, other)]
    single = every.report["metrics"]["enhancement"]["best_single_device"]["si_sdr_db"]
    print(f"SI-SDR every hop {sdr[0]:.2f} dB, every other hop {sdr[1]:.2f} dB, best single device {single:.2f} dB")
    assert abs(sdr[1] - sdr[0]) < 0.3 and sdr[1] > single + 1.0


def test_the_summary_says_how_often_the_tracker_measures(runs, tmp_path):
    from stream.cli import summary
    every, other, _ = runs
    assert "measuring every 2 hops, 16 ms" in summary(other.report, tmp_path)
    assert "measuring every" not in summary(every.report, tmp_path)
    assert "(mean " in summary(other.report, tmp_path)
