"""Online beamforming in the STFT domain. Imports numpy, scipy and numba (the per-hop work runs in
compiled kernels whose FFTs use rocket-fft's numba overloads of ``np.fft``).

- :mod:`beamform.stft`: streaming STFT analysis / weighted-overlap-add synthesis (and batch twins).
- :mod:`beamform.das`: online weighted delay-and-sum (TOA paper eqs. 7-8).
"""
from .das import DelayAndSum, delay_and_sum
from .stft import StreamingIstft, StreamingStft, analysis_window, dual_window, istft, stft

__all__ = [
    "DelayAndSum",
    "delay_and_sum",
    "StreamingStft",
    "StreamingIstft",
    "analysis_window",
    "dual_window",
    "stft",
    "istft",
]
