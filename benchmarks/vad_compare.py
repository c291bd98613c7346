"""Voice-activity detectors for the speech-presence stage (:mod:`stream.speech`): accuracy and CPU.

Candidates (each skipped with a one-line message when its package or model file is missing):

1. ``webrtc``: ``webrtcvad`` (pip ``webrtcvad-wheels``, MIT), aggressiveness 3, 10 ms frames -- the
   engine's current backend.
2. ``ten``: ``ten-vad`` (pip ``ten-vad``; Apache-2.0 *with additional conditions* from Agora, see its
   LICENSE), hop 160 samples (10 ms) at 16 kHz, its own flag at threshold 0.5.
3. ``silero``: Silero VAD v5/v6 ``silero_vad.onnx`` (MIT) run with ``onnxruntime`` (MIT) directly, no torch:
   512-sample windows at 16 kHz with the 64-sample context prepended, state ``(2, batch, 128)``,
   ``intra_op_num_threads = inter_op_num_threads = 1``, threshold 0.5. The model file is taken from
   ``--silero-onnx``, else the one the engine ships (``stream/models/silero_vad.onnx``, the two-rate
   export of silero-vad 6.2.3), else from an installed ``silero_vad`` package, else from a
   ``silero_vad-*.whl`` in ``--silero-wheel-dir`` (default /tmp/silero; get one with
   ``pip download silero-vad --no-deps -d /tmp/silero``), read straight out of the zip.
4. ``silero8k``: the same model at 8 kHz, as the engine runs it: the 16 kHz input resampled with soxr, 256-sample
   windows with 32 samples of context (32 ms). Its batched timing (``silero8k_batch8``) includes the streaming
   resampling of the 8 devices in 128-sample hops.

Ground truth per 10 ms frame: energy of ``truth/clean.flac`` (dry talker on device 0's clock, resampled to
16 kHz) above (max frame energy - 40 dB), then gaps shorter than 100 ms filled.

Conditions:

* each replay fixture, device 0 (``dev00``, same clock as clean.flac);
* each fixture, every device: device ``i``'s truth is device 0's truth mapped through ``truth/toa.csv``
  (``T_i = time_s + toa_s_i``: start offset, drift and propagation); frames that map outside device 0's
  recording are not scored; the per-device figures are reported as the median over devices;
* each fixture, combined decision: every device's decisions with the engine's 0.15 s hangover, mapped onto
  device 0's clock with toa.csv, then the engine's quorum rule (``p = min(1, n_speaking / ceil(0.3 n))``,
  speech when ``p >= 0.5``, the tracker's default ``speech_threshold``);
* meeting_table clean.flac (dry talker) alone, plus ``doing_the_dishes.wav`` (from ``--data``) at 10 dB and
  0 dB SNR, plus white noise at 10 dB SNR, and the dishes noise alone (no speech: every detection is a false
  alarm), and the white noise alone. SNR = speech power over the truth's active frames / noise power over the file.

Caveat: by that rule 92-97 % of the fixtures' frames are speech (the recordings' own floor, -43 dB in CMU
ARCTIC and about -36 dB in VCTK below the peak frame, counts as speech), so the fixtures' false-alarm rates
rest on 29-64 non-speech frames per file; the noise-only conditions are the real false-alarm test.

Metrics at each detector's natural threshold: frame accuracy, speech recall (true-positive rate) and
false-alarm rate on non-speech frames; both raw 10 ms decisions and with the engine's 0.15 s hangover
(``+hang``). Silero's 32 ms window is mapped onto the 10 ms grid by the window that contains the frame centre.

CPU (the machine is shared and noisy: medians and same-process ratios): the detector loop over a whole
16 kHz file (meeting_table dev00, int16 already prepared), 5 repetitions interleaved across detectors,
``time.perf_counter``; microseconds per 10 ms of audio per device, ratio to webrtc, microseconds per call,
and the per-hop cost at 8 devices for a 128-sample hop at 16 kHz (amortised, and the worst hop in which
every device completes one detector call), against the engine's whole budget of 0.4 ms per hop. Also the
first-use time (import, model/library load, first call).

Run: ``.venv/bin/python benchmarks/vad_compare.py [--fixtures DIR] [--data DIR]``. Prints a table and one
final JSON line.
"""
from __future__ import annotations

