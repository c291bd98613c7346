"""Delay estimation: GCC-PHAT over all microphone pairs and relative-TOA estimators.

Imports only numpy, scipy and filterpy. Conventions (units, signs, pair order) are stated once in
:mod:`estimators.conventions`.
"""
from .conventions import SPEED_OF_SOUND_M_S, pair_matrix, pairs, ppm_to_ratio, s_to_samples, samples_to_s
from .gcc import GccPhat, gcc_phat, gcc_phat_spectra
from .toa import FixedLagKalmanToa, KalmanToa, PinvToa, SubsetToa

__all__ = [
    "SPEED_OF_SOUND_M_S",
    "pair_matrix",
    "pairs",
    "ppm_to_ratio",
    "s_to_samples",
    "samples_to_s",
    "GccPhat",
    "gcc_phat",
    "gcc_phat_spectra",
    "SubsetToa",
    "PinvToa",
    "KalmanToa",
    "FixedLagKalmanToa",
]
