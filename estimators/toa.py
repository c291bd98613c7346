"""Relative time-of-arrival (TOA) estimators from pairwise TDOAs (TOA paper section III).

All estimators share one interface:

- the constructor validates its arguments (``ValueError`` with the offending value);
- ``update(tdoa_s, confidence=None) -> toa_s``: ``tdoa_s`` has shape ``(n_pairs,)`` in seconds in
  the pair order of :func:`estimators.conventions.pairs`, ``tdoa_s[p] = toa_i - toa_j`` for
  ``p = (i, j)``; ``toa_s`` has shape ``(n_mics,)`` in seconds with ``toa_s[0] = 0``;
- ``reset()`` returns to the freshly constructed state;
- ``gated`` (bool) tells whether the last update was rejected as clutter (always ``False`` for the
  instantaneous estimators).

Sign: ``y = H @ toa`` (eq. 9) with ``H = pair_matrix(M)`` (eq. 10). The first ``M - 1`` pairs are
``(0, j)`` with ``y = toa_0 - toa_j = -toa_j``, so eq. (11) reads ``toa_j = -tdoa[(0, j)]`` in the
engine's convention (the paper writes ``tau_j = tau_1j`` with a looser sign).

Confidence (optional, shape ``(n_pairs,)``, e.g. the GCC-PHAT peak height in ``[0, 1]``): a pair
whose confidence is ``<= min_confidence`` (default 0, i.e. pairs with a silent channel), or whose
TDOA is not finite, is excluded. Estimators that weight pairs by confidence say so.
"""
from __future__ import annotations

import collections
import math

import numpy as np
import scipy.linalg
import scipy.linalg.lapack
import scipy.stats
from filterpy.common import Q_continuous_white_noise
from filterpy.kalman import KalmanFilter

from .conventions import pair_matrix

__all__ = ["FixedLagKalmanToa", "KalmanToa", "PinvToa", "SubsetToa"]


def _check_n_mics(n_mics: int) -> int:
    if int(n_mics) != n_mics or n_mics < 2:
        raise ValueError(f"{n_mics=} must be an integer >= 2")
    return int(n_mics)


def _check_min_confidence(min_confidence: float) -> float:
    if not np.isfinite(min_confidence) or not 0.0 <= min_confidence < 1.0:
        raise ValueError(f"{min_confidence=} must be in [0, 1)")
    return float(min_confidence)


class _PairModel:
    """Shapes, the reduced observation matrix ``H0`` and input checks shared by the estimators."""

    def __init__(self, n_mics: int, min_confidence: float) -> None:
        self.n_mics = _check_n_mics(n_mics)
        self.n_pairs = self.n_mics * (self.n_mics - 1) // 2
        self.min_confidence = _check_min_confidence(min_confidence)
        # eq. (12): H0 is H of eq. (10) without the column of the reference microphone.
        self._H0 = pair_matrix(self.n_mics)[:, 1:]
        self._H0T = np.ascontiguousarray(self._H0.T)
        self._H0_pinv = np.linalg.pinv(self._H0)  # (H0^T H0)^-1 H0^T, shape (M-1, n_pairs)
        self._zero = np.zeros(1)

    def _inputs(self, tdoa_s, confidence) -> tuple[np.ndarray, np.ndarray | None]:
        """Validated ``(tdoa_s, used)``; ``used`` is ``None`` when every pair is usable."""
        tdoa = np.asarray(tdoa_s, dtype=np.float64)
        if tdoa.shape != (self.n_pairs,):
            raise ValueError(f"tdoa_s.shape={tdoa.shape} must be (n_pairs,)=({self.n_pairs},)")
        conf = None
        if confidence is not None:
            conf = np.asarray(confidence, dtype=np.float64)
            if conf.shape != (self.n_pairs,):
                raise ValueError(f"confidence.shape={conf.shape} must be (n_pairs,)=({self.n_pairs},)")
        # Fast path, every pair usable: a finite sum means no NaN/inf TDOA (a sum of finite TDOAs
        # overflows only near 1e308 s, which then takes the exact test below) and a NaN confidence
        # makes the minimum NaN, which compares False. Two reductions instead of four numpy calls.
        if math.isfinite(np.add.reduce(tdoa)) and (conf is None or np.minimum.reduce(conf) > self.min_confidence):
            return tdoa, None
        used = np.isfinite(tdoa)
        if conf is not None:
            used &= conf > self.min_confidence  # NaN confidence compares False: excluded
        if used.all():
            return tdoa, None
        return np.where(used, tdoa, 0.0), used

    def _toa(self, toa0: np.ndarray) -> np.ndarray:
        return np.concatenate((self._zero, toa0))  # [0, toa0], a new array (one call instead of three)

    def _wls(self, tdoa: np.ndarray, weights: np.ndarray | None) -> np.ndarray:
        """Weighted least-squares ``toa_0`` (eq. 12 with weights); minimum norm if unobservable."""
        if weights is None:
            return self._H0_pinv @ tdoa
        sw = np.sqrt(weights)
        return np.linalg.lstsq(self._H0 * sw[:, None], tdoa * sw, rcond=None)[0]


