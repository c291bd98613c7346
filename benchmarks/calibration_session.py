"""A simulated calibration session, end to end through the streaming engine (``adhoc-array replay`` with a
chirp beacon): recovered positions, clock offsets and drifts against the truth, solve times in the worker, and
the enhancement with and without drift correction.

The scene (seeded, pyroomacoustics, low image-source order): ``n_devices`` devices spread in a shoebox room
start recording up to ``max_offset_s`` apart with clock drifts of up to +-``max_drift_ppm``; a talker (the
``meeting_table`` fixture's dry speech, looped) speaks from a fixed position while a loudspeaker on a robot
moves along a 3-D path and plays a linear chirp at every stop (one RIR set per chirp). Each device's recording
is the band-limited value of the synchronous signal at its own sample instants
(``replay_fixtures/build_fixtures.py:band_limited_at``), plus sensor noise; the odometry of every step has
``odometry_noise_m`` of noise per axis.

    python benchmarks/calibration_session.py [--devices 8] [--events 40] [--seed 0] [--out DIR]

Prints one JSON line: ``position_error_m`` (RMS over devices >= 1 in the mic frame, and max), ``offset_error_ms``,
``drift_error_ppm`` (RMS and max, relative to device 0), the verdict, ``solve_time_s`` (each solve in the
worker), ``step_ms_max`` (the calibration's share of a block: it never waits), ``si_sdr_db`` for
``calibration_apply`` = drift / offsets / none (the plain engine) and the run times.

The functions :func:`simulate_session` and :func:`evaluate` are also used by ``tests/stream/test_calibration.py``.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import importlib.util  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import scipy.signal  # noqa: E402
import soundfile as sf  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import estimators  # noqa: E402
from stream.scoring import metrics  # noqa: E402
from stream.geometry import Geometry  # noqa: E402

SPEECH = REPO / "replay_fixtures" / "meeting_table" / "truth" / "clean.flac"
C = estimators.SPEED_OF_SOUND_M_S
RIR_DELAY = 40   # pyroomacoustics' fixed RIR delay (frac_delay_length // 2), samples


def fixture_builder():
    """``replay_fixtures/build_fixtures.py`` as a module (its band-limited resampler)."""
    name = "build_fixtures"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, REPO / "replay_fixtures" / "build_fixtures.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
    return sys.modules[name]


@dataclasses.dataclass(frozen=True)
class Session:
    """A simulated session: the files the engine reads and the truth to score it against."""

    paths: tuple[Path, ...]            # one WAV per device, device 0 first
    odometry_csv: Path
    sample_rate_hz: int
    positions_m: np.ndarray            # (N, 3) room frame
    start_offsets_s: np.ndarray        # (N,) true time each device starts recording
    drifts_ppm: np.ndarray             # (N,) each device's rate against true time
    events_m: np.ndarray               # (K, 3) beacon positions
    emission_s: np.ndarray             # (K,) true emission times (RIR delay included)
    interval_s: np.ndarray             # (K-1,)
    clean_ref: np.ndarray              # dry talker aligned to device 0's direct path, on device 0's clock
    chirp_arrival_dev0_s: np.ndarray   # (K,) on device 0's clock
    chirp_template: np.ndarray
    chirp: dict
    talker_m: np.ndarray               # (3,) the talker's position
    array_rotation: np.ndarray | None = None   # (3, 3) the array device's rotation (room frame), if there is one
    arrays_toml: Path | None = None    # the arrays file naming it (the engine's ``arrays`` option)

    def clock_s(self, i: int, true_s):
        """Device ``i``'s clock at true time: ``(t - start_i) (1 + drift_i)``."""
        return (np.asarray(true_s) - self.start_offsets_s[i]) * (1.0 + self.drifts_ppm[i] * 1e-6)

    def truth(self, first_event: int = 0) -> dict[str, np.ndarray]:
        """The geometry's truth: ``offsets_s = tau_i - tau_0`` with ``tau_i`` device ``i``'s clock at the
        emission of event ``first_event``, drifts relative to device 0, device 0's clock at that emission."""
        e = self.emission_s[first_event]
        tau = np.array([self.clock_s(i, e) for i in range(len(self.positions_m))])
        q = (1.0 + self.drifts_ppm * 1e-6) / (1.0 + self.drifts_ppm[0] * 1e-6)
        return {"offsets_s": tau - tau[0], "drifts_ppm": (q - 1.0) * 1e6, "epoch_clock_s": tau[0]}


