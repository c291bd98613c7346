"""Array calibration from a moving chirp beacon, periodic in the stream (the solve, the observations, the
calibrator); its file formats are in :mod:`stream.calibration_files`, the batch command in :mod:`stream.calibrate_cli`.

::

    device frames ─▶ RetunableConditioner (stream.condition) ─▶ ChirpDetector (estimators.chirps; per device, own clock) ─▶ CalibrationObservations
                                                   (bounded, drop-oldest)   │ snapshot every N events
    OdometryLog (file now; a zenoh key later) ───────────────────────────────┤
                                                                             ▼
                       calibrate(snapshot) in a concurrent.futures executor ─▶ Geometry
                                                                             │ future.done(), once per block
    Pipeline: at a frame boundary, new rate_ratio per device (drift) + Aligner.shift (offset) ◀─┘ + publish

Time conventions
----------------
- A device's *clock* ``c_i`` is its sample index over its nominal rate (first sample = 0), seconds.
- A device's conditioned stream (working rate) has its own sample index ``m``; :class:`ClockMap` maps ``m`` to
  ``c_i`` (:mod:`stream.condition`; piecewise linear: ``c = c_start + (m - m_start) * rate_ratio / working_rate_hz``), one segment per
  rate change. Chirp onsets are detected on the conditioned stream and carried as ``(m, c_i)``.
- A beacon emits chirp ``j`` at ``t_j`` (``t_0 = 0``, ``interval_s[j] = t_{j+1} - t_j``) after moving by
  ``odometry_m[j]``; the engine knows the schedule and the odometry, not the absolute emission time. The
  arrival on device ``i``'s clock is ``T_ij = |x_i - s_j| / c + tau_i + (1 + delta_i) t_j``
  (:mod:`estimators.hybrid_tdoa`, eq. 4).
- The resulting :class:`estimators.geometry.Geometry` maps device 0's clock to every other device's clock.

Calibration never blocks the stream: the pipeline calls :meth:`StreamCalibrator.step` once per block, which only
checks ``future.done()``; a snapshot of the observations (small immutable arrays) is solved in a
``ThreadPoolExecutor(max_workers=1)``; ``future.result()`` re-raises a worker error on the consumer thread,
where it becomes one sentence in the report and the last good geometry stays in force.
"""
from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import logging
import math
import threading
import time
from typing import Any, Callable, Literal, Sequence

import numpy as np

import estimators
from estimators.chirps import ChirpDetector

from .condition import ClockMap
from .errors import AdhocArrayError, ConfigError
from .geometry import Geometry

log = logging.getLogger(__name__)

__all__ = [
    "CalibrationSnapshot",
    "ChirpDetection",
    "CalibrationObservations",
    "OdometryLog",
    "StreamCalibrator",
    "calibrate",
    "solve_geometry",
]

Method = Literal["hybrid", "baseline"]
Apply = Literal["drift", "offsets", "none"]

ASSIGN_TOLERANCE_S = 0.06     # largest distance of a detection from its scheduled event (reference clock):
                              # coarse-alignment error + propagation differences
MAX_DRIFT = 2e-4              # largest rate difference between device 0's clock and the beacon's schedule
PRIOR_DOF = 4.0               # weight (degrees of freedom) of the assumed TDOA noise in the reported bounds
MIN_SOLVE_EVENTS = 6          # no solve over fewer events (the geometry is not determined)
ADAPT_PASSES = 3              # re-solves with the TDOA noise re-estimated from the residuals
MIN_SIGMA_TDOA_S = 1e-6       # floor of a re-estimated TDOA noise
MIN_EVENTS_TO_NUMBER = 4      # scheduled events matched before the event numbering is fixed
COMPLETE_GUARD_S = 0.1        # an event counts once every device has processed this far past it
MIN_DETECTIONS = 3            # a device needs this many assigned chirps to enter a solve
ATTEMPT_EVERY_S = 0.2         # stream time between two checks for enough new complete events


class CalibrationError(AdhocArrayError, RuntimeError):
    """A calibration cannot be set up or solved (bad measurements, too few events)."""


