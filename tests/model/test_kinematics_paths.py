"""The kinematics' fast paths against plain references."""

from pathlib import Path

import numpy as np
import pytest
from scipy.linalg import expm

from skelid.model import _fk_kernel, load_model
from skelid.model.kinematics import (
    Workspace,
    _forward_general,
    _forward_planar,
    forward_kinematics,
    geometry,
    kinematics_plan,
    marker_jacobian,
    marker_positions,
    stacked_jacobian,
    tilt_tables,
)
from skelid.simulate import builtin_model
from tests.helpers import custom_leg, tree_3d, tree_3d_functional

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
MODELS = {"case-a": lambda: builtin_model("case-a"), "case-b": lambda: builtin_model("case-b"),
          "tree3d": tree_3d, "tree3d_functional": tree_3d_functional,
          "lower_limb": lambda: load_model(EXAMPLES / "lower_limb.toml")}


def _reference(model, theta, q):
    """Joint centres (S, D) and markers (M, D) of one element, segment by segment, with matrix exponentials."""
    D, S = model.dim, len(model.segments)
    g_base, A = model.geometry_map
    g = g_base + A @ theta
    offsets, r = g[: S * D].reshape(S, D), g[S * D:].reshape(-1, D)
    tilted = {}
    for k, ku, kv, e, u, v in model.axis_tilts:
        al = np.radians(theta[ku]) if ku >= 0 else 0.0
        be = np.radians(theta[kv]) if kv >= 0 else 0.0
        tilted[k] = (np.cos(al) * np.cos(be) * np.array(e) + np.sin(al) * np.cos(be) * np.array(u)
                     + np.sin(be) * np.array(v))
    R, p = [None] * S, [None] * S
    for i in range(S):
        par = model.parent_index[i]
        Rp = np.eye(D) if par < 0 else R[par]
        Ri, pi = Rp, (np.zeros(D) if par < 0 else p[par]) + Rp @ offsets[i]
        for k, dof in enumerate(model.dofs):
            if dof.segment != i:
                continue
            if dof.kind == "T":
                pi = pi + Ri @ np.asarray(dof.axis) * q[k]
            elif D == 2:
                Ri = Ri @ expm(np.array([[0.0, -q[k]], [q[k], 0.0]]))
            else:
                a = tilted.get(k, np.asarray(dof.axis, float))
                Ri = Ri @ expm(q[k] * np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]]))
        R[i], p[i] = Ri, pi
    x = np.array([p[s] + R[s] @ r[m] for m, s in enumerate(model.marker_segment)])
    return np.array(p), x


def _draws(model, seed=3):
    rng = np.random.default_rng(seed)
    scale = np.array([3.0 if p.kind == "axis_direction" else 10.0 for p in model.parameters])
    theta = model.theta_nominal + rng.normal(0, 1, size=(3, 1, model.n_params)) * scale
    pose = rng.normal(0, 1.0, size=(1, 4, model.n_pose))
    return theta, pose


@pytest.mark.parametrize("name", MODELS)
def test_forward_kinematics_equals_a_segment_by_segment_reference(name):
    model = MODELS[name]()
    theta, pose = _draws(model)
    kin = forward_kinematics(model, theta, pose)  # (3, 4) batch by broadcasting
    assert kin.markers.shape == (3, 4, len(model.markers), model.dim)
    size = np.abs(kin.markers).max()
    for a in range(3):
        for b in range(4):
            p_ref, x_ref = _reference(model, theta[a, 0], pose[0, b])
            np.testing.assert_allclose(kin.markers[a, b], x_ref, rtol=0, atol=1e-12 * size)
            np.testing.assert_allclose(kin.p_world_seg[a, b], p_ref, rtol=0, atol=1e-12 * size)


@pytest.mark.parametrize("name", ["tree3d_functional", "lower_limb"])
def test_jacobians_of_tilted_models_equal_central_differences_of_the_reference(name):
    model = MODELS[name]()
    assert model.axis_tilts
    theta, pose = _draws(model, seed=8)
    theta, pose = theta[:2, 0], pose[0, :2]  # (2, P), (2, Q): two elements
    _, Jq, Jt = marker_jacobian(model, theta, pose)
    for b in range(2):
        for k, h in ((k, 1e-6) for k in range(model.n_pose)):
            dq = np.zeros(model.n_pose)
            dq[k] = h
            fd = (_reference(model, theta[b], pose[b] + dq)[1] - _reference(model, theta[b], pose[b] - dq)[1]) / (2 * h)
            np.testing.assert_allclose(Jq[b, ..., k], fd, atol=1e-5)
        for k in range(model.n_params):
            dt = np.zeros(model.n_params)
            dt[k] = 1e-5
            fd = (_reference(model, theta[b] + dt, pose[b])[1] - _reference(model, theta[b] - dt, pose[b])[1]) / 2e-5
            np.testing.assert_allclose(Jt[b, ..., k], fd, atol=1e-5)