def _mic_frame(x: np.ndarray) -> np.ndarray:
    g = Geometry(positions_m=x, position_std_m=np.zeros(len(x)), offsets_s=np.zeros(len(x)),
                 offset_std_s=np.zeros(len(x)), drifts_ppm=np.zeros(len(x)), drift_std_ppm=np.zeros(len(x)),
                 verdict="truth", n_events=0)
    return g.mic_frame_positions_m()


def simulate_session(out_dir: str | Path, *, n_devices: int = 5, n_events: int = 16, seed: int = 0,
                     sample_rate_hz: int = 16000, room_m=(5.0, 4.0, 2.8), rt60_s: float = 0.3, max_order: int = 2,
                     interval_range_s=(0.9, 1.3), first_chirp_s: float = 1.0, tail_s: float = 1.5,
                     max_offset_s: float = 0.1, max_drift_ppm: float = 100.0, odometry_noise_m: float = 0.01,
                     chirp_duration_s: float = 0.1, chirp_f0_hz: float = 500.0, chirp_f1_hz: float = 6000.0,
                     chirp_gain: float = 0.3, speech_rms: float = 0.05, sensor_noise_rms: float = 3e-4,
                     array: tuple[int, np.ndarray] | None = None) -> Session:
    """Simulate a session and write it to ``out_dir``: ``dev00.wav ...`` (float WAV, each device's own clock)
    and ``odometry.csv`` (``dx_m,dy_m,dz_m,interval_s``).

    ``array = (d, mics_m)``: device ``d`` is a synchronous array of these mics (its own frame, metres), centred
    where the device would be and turned by a random yaw and a tilt of up to 20 degrees; its file has one
    channel per mic, and ``arrays.toml`` names it. The session's positions, offsets and drifts are then per
    channel (the array's mics one after the other, in device order)."""
    import pyroomacoustics as pra

    bf = fixture_builder()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    fs = int(sample_rate_hz)
    room = np.asarray(room_m, float)
    # devices spread in the room, at least 0.8 m apart
    while True:
        pos = np.column_stack([rng.uniform(0.4, room[0] - 0.4, n_devices), rng.uniform(0.4, room[1] - 0.4, n_devices),
                               rng.uniform(0.4, 1.6, n_devices)])
        d = np.linalg.norm(pos[:, None] - pos[None], axis=2) + 10 * np.eye(n_devices)
        if d.min() > 0.8:
            break
    offsets = rng.uniform(0.0, max_offset_s, n_devices)
    drifts = rng.uniform(-max_drift_ppm, max_drift_ppm, n_devices)
    array_rotation = None
    channel_device = np.arange(n_devices)
    if array is not None:   # the device's mics: its position becomes their centre; they share its clock
        from scipy.spatial.transform import Rotation
        d_arr, local = int(array[0]), np.asarray(array[1], float)
        array_rotation = Rotation.from_euler("ZYX", [rng.uniform(-180, 180), rng.uniform(-20, 20),
                                                     rng.uniform(-20, 20)], degrees=True).as_matrix()
        mics = pos[d_arr] + (local - local.mean(axis=0)) @ array_rotation.T
        channel_device = np.concatenate([[i] if i != d_arr else [i] * len(local) for i in range(n_devices)])
        pos = np.vstack([pos[i:i + 1] if i != d_arr else mics for i in range(n_devices)])
        offsets, drifts = offsets[channel_device], drifts[channel_device]
    n_channels = len(pos)
    talker = np.array([0.3 * room[0] + rng.uniform(-0.2, 0.2), 0.6 * room[1] + rng.uniform(-0.2, 0.2), 1.5])
    # the robot's path: an ellipse around the room centre with the loudspeaker going up and down
    theta = np.linspace(0.0, 1.6 * np.pi, n_events) + rng.uniform(-0.05, 0.05, n_events)
    centre = room / 2
    events = np.column_stack([centre[0] + 0.32 * room[0] * np.cos(theta), centre[1] + 0.30 * room[1] * np.sin(theta),
                              0.9 + 0.45 * np.sin(2.3 * theta + 0.4)])
    emit_idx = np.round((first_chirp_s + np.concatenate([[0.0], np.cumsum(rng.uniform(*interval_range_s,
                                                                                         n_events - 1))])) * fs)
    emission = (emit_idx + RIR_DELAY) / fs
    duration_s = emission[-1] + tail_s
    n_sync = int((duration_s + max_offset_s + 0.5) * fs)
    e_abs, _ = pra.inverse_sabine(rt60_s, list(room))

    def rirs(src):
        r = pra.ShoeBox(list(room), fs=fs, materials=pra.Material(float(e_abs)), max_order=max_order)
        r.add_source(list(src))
        r.add_microphone_array(pos.T)
        r.compute_rir()
        return [np.asarray(r.rir[m][0], float) for m in range(n_channels)]

    sync = np.zeros((n_channels, n_sync))
    # talker: the fixture's dry speech, looped with 0.4 s pauses
    s, rate = sf.read(SPEECH, dtype="float64")
    if rate != fs:
        import soxr
        s = soxr.resample(s, rate, fs)
    s = speech_rms * s / np.sqrt(np.mean(s ** 2))
    dry = np.zeros(n_sync)
    k = int(0.3 * fs)
    while k < n_sync:
        m = min(len(s), n_sync - k)
        dry[k:k + m] = s[:m]
        k += len(s) + int(0.4 * fs)
    for m, h in enumerate(rirs(talker)):
        sync[m] += scipy.signal.fftconvolve(dry, h)[:n_sync]
    template = estimators.linear_chirp(duration_s=chirp_duration_s, f0_hz=chirp_f0_hz, f1_hz=chirp_f1_hz,
                                       sample_rate_hz=fs)
    for j in range(n_events):
        for m, h in enumerate(rirs(events[j])):
            y = scipy.signal.fftconvolve(chirp_gain * template, h)
            a = int(emit_idx[j])
            z = min(a + len(y), n_sync)
            sync[m, a:z] += y[:z - a]
    peak = np.max(np.abs(sync))
    if peak > 0.5:   # no clipping after gains, reflections and noise (SI-SDR is scale-invariant)
        sync *= 0.5 / peak
    # each device samples the synchronous signal at its own instants
    n_dev = int(duration_s * fs)
    k = np.arange(n_dev)
    paths = []
    for i in range(n_devices):
        cols = []
        for c in np.flatnonzero(channel_device == i):
            t = offsets[c] + k / (fs * (1.0 + drifts[c] * 1e-6))
            cols.append(bf.band_limited_at(sync[c], t * fs, cutoff=0.95) + rng.normal(0.0, sensor_noise_rms, n_dev))
        p = out / f"dev{i:02d}.wav"
        sf.write(p, np.column_stack(cols).astype(np.float32), fs, subtype="FLOAT")
        paths.append(p)
    arrays_toml = None
    if array is not None:
        arrays_toml = out / "arrays.toml"
        rows = ", ".join(f"[{v[0]:.4f}, {v[1]:.4f}, {v[2]:.4f}]" for v in local)
        arrays_toml.write_text(f'[[array]]\nname = "dev{d_arr:02d}"\nmics_m = [{rows}]\n')
    t0 = offsets[0] + k / (fs * (1.0 + drifts[0] * 1e-6))
    dist0 = np.linalg.norm(talker - pos[0])
    clean = bf.band_limited_at(dry, (t0 - dist0 / C) * fs - RIR_DELAY, cutoff=0.95)
    steps = np.diff(events, axis=0) + rng.normal(0.0, odometry_noise_m, (n_events - 1, 3))
    iv = np.diff(emission)
    odo_path = out / "odometry.csv"
    np.savetxt(odo_path, np.column_stack([steps, iv]), delimiter=",", header="dx_m,dy_m,dz_m,interval_s",
               comments="", fmt="%.6f")
    arrival0 = (emission + np.linalg.norm(events - pos[0], axis=1) / C - offsets[0]) * (1.0 + drifts[0] * 1e-6)
    return Session(tuple(paths), odo_path, fs, pos, offsets, drifts, events, emission, iv, clean, arrival0,
                   template, dict(chirp_duration_s=chirp_duration_s, chirp_f0_hz=chirp_f0_hz,
                                  chirp_f1_hz=chirp_f1_hz), talker, array_rotation, arrays_toml)


