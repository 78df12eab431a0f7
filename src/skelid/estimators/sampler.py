"""Posterior samples of the parameters when the Gaussian approximation is not good enough.

The default estimator (:mod:`skelid.estimators.marker`) reports a normal
posterior around the joint fit. That is accurate when the data pin every
parameter well inside its prior; it is not when a parameter is weakly
identified (few frames, large noise, several parameters trading off), when
the posterior is skewed, or when it presses against a bound of the prior,
where the normal interval spills outside the bounds. ``marker-smc`` samples
the posterior instead, with the same likelihood, motion model, noise level
and bias correction.

**Likelihood.** With the motion-model penalty ``K`` (the third-difference
Whittaker penalty of :func:`skelid.estimators.fit.joint.smoothing_penalty`, with
the default fit's cutoffs), the penalised marker cost at parameters
``theta`` and poses ``q = (q_1..q_T)`` is

.. math:: c(\\theta, q) = \\sum_t \\lVert y_t - x(q_t, \\theta) \\rVert^2 + q^\\top K q ,

and its profile over the poses ``c(theta) = min_q c(theta, q)`` at
``q_hat(theta)``. The log-likelihood sampled is

.. math:: \\ell(\\theta) = -\\tau \\Big[\\frac{c(\\theta + b)}{2 \\hat\\sigma^2}
          + \\frac{n}{2} \\log (2 \\pi \\hat\\sigma^2)\\Big]

with ``sigma_hat`` the default fit's noise level (estimated from its
residuals, or the user's value; held fixed, not integrated over), ``n`` the
marker coordinates used, ``b`` the default fit's second-order bias and ``tau``
a curvature adjustment (both below). Its Gauss-Newton curvature at the fit is
``S / sigma^2``, the information the default estimator's covariance comes
from, so where the posterior is nearly normal both methods agree (the exact
curvature differs by the residuals' second-order term, a few per cent at
realistic noise).

**Bias.** The penalised fit is biased by ``b`` to second order in the noise
(:func:`skelid.estimators.fit.joint.smoothed_bias`), a constant over the width of
the posterior to that order. Evaluating the likelihood at ``theta + b``
centres it at ``theta_hat - b``, which is the default estimator's corrected
estimate: under a flat prior this is exactly shifting every sample by
``-b``; unlike shifting samples it keeps them inside the prior's bounds and
lets a normal prior act on the corrected likelihood, as the default
estimator combines it.

**Widened intervals.** When the default estimator widened its interval
(``V_NW`` instead of ``V = sigma^2 S^{-1}``) because the residuals are serially
correlated (soft-tissue artefact, Newey-West), or added a stated artefact's,
the marker jackknife's or the markers' placement term,
the likelihood is misspecified and too sharp. As in composite-likelihood
practice its curvature is adjusted by one factor,

.. math:: \\tau = P / \\mathrm{tr}(V^{-1} V_{NW}) ,

which in one dimension is the ratio of the unwidened to the widened variance,
so the sampled posterior has the widened width (Ribatet, Cooley and Davison
2012, "magnitude adjustment"). Otherwise ``tau = 1``.

**Prior.** The model's priors: uniform (``-inf`` outside the bounds),
normal or log-normal (truncated to the bounds).

**Inner pose solve.** Each evaluation minimises ``c(theta, q)`` over all
poses (:func:`profile_poses`) with the exact gradient ``g = J^T r - K q``
(:func:`skelid.model.kinematics.pose_gradient`, no Jacobian formed). The
step is first the chord step ``A_0^{-1} g``, with
``A_0 = blockdiag(J_t^T J_t) + K`` at the default fit factored once (banded
Cholesky), so one solve serves all particles; a particle whose chord step
fails to lower its cost switches to its own Levenberg-Marquardt steps, one
banded factorisation per particle and iteration (the one loop over
particles, in :meth:`PoseSystem.exact`). Without a motion model the frames
decouple and everything is batched. The cost found is an upper bound on the
minimum, so an unconverged solve can only lower the likelihood.

*Near the fit* (within three finite-difference steps ``h = 2 sd`` of
``theta_hat`` in every parameter, capped at a tenth of the prior width) a
point starts from a quadratic model of ``q_hat(theta)`` built from exact
solves around the fit (:class:`ProfileLikelihood`), whatever the particle's
history, and iterates until a step gains less than
``0.01 + 0.01 (l(theta_hat) - l(theta))`` in log-likelihood: there the
likelihood is one function of ``theta``, accurate to about ``10^-3``, and one
or two iterations suffice.

*Farther out* a proposal starts from its parent's poses, moved by
``G (theta - theta_p)`` if that fits better. While the sampler is hot
(temperature below 0.1: the early stages, whose particles roam the prior
and whose target is flat) such a point takes a single step: a cheap lower
bound of ``l`` that only tilts those intermediate distributions away from
the far region. From temperature 0.1 on it is solved to the same tolerance
as near the fit. Final particles outside the near region are solved again to
that tolerance and their weights multiplied by ``exp(l_solved - l_before) >=
1`` (importance sampling), so no rough value is left in the final sample.

**Sampler.** Tempered SMC from the prior (:mod:`skelid.estimators.uncertainty.smc`):
adaptive temperatures keeping half the effective sample size, systematic
resampling, random-walk Metropolis-Hastings moves scaled from the particles.

**Cost.** The default fit, then about ``N (1 + moves x stages)`` profile
evaluations, each two to four forward-kinematics passes over all frames;
the number of stages grows with the information the data add to the prior
(about ``sum_k log(prior width_k / posterior sd_k)``). Measured on one
core with 200 particles: case A, 500 frames, 4 stages, about 5 s after
the default fit; a three-parameter functional joint centre (finger model,
500 frames), 11 stages, about a minute.

Example
-------
>>> import numpy as np
>>> from skelid.simulate import builtin_model, simulate
>>> model = builtin_model("case-a")
>>> trial = simulate(model, n_frames=80, sigma=5.0, rng=np.random.default_rng(0))
>>> r = SamplerEstimator(model, rng=0, n_particles=40, n_moves=1).fit(trial.data).result()
>>> abs(r.parameters["L2"].mean - 250.0) < 4 * r.parameters["L2"].sd + 1.0
True
"""

