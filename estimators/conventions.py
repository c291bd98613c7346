"""Conventions shared by the whole engine, fixed once here.

Units and shapes
----------------
- Time in seconds (``_s``), sample counts in samples (``_samples``), rates in hertz (``_hz``),
  positions in metres (``_m``), clock drift in parts per million (``_ppm``).
- Audio is time-major: ``(n_samples, n_channels)``.
- Positions are ``(n_mics, 3)`` in metres.

Delays
------
- ``toa[i]`` is the time of arrival of one wavefront at device ``i`` read on device ``i``'s own
  clock. Relative TOA subtracts device 0: ``toa[0] = 0``. A positive ``toa[i]`` means device ``i``
  hears the wavefront later than device 0 (propagation plus clock offset).
- ``tdoa[i, j] = toa[i] - toa[j]``.
- Pairs are ordered ``(0,1), (0,2), ..., (0,M-1), (1,2), ..., (M-2,M-1)`` (see :func:`pairs`), and
  the TDOA vector ``y[p] = toa[i] - toa[j]`` for pair ``p = (i, j)``, so ``y = H @ toa`` with
  :func:`pair_matrix` (TOA paper eqs. 9-10).
- A beamformer aligns channel ``i`` to device 0 by advancing it by ``toa[i]``:
  ``y(t) = sum_i w_i x_i(t + toa[i])``, i.e. ``X_i(w) exp(+i w toa[i])`` (TOA paper eqs. 7-8).
"""
from __future__ import annotations

import numpy as np

SPEED_OF_SOUND_M_S = 343.0


def pairs(n_mics: int) -> np.ndarray:
    """All microphone pairs in the engine's order.

    Parameters
    ----------
    n_mics : int
        Number of microphones (devices), ``M >= 2``.

    Returns
    -------
    ndarray, shape (M*(M-1)/2, 2), int
        Rows ``(i, j)`` with ``i < j`` in the order ``(0,1),(0,2),...,(M-2,M-1)``.
    """
    if int(n_mics) != n_mics or n_mics < 2:
        raise ValueError(f"{n_mics=} must be an integer >= 2")
    i, j = np.triu_indices(int(n_mics), k=1)
    return np.stack([i, j], axis=1).astype(np.intp)


def pair_matrix(n_mics: int) -> np.ndarray:
    """Observation matrix ``H`` with ``tdoa = H @ toa`` (TOA paper eq. 10, rows ``e_i - e_j``).

    Returns
    -------
    ndarray, shape (n_pairs, n_mics), float64
    """
    p = pairs(n_mics)
    H = np.zeros((len(p), n_mics))
    H[np.arange(len(p)), p[:, 0]] = 1.0
    H[np.arange(len(p)), p[:, 1]] = -1.0
    return H


def samples_to_s(n_samples, *, sample_rate_hz: float):
    """Convert samples to seconds: ``t_s = n_samples / sample_rate_hz``."""
    return np.asarray(n_samples) / float(sample_rate_hz)


def s_to_samples(t_s, *, sample_rate_hz: float):
    """Convert seconds to (fractional) samples: ``n_samples = t_s * sample_rate_hz``."""
    return np.asarray(t_s) * float(sample_rate_hz)


def ppm_to_ratio(drift_ppm):
    """Clock drift to rate ratio: ``actual_rate / nominal_rate = 1 + drift_ppm * 1e-6``."""
    return 1.0 + np.asarray(drift_ppm) * 1e-6


def delay_phasors(delta_toa_s: np.ndarray, omega_rad_s: np.ndarray) -> np.ndarray:
    """``exp(-i omega delta)`` per channel and bin: what moving each channel later by ``delta_toa_s`` does to its
    spectrum, complex64, shape (n_channels, n_bins).

    The phase is reduced modulo ``2 pi`` in float64 before float32 ``cos``/``sin`` (an aligner's move of a
    second is thousands of turns at 4 kHz), so the error stays below 1e-6 rad for any delay. A pair's rotation of
    its cross power ``X_i X_j^*`` is ``p[i] * conj(p[j])``."""
    phase = np.outer(np.asarray(delta_toa_s, np.float64), omega_rad_s)
    phase -= (2.0 * np.pi) * np.round(phase / (2.0 * np.pi))
    phase = phase.astype(np.float32)
    out = np.cos(phase).astype(np.complex64)
    out.imag = -np.sin(phase)
    return out
