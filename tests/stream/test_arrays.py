"""``adhoc-array calibrate --method multi-array``: two asynchronous 8-mic arrays hear noise probes (free field,
fractional delays, sensor noise); their relative pose comes back from the recordings alone."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import soundfile as sf

from stream.arrays import detect_probes, match_probes
from stream.cli import main
from stream.geometry import load_geometry

FS = 48000
C = 343.0
CUBE = 0.4 * np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) - 0.2


def _yaw(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def _simulate(folder: Path, *, n_probes: int = 20, seed: int = 0, yaw_deg: float = 90.0,
              t_m=(3.0, 3.0, 0.0), offset_s: float = 0.2137, corrupt_channels: bool = False) -> Path:
    """Array A at the origin, array B at ``t_m`` turned by ``yaw_deg``; B's recording starts ``offset_s`` later.
    Probes: 0.15 s white-noise bursts (up to 6 kHz) every 0.5 s at random places between the arrays."""
    rng = np.random.default_rng(seed)
    R, t = _yaw(yaw_deg), np.asarray(t_m)
    mics = [CUBE, CUBE @ R.T + t]                       # global positions
    probes = np.c_[rng.uniform(-0.5, 3.5, n_probes), rng.uniform(-0.5, 3.5, n_probes), rng.uniform(-1.5, 2.0, n_probes)]
    n = int((0.5 * n_probes + 1.5) * FS)
    f = np.fft.rfftfreq(16384, 1 / FS)
    out = []
    for k, m in enumerate(mics):
        x = np.zeros((n, len(m)))
        for p, src in enumerate(probes):
            burst = rng.standard_normal(int(0.15 * FS))
            spec = np.fft.rfft(burst, 16384) * (f < 10000)
            t0 = 0.5 + 0.5 * p - (offset_s if k else 0.0)
            for i, mic in enumerate(m):
                r = np.linalg.norm(src - mic)
                delay = (t0 + r / C) * FS
                i0 = int(np.floor(delay))
                y = np.fft.irfft(spec * np.exp(-2j * np.pi * f * (delay - i0) / FS), 16384) / r
                stop = min(n, i0 + 16384)
                x[i0:stop, i] += y[:stop - i0]
        x += 1e-3 * rng.standard_normal(x.shape)
        out.append(folder / f"array{k}.wav")
        sf.write(out[-1], (0.5 * x / np.abs(x).max()).astype(np.float32), FS, subtype="FLOAT")
    mics_toml = lambda a: "[" + ", ".join(f"[{v[0]:.4f}, {v[1]:.4f}, {v[2]:.4f}]" for v in a) + "]"  # noqa: E731
    (folder / "arrays.toml").write_text(
        "sigma_tdoa_s = 5e-6\n"
        + "".join(f'[[array]]\nname = "{nm}"\nfile = "{p.name}"\nmics_m = {mics_toml(CUBE[:-1] if corrupt_channels and k else CUBE)}\n\n'
                  for k, (nm, p) in enumerate(zip(["table", "shelf"], out))))
    return folder / "arrays.toml"


def test_the_pose_of_a_second_array_comes_back_from_its_recording(tmp_path, capsys):
    arrays = _simulate(tmp_path)
    assert main(["calibrate", "--method", "multi-array", "--arrays", str(arrays), "--out", str(tmp_path / "out")]) == 0
    shown = capsys.readouterr().out
    res = json.loads((tmp_path / "out" / "arrays.json").read_text())
    assert res["n_probes"] == 20 and res["converged"]
    shelf = res["arrays"][1]
    R = np.asarray(shelf["rotation_matrix"])
    angle = np.rad2deg(np.arccos(np.clip((np.trace(R.T @ _yaw(90.0)) - 1) / 2, -1, 1)))
    assert angle < 2.0, shelf                                       # degrees
    assert np.linalg.norm(np.asarray(shelf["translation_m"]) - [3, 3, 0]) < 0.1, shelf   # metres
    assert all(s < 0.1 for s in shelf["translation_std_m"])
    assert (tmp_path / "out" / "arrays.png").stat().st_size > 10_000
    assert "shelf" in shown and "yaw" in shown
    # the same poses as the stream's geometry object: every mic a device, each array placed
    g = load_geometry(tmp_path / "out" / "geometry.json")
    assert g.device_names[:9] == ("table.1", "table.2", "table.3", "table.4", "table.5", "table.6", "table.7",
                                  "table.8", "shelf.1") and [a.name for a in g.arrays] == ["table", "shelf"]
    np.testing.assert_allclose(g.arrays[1].rotation_matrix, R)
    np.testing.assert_allclose(g.mic_positions_m()[8:], CUBE @ R.T + np.asarray(shelf["translation_m"]), atol=1e-9)
    assert np.isnan(g.offsets_s[8]) and g.offsets_s[0] == 0   # the arrays' clocks are not observed here


def test_probes_are_matched_across_clocks_even_with_one_missed():
    a = np.array([0.5, 1.0, 1.5, 2.0, 2.5, 3.1])
    b = np.r_[a[:2], a[3:]] + 7.25                                    # another clock; probe 2 not heard
    m = match_probes([a, b])
    assert m.tolist() == [[0, 0], [1, 1], [3, 2], [4, 3], [5, 4]]


def test_a_silent_recording_and_too_few_probes_say_what_is_missing(tmp_path, capsys):
    arrays = _simulate(tmp_path, n_probes=3)
    assert main(["calibrate", "--method", "multi-array", "--arrays", str(arrays), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "Only 3 probe events were heard by every array" in err and "needs at least 4" in err
    sf.write(tmp_path / "array1.wav", np.zeros((FS, 8), np.float32), FS)
    assert main(["calibrate", "--method", "multi-array", "--arrays", str(arrays), "--out", str(tmp_path / "o")]) == 2
    assert "Array 'shelf': no probe event stands 10 dB above the noise floor" in capsys.readouterr().err
    assert detect_probes(np.zeros((FS, 2), np.float32), FS).shape == (0, 2)


def test_channels_that_do_not_match_the_mics_are_one_sentence(tmp_path, capsys):
    arrays = _simulate(tmp_path, n_probes=6, corrupt_channels=True)
    assert main(["calibrate", "--method", "multi-array", "--arrays", str(arrays), "--out", str(tmp_path / "o")]) == 2
    assert "has 8 channels but the arrays file gives 7 mic positions" in capsys.readouterr().err
