import dataclasses

import numpy as np
import pytest
from scipy.stats import norm

from skelid.estimators.uncertainty.posterior import GaussianPosterior, GridPosterior, SamplePosterior


def _gauss_grid(mu=3.0, sd=0.7):
    x = np.linspace(-5, 10, 3001)
    return GridPosterior.from_log_prior(("a",), (x,), norm.logpdf(x, mu, sd))


def test_grid_summaries_match_a_normal():
    p = _gauss_grid()
    assert p.mean[0] == pytest.approx(3.0, abs=1e-6)
    assert p.sd[0] == pytest.approx(0.7, rel=1e-4)
    lo, hi = p.credible_interval(0.95)[0]
    assert lo == pytest.approx(3.0 - 1.959964 * 0.7, abs=2e-3)
    assert hi == pytest.approx(3.0 + 1.959964 * 0.7, abs=2e-3)
    assert p.map[0] == pytest.approx(3.0, abs=0.005)


def test_update_is_bayes_rule_and_immutable():
    p = _gauss_grid()
    x = p.axes[0]
    q = p.update(norm.logpdf(x, 4.0, 0.7), snapshot=True)
    assert p.n_updates == 0 and q.n_updates == 1 and len(q.history) == 1
    assert q.mean[0] == pytest.approx(3.5, abs=1e-6)
    assert q.weights.sum() == pytest.approx(1.0)


def test_samples_follow_the_posterior():
    p = _gauss_grid()
    s = p.samples(20000, np.random.default_rng(0))
    assert s.shape == (20000, 1)
    assert s.mean() == pytest.approx(3.0, abs=0.02) and s.std() == pytest.approx(0.7, abs=0.02)


def test_two_dimensional_grid_marginals():
    x, y = np.linspace(-4, 4, 201), np.linspace(0, 10, 251)
    X, Y = np.meshgrid(x, y, indexing="ij")
    p = GridPosterior.from_log_prior(("x", "y"), (x, y), norm.logpdf(X, 1, 0.5) + norm.logpdf(Y, 6, 1))
    np.testing.assert_allclose(p.mean, [1, 6], atol=1e-3)
    np.testing.assert_allclose(p.sd, [0.5, 1.0], rtol=1e-3)
    assert p.grid_points.shape == (201 * 251, 2)


def test_gaussian_posterior():
    g = GaussianPosterior(("a", "b"), np.array([1.0, 2.0]), np.diag([4.0, 0.25]))
    np.testing.assert_allclose(g.sd, [2.0, 0.5])
    np.testing.assert_allclose(g.credible_interval(0.95)[1], [2 - 0.98, 2 + 0.98], atol=1e-3)
    assert g.samples(10, np.random.default_rng(0)).shape == (10, 2)


def test_sample_posterior_summaries_match_a_normal():
    rng = np.random.default_rng(3)
    x = rng.normal([1.0, -2.0], [0.5, 2.0], size=(40000, 2))
    p = SamplePosterior(("a", "b"), x, log_target=norm.logpdf(x, [1.0, -2.0], [0.5, 2.0]).sum(axis=1))
    np.testing.assert_allclose(p.mean, [1.0, -2.0], atol=0.03)
    np.testing.assert_allclose(p.sd, [0.5, 2.0], rtol=0.02)
    ci = p.credible_interval(0.95)
    np.testing.assert_allclose(ci[0], [1.0 - 1.96 * 0.5, 1.0 + 1.96 * 0.5], atol=0.03)
    np.testing.assert_allclose(p.map, [1.0, -2.0], atol=0.1)
    assert p.ess == pytest.approx(40000)
    g = GaussianPosterior(("a", "b"), p.mean, p.cov)
    assert set(p.summary()) == set(g.summary()) and set(p.summary()["a"]) == set(g.summary()["a"])


def test_sample_posterior_weights_are_importance_weights():
    # uniform draws weighted by a normal density: the weighted sample is that normal
    rng = np.random.default_rng(4)
    x = rng.uniform(-6, 8, size=(50000, 1))
    p = SamplePosterior(("a",), x, log_weights=norm.logpdf(x[:, 0], 1.0, 0.8) + 123.0)
    assert p.weights.sum() == pytest.approx(1.0)
    assert p.mean[0] == pytest.approx(1.0, abs=0.02) and p.sd[0] == pytest.approx(0.8, abs=0.02)
    assert p.ess < 0.5 * len(x)  # unequal weights: Kish's ESS is smaller than N
    s = p.samples(20000, np.random.default_rng(5))
    assert s.mean() == pytest.approx(1.0, abs=0.03) and s.std() == pytest.approx(0.8, abs=0.03)


def test_sample_posterior_interval_stays_inside_the_support():
    # an exponential posterior against a bound at 0: the interval is skewed and never crosses it
    x = np.random.default_rng(6).exponential(1.0, size=(20000, 1))
    p = SamplePosterior(("a",), x)
    lo, hi = p.credible_interval(0.95)[0]
    assert 0.0 < lo == pytest.approx(np.log(1 / 0.975), abs=0.005) and hi == pytest.approx(np.log(40), rel=0.05)
    assert p.mean[0] - 1.96 * p.sd[0] < 0.0  # the normal approximation's would cross it
    assert p.map[0] < 0.3  # no log target: the KDE mode, near 0


def test_sample_posterior_is_immutable():
    p = SamplePosterior(("a",), np.arange(5.0)[:, None])
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.points = np.zeros((5, 1))
    with pytest.raises(ValueError):
        p.points[0, 0] = 3.0
    with pytest.raises(ValueError):
        SamplePosterior(("a", "b"), np.zeros((5, 1)))
    with pytest.raises(ValueError):
        SamplePosterior(("a",), np.zeros((3, 1)), log_weights=np.full(3, -np.inf))
