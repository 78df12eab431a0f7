"""Markers that sit differently on the body in each trial: a random effect on each trial's offsets.

A joint fit of several trials gives every marker one offset on its body. Skin
slides with the pose, and its mean over a trial follows the trial's mean pose
(a walk's knees flexed 20 degrees more than in the static trial): each trial
then sees its markers elsewhere, and one offset per marker for every trial
pushes the difference into the scales, which the residuals of one white
noise level do not show.

Model. Trial ``k``'s offsets are ``delta + u_k``, ``u_k ~ N(0, tau^2)`` for
every offset coordinate, independent between trials. Linearised at the joint
fit, trial ``k`` contributes ``v_k = I_k (theta + U_k u_k) + e_k`` to the
normal equations (``I_k`` its information, ``U_k`` its columns for the offsets,
``e_k ~ N(0, I_k)``), and its score at the estimate is
``g_k = v_k - I_k H sum_j v_j`` (``H``: the joint posterior covariance). So

.. math:: \\operatorname{Cov}(g_k, g_l) = \\delta_{kl} V_k - V_k H I_l - I_k H V_l
          + I_k H \\Big(\\sum_j V_j\\Big) H I_l, \\qquad V_k = I_k + \\tau^2 U_k U_k^\\top .

Size. ``Q = sum_k g_k^T W g_k`` (``W``: ``H`` on the offsets, zero elsewhere) has mean
``E_0 + tau^2 E_1`` (both from the formula
above, with ``V_k = I_k`` and ``V_k = U_k U_k^T``), so ``tau^2 = max(0, (Q - E_0) / E_1)``
(a moment estimate, added wherever it is positive, as a random-effects spread
is; gated by the test below, spreads the test misses left the intervals short:
coverage 0.91 against 0.94 on a linear model with ``tau`` a tenth of the noise).
The spread is called present when ``Q`` exceeds what ``tau = 0`` explains at
:data:`LEVEL` (``Q`` as a scaled chi-square with the null's mean and variance,
``Var Q = 2 sum_kl tr(W C_kl W C_lk)``; 1.4 % of fits at 1 % on that model):
that is what the warnings say. One trial has no such test: its offsets take
up its own placement.

Effect. The estimate moves by ``H sum_k I_k U_k u_k``, so the effect adds
``tau^2 H (sum_k U_k U_k^T) H`` to the covariance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: level of the test of one placement for every trial below which the trials' placement spread is added
LEVEL = 0.01


@dataclass(frozen=True)
class TrialPlacement:
    """How far the trials' marker placements differ, and the covariance that adds to a joint fit."""

    present: bool  # the test of tau = 0 rejected at LEVEL (the covariance is added wherever tau > 0)
    p_value: float
    tau: float  # sd of an offset coordinate between trials (model units)
    statistic: float  # Q
    null_mean: float  # E_0
    cov: np.ndarray  # (P, P) the covariance it adds (zero where not present)


def trial_placement(info_trials, score_trials, hinv, offsets) -> TrialPlacement:
    """Test one marker placement for every trial of a joint fit; the covariance the spread adds.

    Parameters
    ----------
    info_trials : sequence of (P, P) float
        Each trial's information ``I_k`` in the joint fit (poses profiled out).
    score_trials : sequence of (P,) float
        Each trial's score ``g_k`` at the joint estimate.
    hinv : (P, P) float
        The joint posterior covariance ``(sum_k I_k + Lambda)^-1``.
    offsets : (P,) bool
        The marker-offset parameters.

    Returns
    -------
    TrialPlacement
    """
    from scipy.stats import chi2

    H = np.asarray(hinv, float)
    P = H.shape[0]
    offsets = np.asarray(offsets, bool)
    K = len(info_trials)
    zero = np.zeros((P, P))
    if K < 2 or not offsets.any():
        return TrialPlacement(False, 1.0, 0.0, 0.0, 0.0, zero)
    info = [np.asarray(I, float) for I in info_trials]
    g = [np.asarray(s, float) for s in score_trials]
    U = [I[:, offsets] for I in info]
    X1 = [u @ u.T for u in U]
    B = [I @ H for I in info]  # I_k H
    # the offsets' part of the scores, weighted by their posterior covariance: a shift of one trial's markers
    # shows there; a misfit of the scales or the joints (a walk's 8 mm on subject01) mostly elsewhere
    Wm = np.where(np.outer(offsets, offsets), H, 0.0)
    Q = float(sum(gk @ Wm @ gk for gk in g))

    def mean(V):  # E[Q] for the trials' contributions of covariance V_k
        total = sum(V)
        return float(sum(np.sum(Wm * (V[k] - B[k] @ V[k] - V[k] @ B[k].T + B[k] @ total @ B[k].T))
                         for k in range(K)))
    e0, e1 = mean(info), mean(X1)
    # the null covariance of the scores, block by block (V_k = I_k): C_kl = d_kl I_k - 2 I_k H I_l + I_k H S H I_l
    SH = sum(info) @ H

    def wc(k, l):  # W C_kl
        return Wm @ ((info[k] if k == l else 0.0) - 2.0 * B[k] @ info[l] + B[k] @ SH @ info[l])
    # pair by pair, so that memory stays at a few (P, P) matrices whatever the number of trials
    var = 0.0
    for k in range(K):
        for l in range(k, K):
            a, b = wc(k, l), (wc(l, k) if l != k else None)
            var += float(np.sum(a * a.T)) if b is None else 2.0 * float(np.sum(a * b.T))
    var *= 2.0
    if not (e0 > 0 and var > 0 and e1 > 0 and np.isfinite([Q, e0, e1, var]).all()):
        return TrialPlacement(False, 1.0, 0.0, Q, e0, zero)
    a, nu = var / (2.0 * e0), 2.0 * e0**2 / var
    p_value = float(chi2.sf(Q / a, nu))
    tau2 = max(0.0, (Q - e0) / e1)
    cov = tau2 * H @ sum(X1) @ H
    return TrialPlacement(bool(p_value < LEVEL and tau2 > 0.0), p_value, float(np.sqrt(tau2)), Q, e0,
                          0.5 * (cov + cov.T))
