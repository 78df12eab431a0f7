import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import logsumexp

from skelid.errors import IdentifiabilityError, ModelError
from skelid.estimators.paper import ConstraintSystem, PaperFilter
from skelid.model import joint_positions
from skelid.simulate import builtin_model, simulate
from tests.helpers import tree_3d


def _conditioning(model, trial):
    """Smallest singular value of the per-frame constraint Jacobian at the truth (relative)."""
    system = ConstraintSystem(model)
    J = joint_positions(model, trial.theta, trial.pose)[:, system.joints]
    out = []
    for t in range(len(J)):
        x = np.concatenate([J[t].ravel(), trial.theta])
        _, jac = system.residual(x, trial.clean[t])
        s = np.linalg.svd(jac, compute_uv=False)
        out.append(s[-1] / s[0])
    return np.array(out)


@pytest.mark.parametrize("case", ["case-a", "case-b"])
def test_noise_free_frames_recover_the_true_length(case):
    model = builtin_model(case)
    trial = simulate(model, sigma=0.0, n_frames=200, rng=np.random.default_rng(3), hard_poses=True)
    est = PaperFilter(model).fit(trial.data)
    well = _conditioning(model, trial) > 1e-3
    assert well.sum() > 150
    np.testing.assert_allclose(est.measured_[well], 250.0, atol=1e-6)
    assert est.posterior_.map[0] == 250.0


@pytest.mark.parametrize("case", ["case-a", "case-b"])
def test_equations_are_the_papers(case):
    system = ConstraintSystem(builtin_model(case))
    expected = {"|MA|", "|MN|", "|MB|", "|NB|", "|NC|"} | ({"|MD|", "|ND|"} if case == "case-b" else set())
    assert set(system.labels) == expected
    assert system.n_unknowns == 5


def test_grid_filter_equals_brute_force_enumeration():
    model = builtin_model("case-a")
    trial = simulate(model, sigma=3.0, n_frames=12, rng=np.random.default_rng(5))
    est = PaperFilter(model, sigma=4.0).fit(trial.data)
    grid = model.parameters[0].grid
    m = est.measured_[np.isfinite(est.measured_)]
    brute = np.array([np.prod(np.exp(-0.5 * ((m - L) / 4.0) ** 2)) for L in grid])  # uniform prior
    brute /= brute.sum()
    np.testing.assert_allclose(est.posterior_.weights, brute, rtol=1e-9, atol=1e-300)
    assert logsumexp(est.posterior_.log_weights) == pytest.approx(0.0, abs=1e-12)


def test_fit_equals_folding_update():
    model = builtin_model("case-b")
    trial = simulate(model, sigma=8.0, n_frames=60, rng=np.random.default_rng(7))
    est = PaperFilter(model, history_steps=(10, 60)).fit(trial.data)
    state = est.init_state()
    measured = []
    for frame in trial.data.positions:
        state = est.update(state, frame)
        measured.append(state.measured)
    np.testing.assert_allclose(np.array(measured), est.measured_, equal_nan=True)
    np.testing.assert_allclose(state.posterior.log_weights, est.posterior_.log_weights, atol=1e-9)
    assert [s for s, _ in state.posterior.history] == [10, 60]
    assert state.n_used == est.frames_used_.sum()


@settings(max_examples=15, deadline=None, derandomize=True)
@given(angle=st.floats(-np.pi, np.pi), dx=st.floats(-2000, 2000), dy=st.floats(-2000, 2000))
def test_rigid_motion_leaves_per_frame_lengths_unchanged(angle, dx, dy):
    model = builtin_model("case-a")
    trial = simulate(model, sigma=5.0, n_frames=30, rng=np.random.default_rng(11))
    y = trial.data.positions
    R = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    y2 = y @ R.T + np.array([dx, dy])
    a = PaperFilter(model).measure(y)
    b = PaperFilter(model).measure(y2)
    np.testing.assert_allclose(a, b, atol=1e-6, equal_nan=True)


def test_interval_without_solution_is_an_identifiability_error():
    model = builtin_model("case-a")
    d = model.to_dict()
    d["parameters"][0]["prior"] = {"type": "uniform", "lower": 400.0, "upper": 450.0}
    from skelid.model import model_from_dict

    bad = model_from_dict(d)
    trial = simulate(model, sigma=0.0, n_frames=20)
    with pytest.raises(IdentifiabilityError, match="no solution inside the interval"):
        PaperFilter(bad).fit(trial.data)


def test_paper_method_refuses_models_it_cannot_handle():
    with pytest.raises(ModelError, match="exactly one parameter"):
        ConstraintSystem(tree_3d())


def test_missing_markers_drop_frames_and_warn():
    model = builtin_model("case-a")
    trial = simulate(model, sigma=2.0, n_frames=40, rng=np.random.default_rng(2))
    y = np.array(trial.data.positions)
    y[5:15, 1] = np.nan
    est = PaperFilter(model)
    with pytest.warns(UserWarning, match="missing"):
        est.fit(trial.data.replace(positions=y))
    assert not est.frames_used_[5:15].any()
