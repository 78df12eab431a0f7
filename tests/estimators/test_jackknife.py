"""Leave-one-marker-out jackknife: one-step replicates against literal refits, and folding."""

import numpy as np

from skelid._linalg import psd_sqrt
from skelid.data import MarkerData
from skelid.estimators.fit.joint import joint_fit
from skelid.estimators.marker import MarkerEstimator
from skelid.estimators.uncertainty import jackknife
from skelid.estimators.uncertainty.jackknife import literal_jackknife, marker_jackknife
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
    # the (leverage-corrected) jackknife covariance from the refits and from the one-step replicates agree
    c = np.einsum("mpq,mq->mp", jk.transform, lit)
    assert np.allclose(np.sqrt(np.diag(jk.cov)), np.sqrt(np.diag(c.T @ c)), rtol=0.25)
    assert np.allclose(jk.corrected, np.einsum("mpq,mq->mp", jk.transform, jk.shifts))


def _clustered_regression(seed, n_clusters=6, rows=8, P=3):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n_clusters, rows, P)) * rng.uniform(0.2, 3.0, size=(n_clusters, 1, 1))
    X[0] *= 6.0  # one cluster with high leverage
    return X


def test_cr2_transform_equals_bell_mccaffrey_on_a_linear_regression():
    """Delete-cluster OLS shifts mapped by cr2_transform equal -S^{-1} X_m^T (I - H_mm)^{-1/2} e_m."""
    X = _clustered_regression(1)
    G, n, P = X.shape
    rng = np.random.default_rng(2)
    y = X @ np.array([1.0, -2.0, 0.5]) + rng.normal(size=(G, n)) + rng.normal(size=(G, 1)) * 3.0
    Xs, ys = X.reshape(-1, P), y.ravel()
    S = Xs.T @ Xs
    beta = np.linalg.solve(S, Xs.T @ ys)
    e = (ys - Xs @ beta).reshape(G, n)
    S_isqrt, S_sqrt = jackknife._inv_sqrt(S), psd_sqrt(S)
    for m in range(G):
        keep = np.arange(G) != m
        Xk, yk = X[keep].reshape(-1, P), y[keep].ravel()
        d = np.linalg.solve(Xk.T @ Xk, Xk.T @ yk) - beta  # the literal delete-cluster shift
        T = jackknife.cr2_transform(S_isqrt @ (Xk.T @ Xk) @ S_isqrt, S_isqrt, S_sqrt)
        H = X[m] @ np.linalg.solve(S, X[m].T)
        w, V = np.linalg.eigh(np.eye(n) - H)
        ref = -np.linalg.solve(S, X[m].T @ (V / np.sqrt(w)) @ V.T @ e[m])
        assert np.allclose(T @ d, ref, atol=1e-10)


def test_cr2_is_unbiased_under_white_noise_and_the_plain_jackknife_is_not():
    """Exact expectations under white noise: sum_m E[c_m c_m^T] = S^{-1}; the uncorrected
    replicates' sum exceeds it, most where one cluster carries most of the information."""
    X = _clustered_regression(3)
    G, n, P = X.shape
    Xs = X.reshape(-1, P)
    S = Xs.T @ Xs
    M_res = np.eye(G * n) - Xs @ np.linalg.solve(S, Xs.T)  # residual maker: e = M_res u
    S_isqrt, S_sqrt = jackknife._inv_sqrt(S), psd_sqrt(S)
    E_cr2, E_cr3 = np.zeros((P, P)), np.zeros((P, P))
    for m in range(G):
        rows = slice(m * n, (m + 1) * n)
        S_m = S - X[m].T @ X[m]
        D = -np.linalg.solve(S_m, X[m].T @ M_res[rows])  # d_m = D u: the delete-cluster shift
        C = jackknife.cr2_transform(S_isqrt @ S_m @ S_isqrt, S_isqrt, S_sqrt) @ D
        E_cr2 += C @ C.T
        E_cr3 += D @ D.T
    assert np.allclose(E_cr2, np.linalg.inv(S), rtol=1e-9, atol=1e-12)
    assert np.all(np.diag(E_cr3) > 1.2 * np.diag(np.linalg.inv(S)))


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


def test_a_widening_too_small_to_move_an_estimate_by_half_its_sd_is_made_but_not_named():
    """The markers' disagreement is added to the interval whenever the white-noise test finds it; it is named in
    a warning only where its systematic part could move an estimate by half an sd or more (exactly fitting
    data: a disagreement significant against the rounding moved an estimate by 5e-11)."""
    model, y, q, _ = _wrist_trial(4, slide=5.0)
    fit = joint_fit(model, y, model.theta_center, q, n_iter=50, rate=100.0, cutoff=6.0)
    cov = np.linalg.inv(fit.info) * fit.rss / fit.n_obs
    new, out, msg = jackknife.jackknife_stage(model, y, fit, np.sqrt(fit.rss / fit.n_obs), cov, fold_in=True)
    assert out["folded"] and out["warn"] and out["effect_sd"] >= jackknife.JACKKNIFE_EFFECT and msg
    wide = 400.0 * cov  # the same disagreement beside an interval 20 times wider
    new_w, out_w, msg_w = jackknife.jackknife_stage(model, y, fit, np.sqrt(fit.rss / fit.n_obs), wide, fold_in=True)
    assert out_w["folded"] and not out_w["warn"] and msg_w is None
    assert out_w["effect_sd"] < jackknife.JACKKNIFE_EFFECT
    assert np.all(np.diag(new_w) > np.diag(wide))  # still widened


