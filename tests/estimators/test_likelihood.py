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


def _gait_like_terms(seed=3, T=40, M=12, Q=9, S=5):
    """Pose Jacobians with translation columns 1000 times smaller than rotation ones (a model in mm), scale
    columns that reach every marker, three offset columns per marker reaching its own rows only, one
    marker with two (its third zero everywhere, as is one more), a frame without markers; the columns shuffled."""
    rng = np.random.default_rng(seed)
    Jq = rng.standard_normal((T, 3 * M, Q)) * np.r_[np.full(3, 1.0), np.full(Q - 3, 1000.0)]
    P = S + 3 * M + 1
    Jt = np.zeros((T, 3 * M, P))
    Jt[..., :S] = rng.standard_normal((T, 3 * M, S)) * 300.0
    for k in range(M):
        Jt[:, 3 * k:3 * k + 3, S + 3 * k:S + 3 * k + 3] = rng.standard_normal((T, 3, 3))
    Jt[:, 3:6, S + 5] = 0.0  # the second marker moves with two of its offsets only
    Jq[4], Jt[4] = 0.0, 0.0
    order = rng.permutation(P)
    return Jq, Jt[..., order], rng.standard_normal((T, 3 * M)), np.repeat(rng.uniform(0.3, 3.0, M), 3)


def test_projected_sums_equal_the_sums_of_the_projected_jacobian():
    """The pose-projected information, score and weighted information made without the projected Jacobian
    (each marker's own columns through its rows only, the pose information scaled to a unit diagonal), and
    the score alone from the projected residuals, equal those of an orthogonal projection to 1e-9 of each
    entry's scale."""
    from skelid._linalg import summed_gram, summed_product
    from skelid.estimators.fit.likelihood import projected_score, projected_sums

    Jq, Jt, r, w = _gait_like_terms()
    Qm = np.linalg.qr(Jq)[0]
    K = Jt - Qm @ (np.swapaxes(Qm, -1, -2) @ Jt)
    want = summed_gram(K), summed_product(K, r), summed_gram(K, w=w)
    got = projected_sums(Jq, Jt, r, 3, w)
    assert len(got) == 3 and len(projected_sums(Jq, Jt, r, 3)) == 2
    sd = np.sqrt(np.diag(want[0]))
    zero = sd == 0  # the columns that move nothing
    assert zero.sum() == 2 and not got[0][zero].any() and not got[2][:, zero].any()
    s = np.where(zero, 1.0, sd)
    np.testing.assert_allclose(got[0] / np.outer(s, s), want[0] / np.outer(s, s), rtol=0, atol=1e-9)
    np.testing.assert_allclose(got[1] / s, want[1] / s, rtol=0, atol=1e-9 * np.abs(want[1] / s).max())
    np.testing.assert_allclose(projected_score(Jq, Jt, r) / s, want[1] / s, rtol=0,
                               atol=1e-9 * np.abs(want[1] / s).max())
    sw = np.sqrt(np.where(zero, 1.0, np.diag(want[2])))
    np.testing.assert_allclose(got[2] / np.outer(sw, sw), want[2] / np.outer(sw, sw), rtol=0, atol=1e-9)
