"""Asynchronous microphone-array calibration from hybrid TDOA and odometry.

Implements Zhang, Wang, Kong, "Asynchronous Microphone Array Calibration Using Hybrid TDOA
Information" (arXiv 2403.05791), with a damped, robust, sparse solver.

Model
-----
``N`` asynchronous microphones with position ``x_i``, time offset ``tau_i`` and clock drift ``delta_i``;
``K`` sound events at ``s_j`` emitted at known times ``t_j`` (``t_0 = 0``, ``interval_s[j] = t_{j+1} - t_j``)
by a moving source whose odometry ``m_j = s_{j+1} - s_j + v_j`` is measured. Arrival time on mic ``i``'s
clock (eq. 4)::

    T_ij = |x_i - s_j| / c + tau_i + (1 + delta_i) t_j

Measurements (all optional per entry: NaN marks a missed chirp):

- TDOA-S, adjacent events at one mic, no offset (eq. 5), ``tdoa_events_s[j, i] = T_{i,j+1} - T_{i,j}``::

      (|x_i - s_{j+1}| - |x_i - s_j|) / c + (1 + delta_i) interval_s[j]

- TDOA-M, mic ``i`` against mic 0 at one event (eq. 6), ``tdoa_mics_s[j, i] = T_ij - T_0j``
  (column 0 unused)::

      (|x_i - s_j| - |x_0 - s_j|) / c + (tau_i - tau_0) + (delta_i - delta_0) t_j

- odometry ``odometry_m[j] = s_{j+1} - s_j + v_j`` in the source's odometry frame (eq. 9).

Both TDOAs follow :mod:`estimators.conventions` (``tdoa[i, j] = toa[i] - toa[j]``): TDOA-M is ``tdoa[i, 0]``.

Solver
------
The weighted nonlinear least squares of eq. (10), ``W = diag(sigma_tdoa^2 I, sigma_odo^2 I)``, is solved by
Levenberg-Marquardt (More's scaling, Nielsen's damping update, a trust region on position steps) with a robust
loss (soft-L1 by default, IRLS, its scale following the robust residual scale so that far from the solution
it is plain least squares), on the fixed sparsity pattern of the Jacobian (``J^T W J`` summed over its stored
entries, then Cholesky). Budgets are iterations, never wall-clock time. Each start ends with a verdict:

- the minimum is *certified* mic by mic: each mic's own subproblem (its TDOA-S and TDOA-M, events and mic 0
  fixed) is searched globally on a grid and refined; a mic with a clearly better position elsewhere makes the
  verdict ``suspect_local_minimum`` and the next start moves it there;
- gross errors are rejected before the verdict, and the verdict is on the kept measurements (below);
- residuals must be plausible for the assumed noise (robust scale, cost per degree of freedom, per-mic fit,
  odometry consistency); an implausible but certified minimum triggers one more start and is accepted as
  ``converged`` if reached again.

Gross errors (``reject_sigma``, :class:`RejectedMeasurement`): at a converged start, linearised outlier tests
with the robust-loss weights (studentised residual of each TDOA; for each emission interval the score test
of one more parameter, its error ``e_j``, shared by the TDOA-S of all mics in row ``j``), in robustly scaled
sigmas. A round frees the worst interval above ``reject_sigma`` (a wrong ``interval_s[j]``, e.g. 1 ms off,
moves every TDOA-S of its row together and is otherwise absorbed by bending the trajectory against the
odometry), else drops the worst TDOA of each mic above it (one at a time per mic: a gross error inflates the
residuals of its own mic most); the solution is re-solved on the kept set and the tests repeat until nothing
is left (at most 10 % of the TDOAs). Chi-square, robust scale, verdict and the Fisher information
(``with_covariance``, estimated interval errors as nuisance parameters) are of the kept set
(:func:`without_rejected`, :func:`crlb` with ``unknown_intervals``). A minimum that needed an interval
estimated is accepted from the built-in initialisation, from another start only once a second start reaches
it (an interval error can also absorb the misfit of a wrong basin). Odometry steps are only rejected with
``reject_odometry=True``: on the real data one vertical step is all that separates the two event layers, and
without it the events collapse onto one plane where any mic can be mirrored through it (a wrong basin that
then fits).

Restarts after a bad verdict use a built-in initialisation instead of random draws: events from the
integrated odometry, each mic by a grid search on its own TDOA-S (position and least-squares drift), offsets
from TDOA-M. ``method="baseline"`` drops TDOA-S (the TDOA-M + odometry method the paper compares with); only
relative drifts are observable then (``delta_0 = 0``). Its built-in start (the first without ``init``, the
third with it) places the reference mic 0, which is in every TDOA-M, by a global search (each grid point
scored by how well all other mics' TDOA-M can then be fitted, a Gram-matrix expansion of the least-squares
residual) and the other mics by a grid search on their own TDOA-M; other baseline starts draw the mics at
random around the odometry. A converged baseline start whose mic 0 scores clearly worse than that search's
best is solved again from there and the lower cost kept (mic 0 has no subproblem of its own to certify).

The small dense work inside every iteration and search (residuals, ``J^T W J``, the LM damping and trial step,
the per-mic grid scores and their batched refinement, the baseline's search for mic 0) runs in numba kernels:
compiled on first use after an install (seconds), then loaded from the on-disk cache (the stream's pipeline
does this before its first block when it calibrates).

Frames
------
- Gauge (paper Sec. II): ``s_0 = 0``, ``(s_1)_y = (s_1)_z = (s_2)_z = 0``, ``tau_0 = 0``. The solver rotates the
  odometry into the frame of its own first three integrated points, solves there, and rotates the result
  back: :class:`CalibrationResult` positions are in the odometry frame with event 0 at the origin.
- Mic frame (Appendix A): ``x_0 = 0``, ``(x_1)_y = (x_1)_z = (x_2)_z = 0``, offsets ``tau_i - tau_0`` and drifts
  ``delta_i - delta_0``; errors are scored there (:func:`to_mic_frame`, :func:`mic_frame_error`).

Units: seconds, metres, drift in ppm (``delta = drift_ppm * 1e-6``); mic 0 is the reference.
"""
from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from typing import Literal

import numba
import numpy as np
import scipy.linalg
import scipy.linalg.lapack
import scipy.sparse

from .conventions import SPEED_OF_SOUND_M_S

__all__ = [
    "CalibrationResult",
    "RejectedMeasurement",
    "CrlbResult",
    "HybridTdoaProblem",
    "MicFrameScene",
    "NoiseLevels",
    "Scene",
    "crlb",
    "estimate_noise_levels",
    "mic_frame_error",
    "random_initial_scene",
    "simulate_problem",
    "solve",
    "to_mic_frame",
    "without_rejected",
]

logger = logging.getLogger(__name__)

Method = Literal["hybrid", "baseline"]
Loss = Literal["linear", "soft_l1", "huber"]
Verdict = Literal["converged", "diverged", "suspect_local_minimum", "max_iterations"]

_PPM = 1e-6
_DENSE_LIMIT = 3_000_000  # n_residuals * n_params below which a dense Jacobian is faster

_jit = numba.njit(cache=True, nogil=True, error_model="numpy")  # x / 0 gives inf or NaN, as numpy
_NO_MASK = np.zeros(0)  # an empty mask keeps every residual (compiled helpers)


def _readonly(a, *, shape=None, name="array") -> np.ndarray:
    out = np.array(a, dtype=np.float64, copy=True)
    if shape is not None and out.shape != shape:
        raise ValueError(f"{name} has shape {out.shape}, expected {shape}")
    out.setflags(write=False)
    return out


# --------------------------------------------------------------------------------------------------------------
# Data containers
# --------------------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class HybridTdoaProblem:
    """Measurements of one calibration session (immutable).

    Parameters
    ----------
    tdoa_events_s : ndarray, shape (K-1, N), float, or None
        TDOA-S (eq. 5): ``T_{i,j+1} - T_{i,j}`` on mic ``i``'s clock, seconds; NaN = missing. None for a
        TDOA-M-only session (then only ``method="baseline"`` can be solved).
    tdoa_mics_s : ndarray, shape (K, N), float
        TDOA-M (eq. 6): ``T_ij - T_0j``, seconds; column 0 is ignored; NaN = missing.
    odometry_m : ndarray, shape (K-1, 3), float
        Measured displacement ``s_{j+1} - s_j`` in the source's odometry frame, metres; NaN rows = missing.
    interval_s : ndarray, shape (K-1,), float
        Known emission intervals ``t_{j+1} - t_j``, seconds (on the emitter's clock).
    sigma_tdoa_s : float
        TDOA noise standard deviation, seconds (both kinds unless ``sigma_tdoa_mics_s`` is given).
    sigma_odo_m : float
        Odometry noise standard deviation per axis per step, metres.
    speed_of_sound_m_s : float
    sigma_tdoa_mics_s : float or None
        Separate TDOA-M noise std, seconds (e.g. from :func:`estimate_noise_levels`).
    """

    tdoa_events_s: np.ndarray | None
    tdoa_mics_s: np.ndarray
    odometry_m: np.ndarray
    interval_s: np.ndarray
    sigma_tdoa_s: float
    sigma_odo_m: float
    speed_of_sound_m_s: float = SPEED_OF_SOUND_M_S
    sigma_tdoa_mics_s: float | None = None

    def __post_init__(self):
        tm = np.asarray(self.tdoa_mics_s, dtype=np.float64)
        if tm.ndim != 2 or tm.shape[0] < 3 or tm.shape[1] < 3:
            raise ValueError(f"tdoa_mics_s shape {tm.shape} must be (n_events >= 3, n_mics >= 3)")
        k, n = tm.shape
        object.__setattr__(self, "tdoa_mics_s", _readonly(tm))
        if self.tdoa_events_s is not None:
            object.__setattr__(self, "tdoa_events_s",
                               _readonly(self.tdoa_events_s, shape=(k - 1, n), name="tdoa_events_s"))
        object.__setattr__(self, "odometry_m", _readonly(self.odometry_m, shape=(k - 1, 3), name="odometry_m"))
        iv = _readonly(self.interval_s, shape=(k - 1,), name="interval_s")
        if not np.all(np.isfinite(iv)) or np.any(iv < 0):
            raise ValueError("interval_s must be finite and >= 0 seconds")
        object.__setattr__(self, "interval_s", iv)
        for name in ("sigma_tdoa_s", "sigma_odo_m", "speed_of_sound_m_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name}={v} must be a finite positive number")
        if self.sigma_tdoa_mics_s is not None and not (np.isfinite(self.sigma_tdoa_mics_s)
                                                         and self.sigma_tdoa_mics_s > 0):
            raise ValueError(f"sigma_tdoa_mics_s={self.sigma_tdoa_mics_s} must be a finite positive number or None")
        if not np.all(np.isfinite(self.odometry_m[:2])):
            raise ValueError("odometry_m rows 0 and 1 are needed to fix the frame")

    @property
    def n_mics(self) -> int:
        return self.tdoa_mics_s.shape[1]

    @property
    def n_events(self) -> int:
        return self.tdoa_mics_s.shape[0]

    @property
    def emission_times_s(self) -> np.ndarray:
        """ndarray, shape (K,): ``t_j`` with ``t_0 = 0``, seconds."""
        return np.concatenate([[0.0], np.cumsum(self.interval_s)])

    @property
    def sigma_events_s(self) -> float:
        return float(self.sigma_tdoa_s)

    @property
    def sigma_mics_s(self) -> float:
        return float(self.sigma_tdoa_mics_s if self.sigma_tdoa_mics_s is not None else self.sigma_tdoa_s)


@dataclasses.dataclass(frozen=True)
class Scene:
    """Mic and event geometry with clock parameters (a truth, an initial value, or an estimate).

    Parameters
    ----------
    mic_positions_m : ndarray, shape (N, 3)
    event_positions_m : ndarray, shape (K, 3)
    offsets_s : ndarray, shape (N,), optional
        ``tau_i``, seconds (only differences to mic 0 are observable). Default 0.
    drifts_ppm : ndarray, shape (N,), optional
        ``delta_i * 1e6``. Default 0.
    """

    mic_positions_m: np.ndarray
    event_positions_m: np.ndarray
    offsets_s: np.ndarray | None = None
    drifts_ppm: np.ndarray | None = None

    def __post_init__(self):
        x = _readonly(self.mic_positions_m, name="mic_positions_m")
        s = _readonly(self.event_positions_m, name="event_positions_m")
        if x.ndim != 2 or x.shape[1] != 3 or s.ndim != 2 or s.shape[1] != 3:
            raise ValueError(f"positions must be (n, 3): mics {x.shape}, events {s.shape}")
        n = x.shape[0]
        off = np.zeros(n) if self.offsets_s is None else self.offsets_s
        dr = np.zeros(n) if self.drifts_ppm is None else self.drifts_ppm
        object.__setattr__(self, "mic_positions_m", x)
        object.__setattr__(self, "event_positions_m", s)
        object.__setattr__(self, "offsets_s", _readonly(off, shape=(n,), name="offsets_s"))
        object.__setattr__(self, "drifts_ppm", _readonly(dr, shape=(n,), name="drifts_ppm"))


@dataclasses.dataclass(frozen=True)
class RejectedMeasurement:
    """One measurement :func:`solve` rejected as a gross error (see its ``reject_sigma``).

    Attributes
    ----------
    kind : {"interval", "tdoa_events", "tdoa_mics", "odometry"}
        ``interval``: the emission interval ``interval_s[event]`` (events ``event`` to ``event + 1``) is
        estimated instead of taken as given (its TDOA-S stay in, see
        ``CalibrationResult.interval_corrections_s``); ``tdoa_events``: TDOA-S ``tdoa_events_s[event, mic]``;
        ``tdoa_mics``: TDOA-M ``tdoa_mics_s[event, mic]``; ``odometry``: the step ``odometry_m[event]`` (3 axes).
    event : int
        Row of the measurement in the problem's array (interval or step index for those kinds).
    mic : int
        Column (mic) of a TDOA entry; -1 for the other kinds.
    residual : float
        At the final estimate, which does not use the measurement. TDOA: measured minus predicted, seconds;
        interval: estimated error (true interval = given + error), seconds; odometry: norm of measured minus
        predicted step, metres.
    normalised_residual : float
        The same in units of its noise std: TDOA residual / sigma; interval error / its std (Fisher
        information of the kept set); odometry: norm of the whitened 3-vector.
    statistic : float
        The test statistic that rejected it, robustly scaled sigmas (> ``reject_sigma``).
    reason : str
        One sentence: what was wrong and why it was rejected.
    """

    kind: Literal["interval", "tdoa_events", "tdoa_mics", "odometry"]
    event: int
    mic: int
    residual: float
    normalised_residual: float
    statistic: float
    reason: str


