"""Compiled linearisation of one frame (numba): marker positions and both Jacobians.

The live session's Gaussian form linearises each frame at ``(theta, q)``:
``x(theta, q)``, ``J = dx/dq`` and ``K = dx/dtheta``. For one frame the numpy
:func:`~skelid.model.kinematics.marker_jacobian` spends its time in Python
overheads of many tiny array operations; this module computes the same three
arrays in one compiled call, from the forward kinematics of the compiled pose
kernel (:mod:`skelid.estimators._lm_kernel`, at a batch of one) and

.. math::

    J_{m,k} = w_k \\times (x_m - p_k) \\ (\\text{rotation}),\\quad w_k \\ (\\text{translation}),\\qquad
    K_m = \\sum_{j \\ni m} R_{\\mathrm{parent}(j)} A_j + R_{\\mathrm{seg}(m)} A_m

(``w_k`` the world axis and ``p_k`` a point on it; ``A_j``, ``A_m`` the
columns of the linear geometry map for joint ``j`` and marker ``m``; in 2-D the
rotation column is ``(-(x - p)_y, (x - p)_x)``). The results equal the numpy
path's to rounding (the kernel's sine and cosine are within 1 ulp of the C
library's).

Models with tilted hinge axes, coupled or custom joints are not covered
(:func:`tables` answers None): the numpy path linearises them. Like the pose
kernel, the function is compiled into numba's disk cache in a separate process
(:func:`ready` starts it and answers False meanwhile), so a session never waits
for the compiler; ``SKELID_NUMBA=0`` disables it.
"""

from __future__ import annotations

import subprocess
import time

import numpy as np

from skelid.estimators import _lm_kernel

AVAILABLE = _lm_kernel.AVAILABLE


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
    from skelid.estimators._lm_kernel import _kinematics_planar, _kinematics_spatial, _workspace

    @_lm_kernel._jit
    def linearise(g, q, D, S, M, parent, dof_start, is_t, axis, skew, skew2, ms, moves, nz, tilt, planar,
                  jpar, A_joint, anc, mslot, A_marker):
        """``x (M, D)``, ``J (M, D, Q)``, ``K (M, D, P)`` at geometry ``g (G, 1)`` and pose ``q (Q, 1)``."""
        Q = q.shape[0]
        P = A_joint.shape[2] if A_joint.shape[0] else A_marker.shape[2]
        (cost, cost_new, lam, ok, bad, JtJ, Jtr, L, dinv, step, qn, R, Ri, E, ang, cs, sn, p, w, pivot, xk, r,
         Jk, acc, ux, uy, A1, r1, s1, ridge, nf, chk) = _workspace(Q, 1, S, M, D, 0.0, not planar)
        t_axis, t_skew, t_skew2 = np.zeros((0, 3, 1)), np.zeros((0, 3, 3, 1)), np.zeros((0, 3, 3, 1))
        if planar:
            _kinematics_planar(g, q, D, S, M, parent, dof_start, is_t, axis, skew, skew2, ms, R, Ri, E, ang, cs,
                               sn, p, w, pivot, xk, ux, uy, tilt, t_axis, t_skew, t_skew2)
        else:
            _kinematics_spatial(g, q, D, S, M, parent, dof_start, is_t, axis, skew, skew2, ms, R, Ri, E, ang,
                                cs, sn, p, w, pivot, xk, ux, uy, tilt, t_axis, t_skew, t_skew2)
        x = np.empty((M, D))
        J = np.zeros((M, D, Q))
        K = np.zeros((M, D, P))
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
        return x, J, K

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


# ------------------------------------------------------------------ compiled in the background, as the pose kernel
_found: dict[bool, bool] = {}
_last_check: dict[bool, float] = {}
_warming: dict[bool, subprocess.Popen] = {}


def _example_args(planar: bool) -> tuple:
    """Arguments with the types of every real call (values never used)."""
    f, i, b = np.zeros, np.int64, np.bool_
    return (f((4, 1)), f((1, 1)), 2, 1, 1, np.zeros(2, i), np.zeros(2, i), np.zeros(1, b), f((1, 3)),
            f((1, 3, 3)), f((1, 3, 3)), np.zeros(1, i), f((1, 1)), np.zeros((1, 3), b), np.zeros(1, i), planar,
            np.zeros(0, i), f((0, 2, 1)), f((0, 1)), np.full(1, -1, i), f((0, 2, 1)))


def _cached() -> bool:
    """Whether numba's disk cache holds :func:`linearise` for this machine and source."""
    try:
        sig = tuple(numba_typeof(a) for a in _example_args(True))
        cache = linearise._cache
        key = cache._index_key(sig, linearise.targetctx.codegen())
        return cache._cache_file._load_index().get(key) is not None
    except Exception:  # noqa: BLE001 - numba internals changed: compile when first called
        return True


def numba_typeof(a):
    import numba

    return numba.typeof(a)


def ready() -> bool:
    """Whether :func:`linearise` can run now without compiling in this process.

    As :func:`skelid.estimators._lm_kernel.ready`: False without numba (or with
    ``SKELID_NUMBA=0``); with ``SKELID_NUMBA=wait`` compiles first if need be;
    otherwise starts the compilation in a background process (once) and
    answers False until numba's cache holds it.
    """
    if not AVAILABLE:
        return False
    if _found.get(True) or linearise.signatures or _lm_kernel.MODE == "compile":
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
    """Compile :func:`linearise` into numba's disk cache in a separate process."""
    if not AVAILABLE:
        return False
    code = "from skelid.estimators._live_kernel import _compile_here; _compile_here()"
    return _lm_kernel.compile_in_background(_warming, True, code, _cached, wait, timeout)


def _compile_here() -> None:
    """Compile (or load) :func:`linearise` in this process."""
    linearise(*_example_args(True))
