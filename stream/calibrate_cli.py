"""``adhoc-array calibrate``: the batch calibration from files (measured TDOAs and odometry, or recordings of
the chirp beacon), its outputs (geometry.json, geometry.png) and its summary."""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

import estimators

from .calibration import MIN_DETECTIONS, CalibrationError, CalibrationSnapshot, Method, calibrate, solve_geometry
from .calibration_files import load_measurements, load_odometry_csv
from .errors import ConfigError, InputFileError, why_unreadable
from .geometry import Geometry

log = logging.getLogger(__name__)


def _read_mono(path: Path) -> tuple[np.ndarray, float]:
    import soundfile as sf
    try:
        x, rate = sf.read(str(path), dtype="float64", always_2d=True)
    except (sf.LibsndfileError, RuntimeError, OSError) as err:
        raise InputFileError(f"{path} is not a readable audio file ({why_unreadable(path, err)}).") from None
    return x.mean(axis=1), float(rate)


def calibrate_recordings(paths: Sequence[str | Path], odometry_m: np.ndarray, interval_s: np.ndarray, *,
                         chirp_duration_s: float, chirp_f0_hz: float, chirp_f1_hz: float,
                         sigma_tdoa_s: float, sigma_odo_m: float, method: Method = "hybrid",
                         speed_of_sound_m_s: float = estimators.SPEED_OF_SOUND_M_S,
                         rng: np.random.Generator | int | None = 0) -> tuple[Geometry, np.ndarray]:
    """Batch calibration from one recording per device (device 0 first) and the beacon's odometry.

    Chirps are found with :func:`estimators.extract_tdoas` (matched filter, GCC-PHAT refinement, assignment to
    the schedule). Devices at other rates are resampled to device 0's. Returns the geometry and the onsets
    (K, N) on each device's clock.
    """
    streams, rates = [], []
    for p in paths:
        x, r = _read_mono(Path(p))
        streams.append(x)
        rates.append(r)
    fs = rates[0]
    if any(r != fs for r in rates):
        import soxr
        streams = [x if r == fs else soxr.resample(x, r, fs) for x, r in zip(streams, rates)]
    template = estimators.linear_chirp(duration_s=chirp_duration_s, f0_hz=chirp_f0_hz, f1_hz=chirp_f1_hz,
                                       sample_rate_hz=fs)
    ch = estimators.extract_tdoas(streams, template, sample_rate_hz=fs, interval_s=np.asarray(interval_s, float))
    on = ch.onsets_s
    counts = np.sum(np.isfinite(on), axis=0)
    if counts[0] < MIN_DETECTIONS:
        raise CalibrationError(f"{paths[0]} (device 0) holds only {int(counts[0])} of the {len(on)} scheduled "
                               "chirps; check the chirp settings and the odometry's intervals.")
    snap = CalibrationSnapshot(onsets_s=on, odometry_m=odometry_m, interval_s=interval_s, first_event=0,
                               time_s=float("nan"), sigma_tdoa_s=sigma_tdoa_s, sigma_odo_m=sigma_odo_m,
                               method=method, speed_of_sound_m_s=speed_of_sound_m_s,
                               device_names=tuple(Path(p).stem for p in paths))
    return calibrate(snap, rng=rng), on


def run_calibrate(out_dir: str | Path, *, measurements: str | Path | None = None,
                  audio: Sequence[str | Path] = (), odometry: str | Path | None = None, method: Method = "hybrid",
                  mics: Sequence[int] | None = None, chirp_interval_s: float | None = None,
                  chirp_duration_s: float = 0.1, chirp_f0_hz: float = 500.0, chirp_f1_hz: float = 6000.0,
                  sigma_tdoa_s: float | None = None, sigma_odo_m: float | None = None, seed: int = 0,
                  plots: bool = True) -> dict[str, Any]:
    """``adhoc-array calibrate``: solve, write ``geometry.json`` (and ``geometry.png``) in ``out_dir``.

    Returns the summary that is also written to ``calibration.json`` (geometry, errors against the file's
    ground truth when it has one).
    """
    if method not in ("hybrid", "baseline"):
        raise ConfigError(f"method={method!r} must be 'hybrid' or 'baseline'")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    truth = None
    t0 = time.perf_counter()
    if measurements is not None:
        if audio:
            raise ConfigError("Give either --measurements or audio files with --odometry, not both.")
        m = load_measurements(measurements, mics=mics, sigma_tdoa_s=sigma_tdoa_s, sigma_odo_m=sigma_odo_m)
        if method == "hybrid" and m.problem.tdoa_events_s is None:
            raise ConfigError(f"{measurements} has no tdoa_events_s (TDOA-S); use --method baseline.")
        geometry = solve_geometry(m.problem, method=method, rng=seed, device_names=m.device_names)
        truth, source = m.truth_positions_m, m.source
    else:
        if not audio or odometry is None:
            raise ConfigError("Give --measurements FILE, or one audio file per device and --odometry FILE.")
        if len(audio) < 3:
            raise ConfigError(f"{len(audio)} audio files were given; calibration needs at least 3 devices.")
        odo, iv = load_odometry_csv(odometry, interval_s=chirp_interval_s)
        geometry, _ = calibrate_recordings(
            audio, odo, iv, chirp_duration_s=chirp_duration_s, chirp_f0_hz=chirp_f0_hz, chirp_f1_hz=chirp_f1_hz,
            sigma_tdoa_s=sigma_tdoa_s if sigma_tdoa_s is not None else 5e-5,
            sigma_odo_m=sigma_odo_m if sigma_odo_m is not None else 0.01, method=method, rng=seed)
        source = ", ".join(str(a) for a in audio)
    wall_s = time.perf_counter() - t0
    geometry.save(out / "geometry.json")
    summary: dict[str, Any] = {"source": source, "method": method, "verdict": geometry.verdict,
                               "n_devices": geometry.n_devices, "n_events": geometry.n_events,
                               "solve_time_s": geometry.solve_time_s, "wall_s": wall_s}
    if truth is not None:
        est = geometry.mic_frame_positions_m()
        tru = Geometry(positions_m=truth, position_std_m=np.zeros(len(truth)), offsets_s=np.zeros(len(truth)),
                       offset_std_s=np.zeros(len(truth)), drifts_ppm=np.zeros(len(truth)),
                       drift_std_ppm=np.zeros(len(truth)), verdict="truth", n_events=0).mic_frame_positions_m()
        err = np.linalg.norm(est - tru, axis=1)
        summary["location_error_m"] = {"rms": float(np.sqrt(np.mean(err[1:] ** 2))), "per_device": err.tolist()}
    if plots:
        from .geometry import plot_geometry
        try:
            plot_geometry(out / "geometry.png", geometry)
        except Exception as err:  # noqa: BLE001 - the JSON is the product; a plot failure is one sentence
            log.warning("The geometry plot could not be drawn (%s: %s); geometry.json is written.",
                        type(err).__name__, err)
    summary["outputs"] = sorted({p.name for p in out.iterdir()} | {"calibration.json"})
    from .sinks import write_json
    write_json(out / "calibration.json", {**summary, "geometry": geometry.to_dict()})
    return {**summary, "geometry": geometry}