from __future__ import annotations

import time

import numpy as np
from scipy.linalg import cho_solve_banded, cholesky_banded
from scipy.special import logsumexp
from scipy.stats import norm

from skelid._linalg import frame_gram
from skelid._stop import interruptible
from skelid.data import MarkerData
from skelid.estimators.base import (
    Setting,
    build_result,
    check_fitted,
    check_model,
    check_settings,
    count,
    counted,
    emit,
    make_rng,
    marker_array,
    positive,
)
from skelid.estimators.fit.joint import _banded, _banded_solver
from skelid.estimators.fit.likelihood import frame_terms, pose_information
from skelid.estimators.marker import (
    N_BOOT,
    POOR_FRACTION,
    MarkerEstimator,
    _unit,
    marker_warnings,
    run_marker_fit,
)
from skelid.estimators.uncertainty.posterior import SamplePosterior, weighted_quantiles
from skelid.estimators.uncertainty.smc import kish_ess, tempered_smc
from skelid.model.description import Model
from skelid.model.kinematics import (
    Kinematics,
    forward_kinematics,
    joint_distances,
    pose_gradient,
    pose_jacobian,
)
from skelid.result import FitResult, Warning

#: near the fit, an inner pose step that gains less than INNER_TOL + INNER_RTOL (l(theta_hat) - l(theta))
#: in log-likelihood ends the solve; the steps shrink geometrically (by a factor of about 0.05-0.2),
#: so what is left is smaller still
INNER_TOL = 1e-2
INNER_RTOL = 1e-2
#: outside the near region, while the sampler's temperature is below HOT (the early stages, whose
#: particles roam the prior), the solve stops after FAR_ITER iterations; final particles that
#: were evaluated so are solved again with REFINE_ITER iterations at most
HOT = 0.1
FAR_ITER = 1
REFINE_ITER = 30
#: the quadratic model of the poses is trusted this many finite-difference steps from the fit
NEAR_STEPS = 3.0
#: frames x particles evaluated at once (bounds the memory of the kinematics)
CHUNK_FRAMES = 40000


