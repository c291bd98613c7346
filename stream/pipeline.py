"""The streaming pipeline: one plain loop, one line per stage.

::

    Source ─Frame─▶ DeviceConditioner ─▶ Aligner ─Block─▶ StreamingStft ─▶ GccPhat ─TdoaFrame─▶
        ToaEstimator ─ToaEstimate─▶ DelayAndSum ─▶ sinks (enhanced.wav, toa.csv)

Each channel's spectrum is computed once per hop and shared by GCC-PHAT and the beamformer.
"""
from __future__ import annotations

import collections
import logging
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np

import beamform
import estimators

from .align import Aligner, AlignmentEvent
from .condition import DeviceConditioner, DeviceCounters
from .config import EngineConfig
from .messages import Block, Frame, TdoaFrame, ToaEstimate

log = logging.getLogger(__name__)

RECENTRE_FRAMES = 24   # frames whose median fine TOA decides a re-centring of the coarse alignment


def make_estimator(config: EngineConfig, n_devices: int):
    """The relative-TOA estimator named by ``config.estimator``."""
    frame_period_s = config.hop_samples / config.working_rate_hz
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


@dataclass
class StreamCounters:
    n_blocks: int = 0
    n_gated: int = 0
    n_recentred: int = 0
    n_invalid_device_blocks: int = 0


