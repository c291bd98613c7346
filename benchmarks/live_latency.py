"""Input-to-output latency of ``adhoc-array live`` through a JACK dummy server, timed with clicks.

A patch-bay client plays a click train (one click every 0.5 s over a -60 dBFS noise floor) into the capture
ports of ``live`` (4 devices), records ``live``'s output port, and in the same JACK cycles records its own
click train straight back (the baseline: what the audio server alone costs, in the same process and run).
The latency of a click is the sample distance, on the server's clock, from the cycle that played it to the
cycle that recorded it in the enhanced output (the delay-and-sum of identical clicks is a click).

Two settings at 16 kHz: ``default`` (the engine's frame and hop: 1024/256, JACK period 256) and
``low-latency`` (512/128, JACK period 128), each with the output card's default margin (10 ms queued before
it plays: ``--output-margin-s``) and with none; with ``--batch-s S``, also the low-latency setting with the input
processed in batches of S (``live --batch-s``: less CPU, more latency). Target: at most one frame + one hop + 10 ms
(for the settings without batches). The last stdout line
is one JSON object: per setting the median and max latency in ms (the max also after the first 1 s of
output, once the output queue has shed the burst of the first alignment), the baseline, the target, the underflow
and overflow counts of the run.

Run ``python benchmarks/live_latency.py`` (needs jackd2, as ``make test`` installs it).
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import threading

import numpy as np

from stream.jack_dummy import PatchBay, jack_dummy_server

RATE = 16000
N_DEV = 4
CLICK_EVERY_S = 0.5


def click_train(duration_s: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(signal (n,), click onsets (k,) in samples): 2 ms decaying noise bursts at 0.5 FS."""
    rng = np.random.default_rng(seed)
    n = int(duration_s * RATE)
    x = (1e-3 * rng.standard_normal(n)).astype(np.float32)
    onsets = np.arange(int(0.25 * RATE), n - RATE // 10, int(CLICK_EVERY_S * RATE))
    burst = (0.5 * rng.standard_normal(32) * np.exp(-np.arange(32) / 8.0)).astype(np.float32)
    burst[0] = 0.5
    for o in onsets:
        x[o:o + len(burst)] += burst
    return x, onsets


def detect(y: np.ndarray, threshold: float) -> np.ndarray:
    """Onsets (samples) of clicks in ``y``: first sample above ``threshold`` after 0.2 s below it."""
    above = np.flatnonzero(np.abs(y) > threshold)
    if not len(above):
        return above
    keep = np.r_[True, np.diff(above) > int(0.2 * RATE)]
    return above[keep]


def measure(setting: str, frame: int, hop: int, period: int, duration_s: float, margin_s: float,
            batch_s: float = 0.0) -> dict:
    from stream.live import run_live
    x, onsets = click_train(duration_s)
    with jack_dummy_server(sample_rate_hz=RATE, period_samples=period, n_channels=N_DEV) as server:
        bay = PatchBay(server, n_outputs=N_DEV, n_inputs=2, record_s=duration_s + 20)

        def wire() -> None:
            ins = bay.wait_ports(r"PortAudio:in_", N_DEV, is_input=True)
            for k, port in enumerate(ins):
                bay.rewire(f"bay:out_{k + 1}", port)
            bay.rewire("bay:out_1", "bay:in_2")
            bay.play(np.repeat(x[:, None], N_DEV, axis=1))
            out = bay.wait_ports(r"PortAudio:out_", 1, is_output=True, timeout_s=60)
            bay.rewire(out[0], "bay:in_1")

        threading.Thread(target=wire, daemon=True).start()
        with tempfile.TemporaryDirectory(prefix="live_latency_") as tmp:
            outcome = run_live([f"system:{k + 1}" for k in range(N_DEV)], tmp, output="system",
                               max_duration_s=duration_s + 1.0, status=False, block_samples=period,
                               output_margin_s=margin_s, batch_s=batch_s,
                               overrides=[({"frame_samples": frame, "hop_samples": hop, "plots": False}, "bench")])
        rec = bay.recorded[:bay.n_recorded]
        play0, rec0 = bay.play_start_frame, bay.record_start_frame
        bay.close()
    played = play0 + onsets                                  # server frames at which clicks were played
    loop = detect(rec[:, 1], 0.25) + rec0                    # the bay's own loopback
    out = detect(rec[:, 0], 0.1) + rec0                      # the enhanced output

    def lags(found: np.ndarray) -> np.ndarray:
        res = []
        for f in found:
            before = played[played <= f]
            if len(before):
                res.append(f - before[-1])
        return np.asarray(res, float)

    lat, base = lags(out), lags(loop)
    # the output queue settles within its first half second (the burst released by the first alignment)
    settled = lat[(out[:len(lat)] - out[0]) >= 1.0 * RATE] if len(lat) else lat
    cards = outcome.report["cards"]
    target_ms = 1e3 * (frame + hop) / RATE + 10.0
    return {
        "setting": setting, "output_margin_s": margin_s, "batch_s": batch_s, "frame_samples": frame, "hop_samples": hop, "jack_period_samples": period,
        "n_clicks": int(len(lat)),
        "latency_ms_median": float(1e3 * np.median(lat) / RATE) if len(lat) else None,
        "latency_ms_max": float(1e3 * np.max(lat) / RATE) if len(lat) else None,
        "latency_ms_max_after_first_1_s": float(1e3 * np.max(settled) / RATE) if len(settled) else None,
        "baseline_loopback_ms": float(1e3 * np.median(base) / RATE) if len(base) else None,
        "target_ms": target_ms,
        "engine_output_latency_ms": 1e3 * outcome.report["stream"]["output_latency_s"],
        "n_underflows": cards["output"]["n_underflows"],
        "n_overflows": sum(c["n_overflows"] for c in cards["inputs"]),
        "n_dropped_output_samples": cards["output"]["n_dropped_samples"],
        "n_handouts": cards.get("n_handouts"),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration-s", type=float, default=20.0, help="click train length per setting")
    ap.add_argument("--batch-s", type=float, action="append", default=[], metavar="S",
                    help="also the low-latency setting (10 ms margin) with `live --batch-s S` (repeat)")
    ap.add_argument("--only-batches", action="store_true", help="only the --batch-s runs")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    results = [] if args.only_batches else [
        measure(name, frame, hop, period, args.duration_s, margin)
        for margin in (0.01, 0.0) for name, frame, hop, period in (("default", 1024, 256, 256),
                                                                    ("low-latency", 512, 128, 128))]
    results += [measure("low-latency", 512, 128, 128, args.duration_s, 0.01, batch_s=b) for b in args.batch_s]
    for r in results:
        print(f"{r['setting']:>12} ({r['frame_samples']}/{r['hop_samples']}, JACK period {r['jack_period_samples']}, "
              f"output margin {1e3 * r['output_margin_s']:g} ms"
              + (f", batches of {1e3 * r['batch_s']:g} ms" if r["batch_s"] else "") + "): "
              f"latency median {r['latency_ms_median']:.1f} ms, max {r['latency_ms_max_after_first_1_s']:.1f} ms after "
              f"the first 1 s of output ({r['latency_ms_max']:.1f} ms before) over "
              f"{r['n_clicks']} clicks; target {r['target_ms']:.1f} ms; server loopback alone "
              f"{r['baseline_loopback_ms']:.1f} ms; underflows {r['n_underflows']}, overflows {r['n_overflows']}")
    print(json.dumps({"live_latency": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