# ----------------------------------------------------------------------------------------------------------------
# Odometry and measurement files
# ----------------------------------------------------------------------------------------------------------------
class OdometryLog:
    """The beacon's emission schedule and odometry: step ``j`` (event ``j`` -> ``j + 1``) is a displacement
    ``(3,)`` in metres and an interval in seconds.

    A file fills it at once (:func:`load_odometry_csv`). A live source appends steps as they arrive with
    :meth:`append` (thread-safe) — the seam for a zenoh odometry key once networking lands: a subscriber
    callback only calls ``append``.
    """

    def __init__(self, odometry_m: np.ndarray | None = None, interval_s: np.ndarray | None = None) -> None:
        self._lock = threading.Lock()
        self._odo: list[np.ndarray] = []
        self._iv: list[float] = []
        if odometry_m is not None:
            odo = np.asarray(odometry_m, float).reshape(-1, 3)
            iv = np.asarray(interval_s, float).reshape(-1)
            if len(iv) != len(odo):
                raise ValueError(f"{len(iv)=} intervals must match {len(odo)=} odometry steps")
            for d, t in zip(odo, iv):
                self.append(d, t)

    def append(self, displacement_m, interval_s: float) -> None:
        d = np.asarray(displacement_m, float).reshape(3)
        if not (np.isfinite(interval_s) and interval_s > 0):
            raise ValueError(f"{interval_s=} must be a positive number of seconds")
        with self._lock:
            self._odo.append(d)
            self._iv.append(float(interval_s))

    @property
    def n_steps(self) -> int:
        with self._lock:
            return len(self._iv)

    def snapshot(self) -> tuple[np.ndarray, np.ndarray]:
        """(odometry_m (n_steps, 3), interval_s (n_steps,)) copies."""
        with self._lock:
            odo = np.array(self._odo, float).reshape(-1, 3)
            iv = np.array(self._iv, float)
        return odo, iv


def solve_geometry(problem: estimators.HybridTdoaProblem, *, method: Method = "hybrid",
                   rng: np.random.Generator | int | None = 0, reference_onsets_s: np.ndarray | None = None,
                   solved_at_time_s: float = float("nan"), first_event: int = 0,
                   device_names: Sequence[str] = ()) -> Geometry:
    """Solve one hybrid-TDOA problem and express it as a :class:`Geometry` with CRLB standard deviations.

    Parameters
    ----------
    reference_onsets_s : ndarray, shape (K,), optional
        Chirp arrivals on device 0's clock; they fix ``epoch_clock_s`` (device 0's clock at the emission of
        event 0: ``median_j(T_0j - |x_0 - s_j| / c - (1 + delta_0) t_j)``). Without them it is 0.

    When the residuals of a converged solve are well below the assumed TDOA noise, it is solved again from
    its estimate with the noise re-estimated from the residuals (Appendix B; at most ``ADAPT_PASSES`` times):
    the solver's robust scale and stopping rules follow the assumed noise. Standard deviations are the CRLB at
    the estimate with the TDOA noise re-estimated from the residuals when that is possible, else with the
    problem's own sigmas.
    """
    t0 = time.perf_counter()
    prior_sigma_s = problem.sigma_events_s
    res = estimators.solve_hybrid_tdoa(problem, method=method, rng=rng)
    for _ in range(ADAPT_PASSES):
        # an assumed TDOA noise far above the residuals stops the solver early (its robust scale and
        # plausibility tests follow sigma): re-solve from the estimate with the noise re-estimated (Appendix B)
        if res.verdict != "converged":
            break
        noise = estimators.estimate_noise_levels(estimators.without_rejected(problem, res), res.scene)
        s_ev = noise.tdoa_events_std_s if method == "hybrid" else noise.tdoa_mics_std_s
        s_mi = noise.tdoa_mics_std_s
        if not (np.isfinite(s_ev) and np.isfinite(s_mi)) or max(s_ev, s_mi) > 0.5 * problem.sigma_events_s:
            break
        sharper = dataclasses.replace(problem, sigma_tdoa_s=max(float(s_ev), MIN_SIGMA_TDOA_S),
                                      sigma_tdoa_mics_s=max(float(s_mi), MIN_SIGMA_TDOA_S))
        again = estimators.solve_hybrid_tdoa(sharper, method=method, init=res.scene, rng=rng)
        if again.verdict != "converged":
            break
        problem, res = sharper, again
    solve_s = time.perf_counter() - t0
    n, c = problem.n_mics, problem.speed_of_sound_m_s
    delta = res.drifts_ppm * 1e-6
    ratio = (1.0 + delta) / (1.0 + delta[0])
    std_pos = np.full(n, np.nan)
    std_off = np.full(n, np.nan)
    std_drift = np.full(n, np.nan)
    sigma = problem.sigma_events_s
    if res.verdict != "diverged" and np.all(np.isfinite(res.mic_positions_m)):
        try:
            clean = estimators.without_rejected(problem, res)
            s_ev, s_mi, sigma = _noise_for_bounds(clean, res.scene, method, prior_s=prior_sigma_s)
            p = dataclasses.replace(clean, sigma_tdoa_s=s_ev, sigma_tdoa_mics_s=s_mi)
            cr = estimators.crlb(p, res.scene, method=method, unknown_intervals=res.estimated_intervals)
            v = np.diag(cr.mic_frame_covariance)
            std_pos = np.asarray(cr.per_mic_location_std_m, float)
            std_off = np.sqrt(np.maximum(v[3 * n:4 * n], 0.0))
            std_drift = np.sqrt(np.maximum(v[4 * n:5 * n], 0.0)) * 1e6
        except (np.linalg.LinAlgError, ValueError, FloatingPointError) as err:
            log.debug("CRLB at the estimate failed: %s", err)
    epoch = 0.0
    if reference_onsets_s is not None:
        on = np.asarray(reference_onsets_s, float)
        d0 = np.linalg.norm(res.event_positions_m - res.mic_positions_m[0], axis=1)
        e = on - d0 / c - (1.0 + delta[0]) * problem.emission_times_s
        if np.any(np.isfinite(e)):
            epoch = float(np.nanmedian(e))
    odo = np.nan_to_num(problem.odometry_m)
    path = np.vstack([np.zeros((1, 3)), np.cumsum(odo, axis=0)])
    return Geometry(
        positions_m=res.mic_positions_m, position_std_m=std_pos, offsets_s=res.offsets_s - res.offsets_s[0],
        offset_std_s=std_off, drifts_ppm=(ratio - 1.0) * 1e6, drift_std_ppm=std_drift, verdict=res.verdict,
        n_events=problem.n_events, solved_at_time_s=solved_at_time_s, epoch_clock_s=epoch, method=method,
        emitter_drift_ppm=float(res.drifts_ppm[0]) if method == "hybrid" else float("nan"),
        event_positions_m=res.event_positions_m, odometry_path_m=path, residual_scale=res.residual_scale,
        sigma_tdoa_s=sigma, solve_time_s=solve_s, first_event=first_event, device_names=tuple(device_names),
        rejected=tuple(r.reason for r in getattr(res, "rejected", ())))


