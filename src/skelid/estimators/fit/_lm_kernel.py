"""Compiled Levenberg-Marquardt pose fit (numba).

The same iteration as the numpy path of :func:`skelid.estimators.fit.pose.fit_pose`,
compiled. Every quantity is stored batch-last (``q (Q, B)``, ``J^T J (Q, Q, B)``)
and every step of the forward kinematics, the normal equations ``J^T J``,
``J^T r`` and the Cholesky solve is a loop over the batch innermost, which the
compiler turns into vector instructions; the loops over segments, markers and
pose coordinates run outside with the model's sizes. The iterations run in
lock step over the batch, as the numpy path's do, so the stopping rule (every
element has stopped improving or is stuck) and therefore the results are the
same up to rounding. Where rounding makes the damped normal matrix fail
Cholesky, that element is solved by LU with partial pivoting, as
``numpy.linalg.solve`` would; an element whose normal equations are not
finite takes no step, as in the numpy path.

Hinges tilted by ``axis_direction`` parameters have an axis that depends on
``theta``: their axes and cross-product matrices come in per batch element
(``t_axis (T, 3, B)``, ``t_skew``, ``t_skew2 (T, 3, 3, B)``).

**Compilation.** There are two drivers, one for planar and one for spatial
models; each is compiled on first use and cached on disk by numba
(``cache=True``: beside this file when that folder is writable, otherwise in
the user's cache folder or ``NUMBA_CACHE_DIR``). Compiling one takes tens of
seconds, loading it from the cache well under a second. So that nobody waits
for it, :func:`ready` answers whether a driver can run without compiling in
this process; when it cannot, it starts the compilation in a separate
background process (:func:`warm`) and the caller uses the numpy path
meanwhile. Once that process has written the cache, the next call loads the
compiled driver. The two paths agree to rounding, so only the speed changes.

The environment variable ``SKELID_NUMBA`` selects the path: ``0`` (or
``false``, ``no``, ``off``) always the numpy path; ``wait`` always the
compiled path, waiting for the compilation if the cache is cold (the tests
use this, so that a result never depends on when the cache was written);
anything else (the default) as described above.
"""

from __future__ import annotations

import numpy as np

# the path switch shared by every compiled kernel (MODE, AVAILABLE and compile_in_background are read from here too)
from skelid._numba import AVAILABLE, MODE, Gate, compile_in_background, compile_lock, in_disk_cache, numba  # noqa: F401
from skelid.model.custom_tables import custom_arrays, no_custom

if AVAILABLE:  # pragma: no branch
    from skelid.model.custom_tables import function_value as _function


def plan_arrays(plan) -> tuple | None:
    """The model tables the kernel reads, as contiguous arrays.

    ``None`` if the kernel cannot represent the model (pose coordinates not
    grouped by segment in segment order); the numpy path then fits it.
    """
    S, Q, D = plan.n_segments, plan.n_pose, plan.dim
    order = [k for ks in plan.segment_dofs for k in ks]
    custom = custom_arrays(plan) if plan.has_custom else None
    if order != list(range(Q)) or (plan.has_custom and custom is None):
        return None
    dof_start = np.zeros(S + 1, dtype=np.int64)
    dof_start[1:] = np.cumsum([len(ks) for ks in plan.segment_dofs])
    axis = np.zeros((Q, 3))
    axis[:, :D] = plan.dof_axis
    parent = np.array([S if i < 0 else i for i in plan.parent], dtype=np.int64)  # row S: the ground
    nz = _nonzero_components(plan, axis)
    out = (parent, dof_start, plan.dof_is_t.astype(np.bool_), axis,
           np.ascontiguousarray(plan.dof_skew), np.ascontiguousarray(plan.dof_skew2),
           plan.marker_segment.astype(np.int64), np.ascontiguousarray(plan.moves), nz,
           plan.dof_tilt.astype(np.int64), bool(plan.planar))
    return out if custom is None else out + (custom,)


def _nonzero_components(plan, axis) -> np.ndarray:
    """``(Q, 3)`` bool: component ``a`` of column ``k`` can be non-zero. A translation of the root before
    its rotations moves along a fixed axis; a custom joint's coordinates may move along any."""
    Q, D = plan.n_pose, plan.dim
    nz = np.ones((Q, 3), dtype=np.bool_)
    for k in range(Q):
        seg = plan.dof_segment[k]
        earlier = [j for j in plan.segment_dofs[seg] if j < k]
        custom = bool(plan.custom) and plan.custom[seg] is not None
        if plan.dof_is_t[k] and plan.parent[seg] < 0 and all(plan.dof_is_t[j] for j in earlier) and not custom:
            nz[k, :D] = axis[k, :D] != 0.0
    return nz


def driver_key(plan):
    """Which compiled driver fits a model of this plan: ``True`` planar, ``False`` spatial, ``"custom"``
    spatial with custom (coupled) joints."""
    return "custom" if plan.has_custom else bool(plan.planar)


