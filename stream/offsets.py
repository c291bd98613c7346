"""Coarse offsets between devices (envelope correlation, then PHAT at sample resolution), and the process
that computes the stream's periodic re-checks of them.

A re-check correlates seconds of audio of every device with the reference's (tens of ms of numpy and FFTs at
48 kHz). In a thread of the stream's own process it shares the GIL with the stream loop: every numpy call of
the loop that releases the GIL (any array op over 500 elements) can then wait up to a switch interval for the
worker to hand it back, and a hop that takes 1 ms took 5-10 ms (measured: 7 device frames of 5-6 ms each while
a re-check ran, an output underflow at 48 kHz, JACK period 1024). So a re-check runs in a child process,
``python -m stream.offsets`` (numpy and scipy only, started with the stream), fed through its stdin: a JSON
header line, then the float32 samples; it answers one JSON line. The thread that waits for it only blocks on
the pipe (the GIL released). If the process cannot start or dies, the re-checks run in that thread, as
before, and the log says so once.

This module imports nothing but numpy and scipy (the child stays small: about 0.9 s and 100 MB to start).
"""
from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import scipy.fft
import scipy.signal

log = logging.getLogger(__name__)

JOINT_SEARCH_S = 0.05       # a joint refinement moves a device's pairwise offset by at most this
JOINT_MIN_MOVE_S = 0.008    # ... and is taken only when it moves one by more than this (a gross pairwise error)
SILENCE_RMS = 1e-7          # a block quieter than this (about -140 dBFS) is digital silence
FULL_OVERLAP_SHARE = 0.75   # an envelope overlap this long (of the shorter window) counts in full


def energy_envelope(x: np.ndarray, *, sample_rate_hz: float, hop_s: float = 0.01) -> np.ndarray:
    """Log-energy envelope of a signal, zero mean and unit variance.

    Parameters
    ----------
    x : ndarray, shape (n_samples,), float
    sample_rate_hz : float
    hop_s : float
        Envelope resolution in seconds.

    Returns
    -------
    ndarray, shape (n_samples // hop,), float64
    """
    hop = max(1, int(round(hop_s * sample_rate_hz)))
    n = len(x) // hop
    if n == 0:
        return np.zeros(0)
    e = np.log10(np.mean(np.square(x[: n * hop].reshape(n, hop), dtype=np.float64), axis=1) + 1e-12)
    # the floor is taken over the frames that hold sound: digital silence (a card started before the room made
    # a sound, a stream's end) would pull it down, and its step to the first sound would then out-correlate
    # the sound itself
    sound = e > np.log10(SILENCE_RMS ** 2 + 1e-12) + 0.5
    floor = np.percentile(e[sound] if sound.any() else e, 10) + 0.6
    e = np.maximum(e, floor)  # ignore the noise floor (and 6 dB above it): only what rises above it aligns
    e -= e.mean()
    std = e.std()
    return e / std if std > 0 else e


