"""Batch estimation of ``theta`` and every pose at once, and its bias.

**Joint least squares.** Levenberg-Marquardt on ``(theta, q_1..q_T)``. Each
iteration eliminates the poses through the Schur complement (see
:mod:`skelid.estimators.likelihood`), so the cost is linear in ``T``:

.. math::

    S\\,\\delta\\theta = g_\\theta - \\sum_t H_{\\theta q,t} H_{qq,t}^{-1} g_{q,t},
    \\qquad \\delta q_t = H_{qq,t}^{-1}(g_{q,t} - H_{q\\theta,t}\\,\\delta\\theta).

**Second-order bias (Box 1971).** For ``y = f(\\beta) + \\varepsilon`` with
``\\beta = (\\theta, q_1..q_T)`` the least-squares estimate has bias

.. math:: b = -\\tfrac{\\sigma^2}{2} C J^\\top d, \\quad d_i = \\mathrm{tr}(C \\nabla^2 f_i),

with ``C = (J^\\top J)^{-1}``,
to order ``\\sigma^2``. Because every frame brings its own pose (the
incidental-parameter, or Neyman-Scott, problem) the ``theta`` part of ``b``
does not shrink with ``T``. Using the arrow structure,

.. math:: b_\\theta = -\\tfrac{\\sigma^2}{2} S^{-1} \\sum_t \\big((I-P_t)K_t\\big)^\\top d_t ,

where ``d_t`` needs only the ``(theta, q_t)`` block ``C_t`` of ``C``. Writing
``C_t = L L^T``, ``d_{t,i} = \\sum_k l_k^\\top \\nabla^2 f_{t,i}\\, l_k`` is a sum of
directional second derivatives, taken by central differences of the analytic
Jacobian. Subtracting ``b`` is the "hyperaccurate" correction of geometric
fitting (Kanatani).

**Serially correlated residuals.** Soft-tissue artefact makes residuals slow
and smooth. The per-frame scores ``s_t = ((I-P_t)K_t)^T r_t`` then correlate,
and the Newey-West (Bartlett-kernel) estimate
``S^{-1} (\\sum_{|l|\\le L} w_l \\sum_t s_t s_{t+l}^T) S^{-1}`` replaces
``\\sigma^2 S^{-1}``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from skelid.estimators.likelihood import frame_terms, pose_information, projected_theta_jacobian
from skelid.model.description import Model
from skelid.model.kinematics import marker_jacobian


class JointFit(NamedTuple):
    theta: np.ndarray  # (P,)
    pose: np.ndarray  # (T, Q); frames not used keep their starting pose
    rss: float
    rss_frame: np.ndarray  # (T,); zero for frames not used
    info: np.ndarray  # (P, P) S = sum_t K_perp^T K_perp (unit noise)
    n_obs: int  # coordinates used
    frames_used: np.ndarray  # (T,) bool
    n_iter: int
    converged: bool


def usable_frames(model: Model, y) -> np.ndarray:
    """(T,) bool: frames with enough coordinates to fix the pose and inform theta."""
    n = np.isfinite(y).all(axis=-1).sum(axis=-1) * model.dim
    return n > model.n_pose


def _normal_blocks(r, Jq, Jt):
    Hqq = pose_information(Jq)
    Hqt = np.einsum("tki,tkp->tip", Jq, Jt)
    Htt = np.einsum("tkp,tkq->pq", Jt, Jt)
    gq = np.einsum("tki,tk->ti", Jq, r)
    gt = np.einsum("tkp,tk->p", Jt, r)
    return Hqq, Hqt, Htt, gq, gt


def _schur_step(Hqq, Hqt, Htt, gq, gt, lam):
    Q, P = Hqq.shape[-1], Htt.shape[0]
    dq_ = np.einsum("tii->ti", Hqq)
    # ridge relative to the frame's own scale, or to the trial's for a frame with no rows
    scale = np.maximum(dq_.mean(axis=1), max(dq_.mean(), 1e-300))
    A = Hqq + (lam * dq_)[..., None] * np.eye(Q) + 1e-12 * scale[:, None, None] * np.eye(Q)
    sol = np.linalg.solve(A, np.concatenate([Hqt, gq[..., None]], axis=-1))
    G, u = sol[..., :P], sol[..., P]
    dt_ = np.diag(Htt)
    S = Htt + lam * np.diag(dt_) + 1e-12 * max(dt_.mean(), 1e-300) * np.eye(P) \
        - np.einsum("tip,tiq->pq", Hqt, G)
    rhs = gt - np.einsum("tip,ti->p", Hqt, u)
    dtheta = np.linalg.solve(S, rhs)
    dq = u - np.einsum("tip,p->ti", G, dtheta)
    return dtheta, dq


def joint_fit(model: Model, y, theta0, q0, n_iter: int = 100, tol: float = 1e-12,
              bounds: tuple | None = None, frames=None) -> JointFit:
    """Least squares over ``theta`` and all poses.

    Parameters
    ----------
    y : (T, M, D) float
        Markers (model units), NaN where missing.
    theta0 : (P,) float
    q0 : (T, Q) float
        Starting poses (e.g. from :func:`skelid.estimators.pose.track_poses`).
    bounds : (lower (P,), upper (P,)), optional
        Keep ``theta`` inside these bounds (steps are clipped).
    frames : (T,) bool, optional
        Frames allowed into the fit (others are skipped), on top of the count
        of :func:`usable_frames`.
    """
    y = np.asarray(y, dtype=float)
    use = usable_frames(model, y)
    if frames is not None:
        use &= np.asarray(frames, dtype=bool)
    y = np.where(use[:, None, None], y, np.nan)  # skipped frames give zero rows: no part in the fit
    theta = np.array(theta0, dtype=float)
    q = np.array(q0, dtype=float)
    r, Jq, Jt = frame_terms(model, theta, q, y)
    cost = float(np.sum(r**2))
    lam = 1e-3
    converged = False
    it = 0
    for it in range(1, n_iter + 1):  # noqa: B007 - the count is reported
        Hqq, Hqt, Htt, gq, gt = _normal_blocks(r, Jq, Jt)
        try:
            dtheta, dq = _schur_step(Hqq, Hqt, Htt, gq, gt, lam)
        except np.linalg.LinAlgError:
            lam *= 10.0
            continue
        theta_new = theta + dtheta
        if bounds is not None:
            theta_new = np.clip(theta_new, bounds[0], bounds[1])
        q_new = q + dq
        r_new, Jq_new, Jt_new = frame_terms(model, theta_new, q_new, y)
        cost_new = float(np.sum(r_new**2))
        if np.isfinite(cost_new) and cost_new <= cost:
            small = (cost - cost_new) <= tol * max(cost, 1e-300)
            theta, q, r, Jq, Jt, cost = theta_new, q_new, r_new, Jq_new, Jt_new, cost_new
            lam = max(lam * 0.3, 1e-12)
            if small:
                converged = True
                break
        else:
            lam *= 10.0
            if lam > 1e12:
                converged = True  # no descent direction left: at a minimum to precision
                break
    Kp = projected_theta_jacobian(Jq, Jt)
    info = np.einsum("tkp,tkq->pq", Kp, Kp)
    return JointFit(theta, q, cost, np.sum(r**2, axis=1), info,
                    int(np.isfinite(y).all(axis=-1).sum() * model.dim), use, it, converged)


def box_bias(model: Model, y, theta, q, sigma2: float, step: float = 1e-4) -> np.ndarray:
    """Second-order bias ``b_theta`` (P,) of the joint least-squares estimate.

    Parameters
    ----------
    y : (T, M, D) float
        Markers (only the missing-marker pattern is used).
    theta : (P,) float
    q : (T, Q) float
        The fit's poses.
    sigma2 : float
        Noise variance.
    step : float
        Relative size of the finite-difference step along each direction.
    """
    P, Q = model.n_params, model.n_pose
    r, Jq, Jt = frame_terms(model, theta, q, y)
    Hqq = pose_information(Jq)
    Hqt = np.einsum("tki,tkp->tip", Jq, Jt)
    Hqq_inv = np.linalg.pinv(Hqq, hermitian=True)
    G = Hqq_inv @ Hqt  # (T, Q, P)
    Kp = Jt - Jq @ G
    S = np.einsum("tkp,tkq->pq", Kp, Kp)
    S_inv = np.linalg.inv(S)
    T = len(q)
    C = np.empty((T, P + Q, P + Q))
    C[:, :P, :P] = S_inv
    C[:, P:, :P] = -G @ S_inv
    C[:, :P, P:] = np.swapaxes(C[:, P:, :P], 1, 2)
    C[:, P:, P:] = Hqq_inv + G @ S_inv @ np.swapaxes(G, 1, 2)
    w, V = np.linalg.eigh(C)
    L = V * np.sqrt(np.clip(w, 0.0, None))[:, None, :]  # (T, P+Q, K) columns l_k
    # directional second derivatives along each column, all frames and directions at once
    norms = np.linalg.norm(L, axis=1, keepdims=True)  # (T, 1, K)
    h = step / np.maximum(norms, 1e-300)
    dirs = np.swapaxes(L, 1, 2)  # (T, K, P+Q)
    th = theta[None, None, :] + 0.0 * dirs[..., :P]
    qq = q[:, None, :] + 0.0 * dirs[..., P:]
    hh = np.swapaxes(h, 1, 2)  # (T, K, 1)
    _, Jq_p, Jt_p = marker_jacobian(model, th + hh * dirs[..., :P], qq + hh * dirs[..., P:])
    _, Jq_m, Jt_m = marker_jacobian(model, th - hh * dirs[..., :P], qq - hh * dirs[..., P:])
    Jp = np.concatenate([Jt_p, Jq_p], axis=-1)  # (T, K, M, D, P+Q)
    Jm = np.concatenate([Jt_m, Jq_m], axis=-1)
    second = np.einsum("tkmdj,tkj->tkmd", Jp - Jm, dirs) / (2.0 * hh[..., None])
    mask = np.isfinite(y).all(axis=-1)
    d = (second.sum(axis=1) * mask[..., None]).reshape(T, -1)  # (T, M*D)
    return -0.5 * sigma2 * S_inv @ np.einsum("tkp,tk->p", Kp, d)


def frame_scores(model: Model, y, theta, q) -> np.ndarray:
    """Per-frame scores ``((I-P_t)K_t)^T r_t``: ``(T, P)``."""
    r, Jq, Jt = frame_terms(model, theta, q, y)
    return np.einsum("tkp,tk->tp", projected_theta_jacobian(Jq, Jt), r)


def newey_west(scores, lags: int) -> np.ndarray:
    """Long-run covariance ``(P, P)`` of a score series ``(T, P)`` (Bartlett weights)."""
    s = scores - scores.mean(axis=0)
    out = s.T @ s
    for lag in range(1, lags + 1):
        w = 1.0 - lag / (lags + 1.0)
        g = s[lag:].T @ s[:-lag]
        out += w * (g + g.T)
    return out


def lag1_autocorrelation(resid, used) -> float:
    """Mean lag-1 autocorrelation of the residual coordinates ``(T, M, D)`` over used frames."""
    r = resid[used]
    if len(r) < 4:
        return 0.0
    r = r - np.nanmean(r, axis=0)
    num = np.nansum(r[1:] * r[:-1], axis=0)
    den = np.nansum(r**2, axis=0)
    ok = den > 0
    return float(np.mean(num[ok] / den[ok])) if ok.any() else 0.0
