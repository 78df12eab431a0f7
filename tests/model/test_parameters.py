"""Parameter kinds beyond the linear ones: vectors, functional joint centres, hinge axis tilts."""

import numpy as np
import pytest

from skelid.errors import ModelError
from skelid.model import marker_jacobian, marker_positions, model_from_dict
from skelid.model.kinematics import forward_kinematics, pose_gradient
from tests.helpers import tree_3d, tree_3d_functional


def test_vector_parameters_expand_with_names_and_priors():
    m = tree_3d_functional()
    assert m.parameter_names == ("hip_x", "hip_y", "hip_z", "knee_x", "knee_y", "knee_axis_u",
                                 "knee_axis_v", "f1_x", "f1_z", "arm_offset")
    f1x = m.parameter("f1_x")
    # a normal prior without a mean is centred on the nominal value
    assert f1x.prior.kind == "normal" and f1x.prior.mean == 120.0
    assert m.parameter("f1_z").prior.kind == "uniform"
    np.testing.assert_allclose(m.theta_nominal, [0, 0, 0, 0, 0, 0, 0, 120, 0, 300])
    assert model_from_dict(m.to_dict()) == m


def test_jacobians_with_every_parameter_kind_equal_central_differences():
    m = tree_3d_functional()
    rng = np.random.default_rng(3)
    theta = m.theta_nominal + rng.normal(0, 6, size=(3, m.n_params))
    q = rng.normal(0, 0.8, size=(3, m.n_pose))
    _, Jq, Jt = marker_jacobian(m, theta, q)
    h = 1e-5
    for k in range(m.n_params):
        dt = np.zeros(m.n_params)
        dt[k] = h
        fd = (marker_positions(m, theta + dt, q) - marker_positions(m, theta - dt, q)) / (2 * h)
        np.testing.assert_allclose(Jt[..., k], fd, atol=2e-6, err_msg=m.parameter_names[k])
    for k in range(m.n_pose):
        dq = np.zeros(m.n_pose)
        dq[k] = h
        fd = (marker_positions(m, theta, q + dq) - marker_positions(m, theta, q - dq)) / (2 * h)
        np.testing.assert_allclose(Jq[..., k], fd, atol=2e-5)
    r = rng.normal(0, 2.0, size=(3, len(m.markers), 3))  # J^T r without J, tilted hinge included
    np.testing.assert_allclose(pose_gradient(m, forward_kinematics(m, theta, q), r),
                               np.einsum("...mdk,...md->...k", Jq, r), rtol=1e-10, atol=1e-8)


def test_joint_centre_moves_no_marker_in_the_reference_pose():
    m = tree_3d_functional()
    rng = np.random.default_rng(0)
    q = np.zeros(m.n_pose)
    q[:6] = rng.normal(0, 0.5, 6)  # any root pose; every joint at zero
    base = marker_positions(m, m.theta_nominal, q)
    theta = m.theta_nominal.copy()
    theta[:5] = [12.0, -7.0, 3.0, 9.0, -4.0]
    np.testing.assert_allclose(marker_positions(m, theta, q), base, atol=1e-9)
    q[7] = 0.6  # bend the hip: now the hip centre matters
    assert np.abs(marker_positions(m, theta, q) - marker_positions(m, m.theta_nominal, q)).max() > 1.0


def test_joint_centre_shifts_the_joint_and_its_distances():
    m = tree_3d_functional()
    theta = m.theta_nominal.copy()
    theta[0:3] = [5.0, 6.0, 7.0]
    kin = forward_kinematics(m, theta, np.zeros(m.n_pose))
    hip = m.segment_index["thigh"]
    np.testing.assert_allclose(kin.p_world_seg[hip] - forward_kinematics(
        m, m.theta_nominal, np.zeros(m.n_pose)).p_world_seg[hip], [5, 6, 7], atol=1e-12)
    names = [n for n, _ in m.derived_lengths]
    assert names == ["root-hip", "hip-knee", "knee-ankle"]  # not root-weld: its length is a parameter


def test_axis_tilt_turns_the_hinge():
    m = tree_3d_functional()
    k = m.parameter_names.index("knee_axis_u")
    theta = m.theta_nominal.copy()
    theta[k] = 90.0  # the axis turns fully onto its tilt direction u
    kin = forward_kinematics(m, theta, np.zeros(m.n_pose))
    knee_dof = m.axis_tilts[0][0]
    np.testing.assert_allclose(kin.dof_axis[knee_dof], m.axis_tilts[0][4], atol=1e-12)
    # the tilt basis is orthonormal and u is a coordinate direction made perpendicular to e
    e, u, v = (np.array(x) for x in m.axis_tilts[0][3:])
    np.testing.assert_allclose([e @ u, e @ v, u @ v, np.linalg.norm(v)], [0, 0, 0, 1], atol=1e-12)


@pytest.mark.parametrize("entry, message", [
    ({"name": "a", "kind": "axis_direction", "joint": "hip", "axis": "u",
      "prior": {"type": "uniform", "lower": -5, "upper": 5}}, "needs a hinge"),
    ({"name": "c", "kind": "joint_centre", "joint": "root", "axis": "x",
      "prior": {"type": "uniform", "lower": -5, "upper": 5}}, "attaches the root"),
    ({"name": "c", "kind": "joint_centre", "joint": "knee", "axis": "x", "axes": ["x"],
      "prior": {"type": "uniform", "lower": -5, "upper": 5}}, "either axis or axes"),
    ({"name": "c", "kind": "joint_centre", "joint": "knee", "axes": ["x", "w"],
      "prior": {"type": "uniform", "lower": -5, "upper": 5}}, r"axes\[1\]: unknown value 'w'"),
    ({"name": "c", "kind": "joint_centre", "joint": "knee", "axes": ["x", "x"],
      "prior": {"type": "uniform", "lower": -5, "upper": 5}}, "distinct"),
    ({"name": "c", "kind": "joint_position", "joint": "knee", "axes": ["x", "y"],
      "prior": [{"type": "normal", "sd": 5}]}, "1 priors for 2 axes"),
    ({"name": "c", "kind": "joint_centre", "joint": "knee", "axis": "y",
      "prior": {"type": "uniform", "lower": -5, "upper": 5}}, "is an end of length parameter"),
    ({"name": "c", "kind": "joint_centre", "joint": "hip", "axis": "y",
      "prior": {"type": "uniform", "lower": -5, "upper": 5}}, "is an end of length parameter"),
])
def test_invalid_parameter_tables(entry, message):
    d = tree_3d().to_dict()
    d["parameters"].append(entry)
    with pytest.raises(ModelError, match=message):
        _ = model_from_dict(d, "bad.toml").geometry_map