def _noise_for_bounds(problem: estimators.HybridTdoaProblem, scene: estimators.Scene, method: str, *,
                      prior_s: float) -> tuple[float, float, float]:
    """TDOA noise (TDOA-S, TDOA-M, the one reported) for the CRLB at an estimate.

    The residual estimate (Appendix B) is scaled by ``sqrt(n_meas / dof)`` for the parameters the fit used, then
    pooled with the assumed noise ``prior_s`` as ``PRIOR_DOF`` degrees of freedom of evidence,
    ``sigma^2 = (dof s^2 + PRIOR_DOF prior^2) / (dof + PRIOR_DOF)``: with few events the residuals say little
    (an exactly determined fit has none), and the bound must not claim precision the data cannot give.
    """
    k, n = problem.n_events, problem.n_mics
    n_s = int(np.isfinite(problem.tdoa_events_s).sum()) if (method == "hybrid" and problem.tdoa_events_s is
                                                             not None) else 0
    n_m = int(np.isfinite(problem.tdoa_mics_s[:, 1:]).sum())
    n_o = 3 * int(np.all(np.isfinite(problem.odometry_m), axis=1).sum())
    n_par = 3 * n + (n - 1) + (n if method == "hybrid" else n - 1) + 3 * k - 6
    dof = max(n_s + n_m + n_o - n_par, 0)
    noise = estimators.estimate_noise_levels(problem, scene)
    scale = math.sqrt((n_s + n_m + n_o) / dof) if dof else 0.0

    def pool(est: float) -> float:
        est = est * scale if np.isfinite(est) else 0.0
        return math.sqrt((dof * est * est + PRIOR_DOF * prior_s * prior_s) / (dof + PRIOR_DOF))

    s_mi = pool(noise.tdoa_mics_std_s)
    s_ev = pool(noise.tdoa_events_std_s) if method == "hybrid" else s_mi
    return s_ev, s_mi, s_ev


@dataclasses.dataclass(frozen=True)
class CalibrationSnapshot:
    """Everything one solve needs, copied out of the stream (immutable; safe to hand to a worker).

    Attributes
    ----------
    onsets_s : ndarray, shape (K, N)
        Arrival of chirp ``first_event + j`` on device ``i``'s clock, seconds; NaN = not detected.
    odometry_m : ndarray, shape (K-1, 3)
    interval_s : ndarray, shape (K-1,)
    first_event : int
        Session index of row 0 (older events were dropped).
    time_s : float
        Stream time (device 0's clock) when the snapshot was taken.
    """

    onsets_s: np.ndarray
    odometry_m: np.ndarray
    interval_s: np.ndarray
    first_event: int
    time_s: float
    sigma_tdoa_s: float
    sigma_odo_m: float
    method: Method = "hybrid"
    speed_of_sound_m_s: float = estimators.SPEED_OF_SOUND_M_S
    device_names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for name in ("onsets_s", "odometry_m", "interval_s"):
            a = np.array(getattr(self, name), float, copy=True)
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    @property
    def n_events(self) -> int:
        return int(self.onsets_s.shape[0])

    @property
    def n_devices(self) -> int:
        return int(self.onsets_s.shape[1])


