"""Objective metrics for TOA tracks and beamformed speech (TOA paper eqs. 18-21).

All functions are pure. Signals are 1-D ``(n_samples,)`` arrays at a common sample rate; the
reference is the clean target (close-talk or dry source), the estimate the processed output.

Degenerate inputs are data, not exceptions: a silent (all-zero or non-finite) reference or estimate
gives ``nan`` and a logged warning; signals of different lengths are cropped to the common length.

SAR of a single source
----------------------
BSS Eval (Vincent et al. 2006) decomposes ``y = s_target + e_interf + e_noise + e_artif`` (eq. 19
generalised). With one reference source and no noise reference, ``e_interf = e_noise = 0``, so
``SAR = 10 log10(||s_target||^2 / ||e_artif||^2)`` equals the SDR, where ``s_target`` is the
reference filtered by the least-squares FIR distortion filter of ``filter_length`` taps (512 in
BSS Eval v3, the toolbox used by the paper, eq. 20). :func:`sar_db` is therefore :func:`sdr_db`;
both use ``fast_bss_eval.sdr``.
"""
from __future__ import annotations

import logging
import warnings

import numpy as np
import scipy.fft

__all__ = [
    "align_to_reference",
    "si_sdr_db",
    "sdr_db",
    "sar_db",
    "stoi",
    "speech_segments",
    "segmental_sar_db",
    "ssara_db",
    "toa_rmse_s",
    "toa_rmse_per_mic_s",
]

logger = logging.getLogger(__name__)

_CLAMP_DB = 150.0  # fast_bss_eval fails on an exact (infinite-SDR) match without a clamp


