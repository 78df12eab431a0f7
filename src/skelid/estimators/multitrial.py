"""Several trials of one body: one geometry, poses, motion model and noise per trial.

Model: trial ``k = 1..K`` has its own frames, poses ``q_{kt}``, motion-model
cutoffs (at its own rate) and marker noise levels ``sigma_{km}``, and every
trial sees the same geometry ``theta``:

.. math:: y_{ktm} = x_m(q_{kt}, \\theta) + \\varepsilon_{ktm},
          \\qquad \\varepsilon_{ktm} \\sim N(0, \\sigma_{km}^2 I).

**Joint estimate.** The trials are stacked along the frame axis and fitted at
once (:func:`~skelid.estimators.fit.joint.joint_fit` with ``blocks``: the
low-pass motion-model penalty is block diagonal, so no smoothing crosses a trial
boundary; weights ``1/sigma_{km}^2``). With ``S_k`` the information about
``theta`` from trial ``k`` and ``A = sum_k S_k``, the joint estimate's
second-order bias and covariance are

.. math:: b = A^{-1} \\sum_k S_k b_k, \\qquad
          V = A^{-1} \\Big(\\sum_k S_k (C_k + \\Omega) S_k\\Big) A^{-1},

with ``b_k`` and ``C_k`` each trial's own bias and covariance (``C_k = S_k^{-1}``
for white noise, wider when the trial's residuals were serially correlated or an
artefact was stated). One trial gives back that trial's fit.

**Consistency.** Each trial's own estimate ``theta_k`` (bias removed) against the
joint one: ``X^2 = sum_k (theta_k - theta)^T C_k^{-1} (theta_k - theta)``, a
chi-square with ``(K - 1) P`` degrees of freedom when the trials agree.

**A trial that leaves a parameter unidentified** (its own status ``poor``,
``unidentified`` or ``on-bound``: an elbow centre from a trial whose elbow
never moved) contributes nothing to that parameter: it is marginalised out of
that trial's estimate (the trial's weight is the inverse of its covariance
restricted to the parameters it identifies), it enters neither that
parameter's between-trial variance nor the consistency test, and the joint
status is the best of the trials' own (a parameter no trial identifies keeps
the trials' status, and its interval stays inside its prior's support).

**Errors every trial shares.** Trials of one body recorded with one marker set
share the error of that marker set: a marker's placement on its segment, the
disagreement between markers that the marker jackknife measures. Each trial's
covariance is split into its own part and that shared part (``cov_shared_`` of
its fit). The between-trial variance, the random-effects weights, the
consistency test and the sd a trial is compared with use the own parts (the
shared part cancels in a difference of two trials); the joint estimate carries
the shared part once, not divided by the number of trials
(:func:`shared_covariance`), scaled down where the trials' own spread shows that
it does not recur.

**Between-trial excess variance.** Skin moves differently in different
movements; the part of it that mimics a geometry change shifts each trial's
estimate by a random amount ``u_k ~ N(0, Omega)``. ``Omega = diag(tau_p^2)`` is
estimated per parameter by DerSimonian and Laird's method of moments: with
``w_k = 1/C_{k,pp}``, ``bar theta = sum w_k theta_k / sum w_k`` and
``Q = sum_k w_k (theta_k - bar theta)^2``,

.. math:: \\tau^2 = \\max\\Big(0, \\frac{Q - (K - 1)}{\\sum w_k - \\sum w_k^2 / \\sum w_k}\\Big),

and then replaces the stacked fit (which is then not run) by the random-effects combination
``theta = (sum_k W_k)^{-1} sum_k W_k theta_k`` with ``W_k = (C_k + Omega)^{-1}``
and covariance ``(sum_k W_k)^{-1}``: a trial with a tiny within-trial variance
(a static trial, whose lengths follow the markers' nominal placement) no longer
decides the answer alone. A trial's own interval that includes it uses
``C_k + Omega``.

**Intervals with an estimated between-trial variance.** ``tau^2`` estimated
from ``K`` trials has about ``K - 1`` degrees of freedom, so a statistic
standardised by it follows a Student ``t`` rather than a normal law (with four
trials, ``t_3``: sd 1.7 instead of 1). Each interval therefore uses a ``t``
quantile with Satterthwaite's effective degrees of freedom for a variance
``V = V_w + V_b`` of which only the between-trial part ``V_b`` is estimated
with ``K - 1`` degrees of freedom:

.. math:: \\nu = (K - 1) \\, V^2 / V_b^2, \\qquad
          \\text{interval} = \\hat\\theta \\pm t_{\\nu, 0.975} \\sqrt{V}.

``nu`` is infinite (the normal interval) when ``tau^2 = 0`` and ``K - 1`` when
the between-trial part dominates. For the joint estimate ``V = 1 / sum_k w_k``
and ``V_b = tau^2 sum_k w_k^2 / (sum_k w_k)^2`` with ``w_k = 1 / (C_{k,pp} +
tau^2)``; for one trial's own interval ``V = C_{k,pp} + tau^2`` and ``V_b =
tau^2``. The reported sd is the interval's half-width over 1.959964, so that
anything that forms ``mean +- 1.96 sd`` gets the ``t`` interval.

**Few trials: a prior on the between-trial spread** (``between_trial='prior'``).
With two trials ``tau^2`` rests on one degree of freedom and the ``t_1`` interval
(97.5 % point 12.7) covers but says nothing. Outside information fixes that: each
``tau_p`` gets a half-normal prior whose scale is the sd that a documented
skin-marker artefact would add to one trial's estimate,

.. math:: \\tau_p \\sim \\mathrm{HalfNormal}(s_p), \\qquad
          s_p = a \\sqrt{\\tfrac1K \\textstyle\\sum_k \\Sigma_{art,k}[p, p]},

with ``Sigma_art,k`` the covariance of unit artefact in trial ``k``
(:mod:`skelid.estimators.checks.artefact`) and ``a = 10 mm`` (setting
``prior_artefact_rms``), the lower end of the 10-30 mm reported for thigh skin
markers. ``tau`` is then integrated out on a grid (:func:`tau_posterior`): the
joint interval is the symmetric interval about the random-effects centre (at
the posterior mean of ``tau^2``) holding 95 % of ``mu``'s posterior, a mixture of
normals over ``tau``; each trial's own interval holds 95 % of
``theta_k - mu ~ N(0, C_{k,pp} + tau^2)`` mixed the same way. With many trials the
data outweigh the prior and the intervals approach the estimated-``tau`` ones.
This is an assumption about artefact sizes, reported as such; it cannot widen
for an offset that every trial shares.

Example
-------
>>> import numpy as np
>>> from skelid.estimators.multitrial import dersimonian_laird
>>> tau2, q, df = dersimonian_laird(np.array([[0.0], [1.0], [3.0]]), np.ones((3, 1)))
>>> round(float(tau2[0]), 6), round(float(q[0]), 6), int(df)
(1.333333, 4.666667, 2)
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import brentq
from scipy.stats import chi2
from scipy.stats import t as student_t

from skelid._linalg import psd_sqrt
from skelid._stop import interruptible
from skelid.data import MarkerData
from skelid.errors import ConvergenceError, DataError, IdentifiabilityError, SkelidError
from skelid.estimators.base import (
    Setting,
    check_fitted,
    check_model,
    check_settings,
    emit,
    get_settings,
    make_rng,
    marker_array,
    non_negative_or_none,
    one_of,
)
from skelid.estimators.checks.artefact import artefact_covariance
from skelid.estimators.checks.misfit import MISFIT_ALPHA, MISFIT_EFFECT, joint_ranges
from skelid.estimators.checks.trial_motion import MIN_TRIALS, motion_trend
from skelid.estimators.fit.joint import joint_fit
from skelid.estimators.fit.likelihood import crlb_sd
from skelid.estimators.marker import MarkerEstimator, _combine_normal_priors, marker_warnings, run_marker_fit
from skelid.estimators.uncertainty.posterior import GaussianPosterior
from skelid.model.description import Model
from skelid.model.kinematics import joint_distances
from skelid.result import FitResult, NoiseEstimate, Warning

Z95 = 1.959963984540054


def dersimonian_laird(estimates, variances):
    """Between-trial variance of each parameter by the method of moments.

    Parameters
    ----------
    estimates : (K, P) float
        Each trial's estimate of each parameter.
    variances : (K, P) float
        Their within-trial variances.

    Returns
    -------
    tau2 : (P,) float
        Between-trial variance (0 when the spread is no more than the within-trial
        variances explain, or with one trial).
    q : (P,) float
        Cochran's heterogeneity statistic.
    df : int
        ``K - 1``.
    """
    y = np.atleast_2d(np.asarray(estimates, float))
    v = np.atleast_2d(np.asarray(variances, float))
    K = y.shape[0]
    if K < 2:
        return np.zeros(y.shape[1]), np.zeros(y.shape[1]), 0
    w = 1.0 / v
    sw = w.sum(axis=0)
    mean = (w * y).sum(axis=0) / sw
    q = (w * (y - mean) ** 2).sum(axis=0)
    c = sw - (w**2).sum(axis=0) / sw
    tau2 = np.maximum(0.0, (q - (K - 1)) / c)
    return tau2, q, K - 1


#: a trial's own sd is taken as at least this fraction of its estimate's size (an exact fit's is nil) ...
EXACT_RELATIVE = 1e-9
EXACT_FLOOR = 1e-150  # ... and its own variance as at least this (its weight's square stays finite)
#: eigenvalues of a trial's covariance below this fraction of its largest are left out of the test
CONSISTENCY_RCOND = 1e-12


def consistency_test(estimates, covs, joint) -> dict:
    """Chi-square test of the per-trial estimates against the joint one.

    ``X^2 = sum_k d_k^T C_k^+ d_k`` with ``d_k = theta_k - theta``: the information-weighted
    residual sum of squares of ``sum_k rank(C_k)`` observations about ``P`` parameters, so
    ``sum_k rank(C_k) - P`` degrees of freedom (``(K - 1) P`` when every covariance is of full
    rank). Below one degree of freedom (one trial) nothing is tested: ``p_value`` is None.

    Parameters
    ----------
    estimates : (K, P) float
    covs : (K, P, P) float
        Each trial's covariance.
    joint : (P,) float

    Returns
    -------
    dict with ``statistic``, ``dof``, ``p_value`` (None when not tested) and ``tested``.

    Examples
    --------
    >>> consistency_test(np.array([[1.0, 2.0]]), np.array([np.eye(2)]), np.array([1.0, 2.0]))["tested"]
    False
    """
    d = np.asarray(estimates, float) - np.asarray(joint, float)
    C = np.asarray(covs, float)
    w, V = np.linalg.eigh(0.5 * (C + np.swapaxes(C, -1, -2)))  # (K, P), (K, P, P)
    keep = w > CONSISTENCY_RCOND * np.maximum(w.max(axis=-1, keepdims=True), 1e-300)
    z = np.einsum("kpq,kp->kq", V, d)  # the deviations along each trial's eigenvectors
    stat = float(np.sum(np.where(keep, z**2 / np.where(keep, w, 1.0), 0.0)))
    dof = int(keep.sum()) - d.shape[1]
    if dof < 1:
        return {"statistic": stat, "dof": max(dof, 0), "p_value": None, "tested": False}
    return {"statistic": stat, "dof": dof, "p_value": float(chi2.sf(stat, dof)), "tested": True}


def pooled_noise_interval(sigma, dof, weights, level: float = 0.95) -> np.ndarray:
    """Interval of the pooled noise level ``sqrt(sum_k w_k sigma_k^2)`` from the trials' own levels.

    Each ``sigma_k^2`` is a chi-square estimate with ``dof_k`` degrees of freedom; their
    weighted sum is approximated by a scaled chi-square with Satterthwaite's degrees of freedom
    ``nu = (sum_k w_k s_k^2)^2 / sum_k (w_k s_k^2)^2 / dof_k`` (one trial: its own interval).

    Parameters
    ----------
    sigma, dof, weights : (K,) float
        Each trial's noise level, its degrees of freedom, and its weight (summing to 1).

    Returns
    -------
    (2,) float

    Examples
    --------
    >>> from scipy.stats import chi2
    >>> lo, hi = pooled_noise_interval([2.0], [50], [1.0])
    >>> bool(np.isclose(lo, np.sqrt(4.0 * 50 / chi2.ppf(0.975, 50))))
    True
    """
    v = np.asarray(weights, float) * np.asarray(sigma, float) ** 2
    nu = v.sum() ** 2 / np.sum(v**2 / np.maximum(np.asarray(dof, float), 1.0))
    a = (1.0 - level) / 2.0
    return np.sqrt(v.sum() * nu / chi2.ppf([1.0 - a, a], nu))


def pairwise_z(estimates, sds) -> np.ndarray:
    """``z`` of every pair of trials for each quantity: ``(K (K-1) / 2, P)``.

    ``z = (a - b) / sqrt(sd_a^2 + sd_b^2)``.
    """
    x = np.asarray(estimates, float)
    s = np.asarray(sds, float)
    i, j = np.triu_indices(x.shape[0], 1)
    return (x[i] - x[j]) / np.sqrt(s[i] ** 2 + s[j] ** 2)




def paule_mandel(estimates, variances):
    """Between-trial variance of each parameter by Paule and Mandel's method.

    ``tau^2`` solves ``sum_k w_k (theta_k - bar theta_w)^2 = K - 1`` with
    ``w_k = 1 / (v_k + tau^2)`` (0 when the left side is below ``K - 1`` at
    ``tau^2 = 0``). Unlike DerSimonian-Laird's moments with the fixed-effect
    weights, it is not dominated by one trial with a tiny variance.

    Parameters
    ----------
    estimates, variances : (K, P) float

    Returns
    -------
    tau2 : (P,) float
    q : (P,) float
        Cochran's ``Q`` (fixed-effect weights), as :func:`dersimonian_laird`.
    df : int

    References
    ----------
    Paule RC, Mandel J (1982). Consensus values and weighting factors. J Res Natl Bur Stand 87:377-385.
    Veroniki AA et al. (2016). Methods to estimate the between-study variance and its uncertainty
    in meta-analysis. Res Synth Methods 7:55-79.

    Examples
    --------
    >>> tau2, _, _ = paule_mandel(np.array([[0.0], [1.0], [3.0]]), np.ones((3, 1)))
    >>> round(float(tau2[0]), 6)  # equal variances: the sample variance minus the within one
    1.333333
    """
    y = np.atleast_2d(np.asarray(estimates, float))
    v = np.atleast_2d(np.asarray(variances, float))
    _, q, df = dersimonian_laird(y, v)
    tau2 = np.zeros(y.shape[1])
    if df < 1:
        return tau2, q, df

    def excess(t2, yp, vp):
        w = 1.0 / (vp + t2)
        m = (w * yp).sum() / w.sum()
        return (w * (yp - m) ** 2).sum() - df

    for p in range(y.shape[1]):
        yp, vp = y[:, p], v[:, p]
        if excess(0.0, yp, vp) <= 0:
            continue
        hi = max(float(np.var(yp, ddof=1)), 1e-12)
        while excess(hi, yp, vp) > 0:
            hi *= 4.0
        tau2[p] = brentq(excess, 0.0, hi, args=(yp, vp), xtol=1e-12 * hi, rtol=1e-12)
    return tau2, q, df


#: between-trial variance estimators by name
BETWEEN_TRIAL = {"dl": dersimonian_laird, "pm": paule_mandel}

#: Root-mean-square skin-marker artefact (mm, per marker coordinate) that scales the prior on the
#: between-trial spread: the lower end of the 10-30 mm reported for thigh skin markers (Leardini et al.
#: 2005; Peters et al. 2010), so the prior leans wide for a thigh and wider still for a shank or arm.
PRIOR_ARTEFACT_RMS_MM = 10.0
_MM_PER_UNIT = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


def tau_posterior(estimates, variances, scale, n_grid: int = 801):
    """Posterior of the between-trial sd ``tau`` of each parameter under a half-normal prior, on a grid.

    Model (one parameter): ``theta_k ~ N(mu, v_k + tau^2)``, ``mu`` flat, ``tau ~ HalfNormal(s)``.
    Integrating ``mu`` out leaves the restricted likelihood

    .. math:: p(\\tau \\mid \\theta) \\propto e^{-\\tau^2 / 2 s^2}
              \\prod_k (v_k + \\tau^2)^{-1/2} \\Big(\\sum_k w_k\\Big)^{-1/2}
              \\exp\\Big(-\\tfrac12 \\sum_k w_k (\\theta_k - m)^2\\Big),

    ``w_k = 1 / (v_k + tau^2)``, ``m = sum w_k theta_k / sum w_k``; given ``tau``,
    ``mu ~ N(m, 1 / sum w_k)``. The grid ``tau = 8 s x^2`` (``x`` uniform on [0, 1]) is dense
    near 0, where a precise trial's likelihood varies fastest; trapezoid weights.

    Parameters
    ----------
    estimates, variances : (K, P) float
    scale : (P,) float
        Prior scale ``s`` of each parameter's ``tau`` (0: ``tau = 0``, the fixed-effect combination).
    n_grid : int

    Returns
    -------
    tau : (G, P) float
        Grid of ``tau`` values.
    weight : (G, P) float
        Posterior probability of each grid point (sums to 1 over ``G``).
    mean, var : (G, P) float
        ``mu``'s conditional mean and variance given each ``tau``.
    """
    y = np.atleast_2d(np.asarray(estimates, float))
    v = np.atleast_2d(np.asarray(variances, float))
    s = np.broadcast_to(np.asarray(scale, float), (y.shape[1],))
    x = np.linspace(0.0, 1.0, n_grid)
    tau = 8.0 * s[None, :] * x[:, None] ** 2  # (G, P)
    w = 1.0 / (v[None] + tau[:, None, :] ** 2)  # (G, K, P)
    sw = w.sum(axis=1)
    mean = (w * y[None]).sum(axis=1) / sw
    q = (w * (y[None] - mean[:, None, :]) ** 2).sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        log_prior = np.where(s > 0, -0.5 * (tau / np.where(s > 0, s, 1.0)) ** 2, 0.0)
    log_post = log_prior + 0.5 * np.log(w).sum(axis=1) - 0.5 * np.log(sw) - 0.5 * q
    log_post = log_post - log_post.max(axis=0)
    dt = np.diff(tau, axis=0)
    trap = np.zeros_like(tau)
    trap[:-1] += dt / 2
    trap[1:] += dt / 2
    weight = np.exp(log_post) * trap
    tot = weight.sum(axis=0)
    zero = tot <= 0  # s = 0: all the mass at tau = 0
    weight[:, zero] = 0.0
    weight[0, zero] = 1.0
    weight = weight / weight.sum(axis=0)
    return tau, weight, mean, 1.0 / sw


def mixture_half_width(weight, loc, var, centre, level: float = 0.95, n_iter: int = 60):
    """Half-width ``h`` with probability ``level`` in ``[centre - h, centre + h]`` under a normal mixture.

    Parameters
    ----------
    weight, loc, var : (G, ...) float
        Mixture weights (summing to 1 over ``G``), means and variances.
    centre : (...) float

    Returns
    -------
    (...) float
        By bisection (``n_iter`` halvings of the bracket).
    """
    from scipy.special import ndtr

    weight, loc, var = np.broadcast_arrays(*(np.asarray(a, float) for a in (weight, loc, var)))
    sd = np.sqrt(var)
    c = np.asarray(centre, float)

    def mass(h):
        return (weight * (ndtr((c + h - loc) / sd) - ndtr((c - h - loc) / sd))).sum(axis=0)

    lo = np.zeros(weight.shape[1:])
    hi = (np.abs(loc - c) + 8.0 * sd).max(axis=0)
    for _ in range(n_iter):
        mid = 0.5 * (lo + hi)
        below = mass(mid) < level
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    return 0.5 * (lo + hi)


def random_effects_prior(estimates, variances, scale, level: float = 0.95):
    """Random-effects combination with a half-normal prior on the between-trial sd.

    The joint estimate is ``mu``'s posterior mean and its interval the symmetric one about it
    that holds ``level`` of the posterior (a mixture of normals over ``tau``, see
    :func:`tau_posterior`). Each trial's own interval is the one that holds ``level`` of
    ``theta_k - mu ~ N(0, v_k + tau^2)`` mixed over the same posterior: what another trial's
    estimate is compared with.

    Parameters
    ----------
    estimates, variances : (K, P) float
    scale : (P,) float
        Half-normal prior scale of each parameter's ``tau``.

    Returns
    -------
    mean : (P,) float
    half_width : (P,) float
    tau2 : (P,) float
        Posterior mean of ``tau^2``.
    trial_half_width : (K, P) float

    Examples
    --------
    Two trials 10 apart with unit variances: a ``t_1`` interval (DerSimonian-Laird) would be
    +-12.7 times the combined sd; a prior of scale 5 keeps it informative:

    >>> m, h, tau2, th = random_effects_prior(np.array([[0.0], [10.0]]), np.ones((2, 1)), [5.0])
    >>> float(m[0]), round(float(h[0]), 1), round(float(np.sqrt(tau2[0])), 1)
    (5.0, 9.8, 6.7)
    """
    v = np.atleast_2d(np.asarray(variances, float))
    tau, weight, mean, var = tau_posterior(estimates, v, scale)
    mu = (weight * mean).sum(axis=0)
    half = mixture_half_width(weight, mean, var, mu, level)
    tau2 = (weight * tau**2).sum(axis=0)
    trial_half = mixture_half_width(weight[:, None, :], 0.0, v[None] + tau[:, None, :] ** 2,
                                    np.zeros(v.shape), level)
    return mu, half, tau2, trial_half


def t_factor(dof) -> np.ndarray:
    """``t_{dof, 0.975} / z_{0.975}``: how much wider a ``t`` interval is than the normal one (1 at infinity)."""
    d = np.asarray(dof, float)
    out = np.ones_like(d)
    fin = np.isfinite(d)
    out[fin] = student_t.ppf(0.975, np.maximum(d[fin], 1e-6)) / Z95
    return out


def satterthwaite_dof(total, between, df) -> np.ndarray:
    """Effective degrees of freedom of a variance ``total`` of which ``between`` is estimated with ``df``
    (a scalar, or one per entry).

    ``nu = df * total^2 / between^2`` (infinite where ``between`` is 0).
    """
    total, between = np.broadcast_arrays(np.asarray(total, float), np.asarray(between, float))
    df = np.broadcast_to(np.asarray(df, float), total.shape)
    out = np.full(total.shape, np.inf)
    pos = between > 0
    out[pos] = df[pos] * (total[pos] / between[pos]) ** 2
    return out


def random_effects(estimates, covs, tau2, informs=None):
    """Random-effects combination of the trials and the ``t`` widening of its interval.

    Parameters
    ----------
    estimates : (K, P) float
    covs : (K, P, P) float
        Within-trial covariances ``C_k``.
    tau2 : (P,) float
        Between-trial variances.
    informs : (K, P) bool, optional
        Which trial contributes to which parameter (default: every one to every one). A trial
        that does not contribute to a parameter is marginalised over it: its weight is the
        inverse of ``C_k + Omega`` restricted to the parameters it informs, zero elsewhere.

    Returns
    -------
    theta : (P,) float
        ``(sum W_k)^{-1} sum W_k theta_k`` with ``W_k = (C_k + diag tau2)^{-1}``.
    cov : (P, P) float
        ``(sum W_k)^{-1}``.
    dof : (P,) float
        Satterthwaite degrees of freedom of each variance (see the module notes), with
        ``K_p - 1`` for the ``K_p`` trials that inform parameter ``p``.

    Examples
    --------
    >>> th, cov, dof = random_effects(np.array([[0.0], [2.0]]), np.ones((2, 1, 1)), np.array([1.0]))
    >>> float(th[0]), float(cov[0, 0]), float(dof[0])  # V = 1, V_b = 1/2: nu = 1 * (1 / 0.5)^2
    (1.0, 1.0, 4.0)
    """
    y = np.asarray(estimates, float)
    C = np.asarray(covs, float)
    tau2 = np.asarray(tau2, float)
    K, P = y.shape
    m = np.ones((K, P), bool) if informs is None else np.asarray(informs, bool)
    W = random_effects_weights(C, tau2, m)
    cov = np.linalg.inv(W.sum(axis=0))
    theta = cov @ np.einsum("kpq,kq->p", W, y)
    w = np.where(m, 1.0 / (np.einsum("kpp->kp", C) + tau2), 0.0)  # per-parameter weights for the dof
    total = 1.0 / w.sum(axis=0)
    between = tau2 * (w**2).sum(axis=0) / w.sum(axis=0) ** 2
    return theta, cov, satterthwaite_dof(total, between, np.maximum(m.sum(axis=0) - 1, 1))


def random_effects_weights(covs, tau2, informs) -> np.ndarray:
    """``(K, P, P)``: each trial's weight ``(C_k + diag tau2)^{-1}`` restricted to the parameters it informs."""
    C = np.asarray(covs, float)
    m = np.asarray(informs, bool)
    W = np.zeros(C.shape)
    for k in range(C.shape[0]):
        i = np.flatnonzero(m[k])
        if i.size:
            W[k][np.ix_(i, i)] = np.linalg.inv((C[k] + np.diag(tau2))[np.ix_(i, i)])
    return W


