"""Throughput of the per-hop path against its FFT floor, pyroomacoustics and the real-time budget.

Measured side by side in one process (the machine is shared and noisy: medians and same-process
ratios only; competing paths are interleaved in alternating rounds so load changes hit them alike):

1. GCC-PHAT of 8 channels (28 pairs), 1024-sample frames at 16 kHz:

   - ``gcc_ms_8ch``: :func:`estimators.gcc_phat` on the time-domain frame (window, 8 rfft, PHAT,
     28 cross-spectra, one batched irfft, peak search);
   - ``gcc_spectra_ms_8ch``: :meth:`estimators.GccPhat.process` on precomputed spectra;
   - ``pra_gcc_ms_8ch``: a Python loop over the 28 pairs calling
     ``pyroomacoustics.sync.tdoa(x_i, x_j, interp=1, phat=True, fs=sample_rate_hz)`` (seconds out:
     its ``fs=1`` default returns samples). Its pair convention matches ours:
     ``tdoa(signal, reference) = toa_signal - toa_reference``.

2. The full per-hop path of :meth:`stream.pipeline.Pipeline.process_block` (StreamingStft ->
   GccPhat (with the device validity mask) -> KalmanToa.update -> DelayAndSum.process_spectra, options
   from :class:`stream.config.EngineConfig`) for 8 and 16 devices at 48 kHz (frame 4096, hop 1024) and
   16 kHz (frame 512, hop 128), with equal weights (the engine's default) and with adaptive weights:
   median ms per hop, real-time factor ``ms per hop / hop duration in ms``, and
   ``ratio_to_fft_floor``: path / floor, where the floor is the FFTs the hop cannot avoid and nothing
   else: M ``rfft`` of the frame, ``M (M - 1) / 2`` ``irfft`` for the pair correlations, one ``irfft``
   for the beamformer output, float32 / complex64. The stages compute their FFTs with pocketfft inside
   compiled numba kernels (rocket-fft), so the floor is timed the same way: three compiled calls, one
   per FFT group, as the three stages make them (``fft_floor_ms_*``; the analysis and correlation FFTs
   into preallocated outputs, as the stages write theirs, which saves ~1 us per hop at 8 x 512 against
   allocating them: a floor that allocated would flatter the ratio). That is about half of what the
   same FFTs cost through ``scipy.fft`` (``workers=1``), which is also timed and reported
   (``scipy_fft_floor_ms_*``, ``ratio_to_scipy_fft_floor``): a path that merely switched to the faster
   FFT binding would look better against the scipy floor without being leaner anywhere else.

3. CPU share of one core, ``process_time / audio duration`` (median of runs over
   ``--cpu-audio-s`` seconds of audio): the bare path at 8 devices, 16 kHz, hop 128, and the whole
   engine (:func:`stream.run.run_replay` on 8 synthetic WAV files: replay source, conditioning,
   aligner, pipeline, sinks, report).

Input is speech-like: band-limited noise with syllable-rate amplitude modulation and short pauses,
each device delayed by a fixed fractional delay (circularly, so the signal loops seamlessly) plus
independent sensor noise 25 dB down. The Kalman filter must be updating: the fraction of hops with an
accepted measurement update is reported per configuration.

Run ``python benchmarks/throughput.py`` (``--quick`` for a smoke run; ``--profile`` adds a clock
split of the engine's parts to the table and JSON and prints the cProfile top entries of the path
and the engine to stderr, after all timings). The last line of stdout is one JSON object.
"""
from __future__ import annotations

import os

# The engine asks for one BLAS thread (stream/__init__.py); measure under the same setting.
for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import cProfile  # noqa: E402
import io  # noqa: E402
import json  # noqa: E402
import pathlib  # noqa: E402
import pstats  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402

import numba  # noqa: E402
import numpy as np  # noqa: E402
import scipy.fft  # noqa: E402
import scipy.signal  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

import beamform  # noqa: E402
import estimators  # noqa: E402
from stream.config import EngineConfig  # noqa: E402
from stream.pipeline import make_estimator  # noqa: E402

SEED = 20240611
REPO = pathlib.Path(__file__).resolve().parents[1]
MAX_DELAY_S = 1.5e-3          # per-device delays drawn in +-MAX_DELAY_S (well inside max_tdoa_s)
SENSOR_SNR_DB = 25.0
GCC_N_CHANNELS = 8
GCC_FRAME_SAMPLES = 1024
GCC_RATE_HZ = 16_000.0
GCC_N_FRAMES = 64             # distinct frames cycled through by the GCC benchmark
CPU_CONFIG = (8, 16_000.0, 512, 128)


@dataclass(frozen=True)
class PathConfig:
    n_devices: int
    sample_rate_hz: float
    frame_samples: int
    hop_samples: int
    max_tdoa_s: float | None = None  # None: the engine default (EngineConfig.max_tdoa_s)
    weighting: str = "equal"         # the engine's default; "adaptive" is measured too

    @property
    def key(self) -> str:
        base = f"{self.n_devices}dev_{int(self.sample_rate_hz / 1000)}k_{self.frame_samples}"
        return base if self.weighting == "equal" else f"{base}_{self.weighting}"

    @property
    def hop_ms(self) -> float:
        return 1e3 * self.hop_samples / self.sample_rate_hz


PATH_CONFIGS = tuple(
    PathConfig(m, fs, frame, hop, weighting=w)
    for w in ("equal", "adaptive")
    for m, fs, frame, hop in ((8, 48_000.0, 4096, 1024), (16, 48_000.0, 4096, 1024),
                              (8, 16_000.0, 512, 128), (16, 16_000.0, 512, 128))
)
# Overhead probe: the same chain on 64-sample frames, where every FFT is nearly free, so its time is
# the per-hop cost that does not scale with the frame (Python and numpy call overhead). Reported,
# not part of the ratio_to_fft_floor maximum.
OVERHEAD_PROBE = PathConfig(8, 16_000.0, 64, 16, max_tdoa_s=1e-3)