def test_noise_free_markers_that_differ_in_their_last_digits_are_not_an_artefact():
    """Markers written by another program's kinematics agree with skelid's to the last digits only: their
    disagreement (1e-8 mm, and structured) is tested against rounding, not against a noise level of 1e-9 mm,
    and neither widens the interval nor warns."""
    model, _, q, truth = _wrist_trial(4)
    y = marker_positions(model, truth, q)
    wrist = [k for k, d in enumerate(model.dofs) if d.segment == 1]
    y[:, 3] += 1e-8 * q[:, wrist]
    est = MarkerEstimator(model, cutoff=None, rng=np.random.default_rng(0)).fit(
        MarkerData(y, model.marker_names, 100.0, "mm"))
    assert est.sigma_ < 1e-6
    assert est.jackknife_["available"] and not est.jackknife_["folded"]
    assert not any("leave-one-marker-out" in w.message for w in est.warnings_)


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


def test_a_refit_cut_short_by_the_iteration_cap_has_no_replicate(monkeypatch):
    """A refit that stops at the cap counts as having found no estimate, so the cap must leave
    converging refits room: on the Plug-in-Gait trial a cap of 50 dropped the four most
    influential markers (their refits converged, off the bounds, within 600)."""
    model, y, q, _ = _wrist_trial(4, slide=5.0)
    fit = joint_fit(model, y, model.theta_center, q, n_iter=50, rate=100.0, cutoff=6.0)
    full = marker_jackknife(model, y, fit.theta, fit.pose, fit.penalty)
    assert full.status[0] == "refitted" and full.replicate[0]
    monkeypatch.setattr(jackknife, "REFIT_ITER", 1)
    cut = marker_jackknife(model, y, fit.theta, fit.pose, fit.penalty)
    assert cut.status[0] == "refit failed" and not cut.replicate[0]


def test_a_direction_no_replicate_moves_is_left_alone_by_the_fold():
    """E_0 singular (a parameter that only markers without a replicate inform): the markers' spread is
    compared with white noise's on E_0's range, and the other direction keeps the model's variance."""
    S = np.diag([4.0, 1.0, 9.0])
    S_sqrt, S_isqrt = np.sqrt(S), np.diag(1.0 / np.sqrt(np.diag(S)))
    E0 = np.diag([1.0, 0.5, 0.0])
    B, B_pinv = jackknife.null_factor(E0, S_sqrt, S_isqrt)
    assert B.shape == (3, 2)
    np.testing.assert_allclose(B @ B.T, E0, atol=1e-12)
    np.testing.assert_allclose(B_pinv @ B, np.eye(2), atol=1e-12)
    V = np.diag([0.25, 1.0, 1.0 / 9.0])
    jk = jackknife.Jackknife(np.zeros((4, 3)), np.ones(4, bool), np.diag([3.0, 0.5, 0.0]), E0, 2.0,
                             factor=B)
    folded, lam, _ = jackknife.fold(V, jk)
    np.testing.assert_allclose(np.diag(folded), [0.25 + 2.0, 1.0, 1.0 / 9.0], atol=1e-12)
    assert lam.shape == (3,)


def _wrist_with_x(model, x):
    """The wrist model with the centre's x fixed at ``x`` (only y and z estimated), or, with ``x`` None, all
    three with the prior's upper bound at the fit's x."""
    from skelid.model import model_from_dict

    d = {"model": {"name": "wrist", "dim": 3, "units": "mm"},
         "segments": [{"name": "forearm", "parent": "ground",
                       "joint": {"name": "root", "type": "free", "position": [0.0, 0.0, 0.0]}},
                      {"name": "hand", "parent": "forearm",
                       "joint": {"name": "wrist", "type": "spherical", "position": [250.0 + x[0], 0.0, 0.0]}}],
         # a joint centre moved by the parameter keeps the child's markers where they were
         "markers": [{"name": m.name, "segment": m.segment,
                      "position": list(np.asarray(m.position) - [x[0] * (m.segment == "hand"), 0.0, 0.0])}
                     for m in model.markers],
         "parameters": [{"name": "wrist", "kind": "joint_centre", "joint": "wrist", "axes": x[1],
                         "prior": {"type": "uniform", "lower": -40.0, "upper": x[2]}}]}
    return model_from_dict(d)


