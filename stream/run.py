"""Runs a replay end to end: files -> pipeline -> enhanced.wav, toa.csv, report.json, plots.

Whatever happens mid-stream (a corrupt file, a bug, Ctrl-C), what was produced is written out and
the report says what happened in one sentence.
"""
from __future__ import annotations

import dataclasses
import gc
import logging
import platform
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from tqdm import tqdm

from . import offsets, sinks
from .calibration import CalibrationSnapshot, OdometryLog, StreamCalibrator
from .calibration_files import load_odometry_csv
from .config import EngineConfig, merge
from .errors import AdhocArrayError, InputFileError, StreamError
from .scoring.fixture import Fixture, is_fixture_dir, load_fixture
from .geometry import Geometry
from .pipeline import Pipeline
from .channels import ChannelLayout
from .messages import HopSink
from .stopping import install_stop_handlers as _install_stop_handlers
from .replay import ReplaySource

log = logging.getLogger(__name__)

KEEP_INPUT_MAX_S = 600.0   # every per-frame record and the aligned input are kept (for scoring) only up to this
HISTORY_CAP = 20_000       # longer and live streams keep at most this many per-frame records (report, plots)
# how a report's sentence ends when the tracker found no talker: what the output was instead
NO_TALKER_OUTPUT = ("the output is the average of the aligned devices, or the reference device where that average "
                    "would point at a noise source.")


def reference_note(name: str, share: float, others: float) -> str:
    """The sentence for a reference device the steered talker track rarely measured
    (:meth:`estimators.SourceTracker.reference_heard_poorly`): what it means and what to do."""
    return (f"The reference device '{name}' took part in only {100 * share:.0f} % of the talker track's measurements "
            f"(the other devices: {100 * others:.0f} %, median): it hears the talker poorly, and since every device's "
            "steering and the output's timing are counted from it, they follow guesses there; put a device near the "
            "talker first (replay: its file first; live: its --input first; the aggregator: first in --expect).")


def unsteered_note(unsteered_s: float, speech_s: float) -> str:
    """The sentence for speech mostly not steered at a talker (:meth:`estimators.SourceTracker.unsteered_speech`)."""
    return (f"No talker was tracked in {unsteered_s:.1f} s of the {speech_s:.1f} s of speech "
            f"({100 * unsteered_s / speech_s:.0f} %): the talker's sound did not stand out on every device (far "
            f"devices, a reverberant room or loud noise do this), and there {NO_TALKER_OUTPUT}")


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


def resolve_inputs(inputs: Sequence[str | Path]) -> tuple[list[Path], list[str] | None, Fixture | None,
                                                         tuple[dict[str, Any], str] | None]:
    """Files per device, their names, the fixture when ``inputs`` is one fixture folder, and the engine options
    (with their source) of a recorded folder (``adhoc-array live --record``)."""
    if not inputs:
        raise InputFileError("No input was given; pass a fixture folder or one audio file per device.")
    if len(inputs) == 1 and Path(inputs[0]).is_dir():
        root = Path(inputs[0])
        manifest = root / sinks.RecordingSink.MANIFEST
        if manifest.is_file():
            paths, names, engine = _load_recording(manifest)
            return paths, names, None, (engine, f"{manifest} [engine]")
        if not is_fixture_dir(root):
            raise InputFileError(f"{root} is a folder without a fixture.toml or {sinks.RecordingSink.MANIFEST}; "
                                 "pass the audio files themselves.")
        fixture = load_fixture(root)
        return [d.path for d in fixture.devices], [d.name for d in fixture.devices], fixture, None
    return [Path(p) for p in inputs], None, None, None


def _load_recording(manifest: Path) -> tuple[list[Path], list[str], dict[str, Any]]:
    """Files, names and engine options of a folder written by ``adhoc-array live --record``."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    try:
        doc = tomllib.loads(manifest.read_text(encoding="utf-8"))
        rows = doc["device"]
        paths = [manifest.parent / str(r["file"]) for r in rows]
        names = [str(r["name"]) for r in rows]
        engine = dict(doc.get("engine", {}))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError, KeyError, TypeError) as err:
        raise InputFileError(f"{manifest} is not a valid recording manifest ({type(err).__name__}: {err}).") from None
    if not paths:
        raise InputFileError(f"{manifest} lists no device.")
    return paths, names, engine


def channel_layout(cfg: EngineConfig, devices: Sequence, fixture: Fixture | None = None) -> ChannelLayout:
    """The stream's channels (:mod:`stream.channels`): the devices, an array named in ``cfg.arrays`` as one
    channel per mic. A relative ``arrays`` path is looked up in the current folder, then in the fixture's."""
    if not cfg.arrays:
        return ChannelLayout(devices)
    from .arrays import load_arrays
    path = Path(cfg.arrays)
    if not path.exists() and fixture is not None and (fixture.root / path).exists():
        path = fixture.root / path
    specs, _ = load_arrays(path, streaming=True)
    return ChannelLayout(devices, specs)


