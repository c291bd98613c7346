#!/usr/bin/env python3
"""Build the replay fixtures: simulated ad-hoc-array recordings with exact timing truth.

Run ``python replay_fixtures/build_fixtures.py [--data DIR] [--out DIR] [--only NAME] [--verify]``.
The build is seeded and deterministic: two runs write the same samples (FLAC metadata may differ).

Time model (see ``replay_fixtures/README.md`` for the file format)
--------------------------------------------------------------------
- *True time* ``t`` is simulation time: sample ``n`` of the synchronous simulated microphone
  signals (``truth/sync.flac``) is the sound pressure at ``t = n / fs_sim``.
- The dry talker sample ``s[k]`` is emitted at ``tau = (k + D) / fs_sim`` with ``D = 40`` samples,
  pyroomacoustics' fixed RIR delay ``frac_delay_length // 2``; a wavefront emitted at ``tau`` from
  ``p(tau)`` reaches microphone ``m`` at ``t = tau + |p(tau) - m| / c``.
- Device ``i`` starts recording at true time ``start_offset_s[i]`` and samples at the actual
  rate ``sample_rate_hz[i] * (1 + drift_ppm[i] * 1e-6)``, so its sample ``k`` is taken at
  ``t = start_offset_s[i] + k / (sample_rate_hz[i] * (1 + drift))`` and its clock reads
  ``T_i(t) = k / sample_rate_hz[i] = (t - start_offset_s[i]) * (1 + drift)``.
- ``truth/toa.csv``: for device-0 clock time ``T0`` (10 ms grid),
  ``toa_s_i = T_i(t_i) - T0`` where ``t_i`` is the arrival at device ``i`` of the direct-path
  wavefront that reaches device 0 at ``T0``.

Each device file is a band-limited evaluation of the synchronous signal at the device's sample
instants (Kaiser-windowed sinc, 128 taps, linear phase: no timing error beyond float rounding).
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyroomacoustics as pra
import scipy.signal
import soundfile as sf

REPO_ROOT = Path(__file__).resolve().parents[1]
TOA_GRID_S = 0.01
HALF_TAPS = 64          # windowed-sinc half length (taps per output = 2 * HALF_TAPS)
KAISER_BETA = 8.6       # about -86 dB stop band
N_PHASES = 1024         # kernel table resolution; linear interpolation between phases
CUTOFF = 0.95           # pass band edge as a fraction of the lower Nyquist rate
INT16_SCALE = 32768.0
SYNC_GAIN_DB = -6.0     # sync.flac = device-scale acoustic signals (before gain_db) * 10**(-6/20)


# ----------------------------------------------------------------------------- scene description
@dataclass(frozen=True)
class DeviceSpec:
    name: str
    sample_rate_hz: int
    start_offset_s: float
    drift_ppm: float
    gain_db: float
    position_m: tuple
    sensor_noise_dbfs: float  # RMS of white sensor noise added after the gain, dB re full scale


@dataclass(frozen=True)
class StaticPath:
    """Talker at a fixed position."""

    position_m: tuple

    def __call__(self, tau_s):
        tau_s = np.atleast_1d(np.asarray(tau_s, dtype=float))
        return np.broadcast_to(np.asarray(self.position_m, float), (len(tau_s), 3)).copy()


@dataclass(frozen=True)
class ArcPath:
    """Talker walking on a circle at constant speed: angle = start + speed / radius * tau."""

    center_xy_m: tuple
    radius_m: float
    z_m: float
    speed_m_s: float
    start_angle_rad: float

    def __call__(self, tau_s):
        tau_s = np.atleast_1d(np.asarray(tau_s, dtype=float))
        a = self.start_angle_rad + self.speed_m_s / self.radius_m * tau_s
        return np.stack([self.center_xy_m[0] + self.radius_m * np.cos(a),
                         self.center_xy_m[1] + self.radius_m * np.sin(a),
                         np.full_like(a, self.z_m)], axis=1)


@dataclass(frozen=True)
class TalkerSpec:
    """A further talker (turn-taking scenes): its own path and sentences at given times."""

    path: object
    speech_files: tuple  # relative to the data dir
    starts_s: tuple      # emission time of each sentence's first sample, seconds


@dataclass(frozen=True)
class NoiseSpec:
    file: str            # relative to the data dir, or "generated:white|pink|babble" (see _noise_signal)
    start_s: float       # excerpt start in the file
    position_m: tuple
    target_median_snr_db: float  # talker vs (noise source + sensor noise), median over devices


@dataclass(frozen=True)
class Scene:
    name: str
    description: str
    sim_rate_hz: int
    duration_s: float
    room_dims_m: tuple
    sabine_rt60_s: float         # design RT60 passed to pra.inverse_sabine
    max_order_cap: int
    speech_files: tuple          # relative to the data dir, played back to back
    speech_start_s: float
    speech_gap_s: float
    path: object
    devices: tuple
    noise: NoiseSpec | None
    block_hop_s: float | None    # moving talker: RIR sets every hop, triangular crossfade of 2 hops
    seed: int
    speech_credit: str
    noise_credit: str
    talkers: tuple = ()          # further TalkerSpec (talker 0 is path / speech_files above)
    speech_starts_s: tuple = ()  # talker 0's sentence start times (default: from speech_start_s, gap)
    source_truth: bool = False   # write truth/activity.csv and truth/toa_<source>.csv
    # a measured RIR set (relative to the data dir) instead of the simulated room; out of repr, so that the cache
    # keys of the simulated scenes stay what they were
    measured_rirs: str = dataclasses.field(default="", repr=False)


CMU = "audio/cmu-arctic-16k/"
VCTK = "audio/vctk-48k/"
CMU_CREDIT = (
    "CMU ARCTIC (c) 2003 Carnegie Mellon University, Language Technologies Institute; free use "
    "without restriction (festvox BSD-style terms), modified here (concatenated, level-normalised, "
    "convolved with simulated room responses). Kominek & Black, 'CMU ARCTIC databases for speech "
    "synthesis', CMU-LTI-03-177, 2003. Copied from pyroomacoustics examples/input_samples (MIT, "
    "EPFL-LCAV).")
VCTK_CREDIT = (
    "CSTR VCTK Corpus v0.80 wav48 (c) Centre for Speech Technology Research, University of "
    "Edinburgh, ODC-By 1.0; modified here (concatenated, level-normalised, convolved with simulated "
    "room responses). Veaux, Yamagishi, MacDonald, 'CSTR VCTK Corpus: English Multi-speaker Corpus "
    "for CSTR Voice Cloning Toolkit'. Files taken from github.com/RichardSterry/msc-project "
    "docs/vctk/samples.")
DISHES_CREDIT = (
    "doing_the_dishes.wav from Google's Speech Commands dataset (_background_noise_), (c) Google, "
    "CC BY 4.0; excerpt played from a simulated point source. Warden, 'Speech Commands: A Dataset "
    "for Limited-Vocabulary Speech Recognition', arXiv:1804.03209, 2018. Copied from "
    "pyroomacoustics examples/input_samples.")


def _table(center_xy, offsets_xy, z):
    return tuple((round(center_xy[0] + dx, 3), round(center_xy[1] + dy, 3), z) for dx, dy in offsets_xy)


def scenes() -> dict[str, Scene]:
    """The shipped fixtures."""
    out = {}
    # a) meeting_table: 6 phones on a table, seated talker, dishes in the kitchen corner.
    table_xy, table_z = (2.40, 3.10), 0.75
    phones = _table(table_xy, [(-0.80, 0.30), (-0.35, -0.20), (0.10, 0.35), (0.45, -0.15),
                               (0.85, 0.30), (0.15, -0.05)], table_z)
    a_off = (0.12, 0.0, 0.27, 0.05, 0.21, 0.16)
    a_drift = (23.0, -41.0, 37.0, -28.0, 50.0, -33.0)
    a_gain = (0.0, -1.5, 1.0, -3.0, 0.5, -2.0)
    a_noise = (-60.0, -62.0, -58.0, -61.0, -59.0, -63.0)
    out["meeting_table"] = Scene(
        name="meeting_table",
        description=("Six phones lying on a meeting table (0.3-1.65 m apart) record a seated talker "
                     "0.8-1.4 m away while dishes clatter in a corner; 16 kHz, offsets 0-0.27 s, "
                     "drifts of 23-50 ppm either way."),
        sim_rate_hz=16000, duration_s=8.0, room_dims_m=(5.1, 6.6, 3.0), sabine_rt60_s=0.305,
        max_order_cap=60,
        speech_files=(CMU + "cmu_arctic_us_aew_a0001.wav", CMU + "cmu_arctic_us_aew_a0002.wav",
                      CMU + "cmu_arctic_us_aew_a0003.wav"),
        speech_start_s=0.05, speech_gap_s=0.0,
        path=StaticPath((table_xy[0] + 0.05, table_xy[1] - 0.75, table_z + 0.40)),
        devices=tuple(DeviceSpec(f"phone{i}", 16000, a_off[i], a_drift[i], a_gain[i], phones[i],
                                 a_noise[i]) for i in range(6)),
        noise=NoiseSpec("audio/speechcommands-noise/doing_the_dishes.wav", 32.0,
                        (4.55, 6.15, 0.95), 10.0),
        block_hop_s=None, seed=1001, speech_credit="", noise_credit="")
    # b) walking_talker: 4 devices on a small table, talker walking around it at 0.8 m/s.
    t_xy, t_z = (2.80, 2.40), 0.75
    devs_b = _table(t_xy, [(-0.35, -0.25), (0.30, -0.30), (0.40, 0.25), (-0.30, 0.30)], t_z)
    b_off = (0.30, 0.0, 0.45, 0.18)
    b_drift = (-20.0, 50.0, -50.0, 35.0)
    b_gain = (0.0, 1.0, -2.0, -1.0)
    out["walking_talker"] = Scene(
        name="walking_talker",
        description=("A talker walks at 0.8 m/s on a 1.3 m circle around four devices on a table "
                     "(chunked RIRs, 25 ms hop, triangular crossfade); 16 kHz, offsets 0-0.45 s, "
                     "drifts +-50 ppm."),
        sim_rate_hz=16000, duration_s=7.0, room_dims_m=(6.0, 5.0, 2.8), sabine_rt60_s=0.35,
        max_order_cap=30,
        speech_files=(CMU + "cmu_arctic_us_axb_a0004.wav", CMU + "cmu_arctic_us_axb_a0005.wav",
                      CMU + "cmu_arctic_us_axb_a0006.wav"),
        speech_start_s=0.0, speech_gap_s=0.0,
        path=ArcPath(t_xy, 1.3, 1.60, 0.8, -0.5 * math.pi),
        devices=tuple(DeviceSpec(f"dev{i}", 16000, b_off[i], b_drift[i], b_gain[i], devs_b[i], -60.0)
                      for i in range(4)),
        noise=None, block_hop_s=0.025, seed=2002, speech_credit="", noise_credit="")
    # c) async_8dev: 8 devices around a room, one at 44.1 kHz, one 15 dB quieter.
    pos_c = ((1.20, 1.00, 0.75), (2.90, 0.80, 1.10), (4.60, 1.30, 0.75), (5.80, 2.60, 1.20),
             (5.20, 4.30, 0.80), (3.40, 4.70, 0.75), (1.60, 4.20, 1.05), (0.90, 2.70, 0.90))
    c_rate = (48000, 48000, 48000, 44100, 48000, 48000, 48000, 48000)
    c_off = (0.35, 1.20, 0.0, 2.0, 0.80, 1.55, 0.10, 0.60)
    c_drift = (12.0, 35.0, -80.0, 100.0, -45.0, 60.0, -100.0, 15.0)
    c_gain = (0.0, -2.0, 1.0, -1.0, -3.0, -15.0, 0.5, -1.5)
    c_noise = (-72.0, -72.0, -70.0, -71.0, -72.0, -78.0, -70.0, -72.0)
    out["async_8dev"] = Scene(
        name="async_8dev",
        description=("Eight devices spread around a 7 x 5.5 m room record a standing talker with "
                     "start offsets up to 2 s and drifts up to +-100 ppm; device 3 records at "
                     "44.1 kHz, the others at 48 kHz, and device 5 is 15 dB quieter."),
        sim_rate_hz=48000, duration_s=5.0, room_dims_m=(7.0, 5.5, 3.0), sabine_rt60_s=0.26,
        max_order_cap=40,
        speech_files=(VCTK + "p255_367.wav", VCTK + "p376_193.wav", VCTK + "p314_272.wav"),
        speech_start_s=0.05, speech_gap_s=0.15,
        path=StaticPath((3.30, 2.60, 1.65)),
        devices=tuple(DeviceSpec(f"dev{i}", c_rate[i], c_off[i], c_drift[i], c_gain[i], pos_c[i],
                                 c_noise[i]) for i in range(8)),
        noise=None, block_hop_s=None, seed=3003, speech_credit="", noise_credit="")
    # d) kitchen_noise: dishes at the sink start 2 s before the talker, 5 dB SNR.
    k_xy, k_z = (2.30, 2.00), 0.78
    phones_d = _table(k_xy, [(-0.45, -0.25), (0.35, -0.30), (0.50, 0.20), (-0.20, 0.35)], k_z)
    out["kitchen_noise"] = Scene(
        name="kitchen_noise",
        description=("Four phones on a kitchen table and a laptop on the counter record a seated "
                     "talker while dishes clatter at the sink from 2 s before the talker starts "
                     "(5 dB SNR, median over devices); 16 kHz, laptop 44.1 kHz, offsets 0-0.6 s, "
                     "drifts up to +-80 ppm."),
        sim_rate_hz=16000, duration_s=10.0, room_dims_m=(4.4, 3.8, 2.6), sabine_rt60_s=0.45,
        max_order_cap=40, speech_files=(VCTK + "p376_193.wav",),
        speech_start_s=2.0, speech_gap_s=0.0,
        path=StaticPath((k_xy[0] - 0.10, k_xy[1] - 0.85, k_z + 0.40)),
        devices=tuple(DeviceSpec(f"phone{i}", 16000, (0.0, 0.35, 0.12, 0.60)[i],
                                 (30.0, -55.0, 80.0, -20.0)[i], (0.0, -2.0, 1.0, -1.0)[i],
                                 phones_d[i], -62.0) for i in range(4))
        + (DeviceSpec("laptop", 44100, 0.25, -70.0, -4.0, (0.60, 3.40, 0.95), -70.0),),
        noise=NoiseSpec("audio/speechcommands-noise/doing_the_dishes.wav", 10.0,
                        (4.00, 3.30, 0.95), 5.0),
        block_hop_s=None, seed=4004, speech_credit="", noise_credit="", source_truth=True)
    # e) two_talkers: two people at a meeting table take turns; a projector fan hums (pink).
    m_xy, m_z = (3.00, 2.50), 0.74
    phones_e = _table(m_xy, [(-0.70, -0.20), (-0.30, 0.25), (0.05, -0.30), (0.40, 0.20),
                             (0.75, -0.15), (0.00, 0.05)], m_z)
    out["two_talkers"] = Scene(
        name="two_talkers",
        description=("Two seated people at opposite ends of a meeting table take turns (A, B, A, "
                     "B; 0.4 s between turns) over six phones; a projector fan (pink noise, 25 dB "
                     "SNR) hums above the table; 16 kHz, offsets 0-0.4 s, drifts up to +-60 ppm."),
        sim_rate_hz=16000, duration_s=13.3, room_dims_m=(6.0, 5.0, 2.8), sabine_rt60_s=0.35,
        max_order_cap=40,
        speech_files=(CMU + "cmu_arctic_us_aew_a0001.wav", CMU + "cmu_arctic_us_aew_a0003.wav"),
        speech_start_s=0.3, speech_gap_s=0.0, speech_starts_s=(0.3, 7.6),
        path=StaticPath((m_xy[0] - 1.30, m_xy[1] + 0.10, m_z + 0.45)),
        talkers=(TalkerSpec(StaticPath((m_xy[0] + 1.25, m_xy[1] - 0.30, m_z + 0.50)),
                            (CMU + "cmu_arctic_us_axb_a0004.wav", CMU + "cmu_arctic_us_axb_a0005.wav"),
                            (4.45, 11.5)),),
        devices=tuple(DeviceSpec(f"phone{i}", 16000, (0.05, 0.0, 0.40, 0.22, 0.31, 0.13)[i],
                                 (15.0, -60.0, 42.0, -25.0, 60.0, -5.0)[i],
                                 (0.0, -1.0, 1.5, -2.5, 0.5, -1.5)[i], phones_e[i], -62.0)
                      for i in range(6)),
        noise=NoiseSpec("generated:pink", 0.0, (3.20, 2.10, 2.45), 25.0),
        block_hop_s=None, seed=5005, speech_credit="", noise_credit="", source_truth=True)
    credits = {"meeting_table": (CMU_CREDIT, DISHES_CREDIT),
               "walking_talker": (CMU_CREDIT, "none (white sensor noise generated by the builder)"),
               "async_8dev": (VCTK_CREDIT, "none (white sensor noise generated by the builder)"),
               "kitchen_noise": (VCTK_CREDIT, DISHES_CREDIT),
               "two_talkers": (CMU_CREDIT, "pink noise generated by the builder (seeded), played "
                               "from a point source; white sensor noise")}
    return {k: dataclasses.replace(v, speech_credit=credits[k][0], noise_credit=credits[k][1])
            for k, v in out.items()}


# ----------------------------------------------------------------------------- signal helpers
def _kernel_table(cutoff: float) -> np.ndarray:
    """Windowed-sinc taps for N_PHASES + 1 fractional phases, shape (N_PHASES + 1, 2 * HALF_TAPS).

    Row ``p`` holds ``g(p / N_PHASES - j)`` for ``j = -HALF_TAPS + 1 .. HALF_TAPS`` with
    ``g(u) = cutoff * sinc(cutoff * u) * kaiser(u / HALF_TAPS)``.
    """
    frac = np.arange(N_PHASES + 1)[:, None] / N_PHASES
    j = np.arange(-HALF_TAPS + 1, HALF_TAPS + 1)[None, :]
    u = frac - j
    r = np.clip(1.0 - (u / HALF_TAPS) ** 2, 0.0, None)
    w = np.i0(KAISER_BETA * np.sqrt(r)) / np.i0(KAISER_BETA)
    return cutoff * np.sinc(cutoff * u) * w


def band_limited_at(x: np.ndarray, pos: np.ndarray, *, cutoff: float) -> np.ndarray:
    """Evaluate the band-limited continuation of ``x`` at fractional sample positions ``pos``.

    ``y[k] = sum_n x[n] g(pos[k] - n)`` with the linear-phase kernel of :func:`_kernel_table`
    (zero outside ``x``). The kernel is tabulated at 1/1024-sample phases and interpolated
    linearly, so the timing is exact and the amplitude error is below about -90 dB.
    """
    table = _kernel_table(cutoff)
    pad = 2 * HALF_TAPS + 2
    xp = np.concatenate([np.zeros(pad), np.asarray(x, float), np.zeros(pad)])
    pos = np.asarray(pos, float)
    out = np.zeros(len(pos))
    valid = (pos > -HALF_TAPS) & (pos < len(x) + HALF_TAPS - 1)
    j = np.arange(-HALF_TAPS + 1, HALF_TAPS + 1)
    idx_valid = np.flatnonzero(valid)
    for c0 in range(0, len(idx_valid), 8192):
        sel = idx_valid[c0:c0 + 8192]
        p = pos[sel]
        base = np.floor(p)
        ph = (p - base) * N_PHASES
        ph0 = np.minimum(ph.astype(np.int64), N_PHASES - 1)
        a = (ph - ph0)[:, None]
        g = table[ph0] * (1.0 - a) + table[ph0 + 1] * a
        n = base.astype(np.int64)[:, None] + j[None, :] + pad
        out[sel] = np.einsum("ij,ij->i", xp[n], g)
    return out


def _load_mono(path: Path, rate_hz: int) -> np.ndarray:
    x, fs = sf.read(path, dtype="float64", always_2d=True)
    x = x[:, 0]
    if fs != rate_hz:
        x = scipy.signal.resample_poly(x, rate_hz, fs)
    return x - x.mean()


def _trim_silence(x: np.ndarray, rate_hz: int, *, threshold_db: float = -35.0,
                  margin_s: float = 0.1) -> np.ndarray:
    """Cut leading and trailing silence: keep from the first to the last 20 ms frame whose power
    is within ``threshold_db`` of the loudest frame, plus ``margin_s`` on both sides."""
    h = int(0.02 * rate_hz)
    p = np.array([np.mean(x[i:i + h] ** 2) for i in range(0, len(x) - h + 1, h)])
    on = np.flatnonzero(p >= p.max() * 10 ** (threshold_db / 10))
    m = int(margin_s * rate_hz)
    return x[max(on[0] * h - m, 0):min((on[-1] + 1) * h + m, len(x))]


def _quantise(x: np.ndarray) -> np.ndarray:
    """Float in [-1, 1) to int16 (clipping), the exact inverse of soundfile's int16 -> float."""
    return np.clip(np.round(np.asarray(x) * INT16_SCALE), -32768, 32767).astype(np.int16)


