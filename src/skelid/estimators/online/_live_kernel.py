"""The live Gaussian form's frame, compiled (numba): linearisation, pose fit, update and mean in one call.

The live session's Gaussian form linearises each frame at ``(theta, q)``:
``x(theta, q)``, ``J = dx/dq`` and ``K = dx/dtheta``. For one frame the numpy
:func:`~skelid.model.kinematics.marker_jacobian` spends its time in Python
overheads of many tiny array operations; this module computes the same three
arrays in one compiled call, from the forward kinematics of the compiled pose
kernel (:mod:`skelid.estimators.fit._lm_kernel`, at a batch of one) and

.. math::

    J_{m,k} = w_k \\times (x_m - p_k) \\ (\\text{rotation}),\\quad w_k \\ (\\text{translation}),\\qquad
    K_m = \\sum_{j \\ni m} R_{\\mathrm{parent}(j)} A_j + R_{\\mathrm{seg}(m)} A_m

(``w_k`` the world axis and ``p_k`` a point on it; ``A_j``, ``A_m`` the
columns of the linear geometry map for joint ``j`` and marker ``m``; in 2-D the
rotation column is ``(-(x - p)_y, (x - p)_x)``). The results equal the numpy
path's to rounding (the kernel's sine and cosine are within 1 ulp of the C
library's).

:func:`step` is a whole frame of :class:`skelid.live.Session`'s Gaussian
form in one call, so that a push spends its time in arithmetic rather than
in Python glue: the pose fit at the current mean (the pose kernel's
Levenberg-Marquardt driver from the constant-velocity prediction), the
linearisation, each marker's residual against the outlier limit (a frame
with a marker beyond it is handed back to the general path, which leaves the
marker out), the pose's jump against the motion model (likewise), the rows
of the frame and of the motion model stacked under the square-root
information and triangularised again by Householder reflections
(:func:`skelid.live.absorb`), and the mean of theta and of the newest pose
(:func:`skelid.live.solve_mean`), linearised again at the filtered pose
up to ``n_iter`` times with a motion model, until the filtered pose moves the
markers by less than :data:`RELINEARISE_TOL` of their noise (a pass that moves
them further than the one before is not taken: the passes diverge). Its numbers equal the numpy path's to
rounding (the square root's rows may differ in sign from LAPACK's; the
information they carry does not).

Models with tilted hinge axes, coupled or custom joints are not covered
(:func:`tables` answers None): the numpy path linearises them. Like the pose
kernel, the functions are compiled into numba's disk cache in a separate process
(:func:`ready` starts it and answers False meanwhile), so a session never waits
for the compiler; ``SKELID_NUMBA=0`` disables it.
"""

from __future__ import annotations

import subprocess
import time

import numpy as np

from skelid._numba import AVAILABLE  # the path switch shared by every compiled kernel
from skelid.estimators.fit import _lm_kernel

#: the re-linearisations at the filtered pose stop once that pose moves the frame's markers by less than this
#: share of their noise (root sum of squares over the frame's coordinates): an iterated extended Kalman update
RELINEARISE_TOL = 0.1


def tables(ws) -> tuple | None:
    """The arguments :func:`linearise` needs besides ``g`` and ``q`` (None: the model is not covered)."""
    plan = ws.plan
    if plan.n_tilts or plan.n_coupled or plan.has_custom:
        return None
    base = _lm_kernel.plan_arrays(plan)
    if base is None:
        return None
    parent, dof_start, is_t, axis, skew, skew2, ms, moves, nz, tilt, planar = base
    S, M = plan.n_segments, plan.n_markers
    jpar = np.array([parent[j] for j in plan.used_joints], dtype=np.int64)  # S: the ground
    mslot = np.full(M, -1, dtype=np.int64)  # row of each marker in A_marker, -1 if theta does not move it
    mslot[plan.used_markers] = np.arange(plan.used_markers.size)
    return (plan.dim, S, M, parent, dof_start, is_t, axis, skew, skew2, ms, moves, nz, tilt, bool(planar),
            jpar, np.ascontiguousarray(plan.A_joint, dtype=float),
            np.ascontiguousarray(plan.ancestor_markers, dtype=float), mslot,
            np.ascontiguousarray(plan.A_marker, dtype=float))