import argparse
import glob
import importlib.metadata as md
import json
import math
import os
import sys
import time
import tomllib
import zipfile
from pathlib import Path

import numpy as np
import soundfile as sf

FS = 16000
FRAME = 160                      # 10 ms at 16 kHz
HANGOVER_FRAMES = 15             # stream.speech: hangover_s = 0.15
QUORUM = 0.3
REPO = Path(__file__).resolve().parent.parent


# ---------------------------------------------------------------------------------------------- audio / truth
def load_16k(path: Path) -> np.ndarray:
    x, fs = sf.read(str(path), dtype="float32", always_2d=True)
    x = x[:, 0]
    if fs != FS:
        import soxr
        x = soxr.resample(x, fs, FS).astype(np.float32)
    return x


def to_int16(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(x * 32768.0), -32768, 32767).astype(np.int16)


def frame_energy(x: np.ndarray) -> np.ndarray:
    n = len(x) // FRAME
    f = x[:n * FRAME].astype(np.float64).reshape(n, FRAME)
    return np.mean(f * f, axis=1)


def fill_gaps(v: np.ndarray, max_gap: int) -> np.ndarray:
    v = v.copy()
    idx = np.flatnonzero(v)
    if len(idx) < 2:
        return v
    for a, b in zip(idx[:-1], idx[1:]):
        if 1 < b - a <= max_gap:          # gap of b - a - 1 frames < max_gap frames
            v[a + 1:b] = True
    return v


def truth_labels(clean: np.ndarray) -> np.ndarray:
    e = frame_energy(clean)
    thr = e.max() * 10 ** (-40 / 10)
    return fill_gaps(e > thr, 10)         # gaps shorter than 100 ms


def hangover(v: np.ndarray, frames: int = HANGOVER_FRAMES) -> np.ndarray:
    """stream.speech: a speech decision is held for `frames` further VAD frames."""
    out = np.zeros(len(v), bool)
    held = 0
    for i, s in enumerate(v):
        held = frames + 1 if s else max(held - 1, 0)
        out[i] = held > 0
    return out


