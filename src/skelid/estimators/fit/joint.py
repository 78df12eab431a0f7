"""Batch estimation of ``theta`` and every pose at once, and its bias.

**Joint least squares.** Levenberg-Marquardt on ``(theta, q_1..q_T)``. Each
iteration eliminates the poses through the Schur complement (see
:mod:`skelid.estimators.fit.likelihood`), so the cost is linear in ``T``:

.. math::

    S\\,\\delta\\theta = g_\\theta - \\sum_t H_{\\theta q,t} H_{qq,t}^{-1} g_{q,t},
    \\qquad \\delta q_t = H_{qq,t}^{-1}(g_{q,t} - H_{q\\theta,t}\\,\\delta\\theta).

**Second-order bias (Box 1971).** For ``y = f(\\beta) + \\varepsilon`` with
``\\beta = (\\theta, q_1..q_T)`` the least-squares estimate has bias

.. math:: b = -\\tfrac{\\sigma^2}{2} C J^\\top d, \\quad d_i = \\mathrm{tr}(C \\nabla^2 f_i),

with ``C = (J^\\top J)^{-1}``,
to order ``\\sigma^2``. Because every frame brings its own pose (the
incidental-parameter, or Neyman-Scott, problem) the ``theta`` part of ``b``
does not shrink with ``T``. Using the arrow structure,

.. math:: b_\\theta = -\\tfrac{\\sigma^2}{2} S^{-1} \\sum_t \\big((I-P_t)K_t\\big)^\\top d_t ,

where ``d_t`` needs only the ``(theta, q_t)`` block ``C_t`` of ``C``. Writing
``C_t = L L^T``, ``d_{t,i} = \\sum_k l_k^\\top \\nabla^2 f_{t,i}\\, l_k`` is a sum of
directional second derivatives, taken by central differences of the analytic
Jacobian. Subtracting ``b`` is the "hyperaccurate" correction of geometric
fitting (Kanatani).

**Serially correlated residuals.** Soft-tissue artefact makes residuals slow
and smooth. The per-frame scores ``s_t = ((I-P_t)K_t)^T r_t`` then correlate,
and the Newey-West (Bartlett-kernel) estimate
``S^{-1} (\\sum_{|l|\\le L} w_l \\sum_t s_t s_{t+l}^T) S^{-1}`` replaces
``\\sigma^2 S^{-1}``.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from skelid._linalg import frame_gram, summed_gram, summed_product
from skelid.estimators.fit.likelihood import frame_terms, pose_information, projected_theta_jacobian
from skelid.model import _fk_kernel
from skelid.model.description import Model
from skelid.model.kinematics import Workspace, marker_jacobian, marker_positions, stacked_jacobian


def penalty_band(R, Q: int) -> np.ndarray:
    """The penalty ``R`` in upper banded form, with at least ``Q - 1`` superdiagonals.

    A fit whose penalty stays the same computes this once and passes it as
    ``R_band`` to the banded solvers, which then only add the pose blocks.
    """
    coo = R.tocoo()
    u = max(Q - 1, int(np.max(coo.col - coo.row)) if coo.nnz else 0)
    ab = np.zeros((u + 1, R.shape[0]))
    keep = coo.row <= coo.col
    np.add.at(ab, (u + coo.row[keep] - coo.col[keep], coo.col[keep]), coo.data[keep])
    return ab


def _banded(Hqq, R, R_band=None):
    """Upper banded form (for ``scipy.linalg.cholesky_banded``) of ``blockdiag(Hqq) + R``."""
    T, Q = Hqq.shape[:2]
    ab = (penalty_band(R, Q) if R_band is None else R_band).copy()
    u = ab.shape[0] - 1
    # every entry (a, b), a <= b, of each frame's block lands on its own place of the band: one
    # scattered addition (each place is hit once, so the sums are those of a loop over the entries)
    src, dst = _band_places(T, Q, u)
    ab.ravel()[dst] += Hqq.reshape(T, Q * Q)[:, src].ravel()
    return ab


@functools.lru_cache(maxsize=16)
def _band_places(T: int, Q: int, u: int) -> tuple[np.ndarray, np.ndarray]:
    """Where :func:`_banded` takes each upper entry of the ``(Q, Q)`` blocks and puts it in the band.

    ``src`` (K,): flat indices ``a * Q + b`` (``a <= b``) into one block; ``dst`` (T*K,): flat indices
    into the ``(u+1, T*Q)`` band, frame by frame (the same places for every call of one shape).
    """
    a, b = np.triu_indices(Q)
    col = (np.arange(T)[:, None] * Q + b).ravel()
    row = np.broadcast_to(u - (b - a), (T, a.size)).ravel()
    dst = row * (T * Q) + col
    src = a * Q + b
    src.setflags(write=False)
    dst.setflags(write=False)
    return src, dst


def _banded_system(Hqq, R, ridge: float = 1e-10, R_band=None):
    """``blockdiag(Hqq) + R`` in upper banded form, with a tiny ridge that keeps it definite.

    The ridge is relative to each pose coordinate's own mean diagonal (angles and
    translations have different units: one ridge for all would perturb the
    solution along the translations by a fraction of a percent).
    """
    ab = _banded(Hqq, R, R_band)
    u = ab.shape[0] - 1
    T, Q = Hqq.shape[:2]
    scale = np.maximum(ab[u].reshape(T, Q).mean(axis=0), 1e-300)
    ab[u] += ridge * np.tile(scale, T)  # frames without markers: keep it definite
    return ab


def _dense_from_banded(ab):
    u, n = ab.shape[0] - 1, ab.shape[1]
    A = np.zeros((n, n))
    for k in range(u + 1):
        i = np.arange(n - (u - k))
        A[i, i + (u - k)] = ab[k, u - k:]
    return A + np.triu(A, 1).T


def _banded_solver(Hqq, R, R_band=None):
    """A function ``rhs -> (blockdiag(Hqq) + R)^{-1} rhs`` by banded Cholesky.

    Banded LAPACK beats the dense factor of the same matrix at every size and band measured (9 to 3,000
    unknowns, bands of 2 to half the size: 2 to 50 times quicker, the dense copy included).
    """
    from scipy.linalg import cho_solve_banded, cholesky_banded

    ab = _banded_system(Hqq, R, R_band=R_band)
    cb = cholesky_banded(ab, lower=False, check_finite=False)
    return lambda rhs: cho_solve_banded((cb, False), rhs, check_finite=False)


def band_inverse_blocks(ab, Q: int) -> np.ndarray:
    """Diagonal ``(Q, Q)`` blocks of ``A^{-1}`` for a banded positive definite ``A``.

    Parameters
    ----------
    ab : (u+1, n) float
        ``A`` in upper banded form (``scipy.linalg.cholesky_banded`` layout), ``n = T*Q``.
    Q : int
        Block size.

    Returns
    -------
    (T, Q, Q) float

    Notes
    -----
    Selected inversion (Takahashi, Fagan and Chin 1973): with ``A = U^T U`` and
    ``Z = A^{-1}``, ``U Z = U^{-T}`` is lower triangular, so for ``j >= i``

    .. math:: Z_{ij} = \\big(\\delta_{ij}/U_{ii} - \\textstyle\\sum_{k=i+1}^{i+u} U_{ik} Z_{kj}\\big) / U_{ii},

    which, run from the last row up, needs only entries of ``Z`` inside the band.
    Cost ``O(n u^2)`` and memory ``O(n u)`` instead of the dense inverse's ``O(n^3)``.
    """
    from scipy.linalg import cholesky_banded

    u, n = ab.shape[0] - 1, ab.shape[1]
    T = n // Q
    compiled = Q <= u <= 32 and n % Q == 0 and _fk_kernel.ready("band")
    if n <= 300 and not compiled:  # tiny systems: the dense inverse is quicker than the numpy sweep
        Z = _spd_inverse(_dense_from_banded(ab))
        idx = np.arange(T)[:, None] * Q + np.arange(Q)
        return Z[idx[:, :, None], idx[:, None, :]]
    cb = cholesky_banded(ab, lower=False, check_finite=False)
    Ub = np.zeros((n + u, u + 1))  # Ub[i, d] = U[i, i + d]; rows past the end stay zero
    for d in range(u + 1):
        Ub[:n - d, d] = cb[u - d, d:]
    if u >= Q and n % Q == 0:
        # the same sweep compiled (same values to rounding): far quicker on narrow bands, where the
        # numpy loop is Python overhead; on wide ones (u > 32) BLAS products of the blocks win
        if compiled:
            return _fk_kernel.band_inverse_blocks(Ub, Q, T)
        return _selected_inverse_by_blocks(Ub, Q, T)
    Zb = np.zeros((n, u + 1))  # Zb[i, d] = Z[i, i + d]
    W = np.zeros((u + 1, u + 1))  # Z[i:i+u+1, i:i+u+1] as the sweep moves up
    for i in range(n - 1, -1, -1):
        row = Ub[i, 1:]
        z = -(row @ W[:u, :u]) / Ub[i, 0]
        zii = (1.0 / Ub[i, 0] - row @ z) / Ub[i, 0]
        W[1:, 1:] = W[:u, :u].copy()
        W[0, 0] = zii
        W[0, 1:] = z
        W[1:, 0] = z
        Zb[i, 0] = zii
        Zb[i, 1:] = z
    out = np.empty((T, Q, Q))
    base = np.arange(T) * Q
    for a in range(Q):
        for b in range(a, Q):
            out[:, a, b] = out[:, b, a] = Zb[base + a, b - a]
    return out


def _selected_inverse_by_blocks(Ub, Q: int, T: int) -> np.ndarray:
    """The sweep of :func:`band_inverse_blocks` one frame (``Q`` rows) at a time.

    With frame ``I`` and the ``u`` rows ``F`` after it, ``U Z = U^{-T}`` gives
    ``Z_IF = -U_II^{-1} U_IF Z_FF`` and ``Z_II = U_II^{-1} (U_II^{-T} - U_IF Z_FI)``;
    ``Z_FF`` lies inside the band, so a ``(u, u)`` window of ``Z`` moving up ``Q`` rows
    per step carries everything needed (same operations as the row sweep, grouped).
    """
    u = Ub.shape[1] - 1
    r = np.arange(Q)[:, None]
    d = np.arange(u + 1)[None, :]
    rows = np.arange(T)[:, None, None] * Q + r  # (T, Q, 1)
    Ublk = np.zeros((T, Q, Q + u))  # U[tQ:(t+1)Q, tQ:(t+1)Q + u]
    Ublk[:, r, r + d] = Ub[rows, d]
    Uinv = np.linalg.inv(Ublk[:, :, :Q])  # (T, Q, Q) upper triangular inverses, all frames at once
    U_IF = Ublk[:, :, Q:]
    out = np.empty((T, Q, Q))
    W = np.zeros((u, u))  # Z over the u rows after the current frame
    for t in range(T - 1, -1, -1):
        Ui = Uinv[t]
        Z_IF = -Ui @ (U_IF[t] @ W)  # (Q, u)
        Z_II = Ui @ (Ui.T - U_IF[t] @ Z_IF.T)
        Z_II = 0.5 * (Z_II + Z_II.T)
        out[t] = Z_II
        Wn = np.empty((u, u))
        Wn[:Q, :Q] = Z_II
        Wn[:Q, Q:] = Z_IF[:, :u - Q]
        Wn[Q:, :Q] = Z_IF[:, :u - Q].T
        Wn[Q:, Q:] = W[:u - Q, :u - Q]
        W = Wn
    return out


def _spd_inverse(A) -> np.ndarray:
    """Inverse of a symmetric positive definite matrix from its Cholesky factor (LU if that fails)."""
    from scipy.linalg import lapack

    c, info = lapack.dpotrf(A, lower=0, clean=0)
    if info == 0:
        Z, info = lapack.dpotri(c, lower=0)
    if info != 0:
        return np.linalg.inv(A)
    return np.triu(Z) + np.triu(Z, 1).T


def pose_edf(Jq, R, R_band=None) -> float:
    """Effective number of pose parameters ``tr((H + R)^{-1} H)`` under the penalty ``R``.

    ``H`` is block diagonal (per-frame ``J^T J``), so only the diagonal blocks of
    the inverse are needed: they come from :func:`band_inverse_blocks`, linear in
    the number of frames.
    """
    Hqq = pose_information(Jq)
    Q = Hqq.shape[-1]
    return float(np.einsum("tij,tji->", band_inverse_blocks(_banded_system(Hqq, R, R_band=R_band), Q), Hqq))


class JointFit(NamedTuple):
    theta: np.ndarray  # (P,)
    pose: np.ndarray  # (T, Q); frames not used keep their starting pose
    rss: float
    rss_frame: np.ndarray  # (T,); zero for frames not used
    info: np.ndarray  # (P, P) S = sum_t K_perp^T K_perp (unit noise)
    n_obs: int  # coordinates used
    frames_used: np.ndarray  # (T,) bool
    n_iter: int
    converged: bool
    pose_dof: float  # pose parameters the fit used: T*Q, or the effective number under smoothing
    penalty: object = None  # the motion-model penalty (sparse, frame-major) or None


def usable_frames(model: Model, y) -> np.ndarray:
    """(T,) bool: frames with enough coordinates to fix the pose and inform theta."""
    n = np.isfinite(y).all(axis=-1).sum(axis=-1) * model.dim
    return n > model.n_pose


def _normal_blocks(r, Jq, Jt):
    """Blocks of ``J^T J`` and ``J^T r``.

    Returns ``Hqq (T, Q, Q)``, ``Hqt (T, Q, P)``, ``Htt (P, P)``, ``gq (T, Q)``, ``gt (P,)``.
    """
    Hqq = pose_information(Jq)
    JqT = np.swapaxes(Jq, -1, -2)
    Hqt = np.matmul(JqT, Jt)
    Jt2 = Jt.reshape(-1, Jt.shape[-1])
    Htt = Jt2.T @ Jt2
    gq = np.matmul(JqT, r[..., None])[..., 0]
    gt = r.ravel() @ Jt2
    return Hqq, Hqt, Htt, gq, gt


def _reduce_to_theta(Hqt, Htt, gt, G, u, lam, active=None):
    """Schur complement in theta given ``G = A^{-1} H_{q theta}`` and ``u = A^{-1} g_q``.

    ``active(dtheta)``, where given, names the parameters held where they are (a bound the step
    would cross outward): the step is then solved for the others alone, and the poses' step
    follows the parameters' actual one (a clipped step with the poses' unclipped response is no
    descent direction, and the fit would crawl along the bound).
    """
    P = Htt.shape[0]
    dt_ = np.diag(Htt)
    Hqt2 = Hqt.reshape(-1, P).T  # (P, T*Q): the frame sums as matrix products (BLAS)
    S = Htt + lam * np.diag(dt_) + 1e-12 * max(dt_.mean(), 1e-300) * np.eye(P) - Hqt2 @ G.reshape(-1, P)
    rhs = gt - Hqt2 @ u.ravel()
    dtheta = np.linalg.solve(S, rhs)
    held = None if active is None else active(dtheta)
    if held is not None and held.any():
        free = ~held
        dtheta = np.zeros(P)
        if free.any():
            dtheta[free] = np.linalg.solve(S[np.ix_(free, free)], rhs[free])
    return dtheta, u - G @ dtheta, S


def _schur_step(Hqq, Hqt, Htt, gq, gt, lam, active=None):
    Q, P = Hqq.shape[-1], Htt.shape[0]
    dq_ = np.einsum("tii->ti", Hqq)
    # ridge relative to the frame's own scale, or to the trial's for a frame with no rows
    scale = np.maximum(dq_.mean(axis=1), max(dq_.mean(), 1e-300))
    A = Hqq + (lam * dq_)[..., None] * np.eye(Q) + 1e-12 * scale[:, None, None] * np.eye(Q)
    sol = np.linalg.solve(A, np.concatenate([Hqt, gq[..., None]], axis=-1))
    G, u = sol[..., :P], sol[..., P]
    return _reduce_to_theta(Hqt, Htt, gt, G, u, lam, active)


UNDERSMOOTH = 2.0
CUTOFF_CANDIDATES = (0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0)  # Hz


def _gain(cutoff, rate):
    return (2.0 - 2.0 * np.cos(2.0 * np.pi * np.minimum(np.asarray(cutoff, float) / rate, 0.5))) ** 3


def choose_cutoffs(model: Model, q, used, rate: float) -> np.ndarray:
    """Cutoff frequency (Hz) for each pose coordinate by generalised cross-validation.

    Each coordinate's per-frame track ``z`` (angles unwrapped, skipped frames
    interpolated) is smoothed by the third-difference Whittaker smoother for each
    candidate cutoff, and the cutoff minimising
    ``GCV = T ||z - z_hat||^2 / (T - tr H)^2`` (``tr H`` from the smoother's
    frequency response) is doubled: a nuisance curve smoothed for its own best
    error would bias the parameter, so it is undersmoothed. Slow motion gets a
    low cutoff (more smoothing, less incidental-parameter bias); fast motion
    keeps a high one.

    Returns
    -------
    (Q,) float
    """
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    z = _continuous_poses(model, q, used)
    T, Q = z.shape
    if T < 8:
        return np.full(Q, rate / 2.0)
    D3 = sp.diags([-1.0, 3.0, -3.0, 1.0], [0, 1, 2, 3], shape=(T - 3, T))
    P = (D3.T @ D3).tocsc()
    omega = 2.0 * np.pi * np.arange(T) / T
    resp = (2.0 - 2.0 * np.cos(omega)) ** 3
    best = np.full(Q, np.nan)
    score = np.full(Q, np.inf)
    eye = sp.identity(T, format="csc")
    for fc in CUTOFF_CANDIDATES:
        if fc >= rate / 2.0:
            break
        lam = 1.0 / _gain(fc, rate)
        zh = splu((eye + lam * P).tocsc()).solve(z)
        trace = float(np.sum(1.0 / (1.0 + lam * resp)))
        g = T * np.sum((z - zh) ** 2, axis=0) / max(T - trace, 1.0) ** 2
        better = g < score
        score[better], best[better] = g[better], fc
    # undersmooth: the cutoff that is best for the poses leaves a pose bias that would
    # bias theta; twice that cutoff passes the motion the data resolve almost untouched
    return np.where(np.isfinite(best), np.minimum(UNDERSMOOTH * best, rate / 2.0), rate / 2.0)


def smoothing_penalty(model: Model, Hqq, rate: float, cutoff):
    """Third-difference penalty on pose trajectories: a low-pass motion model.

    The penalty ``sum_k w_k ||D3 q_k||^2`` makes the poses a Whittaker smoother
    of the per-frame fits whose gain is 1/2 at the cutoff (Hz; one value, or one
    per pose coordinate), ``w_k = median_t H_{qq,t,kk} / (2 - 2 cos(2 pi f_k / rate))^3``;
    its gain ``1 / (1 + (f/f_k)^6)`` (roughly) leaves slower motion untouched
    and passes quadratic trajectories exactly.

    Returns
    -------
    R : scipy.sparse matrix (T*Q, T*Q), poses ordered frame-major.
    """
    import scipy.sparse as sp

    T = Hqq.shape[0]
    h = np.median(np.einsum("tii->ti", Hqq), axis=0)
    w = np.maximum(h, 1e-12 * max(h.max(), 1e-300)) / _gain(np.broadcast_to(cutoff, h.shape), rate)
    D3 = sp.diags([-1.0, 3.0, -3.0, 1.0], [0, 1, 2, 3], shape=(max(T - 3, 0), T))
    return sp.kron(D3.T @ D3, sp.diags(w)).tocsc()


def block_penalty(model: Model, Hqq, blocks):
    """Block-diagonal motion-model penalty for trials stacked along the frame axis.

    Parameters
    ----------
    Hqq : (T, Q, Q) float
        Per-frame pose information of all trials.
    blocks : sequence of (start, stop, rate, cutoff)
        Each trial's frames; a cutoff of None leaves its poses unsmoothed.

    Returns
    -------
    scipy.sparse matrix (T*Q, T*Q): :func:`smoothing_penalty` of each trial on
    its own diagonal block, zero across trials.
    """
    import scipy.sparse as sp

    Q = Hqq.shape[-1]
    parts = []
    for a, b, rate, cutoff in blocks:
        if cutoff is None or rate is None:
            parts.append(sp.csc_matrix(((b - a) * Q, (b - a) * Q)))
        else:
            parts.append(smoothing_penalty(model, Hqq[a:b], rate, cutoff))
    return sp.block_diag(parts, format="csc")


def _schur_step_smooth(Hqq, Hqt, Htt, gq, gt, lam, R, q, R_band=None, active=None):
    """Like :func:`_schur_step` with the pose blocks coupled by the penalty ``R``."""
    T, Q = gq.shape
    P = Htt.shape[0]
    dq_ = np.einsum("tii->ti", Hqq)
    solve = _banded_solver(Hqq + (lam * dq_)[..., None] * np.eye(Q), R, R_band)
    rhs_q = (gq.ravel() - R @ q.ravel()).reshape(T, Q)
    sol = solve(np.concatenate([Hqt, rhs_q[..., None]], axis=-1).reshape(T * Q, P + 1))
    sol = sol.reshape(T, Q, P + 1)
    G, u = sol[..., :P], sol[..., P]
    return _reduce_to_theta(Hqt, Htt, gt, G, u, lam, active)


def _continuous_poses(model: Model, q, use):
    """Starting poses fit for a motion model: angles unwrapped, skipped frames interpolated."""
    q = np.array(q, dtype=float)
    idx = np.flatnonzero(use)
    if idx.size == 0:
        return q
    rot = np.array([d.kind == "R" for d in model.dofs])
    qa = np.where(rot, np.unwrap(q[idx], axis=0), q[idx])
    t = np.arange(len(q))
    return np.stack([np.interp(t, idx, qa[:, k]) for k in range(q.shape[1])], axis=-1)


def row_weights(weights, y) -> np.ndarray | None:
    """Square roots of marker weights, one per residual row: ``(T, M*D)``, or None.

    Parameters
    ----------
    weights : (M,) or (T, M) float, or None
        Weight of each marker (or each marker in each frame); ``1/sigma_m^2``
        relative to a common scale.
    y : (T, M, D) float
    """
    if weights is None:
        return None
    T, M, D = y.shape
    w = np.asarray(weights, dtype=float)
    if w.shape not in ((M,), (T, M)):
        raise ValueError(f"weights must have shape ({M},) or ({T}, {M}), got {w.shape}")
    if not np.all(np.isfinite(w) & (w >= 0)):
        raise ValueError("weights must be finite and non-negative")
    return np.repeat(np.sqrt(np.broadcast_to(w, (T, M))), D, axis=1)


def weighted_terms(model: Model, theta, q, y, sw=None, ws: Workspace | None = None):
    """:func:`~skelid.estimators.fit.likelihood.frame_terms` with rows scaled by ``sw`` (T, M*D)."""
    r, Jq, Jt = frame_terms(model, theta, q, y, ws)
    if sw is None:
        return r, Jq, Jt
    return r * sw, Jq * sw[..., None], Jt * sw[..., None]


#: steps the accelerated step of :func:`joint_fit` mixes (Anderson depth; see :func:`_anderson_mixed`). With 5
#: instead of 1: case A's fit 65 instead of 74 iterations, the walk's 51 instead of 60 and its jackknife refits
#: 58 instead of 72, estimates within 2e-5 sd, the refits' replicates ten times nearer (3.5e-4 sd) to refits
#: run to the cost's rounding
ANDERSON_DEPTH = 5
STEP_TOL = 1e-7  # a step in theta below this many standard errors (after the damping is gone) ends the fit


def _residuals(model: Model, theta, q, y, sw=None, ws: Workspace | None = None) -> np.ndarray:
    """Residuals ``(T, M*D)`` of :func:`weighted_terms` without the Jacobians (missing markers: 0)."""
    mask = np.isfinite(y).all(axis=-1)
    r = (np.where(mask[..., None], y, 0.0) - marker_positions(model, theta, q, ws)) * mask[..., None]
    r = r.reshape(r.shape[:-2] + (-1,))
    return r if sw is None else r * sw


def _anderson_step(theta, q, dtheta, dq, prev, Htt, Hqq):
    """Step from ``(theta, q)`` that mixes this Gauss-Newton step with the last one (Anderson, depth 1).

    Where the iterates zig-zag or crawl along one direction (the Gauss-Newton map
    contracts slowly there), the two last steps show that direction and its rate,
    and ``x + f - gamma (dx + df)`` with ``gamma = <f, df> / <df, df>`` jumps to
    where the map's linearisation along it is fixed. Inner products are scaled by
    the diagonal of ``J^T J`` (angles and lengths compare). None if undefined.
    """
    theta0, q0, dtheta0, dq0 = prev
    w_t = np.diag(Htt)
    w_q = np.einsum("tii->ti", Hqq)
    df_t, df_q = dtheta - dtheta0, dq - dq0
    den = float(w_t @ df_t**2 + np.sum(w_q * df_q**2))
    if not den > 0.0:
        return None
    gamma = float(w_t @ (dtheta * df_t) + np.sum(w_q * dq * df_q)) / den
    return (dtheta - gamma * (theta - theta0 + df_t), dq - gamma * (q - q0 + df_q))


def _anderson_mixed(theta, q, dtheta, dq, hist, Htt, Hqq):
    """:func:`_anderson_step` over the last ``len(hist)`` steps (Anderson of that depth), or None.

    ``hist``: ``(theta, q, dtheta, dq, x, f)`` of the earlier accepted iterations, oldest first (``x``
    and ``f``: the iterate and its step as flat vectors, theta first). With
    ``f_k`` the Gauss-Newton steps and ``x_k`` the iterates, ``gamma`` minimises
    ``|f - sum_j gamma_j (f_j - f_{j-1})|`` (inner products scaled as in :func:`_anderson_step`) and the
    step is ``f - sum_j gamma_j (x_j - x_{j-1} + f_j - f_{j-1})``: a secant method on the directions
    the last steps span.
    """
    if len(hist) == 1:
        return _anderson_step(theta, q, dtheta, dq, hist[0][:4], Htt, Hqq)
    w = np.sqrt(np.concatenate([np.diag(Htt), np.einsum("tii->ti", Hqq).ravel()]))
    xs = np.stack([h[4] for h in hist] + [np.concatenate([theta, q.ravel()])], axis=1)
    fs = np.stack([h[5] for h in hist] + [np.concatenate([dtheta, dq.ravel()])], axis=1)
    dX, dF = np.diff(xs, axis=1), np.diff(fs, axis=1)
    if not np.all(np.isfinite(dF)):
        return None
    gamma = np.linalg.lstsq(dF * w[:, None], fs[:, -1] * w, rcond=None)[0]
    step = fs[:, -1] - (dX + dF) @ gamma
    P = len(theta)
    return step[:P], step[P:].reshape(q.shape)


def _inverse_diagonal(S) -> np.ndarray:
    """Diagonal of ``S^{-1}`` (``S`` symmetric); the pseudo-inverse's where ``S`` is singular or indefinite."""
    try:
        d = np.diag(np.linalg.inv(S))
    except np.linalg.LinAlgError:
        d = None
    if d is None or not np.all(np.isfinite(d) & (d >= 0.0)):
        d = np.diag(np.linalg.pinv(S))
    return d