# ---------------------------------------------------------------------------------------- input
def speech_like(n_samples: int, *, sample_rate_hz: float, rng: np.random.Generator) -> np.ndarray:
    """Band-limited (100 Hz - 5 kHz, -6 dB/octave above 500 Hz) noise, amplitude-modulated by
    syllables of 80-250 ms grouped into bursts of 0.4-1.5 s separated by 60-200 ms pauses that keep
    a background 30 dB down. Shape (n_samples,), float64, unit-ish RMS."""
    x = rng.standard_normal(n_samples)
    b, a = scipy.signal.butter(2, [100.0, min(5000.0, 0.45 * sample_rate_hz)], btype="band", fs=sample_rate_hz)
    x = scipy.signal.lfilter(b, a, x)
    b1, a1 = scipy.signal.butter(1, 500.0, fs=sample_rate_hz)
    x = 0.3 * x + scipy.signal.lfilter(b1, a1, x)
    env = np.full(n_samples, 10 ** (-30 / 20))
    t = 0
    while t < n_samples:
        burst_end = min(n_samples, t + int(rng.uniform(0.4, 1.5) * sample_rate_hz))
        while t < burst_end:
            n_syl = int(rng.uniform(0.08, 0.25) * sample_rate_hz)
            seg = np.sin(np.pi * np.arange(n_syl) / n_syl) ** 2 * rng.uniform(0.4, 1.0)
            stop = min(n_samples, t + n_syl)
            env[t:stop] = np.maximum(env[t:stop], seg[: stop - t])
            t = stop
        t += int(rng.uniform(0.06, 0.2) * sample_rate_hz)
    y = x * env
    return y / np.sqrt(np.mean(y**2))


def delayed_channels(source: np.ndarray, delays_s: np.ndarray, *, sample_rate_hz: float,
                     rng: np.random.Generator) -> np.ndarray:
    """``x_i[n] = g_i s(n - delay_i fs)`` (circular, fractional, via the FFT) plus white sensor noise
    ``SENSOR_SNR_DB`` below. Shape (n_samples, n_devices), float32, peak 0.5."""
    n = len(source)
    S = np.fft.rfft(source)
    omega = 2 * np.pi * np.fft.rfftfreq(n, d=1.0 / sample_rate_hz)
    gains = rng.uniform(0.5, 1.0, len(delays_s))
    X = S[:, None] * np.exp(-1j * omega[:, None] * delays_s[None, :]) * gains
    x = np.fft.irfft(X, n=n, axis=0)
    x += rng.standard_normal(x.shape) * np.sqrt(np.mean(x**2, axis=0)) * 10 ** (-SENSOR_SNR_DB / 20)
    return (0.5 * x / np.abs(x).max()).astype(np.float32)


