"""The tempered SMC core against closed forms and quadrature."""

import numpy as np
import pytest
from scipy.special import logsumexp
from scipy.stats import multivariate_normal, norm

from skelid.estimators.uncertainty.posterior import SamplePosterior
from skelid.estimators.uncertainty.smc import kish_ess, next_temperature, resample, tempered_smc


def test_systematic_resampling_counts_are_within_one_of_their_expectation():
    w = np.random.default_rng(0).dirichlet(np.ones(50))
    idx = resample(np.log(w), np.random.default_rng(1))
    counts = np.bincount(idx, minlength=50)
    assert counts.sum() == 50
    assert np.all(np.abs(counts - 50 * w) < 1.0)


def test_next_temperature_keeps_half_the_ess():
    ll = np.random.default_rng(2).normal(0.0, 30.0, size=400)
    lw = np.full(400, -np.log(400))
    b = next_temperature(ll, lw, 0.0, 200.0)
    assert 0.0 < b < 1.0
    assert kish_ess(lw + b * ll) == pytest.approx(200.0, rel=1e-6)
    assert next_temperature(np.zeros(400), lw, 0.3, 200.0) == 1.0  # a flat likelihood: straight to 1


def test_gaussian_prior_times_gaussian_likelihood_matches_the_closed_form():
    # prior N(0, 10^2 I) in 3-D, likelihood N(m, S): posterior N(mu, V) and evidence in closed form
    rng = np.random.default_rng(3)
    P, s0 = 3, 10.0
    m = np.array([2.0, -1.0, 4.0])
    A = np.array([[1.0, 0.0, 0.0], [0.6, 0.5, 0.0], [-0.3, 0.2, 0.3]])
    S = A @ A.T
    S_inv = np.linalg.inv(S)
    V = np.linalg.inv(S_inv + np.eye(P) / s0**2)
    mu = V @ S_inv @ m

    def log_lik(t):
        d = t - m
        return -0.5 * np.einsum("np,pq,nq->n", d, S_inv, d)

    def log_prior(t):
        return norm.logpdf(t, 0.0, s0).sum(axis=1)

    res = tempered_smc(log_lik, log_prior, rng.normal(0.0, s0, size=(1500, P)), rng, n_moves=5)
    post = SamplePosterior(("a", "b", "c"), res.particles, res.log_weights)
    sd = np.sqrt(np.diag(V))
    # Monte Carlo error with 1500 particles is a few hundredths of an sd (seeds 0-9: at most 0.07)
    assert np.all(np.abs(post.mean - mu) < 0.2 * sd), (post.mean, mu, sd)
    np.testing.assert_allclose(post.sd, sd, rtol=0.12)
    # Z = int N(t; 0, s0^2 I) exp(-(t-m)^T S^-1 (t-m) / 2) dt = (2 pi)^{P/2} |S|^{1/2} N(m; 0, S + s0^2 I)
    log_z = 0.5 * P * np.log(2 * np.pi) + 0.5 * np.linalg.slogdet(S)[1] \
        + multivariate_normal(np.zeros(P), S + s0**2 * np.eye(P)).logpdf(m)
    assert res.log_evidence == pytest.approx(log_z, abs=0.5)
    assert res.temperatures[0] == 0.0 and res.temperatures[-1] == 1.0 and res.completed
    assert np.all(np.diff(res.temperatures) > 0)
    assert np.all(res.ess >= 0.5 * 1500 - 1e-6)


def test_banana_target_matches_quadrature():
    # a curved, skewed 2-D posterior under a uniform prior on a box; compare with a fine grid
    b, a = 0.5, 1.5
    lo, hi = np.array([-5.0, -4.0]), np.array([5.0, 8.0])

    def log_lik(t):
        return -0.5 * (t[:, 0] / a) ** 2 - 0.5 * (t[:, 1] - b * (t[:, 0] ** 2 - a**2)) ** 2 / 0.5**2

    def log_prior(t):
        return np.where(np.all((t >= lo) & (t <= hi), axis=1), 0.0, -np.inf)

    rng = np.random.default_rng(4)
    res = tempered_smc(log_lik, log_prior, rng.uniform(lo, hi, size=(2000, 2)), rng, n_moves=8)
    post = SamplePosterior(("x", "y"), res.particles, res.log_weights)
    x, y = np.linspace(lo[0], hi[0], 801), np.linspace(lo[1], hi[1], 961)
    X, Y = np.meshgrid(x, y, indexing="ij")
    lg = log_lik(np.stack([X.ravel(), Y.ravel()], -1)).reshape(X.shape)
    w = np.exp(lg - logsumexp(lg))
    wx, wy = w.sum(axis=1), w.sum(axis=0)
    mean = np.array([wx @ x, wy @ y])
    sd = np.sqrt([wx @ (x - mean[0]) ** 2, wy @ (y - mean[1]) ** 2])
    # errors over seeds 0-9: means within 0.06 sd, sds within 7 %, the upper 5 % tail within 0.3 sd
    assert np.all(np.abs(post.mean - mean) < 0.15 * sd), (post.mean, mean, sd)
    np.testing.assert_allclose(post.sd, sd, rtol=0.12)
    q = np.interp([0.05, 0.95], np.cumsum(wy), y)  # y is skewed: its quantiles are not symmetric
    ci = post.credible_interval(0.90)[1]
    np.testing.assert_allclose(ci, q, atol=0.45 * sd[1])
    assert q[1] - mean[1] > 1.5 * (mean[1] - q[0])  # the check is on a clearly non-Gaussian shape
    assert ci[1] - post.mean[1] > 1.3 * (post.mean[1] - ci[0])  # and the samples show it
    # evidence: the prior is uniform on the box, Z = (int L) / area
    log_z = logsumexp(lg) + np.log((x[1] - x[0]) * (y[1] - y[0])) - np.log(np.prod(hi - lo))
    assert res.log_evidence == pytest.approx(log_z, abs=0.3)


def test_carried_state_follows_its_particle():
    # the state is the theta it was computed at: after resampling and moves it must still match
    calls = []

    def log_lik(t, carry):
        calls.append(len(t))
        assert carry.shape == t.shape
        return -0.5 * np.sum(t**2, axis=1) / 0.1**2, t.copy()

    rng = np.random.default_rng(5)
    init = rng.uniform(-1, 1, size=(300, 2))
    temps = []
    res = tempered_smc(log_lik, lambda t: np.where(np.all(np.abs(t) <= 1, axis=1), 0.0, -np.inf),
                       init, rng, carry=init.copy(), on_stage=temps.append)
    np.testing.assert_array_equal(res.carry, res.particles)
    assert temps == list(res.temperatures)  # told each temperature before evaluating for it
    assert res.n_evaluations == sum(calls)
    np.testing.assert_allclose(res.log_likelihood, -0.5 * np.sum(res.particles**2, axis=1) / 0.01)
