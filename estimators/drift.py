"""Clock drift from the rotation of the pairs' cross-power spectra (a tracker-free estimate).

Every static source (talker, noise, their reflections) of a pair (i, j) shows in the long-time cross-power
spectrum ``C(f) = sum_s |S_s(f)|^2 exp(-2 pi j f tau_s)`` at its TDOA ``tau_s = toa_i - toa_j``. Clock drift moves
every ``tau_s`` of the pair alike: by ``(r_i - r_j) T`` over ``T`` seconds. So the PHAT-weighted product of two
blocks' spectra, ``C_k(f) C_l(f)^*``, is a cross spectrum with a single peak at the shift drift made between them,
whichever sources sound (each source's term with itself keeps its phase; the terms between two sources at other
TDOAs do not add up over frequency). Each block is compared with the ``lag_blocks`` blocks before it (a longer gap
measures the rate more finely); a block's time is each pair's energy centroid (speech and clatter come and go
within a block, and its phase is that of its loud parts: with the block's middle, 8 `s17` and `s31` of the
generated scenes read 75-80 % of their drift). The rates of the last ``memory_blocks`` blocks are combined per
pair by a weighted median (robust to a block where a source moved or changed), then by least squares over the
pairs into each device's relative TOA rate ``r_d`` (``r_0 = 0``).

Units: seconds, seconds per second; pair order as :func:`estimators.conventions.pairs`.
"""
from __future__ import annotations

import numpy as np

from .conventions import delay_phasors, pair_matrix, pairs

__all__ = ["DriftMeter"]