class SubsetToa(_PairModel):
    """TOA from the pairs with the reference microphone only (TOA paper eq. 11).

    ``toa_j = -tdoa[(0, j)]`` for ``j >= 1`` (engine sign, see the module docstring). Pairs not
    involving microphone 0 are ignored.

    Parameters
    ----------
    n_mics : int
        Number of microphones ``M >= 2``.
    min_confidence : float
        Pairs with confidence ``<= min_confidence`` (when given) or a non-finite TDOA are excluded;
        the TOA of an excluded microphone holds its previous value (0 before any).
    """

    def __init__(self, n_mics: int, *, min_confidence: float = 0.0) -> None:
        super().__init__(n_mics, min_confidence)
        self.gated = False
        self.reset()

    def reset(self) -> None:
        """Forget the held values."""
        self._toa_s = np.zeros(self.n_mics)

    def update(self, tdoa_s: np.ndarray, confidence: np.ndarray | None = None) -> np.ndarray:
        """Relative TOA from one TDOA vector.

        Parameters
        ----------
        tdoa_s : ndarray, shape (n_pairs,), float
            Pairwise TDOAs in seconds, ``toa_i - toa_j``.
        confidence : ndarray, shape (n_pairs,), float, optional
            Per-pair confidence; only used to exclude pairs.

        Returns
        -------
        ndarray, shape (n_mics,), float64
            Relative TOA in seconds, ``toa_s[0] = 0``.
        """
        tdoa, used = self._inputs(tdoa_s, confidence)
        m = self.n_mics - 1
        # eq. (11): the first M-1 pairs are (0, j), tdoa = toa_0 - toa_j = -toa_j.
        if used is None:
            self._toa_s[1:] = -tdoa[:m]
        else:
            self._toa_s[1:] = np.where(used[:m], -tdoa[:m], self._toa_s[1:])
        return self._toa_s.copy()


class PinvToa(_PairModel):
    """TOA from all pairs with the Moore-Penrose inverse (TOA paper eq. 12).

    ``toa_0 = (H0^T H0)^-1 H0^T y`` with ``H0`` the pair matrix without column 0; the pseudo-inverse
    is computed once at construction.

    Parameters
    ----------
    n_mics : int
        Number of microphones ``M >= 2``.
    weighted : bool
        ``False`` (default, the paper's estimator): every usable pair has the same weight.
        ``True``: weighted least squares ``(H0^T W H0)^-1 H0^T W y`` with ``W = diag(confidence)``
        when a confidence is given, i.e. a pair's TDOA variance is taken inversely proportional to
        its confidence.
    min_confidence : float
        Pairs with confidence ``<= min_confidence`` (when given) or a non-finite TDOA are excluded
        in both modes. If the remaining pairs do not connect every microphone to microphone 0, the
        minimum-norm least-squares solution is returned (0 for an isolated microphone).
    """

    def __init__(self, n_mics: int, *, weighted: bool = False, min_confidence: float = 0.0) -> None:
        super().__init__(n_mics, min_confidence)
        self.weighted = bool(weighted)
        self.gated = False

    def reset(self) -> None:
        """No state is carried between frames."""

    def update(self, tdoa_s: np.ndarray, confidence: np.ndarray | None = None) -> np.ndarray:
        """Relative TOA from one TDOA vector.

        Parameters
        ----------
        tdoa_s : ndarray, shape (n_pairs,), float
            Pairwise TDOAs in seconds, ``toa_i - toa_j``.
        confidence : ndarray, shape (n_pairs,), float, optional
            Per-pair confidence in ``[0, 1]``: excludes pairs, and weights them if ``weighted``.

        Returns
        -------
        ndarray, shape (n_mics,), float64
            Relative TOA in seconds, ``toa_s[0] = 0``.
        """
        tdoa, used = self._inputs(tdoa_s, confidence)
        if self.weighted and confidence is not None:
            weights = np.asarray(confidence, dtype=np.float64).copy()
            if used is not None:
                weights[~used] = 0.0
        elif used is not None:
            weights = used.astype(np.float64)
        else:
            weights = None
        return self._toa(self._wls(tdoa, weights))


