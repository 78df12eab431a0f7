"""The live step's compiled linearisation equals the numpy one."""

from pathlib import Path

import numpy as np
import pytest

from skelid.estimators.fit.pose import workspace
from skelid.estimators.online import _live_kernel
from skelid.model import load_model
from skelid.model.kinematics import Workspace, geometry, marker_jacobian
from skelid.simulate import builtin_model, simulate

ROOT = Path(__file__).resolve().parents[2]
needs_numba = pytest.mark.skipif(not _live_kernel.AVAILABLE, reason="numba not installed or SKELID_NUMBA=0")


def _model(name):
    if name == "case-a":
        return builtin_model(name)
    return load_model(ROOT / ("benchmarks" if name == "arm10" else "examples") / f"{name}.toml")


@needs_numba
@pytest.mark.parametrize("name", ["case-a", "arm10", "tennis_arm"])
def test_compiled_linearisation_equals_marker_jacobian(name):
    model = _model(name)
    ws = workspace(model)
    tables = _live_kernel.tables(ws)
    assert tables is not None
    trial = simulate(model, n_frames=5, sigma=0.0, rng=np.random.default_rng(2))
    for t in range(5):
        theta = model.theta_center * (1.0 + 0.02 * t)
        x, J, K = marker_jacobian(model, theta, trial.pose[t], ws)
        x2, J2, K2 = _live_kernel.linearise(geometry(model, theta)[:, None].copy(), trial.pose[t][:, None].copy(),
                                           *tables)
        for a, b in ((x, x2), (J, J2), (K, K2)):
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-13 * max(np.abs(a).max(), 1.0))


def test_models_it_does_not_cover_are_left_to_numpy():
    model = load_model(ROOT / "examples" / "lower_limb.toml")
    plan = Workspace(model).plan
    assert plan.n_tilts or plan.n_coupled or plan.has_custom
    assert _live_kernel.tables(Workspace(model)) is None


@needs_numba
@pytest.mark.parametrize("name,cutoff", [("arm10", 6.0), ("arm10", None), ("case-a", 6.0), ("arm10", "auto")])
def test_a_session_gives_the_numpy_paths_estimates_to_rounding(monkeypatch, name, cutoff):
    """The compiled frame step (and linearisation) against the numpy update, frame by frame, with a missing
    marker, a swapped label and a frame with no markers in the stream."""
    from skelid.live import Session

    model = _model(name)
    sigma = 0.002 if name == "arm10" else 2.0
    trial = simulate(model, n_frames=60, sigma=sigma, rng=np.random.default_rng(1))
    y = trial.data.positions.copy()
    y[20, 2] = np.nan
    y[40, [1, 2]] = y[40, [2, 1]]
    y[45] = np.nan
    fast = Session(model, labels=trial.data.names, method="gaussian", cutoff=cutoff)
    assert fast._linearise.tables is not None and fast._step is not None
    monkeypatch.setattr(_live_kernel, "ready", lambda: False)
    slow = Session(model, labels=trial.data.names, method="gaussian", cutoff=cutoff)
    assert slow._linearise.tables is None and slow._step is None
    for frame in y:
        a, b = fast.push(frame), slow.push(frame)
        assert (a.healthy, a.health, a.rejected) == (b.healthy, b.health, b.rejected)
        sd = np.sqrt(np.diag(b.cov))
        np.testing.assert_allclose(a.theta, b.theta, rtol=0, atol=1e-6 * sd.min())
        if b.pose is not None:
            np.testing.assert_allclose(a.pose, b.pose, rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.sqrt(np.diag(a.cov)), sd, rtol=1e-6)
    np.testing.assert_allclose(list(a.marker_residuals.values()), list(b.marker_residuals.values()), rtol=1e-6)


@needs_numba
@pytest.mark.parametrize("name", ["case-a", "arm10"])
def test_the_cache_check_uses_the_signature_of_real_calls(name):
    import numba

    model = _model(name)
    tables = _live_kernel.tables(workspace(model))
    _live_kernel.linearise(geometry(model, model.theta_center)[:, None].copy(), np.zeros((model.n_pose, 1)), *tables)
    sig = tuple(numba.typeof(a) for a in _live_kernel._example_args(True))
    assert _live_kernel.linearise.signatures == [sig]
    from skelid.live import Session  # and the frame step, through a session

    trial = simulate(model, n_frames=3, sigma=0.001 if name == "arm10" else 1.0, rng=np.random.default_rng(0))
    session = Session(model, labels=trial.data.names, method="gaussian")
    for frame in trial.data.positions:
        session.push(frame)
    sig = tuple(numba.typeof(a) for a in _live_kernel._step_example_args())
    assert _live_kernel.step.signatures == [sig]
