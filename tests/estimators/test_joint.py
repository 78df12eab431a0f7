"""The joint fit's linear-time pieces against dense references on small trials."""

import numpy as np
import pytest

from skelid.estimators.fit.joint import (
    _arrow_inverse_blocks,
    _banded,
    _dense_from_banded,
    _inverse_diagonal,
    _smoothed_bias_dense,
    joint_fit,
    smoothing_penalty,
    weighted_terms,
)
from skelid.estimators.fit.likelihood import pose_information
from skelid.model.kinematics import marker_jacobian
from skelid.simulate import builtin_model, simulate


def _small_fit(n_frames=40, seed=3):
    model = builtin_model("case-a")
    trial = simulate(model, sigma=5.0, n_frames=n_frames, rng=np.random.default_rng(seed))
    y = trial.data.positions
    _, Jq, _ = weighted_terms(model, trial.theta, trial.pose, y)
    R = smoothing_penalty(model, pose_information(Jq), trial.data.rate, 8.0)
    return model, y, trial.theta, trial.pose, R


def _dense_normal_matrix(model, y, theta, q, R):
    P, Q, T = model.n_params, model.n_pose, len(q)
    _, Jq, Jt = weighted_terms(model, theta, q, y)
    J = np.zeros((T, Jq.shape[1], P + T * Q))  # rows of frame t: theta columns, then its own pose block
    J[:, :, :P] = Jt
    for t in range(T):
        J[t, :, P + t * Q:P + (t + 1) * Q] = Jq[t]
    J = J.reshape(-1, P + T * Q)
    N = J.T @ J
    N[P:, P:] += R.toarray()
    return N, J


def _frame_index(P, Q, T):
    return np.concatenate([np.broadcast_to(np.arange(P), (T, P)), P + np.arange(T)[:, None] * Q + np.arange(Q)], 1)


def test_banded_form_is_the_block_diagonal_plus_the_penalty():
    model, y, theta, q, R = _small_fit(n_frames=12)
    _, Jq, _ = weighted_terms(model, theta, q, y)
    Hqq = pose_information(Jq)
    T, Q = q.shape
    dense = R.toarray()
    for t in range(T):
        dense[t * Q:(t + 1) * Q, t * Q:(t + 1) * Q] += Hqq[t]
    for _ in range(2):  # the second call takes the places cached by the first
        np.testing.assert_array_equal(_dense_from_banded(_banded(Hqq, R)), dense)


def test_inverse_diagonal_falls_back_to_the_pseudo_inverse():
    S = np.array([[4.0, 1.0], [1.0, 3.0]])
    np.testing.assert_allclose(_inverse_diagonal(S), np.diag(np.linalg.inv(S)), rtol=1e-15)
    singular = np.array([[1.0, 1.0], [1.0, 1.0]])
    np.testing.assert_allclose(_inverse_diagonal(singular), np.diag(np.linalg.pinv(singular)), rtol=1e-12)


def test_arrow_inverse_blocks_equal_the_dense_inverse():
    model, y, theta, q, R = _small_fit()
    P, Q, T = model.n_params, model.n_pose, len(q)
    _, Jq, Jt = weighted_terms(model, theta, q, y)
    blocks, S_inv, _ = _arrow_inverse_blocks(pose_information(Jq), np.einsum("tki,tkp->tip", Jq, Jt),
                                             np.einsum("tkp,tkq->pq", Jt, Jt), R)
    N, _ = _dense_normal_matrix(model, y, theta, q, R)
    C = np.linalg.inv(N)
    idx = _frame_index(P, Q, T)
    dense = C[idx[:, :, None], idx[:, None, :]]
    scale = np.sqrt(np.einsum("tii->ti", dense))
    np.testing.assert_allclose(blocks / (scale[:, :, None] * scale[:, None, :]),
                               dense / (scale[:, :, None] * scale[:, None, :]), atol=1e-8)
    np.testing.assert_allclose(S_inv, C[:P, :P], rtol=1e-8)


