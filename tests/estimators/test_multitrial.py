import warnings

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.stats import chi2, t

from skelid.data import MarkerData
from skelid.errors import ConvergenceError
from skelid.estimators.fit.joint import joint_fit, weighted_terms
from skelid.estimators.marker import MarkerEstimator
from skelid.estimators.multitrial import (
    MultiTrialEstimator,
    consistency_test,
    dersimonian_laird,
    joint_status,
    mixture_half_width,
    own_variance_floor,
    pairwise_z,
    paule_mandel,
    random_effects,
    random_effects_prior,
    satterthwaite_dof,
    shared_covariance,
    t_factor,
    tau_posterior,
)
from skelid.simulate import simulate
from tests.estimators.test_noise import two_link


def _data(model, n_frames, seed, sigma=1.0, rate=100.0):
    trial = simulate(model, sigma=sigma, n_frames=n_frames, rate=rate, rng=np.random.default_rng(seed))
    return trial


def test_dersimonian_laird_closed_forms():
    tau2, q, df = dersimonian_laird(np.array([[0.0], [1.0], [3.0]]), np.ones((3, 1)))
    assert tau2[0] == pytest.approx(4.0 / 3.0) and q[0] == pytest.approx(42.0 / 9.0) and df == 2
    # unequal variances: w = (1, 1/3), mean 1, Q = 4, c = 1/2 -> tau^2 = (4 - 1) / (1/2) = 6
    tau2, q, _ = dersimonian_laird(np.array([[0.0], [4.0]]), np.array([[1.0], [3.0]]))
    assert q[0] == pytest.approx(4.0) and tau2[0] == pytest.approx(6.0)
    # spread smaller than the variances explain: no excess variance
    tau2, _, _ = dersimonian_laird(np.array([[0.0], [0.5]]), np.array([[1.0], [1.0]]))
    assert tau2[0] == 0.0


def test_consistency_test_and_pairwise_z_closed_forms():
    out = consistency_test(np.array([[0.0], [2.0]]), np.array([[[1.0]], [[1.0]]]), np.array([1.0]))
    assert out["statistic"] == pytest.approx(2.0) and out["dof"] == 1
    assert out["p_value"] == pytest.approx(chi2.sf(2.0, 1))
    z = pairwise_z(np.array([[0.0], [3.0], [4.0]]), np.array([[1.0], [1.0], [np.sqrt(7.0)]]))
    np.testing.assert_allclose(z[:, 0], [-3.0 / np.sqrt(2.0), -4.0 / np.sqrt(8.0), -1.0 / np.sqrt(8.0)])


def test_stacked_fit_equals_brute_force_least_squares():
    # two trials, one geometry, per-trial weights, each trial's own motion model: the stacked
    # Gauss-Newton fit equals a generic solver on every unknown at once with the same penalty
    model = two_link()
    a, b = _data(model, 8, 1, sigma=1.0), _data(model, 6, 2, sigma=2.0)
    y = np.concatenate([a.data.positions, b.data.positions])
    q0 = np.concatenate([a.pose, b.pose])
    w = np.concatenate([np.ones((8, 6)), np.full((6, 6), 0.25)])
    blocks = [(0, 8, 100.0, 20.0), (8, 14, 50.0, 10.0)]
    fit = joint_fit(model, y, model.theta_center, q0, blocks=blocks, weights=w, tol=1e-14)
    R = fit.penalty.toarray()
    Q = model.n_pose
    assert np.all(R[:8 * Q, 8 * Q:] == 0.0)  # no smoothing across the trial boundary
    e, V = np.linalg.eigh(R)
    L = np.sqrt(np.clip(e, 0, None))[:, None] * V.T
    sw = np.repeat(np.sqrt(w), 2, axis=1)
    P = model.n_params

    def resid(x):
        th, qq = x[:P], x[P:].reshape(14, Q)
        r, _, _ = weighted_terms(model, th, qq, y, sw)
        return np.concatenate([r.ravel(), L @ qq.ravel()])

    ref = least_squares(resid, np.concatenate([model.theta_center, q0.ravel()]), xtol=1e-14, ftol=1e-14,
                        gtol=1e-14)
    np.testing.assert_allclose(fit.theta, ref.x[:P], atol=1e-6)
    np.testing.assert_allclose(fit.pose.ravel(), ref.x[P:], atol=1e-6)


