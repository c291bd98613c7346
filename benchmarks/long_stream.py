"""Memory and per-hop time of a long stream: the engine must run for as long as a meeting lasts.

An 8-device, 16 kHz stream (frame 512, hop 128, the engine's default estimator) goes through the one stream
runner that replay and live use (:func:`stream.run.run_stream`, with the bounded per-frame history of live
and long streams), as fast as possible, from a looping source: 20 s of the speech-like 8-device scene of
``throughput.py`` (fractional delays, sensor noise), each device stamped in its own clock, repeated without
a seam. Figures (last stdout line, one JSON object):

- ``rss_mb_at_5_min`` and ``rss_mb_at_60_min``: the process's resident memory (``/proc/self/statm``) when
  5 and 60 minutes of audio have been streamed, and their difference (target: under 20 MB);
- ``hop_ms_p50/p99/p999/max`` over the first 10 minutes of audio (the pipeline's per-hop processing time,
  from its running histogram) against half the hop duration (target: p99.9 below it);
- ``baseline_rss_mb``: resident memory before the stream (imports, numba kernels), the same process;
  ``rss_mb_every_5_min``: the curve (the bounded history fills, halves and refills, so memory reaches its
  ceiling within the first minutes and stays there).

Run ``python benchmarks/long_stream.py`` (``--minutes 60``; ``--quick`` streams 12 minutes and reports the
5-minute and 12-minute memory instead).
"""
from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import pathlib  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from throughput import scene  # noqa: E402

from stream.config import EngineConfig  # noqa: E402
from stream.messages import Frame, FrameFlag  # noqa: E402
from stream.replay import DeviceInfo  # noqa: E402
from stream.run import run_stream  # noqa: E402

RATE, N_DEV, FRAME, HOP = 16000, 8, 512, 128
LOOP_S = 20.0
BLOCK_S = 0.05


def rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


class LoopSource:
    """A seamless loop of a multi-device scene for ``duration_s``, as fast as possible (a Source)."""

    live = False
    paced = False

    def __init__(self, audio: np.ndarray, duration_s: float, on_time=None) -> None:
        self.audio = audio
        self.n_total = int(duration_s * RATE)
        self.devices = [DeviceInfo(name=f"dev{d}", path=f"loop:{d}", sample_rate_hz=float(RATE))
                        for d in range(audio.shape[1])]
        self.active = self.devices
        self.on_time = on_time
        self._stop = False

    sample_rates_hz = property(lambda self: [float(RATE)] * len(self.devices))
    duration_s = property(lambda self: self.n_total / RATE)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        pass

    def stop(self) -> None:
        self._stop = True

    def __iter__(self):
        n_loop, block = len(self.audio), int(BLOCK_S * RATE)
        pos, seq = 0, 0
        while pos < self.n_total and not self._stop:
            n = min(block, self.n_total - pos)
            idx = (pos + np.arange(n)) % n_loop
            chunk = self.audio[idx]
            last = pos + n >= self.n_total
            for d in range(chunk.shape[1]):
                yield Frame(d, seq, pos, float(RATE), np.ascontiguousarray(chunk[:, d]),
                            flags=FrameFlag.LAST if last else FrameFlag.NONE)
            pos += n
            seq += 1
            if self.on_time is not None:
                self.on_time(pos / RATE)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=60.0, help="audio streamed (default 60)")
    ap.add_argument("--quick", action="store_true", help="12 minutes")
    ap.add_argument("--keep-all", action="store_true",
                    help="keep every per-frame record and the audio (as a replay of a short fixture does), to "
                         "compare with the bounded history")
    args = ap.parse_args(argv)
    minutes = 12.0 if args.quick else args.minutes
    logging.basicConfig(level=logging.ERROR)
    audio, _ = scene(N_DEV, RATE, LOOP_S, 7)
    cfg = EngineConfig(working_rate_hz=RATE, frame_samples=FRAME, hop_samples=HOP, plots=False, progress=False)
    baseline = rss_mb()
    marks: dict[str, float] = {}
    hop_stats: dict[str, float] = {}
    state: dict = {}
    t0 = time.perf_counter()

    every: list[float] = []

    def on_time(t_s: float) -> None:
        if t_s >= 300.0 * (len(every) + 1):
            every.append(round(rss_mb(), 1))
        for label, at in (("5", 300.0), ("end", minutes * 60.0)):
            if label not in marks and t_s >= at:
                marks[label] = rss_mb()
        if "10" not in hop_stats and t_s >= 600.0 and "pipeline" in state:
            ht = state["pipeline"].hop_times
            hop_stats.update({"10": 1, "p50": ht.percentile(50), "p99": ht.percentile(99),
                              "p999": ht.percentile(99.9), "max": ht.max_ms, "n": ht.n})

    def status(pipeline) -> None:   # keeps a handle on the pipeline (called once per wall second)
        state["pipeline"] = pipeline

    with tempfile.TemporaryDirectory(prefix="long_stream_") as tmp:
        outcome = run_stream(LoopSource(audio, minutes * 60.0, on_time), tmp, config=cfg, status=status,
                             status_every_s=0.5, handle_signals=False, history_cap=-1 if args.keep_all else None)
        wav_mb = pathlib.Path(tmp, "enhanced.wav").stat().st_size / 2**20
    wall = time.perf_counter() - t0
    ht = outcome.pipeline.hop_times
    if not hop_stats:
        hop_stats = {"p50": ht.percentile(50), "p99": ht.percentile(99), "p999": ht.percentile(99.9),
                     "max": ht.max_ms, "n": ht.n}
    half_hop_ms = 0.5e3 * HOP / RATE
    end_label = f"rss_mb_at_{minutes:g}_min"
    result = {
        "config": f"{N_DEV} devices, {RATE} Hz, frame {FRAME}, hop {HOP}, estimator {outcome.report['settings']['estimator']}",
        "minutes": minutes,
        "history": "everything kept" if args.keep_all else "bounded",
        "baseline_rss_mb": round(baseline, 1),
        "rss_mb_at_5_min": round(marks.get("5", float("nan")), 1),
        end_label: round(marks.get("end", rss_mb()), 1),
        "rss_growth_mb_5_to_end": round(marks.get("end", rss_mb()) - marks.get("5", float("nan")), 1),
        "rss_mb_every_5_min": every,
        "hop_ms_p50": round(hop_stats["p50"], 4), "hop_ms_p99": round(hop_stats["p99"], 4),
        "hop_ms_p999": round(hop_stats["p999"], 4), "hop_ms_max": round(hop_stats["max"], 3),
        "hops_in_stats": int(hop_stats["n"]),
        "half_hop_ms": half_hop_ms,
        "p999_over_half_hop": round(hop_stats["p999"] / half_hop_ms, 3),
        "hop_ms_p999_whole_stream": round(ht.percentile(99.9), 4),
        "hop_ms_max_whole_stream": round(ht.max_ms, 3),
        "enhanced_wav_mb": round(wav_mb, 1),
        "wall_s": round(wall, 1),
        "real_time_factor": round(wall / (minutes * 60.0), 4),
        "status": outcome.report["status"],
    }
    print(f"RSS: {result['baseline_rss_mb']} MB before, {result['rss_mb_at_5_min']} MB at 5 min, "
          f"{result[end_label]} MB at {minutes:g} min (growth {result['rss_growth_mb_5_to_end']} MB); per hop over "
          f"the first 10 min: p50 {result['hop_ms_p50']} ms, p99 {result['hop_ms_p99']} ms, "
          f"p99.9 {result['hop_ms_p999']} ms (half a hop: {half_hop_ms} ms); {wall:.0f} s wall")
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