def shared_covariance(weights, norm, shared, tau2, informs) -> tuple[np.ndarray, np.ndarray]:
    """Covariance of a combination of trials from errors that every trial shares.

    The trials were recorded with one marker set on one body, so the error that a marker's
    placement (or its disagreement with the others) causes recurs in each: trial ``k``'s
    shared error is ``L_k u`` with one ``u ~ N(0, I)`` for all (``L_k`` the symmetric square
    root of its shared covariance). The combination ``norm sum_k W_k theta_k`` then carries
    ``G u`` with ``G = norm sum_k W_k L_k``: nothing of it averages out over the trials.

    How much really recurs is measured by the trials themselves: a between-trial variance
    ``tau_p^2`` as large as the shared variance ``s_p^2`` (mean over the trials that inform
    ``p``) says the shared part differs from trial to trial and is already in ``tau``. Row
    ``p`` of ``G`` is therefore scaled by ``sqrt(max(0, 1 - tau_p^2 / s_p^2))``.

    Parameters
    ----------
    weights : (K, P, P) float
    norm : (P, P) float
        ``(sum_k W_k)^{-1}``.
    shared : (K, P, P) float
        Each trial's shared covariance.
    tau2 : (P,) float
    informs : (K, P) bool

    Returns
    -------
    cov : (P, P) float
    recurring : (P,) float
        The scale of each row (1: every trial shares the error, 0: none of it recurs).

    Examples
    --------
    Two trials with the same shared variance 4 and no between-trial spread: the combination keeps
    all of it (an average of two copies of one error is that error):

    >>> W = np.ones((2, 1, 1))
    >>> cov, r = shared_covariance(W, np.array([[0.5]]), np.full((2, 1, 1), 4.0), np.zeros(1), np.ones((2, 1), bool))
    >>> float(cov[0, 0]), float(r[0])
    (4.0, 1.0)
    """
    Sh = np.asarray(shared, float)
    m = np.asarray(informs, bool)
    G = np.asarray(norm, float) @ np.einsum("kpq,kqr->pr", weights, psd_sqrt(Sh))
    v = np.einsum("kpp->kp", Sh)
    n = np.maximum(m.sum(axis=0), 1)
    mean_v = np.where(m, v, 0.0).sum(axis=0) / n
    with np.errstate(divide="ignore", invalid="ignore"):
        recurring = np.where(mean_v > 0, np.sqrt(np.clip(1.0 - np.asarray(tau2, float) / mean_v, 0.0, 1.0)), 0.0)
    G = recurring[:, None] * G
    return G @ G.T, recurring


