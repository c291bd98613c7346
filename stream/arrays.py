"""Multi-array calibration from recorded probe events: ``adhoc-array calibrate --method multi-array``.

Each array is one synchronous multichannel recording with a known internal geometry (its mics in its own
frame); the arrays are mutually asynchronous. A probe (a loudspeaker playing noise bursts) is heard at ``S``
places. For every array::

    multichannel file ─▶ probe onsets (energy above the noise floor) ─▶ GCC-PHAT of every mic pair per probe
        ─▶ TOA of each mic against the array's reference (least squares over all pairs)

the probes are matched across arrays by their onset pattern (the clocks differ by an unknown offset, so the
intervals between probes agree), and :func:`estimators.multi_array.calibrate_arrays` finds the arrays'
poses (maximum likelihood with anisotropic covariance; the rigid-body method with ``--multi-array-method
rigid_body``). Outputs: ``arrays.json`` (poses with standard deviations, fused probe positions, rejected
probes) and ``arrays.png``.

The arrays file (TOML)::

    speed_of_sound_m_s = 343.0          # optional
    sigma_tdoa_s = 2e-5                 # optional: the TDOA noise assumed for the covariances
    [[array]]
    name = "kitchen"
    file = "kitchen.wav"                # relative to the TOML file
    mics_m = [[0.0, 0.0, 0.0], [0.035, 0.0, 0.0], ...]   # in the array's own frame, metres
    reference_mic = 0                   # optional
"""
from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import soundfile as sf

from .config import load_toml
from .errors import ConfigError, InputFileError, why_unreadable

log = logging.getLogger(__name__)

SPEED_OF_SOUND_M_S = 343.0
ENVELOPE_HOP_S = 0.01


@dataclasses.dataclass(frozen=True)
class ArraySpec:
    """One synchronous array: its recording and its mics in its own frame."""

    name: str
    file: Path | None
    mics_m: np.ndarray
    reference_mic: int = 0


def load_arrays(path: str | Path, *, streaming: bool = False) -> tuple[list[ArraySpec], dict[str, Any]]:
    """The arrays of a TOML file (or of a folder holding ``arrays.toml``) and its top-level options.

    ``streaming``: the arrays of a stream (``arrays`` engine option), matched to the stream's devices by name:
    one array is enough, ``file`` is optional and two mics are enough (the calibration needs at least two
    arrays, each with a recording and 4 mics not in one plane)."""
    path = Path(path)
    if path.is_dir():
        path = path / "arrays.toml"
    data = load_toml(path)
    entries = data.get("array")
    need = 1 if streaming else 2
    if not isinstance(entries, list) or len(entries) < need:
        raise ConfigError(f"{path} must list at least {'one' if streaming else 'two'} [[array]] table"
                          f"{'' if streaming else 's'} (name, {'' if streaming else 'file, '}mics_m); "
                          f"it has {len(entries) if isinstance(entries, list) else 0}.")
    specs = []
    for k, e in enumerate(entries):
        try:
            mics = np.asarray(e["mics_m"], float)
            name = str(e["name"] if streaming else e.get("name", f"array{k}"))
            file = path.parent / str(e["file"]) if (not streaming or "file" in e) else None
        except (KeyError, TypeError, ValueError) as err:
            what = "name and mics_m" if streaming else "file and mics_m"
            raise ConfigError(f"{path}: [[array]] {k + 1} needs {what} (a list of [x, y, z] in "
                              f"metres) ({err}).") from None
        min_mics = 2 if streaming else 4
        if mics.ndim != 2 or mics.shape[1] != 3 or len(mics) < min_mics or not np.isfinite(mics).all():
            why = ("a multichannel device with one mic is a single mic" if streaming else
                   "a 3-D position from TDOAs needs 4 mics not in one plane")
            raise ConfigError(f"{path}: array '{name}' has mics_m of shape {mics.shape}; it needs at least "
                              f"{min_mics} mics as finite [x, y, z] rows ({why}).")
        ref = int(e.get("reference_mic", 0))
        if not 0 <= ref < len(mics):
            raise ConfigError(f"{path}: array '{name}' reference_mic {ref} is not one of its {len(mics)} mics.")
        if any(sp.name == name for sp in specs):
            raise ConfigError(f"{path}: two arrays are named '{name}'; each name must be unique.")
        specs.append(ArraySpec(name, file, mics, ref))
    options = {k: v for k, v in data.items() if k != "array"}
    return specs, options