def geometry_errors(session: Session, geometry: Geometry) -> dict[str, float]:
    """Errors of a geometry against the truth: positions in the mic frame (RMS and max over devices >= 1),
    offsets (ms) and drifts (ppm) relative to device 0."""
    truth = session.truth(geometry.first_event)
    pos = np.linalg.norm(geometry.mic_frame_positions_m() - _mic_frame(session.positions_m), axis=1)[1:]
    off = (geometry.offsets_s - truth["offsets_s"])[1:] * 1e3
    dr = (geometry.drifts_ppm - truth["drifts_ppm"])[1:]
    return {"position_rms_m": float(np.sqrt(np.mean(pos ** 2))), "position_max_m": float(np.max(pos)),
            "offset_rms_ms": float(np.sqrt(np.mean(off ** 2))), "offset_max_ms": float(np.max(np.abs(off))),
            "drift_rms_ppm": float(np.sqrt(np.mean(dr ** 2))), "drift_max_ppm": float(np.max(np.abs(dr))),
            "epoch_error_ms": float(1e3 * (geometry.epoch_clock_s - truth["epoch_clock_s"]))}


def enhancement_si_sdr_db(session: Session, enhanced: np.ndarray, *, guard_s: float = 0.35) -> float:
    """SI-SDR (dB) of the enhanced output against the dry talker on device 0's clock, outside the chirps
    (each chirp's arrival at device 0 minus 50 ms to plus ``guard_s`` is left out of both signals)."""
    fs = session.sample_rate_hz
    ref = session.clean_ref
    n = min(len(ref), len(enhanced))
    est, _ = metrics.align_to_reference(enhanced[:n], ref[:n], max_lag_samples=int(0.05 * fs))
    keep = np.ones(n, bool)
    for t in session.chirp_arrival_dev0_s:
        keep[max(0, int((t - 0.05) * fs)):max(0, int((t + guard_s) * fs))] = False
    keep[:int(1.0 * fs)] = False   # the engine's start-up
    return float(metrics.si_sdr_db(est[keep], ref[:n][keep]))


