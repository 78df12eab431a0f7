"""Pose fitting: the per-frame nuisance of every estimator.

For fixed parameters ``theta`` the pose of frame ``t`` minimises the marker
residual over the markers present in that frame,

.. math:: \\hat q_t(\\theta) = \\arg\\min_q \\sum_{m \\in P(t)} \\lVert y_{tm} - x_m(q, \\theta)\\rVert^2 ,

solved by Levenberg-Marquardt, batched over any leading axes (frames,
hypotheses).

**Starting poses.** Least squares over a tree of joints has many local minima,
so the start matters. Every segment that shows at least three non-collinear
markers in a frame gets its placement from a rigid fit of its model markers
``r`` to the observed ``y`` (Kabsch): with weights ``w`` (1 if present),
centroids ``\\bar r, \\bar y`` and ``H = \\sum w (r - \\bar r)(y - \\bar y)^\\top = U S V^\\top``,

.. math:: R = V \\,\\mathrm{diag}(1, \\dots, \\det V U^\\top)\\, U^\\top, \\qquad p = \\bar y - R \\bar r .

Joint coordinates then follow by inverse kinematics of the relative rotation
``R_{rel} = R_{parent}^\\top R_{segment}``: Euler angles z-x-y for ``free`` and
``spherical`` joints, ``atan2(a\\cdot\\mathrm{vee}(R-R^\\top), \\mathrm{tr}R - a^\\top R a)``
for a hinge about ``a`` (the best rotation about ``a`` in the Frobenius sense),
and the first axis from where ``R_{rel}`` takes the second, then the second as a
hinge, for ``universal`` joints. This is done for all frames at once.

Coordinates that no rigid fit determines (a segment with fewer than three
markers, or whose parent has none) start from the previous frame's pose (a
linear prediction from the previous two), or, in the first frame, from the best
of many random starts; Levenberg-Marquardt then polishes every coordinate. Only
frames with such coordinates go through this sequential pass (the one loop over
frames); the final refinement is batched over all frames.
"""

from __future__ import annotations

import numpy as np

from skelid.estimators.fit import _lm_kernel
from skelid.model.description import Model
from skelid.model.kinematics import (
    Workspace,
    _forward_general,
    _forward_planar,
    _rotation,
    geometry,
    kinematics_plan,
    pose_jacobian_from_plan,
    tilt_tables,
    tilted_axes,
)


def workspace(model: Model) -> Workspace:
    """A :class:`~skelid.model.kinematics.Workspace` for ``model`` whose pose fits take one path.

    The compiled kernel is used if it can run now (see
    :func:`skelid.estimators.fit._lm_kernel.ready`: numba installed, not
    ``SKELID_NUMBA=0``, the kernel compiled or in numba's cache); otherwise
    every pose fit with this workspace takes the numpy path, even if the
    kernel's background compilation finishes meanwhile. An estimator creates
    one at the start of a fit, so a fit never switches path halfway and
    reports which one it took (``Workspace.path``).
    """
    ws = Workspace(model)
    ws.compiled = _lm_kernel.ready(_lm_kernel.driver_key(ws.plan))
    return ws


def fit_pose(model: Model, theta, y, q0, n_iter: int = 30, tol: float = 1e-10, damping: float = 1e-3,
             ws: Workspace | None = None):
    """Least-squares pose for each frame (and hypothesis).

    Parameters
    ----------
    model : Model
    theta : (..., P) float
    y : (..., M, D) float
        Observed markers; NaN where missing.
    q0 : (..., Q) float
        Starting poses.
    n_iter : int
        Maximum Levenberg-Marquardt iterations.
    tol : float
        Relative decrease of the residual sum of squares that stops the iteration.
    damping : float
        Initial Levenberg-Marquardt damping; a larger value keeps the first
        steps short (tracking from a good prediction).

    Returns
    -------
    q : (..., Q) float
        Fitted poses.
    rss : (...) float
        Residual sum of squares at ``q``.

    Notes
    -----
    Each iteration solves
    ``(J^T J + \\lambda\\,\\mathrm{diag}(J^T J) + \\rho I)\\,\\delta = J^T r`` with
    ``\\rho = 10^{-9}`` times the mean of ``\\mathrm{diag}(J^T J)``, for every batch
    element; a step that does not lower the element's RSS is rejected and its
    ``\\lambda`` multiplied by 10 (by 0.3 on success). An element whose normal
    equations are not finite (it went astray) takes no step. All elements
    iterate together until every one has stopped improving (relative decrease
    below ``tol``) or is stuck (``\\lambda > 10^8``). A compiled kernel runs
    the same iteration once it is compiled (see
    :mod:`skelid.estimators.fit._lm_kernel`); set ``SKELID_NUMBA=0`` to use numpy.
    """
    q, cost, _ = _fit(model, theta, y, q0, n_iter, tol, damping, False, ws)
    return q, cost