def trial_informs(statuses) -> np.ndarray:
    """``(K, P)`` bool: which trial contributes to which parameter.

    A trial contributes to a parameter its own fit identifies (status ``'identified'``, or
    ``'placement'``: a standing trial's scale factors follow from the markers' placement, with
    the placement's uncertainty in their interval); one that leaves it poorly identified,
    unidentified or on a bound contributes nothing to it (its estimate there is its prior's, or
    noise). Where no trial identifies a parameter every trial contributes, and the joint status
    says so.

    Parameters
    ----------
    statuses : (K, P) sequence of str

    Examples
    --------
    >>> trial_informs([["identified", "poor"], ["placement", "identified"]]).tolist()
    [[True, False], [True, True]]
    >>> trial_informs([["poor"], ["unidentified"]]).tolist()
    [[True], [True]]
    """
    m = np.array([[s in ("identified", "placement") for s in row] for row in statuses], bool)
    m[:, ~m.any(axis=0)] = True
    return m


def joint_status(statuses) -> list[str]:
    """Each parameter's status over several trials: the best of the trials' own
    (``identified`` > ``placement`` > ``poor`` > ``unidentified`` > ``on-bound``)."""
    order = ("identified", "placement", "poor", "unidentified", "unidentifiable", "on-bound", "prior")
    rank = {s: k for k, s in enumerate(order)}
    cols = list(zip(*statuses, strict=True))
    return [min(c, key=lambda s: rank.get(s, len(order))) for c in cols]