def _line_minimum(c0: float, slope: float, c1: float):
    """Minimum of the parabola through ``c(0) = c0``, ``c'(0) = slope``, ``c(1) = c1``, or None.

    A Gauss-Newton step lands at ``alpha = 1`` when the cost is as curved along it as the
    Gauss-Newton model says; where residual curvature makes it twice as curved the iterates
    zig-zag across the valley (and crawl where it is flatter). Returns the step length to try
    instead (between 0.1 and 16), or None when 1 is close enough.
    """
    if not (np.isfinite(c1) and slope < 0.0):
        return None
    a = c1 - c0 - slope
    alpha = 16.0 if a <= 0.0 else min(-slope / (2.0 * a), 16.0)
    return max(alpha, 0.1) if abs(alpha - 1.0) > 0.2 else None


class _LMProblem(NamedTuple):
    """What every iteration of :func:`joint_fit` is measured against: data, weights, penalty, bounds, tolerances."""

    model: Model
    y: np.ndarray  # (T, M, D) markers, NaN where missing or skipped
    sw: np.ndarray | None  # row weights (square roots), see row_weights
    ws: Workspace
    R: object  # the motion-model penalty (sparse, frame-major) or None
    R_band: np.ndarray | None  # R in upper banded form
    bounds: tuple | None
    floor: float  # the cost of residuals at the data's rounding level
    n_rows: int  # marker coordinates in the fit (at least 1)
    tol: float
    step_tol: float
    depth: int  # steps mixed by the Anderson step

    def total(self, r, q) -> float:
        """The cost: the residual sum of squares plus the motion-model penalty ``q^T R q``."""
        c = float(np.sum(r**2))
        return c + float(q.ravel() @ (self.R @ q.ravel())) if self.R is not None else c

    def trial(self, theta, q, alpha: float, dtheta, dq):
        """``(theta, q, r, cost)`` a step of length ``alpha`` along ``(dtheta, dq)`` reaches (theta clipped)."""
        th = theta + alpha * dtheta
        if self.bounds is not None:
            th = np.clip(th, self.bounds[0], self.bounds[1])
        qq = q + alpha * dq
        rr = _residuals(self.model, th, qq, self.y, self.sw, self.ws)
        return th, qq, rr, self.total(rr, qq)