def calibrate(snapshot: CalibrationSnapshot, *, rng: np.random.Generator | int | None = 0) -> Geometry:
    """Solve a snapshot of the stream's chirp onsets and odometry (the worker's function; pure).

    TDOA-S ``onsets[j+1, i] - onsets[j, i]`` (eq. 5) and TDOA-M ``onsets[j, i] - onsets[j, 0]`` (eq. 6).
    Devices with fewer than ``MIN_DETECTIONS`` chirps are left out (NaN rows in the geometry).
    """
    on = snapshot.onsets_s
    n = snapshot.n_devices
    counts = np.sum(np.isfinite(on), axis=0)
    use = np.flatnonzero(counts >= MIN_DETECTIONS)
    if counts[0] < MIN_DETECTIONS:
        raise CalibrationError(f"device 0 (the reference) heard only {int(counts[0])} of {snapshot.n_events} "
                               "chirps")
    if len(use) < 3:
        raise CalibrationError(f"only {len(use)} devices heard at least {MIN_DETECTIONS} chirps; 3 are needed")
    sub = on[:, use]
    tdoa_m = sub - sub[:, :1]
    tdoa_m[:, 0] = np.nan
    problem = estimators.HybridTdoaProblem(
        tdoa_events_s=np.diff(sub, axis=0), tdoa_mics_s=tdoa_m, odometry_m=snapshot.odometry_m,
        interval_s=snapshot.interval_s, sigma_tdoa_s=snapshot.sigma_tdoa_s, sigma_odo_m=snapshot.sigma_odo_m,
        speed_of_sound_m_s=snapshot.speed_of_sound_m_s)
    names = [snapshot.device_names[i] for i in use] if snapshot.device_names else []
    g = solve_geometry(problem, method=snapshot.method, rng=rng, reference_onsets_s=sub[:, 0],
                       solved_at_time_s=snapshot.time_s, first_event=snapshot.first_event, device_names=names)
    if len(use) == n:
        return g

    def full(a, fill=np.nan):
        out = np.full((n,) + a.shape[1:], fill)
        out[use] = a
        return out

    return dataclasses.replace(
        g, positions_m=full(g.positions_m), position_std_m=full(g.position_std_m), offsets_s=full(g.offsets_s),
        offset_std_s=full(g.offset_std_s), drifts_ppm=full(g.drifts_ppm), drift_std_ppm=full(g.drift_std_ppm),
        device_names=snapshot.device_names)



# ----------------------------------------------------------------------------------------------------------------
# Streaming chirp detection
# ----------------------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class ChirpDetection:
    """One chirp heard by one device.

    Attributes
    ----------
    device_id : int
    onset_samples : float
        Matched-filter onset as a working-rate sample index of the device's conditioned stream.
    clock_s : float
        The same instant on the device's own clock (through its :class:`ClockMap`), seconds.
    snr : float
        Envelope peak over the robust noise level of the matched-filter output.
    """

    device_id: int
    onset_samples: float
    clock_s: float
    snr: float


# ----------------------------------------------------------------------------------------------------------------
# Observations: detections + schedule -> snapshots
# ----------------------------------------------------------------------------------------------------------------