if AVAILABLE:  # pragma: no branch
    from skelid.estimators.fit._lm_kernel import (
        _empty_custom,
        _kinematics_planar,
        _kinematics_spatial,
        _lm_planar,
        _lm_spatial,
        _workspace,
    )

    @_lm_kernel._jit
    def linearise(g, q, D, S, M, parent, dof_start, is_t, axis, skew, skew2, ms, moves, nz, tilt, planar,
                  jpar, A_joint, anc, mslot, A_marker):
        """``x (M, D)``, ``J (M, D, Q)``, ``K (M, D, P)`` at geometry ``g (G, 1)`` and pose ``q (Q, 1)``."""
        Q = q.shape[0]
        P = A_joint.shape[2] if A_joint.shape[0] else A_marker.shape[2]
        x = np.empty((M, D))
        J = np.zeros((M, D, Q))
        K = np.zeros((M, D, P))
        _linearise_into(g, q, D, S, M, parent, dof_start, is_t, axis, skew, skew2, ms, moves, nz, tilt, planar,
                        jpar, A_joint, anc, mslot, A_marker, x, J, K)
        return x, J, K

    @_lm_kernel._inline
    def _linearise_into(g, q, D, S, M, parent, dof_start, is_t, axis, skew, skew2, ms, moves, nz, tilt, planar,
                        jpar, A_joint, anc, mslot, A_marker, x, J, K):
        """:func:`linearise` into ``x``, ``J`` and ``K`` (the last two zero on entry)."""
        Q = q.shape[0]
        P = K.shape[2]
        (cost, cost_new, lam, ok, bad, JtJ, Jtr, L, dinv, step, qn, R, Ri, E, ang, cs, sn, p, w, pivot, xk, r,
         Jk, acc, ux, uy, A1, r1, s1, ridge, nf, chk) = _workspace(Q, 1, S, M, D, 0.0, not planar)
        t_axis, t_skew, t_skew2 = np.zeros((0, 3, 1)), np.zeros((0, 3, 3, 1)), np.zeros((0, 3, 3, 1))
        if planar:
            _kinematics_planar(g, q, D, S, M, parent, dof_start, is_t, axis, skew, skew2, ms, R, Ri, E, ang, cs,
                               sn, p, w, pivot, xk, ux, uy, tilt, t_axis, t_skew, t_skew2)
        else:
            _kinematics_spatial(g, q, D, S, M, parent, dof_start, is_t, axis, skew, skew2, ms, R, Ri, E, ang,
                                cs, sn, p, w, pivot, xk, ux, uy, tilt, t_axis, t_skew, t_skew2, np.zeros((Q, 3, 1)),
                                np.empty((2, 1)), _empty_custom(S, Q))
        for m in range(M):
            for a in range(D):
                x[m, a] = xk[m, a, 0]
            for k in range(Q):
                if moves[k, m] == 0.0:
                    continue
                if is_t[k]:
                    for a in range(D):
                        J[m, a, k] = w[k, a, 0]
                elif D == 2:
                    J[m, 0, k] = -(x[m, 1] - pivot[k, 1, 0])
                    J[m, 1, k] = x[m, 0] - pivot[k, 0, 0]
                else:
                    v0 = x[m, 0] - pivot[k, 0, 0]
                    v1 = x[m, 1] - pivot[k, 1, 0]
                    v2 = x[m, 2] - pivot[k, 2, 0]
                    J[m, 0, k] = w[k, 1, 0] * v2 - w[k, 2, 0] * v1
                    J[m, 1, k] = w[k, 2, 0] * v0 - w[k, 0, 0] * v2
                    J[m, 2, k] = w[k, 0, 0] * v1 - w[k, 1, 0] * v0
        Rm = np.empty((D, D))
        for u in range(jpar.size):  # joints whose position depends on theta: R_parent A_joint
            _orientation(jpar[u], D, planar, R, cs, sn, Rm)
            for m in range(M):
                if anc[u, m] == 0.0:
                    continue
                for a in range(D):
                    for c in range(P):
                        acc0 = 0.0
                        for e in range(D):
                            acc0 += Rm[a, e] * A_joint[u, e, c]
                        K[m, a, c] += anc[u, m] * acc0
        for m in range(M):  # markers whose placement depends on theta: R_seg A_marker
            i = mslot[m]
            if i < 0:
                continue
            _orientation(ms[m], D, planar, R, cs, sn, Rm)
            for a in range(D):
                for c in range(P):
                    acc0 = 0.0
                    for e in range(D):
                        acc0 += Rm[a, e] * A_marker[i, e, c]
                    K[m, a, c] += acc0

    @_lm_kernel._inline
    def _orientation(s, D, planar, R, cs, sn, out):
        """World orientation ``out (D, D)`` of segment ``s`` (``S``: the ground) after the kinematics."""
        if planar:
            out[0, 0] = cs[s, 0]
            out[0, 1] = -sn[s, 0]
            out[1, 0] = sn[s, 0]
            out[1, 1] = cs[s, 0]
        else:
            for a in range(D):
                for c in range(D):
                    out[a, c] = R[s, a, c, 0]


    @_lm_kernel._jit
    def step(y, q0, theta, root, rhs, poses, hdiag, rss, n_obs, n_used, weight, n_iter, sigma, fallback, floor, limit,
             s2_now, gate, allow, rot, mu0, L0, lo, hi, g_base, A_geo, D, S, M, parent, dof_start, is_t, axis,
             skew, skew2, ms, moves, nz, tilt, planar, jpar, A_joint, anc, mslot, A_marker):
        """One frame of the live Gaussian form (see :mod:`skelid.live`): pose fit, screen, update, mean.

        Its one long, flat body is deliberate: numba compiles it for speed, and splitting it into
        helpers would slow this hot path down.

        Parameters
        ----------
        y : (M, D) float
            The frame, NaN where a marker is missing (at least one pose's worth present).
        q0 : (Q,) float
            Where the pose fit starts (the constant-velocity prediction).
        theta : (P,) float
            The current mean, where the frame is linearised.
        root, rhs, poses, hdiag, rss, n_obs, n_used
            The state (:class:`skelid.live.GaussianState`; ``poses`` holds at least one pose).
        weight : (Q,) float
            The motion model's weight of each pose coordinate (all 0: none).
        n_iter : int
            Re-linearisations at the filtered pose at most (with a motion model; they stop once the pose
            moves the markers by less than :data:`RELINEARISE_TOL` of their noise).
        sigma : float
            Marker noise, or negative to estimate it from the residuals.
        fallback : float
            Noise variance while the residuals cannot say.
        floor : float
            The least noise variance (:func:`skelid.live.noise_floor`).
        limit : float
            Marker residual beyond which the frame is handed back (``inf``: no screening).
        s2_now : float
            The noise variance before this frame.
        gate : float
            With a motion model and three held poses: the bound on the pose innovation
            (:func:`skelid.live.pose_jump`) beyond which the frame is handed back (status ``M``;
            ``inf``: no check).
        allow : (Q,) float
            The allowance for real movement in the pose-jump check (:func:`skelid.live.pose_jump`).
        rot : (Q,) bool
            Rotational pose coordinates (kept continuous with the previous pose).
        mu0, L0, lo, hi
            The prior's Gaussian summary (:func:`skelid.live.prior_moments`).
        g_base, A_geo
            The geometry map ``g = g_base + A_geo theta``.

        Returns
        -------
        status : int
            -1 when the frame was folded in; otherwise the index of the marker beyond ``limit``, or ``M``
            when the pose jumps beyond the motion model (nothing folded in: the caller updates by the
            general path).
        root, rhs, mean, pose_mean, poses, hdiag, rss, n_obs, n_used
            The new state.
        q : (Q,) float
            The frame's fitted pose.
        resid : (M,) float
            Distance of each marker from the model at ``(theta, q)`` (NaN where missing).
        jump : float
            The pose's jump statistic (:func:`skelid.live.pose_jump`), or -1 where it was not computed.
        """
        Q = q0.size
        P = theta.size
        G = g_base.size
        g = np.empty((G, 1))
        for i in range(G):
            v = g_base[i]
            for c in range(P):
                v += A_geo[i, c] * theta[c]
            g[i, 0] = v
        y0 = np.empty((M, D, 1))
        mask = np.empty((M, 1))
        n_present = 0
        for m in range(M):
            ok = True
            for a in range(D):
                if not np.isfinite(y[m, a]):
                    ok = False
            mask[m, 0] = 1.0 if ok else 0.0
            n_present += 1 if ok else 0
            for a in range(D):
                y0[m, a, 0] = y[m, a] if ok else 0.0
        qq = np.empty((Q, 1))
        for k in range(Q):
            qq[k, 0] = q0[k]
        t_axis, t_skew, t_skew2 = np.zeros((0, 3, 1)), np.zeros((0, 3, 3, 1)), np.zeros((0, 3, 3, 1))
        if planar:
            _lm_planar(g, y0, mask, qq, 10, 1e-10, 1e-3, False, D, S, M, parent, dof_start, is_t, axis, skew,
                       skew2, ms, moves, nz, tilt, t_axis, t_skew, t_skew2)
        else:
            _lm_spatial(g, y0, mask, qq, 10, 1e-10, 1e-3, False, D, S, M, parent, dof_start, is_t, axis, skew,
                        skew2, ms, moves, nz, tilt, t_axis, t_skew, t_skew2)
        x = np.empty((M, D))
        J = np.zeros((M, D, Q))
        K = np.zeros((M, D, P))
        _linearise_into(g, qq, D, S, M, parent, dof_start, is_t, axis, skew, skew2, ms, moves, nz, tilt, planar,
                        jpar, A_joint, anc, mslot, A_marker, x, J, K)
        resid = np.empty(M)
        worst, big = -1, -np.inf
        for m in range(M):
            acc = 0.0
            for a in range(D):
                d = y[m, a] - x[m, a]
                acc += d * d
            resid[m] = np.sqrt(acc)
            if mask[m, 0] > 0.0 and resid[m] > big:
                worst, big = m, resid[m]
        q = np.empty(Q)
        for k in range(Q):
            q[k] = qq[k, 0]
        if worst >= 0 and big > limit:
            return (worst, root, rhs, theta, q, poses, hdiag, rss, n_obs, n_used, q, resid, -1.0)
        k_held = poses.shape[0]
        if k_held:  # angles continuous with the previous pose, for the motion model
            for k in range(Q):
                if rot[k]:
                    last = poses[k_held - 1, k]
                    q[k] = last + (q[k] - last + np.pi) % (2.0 * np.pi) - np.pi
        N = n_present * D
        r, Jq, Jt = _rows(y, x, J, K, mask, N)
        jump = -1.0
        motion = False
        for k in range(Q):
            if weight[k] > 0.0:
                motion = True
        if motion and k_held == 3:
            jump = _jump(q, poses, Jq, hdiag, n_used, weight, s2_now, allow)
            if jump > gate:
                return (M, root, rhs, theta, q, poses, hdiag, rss, n_obs, n_used, q, resid, jump)
        rr = 0.0
        for i in range(N):
            rr += r[i] * r[i]
        rss1, n_obs1, n_used1 = rss + rr, n_obs + N, n_used + 1
        s2 = _sigma2(rss1, n_obs1, n_used1, Q, P, sigma, fallback, floor)
        root1, rhs1, poses1, hdiag1 = _absorb(root, rhs, poses, hdiag, n_used, r, Jq, Jt, q, theta, weight)
        mean, pose_mean = _solve_mean(root1, rhs1, poses1.shape[0], Q, mu0, L0, lo, hi, s2, motion)
        if not motion:
            pose_mean = q.copy()
        last = np.inf
        for _ in range(n_iter if motion else 0):  # iterated: linearised again at the filtered pose
            ql = pose_mean
            for k in range(Q):
                qq[k, 0] = ql[k]
            J[:] = 0.0
            K[:] = 0.0
            _linearise_into(g, qq, D, S, M, parent, dof_start, is_t, axis, skew, skew2, ms, moves, nz, tilt,
                            planar, jpar, A_joint, anc, mslot, A_marker, x, J, K)
            r2, Jq2, Jt2 = _rows(y, x, J, K, mask, N)
            root2, rhs2, poses2, hdiag2 = _absorb(root, rhs, poses, hdiag, n_used, r2, Jq2, Jt2, ql, theta,
                                                  weight)
            mean2, pose_mean2 = _solve_mean(root2, rhs2, poses2.shape[0], Q, mu0, L0, lo, hi, s2, True)
            moved = 0.0  # how far the pose's change moves the markers, squared (first order)
            for i in range(N):
                acc = 0.0
                for k in range(Q):
                    acc += Jq2[i, k] * (pose_mean2[k] - ql[k])
                moved += acc * acc
            if moved > last:  # the passes move further each time: they diverge, the last one is kept
                break
            root1, rhs1, poses1, hdiag1, mean, pose_mean = root2, rhs2, poses2, hdiag2, mean2, pose_mean2
            if moved <= RELINEARISE_TOL * RELINEARISE_TOL * s2:
                break
            last = moved
        return (-1, root1, rhs1, mean, pose_mean, poses1, hdiag1, rss1, n_obs1, n_used1, q, resid, jump)

    @_lm_kernel._inline
    def _rows(y, x, J, K, mask, N):
        """The present markers' residual ``(N,)`` and Jacobian rows ``(N, Q)``, ``(N, P)``, in marker order."""
        M, D, Q = J.shape
        P = K.shape[2]
        r = np.empty(N)
        Jq = np.empty((N, Q))
        Jt = np.empty((N, P))
        i = 0
        for m in range(M):
            if mask[m, 0] == 0.0:
                continue
            for a in range(D):
                r[i] = y[m, a] - x[m, a]
                for k in range(Q):
                    Jq[i, k] = J[m, a, k]
                for c in range(P):
                    Jt[i, c] = K[m, a, c]
                i += 1
        return r, Jq, Jt

    @_lm_kernel._inline
    def _jump(q, poses, Jq, hdiag, n_used, weight, s2, allow):
        """As :func:`skelid.live.pose_jump`."""
        Q = q.size
        JtJ = Jq.T @ Jq
        tr = 0.0
        for k in range(Q):
            tr += JtJ[k, k]
        ridge = 1e-9 * max(tr / Q, 1e-300)
        for k in range(Q):
            JtJ[k, k] += ridge
        V = 21.0 * s2 * np.linalg.inv(JtJ)
        nu = np.empty(Q)
        for k in range(Q):
            V[k, k] += max(s2 / max(weight[k] * hdiag[k] / max(n_used, 1), 1e-300), allow[k])
            nu[k] = q[k] - (3.0 * poses[2, k] - 3.0 * poses[1, k] + poses[0, k])
        z = np.linalg.solve(V, nu)
        out = 0.0
        for k in range(Q):
            out += nu[k] * z[k]
        return out

    @_lm_kernel._inline
    def _sigma2(rss, n_obs, n_used, Q, P, sigma, fallback, floor):
        """As :func:`skelid.live._sigma2` (``sigma < 0``: estimated)."""
        if sigma >= 0.0:
            return max(sigma * sigma, floor)
        dof = n_obs - Q * n_used - P
        if dof >= 3:
            return max(rss / dof, floor)
        return fallback

    @_lm_kernel._inline
    def _absorb(root, rhs, poses, hdiag, n_used, r, Jq, Jt, q, theta, weight):
        """As :func:`skelid.live.absorb` with data: ``(root, rhs, poses, hdiag)`` of the new state.

        Its one long, flat body is deliberate: numba compiles it for speed, and splitting it into
        helpers would slow this hot path down.

        The stacked rows are triangularised by Householder reflections that touch
        only the rows with a non-zero in the column being eliminated (the old
        square root is triangular already), the same factor as LAPACK's up to the
        signs of its rows.
        """
        P = theta.size
        k, Q = poses.shape
        n0 = rhs.size
        n = n0 + Q
        kq = k * Q
        N = r.size
        held = 3
        n_rows = n0 + N + (Q if k == held else 0)
        m_rows = max(n_rows, n + 1)
        A = np.zeros((m_rows, n + 1))
        for i in range(n0):
            for j in range(kq):
                A[i, j] = root[i, j]
            for j in range(P):
                A[i, n - P + j] = root[i, kq + j]
            A[i, n] = rhs[i]
        row = n0
        hd = hdiag.copy()
        for i in range(N):
            b = r[i]
            for j in range(Q):
                A[row + i, kq + j] = Jq[i, j]
                b += Jq[i, j] * q[j]
                hd[j] += Jq[i, j] * Jq[i, j]
            for j in range(P):
                A[row + i, n - P + j] = Jt[i, j]
                b += Jt[i, j] * theta[j]
            A[row + i, n] = b
        row += N
        used = n_used + 1
        motion = False
        for i in range(Q):
            if weight[i] > 0.0:
                motion = True
        if k == held and motion:
            d3 = (-1.0, 3.0, -3.0, 1.0)
            for i in range(Q):
                sw = np.sqrt(weight[i] * hd[i] / used)
                for j in range(held + 1):
                    A[row + i, j * Q + i] = d3[j] * sw
        _householder(A, n)
        s = Q if k == held else 0
        n1 = n - s
        root1 = np.zeros((n1, n1))
        rhs1 = np.empty(n1)
        for i in range(n1):
            for j in range(i, n1):
                root1[i, j] = A[s + i, s + j]
            rhs1[i] = A[s + i, n]
        k1 = k if k == held else k + 1
        poses1 = np.empty((k1, Q))
        for i in range(k1 - 1):
            for j in range(Q):
                poses1[i, j] = poses[i + k - k1 + 1, j]
        for j in range(Q):
            poses1[k1 - 1, j] = q[j]
        return root1, rhs1, poses1, hd

    @_lm_kernel._inline
    def _householder(A, n):
        """Upper-triangularise the first ``n`` columns of ``A`` in place (``R`` in the upper triangle;
        the columns after ``n`` transformed alike)."""
        m_rows, n_cols = A.shape
        rows = np.empty(m_rows, dtype=np.int64)
        v = np.empty(m_rows)
        for j in range(min(n, m_rows)):
            na = 0
            norm2 = 0.0
            for i in range(j, m_rows):
                a = A[i, j]
                if a != 0.0 or i == j:
                    rows[na] = i
                    v[na] = a
                    na += 1
                    norm2 += a * a
            if na == 1 or norm2 == 0.0:
                continue  # nothing below the diagonal to eliminate
            alpha = -np.sqrt(norm2) if v[0] >= 0.0 else np.sqrt(norm2)
            v[0] -= alpha
            vtv = norm2 - A[j, j] * A[j, j] + v[0] * v[0]
            for c in range(j + 1, n_cols):
                dot = 0.0
                for t in range(na):
                    dot += v[t] * A[rows[t], c]
                f = 2.0 * dot / vtv
                if f != 0.0:
                    for t in range(na):
                        A[rows[t], c] -= f * v[t]
            A[j, j] = alpha
            for t in range(1, na):
                A[rows[t], j] = 0.0

    @_lm_kernel._inline
    def _solve_mean(root, rhs, k, Q, mu0, L0, lo, hi, s2, pose):
        """As :func:`skelid.live.solve_mean`: theta ``(P,)`` (clipped to the bounds) and the newest pose ``(Q,)``."""
        P = mu0.size
        n = rhs.size
        t0 = n - P
        Lam = np.empty((P, P))
        eta = np.empty(P)
        for a in range(P):
            for b in range(P):
                acc = 0.0
                for i in range(P):
                    acc += root[t0 + i, t0 + a] * root[t0 + i, t0 + b]
                Lam[a, b] = acc / s2 + L0[a, b]
            acc = 0.0
            for i in range(P):
                acc += root[t0 + i, t0 + a] * rhs[t0 + i]
            e = acc / s2
            for b in range(P):
                e += L0[a, b] * mu0[b]
            eta[a] = e
        theta = np.linalg.solve(Lam, eta)
        for a in range(P):
            theta[a] = min(max(theta[a], lo[a]), hi[a])
        qn = np.zeros(Q)
        if k and pose:
            a0 = (k - 1) * Q
            big = 1e-300
            for i in range(Q):
                big = max(big, abs(root[a0 + i, a0 + i]))
            eps = 1e-12 * big
            for i in range(Q - 1, -1, -1):
                acc = rhs[a0 + i]
                for c in range(P):
                    acc -= root[a0 + i, t0 + c] * theta[c]
                for j in range(i + 1, Q):
                    acc -= root[a0 + i, a0 + j] * qn[j]
                qn[i] = acc / (root[a0 + i, a0 + i] + eps)
        return theta, qn


