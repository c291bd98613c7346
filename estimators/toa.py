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
import warnings
from typing import Protocol

import numba
import numpy as np
import scipy.linalg
import scipy.stats
from filterpy.common import Q_continuous_white_noise
from filterpy.kalman import KalmanFilter

from .numba_tools import borrowed
from .conventions import pair_matrix

_F64 = np.dtype(np.float64)

__all__ = ["FixedLagKalmanToa", "KalmanToa", "PinvToa", "SubsetToa"]


def _check_n_mics(n_mics: int) -> int:
    if int(n_mics) != n_mics or n_mics < 2:
        raise ValueError(f"{n_mics=} must be an integer >= 2")
    return int(n_mics)


def _check_min_confidence(min_confidence: float) -> float:
    if not np.isfinite(min_confidence) or not 0.0 <= min_confidence < 1.0:
        raise ValueError(f"{min_confidence=} must be in [0, 1)")
    return float(min_confidence)


class ToaEstimator(Protocol):
    """What the stream asks of every relative-TOA estimator (the paper's three, the smoother, the tracker).

    - ``update(tdoa_s, confidence) -> toa_s``: one frame in, the relative TOA (``toa_s[0] = 0``) out;
    - ``reset()``: forget everything;
    - ``shift(delta_toa_s, *, delta_rate_s_per_s=None)``: the stream moved a device's coarse alignment
      (or its clock rate): move the held TOA (and rate) with it, so the steering stays continuous;
    - ``gated``: the last update rejected its measurement as clutter;
    - ``initialised``: a TOA is being held or tracked;
    - ``latency_frames``: the TOA returned by ``update`` is that many frames old (the fixed-lag smoother);
      the stream delays the audio it steers by as much.
    """

    gated: bool
    latency_frames: int

    @property
    def initialised(self) -> bool: ...

    def update(self, tdoa_s: np.ndarray, confidence: np.ndarray | None = None) -> np.ndarray: ...

    def reset(self) -> None: ...

    def shift(self, delta_toa_s: np.ndarray, *, delta_rate_s_per_s: np.ndarray | None = None) -> None: ...


class _PairModel:
    """Shapes, the reduced observation matrix ``H0`` and input checks shared by the estimators."""

    latency_frames = 0   # the TOA of update() is the current frame's

    def __init__(self, n_mics: int, min_confidence: float) -> None:
        self.n_mics = _check_n_mics(n_mics)
        self.n_pairs = self.n_mics * (self.n_mics - 1) // 2
        self.min_confidence = _check_min_confidence(min_confidence)
        # eq. (12): H0 is H of eq. (10) without the column of the reference microphone.
        self._H0 = pair_matrix(self.n_mics)[:, 1:]
        self._H0T = np.ascontiguousarray(self._H0.T)
        self._H0_pinv = np.linalg.pinv(self._H0)  # (H0^T H0)^-1 H0^T, shape (M-1, n_pairs)
        self._zero = np.zeros(1)

    def _as_pairs(self, tdoa_s, confidence) -> tuple[np.ndarray, np.ndarray | None]:
        """``(tdoa_s, confidence)`` as float64 arrays of shape ``(n_pairs,)`` (``None`` stays ``None``)."""
        tdoa = np.asarray(tdoa_s, dtype=np.float64)
        if tdoa.shape != (self.n_pairs,):
            raise ValueError(f"tdoa_s.shape={tdoa.shape} must be (n_pairs,)=({self.n_pairs},)")
        conf = None
        if confidence is not None:
            conf = np.asarray(confidence, dtype=np.float64)
            if conf.shape != (self.n_pairs,):
                raise ValueError(f"confidence.shape={conf.shape} must be (n_pairs,)=({self.n_pairs},)")
        return tdoa, conf

    def _inputs(self, tdoa_s, confidence) -> tuple[np.ndarray, np.ndarray | None]:
        """Validated ``(tdoa_s, used)``; ``used`` is ``None`` when every pair is usable."""
        tdoa, conf = self._as_pairs(tdoa_s, confidence)
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

    @property
    def initialised(self) -> bool:
        return True   # every microphone holds a value (0 before any)

    def shift(self, delta_toa_s: np.ndarray, *, delta_rate_s_per_s: np.ndarray | None = None) -> None:
        """Move the held values by ``delta_toa_s`` (n_mics,) seconds (there is no rate to move)."""
        self._toa_s = self._toa_s + np.asarray(delta_toa_s, float) - float(delta_toa_s[0])

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

    @property
    def initialised(self) -> bool:
        return True

    def shift(self, delta_toa_s: np.ndarray, *, delta_rate_s_per_s: np.ndarray | None = None) -> None:
        """No state is carried between frames: nothing to move."""

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