class _LMState(NamedTuple):
    """One iterate of :func:`joint_fit`: the estimate, its residuals and Jacobians, cost, damping, history."""

    theta: np.ndarray  # (P,)
    q: np.ndarray  # (T, Q)
    r: np.ndarray  # (T, m) weighted residuals
    Jq: np.ndarray  # (T, m, Q)
    Jt: np.ndarray  # (T, m, P)
    cost: float
    lam: float  # Levenberg-Marquardt damping
    stalled: bool  # the last accepted step gained less than the tolerance
    hist: list  # (theta, q, dtheta, dq[, x, f]) of the last accepted iterations, for the Anderson step


def _fit_frames(model: Model, y, frames):
    """The markers with the frames the fit skips blanked (NaN: zero rows, no part in the fit), and the frames used.

    Returns ``y (T, M, D)`` and ``use (T,) bool``.
    """
    y = np.asarray(y, dtype=float)
    use = usable_frames(model, y)
    if frames is not None:
        use &= np.asarray(frames, dtype=bool)
    return np.where(use[:, None, None], y, np.nan), use


def _fit_start(model: Model, y, theta, q, use, sw, ws, rate, cutoff, blocks, penalty):
    """The starting poses, their residuals and Jacobians, and the motion-model penalty (None without one).

    Several trials (``blocks``) each get their own penalty and continuous angles; one trial with
    ``rate`` and ``cutoff`` gets :func:`smoothing_penalty`; a given ``penalty`` is used as it is
    (a continued fit's poses already follow its motion model).

    Returns ``q (T, Q)``, ``r (T, m)``, ``Jq (T, m, Q)``, ``Jt (T, m, P)`` and ``R``.
    """
    if blocks is not None and all(c is None or r_ is None for _, _, r_, c in blocks):
        blocks = None  # no trial smoothed: the per-frame fit
    if blocks is not None:
        q = np.concatenate([_continuous_poses(model, q[a:b], use[a:b]) for a, b, *_ in blocks])
        r, Jq, Jt = weighted_terms(model, theta, q, y, sw, ws)
        return q, r, Jq, Jt, block_penalty(model, pose_information(Jq), blocks)
    if penalty is None and (cutoff is None or rate is None):
        return (q, *weighted_terms(model, theta, q, y, sw, ws), None)
    if penalty is None:  # a continued fit's poses already follow its motion model
        q = _continuous_poses(model, q, use)
    r, Jq, Jt = weighted_terms(model, theta, q, y, sw, ws)
    R = penalty if penalty is not None else smoothing_penalty(model, pose_information(Jq), rate, cutoff)
    return q, r, Jq, Jt, R


