import numpy as np
import pytest
import scipy.sparse as sp

from skelid.errors import ModelError
from skelid.estimators.checks.noise import (
    INSTRUMENT_FLOOR_MM,
    effective_dof,
    group_sigma,
    marker_groups,
    row_leverage,
    squeeze_variances,
)
from skelid.estimators.fit.joint import joint_fit, smoothing_penalty, weighted_terms
from skelid.estimators.fit.likelihood import pose_information
from skelid.estimators.marker import MarkerEstimator
from skelid.model import model_from_dict
from skelid.simulate import simulate


def two_link(markers_per_segment: int = 3):
    """Planar arm: a free upper segment and a forearm on a revolute elbow whose centre is unknown."""
    up = [[80.0, 30.0], [180.0, -30.0], [250.0, 25.0]][:markers_per_segment]
    fo = [[60.0, -25.0], [150.0, 30.0], [230.0, -20.0]][:markers_per_segment]
    return model_from_dict({
        "model": {"dim": 2, "units": "mm", "name": "two_link"},
        "segments": [
            {"name": "upper", "parent": "ground", "joint": {"name": "shoulder", "type": "free",
                                                           "position": [0, 0]}},
            {"name": "fore", "parent": "upper", "joint": {"name": "elbow", "type": "revolute",
                                                         "position": [300, 0], "range": [10, 120]}}],
        "markers": [{"name": f"u{i}", "segment": "upper", "position": p} for i, p in enumerate(up)]
        + [{"name": f"f{i}", "segment": "fore", "position": p} for i, p in enumerate(fo)],
        "parameters": [{"name": "elbow", "kind": "joint_centre", "joint": "elbow", "axes": ["x", "y"],
                        "prior": {"type": "uniform", "lower": -60, "upper": 60}}]})


def _trial(sigma_per_marker, n_frames=200, seed=0):
    model = two_link()
    trial = simulate(model, sigma=0.0, n_frames=n_frames, rng=np.random.default_rng(seed))
    rng = np.random.default_rng(seed + 100)
    y = trial.clean + rng.normal(size=trial.clean.shape) * np.asarray(sigma_per_marker)[None, :, None]
    return model, trial, trial.data.__class__(y, model.marker_names, trial.data.rate, model.units)


def test_unit_or_constant_weights_leave_the_fit_unchanged():
    model, trial, data = _trial([2.0] * 6, n_frames=60)
    th0 = model.theta_center
    plain = joint_fit(model, data.positions, th0, trial.pose)
    ones = joint_fit(model, data.positions, th0, trial.pose, weights=np.ones(6))
    four = joint_fit(model, data.positions, th0, trial.pose, weights=np.full((60, 6), 4.0))
    np.testing.assert_array_equal(ones.theta, plain.theta)
    np.testing.assert_allclose(four.theta, plain.theta, rtol=0, atol=1e-8)
    assert four.rss == pytest.approx(4.0 * plain.rss, rel=1e-9)


def test_zero_weight_is_the_marker_left_out():
    model, trial, data = _trial([2.0] * 6, n_frames=60)
    w = np.ones(6)
    w[2] = 0.0
    weighted = joint_fit(model, data.positions, model.theta_center, trial.pose, weights=w)
    y = data.positions.copy()
    y[:, 2] = np.nan
    dropped = joint_fit(model, y, model.theta_center, trial.pose)
    np.testing.assert_allclose(weighted.theta, dropped.theta, atol=1e-7)


@pytest.mark.parametrize("smooth", [False, True])
def test_leverage_equals_the_dense_hat_matrix(smooth):
    model, trial, data = _trial([1.0, 2.0, 1.0, 3.0, 1.0, 1.0], n_frames=12)
    w = np.array([1.0, 0.25, 1.0, 0.1, 1.0, 1.0])
    sw = np.repeat(np.sqrt(w), 2)[None, :].repeat(12, 0)
    _, Jq, Jt = weighted_terms(model, trial.theta, trial.pose, data.positions, sw)
    T, m, Q = Jq.shape
    P = Jt.shape[-1]
    R = smoothing_penalty(model, pose_information(Jq), 100.0, 8.0) if smooth else None
    J = np.zeros((T * m, P + T * Q))
    for t in range(T):
        J[t * m:(t + 1) * m, :P] = Jt[t]
        J[t * m:(t + 1) * m, P + t * Q:P + (t + 1) * Q] = Jq[t]
    N = J.T @ J
    if smooth:
        N[P:, P:] += R.toarray()
    hat = np.einsum("ij,jk,ik->i", J, np.linalg.inv(N), J)
    h = row_leverage(Jq, Jt, R)
    np.testing.assert_allclose(h.ravel(), hat, rtol=1e-5, atol=1e-9)
    if not smooth:
        assert h.sum() == pytest.approx(T * Q + P, rel=1e-9)