def _write_flac(path: Path, x: np.ndarray, rate_hz: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    sf.write(str(path), _quantise(x), int(rate_hz), format="FLAC", subtype="PCM_16")


def _write_csv(path: Path, header: list[str], rows: np.ndarray, fmt: str = "%.9f") -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, rows, delimiter=",", header=",".join(header), comments="", fmt=fmt)


# ----------------------------------------------------------------------------- geometry / truth
def _mic_array(scene: Scene) -> np.ndarray:
    return np.array([d.position_m for d in scene.devices], float)


def emission_time(scene: Scene, t_s: np.ndarray, mic_m: np.ndarray, c: float, path=None) -> np.ndarray:
    """Emission time ``tau`` of the direct-path wavefront reaching ``mic_m`` at true time ``t_s``.

    Solves ``t = tau + |p(tau) - mic| / c`` by fixed-point iteration (contraction ``v / c``);
    ``path`` is the source's path (default: talker 0's).
    """
    path = scene.path if path is None else path
    t_s = np.asarray(t_s, float)
    tau = t_s - np.linalg.norm(path(t_s) - mic_m, axis=1) / c
    for _ in range(6):
        tau = t_s - np.linalg.norm(path(tau) - mic_m, axis=1) / c
    return tau


def device_true_time(dev: DeviceSpec, clock_s):
    """True time of device-clock time ``T``: ``t = start_offset + T / (1 + drift)``."""
    return dev.start_offset_s + np.asarray(clock_s) / (1.0 + dev.drift_ppm * 1e-6)


