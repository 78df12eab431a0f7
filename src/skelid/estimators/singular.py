"""Near-singular poses: a measured check of the local bias approximation, and a fallback that holds.

Model: the joint fit estimates the geometry ``theta`` and every pose ``q_t``; its bias
``b(theta, q)`` (second order, :func:`skelid.estimators.joint.smoothed_bias`) is evaluated
at the estimate. The estimated poses carry an error,

.. math:: \\hat q_t = q_t + e_t, \\qquad e_t \\approx N(0, \\Sigma_t),

with ``Sigma_t = sigma^2 C_{q_t q_t}`` the pose block of ``C = N^{-1}`` (``N`` the joint
fit's normal matrix with the motion-model penalty). Where the markers across a joint
nearly line up (a straight or folded chain), the poses are barely identified: ``Sigma_t``
is large, and ``b`` changes fast with ``q``. Then ``b(theta, q_hat)`` is not ``b(theta, q)``:
the pose error scatters ``q_hat`` away from the singular pose, where the bias comes from,
and the correction (or a parametric bootstrap simulated at ``q_hat``) removes only part
of the bias.

**Pose deconvolution.** ``q_tilde`` low-passes each pose coordinate of ``q_hat`` (zero-phase
Butterworth of order 2, forward-backward gain ``1 / (1 + (f / f_c)^4)``) at the cutoff whose
removed variance equals the estimated pose-error variance,
``mean_t (q_hat - q_tilde)^2 = mean_t Sigma_t`` (the discrepancy principle): it takes away
as much scatter as the fit says its poses carry.

**Check.** The information about ``theta`` (every pose free, per frame)
``I(q) = sum_t K_t(q)^T (I - P_t(q)) K_t(q)`` is evaluated at the fitted and at the
deconvolved poses. Away from a singular pose the scatter of ``q_hat`` hardly changes it
(``|I(q_tilde) - I(q_hat)| / I(q_hat)`` of a few per cent on the i.i.d. cells of the accuracy
study); near one it changes by 20-90 %: the fit's precision and its bias depend on where the
poses are within their own error, and no expansion at ``q_hat`` holds. A change beyond
``POSE_SENSITIVE`` (for any parameter) fails the check.

**Self-consistency, recorded but not trusted.** A correction ``b = b(theta_hat, q_hat)`` larger
than ``BIAS_RELIABLE`` sd (:mod:`skelid.estimators.marker`) goes to the bootstrap. It is also
evaluated once more, at the corrected point (the geometry less its bias, the poses freed of
their scatter),

.. math:: \\Delta = b(\\hat\\theta - b, \\tilde q) - b(\\hat\\theta, \\hat q),

and :func:`expansion_consistent` (``|Delta| <= sd / sqrt(B)``) is recorded with the fallback.
It does not keep the expansion: the profile bias of a fit with incidental poses does not
shrink with the number of frames while its sd does, so ``|b| / sd`` grows like ``sqrt(T)``
(case A, sigma 15 mm: about 1 sd at 10^3 frames, 4 sd at 10^4), and what the expansion leaves
grows with it. At 10^4 frames ``Delta`` is 0.07 sd, yet the expansion leaves 0.19 mm (0.7 sd) of
bias and its interval covers 0.90 (100 trials); the bootstrap leaves 0.02 mm and covers every
trial, at twice the CPU (``benchmarks/results/bias_trigger.md``).

**Fallback.** A parametric bootstrap at the deconvolved poses: ``B`` data sets simulated at
``(theta_tilde, q_tilde)`` and refitted. With common random numbers, ``theta_tilde`` is moved
by fixed-point steps of the indirect-inference equation ``E[theta* | theta_tilde] - theta_tilde
= theta_hat - theta_tilde`` (a bias estimated where the truth probably is, not at the
biased estimate). Each refit's shift has its first Gauss-Newton step as a control variate
(exactly mean zero, known covariance: :mod:`skelid.estimators.bootstrap`), so a few refits
suffice. The covariance added to ``sigma^2 S^{-1}`` is the refits' excess spread, their Monte
Carlo error ``Cov(s - l)/B``, and the square of half the disagreement between the two
bias estimates (bootstrap and second order at ``q_tilde``): the bias estimate's own
uncertainty.

Example
-------
>>> import numpy as np
>>> q = np.cumsum(np.random.default_rng(0).normal(size=(400, 2)), axis=0) * 0.01
>>> noisy = q + np.random.default_rng(1).normal(0.0, 0.05, size=q.shape)
>>> smooth = deconvolve_poses(noisy, np.full(q.shape, 0.05**2))
>>> bool(np.mean((smooth - q) ** 2) < np.mean((noisy - q) ** 2))
True
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from skelid.estimators.bootstrap import Draws, as_draws, draws_bias, draws_covariance, draws_mc_covariance
from skelid.estimators.likelihood import efficient_information, frame_terms
from skelid.model.description import Model

#: relative change of the information about a parameter, between the fitted and the deconvolved
#: poses, beyond which the local (second-order) approximation is not trusted
POSE_SENSITIVE = 0.1
#: fixed-point steps of the indirect-inference equation after the first bootstrap (0: the bias is the
#: bootstrap's at the deconvolved poses and ``theta_hat``; on the straight-elbow cell of the accuracy
#: study, sigma 15 mm, one more step moved it by about 0.1 sd, at the cost of as many refits again)
FIXED_POINT_STEPS = 0
_N_CUTOFFS = 96  # log-spaced cutoffs tried between 1e-3 and 0.95 of the Nyquist frequency


class PoseCheck(NamedTuple):
    """The measured test of the local approximation (see the module's docstring)."""

    q_tilde: np.ndarray  # (T, Q) deconvolved poses
    info_change: np.ndarray  # (P,) (I(q_tilde) - I(q_hat)) / I(q_hat), diagonal
    pose_sd: np.ndarray  # (Q,) rms sd of each pose coordinate's estimate over the frames used
    sensitive: bool  # some |info_change| > POSE_SENSITIVE


def deconvolve_poses(q, variance, used=None) -> np.ndarray:
    """Low-pass each pose coordinate so that the variance removed equals its estimation variance.

    Parameters
    ----------
    q : (T, Q) float
        Estimated poses.
    variance : (T, Q) float
        Variance of each estimate (e.g. from :func:`skelid.estimators.joint.smoothed_bias`'s
        ``pose_var``).
    used : (T,) bool, optional
        Frames whose variance and scatter count (default: all).

    Returns
    -------
    q_tilde : (T, Q) float
        ``q`` filtered in the frequency domain (the signal extended by odd reflection at both
        ends, less the straight line through the extension's ends) with the zero-phase gain
        ``1 / (1 + (f / f_c)^4)``, ``f_c`` the largest of
        ``_N_CUTOFFS`` cutoffs (per coordinate) whose ``mean (q - q_tilde)^2`` reaches
        ``mean variance``; a coordinate that no cutoff takes that far gets the lowest.
    """
    q = np.asarray(q, float)
    T, Q = q.shape
    used = np.ones(T, dtype=bool) if used is None else np.asarray(used, bool)
    if T < 8 or not used.any():
        return q.copy()
    target = np.mean(np.asarray(variance, float)[used], axis=0)  # (Q,)
    pad = T // 2
    ext = np.concatenate([2 * q[:1] - q[pad:0:-1], q, 2 * q[-1:] - q[-2:-pad - 2:-1]])  # odd reflection
    ramp = ext[:1] + (ext[-1:] - ext[:1]) * np.linspace(0.0, 1.0, len(ext))[:, None]
    ext = ext - ramp  # zero at both ends: no jump where the transform wraps round
    X = np.fft.rfft(ext, axis=0)  # (L//2+1, Q)
    f = np.fft.rfftfreq(len(ext))  # cycles per frame; Nyquist 0.5
    cut = np.geomspace(1e-3 * 0.5, 0.95 * 0.5, _N_CUTOFFS)

    def smooth(idx):  # (Q,) cutoff indices -> (T, Q) filtered poses
        gain = 1.0 / (1.0 + (f[:, None] / cut[idx][None, :]) ** 4)
        return (np.fft.irfft(gain * X, n=len(ext), axis=0) + ramp)[pad:pad + T]

    def reaches(idx):  # the variance removed at these cutoffs reaches the target (it falls as they rise)
        return np.mean((q[used] - smooth(idx)[used]) ** 2, axis=0) >= target

    # bisection on the grid, every coordinate at once: the largest cutoff that still removes the target
    lo, hi = np.zeros(Q, dtype=int), np.full(Q, _N_CUTOFFS - 1)
    top, bottom = reaches(hi), reaches(lo)
    while np.any(hi - lo > 1):
        mid = (lo + hi) // 2
        ok = reaches(mid)
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
    pick = np.where(top, _N_CUTOFFS - 1, np.where(bottom, lo, 0))
    return smooth(pick)


def pose_check(model: Model, y, theta, q, pose_var, used, weights_rows=None) -> PoseCheck:
    """Deconvolve the poses and measure how much the information about ``theta`` depends on them.

    Parameters
    ----------
    y : (T, M, D) float
        Markers, NaN where missing.
    theta : (P,) float
    q : (T, Q) float
        Fitted poses.
    pose_var : (T, Q) float
        Variance of each pose estimate.
    used : (T,) bool
        Frames of the fit.
    weights_rows : (T, M*D) float, optional
        Square roots of the row weights of a weighted fit.
    """
    q_tilde = deconvolve_poses(q, pose_var, used)
    yu = y[used]

    def info(qq):
        _, Jq, Jt = frame_terms(model, theta, qq[used], yu)
        if weights_rows is not None:
            Jq, Jt = Jq * weights_rows[used][..., None], Jt * weights_rows[used][..., None]
        return np.diag(efficient_information(Jq, Jt))

    i_hat = info(q)
    change = (info(q_tilde) - i_hat) / np.maximum(i_hat, 1e-300)
    sd = np.sqrt(np.mean(np.asarray(pose_var, float)[used], axis=0))
    return PoseCheck(q_tilde, change, sd, bool(np.any(np.abs(change) > POSE_SENSITIVE)))


def expansion_consistent(b, b_next, sd, n_boot: int) -> np.ndarray:
    """Whether re-evaluating the second-order bias at the corrected geometry leaves it in place.

    Parameters
    ----------
    b : (P,) float
        Second-order bias at the estimate, ``b(theta_hat)``.
    b_next : (P,) float
        The same at the corrected point, ``b(theta_hat - b, q_tilde)``.
    sd : (P,) float
        Standard deviation of the estimate.
    n_boot : int
        Refits of the bootstrap that would stand in for the expansion.

    Returns
    -------
    (P,) bool
        ``|b_next - b| <= sd / sqrt(n_boot)``: the expansion's own error is below the
        bootstrap's Monte Carlo error (see the module's docstring).
    """
    sd = np.asarray(sd, float)
    return np.abs(np.asarray(b_next, float) - np.asarray(b, float)) <= sd / np.sqrt(max(int(n_boot), 1))


def indirect_bias(refit, theta_hat, q_tilde, n_steps: int = FIXED_POINT_STEPS):
    """Bias by simulation at the deconvolved poses, with fixed-point steps on the geometry.

    Parameters
    ----------
    refit : callable
        ``refit(theta, q)``: from ``B`` data sets simulated at ``(theta, q)``, always with the same
        noise draws (common random numbers), either the ``(B, P)`` estimates or a
        :class:`~skelid.estimators.bootstrap.Draws` (shifts from ``theta`` with their linear
        control variates).
    theta_hat : (P,) float
        The fit's estimate.
    q_tilde : (T, Q) float
        Deconvolved poses (:func:`deconvolve_poses`).
    n_steps : int
        Fixed-point steps ``theta <- theta_hat - b(theta)`` after the first (at ``theta_hat``).

    Returns
    -------
    bias : (P,) float
        The last step's bias: the mean shift of its refits from the geometry they were simulated at,
        less the mean of the control variates where there are some
        (:func:`~skelid.estimators.bootstrap.draws_bias`).
    draws : Draws
        That step's shifts (and control variates).
    """
    theta_hat = np.asarray(theta_hat, float)
    theta = theta_hat
    for step in range(n_steps + 1):
        out = refit(theta, q_tilde)
        draws = out if isinstance(out, Draws) else as_draws(np.atleast_2d(out) - theta)
        b = draws_bias(draws)
        if step < n_steps:
            theta = theta_hat - b
    return b, draws


def fallback_covariance(shifts, plain, disagreement) -> np.ndarray:
    """Covariance the fallback adds to ``sigma^2 S^{-1}``: ``(P, P)``.

    The refits' excess spread over ``plain`` (eigenvalues clipped at zero), their Monte Carlo
    error (the bias is a mean of ``B`` shifts: ``C*/B``, or ``Cov(s - l)/B`` with control
    variates ``l``), and ``d d^T / 4`` for the disagreement ``d`` between two estimates of the
    bias (the bias estimate's own uncertainty). With control variates the refits' covariance is
    ``C* = Var(l) + Cov(s) - Cov(l)`` (:func:`~skelid.estimators.bootstrap.draws_covariance`).

    Parameters
    ----------
    shifts : (B, P) float, or Draws
    plain : (P, P) float
    disagreement : (P,) float
    """
    draws = as_draws(shifts)
    B = len(draws.shifts)
    c_boot = B * draws_mc_covariance(draws)  # Cov(s - l): the bias's Monte Carlo covariance is c_boot / B
    w, V = np.linalg.eigh(draws_covariance(draws) - plain)
    d = np.asarray(disagreement, float)
    return (V * np.clip(w, 0.0, None)) @ V.T + c_boot / B + 0.25 * np.outer(d, d)