def test_one_trial_is_the_single_trial_fit():
    model = two_link()
    t = _data(model, 150, 3, sigma=1.5)
    single = MarkerEstimator(model, outlier_threshold=None).fit(t.data)
    multi = MultiTrialEstimator(model, outlier_threshold=None).fit([t.data])
    sd = single.posterior_.sd
    # both fits stop where the cost can no longer tell two points apart (a relative change of 1e-11):
    # on this trial a move of about 1e-4 sd changes the cost by less than that, so the two stopping
    # points agree to a few 1e-4 sd, not better
    assert np.all(np.abs(multi.theta_ - single.theta_) < 5e-4 * sd)
    np.testing.assert_allclose(multi.cov_, single.cov_, rtol=1e-10)
    assert multi.consistency_["dof"] == 0 and multi.tau2_[0] == 0.0


def test_two_trials_different_rates_and_markers():
    model = two_link()
    a = _data(model, 200, 4, sigma=1.0, rate=100.0)
    b = _data(model, 120, 5, sigma=2.0, rate=60.0)
    yb = b.data.positions.copy()
    yb[:40, 0] = np.nan  # a gap in one marker of the second trial
    db = MarkerData(yb, b.data.names, 60.0, b.data.units)
    multi = MultiTrialEstimator(model, outlier_threshold=None).fit([a.data, db])
    one = [MarkerEstimator(model, outlier_threshold=None).fit(d) for d in (a.data, db)]
    # the joint estimate lies between the trials' own, closer to the more precise one, and is
    # near the information-weighted combination of the trials
    S = [np.linalg.inv(e.cov_plain_) for e in one]
    comb = np.linalg.solve(S[0] + S[1], S[0] @ one[0].theta_ + S[1] @ one[1].theta_)
    fe = MultiTrialEstimator(model, outlier_threshold=None, between_trial="none").fit([a.data, db])
    assert np.all(np.abs(fe.theta_ - comb) < 0.2 * fe.posterior_.sd)
    # without between-trial variance the joint interval is narrower than either trial's
    assert np.all(fe.posterior_.sd < np.min([e.posterior_.sd for e in one], axis=0))
    res = multi.result()
    assert len(res.diagnostics["trials"]) == 2 and res.diagnostics["consistency"]["dof"] == 2
    assert res.diagnostics["trials"][1]["sigma"] == pytest.approx(2.0, rel=0.15)


def test_between_trial_variance_widens_the_joint_interval():
    # trials whose geometry really differs (a different elbow per trial): tau^2 > 0 and the joint
    # sd grows to cover the spread; with 'none' it stays at the within-trial sd
    model = two_link()
    datas = []
    for k, dx in enumerate([-3.0, 0.0, 3.0, 6.0]):
        tr = simulate(model, theta=model.theta_center + np.array([dx, 0.0]), sigma=1.0, n_frames=150,
                      rng=np.random.default_rng(10 + k))
        datas.append(tr.data)
    re = MultiTrialEstimator(model, outlier_threshold=None, between_trial="dl").fit(datas)
    fe = MultiTrialEstimator(model, outlier_threshold=None, between_trial="none").fit(datas)
    assert re.tau2_[0] > 1.0
    assert re.posterior_.sd[0] > 3 * fe.posterior_.sd[0]
    assert re.consistency_["p_value"] < 1e-6
    # random-effects combination: weights (C_k + Omega)^{-1}, covariance their summed inverse
    W = np.linalg.inv(re.trial_cov_ + np.diag(re.tau2_))
    np.testing.assert_allclose(re.cov_unscaled_, np.linalg.inv(W.sum(0)), rtol=1e-9)
    np.testing.assert_allclose(re.theta_, re.cov_unscaled_ @ np.einsum("kpq,kq->p", W, re.trial_theta_),
                               rtol=1e-9)
    # tau^2 from four trials: the interval takes a t quantile (Satterthwaite), wider than the normal one
    f = t_factor(re.dof_)
    assert np.all(np.isfinite(re.dof_[re.tau2_ > 0])) and np.all(f[re.tau2_ > 0] > 1.0)
    np.testing.assert_allclose(re.cov_, re.cov_unscaled_ * np.outer(f, f), rtol=1e-12)
    # the elbow x estimates spread about their mean shift (1.5 mm): the joint one is near it
    assert abs(re.theta_[0] - (model.theta_center[0] + 1.5)) < 3 * re.posterior_.sd[0]


