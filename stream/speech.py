"""Speech presence per hop: a voice-activity decision per device, combined into one frame probability.

The multi-source tracker (:mod:`estimators.tracks`) updates and starts talker tracks only on speech frames,
and the noise-aware GCC-PHAT (:mod:`estimators.multipeak`) learns the noise cross-power spectra on the others.

Backend ``"silero"`` (default): Silero VAD v6 (``stream/models/silero_vad.onnx``, the two-rate export
``silero_vad.onnx`` of the ``silero-vad`` 6.2.3 wheel, MIT licence, Silero Team) run with ``onnxruntime`` (MIT)
without torch, on 32 ms windows at 8 kHz (every device's hop goes through one streaming ``soxr`` resampler),
every device in one batched call. The engine runs that model with its rate fixed at 8 kHz and each
convolution written as one matrix product over every device (``stream/models/silero_vad_8k.onnx``, built from
it by ``tools/silero_8k.py``: without the export's branches, 90.8 -> 83.4 us per hop for 8 devices at 16 kHz,
hop 128; as matrix products 84 -> 41 us per hop, the batched call 283 -> 104 us; the speech probability within
2.3e-6 of the two-rate model's over the fixtures' 29 devices and not one decision different). A device speaks
from a window with probability >= 0.5 until one below 0.35 (the model's recommended hysteresis). 8 kHz rather
than the model's 16 kHz mode: the batched call costs about 0.7 of the 16 kHz one with the resampling (285
against 407 us per window of 8 devices, with the model's convolutions as shipped), which brings the engine
with the tracker to the 5 % budget, and it is at least as accurate here: the kitchen recording alone at 10 dB is
speech in 0 % of 10 ms frames (2 % at 16 kHz), with a talker over it the recall is 0.985 (0.952); every shipped
fixture gained with the tracker (README, "Speech presence"). Chosen over WebRTC because WebRTC fires on
noise (the kitchen recording alone: 37 % of 10 ms frames at 10 dB, 99.5 % at 0 dB) while Silero does not,
with the best recall on the fixtures (``benchmarks/vad_compare.py``, README "Speech presence").

Backend ``"webrtc"``: the WebRTC voice-activity detector (``webrtcvad-wheels``, MIT licence; Google's
GMM detector from WebRTC) on 10 ms frames of every device, aggressiveness 3 (fewest false alarms). It takes
8, 16, 32 or 48 kHz directly; other working rates go through a streaming ``soxr`` resampler to 16 kHz.
Measured on this engine's scenes (README, "Speech presence"): 1.7 us per 10 ms frame and device.

Per device, a 10 ms decision is held (hangover) for ``hangover_s`` so that gaps between words do not drop
out; the device's probability is 1 while held, else 0. The frame's probability counts the devices that hear
speech against ``ceil(quorum * n_usable)`` (at least one): a talker heard by only some devices still counts,
a false alarm on one device of many does not make a speech frame.

Latency: a decision refers to the last complete VAD frame (Silero: 32 ms, WebRTC and energy: 10 ms), so it
lags the hop's end by at most that (plus the resampler's delay where the detector's rate is not the working
rate).

Backend ``"energy"`` (fallback when neither ``onnxruntime`` nor ``webrtcvad`` is installed): a device is speaking when its 10 ms frame energy
is 6 dB above its noise floor (the minimum of the smoothed energy over the last 1.5 s). It cannot tell speech
from a noise burst; the report states which backend ran.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path
from dataclasses import dataclass
from typing import Literal

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["SpeechFrame", "SpeechPresence", "make_speech_presence"]

Backend = Literal["silero", "webrtc", "energy"]
_WEBRTC_RATES = (8000, 16000, 32000, 48000)
_VAD_FRAME_S = 0.01
SILERO_MODEL = Path(__file__).resolve().parent / "models" / "silero_vad_8k.onnx"
SILERO_RATE_HZ = 8000       # the shipped two-rate export also runs at 16 kHz; 8 kHz: see the module doc
_SILERO_WINDOW = 256        # samples at 8 kHz (32 ms)
_SILERO_CONTEXT = 32        # samples of the previous window the model sees
SILERO_ON, SILERO_OFF = 0.5, 0.35   # hysteresis (tools/silero_8k.py checks its model's decisions with it)


@dataclass(frozen=True)
class SpeechFrame:
    """Speech presence of one hop.

    Attributes
    ----------
    probability : float
        The frame's combined speech presence in ``[0, 1]``.
    device_probability : ndarray, shape (n_devices,), float64
        Each device's speech presence in ``[0, 1]`` (0 for an unusable device).
    """

    probability: float
    device_probability: np.ndarray


class SpeechPresence:
    """Voice-activity decisions per device and their combination (module doc).

    Parameters
    ----------
    n_devices : int
    sample_rate_hz : float
        Working rate of the hops.
    hop_samples : int
        Samples per hop (any size: the detector buffers its own 10 ms frames).
    backend : {"silero", "webrtc", "energy"}
    aggressiveness : int
        WebRTC mode 0..3 (3: fewest false alarms).
    hangover_s : float
        How long a speech decision is held, seconds.
    quorum : float
        Fraction of the usable devices that must hear speech for a frame probability of 1.
    """

    def __init__(self, n_devices: int, *, sample_rate_hz: float, hop_samples: int, backend: Backend = "silero",
                 aggressiveness: int = 3, hangover_s: float = 0.15, quorum: float = 0.3) -> None:
        if int(n_devices) != n_devices or n_devices < 1:
            raise ValueError(f"{n_devices=} must be an integer >= 1")
        if not (np.isfinite(sample_rate_hz) and sample_rate_hz >= 8000):
            raise ValueError(f"{sample_rate_hz=} must be a rate in Hz >= 8000")
        if int(hop_samples) != hop_samples or hop_samples < 1:
            raise ValueError(f"{hop_samples=} must be an integer >= 1")
        if backend not in ("silero", "webrtc", "energy"):
            raise ValueError(f"{backend=} must be 'silero', 'webrtc' or 'energy'")
        if not 0 <= aggressiveness <= 3:
            raise ValueError(f"{aggressiveness=} must be in 0..3")
        if not 0 < quorum <= 1:
            raise ValueError(f"{quorum=} must be in (0, 1]")
        self.n_devices = int(n_devices)
        self.sample_rate_hz = float(sample_rate_hz)
        self.hop_samples = int(hop_samples)
        self.backend = backend
        self.aggressiveness = int(aggressiveness)
        self.hangover_s = float(hangover_s)
        self.quorum = float(quorum)
        if backend == "silero":
            self.vad_rate_hz = SILERO_RATE_HZ
            self.vad_frame_samples = _SILERO_WINDOW
        else:
            self.vad_rate_hz = int(sample_rate_hz) if (backend == "energy" or int(sample_rate_hz) in _WEBRTC_RATES
                                                       and sample_rate_hz == int(sample_rate_hz)) else 16000
            self.vad_frame_samples = int(round(_VAD_FRAME_S * self.vad_rate_hz))
        frame_s = self.vad_frame_samples / self.vad_rate_hz
        self._hold_frames = max(0, int(round(self.hangover_s / frame_s)))
        if backend == "webrtc":
            import webrtcvad   # optional: make_speech_presence falls back when it is missing
            self._vads = [webrtcvad.Vad(self.aggressiveness) for _ in range(self.n_devices)]
        elif backend == "silero":
            import onnxruntime as ort   # optional: make_speech_presence falls back when it is missing
            opts = ort.SessionOptions()
            opts.intra_op_num_threads = 1
            opts.inter_op_num_threads = 1
            opts.log_severity_level = 3
            self._session = ort.InferenceSession(str(SILERO_MODEL), sess_options=opts,
                                                 providers=["CPUExecutionProvider"])
            # the model reads and writes arrays of ours in place (bound once; the state alternates between two):
            # about 3 % less per call than passing and returning numpy arrays (9 of 315 us for 8 devices, timed
            # alternately in one process), the same output to the bit
            self._silero_input = np.zeros((self.n_devices, _SILERO_CONTEXT + _SILERO_WINDOW), np.float32)
            self._silero_states = np.zeros((2, 2, self.n_devices, 128), np.float32)
            self._silero_out = np.zeros((self.n_devices, 1), np.float32)
            self._binding = self._session.io_binding()
            value = ort.OrtValue.ortvalue_from_numpy
            # the OrtValues keep the bound arrays alive with the binding
            self._bound = (value(self._silero_input), value(self._silero_out))
            self._bound_states = (value(self._silero_states[0]), value(self._silero_states[1]))
            self._binding.bind_ortvalue_input("input", self._bound[0])
            self._binding.bind_ortvalue_output("output", self._bound[1])
        self.reset()

    def reset(self) -> None:
        """Forget buffers, held decisions and noise floors."""
        self._buffer = np.zeros((self.n_devices, 4 * self.vad_frame_samples + 8 * self.hop_samples), np.float32)
        self._fill = np.zeros(self.n_devices, np.int64)
        self._held = np.zeros(self.n_devices, np.int64)     # VAD frames the current decision is still held
        self._resampler = None
        if self.vad_rate_hz != int(self.sample_rate_hz) or self.sample_rate_hz != int(self.sample_rate_hz):
            import soxr
            self._resampler = soxr.ResampleStream(self.sample_rate_hz, self.vad_rate_hz, self.n_devices,
                                                  dtype="float32")
        n_floor = max(1, int(round(1.5 / _VAD_FRAME_S)))
        self._energy_hist = np.full((self.n_devices, n_floor), np.inf)
        self._energy_pos = 0
        self._smoothed = np.zeros(self.n_devices)
        if self.backend == "silero":
            self._silero_states[:] = 0.0
            self._silero_input[:] = 0.0
            self._silero_side = 0                         # the state the next window reads (the other: written)
        self._speaking = np.zeros(self.n_devices, bool)
        self._silero_fill = 0                             # samples buffered (every device alike)
        self._all_usable = np.ones(self.n_devices, bool)
        self._last: SpeechFrame | None = None            # the last hop's presence and its usable devices
        self._last_usable = b""
        self.n_frames = 0
        self.n_speech_frames = 0

    def process(self, samples: np.ndarray, valid: np.ndarray | None = None, *, finite: bool = False) -> SpeechFrame:
        """Speech presence of one hop.

        Parameters
        ----------
        samples : ndarray, shape (hop_samples, n_devices), float
            The hop at the working rate, full scale 1.0. Non-finite samples count as 0.
        valid : ndarray, shape (n_devices,), bool, optional
            Devices to use; an invalid device has probability 0.
        finite : bool
            The caller knows every sample is finite (the pipeline's blocks: the conditioner replaced the
            rest), so the check is skipped.
        """
        x = np.asarray(samples, dtype=np.float32)
        if x.ndim != 2 or x.shape[1] != self.n_devices:
            raise ValueError(f"samples.shape={x.shape} must be (n_samples, n_devices={self.n_devices})")
        if not finite and not np.isfinite(x.sum()):   # one sum, not a mask: a NaN or an inf makes it non-finite
            x = np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)
        usable = self._all_usable if valid is None else np.asarray(valid, bool)
        frame = self.vad_frame_samples
        if self._resampler is not None:   # every device at once: (n, n_devices) at the VAD's rate
            x = self._resampler.resample_chunk(np.ascontiguousarray(x))
        if self.backend == "silero":
            if not self._process_silero(x) and self._last is not None and usable.tobytes() == self._last_usable:
                self.n_frames += 1    # no new window and the same devices: the last hop's presence holds
                self.n_speech_frames += self._last.probability >= 0.5
                return self._last
            return self._combine(self._held > 0, usable)
        for d in range(self.n_devices):
            col = x[:, d]
            n0 = int(self._fill[d])
            buf = self._buffer[d]
            if n0 + len(col) > len(buf):   # never for the hop sizes the engine uses; keep the newest frames
                keep = (len(buf) - len(col)) // frame * frame
                buf[:keep] = buf[n0 - keep:n0]
                n0 = keep
            buf[n0:n0 + len(col)] = col
            n = n0 + len(col)
            start = 0
            while n - start >= frame:
                speech = self._decide(d, buf[start:start + frame])
                self._held[d] = self._hold_frames + 1 if speech else max(self._held[d] - 1, 0)
                start += frame
            if start:
                buf[:n - start] = buf[start:n]
            self._fill[d] = n - start
        return self._combine(self._held > 0, usable)

    def _combine(self, speaking: np.ndarray, usable: np.ndarray) -> SpeechFrame:
        device_p = (speaking & usable).astype(np.float64)
        need = max(1, math.ceil(self.quorum * int(usable.sum())))
        p = min(1.0, float(device_p.sum()) / need)
        self.n_frames += 1
        self.n_speech_frames += p >= 0.5
        self._last, self._last_usable = SpeechFrame(p, device_p), usable.tobytes()
        return self._last

    def _process_silero(self, x: np.ndarray) -> bool:
        """Buffer the hop (at the model's rate) of every device; run each complete 32 ms window of all devices
        in one batched model call, which updates which devices are speaking (hysteresis, then hangover).
        Returns whether a window ran."""
        frame = self.vad_frame_samples
        n_new = len(x)
        n0 = self._silero_fill
        if n0 + n_new > self._buffer.shape[1]:
            keep = (self._buffer.shape[1] - n_new) // frame * frame
            self._buffer[:, :keep] = self._buffer[:, n0 - keep:n0]
            n0 = keep
        self._buffer[:, n0:n0 + n_new] = x.T
        n = n0 + n_new
        start = 0
        inp = self._silero_input
        while n - start >= frame:
            inp[:, :_SILERO_CONTEXT] = inp[:, -_SILERO_CONTEXT:]
            inp[:, _SILERO_CONTEXT:] = self._buffer[:, start:start + frame]
            side = self._silero_side
            self._binding.bind_ortvalue_input("state", self._bound_states[side])
            self._binding.bind_ortvalue_output("stateN", self._bound_states[1 - side])
            self._session.run_with_iobinding(self._binding)
            self._silero_side = 1 - side
            p = self._silero_out[:, 0]
            self._speaking = np.where(self._speaking, p >= SILERO_OFF, p >= SILERO_ON)
            self._held = np.where(self._speaking, self._hold_frames + 1, np.maximum(self._held - 1, 0))
            start += frame
        if start:
            self._buffer[:, :n - start] = self._buffer[:, start:n]
        self._silero_fill = n - start
        return start > 0

    def _decide(self, d: int, frame: np.ndarray) -> bool:
        if self.backend == "webrtc":
            pcm = np.clip(frame * 32768.0, -32768, 32767).astype(np.int16)
            if not pcm.any():
                return False
            return bool(self._vads[d].is_speech(pcm.tobytes(), self.vad_rate_hz))
        energy = float(np.dot(frame, frame)) / len(frame) + 1e-12
        s = self._smoothed[d] = 0.7 * self._smoothed[d] + 0.3 * energy if self._smoothed[d] else energy
        self._energy_hist[d, self._energy_pos % self._energy_hist.shape[1]] = s
        if d == self.n_devices - 1:
            self._energy_pos += 1
        floor = float(np.min(self._energy_hist[d]))
        return energy > 4.0 * floor and energy > 1e-9


def make_speech_presence(n_devices: int, *, sample_rate_hz: float, hop_samples: int,
                         backend: str = "auto") -> SpeechPresence:
    """A :class:`SpeechPresence`; ``backend="auto"`` uses Silero, falls back to WebRTC when ``onnxruntime`` or
    the model file is missing, and to the energy detector when ``webrtcvad`` is missing too, each time with one
    warning sentence."""
    if backend not in ("auto", "silero", "webrtc", "energy"):
        raise ValueError(f"{backend=} must be 'auto', 'silero', 'webrtc' or 'energy'")
    if backend in ("auto", "silero"):
        try:
            return SpeechPresence(n_devices, sample_rate_hz=sample_rate_hz, hop_samples=hop_samples, backend="silero")
        except ImportError:
            log.warning("The voice-activity detector Silero needs onnxruntime, which is not installed (pip install "
                        "onnxruntime); speech presence falls back to WebRTC, which also fires on many noises.")
        except Exception as exc:   # a missing or unreadable model file
            log.warning(f"The Silero voice-activity model {SILERO_MODEL} could not be loaded ({exc}); speech "
                        "presence falls back to WebRTC, which also fires on many noises.")
    if backend in ("auto", "silero", "webrtc"):
        try:
            return SpeechPresence(n_devices, sample_rate_hz=sample_rate_hz, hop_samples=hop_samples, backend="webrtc")
        except ImportError:
            log.warning("The voice-activity detector webrtcvad is not installed (pip install webrtcvad-wheels); "
                        "speech presence falls back to a simple energy detector, which cannot tell speech from "
                        "noise bursts.")
    return SpeechPresence(n_devices, sample_rate_hz=sample_rate_hz, hop_samples=hop_samples, backend="energy")