def test_group_sigma_and_declared_groups():
    s, dof = group_sigma(np.array([4.0, 5.0, 9.0]), np.array([3.0, 1.0, 1.0]), np.array([0, 0, 1]))
    np.testing.assert_allclose(s, [1.5, 1.5, 3.0])
    np.testing.assert_allclose(dof, [4.0, 4.0, 1.0])
    names = ("a", "b", "c")
    lab = marker_groups(names, {"skin": ["a", "c"]})
    assert lab[0] == lab[2] != lab[1]
    with pytest.raises(ModelError, match="does not have"):
        marker_groups(names, {"skin": ["z"]})
    with pytest.raises(ModelError, match="two marker groups"):
        marker_groups(names, {"g1": ["a"], "g2": ["a"]})


def test_a_noisy_marker_does_not_drag_the_joint_centre():
    sig = np.array([1.0, 1.0, 1.0, 10.0, 1.0, 1.0])  # forearm marker f0 ten times as noisy
    model, trial, data = _trial(sig, n_frames=300, seed=0)
    pooled = MarkerEstimator(model, cutoff=None, outlier_threshold=None).fit(data)
    per = MarkerEstimator(model, cutoff=None, outlier_threshold=None, noise="per_marker").fit(data)
    err_pooled = np.linalg.norm(pooled.theta_ - trial.theta)
    err_per = np.linalg.norm(per.theta_ - trial.theta)
    assert err_per < 0.5 * err_pooled
    np.testing.assert_allclose(per.marker_sigma_, sig, rtol=0.15)
    # the weighted interval is the narrower one, and it is reported per marker
    assert np.all(per.posterior_.sd < pooled.posterior_.sd)
    res = per.result()
    assert res.noise.per_marker["f0"] == pytest.approx(10.0, rel=0.15)


def test_equal_noise_gives_the_pooled_estimate():
    model, trial, data = _trial([2.0] * 6, n_frames=300, seed=5)
    pooled = MarkerEstimator(model, cutoff=None, outlier_threshold=None).fit(data)
    per = MarkerEstimator(model, cutoff=None, outlier_threshold=None, noise="per_marker").fit(data)
    assert np.all(np.abs(per.theta_ - pooled.theta_) < 0.1 * pooled.posterior_.sd)
    np.testing.assert_allclose(per.marker_sigma_, 2.0, rtol=0.15)
    assert np.mean(per.marker_sigma_) == pytest.approx(2.0, rel=0.05)
    # the leverage gives each marker its share of the degrees of freedom: they add up to the pooled dof
    assert per.sigma_ == pytest.approx(pooled.sigma_, rel=0.02)


def test_one_group_is_the_pooled_fit():
    model, trial, data = _trial([1.0, 1.0, 1.0, 3.0, 1.0, 1.0], n_frames=100, seed=2)
    pooled = MarkerEstimator(model, cutoff=None, outlier_threshold=None).fit(data)
    one = MarkerEstimator(model, cutoff=None, outlier_threshold=None, noise="per_marker",
                          marker_groups={"all": list(model.marker_names)}).fit(data)
    np.testing.assert_allclose(one.theta_, pooled.theta_, atol=1e-5)  # one refit, to convergence tolerance
    np.testing.assert_allclose(one.marker_sigma_, pooled.sigma_, rtol=1e-6)


def test_sparse_import_is_used():  # keep the scipy.sparse import honest for the penalty helpers
    assert sp.issparse(smoothing_penalty(two_link(), np.ones((10, 3, 3)) * np.eye(3), 100.0, 6.0))


