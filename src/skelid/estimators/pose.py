"""Pose fitting: the per-frame nuisance of every estimator.

For fixed parameters ``theta`` the pose of frame ``t`` minimises the marker
residual over the markers present in that frame,

.. math:: \\hat q_t(\\theta) = \\arg\\min_q \\sum_{m \\in P(t)} \\lVert y_{tm} - x_m(q, \\theta)\\rVert^2 ,

solved by Levenberg-Marquardt, batched over any leading axes (frames,
hypotheses). A trial is tracked by warm-starting each frame from a linear
prediction of the previous two (one short sequential pass, the only loop over
frames), then refined for all frames at once.
"""

from __future__ import annotations

import numpy as np

from skelid.model.description import Model
from skelid.model.kinematics import forward_kinematics, pose_jacobian


def _residual(model, theta, q, y0, mask):
    kin = forward_kinematics(model, theta, q)
    r = (y0 - kin.markers) * mask[..., None]
    return kin, r


def fit_pose(model: Model, theta, y, q0, n_iter: int = 30, tol: float = 1e-10):
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

    Returns
    -------
    q : (..., Q) float
        Fitted poses.
    rss : (...) float
        Residual sum of squares at ``q``.
    """
    y = np.asarray(y, dtype=float)
    mask = np.isfinite(y).all(axis=-1)
    y0 = np.where(mask[..., None], y, 0.0)
    q = np.array(q0, dtype=float)
    batch = np.broadcast_shapes(q.shape[:-1], y.shape[:-2], np.shape(theta)[:-1])
    q = np.broadcast_to(q, batch + q.shape[-1:]).copy()
    kin, r = _residual(model, theta, q, y0, mask)
    cost = np.sum(r**2, axis=(-2, -1))
    lam = np.full(batch, 1e-3)
    Q = model.n_pose
    eye = np.eye(Q)
    for _ in range(n_iter):
        J = pose_jacobian(model, kin) * mask[..., None, None]
        J = J.reshape(batch + (-1, Q))
        rv = r.reshape(batch + (-1,))
        JtJ = np.einsum("...ki,...kj->...ij", J, J)
        Jtr = np.einsum("...ki,...k->...i", J, rv)
        dg = np.einsum("...ii->...i", JtJ)
        ridge = 1e-9 * np.maximum(dg.mean(axis=-1), 1e-300)
        A = JtJ + lam[..., None, None] * dg[..., None, :] * eye + ridge[..., None, None] * eye
        bad = ~np.isfinite(A).all(axis=(-2, -1)) | ~np.isfinite(Jtr).all(axis=-1)
        if bad.any():  # a batch element that went astray stays where it is
            A = np.where(bad[..., None, None], eye, A)
            Jtr = np.where(bad[..., None], 0.0, Jtr)
        step = np.linalg.solve(A, Jtr[..., None])[..., 0]
        q_new = q + np.where(np.isfinite(step), step, 0.0)
        kin_new, r_new = _residual(model, theta, q_new, y0, mask)
        cost_new = np.sum(r_new**2, axis=(-2, -1))
        ok = cost_new <= cost
        q = np.where(ok[..., None], q_new, q)
        r = np.where(ok[..., None, None], r_new, r)
        kin = kin.__class__(*[np.where(_bmask(ok, a, batch), an, a) for a, an in zip(kin, kin_new, strict=True)])
        improve = np.where(ok, cost - cost_new, 0.0)
        cost = np.where(ok, cost_new, cost)
        lam = np.where(ok, lam * 0.3, lam * 10.0)
        if np.all(improve <= tol * (cost + 1e-30)) and np.all(ok | (lam > 1e8)):
            break
    return q, cost


def _bmask(ok, a, batch):
    """Broadcast a batch mask onto an array with extra trailing axes."""
    return ok.reshape(ok.shape + (1,) * (a.ndim - len(batch)))


def random_poses(model: Model, y_frame, rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, Q) float: random starting poses around the markers of one frame."""
    present = np.isfinite(y_frame).all(axis=-1)
    centre = y_frame[present].mean(axis=0) if present.any() else np.zeros(model.dim)
    q = np.empty((n, model.n_pose))
    ranges = _rotation_ranges(model)
    for k, d in enumerate(model.dofs):
        if d.kind == "T":
            q[:, k] = centre @ np.asarray(d.axis) + rng.normal(0.0, 1.0, n) * _model_size(model) * 0.2
        else:
            lo, hi = ranges[k]
            q[:, k] = rng.uniform(lo, hi, n)
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


def initial_pose(model: Model, theta, y_frame, rng: np.random.Generator, n_starts: int = 64):
    """Best pose of one frame from many random starts.

    Returns
    -------
    q : (Q,) float
    rss : float
    """
    q0 = random_poses(model, y_frame, rng, n_starts)
    q, cost = fit_pose(model, np.asarray(theta)[None], y_frame[None], q0, n_iter=60)
    best = int(np.nanargmin(cost))
    return q[best], float(cost[best])


def track_poses(model: Model, theta, y, rng: np.random.Generator, q_first=None,
                n_refine: int = 30, stride: int = 1):
    """Poses of every frame of a trial for fixed ``theta``.

    Parameters
    ----------
    theta : (P,) float
    y : (F, M, D) float
        Markers, NaN where missing.
    q_first : (Q,) float, optional
        Pose of frame 0; found from random starts if not given.
    stride : int
        Track every ``stride``-th frame sequentially and start the frames in
        between from linear interpolation (for densely sampled, smooth motion).

    Returns
    -------
    q : (F, Q) float
    rss : (F,) float
    """
    theta = np.asarray(theta, dtype=float)
    F = y.shape[0]
    q = np.empty((F, model.n_pose))
    if q_first is None:
        q_first, _ = initial_pose(model, theta, y[0], rng)
    q[0] = q_first
    prev2 = prev = q_first
    keys = np.unique(np.r_[np.arange(0, F, max(int(stride), 1)), F - 1])
    for t in keys[1:]:  # cheap sequential predictor-corrector pass over key frames
        pred = prev + 0.5 * (prev - prev2)
        qt, _ = fit_pose(model, theta, y[t], pred, n_iter=4)
        q[t] = qt
        prev2, prev = prev, qt
    if len(keys) < F:
        for k in range(model.n_pose):
            q[:, k] = np.interp(np.arange(F), keys, q[keys, k])
    return fit_pose(model, theta, y, q, n_iter=n_refine)