def fit_pose_logdet(model: Model, theta, y, q0, n_iter: int = 30, tol: float = 1e-10, damping: float = 1e-3,
                    ws: Workspace | None = None):
    """:func:`fit_pose` plus ``log det J^T J`` at the fitted pose.

    Returns
    -------
    q : (..., Q) float
    rss : (...) float
    logdet : (...) float
        ``log det J^T J`` of the pose Jacobian (missing markers give zero rows);
        ``-inf`` where it is not positive (the pose is not determined).
    """
    return _fit(model, theta, y, q0, n_iter, tol, damping, True, ws)


def _fit(model, theta, y, q0, n_iter, tol, damping, want_logdet, ws=None):
    y = np.asarray(y, dtype=float)
    theta = np.asarray(theta, dtype=float)
    mask = np.isfinite(y).all(axis=-1)
    y0 = np.where(mask[..., None], y, 0.0)
    q = np.array(q0, dtype=float)
    batch = np.broadcast_shapes(q.shape[:-1], y.shape[:-2], theta.shape[:-1])
    if ws is None:
        ws = workspace(model)
    plan = kinematics_plan(model, ws)
    g = geometry(model, theta)
    tilt = tilt_tables(model, theta)
    tables = _kernel_tables(ws)
    if tables is not None:
        return _fit_compiled(plan, tables, g, tilt, y0, mask, q, batch, n_iter, tol, damping, want_logdet)
    return _fit_numpy(plan, g, tilt, y0, mask, q, batch, n_iter, tol, damping, want_logdet)


def _kernel_tables(ws: Workspace) -> tuple | None:
    """The compiled kernel's model tables (made once, kept in the workspace).

    None where the numpy path fits: the workspace was made for it (without
    numba, or while the kernel was not yet compiled; see :func:`workspace`),
    or a model the kernel cannot represent.
    """
    if not ws.compiled:
        return None
    if ws.kernel_tables is None:
        ws.kernel_tables = _lm_kernel.plan_arrays(ws.plan)
    return ws.kernel_tables


def _batch_last(a, batch, tail) -> np.ndarray:
    """``a (..., *tail)`` broadcast to ``batch + tail`` and stored as ``tail + (B,)``, contiguous."""
    if not batch:  # one element (the frame-by-frame tracking): a plain copy
        out = np.empty(tail + (1,))
        out[..., 0] = a
        return out
    B = int(np.prod(batch))
    out = np.empty(tail + (B,))
    out.reshape(tail + batch)[...] = np.moveaxis(np.broadcast_to(a, batch + tail),
                                                 tuple(range(len(batch))), tuple(range(-len(batch), 0)))
    return out


def _tilts_batch_last(tilt, batch) -> tuple:
    if tilt is None:
        return _lm_kernel.no_tilts(int(np.prod(batch)))
    T = tilt.axis.shape[-2]
    return (_batch_last(tilt.axis, batch, (T, 3)), _batch_last(tilt.skew, batch, (T, 3, 3)),
            _batch_last(tilt.skew2, batch, (T, 3, 3)))


def _fit_compiled(plan, tables, g, tilt, y0, mask, q, batch, n_iter, tol, damping, want_logdet):
    Q, M, D = plan.n_pose, plan.n_markers, plan.dim
    gT = _batch_last(g, batch, g.shape[-1:])
    yT = _batch_last(y0, batch, (M, D))
    wT = _batch_last(mask, batch, (M,))
    qT = _batch_last(q, batch, (Q,))  # the kernel writes the fitted poses into it
    cost, logdet = _lm_kernel.lm_fit(gT, yT, wT, qT, int(n_iter), float(tol), float(damping), bool(want_logdet),
                                     D, plan.n_segments, M, _tilts_batch_last(tilt, batch), *tables)
    return (np.moveaxis(qT.reshape((Q,) + batch), 0, -1), cost.reshape(batch),
            logdet.reshape(batch) if want_logdet else None)


