"""Shipped replay fixtures: they load, their files match the manifest, and the timing truth
matches both the stated geometry/clocks and the audio itself (numpy-only GCC checks)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import scipy.signal
import soundfile as sf

from stream.scoring.fixture import Fixture, FixtureError, is_fixture_dir, load_fixture

FIXTURE_ROOT = Path(__file__).resolve().parents[2] / "replay_fixtures"
NAMES = ("meeting_table", "walking_talker", "async_8dev", "kitchen_noise", "two_talkers")
MULTI = ("kitchen_noise", "two_talkers")   # scenes with a [sources] table (several sources, activity)
RIR_DELAY_SAMPLES = 40  # pyroomacoustics frac_delay_length // 2; cancels in relative TOAs


@pytest.fixture(scope="module", params=NAMES)
def fx(request) -> Fixture:
    return load_fixture(FIXTURE_ROOT / request.param)


def _clock_s(dev, t_s):
    """eq.: T_i = (t - start_offset_s) * (1 + drift_ppm * 1e-6)."""
    return (np.asarray(t_s) - dev.start_offset_s) * (1.0 + dev.drift_ppm * 1e-6)


def _true_time_s(dev, clock_s):
    return dev.start_offset_s + np.asarray(clock_s) / (1.0 + dev.drift_ppm * 1e-6)


def _recompute_toa(fx: Fixture, ref_true_s: np.ndarray, *, synchronous: bool) -> np.ndarray:
    """Relative TOA from positions, source.csv and clocks (independent of the builder)."""
    c = float(fx.room["speed_of_sound_m_s"])
    t_src, p_src = fx.load_source_path()

    def path(tau):
        return np.stack([np.interp(tau, t_src, p_src[:, k]) for k in range(3)], axis=1)

    mics = fx.positions_m
    tau = ref_true_s - np.linalg.norm(path(ref_true_s) - mics[0], axis=1) / c
    for _ in range(6):  # t = tau + |p(tau) - m0| / c, contraction v / c
        tau = ref_true_s - np.linalg.norm(path(tau) - mics[0], axis=1) / c
    t_arr = tau[:, None] + np.linalg.norm(path(tau)[:, None, :] - mics[None], axis=2) / c
    if synchronous:
        return t_arr - t_arr[:, :1]
    clocks = np.stack([_clock_s(d, t_arr[:, i]) for i, d in enumerate(fx.devices)], axis=1)
    return clocks - clocks[:, :1]


def _gcc_phat_lag(ref: np.ndarray, x: np.ndarray, fs_hz: float, *, max_lag: int = 32,
                  band_hz=(100.0, 4000.0), upsample: int = 8) -> float:
    """Lag in samples with ``x[n] ~ ref[n - lag]``; band-limited PHAT, upsampled, parabolic."""
    n = 1 << int(np.ceil(np.log2(len(ref) + len(x))))
    r = np.fft.rfft(x, n) * np.conj(np.fft.rfft(ref, n))
    f = np.fft.rfftfreq(n, 1.0 / fs_hz)
    r = np.where((f >= band_hz[0]) & (f <= band_hz[1]), r / (np.abs(r) + 1e-20), 0.0)
    cc = np.fft.irfft(r, n * upsample)
    m = max_lag * upsample
    cc = np.concatenate([cc[-m:], cc[:m + 1]])
    k = int(np.argmax(cc))
    a, b, d = cc[k - 1], cc[k], cc[(k + 1) % len(cc)]
    return (k + 0.5 * (a - d) / (a - 2 * b + d) - m) / upsample


def _active(clean: np.ndarray, k0: int, k1: int) -> bool:
    return np.mean(clean[k0:k1] ** 2) >= 0.3 * np.mean(clean ** 2)


# ----------------------------------------------------------------------------- manifest and files
def test_all_shipped_fixtures_present():
    found = sorted(p.name for p in FIXTURE_ROOT.iterdir() if is_fixture_dir(p))
    assert found == sorted(NAMES)


def test_fixture_loads(fx):
    assert fx.n_devices >= 4
    assert fx.devices[0].sample_rate_hz == fx.working_rate_hz
    assert all(p is not None and p.is_file() for p in (
        fx.truth_clean, fx.truth_toa, fx.truth_sync, fx.truth_clean_sync, fx.truth_sync_toa,
        fx.truth_source_path))
    assert len(fx.room["dims_m"]) == 3 and fx.description
    assert fx.credits["speech"]
    assert np.all(fx.positions_m > 0) and np.all(fx.positions_m < np.asarray(fx.room["dims_m"]))


def test_device_files_match_manifest(fx):
    for dev in fx.devices:
        info = sf.info(str(dev.path))
        assert info.format == "FLAC" and info.subtype == "PCM_16" and info.channels == 1
        assert info.samplerate == dev.sample_rate_hz
        assert info.frames == round(fx.duration_s * dev.sample_rate_hz)
    rates = {d.sample_rate_hz for d in fx.devices}
    if fx.name == "kitchen_noise":
        assert rates == {16000, 44100}     # the laptop
    elif fx.name == "async_8dev":
        assert rates == {48000, 44100}
        assert min(d.gain_db for d in fx.devices) == -15.0
        assert max(d.start_offset_s for d in fx.devices) == pytest.approx(2.0)
    else:
        assert rates == {16000}


def test_quiet_device_above_its_sensor_noise():
    fx = load_fixture(FIXTURE_ROOT / "async_8dev")
    quiet = min(fx.devices, key=lambda d: d.gain_db)
    x, _ = quiet.load()
    row = next(r for r in fx.raw["device"] if r["name"] == quiet.name)
    noise_rms = 10 ** (row["sensor_noise_dbfs"] / 20)
    assert np.sqrt(np.mean(x.astype(float) ** 2)) > 3 * noise_rms


# ----------------------------------------------------------------------------- truth tables
def test_truth_toa_matches_geometry_and_clocks(fx):
    grid, toa = fx.load_truth_toa()
    assert np.allclose(np.diff(grid), 0.01) and grid[0] == 0.0
    assert grid[-1] <= fx.duration_s
    assert np.all(toa[:, 0] == 0.0)
    expected = _recompute_toa(fx, _true_time_s(fx.devices[0], grid), synchronous=False)
    moving = np.ptp(fx.load_source_path()[1], axis=0).max() > 0
    rows = _talker0_rows(fx, grid)
    # 1e-8 s is the CSV rounding; a moving talker adds the chord error of the 10 ms source grid.
    assert np.abs(toa - expected)[rows].max() < (2e-7 if moving else 1e-8)


def _talker0_rows(fx: Fixture, grid: np.ndarray) -> np.ndarray:
    """Rows of a truth grid at which ``source.csv``'s talker (talker 0) is the active one: all rows with one
    talker; with several (``toa.csv`` follows the active talker) talker 0's turns, 0.5 s clear of a change
    (the grids of the synchronous and device clocks differ by the offsets)."""
    if sum(not s.is_noise for s in fx.sources) < 2:
        return np.ones(len(grid), bool)
    active, _ = fx.activity_at(grid)
    change_t = grid[np.flatnonzero(np.diff(active) != 0) + 1]
    clear = np.all(np.abs(grid[:, None] - change_t[None, :]) > 0.5, axis=1)
    rows = (active == 0) & clear
    assert rows.sum() > 100
    return rows


def test_static_talker_toa_closed_form():
    fx = load_fixture(FIXTURE_ROOT / "meeting_table")
    grid, toa = fx.load_truth_toa()
    c = fx.room["speed_of_sound_m_s"]
    src = fx.load_source_path()[1][0]
    d = np.linalg.norm(fx.positions_m - src, axis=1) / c
    t0 = _true_time_s(fx.devices[0], grid)
    for i, dev in enumerate(fx.devices):
        # toa_i(T0) = (t0 + d_i - d_0 - off_i)(1 + drift_i) - T0: linear in T0
        want = _clock_s(dev, t0 + d[i] - d[0]) - grid
        assert np.allclose(toa[:, i], want, atol=1e-8, rtol=0)


def test_sync_toa_is_pure_propagation(fx):
    grid, toa = fx.load_sync_toa()
    expected = _recompute_toa(fx, grid, synchronous=True)
    rows = _talker0_rows(fx, grid)
    assert np.abs(toa - expected)[rows].max() < 2e-7
    c = fx.room["speed_of_sound_m_s"]
    span = np.linalg.norm(fx.positions_m[:, None] - fx.positions_m[None], axis=2).max() / c
    assert np.abs(toa).max() <= span + 1e-9


def test_truth_toa_at_interpolates(fx):
    grid, toa = fx.load_truth_toa()
    assert np.allclose(fx.truth_toa_at(grid[:5]), toa[:5])
    mid = 0.5 * (grid[10] + grid[11])
    assert np.allclose(fx.truth_toa_at([mid])[0], 0.5 * (toa[10] + toa[11]))
    assert fx.truth_toa_at(np.array([0.1, 0.2, 0.3])).shape == (3, fx.n_devices)


# ----------------------------------------------------------------------------- truth vs audio
def test_gcc_window_agrees_with_truth(fx):
    """0.5 s windows of device 0 and device i, device i's window placed by the truth TOA: the
    residual GCC-PHAT lag is within a few samples (reverberant, noisy audio)."""
    fs0 = fx.devices[0].sample_rate_hz
    x0, _ = fx.devices[0].load()
    clean, _ = fx.load_clean()
    win_s = 0.25 if fx.name == "walking_talker" else 0.5  # a moving talker smears longer windows
    n = int(win_s * fs0)
    residuals = []
    for t in np.arange(0.5, fx.duration_s - 0.5, 0.5):
        k0 = int(round((t - win_s / 2) * fs0))
        if not _active(clean, k0, k0 + n):
            continue
        toa = fx.truth_toa_at([t])[0]
        for i in range(1, fx.n_devices):
            dev = fx.devices[i]
            start = (t + toa[i] - win_s / 2) * dev.sample_rate_hz
            ki = int(math.floor(start))
            n_i = int(math.ceil(win_s * dev.sample_rate_hz)) + 2
            xi, _ = dev.load()
            if ki < 0 or ki + n_i > len(xi):
                continue  # device i does not record this wavefront
            seg = xi[ki:ki + n_i].astype(float)
            if dev.sample_rate_hz != fs0:
                g = math.gcd(fs0, dev.sample_rate_hz)
                seg = scipy.signal.resample_poly(seg, fs0 // g, dev.sample_rate_hz // g)
            frac = (start - ki) / dev.sample_rate_hz * fs0  # window starts this much early
            lag = _gcc_phat_lag(x0[k0:k0 + n].astype(float), seg[:n], fs0)
            residuals.append(lag - frac)
    residuals = np.abs(np.array(residuals))
    scale = fs0 / 16000  # tolerances in 16 kHz samples
    assert len(residuals) >= 10
    assert np.median(residuals) < 1.0 * scale
    assert np.mean(residuals < 3.0 * scale) >= 0.8


@pytest.mark.parametrize("name", MULTI)
def test_sources_truth_matches_geometry_and_activity(name):
    """Every source's TOA file agrees with its position and the clocks (as the main truth does); the
    activity table has the talkers speaking in turn; the stitched toa.csv follows the active talker."""
    fx = load_fixture(FIXTURE_ROOT / name)
    kinds = [s.kind for s in fx.sources]
    assert kinds.count("talker") == (2 if name == "two_talkers" else 1)
    assert sum(k.startswith("noise:") for k in kinds) == 1 and fx.sources[-1].is_noise
    c = float(fx.room["speed_of_sound_m_s"])
    t = np.arange(0.5, fx.duration_s - 0.5, 0.25)
    dev_pos = fx.positions_m
    for src in fx.sources:
        toa = fx.source_toa_at(src.name, t)
        rel = toa - toa[:, :1]
        prop = np.linalg.norm(dev_pos - src.position_m, axis=1) / c
        # relative TOA = propagation difference + clock offset/drift terms (the same for every source)
        main = fx.truth_toa_at(t)
        talker0 = fx.source_toa_at(fx.sources[0].name, t)
        prop0 = np.linalg.norm(dev_pos - fx.sources[0].position_m, axis=1) / c
        expect = (talker0 - talker0[:, :1]) + ((prop - prop[0]) - (prop0 - prop0[0]))
        assert np.allclose(rel, expect, atol=2e-5), src.name
        assert main.shape == toa.shape
    active, speaking = fx.activity_at(t)
    assert speaking.shape == (len(t), kinds.count("talker"))
    assert speaking.any(axis=0).all()                          # every talker speaks
    assert not (speaking.sum(axis=1) > 1).mean() > 0.05        # turns, hardly any overlap
    main = fx.truth_toa_at(t)
    for j in range(speaking.shape[1]):
        sel = speaking[:, j]
        own = fx.source_toa_at(fx.sources[j].name, t)
        assert np.allclose(main[sel], own[sel], atol=1e-6)     # toa.csv is the active talker's while they speak
    if name == "two_talkers":
        assert len(np.flatnonzero(np.diff(active) != 0)) >= 3  # A, B, A, B
    else:   # the kitchen plays from 0 s; the talker's file starts at 2 s with 3.4 s of its own room noise
        first = t[np.argmax(speaking[:, 0])]   # (about 28 dB below its speech): the first word at 5.4 s
        assert 5.2 <= first <= 5.8


def test_clean_aligned_with_device0(fx):
    x0, fs0 = fx.devices[0].load()
    clean, fs = fx.load_clean()
    assert fs == fs0 and len(clean) == len(x0)
    assert abs(_gcc_phat_lag(clean.astype(float), x0.astype(float), fs)) <= 1.0


def test_clean_sync_aligned_with_sync_channel0(fx):
    sync, fs = fx.load_sync()
    clean_sync, fs_c = fx.load_clean_sync()
    assert fs == fs_c == fx.working_rate_hz and sync.shape == (len(clean_sync), fx.n_devices)
    assert abs(_gcc_phat_lag(clean_sync.astype(float), sync[:, 0].astype(float), fs)) <= 1.0
    grid, _ = fx.load_sync_toa()
    assert grid[-1] <= len(sync) / fs


# ----------------------------------------------------------------------------- loader errors
MINIMAL = """
name = "tiny"
description = "two devices"
working_rate_hz = 16000
duration_s = 0.1
[room]
dims_m = [4.0, 3.0, 2.5]
rt60_s = 0.3
[[device]]
name = "a"
file = "a.flac"
sample_rate_hz = 16000
start_offset_s = 0.0
drift_ppm = 0.0
gain_db = 0.0
position_m = [1.0, 1.0, 1.0]
[[device]]
name = "b"
file = "b.flac"
sample_rate_hz = 16000
start_offset_s = 0.1
drift_ppm = 20.0
gain_db = -3.0
position_m = [2.0, 1.0, 1.0]
"""


def _write_minimal(root: Path, text: str = MINIMAL) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    for f in ("a.flac", "b.flac"):
        sf.write(str(root / f), np.zeros(1600, np.int16), 16000, format="FLAC", subtype="PCM_16")
    (root / "fixture.toml").write_text(text)
    return root


def test_minimal_fixture_without_truth(tmp_path):
    fx = load_fixture(_write_minimal(tmp_path / "tiny"))
    assert fx.n_devices == 2 and fx.truth_toa is None and is_fixture_dir(fx.root)
    assert fx.devices[1].drift_ppm == 20.0 and fx.devices[1].position_m.shape == (3,)
    with pytest.raises(FixtureError, match="no truth 'toa'"):
        fx.load_truth_toa()


def test_missing_manifest(tmp_path):
    assert not is_fixture_dir(tmp_path)
    with pytest.raises(FixtureError, match="no fixture.toml"):
        load_fixture(tmp_path)


def test_malformed_toml(tmp_path):
    root = _write_minimal(tmp_path / "bad", MINIMAL + "\nthis is = = not toml\n")
    with pytest.raises(FixtureError, match="not valid TOML"):
        load_fixture(root)


def test_missing_key(tmp_path):
    root = _write_minimal(tmp_path / "nokey", MINIMAL.replace("drift_ppm = 20.0\n", ""))
    with pytest.raises(FixtureError, match="missing the key 'drift_ppm'"):
        load_fixture(root)


def test_missing_device_file(tmp_path):
    root = _write_minimal(tmp_path / "nofile")
    (root / "b.flac").unlink()
    with pytest.raises(FixtureError, match="b.flac .* does not exist"):
        load_fixture(root)


def test_fixture_error_is_value_error():
    assert issubclass(FixtureError, ValueError)


def test_speech_activity_ignores_lone_frames_of_room_hum():
    """The truth's speech activity: words (runs of 50 ms and more, 15 dB above the recording's own background)
    with the short pauses between them filled; a lone 20 ms crackle of the room hum 17 dB above it is no word
    (in a two-talker scene such frames opened a turn 3 s before the talker's first word)."""
    import sys
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "replay_fixtures"))
    from build_fixtures import speech_activity
    fs = 16000
    rng = np.random.default_rng(1)
    x = 10 ** (-35 / 20) * rng.standard_normal(4 * fs)                      # room hum
    x[int(0.5 * fs):int(0.52 * fs)] *= 10 ** (17 / 20)                       # a lone crackle
    for a, b in ((2.0, 2.4), (2.5, 2.9)):                                    # two words, 0.1 s apart
        i, j = round(a * fs), round(b * fs)
        x[i:j] = 0.3 * np.sin(2 * np.pi * 220 * np.arange(j - i) / fs)
    act = speech_activity(x, fs)
    on = np.flatnonzero(act)
    assert not act[int(0.45 * fs):int(0.6 * fs)].any()
    assert abs(on[0] / fs - 2.0) < 0.011 and abs(on[-1] / fs - 2.9) < 0.011
    assert act[int(2.4 * fs):int(2.5 * fs)].all()                            # the pause between words
