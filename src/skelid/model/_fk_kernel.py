"""Compiled forward kinematics and Jacobians (numba).

The same arithmetic as :func:`skelid.model.kinematics._forward_general`,
:func:`~skelid.model.kinematics.pose_jacobian_from_plan` and
:func:`~skelid.model.kinematics.theta_jacobian` for a 3-D model without
custom (coupled) joints, one batch element at a time: the segment frames

.. math:: R_{ws} = R_{wp} \\prod_k (I + \\sin q_k K_k + (1 - \\cos q_k) K_k^2),
          \\qquad x_m = p_{w s(m)} + R_{w s(m)} r_m ,

the pose columns ``w_k x (x_m - c_k)`` (rotations) or ``w_k`` (translations)
and the geometry columns ``sum_j R_{w p(j)} A_j`` over the joints above each
marker plus ``R_{w s(m)} A_m``, plus the tilted hinges' ``omega x (x_m - c_k)``.
The outputs are written straight into the numpy path's ``(B, M, D, Q)`` and
``(B, M, D, P)`` layouts, so no array of the size of the Jacobians is
allocated more than once per call. Results agree with the numpy path to
rounding (sums are taken in another order).

Planar models (every rotation about ``z``) take a second driver with one angle
per segment, as :func:`~skelid.model.kinematics._forward_planar` does.

Each driver is compiled on first use and cached on disk by numba
(``cache=True``); while it is not cached, :func:`ready` starts its compilation
in a separate process and answers False, and the numpy path is used. The
environment variable ``SKELID_NUMBA`` selects the path as for the pose kernel
(:mod:`skelid.estimators.fit._lm_kernel`): ``0`` always numpy, ``wait`` always
compiled (compiling first if need be).
"""

from __future__ import annotations

import math

import numpy as np

from skelid._numba import AVAILABLE, MODE, Gate, compile_in_background, compile_lock, in_disk_cache, numba  # noqa: F401
from skelid.model.custom_tables import custom_arrays, no_custom
from skelid.model.tilts import tilt_arrays, tilted_axes_from

if AVAILABLE:  # pragma: no branch
    from skelid.model.custom_tables import function_value


def plan_tables(plan) -> tuple | None:
    """The model tables the drivers read, or None where they cannot represent the model.

    They represent 3-D models, custom joints included (:func:`~skelid.model.custom_tables.custom_arrays`;
    not those with carried translations), and planar models (:attr:`KinematicsPlan.planar`).
    """
    custom = custom_arrays(plan) if plan.has_custom else None
    if not plan.planar and (plan.dim != 3 or (plan.has_custom and custom is None)
                            or (plan.n_coupled and not plan.has_custom)):
        return None
    S, Q = plan.n_segments, plan.n_pose
    seg_dofs = np.full((S, max([len(ks) for ks in plan.segment_dofs] + [1])), -1, dtype=np.int64)
    n_dofs = np.zeros(S, dtype=np.int64)
    for i, ks in enumerate(plan.segment_dofs):
        n_dofs[i] = len(ks)
        seg_dofs[i, :len(ks)] = ks
    parent = np.array(plan.parent, dtype=np.int64)
    return (parent, seg_dofs, n_dofs, plan.dof_is_t.astype(np.bool_), np.ascontiguousarray(plan.dof_axis, float),
            np.ascontiguousarray(plan.dof_skew), np.ascontiguousarray(plan.dof_skew2),
            plan.dof_tilt.astype(np.int64), plan.marker_segment.astype(np.int64),
            np.ascontiguousarray(plan.moves), plan.used_joints.astype(np.int64),
            np.ascontiguousarray(plan.A_joint, float), np.ascontiguousarray(plan.ancestor_markers),
            plan.used_markers.astype(np.int64), np.ascontiguousarray(plan.A_marker, float), Q,
            plan.dof_segment.astype(np.int64), no_custom(S, Q) if custom is None else custom,
            np.ascontiguousarray(plan.coupled_moves, float).reshape(plan.n_coupled, plan.n_markers),
            np.ascontiguousarray(plan.A[(S + plan.n_markers) * plan.dim:], float).reshape(plan.n_coupled,
                                                                                       plan.n_params))


def tilt_tables(model) -> tuple | None:
    """The tilted hinges' arrays (:func:`~skelid.model.tilts.tilt_arrays`) and slots, or None."""
    if not model.axis_tilts:
        return None
    return tilt_arrays(model), np.array([[t[0], t[1], t[2]] for t in model.axis_tilts], dtype=np.int64)


