"""The array geometry a calibration produces: an immutable message, its JSON form and its picture.

Clock model (device 0 is the reference; its clock is the stream's time base)::

    c_i = c_0 + offsets_s[i] + drifts_ppm[i] * 1e-6 * (c_0 - epoch_clock_s)

where ``c_i`` is device ``i``'s clock (its sample index / its nominal rate, first sample = 0) at the instant
device 0's clock reads ``c_0``. ``epoch_clock_s`` is device 0's clock at the emission of the first calibration
event the solve used, so ``offsets_s`` are the clock offsets ``tau_i - tau_0`` of the hybrid-TDOA model
(:mod:`estimators.hybrid_tdoa`, eq. 4) and ``1 + drifts_ppm[i] * 1e-6 = (1 + delta_i) / (1 + delta_0)`` is the
rate of device ``i``'s clock relative to device 0's: the ``rate_ratio`` of
:class:`stream.condition.DeviceConditioner` that puts device ``i`` on device 0's time base.

Positions are in metres in the odometry frame of the solve (axes of the beacon's odometry, origin at the first
event the solve used); :meth:`Geometry.mic_frame_positions_m` gives the frame-free mic frame (device 0 at the
origin, device 1 on +x, device 2 in the x-y plane) in which errors are scored. Standard deviations are
Cramer-Rao bounds at the estimate (:func:`estimators.crlb`) with the TDOA noise levels estimated from the
residuals (:func:`estimators.estimate_noise_levels`); device 0's are 0 by construction.
"""
from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["Geometry", "load_geometry", "plot_geometry", "GEOMETRY_FORMAT"]

GEOMETRY_FORMAT = "adhoc-array geometry v1"

_FLOATS = ("solved_at_time_s", "epoch_clock_s", "emitter_drift_ppm", "residual_scale", "sigma_tdoa_s",
           "solve_time_s")
_ARRAYS = ("positions_m", "position_std_m", "offsets_s", "offset_std_s", "drifts_ppm", "drift_std_ppm",
           "event_positions_m", "odometry_path_m")


def _frozen(a, *, ndim: int, name: str) -> np.ndarray:
    out = np.array(a, dtype=np.float64, copy=True)
    if out.ndim != ndim:
        raise ValueError(f"{name} has shape {out.shape}; expected {ndim} dimension(s)")
    out.setflags(write=False)
    return out