@dataclasses.dataclass(frozen=True)
class CalibrationResult:
    """Outcome of :func:`solve` (immutable; safe to hand over from a worker thread).

    Attributes
    ----------
    scene : Scene
        Estimate in the odometry frame with event 0 at the origin; ``offsets_s[0] = 0``; for
        ``method="baseline"`` drifts are relative to mic 0 (``drifts_ppm[0] = 0``).
    method : {"hybrid", "baseline"}
    verdict : {"converged", "diverged", "suspect_local_minimum", "max_iterations"}
        ``converged``: step/cost criteria met and the residuals of the kept measurements plausible (robust
        normalised residual scale ``residual_scale`` <= ``max_residual_scale``, no mic with a systematically bad
        fit, odometry consistent); rejected gross errors (``rejected``) do not count against it;
        ``suspect_local_minimum``: numerically converged but residuals implausible;
        ``max_iterations``: iteration budget spent; ``diverged``: non-finite or exploding estimate.
    cost : float
        Final (robust) cost ``sum rho(r_w)`` of the kept whitened residuals.
    chi2_per_dof : float
        ``sum r_w^2 / (n_kept - n_params)`` over the kept measurements (not robust; estimated interval
        errors count as parameters).
    residual_scale : float
        ``1.4826 * median |r_w|`` of the kept measurements: about 1 when the assumed noise levels are right.
    inlier_fraction : float
        Share of kept whitened residuals below 5 * max(1, residual_scale).
    n_iterations : int
        LM iterations summed over all starts.
    n_starts_used : int
    outliers_tdoa_events : ndarray, shape (K-1, N), bool
        TDOA-S rejected as gross mis-detections (see ``reject_sigma``).
    outliers_tdoa_mics : ndarray, shape (K, N), bool
        TDOA-M rejected as gross mis-detections.
    mic_frame_location_std_m : ndarray, shape (N,) or None
        Per-mic location std in the mic frame from the Fisher information of the kept measurements at the
        estimate (estimated interval errors as nuisance parameters), covariance carried through the Jacobian
        of the frame change (None unless ``with_covariance``).
    rejected : tuple of RejectedMeasurement
        Every gross error rejected, with its residual and the reason (empty when all measurements fit).
    outliers_odometry : ndarray, shape (K-1,), bool, or None
        Odometry steps rejected (None: none).
    interval_corrections_s : ndarray, shape (K-1,), or None
        Estimated errors of the emission intervals, seconds: ``interval_s + interval_corrections_s`` is what
        the TDOA-S fit; non-zero only for rejected intervals (None: none).
    """

    scene: Scene
    method: Method
    verdict: Verdict
    cost: float
    chi2_per_dof: float
    residual_scale: float
    inlier_fraction: float
    n_iterations: int
    n_starts_used: int
    outliers_tdoa_events: np.ndarray
    outliers_tdoa_mics: np.ndarray
    mic_frame_location_std_m: np.ndarray | None = None
    rejected: tuple[RejectedMeasurement, ...] = ()
    outliers_odometry: np.ndarray | None = None
    interval_corrections_s: np.ndarray | None = None

    @property
    def mic_positions_m(self) -> np.ndarray:
        return self.scene.mic_positions_m

    @property
    def event_positions_m(self) -> np.ndarray:
        return self.scene.event_positions_m

    @property
    def offsets_s(self) -> np.ndarray:
        return self.scene.offsets_s

    @property
    def drifts_ppm(self) -> np.ndarray:
        return self.scene.drifts_ppm

    @property
    def estimated_intervals(self) -> np.ndarray:
        """ndarray of int: indices ``j`` of the emission intervals estimated instead of given."""
        return np.array(sorted(m.event for m in self.rejected if m.kind == "interval"), dtype=np.intp)


@dataclasses.dataclass(frozen=True)
class MicFrameScene:
    """A scene expressed in the mic frame of Appendix A (eq. 17-18).

    Attributes
    ----------
    mic_positions_m : ndarray, shape (N, 3)
        ``x_0 = 0``, ``x_1`` on +x, ``x_2`` in the x-y plane (positive y).
    event_positions_m : ndarray, shape (K, 3)
    offsets_s : ndarray, shape (N,)
        ``tau_i - tau_0``.
    drifts_ppm : ndarray, shape (N,)
        ``(delta_i - delta_0) * 1e6``.
    rotation : ndarray, shape (3, 3)
        ``x_mic = rotation @ (x - x_0)``.
    """

    mic_positions_m: np.ndarray
    event_positions_m: np.ndarray
    offsets_s: np.ndarray
    drifts_ppm: np.ndarray
    rotation: np.ndarray


@dataclasses.dataclass(frozen=True)
class CrlbResult:
    """Cramer-Rao bound (eqs. 11-16) of one problem at a true scene, scored in the mic frame.

    ``*_std_*`` are the paper's D_CRLB (eq. 16): ``sqrt(mean_{i>=1} var_i)`` where ``var_i`` sums the
    variances of mic ``i``'s mic-frame coordinates (x of mic 1, x-y of mic 2, x-y-z of the others).

    Attributes
    ----------
    location_std_m, offset_std_s, drift_std_ppm : float
        Covariance carried from the solver gauge into the mic frame with the full Jacobian of the frame
        change (the frame moves with the estimated mics 0, 1, 2).
    location_std_m_authors, offset_std_s_authors, drift_std_ppm_authors : float
        As the authors' code computes it: hybrid, the sound-frame covariance only rotated (eq. 15 with
        ``A`` built from the true rotation, ignoring how the frame depends on mics 0-2); baseline, solved
        directly in the true mic frame with the odometry rotated into it by the true rotation.
    per_mic_location_std_m : ndarray, shape (N,)
        Full-Jacobian per-mic location std (mic 0 is 0 by construction).
    mic_frame_covariance : ndarray, shape (5N, 5N)
        Full-Jacobian covariance of ``[x_mic (N*3, row-major), offsets_s (N), deltas (N, unitless)]``.
    """

    method: str
    location_std_m: float
    offset_std_s: float
    drift_std_ppm: float
    location_std_m_authors: float
    offset_std_s_authors: float
    drift_std_ppm_authors: float
    per_mic_location_std_m: np.ndarray
    mic_frame_covariance: np.ndarray


@dataclasses.dataclass(frozen=True)
class NoiseLevels:
    """TDOA noise levels estimated as in Appendix B.

    Attributes
    ----------
    tdoa_events_std_s : float
        Pooled std of TDOA-S residuals after removing the geometry and a least-squares drift per mic.
    tdoa_mics_std_s : float
        Pooled std of TDOA-M residuals after removing the geometry and a least-squares offset + drift per mic.
    per_mic_events_std_s : ndarray, shape (N,)
    per_mic_mics_std_s : ndarray, shape (N,)
        Entry 0 is NaN (reference mic).
    """

    tdoa_events_std_s: float
    tdoa_mics_std_s: float
    per_mic_events_std_s: np.ndarray
    per_mic_mics_std_s: np.ndarray


