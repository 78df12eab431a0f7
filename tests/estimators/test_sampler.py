"""The marker-smc estimator: profile likelihood, agreement with the normal posterior, bounds."""

import json
import warnings

import numpy as np
import pytest
from scipy.special import logsumexp

from skelid.cli import main
from skelid.errors import IdentifiabilityError, SkelidWarning
from skelid.estimators.marker import MarkerEstimator
from skelid.estimators.sampler import ProfileLikelihood, SamplerEstimator, sample_prior
from skelid.estimators.uncertainty.posterior import SamplePosterior
from skelid.io.results import result_to_dict
from skelid.model import model_from_dict
from skelid.registry import estimators as methods
from skelid.simulate import builtin_model, simulate
from tests.conftest import EXAMPLES


def quadrature(est, grid):
    """Mean, sd and 95 % interval of ``exp(l)`` on ``grid`` (one parameter, flat prior on the grid).

    ``l`` is the estimator's own likelihood, each grid point solved to tolerance starting from its
    nearest solved neighbour (continuation outward from the estimate).
    """
    fit = est.fit_info_
    like = ProfileLikelihood(est.model, est.y_, fit.theta, fit.pose, fit.penalty, est.sigma_**2, est.bias_,
                             tau=est.likelihood_tau_, scale=np.sqrt(np.diag(est.cov_data_)))
    ll = np.empty(grid.size)
    carry = {}
    for i in np.argsort(np.abs(grid - (fit.theta[0] - est.bias_[0]))):
        j = min(carry, key=lambda k: abs(k - i)) if carry else None
        l_i, carry[i] = like.refine(grid[i][None, None], like.initial_carry(1) if j is None else carry[j])
        ll[i] = l_i[0]
    w = np.exp(ll - logsumexp(ll))
    mean = w @ grid
    return mean, np.sqrt(w @ (grid - mean) ** 2), np.interp([0.025, 0.975], np.cumsum(w) - w / 2, grid)


@pytest.fixture(scope="module")
def case_a_fit():
    """Case A, 150 frames at 5 mm: a posterior the normal approximation describes well."""
    model = builtin_model("case-a")
    trial = simulate(model, theta=[250.0], n_frames=150, sigma=5.0, rng=np.random.default_rng(11))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkelidWarning)
        est = SamplerEstimator(model, rng=np.random.default_rng(0), n_particles=300).fit(trial.data)
    return model, trial, est


def test_profile_likelihood_has_the_curvature_of_the_normal_posterior(case_a_fit):
    # deterministic: l(theta_ + k sd) = -k^2/2 to within the curvature the Gauss-Newton information misses
    model, _, est = case_a_fit
    fit = est.fit_info_
    like = ProfileLikelihood(model, est.y_, fit.theta, fit.pose, fit.penalty, est.sigma_**2, est.bias_,
                             scale=est.crlb_motion_sd_)
    sd = est.gaussian_posterior_.sd[0]
    k = np.array([-3.0, -1.0, 0.0, 1.0, 3.0])
    theta = est.gaussian_posterior_.mean[0] + k[:, None] * sd
    ll, carry = like(theta, like.initial_carry(len(k)))
    assert np.all(np.abs(ll + 0.5 * k**2) <= 0.1 * 0.5 * k**2 + 1e-6), ll
    assert ll[2] == pytest.approx(0.0, abs=1e-6)  # the maximum is the bias-corrected estimate
    # near the fit the value does not depend on where the particle came from
    ll2, _ = like(theta, carry[::-1])
    np.testing.assert_allclose(ll2, ll, atol=1e-9)


def test_sampler_agrees_with_the_normal_posterior_when_that_is_accurate(case_a_fit):
    _, _, est = case_a_fit
    g, s = est.gaussian_posterior_, est.posterior_
    assert isinstance(s, SamplePosterior)
    # Monte Carlo error with ~300 particles: over seeds 0-7 the means differ by at most 0.15 sd
    # and the sds by at most 11 %
    assert abs(s.mean[0] - g.mean[0]) < 0.25 * g.sd[0]
    assert s.sd[0] == pytest.approx(g.sd[0], rel=0.2)
    lo, hi = s.credible_interval(0.95)[0]
    # the tails of 300 particles: within 0.2-0.4 sd over seeds 0-7
    assert lo == pytest.approx(g.credible_interval(0.95)[0, 0], abs=0.6 * g.sd[0])
    assert hi == pytest.approx(g.credible_interval(0.95)[0, 1], abs=0.6 * g.sd[0])
    assert est.theta_[0] == pytest.approx(s.mean[0])
    res = est.smc_
    assert res.temperatures[-1] == 1.0 and res.completed
    assert 0.1 < res.acceptance[-1] < 0.9


def test_result_has_the_default_keys_and_the_sampler(case_a_fit):
    model, trial, est = case_a_fit
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkelidWarning)
        ref = MarkerEstimator(model, rng=np.random.default_rng(0)).fit(trial.data).result()
    out = est.result()
    assert set(out.diagnostics) == set(ref.diagnostics) | {"sampler"}
    assert set(out.parameters["L2"].extra) == set(ref.parameters["L2"].extra)
    sampler = out.diagnostics["sampler"]
    assert set(sampler) >= {"particles", "ess", "stages", "acceptance", "log_evidence"}
    assert sampler["particles"] == 300 and 0 < sampler["ess"] <= 300
    assert np.isfinite(sampler["log_evidence"])
    json.dumps(result_to_dict(out))


