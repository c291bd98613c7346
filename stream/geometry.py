"""The geometry's picture; the geometry itself (:class:`Geometry`, :class:`ArrayPlacement`, its JSON form and clock
model) lives in :mod:`estimators.geometry` and is re-exported here."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from estimators.geometry import GEOMETRY_FORMAT, ArrayPlacement, Geometry, load_geometry

__all__ = ["ArrayPlacement", "Geometry", "load_geometry", "plot_geometry", "GEOMETRY_FORMAT"]


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
    n_lines = n_rows + len(g.arrays)
    fig = plt.figure(figsize=(13, 6.4 + 0.19 * n_lines), constrained_layout=True)
    grid = fig.add_gridspec(2, 2, height_ratios=[6.0, 0.4 + 0.19 * n_lines])
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
        for arr in g.arrays:   # a posed array: its mics where its pose puts them, joined in mic order
            if arr.posed:
                m = arr.mic_positions_m()
                ring = np.vstack([m, m[:1]])
                ax.plot(ring[:, a], ring[:, b], ".-", color="tab:purple", lw=1, ms=5, zorder=5,
                        label="arrays (posed)" if arr is next(q for q in g.arrays if q.posed) else None)
                ax.annotate(arr.name, m[:, [a, b]].mean(axis=0), textcoords="offset points", xytext=(0, -18),
                            fontsize=10, color="tab:purple", ha="center", zorder=6)
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
    for arr in g.arrays:
        rows.append(f"   array {arr.name} (devices {arr.channels[0]}-{arr.channels[-1]}): "
                    + (f"roll/pitch/yaw ({', '.join(f'{v:+.1f}' for v in arr.rotation_deg)}) ± "
                       f"{np.nanmax(arr.rotation_std_deg):.1f} deg, at ({', '.join(f'{v:+.2f}' for v in arr.translation_m)}) "
                       f"± {np.nanmax(arr.translation_std_m):.3f} m, fit {1e3 * arr.fit_rms_m:.1f} mm"
                       if arr.posed else "no pose (its mics cannot fix a rotation)"))
    table.text(0.0, 1.0, "\n".join(rows), transform=table.transAxes, va="top", ha="left", fontsize=9,
               family="monospace")
    fig.suptitle(title or f"{g.method} calibration: {g.n_devices} devices, {g.n_events} events, verdict "
                 f"{g.verdict} (offsets and drifts relative to device 0)", fontsize=12)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