def _rounding_floor(y, n_rows: int) -> float:
    """The cost of residuals at the data's rounding level (``1e-12`` of the largest coordinate per row).

    Noise-free data converge to it.
    """
    return n_rows * (1e-12 * max(float(np.nanmax(np.abs(y))) if np.isfinite(y).any() else 1.0, 1e-300)) ** 2


def _damped_step(pb: _LMProblem, s: _LMState, Hqq, Hqt, Htt, gq, gt):
    """The damped Gauss-Newton step ``(dtheta, dq)``, the reduced information ``S`` and the cost's slope along it.

    Raises ``numpy.linalg.LinAlgError``, ``RuntimeError`` or ``ValueError`` where the damped system
    cannot be solved.
    """
    active = None
    if pb.bounds is not None:
        lo, hi = pb.bounds
        tol = 1e-9 * np.maximum(np.asarray(hi, float) - np.asarray(lo, float), 1e-300)
        at_lo, at_hi = s.theta <= lo + tol, s.theta >= hi - tol

        def active(dt):  # a parameter on a bound that the step would push beyond it stays there
            return (at_lo & (dt < 0)) | (at_hi & (dt > 0))
    if pb.R is None:
        dtheta, dq, S = _schur_step(Hqq, Hqt, Htt, gq, gt, s.lam, active)
        slope = -2.0 * (float(gt @ dtheta) + float(np.sum(gq * dq)))
    else:
        dtheta, dq, S = _schur_step_smooth(Hqq, Hqt, Htt, gq, gt, s.lam, pb.R, s.q, pb.R_band, active)
        slope = -2.0 * (float(gt @ dtheta) + float(np.sum(gq * dq)) - float(s.q.ravel() @ (pb.R @ dq.ravel())))
    return dtheta, dq, S, slope