def test_posterior_against_a_prior_bound_stays_inside_it():
    # 40 noisy frames of a forearm whose length (295 mm) is near the prior's upper bound (300 mm):
    # the joint fit ends on the bound, the normal interval spills past it, the samples cannot
    model = builtin_model("case-a")
    trial = simulate(model, theta=[295.0], n_frames=40, sigma=15.0, rng=np.random.default_rng(3))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkelidWarning)
        with pytest.raises(IdentifiabilityError):
            MarkerEstimator(model, rng=np.random.default_rng(0)).fit(trial.data)
        est = SamplerEstimator(model, rng=np.random.default_rng(0)).fit(trial.data)
    g_lo, g_hi = est.gaussian_posterior_.credible_interval(0.95)[0]
    lo, hi = est.posterior_.credible_interval(0.95)[0]
    assert g_hi > 305.0  # the normal interval reaches well past the bound
    assert 200.0 <= est.posterior_.points.min() and est.posterior_.points.max() <= 300.0
    assert hi <= 300.0 and lo > g_lo
    mean = est.posterior_.mean[0]
    assert hi - mean < mean - lo  # skewed away from the bound
    assert any("reaches a bound of its prior" in w.message for w in est.warnings_)
    # the samples follow the estimator's own likelihood: quadrature on the prior interval
    # (sampler seeds 0-9: means within 0.13 sd, sds within 9 %, lower 2.5 % point within 0.51 sd)
    q_mean, q_sd, q_ci = quadrature(est, np.linspace(200.0, 300.0, 401))
    assert mean == pytest.approx(q_mean, abs=0.25 * q_sd)
    assert est.posterior_.sd[0] == pytest.approx(q_sd, rel=0.15)
    assert lo == pytest.approx(q_ci[0], abs=0.7 * q_sd) and hi == pytest.approx(q_ci[1], abs=0.3 * q_sd)
    assert abs(est.gaussian_posterior_.mean[0] - q_mean) > 0.5 * q_sd  # where the normal one is off


def test_serially_correlated_residuals_temper_the_likelihood():
    # soft-tissue artefact: the default estimator widens its interval (Newey-West); the sampler's
    # likelihood is tempered by the variance ratio, so its posterior is as wide or wider, and it
    # still follows its own (tempered) likelihood, heavy right tail included
    model = builtin_model("case-a")
    trial = simulate(model, theta=[250.0], n_frames=120, sigma=2.0, noise="sta", sta_amplitude=10.0,
                     rng=np.random.default_rng(5))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkelidWarning)
        est = SamplerEstimator(model, rng=np.random.default_rng(0)).fit(trial.data)
    assert est.widened_
    plain, widened = est.cov_plain_[0, 0], est.cov_data_[0, 0]
    assert est.likelihood_tau_ == pytest.approx(plain / widened)
    assert est.posterior_.sd[0] > 0.8 * np.sqrt(widened) > 2.0 * np.sqrt(plain)
    q_mean, q_sd, _ = quadrature(est, np.linspace(200.0, 300.0, 401))
    # sampler seeds 0-7: means within 0.12 sd, sds within 10 %
    assert est.posterior_.mean[0] == pytest.approx(q_mean, abs=0.3 * q_sd)
    assert est.posterior_.sd[0] == pytest.approx(q_sd, rel=0.2)


def test_normal_and_lognormal_priors_are_drawn_inside_their_bounds():
    model = model_from_dict({
        "model": {"dim": 2, "units": "mm"},
        "segments": [{"name": "arm", "parent": "ground", "joint": {"type": "revolute", "position": [0, 0]}}],
        "markers": [{"name": "a", "segment": "arm", "position": [100.0, 0.0]},
                    {"name": "b", "segment": "arm", "position": [50.0, 10.0]}],
        "parameters": [
            {"name": "ax", "kind": "marker_position", "marker": "a", "axis": "x",
             "prior": {"type": "normal", "mean": 100.0, "sd": 5.0, "lower": 95.0, "upper": 120.0}},
            {"name": "bx", "kind": "marker_position", "marker": "b", "axis": "x",
             "prior": {"type": "lognormal", "median": 50.0, "sd_log": 0.1}}]})
    x = sample_prior(model, 20000, np.random.default_rng(0))
    assert np.isfinite(model.log_prior(x)).all()
    assert x[:, 0].min() >= 95.0 and x[:, 0].max() <= 120.0
    assert np.median(np.log(x[:, 1])) == pytest.approx(np.log(50.0), abs=0.01)
    assert np.std(np.log(x[:, 1])) == pytest.approx(0.1, rel=0.05)


def test_fit_from_the_command_line(tmp_path, capsys):
    assert methods()["marker-smc"] is SamplerEstimator
    trc = tmp_path / "a.trc"
    assert main(["simulate", "case-a", "--sigma", "5", "--frames", "80", "--seed", "2", "--out", str(trc)]) == 0
    capsys.readouterr()
    out = tmp_path / "fit"
    assert main(["fit", str(EXAMPLES / "case_a.toml"), str(trc), "--method", "marker-smc", "--json",
                 "--out", str(out)]) == 0
    res = json.loads(capsys.readouterr().out)["results"]["marker-smc"]
    l2 = res["parameters"]["L2"]
    assert l2["crlb_sd"] > 0 and "bias_removed" in l2["extra"]
    sampler = res["diagnostics"]["sampler"]
    assert set(sampler) >= {"particles", "ess", "stages", "acceptance", "log_evidence"}
    assert 200 <= l2["interval"][0] < l2["interval"][1] <= 300
    arrays = np.load(out / "arrays.npz")
    assert str(arrays["marker-smc/posterior.kind"]) == "samples"
    assert arrays["marker-smc/samples"].shape == (sampler["particles"], 1)
    assert main(["report", str(out)]) == 0
    html = (out / "report.html").read_text()
    assert "marker-smc" in html