def _as_1d(x: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 2 and 1 in a.shape:
        a = a.reshape(-1)
    if a.ndim != 1:
        raise ValueError(f"{name} must be 1-D (n_samples,), got shape {a.shape}")
    return a


def _common(estimate: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    est = _as_1d(estimate, "estimate")
    ref = _as_1d(reference, "reference")
    n = min(est.size, ref.size)
    if est.size != ref.size:
        logger.debug("cropping estimate (%d) and reference (%d) to %d samples", est.size, ref.size, n)
    return est[:n], ref[:n]


def _degenerate(est: np.ndarray, ref: np.ndarray, what: str) -> bool:
    """True (and a warning is logged) when a metric is undefined for these signals."""
    for name, sig in (("reference", ref), ("estimate", est)):
        if sig.size == 0:
            logger.warning("%s: empty %s; returning nan", what, name)
            return True
        if not np.all(np.isfinite(sig)):
            logger.warning("%s: non-finite samples in the %s; returning nan", what, name)
            return True
        if not np.any(sig != 0.0):
            logger.warning("%s: the %s is silent (all zeros); returning nan", what, name)
            return True
    return False


def align_to_reference(
    estimate: np.ndarray, reference: np.ndarray, *, max_lag_samples: int
) -> tuple[np.ndarray, int]:
    """Shift an estimate by the integer lag that maximises its cross-correlation with a reference.

    Parameters
    ----------
    estimate : ndarray, shape (n_est,)
        Signal to align, e.g. a beamformer output that lags the reference.
    reference : ndarray, shape (n_ref,)
        Reference signal.
    max_lag_samples : int
        Search ``lag`` in ``-max_lag_samples..max_lag_samples`` samples.

    Returns
    -------
    aligned_estimate : ndarray, shape (n_ref,), float64
        ``aligned[n] = estimate[n + lag]``, zero-padded where out of range, reference length.
    lag_samples : int
        Samples by which the estimate lags the reference (positive: the estimate is late).
        ``0`` with a logged warning if either signal is silent.
    """
    if int(max_lag_samples) != max_lag_samples or max_lag_samples < 0:
        raise ValueError(f"{max_lag_samples=} must be a non-negative integer (samples)")
    est = _as_1d(estimate, "estimate")
    ref = _as_1d(reference, "reference")
    lag = 0
    if not _degenerate(est, ref, "align_to_reference"):
        # r[l] = sum_n est[n + l] ref[n], via FFT (full linear correlation).
        n_fft = scipy.fft.next_fast_len(est.size + ref.size - 1, real=True)
        r = scipy.fft.irfft(
            scipy.fft.rfft(est, n_fft) * np.conj(scipy.fft.rfft(ref, n_fft)), n_fft
        )
        lags = np.arange(-int(max_lag_samples), int(max_lag_samples) + 1)
        lags = lags[(lags > -ref.size) & (lags < est.size)]
        lag = int(lags[np.argmax(r[lags % n_fft])])
    aligned = np.zeros(ref.size)
    lo = max(0, -lag)
    hi = min(ref.size, est.size - lag)
    if hi > lo:
        aligned[lo:hi] = est[lo + lag : hi + lag]
    return aligned, lag


def si_sdr_db(estimate: np.ndarray, reference: np.ndarray) -> float:
    """Scale-invariant signal-to-distortion ratio (Le Roux et al. 2019), in dB.

    ``alpha = <est, ref> / ||ref||^2``, ``SI-SDR = 10 log10(||alpha ref||^2 / ||alpha ref - est||^2)``.
    No mean removal and no time alignment: align first (:func:`align_to_reference`).

    Parameters
    ----------
    estimate, reference : ndarray, shape (n_samples,)
        Cropped to the common length.

    Returns
    -------
    float
        SI-SDR in dB; ``nan`` (with a warning) for a silent signal, ``inf`` for an exact match.
    """
    est, ref = _common(estimate, reference)
    if _degenerate(est, ref, "si_sdr_db"):
        return float("nan")
    alpha = np.dot(est, ref) / np.dot(ref, ref)
    target = alpha * ref
    err = est - target
    num, den = np.dot(target, target), np.dot(err, err)
    if den == 0.0:
        return float("inf")
    if num == 0.0:
        return float("-inf")
    return float(10.0 * np.log10(num / den))


def sdr_db(estimate: np.ndarray, reference: np.ndarray, *, filter_length: int = 512) -> float:
    """BSS Eval signal-to-distortion ratio of one source, in dB (``fast_bss_eval.sdr``).

    The reference is allowed a ``filter_length``-tap FIR distortion before the error is measured.

    Parameters
    ----------
    estimate, reference : ndarray, shape (n_samples,)
        Cropped to the common length; must be at least ``filter_length`` samples.
    filter_length : int, optional
        Distortion filter length in samples (512 in BSS Eval v3).

    Returns
    -------
    float
        SDR in dB (clamped to +-150 dB); ``nan`` with a warning for silent or too short signals.
    """
    if int(filter_length) != filter_length or filter_length < 1:
        raise ValueError(f"{filter_length=} must be a positive integer (samples)")
    est, ref = _common(estimate, reference)
    if _degenerate(est, ref, "sdr_db"):
        return float("nan")
    if est.size < filter_length:
        logger.warning("sdr_db: %d samples is shorter than filter_length=%d; returning nan", est.size, filter_length)
        return float("nan")
    import fast_bss_eval

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        try:
            val = fast_bss_eval.sdr(ref[None, :], est[None, :], filter_length=int(filter_length), clamp_db=_CLAMP_DB)
        except np.linalg.LinAlgError:
            logger.warning("sdr_db: singular reference statistics (e.g. a pure tone); returning nan")
            return float("nan")
    return float(np.asarray(val).reshape(-1)[0])


def sar_db(estimate: np.ndarray, reference: np.ndarray, *, filter_length: int = 512) -> float:
    """Sources-to-artifacts ratio of one source (TOA paper eq. 20), in dB.

    With a single reference and no interference or noise components (as in the paper),
    ``e_interf = e_noise = 0`` and BSS Eval's SAR equals its SDR, so this is :func:`sdr_db`.

    Parameters
    ----------
    estimate, reference : ndarray, shape (n_samples,)
    filter_length : int, optional
        Distortion filter length in samples (512 in BSS Eval v3).

    Returns
    -------
    float
        SAR in dB.
    """
    return sdr_db(estimate, reference, filter_length=filter_length)


def stoi(estimate: np.ndarray, reference: np.ndarray, *, sample_rate_hz: float, extended: bool = False) -> float:
    """Short-time objective intelligibility (Taal et al. 2011) via ``pystoi``.

    Parameters
    ----------
    estimate, reference : ndarray, shape (n_samples,)
        Cropped to the common length (pystoi resamples to 10 kHz internally).
    sample_rate_hz : float
        Sample rate in hertz.
    extended : bool, optional
        Extended STOI (Jensen & Taal 2016).

    Returns
    -------
    float
        STOI in ``[0, 1]`` (ESTOI may be slightly negative); ``nan`` for a silent signal.
    """
    if not sample_rate_hz > 0:
        raise ValueError(f"{sample_rate_hz=} must be a positive number of hertz")
    est, ref = _common(estimate, reference)
    if _degenerate(est, ref, "stoi"):
        return float("nan")
    import pystoi

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return float(pystoi.stoi(ref, est, int(round(sample_rate_hz)), extended=extended))


def _segment_bounds(n_samples: int, *, sample_rate_hz: float, segment_s: float) -> np.ndarray:
    if not sample_rate_hz > 0:
        raise ValueError(f"{sample_rate_hz=} must be a positive number of hertz")
    seg = int(round(segment_s * sample_rate_hz))
    if seg < 1:
        raise ValueError(f"{segment_s=} must be at least one sample at {sample_rate_hz=}")
    starts = np.arange(0, n_samples - seg + 1, seg)  # whole segments only
    return np.stack([starts, starts + seg], axis=1)


def speech_segments(
    reference: np.ndarray,
    *,
    sample_rate_hz: float,
    segment_s: float = 0.5,
    threshold_db: float = -30.0,
) -> np.ndarray:
    """Label non-overlapping segments of the reference as speech by energy.

    The paper labelled its 500 ms segments by hand. Here a segment is speech when its energy is
    within ``threshold_db`` of the loudest segment of the reference
    (``10 log10(E_k / max_k E_k) >= threshold_db``). Only whole segments are labelled; a trailing
    partial segment is dropped.

    Parameters
    ----------
    reference : ndarray, shape (n_samples,)
        Clean reference signal.
    sample_rate_hz : float
        Sample rate in hertz.
    segment_s : float, optional
        Segment length in seconds (0.5 s as in the paper).
    threshold_db : float, optional
        Energy threshold relative to the loudest segment, in dB (negative).

    Returns
    -------
    ndarray, shape (n_segments,), bool
        ``n_segments = n_samples // round(segment_s * sample_rate_hz)``; all ``False`` when the
        reference is silent.
    """
    ref = _as_1d(reference, "reference")
    bounds = _segment_bounds(ref.size, sample_rate_hz=sample_rate_hz, segment_s=segment_s)
    if bounds.size == 0:
        return np.zeros(0, dtype=bool)
    energy = np.array([np.dot(ref[a:b], ref[a:b]) for a, b in bounds])
    peak = energy.max() if np.all(np.isfinite(energy)) else np.nan
    if not peak > 0:
        logger.warning("speech_segments: the reference is silent or non-finite; no speech segments")
        return np.zeros(len(bounds), dtype=bool)
    with np.errstate(divide="ignore"):
        rel_db = 10.0 * np.log10(energy / peak)
    return rel_db >= threshold_db


def segmental_sar_db(
    estimate: np.ndarray,
    reference: np.ndarray,
    *,
    sample_rate_hz: float,
    segment_s: float = 0.5,
    threshold_db: float = -30.0,
    filter_length: int = 512,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Segmental SAR (SSAR): eq. (20) on consecutive non-overlapping segments.

    Parameters
    ----------
    estimate, reference : ndarray, shape (n_samples,)
        Aligned signals, cropped to the common length.
    sample_rate_hz : float
        Sample rate in hertz.
    segment_s : float, optional
        Segment length in seconds (0.5 s as in the paper).
    threshold_db : float, optional
        Speech labelling threshold, see :func:`speech_segments`.
    filter_length : int, optional
        BSS Eval distortion filter length in samples.

    Returns
    -------
    segment_start_s : ndarray, shape (n_segments,), seconds
    sar_db : ndarray, shape (n_segments,), dB
        ``nan`` for segments where the SAR is undefined (silent reference or estimate).
    is_speech : ndarray, shape (n_segments,), bool
    """
    est, ref = _common(estimate, reference)
    bounds = _segment_bounds(ref.size, sample_rate_hz=sample_rate_hz, segment_s=segment_s)
    is_speech = speech_segments(ref, sample_rate_hz=sample_rate_hz, segment_s=segment_s, threshold_db=threshold_db)
    fl = min(int(filter_length), int(round(segment_s * sample_rate_hz)))
    sar = np.full(len(bounds), np.nan)
    for k, (a, b) in enumerate(bounds):
        e, r = est[a:b], ref[a:b]
        if np.any(e != 0) and np.any(r != 0):
            sar[k] = sar_db(e, r, filter_length=fl)
    return bounds[:, 0] / float(sample_rate_hz), sar, is_speech


def ssara_db(
    estimate: np.ndarray,
    reference: np.ndarray,
    *,
    sample_rate_hz: float,
    segment_s: float = 0.5,
    threshold_db: float = -30.0,
    filter_length: int = 512,
) -> float:
    """Segmental SAR by arithmetic mean (SSARA), TOA paper eq. (21), in dB.

    ``SSARA = 10 log10( (1/K) sum_k 10^(SAR_k / 10) )`` over the K speech segments
    (:func:`speech_segments`) with a defined SAR.

    Parameters
    ----------
    estimate, reference : ndarray, shape (n_samples,)
    sample_rate_hz : float
    segment_s, threshold_db : float, optional
    filter_length : int, optional

    Returns
    -------
    float
        SSARA in dB; ``nan`` (with a warning) when no speech segment has a defined SAR.
    """
    _, sar, is_speech = segmental_sar_db(
        estimate,
        reference,
        sample_rate_hz=sample_rate_hz,
        segment_s=segment_s,
        threshold_db=threshold_db,
        filter_length=filter_length,
    )
    use = is_speech & np.isfinite(sar)
    if not np.any(use):
        logger.warning("ssara_db: no speech segment with a defined SAR; returning nan")
        return float("nan")
    return float(10.0 * np.log10(np.mean(10.0 ** (sar[use] / 10.0))))  # eq. (21)


def _toa_errors(toa_est_s: np.ndarray, toa_true_s: np.ndarray) -> np.ndarray:
    est = np.asarray(toa_est_s, dtype=np.float64)
    true = np.asarray(toa_true_s, dtype=np.float64)
    if est.ndim == 1:
        est = est[None, :]
    if true.ndim == 1:
        true = true[None, :]
    true = np.broadcast_to(true, est.shape) if true.shape[0] == 1 else true
    if est.shape != true.shape or est.ndim != 2:
        raise ValueError(f"{est.shape=} and {true.shape=} must both be (n_frames, n_mics)")
    if est.shape[1] < 2:
        raise ValueError(f"{est.shape=} needs n_mics >= 2 (element 0 is the reference, always 0)")
    return est[:, 1:] - true[:, 1:]


def toa_rmse_s(toa_est_s: np.ndarray, toa_true_s: np.ndarray) -> float:
    """RMS error of relative TOA vectors over frames (TOA paper eq. 18), in seconds.

    ``RMSE = sqrt( (1/T) sum_t ||tau_hat_t - tau_t||^2 )``, the Euclidean norm of the TOA error
    vector over the devices (element 0, the reference, always 0, is left out), averaged over the
    ``T`` frames; frames with any non-finite entry are skipped. For the per-device RMSE (the norm
    divided by ``sqrt(M - 1)`` when all devices err alike) see :func:`toa_rmse_per_mic_s`.

    Parameters
    ----------
    toa_est_s : ndarray, shape (n_frames, n_mics), seconds
    toa_true_s : ndarray, shape (n_frames, n_mics) or (n_mics,), seconds

    Returns
    -------
    float
        RMSE in seconds; ``nan`` with a warning if no frame is finite.
    """
    err = _toa_errors(toa_est_s, toa_true_s)
    keep = np.all(np.isfinite(err), axis=1)
    if not np.any(keep):
        logger.warning("toa_rmse_s: no finite frame; returning nan")
        return float("nan")
    return float(np.sqrt(np.mean(np.sum(err[keep] ** 2, axis=1))))  # eq. (18)


def toa_rmse_per_mic_s(toa_est_s: np.ndarray, toa_true_s: np.ndarray) -> np.ndarray:
    """RMS error of each relative TOA element over frames, in seconds.

    Parameters
    ----------
    toa_est_s : ndarray, shape (n_frames, n_mics), seconds
    toa_true_s : ndarray, shape (n_frames, n_mics) or (n_mics,), seconds

    Returns
    -------
    ndarray, shape (n_mics,), seconds
        Element 0 is 0 (reference); ``nan`` for a device with no finite frame.
    """
    err = _toa_errors(toa_est_s, toa_true_s)
    fin = np.isfinite(err)
    n = fin.sum(axis=0)
    sq = np.where(fin, err, 0.0) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        rmse = np.sqrt(sq.sum(axis=0) / n)
    return np.concatenate([[0.0], np.where(n > 0, rmse, np.nan)])