if AVAILABLE:  # pragma: no branch
    _jit = numba.njit(cache=True, nogil=True, error_model="numpy")

    @_jit
    def _custom_segment(i, b, gb, g, pose, Ri, p, w, piv, vel, shift, E, tmp, ctab):
        """Segment ``i``'s custom joint for element ``b``: its frame ``Ri`` (in: the parent's), origin
        ``p[i]`` (in: the joint's place), its coordinates' axes ``w``, pivots, velocity terms ``vel``
        and the shift ``f(q) R_p a`` of each scaled coupled translation (``shift``), as
        :func:`skelid.model.kinematics._custom_joint` computes them.

        Kept as one flat loop nest on purpose, for the compiled speed (as :func:`_kinematics`).
        """
        (start, c_is_t, c_axis, c_k, c_fun, c_slot, c_skew, c_skew2, orient, has_orient, _hv,
         f_kind, f_scale, f_start, f_values, f_pstart, f_base, f_coef, fbase) = ctab
        for r in range(start[i], start[i + 1]):
            k = c_k[r]
            if k >= 0:
                for a in range(3):
                    w[k, a] = 0.0
                    vel[k, a] = 0.0
        for r in range(start[i], start[i + 1]):
            if not c_is_t[r]:
                continue
            k, f, sl = c_k[r], c_fun[r], c_slot[r]
            val, der, c = 0.0, 0.0, 1.0
            if f >= 0:
                val, der = function_value(f, pose[b, k] if k >= 0 else 0.0, f_kind, f_scale, f_start, f_values,
                                          f_pstart, f_base, f_coef)
                if sl >= 0:
                    c = g[gb, fbase + sl]
            for a in range(3):
                wa = Ri[a, 0] * c_axis[r, 0] + Ri[a, 1] * c_axis[r, 1] + Ri[a, 2] * c_axis[r, 2]
                if f < 0:
                    w[k, a] = wa
                    p[i, a] += wa * pose[b, k]
                    continue
                p[i, a] += wa * (c * val)
                if k >= 0:
                    vel[k, a] += wa * (c * der)
                if sl >= 0:
                    shift[sl, a] = wa * val
        for r in range(start[i], start[i + 1]):
            k = c_k[r]
            if k >= 0 and not (c_is_t[r] and c_fun[r] < 0):
                for a in range(3):
                    piv[k, a] = p[i, a]
        for r in range(start[i], start[i + 1]):
            if c_is_t[r]:
                continue
            k, f = c_k[r], c_fun[r]
            if f < 0:
                ang, der = pose[b, k], 1.0
            else:
                ang, der = function_value(f, pose[b, k] if k >= 0 else 0.0, f_kind, f_scale, f_start, f_values,
                                          f_pstart, f_base, f_coef)
            if k >= 0:
                for a in range(3):
                    w[k, a] += (Ri[a, 0] * c_axis[r, 0] + Ri[a, 1] * c_axis[r, 1] + Ri[a, 2] * c_axis[r, 2]) * der
            sk, ck = np.sin(ang), np.cos(ang)
            for a in range(3):
                for c in range(3):
                    E[a, c] = ((1.0 if a == c else 0.0) + sk * c_skew[r, a, c]) + (1.0 - ck) * c_skew2[r, a, c]
            for a in range(3):
                for c in range(3):
                    tmp[a, c] = Ri[a, 0] * E[0, c] + Ri[a, 1] * E[1, c] + Ri[a, 2] * E[2, c]
            for a in range(3):
                for c in range(3):
                    Ri[a, c] = tmp[a, c]
        if has_orient[i]:
            for a in range(3):
                for c in range(3):
                    tmp[a, c] = Ri[a, 0] * orient[i, 0, c] + Ri[a, 1] * orient[i, 1, c] + Ri[a, 2] * orient[i, 2, c]
            for a in range(3):
                for c in range(3):
                    Ri[a, c] = tmp[a, c]

    @_jit
    def _kinematics(g, pose, t_axis, t_daxis, tilt_slots, want_jac, parent, seg_dofs, n_dofs, is_t,
                    dof_axis, skew, skew2, dof_tilt, ms, moves, used_j, A_joint, anc, used_m, A_marker,
                    x, Jq, oq, Jt, ot, ctab, cmoves, Bc):
        """Markers ``x (B, M, 3)`` and, with ``want_jac``, ``dx/dq`` in ``Jq[..., oq:oq + Q]`` and ``dx/dtheta``
        in ``Jt[..., ot:ot + P]`` (``Jq`` and ``Jt`` may be one array).

        ``g (Bg, G)``, ``t_axis (Bg, T, 3)`` and ``t_daxis (Bg, T, 2, 3)`` have ``Bg`` = 1 or ``B``
        rows (one shared by every element, or one each); ``pose (B, Q)``; ``tilt_slots (T, 3)``
        the pose coordinate and the two parameters (-1: none) of each tilted hinge. Custom joints
        (``ctab``, :func:`~skelid.model.custom_tables.custom_arrays`) move their segment by
        :func:`_custom_segment`; ``cmoves (C, M)`` and ``Bc (C, P)``: which markers each scaled coupled
        translation moves and its factor's row of the geometry map.

        Kept as one flat loop nest on purpose: numba compiles it to tight loops over small fixed-size arrays,
        and splitting it into functions would cost calls and temporaries per segment and frame.
        """
        B, Q = pose.shape
        S = parent.shape[0]
        M = ms.shape[0]
        nT = t_axis.shape[1]
        P = A_joint.shape[2]
        R = np.empty((S, 3, 3))
        p = np.empty((S, 3))
        Rpar = np.empty((S, 3, 3))
        w = np.zeros((Q, 3))
        piv = np.zeros((Q, 3))
        omega = np.zeros((max(nT, 1), 2, 3))
        Ri = np.empty((3, 3))
        E = np.empty((3, 3))
        tmp = np.empty((3, 3))
        Kt = np.empty((3, 3))
        Kt2 = np.empty((3, 3))
        dw = np.empty((2, 3))
        Cum = np.empty((S, 3, P))
        c_start, has_orient, has_vel = ctab[0], ctab[9], ctab[10]
        C = cmoves.shape[0]
        vel = np.zeros((Q, 3))
        shift = np.zeros((C, 3))
        jmap = np.full(S, -1, dtype=np.int64)  # segment -> its row of A_joint, -1 if theta does not move it
        for jj in range(used_j.shape[0]):
            jmap[used_j[jj]] = jj
        shared_g = g.shape[0] == 1
        shared_t = t_axis.shape[0] == 1
        for b in range(B):
            gb = 0 if shared_g else b
            tb = 0 if shared_t else b
            for i in range(S):
                par = parent[i]
                for a in range(3):
                    for c in range(3):
                        v = (1.0 if a == c else 0.0) if par < 0 else R[par, a, c]
                        Ri[a, c] = v
                        Rpar[i, a, c] = v
                for a in range(3):
                    acc = 0.0
                    for c in range(3):
                        acc += Ri[a, c] * g[gb, 3 * i + c]
                    p[i, a] = (0.0 if par < 0 else p[par, a]) + acc
                n_std = n_dofs[i]
                if c_start[i] < c_start[i + 1] or has_orient[i]:  # a custom joint (a weld: its rotation only)
                    _custom_segment(i, b, gb, g, pose, Ri, p, w, piv, vel, shift, E, tmp, ctab)
                    n_std = 0
                for n in range(n_std):
                    k = seg_dofs[i, n]
                    qk = pose[b, k]
                    j = dof_tilt[k]
                    if is_t[k]:
                        for a in range(3):
                            acc = 0.0
                            for c in range(3):
                                acc += Ri[a, c] * dof_axis[k, c]
                            w[k, a] = acc
                            p[i, a] += acc * qk
                        continue
                    sk, ck = np.sin(qk), np.cos(qk)
                    for a in range(3):
                        piv[k, a] = p[i, a]
                    if j >= 0:  # a hinge whose axis depends on theta
                        for a in range(3):
                            acc = 0.0
                            for c in range(3):
                                acc += Ri[a, c] * t_axis[tb, j, c]
                            w[k, a] = acc
                        ax0, ax1, ax2 = t_axis[tb, j, 0], t_axis[tb, j, 1], t_axis[tb, j, 2]
                        Kt[0, 0], Kt[0, 1], Kt[0, 2] = 0.0, -ax2, ax1
                        Kt[1, 0], Kt[1, 1], Kt[1, 2] = ax2, 0.0, -ax0
                        Kt[2, 0], Kt[2, 1], Kt[2, 2] = -ax1, ax0, 0.0
                        for a in range(3):
                            for c in range(3):
                                acc = 0.0
                                for e in range(3):
                                    acc += Kt[a, e] * Kt[e, c]
                                Kt2[a, c] = acc
                        for u in range(2):
                            for a in range(3):
                                acc = 0.0
                                for c in range(3):
                                    acc += Ri[a, c] * t_daxis[tb, j, u, c]
                                dw[u, a] = acc
                            cr0 = w[k, 1] * dw[u, 2] - w[k, 2] * dw[u, 1]
                            cr1 = w[k, 2] * dw[u, 0] - w[k, 0] * dw[u, 2]
                            cr2 = w[k, 0] * dw[u, 1] - w[k, 1] * dw[u, 0]
                            omega[j, u, 0] = sk * dw[u, 0] + (1.0 - ck) * cr0
                            omega[j, u, 1] = sk * dw[u, 1] + (1.0 - ck) * cr1
                            omega[j, u, 2] = sk * dw[u, 2] + (1.0 - ck) * cr2
                        for a in range(3):
                            for c in range(3):
                                E[a, c] = ((1.0 if a == c else 0.0) + sk * Kt[a, c]) + (1.0 - ck) * Kt2[a, c]
                    else:
                        for a in range(3):
                            acc = 0.0
                            for c in range(3):
                                acc += Ri[a, c] * dof_axis[k, c]
                            w[k, a] = acc
                        for a in range(3):
                            for c in range(3):
                                E[a, c] = ((1.0 if a == c else 0.0) + sk * skew[k, a, c]) + (1.0 - ck) * skew2[k, a, c]
                    for a in range(3):
                        for c in range(3):
                            tmp[a, c] = Ri[a, 0] * E[0, c] + Ri[a, 1] * E[1, c] + Ri[a, 2] * E[2, c]
                    for a in range(3):
                        for c in range(3):
                            Ri[a, c] = tmp[a, c]
                for a in range(3):
                    for c in range(3):
                        R[i, a, c] = Ri[a, c]
            base = 3 * S
            for m in range(M):
                s = ms[m]
                for a in range(3):
                    x[b, m, a] = p[s, a] + (R[s, a, 0] * g[gb, base + 3 * m] + R[s, a, 1] * g[gb, base + 3 * m + 1]
                                            + R[s, a, 2] * g[gb, base + 3 * m + 2])
            if not want_jac:
                continue
            for m in range(M):
                for k in range(Q):
                    mv = moves[k, m]
                    if is_t[k]:
                        for a in range(3):
                            Jq[b, m, a, oq + k] = w[k, a] * mv
                    else:
                        r0 = x[b, m, 0] - piv[k, 0]
                        r1 = x[b, m, 1] - piv[k, 1]
                        r2 = x[b, m, 2] - piv[k, 2]
                        Jq[b, m, 0, oq + k] = (w[k, 1] * r2 - w[k, 2] * r1) * mv
                        Jq[b, m, 1, oq + k] = (w[k, 2] * r0 - w[k, 0] * r2) * mv
                        Jq[b, m, 2, oq + k] = (w[k, 0] * r1 - w[k, 1] * r0) * mv
                    if has_vel[k]:
                        for a in range(3):
                            Jq[b, m, a, oq + k] += vel[k, a] * mv
            # sum of R_wp A_j over the joints at and above each segment (parents come first, so this
            # adds the joints in the order of the numpy path's sum over the ancestors)
            for i in range(S):
                par = parent[i]
                jj = jmap[i]
                for a in range(3):
                    for c in range(P):
                        v = 0.0 if par < 0 else Cum[par, a, c]
                        if jj >= 0:
                            v = v + (Rpar[i, a, 0] * A_joint[jj, 0, c] + Rpar[i, a, 1] * A_joint[jj, 1, c]
                                     + Rpar[i, a, 2] * A_joint[jj, 2, c])
                        Cum[i, a, c] = v
            for m in range(M):
                s = ms[m]
                for a in range(3):
                    for c in range(P):
                        Jt[b, m, a, ot + c] = Cum[s, a, c]
            for mm in range(used_m.shape[0]):
                m = used_m[mm]
                s = ms[m]
                for a in range(3):
                    for c in range(P):
                        Jt[b, m, a, ot + c] += (R[s, a, 0] * A_marker[mm, 0, c] + R[s, a, 1] * A_marker[mm, 1, c]
                                           + R[s, a, 2] * A_marker[mm, 2, c])
            for cc in range(C):  # d x / d c = f(q) R_p a for the markers a scaled coupled translation moves
                for m in range(M):
                    mv = cmoves[cc, m]
                    if mv == 0.0:
                        continue
                    for a in range(3):
                        sa = shift[cc, a] * mv
                        for c in range(P):
                            Jt[b, m, a, ot + c] += sa * Bc[cc, c]
            for j in range(nT):
                k = tilt_slots[j, 0]
                for u in range(2):
                    kp = tilt_slots[j, 1 + u]
                    if kp < 0:
                        continue
                    o0, o1, o2 = omega[j, u, 0], omega[j, u, 1], omega[j, u, 2]
                    for m in range(M):
                        mv = moves[k, m]
                        r0 = x[b, m, 0] - piv[k, 0]
                        r1 = x[b, m, 1] - piv[k, 1]
                        r2 = x[b, m, 2] - piv[k, 2]
                        Jt[b, m, 0, ot + kp] += (o1 * r2 - o2 * r1) * mv
                        Jt[b, m, 1, ot + kp] += (o2 * r0 - o0 * r2) * mv
                        Jt[b, m, 2, ot + kp] += (o0 * r1 - o1 * r0) * mv