# ------------------------------------------------------------------ compiled in the background, as the pose kernel
_found: dict[bool, bool] = {}
_last_check: dict[bool, float] = {}
_warming: dict[bool, subprocess.Popen] = {}


def _example_args(planar: bool) -> tuple:
    """Arguments of :func:`linearise` with the types of every real call (values never used)."""
    f, i, b = np.zeros, np.int64, np.bool_
    return (f((4, 1)), f((1, 1)), 2, 1, 1, np.zeros(2, i), np.zeros(2, i), np.zeros(1, b), f((1, 3)),
            f((1, 3, 3)), f((1, 3, 3)), np.zeros(1, i), f((1, 1)), np.zeros((1, 3), b), np.zeros(1, i), planar,
            np.zeros(0, i), f((0, 2, 1)), f((0, 1)), np.full(1, -1, i), f((0, 2, 1)))


def _step_example_args() -> tuple:
    """Arguments of :func:`step` with the types of every real call (values never used)."""
    f = np.zeros
    state = (f((2, 2)), f(2), f((1, 1)), f(1), 0.0, 0, 0)  # root, rhs, poses, hdiag, rss, n_obs, n_used
    # weight, n_iter, sigma, fallback, floor, limit, s2_now, gate, allow, rot
    settings = (f(1), 1, -1.0, 1.0, 0.0, np.inf, 1.0, 1.0, f(1), np.zeros(1, np.bool_))
    prior = (f(1), f((1, 1)), f(1), f(1))
    return (f((1, 2)), f(1), f(1), *state, *settings, *prior, f(4), f((4, 1)), *_example_args(True)[2:])