# --------------------------------------------------------------------------------------------------------------
# Frames
# --------------------------------------------------------------------------------------------------------------
def _frame_of(p0: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Rotation ``R`` with ``R @ (p - p0)`` putting p1 on +x and p2 in the x-y plane (y > 0) (``any2s``)."""
    ex = p1 - p0
    ex = ex / np.linalg.norm(ex)
    ey = (p2 - p0) - np.dot(p2 - p0, ex) * ex
    ey = ey / np.linalg.norm(ey)
    return np.stack([ex, ey, np.cross(ex, ey)])


def to_mic_frame(scene: Scene | CalibrationResult) -> MicFrameScene:
    """Express a scene in the mic frame of Appendix A (``x_0 = 0``, ``x_1`` on +x, ``x_2`` in x-y).

    Parameters
    ----------
    scene : Scene or CalibrationResult
        Needs at least 3 mics, mics 0, 1, 2 not collinear.
    """
    if isinstance(scene, CalibrationResult):
        scene = scene.scene
    x = scene.mic_positions_m
    if x.shape[0] < 3:
        raise ValueError(f"n_mics={x.shape[0]} must be >= 3 for the mic frame")
    r = _frame_of(x[0], x[1], x[2])
    return MicFrameScene(
        mic_positions_m=_readonly((x - x[0]) @ r.T),
        event_positions_m=_readonly((scene.event_positions_m - x[0]) @ r.T),
        offsets_s=_readonly(scene.offsets_s - scene.offsets_s[0]),
        drifts_ppm=_readonly(scene.drifts_ppm - scene.drifts_ppm[0]),
        rotation=_readonly(r),
    )


def mic_frame_error(estimate: Scene | CalibrationResult, truth: Scene) -> dict[str, float]:
    """Errors scored as in the paper (``compute_error.m``), both scenes in their own mic frames.

    Returns
    -------
    dict
        ``location_m``: ``sqrt(mean_{i>=1} |x_i - x_i_true|^2)``; ``offset_s``: RMS of offset errors (mics >= 1);
        ``drift_ppm``: RMS of relative drift errors (mics >= 1); ``events_m``: RMS event location error.
    """
    a, b = to_mic_frame(estimate), to_mic_frame(truth)
    return {
        "location_m": float(np.sqrt(np.mean(np.sum((a.mic_positions_m[1:] - b.mic_positions_m[1:]) ** 2, 1)))),
        "offset_s": float(np.sqrt(np.mean((a.offsets_s[1:] - b.offsets_s[1:]) ** 2))),
        "drift_ppm": float(np.sqrt(np.mean((a.drifts_ppm[1:] - b.drifts_ppm[1:]) ** 2))),
        "events_m": float(np.sqrt(np.mean(np.sum((a.event_positions_m - b.event_positions_m) ** 2, 1)))),
    }


# --------------------------------------------------------------------------------------------------------------
# Problem layout: parameter vector, gauge, measurement rows, Jacobian pattern
# --------------------------------------------------------------------------------------------------------------
# Full parameter vector: [x (3N, row-major), tau (N), delta (N, unitless), s (3K, row-major), e (n_e)], ``e`` the
# errors of the emission intervals ``free_intervals`` (none unless a gross interval error was detected).
class _Layout:
    """Index arrays shared by every residual/Jacobian evaluation of one problem and gauge.

    Every residual is ``w * (sum_g coef_g |x_m - s_e| + L @ p - y)``: at most two mic-event distances
    (TDOA-S: ``+|x_i - s_{j+1}|, -|x_i - s_j|``; TDOA-M: ``+|x_i - s_j|, -|x_0 - s_j|``; odometry: none) plus a
    constant linear part ``L`` (drift, offset and odometry terms). One evaluation computes the (N, K)
    distances and unit vectors once; the Jacobian entries are gathers of them, summed into a dense array
    (small problems) or CSR data with a fixed pattern (large ones).

    ``free_intervals`` (interval indices ``j``): the given ``interval_s[j]`` is taken as grossly wrong and its
    error ``e_j`` (seconds, true interval = given + ``e_j``) is estimated. It enters TDOA-S row ``j`` of every mic
    as ``+e_j`` (eq. 5; its product with the drift, ``delta_i e_j`` < 1e-7 s for ``e_j`` < 1 ms, is dropped) and
    is ignored in TDOA-M (eq. 6: ``(delta_i - delta_0) e_j``, < 1e-8 s). Rows are the same for every
    ``free_intervals``: a residual mask carries over from one layout to the other.
    """

    def __init__(self, problem: HybridTdoaProblem, method: str, gauge: str = "sound",
                 odometry_gauge_m: np.ndarray | None = None, free_intervals=()):
        n, k = problem.n_mics, problem.n_events
        self.n, self.k = n, k
        self.c = c = problem.speed_of_sound_m_s
        self.problem, self.method, self.gauge, self.odometry_gauge_m = problem, method, gauge, odometry_gauge_m
        self.free_intervals = fi = np.asarray(free_intervals, dtype=np.intp).reshape(-1)
        self.n_e = n_e = len(fi)
        self.n_full = 5 * n + 3 * k + n_e
        o_tau, o_del, o_s, o_e = 3 * n, 4 * n, 5 * n, 5 * n + 3 * k
        self.o_tau, self.o_del, self.o_s, self.o_e = o_tau, o_del, o_s, o_e
        free = np.ones(self.n_full, dtype=bool)
        free[o_tau] = False  # tau_0 = 0
        if method == "baseline":
            free[o_del] = False  # only relative drifts are observable from TDOA-M
        if gauge == "sound":
            free[o_s:o_s + 3] = False  # s_0 = 0
            free[o_s + 4:o_s + 6] = False  # (s_1)_y = (s_1)_z = 0
            free[o_s + 8] = False  # (s_2)_z = 0
        elif gauge == "mic":
            free[0:3] = False  # x_0 = 0
            free[4:6] = False  # (x_1)_y = (x_1)_z = 0
            free[8] = False  # (x_2)_z = 0
        else:  # pragma: no cover - internal
            raise ValueError(f"{gauge=}")
        self.free = free
        self.col_of = np.full(self.n_full, -1, dtype=np.intp)
        self.col_of[free] = np.arange(int(free.sum()))
        self.n_free = int(free.sum())

        t = problem.emission_times_s
        # TDOA-S rows (eq. 5)
        if method == "hybrid":
            if problem.tdoa_events_s is None:
                raise ValueError("method='hybrid' needs tdoa_events_s; use method='baseline' for TDOA-M only")
            jj, ii = np.nonzero(np.isfinite(problem.tdoa_events_s))
        else:
            jj = ii = np.zeros(0, dtype=np.intp)
        self.s_mic, self.s_ev = ii, jj
        self.s_dt = problem.interval_s[jj]
        self.s_y = (problem.tdoa_events_s[jj, ii] - self.s_dt) if len(jj) else np.zeros(0)
        self.s_w = 1.0 / problem.sigma_events_s
        # TDOA-M rows (eq. 6)
        tm = problem.tdoa_mics_s.copy()
        tm[:, 0] = np.nan
        jm, im = np.nonzero(np.isfinite(tm))
        self.m_mic, self.m_ev = im, jm
        self.m_t = t[jm]
        self.m_y = tm[jm, im]
        self.m_w = 1.0 / problem.sigma_mics_s
        # odometry rows (eq. 9)
        odo = problem.odometry_m if odometry_gauge_m is None else odometry_gauge_m
        steps = np.nonzero(np.all(np.isfinite(odo), axis=1))[0]
        self.o_step, self.o_y = steps, odo[steps]
        self.o_w = 1.0 / problem.sigma_odo_m
        ns, nm, no = len(ii), len(im), 3 * len(steps)
        self.n_s, self.n_m, self.n_o = ns, nm, no
        self.n_res = nr = ns + nm + no
        rs, rm, ro = np.arange(ns), ns + np.arange(nm), ns + nm + np.arange(no)
        self.w = np.concatenate([np.full(ns, self.s_w), np.full(nm, self.m_w), np.full(no, self.o_w)])
        self.y = np.concatenate([self.s_y, self.m_y, self.o_y.ravel()])
        # geometric terms: (row, mic, event, coef)
        g_row = np.concatenate([rs, rs, rm, rm])
        g_mic = np.concatenate([ii, ii, im, np.zeros(nm, dtype=np.intp)])
        g_ev = np.concatenate([jj + 1, jj, jm, jm])
        g_coef = np.concatenate([np.full(ns, 1 / c), np.full(ns, -1 / c), np.full(nm, 1 / c), np.full(nm, -1 / c)])
        # residual: the first two geometric slots of each row
        self.ga = np.zeros(nr, dtype=np.intp)
        self.gb = np.zeros(nr, dtype=np.intp)
        self.ca = np.zeros(nr)
        self.cb = np.zeros(nr)
        first = np.concatenate([np.arange(ns), 2 * ns + np.arange(nm)])
        second = np.concatenate([ns + np.arange(ns), 2 * ns + nm + np.arange(nm)])
        self.ga[g_row[first]] = g_mic[first] * k + g_ev[first]
        self.ca[g_row[first]] = g_coef[first]
        self.gb[g_row[second]] = g_mic[second] * k + g_ev[second]
        self.cb[g_row[second]] = g_coef[second]
        # linear part L (n_res, n_full)
        st = np.repeat(steps, 3)
        comp = np.tile(np.arange(3), len(steps))
        e_of = np.full(k - 1, -1, dtype=np.intp)
        e_of[fi] = np.arange(n_e)
        rs_e = rs[e_of[jj] >= 0]  # TDOA-S rows of a free interval: + e_j
        l_row = np.concatenate([rs, rm, rm, rm, rm, ro, ro, rs_e])
        l_col = np.concatenate([o_del + ii, o_tau + im, np.full(nm, o_tau), o_del + im, np.full(nm, o_del),
                                o_s + 3 * (st + 1) + comp, o_s + 3 * st + comp, o_e + e_of[jj[rs_e]]])
        l_val = np.concatenate([self.s_dt, np.ones(nm), -np.ones(nm), self.m_t, -self.m_t, np.ones(no),
                                -np.ones(no), np.ones(len(rs_e))])
        order = np.lexsort((l_col, l_row))  # CSR of L: rows in order, columns sorted (no duplicates)
        self.lin_indptr = np.concatenate([[0], np.cumsum(np.bincount(l_row, minlength=nr))])
        self.lin_indices, self.lin_data = l_col[order], l_val[order]
        # Jacobian entries: 6 per geometric term (x_m: +coef*u, s_e: -coef*u) + the linear ones
        kk = np.arange(3)
        e_row = np.concatenate([np.repeat(g_row, 3), np.repeat(g_row, 3), l_row])
        e_col = np.concatenate([(3 * g_mic[:, None] + kk).ravel(), (o_s + 3 * g_ev[:, None] + kk).ravel(), l_col])
        e_uidx = np.concatenate([((g_mic * k + g_ev)[:, None] * 3 + kk).ravel()] * 2 + [np.zeros(len(l_row), int)])
        e_coef = np.concatenate([np.repeat(g_coef, 3), -np.repeat(g_coef, 3), np.zeros(len(l_row))])
        e_const = np.concatenate([np.zeros(6 * len(g_row)), l_val])
        wr = self.w[e_row]
        cfree = self.col_of[e_col]
        keep = cfree >= 0
        self.e_uidx = e_uidx[keep]
        self.e_coef = (e_coef * wr)[keep]
        self.e_const = (e_const * wr)[keep]
        rows, cols = e_row[keep], cfree[keep]
        flat = rows * self.n_free + cols
        uniq, inv = np.unique(flat, return_inverse=True)  # sorted = CSR order; duplicates summed
        self.e_inv, self.n_uniq = inv, len(uniq)
        self.dense = nr * self.n_free <= _DENSE_LIMIT
        self.u_flat = uniq
        u_rows = uniq // self.n_free
        self.indices = (uniq % self.n_free).astype(np.intp)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(u_rows, minlength=nr))])
        # which residuals belong to which mic (per-mic diagnostics)
        self.res_mic = np.concatenate([self.s_mic, self.m_mic, np.full(no, -1)])

    # -- parameter helpers ---------------------------------------------------------------------------------------
    def pack(self, x, tau, delta, s, e=None) -> np.ndarray:
        e = np.zeros(self.n_e) if e is None else e
        return np.concatenate([np.ravel(x), tau, delta, np.ravel(s), e]).astype(np.float64)

    def unpack(self, p):
        n, k = self.n, self.k
        return (p[:3 * n].reshape(n, 3), p[self.o_tau:self.o_del], p[self.o_del:self.o_s],
                p[self.o_s:self.o_e].reshape(k, 3))

    def with_free_interval(self, j: int) -> "_Layout":
        """The same problem with the error of interval ``j`` estimated too (its parameter appended last)."""
        return _Layout(self.problem, self.method, self.gauge, self.odometry_gauge_m,
                       np.concatenate([self.free_intervals, [j]]))

    def interval_corrections(self, p: np.ndarray) -> np.ndarray:
        """ndarray, shape (K-1,): estimated interval errors ``e_j``, seconds (0 where the interval is given)."""
        out = np.zeros(self.k - 1)
        out[self.free_intervals] = p[self.o_e:]
        return out

    def s_target(self, p: np.ndarray) -> np.ndarray:
        """TDOA-S targets ``y - dt - e_j`` (eq. 5 without its geometric and drift terms), seconds."""
        return self.s_y - self.interval_corrections(p)[self.s_ev] if self.n_e else self.s_y

    def _geometry(self, p: np.ndarray):
        x = p[:3 * self.n].reshape(self.n, 3)
        s = p[self.o_s:self.o_e].reshape(self.k, 3)
        diff = x[:, None, :] - s[None, :, :]
        d = np.sqrt(np.einsum("nki,nki->nk", diff, diff))
        return d.ravel(), diff, d

    # -- residuals and Jacobian ------------------------------------------------------------------------------------
    def residuals(self, p: np.ndarray) -> np.ndarray:
        out = np.empty(self.n_res)
        _residuals_kernel(p, self.n, self.o_s, self.k, self.w, self.ca, self.ga, self.cb, self.gb,
                          self.lin_indptr, self.lin_indices, self.lin_data, self.y, out)
        return out

    def jacobian(self, p: np.ndarray):
        _, diff, d = self._geometry(p)
        u = (diff / np.maximum(d, 1e-12)[..., None]).ravel()
        vals = np.bincount(self.e_inv, weights=self.e_const + self.e_coef * u[self.e_uidx], minlength=self.n_uniq)
        if self.dense:
            j = np.zeros(self.n_res * self.n_free)
            j[self.u_flat] = vals
            return j.reshape(self.n_res, self.n_free)
        return scipy.sparse.csr_matrix((vals, self.indices, self.indptr), shape=(self.n_res, self.n_free))

    def normal_equations(self, p: np.ndarray, w: np.ndarray | None = None, r: np.ndarray | None = None):
        """``A = J^T diag(w) J`` (dense, n_free x n_free) and ``g = J^T diag(w) r`` (None without ``r``).

        Summed row by row over the stored entries of ``J`` (a TDOA row has about a dozen): the cost grows with
        the entries, not with ``n_residuals * n_params``."""
        a = np.empty((self.n_free, self.n_free))
        g = np.empty(self.n_free)
        sw = np.ones(self.n_res) if w is None else np.sqrt(w)
        _normal_equations_kernel(p, self.n, self.o_s, self.k, self.e_uidx, self.e_coef, self.e_const, self.e_inv,
                                 self.n_uniq, self.indptr, self.indices, sw,
                                 np.zeros(0) if r is None else r, a, g)
        return a, (None if r is None else g)


@_jit
def _residuals_kernel(p, n, o_s, k, w, ca, ga, cb, gb, lin_indptr, lin_indices, lin_data, y, out):
    """``out = w * (ca * d[ga] + cb * d[gb] + L @ p - y)`` (see :class:`_Layout`), ``d`` the mic-event
    distances (N * K, flat)."""
    d = np.empty(n * k)
    for m in range(n):
        for e in range(k):
            dx = p[3 * m] - p[o_s + 3 * e]
            dy = p[3 * m + 1] - p[o_s + 3 * e + 1]
            dz = p[3 * m + 2] - p[o_s + 3 * e + 2]
            d[m * k + e] = np.sqrt(dx * dx + dy * dy + dz * dz)
    for row in range(out.shape[0]):
        lin = 0.0
        for t in range(lin_indptr[row], lin_indptr[row + 1]):
            lin += lin_data[t] * p[lin_indices[t]]
        out[row] = w[row] * (ca[row] * d[ga[row]] + cb[row] * d[gb[row]] + lin - y[row])


@_jit
def _normal_equations_kernel(p, n, o_s, k, e_uidx, e_coef, e_const, e_inv, n_uniq, indptr, indices, sw, r, a, g):
    """``a = J^T diag(sw^2) J`` and, if ``r`` is not empty, ``g = J^T diag(sw^2) r``, from the stored entries of
    ``J`` (CSR: ``indptr``, column ``indices``; entry values as in :meth:`_Layout.jacobian`)."""
    u = np.empty(n * k * 3)
    for m in range(n):
        for e in range(k):
            dx = p[3 * m] - p[o_s + 3 * e]
            dy = p[3 * m + 1] - p[o_s + 3 * e + 1]
            dz = p[3 * m + 2] - p[o_s + 3 * e + 2]
            q = max(np.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
            u[3 * (m * k + e)] = dx / q
            u[3 * (m * k + e) + 1] = dy / q
            u[3 * (m * k + e) + 2] = dz / q
    vals = np.zeros(n_uniq)
    for t in range(e_inv.shape[0]):
        vals[e_inv[t]] += e_const[t] + e_coef[t] * u[e_uidx[t]]
    a[:] = 0.0
    g[:] = 0.0
    with_g = r.shape[0] > 0
    for row in range(indptr.shape[0] - 1):
        lo, hi = indptr[row], indptr[row + 1]
        for t in range(lo, hi):
            vt = vals[t] * sw[row]
            ct = indices[t]
            if with_g:
                g[ct] += vt * (r[row] * sw[row])
            for q in range(t, hi):
                a[ct, indices[q]] += vt * (vals[q] * sw[row])
    for c in range(a.shape[0]):  # columns are sorted within a row: the upper triangle holds the sums
        for q in range(c):
            a[c, q] = a[q, c]


# --------------------------------------------------------------------------------------------------------------
# Robust losses (scipy.optimize.least_squares conventions, in whitened units)
# --------------------------------------------------------------------------------------------------------------
def _rho(r: np.ndarray, loss: str, f: float):
    """Per-residual ``rho(r)`` and IRLS weights ``rho'(r)/r``."""
    if loss == "linear":
        return 0.5 * r * r, np.ones_like(r)
    if loss == "soft_l1":
        q = np.sqrt(1.0 + (r / f) ** 2)
        return f * f * (q - 1.0), 1.0 / q
    if loss == "huber":
        a = np.abs(r)
        big = a > f
        return (np.where(big, f * a - 0.5 * f * f, 0.5 * r * r),
                np.where(big, f / np.maximum(a, 1e-300), 1.0))
    raise ValueError(f"{loss=} must be 'linear', 'soft_l1' or 'huber'")


def _loss(r: np.ndarray, loss: str, f: float):
    """Return ``(cost, weights)``: ``cost = sum rho(r)``, IRLS weights ``rho'(r)/r``."""
    rho, w = _rho(r, loss, f)
    return float(rho.sum()), w


def _trimmed_cost(r: np.ndarray, loss: str, f: float, n_trim: int) -> float:
    """``sum rho(r)`` without the ``n_trim`` largest terms: a few gross mis-detections, whose pull is constant
    under a robust loss, must not make a run look stalled at an implausible cost."""
    return float(_sum_without_largest(_rho(r, loss, f)[0], n_trim))


@_jit
def _sum_without_largest(v, n_drop):
    """Sum of ``v`` without its ``n_drop`` largest entries (all of it unless ``0 < n_drop < len(v)``)."""
    n = v.shape[0]
    if n_drop <= 0 or n_drop >= n:
        return v.sum()
    part = np.partition(v, n - n_drop)
    total = 0.0
    for i in range(n - n_drop):
        total += part[i]
    return total


@_jit
def _median_abs(r, mask):
    """``median |r|`` over the entries with ``mask > 0`` (all of them if ``mask`` is empty); NaN if one is NaN
    (as ``np.median``)."""
    buf = np.empty(r.shape[0])
    n = 0
    for i in range(r.shape[0]):
        if mask.shape[0] == 0 or mask[i] > 0:
            v = abs(r[i])
            if np.isnan(v):
                return np.nan
            buf[n] = v
            n += 1
    return np.median(buf[:n])


# --------------------------------------------------------------------------------------------------------------
# Levenberg-Marquardt
# --------------------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class _Run:
    p: np.ndarray
    status: str  # "converged" | "diverged" | "max_iterations"
    cost: float
    n_iterations: int


def _adaptive_scale(r: np.ndarray, f_scale: float, loss: str, mask: np.ndarray | None = None) -> float:
    """Robust-loss scale ``f_scale * max(1, 1.4826 median|r|)`` (over ``mask > 0``): huge far from the solution
    (plain least squares, wide basin), ``f_scale`` sigmas near it (gross mis-detections down-weighted)."""
    if loss == "linear":
        return f_scale
    return f_scale * max(1.0, 1.4826 * float(_median_abs(r, _NO_MASK if mask is None else mask)))


def _levenberg_marquardt(lay: _Layout, p0: np.ndarray, *, loss: str, f_scale: float, max_iterations: int,
                         ftol: float = 1e-8, xtol: float = 1e-5, limit_m: float = 1e3,
                         max_step_m: float = np.inf, mask: np.ndarray | None = None,
                         stall_cost: float = np.inf) -> _Run:
    """Levenberg-Marquardt with More's scaling (running max of ``diag(A)``), Nielsen's damping update, a
    position trust region and IRLS for the robust loss; the loss scale adapts to the robust residual scale at
    every accepted step. ``mask`` (0/1 per residual) drops rejected measurements. A run whose cost (without
    its 5 % largest TDOA terms, which may be gross mis-detections) is still above ``stall_cost`` and fell by
    less than 5 % over the last 10 iterations stops as ``max_iterations`` (stalled in a wrong region: a
    restart is cheaper)."""
    p = p0.copy()
    free = lay.free

    def resid(q):
        return lay.residuals(q) if mask is None else lay.residuals(q) * mask

    def weights(w):
        return w if mask is None else w * mask

    r = resid(p)
    f = _adaptive_scale(r, f_scale, loss, mask)
    cost, w = _loss(r, loss, f)
    if not np.isfinite(cost):
        return _Run(p, "diverged", cost, 0)
    lam, nu = 1e-3, 2.0
    a, g = lay.normal_equations(p, weights(w), r)
    d = np.zeros(lay.n_free)
    pos_cols = np.concatenate([lay.col_of[:3 * lay.n], lay.col_of[lay.o_s:lay.o_e]])
    pos_cols = pos_cols[pos_cols >= 0]
    free_idx = np.nonzero(free)[0]
    it = 0
    n_trim = (lay.n_s + lay.n_m) // 20
    history = []
    while it < max_iterations:
        it += 1
        if np.isfinite(stall_cost) and it > 10:  # from iteration 21 on, compared with 10 iterations back
            history.append(_trimmed_cost(r, loss, f, n_trim))
            if len(history) > 10 and history[-1] > stall_cost and history[-11] - history[-1] < 0.05 * history[-1]:
                return _Run(p, "max_iterations", cost, it)
        m, scaled_gradient = _more_damping(a, g, d, lam)
        if scaled_gradient <= 1e-10 * (1.0 + np.sqrt(2.0 * cost)):
            return _Run(p, "converged", cost, it)
        _, h, info = scipy.linalg.lapack.dposv(m, g)  # Cholesky solve of the damped normal equations
        if info != 0:
            lam *= nu
            nu *= 2.0
            continue
        p_new, step_scaled, pred, far_m = _trial_step(h, a, g, d, p, free_idx, pos_cols, max_step_m, 3 * lay.n,
                                                      lay.o_s, lay.o_e)
        r_new = resid(p_new)
        cost_new, w_new = _loss(r_new, loss, f)
        rho = (cost - cost_new) / pred if pred > 0 else -1.0
        if np.isfinite(cost_new) and rho > 0:
            decrease = cost - cost_new
            p, r, cost, w = p_new, r_new, cost_new, w_new
            if far_m > limit_m:
                return _Run(p, "diverged", cost, it)
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            f_new = _adaptive_scale(r, f_scale, loss, mask)
            if f_new != f:
                f = f_new
                cost, w = _loss(r, loss, f)
            elif decrease <= ftol * cost or step_scaled <= xtol:
                return _Run(p, "converged", cost, it)
            a, g = lay.normal_equations(p, weights(w), r)
        else:
            if step_scaled <= xtol:
                return _Run(p, "converged", cost, it)
            lam *= nu
            nu *= 2.0
            if lam > 1e16:
                return _Run(p, "converged", cost, it)  # no descent direction left: at a minimum
    return _Run(p, "max_iterations", cost, it)


@_jit
def _more_damping(a, g, d, lam):
    """More's scaling: ``d`` (updated in place) is the running maximum of ``diag(A)`` (floored at 1e-12 of its
    largest entry), which keeps down-weighted directions damped. Returns ``A + lam diag(d)`` and the scaled
    gradient ``max |g_i| / sqrt(d_i)``."""
    n = g.shape[0]
    top = 1e-300
    for i in range(n):
        top = max(top, a[i, i])
    floor = 1e-12 * top
    m = a.copy()
    scaled = 0.0
    for i in range(n):
        d[i] = max(d[i], max(a[i, i], floor))
        m[i, i] += lam * d[i]
        scaled = max(scaled, abs(g[i]) / np.sqrt(d[i]))
    return m, scaled


@_jit
def _trial_step(h, a, g, d, p, free_idx, pos_cols, max_step_m, n_mic_coords, o_s, o_e):
    """The LM step ``-h`` (``h`` solves the damped normal equations), scaled down so that no position moves
    more than ``max_step_m`` (trust region: no jump beyond the scene size in one step). Returns the new full
    parameter vector, ``max |step_i| sqrt(d_i)``, the predicted decrease ``-(g.step + step.A step / 2)`` and the
    largest position coordinate of the new vector (``p[:n_mic_coords]`` and ``p[o_s:o_e]``), metres."""
    n = h.shape[0]
    step = np.empty(n)
    for i in range(n):
        step[i] = -h[i]
    big = 0.0
    for c in pos_cols:
        big = max(big, abs(step[c]))
    if big > max_step_m:
        shrink = max_step_m / big
        for i in range(n):
            step[i] *= shrink
    scaled = 0.0
    for i in range(n):
        scaled = max(scaled, abs(step[i]) * np.sqrt(d[i]))
    p_new = p.copy()
    for i in range(n):
        p_new[free_idx[i]] += step[i]
    ah = np.zeros(n)
    for k in range(n):  # A step, row by row of the symmetric A (contiguous)
        for i in range(n):
            ah[i] += a[k, i] * step[k]
    gh = 0.0
    hah = 0.0
    for i in range(n):
        gh += g[i] * step[i]
        hah += step[i] * ah[i]
    far = 0.0
    for i in range(n_mic_coords):
        far = max(far, abs(p_new[i]))
    for i in range(o_s, o_e):
        far = max(far, abs(p_new[i]))
    return p_new, scaled, -(gh + 0.5 * hah), far


# --------------------------------------------------------------------------------------------------------------
# Initialisation
# --------------------------------------------------------------------------------------------------------------
def _integrated_odometry(odometry_m: np.ndarray) -> np.ndarray:
    steps = np.where(np.all(np.isfinite(odometry_m), axis=1)[:, None], odometry_m, 0.0)
    return np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])