if AVAILABLE:  # pragma: no branch

    @_jit
    def _kinematics_planar(g, pose, want_jac, parent, seg_dofs, n_dofs, is_t, dof_axis, dof_seg, ms, moves,
                           used_j, A_joint, anc, used_m, A_marker, x, Jq, oq, Jt, ot):
        """The planar form of :func:`_kinematics`: one angle per segment (see ``_forward_planar``).

        Kept as one flat loop nest on purpose, for the compiled speed (as :func:`_kinematics`).
        """
        B, Q = pose.shape
        S = parent.shape[0]
        M = ms.shape[0]
        P = A_joint.shape[2]
        phi = np.zeros(S)
        cs = np.empty(S + 1)
        sn = np.empty(S + 1)
        p = np.empty((S + 1, 2))
        RA = np.empty((2, P))
        shared_g = g.shape[0] == 1
        for b in range(B):
            gb = 0 if shared_g else b
            cs[S], sn[S] = 1.0, 0.0
            p[S, 0], p[S, 1] = 0.0, 0.0
            for i in range(S):  # angles along the tree (parents first)
                par = parent[i]
                a = 0.0 if par < 0 else phi[par]
                for n in range(n_dofs[i]):
                    k = seg_dofs[i, n]
                    if not is_t[k]:
                        a = a + pose[b, k]
                phi[i] = a
            for i in range(S):
                cs[i] = np.cos(phi[i])
                sn[i] = np.sin(phi[i])
            for i in range(S):
                par = parent[i] if parent[i] >= 0 else S
                ux, uy = g[gb, 2 * i], g[gb, 2 * i + 1]
                for n in range(n_dofs[i]):
                    k = seg_dofs[i, n]
                    if is_t[k]:
                        ux += dof_axis[k, 0] * pose[b, k]
                        uy += dof_axis[k, 1] * pose[b, k]
                p[i, 0] = p[par, 0] + (cs[par] * ux - sn[par] * uy)
                p[i, 1] = p[par, 1] + (sn[par] * ux + cs[par] * uy)
            base = 2 * S
            for m in range(M):
                s = ms[m]
                rx, ry = g[gb, base + 2 * m], g[gb, base + 2 * m + 1]
                x[b, m, 0] = p[s, 0] + (cs[s] * rx - sn[s] * ry)
                x[b, m, 1] = p[s, 1] + (sn[s] * rx + cs[s] * ry)
            if not want_jac:
                continue
            for m in range(M):
                for k in range(Q):
                    mv = moves[k, m]
                    i = dof_seg[k]
                    if is_t[k]:
                        par = parent[i] if parent[i] >= 0 else S
                        a0, a1 = dof_axis[k, 0], dof_axis[k, 1]
                        Jq[b, m, 0, oq + k] = (cs[par] * a0 - sn[par] * a1) * mv
                        Jq[b, m, 1, oq + k] = (sn[par] * a0 + cs[par] * a1) * mv
                    else:
                        Jq[b, m, 0, oq + k] = -(x[b, m, 1] - p[i, 1]) * mv
                        Jq[b, m, 1, oq + k] = (x[b, m, 0] - p[i, 0]) * mv
            for m in range(M):
                for a in range(2):
                    for c in range(P):
                        Jt[b, m, a, ot + c] = 0.0
            for jj in range(used_j.shape[0]):
                s = used_j[jj]
                par = parent[s] if parent[s] >= 0 else S
                for c in range(P):
                    RA[0, c] = cs[par] * A_joint[jj, 0, c] + (-sn[par]) * A_joint[jj, 1, c]
                    RA[1, c] = sn[par] * A_joint[jj, 0, c] + cs[par] * A_joint[jj, 1, c]
                for m in range(M):
                    f = anc[jj, m]
                    if f != 0.0:
                        for a in range(2):
                            for c in range(P):
                                Jt[b, m, a, ot + c] += f * RA[a, c]
            for mm in range(used_m.shape[0]):
                m = used_m[mm]
                s = ms[m]
                for c in range(P):
                    Jt[b, m, 0, ot + c] += cs[s] * A_marker[mm, 0, c] + (-sn[s]) * A_marker[mm, 1, c]
                    Jt[b, m, 1, ot + c] += sn[s] * A_marker[mm, 0, c] + cs[s] * A_marker[mm, 1, c]


