"""Network (Zenoh) fan-in: N device agents streaming to one aggregator on this machine, through the router.

Every device is its own process running the ``adhoc-array device`` command (``stream.cli.main(["device",
...])``), replaying a 48 kHz mono WAV synthesised into a temp dir (or speech from ``--data``) at real time
in 1024-sample frames (int16 on the wire, the default). Its replay waits until all N agents have opened their
sessions and declared everything, then all start at one instant (``LAUNCH``): the N files play in step, as
N phones hear one room (``device_start_spread_ms`` checks it: a device that started late would lag by as
much, and the engine, which aligns on the audio, would wait for it). Everything is on 127.0.0.1 with
``--no-scouting``, SHM off (NetOptions' default).

For each N in ``--devices`` (default 16 and 32):

1. ``peerN`` (the baseline): the N devices in peer mode connect straight to a transport-only receiver in
   this process (a Zenoh peer listening on port 0). No router.
2. ``routerN``: a router process (``adhoc-array router``), the N devices in client mode and, in this
   process, one after another on the same running devices:

   - ``routerN_raw``: a transport-only receiver (Zenoh client subscriber on ``adhoc/bench/dev/*/audio``
     whose callback only unpacks the 56-byte header);
   - ``routerN_netsource``: :class:`stream.net.NetSource` iterated without the pipeline (decode, jitter
     buffers, placement on each device's clock: the aggregator's own transport path);
   - ``routerN_aggregate_RATE``: the full ``adhoc-array aggregate`` command in its own process (the engine's
     defaults: 48 kHz, frame 4096 / hop 1024, kalman; ``--working-rate-hz 16000`` or ``--engine-args`` to
     change them), its report.json, and the end-to-end latency (below);

3. ``inprocessN_RATE``: the same pipeline in this process with no network (the same files through
   ``ReplaySource`` paced at real time in the same frames, the aggregator's engine options, its output
   grouped in 4 hops as NetPublisher does), timed with the same clicks: the baseline of the end-to-end
   latency and of the aggregator's CPU.

Per receiver window (after a warm-up): frames received against the rate (N x 46.875 frames/s), sequence
gaps (frames lost), duplicates and reordering per device; one-way latency = the receiver's
``time.time_ns()`` at arrival minus the frame's ``capture_time_ns`` (the sender's ``time.time_ns()`` when it
encoded the frame; same clock), p50 / p99 / p99.9 / max over all frames; CPU of every process over the window
(``/proc/PID/stat`` utime + stime for the router, the devices and the aggregator; ``time.process_time()``
for a receiver in this process, all its threads, Zenoh's included), in % of one core.

End-to-end latency (``routerN_aggregate_RATE``): every device file carries the same irregular click train
(a 5-sample pulse every 0.5-0.9 s, seeded). This process subscribes to the reference device's frames
(``dev/d00/audio``: the capture time of the frame holding each click) and to ``out/enhanced`` (float32 wire
frames whose ``capture_time_ns`` is the aggregator's publish time). Clicks are found in the enhanced stream
and matched to the input clicks by their audio-time pattern (one constant offset); latency of a click =
publish time of the enhanced frame that holds it - capture time of the d00 frame that holds it, i.e. from
the sample entering the device agent (as a whole frame, when the agent stamps it) to the enhanced sample
leaving the aggregator. Only clicks published >= 3 s after the first output count (the start-up alignment
releases its first seconds at once). Also given without the wait for the rest of the output frame (audio
time from the click to the end of its 4-hop frame). It is compared with the same measurement in-process
(``inprocessN_RATE``) and with the pipeline's algorithmic latency (report.json ``stream.output_latency_s``).

Prints human lines, then one JSON line. Default run ~3 min; ``--quick``: 16 devices, short windows (~1 min).
The machine is shared: compare ratios within a run (``ratios``), and rerun before trusting a tail.
"""
from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import pathlib  # noqa: E402
import re  # noqa: E402
import select  # noqa: E402
import shlex  # noqa: E402
import shutil  # noqa: E402
import signal  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
import types  # noqa: E402

import numpy as np  # noqa: E402

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from stream import wire  # noqa: E402
from stream.net import Keys, NetOptions, NetSource, quiet_zenoh, router_locators  # noqa: E402

ARRAY = "bench"
FS = 48000
FRAME = 1024
FRAME_RATE = FS / FRAME                      # 46.875 frames/s per device
N_FILES = 8                                  # distinct device signals (device i plays file i % N_FILES)
CLK = os.sysconf("SC_CLK_TCK")
PY = sys.executable

# A device agent: ``adhoc-array device ...`` (the CLI's own main), whose file replay waits for a common start:
# once everything before the first frame is done (imports, the Zenoh session, its declarations) it touches
# argv[1] and reads the start instant (time.time()) from stdin. The N files then play in step, as N phones
# hear one room (their content aligned in time; a device that started late would lag by as much, and the
# engine, which aligns on the audio, would wait for it).
LAUNCH = r"""
import pathlib, sys, time
import stream.cli, stream.replay
ready = pathlib.Path(sys.argv[1])
_iter = stream.replay.ReplaySource.__iter__
def _at_start(self):
    ready.touch()
    line = sys.stdin.readline()
    time.sleep(max(0.0, float(line or 0) - time.time()))
    yield from _iter(self)
stream.replay.ReplaySource.__iter__ = _at_start
sys.exit(stream.cli.main(sys.argv[2:]))
"""

