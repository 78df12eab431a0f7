"""Leave-one-marker-out: how much one marker can move the estimate.

A skin marker's artefact is shared by all its frames, so the frames of one
marker are not independent pieces of evidence: the marker is the unit (the
cluster). Deleting marker ``m`` and refitting gives ``theta_(-m)``, and
``d_m = theta_(-m) - theta_hat`` is the replicate's shift.

**Leverage-corrected replicates (CR2).** The plain jackknife
``sum_m d_m d_m^T`` is the cluster-robust covariance of type CR3: in the linear
model ``d_m = -(S - S_m^{own})^{-1} X_m^T e_m``, the marker's residuals inflated
by ``(I - H_mm)^{-1}``. When deleting a marker removes most of the information
about some direction (a high-leverage marker: the heel marker that alone fixes
the ankle in a squat), that factor is large and the shift mostly measures the
replicate's own loss of information: the fit without the marker is poorly
determined and every other marker's error moves it far, which is not evidence
that the full fit is off by as much. Bell and McCaffrey's bias-reduced form
(CR2) inflates the residuals by ``(I - H_mm)^{-1/2}`` instead, which is
unbiased under white noise whatever the leverage. In parameter space it is a
shrinkage of each replicate:

.. math:: c_m = S^{-1/2} \\big(S^{-1/2} S_{(-m)} S^{-1/2}\\big)^{1/2} S^{1/2} \\, d_m ,
          \\qquad V_J = \\textstyle\\sum_m c_m c_m^\\top ,

with ``S`` the information of the fit and ``S_(-m)`` that without marker ``m``
(``X_m^T f(H_mm) = f(S_m^{own} S^{-1}) X_m^T`` turns the observation-space
factor into this ``P x P`` one). A marker that keeps the fraction ``r`` of the
information in a direction has its shift scaled by ``sqrt(r)`` there; a marker
the estimate hardly depends on (``r`` near 1) keeps its shift. ``V_J`` is the
cluster-robust covariance with markers as clusters: it does not assume that the
markers' errors are white or equal, and when one marker's artefact pulls the
estimate, deleting it moves the estimate back, and ``V_J`` grows.

References: R. M. Bell and D. F. McCaffrey (2002), Bias reduction in standard
errors for linear regression with multi-stage samples, Survey Methodology 28;
J. E. Pustejovsky and E. Tipton (2018), Small-sample methods for cluster-robust
variance estimation and hypothesis testing in fixed effects models, J. Business &
Economic Statistics 36.

**One-step form.** Refitting ``M`` times is expensive; one Gauss-Newton step
from the full fit with marker ``m`` deleted is accurate to first order in the
marker's pull (within 20 % of the literal refits' shifts in the tests):

.. math:: \\theta_{(-m)} - \\hat\\theta \\approx S_{(-m)}^{-1} \\textstyle\\sum_t g_{t,(-m)}, \\qquad
          S_{(-m)} = \\sum_t K_{t,(-m)}^\\top A_{t,(-m)} ,

with ``g_t`` the per-frame reduced scores and ``A_t`` the influence rows of
the motion-model fit (:func:`skelid.estimators.fit.joint.smoothed_frame_scores`,
:func:`skelid.estimators.fit.joint.influence_rows`) recomputed with the marker's
rows removed (so its poses' projection is the one of the deleted fit).
:func:`literal_jackknife` refits instead, as a check.

**Where the one step is not enough.** The step extrapolates the quadratic model of
the cost; when deleting the marker leaves a parameter weakly identified the step can
be long and the model wrong over it. Each replicate is therefore checked: along the
joint step ``s = (dq, dtheta)`` (the replicate and its poses' response) the cost
with the marker deleted falls by ``C(0) - C(s)`` (one evaluation of the markers'
positions), against the decrease ``g^T s`` its quadratic model predicts. Only a long
replicate is checked: one whose length ``dtheta^T S_(-m) dtheta / sigma^2`` exceeds what
white noise reaches (``chi^2_P`` at ``1 - LONG_STEP_LEVEL``); a shorter one lies where the
fit's own interval already relies on the linearisation. With the
ratio outside ``[LINEAR_RATIO, 1/LINEAR_RATIO]`` the replicate is the literal refit
(warm start from the full fit, at most ``REFIT_ITER`` iterations); a refit that does
not converge or ends on a prior bound leaves that marker without a replicate (as an
essential one), and a warning names it. On a well-identified trial the ratios are
within a few per cent of 1 and nothing is refitted.

**A parameter held on its prior's bound.** Where the fit's estimate of a parameter sits on a
bound of its prior (a scale the trial does not inform, held at its limit), the replicates are those
of the other parameters with it held there: no replicate moves it (its shift is 0), and a refit
fails only when it takes another parameter to a bound. Left free, the one-step replicate would
cross the bound and fail its cost check, and every refit, ending where the fit did, would count
as one that found no estimate: no jackknife, after the cost of a refit per marker. The artefact's
effect (below) is still that on every parameter, the held one included: the artefact moves it too.

**A marker the model cannot do without.** When deleting a marker leaves a
parameter (nearly) without information (``S_(-m)`` has a direction with less
than ``ESSENTIAL`` of the full information), that marker has no jackknife
replicate: with fewer than ``MIN_MARKERS`` replicates the jackknife is not
available and nothing is folded.

**What white noise alone would give.** With few markers of unequal
information the jackknife is itself noisy, and with the poses profiled out and
a motion-model penalty CR2's exact unbiasedness holds only approximately. Its
distribution under white noise of the fit's level is therefore simulated
through the linearised fit: for draws ``e`` of white noise,

.. math:: \\delta_m(e) = S_{(-m)}^{-1} \\textstyle\\sum_t A_{t,(-m)}^\\top e_t - S^{-1} \\sum_t A_t^\\top e_t

are the replicates' shifts to first order, and ``V_J(e)`` the covariance of
their leverage-corrected forms (``N_NULL`` draws; no refit, only the influence
rows already at hand).

**Folding into the interval** (:func:`fold`). ``E_0``, the mean of ``V_J(e)``, is
what the markers' spread would be under white noise; ``W = E_0^{-1/2} V_J E_0^{-1/2}``
is the spread in its units. The test: the largest eigenvalue of ``W`` exceeds the 95 %
point of the largest such eigenvalue under white noise (the markers disagree beyond
chance). White noise passes it in about one fit in twenty; a fit that does not pass
keeps its covariance.

A fit that passes is widened in two parts.

* *The artefact the disagreement implies, in every direction.* With a dozen markers the
  eigenvalues of ``W`` scatter widely about their mean even where every marker carries
  an artefact of one size: the directions with the small ones are not free of artefact,
  they are where this sample of markers happened to agree. Adding only the directions
  that pass the test left 3-D joint-centre regions with one direction far too narrow (a
  simulated arm with skin artefact: region coverage 0.59-0.73 at 95 %, per-axis 0.86).
  The skin artefact is therefore given a form: each marker coordinate a smooth function
  of the adjacent joint angles with independent coefficients, root-mean-square ``a``
  (:mod:`skelid.estimators.checks.artefact`), which moves the estimate by
  ``a^2 sum_m A_m`` (``A_m``: marker ``m``'s share at unit size). Its size is what the
  replicates show: to first order the leverage-corrected jackknife's mean is
  ``E_0 + a^2 sum_{m replicated} A_m``, so
  ``a^2 = (tr W - r)_+ / tr(E_0^{-1/2} sum_{m replicated} A_m E_0^{-1/2})`` (``r`` the
  rank of ``E_0``), and ``a^2 sum_m A_m`` over *every* marker is added: a marker that has
  no replicate (one the fit cannot do without) carries the same artefact as the others.
* *What that form does not explain.* Under that artefact the replicates' expected spread
  is ``M = I + a^2 E_0^{-1/2} (sum_{m replicated} A_m) E_0^{-1/2}`` (in ``W``'s units), and
  a sample of a dozen markers scatters about it as white noise's does about ``I``. In the
  eigen-directions of ``M^{-1/2} W M^{-1/2}`` whose eigenvalue ``mu`` exceeds the test's
  95 % point, ``(mu - 1)`` times ``M``'s variance in that direction is added: one marker
  whose artefact pulls the estimate more than the others' adds what its deletion reveals,
  and the artefact's own sampling scatter is not counted twice.

The estimated ``a`` is reported (``artefact_rms`` of the summary).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.stats import chi2

from skelid._linalg import psd_sqrt
from skelid.estimators.checks.artefact import marker_artefact_terms
from skelid.estimators.fit.joint import _banded_solver, joint_fit, penalty_band, row_weights
from skelid.estimators.fit.likelihood import frame_terms, pose_information
from skelid.model.description import Model
from skelid.model.kinematics import Workspace, marker_positions

#: deleting a marker that leaves less than this fraction of the information in some direction
#: makes the fit without it meaningless: that marker has no replicate
ESSENTIAL = 0.05
#: fewest replicates for a jackknife
MIN_MARKERS = 3
#: level of the test of the markers' disagreement against white noise
FOLD_LEVEL = 0.05
#: the widening is named in a warning only where its systematic part could move some estimate by at least
#: this many of its sd (the misfit test's effect size, :data:`skelid.estimators.checks.misfit.MISFIT_EFFECT`):
#: on exactly fitting data the markers' disagreement was significant against the rounding and moved an
#: estimate by 5e-11
JACKKNIFE_EFFECT = 0.5
#: white-noise draws that give the jackknife's null distribution
N_NULL = 100
#: a one-step replicate is kept when the cost, with the marker deleted, falls along the step by this
#: fraction (or more) of what the quadratic model of the step predicts, and by at most its inverse
LINEAR_RATIO = 0.8
#: a one-step replicate is checked only when its length ``d^T S_(-m) d / sigma^2`` exceeds the
#: ``1 - LONG_STEP_LEVEL`` point of chi-square with P degrees of freedom (white noise's reach)
LONG_STEP_LEVEL = 0.001
#: iterations of the literal refit that replaces a one-step replicate whose linearisation fails (the
#: lower-limb fits take 50-65 from the nominal start; refits that start 10-30 mm from their estimate
#: took up to 50 and more, and a cap of 50 dropped converging refits as if they had no estimate)
REFIT_ITER = 600
#: ... run in stretches of this many, each a warm start from the last (a refit on a bound stops there)
REFIT_CHUNK = 50
#: the literal refit stops when a step moves no parameter by more than this fraction of its sd ...
REFIT_STEP_TOL = 1e-3
#: ... and lowers the cost by less than this fraction (as the bootstrap's refits do; the joint fit's
#: default, 1e-10, kept the walk's refits going two to four iterations past the step rule, moving
#: the replicates by less than 1e-4 sd)
REFIT_TOL = 1e-7
#: directions of E_0 (whitened by the fit's information) below this fraction of its largest eigenvalue are
#: ones no replicate moves (see :func:`null_factor`)
NULL_RANK_TOL = 1e-10
_CHUNK = 25  # white-noise draws made at once
_DRAWS_KEPT = 16_000_000  # white-noise numbers (128 MB) kept for all deletions; a longer trial draws them again


class Jackknife(NamedTuple):
    shifts: np.ndarray  # (M, P) theta_(-m) - theta_hat; NaN for markers without a replicate
    replicate: np.ndarray  # (M,) bool: markers with a replicate
    cov: np.ndarray | None  # (P, P) V_J = sum_m c_m c_m^T, or None when not available
    null_mean: np.ndarray | None = None  # (P, P) E_0: V_J's mean under white noise of the fit's level
    null_max: float = float("nan")  # 95 % point of the largest eigenvalue of E_0^{-1/2} V_J(e) E_0^{-1/2}
    status: tuple = ()  # (M,) per marker: "one-step", "refitted", "refit failed", "essential" or "missing"
    ratio: np.ndarray | None = None  # (M,) actual / predicted cost decrease along the one-step replicate
    corrected: np.ndarray | None = None  # (M, P) leverage-corrected replicates c_m (CR2); NaN without one
    transform: np.ndarray | None = None  # (M, P, P) c_m = transform[m] @ shifts[m]; NaN without a replicate
    factor: np.ndarray | None = None  # (P, r) B with B B^T = E_0 on E_0's range (:func:`null_factor`)
    # (M, P, P) each marker's share of the covariance a skin artefact of unit rms adds, every parameter
    # free (:func:`skelid.estimators.checks.artefact.marker_artefact_terms`), None where not computed
    artefact: np.ndarray | None = None

    @property
    def available(self) -> bool:
        return self.cov is not None


def _terms(model, y, theta, pose, R, weights):
    """Weighted residuals and Jacobians of a fit: ``(T, M*D)``, ``(T, M*D, Q)``, ``(T, M*D, P)``."""
    r, Jq, Jt = frame_terms(model, theta, pose, y)
    sw = row_weights(weights, y)
    if sw is not None:
        r, Jq, Jt = r * sw, Jq * sw[..., None], Jt * sw[..., None]
    return r, Jq, Jt


def _influence(r, Jq, Jt, pose, R, R_band=None, step=False):
    """Influence rows ``A``, information ``S`` and reduced score of a fit (see the module notes).

    With ``step``, also the pose part of the Gauss-Newton step: ``(dq0 (T, Q), G (T, Q, P))`` with the
    step's poses ``dq = dq0 - G dtheta``, and the pose gradient ``b (T*Q,)`` (``Jq^T r - R q``).
    """
    T, _, Q = Jq.shape
    P = Jt.shape[-1]
    Hqq = pose_information(Jq)
    Hqt = np.matmul(np.swapaxes(Jq, -1, -2), Jt)
    b = np.einsum("tiq,ti->tq", Jq, r).reshape(T * Q)
    if R is not None:
        b = b - R @ pose.ravel()
    if R is None:
        X = np.linalg.pinv(Hqq, hermitian=True) @ np.concatenate([Hqt, b.reshape(T, Q, 1)], axis=-1)
    else:
        X = _banded_solver(Hqq, R, R_band)(np.column_stack([Hqt.reshape(T * Q, P), b])).reshape(T, Q, P + 1)
    G, dq0 = X[..., :P], X[..., P]
    A = Jt - Jq @ G
    A2 = A.reshape(-1, P)
    score = r.ravel() @ A2
    if R is not None:
        score = score + (R @ pose.ravel()) @ G.reshape(-1, P)
    if step:
        return A, Jt.reshape(-1, P).T @ A2, score, (dq0, G, b)
    return A, Jt.reshape(-1, P).T @ A2, score


def _cost_ratio(model, y, theta, pose, R, sw, m, dtheta, score, pose_step, free=None) -> float:
    """Actual over predicted decrease of the cost (marker ``m`` deleted) along the Gauss-Newton step.

    The step is the joint one, ``(dq, dtheta)``: ``dtheta`` the one-step replicate and
    ``dq = dq0 - G dtheta`` the poses' response, so the cost at its end is one evaluation of the
    markers' positions. Its quadratic model predicts the decrease ``g^T s = b^T dq0 + score^T dtheta``
    (``g`` the gradient, ``s`` the step, ``b`` the poses' gradient); a ratio near 1 shows the
    linearisation holding over the replicate's shift. ``free``: the parameters ``dtheta`` moves
    (``(P,) bool``; the others held), all by default.
    """
    dq0, G, b = pose_step
    T = dq0.shape[0]
    pred = float(b @ dq0.ravel() + score @ dtheta)
    if not np.isfinite(pred) or pred <= 0.0:
        return float("nan")
    mask = np.isfinite(y).all(axis=-1)
    mask[:, m] = False
    y0 = np.where(mask[..., None], y, 0.0)

    def cost(th, q):
        r = ((y0 - marker_positions(model, th, q)) * mask[..., None]).reshape(T, -1)
        if sw is not None:
            r = r * sw
        c = float(np.sum(r**2))
        if R is not None:
            c += float(q.ravel() @ (R @ q.ravel()))
        return c

    moved = np.array(theta, float)
    moved[slice(None) if free is None else free] += dtheta
    return (cost(theta, pose) - cost(moved, pose + dq0 - G @ dtheta)) / pred


def held_on_bound(model: Model, theta) -> np.ndarray:
    """``(P,) bool``: the parameters whose estimate sits on a bound of its prior (within 1e-6 of its width)."""
    lower, upper, span = _prior_box(model)
    return (theta - lower <= 1e-6 * span) | (upper - theta <= 1e-6 * span)


def _prior_box(model: Model):
    lower = np.array([p.prior.lower for p in model.parameters], float)
    upper = np.array([p.prior.upper for p in model.parameters], float)
    return lower, upper, np.where(np.isfinite(upper - lower), upper - lower, 1.0)


def _refit(model, y, theta, pose, R, weights, m, ws=None, held=None):
    """The literal replicate ``theta_(-m) - theta`` (warm start), or None when it does not hold.

    The refit starts from the full fit's estimate and poses, keeps its motion-model penalty, and
    holds when it converges within ``REFIT_ITER`` iterations and ends off the prior bounds (a refit
    that wanders to a bound has found no estimate without the marker); the parameters ``held``
    (``(P,) bool``) already sat on a bound in the fit and may stay there. ``ws``: the model's workspace.
    """
    lower, upper, _ = _prior_box(model)
    held = np.zeros(len(theta), bool) if held is None else held
    ym = np.array(y, float)
    ym[:, m] = np.nan
    th, q = theta, pose
    # in stretches of REFIT_CHUNK iterations, so that a refit that has reached a bound stops there
    for k in range(0, REFIT_ITER, REFIT_CHUNK):
        f = joint_fit(model, ym, th, q, n_iter=min(REFIT_CHUNK, REFIT_ITER - k), bounds=(lower, upper), penalty=R,
                      weights=weights, tol=REFIT_TOL, step_tol=REFIT_STEP_TOL, ws=ws, summary=False)
        if not np.all(np.isfinite(f.theta)):
            return None
        if np.any(held_on_bound(model, f.theta) & ~held):
            return None
        if f.converged:
            return f.theta - theta
        th, q = f.theta, f.pose
    return None


def marker_jackknife(model: Model, y, theta, pose, R=None, sigma: float = 1.0,
                     rng: np.random.Generator | None = None, weights=None) -> Jackknife:
    """One-step leave-one-marker-out replicates and their covariance.

    Parameters
    ----------
    y : (T, M, D) float
        Markers the fit used (NaN where missing or in frames not used).
    theta : (P,) float
        The fit's (uncorrected) estimate.
    pose : (T, Q) float
        The fit's poses.
    R : sparse (T*Q, T*Q), optional
        The fit's motion-model penalty.
    sigma : float
        White-noise level of the null distribution.
    rng : numpy.random.Generator, optional
        For the white-noise draws (default ``default_rng(0)``).
    weights : (M,) or (T, M) float, optional
        The fit's marker weights.

    Returns
    -------
    Jackknife
        Parameters held on a prior bound (:func:`held_on_bound`) have no shift and no spread.
    """
    y = np.asarray(y, float)
    held = held_on_bound(model, theta)
    if held.all():
        M, P = y.shape[1], model.n_params
        return Jackknife(np.full((M, P), np.nan), np.zeros(M, bool), None, status=("held",) * M)
    jk = _free_jackknife(model, y, theta, pose, R, sigma, rng, weights, held)
    return jk if not held.any() else _with_held(jk, ~held)


def _with_held(jk: Jackknife, free) -> Jackknife:
    """A jackknife of the free parameters given for all of them: zero where held (no replicate moves them)."""
    P, f = len(free), np.flatnonzero(free)

    def last(a):  # (..., n) -> (..., P)
        out = np.zeros(a.shape[:-1] + (P,))
        out[..., f] = a
        return out

    def square(a):  # (..., n, n) -> (..., P, P)
        if a is None:
            return None
        out = np.zeros(a.shape[:-2] + (P, P))
        out[..., f[:, None], f] = a
        return out

    shifts, corrected, transform = last(jk.shifts), last(jk.corrected), square(jk.transform)
    for a in (shifts, corrected, transform):
        a[~jk.replicate] = np.nan
    return jk._replace(shifts=shifts, cov=square(jk.cov), null_mean=square(jk.null_mean), corrected=corrected,
                       transform=transform, factor=None if jk.factor is None else last(jk.factor.T).T)


def _free_jackknife(model, y, theta, pose, R, sigma, rng, weights, held) -> Jackknife:
    """:func:`marker_jackknife` with the parameters ``held`` fixed: its arrays over the others only."""
    T, M, D = y.shape
    free = ~held
    P = int(free.sum())
    # the kinematics once: deleting marker m only zeroes its D rows of every frame (as frame_terms
    # does for a missing marker), so each deletion reuses the full fit's residuals and Jacobians
    r, Jq, Jt_all = _terms(model, y, theta, pose, R, weights)
    Jt = Jt_all[..., free]
    sw = row_weights(weights, y)
    R_band = None if R is None else penalty_band(R, model.n_pose)
    # every parameter free for the artefact's effect (a held one too: the artefact moves it as well); the
    # pose solve is column by column, so the free parameters' rows are these rows' columns
    A_all, S_all, _ = _influence(r, Jq, Jt_all, pose, R, R_band)
    # nothing held (the usual case): the same arrays, no copy
    A, S = (A_all, S_all) if free.all() else (np.ascontiguousarray(A_all[..., free]), S_all[np.ix_(free, free)])
    S_isqrt = _inv_sqrt(S)
    S_sqrt = psd_sqrt(S)
    rng = np.random.default_rng(0) if rng is None else rng
    seed = int(rng.integers(2**32))
    chunks = [(c, min(_CHUNK, N_NULL - c)) for c in range(0, N_NULL, _CHUNK)]
    # the same white-noise draws for every call; kept when they fit in memory, else drawn again
    keep = N_NULL * A.shape[0] * A.shape[1] <= _DRAWS_KEPT
    kept = {}

    def draws(c, n):
        e = kept.get(c)
        if e is None:
            e = np.random.default_rng([seed, c]).normal(0.0, sigma, size=(n, A.shape[0] * A.shape[1]))
            if keep:
                kept[c] = e
        return e

    def response(A_):  # (K, P): sum_t A_t^T e_t
        A2 = A_.reshape(-1, P)
        return np.concatenate([draws(c, n) @ A2 for c, n in chunks])

    base = response(A) @ np.linalg.inv(S).T  # (K, P) the full fit's response
    null = np.zeros((N_NULL, M, P))
    shifts = np.full((M, P), np.nan)
    corrected = np.full((M, P), np.nan)
    transform = np.full((M, P, P), np.nan)
    # a shift whose length in the deleted fit's information is within white noise's 99.9 % reach
    long_step = sigma**2 * chi2.ppf(1.0 - LONG_STEP_LEVEL, P)
    status = ["missing"] * M
    ratio = np.full(M, np.nan)
    ws = None  # the refits' workspace, made at the first refit
    for m in range(M):  # one deletion per marker: each changes every frame's pose projection
        if not np.isfinite(y[:, m]).any():
            continue
        rows = slice(m * D, (m + 1) * D)
        r_m, Jq_m, Jt_m = r.copy(), Jq.copy(), Jt.copy()
        r_m[:, rows] = 0.0
        Jq_m[:, rows] = 0.0
        Jt_m[:, rows] = 0.0
        A_m, S_m, score_m, step = _influence(r_m, Jq_m, Jt_m, pose, R, R_band, step=True)
        kept_info = S_isqrt @ S_m @ S_isqrt  # the information the deletion keeps, whitened
        if np.linalg.eigvalsh(0.5 * (kept_info + kept_info.T))[0] < ESSENTIAL:
            status[m] = "essential"
            continue
        S_m_inv = np.linalg.inv(S_m)
        d = S_m_inv @ score_m
        status[m] = "one-step"
        # a shift within the noise's reach lies where the fit's own linearisation holds; a longer one
        # is kept when the cost falls along it as predicted
        if d @ S_m @ d > long_step:
            ratio[m] = _cost_ratio(model, y, theta, pose, R, sw, m, d, score_m, step, free)
        if np.isfinite(ratio[m]) and not LINEAR_RATIO <= ratio[m] <= 1.0 / LINEAR_RATIO \
                or d @ S_m @ d > long_step and not np.isfinite(ratio[m]):
            if ws is None:
                ws = Workspace(model)
            d = _refit(model, y, theta, pose, R, weights, m, ws, held)
            status[m] = "refit failed" if d is None else "refitted"
            if d is None:
                continue
            d = d[free]
        shifts[m] = d
        # CR2: the shift scaled down where the deletion loses information (see the module notes)
        T_m = transform[m] = cr2_transform(kept_info, S_isqrt, S_sqrt)
        corrected[m] = T_m @ d
        # the white-noise null stays the linearised one (at the full fit's poses)
        null[:, m] = (response(A_m) @ S_m_inv.T - base) @ T_m.T
    ok = np.isfinite(shifts).all(axis=1)
    n = int(ok.sum())
    if n < MIN_MARKERS:
        return Jackknife(shifts, ok, None, status=tuple(status), ratio=ratio, corrected=corrected,
                         transform=transform)
    V_J = _cr2_cov(corrected[ok])
    V_null = np.einsum("kmp,kmq->kpq", null[:, ok], null[:, ok])  # (K, P, P)
    E0 = V_null.mean(axis=0)
    B, B_pinv = null_factor(E0, S_sqrt, S_isqrt)
    if B.shape[1] == 0:  # no replicate moves the estimate at all: nothing to compare
        return Jackknife(shifts, ok, None, status=tuple(status), ratio=ratio, corrected=corrected,
                         transform=transform)
    lam_max = np.linalg.eigvalsh(B_pinv @ V_null @ B_pinv.T)[:, -1]
    used = np.isfinite(y).any(axis=(1, 2))
    artefact = marker_artefact_terms(model, A_all, S_all, pose, used, sw)  # over every parameter
    return Jackknife(shifts, ok, V_J, E0, float(np.quantile(lam_max, 1.0 - FOLD_LEVEL)), tuple(status), ratio,
                     corrected, transform, B, artefact)


def null_factor(E0, S_sqrt, S_isqrt, rel_tol: float = NULL_RANK_TOL) -> tuple[np.ndarray, np.ndarray]:
    """A factor ``B (P, r)`` of ``E_0`` on its range, ``B B^T = E_0``, and its pseudo-inverse ``(r, P)``.

    ``E_0`` is singular wherever no replicate can move the estimate: a direction that only markers
    without a replicate inform (the essential ones, whose deletion leaves it without information;
    with one scale per body axis, an axis that one marker alone measures is such a direction).
    There neither the white-noise spread nor the markers' spread ``V_J`` has anything to say, so the
    comparison is made on the range of ``E_0`` only. The range is found in coordinates whitened by
    the fit's information (``S^{1/2} E_0 S^{1/2}``: null spread over model spread, unit-free), its
    directions with an eigenvalue above ``rel_tol`` times the largest.
    """
    Z = S_sqrt @ E0 @ S_sqrt
    w, V = np.linalg.eigh(0.5 * (Z + Z.T))
    keep = w > rel_tol * max(float(w.max()), 1e-300)
    root = np.sqrt(w[keep])
    return S_isqrt @ V[:, keep] * root, (V[:, keep] / root).T @ S_sqrt


def cr2_transform(kept_info, S_isqrt, S_sqrt) -> np.ndarray:
    """``(P, P)`` map from a replicate's shift ``d_m`` to its leverage-corrected form ``c_m`` (CR2).

    Parameters
    ----------
    kept_info : (P, P) float
        ``S^{-1/2} S_(-m) S^{-1/2}``: the information kept without the cluster, whitened.
    S_isqrt, S_sqrt : (P, P) float
        ``S^{-1/2}`` and ``S^{1/2}`` of the full information.

    Returns
    -------
    (P, P) float
        ``S^{-1/2} kept_info^{1/2} S^{1/2}``. In a linear regression with the cluster's rows
        ``X_m`` and residuals ``e_m``, the delete-cluster shift is ``-(S - X_m^T X_m)^{-1} X_m^T e_m``
        and this map turns it into ``-S^{-1} X_m^T (I - H_mm)^{-1/2} e_m`` (Bell and McCaffrey).
    """
    return S_isqrt @ psd_sqrt(kept_info) @ S_sqrt


def _cr2_cov(c) -> np.ndarray:
    """Cluster-robust covariance ``sum_m c_m c_m^T`` of leverage-corrected replicates ``c (n, P)``."""
    return c.T @ c


def literal_jackknife(model: Model, y, theta, pose, rate=None, cutoff=None, n_iter: int = 50) -> np.ndarray:
    """``(M, P)`` refitted ``theta_(-m) - theta`` (deleting each marker, refitting from the fit); a check."""
    y = np.asarray(y, float)
    out = np.full((y.shape[1], model.n_params), np.nan)
    for m in range(y.shape[1]):
        ym = y.copy()
        ym[:, m] = np.nan
        f = joint_fit(model, ym, theta, pose, n_iter=n_iter, rate=rate, cutoff=cutoff)
        out[m] = f.theta - theta
    return out


def fold(cov, jack: Jackknife) -> tuple[np.ndarray, np.ndarray, float]:
    """The model-based covariance plus the markers' disagreement beyond white noise.

    Parameters
    ----------
    cov : (P, P) float
        Model-based covariance ``V``.
    jack : Jackknife
        With ``cov`` (``V_J``), ``null_mean`` (``E_0``), ``null_max`` and, where computed, ``artefact``.

    Returns
    -------
    cov_folded : (P, P) float
        ``V + a^2 sum_m A_m + E_0^{1/2} M^{1/2} U diag((mu - 1) [mu > null_max]) U^T M^{1/2} E_0^{1/2}``
        (see the module notes), with ``E_0^{1/2}`` the factor of ``E_0`` on its range
        (:func:`null_factor`); without ``artefact``, ``a = 0`` and ``M = I``.
    lam : (P,) float
        Eigenvalues of ``W = E_0^{-1/2} V_J E_0^{-1/2}`` on that range (the test's); 1 for the directions off it.
    rms : float
        ``a``: the root-mean-square artefact whose effect on the replicates matches their excess spread.
    """
    if not jack.available:
        return cov, np.ones(len(cov)), 0.0
    if jack.factor is not None:
        L = jack.factor
        Li = np.linalg.pinv(L)
    else:
        L = np.linalg.cholesky(jack.null_mean)
        Li = np.linalg.inv(L)
    W = Li @ jack.cov @ Li.T
    W = 0.5 * (W + W.T)
    lam = np.linalg.eigvalsh(W)
    rms2, shared, K = 0.0, np.zeros_like(cov), np.eye(len(W))
    if jack.artefact is not None:
        seen = Li @ jack.artefact[jack.replicate].sum(axis=0) @ Li.T  # what the replicated markers' artefact adds
        seen = 0.5 * (seen + seen.T)
        reach = float(np.trace(seen))
        rms2 = max(float(np.trace(W)) - len(W), 0.0) / reach if reach > 0 else 0.0
        shared = rms2 * jack.artefact.sum(axis=0)
        # the replicates' expected spread under that artefact: W is compared with it, not with white noise's
        K = psd_sqrt(np.eye(len(W)) + rms2 * seen)
    Ki = np.linalg.inv(K)
    mu, U = np.linalg.eigh(Ki @ W @ Ki)
    add = np.where(mu > jack.null_max, mu - 1.0, 0.0)
    lam = np.concatenate([lam, np.ones(len(cov) - len(lam))])  # no replicate moves the other directions
    return cov + shared + L @ K @ (U * add) @ U.T @ K @ L.T, lam, float(np.sqrt(rms2))


def _inv_sqrt(S):
    w, V = np.linalg.eigh(0.5 * (S + S.T))
    return (V / np.sqrt(np.maximum(w, 1e-300 * max(w.max(), 1e-300)))) @ V.T




def jackknife_stage(model: Model, y, fit, sigma: float, cov, fold_in: bool, rng=None, weights=None):
    """The marker jackknife of a fit, folded into its covariance.

    Parameters
    ----------
    y : (T, M, D) float
        Markers the fit used (NaN elsewhere).
    fit : skelid.estimators.fit.joint.JointFit
    sigma : float
        The fit's noise level (for the white-noise null).
    cov : (P, P) float
        The covariance so far.
    weights : (M,) or (T, M) float, optional
        The fit's marker weights.
    fold_in : bool
        Add the markers' disagreement to ``cov`` (False: report only, e.g. when the
        artefact's size is stated).

    Returns
    -------
    cov : (P, P) float
    summary : dict
        ``available``, ``folded``, ``effect_sd`` (the sd of the systematic part the fold adds, in each
        parameter's sd before it: the largest), ``warn`` (folded, with an effect of at least
        :data:`JACKKNIFE_EFFECT`), and per parameter ``sd`` (jackknife), ``sd_white_noise``
        (its white-noise expectation), ``sd_added`` and the marker whose deletion moves it most.
    message : str or None
        A warning when the interval was widened enough to move an estimate by half its sd.
    """
    names = model.parameter_names
    jk = marker_jackknife(model, y, fit.theta, fit.pose, fit.penalty, sigma=sigma, rng=rng, weights=weights)
    out = {"available": jk.available, "folded": False,
           "markers_without_replicate": [model.marker_names[m] for m in np.flatnonzero(~jk.replicate)],
           # one-step replicates whose linearisation failed: refitted, or no replicate when the refit failed
           "markers_refitted": [n for n, s in zip(model.marker_names, jk.status, strict=True) if s == "refitted"],
           "markers_refit_failed": [n for n, s in zip(model.marker_names, jk.status, strict=True)
                                    if s == "refit failed"]}
    if not jk.available:
        return cov, out, None
    new, lam, rms = fold(cov, jk)
    added = np.sqrt(np.clip(np.diag(new), 0, None)) - np.sqrt(np.clip(np.diag(cov), 0, None))
    folded = bool(fold_in and np.any(lam > jk.null_max))
    # the disagreement's size against the interval: the sd of the systematic part the fold adds, in sd
    base = np.clip(np.diag(cov), 1e-300, None)
    effect = float(np.sqrt(np.max(np.clip(np.diag(new) - base, 0.0, None) / base, initial=0.0)))
    ok = np.flatnonzero(jk.replicate)
    worst = ok[np.argmax(np.abs(jk.shifts[ok]), axis=0)]
    out.update(folded=folded, largest_eigenvalue=float(lam.max()), null_95=jk.null_max,
               artefact_rms=rms if folded else 0.0, effect_sd=effect if folded else 0.0,
               warn=bool(folded and effect >= JACKKNIFE_EFFECT),
               parameters={n: {"sd": float(np.sqrt(jk.cov[k, k])), "sd_white_noise": float(np.sqrt(jk.null_mean[k, k])),
                               # the uncorrected jackknife (CR3), for comparison
                               "sd_uncorrected": float(np.sqrt(np.sum(jk.shifts[ok, k] ** 2))),
                               "sd_added": float(added[k]) if folded else 0.0,
                               "most_influential_marker": model.marker_names[worst[k]],
                               "shift": float(jk.shifts[worst[k], k])}
                           for k, n in enumerate(names)})
    if not folded:
        return cov, out, None
    if not out["warn"]:  # widened, but by too little to move an estimate by half its sd: no warning
        return new, out, None
    failed = out["markers_refit_failed"]
    k = int(np.argmax(added / np.sqrt(np.diag(cov))))
    msg = (f"the markers disagree beyond their noise (leave-one-marker-out): without marker "
           f"{model.marker_names[worst[k]]} the estimate of {names[k]} moves by {jk.shifts[worst[k], k]:.3g}; "
           "the interval was widened by the marker jackknife"
           + (f" (as by a skin artefact of {rms:.3g} {model.units} rms on every marker)" if rms else ""))
    if failed:
        msg += (f" (without marker(s) {', '.join(failed)} the refit found no estimate: "
                "they have no replicate)")
    return new, out, msg
