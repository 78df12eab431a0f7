"""The pose fit's numpy and compiled paths against a plain reference, and the grid filter that uses them."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from skelid import _numba
from skelid.estimators.fit import _lm_kernel
from skelid.estimators.fit.likelihood import frame_terms, log_det_pose_information
from skelid.estimators.fit.pose import FramePoseFitter, fit_pose, fit_pose_logdet
from skelid.estimators.online.grid import MarkerGridFilter
from skelid.model import load_model, model_from_dict
from skelid.model.kinematics import forward_kinematics, pose_jacobian
from skelid.simulate import builtin_model, simulate
from tests.helpers import custom_leg, tree_3d, tree_3d_functional

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
needs_numba = pytest.mark.skipif(not _lm_kernel.AVAILABLE, reason="the compiled kernel is turned off (SKELID_NUMBA=0)")
MODELS = {"case-a": lambda: builtin_model("case-a"), "case-b": lambda: builtin_model("case-b"),
          "tree3d": tree_3d, "tree3d_functional": tree_3d_functional,
          "lower_limb": lambda: load_model(EXAMPLES / "lower_limb.toml"), "custom_leg": custom_leg}
PATHS = ["numpy", pytest.param("compiled", marks=needs_numba)]


def _use(path, monkeypatch):
    if path == "numpy":
        monkeypatch.setattr(_lm_kernel, "AVAILABLE", False)


def _reference_fit_pose(model, theta, y, q0, n_iter=30, tol=1e-10, damping=1e-3):
    """Levenberg-Marquardt written plainly on the public kinematics (the iteration the fast paths implement)."""
    y = np.asarray(y, dtype=float)
    mask = np.isfinite(y).all(axis=-1)
    y0 = np.where(mask[..., None], y, 0.0)
    batch = np.broadcast_shapes(np.shape(q0)[:-1], y.shape[:-2], np.shape(theta)[:-1])
    q = np.broadcast_to(np.asarray(q0, float), batch + (model.n_pose,)).copy()

    def residual(q_):
        r_ = (y0 - forward_kinematics(model, theta, q_).markers) * mask[..., None]
        return r_, np.sum(r_**2, axis=(-2, -1))

    r, cost = residual(q)
    lam = np.full(batch, float(damping))
    eye = np.eye(model.n_pose)
    for _ in range(n_iter):
        J = (pose_jacobian(model, forward_kinematics(model, theta, q)) * mask[..., None, None])
        J = J.reshape(batch + (-1, model.n_pose))
        JtJ = np.einsum("...ki,...kj->...ij", J, J)
        Jtr = np.einsum("...ki,...k->...i", J, r.reshape(batch + (-1,)))
        dg = np.einsum("...ii->...i", JtJ)
        A = JtJ + lam[..., None, None] * dg[..., None, :] * eye \
            + (1e-9 * np.maximum(dg.mean(axis=-1), 1e-300))[..., None, None] * eye
        bad = ~np.isfinite(A).all(axis=(-2, -1)) | ~np.isfinite(Jtr).all(axis=-1)
        A = np.where(bad[..., None, None], eye, A)
        Jtr = np.where(bad[..., None], 0.0, Jtr)
        step = np.linalg.solve(A, Jtr[..., None])[..., 0]
        q_new = q + np.where(np.isfinite(step), step, 0.0)
        r_new, cost_new = residual(q_new)
        ok = cost_new <= cost
        q = np.where(ok[..., None], q_new, q)
        r = np.where(ok[..., None, None], r_new, r)
        improve = np.where(ok, cost - cost_new, 0.0)
        cost = np.where(ok, cost_new, cost)
        lam = np.where(ok, lam * 0.3, lam * 10.0)
        if np.all(improve <= tol * (cost + 1e-30)) and np.all(ok | (lam > 1e8)):
            break
    return q, cost


def _problem(name, n=12):
    model = MODELS[name]()
    trial = simulate(model, sigma=2.0, n_frames=20, rng=np.random.default_rng(5))
    rng = np.random.default_rng(6)
    scale = np.array([2.0 if p.kind == "axis_direction" else 0.05 if p.kind == "scale" else 5.0
                      for p in model.parameters])
    theta = model.theta_nominal + rng.normal(0, 1, size=(n, model.n_params)) * scale
    y = trial.data.positions[..., : model.dim]
    q0 = trial.pose[7] + rng.normal(0, 0.05, size=(n, model.n_pose))
    return model, theta, y[7], q0


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("name", MODELS)
def test_fit_equals_the_reference_iteration(name, path, monkeypatch):
    model, theta, y, q0 = _problem(name)
    if name != "case-a":  # case A needs all three markers to fix the pose
        y = y.copy()
        y[1] = np.nan  # a missing marker
    q_ref, rss_ref = _reference_fit_pose(model, theta, y, q0)
    _use(path, monkeypatch)
    q, rss, logdet = fit_pose_logdet(model, theta, y, q0)
    np.testing.assert_allclose(rss, rss_ref, rtol=1e-9)
    # poses agree to what the stopping rule fixes them: the reference itself moves them by
    # about 1e-7 when its inputs change by one rounding error
    np.testing.assert_allclose(q, q_ref, atol=1e-5)
    _, Jq, _ = frame_terms(model, theta, q, y)
    np.testing.assert_allclose(logdet, log_det_pose_information(Jq), rtol=1e-10)  # at the fitted pose
    _, Jq, _ = frame_terms(model, theta, q_ref, y)
    np.testing.assert_allclose(logdet, log_det_pose_information(Jq), rtol=0, atol=1e-6)
    q2, rss2 = fit_pose(model, theta, y, q0)
    np.testing.assert_array_equal(rss2, rss)
    np.testing.assert_array_equal(q2, q)


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("name", ["case-b", "lower_limb", "custom_leg"])
def test_many_frames_with_damping_and_a_lost_element(name, path, monkeypatch):
    """Batch over frames with one theta; an element starting from NaN stays put without disturbing the rest."""
    model = MODELS[name]()
    trial = simulate(model, sigma=1.0, n_frames=15, rng=np.random.default_rng(3))
    y = trial.data.positions[..., : model.dim]
    q0 = trial.pose + 0.05
    q0[4] = np.nan
    q_ref, rss_ref = _reference_fit_pose(model, model.theta_nominal, y, q0, n_iter=6, damping=1e-2)
    _use(path, monkeypatch)
    q, rss = fit_pose(model, model.theta_nominal, y, q0, n_iter=6, damping=1e-2)
    assert np.isnan(rss[4]) and np.isnan(q[4]).all()
    keep = np.arange(15) != 4
    np.testing.assert_allclose(rss[keep], rss_ref[keep], rtol=1e-9)
    np.testing.assert_allclose(q[keep], q_ref[keep], atol=1e-6)


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("name", MODELS)
def test_noise_free_frame_is_fitted_exactly(name, path, monkeypatch):
    model = MODELS[name]()
    trial = simulate(model, sigma=0.0, n_frames=5, rng=np.random.default_rng(1))
    _use(path, monkeypatch)
    q, rss = fit_pose(model, trial.theta, trial.clean, trial.pose + 0.02, n_iter=50)
    np.testing.assert_allclose(rss, 0.0, atol=1e-12)
    turn = np.array([d.kind == "R" for d in model.dofs])
    d = q - trial.pose
    np.testing.assert_allclose(np.where(turn, np.angle(np.exp(1j * d)), d), 0.0, atol=1e-6)


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("name", ["case-a", "tree3d_functional"])
def test_frame_fitter_equals_fit_pose_logdet(name, path, monkeypatch):
    model, theta, y, q0 = _problem(name, n=9)
    _use(path, monkeypatch)
    fitter = FramePoseFitter(model, theta)
    q, rss, logdet = fitter.fit(y, q0, n_iter=8)
    q2, rss2, logdet2 = fit_pose_logdet(model, theta, y[None], q0, n_iter=8)
    np.testing.assert_allclose(rss, rss2, rtol=1e-12)
    np.testing.assert_allclose(logdet, logdet2, rtol=1e-12)
    np.testing.assert_allclose(q, q2, rtol=1e-12)
    q3, _, _ = fitter.fit(y, q0[0], n_iter=8)  # one start for every hypothesis
    q4, _, _ = fit_pose_logdet(model, theta, y[None], q0[0], n_iter=8)
    np.testing.assert_allclose(q3, q4, rtol=1e-12)


@needs_numba
def test_compiled_sine_and_cosine_are_within_one_ulp():
    x = np.random.default_rng(0).uniform(-60.0, 60.0, size=(1, 50_000))
    x[0, :4] = [0.0, np.pi / 2, -np.pi, 1e6]
    c, s = np.empty_like(x), np.empty_like(x)
    _sincos_rows(x, c, s)
    for got, want in ((c, np.cos(x)), (s, np.sin(x))):
        assert np.all(np.abs(got - want) <= np.spacing(np.abs(want)) + 1e-300)


def _sincos_rows(x, c, s):
    import numba

    @numba.njit
    def run(x, c, s):
        _lm_kernel._sincos(x, 0, c, s, 0, x.shape[1])

    run(x, c, s)


def test_grid_fit_equals_folding_update_and_states_are_not_shared():
    model = builtin_model("case-a")
    trial = simulate(model, sigma=10.0, n_frames=30, rng=np.random.default_rng(2))
    f = MarkerGridFilter(model, axes=(np.linspace(220, 280, 31),), history_steps=(10,))
    fitted = f.fit(trial.data).posterior_
    state = f.init_state()
    states = []
    for frame in trial.data.positions[..., :2]:
        state = f.update(state, frame)
        states.append((state, state.pose.copy()))
    post = f.posterior(state)
    np.testing.assert_array_equal(post.log_weights, fitted.log_weights)
    assert post.history[0][0] == 10
    for s, pose in states:  # a later update never writes into an earlier state
        np.testing.assert_array_equal(s.pose, pose)


def _knee_axis_model():
    """The 3-D test tree whose only unknowns are the two tilts of the knee's hinge axis."""
    d = tree_3d_functional().to_dict()
    d["parameters"] = [p for p in d["parameters"] if p["name"].startswith("knee_axis")]
    return model_from_dict(d, "tree3d_knee_axis")