# -- compiled per-frame step of KalmanToa ----------------------------------------------------------

# Slots of KalmanToa._params, constants fixed at construction.
_P_DT = 0                  # frame period dt, s
_P_Q11 = 1                 # eq. (16) Q = [[q11 I, q12 I], [q12 I, q22 I]]: q dt^3 / 3, s^2 (TOA variance)
_P_Q12 = 2                 # q dt^2 / 2, s (TOA-rate covariance)
_P_Q22 = 3                 # q dt, (s/s)^2 (rate variance)
_P_TDOA_VAR = 4            # nominal pair variance tdoa_std_s^2, s^2
_P_MIN_CONFIDENCE = 5
_P_CONFIDENCE_WEIGHTED = 6  # 1.0 or 0.0
_P_PAIR_GATE_SIGMA = 7     # inf when off
_P_REINIT_AFTER = 8        # reinit_after_n_gated, inf when off
_P_M = 9                   # m = n_mics - 1 (the layout of the buffer array, see _kalman_views)
_P_GATE = 10               # eq. (17) thresholds chi2.ppf(gate_probability, k) for k = 0..n_pairs (k = 0: inf)

# Slots of KalmanToa._status: per-frame results and counters, written by _kalman_step (counts are
# stored as float64, exact below 2^53).
_S_INITIALISED = 0
_S_GATED = 1
_S_REINITIALISED = 2
_S_N_GATED = 3
_S_N_REINIT = 4
_S_N_PAIRS_GATED = 5
_S_N_PAIRS_USED = 6
_S_MAHALANOBIS_SQ = 7
_S_CONSECUTIVE_GATED = 8
_N_STATUS = 9

# Return codes of _kalman_step.
_DONE = 0
_INITIALISE = 1            # (re-)initialise from the used pairs left in work[:2 n_pairs]
_BAD_TDOA_SHAPE = 2
_BAD_CONFIDENCE_SHAPE = 3
_SINGULAR = 4


def _work_size(m: int) -> int:
    """Length of the float64 work buffer of :func:`_kalman_step` for ``m = n_mics - 1``."""
    n_pairs = m * (m + 1) // 2
    # y, w (n_pairs each); b (m); B (m x m); B P_prior[:m] (m x 2m); [T, B, b] (m x (2m + 1));
    # [G, g] (m x (m + 1)); K^T ((m + 1) x 2m); the covariance correction (2m x 2m)
    return 2 * n_pairs + m + m * m + 2 * m * m + m * (2 * m + 1) + m * (m + 1) + 2 * m * (m + 1) + 4 * m * m


@numba.njit(cache=True, nogil=True)
def _predict(x, P, x_prior, P_prior, dt, q11, q12, q22):
    """eq. (13) with the blocks of eq. (16): ``x_prior = F x``, ``P_prior = F P F^T + Q``.

    With ``F = [[I, dt I], [0, I]]`` and ``P = [[A, C], [C^T, D]]`` (``m x m`` blocks)::

        F P F^T = [[A + dt (C + C^T) + dt^2 D,  C + dt D],
                   [C^T + dt D,                 D       ]]

    O(m^2) instead of two dense ``2m x 2m`` products. Each element's expression is symmetric in
    its two indices, so a symmetric ``P`` gives an exactly symmetric ``P_prior``.
    """
    m = x.shape[0] // 2
    dt2 = dt * dt
    for a in range(m):
        x_prior[a] = x[a] + dt * x[m + a]
        x_prior[m + a] = x[m + a]
    for a in range(m):
        for c in range(m):
            P_prior[a, c] = P[a, c] + dt * (P[m + a, c] + P[a, m + c]) + dt2 * P[m + a, m + c]
            P_prior[a, m + c] = P[a, m + c] + dt * P[m + a, m + c]
            P_prior[m + a, c] = P[m + a, c] + dt * P[m + a, m + c]
            P_prior[m + a, m + c] = P[m + a, m + c]
        P_prior[a, a] += q11
        P_prior[a, m + a] += q12
        P_prior[m + a, a] += q12
        P_prior[m + a, m + a] += q22