def _signatures() -> dict:
    """The two compiled functions and the signature of their real calls."""
    return {linearise: tuple(numba_typeof(a) for a in _example_args(True)),
            step: tuple(numba_typeof(a) for a in _step_example_args())}


def _cached() -> bool:
    """Whether numba's disk cache holds :func:`linearise` and :func:`step` for this machine and source."""
    try:
        for disp, sig in _signatures().items():
            key = disp._cache._index_key(sig, disp.targetctx.codegen())
            if disp._cache._cache_file._load_index().get(key) is None:
                return False
        return True
    except Exception:  # noqa: BLE001 - numba internals changed: compile when first called
        return True


def numba_typeof(a):
    import numba

    return numba.typeof(a)


def ready() -> bool:
    """Whether :func:`linearise` and :func:`step` can run now without compiling in this process.

    As :func:`skelid.estimators.fit._lm_kernel.ready`: False without numba (or with
    ``SKELID_NUMBA=0``); with ``SKELID_NUMBA=wait`` compiles first if need be;
    otherwise starts the compilation in a background process (once) and
    answers False until numba's cache holds it.
    """
    if not AVAILABLE:
        return False
    if _found.get(True) or (linearise.signatures and step.signatures) or _lm_kernel.MODE == "compile":
        return True
    if _lm_kernel.MODE == "wait":
        if not _cached():
            warm(wait=True)
        return True
    now = time.monotonic()
    if now - _last_check.get(True, -np.inf) < 0.5:
        return False
    _last_check[True] = now
    if _cached():
        _found[True] = True
        return True
    warm(wait=False)
    return False


def warm(wait: bool = True, timeout: float = 600.0) -> bool:
    """Compile :func:`linearise` and :func:`step` into numba's disk cache in a separate process."""
    if not AVAILABLE:
        return False
    code = "from skelid.estimators.online._live_kernel import _compile_here; _compile_here()"
    return _lm_kernel.compile_in_background(_warming, True, code, _cached, wait, timeout)


def _compile_here() -> None:
    """Compile (or load) :func:`linearise` and :func:`step` in this process (numba's cache keeps them),
    unless another process has (one at a time)."""
    import os
    import tempfile
    import zlib

    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX: no lock
        fcntl = None
    where = zlib.crc32(os.path.abspath(__file__).encode())  # one lock per installed copy
    name = f"skelid-numba-live-{getattr(os, 'getuid', lambda: 0)()}-{where:x}.lock"
    with open(os.path.join(tempfile.gettempdir(), name), "a") as fh:
        if fcntl is not None:
            fcntl.flock(fh, fcntl.LOCK_EX)  # released when the file closes
        if not _cached():
            for disp, sig in _signatures().items():
                disp.compile(sig)
