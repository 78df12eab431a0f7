"""Parametric bootstrap of the joint fit with a linear control variate.

Model: data are simulated from the fit, ``y*_b = f(theta, q) + e_b`` with ``e_b ~ N(0, sigma^2 I)``,
and refitted; the refit's shift ``s_b = theta*_b - theta`` has mean ``E[s]``, the bias of the
estimator at ``(theta, q)``. Its first Gauss-Newton step from ``(theta, q)``,

.. math::

    l_b = S^{-1} \\sum_t K_t^\\top e_{b,t}, \\qquad K_t = J_{\\theta,t} - J_{q,t} G_t,
    \\qquad G = (\\mathrm{blockdiag}(J_q^\\top J_q) + R)^{-1} J_q^\\top J_\\theta,
    \\qquad S = J_\\theta^\\top J_\\theta - \\textstyle\\sum_t J_{\\theta,t}^\\top J_{q,t} G_t,

(``R`` the refit's motion-model penalty, built from the same starting poses) is linear in
the noise, so ``E[l] = 0`` exactly, and its covariance is known,
``Var(l) = sigma^2 S^{-1} (\\sum_t K_t^\\top K_t) S^{-1}``. The shift is ``l_b`` plus a rest
(the curvature of the model: the bias, and a spread of its own) that varies far less than
``l_b`` does (case A, sigma 15 mm: the rest's sd is 0.27 of the estimate's sd at 10^3 frames,
0.37 at 10^4; the shift's is 0.9-1.4). Hence

.. math::

    \\hat b = \\frac{1}{B} \\sum_b (s_b - l_b), \\qquad
    \\widehat{\\mathrm{Var}}(s) = \\mathrm{Var}(l) + \\widehat{\\mathrm{Cov}}(s) - \\widehat{\\mathrm{Cov}}(l),

with Monte Carlo error ``Cov(s - l) / B`` instead of ``Cov(s) / B``: a few refits do what many
did without it. All ``l_b`` cost one factorisation of the pose system with ``B`` more
right-hand sides. The same linear steps start the refits after the first one near their own
solutions: refit ``b`` starts at refit 1's solution moved by ``l_b - l_1`` (poses likewise), so
it only has to find its own part of the rest; every refit minimises the same cost (the penalty
is built once, at the simulated poses), whatever its start.

Example
-------
>>> import numpy as np
>>> d = Draws(np.array([[1.0], [3.0]]), np.array([[-1.0], [1.0]]), np.array([[4.0]]))
>>> float(draws_bias(d)[0]), float(draws_covariance(d)[0, 0])
(2.0, 4.0)
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from skelid.estimators.fit.joint import (
    _continuous_poses,
    penalty_band,
    smoothing_penalty,
    usable_frames,
    weighted_terms,
)
from skelid.estimators.fit.likelihood import pose_information
from skelid.estimators.uncertainty.normal import eliminate_poses, solve_normal
from skelid.model.description import Model
from skelid.model.kinematics import Workspace


class Draws(NamedTuple):
    """Refits of a parametric bootstrap with their linear control variates."""

    shifts: np.ndarray  # (B, P) refit less the geometry simulated at
    linear: np.ndarray  # (B, P) the linear response to the same noise (mean zero), or zeros
    linear_cov: np.ndarray  # (P, P) its exact covariance (zeros when no control variate is used)


class LinearResponse(NamedTuple):
    """The joint fit's first Gauss-Newton step from the simulated point, for each noise draw."""

    theta: np.ndarray  # (B, P) steps in theta
    pose: np.ndarray  # (B, T, Q) steps in the poses
    cov_unit: np.ndarray  # (P, P) covariance of the theta step for unit noise variance
    q_start: np.ndarray  # (T, Q) the refits' starting poses (unwrapped where a motion model applies)
    penalty: object  # the refits' motion-model penalty (sparse) or None