@numba.njit(cache=True, nogil=True)
def _copy_prior(x, P, x_prior, P_prior):
    """``x, P = x_prior, P_prior`` (prediction only), element by element."""
    n = x.shape[0]
    for a in range(n):
        x[a] = x_prior[a]
        for c in range(n):
            P[a, c] = P_prior[a, c]


@numba.njit(cache=True, nogil=True)
def _pair_gate(y, w, x_prior, P_prior, sigma, status):
    """Per-pair gate: drop pair ``p = (i, j)`` (``w_p = 0``) when
    ``|y_p - (x_i - x_j)| > sigma sqrt(P_ii + P_jj - 2 P_ij + 1 / w_p)`` (TOA block of the prior,
    index ``k`` of microphone ``k + 1``, terms of microphone 0 absent). Returns the pairs left."""
    m = x_prior.shape[0] // 2
    n_used = 0
    p = 0
    for i in range(m + 1):
        for j in range(i + 1, m + 1):
            if w[p] != 0.0:
                jj = j - 1
                pred = -x_prior[jj]
                spread = P_prior[jj, jj]
                if i > 0:
                    ii = i - 1
                    pred += x_prior[ii]
                    spread += P_prior[ii, ii] - 2.0 * P_prior[ii, jj]
                spread += 1.0 / w[p]
                if abs(y[p] - pred) <= sigma * math.sqrt(spread):
                    n_used += 1
                else:
                    w[p] = 0.0
                    status[_S_N_PAIRS_GATED] += 1.0
            p += 1
    return n_used


