"""Several trials of one body: one geometry, poses, motion model and noise per trial.

Model: trial ``k = 1..K`` has its own frames, poses ``q_{kt}``, motion-model
cutoffs (at its own rate) and marker noise levels ``sigma_{km}``, and every
trial sees the same geometry ``theta``:

.. math:: y_{ktm} = x_m(q_{kt}, \\theta) + \\varepsilon_{ktm},
          \\qquad \\varepsilon_{ktm} \\sim N(0, \\sigma_{km}^2 I).

**Joint estimate.** The trials are stacked along the frame axis and fitted at
once (:func:`~skelid.estimators.joint.joint_fit` with ``blocks``: the
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

**Between-trial excess variance.** Skin moves differently in different
movements; the part of it that mimics a geometry change shifts each trial's
estimate by a random amount ``u_k ~ N(0, Omega)``. ``Omega = diag(tau_p^2)`` is
estimated per parameter by DerSimonian and Laird's method of moments: with
``w_k = 1/C_{k,pp}``, ``bar theta = sum w_k theta_k / sum w_k`` and
``Q = sum_k w_k (theta_k - bar theta)^2``,

.. math:: \\tau^2 = \\max\\Big(0, \\frac{Q - (K - 1)}{\\sum w_k - \\sum w_k^2 / \\sum w_k}\\Big),

and then replaces the stacked fit by the random-effects combination
``theta = (sum_k W_k)^{-1} sum_k W_k theta_k`` with ``W_k = (C_k + Omega)^{-1}``
and covariance ``(sum_k W_k)^{-1}``: a trial with a tiny within-trial variance
(a static trial, whose lengths follow the markers' nominal placement) no longer
decides the answer alone. A trial's own interval that includes it uses
``C_k + Omega``.

Example
-------
>>> import numpy as np
>>> from skelid.estimators.multitrial import dersimonian_laird
>>> tau2, q, df = dersimonian_laird(np.array([[0.0], [1.0], [3.0]]), np.ones((3, 1)))
>>> round(float(tau2[0]), 6), round(float(q[0]), 6), int(df)
(1.333333, 4.666667, 2)
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.stats import chi2

from skelid.data import MarkerData
from skelid.errors import DataError, SkelidError
from skelid.estimators.joint import joint_fit
from skelid.estimators.marker import MarkerEstimator, _combine_normal_priors
from skelid.estimators.posterior import GaussianPosterior
from skelid.model.description import Model
from skelid.model.kinematics import joint_distances

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


def consistency_test(estimates, covs, joint) -> dict:
    """Chi-square test of the per-trial estimates against the joint one.

    Parameters
    ----------
    estimates : (K, P) float
    covs : (K, P, P) float
        Each trial's covariance.
    joint : (P,) float

    Returns
    -------
    dict with ``statistic``, ``dof`` (``(K - 1) P``) and ``p_value``.
    """
    d = np.asarray(estimates, float) - np.asarray(joint, float)
    stat = float(sum(dk @ np.linalg.pinv(ck, hermitian=True) @ dk
                     for dk, ck in zip(d, np.asarray(covs, float), strict=True)))
    dof = (d.shape[0] - 1) * d.shape[1]
    return {"statistic": stat, "dof": int(dof), "p_value": float(chi2.sf(stat, dof)) if dof else 1.0}


def pairwise_z(estimates, sds) -> np.ndarray:
    """``z`` of every pair of trials for each quantity: ``(K (K-1) / 2, P)``.

    ``z = (a - b) / sqrt(sd_a^2 + sd_b^2)``.
    """
    x = np.asarray(estimates, float)
    s = np.asarray(sds, float)
    i, j = np.triu_indices(x.shape[0], 1)
    return (x[i] - x[j]) / np.sqrt(s[i] ** 2 + s[j] ** 2)


class MultiTrialEstimator:
    """One geometry from several trials of one body.

    Parameters
    ----------
    model : Model
    between_trial : {'dl', 'none'}
        Estimate the between-trial excess variance per parameter
        (DerSimonian-Laird) and add it to the interval, or not.
    **settings
        Passed to :class:`~skelid.estimators.marker.MarkerEstimator` for each
        trial (``sigma``, ``cutoff``, ``noise``, ``marker_groups``,
        ``artefact_rms``, ``outlier_threshold``, ``rng`` ...).

    Attributes
    ----------
    theta_ : (P,) float
        Joint estimate (bias removed, normal priors combined).
    cov_ : (P, P) float
        Its covariance, between-trial variance included.
    cov_within_ : (P, P) float
        Without the between-trial variance.
    posterior_ : GaussianPosterior
    trials_ : list of MarkerEstimator
        Each trial's own fit.
    trial_theta_ : (K, P) float
        Each trial's own estimate (bias removed, before priors).
    trial_cov_ : (K, P, P) float
        Their covariances.
    tau2_ : (P,) float
        Between-trial variance of each parameter.
    consistency_ : dict
        :func:`consistency_test` of the trials against the joint estimate.
    heterogeneity_ : dict
        Per parameter: Cochran's ``Q``, ``I^2`` and ``tau``.
    lengths_ : dict
        Derived lengths of the joint estimate.
    fit_info_ : JointFit
        The stacked fit.
    warnings_ : list of str
    """

    name = "marker-multi"

    def __init__(self, model: Model, between_trial: str = "dl", **settings):
        self.model = model
        self.between_trial = between_trial
        self.settings = settings

    def fit(self, trials: Sequence[MarkerData]) -> MultiTrialEstimator:
        """Fit every trial alone, then all of them at once with one geometry."""
        if self.between_trial not in ("dl", "none"):
            raise ValueError("between_trial must be 'dl' or 'none'")
        if isinstance(trials, MarkerData):
            trials = [trials]
        trials = list(trials)
        if not trials:
            raise DataError("no trials to fit", "give at least one marker file")
        model = self.model
        P = model.n_params
        self.trials_ = []
        for k, data in enumerate(trials):
            est = MarkerEstimator(model, **self.settings)
            try:
                est.fit(data)
            except SkelidError as exc:
                name = getattr(data, "source", None) or f"trial {k + 1}"
                raise type(exc)(f"{name}: {exc.problem}", exc.fix) from None
            self.trials_.append(est)
        ests = self.trials_
        self.trial_theta_ = np.array([e.theta_profile_ - e.bias_ for e in ests])
        self.trial_cov_ = np.array([e.cov_data_ for e in ests])
        S = np.array([np.linalg.inv(e.cov_plain_) for e in ests])  # (K, P, P) information
        A = S.sum(axis=0)
        A_inv = np.linalg.inv(A)
        # stacked fit: every trial's frames, poses, motion model and weights, one geometry
        lengths = [len(e.pose_) for e in ests]
        edges = np.concatenate([[0], np.cumsum(lengths)])
        blocks = [(int(a), int(b), trials[k].rate if isinstance(trials[k], MarkerData) else e.rate,
                   e.cutoff_) for k, (a, b, e) in enumerate(zip(edges[:-1], edges[1:], ests, strict=True))]
        M = len(model.marker_names)
        weights = np.concatenate([
            np.broadcast_to((np.ones(M) if e.marker_weights_ is None else e.marker_weights_) / e.sigma_**2,
                            (n, M)) for e, n in zip(ests, lengths, strict=True)])
        y = np.concatenate([e.y_ for e in ests])
        pose = np.concatenate([e.pose_ for e in ests])
        used = np.concatenate([e.frames_used_ for e in ests])
        theta0 = A_inv @ np.einsum("kpq,kq->p", S, np.array([e.theta_profile_ for e in ests]))
        bounds = (np.array([p.prior.lower for p in model.parameters]),
                  np.array([p.prior.upper for p in model.parameters]))
        lo, hi = bounds
        theta0 = np.clip(theta0, lo, hi)
        fit = joint_fit(model, y, theta0, pose, n_iter=self.settings.get("n_iter", 100), bounds=bounds,
                        frames=used, blocks=blocks, weights=weights)
        self.fit_info_ = fit
        self.bias_ = A_inv @ np.einsum("kpq,kq->p", S, np.array([e.bias_ for e in ests]))
        theta = fit.theta - self.bias_
        sandwich = np.einsum("kpq,kqr,krs->ps", S, self.trial_cov_, S)
        self.cov_within_ = A_inv @ sandwich @ A_inv
        var = np.einsum("kpp->kp", self.trial_cov_)
        if self.between_trial == "dl":
            tau2, q, df = dersimonian_laird(self.trial_theta_, var)
        else:
            tau2, q, df = np.zeros(P), dersimonian_laird(self.trial_theta_, var)[1], len(ests) - 1
        self.tau2_ = tau2
        Omega = np.diag(tau2)
        if np.any(tau2 > 0):
            # trials differ beyond their own noise: each trial's estimate is the geometry plus its own
            # random shift, so they are combined with the weights (C_k + Omega)^{-1} (a trial with a
            # tiny within-trial variance no longer decides alone) and the variance that goes with them
            W = np.linalg.inv(self.trial_cov_ + Omega)
            cov = np.linalg.inv(W.sum(axis=0))
            theta = cov @ np.einsum("kpq,kq->p", W, self.trial_theta_)
        else:
            cov = self.cov_within_
        self.consistency_ = consistency_test(self.trial_theta_, self.trial_cov_, theta)
        with np.errstate(divide="ignore", invalid="ignore"):
            i2 = np.where(q > 0, np.maximum(0.0, (q - df) / q), 0.0)
        self.heterogeneity_ = {n: {"q": float(q[k]), "dof": int(df), "i2": float(i2[k]),
                                   "tau": float(np.sqrt(tau2[k]))}
                               for k, n in enumerate(model.parameter_names)}
        self.theta_data_ = theta
        self.cov_data_ = cov
        theta, cov = _combine_normal_priors(model, theta, cov)
        self.theta_, self.cov_ = theta, cov
        self.posterior_ = GaussianPosterior(model.parameter_names, theta, cov)
        self.frames_used_ = used
        self.pose_ = fit.pose
        lens, grad = joint_distances(model, theta)
        sd_len = np.sqrt(np.clip(np.einsum("kp,pq,kq->k", grad, cov, grad), 0.0, None))
        self.lengths_ = {name: {"value": float(v), "sd": float(e), "ci95": [float(v - Z95 * e), float(v + Z95 * e)]}
                         for (name, _), v, e in zip(model.derived_lengths, lens, sd_len, strict=True)}
        self.warnings_ = list(dict.fromkeys(w.message for e in ests for w in e.warnings_))
        if not fit.converged:
            self.warnings_.append("the joint fit of all trials stopped before converging; the estimate may be off")
        if self.consistency_["p_value"] < 0.01:
            self.warnings_.append(
                f"the trials disagree about the geometry beyond their own intervals (chi-square "
                f"{self.consistency_['statistic']:.1f} on {self.consistency_['dof']} degrees of freedom, "
                f"p = {self.consistency_['p_value']:.2g}): the between-trial spread "
                + ("was added to the interval" if self.between_trial == "dl" else "is not in the interval"))
        return self

    def trial_table(self) -> list[dict]:
        """Each trial's own estimate, sd, and sd with the between-trial variance."""
        rows = []
        sd_tau = np.sqrt(self.tau2_)
        for k, e in enumerate(self.trials_):
            sd = np.sqrt(np.clip(np.diag(self.trial_cov_[k]), 0.0, None))
            rows.append({
                "frames_used": int(e.frames_used_.sum()),
                "sigma": e.sigma_,
                "parameters": {n: {"mean": float(self.trial_theta_[k, p]), "sd": float(sd[p]),
                                   "sd_with_between_trial": float(np.hypot(sd[p], sd_tau[p]))}
                               for p, n in enumerate(self.model.parameter_names)},
                "lengths": {n: dict(v) for n, v in e.lengths_.items()},
                "warnings": [w.message for w in e.warnings_],
            })
        return rows

    def result(self) -> dict:
        """JSON-ready summary: the joint estimate, then the trials and the consistency test."""
        out = {"frames_used": int(self.frames_used_.sum()),
               "frames_dropped": int((~self.frames_used_).sum())}
        summ = self.posterior_.summary()
        sd_within = np.sqrt(np.clip(np.diag(self.cov_within_), 0.0, None))
        for k, n in enumerate(self.model.parameter_names):
            summ[n]["bias_removed"] = float(self.bias_[k])
            summ[n]["sd_within_trials"] = float(sd_within[k])
            summ[n]["sd_between_trials"] = float(np.sqrt(self.tau2_[k]))
        out.update(summ)
        out["sigma"] = {"per_trial": [e.sigma_ for e in self.trials_]}
        if self.lengths_:
            out["lengths"] = self.lengths_
        out["trials"] = self.trial_table()
        out["consistency"] = dict(self.consistency_)
        out["heterogeneity"] = self.heterogeneity_
        out["warnings"] = list(self.warnings_)
        return out
