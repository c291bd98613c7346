"""PNG figures for TOA tracks and segmental SAR (after Figs. 2/4 and 5/7 of the TOA paper).

Matplotlib runs on the non-interactive Agg backend; every function writes one PNG and returns its
path. Times on the x axis are in seconds, TOA in milliseconds, SAR in dB.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402
import numpy as np  # noqa: E402

__all__ = ["plot_toa_tracks", "outside_view_note", "plot_segmental_sar", "plot_source_tracks", "label_over_time"]

_DPI = 120


def _save(fig, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def outside_view_note(y_ms: np.ndarray, lim_ms: float) -> str:
    """What a TOA panel cannot show: the share of its frames whose estimate ``y_ms`` (ms from the panel's
    centre) lies beyond ``±lim_ms``, and their range; "" when every finite estimate is in view."""
    y = np.asarray(y_ms, dtype=float)
    y = y[np.isfinite(y)]
    far = y[np.abs(y) > lim_ms]
    if not far.size:
        return ""
    return (f"estimate beyond this view in {100.0 * far.size / y.size:.0f} % of frames "
            f"({far.min():+.1f} to {far.max():+.1f} ms)")


def plot_toa_tracks(
    path: str | Path,
    *,
    time_s: np.ndarray,
    toa_s: np.ndarray,
    true_time_s: np.ndarray | None = None,
    true_toa_s: np.ndarray | None = None,
    gated: np.ndarray | None = None,
    device_names: Sequence[str] | None = None,
    title: str | None = None,
) -> Path:
    """Relative TOA of each device over time, estimates against ground truth.

    One colour per device ``1..M-1`` (device 0 is the reference, always 0, and is skipped).
    Estimates are small dots joined by a thin line, the ground truth a solid black line, and gated
    (rejected as clutter) frames are marked with a grey ``x``. With ground truth, each panel's view is the
    truth's (so that errors of a fraction of a millisecond show); estimates beyond it are drawn as triangles at
    the edge and the panel says in how many frames and by how much (:func:`outside_view_note`).

    Parameters
    ----------
    path : str or Path
        Output PNG file.
    time_s : ndarray, shape (n_frames,), seconds
        Frame times of the estimates.
    toa_s : ndarray, shape (n_frames, n_mics), seconds
        Relative TOA estimates (``toa_s[:, 0] = 0``).
    true_time_s : ndarray, shape (n_true,), seconds, optional
        Times of the ground truth (defaults to ``time_s``).
    true_toa_s : ndarray, shape (n_true, n_mics) or (n_mics,), seconds, optional
        Ground-truth relative TOA; a single row is drawn as constant.
    gated : ndarray, shape (n_frames,) or (n_frames, n_mics), bool, optional
        Frames (or frame/device entries) whose measurement was gated.
    device_names : sequence of str, length n_mics, optional
        Legend labels (default ``"device i"``).
    title : str, optional

    Returns
    -------
    Path
        The written file.
    """
    t = np.asarray(time_s, dtype=float).reshape(-1)
    toa = np.asarray(toa_s, dtype=float)
    if toa.ndim == 1:
        toa = toa[:, None]
    if toa.shape[0] != t.size:
        raise ValueError(f"{toa.shape=} must have {t.size} rows (len(time_s))")
    n_mics = toa.shape[1]
    names = list(device_names) if device_names is not None else [f"device {i}" for i in range(n_mics)]
    if len(names) != n_mics:
        raise ValueError(f"{len(names)=} device_names must match {n_mics=}")
    true = None
    if true_toa_s is not None:
        true = np.asarray(true_toa_s, dtype=float)
        if true.ndim == 1:
            tt = np.array([t.min(), t.max()]) if true_time_s is None else np.asarray(true_time_s, float)
            true = np.broadcast_to(true, (tt.size, n_mics)) if tt.size else true[None, :]
        else:
            tt = t if true_time_s is None else np.asarray(true_time_s, dtype=float)
        if true.shape != (tt.size, n_mics):
            raise ValueError(f"{true.shape=} must be ({tt.size}, {n_mics}) = (n_true, n_mics)")
    gate = None
    if gated is not None:
        gate = np.asarray(gated, dtype=bool)
        if gate.ndim == 1:
            gate = np.broadcast_to(gate[:, None], toa.shape)
        if gate.shape != toa.shape:
            raise ValueError(f"{gate.shape=} must be (n_frames,) or {toa.shape}")

    # one panel per device, each centred on its own median TOA: the offsets between devices are
    # seconds, the tracking errors fractions of a millisecond, so one shared axis hides the latter
    n_panels = n_mics - 1
    if n_panels < 1:
        fig, ax = plt.subplots(figsize=(9, 2.5), constrained_layout=True)
        ax.text(0.5, 0.5, "one device: no relative TOA", ha="center", va="center", transform=ax.transAxes)
        ax.set_axis_off()
        return _save(fig, path)
    fig, axes = plt.subplots(n_panels, 1, figsize=(9, 1.2 + 1.35 * n_panels), sharex=True, squeeze=False,
                             constrained_layout=True)
    colours = plt.get_cmap("tab10")
    for i in range(1, n_mics):
        ax = axes[i - 1, 0]
        c = colours((i - 1) % 10)
        centre = float(np.nanmedian(true[:, i] if true is not None else toa[:, i]))
        ax.plot(t, (toa[:, i] - centre) * 1e3, "-", color=c, lw=0.6, alpha=0.6)
        ax.plot(t, (toa[:, i] - centre) * 1e3, ".", color=c, ms=3, label="estimate")
        if gate is not None and gate[:, i].any():
            g = gate[:, i]
            ax.plot(t[g], (toa[g, i] - centre) * 1e3, "x", color="0.35", ms=4, mew=0.9, label="gated (clutter)")
        if true is not None:
            ax.plot(tt, (true[:, i] - centre) * 1e3, "-", color="k", lw=1.4, label="ground truth")
            spread = np.nanmax(np.abs(true[:, i] - centre)) * 1e3
            lim = max(0.5, 3 * spread)
            ax.set_ylim(-lim, lim)
            # the view is the truth's: estimates beyond it are drawn at its edge and said, not left out of sight
            y = (toa[:, i] - centre) * 1e3
            above, below = y > lim, y < -lim
            label = "estimate beyond the view"
            for far, side, marker in ((above, 1, "^"), (below, -1, "v")):
                if far.any():
                    ax.plot(t[far], np.full(int(far.sum()), side * 0.94 * lim), marker, color=c, ms=3.5, label=label)
                    label = None
            note = outside_view_note(y, lim)
            if note:   # on the side the edge markers leave free
                top = int(below.sum()) >= int(above.sum())
                ax.text(0.01, 0.96 if top else 0.04, note, transform=ax.transAxes, fontsize=7, color="0.15",
                        va="top" if top else "bottom",
                        bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none", "pad": 1.5})
        ax.set_ylabel(f"{names[i]}\n{centre * 1e3:+.2f} ms", fontsize=8)
        ax.grid(True, alpha=0.3)
        if i == 1:
            ax.legend(loc="upper right", fontsize=7, ncol=3, framealpha=0.85)
    axes[-1, 0].set_xlabel("time (s)")
    fig.suptitle(title or "Relative time of arrival per device", fontsize=11)
    fig.supylabel(f"TOA relative to {names[0]}, minus the value shown (ms)", fontsize=9)
    return _save(fig, path)


def plot_segmental_sar(
    path: str | Path,
    *,
    enhanced: np.ndarray,
    sample_rate_hz: float,
    segment_start_s: np.ndarray,
    sar_db: np.ndarray,
    is_speech: np.ndarray,
    title: str | None = None,
) -> Path:
    """Beamformed waveform above its segmental SAR (as in Figs. 5 and 7 of the TOA paper).

    Parameters
    ----------
    path : str or Path
        Output PNG file.
    enhanced : ndarray, shape (n_samples,)
        Beamformed (enhanced) signal.
    sample_rate_hz : float
        Sample rate in hertz.
    segment_start_s : ndarray, shape (n_segments,), seconds
        Start of each segment (equal lengths, from :func:`stream.scoring.metrics.segmental_sar_db`).
    sar_db : ndarray, shape (n_segments,), dB
        SAR per segment (``nan`` where undefined).
    is_speech : ndarray, shape (n_segments,), bool
        Speech segments are drawn in colour, silence in grey (excluded from SSARA).
    title : str, optional

    Returns
    -------
    Path
        The written file.
    """
    if not sample_rate_hz > 0:
        raise ValueError(f"{sample_rate_hz=} must be a positive number of hertz")
    y = np.asarray(enhanced, dtype=float).reshape(-1)
    starts = np.asarray(segment_start_s, dtype=float).reshape(-1)
    sar = np.asarray(sar_db, dtype=float).reshape(-1)
    speech = np.asarray(is_speech, dtype=bool).reshape(-1)
    if not (starts.size == sar.size == speech.size):
        raise ValueError(f"{starts.size=}, {sar.size=} and {speech.size=} must match (n_segments)")
    seg_s = float(np.median(np.diff(starts))) if starts.size > 1 else y.size / sample_rate_hz

    fig, (ax_w, ax_s) = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True, constrained_layout=True,
                                     gridspec_kw={"height_ratios": [1, 1.2]})
    t = np.arange(y.size) / sample_rate_hz
    ax_w.plot(t, y, color="tab:blue", lw=0.4)
    ax_w.set_ylabel("amplitude")
    ax_w.set_title(title or "Beamformed signal and segmental SAR")
    ax_w.grid(True, alpha=0.3)

    finite = np.isfinite(sar)
    colours = np.where(speech, "tab:green", "0.7")
    ax_s.bar(starts[finite], sar[finite], width=seg_s * 0.92, align="edge", color=colours[finite],
             edgecolor="k", linewidth=0.4)
    ax_s.axhline(0.0, color="k", lw=0.6)
    use = finite & speech
    if use.any():
        ssara = 10.0 * np.log10(np.mean(10.0 ** (sar[use] / 10.0)))  # eq. (21)
        ax_s.axhline(ssara, color="tab:red", ls="--", lw=1.2, label=f"SSARA = {ssara:.1f} dB")
    handles, _ = ax_s.get_legend_handles_labels()
    handles += [
        Patch(facecolor="tab:green", edgecolor="k", lw=0.4, label=f"speech segment ({seg_s * 1e3:.0f} ms)"),
        Patch(facecolor="0.7", edgecolor="k", lw=0.4, label="silence (not scored)"),
    ]
    ax_s.set_xlabel("time (s)")
    ax_s.set_ylabel("segmental SAR (dB)")
    ax_s.grid(True, axis="y", alpha=0.3)
    ax_s.legend(handles=handles, loc="lower right", fontsize=8, framealpha=0.85)
    ax_s.set_xlim(0.0, max(t[-1] if t.size else 0.0, starts[-1] + seg_s if starts.size else 0.0))
    return _save(fig, path)


def label_over_time(time_s: np.ndarray, kind: str, relabels: Sequence = ()) -> np.ndarray:
    """A track's label in effect at each of ``time_s``: its first label until its first change (``relabels``:
    ``(time_s, old kind, new kind, ...)`` in time order), and so on; ``kind`` (its last label) without changes."""
    time_s = np.asarray(time_s)
    out = np.full(len(time_s), relabels[0][1] if relabels else kind, dtype=object)
    for when, _, new_kind, *_ in relabels:
        out[time_s >= when] = new_kind
    return out


def plot_source_tracks(
    path: str | Path,
    *,
    tracks: dict,
    time_s: np.ndarray,
    steered_id: np.ndarray,
    truth: dict | None = None,
    device_names: Sequence[str] | None = None,
    max_devices: int = 8,
    title: str | None = None,
    reference: int = 0,
) -> Path:
    """Every tracked source over time, the steered one highlighted (the multi-source tracker).

    One panel per device other than ``reference`` (at most ``max_devices``): its TOA relative to ``reference``
    (device 0, or the device the offsets were measured against when device 0 was left out) for every confirmed
    track (talker tracks in colour, noise tracks grey dashed), the frames in which a track was steered
    drawn thick in black over it, and, when given, each true source as a dotted line. Where a track had no hit
    for a while (``heard`` false) it is the filter's prediction only, drawn faint and thin. A track whose label
    changed (``relabels``: a noise source of the pauses that turned out to be a talker, a talker track that kept
    sounding in the pauses) is drawn in the style of its label at each time, with a triangle where it changed.

    Parameters
    ----------
    path : str or Path
        Output PNG file.
    tracks : dict
        ``id -> {"kind": str, "time_s": list, "toa_s": list of (M,) arrays, "heard": list of bool (optional),
        "relabels": list of (time_s, old kind, new kind, why) (optional)}`` (``PipelineState.source_tracks``).
    time_s : ndarray, shape (n_frames,), seconds
        Frame times.
    steered_id : ndarray, shape (n_frames,), int
        Steered track per frame (-1: none, the output is the reference device).
    truth : dict, optional
        ``name -> (time_s (n,), toa_s (n, M))`` of the true sources (absolute TOAs, same clocks).
    """
    import matplotlib.pyplot as plt

    ids = sorted(tracks)
    m = next((len(tracks[i]["toa_s"][0]) for i in ids if tracks[i]["toa_s"]), 2)
    n_panels = max(1, min(m - 1, max_devices))
    r = int(reference) if 0 <= int(reference) < m else 0
    panel_devices = [d for d in range(m) if d != r][:n_panels]
    names = list(device_names) if device_names is not None else [f"device {i}" for i in range(m)]
    height_in = 2.2 * n_panels + 0.8
    fig, axes = plt.subplots(n_panels, 1, figsize=(10, height_in), sharex=True, squeeze=False)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    steer_times = np.asarray(time_s)
    steered_id = np.asarray(steered_id)
    for p, d in enumerate(panel_devices):
        ax = axes[p, 0]
        if truth:
            for k, (name, (tt, tv)) in enumerate(truth.items()):
                ax.plot(tt, 1e3 * (tv[:, d] - tv[:, r]), ":", color="0.3" if "noise" in name else "k", lw=1.2,
                        label=f"true {name}" if p == 0 else None)
        for n_i, tid in enumerate(ids):
            h = tracks[tid]
            if not h["toa_s"]:
                continue
            t = np.asarray(h["time_s"])
            v = np.vstack(h["toa_s"])
            rel = 1e3 * (v[:, d] - v[:, r])
            relabels = list(h.get("relabels") or ())
            noise_at = label_over_time(t, h["kind"], relabels) == "noise"
            colour = colours[n_i % len(colours)]
            heard = np.asarray(h.get("heard", np.ones(len(t), bool)), bool)   # in step with time_s (History)
            kinds = " -> ".join([relabels[0][1]] + [c[2] for c in relabels]) if relabels else h["kind"]
            label = f"track {tid} ({kinds})" if p == 0 else None
            for noise in (False, True):
                part = noise_at == noise
                if not part.any():
                    continue
                # one frame of overlap at a change of label, so that the line is not broken there
                part |= np.r_[part[1:], False] if noise else np.r_[False, part[:-1]]
                c = "0.6" if noise and not relabels else colour
                # where the track had no hit for a while it is only the filter's prediction: faint and thin, so a
                # drifting prediction is not read as a source that moved
                ax.plot(t, np.where(heard & part, rel, np.nan), "--" if noise else "-", color=c, lw=0.9,
                        label=label)
                label = None
                if not heard[part].all():
                    ax.plot(t, np.where(heard | ~part, np.nan, rel), ":", color=c, lw=0.7, alpha=0.45)
            for when, _, new_kind, *_ in relabels:
                k = int(np.searchsorted(t, when))
                if k < len(t):
                    ax.plot(t[k], rel[k], "^" if new_kind == "speech" else "v", color=colour, ms=7, mec="k",
                            mew=0.6)
            on = np.isin(t, steer_times[steered_id == tid])
            if on.any():
                ax.plot(t, np.where(on, rel, np.nan), "-", color="k", lw=2.6, alpha=0.55,
                        label=None)
        ax.set_ylabel(f"{names[d]} - {names[r]}\n(ms)")
        ax.grid(alpha=0.3)
    axes[0, 0].plot([], [], "-", color="k", lw=2.6, alpha=0.55, label="steered")
    axes[0, 0].plot([], [], ":", color="0.4", lw=0.7, label="predicted (no hit)")
    if any(tracks[i].get("relabels") for i in ids):
        axes[0, 0].plot([], [], "^", color="0.5", mec="k", mew=0.6, label="turned talker")
        axes[0, 0].plot([], [], "v", color="0.5", mec="k", mew=0.6, label="turned noise")
    axes[0, 0].legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    axes[-1, 0].set_xlabel("time (s)")
    shown = f" ({n_panels} of {m - 1} devices)" if n_panels < m - 1 else ""
    fig.suptitle((title or "Tracked sources: relative TOA, steered track thick") + shown)
    # margins in inches, not in shares of the figure: a tall figure (many devices) otherwise gets an inch of
    # empty space under its title
    fig.subplots_adjust(right=0.76, hspace=0.15, top=1 - 0.55 / height_in, bottom=0.55 / height_in)
    return _save(fig, path)
