"""The calibration's file formats: the beacon's odometry (CSV) and measured TDOAs with odometry (npz or JSON,
our own layout or the hybrid-TDOA real data's ``recNN.npz``)."""
from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path
from typing import Sequence

import numpy as np

import estimators

from .errors import InputFileError

_COLUMNS = {"dx": ("dx", "dx_m"), "dy": ("dy", "dy_m"), "dz": ("dz", "dz_m"),
            "interval": ("interval", "interval_s", "dt", "dt_s")}


def load_odometry_csv(path: str | Path, *, interval_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Read the beacon's odometry: one row per step between consecutive chirps.

    Header ``dx_m,dy_m,dz_m,interval_s`` (also ``dx,dy,dz,dt``); row ``j`` is the displacement from chirp
    ``j`` to chirp ``j + 1`` in metres (odometry frame) and the time between their emissions in seconds.
    Without an interval column every interval is ``interval_s``. Empty cells are NaN (missing odometry).

    Returns
    -------
    odometry_m : ndarray, shape (n_steps, 3)
    interval_s : ndarray, shape (n_steps,)
    """
    path = Path(path)
    try:
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
    except OSError as err:
        raise InputFileError(f"Odometry file {path} cannot be read ({err}).") from None
    rows = [r for r in rows if r and not r[0].lstrip().startswith("#")]
    if len(rows) < 3:
        raise InputFileError(f"Odometry file {path} needs a header and at least 2 steps (3 chirps).")
    header = [h.strip().lower() for h in rows[0]]
    col = {}
    for key, names in _COLUMNS.items():
        hits = [header.index(n) for n in names if n in header]
        if hits:
            col[key] = hits[0]
    missing = [k for k in ("dx", "dy", "dz") if k not in col]
    if missing:
        raise InputFileError(f"Odometry file {path} has no column {missing[0]}_m; the header must be "
                             "dx_m,dy_m,dz_m[,interval_s].")
    if "interval" not in col and interval_s is None:
        raise InputFileError(f"Odometry file {path} has no interval_s column; give the chirp interval "
                             "(--chirp-interval-s).")

    def num(cell: str) -> float:
        cell = cell.strip()
        return float(cell) if cell else float("nan")

    try:
        odo = np.array([[num(r[col["dx"]]), num(r[col["dy"]]), num(r[col["dz"]])] for r in rows[1:]])
        iv = (np.array([num(r[col["interval"]]) for r in rows[1:]]) if "interval" in col
              else np.full(len(rows) - 1, float(interval_s)))
    except (ValueError, IndexError) as err:
        raise InputFileError(f"Odometry file {path} has a malformed row ({err}).") from None
    if not np.all(np.isfinite(iv) & (iv > 0)):
        raise InputFileError(f"Odometry file {path}: every interval must be a positive number of seconds.")
    return odo, iv


@dataclasses.dataclass(frozen=True)
class Measurements:
    """A calibration problem read from a file, with its ground truth when the file has one."""

    problem: estimators.HybridTdoaProblem
    truth_positions_m: np.ndarray | None
    device_names: tuple[str, ...]
    source: str


# the authors' M = 6 selection with i = j = k = 1 (benchmarks/hybrid_tdoa_real.py): arrays 1, 2, 3, then 2, 3, 3
SHARED_DEFAULT_MICS = (0, 6, 12, 9, 13, 15)


def load_measurements(path: str | Path, *, mics: Sequence[int] | None = None, sigma_tdoa_s: float | None = None,
                      sigma_odo_m: float | None = None) -> Measurements:
    """Read measured TDOAs and odometry.

    Two formats:

    - ours (``.npz`` or ``.json``): ``tdoa_events_s`` (K-1, N) TDOA-S (optional), ``tdoa_mics_s`` (K, N) TDOA-M
      against device 0, ``odometry_m`` (K-1, 3), ``interval_s`` (K-1,), ``sigma_tdoa_s``, ``sigma_odo_m``, and
      optionally ``sigma_tdoa_mics_s``, ``speed_of_sound_m_s``, ``truth_positions_m`` (N, 3),
      ``device_names``; NaN (JSON null) marks a missed chirp.
    - the hybrid-TDOA real data (``recNN.npz`` of ``../shared/data/hybrid_tdoa_real``): ``tdoa_s``,
      ``tdoa_m_arr2/3``, ``S``, ``dt``; ``mics`` are global mic numbers (0-17), the first one of array 1
      (the reference; default: the authors' 6-mic case ``i = j = k = 1``).
    """
    path = Path(path)
    if not path.exists():
        raise InputFileError(f"Measurement file {path} does not exist.")
    try:
        if path.suffix.lower() == ".json":
            data = {k: (np.array(v, dtype=float) if isinstance(v, list) and k != "device_names" else v)
                    for k, v in json.loads(path.read_text()).items()}
        else:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
    except (OSError, ValueError, json.JSONDecodeError) as err:
        raise InputFileError(f"Measurement file {path} cannot be read ({err}).") from None
    try:
        if "tdoa_m_arr2" in data:
            return _shared_measurements(data, path, mics, sigma_tdoa_s, sigma_odo_m)
        return _own_measurements(data, path, sigma_tdoa_s, sigma_odo_m)
    except KeyError as err:
        raise InputFileError(f"Measurement file {path} lacks the entry {err}; see `adhoc-array calibrate -h` "
                             "for the format.") from None
    except ValueError as err:
        raise InputFileError(f"Measurement file {path} is inconsistent: {err}.") from None


def _own_measurements(d: dict, path: Path, sigma_tdoa_s, sigma_odo_m) -> Measurements:
    tm = np.asarray(d["tdoa_mics_s"], float)
    te = d.get("tdoa_events_s")
    te = None if te is None or np.size(te) == 0 else np.asarray(te, float)
    problem = estimators.HybridTdoaProblem(
        tdoa_events_s=te, tdoa_mics_s=tm, odometry_m=np.asarray(d["odometry_m"], float),
        interval_s=np.asarray(d["interval_s"], float),
        sigma_tdoa_s=float(sigma_tdoa_s if sigma_tdoa_s is not None else d["sigma_tdoa_s"]),
        sigma_odo_m=float(sigma_odo_m if sigma_odo_m is not None else d["sigma_odo_m"]),
        speed_of_sound_m_s=float(d.get("speed_of_sound_m_s", estimators.SPEED_OF_SOUND_M_S)),
        sigma_tdoa_mics_s=(float(d["sigma_tdoa_mics_s"]) if d.get("sigma_tdoa_mics_s") is not None
                           and sigma_tdoa_s is None else None))
    truth = d.get("truth_positions_m")
    names = d.get("device_names")
    names = tuple(str(s) for s in np.asarray(names).tolist()) if names is not None else \
        tuple(f"dev{i}" for i in range(problem.n_mics))
    return Measurements(problem, None if truth is None else np.asarray(truth, float), names, str(path))


def _shared_measurements(d: dict, path: Path, mics, sigma_tdoa_s, sigma_odo_m) -> Measurements:
    glob = list(SHARED_DEFAULT_MICS if mics is None else mics)
    if len(glob) < 3 or len(set(glob)) != len(glob) or not all(0 <= g < 18 for g in glob):
        raise ValueError(f"mics={glob} must be >= 3 distinct global mic numbers in 0..17")
    ref = glob[0]
    if ref >= 6:
        raise ValueError(f"the first mic ({ref}) must belong to array 1 (0..5): TDOA-M exists only against it")
    n_ev = d["tdoa_s"].shape[0] + 1
    tm = np.full((n_ev, len(glob)), np.nan)
    for col, g in enumerate(glob):
        if 6 <= g < 12:
            tm[:, col] = d["tdoa_m_arr2"][ref, g - 6]
        elif g >= 12:
            tm[:, col] = d["tdoa_m_arr3"][ref, g - 12]
    problem = estimators.HybridTdoaProblem(
        tdoa_events_s=d["tdoa_s"][:, glob], tdoa_mics_s=tm, odometry_m=np.diff(d["S"], axis=0),
        interval_s=d["dt"][1:], sigma_tdoa_s=float(sigma_tdoa_s if sigma_tdoa_s is not None else d["sigma_tdoa"]),
        sigma_odo_m=float(sigma_odo_m if sigma_odo_m is not None else d["sigma_odo"]),
        speed_of_sound_m_s=float(d["c"]))
    names = tuple(f"a{g // 6 + 1}m{g % 6 + 1}" for g in glob)
    return Measurements(problem, np.asarray(d["mic_pos_s"], float)[glob], names, str(path))


# ----------------------------------------------------------------------------------------------------------------
# Solving: problem -> Geometry (pure; runs in the worker)
# ----------------------------------------------------------------------------------------------------------------
