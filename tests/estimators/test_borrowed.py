"""The per-hop kernels take their array arguments ``borrowed`` (no reference counting inside the
call): same results, and nothing kept or leaked, in Python reference counts or in numba's allocator."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numba
import numpy as np

from estimators.numba_tools import borrowed

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@numba.njit
def _row_maxima(x, use_borrowed):
    """``max`` of every row of ``x``, through row views handed to a call (the pattern of the kernels)."""
    if use_borrowed:
        x = borrowed(x)
    out = np.empty(x.shape[0])
    for i in range(x.shape[0]):
        out[i] = _max(x[i, 1:])
    return out


@numba.njit
def _max(v):
    best = v[0]
    for k in range(1, v.shape[0]):
        best = max(best, v[k])
    return best


def test_borrowed_views_give_the_same_values_and_hold_no_reference():
    x = np.random.default_rng(0).standard_normal((5, 33))
    expected = x[:, 1:].max(axis=1)
    np.testing.assert_array_equal(_row_maxima(x, False), expected)
    before = sys.getrefcount(x)
    for _ in range(1000):
        np.testing.assert_array_equal(_row_maxima(x, True), expected)
    assert sys.getrefcount(x) == before


def test_per_hop_kernels_free_everything_they_allocate_and_keep_no_reference():
    """Hundreds of hops through StreamingStft, GccPhat, KalmanToa and DelayAndSum (both weightings,
    with a NaN stretch and an invalid device) with numba's allocation counters on: every allocation
    is freed, and the inputs and state arrays end with the reference counts they started with."""
    script = textwrap.dedent(
        """
        import sys
        import numpy as np
        from numba.core.runtime import rtsys
        import beamform, estimators

        m, fs, frame, hop = 6, 16000.0, 512, 128
        rng = np.random.default_rng(3)
        audio = rng.standard_normal((hop * 300, m)).astype(np.float32)
        audio[4000:4100, 2] = np.nan
        valid = np.ones(m, bool)
        for weighting in ("equal", "adaptive"):
            stft = beamform.StreamingStft(m, frame_samples=frame, hop_samples=hop)
            gcc = estimators.GccPhat(m, n_fft=frame, sample_rate_hz=fs, max_tdoa_s=0.01)
            kalman = estimators.KalmanToa(m, frame_period_s=hop / fs)
            das = beamform.DelayAndSum(m, frame_samples=frame, hop_samples=hop, sample_rate_hz=fs,
                                       weighting=weighting)
            def hop_once(block):
                spectra = stft.process(block)
                tdoa_s, confidence = gcc.process(spectra, valid=valid)
                toa_s = kalman.update(tdoa_s, confidence)
                return das.process_spectra(spectra, toa_s, valid=valid)
            for k in range(20):  # warm up (compile, first allocations)
                hop_once(audio[k * hop:(k + 1) * hop])
            kept = [audio, valid, gcc._work, gcc._layout, kalman._buffers, kalman._params, *das._process_args,
                    *stft._kernel_args]
            refs = [sys.getrefcount(a) for a in kept]
            start = rtsys.get_allocation_stats()
            for k in range(20, 300):
                valid[4] = k % 50 < 40  # a device that drops out and comes back
                hop_once(audio[k * hop:(k + 1) * hop])
            end = rtsys.get_allocation_stats()
            assert [sys.getrefcount(a) for a in kept] == refs, weighting
            assert end.alloc - start.alloc == end.free - start.free, (weighting, start, end)
            assert end.mi_alloc - start.mi_alloc == end.mi_free - start.mi_free, (weighting, start, end)
            assert end.alloc > start.alloc, "the counters must see the kernels' allocations"
        print("ok")
        """
    )
    env = dict(os.environ, NUMBA_NRT_STATS="1", PYTHONPATH=ROOT)
    run = subprocess.run([sys.executable, "-c", script], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.strip().endswith("ok")