def normalised_xcorr(e: np.ndarray, e_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pearson correlation of ``e[n + lag]`` with ``e_ref[n]`` over their overlap, for every lag.

    Returns
    -------
    (score, lags) : ndarray, shape (len(e) + len(e_ref) - 1,)
    """
    n_e, n_r = len(e), len(e_ref)
    s_xy = scipy.signal.correlate(e, e_ref, mode="full", method="fft")
    lags = scipy.signal.correlation_lags(n_e, n_r, mode="full")
    lo_r = np.maximum(0, -lags)                 # overlap in e_ref: [lo_r, hi_r)
    hi_r = np.minimum(n_r, n_e - lags)
    n = np.clip(hi_r - lo_r, 1, None).astype(float)
    c_r, c_r2 = np.r_[0, np.cumsum(e_ref)], np.r_[0, np.cumsum(e_ref ** 2)]
    c_e, c_e2 = np.r_[0, np.cumsum(e)], np.r_[0, np.cumsum(e ** 2)]
    s_r, s_r2 = c_r[hi_r] - c_r[lo_r], c_r2[hi_r] - c_r2[lo_r]
    s_e, s_e2 = c_e[hi_r + lags] - c_e[lo_r + lags], c_e2[hi_r + lags] - c_e2[lo_r + lags]
    cov = s_xy - s_e * s_r / n
    var = np.clip(s_e2 - s_e ** 2 / n, 0, None) * np.clip(s_r2 - s_r ** 2 / n, 0, None)
    score = np.where(var > 1e-12, cov / np.sqrt(np.maximum(var, 1e-300)), 0.0)
    return score, lags


def envelope_offset(x_ref: np.ndarray, x: np.ndarray, *, sample_rate_hz: float, max_offset_s: float,
                    envelope_hop_s: float = 0.01) -> tuple[int, float] | None:
    """The envelope step of :func:`coarse_offset`: the lag (samples, in steps of ``envelope_hop_s``) and the
    quality of the best energy-envelope correlation, or None when there is nothing to correlate."""
    hop = max(1, int(round(envelope_hop_s * sample_rate_hz)))
    e_ref = energy_envelope(x_ref, sample_rate_hz=sample_rate_hz, hop_s=envelope_hop_s)
    e = energy_envelope(x, sample_rate_hz=sample_rate_hz, hop_s=envelope_hop_s)
    if len(e_ref) < 4 or len(e) < 4 or not e_ref.any() or not e.any():
        return None
    score, lags = normalised_xcorr(e, e_ref)
    max_lag = int(max_offset_s / envelope_hop_s)
    overlap = np.minimum(len(e_ref), len(e) - lags) - np.maximum(0, -lags)
    min_overlap = max(4, int(0.25 * min(len(e), len(e_ref))))
    ok = (np.abs(lags) <= max_lag) & (overlap >= min_overlap)
    if not ok.any():
        return None
    # rank by correlation times the square root of the overlap share (full weight from FULL_OVERLAP_SHARE on),
    # so that a short overlap that happens to correlate does not beat the long one of the true offset, while
    # among long overlaps the best correlation wins (a repeated sentence correlates at the repetition's lag too)
    share = np.minimum(overlap / (FULL_OVERLAP_SHARE * min(len(e), len(e_ref))), 1.0)
    rank = np.where(ok, score * np.sqrt(share), -np.inf)
    k = int(np.argmax(rank))
    return int(lags[k]) * hop, float(np.clip(score[k], 0.0, 1.0))


def coarse_offset(x_ref: np.ndarray, x: np.ndarray, *, sample_rate_hz: float, max_offset_s: float,
                  envelope_hop_s: float = 0.01, refine_s: float = 0.05) -> tuple[int, float]:
    """Offset of ``x`` relative to ``x_ref`` in samples, and a quality in [0, 1].

    ``x[n + offset]`` lines up with ``x_ref[n]``. The quality is the normalised envelope correlation
    at the chosen lag (about 0 for unrelated signals, up to 1).
    """
    found = envelope_offset(x_ref, x, sample_rate_hz=sample_rate_hz, max_offset_s=max_offset_s,
                            envelope_hop_s=envelope_hop_s)
    if found is None:
        return 0, 0.0
    coarse, quality = found
    # refine at sample resolution: PHAT cross-correlation of the waveforms around the envelope lag
    fine = refine_offset(x_ref, x, coarse_samples=coarse, search_samples=int(refine_s * sample_rate_hz))
    return fine, quality


def _phat_xcorr(a_spectrum: np.ndarray, b_spectrum: np.ndarray, n_fft: int) -> np.ndarray:
    """Circular PHAT cross-correlation of two signals from their rfft spectra (length ``n_fft``): peaks at lag
    ``d`` (index ``d mod n_fft``) when ``b[m + d] = a[m]``."""
    g = b_spectrum * np.conj(a_spectrum)
    g /= np.abs(g) + 1e-12
    return scipy.fft.irfft(g, n_fft)


def refine_offset(x_ref: np.ndarray, x: np.ndarray, *, coarse_samples: int, search_samples: int) -> int:
    """Sample-accurate offset near ``coarse_samples`` by PHAT-weighted cross-correlation."""
    start_ref = max(0, -coarse_samples)
    start = start_ref + coarse_samples
    n = min(len(x_ref) - start_ref, len(x) - start)
    if n <= 2 * search_samples:
        return coarse_samples
    a = x_ref[start_ref:start_ref + n].astype(np.float32)
    b = x[start:start + n].astype(np.float32)
    n_fft = scipy.fft.next_fast_len(n + search_samples)
    r = _phat_xcorr(scipy.fft.rfft(a, n_fft), scipy.fft.rfft(b, n_fft), n_fft)
    lags = np.r_[np.arange(0, search_samples + 1), np.arange(-search_samples, 0)]
    vals = np.r_[r[: search_samples + 1], r[n_fft - search_samples:]]
    # if x[n + coarse + d] = x_ref[n] then b[m + d] = a[m]: the correlation peaks at lag d
    return coarse_samples + int(lags[int(np.argmax(vals))])


def joint_refine(ref: np.ndarray, windows: dict[int, tuple[np.ndarray, int]], *, sample_rate_hz: float,
                 search_s: float = 0.05, min_move_s: float = 0.0, max_sweeps: int = 8) -> dict[int, int]:
    """Offsets of several devices refined together, from the PHAT correlations of every pair.

    ``windows[d] = (x, offset)``: device ``d``'s samples and its offset against ``ref`` as :func:`coarse_offset`
    found it pairwise (``x[n + offset]`` lines up with ``ref[n]``). Against the reference alone, a pair's
    whole-window PHAT peak can sit on a reflection (of the noise, say) or on nothing in particular: measured on
    52 generated rooms, single devices landed 10-24 ms off the talker and off the noise in 6 of them. A wrong
    pairwise lag does not agree with the other pairs, so every device's lag (the reference's too) is moved, by
    coordinate ascent from the pairwise answers, to where it maximises the sum of the PHAT correlations of all its
    pairs at the lags the offsets imply, within ``search_s`` of the pairwise answer. The search runs on the band
    below 2 kHz (correlations at a quarter-millisecond step: cheap, and enough to tell a gross error); each device
    is then placed at the sample where its correlation with the reference peaks, within that step. Returns
    ``{d: offset}`` against ``ref`` for every device of ``windows`` (the reference's own move folded in), or the
    pairwise offsets unchanged if the search moves none by more than ``min_move_s``."""
    devices = list(windows)
    offs = {d: int(o) for d, (_, o) in windows.items()}
    if not devices:
        return offs
    q = max(1, int(sample_rate_hz // 4000))   # decimation of the search's correlations
    L = int(search_s * sample_rate_hz) // q * q
    # the common stretch of every device's window at its pairwise offset, 2L inside each edge
    lo = max([0] + [-o for o in offs.values()]) + 2 * L
    hi = min([len(ref)] + [len(x) - offs[d] for d, (x, _) in windows.items()]) - 2 * L
    n = hi - lo
    if n < 8 * L or n < 1024:
        return offs
    ys = [ref[lo:hi]] + [windows[d][0][lo + offs[d]:hi + offs[d]] for d in devices]
    m = len(ys)
    n_dec = scipy.fft.next_fast_len(-(-(n + 2 * L) // q), real=True)
    n_fft = n_dec * q
    k_dec = n_dec // 2 + 1
    spectra = [scipy.fft.rfft(np.asarray(y, np.float32), n_fft) for y in ys]
    Ld = L // q
    # corr[i][j][l + 2Ld] for |l| <= 2Ld (steps of q samples): y_j[k + q l] lines up with y_i[k] at its peak
    corr = [[None] * m for _ in range(m)]
    for i in range(m):
        for j in range(i + 1, m):
            r = _phat_xcorr(spectra[i][:k_dec], spectra[j][:k_dec], n_dec)
            corr[i][j] = np.r_[r[n_dec - 2 * Ld:], r[:2 * Ld + 1]]
            corr[j][i] = corr[i][j][::-1]
    delta = np.zeros(m, np.int64)   # each window's move from its pairwise offset, in steps (reference: index 0)
    grid = np.arange(-Ld, Ld + 1)
    for _ in range(max_sweeps):
        moved = False
        for d in range(m):
            score = np.zeros(len(grid))
            for j in range(m):
                if j != d:
                    score += corr[j][d][grid - delta[j] + 2 * Ld]   # pair (j, d) peaks at delta_d - delta_j
            best = int(grid[int(np.argmax(score))])
            if best != delta[d]:
                delta[d], moved = best, True
        if not moved:
            break
    moves = q * (delta[1:] - delta[0])
    if not np.any(np.abs(moves) > min_move_s * sample_rate_hz):
        return offs
    out = {}
    for k, d in enumerate(devices):
        lag = int(moves[k])
        if q > 1:   # the sample, within a step, where the full-band correlation with the reference peaks
            r = _phat_xcorr(spectra[0], spectra[k + 1], n_fft)
            near = np.arange(lag - q + 1, lag + q)
            lag = int(near[int(np.argmax(r[near % n_fft]))])
        out[d] = offs[d] + lag
    return out


def silent_share(x: np.ndarray, sample_rate_hz: float) -> float:
    """Share of the 10 ms frames of ``x`` that are digital silence (RMS below ``SILENCE_RMS``)."""
    hop = max(1, int(0.01 * sample_rate_hz))
    n = len(x) // hop
    if n == 0:
        return 1.0
    ms = np.mean(np.square(x[:n * hop].reshape(n, hop), dtype=np.float64), axis=1)
    return float(np.mean(ms < SILENCE_RMS ** 2))


def joint_offsets(ref: np.ndarray, windows: dict[int, tuple[np.ndarray, int, float]], *, sample_rate_hz: float,
                  min_quality: float) -> dict[int, int]:
    """The pairwise offsets of ``windows[d] = (x, offset, quality)``, or all of them refined together
    (:func:`joint_refine`, over the devices with ``quality >= min_quality``) when that moves one of them by more
    than ``JOINT_MIN_MOVE_S``: the fine tracker searches +-12 ms around the coarse offsets and settles smaller
    disagreements itself, pair by pair; a larger one is a pairwise peak on a late reflection or on nothing."""
    clear = {d: (x, o) for d, (x, o, q) in windows.items() if q >= min_quality}
    out = {d: o for d, (_, o, _) in windows.items()}
    if len(clear) < 2:
        return out
    out.update(joint_refine(ref, clear, sample_rate_hz=sample_rate_hz, search_s=JOINT_SEARCH_S,
                            min_move_s=JOINT_MIN_MOVE_S))
    return out


def recheck_offsets(ref: np.ndarray, segments: dict[int, np.ndarray], *, sample_rate_hz: float,
                    max_offset_s: float, max_silent_share: float = 1.0) -> dict[int, tuple[int, float]]:
    """``{device: (offset change in samples, quality)}`` of each segment against the reference's; none if the
    reference's window has more digital silence than ``max_silent_share`` (:func:`silent_share`), and not the
    segments that have. Pairwise: a joint check here (:func:`joint_offsets`) moved the reference against all
    the others in one of the 52 generated rooms (`s21`, -4.8 dB: every track restarts) and helped none."""
    if max_silent_share < 1.0 and silent_share(ref, sample_rate_hz) > max_silent_share:
        return {}
    return {d: coarse_offset(ref, x, sample_rate_hz=sample_rate_hz, max_offset_s=max_offset_s)
            for d, x in segments.items()
            if max_silent_share >= 1.0 or silent_share(x, sample_rate_hz) <= max_silent_share}


# the worker process ------------------------------------------------------------------------------
class OffsetWorker:
    """The child process that computes re-checks (:func:`recheck_offsets`), and its client.

    :meth:`compute` is called from one thread at a time (the aligner's re-check thread) and blocks on the
    pipe until the answer is there. ``cpu_s``: the child's CPU time spent on requests so far (for the
    report's CPU share: the stream's work, wherever it runs).
    """

    def __init__(self) -> None:
        self._proc: subprocess.Popen | None = None
        self._lock = threading.Lock()
        self.cpu_s = 0.0
        self.failed: str | None = None

    def start(self) -> None:
        """Start the child if it is not running (returns at once: it imports while the stream starts)."""
        with self._lock:
            self._start()

    def _start(self) -> None:
        if self.failed is not None or (self._proc is not None and self._proc.poll() is None):
            return
        if self._proc is not None:
            log.info("The offset re-check process ended (%s); starting it again.", _stderr_tail(self._proc))
        root = str(Path(__file__).resolve().parents[1])
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p))
        try:
            self._proc = subprocess.Popen([sys.executable, "-m", "stream.offsets"], stdin=subprocess.PIPE,
                                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
        except OSError as err:
            self._fail(f"it could not start ({err})")

    def _fail(self, why: str) -> None:
        self.failed = why
        log.warning("The process that re-checks the devices' offsets failed: %s; the re-checks run in a thread "
                    "of the stream's process from now on (they may then delay a hop).", why)
        if self._proc is not None:
            self._proc.kill()
            self._proc = None

    def compute(self, ref: np.ndarray, segments: dict[int, np.ndarray], *, sample_rate_hz: float,
                max_offset_s: float, max_silent_share: float = 1.0) -> dict[int, tuple[int, float]]:
        """:func:`recheck_offsets` in the child (in this thread if the child failed)."""
        with self._lock:
            self._start()
            proc = self._proc
            if proc is not None:
                arrays = [np.ascontiguousarray(ref, "<f4")] + [np.ascontiguousarray(x, "<f4") for x in segments.values()]
                head = {"sample_rate_hz": float(sample_rate_hz), "max_offset_s": float(max_offset_s),
                        "max_silent_share": float(max_silent_share),
                        "n_ref": len(arrays[0]), "segments": [[int(d), len(x)] for d, x in zip(segments, arrays[1:])]}
                try:
                    proc.stdin.write(json.dumps(head).encode() + b"\n")
                    for a in arrays:
                        proc.stdin.write(memoryview(a).cast("B"))
                    proc.stdin.flush()
                    line = proc.stdout.readline()
                    if not line:
                        raise OSError(f"it ended ({_stderr_tail(proc)})")
                    answer = json.loads(line)
                    if "error" in answer:
                        raise OSError(answer["error"])
                    self.cpu_s = float(answer["cpu_s"])
                    return {int(d): (int(o), float(q)) for d, (o, q) in answer["offsets"].items()}
                except (OSError, ValueError, KeyError) as err:
                    self._fail(str(err))
        return recheck_offsets(ref, segments, sample_rate_hz=sample_rate_hz, max_offset_s=max_offset_s,
                               max_silent_share=max_silent_share)

    def close(self) -> None:
        with self._lock:
            if self._proc is not None:
                try:
                    self._proc.stdin.close()
                    self._proc.wait(2.0)
                except (OSError, subprocess.TimeoutExpired):
                    self._proc.kill()
                self._proc = None


def _stderr_tail(proc: subprocess.Popen) -> str:
    try:
        proc.wait(1.0)
        lines = proc.stderr.read().decode(errors="replace").strip().splitlines()
    except (OSError, subprocess.TimeoutExpired):
        return "no exit status"
    return f"exit status {proc.returncode}" + (f": {lines[-1]}" if lines else "")


_WORKER: OffsetWorker | None = None


def worker() -> OffsetWorker:
    """The process-wide re-check worker (started by the first aligner that re-checks, stopped at exit)."""
    global _WORKER
    if _WORKER is None:
        import atexit
        _WORKER = OffsetWorker()
        atexit.register(_WORKER.close)
    return _WORKER


def worker_cpu_s() -> float:
    """CPU seconds the re-check process has spent on requests (0 if none ran)."""
    return _WORKER.cpu_s if _WORKER is not None else 0.0


def _serve(stdin, stdout) -> int:
    """The child: answer requests until stdin ends."""
    cpu0 = time.process_time()
    while True:
        line = stdin.readline()
        if not line:
            return 0
        try:
            head = json.loads(line)
            ref = np.frombuffer(stdin.read(4 * head["n_ref"]), "<f4")
            segments = {int(d): np.frombuffer(stdin.read(4 * n), "<f4") for d, n in head["segments"]}
            if len(ref) != head["n_ref"] or any(len(x) != n for x, (_, n) in zip(segments.values(), head["segments"])):
                raise ValueError("the request was cut short")
            out = recheck_offsets(ref, segments, sample_rate_hz=head["sample_rate_hz"],
                                  max_offset_s=head["max_offset_s"], max_silent_share=head["max_silent_share"])
            answer = {"offsets": {str(d): [o, q] for d, (o, q) in out.items()}, "cpu_s": time.process_time() - cpu0}
        except Exception as err:  # noqa: BLE001 - one sentence to the client, which falls back
            answer = {"error": f"{type(err).__name__}: {err}"}
        stdout.write(json.dumps(answer).encode() + b"\n")
        stdout.flush()


if __name__ == "__main__":
    sys.exit(_serve(sys.stdin.buffer, sys.stdout.buffer))