def device_clock(dev: DeviceSpec, t_s):
    """Device-clock time of true time ``t``: ``T = (t - start_offset) * (1 + drift)``."""
    return (np.asarray(t_s) - dev.start_offset_s) * (1.0 + dev.drift_ppm * 1e-6)


def relative_toa(scene: Scene, ref_true_s: np.ndarray, c: float, *, synchronous: bool,
                 path=None) -> np.ndarray:
    """Relative TOA, shape (n, M), for wavefronts reaching device 0 at true times ``ref_true_s``.

    With ``synchronous`` the device clocks are ideal (no offset, no drift) and the result is
    ``t_i - t_0``; otherwise it is ``T_i(t_i) - T_0(t_0)``. ``path``: the source (default talker 0).
    """
    path = scene.path if path is None else path
    mics = _mic_array(scene)
    tau = emission_time(scene, ref_true_s, mics[0], c, path)
    p = path(tau)
    t_arr = tau[:, None] + np.linalg.norm(p[:, None, :] - mics[None, :, :], axis=2) / c
    if synchronous:
        return t_arr - t_arr[:, :1]
    clocks = np.stack([device_clock(d, t_arr[:, i]) for i, d in enumerate(scene.devices)], axis=1)
    return clocks - clocks[:, :1]


# ----------------------------------------------------------------------------- simulation
def _room(scene: Scene, *, anechoic: bool):
    e_abs, max_order = pra.inverse_sabine(scene.sabine_rt60_s, list(scene.room_dims_m))
    max_order = 0 if anechoic else min(int(max_order), scene.max_order_cap)
    return pra.ShoeBox(list(scene.room_dims_m), fs=scene.sim_rate_hz,
                       materials=pra.Material(float(e_abs)), max_order=max_order), e_abs, max_order