class DriftMeter:
    """Relative TOA rates of the devices from the pairs' cross-power spectra.

    Parameters
    ----------
    n_devices : int
        Devices (channels) of the spectra, at least 2.
    n_fft : int
        FFT length of the spectra (bins ``n_fft // 2 + 1``).
    sample_rate_hz : float
        Sample rate of the spectra.
    block_s : float
        Length of one block of the long-time cross-power sum (seconds).
    max_rate_s_per_s : float
        Largest relative TOA rate searched (two clocks at +-100 ppm, and a margin).
    band_hz : (float, float)
        The bins used (speech and most noise; not the lowest bins, where a room's modes sit).
    memory_blocks : int
        Blocks whose comparisons enter the weighted median.
    grid_step_s : float
        Step of the grid of shifts searched (the peak is then interpolated; a 200-4000 Hz band gives a main lobe
        of about 250 us).
    lag_blocks : int
        Each block is compared with this many blocks before it.

    Attributes
    ----------
    rate_s_per_s : ndarray, shape (n_devices,), or None
        The measured rates (``[0] = 0``), None before two blocks; a new array after each block.
    """

    def __init__(self, n_devices: int, *, n_fft: int, sample_rate_hz: float, block_s: float = 1.0,
                 max_rate_s_per_s: float = 2.5e-4, band_hz: tuple[float, float] = (200.0, 4000.0),
                 memory_blocks: int = 30, grid_step_s: float = 1e-5, lag_blocks: int = 3) -> None:
        if n_devices < 2:
            raise ValueError(f"{n_devices=} must be at least 2")
        self.n_devices = int(n_devices)
        self.block_s = float(block_s)
        self.max_rate_s_per_s = float(max_rate_s_per_s)
        self.memory_blocks = int(memory_blocks)
        self.lag_blocks = int(lag_blocks)
        f = np.arange(n_fft // 2 + 1) * (sample_rate_hz / n_fft)
        band = np.flatnonzero((f >= band_hz[0]) & (f <= band_hz[1]))
        self._band = slice(int(band[0]), int(band[-1]) + 1)   # a view of the spectra, not a copy
        self._f = f[self._band]
        # per gap of 1..lag_blocks blocks, the shifts drift can make in it (and half a block of margin: a block's
        # time is its energy centroid), so that the nearer blocks are not searched over the farther ones' span
        self._grids, self._steers = [], []
        for lag in range(1, self.lag_blocks + 1):
            span = max_rate_s_per_s * block_s * (lag + 0.5)
            grid = np.arange(-span, span + grid_step_s / 2, grid_step_s)
            self._grids.append(grid)
            self._steers.append(np.exp(2j * np.pi * np.outer(self._f, grid)).astype(np.complex64))
        self._pairs = pairs(self.n_devices)
        self._H0 = pair_matrix(self.n_devices)[:, 1:]
        self._acc = None     # this block: the cross-power sum (n_pairs, band), its weights and weighted times
        self._acc_w = self._acc_tw = None
        self._acc_t = 0.0
        self._history = []   # the last lag_blocks blocks: (spectra (n_pairs, band), centroid time per pair)
        self._est = []       # per comparison: (rate per pair (n_pairs,), weight per pair (n_pairs,))
        self.rate_s_per_s = None

    def add(self, cross: np.ndarray, time_s: float, dt_s: float) -> None:
        """One sample of the pairs' (short-time averaged) cross-power spectra ``cross`` (n_pairs, n_bins),
        taken at ``time_s``, standing for ``dt_s`` seconds of the stream."""
        c = cross[:, self._band]
        if self._acc is None:
            self._acc = np.zeros(c.shape, c.dtype)
            self._acc_w = np.zeros(c.shape[0])
            self._acc_tw = np.zeros(c.shape[0])
        self._acc += c
        w = np.abs(c).sum(axis=1)
        self._acc_w += w
        self._acc_tw += w * time_s
        self._acc_t += dt_s
        if self._acc_t >= self.block_s:
            self._close()

    def shift(self, delta_toa_s: np.ndarray) -> None:
        """The channels were moved by a known change of their TOAs (a re-alignment, seconds, (n_devices,)):
        the blocks so far are turned with them, so the jump is not read as drift."""
        chan = delay_phasors(delta_toa_s, 2.0 * np.pi * self._f)
        rot = chan[self._pairs[:, 0]] * np.conj(chan[self._pairs[:, 1]])
        if self._acc is not None:
            self._acc *= rot
        for block, _ in self._history:
            block *= rot

    def _close(self) -> None:
        cur = self._acc
        t = self._acc_tw / np.maximum(self._acc_w, 1e-30)
        self._acc, self._acc_t = None, 0.0
        r = np.arange(cur.shape[0])
        for lag, (prev, t_prev) in zip(range(len(self._history), 0, -1), self._history):
            grid = self._grids[lag - 1]
            step = grid[1] - grid[0]
            gap = t - t_prev
            p = cur * np.conj(prev)
            p /= np.maximum(np.abs(p), 1e-30)
            corr = (p @ self._steers[lag - 1]).real / p.shape[1]   # (n_pairs, grid)
            k = np.clip(np.argmax(corr, axis=1), 1, len(grid) - 2)
            y0, y1, y2 = corr[r, k - 1], corr[r, k], corr[r, k + 1]
            den = y0 - 2 * y1 + y2
            frac = np.where(den < 0, 0.5 * (y0 - y2) / np.where(den < 0, den, -1.0), 0.0)
            ok = gap > 0.25 * self.block_s
            rate = (grid[k] + frac * step) / np.where(ok, gap, 1.0)
            # a longer gap measures the rate more finely (a block's time is its energy centroid, known to a
            # fraction of the block): weighted by it
            self._est.append((rate, np.where(ok, np.maximum(y1, 0.0) * gap, 0.0)))
        if self._history:
            self._est = self._est[-self.memory_blocks * self.lag_blocks:]
            self._solve()
        self._history.append((cur, t))
        self._history = self._history[-self.lag_blocks:]

    def _solve(self) -> None:
        rates = np.array([e[0] for e in self._est])    # (estimates, pairs), s/s
        weights = np.array([e[1] for e in self._est])
        med = np.empty(rates.shape[1])
        for p in range(rates.shape[1]):
            o = np.argsort(rates[:, p])
            c = np.cumsum(weights[o, p])
            med[p] = rates[o[np.searchsorted(c, 0.5 * c[-1])], p] if c[-1] > 0 else 0.0
        w = np.sqrt(weights.sum(axis=0))
        sol, *_ = np.linalg.lstsq(self._H0 * w[:, None], med * w, rcond=None)
        out = np.zeros(self.n_devices)
        out[1:] = np.clip(sol, -self.max_rate_s_per_s, self.max_rate_s_per_s)
        self.rate_s_per_s = out
