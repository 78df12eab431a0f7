"""Near-singular poses: a measured check of the local bias approximation, and a fallback that holds.

Model: the joint fit estimates the geometry ``theta`` and every pose ``q_t``; its bias
``b(theta, q)`` (second order, :func:`skelid.estimators.fit.joint.smoothed_bias`) is evaluated
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
(exactly mean zero, known covariance: :mod:`skelid.estimators.uncertainty.bootstrap`), so a few refits
suffice. The covariance added to ``sigma^2 S^{-1}`` is the refits' excess spread, their Monte
Carlo error ``Cov(s - l)/B``, and the square of half the disagreement between the two
bias estimates (bootstrap and second order at ``q_tilde``): the bias estimate's own
uncertainty.

**Spread of the second-order term.** To second order the estimate's error is
``delta_1 + delta_2``, ``delta_1 = C J^T epsilon`` (what ``sigma^2 S^{-1}`` describes) and
``delta_2`` quadratic in the noise (:func:`quadratic_term_draws`); its mean is the bias above.
Near a singular pose its spread is not small: with a correction of ``b`` its sd was 0.3-0.45
``|b|`` on the case-A cells of the accuracy study (sigma 15 mm near the folded pose: 18 % of the
variance). Where the expansion's correction exceeds ``SECOND_ORDER_SPREAD`` sd, ``cov(delta_2)``
from ``N_DRAWS`` Gaussian draws (no refit) joins the interval; ``delta_1`` and ``delta_2`` are
uncorrelated. The third-order cross term ``cov(delta_1, delta_3)``, of the same order, is not included.

**Mirrored branches.** A one-axis joint whose centre ``J`` two marker distances fix (one marker
on the parent segment, ``a``, one on the child, ``b``: :func:`branch_joints`) has two solutions
per frame, mirror images across the line ``ab``. Near a straight or folded pose both fit the
markers almost equally; only the motion model tells them apart, and a stretch of frames can sit
on the mirrored branch in a local minimum of the joint fit (case A, sigma 5 mm, near-folded: 27
frames of one trial, an error of 3 sd; a fit from the true poses reaches a penalised cost lower by
about 140 sigma^2). The signed angle ``psi`` of :func:`branch_side` tells each frame's branch; the
frames on the side fewer frames take are mirrored (``q_k - 2 psi``, then a per-frame pose fit), at
every such joint at once (two neighbouring joints' stretches sit on their wrong branches together,
and mirroring one alone climbs back to the old minimum), and the joint fit repeated from there
(:func:`mirrored_start`); the refit is kept when its penalised cost is lower and every frame
of it keeps to one branch at every such joint (:func:`branch_settled`). Where the fit straddles
the singular pose as far as the data tell (near-straight, sigma 15 mm: 12-48 % of the frames on
the minority side before mirroring, 2-48 % after) the lower minima that mirroring finds lie tens
of mm from the truth, and the refit is not kept. Near the folded pose (sigma 5 mm) such stretches
held 3-20 % of a trial's frames, with errors up to 4 sd, and their refits settled on one branch at
the minimum a fit from the true poses reaches, 13-240 sigma^2 lower.

**The sd along the profile.** The delta-method sd is the information at the estimate, and near a
singular pose the information depends on where the poses lie, which move with ``theta``: along the
profile of ``theta_k`` (the poses following the fit's linear response ``-G d theta``) the sd changed
by 3-5 % per sd (case A, sigma 5 mm, near-folded). It was smallest where the estimate came out too
far from the singular pose, so the largest errors came with the smallest sd (correlation of error
and sd/CRLB -0.6 over 100 trials; an sd that did not follow the estimate would have covered 0.93
where the plug-in covered 0.91). Where a kept correction exceeds ``PROFILE_CHECK`` sd (bias and
change share the log-likelihood's third derivatives), :func:`profile_sd_ratio` evaluates the sd
at the interval's ends and the variance is raised to the larger end's (the symmetric envelope of
the interval whose every point ``theta`` satisfies ``|theta_hat - theta| <= z sd(theta)``).

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

from skelid.estimators.fit.likelihood import efficient_information, frame_terms
from skelid.estimators.uncertainty.bootstrap import Draws, as_draws, draws_bias, draws_covariance, draws_mc_covariance
from skelid.estimators.uncertainty.normal import eliminate_poses, solve_normal
from skelid.model.description import Model

#: relative change of the information about a parameter, between the fitted and the deconvolved
#: poses, beyond which the local (second-order) approximation is not trusted
POSE_SENSITIVE = 0.1
#: fixed-point steps of the indirect-inference equation after the first bootstrap (0: the bias is the
#: bootstrap's at the deconvolved poses and ``theta_hat``; on the straight-elbow cell of the accuracy
#: study, sigma 15 mm, one more step moved it by about 0.1 sd, at the cost of as many refits again)
FIXED_POINT_STEPS = 0
_N_CUTOFFS = 96  # log-spaced cutoffs tried between 1e-3 and 0.95 of the Nyquist frequency
#: a second-order bias correction above this many sd brings the spread of the second-order term into the
#: interval (its sd was 0.3-0.45 of the bias on the accuracy study's case-A cells, so below 0.5 sd it adds
#: under 5 % of the variance)
SECOND_ORDER_SPREAD = 0.5
#: draws of the second-order term (the relative Monte Carlo error of its variance is sqrt(2 / N_DRAWS))
N_DRAWS = 64
_DRAW_BLOCK = 4e6  # floats in one piece of the draws' products


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
        Variance of each estimate (e.g. from :func:`skelid.estimators.fit.joint.smoothed_bias`'s
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
        :class:`~skelid.estimators.uncertainty.bootstrap.Draws` (shifts from ``theta`` with their linear
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
        (:func:`~skelid.estimators.uncertainty.bootstrap.draws_bias`).
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
    ``C* = Var(l) + Cov(s) - Cov(l)`` (:func:`~skelid.estimators.uncertainty.bootstrap.draws_covariance`).

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


def quadratic_term_draws(model: Model, y, theta, q, sigma2: float, R=None, weights=None, n_draws: int = 64,
                         rng=None) -> np.ndarray:
    """Draws of the second-order term of the joint fit's expansion in the noise: ``(n_draws, P)``.

    For ``min ||y - f(beta)||^2 + beta^T R beta`` with ``beta = (theta, q_1..q_T)`` and
    ``y = f(beta) + epsilon``, the estimate's error is, to second order,

    .. math:: \\delta_1 = C J^\\top \\varepsilon, \\qquad
              \\delta_2 = C\\big(-\\tfrac12 J^\\top h(\\delta_1) + \\textstyle\\sum_i \\nabla^2 f_i\\,
              \\delta_1\\, r_i\\big), \\qquad C = (J^\\top J + R)^{-1},

    with ``h_i(delta) = delta^T nabla^2 f_i delta`` and ``r = epsilon - J delta_1``. Its mean is the
    second-order bias (:func:`skelid.estimators.fit.joint.smoothed_bias`); its spread is what the
    delta-method covariance ``sigma^2 S^{-1}`` leaves out. Near a singular pose the pose errors are
    large and ``h`` is far from its mean, so the spread of ``delta_2`` is no longer small. The draws
    are exact Gaussian simulations of ``delta_2``'s ``theta`` part (``epsilon`` drawn, ``delta_1``
    solved through the arrow structure, ``h`` and the second sum from each frame's second
    derivatives): no refit. ``delta_1`` and ``delta_2`` are uncorrelated (odd moments of a Gaussian
    vanish), so ``cov(delta_2)`` adds to ``sigma^2 S^{-1}``.

    Parameters
    ----------
    y : (T, M, D) float
        Markers (only the missing-marker pattern is used), NaN where missing.
    theta : (P,) float
    q : (T, Q) float
    sigma2 : float
        Noise variance (of a weighted residual with ``weights``).
    R : sparse (T*Q, T*Q), optional
        Motion-model penalty on the poses (None: none, every pose on its own).
    weights : (M,) or (T, M) float, optional
        Marker weights of a weighted fit (rows scaled by their square roots).
    n_draws : int
    rng : numpy.random.Generator, optional

    Returns
    -------
    (n_draws, P) float
        ``theta`` part of ``delta_2`` for each draw.
    """
    from skelid.estimators.fit.joint import row_weights, weighted_terms
    from skelid.model.kinematics import Workspace, stacked_jacobian

    rng = np.random.default_rng() if rng is None else rng
    y = np.asarray(y, float)
    theta = np.asarray(theta, float)
    q = np.asarray(q, float)
    P, Q, T = model.n_params, model.n_pose, len(q)
    ws = Workspace(model)
    sw = row_weights(weights, y)
    _, Jq, Jt = weighted_terms(model, theta, q, y, sw, ws)
    m = Jq.shape[1]
    mask = np.repeat(np.isfinite(y).all(axis=-1), model.dim, axis=1).astype(float)  # (T, m)
    wmask = mask if sw is None else mask * sw
    el = eliminate_poses(Jq, Jt, R)

    eps = rng.standard_normal((n_draws, T, m)) * mask * np.sqrt(sigma2)  # (K, T, m) weighted rows
    d_t, d_q = solve_normal(el, np.einsum("tip,kti->kp", Jt, eps), np.einsum("tiq,kti->ktq", Jq, eps))
    eye = np.eye(P + Q)
    step = 1e-4
    w = np.empty((n_draws, T, P + Q))
    # frames in pieces, so that the second derivatives and the draws' products stay small in memory
    size = max(1, int(_DRAW_BLOCK // max(n_draws * m * (P + Q), 1)))
    for a in range(0, T, size):
        sl = slice(a, min(a + size, T))
        n = sl.stop - sl.start
        delta = np.concatenate([np.broadcast_to(d_t[:, None, :], (n_draws, n, P)), d_q[:, sl]], axis=-1)
        Jfull = np.concatenate([Jt[sl], Jq[sl]], axis=-1)  # (n, m, P+Q)
        r1 = eps[:, sl] - np.einsum("tij,ktj->kti", Jfull, delta)
        # DJ[t, j, i, l] = d^2 f_i / d beta_j d beta_l in each frame's (theta, q_t) block, by central
        # differences of the Jacobian
        shape = (n, P + Q, P)
        Jp = stacked_jacobian(model, np.broadcast_to(theta + step * eye[:, :P], shape),
                              q[sl, None, :] + step * eye[None, :, P:], ws).reshape(n, P + Q, m, P + Q)
        Jm = stacked_jacobian(model, np.broadcast_to(theta - step * eye[:, :P], shape),
                              q[sl, None, :] - step * eye[None, :, P:], ws).reshape(n, P + Q, m, P + Q)
        DJ = (Jp - Jm) / (2.0 * step) * wmask[sl, None, :, None]  # weighted rows
        Hd = np.einsum("tjil,ktl->ktij", DJ, delta)  # (K, n, m, P+Q): nabla^2 f_i delta
        h = np.einsum("ktij,ktj->kti", Hd, delta)  # (K, n, m)
        w[:, sl] = -0.5 * np.einsum("tij,kti->ktj", Jfull, h) + np.einsum("ktij,kti->ktj", Hd, r1)
    return solve_normal(el, w[..., :P].sum(axis=1), w[..., P:])[0]


def second_order_covariance(draws) -> np.ndarray:
    """Covariance ``(P, P)`` of the second-order term from :func:`quadratic_term_draws`' draws."""
    d = np.atleast_2d(draws)
    return np.atleast_2d(np.cov(d, rowvar=False)) if len(d) > 1 else np.zeros((d.shape[1],) * 2)


