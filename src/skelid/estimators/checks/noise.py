"""Per-marker noise levels: each marker (or group of markers) its own ``sigma``.

Model: marker ``m`` in frame ``t`` is seen with its own noise level,

.. math:: y_{tm} = x_m(q_t, \\theta) + \\varepsilon_{tm}, \\qquad
          \\varepsilon_{tm} \\sim N(0, \\sigma_m^2 I),

so the likelihood is a weighted least-squares problem with weights
``w_m = 1/sigma_m^2`` (up to one common factor ``s^2``, which ``RSS_w / dof``
estimates). A skin marker over a bony landmark that moves 3 times as much as
the others gets a ninth of their weight and cannot drag a joint centre.

**Degrees of freedom.** The fit spends ``Q`` pose coordinates per frame (or the
effective number under the motion model) and ``P`` parameters. They are
apportioned to the markers by the leverage of the weighted fit: with
``H = J (J^T J + R)^{-1} J^T`` (``J`` the weighted Jacobian of all unknowns,
``R`` the motion-model penalty), the residual of row ``i`` has expectation
``E r_i^2 = sigma_i^2 (1 - H_ii)`` when the weights are right. Through the
arrow structure of ``J`` (poses eliminated, see :mod:`skelid.estimators.fit.joint`)

.. math:: H_{ii} = j_i^\\top [A^{-1}]_{tt}\\, j_i + a_i^\\top S^{-1} a_i, \\qquad
          A = \\mathrm{blockdiag}(J_t^\\top J_t) + R,

with ``j_i`` the row's pose Jacobian, ``a_i`` its influence row
(:func:`~skelid.estimators.fit.joint.influence_rows`) and ``S`` the information
about ``theta``. So

.. math:: \\hat\\sigma_m^2 = \\frac{\\sum_{t,d} r_{tmd}^2}{n_m - \\sum_{t,d} H_{tmd,tmd}} ,

and the weights and the fit are iterated to a fixed point (each step is the
REML-like estimating equation for the variance components of a linear model).

**Partial pooling.** A marker's own level rests on few effective degrees of
freedom when its residuals are serially correlated (a standing trial: a slow
drift, lag-1 autocorrelation near 1) or when the fit follows it closely. Its
level is then a noisy estimate, and an estimate that happens to be small gives
the marker a large weight, the fit follows it more closely, and its level falls
further. Each level is therefore shrunk toward the trial's common level by an
empirical-Bayes prior (Smyth 2004): the groups' variances ``s_g^2`` with
effective degrees of freedom ``d_g`` are taken as draws of a scaled inverse
chi-square law ``(d_0, s_0^2)`` fitted by the moments of ``log s_g^2``, and

.. math:: \\tilde\\sigma_g^2 = \\frac{d_0 s_0^2 + d_g s_g^2}{d_0 + d_g} .

``d_0`` is large when the groups' levels differ no more than their own sampling
error explains (every level near the common one) and small when they clearly
differ (each keeps its own). The effective degrees of freedom of a marker whose
residuals have lag-1 autocorrelation ``rho > 0`` are ``d (1 - rho^2) / (1 + rho^2)``
(the variance of a variance estimate from an AR(1) series). Finally no level
falls below the instrument floor :data:`INSTRUMENT_FLOOR_MM` (or the trial's
pooled level, where the whole trial is quieter than that: simulated data).

References: G. K. Smyth (2004), Linear models and empirical Bayes methods for
assessing differential expression in microarray experiments, Statistical
Applications in Genetics and Molecular Biology 3(1), article 3.

Example
-------
>>> import numpy as np
>>> from skelid.estimators.checks.noise import group_sigma
>>> s, dof = group_sigma(np.array([4.0, 9.0]), np.array([1.0, 1.0]), np.array([0, 1]))
>>> [float(v) for v in s]
[2.0, 3.0]
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np
from scipy.optimize import brentq
from scipy.special import digamma, polygamma

from skelid._linalg import summed_gram
from skelid.data import unit_scale
from skelid.errors import ModelError
from skelid.estimators.fit.joint import (
    JointFit,
    _banded_system,
    band_inverse_blocks,
    influence_rows,
    row_weights,
    weighted_terms,
)
from skelid.estimators.fit.likelihood import pose_information
from skelid.model.description import Model

#: a marker's sigma is kept within this factor of the pooled one (a marker that the fit
#: could follow almost exactly must not take all the weight)
SIGMA_RATIO_LIMIT = 10.0
#: no marker's noise level is estimated below this (mm; an optical system's reconstruction noise is
#: not smaller), unless the whole trial's pooled level is smaller still
INSTRUMENT_FLOOR_MM = 0.1


def row_leverage(Jq, Jt, R=None) -> np.ndarray:
    """Diagonal of the hat matrix of the joint fit, one value per residual row.

    Parameters
    ----------
    Jq : (T, m, Q) float
        Pose Jacobians (weighted rows; missing markers zero rows).
    Jt : (T, m, P) float
        Parameter Jacobians.
    R : sparse (T*Q, T*Q), optional
        Motion-model penalty on the poses.

    Returns
    -------
    (T, m) float, summing to ``T Q + P`` without a penalty (every row present
    and every pose fixed), to the fit's effective number of unknowns with one.
    """
    T, _, Q = Jq.shape
    Hqq = pose_information(Jq)
    if R is None:
        Ainv = np.linalg.pinv(Hqq, hermitian=True)
    else:
        Ainv = band_inverse_blocks(_banded_system(Hqq, R), Q)
    A, _ = influence_rows(Jq, Jt, R)
    S = summed_gram(Jt, A)
    S_inv = np.linalg.pinv(0.5 * (S + S.T), hermitian=True)
    return np.einsum("tki,tij,tkj->tk", Jq, Ainv, Jq) + np.einsum("tkp,pq,tkq->tk", A, S_inv, A)


def marker_leverage(model: Model, y, fit: JointFit, weights=None) -> np.ndarray:
    """Leverage summed over each marker's rows: ``(M,)``, the unknowns its data pay for."""
    y = np.where(fit.frames_used[:, None, None], np.asarray(y, float), np.nan)
    _, Jq, Jt = weighted_terms(model, fit.theta, fit.pose, y, row_weights(weights, y))
    h = row_leverage(Jq, Jt, fit.penalty)
    T, M = y.shape[:2]
    return h.reshape(T, M, model.dim).sum(axis=(0, 2))