def make_calibrator(cfg: EngineConfig, n_devices: int, out: Path, *, device_names: Sequence[str] = (),
                    solver: Callable[[CalibrationSnapshot], Geometry] | None = None,
                    on_geometry: Callable[[Geometry], None] | None = None,
                    paced: bool = False, layout: ChannelLayout | None = None) -> StreamCalibrator | None:
    """The stream's calibrator from the resolved options (None when ``calibration_odometry`` is unset).

    Every adopted geometry is written to ``out/geometry.json`` (atomically) and then handed to
    ``on_geometry`` (the publish hook). ``paced``: the source's (:class:`~stream.messages.Source`).
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
        replay_latency_s=None if paced else cfg.calibration_replay_latency_s,
        arrays=layout.placements() if layout is not None else ())


def _layered(cfg: EngineConfig, fixture: Fixture | None,
             overrides: Sequence[tuple[dict[str, Any], str]]) -> EngineConfig:
    if fixture is not None:
        engine = {"working_rate_hz": fixture.working_rate_hz, **fixture.raw.get("engine", {})}
        cfg = merge(cfg, engine, source=f"{fixture.root}/fixture.toml [engine]")
    for values, source in overrides:
        cfg = merge(cfg, values, source=source)
    return cfg


def run_replay(inputs: Sequence[str | Path], out_dir: str | Path, *, config: EngineConfig | None = None,
               overrides: Sequence[tuple[dict[str, Any], str]] = (),
               solver: Callable[[CalibrationSnapshot], Geometry] | None = None,
               on_geometry: Callable[[Geometry], None] | None = None, speech=None) -> RunOutcome:
    """Replay recordings through the live path and write every output into ``out_dir``.

    Parameters
    ----------
    inputs : sequence of path
        A fixture folder, a recorded folder (``adhoc-array live --record``), or one audio file per device
        (the first usable one is the reference).
    out_dir : path
        Created if needed; receives enhanced.wav, toa.csv, report.json and PNG plots.
    config : EngineConfig, optional
        Base options (defaults when None). A fixture's ``[engine]`` table applies on top of it,
        then each ``(values, source)`` of ``overrides`` in order (a config file, then the CLI).
    """
    paths, names, fixture, recorded = resolve_inputs(inputs)
    cfg = _layered(config or EngineConfig(), fixture, [recorded, *overrides] if recorded else overrides)
    source = ReplaySource(paths, block_s=cfg.block_s, speed=cfg.speed, names=names)
    return run_stream(source, out_dir, config=cfg, fixture=fixture, names=names, solver=solver,
                      on_geometry=on_geometry, speech=speech)


def run_stream(source, out_dir: str | Path, *, config: EngineConfig, fixture: Fixture | None = None,
               names: Sequence[str] | None = None, solver: Callable[[CalibrationSnapshot], Geometry] | None = None,
               on_geometry: Callable[[Geometry], None] | None = None, speech=None,
               on_frame: Callable[[Any], None] | None = None, extra_sinks: Sequence[HopSink] = (),
               status: Callable[[Pipeline], None] | None = None, status_every_s: float = 1.0,
               history_cap: int | None = None, extra_report: Callable[[dict], None] | None = None,
               on_end: Callable[[], None] | None = None,
               handle_signals: bool = True) -> RunOutcome:
    """The one stream loop of replay and live: a :class:`~stream.messages.Source` through the pipeline into the
    sinks (enhanced.wav, toa.csv, written per hop), then report.json and plots.

    Parameters
    ----------
    source : Source
        Not yet opened; opened and closed here.
    on_frame : callable, optional
        Every raw frame, before the pipeline (``--record``).
    extra_sinks : sequence of HopSink
        Sinks of every hop besides enhanced.wav and toa.csv (a sound card); written as the hops are produced
        (``write(HopResult)``), closed by their owner.
    status : callable, optional
        Called with the pipeline every ``status_every_s`` seconds of wall time (a live status line).
    history_cap : int, optional
        Per-frame records kept for the report and plots (:class:`stream.pipeline.History`). None: everything
        for sources of at most ``KEEP_INPUT_MAX_S``, else ``HISTORY_CAP``; negative: everything, always.
    extra_report : callable, optional
        Adds to the report before it is written (sound-card counters).
    on_end : callable, optional
        Called once the source has ended and the pipeline has flushed (before the report is written).
    handle_signals : bool
        SIGINT and SIGTERM stop the source (what was captured is processed and written); a second one
        interrupts at once (still writing what was produced).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cfg = config
    collector = _Collector()
    logging.getLogger().addHandler(collector)
    t_wall0, t_cpu0 = time.perf_counter(), _cpu_s()
    report: dict[str, Any] = {"status": "ok", "inputs": [], "live": bool(getattr(source, "live", False))}
    pipeline = None
    calibrator = None
    layout = None
    wav = csv_sink = None
    steady: list[tuple[float, float]] = []   # (process, wall) time at the first hop out and at the input's end
    stopped: list[str] = []
    restore = _install_stop_handlers(source, stopped) if handle_signals else (lambda: None)
    try:
        with source as src:
            report["inputs"] = [d.path for d in src.devices]
            report["devices"] = [vars(d) for d in src.devices]
            if not src.active:
                what = "inputs" if src.live else "input files"
                raise StreamError(f"None of the {len(src.devices)} {what} could be read; nothing to stream.")
            ref_rate = src.active[0].sample_rate_hz
            cfg = cfg.resolved(ref_rate)
            for info in src.active:
                if info.sample_rate_hz != cfg.working_rate_hz:
                    log.info("Device '%s' records at %g Hz; resampled to %g Hz.", info.name, info.sample_rate_hz,
                             cfg.working_rate_hz)
            if len(src.active) == 1:
                log.warning("Only one device delivers audio; the output is that device's signal and every TOA is 0.")
            duration = src.duration_s
            if history_cap is None and (duration is None or duration > KEEP_INPUT_MAX_S):
                history_cap = HISTORY_CAP
            elif history_cap is not None and history_cap < 0:   # keep everything, whatever the length
                history_cap = None
            keep = fixture is not None and history_cap is None
            layout = channel_layout(cfg, src.active, fixture)
            if not layout.identity:
                report["arrays"] = layout.report()
            calibrator = make_calibrator(cfg, len(layout.channels), out, device_names=layout.names,
                                         solver=solver, on_geometry=on_geometry, paced=src.paced, layout=layout)
            # a replay as fast as possible has every device's audio at hand: a wall-clock deadline there would only
            # make the output depend on the machine's load (a re-check or the first alignment that takes over
            # the deadline, on a loaded machine, left devices out of blocks)
            pipeline = Pipeline(dataclasses.replace(cfg, device_deadline_s=None) if not src.paced else cfg,
                                layout.sample_rates_hz, keep_input=keep, calibrator=calibrator,
                                device_names=layout.names, speech=speech, history_cap=history_cap,
                                clock_groups=layout.clock_groups)
            wav = sinks.WavSink(out / "enhanced.wav", sample_rate_hz=cfg.working_rate_hz,
                                skip_samples=pipeline.latency_samples)
            csv_sink = sinks.ToaCsvSink(out / "toa.csv", layout.names, tracks=pipeline.tracker is not None)

            hop_sinks = [wav, csv_sink, *extra_sinks]

            def write(results) -> None:
                if results and not steady:   # the first hop out: the stream is running (start-up is over)
                    steady.append((_cpu_s(), time.perf_counter()))
                for result in results:
                    for sink in hop_sinks:
                        sink.write(result)

            bar = tqdm(total=round(duration or 0.0, 2), unit="s", desc="replay",
                       disable=None if (cfg.progress and duration is not None and status is None) else True,
                       leave=False, bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} s [{elapsed}<{remaining}]")
            next_status = time.perf_counter() + status_every_s
            # everything built so far (modules, models, stages) lives as long as the stream: the cyclic garbage
            # collector stops scanning it, so that its full collections, which would otherwise walk it all (tens
            # of ms), no longer stall a hop; thawed at the end, so nothing of this run outlives it
            gc.freeze()
            try:
                for frame in src:
                    if on_frame is not None:
                        on_frame(frame)
                    if layout.identity:
                        write(pipeline.feed(frame))
                    else:
                        for part in layout.split(frame):   # an array's mics, one channel each
                            write(pipeline.feed(part))
                    if frame.device_id == 0 and duration is not None:
                        bar.update(min(len(frame.samples) / frame.sample_rate_hz, bar.total - bar.n))
                    if status is not None and time.perf_counter() >= next_status:
                        next_status += status_every_s
                        status(pipeline)
                steady.append((_cpu_s(), time.perf_counter()))   # the input ended
                write(pipeline.finish())
                if on_end is not None:
                    on_end()
            finally:
                bar.close()
                gc.unfreeze()
            wav.max_samples = pipeline.counters.n_blocks * cfg.hop_samples
        if stopped:
            how = " and ".join(stopped)
            report["stopped_by"] = how
            if not report["live"]:
                report["status"] = "interrupted"
                report["error"] = f"Stopped by {how}; everything produced so far was written out."
    except KeyboardInterrupt:
        report["status"] = "interrupted"
        report["error"] = "Interrupted by the user; everything produced so far was written out."
    except Exception as err:  # noqa: BLE001 - the run must write out what it produced, then re-raise
        report["status"] = "failed"
        report["error"] = f"{type(err).__name__}: {err}"
        if not isinstance(err, AdhocArrayError):   # the engine's own errors are one sentence for the caller
            log.error("The stream stopped: %s", err)
        restore()
        if calibrator is not None:
            calibrator.close()
        if extra_report is not None:
            extra_report(report)
        _finalise(report, out, cfg, pipeline, layout, fixture, names, collector, t_wall0, t_cpu0, wav, csv_sink,
                  steady)
        raise
    restore()
    if calibrator is not None:
        calibrator.close()
    if extra_report is not None:
        extra_report(report)
    _finalise(report, out, cfg, pipeline, layout, fixture, names, collector, t_wall0, t_cpu0, wav, csv_sink,
              steady)
    return RunOutcome(report, pipeline, out)


