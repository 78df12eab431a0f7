"""Marker-space likelihood with the per-frame pose as a nuisance.

Model: for frames ``t = 1..T`` with present markers ``m``,

.. math:: y_{tm} = x_m(q_t, \\theta) + \\varepsilon_{tm}, \\qquad \\varepsilon \\sim N(0, \\sigma^2 I).

With ``r_t`` the stacked residuals, ``J_t = \\partial x/\\partial q`` and
``K_t = \\partial x/\\partial \\theta`` of frame ``t`` (missing markers give
zero rows), the Gauss-Newton normal equations of the joint problem in
``(\\theta, q_1, ..., q_T)`` have an arrow structure; eliminating the poses
(Schur complement) leaves

.. math:: S = \\sum_t K_t^\\top (I - P_t) K_t, \\qquad P_t = J_t (J_t^\\top J_t)^{-1} J_t^\\top ,

and ``S / \\sigma^2`` is the *efficient information* about ``\\theta``: its
inverse is the Cramér-Rao bound for an unbiased estimator of ``\\theta`` when
every pose is unknown.

Per-frame likelihoods of a hypothesis ``\\theta`` (used by grid filters):

* profile: ``-\\mathrm{RSS}_t(\\theta) / (2\\sigma^2)`` with ``RSS_t`` minimised over ``q_t``;
* Laplace (pose integrated out under a flat prior):
  ``-\\mathrm{RSS}_t(\\theta)/(2\\sigma^2) - \\tfrac12 \\log\\det J_t^\\top J_t``.

All functions broadcast over leading batch axes (frames, hypotheses).
"""

from __future__ import annotations

import numpy as np

from skelid._linalg import summed_gram
from skelid.model.description import Model
from skelid.model.kinematics import marker_jacobian


def frame_terms(model: Model, theta, q, y, ws=None):
    """Residuals and Jacobians with missing markers zeroed.

    Parameters
    ----------
    theta : (..., P) float
    q : (..., Q) float
    y : (..., M, D) float, NaN where missing
    ws : skelid.model.kinematics.Workspace, optional
        The model's workspace.

    Returns
    -------
    r : (..., M*D) float
    J_pose : (..., M*D, Q) float
    J_theta : (..., M*D, P) float
    """
    mask = np.isfinite(y).all(axis=-1)
    x, Jq, Jt = marker_jacobian(model, theta, q, ws)
    batch = x.shape[:-2]
    if mask.all() and np.shape(y) == x.shape:  # nothing missing: no rows to zero
        r = np.subtract(y, x, out=x)
    else:
        missing = ~mask
        if np.shape(y) == x.shape:
            r = np.subtract(y, x, out=x)
            r[missing] = 0.0  # only the missing rows are written (a few, usually)
        else:
            w = mask[..., None].astype(float)
            r = (np.where(mask[..., None], y, 0.0) - x) * w
        if Jq.shape[:-2] == missing.shape and Jq.flags.writeable and Jt.flags.writeable:
            Jq[missing] = 0.0  # fresh arrays from the kinematics: zeroed in place
            Jt[missing] = 0.0
        else:
            w = mask[..., None, None].astype(float)
            Jq, Jt = Jq * w, Jt * w
    return (r.reshape(batch + (-1,)), Jq.reshape(batch + (-1, model.n_pose)),
            Jt.reshape(batch + (-1, model.n_params)))


def pose_information(J_pose) -> np.ndarray:
    """``J^T J`` per frame: ``(..., Q, Q)``."""
    J_pose = np.asarray(J_pose)
    return np.matmul(np.swapaxes(J_pose, -1, -2), J_pose)


def pose_fixed(J_pose, rel_tol: float = 1e-8) -> np.ndarray:
    """Whether the markers present fix every pose coordinate: ``(...)`` bool.

    The pose information ``J^T J`` is scaled to unit diagonal (so that
    translations and rotations compare); the pose is fixed when no coordinate
    has a zero column and the smallest eigenvalue exceeds ``rel_tol``.
    """
    H = pose_information(J_pose)
    d = np.einsum("...ii->...i", H)
    good = (d > 0).all(axis=-1)
    s = 1.0 / np.sqrt(np.where(d > 0, d, 1.0))
    lam = np.linalg.eigvalsh(H * s[..., :, None] * s[..., None, :])[..., 0]
    return good & (lam > rel_tol)


def log_det_pose_information(J_pose) -> np.ndarray:
    """``log det(J^T J)`` per frame ``(...)``; ``-inf`` where the pose is not determined."""
    sign, logdet = np.linalg.slogdet(pose_information(J_pose))
    return np.where(sign > 0, logdet, -np.inf)


def projected_theta_jacobian(J_pose, J_theta, ridge: float = 1e-12):
    """``(I - P_t) K_t``: the part of ``dx/dtheta`` that no pose change can mimic.

    Returns
    -------
    K_perp : (..., m, P) float
    """
    H = pose_information(J_pose)
    Q = H.shape[-1]
    tr = np.einsum("...ii->...", H) / max(Q, 1)
    # a frame without rows (skipped) gets the mean scale, so that its projection is 0, not NaN
    scale = np.maximum(tr, max(float(np.mean(tr)) if tr.size else 0.0, 1e-300))
    # J_pose (H + ridge)^-1 first: (m, Q) times (Q, P) is cheaper than a solve with P right-hand sides
    W = J_pose @ np.linalg.inv(H + ridge * scale[..., None, None] * np.eye(Q))
    return J_theta - W @ np.matmul(np.swapaxes(J_pose, -1, -2), J_theta)


def efficient_information(J_pose, J_theta, sigma: float = 1.0) -> np.ndarray:
    """Efficient information about ``theta`` summed over frames: ``(P, P)``.

    Parameters
    ----------
    J_pose : (T, m, Q) float
    J_theta : (T, m, P) float
    sigma : float
        Marker noise standard deviation.
    """
    Kp = projected_theta_jacobian(J_pose, J_theta)
    return summed_gram(Kp) / sigma**2


def crlb_sd(info: np.ndarray) -> np.ndarray:
    """Square roots of the diagonal of the inverse information (NaN where singular)."""
    try:
        cov = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return np.full(info.shape[0], np.nan)
    d = np.diag(cov)
    return np.where(d > 0, np.sqrt(np.abs(d)), np.nan)