class BranchJoint(NamedTuple):
    """A one-axis joint whose centre two distance equations fix (see :func:`branch_joints`)."""

    dof: int  # pose coordinate of the joint's angle
    segment: int  # the joint's (child) segment
    parent_marker: int  # the one marker of the parent segment
    child_marker: int  # the one marker of the child segment


def branch_joints(model: Model) -> tuple[BranchJoint, ...]:
    """One-axis (revolute, hinge) joints whose parent and child segment carry one marker each.

    The joint centre ``J`` is then fixed by two distances, ``|J - a|`` to the parent's marker
    and ``|J - b|`` to the child's: two circles (spheres about an axis) that meet in two points,
    mirror images across the line ``ab``. Where ``a``, ``J`` and ``b`` nearly line up (a straight
    or folded joint) both solutions fit the markers almost equally and only the motion model
    tells them apart, so a stretch of frames can settle on the mirrored branch: a local minimum
    of the joint fit (see :func:`branch_side`). A segment with more markers fixes its own pose,
    and the joint has one solution.
    """
    ms = np.asarray(model.marker_segment)
    parent = model.parent_index
    out = []
    for k, d in enumerate(model.dofs):
        c = d.segment
        p = int(parent[c])
        if d.kind != "R" or d.coupled or p < 0 or model.segments[c].joint.type not in ("revolute", "hinge"):
            continue
        a, b = np.flatnonzero(ms == p), np.flatnonzero(ms == c)
        if len(a) == 1 and len(b) == 1:
            out.append(BranchJoint(k, c, int(a[0]), int(b[0])))
    return tuple(out)


