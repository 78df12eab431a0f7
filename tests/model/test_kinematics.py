import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skelid.model import forward_kinematics, marker_jacobian, marker_positions
from skelid.model.kinematics import pose_gradient
from skelid.simulate import builtin_model
from tests.helpers import tree_3d

MODELS = {"case-a": lambda: builtin_model("case-a"), "case-b": lambda: builtin_model("case-b"),
          "tree3d": tree_3d}


@pytest.mark.parametrize("name", MODELS)
def test_jacobians_equal_central_differences(name):
    model = MODELS[name]()
    rng = np.random.default_rng(1)
    theta = model.theta_nominal + rng.normal(0, 5, size=(4, model.n_params))
    q = rng.normal(0, 0.7, size=(4, model.n_pose))
    _, Jq, Jt = marker_jacobian(model, theta, q)
    h = 1e-5
    for k in range(model.n_pose):
        dq = np.zeros(model.n_pose)
        dq[k] = h
        fd = (marker_positions(model, theta, q + dq) - marker_positions(model, theta, q - dq)) / (2 * h)
        np.testing.assert_allclose(Jq[..., k], fd, atol=1e-5)
    for k in range(model.n_params):
        dt = np.zeros(model.n_params)
        dt[k] = h
        fd = (marker_positions(model, theta + dt, q) - marker_positions(model, theta - dt, q)) / (2 * h)
        np.testing.assert_allclose(Jt[..., k], fd, atol=1e-6)


@pytest.mark.parametrize("name", MODELS)
def test_pose_gradient_equals_the_jacobian_transpose_times_residuals(name):
    model = MODELS[name]()
    rng = np.random.default_rng(2)
    theta = model.theta_nominal + rng.normal(0, 5, size=(3, 1, model.n_params))
    q = rng.normal(0, 0.7, size=(3, 4, model.n_pose))
    r = rng.normal(0, 2.0, size=(3, 4, len(model.markers), model.dim))
    _, Jq, _ = marker_jacobian(model, theta, q)
    g = pose_gradient(model, forward_kinematics(model, theta, q), r)
    np.testing.assert_allclose(g, np.einsum("...mdk,...md->...k", Jq, r), rtol=1e-10, atol=1e-8)


def test_batch_axes_broadcast():
    model = builtin_model("case-a")
    rng = np.random.default_rng(0)
    theta = np.linspace(200, 300, 7)[None, :, None]  # (1, H, 1)
    q = rng.normal(size=(5, 1, model.n_pose))  # (F, 1, Q)
    x = marker_positions(model, theta, q)
    assert x.shape == (5, 7, 3, 2)
    np.testing.assert_allclose(x[2, 3], marker_positions(model, theta[0, 3], q[2, 0]))


def _pairwise_within_segments(model, x):
    out = []
    seg = model.marker_segment
    for i in range(len(seg)):
        for j in range(i + 1, len(seg)):
            if seg[i] == seg[j]:
                out.append(np.linalg.norm(x[..., i, :] - x[..., j, :], axis=-1))
    return np.stack(out, -1)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.lists(st.floats(-3, 3), min_size=12, max_size=12))
def test_marker_distances_within_a_segment_are_constant(values):
    model = tree_3d()
    q = np.array(values)
    q[:3] *= 500.0
    d0 = _pairwise_within_segments(model, marker_positions(model, model.theta_nominal, np.zeros(12)))
    d = _pairwise_within_segments(model, marker_positions(model, model.theta_nominal, q))
    np.testing.assert_allclose(d, d0, rtol=1e-10, atol=1e-8)


def test_length_parameter_moves_joint_to_that_distance():
    model = builtin_model("case-a")
    from skelid.model import joint_positions

    for L in (210.0, 287.5):
        p = joint_positions(model, [L], np.array([10.0, -4.0, 0.3, 0.9, -0.2]))
        assert np.linalg.norm(p[2] - p[1]) == pytest.approx(L, abs=1e-9)
