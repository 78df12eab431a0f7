"""Outlier screen with each frame's residual degrees of freedom.

A frame's markers give ``m`` coordinates and cost ``Q`` pose coordinates; the
per-frame pose fit leaves a residual

.. math:: r_t = (I - H_t)\\,\\varepsilon_t, \\qquad H_t = J_t (J_t^\\top J_t)^{+} J_t^\\top ,

whose covariance is ``sigma^2 (I - H_t)`` (to first order; ``J_t`` is the pose
Jacobian, the parameters' own leverage ``P / T`` is negligible). A frame with
few surplus coordinates (``m - Q`` small) has *small* residuals, and how small
differs between markers: a raw residual distance compared with one robust
scale over the trial flags genuine Gaussian data in the frames with many
surplus coordinates and misses glitches in the frames with few.

Each marker's residual ``r_{t,m}`` (``D`` coordinates) is therefore
standardised by its own block ``V_{t,m} = (I - H_t)_{mm}``: on the directions
``u_k`` where ``V`` has eigenvalue ``v_k > V_MIN`` (a direction with less
residual variance cannot reveal a glitch; the pose fit absorbs it)

.. math:: z_{t,m} = \\sum_k (u_k^\\top r_{t,m})^2 / v_k \\;\\sim\\; \\sigma^2 \\chi^2_{d_{t,m}},

with ``d_{t,m}`` the number of such directions. ``sigma^2`` is estimated
robustly as the value that puts half of the ``z / sigma^2`` below their
chi-square medians (the median-unbiased scale of a mixture of chi-squares),
and a position is an outlier when ``z / sigma^2`` exceeds the chi-square
quantile with the tail probability of ``threshold`` standard deviations of one
coordinate (8 sd: about ``10^-15``), so that pure Gaussian data almost never
lose a position.

**A glitch is isolated in time.** A residual that is large because the model
cannot follow the joint (model misfit) or because the skin slides (soft-tissue
artefact) changes slowly, frame to frame; a glitch or a swapped label does not.
A position is therefore flagged only if it is also an outlier after each
marker's residual has had its running median over ``WINDOW`` frames removed
(same standardisation, its own robust scale): noise-free data from a model the
fit cannot represent keep their markers.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.optimize import brentq
from scipy.special import chdtr
from scipy.stats import chi2, norm

from skelid.estimators.fit.likelihood import frame_terms
from skelid.estimators.fit.pose import fit_pose
from skelid.model.description import Model

#: residual variance fraction (eigenvalue of ``I - H`` on a marker's block) below which a direction
#: carries no usable check of that marker
V_MIN = 0.05
#: frames in the running median that a glitch must stand out from
WINDOW = 9


def standardised_residuals(model: Model, theta, pose, y, detrend: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Leverage-corrected squared residuals of every marker position.

    Parameters
    ----------
    theta : (P,) float
    pose : (T, Q) float
        Per-frame poses (fitted to ``y`` with ``theta`` held).
    y : (T, M, D) float
        Markers, NaN where missing.
    detrend : bool
        Remove each marker coordinate's running median over ``WINDOW`` frames from the
        residuals first (what is left of a slow drift is small; a glitch stays).

    Returns
    -------
    z : (T, M) float
        ``sum_k (u_k^T r)^2 / v_k`` over the directions with ``v_k > V_MIN`` (NaN where
        the marker is missing).
    dof : (T, M) int
        Number of those directions (0: the position cannot be checked).
    """
    T, M, D = y.shape
    r, Jq, _ = frame_terms(model, theta, pose, y)
    C = np.linalg.pinv(np.swapaxes(Jq, 1, 2) @ Jq, hermitian=True)  # (T, Q, Q)
    # only each marker's (D, D) diagonal block of I - H is needed, H = Jq C Jq^T: V = I - J_m C J_m^T
    Jm = Jq.reshape(T, M, D, -1)
    V = np.eye(D) - Jm @ C[:, None] @ np.swapaxes(Jm, -1, -2)  # (T, M, D, D)
    w, U = np.linalg.eigh(V)
    rm = r.reshape(T, M, D)
    if detrend:
        rm = rm - running_median(np.where(np.isfinite(y), rm, np.nan), WINDOW)
    proj = np.einsum("tmdk,tmd->tmk", U, rm)
    keep = w > V_MIN
    z = np.sum(np.where(keep, proj**2 / np.where(keep, w, 1.0), 0.0), axis=-1)
    present = np.isfinite(y).all(axis=-1)
    dof = np.where(present, keep.sum(axis=-1), 0)
    return np.where(present, z, np.nan), dof


