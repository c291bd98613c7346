"""Scores a run against a fixture's ground truth: TOA error (eq. 18), enhancement (SI-SDR, STOI,
SAR, SSARA eqs. 19-21), the best single device, and delay-and-sum steered by the true TOA (the pipeline's
own stages, driven by :func:`stream.pipeline.steer_aligned`)."""
from __future__ import annotations

import dataclasses
import logging
from typing import Any

import numpy as np

from . import metrics
from ..config import EngineConfig
from .fixture import Fixture
from ..pipeline import Pipeline, make_estimator, steer_aligned

log = logging.getLogger(__name__)

ALIGN_MAX_LAG_S = 0.05   # the reference is aligned to the output within ±50 ms before scoring


def enhancement_scores(estimate: np.ndarray, reference: np.ndarray, *, sample_rate_hz: float,
                       sar: bool = True) -> dict[str, float]:
    """SI-SDR, STOI, SAR and SSARA (eqs. 20-21; skipped when ``sar`` is False: they cost a 512-tap
    BSS-eval projection per 500 ms segment) of ``estimate`` against ``reference`` after lag alignment."""
    n = min(len(estimate), len(reference))
    if n < sample_rate_hz * 0.5:
        return {"si_sdr_db": float("nan"), "stoi": float("nan"), "sar_db": float("nan"), "ssara_db": float("nan")}
    est, lag = metrics.align_to_reference(estimate[:n], reference[:n],
                                          max_lag_samples=int(ALIGN_MAX_LAG_S * sample_rate_hz))
    ref = reference[:n]
    return {
        "si_sdr_db": float(metrics.si_sdr_db(est, ref)),
        "stoi": float(metrics.stoi(est, ref, sample_rate_hz=sample_rate_hz)),
        "sar_db": float(metrics.sar_db(est, ref)) if sar else float("nan"),
        "ssara_db": float(metrics.ssara_db(est, ref, sample_rate_hz=sample_rate_hz)) if sar else float("nan"),
        "lag_samples": int(lag),
    }


def offline_toa(name: str, config: EngineConfig, tdoa_s: np.ndarray, confidence: np.ndarray,
                offsets_samples: np.ndarray) -> np.ndarray:
    """Re-run another estimator on the recorded TDOA frames; returns total relative TOA (n_frames, M)."""
    n_dev = offsets_samples.shape[1]
    est = make_estimator(dataclasses.replace(config, estimator=name), n_dev)
    fs = config.working_rate_hz
    out = np.zeros((len(tdoa_s), n_dev))
    last = offsets_samples[0]
    for k in range(len(tdoa_s)):
        delta = offsets_samples[k] - last
        last = offsets_samples[k]
        if delta.any():
            est.shift(-(delta / fs))
        out[k] = est.update(tdoa_s[k], confidence[k]) + offsets_samples[k] / fs
    return out