def _observed_drift(pipeline) -> np.ndarray:
    """:func:`observed_drift_ppm` of the stream's TOA over the frames it steered by (the tracker: not those
    without a talker, whose TOA is the last one held)."""
    time_s, toa_s, gated = pipeline.toa_track()
    if pipeline.tracker is not None and len(pipeline.state.track_id) == len(time_s):
        gated = gated | (np.asarray(pipeline.state.track_id) < 0)
    return observed_drift_ppm(time_s, toa_s, gated)


def observed_drift_ppm(time_s: np.ndarray, toa_s: np.ndarray, gated: np.ndarray, *,
                       min_span_s: float = 20.0) -> np.ndarray:
    """Each device's clock drift against the reference as the stream saw it: the slope of its relative TOA
    (coarse offset + fine estimate) over time, by least squares over the frames that were not gated, in ppm
    (``1e6 * d toa / d t``; a talker walking also moves it, by at most ~3000 ppm at 1 m/s). NaN when the
    stream is shorter than ``min_span_s`` (a slope over a few seconds says more about the talker).

    Returns
    -------
    ndarray, shape (n_devices,)
    """
    n_dev = toa_s.shape[1] if toa_s.ndim == 2 else 0
    out = np.full(n_dev, np.nan)
    ok = ~np.asarray(gated, bool)
    if n_dev == 0 or ok.sum() < 10 or np.ptp(time_s[ok]) < min_span_s:
        return out
    t = time_s[ok] - time_s[ok].mean()
    y = toa_s[ok] - toa_s[ok].mean(axis=0)
    out[:] = 1e6 * (t @ y) / (t @ t)
    out[0] = 0.0
    return out