def random_initial_scene(n_mics: int, n_events: int, *, rng: np.random.Generator,
                         low_m=(-0.8, 0.0, -1.0), high_m=(0.8, 2.0, 0.0)) -> Scene:
    """The paper's random initial value (``init_generation1``): every mic and event position uniform in a box,
    offsets and drifts 0. The default box is the real-data one (x in [-0.8, 0.8], y in [0, 2], z in [-1, 0])."""
    lo, hi = np.asarray(low_m, float), np.asarray(high_m, float)
    pos = lo + (hi - lo) * rng.random((n_mics + n_events, 3))
    return Scene(pos[:n_mics], pos[n_mics:])


def _grid(events: np.ndarray, n_grid: int) -> np.ndarray:
    """Search grid: bounding box of the events grown by ``max(1 m, half its largest side)``."""
    lo, hi = events.min(0), events.max(0)
    margin = max(1.0, 0.5 * float(np.max(hi - lo)))
    lo, hi = lo - margin, hi + margin
    h = (np.prod(hi - lo) / n_grid) ** (1 / 3)
    ax, ay, az = (np.arange(lo[d] + h / 2, hi[d], h) for d in range(3))
    out = np.empty((len(ax), len(ay), len(az), 3))  # x slowest, z fastest
    out[..., 0] = ax[:, None, None]
    out[..., 1] = ay[:, None]
    out[..., 2] = az
    return out.reshape(-1, 3)


class _MicBatch:
    """Each mic's own subproblem with the events (and mic 0) fixed, for a batch of mics, rows padded.

    Whitened residual of row ``r`` of mic ``b``: ``w * (geom(x) + known) + A @ theta`` with ``geom`` from TDOA-S
    (eq. 5, ``|x - s_{j+1}| - |x - s_j|``) and, if used, TDOA-M (eq. 6, ``|x - s_j|``) over ``c``, and linear
    parameters ``theta = [delta_i, tau_i]`` (``tau_i`` pinned by a ridge when the mic has no TDOA-M row).
    """

    def __init__(self, lay: _Layout, p: np.ndarray, mics, *, use_m: bool, max_rows: int = 64,
                 s_rows: np.ndarray | None = None):
        x, tau, delta, s = lay.unpack(p)
        self.mics = np.asarray(list(mics), dtype=np.intp)
        c = lay.c
        per = []
        s_ok = np.ones(lay.n_s, dtype=bool) if s_rows is None else s_rows
        s_y = lay.s_target(p)
        for i in self.mics:
            ss = np.nonzero((lay.s_mic == i) & s_ok)[0]
            mm = np.nonzero(lay.m_mic == i)[0] if (use_m and i > 0) else np.zeros(0, dtype=np.intp)
            if len(ss) > max_rows:
                ss = ss[np.linspace(0, len(ss) - 1, max_rows).astype(int)]
            if len(mm) > max_rows:
                mm = mm[np.linspace(0, len(mm) - 1, max_rows).astype(int)]
            per.append((ss, mm))
        b = len(self.mics)
        r_max = max([len(a) + len(m) for a, m in per] + [1])
        self.ev_a = np.zeros((b, r_max), dtype=np.intp)
        self.ev_b = np.zeros((b, r_max), dtype=np.intp)
        self.has_b = np.zeros((b, r_max))
        self.w = np.zeros((b, r_max))
        self.b0 = np.zeros((b, r_max))
        self.a = np.zeros((b, r_max, 2))
        self.n_rows = np.zeros(b, dtype=np.intp)
        self.has_m = np.zeros(b, dtype=bool)
        # eq. (6) terms of mic 0, known with the events: -|x_0 - s_j| / c - delta_0 t_j
        known_m = -np.sqrt(np.sum((x[0] - s[lay.m_ev]) ** 2, 1)) / c - delta[0] * lay.m_t
        for q, (ss, mm) in enumerate(per):
            na, nb = len(ss), len(mm)
            self.ev_a[q, :na], self.ev_a[q, na:na + nb] = lay.s_ev[ss] + 1, lay.m_ev[mm]
            self.ev_b[q, :na], self.ev_b[q, na:na + nb] = lay.s_ev[ss], lay.m_ev[mm]
            self.has_b[q, :na] = 1.0
            self.w[q, :na], self.w[q, na:na + nb] = lay.s_w, lay.m_w
            self.b0[q, :na] = lay.s_w * (0.0 - s_y[ss])
            self.b0[q, na:na + nb] = lay.m_w * (known_m[mm] - lay.m_y[mm])
            self.a[q, :na, 0] = lay.s_w * lay.s_dt[ss]
            self.a[q, na:na + nb, 0] = lay.m_w * lay.m_t[mm]
            self.a[q, na:na + nb, 1] = lay.m_w
            self.n_rows[q] = na + nb
            self.has_m[q] = nb > 0
        self.s, self.c = s, c
        ata = np.einsum("bri,brj->bij", self.a, self.a)
        dg = np.einsum("bii->bi", ata)
        self.ridge = np.where(dg > 0, 1e-8 * dg, 1.0)  # (b, 2)
        self.theta_now = np.stack([delta[self.mics], tau[self.mics]], 1)
        self.x_now = x[self.mics]

    def grid_search(self, dist_t: np.ndarray, cap: float, n_best: int, which: np.ndarray | None = None):
        """The ``n_best`` grid points per mic with the lowest truncated score ``sum min(r^2, cap^2)``, ``theta``
        eliminated by least squares (residual projected out of ``A``'s range). ``dist_t``: (K, G).
        Returns grid indices (b, n_best) and theta (b, n_best, 2) (rows outside ``which`` are 0). One compiled
        call per mic (:func:`_grid_scores`)."""
        b = len(self.mics)
        n_best = min(n_best, dist_t.shape[1])
        top = np.zeros((b, n_best), dtype=np.intp)
        th = np.zeros((b, n_best, 2))
        for q in (range(b) if which is None else which):
            nr = self.n_rows[q]
            a = self.a[q, :nr]
            proj = np.linalg.inv(a.T @ a + np.diag(self.ridge[q])) @ a.T  # (2, R): theta by least squares
            score, thq = _grid_scores(dist_t, self.ev_a[q, :nr], self.ev_b[q, :nr], self.has_b[q, :nr],
                                      self.w[q, :nr] / self.c, self.b0[q, :nr], a, proj, self.ridge[q], cap)
            t = np.argpartition(score, n_best - 1)[:n_best]
            top[q] = t
            th[q] = thq[:, t].T
        return top, th

    def residuals(self, xs: np.ndarray, th: np.ndarray, rep: np.ndarray | None = None) -> np.ndarray:
        q = np.arange(len(self.mics)) if rep is None else rep
        da = np.sqrt(np.sum((xs[:, None, :] - self.s[self.ev_a[q]]) ** 2, -1))
        db = np.sqrt(np.sum((xs[:, None, :] - self.s[self.ev_b[q]]) ** 2, -1))
        return (self.w[q] * (da - self.has_b[q] * db) / self.c + self.b0[q]
                + np.einsum("bri,bi->br", self.a[q], th))

    def costs(self, xs: np.ndarray, th: np.ndarray, f: float, rep: np.ndarray | None = None) -> np.ndarray:
        """Cauchy cost ``sum f^2/2 log(1 + (r/f)^2)`` (padded rows are 0): with a mic's few own rows, one
        gross outlier under a non-redescending loss can pull the mic to the far field."""
        z = (self.residuals(xs, th, rep) / f) ** 2
        return np.sum(0.5 * f * f * np.log1p(z), axis=1)

    def refine(self, xs: np.ndarray, th: np.ndarray, f: float, rep: np.ndarray, box: tuple, max_step_m: float,
               n_iter: int = 10):
        """Batched damped Gauss-Newton with Cauchy IRLS on ``(x, theta)`` for candidates of mics ``rep``;
        position steps are capped at ``max_step_m`` and candidates leaving ``box`` (lo, hi) get cost inf
        (with few rows the far field can fit as well as the truth)."""
        xs, th = np.array(xs, dtype=np.float64), np.array(th, dtype=np.float64)
        cost = _refine_kernel(xs, th, float(f), self.s, self.ev_a, self.ev_b, self.has_b, self.w, self.b0, self.a,
                              self.ridge, np.ascontiguousarray(rep, dtype=np.intp), self.n_rows, float(self.c),
                              np.asarray(box[0], dtype=np.float64), np.asarray(box[1], dtype=np.float64),
                              float(max_step_m), int(n_iter))
        return xs, th, cost


@_jit
def _mic_residuals(x, th, s, ev_a, ev_b, has_b, w, b0, a, n_rows, c, r):
    """Rows ``0..n_rows-1`` of one mic's subproblem into ``r`` (see :meth:`_MicBatch.residuals`)."""
    for t in range(n_rows):
        sa, sb = s[ev_a[t]], s[ev_b[t]]
        da = np.sqrt((x[0] - sa[0]) ** 2 + (x[1] - sa[1]) ** 2 + (x[2] - sa[2]) ** 2)
        db = np.sqrt((x[0] - sb[0]) ** 2 + (x[1] - sb[1]) ** 2 + (x[2] - sb[2]) ** 2)
        r[t] = w[t] * (da - has_b[t] * db) / c + b0[t] + (a[t, 0] * th[0] + a[t, 1] * th[1])


@_jit
def _cauchy_cost(r, n_rows, f):
    """``sum f^2/2 log(1 + (r/f)^2)`` over the first ``n_rows`` entries of ``r``."""
    total = 0.0
    for t in range(n_rows):
        z = r[t] / f
        total += 0.5 * f * f * np.log1p(z * z)
    return total


@_jit
def _solve_pivoted(m, g, h):
    """``h = m^-1 g`` by Gaussian elimination with partial pivoting (``m``, ``g`` overwritten); False if
    ``m`` is singular."""
    n = g.shape[0]
    for col in range(n):
        piv = col
        for i in range(col + 1, n):
            if abs(m[i, col]) > abs(m[piv, col]):
                piv = i
        if m[piv, col] == 0.0:
            return False
        if piv != col:
            for k in range(n):
                m[col, k], m[piv, k] = m[piv, k], m[col, k]
            g[col], g[piv] = g[piv], g[col]
        for i in range(col + 1, n):
            fac = m[i, col] / m[col, col]
            for k in range(col, n):
                m[i, k] -= fac * m[col, k]
            g[i] -= fac * g[col]
    for i in range(n - 1, -1, -1):
        acc = g[i]
        for k in range(i + 1, n):
            acc -= m[i, k] * h[k]
        h[i] = acc / m[i, i]
    return True


