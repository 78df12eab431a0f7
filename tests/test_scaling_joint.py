"""The joint fit of scales and marker offsets: bounds, convergence, the one-factor test, the free markers' prior."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from skelid.io.osim import centred_offset_priors, osim_parameters, read_osim
from skelid.scaling import (
    _bounded_step,
    _joint_refinement,
    fit_osim,
    fit_scales_and_offsets,
    one_factor_test,
)
from tests.test_scaling import _trials, leg  # noqa: F401  (the fixture)


def test_a_parameter_pressing_on_its_bound_is_held_and_the_others_take_their_conditional_step():
    info = np.array([[2.0, 1.0], [1.0, 2.0]])
    hp = np.full(2, 1e-9)  # a flat prior
    score = np.array([-3.0, 2.0])  # the first wants to go down, from its lower bound
    theta, lo, hi = np.array([0.0, 0.0]), np.array([0.0, -10.0]), np.array([10.0, 10.0])
    step = _bounded_step(info, hp, score, theta, lo, hi)
    assert step[0] == 0.0
    assert step[1] == pytest.approx(score[1] / info[1, 1], rel=1e-6)  # the optimum with the first held
    free = _bounded_step(info, hp, score, np.array([1.0, 0.0]), lo, hi)  # off its bound: the full step
    np.testing.assert_allclose(free, np.linalg.solve(info, score), rtol=1e-6)


def test_the_joint_fit_converges_with_an_offset_held_at_its_bound(leg):  # noqa: F811
    """A marker 80 mm from its model place: its offset stays at the prior's bound (50 mm) and the fit
    still converges (the full step clipped at the bound instead stalled, moving the others as if it had
    moved)."""
    truth = {"pelvis": 1.0, "thigh": 1.1, "shank": 1.0}
    trials = _trials(leg, truth, {"thigh1": (80.0, 0.0, 0.0)})
    base, info = read_osim(leg)
    model = osim_parameters(base, info, "bodies", "offsets")
    theta = model.theta_nominal.copy()
    jo = _joint_refinement(model, theta, trials[1:], None, 0)
    assert jo.converged and jo.n_iter < 30
    k = model.parameter_names.index("offset_thigh1_x")
    assert jo.theta[k] == pytest.approx(50.0)


def test_the_one_factor_test_holds_at_a_fit_short_of_its_optimum(leg):  # noqa: F811
    """One factor per body is the truth: the test does not reject it, at the optimum or 3 sd away from it in
    the offsets (a quadratic form of the score alone counted the offsets' scores: T of 1e5 and more)."""
    truth = {"pelvis": 1.04, "thigh": 1.1, "shank": 0.95}
    trials = _trials(leg, truth, {"thigh1": (6.0, -4.0, 3.0), "shank3": (-5.0, 2.0, 4.0)})
    base, info = read_osim(leg)
    model = osim_parameters(base, info, "bodies", "offsets")
    per_axis = osim_parameters(base, info, "axes", "offsets")
    ys = [t.positions for t in trials[1:]]
    jo = fit_scales_and_offsets(model, ys, model.theta_nominal, _joint_refinement(
        model, model.theta_nominal, trials[1:], None, 0).poses)
    sd = np.sqrt(np.diag(jo.cov))
    off = np.array([p.kind == "marker_offset" for p in model.parameters])
    away = replace(jo, theta=jo.theta + 3.0 * sd * off * np.where(np.arange(off.size) % 2, 1, -1))
    for fit in (jo, away):
        tests = one_factor_test(model, per_axis, fit, ys)
        assert set(tests) == {"pelvis", "thigh", "shank"}
        for b, t in tests.items():
            assert t["p"] > 1e-3, (b, t)
            assert len(t["sd"]) == 3 and len(t["axis_identified"]) == 3


def test_a_free_markers_offset_prior_is_centred_on_its_placement(leg):  # noqa: F811
    base, info = read_osim(leg)
    model = osim_parameters(base, info, "bodies", "offsets")
    centred = centred_offset_priors(model, {"thigh1": np.array([70.0, -20.0, 0.0])})
    for p, q in zip(model.parameters, centred.parameters, strict=True):
        if p.target == "thigh1":
            shift = [70.0, -20.0, 0.0][p.axis]
            assert q.prior.mean == p.prior.mean + shift and q.prior.sd == p.prior.sd
            assert (q.prior.lower, q.prior.upper) == (p.prior.lower + shift, p.prior.upper + shift)
        else:
            assert q == p


def test_a_scale_factors_interval_is_never_below_zero(leg):  # noqa: F811
    """The 95 % interval of a scale factor is taken in log space, where its prior is normal."""
    trials = _trials(leg, {"pelvis": 1.0, "thigh": 1.1, "shank": 0.95})
    fit = fit_osim(leg, trials[1:], scale="bodies", markers="offsets")
    for p in fit.model.parameters:
        if p.kind == "scale":
            e = fit.result[p.name]
            lo, hi = e["ci95"]
            assert 0.0 < lo < e["map"] < hi
            assert np.log(hi) - np.log(e["map"]) == pytest.approx(np.log(e["map"]) - np.log(lo), rel=1e-9)


def test_a_factor_beyond_the_priors_central_99_percent_is_implausible(leg):  # noqa: F811
    from skelid.scaling import _implausible_bodies

    base, info = read_osim(leg)
    model = osim_parameters(base, info, "axes", "offsets")
    theta = model.theta_nominal.copy()
    k = model.parameter_names.index("scale_pelvis_y")
    theta[k] = 0.6  # |log 0.6| / 0.15 = 3.4 prior sd
    theta[model.parameter_names.index("scale_thigh_x")] = 1.4  # 2.2 prior sd: plausible
    assert _implausible_bodies(model, theta, ["pelvis", "thigh", "shank"]) == ["pelvis"]
    assert _implausible_bodies(model, theta, ["thigh"]) == []


def test_an_osim_result_folder_holds_poses_residuals_and_draws_with_scales_as_ratios(leg, tmp_path):  # noqa: F811
    from skelid.cli import main
    from skelid.io import write_trc
    from skelid.io.frames import to_dataframe, to_xarray

    static, move = _trials(leg, {"pelvis": 1.0, "thigh": 1.1, "shank": 1.0}, {"thigh1": (5.0, 0.0, -3.0)})
    write_trc(tmp_path / "static.trc", static)
    write_trc(tmp_path / "move.trc", move)
    out = tmp_path / "fit"
    assert main(["fit", str(leg), str(tmp_path / "static.trc"), str(tmp_path / "move.trc"), "--out", str(out),
                 "--quiet"]) == 0
    ds = to_xarray(out)
    n = static.positions.shape[0] + move.positions.shape[0]  # every frame of every trial
    assert ds["pose"].shape[0] == n and ds["residuals"].shape == (n, len(static.names))
    assert float(np.nanmax(ds["residuals"].values)) < 0.2  # mm: near noise-free data
    with np.load(out / "arrays.npz") as a:
        draws = a["marker/posterior.points"]
        assert draws.shape[0] == 400 and np.array_equal(np.unique(a["run/trial"]), [0, 1])
    df = to_dataframe(out)
    scales = df[df["name"].str.startswith("scale_")]
    assert set(scales["unit"]) == {"1"} and scales["crlb_sd"].notna().all()
    k = list(df["name"]).index("scale_thigh_y")
    assert draws[:, k].std() == pytest.approx(float(df["sd"].iloc[k]), rel=0.15)
    offsets = df[df["name"].str.startswith("offset_")]
    assert set(offsets["unit"]) == {"mm"}
    # the report answers first: the scaled model's section before the generic ones, every trial named
    import base64
    import re
    import struct

    assert main(["report", str(out)]) == 0
    html = (out / "report.html").read_text()
    assert html.index('id="opensim"') < html.index('id="summary"')
    first = html[html.index('id="opensim"'):html.index('id="summary"')]
    assert "static.trc, move.trc" in first and "Scale factors (ratios" in first and "thigh1" in first
    assert "skelid report: leg on static.trc + move.trc" in html
    for png in re.findall(r'src="data:image/png;base64,([^"]+)"', html):
        height = struct.unpack(">I", base64.b64decode(png)[20:24])[0]
        assert height <= 2000


def test_an_exactly_fitted_static_trial_does_not_hold_the_joint_fit_at_its_start(leg):  # noqa: F811
    """A static trial without noise: the markers placed on it fit it exactly, so it weighs far more than the
    walk (1 mm noise), and at those weights every step away from the start costs; the fit must still go on
    to the optimum (it stopped after one step with the walk's noise at 2.2 mm and the thigh 3 % long)."""
    from skelid.data import MarkerData

    truth = {"pelvis": 1.04, "thigh": 1.1, "shank": 0.95}
    static, move = _trials(leg, truth, {"thigh1": (25.0, -4.0, 3.0), "shank3": (-25.0, 2.0, 4.0),
                                        "pelvis0": (0.0, 25.0, 0.0)})
    walk = MarkerData(move.positions + np.random.default_rng(1).normal(0, 1.0, move.positions.shape), move.names,
                      move.rate, move.units, "walk")
    exact = MarkerData(np.repeat(static.positions[:1], len(static.positions), axis=0), static.names, static.rate,
                       static.units, "static")
    fit = fit_osim(leg, [exact, walk], scale="bodies", markers="offsets")
    assert fit.joint.converged and fit.joint.n_iter > 1
    assert fit.joint.sigma[1] < 1.2  # mm: the walk's noise is 1 mm
    got = {p.target: fit.theta[k] for k, p in enumerate(fit.model.parameters) if p.kind == "scale"}
    assert got["thigh"] == pytest.approx(truth["thigh"], abs=5e-3)


def test_the_checks_ratios_leave_out_the_placement_term_the_offsets_already_carry():
    """A static trial's 5 mm placement term is in its data covariance; the joint fit, whose offsets are
    parameters, takes only what the other checks added (here a serial-correlation factor of 2 on the
    second parameter)."""
    from types import SimpleNamespace

    from skelid.scaling import check_ratios

    names = ("scale_a", "scale_b")
    plain = np.diag([1.0, 1.0])
    data = np.diag([1.0 + 9.0, 4.0 + 16.0])  # checks: 1 and 4; placement: 9 and 16
    placement = {"parameters": {"scale_a": {"sd_added": 3.0}, "scale_b": {"sd_added": 4.0}}}
    est = SimpleNamespace(cov_data_=data, cov_plain_=plain, placement_=placement,
                          model=SimpleNamespace(parameter_names=names))
    np.testing.assert_allclose(check_ratios(est, SimpleNamespace(n_params=2)), [[1.0, 2.0]])
    est.placement_ = {"parameters": {}}  # no placement term: the whole ratio
    np.testing.assert_allclose(check_ratios(est, SimpleNamespace(n_params=2)), [np.sqrt([10.0, 20.0])])
    several = SimpleNamespace(trials_=[est, est])
    assert check_ratios(several, SimpleNamespace(n_params=2)).shape == (2, 2)


def test_a_trials_checks_widen_the_joint_interval_by_that_trials_weight_in_the_joint_fit():
    """Two trials, the first with 100 times the information: its checks' ratio of 3 widens the joint sd
    almost threefold, the second's hardly at all, whatever the trials' own scale fits said."""
    from types import SimpleNamespace

    from skelid.scaling import deflated_widening

    info = (np.diag([100.0, 100.0, 50.0]), np.diag([1.0, 1.0, 1.0]))
    hp = np.full(3, 1e-12)
    jo = SimpleNamespace(info_trials=info, cov=np.linalg.inv(sum(info) + np.diag(hp)))
    first = deflated_widening(jo, hp, np.array([[3.0, 1.0], [1.0, 1.0]]))
    np.testing.assert_allclose(first, [np.sqrt(101.0 / (100.0 / 9.0 + 1.0)), 1.0], rtol=1e-6)
    second = deflated_widening(jo, hp, np.array([[1.0, 1.0], [3.0, 1.0]]))
    np.testing.assert_allclose(second, [np.sqrt(101.0 / (100.0 + 1.0 / 9.0)), 1.0], rtol=1e-6)
    # correlated information: a scalar per trial never narrows any sd
    A = np.array([[4.0, 3.9, 0.0], [3.9, 4.0, 0.0], [0.0, 0.0, 1.0]])
    jo = SimpleNamespace(info_trials=(A, np.eye(3)), cov=np.linalg.inv(A + np.eye(3) + np.diag(hp)))
    assert np.all(deflated_widening(jo, hp, np.array([[5.0, 1.0], [1.0, 2.0]])) >= 1.0)
    one = deflated_widening(jo, hp, np.array([[2.0, 2.0]]))  # one recording: its ratio for every trial
    np.testing.assert_allclose(one, [2.0, 2.0], rtol=1e-6)


def _linear_trials(rng, tau, K=3, P=12, n_off=8, n=60):
    """A linear model of a joint fit: K trials sharing P parameters, the last n_off offsets, each trial's
    offsets moved by N(0, tau^2); unit noise. Returns the informations, scores, posterior covariance, the
    offsets' mask, the estimate and the truth."""
    off = np.zeros(P, bool)
    off[P - n_off:] = True
    lam = np.full(P, 1e-2)
    A = [rng.normal(size=(n, P)) for _ in range(K)]
    truth = rng.normal(size=P)
    ys = []
    for a in A:
        u = np.zeros(P)
        u[off] = rng.normal(0.0, tau, n_off)
        ys.append(a @ (truth + u) + rng.normal(size=n))
    info = [a.T @ a for a in A]
    H = np.linalg.inv(sum(info) + np.diag(lam))
    est = H @ sum(a.T @ y for a, y in zip(A, ys, strict=True))
    scores = [a.T @ (y - a @ est) for a, y in zip(A, ys, strict=True)]
    return info, scores, H, off, est, truth


def test_the_trials_placement_test_holds_its_level_and_the_spread_it_adds_covers():
    from skelid.estimators.checks.trial_placement import trial_placement

    rng = np.random.default_rng(7)
    p = [trial_placement(*_linear_trials(rng, 0.0)[:4]).p_value for _ in range(400)]
    assert 0.002 <= np.mean(np.array(p) < 0.05) <= 0.1  # about 5 %
    z, taus = [], []
    for _ in range(200):
        info, scores, H, off, est, truth = _linear_trials(rng, 0.5)
        tp = trial_placement(info, scores, H, off)
        taus.append(tp.tau)
        z.append((est - truth) / np.sqrt(np.diag(H + tp.cov)))
        assert tp.present or tp.p_value >= 0.01
    z = np.concatenate(z)
    assert abs(np.mean(taus) - 0.5) < 0.05
    assert 0.92 <= np.mean(np.abs(z) <= 1.96) <= 0.975  # the plain posterior alone covers far less
    info, scores, H, off, est, truth = _linear_trials(rng, 0.5)
    naive = (est - truth) / np.sqrt(np.diag(H))
    assert np.sqrt(np.mean(naive**2)) > 1.5
    one = trial_placement(info[:1], scores[:1], H, off)  # one trial: its offsets take up its placement
    assert not one.present and not one.cov.any()


def test_the_joint_result_drops_the_scale_fits_warnings_of_terms_it_carries_itself():
    from types import SimpleNamespace

    from skelid.result import Warning
    from skelid.scaling import _without_carried_warnings

    w = [Warning("placement-informed", "static: placed", ()), Warning("misfit", "knee misfit", ()),
         Warning("trials-disagree", "the trials disagree", ()), Warning("on-bound", "x on a bound", ()),
         Warning("poorly-identified", "x poorly identified", ())]
    res = {"warnings": ["static: placed", "knee misfit", "the trials disagree", "x on a bound",
                        "x poorly identified"]}
    out = _without_carried_warnings(res, SimpleNamespace(warnings_=tuple(w)))
    assert out["warnings"] == ["knee misfit"] and len(res["warnings"]) == 5


#: the test leg with an unmarked talus between the shank and a marked foot (the ankle and subtalar joints)
FOOT_JOINTS = """<PinJoint name="ankle"><socket_parent_frame>shank_offset</socket_parent_frame>
<socket_child_frame>/bodyset/talus</socket_child_frame><coordinates><Coordinate name="a"/></coordinates>
<frames><PhysicalOffsetFrame name="shank_offset"><socket_parent>/bodyset/shank</socket_parent>
<translation>0 -0.42 0</translation><orientation>0 0 0</orientation></PhysicalOffsetFrame></frames></PinJoint>
<PinJoint name="subtalar"><socket_parent_frame>talus_offset</socket_parent_frame>
<socket_child_frame>/bodyset/foot</socket_child_frame><coordinates><Coordinate name="s"/></coordinates>
<frames><PhysicalOffsetFrame name="talus_offset"><socket_parent>/bodyset/talus</socket_parent>
<translation>-0.05 -0.04 0.01</translation><orientation>-1.2 0.4 0</orientation></PhysicalOffsetFrame>
</frames></PinJoint>
</objects></JointSet>"""


def test_the_checks_test_the_joint_fits_own_geometry_with_an_unmarked_body_at_its_fitted_size(tmp_path):
    """A talus scaled to 0.8 that carries no marker, data of the exact model with 1 mm noise: the joint fit
    scales the talus (under its prior), and its checks, rerun on a scale fit with every marker where the joint
    fit put it, hold the talus at that size too. At the generic size they saw misfit at the hip, knee and
    subtalar joints and widened the thigh's and shank's sd 6.6 and 7.3 times."""
    from skelid.data import MarkerData
    from skelid.model.kinematics import marker_positions
    from tests.helpers import leg_walk_poses
    from tests.test_scaling import MARKERS, MODEL, marker_xml

    xml = MODEL.replace('<Body name="shank"/>', '<Body name="shank"/><Body name="talus"/><Body name="foot"/>')
    feet = dict(MARKERS, foot=[(0.15, -0.02, 0.03), (0.05, -0.03, -0.04), (-0.05, 0.0, 0.02), (0.1, 0.03, 0.0)])
    path = tmp_path / "leg_foot.osim"
    path.write_text(xml.replace("</objects></JointSet>", FOOT_JOINTS).format(markers=marker_xml(feet)))
    base, info = read_osim(path)
    model = osim_parameters(base, info, "bodies", "offsets", holders=True)
    truth = {"pelvis": 1.0, "thigh": 1.1, "shank": 0.95, "talus": 0.8, "foot": 1.05}
    theta = np.array([truth[p.target] if p.kind == "scale" else 0.0 for p in model.parameters])
    q = leg_walk_poses(120, model.n_pose)
    t = np.arange(120) / 60.0
    q[:, 10], q[:, 11] = 0.4 * np.sin(2 * np.pi * 1.7 * t + 0.5), 0.3 * np.sin(2 * np.pi * 0.8 * t + 1.5)
    x = marker_positions(model, theta, q) + np.random.default_rng(0).normal(0, 1.0, (len(q), len(model.markers), 3))
    fit = fit_osim(path, [MarkerData(x, model.marker_names, 60.0, "mm", "sim")], scale="bodies")
    assert "scale_talus" in fit.model.parameter_names
    assert not fit.result["marker_jackknife"]["folded"]
    assert not any("misfit" in w for w in fit.warnings)
    for body in ("thigh", "shank"):
        e = fit.result[f"scale_{body}"]
        assert e["widened_by_checks"] < 1.05
        assert abs(e["mean"] - truth[body]) < 3 * e["sd"]


def _noisy_walk(leg, marker_sd, n_frames=300, seed=3):  # noqa: F811
    """The leg's walk of :func:`tests.test_scaling._trials` with each marker's own noise sd (mm)."""
    from skelid.data import MarkerData
    from skelid.model.kinematics import marker_positions
    from tests.helpers import leg_walk_poses

    base, info = read_osim(leg)
    model = osim_parameters(base, info, "bodies", "offsets")
    truth = model.theta_nominal.copy()
    q = leg_walk_poses(n_frames, model.n_pose)
    rng = np.random.default_rng(seed)
    sd = np.resize(np.asarray(marker_sd, float), len(model.markers))
    x = marker_positions(model, truth, q) + rng.normal(0, 1, (n_frames, len(model.markers), 3)) * sd[:, None]
    return model, MarkerData(x, model.marker_names, 60.0, "mm", "sim"), sd


def test_each_markers_noise_level_is_read_from_the_residuals_and_carried_into_the_interval(leg):  # noqa: F811
    """Markers of 0.5 and 4 mm fitted with one noise level: each marker's level is recovered from its
    residuals (the pose's share of each marker's residual taken out; a quiet marker's level is the
    difference of its residual and what the pose carries over from its noisy neighbours, so it is known
    less well), and the interval is the sandwich with those levels, which the Laplace interval of one
    level is not."""
    from skelid.estimators.fit.likelihood import projected_theta_jacobian
    from skelid.estimators.fit.pose import workspace
    from skelid.scaling import _posed_terms, _prior_terms

    model, walk, sd = _noisy_walk(leg, [0.5, 4.0])
    jo = _joint_refinement(model, model.theta_nominal.copy(), [walk], None, 0)
    np.testing.assert_allclose(jo.marker_sd[0][sd > 1], 4.0, rtol=0.06)
    assert np.all(jo.marker_sd[0][sd < 1] < 1.0)
    # the sandwich with the true levels, at the fit
    _, r, Jq, Jt = _posed_terms(model, jo.theta, walk.positions, jo.poses[0], workspace(model))
    Kp = projected_theta_jacobian(Jq, Jt)
    J = np.einsum("tkp,k,tkq->pq", Kp, np.repeat(sd**2, 3), Kp) / jo.sigma[0] ** 4
    want = jo.cov @ (J + np.diag(_prior_terms(model, jo.theta)[1])) @ jo.cov
    scales = [k for k, p in enumerate(model.parameters) if p.kind == "scale"]
    got_sd, want_sd, laplace_sd = (np.sqrt(np.diag(c))[scales] for c in (jo.cov_noise, want, jo.cov))
    np.testing.assert_allclose(got_sd, want_sd, rtol=0.1)
    assert np.max(np.abs(laplace_sd / want_sd - 1.0)) > 0.1  # one level is wrong here


def test_a_trial_evaluated_for_its_cost_and_completed_gives_the_full_terms(leg):  # noqa: F811
    """The joint fit's backtracking evaluates its trial steps for their cost only and completes the one
    it takes: the poses, sums and RSS are those of the full evaluation."""
    from skelid.estimators.fit.joint import weighted_terms
    from skelid.estimators.fit.pose import workspace
    from skelid.scaling import JOINT_POSE_ITER, _summed_terms, _trial_cost, _trial_terms

    model, walk, _ = _noisy_walk(leg, [2.0], n_frames=60)
    ws = workspace(model)
    theta = model.theta_nominal * 1.02
    q0 = _joint_refinement(model, model.theta_nominal.copy(), [walk], None, 0).poses[0]
    full = _trial_terms(model, theta, walk.positions, q0, ws, None, JOINT_POSE_ITER)
    cheap = _trial_cost(model, theta, walk.positions, q0, ws, None, JOINT_POSE_ITER)
    assert cheap[1] is None and cheap[2] is None
    np.testing.assert_allclose(cheap[0], full[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(cheap[3], full[3], rtol=1e-10)
    done = _summed_terms(model.dim, cheap[0], *weighted_terms(model, theta, cheap[0], walk.positions, None, ws))
    for a, b in zip(done, full, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)
    assert full[3] > 0 and np.abs(full[2]).max() > 0


def test_with_one_noise_level_the_sandwich_is_the_laplace_interval(leg):  # noqa: F811
    model, walk, _ = _noisy_walk(leg, [2.0])
    jo = _joint_refinement(model, model.theta_nominal.copy(), [walk], None, 0)
    np.testing.assert_allclose(np.sqrt(np.diag(jo.cov_noise)), np.sqrt(np.diag(jo.cov)), rtol=0.1)
    np.testing.assert_allclose(jo.marker_sd[0], 2.0, rtol=0.1)


def test_data_simulated_from_the_fit_spread_as_its_interval_says_where_the_fit_is_linear(leg):  # noqa: F811
    """Small i.i.d. noise: the simulated data's steps from the MAP spread as the data's part of the
    interval (the prior's part, C Lambda C, left out: with it the ratio was 0.7-0.8), show no bias
    and widen nothing as a class."""
    from skelid.scaling import bootstrap_check

    model, walk, _ = _noisy_walk(leg, [0.5])
    jo = _joint_refinement(model, model.theta_nominal.copy(), [walk], None, 0)
    bias, widen, entry, bias_var = bootstrap_check(model, jo, [walk.positions], jo.cov_noise, seed=1)
    sd = np.sqrt(np.diag(jo.cov_noise))
    # the linear fit's steps on the same noise take out nearly all of the mean's noise (a plain mean of
    # 12 steps has a variance of sd^2 / 12)
    assert np.median(bias_var / (sd**2 / 12)) < 0.1
    assert np.all(np.abs(bias) < 1.0 * sd) and abs(entry["largest_bias_sd"]) < 1.0
    for kind, r in entry["pooled_sd_ratio"].items():
        assert 0.8 < r < 1.25, (kind, r)
    # the steps' variance over the linear fit's on the same noise: no parameter widened by the chance of 12 sets
    assert widen.max() < 1.1, (widen.max(), entry["largest_widening_parameter"])


# ----------------------------------------------------------------------------- linked axis factors
def test_linked_axis_factors_have_a_correlated_log_normal_prior_whose_gradient_is_its_costs(leg):  # noqa: F811
    from skelid.io.osim import AXIS_CORRELATION
    from skelid.scaling import _prior_cost, _prior_terms, prior_sd

    base, info = read_osim(leg)
    linked = osim_parameters(base, info, "linked", "offsets")
    axes = osim_parameters(base, info, "axes", "offsets")
    assert linked.parameter_names == axes.parameter_names
    groups = {p.prior.group for p in linked.parameters if p.kind == "scale"}
    assert groups == {"scale_pelvis", "scale_thigh", "scale_shank"}
    rng = np.random.default_rng(4)
    theta = np.where([p.kind == "scale" for p in linked.parameters],
                     np.exp(rng.normal(0.0, 0.1, linked.n_params)), rng.normal(0.0, 5.0, linked.n_params))
    g, H = _prior_terms(linked, theta)
    fd = np.array([(_prior_cost(linked, theta + e) - _prior_cost(linked, theta - e)) / 2e-7
                   for e in np.eye(linked.n_params) * 1e-7])
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-6)
    # the curvature of one body's block: diag(1/theta) Sigma^-1 diag(1/theta)
    k = [i for i, p in enumerate(linked.parameters) if p.prior.group == "scale_thigh"]
    sd = linked.parameters[k[0]].prior.sd
    sigma = sd**2 * ((1 - AXIS_CORRELATION) * np.eye(3) + AXIS_CORRELATION * np.ones((3, 3)))
    np.testing.assert_allclose(H[np.ix_(k, k)], np.linalg.inv(sigma) / np.outer(theta[k], theta[k]), rtol=1e-10)
    # each factor's marginal prior is the one factor per axis's; with no correlation, the same terms as 'axes'
    np.testing.assert_allclose(prior_sd(_prior_terms(linked, np.where(np.isin(np.arange(theta.size), k), 1.0,
                                                                      theta))[1])[k], sd, rtol=1e-10)
    free = replace(linked, parameters=tuple(replace(p, prior=replace(p.prior, correlation=0.0))
                                            for p in linked.parameters))
    g0, H0 = _prior_terms(free, theta)
    ga, ha = _prior_terms(axes, theta)
    np.testing.assert_allclose(g0, ga, rtol=1e-12)
    np.testing.assert_allclose(H0, np.diag(ha), rtol=1e-12)


def test_a_prior_precision_matrix_gives_the_posterior_of_its_vector_where_it_is_diagonal():
    from skelid.scaling import _posterior_solver

    rng = np.random.default_rng(5)
    A = rng.normal(size=(20, 6))
    info = A.T @ A
    info[:, 5] = info[5, :] = 0.0  # one direction the data leave to the prior
    h = rng.uniform(0.5, 3.0, 6)
    sv, cv, ev, shv = _posterior_solver(info, h)
    sm, cm, em, shm = _posterior_solver(info, np.diag(h))
    b = rng.normal(size=6)
    np.testing.assert_allclose(cm, cv, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(sm(b), sv(b), rtol=1e-10)
    assert em == pytest.approx(ev, rel=1e-10)
    np.testing.assert_allclose(shm, shv, atol=1e-10)
    # a correlated prior: the covariance is (info + Lambda)^-1
    L = rng.normal(size=(6, 6))
    lam = L @ L.T + 6 * np.eye(6)
    _, c2, _, _ = _posterior_solver(info, lam)
    np.testing.assert_allclose(c2, np.linalg.inv(info + lam), rtol=1e-9)


def test_linked_factors_stay_near_the_bodys_common_factor_where_the_data_say_nothing_of_an_axis(leg):  # noqa: F811
    """The leg's thigh seen in a plane: its out-of-plane factor is left to the prior. Per axis the prior pulls
    it towards its median 1 (1.15 here); linked, it stays nearer the thigh's other factors (1.2; 1.19 here)."""
    truth = {"pelvis": 1.0, "thigh": 1.2, "shank": 1.0}
    trials = _trials(leg, truth)
    fits = {m: fit_osim(leg, trials, scale=m) for m in ("axes", "linked")}
    th = {m: {p.name: v for p, v in zip(f.model.parameters, f.theta, strict=True)} for m, f in fits.items()}
    lin = [th["linked"][f"scale_thigh_{a}"] for a in "xyz"]
    ax = [th["axes"][f"scale_thigh_{a}"] for a in "xyz"]
    assert np.ptp(np.log(lin)) < np.ptp(np.log(ax))


def _sliding_walk(path, seed):
    """The leg walking with markers that slide on their bodies linearly with the joint angles (15 mm per
    radian shared by a body's markers, 5 mm each marker's own, 1 mm white noise): the model, its true
    geometry, the slopes and the markers."""
    from skelid.estimators.checks.pose_artefact import artefact_coordinates
    from skelid.estimators.fit.pose import workspace
    from skelid.model.kinematics import forward_kinematics, marker_positions
    from tests.helpers import leg_walk_poses

    base, info = read_osim(path)
    model = osim_parameters(base, info, "bodies", "offsets")
    truth = model.theta_nominal.copy()
    q = leg_walk_poses(400, model.n_pose)
    rng = np.random.default_rng(seed)
    coords = artefact_coordinates(model)
    mseg = np.asarray(model.marker_segment)
    V = rng.normal(0.0, 15.0, (len(model.segments), 3, coords.size))[mseg]
    V = V + rng.normal(0.0, 5.0, V.shape)
    R = forward_kinematics(model, truth, q, workspace(model)).R_world_seg[:, mseg]
    slide = np.einsum("tmja,mac,tc->tmj", R, V, q[:, coords])
    x = marker_positions(model, truth, q) + slide + rng.normal(0.0, 1.0, slide.shape)
    return model, truth, V, q[:, coords], x


def test_the_slide_is_estimated_at_the_joint_optimum_not_one_step_from_the_fit_that_ignores_it(leg, monkeypatch):  # noqa: F811
    """One step from the fit without the slide leaves the poses holding the slide's rigid part: the geometry
    3-5 mm rms from the truth and 1.0-1.7 times further than its sd says. Iterated, with the poses fitted
    to the markers less the slide, the estimate reaches the joint optimum."""
    import skelid.scaling as scaling
    from skelid.data import MarkerData

    model, truth, _, _, x = _sliding_walk(leg, 12)
    errors, seen = {}, {}
    check = scaling.bootstrap_check

    def spy(model, jo, ys, cov, *args, **kwargs):  # what the bias check of the iterated fit starts from
        seen.update(model=model, jo=jo, ys=ys)
        out = check(model, jo, ys, cov, *args, **kwargs)
        seen.update(boot=out[1])
        return out

    monkeypatch.setattr(scaling, "bootstrap_check", spy)
    for steps in (1, scaling.SLIDE_STEPS):
        monkeypatch.setattr(scaling, "SLIDE_STEPS", steps)
        fit = fit_osim(leg, [MarkerData(x, model.marker_names, 60.0, "mm", "walk")], scale="bodies")
        assert fit.result["artefact"]["steps"] == (1 if steps == 1 else pytest.approx(8, abs=4))
        assert (steps == 1) != fit.result["artefact"]["settled"]
        assert (steps == 1) == any("did not settle" in w for w in fit.warnings)
        names = fit.model.parameter_names  # a body the data contradict gains a factor per axis (truth 1)
        true = dict(zip(model.parameter_names, truth, strict=True))
        sd = np.array([fit.result[n]["sd"] for n in names])
        errors[steps] = (fit.theta - np.array([true.get(n, 1.0) for n in names]), sd)
        if steps == 1:
            one_step_theta = np.array(fit.theta)  # where the one step leaves the geometry
    one, done = errors[1][0], errors[scaling.SLIDE_STEPS][0]
    assert np.sqrt(np.mean(done**2)) < 0.5 * np.sqrt(np.mean(one**2))
    assert np.sqrt(np.mean((done / errors[scaling.SLIDE_STEPS][1]) ** 2)) < 1.0
    _check_after_the_slide(scaling, fit, seen)
    # a step that does not settle (here: none may) is not taken, and the warning says so
    monkeypatch.setattr(scaling, "SLIDE_CONTRACTION", 0.0)
    held = fit_osim(leg, [MarkerData(x, model.marker_names, 60.0, "mm", "walk")], scale="bodies")
    assert held.result["artefact"]["steps"] == 1 and held.result["artefact"]["settled"] is False
    assert any("did not settle and was kept after 1 step" in w for w in held.warnings)
    np.testing.assert_allclose(held.theta, one_step_theta, rtol=1e-12, atol=1e-12)


def _check_after_the_slide(scaling, fit, seen):
    """The bias check of a fit with a slide simulates the white noise the slide leaves (not the slide taken
    for noise), and its steps use the information at the slide's geometry and poses (with the information
    of the fit before the slide, a pelvis scale's "bias" reached 157 sd on an OpenSim walk); the result and
    the report give each body's slide (the leg's bodies share slopes of sd 15 mm per radian)."""
    from skelid.estimators.fit.pose import workspace

    jo, m = seen["jo"], seen["model"]
    white = fit.result["artefact"]["sigma_white"][0]
    np.testing.assert_allclose(jo.sigma, white)
    assert white < 2.0  # the 1 mm white noise, not the slide's 15-20 mm per radian
    fresh = scaling._trial_terms(m, jo.theta, seen["ys"][0], jo.poses[0], workspace(m), None, scaling.POSE_ITER)
    np.testing.assert_allclose(jo.info_trials[0], fresh[1] / white**2, rtol=1e-6, atol=1e-9 * np.abs(fresh[1]).max())
    assert abs(fit.result["bootstrap"]["largest_bias_sd"]) < 3.0
    # the scale fit's checks, which take the slide for misfit, widen nothing the slide's covariance holds
    # (they doubled the thigh and shank scales' sd on OpenSim-generated walks, against their actual spread)
    widened = np.array([fit.result[n]["widened_by_checks"] for n in m.parameter_names])
    assert np.all(widened <= np.maximum(seen["boot"], 1.0) + 1e-12)
    by_body = fit.result["artefact"]["by_body"]
    assert set(by_body) == {m.segments[s].name for s in set(m.marker_segment)}
    assert all(5.0 < b["slope_sd_shared"] < 45.0 and b["rms"] > 0.0 for b in by_body.values())
    text = scaling.report_markdown(fit)  # the report lists the bodies, the one that slides most first
    first = max(by_body, key=lambda b: by_body[b]["rms"])
    rows = text.split("each body's markers")[1].split("\n")
    assert f"| {first} | {by_body[first]['slope_sd_shared']:.1f} |" in rows[4]


def test_the_slide_displaced_at_the_poses_is_each_markers_slopes_turned_with_its_body(leg):  # noqa: F811
    from skelid.estimators.checks.pose_artefact import SlideTerms, artefact_coordinates, slide_displacement
    from skelid.estimators.fit.pose import workspace
    from skelid.model.kinematics import forward_kinematics, marker_positions

    model, truth, V, dq, x = _sliding_walk(leg, 3)
    q = np.zeros((len(dq), model.n_pose))
    coords = artefact_coordinates(model)
    rng = np.random.default_rng(4)
    basis = np.linalg.qr(rng.normal(size=(coords.size, coords.size)))[0]  # any orthonormal directions
    ref = rng.normal(0.0, 0.1, coords.size)
    q[:, coords] = dq + ref
    sl = SlideTerms(A=None, b=None, G=None, bodies=(), tau_s2=1.0, tau_o2=1.0, rss=0.0, coords=coords,
                    reference=ref, basis=basis)
    got = slide_displacement(model, truth, [q[:150], q[150:]], sl, V @ basis)  # the slopes in those directions
    mseg = np.asarray(model.marker_segment)
    R = forward_kinematics(model, truth, q, workspace(model)).R_world_seg[:, mseg]
    want = np.einsum("tmja,mac,tc->tmj", R, V, dq)
    np.testing.assert_allclose(np.concatenate(got), want, atol=1e-9)
    assert np.abs(want).max() > 1.0 and marker_positions(model, truth, q).shape == want.shape


def test_a_slide_that_follows_the_pose_is_estimated_with_the_geometry_and_named(leg):  # noqa: F811
    """Markers that slide on their bodies linearly with the joint angles (15 mm per radian shared by a
    body's markers, 5 mm each marker's own, 1 mm white noise): the joint fit finds the slide, estimates
    its slopes with the geometry (their sizes near the truth's: three bodies tell the shared one roughly),
    and names it; its white noise is the 1 mm left, not the fit's noise level (6 mm here)."""
    from skelid.data import MarkerData

    model, truth, V, dq, x = _sliding_walk(leg, 11)
    fit = fit_osim(leg, [MarkerData(x, model.marker_names, 60.0, "mm", "walk")], scale="bodies")
    art = fit.result["artefact"]
    assert art["present"] and art["estimated_with_geometry"]
    assert 0.8 < art["sigma_white"][0] < 1.3 and art["sigma_white"][0] < 0.5 * fit.result["sigma"]["value"]
    assert 7.5 < art["slope_sd_shared"] < 30.0 and art["slope_sd_own"] < art["slope_sd_shared"]
    assert any("its slopes estimated with the geometry" in w for w in fit.warnings)
    # where each marker sits on average over the trial (the slide at the mean pose, from its offset's place):
    # what the written model holds, near the truth's (rms about 10 mm here)
    from skelid.io.osim import marker_locations
    from skelid.scaling import scaling_table

    got = np.array([art["mean_place_mm"][n] for n in model.marker_names])
    at_mean = np.einsum("mac,c->ma", V, dq.mean(axis=0))
    assert np.corrcoef(got.ravel(), at_mean.ravel())[0, 1] > 0.8
    assert np.sqrt(np.mean((got - at_mean) ** 2)) < 0.6 * np.sqrt(np.mean(at_mean**2))
    written = scaling_table(fit)["marker_locations_m"]
    at_zero = marker_locations(fit.model, fit.info, fit.theta)
    for i, n in enumerate(model.marker_names):
        np.testing.assert_allclose(np.asarray(written[n]) - at_zero[n], got[i] / 1000.0, atol=1e-12)


def test_joint_angles_hold_a_sliding_marker_where_the_written_model_does(leg, tmp_path):  # noqa: F811
    """Where the markers slide, skelid's angles and the written .osim put each marker at its mean place over
    the trials, not at its zero-pose place (which the walk's markers are far from)."""
    from dataclasses import replace as dc_replace

    from skelid.angles import fitted_geometry, joint_angles, read_geometry, write_geometry
    from skelid.data import MarkerData
    from skelid.io.osim import marker_locations
    from skelid.scaling import mean_places, scaling_table

    model, _, _, _, x = _sliding_walk(leg, 11)
    walk = MarkerData(x, model.marker_names, 60.0, "mm", "walk")
    fit = fit_osim(leg, [walk], scale="bodies")
    geom = fitted_geometry(fit)
    assert geom.places == "mean over the trials" and mean_places(fit)
    held = marker_locations(geom.model, fit.info, geom.theta)
    written = scaling_table(fit)["marker_locations_m"]
    for n in model.marker_names:
        np.testing.assert_allclose(held[n], written[n], atol=1e-12)
    zero = dc_replace(geom, model=fit.model, theta=np.asarray(fit.theta, float), places="zero pose")
    at_mean, at_zero = joint_angles(geom, walk, n_draws=0), joint_angles(zero, walk, n_draws=0)
    assert at_mean.sigma < 0.8 * at_zero.sigma  # the markers' residual after the pose fit
    write_geometry(geom, tmp_path)
    back = read_geometry(tmp_path)
    assert back.places == "mean over the trials"
    np.testing.assert_allclose(back.theta, geom.theta)


def test_the_poses_of_the_result_are_fitted_at_the_geometry_it_reports(leg):  # noqa: F811
    """The bias taken off moves the geometry after the joint fit; the poses are fitted again there, so the
    residuals the written trials and the models' average use stay at the noise level (0.01 mm here: at the
    joint fit's own poses they were 100 times larger, and the model average weighed those)."""
    from skelid.estimators.fit.pose import fit_pose, workspace
    from skelid.model.kinematics import marker_positions

    model, walk, _ = _noisy_walk(leg, [0.01], n_frames=120)
    fit = fit_osim(leg, [walk])
    jo, m = fit.joint, fit.model
    assert np.abs(fit.result["bootstrap"]["largest_bias_sd"]) > 0.0
    y = walk.positions[:, [walk.names.index(n) for n in m.marker_names]]
    rms = np.sqrt(np.nanmean(np.sum((y - marker_positions(m, jo.theta, jo.poses[0])) ** 2, axis=-1)) / 3)
    assert rms < 1.5 * jo.sigma[0]
    again = fit_pose(m, jo.theta, y, jo.poses[0], n_iter=30, ws=workspace(m))[0]
    np.testing.assert_allclose(again, jo.poses[0], atol=1e-6)