def _rirs(scene: Scene, source_m, *, anechoic: bool) -> list[np.ndarray]:
    room, _, _ = _room(scene, anechoic=anechoic)
    room.add_source(list(source_m))
    room.add_microphone_array(_mic_array(scene).T)
    room.compute_rir()
    return [np.asarray(room.rir[m][0], float) for m in range(len(scene.devices))]


MEASURED_VERSION = 2         # bump when _measured_rirs changes what it gives (benchmark caches rebuild)
# a measured response is cut at MEASURED_RIR_S, faded out over its last MEASURED_FADE_S: the polimi office's T60 is
# about 40 ms, and past that a response holds its measurement's noise floor (each millisecond 25-39 dB below the
# direct path's)
MEASURED_RIR_S = 0.1
MEASURED_FADE_S = 0.02
MEASURED_WAVELET = (8, 17)   # the direct path's samples kept as the reference's filter: 0.5 ms before, 1 ms after


def _measured_responses(scene: Scene, data: Path, source_m) -> list[tuple[np.ndarray, float]]:
    """Per device, the measured response from ``source_m`` at the simulation rate, cut and faded
    (``MEASURED_RIR_S``, ``MEASURED_FADE_S``), and the sample of its arrival (the peak of its envelope in the first
    10 ms, to a fraction of a sample). The layout and its checks: :func:`_measured_rirs`."""
    import scipy.io
    folder = data / scene.measured_rirs
    xy = scipy.io.loadmat(folder / "source_location.mat")["sourceLocation"]
    dist = np.hypot(xy[:, 0] - source_m[0], xy[:, 1] - source_m[1])
    k = int(np.argmin(dist)) + 1
    if dist[k - 1] > 0.01 or not (folder / f"rir_source_{k}.wav").is_file():
        raise ValueError(f"no measured response from {tuple(source_m)} in {folder}")
    h, rate = sf.read(folder / f"rir_source_{k}.wav", dtype="float64", always_2d=True)
    fs = scene.sim_rate_hz
    g = math.gcd(int(rate), fs)
    n = int(MEASURED_RIR_S * fs)
    fade = np.ones(n)
    n_fade = int(MEASURED_FADE_S * fs)
    fade[n - n_fade:] = 0.5 * (1 + np.cos(np.pi * np.arange(n_fade) / n_fade))
    out = []
    for dev in scene.devices:
        ch = int(round(dev.position_m[1] / 0.03))
        if abs(dev.position_m[0]) > 0.01 or abs(dev.position_m[1] - 0.03 * ch) > 0.01 or not 0 <= ch < h.shape[1]:
            raise ValueError(f"device {dev.name} at {dev.position_m} is not a measured microphone of {folder}")
        x = scipy.signal.resample_poly(h[:, ch], fs // g, int(rate) // g)[:n] * fade
        a = np.abs(scipy.signal.hilbert(x[:int(0.01 * fs)]))   # the arrival as a band-limited GCC sees it
        i = int(np.argmax(a[1:-1])) + 1
        den = a[i - 1] - 2 * a[i] + a[i + 1]
        out.append((x, i + (0.5 * (a[i - 1] - a[i + 1]) / den if den else 0.0)))
    return out


def _measured_rirs(scene: Scene, data: Path, source_m, *, wavelet: bool = False,
                   responses: list[tuple[np.ndarray, float]] | None = None) -> list[np.ndarray]:
    """Measured responses from ``source_m`` to the scene's devices, at the simulation rate, with the time model's
    fixed delay ``frac_delay_length // 2`` in front (as the simulated ones have it).

    The set (``scene.measured_rirs``) is the polimi eStick recording layout (``PROVENANCE.md`` there): files
    ``rir_source_<k>.wav`` (48 kHz, 32 channels), ``source_location.mat`` (the sources' x, y), microphone ``m``
    (0-based) at ``(0, 0.03 m)``, the sources and microphones in one plane. A source or a device must sit on
    one of the measured positions (within 1 cm), given with that plane's height as z. The microphone positions
    were inferred from the data (to 1-2 cm), so each response is moved by a fraction of a millisecond (the peak of
    its envelope in the first 10 ms at the simulation rate, to a fraction of a sample, put at the geometric
    arrival): the scene's timing truth, computed from the positions, then holds to a fraction of a sample.

    With ``wavelet``: a list of one array, the devices' direct paths averaged (each moved so that its arrival
    is sample ``MEASURED_WAVELET[0]``, ``sum(MEASURED_WAVELET)`` samples). A measured response holds the
    loudspeaker's and the microphones' own responses, which colour and shift the phase of every device alike;
    the scene's clean reference is the dry talker through this filter (``Simulation.refs``), so that SI-SDR
    scores what the devices add to the direct path (a simulated response's direct path is a delay).

    ``responses``: :func:`_measured_responses` of this source, when the caller has them already."""
    if responses is None:
        responses = _measured_responses(scene, data, source_m)
    fs = scene.sim_rate_hz
    c = float(pra.constants.get("c"))
    delay = pra.constants.get("frac_delay_length") // 2
    n = int(MEASURED_RIR_S * fs)
    n_fft = 2 * n
    f = np.fft.rfftfreq(n_fft)
    out = []
    for dev, (x, peak) in zip(scene.devices, responses):
        shift = math.dist(dev.position_m, source_m) / c * fs - peak + delay   # to the geometric arrival + delay
        if wavelet:
            shift = MEASURED_WAVELET[0] - peak
        x = np.fft.irfft(np.fft.rfft(x, n_fft) * np.exp(-2j * np.pi * f * shift), n_fft)[:n + delay + 1]
        out.append(x)
    if wavelet:
        return [np.mean([x[:sum(MEASURED_WAVELET)] for x in out], axis=0)]
    return out


def _convolve_static(sig: np.ndarray, rirs: list[np.ndarray], n_out: int) -> np.ndarray:
    out = np.zeros((len(rirs), n_out))
    for m, h in enumerate(rirs):
        y = scipy.signal.fftconvolve(sig, h)[:n_out]
        out[m, :len(y)] = y
    return out


def _convolve_moving(scene: Scene, sig: np.ndarray, n_out: int, *, anechoic: bool) -> np.ndarray:
    """Time-varying convolution: RIR set ``b`` at ``p((b * hop + D) / fs)``, triangular windows of
    two hops centred on ``b * hop`` (they sum to one), overlap-added."""
    fs = scene.sim_rate_hz
    hop = int(round(scene.block_hop_s * fs))
    delay = pra.constants.get("frac_delay_length") // 2
    n_mics = len(scene.devices)
    out = np.zeros((n_mics, n_out))
    win = 1.0 - np.abs(np.arange(-hop, hop)) / hop
    for b in range(0, len(sig) // hop + 2):
        k0 = b * hop - hop
        seg = np.zeros(2 * hop)
        lo, hi = max(k0, 0), min(k0 + 2 * hop, len(sig))
        if lo >= hi:
            continue
        seg[lo - k0:hi - k0] = sig[lo:hi]
        seg *= win
        if not np.any(seg):
            continue
        pos = scene.path((b * hop + delay) / fs)[0]
        for m, h in enumerate(_rirs(scene, pos, anechoic=anechoic)):
            y = scipy.signal.fftconvolve(seg, h)
            a, z = k0, min(k0 + len(y), n_out)
            if z > max(a, 0):
                out[m, max(a, 0):z] += y[max(a, 0) - a:z - a]
    return out


def _dry_speech(scene: Scene, data: Path, n: int, talker: int = 0) -> np.ndarray:
    """Dry signal of talker ``talker`` (0: the scene's own, k: ``scene.talkers[k - 1]``), length ``n``."""
    fs = scene.sim_rate_hz
    if talker == 0:
        files, starts = scene.speech_files, scene.speech_starts_s
    else:
        files, starts = scene.talkers[talker - 1].speech_files, scene.talkers[talker - 1].starts_s
    s = np.zeros(n)
    k = int(round(scene.speech_start_s * fs))
    for i, f in enumerate(files):
        x = _trim_silence(_load_mono(data / f, fs), fs)
        x = 0.1 * x / np.sqrt(np.mean(x ** 2))
        if starts:
            k = int(round(starts[i] * fs))
        m = min(len(x), n - k)
        if m <= 0:
            break
        s[k:k + m] += x[:m]
        k += len(x) + int(round(scene.speech_gap_s * fs))
    return 0.9 * s / np.abs(s).max()


SPEECH_FILES = tuple(CMU + f"cmu_arctic_us_{v}_a{i:04d}.wav" for v, i in
                     [("aew", 1), ("aew", 2), ("aew", 3), ("axb", 4), ("axb", 5), ("axb", 6)]) + \
    tuple(VCTK + f for f in ("p255_367.wav", "p301_102.wav", "p314_272.wav", "p376_193.wav"))
BABBLE_VOICES = 6


def _noise_signal(scene: Scene, data: Path, n: int) -> np.ndarray:
    """The noise source's dry signal, length ``n``, unit RMS.

    ``scene.noise.file`` is a recording (played from ``start_s``) or one of the generated kinds:
    ``generated:white`` (Gaussian), ``generated:pink`` (Gaussian shaped to 1/f power above 20 Hz),
    ``generated:babble`` (``BABBLE_VOICES`` voices talking at once, each a random-order loop of the
    shared speech recordings that no talker of the scene uses, started at a random point).
    """
    spec, fs = scene.noise, scene.sim_rate_hz
    if not spec.file.startswith("generated:"):
        x = _load_mono(data / spec.file, fs)
        k = int(round(spec.start_s * fs))
        x = x[k:k + n]
        return x / np.sqrt(np.mean(x ** 2))
    kind = spec.file.split(":", 1)[1]
    rng = np.random.default_rng([scene.seed, 77])
    if kind == "white":
        x = rng.standard_normal(n)
    elif kind == "pink":
        spec_w = np.fft.rfft(rng.standard_normal(n))
        f = np.fft.rfftfreq(n, 1 / fs)
        x = np.fft.irfft(spec_w / np.sqrt(np.maximum(f, 20.0)), n)
    elif kind == "babble":
        used = set(scene.speech_files) | {f for t in scene.talkers for f in t.speech_files}
        pool = [_trim_silence(_load_mono(data / f, fs), fs) for f in SPEECH_FILES if f not in used]
        x = np.zeros(n)
        for _ in range(BABBLE_VOICES):
            order = rng.permutation(len(pool))
            voice = np.concatenate([pool[i] / np.sqrt(np.mean(pool[i] ** 2)) for i in order])
            voice = np.roll(np.resize(voice, n + len(voice)), -int(rng.integers(len(voice))))[:n]
            x += voice
    else:
        raise ValueError(f"unknown generated noise kind {kind!r} (white, pink, babble)")
    return x / np.sqrt(np.mean(x ** 2))


TRUTH_VERSION = 3   # bump when the truth tables a build writes change (caches rebuild)


def speech_activity(dry: np.ndarray, fs: int, *, frame_s: float = 0.01, floor_db: float = -40.0,
                    above_background_db: float = 15.0, min_run_s: float = 0.05, fill_s: float = 0.2) -> np.ndarray:
    """Per-sample activity (bool) of a dry talker: 10 ms frames within ``floor_db`` of the loudest frame and
    at least ``above_background_db`` above the recording's own background (the 10th percentile of the frames
    that are not digital silence: a corpus file's breath and room hum before the first word is no speech),
    in runs of at least ``min_run_s`` (a syllable; the room hum crosses the threshold in lone 10-30 ms frames),
    gaps shorter than ``fill_s`` filled (pauses between words are not turn ends)."""
    h = int(round(frame_s * fs))
    n_f = len(dry) // h
    p = np.mean(dry[:n_f * h].reshape(n_f, h) ** 2, axis=1)
    sound = p[p > 1e-12 * max(p.max(), 1e-300)]
    background = np.percentile(sound, 10) if len(sound) else 0.0
    on = (p >= p.max() * 10 ** (floor_db / 10)) & (p >= background * 10 ** (above_background_db / 10))
    edges = np.flatnonzero(np.diff(np.r_[0, on.astype(np.int8), 0]))
    min_run = int(round(min_run_s / frame_s))
    for a, b in zip(edges[::2], edges[1::2]):
        if b - a < min_run:
            on[a:b] = False
    idx = np.flatnonzero(on)
    fill = int(round(fill_s / frame_s))
    for a, b in zip(idx[:-1], idx[1:]):
        if 1 < b - a <= fill:
            on[a:b] = True
    act = np.zeros(len(dry), bool)
    act[:n_f * h] = np.repeat(on, h)
    return act


@dataclass
class Simulation:
    talker: np.ndarray   # (M, n) synchronous talker component
    noise: np.ndarray    # (M, n) synchronous noise-source component (zeros without a noise source)
    dry: np.ndarray      # (n_dry,) dry talker s[k]
    e_absorption: float
    max_order: int
    n_rir_sets: int
    measured_rt60_s: float  # median over microphones (Schroeder, pra.experimental.measure_rt60)
    parts: list = dataclasses.field(default_factory=list)  # per talker (M, n) components (sum = talker)
    drys: list = dataclasses.field(default_factory=list)   # per talker dry signals
    refs: list = dataclasses.field(default_factory=list)   # per talker clean reference (default: the dry signal)


def simulate(scene: Scene, data: Path, *, anechoic: bool = False) -> Simulation:
    fs = scene.sim_rate_hz
    t_end = max(d.start_offset_s + scene.duration_s / (1 + d.drift_ppm * 1e-6) for d in scene.devices)
    n_sync = int(math.ceil(t_end * fs)) + 2 * HALF_TAPS + 16
    dry = _dry_speech(scene, data, n_sync)
    if scene.measured_rirs:
        if anechoic or scene.block_hop_s is not None:
            raise ValueError("a measured room has no anechoic version and no moving talker")
        e_abs, max_order = 0.0, 0
        loaded: dict[tuple, list] = {}   # each source's file is read and resampled once (response, rt60, reference)

        def measured(source_m):
            key = tuple(source_m)
            if key not in loaded:
                loaded[key] = _measured_responses(scene, data, source_m)
            return loaded[key]

        def rirs(scene, source_m, *, anechoic):
            return _measured_rirs(scene, data, source_m, responses=measured(source_m))
    else:
        _, e_abs, max_order = _room(scene, anechoic=anechoic)
        rirs = _rirs
    if scene.block_hop_s is None:
        talker = _convolve_static(dry, rirs(scene, scene.path(0.0)[0], anechoic=anechoic), n_sync)
        n_sets = 1
    else:
        talker = _convolve_moving(scene, dry, n_sync, anechoic=anechoic)
        n_sets = n_sync // int(round(scene.block_hop_s * fs)) + 2
    parts, drys = [talker], [dry]
    for j, spec in enumerate(scene.talkers, start=1):
        d = _dry_speech(scene, data, n_sync, talker=j)
        parts.append(_convolve_static(d, rirs(scene, spec.path(0.0)[0], anechoic=anechoic), n_sync))
        drys.append(d)
    if len(parts) > 1:
        talker = np.sum(parts, axis=0)
    noise = np.zeros_like(talker)
    if scene.noise is not None:
        noise = _convolve_static(_noise_signal(scene, data, n_sync),
                                 rirs(scene, scene.noise.position_m, anechoic=anechoic), n_sync)
    rt60 = float("nan")
    if not anechoic:
        rt60 = float(np.median([pra.experimental.measure_rt60(h, fs=fs)
                                for h in rirs(scene, scene.path(0.0)[0], anechoic=False)]))
    refs = list(drys)
    if scene.measured_rirs:   # the dry talker through the direct path's filter, its arrival kept in place
        k0 = MEASURED_WAVELET[0]
        for j, path in enumerate([scene.path] + [t.path for t in scene.talkers]):
            w = _measured_rirs(scene, data, path(0.0)[0], wavelet=True, responses=measured(path(0.0)[0]))[0]
            refs[j] = np.convolve(drys[j], w)[k0:k0 + len(drys[j])]
    return Simulation(talker, noise, dry, float(e_abs), int(max_order), n_sets, rt60, parts, drys, refs)


def _device_positions(scene: Scene, dev: DeviceSpec) -> np.ndarray:
    """Fractional simulation-sample positions of the device's samples."""
    n = int(round(scene.duration_s * dev.sample_rate_hz))
    return device_true_time(dev, np.arange(n) / dev.sample_rate_hz) * scene.sim_rate_hz


def render_device(scene: Scene, sync_m: np.ndarray, dev: DeviceSpec) -> np.ndarray:
    """Device recording before gain and noise: sync signal at the device's sample instants."""
    cutoff = CUTOFF * min(1.0, dev.sample_rate_hz / scene.sim_rate_hz)
    return band_limited_at(sync_m, _device_positions(scene, dev), cutoff=cutoff)


# ----------------------------------------------------------------------------- TOML
def _toml_value(v) -> str:
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(round(float(v), 6))
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v)} to TOML")