@numba.njit(cache=True, nogil=True)
def _information_update(y, w, x, P, x_prior, P_prior, gate, status, work):
    """Gate (eq. 17) and measurement update (eq. 14) in information form.

    With ``W = diag(w)``, ``v = y - H0 x_prior[:m]`` and ``P_pp`` the TOA block of ``P_prior``:
    ``B = H0^T W H0`` (the weighted graph Laplacian of the pairs without row and column 0),
    ``b = H0^T W v``, ``T = I + B P_pp``; Gaussian elimination with partial pivoting solves
    ``T [G, g] = [B, b]``, then ``K = P_prior[:, :m] [G, g]`` and::

        d2 = v^T W v - b^T K[:m, m]               (= v^T S^-1 v, eq. 17)
        x  = x_prior + K[:, m]                    (= x_prior + P H^T S^-1 v)
        P  = P_prior - K[:, :m] P_prior[:m, :]    (= P_prior - P H^T S^-1 H P)

    ``P`` symmetrised. ``P_prior`` is symmetric, so ``P_prior[:m, :]`` (contiguous rows) stands for
    ``P_prior[:, :m]^T`` and the products are BLAS calls on contiguous blocks. Returns 1
    (updated), 0 (gated: ``x``, ``P`` untouched) or -1 (``T`` singular). Writes ``d2`` to the status.
    """
    m = x.shape[0] // 2
    n_pairs = y.shape[0]
    ncol = 2 * m + 1
    off = 2 * n_pairs
    b = work[off:off + m]
    off += m
    B = work[off:off + m * m].reshape((m, m))
    off += m * m
    BP = work[off:off + 2 * m * m].reshape((m, 2 * m))  # B P_prior[:m, :]
    off += 2 * m * m
    A = work[off:off + m * ncol].reshape((m, ncol))  # [T, B, b], eliminated in place
    off += m * ncol
    X = work[off:off + m * (m + 1)].reshape((m, m + 1))  # [G, g]
    off += m * (m + 1)
    KT = work[off:off + 2 * m * (m + 1)].reshape((m + 1, 2 * m))  # (P_prior[:, :m] [G, g])^T
    off += 2 * m * (m + 1)
    C = work[off:off + 4 * m * m].reshape((2 * m, 2 * m))  # K[:, :m] P_prior[:m, :]
    for a in range(m):
        B[a, a] = 0.0
        b[a] = 0.0
    # B and b from the pairs: pair (i, j) has H0 row e_i - e_j (column i - 1; microphone 0 has
    # none), so it adds w_p to B[i-1, i-1] and B[j-1, j-1] and is alone at B[i-1, j-1] = -w_p
    vwv = 0.0
    p = 0
    for i in range(m + 1):
        xi = x_prior[i - 1] if i > 0 else 0.0
        for j in range(i + 1, m + 1):
            wp = w[p]
            jj = j - 1
            if i > 0:
                B[i - 1, jj] = -wp
                B[jj, i - 1] = -wp
            if wp != 0.0:
                v = y[p] - (xi - x_prior[jj])
                wv = wp * v
                vwv += v * wv
                B[jj, jj] += wp
                b[jj] -= wv
                if i > 0:
                    B[i - 1, i - 1] += wp
                    b[i - 1] += wv
            p += 1
    # T = I + B P_pp
    np.dot(B, P_prior[:m], BP)
    for a in range(m):
        for c in range(m):
            A[a, c] = BP[a, c]
            A[a, m + c] = B[a, c]
        A[a, a] += 1.0
        A[a, 2 * m] = b[a]
    # forward elimination with partial pivoting on [T, B, b]
    for k in range(m):
        piv = k
        big = abs(A[k, k])
        for r in range(k + 1, m):
            val = abs(A[r, k])
            if val > big:
                big = val
                piv = r
        if big == 0.0:
            return -1
        if piv != k:
            for c in range(k, ncol):
                tmp = A[k, c]
                A[k, c] = A[piv, c]
                A[piv, c] = tmp
        inv = 1.0 / A[k, k]
        for r in range(k + 1, m):
            f = A[r, k] * inv
            if f != 0.0:
                for c in range(k + 1, ncol):
                    A[r, c] -= f * A[k, c]
    # back substitution into X = [G, g]
    for k in range(m - 1, -1, -1):
        for c in range(m + 1):
            X[k, c] = A[k, m + c]
        for r in range(k + 1, m):
            f = A[k, r]
            if f != 0.0:
                for c in range(m + 1):
                    X[k, c] -= f * X[r, c]
        d = A[k, k]
        for c in range(m + 1):
            X[k, c] /= d
    np.dot(X.T, P_prior[:m], KT)
    d2 = vwv
    for a in range(m):
        d2 -= b[a] * KT[m, a]
    status[_S_MAHALANOBIS_SQ] = d2
    if d2 > gate:
        return 0
    for a in range(2 * m):
        x[a] = x_prior[a] + KT[m, a]
    np.dot(KT[:m].T, P_prior[:m], C)
    for a in range(2 * m):
        for c in range(a + 1):
            P[a, c] = P[c, a] = P_prior[a, c] - 0.5 * (C[a, c] + C[c, a])
    return 1


def _buffer_size(m: int) -> int:
    """Length of the float64 array that holds every buffer of :func:`_kalman_step` (:func:`_kalman_views`)."""
    return _N_STATUS + 2 * (2 * m + 4 * m * m) + m + 1 + _work_size(m)


@numba.njit(cache=True, nogil=True)
def _kalman_views(buffers, m):
    """The buffers of :class:`KalmanToa` as views of its one float64 array (one argument of the
    compiled call instead of eight; each costs ~40 ns to unbox): ``status`` (_N_STATUS,), ``x``,
    ``x_prior`` (2m,), ``P``, ``P_prior`` (2m, 2m), ``toa_out`` (m + 1,) and the rest, ``work``."""
    n = 2 * m
    status = buffers[:_N_STATUS]
    o = _N_STATUS
    x = buffers[o : o + n]
    x_prior = buffers[o + n : o + 2 * n]
    o += 2 * n
    P = buffers[o : o + n * n].reshape((n, n))
    P_prior = buffers[o + n * n : o + 2 * n * n].reshape((n, n))
    o += 2 * n * n
    toa_out = buffers[o : o + m + 1]
    work = buffers[o + m + 1 :]
    return status, x, x_prior, P, P_prior, toa_out, work


