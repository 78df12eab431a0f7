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

from skelid._linalg import summed_gram, summed_product
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


def projected_sums(J_pose, J_theta, r, row_dim: int, w=None, ridge: float = 1e-12) -> tuple:
    """:func:`projected_theta_jacobian`'s sums without the projected Jacobian itself.

    ``(S, K^T r)`` with ``S = sum_t K_perp^T K_perp`` and ``K^T r = sum_t K_perp^T r_t``; with row weights
    ``w (m,)`` (one per row, the same in every frame) also ``sum_t K_perp^T diag(w) K_perp``. As
    ``K_perp = (I - P_t) K_t`` with the projection ``P_t`` off the pose, ``S = sum_t K_t^T K_t - A_t^T H_t^-1
    A_t`` with ``A_t = J_t^T K_t`` (``(Q, P)`` per frame, where ``K_perp`` is ``(m, P)``). A parameter that
    moves one marker only (a marker's offset) has a column of ``K_t`` that is zero but for that marker's
    ``row_dim`` rows: such columns enter the sums through those rows only (:func:`_column_groups`).

    Parameters
    ----------
    J_pose : (T, m, Q) float
    J_theta : (T, m, P) float
    r : (T, m) float
    row_dim : int
        Rows per marker (the markers' dimension).
    """
    Jq, Jt = np.asarray(J_pose, float), np.asarray(J_theta, float)
    r = np.asarray(r, float)
    P = Jt.shape[-1]
    d, Hs = _unit_diagonal(pose_information(Jq), ridge)
    try:  # Hs^-1 = L^-T L^-1 (L L^T = Hs): A^T H^-1 A = B^T B with B = L^-1 D^-1 A, a symmetric product
        Li = np.linalg.inv(np.linalg.cholesky(Hs))
    except np.linalg.LinAlgError:  # not definite to rounding: its symmetric square root's inverse
        lam, V = np.linalg.eigh(Hs)
        Li = np.swapaxes(V / np.sqrt(np.maximum(lam, 1e-300))[..., None, :], -1, -2)
    dense, batches = _column_groups(Jt, row_dim)
    # the sums are made with the columns in this order (dense, then each batch's markers' own), then put back
    order = np.concatenate([dense] + [cols.ravel() for _, cols in batches]).astype(int)
    Kd = Jt[..., dense]
    local = [(rows, Jt[:, rows[:, :, None], cols[:, None, :]]) for rows, cols in batches]  # (T, G, row_dim, c)
    A = _pose_cross(Jq, Kd, local)  # (T, Q, n)
    B = Li @ (A / d[..., None])
    S = _grouped_gram(Kd, local) - summed_gram(B)
    Lr = Li @ (np.matmul(np.swapaxes(Jq, -1, -2), r[..., None]) / d[..., None])  # (T, Q, 1): L^-1 D^-1 J^T r
    Kr = np.concatenate([Kd.reshape(-1, dense.size).T @ r.reshape(-1)]
                        + [np.einsum("tgic,tgi->gc", k, r[:, rows]).ravel() for rows, k in local])
    out = (_put_back(0.5 * (S + S.T), order, P), _put_back(Kr - summed_product(B, Lr[..., 0]), order, P))
    if w is None:
        return out
    w = np.asarray(w, float)
    C = (np.swapaxes(Li, -1, -2) @ B) / d[..., None]  # H^-1 A
    E = _pose_cross(Jq * w[:, None], Kd, local)  # J^T W K per frame
    G = pose_information(Jq * np.sqrt(w)[:, None])  # J^T W J per frame
    cross = summed_gram(E, C)
    Sw = _grouped_gram(Kd, local, w) - cross - cross.T + summed_gram(C, G @ C)
    return out + (_put_back(0.5 * (Sw + Sw.T), order, P),)


def projected_score(J_pose, J_theta, r) -> np.ndarray:
    """``sum_t K_perp^T r_t`` (``(P,)``) alone: ``sum_t K_t^T (I - P_t) r_t``, the residuals projected off the pose
    (:func:`projected_sums` without the information's cost)."""
    Jq, Jt, r = (np.asarray(a, float) for a in (J_pose, J_theta, r))
    d, Hs = _unit_diagonal(pose_information(Jq))
    Jr = np.matmul(np.swapaxes(Jq, -1, -2), r[..., None]) / d[..., None]
    c = np.linalg.solve(Hs, Jr) / d[..., None]
    rp = r - np.matmul(Jq, c)[..., 0]
    return Jt.reshape(-1, Jt.shape[-1]).T @ rp.reshape(-1)


