"""Soft-tissue artefact of a size the residuals tell: how much it moves a joint fit of scales and offsets.

A skin marker slides against its bone by an amount that follows the pose. Part
of the slide looks like a change of the geometry (a longer thigh, a marker
placed elsewhere) and leaves no residual; the interval of a fit that treats
the residuals as white noise is then too narrow by the part it cannot see (on
OpenSim-generated walks with a 5-15 mm artefact: lengths covered 0.26-0.63 of
the time). :mod:`skelid.estimators.checks.artefact` adds that part for an
artefact whose size the user states; this module estimates the size from the
part that does show, the residuals, and adds the effect of the whole.

Model. Marker ``m`` on body ``b`` moves, in the body's frame, by a linear
function of the joint angles,

.. math:: \\delta_m(t) = R_b(t) \\, (V_b + V'_m)\\, \\Delta q(t), \\qquad
          V_b \\sim N(0, \\tau_s^2), \\; V'_m \\sim N(0, \\tau_o^2) \\text{ (every entry)},

``Delta q``: every rotational coordinate of every joint (a free root's are not
joint angles and are left out) from its mean over the trials, in radians;
``V_b`` (3 x C) shared by the markers of the body (the skin of a segment moves
as a whole, the larger part of a real artefact), ``V'_m`` each marker's own.
A linear function of the whole pose holds the modal, adjacent-angle
description as a special case. The constant part is a marker offset.

Size. Linearised at the fit, the residuals are ``r_t = P_t (S_t delta_t + e_t)``
(``P_t``: the projection off the frame's pose Jacobian, ``S_t`` the row
weights), so

.. math:: E \\|r_{tm}\\|^2 = \\sigma_{km}^2 p_{tm} + \\tau_s^2 c^s_{tm} + \\tau_o^2 c^o_{tm}

with ``p, c^s, c^o`` computed from ``P_t``; ``sigma_km`` (one per marker and
trial, so that noise that differs between markers is not taken for an
artefact: only what grows with the pose's distance from the mean is), ``tau_s``
and ``tau_o`` are the weighted least-squares fit of the squared residual
distances to that (a moment estimate, each row weighted by its mean under no
artefact, as a squared residual's spread grows with its mean; the taus kept
non-negative; the projection on the geometry's few directions is left out).
The artefact is taken as present when the F test of ``tau = 0`` in that fit
rejects at :data:`LEVEL` (white noise, of one level or one per marker, should
give no term in 99 of 100 fits; ``benchmarks/opensim_truth.py`` counts how
often it does), and not when it is below :data:`MIN_RMS` of the model's size.
Its size is then the largest of that fit's, the same fit's with one white
level per trial, and, with several trials, the same fit's with one white level
per marker for all of them: the per-marker levels also absorb the mean square
of the slide and size it from its variation in time alone (on simulated walks
15-40 % smaller), one level per trial counts the whole and errs wide where the
markers' noise differs, and one level per marker for every trial (one camera
system) sizes a walk's slide from its excess over a static trial, whose pose
has none (on OpenSim-generated subjects, static trial plus walk with a 5-15 mm
artefact: hip-knee intervals covered 0.50-0.83 of the time with the first two;
with all three, 0.83-1.00 in ``benchmarks/results/opensim_truth.md``).

Effect. The fit moves by ``H^{-1} sum_t K_t^T W delta_t`` (``K_t``: the
geometry's Jacobian with the poses profiled out, ``W`` the fit's weights,
``H^{-1}`` its posterior covariance), so the artefact adds

.. math:: \\Sigma_{art} = H^{-1} \\Big(\\tau_s^2 \\sum_b G_b G_b^\\top + \\tau_o^2 \\sum_m G_m G_m^\\top\\Big) H^{-1},
          \\qquad G_m = \\sum_t K_{tm}^\\top W R_b(t) \\otimes \\Delta q(t)^\\top, \\; G_b = \\sum_{m \\in b} G_m .

Joint estimate (:func:`joint_slide`, where a reference pose is given). The
slide is linear in its slopes, so, linearised at the fit, the slopes can be
estimated beside the geometry as random effects: the residuals are
``K dtheta + Z v + e`` with ``Z`` the slide's columns, now ``Delta q`` from the
reference pose (the marker offsets are then where the markers sit at that
pose, not at the trials' mean one), one white level for every trial; the
white level and the two slope sizes maximise the marginal likelihood of the
residuals, and the geometry takes the step and the covariance of the joint
posterior with the slopes integrated out (:func:`skelid.scaling._slide_converged` repeats the step,
the poses fitted to the markers less the slide, to the joint optimum). What the trials' spread of poses
tells apart from the geometry is removed rather than only added to the intervals (on OpenSim-generated walks
with a 5-15 mm artefact, hip-knee and knee-ankle errors fell from 32-37 to
13-16 mm rms, ``benchmarks/results/opensim_truth.md``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from skelid._linalg import frame_gram
from skelid.estimators.checks.misfit import MISFIT_MIN_RMS
from skelid.model.description import Model

#: level of the F test of no artefact below which the artefact's term is added
LEVEL = 0.01
#: an artefact is taken as present only if its rms displacement is at least this fraction of the model's size
#: (the misfit test's floor, :data:`skelid.estimators.checks.misfit.MISFIT_MIN_RMS`: 0.01 mm on a 1 m body):
#: on noise-free data the residuals are rounding, whose pattern may follow the pose and be "significant"
MIN_RMS = MISFIT_MIN_RMS
#: frames per block of the computation (memory: a block's Jacobians)
BLOCK_FRAMES = 256


@dataclass(frozen=True)
class PoseArtefact:
    """The artefact the residuals of a joint fit show, and what it adds to the fit's covariance."""

    present: bool  # the F test rejected no artefact at LEVEL, and its rms is at least MIN_RMS of the model's size
    p_value: float
    tau_shared: float  # sd (model units per radian) of the shared slopes V_b
    tau_own: float  # ... of each marker's own V'_m
    rms: float  # root-mean-square displacement of a marker coordinate over the trials (model units)
    sigma_white: tuple  # each trial's noise level with the artefact taken out
    cov: np.ndarray  # (P, P) the covariance it adds (zero where not present)
    score_cov: np.ndarray | None = None  # (P, P) the covariance it adds to the fit's score (the sandwich's meat)
    slide: object = None  # SlideTerms where asked for (a reference pose given)


