"""Per-trial estimates that change with how far each trial moves a joint: the meta-regression test
against its nominal size, and the several-trial estimator's warning on simulated trials."""

import numpy as np
import pytest

from skelid.estimators.checks.misfit import joint_ranges
from skelid.estimators.checks.trial_motion import motion_trend
from skelid.estimators.multitrial import MultiTrialEstimator
from skelid.simulate import builtin_model, simulate


def test_the_trend_test_holds_its_size_with_few_trials_and_a_between_trial_spread():
    rng = np.random.default_rng(5)
    for K, tau in ((4, 0.0), (6, 3.0), (12, 3.0)):
        p = []
        for _ in range(2000):
            x, v = rng.uniform(0, 120, K), rng.uniform(1, 30, K)
            p.append(motion_trend(400 + rng.normal(0, np.sqrt(v + tau**2)), v, x)["p_value"])
        # at 1 %: 20 of 2000 expected; binomial sd 4.4
        assert 0.003 < np.mean(np.array(p) < 0.01) < 0.02, (K, tau)


def test_the_trend_is_the_weighted_least_squares_slope_where_the_trials_agree_with_it():
    x = np.array([10.0, 40.0, 55.0, 90.0, 120.0, 130.0])
    v = np.array([1.0, 4.0, 2.0, 9.0, 1.0, 3.0])
    y = 300.0 + 0.2 * x + np.array([0.5, -1.0, 0.3, 1.2, -0.4, 0.6])
    r = motion_trend(y, v, x)
    X = np.column_stack([np.ones(6), x])
    W = np.diag(1 / (v + r["tau"] ** 2))
    beta = np.linalg.solve(X.T @ W @ X, X.T @ W @ y)
    assert r["slope"] == pytest.approx(beta[1]) and r["change"] == pytest.approx(beta[1] * 120.0)
    assert r["dof"] == 4 and r["p_value"] < 1e-3
    assert motion_trend(y[:3], v[:3], x[:3]) is None  # fewer than four trials
    assert motion_trend(y, v, np.full(6, 30.0)) is None  # every trial moves the joint alike
    assert motion_trend(y, np.zeros(6), x) is None


def _trials(slope, seed):
    model = builtin_model("case-a")
    out = []
    for k, n in enumerate((60, 100, 200, 400, 800)):  # short trials move the wrist less
        pose = simulate(model, np.array([250.0]), n_frames=n, sigma=2.0, rng=np.random.default_rng([seed, k])).pose
        L2 = 240.0 + slope * joint_ranges(model, pose)["N"][0]
        t = simulate(model, np.array([L2]), n_frames=n, sigma=2.0, rng=np.random.default_rng([seed, k]))
        assert np.array_equal(t.pose, pose)  # the same motion, the length set from its range
        out.append(t.data)
    return model, out


@pytest.mark.parametrize("slope, flagged", [(0.5, True), (0.0, False)])
def test_a_length_that_grows_with_its_joints_range_is_named_and_a_fixed_one_is_not(slope, flagged):
    model, trials = _trials(slope, seed=3)
    est = MultiTrialEstimator(model, rng=np.random.default_rng(0)).fit(trials)
    trend = est.motion_trend_["L2"]
    assert trend["joint"] == "N" and trend["trials"] == 5
    named = [w for w in est.warnings_ if w.code == "trend-with-motion"]
    assert bool(named) is flagged, (trend, [w.message for w in est.warnings_])
    if flagged:
        assert "L2" in named[0].parameters and "joint N" in named[0].message
        assert trend["slope"] == pytest.approx(slope, abs=0.15)
    res = est.result()
    assert res.diagnostics["motion_trend"]["L2"]["p_value"] == trend["p_value"]
    from skelid.sensitivity import trials_text

    line = next(x for x in trials_text(res).splitlines() if x.startswith("per degree of its joint"))
    assert f"{trend['slope']:+.3g} (p {trend['p_value']:.2g})" in line
