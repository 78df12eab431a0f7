"""The check of the local bias approximation near singular poses, and its fallback, against references."""

import numpy as np
import pytest

from skelid.estimators.fit.joint import box_bias, joint_fit, smoothed_bias
from skelid.estimators.marker import MarkerEstimator
from skelid.estimators.uncertainty.singular import (
    _N_CUTOFFS,
    POSE_SENSITIVE,
    assigned_branch_start,
    branch_joints,
    branch_settled,
    branch_side,
    deconvolve_poses,
    expansion_consistent,
    fallback_covariance,
    indirect_bias,
    mirrored_start,
    pose_check,
    quadratic_term_draws,
)
from skelid.model.kinematics import joint_positions, marker_positions
from skelid.simulate import builtin_model, simulate, simulate_posture
from tests.estimators.test_joint import _dense_normal_matrix, _small_fit


def test_the_pose_variance_of_the_smoothed_bias_is_the_dense_inverse():
    model, y, theta, q, R = _small_fit()
    P, Q, T = model.n_params, model.n_pose, len(q)
    var = []
    smoothed_bias(model, y, theta, q, 4.0, R, pose_var=var)
    N, _ = _dense_normal_matrix(model, y, theta, q, R)
    dense = 4.0 * np.diag(np.linalg.inv(N))[P:].reshape(T, Q)
    np.testing.assert_allclose(var[0], dense, rtol=1e-7)


def test_the_pose_variance_of_the_box_bias_is_the_dense_inverse():
    model, y, theta, q, R = _small_fit(n_frames=12)
    P, Q, T = model.n_params, model.n_pose, len(q)
    var = []
    box_bias(model, y, theta, q, 4.0, pose_var=var)
    N, _ = _dense_normal_matrix(model, y, theta, q, R * 0.0)
    dense = 4.0 * np.diag(np.linalg.inv(N))[P:].reshape(T, Q)
    np.testing.assert_allclose(var[0], dense, rtol=1e-6)


def test_deconvolution_removes_the_stated_variance_and_no_more():
    rng = np.random.default_rng(0)
    t = np.arange(400) / 100.0
    clean = np.stack([np.sin(2 * np.pi * 0.5 * t), 0.3 * np.cos(2 * np.pi * 0.8 * t)], axis=1)
    noisy = clean + rng.normal(0.0, [0.05, 0.02], size=clean.shape)
    variance = np.broadcast_to(np.array([0.05, 0.02]) ** 2, clean.shape)
    out = deconvolve_poses(noisy, variance)
    removed = np.mean((noisy - out) ** 2, axis=0)
    # the discrepancy principle: at least the stated variance removed, within one step of the cutoff grid
    assert np.all(removed >= variance[0]) and np.all(removed < 1.3 * variance[0])
    assert np.all(np.mean((out - clean) ** 2, axis=0) < 0.5 * variance[0])  # closer to the truth than the data
    assert _N_CUTOFFS > 50


def test_deconvolution_of_a_straight_line_keeps_it():
    q = np.linspace(0.0, 1.0, 100)[:, None] * np.array([1.0, -2.0])
    out = deconvolve_poses(q, np.full(q.shape, 1e-6))
    np.testing.assert_allclose(out, q, atol=1e-9)  # the odd reflection extends a line as a line


def test_indirect_bias_solves_the_fixed_point_of_a_linear_bias():
    # refits of a model whose estimate has mean a * theta + c (fixed noise draws): theta_hat = a theta + c + m
    a, c = 0.8, np.array([3.0])
    noise = np.array([[-1.0], [0.5], [2.0], [-0.5]])

    def refit(theta, q):
        return a * theta + c + noise

    theta_hat = np.array([100.0])
    b, draws = indirect_bias(refit, theta_hat, None, n_steps=200)
    theta_true = (theta_hat - c - noise.mean()) / a  # E[theta* | theta] = theta_hat
    np.testing.assert_allclose(theta_hat - b, theta_true, rtol=1e-10)
    np.testing.assert_allclose(draws.shifts, refit(theta_true, None) - theta_true, rtol=1e-8)
    b0, _ = indirect_bias(refit, theta_hat, None, n_steps=0)  # no step: the bias at theta_hat
    np.testing.assert_allclose(b0, (a - 1) * theta_hat + c + noise.mean())