def _read(spec: ArraySpec) -> tuple[np.ndarray, float]:
    try:
        x, fs = sf.read(str(spec.file), dtype="float32", always_2d=True)
    except (sf.LibsndfileError, RuntimeError, OSError) as err:
        raise InputFileError(f"Array '{spec.name}': {spec.file} is not a readable audio file "
                             f"({why_unreadable(spec.file, err)}).") from None
    if x.shape[1] != len(spec.mics_m):
        raise InputFileError(f"Array '{spec.name}': {spec.file} has {x.shape[1]} channels but the arrays file "
                             f"gives {len(spec.mics_m)} mic positions; they must match, channel k = mic k.")
    bad = ~np.isfinite(x)
    if bad.any():
        log.warning("Array '%s': %d non-finite samples were replaced by zeros.", spec.name, int(bad.sum()))
        x = np.where(bad, 0.0, x).astype(np.float32)
    return x, float(fs)


def detect_probes(x: np.ndarray, sample_rate_hz: float, *, threshold_db: float = 10.0, min_duration_s: float = 0.05,
                  merge_gap_s: float = 0.05) -> np.ndarray:
    """Probe events of one array: ``(start_s, stop_s)`` rows where the channels' mean energy stays more than
    ``threshold_db`` above the recording's noise floor (its 10th percentile of 10 ms energies)."""
    hop = max(1, int(round(ENVELOPE_HOP_S * sample_rate_hz)))
    n = len(x) // hop
    if n < 3:
        return np.zeros((0, 2))
    e = np.mean(x[:n * hop].astype(np.float64) ** 2, axis=1).reshape(n, hop).mean(axis=1)
    e_db = 10 * np.log10(np.maximum(e, 1e-20))
    floor = np.percentile(e_db, 10)
    on = e_db > floor + threshold_db
    edges = np.flatnonzero(np.diff(np.r_[0, on.astype(np.int8), 0]))
    segs = edges.reshape(-1, 2) * ENVELOPE_HOP_S
    merged: list[list[float]] = []
    for a, b in segs:
        if merged and a - merged[-1][1] <= merge_gap_s:
            merged[-1][1] = b
        else:
            merged.append([a, b])
    out = np.array([s for s in merged if s[1] - s[0] >= min_duration_s]).reshape(-1, 2)
    return out


def match_probes(onsets_s: Sequence[np.ndarray], *, tolerance_s: float = 0.03) -> np.ndarray:
    """Match probes across arrays whose clocks differ by an unknown offset.

    For each array against the first, the offset is the one (among all onset differences) that pairs the
    most onsets within ``tolerance_s``. Returns ``(n_matched, n_arrays)`` indices of the probes heard by every
    array, in the first array's order.
    """
    ref = np.asarray(onsets_s[0], float)
    columns = [np.arange(len(ref))]
    for on in onsets_s[1:]:
        on = np.asarray(on, float)
        best, best_map = -1, None
        for off in (on[:, None] - ref[None, :]).ravel():
            d = np.abs(on[None, :] - (ref[:, None] + off))
            j = np.argmin(d, axis=1)
            ok = d[np.arange(len(ref)), j] <= tolerance_s
            if ok.sum() > best:
                best, best_map = int(ok.sum()), np.where(ok, j, -1)
        columns.append(best_map if best_map is not None else np.full(len(ref), -1))
    m = np.stack(columns, axis=1)
    return m[(m >= 0).all(axis=1)]