def _lower(best, other):
    """The trial of the two with the lower cost (``best`` on a tie or where ``other``'s is not finite)."""
    return other if np.isfinite(other[3]) and not other[3] >= best[3] else best


def _best_trial(pb: _LMProblem, s: _LMState, dtheta, dq, slope: float, Htt, Hqq):
    """The lowest-cost trial of the full step, the line minimum along it and the Anderson step.

    The line minimum (:func:`_line_minimum`) is tried where the cost along the step is far from the
    Gauss-Newton model's; the Anderson step (:func:`_anderson_mixed`) once the damping is small.
    """
    best = pb.trial(s.theta, s.q, 1.0, dtheta, dq)
    alpha = _line_minimum(s.cost, slope, best[3])
    if alpha is not None:  # the cost along the step is far from the Gauss-Newton model's
        best = _lower(best, pb.trial(s.theta, s.q, alpha, dtheta, dq))
    if s.hist and s.lam <= 1e-4:
        mixed = _anderson_mixed(s.theta, s.q, dtheta, dq, s.hist, Htt, Hqq)
        if mixed is not None:
            best = _lower(best, pb.trial(s.theta, s.q, 1.0, *mixed))
    return best


def _accept(pb: _LMProblem, s: _LMState, best, dtheta, dq, S) -> tuple[_LMState, bool]:
    """The state after an accepted trial, and whether the fit has converged.

    Converged: with the damping gone, the cost fell by less than ``tol`` (relative) and the step
    moved no parameter by more than ``step_tol`` of its standard error (noise from the residuals).
    """
    theta, q = s.theta, s.q
    flat = (np.concatenate([theta, q.ravel()]), np.concatenate([dtheta, dq.ravel()])) if pb.depth > 1 else ()
    hist = [*s.hist, (theta, q, dtheta, dq, *flat)][-pb.depth:]
    theta_new, q_new, _, cost_new = best
    small = (s.cost - cost_new) <= pb.tol * s.cost + pb.floor
    # the step in theta against theta's standard error (noise from the residuals)
    sd = np.sqrt(np.clip(_inverse_diagonal(S), 0.0, None) * max(cost_new, pb.floor) / pb.n_rows)
    still = bool(np.all(np.abs(theta_new - theta) <= pb.step_tol * sd + 1e-12 * np.maximum(np.abs(theta), 1.0)))
    r, Jq, Jt = weighted_terms(pb.model, theta_new, q_new, pb.y, pb.sw, pb.ws)
    lam = max(s.lam * 0.3, 1e-12)
    # a damped step's small gain says nothing about convergence
    return _LMState(theta_new, q_new, r, Jq, Jt, cost_new, lam, small, hist), bool(small and still and lam <= 1e-4)


def _reject(s: _LMState, best) -> tuple[_LMState, bool]:
    """The state after a trial that raised the cost (more damping, no history), and whether to stop.

    Stops where no descent direction is left, or only steps the cost's rounding cannot tell apart.
    """
    lam = s.lam * 10.0
    at_rounding = s.stalled and np.isfinite(best[3]) and best[3] - s.cost <= 1e-11 * abs(s.cost)
    return s._replace(hist=[], lam=lam), bool(lam > 1e12 or (s.stalled and lam > 1e2) or at_rounding)


def _lm_iteration(pb: _LMProblem, s: _LMState) -> tuple[_LMState, bool]:
    """One Levenberg-Marquardt iteration of :func:`joint_fit`: the next state and whether the fit has converged."""
    Hqq, Hqt, Htt, gq, gt = _normal_blocks(s.r, s.Jq, s.Jt)
    try:
        dtheta, dq, S, slope = _damped_step(pb, s, Hqq, Hqt, Htt, gq, gt)
    except (np.linalg.LinAlgError, RuntimeError, ValueError):
        return s._replace(lam=s.lam * 10.0), False
    best = _best_trial(pb, s, dtheta, dq, slope, Htt, Hqq)
    if np.isfinite(best[3]) and best[3] <= s.cost:
        return _accept(pb, s, best, dtheta, dq, S)
    return _reject(s, best)


