"""No tight interval from a broken fit; parameters informed by the markers' placement are said so."""

import numpy as np
import pytest

import skelid.estimators.marker as marker_mod
from skelid.data import MarkerData
from skelid.errors import ConvergenceError, SettingError, SkelidWarning
from skelid.estimators.checks.misfit import placement_information
from skelid.estimators.fit.joint import box_bias
from skelid.estimators.marker import MarkerEstimator
from skelid.estimators.uncertainty.singular import deconvolve_poses
from skelid.model.kinematics import marker_positions
from skelid.simulate import builtin_model, simulate
from tests.estimators.test_misfit import _knee_model


def test_a_fit_that_does_not_converge_fails_in_one_line(monkeypatch):
    model = builtin_model("case-b")
    trial = simulate(model, n_frames=120, sigma=2.0, rng=np.random.default_rng(0))
    real = marker_mod.joint_fit
    calls = []

    def creeping(*args, **kwargs):  # every fit stops early and its estimate keeps moving by 2 mm a call
        calls.append(1)
        f = real(*args, **kwargs)
        return f._replace(converged=False, theta=f.theta + 2.0 * len(calls))

    monkeypatch.setattr(marker_mod, "joint_fit", creeping)
    with pytest.raises(ConvergenceError) as exc:
        MarkerEstimator(model, n_iter=5, cutoff=None, jackknife=False).fit(trial.data)
    assert "\n" not in exc.value.one_line() and "did not converge" in exc.value.one_line()


def test_a_fit_that_keeps_moving_is_kept_and_flagged_when_asked(monkeypatch):
    model = builtin_model("case-b")
    trial = simulate(model, n_frames=120, sigma=2.0, rng=np.random.default_rng(0))
    real = marker_mod.joint_fit
    calls = []

    def creeping(*args, **kwargs):
        calls.append(1)
        f = real(*args, **kwargs)
        return f._replace(converged=False, theta=f.theta + 2.0 * len(calls))

    monkeypatch.setattr(marker_mod, "joint_fit", creeping)
    with pytest.warns(SkelidWarning, match="stopped before converging"):
        est = MarkerEstimator(model, n_iter=5, cutoff=None, jackknife=False, on_nonconvergence="warn").fit(trial.data)
    assert np.all(np.isfinite(est.theta_)) and not est.fit_info_.converged
    with pytest.raises(SettingError, match="on_nonconvergence"):
        MarkerEstimator(model, on_nonconvergence="ignore").fit(trial.data)


def test_a_slow_fit_is_continued_until_it_settles():
    model = builtin_model("case-b")
    trial = simulate(model, n_frames=120, sigma=2.0, rng=np.random.default_rng(0))
    est = MarkerEstimator(model, n_iter=1, cutoff=None, jackknife=False, theta0=[205.0]).fit(trial.data)
    full = MarkerEstimator(model, cutoff=None, jackknife=False).fit(trial.data)
    assert est.theta_[0] == pytest.approx(full.theta_[0], abs=0.25 * full.posterior_.sd[0] + 1e-9)


def test_an_unreliable_bias_correction_falls_back_to_the_bootstrap(monkeypatch):
    model = builtin_model("case-b")
    trial = simulate(model, n_frames=120, sigma=5.0, rng=np.random.default_rng(1))
    monkeypatch.setattr(marker_mod, "BIAS_RELIABLE", 0.0)  # every correction counts as large
    est = MarkerEstimator(model, cutoff=None, n_boot=4, jackknife=False, rng=np.random.default_rng(2))
    est.fit(trial.data)
    assert est.bias_method_ == "bootstrap" and est.bias_fallback_["n_boot"] == 4
    assert est.bias_fallback_["reason"] == "large"
    assert est.bias_[0] == pytest.approx(est.bias_fallback_["bootstrap"][0])
    assert any("parametric bootstrap" in w.message and "more than 0 sd" in w.message for w in est.warnings_)
    # the re-evaluated correction is the second-order bias at theta_hat - b and the deconvolved poses
    # (brute force: the same formula, the poses deconvolved with their own variance)
    fit, used = est.fit_info_, est.frames_used_
    assert used.all()
    b = est.bias_fallback_["box"]
    var = []
    box_bias(model, est.y_, fit.theta, fit.pose, est.sigma_**2, weights=est.marker_weights_, pose_var=var)
    q_tilde = deconvolve_poses(fit.pose, var[0], used)
    again = box_bias(model, est.y_, fit.theta - b, q_tilde, est.sigma_**2, weights=est.marker_weights_)
    assert est.bias_fallback_["box_corrected"] == pytest.approx(again.tolist(), rel=1e-9, abs=1e-12)