if AVAILABLE:  # pragma: no branch

    @_jit
    def _band_inverse_blocks(Ub, Q, T):
        """Diagonal ``(Q, Q)`` blocks of ``A^{-1}`` from ``A``'s banded Cholesky factor, one frame at a time.

        ``Ub[i, d] = U[i, i + d]`` (rows past the end zero). The same sweep as
        :func:`skelid.estimators.fit.joint._selected_inverse_by_blocks`, compiled: with frame
        ``I`` and the ``u`` rows ``F`` after it, ``Z_IF = -U_II^{-1} U_IF Z_FF`` and
        ``Z_II = U_II^{-1} (U_II^{-T} - U_IF Z_FI)``.

        Kept as one flat loop nest on purpose, for the compiled speed (as :func:`_kinematics`).
        """
        u = Ub.shape[1] - 1
        out = np.empty((T, Q, Q))
        W = np.zeros((u, u))
        Wn = np.empty((u, u))
        Ui = np.empty((Q, Q))
        UF = np.empty((Q, u))
        X = np.empty((Q, u))
        ZF = np.empty((Q, u))
        Y = np.empty((Q, Q))
        for t in range(T - 1, -1, -1):
            base = t * Q
            # U_IF (Q, u) and the inverse of the upper triangular U_II by back substitution
            for r in range(Q):
                for j in range(u):
                    d = Q + j - r
                    UF[r, j] = Ub[base + r, d] if d <= u else 0.0
            for c in range(Q - 1, -1, -1):
                for r in range(Q):
                    Ui[r, c] = 0.0
                Ui[c, c] = 1.0 / Ub[base + c, 0]
                for r in range(c - 1, -1, -1):
                    acc = 0.0
                    for k in range(r + 1, c + 1):
                        acc += Ub[base + r, k - r] * Ui[k, c]
                    Ui[r, c] = -acc / Ub[base + r, 0]
            for r in range(Q):  # X = U_IF W
                for j in range(u):
                    acc = 0.0
                    for k in range(u):
                        acc += UF[r, k] * W[k, j]
                    X[r, j] = acc
            for r in range(Q):  # Z_IF = -U_II^{-1} X
                for j in range(u):
                    acc = 0.0
                    for k in range(r, Q):
                        acc += Ui[r, k] * X[k, j]
                    ZF[r, j] = -acc
            for r in range(Q):  # Y = U_II^{-T} - U_IF Z_IF^T
                for c in range(Q):
                    acc = 0.0
                    for k in range(u):
                        acc += UF[r, k] * ZF[c, k]
                    Y[r, c] = Ui[c, r] - acc
            for r in range(Q):  # Z_II = U_II^{-1} Y, symmetrised
                for c in range(Q):
                    acc = 0.0
                    for k in range(r, Q):
                        acc += Ui[r, k] * Y[k, c]
                    out[t, r, c] = acc
            for r in range(Q):
                for c in range(r + 1, Q):
                    v = 0.5 * (out[t, r, c] + out[t, c, r])
                    out[t, r, c] = v
                    out[t, c, r] = v
            for r in range(Q):
                for c in range(Q):
                    Wn[r, c] = out[t, r, c]
                for j in range(u - Q):
                    Wn[r, Q + j] = ZF[r, j]
                    Wn[Q + j, r] = ZF[r, j]
            for i in range(u - Q):
                for j in range(u - Q):
                    Wn[Q + i, Q + j] = W[i, j]
            for i in range(u):
                for j in range(u):
                    W[i, j] = Wn[i, j]
        return out


