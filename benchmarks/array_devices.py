"""Array devices in the stream (``--arrays``): each mic a channel of its own, against the same recordings with
each array mixed down to one channel (the baseline, same process).

The scene: two asynchronous 4-mic arrays (10 cm squares, the second turned 90 degrees, started 0.3 s late) and a
phone (0.12 s late) in a pyroomacoustics room (5 x 6 x 3 m, RT60 0.3 s, image order 12), the ``meeting_table``
talker at (2.0, 3.8, 1.3) m, white sensor noise at ``--snr-db`` per mic against the mean talker power. For each
estimator and SNR: SI-SDR of both runs against the dry talker, and every channel's median and 90th-percentile
error against its direct-path TOA (after 2 s). One JSON line at the end.

    .venv/bin/python benchmarks/array_devices.py                      # kalman and tracks at 0 and 15 dB (~1 min)
    .venv/bin/python benchmarks/array_devices.py --snr-db 5 --estimators tracks
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
from pathlib import Path

import numpy as np
import soundfile as sf

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from stream.scoring import metrics  # noqa: E402
from stream.config import EngineConfig  # noqa: E402
from stream.run import run_replay  # noqa: E402

FS = 16000
C = 343.0
SQUARE = 0.05 * np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
TURN = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], float)
OFFSET_S = {"A": 0.0, "B": 0.3, "phone": 0.12}


def toml_rows(points_m: np.ndarray) -> str:
    """``[[x, y, z], ...]`` of an arrays file's ``mics_m``."""
    return "[" + ", ".join(f"[{v[0]:.4f}, {v[1]:.4f}, {v[2]:.4f}]" for v in points_m) + "]"


def simulate(folder: Path, *, snr_db: float, seed: int = 0, rt60_s: float = 0.3):
    """Write A.wav, B.wav, phone.wav and arrays.toml; return the dry talker and every channel's true TOA."""
    import pyroomacoustics as pra
    rng = np.random.default_rng(seed)
    clean, fs = sf.read(REPO / "replay_fixtures/meeting_table/truth/clean.flac", dtype="float64")
    dims = [5.0, 6.0, 3.0]
    e_abs, max_order = pra.inverse_sabine(rt60_s, dims)
    room = pra.ShoeBox(dims, fs=FS, materials=pra.Material(e_abs), max_order=min(max_order, 12))
    talker = np.array([2.0, 3.8, 1.3])
    room.add_source(talker, signal=clean)
    local = {"A": SQUARE, "B": SQUARE @ TURN.T, "phone": np.zeros((1, 3))}
    centre = {"A": np.array([1.5, 2.5, 0.8]), "B": np.array([3.2, 2.6, 0.8]), "phone": np.array([2.4, 2.2, 0.8])}
    mics = np.vstack([centre[k] + local[k] for k in local])
    room.add_microphone_array(mics.T)
    room.simulate()
    x = room.mic_array.signals[:, :len(clean)]
    x = x + np.sqrt(np.mean(x ** 2) / 10 ** (snr_db / 10)) * rng.standard_normal(x.shape)
    x *= 0.5 / np.abs(x).max()
    cols = {"A": slice(0, 4), "B": slice(4, 8), "phone": slice(8, 9)}
    for k in local:
        sf.write(folder / f"{k}.wav", x[cols[k]].T[int(OFFSET_S[k] * FS):].astype(np.float32), FS, subtype="FLOAT")
    (folder / "arrays.toml").write_text("".join(f'[[array]]\nname = "{k}"\nmics_m = {toml_rows(local[k])}\n\n'
                                                for k in ("A", "B")))
    toa = np.linalg.norm(mics - talker, axis=1) / C - np.repeat([OFFSET_S[k] for k in local], [4, 4, 1])
    return clean.astype(np.float32), toa - toa[0]


def run(folder: Path, clean: np.ndarray, toa_true: np.ndarray, *, estimator: str, arrays: bool) -> dict:
    cfg = EngineConfig(plots=False, progress=False, estimator=estimator,
                       arrays=str(folder / "arrays.toml") if arrays else None)
    out = folder / f"{estimator}_{'arrays' if arrays else 'mixed'}"
    outcome = run_replay([folder / "A.wav", folder / "B.wav", folder / "phone.wav"], out, config=cfg)
    y = sf.read(out / "enhanced.wav", dtype="float32")[0]
    n = min(len(y), len(clean))
    est, _ = metrics.align_to_reference(y[:n], clean[:n], max_lag_samples=800)
    row = {"si_sdr_db": round(float(metrics.si_sdr_db(est, clean[:n])), 2),
           "channels": outcome.report["stream"]["channels"]}
    if arrays:
        t, toa, _ = outcome.pipeline.toa_track()
        err = np.abs(toa[t > 2.0] - toa_true)
        row["toa_err_ms_median"] = (1e3 * np.median(err, axis=0)).round(3).tolist()
        row["toa_err_ms_p90"] = (1e3 * np.percentile(err, 90, axis=0)).round(3).tolist()
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--snr-db", default="0,15", help="sensor SNRs per mic, comma-separated (default 0,15)")
    ap.add_argument("--estimators", default="kalman,tracks")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    logging.disable(logging.WARNING)
    results: dict = {}
    with tempfile.TemporaryDirectory(prefix="array_devices_") as tmp:
        for snr in [float(v) for v in args.snr_db.split(",")]:
            folder = Path(tmp) / f"snr{snr:g}"
            folder.mkdir()
            clean, toa_true = simulate(folder, snr_db=snr, seed=args.seed)
            for est in args.estimators.split(","):
                mixed = run(folder, clean, toa_true, estimator=est, arrays=False)
                arr = run(folder, clean, toa_true, estimator=est, arrays=True)
                results[f"{est}_{snr:g}dB"] = {"mixed_down": mixed, "arrays": arr,
                                                "gain_db": round(arr["si_sdr_db"] - mixed["si_sdr_db"], 2)}
                print(f"{est:7s} {snr:5g} dB: arrays {arr['si_sdr_db']:6.2f} dB, mixed down {mixed['si_sdr_db']:6.2f} "
                      f"dB, worst channel median TOA error {max(arr['toa_err_ms_median']):.3f} ms", file=sys.stderr)
    print(json.dumps({"benchmark": "array_devices", "seed": args.seed, "results": results}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