def test_squeezed_variances_recover_the_prior_they_were_drawn_from():
    # fixed-seed simulation: 1/sigma_g^2 from a scaled inverse chi-square prior (d0 = 10, s0^2 = 2),
    # each s2_g from sigma_g^2 chi^2_4 / 4; the moments recover the prior, and the posterior means
    # are closer to the true variances than the raw ones
    rng = np.random.default_rng(3)
    G, d = 4000, np.full(4000, 4.0)
    true = 10.0 * 2.0 / rng.chisquare(10.0, G)
    s2 = true * rng.chisquare(4.0, G) / 4.0
    post, pdof, d0, s0 = squeeze_variances(s2, d)
    assert d0 == pytest.approx(10.0, rel=0.2)
    assert s0 == pytest.approx(2.0, rel=0.1)
    np.testing.assert_allclose(pdof, d0 + 4.0)
    assert np.mean((np.log(post) - np.log(true)) ** 2) < 0.6 * np.mean((np.log(s2) - np.log(true)) ** 2)


def test_squeeze_keeps_clearly_different_levels_and_needs_three_groups():
    s2 = np.array([1.0, 100.0, 10000.0])
    post, _, d0, _ = squeeze_variances(s2, np.full(3, 5000.0))
    assert d0 < 10.0  # the groups differ far beyond their sampling error: little pooling
    np.testing.assert_allclose(post, s2, rtol=0.01)
    post2, _, d02, _ = squeeze_variances(s2[:2], np.full(2, 5.0))
    assert d02 == 0.0 and np.array_equal(post2, s2[:2])


def test_effective_dof_of_a_correlated_series():
    # the variance of a variance estimate from an AR(1) series of n values is about
    # 2 sigma^4 (1 + rho^2) / (n (1 - rho^2)); simulated: the ratio of the two matches
    rng = np.random.default_rng(1)
    rho, n, reps = 0.8, 400, 3000
    e = rng.normal(size=(reps, n)) * np.sqrt(1 - rho**2)
    x = np.empty_like(e)
    x[:, 0] = rng.normal(size=reps)
    for t in range(1, n):
        x[:, t] = rho * x[:, t - 1] + e[:, t]
    v = (x**2).mean(axis=1)
    dof_sim = 2.0 / v.var()
    assert effective_dof(n, rho) == pytest.approx(dof_sim, rel=0.1)


def test_a_quiet_marker_cannot_collapse_below_the_instrument_floor():
    # one forearm marker at 0.03 mm among markers at 0.3 mm: its level stays at the floor (0.1 mm)
    sig = np.array([0.3, 0.3, 0.3, 0.03, 0.3, 0.3])
    model, trial, data = _trial(sig, n_frames=200, seed=4)
    per = MarkerEstimator(model, cutoff=None, outlier_threshold=None, noise="per_marker").fit(data)
    assert np.all(per.marker_sigma_ >= INSTRUMENT_FLOOR_MM * (1 - 1e-9))
    assert per.marker_sigma_[3] == pytest.approx(INSTRUMENT_FLOOR_MM, rel=1e-9)
    # two groups (no pooling across fewer than three): the floor alone holds it
    two = MarkerEstimator(model, cutoff=None, outlier_threshold=None, noise="per_marker",
                          marker_groups={"rest": ["u0", "u1", "u2", "f1", "f2"]}).fit(data)
    assert two.marker_sigma_[3] == pytest.approx(INSTRUMENT_FLOOR_MM, rel=1e-9)
    # a whole trial quieter than the floor (simulated) keeps its own level
    quiet, _, qdata = _trial([0.01] * 6, n_frames=200, seed=4)
    q = MarkerEstimator(quiet, cutoff=None, outlier_threshold=None, noise="per_marker").fit(qdata)
    np.testing.assert_allclose(q.marker_sigma_, 0.01, rtol=0.15)


def test_per_marker_weights_never_widen_a_joint_range():
    from skelid.estimators.marker import joint_motion

    sig = np.array([1.0, 1.0, 1.0, 0.2, 1.0, 8.0])
    model, trial, data = _trial(sig, n_frames=150, seed=6)
    pooled = MarkerEstimator(model, cutoff=None, outlier_threshold=None).fit(data)
    per = MarkerEstimator(model, cutoff=None, outlier_threshold=None, noise="per_marker").fit(data)
    own = joint_motion(model, per.pose_, per.frames_used_)  # the weighted fit's own poses
    for j, r in per.identifiability_["joint_range_deg"].items():
        assert r == [min(a, b) for a, b in zip(own[j], pooled.identifiability_["joint_range_deg"][j], strict=True)]
