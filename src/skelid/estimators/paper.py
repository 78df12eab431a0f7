"""The seed method: a per-frame constraint solve, then a discrete Bayes filter.

**Per-frame solve.** A joint centre belongs to both segments it joins, so its
distance to every marker on either segment is fixed by the model. With the
joint centres ``J`` (world positions, unknown in every frame) and the length
parameter ``L``, each frame gives the equations

.. math:: \\lVert J_a - y_m \\rVert = d_{am}(L), \\qquad \\lVert J_a - J_b \\rVert = d_{ab}(L)

for every marker ``m`` and joint ``b`` on a segment that joint ``a`` touches,
where the distances ``d`` come from the marker and joint positions in the
segment frames. For the planar arm of case A these are ``|MA|, |MB|, |NB|,
|NC|`` and ``|MN| = L2`` (five equations, five unknowns ``M, N, L2``); case B
adds ``|MD|, |ND|`` (seven equations, least squares). The system is solved by
Newton-Raphson (Gauss-Newton when over-determined), started from the previous
frame's solution. The solved ``L`` is the frame's "measured" length; a frame
whose iteration does not converge, or converges outside the prior interval,
is dropped and counted.

**Bayes filter.** On the grid ``L_min, L_min + ΔL, ..., L_max``,

.. math:: \\log p_t(L_k) = \\log p_{t-1}(L_k) - \\frac{(\\hat L_t - L_k)^2}{2\\sigma^2} - \\log Z_t,

with ``σ`` the marker noise (15 mm in the seed) and ``p_0`` the prior.

Notes
-----
Where the seed is silent this implementation reads it as follows. Markers are
fixed in their segment's frame, whose origin is the proximal joint, so the
distance from a marker on the unknown segment to its *distal* joint depends on
``L`` (that is what makes ``|MN| = L2`` an equation rather than a definition).
The first frame is started from a marker fit of the model at the prior's
centre. A frame that fails does not move the starting point of the next.

Example
-------
>>> import numpy as np
>>> from skelid.simulate import builtin_model, simulate
>>> model = builtin_model("case-a")
>>> trial = simulate(model, n_frames=80, sigma=5.0, rng=np.random.default_rng(0))
>>> r = PaperFilter(model, rng=0).fit(trial.data).result()
>>> r.parameters["L2"].interval[0] < r.parameters["L2"].mean < r.parameters["L2"].interval[1]
True
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from skelid._stop import interruptible
from skelid.data import MarkerData, unit_scale
from skelid.errors import IdentifiabilityError, ModelError
from skelid.estimators.base import (
    RATE,
    RNG,
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
    positive_or_none,
    steps,
)
from skelid.estimators.fit.pose import initial_pose
from skelid.estimators.uncertainty.posterior import GridPosterior
from skelid.model.description import Model
from skelid.model.kinematics import joint_positions
from skelid.result import FitResult, NoiseEstimate, Warning

#: dropping more than this fraction of the frames gets a warning
DROP_WARN_FRACTION = 0.2


class ConstraintSystem:
    """The seed's distance equations for a model with one ``length`` parameter.

    Parameters
    ----------
    model : Model

    Attributes
    ----------
    joints : (J,) int
        Segments whose joint centre is an unknown (every non-root segment).
    eq_a, eq_b : (E,) int
        Endpoints of each equation, indices into ``[joint centres; markers]``.
    eq_d0, eq_d1 : (E, D) float
        The two points in their common segment's frame are ``a0 + a1 L`` and
        ``b0 + b1 L``; ``eq_d0 + eq_d1 L`` is their difference.
    """

    def __init__(self, model: Model):
        check_model(model, type(self).__name__)
        if model.n_params != 1 or model.parameters[0].kind != "length":
            raise ModelError(
                f"the paper method needs exactly one parameter of kind 'length'; model "
                f"{model.name!r} has {model.n_params} ({', '.join(model.parameter_names) or 'none'})",
                "use --method marker, which handles any parameters",
            )
        self.model = model
        D, S = model.dim, len(model.segments)
        g_base, A = model.geometry_map
        self.joints = np.array([i for i in range(S) if model.parent_index[i] >= 0], dtype=int)
        slot = {int(s): k for k, s in enumerate(self.joints)}
        J = len(self.joints)
        # points of each segment: (world index, frame position base, frame position slope)
        pts = {s: [] for s in range(S)}
        for s in self.joints:
            pts[int(s)].append((slot[int(s)], np.zeros(D), np.zeros(D)))
            par = int(model.parent_index[s])
            sl = slice(int(s) * D, int(s) * D + D)
            pts[par].append((slot[int(s)], g_base[sl], A[sl, 0]))
        for m, s in enumerate(model.marker_segment):
            sl = slice((S + m) * D, (S + m) * D + D)
            pts[int(s)].append((J + m, g_base[sl], A[sl, 0]))
        ea, eb, d0, d1 = [], [], [], []
        for s in range(S):
            p = pts[s]
            for i in range(len(p)):
                for j in range(i + 1, len(p)):
                    if p[i][0] >= J and p[j][0] >= J:
                        continue  # two markers: no unknown in the equation
                    ea.append(p[i][0])
                    eb.append(p[j][0])
                    d0.append(p[i][1] - p[j][1])
                    d1.append(p[i][2] - p[j][2])
        self.eq_a, self.eq_b = np.array(ea, int), np.array(eb, int)
        self.eq_d0, self.eq_d1 = np.array(d0, float), np.array(d1, float)
        self.n_joints = J
        self.n_unknowns = J * D + 1
        self.scale = float(max(np.abs(model.nominal_geometry).max(), 1e-9))
        names = [model.segments[s].joint.name for s in self.joints] + list(model.marker_names)
        self.labels = [f"|{names[a]}{names[b]}|" for a, b in zip(self.eq_a, self.eq_b, strict=True)]
        if len(self.eq_a) < self.n_unknowns:
            raise IdentifiabilityError(
                f"model {model.name!r} gives {len(self.eq_a)} distance equations for "
                f"{self.n_unknowns} unknowns per frame",
                "add markers on the segments next to each joint",
            )

    def residual(self, x, y):
        """Residuals ``(E,)`` and Jacobian ``(E, n_unknowns)`` at ``x = [joint centres, L]``."""
        D, J = self.model.dim, self.n_joints
        L = x[-1]
        W = np.concatenate([x[:-1].reshape(J, D), y], axis=0)
        diff = W[self.eq_a] - W[self.eq_b]
        dist = np.linalg.norm(diff, axis=1)
        dv = self.eq_d0 + self.eq_d1 * L
        dmod = np.linalg.norm(dv, axis=1)
        r = dist - dmod
        u = diff / np.where(dist > 0, dist, 1.0)[:, None]
        jac = np.zeros((len(r), self.n_unknowns))
        E = np.arange(len(r))
        for end, sign in ((self.eq_a, 1.0), (self.eq_b, -1.0)):
            isj = end < J
            for d in range(D):
                np.add.at(jac, (E[isj], end[isj] * D + d), sign * u[isj, d])
        jac[:, -1] = -np.einsum("ed,ed->e", dv, self.eq_d1) / np.where(dmod > 0, dmod, 1.0)
        return r, jac

    def solve(self, y, x0, max_iter: int = 50, tol: float = 1e-10):
        """Newton-Raphson / Gauss-Newton for one frame.

        Parameters
        ----------
        y : (M, D) float
            The frame's markers (NaN where missing).
        x0 : (J*D + 1,) float
            Starting point.

        Returns
        -------
        x : (J*D + 1,) float
        converged : bool

        Notes
        -----
        The equations hold distances only: the frame is solved about its markers' mean (in whole
        units), so that where the frame sits changes neither the iteration nor its tests.
        """
        y = np.asarray(y, dtype=float)
        ok = np.isfinite(y).all(axis=1)
        centre = np.round(y[ok].mean(axis=0)) if ok.any() else np.zeros(y.shape[-1])
        move = np.append(np.tile(centre, self.n_joints), 0.0)  # joint positions move, the length does not
        x, converged = self._newton(y - centre, np.asarray(x0, dtype=float) - move, ok, max_iter, tol)
        return x + move, converged

    def _newton(self, y, x0, ok, max_iter: int, tol: float):
        """:meth:`solve` on a frame ``y (M, D)`` about its centre; ``ok (M,)``: markers present."""
        J = self.n_joints
        use = np.ones(len(self.eq_a), bool)
        for end in (self.eq_a, self.eq_b):
            ism = end >= J
            use[ism] &= ok[end[ism] - J]
        if use.sum() < self.n_unknowns:
            return x0, False
        square = use.sum() == self.n_unknowns
        y0 = np.where(ok[:, None], y, 0.0)
        x = np.array(x0, dtype=float)
        for _ in range(max_iter):
            r, jac = self.residual(x, y0)
            r, jac = r[use], jac[use]
            if square:
                try:
                    step = np.linalg.solve(jac, -r)
                except np.linalg.LinAlgError:
                    return x, False
            else:
                step = np.linalg.lstsq(jac, -r, rcond=None)[0]
            x = x + step
            if not np.all(np.isfinite(x)) or np.abs(x).max() > 1e3 * self.scale:
                return x, False
            if np.linalg.norm(step) <= tol * self.scale:
                r, _ = self.residual(x, y0)
                if square and np.abs(r[use]).max() > 1e-6 * self.scale:
                    return x, False
                return x, True
        return x, False


class PaperState(NamedTuple):
    """Online state of :class:`PaperFilter`."""

    posterior: GridPosterior
    x: np.ndarray | None  # last converged solution (warm start)
    n_frames: int
    n_used: int
    measured: float  # this frame's measured length (NaN if dropped)


class PaperFilter:
    """The seed estimator: per-frame Newton-Raphson, then a grid Bayes filter.

    Parameters
    ----------
    model : Model
        Exactly one parameter, of kind ``length``.
    sigma : float, optional
        Width of the Gaussian likelihood of the measured length, in model
        units; defaults to 15 mm.
    history_steps : sequence of int
        Frame counts at which to keep a copy of the posterior.
    max_iter : int
        Newton iterations per frame.
    rng : int, numpy.random.Generator or None
        For the random starts of the first frame's pose fit.
    rate : float, optional
        Sampling rate (Hz) of data given as an array; required then.

    Attributes
    ----------
    posterior_ : GridPosterior
    state_ : PaperState
        The online state after the last frame.
    measured_ : (F,) float
        Per-frame solved length; NaN for dropped frames.
    frames_used_ : (F,) bool
    map_path_ : (F,) float
        Most likely length after each step.
    sigma_ : float
        The likelihood's width used.
    warnings_ : tuple of Warning
    """

    name = "paper"
    settings = (
        Setting("sigma", positive_or_none, "a positive width in model units, or None for 15 mm", cli="sigma"),
        Setting("history_steps", steps, "a sequence of positive frame counts"),
        Setting("max_iter", count, counted("iterations")),
        RNG,
        RATE,
    )

    def __init__(self, model: Model, sigma: float | None = None, history_steps=(50, 100, 500),
                 max_iter: int = 50, rng: np.random.Generator | int | None = None, rate: float | None = None):
        self.model = check_model(model, type(self).__name__)
        self.sigma = sigma
        self.history_steps = history_steps
        self.max_iter = max_iter
        self.rng = rng
        self.rate = rate

    # ---------------------------------------------------------------- helpers
    @property
    def system(self) -> ConstraintSystem:
        if not hasattr(self, "_system"):
            self._system = ConstraintSystem(self.model)
        return self._system

    def _sigma(self) -> float:
        return self.sigma if self.sigma is not None else 15.0 * unit_scale("mm", self.model.units)

    def _grid(self) -> np.ndarray:
        return self.model.parameters[0].grid

    def _loglik(self, measured) -> np.ndarray:
        """(..., K) Gaussian log-likelihood of each grid value given measured lengths (...)."""
        m = np.asarray(measured, dtype=float)[..., None]
        ll = -0.5 * ((m - self._grid()) / self._sigma()) ** 2
        return np.where(np.isfinite(m), ll, 0.0)

    def _start(self, frame) -> np.ndarray:
        """Starting point for the first frame: a marker fit of the model at the prior centre."""
        theta = self.model.theta_center
        q, _ = initial_pose(self.model, theta, frame, make_rng(self.rng))
        J = joint_positions(self.model, theta, q)[self.system.joints]
        # rounded to a millionth of the model's size: the compiled and numpy pose fits agree to far less, and
        # the Newton iteration of a noisy first frame can go either way on a difference of rounding
        step = 1e-6 * self.system.scale
        return np.concatenate([np.round(J.ravel() / step) * step, theta])

    def _accept(self, x, converged) -> bool:
        pr = self.model.parameters[0].prior
        return bool(converged and pr.lower <= x[-1] <= pr.upper)

    # ------------------------------------------------------------------ online
    def init_state(self) -> PaperState:
        p = self.model.parameters[0]
        post = GridPosterior.from_log_prior((p.name,), (self._grid(),), p.prior.log_pdf(self._grid()))
        return PaperState(post, None, 0, 0, np.nan)

    def update(self, state: PaperState, frame) -> PaperState:
        """Fold in one frame ``(M, D)`` of markers (model order and units)."""
        frame = np.asarray(frame, dtype=float)
        x0 = state.x
        if x0 is None:
            if not np.isfinite(frame).all():
                snap = state.n_frames + 1 in tuple(self.history_steps)
                post = state.posterior.update(0.0, snapshot=snap)
                return PaperState(post, None, state.n_frames + 1, state.n_used, np.nan)
            x0 = self._start(frame)
        x, conv = self.system.solve(frame, x0, self.max_iter)
        ok = self._accept(x, conv)
        measured = x[-1] if ok else np.nan
        snap = state.n_frames + 1 in tuple(self.history_steps)
        post = state.posterior.update(self._loglik(measured), snapshot=snap)
        return PaperState(post, x if ok else state.x if state.x is not None else x0,
                          state.n_frames + 1, state.n_used + ok, measured)

    # ------------------------------------------------------------------ batch
    def measure(self, y, progress=None) -> np.ndarray:
        """Per-frame measured lengths ``(F,)`` (NaN where dropped): the sequential solve, by :meth:`update`."""
        return self._fold(np.asarray(y, float), progress)[1]

    def _fold(self, y, progress=None):
        """Fold :meth:`update` over the frames (the one loop over frames): final state, measured, MAP path."""
        state = self.init_state()
        measured = np.full(len(y), np.nan)
        path = np.full(len(y), np.nan)
        grid = self._grid()
        for t, frame in enumerate(y):
            state = self.update(state, frame)
            measured[t] = state.measured
            path[t] = grid[np.argmax(state.posterior.log_weights)]
            if progress is not None:
                progress(1)
        return state, measured, path

    @interruptible
    def fit(self, data: MarkerData | np.ndarray, *, progress=None) -> PaperFilter:
        """Fold :meth:`update` over a whole trial (``progress``: called with 1 after each frame)."""
        check_settings(self)
        y, _ = marker_array(self.model, data, self.rate, self.name)
        found = []
        gaps = int((~np.isfinite(y).all(axis=(1, 2))).sum())
        if gaps:
            found.append(Warning("missing-markers", f"{gaps} of {len(y)} frames have missing markers; the paper "
                                 "method uses only the equations whose markers are present"))
        state, measured, path = self._fold(y, progress)
        used = np.isfinite(measured)
        if used.sum() == 0:
            raise IdentifiabilityError(
                f"the per-frame solve found no solution inside the interval "
                f"[{self.model.parameters[0].prior.lower:g}, {self.model.parameters[0].prior.upper:g}] "
                f"in any of {len(y)} frames",
                "widen the parameter's prior bounds or check the model's marker positions",
            )
        n_dropped = int(len(y) - used.sum())
        if n_dropped > DROP_WARN_FRACTION * len(y):
            found.append(Warning("frames-dropped", f"paper method dropped {n_dropped} of {len(y)} frames "
                                 "(no converged solution inside the interval)"))
        self.state_ = state
        self.posterior_ = state.posterior
        self.map_path_ = path
        self.measured_ = measured
        self.frames_used_ = used
        self.sigma_ = self._sigma()
        self.warnings_ = emit(found)
        return self

    def result(self) -> FitResult:
        """The typed result (:class:`~skelid.result.FitResult`)."""
        check_fitted(self)
        used = self.frames_used_
        return build_result(self, self.posterior_, noise=NoiseEstimate(self.sigma_, fixed=True),
                            skipped={"no_solution": int((~used).sum())},
                            arrays={"measured": self.measured_, "map_path": self.map_path_})