def as_draws(shifts) -> Draws:
    """Plain refit shifts ``(B, P)`` as :class:`Draws` without a control variate (a :class:`Draws` as it is)."""
    if isinstance(shifts, Draws):
        return shifts
    s = np.atleast_2d(np.asarray(shifts, float))
    return Draws(s, np.zeros_like(s), np.zeros((s.shape[1], s.shape[1])))


def _cov(x) -> np.ndarray:
    B, P = x.shape
    return np.atleast_2d(np.cov(x, rowvar=False)) if B > 1 else np.zeros((P, P))


def draws_bias(d: Draws) -> np.ndarray:
    """``mean(s - l)``: the bias, (P,)."""
    return np.mean(d.shifts - d.linear, axis=0)


def draws_covariance(d: Draws) -> np.ndarray:
    """The refits' covariance: ``Var(l) + Cov(s) - Cov(l)`` (sample covariances), (P, P)."""
    return d.linear_cov + _cov(d.shifts) - _cov(d.linear)


def draws_mc_covariance(d: Draws) -> np.ndarray:
    """Monte Carlo covariance of :func:`draws_bias`: ``Cov(s - l) / B``, (P, P)."""
    return _cov(d.shifts - d.linear) / len(d.shifts)


def linear_response(model: Model, y, theta, q, noise, rate: float | None = None, cutoff=None,
                    ws: Workspace | None = None) -> LinearResponse:
    """First Gauss-Newton step (no damping) of the joint fit from ``(theta, q)`` for data ``f(theta, q) + noise``.

    Parameters
    ----------
    model : Model
    y : (T, M, D) float
        Markers; only where they are missing (NaN) matters: those coordinates have no rows.
    theta : (P,) float
    q : (T, Q) float
        The poses the data are simulated at.
    noise : (B, T, M, D) float
        Noise draws.
    rate, cutoff : float, optional
        With both, the refits' motion model (:func:`skelid.estimators.fit.joint.smoothing_penalty`,
        built from the Jacobians at ``(theta, q)``, as :func:`~skelid.estimators.fit.joint.joint_fit`
        builds it from its starting poses).
    ws : Workspace, optional

    Returns
    -------
    LinearResponse
        ``theta``: ``(B, P)`` steps ``S^{-1} sum_t K_t^T e_t`` (see the module's docstring), exactly
        linear in the noise; ``pose``: ``(B, T, Q)``; ``cov_unit``: ``S^{-1} (sum_t K_t^T K_t) S^{-1}``.
        The motion model's pull on the simulated poses themselves (``R q``) is left out: it does not
        depend on the noise, so it belongs to the rest.
    """
    y = np.asarray(y, float)
    use = usable_frames(model, y)
    y = np.where(use[:, None, None], y, np.nan)
    theta = np.asarray(theta, float)
    smooth = rate is not None and cutoff is not None
    q = _continuous_poses(model, q, use) if smooth else np.array(q, float)
    _, Jq, Jt = weighted_terms(model, theta, q, y, None, ws)  # rows of missing coordinates are zero
    T, Q = q.shape
    noise = np.asarray(noise, float)
    B = noise.shape[0]
    E = np.where(np.isfinite(y)[None], noise, 0.0).reshape(B, T, -1)
    gq = np.einsum("tkq,btk->btq", Jq, E)  # (B, T, Q)
    gt = np.einsum("tkp,btk->bp", Jt, E)  # (B, P)
    R = smoothing_penalty(model, pose_information(Jq), rate, cutoff) if smooth else None
    el = eliminate_poses(Jq, Jt, R, penalty_band(R, Q) if smooth else None)
    dtheta, dq = solve_normal(el, gt, gq)  # (B, P), (B, T, Q)
    X = np.einsum("tip,tiq->pq", el.Hqt, el.G)
    KK = el.S - X.T + np.einsum("tip,tij,tjq->pq", el.G, el.Hqq, el.G)  # sum_t K_t^T K_t
    S_inv = np.linalg.inv(el.S)
    cov = S_inv @ KK @ S_inv
    return LinearResponse(dtheta, dq, 0.5 * (cov + cov.T), q, R)
