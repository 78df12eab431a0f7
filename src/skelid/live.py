"""Live geometry: refine the parameters frame by frame while the subject moves.

A :class:`Session` takes labelled frames from a stream (a VR or motion-capture
system), one at a time, and returns after each an immutable
:class:`LiveEstimate`: the parameters with intervals, the current pose, the
joint centres, every marker's residual and a health flag.

**Recursive Gaussian form** (any number of parameters). The posterior of
``theta`` after frame ``t`` is kept as ``N(m_t, \\Lambda_t^{-1})``. Frame
``t + 1`` with markers ``y`` is fitted at ``theta = m_t`` for its pose
``\\hat q`` (Levenberg-Marquardt from the constant-velocity prediction
``2 q_t - q_{t-1}``, the motion prior); with ``r = y - x(\\hat q, m_t)``,
``J = \\partial x / \\partial q`` and ``K = \\partial x / \\partial \\theta``
there, the pose is marginalised (its own information ``J^\\top J`` is
eliminated, a flat prior on the pose):

.. math::

    \\tilde K = (I - J (J^\\top J)^{-1} J^\\top) K, \\qquad
    \\Lambda_{t+1} = \\Lambda_0 + A_{t+1} / \\hat\\sigma^2, \\quad A_{t+1} = A_t + \\tilde K^\\top \\tilde K,

.. math::

    m_{t+1} = m_t + \\Lambda_{t+1}^{-1} \\tilde K^\\top r / \\hat\\sigma^2 ,

an extended Kalman (Gauss-Newton) step of the joint least-squares problem with
every earlier frame summarised by the Gaussian. ``\\Lambda_0`` is the prior's
precision (a uniform prior on ``[a, b]`` counts as sd ``(b - a)/\\sqrt{12}``
and bounds the mean), ``\\hat\\sigma^2`` the running residual variance
``RSS / (n_{obs} - Q n_{frames} - P)``. The cost per frame is one pose fit and
one Jacobian: it does not depend on a grid. Early in a session (after 10, 25,
50, 100 and 200 frames) all frames so far are linearised again at the current
mean (:func:`relinearise`), so the first frames, seen when the mean was still
far off, do not stay linearised there.

This is the joint least-squares fit with every pose free: unlike the batch
``marker`` method it has no motion model and no bias correction, so it keeps
that fit's ``O(sigma^2)`` bias (on case A with 5 mm noise, about 2 mm, 3 sd
after 300 frames; negligible at 1 mm).

**Grid form** (1-3 parameters, or a posterior with several modes): the
online grid filter :class:`~skelid.estimators.grid.MarkerGridFilter`; the pose
is that of the most probable grid point.

**Health.** After the pose fit, a marker more than ``outlier_sd`` noise
standard deviations from the model (a swapped label, a ghost marker) is left
out and the frame refitted without it; a frame with too few markers to fix
the pose leaves the estimate as it was. Either way ``healthy`` turns False
and ``health`` says why.

Examples
--------
>>> import numpy as np
>>> from skelid.live import Session
>>> from skelid.simulate import builtin_model, simulate
>>> model = builtin_model("case-a")
>>> trial = simulate(model, n_frames=200, sigma=1.0, rng=np.random.default_rng(0))
>>> session = Session(model, labels=trial.data.names, units="mm", rate=100.0, method="gaussian")
>>> for frame in trial.data.positions:
...     est = session.push(frame)
>>> bool(abs(est.parameters["L2"].mean - trial.theta[0]) < 4 * est.parameters["L2"].sd)
True
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import NamedTuple

import numpy as np
from scipy.stats import norm

from skelid.data import unit_scale
from skelid.errors import DataError, ModelError
from skelid.estimators.grid import MarkerGridFilter
from skelid.estimators.pose import _model_size, fit_pose, initial_pose, workspace
from skelid.model.description import Model
from skelid.model.kinematics import (
    Workspace,
    forward_kinematics,
    marker_jacobian,
    pose_jacobian,
    theta_jacobian,
)
from skelid.result import ParameterEstimate

_Z95 = float(norm.ppf(0.975))
#: after this many frames, every frame so far is linearised again at the current mean
_RELINEARISE = (10, 25, 50, 100, 200)

__all__ = ["LiveEstimate", "Session", "GaussianState", "gaussian_update", "prior_moments", "Advice"]


# --------------------------------------------------------------------------- the recursive Gaussian
class GaussianState(NamedTuple):
    """State of the recursive Gaussian filter (immutable; an update returns a new one)."""

    mean: np.ndarray  # (P,) posterior mean of theta
    info_data: np.ndarray  # (P, P) sum of the frames' pose-marginalised K~^T K~ (unscaled by sigma)
    pose: np.ndarray | None  # (Q,) last fitted pose
    pose_prev: np.ndarray | None  # (Q,) the one before (for the velocity prediction)
    rss: float  # running residual sum of squares
    n_obs: int  # marker coordinates used
    n_used: int  # frames used


def prior_moments(model: Model) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Gaussian summary of the prior: ``(mean (P,), precision (P, P), lower (P,), upper (P,))``.

    A uniform prior counts as its centre and ``sd = (upper - lower) / sqrt(12)``;
    a log-normal one as its median and ``sd = median * sd_log``.
    """
    mean, sd = [], []
    for p in model.parameters:
        pr = p.prior
        if pr.kind == "uniform":
            mean.append(0.5 * (pr.lower + pr.upper))
            sd.append((pr.upper - pr.lower) / math.sqrt(12.0))
        elif pr.kind == "normal":
            mean.append(pr.mean)
            sd.append(pr.sd)
        else:
            mean.append(pr.mean)
            sd.append(pr.mean * pr.sd)
    lo = np.array([p.prior.lower for p in model.parameters], float)
    hi = np.array([p.prior.upper for p in model.parameters], float)
    return np.array(mean, float), np.diag(1.0 / np.square(sd)), lo, hi