def own_variance_floor(estimates, variances) -> np.ndarray:
    """Each trial's own variance ``(K, P)``, at least ``EXACT_RELATIVE`` of its parameter's size squared.

    A trial fitted exactly (no noise: all of its covariance is the shared placement's) has a nil own
    variance; it weighs as a trial known to that precision, not infinitely (a division by zero)."""
    y = np.atleast_2d(np.asarray(estimates, float))
    v = np.atleast_2d(np.asarray(variances, float))
    size = np.abs(y).max(axis=0, initial=0.0)
    return np.maximum(v, np.maximum((EXACT_RELATIVE * size) ** 2, EXACT_FLOOR))


def per_parameter(between, estimates, variances, informs):
    """A between-trial variance estimator (:data:`BETWEEN_TRIAL`) run for each parameter over the
    trials that inform it: ``tau2, q, df``, each ``(P,)``."""
    y = np.atleast_2d(np.asarray(estimates, float))
    v = np.atleast_2d(np.asarray(variances, float))
    m = np.asarray(informs, bool)
    tau2, q, df = np.zeros(y.shape[1]), np.zeros(y.shape[1]), np.zeros(y.shape[1], int)
    for p in range(y.shape[1]):
        t, qq, d = between(y[m[:, p], p:p + 1], v[m[:, p], p:p + 1])
        tau2[p], q[p], df[p] = t[0], qq[0], d
    return tau2, q, df


def _check_some_trial_moves(model: Model, trials, rate) -> None:
    """Refuse trials of which none moves (:func:`skelid.checks.check_motion`, the first trial's message)."""
    from skelid.checks import check_motion

    first = None
    for k, data in enumerate(trials):
        try:
            check_motion(model, marker_array(model, data, rate)[0], _trial_label(data, k))
            return
        except DataError as exc:
            first = first or exc
        except SkelidError:
            return  # the trial's own fit says what is wrong with it
    if first is not None:
        raise first


