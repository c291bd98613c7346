"""The streaming pipeline: one plain loop, one line per stage.

::

    Source ─Frame─▶ FrameChecker ─▶ DeviceConditioner ─▶ Aligner ─Block─▶ StreamingStft ─▶ GccPhat ─TdoaFrame─▶
        ToaEstimator ─ToaEstimate─▶ DelayAndSum ─▶ sinks (enhanced.wav, toa.csv, a sound card), per hop
                      └─ ChirpDetector ─▶ StreamCalibrator (snapshot ─▶ calibrate() in an executor ─▶ Geometry)

``FrameChecker`` is the one stage that reads ``Frame.first_sample``: it fills gaps (flagged; the device is
left out of those blocks) and drops repeats. Each channel's spectrum is computed once per hop and shared by
GCC-PHAT and the beamformer. With a calibrator, every device's conditioned stream (its own clock) also goes through a chirp detector, and once per
block, at the frame boundary, a newly solved geometry is swapped in: each device's resampler gets its clock
rate (``rate_ratio``) and the aligner its clock offset (:meth:`Pipeline.apply_geometry`).
"""
from __future__ import annotations

import collections
import dataclasses
import logging
import math
import time
from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

import beamform
import estimators
from estimators import SPEED_OF_SOUND_M_S

from . import align, condition
from .align import Aligner, AlignmentEvent
from .calibration import StreamCalibrator
from .condition import DeviceCounters, FrameChecker, RetunableConditioner
from .config import EngineConfig
from .errors import ConfigError
from .geometry import Geometry
from .messages import Block, Frame, FrameFlag, HopResult, TdoaFrame, ToaEstimate

log = logging.getLogger(__name__)

HEARD_S = 0.25        # a track hit this recently is heard (sources.png draws the rest as prediction)
RECENTRE_FRAMES = 24   # frames whose median fine TOA decides a re-centring of the coarse alignment
DRIFT_EVERY_HOPS = 4    # the drift meter takes the short-time cross power every this many hops
DRIFT_STEP_S = 1e-5     # the noise spectra follow the drift in steps of at most this (0.06 rad at 1 kHz)
MAX_OFFSET_STD_S = 1e-3   # a calibrated clock offset moves the coarse alignment only when this certain


def make_estimator(config: EngineConfig, n_devices: int, device_names: Sequence[str] = ()):
    """The relative-TOA estimator named by ``config.estimator`` (``"tracks"``: a
    :class:`estimators.SourceTracker` whose ``target`` policy names its device by name or index)."""
    frame_period_s = config.hop_samples / config.working_rate_hz
    if config.estimator == "tracks":
        frame_period_s *= config.track_stride   # the tracker's frame is its measurement
        words = config.target.split()
        device = None
        if words[0] == "nearest":
            names = list(device_names)
            if words[1] in names:
                device = names.index(words[1])
            elif words[1].isdigit() and int(words[1]) < n_devices:
                device = int(words[1])
            else:
                raise ConfigError(f"target={config.target!r} names no device; devices: "
                                  f"{', '.join(names) or ', '.join(map(str, range(n_devices)))}")
        return estimators.SourceTracker(
            n_devices, frame_period_s=frame_period_s, sample_rate_hz=config.working_rate_hz,
            accel_std_s_per_s2=config.accel_std_s_per_s2, tdoa_std_s=config.track_tdoa_std_s,
            gate_probability=config.gate_probability, target=words[0], target_device=device,
            switch_ratio=config.switch_ratio, activity_time_constant_s=config.activity_time_constant_s,
            forget_after_s=config.forget_after_s, min_peak_value=config.min_confidence)
    if config.estimator == "subset":
        return estimators.SubsetToa(n_devices, min_confidence=config.min_confidence)
    if config.estimator == "pinv":
        return estimators.PinvToa(n_devices, min_confidence=config.min_confidence)
    kwargs = dict(frame_period_s=frame_period_s, accel_std_s_per_s2=config.accel_std_s_per_s2,
                  tdoa_std_s=config.tdoa_std_s, gate_probability=config.gate_probability,
                  min_confidence=config.min_confidence, init_max_residual_s=config.init_max_residual_s)
    if config.estimator == "smoother":
        return estimators.FixedLagKalmanToa(n_devices, lag_frames=config.smoother_lag_frames, **kwargs)
    return estimators.KalmanToa(n_devices, **kwargs)


class GivenToa:
    """Steering by a known relative TOA instead of an estimate: row ``k`` of ``fine_toa_s`` (n_frames,
    n_devices), seconds, at the ``k``-th frame (the last row once the table ends). A pipeline built with it
    (``Pipeline(..., steering=GivenToa(...))``) runs no GCC-PHAT and is driven block by block
    (:func:`steer_aligned`): scoring's true-TOA baselines go through the engine's own stages."""

    latency_frames = 0
    gated = False

    def __init__(self, fine_toa_s: np.ndarray) -> None:
        self._toa = np.atleast_2d(np.asarray(fine_toa_s, dtype=float))
        self._k = 0

    def update(self) -> np.ndarray:
        row = self._toa[min(self._k, len(self._toa) - 1)]
        self._k += 1
        return row


