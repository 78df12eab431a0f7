"""Normal-equation pieces of the marker likelihood against per-frame loops."""

import numpy as np

from skelid.estimators.fit.likelihood import frame_terms, pose_information, projected_theta_jacobian
from tests.helpers import tree_3d_functional


def _stack():
    model = tree_3d_functional()
    rng = np.random.default_rng(2)
    theta = model.theta_nominal + rng.normal(0, 2, size=(4, 1, model.n_params))
    q = rng.normal(0, 0.6, size=(1, 5, model.n_pose))
    y = np.full((1, 5, len(model.markers), 3), 0.0)
    y[0, 2, 3] = np.nan  # a missing marker gives zero rows
    _, Jq, Jt = frame_terms(model, theta, q, y)
    return Jq, Jt


def test_pose_information_equals_a_loop_over_frames():
    Jq, _ = _stack()
    H = pose_information(Jq)
    assert H.shape == Jq.shape[:-2] + (Jq.shape[-1],) * 2
    for idx in np.ndindex(Jq.shape[:-2]):
        np.testing.assert_allclose(H[idx], Jq[idx].T @ Jq[idx], rtol=1e-13, atol=1e-9)


def test_projected_theta_jacobian_is_the_residual_of_a_least_squares_fit_on_the_pose_columns():
    Jq, Jt = _stack()
    Kp = projected_theta_jacobian(Jq, Jt)
    for idx in np.ndindex(Jq.shape[:-2]):
        coef, *_ = np.linalg.lstsq(Jq[idx], Jt[idx], rcond=None)
        np.testing.assert_allclose(Kp[idx], Jt[idx] - Jq[idx] @ coef, atol=1e-6 * np.abs(Jt[idx]).max())