def artefact_coordinates(model: Model) -> np.ndarray:
    """Indices of the pose coordinates the artefact follows: every joint rotation but a free root's."""
    par = model.parent_index
    return np.array([k for k, d in enumerate(model.dofs)
                     if d.kind == "R" and not (par[d.segment] < 0 and model.segments[d.segment].joint.type == "free")],
                    dtype=int)


def pose_artefact(model: Model, theta, ys, poses, sigma, hinv, weights=None, reference=None,
                  tested: bool = True) -> PoseArtefact:
    """Estimate the pose-dependent artefact of a fit and the covariance it adds.

    Parameters
    ----------
    model : Model
    theta : (P,) float
        The fit's geometry.
    ys : sequence of (F_k, M, 3) float
        Each trial's markers (model order, NaN where missing).
    poses : sequence of (F_k, Q) float
        The fit's poses.
    sigma : (K,) float
        The noise level the fit weighted each trial with.
    hinv : (P, P) float
        The fit's posterior covariance (before any widening).
    weights : (M,) float, optional
        Relative marker weights the fit used.
    reference : (Q,) float, optional
        The pose the slide is measured from; None: no slide terms.
    tested : bool
        False: the artefact taken as present whatever its test says (a fit that has already found it
        and moved the poses to the markers less its slide, whose residuals no longer show it as the
        test expects).

    Returns
    -------
    PoseArtefact
    """
    from skelid.estimators.fit.joint import row_weights, weighted_terms
    from skelid.estimators.fit.likelihood import projected_theta_jacobian
    from skelid.estimators.fit.pose import workspace
    from skelid.model.kinematics import forward_kinematics

    ws = workspace(model)
    theta = np.asarray(theta, float)
    coords = artefact_coordinates(model)
    M, P, K = len(model.markers), model.n_params, len(ys)
    zero = PoseArtefact(False, 1.0, 0.0, 0.0, 0.0, tuple(float(s) for s in sigma), np.zeros((P, P)))
    if coords.size == 0 or P == 0:
        return zero
    qbar = np.concatenate([np.asarray(q, float)[:, coords] for q in poses]).mean(axis=0)
    mseg = np.asarray(model.marker_segment)
    bodies = [np.flatnonzero(mseg == b) for b in np.unique(mseg)]
    G = np.zeros((M, P, 3 * coords.size))
    rows, groups, z = [], [], []
    n_dir = 0 if reference is None else _slide_directions(model, ys)
    joint = n_dir > 0
    if joint:
        qref = np.asarray(reference, float)[coords]
        basis = slide_basis([np.asarray(q, float)[:, coords] - qref for q in poses], n_dir)
        nc = basis.shape[1]
        acc = {"A": np.zeros((3 * M, 3 * M, nc, nc)), "b": np.zeros((M, 3, nc)), "G": np.zeros((M, P, 3, nc)),
               "rss": 0.0}
    for k, (y, q) in enumerate(zip(ys, poses, strict=True)):
        y, q = np.asarray(y, float), np.asarray(q, float)
        for a in range(0, len(q), BLOCK_FRAMES):
            yb, qb = y[a:a + BLOCK_FRAMES], q[a:a + BLOCK_FRAMES]
            sw = row_weights(weights, yb)
            r, Jq, Jt = weighted_terms(model, theta, qb, yb, sw, ws)
            s = np.ones_like(r) if sw is None else sw
            present = np.isfinite(yb).all(axis=-1)  # (T, M)
            s = s * np.repeat(present, 3, axis=1)
            dq = qb[:, coords] - qbar
            g2 = np.sum(dq**2, axis=1)  # (T,)
            x = _moment_rows(Jq, s, g2, bodies, M)  # (T, M, 3): p, c_s, c_o
            T = len(qb)
            rows.append(x[present])
            groups.append(np.broadcast_to(k * M + np.arange(M), (T, M))[present])  # white noise of marker, trial
            z.append(np.sum(r.reshape(T, M, 3) ** 2, axis=-1)[present])
            Kp = projected_theta_jacobian(Jq, Jt).reshape(T, M, 3, P)
            R = forward_kinematics(model, theta, qb, ws).R_world_seg[:, mseg]  # (T, M, 3, 3)
            B = np.swapaxes(Kp * s.reshape(T, M, 3, 1), -1, -2) @ R  # (T, M, P, 3): K^T S R per frame, marker
            G += (np.tensordot(dq, B, axes=(0, 0)).transpose(1, 2, 3, 0).reshape(M, P, -1)
                  / float(sigma[k]) ** 2)
            if joint:  # raw units (not over each trial's sigma): one white level for every trial
                _add_slide_sums(acc, Jq, s.reshape(T, M, 3), R, r, B, (qb[:, coords] - qref) @ basis)
    x, g, z = np.concatenate(rows), np.concatenate(groups), np.concatenate(z)
    p_value, tau_s2, tau_o2, white = _moment_sizes(x, g, z, K, M)
    n_rms = np.mean(np.concatenate([np.sum((np.asarray(q, float)[:, coords] - qbar) ** 2, axis=1) for q in poses]))
    rms = float(np.sqrt((tau_s2 + tau_o2) * n_rms))
    size = float(np.abs(model.nominal_geometry).max())
    if tested and (p_value >= LEVEL or rms < MIN_RMS * size):
        return PoseArtefact(False, p_value, float(np.sqrt(tau_s2)), float(np.sqrt(tau_o2)), rms, white,
                            np.zeros((P, P)))
    C = tau_o2 * np.einsum("mpc,mqc->pq", G, G)
    for idx in bodies:
        Gb = G[idx].sum(axis=0)
        C += tau_s2 * Gb @ Gb.T
    hinv = np.asarray(hinv, float)
    cov = hinv @ C @ hinv
    slide = None
    if joint:
        slide = SlideTerms(acc["A"], acc["b"], acc["G"], tuple(bodies), float(tau_s2), float(tau_o2), acc["rss"],
                           float(n_rms), (qbar - qref) @ basis, coords, qref, basis)
    return PoseArtefact(True, p_value, float(np.sqrt(tau_s2)), float(np.sqrt(tau_o2)), rms, white,
                        0.5 * (cov + cov.T), 0.5 * (C + C.T), slide)