class FramePoseFitter:
    """Fit one frame's pose for each of K fixed hypotheses, frame after frame.

    The online grid filter calls this once per frame: the geometry (and the
    tilted hinge axes) of every hypothesis is computed once, and with the
    compiled kernel the arrays are kept in the kernel's batch-last layout.

    Parameters
    ----------
    model : Model
    theta : (K, P) float
        The hypotheses.
    """

    def __init__(self, model: Model, theta, ws: Workspace | None = None):
        self.model = model
        self.ws = workspace(model) if ws is None else ws
        self.plan = kinematics_plan(model, self.ws)
        self.theta = np.asarray(theta, dtype=float)
        self.g = geometry(model, self.theta)  # (K, G)
        self.tilt = tilt_tables(model, self.theta)
        self.n = self.g.shape[0]
        self.tables = None
        self._use_kernel()

    def _use_kernel(self) -> bool:
        """Whether to call the compiled kernel now (its batch-last arrays are made the first time)."""
        if self.tables is None:
            self.tables = _kernel_tables(self.ws)
            if self.tables is None:
                return False
            self.gT = np.ascontiguousarray(self.g.T)
            self.tiltT = _tilts_batch_last(self.tilt, (self.n,))
            self.yT = np.empty((self.plan.n_markers, self.plan.dim, self.n))
            self.wT = np.empty((self.plan.n_markers, self.n))
        return True

    def fit(self, y, q0, n_iter: int = 8, tol: float = 1e-10, damping: float = 1e-3):
        """Poses of one frame ``y (M, D)`` (NaN where missing) from ``q0 (K, Q)`` or ``(Q,)``.

        The same iteration as :func:`fit_pose_logdet` for ``theta (K, P)``, ``y[None]``.

        Returns
        -------
        q : (K, Q) float
        rss : (K,) float
        logdet : (K,) float
            ``log det J^T J`` at ``q``; ``-inf`` where not positive.
        """
        y = np.asarray(y, dtype=float)
        present = np.isfinite(y).all(axis=-1)
        y0 = np.where(present[:, None], y, 0.0)
        if not self._use_kernel():
            q = np.array(np.broadcast_to(q0, (self.n, self.plan.n_pose)), dtype=float)
            return _fit_numpy(self.plan, self.g, self.tilt, y0, present, q, (self.n,), n_iter, tol, damping, True)
        self.yT[...] = y0[..., None]
        self.wT[...] = present[:, None]
        qT = np.empty((self.plan.n_pose, self.n))  # the kernel writes the fitted poses into it
        qT[...] = np.asarray(q0, dtype=float).T if np.ndim(q0) == 2 else np.asarray(q0, dtype=float)[:, None]
        cost, logdet = _lm_kernel.lm_fit(self.gT, self.yT, self.wT, qT, int(n_iter), float(tol), float(damping),
                                         True, self.plan.dim, self.plan.n_segments, self.plan.n_markers,
                                         self.tiltT, *self.tables)
        return qT.T, cost, logdet


def _normal_equations(plan, kin, r, mask, batch):
    """``J^T J (..., Q, Q)`` and ``J^T r (..., Q)`` with missing markers' rows zeroed."""
    Q = plan.n_pose
    J = pose_jacobian_from_plan(plan, kin, mask).reshape(batch + (-1, Q))
    Jt = np.swapaxes(J, -1, -2)
    return Jt @ J, (Jt @ r.reshape(batch + (-1, 1)))[..., 0]


