"""Delay estimation: GCC-PHAT over all microphone pairs and relative-TOA estimators.

Imports numpy, scipy, filterpy and numba: the per-hop work of GCC-PHAT and the Kalman update runs in
compiled kernels (GCC-PHAT's inverse FFTs through rocket-fft's numba overloads of ``np.fft``); nothing from
:mod:`stream`. Conventions (units, signs, pair order) are stated once in :mod:`estimators.conventions`.
"""
from .conventions import SPEED_OF_SOUND_M_S, pair_matrix, pairs, ppm_to_ratio, s_to_samples, samples_to_s
from .gcc import GccPhat, gcc_phat, gcc_phat_spectra
from .toa import FixedLagKalmanToa, KalmanToa, PinvToa, SubsetToa, ToaEstimator
from .multipeak import NoiseAwareGcc
from .drift import DriftMeter
from .tracks import SourceTracker, Track, within_but_one
from .chirps import ChirpDetector, ChirpTdoas, detect_chirps, extract_tdoas, gcc_phat_delays, linear_chirp, matched_filter
from .hybrid_tdoa import (CalibrationResult, CrlbResult, HybridTdoaProblem, MicFrameScene, NoiseLevels, Scene,
                          RejectedMeasurement, crlb, estimate_noise_levels, mic_frame_error, random_initial_scene,
                          simulate_problem, to_mic_frame, without_rejected)
from .hybrid_tdoa import solve as solve_hybrid_tdoa
from .geometry import GEOMETRY_FORMAT, ArrayPlacement, Geometry, load_geometry
from .multi_array import (ArrayPose, CalibrationInputError, MultiArrayCalibration, calibrate_arrays,
                          calibrate_from_locations, localization_covariance, localize_spherical_ls, refine_mle,
                          rigid_body_ransac, rotation_error_deg, translation_angle_error_deg)

__all__ = [
    "within_but_one",
    "ArrayPlacement",
    "Geometry",
    "GEOMETRY_FORMAT",
    "load_geometry",
    "RejectedMeasurement",
    "without_rejected",
    "ArrayPose",
    "CalibrationInputError",
    "MultiArrayCalibration",
    "calibrate_arrays",
    "calibrate_from_locations",
    "localization_covariance",
    "localize_spherical_ls",
    "refine_mle",
    "rigid_body_ransac",
    "rotation_error_deg",
    "translation_angle_error_deg",
    "SPEED_OF_SOUND_M_S",
    "pair_matrix",
    "pairs",
    "ppm_to_ratio",
    "s_to_samples",
    "samples_to_s",
    "GccPhat",
    "gcc_phat",
    "gcc_phat_spectra",
    "ToaEstimator",
    "SubsetToa",
    "PinvToa",
    "KalmanToa",
    "FixedLagKalmanToa",
    "NoiseAwareGcc",
    "DriftMeter",
    "SourceTracker",
    "Track",
    "ChirpDetector",
    "ChirpTdoas",
    "detect_chirps",
    "extract_tdoas",
    "gcc_phat_delays",
    "linear_chirp",
    "matched_filter",
    "CalibrationResult",
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
    "to_mic_frame",
    "solve_hybrid_tdoa",
]
