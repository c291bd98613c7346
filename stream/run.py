"""Runs a replay end to end: files -> pipeline -> enhanced.wav, toa.csv, report.json, plots.

Whatever happens mid-stream (a corrupt file, a bug, Ctrl-C), what was produced is written out and
the report says what happened in one sentence.
"""
from __future__ import annotations

import logging
import platform
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from tqdm import tqdm

from . import sinks
from .calibration import CalibrationSnapshot, OdometryLog, StreamCalibrator, load_odometry_csv
from .config import EngineConfig, merge
from .errors import InputFileError, StreamError
from .fixture import Fixture, is_fixture_dir, load_fixture
from .geometry import Geometry
from .pipeline import Pipeline
from .replay import ReplaySource

log = logging.getLogger(__name__)

KEEP_INPUT_MAX_S = 600.0   # aligned input is kept in memory for scoring only up to this duration
FLUSH_BLOCKS = 32          # enhanced.wav and toa.csv are appended every this many blocks


@dataclass
class RunOutcome:
    """What a run produced: the report (also in report.json) and the pipeline (for tests)."""

    report: dict[str, Any]
    pipeline: Pipeline | None
    out_dir: Path


class _Collector(logging.Handler):
    """Collects warnings of the run so the report can list them."""

    def __init__(self) -> None:
        super().__init__(level=logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def resolve_inputs(inputs: Sequence[str | Path]) -> tuple[list[Path], list[str] | None, Fixture | None]:
    """Files per device, their names, and the fixture when ``inputs`` is one fixture folder."""
    if not inputs:
        raise InputFileError("No input was given; pass a fixture folder or one audio file per device.")
    if len(inputs) == 1 and Path(inputs[0]).is_dir():
        root = Path(inputs[0])
        if not is_fixture_dir(root):
            raise InputFileError(f"{root} is a folder without a fixture.toml; pass the audio files themselves.")
        fixture = load_fixture(root)
        return [d.path for d in fixture.devices], [d.name for d in fixture.devices], fixture
    return [Path(p) for p in inputs], None, None


def make_calibrator(cfg: EngineConfig, n_devices: int, out: Path, *, device_names: Sequence[str] = (),
                    solver: Callable[[CalibrationSnapshot], Geometry] | None = None,
                    on_geometry: Callable[[Geometry], None] | None = None) -> StreamCalibrator | None:
    """The stream's calibrator from the resolved options (None when ``calibration_odometry`` is unset).

    Every adopted geometry is written to ``out/geometry.json`` (atomically) and then handed to
    ``on_geometry`` (the publish hook).
    """
    if not cfg.calibration_odometry:
        return None
    if n_devices < 3:
        log.warning("Calibration needs at least 3 devices and %d deliver audio; the stream runs without it.",
                    n_devices)
        return None
    odo, iv = load_odometry_csv(cfg.calibration_odometry, interval_s=cfg.chirp_interval_s)
    import estimators
    template = estimators.linear_chirp(duration_s=cfg.chirp_duration_s, f0_hz=cfg.chirp_f0_hz,
                                       f1_hz=cfg.chirp_f1_hz, sample_rate_hz=cfg.working_rate_hz)

    def publish(geometry: Geometry) -> None:
        geometry.save(out / "geometry.json")
        if on_geometry is not None:
            on_geometry(geometry)

    return StreamCalibrator(
        n_devices, template=template, sample_rate_hz=cfg.working_rate_hz, odometry=OdometryLog(odo, iv),
        recalibrate_every=cfg.recalibrate_every, method=cfg.calibration_method, apply=cfg.calibration_apply,
        sigma_tdoa_s=cfg.calibration_sigma_tdoa_s, sigma_odo_m=cfg.calibration_sigma_odo_m,
        threshold=cfg.chirp_threshold, solver=solver, on_geometry=publish, executor=cfg.calibration_executor,
        max_events=cfg.calibration_max_events, device_names=device_names,
        # unpaced replay: adopt solves at fixed stream times (reproducible); paced (fake live): never wait
        replay_latency_s=cfg.calibration_replay_latency_s if cfg.speed is None else None)


def run_replay(inputs: Sequence[str | Path], out_dir: str | Path, *, config: EngineConfig | None = None,
               overrides: Sequence[tuple[dict[str, Any], str]] = (),
               solver: Callable[[CalibrationSnapshot], Geometry] | None = None,
               on_geometry: Callable[[Geometry], None] | None = None, speech=None) -> RunOutcome:
    """Replay recordings through the live path and write every output into ``out_dir``.

    Parameters
    ----------
    inputs : sequence of path
        A fixture folder, or one audio file per device (the first usable one is the reference).
    out_dir : path
        Created if needed; receives enhanced.wav, toa.csv, report.json and PNG plots.
    config : EngineConfig, optional
        Base options (defaults when None). A fixture's ``[engine]`` table applies on top of it,
        then each ``(values, source)`` of ``overrides`` in order (a config file, then the CLI).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths, names, fixture = resolve_inputs(inputs)
    cfg = config or EngineConfig()
    if fixture is not None:
        engine = {"working_rate_hz": fixture.working_rate_hz, **fixture.raw.get("engine", {})}
        cfg = merge(cfg, engine, source=f"{fixture.root}/fixture.toml [engine]")
    for values, source in overrides:
        cfg = merge(cfg, values, source=source)
    collector = _Collector()
    logging.getLogger().addHandler(collector)
    t_wall0, t_cpu0 = time.perf_counter(), time.process_time()
    report: dict[str, Any] = {"status": "ok", "inputs": [str(p) for p in paths]}
    pipeline = None
    calibrator = None
    wav = csv_sink = None
    try:
        with ReplaySource(paths, block_s=cfg.block_s, speed=cfg.speed, names=names) as src:
            report["devices"] = [vars(d) for d in src.devices]
            if not src.active:
                raise StreamError(f"None of the {len(paths)} input files could be read; nothing to stream.")
            ref_rate = src.active[0].sample_rate_hz
            cfg = cfg.resolved(ref_rate)
            for info in src.active:
                if info.sample_rate_hz != cfg.working_rate_hz:
                    log.info("Device '%s' records at %g Hz; resampled to %g Hz.", info.name, info.sample_rate_hz,
                             cfg.working_rate_hz)
            if len(src.active) == 1:
                log.warning("Only one device delivers audio; the output is that device's signal and every TOA is 0.")
            keep = fixture is not None and src.duration_s <= KEEP_INPUT_MAX_S
            calibrator = make_calibrator(cfg, len(src.active), out, device_names=[d.name for d in src.active],
                                         solver=solver, on_geometry=on_geometry)
            pipeline = Pipeline(cfg, src.sample_rates_hz, keep_input=keep, calibrator=calibrator,
                                device_names=[d.name for d in src.active], speech=speech)
            wav = sinks.WavSink(out / "enhanced.wav", sample_rate_hz=cfg.working_rate_hz,
                                skip_samples=pipeline.latency_samples)
            csv_sink = sinks.ToaCsvSink(out / "toa.csv", [d.name for d in src.active],
                                        tracks=pipeline.tracker is not None)
            written = [0]

            def flush_outputs() -> None:
                st = pipeline.state
                for k in range(written[0], len(st.enhanced)):
                    wav.write(st.enhanced[k])
                for k in range(csv_sink.n_rows, len(st.time_s)):
                    csv_sink.write(st.time_s[k], st.toa_s[k], st.gated[k], st.track_id[k], st.speech_probability[k])
                written[0] = len(st.enhanced)

            # write out every FLUSH_BLOCKS blocks: few, larger writes; at most that much is lost on a hard kill
            pipeline.on_block = lambda block, *_: flush_outputs() if block.seq % FLUSH_BLOCKS == 0 else None
            bar = tqdm(total=round(src.duration_s, 2), unit="s", desc="replay", disable=None if cfg.progress else True,
                       leave=False, bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} s [{elapsed}<{remaining}]")
            try:
                for frame in src:
                    pipeline.feed(frame)
                    if frame.device_id == 0:
                        bar.update(min(len(frame.samples) / frame.sample_rate_hz, bar.total - bar.n))
                pipeline.finish()
            finally:
                bar.close()
            wav.max_samples = pipeline.counters.n_blocks * cfg.hop_samples
            flush_outputs()
    except KeyboardInterrupt:
        report["status"] = "interrupted"
        report["error"] = "Interrupted by the user; everything produced so far was written out."
    except Exception as err:  # noqa: BLE001 - the run must write out what it produced, then re-raise
        report["status"] = "failed"
        report["error"] = f"{type(err).__name__}: {err}"
        log.error("The stream stopped: %s", err)
        if pipeline is not None and wav is not None:
            try:
                flush_outputs()
            except Exception:  # noqa: BLE001
                pass
        if calibrator is not None:
            calibrator.close()
        _finalise(report, out, cfg, pipeline, fixture, names, paths, collector, t_wall0, t_cpu0, wav, csv_sink)
        raise
    if calibrator is not None:
        calibrator.close()
    _finalise(report, out, cfg, pipeline, fixture, names, paths, collector, t_wall0, t_cpu0, wav, csv_sink)
    return RunOutcome(report, pipeline, out)


def _finalise(report, out, cfg, pipeline, fixture, names, paths, collector, t_wall0, t_cpu0, wav, csv_sink) -> None:
    for s in (wav, csv_sink):
        if s is not None:
            s.close()
    logging.getLogger().removeHandler(collector)
    wall_s, cpu_s = time.perf_counter() - t_wall0, time.process_time() - t_cpu0
    report["settings"] = cfg.as_dict()
    report["python"] = platform.python_version()
    if pipeline is not None:
        fs = cfg.working_rate_hz
        n_blocks = pipeline.counters.n_blocks
        audio_s = n_blocks * cfg.hop_samples / fs
        block_ms = np.asarray(pipeline.state.block_ms) if pipeline.state.block_ms else np.zeros(1)
        report["stream"] = {
            "n_devices": pipeline.n_devices,
            "working_rate_hz": fs,
            "frame_samples": cfg.frame_samples,
            "hop_samples": cfg.hop_samples,
            "output_latency_samples": pipeline.latency_samples,
            "output_latency_s": pipeline.latency_samples / fs,
            "algorithmic_latency_s": (cfg.frame_samples) / fs,
            "audio_s": audio_s,
            "n_blocks": n_blocks,
            "n_gated": pipeline.counters.n_gated,
            "n_recentred": pipeline.counters.n_recentred,
            "n_invalid_device_blocks": pipeline.counters.n_invalid_device_blocks,
            "coarse_offsets_s": (pipeline.aligner.offsets_samples / fs).tolist(),
            "alignment_quality": pipeline.aligner.quality.tolist(),
            "aligned": pipeline.aligner.aligned.tolist(),
            "alignment_events": [vars(e) for e in pipeline.alignment_events],
            "final_channel_weights": (pipeline.state.weights[-1].tolist() if pipeline.state.weights else []),
        }
        active = [d for d in report.get("devices", []) if d["usable"]]
        for info, counters in zip(active, pipeline.device_counters):
            info.update(vars(counters))
            if counters.n_nan_samples:
                info["problems"].append(f"Device '{info['name']}': {counters.n_nan_samples} non-finite samples "
                                        "were replaced by zeros.")
            if counters.n_clipped_samples:
                info["problems"].append(f"Device '{info['name']}': {counters.n_clipped_samples} samples are "
                                        "clipped (at full scale).")
            if counters.n_blocks and counters.n_silent_blocks == counters.n_blocks:
                info["problems"].append(f"Device '{info['name']}' is silent throughout; it is left out of the "
                                        "beamformer.")
        report["timing"] = {
            "wall_s": wall_s,
            "cpu_s": cpu_s,
            "real_time_factor": wall_s / audio_s if audio_s else None,
            "block_ms_median": float(np.median(block_ms)),
            "block_ms_p95": float(np.percentile(block_ms, 95)),
            "hop_ms": 1e3 * cfg.hop_samples / fs,
            "cpu_fraction_of_one_core": float(np.median(block_ms) / (1e3 * cfg.hop_samples / fs)),
            "kernel_compile_s": pipeline.compile_s,   # numba: compile or cache load before the first block
        }
        if pipeline.tracker is not None:
            sources = pipeline.tracker.report()
            sources["speech_presence"] = {"backend": getattr(pipeline.speech, "backend", type(pipeline.speech).__name__),
                                          "speech_fraction": float(np.mean(np.asarray(pipeline.state.speech_probability)
                                                                          >= pipeline.tracker.speech_threshold))
                                          if pipeline.state.speech_probability else 0.0}
            note = None
            if sources["n_speech_frames"] == 0:
                note = ("No speech was detected in the whole stream; the output is the reference device "
                        "(no beam is steered at a noise source).")
            elif not any(t["kind"] == "speech" for t in sources["tracks"]):
                note = "Speech was detected but no talker could be tracked; the output is the reference device."
            if note is not None:   # the run's log collector is already detached here
                log.warning(note)
                collector.messages.append(note)
            report["sources"] = sources
        if pipeline.calibrator is not None:
            report["calibration"] = {**pipeline.calibrator.report(), "applied": pipeline.geometry_log}
            if cfg.plots and pipeline.calibrator.geometry is not None:
                from .geometry import plot_geometry
                try:
                    plot_geometry(out / "geometry.png", pipeline.calibrator.geometry)
                except Exception as err:  # noqa: BLE001 - plots must never lose the other outputs
                    log.warning("The geometry plot could not be drawn (%s: %s); geometry.json is written.",
                                type(err).__name__, err)
        if fixture is not None and report["status"] == "ok":
            from .evaluate import evaluate_run
            index = [names.index(d["name"]) for d in active] if names else list(range(pipeline.n_devices))
            try:
                report["metrics"] = evaluate_run(pipeline, fixture, index)
            except Exception as err:  # noqa: BLE001 - scoring must not lose the outputs
                log.exception("Scoring against the fixture's truth failed")
                report["metrics_error"] = f"{type(err).__name__}: {err}"
        if cfg.plots and n_blocks:
            _plots(out, pipeline, fixture, report, names, cfg)
    report["messages"] = collector.messages
    report["outputs"] = sorted(p.name for p in out.iterdir())
    if "report.json" not in report["outputs"]:
        report["outputs"].append("report.json")
    sinks.write_json(out / "report.json", report)


def _plots(out: Path, pipeline: Pipeline, fixture: Fixture | None, report: dict, names, cfg: EngineConfig) -> None:
    from . import metrics, plots
    try:
        time_s, toa_s, gated = pipeline.toa_track()
        true_t = true_toa = None
        dev_names = [d["name"] for d in report.get("devices", []) if d["usable"]]
        if fixture is not None and fixture.truth_toa is not None:
            index = [names.index(n) for n in dev_names]
            true_t, true_all = fixture.load_truth_toa()
            true_toa = true_all[:, index] - true_all[:, index[:1]]
        plots.plot_toa_tracks(out / "toa_tracks.png", time_s=time_s, toa_s=toa_s, true_time_s=true_t,
                              true_toa_s=true_toa, gated=gated, device_names=dev_names,
                              title=f"Relative TOA ({cfg.estimator})")
        if pipeline.tracker is not None and pipeline.state.source_tracks:
            index = [names.index(n) for n in dev_names]
            truth = None
            if fixture is not None and fixture.sources:
                truth = {}
                for src in fixture.sources:
                    tv = fixture.source_toa_at(src.name, time_s)
                    truth[src.name] = (time_s, tv[:, index])
            tracks = {k: {"kind": h["kind"], "time_s": h["time_s"],
                          "toa_s": [np.asarray(v)[index] for v in h["toa_s"]]} for k, h in
                      pipeline.state.source_tracks.items()}
            plots.plot_source_tracks(out / "sources.png", tracks=tracks, time_s=time_s,
                                     steered_id=np.asarray(pipeline.state.track_id), truth=truth,
                                     device_names=dev_names, title="Tracked sources (steered: thick)")
        enhanced = pipeline.enhanced_signal()
        fs = cfg.working_rate_hz
        if fixture is not None and fixture.truth_clean is not None:
            clean, rate = fixture.load_clean()
            if rate != fs:
                import soxr
                clean = soxr.resample(clean, rate, fs).astype(np.float32)
            n = min(len(clean), len(enhanced))
            est, _ = metrics.align_to_reference(enhanced[:n], clean[:n], max_lag_samples=int(0.05 * fs))
            start, sar, speech = metrics.segmental_sar_db(est, clean[:n], sample_rate_hz=fs)
            plots.plot_segmental_sar(out / "segmental_sar.png", enhanced=est, sample_rate_hz=fs,
                                     segment_start_s=start, sar_db=sar, is_speech=speech,
                                     title=f"Segmental SAR, {cfg.estimator} steering")
    except Exception as err:  # noqa: BLE001 - plots must never lose the other outputs
        log.warning("Plots could not be drawn (%s: %s); the other outputs are written.", type(err).__name__, err)
