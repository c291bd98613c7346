"""Enhancement on the replay fixtures: Kalman-steered delay-and-sum against delay-and-sum steered by
the true TOA on the synchronous signals, equal against adaptive weights, and the best single device.

Runs every fixture in ``--fixtures`` (default: the shipped ones) through the full replay path once
per weighting and prints a table, then one JSON line with the figures (SI-SDR in dB, STOI).
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stream.config import EngineConfig  # noqa: E402
from stream.run import run_replay  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--fixtures", nargs="*", default=None, help="fixture folders (default: replay_fixtures/*)")
    ap.add_argument("--estimator", default="kalman")
    args = ap.parse_args(argv)
    folders = [Path(f) for f in args.fixtures] if args.fixtures else sorted(
        p.parent for p in (ROOT / "replay_fixtures").glob("*/fixture.toml"))
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for folder in folders:
            row = {}
            for weighting in ("equal", "adaptive"):
                cfg = EngineConfig(estimator=args.estimator, weighting=weighting, plots=False, progress=False)
                out = run_replay([folder], Path(tmp) / f"{folder.name}_{weighting}", config=cfg)
                enh = out.report["metrics"]["enhancement"]
                toa = out.report["metrics"]["toa"]
                row[f"engine_{weighting}"] = enh["engine"]
                row[f"true_toa_sync_{weighting}"] = enh[f"true_toa_sync_{weighting}"]
                row["best_single_device"] = enh["best_single_device"]
                row["toa_rmse_samples"] = {k: v["rmse_samples"] for k, v in toa.items()}
            row["kalman_minus_true_sync_equal_db"] = (row["engine_equal"]["si_sdr_db"]
                                                      - row["true_toa_sync_equal"]["si_sdr_db"])
            row["kalman_minus_true_sync_adaptive_db"] = (row["engine_adaptive"]["si_sdr_db"]
                                                         - row["true_toa_sync_adaptive"]["si_sdr_db"])
            row["equal_minus_best_single_db"] = (row["engine_equal"]["si_sdr_db"]
                                                 - row["best_single_device"]["si_sdr_db"])
            row["adaptive_minus_best_single_db"] = (row["engine_adaptive"]["si_sdr_db"]
                                                    - row["best_single_device"]["si_sdr_db"])
            results[folder.name] = row
    print(f"{'fixture':<16}{'kalman eq':>10}{'true/sync eq':>13}{'kalman ad':>10}{'true/sync ad':>13}"
          f"{'best single':>12}   (SI-SDR dB)")
    for name, r in results.items():
        print(f"{name:<16}{r['engine_equal']['si_sdr_db']:>10.2f}{r['true_toa_sync_equal']['si_sdr_db']:>13.2f}"
              f"{r['engine_adaptive']['si_sdr_db']:>10.2f}{r['true_toa_sync_adaptive']['si_sdr_db']:>13.2f}"
              f"{r['best_single_device']['si_sdr_db']:>12.2f}")
    summary = {name: {k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()
                      if k.endswith("_db")} for name, r in results.items()}
    print(json.dumps({"estimator": args.estimator, "summary": summary, "details": results}, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
