"""Simulations of the hybrid-TDOA calibration paper (arXiv 2403.05791, Sec. III, Table I, Fig. 3, Table II).

Two trajectories as in the paper: 3x3x3 m with 8 events (cube corners) and 2x6x2 m with 10 events
(``--trajectories 1,2,3`` adds the authors' code's third one, 4x4x2 m with 14 events, which their published
medians pool). True mics
uniform in the trajectory box, ``|tau_i - tau_0| <= 0.1 s``, ``|delta_i| <= 1e-4``, intervals uniform in [0, 10] s,
c = 340 m/s, sigma_odo = 0.01 m. Runs per trajectory: 200 (``--quick``: 20); both trajectories pooled.

- Part A: N = 4, 6, 8, 10, sigma_tdoa = 0.1 ms, random initial values (all mic and event positions uniform in
  the trajectory box, offsets and drifts 0).
- Part B: N = 6, initial value = truth + N(0, sigma_init^2) per coordinate, sigma_init = 0/1/2/3 m (trajectory 1)
  and 0/2/4/6 m (trajectory 2).
- Part C: N = 6, sigma_tdoa = 0.05 / 0.1 / 0.5 ms, random initial values.
- Part D / Table II: CRLB at the Part C settings, both as the authors compute it (rotate-only for the hybrid,
  mic-frame parameterisation for the baseline) and with the full Jacobian of the frame change; aggregated as
  the authors do (mean after removing Tukey outliers) and as a median.
- Scale: N = 64 mics, K = 200 events: solve time from the built-in initialisation and from a random one.
- Solver comparison: our sparse LM against ``scipy.optimize.least_squares(method='trf', loss='soft_l1',
  x_scale='jac', jac_sparsity=...)`` from the same start, small (N=10, K=14) and large (N=64, K=200).

Box plots (location, offset, drift errors of converged runs, log scale) go to ``--out``/part{A,B,C}.png. One
JSON line with per setting and method: cases, conv_rate, wrong_min_rate (converged with location error
> 0.5 m), median / IQR of location (m), offset (ms) and drift (ppm) errors, median solve time (s).

    python benchmarks/hybrid_tdoa_sim.py --out out/hybrid_tdoa_sim [--quick]
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import pathlib  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from estimators import hybrid_tdoa as ht  # noqa: E402

C_M_S = 340.0
SIGMA_ODO_M = 0.01
WRONG_MIN_M = 0.5
TRAJECTORIES = {
    1: (3.0 * np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 1, 1], [0, 0, 1], [1, 0, 1], [1, 1, 1]],
                       float), np.array([3.0, 3.0, 3.0])),
    2: (np.array([[0, 0, 0], [2, 0, 0], [2, 2, 0], [2, 4, 0], [2, 6, 0], [2, 6, 2], [2, 4, 2], [2, 2, 2], [2, 0, 2],
                  [0, 0, 2]], float), np.array([2.0, 6.0, 2.0])),
    # not in the paper's text, but pooled with 1 and 2 by the authors' sim_main.m / DataAnalysis.m
    3: (2.0 * np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 2, 0], [0, 2, 0], [-1, 2, 0], [-1, 1, 0], [-1, 0, 0],
                        [-1, 0, 1], [-1, 1, 1], [-1, 2, 1], [0, 2, 1], [1, 2, 1], [1, 1, 1]], float),
        np.array([4.0, 4.0, 2.0])),
}
BOX_LOW_M = {1: (0.0, 0.0, 0.0), 2: (0.0, 0.0, 0.0), 3: (-2.0, 0.0, 0.0)}
SIGMA_INIT_M = {1: (0.0, 1.0, 2.0, 3.0), 2: (0.0, 2.0, 4.0, 6.0), 3: (0.0, 2.0, 4.0, 6.0)}


def make_case(traj: int, n_mics: int, sigma_tdoa_s: float, rng: np.random.Generator):
    events, box = TRAJECTORIES[traj]
    offsets = rng.uniform(-0.1, 0.1, n_mics)
    offsets[0] = 0.0
    mics = np.asarray(BOX_LOW_M[traj]) + rng.random((n_mics, 3)) * box
    truth = ht.Scene(mics, events, offsets, rng.uniform(-100.0, 100.0, n_mics))
    problem = ht.simulate_problem(truth, 10.0 * rng.random(len(events) - 1), sigma_tdoa_s=sigma_tdoa_s,
                                  sigma_odo_m=SIGMA_ODO_M, rng=rng, speed_of_sound_m_s=C_M_S)
    return problem, truth


def run_solves(problem, truth, init, rng) -> dict:
    out = {}
    for method in ("hybrid", "baseline"):
        t0, c0 = time.perf_counter(), time.thread_time()
        res = ht.solve(problem, method=method, init=init, rng=rng)
        wall, cpu = time.perf_counter() - t0, time.thread_time() - c0
        err = ht.mic_frame_error(res, truth)
        out[method] = (err["location_m"], err["offset_s"] * 1e3, err["drift_ppm"], res.verdict, wall, cpu)
    return out


def summarise(rows: list) -> dict:
    a = np.array([r[:3] for r in rows], float)
    conv = np.array([r[3] == "converged" for r in rows])
    wall = np.array([r[4] for r in rows])
    cpu = np.array([r[5] for r in rows])
    out = {"cases": len(rows), "conv_rate": round(float(conv.mean()), 4)}
    ac = a[conv]
    out["wrong_min_rate"] = round(float(np.mean(ac[:, 0] > WRONG_MIN_M)), 4) if len(ac) else None
    for k, name in enumerate(("loc_m", "off_ms", "dri_ppm")):
        if len(ac):
            q1, q2, q3 = np.percentile(ac[:, k], [25, 50, 75])
            out[f"median_{name}"] = float(f"{q2:.4g}")
            out[f"iqr_{name}"] = float(f"{q3 - q1:.4g}")
    out["median_solve_s"] = round(float(np.median(wall)), 5)
    out["median_solve_cpu_s"] = round(float(np.median(cpu)), 5)
    return out


def boxplot(path: pathlib.Path, title: str, labels: list[str], data: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    for k, (ylabel, ax) in enumerate(zip(("Loc. err. (m)", "Off. err. (ms)", "Dri. err. (ppm)"), axes)):
        for m, (method, color) in enumerate((("hybrid", "tab:red"), ("baseline", "tab:blue"))):
            vals = [np.array([r[k] for r in data[lab][method] if r[3] == "converged"]) for lab in labels]
            vals = [np.maximum(v, 1e-12) if len(v) else np.array([np.nan]) for v in vals]
            pos = np.arange(len(labels)) * 3.0 + m
            bp = ax.boxplot(vals, positions=pos, widths=0.8, patch_artist=True, showfliers=True,
                            flierprops={"markersize": 2})
            for box in bp["boxes"]:
                box.set_facecolor(color)
                box.set_alpha(0.5)
            ax.plot([], [], color=color, lw=6, alpha=0.5, label="hybrid (ours)" if m == 0 else "baseline TDOA-M")
        ax.set_xticks(np.arange(len(labels)) * 3.0 + 0.5, labels)
        ax.set_yscale("log")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(loc="upper left")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def tukey_mean(v: np.ndarray) -> float:
    """Mean after removing values beyond 1.5 IQR of the quartiles (the authors' ``DataAnalysis.m``)."""
    q1, q3 = np.percentile(v, [25, 75])
    lo, hi = q1 - 1.5 * (q3 - q1), q3 + 1.5 * (q3 - q1)
    return float(np.mean(v[(v > lo) & (v < hi)]))


def random_walk_scene(n_mics: int, n_events: int, rng: np.random.Generator):
    box = np.array([6.0, 6.0, 2.0])
    ev = np.zeros((n_events, 3))
    pos, vel = box / 2, np.zeros(3)
    for j in range(n_events):
        vel = 0.7 * vel + rng.normal(0.0, 0.25, 3) * np.array([1.0, 1.0, 0.3])
        pos = np.clip(pos + vel, 0.0, box)
        ev[j] = pos
    truth = ht.Scene(rng.random((n_mics, 3)) * box, ev, rng.uniform(-0.1, 0.1, n_mics),
                     rng.uniform(-100.0, 100.0, n_mics))
    problem = ht.simulate_problem(truth, rng.uniform(1.0, 5.0, n_events - 1), sigma_tdoa_s=1e-4,
                                  sigma_odo_m=SIGMA_ODO_M, rng=rng, speed_of_sound_m_s=C_M_S)
    return problem, truth, box


def scale_test(rng: np.random.Generator, n_mics: int = 64, n_events: int = 200) -> dict:
    problem, truth, box = random_walk_scene(n_mics, n_events, rng)
    out = {}
    init = ht.random_initial_scene(n_mics, n_events, rng=rng, low_m=(0, 0, 0), high_m=tuple(box))
    for name, ini in (("builtin_init", None), ("random_init", init)):
        t0 = time.perf_counter()
        res = ht.solve(problem, init=ini, rng=rng)
        out[name] = {"solve_s": round(time.perf_counter() - t0, 3), "verdict": res.verdict,
                     "n_starts": res.n_starts_used, "n_iterations": res.n_iterations,
                     "loc_err_m": round(ht.mic_frame_error(res, truth)["location_m"], 4)}
    return out


def compare_scipy(rng: np.random.Generator) -> dict:
    """Our LM vs scipy.optimize.least_squares (trf, soft_l1, x_scale='jac'; analytic Jacobian, sparse with
    tr_solver='lsmr' for the large problem) from the same start (built-in initialisation) on the same
    residuals; uses the solver's private layout to share the residual function."""
    import scipy.optimize

    out = {}
    small = make_case(2, 10, 1e-4, rng)[0]
    big = random_walk_scene(64, 200, rng)[0]
    for name, problem in (("N10_K10", small), ("N64_K200", big)):
        rot = ht._odometry_gauge(problem)
        lay = ht._Layout(problem, "hybrid", "sound", problem.odometry_m @ rot.T)
        p0 = ht._apply_gauge(lay, ht._smart_init(lay, problem.odometry_m @ rot.T, "hybrid", rng, 700))
        free = lay.free

        def fun(z):
            p = p0.copy()
            p[free] = z
            return lay.residuals(p)

        def jac(z):
            p = p0.copy()
            p[free] = z
            j = lay.jacobian(p)
            return j if lay.dense else j.tocsr()

        reps = 5 if name == "N10_K10" else 1
        ht._levenberg_marquardt(lay, p0, loss="soft_l1", f_scale=3.0, max_iterations=2)  # numba: load its kernels
        t0 = time.perf_counter()
        for _ in range(reps):
            run = ht._levenberg_marquardt(lay, p0, loss="soft_l1", f_scale=3.0, max_iterations=100)
        t_ours = (time.perf_counter() - t0) / reps
        t0 = time.perf_counter()
        for _ in range(reps):
            sol = scipy.optimize.least_squares(fun, p0[free], jac=jac, method="trf", loss="soft_l1", f_scale=3.0,
                                               x_scale="jac", tr_solver="exact" if lay.dense else "lsmr",
                                               max_nfev=200)
        t_scipy = (time.perf_counter() - t0) / reps
        cost_ours = ht._loss(lay.residuals(run.p), "soft_l1", 3.0)[0]
        out[name] = {"ours_s": round(t_ours, 4), "ours_iterations": run.n_iterations,
                     "ours_cost": round(cost_ours, 3), "scipy_trf_s": round(t_scipy, 4),
                     "scipy_nfev": int(sol.nfev), "scipy_cost": round(float(sol.cost), 3)}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("out/hybrid_tdoa_sim"))
    ap.add_argument("--quick", action="store_true", help="20 runs per trajectory instead of 200")
    ap.add_argument("--runs", type=int, default=None, help="runs per trajectory (overrides --quick)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--parts", default="A,B,C,D,scale,scipy")
    ap.add_argument("--trajectories", default="1,2",
                    help="the paper's two (default); 1,2,3 pools the third one as the authors' code does")
    args = ap.parse_args(argv)
    runs = args.runs if args.runs is not None else (20 if args.quick else 200)
    parts = set(args.parts.split(","))
    args.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    trajs = tuple(int(t) for t in args.trajectories.split(","))
    result: dict = {"runs_per_trajectory": runs, "trajectories": list(trajs)}

    def random_init(traj, problem):
        lo = np.asarray(BOX_LOW_M[traj])
        return ht.random_initial_scene(problem.n_mics, problem.n_events, rng=rng, low_m=tuple(lo),
                                       high_m=tuple(lo + TRAJECTORIES[traj][1]))

    if "A" in parts:
        data = {}
        for n in (4, 6, 8, 10):
            rows = {"hybrid": [], "baseline": []}
            for traj in trajs:
                for _ in range(runs):
                    problem, truth = make_case(traj, n, 1e-4, rng)
                    res = run_solves(problem, truth, random_init(traj, problem), rng)
                    for m in rows:
                        rows[m].append(res[m])
            data[f"N{n}"] = rows
        result["partA"] = {k: {m: summarise(v[m]) for m in v} for k, v in data.items()}
        boxplot(args.out / "partA.png", "Part A: number of mics (sigma_tdoa = 0.1 ms, random init)",
                list(data), data)
    if "B" in parts:
        data = {}
        for level in range(4):
            rows = {"hybrid": [], "baseline": []}
            for traj in trajs:
                sig = SIGMA_INIT_M[traj][level]
                for _ in range(runs):
                    problem, truth = make_case(traj, 6, 1e-4, rng)
                    init = ht.Scene(truth.mic_positions_m + rng.normal(0, sig, truth.mic_positions_m.shape),
                                    truth.event_positions_m + rng.normal(0, sig, truth.event_positions_m.shape))
                    res = run_solves(problem, truth, init, rng)
                    for m in rows:
                        rows[m].append(res[m])
            data["/".join(f"{SIGMA_INIT_M[t][level]:g}" for t in trajs)] = rows
        result["partB"] = {k: {m: summarise(v[m]) for m in v} for k, v in data.items()}
        boxplot(args.out / "partB.png", "Part B: initial-value noise sigma_init (m), traj 1 / traj 2", list(data),
                data)
    if "C" in parts or "D" in parts:
        data, crlbs = {}, {}
        for sig in (5e-5, 1e-4, 5e-4):
            rows = {"hybrid": [], "baseline": []}
            cr = {"hybrid": [], "baseline": []}
            for traj in trajs:
                for _ in range(runs):
                    problem, truth = make_case(traj, 6, sig, rng)
                    if "D" in parts:
                        for m in cr:
                            c = ht.crlb(problem, truth, method=m)
                            cr[m].append((c.location_std_m_authors, c.location_std_m, c.offset_std_s * 1e3,
                                          c.drift_std_ppm))
                    if "C" in parts:
                        res = run_solves(problem, truth, random_init(traj, problem), rng)
                        for m in rows:
                            rows[m].append(res[m])
            key = f"{sig:g}"
            data[key] = rows
            crlbs[key] = cr
        if "C" in parts:
            result["partC"] = {k: {m: summarise(v[m]) for m in v} for k, v in data.items()}
            boxplot(args.out / "partC.png", "Part C: TDOA noise sigma_tdoa (s), N = 6, random init", list(data), data)
        if "D" in parts:
            table = {}
            for k, cr in crlbs.items():
                table[k] = {}
                for m, v in cr.items():
                    a = np.array(v)
                    table[k][m] = {"loc_m_authors": round(tukey_mean(a[:, 0]), 4),
                                   "loc_m_full_jacobian": round(tukey_mean(a[:, 1]), 4),
                                   "off_ms": round(tukey_mean(a[:, 2]), 4), "dri_ppm": round(tukey_mean(a[:, 3]), 3),
                                   "loc_m_authors_median": round(float(np.median(a[:, 0])), 4),
                                   "loc_m_full_jacobian_median": round(float(np.median(a[:, 1])), 4)}
            result["tableII_crlb"] = table
    if "scale" in parts:
        result["scale_N64_K200"] = scale_test(rng)
    if "scipy" in parts:
        result["solver_comparison"] = compare_scipy(rng)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
