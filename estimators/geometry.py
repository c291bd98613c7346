"""The array geometry a calibration produces: an immutable message and its JSON form (its picture:
:func:`stream.geometry.plot_geometry`).

Clock model (device 0 is the reference; its clock is the stream's time base)::

    c_i = c_0 + offsets_s[i] + drifts_ppm[i] * 1e-6 * (c_0 - epoch_clock_s)

where ``c_i`` is device ``i``'s clock (its sample index / its nominal rate, first sample = 0) at the instant
device 0's clock reads ``c_0``. ``epoch_clock_s`` is device 0's clock at the emission of the first calibration
event the solve used, so ``offsets_s`` are the clock offsets ``tau_i - tau_0`` of the hybrid-TDOA model
(:mod:`estimators.hybrid_tdoa`, eq. 4) and ``1 + drifts_ppm[i] * 1e-6 = (1 + delta_i) / (1 + delta_0)`` is the
rate of device ``i``'s clock relative to device 0's: the ``rate_ratio`` of
``stream.condition.DeviceConditioner`` that puts device ``i`` on device 0's time base.

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

__all__ = ["ArrayPlacement", "Geometry", "load_geometry", "GEOMETRY_FORMAT"]

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
class ArrayPlacement:
    """A synchronous array among a geometry's devices: its mics in its own frame and its pose in the geometry's
    frame, ``x = rotation_matrix @ x_array + translation_m``.

    Attributes
    ----------
    name : str
    channels : tuple of int
        The geometry's devices that are its mics: mic ``k`` (row ``k`` of ``mics_m``) is device ``channels[k]``.
    mics_m : ndarray, shape (n_mics, 3)
        The mics in the array's own frame (its known internal geometry), metres.
    rotation_matrix : ndarray, shape (3, 3)
        NaN when the mics cannot fix a rotation (fewer than 3, or in one line).
    translation_m : ndarray, shape (3,)
    rotation_std_deg : ndarray, shape (3,)
        Standard deviation of small rotations about the geometry's x, y, z axes, degrees.
    translation_std_m : ndarray, shape (3,)
    fit_rms_m : float
        RMS distance between the mics' own position estimates and the posed mics (NaN for a pose that was
        solved as a pose).
    """

    name: str
    channels: tuple[int, ...]
    mics_m: np.ndarray
    rotation_matrix: np.ndarray
    translation_m: np.ndarray
    rotation_std_deg: np.ndarray = dataclasses.field(default_factory=lambda: np.full(3, np.nan))
    translation_std_m: np.ndarray = dataclasses.field(default_factory=lambda: np.full(3, np.nan))
    fit_rms_m: float = float("nan")

    def __post_init__(self) -> None:
        object.__setattr__(self, "channels", tuple(int(c) for c in self.channels))
        object.__setattr__(self, "mics_m", _frozen(self.mics_m, ndim=2, name="mics_m"))
        for name, shape in (("rotation_matrix", (3, 3)), ("translation_m", (3,)), ("rotation_std_deg", (3,)),
                            ("translation_std_m", (3,))):
            a = _frozen(getattr(self, name), ndim=len(shape), name=name)
            if a.shape != shape:
                raise ValueError(f"{name} has shape {a.shape}; expected {shape}")
            object.__setattr__(self, name, a)
        if self.mics_m.shape != (len(self.channels), 3):
            raise ValueError(f"mics_m has shape {self.mics_m.shape}; expected ({len(self.channels)}, 3), one row "
                             "per channel")

    @property
    def posed(self) -> bool:
        """Whether the pose is known (a rotation could be fixed)."""
        return bool(np.all(np.isfinite(self.rotation_matrix)) and np.all(np.isfinite(self.translation_m)))

    @property
    def rotation_deg(self) -> np.ndarray:
        """``(roll, pitch, yaw)`` of ``rotation_matrix``, degrees (NaN when not posed)."""
        if not self.posed:
            return np.full(3, np.nan)
        from .multi_array import rotation_deg_from_matrix
        return rotation_deg_from_matrix(self.rotation_matrix)

    def mic_positions_m(self) -> np.ndarray:
        """The mics in the geometry's frame, ``mics_m @ R.T + t`` (NaN when not posed), shape (n_mics, 3)."""
        return self.mics_m @ self.rotation_matrix.T + self.translation_m

    @classmethod
    def fit(cls, name: str, channels, mics_m, positions_m, position_std_m=None) -> "ArrayPlacement":
        """The pose that puts the array's mics (``mics_m``, its own frame) best onto their estimated positions
        (``positions_m``, one per mic, the geometry's frame): weighted Kabsch (weights ``1 / std^2``).

        Standard deviations take isotropic errors per mic of ``sigma`` per axis: the larger of the stated
        CRLB (``std / sqrt(3)``) and the fit's own residual. The rotation's about axis ``a`` is ``sigma`` over
        the root of the summed squared distances of the mics from the axis through their centroid
        (small-angle least squares, the mics' errors independent); the translation's is ``sigma`` itself, not
        ``sigma / sqrt(n_mics)``: the mics of one array share a clock, and the errors of their positions
        along the common direction are nearly the same.
        """
        from .multi_array import rigid_transform
        local = np.asarray(mics_m, float)
        x = np.asarray(positions_m, float)
        k = len(local)
        std = np.full(k, np.nan) if position_std_m is None else np.asarray(position_std_m, float)
        ok = np.all(np.isfinite(x), axis=1)
        nan3 = np.full(3, np.nan)
        if ok.sum() < 3:
            return cls(name, channels, local, np.full((3, 3), np.nan), nan3)
        w = np.where(np.isfinite(std) & (std > 0), 1.0 / np.maximum(std, 1e-12) ** 2, 1.0)[ok]
        try:
            pose = rigid_transform(local[ok], x[ok], w / w.sum())
        except ValueError:   # collinear mics: no rotation about their line
            return cls(name, channels, local, np.full((3, 3), np.nan), nan3)
        posed = pose.to_reference(local)
        resid = np.linalg.norm(posed[ok] - x[ok], axis=1)
        n_ok = int(ok.sum())
        fit_rms = float(np.sqrt(np.mean(resid ** 2)))
        stated = float(np.sqrt(np.nanmean(std[ok] ** 2))) if np.any(np.isfinite(std[ok])) else 0.0
        dof = max(3 * n_ok - 6, 1)
        sigma_axis = max(stated / math.sqrt(3.0), fit_rms * math.sqrt(n_ok / dof))
        d = posed[ok] - posed[ok].mean(axis=0)
        lever2 = np.array([np.sum(d ** 2) - np.sum(d[:, a] ** 2) for a in range(3)])
        rot_std = np.degrees(sigma_axis / np.sqrt(np.maximum(lever2, 1e-300)))
        return cls(name, channels, local, pose.rotation_matrix, pose.translation_m, rot_std,
                   np.full(3, sigma_axis), fit_rms)

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "channels": list(self.channels),
                "mics_m": [[_num(c) for c in row] for row in self.mics_m],
                "rotation_matrix": [[_num(c) for c in row] for row in self.rotation_matrix],
                "rotation_deg": [_num(c) for c in self.rotation_deg],
                "rotation_std_deg": [_num(c) for c in self.rotation_std_deg],
                "translation_m": [_num(c) for c in self.translation_m],
                "translation_std_m": [_num(c) for c in self.translation_std_m],
                "fit_rms_m": _num(self.fit_rms_m)}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "ArrayPlacement":
        def arr(v):
            a = np.array(v, dtype=object)
            return np.where(a == None, np.nan, a).astype(float)  # noqa: E711 - JSON null is NaN
        return cls(str(data["name"]), tuple(data["channels"]), arr(data["mics_m"]), arr(data["rotation_matrix"]),
                   arr(data["translation_m"]), arr(data["rotation_std_deg"]), arr(data["translation_std_m"]),
                   float("nan") if data.get("fit_rms_m") is None else float(data["fit_rms_m"]))


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
    arrays : tuple of ArrayPlacement
        The synchronous arrays among the devices (each mic a device), with their poses in this frame
        (:meth:`with_arrays`); the other devices are single mics.
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
    arrays: tuple[ArrayPlacement, ...] = ()

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
        object.__setattr__(self, "arrays", tuple(self.arrays))
        for a in self.arrays:
            if any(not 0 <= c < n for c in a.channels):
                raise ValueError(f"array '{a.name}' names channels {a.channels}; the geometry has {n} devices")

    def with_arrays(self, arrays) -> "Geometry":
        """This geometry with its synchronous arrays placed: for each ``(name, channels, mics_m)`` (the devices
        that are the array's mics, and the mics in the array's own frame), the pose fitted to those devices'
        positions (:meth:`ArrayPlacement.fit`)."""
        for name, channels, _ in arrays:
            if any(not 0 <= int(c) < self.n_devices for c in channels):
                raise ValueError(f"array '{name}' names channels {list(channels)}; the geometry has "
                                 f"{self.n_devices} devices")
        placed = tuple(ArrayPlacement.fit(name, channels, mics, self.positions_m[list(channels)],
                                          self.position_std_m[list(channels)]) for name, channels, mics in arrays)
        return dataclasses.replace(self, arrays=placed)

    def mic_positions_m(self) -> np.ndarray:
        """Every device's position: an array's mics from its pose and internal geometry (where posed), the
        other devices as solved, shape (n_devices, 3), metres."""
        x = self.positions_m.copy()
        for a in self.arrays:
            if a.posed:
                x[list(a.channels)] = a.mic_positions_m()
        return x

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
            if f.name == "arrays":
                out["arrays"] = [a.to_dict() for a in v]
                continue
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
            elif key == "arrays":
                value = tuple(ArrayPlacement.from_dict(a) for a in value)
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