def branch_side(model: Model, theta, q, joint: BranchJoint, ws=None) -> np.ndarray:
    """Signed angle ``psi`` (T,) of the joint from its nearest singular pose (radians, in (-pi/2, pi/2]).

    With ``u = a - J`` (parent's marker) and ``v = b - J`` (child's marker), projected on the
    plane normal to the joint's axis, ``psi`` is the angle from ``u`` to ``v`` less the nearest
    multiple of ``pi`` (0: folded, the markers on one side; ``pi``: straight), oriented so that
    it grows with the joint's coordinate. Its sign tells the branch; ``q_k - 2 psi`` is the
    joint's mirrored angle (the child's marker reflected across the line ``J a``).
    """
    return _fold(_branch_angle(model, theta, q, joint, ws))[0]


def _fold(ang):
    """``psi`` of :func:`branch_side` from the signed angle, and whether the straight pose is the nearer one."""
    turns = np.round(ang / np.pi)
    return ang - np.pi * turns, turns != 0


def _branch_angle(model: Model, theta, q, joint: BranchJoint, ws=None) -> np.ndarray:
    """Signed angle (T,) from the parent's to the child's marker about the joint, in (-pi, pi] (:func:`branch_side`)."""
    from skelid.model.kinematics import joint_positions, marker_jacobian

    q = np.asarray(q, float)
    X, Jq, _ = marker_jacobian(model, theta, q, ws)  # (T, M, D), (T, M, D, Q)
    centre = joint_positions(model, theta, q, ws)[:, joint.segment]
    u = X[:, joint.parent_marker] - centre
    v = X[:, joint.child_marker] - centre
    dv = Jq[:, joint.child_marker, :, joint.dof]  # (T, D): the child's marker moves about the axis
    if model.dim == 2:
        sense = np.sign(v[:, 0] * dv[:, 1] - v[:, 1] * dv[:, 0])
        ang = sense * np.arctan2(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0], np.sum(u * v, axis=-1))
    else:
        n = np.cross(v, dv)
        n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
        u = u - n * np.sum(n * u, axis=-1, keepdims=True)
        v = v - n * np.sum(n * v, axis=-1, keepdims=True)
        ang = np.arctan2(np.sum(n * np.cross(u, v), axis=-1), np.sum(u * v, axis=-1))
    return ang


