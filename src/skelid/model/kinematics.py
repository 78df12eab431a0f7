"""Forward kinematics of a segment tree and its analytic Jacobians.

For a model with segments ``s = 0..S-1`` (parents first), pose ``q`` and
geometry ``g = g_base + theta @ A.T`` (see :mod:`skelid.model.description`):

.. math::

    R_{ws} = R_{wp}\\,\\prod_k E_k(q_k), \\qquad
    p_{ws} = p_{wp} + R_{wp}\\, o_s + \\sum_{k\\,\\in\\,T(s)} R_{wp} e_k q_k,
    \\qquad x_m = p_{w s(m)} + R_{w s(m)}\\, r_m

where ``p`` is the segment's parent, ``o_s`` its joint's position in the
parent frame, ``E_k`` the elementary rotations of the joint and ``r_m`` the
marker's position in its segment. The Jacobians are

* rotation ``k`` about world axis ``w_k`` through ``c_k``: ``dx_m/dq_k = w_k x (x_m - c_k)``
  (in 2-D, ``w x v = (-v_y, v_x)``); translation: ``dx_m/dq_k = w_k``;
* joint offset ``o_s``: ``dx_m/do_s = R_wp`` for every marker below ``s``;
  marker offset: ``dx_m/dr_m = R_{w s(m)}``; and ``dx/dtheta = dx/dg · A``.

Every function broadcasts over any leading batch axes shared by ``theta``
``(..., P)`` and ``pose (..., Q)``, typically ``(frames, hypotheses)``. The only
Python loop runs over the model's segments (the depth of the tree).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from skelid.model.description import Model


class Kinematics(NamedTuple):
    """Result of :func:`forward_kinematics` (all arrays share the batch shape ``...``)."""

    R_world_seg: np.ndarray  # (..., S, D, D)
    p_world_seg: np.ndarray  # (..., S, D) joint centre = segment origin
    R_world_parent: np.ndarray  # (..., S, D, D) frame the joint acts in
    dof_axis: np.ndarray  # (..., Q, D) world axis (3-D rotation or translation); 2-D rotation: 0
    dof_pivot: np.ndarray  # (..., Q, D) a point on the rotation axis
    markers: np.ndarray  # (..., M, D)
    g: np.ndarray  # (..., G)


def geometry(model: Model, theta) -> np.ndarray:
    """Geometry vector for parameter values.

    Parameters
    ----------
    theta : (..., P) float

    Returns
    -------
    g : (..., G) float
        Joint positions (S*D) then marker positions (M*D).
    """
    g_base, A = model.geometry_map
    theta = np.asarray(theta, dtype=float)
    if theta.shape[-1:] != (model.n_params,):
        raise ValueError(f"theta must end in {model.n_params} parameters, got shape {theta.shape}")
    return g_base + theta @ A.T


def _rotation(dim: int, axis, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., D, D)`` by ``angle (...)`` about ``axis`` (3-D) or z (2-D)."""
    c, s = np.cos(angle), np.sin(angle)
    if dim == 2:
        return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    a = np.asarray(axis)
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + s[..., None, None] * K + (1.0 - c)[..., None, None] * (K @ K)


def _perp(v: np.ndarray) -> np.ndarray:
    """2-D cross product of the unit z axis with ``v (..., 2)``."""
    return np.stack([-v[..., 1], v[..., 0]], -1)


