"""A long live run through a JACK dummy server: overflows, underflows and the CPU share of ``adhoc-array live``.

``adhoc-array live`` runs in its own process (as a user runs it), 8 devices on the server's 8 capture
channels, playing the enhanced stream on the server's output; a patch-bay client in this process plays a
looping 8-device recording into its inputs for the whole run: the ``async_8dev`` fixture's synchronous signals
(real speech in a room at 8 devices) resampled to the run's rate. Figures from the
run's report.json:

- overflows (PortAudio's input-overflow flags), gaps (samples lost in our rings), output underflows;
- ``cpu_share``: the engine process's CPU time over its wall time from the start of the stream runner to
  the end (every thread: the PortAudio callbacks, the stream loop, the workers), in % of one core;
  ``running_cpu_share``: the same from the first hop out to the end of the input (``report.json``
  ``timing.running_cpu_share``): the stream once it runs, without the start-up's wait for the first alignment,
  which lowers the whole-run figure.

Baseline, same process and server: a bare sounddevice process that captures the same channels and plays one
channel with callbacks that only copy (``baseline_cpu_share``): what the audio I/O alone costs in Python.

Configurations: ``soak``: 8 channels at 48 kHz (frame 4096, hop 1024, JACK period 1024) for ``--minutes``
(default 10; target 0 overflows and 0 underflows); ``cpu``: 8 devices at 16 kHz, frame 512, hop 128, JACK
period 128, for ``--cpu-minutes`` (default 2; target at most 5 % of one core). The last stdout line is one
JSON object. Needs jackd2 (``make test`` installs it).
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))

from stream.jack_dummy import PatchBay, jack_dummy_server  # noqa: E402

N_DEV = 8
FIXTURE = pathlib.Path(__file__).resolve().parent.parent / "replay_fixtures" / "async_8dev"


def fixture_audio(rate: int) -> np.ndarray:
    """The fixture's synchronous signals (its 8 devices on one clock: the server's channels share one, and the
    engine's offsets come from the stream) at ``rate``: (n_samples, 8) float32. Real speech in a room, so that the
    default tracker runs as it does on a talker (a synthetic scene has no speech for it)."""
    import soundfile as sf
    import soxr

    x, fs = sf.read(FIXTURE / "truth" / "sync.flac", dtype="float32", always_2d=True)
    return np.ascontiguousarray(soxr.resample(x[:, :N_DEV], fs, rate), np.float32)

BARE = r"""
import sys, time, numpy as np, sounddevice as sd
rate, n, seconds = float(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
ring = np.zeros((int(rate) * 4, n), np.float32); pos = [0]
def icb(indata, frames, t, status):
    i = pos[0] % (len(ring) - frames); ring[i:i + frames] = indata; pos[0] += frames
def ocb(outdata, frames, t, status):
    outdata[:] = ring[:frames, :1]
t0, c0 = time.perf_counter(), time.process_time()
with sd.InputStream(device="system", channels=n, samplerate=rate, dtype="float32", callback=icb), \
     sd.OutputStream(device="system", channels=1, samplerate=rate, dtype="float32", callback=ocb):
    time.sleep(seconds)
print((time.process_time() - c0) / (time.perf_counter() - t0))
"""


def _looping_player(bay: PatchBay, audio: np.ndarray, client: str, stop: threading.Event) -> None:
    ins = bay.wait_ports(rf"{client}:in_", N_DEV, is_input=True, timeout_s=60)
    for k, port in enumerate(ins):
        bay.rewire(f"bay:out_{k + 1}", port)
    while not stop.is_set():
        bay.play(audio)
        while bay.playing and not stop.is_set():
            time.sleep(0.05)


def run(name: str, rate: int, frame: int, hop: int, period: int, seconds: float, estimator: str | None = None,
        engine_args: list[str] = ()) -> dict:
    audio = fixture_audio(rate)
    with jack_dummy_server(sample_rate_hz=rate, period_samples=period, n_channels=N_DEV) as server:
        env = dict(os.environ, JACK_DEFAULT_SERVER=server.name)
        bay = PatchBay(server, n_outputs=N_DEV, n_inputs=1, record_s=1.0)
        # baseline: the audio I/O alone, in its own process
        stop = threading.Event()
        player = threading.Thread(target=_looping_player, args=(bay, audio, "PortAudio[-0-9]*", stop), daemon=True)
        player.start()
        bare = subprocess.run([sys.executable, "-c", BARE, str(rate), str(N_DEV), str(min(seconds, 60.0))],
                              env=env, capture_output=True, text=True, timeout=seconds + 120)
        stop.set()
        player.join(5)
        baseline = float(bare.stdout.strip().splitlines()[-1]) if bare.returncode == 0 else float("nan")
        # the engine
        stop = threading.Event()
        player = threading.Thread(target=_looping_player, args=(bay, audio, "PortAudio[-0-9]*", stop), daemon=True)
        player.start()
        with tempfile.TemporaryDirectory(prefix="live_soak_") as tmp:
            cmd = [sys.executable, "-m", "stream.cli", "live", "--out", tmp, "--output", "system", "--no-status",
                   "--no-plots", "--duration", str(seconds), "--blocksize", str(period), "--frame-samples",
                   str(frame), "--hop-samples", str(hop)]
            for k in range(N_DEV):
                cmd += ["--input", f"system:{k + 1}"]
            if estimator:
                cmd += ["--estimator", estimator]
            cmd += list(engine_args)
            eng = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=seconds + 300)
            stop.set()
            player.join(5)
            report = json.loads(pathlib.Path(tmp, "report.json").read_text())
        bay.close()
    cards = report.get("cards", {})
    timing = report.get("timing", {})
    share = timing["cpu_s"] / timing["wall_s"] if timing else float("nan")
    return {
        "config": name, "rate_hz": rate, "n_devices": N_DEV, "frame_samples": frame, "hop_samples": hop,
        "jack_period_samples": period, "seconds": seconds, "status": report.get("status"),
        "estimator": report.get("settings", {}).get("estimator"),
        "engine_args": list(engine_args),
        "exit_code": eng.returncode,
        "audio_s": report.get("stream", {}).get("audio_s"),
        "n_overflows": sum(c["n_overflows"] for c in cards.get("inputs", [])),
        "overflows_s": [c.get("overflows_s") for c in cards.get("inputs", []) if c.get("overflows_s")],
        "n_gaps": sum(c["n_gaps"] for c in cards.get("inputs", [])),
        "n_underflows": cards.get("output", {}).get("n_underflows"),
        "underflows_s": cards.get("output", {}).get("underflows_s"),
        "n_port_underflows": cards.get("output", {}).get("n_port_underflows"),
        "alignment_quality": report.get("stream", {}).get("alignment_quality"),
        "cpu_share_percent": round(100 * share, 2),
        "running_cpu_share_percent": (round(100 * timing["running_cpu_share"], 2)
                                      if timing.get("running_cpu_share") is not None else None),
        "baseline_cpu_share_percent": round(100 * baseline, 2),
        "hop_ms_p50": timing.get("block_ms_median"), "hop_ms_p99": timing.get("block_ms_p99"),
        "hop_ms_p999": timing.get("block_ms_p999"), "hop_ms_max": timing.get("block_ms_max"),
        "engine_stderr_tail": eng.stderr.strip().splitlines()[-3:],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="soak run (8 ch, 48 kHz; 0: skip it)")
    ap.add_argument("--cpu-minutes", type=float, default=2.0, help="CPU run (8 dev, 16 kHz, hop 128; 0: skip it)")
    ap.add_argument("--estimator", help="the engine's TOA estimator (default: live's, the tracker)")
    ap.add_argument("--engine-arg", action="append", default=[], metavar="ARG",
                    help="one more argument for `adhoc-array live` (repeat; e.g. --engine-arg=--track-interval-s "
                         "--engine-arg=0)")
    args = ap.parse_args(argv)
    if args.minutes < 0 or args.cpu_minutes < 0 or not (args.minutes or args.cpu_minutes):
        ap.error("--minutes and --cpu-minutes must be >= 0, and one of them > 0")
    results = ([run("cpu", 16000, 512, 128, 128, 60 * args.cpu_minutes, args.estimator, args.engine_arg)]
               if args.cpu_minutes else []) \
        + ([run("soak", 48000, 4096, 1024, 1024, 60 * args.minutes, args.estimator, args.engine_arg)]
           if args.minutes else [])
    for r in results:
        print(f"{r['config']:>4}: {r['n_devices']} devices at {r['rate_hz']} Hz, {r['frame_samples']}/{r['hop_samples']}, "
              f"{r['estimator']}, "
              f"{r['audio_s']:.0f} s: overflows {r['n_overflows']}, gaps {r['n_gaps']}, underflows "
              f"{r['n_underflows']}; CPU {r['cpu_share_percent']} % of a core (running: "
              f"{r['running_cpu_share_percent']} %; I/O alone "
              f"{r['baseline_cpu_share_percent']} %); per hop p50 {r['hop_ms_p50']:.3f} / p99.9 "
              f"{r['hop_ms_p999']:.3f} ms")
    print(json.dumps({"live_soak": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
