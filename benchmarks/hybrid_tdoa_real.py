"""Real-world Part A of the hybrid-TDOA calibration paper (arXiv 2403.05791, Fig. 5a) on recorded data.

For M = 4, 6, 8, 10 mics, every case of the authors' selection (``DIR/cases.json``, rule
``|mean sigma_S - mean sigma_M| < 1e-5 s``) on every recording ``DIR/recNN.npz``, solved by the hybrid method and
by the TDOA-M + odometry baseline from the paper's random initial value (all mic and event positions uniform
in x [-0.8, 0.8], y [0, 2], z [-1, 0] m, offsets and drifts 0); restarts after a bad verdict are the solver's
own and count in the solve time. Location error: RMS over mics 2..M in the frame of mics 1-3 (as the authors).

Prints one JSON line ``{"M4": {"hybrid": {...}, "baseline": {...}}, ...}`` with per method ``cases``,
``conv_rate`` (verdict ``converged``), ``wrong_min_rate`` (converged with error > 0.5 m), ``median_m``, ``iqr_m``
(over converged runs), ``median_solve_s`` (wall clock; plus ``median_solve_cpu_s``, the thread's CPU time,
which is what a shared machine cannot inflate), ``p90_solve_s``, ``median_all_m`` and ``median_chi2_per_dof``
(all cases; chi-square of the kept measurements), and what the solver rejected as gross errors:
``cases_with_rejections`` and ``rejected`` (counts per kind over all cases).

``--cases partC_caseE`` (or any other Part C list of ``cases.json``; those are M = 6) runs that list instead
of Part A: case E is every selection of every recording, gross errors included (Part A's selection rule keeps
recording 1, whose emission interval ``dt[2]`` is about 1 ms off, out). ``--cases all`` runs every selection
``(i, j, k)`` of every recording at each M of ``--mics``. ``--recs 1`` keeps only the cases of those
recordings.

    python benchmarks/hybrid_tdoa_real.py --data ../shared/data/hybrid_tdoa_real [--max-cases 20]
    python benchmarks/hybrid_tdoa_real.py --data ../shared/data/hybrid_tdoa_real --cases partC_caseE
    python benchmarks/hybrid_tdoa_real.py --data ../shared/data/hybrid_tdoa_real --cases all --recs 1
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
REJECTED_KINDS = ("interval", "tdoa_events", "tdoa_mics", "odometry")


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


def summarise(errors: list[float], verdicts: list[str], times: list[float], cpu_times: list[float],
              rejected: list[dict[str, int]], chi2: list[float]) -> dict:
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
        "median_chi2_per_dof": round(float(np.median(chi2)), 3) if len(chi2) else None,
        "cases_with_rejections": int(sum(1 for r in rejected if sum(r.values()))),
        "rejected": {kind: int(sum(r.get(kind, 0) for r in rejected)) for kind in REJECTED_KINDS},
    }


def rejected_counts(res) -> dict[str, int]:
    """Rejected measurements of one solve by kind (``CalibrationResult.rejected``; the solver before it had
    only ``outliers_tdoa_*``)."""
    rej = getattr(res, "rejected", None)
    if rej is None:
        return {"tdoa_events": int(res.outliers_tdoa_events.sum()), "tdoa_mics": int(res.outliers_tdoa_mics.sum())}
    return {kind: sum(1 for r in rej if r.kind == kind) for kind in REJECTED_KINDS}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, type=pathlib.Path, help="folder with recNN.npz and cases.json")
    ap.add_argument("--max-cases", type=int, default=None, help="per M, evenly spaced subset (development)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--methods", default="hybrid,baseline")
    ap.add_argument("--mics", default="4,6,8,10", help="Part A and all")
    ap.add_argument("--cases", default="partA",
                    help="partA (default), all (every selection), or a Part C list of cases.json, e.g. partC_caseE")
    ap.add_argument("--recs", default=None, help="only these recordings, e.g. 1,2")
    args = ap.parse_args(argv)
    cases = json.loads((args.data / "cases.json").read_text())
    recs = {}
    for f in sorted(args.data.glob("rec*.npz")):
        with np.load(f) as z:
            recs[int(z["rec_id"])] = {k: z[k] for k in z.files}
    rng = np.random.default_rng(args.seed)
    methods = args.methods.split(",")
    out = {}
    keep = set(recs) if args.recs is None else {int(v) for v in args.recs.split(",")} & set(recs)
    mic_numbers = [int(v) for v in args.mics.split(",")]
    if args.cases == "partA":
        lists = [(f"M{m}", m, cases[f"partA_M{m}"]) for m in mic_numbers]
    elif args.cases == "all":
        every = [{"rec_id": r, "i": i, "j": j, "k": k} for r in sorted(recs)
                 for i in range(1, 7) for j in range(1, 7) for k in range(1, 7)]
        lists = [(f"all_M{m}", m, every) for m in mic_numbers]
    elif args.cases in cases and args.cases.startswith("partC"):
        lists = [(f"{args.cases}_M6", 6, cases[args.cases])]
    else:
        raise SystemExit(f"--cases {args.cases!r}: 'partA', 'all' or one of the Part C lists "
                         f"{sorted(c for c in cases if c.startswith('partC'))}")
    for key, m, lst in lists:
        lst = [c for c in lst if c["rec_id"] in keep]
        if args.max_cases is not None and len(lst) > args.max_cases:
            lst = [lst[t] for t in np.linspace(0, len(lst) - 1, args.max_cases).astype(int)]
        acc = {meth: ([], [], [], [], [], []) for meth in methods}
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
                acc[meth][4].append(rejected_counts(res))
                acc[meth][5].append(res.chi2_per_dof)
        out[key] = {meth: summarise(*acc[meth]) for meth in methods}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