def evaluate_run(pipeline: Pipeline, fixture: Fixture, device_index: list[int]) -> dict[str, Any]:
    """Metrics of a finished run against the fixture's truth.

    ``device_index[k]`` is the fixture device index of the pipeline's device ``k`` (devices whose
    files could not be opened are not in the pipeline).
    """
    cfg = pipeline.config
    fs = cfg.working_rate_hz
    s = pipeline.state
    result: dict[str, Any] = {}
    time_s, toa_s, gated = pipeline.toa_track()
    offsets = np.vstack([np.asarray(o) for o in s.offsets]) if getattr(s, "offsets", None) else None
    if len(time_s) and fixture.truth_toa is not None:
        truth = fixture.truth_toa_at(time_s)[:, device_index]
        truth = truth - truth[:, :1]
        # score frames inside the truth's time range and where the reference is not silent
        t_true, _ = fixture.load_truth_toa()
        inside = (time_s >= t_true[0]) & (time_s <= t_true[-1])
        toa_report = {}
        tdoa = np.vstack(s.tdoa_s) if s.tdoa_s and len(s.tdoa_s[0]) else None
        conf = np.vstack(s.confidence) if tdoa is not None else None
        # the run's own estimator first (the tracker's steered TOA included), then the paper's, re-run offline
        for name in dict.fromkeys((cfg.estimator, "subset", "pinv", "kalman", "smoother")):
            if name == cfg.estimator:
                est = toa_s
            elif tdoa is not None and offsets is not None:
                est = offline_toa(name, cfg, tdoa, conf, offsets)
            else:
                continue
            err = est[inside, 1:] - truth[inside, 1:]
            if name == "smoother" and name != cfg.estimator:
                # re-run offline, its output at frame t describes frame t - lag (the engine's own record is
                # stamped with the frame it describes)
                lag = cfg.smoother_lag_frames
                err = est[inside][lag:, 1:] - truth[inside][:-lag or None, 1:]
            rmse_s = float(np.sqrt(np.mean(np.sum(err ** 2, axis=1)))) if len(err) else float("nan")
            toa_report[name] = {
                "rmse_s": rmse_s,                                    # eq. (18): norm over devices
                "rmse_samples": rmse_s * fs,
                "rmse_per_element_samples": float(np.sqrt(np.mean(err ** 2)) * fs) if len(err) else float("nan"),
                "median_abs_error_samples": float(np.median(np.abs(err)) * fs) if len(err) else float("nan"),
            }
        result["toa"] = toa_report
    if fixture.truth_clean is not None:
        clean, rate = fixture.load_clean()
        if rate != fs:
            import soxr
            clean = soxr.resample(clean, rate, fs).astype(np.float32)
        enhanced = pipeline.enhanced_signal()
        scores = {"engine": enhancement_scores(enhanced, clean, sample_rate_hz=fs)}
        if s.aligned_input:
            x = np.vstack(s.aligned_input)
            valid = np.vstack(s.valid)
            singles = {}
            for d in range(x.shape[1]):
                singles[str(d)] = enhancement_scores(x[:, d], clean, sample_rate_hz=fs, sar=False)
            scores["single_devices"] = singles
            best = max(singles, key=lambda k: np.nan_to_num(singles[k]["si_sdr_db"], nan=-np.inf))
            scores["best_single_device"] = {"device": int(best), **enhancement_scores(x[:, int(best)], clean,
                                                                                      sample_rate_hz=fs)}
            fine_est = toa_s - offsets / fs if offsets is not None else toa_s
            other = "adaptive" if cfg.weighting == "equal" else "equal"
            scores[f"estimated_toa_{other}_weights"] = enhancement_scores(
                steer_aligned(cfg, x, fine_est, weighting=other, valid=valid), clean, sample_rate_hz=fs,
                sar=False)
            if fixture.truth_toa is not None and offsets is not None:
                centre = (np.arange(len(x) // cfg.hop_samples) * cfg.hop_samples + cfg.hop_samples
                          - cfg.frame_samples / 2) / fs
                truth = fixture.truth_toa_at(centre)[:, device_index]
                truth = truth - truth[:, :1]
                fine_true = truth - offsets[: len(truth)] / fs
                for weighting in ("equal", "adaptive"):
                    scores[f"true_toa_async_{weighting}"] = enhancement_scores(
                        steer_aligned(cfg, x, fine_true, weighting=weighting, valid=valid), clean,
                        sample_rate_hz=fs, sar=False)
        if fixture.truth_sync is not None:
            sync, sync_rate = fixture.load_sync()
            clean_sync, _ = fixture.load_clean_sync()
            if sync_rate == fs:
                sync = sync[:, device_index]
                t_sync, toa_sync = fixture.load_sync_toa()
                n_blocks = len(sync) // cfg.hop_samples
                centre = (np.arange(n_blocks) * cfg.hop_samples + cfg.hop_samples - cfg.frame_samples / 2) / fs
                toa_true = np.stack([np.interp(centre, t_sync, toa_sync[:, d]) for d in device_index], axis=1)
                toa_true -= toa_true[:, :1]
                for weighting in ("equal", "adaptive"):
                    scores[f"true_toa_sync_{weighting}"] = enhancement_scores(
                        steer_aligned(cfg, sync.astype(np.float32), toa_true, weighting=weighting),
                        clean_sync, sample_rate_hz=fs)
        result["enhancement"] = scores
    return result