def test_smoothed_bias_equals_the_dense_formula():
    """b = sigma^2 C (-1/2 J^T d + sum_i H_i v_i), d_i = tr(C J^T J C H_i), v_i = (C R C J^T)_i, all dense."""
    model, y, theta, q, R = _small_fit()
    P, Q, T = model.n_params, model.n_pose, len(q)
    N, J = _dense_normal_matrix(model, y, theta, q, R)
    C = np.linalg.inv(N)
    Rt = np.zeros_like(N)
    Rt[P:, P:] = R.toarray()
    Sig, V = C @ (N - Rt) @ C, C @ Rt @ C @ J.T
    step = 1e-4
    m = J.shape[0] // T
    w = np.zeros(P + T * Q)
    for t in range(T):  # second derivatives of frame t's rows in (theta, q_t) by central differences
        cols = _frame_index(P, Q, T)[t]
        H = np.zeros((m, P + Q, P + Q))
        for j in range(P + Q):
            e = np.zeros(P + Q)
            e[j] = step
            _, qp, tp = marker_jacobian(model, theta + e[:P], q[t] + e[P:])
            _, qm, tm = marker_jacobian(model, theta - e[:P], q[t] - e[P:])
            H[:, j, :] = (np.concatenate([tp, qp], -1) - np.concatenate([tm, qm], -1)).reshape(m, P + Q) / (2 * step)
        rows = slice(t * m, (t + 1) * m)
        d = np.einsum("ijl,lj->i", H, Sig[np.ix_(cols, cols)])
        w += -0.5 * J[rows].T @ d
        w[cols] += np.einsum("ijl,li->j", H, V[np.ix_(cols, np.arange(J.shape[0])[rows])])
    expected = (C @ w)[:P]
    b, S, _ = _smoothed_bias_dense(model, y, theta, q, 1.0, R, step)
    np.testing.assert_allclose(b, expected, rtol=1e-6)
    np.testing.assert_allclose(S, np.linalg.inv(C[:P, :P]), rtol=1e-8)


@pytest.mark.parametrize("cutoff", [None, 6.0])
def test_joint_fit_stops_where_a_fit_run_to_the_cost_rounding_stops(cutoff):
    model = builtin_model("case-a")
    trial = simulate(model, sigma=15.0, n_frames=80, rng=np.random.default_rng(5))
    y, rate = trial.data.positions, trial.data.rate
    fit = joint_fit(model, y, model.theta_center, trial.pose, rate=rate, cutoff=cutoff)
    assert fit.converged and fit.n_iter < 100
    tight = joint_fit(model, y, fit.theta, fit.pose, n_iter=300, tol=0.0, step_tol=0.0, penalty=fit.penalty,
                      rate=rate, cutoff=cutoff)
    sd = np.sqrt(np.diag(np.linalg.inv(fit.info)) * fit.rss / (fit.n_obs - fit.pose_dof - model.n_params))
    assert np.all(np.abs(tight.theta - fit.theta) <= 1e-6 * sd)


def test_an_optimum_beyond_a_bound_is_reached_on_the_bound_as_a_bounded_solver_finds_it():
    # the elbow centre's x lies 20 mm beyond its upper bound: the fit holds it on the bound and
    # solves for the rest (poses included) as a generic bounded least-squares solver does
    from scipy.optimize import least_squares

    from skelid.estimators.fit.joint import weighted_terms
    from tests.estimators.test_noise import two_link

    model = two_link()
    trial = simulate(model, sigma=1.0, n_frames=30, rng=np.random.default_rng(5))
    truth = trial.theta
    lo, hi = truth - np.array([40.0, 40.0]), truth + np.array([-20.0, 40.0])
    start = np.array([hi[0] - 5.0, truth[1]])
    y = trial.data.positions
    fit = joint_fit(model, y, start, trial.pose, bounds=(lo, hi), tol=1e-14, n_iter=200)
    P, T, Q = model.n_params, len(y), model.n_pose

    def resid(x):
        return weighted_terms(model, x[:P], x[P:].reshape(T, Q), y, None)[0].ravel()

    big = np.full(T * Q, np.inf)
    ref = least_squares(resid, np.concatenate([start, trial.pose.ravel()]), xtol=1e-15, ftol=1e-15, gtol=1e-15,
                        bounds=(np.concatenate([lo, -big]), np.concatenate([hi, big])))
    assert fit.converged and fit.theta[0] == pytest.approx(hi[0])
    np.testing.assert_allclose(fit.theta, ref.x[:P], atol=1e-5)
    np.testing.assert_allclose(fit.pose.ravel(), ref.x[P:], atol=1e-5)