@_jit
def _refine_kernel(xs, th, f, s, ev_a, ev_b, has_b, w, b0, a, ridge, rep, n_rows, c, lo, hi, max_step_m, n_iter):
    """:meth:`_MicBatch.refine` for candidates ``(xs[q], th[q])`` of batch mics ``rep[q]`` (updated in place);
    returns their costs. All candidates step together: a singular system stops every one of them."""
    n_cand, r_max = xs.shape[0], w.shape[1]
    r = np.empty(r_max)
    cost = np.empty(n_cand)
    for q in range(n_cand):
        b = rep[q]
        _mic_residuals(xs[q], th[q], s, ev_a[b], ev_b[b], has_b[b], w[b], b0[b], a[b], n_rows[b], c, r)
        cost[q] = _cauchy_cost(r, n_rows[b], f)
    lam = np.full(n_cand, 1e-3)
    steps = np.empty((n_cand, 5))
    jt = np.empty(5)
    m = np.empty((5, 5))
    g = np.empty(5)
    xn = np.empty(3)
    tn = np.empty(2)
    for _ in range(n_iter):
        for q in range(n_cand):  # the damped, Cauchy-weighted normal equations of every candidate
            b = rep[q]
            nr = n_rows[b]
            x = xs[q]
            _mic_residuals(x, th[q], s, ev_a[b], ev_b[b], has_b[b], w[b], b0[b], a[b], nr, c, r)
            m[:] = 0.0
            g[:] = 0.0
            for t in range(nr):
                sa, sb = s[ev_a[b, t]], s[ev_b[b, t]]
                na = max(np.sqrt((x[0] - sa[0]) ** 2 + (x[1] - sa[1]) ** 2 + (x[2] - sa[2]) ** 2), 1e-12)
                nb = max(np.sqrt((x[0] - sb[0]) ** 2 + (x[1] - sb[1]) ** 2 + (x[2] - sb[2]) ** 2), 1e-12)
                for k in range(3):
                    jt[k] = w[b, t] * ((x[k] - sa[k]) / na - has_b[b, t] * ((x[k] - sb[k]) / nb)) / c
                jt[3], jt[4] = a[b, t, 0], a[b, t, 1]
                wt = 1.0 / (1.0 + (r[t] / f) ** 2)  # Cauchy IRLS weight
                for i in range(5):
                    g[i] += jt[i] * wt * r[t]
                    for k in range(5):
                        m[i, k] += jt[i] * wt * jt[k]
            for i in range(5):
                m[i, i] += lam[q] * m[i, i] + (ridge[b, i - 3] if i >= 3 else 0.0)
            if not _solve_pivoted(m, g, steps[q]):
                return _outside_inf(xs, cost, lo, hi)
        for q in range(n_cand):
            b = rep[q]
            big = max(abs(steps[q, 0]), abs(steps[q, 1]), abs(steps[q, 2]))
            shrink = min(1.0, max_step_m / max(big, 1e-300))
            for k in range(3):
                xn[k] = xs[q, k] - steps[q, k] * shrink
            for k in range(2):
                tn[k] = th[q, k] - steps[q, 3 + k] * shrink
            _mic_residuals(xn, tn, s, ev_a[b], ev_b[b], has_b[b], w[b], b0[b], a[b], n_rows[b], c, r)
            cn = _cauchy_cost(r, n_rows[b], f)
            if cn < cost[q]:
                xs[q, :] = xn
                th[q, :] = tn
                cost[q] = cn
                lam[q] = max(lam[q] / 3, 1e-9)
            else:
                lam[q] *= 4
    return _outside_inf(xs, cost, lo, hi)


@_jit
def _outside_inf(xs, cost, lo, hi):
    """``cost`` with inf where a candidate left the box ``[lo, hi]``."""
    for q in range(xs.shape[0]):
        for k in range(3):
            if xs[q, k] < lo[k] or xs[q, k] > hi[k]:
                cost[q] = np.inf
    return cost


@_jit
def _grid_scores(dist_t, ev_a, ev_b, has_b, wc, b0, a, proj, ridge, cap):
    """:meth:`_MicBatch.grid_search` of one mic: at every grid point ``g`` (column of ``dist_t``, (K, G)) the
    whitened residuals ``e = wc (|g - s_a| - has_b |g - s_b|) + b0 + a theta`` (R rows), ``theta`` fitted by
    least squares (``theta = -proj e_0``), then refitted without the rows above ``max(cap, 3 mean |e|)`` (a
    grossly mis-detected chirp must not drag theta; a median would cost a partition per point). Returns the
    truncated score ``sum min(e^2, cap^2)`` (G,) and theta (2, G)."""
    n_rows, n_grid = ev_a.shape[0], dist_t.shape[1]
    et = np.empty((n_rows, n_grid))
    for r in range(n_rows):
        for g in range(n_grid):
            v = wc[r] * dist_t[ev_a[r], g]
            if has_b[r] > 0:
                v -= wc[r] * dist_t[ev_b[r], g]
            et[r, g] = v + b0[r]
    th0 = np.zeros(n_grid)
    th1 = np.zeros(n_grid)
    for r in range(n_rows):
        for g in range(n_grid):
            th0[g] -= proj[0, r] * et[r, g]
            th1[g] -= proj[1, r] * et[r, g]
    limit = np.zeros(n_grid)
    for r in range(n_rows):
        for g in range(n_grid):
            limit[g] += abs(et[r, g] + (a[r, 0] * th0[g] + a[r, 1] * th1[g]))
    for g in range(n_grid):
        limit[g] = max(cap, 3.0 * (limit[g] / n_rows))
    s00 = np.full(n_grid, ridge[0])
    s01 = np.zeros(n_grid)
    s11 = np.full(n_grid, ridge[1])
    r0 = np.zeros(n_grid)
    r1 = np.zeros(n_grid)
    for r in range(n_rows):
        for g in range(n_grid):
            e = et[r, g]
            if abs(e + (a[r, 0] * th0[g] + a[r, 1] * th1[g])) < limit[g]:
                s00[g] += a[r, 0] * a[r, 0]
                s01[g] += a[r, 0] * a[r, 1]
                s11[g] += a[r, 1] * a[r, 1]
                r0[g] -= a[r, 0] * e
                r1[g] -= a[r, 1] * e
    theta = np.empty((2, n_grid))
    for g in range(n_grid):
        det = s00[g] * s11[g] - s01[g] * s01[g]
        theta[0, g] = (s11[g] * r0[g] - s01[g] * r1[g]) / det
        theta[1, g] = (s00[g] * r1[g] - s01[g] * r0[g]) / det
    score = np.zeros(n_grid)
    cap2 = cap * cap
    for r in range(n_rows):
        for g in range(n_grid):
            e = et[r, g] + (a[r, 0] * theta[0, g] + a[r, 1] * theta[1, g])
            score[g] += min(e * e, cap2)
    return score, theta


def _best_mic_positions(lay: _Layout, p: np.ndarray, mics, *, use_m: bool, grid: np.ndarray, f: float = 3.0,
                        cap: float = 10.0, n_best: int = 4, skip_near_current_m: float | None = None,
                        s_rows: np.ndarray | None = None, min_current_cost: float | None = None):
    """Per-mic global search of each mic's own subproblem (events and mic 0 fixed): grid, then local
    refinement of the ``n_best`` best grid points (those closer than ``skip_near_current_m`` to the current
    estimate are skipped: the global solve already refined that basin). Only mics whose current cost exceeds
    ``min_current_cost`` are searched. Returns the batch, best positions (b, 3), theta (b, 2), best cost (b,;
    inf when nothing was refined) and the cost at the current estimate (b,)."""
    batch = _MicBatch(lay, p, mics, use_m=use_m, s_rows=s_rows)
    now = batch.costs(batch.x_now, batch.theta_now, f)
    b = len(batch.mics)
    which = np.arange(b) if min_current_cost is None else np.nonzero(now > min_current_cost)[0]
    xb, thb, cb = batch.x_now.copy(), batch.theta_now.copy(), np.full(b, np.inf)
    if len(which) == 0:
        return batch, xb, thb, cb, now
    s = lay.unpack(p)[3]
    dist_t = _distances(s, grid)  # (K, G), shared by all mics
    top, th = batch.grid_search(dist_t, cap, n_best, which)
    cand = grid[top]  # (b, nb, 3)
    use = np.zeros(top.shape, dtype=bool)
    use[which] = True
    if skip_near_current_m is not None:
        use &= np.linalg.norm(cand - batch.x_now[:, None, :], axis=2) > skip_near_current_m
    if skip_near_current_m is None:  # initialisation: fall back on a top grid point
        xb[which], thb[which] = cand[which, 0], th[which, 0]
    if np.any(use):
        rep = np.nonzero(use)[0]
        h = _grid_step_m(grid)
        box = (grid.min(0) - h, grid.max(0) + h)
        xr, thr, cr = batch.refine(cand[use], th[use], f, rep, box, h)
        for q in range(len(rep)):
            if cr[q] < cb[rep[q]]:
                xb[rep[q]], thb[rep[q]], cb[rep[q]] = xr[q], thr[q], cr[q]
    return batch, xb, thb, cb, now


def _grid_step_m(grid: np.ndarray) -> float:
    return float(np.min(np.diff(np.unique(grid[:, 0])))) if len(np.unique(grid[:, 0])) > 1 else 1.0


def _odometry_segments(odo: np.ndarray) -> np.ndarray:
    """Segment index per event: a missing odometry step starts a new rigid segment."""
    gap = ~np.all(np.isfinite(odo), axis=1)
    return np.concatenate([[0], np.cumsum(gap)])


def _place_segment(lay: _Layout, events: np.ndarray, seg: np.ndarray, g: int, placed: np.ndarray,
                   pos: np.ndarray, drift: np.ndarray, grid: np.ndarray, cap: float = 10.0) -> np.ndarray:
    """Translation of odometry segment ``g`` (events known up to a shift) by a grid search on the TDOA-S rows
    that touch it and an already placed segment or itself, mics and drifts fixed. Returns the new events."""
    in_g = seg == g
    a_ok = in_g[lay.s_ev + 1] | placed[lay.s_ev + 1]
    b_ok = in_g[lay.s_ev] | placed[lay.s_ev]
    rows = np.nonzero((in_g[lay.s_ev + 1] | in_g[lay.s_ev]) & a_ok & b_ok)[0]
    if len(rows) < 3:
        return events
    shifts = grid - events[in_g].mean(0)  # (G, 3) candidate translations
    xi = pos[lay.s_mic[rows]]

    def dist(ev_idx):
        base = events[ev_idx]  # (R, 3)
        moving = in_g[ev_idx]
        pts = base[None, :, :] + shifts[:, None, :] * moving[None, :, None]
        return np.sqrt(np.sum((xi[None] - pts) ** 2, -1))  # (G, R)

    geo = (dist(lay.s_ev[rows] + 1) - dist(lay.s_ev[rows])) / lay.c
    res = lay.s_w * (geo + drift[lay.s_mic[rows]] * lay.s_dt[rows] - lay.s_y[rows])
    best = int(np.argmin(np.sum(np.minimum(res * res, cap * cap), axis=1)))
    out = events.copy()
    out[in_g] += shifts[best]
    return out


@_jit
def _distances(a, b):
    """ndarray, shape (len(a), len(b)): ``|a_i - b_j|`` of two point sets, shapes (n, 3) and (m, 3)."""
    out = np.empty((a.shape[0], b.shape[0]))
    for i in range(a.shape[0]):
        for j in range(b.shape[0]):
            dx = a[i, 0] - b[j, 0]
            dy = a[i, 1] - b[j, 1]
            dz = a[i, 2] - b[j, 2]
            out[i, j] = np.sqrt(dx * dx + dy * dy + dz * dz)
    return out


@_jit
def _min_plus(cross, a):
    """``min_g cross[g, h] + a[g]`` for every ``h`` (float32 in and out, as ``np.min(cross + a[:, None], 0)``
    without the (G, H) temporary)."""
    best = cross[0] + a[0]
    for g in range(1, cross.shape[0]):
        ag = a[g]
        for h in range(cross.shape[1]):
            best[h] = min(best[h], cross[g, h] + ag)
    return best


def _reference_candidates(lay: _Layout, events: np.ndarray, grid: np.ndarray, ref_grid: np.ndarray, n_best: int,
                          cap: float = 100.0, min_separation_m: float = 0.0) -> np.ndarray:
    """Baseline: points of ``ref_grid`` for mic 0 ranked by how well every other mic's TDOA-M can then be
    fitted from a point of ``grid``, the events fixed. Returns ``ref_grid`` indices, best first, each at least
    ``min_separation_m`` from the better ones (distinct starts, not neighbours in one basin), and the score of
    every point.

    With mic 0 at ``h`` and mic ``i`` at ``g``, eq. (6) whitened and projected out of the offset + drift
    columns ``[1, t_j]`` (``P``) leaves ``|D_g - D_h - u_i|^2`` with ``D = P w |x - s_j| / c`` and
    ``u_i = P w y_i``. Expanded, the minimum over ``g`` for every ``h`` needs only the cross products
    ``D_g . D_h`` (shared by the mics with the same TDOA-M rows). Least squares, so a mic's score is capped at
    ``cap`` sigmas squared per row (a grossly mis-detected chirp spoils one mic, not the ranking).
    """
    scale = lay.m_w / lay.c
    dist_g = _distances(events, grid) * scale  # (K, G)
    dist_h = _distances(events, ref_grid) * scale  # (K, H)
    total = np.zeros(len(ref_grid))
    cache: dict[bytes, tuple] = {}
    for i in range(1, lay.n):
        sel = np.nonzero(lay.m_mic == i)[0]
        if len(sel) < 4:
            continue
        jm = lay.m_ev[sel]
        key = jm.tobytes()
        if key not in cache:
            q, _ = np.linalg.qr(np.stack([np.ones(len(sel)), lay.m_t[sel]], 1))
            dg = dist_g[jm] - q @ (q.T @ dist_g[jm])  # P D, (R, G)
            dh = dist_h[jm] - q @ (q.T @ dist_h[jm])
            # float32 for the (G, H) part: scores differ by >= 1 (sigma^2) where they matter, out of <~1e5
            cross = dg.T @ dh
            cross *= -2.0
            cache[key] = (q, dg, dh, cross.astype(np.float32), np.sum(dg * dg, 0), np.sum(dh * dh, 0))
        q, dg, dh, cross, ng, nh = cache[key]
        y = lay.m_w * lay.m_y[sel]
        u = y - q @ (q.T @ y)
        # S(g, h) = |D_g|^2 + |D_h|^2 + |u|^2 - 2 D_g.D_h - 2 D_g.u + 2 D_h.u, minimised over g
        a = (ng - 2.0 * (u @ dg)).astype(np.float32)
        best = _min_plus(cross, a) + nh + u @ u + 2.0 * (u @ dh)
        total += np.minimum(np.maximum(best, 0.0), cap * len(sel))
    order = np.argsort(total)
    if min_separation_m <= 0.0:
        return order[:n_best], total
    out: list[int] = []
    for h in order:
        if all(np.linalg.norm(ref_grid[h] - ref_grid[o]) >= min_separation_m for o in out):
            out.append(int(h))
            if len(out) == n_best:
                break
    return np.asarray(out, dtype=np.intp), total