def test_fallback_covariance_closed_form():
    shifts = np.array([[1.0, 0.0], [3.0, 2.0], [5.0, 0.0], [7.0, 2.0]])
    plain = np.diag([1.0, 10.0])
    c = np.cov(shifts, rowvar=False)
    got = fallback_covariance(shifts, plain, np.array([2.0, 0.0]))
    w, V = np.linalg.eigh(c - plain)
    expected = (V * np.clip(w, 0, None)) @ V.T + c / 4 + np.array([[1.0, 0.0], [0.0, 0.0]])
    np.testing.assert_allclose(got, expected)


def _check(model, trial, **kw):
    est = MarkerEstimator(model, jackknife=False, rng=0, **kw).fit(trial.data)
    f = est.fit_
    fit = f.weights.fit
    var = []
    y = np.where(f.frames.used[:, None, None], f.screen.y, np.nan)
    smoothed_bias(model, y, fit.theta, fit.pose, est.sigma_**2, fit.penalty, pose_var=var)
    return est, pose_check(model, f.screen.y, fit.theta, fit.pose, var[0], f.frames.used)


def test_near_the_straight_pose_the_check_fails_and_the_bootstrap_stands_in():
    model = builtin_model("case-a")
    trial = simulate_posture(model, [250.0], 80, 15.0, (0.0, 25.0), np.random.default_rng(7))
    est, check = _check(model, trial, n_boot=2)
    assert check.sensitive and np.abs(check.info_change[0]) > POSE_SENSITIVE
    assert est.bias_method_ == "bootstrap" and est.bias_fallback_["reason"] == "pose"
    assert est.bias_[0] == pytest.approx(est.bias_fallback_["bootstrap"][0])
    assert any(w.code == "bias-fallback" and "singular pose" in w.message for w in est.warnings_)


def test_away_from_singular_poses_the_check_passes():
    model = builtin_model("case-a")
    trial = simulate(model, theta=[250.0], n_frames=80, sigma=5.0, rng=np.random.default_rng(7))
    est, check = _check(model, trial)
    assert not check.sensitive and est.bias_method_ == "box"
    assert not any(w.code == "bias-fallback" for w in est.warnings_)


def test_the_self_consistency_rule_is_scale_free_where_the_size_rule_is_not():
    # closed form: a profile bias b(theta) = c / theta that does not shrink with the frames (incidental
    # poses), an sd that does (sd ~ 1 / sqrt(T)); re-evaluated at theta - b it changes by c b / (theta (theta - b))
    c, theta, n_boot = 300.0, 250.0, 10
    b = np.array([c / theta])
    b_next = c / (theta - b)
    assert b_next - b == pytest.approx(c * b / (theta * (theta - b)))
    for frames in (100, 1_000, 10_000, 100_000):
        sd = np.array([25.0 / np.sqrt(frames)])
        assert expansion_consistent(b, b_next, sd, n_boot).all()  # trusted at every length ...
    assert np.abs(b) > 1.5 * 25.0 / np.sqrt(10_000)  # ... where "larger than 1.5 sd" distrusts it
    # a bias that changes fast with theta (theta near c's scale): the expansion's own error is large
    theta = 2.0
    b = np.array([c / theta])
    assert not expansion_consistent(b, c / (theta - b), np.array([1.0]), n_boot).any()
    # the boundary is the bootstrap's Monte Carlo error sd / sqrt(n_boot)
    assert expansion_consistent([0.0], [0.099], [1.0], 100).all()
    assert not expansion_consistent([0.0], [0.101], [1.0], 100).any()


def test_a_large_correction_goes_to_the_bootstrap_even_where_it_stays_put(monkeypatch):
    """Staying put at the corrected point does not vouch for the expansion: on long trials it does
    and still leaves 0.7 sd of bias (benchmarks/results/bias_trigger.md), so the size decides."""
    import skelid.estimators.marker as marker_mod

    model = builtin_model("case-a")
    trial = simulate(model, theta=[250.0], n_frames=80, sigma=5.0, rng=np.random.default_rng(7))
    monkeypatch.setattr(marker_mod, "BIAS_RELIABLE", 0.0)  # every correction is large
    est = MarkerEstimator(model, jackknife=False, n_boot=4, rng=0).fit(trial.data)
    assert est.bias_method_ == "bootstrap" and est.bias_fallback_["reason"] == "large"
    assert est.bias_fallback_["consistent"] == [True]
    # the reference: the second-order bias at the estimate, which moves by less than sd / sqrt(n_boot)
    # when evaluated at the corrected geometry and the deconvolved poses
    # in the fit's own frame (the data less origin_), where its numbers were computed
    fit, used = est.fit_.weights.fit, est.frames_used_
    y = np.where(used[:, None, None], est.fit_.screen.y, np.nan)
    var = []
    b = smoothed_bias(model, y, fit.theta, fit.pose, est.sigma_**2, fit.penalty, weights=est.marker_weights_,
                      pose_var=var)
    np.testing.assert_allclose(est.bias_fallback_["box"], b, rtol=1e-9)
    q_tilde = deconvolve_poses(fit.pose, var[0], used)
    again = smoothed_bias(model, y, fit.theta - b, q_tilde, est.sigma_**2, fit.penalty,
                          weights=est.marker_weights_)
    np.testing.assert_allclose(est.bias_fallback_["box_corrected"], again, rtol=1e-9)
    sd = est.sigma_ * np.sqrt(np.diag(np.linalg.inv(fit.info)))
    assert np.all(np.abs(again - b) <= sd / np.sqrt(est.n_boot))


