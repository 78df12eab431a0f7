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


#: tail probability below which an angle-driven residual pattern is not noise
MISFIT_P = 1e-6
#: share of a segment's angle-driven residual that its markers have in common, above which it is the
#: joint model, not soft tissue (soft-tissue artefact moves each marker its own way)
MISFIT_COMMON = 0.5


def model_misfit(model: Model, y, theta, pose, used, sigma: float) -> dict[str, dict]:
    """Residual structure that follows a joint angle and moves a segment's markers together.

    For each segment ``s`` with at least two markers and a joint with rotation
    coordinates ``u``, the residuals of its markers are expressed in the segment's
    frame and regressed on ``u, u^2, u^3`` (centred and scaled, with a constant).
    Soft-tissue artefact also follows the joint angles, but moves each marker its
    own way; a joint model that cannot follow the joint (a knee whose centre
    moves with flexion, fitted as a fixed hinge) moves all the segment's markers
    together. So the test is on the *mean* residual of the segment's ``n``
    markers: its angle-explained sum of squares ``SS_c`` against white noise
    (``SS_c n / sigma^2 ~ chi^2_{kD}``, tail below ``MISFIT_P``), and its share of the
    markers' own explained sums, ``n SS_c / sum_m SS_m`` (1 when they move as one,
    about ``1/n`` for independent artefacts), above ``MISFIT_COMMON``.

    Returns
    -------
    dict
        joint name -> ``{"rms": rms of the common pattern (model units), "common_share": ...,
        "log10_p": ..., "segment": ..., "flagged": bool}``.
    """
    from scipy.stats import chi2

    used = np.asarray(used, bool)
    out: dict[str, dict] = {}
    if used.sum() < 20 or not np.isfinite(sigma) or sigma <= 0:
        return out
    kin = forward_kinematics(model, theta, pose[used])
    r = np.asarray(y, float)[used] - kin.markers  # (T, M, D)
    for s, seg in enumerate(model.segments):
        if seg.parent is None:
            continue
        ks = [k for k, d in enumerate(model.dofs) if d.segment == s and d.kind == "R"]
        ms = np.flatnonzero(np.asarray(model.marker_segment) == s)
        if not ks or len(ms) < 2:
            continue
        r_seg = np.einsum("tji,tmj->tmi", kin.R_world_seg[:, s], r[:, ms])  # in the segment's frame
        ok = np.isfinite(r_seg).all(axis=(1, 2))
        if ok.sum() < 20:
            continue
        u = pose[used][ok][:, ks]
        u = (u - u.mean(axis=0)) / np.maximum(u.std(axis=0), 1e-12)
        X = np.concatenate([np.ones((len(u), 1)), u, u**2, u**3], axis=1)
        k = X.shape[1] - 1
        beta, *_ = np.linalg.lstsq(X, r_seg[ok].reshape(len(u), -1), rcond=None)
        fitted = X[:, 1:] @ beta[1:]  # (T, n*D) angle-driven part (constant left out)
        fitted = fitted - fitted.mean(axis=0)
        per_marker = float(np.sum(fitted**2))
        common = fitted.reshape(len(u), len(ms), -1).mean(axis=1)  # (T, D)
        ss_c = float(np.sum(common**2))
        share = len(ms) * ss_c / per_marker if per_marker > 0 else 0.0
        dfree = k * model.dim
        log10_p = float(chi2.logsf(ss_c * len(ms) / sigma**2, dfree) / np.log(10))
        rms = float(np.sqrt(np.mean(np.sum(common**2, axis=1))))
        out[seg.joint.name] = {"segment": seg.name, "rms": rms, "common_share": round(share, 3),
                               "log10_p": round(log10_p, 1),
                               "flagged": bool(log10_p < np.log10(MISFIT_P) and share > MISFIT_COMMON)}
    return out


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