def _fit_numpy(plan, g, tilt, y0, mask, q, batch, n_iter, tol, damping, want_logdet):
    q = np.broadcast_to(q, batch + q.shape[-1:]).copy()

    def residual(q_):
        if plan.planar:
            kin_ = _forward_planar(plan, g, q_)
        else:
            kin_ = _forward_general(plan, g, q_, tilt, want_omega=False)
        r_ = (y0 - kin_.markers) * mask[..., None]
        return kin_, r_, np.sum(r_**2, axis=(-2, -1))

    kin, r, cost = residual(q)
    JtJ, Jtr = _normal_equations(plan, kin, r, mask, batch)
    lam = np.full(batch, float(damping))
    Q = plan.n_pose
    eye = np.eye(Q)
    diag = np.arange(Q)
    for it in range(n_iter):
        dg = JtJ[..., diag, diag]
        ridge = 1e-9 * np.maximum(dg.mean(axis=-1), 1e-300)
        A = JtJ.copy()
        A[..., diag, diag] = (dg + lam[..., None] * dg) + ridge[..., None]
        rhs = Jtr
        bad = ~np.isfinite(A).all(axis=(-2, -1)) | ~np.isfinite(Jtr).all(axis=-1)
        if bad.any():  # a batch element that went astray stays where it is
            A = np.where(bad[..., None, None], eye, A)
            rhs = np.where(bad[..., None], 0.0, Jtr)
        step = np.linalg.solve(A, rhs[..., None])[..., 0]
        q_new = q + np.where(np.isfinite(step), step, 0.0)
        kin_new, r_new, cost_new = residual(q_new)
        ok = cost_new <= cost
        q = np.where(ok[..., None], q_new, q)
        improve = np.where(ok, cost - cost_new, 0.0)
        cost = np.where(ok, cost_new, cost)
        lam = np.where(ok, lam * 0.3, lam * 10.0)
        done = np.all(improve <= tol * (cost + 1e-30)) and np.all(ok | (lam > 1e8))
        if (done or it == n_iter - 1) and not want_logdet:
            break
        if ok.any():  # normal equations where the step was taken; the others keep theirs
            JtJ_new, Jtr_new = _normal_equations(plan, kin_new, r_new, mask, batch)
            JtJ = np.where(ok[..., None, None], JtJ_new, JtJ)
            Jtr = np.where(ok[..., None], Jtr_new, Jtr)
        if done:
            break
    logdet = None
    if want_logdet:
        sign, logdet = np.linalg.slogdet(JtJ)
        logdet = np.where(sign > 0, logdet, -np.inf)
    return q, cost, logdet


def random_poses(model: Model, y_frame, rng: np.random.Generator, n: int) -> np.ndarray:
    """Random starting poses around the markers of a frame.

    Parameters
    ----------
    y_frame : (..., M, D) float
        One frame (or a batch of frames), NaN where missing.

    Returns
    -------
    q : (..., n, Q) float
    """
    y_frame = np.asarray(y_frame, dtype=float)
    batch = y_frame.shape[:-2]
    present = np.isfinite(y_frame).all(axis=-1)
    cnt = present.sum(axis=-1)[..., None]
    centre = np.where(cnt > 0, np.where(present[..., None], y_frame, 0.0).sum(axis=-2)
                      / np.maximum(cnt, 1), 0.0)  # (..., D)
    q = np.empty(batch + (n, model.n_pose))
    ranges = _rotation_ranges(model)
    for k, d in enumerate(model.dofs):
        if d.kind == "T":
            q[..., k] = (centre @ np.asarray(d.axis))[..., None] \
                + rng.normal(0.0, 1.0, batch + (n,)) * _model_size(model) * 0.2
        else:
            lo, hi = ranges[k]
            q[..., k] = rng.uniform(lo, hi, batch + (n,))
    return q


def _model_size(model: Model) -> float:
    g = np.abs(model.nominal_geometry)
    return float(max(g.max(), 1e-9))


def _rotation_ranges(model: Model) -> dict[int, tuple[float, float]]:
    """Radian range of each rotational pose coordinate (joint range or a wide default)."""
    out = {}
    for s_i, s in enumerate(model.segments):
        ks = [k for k, d in enumerate(model.dofs) if d.segment == s_i and d.kind == "R"]
        for j, k in enumerate(ks):
            if j < len(s.joint.range):
                lo, hi = np.radians(s.joint.range[j])
            elif s.joint.type == "free":
                lo, hi = -np.pi, np.pi
            else:
                lo, hi = -np.pi / 2, np.pi / 2
            out[k] = (float(lo), float(hi))
    return out