def test_a_static_trial_flags_placement_and_carries_its_uncertainty():
    model = _knee_model()
    rng = np.random.default_rng(3)
    n = 120
    q = np.zeros((n, model.n_pose))
    for k, d in enumerate(model.dofs):  # standing still: joints move well under a degree
        q[:, k] = (0.2 if d.segment == 1 else 0.0) + np.radians(0.2) * np.sin(0.05 * np.arange(n) + k)
    y = marker_positions(model, model.theta_center, q) + rng.normal(0.0, 0.5, size=(n, 6, 3))
    data = MarkerData(y, model.marker_names, 100.0, "mm")
    est = MarkerEstimator(model, cutoff=None, jackknife=False, rng=np.random.default_rng(0)).fit(data)
    assert est.placement_["static"] and est.placement_["placement_sd"] == 5.0
    assert all(v["informed_by_placement"] for v in est.placement_["parameters"].values())
    assert any("nominal placement" in w.message for w in est.warnings_)
    # the covariance added is exactly sd^2 times the placement sensitivity (closed form)
    fit = est.fit_info_
    place = placement_information(model, est.y_, fit.theta, fit.pose, est.frames_used_, fit.penalty)
    bare = MarkerEstimator(model, cutoff=None, jackknife=False, placement_sd=0.0,
                           rng=np.random.default_rng(0)).fit(data)
    assert np.allclose(est.cov_data_ - bare.cov_data_, 25.0 * place["cov_per_unit"], rtol=1e-6, atol=1e-12)
    assert np.all(est.posterior_.sd > bare.posterior_.sd)
    # the joints stood still: the values are the placement's, not identified by motion
    assert {p.status for p in bare.result().parameters.values()} == {"placement"}
    assert {p.status for p in est.result().parameters.values()} <= {"placement", "poor"}
    moving = simulate(model, n_frames=120, sigma=0.5, rng=np.random.default_rng(4))
    moved = MarkerEstimator(model, cutoff=None, jackknife=False, rng=np.random.default_rng(0)).fit(moving.data)
    assert not moved.placement_["static"]
    assert all(r["status"] != "placement" for r in moved.identifiability_["table"])


def test_a_stated_placement_sd_widens_a_functional_centre_too():
    # a joint centre found from motion (nothing flagged as placement-informed) still moves with a
    # misplaced marker: a stated placement sd adds its effect on every parameter (closed form)
    from tests.estimators.test_noise import two_link

    model = two_link()
    trial = simulate(model, n_frames=120, sigma=0.5, rng=np.random.default_rng(4))
    kw = {"cutoff": None, "jackknife": False, "rng": np.random.default_rng(0)}
    moved = MarkerEstimator(model, **kw).fit(trial.data)
    assert not any(v["informed_by_placement"] for v in moved.placement_["parameters"].values())
    stated = MarkerEstimator(model, placement_sd=2.0, **kw).fit(trial.data)
    f = moved.fit_info_
    place = placement_information(model, moved.y_, f.theta, f.pose, moved.frames_used_, f.penalty)
    assert np.all(np.diag(place["cov_per_unit"]) > 0)
    assert np.allclose(stated.cov_data_ - moved.cov_data_, 4.0 * place["cov_per_unit"], rtol=1e-6, atol=1e-12)
    assert np.allclose(stated.cov_shared_, 4.0 * place["cov_per_unit"], rtol=1e-6, atol=1e-12)


def test_near_a_singular_pose_the_fit_reaches_the_minimum_a_start_at_the_truth_reaches():
    # an elbow kept near the folded pose: per-frame fits jump between pose branches, and a motion-model
    # fit started from them sticks in a local minimum unless a stiffer motion model is fitted first
    from skelid.estimators.fit.joint import joint_fit
    from skelid.simulate import simulate_posture

    model = builtin_model("case-a")
    trial = simulate_posture(model, [250.0], 80, 5.0, (150.0, 172.0), np.random.default_rng(0))
    est = MarkerEstimator(model, cutoff=8.0, outlier_threshold=None)
    y = trial.data.positions
    st = marker_mod.start_stage(model, y, 100.0, est, np.random.default_rng(0))
    sc = marker_mod.screen_stage(model, st, est)

    def cost(f):
        return f.rss + f.pose.ravel() @ (f.penalty @ f.pose.ravel())

    def fit(start, cutoff, n_iter=100):
        return joint_fit(model, sc.y, start.theta, start.pose, bounds=st.bounds, frames=sc.fixed, rate=100.0,
                         cutoff=cutoff, n_iter=n_iter)

    ref = joint_fit(model, y, trial.theta, trial.pose, rate=100.0, cutoff=8.0)
    graduated = fit(fit(sc.fit, 8.0 / marker_mod.STIFFER, marker_mod.STIFF_ITER), 8.0)  # the motion stage's start
    assert cost(graduated) <= cost(ref) + 10.0 and graduated.theta[0] == pytest.approx(ref.theta[0], abs=0.05)
    assert cost(fit(sc.fit, 8.0)) > cost(ref) + 100.0  # without the stiffer fit first: a local minimum


def test_the_bootstrap_that_stands_in_for_the_correction_also_widens_the_interval(monkeypatch):
    model = builtin_model("case-b")
    trial = simulate(model, n_frames=120, sigma=5.0, rng=np.random.default_rng(1))
    monkeypatch.setattr(marker_mod, "BIAS_RELIABLE", 0.0)  # every correction counts as large
    monkeypatch.setattr(marker_mod, "PROFILE_CHECK", np.inf)  # the bootstrap's own terms, no sd along the profile
    shifts = np.array([[1.0], [3.0], [5.0], [7.0]])  # refits' shifts: mean 4, variance 20/3
    monkeypatch.setattr(MarkerEstimator, "_bootstrap_bias", lambda self, *a: shifts)
    est = MarkerEstimator(model, cutoff=None, jackknife=False, rng=0).fit(trial.data)
    assert est.bias_[0] == pytest.approx(4.0)
    plain = est.cov_plain_[0, 0]
    # the refits' excess spread, their Monte Carlo error, and half the disagreement with the second-order
    # bias at the deconvolved poses, squared
    b_tilde = est.bias_fallback_["box_deconvolved"][0]
    extra = max(20.0 / 3.0 - plain, 0.0) + 20.0 / 3.0 / 4 + 0.25 * (4.0 - b_tilde) ** 2
    assert est.cov_data_[0, 0] == pytest.approx(est.fit_.cov.data[0, 0] + extra)
    assert est.posterior_.sd[0] == pytest.approx(np.sqrt(est.fit_.cov.data[0, 0] + extra))
    assert any("spread" in w.message for w in est.warnings_)
