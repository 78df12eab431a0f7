"""Checks on a fit that say how far its numbers can be trusted.

**Joint range as a rotation angle.** A joint with two or three rotation axes
(universal, spherical) is described by its relative rotation
``R_t = R_{world,parent}^T R_{world,seg}`` at each frame. Its mean ``R_bar``
(the chordal L2 mean, :meth:`scipy.spatial.transform.Rotation.mean`) is the
joint's typical posture, and the joint's excursion at frame ``t`` is the
rotation angle

.. math:: \\alpha_t = \\lVert \\log(\\bar R^\\top R_t) \\rVert ,

which, unlike Euler angles, does not swing through 180 degrees near gimbal lock.
The reported range is ``2 * quantile_{0.95}(alpha)``: the opening of the cone
(about the mean posture) holding 95 % of the frames, which for a one-axis joint
swinging symmetrically equals its range of motion. One-axis joints (and every
joint of a planar model) keep the central 95 % range of their angle about its
circular mean.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from skelid._linalg import summed_gram, summed_product
from skelid.model.description import Model
from skelid.model.kinematics import Workspace, forward_kinematics

#: the range of a multi-axis joint is twice this quantile of its rotation angle from the mean
RANGE_QUANTILE = 0.95
#: a joint that moves less than this (degrees) gives little functional information: a trial whose joints all
#: moved less is a static one, whose geometry follows from where the model places the markers
STILL_JOINT_DEG = 5.0


def joint_rotations(model: Model) -> np.ndarray:
    """Indices of the pose coordinates that rotate a joint (every rotation but the root's): ``(K,) int``."""
    return np.array([k for k, d in enumerate(model.dofs)
                     if d.kind == "R" and model.segments[d.segment].parent is not None], dtype=int)


def joint_ranges(model: Model, pose, used=None, theta=None) -> dict[str, list[float]]:
    """Range of every joint rotation but the root's, in degrees.

    Parameters
    ----------
    pose : (T, Q) float
    used : (T,) bool, optional
        Frames to include.
    theta : (P,) float, optional
        Parameters (they matter only for tilted hinge axes); default the prior centres.

    Returns
    -------
    dict
        joint name -> ``[range]`` for a multi-axis joint of a 3-D model (rotation angle,
        see the module notes), or one range per rotation coordinate otherwise.
    """
    pose = np.asarray(pose, float)
    if used is not None:
        pose = pose[np.asarray(used, bool)]
    out: dict[str, list[float]] = {}
    if len(pose) == 0:
        return out
    kin = None
    for s, seg in enumerate(model.segments):
        if seg.parent is None:
            continue
        ks = [k for k, d in enumerate(model.dofs) if d.segment == s and d.kind == "R"]
        if not ks:
            continue
        if model.dim == 3 and len(ks) > 1:
            if kin is None:
                th = model.theta_center if theta is None else np.asarray(theta, float)
                kin = forward_kinematics(model, th, pose)
            R_rel = np.swapaxes(kin.R_world_parent[:, s], -1, -2) @ kin.R_world_seg[:, s]
            rot = Rotation.from_matrix(R_rel)
            alpha = (rot.mean().inv() * rot).magnitude()
            out[seg.joint.name] = [round(float(np.degrees(2.0 * np.quantile(alpha, RANGE_QUANTILE))), 2)]
            continue
        z = np.exp(1j * pose[:, ks])
        ang = np.angle(z * np.conj(z.mean(axis=0)))  # about the circular mean, in (-pi, pi]
        lo, hi = np.percentile(ang, [2.5, 97.5], axis=0)
        out[seg.joint.name] = [round(float(v), 2) for v in np.degrees(hi - lo)]
    return out


#: family-wise false-alarm rate of the misfit test (split evenly over the joints tested)
MISFIT_ALPHA = 0.01
#: share of a segment's angle-driven residual that its markers have in common, above which it is the
#: joint model, not soft tissue (soft-tissue artefact moves each marker its own way)
MISFIT_COMMON = 0.5
#: polynomial degree in each rotation coordinate of the joint for the residual regression
MISFIT_DEGREE = 3
#: share of a one-rotation joint's false-alarm rate given to its rolling-path test (the rest to the broad test)
MISFIT_PATH_SHARE = 0.8
#: a significant misfit is flagged only where the systematic part of the residuals would move some parameter's
#: estimate by at least this many of its standard deviations (see model_misfit, "Effect size")
MISFIT_EFFECT = 0.5
#: ... and where the pattern's rms is at least this share of the model's size (1e-5: 0.01 mm on a
#: 1 m body, below what optical motion capture resolves; on exact data a fit stopped at that level
#: leaves patterns of 1e-4 mm that move an estimate by many of its tiny sds but change nothing)
MISFIT_MIN_RMS = 1e-5
#: a joint's test is not trusted when the second-order mean of its residuals could shift its statistic
#: by more than this many times its degrees of freedom (a bound on the non-centrality, see model_misfit)
MISFIT_NONLINEAR = 0.5


def _per_frame_projection(model: Model, theta, pose, y):
    """Residuals re-projected per frame, and the per-frame pose hat matrices' pieces.

    One Gauss-Newton step of each frame's pose from ``pose`` (no motion model) leaves the
    residual ``r~_t = (I - P_t) r_t`` with ``P_t = J_t (J_t^T J_t)^+ J_t^T``; under a correct
    model with white noise, ``r~_t ~ N(0, sigma^2 (I - P_t))`` independently over frames
    (to first order), whatever smoothing the fit used.

    Parameters
    ----------
    theta : (P,) float
    pose : (..., T, Q) float
    y : (..., T, M, D) float

    Returns
    -------
    r : (..., T, M*D) float, zero where missing
    Jq : (..., T, M*D, Q) float
    Hinv : (..., T, Q, Q) float
    """
    r, Jq, Hinv, _ = _projection_terms(model, theta, pose, y)
    return r, Jq, Hinv


def _projection_terms(model: Model, theta, pose, y):
    """:func:`_per_frame_projection`'s ``(r, Jq, Hinv)`` and the parameter Jacobian ``Jt (..., T, M*D, P)``."""
    from skelid.estimators.fit.likelihood import frame_terms

    r, Jq, Jt = frame_terms(model, theta, pose, y)
    H = np.einsum("...kq,...kp->...qp", Jq, Jq)
    Hinv = np.linalg.pinv(H, hermitian=True)
    r = _project_out(Jq, Hinv, r[..., None])[..., 0]
    return r, Jq, Hinv, Jt


def _project_out(Jq, Hinv, X):
    """``(I - P_t) X`` for ``X (..., T, K, n)``: each frame's pose directions out (``P_t = J_q H^-1 J_q^T``)."""
    return X - Jq @ (Hinv @ (np.swapaxes(Jq, -1, -2) @ X))


def misfit_noise(r, Jq, Hinv, present) -> tuple[float, int]:
    """White-noise sd from successive differences of the re-projected residuals.

    ``E ||r~_{t+1} - r~_t||^2 = sigma^2 sum_k (2 - P_{t+1,kk} - P_{t,kk})`` over the coordinates
    present in both frames; a residual pattern that follows the (slowly changing) joint angles
    barely enters the differences, so a misfit does not inflate it.

    Parameters
    ----------
    r : (..., T, K) float
    Jq : (..., T, K, Q) float
    Hinv : (..., T, Q, Q) float
    present : (T, K) bool

    Returns
    -------
    sigma : float, or (...) float for batched residuals
    dof : int
        Coordinates in the differences less their leverage (for an F reference).
    """
    lev = np.sum((Jq @ Hinv) * Jq, axis=-1)  # diagonal of P_t
    both = present[1:] & present[:-1]
    d2 = np.sum(np.where(both, (r[..., 1:, :] - r[..., :-1, :]) ** 2, 0.0), axis=(-2, -1))
    expect = np.sum(np.where(both, 2.0 - lev[..., 1:, :] - lev[..., :-1, :], 0.0), axis=(-2, -1))
    sigma = np.sqrt(d2 / np.where(expect > 0, expect, np.nan))
    dof = int(np.mean(expect) / 2)
    return (float(sigma) if np.ndim(sigma) == 0 else sigma), dof


class _Design(NamedTuple):
    """One joint's residual regression: which frames and rows, the basis, the contrasts, their covariance."""

    joint: str
    segment: str  # the child segment
    ok: np.ndarray  # (T,) bool: frames with every marker of the two segments
    rows: np.ndarray  # (n D,) residual rows of the two segments' markers
    basis: np.ndarray  # (T_ok, k) orthonormal powers of the joint angles, centred
    R_parent: np.ndarray  # (T_ok, D, D) the parent's rotation
    child: np.ndarray  # (n_child,) positions of the child's markers among the n
    contrast: np.ndarray  # (k D, k n D): child markers' mean pattern less the parent's
    own: np.ndarray  # (k n_child D, k n D): each child marker's pattern about the child's mean
    C: np.ndarray  # (k n D, k n D): covariance of the coefficients for unit noise
    R_child: np.ndarray  # (T_ok, D, D) the child's rotation
    nonrigid: np.ndarray  # (n_child D, n_child D): projector onto the child markers' deformations


def _designs(model: Model, kin, pose_u, present, Jq, Hinv, with_cov: bool = True) -> list[_Design]:
    """The regression of every joint's residuals on powers of its angles (see :func:`model_misfit`)."""
    D = model.dim
    seg_of = np.asarray(model.marker_segment)
    out = []
    for s, seg in enumerate(model.segments):
        p = int(model.parent_index[s])
        ks = [k for k, d in enumerate(model.dofs) if d.segment == s and d.kind == "R"]
        ms = np.flatnonzero((seg_of == s) | (seg_of == p))
        child = np.flatnonzero(seg_of[ms] == s)
        if p < 0 or not ks or len(child) == 0:
            continue
        ok = present[:, ms].all(axis=1)
        T = int(ok.sum())
        if T < 20:
            continue
        u = pose_u[ok][:, ks]
        u = (u - u.mean(axis=0)) / np.maximum(u.std(axis=0), 1e-12)
        X = np.concatenate([u**e for e in range(1, MISFIT_DEGREE + 1)], axis=1)
        X = X - X.mean(axis=0)
        Qx, Rx = np.linalg.qr(X)
        Qx = Qx * np.where(np.diag(Rx) < 0, -1.0, 1.0)  # one sign convention: replicates' bases agree
        B = Qx[:, np.abs(np.diag(Rx)) > 1e-8 * max(np.abs(np.diag(Rx)).max(), 1e-300)]  # (T, k)
        rows = (ms[:, None] * D + np.arange(D)).ravel()
        Rp = kin.R_world_seg[ok, p]  # (T, D, D)
        k = B.shape[1]
        C = _coefficient_cov(B, Jq[ok][:, rows], Hinv[ok], Rp, len(ms)) if with_cov else None
        # the contrast: the child's markers' mean pattern less the parent's (a joint that cannot follow
        # the data moves the child against the parent; the fit shares the error between the two)
        wts = np.where(seg_of[ms] == s, 1.0 / len(child), 0.0)
        if len(child) < len(ms):
            wts = wts - np.where(seg_of[ms] == s, 0.0, 1.0 / (len(ms) - len(child)))
        L = np.kron(np.eye(k), np.kron(wts[None, :], np.eye(D)))
        own = np.zeros((len(ms), len(ms)))
        own[child[:, None], child[None, :]] = np.eye(len(child)) - 1.0 / len(child)
        Lo = np.kron(np.eye(k), np.kron(own[child], np.eye(D)))
        m_child = np.einsum("ji,mj->mi", kin.R_world_seg[0, s], kin.markers[0, ms[child]] - kin.p_world_seg[0, s])
        out.append(_Design(seg.joint.name, seg.name, ok, rows, B, Rp, child, L, Lo, C, kin.R_world_seg[ok, s],
                           nonrigid_projector(m_child)))
    return out


def nonrigid_projector(m) -> np.ndarray:
    """Projector onto the displacements of markers ``m (n, D)`` that no rigid motion makes.

    The rigid displacements of markers at ``m_i`` (one segment's frame) are ``a + b x m_i``
    (3-D; ``a + b J m_i`` in 2-D, ``J`` the quarter turn): a ``D (D + 1) / 2``-dimensional
    space (less for markers on a line). Its orthogonal complement in ``R^{n D}`` holds the
    changes of the distances between the markers.

    Returns
    -------
    N : (n D, n D) float
        Symmetric, idempotent; zero for one marker.
    """
    m = np.asarray(m, float)
    n, D = m.shape
    cols = [np.tile(np.eye(D)[d], n) for d in range(D)]
    if D == 3:
        cols += [np.cross(np.eye(3)[e], m).ravel() for e in range(3)]
    else:
        cols.append(np.stack([-m[:, 1], m[:, 0]], axis=1).ravel())
    U, sv, _ = np.linalg.svd(np.stack(cols, axis=1), full_matrices=False)
    U = U[:, sv > 1e-9 * max(sv.max(), 1e-300)]
    return np.eye(n * D) - U @ U.T


def _coefficient_cov(B, Jr, Hinv, Rp, n: int) -> np.ndarray:
    """``C = sum_t (b_t b_t^T) kron (R_t^T (I - P_t) R_t)``: covariance of the coefficients for unit noise.

    ``B (T, k)``, ``Jr (T, n D, Q)`` the rows of the ``n`` markers, ``Hinv (T, Q, Q)``, ``Rp (T, D, D)``.
    """
    T, k = B.shape
    D, nD = Rp.shape[-1], Jr.shape[1]
    # R^T (I - J H^-1 J^T) R = I - (R^T J) H^-1 (R^T J)^T, R block-diagonal with n blocks R_t
    JR = np.einsum("tji,tnjq->tniq", Rp, Jr.reshape(T, n, D, -1)).reshape(T, nD, -1)
    Mt = np.eye(nD)[None] - (JR @ Hinv) @ np.swapaxes(JR, 1, 2)
    G = (B[:, :, None] * B[:, None, :]).reshape(T, k * k)
    return (G.T @ Mt.reshape(T, nD * nD)).reshape(k, k, nD, nD).transpose(0, 2, 1, 3).reshape(k * nD, k * nD)


def _coefficients(d: _Design, r) -> np.ndarray:
    """Regression coefficients ``z (..., k, n, D)`` of residuals ``r (..., T, K)``, parent frame."""
    D = d.R_parent.shape[-1]
    rr = r[..., d.ok, :][..., d.rows]
    rr = rr.reshape(rr.shape[:-1] + (len(d.rows) // D, D))
    r_par = np.einsum("tji,...tmj->...tmi", d.R_parent, rr)
    return np.einsum("tj,...tma->...jma", d.basis, r_par)


def _nonrigid_coefficients(d: _Design, r) -> np.ndarray:
    """Regression coefficients ``(..., k, n_child D)`` of the child markers' deformations, child frame."""
    D = d.R_child.shape[-1]
    rr = r[..., d.ok, :][..., d.rows]
    rr = rr.reshape(rr.shape[:-1] + (len(d.rows) // D, D))[..., d.child, :]
    r_child = np.einsum("tji,...tmj->...tmi", d.R_child, rr)
    r_child = r_child.reshape(r_child.shape[:-2] + (-1,)) @ d.nonrigid
    return np.einsum("tj,...tk->...jk", d.basis, r_child)


def second_order_residual(model: Model, theta, pose, y, sigma: float, Jq, Hinv, step: float = 1e-4,
                          ws: Workspace | None = None) -> np.ndarray:
    """Mean of the re-projected residual at second order in the noise.

    With the fitted pose ``q^_t = q_t + delta_t``, ``delta_t ~ N(0, V_t)``,
    ``V_t = sigma^2 (J_t^T J_t)^{-1}``, the residual ``y_t - f(q^_t)`` re-projected per frame has

    .. math:: E[\tilde r_t] = -\tfrac12 (I - P_t) \\sum_{ij} (V_t)_{ij}\\,
              \\partial^2 f_t / \\partial q_i \\partial q_j

    (the curvature of the marker positions in the pose; second derivatives by central
    differences of the pose Jacobian). It follows the pose, so a regression on the joint
    angles picks it up as structure.

    Parameters
    ----------
    pose : (T, Q) float
    y : (T, M, D) float
    Jq : (T, K, Q) float
    Hinv : (T, Q, Q) float
    ws : skelid.model.kinematics.Workspace, optional
        The model's workspace; one is made here, once for all ``2 Q`` perturbed Jacobians,
        without it.

    Returns
    -------
    b : (T, K) float
    """
    from skelid.estimators.fit.likelihood import frame_terms

    if ws is None:
        ws = Workspace(model)
    V = sigma**2 * Hinv
    acc = np.zeros(Jq.shape[:2])
    for j in range(pose.shape[-1]):
        e = np.zeros(pose.shape[-1])
        e[j] = step
        dJ = (frame_terms(model, theta, pose + e, y, ws)[1]
              - frame_terms(model, theta, pose - e, y, ws)[1]) / (2 * step)
        acc += (dJ @ V[:, :, j, None])[..., 0]
    return -0.5 * _project_out(Jq, Hinv, acc[..., None])[..., 0]


def _rolling_designs(model: Model, kin, theta, pose_u, present) -> dict[int, np.ndarray]:
    """The rolling paths of every one-rotation joint: ``G (T, M*D, D)`` per child segment (see :func:`rolling_test`)."""
    D = model.dim
    seg_of = np.asarray(model.marker_segment)
    par = np.asarray(model.parent_index)
    rows = np.repeat(present, D, axis=1)  # (T, M*D)
    out = {}
    for s in range(len(model.segments)):
        ks = [k for k, d in enumerate(model.dofs) if d.segment == s and d.kind == "R"]
        p = int(par[s])
        if p < 0 or len(ks) != 1:
            continue
        below = np.zeros(len(model.segments), bool)
        below[s] = True
        for c in range(s + 1, len(model.segments)):  # segments are ordered parents first
            below[c] = below[par[c]]
        mk = below[seg_of]
        if not mk.any():
            continue
        # the joint's rotation from its zero angle, parent frame: R(q) = R_rel(q) R_rel(0)^T
        zero = pose_u[:1].copy()
        zero[:, ks[0]] = 0.0
        k0 = forward_kinematics(model, theta, zero)
        R0 = k0.R_world_seg[0, p].T @ k0.R_world_seg[0, s]
        Rp = kin.R_world_seg[:, p]
        Rq = np.swapaxes(Rp, -1, -2) @ kin.R_world_seg[:, s] @ R0.T
        g = Rp @ (np.eye(D) - np.swapaxes(Rq, -1, -2))  # (T, D, D): column a is the path for a = e_a, world
        G = np.zeros((len(pose_u), len(seg_of), D, D))
        G[:, mk] = g[:, None]
        out[s] = np.where(rows[..., None], G.reshape(len(pose_u), -1, D), 0.0)
    return out


def rolling_test(G, r, Jq, Hinv, At, S_pinv, sigma: float, noise_dof: int, b=None):
    """Score test of one joint's rolling path: ``(statistic, dof, log tail probability, nonlinearity)``.

    ``G (T, K, D)``: the path's columns (:func:`_rolling_designs`); ``r (T, K)`` the residuals
    re-projected per frame; ``At (T, K, P)`` the parameter Jacobian re-projected per frame and
    ``S_pinv`` the pseudo-inverse of ``sum_t At^T At``; ``b (T, K)`` the residuals' second-order
    mean (:func:`second_order_residual`), whose share of the statistic is the nonlinearity.
    See :func:`model_misfit` for the model.
    """
    Z = _project_out(Jq, Hinv, G).reshape(-1, G.shape[-1])
    At = At.reshape(len(Z), -1)
    ZA = Z.T @ At
    info = Z.T @ Z - ZA @ S_pinv @ ZA.T
    w, V = np.linalg.eigh(info)
    keep = w > 1e-9 * max(w.max(), 1e-300)
    dof = int(keep.sum())
    if dof == 0:
        return 0.0, 0, 0.0, 0.0

    def quad(x):
        x = np.reshape(x, -1)
        u = Z.T @ x - ZA @ (S_pinv @ (At.T @ x))
        return float(np.sum((V[:, keep].T @ u) ** 2 / w[keep])) / sigma**2

    from scipy.stats import f as f_dist

    stat = quad(r)
    lam = quad(b) if b is not None else 0.0
    return stat, dof, float(f_dist.logsf(stat / dof, dof, max(noise_dof, 1))), lam


def pattern_shift(G, r, Jq, Hinv, At, S_pinv, Atr) -> tuple[np.ndarray, np.ndarray]:
    """Shift ``(P,)`` of the parameters that the residuals' part along the pattern ``G`` causes (linear response).

    ``G (T, K, c)``: the pattern's columns at the rows ``K`` of the frames ``T`` it touches (zero rows
    may be left out); ``r (T, K)``, ``Jq (T, K, Q)``, ``At (T, K, P)`` the re-projected residuals, pose
    Jacobian and re-projected parameter Jacobian at the same rows, ``Hinv (T, Q, Q)`` per frame;
    ``S_pinv`` the pseudo-inverse of ``S = sum_t A_t^T A_t`` and ``Atr = sum_t A_t^T r~_t`` over all rows.
    The residuals with the parameters free, ``r_perp = r~ - A S^+ A^T r~`` (those of the per-frame
    linearised fit: a motion model's pull on the parameters is not a misfit), are fitted on
    ``Z_t = (I - P_t) G_t``: their systematic part is ``s = Z c``, ``c = (Z^T Z)^+ Z^T r_perp``, and a
    perturbation ``s`` of the markers moves the estimate by ``delta = S^+ sum_t A_t^T s_t = S^+ Z_A^T c``
    (``Z_A = sum_t Z_t^T A_t``; the per-frame form of :func:`skelid.estimators.fit.joint.influence_rows`).
    ``(I - P_t)`` is never formed: ``Z^T x = G^T x`` for a re-projected ``x`` and
    ``Z^T Z = G^T G - (G^T J_q) H^{-1} (J_q^T G)``.

    Returns
    -------
    delta : (P,) float
    noise : (P,) float
        The variance of ``delta`` that white noise of unit sd gives under a correct model, the diagonal of
        ``M^T (Z^T Z - Z_A S^+ Z_A^T) M`` with ``M = (Z^T Z)^+ Z_A S^+``.
    """
    GJ = np.swapaxes(G, -1, -2) @ Jq  # (T, c, Q)
    ZZ = summed_gram(G) - summed_gram(np.swapaxes(GJ @ Hinv, -1, -2), np.swapaxes(GJ, -1, -2))
    ZA = summed_gram(G, At)
    w, V = np.linalg.eigh(0.5 * (ZZ + ZZ.T))
    keep = w > 1e-9 * max(w.max(), 1e-300)
    ZZ_pinv = (V[:, keep] / w[keep]) @ V[:, keep].T
    c = ZZ_pinv @ (summed_product(G, r) - ZA @ (S_pinv @ Atr))
    M = ZZ_pinv @ ZA @ S_pinv  # (c, P)
    noise = np.einsum("cp,cd,dp->p", M, ZZ - ZA @ S_pinv @ ZA.T, M)
    return S_pinv @ (ZA.T @ c), np.clip(noise, 0.0, None)


def _broad_pattern(d: _Design) -> np.ndarray:
    """The broad test's pattern ``G (T_ok, n D, k D)``: basis function ``j`` times the contrast's weight of each
    marker along the parent's axis ``a`` (so that ``G^T r~`` is the contrast ``L z``)."""
    D = d.R_parent.shape[-1]
    k, n = d.basis.shape[1], len(d.rows) // D
    wts = d.contrast[0, : n * D : D]  # (n,) each marker's weight in the contrast
    G = d.basis[:, None, None, :, None] * wts[None, :, None, None, None] * d.R_parent[:, None, :, None, :]
    return G.reshape(len(d.basis), n * D, k * D)


def _effect(shift, noise, sigma: float, sd) -> float:
    """``max_k sqrt(max(shift_k^2 - sigma^2 noise_k, 0)) / sd_k`` over the parameters with ``sd_k > 0``.

    The noise's share of the squared shift taken out: an estimate of ``|E shift_k| / sd_k``. 0 without a
    parameter.
    """
    ok = sd > 0
    size = np.sqrt(np.clip(shift[ok] ** 2 - sigma**2 * noise[ok], 0.0, None))
    return float(np.max(size / sd[ok])) if ok.any() else 0.0


def model_misfit(model: Model, y, theta, pose, used, sigma: float | None = None,
                 alpha: float = MISFIT_ALPHA) -> dict[str, dict]:
    """Residual structure that follows a joint angle and moves a segment's markers together.

    **Test.** For each joint ``j`` with rotation coordinates ``u`` (not the root's), take
    the residuals of the markers of the joint's child and parent segments, re-projected per
    frame (``r~_t = (I - P_t) r_t``, see :func:`_per_frame_projection`) and written in the
    parent segment's frame, where a joint that cannot follow the data leaves a pattern that
    depends on ``u`` alone. Regress them on ``B``: the powers ``u_i, u_i^2, ..., u_i^d``
    (``d = MISFIT_DEGREE``), centred and orthonormalised over the frames. The coefficients
    ``z = B^T r~`` have, under a correct model with white noise of sd ``sigma``,

    .. math:: \\operatorname{Cov}(z) = \\sigma^2 C, \\quad C = \\sum_t (b_t b_t^\\top) \\otimes
              (R_t^\\top (I - P_t) R_t)

    (``R_t`` the parent's rotation for each marker). A joint that cannot follow the data moves
    the child against the parent (the fit shares the error between them), so the test takes the
    contrast ``L z``: the child's markers' mean pattern less the parent's. Then
    ``z^T L^T (L C L^T)^+ L z / sigma^2 ~ chi^2`` on the rank of ``L C L^T`` (``k D`` for ``k``
    basis functions); with ``sigma`` estimated from successive differences
    (:func:`misfit_noise`) the statistic over its rank is referred to an F distribution.

    **A rolling centre.** That broad test spends ``k D`` (9 for a 3-D hinge) degrees of
    freedom on any angle-driven pattern. The commonest misfit of a one-rotation joint, a
    centre that slides with the angle, needs two. Write ``R(q) = R_rel(q) R_rel(0)^T`` for the
    joint's rotation from its zero angle (parent frame; ``R_rel`` the child's rotation in the
    parent's). A shift ``delta`` of the joint's centre moves the child's markers by the path
    ``(I - R(q)) delta``, which a fitted centre absorbs; a centre path ``t(q) = b q + c q^2``
    splits, to second order in ``q``, into that and the *rolling* path

    .. math:: t_a(q) = (I - R(q)^\\top)\\, a = (1 - \\cos q)\\, a + \\sin q\\, (e \\times a),
              \\quad a \\perp e

    (``b = e x (a - delta)``, ``c = (a + delta) / 2``), which no hinge reproduces. The test is
    the score test of ``t_a`` added to the child's subtree (``G_t``: the columns ``R_p,t (I -
    R(q_t)^T)``, zero for other markers and missing ones): with ``Z_t = (I - P_t) G_t`` and
    ``A_t = (I - P_t) J_theta,t`` (poses and parameters projected out; ``S = sum A^T A``),

    .. math:: U = \\sum_t Z_t^\\top \\tilde r_t - Z_A S^+ \\sum_t A_t^\\top \\tilde r_t, \\quad
              I = \\sum_t Z_t^\\top Z_t - Z_A S^+ Z_A^\\top, \\quad Z_A = \\sum_t Z_t^\\top A_t,

    ``U^T I^+ U / sigma^2 ~ chi^2`` on the rank of ``I`` (2 in 3-D, the component along the axis
    being zero); ``U`` does not depend on where the poses and parameters were fitted (to first
    order), so a fit with a motion model is tested as well. It equals the drop in residual sum
    of squares when the path joins the linearised fit. On the mismatch benchmark's polynomial
    knee it carries 99.7 % of the hinge's noise-free residual sum of squares (88 % of OpenSim's
    gait2354 knee's) on 2 degrees of freedom instead of 9. Its second-order shift
    (``U_b^T I^+ U_b / sigma^2``, ``b`` as below) must stay under ``MISFIT_NONLINEAR`` times its
    degrees of freedom, else only the broad test counts.

    **Level.** The joint's p-value is Bonferroni's over its two tests:
    ``min(p_broad / (1 - s), p_rolling / s, 1)`` with ``s = MISFIT_PATH_SHARE`` (the broad
    test's alone for joints with several rotations), and the joint is significant when it is
    below ``alpha / n_joints``: the family-wise false-alarm rate stays at most ``alpha``.

    **Effect size.** A significant pattern need not matter: with many frames and little noise a
    residual structure of a few micrometres is significant, yet moves no estimate. A joint is
    flagged only where its pattern would also move some parameter by at least ``MISFIT_EFFECT`` of
    its sd. For a test's pattern columns ``G`` (the broad test's: each basis function times the
    contrast's marker weights along each parent axis, so that ``G^T r~ = L z``; the rolling test's
    path), ``Z_t = (I - P_t) G_t``: the systematic part of the residuals is their least-squares fit
    on the pattern, ``s = Z c`` with ``c = (Z^T Z)^+ Z^T r_perp``, where ``r_perp = r~ - A S^+ A^T r~``
    are the residuals with the parameters free (a motion model's pull on the parameters, which
    leaves structure even in noise-free data, is no misfit), and through the fit's linear response
    (a marker perturbation ``delta_t`` moves the estimate by ``S^+ sum_t A_t^T delta_t``, see
    :func:`skelid.estimators.fit.joint.influence_rows`) it moves the parameters by

    .. math:: \\delta = S^+ Z_A^\\top c, \\qquad
              \\operatorname{Var}_0(\\delta) = \\sigma^2\\, M^\\top (Z^\\top Z - Z_A S^+ Z_A^\\top) M,
              \\quad M = (Z^\\top Z)^+ Z_A S^+

    (:func:`pattern_shift`; ``Var_0`` under a correct model with white noise). The effect is
    ``max_k sqrt(max(delta_k^2 - Var_0(delta)_kk, 0)) / sd_k`` with ``sd_k = sigma sqrt(S^+_kk)``
    (the noise's share of ``delta_k^2`` taken out; the larger of the two tests' effects where the
    rolling test counts). ``sigma`` is the test's, held at least at ``1e-7`` of the model's size,
    so that structure at the data's rounding level moves nothing by a rounding-level sd.
    ``delta^T S delta <= ||s||^2``, so the effect of a pattern is at most ``||s|| / sigma``, and
    zero for a pattern the parameters cannot follow (``Z_A = 0``: a knee's markers sliding along
    its hinge axis, where its centre is fitted in the plane). ``S`` is the per-frame information:
    a fit with a motion model has at least as much, so its sd is smaller and a warning on this
    sd is conservative.

    **Where the linearisation fails.** That null holds to first order in the noise. The
    fitted poses also follow the noise (``delta_t ~ N(0, sigma^2 H_t^{-1})``), and at second
    order the re-projected residual has a mean ``b_t`` that follows the pose
    (:func:`second_order_residual`), which the regression on the joint angles picks up as
    structure; its size bounds the statistic's non-centrality by
    ``lambda = sum_t ||b_t||^2 / sigma^2`` over the joint's rows and frames. Where ``lambda``
    exceeds ``MISFIT_NONLINEAR`` times the test's degrees of freedom, the poses are too
    uncertain for a linearised test and the joint is reported as not tested (``reliable``
    false, never significant). This is the case of built-in case A fitted frame by frame
    (one coordinate per frame beyond the pose, near-singular wrist): at 15 mm of noise its
    fitted wrist angle is off by 0.9 rad rms, the statistic is 2-5 times its degrees of
    freedom on pure Gaussian data and the successive-difference noise is 0.8 sigma (third and
    higher orders dominate, so subtracting ``b_t`` does not help; ``lambda`` is 13-15 there,
    5-7 at 5 mm, 1-2 at 2-3 mm where the test holds its level). The knee models of the
    mismatch benchmark have ``lambda`` about 1 at 10 mm. ``lambda`` is computed for poses fitted
    frame by frame; the poses of a fit with a motion model follow the noise less, so for it
    ``lambda`` is an upper bound and the check conservative.

    **Misfit or soft tissue.** Soft-tissue artefact also follows the joint angles, but moves
    each marker its own way. The same test on each child marker's pattern about the child's
    mean, and the share of the child markers' angle-driven sum of squares that their mean
    carries (``n SS_c / sum_m SS_m``, each with its expected noise part subtracted: 1 when they
    move as one, about ``1/n`` for independent artefacts), tell them apart. Neither alone is
    enough: a joint whose centre slides with the angle, fitted as a hinge, leaves the child a
    translation and a rotation error that the fit shares with the joint angle, so its
    markers' own patterns are significant too and the share falls to 0.4-0.5 (OpenSim's
    gait2354 knee at 1 mm of noise). What soft tissue does and no joint model can is deform
    the segment's marker set: the child's residuals in its own frame, projected onto the
    displacements no rigid motion makes (:func:`nonrigid_projector`; the per-frame pose
    projection leaves that space alone, so its coefficients ``z_N`` have covariance
    ``sigma^2 I kron N`` exactly), are tested the same way (``log10_p_nonrigid``). A
    significant joint is flagged as misfit unless its markers' own patterns are significant,
    the share is at most ``MISFIT_COMMON`` and the markers deform. A child segment with one
    marker is never flagged (its artefact and a misfit look alike); rigid motion of a whole
    marker cluster that follows the angle is a joint misfit to this test.

    Parameters
    ----------
    y : (T, M, D) float
    theta : (P,) float
    pose : (T, Q) float
    used : (T,) bool
    sigma : float, optional
        White-noise sd; estimated from successive differences when not given.
    alpha : float
        Family-wise false-alarm rate over the joints tested.

    Returns
    -------
    dict
        joint name -> ``{"segment": child segment, "rms": rms of the common pattern (model
        units), "common_share", "statistic", "dof", "log10_p", "log10_p_own" (the markers' own
        patterns), "log10_p_nonrigid" (their deformation), "significant", "flagged",
        "nonlinearity" (``lambda``), "reliable", "log10_p_broad" (the broad test), "statistic_rolling",
        "dof_rolling", "log10_p_rolling", "nonlinearity_rolling", "rolling_tested" (the rolling test counts),
        "soft_tissue" (the markers' patterns say soft tissue), "effect" (the pattern's shift of the estimate in
        sds, see "Effect size"), "shift" (parameter name -> that shift, model units)}``; "log10_p" is the
        joint's (both tests); "flagged" needs "significant", an effect of at least ``MISFIT_EFFECT`` and an
        rms of at least ``MISFIT_MIN_RMS`` of the model's size.
    """
    used = np.asarray(used, bool)
    out: dict[str, dict] = {}
    if used.sum() < 20:
        return out
    pose_u = np.asarray(pose, float)[used]
    y_u = np.asarray(y, float)[used]
    D = model.dim
    present = np.isfinite(y_u).all(axis=-1)  # (T, M)
    r, Jq, Hinv, Jt = _projection_terms(model, theta, pose_u, y_u)
    noise_sd, noise_dof = misfit_noise(r, Jq, Hinv, np.repeat(present, D, axis=1))
    if sigma is None:
        sigma = noise_sd
    size = float(np.abs(model.nominal_geometry).max())
    floor = 1e-7 * size  # below: rounding, not noise
    if not np.isfinite(sigma):
        return out
    sigma = max(float(sigma), floor)
    kin = forward_kinematics(model, theta, pose_u)
    designs = _designs(model, kin, pose_u, present, Jq, Hinv)
    if not designs:
        return out
    b = second_order_residual(model, theta, pose_u, y_u, sigma, Jq, Hinv)
    level = np.log(alpha / len(designs))
    paths = _rolling_designs(model, kin, theta, pose_u, present)
    At = _project_out(Jq, Hinv, Jt)
    S_pinv = np.linalg.pinv(np.einsum("tka,tkc->ac", At, At), hermitian=True)
    Atr = summed_product(At, r)
    sd = sigma * np.sqrt(np.clip(np.diag(S_pinv), 0.0, None))  # the parameters' sd, this linearisation
    for d in designs:
        z = _coefficients(d, r)  # (k, n, D)
        k, n = z.shape[:2]
        stat, dof, log_p_broad = _chi2_test(d.contrast @ z.reshape(-1), d.contrast @ d.C @ d.contrast.T, sigma,
                                            noise_dof)
        _, _, log_p_own = _chi2_test(d.own @ z.reshape(-1), d.own @ d.C @ d.own.T, sigma, noise_dof)
        z_nr = _nonrigid_coefficients(d, r)
        _, _, log_p_nonrigid = _chi2_test(z_nr.reshape(-1), np.kron(np.eye(k), d.nonrigid), sigma, noise_dof)
        # common pattern of the child's markers against each marker's own, noise parts removed
        zc, Cd = z[:, d.child], d.C.reshape(k, n, D, k, n, D)
        ss_m = np.sum(zc**2) - sigma**2 * sum(np.trace(Cd[:, i, :, :, i, :].reshape(k * D, k * D))
                                              for i in d.child)
        avg = Cd[:, d.child][:, :, :, :, d.child].mean(axis=(1, 4))
        ss_c = np.sum(zc.mean(axis=1) ** 2) - sigma**2 * np.trace(avg.reshape(k * D, k * D))
        share = len(d.child) * max(ss_c, 0.0) / ss_m if ss_m > 0 else 0.0
        lam = float(np.sum(b[d.ok][:, d.rows] ** 2)) / sigma**2
        reliable = lam <= MISFIT_NONLINEAR * max(dof, 1)
        s_child = model.segment_index[d.segment]
        stat_p, dof_p, log_p_path, lam_p = (rolling_test(paths[s_child], r, Jq, Hinv, At, S_pinv, sigma, noise_dof, b)
                                            if s_child in paths else (0.0, 0, 0.0, 0.0))
        # the joint's p-value: Bonferroni over its two tests where the rolling test is sound
        with_path = dof_p > 0 and lam_p <= MISFIT_NONLINEAR * dof_p
        log_p = (min(log_p_broad - np.log1p(-MISFIT_PATH_SHARE), log_p_path - np.log(MISFIT_PATH_SHARE), 0.0)
                 if with_path else log_p_broad)
        significant = bool(reliable and log_p < level)
        shift, noise = pattern_shift(_broad_pattern(d), r[d.ok][:, d.rows], Jq[d.ok][:, d.rows], Hinv[d.ok],
                                     At[d.ok][:, d.rows], S_pinv, Atr)
        effect = _effect(shift, noise, sigma, sd)
        if with_path:  # the larger of the two tests' effects
            path_shift, path_noise = pattern_shift(paths[s_child], r, Jq, Hinv, At, S_pinv, Atr)
            if _effect(path_shift, path_noise, sigma, sd) > effect:
                shift, effect = path_shift, _effect(path_shift, path_noise, sigma, sd)
        # soft tissue: the markers' own patterns are significant and carry most of the structure, and the
        # markers deform (their distances change with the angle: no joint model can do that)
        tissue = bool(log_p_own < level and share <= MISFIT_COMMON and log_p_nonrigid < level)
        out[d.joint] = {"segment": d.segment, "rms": float(np.sqrt(max(ss_c, 0.0) / len(d.basis))),
                        "common_share": round(float(share), 3), "statistic": round(stat, 2), "dof": dof,
                        "log10_p": round(log_p / np.log(10), 2), "log10_p_broad": round(log_p_broad / np.log(10), 2),
                        "statistic_rolling": round(stat_p, 2), "dof_rolling": dof_p,
                        "log10_p_rolling": round(log_p_path / np.log(10), 2),
                        "nonlinearity_rolling": round(lam_p, 3), "rolling_tested": bool(with_path),
                        "log10_p_own": round(log_p_own / np.log(10), 2),
                        "log10_p_nonrigid": round(log_p_nonrigid / np.log(10), 2), "soft_tissue": tissue,
                        "significant": significant, "effect": round(effect, 3),
                        "shift": dict(zip(model.parameter_names, shift.tolist(), strict=True)),
                        "flagged": bool(significant and effect >= MISFIT_EFFECT and len(d.child) >= 2 and not tissue
                                        and np.sqrt(max(ss_c, 0.0) / len(d.basis)) >= MISFIT_MIN_RMS * size),
                        "nonlinearity": round(lam, 3), "reliable": bool(reliable)}
    return out


def relaxed_estimate(variant: Model, fit, n_params: int) -> tuple[np.ndarray, np.ndarray]:
    """A relaxed model's estimate of the first ``n_params`` parameters and their sd, normal priors combined.

    ``sigma^2 = RSS / (n_obs - pose dof - P_v)``; the data's precision ``A = S / sigma^2``
    (``S`` the fit's efficient information) is combined with the normal priors' precisions
    ``Lambda`` (zero for uniform ones): ``cov = (A + Lambda)^{-1}``,
    ``mean = cov (A theta^ + Lambda mu)``.

    Parameters
    ----------
    variant : Model
    fit : skelid.estimators.fit.joint.JointFit
        The variant's joint least-squares fit.
    n_params : int

    Returns
    -------
    theta : (n_params,) float
    sd : (n_params,) float
    """
    dof = max(fit.n_obs - fit.pose_dof - variant.n_params, 1.0)
    A = np.asarray(fit.info, float) * dof / max(fit.rss, 1e-300)
    prec = np.array([1.0 / p.prior.sd**2 if p.prior.kind == "normal" else 0.0 for p in variant.parameters])
    mu = np.array([p.prior.mean if p.prior.kind == "normal" else 0.0 for p in variant.parameters])
    cov = np.linalg.pinv(A + np.diag(prec), hermitian=True)
    mean = cov @ (A @ fit.theta + prec * mu)
    return mean[:n_params], np.sqrt(np.clip(np.diag(cov)[:n_params], 0.0, None))


def _chi2_test(z, C, sigma: float, noise_dof: int) -> tuple[float, int, float]:
    """``z^T C^+ z / sigma^2`` (``z ~ N(0, sigma^2 C)``), its rank and the log tail probability (F)."""
    from scipy.stats import f as f_dist

    w, V = np.linalg.eigh(C)
    keep = w > 1e-9 * max(w.max(), 1e-300)
    dof = int(keep.sum())
    if dof == 0:
        return 0.0, 0, 0.0
    stat = float(np.sum((V[:, keep].T @ z) ** 2 / w[keep])) / sigma**2
    return stat, dof, float(f_dist.logsf(stat / dof, dof, max(noise_dof, 1)))


#: a parameter is informed by the nominal marker placement when one still pose gives at least this
#: share of the precision that the whole trial gives
PLACEMENT_SHARE = 0.5
#: default standard deviation (mm) of a skin marker's placement on its segment, per coordinate,
#: folded in when a placement-informed parameter comes from a trial whose joints barely moved
DEFAULT_PLACEMENT_SD_MM = 5.0


def placement_information(model: Model, y, theta, pose, used, R=None, weights=None) -> dict:
    """How much of each parameter's information a still pose gives, and its sensitivity to placement.

    **Where the information comes from.** ``S = sum_t K_t^T A_t`` is the information about
    ``theta`` (unit noise). A trial standing still at one pose ``q*`` (the used frame nearest
    the median pose) for the same number of frames would give ``S_* = T K_*^T (I - P_*) K_*``.
    The share ``S^{-1}_kk / S_*^{-1}_kk`` (0 when ``S_*`` does not identify parameter ``k``) is
    near 1 for a parameter that follows from the markers' nominal positions in their
    segments (a segment ``length`` between markers), and near 0 for a functional one (a
    joint centre found from the joint's motion).

    **Placement.** The markers' positions on their segments are constants of the model. A
    change ``delta`` (segment frame) of marker ``m``'s position moves it by ``R_t delta`` in
    every frame and, to first order, the estimate by ``g_m delta`` with
    ``g_m = S^{-1} sum_t A_{t,m}^T R_{t,s(m)}``. Independent placement errors of standard
    deviation ``s`` per coordinate add ``s^2 sum_m g_m g_m^T`` to the covariance.

    Returns
    -------
    dict
        ``share_still`` (P,) and ``cov_per_unit`` (P, P): the placement covariance for ``s = 1``.
    """
    from skelid.estimators.fit.joint import influence_rows, row_weights
    from skelid.estimators.fit.likelihood import frame_terms, projected_theta_jacobian

    used = np.asarray(used, bool)
    yu = np.where(used[:, None, None], y, np.nan)
    r, Jq, Jt = frame_terms(model, theta, pose, yu)
    sw = row_weights(weights, yu)
    if sw is not None:
        Jq, Jt = Jq * sw[..., None], Jt * sw[..., None]
    A, _ = influence_rows(Jq, Jt, R)
    S = summed_gram(Jt, A)
    S_inv = np.linalg.pinv(S)
    # a still trial at the frame nearest the median pose
    idx = np.flatnonzero(used)
    med = np.median(pose[idx], axis=0)
    t0 = idx[np.argmin(np.sum((pose[idx] - med) ** 2, axis=1))]
    Kp = projected_theta_jacobian(Jq[t0], Jt[t0])
    S_still = len(idx) * Kp.T @ Kp
    w, V = np.linalg.eigh(S_still)
    good = w > 1e-9 * max(abs(w).max(), 1e-300)
    # a parameter with any weight on a direction the still pose cannot see gets share 0
    blind = np.abs(V[:, ~good]).max(axis=1) > 1e-3 if (~good).any() else np.zeros(len(w), bool)
    var_still = (V[:, good] ** 2 / w[good]).sum(axis=1)
    share = np.where(blind, 0.0, np.diag(S_inv) / np.maximum(var_still, 1e-300))
    # sensitivity to each marker's placement, in its segment's frame
    kin = forward_kinematics(model, theta, pose)
    D, M = model.dim, len(model.markers)
    Rm = kin.R_world_seg[:, np.asarray(model.marker_segment)]  # (T, M, D, D)
    Am = A.reshape(len(pose), M, D, -1)  # (T, M, D, P)
    g = np.einsum("pq,tmdq,tmde->mpe", S_inv, Am, Rm)  # (M, P, D)
    cov_unit = np.einsum("mpe,mqe->pq", g, g)
    return {"share_still": np.clip(share, 0.0, 1.0), "cov_per_unit": cov_unit}