def segment_placements(model: Model, theta, y, min_markers: int = 3, flat_tol: float = 1e-3):
    """Rigid (Kabsch) fit of every segment's model markers to each frame.

    Parameters
    ----------
    theta : (P,) float
    y : (F, M, D) float
        Markers, NaN where missing.
    min_markers : int
        Fewest present markers that place a segment (at least ``D``).
    flat_tol : float
        A segment whose present markers lie within ``flat_tol`` times their
        spread of a line (3-D) or a point (2-D) is not placed.

    Returns
    -------
    R_world_seg : (F, S, D, D) float
    p_world_seg : (F, S, D) float
        Origin of each segment's frame.
    placed : (F, S) bool
        Whether the segment was placed in that frame.
    """
    D, S, M = model.dim, len(model.segments), len(model.markers)
    y = np.asarray(y, dtype=float)
    F = y.shape[0]
    g = geometry(model, theta)
    r_all = g[S * D:(S + M) * D].reshape(M, D)
    R = np.broadcast_to(np.eye(D), (F, S, D, D)).copy()
    p = np.zeros((F, S, D))
    placed = np.zeros((F, S), dtype=bool)
    present = np.isfinite(y).all(axis=-1)
    for s in range(S):  # the tree's segments: the only loop
        idx = np.flatnonzero(model.marker_segment == s)
        if idx.size < max(min_markers, D):
            continue
        w = present[:, idx].astype(float)  # (F, n)
        n = w.sum(axis=1)
        ok = n >= max(min_markers, D)
        if not ok.any():
            continue
        ys = np.where(present[:, idx, None], y[:, idx], 0.0)
        r = r_all[idx]
        nn = np.maximum(n, 1.0)[:, None]
        rbar = (w @ r) / nn  # (F, D)
        ybar = np.einsum("fn,fnd->fd", w, ys) / nn
        rc = r[None] - rbar[:, None]
        yc = ys - ybar[:, None]
        H = np.einsum("fn,fni,fnj->fij", w, rc, yc)
        Crr = np.einsum("fn,fni,fnj->fij", w, rc, rc)
        lam = np.linalg.eigvalsh(Crr)  # ascending
        spread = lam[:, -1] if D == 2 else lam[:, -2]
        ok &= spread > flat_tol**2 * np.maximum(lam[:, -1], 1e-300)
        U, _, Vt = np.linalg.svd(H)
        V = np.swapaxes(Vt, -1, -2)
        d = np.sign(np.linalg.det(V @ np.swapaxes(U, -1, -2)))
        d = np.where(d == 0, 1.0, d)
        fix = np.ones((F, D))
        fix[:, -1] = d
        Rs = np.einsum("fij,fj,fkj->fik", V, fix, U)
        R[ok, s] = Rs[ok]
        p[ok, s] = (ybar - np.einsum("fij,fj->fi", Rs, rbar))[ok]
        placed[:, s] = ok
    return R, p, placed


def _hinge_angle(R_rel, a) -> np.ndarray:
    """Angle (...) of the rotation about unit ``a (..., 3)`` closest to ``R_rel (..., 3, 3)``."""
    vee = np.stack([R_rel[..., 2, 1] - R_rel[..., 1, 2], R_rel[..., 0, 2] - R_rel[..., 2, 0],
                    R_rel[..., 1, 0] - R_rel[..., 0, 1]], -1)
    tr = np.einsum("...ii->...", R_rel)
    return np.arctan2(np.sum(a * vee, -1), tr - np.einsum("...i,...ij,...j->...", a, R_rel, a))


def _euler_zxy(R_rel) -> np.ndarray:
    """Angles (..., 3) with ``R_rel = Rz(a) Rx(b) Ry(c)``."""
    a = np.arctan2(-R_rel[..., 0, 1], R_rel[..., 1, 1])
    b = np.arctan2(R_rel[..., 2, 1], np.hypot(R_rel[..., 0, 1], R_rel[..., 1, 1]))
    c = np.arctan2(-R_rel[..., 2, 0], R_rel[..., 2, 2])
    return np.stack([a, b, c], -1)