def _fit_information(model: Model, pb: _LMProblem, s: _LMState, use, summary: bool):
    """``info`` (the information about theta, unit noise) and ``pose_dof`` at the fit's end.

    Without a motion model ``info = sum_t K_perp^T K_perp`` and every used frame's pose counts in
    full; with one, ``info`` is the reduced information of the smoothed normal equations and
    ``pose_dof`` the poses' effective number (:func:`pose_edf`). ``summary`` False: None and NaN.
    """
    if not summary:
        return None, float("nan")
    if pb.R is None:
        Kp = projected_theta_jacobian(s.Jq, s.Jt)
        return summed_gram(Kp), float(model.n_pose * use.sum())
    Hqq, Hqt, Htt, gq, gt = _normal_blocks(s.r, s.Jq, s.Jt)
    *_, info = _schur_step_smooth(Hqq, Hqt, Htt, gq, gt, 0.0, pb.R, s.q, pb.R_band)
    return info, pose_edf(s.Jq, pb.R, pb.R_band)  # skipped frames have no rows: they add nothing


def joint_fit(model: Model, y, theta0, q0, n_iter: int = 100, tol: float = 1e-10,
              bounds: tuple | None = None, rate: float | None = None,
              cutoff: float | None = None, frames=None, weights=None, blocks=None, penalty=None,
              step_tol: float = STEP_TOL, ws: Workspace | None = None, summary: bool = True,
              anderson_depth: int | None = None) -> JointFit:
    """Least squares over ``theta`` and all poses.

    Parameters
    ----------
    y : (T, M, D) float
        Markers (model units), NaN where missing.
    theta0 : (P,) float
    q0 : (T, Q) float
        Starting poses (e.g. from :func:`skelid.estimators.fit.pose.track_poses`).
    bounds : (lower (P,), upper (P,)), optional
        Keep ``theta`` inside these bounds (steps are clipped).
    rate, cutoff : float, optional
        With both, poses follow the low-pass motion model of
        :func:`smoothing_penalty` (cutoff in Hz); ``info`` is then the
        information about ``theta`` given that motion model.
    frames : (T,) bool, optional
        Frames allowed into the fit (others are skipped), on top of the count
        of :func:`usable_frames`.
    weights : (M,) or (T, M) float, optional
        Weighted least squares: each marker's residual and Jacobian rows are
        scaled by the square root of its weight (``1/sigma_m^2`` up to a common
        factor). ``rss`` and ``info`` are then weighted ones: ``rss / dof``
        estimates that common factor.
    blocks : sequence of (start, stop, rate, cutoff), optional
        Several trials stacked along the frame axis: each block of frames gets
        its own motion-model penalty (rate and cutoff; cutoff None for none)
        and no smoothing crosses a block boundary. Replaces ``rate``/``cutoff``.
    penalty : scipy.sparse matrix, optional
        The motion-model penalty of an earlier fit (its ``penalty``), used as it
        is instead of one built from the starting poses (with ``rate`` and
        ``cutoff``): continuing a fit then minimises the same cost.
    step_tol : float
        The fit has converged when, with the damping gone, the cost falls by less
        than ``tol`` (relative) or a step moves no parameter by more than
        ``step_tol`` of its standard error (the noise taken from the residuals).
        A loose value (``1e-3``) suffices for a fit whose estimate is not reported.
    ws : Workspace, optional
        The model's workspace (one is made for this fit without it).
    summary : bool
        Compute ``info`` and ``pose_dof`` at the end (False: None and NaN, for a
        fit that is only compared by its cost).
    anderson_depth : int, optional
        Steps mixed by the accelerated step tried beside each Gauss-Newton step
        (:func:`_anderson_mixed`; default ``ANDERSON_DEPTH``).
    """
    if ws is None:
        ws = Workspace(model)
    y, use = _fit_frames(model, y, frames)
    sw = row_weights(weights, y)
    q, r, Jq, Jt, R = _fit_start(model, y, np.array(theta0, dtype=float), np.array(q0, dtype=float), use, sw, ws,
                                 rate, cutoff, blocks, penalty)
    n_rows = max(int(np.isfinite(y).all(axis=-1).sum() * model.dim), 1)
    pb = _LMProblem(model, y, sw, ws, R, None if R is None else penalty_band(R, model.n_pose), bounds,
                    _rounding_floor(y, n_rows), n_rows, tol, step_tol,
                    ANDERSON_DEPTH if anderson_depth is None else int(anderson_depth))
    s = _LMState(np.array(theta0, dtype=float), q, r, Jq, Jt, pb.total(r, q), 1e-3, False, [])
    converged = False
    it = 0
    for it in range(1, n_iter + 1):  # noqa: B007 - the count is reported
        if s.cost <= pb.floor:  # the residuals are rounding: nothing left to fit
            converged = True
            break
        s, stop = _lm_iteration(pb, s)
        if stop:
            converged = True
            break
    info, pose_dof = _fit_information(model, pb, s, use, summary)
    return JointFit(s.theta, s.q, float(np.sum(s.r**2)), np.sum(s.r**2, axis=1), info,
                    int(np.isfinite(y).all(axis=-1).sum() * model.dim), use, it, converged, pose_dof, R)


def box_bias(model: Model, y, theta, q, sigma2: float, step: float = 1e-4, weights=None,
             pose_var: list | None = None) -> np.ndarray:
    """Second-order bias ``b_theta`` (P,) of the joint least-squares estimate.

    Parameters
    ----------
    y : (T, M, D) float
        Markers (only the missing-marker pattern is used).
    theta : (P,) float
    q : (T, Q) float
        The fit's poses.
    sigma2 : float
        Noise variance.
    step : float
        Relative size of the finite-difference step along each direction.
    weights : (M,) or (T, M) float, optional
        Marker weights of a weighted fit (``sigma2`` is then the variance of a
        weighted residual): every row ``f_i`` becomes ``sqrt(w_i) f_i``.
    pose_var : list, optional
        When given, the variance of each pose estimate per frame, ``(T, Q)`` (the diagonal of
        the pose blocks of ``sigma2 C``), is appended to it.
    """
    P, Q = model.n_params, model.n_pose
    sw = row_weights(weights, np.asarray(y, float))
    r, Jq, Jt = weighted_terms(model, theta, q, y, sw)
    Hqq = pose_information(Jq)
    Hqt = frame_gram(Jq, Jt)
    Hqq_inv = np.linalg.pinv(Hqq, hermitian=True)
    G = Hqq_inv @ Hqt  # (T, Q, P)
    Kp = Jt - Jq @ G
    S = summed_gram(Kp)
    S_inv = np.linalg.inv(S)
    T = len(q)
    C = np.empty((T, P + Q, P + Q))
    C[:, :P, :P] = S_inv
    C[:, P:, :P] = -G @ S_inv
    C[:, :P, P:] = np.swapaxes(C[:, P:, :P], 1, 2)
    C[:, P:, P:] = Hqq_inv + G @ S_inv @ np.swapaxes(G, 1, 2)
    if pose_var is not None:
        pose_var.append(sigma2 * np.clip(np.diagonal(C[:, P:, P:], axis1=1, axis2=2), 0.0, None))
    w, V = np.linalg.eigh(C)
    L = V * np.sqrt(np.clip(w, 0.0, None))[:, None, :]  # (T, P+Q, K) columns l_k
    # directional second derivatives along each column, all frames and directions at once
    norms = np.linalg.norm(L, axis=1, keepdims=True)  # (T, 1, K)
    h = step / np.maximum(norms, 1e-300)
    dirs = np.swapaxes(L, 1, 2)  # (T, K, P+Q)
    th = theta[None, None, :] + 0.0 * dirs[..., :P]
    qq = q[:, None, :] + 0.0 * dirs[..., P:]
    hh = np.swapaxes(h, 1, 2)  # (T, K, 1)
    _, Jq_p, Jt_p = marker_jacobian(model, th + hh * dirs[..., :P], qq + hh * dirs[..., P:])
    _, Jq_m, Jt_m = marker_jacobian(model, th - hh * dirs[..., :P], qq - hh * dirs[..., P:])
    Jp = np.concatenate([Jt_p, Jq_p], axis=-1)  # (T, K, M, D, P+Q)
    Jm = np.concatenate([Jt_m, Jq_m], axis=-1)
    second = np.einsum("tkmdj,tkj->tkmd", Jp - Jm, dirs) / (2.0 * hh[..., None])
    mask = np.isfinite(y).all(axis=-1)
    d = (second.sum(axis=1) * mask[..., None]).reshape(T, -1)  # (T, M*D)
    if sw is not None:
        d = d * sw
    return -0.5 * sigma2 * S_inv @ summed_product(Kp, d)