def _baseline_start(lay: _Layout, events: np.ndarray, x0: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Baseline start with the events and mic 0 at ``x0`` given: every other mic by the global search of its
    own TDOA-M (position, offset and drift)."""
    pos = np.repeat(np.asarray(x0, float)[None, :], lay.n, axis=0)
    tau, delta = np.zeros(lay.n), np.zeros(lay.n)
    mics = [i for i in range(1, lay.n) if np.sum(lay.m_mic == i) >= 4]
    if mics:
        _, xb, thb, _, _ = _best_mic_positions(lay, lay.pack(pos, tau, delta, events), mics, use_m=True,
                                               grid=grid)
        pos[mics], delta[mics], tau[mics] = xb, thb[:, 0], thb[:, 1]
    return lay.pack(pos, tau, delta, events)


class _BaselineStarts:
    """Baseline initialisations, best first: events from the integrated odometry, mic 0 at the ``b``-th of
    :func:`_reference_candidates`, the other mics by :func:`_baseline_start`. The ranking is computed on first
    use, each start only when asked for."""

    def __init__(self, lay: _Layout, odo_gauge: np.ndarray, n_grid: int, n_best: int = 1):
        self.lay, self.n_grid, self.n_best = lay, n_grid, n_best
        self.events = _integrated_odometry(odo_gauge)
        self.ref = None

    def get(self, b: int) -> np.ndarray | None:
        """The ``b``-th start (None when there are fewer candidates)."""
        if b < 0:
            return None
        grid = _grid(self.events, self.n_grid)
        if self.ref is None:
            ref_grid = _grid(self.events, max(self.n_grid // 4, 8))
            self.ref = ref_grid[_reference_candidates(self.lay, self.events, grid, ref_grid, self.n_best,
                                                      min_separation_m=2.5 * _grid_step_m(ref_grid))[0]]
        return _baseline_start(self.lay, self.events, self.ref[b], grid) if 0 <= b < len(self.ref) else None


def _check_reference(lay: _Layout, p: np.ndarray, n_grid: int) -> np.ndarray | None:
    """Baseline: mic 0, which every TDOA-M involves, has no subproblem of its own to certify. Rank positions of
    mic 0 with :func:`_reference_candidates` at the estimated events; if the estimate is not among the best
    three, scores 20 % worse than the best and is more than half a grid step from it, return a start with mic 0
    at the best (else None). The score puts the other mics on grid points, hence the tolerances."""
    x, _, _, events = lay.unpack(p)
    grid = _grid(events, n_grid)
    ref_grid = _grid(events, max(n_grid // 4, 8))
    step = _grid_step_m(ref_grid)
    top, score = _reference_candidates(lay, events, grid, np.vstack([ref_grid, x[:1]]), 3)
    if (len(ref_grid) in top or score[-1] <= 1.2 * score[top[0]]
            or np.linalg.norm(ref_grid[top[0]] - x[0]) <= 0.5 * step):
        return None
    return _baseline_start(lay, events, ref_grid[top[0]], grid)


def _smart_init(lay: _Layout, odo_gauge: np.ndarray, method: str, rng: np.random.Generator,
                n_grid: int) -> np.ndarray:
    """Events from the integrated odometry; each mic by a global search on its own TDOA-S (position and
    drift); offsets from the TDOA-M median. Mics without TDOA-S (baseline) are drawn around the events.
    A missing odometry step splits the events into rigid segments: mics are found against the largest one,
    then every other segment is shifted into place by a grid search on its TDOA-S."""
    events = _integrated_odometry(odo_gauge)
    n = lay.n
    lo, hi = events.min(0) - 1.0, events.max(0) + 1.0
    pos = lo + (hi - lo) * rng.random((n, 3))
    drift = np.zeros(n)
    if method == "hybrid":
        seg = _odometry_segments(odo_gauge)
        ref = int(np.argmax(np.bincount(seg)))
        s_rows = (seg[lay.s_ev] == ref) & (seg[lay.s_ev + 1] == ref)
        counts = np.bincount(lay.s_mic[s_rows], minlength=n)
        mics = np.nonzero(counts >= 5)[0]
        if len(mics):
            p = lay.pack(pos, np.zeros(n), drift, events)
            grid = _grid(events[seg == ref], n_grid)
            _, xb, thb, _, _ = _best_mic_positions(lay, p, mics, use_m=False, grid=grid, s_rows=s_rows)
            pos[mics], drift[mics] = xb, thb[:, 0]
            placed = seg == ref
            for g in np.unique(seg):
                if g != ref:
                    events = _place_segment(lay, events, seg, int(g), placed, pos, drift,
                                            _grid(np.concatenate([events[placed], pos[mics]]), n_grid))
                    placed |= seg == g
            pos -= events[0]
            events = events - events[0]  # gauge: s_0 = 0
    tau = np.zeros(n)
    d = np.linalg.norm(pos[:, None, :] - events[None, :, :], axis=2)
    for i in range(1, n):
        sel = lay.m_mic == i
        if np.any(sel):
            jj = lay.m_ev[sel]
            pred = (d[i, jj] - d[0, jj]) / lay.c + (drift[i] - drift[0]) * lay.m_t[sel]
            tau[i] = float(np.median(lay.m_y[sel] - pred))
    return lay.pack(pos, tau, drift, events)


def _certify(lay: _Layout, p: np.ndarray, method: str, grid: np.ndarray, f: float) -> tuple[list, np.ndarray]:
    """Check that every mic sits at the global optimum of its own subproblem (events, mic 0 fixed; estimated
    interval errors applied). Every TDOA counts, rejected ones included (Cauchy-weighted): several rejected
    entries of one mic are as likely the mic in a wrong basin as mis-detected chirps.

    Returns the mics that have a clearly better position elsewhere and a parameter vector with those mics
    moved there (the restart point)."""
    counts = np.bincount(lay.s_mic, minlength=lay.n) + np.bincount(lay.m_mic, minlength=lay.n)
    mics = [i for i in range(lay.n) if counts[i] >= 6 and (method == "hybrid" or i > 0)]
    if not mics:
        return [], p
    # a move needs best < 0.8 * now - 4, impossible unless now > 5: mics that fit well are not searched
    batch, xb, thb, cb, cnow = _best_mic_positions(lay, p, mics, use_m=True, grid=grid, f=f,
                                                   skip_near_current_m=2.5 * _grid_step_m(grid),
                                                   min_current_cost=5.0)
    q = p.copy()
    moved = []
    for b, i in enumerate(batch.mics):
        if cb[b] < 0.8 * cnow[b] - 4.0:
            moved.append(int(i))
            q[3 * i:3 * i + 3] = xb[b]
            q[lay.o_del + i] = thb[b, 0]
            if batch.has_m[b]:
                q[lay.o_tau + i] = thb[b, 1]
    return moved, q


# --------------------------------------------------------------------------------------------------------------
# Solve
# --------------------------------------------------------------------------------------------------------------
def _odometry_gauge(problem: HybridTdoaProblem):
    """Rotation ``R`` taking the odometry frame into the gauge frame (first three integrated points)."""
    pts = _integrated_odometry(problem.odometry_m)
    return _frame_of(pts[0], pts[1], pts[2])


def _apply_gauge(lay: _Layout, p: np.ndarray) -> np.ndarray:
    p = p.copy()
    p[lay.o_tau] = 0.0
    fixed_s = ~lay.free[lay.o_s:lay.o_s + 9]
    p[lay.o_s:lay.o_s + 9][fixed_s] = 0.0
    if not lay.free[lay.o_del]:
        p[lay.o_del + 1:lay.o_s] -= p[lay.o_del]
        p[lay.o_del] = 0.0
    return p


# --------------------------------------------------------------------------------------------------------------
# Gross errors: detection, rejection, re-solve
# --------------------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class _GrossTests:
    """Outlier statistics at one estimate, in robustly scaled sigmas (see :func:`_gross_error_tests`)."""

    interval_z: np.ndarray  # (K-1,) NaN where not testable
    row_t: np.ndarray  # (n_s + n_m,) TDOA rows, NaN where rejected
    step_t: np.ndarray  # (len(o_step),) odometry steps, NaN where not testable


def _gross_error_tests(lay: _Layout, p: np.ndarray, mask: np.ndarray, loss: str,
                       f_scale: float) -> _GrossTests | None:
    """Outlier tests at a converged (robust) estimate, linearised, with the robust-loss IRLS weights ``W``.

    With ``J`` the whitened Jacobian, ``A = J^T W J`` and ``h_k = w_k J_k A^-1 J_k^T`` (leverage):

    - TDOA entry ``k``: studentised residual ``|r_k| / sqrt(1 - h_k)``;
    - odometry step (rows ``R``, steps 0 and 1 excluded: they fix the gauge): ``sqrt(r_R^T (I - H_RR)^-1 r_R)``;
    - emission interval ``j`` (hybrid): the score test of one more parameter ``e_j`` entering all TDOA-S of
      row ``j`` with whitened column ``a``: ``|a^T W r| / sqrt(a^T W a - (J^T W a)^T A^-1 (J^T W a))`` (the
      square root of the chi-square drop when ``e_j`` is freed). The IRLS weights bound what one mis-detected
      chirp adds to it (soft-L1: ``f_scale`` sigmas), so a single bad TDOA-S does not pass for a bad interval.

    TDOA statistics are divided by the robust TDOA scale ``max(1, 1.4826 median |r|)`` of the kept set, the
    odometry ones by that of the odometry. Large problems (sparse Jacobian) take ``h = 0``.
    """
    r = lay.residuals(p)
    kept = mask > 0
    n_t = lay.n_s + lay.n_m
    rt = r[:n_t][kept[:n_t]]
    if len(rt) == 0:
        return None
    scale = max(1.0, 1.4826 * float(_median_abs(rt, _NO_MASK)))
    ro = r[n_t:][kept[n_t:]]
    scale_o = max(1.0, 1.4826 * float(_median_abs(ro, _NO_MASK))) if len(ro) else 1.0
    f = _adaptive_scale(r, f_scale, loss, mask)
    w = _rho(r, loss, f)[1] * mask
    j = lay.jacobian(p)
    sw = np.sqrt(w)
    jw = j * sw[:, None] if lay.dense else scipy.sparse.diags(sw) @ j
    a = jw.T @ jw
    a = a if lay.dense else a.toarray()
    try:
        chol = scipy.linalg.cholesky(a + 1e-12 * np.diag(np.diag(a)), lower=True)
    except np.linalg.LinAlgError:
        return None
    v = scipy.linalg.solve_triangular(chol, jw.T, lower=True) if lay.dense else None  # L^-1 J^T W^1/2
    h = np.sum(v * v, axis=0) if v is not None else np.zeros(lay.n_res)
    row_t = np.abs(r[:n_t]) / np.sqrt(np.maximum(1.0 - h[:n_t], 0.05)) / scale
    row_t[~kept[:n_t]] = np.nan
    # odometry steps >= 2, three rows each
    step_t = np.full(len(lay.o_step), np.nan)
    ok = (lay.o_step >= 2) & kept[n_t::3]
    if np.any(ok):
        rows = n_t + 3 * np.nonzero(ok)[0][:, None] + np.arange(3)  # (G, 3)
        rr = r[rows]
        if v is not None:
            vr = v[:, rows]  # (n_free, G, 3)
            hh = np.einsum("fgi,fgj->gij", vr, vr)
            ev, u = np.linalg.eigh(np.eye(3)[None] - hh)  # I - H_RR, eigenvalues floored like 1 - h_k
            t2 = np.sum(np.einsum("gij,gi->gj", u, rr) ** 2 / np.maximum(ev, 0.05), axis=1)
        else:
            t2 = np.sum(rr * rr, axis=1)
        step_t[ok] = np.sqrt(np.maximum(t2, 0.0)) / scale_o
    # emission intervals (hybrid): score test of e_j
    interval_z = np.full(lay.k - 1, np.nan)
    if lay.n_s:
        rs = np.nonzero(kept[:lay.n_s])[0]
        cnt = np.bincount(lay.s_ev[rs], minlength=lay.k - 1)
        cand = np.ones(lay.k - 1, dtype=bool)
        cand[lay.free_intervals] = False
        cand &= cnt >= 3
        if np.any(cand):
            if lay.dense:
                e_w = (lay.s_ev[rs][None, :] == np.arange(lay.k - 1)[:, None]) * (w[rs] * lay.s_w)  # (K-1, R)
                g, score = e_w @ j[rs], e_w @ r[rs]  # J^T W a and a^T W r per interval
            else:
                e_w = scipy.sparse.csr_matrix((w[rs] * lay.s_w, (lay.s_ev[rs], rs)), shape=(lay.k - 1, lay.n_res))
                g, score = (e_w @ j).toarray(), e_w @ r
            aa = np.bincount(lay.s_ev[rs], weights=w[rs], minlength=lay.k - 1) * lay.s_w ** 2
            y = scipy.linalg.solve_triangular(chol, g.T, lower=True)
            info = aa - np.sum(y * y, axis=0)
            good = cand & (info > 1e-6 * np.maximum(aa, 1e-300))
            interval_z[good] = np.abs(score[good]) / np.sqrt(info[good]) / scale
    return _GrossTests(interval_z, row_t, step_t)


def _reject_gross_errors(lay: _Layout, run: _Run, *, loss: str, f_scale: float, reject_sigma: float,
                         max_iterations: int, limit_m: float, max_step_m: float, reject_odometry: bool,
                         max_rounds: int = 8):
    """Reject gross errors one kind per round and re-solve on the kept set, until none is left.

    A round frees the interval with the largest score above ``reject_sigma`` (a wrong ``interval_s[j]`` moves
    all TDOA-S of row ``j`` together; it is estimated, not dropped), else drops the worst TDOA of every mic
    and the worst odometry step above ``reject_sigma`` (see :func:`_gross_error_tests`), then polishes.
    Entries stay at
    most 10 % of the TDOAs, odometry steps and intervals at most a quarter of the steps (more points to a wrong
    basin, not to bad measurements); a round whose polish does not converge is undone.

    Returns the layout (with the freed intervals), the run, the residual mask (None if nothing was dropped),
    the test statistic of every rejection ``{("interval", j) | ("row", k) | ("step", g): sigmas}`` and the
    iterations used.
    """
    mask = np.ones(lay.n_res)
    n_t = lay.n_s + lay.n_m
    max_rows, max_groups = n_t // 10, max(1, (lay.k - 1) // 4)
    stats: dict[tuple[str, int], float] = {}
    n_it = 0
    for _ in range(max_rounds):
        tests = _gross_error_tests(lay, run.p, mask, loss, f_scale)
        if tests is None:
            break
        new_lay, p0, new_mask, new_stats = lay, run.p, mask.copy(), {}
        iz = np.nan_to_num(tests.interval_z, nan=0.0)
        if iz.size and iz.max() > reject_sigma and lay.n_e < max_groups:
            jb = int(np.argmax(iz))
            new_lay = lay.with_free_interval(jb)
            p0 = np.concatenate([run.p, [0.0]])
            new_stats[("interval", jb)] = float(iz[jb])
        else:
            # the worst TDOA of each mic and the worst odometry step: a gross error also inflates the
            # residuals it is fitted with (swamping), most of all those of its own mic
            t = np.nan_to_num(tests.row_t, nan=0.0)
            rows = []
            for i in np.unique(lay.res_mic[:n_t][t > reject_sigma]):
                own = np.nonzero(lay.res_mic[:n_t] == i)[0]
                rows.append(int(own[np.argmax(t[own])]))
            st = np.nan_to_num(tests.step_t, nan=0.0)
            steps = [int(np.argmax(st))] if reject_odometry and st.size and st.max() > reject_sigma else []
            n_rows = int(np.sum(mask[:n_t] == 0)) + len(rows)
            n_steps = int(np.sum(mask[n_t::3] == 0)) + len(steps)
            if (len(rows) == 0 and len(steps) == 0) or n_rows > max_rows or n_steps > max_groups:
                break
            new_mask[rows] = 0.0
            for g in steps:
                new_mask[n_t + 3 * g:n_t + 3 * g + 3] = 0.0
            new_stats.update({("row", int(k)): float(tests.row_t[k]) for k in rows})
            new_stats.update({("step", int(g)): float(tests.step_t[g]) for g in steps})
        polish = _levenberg_marquardt(new_lay, p0, loss=loss, f_scale=f_scale, max_iterations=max_iterations,
                                      limit_m=limit_m, max_step_m=max_step_m, mask=new_mask)
        n_it += polish.n_iterations
        if polish.status != "converged" or not np.all(np.isfinite(polish.p)):
            break
        lay, run, mask = new_lay, polish, new_mask
        stats.update(new_stats)
    return lay, run, (None if np.all(mask > 0) else mask), stats, n_it


def _rejected_report(lay: _Layout, p: np.ndarray, mask: np.ndarray | None,
                     stats: dict[tuple[str, int], float], reject_sigma: float) -> tuple["RejectedMeasurement", ...]:
    """Describe every rejection at the final estimate (which no longer uses the rejected measurements)."""
    if not stats:
        return ()
    r = lay.residuals(p)
    n_t = lay.n_s + lay.n_m
    out = []
    corr = lay.interval_corrections(p)
    if lay.n_e:
        cov_e = np.diag(_covariance(lay, p, mask))[lay.o_e:]
    for (kind, idx), stat in stats.items():
        if kind == "interval":
            std = float(np.sqrt(cov_e[list(lay.free_intervals).index(idx)]))
            keep_s = np.ones(lay.n_s, dtype=bool) if mask is None else mask[:lay.n_s] > 0
            n_rows = int(np.sum((lay.s_ev == idx) & keep_s))
            out.append(RejectedMeasurement(
                kind="interval", event=idx, mic=-1, residual=float(corr[idx]),
                normalised_residual=float(corr[idx] / std) if std > 0 else float("inf"), statistic=stat,
                reason=(f"the TDOA-S of {n_rows} mics between events {idx} and {idx + 1} share an offset: "
                        f"interval_s[{idx}] is off by {corr[idx] * 1e3:+.3f} ms (score test {stat:.1f} sigma "
                        f"> {reject_sigma:g}); estimated instead of given")))
        elif kind == "row":
            meas = -r[idx] / lay.w[idx]  # measured minus predicted, seconds
            if idx < lay.n_s:
                kd, ev, mic, what = "tdoa_events", int(lay.s_ev[idx]), int(lay.s_mic[idx]), "TDOA-S"
                where = f"events {ev} and {ev + 1}"
            else:
                q = idx - lay.n_s
                kd, ev, mic, what = "tdoa_mics", int(lay.m_ev[q]), int(lay.m_mic[q]), "TDOA-M"
                where = f"event {ev}"
            out.append(RejectedMeasurement(
                kind=kd, event=ev, mic=mic, residual=float(meas), normalised_residual=float(-r[idx]),
                statistic=stat,
                reason=(f"{what} of mic {mic} at {where} is {meas * 1e3:+.3f} ms from the fit "
                        f"({stat:.1f} sigma > {reject_sigma:g}): a mis-detected chirp")))
        else:
            step = int(lay.o_step[idx])
            rr = r[n_t + 3 * idx:n_t + 3 * idx + 3]
            out.append(RejectedMeasurement(
                kind="odometry", event=step, mic=-1, residual=float(np.linalg.norm(rr / lay.o_w)),
                normalised_residual=float(np.linalg.norm(rr)), statistic=stat,
                reason=(f"odometry step {step} (events {step} to {step + 1}) is "
                        f"{np.linalg.norm(rr / lay.o_w) * 100:.1f} cm from the fit ({stat:.1f} sigma > "
                        f"{reject_sigma:g})")))
    order = {"interval": 0, "tdoa_events": 1, "tdoa_mics": 2, "odometry": 3}
    return tuple(sorted(out, key=lambda m: (order[m.kind], m.event, m.mic)))


def _diagnostics(lay: _Layout, p: np.ndarray, mask: np.ndarray | None = None) -> dict:
    r = lay.residuals(p)
    keep = np.ones(len(r), dtype=bool) if mask is None else mask > 0
    rk = r[keep]
    dof = max(int(keep.sum()) - lay.n_free, 1)
    scale = 1.4826 * float(_median_abs(rk, _NO_MASK)) if len(rk) else 0.0
    inl = np.abs(rk) < 5.0 * max(1.0, scale)
    # per-mic robust scale: a mic stuck in a wrong basin fits systematically badly
    worst = 0.0
    for i in range(lay.n):
        own = (lay.res_mic == i) & keep
        if np.count_nonzero(own) >= 4:
            worst = max(worst, 1.4826 * float(_median_abs(r, own)))
    ro = r[lay.n_s + lay.n_m:][keep[lay.n_s + lay.n_m:]]
    return {"chi2_per_dof": float(rk @ rk) / dof, "residual_scale": scale,
            "inlier_fraction": float(np.mean(inl)) if len(rk) else 1.0, "worst_mic_scale": worst,
            "odometry_rms": float(np.sqrt(np.mean(ro * ro))) if len(ro) else 0.0,
            "n_outliers": int(len(r) - keep.sum()),
            "cost_per_dof": 2.0 * _loss(rk, "soft_l1", 3.0)[0] / dof}


def _plausible(diag: dict, max_residual_scale: float, max_odometry_rms: float, max_cost_per_dof: float) -> bool:
    """Residuals consistent with the assumed noise: robust TDOA scale, robust cost per degree of freedom,
    no mic fitting far worse than the rest, most residuals inliers, and an event trajectory that agrees with
    the odometry (a wrong basin often fits the TDOAs by bending the trajectory)."""
    return (diag["residual_scale"] <= max_residual_scale
            and diag["cost_per_dof"] <= max_cost_per_dof
            and diag["worst_mic_scale"] <= max(3.0 * diag["residual_scale"], 2.0 * max_residual_scale)
            and diag["inlier_fraction"] >= 0.7
            and diag["odometry_rms"] <= max_odometry_rms)


def solve(problem: HybridTdoaProblem, *, method: Method = "hybrid", init: Scene | None = None,
          rng: np.random.Generator | int | None = None, max_iterations: int = 100, n_starts: int = 3,
          loss: Loss = "soft_l1", f_scale: float = 3.0, max_residual_scale: float = 4.0,
          max_odometry_rms: float = 2.0, max_cost_per_dof: float = 2.0, reject_sigma: float | None = 8.0,
          with_covariance: bool = False, n_grid: int = 700, reject_odometry: bool = False) -> CalibrationResult:
    """Calibrate mics and events from hybrid TDOA + odometry (eq. 10). Pure function.

    Parameters
    ----------
    problem : HybridTdoaProblem
    method : {"hybrid", "baseline"}
        ``hybrid``: TDOA-S + TDOA-M + odometry (the paper); ``baseline``: TDOA-M + odometry.
    init : Scene or None
        First start, in the odometry frame (gauge coordinates are overwritten: ``s_0 = 0`` etc.).
        None: start from the built-in initialisation (events from integrated odometry, each mic by a grid
        search on its TDOA-S with a least-squares drift, offsets from TDOA-M).
    rng : Generator, int or None
        For random restarts (baseline, or mics without TDOA-S).
    max_iterations : int
        Levenberg-Marquardt iteration budget per start (no wall-clock limit). A start that stalls at an
        implausible cost (see ``max_cost_per_dof``) ends early.
    n_starts : int
        Maximum number of starts. A restart happens only after a verdict other than ``converged``; the
        second start uses the built-in initialisation, later ones perturb it (hybrid) or draw random mic
        positions around the odometry (baseline). The best plausible start wins.
    loss : {"soft_l1", "huber", "linear"}
        Robust loss on whitened residuals (``f_scale`` in units of sigma): soft_l1 / huber down-weight
        grossly mis-detected chirps.
    f_scale : float
        Inlier scale of the robust loss, in sigmas.
    max_residual_scale : float
        Largest plausible robust residual scale (``1.4826 median |r| / sigma``) for a ``converged`` verdict;
        real detections are often 1-3 sigma of the nominal noise.
    max_odometry_rms : float
        Largest plausible RMS of the whitened odometry residuals for a ``converged`` verdict at the first
        minimum found; above it the solver restarts, and accepts the minimum if a second start reaches it too.
    max_cost_per_dof : float
        Largest plausible ``2 * cost / (n_residuals - n_params)`` (soft-L1 at 3 sigma, about 1 when the noise
        levels are right) for a ``converged`` verdict at the first minimum found (restart otherwise, accept
        a minimum reached twice).
    reject_sigma : float or None
        Gross-error threshold, robustly scaled sigmas: after a start converges, emission intervals whose score
        test exceeds it are estimated instead of given, and TDOAs whose studentised residual exceeds it are
        dropped as mis-detected chirps (at most 10 % of the TDOAs: more points to a wrong basin, not to bad
        detections), re-solving on the kept set until none is left (see the module docstring). Reported in
        ``CalibrationResult.rejected`` (with residuals and reasons), ``outliers_*`` and
        ``interval_corrections_s``. None keeps every measurement as given.
    with_covariance : bool
        Also compute per-mic mic-frame location std from the Fisher information at the estimate.
    n_grid : int
        Number of points of the per-mic search grid (initialisation and local-minimum check).
    reject_odometry : bool
        Also test odometry steps (from step 2 on: steps 0 and 1 fix the gauge) and drop those above
        ``reject_sigma``. Off by default: a single step can be all that tells the scene from a mirrored or
        collapsed one.

    Returns
    -------
    CalibrationResult
    """
    if method not in ("hybrid", "baseline"):
        raise ValueError(f"{method=} must be 'hybrid' or 'baseline'")
    if loss not in ("linear", "soft_l1", "huber"):
        raise ValueError(f"{loss=} must be 'linear', 'soft_l1' or 'huber'")
    if int(max_iterations) < 1 or int(n_starts) < 1:
        raise ValueError(f"{max_iterations=} and {n_starts=} must be >= 1")
    if not (f_scale > 0 and max_residual_scale > 0):
        raise ValueError(f"{f_scale=} and {max_residual_scale=} must be > 0 (sigmas)")
    if reject_sigma is not None and not reject_sigma > 0:
        raise ValueError(f"{reject_sigma=} must be > 0 (sigmas) or None")
    rng = np.random.default_rng(rng)
    rot = _odometry_gauge(problem)  # odometry frame -> gauge frame
    odo_gauge = problem.odometry_m @ rot.T
    lay = _Layout(problem, method, "sound", odo_gauge)
    events_odo = _integrated_odometry(odo_gauge)
    scale_m = max(1.0, float(np.max(np.ptp(events_odo, axis=0))))

    baseline_starts = _BaselineStarts(lay, odo_gauge, n_grid)

    def start_from(k: int) -> np.ndarray:
        """Start 0: ``init`` if given. Then the built-in initialisation, later ones perturbed (hybrid) or
        from the next candidate position of mic 0 (baseline; random mics around the odometry once those are
        used up)."""
        if k == 0 and init is not None:
            if init.mic_positions_m.shape != (lay.n, 3) or init.event_positions_m.shape != (lay.k, 3):
                raise ValueError(f"init has {init.mic_positions_m.shape[0]} mics and "
                                 f"{init.event_positions_m.shape[0]} events, the problem {lay.n} and {lay.k}")
            if not all(np.all(np.isfinite(a)) for a in (init.mic_positions_m, init.event_positions_m,
                                                        init.offsets_s, init.drifts_ppm)):
                raise ValueError("init must be finite (metres, seconds, ppm)")
            return _apply_gauge(lay, lay.pack(init.mic_positions_m @ rot.T, init.offsets_s,
                                              init.drifts_ppm * _PPM, init.event_positions_m @ rot.T))
        if method == "baseline":
            p = baseline_starts.get(k - (0 if init is None else 2))
            if p is not None:
                return _apply_gauge(lay, p)
        p = _smart_init(lay, odo_gauge, method, rng, n_grid)
        n_smart = 1 if init is None else 2
        if method == "hybrid" and k >= n_smart:
            p[:3 * lay.n] += rng.normal(0.0, 0.3 * scale_m, 3 * lay.n)
        return _apply_gauge(lay, p)

    stall_cost = 0.5 * max_cost_per_dof * max(lay.n_res - lay.n_free, 1)  # an implausible cost
    best = None
    total_it = 0
    starts = 0
    certified_costs: list[float] = []  # certified but implausible minima; reached twice = confirmed
    corrected_minima: list[np.ndarray] = []  # plausible only with interval errors estimated; twice = confirmed
    builtin = 0 if init is None else 1  # the start from the built-in initialisation, unperturbed
    p0 = start_from(0)
    from_builtin = builtin == 0
    for k in range(int(n_starts)):
        run = _levenberg_marquardt(lay, p0, loss=loss, f_scale=f_scale, max_iterations=int(max_iterations),
                                   limit_m=10.0 * scale_m + 10.0, max_step_m=scale_m, stall_cost=stall_cost)
        starts += 1
        total_it += run.n_iterations
        finite = bool(np.all(np.isfinite(run.p)))
        alt = _check_reference(lay, run.p, n_grid) if (run.status == "converged" and finite
                                                       and method == "baseline") else None
        if alt is not None:  # a second opinion from mic 0's best candidate position; the lower cost wins
            other = _levenberg_marquardt(lay, _apply_gauge(lay, alt), loss=loss, f_scale=f_scale,
                                         max_iterations=int(max_iterations), limit_m=10.0 * scale_m + 10.0,
                                         max_step_m=scale_m, stall_cost=stall_cost)
            total_it += other.n_iterations
            better = _loss(lay.residuals(other.p), loss, f_scale)[0] < _loss(lay.residuals(run.p), loss, f_scale)[0]
            if other.status == "converged" and np.all(np.isfinite(other.p)) and better:
                run = other
        lay_k, mask, stats = lay, None, {}
        if run.status == "converged" and finite and reject_sigma is not None:
            # gross errors: reject them and re-solve on the kept set (a robust loss alone keeps a constant
            # pull, and a wrong emission interval is absorbed by the events and odometry, not down-weighted)
            lay_k, run, mask, stats, n_it = _reject_gross_errors(
                lay, run, loss=loss, f_scale=f_scale, reject_sigma=float(reject_sigma),
                max_iterations=int(max_iterations), limit_m=10.0 * scale_m + 10.0, max_step_m=scale_m,
                reject_odometry=reject_odometry)
            total_it += n_it
        diag = _diagnostics(lay_k, run.p, mask) if finite else None
        r_all = lay_k.residuals(run.p) if finite else None
        cost_cmp = _loss(r_all, loss, f_scale)[0] if finite else np.inf
        next_p0 = None
        if run.status == "converged" and finite:
            f_now = _adaptive_scale(r_all, f_scale, loss, mask)
            events = lay_k.unpack(run.p)[3]
            moved, q = _certify(lay_k, run.p, method, _grid(events, n_grid), f_now)
            if moved:
                verdict = "suspect_local_minimum"
                next_p0 = _apply_gauge(lay, q[:lay.n_full])
            elif _plausible(diag, max_residual_scale, max_odometry_rms, max_cost_per_dof):
                verdict = "converged"
                if lay_k.n_e and not (from_builtin and method == "hybrid"):
                    # an estimated interval error also absorbs the misfit of a wrong basin (e.g. events
                    # collapsed onto one plane): accept it from the built-in initialisation (mics from their
                    # own TDOA-S) or once a second start reaches the same mics (within 5 % of the scene
                    # size: the starts may differ in a rejected TDOA or two)
                    x_now = lay_k.unpack(run.p)[0]
                    if not any(np.max(np.abs(x_now - x0)) <= 0.05 * scale_m for x0 in corrected_minima):
                        verdict = "suspect_local_minimum"
                        corrected_minima.append(x_now)
            elif any(abs(cost_cmp - c0) <= 1e-6 * max(cost_cmp, 1.0) for c0 in certified_costs):
                verdict = "converged"  # the same certified minimum from two different starts
            else:
                verdict = "suspect_local_minimum"
                certified_costs.append(cost_cmp)
        else:
            verdict = run.status
        rank = {"converged": 0, "suspect_local_minimum": 1, "max_iterations": 2, "diverged": 3}[verdict]
        cand = (rank, cost_cmp if np.isfinite(cost_cmp) else np.inf, run, verdict, diag, mask, lay_k, stats)
        if best is None or cand[:2] < best[:2]:
            best = cand
        logger.debug("start %d: %s cost=%.4g it=%d rejected=%d", k, verdict, run.cost, run.n_iterations,
                     len(stats))
        if verdict == "converged":
            break
        p0 = next_p0 if next_p0 is not None else start_from(k + 1)
        from_builtin = next_p0 is None and k + 1 == builtin
    _, _, run, verdict, diag, mask, lay_k, stats = best
    if diag is None:
        diag = {"chi2_per_dof": np.inf, "residual_scale": np.inf, "inlier_fraction": 0.0}
    x, tau, delta, s = lay_k.unpack(run.p)
    scene = Scene(mic_positions_m=x @ rot, event_positions_m=s @ rot, offsets_s=tau - tau[0], drifts_ppm=delta / _PPM)
    std = None
    if with_covariance and verdict != "diverged":
        std = _mic_frame_std(lay_k, run.p, mask)
    out_s = np.zeros((lay.k - 1, lay.n), dtype=bool)
    out_m = np.zeros((lay.k, lay.n), dtype=bool)
    out_o = None
    if mask is not None:
        rej = mask == 0
        out_s[lay.s_ev[rej[:lay.n_s]], lay.s_mic[rej[:lay.n_s]]] = True
        rm = rej[lay.n_s:lay.n_s + lay.n_m]
        out_m[lay.m_ev[rm], lay.m_mic[rm]] = True
        ro = rej[lay.n_s + lay.n_m::3]
        if np.any(ro):
            out_o = np.zeros(lay.k - 1, dtype=bool)
            out_o[lay.o_step[ro]] = True
            out_o.setflags(write=False)
    out_s.setflags(write=False)
    out_m.setflags(write=False)
    finite = bool(np.all(np.isfinite(run.p)))
    rejected = _rejected_report(lay_k, run.p, mask, stats, float(reject_sigma)) if finite and stats else ()
    return CalibrationResult(scene=scene, method=method, verdict=verdict, cost=float(run.cost),
                             chi2_per_dof=float(diag["chi2_per_dof"]), residual_scale=float(diag["residual_scale"]),
                             inlier_fraction=float(diag["inlier_fraction"]), n_iterations=int(total_it),
                             n_starts_used=starts, outliers_tdoa_events=out_s, outliers_tdoa_mics=out_m,
                             mic_frame_location_std_m=None if std is None else _readonly(std),
                             rejected=rejected, outliers_odometry=out_o,
                             interval_corrections_s=_readonly(lay_k.interval_corrections(run.p)) if lay_k.n_e
                             else None)


# --------------------------------------------------------------------------------------------------------------
# Covariance, CRLB
# --------------------------------------------------------------------------------------------------------------
def _covariance(lay: _Layout, p: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Full-vector covariance ``F^-1`` (eq. 13; zero rows/columns for gauge-fixed parameters)."""
    a, _ = lay.normal_equations(p, mask)
    try:
        ci = scipy.linalg.cho_solve(scipy.linalg.cho_factor(a), np.eye(lay.n_free))
    except np.linalg.LinAlgError:
        ci = np.linalg.pinv(a)
    cov = np.zeros((lay.n_full, lay.n_full))
    idx = np.nonzero(lay.free)[0]
    cov[np.ix_(idx, idx)] = ci
    return cov


def _frame_jacobian(lay: _Layout, p: np.ndarray, *, rotate_only: bool) -> np.ndarray:
    """Jacobian of the mic-frame vector (eq. 18) w.r.t. the full parameter vector."""
    n = lay.n
    x, tau, delta, _ = lay.unpack(p)
    r = _frame_of(x[0], x[1], x[2])
    g = np.zeros((5 * n, lay.n_full))
    for i in range(n):
        g[3 * i:3 * i + 3, 3 * i:3 * i + 3] = r
    if not rotate_only:
        for i in range(n):
            g[3 * i:3 * i + 3, 0:3] -= r  # translation by x_0
        eps = 1e-7
        for col in range(9):  # rotation depends on x_0, x_1, x_2
            dx = np.zeros((n, 3))
            dx.ravel()[col] = eps
            rp = _frame_of(*(x + dx)[:3])
            rm = _frame_of(*(x - dx)[:3])
            g[:3 * n, col] += (((x - x[0]) @ rp.T) - ((x - x[0]) @ rm.T)).ravel() / (2 * eps)
    g[3 * n + np.arange(n), lay.o_tau + np.arange(n)] = 1.0
    g[3 * n + np.arange(n), lay.o_tau] -= 1.0
    g[4 * n + np.arange(n), lay.o_del + np.arange(n)] = 1.0
    g[4 * n + np.arange(n), lay.o_del] -= 1.0
    return g


def _d_crlb(cov_mic: np.ndarray, n: int) -> tuple[float, float, float]:
    """Eq. (16) as in ``compute_CRLB.m``: x of mic 1, x-y of mic 2, x-y-z of mics >= 3; offsets, drifts."""
    v = np.diag(cov_mic)
    loc = [v[3], v[6] + v[7]] + [v[3 * i:3 * i + 3].sum() for i in range(3, n)]
    off = v[3 * n + 1:4 * n]
    dri = v[4 * n + 1:5 * n]
    return float(np.sqrt(np.mean(loc))), float(np.sqrt(np.mean(off))), float(np.sqrt(np.mean(dri)) / _PPM)


def _mic_frame_std(lay: _Layout, p: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    cov = _covariance(lay, p, mask)
    g = _frame_jacobian(lay, p, rotate_only=False)
    cm = g @ cov @ g.T
    v = np.diag(cm)[:3 * lay.n].reshape(lay.n, 3)
    return np.sqrt(np.maximum(v.sum(1), 0.0))


def _sound_frame_truth(truth: Scene) -> Scene:
    s = truth.event_positions_m
    r = _frame_of(s[0], s[1], s[2])
    return Scene((truth.mic_positions_m - s[0]) @ r.T, (s - s[0]) @ r.T, truth.offsets_s, truth.drifts_ppm)


def crlb(problem: HybridTdoaProblem, truth: Scene, *, method: Method = "hybrid",
         unknown_intervals: Sequence[int] = ()) -> CrlbResult:
    """Cramer-Rao bound ``C = (J^T W^-1 J)^-1`` (eqs. 11-13) at the true scene, scored in the mic frame.

    Only the structure of ``problem`` is used (which measurements exist, intervals, noise levels, speed of
    sound), not the measured values. Reports both the full-Jacobian frame change and the authors' variant
    (see :class:`CrlbResult`).

    For the kept measurements of a solve pass ``without_rejected(problem, result)`` and
    ``unknown_intervals=result.estimated_intervals``: the intervals the solver estimated (hybrid) are then
    nuisance parameters, not known values.
    """
    n = problem.n_mics
    if truth.mic_positions_m.shape != (n, 3) or truth.event_positions_m.shape != (problem.n_events, 3):
        raise ValueError("truth shapes do not match the problem")
    unknown = np.asarray(unknown_intervals, dtype=np.intp).reshape(-1) if method == "hybrid" else ()
    if len(unknown) and (np.min(unknown) < 0 or np.max(unknown) >= problem.n_events - 1):
        raise ValueError(f"{unknown_intervals=} must be interval indices in 0..{problem.n_events - 2}")
    t = _sound_frame_truth(truth)
    lay = _Layout(problem, method, "sound", free_intervals=unknown)
    p = lay.pack(t.mic_positions_m, t.offsets_s - t.offsets_s[0],
                 t.drifts_ppm * _PPM - (t.drifts_ppm[0] * _PPM if method == "baseline" else 0.0),
                 t.event_positions_m)
    cov = _covariance(lay, p)
    cm = _frame_jacobian(lay, p, rotate_only=False) @ cov @ _frame_jacobian(lay, p, rotate_only=False).T
    full = _d_crlb(cm, n)
    if method == "hybrid":
        g = _frame_jacobian(lay, p, rotate_only=True)
        authors = _d_crlb(g @ cov @ g.T, n)
    else:  # authors' baseline: parameterised directly in the true mic frame (sg_generation.m)
        mf = to_mic_frame(truth)
        lay_m = _Layout(problem, method, "mic")
        pm = lay_m.pack(mf.mic_positions_m, mf.offsets_s, mf.drifts_ppm * _PPM, mf.event_positions_m)
        cov_m = _covariance(lay_m, pm)
        g = _frame_jacobian(lay_m, pm, rotate_only=True)
        authors = _d_crlb(g @ cov_m @ g.T, n)
    per_mic = np.sqrt(np.maximum(np.diag(cm)[:3 * n].reshape(n, 3).sum(1), 0.0))
    return CrlbResult(method=method, location_std_m=full[0], offset_std_s=full[1], drift_std_ppm=full[2],
                      location_std_m_authors=authors[0], offset_std_s_authors=authors[1],
                      drift_std_ppm_authors=authors[2], per_mic_location_std_m=_readonly(per_mic),
                      mic_frame_covariance=_readonly(cm))


def without_rejected(problem: HybridTdoaProblem, result: CalibrationResult) -> HybridTdoaProblem:
    """The problem as the solver kept it: rejected TDOAs and odometry steps NaN (missing), rejected emission
    intervals replaced by their estimates (``interval_s + interval_corrections_s``).

    Use it for noise estimates (:func:`estimate_noise_levels`) and bounds (:func:`crlb`, with
    ``unknown_intervals=result.estimated_intervals``) of the kept set.
    """
    te = problem.tdoa_events_s
    if te is not None:
        te = np.where(result.outliers_tdoa_events, np.nan, te)
    tm = np.where(result.outliers_tdoa_mics, np.nan, problem.tdoa_mics_s)
    odo = problem.odometry_m
    if result.outliers_odometry is not None:
        odo = np.where(result.outliers_odometry[:, None], np.nan, odo)
    iv = problem.interval_s
    if result.interval_corrections_s is not None:
        iv = iv + result.interval_corrections_s
    return dataclasses.replace(problem, tdoa_events_s=te, tdoa_mics_s=tm, odometry_m=odo, interval_s=iv)


# --------------------------------------------------------------------------------------------------------------
# Noise levels (Appendix B) and simulation
# --------------------------------------------------------------------------------------------------------------
def estimate_noise_levels(problem: HybridTdoaProblem, scene: Scene) -> NoiseLevels:
    """Appendix B: TDOA-S / TDOA-M noise std given a scene (the truth, or a calibration estimate).

    TDOA-S of mic ``i``: remove the geometry and the interval, fit ``delta_i`` by least squares
    (``sum dt*r / sum dt^2``), std of the rest with one degree of freedom removed. TDOA-M of mic ``i >= 1``:
    remove the geometry, fit offset + drift ``[1, t_j]`` by least squares, two degrees removed.
    The pooled values use all residuals.
    """
    n, c = problem.n_mics, problem.speed_of_sound_m_s
    x, s = scene.mic_positions_m, scene.event_positions_m
    d = np.linalg.norm(x[:, None, :] - s[None, :, :], axis=2)  # (N, K)
    ev = np.full(n, np.nan)
    ss_e, dof_e = 0.0, 0
    if problem.tdoa_events_s is not None:
        for i in range(n):
            y = problem.tdoa_events_s[:, i]
            ok = np.isfinite(y)
            if ok.sum() < 2:
                continue
            dt = problem.interval_s[ok]
            e = y[ok] - dt - (d[i, 1:][ok] - d[i, :-1][ok]) / c
            res = e - (e @ dt) / (dt @ dt) * dt
            ev[i] = np.sqrt(res @ res / (len(res) - 1))
            ss_e += res @ res
            dof_e += len(res) - 1
    mi = np.full(n, np.nan)
    ss_m, dof_m = 0.0, 0
    t = problem.emission_times_s
    for i in range(1, n):
        y = problem.tdoa_mics_s[:, i]
        ok = np.isfinite(y)
        if ok.sum() < 3:
            continue
        e = y[ok] - (d[i, ok] - d[0, ok]) / c
        a = np.stack([np.ones(ok.sum()), t[ok]], 1)
        coef, *_ = np.linalg.lstsq(a, e, rcond=None)
        res = e - a @ coef
        mi[i] = np.sqrt(res @ res / (len(res) - 2))
        ss_m += res @ res
        dof_m += len(res) - 2
    return NoiseLevels(tdoa_events_std_s=float(np.sqrt(ss_e / dof_e)) if dof_e else float("nan"),
                       tdoa_mics_std_s=float(np.sqrt(ss_m / dof_m)) if dof_m else float("nan"),
                       per_mic_events_std_s=_readonly(ev), per_mic_mics_std_s=_readonly(mi))


def simulate_problem(truth: Scene, interval_s, *, sigma_tdoa_s: float, sigma_odo_m: float,
                     rng: np.random.Generator | int | None = None,
                     speed_of_sound_m_s: float = SPEED_OF_SOUND_M_S, noise_free: bool = False) -> HybridTdoaProblem:
    """Noisy TDOA-S, TDOA-M and odometry of a true scene (eqs. 4-6, 9; i.i.d. Gaussian noise).

    Odometry is expressed in the frame of ``truth``. With ``noise_free`` the measurements are exact and the
    sigmas only set the weights.
    """
    rng = np.random.default_rng(rng)
    scale = 0.0 if noise_free else 1.0
    x, s = truth.mic_positions_m, truth.event_positions_m
    n, k = x.shape[0], s.shape[0]
    iv = np.asarray(interval_s, float)
    t = np.concatenate([[0.0], np.cumsum(iv)])
    c = speed_of_sound_m_s
    delta = truth.drifts_ppm * _PPM
    d = np.linalg.norm(x[None, :, :] - s[:, None, :], axis=2)  # (K, N)
    toa = d / c + truth.offsets_s[None, :] + (1 + delta[None, :]) * t[:, None]  # eq. (4)
    tdoa_s = ((d[1:] - d[:-1]) / c + (1 + delta[None, :]) * iv[:, None]
              + scale * rng.normal(0, sigma_tdoa_s, (k - 1, n)))  # eq. (5)
    tdoa_m = toa - toa[:, :1] + scale * rng.normal(0, sigma_tdoa_s, (k, n))  # eq. (6)
    tdoa_m[:, 0] = np.nan
    odo = s[1:] - s[:-1] + scale * rng.normal(0, sigma_odo_m, (k - 1, 3))  # eq. (9)
    return HybridTdoaProblem(tdoa_events_s=tdoa_s, tdoa_mics_s=tdoa_m, odometry_m=odo, interval_s=iv,
                             sigma_tdoa_s=sigma_tdoa_s, sigma_odo_m=sigma_odo_m, speed_of_sound_m_s=c)
