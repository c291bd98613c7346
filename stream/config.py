"""Engine options: one dataclass, filled from defaults, a fixture's ``[engine]`` table, a TOML config
file and command-line flags (in that order of precedence, the last wins).

A TOML config uses the same names as the long CLI flags, with underscores::

    estimator = "tracks"
    frame_samples = 512
    hop_samples = 128
    working_rate_hz = 16000

Calibration from a moving chirp beacon is on when ``calibration_odometry`` names the beacon's odometry file
(``dx_m,dy_m,dz_m[,interval_s]``, one row per step between chirps)::

    calibration_odometry = "beacon_odometry.csv"
    recalibrate_every = 8          # re-solve every 8 new chirps
    calibration_apply = "drift"    # resample each device to its clock rate and set its offset
"""
from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Literal

from .errors import ConfigError

Estimator = Literal["tracks", "subset", "pinv", "kalman", "smoother"]
GccWeighting = Literal["subtract", "subtract-snr", "phat"]
Weighting = Literal["equal", "adaptive", "level"]
CalibrationMethod = Literal["hybrid", "baseline"]
CalibrationApply = Literal["drift", "offsets", "none"]
CalibrationExecutor = Literal["thread", "process"]

PAPER_FRAME_S = 4096 / 48000  # the TOA paper's analysis frame: 4096 samples at 48 kHz (85.3 ms)