@dataclasses.dataclass(frozen=True)
class Geometry:
    """Positions, clock offsets and drifts of ``n_devices`` devices from one calibration solve.

    Attributes
    ----------
    positions_m : ndarray, shape (n_devices, 3), float64
        Device positions in the odometry frame of the solve, metres.
    position_std_m : ndarray, shape (n_devices,)
        CRLB standard deviation of each position in the mic frame (root of the summed variances), metres.
    offsets_s : ndarray, shape (n_devices,)
        Clock offset ``c_i - c_0`` at ``epoch_clock_s`` (see the module docstring), seconds; entry 0 is 0.
    offset_std_s : ndarray, shape (n_devices,)
    drifts_ppm : ndarray, shape (n_devices,)
        Clock rate of device ``i`` relative to device 0, ``(rate_ratio - 1) * 1e6``; entry 0 is 0.
    drift_std_ppm : ndarray, shape (n_devices,)
    verdict : str
        The solver's verdict (``converged``, ``suspect_local_minimum``, ``max_iterations``, ``diverged``).
    n_events : int
        Number of calibration events (chirps) the solve used.
    solved_at_time_s : float
        Stream time (device 0's clock) of the observations' snapshot; NaN for a batch calibration.
    epoch_clock_s : float
        Device 0's clock at the emission of the first event of the solve, seconds.
    method : str
        ``hybrid`` or ``baseline``.
    emitter_drift_ppm : float
        Drift of device 0's clock against the beacon's (``delta_0 * 1e6``); NaN for the baseline, which
        cannot observe it.
    event_positions_m : ndarray, shape (n_events, 3)
        Estimated event (beacon) positions in the same frame.
    odometry_path_m : ndarray, shape (n_events, 3)
        The integrated odometry, in the same frame (for plots).
    residual_scale : float
        Robust whitened residual scale of the solve (about 1 when the assumed noise levels are right).
    sigma_tdoa_s : float
        TDOA noise level used for the standard deviations, seconds.
    solve_time_s : float
        Wall-clock duration of the solve (in the worker), seconds.
    first_event : int
        Index of the first event of the solve in the session (0 unless old events were dropped).
    device_names : tuple of str
    rejected : tuple of str
        The measurements the solver rejected as gross errors, one sentence each (what, by how much, why).
    """

    positions_m: np.ndarray
    position_std_m: np.ndarray
    offsets_s: np.ndarray
    offset_std_s: np.ndarray
    drifts_ppm: np.ndarray
    drift_std_ppm: np.ndarray
    verdict: str
    n_events: int
    solved_at_time_s: float = float("nan")
    epoch_clock_s: float = 0.0
    method: str = "hybrid"
    emitter_drift_ppm: float = float("nan")
    event_positions_m: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    odometry_path_m: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    residual_scale: float = float("nan")
    sigma_tdoa_s: float = float("nan")
    solve_time_s: float = float("nan")
    first_event: int = 0
    device_names: tuple[str, ...] = ()
    rejected: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for name in _ARRAYS:
            ndim = 2 if name in ("positions_m", "event_positions_m", "odometry_path_m") else 1
            object.__setattr__(self, name, _frozen(getattr(self, name), ndim=ndim, name=name))
        n = self.positions_m.shape[0]
        if self.positions_m.shape != (n, 3):
            raise ValueError(f"positions_m has shape {self.positions_m.shape}; expected (n_devices, 3)")
        for name in ("position_std_m", "offsets_s", "offset_std_s", "drifts_ppm", "drift_std_ppm"):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"{name} has shape {getattr(self, name).shape}; expected ({n},)")
        for name in ("event_positions_m", "odometry_path_m"):
            a = getattr(self, name)
            if a.size == 0:
                object.__setattr__(self, name, _frozen(np.zeros((0, 3)), ndim=2, name=name))
            elif a.shape[1] != 3:
                raise ValueError(f"{name} has shape {a.shape}; expected (n_events, 3)")
        object.__setattr__(self, "device_names", tuple(str(s) for s in self.device_names))
        if self.device_names and len(self.device_names) != n:
            raise ValueError(f"{len(self.device_names)=} must equal n_devices={n}")

    # clock model -----------------------------------------------------------------------------
    @property
    def n_devices(self) -> int:
        return int(self.positions_m.shape[0])

    @property
    def converged(self) -> bool:
        return self.verdict == "converged"

    @property
    def rate_ratios(self) -> np.ndarray:
        """``1 + drifts_ppm * 1e-6``: device ``i``'s clock rate over device 0's (DeviceConditioner ``rate_ratio``)."""
        return 1.0 + self.drifts_ppm * 1e-6

    def device_clock_s(self, reference_clock_s) -> np.ndarray:
        """Every device's clock when device 0's reads ``reference_clock_s``.

        ``c_i = c_0 + offsets_s[i] + drifts_ppm[i] * 1e-6 * (c_0 - epoch_clock_s)``.

        Returns
        -------
        ndarray, shape (..., n_devices), seconds
        """
        c0 = np.asarray(reference_clock_s, float)[..., None]
        return c0 + self.offsets_s + self.drifts_ppm * 1e-6 * (c0 - self.epoch_clock_s)

    def mic_frame_positions_m(self) -> np.ndarray:
        """Positions in the mic frame: device 0 at the origin, device 1 on +x, device 2 in the x-y plane (y > 0).

        Returns
        -------
        ndarray, shape (n_devices, 3), metres (NaN when devices 0-2 are collinear or unknown)
        """
        x = self.positions_m
        if x.shape[0] < 3 or not np.all(np.isfinite(x[:3])):
            return np.full_like(x, np.nan)
        ex = x[1] - x[0]
        ey = (x[2] - x[0]) - np.dot(x[2] - x[0], ex) / max(np.dot(ex, ex), 1e-300) * ex
        if np.linalg.norm(ex) < 1e-9 or np.linalg.norm(ey) < 1e-9:
            return np.full_like(x, np.nan)
        ex, ey = ex / np.linalg.norm(ex), ey / np.linalg.norm(ey)
        r = np.stack([ex, ey, np.cross(ex, ey)])
        return (x - x[0]) @ r.T

    # JSON ------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (NaN becomes None); :meth:`from_dict` inverts it exactly."""
        out: dict[str, Any] = {"format": GEOMETRY_FORMAT}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, np.ndarray):
                v = [[_num(c) for c in row] for row in v] if v.ndim == 2 else [_num(c) for c in v]
            elif isinstance(v, float):
                v = _num(v)
            elif isinstance(v, tuple):
                v = list(v)
            out[f.name] = v
        out["mic_frame_positions_m"] = [[_num(c) for c in row] for row in self.mic_frame_positions_m()]
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "Geometry":
        names = {f.name: f for f in dataclasses.fields(cls)}
        kw: dict[str, Any] = {}
        for key, value in data.items():
            if key not in names:
                continue  # derived entries (mic_frame_positions_m) and the format tag
            if key in _ARRAYS:
                a = np.array(value if value is not None else [], dtype=object)
                value = np.where(a == None, np.nan, a).astype(float)  # noqa: E711 - JSON null is NaN
                if key in ("event_positions_m", "odometry_path_m") and value.size == 0:
                    value = np.zeros((0, 3))
            elif key in _FLOATS:
                value = float("nan") if value is None else float(value)
            elif key in ("n_events", "first_event"):
                value = int(value)
            elif key in ("device_names", "rejected"):
                value = tuple(value)
            kw[key] = value
        return cls(**kw)

    def to_json(self) -> str:
        """JSON with one line per vector or matrix row."""
        text = json.dumps(self.to_dict(), indent=2)
        return re.sub(r"\[\s*([^\[\]{}]*?)\s*\]", lambda m: "[" + re.sub(r"\s*\n\s*", " ", m.group(1)) + "]", text)

    @classmethod
    def from_json(cls, text: str) -> "Geometry":
        return cls.from_dict(json.loads(text))

    def save(self, path: str | Path) -> Path:
        """Write ``path`` (JSON) atomically: a reader never sees half a file."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(self.to_json() + "\n")
        tmp.replace(path)
        return path

    def summary(self) -> str:
        """One line: verdict, events, per-device offsets and drifts."""
        dev = ", ".join(f"{i}: {1e3 * o:+.2f} ms {d:+.1f} ppm" for i, (o, d) in
                        enumerate(zip(self.offsets_s, self.drifts_ppm)) if i > 0)
        return f"{self.method} calibration over {self.n_events} events: {self.verdict}; offsets/drifts {dev}"


def _num(v) -> float | None:
    v = float(v)
    return None if math.isnan(v) or math.isinf(v) else v


def load_geometry(path: str | Path) -> Geometry:
    """Read a geometry JSON written by :meth:`Geometry.save`."""
    return Geometry.from_json(Path(path).read_text())


def plot_geometry(path: str | Path, geometry: Geometry, *, truth_positions_m: np.ndarray | None = None,
                  title: str | None = None) -> Path:
    """PNG of the devices (with their 2-sigma CRLB circles), the estimated events and the odometry path.

    Two panels share the odometry frame: a top view (x-y) and a side view (x-z). ``truth_positions_m``
    (n_devices, 3), in the same frame, is drawn as crosses when given.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    g = geometry
    names = list(g.device_names) or [f"dev{i}" for i in range(g.n_devices)]
    n_rows = min(g.n_devices, 12)
    fig = plt.figure(figsize=(13, 6.4 + 0.19 * n_rows), constrained_layout=True)
    grid = fig.add_gridspec(2, 2, height_ratios=[6.0, 0.4 + 0.19 * n_rows])
    axes = [fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[0, 1])]
    offsets = [(7, 6), (7, -14), (-16, 6), (-16, -14)]
    for ax, b, label in zip(axes, (1, 2), ("top view (x-y)", "side view (x-z)")):
        a = 0
        if len(g.odometry_path_m):
            p = g.odometry_path_m
            ax.plot(p[:, a], p[:, b], "-", color="0.6", lw=1.5, zorder=1, label="odometry path (integrated)")
        if len(g.event_positions_m):
            e = g.event_positions_m
            ax.plot(e[:, a], e[:, b], "o", ms=5, color="tab:orange", zorder=3, label="events (estimated)")
            step = max(1, len(e) // 12)
            for k in range(0, len(e), step):
                ax.annotate(str(k + g.first_event), e[k, [a, b]], textcoords="offset points", xytext=(4, -10),
                            fontsize=8, color="tab:orange")
        x = g.positions_m
        ok = np.all(np.isfinite(x), axis=1)
        ax.plot(x[ok, a], x[ok, b], "^", ms=11, color="tab:blue", mec="k", zorder=4, label="devices (estimated)")
        for i in np.flatnonzero(ok):
            s = g.position_std_m[i]
            if np.isfinite(s) and s > 0:
                ax.add_patch(Circle((x[i, a], x[i, b]), 2 * s, fill=False, color="tab:blue", lw=1, alpha=0.6,
                                    zorder=2))
            ax.annotate(str(i), x[i, [a, b]], textcoords="offset points", xytext=offsets[i % 4], fontsize=11,
                        fontweight="bold", color="navy", zorder=6)
        if truth_positions_m is not None:
            t = np.asarray(truth_positions_m, float)
            ax.plot(t[:, a], t[:, b], "x", ms=10, mew=2, color="tab:green", zorder=5, label="devices (truth)")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)" if b == 1 else "z (m)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
        ax.set_title(f"{label}, odometry frame (event {g.first_event} at the origin)")
    handles, labels = axes[0].get_legend_handles_labels()
    if np.any(np.isfinite(g.position_std_m) & (g.position_std_m > 0)):
        handles.append(Circle((0, 0), 1, fill=False, color="tab:blue"))
        labels.append("2 sigma (CRLB)")
    axes[0].legend(handles, labels, loc="best", fontsize=9, framealpha=0.85)
    table = fig.add_subplot(grid[1, :])
    table.axis("off")
    rows = [f"{i:>2} {names[i]:<10} position ({g.positions_m[i, 0]:+6.2f}, {g.positions_m[i, 1]:+6.2f}, "
            f"{g.positions_m[i, 2]:+6.2f}) ± {g.position_std_m[i]:.3f} m   offset {1e3 * g.offsets_s[i]:+9.3f} ± "
            f"{1e3 * g.offset_std_s[i]:.3f} ms   drift {g.drifts_ppm[i]:+7.1f} ± {g.drift_std_ppm[i]:.1f} ppm"
            for i in range(n_rows)]
    if g.n_devices > n_rows:
        rows.append(f"   ... {g.n_devices - n_rows} more devices in geometry.json")
    table.text(0.0, 1.0, "\n".join(rows), transform=table.transAxes, va="top", ha="left", fontsize=9,
               family="monospace")
    fig.suptitle(title or f"{g.method} calibration: {g.n_devices} devices, {g.n_events} events, verdict "
                 f"{g.verdict} (offsets and drifts relative to device 0)", fontsize=12)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

