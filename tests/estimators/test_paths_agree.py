"""The compiled pose kernel and the numpy path give the same final estimates on every example model."""

from pathlib import Path

import numpy as np
import pytest

from skelid.estimators.fit import _lm_kernel
from skelid.estimators.online.grid import MarkerGridFilter
from skelid.model import load_model, model_from_dict
from skelid.simulate import simulate

EXAMPLES = sorted((Path(__file__).resolve().parents[2] / "examples").glob("*.toml"))
needs_kernel = pytest.mark.skipif(not _lm_kernel.AVAILABLE, reason="the compiled kernel is turned off (SKELID_NUMBA=0)")


def _noise(model) -> float:
    return 0.002 if model.units == "m" else 2.0


def _both_paths(fit, monkeypatch):
    compiled = fit()
    with monkeypatch.context() as mp:
        mp.setattr(_lm_kernel, "AVAILABLE", False)
        plain = fit()
    return compiled, plain


def _at_most_three_parameters(model):
    """The model itself, or with only its first parameter unknown (the others at their nominal values)."""
    if model.n_params <= 3:
        return model
    d = model.to_dict()
    d["parameters"] = d["parameters"][:1]
    return model_from_dict(d, model.name + "_first")


@needs_kernel
@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.stem)
def test_online_grid_estimate_is_the_same_on_both_paths(path, monkeypatch):
    model = _at_most_three_parameters(load_model(path))
    trial = simulate(model, n_frames=12, sigma=_noise(model), rng=np.random.default_rng(6))
    axes = tuple(np.linspace(*p.grid[[0, -1]], 7) for p in model.parameters)

    def fit():
        post = MarkerGridFilter(model, axes=axes, rng=np.random.default_rng(0)).fit(trial.data).posterior_
        s = post.summary()
        return np.array([s[n]["mean"] for n in model.parameter_names]), \
            np.array([s[n]["sd"] for n in model.parameter_names])

    (a, sd), (b, _) = _both_paths(fit, monkeypatch)
    np.testing.assert_array_less(np.abs(a - b), 1e-6 * sd + 1e-300)


def test_tennis_forearm_first_pose_is_the_same_on_both_paths(shared_data, monkeypatch):
    """The first pose is chosen among equal-cost angle branches the same way whatever the rounding."""
    from skelid.estimators.base import prepare
    from skelid.estimators.fit.pose import initial_pose
    from skelid.io import read_markers

    model = load_model(Path(__file__).resolve().parents[2] / "examples" / "tennis_forearm.toml")
    y = prepare(model, read_markers(shared_data / "kineticstoolkit-tennis" / "kinematics_tennis_serve.c3d"))

    def first():
        return initial_pose(model, model.theta_center, y[0], np.random.default_rng(0))[0]

    a, b = _both_paths(first, monkeypatch)
    np.testing.assert_allclose(a, b, atol=1e-6)


def test_a_fit_takes_the_path_ready_at_its_start_and_says_which(monkeypatch):
    from skelid.estimators.fit.pose import fit_pose, workspace
    from skelid.estimators.marker import MarkerEstimator
    from skelid.simulate import builtin_model

    model = builtin_model("case-a")
    trial = simulate(model, sigma=5.0, n_frames=40, rng=np.random.default_rng(2))
    with monkeypatch.context() as mp:
        mp.setattr(_lm_kernel, "ready", lambda planar: False)  # the kernel still compiling at the start
        ws = workspace(model)
        est = MarkerEstimator(model).fit(trial.data)
    assert ws.path == "numpy" and est.result().diagnostics["pose_path"] == "numpy"
    # ready now, but a workspace made before stays on its path
    fit_pose(model, model.theta_center, trial.data.positions[:3], trial.pose[:3], ws=ws)
    assert ws.kernel_tables is None
    expected = "compiled" if _lm_kernel.ready(True) else "numpy"
    assert MarkerEstimator(model).fit(trial.data).result().diagnostics["pose_path"] == expected
