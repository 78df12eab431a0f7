import numpy as np
import pytest

from skelid.errors import IdentifiabilityError
from skelid.estimators.fit.joint import box_bias, joint_fit
from skelid.estimators.fit.likelihood import efficient_information, frame_terms
from skelid.estimators.marker import MarkerEstimator
from skelid.model import model_from_dict
from skelid.simulate import builtin_model, simulate


def _circle(R=100.0):
    """A marker at distance R from a fixed pivot, angle unknown in every frame."""
    return model_from_dict({
        "model": {"dim": 2, "units": "mm"},
        "segments": [{"name": "arm", "parent": "ground", "joint": {"type": "revolute", "position": [0, 0]}}],
        "markers": [{"name": "a", "segment": "arm", "position": [R, 0.0]}],
        "parameters": [{"name": "R", "kind": "marker_position", "marker": "a", "axis": "x",
                        "prior": {"type": "uniform", "lower": 50, "upper": 150}}]})


def test_box_bias_equals_the_circle_closed_form():
    # radius from points at unknown angles: E[R_hat] - R = sigma^2 / (2 R) to second order
    model, R, sigma = _circle(), 100.0, 7.0
    phi = np.linspace(-3, 3, 50)[:, None]
    y = np.stack([R * np.cos(phi), R * np.sin(phi)], -1)
    b = box_bias(model, y, np.array([R]), phi, sigma**2)
    assert b[0] == pytest.approx(sigma**2 / (2 * R), rel=1e-4)


@pytest.mark.parametrize("case", ["case-a", "case-b"])
@pytest.mark.parametrize("cutoff", [None, 6.0])
def test_noise_free_data_recover_the_truth(case, cutoff):
    model = builtin_model(case)
    trial = simulate(model, theta=[237.0], sigma=0.0, n_frames=150, rng=np.random.default_rng(4))
    est = MarkerEstimator(model, sigma=1.0, cutoff=cutoff, bias_correction="none").fit(trial.data)
    assert est.theta_[0] == pytest.approx(237.0, abs=1e-6 if cutoff is None else 0.05)
    assert est.frames_used_.all()


def test_efficient_information_is_the_schur_complement_of_the_full_fisher_matrix():
    model = builtin_model("case-b")
    trial = simulate(model, sigma=0.0, n_frames=6, rng=np.random.default_rng(1))
    _, Jq, Jt = frame_terms(model, trial.theta, trial.pose, trial.clean)
    T, m, Q = Jq.shape
    # dense Jacobian over (theta, q_1..q_T)
    J = np.zeros((T * m, 1 + T * Q))
    for t in range(T):
        J[t * m:(t + 1) * m, 0] = Jt[t, :, 0]
        J[t * m:(t + 1) * m, 1 + t * Q:1 + (t + 1) * Q] = Jq[t]
    F = J.T @ J / 4.0
    schur = F[0, 0] - F[0, 1:] @ np.linalg.solve(F[1:, 1:], F[1:, 0])
    assert efficient_information(Jq, Jt, sigma=2.0)[0, 0] == pytest.approx(schur, rel=1e-8)


def test_noise_level_and_bound_are_reported():
    model = builtin_model("case-b")
    trial = simulate(model, sigma=5.0, n_frames=300, rng=np.random.default_rng(8))
    est = MarkerEstimator(model).fit(trial.data)
    assert est.sigma_ == pytest.approx(5.0, rel=0.08)
    lo, hi = est.sigma_ci_
    assert lo < est.sigma_ < hi
    res = est.result()
    assert res.parameters["L2"].crlb_sd > 0 and res.noise.fixed is False
    assert res.parameters["L2"].status == "identified"
    assert abs(est.theta_[0] - 250.0) < 5 * est.posterior_.sd[0]


def test_unidentifiable_parameter_is_named():
    d = builtin_model("case-a").to_dict()
    # the root joint's position is absorbed by the free translation of the root
    d["parameters"].append({"name": "shoulder_x", "kind": "joint_position", "joint": "shoulder",
                            "axis": "x", "prior": {"type": "uniform", "lower": -50, "upper": 50}})
    model = model_from_dict(d)
    trial = simulate(builtin_model("case-a"), sigma=2.0, n_frames=60, rng=np.random.default_rng(0))
    with pytest.raises(IdentifiabilityError, match="shoulder_x"):
        MarkerEstimator(model, cutoff=None).fit(trial.data)


def test_joint_fit_handles_missing_markers_and_skips_frames():
    model = builtin_model("case-b")
    trial = simulate(model, sigma=2.0, n_frames=80, rng=np.random.default_rng(3))
    y = np.array(trial.data.positions)
    y[10:20, 2] = np.nan  # D missing: frames keep 6 coordinates, still usable
    y[40:45, :2] = np.nan  # A and B missing: pose not determined, frames skipped
    est = MarkerEstimator(model, cutoff=None)
    with pytest.warns(UserWarning, match="5 of 80 frames"):
        est.fit(trial.data.replace(positions=y))
    assert est.frames_used_[10:20].all() and not est.frames_used_[40:45].any()
    assert abs(est.theta_[0] - 250.0) < 5 * est.posterior_.sd[0]