if AVAILABLE:  # pragma: no branch
    _jit = numba.njit(cache=True, nogil=True, error_model="numpy")
    _inline = numba.njit(cache=True, nogil=True, error_model="numpy")

    # sine and cosine by Cody-Waite reduction modulo pi/2 and the minimax polynomials of
    # fdlibm/musl (within 1 ulp of the C library): unlike calls to the C library, the loop
    # over the batch compiles to vector instructions
    _TOINT = 1.5 / np.finfo(float).eps
    _INVPIO2 = 6.36619772367581382433e-01
    _PIO2_1 = 1.57079632673412561417e+00
    _PIO2_1T = 6.07710050650619224932e-11
    _PIO2_2 = 6.07710050630396597660e-11
    _PIO2_2T = 2.02226624879595063154e-21
    _S1, _S2, _S3 = -1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04
    _S4, _S5, _S6 = 2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10
    _C1, _C2, _C3 = 4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05
    _C4, _C5, _C6 = -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11

    @_inline
    def _sincos(src, i, cs, sn, o, B):
        """``cs[o, :B], sn[o, :B] = cos, sin of src[i, :B]``."""
        for b in range(B):
            x = src[i, b]
            fn = (x * _INVPIO2 + _TOINT) - _TOINT  # nearest integer
            r = x - fn * _PIO2_1
            w = fn * _PIO2_2
            t = r
            r = t - w
            w = fn * _PIO2_2T - ((t - r) - w)
            y0 = r - w  # x - fn pi/2 as y0 + y1
            y1 = (r - y0) - w
            z = y0 * y0
            zz = z * z
            rs = _S2 + z * (_S3 + z * _S4) + z * zz * (_S5 + z * _S6)
            v = z * y0
            s = y0 - ((z * (0.5 * y1 - v * rs) - y1) - v * _S1)
            rc = z * (_C1 + z * (_C2 + z * _C3)) + zz * zz * (_C4 + z * (_C5 + z * _C6))
            hz = 0.5 * z
            w1 = 1.0 - hz
            c = w1 + (((1.0 - w1) - hz) + (z * rc - y0 * y1))
            n = np.int64(fn)
            odd = (n & 1) == 1
            sn[o, b] = (c if odd else s) * (1.0 - 2.0 * ((n >> 1) & 1))
            cs[o, b] = (s if odd else c) * (1.0 - 2.0 * (((n + 1) >> 1) & 1))
        for b in range(B):  # huge or non-finite angles: the C library
            x = src[i, b]
            if not abs(x) < 1e5:
                cs[o, b] = np.cos(x)
                sn[o, b] = np.sin(x)

    @_inline
    def _kinematics_planar(g, pose, D, S, M, parent, dof_start, is_t, axis, skew, skew2, ms, R, Ri, E,
                           ang, cs, sn, p, w, pivot, x, ux, uy, tilt, t_axis, t_skew, t_skew2):
        """Planar forward kinematics of the batch at ``pose (Q, B)``: one angle per segment.

        Rows ``S`` of ``ang, cs, sn, p`` hold the ground (angle 0, origin 0).
        """
        B = pose.shape[1]
        for i in range(S):
            par = parent[i]
            for b in range(B):
                ang[i, b] = ang[par, b]
                ux[b] = g[2 * i, b]
                uy[b] = g[2 * i + 1, b]
            for k in range(dof_start[i], dof_start[i + 1]):
                if is_t[k]:
                    a0, a1 = axis[k, 0], axis[k, 1]
                    for b in range(B):
                        ux[b] += a0 * pose[k, b]
                        uy[b] += a1 * pose[k, b]
                        w[k, 0, b] = cs[par, b] * a0 - sn[par, b] * a1
                        w[k, 1, b] = sn[par, b] * a0 + cs[par, b] * a1
                else:
                    for b in range(B):
                        ang[i, b] = ang[i, b] + pose[k, b]
            for b in range(B):
                p[i, 0, b] = p[par, 0, b] + (cs[par, b] * ux[b] - sn[par, b] * uy[b])
                p[i, 1, b] = p[par, 1, b] + (sn[par, b] * ux[b] + cs[par, b] * uy[b])
            for k in range(dof_start[i], dof_start[i + 1]):
                if not is_t[k]:
                    for b in range(B):
                        pivot[k, 0, b] = p[i, 0, b]
                        pivot[k, 1, b] = p[i, 1, b]
            _sincos(ang, i, cs, sn, i, B)
        base = 2 * S
        for m in range(M):
            s = ms[m]
            for b in range(B):
                rx = g[base + 2 * m, b]
                ry = g[base + 2 * m + 1, b]
                x[m, 0, b] = p[s, 0, b] + (cs[s, b] * rx - sn[s, b] * ry)
                x[m, 1, b] = p[s, 1, b] + (sn[s, b] * rx + cs[s, b] * ry)

    @_inline
    def _custom_motions(i, g, pose, Ri, E, p, w, pivot, vel, cs, sn, tmp, ctab):
        """Segment ``i``'s custom joint (:func:`custom_arrays`): its frame ``Ri`` (in: the parent's) and
        origin ``p[i]`` (in: the joint's place), the axes, pivots and velocity terms of its coordinates.

        Translations along the parent's axes by the coordinate or by ``c f(q)`` (``c`` the parent's
        scale factor, from ``g``), then rotations by the coordinate or ``f(q)`` about axes carried by
        the earlier ones, then the constant rotation; as :func:`skelid.model.kinematics._custom_joint`.
        Kept as one flat loop nest on purpose, for the compiled speed (as :func:`_kinematics_spatial`).
        """
        (start, c_is_t, c_axis, c_k, c_fun, c_slot, c_skew, c_skew2, orient, has_orient, _hv,
         f_kind, f_scale, f_start, f_values, f_pstart, f_base, f_coef, fbase) = ctab
        B = pose.shape[1]
        for r in range(start[i], start[i + 1]):
            k = c_k[r]
            if k >= 0:
                for a in range(3):
                    for b in range(B):
                        w[k, a, b] = 0.0
                        vel[k, a, b] = 0.0
        for r in range(start[i], start[i + 1]):
            if not c_is_t[r]:
                continue
            k, f, sl = c_k[r], c_fun[r], c_slot[r]
            a0, a1, a2 = c_axis[r, 0], c_axis[r, 1], c_axis[r, 2]
            for b in range(B):
                if f >= 0:
                    val, der = _function(f, pose[k, b] if k >= 0 else 0.0, f_kind, f_scale, f_start, f_values,
                                         f_pstart, f_base, f_coef)
                    c = g[fbase + sl, b] if sl >= 0 else 1.0
                for a in range(3):
                    wa = Ri[a, 0, b] * a0 + Ri[a, 1, b] * a1 + Ri[a, 2, b] * a2
                    if f < 0:
                        w[k, a, b] = wa
                        p[i, a, b] += wa * pose[k, b]
                    else:
                        p[i, a, b] += wa * (c * val)
                        if k >= 0:
                            vel[k, a, b] += wa * (c * der)
        for r in range(start[i], start[i + 1]):
            k = c_k[r]
            if k >= 0 and not (c_is_t[r] and c_fun[r] < 0):
                for a in range(3):
                    for b in range(B):
                        pivot[k, a, b] = p[i, a, b]
        for r in range(start[i], start[i + 1]):
            if c_is_t[r]:
                continue
            k, f = c_k[r], c_fun[r]
            a0, a1, a2 = c_axis[r, 0], c_axis[r, 1], c_axis[r, 2]
            for b in range(B):
                if f < 0:
                    tmp[0, b], tmp[1, b] = pose[k, b], 1.0
                else:
                    tmp[0, b], tmp[1, b] = _function(f, pose[k, b] if k >= 0 else 0.0, f_kind, f_scale, f_start,
                                                     f_values, f_pstart, f_base, f_coef)
                if k >= 0:
                    for a in range(3):
                        w[k, a, b] += (Ri[a, 0, b] * a0 + Ri[a, 1, b] * a1 + Ri[a, 2, b] * a2) * tmp[1, b]
            _sincos(tmp, 0, cs, sn, 0, B)
            for a in range(3):
                for c in range(3):
                    k0, k1, k2 = (1.0 if a == c else 0.0), c_skew[r, a, c], c_skew2[r, a, c]
                    for b in range(B):
                        E[a, c, b] = k0 + sn[0, b] * k1 + (1.0 - cs[0, b]) * k2
            _times(Ri, E, B)
        if has_orient[i]:
            for a in range(3):
                for c in range(3):
                    for b in range(B):
                        E[a, c, b] = orient[i, a, c]
            _times(Ri, E, B)

    @_inline
    def _times(Ri, E, B):
        """``Ri = Ri E`` per element."""
        for a in range(3):
            for b in range(B):
                r0, r1, r2 = Ri[a, 0, b], Ri[a, 1, b], Ri[a, 2, b]
                Ri[a, 0, b] = r0 * E[0, 0, b] + r1 * E[1, 0, b] + r2 * E[2, 0, b]
                Ri[a, 1, b] = r0 * E[0, 1, b] + r1 * E[1, 1, b] + r2 * E[2, 1, b]
                Ri[a, 2, b] = r0 * E[0, 2, b] + r1 * E[1, 2, b] + r2 * E[2, 2, b]

    @_inline
    def _kinematics_spatial(g, pose, D, S, M, parent, dof_start, is_t, axis, skew, skew2, ms, R, Ri, E,
                            ang, cs, sn, p, w, pivot, x, ux, uy, tilt, t_axis, t_skew, t_skew2, vel, tmp, ctab):
        """Forward kinematics of the batch at ``pose (Q, B)`` by products of elementary rotations.

        Its one long, flat body is deliberate: numba compiles it for speed, and splitting it into
        helpers would slow this hot path down.

        Row ``S`` of ``R`` and ``p`` holds the ground (identity, origin 0). A
        rotation with ``tilt[k] = j >= 0`` turns about ``t_axis[j, :, b]``. A segment with a
        custom joint (rows in ``ctab``, :func:`custom_arrays`) moves by :func:`_custom_motions`.
        """
        B = pose.shape[1]
        c_start, has_orient = ctab[0], ctab[9]
        for i in range(S):
            par = parent[i]
            for a in range(D):
                for c in range(D):
                    for b in range(B):
                        Ri[a, c, b] = R[par, a, c, b]
            for a in range(D):
                for b in range(B):
                    acc = 0.0
                    for c in range(D):
                        acc += Ri[a, c, b] * g[i * D + c, b]
                    p[i, a, b] = p[par, a, b] + acc
            custom = c_start[i] < c_start[i + 1] or has_orient[i]  # a custom joint (a weld: its rotation only)
            if custom:
                _custom_motions(i, g, pose, Ri, E, p, w, pivot, vel, cs, sn, tmp, ctab)
            for k in range(dof_start[i], dof_start[i] if custom else dof_start[i + 1]):
                j = tilt[k]
                if j >= 0:
                    for a in range(D):
                        for b in range(B):
                            acc = 0.0
                            for c in range(D):
                                acc += Ri[a, c, b] * t_axis[j, c, b]
                            w[k, a, b] = acc
                else:
                    for a in range(D):
                        for b in range(B):
                            acc = 0.0
                            for c in range(D):
                                acc += Ri[a, c, b] * axis[k, c]
                            w[k, a, b] = acc
                if is_t[k]:
                    for a in range(D):
                        for b in range(B):
                            p[i, a, b] += w[k, a, b] * pose[k, b]
                    continue
                for a in range(D):
                    for b in range(B):
                        pivot[k, a, b] = p[i, a, b]
                _sincos(pose, k, cs, sn, 0, B)
                if D == 2:
                    for a in range(2):
                        for b in range(B):
                            r0, r1 = Ri[a, 0, b], Ri[a, 1, b]
                            Ri[a, 0, b] = r0 * cs[0, b] + r1 * sn[0, b]
                            Ri[a, 1, b] = -r0 * sn[0, b] + r1 * cs[0, b]
                else:
                    for a in range(3):
                        for c in range(3):
                            k0 = 1.0 if a == c else 0.0
                            if j >= 0:  # a tilted hinge: this element's axis
                                for b in range(B):
                                    E[a, c, b] = (k0 + sn[0, b] * t_skew[j, a, c, b]
                                                  + (1.0 - cs[0, b]) * t_skew2[j, a, c, b])
                            else:
                                k1, k2 = skew[k, a, c], skew2[k, a, c]
                                for b in range(B):
                                    E[a, c, b] = k0 + sn[0, b] * k1 + (1.0 - cs[0, b]) * k2
                    for a in range(3):
                        for b in range(B):
                            r0, r1, r2 = Ri[a, 0, b], Ri[a, 1, b], Ri[a, 2, b]
                            Ri[a, 0, b] = r0 * E[0, 0, b] + r1 * E[1, 0, b] + r2 * E[2, 0, b]
                            Ri[a, 1, b] = r0 * E[0, 1, b] + r1 * E[1, 1, b] + r2 * E[2, 1, b]
                            Ri[a, 2, b] = r0 * E[0, 2, b] + r1 * E[1, 2, b] + r2 * E[2, 2, b]
            for a in range(D):
                for c in range(D):
                    for b in range(B):
                        R[i, a, c, b] = Ri[a, c, b]
        base = S * D
        for m in range(M):
            s = ms[m]
            for a in range(D):
                for b in range(B):
                    acc = 0.0
                    for c in range(D):
                        acc += R[s, a, c, b] * g[base + m * D + c, b]
                    x[m, a, b] = p[s, a, b] + acc

    @_inline
    def _residual(y0, mask, x, D, M, r, cost):
        """Residuals ``r (M*D, B)`` (zero for missing markers) and their sums of squares ``cost (B,)``."""
        B = x.shape[2]
        for b in range(B):
            cost[b] = 0.0
        for m in range(M):
            for a in range(D):
                for b in range(B):
                    v = (y0[m, a, b] - x[m, a, b]) * mask[m, b]
                    r[m * D + a, b] = v
                    cost[b] += v * v

    @_inline
    def _normal(x, r, mask, ok, D, M, Q, is_t, w, pivot, moves, nz, J, acc, JtJ, Jtr, vel, has_vel):
        """``J^T J`` and ``J^T r`` written where ``ok`` (missing markers give zero rows).

        Its one long, flat body is deliberate: numba compiles it for speed, and splitting it into
        helpers would slow this hot path down.

        ``nz[k, a]`` is False where component ``a`` of column ``k`` is zero whatever
        the pose (a translation of the root along a coordinate axis): those rows
        are skipped. Where ``has_vel[k]``, column ``k`` gains ``vel[k]`` (a custom joint's
        translations by functions of the coordinate).
        """
        B = x.shape[2]
        for m in range(M):
            for k in range(Q):
                if moves[k, m] == 0.0:
                    continue
                if is_t[k]:
                    for a in range(D):
                        if nz[k, a]:
                            for b in range(B):
                                J[m * D + a, k, b] = w[k, a, b] * mask[m, b]
                elif D == 2:
                    for b in range(B):
                        J[m * D, k, b] = -(x[m, 1, b] - pivot[k, 1, b]) * mask[m, b]
                        J[m * D + 1, k, b] = (x[m, 0, b] - pivot[k, 0, b]) * mask[m, b]
                else:
                    for b in range(B):
                        v0 = x[m, 0, b] - pivot[k, 0, b]
                        v1 = x[m, 1, b] - pivot[k, 1, b]
                        v2 = x[m, 2, b] - pivot[k, 2, b]
                        J[m * D, k, b] = (w[k, 1, b] * v2 - w[k, 2, b] * v1) * mask[m, b]
                        J[m * D + 1, k, b] = (w[k, 2, b] * v0 - w[k, 0, b] * v2) * mask[m, b]
                        J[m * D + 2, k, b] = (w[k, 0, b] * v1 - w[k, 1, b] * v0) * mask[m, b]
                if has_vel[k]:
                    for a in range(D):
                        for b in range(B):
                            J[m * D + a, k, b] += vel[k, a, b] * mask[m, b]
        for i in range(Q):
            for j in range(i - 1, Q):  # j = i - 1 stands for J^T r
                first = True
                for m in range(M):
                    if moves[i, m] == 0.0 or (j >= i and moves[j, m] == 0.0):
                        continue
                    for a in range(D):
                        if not nz[i, a] or (j >= i and not nz[j, a]):
                            continue
                        row = m * D + a
                        if j < i:
                            if first:
                                for b in range(B):
                                    acc[b] = J[row, i, b] * r[row, b]
                            else:
                                for b in range(B):
                                    acc[b] += J[row, i, b] * r[row, b]
                        elif first:
                            for b in range(B):
                                acc[b] = J[row, i, b] * J[row, j, b]
                        else:
                            for b in range(B):
                                acc[b] += J[row, i, b] * J[row, j, b]
                        first = False
                if first:
                    for b in range(B):
                        acc[b] = 0.0
                if j < i:
                    for b in range(B):
                        Jtr[i, b] = acc[b] if ok[b] else Jtr[i, b]
                else:
                    for b in range(B):
                        v = acc[b] if ok[b] else JtJ[i, j, b]
                        JtJ[i, j, b] = v
                        JtJ[j, i, b] = v

    @_inline
    def _cholesky(A, lam, ridge, Q, L, dinv, bad, chk):
        """Lower Cholesky factors ``L (Q, Q, B)`` of ``A + lam diag(A) + ridge I`` and ``dinv = 1 / diag(L)``.

        ``bad[b]`` is set where the matrix is not positive definite (its factors are then meaningless).
        ``chk[b]`` gains ``v * 0`` for every entry ``v`` of the lower triangle of the damped matrix:
        it stays finite only where they all are (``A`` is symmetric).
        """
        B = A.shape[2]
        for j in range(Q):
            for b in range(B):
                v = (A[j, j, b] + lam[b] * A[j, j, b]) + ridge[b]
                L[j, j, b] = v
                chk[b] += v * 0.0
            for c in range(j):
                for b in range(B):
                    L[j, j, b] -= L[j, c, b] * L[j, c, b]
            for b in range(B):
                d = L[j, j, b]
                if not d > 0.0:
                    bad[b] = True
                    d = 1.0
                d = np.sqrt(d)
                L[j, j, b] = d
                dinv[j, b] = 1.0 / d
            for i in range(j + 1, Q):
                for b in range(B):
                    v = A[i, j, b]
                    L[i, j, b] = v
                    chk[b] += v * 0.0
                for c in range(j):
                    for b in range(B):
                        L[i, j, b] -= L[i, c, b] * L[j, c, b]
                for b in range(B):
                    L[i, j, b] *= dinv[j, b]

    @_inline
    def _lu_solve(A, rhs, Q, out):
        """``out = A^{-1} rhs`` for one element by LU with partial pivoting (``A`` overwritten)."""
        for i in range(Q):
            out[i] = rhs[i]
        for j in range(Q):
            best, bi = abs(A[j, j]), j
            for i in range(j + 1, Q):
                if abs(A[i, j]) > best:
                    best, bi = abs(A[i, j]), i
            if bi != j:
                for c in range(Q):
                    t = A[j, c]
                    A[j, c] = A[bi, c]
                    A[bi, c] = t
                t = out[j]
                out[j] = out[bi]
                out[bi] = t
            d = A[j, j]
            for i in range(j + 1, Q):
                f = A[i, j] / d
                for c in range(j + 1, Q):
                    A[i, c] -= f * A[j, c]
                out[i] -= f * out[j]
        for i in range(Q - 1, -1, -1):
            acc = out[i]
            for c in range(i + 1, Q):
                acc -= A[i, c] * out[c]
            out[i] = acc / A[i, i]

    @_inline
    def _lu_logdet(A, Q):
        """``log det A`` for one element; ``-inf`` unless positive (as ``slogdet``)."""
        sign = 1.0
        total = 0.0
        for j in range(Q):
            best, bi = abs(A[j, j]), j
            for i in range(j + 1, Q):
                if abs(A[i, j]) > best:
                    best, bi = abs(A[i, j]), i
            if bi != j:
                sign = -sign
                for c in range(Q):
                    t = A[j, c]
                    A[j, c] = A[bi, c]
                    A[bi, c] = t
            d = A[j, j]
            if d == 0.0:
                return -np.inf
            if d < 0.0:
                sign = -sign
            total += np.log(abs(d))
            for i in range(j + 1, Q):
                f = A[i, j] / d
                for c in range(j + 1, Q):
                    A[i, c] -= f * A[j, c]
        return total if sign > 0 else -np.inf

    @_inline
    def _step(JtJ, Jtr, lam, Q, L, dinv, bad, A1, r1, s1, step, ridge, nf, chk):
        """Solve ``(J^T J + lam diag(J^T J) + ridge I) step = J^T r`` for the whole batch.

        Its one long, flat body is deliberate: numba compiles it for speed, and splitting it into
        helpers would slow this hot path down.

        ``ridge = 1e-9 mean(diag(J^T J))``. An element whose damped matrix or
        ``J^T r`` is not finite takes no step; non-finite components of a step
        are set to 0.
        """
        B = Jtr.shape[1]
        for b in range(B):
            bad[b] = False
            ridge[b] = 0.0
        for j in range(Q):
            for b in range(B):
                ridge[b] += JtJ[j, j, b]
        for b in range(B):
            ridge[b] = 1e-9 * max(ridge[b] / Q, 1e-300)
        # v * 0 is 0 for finite v and NaN otherwise: one sum per element finds them without branches
        for b in range(B):
            chk[b] = 0.0
        _cholesky(JtJ, lam, ridge, Q, L, dinv, bad, chk)
        for i in range(Q):
            for b in range(B):
                step[i, b] = Jtr[i, b]
                chk[b] += Jtr[i, b] * 0.0
            for c in range(i):
                for b in range(B):
                    step[i, b] -= L[i, c, b] * step[c, b]
            for b in range(B):
                step[i, b] *= dinv[i, b]
        for i in range(Q - 1, -1, -1):
            for c in range(i + 1, Q):
                for b in range(B):
                    step[i, b] -= L[c, i, b] * step[c, b]
            for b in range(B):
                step[i, b] *= dinv[i, b]
        for b in range(B):
            nf[b] = chk[b] != chk[b]
        for b in range(B):
            if bad[b] and not nf[b]:
                for i in range(Q):
                    r1[i] = Jtr[i, b]
                    for j in range(Q):
                        A1[i, j] = JtJ[i, j, b]
                    A1[i, i] = (JtJ[i, i, b] + lam[b] * JtJ[i, i, b]) + ridge[b]
                _lu_solve(A1, r1, Q, s1)
                for i in range(Q):
                    step[i, b] = s1[i]
        for i in range(Q):
            for b in range(B):
                v = step[i, b]
                step[i, b] = 0.0 if nf[b] or v - v != 0.0 else v

    @_inline
    def _workspace(Q, B, S, M, D, damping, spatial):
        """Every array one fit needs, allocated once.

        Only what is read before it is written is initialised: the ground's row
        ``S`` of the frames, angles and origins. ``J``, ``w`` and ``pivot`` are
        written wherever :func:`_normal` reads them. The planar kinematics use
        no rotation matrices (``R``, ``Ri``, ``E`` get a token size).
        """
        n = M * D
        Bm = B if spatial else 1
        R = np.empty((S + 1 if spatial else 1, 3, 3, Bm))
        if spatial:
            R[S] = 0.0
            for a in range(3):
                R[S, a, a, :] = 1.0  # the ground's orientation
        p = np.empty((S + 1, 3, B))
        p[S] = 0.0  # the ground's origin
        return (np.empty(B), np.empty(B), np.full(B, damping), np.ones(B, dtype=np.bool_),
                np.zeros(B, dtype=np.bool_), np.empty((Q, Q, B)), np.empty((Q, B)), np.empty((Q, Q, B)),
                np.empty((Q, B)), np.empty((Q, B)), np.empty((Q, B)), R, np.empty((3, 3, Bm)),
                np.empty((3, 3, Bm)), np.zeros((S + 1, B)), np.ones((S + 1, B)), np.zeros((S + 1, B)),
                p, np.empty((Q, 3, B)), np.empty((Q, 3, B)), np.empty((M, D, B)),
                np.empty((n, B)), np.empty((n, Q, B)), np.empty(B), np.empty(B), np.empty(B),
                np.empty((Q, Q)), np.empty(Q), np.empty(Q), np.empty(B), np.zeros(B, dtype=np.bool_),
                np.empty(B))

    @_inline
    def _trial(JtJ, Jtr, lam, q, Q, L, dinv, bad, A1, r1, s1, step, qn, ridge, nf, chk):
        """The trial poses ``qn = q + step`` of one iteration."""
        B = q.shape[1]
        _step(JtJ, Jtr, lam, Q, L, dinv, bad, A1, r1, s1, step, ridge, nf, chk)
        for i in range(Q):
            for b in range(B):
                qn[i, b] = q[i, b] + step[i, b]

    @_inline
    def _accept(cost, cost_new, lam, ok, q, qn, tol):
        """Keep the steps that lower the RSS, adapt the damping; (all done, any step taken)."""
        Q, B = q.shape
        all_small = True
        all_settled = True
        any_ok = False
        for b in range(B):
            okb = cost_new[b] <= cost[b]
            ok[b] = okb
            if okb:
                improve = cost[b] - cost_new[b]
                cost[b] = cost_new[b]
                lam[b] = lam[b] * 0.3
                any_ok = True
            else:
                improve = 0.0
                lam[b] = lam[b] * 10.0
            if not improve <= tol * (cost[b] + 1e-30):
                all_small = False
            if not (okb or lam[b] > 1e8):
                all_settled = False
        for i in range(Q):
            for b in range(B):
                if ok[b]:
                    q[i, b] = qn[i, b]
        return all_small and all_settled, any_ok

    @_inline
    def _logdets(JtJ, want, Q, L, dinv, bad, lam, acc, A1, ridge):
        """``log det J^T J`` per element (``-inf`` unless positive; zeros unless ``want``)."""
        B = JtJ.shape[2]
        logdet = np.zeros(B)
        if not want:
            return logdet
        for b in range(B):
            bad[b] = False
            lam[b] = 0.0
            ridge[b] = 0.0
        _cholesky(JtJ, lam, ridge, Q, L, dinv, bad, acc)
        for b in range(B):
            acc[b] = 1.0
        for j in range(Q):
            for b in range(B):
                acc[b] *= L[j, j, b]
        for b in range(B):
            if bad[b]:
                for i in range(Q):
                    for j in range(Q):
                        A1[i, j] = JtJ[i, j, b]
                logdet[b] = _lu_logdet(A1, Q)
            elif 1e-150 < acc[b] < 1e150:
                logdet[b] = 2.0 * np.log(acc[b])
            else:
                total = 0.0
                for j in range(Q):
                    total += np.log(L[j, j, b])
                logdet[b] = 2.0 * total
        return logdet

    # The two drivers differ only in the forward kinematics they call; each is compiled
    # (and cached) on first use, so a planar model never pays for the spatial one.
    @_jit
    def _lm_planar(g, y0, mask, q, n_iter, tol, damping, want_logdet, D, S, M, parent, dof_start, is_t, axis,
                   skew, skew2, ms, moves, nz, tilt, t_axis, t_skew, t_skew2):
        Q, B = q.shape
        (cost, cost_new, lam, ok, bad, JtJ, Jtr, L, dinv, step, qn, R, Ri, E, ang, cs, sn, p, w, pivot, x, r,
         J, acc, ux, uy, A1, r1, s1, ridge, nf, chk) = _workspace(Q, B, S, M, D, damping, False)
        vel, has_vel = np.zeros((0, 3, 1)), np.zeros(Q, dtype=np.bool_)
        _kinematics_planar(g, q, D, S, M, parent, dof_start, is_t, axis, skew, skew2, ms, R, Ri, E, ang, cs,
                           sn, p, w, pivot, x, ux, uy, tilt, t_axis, t_skew, t_skew2)
        _residual(y0, mask, x, D, M, r, cost)
        _normal(x, r, mask, ok, D, M, Q, is_t, w, pivot, moves, nz, J, acc, JtJ, Jtr, vel, has_vel)
        for it in range(n_iter):
            _trial(JtJ, Jtr, lam, q, Q, L, dinv, bad, A1, r1, s1, step, qn, ridge, nf, chk)
            _kinematics_planar(g, qn, D, S, M, parent, dof_start, is_t, axis, skew, skew2, ms, R, Ri, E, ang,
                               cs, sn, p, w, pivot, x, ux, uy, tilt, t_axis, t_skew, t_skew2)
            _residual(y0, mask, x, D, M, r, cost_new)
            done, any_ok = _accept(cost, cost_new, lam, ok, q, qn, tol)
            if any_ok and (want_logdet or not (done or it == n_iter - 1)):
                _normal(x, r, mask, ok, D, M, Q, is_t, w, pivot, moves, nz, J, acc, JtJ, Jtr, vel, has_vel)
            if done:
                break
        return cost, _logdets(JtJ, want_logdet, Q, L, dinv, bad, lam, acc, A1, ridge)

    @_inline
    def _empty_custom(S, Q):
        """:func:`no_custom` in compiled code."""
        i = np.int64
        return (np.zeros(S + 1, i), np.zeros(0, np.bool_), np.zeros((0, 3)), np.zeros(0, i), np.zeros(0, i),
                np.zeros(0, i), np.zeros((0, 3, 3)), np.zeros((0, 3, 3)), np.zeros((S, 3, 3)),
                np.zeros(S, np.bool_), np.zeros(Q, np.bool_), np.zeros(0, i), np.zeros(0), np.zeros(1, i),
                np.zeros(0), np.zeros(1, i), np.zeros(0), np.zeros((0, 4)), 0)

    @_jit
    def _lm_spatial(g, y0, mask, q, n_iter, tol, damping, want_logdet, D, S, M, parent, dof_start, is_t, axis,
                    skew, skew2, ms, moves, nz, tilt, t_axis, t_skew, t_skew2):
        return _lm_general(g, y0, mask, q, n_iter, tol, damping, want_logdet, D, S, M, parent, dof_start, is_t,
                           axis, skew, skew2, ms, moves, nz, tilt, t_axis, t_skew, t_skew2,
                           _empty_custom(S, q.shape[0]))

    @_jit
    def _lm_custom(g, y0, mask, q, n_iter, tol, damping, want_logdet, D, S, M, parent, dof_start, is_t, axis,
                   skew, skew2, ms, moves, nz, tilt, t_axis, t_skew, t_skew2, ctab):
        return _lm_general(g, y0, mask, q, n_iter, tol, damping, want_logdet, D, S, M, parent, dof_start, is_t,
                           axis, skew, skew2, ms, moves, nz, tilt, t_axis, t_skew, t_skew2, ctab)

    @_inline
    def _lm_general(g, y0, mask, q, n_iter, tol, damping, want_logdet, D, S, M, parent, dof_start, is_t, axis,
                    skew, skew2, ms, moves, nz, tilt, t_axis, t_skew, t_skew2, ctab):
        """The spatial driver, custom joints included (``ctab``: :func:`custom_arrays`)."""
        Q, B = q.shape
        (cost, cost_new, lam, ok, bad, JtJ, Jtr, L, dinv, step, qn, R, Ri, E, ang, cs, sn, p, w, pivot, x, r,
         J, acc, ux, uy, A1, r1, s1, ridge, nf, chk) = _workspace(Q, B, S, M, D, damping, True)
        has_vel = ctab[10]
        vel, tmp = np.zeros((Q, 3, B)), np.empty((2, B))
        _kinematics_spatial(g, q, D, S, M, parent, dof_start, is_t, axis, skew, skew2, ms, R, Ri, E, ang, cs,
                            sn, p, w, pivot, x, ux, uy, tilt, t_axis, t_skew, t_skew2, vel, tmp, ctab)
        _residual(y0, mask, x, D, M, r, cost)
        _normal(x, r, mask, ok, D, M, Q, is_t, w, pivot, moves, nz, J, acc, JtJ, Jtr, vel, has_vel)
        for it in range(n_iter):
            _trial(JtJ, Jtr, lam, q, Q, L, dinv, bad, A1, r1, s1, step, qn, ridge, nf, chk)
            _kinematics_spatial(g, qn, D, S, M, parent, dof_start, is_t, axis, skew, skew2, ms, R, Ri, E, ang,
                                cs, sn, p, w, pivot, x, ux, uy, tilt, t_axis, t_skew, t_skew2, vel, tmp, ctab)
            _residual(y0, mask, x, D, M, r, cost_new)
            done, any_ok = _accept(cost, cost_new, lam, ok, q, qn, tol)
            if any_ok and (want_logdet or not (done or it == n_iter - 1)):
                _normal(x, r, mask, ok, D, M, Q, is_t, w, pivot, moves, nz, J, acc, JtJ, Jtr, vel, has_vel)
            if done:
                break
        return cost, _logdets(JtJ, want_logdet, Q, L, dinv, bad, lam, acc, A1, ridge)

    def lm_fit(g, y0, mask, q, n_iter, tol, damping, want_logdet, D, S, M, tilts, parent, dof_start, is_t,
               axis, skew, skew2, ms, moves, nz, tilt, planar, ctab=None):
        """Levenberg-Marquardt over a batch, in place on ``q (Q, B)``.

        Parameters
        ----------
        g : (G, B) float
            Geometry of each element.
        y0 : (M, D, B) float
            Markers with missing ones set to 0.
        mask : (M, B) float
            1 where a marker is present.
        q : (Q, B) float
            Starting poses, overwritten by the fitted ones.
        damping : float
            Initial damping ``lam``.
        tilts : tuple of (T, 3, B), (T, 3, 3, B), (T, 3, 3, B) float
            Axis, cross-product matrix and its square of each tilted hinge, per
            element (``T = 0`` when the model has none).
        tilt, planar, ctab
            From :func:`plan_arrays`: the slot of each pose coordinate's tilted
            axis (-1: fixed axis), whether to use the planar kinematics, and the
            custom joints' tables (:func:`custom_arrays`; None: the model has none).

        Returns
        -------
        cost : (B,) float
            Residual sum of squares at the returned poses.
        logdet : (B,) float
            ``log det J^T J`` there (``-inf`` if not positive; zeros unless ``want_logdet``).
        """
        args = (g, y0, mask, q, n_iter, tol, damping, want_logdet, D, S, M, parent, dof_start, is_t, axis,
                skew, skew2, ms, moves, nz, tilt, *tilts)
        if ctab is not None:
            return _lm_custom(*args, ctab)
        return (_lm_planar if planar else _lm_spatial)(*args)