def marginal_theta_jacobian(J_pose, J_theta, ridge: float = 1e-10) -> np.ndarray:
    """``(I - J (J^T J)^{-1} J^T) K``: the part of ``K`` no pose change can mimic.

    Parameters
    ----------
    J_pose : (..., N, Q) float
    J_theta : (..., N, P) float

    Returns
    -------
    (..., N, P) float
    """
    JtJ = np.swapaxes(J_pose, -1, -2) @ J_pose
    scale = np.maximum(np.trace(JtJ, axis1=-2, axis2=-1) / JtJ.shape[-1], 1e-300)
    JtJ = JtJ + (ridge * scale)[..., None, None] * np.eye(JtJ.shape[-1])
    coef = np.linalg.solve(JtJ, np.swapaxes(J_pose, -1, -2) @ J_theta)
    return J_theta - J_pose @ coef


def _sigma2(rss: float, n_obs: int, n_used: int, model: Model, sigma: float | None, fallback: float) -> float:
    if sigma is not None:
        return float(sigma) ** 2
    dof = n_obs - model.n_pose * n_used - model.n_params
    if dof >= 3 and rss > 0:
        return rss / dof
    return fallback


def gaussian_update(model: Model, state: GaussianState, y, prior, sigma2: float, n_iter: int = 10,
                    ws: Workspace | None = None):
    """One frame ``y (M, D)`` (model units, NaN where missing) folded into ``state``.

    Parameters
    ----------
    prior : tuple
        :func:`prior_moments` of the model.
    sigma2 : float
        Noise variance of a marker coordinate used for this frame's weight.

    Returns
    -------
    state : GaussianState
    """
    q0 = state.pose if state.pose_prev is None else 2.0 * state.pose - state.pose_prev
    if ws is None:
        ws = workspace(model)
    q, _ = fit_pose(model, state.mean, y, q0, n_iter=n_iter, ws=ws)
    return _fold(model, state, y, q, forward_kinematics(model, state.mean, q, ws), prior, sigma2, ws)


