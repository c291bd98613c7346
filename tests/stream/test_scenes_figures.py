"""``benchmarks/scenes.py``'s steering figures: a beam on a source with every device but one."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from scenes import within_but_one  # noqa: E402  (a script of benchmarks/, importable by its folder)

W = 2.5e-4


def test_every_device_but_one_within_counts_any_odd_device_and_not_two():
    err = np.array([
        [0.0, 1e-4, -1e-4, 5e-5, 0.0, 1e-4],        # every device within
        [0.0, 1e-4, -1e-4, 3e-3, 0.0, 1e-4],        # device 3 on another peak
        [0.0, -2e-3, -2.1e-3, -1.9e-3, -2e-3, -2e-3],   # device 0 odd: the others agree up to a common shift
        [0.0, 1e-4, 2e-3, 3e-3, 0.0, 1e-4],         # two devices off
        [0.0, 3e-4, -3e-4, 3e-4, -3e-4, 0.0],       # a spread of 0.6 ms without any one device: not within
    ])
    assert within_but_one(err, W).tolist() == [True, True, True, False, False]


def test_fewer_than_five_devices_need_every_device():
    err = np.array([[0.0, 1e-4, 3e-3, 0.0], [0.0, 1e-4, -1e-4, 2e-4]])
    assert within_but_one(err, W).tolist() == [False, True]