def minority_branch(model: Model, theta, q, joint: BranchJoint, used, ws=None, tol: float = 0.0):
    """Frames (of those ``used``) on the side of their nearest singular pose that fewer of its frames take.

    The frames nearer the folded pose (the markers on one side of the joint) and those nearer the
    straight pose are taken apart: a motion that swings from one to the other changes the sign of
    ``psi`` where it passes 90 degrees from both, on no wrong branch.

    A frame within ``tol`` (radians) of the singular pose is on neither side: there the noise
    decides the sign of ``psi``.

    Returns
    -------
    flip : (T,) bool
        Those frames (none when the used frames near each singular pose are all on one side).
    psi : (T,) float
        :func:`branch_side`.
    """
    psi, straight = _fold(_branch_angle(model, theta, q, joint, ws))
    side = np.sign(psi)
    used = np.asarray(used, bool) & (np.abs(psi) > tol)
    flip = np.zeros(len(psi), dtype=bool)
    for near in (straight, ~straight):
        u = used & near
        major = 1.0 if np.sum(side[u] > 0) >= np.sum(side[u] < 0) else -1.0
        flip |= u & (side != major)
    return flip, psi


def mirrored_start(model: Model, theta, q, y, joints, used, ws=None):
    """Poses with every joint's minority branch mirrored, or None when each joint's used frames are on one side.

    For each of ``joints``, the frames (of those ``used``) on the side of its singular pose that
    fewer frames take (:func:`minority_branch`) get the mirrored angle ``q_k - 2 psi``
    (:func:`branch_side`); every frame so changed then gets a per-frame pose fit at ``theta``
    from there; the other frames keep ``q``. All joints are mirrored at once: near a folded
    chain the stretches of two neighbouring joints sit on their wrong branches together (the
    marker between them pulls both), and a refit with one of them mirrored climbs back to the
    old minimum (case A, sigma 5 mm, near-folded). A joint fit from these poses under the same
    motion model tells whether the stretches sat on the wrong branch: its penalised cost is then
    lower, and its poses keep to one branch (:func:`branch_settled`).

    Parameters
    ----------
    theta : (P,) float
    q : (T, Q) float
    y : (T, M, D) float
    joints : BranchJoint or sequence of BranchJoint
    used : (T,) bool

    Returns
    -------
    (T, Q) float or None
    """
    joints = (joints,) if isinstance(joints, BranchJoint) else tuple(joints)
    return _mirror_frames(model, theta, q, y, [(j, *minority_branch(model, theta, q, j, used, ws)) for j in joints],
                          ws)