def no_tilts(B: int) -> tuple:
    """The ``tilts`` argument of :func:`lm_fit` for a model without tilted hinges."""
    return np.zeros((0, 3, B)), np.zeros((0, 3, 3, B)), np.zeros((0, 3, 3, B))


# ------------------------------------------------------------------ which path, and warming the cache
def _example_args(planar) -> tuple:
    """Arguments with the types of every real call of a driver (their values are never used); ``planar``:
    the driver's key (:func:`driver_key`)."""
    f, i, b = np.zeros, np.int64, np.bool_
    args = (f((2, 1)), f((1, 2, 1)), f((1, 1)), f((1, 1)), 1, 1e-10, 1e-3, True, 2, 1, 1,
            np.zeros(2, i), np.zeros(2, i), np.zeros(1, b), f((1, 3)), f((1, 3, 3)), f((1, 3, 3)),
            np.zeros(1, i), f((1, 1)), np.zeros((1, 3), b), np.zeros(1, i),
            f((0, 3, 1)), f((0, 3, 3, 1)), f((0, 3, 3, 1)))
    return args + (no_custom(1, 1),) if planar == "custom" else args


def _driver(planar):
    if planar == "custom":
        return _lm_custom
    return _lm_planar if planar else _lm_spatial


def _cached(planar) -> bool:
    """Whether numba's disk cache holds the driver for this machine and this source.

    True where that cache's index cannot be read in this numba version (the driver is then
    compiled in this process when first called).
    """
    return in_disk_cache(_driver(planar), tuple(numba.typeof(a) for a in _example_args(planar)))