def test_the_second_order_draws_average_to_the_smoothed_bias():
    # the mean of delta_2 over Gaussian draws is the closed-form second-order bias (with the penalty's term)
    model, y, theta, q, R = _small_fit()
    b = smoothed_bias(model, y, theta, q, 25.0, R, max_frames=10**6)
    d = quadratic_term_draws(model, y, theta, q, 25.0, R, n_draws=4000, rng=np.random.default_rng(0))
    se = d.std(axis=0) / np.sqrt(len(d))
    assert np.all(np.abs(d.mean(axis=0) - b) < 4 * se)
    assert np.all(d.std(axis=0) > 0)


def test_without_a_penalty_the_second_order_draws_average_to_box_bias():
    model, y, theta, q, _ = _small_fit(n_frames=30)
    b = box_bias(model, y, theta, q, 25.0)
    d = quadratic_term_draws(model, y, theta, q, 25.0, None, n_draws=4000, rng=np.random.default_rng(1))
    assert np.all(np.abs(d.mean(axis=0) - b) < 4 * d.std(axis=0) / np.sqrt(len(d)))


def test_branch_joints_are_those_fixed_by_two_distances():
    assert [j.dof for j in branch_joints(builtin_model("case-a"))] == [3, 4]  # one marker per element
    assert branch_joints(builtin_model("case-b")) == ()  # the forearm's two markers fix its pose


def test_the_mirrored_angle_reflects_the_child_marker_across_the_line_through_the_joint():
    model = builtin_model("case-a")
    trial = simulate_posture(model, [250.0], 20, 0.0, (150.0, 172.0), np.random.default_rng(2))
    theta, q = trial.theta, trial.pose
    for joint in branch_joints(model):
        psi = branch_side(model, theta, q, joint)
        assert np.all(np.abs(psi) <= np.pi / 2)
        mirrored = q.copy()
        mirrored[:, joint.dof] -= 2 * psi
        np.testing.assert_allclose(branch_side(model, theta, mirrored, joint), -psi, atol=1e-9)
        # reference: reflect the child's marker across the line from the joint centre to the parent's marker
        centre = joint_positions(model, theta, q)[:, joint.segment]
        u = marker_positions(model, theta, q)[:, joint.parent_marker] - centre
        v = marker_positions(model, theta, q)[:, joint.child_marker] - centre
        e = u / np.linalg.norm(u, axis=-1, keepdims=True)
        reflected = centre + 2 * np.sum(v * e, axis=-1, keepdims=True) * e - v
        np.testing.assert_allclose(marker_positions(model, theta, mirrored)[:, joint.child_marker], reflected,
                                   atol=1e-9)
        # at the singular pose itself the angle is zero
        on_line = q.copy()
        on_line[:, joint.dof] -= psi
        np.testing.assert_allclose(branch_side(model, theta, on_line, joint), 0.0, atol=1e-9)


@pytest.mark.parametrize("seed", [20, 22])
def test_a_stretch_of_frames_on_the_mirrored_branch_is_found_and_refitted(seed):
    # near the folded elbow, 27 frames of trial 20 settle on the mirrored branch of the wrist, and in trial
    # 22 16 frames of the elbow's and 20 of the wrist's together (a local minimum of the motion-model fit
    # that mirroring either joint alone does not leave); the fit must reach the minimum a fit from the
    # true poses reaches
    model = builtin_model("case-a")
    trial = simulate_posture(model, [250.0], 500, 5.0, (150.0, 172.0), np.random.default_rng([0, 5, 250, 3, seed]))
    est = MarkerEstimator(model).fit(trial.data)
    fit = est.fit_info_
    ref = joint_fit(model, est.y_, fit.theta, trial.pose, rate=trial.data.rate, penalty=fit.penalty)

    def cost(f):
        return f.rss + float(f.pose.ravel() @ (f.penalty @ f.pose.ravel()))

    assert cost(fit) == pytest.approx(cost(ref), rel=1e-7)
    assert fit.theta[0] == pytest.approx(ref.theta[0], abs=1e-3)
    # and that fit's poses are on one branch: nothing left to mirror
    for joint in branch_joints(model):
        assert mirrored_start(model, fit.theta, fit.pose, est.y_, joint, fit.frames_used) is None