def _add_slide_sums(acc: dict, Jq, s, R, r, B, dr) -> None:
    """Add a block of frames to the slide's sums: ``Z^T S P S Z``, ``Z^T S r``, ``K^T S Z`` and ``r^T r``.

    ``Jq`` (T, 3M, Q) and ``r`` (T, 3M) row-weighted, ``s`` (T, M, 3) the row weights, ``R`` (T, M, 3, 3)
    each marker's body rotation, ``B`` (T, M, P, 3) ``K^T S R``, ``dr`` (T, C) the pose's distance from the
    reference in the slide's directions.
    """
    T, M = s.shape[:2]
    Q = Jq.shape[-1]
    Rs = s[..., None] * R  # (T, M, 3 j, 3 a)
    N = (np.swapaxes(Jq.reshape(T, M, 3, Q), -1, -2) @ Rs).transpose(0, 2, 1, 3).reshape(T, Q, 3 * M)
    Hq = frame_gram(Jq)
    tr = np.einsum("tqq->t", Hq) / max(Q, 1)
    Hq = Hq + 1e-12 * np.maximum(tr, 1e-300)[:, None, None] * np.eye(Q)
    X = -np.matmul(N.swapaxes(1, 2), np.linalg.solve(Hq, N))  # (T, 3M, 3M): off each frame's pose
    # the residuals off each frame's pose too (poses fitted to the data less a slide leave some on it)
    r = r - np.einsum("tiq,tq->ti", Jq, np.linalg.solve(Hq, np.einsum("tiq,ti->tq", Jq, r)[..., None])[..., 0])
    Y = np.einsum("tmja,tmjb->tmab", Rs, Rs)
    for m in range(M):
        X[:, 3 * m:3 * m + 3, 3 * m:3 * m + 3] += Y[:, m]
    C = dr.shape[1]
    DD = (dr[:, :, None] * dr[:, None, :]).reshape(T, C * C)
    acc["A"] += (X.reshape(T, -1).T @ DD).reshape(3 * M, 3 * M, C, C)
    acc["b"] += np.tensordot(np.sum(Rs * r.reshape(T, M, 3, 1), axis=2), dr, axes=(0, 0))  # (M, 3, C)
    acc["G"] += np.tensordot(dr, B, axes=(0, 0)).transpose(1, 2, 3, 0)
    acc["rss"] += float(np.sum(r**2))