@dataclass
class PipelineState:
    """What the pipeline produced so far (kept so that everything can be written out on failure)."""

    time_s: list[float] = field(default_factory=list)
    toa_s: list[np.ndarray] = field(default_factory=list)
    gated: list[bool] = field(default_factory=list)
    tdoa_s: list[np.ndarray] = field(default_factory=list)
    confidence: list[np.ndarray] = field(default_factory=list)
    valid: list[np.ndarray] = field(default_factory=list)
    weights: list[np.ndarray] = field(default_factory=list)
    enhanced: list[np.ndarray] = field(default_factory=list)
    aligned_input: list[np.ndarray] = field(default_factory=list)
    block_ms: list[float] = field(default_factory=list)
    offsets: list[np.ndarray] = field(default_factory=list)


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
    on_block : callable, optional
        Called with ``(Block, ToaEstimate, enhanced_hop)`` after each block (sinks).
    """

    def __init__(self, config: EngineConfig, device_rates_hz: Iterable[float], *, keep_input: bool = False,
                 on_block: Callable[[Block, ToaEstimate, np.ndarray], None] | None = None,
                 rate_ratios: Iterable[float] | None = None) -> None:
        self.config = config
        rates = list(device_rates_hz)
        self.n_devices = len(rates)
        ratios = list(rate_ratios) if rate_ratios is not None else [1.0] * self.n_devices
        fs = config.working_rate_hz
        self.conditioners = [DeviceConditioner(r, working_rate_hz=fs, rate_ratio=q) for r, q in zip(rates, ratios)]
        self.aligner = Aligner(self.n_devices, sample_rate_hz=fs, hop_samples=config.hop_samples,
                               align_window_s=config.align_window_s, max_offset_s=config.max_offset_s,
                               recheck_s=config.align_recheck_s)
        self.stft = beamform.StreamingStft(self.n_devices, frame_samples=config.frame_samples,
                                           hop_samples=config.hop_samples)
        self.gcc = None
        self.estimator = None
        if self.n_devices >= 2:
            self.gcc = estimators.GccPhat(self.n_devices, n_fft=config.frame_samples, sample_rate_hz=fs,
                                          max_tdoa_s=config.max_tdoa_s)
            self.estimator = make_estimator(config, self.n_devices)
        self.das = beamform.DelayAndSum(self.n_devices, frame_samples=config.frame_samples,
                                        hop_samples=config.hop_samples, sample_rate_hz=fs,
                                        weighting=config.weighting)
        self.keep_input = keep_input
        self.on_block = on_block
        self.counters = StreamCounters()
        self.state = PipelineState()
        self._fine_toa_s = np.zeros(self.n_devices)
        self._last_offsets = np.zeros(self.n_devices, dtype=np.int64)
        self._recent: collections.deque = collections.deque(maxlen=RECENTRE_FRAMES)

    @property
    def device_counters(self) -> list[DeviceCounters]:
        return [c.counters for c in self.conditioners]

    @property
    def latency_samples(self) -> int:
        return int(self.das.latency_samples)

    def feed(self, frame: Frame) -> None:
        """Process one device frame (all complete blocks it releases go through the chain)."""
        samples, flags = self.conditioners[frame.device_id].process(frame)
        for block in self.aligner.push(frame.device_id, samples, flags):
            self.process_block(block)

    def finish(self) -> None:
        """Flush: release the last blocks and the beamformer's tail."""
        for block in self.aligner.finish():
            self.process_block(block)
        tail_blocks = -(-self.latency_samples // self.config.hop_samples)
        zeros = np.zeros((self.config.hop_samples, self.n_devices), np.float32)
        toa = self._fine_toa_s
        for _ in range(tail_blocks):
            spectra = self.stft.process(zeros)
            self.state.enhanced.append(self.das.process_spectra(spectra, toa))

    def process_block(self, block: Block) -> None:
        t0 = time.perf_counter()
        cfg = self.config
        fs = cfg.working_rate_hz
        time_s = (block.first_sample + cfg.hop_samples - cfg.frame_samples / 2) / fs   # frame centre
        self._follow_offsets(block)
        spectra = self.stft.process(block.samples)
        if self.gcc is not None:
            tdoa_s, confidence = self.gcc.process(spectra)
            confidence = np.where(self._pair_valid(block.valid), confidence, 0.0)
            tdoa = TdoaFrame(block.seq, time_s, tdoa_s, confidence)
            fine = self.estimator.update(tdoa.tdoa_s, tdoa.confidence)
            gated = bool(getattr(self.estimator, "gated", False))
        else:
            tdoa = TdoaFrame(block.seq, time_s, np.zeros(0), np.zeros(0))
            fine, gated = np.zeros(1), False
        self._fine_toa_s = fine
        enhanced = self.das.process_spectra(spectra, fine, valid=block.valid)
        toa = ToaEstimate(block.seq, time_s, block.offsets_samples / fs + fine, gated)
        self._record(block, tdoa, toa, enhanced)
        self._recentre(fine, block)
        self.state.block_ms.append(1e3 * (time.perf_counter() - t0))
        if self.on_block is not None:
            self.on_block(block, toa, enhanced)

    # helpers ---------------------------------------------------------------------------------
    def _pair_valid(self, valid: np.ndarray) -> np.ndarray:
        p = estimators.pairs(self.n_devices)
        return valid[p[:, 0]] & valid[p[:, 1]]

    def _record(self, block: Block, tdoa: TdoaFrame, toa: ToaEstimate, enhanced: np.ndarray) -> None:
        s, c = self.state, self.counters
        c.n_blocks += 1
        c.n_gated += int(toa.gated)
        c.n_invalid_device_blocks += int((~block.valid).sum())
        s.time_s.append(toa.time_s)
        s.toa_s.append(toa.toa_s)
        s.gated.append(toa.gated)
        s.tdoa_s.append(tdoa.tdoa_s)
        s.confidence.append(tdoa.confidence)
        s.valid.append(block.valid)
        s.offsets.append(block.offsets_samples)
        s.weights.append(np.asarray(self.das.channel_weights, dtype=np.float32).copy())
        s.enhanced.append(enhanced)
        if self.keep_input:
            s.aligned_input.append(block.samples)

    def _recentre(self, fine_toa_s: np.ndarray, block: Block) -> None:
        """Re-check of the coarse alignment: move a device whose fine TOA has stayed near the GCC
        search edge (median over the last ``RECENTRE_FRAMES`` frames) by that median."""
        self._recent.append(fine_toa_s)
        if len(self._recent) < RECENTRE_FRAMES:
            return
        median = np.median(np.asarray(self._recent), axis=0)
        limit = 0.5 * self.config.max_tdoa_s
        pending = block.offsets_samples != self.aligner.offsets_samples   # a shift not yet in effect
        fs = self.config.working_rate_hz
        moved = False
        for d in np.flatnonzero((np.abs(median) > limit) & ~pending):
            self.aligner.shift(int(d), int(round(median[d] * fs)), reason="fine TOA near the search limit")
            self.counters.n_recentred += 1
            moved = True
        if moved:
            self._recent.clear()

    def _follow_offsets(self, block: Block) -> None:
        """When the aligner moved a device, move the estimator's state with it."""
        delta = block.offsets_samples - self._last_offsets
        self._last_offsets = block.offsets_samples.copy()
        if self.estimator is None or not delta.any() or block.seq == 0:
            return
        delta_s = delta / self.config.working_rate_hz
        if hasattr(self.estimator, "shift"):
            self.estimator.shift(-(delta_s - delta_s[0]))
        else:
            self.estimator.reset()

    # results ---------------------------------------------------------------------------------
    def enhanced_signal(self) -> np.ndarray:
        """Enhanced output on the reference clock (beamformer latency removed), float32."""
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
