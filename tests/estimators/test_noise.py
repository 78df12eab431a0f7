import numpy as np
import pytest
import scipy.sparse as sp

from skelid.errors import ModelError
from skelid.estimators.checks.noise import group_sigma, marker_groups, row_leverage
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
