"""The tracker's look-ahead (``tracker_lookahead_s``): frame t is steered by the decision the causal tracker makes
at frame t + L (the steered track, its TOA then taken back along its TOA rate to frame t); the output is L hops
later. Replay's default (0.128 s); live and network sources stay causal (their latency budget)."""
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from stream.config import EngineConfig
from stream.errors import ConfigError
from stream.run import run_replay

FIXTURE = Path(__file__).resolve().parents[2] / "replay_fixtures" / "two_talkers"


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    out = tmp_path_factory.mktemp("lookahead")
    cfg = dict(plots=False, progress=False)
    causal = run_replay([FIXTURE], out / "causal", config=EngineConfig(tracker_lookahead_s=0.0, **cfg))
    ahead = run_replay([FIXTURE], out / "ahead", config=EngineConfig(tracker_lookahead_s=0.128, **cfg))
    return causal, ahead


def test_each_frame_follows_the_decision_lookahead_frames_later(runs):
    causal, ahead = runs
    cfg = causal.pipeline.config
    lag = round(0.128 * cfg.working_rate_hz / cfg.hop_samples)
    ids_c = np.asarray(causal.pipeline.state.track_id)
    ids_a = np.asarray(ahead.pipeline.state.track_id)
    assert len(ids_a) == len(ids_c) and lag == 8
    assert len(set(ids_c[ids_c >= 0])) >= 2   # the fixture's turns change the steered track
    np.testing.assert_array_equal(ids_a[:-lag], ids_c[lag:])
    assert (ids_a[-lag:] == ids_c[-1]).all()  # the stream's end: the last decision
    assert (ahead.report["stream"]["output_latency_samples"]
            == causal.report["stream"]["output_latency_samples"] + lag * cfg.hop_samples)


def test_a_frame_is_steered_by_the_toa_lookahead_frames_later_taken_back_along_its_rate(runs):
    causal, ahead = runs
    lag = 8
    ids_c = np.asarray(causal.pipeline.state.track_id)
    toa_c, toa_a = causal.pipeline.toa_track()[1], ahead.pipeline.toa_track()[1]
    steered = ids_c[lag:] >= 0   # total TOA (coarse offset + fine): the causal run's, L frames on, less its rate
    assert steered.mean() > 0.5  # times the L frames (the tracker keeps rates within 3 ms/s)
    back = np.abs(toa_a[:-lag][steered] - toa_c[lag:][steered])
    print(f"taken back: median {1e6 * np.median(back):.2f} us, max {1e6 * back.max():.1f} us")
    assert back.max() <= 3e-3 * 0.128 + 1e-9
    assert np.median(back) < 2e-5 and (back > 1e-9).mean() > 0.5   # seated talkers: clock drift's few us
    tail = np.abs(toa_a[-lag:] - toa_c[-1])   # the stream's end: the last decision, taken back 1..L frames
    assert tail.max() <= 3e-3 * 0.128 + 1e-9


def test_output_is_as_long_and_in_step(runs):
    causal, ahead = runs   # latency removed: the same signal, in step (no shift), where the decisions agree
    ya, yc = ahead.pipeline.enhanced_signal(), causal.pipeline.enhanced_signal()
    assert len(ya) == len(yc)
    xc = signal.correlate(ya, yc, method="fft")
    mid = len(yc) - 1
    near = xc[mid - 256: mid + 257]
    rho = xc[mid] / np.sqrt(np.sum(ya ** 2) * np.sum(yc ** 2))
    print(f"correlation at lag 0: {rho:.3f}")
    assert np.argmax(near) == 256 and rho > 0.95


@pytest.mark.parametrize("kw", [dict(tracker_lookahead_s=-0.1), dict(tracker_lookahead_s=float("nan")),
                                dict(tracker_lookahead_s=2.5)])
def test_bad_lookahead_options_are_one_sentence(kw):
    with pytest.raises(ConfigError, match="tracker_lookahead"):
        EngineConfig(**kw).resolved(16000.0)


def test_replay_looks_ahead_by_default_and_live_does_not():
    from stream.config import merge
    from stream.live import LIVE_DEFAULTS
    assert EngineConfig().tracker_lookahead_s == pytest.approx(0.128)
    assert merge(EngineConfig(), LIVE_DEFAULTS, source="live defaults").tracker_lookahead_s == 0.0