def _unit_diagonal(H, ridge: float = 1e-12) -> tuple:
    """``(d, Hs)``: the pose information scaled to a unit diagonal, ``H = D Hs D`` with ``D = diag(d)``, plus
    ``ridge`` times the identity. Translations beside rotations leave ``H``'s condition at 1e6-1e7 (a gait
    model's frames): ``A^T H^-1 A`` from ``H`` itself lost 5e-7 of the information, against 4e-14 scaled."""
    d = np.sqrt(np.einsum("...ii->...i", H))
    d = np.where(d > 0.0, d, 1.0)  # a pose coordinate without rows (or a frame without markers)
    return d, H / d[..., :, None] / d[..., None, :] + ridge * np.eye(H.shape[-1])


def _column_groups(J_theta, row_dim: int) -> tuple:
    """``(dense, [(rows (G, row_dim), columns (G, c)), ...])``: the columns of ``J_theta`` that are non-zero in
    the rows of more than one marker, and batches of markers with ``c`` columns each that are non-zero in that
    marker's rows only (one batch per ``c``). Columns zero everywhere are in neither."""
    T, m, P = J_theta.shape
    M = m // row_dim
    nz = np.logical_or.reduce(J_theta != 0.0, axis=0).reshape(M, row_dim, P).any(axis=1)  # (M, P)
    count = nz.sum(axis=0)
    own = nz & (count == 1)
    per = own.sum(axis=1)
    batches = []
    for c in np.unique(per[per > 0]):
        ks = np.flatnonzero(per == c)
        cols = np.array([np.flatnonzero(own[k]) for k in ks])
        batches.append((ks[:, None] * row_dim + np.arange(row_dim), cols))
    return np.flatnonzero(count > 1), batches


def _put_back(x, order, P: int) -> np.ndarray:
    """``x`` (over the columns ``order``) as ``(P,)`` or ``(P, P)``, zero elsewhere."""
    out = np.zeros((P,) * x.ndim)
    out[np.ix_(*(order,) * x.ndim)] = x
    return out


def _grouped_gram(Kd, local, w=None) -> np.ndarray:
    """``sum_t K_t^T diag(w) K_t`` over the columns ``Kd`` (``(T, m, D)``) and each batch's own (``local``: rows
    ``(G, row_dim)`` and ``(T, G, row_dim, c)`` values, :func:`projected_sums`), in that order."""
    T, _, D = Kd.shape
    n = D + sum(k.shape[1] * k.shape[3] for _, k in local)
    out = np.zeros((n, n))
    out[:D, :D] = summed_gram(Kd, w=w)
    at = D
    for rows, k in local:
        G, c = k.shape[1], k.shape[3]
        kw = k if w is None else k * w[rows][None, :, :, None]
        idx = at + np.arange(G * c).reshape(G, c)
        out[idx[:, :, None], idx[:, None, :]] = np.einsum("tgic,tgid->gcd", kw, k)
        if D:  # row by row of the batch's markers over the frames, then each marker's rows summed
            block = np.matmul(np.moveaxis(kw, 0, 3), np.moveaxis(Kd[:, rows], 0, 2)).sum(axis=1)  # (G, c, D)
            out[at:at + G * c, :D] = block.reshape(G * c, D)
            out[:D, at:at + G * c] = block.reshape(G * c, D).T
        at += G * c
    return out


def _pose_cross(Jq, Kd, local) -> np.ndarray:
    """``J_t^T K_t`` per frame (``(T, Q, n)``) over the columns ``Kd`` and each batch's own, in that order
    (:func:`_grouped_gram`)."""
    T, _, Q = Jq.shape
    parts = [np.matmul(np.swapaxes(Jq, -1, -2), Kd)]
    for rows, k in local:  # (T, G, Q, c) -> (T, Q, G * c)
        part = np.matmul(np.swapaxes(Jq[:, rows], -1, -2), k)
        parts.append(np.moveaxis(part, 2, 1).reshape(T, Q, -1))
    return np.concatenate(parts, axis=-1)


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