def rigid_poses(model: Model, theta, y, ws: Workspace | None = None):
    """Pose coordinates from per-segment rigid fits and inverse kinematics.

    Parameters
    ----------
    theta : (P,) float
    y : (F, M, D) float
        Markers, NaN where missing.

    Returns
    -------
    q : (F, Q) float
        Coordinates found (zero where ``known`` is False).
    known : (F, Q) bool
        Coordinates determined by the rigid fits of the segment and its parent.
    """
    D, S, Q = model.dim, len(model.segments), model.n_pose
    theta = np.asarray(theta, dtype=float)
    y = np.asarray(y, dtype=float)
    F = y.shape[0]
    R, p, placed = segment_placements(model, theta, y)
    g = geometry(model, theta)
    offsets = g[: S * D].reshape(S, D)
    t_axis, _ = tilted_axes(model, theta)
    local_axis = {k: t_axis[j] for j, (k, *_rest) in enumerate(model.axis_tilts)}
    q = np.zeros((F, Q))
    known = np.zeros((F, Q), dtype=bool)
    ks_of = [[k for k, d in enumerate(model.dofs) if d.segment == s] for s in range(S)]
    for s, seg in enumerate(model.segments):
        ks = ks_of[s]
        if not ks:
            continue
        par = model.parent_index[s]
        Rp = np.eye(D) if par < 0 else R[:, par]
        ok = placed[:, s] & (True if par < 0 else placed[:, par])
        R_rel = np.swapaxes(Rp, -1, -2) @ R[:, s]
        kind = seg.joint.type
        if D == 2:
            ang = np.arctan2(R_rel[:, 1, 0], R_rel[:, 0, 0])
            vals = [ang] if kind == "revolute" else \
                [*np.moveaxis(p[:, s] - offsets[s], -1, 0), ang]  # free root: parent is the world
        elif kind in ("free", "spherical"):
            eul = np.moveaxis(_euler_zxy(R_rel), -1, 0)
            vals = list(eul) if kind == "spherical" else \
                [*np.moveaxis(p[:, s] - offsets[s], -1, 0), *eul]
        elif kind == "custom":
            vals = custom_joint_coordinates(model, s, R_rel, p[:, s] - offsets[s] if par < 0 else None, ws)
            if vals is None:
                continue
        elif kind == "hinge":
            a = local_axis.get(ks[0], np.asarray(model.dofs[ks[0]].axis))
            vals = [_hinge_angle(R_rel, np.broadcast_to(a, (F, 3)))]
        else:  # universal
            a1, a2 = (np.asarray(model.dofs[k].axis) for k in ks)
            b = R_rel @ a2
            u = a2 - (a1 @ a2) * a1
            v = b - (b @ a1)[:, None] * a1
            t1 = np.arctan2(np.cross(u, v) @ a1, v @ u)
            R2 = np.swapaxes(_rotation(3, a1, t1), -1, -2) @ R_rel
            vals = [t1, _hinge_angle(R2, np.broadcast_to(a2, (F, 3)))]
        for k, v in zip(ks, vals, strict=True):
            q[:, k] = np.where(ok, v, 0.0)
            known[:, k] = ok
    return q, known


def _plain_custom_motions(plan, s: int):
    """The rotations and translations ``[(axis, k)]`` of custom joint ``s``'s plan, or None if not plain.

    Plain: every motion driven by a coordinate is that coordinate itself (an identity
    function), and every motion driven by none is zero at rest.
    """
    rows = plan.custom[s]
    if any(k >= 0 and not f.is_identity for _t, _a, k, f, *_ in rows) \
            or any(k < 0 and np.any(f.value(np.zeros(1)) != 0) for _t, _a, k, f, *_ in rows):
        return None
    rot = [(a, k) for t, a, k, *_ in rows if not t and k >= 0]
    trans = [(a, k) for t, a, k, *_ in rows if t and k >= 0]
    return rot, trans


def _custom_rotation_angles(ax, R_rel) -> list:
    """Angles ``[(F,)]`` about one to three perpendicular axes ``ax (n, 3)`` that make ``R_rel (F, 3, 3)``.

    One axis: the hinge angle. Two or three: the Cardan angles ``Rx(a) Ry(b) Rz(c)`` in the basis of
    the axes (the third the cross product of the first two when only two are given), made proper
    by flipping the third axis, whose angle then changes sign.
    """
    F = R_rel.shape[0]
    if len(ax) == 1:
        return [_hinge_angle(R_rel, np.broadcast_to(ax[0], (F, 3)))]
    if len(ax) == 0:
        return []
    B = np.array(ax.T) if len(ax) == 3 else np.stack([ax[0], ax[1], np.cross(ax[0], ax[1])], -1)
    sgn = np.sign(np.linalg.det(B))
    B[:, 2] *= sgn  # a proper rotation; the third angle changes sign with it
    Rb = B.T @ R_rel @ B  # = Rx(a) Ry(b) Rz(c)
    a = np.arctan2(-Rb[:, 1, 2], Rb[:, 2, 2])
    b = np.arcsin(np.clip(Rb[:, 0, 2], -1.0, 1.0))
    c = np.arctan2(-Rb[:, 0, 1], Rb[:, 0, 0])
    return [a, b, sgn * c][:len(ax)]