@pytest.mark.parametrize("path", PATHS)
def test_grid_over_hinge_tilts_equals_brute_force_enumeration(path, monkeypatch):
    model = _knee_axis_model()
    assert model.n_params == 2 and model.axis_tilts
    sigma = 1.0
    trial = simulate(model, theta=[3.0, -2.0], sigma=sigma, n_frames=8, rng=np.random.default_rng(9))
    axes = (np.linspace(-6.0, 6.0, 5), np.linspace(-6.0, 6.0, 5))
    _use(path, monkeypatch)
    filt = MarkerGridFilter(model, sigma=sigma, axes=axes, n_iter=30).fit(trial.data)
    y = trial.data.positions
    log_w = np.empty((5, 5))
    for i, a in enumerate(axes[0]):
        for j, b in enumerate(axes[1]):
            th = np.array([a, b])
            q, rss = _reference_fit_pose(model, th, y, trial.pose, n_iter=60)
            _, Jq, _ = frame_terms(model, th, q, y)
            log_w[i, j] = -rss.sum() / (2 * sigma**2) - 0.5 * log_det_pose_information(Jq).sum()
    log_w -= np.logaddexp.reduce(log_w.ravel())
    np.testing.assert_allclose(filt.posterior_.log_weights, log_w, atol=1e-6)


