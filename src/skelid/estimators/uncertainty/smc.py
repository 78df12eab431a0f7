"""Tempered sequential Monte Carlo: particles carried from the prior to the posterior.

The sampler knows nothing about skeletons: it needs a log prior, draws from
that prior, and a log-likelihood that takes a batch of parameter vectors.

**Path of distributions.** With prior ``p`` and likelihood ``L``,

.. math:: \\pi_\\beta(\\theta) \\propto p(\\theta)\\, L(\\theta)^{\\beta},
          \\qquad 0 = \\beta_0 < \\beta_1 < \\dots < \\beta_K = 1 .

**Stage k** (particles ``theta_i`` with normalised weights ``W_i``, equal after
resampling):

1. *Reweight.* ``w_i = W_i L(theta_i)^{beta_k - beta_{k-1}}``. The step is the
   largest one (found by bisection) for which the effective sample size
   ``ESS = (sum_i w_i)^2 / sum_i w_i^2`` stays at ``alpha N`` (``alpha = 1/2``),
   or ``beta_k = 1`` if the ESS stays above that all the way.
2. *Evidence.* ``log Z += log sum_i W_i L(theta_i)^{beta_k - beta_{k-1}}``;
   after the last stage ``Z`` estimates ``int p(theta) L(theta) d theta`` (the
   prior must be normalised for ``Z`` to mean the evidence, not for the
   posterior).
3. *Resample* (systematic, or multinomial) with the explicit generator.
4. *Move.* ``n_moves`` random-walk Metropolis-Hastings steps that leave
   ``pi_{beta_k}`` invariant: ``theta' = theta + e``, ``e ~ N(0, s 2.38^2/P C)``
   with ``C`` the particles' covariance at the start of the stage (Roberts,
   Gelman and Gilks' scaling), accepted with probability
   ``min(1, exp(beta_k (l(theta') - l(theta)) + log p(theta') - log p(theta)))``.
   The factor ``s`` (1 at first) is halved after a stage that accepted fewer
   than 10 % of the moves and raised by half after one that accepted more
   than 50 %, so curved or skewed targets still mix; the kernel is fixed
   within a stage, so each stage's moves are exactly invariant.

The stage loop is the one loop; everything inside it is vectorised over the
``N`` particles, and the log-likelihood is called once per move on all
proposals that the prior allows.

**Carried state.** An expensive likelihood (a profile over nuisance
parameters) can be warm-started from its last solution. With ``carry`` given,
the callback is ``log_likelihood(theta (n, P), carry (n, ...)) -> (log_lik (n,),
carry (n, ...))``: it receives the state of the particles the proposals were
made from and returns the state at the proposals; the sampler resamples the
state with the particles and keeps it for accepted moves only.

References
----------
Del Moral, Doucet and Jasra (2006), Sequential Monte Carlo samplers, JRSS B 68.
Jasra, Stephens, Doucet and Tsagaris (2011), Inference for Lévy-driven
stochastic volatility models via adaptive SMC, Scand. J. Stat. 38 (adaptive
temperatures). Chopin and Papaspiliopoulos (2020), An Introduction to
Sequential Monte Carlo, ch. 17. Roberts, Gelman and Gilks (1997), Ann. Appl.
Probab. 7 (the 2.38^2/d scaling).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from scipy.special import logsumexp

SCALE_RWM = 2.38**2


class SMCResult(NamedTuple):
    """What :func:`tempered_smc` returns.

    Attributes
    ----------
    particles : (N, P) float
        Draws from the posterior (after the last stage's moves; equally weighted).
    log_weights : (N,) float
        Their normalised log weights (all ``-log N``).
    log_likelihood : (N,) float
    log_prior : (N,) float
    log_evidence : float
        Estimate of ``log int p(theta) L(theta) d theta``.
    temperatures : (K + 1,) float
        ``beta_0 = 0, ..., beta_K = 1``.
    ess : (K,) float
        Effective sample size after each stage's reweighting.
    acceptance : (K,) float
        Fraction of accepted moves in each stage.
    n_evaluations : int
        Likelihood evaluations (one per particle and call).
    carry : array or None
        The carried state of the final particles.
    completed : bool
        False if ``max_stages`` forced the last step to ``beta = 1``.
    """

    particles: np.ndarray
    log_weights: np.ndarray
    log_likelihood: np.ndarray
    log_prior: np.ndarray
    log_evidence: float
    temperatures: np.ndarray
    ess: np.ndarray
    acceptance: np.ndarray
    n_evaluations: int
    carry: object
    completed: bool


def kish_ess(log_w) -> float:
    """Effective sample size ``(sum w)^2 / sum w^2`` of log weights ``(N,)`` (any constant)."""
    log_w = np.asarray(log_w, float)
    if not np.isfinite(log_w).any():
        return 0.0
    return float(np.exp(2.0 * logsumexp(log_w) - logsumexp(2.0 * log_w)))


def _increment(log_lik, delta: float) -> np.ndarray:
    """``delta * log_lik`` with ``-inf`` where the likelihood is zero or undefined."""
    ok = np.isfinite(log_lik)
    return np.where(ok, delta * np.where(ok, log_lik, 0.0), -np.inf)


def next_temperature(log_lik, log_w, beta: float, ess_target: float, n_bisect: int = 60) -> float:
    """The next temperature: the largest step whose reweighting keeps ``ESS >= ess_target``.

    Parameters
    ----------
    log_lik : (N,) float
        Log-likelihood of the particles.
    log_w : (N,) float
        Their current normalised log weights.
    beta : float
        Current temperature.
    ess_target : float
        Effective sample size to keep (e.g. ``N / 2``).

    Returns
    -------
    float
        ``beta_next`` in ``(beta, 1]``.
    """
    def ess(delta):
        return kish_ess(log_w + _increment(log_lik, delta))

    room = 1.0 - beta
    if ess(room) >= ess_target:
        return 1.0
    lo, hi = 0.0, room
    for _ in range(n_bisect):
        mid = 0.5 * (lo + hi)
        if ess(mid) >= ess_target:
            lo = mid
        else:
            hi = mid
    return min(beta + (lo if lo > 0.0 else hi), 1.0)  # always some progress


def resample(log_w, rng: np.random.Generator, method: str = "systematic") -> np.ndarray:
    """(N,) int: indices of the particles drawn in proportion to ``exp(log_w)``.

    ``systematic``: one uniform ``u``, points ``(u + i) / N``; ``multinomial``:
    ``N`` independent draws.
    """
    w = np.exp(log_w - logsumexp(log_w))
    n = w.size
    if method == "multinomial":
        return rng.choice(n, size=n, p=w / w.sum())
    if method != "systematic":
        raise ValueError("resampling must be 'systematic' or 'multinomial'")
    c = np.cumsum(w)
    c[-1] = 1.0
    return np.minimum(np.searchsorted(c, (rng.random() + np.arange(n)) / n), n - 1)


def _take(carry, idx):
    return None if carry is None else carry[idx]


def tempered_smc(log_likelihood: Callable, log_prior: Callable, initial, rng: np.random.Generator, *,
                 n_moves: int = 3, ess_fraction: float = 0.5, max_stages: int = 200,
                 resampling: str = "systematic", carry=None, on_stage: Callable | None = None) -> SMCResult:
    """Sample ``p(theta) L(theta)`` by tempered SMC from draws of the prior.

    Parameters
    ----------
    log_likelihood : callable
        ``(n, P) -> (n,)``, the log-likelihood of a batch (``-inf`` allowed);
        with ``carry`` given, ``(theta (n, P), carry (n, ...)) -> (log_lik (n,),
        carry (n, ...))`` (see the module docstring).
    log_prior : callable
        ``(n, P) -> (n,)``, the log prior density (up to a constant; ``-inf``
        outside its support).
    initial : (N, P) float
        Independent draws from the (normalised) prior.
    rng : numpy.random.Generator
        For resampling, proposals and acceptance.
    n_moves : int
        Metropolis-Hastings moves per stage.
    ess_fraction : float
        The ESS kept at each reweighting, as a fraction of ``N``.
    max_stages : int
        A run that has not reached ``beta = 1`` by then jumps there
        (``completed`` is then False and the last ESS shows the damage).
    resampling : {'systematic', 'multinomial'}
    carry : array with leading axis N, optional
        Starting state of a stateful likelihood, one per particle.
    on_stage : callable, optional
        Called with the temperature before the likelihood is evaluated for
        it (0 for the initial draws, then each stage's ``beta_k`` before its
        moves): a likelihood computed to a temperature-dependent accuracy
        (rougher while the target is flat) can adapt.

    Returns
    -------
    SMCResult

    Examples
    --------
    A likelihood N(1, 1/4) under a prior N(0, 1): the posterior is N(0.8, 0.2).

    >>> rng = np.random.default_rng(0)
    >>> res = tempered_smc(lambda t: -2.0 * (t[:, 0] - 1.0) ** 2, lambda t: -0.5 * t[:, 0] ** 2,
    ...                    rng.normal(size=(2000, 1)), rng)
    >>> round(float(res.particles.mean()), 1), round(float(res.particles.var()), 1)
    (0.8, 0.2)
    """
    theta = np.array(initial, dtype=float, ndmin=2)
    N, P = theta.shape
    if N < 2:
        raise ValueError("tempered SMC needs at least two particles")
    if not 0.0 < ess_fraction < 1.0:
        raise ValueError("ess_fraction must lie in (0, 1)")
    stateful = carry is not None
    n_eval = 0

    def loglik(th, c):
        nonlocal n_eval
        n_eval += len(th)
        if stateful:
            ll, c_new = log_likelihood(th, c)
        else:
            ll, c_new = log_likelihood(th), None
        ll = np.asarray(ll, dtype=float).reshape(len(th))
        return np.where(np.isnan(ll), -np.inf, ll), c_new

    lp = np.asarray(log_prior(theta), dtype=float)
    if not np.isfinite(lp).all():
        raise ValueError("some initial particles lie outside the prior's support")
    if on_stage is not None:
        on_stage(0.0)
    ll, carry = loglik(theta, carry)
    log_w = np.full(N, -np.log(N))
    beta, log_z = 0.0, 0.0
    betas, esss, accs = [0.0], [], []
    scale = 1.0
    completed = True
    while beta < 1.0:
        if len(esss) == max_stages - 1:
            new_beta, completed = 1.0, False
        else:
            new_beta = next_temperature(ll, log_w, beta, ess_fraction * N)
        inc = _increment(ll, new_beta - beta)
        if not np.isfinite(inc).any():
            raise FloatingPointError("the likelihood is zero (or undefined) at every particle")
        log_z += float(logsumexp(log_w + inc))
        log_w = log_w + inc
        log_w -= logsumexp(log_w)
        beta = new_beta
        betas.append(beta)
        if on_stage is not None:
            on_stage(beta)
        esss.append(kish_ess(log_w))
        # resample, then move with a kernel that leaves pi_beta invariant
        idx = resample(log_w, rng, resampling)
        theta, ll, lp, carry = theta[idx], ll[idx], lp[idx], _take(carry, idx)
        log_w = np.full(N, -np.log(N))
        cov = np.atleast_2d(np.cov(theta, rowvar=False))
        jitter = 1e-12 * max(float(np.max(np.abs(np.diag(cov)))), 1e-300)
        chol = np.linalg.cholesky(SCALE_RWM / P * scale * cov + jitter * np.eye(P))
        n_acc = 0
        for _ in range(n_moves):
            prop = theta + rng.standard_normal((N, P)) @ chol.T
            lp_prop = np.asarray(log_prior(prop), dtype=float)
            ok = np.isfinite(lp_prop)
            ll_prop = np.full(N, -np.inf)
            c_prop = None
            if ok.any():
                ll_prop[ok], c_prop = loglik(prop[ok], _take(carry, ok))
            good = ok & np.isfinite(ll_prop) & np.isfinite(ll)
            log_alpha = np.full(N, -np.inf)
            log_alpha[good] = beta * (ll_prop[good] - ll[good]) + lp_prop[good] - lp[good]
            acc = np.log(rng.random(N)) < log_alpha
            acc |= ok & np.isfinite(ll_prop) & ~np.isfinite(ll)  # leave a point of zero likelihood
            theta = np.where(acc[:, None], prop, theta)
            ll = np.where(acc, ll_prop, ll)
            lp = np.where(acc, lp_prop, lp)
            if stateful and acc.any():
                carry = carry.copy()
                carry[acc] = c_prop[acc[ok]]
            n_acc += int(acc.sum())
        rate = n_acc / max(N * n_moves, 1)
        accs.append(rate)
        if rate < 0.1:
            scale *= 0.5
        elif rate > 0.5:
            scale = min(scale * 1.5, 4.0)
    return SMCResult(theta, log_w, ll, lp, log_z, np.array(betas), np.array(esss), np.array(accs),
                     n_eval, carry, completed)