def steer_aligned(config: EngineConfig, samples: np.ndarray, fine_toa_s: np.ndarray, *, weighting: str,
                  valid: np.ndarray | None = None) -> np.ndarray:
    """Delay-and-sum of already aligned input through the pipeline's stages (STFT, beamformer, overlap-add
    tail, latency), steered per hop by a given fine TOA.

    Parameters
    ----------
    samples : ndarray, shape (n, n_devices)
        Aligned input at ``config.working_rate_hz`` (a run's ``aligned_input``, or synchronous signals).
    fine_toa_s : ndarray, shape (n_blocks, n_devices)
        Relative TOA (seconds) to steer hop ``k`` by (the last row for hops beyond).
    weighting : str
        The beamformer's channel weighting (``config.weighting`` is replaced by it).
    valid : ndarray, shape (n_blocks, n_devices), bool, optional
        Devices usable per hop (default: all).

    Returns
    -------
    ndarray, shape (n_blocks * hop,), float32
        The output on the reference clock (latency removed), as :meth:`Pipeline.enhanced_signal`.
    """
    hop = config.hop_samples
    fs = config.working_rate_hz
    n_dev = samples.shape[1]
    pipeline = Pipeline(dataclasses.replace(config, weighting=weighting), [fs] * n_dev,
                        steering=GivenToa(fine_toa_s))
    all_valid, no_offsets = np.ones(n_dev, bool), np.zeros(n_dev, np.int64)
    for k in range(len(samples) // hop):
        ok = all_valid if valid is None else np.asarray(valid[min(k, len(valid) - 1)], bool)
        pipeline.process_block(Block(seq=k, first_sample=k * hop, sample_rate_hz=fs, valid=ok,
                                     samples=np.ascontiguousarray(samples[k * hop:(k + 1) * hop], np.float32),
                                     offsets_samples=no_offsets))
    pipeline.finish()
    return pipeline.enhanced_signal()


@dataclass
class StreamCounters:
    n_blocks: int = 0
    n_gated: int = 0
    n_recentred: int = 0
    n_invalid_device_blocks: int = 0


class History(list):
    """A list for per-frame records that holds at most ``cap`` items however long the stream runs.

    When full, every other item is dropped and from then on only every ``stride``-th append is kept (the
    stride doubles each time): the record spans the whole stream at a resolution that halves as it grows.
    The dropping is spread over the next appends, ``THIN_CHUNK`` items at a time: dropping half of 20,000
    records in one append (each of a stream's ten lists at once, tens of thousands of arrays freed) took one
    hop 40-60 ms, an output underflow live. Meanwhile the older part is being thinned while new records
    already come at the new stride. Lists appended in lockstep stay in step. ``cap=None`` keeps everything;
    ``cap=0`` keeps nothing.
    """

    THIN_CHUNK = 256   # even: a chunk starts at an even index of the part being thinned, whose item is kept

    def __init__(self, cap: int | None = None) -> None:
        super().__init__()
        self.cap = cap
        self.stride = 1
        self.n_appended = 0
        self._thin_at = 0     # the part being thinned: [_thin_at, _thin_end) still holds every item
        self._thin_end = 0

    def append(self, value) -> None:   # noqa: D102 - list.append
        n, cap = self.n_appended, self.cap
        self.n_appended = n + 1
        if cap is None:
            list.append(self, value)
        elif cap > 0 and n % self.stride == 0:
            list.append(self, value)
            if self._thin_at < self._thin_end:
                self._thin()
            elif len(self) > cap:
                self.stride *= 2
                self._thin_at, self._thin_end = 0, len(self) - 1   # the new item stays
                self._thin()

    def _thin(self) -> None:
        """Drop every other item of the next chunk of the part being thinned."""
        a = self._thin_at
        b = min(a + self.THIN_CHUNK, self._thin_end)
        kept = self[a:b:2]
        self[a:b] = kept
        self._thin_at = a + len(kept)
        self._thin_end -= (b - a) - len(kept)


class HopTimes:
    """Running distribution of the per-hop processing time (bounded: a histogram of 1 µs bins up to 100 ms)."""

    BIN_MS = 1e-3
    N_BINS = 100_001

    def __init__(self) -> None:
        self.counts = np.zeros(self.N_BINS, np.int64)
        self.n = 0
        self.max_ms = 0.0
        self.sum_ms = 0.0

    def add(self, ms: float) -> None:
        self.counts[min(int(ms / self.BIN_MS), self.N_BINS - 1)] += 1
        self.n += 1
        self.sum_ms += ms
        self.max_ms = max(self.max_ms, ms)

    def percentile(self, q: float) -> float:
        """The ``q``-th percentile in ms (bin centre; NaN before the first hop)."""
        if not self.n:
            return float("nan")
        k = int(np.searchsorted(np.cumsum(self.counts), q / 100.0 * self.n, side="left"))
        return (min(k, self.N_BINS - 1) + 0.5) * self.BIN_MS


@dataclass
class PipelineState:
    """What the pipeline keeps per frame for the report, the plots and scoring.

    With ``history_cap=None`` (replays of fixtures) every frame is kept; otherwise each list is a
    :class:`History` of at most that many frames (the enhanced audio and the aligned input, which sinks
    write out as the stream goes, are then not kept at all): memory stays flat however long the stream runs.
    """

    history_cap: int | None = None

    def __post_init__(self) -> None:
        cap = self.history_cap
        for name in ("time_s", "toa_s", "gated", "tdoa_s", "confidence", "valid", "weights", "offsets",
                     "track_id", "speech_probability"):
            setattr(self, name, History(cap))
        audio_cap = None if cap is None else 0
        self.enhanced = History(audio_cap)
        self.aligned_input = History(audio_cap)
        # tracker only: every confirmed track's TOA per frame (coarse offsets included), for the sources plot
        self.source_tracks: dict = {}   # id -> {"kind", "time_s": History, "toa_s": History, "heard": History,
        #                                        "relabels": [(time_s, old kind, new kind, why)]}


class Pipeline:
    """Wires the stages for ``n_devices`` devices at the given rates.

    Parameters
    ----------
    config : EngineConfig
        Resolved configuration (``config.resolved(...)``).
    device_rates_hz : sequence of float
        Nominal rate of every device.
    keep_input : bool
        Keep the aligned multi-device input in memory (for metrics against ground truth).
    rate_ratios : sequence of float, optional
        Initial clock correction of every device (``DeviceConditioner.rate_ratio``).
    calibrator : StreamCalibrator, optional
        Periodic recalibration from a chirp beacon (detection per device, solves in a worker, swaps).
    device_names : sequence of str
        Device names (for ``target = "nearest NAME"``).
    history_cap : int, optional
        Keep at most this many per-frame records (:class:`History`) and no audio: for long and live streams,
        whose sinks write as they go. None keeps everything (fixtures, scoring).
    speech : object, optional
        Speech presence per hop for ``estimator = "tracks"`` (``process(samples, valid) -> SpeechFrame``);
        default :func:`stream.speech.make_speech_presence` with ``config.vad``.
    clock_groups : sequence of int, optional
        The first device of each device's clock group: the mics of one array (:mod:`stream.channels`) share
        one coarse offset (:class:`~stream.align.Aligner`). Default: every device its own clock.
    steering : GivenToa, optional
        Steer by a given TOA table instead of an estimate (no GCC-PHAT, no re-centring); the pipeline is then
        fed aligned blocks (:meth:`process_block`, then :meth:`finish`), not device frames: :func:`steer_aligned`.
    """

    def __init__(self, config: EngineConfig, device_rates_hz: Iterable[float], *, keep_input: bool = False,
                 rate_ratios: Iterable[float] | None = None, calibrator: StreamCalibrator | None = None,
                 device_names: Sequence[str] = (), speech=None, history_cap: int | None = None,
                 clock_groups: Sequence[int] | None = None, steering: GivenToa | None = None) -> None:
        self.config = config
        rates = list(device_rates_hz)
        self.n_devices = len(rates)
        ratios = list(rate_ratios) if rate_ratios is not None else [1.0] * self.n_devices
        fs = config.working_rate_hz
        retune = calibrator is not None and calibrator.apply == "drift"
        self.conditioners = [RetunableConditioner(r, working_rate_hz=fs, rate_ratio=q, keep_history=retune)
                             for r, q in zip(rates, ratios)]
        self.checkers = [FrameChecker() for _ in rates]
        self.calibrator = calibrator
        self.geometry: Geometry | None = None
        self.geometry_log: list[dict] = []
        if calibrator is not None:
            if calibrator.n_devices != self.n_devices:
                raise ValueError(f"calibrator.n_devices={calibrator.n_devices} must equal {self.n_devices=}")
            calibrator.bind([c.clock for c in self.conditioners])
        self.aligner = Aligner(self.n_devices, sample_rate_hz=fs, hop_samples=config.hop_samples,
                               align_window_s=config.align_window_s, max_offset_s=config.max_offset_s,
                               recheck_s=config.align_recheck_s, deadline_s=config.device_deadline_s,
                               clock_groups=clock_groups)
        self.stft = beamform.StreamingStft(self.n_devices, frame_samples=config.frame_samples,
                                           hop_samples=config.hop_samples)
        self.gcc = None
        self.estimator = None
        self.drift_meter: estimators.DriftMeter | None = None
        self._drift_phase = 0
        self._drift_moved_s: np.ndarray | None = None   # drift not yet turned into the noise spectra
        self._drift_rate_used: np.ndarray | None = None   # the meter's rate they were last turned at
        self._drift_rate_step_s = 0.0      # its largest move per hop
        self._drift_moved_bound_s = 0.0    # at least the largest of `_drift_moved_s`
        self.tracker: estimators.SourceTracker | None = None
        self.speech = None
        self._steering = steering
        estimated = self.n_devices >= 2 and steering is None   # a given TOA (scoring): no estimator, no GCC
        # the tracker measures (GCC peaks, track update) every `track_stride` hops, its frame; the GCC's averages
        # take every hop
        self.track_stride = config.track_stride if estimated and config.estimator == "tracks" else 1
        self._track_phase = 0
        if estimated and config.estimator == "tracks":
            self.gcc = estimators.NoiseAwareGcc(
                self.n_devices, n_fft=config.frame_samples, sample_rate_hz=fs, hop_s=config.hop_samples / fs,
                max_tdoa_s=config.max_tdoa_s, n_peaks=config.n_peaks, weighting=config.gcc_weighting,
                noise_time_constant_s=config.noise_time_constant_s, smoothing_time_constant_s=config.gcc_smoothing_s,
                fast_smoothing_time_constant_s=min(config.gcc_fast_smoothing_s, config.gcc_smoothing_s),
                noise_delay_s=config.noise_delay_s, phat_beta=config.gcc_phat_beta,
                phat_beta_near_noise=config.gcc_phat_beta_near_noise)
            # clock drift measured from the pairs' cross-power spectra; the noise spectra follow it (below)
            self.drift_meter = (estimators.DriftMeter(self.n_devices, n_fft=config.frame_samples, sample_rate_hz=fs)
                                if config.noise_follows_drift else None)
            self.estimator = self.tracker = make_estimator(config, self.n_devices, device_names)
            if speech is None:
                from .speech import make_speech_presence
                speech = make_speech_presence(self.n_devices, sample_rate_hz=fs, hop_samples=config.hop_samples,
                                              backend=config.vad)
            self.speech = speech
        elif estimated:
            self.gcc = estimators.GccPhat(self.n_devices, n_fft=config.frame_samples, sample_rate_hz=fs,
                                          max_tdoa_s=config.max_tdoa_s)
            self.estimator = make_estimator(config, self.n_devices)
        self._reference_only = np.zeros(self.n_devices, bool)
        self._speech_threshold = self.tracker.speech_threshold if self.tracker is not None else 0.5
        self._level = config.weighting == "level"
        self.das = beamform.DelayAndSum(self.n_devices, frame_samples=config.frame_samples,
                                        hop_samples=config.hop_samples, sample_rate_hz=fs,
                                        weighting=config.weighting,
                                        level_snr_exponent=config.level_snr_exponent)
        self._height_exp = config.level_height_exponent if self._level and self.tracker is not None else 0.0
        self._height_key = (-1, 0)
        self._height_log = np.zeros(self.n_devices)
        self.keep_input = keep_input
        self._results: list[HopResult] = []
        self.counters = StreamCounters()
        self.state = PipelineState(history_cap=history_cap)
        self.hop_times = HopTimes()
        self._fine_toa_s = np.zeros(self.n_devices)
        self._last_offsets = np.zeros(self.n_devices, dtype=np.int64)
        self._coarse_of: np.ndarray | None = None   # the offsets array `_coarse_s` was computed from
        self._coarse_s_cached = np.zeros(self.n_devices)
        self._recent: collections.deque = collections.deque(maxlen=RECENTRE_FRAMES)
        # frames wait in `_delayed` for `_lag` frames: a lagging estimator's TOA of them (the smoother), or the
        # tracker's decision `lookahead_frames` later (the tracker itself is causal: latency_frames 0)
        self.lookahead_frames = (int(round(config.tracker_lookahead_s * fs / config.hop_samples))
                                 if self.tracker is not None else 0)
        self._lag = (self.lookahead_frames if self.tracker is not None
                     else int(self.estimator.latency_frames) if self.estimator is not None else 0)
        self._delayed: collections.deque = collections.deque()
        self._zeros = np.zeros(self.n_devices)   # no rate, no fine TOA (never written)
        self._decision: tuple = (-1, False, np.zeros(self.n_devices), self._zeros, 0.0)
        self._measured: tuple = (np.zeros(0), np.zeros(0), False, False)   # the last measurement, held
        self.compile_s = self._compile_kernels()

    def _compile_kernels(self) -> float:
        """One silent hop through throwaway stages of the same shapes, so that numba compiles (first run after
        an install, a few seconds) or loads from its on-disk cache (milliseconds) every per-hop kernel here and
        not in the first block of a paced or live stream. Returns the seconds it took."""
        t0 = time.perf_counter()
        cfg, m = self.config, self.n_devices
        stft = beamform.StreamingStft(m, frame_samples=cfg.frame_samples, hop_samples=cfg.hop_samples)
        spectra = stft.process(np.zeros((cfg.hop_samples, m), np.float32))
        condition.compile_kernels(cfg.hop_samples)
        align.compile_kernels(cfg.hop_samples, m)
        if self.tracker is not None:
            gcc = estimators.NoiseAwareGcc(m, n_fft=cfg.frame_samples, sample_rate_hz=cfg.working_rate_hz,
                                           hop_s=cfg.hop_samples / cfg.working_rate_hz, max_tdoa_s=cfg.max_tdoa_s,
                                           n_peaks=cfg.n_peaks, weighting=cfg.gcc_weighting,
                                           phat_beta=cfg.gcc_phat_beta,
                                           phat_beta_near_noise=cfg.gcc_phat_beta_near_noise)
            peak_tdoa, peak_value = gcc.process(spectra, speech_probability=0.0, valid=np.ones(m, bool))
            noise = gcc.noise_peaks()
            if m >= 2:
                estimators.SourceTracker.compile_kernels(m, peak_tdoa, peak_value, noise,
                                                         frame_period_s=cfg.hop_samples / cfg.working_rate_hz,
                                                         sample_rate_hz=cfg.working_rate_hz)
        elif self.gcc is not None:
            estimators.GccPhat(m, n_fft=cfg.frame_samples, sample_rate_hz=cfg.working_rate_hz,
                               max_tdoa_s=cfg.max_tdoa_s).process(spectra, valid=np.ones(m, bool))
        das = beamform.DelayAndSum(m, frame_samples=cfg.frame_samples, hop_samples=cfg.hop_samples,
                                   sample_rate_hz=cfg.working_rate_hz, weighting=cfg.weighting)
        das.note_frame(spectra, np.ones(m, bool), pause=True)
        das.process_spectra(spectra, np.zeros(m), valid=np.ones(m, bool))
        if m >= 2 and self.tracker is None and self._steering is None:
            # the estimator's kernels
            estimator = make_estimator(cfg, m)
            n_pairs = m * (m - 1) // 2
            for _ in range(3):   # initialise, then update
                estimator.update(np.zeros(n_pairs), np.ones(n_pairs))
        if self.calibrator is not None:   # the calibration solver's kernels: compiled by a first solve in the
            # worker instead, they would stall this thread (the GIL) for up to ~0.2 s at a time over seconds.
            # A noisy cube of 8 events, from the built-in start (grid searches) and from a collapsed one (> 10
            # iterations): every kernel of the method runs
            corners = 3.0 * np.array(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij")).reshape(3, -1).T
            truth = estimators.Scene(0.5 + 0.6 * corners[[1, 2, 4, 7, 3]], corners)
            problem = estimators.simulate_problem(truth, np.full(7, 2.0), sigma_tdoa_s=1e-4, sigma_odo_m=0.01,
                                                  rng=0)
            for start in (None, estimators.Scene(np.full((5, 3), 1.5), 1.5 + 0.1 * corners)):
                estimators.solve_hybrid_tdoa(problem, method=self.calibrator.method, init=start, rng=0)
        return time.perf_counter() - t0

    @property
    def device_counters(self) -> list[DeviceCounters]:
        return [c.counters for c in self.conditioners]

    @property
    def latency_samples(self) -> int:
        """Output delay in samples: the beamformer's overlap-add, plus the estimator's lag in hops."""
        return int(self.das.latency_samples) + self._lag * self.config.hop_samples

    def feed(self, frame: Frame) -> list[HopResult]:
        """Process one device frame: every complete block it releases goes through the chain. Returns the
        hops produced (for the sinks), in order."""
        frame = self.checkers[frame.device_id].process(frame)
        samples, flags = self.conditioners[frame.device_id].process(frame)
        if self.calibrator is not None:
            self.calibrator.observe(frame.device_id, samples, last=bool(flags & FrameFlag.LAST))
        for block in self.aligner.push(frame.device_id, samples, flags):
            self.process_block(block)
        return self._take_results()

    def _take_results(self) -> list[HopResult]:
        out, self._results = self._results, []
        return out

    def finish(self) -> list[HopResult]:
        """Flush: release the last blocks and the beamformer's tail; then a last calibration solve (bounded
        wait: the audio is done). Returns the hops produced, in order."""
        for block in (self.aligner.finish() if self._steering is None else ()):   # a steered pipeline is fed
            self.process_block(block)                                               # blocks, not frames
        while self._delayed:   # the last `lag` frames: steered by the newest estimate or decision (none will come)
            if self.lookahead_frames:
                self._steer_ahead()
                continue
            spectra, block, time_s, tdoa, valid = self._delayed.popleft()
            self._steer(spectra, block, time_s, tdoa, valid, self._fine_toa_s, False, -1, float("nan"))
        if self.calibrator is not None:
            n0 = self.counters.n_blocks * self.config.hop_samples
            geometry = self.calibrator.finish(
                time_s=n0 / self.config.working_rate_hz,
                delta_s=self.clock_relation(n0, self._last_offsets) if self.aligner.ready else None)
            if geometry is not None:
                self.geometry = geometry
                off = [False] * self.n_devices
                self.geometry_log.append({"time_s": n0 / self.config.working_rate_hz, "n_events": geometry.n_events,
                                          "applied": False, "drift_applied": off, "offset_applied": off,
                                          "offset_action": [None] * self.n_devices,
                                          "shift_samples": [0] * self.n_devices,
                                          "rate_ratios": [c.rate_ratio for c in self.conditioners],
                                          "note": "solved after the end of the audio"})
        tail_blocks = -(-int(self.das.latency_samples) // self.config.hop_samples)
        zeros = np.zeros((self.config.hop_samples, self.n_devices), np.float32)
        toa = self._fine_toa_s
        for _ in range(tail_blocks):
            spectra = self.stft.process(zeros)
            enhanced = self.das.process_spectra(spectra, toa)
            self.state.enhanced.append(enhanced)
            self._results.append(HopResult(enhanced))
        return self._take_results()

    def _pre_roll(self, t0: float) -> None:
        """The first ``lag`` hops of a lagging estimator: the output is silence (the beamformer's output is
        ``lag`` hops later; :attr:`latency_samples` includes them) and nothing is recorded yet."""
        enhanced = np.zeros(self.config.hop_samples, np.float32)
        self.state.enhanced.append(enhanced)
        self.hop_times.add(1e3 * (time.perf_counter() - t0))
        self._results.append(HopResult(enhanced))

    def process_block(self, block: Block) -> None:
        """One aligned block through the chain; its hop is queued for :meth:`feed`/:meth:`finish` to return."""
        t0 = time.perf_counter()
        cfg = self.config
        fs = cfg.working_rate_hz
        time_s = (block.first_sample + cfg.hop_samples - cfg.frame_samples / 2) / fs   # frame centre
        if self.calibrator is not None:  # frame boundary: collect a finished solve, never wait for one
            geometry = self.calibrator.step(
                time_s=block.first_sample / fs,
                delta_s=lambda: self.clock_relation(block.first_sample, block.offsets_samples))
            if geometry is not None:
                self.apply_geometry(geometry, next_first_sample=block.first_sample + cfg.hop_samples)
        self._follow_offsets(block)
        spectra = self.stft.process(block.samples)
        valid, track_id, p_speech, measure = block.valid, -1, float("nan"), True
        if self.tracker is not None:
            p_speech = self.speech.process(block.samples, block.valid, finite=True).probability
            measure = self._track_phase == 0
            self._track_phase = (self._track_phase + 1) % self.track_stride
            # every hop moves the GCC's averages; its peaks are searched on the tracker's measurements only
            peaks = self.gcc.process(spectra, speech_probability=p_speech, valid=block.valid,
                                     raw=p_speech < self.tracker.speech_threshold, peaks=measure)
            if self.drift_meter is not None:
                self._follow_drift(time_s)
            if measure:
                fine, tdoa, gated, track_id, fallback = self._track(*peaks, block, time_s, p_speech)
            else:   # between measurements the last decision holds (the look-ahead takes its TOA along its rate;
                # a re-aligned device has moved the tracks with it; a reset leaves nothing steered)
                tdoa_s, confidence, gated, fallback = self._measured
                tdoa = TdoaFrame(block.seq, time_s, tdoa_s, confidence)
                steered = self.tracker.steered
                fine = steered.toa_s if steered is not None else self.tracker.steered_toa_s
                track_id = self.tracker.steered_id
            if self.lookahead_frames:
                self._fine_toa_s = fine
                if measure:
                    rate = self.tracker.steered.toa_rate_s_per_s if track_id >= 0 else self._zeros
                    self._decision = (track_id, fallback, self._coarse_s(block) + fine, rate, time_s)
                self._look_ahead(t0, spectra, block, time_s, tdoa, gated, p_speech, measure)
                return
            if fallback:
                valid = self._reference_only_of(block.valid)
        elif self.gcc is not None:
            tdoa_s, confidence = self.gcc.process(spectra, valid=block.valid)   # invalid device: confidence 0
            tdoa = TdoaFrame(block.seq, time_s, tdoa_s, confidence)
            fine = self.estimator.update(tdoa.tdoa_s, tdoa.confidence)
            gated = bool(self.estimator.gated)
        else:
            tdoa = TdoaFrame(block.seq, time_s, np.zeros(0), np.zeros(0))
            fine = self._steering.update() if self._steering is not None else np.zeros(1)
            gated = False
        self._fine_toa_s = fine
        if self._lag:   # the estimate is `lag` frames old: steer the spectra of that frame with it
            if not self._held(t0, (spectra.copy(order="K"), block, time_s, tdoa, valid.copy())):
                return
            spectra, block, time_s, tdoa, valid = self._delayed.popleft()
        self._steer(spectra, block, time_s, tdoa, valid, fine, gated, track_id, p_speech)
        if measure:   # on each measurement's TOA once
            self._recentre(fine, block)
        self.hop_times.add(1e3 * (time.perf_counter() - t0))

    def _track(self, peak_tdoa: np.ndarray, peak_value: np.ndarray, block: Block, time_s: float,
               p_speech: float) -> tuple:
        """One tracker measurement from the frame's GCC peaks: the track bank's update, each source track's
        history. Returns (the steered fine TOA, the TDOA frame, gated, the steered track id, fallback)."""
        tdoa = TdoaFrame(block.seq, time_s, peak_tdoa[:, 0], peak_value[:, 0])
        fine = self.tracker.update(peak_tdoa, peak_value, speech_probability=p_speech,
                                   usable=self.gcc.usable, time_s=time_s,
                                   noise_peaks=self.gcc.noise_peaks if self.gcc.noise_mature else None)
        gated = self.tracker.gated
        track_id = self.tracker.steered_id
        coarse = self._coarse_s(block)
        for t in self.tracker.tracks:
            if t.kind != "tentative":
                h = self.state.source_tracks.get(t.track_id)
                if h is None:
                    cap = self.state.history_cap
                    h = self.state.source_tracks[t.track_id] = {"kind": t.kind, "time_s": History(cap),
                                                                "toa_s": History(cap), "heard": History(cap),
                                                                "relabels": t.relabels}
                h["kind"] = t.kind
                h["time_s"].append(time_s)
                h["toa_s"].append(coarse + t.toa_s)
                h["heard"].append(time_s - t.last_hit_s <= HEARD_S)
        # no talker tracked, and the devices' average at the coarse alignment would point at a tracked
        # noise source: the output is the reference device, not a beam at the noise (otherwise the
        # average: no louder than one device, with less of the room's reverberation and sensor noise)
        fallback = track_id < 0 and self.tracker.noise_at(fine)
        self._measured = (tdoa.tdoa_s, tdoa.confidence, gated, fallback)
        return fine, tdoa, gated, track_id, fallback

    def _reference_only_of(self, valid: np.ndarray) -> np.ndarray:
        out = self._reference_only
        out[:] = False
        out[int(np.argmax(valid))] = True
        return out

    def _look_ahead(self, t0: float, spectra, block: Block, time_s: float, tdoa: TdoaFrame, gated: bool,
                    p_speech: float, measured: bool) -> None:
        """Tracker look-ahead: this frame waits ``lookahead`` frames, and the frame that many frames old is
        steered by the newest ``_decision`` (track id, fallback, total TOA = coarse offset + fine, its rate, the
        time it was made: this frame's when ``measured``): the steered track at its newest TOA taken back to the
        old frame's time along its TOA rate (the Kalman state's velocity: a walking talker's TOA moves in those
        frames), or the reference device when nothing is steered and the average would point at a noise
        source."""
        if measured:
            self._recentre(self._fine_toa_s, block)
        # order "K" keeps the STFT's column-major layout, which the beamformer's kernels take as it is (a plain
        # copy is row-major: the beamformer copied it once more, in every hop)
        if self._held(t0, (spectra.copy(order="K"), block, time_s, tdoa, block.valid.copy(), gated, p_speech)):
            self._steer_ahead()
            self.hop_times.add(1e3 * (time.perf_counter() - t0))

    def _held(self, t0: float, frame: tuple) -> bool:
        """Queue ``frame`` in ``_delayed``; while fewer than ``_lag`` frames wait, a silent hop and False."""
        self._delayed.append(frame)
        if len(self._delayed) <= self._lag:
            self._pre_roll(t0)
            return False
        return True

    def _steer_ahead(self) -> None:
        spectra, block, time_s, tdoa, valid, gated, p_speech = self._delayed.popleft()
        track_id, fallback, total_toa_s, rate, decided_s = self._decision
        if track_id < 0:   # nothing steered: the devices' average at the coarse alignment
            fine = self._zeros
        else:
            fine = total_toa_s - rate * (decided_s - time_s) - self._coarse_s(block)
        if fallback:
            valid = self._reference_only_of(valid)
        if self._height_exp:
            self._height_factors(track_id)
        self._steer(spectra, block, time_s, tdoa, valid, fine, gated, track_id, p_speech)

    def _height_factors(self, track_id: int) -> None:
        """``level_height_exponent``: each device's weight times (its matched peak height on the steered talker
        track / the median device's) to that power (:meth:`SourceTracker.steered_height_factors`); none while
        nothing is steered. Computed again only when the steered track or its hits change."""
        t = self.tracker.steered if track_id >= 0 else None
        key = (-1, 0) if t is None else (t.track_id, self.tracker.n_steered_hits)
        if key == self._height_key:
            return
        self._height_key = key
        if t is not None and self.tracker.steered_height_factors(self._height_exp, self._height_log):
            self.das.set_level_factors(self._height_log)
        else:
            self.das.set_level_factors(None)

    def _steer(self, spectra, block: Block, time_s: float, tdoa: TdoaFrame, valid: np.ndarray, fine: np.ndarray,
               gated: bool, track_id: int, p_speech: float) -> None:
        """Delay-and-sum of one frame's spectra steered by ``fine``; record it and queue its hop."""
        r = self.aligner.time_reference
        if self._level and not math.isnan(p_speech):   # NaN: no speech detector, no pauses to learn from
            # "level" weighting: every device's noise floor from the pauses, its speech level from the rest
            self.das.note_frame(spectra, block.valid, pause=p_speech < self._speech_threshold)
        enhanced = self.das.process_spectra(spectra, fine - fine[r] if r else fine, valid=valid)
        toa = ToaEstimate(block.seq, time_s, self._coarse_s(block) + fine, gated, track_id, p_speech)
        self._record(block, tdoa, toa, enhanced)
        self._results.append(HopResult(enhanced, toa))

    # calibration -----------------------------------------------------------------------------
    def clock_relation(self, first_sample: int, offsets_samples: np.ndarray) -> np.ndarray:
        """``c_i - c_0`` (seconds): every device's clock minus device 0's at reference sample ``first_sample``,
        through the coarse alignment and each device's clock map. NaN for devices the aligner left out.

        Returns
        -------
        ndarray, shape (n_devices,)
        """
        c = np.array([cond.clock.clock_s(first_sample + int(o)) for cond, o in
                      zip(self.conditioners, offsets_samples)])
        out = c - c[0]
        out[~self.aligner.aligned] = np.nan
        out[0] = 0.0
        return out

    def apply_geometry(self, geometry: Geometry, *, next_first_sample: int) -> None:
        """Swap in a new geometry at a frame boundary (effective from the next block).

        Per device ``i >= 1``, with the clock model ``c_i = c_0 + offset_i + drift_i (c_0 - epoch)``
        (:mod:`estimators.geometry`):

        - drift (``calibration_apply = "drift"``, once its CRLB standard deviation is at most
          ``calibration_max_drift_std_ppm``): the device's resampler takes the rate ``q = 1 + drift_i``; its
          last clock segment ``c = c_s + (m - m_s) q / fs`` then puts the clock offset (the working-rate sample
          ``m`` that lines up with reference sample ``n``) at the constant ``o = m - n = m_s + fs (offset_i -
          (q - 1) epoch - c_s) / q``, and the TOA estimator's rate state moves by the rate change;
        - offset (``drift`` or ``offsets``, once its standard deviation is at most ``MAX_OFFSET_STD_S``): the
          current total TOA (coarse offset + fine TOA) minus the clock offset ``o = index_of(c_i(n)) - n`` is the
          acoustic part. When it is plausible (within the device distance over c, plus 3 standard deviations
          and 2 ms) the coarse/fine split is kept: GCC-PHAT stays centred on the talker. Otherwise the coarse
          alignment was wrong: it is repaired to the clock offset and the estimator restarts.

        Every coarse change goes through :meth:`Aligner.shift`; :meth:`_follow_offsets` moves the estimator
        with it, so the steering stays continuous.
        """
        self.geometry = geometry
        mode = self.calibrator.apply if self.calibrator is not None else "drift"
        fs = self.config.working_rate_hz
        n_dev = self.n_devices
        entry = {"time_s": next_first_sample / fs, "n_events": geometry.n_events, "applied": mode != "none",
                 "drift_applied": [False] * n_dev, "offset_applied": [False] * n_dev,
                 "offset_action": [None] * n_dev, "shift_samples": [0] * n_dev,
                 "rate_ratios": [c.rate_ratio for c in self.conditioners]}
        if mode == "none":
            self.geometry_log.append(entry)
            return
        n = int(next_first_sample)
        c0 = n / fs
        rate_change = np.zeros(n_dev)
        repaired = False
        for d in range(1, n_dev):
            off, drift, q = geometry.offsets_s[d], geometry.drifts_ppm[d], float(geometry.rate_ratios[d])
            if not (np.isfinite(off) and np.isfinite(drift) and geometry.offset_std_s[d] <= MAX_OFFSET_STD_S):
                continue
            cond = self.conditioners[d]
            o_now = cond.clock.index_of(c0 + off + (q - 1.0) * (c0 - geometry.epoch_clock_s)) - n
            coarse = int(self.aligner.offsets_samples[d])
            acoustic = coarse + self._fine_toa_s[d] * fs - o_now
            dist_s = float(np.linalg.norm(geometry.positions_m[d] - geometry.positions_m[0])) / SPEED_OF_SOUND_M_S
            bound = (dist_s if np.isfinite(dist_s) else self.config.max_tdoa_s) + 3 * geometry.offset_std_s[d] + 2e-3
            o_new = o_now
            drift_ok = geometry.drift_std_ppm[d] <= self.config.calibration_max_drift_std_ppm
            if mode == "drift" and not cond.ended and drift_ok:
                rate_change[d] = q - cond.rate_ratio
                cond.retune(q)
                m_s, c_s = cond.clock.start_index[-1], cond.clock.start_clock_s[-1]
                o_new = m_s + fs * (off - (q - 1.0) * geometry.epoch_clock_s - c_s) / q
                entry["drift_applied"][d] = True
            if abs(acoustic) <= bound * fs:
                target, action = coarse + (o_new - o_now), "kept"
            else:
                target, action = o_new, "repaired"
                repaired = True
            delta = int(round(target)) - coarse
            entry["shift_samples"][d] = delta
            entry["offset_applied"][d] = True
            entry["offset_action"][d] = action
            reason = ("calibration: clock rate" if action == "kept" else
                      f"calibration: coarse offset disagreed with the clock offset by {1e3 * acoustic / fs:+.1f} ms")
            self.aligner.shift(d, delta, reason=reason, correction=action == "repaired")
        entry["rate_ratios"] = [c.rate_ratio for c in self.conditioners]
        if repaired and self.estimator is not None:
            self.estimator.reset()
        elif rate_change.any():
            self._shift_toa_rate(-rate_change)
        self.geometry_log.append(entry)

    def _shift_toa_rate(self, delta_rate: np.ndarray) -> None:
        """A resampler's new rate changes the fine TOA's rate (s/s) the estimator tracks by ``delta_rate``
        (device ``i`` against device 0): move its rate state with it, as :meth:`KalmanToa.shift` does for
        the TOA, so that the change does not look like clutter. Estimators without a rate are left alone."""
        if self.estimator.initialised:
            self.estimator.shift(np.zeros(self.n_devices), delta_rate_s_per_s=delta_rate)

    # helpers ---------------------------------------------------------------------------------
    def _record(self, block: Block, tdoa: TdoaFrame, toa: ToaEstimate, enhanced: np.ndarray) -> None:
        s, c = self.state, self.counters
        c.n_blocks += 1
        c.n_gated += int(toa.gated)
        c.n_invalid_device_blocks += self.n_devices - int(np.count_nonzero(block.valid))
        s.time_s.append(toa.time_s)
        s.toa_s.append(toa.toa_s)
        s.gated.append(toa.gated)
        s.tdoa_s.append(tdoa.tdoa_s)
        s.confidence.append(tdoa.confidence)
        s.valid.append(block.valid)
        s.offsets.append(block.offsets_samples)
        s.track_id.append(toa.track_id)
        s.speech_probability.append(toa.speech_probability)
        s.weights.append(self.das.channel_weights)   # float32, a copy
        s.enhanced.append(enhanced)
        if self.keep_input:
            s.aligned_input.append(block.samples)

    def _recentre(self, fine_toa_s: np.ndarray, block: Block) -> None:
        """Re-check of the coarse alignment: move a device whose fine TOA has stayed near the GCC
        search edge (median over the last ``RECENTRE_FRAMES`` frames) by that median. Not during the first
        ``align_window_s`` of the stream: the estimators are starting up (a young track may still slide from a
        wrong peak to the talker), and the coarse alignment was just measured on that very audio."""
        if block.first_sample < self.aligner.window_samples or self._steering is not None:
            return
        self._recent.append(fine_toa_s)
        limit = 0.5 * self.config.max_tdoa_s
        # checked only on frames whose newest value passes the limit (cheap): when the median
        # passes it, most recent frames do
        if len(self._recent) < RECENTRE_FRAMES or not (np.abs(fine_toa_s) > limit).any():
            return
        median = np.median(np.asarray(self._recent), axis=0)
        pending = block.offsets_samples != self.aligner.offsets_samples   # a shift not yet in effect
        fs = self.config.working_rate_hz
        moved = False
        first = np.asarray(self.aligner.clock_groups) == np.arange(self.n_devices)   # an array moves as one clock
        for d in np.flatnonzero((np.abs(median) > limit) & ~pending & first):
            self.aligner.shift_group(int(d), int(round(median[d] * fs)), reason="fine TOA near the search limit")
            self.counters.n_recentred += 1
            moved = True
        if moved:
            self._recent.clear()

    def _follow_drift(self, time_s: float) -> None:
        """Clock drift moves every source's TDOA, the noise's too, while the noise average only takes
        non-speech frames: over seconds of speech it would subtract the noise where it was. The drift meter takes
        the short-time cross power every ``DRIFT_EVERY_HOPS`` hops; the noise spectra are turned by the drift
        since they were last turned once a device has moved by ``DRIFT_STEP_S``. A new measurement turns them by
        the change of rate times the age of the average's frames (turned at the old rate since they were taken;
        the first measurement comes after 2 s of stream, when nothing had turned them)."""
        hop_s = self.config.hop_samples / self.config.working_rate_hz
        self._drift_phase = (self._drift_phase + 1) % DRIFT_EVERY_HOPS
        if self._drift_phase == 0:
            self.drift_meter.add(self.gcc.short_time_cross_power, time_s, DRIFT_EVERY_HOPS * hop_s)
        rate = self.drift_meter.rate_s_per_s
        if rate is None:
            return
        if self._drift_moved_s is None:
            self._drift_moved_s = np.zeros(self.n_devices)
            self._drift_rate_used = np.zeros(self.n_devices)
        if rate is not self._drift_rate_used:
            # a new measurement: the average's frames were turned at the old rate since they were taken
            self._drift_moved_s += (rate - self._drift_rate_used) * self.gcc.noise_age_s
            self._drift_rate_used = rate
            self._drift_rate_step_s = float(np.abs(rate).max()) * hop_s
            self._drift_moved_bound_s = float(np.abs(self._drift_moved_s).max())
        self._drift_moved_s += rate * hop_s
        # the exact test only once a bound on it (the largest move plus the largest rate per hop) could pass
        self._drift_moved_bound_s += self._drift_rate_step_s
        if (self._drift_moved_bound_s >= DRIFT_STEP_S * (1.0 - 1e-9)
                and np.abs(self._drift_moved_s).max() >= DRIFT_STEP_S):
            self.gcc.shift_noise(self._drift_moved_s, short_time=False)   # the meter measures the short-time one
            self._drift_moved_s[:] = 0.0
            self._drift_moved_bound_s = 0.0

    def _coarse_s(self, block: Block) -> np.ndarray:
        """The block's coarse offsets in seconds (the aligner hands out the same array while they do not change,
        and no stage writes to a block's arrays: computed once per change)."""
        if block.offsets_samples is not self._coarse_of:
            self._coarse_of = block.offsets_samples
            self._coarse_s_cached = block.offsets_samples / self.config.working_rate_hz
        return self._coarse_s_cached

    def _follow_offsets(self, block: Block) -> None:
        """When the aligner moved a device, move the estimator's state with it."""
        if block.offsets_samples is self._last_offsets:   # the aligner's array of the blocks before: no move
            return
        delta = block.offsets_samples - self._last_offsets
        self._last_offsets = block.offsets_samples
        if self.estimator is None or not delta.any() or block.seq == 0:
            return
        delta_s = delta / self.config.working_rate_hz
        if self.drift_meter is not None:   # the noise did not move: its spectra are moved with the alignment
            self.gcc.shift_noise(-delta_s)
            self.drift_meter.shift(-delta_s)
        if block.corrected is not None:   # the old alignment was wrong: what was tracked under it means nothing
            self.estimator.reset()
            self._recent.clear()
            return
        self.estimator.shift(-(delta_s - delta_s[0]))

    # results ---------------------------------------------------------------------------------
    def enhanced_signal(self) -> np.ndarray:
        """Enhanced output on the reference clock (beamformer latency removed), float32 (empty when the
        pipeline keeps no audio: ``history_cap`` set)."""
        if not self.state.enhanced:
            return np.zeros(0, np.float32)
        y = np.concatenate(self.state.enhanced)
        n = self.counters.n_blocks * self.config.hop_samples
        return y[self.latency_samples:self.latency_samples + n]

    def toa_track(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s = self.state
        if not s.time_s:
            return np.zeros(0), np.zeros((0, self.n_devices)), np.zeros(0, bool)
        return np.asarray(s.time_s), np.vstack(s.toa_s), np.asarray(s.gated)

    @property
    def alignment_events(self) -> list[AlignmentEvent]:
        return self.aligner.events