def frame_scores(model: Model, y, theta, q, weights=None) -> np.ndarray:
    """Per-frame scores ``((I-P_t)K_t)^T r_t``: ``(T, P)`` (weighted rows with ``weights``)."""
    r, Jq, Jt = weighted_terms(model, theta, q, y, row_weights(weights, np.asarray(y, float)))
    return np.einsum("tkp,tk->tp", projected_theta_jacobian(Jq, Jt), r)


def smoothed_frame_scores(model: Model, y, theta, q, R, weights=None) -> np.ndarray:
    """Per-frame scores ``(T, P)`` of the motion-model fit that sum to its reduced gradient.

    With ``A = blockdiag(J_t^T J_t) + R`` and ``G = A^{-1} H_{q theta}``,
    ``g_t = (K_t - J_t G_t)^T r_t + G_t^T (R q)_t``; their sum is the gradient in
    ``theta`` after the poses are eliminated (zero at the optimum), so their
    long-run covariance goes with the information ``S`` of :func:`joint_fit`.
    """
    r, Jq, Jt = weighted_terms(model, theta, q, y, row_weights(weights, np.asarray(y, float)))
    A, G = influence_rows(Jq, Jt, R)
    Rq = (R @ q.ravel()).reshape(q.shape)
    return np.einsum("tkp,tk->tp", A, r) + np.einsum("tqp,tq->tp", G, Rq)


def influence_rows(Jq, Jt, R=None, R_band=None):
    """Rows ``A_t = K_t - J_t G_t`` through which the markers move the fit's ``theta``.

    ``G = (blockdiag(J_t^T J_t) + R)^{-1} H_{q theta}`` (per frame when ``R`` is
    None). To first order a marker perturbation ``delta`` moves the estimate by
    ``S^{-1} sum_t A_t^T delta_t`` with ``S = sum_t K_t^T A_t``.

    Parameters
    ----------
    Jq : (T, m, Q) float
    Jt : (T, m, P) float
    R : sparse (T*Q, T*Q), optional
    R_band : (u+1, T*Q) float, optional
        ``R`` in upper banded form (:func:`penalty_band`), when the caller has it.

    Returns
    -------
    A : (T, m, P) float
    G : (T, Q, P) float
    """
    T, _, Q = Jq.shape
    P = Jt.shape[-1]
    Hqq = pose_information(Jq)
    Hqt = np.matmul(np.swapaxes(Jq, -1, -2), Jt)
    if R is None:
        G = np.linalg.pinv(Hqq, hermitian=True) @ Hqt
    else:
        G = _banded_solver(Hqq, R, R_band)(Hqt.reshape(T * Q, P)).reshape(T, Q, P)
    return Jt - Jq @ G, G


def newey_west(scores, lags: int) -> np.ndarray:
    """Long-run covariance ``(P, P)`` of a score series ``(T, P)`` (Bartlett weights)."""
    s = scores - scores.mean(axis=0)
    out = s.T @ s
    for lag in range(1, lags + 1):
        w = 1.0 - lag / (lags + 1.0)
        g = s[lag:].T @ s[:-lag]
        out += w * (g + g.T)
    return out


def lag1_autocorrelation(x, used=None) -> float:
    """Mean lag-1 autocorrelation of the series in ``x (T, ...)`` over the frames ``used`` (default: all).

    Each column of ``x`` (a residual coordinate, a marker's residual distance, a per-frame
    value) is one series; NaN entries are left out. Measurement noise gives values near 0,
    slow drift (soft-tissue artefact) values near 1; fewer than 4 frames give 0.
    """
    r = np.asarray(x, float)
    r = r if used is None else r[np.asarray(used, bool)]
    r = r.reshape(len(r), -1)
    if len(r) < 4:
        return 0.0
    r = r - np.nanmean(r, axis=0)
    num = np.nansum(r[1:] * r[:-1], axis=0)
    den = np.nansum(r**2, axis=0)
    ok = den > 0
    return float(np.mean(num[ok] / den[ok])) if ok.any() else 0.0