def _fold(model, state, y, q, kin, prior, sigma2, ws=None):
    """The update of :func:`gaussian_update` at the fitted pose ``q`` with its kinematics ``kin``."""
    _, L0, lo, hi = prior
    theta = state.mean
    present = np.isfinite(y).all(axis=-1)
    w = present[:, None].astype(float)
    r = (np.where(present[:, None], y, 0.0) - kin.markers) * w
    N = r.size
    Jq = (pose_jacobian(model, kin, ws) * w[..., None]).reshape(N, -1)
    Kt = marginal_theta_jacobian(Jq, (theta_jacobian(model, kin, ws) * w[..., None]).reshape(N, -1))
    rv = r.reshape(N)
    A = state.info_data + Kt.T @ Kt
    step = np.linalg.solve(L0 + A / sigma2, Kt.T @ rv / sigma2)
    mean = np.clip(theta + step, lo, hi)
    rss_frame = float(np.sum((rv - Kt @ (mean - theta)) ** 2))
    return GaussianState(mean, A, q, state.pose, state.rss + rss_frame,
                         state.n_obs + int(present.sum()) * model.dim, state.n_used + 1)


def relinearise(model: Model, state: GaussianState, frames, prior, sigma: float | None, n_iter: int = 2,
                ws: Workspace | None = None):
    """The state recomputed from ``frames`` (every frame used so far) by Gauss-Newton at the current mean.

    The recursive update linearises each frame at the mean of its time; the
    first frames see a mean far from the final one. Early in a session
    (:data:`_RELINEARISE` frames) all frames so far are fitted again at the
    current mean and the posterior is recomputed from them in one batched
    Gauss-Newton step (``n_iter`` times), as the batch joint fit would.

    Parameters
    ----------
    frames : list of ((M, D) float, (Q,) float)
        Each frame used (NaN where missing or left out) and its last fitted pose.
    """
    mu0, L0, lo, hi = prior
    Y = np.stack([f[0] for f in frames])
    Q0 = np.stack([f[1] for f in frames])
    present = np.isfinite(Y).all(axis=-1)
    w = present[..., None].astype(float)
    Y0 = np.where(present[..., None], Y, 0.0)
    B, M, D = Y.shape
    mean = state.mean
    n_obs = int(present.sum()) * D
    for _ in range(n_iter):
        q, _ = fit_pose(model, mean, Y, Q0, n_iter=10, ws=ws)
        kin = forward_kinematics(model, mean, q, ws)
        r = ((Y0 - kin.markers) * w).reshape(B, M * D)
        Jq = (pose_jacobian(model, kin, ws) * w[..., None]).reshape(B, M * D, -1)
        Kt = marginal_theta_jacobian(Jq, (theta_jacobian(model, kin, ws) * w[..., None]).reshape(B, M * D, -1))
        A = np.einsum("bnp,bnq->pq", Kt, Kt)
        g = np.einsum("bnp,bn->p", Kt, r)
        rss = float(np.sum(r**2))
        s2 = _sigma2(rss, n_obs, B, model, sigma, (rss / max(n_obs - model.n_pose * B, 1)) or 1.0)
        step = np.linalg.solve(L0 + A / s2, g / s2 - L0 @ (mean - mu0))
        new_mean = np.clip(mean + step, lo, hi)
        rss = float(np.sum((r - Kt @ (new_mean - mean)) ** 2))
        mean, Q0 = new_mean, q
    for k, (y, _) in enumerate(frames):
        frames[k] = (y, q[k])
    return GaussianState(mean, A, q[-1], q[-2] if B > 1 else None, rss, n_obs, B)