def _toml(doc: dict) -> str:
    lines = []
    tables = {k: v for k, v in doc.items() if isinstance(v, dict)}
    arrays = {k: v for k, v in doc.items() if isinstance(v, list) and v and isinstance(v[0], dict)}
    for k, v in doc.items():
        if k not in tables and k not in arrays:
            lines.append(f"{k} = {_toml_value(v)}")
    for k, t in tables.items():
        lines += ["", f"[{k}]"] + [f"{kk} = {_toml_value(vv)}" for kk, vv in t.items()]
    for k, rows in arrays.items():
        for t in rows:
            lines += ["", f"[[{k}]]"] + [f"{kk} = {_toml_value(vv)}" for kk, vv in t.items()]
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- build
def build(scene: Scene, data: Path, out_root: Path) -> dict:
    """Simulate one scene and write its folder. Returns a summary dict."""
    t_start = time.perf_counter()
    fs = scene.sim_rate_hz
    c = float(pra.constants.get("c"))
    delay = pra.constants.get("frac_delay_length") // 2
    rng = np.random.default_rng(scene.seed)
    sim = simulate(scene, data)
    n_mics = len(scene.devices)
    # Level: talker alone peaks at 0.3 at the loudest microphone.
    scale = 0.3 / np.abs(sim.talker).max()
    talker, noise = sim.talker * scale, sim.noise
    sensor_var = np.array([10 ** (d.sensor_noise_dbfs / 10) for d in scene.devices])
    gains = np.array([10 ** (d.gain_db / 20) for d in scene.devices])
    p_talk = np.mean(talker ** 2, axis=1)
    if scene.noise is not None:
        # Noise-source gain so that the median device SNR (talker vs noise source + sensor noise
        # referred to the acoustic level) is the target.
        p_noise1 = np.mean(noise ** 2, axis=1)
        target = 10 ** (scene.noise.target_median_snr_db / 10)
        lo, hi = 1e-6, 1e3
        for _ in range(80):
            mid = math.sqrt(lo * hi)
            snr = p_talk / (mid ** 2 * p_noise1 + sensor_var / gains ** 2)
            lo, hi = (mid, hi) if np.median(snr) > target else (lo, mid)
        noise = noise * lo
    sync = talker + noise
    snr_db = 10 * np.log10(p_talk / (np.mean(noise ** 2, axis=1) + sensor_var / gains ** 2))

    folder = out_root / scene.name
    (folder / "truth").mkdir(parents=True, exist_ok=True)
    for old in folder.glob("dev*.flac"):
        old.unlink()
    # Devices.
    dev_rows = []
    for i, dev in enumerate(scene.devices):
        x = render_device(scene, sync[i], dev) * gains[i]
        x = x + rng.standard_normal(len(x)) * np.sqrt(sensor_var[i])
        clipped = int(np.sum((x >= 1 - 1 / INT16_SCALE) | (x < -1)))
        _write_flac(folder / f"dev{i:02d}.flac", x, dev.sample_rate_hz)
        dev_rows.append({
            "name": dev.name, "file": f"dev{i:02d}.flac", "sample_rate_hz": dev.sample_rate_hz,
            "start_offset_s": dev.start_offset_s, "drift_ppm": dev.drift_ppm, "gain_db": dev.gain_db,
            "position_m": list(dev.position_m), "n_samples": len(x),
            "sensor_noise_dbfs": dev.sensor_noise_dbfs, "snr_db": round(float(snr_db[i]), 2),
            "clipped_samples": clipped})
    # Truth: synchronous signals and their TOA.
    n_sync = sync.shape[1]
    # Stored 6 dB down (SYNC_GAIN_DB) to keep the files small; 16 bits still leave > 70 dB SNR.
    _write_flac(folder / "truth" / "sync.flac", sync.T * 10 ** (SYNC_GAIN_DB / 20), fs)
    t_sync = np.arange(0.0, (n_sync - 1) / fs + 1e-12, TOA_GRID_S)
    mics = _mic_array(scene)
    paths = [scene.path] + [t.path for t in scene.talkers]
    acts = [speech_activity(d, fs) for d in sim.drys]

    def active(t_true):
        """Talker index per true arrival time at mic 0 and per-talker flags (held: the last talker
        who spoke stays the target through pauses; talker 0 before anyone)."""
        flags = np.zeros((len(t_true), len(paths)), bool)
        for j, path in enumerate(paths):
            k = np.round(emission_time(scene, t_true, mics[0], c, path) * fs - delay).astype(int)
            inside = (k >= 0) & (k < len(acts[j]))
            flags[inside, j] = acts[j][k[inside]]
        who = np.zeros(len(t_true), int)
        cur = 0
        for i, f in enumerate(flags):
            if not f[cur] and f.any():
                cur = int(np.argmax(f))
            who[i] = cur
        return who, flags

    def stitched(t_true, synchronous):
        toas = [relative_toa(scene, t_true, c, synchronous=synchronous, path=p) for p in paths]
        if len(paths) == 1:
            return toas[0], toas
        who, _ = active(t_true)
        return np.stack(toas)[who, np.arange(len(t_true))], toas

    toa_sync, _ = stitched(t_sync, True)
    hdr = ["time_s"] + [f"toa_s_{i}" for i in range(n_mics)]
    _write_csv(folder / "truth" / "sync_toa.csv", hdr, np.column_stack([t_sync, toa_sync]))

    def aligned_clean(t_true, rate_hz):
        # s_j at the emission time of the wavefront reaching mic 0 at t_true, summed over talkers
        out = 0.0
        for path, dry in zip(paths, sim.refs):
            tau = emission_time(scene, t_true, mics[0], c, path)
            out = out + band_limited_at(dry, tau * fs - delay, cutoff=CUTOFF * min(1.0, rate_hz / fs))
        return out

    # clean_sync[n] = s at the emission time of the wavefront reaching mic 0 at t = n / fs.
    _write_flac(folder / "truth" / "clean_sync.flac", aligned_clean(np.arange(n_sync) / fs, fs), fs)
    # Truth on device 0's clock.
    dev0 = scene.devices[0]
    n0 = int(round(scene.duration_s * dev0.sample_rate_hz))
    t_dev0 = np.arange(0.0, (n0 - 1) / dev0.sample_rate_hz + 1e-12, TOA_GRID_S)
    toa, toa_each = stitched(device_true_time(dev0, t_dev0), False)
    _write_csv(folder / "truth" / "toa.csv", hdr, np.column_stack([t_dev0, toa]))
    clean = aligned_clean(device_true_time(dev0, np.arange(n0) / dev0.sample_rate_hz), dev0.sample_rate_hz)
    _write_flac(folder / "truth" / "clean.flac", clean, dev0.sample_rate_hz)
    sources = {}
    if scene.source_truth:
        # Every source's own TOA and who is active, on device 0's clock.
        who, flags = active(device_true_time(dev0, t_dev0))
        names = [f"talker{j}" for j in range(len(paths))]
        for name, tj in zip(names, toa_each):
            _write_csv(folder / "truth" / f"toa_{name}.csv", hdr, np.column_stack([t_dev0, tj]))
        kinds = ["talker"] * len(paths)
        positions = [list(np.round(p(0.0)[0], 4)) for p in paths]
        if scene.noise is not None:
            static = StaticPath(tuple(scene.noise.position_m))
            tn = relative_toa(scene, device_true_time(dev0, t_dev0), c, synchronous=False, path=static)
            _write_csv(folder / "truth" / "toa_noise.csv", hdr, np.column_stack([t_dev0, tn]))
            names.append("noise")
            kinds.append("noise:" + scene.noise.file.split("/")[-1].replace("generated:", ""))
            positions.append(list(scene.noise.position_m))
        _write_csv(folder / "truth" / "activity.csv",
                   ["time_s", "active_talker"] + [f"speaking_{j}" for j in range(len(paths))],
                   np.column_stack([t_dev0, who, flags.astype(int)]), fmt="%.6g")
        sources = {"names": names, "kinds": kinds, "toa": [f"truth/toa_{n}.csv" for n in names],
                   "positions_m": positions, "activity": "truth/activity.csv"}
    # Emission grid from -50 ms: the truth at t = 0 refers to wavefronts emitted up to
    # (room diagonal / c) earlier.
    t_src = np.round(np.arange(-0.05, n_sync / fs, TOA_GRID_S), 9)
    _write_csv(folder / "truth" / "source.csv", ["time_s", "x_m", "y_m", "z_m"],
               np.column_stack([t_src, scene.path(t_src)]), fmt="%.6f")

    doc = {
        "name": scene.name,
        "description": scene.description,
        "working_rate_hz": fs,
        "duration_s": scene.duration_s,
        "seed": scene.seed,
        "room": {"dims_m": list(scene.room_dims_m), "rt60_s": round(sim.measured_rt60_s, 3),
                 "sabine_rt60_s": scene.sabine_rt60_s,
                 "e_absorption": round(sim.e_absorption, 6), "max_order": sim.max_order,
                 "speed_of_sound_m_s": c},
        "simulation": {"rate_hz": fs, "rir_delay_samples": int(delay),
                       "talker": "moving" if scene.block_hop_s else "static",
                       "block_hop_s": scene.block_hop_s or 0.0,
                       "rir_sets": sim.n_rir_sets,
                       "sync_gain_db": SYNC_GAIN_DB},
        "truth": {"clean": "truth/clean.flac", "toa": "truth/toa.csv", "sync": "truth/sync.flac",
                  "clean_sync": "truth/clean_sync.flac", "sync_toa": "truth/sync_toa.csv",
                  "source_path": "truth/source.csv"},
        **({"sources": sources} if sources else {}),
        "credits": {"speech": "; ".join(Path(f).name for f in scene.speech_files
                                        + tuple(f for t in scene.talkers for f in t.speech_files)) + ". "
                    + scene.speech_credit, "noise": (scene.noise.file.split("/")[-1] + f" from "
                    f"{scene.noise.start_s:.1f} s. " if scene.noise else "") + scene.noise_credit},
        "device": dev_rows,
    }
    (folder / "fixture.toml").write_text(_toml(doc))
    return {"name": scene.name, "seconds": time.perf_counter() - t_start,
            "snr_db": snr_db, "max_order": sim.max_order, "rir_sets": sim.n_rir_sets,
            "rt60_s": sim.measured_rt60_s,
            "clipped": [r["clipped_samples"] for r in dev_rows],
            "bytes": sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())}