def smoothed_bias(model: Model, y, theta, q, sigma2: float, R, step: float = 1e-4,
                  max_frames: int | None = None, weights=None, pose_var: list | None = None) -> np.ndarray:
    """Second-order bias ``b_theta`` (P,) of the joint fit under the motion-model penalty ``R``.

    For ``min ||y - f(beta)||^2 + beta^T R beta`` (``R`` acts on the poses) the
    expansion of the estimating equation to second order in the noise gives

    .. math:: b = \\sigma^2 C\\,\\big(-\\tfrac12 J^\\top d + \\textstyle\\sum_i \\nabla^2 f_i\\, v_i\\big),
              \\quad C = (J^\\top J + R)^{-1},

    with ``d_i = tr(C J^T J C \\nabla^2 f_i)`` and ``v_i = (C R C J^T)_{:, i}``;
    without a penalty it is Box's formula. The regularisation bias
    ``-C R beta`` of a motion that is not exactly smooth is not included. Long
    trials are cut into pieces of ``max_frames`` (default: 2400 pose
    coordinates' worth) whose biases are averaged with their information as weights.
    With marker ``weights`` (see :func:`box_bias`) every row is scaled by ``sqrt(w_i)``.
    With a list ``pose_var``, the variance of each pose estimate per frame ``(T, Q)`` (the
    diagonal of the pose blocks of ``sigma2 C``, piece by piece) is appended to it.
    """
    T = len(q)
    if max_frames is None:
        max_frames = max(50, 2400 // model.n_pose)
    if T > max_frames:
        num, den = smoothed_bias_sums(model, y, theta, q, sigma2, R, step, max_frames, weights, pose_var)
        return np.linalg.solve(den, num)
    pieces = None if pose_var is None else []
    if weights is not None:
        weights = np.broadcast_to(np.asarray(weights, float), np.asarray(y).shape[:2])
    b = _smoothed_bias_dense(model, y, theta, q, sigma2, R, step, weights, pieces)[0]
    if pieces is not None:
        pose_var.append(pieces[0])
    return b


def smoothed_bias_sums(model: Model, y, theta, q, sigma2: float, R, step: float = 1e-4,
                       max_frames: int | None = None, weights=None, pose_var: list | None = None,
                       theta_known: bool = False, ws: Workspace | None = None):
    """:func:`smoothed_bias`'s pieces summed: ``(sum_k S_k b_k (P,), sum_k S_k (P, P))``.

    ``S_k`` is piece ``k``'s information about theta (unit noise), ``b_k`` its bias: sums over frames
    that can be added to (a live session's blocks); the bias of them all is ``solve(sum S, sum S b)``
    where the sum is definite. With ``theta_known``, each piece's expansion takes theta as known (the
    limit of many frames besides it, :func:`_arrow_inverse_blocks`): its terms of order ``sigma^2 / T`` are
    left out, and a piece that alone leaves theta unidentified (a joint still in it) has a bias. ``ws``: the
    kinematics' workspace (a new one if None).
    """
    T = len(q)
    pieces = None if pose_var is None else []
    if weights is not None:
        weights = np.broadcast_to(np.asarray(weights, float), np.asarray(y).shape[:2])
    if max_frames is None:
        max_frames = max(50, 2400 // model.n_pose)
    edges = np.linspace(0, T, max(1, int(np.ceil(T / max_frames))) + 1).astype(int)
    num, den = 0.0, 0.0
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        Rp = smoothing_penalty_like(R, T, model.n_pose, a, b)
        _, S, score = _smoothed_bias_dense(model, y[a:b], theta, q[a:b], sigma2, Rp, step,
                                           None if weights is None else weights[a:b], pieces, theta_known, ws)
        num = num + score
        den = den + S
    if pieces is not None:
        pose_var.append(np.concatenate(pieces))
    return num, den


def smoothing_penalty_like(R, T: int, Q: int, a: int, b: int):
    """The part of a frame-major penalty ``R`` that couples frames ``a..b-1`` only."""
    return R[a * Q:b * Q, a * Q:b * Q]


def _arrow_inverse_blocks(Hqq, Hqt, Htt, R, scale: float = 1.0, theta_known: bool = False, R_band=None):
    """Diagonal ``(theta, q_t)`` blocks of ``C = N^{-1}`` for the arrow matrix of a smoothed joint fit.

    ``N = s [[Htt, Hqt^T], [Hqt, blockdiag(Hqq)]] + [[0, 0], [0, R]]`` with ``s = scale``; with
    ``theta_known``, the limit of information about theta from elsewhere without bound (``S^{-1} = 0``: the
    poses' own covariance only).
    Eliminating the poses, ``A = s blockdiag(Hqq) + R`` (banded), ``G = A^{-1} s Hqt``,
    ``S = s Htt - s Hqt^T G``; then ``C_{theta theta} = S^{-1}``,
    ``C_{q_t theta} = -G_t S^{-1}`` and ``C_{q_t q_t} = (A^{-1})_{tt} + G_t S^{-1} G_t^T``,
    with the diagonal blocks of ``A^{-1}`` from :func:`band_inverse_blocks` (linear in frames).

    Returns
    -------
    blocks : (T, P+Q, P+Q) float
    S_inv : (P, P) float
    G : (T, Q, P) float
    """
    from scipy.linalg import cho_solve_banded, cholesky_banded

    T, Q = Hqq.shape[:2]
    P = Htt.shape[0]
    for ridge in (0.0, 1e-10):  # exact unless a frame without markers leaves it singular
        ab = _banded_system(scale * Hqq, R, ridge, R_band)
        try:
            U = cholesky_banded(ab, lower=False, check_finite=False)
            break
        except np.linalg.LinAlgError:
            continue
    G = cho_solve_banded((U, False), scale * Hqt.reshape(T * Q, P), check_finite=False).reshape(T, Q, P)
    if theta_known:
        S_inv = np.zeros((P, P))
    else:
        S = scale * Htt - scale * summed_gram(Hqt, G)
        S_inv = np.linalg.inv(0.5 * (S + S.T))
    GS = G @ S_inv  # (T, Q, P)
    out = np.empty((T, P + Q, P + Q))
    out[:, :P, :P] = S_inv
    out[:, P:, :P] = -GS
    out[:, :P, P:] = -np.swapaxes(GS, 1, 2)
    out[:, P:, P:] = band_inverse_blocks(ab, Q) + GS @ np.swapaxes(G, 1, 2)
    return out, S_inv, G


#: relative step of the derivative that gives the diagonal blocks of C J^T J C (see _smoothed_bias_terms)
_SANDWICH_STEP = 1e-4


def _smoothed_bias_dense(model, y, theta, q, sigma2, R, step, weights=None, pose_var=None,
                         theta_known: bool = False, ws: Workspace | None = None):
    """The bias ``b`` of one piece of a trial (see :func:`smoothed_bias`), its information ``S`` and ``S b``.

    Linear in frames: only diagonal ``(theta, q_t)`` blocks of ``C = N^{-1}`` and of
    ``C R C`` are needed. The first come from :func:`_arrow_inverse_blocks`; for
    the second, ``C J^T J C = -dC(s)/ds`` at ``s = 1`` where ``C(s)`` is the inverse
    with ``J^T J`` scaled by ``s``, so its diagonal blocks are a central difference of
    two more :func:`_arrow_inverse_blocks` (relative error ``~ _SANDWICH_STEP^2``), and
    ``C R C = C - C J^T J C``.
    """
    P, Q = model.n_params, model.n_pose
    T = len(q)
    ws = Workspace(model) if ws is None else ws
    sw = row_weights(weights, np.asarray(y, float))
    _, Jq, Jt = weighted_terms(model, theta, q, y, sw, ws)
    m = Jq.shape[1]
    Hqq = pose_information(Jq)
    Hqt = frame_gram(Jq, Jt)
    Htt = summed_gram(Jt)
    h = _SANDWICH_STEP
    R_band = penalty_band(R, Q)  # the same penalty in all three
    plus, _, _ = _arrow_inverse_blocks(Hqq, Hqt, Htt, R, 1.0 + h, theta_known, R_band)
    minus, _, _ = _arrow_inverse_blocks(Hqq, Hqt, Htt, R, 1.0 - h, theta_known, R_band)
    Cdiag, S_inv, G = _arrow_inverse_blocks(Hqq, Hqt, Htt, R, theta_known=theta_known, R_band=R_band)
    if pose_var is not None:  # the variance of each pose estimate, for the check of the expansion
        pose_var.append(sigma2 * np.clip(np.diagonal(Cdiag[:, P:, P:], axis1=1, axis2=2), 0.0, None))
    Sig = (minus - plus) / (2.0 * h)  # blocks of C J^T J C (unit noise)
    Sig = 0.5 * (Sig + np.swapaxes(Sig, 1, 2))
    CRC = Cdiag - Sig  # blocks of C R C
    mask = np.isfinite(y).all(axis=-1)
    wmask = np.repeat(mask, model.dim, axis=1).astype(float)  # (T, m)
    if sw is not None:
        wmask = wmask * sw  # a weighted row's second derivatives scale with it

    def jac_full(th, qq):
        return stacked_jacobian(model, th, qq, ws).reshape(th.shape[:-1] + (m, P + Q))

    # one central difference of the Jacobian along each coordinate of (theta, q_t) gives every
    # second derivative the formula needs: DJ[t, j, i, l] = d^2 f_i / d beta_j d beta_l
    eye = np.eye(P + Q)
    shape = (T, P + Q, P)
    Jp = jac_full(np.broadcast_to(theta + step * eye[:, :P], shape), q[:, None, :] + step * eye[None, :, P:])
    Jm = jac_full(np.broadcast_to(theta - step * eye[:, :P], shape), q[:, None, :] - step * eye[None, :, P:])
    DJ = (Jp - Jm) / (2.0 * step)  # (T, P+Q, m, P+Q)
    # the contractions over DJ as batched matrix products (BLAS; einsum's own loops were slower)
    d = (DJ @ np.swapaxes(Sig, 1, 2)[..., None])[..., 0].sum(axis=1) * wmask  # d_i = tr(Sig H_i), (T, m)
    Jfull = np.concatenate([Jt, Jq], axis=-1)  # (T, m, P+Q)
    v = np.einsum("tkl,til->tik", CRC, Jfull)  # (T, m, P+Q): v_i restricted to the frame block
    u = (DJ.reshape(T, P + Q, -1) @ (v * wmask[..., None]).reshape(T, -1, 1))[..., 0]  # sum_i H_i v_i per block
    wvec = -0.5 * np.einsum("tij,ti->tj", Jfull, d) + u  # (T, P+Q)
    # b = sigma^2 C[:P] w with C[theta, theta] = S^{-1}, C[theta, q_t] = -S^{-1} G_t^T
    score = sigma2 * (wvec[:, :P].sum(axis=0) - np.einsum("tqp,tq->p", G, wvec[:, P:]))  # = S b
    S = Htt - summed_gram(Hqt, G) if theta_known else np.linalg.inv(S_inv)
    return S_inv @ score, S, score