# --------------------------------------------------------------------------- what a push returns
@dataclass(frozen=True)
class LiveEstimate:
    """Everything known after one frame (immutable; arrays are read-only).

    Attributes
    ----------
    frame : int
        Frames pushed so far.
    time : float
        ``frame / rate`` (s).
    parameters : mapping of str to ParameterEstimate
        Mean, sd and 95 % interval of each parameter (model units).
    theta : (P,) float
    cov : (P, P) float
    pose : (Q,) float or None
        Current pose (None until a frame fixes it).
    joint_centres : mapping of str to (D,) float
        World position of each segment's joint (model units).
    marker_residuals : mapping of str to float
        Distance of each model marker from the fitted model in this frame (NaN if missing or left out).
    sigma : float
        Noise level used (model units).
    healthy : bool
        False if this frame could not be used fully (markers missing beyond what fixes the
        pose, markers left out as outliers).
    health : str
        ``"ok"`` or what went wrong.
    rejected : tuple of str
        Markers left out of this frame as outliers.
    """

    frame: int
    time: float
    parameters: Mapping[str, ParameterEstimate]
    theta: np.ndarray
    cov: np.ndarray
    pose: np.ndarray | None
    joint_centres: Mapping[str, np.ndarray]
    marker_residuals: Mapping[str, float]
    sigma: float
    healthy: bool
    health: str
    rejected: tuple[str, ...] = ()


def _frozen(a):
    if a is None:
        return None
    a = np.array(a, dtype=float)
    a.flags.writeable = False
    return a


class Advice(NamedTuple):
    """One candidate movement, as ranked by :meth:`Session.advice`."""

    text: str  # what to do, in words
    joint: str
    dof: int  # pose coordinate moved
    lower_deg: float  # the sweep, in degrees (or model units for a translation)
    upper_deg: float
    parameter: str  # the worst-determined parameter it is judged for
    sd_now: float
    sd_after: float  # expected sd of that parameter after the movement


