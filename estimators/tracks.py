"""Several sources at once: a bank of relative-TOA tracks with data association, birth, death and labels.

The TOA paper tracks one source with one Kalman filter (:class:`estimators.KalmanToa`). In a room with a
persistent noise source, or with several talkers taking turns, that one filter follows whatever is loudest:
in a speech pause it re-initialises on the noise. :class:`SourceTracker` keeps a small bank of tracks instead,
each a :class:`~estimators.KalmanToa` (Wiener-velocity model, clutter gate of eq. 17), fed per frame with the
N best GCC-PHAT peaks of every pair (:class:`estimators.multipeak.NoiseAwareGcc`):

- **Association** (speech frames only): each track, most active first (the steered one has no priority: a
  side lobe steered by mistake must not take the peaks it shares with its talker), takes per pair the unused peak
  nearest its predicted TDOA ``H0 (toa + dt rate)`` within a gate of three predicted standard deviations
  (at least ``gate_min_s``, at most ``gate_max_s``); the track updates with the pairs it took (the others
  are left out, confidence 0). A *hit* is an update that used at least ``min_pair_fraction`` of the usable
  pairs and was not gated as clutter. A pair where a noise source found in the pauses (below) is predicted within
  ``noise_near_s`` of a talker track's prediction is left out of that track's update (``n_pairs_near_noise`` in
  the report): there the noise's peak merges with the talker's into one lobe or sits beside it, and the nearest
  peak may be the noise's, a bias of a sample or two that holds as long as the sources do.
  With ``unpinned_s`` (off by default: measured, docs/tracking-log.md), a device of a track that no matched pair has
  measured for that long (speech frames) goes on at its clock drift rate (the track's average over the hits that
  measured it), not at a rate nothing measures.
- **Birth** (speech frames only): from the peaks no track took, the highest of every pair, a robust
  least-squares TOA fit (eq. 12; pairs off by more than ``birth_max_residual_s`` dropped, then refitted)
  whose kept pairs are self-consistent, cover at least ``min_pair_fraction`` of the usable pairs and
  connect every usable device, starts a *tentative* track. It is *confirmed* after ``confirm_hits`` hits
  within ``confirm_window_s`` and deleted otherwise.
- **Noise sources**: every ``noise_every_s`` the PHAT-weighted noise cross-power spectra (tracked on
  non-speech frames by :class:`~estimators.multipeak.NoiseAwareGcc`) give the delays of the persistent noise
  sources; each consistent fit updates (or starts) a track labelled ``"noise"``. A source heard *alone* is
  found sooner: on non-speech frames past a talker's tail a tentative noise track is born from the plain PHAT
  peaks (as a talker's on speech frames) and confirmed ``"noise"`` when it is hit in ``quiet_confirm_share`` of
  the non-speech frames of its first ``quiet_confirm_s`` (a speech frame before that ends it: a talker's onset,
  heard before the detector fires, is far shorter); such a track follows its peaks on non-speech frames, and in
  speech frames it takes its source's peaks after the talkers, so that no talker track is born on them though
  the detector calls every frame speech while it sounds (a dish clatter fires Silero); there its gate stays
  capped however young it is (an open gate took the talker's peaks at the first word). It turns talker only
  once the pauses are quiet of it, or when over its first speech hits its peaks are ``louder_ratio`` times higher
  in speech frames than in the pauses and it is hit in most speech frames (over ``LOUDER_MIN_HITS`` hits; over
  ``LOUDER_EARLY_HITS``, whatever its hit rate, where they are ``LOUDER_EARLY_RATIO`` times higher): a talker
  heard before the first word (the room or the breath of the recording); a noise source is masked by the talker
  instead (``n_talkers_from_pauses`` in the report). The noise spectra correct it when they agree on all devices but one
  (a single pause's peaks may put one device on a reflection). A talker track within ``NOISE_SAME_S`` of it on
  every device, or on every device but one (at least four agreeing, up to a common shift: born on the noise's
  peaks where its gate missed them, one device on another peak), is that noise source, and goes; unless the
  talker's peaks are ``LOUDER_EARLY_RATIO`` times the noise track's in the pauses and the noise track was born
  after somebody spoke: then it is the talker's own sound in the pauses, and the noise track goes.
- **Labels**: a track is ``"speech"`` when it was born and confirmed on speech frames; it becomes ``"noise"``
  when its activity does not follow speech presence: on non-speech frames (plain PHAT peaks) every track is
  checked, without an update, for its peaks (from 0.3 s after the last speech frame on, past a talker's
  reverberant tail); when they are there in more than ``noise_quiet_activity`` of
  the non-speech frames and more often than the track has hits on speech frames (both exponential averages
  over 1 s), the source keeps sounding when nobody speaks.
  A noise track that starts having hits on speech frames (a talker whose breath, or the room of the recording,
  was heard before the first word) turns talker within about half a second (its hit rate on speech frames is
  averaged over ``activity_time_constant_s``, a talker's over 1 s); one heard in the pauses for ``PAUSE_FIRST_S``
  before its first hit on a speech frame, or found on the pauses' own peaks, only once the pauses are quiet of it.
  In the pauses a peak that such a noise source takes does not count for a talker track on the pairs where the two
  are more than ``NOISE_SAME_S`` apart (a talker beside the noise). Noise tracks are never steered at.
- **Re-anchoring** (the steered track): one device locked on a reflection or a side lobe while the others are
  right shows up as every pair of that device peaking at one other TOA for it; the peaks' votes (decaying over
  about half a second of speech frames) move that device there when they outweigh staying ``REANCHOR_RATIO``
  to one (``n_reanchored`` in the report). A peak where a confirmed noise track is predicted in its pair does
  not vote for a move (``anchor_noise_s``): a noise heard in speech frames (a dish clatter) must not carry the
  beam onto itself one device at a time. The reference device (device 0, the origin of every TOA and of the
  output's time) is not moved while it is heard poorly (:meth:`SourceTracker.reference_heard_poorly`): its pairs'
  peaks are then not the talker's, and its move would shift every other device's steering and the output with it.
- **Take-over** (``"active-talker"``): a talker track confirmed within ``TAKEOVER_S`` (every device) of the
  steered track is the steered talker where it is now (a walking talker outruns a track's capped gate); the
  steered track takes its state and the beam follows at once (``n_taken_over`` in the report).
- **Ghosts**: two talker tracks hit in the same speech frames (over the last half second) are one talker; the
  weaker of the two in those frames (matched peak heights summed over the pairs) is a side lobe of its voice
  (GCC-PHAT of voiced speech peaks again near multiples of the pitch period) or a reflection, and is removed
  (``death_reason`` "a ghost of track N"); no track is born again at its TOA for ``GHOST_MEMORY_S``.
- **Death**: a speech track without a hit for ``forget_after_s``, or a noise track not seen in the noise
  spectra for ``forget_after_s``; when the bank is full the least recently hit track that is not steered goes.
  Two tracks of the same kind closer than ``same_source_s`` are merged (the younger goes; when the younger is
  steered, it stays and takes the older one's filter state).
- **Steering** (``target``): ``"active-talker"`` steers at the speech track with the highest activity (an
  exponential average over speech frames, time constant ``activity_time_constant_s``, of the matched peak
  heights of its hits summed over the pairs and divided by the usable pairs: a track that explains few pairs
  scores low) and switches when another's activity exceeds the steered one's by ``switch_ratio`` and that
  track is heard now (a hit within the last ``QUIET_S`` of speech frames). A turn is taken faster: once the
  steered talker has had no hit for ``QUIET_S`` of speech frames, the beam moves to the talker track hit in this
  frame whose activity over the last ``FAST_ACTIVITY_S`` exceeds the steered one's by ``switch_ratio``;
  ``"nearest"`` steers at the speech track heard earliest by device ``target_device`` relative to the mean
  of all devices (clock offsets cancel between tracks), among tracks with a hit in the last
  ``forget_after_s``. With no confirmed speech track nothing is steered (the caller outputs the average of the
  devices at their coarse alignment, or the reference device where a noise track sits there).

On non-speech frames every talker track only predicts: no talker update and no talker birth comes from a frame
without speech (only noise sources, above).
Units: seconds throughout; TOA vectors relative to device 0 (``toa[0] = 0``), as :mod:`estimators.conventions`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numba
import numpy as np

from .conventions import pair_matrix, pairs
from .toa import KalmanToa

__all__ = ["SourceTracker", "Track", "TrackKind", "TargetPolicy", "within_but_one"]

TrackKind = Literal["tentative", "speech", "noise"]
GHOST_MEMORY_S = 3.0              # a removed ghost is not born again at the same TOA for this long
REANCHOR_RATIO = 2.0              # votes for moving one device of the steered track against staying
MAX_DRIFT_RATE_S_PER_S = 2.5e-4   # relative TOA rate two clocks at +-100 ppm (and some margin) can give
TargetPolicy = Literal["active-talker", "nearest"]
NOISE_SAME_S = 2.5e-4            # a talker track this close to a noise source found in the pauses (every device) is it
TAKEOVER_S = 1e-3                 # a new talker track this close to the steered one (every device) is its talker
QUIET_S = 0.048                   # the steered talker unheard for this long (speech frames): another may take the turn
FAST_ACTIVITY_S = 0.1             # ... the one most active over about this long (speech frames)
LOUDER_MIN_HITS = 15              # hits in speech frames and in the pauses before ``louder_ratio`` is applied,
LOUDER_MAX_HITS = 50              # ... and in speech frames after which it is not (a talker's first second)
LOUDER_EARLY_HITS = 4             # ... but this many speech hits are enough where the peaks are this many times
LOUDER_EARLY_RATIO = 2.0          # higher than in the pauses
HEIGHT_S = 2.0                    # time constant of a talker track's per-device matched peak heights (its hits)
HEIGHT_FLOOR = 0.02               # ... heights below this count as this in the beam's weights
REFERENCE_SHARE_MIN = 0.7         # the reference device in fewer of the steered track's hits is heard poorly ...
REFERENCE_MIN_HITS = 60           # ... judged after this many hits (about 1 s of speech at the default 16 ms)
UNSTEERED_SHARE_MAX = 0.35        # speech with no talker steered in more than this share of the speech frames ...
UNSTEERED_MIN_S = 1.0             # ... and for at least this long is said (unsteered_speech)
NOISE_KNOWN_S = 0.5               # a noise track this old may make the output the reference device (noise_at)
PAUSE_FIRST_S = 0.5               # a noise track heard this long in the pauses before its first hit on a speech
#                                   frame is a noise source first (:attr:`Track.pause_first`)


def within_but_one(err_s: np.ndarray, within_s: float) -> np.ndarray:
    """Per row of ``err_s`` ((n_frames, n_devices) or one vector: differences of two relative TOA vectors, device
    0's at 0), whether every device is within ``within_s`` (the every-device test ``max |err| <= within_s``), or,
    from five devices on, every device but one agrees as that test asks (a spread of ``2 within_s``), the odd one
    device 0 included (the others then agree up to a common shift). A source with one device on another peak (a
    reflection, a lobe of another source) is still that source: the tracker's twin rule for noise sources, and
    ``benchmarks/scenes.py``'s ``noise_steer_but_one_s``. Seed 8's `s08`: eight talker tracks on the dishes, six
    of seven devices within 0.5 ms of the noise track."""
    err_s = np.atleast_2d(err_s)
    if err_s.shape[1] < 5:
        return np.max(np.abs(err_s), axis=1) <= within_s
    d = np.sort(err_s, axis=1)   # the spread without one device is least without the lowest or the highest
    return np.minimum(d[:, -1] - d[:, 1], d[:, -2] - d[:, 0]) <= 2 * within_s


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _anchor_vote(votes, peak_tdoa, peak_value, pred, pair_ok, pair_idx, decay, inv_bin_s, min_peak, gate_bins,
                 ratio, min_votes, noise_lag, noise_tol):
    """One frame of :meth:`SourceTracker._reanchor`'s votes, compiled (numpy's per-call overhead was most of its
    cost). ``votes`` (M, bins, centre bin = no move) decays by ``decay`` and takes the frame's peaks: a peak of
    pair (i, j) at ``pred + d`` votes, with its height, for moving device i by ``d`` and device j by ``-d``; not
    for a move when it lies within ``noise_tol`` of a noise source's TDOA in that pair (``noise_lag`` (pairs, K),
    NaN for none): that peak is the noise's (a vote for staying still counts).
    Returns (device, bin) of the move with the most votes among the devices whose best three neighbouring bins
    centred beyond ``gate_bins`` of the centre have more than ``ratio`` times the votes of the three centre bins
    and more than ``min_votes`` (the move goes to the highest of the three); (-1, -1) when no device qualifies."""
    n_dev, n_bins = votes.shape
    c = n_bins // 2
    for i in range(n_dev):
        for b in range(n_bins):
            votes[i, b] *= decay
    for p in range(peak_tdoa.shape[0]):
        if not pair_ok[p]:
            continue
        i, j = pair_idx[p, 0], pair_idx[p, 1]
        for k in range(peak_tdoa.shape[1]):
            w = peak_value[p, k]
            if not w >= min_peak:
                continue
            b = int(np.rint((peak_tdoa[p, k] - pred[p]) * inv_bin_s))
            if abs(b) > 1:
                noise = False
                for q in range(noise_lag.shape[1]):
                    noise |= abs(peak_tdoa[p, k] - noise_lag[p, q]) < noise_tol
                if noise:
                    continue
            votes[i, min(max(c + b, 0), n_bins - 1)] += w
            votes[j, min(max(c - b, 0), n_bins - 1)] += w
    dev, dev_bin, dev_votes = -1, -1, -1.0
    for i in range(n_dev):
        # staying and moving are both judged on three bins: one TOA's peaks fall in two neighbouring bins as often
        # as in one, and a move judged on its single best bin needed about twice the ratio staying needed
        stay = votes[i, c - 1] + votes[i, c] + votes[i, c + 1]
        best, v = 0, 0.0
        for lo, hi in ((1, c - gate_bins), (c + gate_bins + 1, n_bins - 1)):   # windows centred beyond the gate
            for b in range(lo, hi):
                w3 = votes[i, b - 1] + votes[i, b] + votes[i, b + 1]
                if w3 > v:
                    best, v = b, w3
        if v > ratio * stay and v > min_votes and v > dev_votes:
            top = best   # the move goes to the window's highest bin
            if votes[i, best - 1] > votes[i, top]:
                top = best - 1
            if votes[i, best + 1] > votes[i, top]:
                top = best + 1
            dev, dev_bin, dev_votes = i, top, v
    return dev, dev_bin


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _note_heights(height, conf, pair_ok, pair_idx, beta, total, count):
    """One hit of a talker track into ``height`` (M,): per device, the mean of ``conf`` (the matched peak heights,
    0 where a pair took none) over its pairs with ``pair_ok``; NaN entries (never measured) take it as it is, the
    others move by ``beta`` towards it; a device with no usable pair keeps its value. ``total``, ``count``: (M,)
    work arrays."""
    total[:] = 0.0
    count[:] = 0.0
    for q in range(conf.shape[0]):
        if pair_ok[q]:
            for d in (pair_idx[q, 0], pair_idx[q, 1]):
                total[d] += conf[q]
                count[d] += 1.0
    for d in range(height.shape[0]):
        if count[d] > 0.0:
            h = total[d] / count[d]
            height[d] = h if np.isnan(height[d]) else height[d] + beta * (h - height[d])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _height_factors(height, exponent, floor, out):
    """``out[d] = exponent * log(max(height[d], floor) / max(median, floor))`` over the measured (finite) heights;
    0 for a device never measured. Returns False (``out`` untouched) when none is."""
    seen = height[np.isfinite(height)]
    if seen.shape[0] == 0:
        return False
    med = max(np.median(seen), floor)
    for d in range(height.shape[0]):
        out[d] = exponent * math.log(max(height[d], floor) / med) if np.isfinite(height[d]) else 0.0
    return True


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _mark_measured(last, took, pair_idx, frame):
    """``last[d] = frame`` for every device ``d`` in a pair ``took`` (n_pairs,) bool; returns the oldest of
    ``last[1:]`` (the devices whose TOA rates the track holds)."""
    for q in range(took.shape[0]):
        if took[q]:
            last[pair_idx[q, 0]] = frame
            last[pair_idx[q, 1]] = frame
    oldest = frame
    for d in range(1, last.shape[0]):
        oldest = min(oldest, last[d])
    return oldest


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _drift_step(drift, rate, beta, last, frame):
    """The drift average ``drift`` (M-1,) of devices 1..M-1 steps towards ``rate`` by ``beta`` where this frame
    measured the device (``last[d] == frame``)."""
    for d in range(drift.shape[0]):
        if last[d + 1] == frame:
            drift[d] += beta * (rate[d] - drift[d])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _hold_unpinned(rate, last, drift, before, limit):
    """A device last measured at speech frame ``before`` or earlier goes on at its drift average, within
    +-``limit``."""
    for d in range(rate.shape[0]):
        if last[d + 1] <= before:
            rate[d] = min(max(drift[d], -limit), limit)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _predict_gate(x, P, H0, dt, gate_min, gate_max, young, pred, gate):
    """:meth:`SourceTracker._predicted`, compiled: ``pred = H0 (toa + dt rate)`` and the gate half-widths
    ``max(3 sqrt(h P h^T), gate_min)``, capped at ``gate_max`` unless the track is ``young`` and the gate is
    over four times the cap."""
    n_pairs, m = H0.shape
    for p in range(n_pairs):
        acc = 0.0
        var = 0.0
        for a in range(m):
            ha = H0[p, a]
            if ha == 0.0:
                continue
            acc += ha * (x[a] + dt * x[m + a])
            for b in range(m):
                var += ha * P[a, b] * H0[p, b]
        pred[p] = acc
        g = max(3.0 * np.sqrt(max(var, 0.0)), gate_min)
        if g <= 4.0 * gate_max or not young:
            g = min(g, gate_max)
        gate[p] = g


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _pick_peaks(peak_tdoa, peak_value, pred, gate, used, pair_ok, min_peak, k_out, took):
    """Per pair, the unused peak (height at least ``min_peak``) nearest ``pred`` within ``gate``: its index
    into ``k_out`` (0 where none) and ``took``. Returns the number of pairs that took one."""
    n_took = 0
    for p in range(peak_tdoa.shape[0]):
        best, best_d = 0, np.inf
        if pair_ok[p]:
            for k in range(peak_tdoa.shape[1]):
                d = abs(peak_tdoa[p, k] - pred[p])
                if d <= gate[p] and peak_value[p, k] >= min_peak and not used[p, k] and d < best_d:
                    best, best_d = k, d
        k_out[p] = best
        took[p] = best_d < np.inf
        n_took += took[p]
    return n_took


@numba.njit(cache=True, nogil=True)
def _birth_support(peak_tdoa, free_ok, has, best_tdoa, usable, star_idx, star_sign, star_other, pair_i, pair_j,
                   tol, support, near):
    """The birth's hypotheses (:meth:`SourceTracker._birth`), one per usable device ``r`` with enough pairs: the
    TOA vector its pairs' best free peaks give (``toa_j - toa_r``, then relative to device 0), and the free
    peaks within ``tol`` of it. Writes the most supported one's pairs (``support``, (P,)) and peaks (``near``,
    (P, K)); returns its number of pairs, or -1 when no device has enough."""
    m = usable.shape[0]
    n_pairs, n_peaks = peak_tdoa.shape
    n_usable = 0
    for r in range(m):
        n_usable += usable[r]
    toa = np.empty(m)
    best_n = -1
    for r in range(m):
        if not usable[r]:
            continue
        n_ok = 0
        for q in range(m - 1):
            n_ok += has[star_idx[r, q]] and usable[star_other[r, q]]
        if n_ok < max(2, n_usable - 2):
            continue
        toa[:] = 0.0
        for q in range(m - 1):
            if has[star_idx[r, q]] and usable[star_other[r, q]]:
                toa[star_other[r, q]] = star_sign[r, q] * best_tdoa[star_idx[r, q]]   # toa_j - toa_r
        t0 = toa[0]
        for j in range(m):
            toa[j] -= t0
        n = 0
        for p in range(n_pairs):
            pred = toa[pair_i[p]] - toa[pair_j[p]]
            for k in range(n_peaks):
                if free_ok[p, k] and abs(peak_tdoa[p, k] - pred) <= tol:
                    n += 1
                    break
        if n > best_n:
            best_n = n
            for p in range(n_pairs):
                pred = toa[pair_i[p]] - toa[pair_j[p]]
                any_near = False
                for k in range(n_peaks):
                    near[p, k] = free_ok[p, k] and abs(peak_tdoa[p, k] - pred) <= tol
                    any_near = any_near or near[p, k]
                support[p] = any_near
    return best_n


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _solve_pairs(H0, tdoa, keep, out):
    """Least squares ``H0[keep] toa = tdoa[keep]`` through the normal equations (Cholesky of the
    ``(M-1) x (M-1)`` matrix ``H0[keep]^T H0[keep]``, which is regular when the kept pairs connect every device
    to device 0). Returns False, leaving ``out`` undefined, when it is not."""
    n_pairs, m = H0.shape
    A = np.zeros((m, m))
    b = np.zeros(m)
    for p in range(n_pairs):
        if not keep[p]:
            continue
        for i in range(m):
            hi = H0[p, i]
            if hi == 0.0:
                continue
            b[i] += hi * tdoa[p]
            for j in range(m):
                A[i, j] += hi * H0[p, j]
    L = np.zeros((m, m))
    for j in range(m):
        d = A[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        if d <= 1e-9:
            return False
        L[j, j] = np.sqrt(d)
        for i in range(j + 1, m):
            v = A[i, j]
            for k in range(j):
                v -= L[i, k] * L[j, k]
            L[i, j] = v / L[j, j]
    for i in range(m):   # L y = b, then L^T out = y
        v = b[i]
        for k in range(i):
            v -= L[i, k] * out[k]
        out[i] = v / L[i, i]
    for i in range(m - 1, -1, -1):
        v = out[i]
        for k in range(i + 1, m):
            v -= L[k, i] * out[k]
        out[i] = v / L[i, i]
    return True


@dataclass
class Track:
    """One tracked source: its filter, label and running statistics (times in stream seconds)."""

    track_id: int
    kalman: KalmanToa
    kind: TrackKind
    born_s: float
    last_hit_s: float
    n_hits: int = 0
    confirmed_s: float | None = None
    activity: float = 0.0            # EMA over speech frames of the matched peak heights summed over the pairs,
    #                                  divided by the usable pairs (0 without a hit)
    hit_now: bool = False            # hit in the last speech frame
    hit_value: float = 0.0           # and its matched peak heights summed over the pairs / usable pairs
    miss_run: int = 0                # speech frames since its last hit
    fast_activity: float = 0.0       # as ``activity``, over FAST_ACTIVITY_S
    anchor_votes: np.ndarray | None = field(default=None, repr=False)   # (M, bins): see SourceTracker._reanchor
    device_height: np.ndarray | None = None   # (M,) EMA over its hits (HEIGHT_S) of each device's matched peak
    #                                            height over its usable pairs (0 where a pair took none)
    drift_rate_s_per_s: np.ndarray | None = None   # EMA over its hits (3 s) of its TOA rates: clock drift
    last_measured: np.ndarray | None = None   # (M,) int64: per device, the speech frame (count) a matched pair
    #                                           measured it last (its birth's at first)
    oldest_measured: int = 0         # the oldest of those over devices 1..M-1
    quiet_activity: float = 0.0      # EMA over non-speech frames of "its peaks are there" (0 or 1)
    speech_rate: float = 0.0         # EMA over speech frames of "it had a hit" (0 or 1)
    active_s: float = 0.0            # seconds of frames with a hit
    steered_s: float = 0.0           # seconds steered at
    toa_sum_s: np.ndarray | None = None   # running sums for the TOA summary (hits only)
    toa_sq_sum_s2: np.ndarray | None = None
    hit_times_s: list = field(default_factory=list)   # recent hits of a tentative track
    quiet_born: bool = False         # a tentative noise source, born on a non-speech frame
    quiet_origin: bool = False       # a noise source found on non-speech frames (updated on them)
    quiet_there_s: float = 0.0       # seconds of non-speech frames its peaks were there before its first speech hit
    quiet_seen: int = 0              # its non-speech frames since birth, and its hits in them
    quiet_hits: int = 0
    quiet_value: float = 0.0         # mean matched peak height (as ``hit_value``) of its hits on non-speech frames
    n_quiet_values: int = 0          # (a running mean over the first 50 hits, then an average over the last ~50)
    speech_value: float = 0.0        # ... and of its hits on speech frames
    n_speech_values: int = 0
    died_s: float | None = None
    death_reason: str = ""
    relabels: list = field(default_factory=list)   # (time_s, old kind, new kind, why) of each change of label

    @property
    def toa_s(self) -> np.ndarray:
        """Current relative TOA, shape (n_devices,), seconds (``toa[0] = 0``)."""
        return self._state(0)

    @property
    def toa_rate_s_per_s(self) -> np.ndarray:
        """Current rate of the relative TOA, shape (n_devices,), seconds per second (``rate[0] = 0``)."""
        return self._state(1)

    def take_filter(self, other: "Track") -> None:
        """Take ``other``'s Kalman state and covariance (TOA and rate): the source it tracked is this track's."""
        self.kalman._kf.x[:] = other.kalman._kf.x
        self.kalman._kf.P[:] = other.kalman._kf.P

    def _state(self, part: int) -> np.ndarray:
        m = self.kalman.n_mics - 1
        out = np.zeros(m + 1)
        out[1:] = self.kalman._kf.x[part * m:(part + 1) * m]
        return out

    def summary(self) -> dict:
        n = max(self.n_hits, 1)
        mean = (self.toa_sum_s / n) if self.toa_sum_s is not None else self.toa_s
        std = (np.sqrt(np.maximum(self.toa_sq_sum_s2 / n - mean ** 2, 0.0)) if self.toa_sq_sum_s2 is not None
               else np.zeros_like(mean))
        return {"id": self.track_id, "kind": self.kind, "born_s": round(self.born_s, 3),
                "confirmed_s": None if self.confirmed_s is None else round(self.confirmed_s, 3),
                "died_s": None if self.died_s is None else round(self.died_s, 3), "death_reason": self.death_reason,
                "n_hits": self.n_hits, "active_s": round(self.active_s, 3), "steered_s": round(self.steered_s, 3),
                "mean_toa_s": [float(v) for v in mean], "std_toa_s": [float(v) for v in std],
                "last_toa_s": [float(v) for v in self.toa_s],
                # its matched peak heights in speech frames and in the pauses (``louder_ratio``; None without hits)
                "speech_peak": round(self.speech_value, 4) if self.n_speech_values else None,
                "pause_peak": round(self.quiet_value, 4) if self.n_quiet_values else None,
                # a talker track's per device mean matched peak height over its pairs (HEIGHT_S; None: never)
                "device_peak": (None if self.device_height is None else
                                [None if not np.isfinite(v) else round(float(v), 4) for v in self.device_height]),
                "relabels": [{"time_s": round(t, 3), "from": a, "to": b, "why": why}
                             for t, a, b, why in self.relabels]}

    @property
    def pause_first(self) -> bool:
        """Heard in the pauses for ``PAUSE_FIRST_S`` before its first hit on a speech frame: a noise source that
        sounded before anybody spoke, not a talker's onset that leaked into the noise spectra."""
        return self.quiet_there_s >= PAUSE_FIRST_S

    def talker_like(self, noise_quiet_activity: float) -> bool:
        """So far more like a talker than a noise source: hit in speech frames more often than heard in the
        pauses, or its peaks higher when somebody speaks than in the pauses; a source heard in the pauses first
        (:attr:`pause_first`) only once the pauses are quiet of it."""
        if self.pause_first and self.quiet_activity >= noise_quiet_activity:
            return False
        return self.speech_rate > self.quiet_activity or bool(
            self.n_speech_values and self.n_quiet_values and self.speech_value > self.quiet_value)

    def relabel(self, kind: TrackKind, time_s: float, why: str) -> None:
        """Change the label, recording when and why (``relabels``; the report and ``sources.png`` show them)."""
        self.relabels.append((time_s, self.kind, kind, why))
        self.kind = kind