class CalibrationObservations:
    """Chirp detections of every device (bounded, drop-oldest) and their assignment to scheduled events.

    Assignment (at snapshot time): each detection is moved to device 0's clock with the stream's current clock
    relation ``delta_s[i] = c_i - c_0`` (coarse alignment, or the last geometry), the reference-clock time of
    event 0 is found by matching the detections to the schedule (most matched detections; on a tie the
    earliest: the first chirp heard is event 0), refined with a linear fit (device 0 vs the beacon's clock),
    and each device's nearest detection within ``ASSIGN_TOLERANCE_S`` of each scheduled event is taken.
    """

    def __init__(self, n_devices: int, odometry: OdometryLog, *, max_detections: int = 1024) -> None:
        self.n_devices = n_devices
        self.odometry = odometry
        self.detections = [collections.deque(maxlen=max_detections) for _ in range(n_devices)]
        self.final_clock_s = np.full(n_devices, -np.inf)
        self.n_detections = np.zeros(n_devices, dtype=np.int64)
        self._event0_s: float | None = None   # kept once found: event numbers never change
        self._rate = 1.0

    def add(self, det: ChirpDetection) -> None:
        self.detections[det.device_id].append(det)
        self.n_detections[det.device_id] += 1

    def assign(self, delta_s: np.ndarray) -> tuple[np.ndarray, float, float]:
        """Onsets (K_sched, N) on each device's clock (NaN = missed), event 0's reference-clock time ``a`` and
        the reference clock's rate against the schedule ``1 + s``. ``K_sched`` = odometry steps + 1."""
        _, iv = self.odometry.snapshot()
        sched = np.concatenate([[0.0], np.cumsum(iv)])
        k = len(sched)
        onsets = np.full((k, self.n_devices), np.nan)
        r_list, d_list = [], []
        for i, dq in enumerate(self.detections):
            if np.isfinite(delta_s[i]):
                r_list += [d.clock_s - delta_s[i] for d in dq]
                d_list += [i] * len(dq)
        if not r_list:
            return onsets, math.nan, 1.0
        r = np.asarray(r_list)
        if self._event0_s is not None:
            a, s = self._event0_s, self._rate - 1.0
        else:
            a, s = self._find_event0(r, np.asarray(d_list), sched), 0.0
            if not np.isfinite(a):
                return onsets, math.nan, 1.0
        tol = ASSIGN_TOLERANCE_S + (MAX_DRIFT * sched if self._event0_s is None else 0.0)
        for _ in range(2):  # refit a and the rate of device 0's clock against the schedule
            pred = a + (1.0 + s) * sched
            j = np.clip(np.searchsorted(pred, r), 1, max(k - 1, 1))
            j = np.where(np.abs(r - pred[j - 1]) < np.abs(r - pred[np.minimum(j, k - 1)]), j - 1,
                         np.minimum(j, k - 1))
            ok = np.abs(r - pred[j]) < (tol[j] if np.ndim(tol) else tol)
            n_events = len(np.unique(j[ok]))
            if n_events >= 2:
                coef = np.polyfit(sched[j[ok]], r[ok], 1)
                s, a = float(np.clip(coef[0] - 1.0, -MAX_DRIFT, MAX_DRIFT)), float(coef[1])
                if n_events < 3:
                    s = 0.0
                    a = float(np.median(r[ok] - sched[j[ok]]))
        if n_events >= MIN_EVENTS_TO_NUMBER:  # confident: the event numbering is kept from now on
            self._event0_s, self._rate = a, 1.0 + s
        pred = a + (1.0 + s) * sched
        for i, dq in enumerate(self.detections):
            if not np.isfinite(delta_s[i]) or not dq:
                continue
            c = np.array([d.clock_s for d in dq])
            err = np.abs((c - delta_s[i])[:, None] - pred[None, :])         # (D_i, K)
            best = np.argmin(err, axis=0)
            ok = err[best, np.arange(k)] < ASSIGN_TOLERANCE_S
            onsets[ok, i] = c[best[ok]]
        return onsets, a, 1.0 + s

    @staticmethod
    def _find_event0(r: np.ndarray, dev: np.ndarray, sched: np.ndarray) -> float:
        """Reference-clock time of event 0: detections within ``ASSIGN_TOLERANCE_S`` of each other form one
        heard chirp (weighted by its number of devices); every (chirp, scheduled event) pair proposes an event-0
        time; the one matching the most weight (within the tolerance plus ``MAX_DRIFT`` of the schedule time)
        wins, on a tie the latest (the first chirp heard is event 0)."""
        order = np.argsort(r)
        r, dev = r[order], dev[order]
        cut = np.flatnonzero(np.diff(r) > ASSIGN_TOLERANCE_S) + 1
        groups = np.split(np.arange(len(r)), cut)
        centre = np.array([np.median(r[g]) for g in groups])
        weight = np.array([len(np.unique(dev[g])) for g in groups], float)
        cand = np.unique(np.round((centre[:, None] - sched[None, :]).ravel(), 4))
        best_a, best_w = math.nan, 0.0
        k = len(sched)
        for chunk in np.array_split(cand, max(1, len(cand) * len(centre) // 2_000_000 + 1)):
            rel = centre[None, :] - chunk[:, None]                         # (C, G)
            j = np.clip(np.searchsorted(sched, rel), 1, max(k - 1, 1))
            jn = np.where(np.abs(rel - sched[j - 1]) < np.abs(rel - sched[np.minimum(j, k - 1)]), j - 1,
                          np.minimum(j, k - 1))
            near = np.abs(rel - sched[jn]) < ASSIGN_TOLERANCE_S + MAX_DRIFT * sched[jn]
            w = near.astype(float) @ weight
            top = float(np.max(w))
            a_top = float(np.max(chunk[w == top]))
            if top > best_w or (top == best_w and a_top > best_a):
                best_w, best_a = top, a_top
        return best_a

    def snapshot(self, delta_s: np.ndarray, *, time_s: float, n_min: int, max_events: int, sigma_tdoa_s: float,
                 sigma_odo_m: float, method: Method, speed_of_sound_m_s: float,
                 device_names: Sequence[str]) -> CalibrationSnapshot | None:
        """A snapshot of the complete events (every device past them), or None if there are fewer than
        ``n_min``."""
        odo, iv = self.odometry.snapshot()
        if len(iv) < 2 or self.n_detections[0] == 0:
            return None
        onsets, a, rate = self.assign(delta_s)
        if not np.isfinite(a):
            return None
        sched = a + rate * np.concatenate([[0.0], np.cumsum(iv)])
        horizon = np.inf
        for i in range(self.n_devices):
            if np.isfinite(delta_s[i]):
                horizon = min(horizon, self.final_clock_s[i] - delta_s[i])
        n_complete = int(np.searchsorted(sched + COMPLETE_GUARD_S, horizon))
        if n_complete < max(n_min, MIN_SOLVE_EVENTS):
            return None
        first = max(0, n_complete - max_events)
        return CalibrationSnapshot(
            onsets_s=onsets[first:n_complete], odometry_m=odo[first:n_complete - 1],
            interval_s=iv[first:n_complete - 1], first_event=first, time_s=time_s, sigma_tdoa_s=sigma_tdoa_s,
            sigma_odo_m=sigma_odo_m, method=method, speed_of_sound_m_s=speed_of_sound_m_s,
            device_names=tuple(device_names))


# ----------------------------------------------------------------------------------------------------------------
# The stream's calibrator: detection, snapshots, the worker, the swap
# ----------------------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class SolveRecord:
    """One solve, as reported."""

    snapshot_time_s: float
    n_events: int
    first_event: int
    status: str = "pending"          # pending | adopted | rejected | failed | abandoned
    verdict: str | None = None
    solve_time_s: float | None = None
    wait_s: float | None = None      # submit -> result seen by the stream (wall clock)
    adopted_at_time_s: float | None = None
    message: str | None = None


class StreamCalibrator:
    """Periodic recalibration while streaming.

    Parameters
    ----------
    n_devices : int
    template : ndarray, shape (n_template,)
        The beacon's chirp at the working rate.
    sample_rate_hz : float
        Working rate.
    odometry : OdometryLog
        Schedule (intervals) and odometry of the beacon.
    recalibrate_every : int
        Re-solve every this many new complete events (the first solve after as many).
    method : {"hybrid", "baseline"}
    apply : {"drift", "offsets", "none"}
        What a new geometry changes in the stream: ``drift`` re-tunes each device's resampler to its clock rate
        and sets its coarse offset from the clock model; ``offsets`` only sets the coarse offsets; ``none``
        only publishes the geometry.
    solver : callable, optional
        ``solver(snapshot) -> Geometry``, run in the worker; default :func:`calibrate`.
    on_geometry : callable, optional
        Called on the stream's thread with every adopted geometry (the publish hook: a file now, a zenoh
        publisher later).
    executor : {"thread", "process"}
    max_events : int
        Solve over at most the last this many events.
    finish_timeout_s : float
        At the end of the stream, wait at most this long for a pending solve; also the bound of a wait
        for ``replay_latency_s``.
    replay_latency_s : float or None
        None (live and paced streams): a finished solve is collected at the next frame boundary and the
        stream never waits. A number (a replay as fast as possible): a solve submitted at stream time ``t``
        is adopted at the first frame boundary at or after ``t + replay_latency_s`` (stream seconds), waiting
        for the worker there if it has not finished, so that the replay gives the same result on any
        machine, however fast the stream runs past the solver (counted in ``blocks_waited_on_calibration``).
    arrays : sequence of (name, devices, mics_m)
        Synchronous arrays among the devices (their mics are devices of their own, :mod:`stream.channels`):
        every adopted geometry places them (:meth:`Geometry.with_arrays`: each array's pose from its mics'
        positions and its known internal geometry).
    """

    def __init__(self, n_devices: int, *, template: np.ndarray, sample_rate_hz: float, odometry: OdometryLog,
                 recalibrate_every: int = 8, method: Method = "hybrid", apply: Apply = "drift",
                 sigma_tdoa_s: float = 5e-5, sigma_odo_m: float = 0.01,
                 speed_of_sound_m_s: float = estimators.SPEED_OF_SOUND_M_S, threshold: float = 10.0,
                 solver: Callable[[CalibrationSnapshot], Geometry] | None = None,
                 on_geometry: Callable[[Geometry], None] | None = None,
                 executor: Literal["thread", "process"] = "thread", max_events: int = 200,
                 finish_timeout_s: float = 60.0, final_solve: bool = True,
                 device_names: Sequence[str] = (), replay_latency_s: float | None = None,
                 arrays: Sequence[tuple[str, Sequence[int], np.ndarray]] = ()) -> None:
        if n_devices < 3:
            raise ConfigError(f"calibration needs >= 3 devices; {n_devices=}")
        if int(recalibrate_every) < 3:
            raise ConfigError(f"recalibrate_every={recalibrate_every} must be >= 3 events")
        if method not in ("hybrid", "baseline"):
            raise ConfigError(f"calibration_method={method!r} must be 'hybrid' or 'baseline'")
        if apply not in ("drift", "offsets", "none"):
            raise ConfigError(f"calibration_apply={apply!r} must be 'drift', 'offsets' or 'none'")
        self.n_devices = n_devices
        self.sample_rate_hz = float(sample_rate_hz)
        self.odometry = odometry
        self.recalibrate_every = int(recalibrate_every)
        self.method: Method = method
        self.apply: Apply = apply
        self.sigma_tdoa_s = float(sigma_tdoa_s)
        self.sigma_odo_m = float(sigma_odo_m)
        self.speed_of_sound_m_s = float(speed_of_sound_m_s)
        self.max_events = int(max_events)
        self.finish_timeout_s = float(finish_timeout_s)
        if replay_latency_s is not None and not (math.isfinite(replay_latency_s) and replay_latency_s >= 0):
            raise ConfigError(f"{replay_latency_s=} must be None or a finite number of seconds >= 0")
        self.replay_latency_s = replay_latency_s
        self.blocks_waited = 0                         # frame boundaries that waited for a solve (replay only)
        self.final_solve = final_solve
        self.device_names = tuple(device_names) or tuple(f"dev{i}" for i in range(n_devices))
        self.solver = solver or calibrate
        self.on_geometry = on_geometry
        self.arrays = tuple(arrays)
        _, iv = odometry.snapshot()
        min_sep = 0.5 * float(np.min(iv)) if len(iv) else 0.5
        min_sep = max(min_sep, 1.2 * len(template) / sample_rate_hz)
        self.detectors = [ChirpDetector(template, sample_rate_hz=sample_rate_hz, min_separation_s=min_sep,
                                        threshold=threshold) for _ in range(n_devices)]
        self.observations = CalibrationObservations(n_devices, odometry)
        self.clocks: list[ClockMap] | None = None
        self.geometry: Geometry | None = None          # last good geometry
        self.history: list[SolveRecord] = []
        self.messages: list[str] = []
        self.step_ms: list[float] = []
        self.finish_wait_s = 0.0                       # waited for solves after the last block (bounded)
        self._n_solved_events = 0
        self._next_attempt_s = -math.inf
        self._future: concurrent.futures.Future | None = None
        self._record: SolveRecord | None = None
        self._submitted_at = 0.0
        self._executor_kind = executor
        self._executor: concurrent.futures.Executor | None = None

    # wiring ----------------------------------------------------------------------------------
    def bind(self, clocks: Sequence[ClockMap]) -> None:
        """Attach each device's clock map (the pipeline's conditioners)."""
        if len(clocks) != self.n_devices:
            raise ValueError(f"{len(clocks)=} must equal {self.n_devices=}")
        self.clocks = list(clocks)

    def _pool(self) -> concurrent.futures.Executor:
        if self._executor is None:
            if self._executor_kind == "process":
                self._executor = concurrent.futures.ProcessPoolExecutor(max_workers=1)
            else:
                self._executor = concurrent.futures.ThreadPoolExecutor(max_workers=1,
                                                                       thread_name_prefix="calibration")
        return self._executor

    def close(self) -> None:
        """Stop the worker (a running solve is abandoned)."""
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None

    def __enter__(self) -> "StreamCalibrator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # the audio path --------------------------------------------------------------------------
    def observe(self, device_id: int, samples: np.ndarray, *, last: bool = False) -> None:
        """Conditioned samples of one device (its own clock): run its chirp detector (cheap per hop)."""
        det = self.detectors[device_id]
        clock = self.clocks[device_id]
        for onset, snr in det.process(samples, last=last):
            self.observations.add(ChirpDetection(device_id, onset, clock.clock_s(onset), snr))
        fb = det.final_before
        self.observations.final_clock_s[device_id] = math.inf if fb == math.inf else clock.clock_s(fb)

    def step(self, *, time_s: float,
             delta_s: np.ndarray | Callable[[], np.ndarray | None] | None) -> Geometry | None:
        """Once per block, at the frame boundary: collect a finished solve (``future.done()``, never waits) and
        start the next one when ``recalibrate_every`` new events are complete.

        Parameters
        ----------
        time_s : float
            Stream time of the block (device 0's clock).
        delta_s : ndarray, shape (n_devices,), or a callable returning it, or None
            Current clock relation ``c_i - c_0`` of the stream (NaN for a device that is not aligned); None
            before the coarse alignment. A callable is only evaluated when a snapshot is attempted (at most
            every ``ATTEMPT_EVERY_S`` of stream time).

        Returns
        -------
        Geometry or None
            A newly adopted (converged) geometry, to apply at this frame boundary.
        """
        t0 = time.perf_counter()
        adopted = None
        if self._future is not None:
            if self.replay_latency_s is None:
                if self._future.done():
                    adopted = self._collect(time_s)
            elif time_s >= self._record.snapshot_time_s + self.replay_latency_s:
                # replay: adopt at a fixed stream time after the submit, whatever the machine's speed
                if not self._future.done():
                    self.blocks_waited += 1
                adopted = self._wait(time_s)
        if self._future is None and time_s >= self._next_attempt_s:
            self._next_attempt_s = time_s + ATTEMPT_EVERY_S
            delta = delta_s() if callable(delta_s) else delta_s
            if delta is not None:
                self._maybe_submit(time_s, delta, n_min=self._n_solved_events + self.recalibrate_every)
        self.step_ms.append(1e3 * (time.perf_counter() - t0))
        return adopted

    def finish(self, *, time_s: float, delta_s: np.ndarray | None) -> Geometry | None:
        """End of stream: a last solve over every new complete event, then wait (bounded) for a pending one."""
        for d, det in enumerate(self.detectors):
            if not det.ended:
                self.observe(d, np.zeros(0, np.float32), last=True)
        adopted = None
        if self._future is not None:
            adopted = self._wait(time_s) or adopted
        if self.final_solve and delta_s is not None:
            self._maybe_submit(time_s, delta_s, n_min=self._n_solved_events + 1)
            if self._future is not None:
                adopted = self._wait(time_s) or adopted
        return adopted

    # internals -------------------------------------------------------------------------------
    def _wait(self, time_s: float) -> Geometry | None:
        t0 = time.perf_counter()
        concurrent.futures.wait([self._future], timeout=self.finish_timeout_s)
        self.finish_wait_s += time.perf_counter() - t0
        if not self._future.done():
            rec = self._record
            rec.status = "abandoned"
            rec.message = (f"t={time_s:.1f} s: the calibration solve over {rec.n_events} events did not finish "
                           f"within {self.finish_timeout_s:g} s of the end of the stream; "
                           f"{self._kept_sentence()}")
            self._say(rec.message)
            self._future.cancel()
            self._future = None
            return None
        return self._collect(time_s)

    def _maybe_submit(self, time_s: float, delta_s: np.ndarray, *, n_min: int) -> None:
        snap = self.observations.snapshot(
            np.asarray(delta_s, float), time_s=time_s, n_min=n_min, max_events=self.max_events,
            sigma_tdoa_s=self.sigma_tdoa_s, sigma_odo_m=self.sigma_odo_m, method=self.method,
            speed_of_sound_m_s=self.speed_of_sound_m_s, device_names=self.device_names)
        if snap is None:
            return
        self._n_solved_events = snap.first_event + snap.n_events
        self._record = SolveRecord(time_s, snap.n_events, snap.first_event)
        self.history.append(self._record)
        self._submitted_at = time.perf_counter()
        self._future = self._pool().submit(self.solver, snap)
        log.info("t=%.1f s: calibration solve started over %d events.", time_s, snap.n_events)

    def _kept_sentence(self) -> str:
        g = self.geometry
        if g is None:
            return "there is no good geometry yet, so the stream keeps its own alignment."
        return f"kept the last good geometry (solved at t={g.solved_at_time_s:.1f} s over {g.n_events} events)."

    def _collect(self, time_s: float) -> Geometry | None:
        fut, rec = self._future, self._record
        self._future = None
        rec.wait_s = time.perf_counter() - self._submitted_at
        try:
            g = fut.result()   # re-raises the worker's exception here, on the stream's thread
        except Exception as err:  # noqa: BLE001 - a failed solve must never stop the stream
            rec.status = "failed"
            rec.message = (f"t={time_s:.1f} s: the calibration solve over {rec.n_events} events failed "
                           f"({type(err).__name__}: {err}); {self._kept_sentence()}")
            self._say(rec.message)
            return None
        rec.verdict = g.verdict
        rec.solve_time_s = g.solve_time_s
        if not g.converged:
            rec.status = "rejected"
            rec.message = (f"t={time_s:.1f} s: the calibration solve over {rec.n_events} events ended "
                           f"'{g.verdict}'; {self._kept_sentence()}")
            self._say(rec.message)
            return None
        rec.status = "adopted"
        rec.adopted_at_time_s = time_s
        if self.arrays:
            g = g.with_arrays(self.arrays)
        self.geometry = g
        log.info("t=%.1f s: new geometry adopted (%s).", time_s, g.summary())
        if self.on_geometry is not None:
            try:
                self.on_geometry(g)
            except Exception as err:  # noqa: BLE001 - publishing is a side output
                self._say(f"t={time_s:.1f} s: publishing the new geometry failed ({type(err).__name__}: {err}); "
                          "the stream uses it anyway.")
        return g

    def _say(self, message: str) -> None:
        self.messages.append(message)
        log.warning("%s", message)

    def report(self) -> dict[str, Any]:
        """The calibration section of report.json."""
        step = np.asarray(self.step_ms) if self.step_ms else np.zeros(1)
        solves = [dataclasses.asdict(r) for r in self.history]
        times = [r.solve_time_s for r in self.history if r.solve_time_s is not None]
        return {
            "method": self.method,
            "apply": self.apply,
            "recalibrate_every": self.recalibrate_every,
            "executor": self._executor_kind,
            "n_detections": self.observations.n_detections.tolist(),
            "n_solves": len(self.history),
            "n_adopted": sum(r.status == "adopted" for r in self.history),
            "solves": solves,
            "solve_time_s_median": float(np.median(times)) if times else None,
            "solve_time_s_max": float(np.max(times)) if times else None,
            "step_ms_median": float(np.median(step)),
            "step_ms_max": float(np.max(step)),
            "replay_latency_s": self.replay_latency_s,
            "blocks_waited_on_calibration": self.blocks_waited,   # 0 unless a replay waited (replay_latency_s)
            "finish_wait_s": self.finish_wait_s,
            "geometry": self.geometry.to_dict() if self.geometry is not None else None,
            "messages": list(self.messages),
        }


# ----------------------------------------------------------------------------------------------------------------
# Batch calibration (adhoc-array calibrate)
# ----------------------------------------------------------------------------------------------------------------