def marker_rss(model: Model, y, fit: JointFit) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unweighted residual sum of squares ``(M,)``, coordinate count ``(M,)`` and the lag-1
    autocorrelation ``(M,)`` of each marker's residuals (over consecutive frames with the marker)."""
    from skelid.model.kinematics import marker_positions

    y = np.where(fit.frames_used[:, None, None], np.asarray(y, float), np.nan)
    r = y - marker_positions(model, fit.theta, fit.pose)
    ok = np.isfinite(r).all(axis=-1)
    r0 = np.where(ok[..., None], r, 0.0)
    rss = (r0**2).sum(axis=(0, 2))
    lag = (r0[1:] * r0[:-1]).sum(axis=(0, 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.where(rss > 0, lag / rss, 0.0)
    return rss, ok.sum(axis=0) * float(model.dim), np.clip(rho, -1.0, 1.0)


def effective_dof(dof, rho) -> np.ndarray:
    """Degrees of freedom of a variance estimated from an AR(1) series: ``d (1 - rho^2) / (1 + rho^2)``
    for ``rho > 0`` (a positive correlation makes the estimate noisier), ``d`` otherwise.

    Examples
    --------
    >>> [round(float(v), 2) for v in effective_dof(np.array([100.0, 100.0]), np.array([0.0, 0.5]))]
    [100.0, 60.0]
    """
    r2 = np.clip(np.asarray(rho, float), 0.0, 0.999) ** 2
    return np.asarray(dof, float) * (1.0 - r2) / (1.0 + r2)


def _trigamma_inverse(x: float) -> float:
    """``y`` with ``polygamma(1, y) = x`` (the trigamma function is decreasing on ``y > 0``)."""
    lo, hi = 1e-8, 1e8
    return float(brentq(lambda v: float(polygamma(1, v)) - x, lo, hi, xtol=1e-12, rtol=1e-12))


def squeeze_variances(s2, dof) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Empirical-Bayes posterior variances: each ``s2_g`` shrunk toward a common prior (Smyth 2004).

    The variances are modelled as ``s2_g ~ s_g^2 chi^2_{d_g} / d_g`` with ``1 / s_g^2`` drawn from
    a scaled inverse chi-square prior of ``d_0`` degrees of freedom and scale ``s_0^2``, fitted by
    the first two moments of ``log s2_g`` (its mean and variance less the sampling part
    ``trigamma(d_g / 2)``).

    Parameters
    ----------
    s2, dof : (G,) float
        Each group's variance and its (effective) degrees of freedom (> 0).

    Returns
    -------
    post : (G,) float
        ``(d_0 s_0^2 + d_g s2_g) / (d_0 + d_g)``.
    post_dof : (G,) float
        ``d_0 + d_g``.
    d0, s0_2 : float
        The prior (``d0`` infinite when the groups differ by less than their sampling error:
        every level is then ``s0_2``; 0 with fewer than three groups: no pooling).

    Examples
    --------
    Four groups whose levels differ by no more than two degrees of freedom explain keep little of
    their own:

    >>> post, _, d0, s0 = squeeze_variances(np.array([0.5, 1.0, 1.5, 2.0]), np.full(4, 2.0))
    >>> bool(np.isinf(d0)), [round(float(v), 3) for v in post]
    (True, [1.25, 1.25, 1.25, 1.25])
    """
    s2 = np.asarray(s2, float)
    d = np.asarray(dof, float)
    G = len(s2)
    if G < 3 or np.any(s2 <= 0) or np.any(d <= 0):
        return s2.copy(), d.copy(), 0.0, float(np.nan)
    e = np.log(s2) - digamma(d / 2) + np.log(d / 2)
    e_mean = float(e.mean())
    e_var = float(e.var(ddof=1) - np.mean(polygamma(1, d / 2)))
    if e_var <= 0:  # one common level: its pooled estimate
        s0_2 = float(np.sum(d * s2) / np.sum(d))
        return np.full(G, s0_2), np.full(G, np.inf), float(np.inf), s0_2
    d0 = 2.0 * _trigamma_inverse(e_var)
    s0_2 = float(np.exp(e_mean + digamma(d0 / 2) - np.log(d0 / 2)))
    return (d0 * s0_2 + d * s2) / (d0 + d), d0 + d, float(d0), s0_2


def pooled_levels(sigma, dof, groups, floor: float) -> tuple[np.ndarray, np.ndarray]:
    """Each marker's level shrunk toward the others' (:func:`squeeze_variances` over its groups) and
    held at or above ``floor``.

    Parameters
    ----------
    sigma, dof : (M,) float
        Each marker's (group's) own level and effective degrees of freedom; NaN where it has none.
    groups : (M,) int
    floor : float

    Returns
    -------
    sigma, dof : (M,) float
        The pooled levels and their posterior degrees of freedom.
    """
    sigma = np.asarray(sigma, float)
    dof = np.asarray(dof, float)
    _, first, inv = np.unique(np.asarray(groups), return_index=True, return_inverse=True)
    s, d = sigma[first], dof[first]
    ok = np.isfinite(s) & np.isfinite(d) & (s > 0) & (d > 0)
    post, pdof = s**2, d.copy()
    if ok.any():
        post[ok], pdof[ok], _, _ = squeeze_variances(s[ok] ** 2, d[ok])
    out = np.where(ok, np.sqrt(np.maximum(post, floor**2)), s)
    return out[inv], np.where(ok, pdof, d)[inv]


def group_sigma(rss, dof, groups) -> tuple[np.ndarray, np.ndarray]:
    """Noise level of each group, given to each of its markers.

    Parameters
    ----------
    rss, dof : (M,) float
        Each marker's residual sum of squares and residual degrees of freedom.
    groups : (M,) int
        Group label of each marker.

    Returns
    -------
    sigma, dof : (M,) float
        ``sqrt(sum rss / sum dof)`` over the marker's group, and that group's dof
        (NaN where the group has no residual degrees of freedom).
    """
    groups = np.asarray(groups)
    labels, inv = np.unique(groups, return_inverse=True)
    g_rss = np.bincount(inv, weights=rss, minlength=len(labels))
    g_dof = np.bincount(inv, weights=dof, minlength=len(labels))
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(g_dof > 0, np.sqrt(g_rss / np.where(g_dof > 0, g_dof, 1.0)), np.nan)
    return s[inv], np.where(g_dof > 0, g_dof, np.nan)[inv]


def marker_groups(names: Sequence[str], groups: Mapping[str, Sequence[str]] | None) -> np.ndarray:
    """(M,) int labels: markers named in one declared group share a label; others their own.

    Raises
    ------
    ModelError
        A group names a marker the model does not have, or a marker is in two groups.
    """
    label = np.arange(len(names))
    if not groups:
        return label
    index = {n: i for i, n in enumerate(names)}
    seen: dict[str, str] = {}
    for k, (gname, members) in enumerate(groups.items()):
        for n in members:
            if n not in index:
                raise ModelError(f"marker group {gname!r} names marker {n!r}, which the model does not have",
                                 f"use marker names of the model: {', '.join(names)}")
            if n in seen:
                raise ModelError(f"marker {n!r} is in two marker groups ({seen[n]!r} and {gname!r})",
                                 "put each marker in at most one group")
            seen[n] = gname
            label[index[n]] = len(names) + k
    return label


def weights_from_sigma(sigma, present) -> np.ndarray:
    """Weights ``s^2 / sigma_m^2`` (M,) with ``s`` the geometric mean over the markers present.

    Markers without an estimate (no data, no residual dof) get weight 1; each
    sigma is kept within :data:`SIGMA_RATIO_LIMIT` of the geometric mean.
    """
    sigma = np.asarray(sigma, float)
    ok = np.asarray(present, bool) & np.isfinite(sigma) & (sigma > 0)
    if not ok.any():
        return np.ones_like(sigma)
    ref = float(np.exp(np.mean(np.log(sigma[ok]))))
    s = np.clip(np.where(ok, sigma, ref), ref / SIGMA_RATIO_LIMIT, ref * SIGMA_RATIO_LIMIT)
    return (ref / s) ** 2


def per_marker_fit(model: Model, y, refit: Callable[[np.ndarray | None, JointFit], JointFit],
                   fit: JointFit, groups=None, n_rounds: int = 8, rtol: float = 1e-3):
    """Iterate weighted fits and per-marker noise levels to a fixed point.

    Parameters
    ----------
    y : (T, M, D) float
        Markers of the fit.
    refit : callable ``(weights (M,), previous fit) -> JointFit``
        Runs the weighted joint fit (with the caller's motion model and bounds).
    fit : JointFit
        The unweighted fit to start from.
    groups : (M,) int, optional
        Markers sharing a noise level (see :func:`marker_groups`).

    Returns
    -------
    fit : JointFit
        The last weighted fit.
    weights : (M,) float
    sigma : (M,) float
        Each marker's noise level (model units; NaN for a marker without data).
    dof : (M,) float
        Degrees of freedom behind each marker's (group's) level: its effective residual degrees
        of freedom and the pooling prior's (:func:`pooled_levels`).
    n_rounds : int
        Fits run.
    """
    M = np.asarray(y).shape[1]
    groups = np.arange(M) if groups is None else np.asarray(groups)
    weights = np.ones(M)
    sigma_old = None
    k = 0
    for k in range(1, n_rounds + 1):  # noqa: B007 - the count is reported
        rss, n, rho = marker_rss(model, y, fit)
        resid_dof = np.maximum(n - marker_leverage(model, y, fit, weights), 0.0)
        sigma, _ = group_sigma(rss, resid_dof, groups)
        _, eff = group_sigma(rss, effective_dof(resid_dof, rho), groups)
        pooled = float(np.sqrt(rss.sum() / max(resid_dof.sum(), 1e-300)))
        floor = min(INSTRUMENT_FLOOR_MM * unit_scale("mm", model.units), pooled)
        sigma, dof = pooled_levels(sigma, eff, groups, floor)
        new = weights_from_sigma(sigma, n > 0)
        if sigma_old is not None and np.allclose(sigma, sigma_old, rtol=rtol, equal_nan=True):
            break
        sigma_old = sigma
        weights = new
        fit = refit(weights, fit)
    return fit, weights, sigma, dof, k
