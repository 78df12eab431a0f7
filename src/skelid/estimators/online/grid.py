"""Recursive (online) grid filter with the marker-space likelihood.

For hypotheses ``theta_k`` on a grid of 1-3 parameters, every frame ``t``
contributes

.. math::

    \\ell_t(\\theta_k) = -\\frac{\\mathrm{RSS}_t(\\theta_k)}{2\\sigma^2}
                        - \\tfrac12 \\log\\det J_t^\\top J_t \\quad\\text{(Laplace)}

(without the log-determinant for the profile likelihood), where
``RSS_t(theta_k)`` is the marker residual after fitting frame ``t``'s pose for
that hypothesis. The state keeps, per hypothesis, the running sums of RSS and
log-determinants and the last pose (the warm start of the next frame), so it
is ``O(K)`` whatever the trial length. The posterior at any step is

.. math:: \\log p_t(\\theta_k) = \\log p_0(\\theta_k) + \\sum_{s \\le t} \\ell_s(\\theta_k) - \\log Z_t ,

with ``sigma`` fixed by the user or estimated from the running residual at
the most likely hypothesis, ``sigma^2 = RSS / (n_obs - Q n_frames - P)``,
either way at least :func:`noise_floor` (a noise-free stream would otherwise
give ``sigma^2 = 0`` and no likelihood at all).
Unlike the seed filter this needs no per-frame solve of a noisy length and
drops no frame that has enough markers to fix its pose. It carries the
O(sigma^2) bias of the profile and Laplace likelihoods (no motion model, no
bias correction); :class:`~skelid.estimators.marker.MarkerEstimator` is the
batch estimator with both.

Example
-------
>>> import numpy as np
>>> from skelid.simulate import builtin_model, simulate
>>> model = builtin_model("case-a")
>>> trial = simulate(model, n_frames=80, sigma=5.0, rng=np.random.default_rng(0))
>>> r = MarkerGridFilter(model, rng=0, axes=(np.linspace(230.0, 270.0, 41),)).fit(trial.data).result()
>>> abs(r.parameters["L2"].mean - 250.0) < 4 * r.parameters["L2"].sd + 1.0
True
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from skelid._stop import interruptible
from skelid.data import MarkerData
from skelid.errors import DataError, ModelError, SettingError
from skelid.estimators.base import (
    RATE,
    RNG,
    Setting,
    array_or_none,
    build_result,
    check_fitted,
    check_model,
    check_settings,
    count,
    counted,
    emit,
    make_rng,
    marker_array,
    one_of,
    positive_or_none,
    steps,
)
from skelid.estimators.checks.misfit import STILL_JOINT_DEG
from skelid.estimators.fit.joint import usable_frames
from skelid.estimators.fit.pose import FramePoseFitter, _model_size, initial_pose
from skelid.estimators.uncertainty.posterior import GridPosterior
from skelid.model.description import Model
from skelid.result import FitResult, NoiseEstimate, Warning

#: The noise floor as a fraction of the model's size (:func:`noise_floor`).
NOISE_FLOOR = 1e-5


def noise_floor(model: Model) -> float:
    """The least marker noise variance the online filters use: ``(NOISE_FLOOR * size)^2``.

    ``size`` is the model's extent (its units). A noise-free stream (simulated
    markers, ``sigma=0``) leaves residuals at rounding level, ``sigma^2 ~ 1e-32``
    in metres, or exactly zero where a grid point is the truth: the data's
    precision then swamps the prior's (the Gaussian form's precision of theta is
    singular wherever a few frames do not fix it yet), or the likelihood is
    undefined (the grid form). Below a hundred-thousandth of the body (18 um on
    a 1.8 m body, far under any motion-capture system's noise) the noise level
    is held at that floor.
    """
    return (NOISE_FLOOR * _model_size(model)) ** 2


class GridState(NamedTuple):
    """Online state of :class:`MarkerGridFilter` (all arrays over the K grid points)."""

    rss: np.ndarray  # (K,) running residual sum of squares
    logdet: np.ndarray  # (K,) running log det J^T J
    pose: np.ndarray | None  # (K, Q) last fitted pose per hypothesis
    n_obs: int
    n_frames: int
    n_used: int
    history: tuple  # ((step, log_weights), ...)


class MarkerGridFilter:
    """Grid posterior over 1-3 parameters, updated frame by frame from marker coordinates.

    Parameters
    ----------
    model : Model
    sigma : float, optional
        Marker noise (model units); estimated online if not given.
    likelihood : {'laplace', 'profile'}
    axes : sequence of arrays, optional
        Grid per parameter; defaults to each parameter's prior interval and ``grid_step``.
    history_steps : sequence of int
        Steps (frame counts) at which the posterior is stored.
    n_iter : int
        Pose iterations per frame and hypothesis in :meth:`update`.
    rng : int, numpy.random.Generator or None
    rate : float, optional
        Sampling rate (Hz) of data given as an array; required then.

    Attributes
    ----------
    posterior_ : GridPosterior
    state_ : GridState
        The online state after the last frame.
    map_path_ : (T,) float
        Most likely value of the first parameter after each step.
    sigma_ : float
    frames_used_ : (T,) bool
    warnings_ : tuple of Warning
    """

    name = "marker-grid"
    settings = (
        Setting("sigma", positive_or_none, "a positive noise level in model units, or None to estimate it",
                cli="sigma"),
        Setting("likelihood", one_of("laplace", "profile"), "'laplace' or 'profile'"),
        Setting("axes", lambda v: v is None or all(array_or_none(a) and np.size(a) > 0 for a in v),
                "None or one non-empty sequence of finite grid values per parameter"),
        Setting("history_steps", steps, "a sequence of positive frame counts"),
        Setting("n_iter", count, counted("iterations")),
        RNG,
        RATE,
    )

    def __init__(self, model: Model, sigma: float | None = None, likelihood: str = "laplace",
                 axes=None, history_steps=(50, 100, 500), n_iter: int = 8,
                 rng: np.random.Generator | int | None = None, rate: float | None = None):
        self.model = check_model(model, type(self).__name__)
        self.sigma = sigma
        self.likelihood = likelihood
        self.axes = axes
        self.history_steps = history_steps
        self.n_iter = n_iter
        self.rng = rng
        self.rate = rate

    # ---------------------------------------------------------------- grid
    def _axes(self):
        if not 1 <= self.model.n_params <= 3:
            raise ModelError(
                f"a grid filter handles 1 to 3 parameters; model {self.model.name!r} has "
                f"{self.model.n_params}", "use --method marker for more parameters")
        if self.axes is not None:
            return self._given_axes()
        return tuple(p.grid for p in self.model.parameters)

    def _given_axes(self) -> tuple[np.ndarray, ...]:
        """The ``axes`` setting as one increasing 1-D grid per parameter, or a one-line :class:`SettingError`."""
        names = list(self.model.parameter_names)
        try:
            axes = tuple(np.asarray(a, float) for a in self.axes)
        except (TypeError, ValueError):
            axes = ()
        if len(axes) != len(names) or not all(a.ndim == 1 and a.size and bool(np.all(np.diff(a) > 0))
                                              for a in axes):
            raise SettingError(f"{type(self).__name__} setting axes does not fit model {self.model.name!r}: "
                               f"{len(names)} parameter(s) {names} need one increasing grid each",
                               f"give {len(names)} one-dimensional increasing arrays, e.g. "
                               "(numpy.linspace(230.0, 270.0, 41),), or None for the priors' grids")
        return axes

    def _grid(self):
        """``(axes, points (K, n_params), log prior (K,))``, built once per model and axes."""
        cached = self.__dict__.get("_grid_cache")
        if cached is not None and cached[0] is self.model and cached[1] is self.axes:
            return cached[2]
        axes = self._axes()
        self._check_size(axes)
        mesh = np.meshgrid(*axes, indexing="ij")
        pts = np.stack([m.ravel() for m in mesh], axis=-1)
        log_prior = self.model.log_prior(pts)
        pts.flags.writeable = False
        log_prior.flags.writeable = False
        self._grid_cache = (self.model, self.axes, (axes, pts, log_prior))
        return axes, pts, log_prior

    def _points(self):
        return self._grid()[:2]

    def _check_size(self, axes) -> None:
        """Refuse in one line a grid whose points' pose Jacobians would not fit the memory limit
        (:mod:`skelid.resources`: ``SKELID_MAX_MEMORY``, 4 GiB by default), before anything is allocated."""
        from skelid import resources

        m = self.model
        n_points = float(np.prod([float(a.size) for a in axes]))
        per_point = len(m.markers) * m.dim * (m.n_pose + m.n_params) * 8 * resources.TEMP_FACTOR + (m.n_pose + 16) * 8
        limits = resources.Limits.from_settings()
        cost = resources.Cost(n_points * per_point, 0.0, f"a grid of {n_points:.3g} points",
                              "a coarser grid_step in the model file (or a smaller axes setting)")
        resources.check(cost, resources.Limits(limits.memory, float("inf")), what=f"the {self.name} fit")

    def _floor(self) -> float:
        """:func:`noise_floor` of the model (computed once per model)."""
        cached = self.__dict__.get("_floor_cache")
        if cached is None or cached[0] is not self.model:
            cached = (self.model, noise_floor(self.model))
            self._floor_cache = cached
        return cached[1]

    def _dof_sigma2(self, rss_min, n_obs, n_used):
        """Noise variance: ``sigma^2`` if given, else ``RSS_min / dof`` (NaN before any degree of freedom),
        at least :func:`noise_floor`."""
        if self.sigma is not None:
            return max(float(self.sigma) ** 2, self._floor())
        dof = n_obs - self.model.n_pose * n_used - self.model.n_params
        return max(float(rss_min / dof), self._floor()) if dof > 0 else np.nan

    def _log_weights(self, rss, logdet, n_obs, n_used):
        axes, _, lw = self._grid()
        s2 = self._dof_sigma2(np.min(rss), n_obs, n_used)
        if np.isfinite(s2):
            lw = lw - rss / (2.0 * s2)
            if self.likelihood == "laplace":
                lw = lw - 0.5 * logdet
        lw = lw.reshape(tuple(a.size for a in axes))
        return lw - np.logaddexp.reduce(lw.ravel())

    def _fitter(self, pts) -> FramePoseFitter:
        """The per-frame pose fitter of the grid points (built once per model and grid)."""
        cached = self.__dict__.get("_fitter_cache")
        if cached is None or cached[0] is not pts:
            cached = (pts, FramePoseFitter(self.model, pts))
            self._fitter_cache = cached
        return cached[1]

    def _frame_loglik_terms(self, pts, q, y):
        """Fit the poses of one frame ``y (M, D)`` for every hypothesis; RSS and log det."""
        return self._fitter(pts).fit(y, q, n_iter=self.n_iter)

    # -------------------------------------------------------------- online
    def init_state(self) -> GridState:
        K = self._points()[1].shape[0]
        return GridState(np.zeros(K), np.zeros(K), None, 0, 0, 0, ())

    def update(self, state: GridState, frame) -> GridState:
        """Fold in one frame ``(M, D)`` (model order and units)."""
        frame = np.asarray(frame, float)
        _, pts = self._points()
        n_coord = int(np.isfinite(frame).all(axis=-1).sum()) * self.model.dim
        step = state.n_frames + 1
        usable = bool(usable_frames(self.model, frame[None])[0])
        q = state.pose
        if usable and q is None:
            q0, _ = initial_pose(self.model, self.model.theta_center, frame, make_rng(self.rng),
                                 ws=self._fitter(pts).ws)  # the fitter's workspace: one pose path
            q = np.broadcast_to(q0, (len(pts), self.model.n_pose))
        if usable:
            q, rss, logdet = self._frame_loglik_terms(pts, q, frame)
            state = GridState(state.rss + rss, state.logdet + logdet, q, state.n_obs + n_coord,
                              step, state.n_used + 1, state.history)
        else:
            state = state._replace(n_frames=step)
        if step in tuple(self.history_steps):
            lw = self._log_weights(state.rss, state.logdet, state.n_obs, state.n_used)
            state = state._replace(history=state.history + ((step, lw),))
        return state

    def posterior(self, state: GridState) -> GridPosterior:
        axes, _ = self._points()
        lw = self._log_weights(state.rss, state.logdet, state.n_obs, state.n_used)
        return GridPosterior(self.model.parameter_names, axes, lw, state.n_frames, state.history)

    # --------------------------------------------------------------- batch
    @interruptible
    def fit(self, data: MarkerData | np.ndarray, *, progress=None) -> MarkerGridFilter:
        """Fold :meth:`update` over every frame (the one loop over frames)."""
        check_settings(self)
        y, _ = marker_array(self.model, data, self.rate, self.name)
        axes, _ = self._points()
        state = self.init_state()
        shape = tuple(a.size for a in axes)
        path = np.empty(len(y))
        used = np.zeros(len(y), bool)
        for t, frame in enumerate(y):
            n_before = state.n_used
            state = self.update(state, frame)
            used[t] = state.n_used > n_before
            lw = self._log_weights(state.rss, state.logdet, state.n_obs, state.n_used)
            path[t] = axes[0][np.unravel_index(np.argmax(lw), shape)[0]]
            if progress is not None:
                progress(1)
        if not used.any():
            raise DataError("no frame has enough markers to fix the pose",
                            "check that the file holds the model's markers")
        self.state_ = state
        self.posterior_ = self.posterior(state)
        self.map_path_ = path
        self.sigma_ = float(np.sqrt(self._dof_sigma2(state.rss.min(), state.n_obs, state.n_used)))
        self.frames_used_ = used
        found = []
        if (~used).any():
            found.append(Warning("frames-skipped", f"{int((~used).sum())} of {len(y)} frames have too few markers "
                                 "to fix the pose and were skipped"))
        self.still_ = still_trial(self.model, self.posterior_.mean, y[used], make_rng(self.rng))
        if self.still_:
            found.append(Warning("still-joint", f"no joint moved more than {STILL_JOINT_DEG:g} degrees: the "
                                 "estimate follows from where the model places the markers, not from motion "
                                 "(status 'placement')", list(self.model.parameter_names)))
        self.warnings_ = emit(found)
        return self

    def result(self) -> FitResult:
        """The typed result (:class:`~skelid.result.FitResult`)."""
        check_fitted(self)
        used = self.frames_used_
        status = {n: "placement" for n in self.model.parameter_names} if getattr(self, "still_", False) else None
        return build_result(self, self.posterior_, noise=NoiseEstimate(self.sigma_, fixed=self.sigma is not None),
                            skipped={"too_few_coordinates": int((~used).sum())},
                            arrays={"map_path": self.map_path_}, status=status)


def still_trial(model: Model, theta, y, rng) -> bool:
    """Whether no joint of ``model`` moved more than :data:`~skelid.estimators.checks.misfit.STILL_JOINT_DEG`
    over the frames ``y (T, M, D)``, their poses fitted at ``theta`` (a model with no joint rotation: False).

    Such a trial informs the geometry only through where the model places the markers on their segments."""
    from skelid.estimators.checks.misfit import joint_ranges, joint_rotations
    from skelid.estimators.fit.pose import track_poses

    if not len(y) or not joint_rotations(model).size:
        return False
    poses = track_poses(model, np.asarray(theta, float), y, rng)[0]
    ranges = joint_ranges(model, poses, theta=theta)
    return bool(ranges) and max(max(r) for r in ranges.values()) < STILL_JOINT_DEG
