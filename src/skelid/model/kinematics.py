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
  marker offset: ``dx_m/dr_m = R_{w s(m)}``; and ``dx/dtheta = dx/dg · A``;
* a hinge axis ``a(alpha, beta)`` tilted by ``axis_direction`` parameters
  (angles in degrees): with ``R_b`` the frame the hinge acts in and ``q`` its
  angle, ``d R / d alpha = [w]_x R`` with the world vector
  ``w = sin(q) R_b a' + (1 - cos q) (R_b a) x (R_b a')``, ``a' = da/dalpha``
  (the left Jacobian of the exponential map, simplified because ``a' ⊥ a``),
  so ``dx_m/dalpha = w x (x_m - c)`` for every marker below the hinge.

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
    tilt_omega: np.ndarray  # (..., T, 2, D) world d(rotation)/d(tilt) of each tilted hinge, per degree


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


def _skew(a: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``(..., 3, 3)`` of vectors ``(..., 3)``."""
    a = np.asarray(a, dtype=float)
    z = np.zeros(a.shape[:-1])
    return np.stack([np.stack([z, -a[..., 2], a[..., 1]], -1),
                     np.stack([a[..., 2], z, -a[..., 0]], -1),
                     np.stack([-a[..., 1], a[..., 0], z], -1)], -2)


def _rotation(dim: int, axis, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., D, D)`` by ``angle (...)`` about ``axis`` (3-D) or z (2-D).

    ``axis`` is a unit vector ``(3,)`` or a batch of them ``(..., 3)``.
    """
    c, s = np.cos(angle), np.sin(angle)
    if dim == 2:
        return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    axis = np.asarray(axis, dtype=float)
    if axis.ndim == 1:
        K = _SKEW_CACHE.get(axis.tobytes())
        if K is None:
            K = _SKEW_CACHE.setdefault(axis.tobytes(), (_skew(axis), _skew(axis) @ _skew(axis)))
        K, K2 = K
    else:
        K = _skew(axis)
        K2 = K @ K
    return np.eye(3) + s[..., None, None] * K + (1.0 - c)[..., None, None] * K2


_SKEW_CACHE: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}


def tilted_axes(model: Model, theta) -> tuple[np.ndarray, np.ndarray]:
    """Axes of the hinges that have ``axis_direction`` parameters.

    Parameters
    ----------
    theta : (..., P) float

    Returns
    -------
    axis : (..., T, 3) float
        Unit axis of each tilted hinge (in the frame it acts in), in the order
        of :attr:`Model.axis_tilts`.
    d_axis : (..., T, 2, 3) float
        Its derivatives with respect to the two tilts, per degree.
    """
    theta = np.asarray(theta, dtype=float)
    tilts = model.axis_tilts
    batch = theta.shape[:-1]
    if not tilts:
        return np.zeros(batch + (0, 3)), np.zeros(batch + (0, 2, 3))
    ku = np.array([t[1] for t in tilts])
    kv = np.array([t[2] for t in tilts])
    e = np.array([t[3] for t in tilts])
    u = np.array([t[4] for t in tilts])
    v = np.array([t[5] for t in tilts])
    al = np.where(ku >= 0, np.radians(theta[..., np.maximum(ku, 0)]), 0.0)[..., None]
    be = np.where(kv >= 0, np.radians(theta[..., np.maximum(kv, 0)]), 0.0)[..., None]
    ca, sa, cb, sb = np.cos(al), np.sin(al), np.cos(be), np.sin(be)
    axis = ca * cb * e + sa * cb * u + sb * v
    d_al = cb * (-sa * e + ca * u)
    d_be = -sb * (ca * e + sa * u) + cb * v
    deg = np.pi / 180.0
    d_axis = np.stack([d_al * (ku >= 0)[:, None], d_be * (kv >= 0)[:, None]], -2) * deg
    return axis, d_axis


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
    tilt_slot = {t[0]: j for j, t in enumerate(model.axis_tilts)}
    if tilt_slot:
        t_axis, t_daxis = tilted_axes(model, np.broadcast_to(np.asarray(theta, float),
                                                             batch + (model.n_params,)))
    omega = np.zeros(batch + (len(tilt_slot), 2, D))
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
            elif k in tilt_slot:
                j = tilt_slot[k]
                a_loc = t_axis[..., j, :]
                w = np.einsum("...ij,...j->...i", Ri, a_loc)
                dw = np.einsum("...ij,...tj->...ti", Ri, t_daxis[..., j, :, :])
                omega[..., j, :, :] = np.sin(qk)[..., None, None] * dw \
                    + (1.0 - np.cos(qk))[..., None, None] * np.cross(w[..., None, :], dw)
                axis[..., k, :] = w
                pivot[..., k, :] = pi
                Ri = Ri @ _rotation(D, a_loc, qk)
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
    return Kinematics(R, p, Rpar, axis, pivot, x, g, omega)


def joint_distances(model: Model, theta) -> tuple[np.ndarray, np.ndarray]:
    """The model's derived lengths and their gradients.

    Parameters
    ----------
    theta : (..., P) float

    Returns
    -------
    lengths : (..., K) float
        ``|o_s(theta)|`` for each entry of :attr:`Model.derived_lengths`.
    grad : (..., K, P) float
        ``d lengths / d theta``.
    """
    D = model.dim
    g_base, A = model.geometry_map
    segs = [s for _, s in model.derived_lengths]
    theta = np.asarray(theta, dtype=float)
    if not segs:
        return np.zeros(theta.shape[:-1] + (0,)), np.zeros(theta.shape[:-1] + (0, model.n_params))
    rows = np.array([[s * D + d for d in range(D)] for s in segs])  # (K, D)
    o = g_base[rows] + np.einsum("kdp,...p->...kd", A[rows], theta)
    n = np.linalg.norm(o, axis=-1)
    grad = np.einsum("...kd,kdp->...kp", o / np.maximum(n, 1e-300)[..., None], A[rows])
    return n, grad


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
    for j, (k, ku, kv, *_) in enumerate(model.axis_tilts):
        moved = model.dof_moves_marker[k][:, None]
        rel = kin.markers - kin.dof_pivot[..., k, None, :]
        for c, kp in enumerate((ku, kv)):
            if kp >= 0:
                J[..., kp] += np.cross(kin.tilt_omega[..., j, c, None, :], rel) * moved
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