def _trial_status(est) -> list[str]:
    """A fitted trial's own status of each parameter (its identifiability table, final interval)."""
    rows = {r["parameter"]: r["status"] for r in est.identifiability_.get("table", [])}
    return [rows.get(n, "identified") for n in est.model.parameter_names]


def _trial_label(data, k: int) -> str:
    src = getattr(data, "source", None)
    if src:
        return str(src).replace("\\", "/").rsplit("/", 1)[-1]
    return f"trial {k + 1}"


def _as_trials(trials) -> list:
    """A list of trials from one MarkerData or array, or a sequence of them."""
    if isinstance(trials, MarkerData) or (isinstance(trials, np.ndarray) and trials.ndim == 3):
        return [trials]
    try:
        return list(trials)
    except TypeError:
        raise DataError(f"trials must be MarkerData, an array or a list of them, got {type(trials).__name__}",
                        "give a list of MarkerData, one per trial") from None


class MultiTrialEstimator:
    """One geometry from several trials of one body.

    Parameters
    ----------
    model : Model
    between_trial : {'prior', 'dl', 'pm', 'none'}
        Integrate the between-trial sd of each parameter out under a half-normal prior
        ('prior', the default, see the module notes: informative from two trials on),
        estimate it (DerSimonian-Laird or Paule-Mandel, with a ``t`` quantile of
        ``K - 1`` degrees of freedom), or leave it out.
    prior_artefact_rms : float, optional
        Root-mean-square skin-marker artefact (model units) that scales the prior on
        the between-trial sd (``between_trial='prior'``); None: 10 mm.
    **settings
        Every setting of :class:`~skelid.estimators.marker.MarkerEstimator` (``sigma``,
        ``cutoff``, ``noise``, ``marker_groups``, ``artefact_rms``, ``outlier_threshold``,
        ``rng``, ``rate`` ...), used for each trial; they become attributes of this
        estimator as well.

    Attributes
    ----------
    theta_ : (P,) float
        Joint estimate (bias removed, normal priors combined).
    cov_ : (P, P) float
        Its covariance, between-trial variance included and scaled by the ``t``
        factor of each parameter (so that ``theta_ +- 1.96 sd`` is the ``t`` interval).
    cov_within_ : (P, P) float
        Without the between-trial variance.
    dof_ : (P,) float
        Satterthwaite degrees of freedom of the joint interval (inf: normal).
    posterior_ : GaussianPosterior
    sigma_ : float
        Root-mean-square of the trials' noise levels, weighted by their frames used.
    sigma_ci_ : (2,) float or None
        Its 95 % interval (:func:`pooled_noise_interval`); None when ``sigma`` is given.
    crlb_sd_ : (P,) float
        Cramér-Rao bound (standard deviation) of all the trials' frames with one geometry and
        every pose free: the inverse of the sum of the trials' efficient informations.
    frames_used_ : (sum F_k,) bool
        The trials' frames, one after the other.
    trials_ : list of MarkerEstimator
        Each trial's own fit.
    trial_labels_ : list of str
    trial_theta_ : (K, P) float
        Each trial's own estimate (bias removed, before priors).
    trial_cov_ : (K, P, P) float
        Their covariances.
    trial_sd_ : (K, P) float
        Each trial's own sd with the between-trial variance and its ``t`` factor, without the part
        that every trial shares (it cancels between trials): what another trial's estimate, or
        the joint one, is compared with.
    trial_shared_ : (K, P, P) float
        Each trial's shared covariance (``cov_shared_`` of its fit: the marker jackknife's and
        the placement's terms).
    cov_shared_ : (P, P) float
        The part of ``cov_`` from errors every trial shares (:func:`shared_covariance`).
    shared_recurring_ : (P,) float
        How much of each parameter's shared error the trials' agreement says recurs (1: all).
    trial_status_ : (K, P) str
        Each trial's own status of each parameter (``identified``, ``poor``, ...).
    trial_informs_ : (K, P) bool
        Which trial contributes to which parameter (:func:`trial_informs`): a trial that leaves a
        parameter unidentified or poorly identified adds nothing to it, neither to the estimate nor
        to its between-trial variance or the consistency test.
    status_ : dict
        Each parameter's status over the trials (:func:`joint_status`).
    tau2_ : (P,) float
        Between-trial variance of each parameter (its posterior mean with ``'prior'``).
    tau_prior_scale_ : (P,) float
        Half-normal prior scale of each between-trial sd (0 unless ``'prior'``).
    trials_set_aside_ : list of str
        Trials left out of the combination because their own fit ended on a
        prior bound, or did not converge (their own estimates are still
        reported); empty when none was, or when every trial ended on a bound.
    trials_not_converged_ : list of str
        The trials set aside because their own fit did not converge.
    consistency_ : dict
        :func:`consistency_test` of the trials against the joint estimate (``tested`` False,
        ``p_value`` None below one degree of freedom).
    heterogeneity_ : dict
        Per parameter: Cochran's ``Q``, ``I^2``, ``tau`` and the degrees of freedom.
    motion_trend_ : dict
        Per parameter of a joint, with at least four trials that inform it: the meta-regression of
        their estimates on the range of that joint's motion in each trial
        (:func:`~skelid.estimators.checks.trial_motion.motion_trend`); a significant trend of at least
        half an sd is named in a warning (``trend-with-motion``).
    lengths_ : dict
        Derived lengths of the joint estimate.
    fit_info_ : JointFit or None
        The stacked fit (all frames, one geometry); None when the trials disagree
        (some ``tau^2 > 0``) and the joint estimate combines the trials' own.
    pose_ : (sum F_k, Q) float
        Poses of the stacked fit, or each trial's own when there is none.
    converged_ : bool
        Whether the stacked fit (or, without one, every trial's fit) converged.
    warnings_ : tuple of Warning
    """

    name = "marker-multi"
    settings = (Setting("between_trial", one_of("dl", "pm", "prior", "none"), "'dl', 'pm', 'prior' or 'none'"),
                Setting("prior_artefact_rms", non_negative_or_none, "a distance >= 0 in model units, or None"),
                *MarkerEstimator.settings)

    def __init__(self, model: Model, between_trial: str = "prior", prior_artefact_rms: float | None = None,
                 **settings):
        self.model = check_model(model, type(self).__name__)
        self.between_trial = between_trial
        self.prior_artefact_rms = prior_artefact_rms
        # the single-trial estimator's declared settings and defaults, stored here as well
        for k, v in get_settings(MarkerEstimator(model, **settings)).items():
            setattr(self, k, v)

    def _trial_settings(self) -> dict:
        return {s.name: getattr(self, s.name) for s in MarkerEstimator.settings}

    @interruptible
    def fit(self, trials, *, progress=None) -> MultiTrialEstimator:
        """Fit every trial alone, then all of them at once with one geometry.

        Parameters
        ----------
        trials : MarkerData, (F, M, D) array, or a sequence of them
            The trials (arrays with the ``rate`` setting).
        progress : callable, optional
            Called with each trial's number of frames once it is fitted.
        """
        check_settings(self)
        trials = _as_trials(trials)
        if not trials:
            raise DataError("no trials to fit", "give at least one marker file")
        ests, labels = [], []
        if len(trials) > 1:  # a still trial (a static one) among several is fine where another moves
            _check_some_trial_moves(self.model, trials, self.rate)
        for k, data in enumerate(trials):
            label = _trial_label(data, k)
            try:
                est = self.fit_trial(data, alone=len(trials) == 1)
            except SkelidError as exc:
                raise type(exc)(f"{label}: {exc.problem}", exc.fix) from None
            ests.append(est)
            labels.append(label if label not in labels else f"{label} ({k + 1})")
            if progress is not None:
                progress(len(est.frames_used_))
        if self.model.n_params == 1 and all(bool(np.any(e.fit_.pinned)) for e in ests):
            p = self.model.parameters[0]
            raise IdentifiabilityError(
                f"no solution inside the interval [{p.prior.lower:g}, {p.prior.upper:g}] of parameter {p.name}: "
                f"the best fit of every trial sits on a bound", "widen the parameter's prior bounds or check the "
                "model's marker positions")
        rates = [d.rate if isinstance(d, MarkerData) else float(self.rate) for d in trials]
        return self.combine(ests, rates, labels)

    def fit_trial(self, data, alone: bool = True) -> MarkerEstimator:
        """One trial's own fit, as :meth:`fit` makes it (``alone=False``: a trial among several, which
        may be still).

        As :meth:`MarkerEstimator.fit <skelid.estimators.marker.MarkerEstimator.fit>` with this
        estimator's settings, except that a fit ending on a bound of the prior warns instead of
        refusing (a single-parameter model refuses there when fitted alone), and, among several
        trials, a fit that does not converge keeps its estimate with the ``not-converged``
        warning instead of refusing: :meth:`combine` sets such a trial aside and the other
        trials decide.
        """
        check_settings(self)
        settings = self._trial_settings()
        if not alone:
            settings["on_nonconvergence"] = "warn"
        est = MarkerEstimator(self.model, **settings)
        check_settings(est)
        y, rate = marker_array(self.model, data, est.rate, self.name, motion=alone)
        f = run_marker_fit(est, y, rate, make_rng(est.rng), on_bound="warn")
        est._publish(f, emit(marker_warnings(self.model, est, f)))
        return est

    def combine(self, fitted, rates, labels=None) -> MultiTrialEstimator:
        """One geometry from trials already fitted one by one (what :meth:`fit` does after its trial fits).

        Parameters
        ----------
        fitted : sequence of fitted MarkerEstimator
            One per trial, fitted to the same model with this estimator's settings.
        rates : sequence of float
            Each trial's sampling rate (Hz).
        labels : sequence of str, optional
            Names of the trials in the result (default ``trial 1``, ``trial 2``, ...).
        """
        check_settings(self)
        ests = list(fitted)
        if not ests:
            raise DataError("no trials to combine", "give at least one fitted trial")
        key = (self.model.parameter_names, self.model.marker_names)
        if any((e.model.parameter_names, e.model.marker_names) != key for e in ests):
            raise DataError("the fitted trials use another model than this estimator",
                            "fit every trial with the same model")
        self.trials_ = ests
        self.trial_labels_ = list(labels) if labels is not None else [f"trial {k + 1}" for k in range(len(ests))]
        self.trial_theta_ = np.array([e.theta_profile_ - e.bias_ for e in ests])
        self.trial_cov_ = np.array([e.cov_data_ for e in ests])
        zero = np.zeros((self.model.n_params, self.model.n_params))
        self.trial_shared_ = np.array([zero if getattr(e, "cov_shared_", None) is None else e.cov_shared_
                                       for e in ests])
        self.trial_status_ = np.array([_trial_status(e) for e in ests], dtype=object)
        self._within(ests)
        fit = self._combine(lambda: self._stacked_fit(ests, [float(r) for r in rates]))
        self._publish(fit, ests)
        return self

    def _within(self, ests) -> None:
        """Bias and covariance of the information-weighted combination (no between-trial variance)."""
        S = np.array([np.linalg.inv(e.cov_plain_) for e in ests])  # (K, P, P) information
        A_inv = np.linalg.inv(S.sum(axis=0))
        self.bias_ = A_inv @ np.einsum("kpq,kq->p", S, np.array([e.bias_ for e in ests]))
        own = self.trial_cov_ - self.trial_shared_
        sandwich = np.einsum("kpq,kqr,krs->ps", S, own, S)
        shared, _ = shared_covariance(S, A_inv, self.trial_shared_, np.zeros(len(A_inv)), np.ones(own.shape[:2], bool))
        self._shared_within = shared
        self.cov_within_ = A_inv @ sandwich @ A_inv + shared

    def _stacked_fit(self, ests, rates):
        """All trials' frames at once with one geometry (block-diagonal motion model, per-trial weights)."""
        model = self.model
        S = np.array([np.linalg.inv(e.cov_plain_) for e in ests])
        A_inv = np.linalg.inv(S.sum(axis=0))
        lengths = [len(e.pose_) for e in ests]
        edges = np.concatenate([[0], np.cumsum(lengths)])
        blocks = [(int(a), int(b), rates[k], e.cutoff_)
                  for k, (a, b, e) in enumerate(zip(edges[:-1], edges[1:], ests, strict=True))]
        M = len(model.marker_names)
        weights = np.concatenate([
            np.broadcast_to((np.ones(M) if e.marker_weights_ is None else e.marker_weights_) / e.sigma_**2,
                            (n, M)) for e, n in zip(ests, lengths, strict=True)])
        y = np.concatenate([e.y_ for e in ests])
        pose = np.concatenate([e.pose_ for e in ests])
        used = np.concatenate([e.frames_used_ for e in ests])
        lo = np.array([p.prior.lower for p in model.parameters])
        hi = np.array([p.prior.upper for p in model.parameters])
        theta0 = np.clip(A_inv @ np.einsum("kpq,kq->p", S, np.array([e.theta_profile_ for e in ests])), lo, hi)
        return joint_fit(model, y, theta0, pose, n_iter=self.n_iter, bounds=(lo, hi), frames=used,
                         blocks=blocks, weights=weights)

    def _combine(self, stacked):
        """Between-trial variance, the joint estimate and its interval, each trial's own interval.

        ``stacked()`` runs the stacked fit; it is needed (and run) only when the trials agree
        (every ``tau^2 = 0``): otherwise the joint estimate is the random-effects combination of
        the trials' own estimates. Returns the stacked fit or None.
        """
        fit = None
        P = self.model.n_params
        # each trial's own errors: its shared part (the marker set's placement) cancels between trials
        own = self.trial_cov_ - self.trial_shared_
        var = own_variance_floor(self.trial_theta_, np.einsum("kpp->kp", own))
        keep = self._kept()
        theta_k, cov_k, K = self.trial_theta_[keep], own[keep], int(keep.sum())
        # a trial that leaves a parameter unidentified contributes nothing to it
        self.trial_informs_ = np.ones_like(self.trial_theta_, bool)
        self.trial_informs_[keep] = informs = trial_informs(self.trial_status_[keep])
        method = self.between_trial if self.between_trial in BETWEEN_TRIAL else "dl"
        tau2, q, df = per_parameter(BETWEEN_TRIAL[method], theta_k, var[keep], informs)
        if self.between_trial == "none":
            tau2 = np.zeros(P)
        prior = self.between_trial == "prior" and K > 1
        self.tau_prior_scale_ = self._tau_prior_scale([e for e, k in zip(self.trials_, keep, strict=True) if k])
        if prior:
            # half-normal prior on each tau: the joint interval and each trial's own hold 95 % of the
            # posterior (a normal mixture over tau); centre: the random-effects combination at E[tau^2]
            cols = [tau_posterior(theta_k[informs[:, p], p:p + 1], var[keep][informs[:, p], p:p + 1],
                                  self.tau_prior_scale_[p:p + 1]) for p in range(P)]
            grid, weight, mean, cvar = (np.concatenate(a, axis=1) for a in zip(*cols, strict=True))
            tau2 = (weight * grid**2).sum(axis=0)
        self.tau2_ = tau2
        if prior:
            theta, cov, _ = random_effects(theta_k, cov_k, tau2, informs)
            dof = np.full(P, np.inf)
            f = mixture_half_width(weight, mean, cvar, theta) / (Z95 * np.sqrt(np.diag(cov)))
            trial_sd = mixture_half_width(weight[:, None, :], 0.0, var[None] + grid[:, None, :] ** 2,
                                          np.zeros(var.shape)) / Z95
        elif np.any(tau2 > 0) or not keep.all() or not informs.all():
            # trials differ beyond their own noise: each trial's estimate is the geometry plus its own
            # random shift, so they are combined with the weights (C_k + Omega)^{-1} (a trial with a
            # tiny within-trial variance no longer decides alone)
            theta, cov, dof = random_effects(theta_k, cov_k, tau2, informs)
        else:
            fit = stacked()
            theta, cov, dof = fit.theta - self.bias_, self.cov_within_, np.full(P, np.inf)
        if not prior:
            f = t_factor(dof)
        self.dof_ = dof
        if fit is None:  # the combination's part of the errors every trial shares, added once
            shared, self.shared_recurring_ = shared_covariance(
                random_effects_weights(cov_k, tau2, informs), cov, self.trial_shared_[keep], tau2, informs)
        else:  # the stacked fit's cov_within_ holds it already
            shared, self.shared_recurring_ = np.zeros((P, P)), np.ones(P)
        self.cov_unscaled_ = cov + shared
        self.cov_shared_ = shared if fit is None else self._shared_within
        cov = cov * np.outer(f, f) + shared
        trial_var = var + tau2
        if prior:
            self.trial_dof_ = np.full(var.shape, np.inf)
            self.trial_sd_ = trial_sd
        else:
            self.trial_dof_ = satterthwaite_dof(trial_var, np.broadcast_to(tau2, var.shape), np.maximum(df, 1))
            self.trial_sd_ = np.sqrt(np.clip(trial_var, 0.0, None)) * t_factor(self.trial_dof_)
        self._checks(theta_k, cov_k, informs, theta, q, df, dof, f)
        self.motion_trend_ = self._motion_trends(theta_k, var[keep], informs, keep)
        self.theta_data_, self.cov_data_ = theta, cov
        self.status_ = dict(zip(self.model.parameter_names, joint_status(self.trial_status_[keep]), strict=True))
        return fit

    def _kept(self) -> np.ndarray:
        """(K,) bool: the trials combined.

        A trial whose own fit ended on a prior bound has no Gaussian approximation to combine (e.g. a
        standing trial and functional joint centres): it is set aside from the combination of the
        trials' own estimates, unless no trial is left.
        """
        pinned = np.array([bool(np.any(getattr(getattr(e, "fit_", None), "pinned", False))) for e in self.trials_])
        # a fit that did not converge has no interval to give (unless this estimator keeps such fits)
        stuck = np.array([self.on_nonconvergence == "error" and not bool(getattr(e.fit_info_, "converged", True))
                          for e in self.trials_])
        if stuck.all():
            raise ConvergenceError("no trial's joint fit converged, so no interval can be given",
                                   "raise n_iter, or check the model's starting geometry and the data")
        out = pinned | stuck
        keep = ~out if (out.any() and not out.all()) else ~stuck
        self.trials_set_aside_ = [lab for lab, k in zip(self.trial_labels_, keep, strict=True) if not k]
        self.trials_not_converged_ = [lab for lab, k in zip(self.trial_labels_, stuck, strict=True) if k]
        self._keep = keep
        return keep

    def _checks(self, theta_k, cov_k, informs, theta, q, df, dof, f) -> None:
        """The consistency test and the heterogeneity table of the trials combined.

        The test sees each trial only where it contributes: a parameter it leaves unidentified is
        left out of its deviation and covariance.
        """
        mask2 = informs[:, :, None] & informs[:, None, :]
        self.consistency_ = consistency_test(np.where(informs, theta_k, theta), np.where(mask2, cov_k, 0.0), theta)
        with np.errstate(divide="ignore", invalid="ignore"):
            i2 = np.where(q > 0, np.maximum(0.0, (q - df) / q), 0.0)
        self.heterogeneity_ = {n: {"q": float(q[k]), "dof": int(df[k]), "i2": float(i2[k]),
                                   "trials": int(informs[:, k].sum()),
                                   "tau": float(np.sqrt(self.tau2_[k])), "t_dof": float(dof[k]),
                                   "t_factor": float(f[k])}
                               for k, n in enumerate(self.model.parameter_names)}

    def _motion_trends(self, theta_k, var_k, informs, keep) -> dict:
        """Each parameter's per-trial estimates against the range of its joint's motion in each trial
        (:func:`~skelid.estimators.checks.trial_motion.motion_trend`, the trials that inform it, each with
        its own variance): ``{parameter: {"joint", "slope", ..., "p_value"}}``, empty with too few trials."""
        model = self.model
        ests = [e for e, k in zip(self.trials_, keep, strict=True) if k]
        joints = {s.joint.name for s in model.segments if s.parent is not None}
        tested = [p for p, par in enumerate(model.parameters)  # a body's scale or a marker's place has no one joint
                  if par.kind not in ("marker_position", "marker_offset", "scale") and par.target in joints]
        if len(ests) < MIN_TRIALS or not tested:
            return {}
        ranges = [joint_ranges(model, e.pose_, e.frames_used_, e.theta_) for e in ests]
        out = {}
        for p in tested:
            par = model.parameters[p]
            x = np.array([max(r.get(par.target) or [np.nan]) for r in ranges])
            use = informs[:, p] & np.isfinite(x)
            trend = motion_trend(theta_k[use, p], var_k[use, p], x[use])
            if trend is not None:
                out[par.name] = {"joint": par.target, "trials": int(use.sum()), **trend}
        return out

    def _trend_warnings(self) -> list[Warning]:
        """A parameter whose trials' estimates change with the range of its joint's motion (Bonferroni over the
        parameters tested at :data:`MISFIT_ALPHA`), by at least :data:`MISFIT_EFFECT` of its sd over the trials."""
        trends = getattr(self, "motion_trend_", None) or {}
        sd = dict(zip(self.model.parameter_names, np.sqrt(np.clip(np.diag(self.cov_), 0.0, None)), strict=True))
        unit = self.model.units
        new = []
        for n, r in trends.items():
            if r["p_value"] >= MISFIT_ALPHA / len(trends) or abs(r["change"]) < MISFIT_EFFECT * sd[n]:
                continue
            new.append(Warning("trend-with-motion", (
                f"{n}: the trials' own estimates change with the range through which each trial moves joint "
                f"{r['joint']} ({r['slope']:+.3g} {unit} per degree, t = {r['t']:.1f} on {r['dof']} degrees of "
                f"freedom, p = {r['p_value']:.2g}; {r['change']:+.3g} {unit} from the trial that moves it least to "
                f"the one that moves it most): the model does not follow that joint (a centre that rolls or "
                "slides with it, skin that slides with it), so the estimate depends on the activity recorded"), (n,)))
        return new

    def _tau_prior_scale(self, ests) -> np.ndarray:
        """Half-normal scale of each parameter's between-trial sd: what the prior artefact does to one trial.

        ``s_p = a sqrt(mean_k Sigma_art,k[p, p])`` with ``Sigma_art,k`` the covariance that an artefact
        of root-mean-square 1 adds to trial ``k``'s estimate
        (:func:`~skelid.estimators.checks.artefact.artefact_covariance`)
        and ``a`` the ``prior_artefact_rms`` setting (default :data:`PRIOR_ARTEFACT_RMS_MM` in the model's units).
        """
        if self.between_trial != "prior" or len(ests) < 2:
            return np.zeros(self.model.n_params)
        a = self.prior_artefact_rms
        if a is None:
            a = PRIOR_ARTEFACT_RMS_MM / _MM_PER_UNIT[self.model.units]
        unit = np.array([np.diag(artefact_covariance(self.model, e.y_, e.fit_info_.theta, e.fit_info_.pose,
                                                     e.fit_info_.penalty, 1.0, e.frames_used_)) for e in ests])
        return float(a) * np.sqrt(np.clip(unit, 0.0, None).mean(axis=0))

    def _publish(self, fit, ests) -> None:
        model = self.model
        theta, cov = _combine_normal_priors(model, self.theta_data_, self.cov_data_)
        self.fit_info_ = fit
        self.converged_ = bool(fit.converged) if fit is not None else all(
            e.fit_info_.converged for e, k in zip(ests, self._keep, strict=True) if k)
        self.n_iter_ = int(fit.n_iter) if fit is not None else 0
        self.theta_, self.cov_ = theta, cov
        self.posterior_ = GaussianPosterior(model.parameter_names, theta, cov)
        self.frames_used_ = np.concatenate([e.frames_used_ for e in ests])
        n_used = np.array([e.frames_used_.sum() for e in ests], float)
        sig = np.array([e.sigma_ for e in ests])
        self.sigma_ = float(np.sqrt(np.sum(n_used * sig**2) / max(n_used.sum(), 1.0)))
        self.sigma_ci_ = (None if self.sigma is not None else
                          pooled_noise_interval(sig, [e.fit_.noise.dof for e in ests], n_used / max(n_used.sum(), 1.0)))
        # the bound of all the trials' frames together: their efficient informations add up
        self.crlb_sd_ = crlb_sd(np.sum([e.crlb_information_ for e in ests], axis=0))
        # the joint fit's poses, or (random-effects combination) each trial's own
        self.pose_ = fit.pose if fit is not None else np.concatenate([e.pose_ for e in ests])
        lens, grad = joint_distances(model, theta)
        sd_len = np.sqrt(np.clip(np.einsum("kp,pq,kq->k", grad, cov, grad), 0.0, None))
        self.lengths_ = {name: {"value": float(v), "sd": float(e), "ci95": [float(v - Z95 * e), float(v + Z95 * e)]}
                         for (name, _), v, e in zip(model.derived_lengths, lens, sd_len, strict=True)}
        found = []
        for label, e in zip(self.trial_labels_, ests, strict=True):
            found += [Warning(w.code, f"{label}: {w.message}", w.parameters) for w in e.warnings_]
        self.warnings_ = tuple(found) + emit(self._joint_warnings(fit))

    def _joint_warnings(self, fit) -> list[Warning]:
        """The joint fit's own warnings: not converged, trials set aside, trials that disagree."""
        new = []
        if fit is not None and not fit.converged:
            new.append(Warning("not-converged", "the joint fit of all trials stopped before converging; "
                               "the estimate may be off"))
        bound = [t for t in self.trials_set_aside_ if t not in self.trials_not_converged_]
        if bound:
            new.append(Warning("trials-set-aside", f"{', '.join(bound)}: the fit ended on a "
                               "bound of the prior (the trial cannot locate these parameters), so the joint "
                               "estimate combines the other trials only"))
        if self.trials_not_converged_:
            new.append(Warning("trials-set-aside", f"{', '.join(self.trials_not_converged_)}: the trial's own "
                               "fit did not converge (no interval of its own), so the joint estimate combines the "
                               "other trials only"))
        new += self._trend_warnings()
        c = self.consistency_
        if c["tested"] and c["p_value"] < 0.01:
            how = ("was added to the interval" if self.between_trial != "none" else "is not in the interval")
            new.append(Warning("trials-disagree", f"the trials disagree about the geometry beyond their own "
                               f"intervals (chi-square {c['statistic']:.1f} on {c['dof']} degrees of freedom, "
                               f"p = {c['p_value']:.2g}): the between-trial spread {how}",
                               tuple(n for n, h in self.heterogeneity_.items() if h["tau"] > 0)))
        return new

    def trial_table(self) -> list[dict]:
        """Each trial's own estimate, its sd, and its sd with the between-trial variance (``t``-scaled)."""
        check_fitted(self)
        rows = []
        for k, e in enumerate(self.trials_):
            sd = np.sqrt(np.clip(np.diag(self.trial_cov_[k]), 0.0, None))
            params = {}
            sh = np.sqrt(np.clip(np.diag(self.trial_shared_[k]), 0.0, None)) * self.shared_recurring_
            for p, n in enumerate(self.model.parameter_names):
                m, s = float(self.trial_theta_[k, p]), float(self.trial_sd_[k, p])
                h = float(np.hypot(s, sh[p]))  # for the truth: the shared part as well
                params[n] = {"mean": m, "sd": float(sd[p]), "sd_with_between_trial": s, "sd_shared": float(sh[p]),
                             "status": str(self.trial_status_[k, p]),
                             "contributes": bool(self.trial_informs_[k, p]),
                             "interval": [m - Z95 * h, m + Z95 * h],
                             "t_dof": float(self.trial_dof_[k, p]) if np.isfinite(self.trial_dof_[k, p]) else None}
            ms = e.marker_sigma_
            rows.append({
                "trial": self.trial_labels_[k],
                "frames": int(len(e.frames_used_)),
                "frames_used": int(e.frames_used_.sum()),
                "sigma": float(e.sigma_),
                "per_marker_sigma": ({} if ms is None else
                                     {n: float(v) for n, v in zip(self.model.marker_names, ms, strict=True)
                                      if np.isfinite(v)}),
                "parameters": params,
                "lengths": {n: dict(v) for n, v in e.lengths_.items()},
                "warnings": [w.message for w in e.warnings_],
            })
        return rows

    def result(self) -> FitResult:
        """The typed result: the joint estimate; trials, consistency and heterogeneity in ``diagnostics``."""
        from skelid.estimators.base import build_result

        check_fitted(self)
        model = self.model
        sd_within = np.sqrt(np.clip(np.diag(self.cov_within_), 0.0, None))
        sd_shared = np.sqrt(np.clip(np.diag(self.cov_shared_), 0.0, None))
        extra = {n: {"bias_removed": float(self.bias_[k]), "sd_within_trials": float(sd_within[k]),
                     "sd_between_trials": float(np.sqrt(self.tau2_[k])),
                     "sd_shared_by_trials": float(sd_shared[k]),
                     "shared_recurring": float(self.shared_recurring_[k]),
                     "t_dof": float(self.dof_[k]) if np.isfinite(self.dof_[k]) else None}
                 for k, n in enumerate(model.parameter_names)}
        per = {}
        ms = [e.marker_sigma_ for e in self.trials_]
        if all(m is not None for m in ms):
            n_used = np.array([e.frames_used_.sum() for e in self.trials_], float)[:, None]
            s2 = np.array(ms) ** 2
            ok = np.isfinite(s2)
            with np.errstate(invalid="ignore", divide="ignore"):
                rms = np.sqrt(np.where(ok, n_used * s2, 0.0).sum(0) / np.where(ok, n_used, 0.0).sum(0))
            per = {n: float(v) for n, v in zip(model.marker_names, rms, strict=True) if np.isfinite(v)}
        noise = NoiseEstimate(self.sigma_, None if self.sigma_ci_ is None else tuple(map(float, self.sigma_ci_)),
                              fixed=self.sigma is not None, per_marker=per,
                              extra={"per_trial": [float(e.sigma_) for e in self.trials_]})
        skipped: dict[str, int] = {}
        for e in self.trials_:
            for k, v in e.frames_skipped_.items():
                skipped[k] = skipped.get(k, 0) + int(v)
        diagnostics = {
            "trials": self.trial_table(), "consistency": dict(self.consistency_),
            "heterogeneity": self.heterogeneity_,
            "between_trial": {"method": self.between_trial, "n_trials": len(self.trials_),
                              "interval": ("95 % of the posterior with a half-normal prior on each between-trial sd"
                                           if self.between_trial == "prior" else
                                           "t quantile with Satterthwaite degrees of freedom"),
                              "prior_scale": {n: float(v) for n, v in zip(model.parameter_names,
                                                                          self.tau_prior_scale_, strict=True)}},
            "converged": self.converged_, "stacked_fit_iterations": self.n_iter_,
            "motion_trend": getattr(self, "motion_trend_", {})}
        return build_result(self, self.posterior_, crlb_sd=self.crlb_sd_, extra=extra, noise=noise, skipped=skipped,
                            diagnostics=diagnostics, derived=self.lengths_, status=self.status_,
                            arrays={"pose": self.pose_, "trial_theta": self.trial_theta_,
                                    "trial_cov": self.trial_cov_, "trial_sd": self.trial_sd_,
                                    "trial_frames": np.array([len(e.frames_used_) for e in self.trials_])})