# ----------------------------------------------------------------------------- verification
def _xcorr_lag(ref: np.ndarray, x: np.ndarray, *, fs_hz: float, max_lag: int,
               band_hz: tuple | None = None, upsample: int = 16) -> float:
    """Lag in samples at which ``x`` best matches ``ref`` (``x[n] ~ ref[n - lag]``).

    Plain cross-correlation if ``band_hz`` is None, else GCC-PHAT restricted to ``band_hz``; the
    correlation is upsampled ``upsample`` times (zero padding) before a parabolic peak fit.
    """
    n = 1 << int(np.ceil(np.log2(len(ref) + len(x))))
    r = np.fft.rfft(x, n) * np.conj(np.fft.rfft(ref, n))
    if band_hz is not None:
        f = np.fft.rfftfreq(n, 1.0 / fs_hz)
        r = np.where((f >= band_hz[0]) & (f <= band_hz[1]), r / (np.abs(r) + 1e-20), 0.0)
    cc = np.fft.irfft(r, n * upsample)
    m = max_lag * upsample
    cc = np.concatenate([cc[-m:], cc[:m + 1]])
    k = int(np.argmax(cc))
    if 0 < k < len(cc) - 1:
        a, b, d = cc[k - 1], cc[k], cc[k + 1]
        k = k + 0.5 * (a - d) / (a - 2 * b + d)
    return (k - m) / upsample