_RO_PAIRS = numba.types.Array(numba.types.float64, 1, "A", readonly=True)  # any float64 (n_pairs,) input
_VEC = numba.types.float64[::1]


@numba.njit(cache=True, nogil=True)
def _step(tdoa, confidence, x, P, x_prior, P_prior, params, status, toa_out, work):
    """One frame of :class:`KalmanToa`: used pairs, predict (eq. 13), gate (eq. 17), update (eq. 14).

    A pair is used when its TDOA is finite and ``confidence_p > min_confidence`` (NaN excluded);
    its weight is ``w_p = 1 / tdoa_var``, or ``confidence_p / tdoa_var`` when confidence-weighted,
    and 0 when unused. ``y`` (TDOAs, 0 when unused) and ``w`` are left in ``work[:2 n_pairs]`` for
    a (re-)initialisation. Not yet initialised: only that. Initialised: :func:`_predict`; with no
    used pair ``x, P = x_prior, P_prior``; else the optional :func:`_pair_gate`, then
    :func:`_information_update`, or ``x, P = x_prior, P_prior`` when gated. Writes the counters to
    ``status`` and ``[0, x[:m]]`` to ``toa_out``.

    Returns
    -------
    int
        ``_DONE``; ``_INITIALISE`` when the caller must try to (re-)initialise (not initialised
        with a used pair, or ``reinit_after_n_gated`` consecutive gated frames);
        ``_BAD_TDOA_SHAPE`` / ``_BAD_CONFIDENCE_SHAPE`` (nothing changed); ``_SINGULAR``.
    """
    m = x.shape[0] // 2
    n_pairs = m * (m + 1) // 2
    if tdoa.shape[0] != n_pairs:
        return _BAD_TDOA_SHAPE
    if confidence.shape[0] != n_pairs:
        return _BAD_CONFIDENCE_SHAPE
    status[_S_GATED] = 0.0
    status[_S_REINITIALISED] = 0.0
    status[_S_MAHALANOBIS_SQ] = np.nan
    y = work[:n_pairs]
    w = work[n_pairs:2 * n_pairs]
    tdoa_var = params[_P_TDOA_VAR]
    min_confidence = params[_P_MIN_CONFIDENCE]
    weighted = params[_P_CONFIDENCE_WEIGHTED] != 0.0
    w_nominal = 1.0 / tdoa_var
    n_used = 0
    for p in range(n_pairs):
        t = tdoa[p]
        c = confidence[p]
        if math.isfinite(t) and c > min_confidence:  # NaN confidence compares False: excluded
            y[p] = t
            w[p] = c / tdoa_var if weighted else w_nominal
            n_used += 1
        else:
            y[p] = 0.0
            w[p] = 0.0
    status[_S_N_PAIRS_USED] = n_used
    code = _DONE
    if status[_S_INITIALISED] == 0.0:
        if n_used > 0:
            code = _INITIALISE
    else:
        _predict(x, P, x_prior, P_prior, params[_P_DT], params[_P_Q11], params[_P_Q12], params[_P_Q22])
        updated = 0
        if n_used > 0:
            if params[_P_PAIR_GATE_SIGMA] < math.inf:
                n_used = _pair_gate(y, w, x_prior, P_prior, params[_P_PAIR_GATE_SIGMA], status)
            if n_used > 0:
                updated = _information_update(y, w, x, P, x_prior, P_prior, params[_P_GATE + n_used],
                                              status, work)
        if updated == 1:
            status[_S_CONSECUTIVE_GATED] = 0.0
        else:  # prediction only
            _copy_prior(x, P, x_prior, P_prior)
            if updated == -1:
                code = _SINGULAR
            elif status[_S_N_PAIRS_USED] > 0.0:  # gated (eq. 17, or every pair by the pair gate)
                status[_S_GATED] = 1.0
                status[_S_N_GATED] += 1.0
                status[_S_CONSECUTIVE_GATED] += 1.0
                if status[_S_CONSECUTIVE_GATED] >= params[_P_REINIT_AFTER]:
                    code = _INITIALISE
    toa_out[0] = 0.0
    for a in range(m):
        toa_out[a + 1] = x[a]
    return code