def probe_toas(x: np.ndarray, sample_rate_hz: float, segments_s: np.ndarray, mics_m: np.ndarray, *,
               reference_mic: int = 0, speed_of_sound_m_s: float = SPEED_OF_SOUND_M_S,
               max_frame_s: float = 0.25) -> np.ndarray:
    """``toa[m] - toa[reference_mic]`` of every probe, seconds, shape ``(n_probes, n_mics)``: GCC-PHAT of all
    mic pairs over each probe (at most ``max_frame_s`` of it), then least squares over the pairs (the TOA
    paper's pseudo-inverse, eq. 12)."""
    from estimators import gcc_phat, pair_matrix
    n_mics = x.shape[1]
    aperture_m = float(np.max(np.linalg.norm(mics_m[:, None] - mics_m[None], axis=-1)))
    max_tdoa_s = 1.2 * aperture_m / speed_of_sound_m_s + 2 / sample_rate_hz
    A = np.delete(pair_matrix(n_mics), reference_mic, axis=1)          # toa[reference] = 0
    out = np.full((len(segments_s), n_mics), np.nan)
    for s, (a, b) in enumerate(segments_s):
        i0 = int(a * sample_rate_hz)
        i1 = min(len(x), int(min(b, a + max_frame_s) * sample_rate_hz))
        if i1 - i0 < 16:
            continue
        n = 1 << int(np.floor(np.log2(i1 - i0)))
        tdoa, conf = gcc_phat(x[i0:i0 + n], sample_rate_hz=sample_rate_hz, max_tdoa_s=max_tdoa_s)
        w = np.sqrt(np.maximum(conf, 1e-3))
        sol = np.linalg.lstsq(A * w[:, None], tdoa * w, rcond=None)[0]
        out[s] = np.insert(sol, reference_mic, 0.0)
    return out


def run_multi_array(arrays: str | Path, out_dir: str | Path, *, method: str = "mle", sigma_tdoa_s: float | None = None,
                    seed: int = 0, plots: bool = True) -> dict[str, Any]:
    """Calibrate the arrays of ``arrays`` (a TOML file or a folder with ``arrays.toml``); write ``arrays.json``
    and ``arrays.png`` into ``out_dir``. Returns the summary written to ``arrays.json``."""
    from estimators import multi_array as ma
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    specs, options = load_arrays(arrays)
    c = float(options.get("speed_of_sound_m_s", SPEED_OF_SOUND_M_S))
    sigma = float(sigma_tdoa_s or options.get("sigma_tdoa_s", 2e-5))
    signals = [_read(s) for s in specs]
    events = []
    for spec, (x, fs) in zip(specs, signals):
        seg = detect_probes(x, fs)
        log.info("Array '%s': %d probe events.", spec.name, len(seg))
        if len(seg) == 0:
            raise InputFileError(f"Array '{spec.name}': no probe event stands 10 dB above the noise floor of "
                                 f"{spec.file}; nothing to calibrate from.")
        events.append(seg)
    matched = match_probes([e[:, 0] for e in events])
    need = 4
    if len(matched) < need:
        raise InputFileError(f"Only {len(matched)} probe events were heard by every array (events per array: "
                             + ", ".join(f"{s.name} {len(e)}" for s, e in zip(specs, events))
                             + f"); the calibration needs at least {need}, better 20, from several directions.")
    toas = []
    for k, (spec, (x, fs)) in enumerate(zip(specs, signals)):
        segs = events[k][matched[:, k]]
        toas.append(probe_toas(x, fs, segs, spec.mics_m, reference_mic=spec.reference_mic, speed_of_sound_m_s=c))
    try:
        result = ma.calibrate_arrays(toas, [s.mics_m for s in specs], sigma_tdoa_s=sigma, speed_of_sound_m_s=c,
                                     reference_mics=[s.reference_mic for s in specs], method=method, rng=seed)
    except ma.CalibrationInputError as err:
        raise InputFileError(f"The arrays cannot be calibrated from these probes: {err}") from None
    summary = {
        "method": method, "converged": bool(result.converged), "n_probes": int(len(matched)),
        "rejected_probes": [int(i) for i in result.rejected_sources],
        "speed_of_sound_m_s": c, "sigma_tdoa_s": sigma, "solve_s": time.perf_counter() - t0,
        "arrays": [{"name": s.name, "file": str(s.file), "n_mics": len(s.mics_m),
                    "n_events": int(len(e)),
                    "rotation_deg": [float(v) for v in p.rotation_deg],
                    "rotation_std_deg": [float(v) for v in p.rotation_std_deg],
                    "translation_m": [float(v) for v in p.translation_m],
                    "translation_std_m": [float(v) for v in p.translation_std_m],
                    "rotation_matrix": np.asarray(p.rotation_matrix).tolist()}
                   for s, e, p in zip(specs, events, result.poses)],
        "probe_positions_m": np.asarray(result.fused_sources_m).tolist(),
        "frame": f"array '{specs[result.reference_array].name}' (the reference: identity pose); a mic at y in "
                 "array k's frame is at R_k y + t_k",
    }
    outputs = ["arrays.json", "geometry.json"]
    (out / "arrays.json").write_text(json.dumps(summary, indent=2))
    multi_array_geometry(specs, result, n_probes=len(matched), solve_s=summary["solve_s"]).save(out / "geometry.json")
    if plots:
        try:
            _plot(out / "arrays.png", specs, result)
            outputs.append("arrays.png")
        except Exception as err:  # noqa: BLE001 - a plot must never lose the poses
            log.warning("The arrays plot could not be drawn (%s: %s); arrays.json is written.", type(err).__name__, err)
    summary["outputs"] = outputs
    return summary


