"""The parametric bootstrap's linear control variate against dense algebra, finite differences and refits."""

import numpy as np
import pytest

from skelid.estimators.fit.joint import joint_fit, usable_frames
from skelid.estimators.marker import MarkerEstimator
from skelid.estimators.uncertainty.bootstrap import (
    Draws,
    as_draws,
    draws_bias,
    draws_covariance,
    draws_mc_covariance,
    linear_response,
)
from skelid.estimators.uncertainty.singular import fallback_covariance
from skelid.model.kinematics import marker_positions
from skelid.simulate import builtin_model, simulate
from tests.estimators.test_joint import _dense_normal_matrix, _small_fit


@pytest.mark.parametrize("smooth", [False, True])
def test_the_linear_response_is_the_dense_gauss_newton_step(smooth):
    model, y, theta, q, _ = _small_fit(n_frames=30)
    P, Q, T = model.n_params, model.n_pose, len(q)
    y = y.copy()
    y[4, 1] = np.nan  # a missing marker has no rows
    y[9, :2] = np.nan  # nor has a frame whose markers do not fix its pose
    noise = np.random.default_rng(0).normal(0.0, 5.0, size=(3,) + y.shape)
    rate, cutoff = (100.0, 8.0) if smooth else (None, None)
    lin = linear_response(model, y, theta, q, noise, rate, cutoff)
    R = lin.penalty if smooth else np.zeros((T * Q, T * Q))
    N, J = _dense_normal_matrix(model, np.where(usable_frames(model, y)[:, None, None], y, np.nan), theta, q,
                                _Dense(R))
    N[P:, P:] += 1e-10 * np.diag(np.tile(np.maximum(np.diag(N)[P:].reshape(T, Q).mean(axis=0), 1e-300), T)) \
        if smooth else 1e-12 * np.eye(T * Q)  # the solvers' ridge keeps the frame without rows definite
    e = np.where(np.isfinite(y)[None], noise, 0.0).reshape(3, -1)
    step = np.linalg.solve(N, J.T @ e.T).T  # (3, P + T Q)
    np.testing.assert_allclose(lin.theta, step[:, :P], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(lin.pose, step[:, P:].reshape(3, T, Q), rtol=1e-6, atol=1e-6 * np.abs(step).max())
    A = np.linalg.solve(N, J.T)[:P]  # theta's step per unit of noise
    np.testing.assert_allclose(lin.cov_unit, A @ A.T, rtol=1e-6)


class _Dense:
    """A dense matrix with the sparse ``toarray`` the dense helper calls."""

    def __init__(self, R):
        self.R = R

    def toarray(self):
        return self.R.toarray() if hasattr(self.R, "toarray") else np.asarray(self.R)


@pytest.mark.parametrize("smooth", [False, True])
def test_the_linear_response_is_the_refits_derivative_in_the_noise(smooth):
    # at zero noise the refit stays at the simulated point (poses on a parabola: no motion-model pull),
    # so the central difference of the refit in the noise's size is the linear response
    model = builtin_model("case-a")
    theta = np.array([250.0])
    s = np.linspace(-1.0, 1.0, 30)[:, None]
    q = np.array([30.0, -40.0, 2.0, 2.0, 0.75]) + np.array([10.0, 5.0, 0.1, 0.3, 0.05]) * s \
        + np.array([3.0, -2.0, 0.05, -0.1, 0.02]) * s**2
    clean = marker_positions(model, theta, q)
    e = np.random.default_rng(1).normal(0.0, 1.0, size=clean.shape)
    rate, cutoff = (100.0, 6.0) if smooth else (None, None)
    lin = linear_response(model, clean, theta, q, e[None], rate, cutoff)
    h = 0.1  # mm: far below the curvature (error h^2), far above the refits' stopping rules

    def refit(sign):
        f = joint_fit(model, clean + sign * h * e, theta, q, penalty=lin.penalty, step_tol=1e-10, tol=1e-15,
                      n_iter=500)
        assert f.converged
        return f.theta

    np.testing.assert_allclose((refit(1.0) - refit(-1.0)) / (2 * h), lin.theta[0], rtol=1e-3)


def test_the_control_variate_keeps_the_bootstraps_mean_and_shrinks_its_error():
    model = builtin_model("case-a")
    trial = simulate(model, sigma=15.0, n_frames=400, rng=np.random.default_rng(4))
    y = trial.data.positions
    fit = joint_fit(model, y, trial.theta, trial.pose, rate=100.0, cutoff=6.0, step_tol=1e-3)
    B = 12
    d = MarkerEstimator(model, n_boot=B)._bootstrap_bias(y, fit, 15.0, 100.0, 6.0, None, np.random.default_rng(5))
    assert isinstance(d, Draws) and d.shifts.shape == d.linear.shape == (B, 1)
    # plain and control-variate means differ by mean(l), which has mean zero and a known sd
    se_l = np.sqrt(np.diag(d.linear_cov) / B)
    assert np.all(np.abs(d.shifts.mean(axis=0) - draws_bias(d)) <= 4 * se_l)
    # the rest varies far less than the shift: a smaller Monte Carlo error for the same refits
    assert np.all(np.std(d.shifts - d.linear, axis=0) < 0.5 * np.std(d.shifts, axis=0))
    # the linear parts' known covariance is their spread (1000 draws of the linear step alone: sd 4.5 %)
    clean = marker_positions(model, fit.theta, fit.pose)
    noise = np.random.default_rng(6).normal(0.0, 15.0, size=(1000,) + clean.shape)
    lin = linear_response(model, y, fit.theta, fit.pose, noise, 100.0, 6.0)
    assert float(np.var(lin.theta, ddof=1) / (225.0 * lin.cov_unit[0, 0])) == pytest.approx(1.0, abs=0.15)
    np.testing.assert_allclose(225.0 * lin.cov_unit, d.linear_cov)


def test_draws_without_a_control_variate_are_the_plain_bootstrap():
    shifts = np.array([[1.0, 0.0], [3.0, 2.0], [5.0, 0.0], [7.0, 2.0]])
    d = as_draws(shifts)
    np.testing.assert_allclose(draws_bias(d), shifts.mean(axis=0))
    np.testing.assert_allclose(draws_covariance(d), np.cov(shifts, rowvar=False))
    np.testing.assert_allclose(draws_mc_covariance(d), np.cov(shifts, rowvar=False) / 4)
    assert as_draws(d) is d


def test_fallback_covariance_with_control_variates_closed_form():
    s = np.array([[1.0], [3.0], [6.0]])
    lin = np.array([[-1.0], [0.0], [2.0]])
    d = Draws(s, lin, np.array([[2.0]]))
    # Var(l) + Cov(s) - Cov(l), less plain, plus Cov(s - l) / B and the disagreement's term
    c = 2.0 + np.var(s, ddof=1) - np.var(lin, ddof=1)
    expected = max(c - 1.5, 0.0) + np.var(s - lin, ddof=1) / 3 + 0.25 * 0.4**2
    np.testing.assert_allclose(fallback_covariance(d, np.array([[1.5]]), np.array([0.4])), [[expected]])
    assert draws_bias(d)[0] == pytest.approx(np.mean(s - lin))


def test_the_linear_response_without_a_motion_model_has_the_bound_as_its_covariance():
    # every pose free: the first Gauss-Newton step is the efficient score over the efficient
    # information, so its covariance is exactly the Cramer-Rao bound (the accuracy study's control variate)
    from skelid.estimators.fit.likelihood import efficient_information, frame_terms

    model = builtin_model("case-b")
    trial = simulate(model, n_frames=40, sigma=3.0, rng=np.random.default_rng(2))
    lin = linear_response(model, trial.clean, trial.theta, trial.pose, np.zeros((1,) + trial.clean.shape))
    _, Jq, Jt = frame_terms(model, trial.theta, trial.pose, trial.clean)
    bound = np.linalg.inv(efficient_information(Jq, Jt, 3.0))
    np.testing.assert_allclose(9.0 * lin.cov_unit, bound, rtol=1e-6)  # the solver's 1e-12 ridge
    np.testing.assert_allclose(lin.theta, 0.0, atol=1e-12)  # no noise, no step
