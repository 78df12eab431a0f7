"""The artefact's slopes estimated with the geometry: a linear mixed model checked against its direct solution."""

import numpy as np
import pytest

from skelid.estimators.checks.pose_artefact import SlideTerms, joint_slide


def _mixed_problem(seed, T=300, bodies=6, per_body=3, C=3, P=4, sigma=1.0, tau_s=3.0, tau_o=1.5):
    """Residuals of a linear fit whose markers slide linearly with the pose (no pose to profile); ``tau_s``
    one shared size for every body or one per body."""
    rng = np.random.default_rng(seed)
    M = bodies * per_body
    body = np.repeat(np.arange(bodies), per_body)
    dq = rng.normal(0.0, 0.5, (T, C))
    K = rng.normal(size=(T, M, 3, P))
    tau_s = np.broadcast_to(np.asarray(tau_s, float), (bodies,))[:, None, None]
    V = (rng.normal(0.0, 1.0, (bodies, 3, C)) * tau_s)[body] + rng.normal(0.0, tau_o, (M, 3, C))  # (M, 3, C)
    y = np.einsum("mac,tc->tma", V, dq) + rng.normal(0.0, sigma, (T, M, 3))
    Kf = K.reshape(T * M * 3, P)
    theta = np.linalg.lstsq(Kf, y.reshape(-1), rcond=None)[0]  # the fit that knows of no slide
    r = y - np.einsum("tmap,p->tma", K, theta)
    A = np.zeros((3 * M, 3 * M, C, C))
    DD = dq.T @ dq
    for i in range(3 * M):
        A[i, i] = DD
    terms = SlideTerms(A=A, b=np.einsum("tma,tc->mac", r, dq), G=np.einsum("tmap,tc->mpac", K, dq),
                       bodies=tuple(np.flatnonzero(body == b) for b in range(bodies)),
                       tau_s2=1.0, tau_o2=0.25, rss=float(np.sum(r**2)))
    # the columns of the slide: each marker's own slopes, and its body's
    Z_own = np.einsum("tc,ab,mn->tmanbc", dq, np.eye(3), np.eye(M)).reshape(T * M * 3, M * 3 * C)
    Z_body = np.einsum("tc,ab,mn->tmanbc", dq, np.eye(3), np.eye(bodies)[body]).reshape(T * M * 3, -1)
    return terms, Kf, r.reshape(-1), Z_own, Z_body, T * M * 3 - P