def custom_joint_coordinates(model: Model, s: int, R_rel, shift=None, ws: Workspace | None = None):
    """Coordinates of custom joint ``s`` from its relative rotation, or None if not plain.

    Handled: every coordinate drives one motion as itself; the rotations, one
    to three, about mutually perpendicular axes; translations (of the root,
    ``shift (F, 3)`` in the world) along independent axes.
    """
    plan = kinematics_plan(model, ws)
    motions = _plain_custom_motions(plan, s)
    if motions is None:
        return None
    rot, trans = motions
    if plan.orientation[s] is not None:
        R_rel = R_rel @ plan.orientation[s].T
    if trans and shift is None:
        return None
    ax = np.array([a for a, _ in rot])
    if len(rot) > 1 and np.abs(ax @ ax.T - np.eye(len(rot))).max() > 1e-9:
        return None
    ang = _custom_rotation_angles(ax, R_rel)
    tv = list(np.linalg.lstsq(np.array([a for a, _ in trans]).T, shift.T, rcond=None)[0]) if trans else []
    out = dict(zip([k for _, k in rot], ang, strict=True)) | dict(zip([k for _, k in trans], tv, strict=True))
    return [out[k] for k, d in enumerate(model.dofs) if d.segment == s]


def initial_pose(model: Model, theta, y_frame, rng: np.random.Generator, n_starts: int = 64,
                 q_known=None, known=None, ws: Workspace | None = None):
    """Best pose of one frame from many random starts.

    Parameters
    ----------
    q_known : (Q,) float, optional
    known : (Q,) bool, optional
        Coordinates already determined (by rigid fits): every start uses them
        and only the others are drawn at random.

    Returns
    -------
    q : (Q,) float
    rss : float
    """
    q0 = random_poses(model, y_frame, rng, n_starts)
    if known is not None:
        q0 = np.where(known, q_known, q0)
        q0[0] = np.where(known, q_known, 0.0)  # and one start at the reference pose
    q, cost = fit_pose(model, np.asarray(theta)[None], y_frame[None], q0, n_iter=60, ws=ws)
    best = _canonical_best(model, q, cost, y_frame)
    return _wrap_angles(model, q[best]), float(cost[best])


def _wrap_angles(model: Model, q) -> np.ndarray:
    """``q (..., Q)`` with every rotational coordinate wrapped into ``[-pi, pi)``."""
    rot = np.array([d.kind == "R" for d in model.dofs])
    return np.where(rot, (q + np.pi) % (2.0 * np.pi) - np.pi, q)


def _canonical_best(model: Model, q, cost, y_frame) -> int:
    """Index of the start to keep: of the poses at the lowest cost (to rounding), the one nearest the reference.

    Different angle branches of one placement (e.g. the two Euler triples of
    one rotation) reach the same cost; which start reaches it first is
    decided by rounding. Taking, among the poses within a relative ``1e-6``
    of the lowest cost, the one with the smallest wrapped angles makes the
    choice independent of rounding (and of the compiled or numpy path).
    """
    if not np.isfinite(cost).any():
        return 0
    n_obs = int(np.isfinite(y_frame).all(axis=-1).sum()) * model.dim
    floor = 1e-12 * max(float(np.nanmax(np.abs(y_frame), initial=0.0)), 1.0) ** 2 * n_obs
    low = np.isfinite(cost) & (cost <= np.nanmin(cost) * (1.0 + 1e-6) + floor)
    size = np.sum(_wrap_angles(model, q) ** 2, axis=-1)
    return int(np.argmin(np.where(low, size, np.inf)))


def pose_determined(model: Model, y) -> np.ndarray:
    """(F,) bool: frames with more marker coordinates than pose coordinates."""
    n = np.isfinite(y).all(axis=-1).sum(axis=-1) * model.dim
    return n > model.n_pose