def test_a_second_order_correction_above_half_an_sd_widens_the_interval_by_its_spread(monkeypatch):
    import skelid.estimators.marker as marker

    model = builtin_model("case-a")
    trial = simulate(model, theta=[250.0], n_frames=60, sigma=5.0, rng=np.random.default_rng(4))
    fits = {}
    for threshold in (0.0, np.inf):
        monkeypatch.setattr(marker, "SECOND_ORDER_SPREAD", threshold)
        fits[threshold] = MarkerEstimator(model, jackknife=False, rng=0).fit(trial.data)
    wide, plain = fits[0.0], fits[np.inf]
    assert wide.bias_method_ == plain.bias_method_ == "box"
    np.testing.assert_allclose(wide.theta_, plain.theta_)
    np.testing.assert_allclose(plain.cov_, plain.cov_data_)
    assert wide.cov_[0, 0] > plain.cov_[0, 0]


def _folded_case_a():
    """Case A near the folded pose, noise-free: model, truth, poses, markers, branch joints, every frame used."""
    model = builtin_model("case-a")
    trial = simulate_posture(model, [250.0], 100, 0.0, (150.0, 172.0), np.random.default_rng(5))
    return model, trial.theta, trial.pose, trial.clean, branch_joints(model), np.ones(len(trial.pose), dtype=bool)


def test_the_minority_branch_of_every_joint_is_mirrored_back_at_once():
    model, theta, q, y, joints, used = _folded_case_a()
    assert branch_settled(model, theta, q, joints, used)
    assert mirrored_start(model, theta, q, y, joints, used) is None
    wrong = q.copy()
    for joint, frames in zip(joints, (slice(60, 90), slice(40, 45)), strict=True):  # 30 % and 5 % of the frames
        wrong[frames, joint.dof] -= 2 * branch_side(model, theta, q, joint)[frames]
    assert not branch_settled(model, theta, wrong, joints, used)
    assert branch_settled(model, theta, wrong, joints, used & (np.arange(len(q)) < 40))  # unused frames do not count
    start = mirrored_start(model, theta, wrong, y, joints, used)
    np.testing.assert_allclose(start, q, atol=1e-6)  # noise-free markers: back to the true poses exactly
    # one joint alone: only its frames change
    start = mirrored_start(model, theta, wrong, y, joints[1], used)
    np.testing.assert_allclose(start[:, joints[1].dof], np.where(np.arange(len(q)) < 60, q[:, joints[1].dof],
                                                                  wrong[:, joints[1].dof]), atol=1e-6)


def test_the_sd_along_the_profile_matches_refitted_poses_at_the_interval_ends():
    # without a motion model the profile poses at a fixed geometry are per-frame fits: the sd at the
    # interval's ends from those must match the one from the poses' linear response
    from skelid.estimators.fit.pose import fit_pose
    from skelid.estimators.uncertainty.singular import _schur, profile_sd_ratio

    model = builtin_model("case-a")
    trial = simulate_posture(model, [250.0], 60, 5.0, (150.0, 172.0), np.random.default_rng(3))
    y = trial.data.positions
    fit = joint_fit(model, y, trial.theta, trial.pose)
    sigma = 5.0
    ratio = profile_sd_ratio(model, y, fit.theta, fit.pose, sigma)
    from scipy import sparse

    R = sparse.csr_matrix((fit.pose.size,) * 2)
    S, _ = _schur(model, fit.theta, fit.pose, y, None, R)
    sd = sigma / np.sqrt(S[0, 0])
    ends = []
    for sign in (-1.0, 1.0):
        th = fit.theta + sign * 1.959964 * sd
        q = fit_pose(model, th, y, fit.pose)[0]
        S_end, _ = _schur(model, th, q, y, None, R)
        ends.append(sigma / np.sqrt(S_end[0, 0]))
    brute = max(1.0, max(ends) / sd)
    assert ratio.shape == (1,) and ratio[0] >= 1.0
    assert brute > 1.01  # near the folded pose the sd changes over the interval
    assert ratio[0] - 1.0 == pytest.approx(brute - 1.0, rel=0.2)


