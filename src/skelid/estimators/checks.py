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

import numpy as np
from scipy.spatial.transform import Rotation

from skelid.model.description import Model
from skelid.model.kinematics import forward_kinematics

#: the range of a multi-axis joint is twice this quantile of its rotation angle from the mean
RANGE_QUANTILE = 0.95


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


def _per_frame_projection(model: Model, theta, pose, y):
    """Residuals re-projected per frame, and the per-frame pose hat matrices' pieces.

    One Gauss-Newton step of each frame's pose from ``pose`` (no motion model) leaves the
    residual ``r~_t = (I - P_t) r_t`` with ``P_t = J_t (J_t^T J_t)^+ J_t^T``; under a correct
    model with white noise, ``r~_t ~ N(0, sigma^2 (I - P_t))`` independently over frames
    (to first order), whatever smoothing the fit used.

    Returns
    -------
    r : (T, M*D) float, zero where missing
    Jq : (T, M*D, Q) float
    Hinv : (T, Q, Q) float
    """
    from skelid.estimators.likelihood import frame_terms

    r, Jq, _ = frame_terms(model, theta, pose, y)
    H = np.einsum("tkq,tkp->tqp", Jq, Jq)
    Hinv = np.linalg.pinv(H, hermitian=True)
    r = r - np.einsum("tkq,tqp,tp->tk", Jq, Hinv, np.einsum("tkq,tk->tq", Jq, r))
    return r, Jq, Hinv