@needs_numba
@pytest.mark.parametrize("case", ["case-a", "case-b"])
def test_grid_filter_paths_agree(case, monkeypatch):
    model = builtin_model(case)
    trial = simulate(model, sigma=8.0, n_frames=40, rng=np.random.default_rng(4))
    axes = (np.linspace(230, 270, 41),)
    fast = MarkerGridFilter(model, axes=axes).fit(trial.data)
    monkeypatch.setattr(_lm_kernel, "AVAILABLE", False)
    slow = MarkerGridFilter(model, axes=axes).fit(trial.data)
    np.testing.assert_allclose(fast.posterior_.log_weights, slow.posterior_.log_weights, rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(fast.state_.rss, slow.state_.rss, rtol=1e-9)
    np.testing.assert_allclose(fast.state_.logdet, slow.state_.logdet, rtol=1e-9)
    assert fast.sigma_ == pytest.approx(slow.sigma_, rel=1e-9)


@needs_numba
def test_a_cold_cache_starts_the_compilation_aside_once_and_uses_numpy_meanwhile(monkeypatch):
    started = []
    monkeypatch.setattr(_lm_kernel, "MODE", "1")
    monkeypatch.setattr(_lm_kernel, "compiled", lambda planar: False)
    monkeypatch.setattr(_lm_kernel, "_cached", lambda planar: False)
    monkeypatch.setattr(_lm_kernel, "warm", lambda planar, wait=True: started.append((planar, wait)))
    monkeypatch.setattr(_lm_kernel._gate, "last_check", {})
    monkeypatch.setattr(_lm_kernel._gate, "found", {})
    assert not _lm_kernel.ready(True)
    assert not _lm_kernel.ready(True)  # looked at again only after a while
    assert started == [(True, False)]
    model = builtin_model("case-a")
    trial = simulate(model, sigma=5.0, n_frames=3, rng=np.random.default_rng(1))
    q, _ = fit_pose(model, model.theta_center, trial.data.positions[..., :2], trial.pose)
    assert np.all(np.isfinite(q))
    monkeypatch.setattr(_lm_kernel, "_cached", lambda planar: True)
    monkeypatch.setattr(_lm_kernel._gate, "last_check", {})
    assert _lm_kernel.ready(True)
    assert _lm_kernel.ready(True)  # a cached driver stays ready: a second workspace made at once takes it too


@pytest.mark.skipif(os.name != "posix", reason="the compiling processes take turns through fcntl locks")
def test_compiling_processes_take_turns(tmp_path):
    """Kernels missing from the cache compile one process at a time, leaving a core to the fit."""
    code = ("import time, sys\nt0 = time.monotonic()\ntime.sleep(0.3)\n"
            "print(t0, time.monotonic())\n")
    prefix = _numba.one_at_a_time(str(tmp_path / "lock"))
    procs = [subprocess.Popen([sys.executable, "-c", prefix + code], stdout=subprocess.PIPE, text=True)
             for _ in range(2)]
    (a0, a1), (b0, b1) = sorted(tuple(map(float, p.communicate(timeout=60)[0].split())) for p in procs)
    assert all(p.returncode == 0 for p in procs)
    assert b0 >= a1  # the second started its work after the first had finished


@needs_numba
@pytest.mark.parametrize("planar", [True, False, "custom"])
def test_the_cache_check_uses_the_signature_of_real_calls(planar):
    model = builtin_model("case-a") if planar is True else custom_leg() if planar == "custom" else tree_3d()
    assert _lm_kernel.driver_key(_lm_kernel_plan(model)) == planar
    trial = simulate(model, sigma=1.0, n_frames=2, rng=np.random.default_rng(1))
    y = trial.data.positions[..., : model.dim]
    fit_pose_logdet(model, model.theta_center, y, trial.pose)
    import numba

    sig = tuple(numba.typeof(a) for a in _lm_kernel._example_args(planar))
    assert sig in _lm_kernel._driver(planar).signatures
    assert _lm_kernel._cached(planar)


def _lm_kernel_plan(model):
    from skelid.model.kinematics import kinematics_plan

    return kinematics_plan(model)


@needs_numba
def test_custom_joints_take_the_compiled_path_and_carried_translations_do_not():
    """Custom joints (functions of coordinates, constant motions and rotations) are in the compiled kernel's
    tables; a translation carried by the joint's rotations is left to the numpy path."""
    from skelid.model.kinematics import kinematics_plan

    plan = kinematics_plan(custom_leg())
    tables = _lm_kernel.plan_arrays(plan)
    assert tables is not None and len(tables) == 12
    ctab = tables[-1]
    assert ctab[10].tolist() == [False] * 6 + [False] * 3 + [True, False]  # the knee slides: a velocity term
    rows = list(plan.custom)
    t, a, k, f, sl, K, K2, _ = rows[3][0]
    rows[3] = ((t, a, k, f, sl, K, K2, (np.ones(3), 0)),) + rows[3][1:]
    assert _lm_kernel.plan_arrays(plan._replace(custom=tuple(rows))) is None
