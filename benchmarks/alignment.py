"""Coarse alignment accuracy on the generated scenes: how far each device's coarse offset lands from the truth.

For every scene of ``benchmarks/scenes.py`` (built into ``--cache`` from ``--data`` when missing) and every device
``d >= 1``: the offset of device ``d`` against device 0 over the first alignment window, as the aligner's
pairwise step finds it (:func:`stream.offsets.coarse_offset`: energy-envelope lag, then the PHAT refine), and its
error to the nearer source (talker or noise) at the window's middle. The baseline, in the same run, is the
envelope lag alone (10 ms steps, no refine). The tracker searches ±12 ms (``max_tdoa_s``) around the coarse
offset: a device further off has no talker peak in its pairs (README, "What fails": "No talker track at all").

The last line is one JSON object: per layout and overall, the share of device alignments more than 1 / 2 / 5 /
10 ms off, for the refine and for the baseline.

Usage::

    python benchmarks/alignment.py --data ../shared/data --seeds 7,8,9,10,11
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import soundfile as sf
import soxr

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

import scenes as S  # noqa: E402
from stream import offsets as O  # noqa: E402
from stream.scoring.fixture import load_fixture  # noqa: E402

RATE_HZ = 16000
WINDOW_S = 8.0        # the aligner's default `align_window_s`
MAX_OFFSET_S = 4.0    # ... and `max_offset_s`
THRESHOLDS_MS = (1, 2, 5, 10)


def scene_errors(folder: Path) -> list[dict]:
    fx = load_fixture(folder)

    def load(d: int) -> np.ndarray:
        x, fs = sf.read(fx.devices[d].path, dtype="float32", always_2d=True)
        x = x[:, 0]
        return x if fs == RATE_HZ else soxr.resample(x, fs, RATE_HZ).astype(np.float32)

    w = int(WINDOW_S * RATE_HZ)
    ref = load(0)[:w]
    t = np.array([WINDOW_S / 2])
    toa = [fx.source_toa_at(s.name, t).ravel() for s in fx.sources]
    rows = []
    for d in range(1, len(fx.devices)):
        x = load(d)[:w + int(MAX_OFFSET_S * RATE_HZ)]
        truth = [(v[d] - v[0]) * RATE_HZ for v in toa]
        refined, _ = O.coarse_offset(ref, x, sample_rate_hz=RATE_HZ, max_offset_s=MAX_OFFSET_S)
        envelope = O.envelope_offset(ref, x, sample_rate_hz=RATE_HZ, max_offset_s=MAX_OFFSET_S)   # the baseline
        rows.append({"scene": folder.name, "device": d,
                     **{name: 1e3 * min(abs(o - tr) for tr in truth) / RATE_HZ
                        for name, o in (("refine", refined), ("envelope", envelope[0] if envelope else 0))}})
    return rows


def shares(rows: list[dict], key: str) -> dict:
    e = np.array([r[key] for r in rows])
    return {"n": int(len(e)), "median_ms": round(float(np.median(e)), 3),
            **{f"over_{m}ms": round(float(np.mean(e > m)), 4) for m in THRESHOLDS_MS}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data",
                    help="the shared data folder (speech and noise recordings)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp"),
                    help="scenes are built into CACHE/adhoc-array-scenes-sSEED")
    ap.add_argument("--seeds", default="7", help="comma-separated scene seeds")
    args = ap.parse_args()
    S.DATA = args.data
    rows = []
    for seed in (int(s) for s in args.seeds.split(",")):
        cache = args.cache / f"adhoc-array-scenes-s{seed}"
        cache.mkdir(parents=True, exist_ok=True)
        for _, _, scene in S.make_scenes(seed):
            rows += [{"seed": seed, **r} for r in scene_errors(S.built(scene, cache, args.data))]
        print(f"seed {seed}: {len(rows)} device alignments so far", flush=True)
    out = {}
    for layout in ("all", "table", "spread", "two_talkers", "moving"):
        sel = [r for r in rows if layout == "all" or layout in r["scene"]]   # "table": every kind at a table
        if sel:
            out[layout] = {"refine": shares(sel, "refine"), "envelope_only": shares(sel, "envelope")}
    for layout, v in out.items():
        r, e = v["refine"], v["envelope_only"]
        print(f"{layout:12s} refine  > 2 / 5 / 10 ms: {100 * r['over_2ms']:.1f} / {100 * r['over_5ms']:.1f} / "
              f"{100 * r['over_10ms']:.1f} %   envelope only: {100 * e['over_2ms']:.1f} / "
              f"{100 * e['over_5ms']:.1f} / {100 * e['over_10ms']:.1f} %  (n {r['n']})")
    print(json.dumps({"benchmark": "alignment", "seeds": args.seeds, "layouts": out}))


if __name__ == "__main__":
    main()