def forward_kinematics(model: Model, theta, pose) -> Kinematics:
    """Segment frames, joint axes and marker positions.

    Parameters
    ----------
    model : Model
    theta : (..., P) float
        Parameter values.
    pose : (..., Q) float
        Pose coordinates (see the model's joint table); angles in radians.

    Returns
    -------
    Kinematics
    """
    D, S, M = model.dim, len(model.segments), len(model.markers)
    g = geometry(model, theta)
    pose = np.asarray(pose, dtype=float)
    if pose.shape[-1:] != (model.n_pose,):
        raise ValueError(f"pose must end in {model.n_pose} coordinates, got shape {pose.shape}")
    batch = np.broadcast_shapes(g.shape[:-1], pose.shape[:-1])
    g = np.broadcast_to(g, batch + g.shape[-1:])
    offsets = g[..., : S * D].reshape(batch + (S, D))
    r_marker = g[..., S * D :].reshape(batch + (M, D))
    eye = np.broadcast_to(np.eye(D), batch + (D, D))
    R = np.empty(batch + (S, D, D))
    p = np.empty(batch + (S, D))
    Rpar = np.empty(batch + (S, D, D))
    Q = model.n_pose
    axis = np.zeros(batch + (Q, D))
    pivot = np.zeros(batch + (Q, D))
    k = 0
    for i in range(S):
        par = model.parent_index[i]
        Rp = eye if par < 0 else R[..., par, :, :]
        pp = np.zeros(batch + (D,)) if par < 0 else p[..., par, :]
        Ri = Rp
        pi = pp + np.einsum("...ij,...j->...i", Rp, offsets[..., i, :])
        while k < Q and model.dofs[k].segment == i:
            dof = model.dofs[k]
            qk = pose[..., k]
            if dof.kind == "T":
                w = Ri @ np.asarray(dof.axis)
                axis[..., k, :] = w
                pi = pi + w * qk[..., None]
            else:
                if D == 3:
                    axis[..., k, :] = Ri @ np.asarray(dof.axis)
                pivot[..., k, :] = pi
                Ri = Ri @ _rotation(D, dof.axis, qk)
            k += 1
        R[..., i, :, :] = Ri
        p[..., i, :] = pi
        Rpar[..., i, :, :] = Rp
    ms = model.marker_segment
    x = p[..., ms, :] + np.einsum("...mij,...mj->...mi", R[..., ms, :, :], r_marker)
    return Kinematics(R, p, Rpar, axis, pivot, x, g)


def marker_positions(model: Model, theta, pose) -> np.ndarray:
    """Marker positions ``(..., M, D)`` for ``theta (..., P)`` and ``pose (..., Q)``."""
    return forward_kinematics(model, theta, pose).markers


def joint_positions(model: Model, theta, pose) -> np.ndarray:
    """World positions ``(..., S, D)`` of every segment's joint centre."""
    return forward_kinematics(model, theta, pose).p_world_seg


def pose_jacobian(model: Model, kin: Kinematics) -> np.ndarray:
    """``dx/dq`` as ``(..., M, D, Q)`` from a :class:`Kinematics`."""
    x = kin.markers  # (..., M, D)
    rel = x[..., None, :, :] - kin.dof_pivot[..., :, None, :]  # (..., Q, M, D)
    if model.dim == 2:
        rot = _perp(rel)
    else:
        rot = np.cross(kin.dof_axis[..., :, None, :], rel)
    is_t = np.array([d.kind == "T" for d in model.dofs], dtype=bool)
    cols = np.where(is_t[:, None, None], kin.dof_axis[..., :, None, :], rot)
    cols = cols * model.dof_moves_marker[..., None]
    return np.moveaxis(cols, -3, -1)


def theta_jacobian(model: Model, kin: Kinematics) -> np.ndarray:
    """``dx/dtheta`` as ``(..., M, D, P)`` from a :class:`Kinematics`."""
    D, S = model.dim, len(model.segments)
    _, A = model.geometry_map
    P = A.shape[1]
    A_joint = A[: S * D].reshape(S, D, P)
    A_mark = A[S * D :].reshape(-1, D, P)
    ms = model.marker_segment
    J = np.zeros(kin.markers.shape + (P,))
    used_j = np.flatnonzero(np.abs(A_joint).sum(axis=(1, 2)))
    if used_j.size:
        RA = np.einsum("...sij,sjp->...sip", kin.R_world_parent[..., used_j, :, :], A_joint[used_j])
        J = J + np.einsum("...sip,sm->...mip", RA, model.ancestor[used_j][:, ms].astype(float))
    used_m = np.flatnonzero(np.abs(A_mark).sum(axis=(1, 2)))
    if used_m.size:
        J[..., used_m, :, :] += np.einsum(
            "...mij,mjp->...mip", kin.R_world_seg[..., ms[used_m], :, :], A_mark[used_m]
        )
    return J


def marker_jacobian(model: Model, theta, pose):
    """Marker positions and both Jacobians.

    Parameters
    ----------
    theta : (..., P) float
    pose : (..., Q) float

    Returns
    -------
    x : (..., M, D) float
        Marker positions.
    J_pose : (..., M, D, Q) float
        ``dx/dpose``.
    J_theta : (..., M, D, P) float
        ``dx/dtheta``.
    """
    kin = forward_kinematics(model, theta, pose)
    return kin.markers, pose_jacobian(model, kin), theta_jacobian(model, kin)