def test_paule_mandel_solves_its_equation_and_equals_dl_for_equal_variances():
    y = np.array([[0.0, 1.0], [1.0, 1.2], [3.0, 0.9], [2.0, 1.1]])
    v = np.array([[1.0, 0.5], [1.0, 0.5], [1.0, 0.5], [1.0, 0.5]])
    dl, _, _ = dersimonian_laird(y, v)
    pm, _, df = paule_mandel(y, v)
    np.testing.assert_allclose(pm, dl, atol=1e-9)  # equal variances: both are the moment estimator
    assert pm[1] == 0.0
    # unequal variances: the generalised Q with weights 1 / (v + tau^2) equals K - 1 at the solution
    v2 = np.array([[0.01], [1.0], [2.0], [0.5]])
    tau2, _, df = paule_mandel(y[:, :1], v2)
    w = 1.0 / (v2[:, 0] + tau2[0])
    m = (w * y[:, 0]).sum() / w.sum()
    assert tau2[0] > 0 and (w * (y[:, 0] - m) ** 2).sum() == pytest.approx(df, rel=1e-9)


def test_t_factor_and_satterthwaite_degrees_of_freedom():
    np.testing.assert_allclose(t_factor([np.inf, 3.0]), [1.0, t.ppf(0.975, 3) / t.ppf(0.975, np.inf)])
    # all of the variance between trials: K - 1 degrees of freedom; none: infinite
    np.testing.assert_allclose(satterthwaite_dof([2.0, 2.0, 2.0], [2.0, 1.0, 0.0], 3), [3.0, 12.0, np.inf])


def test_random_effects_degrees_of_freedom_closed_form():
    # two trials, within variances 1 and 3, tau^2 = 1: w = (1/2, 1/4), V = 4/3,
    # V_b = tau^2 (1/4 + 1/16) / (3/4)^2 = 5/9, nu = 1 * (4/3)^2 / (5/9)^2 = 5.76
    th, cov, dof = random_effects(np.array([[0.0], [3.0]]), np.array([[[1.0]], [[3.0]]]), np.array([1.0]))
    assert cov[0, 0] == pytest.approx(4.0 / 3.0) and th[0] == pytest.approx(1.0)
    assert dof[0] == pytest.approx((4.0 / 3.0) ** 2 / (5.0 / 9.0) ** 2)