def test_soft_tissue_artefact_is_flagged_and_widens_the_interval():
    model = builtin_model("case-b")
    trial = simulate(model, sigma=3.0, n_frames=300, noise="sta", sta_amplitude=15.0,
                     rng=np.random.default_rng(2))
    plain = MarkerEstimator(model, robust="never").fit(trial.data)
    with pytest.warns(UserWarning, match="soft-tissue artefact"):
        auto = MarkerEstimator(model).fit(trial.data)
    assert auto.sta_score_ > 0.25
    assert auto.posterior_.sd[0] > plain.posterior_.sd[0]


def test_joint_fit_uses_the_motion_model_information():
    model = builtin_model("case-a")
    trial = simulate(model, sigma=5.0, n_frames=200, rng=np.random.default_rng(6))
    y = trial.data.positions
    plain = joint_fit(model, y, trial.theta, trial.pose)
    smooth = joint_fit(model, y, trial.theta, trial.pose, rate=100.0, cutoff=6.0)
    assert smooth.info[0, 0] > plain.info[0, 0]  # a motion model adds information
    assert smooth.pose_dof < plain.pose_dof


def test_cutoffs_follow_the_motion():
    from skelid.estimators.fit.joint import choose_cutoffs

    model = builtin_model("case-a")
    rng = np.random.default_rng(0)
    t = np.arange(1000) / 100.0
    slow = np.sin(2 * np.pi * 0.5 * t)
    fast = np.sin(2 * np.pi * 5.0 * t)
    q = np.zeros((1000, model.n_pose))
    q[:, 3] = slow + rng.normal(0, 0.05, 1000)
    q[:, 4] = fast + rng.normal(0, 0.05, 1000)
    fc = choose_cutoffs(model, q, np.ones(1000, bool), 100.0)
    assert fc[3] <= 3.0 < 6.0 <= fc[4]  # slow motion is smoothed more than fast motion
    assert np.all(fc <= 50.0)


def test_automatic_cutoff_is_recorded():
    model = builtin_model("case-b")
    trial = simulate(model, sigma=5.0, n_frames=200, rng=np.random.default_rng(9))
    est = MarkerEstimator(model).fit(trial.data)
    assert np.shape(est.cutoff_) == (model.n_pose,)
    assert len(est.result().diagnostics["cutoff_hz"]) == model.n_pose


@pytest.mark.parametrize("n_frames", [30, 400])  # the dense path and the banded sweep
def test_selected_inverse_blocks_equal_the_dense_inverse(n_frames):
    import scipy.sparse as sp

    from skelid.estimators.fit.joint import _banded_system, band_inverse_blocks, pose_edf

    rng = np.random.default_rng(5)
    Q = 4
    Jq = rng.normal(size=(n_frames, 6, Q))
    Jq[3] = 0.0  # a frame without markers: only the penalty holds it
    H = np.einsum("tki,tkj->tij", Jq, Jq)
    D3 = sp.diags([-1.0, 3.0, -3.0, 1.0], [0, 1, 2, 3], shape=(n_frames - 3, n_frames))
    R = sp.kron(D3.T @ D3, sp.diags(rng.uniform(1.0, 50.0, Q))).tocsc()
    ab = _banded_system(H, R)
    A = sp.block_diag(list(H)).toarray() + R.toarray()
    A[np.diag_indices_from(A)] += ab[-1] - np.diag(A)  # the same ridge
    Z = np.linalg.inv(A)
    idx = np.arange(n_frames)[:, None] * Q + np.arange(Q)
    ref = Z[idx[:, :, None], idx[:, None, :]]
    got = band_inverse_blocks(ab, Q)
    assert np.allclose(got, ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max())
    assert pose_edf(Jq, R) == pytest.approx(np.trace(Z @ sp.block_diag(list(H)).toarray()), rel=1e-9)


def test_artefact_influence_predicts_the_shift_of_a_refit():
    from skelid.estimators.checks.artefact import artefact_basis, artefact_influence

    model = builtin_model("case-a")
    trial = simulate(model, theta=[250.0], n_frames=300, sigma=0.0, rng=np.random.default_rng(4))
    settings = dict(sigma=1.0, cutoff=6.0, bias_correction="none", robust="never", outlier_threshold=None)
    base = MarkerEstimator(model, **settings).fit(trial.data)
    used = base.frames_used_
    y = np.where(used[:, None, None], trial.data.positions, np.nan)
    g, owner = artefact_influence(model, y, base.fit_info_.theta, base.pose_, base.fit_info_.penalty, used)
    funcs, owner_ = artefact_basis(model, base.pose_, used)
    k = int(np.argmax(np.abs(g[0])))  # the basis function that moves L2 most
    h = 0.5  # mm: small enough for the linearisation
    bump = np.zeros(trial.data.positions.shape)
    bump[:, owner_[k] // model.dim, owner_[k] % model.dim] = funcs[:, k]
    shifted = trial.data.replace(positions=trial.data.positions + h * bump)
    moved = MarkerEstimator(model, **settings).fit(shifted)
    assert abs(g[0, k]) > 0.1  # a real effect, not a vanishing one
    assert moved.theta_[0] - base.theta_[0] == pytest.approx(h * g[0, k], rel=0.05)
    # a stated artefact widens the interval by exactly that term
    wide = MarkerEstimator(model, artefact_rms=3.0, **settings).fit(trial.data)
    assert wide.cov_[0, 0] == pytest.approx(base.cov_[0, 0] + wide.cov_artefact_[0, 0], rel=1e-9)
    assert np.sqrt(wide.cov_artefact_[0, 0]) > 0.3