def _cpu_s() -> float:
    """CPU seconds of the stream's work: this process (every thread) and the offset re-check process."""
    return time.process_time() + offsets.worker_cpu_s()


def _finalise(report, out, cfg, pipeline, layout, fixture, names, collector, t_wall0, t_cpu0, wav, csv_sink,
              steady) -> None:
    for s in (wav, csv_sink):
        if s is not None:
            s.close()
    logging.getLogger().removeHandler(collector)
    wall_s, cpu_s = time.perf_counter() - t_wall0, _cpu_s() - t_cpu0
    report["settings"] = cfg.as_dict()
    report["python"] = platform.python_version()
    if pipeline is not None:
        fs = cfg.working_rate_hz
        n_blocks = pipeline.counters.n_blocks
        audio_s = n_blocks * cfg.hop_samples / fs
        ht = pipeline.hop_times
        report["stream"] = {
            "n_devices": layout.n_devices,
            "n_channels": pipeline.n_devices,   # an array's mics are channels of their own (stream.channels)
            "channels": layout.names,
            "working_rate_hz": fs,
            "frame_samples": cfg.frame_samples,
            "hop_samples": cfg.hop_samples,
            "output_latency_samples": pipeline.latency_samples,
            "output_latency_s": pipeline.latency_samples / fs,
            "algorithmic_latency_s": (cfg.frame_samples) / fs,
            "tracker_lookahead_s": pipeline.lookahead_frames * cfg.hop_samples / fs,   # part of output_latency_s
            "tracker_every_hops": pipeline.track_stride,   # the tracker measures every this many hops
            "audio_s": audio_s,
            "n_blocks": n_blocks,
            "n_gated": pipeline.counters.n_gated,
            "n_recentred": pipeline.counters.n_recentred,
            "n_invalid_device_blocks": pipeline.counters.n_invalid_device_blocks,
            "coarse_offsets_s": (pipeline.aligner.offsets_samples / fs).tolist(),
            "alignment_quality": pipeline.aligner.quality.tolist(),
            "aligned": pipeline.aligner.aligned.tolist(),
            "alignment_events": [vars(e) for e in pipeline.alignment_events],
            "late_blocks": pipeline.aligner.n_late_blocks.tolist(),
            "final_channel_weights": np.asarray(pipeline.das.channel_weights, float).tolist(),
            "observed_drift_ppm": _observed_drift(pipeline).tolist(),
            # measured from the rotation of the pairs' cross-power spectra (the tracker; followed by its noise
            # spectra); None before two blocks
            "spectra_drift_ppm": (None if pipeline.drift_meter is None or pipeline.drift_meter.rate_s_per_s is None
                                  else np.round(1e6 * pipeline.drift_meter.rate_s_per_s, 2).tolist()),
        }
        active = [d for d in report.get("devices", []) if d["usable"]]
        for channel, counters, checker in zip(layout.channels, pipeline.device_counters, pipeline.checkers):
            info = active[channel.device_id]
            if channel.mic >= 0:   # one mic of an array: its counters go in the device's list of mics
                mics = info.setdefault("mics", [])
                mics.append({"name": channel.name, **vars(counters), **vars(checker.counters)})
                if channel.mic == 0:
                    info.update(vars(checker.counters))   # gaps are the device's: every mic has the same
            else:
                info.update(vars(counters))
                info.update(vars(checker.counters))
            if checker.counters.n_gaps and channel.mic <= 0:
                info["problems"].append(f"Device '{info['name']}': {checker.counters.n_gap_samples} samples were "
                                        f"lost in {checker.counters.n_gaps} gaps (filled with zeros and left out "
                                        "of the beam).")
            if counters.n_nan_samples:
                info["problems"].append(f"Device '{channel.name}': {counters.n_nan_samples} non-finite samples "
                                        "were replaced by zeros.")
            if counters.n_clipped_samples:
                info["problems"].append(f"Device '{channel.name}': {counters.n_clipped_samples} samples are "
                                        "clipped (at full scale).")
            if counters.n_blocks and counters.n_silent_blocks == counters.n_blocks:
                info["problems"].append(f"Device '{channel.name}' is silent throughout; it is left out of the "
                                        "beamformer.")
        report["timing"] = {
            "wall_s": wall_s,
            "cpu_s": cpu_s,   # this process and the offset re-check process (stream.offsets)
            "recheck_process": ("failed: " + offsets.worker().failed) if offsets.worker().failed else "ok",
            "real_time_factor": wall_s / audio_s if audio_s else None,
            "block_ms_median": ht.percentile(50),
            "block_ms_mean": ht.sum_ms / ht.n if ht.n else 0.0,   # the tracker measures on some hops only
            "block_ms_p95": ht.percentile(95),
            "block_ms_p99": ht.percentile(99),
            "block_ms_p999": ht.percentile(99.9),
            "block_ms_max": ht.max_ms,
            "hop_ms": 1e3 * cfg.hop_samples / fs,
            "cpu_fraction_of_one_core": ht.percentile(50) / (1e3 * cfg.hop_samples / fs),
            "kernel_compile_s": pipeline.compile_s,   # numba: compile or cache load before the first block
            # CPU share (every thread) from the first hop out to the end of the input: the running stream,
            # without the start-up (kernels, the first alignment) and the report
            "running_cpu_share": ((steady[1][0] - steady[0][0]) / (steady[1][1] - steady[0][1])
                                  if len(steady) == 2 and steady[1][1] > steady[0][1] else None),
            "running_wall_s": steady[1][1] - steady[0][1] if len(steady) == 2 else None,
        }
        if pipeline.tracker is not None:
            sources = pipeline.tracker.report()
            sources["speech_presence"] = {"backend": getattr(pipeline.speech, "backend", type(pipeline.speech).__name__),
                                          "rate_hz": getattr(pipeline.speech, "vad_rate_hz", None),
                                          "speech_fraction": float(np.mean(np.asarray(pipeline.state.speech_probability)
                                                                          >= pipeline.tracker.speech_threshold))
                                          if pipeline.state.speech_probability else 0.0}
            note = None
            if sources["n_speech_frames"] == 0:
                note = (f"No speech was detected in the whole stream; {NO_TALKER_OUTPUT[:-1]} (for a source that "
                        "is not speech, --estimator kalman steers at whatever is loudest).")
            elif not any(t["kind"] == "speech" for t in sources["tracks"]):
                note = f"Speech was detected but no talker could be tracked; {NO_TALKER_OUTPUT}"
            poorly = pipeline.tracker.reference_heard_poorly()
            if note is None and poorly is not None:
                note = reference_note(layout.channels[0].name, *poorly)
            unsteered = pipeline.tracker.unsteered_speech()
            if note is None and unsteered is not None:
                note = unsteered_note(*unsteered)
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
            from .scoring.evaluate import evaluate_run
            try:
                report["metrics"] = evaluate_run(pipeline, fixture, layout.source_index(names))
            except Exception as err:  # noqa: BLE001 - scoring must not lose the outputs
                log.exception("Scoring against the fixture's truth failed")
                report["metrics_error"] = f"{type(err).__name__}: {err}"
        if cfg.plots and n_blocks:
            _plots(out, pipeline, layout, fixture, names, cfg)
    report["messages"] = collector.messages
    report["outputs"] = sorted(p.name for p in out.iterdir())
    if "report.json" not in report["outputs"]:
        report["outputs"].append("report.json")
    sinks.write_json(out / "report.json", report)