def sample_prior(model: Model, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, P) float: independent draws from the model's priors, truncated to their bounds.

    Uniform priors are drawn directly, normal and log-normal ones by the inverse
    distribution function between the bounds (on the log scale for log-normal).
    """
    out = np.empty((n, model.n_params))
    for k, p in enumerate(model.parameters):
        pr = p.prior
        if pr.kind == "uniform":
            out[:, k] = rng.uniform(pr.lower, pr.upper, size=n)
            continue
        if pr.kind == "normal":
            centre, lo, hi = pr.mean, pr.lower, pr.upper
        else:  # log-normal: the log is normal around log(median)
            centre, lo, hi = np.log(pr.mean), np.log(max(pr.lower, 1e-300)), np.log(pr.upper)
        a, b = norm.cdf((lo - centre) / pr.sd), norm.cdf((hi - centre) / pr.sd)
        z = centre + pr.sd * norm.ppf(rng.uniform(a, b, size=n))
        out[:, k] = np.clip(z if pr.kind == "normal" else np.exp(z), pr.lower, pr.upper)
    return out


class PoseSystem:
    """The pose problem's normal matrix ``A = blockdiag(H_t) + K`` at the fit, and per particle.

    ``A_0`` (at the default fit) is factored once: a *chord* step
    ``A_0^{-1} g`` costs one triangular solve for every particle at once.
    A particle's own matrix (with damping) is assembled from ``K``'s banded
    form (kept) and its blocks ``H_t`` by one indexed add, and factored by
    banded Cholesky. Without a motion model (``K`` None) both are
    block-diagonal and solved frame by frame, batched.

    Parameters
    ----------
    H0 : (T, Q, Q) float
        ``J_t^T J_t`` at the fit.
    R : scipy.sparse matrix (T*Q, T*Q) or None
        The motion-model penalty ``K``.
    """

    def __init__(self, H0, R=None):
        self.T, self.Q = H0.shape[:2]
        self.R = R
        T, Q = self.T, self.Q
        if R is None:
            d = np.einsum("tii->ti", H0)
            ridge = 1e-10 * np.maximum(d.mean(axis=1), max(float(d.mean()), 1e-300))
            self.inv0 = np.linalg.inv(H0 + ridge[:, None, None] * np.eye(Q))
            return
        self.ab = _banded(np.zeros((T, Q, Q)), R)
        u = self.ab.shape[0] - 1
        self.u = u
        rows, cols, tt, ii, jj = [], [], [], [], []
        base = np.arange(T)[:, None] * Q
        for off in range(Q):
            b = np.arange(off, Q)
            c = (base + b).ravel()
            rows.append(np.full(c.size, u - off))
            cols.append(c)
            tt.append(np.repeat(np.arange(T), b.size))
            ii.append(np.tile(b - off, T))
            jj.append(np.tile(b, T))
        self.rows, self.cols = np.concatenate(rows), np.concatenate(cols)
        self.tt, self.ii, self.jj = np.concatenate(tt), np.concatenate(ii), np.concatenate(jj)
        self.cb0 = cholesky_banded(self._assemble(H0, 0.0), lower=False, check_finite=False)

    def _assemble(self, H, lam: float) -> np.ndarray:
        ab = self.ab.copy()
        ab[self.rows, self.cols] += H[self.tt, self.ii, self.jj]
        ab[self.u] += lam * np.einsum("tii->ti", H).ravel()
        ab[self.u] += 1e-10 * max(float(np.mean(ab[self.u])), 1e-300)  # frames without markers
        return ab

    def chord(self, g) -> np.ndarray:
        """``A_0^{-1} g`` for ``g (n, T, Q)``: (n, T, Q)."""
        n = len(g)
        if self.R is None:
            return np.einsum("tij,ntj->nti", self.inv0, g)
        x = cho_solve_banded((self.cb0, False), g.reshape(n, -1).T, check_finite=False)
        return x.T.reshape(n, self.T, self.Q)

    def exact(self, H, g, lam) -> np.ndarray:
        """``(blockdiag(H) + K + lam diag(H))^{-1} g`` per particle: ``H (n, T, Q, Q)``, ``g (n, T, Q)``."""
        if self.R is None:
            d = np.einsum("ntii->nti", H)
            ridge = 1e-10 * np.maximum(d.mean(axis=-1), 1e-300)
            A = H + (np.asarray(lam)[:, None, None] * d + ridge[..., None])[..., None] * np.eye(self.Q)
            return np.linalg.solve(A, g[..., None])[..., 0]
        out = np.empty_like(g)
        for j in range(len(g)):  # the one loop over particles: a banded factorisation each
            cb = cholesky_banded(self._assemble(H[j], float(lam[j])), lower=False, check_finite=False)
            out[j] = cho_solve_banded((cb, False), g[j].ravel(), check_finite=False).reshape(self.T, self.Q)
        return out


def profile_poses(model: Model, theta, y, q0, system: PoseSystem, n_iter=8, tol: float = 0.0,
                  rel_tol: float = 0.0, floor: float = 0.0):
    """Minimise the penalised marker cost over all poses at fixed parameters, per particle.

    .. math:: c(\\theta) = \\min_q \\sum_t \\lVert y_t - x(q_t, \\theta)\\rVert^2 + q^\\top K q

    Each iteration takes the gradient ``g = J^T r - K q`` at the particle's
    poses and first tries the chord step ``A_0^{-1} g`` (the normal matrix at
    the default fit, factored once, so all particles share one solve); a
    particle whose chord step does not lower its cost switches to its own
    Levenberg-Marquardt steps ``(A + lam diag(H))^{-1} g`` for the rest of the
    solve. Both have the exact gradient, so they converge to the same
    minimum. A particle stops when an accepted step lowers its cost by
    ``tol + rel_tol (c - floor)`` or less: far from the optimum of ``theta``
    (``c`` well above ``floor``, the cost at the fit) a relative error is
    enough, for the likelihood there is small whatever its exact value.

    Parameters
    ----------
    theta : (N, P) float
    y : (T, M, D) float
        Markers, NaN where missing (a frame with none has no rows).
    q0 : (N, T, Q) float
        Starting poses.
    system : PoseSystem
        The normal matrix at the fit and the penalty.
    n_iter : int or (N,) int
        Iterations at most.
    tol, rel_tol, floor : float
        A cost decrease of ``tol + rel_tol (c - floor)`` or less counts as converged.

    Returns
    -------
    cost : (N,) float
        ``c`` at the returned poses (an upper bound on the minimum).
    q : (N, T, Q) float
    n_done : (N,) int
        Iterations each particle took.
    """
    theta = np.asarray(theta, float)
    y = np.asarray(y, float)
    q = np.array(q0, dtype=float)
    N, T, Q = q.shape
    R = system.R
    mask = np.isfinite(y).all(axis=-1)
    y0 = np.where(mask[..., None], y, 0.0)

    def residual(th, qq):
        """What the pose Jacobian needs (axes, pivots, markers) and the residuals."""
        kin = forward_kinematics(model, th[:, None, :], qq)
        return [kin.dof_axis, kin.dof_pivot, kin.markers], (y0 - kin.markers) * mask[..., None]

    def penalty_grad(qq):
        return np.zeros_like(qq) if R is None else (R @ qq.reshape(len(qq), -1).T).T.reshape(qq.shape)

    def cost_of(r, qq, Kq):
        return np.einsum("ntmd,ntmd->n", r, r) + np.einsum("nti,nti->n", qq, Kq)

    kin, r = residual(theta, q)
    Kq = penalty_grad(q)
    cost = cost_of(r, q, Kq)
    n_iter = np.broadcast_to(np.asarray(n_iter, int), (N,))
    lam = np.full(N, 1e-3)
    own = np.zeros(N, dtype=bool)  # particles that take their own (damped) steps
    n_done = np.zeros(N, dtype=int)
    active = np.isfinite(cost) & (n_iter > 0)
    cost = np.where(np.isfinite(cost), cost, np.inf)
    for _ in range(int(n_iter.max(initial=0))):
        act = np.flatnonzero(active)
        if act.size == 0:
            break
        th, qa = theta[act], q[act]
        kin_a = Kinematics(None, None, None, *(a[act] for a in kin), None, None)
        g = pose_gradient(model, kin_a, r[act]) - Kq[act]
        step = np.empty_like(qa)
        mine = own[act]
        if (~mine).any():
            step[~mine] = system.chord(g[~mine])
        if mine.any():
            kin_m = Kinematics(None, None, None, *(a[act[mine]] for a in kin), None, None)
            J = (pose_jacobian(model, kin_m) * mask[..., None, None]).reshape(int(mine.sum()), T, -1, Q)
            H = np.einsum("ntki,ntkj->ntij", J, J)
            step[mine] = system.exact(H, g[mine], lam[act[mine]])
        q_new = qa + np.where(np.isfinite(step), step, 0.0)
        kin_new, r_new = residual(th, q_new)
        Kq_new = penalty_grad(q_new)
        c_new = cost_of(r_new, q_new, Kq_new)
        ok = np.isfinite(c_new) & (c_new <= cost[act])
        gain = np.where(ok, cost[act] - c_new, 0.0)
        acc = act[ok]
        q[acc], cost[acc], r[acc], Kq[acc] = q_new[ok], c_new[ok], r_new[ok], Kq_new[ok]
        for a, an in zip(kin, kin_new, strict=True):
            a[acc] = an[ok]
        n_done[act] += 1
        lam[act] = np.where(ok | ~mine, np.maximum(lam[act] * 0.3, 1e-9), lam[act] * 10.0)
        own[act] |= ~ok  # a chord step that failed: from now on, its own steps
        limit = tol + rel_tol * np.maximum(cost[act] - floor, 0.0)
        active[act] = ~((ok & (gain <= limit)) | (lam[act] > 1e8) | (n_done[act] >= n_iter[act]))
    return cost, q, n_done


class ProfileLikelihood:
    """The sampled log-likelihood ``l(theta)`` (see the module docstring), with warm starts.

    Parameters
    ----------
    model : Model
    y : (T, M, D) float
        The markers the default fit used (NaN where missing or skipped).
    theta_fit : (P,) float
        The penalised fit's ``theta`` (before bias correction).
    pose_fit : (T, Q) float
        Its poses.
    R : sparse (T*Q, T*Q) or None
        Its motion-model penalty.
    sigma2 : float
        Noise variance.
    bias : (P,) float
        The likelihood is evaluated at ``theta + bias``.
    tau : float
        Curvature adjustment (1: none).
    scale : (P,) float, optional
        The likelihood's width in each parameter (e.g. the Cramér-Rao sd): sets
        the finite-difference steps of the pose response.
    bounds : (lower (P,), upper (P,)), optional
        The prior's bounds: the steps stay below a tenth of their width.
    n_iter : int
        Inner iterations at most.

    Notes
    -----
    Called as ``log_lik, carry = self(theta (N, P), carry (N, P + T*Q))``: the
    carry holds the point each particle was last evaluated at and its poses.
    :meth:`initial_carry` gives the carry of new particles (the fit's poses at
    the fit's ``theta``).

    **Warm starts.** A quadratic model of the optimal poses around the fit,

    .. math:: m(\\delta) = G\\,\\delta + \\tfrac12\\, \\delta^\\top G_2\\, \\delta ,
              \\qquad \\delta = \\theta - \\hat\\theta ,

    is taken from exact pose solves at ``theta_hat +- h_k e_k`` and
    ``theta_hat + h_j e_j + h_k e_k`` (central and mixed differences, ``h``
    twice ``scale``); the Gauss-Newton response ``-A^{-1} H_{q theta}``
    misses the residuals' curvature, which at realistic noise is tens of per
    cent. Within ``NEAR_STEPS`` steps ``h`` of the fit in every parameter (the
    *near region*, where the posterior is unless the data say little) a point
    starts from ``q_hat + m(theta - theta_hat)``, whatever the particle's
    history, so that the likelihood there is one function of ``theta``, and is
    solved to ``INNER_TOL``. Farther out the quadratic model extrapolates
    badly: a proposal made from a particle at ``theta_p`` starts from that
    particle's poses, moved by ``G (theta - theta_p)`` if that fits better; while
    the temperature (:meth:`set_temperature`) is below ``HOT`` it takes only
    ``FAR_ITER`` step(s), a lower bound of the likelihood (see :meth:`refine`).
    """

    def __init__(self, model: Model, y, theta_fit, pose_fit, R, sigma2: float, bias, tau: float = 1.0,
                 scale=None, bounds=None, n_iter: int = 8):
        self.model, self.y, self.R = model, np.asarray(y, float), R
        self.theta_fit = np.asarray(theta_fit, float)
        self.pose_fit = np.asarray(pose_fit, float)
        self.sigma2, self.tau, self.n_iter = float(sigma2), float(tau), n_iter
        self.bias = np.asarray(bias, float)
        T, Q = self.pose_fit.shape
        P = self.theta_fit.size
        self.shape = (T, Q)
        self.n_obs = int(np.isfinite(self.y).all(axis=-1).sum() * model.dim)
        _, Jq, Jt = frame_terms(model, self.theta_fit, self.pose_fit, self.y)
        Hqq = pose_information(Jq)
        self.system = PoseSystem(Hqq, R)
        gn = self._gauss_newton_response(Hqq, frame_gram(Jq, Jt))
        h = np.ones(P) if scale is None else 2.0 * np.asarray(scale, float)
        if bounds is not None:
            h = np.minimum(h, 0.1 * (np.asarray(bounds[1], float) - np.asarray(bounds[0], float)))
        self.step = np.where(np.isfinite(h) & (h > 0), h, 1.0)
        self.n_inner = 0
        self.n_calls = 0
        self.temperature = 1.0
        self.cost_fit, self.response, self.curvature = self._quadratic_response(gn)

    def _gauss_newton_response(self, Hqq, Hqt) -> np.ndarray:
        """(T, Q, P) float: ``dq_hat/dtheta = -A^{-1} H_{q theta}`` at the fit (Gauss-Newton)."""
        T, Q = self.shape
        P = Hqt.shape[-1]
        if self.R is None:
            return -np.moveaxis(self.system.chord(np.moveaxis(Hqt, -1, 0)), 0, -1)
        return -_banded_solver(Hqq, self.R)(Hqt.reshape(T * Q, P)).reshape(T, Q, P)

    def _quadratic_response(self, gn):
        """Cost at the fit, ``G (T, Q, P)`` and ``G_2 (T, Q, P, P)`` from exact solves around it."""
        P = self.theta_fit.size
        h = self.step
        E = np.diag(h)
        pairs = [(j, k) for j in range(P) for k in range(j + 1, P)]
        delta = np.concatenate([np.zeros((1, P)), E, -E] + ([np.array([E[j] + E[k] for j, k in pairs])]
                                                            if pairs else []))
        start = self.pose_fit[None] + np.einsum("tqp,np->ntq", gn, delta)
        cost, q = self._chunks(self.theta_fit + delta, start, 50, 1e-8 * self.sigma2, 0.0, 0.0)
        q0, qp, qm = q[0], q[1:P + 1], q[P + 1:2 * P + 1]
        G = np.moveaxis((qp - qm) / (2.0 * h[:, None, None]), 0, -1)
        G2 = np.zeros(self.shape + (P, P))
        for k in range(P):
            G2[..., k, k] = (qp[k] - 2.0 * q0 + qm[k]) / h[k] ** 2
        for i, (j, k) in enumerate(pairs):
            G2[..., j, k] = G2[..., k, j] = (q[2 * P + 1 + i] - qp[j] - qp[k] + q0) / (h[j] * h[k])
        return float(cost[0]), G, G2

    def near(self, point) -> np.ndarray:
        """(N,) bool: points within ``NEAR_STEPS`` steps ``h`` of the fit in every parameter."""
        return np.max(np.abs(np.asarray(point, float) - self.theta_fit) / self.step, axis=-1) <= NEAR_STEPS

    def start(self, point, carry) -> np.ndarray:
        """(N, T, Q) float: starting poses for ``point (N, P)`` (see the class notes)."""
        point = np.asarray(point, float)
        N, P = point.shape
        out = np.empty((N,) + self.shape)
        near = self.near(point)
        if near.any():
            dn = point[near] - self.theta_fit
            out[near] = self.pose_fit + np.einsum("tqp,np->ntq", self.response, dn) \
                + 0.5 * np.einsum("tqjk,nj,nk->ntq", self.curvature, dn, dn)
        far = np.flatnonzero(~near)
        if far.size:  # the parent's poses, with or without the linear change: whichever fits better
            parent = carry[far, P:].reshape((far.size,) + self.shape)
            moved = parent + np.einsum("tqp,np->ntq", self.response, point[far] - carry[far, :P])
            cand = np.concatenate([moved, parent])
            cost, _, _ = profile_poses(self.model, np.concatenate([point[far], point[far]]), self.y, cand,
                                       self.system, n_iter=0)
            out[far] = np.where((cost[:far.size] <= cost[far.size:])[:, None, None], moved, parent)
        return out

    def initial_carry(self, n: int) -> np.ndarray:
        """(n, P + T*Q) float: the fit's point and poses for every particle."""
        return np.tile(np.concatenate([self.theta_fit, self.pose_fit.ravel()]), (n, 1))

    @property
    def offset(self) -> float:
        """The constant subtracted from ``l`` inside the sampler: ``l`` at the fit."""
        return -self.tau * (self.cost_fit / (2.0 * self.sigma2)
                            + 0.5 * self.n_obs * np.log(2.0 * np.pi * self.sigma2))

    def __call__(self, theta, carry):
        """``(l(theta) - offset (N,), carry (N, P + T*Q))``."""
        theta = np.asarray(theta, float)
        at = theta + self.bias
        near = self.near(at)
        s2 = 2.0 * self.sigma2 / self.tau  # one unit of log-likelihood in cost units
        n_iter = np.where(near | (self.temperature >= HOT), self.n_iter, FAR_ITER)
        return self._solve(at, self.start(at, carry), INNER_TOL * s2, INNER_RTOL, n_iter)

    def set_temperature(self, beta: float) -> None:
        """The sampler's temperature: below ``HOT``, far points get a rough solve."""
        self.temperature = float(beta)

    def refine(self, theta, carry):
        """Like calling it, but to the tolerance of the near region wherever ``theta`` is.

        The poses start from the carried ones (computed at the same points).
        """
        theta = np.asarray(theta, float)
        N, P = theta.shape
        at = theta + self.bias
        start = carry[:, P:].reshape((N,) + self.shape)
        s2 = 2.0 * self.sigma2 / self.tau
        return self._solve(at, start, INNER_TOL * s2, INNER_RTOL, max(self.n_iter, REFINE_ITER))

    def _chunks(self, at, start, n_iter, tol, rel, floor):
        """:func:`profile_poses` over ``CHUNK_FRAMES`` frames x points at a time: ``(cost (N,), q)``."""
        N = len(at)
        T, Q = self.shape
        n_iter = np.broadcast_to(n_iter, (N,))
        cost = np.empty(N)
        q = np.empty((N, T, Q))
        step = max(1, CHUNK_FRAMES // max(T, 1))
        for a in range(0, N, step):
            b = min(a + step, N)
            cost[a:b], q[a:b], n = profile_poses(self.model, at[a:b], self.y, start[a:b], self.system,
                                                 n_iter=n_iter[a:b], tol=tol, rel_tol=rel, floor=floor)
            self.n_inner += int(n.sum())
        return cost, q

    def _solve(self, at, start, tol, rel, n_iter):
        N = len(at)
        cost, q = self._chunks(at, start, n_iter, tol, rel, self.cost_fit)
        self.n_calls += N
        ll = -self.tau * (cost - self.cost_fit) / (2.0 * self.sigma2)
        return np.where(np.isfinite(ll), ll, -np.inf), np.concatenate([at, q.reshape(N, -1)], axis=1)


class SamplerEstimator:
    """Posterior samples of the parameters by tempered SMC on the profile marker likelihood.

    Holds a :class:`~skelid.estimators.marker.MarkerEstimator` fit with the same
    settings (its noise level, motion model, poses and bias are used), then
    samples ``p(theta) exp(l(theta))`` (see the module docstring).

    Parameters
    ----------
    model : Model
    sigma, cutoff, bias_correction, n_boot, robust, rng, n_iter, rate, outlier_threshold, theta0, pose0, n_starts
        As for :class:`~skelid.estimators.marker.MarkerEstimator`; ``rng`` also
        drives the sampler.
    n_particles : int
        Particles (default 200).
    n_moves : int
        Metropolis-Hastings moves per tempering stage (default 3).
    ess_fraction : float
        Effective sample size kept at each reweighting, as a fraction of the
        particles (default 1/2).
    inner_iter : int
        Gauss-Newton iterations of the pose solve at most, per evaluation.

    Attributes
    ----------
    posterior_ : SamplePosterior
        The samples (with their log posterior density, up to a constant).
    marker_ : MarkerEstimator
        The fitted default estimator the sampler started from.
    gaussian_posterior_ : GaussianPosterior
        The default estimator's normal posterior, for comparison.
    theta_ : (P,) float
        Posterior mean.
    cov_ : (P, P) float
        Posterior covariance of the samples.
    lengths_ : dict
        Derived joint-to-joint lengths: mean, sd and equal-tailed 95 % interval
        over the samples.
    identifiability_ : dict
        The default estimator's, with the samples' sd and status.
    smc_ : SMCResult
        The sampler's record (temperatures, ESS, acceptance, evidence).
    refined_ : int
        Final particles outside the near region, solved again and reweighted.
    likelihood_tau_ : float
        The curvature adjustment ``tau``.
    sampler_seconds_ : float
        Time spent sampling (after the default fit).
    warnings_ : tuple of Warning

    The attributes in ``SHARED`` are the default estimator's (``sigma_``, ``bias_``,
    ``crlb_sd_``, ``pose_``, ``residuals_``, ``frames_used_``, ...).
    """

    name = "marker-smc"
    #: fitted attributes taken from the default estimator's fit
    SHARED = ("frames_used_", "frames_skipped_", "outliers_", "sigma_", "sigma_ci_", "sigma_white_", "bias_",
              "bias_method_", "crlb_sd_", "crlb_motion_sd_", "pose_", "residuals_", "y_", "cutoff_",
              "sta_score_", "widened_", "cov_plain_", "cov_data_", "cov_artefact_", "theta_profile_",
              "fit_info_")
    settings = MarkerEstimator.settings + (
        Setting("n_particles", lambda v: count(v) and v >= 2, counted("particles", 2)),
        Setting("n_moves", count, counted("moves per stage")),
        Setting("ess_fraction", lambda v: positive(v) and v < 1, "a fraction between 0 and 1"),
        Setting("inner_iter", count, counted("iterations")),
    )

    def __init__(self, model: Model, sigma: float | None = None, cutoff: float | str | None = "auto",
                 bias_correction: str = "auto", n_boot: int = N_BOOT, robust: str = "auto",
                 rng: np.random.Generator | int | None = None, n_iter: int = 100, rate: float | None = None,
                 outlier_threshold: float | None = 8.0, theta0=None, pose0=None, n_particles: int = 200,
                 n_moves: int = 3, ess_fraction: float = 0.5, inner_iter: int = 8,
                 artefact_rms: float | None = None, noise: str = "pooled", marker_groups: dict | None = None,
                 jackknife: bool = True, placement_sd: float | None = None, on_nonconvergence: str = "error",
                 n_starts: int | str = "auto"):
        self.model = check_model(model, type(self).__name__)
        self.sigma = sigma
        self.cutoff = cutoff
        self.bias_correction = bias_correction
        self.n_boot = n_boot
        self.robust = robust
        self.rng = rng
        self.n_iter = n_iter
        self.rate = rate
        self.outlier_threshold = outlier_threshold
        self.theta0 = theta0
        self.pose0 = pose0
        self.n_particles = n_particles
        self.n_moves = n_moves
        self.ess_fraction = ess_fraction
        self.inner_iter = inner_iter
        self.artefact_rms = artefact_rms
        self.noise = noise
        self.marker_groups = marker_groups
        self.jackknife = jackknife
        self.placement_sd = placement_sd
        self.on_nonconvergence = on_nonconvergence
        self.n_starts = n_starts

    @interruptible
    def fit(self, data: MarkerData | np.ndarray, *, progress=None) -> SamplerEstimator:
        """Fit the default estimator, then sample the posterior."""
        check_settings(self)
        model = self.model
        y, rate = marker_array(model, data, self.rate, self.name)
        marker = MarkerEstimator(model, **{s.name: getattr(self, s.name) for s in MarkerEstimator.settings
                                           if hasattr(self, s.name)})
        rng = make_rng(self.rng)
        f = run_marker_fit(marker, y, rate, rng, on_bound="warn", misfit_refit=False)
        # the default estimator's bound check is about its normal estimate; the samples stay inside
        found = [w for w in marker_warnings(model, marker, f) if w.code != "outside-prior"]
        marker._publish(f, ())
        if not isinstance(self.rng, np.random.Generator):
            rng = make_rng(self.rng)
        t0 = time.perf_counter()
        res, like, post, refined = self._sample(marker, rng)
        self.marker_ = marker
        for a in self.SHARED:
            setattr(self, a, getattr(marker, a))
        self.smc_ = res
        self.likelihood_tau_ = like.tau
        self.refined_ = refined
        self.inner_iterations_ = like.n_inner
        self.gaussian_posterior_ = marker.posterior_
        self.posterior_ = post
        self.theta_ = post.mean
        self.cov_ = post.cov
        self.lengths_ = _sample_lengths(model, post)
        self.identifiability_ = dict(marker.identifiability_, table=_sample_table(model, marker, post))
        self.warnings_ = emit(found + _sample_warnings(model, marker, post, res))
        self.sampler_seconds_ = time.perf_counter() - t0
        if progress is not None:
            progress(len(y))
        return self

    def _sample(self, marker: MarkerEstimator, rng):
        """``(SMCResult, likelihood, SamplePosterior, n_refined)``: tempered SMC from the prior to the posterior."""
        model = self.model
        fit = marker.fit_info_
        tau = 1.0
        if marker.widened_ or marker.artefact_rms or marker.jackknife_.get("folded") \
                or marker.placement_["placement_sd"] > 0:
            # Newey-West, a stated artefact, the marker jackknife or the placement term widened the interval
            tau = min(float(model.n_params / np.trace(np.linalg.solve(marker.cov_plain_, marker.cov_data_))), 1.0)
        bounds = (np.array([p.prior.lower for p in model.parameters]),
                  np.array([p.prior.upper for p in model.parameters]))
        # in the marker fit's own frame (the data less its origin_): no number depends on where the data sit
        y = np.where(marker.frames_used_[:, None, None], marker.fit_.screen.y, np.nan)
        like = ProfileLikelihood(model, y, fit.theta, marker.fit_.weights.fit.pose, fit.penalty, marker.sigma_**2,
                                 marker.bias_, tau=tau, scale=np.sqrt(np.diag(marker.cov_data_)), bounds=bounds,
                                 n_iter=self.inner_iter)
        init = sample_prior(model, self.n_particles, rng)
        res = tempered_smc(like, model.log_prior, init, rng, n_moves=self.n_moves,
                           ess_fraction=self.ess_fraction, carry=like.initial_carry(self.n_particles),
                           on_stage=like.set_temperature)
        # particles outside the near region had a looser solve: refine them, and correct their
        # weights by importance sampling (the refined likelihood is never lower)
        ll, log_w = res.log_likelihood.copy(), res.log_weights.copy()
        far = np.flatnonzero(~like.near(res.particles + like.bias))
        if far.size:
            ll_far, _ = like.refine(res.particles[far], res.carry[far])
            ll_far = np.maximum(ll_far, ll[far])
            log_w[far] += ll_far - ll[far]
            ll[far] = ll_far
        res = res._replace(log_evidence=res.log_evidence + like.offset, log_likelihood=ll + like.offset,
                           log_weights=log_w - logsumexp(log_w), carry=None)
        # moved particles are correlated copies: the last reweighting's ESS is the honest count
        ess = float(res.ess[-1]) * (kish_ess(log_w) / len(log_w))
        post = SamplePosterior(model.parameter_names, res.particles, log_w,
                               log_target=ll + res.log_prior, ess=ess)
        return res, like, post, int(far.size)

    def _sampler_record(self) -> dict:
        res = self.smc_
        return {
            "particles": int(len(res.particles)),
            "ess": float(self.posterior_.ess),
            "stages": int(len(res.ess)),
            "acceptance": float(res.acceptance[-1]),
            "log_evidence": float(res.log_evidence),
            "temperatures": [float(b) for b in res.temperatures],
            "likelihood_evaluations": int(res.n_evaluations),
            "inner_iterations": int(self.inner_iterations_),
            "likelihood_tau": float(self.likelihood_tau_),
            "unique_particles": int(len(np.unique(res.particles, axis=0))),
            "refined": int(self.refined_),
            "seconds": round(float(self.sampler_seconds_), 3),
        }

    def result(self) -> FitResult:
        """The typed result: the samples' summaries, the default estimator's diagnostics, the sampler record."""
        check_fitted(self)
        r = self.marker_.result()
        extra = {n: dict(r.parameters[n].extra) for n in self.model.parameter_names}
        diagnostics = dict(r.diagnostics, identifiability=self.identifiability_["table"],
                           sampler=self._sampler_record())
        return build_result(self, self.posterior_, crlb_sd=self.crlb_sd_, extra=extra, noise=r.noise,
                            skipped=self.frames_skipped_, diagnostics=diagnostics, derived=self.lengths_,
                            arrays=dict(r.arrays, samples=self.posterior_.points,
                                        sample_weights=self.posterior_.weights))


def _sample_lengths(model: Model, post: SamplePosterior) -> dict:
    """Derived lengths: weighted mean, sd and equal-tailed 95 % interval over the samples."""
    w = post.weights
    lengths, _ = joint_distances(model, post.points)
    out = {}
    for k, (name, _) in enumerate(model.derived_lengths):
        v = lengths[:, k]
        mean = float(w @ v)
        lo, hi = weighted_quantiles(v, w, [0.025, 0.975])
        out[name] = {"value": mean, "sd": float(np.sqrt(max(w @ (v - mean) ** 2, 0.0))), "ci95": [float(lo), float(hi)]}
    return out


def _sample_table(model: Model, marker: MarkerEstimator, post: SamplePosterior) -> list:
    """The default estimator's identifiability rows with the samples' sd (which also decides 'poor')."""
    table = []
    for k, row in enumerate(marker.identifiability_["table"]):
        p = model.parameters[k]
        row = dict(row, sd=float(post.sd[k]))
        if row["status"] == "identified" and post.sd[k] > POOR_FRACTION * (p.prior.upper - p.prior.lower):
            row["status"] = "poor"
        table.append(row)
    return table


def _sample_warnings(model: Model, marker: MarkerEstimator, post: SamplePosterior, res) -> list[Warning]:
    out = []
    ci = post.credible_interval(0.95)
    for k, (before, row) in enumerate(zip(marker.identifiability_["table"], _sample_table(model, marker, post),
                                          strict=True)):
        p = model.parameters[k]
        if before["status"] == "identified" and row["status"] == "poor":
            out.append(Warning("poorly-identified", f"parameter {p.name} is poorly identified for this motion "
                               f"(posterior sd {row['sd']:.3g} {_unit(model, k)} is more than a quarter of its "
                               "prior range)", (p.name,)))
        edge = 0.01 * (p.prior.upper - p.prior.lower)
        if ci[k, 0] <= p.prior.lower + edge or ci[k, 1] >= p.prior.upper - edge:
            out.append(Warning("posterior-on-bound", f"the posterior of {p.name} reaches a bound of its prior "
                               f"[{p.prior.lower:g}, {p.prior.upper:g}]: the data do not pin it inside that "
                               "interval, which shapes the result", (p.name,)))
    if not res.completed:
        out.append(Warning("sampler-incomplete", "the sampler hit its limit of tempering stages and jumped to "
                           f"the posterior; its final effective sample size is {res.ess[-1]:.0f}"))
    if res.acceptance[-1] < 0.05:
        out.append(Warning("sampler-not-mixed", f"the sampler's moves were accepted only "
                           f"{100 * res.acceptance[-1]:.1f} % of the time at the posterior: the samples may "
                           "not have mixed"))
    return out