def _mirror_frames(model: Model, theta, q, y, chosen, ws=None):
    """``q`` with each ``(joint, flip (T,) bool, psi (T,))`` of ``chosen`` mirrored in its flipped frames
    (``q_k - 2 psi``), and every changed frame a per-frame pose fit at ``theta`` from there; None if none."""
    from skelid.estimators.fit.pose import fit_pose

    start = np.array(q, float)
    changed = np.zeros(len(start), dtype=bool)
    for joint, flip, psi in chosen:
        start[flip, joint.dof] -= 2.0 * psi[flip]
        changed |= flip
    if not changed.any():
        return None
    start[changed] = fit_pose(model, theta, y[changed], start[changed], ws=ws)[0]
    return start


def keeps_near_singular(model: Model, theta, q, joint: BranchJoint, used, ws=None,
                        limit: float = np.pi / 4) -> bool:
    """Whether every used frame of ``joint`` lies within ``limit`` (radians) of one and the same singular pose.

    Only such a joint can sit on its mirrored branch as a whole: a motion that takes the joint far from
    its singular poses has one branch that fits (:func:`assigned_branch_start`).
    """
    psi, straight = _fold(_branch_angle(model, theta, q, joint, ws))
    used = np.asarray(used, bool)
    return bool(used.any() and np.all(np.abs(psi[used]) <= limit)
                and (straight[used].all() or not straight[used].any()))


def assigned_branch_start(model: Model, theta, q, y, joints, signs, used, ws=None):
    """Poses with every used frame of each joint on the branch ``signs`` names, or None where none moves.

    :func:`mirrored_start` mirrors each joint's minority stretch, toward the branch most frames already
    take. A trial can sit on the mirrored branch as a whole (near the folded pose the chain can zig-zag
    the other way, and the geometry that fits that best lies tens of sd from the truth), or take the
    wrong side for most of its frames: here each joint's side is given, ``signs[i]`` (+1 or -1) the sign
    of :func:`branch_side` for ``joints[i]``, and every used frame on the other side gets the mirrored
    angle ``q_k - 2 psi`` and a per-frame pose fit at ``theta`` from there.
    """
    used = np.asarray(used, bool)
    chosen = []
    for joint, sign in zip(joints, signs, strict=True):
        psi = branch_side(model, theta, q, joint, ws)
        chosen.append((joint, used & (np.sign(psi) == -sign), psi))
    return _mirror_frames(model, theta, q, y, chosen, ws)


def branch_settled(model: Model, theta, q, joints, used, ws=None, before=None, sigma: float = 0.0) -> bool:
    """Whether every used frame is on one side of its nearest singular pose, at each joint.

    A refit from :func:`mirrored_start` that lowers the penalised cost and settles so is kept: the
    mirrored frames were a stretch on the wrong branch (near the folded pose, case A, sigma 5 mm:
    every refit that reached the minimum a fit from the true poses reaches left no frame on the
    minority side). One that still leaves frames on both sides is a motion that straddles the
    singular pose as far as the data tell, and a lower cost found by mirroring is no evidence of a
    wrong branch (near-straight, sigma 15 mm: 12-48 % of the frames on the minority side before
    mirroring, 2-48 % after, and lower costs found tens of mm from the truth); it is not kept.

    Parameters
    ----------
    before : (theta (P,), q (T, Q)), optional
        The fit before mirroring: then every used frame must also stay nearest the same singular
        pose as there (a mirrored stretch does not swing frames across to the other singular pose;
        near-straight, sigma 15 mm, a refit that swung 11 frames of the wrist 90 degrees, to the
        folded side, settled 47 mm from the truth).
    sigma : float
        The markers' noise level: a frame within ``sigma / |b|`` of the singular pose (``|b|`` the child's
        marker's distance from the joint centre), one angular noise sd, is on neither branch
        (:func:`minority_branch`).
    """
    joints = (joints,) if isinstance(joints, BranchJoint) else tuple(joints)
    used = np.asarray(used, bool)
    for j in joints:
        tol = sigma / max(float(np.linalg.norm(model.markers[j.child_marker].position)), 1e-300)
        if minority_branch(model, theta, q, j, used, ws, tol)[0].any():
            return False
        if before is not None:
            now, was = (_nearest_straight(model, th, qq, j, ws) for th, qq in ((theta, q), before))
            if np.any((now != was) & used):
                return False
    return True