def test_the_joint_slide_is_the_mixed_models_posterior_at_the_sizes_it_finds():
    terms, K, r, Z_own, Z_body, dof = _mixed_problem(1, T=120, bodies=3, per_body=2, C=2, P=3)
    lam = np.full(K.shape[1], 1e-6)
    fit = joint_slide(terms, K.T @ K, K.T @ r, np.zeros(K.shape[1]), lam, dof)
    s2 = fit.sigma_white**2
    shared = np.repeat(fit.tau_bodies**2, Z_body.shape[1] // len(fit.tau_bodies))  # each body's own size
    cov_v = np.concatenate([shared, np.full(Z_own.shape[1], fit.tau_own**2)])
    Z = np.concatenate([Z_body, Z_own], axis=1)
    Sigma = s2 * np.eye(len(r)) + (Z * cov_v) @ Z.T
    Si = np.linalg.inv(Sigma)
    cov = np.linalg.inv(K.T @ Si @ K + np.diag(lam))
    np.testing.assert_allclose(fit.cov, cov, rtol=1e-6, atol=1e-12 * np.abs(cov).max())
    np.testing.assert_allclose(fit.shift, cov @ K.T @ Si @ r, rtol=1e-6, atol=1e-8 * np.sqrt(np.diag(cov)).max())


@pytest.mark.parametrize("seed, start", [(2, (1.0, 0.25)), (3, (0.0, 0.0)), (5, (40.0, 0.0))])
def test_the_marginal_likelihood_finds_the_white_level_and_both_slope_sizes(seed, start):
    # whatever the moment fit's start (none, or the own slopes taken for none), the three sizes are found
    terms, K, r, *_, dof = _mixed_problem(seed, sigma=1.0, tau_s=3.0, tau_o=1.5)
    terms = SlideTerms(**{**terms.__dict__, "tau_s2": start[0], "tau_o2": start[1], "pose_spread": 0.25})
    fit = joint_slide(terms, K.T @ K, K.T @ r, np.zeros(K.shape[1]), np.full(K.shape[1], 1e-6), dof)
    assert fit.sigma_white == pytest.approx(1.0, rel=0.05)
    assert fit.tau_shared == pytest.approx(3.0, rel=0.3)
    assert fit.tau_own == pytest.approx(1.5, rel=0.15)
    assert fit.rms == pytest.approx(np.sqrt((fit.tau_shared**2 + fit.tau_own**2) * 0.25))


def test_each_body_slides_by_its_own_amount():
    # bodies whose skin slides 0.5 to 8 per radian: each body's shared size is found, not one for all
    tau = np.array([0.5, 1.0, 2.0, 4.0, 8.0, 8.0])
    terms, K, r, *_, dof = _mixed_problem(8, T=300, per_body=4, tau_s=tau, tau_o=0.5)
    fit = joint_slide(terms, K.T @ K, K.T @ r, np.zeros(K.shape[1]), np.full(K.shape[1], 1e-6), dof)
    np.testing.assert_allclose(np.log(fit.tau_bodies), np.log(tau), atol=0.7)
    assert fit.tau_own == pytest.approx(0.5, rel=0.15)
    one = joint_slide(terms, K.T @ K, K.T @ r, np.zeros(K.shape[1]), np.full(K.shape[1], 1e-6), dof,
                      sizes=(fit.sigma_white**2, fit.tau_shared**2, fit.tau_own**2))  # one size for every body
    np.testing.assert_allclose(one.tau_bodies, fit.tau_shared)


def test_a_slide_the_geometry_cannot_see_leaves_the_estimate_and_narrows_nothing_it_should_not():
    # the geometry's columns orthogonal to every slide column: no step, and the geometry's own covariance
    terms, K, r, Z_own, Z_body, dof = _mixed_problem(4, T=100, bodies=2, per_body=2, C=2, P=2)
    Z = np.concatenate([Z_body, Z_own], axis=1)
    Kp = K - Z @ np.linalg.lstsq(Z, K, rcond=None)[0]
    r = r - Kp @ np.linalg.lstsq(Kp, r, rcond=None)[0]
    G = np.einsum("np,nk->pk", Kp, Z_own).reshape(2, 4, 3, 2).transpose(1, 0, 2, 3)
    terms = SlideTerms(**{**terms.__dict__, "G": G, "b": (Z_own.T @ r).reshape(4, 3, 2), "rss": float(r @ r)})
    fit = joint_slide(terms, Kp.T @ Kp, Kp.T @ r, np.zeros(2), np.full(2, 1e-9), dof)
    np.testing.assert_allclose(fit.shift, 0.0, atol=1e-8)
    np.testing.assert_allclose(fit.cov, fit.sigma_white**2 * np.linalg.inv(Kp.T @ Kp), rtol=1e-6)


def test_the_slide_follows_every_direction_the_poses_take_and_none_they_never_take():
    from skelid.estimators.checks.pose_artefact import slide_basis

    rng = np.random.default_rng(6)
    dq = rng.normal(size=(200, 4)) * [1.0, 0.3, 0.01, 0.0]  # the last coordinate locked
    B = slide_basis([dq[:120], dq[120:]])
    assert B.shape == (4, 3)  # even a direction of 1e-4 of the motion is kept; the locked one is not
    np.testing.assert_allclose(B.T @ B, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(B[3], 0.0, atol=1e-12)
    assert slide_basis([dq], max_directions=2).shape == (4, 2)  # the bound on the slopes keeps the main ones
    np.testing.assert_allclose(np.abs(slide_basis([dq], max_directions=1)[:, 0]), [1, 0, 0, 0], atol=0.05)


def test_sizes_given_are_taken_and_give_the_fit_those_sizes_found():
    terms, K, r, *_, dof = _mixed_problem(7, T=150, bodies=3, per_body=2, C=2, P=3)
    args = (terms, K.T @ K, K.T @ r, np.zeros(K.shape[1]), np.full(K.shape[1], 1e-6), dof)
    found = joint_slide(*args)
    sizes = found.sizes
    again = joint_slide(*args, sizes=sizes)
    np.testing.assert_allclose(again.shift, found.shift, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(again.cov, found.cov, rtol=1e-10)
    other = joint_slide(*args, sizes=(sizes[0], 4.0 * sizes[1], 4.0 * sizes[2]))
    assert other.tau_shared == pytest.approx(2.0 * found.tau_shared)
    np.testing.assert_allclose(other.tau_bodies, 2.0 * found.tau_bodies)
    assert np.trace(other.cov) > np.trace(found.cov)  # larger slopes a priori: the geometry less known


def test_the_profiled_likelihoods_gradient_is_its_derivative_and_its_optimum_the_sizes():
    """The search's objective, with the white level profiled out in closed form: its analytic gradient
    against central differences, and the sizes at its optimum near the simulated ones."""
    from skelid.estimators.checks import pose_artefact as pa

    terms, K, r, *_, dof = _mixed_problem(4, T=150, bodies=3, per_body=2, C=2, P=3, tau_s=[4.0, 1.0, 2.0])
    M, P, _, C = terms.G.shape
    n_own = M * 3 * C
    A = terms.A.reshape(M, 3, M, 3, C, C).transpose(0, 1, 4, 2, 3, 5).reshape(n_own, n_own)
    Gf = terms.G.reshape(M, P, 3 * C).transpose(1, 0, 2).reshape(P, n_own)
    nll, bounds, starts, sizes = pa._size_likelihood(terms, K.T @ K, K.T @ r, dof, Gf, A, n_own)
    for y in [starts[0], np.log([0.3, 2.0, 0.05, 8.0])]:
        f, g = nll(y)
        fd = [(nll(y + h)[0] - nll(y - h)[0]) / 2e-6 for h in 1e-6 * np.eye(len(y))]
        np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-6 * max(1.0, np.abs(fd).max()))
    s2, ts2, to2 = sizes(pa._size_search(nll, bounds, starts))
    assert s2 == pytest.approx(1.0, rel=0.1) and to2 == pytest.approx(1.5**2, rel=0.6)
    assert ts2[0] > ts2[1]  # the body that slides most has the largest shared size
