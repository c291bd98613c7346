"""``benchmarks/scenes.py``'s summaries: the split of the distance to the oracle into steering and the engine's input,
and the speech detector against the truth."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from scenes import gap_split  # noqa: E402  (a script of benchmarks/, importable by its folder)


def _row(snr, engine, true_toa, oracle):
    return {"scene": f"s_{snr}_{engine}", "snr_db": snr,
            "tracks": {"si_sdr_db": engine, "true_toa_db": true_toa, "oracle_db": oracle}}


def test_the_distance_to_the_oracle_splits_into_steering_and_input_over_the_scenes_at_5_db_and_above():
    rows = [_row(5, 1.0, 2.0, 2.5),        # steering -1.0, input -0.5
            _row(10, 3.0, 3.5, 3.5),       # -0.5, 0.0
            _row(20, 0.0, 2.0, 1.0),       # -2.0, +1.0
            _row(0, -9.0, 5.0, 5.0),       # 0 dB: left out
            _row(30, 1.0, float("nan"), 1.0)]   # no truth TOA: left out
    split = gap_split(rows, "tracks")
    assert split == {"steering_db": -1.0, "clocks_db": 0.0, "n": 3}
    one = gap_split([_row(5, 1.0, 2.0, 2.5)], "tracks")
    assert one["steering_db"] + one["clocks_db"] == pytest.approx(1.0 - 2.5)   # one scene: the two parts add up


def test_no_scene_with_a_true_toa_figure_gives_no_split():
    assert gap_split([_row(0, 1.0, 2.0, 2.5), _row(5, 1.0, float("nan"), 2.0)], "tracks") == {}


def test_the_speech_detector_figures_leave_out_its_hold_after_speech():
    from scenes import SPEECH_TAIL_S, speech_detector_figures
    hop_s = 0.016
    n = 200
    speaking = np.zeros((n, 2), bool)
    speaking[20:60, 0] = True                     # talker 0, then talker 1
    speaking[120:150, 1] = True
    p = np.zeros(n)
    p[20:50] = 0.9                                # 50 of the 70 speech frames called speech
    p[130:150] = 0.9
    k = int(round(SPEECH_TAIL_S / hop_s))
    p[60:60 + k] = 0.9                            # the hold after talker 0: not a false alarm
    p[100:110] = 0.7                              # 10 false alarms
    silent = n - 70 - 2 * k                       # frames neither speech nor within the hold after it
    f = speech_detector_figures(p, speaking, hop_s)
    assert f["speech_recall"] == pytest.approx(50 / 70)
    assert f["speech_false_alarm"] == pytest.approx(10 / silent)
    none = speech_detector_figures(np.zeros(10), np.zeros((10, 1), bool), hop_s)
    assert np.isnan(none["speech_recall"]) and none["speech_false_alarm"] == 0.0


def test_the_oracle_alignment_puts_every_device_on_the_talker_and_leaves_the_aligner_as_it_was(tmp_path):
    """``--oracle-alignment talker``: the first offsets are the talker's true ones (within a sample at the working
    rate); ``nearest``: each device on the true source nearest the measured offset; outside, the aligner is the
    engine's own."""
    from scenes import oracle_alignment, true_offsets_s
    from stream.align import Aligner
    from stream.config import EngineConfig
    from stream.run import run_replay
    from stream.scoring.fixture import load_fixture
    folder = Path(__file__).resolve().parents[2] / "replay_fixtures" / "kitchen_noise"
    truth = true_offsets_s(load_fixture(folder))
    assert len(truth) == 2 and all(o[0] == 0.0 for o in truth)   # the talker, the noise; device 0 at 0
    config = EngineConfig(progress=False, plots=False)
    measured = Aligner._initial_alignment
    rate = {}

    def run(mode, offsets_s):
        with oracle_alignment(mode, offsets_s):
            res = run_replay([folder], tmp_path / str(mode), config=config)
        assert Aligner._initial_alignment is measured
        rate["hz"] = res.pipeline.config.working_rate_hz
        return np.asarray(list(res.pipeline.state.offsets)[0], float) / rate["hz"]

    first = run(None, truth)
    fs = rate["hz"]   # the fixture's working rate
    assert np.max(np.abs(first - truth[0])) > 10 / fs   # measured: up to 29 samples off the talker
    assert np.max(np.abs(run("talker", truth) - truth[0])) <= 1 / fs
    # a third "source" 0.4 samples from every measured offset is the nearest one for every device
    near = first + 0.4 / fs
    near[0] = 0.0
    assert np.max(np.abs(run("nearest", [*truth, near]) - near)) <= 1 / fs
