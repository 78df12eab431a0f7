"""Leave-one-marker-out jackknife: one-step replicates against literal refits, and folding."""

import numpy as np

from skelid.data import MarkerData
from skelid.estimators import jackknife
from skelid.estimators.jackknife import literal_jackknife, marker_jackknife
from skelid.estimators.joint import joint_fit
from skelid.estimators.marker import MarkerEstimator
from skelid.model.kinematics import marker_positions
from skelid.simulate import builtin_model, simulate
from tests.estimators.test_checks import _wrist_model

TRUTH_SHIFT = np.array([5.0, -3.0, 2.0])


def _wrist_trial(seed, slide=0.0, n=200):
    """Wrist model moving freely; marker H1 optionally slides with the wrist angles (mm per rad)."""
    model = _wrist_model()
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 100.0
    q = np.zeros((n, model.n_pose))
    for k, d in enumerate(model.dofs):
        amp = 0.5 if d.kind == "R" else 50.0
        q[:, k] = amp * np.sin(2 * np.pi * rng.uniform(0.2, 1.0) * t + rng.uniform(0, 6))
    truth = model.theta_center + TRUTH_SHIFT
    y = marker_positions(model, truth, q) + rng.normal(0.0, 1.0, size=(n, 6, 3))
    wrist = [k for k, d in enumerate(model.dofs) if d.segment == 1]
    y[:, 3] += slide * q[:, wrist]
    return model, y, q, truth


def test_one_step_replicates_match_literal_refits():
    model, y, q, _ = _wrist_trial(0)
    fit = joint_fit(model, y, model.theta_center, q, n_iter=50, rate=100.0, cutoff=6.0)
    jk = marker_jackknife(model, y, fit.theta, fit.pose, fit.penalty)
    lit = literal_jackknife(model, y, fit.theta, fit.pose, rate=100.0, cutoff=6.0)
    assert jk.available and jk.replicate.all()
    scale = np.abs(lit).max()
    # one Gauss-Newton step from the full fit: first-order accurate in the marker's pull
    assert np.abs(jk.shifts - lit).max() < 0.2 * scale
    # the jackknife covariance from the refits and from the one-step replicates agree
    c = lit - lit.mean(axis=0)
    V_lit = 5 / 6 * c.T @ c
    assert np.allclose(np.sqrt(np.diag(jk.cov)), np.sqrt(np.diag(V_lit)), rtol=0.25)


def test_a_sliding_marker_widens_the_interval_and_white_noise_does_not():
    model, y, _, truth = _wrist_trial(4, slide=5.0)
    data = MarkerData(y, model.marker_names, 100.0, "mm")
    est = MarkerEstimator(model, cutoff=6.0, rng=np.random.default_rng(0)).fit(data)
    plain = MarkerEstimator(model, cutoff=6.0, jackknife=False, rng=np.random.default_rng(0)).fit(data)
    assert est.jackknife_["folded"]
    assert np.all(est.posterior_.sd >= plain.posterior_.sd - 1e-12)
    assert np.max(est.posterior_.sd / plain.posterior_.sd) > 1.5
    assert any("leave-one-marker-out" in w.message for w in est.warnings_)
    model, y, _, _ = _wrist_trial(2)
    clean = MarkerEstimator(model, cutoff=6.0, rng=np.random.default_rng(0)).fit(
        MarkerData(y, model.marker_names, 100.0, "mm"))
    assert clean.jackknife_["available"] and not clean.jackknife_["folded"]


def test_no_jackknife_when_every_marker_is_needed():
    """Case A: each of the three markers is needed to fix the pose; no replicate exists."""
    model = builtin_model("case-a")
    trial = simulate(model, n_frames=150, sigma=5.0, rng=np.random.default_rng(0))
    fit = joint_fit(model, trial.data.positions, trial.theta, trial.pose, n_iter=30)
    jk = marker_jackknife(model, trial.data.positions, fit.theta, fit.pose)
    assert not jk.available and not jk.replicate.any()


def test_stated_artefact_reports_the_jackknife_without_folding():
    model, y, _, _ = _wrist_trial(4, slide=5.0)
    est = MarkerEstimator(model, cutoff=6.0, artefact_rms=2.0, rng=np.random.default_rng(0)).fit(
        MarkerData(y, model.marker_names, 100.0, "mm"))
    assert est.jackknife_["available"] and not est.jackknife_["folded"]


def test_a_replicate_whose_cost_check_fails_is_the_literal_refit():
    """Marker H1 slides with the wrist: along its one-step replicate the cost falls by only 0.7 of
    the quadratic model's prediction, so the replicate is refitted; the others stay one-step."""
    model, y, q, _ = _wrist_trial(4, slide=5.0)
    fit = joint_fit(model, y, model.theta_center, q, n_iter=50, rate=100.0, cutoff=6.0)
    jk = marker_jackknife(model, y, fit.theta, fit.pose, fit.penalty)
    refitted = [m for m, s in enumerate(jk.status) if s == "refitted"]
    assert 0 in refitted and jk.status.count("one-step") >= 3
    lo = jackknife.LINEAR_RATIO
    for m in range(6):  # refitted exactly where the check ran and failed
        assert (m in refitted) == (np.isfinite(jk.ratio[m]) and not lo <= jk.ratio[m] <= 1.0 / lo)
    for m in refitted:
        ym = y.copy()
        ym[:, m] = np.nan
        ref = joint_fit(model, ym, fit.theta, fit.pose, n_iter=100, penalty=fit.penalty).theta - fit.theta
        assert np.allclose(jk.shifts[m], ref, atol=1e-3)


def test_clean_trial_keeps_every_one_step_replicate(monkeypatch):
    model, y, q, _ = _wrist_trial(2)
    fit = joint_fit(model, y, model.theta_center, q, n_iter=50, rate=100.0, cutoff=6.0)
    jk = marker_jackknife(model, y, fit.theta, fit.pose, fit.penalty)
    assert jk.status == ("one-step",) * 6
    checked = np.isfinite(jk.ratio)
    assert np.all(np.abs(jk.ratio[checked] - 1.0) < 0.05)
    monkeypatch.setattr(jackknife, "LINEAR_RATIO", 1e-12)  # every one-step replicate accepted
    unchecked = marker_jackknife(model, y, fit.theta, fit.pose, fit.penalty)
    assert np.array_equal(jk.shifts, unchecked.shifts) and np.array_equal(jk.cov, unchecked.cov)