def test_a_parameter_on_its_bound_is_held_and_the_others_replicated_as_without_it():
    """A parameter whose estimate sits on its prior's bound: no replicate moves it, no marker loses its
    replicate to a refit that ends there, and the others' replicates are those of the model without it."""
    model, y, q, _ = _wrist_trial(0)
    fit = joint_fit(model, y, model.theta_center, q, n_iter=50, rate=100.0, cutoff=6.0)
    x = float(fit.theta[0])
    assert x > max(fit.theta[1:])  # the upper bound at x holds x and no other
    on_bound = _wrist_with_x(model, (0.0, ["x", "y", "z"], x))
    assert jackknife.held_on_bound(on_bound, fit.theta).tolist() == [True, False, False]
    jk = marker_jackknife(on_bound, y, fit.theta, fit.pose, fit.penalty)
    assert jk.available and jk.replicate.all() and "refit failed" not in jk.status
    assert np.all(jk.shifts[:, 0] == 0) and np.all(jk.cov[0] == 0) and np.all(jk.null_mean[:, 0] == 0)
    without = _wrist_with_x(model, (x, ["y", "z"], 40.0))
    ref = marker_jackknife(without, y, fit.theta[1:], fit.pose, fit.penalty)
    np.testing.assert_allclose(jk.shifts[:, 1:], ref.shifts, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(jk.cov[1:, 1:], ref.cov, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(jk.null_mean[1:, 1:], ref.null_mean, rtol=1e-8, atol=1e-12)
    cov = np.diag([1.0, 2.0, 3.0])
    folded, _, _ = jackknife.fold(cov, jk)
    assert folded[0, 0] == 1.0 and np.all(folded[0, 1:] == 0)


def test_the_markers_artefact_terms_sum_to_the_stated_artefacts_covariance():
    """Each marker's share of the artefact's covariance (unit rms) sums, times rms^2, to
    :func:`artefact_covariance`, which a refit checks (``test_artefact_influence_predicts_the_shift_of_a_refit``)."""
    from skelid.estimators.checks.artefact import artefact_covariance

    model, y, q, _ = _wrist_trial(3)
    fit = joint_fit(model, y, model.theta_center, q, n_iter=50, rate=100.0, cutoff=6.0)
    jk = marker_jackknife(model, y, fit.theta, fit.pose, fit.penalty)
    used = np.ones(len(y), bool)
    ref = artefact_covariance(model, y, fit.theta, fit.pose, fit.penalty, 2.0, used)
    assert jk.artefact.shape == (6, 3, 3)
    np.testing.assert_allclose(4.0 * jk.artefact.sum(axis=0), ref, rtol=1e-8, atol=1e-10 * np.abs(ref).max())
    for A_m in jk.artefact:  # each share a covariance
        assert np.linalg.eigvalsh(A_m).min() > -1e-10 * np.abs(ref).max()


def test_the_fold_adds_the_artefact_the_replicates_imply_to_every_direction_and_marker():
    """Replicates spread exactly as white noise plus an artefact of rms 2 on the markers with a replicate:
    the fold finds rms 2, adds 4 times every marker's share (the one without a replicate too), and nothing
    else; the test's own eigenvalues are those of the spread."""
    rng = np.random.default_rng(1)
    P, M = 3, 5
    terms = np.array([(lambda g: g @ g.T)(rng.normal(size=(P, 2))) for _ in range(M)])
    replicate = np.array([True, True, True, True, False])
    E0 = np.diag([1.0, 2.0, 0.5])
    V_J = E0 + 4.0 * terms[replicate].sum(axis=0)
    jk = jackknife.Jackknife(np.zeros((M, P)), replicate, V_J, E0, 1e6, artefact=terms)
    V = np.diag([0.3, 0.4, 0.2])
    folded, lam, rms = jackknife.fold(V, jk)
    assert rms == 2.0 or abs(rms - 2.0) < 1e-10
    np.testing.assert_allclose(folded, V + 4.0 * terms.sum(axis=0), rtol=1e-10)
    L = np.linalg.cholesky(E0)
    Li = np.linalg.inv(L)
    np.testing.assert_allclose(np.sort(lam), np.linalg.eigvalsh(Li @ V_J @ Li.T), rtol=1e-10)
    # one marker pulls beyond that form: its excess along its own direction is added on top
    pull = np.array([30.0, 0.0, 0.0])
    jk2 = jk._replace(cov=V_J + np.outer(pull, pull), null_max=2.0)
    folded2, _, rms2 = jackknife.fold(V, jk2)
    assert rms2 > 2.0
    base = V + rms2**2 * terms.sum(axis=0)
    assert np.linalg.eigvalsh(folded2 - base).min() > -1e-9 and (folded2 - base)[0, 0] > 1.0
    # replicates within white noise: nothing of the form is added
    jk3 = jk._replace(cov=0.8 * E0)
    assert jackknife.fold(V, jk3)[2] == 0.0
    np.testing.assert_allclose(jackknife.fold(V, jk3)[0], V)