def track_poses(model: Model, theta, y, rng: np.random.Generator, q_first=None,
                n_refine: int = 30, n_starts: int = 64, stride: int = 1, ws: Workspace | None = None):
    """Poses of every frame of a trial for fixed ``theta``.

    Rigid fits and inverse kinematics give every coordinate they can, in all
    frames at once; the rest come from the previous frame (or random starts in
    the first frame) and Levenberg-Marquardt, frame by frame; then all frames
    are refined together. Frames that end far worse than the typical frame are
    tried again from random starts.

    Parameters
    ----------
    theta : (P,) float
    y : (F, M, D) float
        Markers, NaN where missing.
    q_first : (Q,) float, optional
        Pose of frame 0, if known.
    stride : int
        Of the frames that rigid fits do not settle, track only every
        ``stride``-th sequentially and start the others from linear
        interpolation between resolved frames (for densely sampled, smooth motion).
    ws : Workspace, optional
        The model's workspace (:func:`workspace`; one is made for this call without it).

    Returns
    -------
    q : (F, Q) float
    rss : (F,) float
    """
    theta = np.asarray(theta, dtype=float)
    y = np.asarray(y, dtype=float)
    F = y.shape[0]
    if ws is None:
        ws = workspace(model)
    q, known = rigid_poses(model, theta, y, ws)
    enough = pose_determined(model, y)
    todo = ~known.all(axis=1) & enough
    if q_first is not None:
        q[0], known[0], todo[0] = q_first, True, False
    stride = max(int(stride), 1)
    later = np.zeros(F, dtype=bool)
    if stride > 1:
        pos = np.cumsum(todo) - 1  # rank among the frames to track
        later = todo & (pos % stride != 0)
        later[np.flatnonzero(todo)[-1:]] = False  # the last one is tracked
        todo &= ~later
    prev2 = prev = None
    for t in range(F):  # only frames that rigid fits do not settle
        if not todo[t]:
            if enough[t] and not later[t]:
                prev2, prev = prev, q[t]
            continue
        if prev is None:
            q[t], _ = initial_pose(model, theta, y[t], rng, n_starts, q[t], known[t], ws=ws)
        else:
            pred = prev if prev2 is None else prev + 0.5 * (prev - prev2)
            q[t], _ = fit_pose(model, theta, y[t], np.where(known[t], q[t], pred), n_iter=5, ws=ws)
        prev2, prev = prev, q[t]
    if later.any():
        anchors = np.flatnonzero(enough & ~later)
        if anchors.size:
            rot = np.array([d.kind == "R" for d in model.dofs])
            qa = np.where(rot, np.unwrap(q[anchors], axis=0), q[anchors])
            interp = np.stack([np.interp(np.flatnonzero(later), anchors, qa[:, k])
                               for k in range(model.n_pose)], axis=-1)
            q[later] = np.where(known[later], q[later], interp)
    q, rss = fit_pose(model, theta, y, q, n_iter=n_refine, ws=ws)
    # frames that ended in a poor local minimum: random restarts (batched over those frames)
    ok = enough & np.isfinite(rss)
    if ok.sum() >= 3:
        typical = np.median(rss[ok])
        n_obs = np.isfinite(y).all(axis=-1).sum(axis=-1) * model.dim
        floor = 1e-12 * max(float(np.nanmax(np.abs(y))), 1.0) ** 2 * n_obs
        bad = np.flatnonzero(ok & (rss > 25.0 * typical + floor))
        if bad.size:
            starts = random_poses(model, y[bad], rng, n_starts)  # (B, n, Q)
            starts = np.where(known[bad, None], q[bad, None], starts)
            starts[:, 0] = q[bad]
            qb, cb = fit_pose(model, theta, y[bad, None], starts, n_iter=60, ws=ws)
            # of the starts that reach the lowest cost (to rounding), keep the one nearest the tracked
            # pose: equal-cost poses on another angle branch would break the trial's continuity
            low = cb <= np.nanmin(cb, axis=1, keepdims=True) * (1.0 + 1e-6) + floor[bad, None]
            rot = np.array([d.kind == "R" for d in model.dofs])
            dq = qb - q[bad, None]
            dq = np.where(rot, (dq + np.pi) % (2.0 * np.pi) - np.pi, dq)
            best = np.argmin(np.where(low, np.sum(dq**2, axis=-1), np.inf), axis=1)
            better = cb[np.arange(bad.size), best] < rss[bad] * (1.0 - 1e-6)
            chosen = q[bad] + dq[np.arange(bad.size), best]  # angles on the tracked pose's branch
            q[bad[better]] = chosen[better]
            rss[bad[better]] = cb[np.arange(bad.size), best][better]
    return q, rss