def band_inverse_blocks(Ub: np.ndarray, Q: int, T: int) -> np.ndarray:
    """Diagonal ``(T, Q, Q)`` blocks of the inverse from the band of its Cholesky factor (compiled).

    Parameters
    ----------
    Ub : (T*Q + u, u + 1) float
        ``Ub[i, d] = U[i, i + d]`` with ``u >= Q`` superdiagonals.
    """
    return _band_inverse_blocks(np.ascontiguousarray(Ub, dtype=float), int(Q), int(T))


def _rows(a: np.ndarray, batch: tuple, tail: tuple) -> np.ndarray:
    """``a (..., *tail)`` as ``(1, *tail)`` when it has no batch axes, else ``(B, *tail)`` (contiguous)."""
    if a.ndim == len(tail):
        out = a.reshape((1,) + tail)
    elif a.shape[:-len(tail)] == batch:
        out = a.reshape((-1,) + tail)
    else:
        out = np.broadcast_to(a, batch + tail).reshape((-1,) + tail)
    if not out.flags.c_contiguous:
        out = np.ascontiguousarray(out)
    return out if out.flags.writeable else out.copy()  # one compiled signature: writeable arrays


def kinematics(model, plan, tables, tilts, g, pose, theta, want_jac: bool = True, stacked: bool = False):
    """Markers and, with ``want_jac``, both Jacobians by the compiled driver.

    Parameters
    ----------
    plan : KinematicsPlan
    tables : tuple
        :func:`plan_tables` of ``plan``.
    tilts : tuple or None
        :func:`tilt_tables` of the model.
    g : (..., G) float
        Geometry (``g_base + theta A^T``).
    pose : (..., Q) float
    theta : (..., P) float
        For the tilted hinges' axes.
    stacked : bool
        Return ``[dx/dtheta, dx/dq]`` as one ``(..., M, D, P + Q)`` array instead of the two.

    Returns
    -------
    x : (..., M, D)
    J_pose : (..., M, D, Q) or None
    J_theta : (..., M, D, P) or None
        Or, with ``stacked``, ``x`` and the ``(..., M, D, P + Q)`` array.
    """
    gb, pb = g.shape[:-1], pose.shape[:-1]  # g's batch axes are theta's
    batch = gb if gb == pb or not pb else pb if not gb else np.broadcast_shapes(gb, pb)
    B = math.prod(batch)
    M, Q, P, D = plan.n_markers, plan.n_pose, plan.n_params, plan.dim
    gg = _rows(g, batch, g.shape[-1:])
    qq = _rows(pose, batch, (Q,))
    if qq.shape[0] != B:
        qq = np.broadcast_to(qq, (B, Q)).copy()
    parent, seg_dofs, n_dofs, is_t, axis, skew, skew2, tilt, ms, moves, uj, Aj, anc, um, Am, _, dof_seg, ctab, \
        cmoves, Bc = tables
    x = np.empty((B, M, D))
    if not want_jac:
        Jq = Jt = np.empty((1, M, D, P + Q))
        oq, ot = P, 0
    elif stacked:
        Jq = Jt = np.empty((B, M, D, P + Q))
        oq, ot = P, 0
    else:
        Jq, Jt = np.empty((B, M, D, Q)), np.empty((B, M, D, P))
        oq = ot = 0
    if plan.planar:
        _kinematics_planar(gg, qq, bool(want_jac), parent, seg_dofs, n_dofs, is_t, axis, dof_seg, ms, moves, uj,
                           Aj, anc, um, Am, x, Jq, oq, Jt, ot)
    else:
        if tilts is not None:
            ax, dax = tilted_axes_from(tilts[0], theta)
            t_axis, t_daxis = _rows(ax, batch, ax.shape[-2:]), _rows(dax, batch, dax.shape[-3:])
            slots = tilts[1]
        else:
            t_axis, t_daxis, slots = _NO_TILT
        _kinematics(gg, qq, t_axis, t_daxis, slots, bool(want_jac), parent, seg_dofs, n_dofs, is_t, axis, skew,
                    skew2, tilt, ms, moves, uj, Aj, anc, um, Am, x, Jq, oq, Jt, ot, ctab, cmoves, Bc)
    x = x.reshape(batch + (M, D))
    if not want_jac:
        return x, None, None
    if stacked:
        return x, Jq.reshape(batch + (M, D, P + Q))
    return x, Jq.reshape(batch + (M, D, Q)), Jt.reshape(batch + (M, D, P))


