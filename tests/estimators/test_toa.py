"""Relative-TOA estimators against known TOA vectors (tolerances in seconds unless stated)."""
from __future__ import annotations

import copy
import pickle

import numpy as np
import pytest
import scipy.stats
from filterpy.kalman import KalmanFilter
from hypothesis import given, settings
from hypothesis import strategies as st

from estimators import FixedLagKalmanToa, KalmanToa, PinvToa, SubsetToa, pair_matrix

FRAME_S = 0.02
TDOA_STD_S = 2e-5


def random_toa(rng: np.random.Generator, n_mics: int, scale_s: float = 1e-3) -> np.ndarray:
    toa = rng.normal(0.0, scale_s, n_mics)
    return toa - toa[0]


def drifting_track(n_mics: int, n_frames: int, seed: int = 0):
    """Relative TOA moving linearly: toa(t) = toa0 + rate * t; returns (truth, noisy tdoa)."""
    rng = np.random.default_rng(seed)
    toa0 = random_toa(rng, n_mics)
    rate = np.r_[0.0, rng.uniform(-5e-3, 5e-3, n_mics - 1)]  # s/s
    t_s = np.arange(n_frames) * FRAME_S
    truth = toa0[None, :] + t_s[:, None] * rate[None, :]
    H = pair_matrix(n_mics)
    tdoa = truth @ H.T + rng.normal(0.0, TDOA_STD_S, (n_frames, len(H)))
    return truth, tdoa, rate


def kalman(n_mics: int, **kwargs) -> KalmanToa:
    kwargs.setdefault("frame_period_s", FRAME_S)
    kwargs.setdefault("tdoa_std_s", TDOA_STD_S)
    kwargs.setdefault("accel_std_s_per_s2", 1e-3)
    return KalmanToa(n_mics, **kwargs)


# KalmanToa predicts with the block structure of F (eq. 16) instead of np.dot(np.dot(F, P), F.T),
# which rounds differently: states agree with filterpy's predict to rtol 1e-12 (atol 1e-18 s,
# i.e. 1e-15 of the 1 ms TOAs used here), covariances to rtol 1e-12 with an absolute tolerance of
# 1e-12 of the largest element (s^2).
def assert_state_close(actual, desired) -> None:
    np.testing.assert_allclose(actual, desired, rtol=1e-12, atol=1e-18)


def assert_covariance_close(actual, desired) -> None:
    np.testing.assert_allclose(actual, desired, rtol=1e-12, atol=1e-12 * np.abs(desired).max())


# -- instantaneous estimators ----------------------------------------------------------------------


@pytest.mark.parametrize("n_mics", [2, 3, 5, 10])
@pytest.mark.parametrize("cls", [SubsetToa, PinvToa])
def test_noise_free_recovery(cls, n_mics):
    toa = random_toa(np.random.default_rng(n_mics), n_mics)
    est = cls(n_mics)
    out = est.update(pair_matrix(n_mics) @ toa)
    assert out.shape == (n_mics,) and out[0] == 0.0
    np.testing.assert_allclose(out, toa, atol=1e-15)
    assert est.gated is False


def test_subset_sign():
    # pair (0, 1): tdoa = toa_0 - toa_1; mic 1 hears 1 ms later than mic 0 -> tdoa = -1 ms
    out = SubsetToa(3).update(np.array([-1e-3, 2e-3, 0.0]))
    np.testing.assert_allclose(out, [0.0, 1e-3, -2e-3])


def test_pinv_beats_subset_on_noise():
    n_mics, n_frames = 6, 2000
    rng = np.random.default_rng(1)
    H = pair_matrix(n_mics)
    toa = random_toa(rng, n_mics)
    tdoa = toa @ H.T + rng.normal(0.0, TDOA_STD_S, (n_frames, len(H)))
    sub, pinv = SubsetToa(n_mics), PinvToa(n_mics)
    err_sub = np.array([sub.update(y) - toa for y in tdoa])[:, 1:]
    err_pinv = np.array([pinv.update(y) - toa for y in tdoa])[:, 1:]
    rmse_sub = np.sqrt(np.mean(err_sub**2))
    rmse_pinv = np.sqrt(np.mean(err_pinv**2))
    assert rmse_sub == pytest.approx(TDOA_STD_S, rel=0.05)
    # complete graph: per-element variance of eq. (12) is 2 / M of the pair variance
    assert rmse_pinv == pytest.approx(TDOA_STD_S * np.sqrt(2 / n_mics), rel=0.05)