def compiled(planar) -> bool:
    """Whether the driver is already compiled (or loaded) in this process."""
    return AVAILABLE and bool(_driver(planar).signatures)


def ready(planar) -> bool:
    """Whether the compiled driver can run now without compiling in this process (``planar``: the
    driver's key, :func:`driver_key`).

    False without numba (or with ``SKELID_NUMBA=0``). True once the driver is
    loaded or when numba's cache holds it; with ``SKELID_NUMBA=wait`` always
    True, after waiting for :func:`warm` if the cache is cold.
    Otherwise starts :func:`warm` in the background (once) and answers False;
    while the driver is not cached the cache is looked at again at most every
    half second, so calling this per frame costs nothing (:class:`skelid._numba.Gate`).
    """
    return AVAILABLE and _gate.ready(planar if planar == "custom" else bool(planar))


def warm(planar, wait: bool = True, timeout: float = 600.0) -> bool:
    """Compile the driver into numba's disk cache in a separate process.

    Parameters
    ----------
    planar : bool or "custom"
        Which driver (:func:`driver_key`).
    wait : bool
        Wait for the process to finish (at most ``timeout`` seconds).

    Returns
    -------
    bool
        Whether the driver is cached (after waiting, if asked).
    """
    if not AVAILABLE:
        return False
    code = f"from skelid.estimators.fit._lm_warmup import compile_here; compile_here({planar!r})"
    return compile_in_background(_gate.warming, planar, code, lambda: _cached(planar), wait, timeout)


# the module's names are looked up at each call (a test may replace them)
_gate = Gate(lambda k: compiled(k), lambda k: _cached(k), lambda k, wait: warm(k, wait=wait), lambda: MODE)