class KalmanToa(_PairModel):
    """Kalman filter on the relative TOA with clutter gating (TOA paper eqs. 13-17).

    State ``x = [toa_0, d toa_0 / dt]`` of length ``2 (M - 1)`` in seconds and seconds per second
    (eq. 15, TOA of microphones ``1..M-1``, then their rates). Wiener-velocity model (eq. 16):
    ``F = [[I, dt I], [0, I]]`` with continuous white-noise acceleration
    ``Q = q [[dt^3/3, dt^2/2], [dt^2/2, dt]] (x) I`` (``filterpy.common.Q_continuous_white_noise``,
    ``order_by_dim=False`` for this derivative-major order). Observation (eq. 14): all pairs,
    ``y = [H0, 0] x + r``, ``r ~ N(0, R)``, ``R = diag(tdoa_var_p)``.

    Parameters
    ----------
    n_mics : int
        Number of microphones ``M >= 2``.
    frame_period_s : float
        Time between updates (the hop) in seconds, > 0.
    accel_std_s_per_s2 : float
        TOA acceleration noise, > 0: the spectral density of the white acceleration is
        ``q = accel_std_s_per_s2**2`` (per second), so the TOA rate diffuses by
        ``accel_std_s_per_s2 * sqrt(t_s)`` in ``t_s`` seconds, independently of the frame period.
    tdoa_std_s : float
        Standard deviation of one pair's TDOA error in seconds, > 0.
    initial_rate_std_s_per_s : float
        Prior standard deviation of the TOA rates at (re-)initialisation, in s/s, > 0.
    gate_probability : float or None
        Clutter gate (eq. 17): the innovation ``v = y - H x`` of the used pairs is rejected when its
        squared Mahalanobis distance ``v^T S^-1 v`` (``S = H P H^T + R``) exceeds
        ``chi2.ppf(gate_probability, n_used_pairs)``, i.e. when ``N(y | H x, S)`` is below the level
        that keeps ``gate_probability`` of true measurements. The filter then only predicts.
        ``None`` disables gating (the paper's simulation).
    reinit_after_n_gated : int or None
        After this many consecutive gated frames the track is considered lost and the filter is
        re-initialised from the pseudo-inverse estimate of the current measurement (counted in
        ``n_reinit``). ``None`` never re-initialises.
    min_confidence : float
        When a confidence is given, pairs with confidence ``<= min_confidence`` (default 0: pairs
        with a silent channel) are removed from the observation, as are non-finite TDOAs. With no
        usable pair the filter only predicts and ``gated`` is ``False``.
    confidence_weighted : bool
        When ``True`` and a confidence is given, a used pair's TDOA variance is
        ``tdoa_std_s**2 / confidence_p`` (a heuristic: the PHAT peak height falls with the SNR).
    pair_gate_sigma : float or None
        Per-pair clutter gate applied before eq. (17): pairs whose innovation exceeds this many
        standard deviations of their predicted spread are left out of the update (counted in
        ``n_pairs_gated``); None (default) keeps the paper's whole-frame gate only.
    init_max_residual_s : float or None
        (Re-)initialise only from a frame whose pseudo-inverse fit leaves an RMS TDOA residual
        below this (seconds): a self-consistent frame. None (default) initialises from the first
        frame that makes every TOA observable, as the paper does.
    initial_toa_std_s : float or None
        A weak prior ``toa ~ N(0, initial_toa_std_s**2)`` at (re-)initialisation, so that the
        filter starts as soon as three pairs are usable, even while some devices have not started
        (their TOA starts at 0 with this spread). None (default): wait until every TOA is observable.

    Attributes
    ----------
    gated : bool
        The last measurement was rejected by the gate.
    reinitialised : bool
        The last update (re-)initialised the state from the measurement.
    n_gated, n_reinit : int
        Totals since construction or :meth:`reset`.
    n_pairs_used : int
        Pairs used by the last update.
    last_mahalanobis_sq : float
        ``v^T S^-1 v`` of the last measurement (NaN when none was evaluated).

    Notes
    -----
    Initialisation (paper, end of section III-C): the first usable measurement whose pairs connect
    every microphone gives the state ``[pinv estimate, 0]`` with covariance
    ``blockdiag((H0^T R^-1 H0)^-1, initial_rate_std**2 I)``; until then :meth:`update` returns zeros.

    The prediction is ``filterpy.kalman.KalmanFilter.predict``. The measurement update is written
    here in information form: filterpy's generic update inverts the ``n_pairs x n_pairs`` matrix
    ``S`` (120 x 120 at 16 microphones) and the gate would need ``S`` once more before deciding;
    since ``H = [H0, 0]`` and ``R`` is diagonal, the same posterior and Mahalanobis distance follow
    from one ``(M-1) x (M-1)`` solve (see :meth:`_measurement_update`). The test suite checks it
    against ``KalmanFilter.update``. The prediction runs the same ``dot`` calls as
    ``KalmanFilter.predict`` (hence the same values) without its per-call overhead. The filter never
    modifies its arrays in place (every step binds new ones), so ``x_prior``/``x_post`` and
    ``P_prior``/``P_post`` of the filterpy object share them with ``x`` and ``P`` instead of
    copying.
    """

    def __init__(
        self,
        n_mics: int,
        *,
        frame_period_s: float,
        accel_std_s_per_s2: float = 0.01,
        tdoa_std_s: float = 1e-4,
        initial_rate_std_s_per_s: float = 0.01,
        gate_probability: float | None = 0.999,
        reinit_after_n_gated: int | None = 25,
        min_confidence: float = 0.0,
        confidence_weighted: bool = False,
        pair_gate_sigma: float | None = None,
        init_max_residual_s: float | None = None,
        initial_toa_std_s: float | None = None,
    ) -> None:
        super().__init__(n_mics, min_confidence)
        if initial_toa_std_s is not None and not initial_toa_std_s > 0:
            raise ValueError(f"{initial_toa_std_s=} must be None or > 0 seconds")
        self.initial_toa_std_s = initial_toa_std_s
        if init_max_residual_s is not None and not init_max_residual_s > 0:
            raise ValueError(f"{init_max_residual_s=} must be None or > 0 seconds")
        self.init_max_residual_s = init_max_residual_s
        if pair_gate_sigma is not None and not pair_gate_sigma > 0:
            raise ValueError(f"{pair_gate_sigma=} must be None or > 0 standard deviations")
        self.pair_gate_sigma = pair_gate_sigma
        for name, value in (
            ("frame_period_s", frame_period_s),
            ("accel_std_s_per_s2", accel_std_s_per_s2),
            ("tdoa_std_s", tdoa_std_s),
            ("initial_rate_std_s_per_s", initial_rate_std_s_per_s),
        ):
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"{name}={value!r} must be finite and > 0")
        if gate_probability is not None and not 0.0 < gate_probability < 1.0:
            raise ValueError(f"{gate_probability=} must be None or in (0, 1)")
        if reinit_after_n_gated is not None and (
            int(reinit_after_n_gated) != reinit_after_n_gated or reinit_after_n_gated < 1
        ):
            raise ValueError(f"{reinit_after_n_gated=} must be None or an integer number of frames >= 1")
        self.frame_period_s = float(frame_period_s)
        self.accel_std_s_per_s2 = float(accel_std_s_per_s2)
        self.tdoa_std_s = float(tdoa_std_s)
        self.initial_rate_std_s_per_s = float(initial_rate_std_s_per_s)
        self.gate_probability = gate_probability
        self.reinit_after_n_gated = None if reinit_after_n_gated is None else int(reinit_after_n_gated)
        self.confidence_weighted = bool(confidence_weighted)

        m = self.n_mics - 1
        self._m = m
        dt = self.frame_period_s
        self._F = np.block([[np.eye(m), dt * np.eye(m)], [np.zeros((m, m)), np.eye(m)]])  # eq. (16)
        self._Q = Q_continuous_white_noise(
            dim=2, dt=dt, spectral_density=self.accel_std_s_per_s2**2, block_size=m, order_by_dim=False
        )
        self._tdoa_var = self.tdoa_std_s**2
        # eq. (12) information matrix with all pairs at the nominal variance: H0^T R^-1 H0.
        self._B_all = self._H0T @ self._H0 / self._tdoa_var
        # eq. (17) gate: chi-square quantile for k = 0..n_pairs used pairs.
        if gate_probability is None:
            self._gate = np.full(self.n_pairs + 1, np.inf)
        else:
            self._gate = np.concatenate(
                [[np.inf], scipy.stats.chi2.ppf(gate_probability, np.arange(1, self.n_pairs + 1))]
            )
        self._eye_m = np.eye(m)
        self._FT = self._F.T
        self._rhs = np.empty((m, m + 1))  # right-hand sides [B, b] of the measurement update
        self._rhs_B: np.ndarray | None = None  # the B held in self._rhs[:, :m] (only ever _B_all)
        self._kf = KalmanFilter(dim_x=2 * m, dim_z=self.n_pairs)
        self._kf.F = self._F
        self._kf.Q = self._Q
        self._kf.H = np.hstack([self._H0, np.zeros((self.n_pairs, m))])  # eq. (14)
        self._kf.R = self._tdoa_var * np.eye(self.n_pairs)
        self.reset()

    # -- public interface ------------------------------------------------------------------------

    @property
    def latency_s(self) -> float:
        """Extra output latency in seconds (0 for the filter)."""
        return 0.0

    @property
    def initialised(self) -> bool:
        """Whether the state has been initialised from a measurement."""
        return self._initialised

    @property
    def state(self) -> np.ndarray:
        """Copy of the state ``[toa_0, toa_rate_0]``, shape (2 (n_mics - 1),), s and s/s."""
        return np.asarray(self._kf.x, dtype=np.float64).copy()

    @property
    def state_covariance(self) -> np.ndarray:
        """Copy of the state covariance, shape (2 (n_mics - 1), 2 (n_mics - 1))."""
        return np.asarray(self._kf.P, dtype=np.float64).copy()

    def reset(self) -> None:
        """Forget the track and the counters."""
        m = self._m
        self._kf.x = np.zeros(2 * m)
        self._kf.P = np.eye(2 * m)
        self._kf.x_prior = self._kf.x.copy()
        self._kf.P_prior = self._kf.P.copy()
        self._kf.x_post = self._kf.x.copy()
        self._kf.P_post = self._kf.P.copy()
        self._initialised = False
        self.gated = False
        self.reinitialised = False
        self.n_gated = 0
        self.n_reinit = 0
        self.n_pairs_gated = 0
        self.n_pairs_used = 0
        self.last_mahalanobis_sq = float("nan")
        self._consecutive_gated = 0

    def shift(self, delta_toa_s: np.ndarray, *, delta_rate_s_per_s: np.ndarray | None = None) -> None:
        """Move the tracked TOA by ``delta_toa_s`` (n_mics,) seconds, and optionally its rate by
        ``delta_rate_s_per_s`` (n_mics,), keeping the covariance.

        Used when the stream re-aligns a device by a whole number of samples (the fine TOA jumps by
        a known amount) or corrects a device's clock drift (its TOA rate changes by a known
        amount): a known change must not look like clutter.
        """
        self._kf.x, self._kf.x_prior, self._kf.x_post = (
            np.asarray(getattr(self._kf, name), dtype=np.float64) + self._shift_step(delta_toa_s, delta_rate_s_per_s)
            for name in ("x", "x_prior", "x_post"))

    def _shift_step(self, delta_toa_s, delta_rate_s_per_s) -> np.ndarray:
        step = np.zeros(2 * self._m)
        for k, (name, value) in enumerate((("delta_toa_s", delta_toa_s), ("delta_rate_s_per_s", delta_rate_s_per_s))):
            if value is None:
                continue
            d = np.asarray(value, dtype=np.float64)
            if d.shape != (self.n_mics,):
                raise ValueError(f"{name}.shape={d.shape} must be (n_mics,)=({self.n_mics},)")
            step[k * self._m:(k + 1) * self._m] = d[1:] - d[0]
        return step

    def update(self, tdoa_s: np.ndarray, confidence: np.ndarray | None = None) -> np.ndarray:
        """Predict one frame ahead, then update with (or gate out) one TDOA vector.

        Parameters
        ----------
        tdoa_s : ndarray, shape (n_pairs,), float
            Pairwise TDOAs in seconds, ``toa_i - toa_j``.
        confidence : ndarray, shape (n_pairs,), float, optional
            Per-pair confidence in ``[0, 1]``; see ``min_confidence`` and ``confidence_weighted``.

        Returns
        -------
        ndarray, shape (n_mics,), float64
            Filtered relative TOA of the current frame in seconds, ``toa_s[0] = 0``.
        """
        tdoa, used = self._inputs(tdoa_s, confidence)
        var = None
        if self.confidence_weighted and confidence is not None:
            conf = np.asarray(confidence, dtype=np.float64)
            mask = used if used is not None else np.ones(self.n_pairs, bool)
            var = np.where(mask, self._tdoa_var / np.where(mask, conf, 1.0), np.inf)
        self._step(tdoa, used, var)
        return self._toa(self._kf.x[: self._m])

    def predict(self) -> np.ndarray:
        """Advance one frame without a measurement (e.g. no speech); returns the predicted TOA."""
        self._step(None, None, None)
        return self._toa(self._kf.x[: self._m])

    # -- internals -------------------------------------------------------------------------------

    def _step(self, tdoa: np.ndarray | None, used: np.ndarray | None, var: np.ndarray | None) -> None:
        """One frame: (initialise |) predict, gate, update. Sets the per-frame attributes."""
        self.gated = False
        self.reinitialised = False
        self.last_mahalanobis_sq = float("nan")
        n_used = 0 if tdoa is None else (self.n_pairs if used is None else int(used.sum()))
        self.n_pairs_used = n_used
        if not self._initialised:
            if n_used and self._initialise(tdoa, used, var):
                self.reinitialised = True
            return
        kf = self._kf
        self._predict()
        if n_used == 0:
            kf.x_post, kf.P_post = kf.x, kf.P
            return
        if self.pair_gate_sigma is not None:
            used, var, n_used = self._pair_gate(tdoa, used, var)
        if n_used and self._measurement_update(tdoa, used, var, n_used):
            self._consecutive_gated = 0
            return
        self.gated = True
        self.n_gated += 1
        self._consecutive_gated += 1
        kf.x_post, kf.P_post = kf.x, kf.P
        if self.reinit_after_n_gated is not None and self._consecutive_gated >= self.reinit_after_n_gated:
            if self._initialise(tdoa, used, var):
                self.reinitialised = True
                self.n_reinit += 1

    def _predict(self) -> None:
        """eq. (13): ``x = F x``, ``P = F P F^T + Q``.

        The arithmetic of ``filterpy.kalman.KalmanFilter.predict`` (same ``np.dot`` calls, so
        bit-identical results) without its argument handling and its two copies of the prior:
        2.9 instead of 3.9 us at 8 microphones.
        """
        kf = self._kf
        F = self._F
        kf.x = np.dot(F, kf.x)
        kf.P = np.dot(np.dot(F, kf.P), self._FT) + self._Q
        kf.x_prior, kf.P_prior = kf.x, kf.P

    def _pair_gate(self, tdoa: np.ndarray, used: np.ndarray | None, var: np.ndarray | None):
        """Per-pair clutter gate: drop pairs whose innovation exceeds ``pair_gate_sigma`` standard
        deviations of its own predicted spread ``sqrt(H0_p P H0_p^T + R_pp)``.

        A reverberant frame often has one or two pairs locked on a reflection while the rest are
        right; eq. (17) alone would reject the whole frame. Returns ``(used, var, n_used)``.
        """
        m = self._m
        x, P = self._kf.x, self._kf.P[:m, :m]
        v = tdoa - self._H0 @ x[:m]
        r = self._tdoa_var if var is None else var
        spread = np.einsum("pi,ij,pj->p", self._H0, P, self._H0) + r
        ok = np.abs(v) <= self.pair_gate_sigma * np.sqrt(spread)
        new_used = ok if used is None else (used & ok)
        self.n_pairs_gated += int(((used if used is not None else True) & ~ok).sum())
        if var is not None:
            var = np.where(new_used, var, np.inf)
        return new_used, var, int(new_used.sum())

    def _information(self, used: np.ndarray | None, var: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Per-pair weights ``w = 1 / var`` (0 for unused pairs) and ``B = H0^T diag(w) H0``."""
        if var is None and used is None:
            return np.full(self.n_pairs, 1.0 / self._tdoa_var), self._B_all
        if var is None:
            w = used / self._tdoa_var
        else:
            w = 1.0 / var  # inf variance (unused) -> 0
        return w, (self._H0T * w) @ self._H0

    def _initialise(self, tdoa: np.ndarray, used: np.ndarray | None, var: np.ndarray | None) -> bool:
        """State ``[WLS estimate (eq. 12), 0]``; ``False`` if the used pairs leave a TOA unobservable."""
        w, B = self._information(used, var)
        if self.initial_toa_std_s is not None:
            # weak prior toa ~ N(0, initial_toa_std_s^2): devices without a usable pair yet (not
            # started, silent) start at 0 with a wide spread instead of blocking the start
            if int(np.count_nonzero(w)) < min(3, self.n_pairs):
                return False
            B = B + self._eye_m / self.initial_toa_std_s**2
        try:
            cov_pos = scipy.linalg.inv(B, check_finite=False)
            if not np.all(np.isfinite(cov_pos)) or np.linalg.cond(B) > 1e12:
                return False
        except (np.linalg.LinAlgError, ValueError):
            return False
        m = self._m
        x = np.zeros(2 * m)
        x[:m] = cov_pos @ (self._H0T @ (w * tdoa))
        if self.init_max_residual_s is not None:
            # start only from a self-consistent frame: TDOAs of all pairs must agree with one TOA
            # vector (a pair locked on a reflection breaks the triangle relations tdoa_ij = tdoa_0j - tdoa_0i)
            ok = w > 0
            resid = (tdoa - self._H0 @ x[:m])[ok]
            if resid.size and float(np.sqrt(np.mean(resid**2))) > self.init_max_residual_s:
                return False
        P = np.zeros((2 * m, 2 * m))
        P[:m, :m] = cov_pos
        P[m:, m:] = self.initial_rate_std_s_per_s**2 * self._eye_m
        kf = self._kf
        kf.x, kf.P = x, P
        kf.x_prior, kf.P_prior = x.copy(), P.copy()
        kf.x_post, kf.P_post = x.copy(), P.copy()
        self._initialised = True
        self._consecutive_gated = 0
        return True

    def _measurement_update(
        self, tdoa: np.ndarray, used: np.ndarray | None, var: np.ndarray | None, n_used: int
    ) -> bool:
        """Gate (eq. 17) then update (eq. 14) in information form; ``False`` if gated.

        With ``H = [H0, 0]``, ``W = R^-1`` (zero for unused pairs), ``B = H0^T W H0``,
        ``b = H0^T W v`` and ``P_pp`` the TOA block of ``P``, Woodbury's identity on
        ``S = H0 P_pp H0^T + R`` gives, with ``T = I + B P_pp``::

            H0^T S^-1 v  = T^-1 b                    (= g)
            H0^T S^-1 H0 = T^-1 B                    (= G)
            v^T S^-1 v   = v^T W v - b^T P_pp g
            x <- x + P[:, :m] g,   P <- P - P[:, :m] G P[:m, :]

        which is the Kalman update ``K = P H^T S^-1``, ``x += K v``, ``P -= K S K^T``.
        """
        kf = self._kf
        m = self._m
        x, P = kf.x, kf.P
        v = tdoa - self._H0 @ x[:m]
        if used is None and var is None:  # every pair at the nominal variance (the usual case)
            B = self._B_all
            wv = v * (1.0 / self._tdoa_var)  # the same products as w * v with w = 1 / var
        else:
            w, B = self._information(used, var)
            if used is not None:
                v[~used] = 0.0
            wv = w * v
        # Right-hand sides [B, b] (m, m + 1). dgesv works on its own copy of them, so B stays in
        # place between frames and only b is written while every pair is used.
        rhs = self._rhs
        if B is not self._rhs_B:
            rhs[:, :m] = B
            self._rhs_B = B if B is self._B_all else None
        b = rhs[:, m]
        np.matmul(self._H0T, wv, out=b)
        P_c = P[:, :m]
        T = B @ P[:m, :m]
        T += self._eye_m
        # Solve T [G, g] = [B, b] with LAPACK's dgesv directly: np.linalg.solve costs ~8 us of
        # Python and checks on top of the same factorisation, this ~2 us.
        _, _, sol, info = scipy.linalg.lapack.dgesv(T, rhs)
        if info != 0:
            raise np.linalg.LinAlgError(f"singular T = I + B P in the measurement update (dgesv info {info})")
        # K_all = P_c [G, g]: its last column is the state step P_c g, whose first m entries are
        # P_pp g for the gate; one product instead of three.
        K_all = P_c @ sol
        step = K_all[:, m]
        d2 = float(v @ wv - b @ step[:m])
        self.last_mahalanobis_sq = d2
        if d2 > self._gate[n_used]:
            return False
        x_new = x + step
        P_new = P - K_all[:, :m] @ P_c.T
        P_new = 0.5 * (P_new + P_new.T)
        kf.x, kf.P = x_new, P_new
        kf.x_post, kf.P_post = x_new, P_new
        return True


class FixedLagKalmanToa(KalmanToa):
    """:class:`KalmanToa` followed by a fixed-lag Rauch-Tung-Striebel smoother.

    Each :meth:`update` runs the gated filter on frame ``t`` and returns the smoothed TOA of frame
    ``t - lag_frames``, ``E[toa(t - lag) | y(1..t)]``, by an RTS backward pass over the last
    ``lag_frames`` filter steps (filterpy's ``FixedLagSmoother`` has its own ungated filter, so the
    backward pass is run here on the gated filter's stored estimates). The output is therefore
    ``latency_s = lag_frames * frame_period_s`` late. During the first ``lag_frames`` frames after
    construction or :meth:`reset`, the filtered estimate of the current frame is returned. A
    (re-)initialisation cuts the backward pass: frames before it keep their filtered estimates.

    Parameters
    ----------
    n_mics : int
        Number of microphones ``M >= 2``.
    lag_frames : int
        Smoothing lag in frames, >= 0 (0 gives the filter's output).
    **kwargs
        Keyword arguments of :class:`KalmanToa` (``frame_period_s`` is required).

    Attributes
    ----------
    filtered_toa_s : ndarray, shape (n_mics,)
        Filtered TOA of the current frame (no extra latency), in seconds.

    Notes
    -----
    Per frame: one ``2(M-1)`` solve for the smoother gain ``C = P_post F^T P_prior^-1`` of the new
    step, then ``lag_frames`` matrix-vector products
    ``x_s(k) = x(k) + C(k) (x_s(k+1) - x_prior(k+1))``.
    """

    def __init__(self, n_mics: int, *, lag_frames: int, **kwargs) -> None:
        if int(lag_frames) != lag_frames or lag_frames < 0:
            raise ValueError(f"{lag_frames=} must be an integer number of frames >= 0")
        self.lag_frames = int(lag_frames)
        self._history: collections.deque = collections.deque(maxlen=self.lag_frames + 1)
        super().__init__(n_mics, **kwargs)

    @property
    def latency_s(self) -> float:
        """Extra output latency in seconds: ``lag_frames * frame_period_s``."""
        return self.lag_frames * self.frame_period_s

    def reset(self) -> None:
        """Forget the track, the counters and the smoothing window."""
        super().reset()
        self._history.clear()
        self.filtered_toa_s = np.zeros(self.n_mics)

    def update(self, tdoa_s: np.ndarray, confidence: np.ndarray | None = None) -> np.ndarray:
        """Filter frame ``t`` and return the smoothed relative TOA of frame ``t - lag_frames``.

        Parameters
        ----------
        tdoa_s : ndarray, shape (n_pairs,), float
            Pairwise TDOAs in seconds, ``toa_i - toa_j``.
        confidence : ndarray, shape (n_pairs,), float, optional
            See :class:`KalmanToa`.

        Returns
        -------
        ndarray, shape (n_mics,), float64
            Smoothed relative TOA of frame ``t - lag_frames`` in seconds (filtered TOA of frame
            ``t`` while fewer than ``lag_frames + 1`` frames have been seen), ``toa_s[0] = 0``.
        """
        P_prev = self._kf.P.copy() if self._initialised else None
        self.filtered_toa_s = super().update(tdoa_s, confidence)
        return self._smooth(P_prev)

    def shift(self, delta_toa_s: np.ndarray, *, delta_rate_s_per_s: np.ndarray | None = None) -> None:
        """As :meth:`KalmanToa.shift`, also for the frames kept for smoothing."""
        super().shift(delta_toa_s, delta_rate_s_per_s=delta_rate_s_per_s)
        step = self._shift_step(delta_toa_s, delta_rate_s_per_s)
        self._history = type(self._history)(((x + step, xp + step, g) for x, xp, g in self._history),
                                            maxlen=self._history.maxlen)

    def predict(self) -> np.ndarray:
        """Advance one frame without a measurement; returns the smoothed TOA of frame ``t - lag``."""
        P_prev = self._kf.P.copy() if self._initialised else None
        self.filtered_toa_s = super().predict()
        return self._smooth(P_prev)

    def _smooth(self, P_prev: np.ndarray | None) -> np.ndarray:
        if not self._initialised:
            return self.filtered_toa_s.copy()
        kf = self._kf
        if P_prev is None or self.reinitialised:
            gain = None  # no link to the previous frame
        else:
            # RTS gain C(t-1) = P_post(t-1) F^T P_prior(t)^-1 (both symmetric).
            gain = np.linalg.solve(kf.P_prior, self._F @ P_prev).T
        self._history.append((kf.x.copy(), kf.x_prior.copy(), gain))
        if len(self._history) <= self.lag_frames:
            return self.filtered_toa_s.copy()
        # Backward pass t -> t - lag: x_s(k-1) = x(k-1) + C(k-1) (x_s(k) - x_prior(k)).
        hist = self._history
        x_s = hist[-1][0]
        for k in range(len(hist) - 1, 0, -1):
            _, x_prior_k, gain_k = hist[k]
            x_filt_prev = hist[k - 1][0]
            x_s = x_filt_prev if gain_k is None else x_filt_prev + gain_k @ (x_s - x_prior_k)
        return self._toa(x_s[: self._m])