class SourceTracker:
    """A bank of relative-TOA tracks fed with the N best GCC peaks per pair (module doc).

    Parameters
    ----------
    n_devices : int
        Number of devices ``M >= 2``.
    frame_period_s : float
        Time between frames (the hop), seconds.
    sample_rate_hz : float
        Working rate, Hz (sets the gates' floors in samples).
    accel_std_s_per_s2, tdoa_std_s, gate_probability : float
        Each track's :class:`~estimators.KalmanToa` parameters.
    target : {"active-talker", "nearest"}
        Steering policy; ``"nearest"`` needs ``target_device``.
    target_device : int, optional
        Device index for ``target="nearest"``.
    max_tracks : int
        Tracks kept at once (speech, tentative and noise).
    speech_threshold : float
        A frame with speech presence at least this is a speech frame.
    quiet_confirm_s, quiet_confirm_share : float
        A noise source born on non-speech frames is confirmed when hit in ``quiet_confirm_share`` of the
        non-speech frames of its first ``quiet_confirm_s`` (module doc); ``quiet_confirm_s=None``: noise sources
        come from the noise spectra only (the tracker before 2026-11-27).
    noise_near_s : float or None
        A pair where a noise source found in the pauses is predicted within this of a talker track's prediction
        is left out of that track's update (module doc; 3 samples at 16 kHz); None or 0: never.
    unpinned_s : float or None
        A device of a track that no matched pair has measured for this long (speech frames) goes on at its clock
        drift rate (that track's average over the hits that measured it, within ``MAX_DRIFT_RATE_S_PER_S``),
        not at a motion nothing measures; None or 0 (the default): never. Measured on the generated scenes
        (2026-11-29): TOA closer, SI-SDR a wash, more speech at a noise on three seeds: not the default.
    louder_ratio : float or None
        A noise source found in the pauses turns talker when, over its first ``LOUDER_MAX_HITS`` hits in speech
        frames, its peaks are this many times higher there than in the pauses (and it is hit in most speech
        frames): a talker heard before the first word. None or 0: never (the tracker before 2026-11-29).
    anchor_noise_s : float or None
        A GCC peak within this of a confirmed noise track's predicted TDOA in its pair does not vote for moving a
        device of the steered track (re-anchoring, module doc): the noise's peaks must not carry the beam onto
        the noise one device at a time. None or 0: they vote (the tracker before 2026-11-29).
    """

    latency_frames = 0   # causal: the steered TOA is the current frame's

    def __init__(self, n_devices: int, *, frame_period_s: float, sample_rate_hz: float,
                 accel_std_s_per_s2: float = 1e-3, tdoa_std_s: float = 1e-4, gate_probability: float = 0.99,
                 target: TargetPolicy = "active-talker", target_device: int | None = None, max_tracks: int = 8,
                 speech_threshold: float = 0.5, min_peak_value: float = 0.15, min_pair_fraction: float = 0.4,
                 gate_min_s: float | None = None, gate_max_s: float = 5e-4, birth_max_residual_s: float | None = None,
                 confirm_hits: int = 4, confirm_window_s: float = 0.3, forget_after_s: float = 30.0,
                 activity_time_constant_s: float = 0.4, switch_ratio: float = 1.5, same_source_s: float = 2e-4,
                 noise_every_s: float = 0.25, noise_quiet_activity: float = 0.3,
                 max_rate_s_per_s: float = 3e-3, quiet_confirm_s: float | None = 0.5,
                 quiet_confirm_share: float = 0.7, noise_near_s: float | None = 1.875e-4,
                 unpinned_s: float | None = None, louder_ratio: float | None = 1.3,
                 anchor_noise_s: float | None = 2.5e-4) -> None:
        if int(n_devices) != n_devices or n_devices < 2:
            raise ValueError(f"{n_devices=} must be an integer >= 2")
        if target not in ("active-talker", "nearest"):
            raise ValueError(f"{target=} must be 'active-talker' or 'nearest'")
        if target == "nearest" and (target_device is None or not 0 <= int(target_device) < n_devices):
            raise ValueError(f"{target_device=} must be a device index in 0..{n_devices - 1} for target='nearest'")
        for name, value in (("frame_period_s", frame_period_s), ("sample_rate_hz", sample_rate_hz)):
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name}={value!r} must be finite and > 0")
        if int(max_tracks) != max_tracks or max_tracks < 1:
            raise ValueError(f"{max_tracks=} must be an integer >= 1")
        self.n_devices = int(n_devices)
        self.n_pairs = self.n_devices * (self.n_devices - 1) // 2
        self.frame_period_s = float(frame_period_s)
        self.sample_rate_hz = float(sample_rate_hz)
        self.target = target
        self.target_device = None if target_device is None else int(target_device)
        self.max_tracks = int(max_tracks)
        self.speech_threshold = float(speech_threshold)
        self.min_peak_value = float(min_peak_value)
        self.min_pair_fraction = float(min_pair_fraction)
        # floors in samples and in time: at 48 kHz reverberant peaks wander by more samples
        self.gate_min_s = float(gate_min_s) if gate_min_s is not None else max(2.5 / self.sample_rate_hz, 8e-5)
        self.gate_max_s = float(gate_max_s)
        self.birth_max_residual_s = (float(birth_max_residual_s) if birth_max_residual_s is not None
                                     else max(1.5 / self.sample_rate_hz, 6e-5))
        self.confirm_hits = int(confirm_hits)
        self.confirm_window_s = float(confirm_window_s)
        self.forget_after_s = float(forget_after_s)
        self.activity_beta = 1.0 - math.exp(-self.frame_period_s / float(activity_time_constant_s))
        self._fast_beta = 1.0 - math.exp(-self.frame_period_s / FAST_ACTIVITY_S)
        self._turn_frames = max(1, int(round(QUIET_S / self.frame_period_s)))
        self.switch_ratio = float(switch_ratio)
        self.same_source_s = float(same_source_s)
        self.noise_every_frames = max(1, int(round(noise_every_s / self.frame_period_s)))
        self.quiet_beta = 1.0 - math.exp(-self.frame_period_s / 1.0)   # 1 s average over non-speech frames
        self.quiet_skip_frames = max(1, int(round(0.3 / self.frame_period_s)))  # 0.3 s after speech: its tail
        self._drift_beta = 1.0 - math.exp(-self.frame_period_s / 3.0)   # 3 s average over a track's hits
        self._unpinned_frames = (None if not unpinned_s
                                 else max(1, int(round(float(unpinned_s) / self.frame_period_s))))
        self.louder_ratio = None if not louder_ratio else float(louder_ratio)
        self.noise_quiet_activity = float(noise_quiet_activity)
        self.max_rate_s_per_s = float(max_rate_s_per_s)
        self.quiet_confirm_frames = (None if quiet_confirm_s is None
                                     else max(1, int(round(quiet_confirm_s / self.frame_period_s))))
        self.quiet_confirm_share = float(quiet_confirm_share)
        self.noise_near_s = None if not noise_near_s else float(noise_near_s)
        self.anchor_noise_s = float(anchor_noise_s or 0.0)
        self.young_s = 3.0
        self._bin_s = 2.0 / self.sample_rate_hz
        self._n_bins = 2 * int(math.ceil(0.02 / self._bin_s)) + 1          # moves up to +-20 ms
        self._anchor_gate_bins = max(2, int(math.ceil(self.gate_max_s / self._bin_s)))
        self._no_noise_lag = np.full((self.n_pairs, 1), np.nan)
        self._half_s_beta = 1.0 - math.exp(-self.frame_period_s / 0.5)   # averages over ~0.5 s of speech frames
        # a floor against moving on next to no votes: one frame of every pair of the device at height 0.15
        self._anchor_min_votes = 0.15 * (self.n_devices - 1)
        self._kalman_kwargs = dict(frame_period_s=self.frame_period_s, accel_std_s_per_s2=accel_std_s_per_s2,
                                   tdoa_std_s=tdoa_std_s, gate_probability=gate_probability,
                                   reinit_after_n_gated=None, min_confidence=0.0)
        self._tdoa_std_s = float(tdoa_std_s)
        self._pairs = pairs(self.n_devices)
        self._H0 = pair_matrix(self.n_devices)[:, 1:]
        self._rows = np.arange(self.n_pairs)
        self._pinv_cache: dict[bytes, np.ndarray] = {}
        # the talker tracks' per-device peak heights (:func:`_note_heights`): its work arrays and its EMA step
        self._height_sum, self._height_n = np.zeros(self.n_devices), np.zeros(self.n_devices)
        self._height_beta = 1.0 - math.exp(-self.frame_period_s / HEIGHT_S)
        # per device r, (M, M-1) arrays for the compiled birth (:func:`_birth_support`): the pairs (r, j) / (j, r)
        # with every other device j, that device j, and the sign that turns the pair's TDOA into toa_j - toa_r
        self._star_idx = np.array([np.flatnonzero((self._pairs == r).any(axis=1)) for r in range(self.n_devices)],
                                  np.int64).reshape(self.n_devices, -1)
        r_first = self._pairs[self._star_idx, 0] == np.arange(self.n_devices)[:, None]
        self._star_oth = np.where(r_first, self._pairs[self._star_idx, 1], self._pairs[self._star_idx, 0])
        self._star_sign = np.where(r_first, -1.0, 1.0)
        self._pair_i = np.ascontiguousarray(self._pairs[:, 0], np.int64)
        self._pair_j = np.ascontiguousarray(self._pairs[:, 1], np.int64)
        self.reset()

    @classmethod
    def compile_kernels(cls, n_devices: int, peak_tdoa: np.ndarray, peak_value: np.ndarray, noise: tuple, *,
                        frame_period_s: float, sample_rate_hz: float) -> None:
        """Compile (or load from numba's cache) every kernel a stream's tracker calls, before the stream: births,
        association, the steered track's re-anchoring votes, its tracks' Kalman steps, the pauses' checks and
        the noise sources from the noise spectra. Compiled by the first talker or the first mature noise spectra
        instead, they stalled that hop for 0.26-0.5 s on a first run (live: input overflows, an output
        underflow). A throwaway tracker hears one talker, then silence, and a noise source. ``peak_tdoa``,
        ``peak_value`` and ``noise`` (``(peak_tdoa, peak_value, correlation)``) are scratch arrays of the types
        the stream passes (a GCC stage's outputs): overwritten."""
        m = n_devices
        tracker = cls(m, frame_period_s=frame_period_s, sample_rate_hz=sample_rate_hz)
        h = pair_matrix(m)
        talker, source = h @ np.linspace(0.0, 1e-3, m), h @ np.linspace(0.0, -2e-3, m)
        n_speech, n_frames = 10, 10 + int(0.4 / frame_period_s) + 2
        for k in range(n_frames):
            for tdoa, value, first in ((peak_tdoa, peak_value, talker), (noise[0], noise[1], source)):
                tdoa[:] = np.linspace(-5e-3, 5e-3, tdoa.shape[1])
                tdoa[:, 0] = first
                value[:] = 0.05
                value[:, 0] = 0.5
            tracker.update(peak_tdoa, peak_value, speech_probability=1.0 if k < n_speech else 0.0,
                           usable=np.ones(m, bool), time_s=k * frame_period_s, noise_peaks=lambda: noise)
        _height_factors(np.full(m, 0.5), 1.0, HEIGHT_FLOOR, np.zeros(m))   # the pipeline's, for the beam

    # -- state ---------------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget every track and the steering (the stream re-aligned a device: what was tracked under the old
        alignment means nothing). Ended tracks, switches and the counters stay for the report; new tracks get
        new ids."""
        if not hasattr(self, "tracks"):   # first call, from __init__
            self.ended: list[Track] = []
            self.switches: list[dict] = []
            self.n_frames = 0
            self.n_speech_frames = 0
            self.n_speech_unsteered = 0   # of those, the frames in which no talker track was steered
            self.first_speech_s: float | None = None   # the time of the first speech frame
            self.n_births = 0
            self.n_reanchored = 0
            self.n_taken_over = 0
            self.n_pairs_near_noise = 0
            self.n_talkers_from_pauses = 0
            # the steered track's hits, and per device those where a pair of it took a peak (REFERENCE_SHARE_MIN)
            self.n_steered_hits = 0
            self._device_matched = np.zeros(self.n_devices, np.int64)
            self._matched_at = np.zeros(self.n_devices, np.int64)   # per device, the last such hit (its count)
            self._device_usable = np.zeros(self.n_devices, np.int64)
            self._usable = np.ones(self.n_devices, bool)   # the frame's usable devices (update)
            self._next_id = 0
            self._last_time_s = 0.0
        else:
            if self.steered is not None:
                self.switches.append({"time_s": round(self._last_time_s, 3), "from": self.steered.track_id,
                                      "to": -1, "reason": "the stream re-aligned a device: every track restarts"})
            for t in list(self.tracks):
                self._end(t, self._last_time_s, "reset: the stream re-aligned a device")
        self.tracks: list[Track] = []
        self._co: dict[tuple[int, int], list[float]] = {}   # per pair of talker tracks: EMA of both hit, either hit
        self._ghost_of: tuple[int, int] | None = None       # (ghost, its source) when the steered track was a ghost
        self._from_id = -1                                   # the track the next switch comes from, when it ended
        self._steered_end: tuple[int, str] | None = None     # (track, death reason) when the steered track ended
        self._ghost_toas: list[tuple[float, np.ndarray]] = []  # (time removed, TOA) of recent ghosts
        self.steered: Track | None = None
        self._quiet_frames = 0
        self.gated = False
        self.steered_toa_s = np.zeros(self.n_devices)

    @property
    def initialised(self) -> bool:
        """Whether any track exists (the estimator protocol of :class:`~estimators.KalmanToa`)."""
        return bool(self.tracks)

    @property
    def latency_s(self) -> float:
        """Extra output latency in seconds (0: causal filters)."""
        return 0.0

    def shift(self, delta_toa_s: np.ndarray, *, delta_rate_s_per_s: np.ndarray | None = None) -> None:
        """Move every track by a known TOA (and rate) change, as :meth:`KalmanToa.shift` (a re-aligned
        device or a corrected clock rate must not look like clutter). A rate change moves each track's averaged
        drift rate too: the rate it goes on at in the pauses, and at a device no pair measures."""
        d_rate = None if delta_rate_s_per_s is None else np.asarray(delta_rate_s_per_s, np.float64)
        for t in self.tracks:
            if t.kalman.initialised:
                t.kalman.shift(delta_toa_s, delta_rate_s_per_s=delta_rate_s_per_s)
                if d_rate is not None and t.drift_rate_s_per_s is not None:
                    t.drift_rate_s_per_s += d_rate[1:] - d_rate[0]

    @property
    def steered_id(self) -> int:
        """Id of the steered track, -1 when none (the output is then the devices' average at the coarse alignment,
        or the reference device where that average would point at a noise track: :meth:`noise_at`)."""
        return -1 if self.steered is None else self.steered.track_id

    def noise_at(self, toa_s: np.ndarray, tol_s: float = 2.5e-4) -> bool:
        """Whether a tracked noise source sits at the relative TOA ``toa_s`` (every device within ``tol_s``), one
        known as such (:meth:`_heard_as_noise`): a talker's onset that leaked into the noise spectra, born there
        as the first word began, is not (taking it for the noise made seed 8's `s36`, pink noise at 30 dB, the
        reference device alone for 0.15 s of the first word, 3 dB below the beam over that second)."""
        return any(t.kind == "noise" and self._gap(t.toa_s, toa_s) <= tol_s and self._heard_as_noise(t)
                   for t in self.tracks)

    def _heard_as_noise(self, t: Track) -> bool:
        """A noise track old enough to be a noise source for :meth:`noise_at` (``NOISE_KNOWN_S`` since its birth)
        and not behaving like a talker so far (:meth:`Track.talker_like`). A talker's onset leaks into the noise
        spectra before the speech detector fires, and a noise track is born there at her TOA (seed 11's `s34`:
        at 5.09 s, the first word at 5.1 s; it turned talker within half a second)."""
        return (self._time_s - t.born_s >= NOISE_KNOWN_S
                and not t.talker_like(self.noise_quiet_activity))

    def _reference_poor(self) -> bool:
        """A pair of the reference took part in fewer than ``REFERENCE_SHARE_MIN`` of at least
        ``REFERENCE_MIN_HITS`` hits of the steered track while it was usable (:meth:`reference_heard_poorly`)."""
        usable = self._device_usable[0]
        return usable >= REFERENCE_MIN_HITS and self._device_matched[0] < REFERENCE_SHARE_MIN * usable

    def reference_heard_poorly(self) -> tuple[float, float] | None:
        """(the reference device's share of the steered track's hits, the other devices' median share) when a pair
        of the reference took part in fewer than ``REFERENCE_SHARE_MIN`` of at least ``REFERENCE_MIN_HITS`` hits
        while it was usable, else None. Device 0 is the origin of every TOA and of the output's time: where its
        pairs hold no peak of the talker, the common part of every device's steering is not measured and follows
        guesses (the spread layout's largest losses: seed 11's `s33` 21 %, seed 7's `s19` 38 %, seed 11's `s09`
        57 %; 82 % or more in the 74 other scenes of seeds 7 and 11 at 5-30 dB with 60 hits or more)."""
        if not self._reference_poor():
            return None
        share = self._device_matched / np.maximum(self._device_usable, 1)
        return float(share[0]), float(np.median(share[1:][self._device_usable[1:] > 0]))

    def speech_seconds(self) -> tuple[float, float]:
        """(seconds of speech frames with no talker track steered, seconds of speech frames) so far."""
        return self.n_speech_unsteered * self.frame_period_s, self.n_speech_frames * self.frame_period_s

    def unsteered_speech(self) -> tuple[float, float] | None:
        """:meth:`speech_seconds` when the first is more than ``UNSTEERED_SHARE_MAX`` of the second and at least
        ``UNSTEERED_MIN_S``, else None. There the output is not steered at anyone (the pipeline's fallback). A
        talker track needs a few frames to be born (the fixtures steered from their first words: 0.05-0.06 s of
        3.9-11.7 s of speech); much speech unsteered means the tracker did not find the talker on every device. Over the 260 generated scenes of seeds 7-11 (twenty-sixth session) it is said in 32,
        each with more than 1 s of the talker's speech truly not beamed at (32 of the 36 such scenes; the most
        unsteered share where it is not said, 33 %, is babble noise the detector calls speech); mostly devices
        spread in a reverberant room under broadband noise (seed 8's `s35`: 4 devices, RT60 0.66 s, white noise at
        30 dB, the first talker track born after 8.2 s)."""
        unsteered_s, speech_s = self.speech_seconds()
        if unsteered_s >= UNSTEERED_MIN_S and unsteered_s > UNSTEERED_SHARE_MAX * speech_s:
            return unsteered_s, speech_s
        return None

    def report(self) -> dict:
        """Tracks (alive and ended), switches and counters, for ``report.json``."""
        unsteered_s, speech_s = self.speech_seconds()
        return {"target": self.target if self.target != "nearest" else f"nearest {self.target_device}",
                "n_frames": self.n_frames, "n_speech_frames": self.n_speech_frames, "n_births": self.n_births,
                "speech_s": round(speech_s, 3), "unsteered_speech_s": round(unsteered_s, 3),
                "n_reanchored": self.n_reanchored, "n_taken_over": self.n_taken_over,
                "n_pairs_near_noise": self.n_pairs_near_noise, "n_talkers_from_pauses": self.n_talkers_from_pauses,
                "steered_hits": self.n_steered_hits,
                # per device: the share of the steered track's hits, while it was usable, that took a pair of it
                "device_matched_share": [round(float(n) / float(u), 3) if u else None
                                         for n, u in zip(self._device_matched, self._device_usable)],
                "tracks": [t.summary() for t in sorted(self.ended + self.tracks, key=lambda t: t.track_id)
                           if t.kind != "tentative" or t.n_hits >= self.confirm_hits],
                "switches": self.switches}

    # -- per frame -----------------------------------------------------------------------------------
    def update(self, peak_tdoa_s: np.ndarray, peak_value: np.ndarray, *, speech_probability: float,
               usable: np.ndarray, time_s: float, noise_peaks=None) -> np.ndarray:
        """One frame: associate, update, give birth, label, forget, steer.

        Parameters
        ----------
        peak_tdoa_s, peak_value : ndarray, shape (n_pairs, n_peaks), float64
            The N best GCC peaks of every pair (:meth:`NoiseAwareGcc.process`).
        speech_probability : float
            The frame's speech presence in ``[0, 1]``.
        usable : ndarray, shape (n_devices,), bool
            Devices usable in this frame.
        time_s : float
            Stream time of the frame (seconds), for the report.
        noise_peaks : callable, optional
            Returns ``(peak_tdoa_s, peak_value)`` of the noise cross-power spectra; called every
            ``noise_every_s``.

        Returns
        -------
        ndarray, shape (n_devices,), float64
            The steered relative TOA (seconds; ``toa[0] = 0``), zeros when nothing is steered.
        """
        self.n_frames += 1
        self._last_time_s = time_s
        self._time_s = time_s
        speech = bool(speech_probability >= self.speech_threshold)
        pair_ok = usable[self._pairs[:, 0]] & usable[self._pairs[:, 1]]
        self._usable = usable
        n_ok = int(pair_ok.sum())
        hit_any = False
        self.gated = False
        if speech and n_ok:
            self.n_speech_frames += 1
            if self.first_speech_s is None:
                self.first_speech_s = time_s
            for t in [t for t in self.tracks if t.quiet_born]:   # a noise source is confirmed in one pause
                self._end(t, time_s, "not confirmed")
            hit_any = self._associate(peak_tdoa_s, peak_value, pair_ok, n_ok, time_s)
            if not hit_any or self.n_speech_frames % 4 == 0:
                self._birth(peak_tdoa_s, peak_value, pair_ok, n_ok, usable, time_s)
            self._quiet_frames = 0
        else:
            self._quiet_frames += 1
            quiet = self._quiet_frames >= self.quiet_skip_frames   # past the talker's reverberant tail
            sources = bool(n_ok) and quiet and self.quiet_confirm_frames is not None
            for t in self.tracks:
                if not (sources and (t.quiet_origin or t.quiet_born)):   # those step with their peaks below
                    t.kalman.predict()
                    self._hold_still(t, quiet=quiet)
            if n_ok and quiet:
                taken = None
                if sources:
                    taken = self._quiet_sources(peak_tdoa_s, peak_value, pair_ok, n_ok, usable, time_s)
                self._quiet_check(peak_tdoa_s, peak_value, pair_ok, n_ok, taken)
        if noise_peaks is not None and self.n_frames % self.noise_every_frames == 0:
            self._noise_update(*noise_peaks(), pair_ok, n_ok, usable, time_s)
        self._housekeeping(time_s)
        self._steer(time_s, speech)
        if speech and n_ok and self.steered is None:
            self.n_speech_unsteered += 1
        if self.steered is not None:
            self.steered.steered_s += self.frame_period_s
            self.steered_toa_s = self.steered.toa_s
        else:
            self.steered_toa_s = np.zeros(self.n_devices)
        return self.steered_toa_s

    def _predicted(self, t: Track, *, speech: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Predicted pair TDOAs (n_pairs,) and their gate half-widths (n_pairs,), seconds; ``speech``: for a
        speech frame's association."""
        kf = t.kalman._kf
        pred, gate = np.empty(self.n_pairs), np.empty(self.n_pairs)
        # the cap keeps a tracked source from wandering onto clutter; in a young track a device it has not
        # pinned down yet (its spread is far wider) keeps its whole gate, so that it can be picked up or
        # corrected; later a wide spread means the track went unhit for long, and it must not jump. A noise
        # source is corrected in the pauses only: in a speech frame a young noise track's open gate takes the
        # talker's peaks at the first word, and the talker's track is then born on the noise (seed 11's `s10`)
        young = self._time_s - t.born_s < self.young_s and not (speech and t.kind == "noise")
        _predict_gate(kf.x, kf.P, self._H0, self.frame_period_s, self.gate_min_s, self.gate_max_s,
                      young, pred, gate)
        return pred, gate

    def _associate(self, peak_tdoa, peak_value, pair_ok, n_ok, time_s) -> bool:
        used = np.zeros(peak_value.shape, bool)
        # the strongest talker first: a steered side lobe must not take the peaks its own source shares with it
        order = sorted(self.tracks, key=lambda t: (t.kind == "tentative", -t.activity))
        hit_any = False
        min_pairs = max(2, int(math.ceil(self.min_pair_fraction * n_ok)))
        k, picked = np.empty(self.n_pairs, np.int64), np.empty(self.n_pairs, bool)
        # noise sources found in the pauses: predicted once, for the talker tracks' pairs and their own update
        noise = ({id(n): self._predicted(n, speech=True) for n in self.tracks
                  if n.kind == "noise" and n.quiet_origin}
                 if self.noise_near_s else {})
        noise_pred = [pred for pred, _ in noise.values()]
        for t in order:
            if t.quiet_born:   # a noise candidate counts non-speech frames only
                continue
            pred, gate = noise[id(t)] if id(t) in noise else self._predicted(t, speech=True)
            # (on the frame's prediction, before any re-anchoring below)
            ok = self._clear_of_noise(pred, noise_pred, pair_ok, min_pairs) if t.kind != "noise" else pair_ok
            if t is self.steered and self._reanchor(t, peak_tdoa, peak_value, pred, pair_ok, self._noise_lags()):
                pred, gate = self._predicted(t)
            took, conf = self._match(t, pred, gate, peak_tdoa, peak_value, ok, used, min_pairs, k, picked)
            hit = False
            if conf is not None:
                if not t.kalman.gated:
                    hit = True
                    used[self._rows[took], k[took]] = True
                    value = float(conf[took].sum()) / n_ok   # peak height times the share of pairs
                    if self._unpinned_frames is not None:
                        t.oldest_measured = _mark_measured(t.last_measured, took, self._pairs, self.n_speech_frames)
                    t.n_speech_values += 1
                    t.speech_value += (value - t.speech_value) / min(t.n_speech_values, 50)
                    if t.kind == "speech":
                        self._note_heights(t, conf, ok)
                    if t is self.steered:
                        self.n_steered_hits += 1
                        _mark_measured(self._matched_at, took, self._pairs, self.n_steered_hits)
                        self._device_matched += self._matched_at == self.n_steered_hits
                        self._device_usable += self._usable
                    self._record_hit(t, time_s, value, measured=True)
                elif t is self.steered:
                    self.gated = True
            else:
                t.kalman.predict()
            self._hold_still(t, quiet=False)
            if t.kind == "speech":
                t.activity += self.activity_beta * ((value if hit else 0.0) - t.activity)
                t.fast_activity += self._fast_beta * ((value if hit else 0.0) - t.fast_activity)
                t.miss_run = 0 if hit else t.miss_run + 1
            if t.kind != "tentative":
                # a noise track that starts being hit on speech frames (a talker whose breath or the room of
                # the recording was heard before the first word) turns talker within about half a second
                beta = self.activity_beta if t.kind == "noise" else self.quiet_beta
                t.speech_rate += beta * (float(hit) - t.speech_rate)
                self._relabel(t)
            hit_any |= hit and t.kind != "noise"
            t.hit_now = hit
            t.hit_value = value if hit else 0.0
        self._ghosts(time_s)
        if self.target == "active-talker":
            self._take_over(time_s)
        self._used = used
        return hit_any

    def _clear_of_noise(self, pred: np.ndarray, noise_pred: list[np.ndarray], pair_ok: np.ndarray,
                        min_pairs: int) -> np.ndarray:
        """``pair_ok`` without the pairs where a noise source found in the pauses is predicted within
        ``noise_near_s`` of ``pred`` (a talker track's predicted TDOAs), unless fewer than ``max(min_pairs, 3)``
        pairs would be left."""
        if not noise_pred:
            return pair_ok
        near = np.zeros(self.n_pairs, bool)
        for p in noise_pred:
            near |= np.abs(p - pred) < self.noise_near_s
        if not near.any():
            return pair_ok
        keep = pair_ok & ~near
        if int(keep.sum()) < max(min_pairs, 3):
            return pair_ok
        self.n_pairs_near_noise += int((pair_ok & near).sum())
        return keep

    def _match(self, t: Track, pred, gate, peak_tdoa, peak_value, pair_ok, used, min_pairs, k, picked):
        """Per pair the unused peak nearest ``t``'s prediction within its gate (into ``k``, ``picked``), kept if
        the peaks agree with one TOA vector; with at least ``min_pairs`` of them the track updates (it may gate
        them out as clutter: ``t.kalman.gated``). Returns (the pairs kept, their confidences, or None when the
        track did not update)."""
        n_took = _pick_peaks(peak_tdoa, peak_value, pred, gate, used, pair_ok, self.min_peak_value, k, picked)
        tdoa = peak_tdoa[self._rows, k]
        took = self._consistent(tdoa, picked) if n_took >= min_pairs else picked   # peaks must also agree
        if int(took.sum()) < min_pairs:
            return took, None
        conf = np.where(took, peak_value[self._rows, k], 0.0)
        t.kalman.update(tdoa, conf)
        return took, conf

    def _note_heights(self, t: Track, conf: np.ndarray, pair_ok: np.ndarray) -> None:
        """A talker track's hit: each device's mean matched peak height over its usable pairs (a pair that took
        no peak counts 0) into ``t.device_height`` (EMA over ``HEIGHT_S`` of its hits; :func:`_note_heights`)."""
        if t.device_height is None:
            t.device_height = np.full(self.n_devices, np.nan)
        _note_heights(t.device_height, conf, pair_ok, self._pairs, self._height_beta, self._height_sum,
                      self._height_n)

    def steered_height_factors(self, exponent: float, out: np.ndarray) -> bool:
        """Into ``out`` (M,): ``exponent`` times the log of each device's matched peak height on the steered
        talker track over the median device's (heights below ``HEIGHT_FLOOR`` count as it; 0 for a device never
        measured): the log factors of the beam's ``level`` weights (``EngineConfig.level_height_exponent``).
        False when nothing is steered or nothing measured."""
        t = self.steered
        if t is None or t.device_height is None:
            return False
        return _height_factors(t.device_height, float(exponent), HEIGHT_FLOOR, out)

    def _reanchor(self, t: Track, peak_tdoa, peak_value, pred, pair_ok, noise_lag) -> bool:
        """One device of the steered track locked on a reflection or a side lobe: all its pairs show a peak at
        one other TOA for it, while the others agree with the track. Every peak of pair (i, j) votes for moving
        device i by ``peak - pred`` and device j by the opposite (weighted by its height, averaged over about half
        a second of speech frames, in bins of two samples); a device whose best move beyond the gate has more
        than ``REANCHOR_RATIO`` times the votes of staying is moved there (a known shift, as a re-alignment).
        A peak where a confirmed noise track is predicted in that pair (``anchor_noise_s``) does not vote for a move: in
        seed 10's `s17` (spread, dishes at 10 dB) the dish clatter's peaks moved device 3 of the steered talker
        track onto the noise, and 32 ms later device 2, so that the beam sat on the noise for 4 s.
        Returns whether a device moved."""
        if t.anchor_votes is None:
            t.anchor_votes = np.zeros((self.n_devices, self._n_bins))
        votes = t.anchor_votes
        c = self._n_bins // 2
        dev, best = _anchor_vote(votes, peak_tdoa, peak_value, pred, pair_ok, self._pairs,
                                 1.0 - self._half_s_beta, 1.0 / self._bin_s, self.min_peak_value,
                                 self._anchor_gate_bins, REANCHOR_RATIO, self._anchor_min_votes,
                                 noise_lag, self.anchor_noise_s)
        if dev < 0:
            return False
        if dev == 0 and self._reference_poor():
            # a reference heard this poorly (:meth:`reference_heard_poorly`) is not moved: its pairs' peaks are
            # not the talker's, and a move shifts every other device's steering and the output's time with it
            votes[0] = 0.0
            return False
        delta = np.zeros(self.n_devices)
        delta[dev] = (best - c) * self._bin_s
        t.kalman.shift(delta - delta[0])
        votes[:] = 0.0
        self.n_reanchored += 1
        return True

    def _noise_lags(self) -> np.ndarray:
        """Predicted pair TDOAs of the confirmed noise tracks, shape (n_pairs, n_noise) (one column of NaN when
        there is none or ``anchor_noise_s`` is off), but not of a noise track that behaves like a talker so far
        (:attr:`Track.talker_like`): a talker's onset that leaked into the noise spectra is such a track until it
        turns talker (seed 7's `s32`: it held the steered track off its talker for 0.15 s, −2 dB)."""
        if not self.anchor_noise_s:
            return self._no_noise_lag
        cols = [self._predicted(n, speech=True)[0] for n in self.tracks
                if n.kind == "noise" and not n.talker_like(self.noise_quiet_activity)]
        return np.stack(cols, axis=1) if cols else self._no_noise_lag

    def _take_over(self, time_s: float) -> None:
        """A talker track confirmed in this frame within ``TAKEOVER_S`` of the steered track on every device is
        the steered talker where it is now (a walking talker outruns a track's capped gate, and a new track is
        born from the peaks the old one no longer reaches): the steered track takes the new one's state, and
        the beam follows without waiting for the new track to become the more active (``n_taken_over``)."""
        st = self.steered
        if st is None or st.kind != "speech":
            return
        for t in self.tracks:
            if t is not st and t.kind == "speech" and t.confirmed_s == time_s \
                    and self._gap(t.toa_s, st.toa_s) <= TAKEOVER_S:
                st.take_filter(t)
                st.last_hit_s = time_s
                self.n_taken_over += 1
                self._end(t, time_s, f"taken over by the steered track {st.track_id} (its talker, moved)")
                return

    def _ghosts(self, time_s: float) -> None:
        """Two talker tracks heard in the same speech frames (over the last half second) are one talker: the
        weaker in those frames (matched peak heights summed over the pairs) is a side lobe of its voice or a
        reflection, and goes. Comparing them on their common frames only keeps a talker who returns after a
        turn (whose ``activity`` decayed meanwhile) against a noise heard in speech frames."""
        talkers = [t for t in self.tracks if t.kind == "speech"]
        beta = self._half_s_beta
        alive = set()
        for i, a in enumerate(talkers):
            for b in talkers[i + 1:]:
                key = (a.track_id, b.track_id) if a.track_id < b.track_id else (b.track_id, a.track_id)
                alive.add(key)
                c = self._co.setdefault(key, [0.0, 0.0, 0.0])   # both hit, either hit, value(lo id) - value(hi id)
                both = a.hit_now and b.hit_now
                c[0] += beta * (float(both) - c[0])
                c[1] += beta * (float(a.hit_now or b.hit_now) - c[1])
                if not both:
                    continue
                lo, hi = (a, b) if a.track_id < b.track_id else (b, a)
                c[2] += beta * (lo.hit_value - hi.hit_value - c[2])
                if c[1] > 0.3 and c[0] > 0.6 * c[1] and a in self.tracks and b in self.tracks:
                    weak, keep = (hi, lo) if c[2] > 0 else (lo, hi)
                    if weak is self.steered:   # _steer picks the next one, saying why
                        self._ghost_of = (weak.track_id, keep.track_id)
                    self._end(weak, time_s, f"a ghost of track {keep.track_id}: heard in the same frames, "
                                            "weaker (a side lobe of its voice or a reflection)")
                    self._ghost_toas.append((time_s, weak.toa_s))
        for key in list(self._co):
            if key not in alive:
                del self._co[key]

    def _hold_still(self, t: Track, *, quiet: bool) -> None:
        """Keep a track's TOA rates physical: at most ``max_rate_s_per_s`` (a talker walking at 1 m/s changes
        a TDOA by at most 2.9 ms/s; clock drift adds 0.2 ms/s), so that a rate learned from a few stray peaks
        cannot carry a track away while it is not corrected. In a pause (``quiet``, from 0.3 s after the last
        speech frame) the track goes on at its rate averaged over its hits (clock drift, which goes on while the
        talker is silent: not damped to 0), held to what clock drift alone gives (``MAX_DRIFT_RATE_S_PER_S``): a
        motion or a stray rate learned from its last few peaks must not carry the track seconds away before it
        is heard again."""
        x = t.kalman._kf.x
        m = self.n_devices - 1
        limit = MAX_DRIFT_RATE_S_PER_S if quiet else self.max_rate_s_per_s
        rate = x[m:]
        if quiet and t.drift_rate_s_per_s is not None:
            rate[:] = t.drift_rate_s_per_s
        elif not quiet and self._unpinned_frames is not None and t.drift_rate_s_per_s is not None and \
                self.n_speech_frames - t.oldest_measured >= self._unpinned_frames:
            # a device no matched pair has measured for ``unpinned_s``: its rate is what its clock drift gives, not a
            # motion nothing measures (seed 11's `s41`: one device of a talker track unmatched for 7 s drifted at
            # -0.36 ms/s, 5-8 ms off its talker)
            _hold_unpinned(rate, t.last_measured, t.drift_rate_s_per_s, self.n_speech_frames - self._unpinned_frames,
                           MAX_DRIFT_RATE_S_PER_S)
        np.minimum(rate, limit, out=rate)
        np.maximum(rate, -limit, out=rate)

    def _quiet_check(self, peak_tdoa, peak_value, pair_ok, n_ok, taken=None) -> None:
        """Non-speech frame (peaks of the plain PHAT): which tracks' peaks are still there? A source that
        keeps sounding when nobody speaks is a noise source (label ``"noise"``); a talker is silent then. A peak
        that a noise source found in the pauses took in this frame (``taken``, from :meth:`_quiet_sources`) is
        that source's, not a talker's, on the pairs where the two are more than ``NOISE_SAME_S`` apart: in the
        measured office's `m18` (bar, white noise at 10 dB) the noise sat
        within 0.1-0.5 ms of the talker on several pairs, its peaks fell in the talker track's gates in the
        pauses, and the talker track turned noise 1.4 s into the first pause (−0.98 dB against 4.7 with the truth)."""
        min_pairs = max(2, int(math.ceil(self.min_pair_fraction * n_ok)))
        near_noise = taken is not None and taken.any()
        # each track predicted once (nothing here moves a filter): the confirmed ones, and the noise sources
        predicted = {id(t): self._predicted(t) for t in self.tracks
                     if t.kind != "tentative" or (near_noise and (t.quiet_origin or t.quiet_born))}
        noise_pred = [predicted[id(n)][0] for n in self.tracks if n.quiet_origin or n.quiet_born] if near_noise else []
        for t in self.tracks:
            if t.kind == "tentative":
                continue
            pred, gate = predicted[id(t)]
            ok = (np.abs(peak_tdoa - pred[:, None]) <= gate[:, None]) & (peak_value >= self.min_peak_value)
            if noise_pred and t.kind == "speech":
                # only on the pairs where the talker is apart from every such source: a talker track on the
                # noise but for a device or two (the measured office's `m30`, babble) is still heard in the pauses
                apart = np.ones(self.n_pairs, bool)
                for p in noise_pred:
                    apart &= np.abs(p - pred) > NOISE_SAME_S
                ok &= ~(taken & apart[:, None])
            there = float(int((ok.any(axis=1) & pair_ok).sum()) >= min_pairs)
            t.quiet_activity += self.quiet_beta * (there - t.quiet_activity)
            if there and not t.n_speech_values:
                t.quiet_there_s += self.frame_period_s
            if t.kind == "noise" and there:
                t.last_hit_s = self._time_s
            self._relabel(t)

    def _relabel(self, t: Track) -> None:
        """Speech or noise, by how the track's activity follows speech presence (module doc). A noise track
        found in the noise spectra that has hits on speech frames and is quiet in the pauses (a talker's
        onset leaked into the noise average before the detector caught it) becomes a talker."""
        if t.kind == "speech" and t.quiet_activity > max(self.noise_quiet_activity, t.speech_rate):
            t.relabel("noise", self._time_s, "it keeps sounding in the pauses")
            t.activity = 0.0
        elif t.kind == "noise" and t.speech_rate > max(self.noise_quiet_activity, t.quiet_activity) + 0.1 and (
                not (t.quiet_origin or t.pause_first) or t.quiet_activity < self.noise_quiet_activity):
            # a source found sounding in the pauses (or found in the noise spectra and heard in the pauses before
            # anybody spoke: seed 10's `s17`, a dish clatter heard 1.8 s before the talker, turned talker when it
            # clattered through 0.5 s of speech, and the beam followed it for 2.2 s) turns talker only once the
            # pauses are quiet of it
            t.relabel("speech", self._time_s, "heard when somebody speaks, quiet in the pauses")
            t.quiet_origin = False
        elif t.kind == "noise" and t.quiet_origin and self._louder_when_speaking(t):
            # a source of the pauses that is louder when somebody speaks is a talker heard before the first word
            # (the room or the breath of the recording): a noise source is masked by the talker instead. Over the
            # scenes of seeds 7-10 a noise source's peaks were 0.5-1.0 times as high in speech frames as in the
            # pauses, such a talker's 1.6-2.2 times (seed 9's `s45`, seed 10's `s47`). Decided over the source's
            # first speech hits only: white noise at 0 dB (seed 11's `s02`) reached 1.37 after 2.5 s of speech
            t.relabel("speech", self._time_s, f"its peaks are {t.speech_value / max(t.quiet_value, 1e-12):.1f} times "
                      "as high when somebody speaks as in the pauses")
            t.quiet_origin = False
            t.quiet_activity = 0.0
            self.n_talkers_from_pauses += 1

    def _louder_when_speaking(self, t: Track) -> bool:
        """Over its first speech hits (at most ``LOUDER_MAX_HITS``, with ``LOUDER_MIN_HITS`` in the pauses) its
        peaks are ``louder_ratio`` times as high in speech frames as in the pauses and it is hit in most speech
        frames (from ``LOUDER_MIN_HITS`` speech hits on), or :meth:`_far_louder` (from ``LOUDER_EARLY_HITS``)."""
        if self.louder_ratio is None or t.n_quiet_values < LOUDER_MIN_HITS or t.n_speech_values > LOUDER_MAX_HITS:
            return False
        if t.n_speech_values >= LOUDER_MIN_HITS and t.speech_rate > 0.5 and \
                t.speech_value > self.louder_ratio * t.quiet_value:
            return True
        return t.n_speech_values >= LOUDER_EARLY_HITS and self._far_louder(t.speech_value, t.quiet_value)

    def _far_louder(self, speech_value: float, quiet_value: float) -> bool:
        """Peaks in speech frames ``LOUDER_EARLY_RATIO`` (and ``louder_ratio``) times those in the pauses: a talker's
        own sound in the pauses, not a noise source the talker masks."""
        return self.louder_ratio is not None and \
            speech_value > max(LOUDER_EARLY_RATIO, self.louder_ratio) * quiet_value

    def _record_hit(self, t: Track, time_s: float, value: float, *, measured: bool = False) -> None:
        rate = t.kalman._kf.x[self.n_devices - 1:]
        if t.drift_rate_s_per_s is None:
            t.drift_rate_s_per_s = rate.copy()
        else:
            # a plain average over its first hits, then the 3 s exponential one (no pull towards the first rate);
            # with ``unpinned_s``, a device no pair of this hit (``measured``: ``t.last_measured`` marked) measured
            # keeps its average
            beta = max(self._drift_beta, 1.0 / (t.n_hits + 1))
            if measured and self._unpinned_frames is not None:
                _drift_step(t.drift_rate_s_per_s, rate, beta, t.last_measured, self.n_speech_frames)
            else:
                t.drift_rate_s_per_s += beta * (rate - t.drift_rate_s_per_s)
        t.n_hits += 1
        t.last_hit_s = time_s
        t.active_s += self.frame_period_s
        toa = t.toa_s
        if t.toa_sum_s is None:
            t.toa_sum_s, t.toa_sq_sum_s2 = toa.copy(), toa ** 2
        else:
            t.toa_sum_s += toa
            t.toa_sq_sum_s2 += toa ** 2
        if t.kind == "tentative":
            t.hit_times_s.append(time_s)
            if len(t.hit_times_s) >= self.confirm_hits:
                t.kind = "speech"
                t.confirmed_s = time_s
                t.activity = value
                # the hit rate's average as if it had run from the birth: a few hits are little evidence against
                # a source heard all through the pauses (a dish clatter that fired the speech detector)
                t.speech_rate = 1.0 - (1.0 - self.quiet_beta) ** t.n_hits
                t.hit_times_s = []

    def _lstsq(self, tdoa: np.ndarray, keep: np.ndarray) -> np.ndarray:
        """Least-squares (minimum-norm) relative TOA of devices 1..M-1 from the pairs ``keep`` (eq. 12): the
        normal equations (one compiled call) when the pairs connect every device, else a cached pseudo-inverse
        per set of pairs."""
        sol = np.empty(self.n_devices - 1)
        if _solve_pairs(self._H0, tdoa, keep, sol):
            return sol
        key = keep.tobytes()   # the kept pairs leave a device unconnected: the minimum-norm solution
        pinv = self._pinv_cache.get(key)
        if pinv is None:
            if len(self._pinv_cache) >= 256:
                self._pinv_cache.clear()
            pinv = self._pinv_cache[key] = np.linalg.pinv(self._H0[keep])
        return pinv @ tdoa[keep]

    def _consistent(self, tdoa: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """The pairs of ``ok`` whose TDOAs agree with one TOA vector (eq. 12 fit, one refit without the
        pairs off by more than ``birth_max_residual_s``)."""
        keep = ok
        for _ in range(2):
            if keep.sum() < self.n_devices - 1:
                return keep
            sol = self._lstsq(tdoa, keep)
            new = ok & (np.abs(self._H0 @ sol - tdoa) <= self.birth_max_residual_s)
            if np.array_equal(new, keep):
                return keep   # the refit would be the same fit
            keep = new
        return keep

    def _fit(self, tdoa, ok, usable, *, max_residual_s: float | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """Robust eq. (12) fit of the pairs ``ok``: returns (toa (M,), kept pairs) or None when the kept
        pairs are too few, inconsistent (residual above ``max_residual_s``, default ``birth_max_residual_s``)
        or leave a usable device unconnected."""
        max_residual_s = self.birth_max_residual_s if max_residual_s is None else max_residual_s
        need = self.n_devices - 1
        keep = ok.copy()
        for _ in range(2):
            if keep.sum() < need:
                return None
            sol = self._lstsq(tdoa, keep)
            resid = np.abs(self._H0 @ sol - tdoa)
            keep = ok & (resid <= max_residual_s)
        n_ok = int(ok.sum())
        if keep.sum() < max(need, math.ceil(self.min_pair_fraction * n_ok)):
            return None
        covered = np.zeros(self.n_devices, bool)
        covered[self._pairs[keep, 0]] = True
        covered[self._pairs[keep, 1]] = True
        if not covered[usable].all():
            return None
        H0 = self._H0[keep]
        sol = self._lstsq(tdoa, keep)
        if np.sqrt(np.mean((H0 @ sol - tdoa[keep]) ** 2)) > 0.5 * max_residual_s:
            return None
        return np.concatenate([[0.0], sol]), keep

    def _birth(self, peak_tdoa, peak_value, pair_ok, n_ok, usable, time_s, *, quiet: bool = False) -> None:
        """A tentative track from the peaks no track took: hypotheses from each usable device's pairs with
        every other device (their best free peaks give one TOA vector each), the one most pairs support (any
        free peak within ``birth_max_residual_s``) refitted on its support (robust to pairs whose best peak is
        a reflection or another source, which a plain least-squares fit of the best peaks is not)."""
        free_ok = ~self._used & (peak_value >= self.min_peak_value) & pair_ok[:, None]
        free = np.where(free_ok, peak_value, -np.inf)
        k_best = np.argmax(free, axis=1)
        has = np.isfinite(free[self._rows, k_best])
        if has.sum() < self.n_devices - 1:
            return
        best_tdoa = peak_tdoa[self._rows, k_best]
        support, near = np.empty(self.n_pairs, bool), np.empty(peak_tdoa.shape, bool)   # filled unless -1
        if _birth_support(np.ascontiguousarray(peak_tdoa, np.float64), free_ok, has, best_tdoa,
                          np.ascontiguousarray(usable, np.bool_), self._star_idx, self._star_sign, self._star_oth,
                          self._pair_i, self._pair_j, float(self.birth_max_residual_s), support, near) < 0:
            return
        k = np.argmax(np.where(near, peak_value, -np.inf), axis=1)
        tdoa = peak_tdoa[self._rows, k]
        fit = self._fit(tdoa, support, usable)
        if fit is None:
            return
        toa, keep = fit
        if any(self._distance(toa, t.toa_s) < self.same_source_s for t in self.tracks):
            return
        # no rebirth of a ghost removed in the last few seconds (its source still speaks)
        self._ghost_toas = [(s, g) for s, g in self._ghost_toas if time_s - s < GHOST_MEMORY_S]
        if any(self._distance(toa, g) < self.same_source_s for _, g in self._ghost_toas):
            return
        t = self._new_track("tentative", time_s)
        t.kalman.update(np.where(keep, tdoa, 0.0), keep.astype(float))
        if not t.kalman.initialised:
            self.tracks.remove(t)
            return
        if quiet:
            t.quiet_born = True
            t.quiet_seen = t.quiet_hits = 1
            t.n_hits = 1
            return
        self._record_hit(t, time_s, float(peak_value[self._rows, k][keep].sum()) / n_ok)

    def _new_track(self, kind: TrackKind, time_s: float) -> Track:
        if len(self.tracks) >= self.max_tracks:
            victims = [t for t in self.tracks if t is not self.steered]
            if not victims:
                raise RuntimeError("max_tracks must leave room beside the steered track")
            victim = min(victims, key=lambda t: (t.kind != "tentative", t.last_hit_s))
            self._end(victim, time_s, "bank full")
        kalman = KalmanToa(self.n_devices, initial_toa_std_s=0.05, **self._kalman_kwargs)
        t = Track(self._next_id, kalman, kind, born_s=time_s, last_hit_s=time_s,
                  last_measured=np.full(self.n_devices, self.n_speech_frames, np.int64),
                  oldest_measured=self.n_speech_frames)
        self._next_id += 1
        self.n_births += 1
        self.tracks.append(t)
        return t

    def _end(self, t: Track, time_s: float, reason: str) -> None:
        t.died_s = time_s
        t.death_reason = reason
        self.tracks.remove(t)
        if t.kind != "tentative":
            self.ended.append(t)
        if t is self.steered:
            self.steered = None
            self._steered_end = (t.track_id, reason)

    def _quiet_sources(self, peak_tdoa, peak_value, pair_ok, n_ok, usable, time_s) -> np.ndarray:
        """Non-speech frame past a talker's tail (plain PHAT peaks): noise sources are born here too. A source
        heard when nobody speaks is a noise source, whatever the speech detector says later while it sounds
        (a dish clatter fires it): a tentative noise track is born from the peaks no noise track explains and
        is confirmed as ``"noise"`` when it was hit in ``quiet_confirm_share`` of the non-speech frames of its
        first ``quiet_confirm_s`` (a talker's onset heard before the detector fires is far shorter); the noise
        tracks found this way update with their peaks here. In speech frames a noise track then takes its
        source's peaks after the talkers, so no talker track is born on them."""
        used = np.zeros(peak_value.shape, bool)
        min_pairs = max(2, int(math.ceil(self.min_pair_fraction * n_ok)))
        k, picked = np.empty(self.n_pairs, np.int64), np.empty(self.n_pairs, bool)
        for t in list(self.tracks):
            if not (t.quiet_origin or t.quiet_born):
                continue
            pred, gate = self._predicted(t)
            took, conf = self._match(t, pred, gate, peak_tdoa, peak_value, pair_ok, used, min_pairs, k, picked)
            if conf is None:   # one step per frame: the update predicts, so only a track without one does here
                t.kalman.predict()
            self._hold_still(t, quiet=True)
            hit = conf is not None and not t.kalman.gated
            if hit:
                used[self._rows[took], k[took]] = True
                t.last_hit_s = time_s
                t.n_quiet_values += 1
                t.quiet_value += (float(conf[took].sum()) / n_ok - t.quiet_value) / min(t.n_quiet_values, 50)
            if not t.quiet_born:
                continue
            t.quiet_seen += 1
            t.quiet_hits += hit
            if t.quiet_seen >= self.quiet_confirm_frames:
                if t.quiet_hits >= self.quiet_confirm_share * t.quiet_seen:
                    t.kind, t.quiet_born, t.quiet_origin = "noise", False, True
                    t.confirmed_s = time_s
                    t.n_hits = t.quiet_hits
                    t.quiet_activity = 1.0   # heard all through the pauses so far
                else:
                    self._end(t, time_s, "not confirmed")
        if not any(t.quiet_born for t in self.tracks):
            self._used = used
            self._birth(peak_tdoa, peak_value, pair_ok, n_ok, usable, time_s, quiet=True)
        return used

    def _noise_update(self, peak_tdoa, peak_value, correlation, pair_ok, n_ok, usable, time_s) -> None:
        """Noise sources from the PHAT of the noise cross-power spectra (best and second-best peaks): the
        averaged spectra of a reverberant noise give lower, wider peaks than one speech frame, so the fit
        allows twice the birth residual."""
        for rank in range(min(2, peak_tdoa.shape[1])):
            ok = pair_ok & (peak_value[:, rank] >= self.min_peak_value)
            if ok.sum() < self.n_devices - 1:
                continue
            # a contiguous copy of the column: the kernels see the layout they are compiled for (a column view
            # compiled another specialisation of _solve_pairs, a 0.26 s stall the first time a noise source was fit)
            tdoa = np.ascontiguousarray(peak_tdoa[:, rank])
            fit = self._fit(tdoa, ok, usable, max_residual_s=2 * self.birth_max_residual_s)
            if fit is None:
                continue
            toa, keep = fit
            nearest = min((t for t in self.tracks if t.kind == "noise"),
                          key=lambda t: self._distance(toa, t.toa_s), default=None)
            # a source found on a single pause's frames may have one device on a reflection: the averaged spectra
            # put it right (rather than start a second track of the same source that could wander off)
            near = nearest is not None and (self._distance(toa, nearest.toa_s) < 3 * self.same_source_s or (
                nearest.quiet_origin and int((np.abs(toa - nearest.toa_s) > 3 * self.same_source_s).sum()) <= 1))
            if near:
                t = nearest
                # a direct correction: noise tracks are refreshed a few times per second
                t.kalman._kf.x[:self.n_devices - 1] = toa[1:]
                t.kalman._kf.x[self.n_devices - 1:] = 0.0
            else:
                if rank > 0 or any(self._distance(toa, s.toa_s) < 3 * self.same_source_s for s in self.tracks
                                   if s.kind == "speech"):
                    continue   # second peaks only refresh known sources; a talker's leak is no noise source
                t = self._new_track("noise", time_s)
                t.kalman.update(np.where(keep, tdoa, 0.0), keep.astype(float))
                t.confirmed_s = time_s
                t.quiet_activity = self.noise_quiet_activity + 0.1   # evidence that decays in the pauses
            t.n_hits += 1
            t.last_hit_s = time_s
            t.active_s += self.noise_every_frames * self.frame_period_s

    @staticmethod
    def _distance(a: np.ndarray, b: np.ndarray) -> float:
        """RMS over devices of the difference of two relative TOA vectors, seconds."""
        return float(np.sqrt(np.mean((a - b) ** 2)))

    @staticmethod
    def _gap(a: np.ndarray, b: np.ndarray) -> float:
        """Largest difference over devices of two relative TOA vectors, seconds ("every device within")."""
        return float(np.max(np.abs(a - b)))

    def _housekeeping(self, time_s: float) -> None:
        for t in list(self.tracks):
            if t.kind == "tentative":
                if t.hit_times_s and time_s - t.hit_times_s[0] > self.confirm_window_s:
                    self._end(t, time_s, "not confirmed")
            elif time_s - t.last_hit_s > self.forget_after_s:
                self._end(t, time_s, f"no hit for {self.forget_after_s:g} s")
        # a talker track on a noise source found in the pauses is that noise source (heard in speech frames too)
        for n in [t for t in self.tracks if t.quiet_origin and t.kind == "noise"]:
            n_toa = n.toa_s
            for t in [t for t in self.tracks if t.kind == "speech"]:
                if not within_but_one(t.toa_s - n_toa, NOISE_SAME_S)[0]:
                    continue
                # (a speech track with LOUDER_MIN_HITS speech hits: somebody spoke, first_speech_s is set)
                if t.n_speech_values >= LOUDER_MIN_HITS and n.n_quiet_values >= LOUDER_MIN_HITS and \
                        n.born_s > self.first_speech_s and self._far_louder(t.speech_value, n.quiet_value):
                    # the talker's own sound in the pauses (the room or the breath of the recording), found as a
                    # noise source: the talker's peaks are far higher when they speak (measured office's `m47`:
                    # the second talker's track went at their third turn, and the beam stayed on the first). Not
                    # a source heard before anybody spoke: a quiet noise source where a talker stands, as seen
                    # from the devices (the office's `m43`, dishes 20 dB below the talker)
                    self._end(n, time_s, f"the sound of talker {t.track_id} in the pauses (its peaks "
                                         f"{t.speech_value / max(n.quiet_value, 1e-12):.1f} times as high when "
                                         "the talker speaks)")
                    break
                self._end(t, time_s, f"merged into noise track {n.track_id} (the same source, heard in the "
                                     "pauses)")
        # merge duplicates of the same kind (the younger goes)
        confirmed = [t for t in self.tracks if t.kind != "tentative"]
        for a_i, a in enumerate(confirmed):
            for b in confirmed[a_i + 1:]:
                if a.kind == b.kind and b in self.tracks and a in self.tracks and \
                        self._distance(a.toa_s, b.toa_s) < self.same_source_s:
                    young = b if b.born_s >= a.born_s else a
                    if young is self.steered:
                        # the beam keeps its track, but with the older one's filter: a young track's TOA rate
                        # comes from a few peaks around its birth (`two_talkers`: 2 ms/s, which carried the
                        # beam 1 ms off its talker within 0.6 s of speech), the older one's from seconds of hits
                        old = a if young is b else b
                        young.take_filter(old)
                        if old.drift_rate_s_per_s is not None:
                            young.drift_rate_s_per_s = old.drift_rate_s_per_s.copy()
                        young = old
                    self._end(young, time_s, f"merged into track {(a if young is b else b).track_id}")

    def _steer(self, time_s: float, speech: bool) -> None:
        talkers = [t for t in self.tracks if t.kind == "speech"]
        current = self.steered if self.steered in talkers else None
        if current is None and self.steered is not None:
            reason = f"track {self.steered.track_id} is now labelled {self.steered.kind}"
            self.steered = None
        elif self._ghost_of is not None:
            reason = f"track {self._ghost_of[0]} was a ghost of track {self._ghost_of[1]}"
            self._from_id = self._ghost_of[0]
        elif self._steered_end is not None:   # the steered track ended (merged into a noise source, forgotten)
            reason = f"track {self._steered_end[0]} ended: {self._steered_end[1]}"
            self._from_id = self._steered_end[0]
        else:
            reason = ""
        self._ghost_of = None
        self._steered_end = None
        if not talkers:
            if reason:
                self.switches.append({"time_s": round(time_s, 3), "from": self._last_id, "to": -1, "reason": reason})
                self._from_id = -1   # the next switch comes from nothing steered
            return
        if self.target == "nearest":
            recent = [t for t in talkers if time_s - t.last_hit_s <= self.forget_after_s]
            d = self.target_device
            best = min(recent or talkers, key=lambda t: t.toa_s[d] - t.toa_s.mean())
            if best is not current:
                why = (f"track {best.track_id} is heard earliest at device {d}" if current is not None
                       else f"first talker track {best.track_id}")
                self._switch(current, best, time_s, reason or why)
            return
        best = max(talkers, key=lambda t: t.activity)
        if current is None:
            if best.activity > 0:
                self._switch(None, best, time_s, reason or f"first talker track {best.track_id}")
        elif best is not current and speech and best.activity > self.switch_ratio * current.activity \
                and best.miss_run < self._turn_frames:
            self._switch(current, best, time_s,
                         f"track {best.track_id} more active ({best.activity:.2f} vs {current.activity:.2f})")
        elif speech and current.miss_run >= self._turn_frames:
            # a turn: the steered talker has gone quiet and another talker is heard now
            heard = [t for t in talkers if t.miss_run == 0]
            new = max(heard, key=lambda t: t.fast_activity) if heard else None
            if new is not None and new.fast_activity > self.switch_ratio * current.fast_activity:
                self._switch(current, new, time_s,
                             f"track {new.track_id} heard, track {current.track_id} quiet for "
                             f"{current.miss_run * self.frame_period_s:.2f} s of speech")

    @property
    def _last_id(self) -> int:
        return self.switches[-1]["to"] if self.switches else -1

    def _switch(self, old: Track | None, new: Track, time_s: float, reason: str) -> None:
        from_id = self._from_id if old is None else old.track_id
        self._from_id = -1
        self.switches.append({"time_s": round(time_s, 3), "from": from_id, "to": new.track_id, "reason": reason})
        self.steered = new