CHILDREN: list[subprocess.Popen] = []


def log(msg: str) -> None:
    print(f"[net_fanin {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


# ------------------------------------------------------------------------------------------------ signals
def speech_like(n: int, rng: np.random.Generator) -> np.ndarray:
    """Band-limited noise in syllables (~4/s) with pauses: RMS 0.05 where active."""
    import scipy.signal as ss
    x = ss.sosfilt(ss.butter(4, [150, 4000], "bandpass", fs=FS, output="sos"), rng.standard_normal(n))
    env = np.zeros(n)
    t = 0.0
    while t < n / FS:
        if rng.random() < 0.15:                 # a pause
            t += rng.uniform(0.3, 0.8)
            continue
        d = rng.uniform(0.12, 0.3)
        i0, i1 = int(t * FS), min(n, int((t + d) * FS))
        env[i0:i1] = rng.uniform(0.4, 1.0) * np.sin(np.linspace(0, np.pi, i1 - i0)) ** 2
        t += d + rng.uniform(0.02, 0.1)
    y = x * env
    return 0.05 * y / np.sqrt(np.mean(y[env > 0.1] ** 2))


def speech_from(data: pathlib.Path, n: int, rng: np.random.Generator) -> np.ndarray:
    """Real speech: every mono WAV under ``data`` (resampled to 48 kHz), with pauses, looped to n samples."""
    import scipy.signal as ss
    import soundfile as sf
    parts = []
    for path in sorted(data.rglob("*.wav"))[:40]:
        x, fs = sf.read(str(path), dtype="float32", always_2d=True)
        x = x[:, 0].astype(np.float64)
        if fs != FS:
            g = np.gcd(int(fs), FS)
            x = ss.resample_poly(x, FS // g, int(fs) // g)
        if np.sqrt(np.mean(x ** 2)) > 1e-4:
            parts += [x / np.sqrt(np.mean(x ** 2)) * 0.05, np.zeros(int(rng.uniform(0.2, 0.6) * FS))]
    if not parts:
        raise SystemExit(f"--data {data}: no readable WAV with sound in it")
    y = np.concatenate(parts)
    return np.tile(y, -(-n // len(y)))[:n]


def make_files(tmp: pathlib.Path, seconds: float, data: str | None, seed: int = 7) -> tuple[list[str], np.ndarray]:
    """N_FILES device WAVs (48 kHz mono int16): one source, per-file delays up to +-1 ms, sensor noise 25 dB
    down, and the click train. Returns the paths and the click sample indices of file 0 (delay 0)."""
    import soundfile as sf
    rng = np.random.default_rng(seed)
    n = int(seconds * FS)
    src = speech_from(pathlib.Path(data), n, rng) if data else speech_like(n, rng)
    clicks = []
    t = 1.0
    while t < seconds - 1.0:
        clicks.append(int(t * FS))
        t += rng.uniform(0.5, 0.9)
    clicks = np.asarray(clicks)
    for c in clicks:
        src[c:c + 5] = 0.9
    paths = []
    for k in range(N_FILES):
        delay = 0 if k == 0 else int(rng.integers(-48, 49))
        x = np.roll(src, delay) + 0.05 * 10 ** (-25 / 20) * rng.standard_normal(n)
        path = tmp / f"dev{k}.wav"
        sf.write(str(path), np.clip(x, -1, 1).astype(np.float32), FS, subtype="PCM_16")
        paths.append(str(path))
    return paths, clicks


# ------------------------------------------------------------------------------------------------ processes
def proc_cpu_s(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/stat") as f:
            s = f.read()
    except OSError:
        return float("nan")
    fields = s[s.rindex(")") + 2:].split()
    return (int(fields[11]) + int(fields[12])) / CLK


def spawn(cmd: list[str], **kw) -> subprocess.Popen:
    p = subprocess.Popen(cmd, cwd=str(REPO), **kw)
    CHILDREN.append(p)
    return p


def stop(procs: list[subprocess.Popen], timeout_s: float = 10.0) -> None:
    """SIGINT (the commands end cleanly and print their summary), then SIGKILL what is left."""
    for p in procs:
        if p.poll() is None:
            try:
                p.send_signal(signal.SIGINT)
            except OSError:
                pass
    t_end = time.monotonic() + timeout_s
    for p in procs:
        try:
            p.wait(max(0.1, t_end - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5)


def start_router() -> tuple[subprocess.Popen, str]:
    p = spawn([PY, "-m", "stream.cli", "router", "--listen", "tcp/127.0.0.1:0", "--no-scouting"],
              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t_end = time.monotonic() + 30
    line = ""
    while time.monotonic() < t_end and p.poll() is None:
        r, _, _ = select.select([p.stdout], [], [], 0.2)
        if r:
            line = p.stdout.readline()
            break
    m = re.search(r"listening on (tcp/127\.0\.0\.1:\d+)", line)
    if not m:
        stop([p])
        raise SystemExit(f"the router did not start: {line!r} {p.stderr.read()[-500:] if p.poll() is not None else ''}")
    return p, m.group(1)


class Fleet:
    """N device agents (``adhoc-array device``), all ready before any streams, then started at one instant."""

    def __init__(self, tmp: pathlib.Path, files: list[str], n: int, mode: str, endpoint: str, tag: str) -> None:
        self.names = [f"d{i:02d}" for i in range(n)]
        self.logs = [tmp / f"{tag}_{name}.log" for name in self.names]
        ready = [tmp / f"{tag}_{name}.ready" for name in self.names]
        self.procs = []
        t0 = time.monotonic()
        for i, name in enumerate(self.names):
            cmd = [PY, "-c", LAUNCH, str(ready[i]), "device", "--name", name, "--input", files[i % len(files)],
                   "--speed", "1.0", "--no-scouting", "--mode", mode, "--connect", endpoint, "--array", ARRAY]
            with open(self.logs[i], "w") as out:
                self.procs.append(spawn(cmd, stdin=subprocess.PIPE, stdout=out, stderr=subprocess.STDOUT, text=True))
        t_end = time.monotonic() + 60 + n
        while time.monotonic() < t_end and not all(r.exists() for r in ready):
            if any(p.poll() is not None for p in self.procs):
                break
            time.sleep(0.05)
        self.n_ready = sum(r.exists() for r in ready)
        self.ready_s = round(time.monotonic() - t0, 1)
        if self.n_ready < n:
            log(f"{tag}: only {self.n_ready} of {n} devices ready after {self.ready_s} s")
        self.t_start = time.time() + 0.2
        self._go()

    def _go(self) -> None:
        for p in self.procs:
            try:
                p.stdin.write(f"{self.t_start:.6f}\n")
                p.stdin.close()
            except (OSError, ValueError):
                pass

    def alive(self) -> int:
        return sum(p.poll() is None for p in self.procs)

    def stop(self) -> dict:
        stop(self.procs)
        sent, errors, other = [], 0, []
        for path in self.logs:
            text = path.read_text(errors="replace")
            m = re.search(r"sent (\d+) frames .* (\d+) send errors", text)
            if m:
                sent.append(int(m.group(1)))
                errors += int(m.group(2))
            other += [ln for ln in text.splitlines() if ln.strip() and "adhoc-array device" not in ln][:2]
        out = {"devices_ready": self.n_ready, "fleet_ready_s": self.ready_s, "devices_reporting": len(sent),
               "frames_sent_total": int(sum(sent)), "send_errors": errors}
        if other:
            out["device_messages"] = other[:4]
        return out


def cpu_snapshot(roles: dict[str, list[subprocess.Popen]]) -> dict[str, list[float]]:
    snap = {role: [proc_cpu_s(p.pid) for p in ps] for role, ps in roles.items()}
    snap["self"] = [time.process_time()]
    return snap


def cpu_percent(a: dict, b: dict, wall_s: float) -> dict:
    out = {}
    for role in a:
        d = 100 * (np.asarray(b[role]) - np.asarray(a[role])) / wall_s
        if role == "devices":
            out["devices_median"] = round(float(np.nanmedian(d)), 2)
            out["devices_max"] = round(float(np.nanmax(d)), 2)
            out["devices_total"] = round(float(np.nansum(d)), 1)
        else:
            out[role] = round(float(d[0]), 2)
    return out


def load_avg() -> float:
    return float(open("/proc/loadavg").read().split()[0])


# ------------------------------------------------------------------------------------------------ receivers
def lat_stats(lat_ms: np.ndarray) -> dict:
    if len(lat_ms) == 0:
        return {}
    return {"p50_ms": round(float(np.percentile(lat_ms, 50)), 3), "p99_ms": round(float(np.percentile(lat_ms, 99)), 3),
            "p999_ms": round(float(np.percentile(lat_ms, 99.9)), 3), "max_ms": round(float(lat_ms.max()), 3)}


class RawReceiver:
    """Transport only: a subscriber whose callback records (device, seq, capture ns, arrival ns)."""

    def __init__(self, session, key: str) -> None:
        self.on = False
        self.rec: list[tuple[str, int, int, int]] = []
        self.seen: set[str] = set()
        head = wire.HEADER

        def cb(sample) -> None:
            arr = time.time_ns()
            name = Keys.device_of(str(sample.key_expr))
            if not self.on:
                self.seen.add(name)
                return
            h = head.unpack_from(sample.payload.to_bytes())
            self.rec.append((name, h[5], h[8], arr))

        self.sub = session.declare_subscriber(key, cb)

    def wait_all(self, names: list[str], timeout_s: float) -> bool:
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            if all(n in self.seen for n in names):
                return True
            time.sleep(0.1)
        return False

    def summary(self, names: list[str], window_s: float) -> dict:
        rec = list(self.rec)
        lat = np.array([(arr - cap) / 1e6 for _, _, cap, arr in rec])
        arr_s = np.array([(arr - rec[0][3]) / 1e9 for *_, arr in rec]) if rec else np.zeros(0)
        bins = [lat[(arr_s >= k) & (arr_s < k + 1)] for k in range(int(window_s))]
        p99_1s = [np.percentile(b, 99) for b in bins if len(b)]
        lost = dup = reord = 0
        per_dev_p99, starts = [], []
        frames = []
        for name in names:
            mine = [(s, (a - c) / 1e6) for n, s, c, a in rec if n == name]
            seqs = [s for s, _ in mine]
            frames.append(len(seqs))
            starts += [np.median([c - s * FRAME / FS * 1e9 for n, s, c, _ in rec if n == name])] if seqs else []
            if not seqs:
                continue
            u = sorted(set(seqs))
            lost += u[-1] - u[0] + 1 - len(u)
            dup += len(seqs) - len(u)
            reord += int(np.sum(np.diff(seqs) < 0))
            per_dev_p99.append(np.percentile([v for _, v in mine], 99))
        return {"frames": len(rec), "frames_expected": int(round(len(names) * FRAME_RATE * window_s)),
                "frames_per_device_min": int(min(frames)), "devices_heard": int(sum(f > 0 for f in frames)),
                "lost": int(lost), "duplicates": int(dup), "reordered": int(reord),
                **lat_stats(lat), "worst_device_p99_ms": round(float(max(per_dev_p99)), 3) if per_dev_p99 else None,
                "p99_ms_median_of_1s": round(float(np.median(p99_1s)), 3) if p99_1s else None,
                "p99_ms_worst_1s": round(float(np.max(p99_1s)), 3) if p99_1s else None,
                "share_over_5ms": round(float(np.mean(lat > 5.0)), 5) if len(lat) else None,
                "device_start_spread_ms": round(float(np.ptp(starts)) / 1e6, 1) if starts else None}


def raw_window(session, names, roles, warm_s, window_s) -> dict:
    rx = RawReceiver(session, Keys(ARRAY).audio())
    try:
        if not rx.wait_all(names, 30 + 0.3 * len(names)):
            log(f"only {len(rx.seen)} of {len(names)} devices heard")
        time.sleep(warm_s)
        a, t0 = cpu_snapshot(roles), time.monotonic()
        rx.on = True
        time.sleep(window_s)
        rx.on = False
        wall = time.monotonic() - t0
        b = cpu_snapshot(roles)
    finally:
        rx.sub.undeclare()
    out = rx.summary(names, wall)
    out["cpu_percent"] = cpu_percent(a, b, wall)
    out["window_s"] = round(wall, 2)
    out["load_avg_1min"] = load_avg()
    return out


def netsource_window(endpoint: str, names, roles, warm_s, window_s) -> dict:
    """NetSource iterated without the pipeline (the aggregator's transport path), in this process."""
    src = NetSource(NetOptions(mode="client", connect=[endpoint], scouting=False), array=ARRAY, expect=names,
                    discover_s=10.0, jitter_s=0.1)
    src.open()
    frames = 0
    t_warm = time.monotonic() + warm_s
    a = None
    marks: list[tuple[int, int, int, int]] = []
    it = iter(src)
    try:
        for fr in it:
            now = time.monotonic()
            if a is None:
                if now < t_warm:
                    continue
                a, t0 = cpu_snapshot(roles), now
                marks = [(src._latency(d.name).n, ln.buffer.counters.n_lost_frames,
                          ln.buffer.counters.n_concealed_samples, src._overrun.get(d.name, 0))
                         for d, ln in zip(src.active, src._lanes)]
            frames += 1
            if now - t0 >= window_s:
                break
        if a is None:
            raise RuntimeError("NetSource delivered nothing")
        wall = time.monotonic() - t0
        b = cpu_snapshot(roles)
    finally:
        it.close()
        src.close()
    lat, lost, concealed, overrun = [], 0, 0, 0
    for d, ln, (k0, l0, c0, o0) in zip(src.active, src._lanes, marks):
        c = ln.buffer.counters
        lat += list(src._latency(d.name).values()[k0:])    # arrival latencies (the run is shorter than the reservoir)
        lost += c.n_lost_frames - l0
        concealed += c.n_concealed_samples - c0
        overrun += src._overrun.get(d.name, 0) - o0
    return {"frames": frames, "frames_expected": int(round(len(names) * FRAME_RATE * wall)), "lost": int(lost),
            "concealed_samples": int(concealed), "overrun_frames": int(overrun),
            **lat_stats(np.asarray(lat)), "cpu_percent": cpu_percent(a, b, wall), "window_s": round(wall, 2),
            "load_avg_1min": load_avg()}


# ------------------------------------------------------------------------------------------------ aggregate
class OutputTap:
    """Subscribes to the enhanced output and to the reference device's frames (for the click latency)."""

    def __init__(self, session, ref: str) -> None:
        keys = Keys(ARRAY)
        self.enh: list[tuple[int, np.ndarray, int, int, float]] = []
        self.ref_cap: dict[int, int] = {}
        self.lock = threading.Lock()

        def on_enh(sample) -> None:
            arr = time.time_ns()
            f = wire.decode(sample.payload.to_bytes())
            with self.lock:
                self.enh.append((f.first_sample, f.samples[:, 0], f.capture_time_ns, arr, f.sample_rate_hz))

        def on_ref(sample) -> None:
            h = wire.HEADER.unpack_from(sample.payload.to_bytes())
            self.ref_cap[h[5]] = h[8]       # seq -> capture ns (first_sample = seq * FRAME)

        self.subs = [session.declare_subscriber(keys.out("enhanced"), on_enh),
                     session.declare_subscriber(keys.audio(ref), on_ref)]

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()


def click_latency(tap: OutputTap, clicks: np.ndarray, t_from_ns: int) -> dict:
    """Match the clicks in the enhanced stream to the input's and time them (module doc)."""
    with tap.lock:
        enh = list(tap.enh)
    if not enh:
        return {"n_clicks": 0}
    fs = enh[0][4]
    end = max(f + len(x) for f, x, *_ in enh)
    y = np.zeros(end, np.float32)
    pub = np.zeros(end, np.int64)
    fend = np.zeros(end, np.int64)
    for f, x, cap, _, _ in enh:
        y[f:f + len(x)] = x
        pub[f:f + len(x)] = cap
        fend[f:f + len(x)] = f + len(x)
    env = np.abs(y)
    thr = max(0.2, 0.4 * np.percentile(env, 99.99))
    cand = []
    i = 0
    above = np.flatnonzero(env > thr)
    while i < len(above):
        j = above[i]
        seg = slice(j, min(end, j + int(0.2 * fs)))
        k = j + int(np.argmax(env[seg]))
        cand.append(k)
        i = int(np.searchsorted(above, j + int(0.3 * fs)))
    cand = np.asarray(cand)
    if len(cand) == 0:
        return {"n_clicks": 0, "threshold": float(thr)}
    t_out = cand / fs
    t_in = clicks / FS
    best = (0, 0.0)
    for o in t_out[:10]:
        for ti in t_in:
            c = o - ti
            d = np.abs(t_out[:, None] - t_in[None, :] - c).min(axis=1)
            n = int(np.sum(d < 0.004))
            if n > best[0]:
                best = (n, c)
    n_match, offset = best
    lat, framing = [], []
    for k, o in zip(cand, t_out):
        d = np.abs(o - t_in - offset)
        m = int(np.argmin(d))
        if d[m] >= 0.004 or pub[k] < t_from_ns:
            continue
        seq = int(clicks[m]) // FRAME
        cap = tap.ref_cap.get(seq)
        if cap is None:
            continue
        lat.append((pub[k] - cap) / 1e6)
        framing.append(1e3 * (fend[k] - k) / fs)
    lat = np.asarray(lat)
    out = {"n_clicks": int(len(lat)), "n_candidates": int(len(cand)), "n_matched_all": int(n_match),
           "audio_offset_s": round(float(offset), 4)}
    if len(lat):
        h = len(lat) // 2
        out.update({"p50_ms": round(float(np.median(lat)), 1), "min_ms": round(float(lat.min()), 1),
                    "max_ms": round(float(lat.max()), 1),
                    "output_framing_median_ms": round(float(np.median(framing)), 1),
                    "minus_output_framing_median_ms": round(float(np.median(lat - np.asarray(framing))), 1),
                    "first_half_median_ms": round(float(np.median(lat[:max(h, 1)])), 1),
                    "second_half_median_ms": round(float(np.median(lat[h:])), 1)})
    return out


def aggregate_window(tmp: pathlib.Path, endpoint: str, names, roles, clicks, warm_s, window_s,
                     working_rate_hz: float, engine_args: list[str], session) -> dict:
    out_dir = tmp / f"agg{len(names)}"
    cmd = [PY, "-m", "stream.cli", "aggregate", "--out", str(out_dir), "--expect", ",".join(names),
           "--discover-s", "15", "--mode", "client", "--connect", endpoint, "--no-scouting", "--array", ARRAY,
           "--no-plots", "--no-progress"]
    if working_rate_hz:
        cmd += ["--working-rate-hz", f"{working_rate_hz:g}"]
    cmd += engine_args
    tap = OutputTap(session, names[0])
    logf = open(tmp / f"agg{len(names)}.log", "w")
    t_launch = time.monotonic()
    agg = spawn(cmd, stdout=logf, stderr=subprocess.STDOUT)
    roles = {**roles, "aggregator": [agg]}
    result: dict = {"engine_args": " ".join(shlex.quote(c) for c in cmd[cmd.index("--no-progress") + 1:])}
    try:
        t_end = time.monotonic() + 120
        while not tap.enh and time.monotonic() < t_end and agg.poll() is None:
            time.sleep(0.05)
        if not tap.enh:
            result["error"] = f"no enhanced output (exit {agg.poll()})"
            return result
        result["first_output_after_s"] = round(time.monotonic() - t_launch, 2)
        time.sleep(warm_s)
        with tap.lock:
            n0 = sum(len(e[1]) for e in tap.enh)
        a, t0, t0_ns = cpu_snapshot(roles), time.monotonic(), time.time_ns()
        time.sleep(window_s)
        with tap.lock:
            n1 = sum(len(e[1]) for e in tap.enh)
            fs_out = tap.enh[0][4]
        wall = time.monotonic() - t0
        b = cpu_snapshot(roles)
        result["cpu_percent"] = cpu_percent(a, b, wall)
        result["window_s"] = round(wall, 2)
        result["load_avg_1min"] = load_avg()
        result["output_real_time_ratio"] = round((n1 - n0) / fs_out / wall, 3)
        result["e2e_click_latency_ms"] = click_latency(tap, clicks, t0_ns)
        enh_lat = np.array([(arr - cap) / 1e6 for _, _, cap, arr, _ in tap.enh])
        result["enhanced_publish_to_arrival_ms"] = lat_stats(enh_lat)
    finally:
        stop([agg], timeout_s=60)
        tap.close()
        logf.close()
    report_path = out_dir / "report.json"
    if not report_path.exists():
        result["error"] = "no report.json: " + " | ".join((tmp / f"agg{len(names)}.log").read_text().splitlines()[-3:])
        return result
    rep = json.loads(report_path.read_text())
    st, tm, nw = rep.get("stream", {}), rep.get("timing", {}), rep.get("network", {})
    devs = list(nw.get("devices", {}).values())
    p50 = [d["latency_ms"]["p50"] for d in devs if "latency_ms" in d]
    p99 = [d["latency_ms"]["p99"] for d in devs if "latency_ms" in d]
    result.update({
        "status": rep.get("status"), "exit_code": agg.returncode,
        "working_rate_hz": st.get("working_rate_hz"), "frame_samples": st.get("frame_samples"),
        "hop_samples": st.get("hop_samples"), "estimator": rep.get("settings", {}).get("estimator"),
        "output_latency_ms": round(1e3 * st["output_latency_s"], 1) if "output_latency_s" in st else None,
        "audio_s": st.get("audio_s"), "wall_s": tm.get("wall_s"),
        "report_cpu_percent": round(100 * tm["cpu_s"] / tm["wall_s"], 1) if tm.get("wall_s") else None,
        "hop_ms_median": tm.get("block_ms_median"), "hop_ms_p99": tm.get("block_ms_p99"),
        "hop_budget_ms": tm.get("hop_ms"),
        "net_lost_frames": int(sum(d["n_lost_frames"] for d in devs)),
        "net_late_frames": int(sum(d["n_late_frames"] for d in devs)),
        "net_overrun_frames": int(sum(d["n_overrun_frames"] for d in devs)),
        "net_concealed_samples": int(sum(d["n_concealed_samples"] for d in devs)),
        "net_release_latency_p50_ms_median": round(float(np.median(p50)), 2) if p50 else None,
        "net_release_latency_p99_ms_max": round(float(np.max(p99)), 2) if p99 else None,
        "late_blocks_max": int(max(st.get("late_blocks") or [0])),
        "coarse_offsets_ms_max": round(1e3 * float(np.max(np.abs(st.get("coarse_offsets_s") or [0]))), 1),
        "devices_in_report": len(devs),
    })
    e2e = result["e2e_click_latency_ms"].get("p50_ms")
    if e2e is not None and result["output_latency_ms"] is not None:
        result["e2e_minus_output_latency_ms"] = round(e2e - result["output_latency_ms"], 1)
    return result


def inprocess_window(tmp: pathlib.Path, files, n, clicks, rate: float, engine_args: list[str], seconds: float) -> dict:
    """The same pipeline in this process, no network: the same files paced at real time in the same 1024-sample
    frames (``ReplaySource``), the aggregator's engine options (live defaults, ``--working-rate-hz``, the
    engine args), the output grouped in 4 hops as NetPublisher does; the same click timing (capture = the
    source yielding d00's frame, output = the group of 4 hops complete)."""
    from stream.cli import _overrides, build_parser
    from stream.config import EngineConfig, merge
    from stream.live import LIVE_DEFAULTS
    from stream.replay import ReplaySource
    from stream.run import run_stream
    opts = _overrides(build_parser().parse_args(["replay", "x", "--out", "x", *engine_args]))
    cfg = merge(EngineConfig(), LIVE_DEFAULTS, source="live defaults")
    cfg = merge(cfg, {**opts, "working_rate_hz": rate or None, "plots": False, "progress": False}, source="bench")
    names = [f"d{i:02d}" for i in range(n)]
    src = ReplaySource([files[i % len(files)] for i in range(n)], block_s=FRAME / FS, speed=1.0, names=names)
    tap = types.SimpleNamespace(enh=[], ref_cap={}, lock=threading.Lock())

    class Group:                              # NetPublisher's framing: 4 hops per published frame
        def __init__(self) -> None:
            self.pending: list[np.ndarray] = []
            self.first = 0
            self.fs = float(rate or FS)

        def write(self, result) -> None:
            self.pending.append(result.enhanced)
            if len(self.pending) >= 4:
                x = np.concatenate(self.pending)
                self.pending = []
                tap.enh.append((self.first, x, time.time_ns(), 0, self.fs))
                self.first += len(x)

        def close(self) -> None:
            pass

    def on_frame(frame) -> None:
        if frame.device_id == 0:
            tap.ref_cap[frame.first_sample // FRAME] = time.time_ns()

    timer = threading.Timer(seconds, src.stop)
    timer.start()
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        outcome = run_stream(src, tmp / f"inproc{n}", config=cfg, extra_sinks=[Group()], on_frame=on_frame,
                             handle_signals=False)
    finally:
        timer.cancel()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    rep = outcome.report
    st, tm = rep.get("stream", {}), rep.get("timing", {})
    return {"working_rate_hz": st.get("working_rate_hz"), "frame_samples": st.get("frame_samples"),
            "hop_samples": st.get("hop_samples"), "output_latency_ms": round(1e3 * st["output_latency_s"], 1),
            "cpu_percent": round(100 * cpu / wall, 1), "hop_ms_median": tm.get("block_ms_median"),
            "e2e_click_latency_ms": click_latency(tap, clicks, tap.enh[0][2] + int(3e9) if tap.enh else 0),
            "coarse_offsets_ms_max": round(1e3 * float(np.max(np.abs(st.get("coarse_offsets_s", [0])))), 1),
            "status": rep.get("status"), "load_avg_1min": load_avg()}


# ------------------------------------------------------------------------------------------------ fleets
def peer_fleet(tmp, files, n, warm_s, window_s) -> dict:
    import zenoh
    cfg = NetOptions(mode="peer", listen=["tcp/127.0.0.1:0"], scouting=False).config()
    cfg.insert_json5("adminspace/enabled", "true")
    session = zenoh.open(cfg)
    fleet = None
    try:
        loc = [x for x in router_locators(session) if x.startswith("tcp/127.0.0.1:")]
        fleet = Fleet(tmp, files, n, "peer", loc[0], f"peer{n}")
        res = raw_window(session, fleet.names, {"devices": fleet.procs}, warm_s, window_s)
        res["devices_alive_at_end"] = fleet.alive()
    finally:
        if fleet is not None:
            res_dev = fleet.stop()
        session.close()
    res.update(res_dev)
    return res


def router_fleet(tmp, files, n, args, clicks, engine_args) -> dict:
    router, endpoint = start_router()
    fleet = None
    out: dict = {}
    try:
        fleet = Fleet(tmp, files, n, "client", endpoint, f"router{n}")
        roles = {"router": [router], "devices": fleet.procs}
        session = NetOptions(mode="client", connect=[endpoint], scouting=False).open()
        try:
            log(f"router{n}: transport-only receiver")
            out[f"router{n}_raw"] = raw_window(session, fleet.names, roles, args.warm_s, args.window_s)
            if not args.no_netsource:
                log(f"router{n}: NetSource without the pipeline")
                out[f"router{n}_netsource"] = netsource_window(endpoint, fleet.names, roles, args.warm_s,
                                                               args.window_s)
            for rate in ([] if args.no_aggregate else args.rates):
                tag = f"router{n}_aggregate_{rate / 1000:g}k" if rate else f"router{n}_aggregate_native"
                log(f"{tag}: adhoc-array aggregate")
                out[tag] = aggregate_window(tmp, endpoint, fleet.names, roles, clicks, args.warm_s + 1,
                                            args.aggregate_s, rate, engine_args, session)
            out[f"router{n}_raw"]["devices_alive_at_end"] = fleet.alive()
        finally:
            session.close()
    finally:
        if fleet is not None:
            sent = fleet.stop()
            out.setdefault(f"router{n}_raw", {}).update(sent)
        stop([router])
    return out


# ------------------------------------------------------------------------------------------------ main
def ratio(a, b):
    return round(a / b, 2) if a is not None and b else None


def fmt_raw(name: str, r: dict) -> str:
    c = r["cpu_percent"]
    extra = f", router {c['router']:.1f} %" if "router" in c else ""
    return (f"{name:>25}: {r['frames']}/{r['frames_expected']} frames, lost {r['lost']}, dup {r.get('duplicates', 0)}, "
            f"reord {r.get('reordered', 0)}; latency p50 {r.get('p50_ms', float('nan')):.2f} / p99 "
            f"{r.get('p99_ms', float('nan')):.2f} / p99.9 {r.get('p999_ms', float('nan')):.2f} / max "
            f"{r.get('max_ms', float('nan')):.1f} ms"
            + (f" (p99 per second: median {r['p99_ms_median_of_1s']:.2f}, worst {r['p99_ms_worst_1s']:.2f})"
               if r.get("p99_ms_median_of_1s") is not None else "") +
            f"; CPU receiver {c['self']:.1f} %{extra}, devices median "
            f"{c['devices_median']:.1f} % (sum {c['devices_total']:.0f} %); load {r['load_avg_1min']:.1f}"
            + (f"; devices started within {r['device_start_spread_ms']} ms"
               if r.get("device_start_spread_ms") is not None else ""))


def fmt_agg(name: str, r: dict) -> str:
    if "error" in r and "status" not in r:
        return f"{name:>25}: {r['error']}"
    c, e = r.get("cpu_percent", {}), r.get("e2e_click_latency_ms", {})
    return (f"{name:>25}: {r['working_rate_hz']:g} Hz {r['frame_samples']}/{r['hop_samples']} {r['estimator']}; "
            f"output {r.get('output_real_time_ratio')} x real time, hop median {r['hop_ms_median']:.2f} ms of "
            f"{r['hop_budget_ms']:.1f}; CPU aggregator {c.get('aggregator', float('nan')):.1f} % (report "
            f"{r['report_cpu_percent']} %), router {c.get('router', float('nan')):.1f} %; network lost "
            f"{r['net_lost_frames']}, overrun {r['net_overrun_frames']}, release latency p50 "
            f"{r['net_release_latency_p50_ms_median']} / p99 max {r['net_release_latency_p99_ms_max']} ms\n"
            f"{'':>27}end-to-end (click, device agent -> enhanced published) median {e.get('p50_ms')} ms "
            f"(min {e.get('min_ms')}, max {e.get('max_ms')}; {e.get('n_clicks')} clicks; halves "
            f"{e.get('first_half_median_ms')} -> {e.get('second_half_median_ms')}); without the wait for the rest of "
            f"the output frame {e.get('minus_output_framing_median_ms')} ms; pipeline's algorithmic latency "
            f"{r['output_latency_ms']} ms")


def fmt_inproc(name: str, r: dict) -> str:
    e = r["e2e_click_latency_ms"]
    return (f"{name:>25}: {r['working_rate_hz']:g} Hz {r['frame_samples']}/{r['hop_samples']}, no network: CPU "
            f"{r['cpu_percent']} %, hop median {r['hop_ms_median']:.2f} ms; click latency (source frame -> group of "
            f"4 hops out) median {e.get('p50_ms')} ms (min {e.get('min_ms')}, max {e.get('max_ms')}; "
            f"{e.get('n_clicks')} clicks), without the output framing {e.get('minus_output_framing_median_ms')} ms; "
            f"algorithmic {r['output_latency_ms']} ms")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--devices", default="16,32", help="device counts, comma-separated (default 16,32)")
    ap.add_argument("--window-s", type=float, default=10.0, help="measurement window per receiver (default 10)")
    ap.add_argument("--warm-s", type=float, default=2.0, help="warm-up before each window (default 2)")
    ap.add_argument("--aggregate-s", type=float, default=15.0,
                    help="window of the aggregate run, and (+ 5 s) length of the in-process run (default 15)")
    ap.add_argument("--working-rate-hz", default="0",
                    help="aggregate's engine rate(s), comma-separated, one aggregate (and in-process) run each "
                         "(default 0: the engine's default, the devices' 48 kHz; e.g. 0,16000)")
    ap.add_argument("--engine-args", default="--estimator kalman",
                    help="more aggregate options (default \"--estimator kalman\": the network path's figures, as in "
                         "the README, without the tracker's cost; \"\" for the live default)")
    ap.add_argument("--data", help="folder of speech WAVs (e.g. ../shared/data/audio/vctk-48k); default synthetic")
    ap.add_argument("--no-peer", action="store_true", help="skip the peer-to-peer baseline")
    ap.add_argument("--no-netsource", action="store_true", help="skip the NetSource receiver")
    ap.add_argument("--no-aggregate", action="store_true", help="skip the aggregate command")
    ap.add_argument("--no-inprocess", action="store_true", help="skip the in-process pipeline baseline")
    ap.add_argument("--quick", action="store_true", help="16 devices, 6 s windows (~1 min)")
    ap.add_argument("--keep", action="store_true", help="keep the temp dir (device files, logs, report.json)")
    args = ap.parse_args(argv)
    if args.quick:
        args.devices, args.window_s, args.aggregate_s = "16", 6.0, 10.0
    counts = [int(v) for v in args.devices.split(",")]
    args.rates = [float(v) for v in args.working_rate_hz.split(",") if v.strip()]
    engine_args = shlex.split(args.engine_args)
    quiet_zenoh()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))     # the finally below stops every child
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="net_fanin_"))
    results: dict = {}
    t_run = time.monotonic()
    try:
        seconds = (30 + 0.5 * max(counts) + 2 * (args.warm_s + args.window_s)
                   + len(args.rates) * (args.aggregate_s + args.warm_s + 30) + 30)
        files, clicks = make_files(tmp, seconds, args.data)
        log(f"{N_FILES} device files of {seconds:.0f} s in {tmp}")
        for n in counts:
            if not args.no_peer:
                log(f"peer{n}: {n} devices in peer mode straight to the receiver")
                results[f"peer{n}"] = peer_fleet(tmp, files, n, args.warm_s, args.window_s)
            log(f"router{n}: router + {n} devices in client mode")
            results.update(router_fleet(tmp, files, n, args, clicks, engine_args))
            for rate in ([] if args.no_aggregate or args.no_inprocess else args.rates):
                tag = f"inprocess{n}_{rate / 1000:g}k" if rate else f"inprocess{n}_native"
                log(f"{tag}: the same pipeline in this process, no network")
                results[tag] = inprocess_window(tmp, files, n, clicks, rate, engine_args, args.aggregate_s + 5)
    finally:
        stop([p for p in CHILDREN if p.poll() is None])
        if args.keep:
            log(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    ratios = {}
    for n in counts:
        r, p = results.get(f"router{n}_raw"), results.get(f"peer{n}")
        if r and p:
            ratios[f"router{n}_over_peer{n}"] = {k: ratio(r.get(k), p.get(k)) for k in ("p50_ms", "p99_ms")}
            ratios[f"router{n}_over_peer{n}"]["receiver_cpu"] = ratio(r["cpu_percent"]["self"],
                                                                       p["cpu_percent"]["self"])
    if len(counts) > 1:
        a, b = results.get(f"router{counts[-1]}_raw"), results.get(f"router{counts[0]}_raw")
        if a and b:
            key = f"router{counts[-1]}_over_router{counts[0]}"
            ratios[key] = {k: ratio(a.get(k), b.get(k)) for k in ("p50_ms", "p99_ms")}
            for role in ("self", "router", "devices_median"):
                ratios[key][f"cpu_{role}"] = ratio(a["cpu_percent"][role], b["cpu_percent"][role])
    for name, r in results.items():
        if "_aggregate" not in name or "e2e_click_latency_ms" not in r:
            continue
        n_dev = name[len("router"):].split("_")[0]
        base = results.get(name.replace(f"router{n_dev}_aggregate", f"inprocess{n_dev}"))
        if base:
            e, b = r["e2e_click_latency_ms"], base["e2e_click_latency_ms"]
            ratios[f"{name}_over_inprocess"] = {
                "e2e_p50": ratio(e.get("p50_ms"), b.get("p50_ms")),
                "e2e_p50_added_ms": round(e["p50_ms"] - b["p50_ms"], 1) if "p50_ms" in e and "p50_ms" in b else None,
                "cpu": ratio(r.get("cpu_percent", {}).get("aggregator"), base["cpu_percent"])}
    for name, r in results.items():
        print(fmt_agg(name, r) if "_aggregate" in name else fmt_inproc(name, r) if name.startswith("inprocess")
              else fmt_raw(name, r))
    for name, r in ratios.items():
        print(f"{name:>25}: " + ", ".join(f"{k} {v}" for k, v in r.items()))
    print(f"total {time.monotonic() - t_run:.0f} s")
    print(json.dumps({"net_fanin": {"results": results, "ratios": ratios, "devices": counts,
                                    "signal": "speech " + args.data if args.data else "synthetic speech-like",
                                    "frame_samples": FRAME, "sample_rate_hz": FS}}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
