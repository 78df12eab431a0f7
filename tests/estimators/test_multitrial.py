import warnings

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.stats import chi2, t

from skelid.data import MarkerData
from skelid.estimators.joint import joint_fit, weighted_terms
from skelid.estimators.marker import MarkerEstimator
from skelid.estimators.multitrial import (
    MultiTrialEstimator,
    consistency_test,
    dersimonian_laird,
    pairwise_z,
    paule_mandel,
    random_effects,
    satterthwaite_dof,
    t_factor,
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
    re = MultiTrialEstimator(model, outlier_threshold=None).fit(datas)
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