@numba.njit(numba.types.int64(_RO_PAIRS, _RO_PAIRS, _VEC, _VEC), cache=True, nogil=True)
def _kalman_step(tdoa, confidence, buffers, params):
    """:func:`_step` on the buffers of :func:`_kalman_views`."""
    # borrowed (estimators.numba_tools): no reference-count updates for the views and calls below
    tdoa, confidence, buffers, params = borrowed(tdoa), borrowed(confidence), borrowed(buffers), borrowed(params)
    status, x, x_prior, P, P_prior, toa_out, work = _kalman_views(buffers, int(params[_P_M]))
    return _step(tdoa, confidence, x, P, x_prior, P_prior, params, status, toa_out, work)


def _status_attribute(slot: int, kind: type, doc: str) -> property:
    """Public attribute kept in ``KalmanToa._status[slot]``, where the compiled step writes it."""

    def get(self):
        return kind(self._status[slot])

    def set_(self, value) -> None:
        self._status[slot] = value

    return property(get, set_, doc=doc)


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
    n_pairs_gated : int
        Pairs left out by the per-pair gate (``pair_gate_sigma``) since construction or :meth:`reset`.
    last_mahalanobis_sq : float
        ``v^T S^-1 v`` of the last measurement (NaN when none was evaluated).

    Notes
    -----
    Initialisation (paper, end of section III-C): the first usable measurement whose pairs connect
    every microphone gives the state ``[pinv estimate, 0]`` with covariance
    ``blockdiag((H0^T R^-1 H0)^-1, initial_rate_std**2 I)``; until then :meth:`update` returns zeros.

    Each :meth:`update` (and :meth:`predict`) is one compiled call, :func:`_kalman_step`: pair
    selection, prediction (eq. 13 with the block structure of ``F`` and ``Q``, O(M^2)), clutter gate
    and measurement update. The update is written in information form: filterpy's generic update
    inverts the ``n_pairs x n_pairs`` matrix ``S`` (120 x 120 at 16 microphones) and the gate would
    need ``S`` once more before deciding; since ``H = [H0, 0]`` and ``R`` is diagonal, the same
    posterior and Mahalanobis distance follow from one ``(M-1) x (M-1)`` solve (see
    :func:`_information_update`). The test suite checks both steps against
    ``filterpy.kalman.KalmanFilter``. The filterpy object ``_kf`` holds the state: the step writes
    ``x``, ``P``, ``x_prior`` and ``P_prior`` in place (``x_post`` and ``P_post`` are the same arrays
    as ``x`` and ``P``), so copy them to keep them. (Re-)initialisation runs in numpy.
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
        # eq. (17) gate: chi-square quantile for k = 0..n_pairs used pairs.
        if gate_probability is None:
            gate = np.full(self.n_pairs + 1, np.inf)
        else:
            gate = np.concatenate([[np.inf], scipy.stats.chi2.ppf(gate_probability, np.arange(1, self.n_pairs + 1))])
        params = np.empty(_P_GATE + self.n_pairs + 1)
        params[_P_DT] = dt
        params[_P_Q11], params[_P_Q12], params[_P_Q22] = self._Q[0, 0], self._Q[0, m], self._Q[m, m]
        params[_P_TDOA_VAR] = self._tdoa_var
        params[_P_MIN_CONFIDENCE] = self.min_confidence
        params[_P_CONFIDENCE_WEIGHTED] = float(self.confidence_weighted)
        params[_P_PAIR_GATE_SIGMA] = np.inf if pair_gate_sigma is None else pair_gate_sigma
        params[_P_REINIT_AFTER] = np.inf if reinit_after_n_gated is None else self.reinit_after_n_gated
        params[_P_M] = m
        params[_P_GATE:] = gate
        self._params = params
        self._buffers = np.zeros(_buffer_size(m))  # every buffer of the compiled step (_kalman_views)
        self._ones = np.ones(self.n_pairs)  # the confidence when none is given: every finite pair, weight 1 / var
        self._no_pairs = np.full(self.n_pairs, np.nan)  # the TDOAs of predict(): no usable pair
        self._eye_m = np.eye(m)
        self._kf = KalmanFilter(dim_x=2 * m, dim_z=self.n_pairs)
        self._kf.F = self._F
        self._kf.Q = self._Q
        self._kf.H = np.hstack([self._H0, np.zeros((self.n_pairs, m))])  # eq. (14)
        self._kf.R = self._tdoa_var * np.eye(self.n_pairs)
        self._bind_buffers()
        self.reset()

    def _bind_buffers(self) -> None:
        """Point the filter's arrays at their views of ``self._buffers``, which every step writes in
        place (``x_post`` and ``P_post`` are ``x`` and ``P``; ``_toa_out`` is ``[0, x[:m]]`` of the
        last step)."""
        kf = self._kf
        # Sliced by numpy (py_func): the views then carry numpy's own float64 dtype object, which the
        # stages' input checks compare by identity.
        self._status, kf.x, kf.x_prior, kf.P, kf.P_prior, self._toa_out, self._work = _kalman_views.py_func(
            self._buffers, self._m)
        kf.x_post = kf.x
        kf.P_post = kf.P

    def __setstate__(self, state: dict) -> None:
        # copy.deepcopy and pickle copy each view of _buffers as an array of its own: re-attach them.
        self.__dict__.update(state)
        self._bind_buffers()

    # -- public interface ------------------------------------------------------------------------

    gated = _status_attribute(_S_GATED, bool, "The last measurement was rejected by the gate.")
    reinitialised = _status_attribute(
        _S_REINITIALISED, bool, "The last update (re-)initialised the state from the measurement.")
    n_gated = _status_attribute(_S_N_GATED, int, "Gated frames since construction or reset().")
    n_reinit = _status_attribute(_S_N_REINIT, int, "Re-initialisations since construction or reset().")
    n_pairs_gated = _status_attribute(
        _S_N_PAIRS_GATED, int, "Pairs left out by the per-pair gate since construction or reset().")
    n_pairs_used = _status_attribute(_S_N_PAIRS_USED, int, "Pairs used by the last update.")
    last_mahalanobis_sq = _status_attribute(
        _S_MAHALANOBIS_SQ, float, "v^T S^-1 v of the last measurement (NaN when none was evaluated).")
    _consecutive_gated = _status_attribute(_S_CONSECUTIVE_GATED, int, "Gated frames in a row.")

    @property
    def latency_s(self) -> float:
        """Extra output latency in seconds (0 for the filter)."""
        return self.latency_frames * self.frame_period_s

    @property
    def initialised(self) -> bool:
        """Whether the state has been initialised from a measurement."""
        return bool(self._status[_S_INITIALISED])

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
        kf = self._kf
        kf.x[:] = 0.0
        kf.P[:] = 0.0
        np.fill_diagonal(kf.P, 1.0)
        kf.x_prior[:] = kf.x
        kf.P_prior[:] = kf.P
        self._status[:] = 0.0
        self._status[_S_MAHALANOBIS_SQ] = np.nan
        self._toa_out[:] = 0.0

    def shift(self, delta_toa_s: np.ndarray, *, delta_rate_s_per_s: np.ndarray | None = None) -> None:
        """Move the tracked TOA by ``delta_toa_s`` (n_mics,) seconds, and optionally its rate by
        ``delta_rate_s_per_s`` (n_mics,), keeping the covariance.

        Used when the stream re-aligns a device by a whole number of samples (the fine TOA jumps by
        a known amount) or corrects a device's clock drift (its TOA rate changes by a known
        amount): a known change must not look like clutter.
        """
        step = self._shift_step(delta_toa_s, delta_rate_s_per_s)
        kf = self._kf
        kf.x += step  # also x_post: the same buffer
        kf.x_prior += step

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
        conf = self._ones if confidence is None else confidence
        # The step is compiled for 1-D float64 arrays of any layout; anything else (lists, float32)
        # is converted first, here rather than by a failed call (numba takes ~70 us to word its
        # TypeError). The step checks the lengths.
        try:
            usual = tdoa_s.dtype is _F64 and conf.dtype is _F64
        except AttributeError:  # not arrays
            usual = False
        if usual:
            try:
                code = _kalman_step(tdoa_s, conf, self._buffers, self._params)
            except TypeError:  # the usual dtype with other dimensions
                usual = False
        if not usual:
            tdoa, conf = self._as_pairs(tdoa_s, confidence)  # raises on the wrong shape
            code = _kalman_step(tdoa, self._ones if conf is None else conf, self._buffers, self._params)
        if code:
            self._finish_step(code, tdoa_s, confidence)
        return self._toa_out.copy()

    def predict(self) -> np.ndarray:
        """Advance one frame without a measurement (e.g. no speech); returns the predicted TOA."""
        _kalman_step(self._no_pairs, self._ones, self._buffers, self._params)
        return self._toa_out.copy()

    # -- internals -------------------------------------------------------------------------------

    def _finish_step(self, code: int, tdoa_s, confidence) -> None:
        """The rare outcomes of :func:`_kalman_step`: (re-)initialisation and errors."""
        if code == _INITIALISE:
            status = self._status
            first = not status[_S_INITIALISED]
            if self._initialise():
                status[_S_REINITIALISED] = 1.0
                if not first:
                    status[_S_N_REINIT] += 1.0
        elif code == _SINGULAR:
            raise np.linalg.LinAlgError("singular T = I + B P in the measurement update")
        else:
            self._as_pairs(tdoa_s, confidence)  # raises the ValueError naming the bad shape
            raise AssertionError(f"unexpected return code {code} of _kalman_step")

    def _initialise(self) -> bool:
        """State ``[WLS estimate (eq. 12), 0]`` from the pairs of the last frame (``y`` and ``w``
        left in the work buffer by :func:`_kalman_step`); ``False`` if they leave a TOA unobservable.
        """
        n, m = self.n_pairs, self._m
        tdoa, w = self._work[:n], self._work[n:2 * n]
        B = (self._H0T * w) @ self._H0  # eq. (12) information H0^T W H0
        if self.initial_toa_std_s is not None:
            # weak prior toa ~ N(0, initial_toa_std_s^2): devices without a usable pair yet (not
            # started, silent) start at 0 with a wide spread instead of blocking the start
            if int(np.count_nonzero(w)) < min(3, n):
                return False
            B = B + self._eye_m / self.initial_toa_std_s**2
        try:
            with warnings.catch_warnings():   # an ill-conditioned B is refused just below, not warned about
                warnings.simplefilter("ignore", scipy.linalg.LinAlgWarning)
                cov_pos = scipy.linalg.inv(B, check_finite=False)
            if not np.all(np.isfinite(cov_pos)) or np.linalg.cond(B) > 1e12:
                return False
        except (np.linalg.LinAlgError, ValueError):
            return False
        toa0 = cov_pos @ (self._H0T @ (w * tdoa))
        if self.init_max_residual_s is not None:
            # start only from a self-consistent frame: TDOAs of all pairs must agree with one TOA
            # vector (a pair locked on a reflection breaks the triangle relations tdoa_ij = tdoa_0j - tdoa_0i)
            ok = w > 0
            resid = (tdoa - self._H0 @ toa0)[ok]
            if resid.size and float(np.sqrt(np.mean(resid**2))) > self.init_max_residual_s:
                return False
        kf = self._kf
        kf.x[:m] = toa0
        kf.x[m:] = 0.0
        kf.P[:] = 0.0
        kf.P[:m, :m] = 0.5 * (cov_pos + cov_pos.T)  # exactly symmetric: the compiled step relies on it
        kf.P[m:, m:] = self.initial_rate_std_s_per_s**2 * self._eye_m
        kf.x_prior[:] = kf.x
        kf.P_prior[:] = kf.P
        self._status[_S_INITIALISED] = 1.0
        self._status[_S_CONSECUTIVE_GATED] = 0.0
        self._toa_out[1:] = toa0
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
    def latency_frames(self) -> int:
        """The TOA of :meth:`update` is this many frames old (the stream delays the audio it steers by as
        much)."""
        return self.lag_frames

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
        P_prev = self._kf.P.copy() if self.initialised else None
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
        P_prev = self._kf.P.copy() if self.initialised else None
        self.filtered_toa_s = super().predict()
        return self._smooth(P_prev)

    def _smooth(self, P_prev: np.ndarray | None) -> np.ndarray:
        if not self.initialised:
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