@pytest.mark.parametrize("case", ["case-a", "case-b"])
def test_planar_path_equals_products_of_rotations(case):
    model = builtin_model(case)
    plan = kinematics_plan(model)
    assert plan.planar
    rng = np.random.default_rng(3)
    theta = model.theta_nominal + rng.normal(0, 20, size=(5, 1, model.n_params))
    pose = rng.normal(0, 2.0, size=(1, 4, model.n_pose))
    g = geometry(model, theta)
    fast, slow = _forward_planar(plan, g, pose), _forward_general(plan, g, pose)
    for name, a, b in zip(fast._fields, fast, slow, strict=True):
        if a is None and b is None:  # terms of coupled (custom) joints only
            continue
        assert a.shape == b.shape, name
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-9, err_msg=name)


def test_general_path_without_omega_leaves_the_rest_unchanged():
    model = tree_3d_functional()
    plan = kinematics_plan(model)
    assert not plan.planar and plan.n_tilts == 1
    theta, pose = _draws(model)
    g = geometry(model, theta)
    full = _forward_general(plan, g, pose, tilt_tables(model, theta))
    lean = _forward_general(plan, g, pose, tilt_tables(model, theta), want_omega=False)
    for name, a, b in zip(full._fields, full, lean, strict=True):
        if name != "tilt_omega":
            np.testing.assert_array_equal(a, b, err_msg=name)
    assert np.abs(full.tilt_omega).max() > 0 and not np.any(lean.tilt_omega)
    with pytest.raises(ValueError, match="tilt"):
        _forward_general(plan, g, pose)


def test_plan_lives_in_the_workspace_never_in_the_model():
    model = builtin_model("case-a")
    other = builtin_model("case-a")
    before = set(vars(model))
    ws = Workspace(model)
    forward_kinematics(model, model.theta_nominal, np.zeros(model.n_pose), ws)
    forward_kinematics(model, model.theta_nominal, np.zeros(model.n_pose))
    assert kinematics_plan(model, ws) is ws.plan is kinematics_plan(model, ws)
    assert set(vars(model)) - before <= {"dofs", "geometry_map", "parent_index", "marker_segment", "ancestor",
                                         "dof_moves_marker", "nominal_geometry", "axis_tilts", "derived_lengths",
                                         "coupled_translations"}  # the description's own derived fields only
    assert model == other and hash(model) == hash(other)
    with pytest.raises(ValueError, match="workspace belongs"):
        kinematics_plan(builtin_model("case-b"), ws)


ALL_MODELS = {**{p.stem: (lambda p=p: load_model(p)) for p in sorted(EXAMPLES.glob("*.toml"))}, **MODELS,
              "custom_leg": custom_leg}


@pytest.mark.skipif(not _fk_kernel.AVAILABLE, reason="the compiled kinematics are turned off (SKELID_NUMBA=0)")
@pytest.mark.parametrize("name", ALL_MODELS)
def test_compiled_kinematics_equal_the_numpy_path(name):
    model = ALL_MODELS[name]()
    compiled, plain = Workspace(model), Workspace(model)
    plain.fk_tables = False  # the numpy path
    theta, pose = _draws(model, seed=5)
    for th, q in ((theta, pose), (theta[0, 0], pose[0]), (theta[:, 0], pose[0, 0])):  # broadcast, shared, per element
        x, Jq, Jt = marker_jacobian(model, th, q, compiled)
        assert compiled.fk_tables is not False  # the compiled path was taken
        x0, Jq0, Jt0 = marker_jacobian(model, th, q, plain)
        assert x.shape == x0.shape and Jq.shape == Jq0.shape and Jt.shape == Jt0.shape
        for a, b in ((x, x0), (Jq, Jq0), (Jt, Jt0)):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-13 * max(np.abs(b).max(), 1.0))
        np.testing.assert_allclose(marker_positions(model, th, q, compiled), x0, rtol=0,
                                   atol=1e-13 * np.abs(x0).max())
        both = np.concatenate([Jt0, Jq0], axis=-1)
        for ws in (compiled, plain):
            np.testing.assert_allclose(stacked_jacobian(model, th, q, ws), both, rtol=0,
                                       atol=1e-13 * max(np.abs(both).max(), 1.0))