def running_median(x, window: int) -> np.ndarray:
    """Centred running median over the first axis, ignoring NaN (edges use the frames there are)."""
    h = window // 2
    pad = np.concatenate([np.full((h,) + x.shape[1:], np.nan), x, np.full((h,) + x.shape[1:], np.nan)])
    win = np.lib.stride_tricks.sliding_window_view(pad, window, axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-missing window
        med = np.nanmedian(win, axis=-1)
    return np.where(np.isfinite(med), med, 0.0)


def robust_variance(z, dof) -> float:
    """``sigma^2`` such that half of the checkable ``z / sigma^2`` lie below their chi-square medians."""
    ok = (dof > 0) & np.isfinite(z)
    if not ok.any():
        return float("nan")
    zz, dd = z[ok], dof[ok]
    med = chi2.median(dd)
    ratio = zz / med  # each entry's own scale estimate; the target splits them in half
    lo, hi = np.log(max(np.min(ratio[ratio > 0], initial=1e-300), 1e-300)), np.log(max(ratio.max(), 1e-300))

    def excess(m):  # fraction below the medians at sigma^2 = exp(m), less one half: falls with m
        return float(np.mean(chdtr(dd, zz / np.exp(m)))) - 0.5  # chi2.cdf without its per-call checks

    if lo < hi and excess(lo) > 0.0 and excess(hi) <= 0.0:  # a root inside: Brent's method, a dozen evaluations
        return float(np.exp(brentq(excess, lo, hi, xtol=1e-14, rtol=4.0 * np.finfo(float).eps)))
    for _ in range(60):  # bisection in log sigma^2 on the fraction below the median
        mid = 0.5 * (lo + hi)
        frac = np.mean(chdtr(dd, zz / np.exp(mid)))  # chi2.cdf without its per-call argument checks
        if frac > 0.5:
            lo = mid
        else:
            hi = mid
    return float(np.exp(0.5 * (lo + hi)))


def outlying_markers(model: Model, y, theta, pose, used, threshold: float, n_rounds: int = 4, ws=None) -> np.ndarray:
    """(T, M) bool: marker positions whose standardised residual is an outlier.

    Parameters
    ----------
    y : (T, M, D) float
        Markers, NaN where missing.
    theta : (P,) float
        The first fit's parameters.
    pose : (T, Q) float
        The first fit's poses (refitted per frame here, so that a glitch does not
        spread to its neighbours through a motion model).
    used : (T,) bool
        Frames in the first fit.
    ws : skelid.model.kinematics.Workspace, optional
        The fit's workspace (its pose fits keep the fit's path).
    threshold : float
        In standard deviations of one Gaussian coordinate; converted to the tail
        probability ``2 Phi(-threshold)`` of each position's chi-square.

    Notes
    -----
    One glitched marker drags its frame's pose, so in each round only the worst
    position of a frame (smallest tail probability) is flagged, and that frame's
    pose refitted without it.
    """
    out = np.zeros(y.shape[:2], dtype=bool)
    used = np.asarray(used, bool)
    if not used.any():
        return out
    pose, _ = fit_pose(model, theta, y, pose, n_iter=20, ws=ws)
    y = np.where(used[:, None, None], y, np.nan)
    z, dof = standardised_residuals(model, theta, pose, y)
    s2 = robust_variance(z, dof)
    if not np.isfinite(s2):
        return out
    zd, dofd = standardised_residuals(model, theta, pose, y, detrend=True)
    s2d = robust_variance(zd, dofd)
    floor = (1e-3 * float(np.abs(model.nominal_geometry).max())) ** 2  # below this a deviation is irrelevant
    log_p_limit = np.log(2.0) + norm.logsf(threshold)

    def log_tail(zz, dd, var):
        with np.errstate(divide="ignore", invalid="ignore"):
            lp = chi2.logsf(zz / var, np.maximum(dd, 1))
        return np.where((dd > 0) & np.isfinite(zz) & (zz > floor), lp, 0.0)

    # an outlier must stand out from its frame's noise and from its own neighbours in time
    isolated = log_tail(zd, dofd, s2d) < log_p_limit if np.isfinite(s2d) else np.zeros_like(out)
    lp = np.where(isolated, log_tail(z, dof, s2), 0.0)
    for _ in range(n_rounds):
        worst = np.argmin(lp, axis=1)
        flag = used & (lp[np.arange(len(lp)), worst] < log_p_limit)
        if not flag.any():
            break
        out[flag, worst[flag]] = True
        yy = np.where(out[flag][..., None], np.nan, y[flag])
        pf, _ = fit_pose(model, theta, yy, pose[flag], n_iter=20, ws=ws)
        pose[flag] = pf
        zf, df = standardised_residuals(model, theta, pf, yy)
        lp[flag] = np.where(isolated[flag] & ~out[flag], log_tail(zf, df, s2), 0.0)
    return out