def _nearest_straight(model: Model, theta, q, joint: BranchJoint, ws=None) -> np.ndarray:
    """(T,) bool: the joint's nearest singular pose is the straight one (else the folded one)."""
    return _fold(_branch_angle(model, theta, q, joint, ws))[1]


#: a kept second-order correction above this many sd has the sd evaluated along the profile as well
#: (:func:`profile_sd_ratio`); below it the information hardly changes over the interval (the bias and the
#: change share the third derivatives of the log-likelihood), and the check costs two normal matrices per
#: parameter
PROFILE_CHECK = 0.25
#: the interval's half-width in sd at whose ends the sd is evaluated (95 %)
PROFILE_Z = 1.959964


def _schur(model: Model, theta, q, y, sw, R, ws=None):
    """``S`` (P, P), the information about ``theta`` with the poses eliminated, and ``G`` (T, Q, P)."""
    from skelid.estimators.fit.joint import weighted_terms

    _, Jq, Jt = weighted_terms(model, theta, q, y, sw, ws)
    el = eliminate_poses(Jq, Jt, R)
    return el.S, el.G


def profile_sd_ratio(model: Model, y, theta, q, sigma: float, R=None, weights=None, z: float = PROFILE_Z,
                     ws=None) -> np.ndarray:
    """How much larger each parameter's sd is at the ends of its interval than at the estimate: ``(P,)``, >= 1.

    The delta-method sd ``sigma sqrt((S^{-1})_kk)`` is the information at the estimate. Near a
    singular pose the information depends on where the poses lie, and the poses move with
    ``theta``: along the profile of ``theta_k`` (the other parameters at their conditional
    estimates, ``d theta = t C_{:k} / C_kk``, the poses following the joint fit's linear response,
    ``d q_t = -G_t d theta``), the sd changes by 3-5 % per sd near the folded pose (case A, sigma
    5 mm). It is smallest where the estimate came out too far from the singular pose, so the
    estimates with the largest errors got the smallest sd (correlation of error and sd/CRLB -0.6 over
    100 trials): an interval whose truth lies at either end must use the sd there. ``S`` is
    evaluated at ``t = -z sd_k`` and ``t = +z sd_k``; the ratio is the larger end's sd over the
    estimate's (the symmetric envelope of the interval whose every point ``theta`` satisfies
    ``|theta_hat - theta| <= z sd(theta)``).

    Parameters
    ----------
    y : (T, M, D) float
        Markers used by the fit (NaN where missing or left out).
    theta : (P,) float
    q : (T, Q) float
    sigma : float
        Noise level (of a weighted residual with ``weights``).
    R : sparse (T*Q, T*Q), optional
        The fit's motion-model penalty (None: every pose on its own).
    weights : (M,) or (T, M) float, optional
        Marker weights of a weighted fit.
    z : float
        Half-width of the interval in sd.

    Returns
    -------
    (P,) float
    """
    from skelid.estimators.fit.joint import row_weights

    y = np.asarray(y, float)
    theta = np.asarray(theta, float)
    q = np.asarray(q, float)
    sw = row_weights(weights, y)
    S, G = _schur(model, theta, q, y, sw, R, ws)
    C = np.linalg.inv(0.5 * (S + S.T))
    sd = sigma * np.sqrt(np.diag(C))
    ratio = np.ones(len(theta))
    for k in range(len(theta)):
        direction = C[:, k] / C[k, k]  # the profile of theta_k: the others at their conditional estimates
        for sign in (-1.0, 1.0):
            d = sign * z * sd[k] * direction
            S_end, _ = _schur(model, theta + d, q - np.einsum("tqp,p->tq", G, d), y, sw, R, ws)
            try:
                sd_end = sigma * np.sqrt(np.linalg.inv(0.5 * (S_end + S_end.T))[k, k])
            except np.linalg.LinAlgError:
                continue
            ratio[k] = max(ratio[k], sd_end / sd[k])
    return ratio


def profile_covariance(ratio, plain) -> np.ndarray:
    """Covariance ``(P, P)`` that takes each variance of ``plain`` to ``ratio^2`` times it (diagonal, >= 0)."""
    r = np.maximum(np.asarray(ratio, float), 1.0)
    return np.diag((r**2 - 1.0) * np.diag(np.asarray(plain, float)))