# --------------------------------------------------------------------------- the session
class Session:
    """A live fit of ``model`` to a stream of labelled frames.

    Parameters
    ----------
    model : Model
    labels : sequence of str or mapping, optional
        A sequence: the stream's marker names in the order of the rows of an array
        frame. A mapping: stream name -> model marker name (for streams whose names
        differ). Stream names match model markers by name or by the model's marker
        label. Names the model does not know are ignored.
    units : str, optional
        Length unit of the stream (``mm``, ``cm``, ``m``); default the model's.
    rate : float
        Frames per second of the stream.
    method : {'auto', 'gaussian', 'grid'}
        ``auto``: the grid filter for 1-3 parameters, the recursive Gaussian for more.
    sigma : float, optional
        Marker noise (model units); estimated from the residuals if not given.
    outlier_sd : float
        Residual, in noise standard deviations, beyond which a marker is left out of a frame.
    rng : numpy.random.Generator, optional
        For the random starts of the first pose.

    Raises
    ------
    DataError
        Labels that match none of the model's markers, or an unknown unit.
    ModelError
        ``method='grid'`` for more than 3 parameters.
    """

    def __init__(self, model: Model, labels=None, units: str | None = None, rate: float = 100.0,
                 method: str = "auto", sigma: float | None = None, outlier_sd: float = 6.0,
                 rng: np.random.Generator | None = None):
        if method not in ("auto", "gaussian", "grid"):
            raise ModelError(f"unknown live method {method!r}", "use 'auto', 'gaussian' or 'grid'")
        if method == "grid" and model.n_params > 3:
            raise ModelError(f"the grid form handles 1 to 3 parameters; {model.name!r} has {model.n_params}",
                             "use method='gaussian'")
        if not rate > 0:
            raise DataError(f"rate must be positive, got {rate!r}", "pass the stream's frames per second")
        self.model = model
        self.rate = float(rate)
        self.method = ("grid" if model.n_params <= 3 else "gaussian") if method == "auto" else method
        self.sigma = sigma
        self.outlier_sd = float(outlier_sd)
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.scale = unit_scale(units or model.units, model.units)
        self._index = self._name_index(labels)
        self._order = self._array_order(labels)
        self._prior = prior_moments(model)
        self._ws = workspace(model)  # the session's tables; its pose fits keep one path throughout
        self._frame = 0
        self._early: list = []  # the first frames used, (y, pose), for re-linearisation
        self.estimate: LiveEstimate | None = None
        if self.method == "grid":
            self._grid = MarkerGridFilter(model, sigma=sigma, history_steps=(), rng=self.rng)
            self._state = self._grid.init_state()
        else:
            self._state = GaussianState(self._prior[0].copy(), np.zeros((model.n_params,) * 2), None, None,
                                        0.0, 0, 0)
        self._sigma_fallback = (0.01 * _model_size(model)) ** 2  # before the residuals say: 1 % of the model's size

    # ------------------------------------------------------------------ names
    def _name_index(self, labels) -> dict[str, int]:
        """Stream name -> model marker index."""
        model = self.model
        index = {n: i for i, n in enumerate(model.marker_names)}
        for name, label in model.marker_labels.items():
            index[label] = model.marker_names.index(name)
        if isinstance(labels, Mapping):
            for stream, name in labels.items():
                if name not in model.marker_names:
                    raise DataError(f"labels maps {stream!r} to {name!r}, which is not a marker of {model.name!r}",
                                    f"use one of {', '.join(model.marker_names)}")
                index[str(stream)] = model.marker_names.index(name)
        return index

    def _array_order(self, labels):
        """(model index of each array row, or -1) for array frames; None if none declared."""
        if labels is None or isinstance(labels, Mapping):
            return None
        if isinstance(labels, str) or not isinstance(labels, Sequence):
            raise DataError("labels must be a sequence of marker names or a mapping",
                            "pass the stream's marker names in the order of the array rows")
        order = np.array([self._index.get(str(n), -1) for n in labels], dtype=int)
        if not (order >= 0).any():
            raise DataError(f"none of the labels matches a marker of {self.model.name!r}",
                            f"name the stream's markers as the model does: {', '.join(self.model.marker_names)}")
        return order

    def _frame_array(self, frame) -> np.ndarray:
        """The frame as ``(M, D)`` in model order and units, NaN where missing."""
        model = self.model
        M, D = len(model.markers), model.dim
        y = np.full((M, D), np.nan)
        if isinstance(frame, Mapping):
            for name, xyz in frame.items():
                i = self._index.get(str(name))
                if i is not None:
                    v = np.asarray(xyz, dtype=float).ravel()
                    if v.size < D:
                        raise DataError(f"marker {name!r} has {v.size} coordinates, the model needs {D}",
                                        "send x, y (and z) for every marker")
                    y[i] = v[:D]
        else:
            a = np.asarray(frame, dtype=float)
            order = self._order
            if order is None:
                if a.shape[0] != M:
                    raise DataError(f"an array frame has {a.shape[0]} rows; without labels it must have one per "
                                    f"model marker ({M})", "pass labels=... naming the rows")
                order = np.arange(M)
            if a.ndim != 2 or a.shape[0] != order.size or a.shape[1] < D:
                raise DataError(f"an array frame must be ({order.size}, {D}) or ({order.size}, 3); got {a.shape}",
                                "send one row per declared label")
            keep = order >= 0
            y[order[keep]] = a[keep, :D]
        return y * self.scale

    # ------------------------------------------------------------------ the update
    def push(self, frame) -> LiveEstimate:
        """Fold one frame in and return the estimate after it.

        Parameters
        ----------
        frame : mapping of str to (3,) or (D,) float, or (N, 3) array
            Marker positions by name, or as rows in the order of ``labels``. Missing
            markers: absent from the mapping, or NaN.
        """
        y = self._frame_array(frame)
        self._frame += 1
        if self.method == "grid":
            self.estimate = self._push_grid(y)
        else:
            self.estimate = self._push_gaussian(y)
        return self.estimate

    def _usable(self, y) -> bool:
        return int(np.isfinite(y).all(axis=-1).sum()) * self.model.dim > self.model.n_pose

    def _current_sigma2(self) -> float:
        st = self._state
        return _sigma2(st.rss, st.n_obs, st.n_used, self.model, self.sigma, self._sigma_fallback)

    def _screen(self, resid, sigma2, present) -> np.ndarray:
        """Markers to leave out: the worst one beyond ``outlier_sd`` noise sds (once the noise is known)."""
        known = self.sigma is not None or self._state.n_used >= 10
        if not known:
            return np.zeros_like(present)
        # a marker residual distance has D coordinates of noise: compare with sqrt(D) sigma
        limit = self.outlier_sd * math.sqrt(sigma2 * self.model.dim)
        bad = np.zeros_like(present)
        r = np.where(np.isfinite(resid), resid, -np.inf)
        worst = int(np.argmax(r))
        if r[worst] > limit:
            bad[worst] = True
        return bad

    def _push_gaussian(self, y) -> LiveEstimate:
        model, ws = self.model, self._ws
        problems = _missing(y)
        if not self._usable(y):
            return self._estimate(self._state.pose, np.full(len(model.markers), np.nan), False,
                                  problems + ["too few markers to fix the pose: frame not used"], ())
        st = self._state
        s2 = self._current_sigma2()
        if st.pose is None:
            q, _ = initial_pose(model, st.mean, y, self.rng, ws=ws)
        else:
            q0 = st.pose if st.pose_prev is None else 2.0 * st.pose - st.pose_prev
            q, _ = fit_pose(model, st.mean, y, q0, n_iter=10, ws=ws)
        rejected = []
        for _ in range(3):  # leave out up to three markers that do not fit (a swapped pair needs two)
            kin = forward_kinematics(model, st.mean, q, ws)
            resid = _distances(kin.markers, y)
            bad = self._screen(resid, s2, np.isfinite(y).all(axis=-1))
            if not bad.any():
                break
            y = y.copy()
            y[bad] = np.nan
            rejected += [model.marker_names[i] for i in np.flatnonzero(bad)]
            if not self._usable(y):
                return self._estimate(st.pose, resid, False, problems + [
                    f"left out {', '.join(rejected)} (residual beyond {self.outlier_sd:g} sd) and too few "
                    "markers remain: frame not used"], tuple(rejected))
            q, _ = fit_pose(model, st.mean, y, q, n_iter=10, ws=ws)
        else:
            kin = forward_kinematics(model, st.mean, q, ws)
            resid = _distances(kin.markers, y)
        if rejected:
            problems.append(f"left out {', '.join(rejected)}: residual beyond {self.outlier_sd:g} noise sd "
                            "(swapped or wrong label?)")
        self._state = _fold(model, st, y, q, kin, self._prior, s2, ws)
        if self._state.n_used <= _RELINEARISE[-1]:
            self._early.append((y, q))
            if self._state.n_used in _RELINEARISE:
                self._state = relinearise(model, self._state, self._early, self._prior, self.sigma, ws=ws)
        return self._estimate(q, resid, not problems, problems, tuple(rejected), kin.p_world_seg)

    def _push_grid(self, y) -> LiveEstimate:
        model, ws = self.model, self._ws
        problems = _missing(y)
        if not self._usable(y):
            problems.append("too few markers to fix the pose: frame not used")
        self._state = self._grid.update(self._state, y)
        st = self._state
        q = None
        resid = np.full(len(model.markers), np.nan)
        if st.pose is not None:
            lw = self._grid._log_weights(st.rss, st.logdet, st.n_obs, st.n_used).ravel()
            k = int(np.argmax(lw))
            q = st.pose[k]
            if self._usable(y):
                kin = forward_kinematics(model, self._grid._points()[1][k], q, ws)
                resid = _distances(kin.markers, y)
                return self._estimate(q, resid, not problems, problems, (), kin.p_world_seg)
        return self._estimate(q, resid, not problems, problems, ())

    # ------------------------------------------------------------------ the result
    def posterior(self) -> tuple[np.ndarray, np.ndarray]:
        """Current ``(mean (P,), cov (P, P))`` of theta (a Gaussian summary of the grid posterior)."""
        if self.method == "grid":
            post = self._grid.posterior(self._state)
            lw = post.log_weights.ravel()
            w = np.exp(lw - lw.max())
            w /= w.sum()
            pts = self._grid._points()[1]
            mean = w @ pts
            d = pts - mean
            # plus the grid's own quantisation variance (step^2 / 12), so that a posterior on one point
            # still has an invertible covariance
            steps = np.array([np.diff(a).mean() if a.size > 1 else 0.0 for a in post.axes])
            return mean, (d * w[:, None]).T @ d + np.diag(steps**2 / 12.0)
        _, L0, _, _ = self._prior
        Lam = L0 + self._state.info_data / self._current_sigma2()
        return self._state.mean.copy(), np.linalg.inv(Lam)

    def _estimate(self, q, resid, healthy, problems, rejected, centres=None) -> LiveEstimate:
        model, ws = self.model, self._ws
        mean, cov = self.posterior()
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        z = _Z95
        _, L0, lo, hi = self._prior
        prior_sd = 1.0 / np.sqrt(np.diag(L0))
        params = {}
        for k, p in enumerate(model.parameters):
            unit = "deg" if p.kind == "axis_direction" else model.units
            status = "prior" if sd[k] > 0.9 * prior_sd[k] else "identified"
            params[p.name] = ParameterEstimate(p.name, unit, float(mean[k]), float(mean[k]), float(sd[k]),
                                               (float(max(mean[k] - z * sd[k], lo[k])),
                                                float(min(mean[k] + z * sd[k], hi[k]))), status=status)
        joints = {}
        if q is not None:
            if centres is None:
                centres = forward_kinematics(model, mean, q, ws).p_world_seg
            joints = {s.joint.name: _frozen(centres[i]) for i, s in enumerate(model.segments)}
        return LiveEstimate(
            frame=self._frame, time=self._frame / self.rate, parameters=MappingProxyType(params),
            theta=_frozen(mean), cov=_frozen(cov), pose=_frozen(q), joint_centres=MappingProxyType(joints),
            marker_residuals=MappingProxyType({n: float(r) for n, r in zip(model.marker_names, resid, strict=True)}),
            sigma=math.sqrt(self._current_sigma2()) if self.method == "gaussian" else self._grid_sigma(),
            healthy=bool(healthy), health="ok" if healthy else "; ".join(problems), rejected=tuple(rejected))

    def _grid_sigma(self) -> float:
        st = self._state
        s2 = self._grid._dof_sigma2(np.min(st.rss), st.n_obs, st.n_used)
        return float(math.sqrt(s2)) if np.isfinite(s2) else math.nan

    def _current_sigma2_any(self) -> float:
        if self.method == "gaussian":
            return self._current_sigma2()
        s = self._grid_sigma()
        return s * s if np.isfinite(s) else self._sigma_fallback

    # ------------------------------------------------------------------ advice
    def advice(self, amplitudes_deg=(30.0, 60.0, 90.0), n_frames: int = 30) -> list[Advice]:
        """Which movement would help most now, ranked.

        For each rotational degree of freedom of a joint (not the root) and each
        amplitude, a sweep of that coordinate through the amplitude, centred on
        its current value and kept inside the joint's range, with the others
        held at the current pose, adds the expected information
        ``\\sum_s \\tilde K_s^\\top \\tilde K_s / \\sigma^2`` (``n_frames`` poses
        of the sweep) to the current posterior precision. The worst-determined
        parameter is the one whose sd is the largest fraction of its prior sd;
        the movements are ranked by that parameter's sd after the movement.

        Returns
        -------
        list of Advice
            Best first. Empty before the first pose is known.
        """
        if self.estimate is None or self.estimate.pose is None:
            return []
        model, ws = self.model, self._ws
        mean, cov = self.posterior()
        _, L0, _, _ = self._prior
        prior_sd = 1.0 / np.sqrt(np.diag(L0))
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        worst = int(np.argmax(sd / prior_sd))
        s2 = self._current_sigma2_any()
        q_now = np.asarray(self.estimate.pose, float)
        cands, poses = _sweeps(model, q_now, amplitudes_deg, n_frames)
        if not cands:
            return []
        _, Jq, Jt = marker_jacobian(model, mean, np.concatenate(poses), ws)
        N = Jq.shape[-3] * Jq.shape[-2]
        Kt = marginal_theta_jacobian(Jq.reshape(-1, N, model.n_pose), Jt.reshape(-1, N, model.n_params))
        info = np.einsum("fnp,fnq->fpq", Kt, Kt).reshape(len(cands), n_frames, model.n_params, model.n_params)
        Lam = np.linalg.inv(cov) + info.sum(axis=1) / s2  # (C, P, P)
        after = np.sqrt(np.linalg.inv(Lam)[:, worst, worst])
        out = []
        pname = model.parameters[worst].name
        for c, sd_after in zip(cands, after, strict=True):
            k, lo, hi = c
            out.append(Advice(_words(model, k, lo, hi), model.segments[model.dofs[k].segment].joint.name, k,
                              lo, hi, pname, float(sd[worst]), float(sd_after)))
        out.sort(key=lambda a: a.sd_after)
        return out