_NO_TILT = (np.zeros((1, 0, 3)), np.zeros((1, 0, 2, 3)), np.zeros((0, 3), dtype=np.int64))


# ------------------------------------------------------------------ which path, and warming the cache
def _example_args(planar) -> tuple:
    """Arguments with the types of every real call of a driver (their values are never used)."""
    f, i = np.zeros, np.int64
    if planar == "band":
        Ub = f((3, 3))
        Ub[:, 0] = 1.0
        return Ub, 1, 1
    if planar:
        return (f((1, 4)), f((1, 1)), True, np.full(1, -1, i), np.zeros((1, 1), i), np.ones(1, i),
                np.zeros(1, np.bool_), f((1, 2)), np.zeros(1, i), np.zeros(1, i), f((1, 1)), np.zeros(0, i),
                f((0, 2, 1)), f((0, 1)), np.zeros(0, i), f((0, 2, 1)), f((1, 1, 2)), f((1, 1, 2, 1)), 0,
                f((1, 1, 2, 1)), 0)
    return (f((1, 6)), f((1, 1)), f((1, 0, 3)), f((1, 0, 2, 3)), np.zeros((0, 3), i), True,
            np.full(1, -1, i), np.zeros((1, 1), i), np.ones(1, i), np.zeros(1, np.bool_), f((1, 3)),
            f((1, 3, 3)), f((1, 3, 3)), np.full(1, -1, i), np.zeros(1, i), f((1, 1)), np.zeros(0, i),
            f((0, 3, 1)), f((0, 1)), np.zeros(0, i), f((0, 3, 1)), f((1, 1, 3)), f((1, 1, 3, 1)), 0,
            f((1, 1, 3, 1)), 0, no_custom(1, 1), f((0, 1)), f((0, 1)))