@dataclass(frozen=True)
class EngineConfig:
    """All engine options (units in the names).

    ``working_rate_hz``, ``frame_samples``, ``hop_samples`` and ``min_confidence`` may be None: the
    working rate is then the reference device's rate, the frame the power of two closest to 85.3 ms
    (4096 at 48 kHz, as in the TOA paper), the hop a quarter of the frame (75 % overlap), and the
    smallest usable GCC-PHAT peak ``5 / sqrt(frame_samples)``.
    """

    estimator: Estimator = "tracks"
    working_rate_hz: float | None = None
    frame_samples: int | None = None
    hop_samples: int | None = None
    max_tdoa_s: float = 0.012
    weighting: Weighting = "level"   # beamform.DelayAndSum; "level" learns from the tracker's speech detector
    # (the other estimators have none: for them it is "equal")
    level_snr_exponent: float = 1.0  # "level": weights also ~ (device SNR / median SNR)^(this / 2); 1 is MRC
    level_height_exponent: float = 1.0   # "level" with the tracker: weights also ~ (the device's mean matched GCC
    #                                      peak height on the steered talker track / the median device's)^this
    # Kalman TOA (eqs. 13-17)
    accel_std_s_per_s2: float = 1e-3
    tdoa_std_s: float = 5e-4
    gate_probability: float = 0.99
    min_confidence: float | None = None
    init_max_residual_s: float = 5e-5
    smoother_lag_frames: int = 4
    # Several sources (estimator = "tracks", estimators.tracks): speech presence, noise-aware GCC, track bank
    target: str = "active-talker"                  # or "nearest DEVICE" (a device name or index)
    vad: str = "auto"                              # speech-presence backend (stream.speech), "auto" = the default
    gcc_weighting: GccWeighting = "subtract"       # noise cross-power removal before PHAT (estimators.multipeak)
    gcc_phat_beta: float = 1.0                     # PHAT-beta exponent of the tracker's GCC (1: PHAT)
    gcc_phat_beta_near_noise: bool = False         # the exponent only where a pair is near the noise, PHAT elsewhere
    n_peaks: int = 5                               # GCC peaks kept per pair (tracker)
    noise_time_constant_s: float = 1.0             # noise cross-power average over non-speech frames
    noise_delay_s: float = 0.25                    # a frame joins the noise average this late, if no speech came since
    gcc_smoothing_s: float = 0.1                   # short-time cross-power average before the noise removal (0: off)
    gcc_fast_smoothing_s: float = 0.03             # ... where the frame stands 15-30 dB above the noise (at most gcc_smoothing_s)
    noise_follows_drift: bool = True               # the noise cross-power spectra follow the clocks' measured drift
    track_tdoa_std_s: float = 1e-4                 # each track's TDOA noise
    switch_ratio: float = 1.5                      # activity ratio that moves the beam to another talker
    activity_time_constant_s: float = 0.4          # talker activity average over speech frames
    forget_after_s: float = 30.0                   # a track without a hit for this long is forgotten
    # look-ahead (adds this much latency): frame t is steered by the tracker's decision at t + look-ahead (the
    # steered track, its TOA then taken back to t along its rate); 0 = causal, live's and the network's default
    # (stream.live.LIVE_DEFAULTS)
    tracker_lookahead_s: float = 0.128
    # the tracker measures (GCC peaks, track update) once every k hops, the largest k whose span is at most this
    # (at least every hop): a 128-sample hop at 16 kHz keeps its latency and measures every 16 ms as the default
    # 256-sample hop does; the GCC's averages take every hop, the hops between are steered by the last decision
    # (0: measure every hop)
    track_interval_s: float = 0.016
    # coarse alignment
    align_window_s: float = 8.0
    max_offset_s: float = 4.0
    align_recheck_s: float = 10.0
    device_deadline_s: float | None = 2.0          # a device this far behind the others is left out until it catches up
    # devices that are synchronous mic arrays (stream.channels): an arrays file ([[array]] name, mics_m)
    arrays: str | None = None
    # replay
    speed: float | None = None
    block_s: float = 0.05
    # outputs
    plots: bool = True
    progress: bool = True
    # calibration from a moving chirp beacon (stream/calibration.py); off without calibration_odometry
    calibration_odometry: str | None = None
    chirp_interval_s: float | None = None        # when the odometry file has no interval_s column
    recalibrate_every: int = 8                   # re-solve every this many new chirps
    chirp_duration_s: float = 0.1
    chirp_f0_hz: float = 500.0
    chirp_f1_hz: float = 6000.0
    chirp_threshold: float = 10.0                # matched-filter envelope over its robust noise level
    calibration_method: CalibrationMethod = "hybrid"
    calibration_apply: CalibrationApply = "drift"
    calibration_sigma_tdoa_s: float = 5e-5
    calibration_sigma_odo_m: float = 0.01
    calibration_max_drift_std_ppm: float = 5.0   # a device's drift is corrected once its CRLB std is this small
    calibration_max_events: int = 200
    calibration_executor: CalibrationExecutor = "thread"
    # a replay as fast as possible adopts each solve this long (stream time) after submitting it, waiting for
    # the worker if needed: the same result on any machine. Paced (speed) and live streams never wait.
    calibration_replay_latency_s: float = 1.0

    def resolved(self, reference_rate_hz: float) -> "EngineConfig":
        """Fill in the automatic values for a given reference device rate and validate everything."""
        rate = float(self.working_rate_hz or reference_rate_hz)
        frame = self.frame_samples or int(2 ** round(math.log2(PAPER_FRAME_S * rate)))
        hop = self.hop_samples or frame // 4
        # a PHAT peak must stand about 5 standard deviations above the correlation of unrelated
        # noise, whose spread is 1/sqrt(frame_samples)
        min_conf = self.min_confidence if self.min_confidence is not None else 5.0 / math.sqrt(frame)
        cfg = dataclasses.replace(self, working_rate_hz=rate, frame_samples=int(frame), hop_samples=int(hop),
                                  min_confidence=float(min_conf))
        cfg.validate()
        return cfg

    @property
    def track_stride(self) -> int:
        """Hops per tracker measurement (``track_interval_s``; a resolved config)."""
        hop_s = self.hop_samples / self.working_rate_hz
        return max(1, int(math.floor(self.track_interval_s / hop_s + 1e-9)))

    def validate(self) -> None:
        """Raise ConfigError with the option, its value and the condition it breaks."""
        if self.estimator not in ("tracks", "subset", "pinv", "kalman", "smoother"):
            raise ConfigError(f"estimator={self.estimator!r} must be one of tracks, subset, pinv, kalman, smoother")
        if not (math.isfinite(self.gcc_phat_beta) and 0 < self.gcc_phat_beta <= 1):
            raise ConfigError(f"gcc_phat_beta={self.gcc_phat_beta} must be in (0, 1] (1: plain PHAT)")
        if not isinstance(self.noise_follows_drift, bool):
            raise ConfigError(f"noise_follows_drift={self.noise_follows_drift!r} must be true or false")
        if not isinstance(self.gcc_phat_beta_near_noise, bool):
            raise ConfigError(f"gcc_phat_beta_near_noise={self.gcc_phat_beta_near_noise!r} must be true or false")
        if self.gcc_weighting not in ("subtract", "subtract-snr", "phat"):
            raise ConfigError(f"gcc_weighting={self.gcc_weighting!r} must be 'subtract', 'subtract-snr' or 'phat'")
        if self.gcc_phat_beta != 1 and self.gcc_weighting == "subtract-snr":
            raise ConfigError(f"gcc_phat_beta={self.gcc_phat_beta} has no effect with gcc_weighting='subtract-snr' "
                              "(its per-bin SNR weight takes the place of PHAT-beta): use 'subtract' or 'phat', or "
                              "gcc_phat_beta=1")
        if self.gcc_phat_beta_near_noise and self.gcc_weighting != "subtract":
            raise ConfigError(f"gcc_phat_beta_near_noise needs gcc_weighting='subtract', not {self.gcc_weighting!r}: "
                              "it measures each pair against the noise cross power that 'subtract' removes")
        words = str(self.target).split()
        if not words or words[0] not in ("active-talker", "nearest") or (words[0] == "nearest") != (len(words) == 2) \
                or (words[0] == "active-talker" and len(words) != 1):
            raise ConfigError(f"target={self.target!r} must be 'active-talker' or 'nearest DEVICE' "
                              "(a device name or index)")
        if int(self.n_peaks) != self.n_peaks or not 1 <= self.n_peaks <= 8:
            raise ConfigError(f"n_peaks={self.n_peaks} must be an integer in 1..8")
        if not (math.isfinite(self.gcc_smoothing_s) and 0 <= self.gcc_smoothing_s <= 2):
            raise ConfigError(f"gcc_smoothing_s={self.gcc_smoothing_s} must be in 0..2 seconds")
        if not (math.isfinite(self.gcc_fast_smoothing_s) and 0 <= self.gcc_fast_smoothing_s <= 2):
            raise ConfigError(f"gcc_fast_smoothing_s={self.gcc_fast_smoothing_s} must be in 0..2 seconds")
        if not (math.isfinite(self.noise_delay_s) and 0 <= self.noise_delay_s <= 2):
            raise ConfigError(f"noise_delay_s={self.noise_delay_s} must be in 0..2 seconds")
        for name in ("noise_time_constant_s", "track_tdoa_std_s", "activity_time_constant_s", "forget_after_s"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ConfigError(f"{name}={getattr(self, name)} must be > 0")
        if not (math.isfinite(self.switch_ratio) and self.switch_ratio >= 1):
            raise ConfigError(f"switch_ratio={self.switch_ratio} must be >= 1")
        if self.weighting not in ("equal", "adaptive", "level"):
            raise ConfigError(f"weighting={self.weighting!r} must be 'equal', 'adaptive' or 'level'")
        if not (math.isfinite(self.level_height_exponent) and 0 <= self.level_height_exponent <= 4):
            raise ConfigError(f"level_height_exponent={self.level_height_exponent} must be in 0..4")
        if not (math.isfinite(self.level_snr_exponent) and 0 <= self.level_snr_exponent <= 2):
            raise ConfigError(f"level_snr_exponent={self.level_snr_exponent} must be in 0..2 (1: maximal-ratio "
                              "combining, 0: the noise floors alone)")
        if self.working_rate_hz is not None and not 1000 <= self.working_rate_hz <= 384000:
            raise ConfigError(f"working_rate_hz={self.working_rate_hz} must be in 1000..384000 Hz")
        if self.frame_samples is not None and not 32 <= self.frame_samples <= 65536:
            raise ConfigError(f"frame_samples={self.frame_samples} must be in 32..65536")
        if self.hop_samples is not None and self.frame_samples is not None and not (
                1 <= self.hop_samples <= self.frame_samples // 2 and self.frame_samples % self.hop_samples == 0):
            raise ConfigError(f"hop_samples={self.hop_samples} must divide frame_samples={self.frame_samples} "
                              "and be at most half of it")
        for name in ("max_tdoa_s", "accel_std_s_per_s2", "tdoa_std_s", "align_window_s", "block_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}={getattr(self, name)} must be > 0")
        if self.device_deadline_s is not None and not self.device_deadline_s > 0:
            raise ConfigError(f"device_deadline_s={self.device_deadline_s} must be > 0 seconds (or absent)")
        if not 0 < self.gate_probability < 1:
            raise ConfigError(f"gate_probability={self.gate_probability} must be in (0, 1)")
        if self.speed is not None and not self.speed > 0:
            raise ConfigError(f"speed={self.speed} must be > 0 (or absent for as fast as possible)")
        if not (math.isfinite(self.tracker_lookahead_s) and 0 <= self.tracker_lookahead_s <= 2.0):
            raise ConfigError(f"tracker_lookahead_s={self.tracker_lookahead_s} must be in 0..2 seconds")
        if not (math.isfinite(self.track_interval_s) and 0 <= self.track_interval_s <= 0.1):
            raise ConfigError(f"track_interval_s={self.track_interval_s} must be in 0..0.1 seconds")
        if self.smoother_lag_frames < 1:
            raise ConfigError(f"smoother_lag_frames={self.smoother_lag_frames} must be >= 1")
        self._validate_calibration()
        if self.frame_samples and self.working_rate_hz and self.max_tdoa_s * self.working_rate_hz >= self.frame_samples / 2:
            raise ConfigError(f"max_tdoa_s={self.max_tdoa_s} must be shorter than half a frame "
                              f"({self.frame_samples / 2 / self.working_rate_hz:.4f} s)")

    def _validate_calibration(self) -> None:
        if self.calibration_method not in ("hybrid", "baseline"):
            raise ConfigError(f"calibration_method={self.calibration_method!r} must be 'hybrid' or 'baseline'")
        if self.calibration_apply not in ("drift", "offsets", "none"):
            raise ConfigError(f"calibration_apply={self.calibration_apply!r} must be 'drift', 'offsets' or 'none'")
        if self.calibration_executor not in ("thread", "process"):
            raise ConfigError(f"calibration_executor={self.calibration_executor!r} must be 'thread' or 'process'")
        if int(self.recalibrate_every) != self.recalibrate_every or self.recalibrate_every < 3:
            raise ConfigError(f"recalibrate_every={self.recalibrate_every} must be an integer >= 3 (chirps)")
        if int(self.calibration_max_events) != self.calibration_max_events or self.calibration_max_events < 3:
            raise ConfigError(f"calibration_max_events={self.calibration_max_events} must be an integer >= 3")
        for name in ("chirp_duration_s", "chirp_threshold", "calibration_sigma_tdoa_s", "calibration_sigma_odo_m",
                     "calibration_max_drift_std_ppm"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}={getattr(self, name)} must be > 0")
        if not (math.isfinite(self.calibration_replay_latency_s) and self.calibration_replay_latency_s >= 0):
            raise ConfigError(f"calibration_replay_latency_s={self.calibration_replay_latency_s} must be a "
                              "finite number of seconds >= 0")
        if self.chirp_interval_s is not None and not self.chirp_interval_s > 0:
            raise ConfigError(f"chirp_interval_s={self.chirp_interval_s} must be > 0 s")
        if not 0 <= self.chirp_f0_hz < self.chirp_f1_hz:
            raise ConfigError(f"chirp_f0_hz={self.chirp_f0_hz} and chirp_f1_hz={self.chirp_f1_hz} must satisfy "
                              "0 <= f0 < f1")
        if (self.calibration_odometry is not None and self.working_rate_hz
                and self.chirp_f1_hz >= self.working_rate_hz / 2):
            raise ConfigError(f"chirp_f1_hz={self.chirp_f1_hz} must be below half the working rate "
                              f"({self.working_rate_hz / 2:g} Hz)")

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def option_names() -> list[str]:
    return [f.name for f in fields(EngineConfig)]


def merge(config: EngineConfig, values: dict[str, Any], *, source: str) -> EngineConfig:
    """Return ``config`` with ``values`` applied; unknown keys raise a ConfigError naming ``source``."""
    known = {f.name: f for f in fields(EngineConfig)}
    clean = {}
    for key, value in values.items():
        key = key.replace("-", "_")
        if key not in known:
            raise ConfigError(f"{source}: unknown option {key!r}; known options: {', '.join(known)}")
        if value is not None:
            clean[key] = value
    try:
        return dataclasses.replace(config, **clean)
    except TypeError as err:  # pragma: no cover - dataclasses.replace only fails on unknown names
        raise ConfigError(f"{source}: {err}") from err


def load_toml(path: str | Path) -> dict[str, Any]:
    """Read a TOML config file; a missing or malformed file gives one clear sentence."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"Config file {path} does not exist.") from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"Config file {path} is not valid TOML: {err}.") from None
    return data.get("engine", data) if isinstance(data.get("engine"), dict) else data
