"""Averaging the fits of several models of one body: stacking weights and the mixture they give.

When models of the same body (another joint type, another nominal geometry) place a joint centre
tens of millimetres apart, an interval from any one of them leaves out the choice of model. The
models' average keeps it: each model's posterior weighted, and the interval the mixture's.

The weights are those of *stacking* (Yao, Vehtari, Simpson and Gelman, Bayesian Analysis 2018):
the weights ``w`` on the simplex that maximise the log score of the averaged predictive density
over held-out units,

    max_w  sum_i log sum_k w_k p_k(y_i),

with ``p_k(y_i)`` model ``k``'s predictive density of unit ``i``. Unlike weights from the
evidence, which go to one model whenever thousands of frames are fitted, even where every model
is wrong in its own way, stacking gives a model the share of the data it predicts best; where one
model predicts every unit better it takes all the weight. The maximum is found by the
fixed-point iteration of a mixture's weights, ``w_k <- w_k mean_i p_ik / sum_j w_j p_ij``, which
raises the (concave) objective at every step.

The average of quantity ``q`` is the mixture ``sum_k w_k N(mu_k, s_k^2)`` of the models' normal
posteriors (in log space for a ratio such as a scale factor): its mean, its sd
``sqrt(sum_k w_k (s_k^2 + (mu_k - mean)^2))``, and its central interval from the mixture's own
quantiles.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import brentq
from scipy.special import ndtr, ndtri

#: the fixed-point iteration stops when no weight moves by more than this in a step
WEIGHT_TOL = 1e-10
MAX_ITER = 100_000


def stacking_weights(log_density) -> np.ndarray:
    """Stacking weights of ``K`` models from their log predictive densities of ``n`` held-out units.

    Parameters
    ----------
    log_density : (n, K) float
        ``log p_k(y_i)``; a non-finite entry is a unit the model cannot predict (density 0). Every
        model needs at least one finite entry, every unit one finite entry.

    Returns
    -------
    (K,) float
        Weights on the simplex maximising ``sum_i log sum_k w_k p_k(y_i)``.

    Raises
    ------
    ValueError
        No units, no models, or a unit or model with no finite log density.

    >>> stacking_weights([[0.0, -50.0], [0.0, -40.0], [-30.0, 0.0]]).round(3)  # wins two units of three
    array([0.667, 0.333])
    >>> stacking_weights([[0.0, -1.0]] * 4).round(6)  # one model predicts every unit better
    array([1., 0.])
    """
    lp = np.asarray(log_density, dtype=float)
    if lp.ndim != 2 or not lp.size:
        raise ValueError(f"stacking needs an (units, models) array of log densities, got shape {lp.shape}")
    finite = np.isfinite(lp)
    if not finite.any(axis=1).all() or not finite.any(axis=0).all():
        raise ValueError("stacking needs every unit predicted by some model and every model predicting some unit")
    lp = np.where(finite, lp, -np.inf)
    p = np.exp(lp - lp.max(axis=1, keepdims=True))  # each unit's densities relative to its best model
    K = p.shape[1]
    w = np.full(K, 1.0 / K)
    for _ in range(MAX_ITER):
        new = (p * w / (p @ w)[:, None]).mean(axis=0)  # the mean responsibility of each model for the units
        settled = np.max(np.abs(new - w)) <= WEIGHT_TOL
        w = new
        if settled:
            break
    return w / w.sum()


def mixture_summary(means, sds, weights, level: float = 0.95, log: bool = False) -> dict:
    """Mean, sd and central interval of the weighted mixture of normal posteriors.

    Parameters
    ----------
    means, sds : (K,) float
        Each model's posterior mean and sd (of the logarithm where ``log``).
    weights : (K,) float
        Non-negative, summing to 1 (models of weight 0 are left out).
    level : float
        The interval's probability.
    log : bool
        The normals are of the quantity's logarithm (a ratio): the value returned is the
        exponential of the mixture's mean of the logarithm, the interval the exponentials of its
        quantiles and the sd that of the quantity by the delta method.

    Returns
    -------
    dict
        ``value``, ``sd``, ``interval`` (a list of two floats).

    >>> r = mixture_summary([0.0, 0.0], [1.0, 1.0], [0.5, 0.5])
    >>> round(r["sd"], 6), [round(x, 4) for x in r["interval"]]
    (1.0, [-1.96, 1.96])
    >>> r = mixture_summary([-3.0, 3.0], [1.0, 1.0], [0.5, 0.5])  # two models far apart
    >>> round(r["sd"] ** 2, 6), round(r["interval"][1], 3)
    (10.0, 4.645)
    """
    mu, s, w = (np.asarray(x, dtype=float) for x in (means, sds, weights))
    keep = w > 0
    mu, s, w = mu[keep], s[keep], w[keep] / w[keep].sum()
    mean = float(w @ mu)
    var = float(w @ (s**2 + (mu - mean) ** 2))
    lo_hi = [_quantile(mu, s, w, q) for q in ((1 - level) / 2, (1 + level) / 2)]
    if log:
        return {"value": float(np.exp(mean)), "sd": float(np.exp(mean) * np.sqrt(var)),
                "interval": [float(np.exp(v)) for v in lo_hi]}
    return {"value": mean, "sd": float(np.sqrt(var)), "interval": lo_hi}


def _quantile(mu, s, w, q: float) -> float:
    """The ``q`` quantile of ``sum_k w_k N(mu_k, s_k^2)`` (a model with ``s_k = 0`` is a point mass)."""
    point = s <= 0
    if point.all():
        order = np.argsort(mu)
        return float(mu[order][np.searchsorted(np.cumsum(w[order]), q)])
    z = abs(float(ndtri(q)))  # every component's cdf is at most min(q, 1-q) at lo, at least max(q, 1-q) at hi
    span = 1e-12 * max(1.0, float(np.max(np.abs(mu))))
    lo, hi = float(np.min(mu - z * s)) - span, float(np.max(mu + z * s)) + span
    safe = np.where(point, 1.0, s)

    def cdf(x):
        return float(w @ np.where(point, (mu <= x).astype(float), ndtr((x - mu) / safe))) - q

    return float(brentq(cdf, lo, hi, xtol=1e-14 * max(1.0, abs(lo), abs(hi)), maxiter=200))