def test_pinv_excludes_low_confidence_and_nonfinite_pairs():
    n_mics = 4
    toa = random_toa(np.random.default_rng(2), n_mics)
    y = pair_matrix(n_mics) @ toa
    conf = np.ones(len(y))
    y_bad = y.copy()
    y_bad[1] += 0.5  # outlier with zero confidence
    y_bad[4] = np.nan
    conf[1] = 0.0
    for weighted in (False, True):
        out = PinvToa(n_mics, weighted=weighted).update(y_bad, conf)
        np.testing.assert_allclose(out, toa, atol=1e-12)


def test_pinv_weighted_equal_confidence_is_unweighted():
    rng = np.random.default_rng(3)
    y = rng.normal(0.0, 1e-3, 10)
    a = PinvToa(5).update(y)
    b = PinvToa(5, weighted=True).update(y, np.full(10, 0.4))
    np.testing.assert_allclose(a, b, atol=1e-15)


def test_subset_holds_excluded_mic():
    est = SubsetToa(3)
    est.update(np.array([-1e-3, -2e-3, 1e-3]))
    out = est.update(np.array([np.nan, -3e-3, 0.0]))
    np.testing.assert_allclose(out, [0.0, 1e-3, 3e-3])


def test_shape_errors():
    with pytest.raises(ValueError, match="tdoa_s.shape"):
        PinvToa(4).update(np.zeros(5))
    with pytest.raises(ValueError, match="confidence.shape"):
        kalman(3).update(np.zeros(3), np.ones(2))


@pytest.mark.parametrize(
    "factory",
    [
        lambda: SubsetToa(1),
        lambda: PinvToa(2.5),
        lambda: PinvToa(3, min_confidence=1.0),
        lambda: KalmanToa(3, frame_period_s=0.0),
        lambda: KalmanToa(3, frame_period_s=0.02, tdoa_std_s=-1.0),
        lambda: KalmanToa(3, frame_period_s=0.02, gate_probability=1.0),
        lambda: KalmanToa(3, frame_period_s=0.02, reinit_after_n_gated=0),
        lambda: FixedLagKalmanToa(3, lag_frames=-1, frame_period_s=0.02),
    ],
)
def test_bad_arguments_raise_at_construction(factory):
    with pytest.raises(ValueError):
        factory()


# -- Kalman filter ---------------------------------------------------------------------------------


def test_process_noise_is_wiener_velocity():
    m, dt, q_std = 4, 0.02, 0.3
    est = KalmanToa(m + 1, frame_period_s=dt, accel_std_s_per_s2=q_std)
    block = q_std**2 * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    np.testing.assert_allclose(est._kf.Q, np.kron(block, np.eye(m)))  # eq. (16) state order
    np.testing.assert_allclose(est._kf.F, np.kron([[1, dt], [0, 1]], np.eye(m)))


def test_first_update_is_pinv_with_zero_rate():
    n_mics = 4
    rng = np.random.default_rng(4)
    y = rng.normal(0.0, 1e-3, 6)
    est = kalman(n_mics)
    out = est.update(y)
    np.testing.assert_allclose(out, PinvToa(n_mics).update(y), atol=1e-15)
    np.testing.assert_array_equal(est.state[n_mics - 1 :], 0.0)
    assert est.initialised and est.reinitialised


@pytest.mark.parametrize("n_mics", [3, 8])
def test_tracks_linear_drift(n_mics):
    truth, tdoa, rate = drifting_track(n_mics, 300)
    est = kalman(n_mics, accel_std_s_per_s2=1e-5)
    out = np.array([est.update(y) for y in tdoa])
    err = out[150:, 1:] - truth[150:, 1:]
    pinv_std = TDOA_STD_S * np.sqrt(2 / n_mics)  # per-element error of the instantaneous eq. (12)
    assert np.sqrt(np.mean(err**2)) < 0.25 * pinv_std
    np.testing.assert_allclose(est.state[n_mics - 1 :], rate[1:], atol=2e-4)
    assert est.n_gated <= 2  # 0.999 gate on clean Gaussian data