def _distances(x, y) -> np.ndarray:
    """Distance ``(M,)`` of each observed marker from its model position (NaN where missing)."""
    return np.where(np.isfinite(y).all(axis=-1), np.linalg.norm(np.nan_to_num(y) - x, axis=-1), np.nan)


def _sweeps(model: Model, q_now, amplitudes_deg, n_frames):
    """Candidate sweeps ``[(dof, lo_deg, hi_deg)]`` and their poses ``[(n_frames, Q)]``."""
    from skelid.estimators.pose import _rotation_ranges

    ranges = _rotation_ranges(model)
    cands, poses = [], []
    s = np.sin(np.linspace(0.0, 2.0 * np.pi, n_frames, endpoint=False))
    for k, d in enumerate(model.dofs):
        if d.kind != "R" or model.parent_index[d.segment] < 0:
            continue  # the root's motion shows no joint
        lo_r, hi_r = ranges[k]
        for amp in amplitudes_deg:
            half = 0.5 * min(math.radians(amp), hi_r - lo_r)
            c = float(np.clip(q_now[k], lo_r + half, hi_r - half))
            seq = np.repeat(q_now[None], n_frames, axis=0)
            seq[:, k] = c + half * s
            lo, hi = math.degrees(c - half), math.degrees(c + half)
            if cands and cands[-1][0] == k and abs(cands[-1][1] - lo) < 1e-9 and abs(cands[-1][2] - hi) < 1e-9:
                continue  # the range already capped a smaller amplitude
            cands.append((k, lo, hi))
            poses.append(seq)
    return cands, poses


def _words(model: Model, k: int, lo: float, hi: float) -> str:
    seg = model.segments[model.dofs[k].segment]
    j = seg.joint
    ks = [i for i, d in enumerate(model.dofs) if d.segment == model.dofs[k].segment and d.kind == "R"]
    rng = f"{lo:.0f} to {hi:.0f}°" if lo < 0 else f"{lo:.0f}–{hi:.0f}°"
    if len(ks) == 1:
        return f"bend the {j.name} through {rng}"
    axis = np.asarray(model.dofs[k].axis, float)
    names = {0: "x", 1: "y", 2: "z"}
    a = int(np.argmax(np.abs(axis)))
    about = f"its {names[a]} axis" if abs(axis[a]) > 0.99 else f"axis {ks.index(k) + 1} of {len(ks)}"
    return f"turn the {j.name} about {about} through {rng}"


def _missing(y) -> list[str]:
    """The frame's problem line for markers without a position (none when every marker is there)."""
    n = int((~np.isfinite(y).all(axis=-1)).sum())
    return [f"{n} marker(s) missing"] if n else []