def scene(n_devices: int, sample_rate_hz: float, duration_s: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(audio (n_samples, n_devices) float32, relative TOA (n_devices,) s with toa[0] = 0)."""
    rng = np.random.default_rng(seed)
    n = int(round(duration_s * sample_rate_hz))
    delays = rng.uniform(-MAX_DELAY_S, MAX_DELAY_S, n_devices)
    delays[0] = 0.0
    return delayed_channels(speech_like(n, sample_rate_hz=sample_rate_hz, rng=rng), delays,
                            sample_rate_hz=sample_rate_hz, rng=rng), delays


# ---------------------------------------------------------------------------------------- stages
class HopPath:
    """The per-hop chain of Pipeline.process_block, without recording and re-centring."""

    def __init__(self, cfg: PathConfig) -> None:
        extra = {} if cfg.max_tdoa_s is None else {"max_tdoa_s": cfg.max_tdoa_s}
        engine = EngineConfig(working_rate_hz=cfg.sample_rate_hz, frame_samples=cfg.frame_samples, estimator="kalman",
                              hop_samples=cfg.hop_samples, weighting=cfg.weighting, **extra).resolved(cfg.sample_rate_hz)
        m, fs = cfg.n_devices, cfg.sample_rate_hz
        self.stft = beamform.StreamingStft(m, frame_samples=cfg.frame_samples, hop_samples=cfg.hop_samples)
        self.gcc = estimators.GccPhat(m, n_fft=cfg.frame_samples, sample_rate_hz=fs, max_tdoa_s=engine.max_tdoa_s)
        self.estimator = make_estimator(engine, m)
        self.das = beamform.DelayAndSum(m, frame_samples=cfg.frame_samples, hop_samples=cfg.hop_samples,
                                        sample_rate_hz=fs, weighting=engine.weighting)
        self.valid = np.ones(m, bool)
        self.n_hops = self.n_updates = self.n_gated = 0
        self.toa_s = np.zeros(m)

    def hop(self, block: np.ndarray) -> np.ndarray:
        valid = self.valid
        spectra = self.stft.process(block)
        tdoa_s, confidence = self.gcc.process(spectra, valid=valid)
        fine = self.estimator.update(tdoa_s, confidence)
        out = self.das.process_spectra(spectra, fine, valid=valid)
        self.toa_s = fine
        return out

    def hop_staged(self, block: np.ndarray, times: dict[str, list[float]]) -> np.ndarray:
        """:meth:`hop` with a clock between the stages (appends seconds to ``times[stage]``)."""
        perf = time.perf_counter
        valid = self.valid
        t0 = perf()
        spectra = self.stft.process(block)
        t1 = perf()
        tdoa_s, confidence = self.gcc.process(spectra, valid=valid)
        t2 = perf()
        fine = self.estimator.update(tdoa_s, confidence)
        t3 = perf()
        out = self.das.process_spectra(spectra, fine, valid=valid)
        t4 = perf()
        self.toa_s = fine
        for name, a, b in (("stft", t0, t1), ("gcc", t1, t2), ("kalman", t2, t3), ("das", t3, t4)):
            times[name].append(b - a)
        return out

    def count(self) -> None:
        """Book-keeping of the Kalman's last step (outside the timed region)."""
        est = self.estimator
        self.n_hops += 1
        self.n_gated += int(est.gated)
        self.n_updates += int(est.initialised and not est.gated and est.n_pairs_used > 0
                              and not est.reinitialised)


@numba.njit(cache=True, nogil=True)
def _rfft_rows(x, out):
    np.fft.rfft(x, x.shape[1], -1, None, out)


@numba.njit(cache=True, nogil=True)
def _irfft_rows(c, out):
    np.fft.irfft(c, out.shape[-1], -1, None, out)


@numba.njit(cache=True, nogil=True)
def _irfft(c, n):
    return np.fft.irfft(c, n)


class Floor:
    """The FFTs one hop must do: M rfft of the frame, n_pairs irfft, 1 irfft (float32/complex64).

    ``ffts`` makes them as the stages do, with pocketfft inside three compiled calls (one per FFT
    group: analysis, pair correlations, synthesis), the first two into preallocated outputs (as
    ``StreamingStft`` and ``GccPhat`` write theirs) and the synthesis into a new array (as
    ``DelayAndSum`` does); ``scipy_ffts`` through ``scipy.fft``.
    """

    def __init__(self, cfg: PathConfig) -> None:
        m, n = cfg.n_devices, cfg.frame_samples
        self.n = n
        self.frame = np.empty((m, n), np.float32)  # channel-major: the fastest layout
        n_bins = n // 2 + 1
        rng = np.random.default_rng(1)
        self.cross = (rng.standard_normal((m * (m - 1) // 2, n_bins))
                      + 1j * rng.standard_normal((m * (m - 1) // 2, n_bins))).astype(np.complex64)
        self.out = self.cross[0].copy()
        self.spectra = np.empty((m, n_bins), np.complex64)
        self.corr = np.empty((m * (m - 1) // 2, n), np.float32)

    def load(self, frame_time_major: np.ndarray) -> None:
        """Copy a frame in (outside the timed call)."""
        self.frame[...] = frame_time_major.T

    def ffts(self) -> None:
        _rfft_rows(self.frame, self.spectra)
        _irfft_rows(self.cross, self.corr)
        _irfft(self.out, self.n)

    def scipy_ffts(self) -> None:
        n = self.n
        scipy.fft.rfft(self.frame, axis=-1, workers=1)
        scipy.fft.irfft(self.cross, n=n, axis=-1, workers=1)
        scipy.fft.irfft(self.out, n=n, workers=1)


# ---------------------------------------------------------------------------------------- GCC
def pra_gcc(tdoa, frame: np.ndarray, pairs_ij: list[tuple[int, int]], sample_rate_hz: float) -> np.ndarray:
    """``tdoa_s[p] = toa_i - toa_j`` by ``pyroomacoustics.sync.tdoa`` called once per pair.

    ``tdoa(signal, reference, interp=1, phat=False, fs=1)``: zero-padded linear correlation of
    ``N1 + N2 - 1`` points (numpy.fft, float64), peak over all lags, integer lags for ``interp=1``,
    in samples for ``fs=1`` and in seconds for ``fs=sample_rate_hz``; positive when ``signal`` lags.
    """
    out = np.empty(len(pairs_ij))
    for p, (i, j) in enumerate(pairs_ij):
        out[p] = tdoa(frame[:, i], frame[:, j], interp=1, phat=True, fs=sample_rate_hz)
    return out


def bench_gcc(repeats: int, frames_per_round: int) -> dict:
    from pyroomacoustics.sync import tdoa as pra_tdoa

    m, n, fs = GCC_N_CHANNELS, GCC_FRAME_SAMPLES, GCC_RATE_HZ
    audio, toa = scene(m, fs, (GCC_N_FRAMES + 1) * n / fs, SEED + 1)
    frames = [np.ascontiguousarray(audio[k * n:(k + 1) * n]) for k in range(GCC_N_FRAMES)]
    win = beamform.analysis_window("hann", n)
    spectra = [scipy.fft.rfft(f * win[:, None], axis=0, workers=1) for f in frames]
    p = estimators.pairs(m)
    pi, pj = p[:, 0], p[:, 1]
    truth_s = toa[pi] - toa[pj]
    gcc = estimators.GccPhat(m, n_fft=n, sample_rate_hz=fs)

    def ours(k):
        return estimators.gcc_phat(frames[k], sample_rate_hz=fs)

    def ours_spectra(k):
        return gcc.process(spectra[k])

    pairs_ij = [(int(i), int(j)) for i, j in zip(pi, pj)]

    def pra_loop(k):
        return pra_gcc(pra_tdoa, frames[k], pairs_ij, fs)

    # accuracy (not timed): frames whose PHAT peak is confident
    err_ours, err_pra = [], []
    for k in range(GCC_N_FRAMES):
        t, c = ours(k)
        tp = pra_loop(k)
        good = c > 5 / np.sqrt(n)
        err_ours.append(np.abs(t - truth_s)[good])
        err_pra.append(np.abs(tp - truth_s)[good])
    err_ours = np.concatenate(err_ours) * fs
    err_pra = np.concatenate(err_pra) * fs

    funcs = {"gcc": ours, "gcc_spectra": ours_spectra, "pra": pra_loop}
    times = {name: [] for name in funcs}
    for name, f in funcs.items():  # warm-up
        for k in range(8):
            f(k)
    order = list(funcs)
    pos = 0
    for r in range(repeats):
        for name in (order if r % 2 == 0 else order[::-1]):
            f = funcs[name]
            for q in range(frames_per_round):
                k = (pos + q) % GCC_N_FRAMES
                t0 = time.perf_counter()
                f(k)
                times[name].append(time.perf_counter() - t0)
        pos += frames_per_round
    med = {name: 1e3 * float(np.median(v)) for name, v in times.items()}
    return {
        "gcc_ms_8ch": med["gcc"],
        "gcc_spectra_ms_8ch": med["gcc_spectra"],
        "pra_gcc_ms_8ch": med["pra"],
        "gcc_speedup_vs_pra": med["pra"] / med["gcc"],
        "gcc_n_frames_timed": len(times["gcc"]),
        "gcc_median_abs_err_samples": float(np.median(err_ours)),
        "pra_median_abs_err_samples": float(np.median(err_pra)),
        "gcc_within_1_sample": float(np.mean(err_ours <= 1.0)),
        "pra_within_1_sample": float(np.mean(err_pra <= 1.0)),
    }


# ---------------------------------------------------------------------------------------- path
STAGES = ("stft", "gcc", "kalman", "das")


def bench_paths(repeats: int, hops_per_round: int, audio_s: float) -> tuple[dict, list[dict]]:
    """Path and floor per config, interleaved: every round runs each config's floor and path for
    ``hops_per_round`` hops, in an order that alternates between rounds. Then a shorter pass with a
    clock between the stages (per-stage medians; their sum is close to, not equal to, the path)."""
    configs = PATH_CONFIGS + (OVERHEAD_PROBE,)
    state = {}
    for k, cfg in enumerate(configs):
        audio, toa = scene(cfg.n_devices, cfg.sample_rate_hz, audio_s, SEED + 10 + k)
        n_hops = len(audio) // cfg.hop_samples
        audio = audio[: n_hops * cfg.hop_samples]
        path, floor = HopPath(cfg), Floor(cfg)
        # warm-up: 2 s of audio through the path (the Kalman initialises, the beamformer's start-up
        # ALS iterations end after 1 s), a few floors
        pos = 0
        for _ in range(int(np.ceil(2.0 * cfg.sample_rate_hz / cfg.hop_samples))):
            path.hop(audio[pos * cfg.hop_samples:(pos + 1) * cfg.hop_samples])
            pos = (pos + 1) % n_hops
        floor.load(audio[: cfg.frame_samples])
        for _ in range(20):
            floor.ffts()
            floor.scipy_ffts()
        path.n_hops = path.n_updates = path.n_gated = 0
        state[cfg] = dict(audio=audio, toa=toa, n_hops=n_hops, pos=pos, path=path, floor=floor,
                          t_path=[], t_floor=[], t_scipy=[], toa_err=[], stages={name: [] for name in STAGES})

    perf = time.perf_counter
    for r in range(repeats):
        for cfg in (configs if r % 2 == 0 else configs[::-1]):
            s = state[cfg]
            path, floor, audio, hop, n_hops = s["path"], s["floor"], s["audio"], cfg.hop_samples, s["n_hops"]
            runs = ("floor", "scipy", "path") if r % 4 < 2 else ("path", "scipy", "floor")
            for what in runs:
                if what in ("floor", "scipy"):
                    start = (s["pos"] * hop) % (len(audio) - cfg.frame_samples)
                    floor.load(audio[start:start + cfg.frame_samples])
                    ffts, times = (floor.ffts, s["t_floor"]) if what == "floor" else (floor.scipy_ffts, s["t_scipy"])
                    for _ in range(hops_per_round):
                        t0 = perf()
                        ffts()
                        times.append(perf() - t0)
                else:
                    pos = s["pos"]
                    for _ in range(hops_per_round):
                        block = audio[pos * hop:(pos + 1) * hop]
                        t0 = perf()
                        path.hop(block)
                        s["t_path"].append(perf() - t0)
                        path.count()
                        if path.estimator.initialised:
                            s["toa_err"].append(np.abs(path.toa_s - s["toa"]).max())
                        pos = (pos + 1) % n_hops
                    s["pos"] = pos
    for r in range(max(1, repeats // 2)):  # stage split, also interleaved
        for cfg in (configs if r % 2 == 0 else configs[::-1]):
            s = state[cfg]
            path, audio, hop, pos = s["path"], s["audio"], cfg.hop_samples, s["pos"]
            for _ in range(hops_per_round):
                path.hop_staged(audio[pos * hop:(pos + 1) * hop], s["stages"])
                pos = (pos + 1) % s["n_hops"]
            s["pos"] = pos

    out, rows = {}, []
    for cfg in configs:
        s = state[cfg]
        key = cfg.key
        path_ms = 1e3 * float(np.median(s["t_path"]))
        floor_ms = 1e3 * float(np.median(s["t_floor"]))
        scipy_floor_ms = 1e3 * float(np.median(s["t_scipy"]))
        p = s["path"]
        row = {
            "config": key, "n_devices": cfg.n_devices, "rate_khz": cfg.sample_rate_hz / 1000,
            "frame": cfg.frame_samples, "hop": cfg.hop_samples, "hop_ms": cfg.hop_ms,
            "path_ms": path_ms, "path_p90_ms": 1e3 * float(np.percentile(s["t_path"], 90)),
            "floor_ms": floor_ms, "ratio": path_ms / floor_ms, "rtf": path_ms / cfg.hop_ms,
            "scipy_floor_ms": scipy_floor_ms, "ratio_scipy": path_ms / scipy_floor_ms,
            "weighting": cfg.weighting,
            "n_hops": len(s["t_path"]),
            "update_fraction": p.n_updates / max(p.n_hops, 1),
            "gated_fraction": p.n_gated / max(p.n_hops, 1),
            "toa_err_median_samples": float(np.median(s["toa_err"])) * cfg.sample_rate_hz if s["toa_err"] else None,
            "stages_ms": {name: 1e3 * float(np.median(v)) for name, v in s["stages"].items() if v},
            "probe": cfg is OVERHEAD_PROBE,
        }
        rows.append(row)
        out[f"path_ms_{key}"] = path_ms
        out[f"fft_floor_ms_{key}"] = floor_ms
        out[f"rtf_{key}"] = row["rtf"]
        out[f"ratio_to_fft_floor_{key}"] = row["ratio"]
        out[f"scipy_fft_floor_ms_{key}"] = scipy_floor_ms
        out[f"ratio_to_scipy_fft_floor_{key}"] = row["ratio_scipy"]
        out[f"kalman_update_fraction_{key}"] = row["update_fraction"]
        out[f"toa_err_median_samples_{key}"] = row["toa_err_median_samples"]
        out[f"stages_ms_{key}"] = row["stages_ms"]
    out["ratio_to_fft_floor"] = max(r["ratio"] for r in rows if not r["probe"])
    out["ratio_to_fft_floor_equal"] = max(r["ratio"] for r in rows if not r["probe"] and r["weighting"] == "equal")
    out["ratio_to_scipy_fft_floor"] = max(r["ratio_scipy"] for r in rows if not r["probe"])
    return out, rows


# ---------------------------------------------------------------------------------------- CPU
def bench_cpu_path(repeats: int, audio_s: float) -> dict:
    """process_time and thread_time of the bare path over ``audio_s`` of audio, fresh stages per run."""
    m, fs, frame, hop = CPU_CONFIG
    cfg = PathConfig(m, fs, frame, hop, weighting="adaptive")  # the costlier weighting, as the engine run
    audio, _ = scene(m, fs, audio_s, SEED + 100)
    n_hops = len(audio) // hop
    blocks = [audio[k * hop:(k + 1) * hop] for k in range(n_hops)]
    proc, thread = [], []
    for r in range(repeats + 1):  # run 0 is the warm-up
        path = HopPath(cfg)
        p0, t0 = time.process_time(), time.thread_time()
        for b in blocks:
            path.hop(b)
        p1, t1 = time.process_time(), time.thread_time()
        if r:
            proc.append(p1 - p0)
            thread.append(t1 - t0)
    duration_s = n_hops * hop / fs
    return {
        "cpu_fraction_8dev_16k_hop128": float(np.median(proc)) / duration_s,
        "cpu_fraction_8dev_16k_hop128_thread": float(np.median(thread)) / duration_s,
        "cpu_runs_audio_s": duration_s,
    }


def write_wavs(folder: pathlib.Path, n_devices: int, sample_rate_hz: float, audio_s: float) -> list[pathlib.Path]:
    import soundfile as sf

    audio, _ = scene(n_devices, sample_rate_hz, audio_s, SEED + 200)
    paths = []
    for d in range(n_devices):
        p = folder / f"dev{d}.wav"
        sf.write(str(p), audio[:, d], int(sample_rate_hz), subtype="FLOAT")
        paths.append(p)
    return paths


def bench_engine(repeats: int, audio_s: float, profile: bool) -> dict:
    import logging

    from stream.run import run_replay

    logging.getLogger().setLevel(logging.ERROR)
    m, fs, frame, hop = CPU_CONFIG
    # the bare path's stages: the Kalman TOA (the default is the tracker since 2026-11-26: bench_engine_tracks),
    # adaptive weighting
    config = EngineConfig(working_rate_hz=fs, frame_samples=frame, hop_samples=hop, weighting="adaptive",
                          estimator="kalman", plots=False, progress=False)
    fractions, wall, block_ms, in_blocks = [], [], [], []
    with tempfile.TemporaryDirectory(prefix="throughput_") as tmp:
        tmp = pathlib.Path(tmp)
        wavs = write_wavs(tmp, m, fs, audio_s)
        for r in range(repeats + 1):  # run 0 is the warm-up (imports, caches)
            outcome = run_replay(wavs, tmp / f"out{r}", config=config)
            rep = outcome.report
            audio = rep["stream"]["audio_s"]
            if r:
                fractions.append(rep["timing"]["cpu_s"] / audio)
                wall.append(rep["timing"]["wall_s"] / audio)
                block_ms.append(rep["timing"]["block_ms_median"])
                # Pipeline.process_block wall time (stages + its book-keeping, not the sinks)
                in_blocks.append(1e-3 * outcome.pipeline.hop_times.sum_ms / audio)
        n_gated = rep["stream"]["n_gated"]
        n_blocks = rep["stream"]["n_blocks"]
        split = None
        if profile:
            split = engine_split(wavs, tmp / "split", config)
            prof = cProfile.Profile()
            prof.enable()
            run_replay(wavs, tmp / "profiled", config=config)
            prof.disable()
            print_profile(prof, "engine: run_replay, 8 devices, 16 kHz, frame 512, hop 128")
    result = {
        "cpu_fraction_8dev_16k_hop128_engine": float(np.median(fractions)),
        "engine_wall_fraction_8dev_16k_hop128": float(np.median(wall)),
        "engine_process_block_fraction": float(np.median(in_blocks)),
        "engine_block_ms_median": float(np.median(block_ms)),
        "engine_gated_fraction": n_gated / max(n_blocks, 1),
        "engine_audio_s": audio,
    }
    if split is not None:
        result["engine_split_fraction"] = split
    return result


TRACKS_SCENES = ("s14_noise_table_babble_5dB", "s42_two_talkers_table_white_10dB")   # 8 devices, 16 kHz


def _rewritten(files: list, tmp: pathlib.Path, name: str, change) -> list[pathlib.Path]:
    """Every file through ``change(x, fs) -> (y, rate)``, written as 16-bit WAV (as the scene files' FLAC hold)
    to ``tmp`` as ``name`` (a format string of the file's ``stem``) plus ".wav"."""
    import soundfile as sf

    out = []
    for f in files:
        x, fs = sf.read(f, dtype="float32")
        y, rate = change(x, fs)
        path = tmp / (name.format(stem=pathlib.Path(f).stem) + ".wav")
        sf.write(path, y, rate, subtype="PCM_16")
        out.append(path)
    return out


def _inputs_16k(files: list, tmp: pathlib.Path) -> list[pathlib.Path]:
    """The files resampled to 16 kHz (soxr): devices that record at the issue's rate."""
    import soxr

    return _rewritten(files, tmp, "{stem}_16k", lambda x, fs: (soxr.resample(x, fs, 16000), 16000))


def _first_half(files: list, tmp: pathlib.Path, tag: str) -> list[pathlib.Path]:
    """The first half of every device file (the same seconds on every device, each at its own rate): the
    running cost of a stream is the difference between the whole input and its first half, in which the
    start-up (numba caches, the speech model, the first alignment over the same window) and the report cancel."""
    import soundfile as sf

    seconds = min(sf.info(str(f)).duration for f in files) / 2
    return _rewritten(files, tmp, tag + "_{stem}_half", lambda x, fs: (x[:int(round(seconds * fs))], fs))


def _scene_inputs(data: pathlib.Path, tmp: pathlib.Path) -> dict[str, list]:
    """Device files of :data:`TRACKS_SCENES` (``benchmarks/scenes.py``, seed 7), built from ``data``."""
    import scenes as sc   # benchmarks/scenes.py: pyroomacoustics rooms, real speech and noise

    sc.DATA = data   # the speech files' lengths place the talkers
    out = {}
    for kind, snr, scene in sc.make_scenes(7):
        if scene.name in TRACKS_SCENES:
            sc.bf.build(scene, data, tmp)
            out[scene.name] = sorted((tmp / scene.name).glob("dev*.flac"))
    return out


def bench_engine_tracks(repeats: int, data: pathlib.Path | None = None) -> dict:
    """The whole engine with the multi-source tracker (``estimator="tracks"``: Silero speech presence,
    noise-aware multi-peak GCC-PHAT, the bank of TOA tracks) against the same engine with the single
    ``KalmanToa``, the tracker without replay's look-ahead (``tracks_causal``, live's setting), the tracker
    measuring every 8 ms hop instead of every 16 ms (``tracks_every_hop``: ``track_interval_s = 0``) and with the
    WebRTC detector instead of Silero (``tracks_webrtc``), alternating
    runs in this process, on real speech, frame 512, hop 128, working rate 16 kHz, 8 devices:

    - ``async_8dev``: the 8 device files of the shipped fixture as recorded (48 / 44.1 kHz: decoding and
      resampling to 16 kHz are part of the run), given as plain files so that no evaluation runs;
    - ``async_8dev_16k``: the same recordings resampled to 16 kHz beforehand (devices that record at 16 kHz);
    - with ``data`` (``../shared/data``): two 8-device scenes of ``benchmarks/scenes.py`` at 16 kHz, a
      babble noise source at 5 dB and two talkers taking turns with white noise at 10 dB.

    CPU share of one core (process time / audio duration, setup and report included) and the median
    ``Pipeline.process_block`` time per hop, also as a ratio to the FFT floor of 8 x 512. On the scenes (16 s,
    twice the first alignment's 8 s window) also the share of the running stream
    (``engine_running_cpu_fraction_by_input``): the process time of the whole input minus that of its first half
    (:func:`_first_half`, run in the same round) over the audio between them; the start-up, paid once per stream
    (about 0.1 s of a core: kernels from the cache, the speech model, the first alignment), and the report
    cancel, which is what a stream that runs for minutes pays per second."""
    import logging

    from stream.scoring.fixture import load_fixture
    from stream.run import run_replay

    logging.getLogger().setLevel(logging.ERROR)
    m, fs, frame, hop = CPU_CONFIG
    fx = load_fixture(REPO / "replay_fixtures" / "async_8dev")
    variants = {"kalman": {"estimator": "kalman"}, "tracks": {"estimator": "tracks"},
                "tracks_causal": {"estimator": "tracks", "tracker_lookahead_s": 0.0},   # live's setting
                # the tracker measuring every hop (8 ms) instead of every 16 ms (track_interval_s, the default)
                "tracks_every_hop": {"estimator": "tracks", "track_interval_s": 0.0},
                "tracks_webrtc": {"estimator": "tracks", "vad": "webrtc"}}
    cpu: dict[str, dict[str, list]] = {}
    block: dict[str, list] = {v: [] for v in variants}
    block_mean: dict[str, list] = {v: [] for v in variants}
    backend = ""
    with tempfile.TemporaryDirectory(prefix="throughput_tracks_") as tmp:
        tmp = pathlib.Path(tmp)
        inputs = {"async_8dev": [d.path for d in fx.devices][:m]}
        inputs["async_8dev_16k"] = _inputs_16k(inputs["async_8dev"], tmp)
        halves = {}
        if data is not None:
            scenes = _scene_inputs(data, tmp)
            inputs.update(scenes)
            halves = {name: _first_half(files, tmp, name) for name, files in scenes.items()}
        running: dict[str, dict[str, list]] = {}
        for r in range(repeats + 1):   # run 0 is the warm-up (imports, compiled caches, the VAD model)
            for name, files in inputs.items():
                for v, opts in variants.items():
                    config = EngineConfig(working_rate_hz=fs, frame_samples=frame, hop_samples=hop, plots=False,
                                          progress=False, **opts)
                    rep = run_replay(files, tmp / f"{name}_{v}_{r}", config=config).report
                    if name in halves:   # its first half, right after (the same load)
                        half = run_replay(halves[name], tmp / f"{name}_{v}_{r}_half", config=config).report
                    if not r:
                        continue
                    cpu.setdefault(name, {}).setdefault(v, []).append(rep["timing"]["cpu_s"] / rep["stream"]["audio_s"])
                    if name in halves:
                        running.setdefault(name, {}).setdefault(v, []).append(
                            (rep["timing"]["cpu_s"] - half["timing"]["cpu_s"])
                            / (rep["stream"]["audio_s"] - half["stream"]["audio_s"]))
                    if name == "async_8dev":
                        block[v].append(rep["timing"]["block_ms_median"])
                        block_mean[v].append(rep["timing"]["block_ms_mean"])
                    if v == "tracks":
                        backend = rep.get("sources", {}).get("speech_presence", {}).get("backend", "")
    floor = Floor(PathConfig(m, fs, frame, hop))
    floor.load(np.zeros((frame, m), np.float32))
    ts = []
    for _ in range(200):
        t0 = time.perf_counter()
        floor.ffts()
        ts.append(time.perf_counter() - t0)
    floor_ms = 1e3 * float(np.median(ts[20:]))
    out = {"tracks_vad_backend": backend, "tracks_fft_floor_ms_8x512": floor_ms,
           "engine_cpu_fraction_by_input": {name: {v: float(np.median(x)) for v, x in by.items()}
                                            for name, by in cpu.items()},
           "engine_running_cpu_fraction_by_input": {name: {v: float(np.median(x)) for v, x in by.items()}
                                                    for name, by in running.items()}}
    for v in variants:
        out[f"engine_{v}_cpu_fraction_8dev_16k_hop128"] = float(np.median(cpu["async_8dev"][v]))
        out[f"engine_{v}_block_ms_median"] = float(np.median(block[v]))
        out[f"engine_{v}_block_ratio_to_fft_floor"] = out[f"engine_{v}_block_ms_median"] / floor_ms
        out[f"engine_{v}_block_ms_mean"] = float(np.median(block_mean[v]))
        out[f"engine_{v}_block_mean_ratio_to_fft_floor"] = out[f"engine_{v}_block_ms_mean"] / floor_ms
    out["tracks_cpu_ratio_to_kalman"] = (out["engine_tracks_cpu_fraction_8dev_16k_hop128"]
                                         / out["engine_kalman_cpu_fraction_8dev_16k_hop128"])
    return out


def engine_split(wavs: list[pathlib.Path], out_dir: pathlib.Path, config: EngineConfig) -> dict[str, float]:
    """One run_replay with a clock around the engine's parts (class attributes wrapped for the run
    and restored): seconds per second of audio. ``process_block`` includes the stages listed under
    it; ``aligner_push.emit_blocks`` is the cutting of blocks (the aligner hands them out one at a time, so
    it excludes ``process_block``); ``sinks`` are enhanced.wav and toa.csv, written per hop by the runner."""
    import functools

    import stream.align
    import stream.condition
    import stream.pipeline
    import stream.replay
    import stream.sinks
    from stream.run import run_replay

    acc: dict[str, float] = {}
    originals = []

    def wrap(owner, name: str, label: str, generator: bool = False) -> None:
        f = getattr(owner, name)
        originals.append((owner, name, f))
        if generator:
            def g(self):
                it = f(self)
                while True:
                    t0 = time.perf_counter()
                    try:
                        item = next(it)
                    except StopIteration:
                        acc[label] = acc.get(label, 0.0) + time.perf_counter() - t0
                        return
                    acc[label] = acc.get(label, 0.0) + time.perf_counter() - t0
                    yield item
        else:
            @functools.wraps(f)
            def g(*a, **k):
                t0 = time.perf_counter()
                try:
                    return f(*a, **k)
                finally:
                    acc[label] = acc.get(label, 0.0) + time.perf_counter() - t0
        setattr(owner, name, g)

    wrap(stream.replay.ReplaySource, "__iter__", "replay_source_read", generator=True)
    wrap(stream.condition.DeviceConditioner, "process", "conditioner")
    wrap(stream.align.Aligner, "push", "aligner_push")
    wrap(stream.align.Aligner, "_emit", "aligner_push.emit_blocks", generator=True)
    wrap(stream.pipeline.Pipeline, "process_block", "process_block")
    wrap(beamform.StreamingStft, "process", "process_block.stft")
    wrap(estimators.GccPhat, "process", "process_block.gcc")
    wrap(type(make_estimator(EngineConfig().resolved(16_000.0), 8)), "update", "process_block.kalman")
    wrap(beamform.DelayAndSum, "process_spectra", "process_block.das")
    wrap(stream.pipeline.Pipeline, "_recentre", "process_block.recentre")
    wrap(stream.pipeline.Pipeline, "_record", "process_block.record")
    wrap(stream.sinks.WavSink, "write", "sinks")
    wrap(stream.sinks.ToaCsvSink, "write", "sinks")
    try:
        p0 = time.process_time()
        outcome = run_replay(wavs, out_dir, config=config)
        cpu_s = time.process_time() - p0
    finally:
        for owner, name, f in reversed(originals):
            setattr(owner, name, f)
    audio = outcome.report["stream"]["audio_s"]
    split = {k: v / audio for k, v in sorted(acc.items())}
    split["total_cpu"] = cpu_s / audio
    return split


def print_profile(prof: cProfile.Profile, title: str, n: int = 25) -> None:
    buf = io.StringIO()
    pstats.Stats(prof, stream=buf).sort_stats("tottime").print_stats(n)
    print(f"\n===== cProfile ({title}), by own time =====", file=sys.stderr)
    print(buf.getvalue(), file=sys.stderr)


def profile_path(audio_s: float) -> None:
    for cfg in PATH_CONFIGS:
        audio, _ = scene(cfg.n_devices, cfg.sample_rate_hz, audio_s, SEED + 300)
        hop = cfg.hop_samples
        blocks = [audio[k * hop:(k + 1) * hop] for k in range(len(audio) // hop)]
        path = HopPath(cfg)
        for b in blocks[: len(blocks) // 4]:
            path.hop(b)
        prof = cProfile.Profile()
        prof.enable()
        for b in blocks:
            path.hop(b)
        prof.disable()
        print_profile(prof, f"path {cfg.key}, {len(blocks)} hops", n=20)


# ---------------------------------------------------------------------------------------- main
def machine(load_start: tuple, load_end: tuple) -> dict:
    return {
        "nproc": os.cpu_count(),
        "affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "loadavg_start": [round(v, 2) for v in load_start],
        "loadavg_end": [round(v, 2) for v in load_end],
        "python": sys.version.split()[0],
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "numba": numba.__version__,
        "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=None,
                    help="interleaved rounds for GCC and path timing (default 40, quick 3); the CPU "
                         "and engine runs use max(1, repeats // 4) (default 10, quick 1)")
    ap.add_argument("--quick", action="store_true", help="smoke run: few rounds, 3 s of audio for the CPU runs")
    ap.add_argument("--cpu-audio-s", type=float, default=None, help="audio per CPU run in seconds (default 10)")
    ap.add_argument("--profile", action="store_true", help="print cProfile top entries of the path and engine to stderr")
    ap.add_argument("--data", type=pathlib.Path, default=REPO.parent / "shared" / "data",
                    help="shared data dir (audio/): two 8-device scenes for the tracker's CPU (default ../shared/data)")
    args = ap.parse_args(argv)
    repeats = args.repeats or (3 if args.quick else 40)
    if repeats < 1:
        ap.error(f"{repeats=} must be >= 1")
    cpu_repeats = max(1, repeats // 4)
    cpu_audio_s = args.cpu_audio_s or (3.0 if args.quick else 10.0)
    frames_per_round = 10 if args.quick else 25
    hops_per_round = 20 if args.quick else 50

    load_start = os.getloadavg()
    t_start = time.perf_counter()
    result: dict = {"benchmark": "throughput", "quick": bool(args.quick), "repeats": repeats}
    gcc = bench_gcc(repeats, frames_per_round)
    paths, rows = bench_paths(repeats, hops_per_round, audio_s=4.0 if args.quick else 8.0)
    cpu = bench_cpu_path(cpu_repeats, cpu_audio_s)
    engine = bench_engine(cpu_repeats, cpu_audio_s, args.profile)
    data = args.data if (args.data / "audio").is_dir() else None
    if data is None:
        print(f"--data {args.data} has no audio/ folder: the tracker's CPU is measured on async_8dev only",
              file=sys.stderr)
    tracks = bench_engine_tracks(1 if args.quick else max(2, cpu_repeats // 2), data=None if args.quick else data)
    engine.update(tracks)
    if args.profile:
        profile_path(4.0)
    result.update(gcc)
    result.update(paths)
    result.update(cpu)
    result.update(engine)
    result["elapsed_s"] = time.perf_counter() - t_start
    result["machine"] = machine(load_start, os.getloadavg())

    print(f"GCC-PHAT, {GCC_N_CHANNELS} channels ({GCC_N_CHANNELS * (GCC_N_CHANNELS - 1) // 2} pairs), "
          f"{GCC_FRAME_SAMPLES}-sample frames at {GCC_RATE_HZ / 1000:g} kHz, median of {gcc['gcc_n_frames_timed']} frames")
    print(f"  {'method':<46} {'ms/frame':>9} {'err med (smp)':>14} {'<=1 smp':>8}")
    print(f"  {'gcc_phat(frame) (8 rfft + GCC)':<46} {gcc['gcc_ms_8ch']:9.3f} "
          f"{gcc['gcc_median_abs_err_samples']:14.3f} {gcc['gcc_within_1_sample']:8.1%}")
    print(f"  {'GccPhat.process(spectra)':<46} {gcc['gcc_spectra_ms_8ch']:9.3f}")
    print(f"  {'pyroomacoustics.sync.tdoa loop (phat, interp=1)':<46} {gcc['pra_gcc_ms_8ch']:9.3f} "
          f"{gcc['pra_median_abs_err_samples']:14.3f} {gcc['pra_within_1_sample']:8.1%}")
    print(f"  speed-up vs pyroomacoustics: {gcc['gcc_speedup_vs_pra']:.1f}x   (target gcc <= 1 ms)")
    print()
    print("Full per-hop path (StreamingStft + GccPhat + KalmanToa + DelayAndSum) vs FFT floor")
    print(f"  {'config':<26} {'hop ms':>7} {'path ms':>8} {'p90 ms':>7} {'floor ms':>9} {'ratio':>6} "
          f"{'scipy floor':>11} {'ratio':>6} {'RTF':>7} {'updated':>8} {'TOA err':>8} {'hops':>6}")
    for r in rows:
        print(f"  {r['config']:<26} {r['hop_ms']:7.2f} {r['path_ms']:8.3f} {r['path_p90_ms']:7.3f} "
              f"{r['floor_ms']:9.3f} {r['ratio']:6.2f} {r['scipy_floor_ms']:11.3f} {r['ratio_scipy']:6.2f} "
              f"{r['rtf']:7.4f} {r['update_fraction']:8.1%} {r['toa_err_median_samples']:8.3f} {r['n_hops']:6d}")
    print(f"  max ratio to FFT floor: {paths['ratio_to_fft_floor']:.2f} (equal weights: "
          f"{paths['ratio_to_fft_floor_equal']:.2f}; against the scipy.fft floor: "
          f"{paths['ratio_to_scipy_fft_floor']:.2f})   (target <= 2; {OVERHEAD_PROBE.key} is the overhead "
          "probe, not in the max)")
    print("  (floor: the same FFTs in compiled pocketfft calls, as the stages make them; scipy floor: through "
          "scipy.fft)")
    print("  (TOA err: median over hops of max_i |toa_i - truth_i| in samples; updated: hops with an accepted "
          "Kalman update)")
    print()
    print("Per-stage median ms (separate pass with a clock between stages)")
    print(f"  {'config':<26} " + " ".join(f"{name:>13}" for name in STAGES) + f" {'sum':>7} {'floor':>7}")
    for r in rows:
        st = r["stages_ms"]
        print(f"  {r['config']:<26} " + " ".join(f"{st.get(name, float('nan')):13.3f}" for name in STAGES)
              + f" {sum(st.values()):7.3f} {r['floor_ms']:7.3f}")
    print()
    print(f"CPU share of one core, 8 devices, 16 kHz, frame 512 / hop 128, {cpu['cpu_runs_audio_s']:.1f} s of audio, "
          f"median of {cpu_repeats} runs")
    print(f"  path only (process_time)       {cpu['cpu_fraction_8dev_16k_hop128']:7.2%}"
          f"   (thread_time {cpu['cpu_fraction_8dev_16k_hop128_thread']:.2%}; target <= 5 %)")
    print(f"  whole engine (run_replay)      {engine['cpu_fraction_8dev_16k_hop128_engine']:7.2%}"
          f"   (wall {engine['engine_wall_fraction_8dev_16k_hop128']:.2%}, "
          f"gated {engine['engine_gated_fraction']:.1%} of blocks)")
    print(f"    of which Pipeline.process_block {engine['engine_process_block_fraction']:7.2%}")
    if "engine_split_fraction" in engine:
        print("  engine split (--profile; wall s per s of audio):")
        for name, v in engine["engine_split_fraction"].items():
            print(f"    {name:<34} {v:7.2%}")
    print()
    m = result["machine"]
    print(f"machine: nproc {m['nproc']}, load {m['loadavg_start']} -> {m['loadavg_end']}, "
          f"elapsed {result['elapsed_s']:.0f} s")
    print()
    print("Whole engine with the multi-source tracker vs the single Kalman, real speech, 8 devices, working rate "
          "16 kHz, frame 512, hop 128")
    print(f"  speech presence: {result['tracks_vad_backend']}; FFT floor {result['tracks_fft_floor_ms_8x512']:.3f} ms/hop")
    for est in ("kalman", "tracks", "tracks_causal", "tracks_every_hop", "tracks_webrtc"):
        print(f"  {est:16s} process_block median {result[f'engine_{est}_block_ms_median']:.3f} ms "
              f"({result[f'engine_{est}_block_ratio_to_fft_floor']:.1f} x floor), mean "
              f"{result[f'engine_{est}_block_ms_mean']:.3f} ms ({result[f'engine_{est}_block_mean_ratio_to_fft_floor']:.1f}"
              " x floor) on async_8dev")
    by_input = result["engine_cpu_fraction_by_input"]
    variants = list(next(iter(by_input.values())))
    print("  CPU share of one core (whole engine, setup and report included), median of runs:")
    print(f"    {'input':<34} " + " ".join(f"{v:>13}" for v in variants))
    for name, by in by_input.items():
        print(f"    {name:<34} " + " ".join(f"{100 * by[v]:12.2f}%" for v in variants))
    running = result.get("engine_running_cpu_fraction_by_input") or {}
    if running:
        print("  CPU share of one core of the running stream (whole input minus its first half, per second of "
              "audio between them), median of runs:")
        for name, by in running.items():
            print(f"    {name:<34} " + " ".join(f"{100 * by[v]:12.2f}%" for v in variants))
    print(f"  tracks / kalman CPU (async_8dev): {result['tracks_cpu_ratio_to_kalman']:.2f}  "
          "(target: whole engine <= 5 % of a core)")
    print(json.dumps(result, sort_keys=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