def replay_config(session: Session, *, apply: str = "drift", recalibrate_every: int = 6, **kw):
    from stream.config import EngineConfig
    return EngineConfig(plots=kw.pop("plots", False), progress=False, align_window_s=kw.pop("align_window_s", 4.0),
                        max_offset_s=kw.pop("max_offset_s", 0.5), calibration_odometry=str(session.odometry_csv),
                        recalibrate_every=recalibrate_every, calibration_apply=apply, **session.chirp, **kw)


def evaluate(session: Session, out_dir: Path, *, applies=("drift", "offsets", "none"), **kw) -> dict:
    """Replay the session once per ``calibration_apply`` mode; geometry errors, SI-SDR, timings."""
    from stream.run import run_replay
    result: dict = {}
    for apply in applies:
        t0 = time.perf_counter()
        outcome = run_replay(session.paths, Path(out_dir) / apply, config=replay_config(session, apply=apply, **kw))
        wall = time.perf_counter() - t0
        cal = outcome.report["calibration"]
        g = outcome.pipeline.calibrator.geometry
        entry = {"si_sdr_db": round(enhancement_si_sdr_db(session, outcome.pipeline.enhanced_signal()), 3),
                 "wall_s": round(wall, 2), "n_solves": cal["n_solves"], "n_adopted": cal["n_adopted"],
                 "solve_time_s": [round(s["solve_time_s"], 4) for s in cal["solves"] if s["solve_time_s"]],
                 "step_ms_max": round(cal["step_ms_max"], 3),
                 "block_ms_p95": round(outcome.report["timing"]["block_ms_p95"], 3),
                 "messages": cal["messages"]}
        if g is not None:
            entry["verdict"] = g.verdict
            entry["n_events"] = g.n_events
            entry.update({k: round(v, 5) for k, v in geometry_errors(session, g).items()})
        result[apply] = entry
    return result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", type=int, default=8)
    ap.add_argument("--events", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-order", type=int, default=3)
    ap.add_argument("--recalibrate-every", type=int, default=8)
    ap.add_argument("--executor", choices=["thread", "process"], default="thread")
    ap.add_argument("--out", type=Path, default=None, help="keep the session and the runs here")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        t0 = time.perf_counter()
        session = simulate_session(out / "session", n_devices=args.devices, n_events=args.events, seed=args.seed,
                                   max_order=args.max_order)
        sim_s = time.perf_counter() - t0
        res = evaluate(session, out / "runs", recalibrate_every=args.recalibrate_every,
                       calibration_executor=args.executor)
    print(json.dumps({"devices": args.devices, "events": args.events, "seed": args.seed,
                      "audio_s": round(len(session.clean_ref) / session.sample_rate_hz, 1),
                      "simulate_s": round(sim_s, 2), **res}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
