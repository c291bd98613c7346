"""Hybrid-TDOA calibration (estimators.hybrid_tdoa): synthetic truth -> measurements -> solve -> mic frame."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from estimators import hybrid_tdoa as ht

C = 340.0
CUBE = 3.0 * np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 1, 1], [0, 0, 1], [1, 0, 1], [1, 1, 1]], float)


def make_truth(rng: np.random.Generator, n_mics: int = 6, events: np.ndarray = CUBE) -> ht.Scene:
    offsets = rng.uniform(-0.1, 0.1, n_mics)
    offsets[0] = 0.0
    return ht.Scene(rng.uniform(0.0, 3.0, (n_mics, 3)), events, offsets, rng.uniform(-100, 100, n_mics))


def make_problem(truth: ht.Scene, rng: np.random.Generator, **kw) -> ht.HybridTdoaProblem:
    iv = rng.uniform(2.0, 10.0, truth.event_positions_m.shape[0] - 1)
    return ht.simulate_problem(truth, iv, sigma_tdoa_s=kw.pop("sigma_tdoa_s", 1e-4), sigma_odo_m=0.01, rng=rng,
                               speed_of_sound_m_s=C, **kw)


def test_noise_free_recovers_truth_in_mic_frame():
    rng = np.random.default_rng(1)
    truth = make_truth(rng)
    problem = make_problem(truth, rng, noise_free=True)
    init = ht.random_initial_scene(6, 8, rng=rng, low_m=(0, 0, 0), high_m=(3, 3, 3))
    res = ht.solve(problem, init=init, rng=rng)
    assert res.verdict == "converged"
    a, b = ht.to_mic_frame(res), ht.to_mic_frame(truth)
    assert np.max(np.abs(a.mic_positions_m - b.mic_positions_m)) < 1e-3  # metres
    assert np.max(np.abs(a.offsets_s - b.offsets_s)) < 1e-7  # seconds
    assert np.max(np.abs(res.drifts_ppm - truth.drifts_ppm)) < 0.05  # hybrid: absolute drifts are observable
    assert np.max(np.abs(a.event_positions_m - b.event_positions_m)) < 1e-3


def test_baseline_noise_free_recovers_truth():
    rng = np.random.default_rng(2)
    truth = make_truth(rng)
    problem = make_problem(truth, rng, noise_free=True)
    res = ht.solve(problem, method="baseline", init=truth, rng=rng)
    assert res.verdict == "converged"
    err = ht.mic_frame_error(res, truth)
    assert err["location_m"] < 1e-3 and err["offset_s"] < 1e-7 and err["drift_ppm"] < 0.05
    assert res.drifts_ppm[0] == 0.0  # baseline: drifts relative to mic 0


@settings(max_examples=5, deadline=None)
@given(angles=st.tuples(*[st.floats(-np.pi, np.pi)] * 3),
       shift=st.tuples(*[st.floats(-5.0, 5.0)] * 3))
def test_invariant_to_rigid_motion_of_the_scene(angles, shift):
    rng = np.random.default_rng(3)
    truth = make_truth(rng)
    problem = make_problem(truth, rng)
    rot = Rotation.from_euler("xyz", angles).as_matrix()
    t = np.asarray(shift)
    moved = dataclasses.replace(problem, odometry_m=problem.odometry_m @ rot.T)  # TDOAs are invariant
    init = ht.Scene(truth.mic_positions_m + 0.3, truth.event_positions_m)
    init_moved = ht.Scene(init.mic_positions_m @ rot.T + t, init.event_positions_m @ rot.T + t)
    a = ht.to_mic_frame(ht.solve(problem, init=init, rng=0))
    b = ht.to_mic_frame(ht.solve(moved, init=init_moved, rng=0))
    np.testing.assert_allclose(a.mic_positions_m, b.mic_positions_m, atol=1e-5)
    np.testing.assert_allclose(a.offsets_s, b.offsets_s, atol=1e-7)
    np.testing.assert_allclose(a.drifts_ppm, b.drifts_ppm, atol=1e-2)


def test_robust_loss_survives_gross_outlier():
    rng = np.random.default_rng(4)
    truth = make_truth(rng)
    problem = make_problem(truth, rng)
    bad = problem.tdoa_events_s.copy()
    bad[3, 2] += 0.05  # a chirp mis-detected by 50 ms (500 sigma)
    corrupted = dataclasses.replace(problem, tdoa_events_s=bad)
    clean = ht.mic_frame_error(ht.solve(problem, rng=0), truth)["location_m"]
    robust = ht.solve(corrupted, rng=0)
    plain = ht.solve(corrupted, rng=0, loss="linear", reject_sigma=None)
    assert robust.verdict == "converged"
    assert ht.mic_frame_error(robust, truth)["location_m"] < 1.5 * clean + 0.01
    assert ht.mic_frame_error(plain, truth)["location_m"] > 2 * ht.mic_frame_error(robust, truth)["location_m"]


def corrupt(problem: ht.HybridTdoaProblem, *, interval: int, entries_s, tdoa_m=None) -> ht.HybridTdoaProblem:
    """Gross errors: ``interval_s[interval]`` given 1 ms short of the truth (the TDOA-S were measured with the
    true one), TDOA-S ``entries_s`` ((row, mic), ...) 2 ms late, optionally TDOA-M ``tdoa_m`` (row, mic) 0.5 s off
    (a chirp missed by a device)."""
    iv = problem.interval_s.copy()
    iv[interval] -= 1e-3
    s = problem.tdoa_events_s.copy()
    for j, i in entries_s:
        s[j, i] += 2e-3
    m = problem.tdoa_mics_s.copy()
    if tdoa_m is not None:
        m[tdoa_m] -= 0.5
    return dataclasses.replace(problem, interval_s=iv, tdoa_events_s=s, tdoa_mics_s=m)


def test_gross_errors_are_rejected_named_and_harmless():
    rng = np.random.default_rng(13)
    events = np.concatenate([CUBE, CUBE[::-1] + [0.5, 0.5, 0.3]])
    truth = make_truth(rng, n_mics=6, events=events)
    problem = make_problem(truth, rng)
    bad_s = [(2, 1), (9, 4), (11, 0)]
    bad = corrupt(problem, interval=5, entries_s=bad_s, tdoa_m=(7, 3))
    clean = ht.solve(problem, rng=0)
    res = ht.solve(bad, rng=0, with_covariance=True)
    plain = ht.solve(bad, rng=0, reject_sigma=None)
    assert res.verdict == "converged" and res.chi2_per_dof < 2.0
    named = {(m.kind, m.event, m.mic) for m in res.rejected}
    assert named == {("interval", 5, -1), ("tdoa_mics", 7, 3)} | {("tdoa_events", j, i) for j, i in bad_s}
    for m in res.rejected:
        assert m.statistic > 8.0 and m.reason
        if m.kind == "interval":
            assert m.residual == pytest.approx(1e-3, abs=1e-4)  # seconds: given + correction = truth
            assert res.interval_corrections_s[5] == m.residual and m.normalised_residual > 8.0
        elif m.kind == "tdoa_events":
            assert m.residual == pytest.approx(2e-3, abs=5e-4) and m.normalised_residual > 15.0
        else:
            assert m.residual == pytest.approx(-0.5, abs=1e-3)
    assert res.outliers_tdoa_events.sum() == 3 and res.outliers_tdoa_mics[7, 3] and res.outliers_odometry is None
    np.testing.assert_array_equal(res.estimated_intervals, [5])
    err = ht.mic_frame_error(res, truth)["location_m"]
    assert err < 1.2 * ht.mic_frame_error(clean, truth)["location_m"] + 0.005  # metres
    assert plain.verdict != "converged" or plain.chi2_per_dof > 5.0  # without rejection: no honest fit
    # the Fisher information of the kept set, interval 5 a nuisance parameter, is what crlb() gives for it
    kept = ht.without_rejected(bad, res)
    assert np.isnan(kept.tdoa_events_s[2, 1]) and kept.interval_s[5] == pytest.approx(problem.interval_s[5], abs=1e-4)
    bound = ht.crlb(kept, res.scene, unknown_intervals=res.estimated_intervals)
    np.testing.assert_allclose(res.mic_frame_location_std_m, bound.per_mic_location_std_m, rtol=1e-3, atol=1e-9)
    assert bound.location_std_m > ht.crlb(kept, res.scene).location_std_m  # an unknown interval costs precision


def test_clean_problems_reject_nothing():
    rng = np.random.default_rng(14)
    for n_mics in (4, 8):
        truth = make_truth(rng, n_mics=n_mics)
        for method in ("hybrid", "baseline"):
            res = ht.solve(make_problem(truth, rng), method=method, rng=0)
            assert res.verdict == "converged"
            assert res.rejected == () and res.interval_corrections_s is None
            assert not res.outliers_tdoa_events.any() and not res.outliers_tdoa_mics.any()


def test_baseline_rejects_a_missed_chirp():
    rng = np.random.default_rng(15)
    truth = make_truth(rng, n_mics=6)
    problem = make_problem(truth, rng)
    m = problem.tdoa_mics_s.copy()
    m[0, 4] -= 0.5  # 0.5 s: the device heard another chirp
    res = ht.solve(dataclasses.replace(problem, tdoa_mics_s=m), method="baseline", rng=0)
    assert res.verdict == "converged"
    assert [(r.kind, r.event, r.mic) for r in res.rejected] == [("tdoa_mics", 0, 4)]
    clean = ht.solve(problem, method="baseline", rng=0)
    assert ht.mic_frame_error(res, truth)["location_m"] < 1.2 * ht.mic_frame_error(clean, truth)["location_m"] + 0.005


def test_odometry_rejection_is_opt_in():
    rng = np.random.default_rng(16)
    events = np.concatenate([CUBE, CUBE[::-1] + [0.5, 0.5, 0.3]])
    truth = make_truth(rng, n_mics=6, events=events)
    problem = make_problem(truth, rng)
    odo = problem.odometry_m.copy()
    odo[6] += [0.3, -0.2, 0.0]  # wheel slip, 36 cm (36 sigma)
    slipped = dataclasses.replace(problem, odometry_m=odo)
    res = ht.solve(slipped, rng=0, reject_odometry=True)
    assert [(r.kind, r.event) for r in res.rejected] == [("odometry", 6)]
    assert res.verdict == "converged" and res.outliers_odometry[6] and res.rejected[0].residual > 0.3
    kept = ht.without_rejected(slipped, res)
    assert np.all(np.isnan(kept.odometry_m[6])) and np.all(np.isfinite(np.delete(kept.odometry_m, 6, 0)))
    assert all(r.kind != "odometry" for r in ht.solve(slipped, rng=0).rejected)


def test_missing_measurements_are_tolerated():
    rng = np.random.default_rng(5)
    truth = make_truth(rng, n_mics=7)
    problem = make_problem(truth, rng)
    s = problem.tdoa_events_s.copy()
    m = problem.tdoa_mics_s.copy()
    o = problem.odometry_m.copy()
    s[2, 4] = s[5, 1] = np.nan  # device missed a chirp: both adjacent TDOA-S
    s[3, 4] = np.nan
    m[3, 4] = m[0, 2] = np.nan
    m[6, :] = np.nan  # reference device missed event 6: no TDOA-M at all
    o[4] = np.nan  # odometry dropout
    holey = dataclasses.replace(problem, tdoa_events_s=s, tdoa_mics_s=m, odometry_m=o)
    res = ht.solve(holey, rng=0)
    assert res.verdict == "converged"
    assert ht.mic_frame_error(res, truth)["location_m"] < 0.15


def test_crlb_matches_monte_carlo_std():
    rng = np.random.default_rng(6)
    truth = make_truth(rng, n_mics=6)
    iv = rng.uniform(2.0, 10.0, 7)
    sq = []
    for _ in range(40):
        problem = ht.simulate_problem(truth, iv, sigma_tdoa_s=1e-4, sigma_odo_m=0.01, rng=rng,
                                      speed_of_sound_m_s=C)
        res = ht.solve(problem, init=truth, loss="linear", rng=0)
        a, b = ht.to_mic_frame(res), ht.to_mic_frame(truth)
        sq.append(np.sum((a.mic_positions_m[1:] - b.mic_positions_m[1:]) ** 2, axis=1))
    empirical = float(np.sqrt(np.mean(sq)))  # D_CRLB of eq. (16) is the RMS over mics 1.. of the variance
    bound = ht.crlb(problem, truth, method="hybrid")
    assert abs(empirical / bound.location_std_m - 1.0) < 0.3
    # the authors' rotate-only frame change under-states the location bound of the hybrid method
    assert bound.location_std_m_authors < bound.location_std_m
    assert bound.offset_std_s == pytest.approx(bound.offset_std_s_authors)


def test_crlb_hybrid_below_baseline():
    rng = np.random.default_rng(7)
    truth = make_truth(rng)
    problem = make_problem(truth, rng)
    h = ht.crlb(problem, truth, method="hybrid")
    b = ht.crlb(problem, truth, method="baseline")
    assert h.location_std_m < b.location_std_m
    assert h.per_mic_location_std_m[0] == pytest.approx(0.0, abs=1e-12)


def test_noise_levels_appendix_b():
    rng = np.random.default_rng(8)
    events = np.concatenate([CUBE, CUBE[::-1] + 0.3, CUBE + 0.6, CUBE[::-1] + 0.9])
    truth = make_truth(rng, n_mics=10, events=events)
    problem = make_problem(truth, rng, sigma_tdoa_s=2e-4)
    lv = ht.estimate_noise_levels(problem, truth)
    assert lv.tdoa_events_std_s == pytest.approx(2e-4, rel=0.15)
    assert lv.tdoa_mics_std_s == pytest.approx(2e-4, rel=0.15)
    assert np.isnan(lv.per_mic_mics_std_s[0])


def test_verdict_reports_exhausted_budget():
    rng = np.random.default_rng(9)
    truth = make_truth(rng)
    problem = make_problem(truth, rng)
    init = ht.random_initial_scene(6, 8, rng=rng, low_m=(0, 0, 0), high_m=(3, 3, 3))
    res = ht.solve(problem, init=init, max_iterations=1, n_starts=1)
    assert res.verdict == "max_iterations"
    assert res.n_starts_used == 1 and res.n_iterations == 1


def test_sparse_jacobian_equals_dense(monkeypatch):
    rng = np.random.default_rng(10)
    truth = make_truth(rng)
    problem = make_problem(truth, rng)
    p = np.concatenate([truth.mic_positions_m.ravel(), truth.offsets_s, truth.drifts_ppm * 1e-6,
                        truth.event_positions_m.ravel()])
    dense = ht._Layout(problem, "hybrid").jacobian(p)
    monkeypatch.setattr(ht, "_DENSE_LIMIT", 0)
    sparse = ht._Layout(problem, "hybrid").jacobian(p)
    np.testing.assert_allclose(sparse.toarray(), dense, rtol=0, atol=1e-12)
    # analytic Jacobian against central differences
    lay = ht._Layout(problem, "hybrid")
    num = np.zeros_like(dense)
    for col, k in enumerate(np.nonzero(lay.free)[0]):
        e = np.zeros_like(p)
        e[k] = 1e-6 if (k < lay.o_tau or k >= lay.o_s) else 1e-9
        num[:, col] = (lay.residuals(p + e) - lay.residuals(p - e)) / (2 * e[k])
    np.testing.assert_allclose(dense, num, atol=1e-4 * np.max(np.abs(dense)))


@pytest.mark.parametrize("method", ["hybrid", "baseline"])
def test_normal_equations_are_the_jacobian_products(method):
    """The compiled ``J^T W J`` and ``J^T W r`` (summed over the stored entries of each row) equal the products
    of the explicit Jacobian, with a free interval error too; ``residuals`` is eq. (5)/(6)/(9) row by row."""
    rng = np.random.default_rng(11)
    truth = make_truth(rng)
    problem = make_problem(truth, rng)
    lay = ht._Layout(problem, method, free_intervals=[3] if method == "hybrid" else ())
    p = lay.pack(truth.mic_positions_m + rng.normal(0, 0.3, (6, 3)), truth.offsets_s, truth.drifts_ppm * 1e-6,
                 truth.event_positions_m, np.full(lay.n_e, 2e-4))
    w, r = rng.uniform(0.0, 1.0, lay.n_res), rng.normal(0.0, 3.0, lay.n_res)
    j = lay.jacobian(p)
    a, g = lay.normal_equations(p, w, r)
    scale = np.max(np.abs(j.T @ j))
    np.testing.assert_allclose(a, j.T @ (w[:, None] * j), rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(g, j.T @ (w * r), rtol=0, atol=1e-12 * np.max(np.abs(j)) * np.sum(np.abs(r)))
    assert np.array_equal(a, a.T)
    a1, g1 = lay.normal_equations(p)
    assert g1 is None
    np.testing.assert_allclose(a1, j.T @ j, rtol=0, atol=1e-12 * scale)
    d = np.linalg.norm(p[:18].reshape(6, 1, 3) - p[lay.o_s:lay.o_e].reshape(1, 8, 3), axis=2)
    c = problem.speed_of_sound_m_s
    i, k = lay.m_mic[5], lay.m_ev[5]  # a TDOA-M row, eq. (6)
    tau, delta, t = p[lay.o_tau:lay.o_del], p[lay.o_del:lay.o_s], problem.emission_times_s
    pred = (d[i, k] - d[0, k]) / c + tau[i] - tau[0] + (delta[i] - delta[0]) * t[k]
    assert lay.residuals(p)[lay.n_s + 5] == pytest.approx((pred - problem.tdoa_mics_s[k, i]) * lay.m_w, abs=1e-9)


def test_mic_frame_definition_and_immutability():
    rng = np.random.default_rng(11)
    truth = make_truth(rng)
    mf = ht.to_mic_frame(truth)
    assert np.allclose(mf.mic_positions_m[0], 0.0)
    assert np.allclose(mf.mic_positions_m[1, 1:], 0.0) and mf.mic_positions_m[1, 0] > 0
    assert abs(mf.mic_positions_m[2, 2]) < 1e-12 and mf.mic_positions_m[2, 1] > 0
    problem = make_problem(truth, rng)
    res = ht.solve(problem, rng=0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.verdict = "converged"
    with pytest.raises(ValueError):
        res.mic_positions_m[0, 0] = 1.0


def test_bad_arguments_raise():
    rng = np.random.default_rng(12)
    truth = make_truth(rng)
    problem = make_problem(truth, rng)
    with pytest.raises(ValueError, match="sigma_tdoa_s"):
        dataclasses.replace(problem, sigma_tdoa_s=0.0)
    with pytest.raises(ValueError, match="odometry_m"):
        dataclasses.replace(problem, odometry_m=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="method"):
        ht.solve(problem, method="tdoa")
    with pytest.raises(ValueError, match="hybrid"):
        ht.solve(dataclasses.replace(problem, tdoa_events_s=None))
    with pytest.raises(ValueError, match="reject_sigma"):
        ht.solve(problem, reject_sigma=0.0)
    with pytest.raises(ValueError, match="unknown_intervals"):
        ht.crlb(problem, truth, unknown_intervals=[7])
    assert ht.solve(dataclasses.replace(problem, tdoa_events_s=None), method="baseline", init=truth).verdict \
        == "converged"