def _slide_directions(model: Model, ys) -> int:
    """How many pose directions the slide's slopes may follow: :data:`MAX_SLIDE_SLOPES` and the data's rows."""
    M, Q = len(model.markers), len(model.dofs)
    rows = sum(float(np.clip(3 * np.isfinite(np.asarray(y, float)).all(axis=-1).sum(axis=-1) - Q, 0, None).sum())
               for y in ys)
    return int(min(MAX_SLIDE_SLOPES, rows / SLIDE_ROWS_PER_SLOPE) // (3 * M))


@dataclass(frozen=True)
class SlideTerms:
    """Sums over frames (raw units) for a fit with the slide's slopes estimated beside the geometry."""

    A: np.ndarray  # (3M, 3M, C, C) Z^T S P S Z (P: off each frame's pose Jacobian)
    b: np.ndarray  # (M, 3, C) Z^T S r
    G: np.ndarray  # (M, P, 3, C) K^T S Z (K: the geometry's Jacobian with the poses profiled out)
    bodies: tuple
    tau_s2: float  # the moment fit's sizes (a start)
    tau_o2: float
    rss: float
    pose_spread: float = 1.0  # mean squared distance of the pose from the trials' mean (rad^2): the rms's scale
    mean_dr: np.ndarray | None = None  # (C,) the trials' mean pose from the reference, in the slide's directions
    coords: np.ndarray | None = None  # the pose coordinates the slide follows (:func:`artefact_coordinates`)
    reference: np.ndarray | None = None  # (len(coords),) their reference values
    basis: np.ndarray | None = None  # (len(coords), C) the slide's directions (:func:`slide_basis`)


def slide_displacement(model: Model, theta, poses, sl: SlideTerms, slopes) -> list:
    """Each trial's slide ``(F, M, 3)`` (model units, ground frame) at ``poses`` with ``slopes`` ``(M, 3, C)``.

    Marker ``m`` moves by ``R_b(t) W_m dr(t)``, ``dr`` the pose's distance from the reference in the
    slide's directions: what the joint estimate (:func:`joint_slide`) takes the residuals to hold.
    """
    from skelid.estimators.fit.pose import workspace
    from skelid.model.kinematics import forward_kinematics

    ws = workspace(model)
    mseg = np.asarray(model.marker_segment)
    out = []
    for q in poses:
        q = np.asarray(q, float)
        d = np.empty((len(q), len(mseg), 3))
        for a in range(0, len(q), BLOCK_FRAMES):
            qb = q[a:a + BLOCK_FRAMES]
            R = forward_kinematics(model, theta, qb, ws).R_world_seg[:, mseg]  # (T, M, 3, 3)
            body = np.einsum("mac,tc->tma", slopes, (qb[:, sl.coords] - sl.reference) @ sl.basis)
            d[a:a + BLOCK_FRAMES] = np.einsum("tmja,tma->tmj", R, body)
        out.append(d)
    return out


#: the slide follows the pose in the directions that hold this share of its squared distance from the
#: reference over the trials: those the poses never take (a locked coordinate) are dropped. Keeping
#: fewer cost coverage: on OpenSim-generated walks with a 5-15 mm artefact, the directions of 99.5 %
#: (6 of 18 joint rotations) left hip-knee intervals covering 0.42-0.50 of two walks' draws, all of
#: them 0.75-0.92 (12 draws each)
SLIDE_POSE_SHARE = 1.0 - 1e-9
#: at most this many slopes per marker set (3 per marker and direction), so that the joint estimate's
#: time and memory stay bounded (its matrices are this size squared: 39 MB each; gait2354's 39 markers keep
#: all 18 directions; a model of 49 markers and 28 joint rotations its 14 main directions)
MAX_SLIDE_SLOPES = 2200
#: ... and at most one per this many residual rows the poses leave (a few frames cannot size thousands of
#: slopes: a 16-frame clip of subject01 gave a model OpenSim's IK tracked at 182 mm); a marker set that keeps
#: no direction under both bounds has its slide's effect only added to the intervals
SLIDE_ROWS_PER_SLOPE = 5


def slide_basis(dqs, max_directions: int | None = None) -> np.ndarray:
    """``(C, k)``: the main directions of the poses' distances ``dqs`` (each ``(F, C)``) from the reference."""
    D = np.concatenate([np.asarray(d, float) for d in dqs])
    w, V = np.linalg.eigh(D.T @ D)
    w, V = w[::-1], V[:, ::-1]
    total = float(w.sum())
    if total <= 0:
        return V[:, :1]
    k = min(int(np.searchsorted(np.cumsum(w) / total, SLIDE_POSE_SHARE) + 1), len(w))
    return V[:, :k if max_directions is None else max(1, min(k, max_directions))]


@dataclass(frozen=True)
class SlideFit:
    """The geometry with the slide's slopes estimated beside it (:func:`joint_slide`)."""

    shift: np.ndarray  # (P,) the step from the fit's geometry
    cov: np.ndarray  # (P, P) the geometry's covariance, the slopes integrated out
    sigma_white: float  # the white noise level left (model units)
    tau_shared: float  # sd of the slopes a body's markers share (model units per radian), rms over the markers
    tau_own: float  # ... of each marker's own
    rms: float  # the slide's root-mean-square displacement per marker coordinate at those sizes
    slopes: np.ndarray | None = None  # (M, 3, C) each marker's slopes, their posterior mean
    tau_bodies: np.ndarray | None = None  # (B,) each body's shared sd, in the order of ``SlideTerms.bodies``

    @property
    def sizes(self) -> tuple:
        """``(sigma_w^2, tau_s^2 (B,), tau_o^2)``: what :func:`joint_slide` takes as ``sizes``."""
        return self.sigma_white**2, np.asarray(self.tau_bodies, float) ** 2, self.tau_own**2


def joint_slide(sl: SlideTerms, info_raw, score_raw, prior_grad, prior_curv, dof, sizes=None,
                start=None) -> SlideFit:
    """The fit's geometry and covariance with the slide's slopes as random effects (a linear mixed model).

    Raises ``numpy.linalg.LinAlgError`` where the slopes' posterior precision, a Schur complement of terms of
    size ``1 / sigma^2`` that nearly cancel, comes out indefinite in floating point (noise-free data that one
    factor per body cannot fit, sigma 0.008 mm): the slopes cannot then be told from the geometry.

    Linearised at the fit, with the poses profiled out, the residuals are
    ``r = K dtheta + Z v + e``: ``Z v`` the slide (its columns ``R_b(t) (x) Delta q(t)``, the
    pose's distance from the reference in its main directions), ``v`` the slopes shared by a
    body's markers (sd ``tau_s``) and each marker's own (``tau_o``), ``e`` white noise of one
    level ``sigma_w`` for every trial. The three sizes maximise the marginal likelihood of the
    residuals with the geometry profiled out (one eigendecomposition of the own slopes'
    information; the shared ones enter by the determinant lemma); the geometry's step and
    covariance are those of the joint Gaussian posterior of ``(dtheta, v)`` with the model's
    prior, the slopes integrated out.

    Parameters
    ----------
    sl : SlideTerms
    info_raw : (P, P) float
        The data's information about the geometry at unit noise (``K^T S K``).
    score_raw : (P,) float
        ``K^T S r`` at the fit.
    prior_grad, prior_curv : (P,) float, (P,) or (P, P) float
        Gradient and curvature of the negative log prior at the fit.
    dof : float
        The residuals' degrees of freedom.
    sizes : tuple, optional
        ``(sigma_w^2, tau_s^2, tau_o^2)`` to take instead of estimating them (the steps after the first of
        an iterated fit, whose residuals differ little); ``tau_s^2`` one per body or one for all.
    start : tuple, optional
        Sizes of the same form to start their search from as well (those an iterated fit has so far:
        the moment fit of residuals whose slide has been taken out may find none, and a search started
        only from none stays there).
    """
    from scipy.linalg import cho_factor, cho_solve

    M, P, _, C = sl.G.shape
    n_own = M * 3 * C
    A = sl.A.reshape(M, 3, M, 3, C, C).transpose(0, 1, 4, 2, 3, 5).reshape(n_own, n_own)
    Gf = sl.G.reshape(M, P, 3 * C).transpose(1, 0, 2).reshape(P, n_own)
    s2, ts2, to2 = _slide_sizes(sl, info_raw, score_raw, dof, Gf, A, n_own, start) if sizes is None else sizes
    ts2 = np.broadcast_to(np.asarray(ts2, float), (len(sl.bodies),))
    # the joint posterior of the geometry and each marker's slopes W_m = V_b + V'_m, whose prior
    # covariance is to2 I + ts2 (1 1^T (x) I) within a body (its inverse in closed form)
    Oi = np.eye(n_own) / to2
    k = np.arange(3 * C)
    for idx, t in zip(sl.bodies, ts2, strict=True):
        share = t / (to2 * (to2 + len(idx) * t))
        for m in idx:
            for m2 in idx:
                Oi[m * 3 * C + k, m2 * 3 * C + k] -= share
    lam = np.asarray(prior_curv, float)
    lam = lam if lam.ndim == 2 else np.diag(lam)
    H = info_raw / s2 + lam
    HB = np.linalg.solve(H, Gf / s2)
    S = Oi + A / s2 - (Gf / s2).T @ HB
    S = 0.5 * (S + S.T)
    Hg = np.linalg.solve(H, score_raw / s2 - prior_grad)  # the geometry's own step at this noise level
    Sc = cho_factor(S, check_finite=False)  # the slopes' posterior precision, once for both solves
    u = cho_solve(Sc, sl.b.reshape(n_own) / s2 - (Gf / s2).T @ Hg, check_finite=False)
    cov = np.linalg.inv(H) + HB @ cho_solve(Sc, HB.T, check_finite=False)
    shared = float(np.sum([len(idx) * t for idx, t in zip(sl.bodies, ts2, strict=True)])
                   / max(sum(len(idx) for idx in sl.bodies), 1))  # per marker, over the markers of the bodies
    return SlideFit(Hg - HB @ u, 0.5 * (cov + cov.T), float(np.sqrt(s2)), float(np.sqrt(shared)),
                    float(np.sqrt(to2)), float(np.sqrt((shared + to2) * sl.pose_spread)), u.reshape(M, 3, C),
                    np.sqrt(ts2))


def _slide_sizes(sl: SlideTerms, info_raw, score_raw, dof, Gf, A, n_own, start=None) -> tuple:
    """The white level, each body's shared slope size and the own one: ``(sigma_w^2, tau_s^2 (B,), tau_o^2)``
    of :func:`joint_slide`.

    Each body's markers share slopes of their own size: bodies slide by different amounts (skin over a
    thigh more than over a shank), and one shared size for all of them shrinks the slopes of the bodies
    that slide most too far, leaving their slide to the geometry.
    """
    nll, bounds, y0, sizes = _size_likelihood(sl, info_raw, score_raw, dof, Gf, A, n_own, start)
    return sizes(_size_search(nll, bounds, y0))


def _size_likelihood(sl: SlideTerms, info_raw, score_raw, dof, Gf, A, n_own, start=None):
    """``(nll, bounds, starts, sizes)`` of :func:`_slide_sizes`' search.

    With the slopes' variances as ratios to the white one, ``rho_o = tau_o^2 / sigma_w^2`` and
    ``rho_s = tau_s^2 / sigma_w^2`` (each body's), ``-2 log L = N log sigma_w^2 + a(rho) + b(rho) / sigma_w^2``
    (the determinants do not depend on the white level; the quadratic form scales with its inverse), so
    the white level's optimum is ``b / N`` in closed form and is profiled out: ``nll(y) -> (-2 log L,
    gradient)`` in ``y = (log rho_o, log rho_s of each body)``; ``sizes(y)`` the sizes there. Profiled,
    the search skips the white level's own slow path (subject01's walk: 119 evaluations from the even
    start, the first dozen spent bringing the white level down from the residuals' whole variance).
    """
    from scipy.linalg import blas, cho_factor, cho_solve, solve_triangular

    C = sl.G.shape[-1]
    B = len(sl.bodies)
    E = np.zeros((n_own, B * 3 * C))  # a body's shared slopes: the sum of its markers' columns
    for j, idx in enumerate(sl.bodies):
        for m in idx:
            E[m * 3 * C:(m + 1) * 3 * C, j * 3 * C:(j + 1) * 3 * C] = np.eye(3 * C)
    Ii = np.linalg.pinv(info_raw, rcond=1e-10, hermitian=True)
    Ac = A - Gf.T @ Ii @ Gf  # the geometry's data-determined directions profiled out
    bc = sl.b.reshape(n_own) - Gf.T @ Ii @ score_raw
    mu, U = np.linalg.eigh(0.5 * (Ac + Ac.T))
    mu = np.clip(mu, 0.0, None)
    c = U.T @ bc
    c = np.where(mu > 1e-9 * max(mu.max(initial=0.0), 1e-300), c, 0.0)
    Ep = U.T @ E
    N = max(float(dof), 1.0)
    # the residuals' sum of squares with the geometry profiled out too (trials weighted alike here)
    rss = max(float(sl.rss) - float(score_raw @ Ii @ score_raw), 1e-300)
    EpF = np.asfortranarray(Ep)
    cols = np.repeat(np.arange(B), 3 * C)  # each shared column's body

    def parts(ro, rs):  # a, b and their gradients in (rho_o, rho_s): the likelihood at sigma_w^2 = 1
        d = 1.0 + ro * mu
        w, cd = mu / d, c / d
        F = np.triu(blas.dsyrk(1.0, EpF * np.sqrt(w)[:, None], trans=1))  # Ep^T diag(w) Ep, one triangle
        F = F + np.triu(F, 1).T
        g = Ep.T @ cd
        s = np.sqrt(rs)[cols]
        L = cho_factor(np.eye(F.shape[0]) + s[:, None] * F * s[None, :], check_finite=False)
        h = s * cho_solve(L, s * g, check_finite=False)  # (T^-1 + F)^-1 g: the shared slopes' posterior mean
        X = solve_triangular(L[0], s[:, None] * Ep.T, trans="T", lower=L[1], check_finite=False)
        q = np.einsum("ij,ij->j", X, X)  # diag(Ep (T^-1 + F)^-1 Ep^T)
        Y = solve_triangular(L[0], s[:, None] * F, trans="T", lower=L[1], check_finite=False)
        k_diag = np.diag(F) - np.einsum("ij,ij->j", Y, Y)  # diag((F^-1 + T)^-1): log det's slope in T
        p = g - F @ h
        e = Ep @ h
        a = np.sum(np.log(d)) + 2.0 * np.sum(np.log(np.diag(L[0])))
        b = rss - ro * np.sum(c * cd) - g @ h
        # through each d_i = 1 + rho_o mu_i: the determinants, the white part and the shared part
        da = np.concatenate([[mu @ (1.0 / d - q * mu / d**2)], np.bincount(cols, k_diag, B)])
        db = np.concatenate([[mu @ ((ro * c**2 + 2.0 * e * c - e**2 * mu) / d**2) - np.sum(c * cd)],
                             -np.bincount(cols, p**2, B)])
        return a, max(b, 1e-300 * rss), da, db

    def nll(y):  # -2 log L with the white level at its optimum b / N, and its gradient in y
        rho = np.exp(y)
        a, b, da, db = parts(rho[0], rho[1:])
        return N * np.log(b / N) + a + N, rho * (da + (N / b) * db)

    def sizes(y):
        rho = np.exp(y)
        s2 = parts(rho[0], rho[1:])[1] / N
        return float(s2), s2 * rho[1:], float(s2 * rho[0])

    # started from the moment fit's sizes and from their total split evenly (each over the residuals' whole
    # variance); the better optimum is kept. A size started at its floor has no gradient there: on subject01
    # the moment fit's start (its shared size 0) ends at a shared sd of 0.005 and -2 log L 610 above the even
    # split's optimum, which a 49-start grid confirms; on a simulated walk it takes 53 evaluations to the even
    # split's 14. The ratios are searched from 1e-6 (no slide) up; the even split starts no lower than
    # 1e-3, where the gradient (proportional to the ratio) still exceeds the search's tolerance.
    half = 0.5 * (sl.tau_s2 + sl.tau_o2)
    floor = 1e-6
    bounds = [(np.log(floor), np.log(floor) + 40.0)] * (1 + B)
    y0 = [np.log(np.maximum(np.array([o] + [a] * B) / (rss / N), least))
          for (a, o), least in dict.fromkeys([((half, half), 1e-3), ((sl.tau_s2, sl.tau_o2), floor)])]
    if start is not None:  # and from the sizes given (each body's own)
        ts = np.broadcast_to(np.asarray(start[1], float), (B,))
        y0.append(np.log(np.maximum(np.concatenate([[start[2]], ts]) / start[0], floor)))
    return nll, bounds, [np.clip(y, bounds[0][0], bounds[0][1]) for y in y0], sizes


def _size_search(nll, bounds, x0) -> np.ndarray:
    """The log sizes at the lowest optimum reached from the starts ``x0``."""
    from scipy.optimize import minimize

    fits = [minimize(nll, x, method="L-BFGS-B", jac=True, bounds=bounds) for x in x0]
    return min(fits, key=lambda r: r.fun).x


def _moment_sizes(x, g, z, K, M):
    """The F test's p-value, the slide's two variances and the white levels from the moment fits."""
    # the test: one white level per marker and trial (noise that differs between markers is not an artefact)
    p_value, tau_s2, tau_o2, white = _moment_fit(x, g, z, K, M)
    # the size: the larger of that and the fit with one white level per trial, which also counts the
    # slide's mean square (the per-marker levels absorb it and size the slide from its variation in
    # time alone: 15-40 % smaller on simulated walks)
    _, ts2, to2, w2 = _moment_fit(x, g // M, z, K, 1)
    if ts2 + to2 > tau_s2 + tau_o2:
        tau_s2, tau_o2, white = ts2, to2, w2
    if K > 1:  # one white level per marker for every trial (one camera system): a trial's slide is its excess
        _, ts3, to3, _ = _moment_fit(x, g % M, z, 1, M)
        if ts3 + to3 > tau_s2 + tau_o2:
            tau_s2, tau_o2 = ts3, to3
    return p_value, tau_s2, tau_o2, white


def _moment_fit(x, g, z, K, M):
    """The moment fit of the squared residuals ``z`` and its F test: ``(p_value, tau_s^2, tau_o^2, sigma_white)``.

    ``E z = sigma_g^2 p + tau_s^2 c_s + tau_o^2 c_o`` (``x``: rows ``p, c_s, c_o``), one white
    variance per marker and trial (``g``), so that noise that differs between markers is not taken
    for an artefact: only what grows with the distance of the pose from the mean is. Each row is
    scaled by its mean under no artefact (a quasi-likelihood: the spread of a squared residual
    grows with its mean); the white variances are profiled out group by group (Frisch-Waugh), and
    the two artefact variances fitted by non-negative least squares.
    """
    from scipy.optimize import nnls
    from scipy.stats import f as f_dist

    G = K * M
    p, c = x[:, 0], x[:, 1:]

    def group_fit(w, zz):  # per-group least squares of zz on p with row weights w: coefficients
        num = np.bincount(g, w * p * zz, G)
        den = np.bincount(g, w * p * p, G)
        return np.where(den > 0, num / np.maximum(den, 1e-300), 0.0), den

    a0, _ = group_fit(np.ones_like(z), z)
    mu0 = np.maximum(a0, 0.0)[g] * p
    # a trial fitted exactly (markers placed on a static one) has means near zero: floored at 1e-12 of the
    # largest, so that the weights stay finite (1e-300 squared overflowed)
    mu0 = np.maximum(mu0, 1e-12 * max(float(mu0.max(initial=0.0)), 1e-300))
    w = mu0 ** -2.0
    a, den = group_fit(w, z)
    zt = z - a[g] * p
    ct = np.stack([c[:, j] - group_fit(w, c[:, j])[0][g] * p for j in range(c.shape[1])], axis=1)
    sw = np.sqrt(w)
    coef, _ = nnls(ct * sw[:, None], zt * sw)
    rss0 = float(np.sum(w * zt**2))
    rss1 = float(np.sum(w * (zt - ct @ coef) ** 2))
    dof = max(len(z) - int(np.count_nonzero(den)) - c.shape[1], 1)
    F = ((rss0 - rss1) / c.shape[1]) / max(rss1 / dof, 1e-300)
    p_value = float(f_dist.sf(F, c.shape[1], dof)) if rss0 > rss1 else 1.0
    var = np.maximum(a - np.stack([group_fit(w, c[:, j])[0] for j in range(c.shape[1])], axis=1) @ coef, 0.0)
    seen = (den > 0).reshape(K, M)
    white = tuple(float(np.sqrt(v[s].mean())) if s.any() else float("nan")  # each trial's mean over its markers
                  for v, s in zip(var.reshape(K, M), seen, strict=True))
    return p_value, float(coef[0]), float(coef[1]), white


def _moment_rows(Jq, s, g2, bodies, M) -> np.ndarray:
    """Per frame and marker, ``p`` (white noise), ``c_s`` (shared artefact) and ``c_o`` (own): ``(T, M, 3)``.

    ``E = J (J^T J)^{-1} J^T``, ``P = I - E``: ``p_m = sum_{i in m} P_ii``; with ``D = g2 s^2`` the
    own part's diagonal ``diag(P D P)_i = D_i (1 - 2 E_ii) + J_i H^{-1} (J^T D J) H^{-1} J_i^T``; the
    shared part ``sum_b g2 ||(P U_b)_m||_F^2`` with ``U_b = S (1_b (x) I_3)``.
    """
    T, n, Q = Jq.shape
    H = frame_gram(Jq)
    tr = np.einsum("tqq->t", H) / max(Q, 1)
    Hi = np.linalg.inv(H + 1e-12 * np.maximum(tr, 1e-300)[:, None, None] * np.eye(Q))
    JH = Jq @ Hi  # (T, n, Q)
    Eii = np.einsum("tiq,tiq->ti", JH, Jq)
    on = (s > 0).astype(float)
    p = (on * (1.0 - Eii)).reshape(T, M, 3).sum(-1)
    D = g2[:, None] * s**2
    # the three-operand sums as matrix products (BLAS): einsum's own loops were most of this function's time
    F = np.swapaxes(Jq * D[..., None], -1, -2) @ Jq
    own = D * (1.0 - 2.0 * Eii) + np.sum((JH @ F) * JH, axis=-1)
    co = (on * own).reshape(T, M, 3).sum(-1)
    cs = np.zeros((T, M))
    for idx in bodies:
        U = np.zeros((T, n, 3))
        for m in idx:
            for a in range(3):
                U[:, 3 * m + a, a] = s[:, 3 * m + a]
        PU = U - JH @ (np.swapaxes(Jq, -1, -2) @ U)
        cs += g2[:, None] * (on[..., None] * PU**2).reshape(T, M, 3, 3).sum(axis=(2, 3))
    return np.stack([p, cs, co], axis=-1)