def warp_to_reference(x: np.ndarray, rate_hz: float, ref_rate_hz: float, n_out: int,
                      grid_s: np.ndarray, toa_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Device signal resampled onto the reference clock through a relative-TOA curve.

    ``z[n] = x(T + toa(T))`` with ``T = n / ref_rate_hz`` read on the reference clock and
    ``toa`` linearly interpolated from ``(grid_s, toa_s)``. If the TOA curve is exact, the direct
    path of ``z`` is aligned with the reference device sample by sample. Returns ``z`` and a mask
    of the samples that fall inside ``x``.
    """
    t_ref = np.arange(n_out) / ref_rate_hz
    pos = (t_ref + np.interp(t_ref, grid_s, toa_s)) * rate_hz
    cutoff = CUTOFF * min(1.0, ref_rate_hz / rate_hz)
    inside = (pos >= HALF_TAPS) & (pos <= len(x) - 1 - HALF_TAPS)
    return band_limited_at(x, pos, cutoff=cutoff), inside


def _window_lags(ref: np.ndarray, z: np.ndarray, inside: np.ndarray, fs_hz: float,
                 centres_s: np.ndarray, *, band_hz, talker: np.ndarray, win_s: float = 0.5
                 ) -> list[float]:
    """Residual lags on windows where ``z`` is defined and the talker is active (window power of
    the aligned dry ``talker`` at least -10 dB re its mean power)."""
    out = []
    h = int(round(win_s / 2 * fs_hz))
    p_mean = np.mean(talker ** 2)
    for t in centres_s:
        k = int(round(t * fs_hz))
        if k - h < 0 or k + h > len(ref) or not inside[k - h:k + h].all():
            continue
        if np.mean(talker[k - h:k + h] ** 2) < 0.1 * p_mean:
            continue
        w = np.hanning(2 * h)
        out.append(_xcorr_lag(ref[k - h:k + h] * w, z[k - h:k + h] * w, fs_hz=fs_hz,
                              max_lag=32, band_hz=band_hz))
    return out


def verify(scene: Scene, data: Path, out_root: Path) -> dict:
    """Compare the written truth with the signals. Every number is a residual lag in samples at
    the reference rate (0 means the truth matches the signal)."""
    folder = out_root / scene.name
    grid, toa = _read_csv(folder / "truth" / "toa.csv")
    devs = scene.devices
    fs0 = devs[0].sample_rate_hz
    real = [sf.read(folder / f"dev{i:02d}.flac", dtype="float64")[0] for i in range(len(devs))]
    clean, _ = sf.read(folder / "truth" / "clean.flac", dtype="float64")
    clean_sync, _ = sf.read(folder / "truth" / "clean_sync.flac", dtype="float64")
    sim = simulate(scene, data, anechoic=True)
    anech = [render_device(scene, sim.talker[i], d) for i, d in enumerate(devs)]
    centres = np.arange(0.5, scene.duration_s - 0.25, 0.5)
    band = (100.0, 4000.0)
    res = {"anechoic": [], "real": [], "sync": []}
    for i in range(1, len(devs)):
        rate = devs[i].sample_rate_hz
        z, inside = warp_to_reference(anech[i], rate, fs0, len(anech[0]), grid, toa[:, i])
        res["anechoic"] += _window_lags(anech[0], z, inside, fs0, centres, band_hz=None,
                                        talker=clean)
        z, inside = warp_to_reference(real[i], rate, fs0, len(real[0]), grid, toa[:, i])
        res["real"] += _window_lags(real[0], z, inside, fs0, centres, band_hz=band, talker=clean)
    sync, fs = sf.read(folder / "truth" / "sync.flac", dtype="float64")
    gs, toas = _read_csv(folder / "truth" / "sync_toa.csv")
    c_sync = np.arange(0.5, len(sync) / fs - 0.25, 0.5)
    for i in range(1, len(devs)):
        z, inside = warp_to_reference(sync[:, i], fs, fs, len(sync), gs, toas[:, i])
        res["sync"] += _window_lags(sync[:, 0], z, inside, fs, c_sync, band_hz=band,
                                    talker=clean_sync)
    everywhere = np.ones(len(clean), bool)
    out = {k: np.array(v) for k, v in res.items()}
    out["clean_real"] = _xcorr_lag(clean, real[0], fs_hz=fs0, max_lag=32, band_hz=band)
    out["clean_sync"] = _xcorr_lag(clean_sync, sync[:, 0], fs_hz=fs, max_lag=32, band_hz=band)
    out["clean_anechoic"] = np.array(_window_lags(anech[0], clean, everywhere, fs0, centres,
                                                  band_hz=None, talker=clean))
    return out


def _read_csv(path: Path):
    a = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return a[:, 0], a[:, 1:]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=REPO_ROOT / ".." / "shared" / "data",
                    help="shared data dir holding audio/ (default: ../shared/data from the repo root)")
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "replay_fixtures",
                    help="output dir (default: replay_fixtures/)")
    ap.add_argument("--only", choices=sorted(scenes()), help="build only this fixture")
    ap.add_argument("--verify", action="store_true",
                    help="after building, compare the truth with the signals (GCC) and print residuals")
    args = ap.parse_args(argv)
    data = args.data.resolve()
    if not (data / "audio").is_dir():
        ap.error(f"--data {data} has no audio/ folder; pass the shared data dir")
    t0 = time.perf_counter()
    todo = [scenes()[args.only]] if args.only else list(scenes().values())
    for scene in todo:
        s = build(scene, data, args.out)
        print(f"{s['name']}: {s['bytes'] / 1e6:.2f} MB, max_order {s['max_order']}, "
              f"RT60 {s['rt60_s']:.3f} s, "
              f"{s['rir_sets']} RIR set(s), SNR dB {np.round(s['snr_db'], 1).tolist()}, "
              f"clipped {s['clipped']}, {s['seconds']:.1f} s")
        if args.verify:
            v = verify(scene, data, args.out)

            def stat(r):
                return (f"n={len(r)}, median |res| {np.median(np.abs(r)):.3f}, "
                        f"{np.mean(np.abs(r) <= 2) * 100:.0f}% within 2, max |res| {np.abs(r).max():.3f}")

            print(f"  verify, residual lags in samples at the reference rate (0.5 s windows):\n"
                  f"    devices, anechoic noise-free, warped by toa.csv: {stat(v['anechoic'])}\n"
                  f"    devices, real files, GCC-PHAT 0.1-4 kHz:         {stat(v['real'])}\n"
                  f"    sync.flac warped by sync_toa.csv, GCC-PHAT:      {stat(v['sync'])}\n"
                  f"    clean vs dev00 (whole file, GCC-PHAT) {v['clean_real']:+.3f}; clean vs "
                  f"anechoic dev00 per window: {stat(v['clean_anechoic'])}\n"
                  f"    clean_sync vs sync channel 0 (GCC-PHAT) {v['clean_sync']:+.3f}")
    print(f"total run time {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