def test_the_profile_term_raises_each_variance_to_the_larger_end():
    from skelid.estimators.uncertainty.singular import profile_covariance

    plain = np.array([[4.0, 1.0], [1.0, 9.0]])
    extra = profile_covariance([1.1, 0.9], plain)
    np.testing.assert_allclose(np.diag(plain + extra), [4.0 * 1.21, 9.0])
    assert np.all(np.linalg.eigvalsh(extra) >= 0.0)


def test_a_motion_from_near_straight_to_near_folded_is_on_no_wrong_branch():
    # psi changes sign where the joint passes 90 degrees from both singular poses: not a mirrored branch
    from skelid.estimators.uncertainty.singular import minority_branch

    model = builtin_model("case-a")
    trial = simulate_posture(model, [250.0], 100, 0.0, (20.0, 170.0), np.random.default_rng(6))
    used = np.ones(100, dtype=bool)
    elbow = branch_joints(model)[0]
    psi = branch_side(model, trial.theta, trial.pose, elbow)
    assert np.any(psi > 0) and np.any(psi < 0)
    assert not minority_branch(model, trial.theta, trial.pose, elbow, used)[0].any()
    assert branch_settled(model, trial.theta, trial.pose, branch_joints(model), used)
    # a refit that swings frames across to the other singular pose is not the mirror of a stretch
    before = trial.pose.copy()
    near_straight = np.flatnonzero(psi > 0)[:5]
    before[near_straight, elbow.dof] = np.radians(165.0)
    assert branch_settled(model, trial.theta, trial.pose, branch_joints(model), used, before=(trial.theta, trial.pose))
    assert not branch_settled(model, trial.theta, trial.pose, branch_joints(model), used, before=(trial.theta, before))


def test_every_frame_of_a_joint_is_put_on_the_branch_asked_for():
    model, theta, q, y, joints, used = _folded_case_a()
    signs = tuple(float(np.sign(branch_side(model, theta, q, j)[0])) for j in joints)
    assert assigned_branch_start(model, theta, q, y, joints, signs, used) is None  # already there
    # the whole trial on the other branch of both joints: no minority stretch to mirror back
    wrong = q.copy()
    for joint in joints:
        wrong[:, joint.dof] -= 2 * branch_side(model, theta, q, joint)
    assert branch_settled(model, theta, wrong, joints, used)
    assert mirrored_start(model, theta, wrong, y, joints, used) is None
    start = assigned_branch_start(model, theta, wrong, y, joints, signs, used)
    np.testing.assert_allclose(start, q, atol=1e-6)  # noise-free markers: back to the true poses exactly


def test_a_frame_within_the_angle_noise_of_the_singular_pose_is_on_neither_branch():
    model, theta, q, _, joints, used = _folded_case_a()
    wrong = q.copy()
    j = joints[1]
    psi = branch_side(model, theta, q, j)
    b = float(np.linalg.norm(model.markers[j.child_marker].position))
    wrong[7, j.dof] -= psi[7] + 0.3 * np.sign(psi[7]) * 2.0 / b  # just across the singular pose: 0.3 sd at 2 mm
    assert np.sign(branch_side(model, theta, wrong, j)[7]) == -np.sign(psi[7])
    assert not branch_settled(model, theta, wrong, joints, used)
    assert branch_settled(model, theta, wrong, joints, used, sigma=2.0)
    assert not branch_settled(model, theta, wrong, joints, used, sigma=0.3)


def test_a_trial_settled_on_the_mirrored_branch_as_a_whole_reaches_the_better_minimum():
    # near the folded pose on a drawn geometry (the accuracy study's near-folded cell, sigma 15 mm, trial
    # 29), the first fit's poses sit on the mirrored branch of both joints in every frame, 21 sd from the
    # truth; the minimum a fit from the true poses reaches has a penalised cost lower by 38 sigma^2
    from pathlib import Path

    from skelid.estimators.marker import penalised_cost
    from tests.helpers import load_script

    acc = load_script(Path(__file__).resolve().parents[2] / "benchmarks" / "accuracy.py", "accuracy_study")
    seed = [0, 15, 0, (acc.NOISES + tuple(acc.POSTURES) + ("coupled",)).index("folded"), 29]
    trial = acc.singular_trial("case-a", 500, 15.0, "folded", np.random.default_rng(seed))
    est = MarkerEstimator(trial.model).fit(trial.data)
    fit = est.fit_info_
    ref = joint_fit(trial.model, est.y_, trial.theta, trial.pose, n_iter=300, penalty=fit.penalty)
    assert penalised_cost(fit) == pytest.approx(penalised_cost(ref), rel=1e-6)
    assert abs(est.theta_[0] - trial.theta[0]) < 1.96 * est.posterior_.sd[0]