def multi_array_geometry(specs: Sequence[ArraySpec], result, *, n_probes: int, solve_s: float = float("nan")):
    """The arrays' poses as a :class:`estimators.geometry.Geometry` (the stream's geometry object): every mic a
    device (``NAME.k``) at its posed position in the reference array's frame, each array an
    :class:`~estimators.geometry.ArrayPlacement` with its pose and standard deviations, the fused probes as the
    events. Clock offsets and drifts between arrays are not observed by this calibration (NaN); the reference
    array's mics share its clock (0)."""
    from .geometry import ArrayPlacement, Geometry
    placements, positions, names = [], [], []
    ref = result.reference_array
    clock = []
    for k, (spec, pose) in enumerate(zip(specs, result.poses)):
        first = len(names)
        placements.append(ArrayPlacement(spec.name, range(first, first + len(spec.mics_m)), spec.mics_m,
                                         pose.rotation_matrix, pose.translation_m, pose.rotation_std_deg,
                                         pose.translation_std_m))
        positions.append(pose.to_reference(spec.mics_m))
        names += [f"{spec.name}.{m + 1}" for m in range(len(spec.mics_m))]
        clock += [0.0 if k == ref else np.nan] * len(spec.mics_m)
    x = np.vstack(positions)
    clock = np.asarray(clock)
    std = np.concatenate([np.full(len(s.mics_m), float(np.linalg.norm(p.translation_std_m)))
                          for s, p in zip(specs, result.poses)])
    return Geometry(positions_m=x, position_std_m=std, offsets_s=clock, offset_std_s=clock, drifts_ppm=clock,
                    drift_std_ppm=clock, verdict="converged" if result.converged else "max_iterations",
                    n_events=int(n_probes), method=f"multi-array ({result.method})",
                    event_positions_m=np.asarray(result.fused_sources_m), residual_scale=float(result.variance_factor),
                    sigma_tdoa_s=float(result.sigma_tdoa_s or np.nan), solve_time_s=float(solve_s),
                    device_names=tuple(names), rejected=tuple(f"probe {i} is inconsistent across the arrays"
                                                              for i in result.rejected_sources),
                    arrays=tuple(placements))


def _plot(path: Path, specs: Sequence[ArraySpec], result) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    src = np.asarray(result.fused_sources_m)
    rejected = np.zeros(len(src), bool)
    rejected[list(result.rejected_sources)] = True
    rejected &= np.isfinite(src).all(axis=1)     # a rejected probe has a fused position only if it was fused
    for ax, (i, j, label) in zip(axes, [(0, 1, "top view (x, y)"), (0, 2, "side view (x, z)")]):
        ax.scatter(src[~rejected, i], src[~rejected, j], s=14, c="0.5", label="probes (fused)")  # NaN not drawn
        if rejected.any():
            ax.scatter(src[rejected, i], src[rejected, j], s=30, marker="x", c="r", label="rejected probes")
        for k, (spec, pose) in enumerate(zip(specs, result.poses)):
            mics = spec.mics_m @ np.asarray(pose.rotation_matrix).T + np.asarray(pose.translation_m)
            ax.scatter(mics[:, i], mics[:, j], s=18, marker="^", label=f"{spec.name}")
            ctr = mics.mean(axis=0)
            std = np.asarray(pose.translation_std_m)
            ax.annotate(f"{spec.name}\n±{1e2 * float(np.linalg.norm(std)):.1f} cm", ctr[[i, j]], fontsize=8)
        ax.set_title(label)
        ax.set_xlabel("m")
        ax.set_ylabel("m")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="best")
    fig.suptitle(f"multi-array calibration ({result.method}): {len(src)} probes, "
                 f"{int(rejected.sum())} rejected")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