def map_truth(truth0: np.ndarray, toa: np.ndarray | None, dev: int, n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Truth on device `dev`'s 10 ms grid and the mask of frames that map inside device 0's recording."""
    if dev == 0 or toa is None:
        n = min(n_frames, len(truth0))
        t = np.zeros(n_frames, bool)
        t[:n] = truth0[:n]
        m = np.zeros(n_frames, bool)
        m[:n] = True
        return t, m
    time_s, toa_d = toa[:, 0], toa[:, 1 + dev]
    centre = (np.arange(n_frames) + 0.5) * 0.01                 # device clock
    t0 = np.interp(centre, time_s + toa_d, time_s, left=-1.0, right=-1.0)   # device-0 clock
    k = np.floor(t0 / 0.01).astype(int)
    m = (t0 >= 0) & (k < len(truth0))
    t = np.zeros(n_frames, bool)
    t[m] = truth0[k[m]]
    return t, m


def to_dev0_clock(dec: np.ndarray, toa: np.ndarray, dev: int, n0: int) -> np.ndarray:
    """Decisions of device `dev` (its 10 ms grid) sampled on device 0's 10 ms grid (False outside its file)."""
    if dev == 0:
        out = np.zeros(n0, bool)
        n = min(n0, len(dec))
        out[:n] = dec[:n]
        return out
    time_s, toa_d = toa[:, 0], toa[:, 1 + dev]
    centre0 = (np.arange(n0) + 0.5) * 0.01
    td = centre0 + np.interp(centre0, time_s, toa_d)
    k = np.floor(td / 0.01).astype(int)
    ok = (k >= 0) & (k < len(dec))
    out = np.zeros(n0, bool)
    out[ok] = dec[k[ok]]
    return out


def scores(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> dict:
    n = min(len(pred), len(truth))
    p, t = pred[:n], truth[:n]
    if mask is not None:
        p, t = p[mask[:n]], t[mask[:n]]
    sp, ns = t.sum(), (~t).sum()
    return {"acc": float(np.mean(p == t)) if len(t) else math.nan,
            "recall": float((p & t).sum() / sp) if sp else math.nan,
            "fa": float((p & ~t).sum() / ns) if ns else math.nan,
            "n": int(len(t)), "n_speech": int(sp)}


# ---------------------------------------------------------------------------------------------- detectors
class WebRtc:
    name = "webrtc"
    call_samples = FRAME

    def __init__(self):
        import webrtcvad
        self._mod = webrtcvad
        self.reset()

    def reset(self):
        self.vad = self._mod.Vad(3)

    def run(self, pcm: np.ndarray) -> np.ndarray:
        """Decision per 10 ms frame of an int16 signal."""
        vad, n = self.vad, len(pcm) // FRAME
        b = pcm[:n * FRAME].tobytes()
        step = 2 * FRAME
        return np.fromiter((vad.is_speech(b[i * step:(i + 1) * step], FS) for i in range(n)), bool, n)


class Ten:
    name = "ten"
    call_samples = FRAME

    def __init__(self):
        import ctypes
        import ten_vad
        from ten_vad import TenVad
        lib = Path(ten_vad.__file__).parent / "lib" / "Linux" / "x64" / "libten_vad.so"
        if lib.exists():      # load it first: a failed load inside TenVad() also raises in its __del__
            try:
                ctypes.CDLL(str(lib))
            except OSError as e:
                raise OSError(f"{e} (ten-vad's library needs libc++: apt-get install libc++1)") from None
        self._cls = TenVad
        self.reset()

    def reset(self):
        self.vad = self._cls(hop_size=FRAME, threshold=0.5)

    def run(self, pcm: np.ndarray) -> np.ndarray:
        vad, n = self.vad, len(pcm) // FRAME
        out = np.zeros(n, bool)
        self.prob = np.zeros(n, np.float32)
        for i in range(n):
            p, f = vad.process(pcm[i * FRAME:(i + 1) * FRAME])
            out[i] = f
            self.prob[i] = p
        return out


def find_silero_onnx(explicit: str | None, wheel_dir: str) -> tuple[bytes | str, str]:
    """The model (path or bytes) and where it came from; raises FileNotFoundError."""
    if explicit:
        return explicit, explicit
    shipped = Path(__file__).resolve().parents[1] / "stream" / "models" / "silero_vad.onnx"
    if shipped.is_file():
        return str(shipped), str(shipped)
    try:
        import importlib.util
        spec = importlib.util.find_spec("silero_vad")
        if spec and spec.submodule_search_locations:
            p = Path(list(spec.submodule_search_locations)[0]) / "data" / "silero_vad.onnx"
            if p.exists():
                return str(p), str(p)
    except Exception:
        pass
    wheels = sorted(glob.glob(os.path.join(wheel_dir, "silero_vad-*.whl")))
    if wheels:
        with zipfile.ZipFile(wheels[-1]) as z:
            return z.read("silero_vad/data/silero_vad.onnx"), f"{wheels[-1]}!silero_vad/data/silero_vad.onnx"
    raise FileNotFoundError(f"no silero_vad.onnx (give --silero-onnx, or run: pip download silero-vad --no-deps "
                            f"-d {wheel_dir})")


class Silero:
    """Silero on 32 ms windows at ``rate`` (16 kHz: 512 samples, 64 of context; 8 kHz: 256 and 32, the input
    resampled from 16 kHz with soxr first, as the engine does)."""
    name = "silero"

    def __init__(self, model, batch: int = 1, rate: int = FS):
        import onnxruntime as ort
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1
        opts.inter_op_num_threads = 1
        self.session = ort.InferenceSession(model, sess_options=opts, providers=["CPUExecutionProvider"])
        self.batch = batch
        self.rate = rate
        self.window = 512 * rate // FS
        self.context_samples = 64 * rate // FS
        self.call_samples = 512                       # at 16 kHz: one window per call
        if rate != FS:
            self.name = f"silero{rate // 1000}k"
        self.sr = np.array(rate, dtype=np.int64)
        self.reset()

    def reset(self):
        self.state = np.zeros((2, self.batch, 128), np.float32)
        self.context = np.zeros((self.batch, self.context_samples), np.float32)

    def step(self, x: np.ndarray) -> np.ndarray:
        """One window per batch row (float32, full scale 1.0, at ``rate``); speech probabilities."""
        inp = np.concatenate([self.context, x], axis=1)
        out, self.state = self.session.run(None, {"input": inp, "state": self.state, "sr": self.sr})
        self.context = inp[:, -self.context_samples:]
        return out[:, 0]

    def run(self, pcm: np.ndarray) -> np.ndarray:
        x = pcm.astype(np.float32) / 32768.0
        if self.rate != FS:
            import soxr
            x = soxr.resample(x, FS, self.rate).astype(np.float32)
        w = self.window
        nw = len(x) // w
        prob = np.empty(nw, np.float32)
        for k in range(nw):
            prob[k] = self.step(x[None, k * w:(k + 1) * w])[0]
        self.prob_windows = prob
        n = len(pcm) // FRAME
        k = np.minimum(((np.arange(n) + 0.5) * FRAME // 512).astype(int), max(nw - 1, 0))
        self.prob = prob[k] if nw else np.zeros(n, np.float32)
        return self.prob >= 0.5


def make_detectors(args) -> tuple[list, dict, list[str]]:
    dets, load, skipped = [], {}, []
    for name in ("webrtc", "ten", "silero", "silero8k"):
        t0 = time.perf_counter()
        try:
            if name == "webrtc":
                d = WebRtc()
            elif name == "ten":
                d = Ten()
            else:
                model, src = find_silero_onnx(args.silero_onnx, args.silero_wheel_dir)
                d = Silero(model, rate=8000 if name == "silero8k" else FS)
                d.model_source = src
        except (ImportError, OSError, FileNotFoundError) as e:
            msg = f"skipping {name}: {type(e).__name__}: {e}"
            print(msg)
            skipped.append(msg)
            continue
        t1 = time.perf_counter()
        d.run(np.zeros(d.call_samples, np.int16))      # first call
        t2 = time.perf_counter()
        d.reset()
        load[name] = {"import_and_load_ms": (t1 - t0) * 1e3, "first_call_ms": (t2 - t1) * 1e3}
        dets.append(d)
    return dets, load, skipped


# ---------------------------------------------------------------------------------------------- evaluation
def read_toa(path: Path) -> np.ndarray | None:
    try:
        return np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except OSError:
        return None


def evaluate_fixture(fx: Path, dets) -> dict:
    cfg = tomllib.loads((fx / "fixture.toml").read_text())
    truth0 = truth_labels(load_16k(fx / cfg["truth"]["clean"]))
    toa = read_toa(fx / cfg["truth"].get("toa", "truth/toa.csv"))
    pcms = [to_int16(load_16k(fx / d["file"])) for d in cfg["device"]]
    res = {"speech_fraction": float(truth0.mean()), "n_devices": len(pcms)}
    for det in dets:
        per_dev, per_dev_h, held0 = [], [], []
        for i, pcm in enumerate(pcms):
            det.reset()
            dec = det.run(pcm)
            t, m = map_truth(truth0, toa, i, len(dec))
            h = hangover(dec)
            per_dev.append(scores(dec, t, m))
            per_dev_h.append(scores(h, t, m))
            if i == 0:
                res.setdefault(det.name, {})["dev0"] = per_dev[-1]
                res[det.name]["dev0_hang"] = per_dev_h[-1]
            if toa is not None:
                held0.append(to_dev0_clock(h, toa, i, len(truth0)))
        r = res[det.name]
        for key, lst in (("median_dev", per_dev), ("median_dev_hang", per_dev_h)):
            r[key] = {k: float(np.nanmedian([s[k] for s in lst])) for k in ("acc", "recall", "fa")}
            r[key].update({k: int(sum(s[k] for s in lst)) for k in ("n", "n_speech")})   # summed over devices
        if held0:
            cnt = np.sum(held0, axis=0)
            need = max(1, math.ceil(QUORUM * len(pcms)))
            comb = np.minimum(1.0, cnt / need) >= 0.5
            r["combined"] = scores(comb, truth0)
    return res


def noisy_conditions(fixtures: Path, data: Path, rng: np.random.Generator) -> tuple[dict, np.ndarray, str | None]:
    clean = load_16k(fixtures / "meeting_table" / "truth" / "clean.flac")
    truth = truth_labels(clean)
    n = len(truth) * FRAME
    clean = clean[:n].astype(np.float64)
    # the truth, dry talker at its stored level (peak normalised to -3 dBFS so that 0 dB SNR does not clip)
    clean *= 10 ** (-3 / 20) / max(np.abs(clean).max(), 1e-9)
    mask = np.repeat(truth, FRAME)
    p_speech = float(np.mean(clean[mask] ** 2))
    conds = {"dry": clean}
    note = None
    dishes_path = data / "audio" / "speechcommands-noise" / "doing_the_dishes.wav"
    try:
        dishes = load_16k(dishes_path).astype(np.float64)
        # from 0 s (the meeting_table fixture uses the excerpt from 32 s); long enough for 8 s
        dishes = np.resize(dishes, n)
        pd = float(np.mean(dishes ** 2))
        for snr in (10, 0):
            g = math.sqrt(p_speech / (pd * 10 ** (snr / 10)))
            conds[f"dishes{snr}dB"] = clean + g * dishes
        for snr in (10, 0):                             # the noise alone, no speech, at both levels
            conds[f"dishes_only_at{snr}dB"] = math.sqrt(p_speech / (pd * 10 ** (snr / 10))) * dishes
    except (OSError, RuntimeError) as e:
        note = f"dishes conditions skipped: {e}"
        print(note)
    w = rng.standard_normal(n)
    conds["white10dB"] = clean + w * math.sqrt(p_speech / 10)
    conds["white_only_at10dB"] = w * math.sqrt(p_speech / 10)
    peak = max(np.abs(x).max() for x in conds.values())
    scale = min(1.0, 0.99 / peak)
    return {k: to_int16(v * scale) for k, v in conds.items()}, truth, note


def evaluate_noisy(conds: dict, truth: np.ndarray, dets) -> dict:
    res = {}
    for name, pcm in conds.items():
        t = np.zeros_like(truth) if "_only" in name else truth
        for det in dets:
            det.reset()
            dec = det.run(pcm)
            res.setdefault(name, {})[det.name] = {"raw": scores(dec, t), "hang": scores(hangover(dec), t)}
    return res


# ---------------------------------------------------------------------------------------------- timing
def timing(dets, pcm: np.ndarray, reps: int) -> dict:
    n10 = len(pcm) // FRAME
    times = {d.name: [] for d in dets}
    for _ in range(reps):                          # interleaved: load changes hit all detectors alike
        for d in dets:
            d.reset()
            t0 = time.perf_counter()
            d.run(pcm)
            times[d.name].append(time.perf_counter() - t0)
    out = {}
    for d in dets:
        med = float(np.median(times[d.name]))
        us10 = med / n10 * 1e6
        n_calls = len(pcm) // d.call_samples
        us_call = med / n_calls * 1e6
        hop = 128
        out[d.name] = {
            "us_per_10ms": us10,
            "us_per_call": us_call,
            "call_samples": d.call_samples,
            "hop128_8dev_amortised_us": us10 * hop / FRAME * 8,
            "hop128_8dev_worst_us": us_call * 8 * math.ceil(hop / d.call_samples)
            if d.call_samples <= hop else us_call * 8,
            "reps_s": [float(x) for x in times[d.name]],
        }
    if "webrtc" in out:
        for k in out:
            out[k]["ratio_to_webrtc"] = out[k]["us_per_10ms"] / out["webrtc"]["us_per_10ms"]
    return out


def silero_batched_timing(model, pcm: np.ndarray, reps: int, batch: int = 8, rate: int = FS) -> dict:
    """Silero with the 8 devices as one batch of one session.run (one window per device per call), at
    ``rate`` (8 kHz: the resampling of the 8 devices from 16 kHz included, as the engine's streaming resampler
    does it, in hops of 128 samples)."""
    s = Silero(model, batch=batch, rate=rate)
    x16 = np.tile(pcm.astype(np.float32)[None, :] / 32768.0, (batch, 1))
    w = s.window
    ts = []
    for _ in range(reps):
        s.reset()
        t0 = time.perf_counter()
        if rate != FS:
            import soxr
            rs = soxr.ResampleStream(FS, rate, batch, dtype="float32")
            x = np.concatenate([rs.resample_chunk(np.ascontiguousarray(x16[:, i:i + 128].T))
                                for i in range(0, x16.shape[1] - 127, 128)]).T
        else:
            x = x16
        nw = x.shape[1] // w
        for k in range(nw):
            s.step(np.ascontiguousarray(x[:, k * w:(k + 1) * w]))
        ts.append(time.perf_counter() - t0)
    med = float(np.median(ts))
    n10 = x16.shape[1] // FRAME
    return {"us_per_10ms_per_device": med / n10 / batch * 1e6,
            "us_per_call_8dev": med / nw * 1e6,
            "hop128_8dev_amortised_us": med / n10 * 1e6 * 128 / FRAME,
            "hop128_8dev_worst_us": med / nw * 1e6}


# ---------------------------------------------------------------------------------------------- main
def pkg_info(dist: str) -> dict:
    try:
        m = md.metadata(dist)
    except md.PackageNotFoundError:
        return {"installed": False}
    lic = m.get("License-Expression") or m.get("License") or ""
    if not lic:
        lic = "; ".join(c.split("::")[-1].strip() for c in m.get_all("Classifier") or [] if c.startswith("License"))
    if not lic:                                   # e.g. ten-vad: only a LICENSE file in the dist-info
        for f in md.files(dist) or []:
            if f.name.upper().startswith("LICENSE"):
                try:
                    text = f.read_text()
                except OSError:
                    continue
                line = next((l.strip() for l in text.splitlines() if "licensed" in l.lower()), "")
                lic = f"LICENSE file: {line}" if line else "LICENSE file (see dist-info)"
                if "Apache License" in text and "additional conditions" in text.replace("\n", " "):
                    lic = "Apache-2.0 with additional conditions (LICENSE file in dist-info)"
                break
    return {"installed": True, "version": m["Version"], "license": lic or "(none in metadata)"}


def _no_nan(o):
    """NaN (e.g. recall of a condition without speech) as JSON null."""
    if isinstance(o, dict):
        return {k: _no_nan(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_no_nan(v) for v in o]
    if isinstance(o, (float, np.floating)):
        return None if math.isnan(o) else float(o)
    if isinstance(o, np.integer):
        return int(o)
    return o


def fmt(v: float) -> str:
    return "  -  " if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:5.3f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fixtures", default=str(REPO / "replay_fixtures"))
    ap.add_argument("--data", default=str(REPO.parent / "shared" / "data"))
    ap.add_argument("--silero-onnx", default=None, help="path to silero_vad.onnx")
    ap.add_argument("--silero-wheel-dir", default="/tmp/silero", help="folder with a downloaded silero_vad-*.whl")
    ap.add_argument("--reps", type=int, default=5)
    args = ap.parse_args()
    fixtures, data = Path(args.fixtures), Path(args.data)
    rng = np.random.default_rng(7)

    dets, load, skipped = make_detectors(args)
    if not dets:
        print("no detector available")
        return 1
    names = [d.name for d in dets]

    fx_res = {}
    for fx in ("meeting_table", "walking_talker", "async_8dev"):
        if (fixtures / fx / "fixture.toml").exists():
            fx_res[fx] = evaluate_fixture(fixtures / fx, dets)
        else:
            print(f"skipping fixture {fx}: not found in {fixtures}")
    conds, truth, note = noisy_conditions(fixtures, data, rng)
    noisy = evaluate_noisy(conds, truth, dets)

    pcm_t = to_int16(load_16k(fixtures / "meeting_table" / "dev00.flac"))
    tim = timing(dets, pcm_t, args.reps)
    silero = next((d for d in dets if d.name == "silero"), None)
    if silero is not None:
        model, _ = find_silero_onnx(args.silero_onnx, args.silero_wheel_dir)
        for key, rate in (("silero_batch8", FS), ("silero8k_batch8", 8000)):
            if rate != FS and not any(d.name == "silero8k" for d in dets):
                continue
            tim[key] = silero_batched_timing(model, pcm_t, args.reps, rate=rate)
            if "webrtc" in tim:
                tim[key]["ratio_to_webrtc"] = tim[key]["us_per_10ms_per_device"] / tim["webrtc"]["us_per_10ms"]

    # ---- table
    print("\nAccuracy (acc / recall / false-alarm rate), raw 10 ms decisions | with 0.15 s hangover")
    hdr = f"{'condition':44s}{'detector':8s}   acc recall    fa |   acc recall    fa  frames(speech)"
    print(hdr)
    print("-" * len(hdr))
    for fx, r in fx_res.items():
        for which, key, keyh in (("dev0", "dev0", "dev0_hang"), ("median over devices", "median_dev", "median_dev_hang")):
            for n in names:
                a, b = r[n][key], r[n][keyh]
                print(f"{fx + ' ' + which:44s}{n:8s} {fmt(a['acc'])}  {fmt(a['recall'])} {fmt(a['fa'])} | "
                      f"{fmt(b['acc'])}  {fmt(b['recall'])} {fmt(b['fa'])}  {a['n']}({a['n_speech']})")
        for n in names:
            if "combined" in r[n]:
                c = r[n]["combined"]
                print(f"{fx + ' combined (hang+quorum)':44s}{n:8s} {'':19s} | "
                      f"{fmt(c['acc'])}  {fmt(c['recall'])} {fmt(c['fa'])}  {c['n']}({c['n_speech']})")
    for cond, r in noisy.items():
        for n in names:
            a, b = r[n]["raw"], r[n]["hang"]
            print(f"{'meeting_table clean.flac ' + cond:44s}{n:8s} {fmt(a['acc'])}  {fmt(a['recall'])} {fmt(a['fa'])} | "
                  f"{fmt(b['acc'])}  {fmt(b['recall'])} {fmt(b['fa'])}  {a['n']}({a['n_speech']})")

    print(f"\nCPU (median of {args.reps}, meeting_table dev00, 8 s at 16 kHz); engine budget 400 us per 128-sample hop")
    print(f"{'detector':14s}{'us/10ms/dev':>12s}{'x webrtc':>10s}{'us/call':>10s}{'call':>6s}"
          f"{'hop128x8 avg':>14s}{'hop128x8 worst':>16s}{'load ms':>9s}{'1st call ms':>12s}")
    for n, t in tim.items():
        if n in ("silero_batch8", "silero8k_batch8"):
            label, call = (("silero batch8", "8x512") if n == "silero_batch8" else ("silero8k bat8", "8x256"))
            print(f"{label:14s}{t['us_per_10ms_per_device']:12.1f}{t.get('ratio_to_webrtc', math.nan):10.1f}"
                  f"{t['us_per_call_8dev']:10.1f}{call:>6s}{t['hop128_8dev_amortised_us']:14.1f}"
                  f"{t['hop128_8dev_worst_us']:16.1f}")
            continue
        print(f"{n:14s}{t['us_per_10ms']:12.1f}{t.get('ratio_to_webrtc', math.nan):10.1f}{t['us_per_call']:10.1f}"
              f"{t['call_samples']:6d}{t['hop128_8dev_amortised_us']:14.1f}{t['hop128_8dev_worst_us']:16.1f}"
              f"{load[n]['import_and_load_ms']:9.1f}{load[n]['first_call_ms']:12.2f}")

    pk = {p: pkg_info(p) for p in ("webrtcvad-wheels", "ten-vad", "onnxruntime", "silero-vad", "soxr")}
    if silero is not None:
        pk["silero-vad"]["model_source"] = silero.model_source
        if not pk["silero-vad"]["installed"]:
            try:
                whl = silero.model_source.split("!")[0]
                with zipfile.ZipFile(whl) as z:
                    meta = next(f for f in z.namelist() if f.endswith(".dist-info/METADATA"))
                    text = z.read(meta).decode()
                ver = next(l.split(":", 1)[1].strip() for l in text.splitlines() if l.startswith("Version:"))
                lic = [l.split("::")[-1].strip() for l in text.splitlines() if l.startswith("Classifier: License")]
                pk["silero-vad"].update({"wheel_version": ver, "license": "; ".join(lic)})
            except Exception:
                pass
    print("\nPackages:", ", ".join(f"{k} {v.get('version') or v.get('wheel_version', '-')} ({v.get('license', '-')})"
                                   for k, v in pk.items()))

    out = {"benchmark": "vad_compare", "detectors": names, "skipped": skipped, "fixtures": fx_res,
           "noisy_meeting_table": noisy, "cpu": tim, "first_use": load, "packages": pk,
           "notes": [n for n in [note] if n]}
    print(json.dumps(_no_nan(out), separators=(",", ":"), allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