def _plots(out: Path, pipeline: Pipeline, layout: ChannelLayout, fixture: Fixture | None, names,
           cfg: EngineConfig) -> None:
    from .scoring import metrics, plots
    try:
        time_s, toa_s, gated = pipeline.toa_track()
        true_t = true_toa = None
        dev_names = layout.names
        index = layout.source_index(names)
        if fixture is not None and fixture.truth_toa is not None:
            true_t, true_all = fixture.load_truth_toa()
            true_toa = true_all[:, index] - true_all[:, index[:1]]
        plots.plot_toa_tracks(out / "toa_tracks.png", time_s=time_s, toa_s=toa_s, true_time_s=true_t,
                              true_toa_s=true_toa, gated=gated, device_names=dev_names,
                              title=f"Relative TOA ({cfg.estimator})")
        if pipeline.tracker is not None and pipeline.state.source_tracks:
            truth = None
            if fixture is not None and fixture.sources:
                truth = {}
                for src in fixture.sources:
                    tv = fixture.source_toa_at(src.name, time_s)
                    truth[src.name] = (time_s, tv[:, index])
            # the tracks are the pipeline's channels already (the truth was mapped to them above)
            tracks = {k: {"kind": h["kind"], "time_s": h["time_s"], "toa_s": list(h["toa_s"]),
                          "heard": list(h["heard"]), "relabels": list(h.get("relabels", ()))}
                      for k, h in pipeline.state.source_tracks.items()}
            plots.plot_source_tracks(out / "sources.png", tracks=tracks, time_s=time_s,
                                     steered_id=np.asarray(pipeline.state.track_id), truth=truth,
                                     device_names=dev_names, title="Tracked sources (steered: thick)",
                                     reference=pipeline.aligner.time_reference)
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
