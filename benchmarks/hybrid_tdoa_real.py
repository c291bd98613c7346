"""Real-world Part A of the hybrid-TDOA calibration paper (arXiv 2403.05791, Fig. 5a) on recorded data.

For M = 4, 6, 8, 10 mics, every case of the authors' selection (``DIR/cases.json``, rule
``|mean sigma_S - mean sigma_M| < 1e-5 s``) on every recording ``DIR/recNN.npz``, solved by the hybrid method and
by the TDOA-M + odometry baseline from the paper's random initial value (all mic and event positions uniform
in x [-0.8, 0.8], y [0, 2], z [-1, 0] m, offsets and drifts 0); restarts after a bad verdict are the solver's
own and count in the solve time. Location error: RMS over mics 2..M in the frame of mics 1-3 (as the authors).

Prints one JSON line ``{"M4": {"hybrid": {...}, "baseline": {...}}, ...}`` with per method ``cases``,
``conv_rate`` (verdict ``converged``), ``wrong_min_rate`` (converged with error > 0.5 m), ``median_m``, ``iqr_m``
(over converged runs), ``median_solve_s`` (wall clock; plus ``median_solve_cpu_s``, the thread's CPU time,
which is what a shared machine cannot inflate), ``p90_solve_s`` and ``median_all_m`` (all cases).

    python benchmarks/hybrid_tdoa_real.py --data ../shared/data/hybrid_tdoa_real [--max-cases 20]
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # small dense problems: threads only add overhead
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import pathlib  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from estimators.hybrid_tdoa import (  # noqa: E402
    HybridTdoaProblem,
    Scene,
    mic_frame_error,
    random_initial_scene,
    solve,
)

MIC_NUMBERS = (4, 6, 8, 10)
WRONG_MIN_M = 0.5


def mic_ids(m: int, i: int, j: int, k: int) -> np.ndarray:
    """The authors' selection matrix (rows = arrays 1..3, 0 = unused), ``real_main.m``."""
    mp = [1, 2, 3, 4, 5, 6, 1, 2, 3, 4, 5, 6]

    def w(a, d):  # Map(a + d), 1-based
        return mp[a + d - 1]

    if m == 4:
        return np.array([[i, 0], [j, 0], [k, w(k, 3)]])
    if m == 6:
        return np.array([[i, 0, 0], [j, w(j, 3), 0], [k, w(k, 1), w(k, 3)]])
    if m == 8:
        return np.array([[i, 0, 0, 0], [j, w(j, 1), w(j, 3), 0], [k, w(k, 1), w(k, 2), w(k, 3)]])
    if m == 10:
        return np.array([[i, 0, 0, 0, 0], [j, w(j, 1), w(j, 2), w(j, 3), 0],
                         [k, w(k, 1), w(k, 2), w(k, 3), w(k, 4)]])
    raise ValueError(f"{m=} must be one of {MIC_NUMBERS}")


def build_case(rec: dict, m: int, i: int, j: int, k: int) -> tuple[HybridTdoaProblem, Scene]:
    """Problem and ground truth (s-frame) of one case; solver mic order = column-major over ``mic_ids``."""
    ids = mic_ids(m, i, j, k)
    order = [(a, ids[a, col]) for col in range(ids.shape[1]) for a in range(3) if ids[a, col] > 0]
    glob = [6 * a + (mic - 1) for a, mic in order]
    n_ev = rec["src_pos_s"].shape[0]
    tdoa_m = np.full((n_ev, len(order)), np.nan)
    for col, (a, mic) in enumerate(order):
        if a == 1:
            tdoa_m[:, col] = rec["tdoa_m_arr2"][i - 1, mic - 1]
        elif a == 2:
            tdoa_m[:, col] = rec["tdoa_m_arr3"][i - 1, mic - 1]
    problem = HybridTdoaProblem(
        tdoa_events_s=rec["tdoa_s"][:, glob], tdoa_mics_s=tdoa_m, odometry_m=np.diff(rec["S"], axis=0),
        interval_s=rec["dt"][1:], sigma_tdoa_s=float(rec["sigma_tdoa"]), sigma_odo_m=float(rec["sigma_odo"]),
        speed_of_sound_m_s=float(rec["c"]))
    truth = Scene(rec["mic_pos_s"][glob], rec["src_pos_s"])
    return problem, truth


def summarise(errors: list[float], verdicts: list[str], times: list[float], cpu_times: list[float]) -> dict:
    e = np.asarray(errors)
    conv = np.asarray([v == "converged" for v in verdicts])
    ec = e[conv]
    q1, q3 = np.percentile(ec, [25, 75]) if len(ec) else (np.nan, np.nan)
    return {
        "cases": int(len(e)),
        "conv_rate": round(float(conv.mean()), 4) if len(e) else None,
        "wrong_min_rate": round(float(np.mean(ec > WRONG_MIN_M)), 4) if len(ec) else None,
        "median_m": round(float(np.median(ec)), 4) if len(ec) else None,
        "iqr_m": round(float(q3 - q1), 4) if len(ec) else None,
        "median_solve_s": round(float(np.median(times)), 5) if len(times) else None,
        "median_solve_cpu_s": round(float(np.median(cpu_times)), 5) if len(cpu_times) else None,
        "p90_solve_s": round(float(np.percentile(times, 90)), 5) if len(times) else None,
        "median_all_m": round(float(np.median(e)), 4) if len(e) else None,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, type=pathlib.Path, help="folder with recNN.npz and cases.json")
    ap.add_argument("--max-cases", type=int, default=None, help="per M, evenly spaced subset (development)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--methods", default="hybrid,baseline")
    ap.add_argument("--mics", default="4,6,8,10")
    args = ap.parse_args(argv)
    cases = json.loads((args.data / "cases.json").read_text())
    recs = {}
    for f in sorted(args.data.glob("rec*.npz")):
        with np.load(f) as z:
            recs[int(z["rec_id"])] = {k: z[k] for k in z.files}
    rng = np.random.default_rng(args.seed)
    methods = args.methods.split(",")
    out = {}
    for m in (int(v) for v in args.mics.split(",")):
        lst = [c for c in cases[f"partA_M{m}"] if c["rec_id"] in recs]
        if args.max_cases is not None and len(lst) > args.max_cases:
            lst = [lst[t] for t in np.linspace(0, len(lst) - 1, args.max_cases).astype(int)]
        acc = {meth: ([], [], [], []) for meth in methods}
        for c in lst:
            problem, truth = build_case(recs[c["rec_id"]], m, c["i"], c["j"], c["k"])
            init = random_initial_scene(problem.n_mics, problem.n_events, rng=rng)
            for meth in methods:
                t0, c0 = time.perf_counter(), time.thread_time()
                res = solve(problem, method=meth, init=init, rng=rng)
                dt, dc = time.perf_counter() - t0, time.thread_time() - c0
                acc[meth][0].append(mic_frame_error(res, truth)["location_m"])
                acc[meth][1].append(res.verdict)
                acc[meth][2].append(dt)
                acc[meth][3].append(dc)
        out[f"M{m}"] = {meth: summarise(*acc[meth]) for meth in methods}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