def test_result_is_typed_and_round_trips(tmp_path):
    from skelid.io.results import read_run, write_run
    from skelid.result import FitResult, FitRun

    model = two_link()
    datas = [_data(model, 25, 20 + k, sigma=1.0).data for k in range(3)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = MultiTrialEstimator(model, outlier_threshold=None, jackknife=False, cutoff=None).fit(datas)
    r = est.result()
    assert isinstance(r, FitResult) and r.method == "marker-multi"
    assert r.names == model.parameter_names  # nothing but the parameters beside each other
    d = r.diagnostics
    assert len(d["trials"]) == 3 and d["consistency"]["dof"] == 2 * model.n_params
    assert set(d["heterogeneity"]) == set(model.parameter_names)
    for row, k in zip(d["trials"], range(3), strict=True):
        for p, n in enumerate(model.parameter_names):
            assert row["parameters"][n]["mean"] == est.trial_theta_[k, p]
            assert row["parameters"][n]["sd_with_between_trial"] >= row["parameters"][n]["sd"]
    write_run(tmp_path, FitRun({"marker-multi": r}))
    back = read_run(tmp_path).results["marker-multi"]
    assert back.diagnostics["trials"] == d["trials"] and back.diagnostics["consistency"] == d["consistency"]
    np.testing.assert_array_equal(back.arrays["trial_theta"], est.trial_theta_)
    assert back.parameters == r.parameters


def test_combine_equals_fit():
    model = two_link()
    datas = [_data(model, 25, 30 + k, sigma=1.0).data for k in range(2)]
    kw = {"outlier_threshold": None, "jackknife": False, "cutoff": None}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = MultiTrialEstimator(model, **kw).fit(datas)
        ests = [MarkerEstimator(model, **kw).fit(d) for d in datas]
        b = MultiTrialEstimator(model, **kw).combine(ests, [d.rate for d in datas])
    np.testing.assert_array_equal(a.theta_, b.theta_)
    np.testing.assert_array_equal(a.cov_, b.cov_)


def test_a_trial_pinned_on_a_prior_bound_is_set_aside():
    """A trial whose own fit ended on a prior bound has no Gaussian approximation: the others decide."""
    model = two_link()
    datas = [_data(model, 25, 40 + k, sigma=1.0).data for k in range(2)]
    kw = {"outlier_threshold": None, "jackknife": False, "cutoff": None}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ests = [MarkerEstimator(model, **kw).fit(d) for d in datas]
        ests[1].fit_ = ests[1].fit_._replace(pinned=np.array([True, False]))
        m = MultiTrialEstimator(model, **kw).combine(ests, [d.rate for d in datas], ["moving", "still"])
    assert m.trials_set_aside_ == ["still"]
    assert "trials-set-aside" in {w.code for w in m.warnings_}
    np.testing.assert_allclose(m.theta_data_, m.trial_theta_[0])
    np.testing.assert_allclose(m.cov_unscaled_, m.trial_cov_[0])
    assert m.trial_theta_.shape[0] == 2 and m.consistency_["dof"] == 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ests[1].fit_ = ests[1].fit_._replace(pinned=np.array([False, False]))
        both = MultiTrialEstimator(model, **kw).combine(ests, [d.rate for d in datas])
    assert both.trials_set_aside_ == [] and both.consistency_["dof"] == model.n_params


def test_prior_posterior_equals_brute_force_integration():
    """Half-normal prior on tau: posterior mean of mu, E[tau^2] and the interval's mass on a 2-d grid."""
    y, v, s = np.array([0.0, 10.0, 3.0]), np.array([1.0, 4.0, 0.5]), 5.0
    mu = np.linspace(-30.0, 40.0, 1401)[:, None]
    tau = np.linspace(0.0, 35.0, 701)[None, :]
    log_dens = -0.5 * (tau / s) ** 2 + sum(-0.5 * np.log(vk + tau**2) - 0.5 * (yk - mu) ** 2 / (vk + tau**2)
                                           for yk, vk in zip(y, v, strict=True))
    dens = np.exp(log_dens - log_dens.max())
    dens /= dens.sum()
    mean, half, tau2, _ = random_effects_prior(y[:, None], v[:, None], [s])
    assert mean[0] == pytest.approx((dens * mu).sum(), abs=1e-4)
    assert tau2[0] == pytest.approx((dens * tau**2).sum(), rel=1e-3)
    inside = dens[np.abs(mu[:, 0] - mean[0]) <= half[0]].sum()
    assert inside == pytest.approx(0.95, abs=2e-3)


def test_prior_closed_forms():
    y, v = np.array([[1.0, 0.0], [3.0, 2.0], [8.0, 1.0]]), np.array([[1.0, 2.0], [0.5, 2.0], [2.0, 2.0]])
    # scale 0: tau = 0, the fixed-effect (inverse-variance) combination
    mean, half, tau2, trial = random_effects_prior(y, v, [0.0, 0.0])
    w = 1.0 / v
    np.testing.assert_allclose(mean, (w * y).sum(0) / w.sum(0), rtol=1e-12)
    np.testing.assert_allclose(half, 1.959963984540054 / np.sqrt(w.sum(0)), rtol=1e-9)
    np.testing.assert_array_equal(tau2, 0.0)
    np.testing.assert_allclose(trial, 1.959963984540054 * np.sqrt(v), rtol=1e-9)
    # one trial says nothing about tau: its posterior is the half-normal prior (E tau^2 = s^2)
    _, w1, _, _ = tau_posterior(y[:1], v[:1], [3.0, 0.5])
    grid, _, _, _ = tau_posterior(y[:1], v[:1], [3.0, 0.5])
    np.testing.assert_allclose((w1 * grid**2).sum(0), [9.0, 0.25], rtol=1e-4)
    # equal variances, data symmetric about 2: the posterior mean is 2 whatever the prior
    mean, _, _, _ = random_effects_prior(np.array([[0.0], [1.0], [3.0], [4.0]]), np.ones((4, 1)), [7.0])
    assert mean[0] == pytest.approx(2.0, abs=1e-12)
    # one normal: the 95 % half-width is 1.96 sd
    assert mixture_half_width(np.ones((1, 1)), [[0.3]], [[4.0]], [0.3])[0] == pytest.approx(2 * 1.959963984540054)


def test_prior_between_trial_in_the_estimator():
    """The estimator's 'prior' intervals are the posterior's; its prior scale is the artefact's effect."""
    from skelid.estimators.checks.artefact import artefact_covariance

    model = two_link()
    kw = {"outlier_threshold": None, "jackknife": False, "cutoff": None}
    ests = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for k, dx in enumerate([-4.0, 4.0]):
            tr = simulate(model, theta=model.theta_center + np.array([dx, 0.0]), sigma=1.0, n_frames=40,
                          rng=np.random.default_rng(50 + k))
            ests.append(MarkerEstimator(model, **kw).fit(tr.data))
        m = MultiTrialEstimator(model, between_trial="prior", prior_artefact_rms=3.0, **kw).combine(ests, [100.0] * 2)
        dl = MultiTrialEstimator(model, between_trial="dl", **kw).combine(ests, [100.0] * 2)
    unit = [np.diag(artefact_covariance(model, e.y_, e.fit_info_.theta, e.fit_info_.pose, e.fit_info_.penalty,
                                        1.0, e.frames_used_)) for e in ests]
    np.testing.assert_allclose(m.tau_prior_scale_, 3.0 * np.sqrt(np.mean(unit, axis=0)), rtol=1e-12)
    var = np.einsum("kpp->kp", m.trial_cov_)
    _, half, tau2, trial = random_effects_prior(m.trial_theta_, var, m.tau_prior_scale_)
    np.testing.assert_allclose(m.tau2_, tau2, rtol=1e-12)
    np.testing.assert_allclose(m.trial_sd_, trial / 1.959963984540054, rtol=1e-9)
    # the joint interval: the random-effects centre at E[tau^2], the posterior's 95 % about it
    W = np.linalg.inv(m.trial_cov_ + np.diag(tau2))
    np.testing.assert_allclose(m.cov_unscaled_, np.linalg.inv(W.sum(0)), rtol=1e-9)
    grid, weight, mean, cvar = tau_posterior(m.trial_theta_, var, m.tau_prior_scale_)
    sd = mixture_half_width(weight, mean, cvar, m.theta_data_) / 1.959963984540054
    np.testing.assert_allclose(np.sqrt(np.diag(m.cov_data_)), sd, rtol=1e-9)
    # two trials 8 mm apart: t_1 with DerSimonian-Laird says almost nothing; the prior keeps it informative
    assert m.tau2_[0] > 0 and m.posterior_.sd[0] < 0.5 * dl.posterior_.sd[0]
    d = m.result().diagnostics["between_trial"]
    assert d["method"] == "prior" and d["prior_scale"]["elbow_x"] == m.tau_prior_scale_[0]


def test_a_single_parameter_trial_on_its_bound_is_set_aside_not_fatal():
    """Alone, a one-parameter fit on a prior bound refuses; among several trials it is set aside."""
    from skelid.errors import IdentifiabilityError
    from skelid.simulate import builtin_model

    model = builtin_model("case-a")  # L2 in [200, 300]
    datas = [simulate(model, theta=np.array([L]), sigma=2.0, n_frames=30, rng=np.random.default_rng(60 + k)).data
             for k, L in enumerate([250.0, 252.0, 330.0])]
    kw = {"outlier_threshold": None, "jackknife": False, "bias_correction": "none", "cutoff": None}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(IdentifiabilityError, match="sits on the bound"):
            MarkerEstimator(model, **kw).fit(datas[2])
        m = MultiTrialEstimator(model, **kw).fit(datas)
    assert m.trials_set_aside_ == ["simulated (3)"]
    assert "on-bound" in {w.code for w in m.trials_[2].warnings_}
    assert 245.0 < m.theta_[0] < 257.0
    with warnings.catch_warnings():  # every trial on the bound: refused, as one trial alone is
        warnings.simplefilter("ignore")
        with pytest.raises(IdentifiabilityError, match="every trial sits on a bound"):
            MultiTrialEstimator(model, **kw).fit([datas[2], datas[2]])


KW = {"outlier_threshold": None, "jackknife": False, "cutoff": None}


def _fitted(seed0: int, n: int):
    """``n`` simulated two-link trials (25 frames, seeds ``seed0 + k``), each fitted alone."""
    model = two_link()
    datas = [_data(model, 25, seed0 + k, sigma=1.0).data for k in range(n)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ests = [MarkerEstimator(model, **KW).fit(d) for d in datas]
    return model, datas, ests


def _with_status(est, statuses):
    est.identifiability_ = dict(est.identifiability_, table=[dict(r, status=s) for r, s in
                                                          zip(est.identifiability_["table"], statuses, strict=True)])
    return est


@pytest.mark.parametrize("between", ["dl", "prior"])
def test_a_trial_that_leaves_a_parameter_unidentified_contributes_nothing_to_it(between):
    model, datas, ests = _fitted(60, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # the third trial leaves elbow_y poorly identified, 40 mm off
        ests[2].theta_profile_ = ests[2].theta_profile_ + np.array([0.0, 40.0])
        _with_status(ests[2], ["identified", "poor"])
        m = MultiTrialEstimator(model, between_trial=between, **KW).combine(ests, [d.rate for d in datas])
    assert m.trial_informs_.tolist() == [[True, True], [True, True], [True, False]]
    # its between-trial variance is the two other trials' own
    if between == "dl":
        tau2, _, df = dersimonian_laird(m.trial_theta_[:2, 1:], np.einsum("kpp->kp", m.trial_cov_)[:2, 1:])
        assert m.tau2_[1] == pytest.approx(tau2[0]) and m.heterogeneity_["elbow_y"]["dof"] == df == 1
    assert m.heterogeneity_["elbow_y"]["trials"] == 2 and m.heterogeneity_["elbow_x"]["trials"] == 3
    # the combination is the limit of an infinite variance on the trial's elbow_y (marginalised out)
    C = m.trial_cov_.copy()
    C[2, 1, 1] += 1e12
    th, cov, _ = random_effects(m.trial_theta_, C, m.tau2_)
    np.testing.assert_allclose(m.cov_unscaled_, cov, rtol=1e-6)
    np.testing.assert_allclose(m.theta_data_, th, rtol=1e-6, atol=1e-6)
    assert abs(m.theta_data_[1] - np.mean(m.trial_theta_[:2, 1])) < 5.0  # not dragged 40 / 3 mm
    # tested on the parameters each trial informs: 2 + 2 + 1 observations of 2 parameters
    assert m.consistency_["dof"] == 3
    res = m.result()
    assert res.parameters["elbow_y"].status == "identified"
    rows = res.diagnostics["trials"]
    assert rows[2]["parameters"]["elbow_y"]["contributes"] is False
    assert rows[2]["parameters"]["elbow_y"]["status"] == "poor"


def test_a_parameter_no_trial_identifies_keeps_their_status_and_the_prior_support():
    model, datas, ests = _fitted(70, 2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for e in ests:
            _with_status(e, ["identified", "poor"])
            # as wide as a poorly identified parameter's: far beyond its +-60 mm prior
            e.cov_data_ = e.cov_data_ + np.diag([0.0, 80.0**2])
        m = MultiTrialEstimator(model, between_trial="dl", **KW).combine(ests, [d.rate for d in datas])
    assert m.trial_informs_.all()
    p = m.result().parameters["elbow_y"]
    assert p.status == "poor"
    assert -60.0 <= p.interval[0] < p.interval[1] <= 60.0 and p.interval == (-60.0, 60.0)


def test_joint_status_and_in_support_closed_forms():
    from skelid.estimators.base import in_support
    from skelid.model.description import Prior

    assert joint_status([["poor", "unidentified"], ["identified", "poor"]]) == ["identified", "poor"]
    pr = Prior("uniform", 0.0, 10.0)
    assert in_support(pr, (4.0, 4.0), (-3.0, 11.0), "poor") == ((4.0, 4.0), (0.0, 10.0), "poor")
    assert in_support(pr, (12.0, 12.0), (11.0, 13.0), "identified") == ((10.0, 10.0), (10.0, 10.0), "on-bound")


def test_shared_covariance_closed_forms():
    W = np.array([np.eye(2), 3.0 * np.eye(2)])
    norm = np.linalg.inv(W.sum(axis=0))
    Sh = np.array([np.diag([4.0, 1.0]), np.diag([4.0, 9.0])])
    m = np.ones((2, 2), bool)
    cov, r = shared_covariance(W, norm, Sh, np.zeros(2), m)
    # one error u: 0.25 * 2 u + 0.75 * 2 u on the first, 0.25 * 1 u + 0.75 * 3 u on the second
    np.testing.assert_allclose(cov, np.diag([4.0, 2.5**2]))
    np.testing.assert_allclose(r, 1.0)
    # a between-trial variance as large as the mean shared variance: none of it recurs
    cov, r = shared_covariance(W, norm, Sh, np.array([4.0, 2.5]), m)
    np.testing.assert_allclose(r, [0.0, np.sqrt(0.5)])
    np.testing.assert_allclose(cov, np.diag([0.0, 0.5 * 2.5**2]))


def test_the_shared_part_of_each_trial_is_carried_once_and_left_out_of_comparisons():
    model, datas, ests = _fitted(83, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plain = MultiTrialEstimator(model, between_trial="none", **KW).combine(ests, [d.rate for d in datas])
        for e in ests:  # a placement error of sd 3 mm on elbow_x that every trial shares
            e.cov_shared_ = np.diag([9.0, 0.0])
            e.cov_data_ = e.cov_data_ + e.cov_shared_
        m = MultiTrialEstimator(model, between_trial="none", **KW).combine(ests, [d.rate for d in datas])
    # the own parts combine as before; the shared one is added once, not divided by three
    np.testing.assert_allclose(m.cov_, plain.cov_ + np.diag([9.0, 0.0]), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(m.trial_sd_, plain.trial_sd_)  # comparisons: it cancels
    assert m.consistency_["statistic"] == pytest.approx(plain.consistency_["statistic"])
    rows = m.result().diagnostics["trials"]
    assert rows[0]["parameters"]["elbow_x"]["sd_shared"] == pytest.approx(3.0)
    lo, hi = rows[0]["parameters"]["elbow_x"]["interval"]
    s = rows[0]["parameters"]["elbow_x"]["sd_with_between_trial"]
    assert (hi - lo) / 2 == pytest.approx(1.959964 * np.hypot(s, 3.0), rel=1e-6)
    assert m.result().parameters["elbow_x"].extra["sd_shared_by_trials"] == pytest.approx(3.0)


def test_a_trial_whose_fit_did_not_converge_is_set_aside_and_all_of_them_refuse():
    model, datas, ests = _fitted(60, 3)
    kw = KW
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ests[1].fit_info_ = ests[1].fit_info_._replace(converged=False)
        m = MultiTrialEstimator(model, between_trial="dl", **kw).combine(ests, [d.rate for d in datas],
                                                                           ["a", "b", "c"])
        both = MultiTrialEstimator(model, between_trial="dl", **kw).combine([ests[0], ests[2]],
                                                                              [d.rate for d in datas[::2]])
    assert m.trials_set_aside_ == ["b"] and m.trials_not_converged_ == ["b"] and m.converged_
    assert any("did not converge" in w.message for w in m.warnings_)
    np.testing.assert_allclose(m.theta_data_, both.theta_data_, rtol=1e-9, atol=1e-9)
    # an estimator that keeps unconverged fits ('warn') keeps the trial
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        w = MultiTrialEstimator(model, between_trial="dl", on_nonconvergence="warn", **kw).combine(
            ests, [d.rate for d in datas])
    assert w.trials_set_aside_ == []
    for e in ests:
        e.fit_info_ = e.fit_info_._replace(converged=False)
    with pytest.raises(ConvergenceError, match="no trial's joint fit converged"):
        MultiTrialEstimator(model, **kw).combine(ests, [d.rate for d in datas])


def test_a_trial_fitted_exactly_weighs_as_one_known_to_a_part_in_a_billion_not_infinitely():
    # own variances of nil (an exact trial: all of its covariance is the shared placement's)
    theta = np.array([[1.0569526, 250.0], [1.05677553, 251.0]])
    var = np.array([[0.0, 0.0], [3.6e-7, 4.0]])
    floored = own_variance_floor(theta, var)
    np.testing.assert_allclose(floored[0], [(1e-9 * 1.0569526) ** 2, (1e-9 * 251.0) ** 2], rtol=1e-12)
    np.testing.assert_array_equal(floored[1], var[1])  # a trial with its own noise keeps its variance
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tau2, q, df = dersimonian_laird(theta, floored)
    assert np.all(np.isfinite(tau2)) and np.all(np.isfinite(q)) and df == 1
    np.testing.assert_array_equal(own_variance_floor(np.zeros((2, 1)), np.zeros((2, 1))), 1e-150)