def _driver(planar):
    if planar == "band":
        return _band_inverse_blocks
    return _kinematics_planar if planar else _kinematics


def _cached(planar: bool | str) -> bool:
    """Whether numba's disk cache holds the driver (True where its index cannot be read)."""
    return in_disk_cache(_driver(planar), tuple(numba.typeof(a) for a in _example_args(planar)))


def compiled(planar: bool | str) -> bool:
    """Whether the driver is already compiled (or loaded) in this process."""
    return AVAILABLE and bool(_driver(planar).signatures)


def ready(planar: bool | str) -> bool:
    """Whether a compiled driver can run now without compiling in this process.

    ``planar``: True for the planar kinematics, False for the spatial ones,
    ``"band"`` for the selected inversion of :func:`band_inverse_blocks`.

    False without numba (or with ``SKELID_NUMBA=0``); with ``SKELID_NUMBA=wait``
    always True (compiling first if the cache is cold). Otherwise True once
    cached; while it is not, starts its compilation in the background (once) and
    answers False, looking at the cache again at most every half second.
    """
    return AVAILABLE and _gate.ready(planar)


def warm(planar: bool | str, wait: bool = True, timeout: float = 600.0) -> bool:
    """Compile a driver into numba's disk cache in a separate process; whether it is cached."""
    if not AVAILABLE:
        return False
    code = f"from skelid.model._fk_kernel import _compile_here; _compile_here({planar!r})"
    return compile_in_background(_gate.warming, planar, code, lambda: _cached(planar), wait, timeout)


# the module's names are looked up at each call (a test may replace them)
_gate = Gate(lambda k: compiled(k), lambda k: _cached(k), lambda k, wait: warm(k, wait=wait), lambda: MODE)


def _compile_here(planar: bool | str) -> None:
    """Compile a driver into the cache in this process (one process at a time)."""
    with compile_lock("fk-" + (planar if planar == "band" else "planar" if planar else "spatial")):
        if not _cached(planar):
            _driver(planar)(*_example_args(planar))
