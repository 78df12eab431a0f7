"""The joint fit's normal equations with the poses eliminated (its arrow structure).

Model: the joint fit minimises ``||y - f(beta)||^2 + q^T R q`` over ``beta = (theta, q_1..q_T)``,
``R`` the motion model's penalty on the poses (none: every pose on its own). With ``J = [J_theta,
J_q]`` its Gauss-Newton normal matrix is an arrow,

.. math::

    N = \\begin{pmatrix} H_{\\theta\\theta} & H_{q\\theta}^\\top \\\\ H_{q\\theta} & A \\end{pmatrix},
    \\qquad A = \\mathrm{blockdiag}_t(J_{q,t}^\\top J_{q,t}) + R \\ \\text{(banded)},

and eliminating the poses,

.. math::

    G = A^{-1} H_{q\\theta}, \\qquad S = H_{\\theta\\theta} - H_{q\\theta}^\\top G, \\qquad
    N^{-1} \\begin{pmatrix} g_\\theta \\\\ g_q \\end{pmatrix} =
    \\begin{pmatrix} d_\\theta \\\\ A^{-1} g_q - G d_\\theta \\end{pmatrix}, \\quad
    d_\\theta = S^{-1} (g_\\theta - G^\\top g_q).

``S`` is the information about ``theta`` (unit noise); ``N^{-1} J^T epsilon`` is the estimate's
linear response to the noise ``epsilon``, used by the bootstrap's control variate
(:mod:`skelid.estimators.uncertainty.bootstrap`), the second-order term's draws and the sd along the
profile (:mod:`skelid.estimators.uncertainty.singular`). One factorisation of ``A`` serves every right-hand
side.

Example
-------
>>> import numpy as np
>>> rng = np.random.default_rng(0)
>>> Jq, Jt = rng.normal(size=(4, 3, 1)), rng.normal(size=(4, 3, 2))
>>> el = eliminate_poses(Jq, Jt)
>>> g_t, g_q = rng.normal(size=(1, 2)), rng.normal(size=(1, 4, 1))
>>> d_t, d_q = solve_normal(el, g_t, g_q)
>>> J = np.zeros((12, 6)); J[:, :2] = Jt.reshape(12, 2)
>>> for t in range(4): J[3 * t:3 * t + 3, 2 + t] = Jq[t, :, 0]
>>> ref = np.linalg.solve(J.T @ J, np.concatenate([g_t[0], g_q[0, :, 0]]))
>>> bool(np.allclose(np.concatenate([d_t[0], d_q[0, :, 0]]), ref))
True
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from skelid._linalg import frame_gram, summed_gram
from skelid.estimators.fit.likelihood import pose_information


class Eliminated(NamedTuple):
    """The poses eliminated from the normal equations (see the module's docstring)."""

    S: np.ndarray  # (P, P) information about theta, unit noise
    G: np.ndarray  # (T, Q, P) A^{-1} H_{q theta}
    solve_poses: Callable  # (T*Q, K) -> A^{-1} rhs
    Hqq: np.ndarray  # (T, Q, Q) per-frame pose information
    Hqt: np.ndarray  # (T, Q, P)


def eliminate_poses(Jq, Jt, R=None, R_band=None) -> Eliminated:
    """Eliminate the poses from the joint fit's normal equations.

    Parameters
    ----------
    Jq : (T, m, Q) float
        Pose Jacobian of each frame's rows (weighted, zero for missing coordinates).
    Jt : (T, m, P) float
        Geometry Jacobian of the same rows.
    R : sparse (T*Q, T*Q), optional
        Motion-model penalty (frame-major). None: ``A`` is block-diagonal and solved frame by
        frame, a frame without rows keeping a ridge of ``1e-12`` of its scale.
    R_band : int, optional
        Bandwidth of ``R`` (found from it when not given).

    Returns
    -------
    Eliminated
    """
    from skelid.estimators.fit.joint import _banded_solver

    Jq, Jt = np.asarray(Jq, float), np.asarray(Jt, float)
    T, _, Q = Jq.shape
    P = Jt.shape[-1]
    Hqq = pose_information(Jq)
    Hqt = frame_gram(Jq, Jt)
    Htt = summed_gram(Jt)
    if R is None:
        d = np.einsum("tii->ti", Hqq)
        scale = np.maximum(d.mean(axis=1), max(d.mean(), 1e-300))
        A = Hqq + 1e-12 * scale[:, None, None] * np.eye(Q)

        def solve(rhs):
            rhs = np.asarray(rhs, float)
            K = rhs.shape[-1]
            return np.linalg.solve(A, rhs.reshape(T, Q, K)).reshape(T * Q, K)
    else:
        solve = _banded_solver(Hqq, R, R_band)
    G = solve(Hqt.reshape(T * Q, P)).reshape(T, Q, P)
    S = Htt - summed_gram(Hqt, G)
    return Eliminated(0.5 * (S + S.T), G, solve, Hqq, Hqt)


def solve_normal(el: Eliminated, g_t, g_q):
    """``N^{-1} g`` for ``K`` right-hand sides: ``g_t (K, P)``, ``g_q (K, T, Q)`` -> ``(K, P)``, ``(K, T, Q)``."""
    g_t, g_q = np.atleast_2d(np.asarray(g_t, float)), np.asarray(g_q, float)
    K, T, Q = g_q.shape
    u = el.solve_poses(g_q.reshape(K, T * Q).T).T.reshape(K, T, Q)
    d_t = np.linalg.solve(el.S, (g_t - np.einsum("tqp,ktq->kp", el.G, g_q)).T).T
    return d_t, u - np.einsum("tqp,kp->ktq", el.G, d_t)