def misfit_noise(r, Jq, Hinv, present) -> tuple[float, int]:
    """White-noise sd from successive differences of the re-projected residuals.

    ``E ||r~_{t+1} - r~_t||^2 = sigma^2 sum_k (2 - P_{t+1,kk} - P_{t,kk})`` over the coordinates
    present in both frames; a residual pattern that follows the (slowly changing) joint angles
    barely enters the differences, so a misfit does not inflate it.

    Returns
    -------
    sigma : float
    dof : int
        Coordinates in the differences less their leverage (for an F reference).
    """
    lev = np.einsum("tkq,tqp,tkp->tk", Jq, Hinv, Jq)  # (T, K) diagonal of P_t
    both = present[1:] & present[:-1]
    d2 = float(np.sum(np.where(both, (r[1:] - r[:-1]) ** 2, 0.0)))
    expect = float(np.sum(np.where(both, 2.0 - lev[1:] - lev[:-1], 0.0)))
    return (float(np.sqrt(d2 / expect)) if expect > 0 else float("nan")), int(expect / 2)


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
    (:func:`misfit_noise`) the statistic over its rank is referred to an F distribution. A joint
    is significant when ``p < alpha / n_joints``.

    **Misfit or soft tissue.** Soft-tissue artefact also follows the joint angles, but moves
    each marker its own way. The same test on each child marker's pattern about the child's
    mean, and the share of the child markers' angle-driven sum of squares that their mean
    carries (``n SS_c / sum_m SS_m``, each with its expected noise part subtracted: 1 when they
    move as one, about ``1/n`` for independent artefacts), tell them apart: a significant joint
    is flagged as misfit unless its markers' own patterns are significant too and the share is
    at most ``MISFIT_COMMON``. A child segment with one marker is never flagged (its artefact
    and a misfit look alike).

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
        patterns), "significant", "flagged"}``.
    """
    used = np.asarray(used, bool)
    out: dict[str, dict] = {}
    if used.sum() < 20:
        return out
    pose_u = np.asarray(pose, float)[used]
    y_u = np.asarray(y, float)[used]
    D = model.dim
    present = np.isfinite(y_u).all(axis=-1)  # (T, M)
    r, Jq, Hinv = _per_frame_projection(model, theta, pose_u, y_u)
    pres_k = np.repeat(present, D, axis=1)
    noise_sd, noise_dof = misfit_noise(r, Jq, Hinv, pres_k)
    if sigma is None:
        sigma = noise_sd
    floor = 1e-7 * float(np.abs(model.nominal_geometry).max())  # below: rounding, not noise
    if not np.isfinite(sigma):
        return out
    sigma = max(float(sigma), floor)
    kin = forward_kinematics(model, theta, pose_u)
    seg_of = np.asarray(model.marker_segment)
    tests = []
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
        B = Qx[:, np.abs(np.diag(Rx)) > 1e-8 * max(np.abs(np.diag(Rx)).max(), 1e-300)]  # (T, k)
        rows = (ms[:, None] * D + np.arange(D)).ravel()
        Rp = kin.R_world_seg[ok, p]  # (T, D, D)
        r_par = np.einsum("tji,tmj->tmi", Rp, r[ok][:, rows].reshape(T, len(ms), D))  # parent frame
        z = np.einsum("tj,tma->jma", B, r_par)  # (k, n, D)
        # per-frame covariance of r~ on these rows, in the parent's frame (unit noise)
        Jr = Jq[ok][:, rows]
        Pt = (Jr @ Hinv[ok]) @ np.swapaxes(Jr, 1, 2)
        Mt = np.eye(len(rows))[None] - Pt
        Rb = np.zeros((T, len(rows), len(rows)))
        for i in range(len(ms)):
            Rb[:, i * D:(i + 1) * D, i * D:(i + 1) * D] = Rp
        Mt = np.swapaxes(Rb, 1, 2) @ Mt @ Rb
        k, nD = B.shape[1], len(rows)
        G = (B[:, :, None] * B[:, None, :]).reshape(T, k * k)
        C = (G.T @ Mt.reshape(T, nD * nD)).reshape(k, k, nD, nD).transpose(0, 2, 1, 3).reshape(k * nD, k * nD)
        # the contrast: the child's markers' mean pattern less the parent's (a joint that cannot follow
        # the data moves the child against the parent; the fit shares the error between the two)
        wts = np.where(seg_of[ms] == s, 1.0 / len(child), 0.0)
        if len(child) < len(ms):
            wts = wts - np.where(seg_of[ms] == s, 0.0, 1.0 / (len(ms) - len(child)))
        L = np.kron(np.eye(k), np.kron(wts[None, :], np.eye(D)))  # (k D, k n D)
        stat, dof, log_p = _chi2_test(L @ z.reshape(-1), L @ C @ L.T, sigma, noise_dof)
        # each child marker's own pattern about the child's mean: what soft tissue leaves
        own = np.zeros((len(ms), len(ms)))
        own[child[:, None], child[None, :]] = np.eye(len(child)) - 1.0 / len(child)
        Lo = np.kron(np.eye(k), np.kron(own[child], np.eye(D)))
        _, _, log_p_own = _chi2_test(Lo @ z.reshape(-1), Lo @ C @ Lo.T, sigma, noise_dof)
        # common pattern of the child's markers against each marker's own, noise parts removed
        zc, Cd = z[:, child], C.reshape(k, len(ms), D, k, len(ms), D)
        ss_m = np.sum(zc**2) - sigma**2 * sum(np.trace(Cd[:, i, :, :, i, :].reshape(k * D, k * D))
                                              for i in child)
        avg = Cd[:, child][:, :, :, :, child].mean(axis=(1, 4))
        ss_c = np.sum(zc.mean(axis=1) ** 2) - sigma**2 * np.trace(avg.reshape(k * D, k * D))
        share = len(child) * max(ss_c, 0.0) / ss_m if ss_m > 0 else 0.0
        rms = float(np.sqrt(max(ss_c, 0.0) / T))
        tests.append((seg.joint.name, seg.name, rms, share, stat, dof, log_p, log_p_own, len(child)))
    for name, seg_name, rms, share, stat, dof, log_p, log_p_own, n_child in tests:
        level = np.log(alpha / len(tests))
        significant = bool(log_p < level)
        # soft tissue: the markers' own patterns are significant and carry most of the structure
        tissue = bool(log_p_own < level and share <= MISFIT_COMMON)
        out[name] = {"segment": seg_name, "rms": rms, "common_share": round(float(share), 3),
                     "statistic": round(stat, 2), "dof": dof, "log10_p": round(log_p / np.log(10), 2),
                     "log10_p_own": round(log_p_own / np.log(10), 2), "significant": significant,
                     "flagged": bool(significant and n_child >= 2 and not tissue)}
    return out


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
    from skelid.estimators.joint import influence_rows, row_weights
    from skelid.estimators.likelihood import frame_terms, projected_theta_jacobian

    used = np.asarray(used, bool)
    yu = np.where(used[:, None, None], y, np.nan)
    r, Jq, Jt = frame_terms(model, theta, pose, yu)
    sw = row_weights(weights, yu)
    if sw is not None:
        Jq, Jt = Jq * sw[..., None], Jt * sw[..., None]
    A, _ = influence_rows(Jq, Jt, R)
    S = np.einsum("tkp,tkq->pq", Jt, A)
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