@pytest.mark.parametrize("with_mask", [False, True])
def test_information_form_update_equals_filterpy(with_mask):
    n_mics = 5
    truth, tdoa, _ = drifting_track(n_mics, 12, seed=5)
    est = kalman(n_mics, gate_probability=None)
    for y in tdoa[:10]:
        est.update(y)
    conf = None
    used = np.ones(len(tdoa[10]), bool)
    if with_mask:
        conf = np.full(len(used), 0.9)
        conf[[2, 7]] = 0.0
        used = conf > 0
    ref = copy.deepcopy(est._kf)
    est.update(tdoa[10], conf)
    kf = KalmanFilter(dim_x=ref.dim_x, dim_z=int(used.sum()))
    kf.x, kf.P, kf.F, kf.Q = ref.x.copy(), ref.P.copy(), ref.F, ref.Q
    kf.H, kf.R = ref.H[used], TDOA_STD_S**2 * np.eye(int(used.sum()))
    kf.predict()
    kf.update(tdoa[10][used])
    np.testing.assert_allclose(est.state, kf.x, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(est.state_covariance, kf.P, rtol=1e-7, atol=1e-20)
    assert est.last_mahalanobis_sq == pytest.approx(kf.mahalanobis**2, rel=1e-8)
    assert est.n_pairs_used == used.sum()


@pytest.mark.parametrize("n_mics", [3, 8])
def test_long_run_equals_filterpy_with_changing_masks(n_mics):
    """Every step of a long run (fast all-pairs path, masked pairs, NaN TDOAs, low confidence,
    frames without any usable pair) matches filterpy's predict + update on the used pairs."""
    rng = np.random.default_rng(n_mics)
    _, tdoa, _ = drifting_track(n_mics, 120, seed=n_mics)
    est = kalman(n_mics, gate_probability=None, min_confidence=0.2)
    n_pairs = tdoa.shape[1]
    for k, y in enumerate(tdoa):
        conf = np.full(n_pairs, 0.9)
        y = y.copy()
        kind = k % 7 if k > 2 else 0  # the first frames initialise from all pairs
        if kind == 1:
            conf[rng.integers(0, n_pairs, 2)] = 0.1
        elif kind == 2:
            y[rng.integers(0, n_pairs)] = np.nan
        elif kind == 3:
            conf[:] = 0.0
        elif kind == 4:
            conf[rng.integers(0, n_pairs)] = np.nan
        used = np.isfinite(y) & (conf > 0.2)
        ref = copy.deepcopy(est._kf)
        out = est.update(y, conf)
        if k == 0:
            continue
        kf = KalmanFilter(dim_x=ref.dim_x, dim_z=max(1, int(used.sum())))
        kf.x, kf.P, kf.F, kf.Q = ref.x.copy(), ref.P.copy(), ref.F, ref.Q
        kf.predict()
        if used.any():
            kf.H, kf.R = ref.H[used], TDOA_STD_S**2 * np.eye(int(used.sum()))
            kf.update(y[used])
            assert est.last_mahalanobis_sq == pytest.approx(kf.mahalanobis**2, rel=1e-7)
        else:
            assert_state_close(est.state, kf.x)  # prediction only
            assert_covariance_close(est.state_covariance, kf.P)
        np.testing.assert_allclose(est.state, kf.x, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(est.state_covariance, kf.P, rtol=1e-7, atol=1e-20)
        np.testing.assert_array_equal(out, np.r_[0.0, est.state[: n_mics - 1]])
        assert est.n_pairs_used == used.sum()


def test_gated_outlier_leaves_prediction():
    n_mics = 4
    _, tdoa, _ = drifting_track(n_mics, 60)
    est = kalman(n_mics)
    for y in tdoa[:50]:
        est.update(y)
    predicted = copy.deepcopy(est)
    predicted._kf.predict()
    outlier = tdoa[50].copy()
    outlier[0] += 1e-2  # 500 sigma
    out = est.update(outlier)
    assert est.gated and est.n_gated == 1
    # the prediction, exactly the filter's own prior, and filterpy's to float tolerance
    np.testing.assert_array_equal(est.state, est._kf.x_prior)
    np.testing.assert_array_equal(est.state_covariance, est._kf.P_prior)
    assert_state_close(est.state, predicted._kf.x)
    assert_covariance_close(est.state_covariance, predicted._kf.P)
    np.testing.assert_array_equal(out[1:], est.state[: n_mics - 1])
    est.update(tdoa[51])
    assert not est.gated


@settings(max_examples=20, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    pair=st.integers(0, 5),
    jump_s=st.floats(2e-3, 1e-1),
    sign=st.sampled_from([-1.0, 1.0]),
)
def test_gate_leaves_prior_untouched(seed, pair, jump_s, sign):
    _, tdoa, _ = drifting_track(4, 31, seed=seed % 1000)
    est = kalman(4)
    for y in tdoa[:30]:
        est.update(y)
    prior = copy.deepcopy(est._kf)
    prior.predict()
    y = tdoa[30].copy()
    y[pair] += sign * jump_s
    est.update(y)
    assert est.gated
    np.testing.assert_array_equal(est.state, est._kf.x_prior)
    np.testing.assert_array_equal(est.state_covariance, est._kf.P_prior)
    assert_state_close(est.state, prior.x)
    assert_covariance_close(est.state_covariance, prior.P)


def test_no_usable_pair_only_predicts():
    n_mics = 3
    _, tdoa, _ = drifting_track(n_mics, 20)
    est = kalman(n_mics)
    for y in tdoa[:19]:
        est.update(y)
    predicted = copy.deepcopy(est._kf)
    predicted.predict()
    est.update(tdoa[19], np.zeros(3))
    assert not est.gated and est.n_pairs_used == 0
    np.testing.assert_array_equal(est.state, est._kf.x_prior)
    assert_state_close(est.state, predicted.x)
    assert_covariance_close(est.state_covariance, predicted.P)


def test_reset_restores_initial_state():
    n_mics = 4
    _, tdoa, _ = drifting_track(n_mics, 40)
    first = kalman(n_mics)
    fresh = [first.update(y) for y in tdoa[:20]]
    est = kalman(n_mics)
    for y in tdoa:
        est.update(y)
    est.update(tdoa[0] + 1.0)  # gated
    est.reset()
    assert not est.initialised and est.n_gated == 0 and est.n_reinit == 0 and not est.gated
    np.testing.assert_array_equal([est.update(y) for y in tdoa[:20]], fresh)


def test_reinitialises_after_many_gated_frames():
    n_mics = 4
    H = pair_matrix(n_mics)
    rng = np.random.default_rng(6)
    toa_a, toa_b = random_toa(rng, n_mics), random_toa(rng, n_mics, 5e-3)
    est = kalman(n_mics, reinit_after_n_gated=10)
    for _ in range(30):
        est.update(H @ toa_a + rng.normal(0, TDOA_STD_S, len(H)))
    gated = []
    for _ in range(15):
        out = est.update(H @ toa_b + rng.normal(0, TDOA_STD_S, len(H)))
        gated.append(est.gated)
    assert gated[:10] == [True] * 10 and not any(gated[10:])
    assert est.n_reinit == 1
    np.testing.assert_allclose(out, toa_b, atol=4 * TDOA_STD_S)


def test_confidence_weighting_downweights_pairs():
    n_mics = 3
    rng = np.random.default_rng(7)
    toa = random_toa(rng, n_mics)
    H = pair_matrix(n_mics)
    est_w = kalman(n_mics, confidence_weighted=True, gate_probability=None)
    est_u = kalman(n_mics, gate_probability=None)
    conf = np.array([1.0, 1.0, 0.01])
    for _ in range(30):
        y = H @ toa + rng.normal(0, TDOA_STD_S, 3)
        y[2] += 5 * TDOA_STD_S  # biased pair, low confidence
        out_w, out_u = est_w.update(y, conf), est_u.update(y, conf)
    assert np.abs(out_w - toa).max() < np.abs(out_u - toa).max()


# -- the compiled step against plain numpy ---------------------------------------------------------


def information_form_reference(x, P, F, Q, y, confidence, *, tdoa_var, min_confidence, weighted, gate_probability):
    """Plain numpy restatement of one KalmanToa step from the posterior ``(x, P)``: predict
    (eq. 13), used pairs and weights, gate (eq. 17), information-form update (eq. 14).

    Returns ``(x, P, d2, gated)``; checks itself against the textbook ``K = P H^T S^-1`` update.
    """
    m = len(x) // 2
    H0 = pair_matrix(m + 1)[:, 1:]
    x_p = F @ x
    P_p = F @ P @ F.T + Q
    conf = np.ones(len(y)) if confidence is None else confidence
    used = np.isfinite(y) & (conf > min_confidence)
    w = np.where(used, (conf if weighted else 1.0) / tdoa_var, 0.0)
    v = np.where(used, y - H0 @ x_p[:m], 0.0)
    B = H0.T @ (w[:, None] * H0)
    b = H0.T @ (w * v)
    sol = np.linalg.solve(np.eye(m) + B @ P_p[:m, :m], np.column_stack([B, b]))
    G, g = sol[:, :m], sol[:, m]
    P_c = P_p[:, :m]
    d2 = v @ (w * v) - b @ (P_c[:m] @ g)
    x_new = x_p + P_c @ g
    P_new = P_p - P_c @ G @ P_c.T
    # the same posterior from S = H P H^T + R on the used pairs
    Hu = H0[used]
    S = Hu @ P_p[:m, :m] @ Hu.T + np.diag(1.0 / w[used])
    K = P_c @ Hu.T @ np.linalg.inv(S)
    np.testing.assert_allclose(x_new, x_p + K @ v[used], rtol=1e-9, atol=1e-18)
    np.testing.assert_allclose(P_new, P_p - K @ S @ K.T, rtol=1e-6, atol=1e-9 * np.abs(P_p).max())
    assert d2 == pytest.approx(v[used] @ np.linalg.solve(S, v[used]), rel=1e-9)
    if gate_probability is not None and d2 > scipy.stats.chi2.ppf(gate_probability, int(used.sum())):
        return x_p, P_p, d2, True
    return x_new, 0.5 * (P_new + P_new.T), d2, False


def random_posterior(rng: np.random.Generator, m: int) -> tuple[np.ndarray, np.ndarray]:
    """A state around 1 ms and an exactly symmetric positive-definite covariance (the filter
    keeps its covariance exactly symmetric)."""
    L = rng.normal(0.0, 2e-5, (2 * m, 2 * m))
    P = L @ L.T + 1e-12 * np.eye(2 * m)
    return rng.normal(0.0, 1e-3, 2 * m), 0.5 * (P + P.T)


@pytest.mark.parametrize("n_mics", [2, 3, 8, 16])
@pytest.mark.parametrize("mode", ["all pairs", "masked", "confidence weighted"])
def test_compiled_step_equals_numpy_information_form(n_mics, mode):
    """On random covariances: used pairs (low, zero and NaN confidence, NaN TDOA), weights, the
    prediction, the gate and the update match the numpy restatement (float reordering: the
    compiled step solves by its own elimination and predicts with the blocks of F)."""
    rng = np.random.default_rng(n_mics + 100 * len(mode))
    m, n_pairs = n_mics - 1, n_mics * (n_mics - 1) // 2
    weighted = mode == "confidence weighted"
    kw = dict(tdoa_var=TDOA_STD_S**2, min_confidence=0.1, weighted=weighted, gate_probability=0.999)
    est = kalman(n_mics, min_confidence=0.1, confidence_weighted=weighted, reinit_after_n_gated=None)
    est.update(np.zeros(n_pairs))  # initialised; the state is replaced below
    n_gated = 0
    for trial in range(12):
        x0, P0 = random_posterior(rng, m)
        x_p = est._kf.F @ x0  # measurements around the prediction: most frames pass the gate
        y = pair_matrix(n_mics) @ np.r_[0.0, x_p[:m]] + rng.normal(0.0, TDOA_STD_S, n_pairs)
        if trial % 4 == 3:
            y[rng.integers(n_pairs)] += 5e-3  # clutter: gated
        conf = None
        if mode != "all pairs":
            conf = rng.uniform(0.2, 1.0, n_pairs)
            drop = rng.random(n_pairs) < 0.3
            conf[drop] = rng.choice([0.0, 0.05, np.nan], int(drop.sum()))
            y[1:][rng.random(n_pairs - 1) < 0.1] = np.nan
            conf[0] = 0.9  # at least one usable pair
        est._kf.x[:] = x0
        est._kf.P[:] = P0
        out = est.update(y, conf)
        x_ref, P_ref, d2_ref, gated_ref = information_form_reference(x0, P0, est._kf.F, est._kf.Q, y, conf, **kw)
        n_gated += gated_ref
        assert est.gated == gated_ref and est.n_gated == n_gated
        assert est.last_mahalanobis_sq == pytest.approx(d2_ref, rel=1e-11)
        used = np.isfinite(y) & ((conf if conf is not None else 1.0) > 0.1)
        assert est.n_pairs_used == used.sum()
        # tolerances: 1e-17 s on ~1 ms TOAs (seen: 4e-19 s); covariance to 1e-12 of its largest
        # element (seen: 1e-15), in s^2
        np.testing.assert_allclose(est.state, x_ref, rtol=1e-12, atol=1e-17)
        np.testing.assert_allclose(est.state_covariance, P_ref, rtol=1e-12, atol=1e-12 * np.abs(P_ref).max())
        np.testing.assert_array_equal(est.state_covariance, est.state_covariance.T)
        np.testing.assert_array_equal(out, np.r_[0.0, est.state[:m]])
        # the prior of this step stays readable (the smoother uses it)
        assert_state_close(est._kf.x_prior, est._kf.F @ x0)
        assert_covariance_close(est._kf.P_prior, est._kf.F @ P0 @ est._kf.F.T + est._kf.Q)
    assert 0 < n_gated < 12


@pytest.mark.parametrize("n_mics", [2, 5, 16])
def test_predict_equals_dense_prediction(n_mics):
    rng = np.random.default_rng(n_mics)
    m = n_mics - 1
    est = kalman(n_mics)
    assert not est.initialised
    np.testing.assert_array_equal(est.predict(), np.zeros(n_mics))  # nothing to predict yet
    est.update(np.zeros(n_mics * m // 2))
    x0, P0 = random_posterior(rng, m)
    est._kf.x[:] = x0
    est._kf.P[:] = P0
    n_gated = est.n_gated
    out = est.predict()
    F, Q = est._kf.F, est._kf.Q
    assert_state_close(est.state, F @ x0)
    assert_covariance_close(est.state_covariance, F @ P0 @ F.T + Q)
    np.testing.assert_array_equal(est.state_covariance, est.state_covariance.T)
    np.testing.assert_array_equal(est._kf.P_prior, est._kf.P)
    np.testing.assert_array_equal(out, np.r_[0.0, est.state[:m]])
    assert not est.gated and est.n_gated == n_gated and est.n_pairs_used == 0
    assert np.isnan(est.last_mahalanobis_sq)


def test_update_converts_other_input_types():
    """Lists, float32, read-only and strided arrays give the float64 result; bad shapes raise."""
    n_mics = 4
    _, tdoa, _ = drifting_track(n_mics, 8, seed=11)
    conf = np.full(tdoa.shape[1], 0.8)
    conf[2] = 0.0
    est = kalman(n_mics)
    ref = [est.update(y, conf) for y in tdoa]
    for convert, exact in (
        (list, True),
        (lambda a: a.astype(np.float32), False),
        (lambda a: np.frombuffer(a.tobytes()), True),  # read-only
        (lambda a: np.repeat(a, 2)[::2], True),  # strided view
    ):
        est.reset()
        for y, r in zip(tdoa, ref):
            out = est.update(convert(y), convert(conf))
            if exact:
                np.testing.assert_array_equal(out, r)
            else:
                np.testing.assert_allclose(out, r, atol=1e-8)  # float32 rounding of ~1 ms TDOAs
    with pytest.raises(ValueError, match="tdoa_s.shape"):
        est.update(tdoa[:2])
    with pytest.raises(ValueError, match="tdoa_s.shape"):
        est.update(np.zeros(7))
    with pytest.raises(ValueError, match="confidence.shape"):
        est.update(tdoa[0], [1.0, 1.0])


def test_pair_gate_drops_outlying_pairs():
    n_mics, sigma = 5, 4.0
    _, tdoa, _ = drifting_track(n_mics, 31, seed=12)
    est = kalman(n_mics, pair_gate_sigma=sigma, gate_probability=0.999)
    for y in tdoa[:30]:
        est.update(y)
    x0, P0 = est.state, est.state_covariance
    y = tdoa[30].copy()
    y[[1, 7]] += 50 * TDOA_STD_S
    # per-pair gate restated: |v_p| <= sigma sqrt(H0_p P_pp H0_p^T + R_pp)
    m = n_mics - 1
    F, Q, H0 = est._kf.F, est._kf.Q, pair_matrix(n_mics)[:, 1:]
    x_p, P_p = F @ x0, F @ P0 @ F.T + Q
    spread = np.einsum("pi,ij,pj->p", H0, P_p[:m, :m], H0) + TDOA_STD_S**2
    ok = np.abs(y - H0 @ x_p[:m]) <= sigma * np.sqrt(spread)
    assert not ok[1] and not ok[7]
    n_pairs_gated = est.n_pairs_gated
    est.update(y)
    assert est.n_pairs_gated == n_pairs_gated + int((~ok).sum())
    assert est.n_pairs_used == len(y) and not est.gated
    x_ref, P_ref, _, _ = information_form_reference(
        x0, P0, F, Q, y, ok.astype(float), tdoa_var=TDOA_STD_S**2, min_confidence=0.0, weighted=False,
        gate_probability=0.999)
    np.testing.assert_allclose(est.state, x_ref, rtol=1e-12, atol=1e-17)
    np.testing.assert_allclose(est.state_covariance, P_ref, rtol=1e-12, atol=1e-12 * np.abs(P_ref).max())


@pytest.mark.parametrize("duplicate", [copy.deepcopy, lambda est: pickle.loads(pickle.dumps(est))])
def test_deepcopy_continues_like_the_original(duplicate):
    # The compiled step writes the filter's arrays in place through one buffer array; a copy must
    # get its own buffer with its filter arrays attached to it, not detached copies of the views.
    _, tdoa, _ = drifting_track(4, 30, seed=13)
    est = kalman(4)
    for y in tdoa[:10]:
        est.update(y)
    twin = duplicate(est)
    assert twin._kf.x is twin._kf.x_post and twin._kf.x is not est._kf.x
    for a in (twin._kf.x, twin._kf.P, twin._kf.x_prior, twin._kf.P_prior, twin._toa_out):
        assert np.shares_memory(a, twin._buffers) and not np.shares_memory(a, est._buffers)
    for y in tdoa[10:]:
        np.testing.assert_array_equal(twin.update(y), est.update(y))
    np.testing.assert_array_equal(twin.state_covariance, est.state_covariance)
    assert twin.n_gated == est.n_gated


def test_init_waits_for_a_self_consistent_frame():
    n_mics = 4
    H = pair_matrix(n_mics)
    toa = random_toa(np.random.default_rng(14), n_mics)
    inconsistent = H @ toa
    inconsistent[5] += 1e-3  # pair (2, 3) on a reflection: breaks tdoa_23 = tdoa_03 - tdoa_02
    est = kalman(n_mics, init_max_residual_s=1e-5)
    np.testing.assert_array_equal(est.update(inconsistent), np.zeros(n_mics))
    assert not est.initialised and not est.reinitialised
    np.testing.assert_allclose(est.update(H @ toa), toa, atol=1e-15)
    assert est.initialised and est.reinitialised and est.n_reinit == 0


def test_shift_moves_state_and_prior():
    n_mics = 3
    _, tdoa, _ = drifting_track(n_mics, 10, seed=15)
    est = kalman(n_mics)
    for y in tdoa:
        est.update(y)
    x, x_prior, P = est.state, est._kf.x_prior.copy(), est.state_covariance
    est.shift(np.array([1e-3, 2e-3, -1e-3]), delta_rate_s_per_s=np.array([0.0, 1e-4, 0.0]))
    step = np.array([1e-3, -2e-3, 1e-4, 0.0])  # toa and rate against device 0
    np.testing.assert_allclose(est.state, x + step, rtol=0, atol=1e-18)
    np.testing.assert_allclose(est._kf.x_prior, x_prior + step, rtol=0, atol=1e-18)
    np.testing.assert_array_equal(est._kf.x_post, est.state)
    np.testing.assert_array_equal(est.state_covariance, P)


# -- fixed-lag smoother ----------------------------------------------------------------------------


def moving_track(n_mics: int, n_frames: int, seed: int):
    rng = np.random.default_rng(seed)
    t_s = np.arange(n_frames) * FRAME_S
    amp = rng.uniform(1e-3, 3e-3, n_mics)
    phase = rng.uniform(0, 2 * np.pi, n_mics)
    truth = amp * np.sin(2 * np.pi * 0.5 * t_s[:, None] + phase)
    truth -= truth[:, :1]
    H = pair_matrix(n_mics)
    return truth, truth @ H.T + rng.normal(0.0, 5 * TDOA_STD_S, (n_frames, len(H)))


def test_smoother_beats_filter_on_moving_track():
    n_mics, n_frames, lag = 4, 300, 8
    kw = dict(frame_period_s=FRAME_S, tdoa_std_s=5 * TDOA_STD_S, accel_std_s_per_s2=0.05)
    truth, tdoa = moving_track(n_mics, n_frames, seed=8)
    filt = KalmanToa(n_mics, **kw)
    smooth = FixedLagKalmanToa(n_mics, lag_frames=lag, **kw)
    f_out = np.array([filt.update(y) for y in tdoa])
    s_out = np.array([smooth.update(y) for y in tdoa])
    f_err = f_out[50:] - truth[50:]
    s_err = s_out[50:] - truth[50 - lag : n_frames - lag]  # output t is frame t - lag
    rmse_f, rmse_s = np.sqrt(np.mean(f_err**2)), np.sqrt(np.mean(s_err**2))
    assert rmse_s < 0.85 * rmse_f
    assert smooth.latency_s == pytest.approx(lag * FRAME_S)
    np.testing.assert_array_equal(smooth.filtered_toa_s, f_out[-1])


def test_smoother_first_frames_and_zero_lag():
    truth, tdoa = moving_track(3, 20, seed=9)
    kw = dict(frame_period_s=FRAME_S, tdoa_std_s=5 * TDOA_STD_S, accel_std_s_per_s2=0.05)
    filt = KalmanToa(3, **kw)
    s0 = FixedLagKalmanToa(3, lag_frames=0, **kw)
    s5 = FixedLagKalmanToa(3, lag_frames=5, **kw)
    for t, y in enumerate(tdoa):
        f = filt.update(y)
        np.testing.assert_array_equal(s0.update(y), f)
        out5 = s5.update(y)
        if t < 5:
            np.testing.assert_array_equal(out5, f)
    s5.reset()
    assert s5.initialised is False
    np.testing.assert_array_equal(s5.update(tdoa[0]), KalmanToa(3, **kw).update(tdoa[0]))


def test_smoother_equals_batch_rts():
    """Fixed lag L at the last frame equals the full RTS smoother over the last L+1 frames."""
    n_mics, lag = 3, 6
    truth, tdoa = moving_track(n_mics, 30, seed=10)
    kw = dict(frame_period_s=FRAME_S, tdoa_std_s=5 * TDOA_STD_S, accel_std_s_per_s2=0.05, gate_probability=None)
    smooth = FixedLagKalmanToa(n_mics, lag_frames=lag, **kw)
    filt = KalmanToa(n_mics, **kw)
    xs, Ps = [], []
    for y in tdoa:
        out = smooth.update(y)
        filt.update(y)
        xs.append(filt.state)
        Ps.append(filt.state_covariance)
    Ms, Ns = np.array(xs), np.array(Ps)
    F, Q = filt._kf.F, filt._kf.Q
    x_s = Ms[-1]
    for k in range(len(Ms) - 2, len(Ms) - 2 - lag, -1):
        P_pred = F @ Ns[k] @ F.T + Q
        C = Ns[k] @ F.T @ np.linalg.inv(P_pred)
        x_s = Ms[k] + C @ (x_s - F @ Ms[k])
    np.testing.assert_allclose(out[1:], x_s[: n_mics - 1], rtol=1e-9, atol=1e-15)


def test_shift_moves_the_track_without_gating():
    """A known jump of the fine TOA (the stream re-aligned a device) is absorbed by shift()."""
    from estimators import FixedLagKalmanToa, KalmanToa, pair_matrix

    H = pair_matrix(3)
    for cls, kw in ((KalmanToa, {}), (FixedLagKalmanToa, {"lag_frames": 3})):
        est = cls(3, frame_period_s=0.02, tdoa_std_s=1e-5, **kw)
        toa = np.array([0.0, 0.001, -0.002])
        for _ in range(20):
            est.update(H @ toa)
        jump = np.array([0.0, -0.004, 0.0])
        est.shift(jump)
        out = est.update(H @ (toa + jump))
        assert not est.gated
        if cls is KalmanToa:
            np.testing.assert_allclose(out, toa + jump, atol=2e-5)


def test_weak_prior_starts_before_every_device_is_heard():
    """With initial_toa_std_s the filter starts on the devices it hears; a silent one starts at 0."""
    from estimators import KalmanToa, pair_matrix, pairs

    H = pair_matrix(4)
    toa = np.array([0.0, 0.001, -0.002, 0.003])
    conf = np.where((pairs(4) == 3).any(axis=1), 0.0, 0.9)      # device 3 not heard yet
    waiting = KalmanToa(4, frame_period_s=0.02)
    started = KalmanToa(4, frame_period_s=0.02, initial_toa_std_s=0.005)
    waiting.update(H @ toa, conf)
    out = started.update(H @ toa, conf)
    assert not waiting.initialised and started.initialised
    np.testing.assert_allclose(out[:3], toa[:3], atol=1e-6)
    assert out[3] == pytest.approx(0.0, abs=1e-6)
