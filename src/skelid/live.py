"""Live geometry: refine the parameters frame by frame while the subject moves.

A :class:`Session` takes labelled frames from a stream (a VR or motion-capture
system), one at a time, and returns after each an immutable
:class:`LiveEstimate`: the parameters with intervals, the current pose, the
joint centres, every marker's residual and a health flag.

**Recursive Gaussian form** (any number of parameters). The state is the
square-root information ``R`` (upper triangular) and right-hand side ``d`` of
the Gauss-Newton summary ``||R z - d||^2`` of every frame so far, over
``z = (q_{t-2}, q_{t-1}, q_t, \\theta)``: the last three poses and the
geometry, every earlier pose marginalised. Frame ``t + 1`` with markers ``y``
is fitted at ``theta = m_t`` (the current mean) for its pose ``\\hat q``
(Levenberg-Marquardt from the constant-velocity prediction); with
``r = y - x(\\hat q, m_t)``, ``J = \\partial x / \\partial q`` and
``K = \\partial x / \\partial \\theta`` there, the rows

.. math::

    [J \\;\\; K] \\begin{pmatrix} q_{t+1} \\\\ \\theta \\end{pmatrix} = r + J \\hat q + K m_t, \\qquad
    \\sqrt{w_k}\\,(q_{t+1} - 3 q_t + 3 q_{t-1} - q_{t-2})_k = 0

are appended (the second only with a motion model, ``cutoff``: the batch
``marker`` method's third-difference penalty, ``w_k = \\overline{(J^\\top J)_{kk}} / \\mathrm{gain}(f_k)``),
one QR factorisation makes ``R`` triangular again, and the rows of the oldest
pose are dropped, which marginalises it. The posterior of ``theta`` is
Gaussian with precision ``R_{\\theta\\theta}^\\top R_{\\theta\\theta} / \\hat\\sigma^2 + \\Lambda_0``
(``\\Lambda_0`` the prior's precision: a uniform prior on ``[a, b]`` counts as
sd ``(b - a)/\\sqrt{12}`` and bounds the mean; ``\\hat\\sigma^2`` the running
residual variance ``RSS / (n_{obs} - Q n_{frames} - P)``, held at least at
:func:`noise_floor`, ``1e-5`` of the model's size, so that a noise-free
stream keeps the prior in the precision). With a motion
model the frame is linearised once more at its filtered pose (``n_iter``: more passes, each at the pose the
last one filtered, stop once it moves the markers by less than a tenth of their noise, and a pass that moves
it further than the one before is not taken: an iterated extended Kalman update. Four passes took the mean
bias of case A at 15 mm after 1000 frames from -0.85 to +0.08 sd, but left the rms z where it was and put
some tennis-arm sessions further off: ``benchmarks/experiments/live_long_iterated.md``; one pass stays the
default).
The cost per frame is one pose fit, one kinematics call per linearisation
and one small QR: it does not depend on a grid. With numba a frame is one
compiled call (:func:`skelid.estimators.online._live_kernel.step`: pose fit,
screen, update and mean), equal to the numpy path to rounding; a frame with a
marker to leave out, the first frame and the early re-linearisations take the
general path (its pose fit and linearisation compiled too). The numpy path
(``SKELID_NUMBA=0``, or while the kernels compile in the background) gives
the same estimates, slower. Early in a session (after
10, 25, 50, 100 and 200 frames) all frames so far are linearised again at
the current mean (:func:`relinearise`). For a linear model the last mean
equals the batch joint fit with the same motion model.

Without a motion model (``cutoff=None``) this is the joint least-squares fit
with every pose free: it keeps that fit's ``O(sigma^2)`` bias (on case A with
5 mm noise about 1.5 mm, 3 sd, after 300 frames; negligible at 1 mm). With
the motion model the early re-linearisations use the frames' smoothed poses
(:func:`smoothed_poses`), as the batch fit converges to, which removes most
of that bias; the noise level still comes from each frame's freely fitted pose
(the residual degrees of freedom count a free pose per frame: the smoothed
poses' misfit doubled sigma, and so the sd, on case A). After the last re-linearisation (200 frames) each frame is
linearised on arrival at its filtered pose, which is off by the noise; where a pose is poorly fixed (the
tennis arm's hand has one marker) that leaves an ``O(sigma^2)`` error of one sign, frame after frame. So
each block of :data:`_BLOCK` frames is folded in again at its poses smoothed with :data:`_LAG` frames on
either side (:meth:`Session._close_block`): its information about theta at those poses, one banded solve
(:func:`block_information`), replaces what the block's frames gave the state on arrival (the difference of
the state's information at the block's two ends, :func:`theta_marginal`), a term in theta alone
(:func:`add_theta_information`). The frame on hand is never folded again, and the work is done a step at a
time between frames (:meth:`Session.work`). The second-order bias of the batch fit with this motion
model, which that fit takes off, is summed block by block at the smoothed poses and taken off what a
session reports (:meth:`Session._unbiased`). What a session reports holds the frames folded in again only
(:meth:`Session._folded_state`): the filtered frames' own error is not that bias. Where smoothed poses misfit
the markers, the cutoff is raised before a block falls back on its free poses (:func:`fitting_smooth_steps`).

A fixed cutoff is wrong for fast movements: with ``cutoff=6.0`` and the
simulated arm motion played five times faster (up to 7.5 Hz) the live
estimate lands 5-30 sd from the truth while every frame looks healthy. The
default, ``cutoff='auto'``, chooses the cutoff from the frames as the batch
``marker`` method does (:func:`live_cutoff`: each pose coordinate's cutoff
by generalised cross-validation, doubled, at least 6 Hz; the highest of them
is used for every coordinate, since the movement to come may be another
joint's (:func:`_for_all`; where the batch method's per-coordinate cutoffs
differ from it the two estimates differ by up to about 2.5 batch sd on the
10-marker arm; a cutoff per coordinate can be given explicitly, and the live
estimate then equals the batch one before its bias correction): no motion model for
the first 50 frames, the cutoffs chosen at each early re-linearisation from 50
frames on, and again every 200 frames after them (from the poses as fitted on
arrival, by a banded solve: about a millisecond), so that they follow the
movement. A coordinate moving too fast for any cutoff below half the frame
rate is left free. Where the smoothed poses of the early frames fit the markers
worse than poses at the truth would (a ball joint passing through gimbal lock:
the free fits' outer Euler angles wander by tens of radians, and no smoother
started there finds the smooth path), those frames are linearised at their
free poses without the motion model, which starts afresh at the next frame
(:func:`relinearise`): linearised at the misfitting poses, theta landed 30-86
sd from the truth in 4-6 % of the simulated arm trials. ``benchmarks/live_agreement.py`` measures all three
settings against the batch estimate and the truth.

A frame with a marker left out as an outlier gives no data under the motion
model; its pose follows the prediction, for at most :data:`_BRIDGE` frames
in a row: after a longer gap (a dropout of the whole marker set) the held
poses are marginalised (:func:`drop_poses`) and the next pose is found
afresh, since a constant-velocity prediction run on through a gap pulls the
geometry (13.6 sd on a tennis-arm trial with a 0.4 s dropout, 0.5 sd with the
chain let go).

**Grid form** (1-3 parameters, or a posterior with several modes): the
online grid filter :class:`~skelid.estimators.online.grid.MarkerGridFilter`; the pose
is that of the most probable grid point.

**Health.** After the pose fit, a marker more than ``outlier_sd`` noise
standard deviations from the model (a swapped label, a ghost marker) is left
out and the frame refitted without it (in the grid form, at the most probable
grid point, the grid updated again without it); a frame with too few markers
to fix the pose leaves the estimate as it was (in the grid form also one whose
markers leave the pose unfixed at some grid point: its log determinant,
``-inf`` there, would leave every later posterior NaN). Under the motion model a frame whose
freely fitted pose jumps away from the prediction (:func:`pose_jump`; a
swapped label where the markers barely fix the pose, so that the pose fit
absorbs it and no marker stands out) is not used either; the check allows
for the movement actually seen (a robust variance of each coordinate's recent
third differences, :func:`pose_jump`), since the motion model's own allowance
shrinks with the noise, and it waits, as the marker screen does, until the
noise level rests on :data:`_KNOWN_DOF` degrees of freedom. Before a marker is
blamed, the frame's pose is fitted again from the last whole frame's pose: a
fit started from a prediction carried through a glitch can land in a wrong
basin, where a good marker looks like the outlier. Either way
``healthy`` turns False and ``health`` says why. When two or more markers are
left out, or the pose jumps, each pair among them and the worst residuals is
swapped back and the pose refitted: a pair with which every marker fits, the
frame's residual sum of squares drops to a quarter or less (two markers close
together fit about as well either way round) and the pose no longer jumps is
named (``labels A and B look swapped``).

The checks below apply to both forms (:mod:`skelid.live_health` states
their statistics). A frame that repeats the last one exactly (a frozen
stream), or whose markers all lie within 5 % of the model's size of one point
(a zeroed stream; no pose of a model puts the markers that fix it that close),
is not used: it would count the same information twice, or none. Before any
pose is fitted, each marker's position is compared with its own track (the
constant-velocity prediction from its last two positions, against a robust
scale of its recent innovations): two markers that both leave their tracks
(``chi^2_D``, ``p = 1e-6``) and each land on the other's are named as swapped
and the frame is not used, from the first swapped frame on and before the
noise level or a motion model exists, unless the model clearly fits the
labels as they came and not swapped back (the tracks may have followed a swap
that began where they could not see it). Each frame's scale is compared with
the model's (:class:`~skelid.live_health.ScaleCheck`: distances within rigid
segments, or the markers' spread against its range over the model's poses):
a scale more than 1.5 times off is reported with the stream unit it points
to (a spread that is the model's over 1000 names metres, not a zeroed
stream), the frame still used. A parameter whose estimate sits on its
prior's bound has status ``on-bound``; where the data put it more than
:data:`~skelid.live_health.BOUND_Z` sd beyond, the health says so.

Once the noise is known, a frame used whole has its residual sum of squares
checked against ``sigma^2`` on ``nD - Q`` degrees of freedom (``p = 1e-7``;
an ``F`` quantile against an estimated noise level), and the last 50 such
frames as a whole and marker by marker (:class:`~skelid.live_health.MisfitWindow`):
the window's residual variance beyond 4 times a stated ``sigma^2`` or that of
the frames before the window, or one marker's mean squared residual beyond
``4 D sigma^2`` (both at ``p = 1e-6``), is a misfit the noise does not
explain (a wrong model, wrong units, a marker placed elsewhere or loose, a
motion model too slow for the movement that has pulled theta off), reported,
not hidden behind ``"ok"``. An estimated noise level grows to cover a misfit
of every marker alike, so only a stated one can show that; an estimated noise
sd over 10 % of the model's size (:data:`_LOOSE`; a stream in the wrong unit)
is reported either way. A marker is named only where leaving the markers out
in turn tells it from the others (:func:`~skelid.live_health.alike_markers`);
a frame whose screen would leave too few markers to fix the pose blames none
(case A has one residual degree of freedom per frame: any marker left out
leaves the other two fitting).

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

import dataclasses
import itertools
import math
import numbers
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property, lru_cache, partial
from types import MappingProxyType
from typing import NamedTuple

import numpy as np
from scipy.linalg.lapack import dgeqrf as _dgeqrf
from scipy.linalg.lapack import dpbsv as _dpbsv
from scipy.stats import chi2, norm

from skelid._linalg import frame_gram, one_blas_thread
from skelid._stop import interruptible
from skelid.data import MAX_FIT_COORDINATE_MM, MarkerData, unit_scale
from skelid.errors import DataError, ModelError, SettingError, SkelidError
from skelid.estimators.checks.misfit import STILL_JOINT_DEG, joint_rotations
from skelid.estimators.fit import _lm_kernel
from skelid.estimators.fit.joint import _gain, smoothed_bias_sums, smoothing_penalty
from skelid.estimators.fit.pose import _kernel_tables, _model_size, _tilts_batch_last, fit_pose, initial_pose, workspace
from skelid.estimators.online import _live_kernel
from skelid.estimators.online._live_kernel import RELINEARISE_TOL
from skelid.estimators.online.grid import NOISE_FLOOR, MarkerGridFilter, noise_floor
from skelid.live_health import (
    BOUND_Z,
    EFFECT_MARKER,
    SCALE_EVERY,
    MarkerTracks,
    MisfitWindow,
    ScaleCheck,
    finish_steps,
    gaussian_bound_z,
    grid_bound_z,
    ratio_limit,
)
from skelid.model.description import Model
from skelid.model.kinematics import (
    Workspace,
    forward_kinematics,
    geometry,
    marker_jacobian,
    marker_positions,
    tilt_tables,
)
from skelid.result import ParameterEstimate

_Z95 = float(norm.ppf(0.975))
#: after this many frames, every frame so far is linearised again at the current mean
_RELINEARISE = (10, 25, 50, 100, 200)
#: the Gaussian form of a model with at most this many parameters has the grid filter beside it (early frames)
_SHADOW_PARAMS = 3
#: ... and relinearises at the grid's mean where its own lies more than this many of the grid's sds from it
_ASTRAY = 4.0
#: the stopping rule says done only once an estimated noise level rests on this many residual degrees of
#: freedom (its relative sd 1 / sqrt(2 dof) = 7 %): two frames once gave a noise sd of 0.4 mm for 5 mm, and "done"
DONE_NOISE_DOF = 100
#: ... and, in the Gaussian form, keeps at most this many frames to check "done" with (about 5 MB for 30 markers)
_DONE_KEEP = 20000
#: ... and where the batch fit of those frames puts a parameter more than this many of its sds away, the basin
#: whose frames fit better is taken
_BATCH_SD = 2.0
#: the early frames' basin is checked by a batch fit where it costs at most this (:func:`_basin_affordable`)
_BASIN_COST = 1e7
#: after the early frames, the frames are folded in again at their smoothed poses this many at a time
#: (:meth:`Session._close_block`) ...
_BLOCK = 100
#: ... each smoothed with this many frames before it and after it
_LAG = 50
#: ... and the bias they carry is solved again with the information of every frame at most this many frames apart
_BIAS_EVERY = 10
#: ... and is found a piece of frames at a time (one step of :meth:`Session.work` each), its cost
#: (frames x (parameters + pose coordinates)^2) at most this: case A's blocks in one piece, the 10-marker arm's in 4
_BIAS_COST = 7200
#: the motion model carries the pose through at most this many frames without data in a row; after a longer
#: gap the held poses are marginalised and the next frame's pose is found afresh
_BRIDGE = 5
#: residual degrees of freedom after which the running noise estimate is trusted for the marker screen and the
#: pose-jump check (before that a chi-square estimate on a few degrees of freedom can be several times too small)
_KNOWN_DOF = 30
#: the pose-jump check's allowance for real movement follows this many recent frames (see Session._allowance)
_JUMP_WINDOW = 25
#: median of chi-square with one degree of freedom: a robust variance is median(nu^2) / this
_CHI2_1_MEDIAN = 0.454936423119572
#: a noise sd beyond this fraction of the model's size (its largest length) is no marker noise but a misfit: the
#: seed paper's hardest case, 15 mm on a 300 mm forearm, is 5 %; a stream in the wrong unit gives far more
_LOOSE = 0.10
#: a swapped pair is named only when, swapped back, the frame's residual sum of squares is at most this fraction
#: of its own (a 6 sd outlier alone is 36 noise variances per coordinate: a swap leaves about one)
_DECISIVE = 0.25
#: the allowance is recomputed every this many frames checked (every frame for the first ones)
_ALLOW_EVERY = 5
#: markers within this fraction of the model's size of one point coincide: a zeroed or stuck stream. Any set of
#: markers that can fix a pose spans at least 0.126 of the model's size (the pendulum; 0.17-0.76 for the other
#: example models) through the poses simulate(hard_poses=True) visits; case A's chain folds to fit three markers
#: within a few millimetres of one point, which then passed for data (L2 "identified", health "ok")
_COINCIDE = 0.05
#: tail probability of one frame's residual sum of squares beyond which the frame misfits as a whole: per frame
#: a test at 1e-4 fired on 1-3 of 10-20 clean simulated sessions of 300 frames (the pose fit's tail is
#: a little heavier than chi-square's); a lasting misfit too small for this is the window's (skelid.live_health)
_FRAME_P = 1e-7

__all__ = ["LiveEstimate", "Session", "NOISE_FLOOR", "noise_floor", "GaussianState",
           "absorb", "drop_poses", "solve_mean", "theta_cov",
           "prior_moments", "Advice", "SCHEMA", "message", "run"]

#: the ``schema`` field of every message :func:`message` makes (docs/live-protocol.md)
SCHEMA = "skelid.live/1"


# --------------------------------------------------------------------------- the recursive Gaussian
#: poses held in the state besides theta: the third-difference motion model links four consecutive poses
_HELD = 3
#: coefficients of the third difference q_t - 3 q_{t-1} + 3 q_{t-2} - q_{t-3}, oldest first
_D3 = np.array([-1.0, 3.0, -3.0, 1.0])


class GaussianState(NamedTuple):
    """State of the recursive Gaussian filter (immutable; an update returns a new one).

    The state is the square-root (Gauss-Newton) summary of the objective
    ``RSS + motion penalty`` over ``z = (q_{t-k+1}, ..., q_t, theta)``, the last
    ``k <= 3`` poses and the geometry, every earlier pose marginalised:
    ``||root z - rhs||^2`` up to a constant, ``root`` upper triangular (residual
    units; the prior and the noise level enter only when the mean is solved,
    :func:`solve_mean`).
    """

    root: np.ndarray  # (n, n) upper-triangular square-root information of z, n = k Q + P
    rhs: np.ndarray  # (n,)
    mean: np.ndarray  # (P,) posterior mean of theta, inside the prior bounds
    poses: np.ndarray  # (k, Q) the held frames' poses where they were linearised, oldest first
    pose_mean: np.ndarray | None  # (Q,) filtered mean of the newest pose
    hdiag: np.ndarray  # (Q,) sum over frames of diag(J_q^T J_q) (scale of the motion model)
    rss: float  # running residual sum of squares (each frame's pose fitted freely)
    n_obs: int  # marker coordinates used
    n_used: int  # frames used


def empty_state(model: Model, prior) -> GaussianState:
    """The state before any frame: the prior's mean, no information."""
    P, Q = model.n_params, model.n_pose
    return GaussianState(np.zeros((P, P)), np.zeros(P), prior[0].copy(), np.zeros((0, Q)), None,
                         np.zeros(Q), 0.0, 0, 0)


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


def _sigma2(rss: float, n_obs: int, n_used: int, model: Model, sigma: float | None, fallback: float,
            floor: float = 0.0) -> float:
    """Noise variance: ``sigma^2`` if given, else ``RSS / dof`` (``fallback`` while ``dof < 3``), at least ``floor``."""
    if sigma is not None:
        return max(float(sigma) ** 2, floor)
    dof = n_obs - model.n_pose * n_used - model.n_params
    if dof >= 3:
        return max(rss / dof, floor)
    return fallback


def motion_scale(cutoff, rate: float):
    """``1 / gain``: the motion model's weight per unit of pose information (0: no motion model).

    The batch ``marker`` method's third-difference penalty
    (:func:`~skelid.estimators.fit.joint.smoothing_penalty`) with one cutoff (Hz), or one per pose
    coordinate (an array in, an array out; a coordinate at or above half the rate gets 0).
    """
    if cutoff is None:
        return 0.0
    c = np.asarray(cutoff, dtype=float)
    w = np.where((c > 0) & (c < rate / 2.0), 1.0 / _gain(np.clip(c, 1e-12, None), rate), 0.0)
    return float(w) if w.ndim == 0 else w


def absorb(state: GaussianState, r, J_pose, J_theta, q, theta_lin, weight: float, n_coord: int,
           rss_frame: float) -> GaussianState:
    """One frame's linearised residual and the motion model folded into ``state``.

    Parameters
    ----------
    r : (N,) float or None
        Residual ``y - x(theta_lin, q)`` of the frame's present coordinates (None: no data,
        the pose follows the motion model alone).
    J_pose : (N, Q) float
    J_theta : (N, P) float
    q : (Q,) float
        Pose where the frame is linearised.
    theta_lin : (P,) float
        Geometry where the frame is linearised.
    weight : float or (Q,) float
        :func:`motion_scale`: the penalty on the third difference of pose
        coordinate ``k`` is ``weight_k * mean_t (J_q^T J_q)_kk``.

    Returns
    -------
    GaussianState
        The new pose appended, the oldest beyond three marginalised; the mean is
        not solved (:func:`solve_mean`).

    Notes
    -----
    A frame adds the rows ``[J, K] (q, theta) = r + J q_lin + K theta_lin`` and,
    once four poses are held, ``sqrt(w_k) (q_t - 3 q_{t-1} + 3 q_{t-2} - q_{t-3})_k = 0``
    to the square-root information; one QR factorisation triangularises it
    again, and the rows of the oldest pose (its columns come first) are dropped:
    that marginalises it. For a linear model this is exactly the batch fit's
    objective, so the last mean equals the batch estimate.
    """
    P, Q = state.mean.size, q.size
    k = state.poses.shape[0]
    n0 = state.rhs.size
    n = n0 + Q
    kq = k * Q
    n_rows = n0 + (0 if r is None else r.size) + (Q if k == _HELD else 0)
    A = np.zeros((max(n_rows, n + 1), n + 1))
    A[:n0, :kq] = state.root[:, :kq]
    A[:n0, n - P:n] = state.root[:, kq:]
    A[:n0, n] = state.rhs
    row = n0
    hdiag = state.hdiag
    n_used = state.n_used
    if r is not None:
        N = r.size
        A[row:row + N, kq:kq + Q] = J_pose
        A[row:row + N, n - P:n] = J_theta
        A[row:row + N, n] = r + J_theta @ theta_lin + J_pose @ q
        row += N
        hdiag = hdiag + np.einsum("ij,ij->j", J_pose, J_pose)
        n_used += 1
    if k == _HELD:
        if np.any(np.asarray(weight) > 0.0) and n_used > 0:
            sw = np.sqrt(weight * hdiag / n_used)
            for j in range(_HELD + 1):
                A[row:row + Q, j * Q:(j + 1) * Q] = np.diag(_D3[j] * sw)
    R = _dgeqrf(A, overwrite_a=True)[0]  # R in the upper triangle (LAPACK, without numpy's wrapper costs)
    poses = np.concatenate([state.poses, q[None]])
    s = Q if k == _HELD else 0  # eliminate the oldest pose: its rows go
    root = np.triu(R[s:n, s:n])
    rhs = R[s:n, n].copy()
    if k == _HELD:
        poses = poses[1:]
    return GaussianState(root, rhs, state.mean, poses, state.pose_mean, hdiag, state.rss + rss_frame,
                         state.n_obs + n_coord, n_used)


def drop_poses(state: GaussianState) -> GaussianState:
    """``state`` with every held pose marginalised (the motion model's chain broken; theta's information kept).

    The square root is ordered poses first, so the trailing ``(P, P)`` block of
    ``root`` and of ``rhs`` is the information of theta with the poses
    marginalised.
    """
    kq = state.poses.size
    return state._replace(root=state.root[kq:, kq:].copy(), rhs=state.rhs[kq:].copy(), poses=state.poses[:0])


def pose_jump(state: GaussianState, q, J_pose, weight: float, sigma2: float, allow=None) -> float:
    """How far a frame's pose lies from the motion model's prediction: ``nu^T V^{-1} nu``.

    ``nu = q - (3 q_t - 3 q_{t-1} + q_{t-2})`` is the innovation of the freely
    fitted pose against the held poses' third-difference prediction; its
    covariance is taken generously as ``21 sigma^2 (J^T J)^{-1}`` (the free fit's
    error, and the three held poses' as if they were no better) plus the motion
    model's own ``sigma^2 / w_k`` (``w_k = weight * mean (J^T J)_kk``), or the
    allowance ``allow_k`` for the movement actually seen where that is larger
    (the motion model's term shrinks with the noise: on near-noise-free data a
    movement faster than the cutoff expects would look like a jump on every
    frame). Beyond a
    chi-square quantile with ``Q`` degrees of freedom the pose has jumped (a
    swapped label the marker screen cannot see, where the markers barely fix the
    pose, or a wrong start of the pose fit). When the three held poses come from
    data, or the frames before were left out for such a jump (a swap lasts
    several frames), the session leaves the frame out; when some held poses were
    predicted through frames without usable data (less certain than this
    covariance says) it lets the prediction go instead and starts a new chain at
    this frame.

    Parameters
    ----------
    state : GaussianState
        Holding three poses.
    q : (Q,) float
        The frame's pose fitted on its own (angles continuous with the held poses).
    J_pose : (N, Q) float
        ``dx/dq`` of the frame's present coordinates at ``q``.
    allow : (Q,) float, optional
        Variance of the third difference of each pose coordinate that the recent movement shows
        (:meth:`Session._allowance`; none by default).
    """
    p = state.poses
    Q = q.size
    JtJ = J_pose.T @ J_pose
    JtJ = JtJ + np.eye(Q) * (1e-9 * max(np.trace(JtJ) / Q, 1e-300))
    hbar = np.maximum(state.hdiag / max(state.n_used, 1), 1e-300)
    model_var = sigma2 / np.maximum(weight * hbar, 1e-300)
    V = 21.0 * sigma2 * np.linalg.inv(JtJ) + np.diag(model_var if allow is None else np.maximum(model_var, allow))
    nu = q - (3.0 * p[2] - 3.0 * p[1] + p[0])
    return float(nu @ np.linalg.solve(V, nu))


def _theta_information(state: GaussianState, prior, sigma2: float):
    """Precision ``(P, P)`` and information vector ``(P,)`` of theta, poses marginalised, prior included."""
    mu0, L0 = prior[0], prior[1]
    P = mu0.size
    Rt = state.root[-P:, -P:]
    return Rt.T @ Rt / sigma2 + L0, Rt.T @ state.rhs[-P:] / sigma2 + L0 @ mu0


def solve_mean(state: GaussianState, prior, sigma2: float, pose: bool = True) -> GaussianState:
    """The state with its mean solved: theta (clipped to the prior bounds) and, with ``pose``, the newest pose."""
    lo, hi = prior[2], prior[3]
    Lam, eta = _theta_information(state, prior, sigma2)
    theta = np.clip(np.linalg.solve(Lam, eta), lo, hi)
    q = None
    k, Q = state.poses.shape
    if k and pose:
        P = theta.size
        a = (k - 1) * Q
        Rq = state.root[a:a + Q, a:a + Q].copy()
        Rq.flat[::Q + 1] += 1e-12 * max(np.abs(np.diag(Rq)).max(), 1e-300)
        q = np.linalg.solve(Rq, state.rhs[a:a + Q] - state.root[a:a + Q, -P:] @ theta)
    return state._replace(mean=theta, pose_mean=q)


def theta_cov(state: GaussianState, prior, sigma2: float) -> np.ndarray:
    """Covariance ``(P, P)`` of theta, every held pose marginalised."""
    return np.linalg.inv(_theta_information(state, prior, sigma2)[0])


def smoothed_poses(model: Model, theta, y, q, used, rate: float, cutoff: float, ws: Workspace | None = None,
                   n_iter: int = 10, tol: float = 1e-6) -> np.ndarray:
    """Poses ``(T, Q)`` of frames ``y (T, M, D)`` smoothed by the batch method's motion model at fixed ``theta``
    (:func:`smoothing_steps`, run to the end)."""
    return finish_steps(smoothing_steps(model, theta, y, q, used, rate, cutoff, ws, n_iter, tol))


def smoothing_steps(model: Model, theta, y, q, used, rate: float, cutoff: float, ws: Workspace | None = None,
                    n_iter: int = 10, tol: float = 1e-6):
    """The steps of :func:`smoothed_poses`.

    Minimises ``S(q) = sum_t ||y_t - x(theta, q_t)||^2 + q^T R q`` over the poses
    only, ``R`` the third-difference penalty of
    :func:`~skelid.estimators.fit.joint.smoothing_penalty`, from the per-frame fits
    ``q`` (angles unwrapped, as the batch method starts); frames not ``used`` follow the motion model
    alone. Each Gauss-Newton
    step (one sparse solve) is halved until ``S`` decreases, and the iteration
    stops when ``S`` changes by less than ``tol`` of itself (at most ``n_iter``
    steps). The per-frame fits can wander far along a direction the markers
    barely fix (a ball joint near gimbal lock: two Euler angles moving in
    opposite directions by tens of radians while the segment hardly moves); a
    full step from there overshoots on the curved Euler-angle surface and lands
    on poses that fit neither the markers nor the motion model.

    A generator: it yields after each Gauss-Newton step (a live session spreads them over frames) and
    returns the poses.
    """
    from skelid.estimators.fit.joint import _banded_solver, _continuous_poses, penalty_band

    T, Q = q.shape
    m = np.isfinite(y).all(axis=-1) & np.asarray(used, bool)[:, None]
    y0 = np.where(m[..., None], y, 0.0)
    q = _continuous_poses(model, q, used)

    def objective(x, qv):
        return float(np.sum(((y0 - x) * m[..., None]) ** 2) + qv.ravel() @ (R @ qv.ravel()))

    x, Jq, _ = marker_jacobian(model, theta, q, ws)
    J = (Jq * m[..., None, None]).reshape(T, -1, Q)
    Hqq = frame_gram(J)
    R = smoothing_penalty(model, Hqq, rate, cutoff)
    R_band = penalty_band(R, Q)
    S = objective(x, q)
    yield
    for _ in range(n_iter):
        r = ((y0 - x) * m[..., None]).reshape(T, -1)
        # blockdiag(Hqq) + R is banded (the motion model links four frames): a banded Cholesky
        dq = _banded_solver(Hqq, R, R_band)(np.einsum("tni,tn->ti", J, r).ravel() - R @ q.ravel()).reshape(T, Q)
        for _ in range(30):  # step halving: S must not increase
            q_new = q + dq
            x_new = marker_positions(model, theta, q_new, ws)
            S_new = objective(x_new, q_new)
            if S_new <= S:
                break
            dq = 0.5 * dq
        else:
            break
        done = S - S_new <= tol * S
        q, S = q_new, S_new
        if done:
            break
        x, Jq, _ = marker_jacobian(model, theta, q, ws)
        J = (Jq * m[..., None, None]).reshape(T, -1, Q)
        Hqq = frame_gram(J)
        yield
    return q


def gcv_cutoffs(model: Model, q, used, rate: float) -> np.ndarray:
    """Each pose coordinate's cutoff (Hz) by generalised cross-validation, doubled: ``(Q,)`` float.

    The batch method's choice (:func:`~skelid.estimators.fit.joint.choose_cutoffs`, equal to rounding), with
    the Whittaker smoother ``(I + lambda D_3^T D_3) z_hat = z`` solved as the banded symmetric system it is
    (LAPACK's ``dpbsv``) instead of a general sparse factorisation: on 200 frames the
    twelve candidates cost well under a millisecond, so a live session can choose again without a pause.
    """
    from skelid.estimators.fit.joint import CUTOFF_CANDIDATES, UNDERSMOOTH, _continuous_poses

    z = _continuous_poses(model, q, used)
    T, Q = z.shape
    if T < 8:
        return np.full(Q, rate / 2.0)
    band = _d3_band(T)
    resp = (2.0 - 2.0 * np.cos(2.0 * np.pi * np.arange(T) / T)) ** 3
    best = np.full(Q, np.nan)
    score = np.full(Q, np.inf)
    for fc in CUTOFF_CANDIDATES:
        if fc >= rate / 2.0:
            break
        lam = 1.0 / _gain(fc, rate)
        ab = lam * band
        ab[-1] += 1.0
        zh, info = _dpbsv(ab, z, lower=0, overwrite_ab=1)[1:]
        if info:
            continue  # not positive definite: cannot happen for lam >= 0, but never trust a failed solve
        trace = float(np.sum(1.0 / (1.0 + lam * resp)))
        g = T * np.sum((z - zh) ** 2, axis=0) / max(T - trace, 1.0) ** 2
        better = g < score
        score[better], best[better] = g[better], fc
    return np.where(np.isfinite(best), np.minimum(UNDERSMOOTH * best, rate / 2.0), rate / 2.0)


@lru_cache(maxsize=8)
def _d3_band(T: int) -> np.ndarray:
    """``D_3^T D_3`` (``T x T``, third differences) in upper banded storage ``(4, T)`` (read-only)."""
    D3 = np.zeros((T - 3, T))
    for j, c in enumerate(_D3):
        D3[np.arange(T - 3), np.arange(T - 3) + j] = c
    full = D3.T @ D3
    ab = np.zeros((4, T))
    for k in range(4):
        ab[3 - k, k:] = np.diagonal(full, k)
    ab.flags.writeable = False
    return ab


def live_cutoff(model: Model, frames, theta, rate: float, ws: Workspace | None = None,
                refit: bool = True) -> np.ndarray:
    """The motion model's cutoff (Hz) for ``cutoff='auto'``, chosen from the frames as the batch method does.

    Each frame's pose is fitted on its own at ``theta`` (``refit``; otherwise the frames'
    poses as fitted when they came are used); each coordinate's cutoff is
    chosen by generalised cross-validation and doubled
    (:func:`gcv_cutoffs`), at least the batch method's
    ``MIN_AUTO_CUTOFF``: ``(Q,)`` float, one cutoff per pose coordinate as the batch method has.
    """
    from skelid.estimators.marker import MIN_AUTO_CUTOFF

    q = np.stack([f[1] for f in frames])
    used = np.array([f[2] for f in frames])
    if refit and used.any():
        Y = np.stack([f[0] for f in frames])
        q[used], _ = fit_pose(model, theta, Y[used], q[used], n_iter=10, ws=ws)
    return np.maximum(gcv_cutoffs(model, q, used, rate), min(MIN_AUTO_CUTOFF, rate / 2.0))


def _smooth_fits(model: Model, theta, y, q, rss_free: float, sigma2: float, ws: Workspace | None = None,
                 p_value: float = 1e-4) -> bool:
    """Whether smoothed poses ``q (T, Q)`` fit the markers ``y (T, M, D)`` as poses near the truth would.

    At the true poses the residual sum of squares exceeds the free fits'
    ``rss_free`` by about ``sigma^2 chi^2_{TQ}`` (the free fits absorb ``Q``
    noise dimensions per frame); smoothing can only cost less. Beyond the
    ``p_value`` quantile of that the smoother has not converged to a
    smooth path through the data (per-frame fits that wander along a
    direction the markers barely fix, a ball joint near gimbal lock) and
    linearising there would pull theta far off.
    """
    T, Q = q.shape
    rss = float(np.nansum((y - marker_positions(model, theta, q, ws)) ** 2))
    return rss - rss_free <= sigma2 * float(chi2.isf(p_value, T * Q))


#: where the smoothed poses misfit (:func:`_smooth_fits`), the cutoff is doubled at most this many times, up to a
#: quarter of the rate (:func:`fitting_smooth_steps`)
_CUTOFF_DOUBLINGS = 2


def fitting_smooth_steps(model: Model, theta, y, q, used, rate: float, cutoff, rss_free: float, sigma2: float,
                         ws: Workspace | None = None, check: bool = True):
    """The steps of :func:`smoothing_steps` at ``cutoff``, and, with ``check``, where the smoothed poses misfit
    the markers (:func:`_smooth_fits`), at the cutoff doubled (at most :data:`_CUTOFF_DOUBLINGS` times, up to a
    quarter of the rate): ``(poses, the cutoff they were smoothed at)``, or ``(None, None)`` where none fits.

    The check's reference, the markers at the true poses, holds for a cutoff above the movement; one below it
    cannot follow the poses and misfits too. The per-frame poses that stand in then, without the motion model,
    bias theta most where the markers barely fix a pose (case A at 15 mm: 200 frames 20 mm off, 9 sd, at
    6-8 Hz, where 16 Hz fitted and gave the batch fit's estimate)."""
    c = cutoff
    for k in range(_CUTOFF_DOUBLINGS + 1 if check else 1):
        if k:
            higher = np.maximum(np.minimum(2.0 * np.asarray(c, float), rate / 4.0), np.asarray(c, float))
            if np.array_equal(higher, np.asarray(c, float)):
                break
            c = higher
        qs = yield from smoothing_steps(model, theta, y, q, used, rate, c, ws)
        if not check or _smooth_fits(model, theta, y[used], qs[used], rss_free, sigma2, ws):
            return qs, c
    return None, None


def relinearise(model: Model, frames, prior, sigma: float | None, weight, theta, fallback: float,
                n_iter: int = 2, ws: Workspace | None = None, smoother: tuple | None = None,
                floor: float = 0.0, check: bool = False, split: int | None = None):
    """The state recomputed from ``frames`` (every frame so far) linearised at ``theta``.

    The recursive update linearises each frame at the mean of its time; the
    first frames see a mean far from the final one. Early in a session
    (:data:`_RELINEARISE` frames) every frame so far is fitted again at the
    current mean (the poses in one batched call) and folded in again
    (``n_iter`` times, the mean solved after each pass), as the batch fit would.

    Parameters
    ----------
    frames : list of ((M, D) float, (Q,) float, bool)
        Each frame (NaN where missing or left out), its last pose and whether it was used.
    theta : (P,) float
        Where to linearise first.
    fallback : float
        Noise variance while the residuals cannot say.
    smoother : (rate, cutoff), optional
        The motion model: the frames are then linearised at their smoothed poses
        (:func:`smoothed_poses`).
    floor : float
        The least noise variance (:func:`noise_floor`).
    check : bool
        Whether the smoothed poses must fit the markers (:func:`_smooth_fits`): for a cutoff chosen from
        the movement, which fits it to the noise level, a misfit means the smoother started from per-frame
        poses it could not follow (a ball joint near gimbal lock, its two outer Euler angles wandering by
        tens of radians in opposite directions); the frames are then linearised at their free poses
        without the motion model, and its chain starts afresh at the next frame. A fixed cutoff may be
        slower than the movement, and its smoothed poses misfit as the batch fit's do: not checked.
    split : int, optional
        Also return the state after the frames before ``frames[split]``, its mean solved:
        ``(state after all, state at split)``.

    Returns
    -------
    GaussianState, or (GaussianState, GaussianState) with ``split``
    """
    Y = np.stack([f[0] for f in frames])
    Q0 = np.stack([f[1] for f in frames])
    used = np.array([f[2] for f in frames])
    present = np.isfinite(Y).all(axis=-1)
    B = len(frames)
    state = None
    motion = bool(np.any(np.asarray(weight) > 0))
    for _ in range(n_iter):
        q = Q0.copy()
        rss_free = np.zeros(B)  # each frame's residual at its freely fitted pose: the noise estimate's RSS
        if used.any():
            q[used], rss_free[used] = fit_pose(model, theta, Y[used], Q0[used], n_iter=10, ws=ws)
        chain = motion  # the early frames linked by the motion model
        w = np.asarray(weight, float)
        if smoother is not None and used.sum() >= 8:
            # linearise at the smoothed poses, as the batch fit with this motion model converges to: the
            # per-frame or filtered poses are off by the noise, which biases theta where a pose is poorly fixed
            n_obs = int(present[used].sum()) * model.dim
            s2 = _sigma2(float(rss_free.sum()), n_obs, int(used.sum()), model, sigma, fallback, floor)
            qs, c = finish_steps(fitting_smooth_steps(model, theta, Y, q, used, smoother[0], smoother[1],
                                                      float(rss_free.sum()), s2, ws, check))
            if qs is not None:
                q = qs
                if c is not smoother[1]:  # a higher cutoff than the session's: the chain's weight follows it
                    w = np.broadcast_to(np.asarray(motion_scale(c, smoother[0]), float), w.shape)
            else:
                chain = False
        w = w if chain else np.zeros_like(w)
        state, snap = _folded(model, empty_state(model, prior), Y, q, used, rss_free, theta, w, chain, split, ws)
        state = _solved(model, state, prior, sigma, fallback, floor, chain, motion, q, used)
        theta, Q0 = state.mean, q
    for k, (y, _, u) in enumerate(frames):
        frames[k] = (y, Q0[k], u)
    if split is None:
        return state
    return state, _solved(model, snap, prior, sigma, fallback, floor, chain, motion, q[:split], used[:split])


def _folded(model: Model, state: GaussianState, Y, q, used, rss_free, theta, w, chain: bool,
            split: int | None, ws: Workspace | None) -> tuple[GaussianState, GaussianState]:
    """Frames ``Y (B, M, D)`` folded into ``state``, each linearised at ``(theta, q[b])``
    (:func:`absorb`): ``(state after all, state before frame split)``.

    A frame not ``used`` lets the pose go on by the motion model alone (``chain``), for at most
    :data:`_BRIDGE` frames in a row; after a longer gap the held poses are marginalised.
    """
    B = len(Y)
    P, D = model.n_params, model.dim
    present = np.isfinite(Y).all(axis=-1)
    x, Jq, Jt = marker_jacobian(model, theta, q, ws)
    snap = state
    gap = 0
    for b in range(B):
        if b == split:
            snap = state
        if not used[b]:
            gap += 1
            if chain and state.poses.shape[0]:  # the pose goes on by the motion model alone
                state = (drop_poses(state) if gap > _BRIDGE else
                         absorb(state, None, None, None, q[b], theta, w, 0, 0.0))
            continue
        gap = 0
        m = present[b]
        r = (Y[b, m] - x[b, m]).reshape(-1)
        state = absorb(state, r, Jq[b, m].reshape(r.size, -1), Jt[b, m].reshape(r.size, P), q[b], theta,
                       w, int(m.sum()) * D, float(rss_free[b]))
    return state, (state if split is None or split >= B else snap)


def _solved(model: Model, state: GaussianState, prior, sigma, fallback: float, floor: float, chain: bool,
            motion: bool, q, used) -> GaussianState:
    """``state`` after :func:`relinearise`'s frames ``q``, ``used``: its mean solved (the newest pose too where
    the motion model's chain holds; else the last used frame's pose, the chain to start afresh)."""
    s2 = _sigma2(state.rss, state.n_obs, state.n_used, model, sigma, fallback, floor)
    state = solve_mean(state, prior, s2, pose=chain)
    if not chain:
        if motion:  # the motion model starts afresh at the next frame
            state = drop_poses(state)
        state = state._replace(pose_mean=q[np.flatnonzero(used)[-1]] if used.any() else None)
    return state


def theta_marginal(state: GaussianState) -> tuple[np.ndarray, np.ndarray]:
    """The information ``(Lambda (P, P), eta (P,))`` about theta that ``state`` holds, its poses marginalised
    (residual units, without the prior): the objective is ``theta^T Lambda theta - 2 eta^T theta`` + const.

    The square root is ordered poses first, so its trailing block is theta's marginal.
    """
    P = state.mean.size
    Rt = state.root[-P:, -P:]
    return Rt.T @ Rt, Rt.T @ state.rhs[-P:]


def add_theta_information(state: GaussianState, Lam, eta) -> GaussianState | None:
    """``state`` with ``theta^T Lam theta - 2 eta^T theta`` added to its objective (``Lam`` may be indefinite: a
    difference of two summaries of the same frames); None where the sum is not positive definite.

    A term in theta alone changes only the trailing ``(P, P)`` block of the square root and of its right-hand
    side: with ``root = [[R_qq, R_qt], [0, R_tt]]``, ``R_tt' = chol(R_tt^T R_tt + Lam)`` and
    ``rhs_t' = R_tt'^{-T} (R_tt^T rhs_t + eta)``. The mean is not solved (:func:`solve_mean`).
    """
    from scipy.linalg import solve_triangular

    P = state.mean.size
    Rt = state.root[-P:, -P:]
    A = Rt.T @ Rt + Lam
    try:
        U = np.linalg.cholesky(0.5 * (A + A.T)).T
    except np.linalg.LinAlgError:
        return None
    root, rhs = state.root.copy(), state.rhs.copy()
    rhs[-P:] = solve_triangular(U, Rt.T @ state.rhs[-P:] + eta, trans="T", check_finite=False)
    root[-P:, -P:] = U
    return state._replace(root=root, rhs=rhs)


def block_information(model: Model, theta, y, q, used, R=None, ws: Workspace | None = None):
    """The information about theta of frames ``y (T, M, D)`` linearised at ``(theta, q (T, Q))``, every pose
    marginalised: ``(Lambda (P, P), eta (P,))`` in :func:`theta_marginal`'s form.

    The frames' rows ``J_t q_t + K_t theta = r_t + J_t q_t0 + K_t theta_0`` (as :func:`absorb` makes them;
    frames not ``used`` and missing markers give none) and the motion penalty ``q^T R q`` (``R``:
    :func:`~skelid.estimators.fit.joint.smoothing_penalty` over these frames, or None) make a quadratic in
    ``(q, theta)`` whose pose block is banded; with ``A = blockdiag(J^T J) + R``,
    ``Lambda = sum K^T K - H^T A^{-1} H`` and ``eta = sum K^T c - H^T A^{-1} J^T c`` (``H`` the stacked
    ``J_t^T K_t``, ``c`` the right-hand sides): one banded Cholesky for every frame at once, where
    :func:`absorb` takes one QR per frame. Where a pose is fixed by nothing (a frame without data and no
    penalty, too few markers), a ridge of 1e-10 of each coordinate's mean information keeps it definite
    (:func:`absorb` leaves such a pose's theta information out exactly).
    """
    import scipy.sparse as sp
    from scipy.linalg import cho_solve_banded, cholesky_banded

    from skelid._linalg import summed_gram, summed_product
    from skelid.estimators.fit.joint import _banded_system

    P, Q = model.n_params, model.n_pose
    T = len(q)
    m = np.isfinite(y).all(axis=-1) & np.asarray(used, bool)[:, None]  # (T, M)
    x, Jq, Jt = marker_jacobian(model, theta, q, ws)
    Jq = (Jq * m[..., None, None]).reshape(T, -1, Q)
    Jt = (Jt * m[..., None, None]).reshape(T, -1, P)
    r = np.where(m[..., None], y - x, 0.0).reshape(T, -1)
    c = r + np.einsum("tkq,tq->tk", Jq, q) + Jt @ theta
    H = frame_gram(Jq, Jt).reshape(T * Q, P)
    bq = np.einsum("tkq,tk->tq", Jq, c).reshape(T * Q)
    Hqq = frame_gram(Jq)
    R = sp.csc_matrix((T * Q, T * Q)) if R is None else R
    for ridge in (0.0, 1e-10):  # exact unless a pose is fixed by nothing (a frame without data, no penalty)
        try:
            U = cholesky_banded(_banded_system(Hqq, R, ridge), lower=False, check_finite=False)
            break
        except np.linalg.LinAlgError:
            continue
    X = cho_solve_banded((U, False), np.concatenate([H, bq[:, None]], axis=1), check_finite=False)
    Lam = summed_gram(Jt) - H.T @ X[:, :P]
    eta = summed_product(Jt, c) - H.T @ X[:, P]
    return 0.5 * (Lam + Lam.T), eta


# --------------------------------------------------------------------------- what a push returns
@dataclass(frozen=True, eq=False)
class LiveEstimate:
    """Everything known after one frame (immutable; arrays are read-only).

    The fields a loop reads every frame (``theta``, ``pose``, ``healthy``) are
    stored; ``cov``, ``parameters``, ``joint_centres`` and ``marker_residuals``
    are computed on first access, so a push costs nothing for what is not read.

    Attributes
    ----------
    frame : int
        Frames pushed so far.
    time : float
        ``frame / rate`` (s).
    theta : (P,) float
        Posterior mean of the parameters (model units).
    pose : (Q,) float or None
        Current pose (None until a frame fixes it).
    sigma : float
        Noise level used (model units).
    healthy : bool
        False if this frame could not be used fully (markers missing, markers
        left out as outliers, labels swapped, too few markers to fix the pose,
        a frozen or zeroed stream, a frame refused) or its residuals, or those
        of the recent frames, exceed what the noise explains (module notes).
    health : str
        ``"ok"`` or what went wrong.
    rejected : tuple of str
        Markers left out of this frame as outliers.
    cov : (P, P) float
        Posterior covariance of ``theta``.
    parameters : mapping of str to ParameterEstimate
        Mean, sd and 95 % interval of each parameter (model units); status ``'prior'`` where the data
        have added little, ``'on-bound'`` where the estimate sits on its prior's bound (the Gaussian
        form's mean held there, the grid form's marginal posterior largest at its edge),
        ``'placement'`` while no joint has moved more than
        :data:`~skelid.estimators.checks.misfit.STILL_JOINT_DEG` over the frames used (the estimate then
        rests on where the model places the markers, not on motion, as a batch fit of a static
        trial says: :meth:`Session._still_now`), else ``'identified'``.
    joint_centres : mapping of str to (D,) float
        World position of each segment's joint (model units); empty without a pose.
    marker_residuals : mapping of str to float
        Distance of each model marker from the fitted model in this frame (NaN if missing or left out).
    done : bool or None
        With the session's ``target_sd``: True when this frame is healthy, every requested parameter
        is ``'identified'`` with its sd at or below its target, and a noise level estimated from the
        residuals rests on at least :data:`DONE_NOISE_DOF` degrees of freedom (the stopping rule);
        None without targets.
    """

    frame: int
    time: float
    theta: np.ndarray
    pose: np.ndarray | None
    sigma: float
    healthy: bool
    health: str
    rejected: tuple[str, ...] = ()
    _model: Model | None = field(default=None, repr=False)
    _cov: Callable[[], np.ndarray] | None = field(default=None, repr=False)
    _residuals: np.ndarray | Callable[[], np.ndarray] | None = field(default=None, repr=False)
    _ranges: tuple | None = field(default=None, repr=False)  # (lower, upper, prior sd) of each parameter
    _on_bound: np.ndarray | None = field(default=None, repr=False)  # (P,) bool: the estimate sits on a bound
    _still: Callable[[], bool] | None = field(default=None, repr=False)  # no joint had moved by then (Session)
    _targets: np.ndarray | None = field(default=None, repr=False)  # (P,) target sd (inf: not requested)
    _noise_dof: float = math.inf  # residual degrees of freedom of an estimated noise level (inf: stated)
    _done_held: bool | None = None  # what the session's last check of done said, held until the next (None: none)

    @cached_property
    def cov(self) -> np.ndarray:
        return _frozen(self._cov())

    @cached_property
    def parameters(self) -> Mapping[str, ParameterEstimate]:
        model, mean = self._model, self.theta
        sd = np.sqrt(np.clip(np.diag(self.cov), 0.0, None))
        lo, hi, prior_sd = self._ranges
        params = {}
        on = np.zeros(mean.size, dtype=bool) if self._on_bound is None else self._on_bound
        still = None
        for k, p in enumerate(model.parameters):
            unit = _unit(model, p)
            status = "prior" if sd[k] > 0.9 * prior_sd[k] else "on-bound" if on[k] else "identified"
            if status == "identified" and still is None:
                still = bool(self._still is not None and self._still())
            status = "placement" if status == "identified" and still else status
            params[p.name] = ParameterEstimate(p.name, unit, float(mean[k]), float(mean[k]), float(sd[k]),
                                               (float(max(mean[k] - _Z95 * sd[k], lo[k])),
                                                float(min(mean[k] + _Z95 * sd[k], hi[k]))), status=status)
        return MappingProxyType(params)

    @cached_property
    def done(self) -> bool | None:
        if self._targets is None:
            return None
        if not self.healthy or self._noise_dof < DONE_NOISE_DOF:
            return False
        if self._done_held is not None:
            return self._done_held
        params = list(self.parameters.values())
        return all(p.status == "identified" and p.sd <= t for p, t in zip(params, self._targets, strict=True)
                   if np.isfinite(t))

    @cached_property
    def joint_centres(self) -> Mapping[str, np.ndarray]:
        model = self._model
        if self.pose is None:
            return MappingProxyType({})
        centres = forward_kinematics(model, self.theta, self.pose).p_world_seg
        return MappingProxyType({s.joint.name: _frozen(centres[i]) for i, s in enumerate(model.segments)})

    @cached_property
    def marker_residuals(self) -> Mapping[str, float]:
        names = self._model.marker_names
        r = self._residuals() if callable(self._residuals) else self._residuals
        r = np.full(len(names), np.nan) if r is None else r
        return MappingProxyType(dict(zip(names, r.tolist(), strict=True)))


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
    dof: int  # pose coordinate moved (-1: "done", the stopping rule's last advice)
    lower_deg: float  # the sweep, in degrees (or model units for a translation)
    upper_deg: float
    parameter: str  # the worst-determined parameter it is judged for
    sd_now: float
    sd_after: float  # expected sd of that parameter after the movement


def _batch_theta(model: Model, frames, rate: float, sigma: float | None):
    """The batch ``marker`` fit of the frames used (its estimate, covariance and the used frames' poses), or
    None where it fails.

    The check of the stopping rule: the recursive form follows the basin of its first linearisations, the
    batch fit starts from its own search of the prior (a 3-D arm once said done 44 batch sd from it, with
    every frame fitting)."""
    import warnings

    from skelid.estimators.marker import MarkerEstimator

    used = [f[0] for f in frames if f[2]]
    if len(used) < 2:
        return None
    data = MarkerData(np.stack(used), model.marker_names, rate, model.units)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit = MarkerEstimator(model, sigma=sigma, rng=np.random.default_rng(0)).fit(data)
    except SkelidError:
        return None
    pose = np.asarray(fit.pose_, float)
    if pose.shape != (len(used), model.n_pose):
        return None
    # its estimate before the bias is taken off, as the session's state holds it (the session takes the same
    # second-order bias off what it reports)
    return np.asarray(fit.theta_profile_, float), np.asarray(fit.cov_, float), pose


def _basin_fit(model: Model, frames, rate: float, theta=None):
    """The batch ``marker`` fit's joint estimate of the frames used, without its posterior (its start, screening
    and motion-model stages: a fraction of the whole fit's time), as :func:`_batch_theta` gives it: the estimate,
    its Gauss-Newton covariance and the used frames' poses; None where it fails.

    With ``theta`` (the session's estimate; ``frames`` hold its poses), the same joint fit also settles from
    there, and the lower of the two minima of the penalised cost is the answer: the session's estimate is not
    itself a minimum of the early frames' cost, and a batch minimum that only fits better than it can be the
    wrong one (a tennis arm's slow routine: 16-30 % lower residuals than the session's estimate, 42 sd off the
    truth).

    The check of the early frames' basin (:meth:`Session._relinearise`): only which minimum, not the interval."""
    import warnings

    from skelid.estimators.base import move_root
    from skelid.estimators.fit.joint import joint_fit
    from skelid.estimators.marker import FIT_STEP_TOL, MarkerEstimator, joint_stages, penalised_cost

    y = np.stack([f[0] for f in frames if f[2]]) if any(f[2] for f in frames) else None
    if y is None or len(y) < 2:
        return None
    est = MarkerEstimator(model, rng=np.random.default_rng(0))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ws = workspace(model)
            origin, st, sc, mo = joint_stages(est, y, rate, np.random.default_rng(0), ws)
            fit = mo.fit
            if theta is not None:
                q = move_root(model, np.stack([f[1] for f in frames if f[2]]), -origin)
                start = np.clip(theta, *st.bounds) if st.bounds is not None else theta
                own = joint_fit(model, sc.y, start, q, n_iter=est.n_iter, bounds=st.bounds, frames=sc.fixed,
                                penalty=fit.penalty, step_tol=FIT_STEP_TOL, ws=ws)
                fit = min((own, fit), key=penalised_cost)
            cov = np.linalg.inv(fit.info) * fit.rss / max(fit.n_obs - fit.pose_dof - model.n_params, 1.0)
    except (SkelidError, np.linalg.LinAlgError):
        return None
    if not (np.isfinite(fit.theta).all() and np.isfinite(cov).all()):
        return None
    return fit.theta, cov, move_root(model, fit.pose, origin)


def _basin_affordable(model: Model, T: int) -> bool:
    """Whether :func:`_basin_fit` of ``T`` frames costs at most about a second (:data:`_BASIN_COST`): frames x pose
    coordinates x (pose coordinates + parameters)^2 (about 0.1-0.2 s for the 3-D arms, 0.5 s for gait2354's
    body scales, 15 s with its 93 marker offsets as well: that session goes without the check)."""
    Q, P = model.n_pose, model.n_params
    return T * Q * (Q + P) ** 2 <= _BASIN_COST


def _done_advice(model: Model, est: LiveEstimate, targets: np.ndarray) -> Advice:
    """The stopping rule's last advice: every requested parameter is at its target (named with its sd)."""
    asked = [(p, t) for p, t in zip(est.parameters.values(), targets, strict=True) if np.isfinite(t)]
    last, _ = max(asked, key=lambda pt: pt[0].sd / pt[1])  # the nearest its target: the last to reach it
    unit = lambda p: "" if p.unit == "1" else f" {p.unit}"  # noqa: E731
    reached = ", ".join(f"{p.name} sd {p.sd:.3g} <= {t:.3g}{unit(p)}" for p, t in asked[:4])
    more = f" and {len(asked) - 4} more" if len(asked) > 4 else ""
    return Advice(f"done: every requested parameter has reached its target sd ({reached}{more})", "", -1,
                  math.nan, math.nan, last.name, last.sd, last.sd)


# --------------------------------------------------------------------------- the session
def _number(name: str, value, fix: str, error=SettingError) -> float:
    """``value`` as a finite float, or one line naming the setting (a string, None or NaN is refused)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise error(f"{name} must be a number, got {value!r}", fix)
    v = float(value)
    if not math.isfinite(v):
        raise error(f"{name} must be finite, got {value!r}", fix)
    return v


def target_sds(model: Model, target_sd) -> np.ndarray | None:
    """The stopping rule's target sd of each parameter ``(P,)`` (inf: not requested), or None."""
    if target_sd is None:
        return None
    fix = "give target_sd as a positive number (every parameter) or a mapping of parameter names to numbers"
    names = model.parameter_names
    if not names:
        raise SettingError(f"target_sd: model {model.name!r} has no parameters to reach a target",
                           "leave target_sd out")
    if isinstance(target_sd, Mapping):
        if not target_sd:
            raise SettingError("target_sd names no parameter", fix)
        unknown = [str(n) for n in target_sd if n not in names]
        if unknown:
            raise SettingError(f"target_sd names {', '.join(map(repr, unknown))}, which {model.name!r} does not "
                               "have", f"use one of: {', '.join(names)}")
        wanted = {str(n): v for n, v in target_sd.items()}
    else:
        wanted = dict.fromkeys(names, target_sd)
    out = np.full(len(names), np.inf)
    for n, v in wanted.items():
        v = _number(f"target_sd of {n}", v, fix)
        if v <= 0:
            raise SettingError(f"target_sd of {n} must be above 0, got {v!r}", fix)
        out[names.index(n)] = v
    return out


def _check_session_settings(model: Model, method: str, rate, sigma, outlier_sd=6.0, n_iter=1) -> None:
    """Refuse a live method, rate, noise level or screen setting a :class:`Session` cannot run with.

    Raises
    ------
    ModelError
        An unknown method, or ``'grid'`` for more than 3 parameters.
    DataError
        A rate that is not a positive finite number; a negative or non-finite ``sigma``.
    SettingError
        An ``outlier_sd`` that is not a positive number, an ``n_iter`` that is not a count.
    """
    if method not in ("auto", "gaussian", "grid"):
        raise ModelError(f"unknown live method {method!r}", "use 'auto', 'gaussian' or 'grid'")
    if method == "grid" and model.n_params > 3:
        raise ModelError(f"the grid form handles 1 to 3 parameters; {model.name!r} has {model.n_params}",
                         "use method='gaussian'")
    fix_rate = "pass the stream's frames per second as a number, e.g. rate=100.0"
    if not _number("rate", rate, fix_rate, DataError) > 0:
        raise DataError(f"rate must be positive, got {rate!r}", fix_rate)
    if sigma is not None:
        fix = "pass the marker noise in model units, or leave it out to estimate it"
        if not _number("sigma", sigma, fix, DataError) >= 0:
            raise DataError(f"sigma must be a finite noise level >= 0, got {sigma!r}", fix)
    fix = "give the residual, in noise sd, beyond which a marker is left out (default 6)"
    if not _number("outlier_sd", outlier_sd, fix) > 0:
        raise SettingError(f"outlier_sd must be positive, got {outlier_sd!r}", fix)
    if isinstance(n_iter, bool) or not isinstance(n_iter, numbers.Integral) or n_iter < 0:
        raise SettingError(f"n_iter must be a whole number >= 0, got {n_iter!r}",
                           "give how often each frame is linearised again (default 1)")


def _check_cutoff(model: Model, cutoff) -> bool:
    """Whether ``cutoff`` asks for the automatic choice (``'auto'``); refuse one a session cannot use.

    Raises
    ------
    ModelError
        A string other than ``'auto'``, or an array of cutoffs that is not one per pose coordinate.
    """
    auto = isinstance(cutoff, str)
    if auto and cutoff != "auto":
        raise ModelError(f"unknown cutoff {cutoff!r}", "give a cutoff in Hz, 'auto' or None")
    if auto or cutoff is None:
        return auto
    fix = "give one cutoff in Hz, one per pose coordinate, 'auto' or None"
    try:
        c = np.asarray(cutoff)
    except (TypeError, ValueError):
        c = np.asarray(None, dtype=object)
    if isinstance(cutoff, bool) or c.dtype.kind not in "iuf":  # True/False, text, bytes, mappings, objects
        raise SettingError(f"cutoff must be a number of Hz, not {type(cutoff).__name__} {cutoff!r:.40}", fix)
    if c.ndim and c.shape != (model.n_pose,):
        raise ModelError(f"cutoff has {c.size} values; the model has {model.n_pose} pose coordinates", fix)
    if not np.all(np.isfinite(c)):
        raise SettingError(f"cutoff must be finite, got {cutoff!r:.40}", fix)
    return auto


def _live_method(model: Model, method: str) -> str:
    """The form a session runs: ``'auto'`` is the Gaussian form (with the grid beside it over the early
    frames for 1-3 parameters); the grid form alone only when asked for."""
    return "gaussian" if method == "auto" else method


class _Screened(NamedTuple):
    """A frame's pose after the markers that do not fit were left out (:meth:`Session._screened_pose`)."""

    y: np.ndarray  # (M, D) the frame, NaN for the markers left out
    q: np.ndarray  # (Q,) its pose
    x: np.ndarray  # (M, D) the model's markers at that pose
    Jq: np.ndarray  # (M, D, Q) their pose Jacobian
    Jt: np.ndarray  # (M, D, P) their parameter Jacobian
    resid: np.ndarray  # (M,) residual distances before the last marker was left out
    present: np.ndarray  # (M,) bool: markers used
    n_present: int
    rejected: list  # names of the markers left out
    too_few: bool  # too few markers remain to fix the pose


def _frame_rows(sc: _Screened, n_markers: int):
    """The frame's residual ``r (m,)`` and Jacobian rows ``(m, Q)``, ``(m, P)`` of the markers used."""
    if sc.n_present == n_markers:
        r = (sc.y - sc.x).reshape(-1)
        return r, sc.Jq.reshape(r.size, -1), sc.Jt.reshape(r.size, -1)
    r = (sc.y[sc.present] - sc.x[sc.present]).reshape(-1)
    return r, sc.Jq[sc.present].reshape(r.size, -1), sc.Jt[sc.present].reshape(r.size, -1)


@dataclass(eq=False)
class _Refold:
    """A block of a session's frames to fold in again (:meth:`Session._close_block`): the state's information
    about theta at its first and last frame (:meth:`Session._raw`), whether its correction still applies, and
    its work's steps (:meth:`Session._refold_steps`)."""

    start: tuple
    end: tuple
    correct: bool = True
    steps: object = None


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
        Either way the Gaussian form holds it at least at :func:`noise_floor`
        (``1e-5`` of the model's size), so a noise-free stream works. Stated, it is
        also what the recent residuals are checked against (module notes): the
        health then shows a misfit of every marker alike, which an estimated
        noise level would grow to cover.
    outlier_sd : float
        Residual, in noise standard deviations, beyond which a marker is left out of a frame.
    cutoff : float, (Q,) float, 'auto' or None
        Cutoff (Hz) of the Gaussian form's motion model, the batch ``marker``
        method's third-difference smoother (one for every pose coordinate, or
        one per coordinate). ``'auto'`` (default): chosen from
        the frames as the batch method chooses it and re-chosen as the movement
        changes (:func:`live_cutoff`). None: every pose free, as in the plain
        joint fit, which keeps that fit's ``O(sigma^2)`` bias. A fixed cutoff
        biases the estimate when the movement is fast for it. See the module
        notes.
    n_iter : int
        Gaussian form: at most this many times each frame is linearised again at its filtered pose
        (iterated extended Kalman update), until that pose moves the frame's markers by less than
        :data:`RELINEARISE_TOL` (0.1) of their noise; a pass that moves it further than the one before
        is not taken (the passes diverge). 0 is faster and less accurate; more than 1 takes the early bias
        of a poorly fixed pose off but leaves the interval as short (see the module notes).
    rng : numpy.random.Generator, optional
        For the random starts of the first pose.
    target_sd : float or mapping of str to float, optional
        The stopping rule: the sd (each parameter's own unit) each requested parameter should reach.
        A number asks it of every parameter; a mapping of parameter names asks it of those. Each
        estimate then says whether it is ``done`` (:attr:`LiveEstimate.done`), :meth:`advice`
        aims at the requested parameter farthest from its target and says "done" when all are there.
        In the Gaussian form the estimate that would be done is first made again from every frame so
        far, each linearised at its smoothed pose, and checked against the batch fit of the same
        frames (the session keeps the frames for it; a pause of one to a few seconds per thousand
        frames of a 3-D arm, once, and again once the frames have grown by half).

    Raises
    ------
    DataError
        Labels that match none of the model's markers, an unknown unit, a
        ``rate`` that is not a positive finite number, or a ``sigma`` that is
        not a finite number >= 0.
    ModelError
        ``method='grid'`` for more than 3 parameters.
    SettingError
        An ``outlier_sd`` that is not a positive finite number, an ``n_iter`` that is not a count,
        a ``target_sd`` that is not a positive number or names a parameter the model does not have.
    """

    def __init__(self, model: Model, labels=None, units: str | None = None, rate: float = 100.0,
                 method: str = "auto", sigma: float | None = None, outlier_sd: float = 6.0,
                 cutoff: float | str | None = "auto", n_iter: int = 1, rng: np.random.Generator | None = None,
                 target_sd: float | Mapping[str, float] | None = None):
        _check_session_settings(model, method, rate, sigma, outlier_sd, n_iter)
        self._targets = target_sds(model, target_sd)
        self.target_sd = target_sd
        # the Gaussian form with a stopping rule keeps every frame, to check the estimate that would be done
        self._kept: list | None = [] if self._targets is not None and _live_method(model, method) == "gaussian" \
            else None
        self._verified_until = 0
        self._held_done = False  # the last check of done said done (held until _verified_until)
        self.model = model
        self.rate = float(rate)
        self.method = _live_method(model, method)
        self.sigma = sigma
        self.outlier_sd = float(outlier_sd)
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.scale = unit_scale(units or model.units, model.units)
        self._index = self._name_index(labels)
        self._order = self._array_order(labels)
        self._identity = self._order is not None and np.array_equal(self._order, np.arange(len(model.markers)))
        self._prior = prior_moments(model)
        self._ws = workspace(model)  # the session's tables; its pose fits keep one path throughout
        self._pose_fit = _FramePose(model, self._ws)
        self._linearise = _Linearise(model, self._ws)
        self._frame = 0
        self._early: list = []  # the first frames, (y, pose, used), for re-linearisation
        self._gap = 0  # frames in a row whose data were not used
        self._run = 0  # frames in a row whose data were used (see pose_jump)
        self._jumped = False  # the last frame not used was left out for its pose's jump
        self._jump_limit = float(chi2.isf(1e-4, model.n_pose))  # a pose's jump beyond the motion model
        self._nu2 = np.zeros((_JUMP_WINDOW, model.n_pose))  # recent squared pose innovations (see _allowance)
        self._n_nu = 0
        self._allow, self._allow_at = np.zeros(model.n_pose), 0  # the allowance and self._n_nu when computed
        self._good: np.ndarray | None = None  # pose of the last frame whose markers all fitted
        self._last_y: np.ndarray | None = None  # the last frame (model order and units), to see a frozen stream
        self._n_repeat = 0  # frames in a row that repeat the one before exactly
        self.estimate: LiveEstimate | None = None
        self.cutoff = cutoff
        self._auto = _check_cutoff(model, cutoff)
        self._cutoff_now = None if self._auto else cutoff  # the motion model's cutoff in force (Hz)
        self._recent: deque = deque()  # frames since the cutoff was last chosen (after the early frames)
        # after the early frames, under a motion model, each _BLOCK frames are folded in again at their smoothed
        # poses, a step at a time between frames (:meth:`_close_block`, :meth:`work`): the frames kept for it
        # (the _LAG before the open block, then the block's), the frames in the open block, and the information
        # about theta the state had at its start, without the corrections applied since (:meth:`_raw`)
        self._blocks = False
        self._block: list = []
        self._n_new = 0
        self._raw_open: tuple | None = None
        self._applied = (np.zeros((model.n_params, model.n_params)), np.zeros(model.n_params))
        self._closed: _Refold | None = None  # the block closed, waiting for the _LAG frames after it
        self._pending: _Refold | None = None  # the block being folded in again
        self._folded: GaussianState | None = None  # the state the estimate is read from (:meth:`_folded_state`)
        # the second-order bias of the frames folded in at their smoothed poses (:meth:`_bias_sum_of`): sum S b at
        # unit noise (S a block's information, b its bias)
        self._bias_sum: np.ndarray | None = None
        self._bias, self._bias_at = np.zeros(model.n_params), 0  # the bias per unit noise variance, and when
        self.n_iter = int(n_iter)
        self._set_weight(self._cutoff_now)
        self._rot = np.array([d.kind == "R" for d in model.dofs])
        _, L0, lo, hi = self._prior
        self._ranges = (lo, hi, 1.0 / np.sqrt(np.diag(L0)))
        self._M, self._D = len(model.markers), model.dim
        self._min_present = model.n_pose // model.dim + 1  # markers that fix a pose: n * D > Q
        if self.method == "grid" or model.n_params <= _SHADOW_PARAMS:
            self._grid = MarkerGridFilter(model, sigma=sigma, history_steps=(), rng=self.rng)
            self._grid_shape = tuple(a.size for a in self._grid._points()[0])
        self._state = self._grid.init_state() if self.method == "grid" else empty_state(model, self._prior)
        # the Gaussian form of a model with few parameters runs the grid filter beside it over the early frames,
        # and relinearises where the grid puts the posterior when its own mean has gone astray (:meth:`_relinearise`)
        self._shadow = self._grid.init_state() if self.method == "gaussian" and model.n_params <= _SHADOW_PARAMS \
            else None
        self._sigma_fallback = (0.01 * _model_size(model)) ** 2  # before the residuals say: 1 % of the model's size
        self._sigma_floor = noise_floor(model)
        self._size = _model_size(model)
        self._marker_cap = self._D * ratio_limit(_FRAME_P, self._D)  # one marker's r^2 / sigma^2 at 1 - _FRAME_P
        self._coincide = max(_COINCIDE * self._size, math.sqrt(self._sigma_floor))
        self._max_coordinate = MAX_FIT_COORDINATE_MM / unit_scale(model.units, "mm")
        # the joints' motion so far (_still_now): each joint rotation coordinate (the root's left out), and
        # for each the frame where it was lowest and highest on arrival (their values, frames and poses)
        self._joint_rot = joint_rotations(model)
        self._extreme_at = np.array([[np.inf], [-np.inf]]) * np.ones(self._joint_rot.size)  # (2, K) lowest, highest
        self._extreme = [[(None, None), (None, None)] for _ in self._joint_rot]  # their (frame, pose)
        self._extreme_version, self._still_memo, self._moved = 0, (-1, True), False
        self._tracks = MarkerTracks(self._M, self._D, self._sigma_floor)  # each marker's path: swapped labels
        self._claim = None  # the evidence on the tracks' present claim of a swap (see _labels_fit)
        self._window = MisfitWindow(self._M, self._D, model.n_pose, self._sigma_floor)  # a lasting misfit
        self._declared = units or model.units
        self._scale_check = ScaleCheck(model, self._declared)  # each frame's scale: a stream in the wrong unit
        self._scale_line: str | None = None  # what the scale check found in the frame (None: nothing)
        compiled = self._linearise.tables is not None and self._pose_fit.tables is not None
        self._step = _Step(self) if compiled else None

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
        labels = [str(n) for n in labels]
        bare = [n.rsplit(":", 1)[-1] for n in labels]
        unique = {b for b in bare if bare.count(b) == 1}
        # a subject prefix ("Derrick:RSHO") is tolerated where the bare name is unique, as MarkerData.select does
        order = np.array([self._index.get(n, self._index.get(b, -1) if b in unique else -1)
                          for n, b in zip(labels, bare, strict=True)], dtype=int)
        for i in np.unique(order[order >= 0]):  # two rows for one marker: the later would overwrite the earlier
            rows = np.flatnonzero(order == i)
            if rows.size > 1:
                raise DataError(f"labels name marker {self.model.marker_names[i]!r} {rows.size} times (rows "
                                f"{', '.join(str(r + 1) for r in rows)}: {', '.join(repr(labels[r]) for r in rows)})",
                                "give each array row its own marker's name, once")
        if not (order >= 0).any():
            raise DataError(f"none of the labels matches a marker of {self.model.name!r}",
                            f"name the stream's markers as the model does: {', '.join(self.model.marker_names)}")
        return order

    def _frame_array(self, frame) -> np.ndarray:
        """The frame as ``(M, D)`` in model order and units, NaN where missing (or not finite).

        Raises
        ------
        DataError
            A frame that is neither a mapping of marker name to coordinates nor an array of one row per
            label, coordinates that are not numbers, a mapping that names no marker of the model.
        """
        if isinstance(frame, Mapping):
            y = self._mapping_frame(frame)
        else:
            y, final = self._array_frame(frame)
            if final:  # rows in model order: scaled and cleaned there
                return y
        y = y * self.scale
        y[~np.isfinite(y)] = np.nan
        return y

    def _mapping_frame(self, frame: Mapping) -> np.ndarray:
        """A mapping of marker name to coordinates as ``(M, D)`` in model order (NaN where not given)."""
        model = self.model
        M, D = len(model.markers), model.dim
        y = np.full((M, D), np.nan)
        seen = set()
        for name, xyz in frame.items():
            name = str(name)
            i = self._index.get(name)
            if i is None:  # a subject prefix ("Derrick:RSHO"), as MarkerData.select tolerates
                i = self._index.get(name.rsplit(":", 1)[-1])
            if i is None:
                continue
            if i in seen:
                raise DataError(f"the frame gives marker {model.marker_names[i]!r} twice (as {name!r} too)",
                                "send each marker once, or map the stream's names with labels=...")
            seen.add(i)
            v = _coordinates(xyz, f"marker {name!r}").ravel()
            if not D <= v.size <= 3:
                raise DataError(f"marker {name!r} has {v.size} coordinates, the model needs {D}",
                                "send x, y (and z) for every marker")
            y[i] = v[:D]
        if frame and not seen:
            shown = ", ".join(repr(str(n)) for n in list(frame)[:3]) + (", ..." if len(frame) > 3 else "")
            raise DataError(f"the frame names no marker of {model.name!r} ({shown})",
                            f"name the markers as the model does: {', '.join(model.marker_names)}, "
                            "or map the stream's names with labels={stream: model}")
        return y

    def _array_frame(self, frame) -> tuple[np.ndarray, bool]:
        """An array frame (one row per label) as ``(M, D)`` in model order, and whether it is final.

        Rows already in model order come back scaled, non-finite values NaN (final); others in model
        order only.
        """
        model = self.model
        M, D = len(model.markers), model.dim
        if isinstance(frame, str | bytes):
            raise DataError(f"a frame must be marker positions, got the text {frame[:20]!r}",
                            "send a mapping of marker name to (x, y, z) or an array with one row per label")
        a = _coordinates(frame, "an array frame")
        order = self._order
        n_rows = M if order is None else order.size
        if a.ndim != 2 or a.shape[0] != n_rows or not D <= a.shape[1] <= 3:
            how = ("one row per declared label" if order is not None
                   else f"one row per model marker ({M}), or pass labels=... naming the rows")
            raise DataError(f"an array frame must be ({n_rows}, {D}) or ({n_rows}, 3); got {a.shape}",
                            f"send {how}")
        if self._identity:
            y = a[:, :D] * self.scale if a.shape[1] != D else a * self.scale
            y = y if y is not a else y.copy()
            y[~np.isfinite(y)] = np.nan
            return y, True
        order = np.arange(M) if order is None else order
        y = np.full((M, D), np.nan)
        keep = order >= 0
        y[order[keep]] = a[keep, :D]
        return y, False

    # ------------------------------------------------------------------ the update
    @interruptible
    def push(self, frame, defer: bool = False) -> LiveEstimate:
        """Fold one frame in and return the estimate after it.

        Parameters
        ----------
        frame : mapping of str to (3,) or (D,) float, or (N, 3) array
            Marker positions by name, or as rows in the order of ``labels``. Missing
            markers: absent from the mapping, or NaN (or infinite).
        defer : bool
            Leave the step of pending work each push does after its frame (:meth:`work`) to the caller,
            to call once the estimate is on its way: the frame's latency is then the push alone. The
            estimates are the same either way, as long as :meth:`work` is called before the next push (work
            left undone is done all at once when the next block's work starts).

        Raises
        ------
        DataError
            A frame of the wrong shape or not of real numbers (text, complex numbers, true/false values;
            :meth:`_frame_array`); the session is left as it was. A frame that is well formed but cannot be
            used (it repeats the last one, its markers all coincide, labels swapped, too few markers) is not
            an error: ``healthy`` is False and ``health`` says why.
        """
        y = self._frame_array(frame)
        self._frame += 1
        problem = self._input_problem(y)
        if problem is not None:
            self._tracks.reset()
            self.estimate = self._unused(y, problem)
        elif pairs := self._swaps(y):
            self.estimate = self._swapped(y, pairs)
        elif self.method == "grid":
            self.estimate = self._push_grid(y)
        else:
            self.estimate = self._push_gaussian(y)
            if self._kept is not None and self.estimate.done is not None:
                self.estimate = self._checked_done(self.estimate)
        if not defer:
            self.work()
        return self.estimate

    @interruptible
    def work(self) -> bool:
        """One step of the session's pending work; False when there was none.

        Under the motion model, every :data:`_BLOCK` frames after the early ones a block of frames is
        folded in again at its smoothed poses (:meth:`_close_block`). That takes several milliseconds, so
        it is done a step at a time (a step: the block's pose fits, one step of their smoothing, its
        information about theta, or its second-order bias for a piece of its frames), one step after each frame:
        :meth:`push` does it after the frame's estimate, or, with ``defer``, the caller does once the
        estimate is sent (:meth:`feed` and :func:`run` do), in the time until the next frame comes.
        A step of the health window's refresh of which marker misfits (:meth:`MisfitWindow.advance
        <skelid.live_health.MisfitWindow.advance>`) is taken the same way.
        """
        refreshed = self._window.advance()  # the health window's refresh, a step at a time
        p = self._pending
        if p is None:
            return refreshed
        try:
            with one_blas_thread():
                next(p.steps)
        except StopIteration as stop:
            self._pending = None
            self._apply(p, *stop.value)
        return True

    def _checked_done(self, est: LiveEstimate) -> LiveEstimate:
        """The stopping rule under the motion model: the first estimate that would be done, and the first
        after the frames have grown by half since, is made again from every frame so far linearised at its
        smoothed pose (:func:`relinearise`). Each frame is otherwise linearised once, at its pose filtered
        from the frames before it, and kept there: where a joint rests while another moves, the remainder
        biases the estimate by many sd over a few hundred frames (the 3-D arm's wrist centre: 6-7 sd at
        "done", about 1 after this). The batch fit of the same frames (:func:`_batch_theta`) checks the
        basin. Done holds from then on until the frames have grown by half again; a check that does not say
        done holds that until they have grown by an eighth."""
        if self._frame <= self._verified_until:
            # between checks done is what the last one said: the estimate's information grows a block at a
            # time, and the noise level it is scaled by moves frame by frame
            return est if est.done == self._held_done else dataclasses.replace(est, _done_held=self._held_done)
        if not (est.done or (est.healthy and self._done_with_every_frame())):
            return est
        frames = self._early + self._kept
        if len(frames) > _DONE_KEEP:  # past the frames kept: done is not checked again
            return est
        # the frames of the open block are the last ones: the information about theta before them starts it
        # again (:meth:`_close_block`)
        split = len(frames) - self._n_new % _BLOCK if self._blocks else None
        with one_blas_thread():
            here = self._relinearised(list(frames), self._state.mean, split=split)  # a copy: the other basin
            here = self._basin(frames, here, _batch_theta(self.model, frames, self.rate, self.sigma), split)[0]
        if split is None:
            self._state = here
        else:
            self._state, at = here
            self._raw_open = theta_marginal(at)
            self._applied = tuple(np.zeros_like(a) for a in self._applied)
            for p in (self._closed, self._pending):  # their frames are now folded in at their smoothed poses
                if p is not None:
                    p.correct = False
        self._bias_at = -_BIAS_EVERY  # the bias solved again with the new state's information
        self._folded = self._state  # every frame at its smoothed pose: the estimate holds them all
        new = self._gaussian_estimate(None, [], ())
        self._held_done = bool(new.done)
        # done holds until the frames have grown by half; not done is checked again once they have grown by an
        # eighth (at least _LAG frames)
        self._verified_until = self._frame + (self._frame // 2 if self._held_done else max(_LAG, self._frame // 8))
        problems = list(dict.fromkeys(h for h in (est.health, new.health) if h != "ok"))
        return dataclasses.replace(new, healthy=not problems, health="; ".join(problems) or "ok",
                                   rejected=est.rejected)

    def _done_with_every_frame(self) -> bool:
        """Whether the estimate of every frame held, the frames still at their filtered poses included (which
        the estimate leaves out: :meth:`_folded_state`), would say done: the check of :meth:`_checked_done`
        then folds them in at their smoothed poses, and done comes when the frames say so, not a block later."""
        return bool(self._estimate_from(self._state).done)

    def _estimate_from(self, folded: GaussianState, bias_sum=None) -> LiveEstimate:
        """The estimate read from ``folded`` (and with ``bias_sum``, its bias solved again from that sum), the
        session's own state for the estimate left as it was."""
        saved = (self._folded, self._bias_sum, self._bias, self._bias_at)
        try:
            self._folded = folded
            if bias_sum is not None:
                self._bias_sum, self._bias_at = bias_sum, -_BIAS_EVERY
            return self._gaussian_estimate(None, [], ())
        finally:
            self._folded, self._bias_sum, self._bias, self._bias_at = saved

    def _basin(self, frames, here, batch, split=None):
        """``here`` (:meth:`_relinearised` of ``frames``), or, where the batch fit ``batch`` (estimate, covariance,
        used frames' poses: :func:`_batch_theta`, :func:`_basin_fit`) puts a parameter more than
        :data:`_BATCH_SD` of its sds away, the frames relinearised from its basin (its poses too), whichever's
        frames fit better, each at its own pose: ``(state, the frames with its poses)``. The recent residuals
        the health weighs (:class:`~skelid.live_health.MisfitWindow`) are forgotten with the basin left."""
        if batch is None:
            return here, frames
        sd = np.sqrt(np.clip(np.diag(batch[1]), 0.0, None))
        if not np.any(np.abs(_live_part(here).mean - batch[0]) > _BATCH_SD * np.maximum(sd, 1e-300)):
            return here, frames
        poses = iter(batch[2])
        other = [(y, next(poses) if u else q, u) for y, q, u in frames]
        there = self._relinearised(other, batch[0], split=split)
        if _live_part(there).rss >= _live_part(here).rss:
            return here, frames
        self._window = MisfitWindow(self._M, self._D, self.model.n_pose, self._sigma_floor)  # the other basin's
        return there, other

    def _relinearised(self, frames, theta, **how):
        """:func:`relinearise` of ``frames`` (their poses written back) at ``theta`` with the session's settings
        (``how``: its other arguments)."""
        return relinearise(self.model, frames, self._prior, self.sigma, self._weight, theta,
                           self._sigma_fallback, ws=self._ws,
                           smoother=(self.rate, self._cutoff_now) if self._motion else None,
                           floor=self._sigma_floor, check=self._auto, **how)

    def feed(self, frames, max_frames: int | None = None):
        """Push each frame of ``frames`` (any iterable) in turn, yielding the estimate after each.

        A frame the session refuses (:meth:`push` raises :class:`~skelid.errors.DataError`) does not end the
        stream: its estimate is the last one with ``healthy`` False and the problem in ``health``, and the
        session keeps what it had.

        Parameters
        ----------
        frames : iterable
            Frames as :meth:`push` takes them.
        max_frames : int, optional
            Stop after this many frames.

        Yields
        ------
        LiveEstimate
        """
        for frame in itertools.islice(frames, max_frames):  # no frame is asked for beyond max_frames
            try:
                yield self.push(frame, defer=True)
            except DataError as exc:
                self.estimate = self._refused(exc)
                yield self.estimate
            self.work()  # once the estimate is on its way, before the next frame is asked for

    def _refused(self, exc: DataError) -> LiveEstimate:
        """The estimate after a frame that was refused: the last one, flagged with the problem."""
        line = f"frame refused: {exc.one_line()}"
        if self.estimate is None:
            return self._unused(np.full((self._M, self._D), np.nan), line, count=False)
        return dataclasses.replace(self.estimate, healthy=False, health=line, rejected=())

    def _input_problem(self, y) -> str | None:
        """Why a well-formed frame cannot be used at all: it repeats the last frame exactly (a frozen
        stream), or the markers that would fix its pose all lie at one point (a stream of zeros; within
        :data:`_COINCIDE` of the model's size, closer than any pose of a model puts them; where their spread
        is the model's scaled by a unit's factor, a stream in that unit). None when it can be used.

        The frame's scale is checked against the model's on the way
        (:class:`~skelid.live_health.ScaleCheck`, every :data:`~skelid.live_health.SCALE_EVERY` frames while
        it is on scale): a stream in the wrong unit is reported on every frame (``_scale_line``), its frames
        still used.
        """
        present = np.isfinite(y).all(axis=-1)
        last, self._last_y = self._last_y, y
        if not present.any():
            return None  # every marker missing: the usual path says so
        reach = float(np.abs(y[present]).max())
        if reach > self._max_coordinate:  # as a fit refuses them (skelid.data.MAX_FIT_COORDINATE_MM)
            return (f"marker coordinates reach {reach:.3g} {self.model.units}, beyond the {self._max_coordinate:g} "
                    f"{self.model.units} ({MAX_FIT_COORDINATE_MM / 1e3:g} m) a session accepts (a unit or an "
                    "origin gone wrong?); frame not used")
        if last is not None and np.array_equal(last, y, equal_nan=True):
            self._n_repeat += 1
            return (f"frame repeats the last one exactly ({self._n_repeat + 1} in a row: a frozen stream?); "
                    "frame not used")
        self._n_repeat = 0
        if present.sum() >= self._min_present:
            extent = float(np.ptp(y[present], axis=0).max())
            if extent <= self._coincide:
                self._scale_line = None  # said here, if at all
                scale = self._scale_check.check(y, present, keep=False) if extent > 0 else None
                if scale is not None and scale.unit is not None:
                    return (f"every marker within {extent:.3g} {self.model.units} of one point: "
                            f"{_scale_words(scale, self._declared)}; frame not used")
                return (f"every marker at one point (all within {self._coincide:.3g} {self.model.units}: a zeroed "
                        "stream?); frame not used")
        if self._scale_line is not None or self._frame <= SCALE_EVERY or self._frame % SCALE_EVERY == 0:
            scale = self._scale_check.check(y, present)
            self._scale_line = _scale_words(scale, self._declared) if scale is not None and scale.off else None
        return None

    def _unused(self, y, problem: str, count: bool = True, rejected: tuple = ()) -> LiveEstimate:
        """The estimate after a frame whose data are not used: the state as it was, ``problem`` in health."""
        problems = _missing(y) + [problem]
        if self.method == "grid":
            return self._grid_estimate(None, problems, rejected)
        st = self._state
        if count:
            self._not_used(st, np.full_like(y, np.nan), self._current_sigma2())
        return self._gaussian_estimate(None, problems, rejected)

    def _swaps(self, y) -> list[tuple[int, int]]:
        """Pairs of markers (model indices) whose labels look swapped against the markers' own tracks
        (:class:`~skelid.live_health.MarkerTracks`), unless the model fits the labels as they came and not
        swapped back (:meth:`_labels_fit`: the tracks' history may itself hold a swap that began where no
        track could see it, and the tracks would call its end a swap)."""
        pairs = self._tracks.check(y)
        if not pairs:
            self._claim = None
        elif self._labels_fit(y, pairs):
            self._tracks.amend(pairs)  # the history keeps the labels as they came
            self._claim = None
            return []
        return pairs

    def _labels_fit(self, y, pairs) -> bool:
        """Whether the frames of the tracks' present claim (``pairs`` swapped in ``y`` and the frames before
        it that the same claim covered) fit the model as labelled, their pose fits' residual sum of squares
        within the ``1 - 1e-4`` chi-square quantile of the noise on their degrees of freedom, while with
        ``pairs`` swapped back they do not.

        The evidence adds up over the claim's frames, so that a model whose frames tell the labellings
        apart only weakly (case A's have one degree of freedom each) decides after a few. Only asked when
        the tracks see a swap; False while the noise level is not known (the tracks are then trusted).
        """
        ref = self._reference()
        n = int(np.isfinite(y).all(axis=-1).sum())
        dof = n * self._D - self.model.n_pose
        if ref is None or dof <= 0:
            self._claim = None
            return False
        theta, q0, s2 = ref
        key = tuple(pairs)
        claim = self._claim if self._claim is not None and self._claim[0] == key else (key, q0, q0, 0.0, 0.0, 0)
        back = y.copy()
        for i, j in pairs:
            back[[i, j]] = y[[j, i]]
        q_as, q_back = self._pose_fit(theta, y, claim[1]), self._pose_fit(theta, back, claim[2])
        rss_as = claim[3] + float(np.nansum((y - self._linearise(theta, q_as)[0]) ** 2))
        rss_back = claim[4] + float(np.nansum((back - self._linearise(theta, q_back)[0]) ** 2))
        dof += claim[5]
        self._claim = (key, q_as, q_back, rss_as, rss_back, dof)
        limit = s2 * _chi2_limit(dof)
        return rss_as <= limit < rss_back

    def _grid_noise(self) -> float | None:
        """The grid form's noise variance once it is known (stated, or on :data:`_KNOWN_DOF` degrees of
        freedom), else None."""
        st = self._state
        if st.pose is None or (self.sigma is None and st.n_obs - self.model.n_pose * st.n_used
                               - self.model.n_params < _KNOWN_DOF):
            return None
        s2 = self._grid_sigma() ** 2
        return s2 if np.isfinite(s2) else None

    def _reference(self):
        """``(theta, pose, sigma^2)`` to fit a frame at once the noise level is known (None before)."""
        if self.method == "grid":
            s2 = self._grid_noise()
            if s2 is None:
                return None
            st = self._state
            k = self._grid_map(st)
            return self._grid._points()[1][k], st.pose[k], s2
        st = self._state
        if not st.poses.shape[0] or not self._noise_known(st):
            return None
        return st.mean, self._good if self._good is not None else self._predict(st), self._current_sigma2()

    def _swapped(self, y, pairs) -> LiveEstimate:
        """The estimate after a frame whose labels look swapped: the frame is not used, the pairs named."""
        names = self.model.marker_names
        line = "; ".join(f"labels {names[i]} and {names[j]} look swapped (each marker jumped onto the "
                         "other's track)" for i, j in pairs) + "; frame not used"
        rejected = tuple(names[k] for pair in pairs for k in pair)
        if self.method == "grid":
            return self._unused(y, line, rejected=rejected)
        problems = _missing(y) + [line]
        blank = y.copy()
        blank[[k for pair in pairs for k in pair]] = np.nan
        self._not_used(self._state, blank, self._current_sigma2())
        return self._gaussian_estimate(None, problems, rejected)

    def _current_sigma2(self) -> float:
        st = self._state
        return _sigma2(st.rss, st.n_obs, st.n_used, self.model, self.sigma, self._sigma_fallback,
                       self._sigma_floor)

    def _noise_known(self, st: GaussianState) -> bool:
        """Whether the noise level is given, or estimated on at least :data:`_KNOWN_DOF` degrees of freedom."""
        return (self.sigma is not None
                or st.n_obs - self.model.n_pose * st.n_used - self.model.n_params >= _KNOWN_DOF)

    def _gate(self, st: GaussianState) -> float:
        """The bound on :func:`pose_jump` beyond which a frame's pose has jumped (``inf``: no check yet)."""
        return self._jump_limit if self._noise_known(st) else math.inf

    def _allowance(self) -> np.ndarray:
        """Variance ``(Q,)`` of each pose coordinate's third difference in the recent movement.

        A robust estimate, ``median(nu_k^2) / median(chi^2_1)`` over the innovations ``nu`` of the last
        :data:`_JUMP_WINDOW` frames checked (used or not): a real movement persists and raises it, a
        swapped label lasts a few frames and does not. Recomputed every :data:`_ALLOW_EVERY` frames checked
        (a median per frame would cost a quarter of a push).
        """
        n = self._n_nu
        if n != self._allow_at and (n < _ALLOW_EVERY or n % _ALLOW_EVERY == 0):
            self._allow = np.median(self._nu2[:min(n, _JUMP_WINDOW)], axis=0) / _CHI2_1_MEDIAN
            self._allow_at = n
        return self._allow

    def _note_jump(self, st: GaussianState, q) -> None:
        """Record the frame's innovation against the held poses (for :meth:`_allowance`)."""
        p = st.poses
        self._nu2[self._n_nu % _JUMP_WINDOW] = np.square(q - (3.0 * p[2] - 3.0 * p[1] + p[0]))
        self._n_nu += 1

    def _screen(self, resid, sigma2) -> np.ndarray | None:
        """Index of the marker to leave out: the worst one beyond ``outlier_sd`` noise sds (once the noise is
        known), or None."""
        if not self._noise_known(self._state):
            return None
        # a marker residual distance has D coordinates of noise: compare with sqrt(D) sigma
        limit = self.outlier_sd * math.sqrt(sigma2 * self._D)
        r = np.where(np.isnan(resid), -np.inf, resid)
        worst = int(np.argmax(r))
        return worst if r[worst] > limit else None

    def _push_gaussian(self, y) -> LiveEstimate:
        """One frame of the Gaussian form: screen its markers, check its pose's jump, absorb it.

        A pipeline of :meth:`_screened_pose` (the pose with the markers that do not fit left out),
        :meth:`_pose_jumped` (the pose against the motion model) and :meth:`_absorbed` (the state
        after the frame); each way out leaves the frame unused with the problem named.
        """
        st = self._state
        present = ~np.isnan(y).any(axis=-1)
        n_present = int(present.sum())
        problems = [] if n_present == self._M else [f"{self._M - n_present} marker(s) missing"]
        if n_present < self._min_present:
            problems.append("too few markers to fix the pose: frame not used")
            self._not_used(st, y, self._current_sigma2())
            return self._gaussian_estimate(None, problems, ())
        s2 = self._current_sigma2()
        if self._step is not None and st.poses.shape[0]:
            est = self._step(y, st, s2, n_present)
            if est is not None:
                return est
        theta = st.mean
        sc = self._screened_pose(theta, y, self._first_pose(theta, y, st), s2, present, n_present)
        rejected = tuple(sc.rejected)
        bad = [self.model.marker_names.index(n) for n in rejected]
        if sc.too_few:
            # without the last marker left out too few remain to fix the pose: every marker taken out would
            # leave the rest fitting, so the frame cannot say which misfits
            problems.append(_too_few_line(rejected[:-1], self.outlier_sd))
            self._tracks.amend(lost=bad[:-1])
            self._not_used(st, sc.y, s2)
            return self._gaussian_estimate(sc.resid, problems, rejected[:-1])
        if rejected:
            # a frame with a marker that does not fit (a swapped label) may have its pose fitted wrongly too, and
            # the motion model would carry that pose into its neighbours: its data are left out, and its pose
            # follows the motion model alone
            problems.append(f"left out {', '.join(rejected)}: residual beyond {self.outlier_sd:g} noise sd "
                            "(swapped or wrong label?); frame not used")
            pair = self._swapped_pair(theta, y, sc.q, s2, _worst_first(sc.resid, bad))
            self._amend_tracks(pair, bad)
            if pair:
                problems.insert(len(problems) - 1, _swap_line(pair))
            if self._motion:
                self._not_used(st, sc.y, s2)
                return self._gaussian_estimate(sc.resid, problems, rejected)
        q = self._continuous(st, sc.q)
        r, Jq2, Jt2 = _frame_rows(sc, self._M)
        if self._pose_jumped(st, q, Jq2, s2):
            if self._run >= _HELD or self._jumped:  # held poses from data, or a jump still going on: left out
                problems.append("the pose jumps beyond the motion model (swapped or wrong label?); frame not used")
                pair = self._swapped_pair(theta, y, sc.q, s2, _worst_first(sc.resid, []), st)
                if pair:
                    problems.insert(len(problems) - 1, _swap_line(pair))
                    self._amend_tracks(pair, ())
                self._not_used(st, sc.y, s2, jumped=True)
                return self._gaussian_estimate(sc.resid, problems, rejected)
            st = drop_poses(st)  # the prediction ran on through frames without data: a new chain from this frame
        self._state = st = self._absorbed(st, sc, theta, q, r, Jq2, Jt2)
        self._gap = 0
        self._run += 1
        if not rejected:
            self._good = q
        if self._remember(sc.y, q, True):
            self._relinearise(st.mean)
        return self._gaussian_estimate(sc.resid, problems, rejected, used=not rejected, y=sc.y, q=q)

    def _amend_tracks(self, pair, lost) -> None:
        """Tell the markers' tracks what the model found in the frame: a swapped ``pair`` of names (the tracks
        follow the markers, not the labels), markers ``lost`` (indices) left out as outliers."""
        index = self.model.marker_names.index
        pairs = [(index(pair[0]), index(pair[1]))] if pair else []
        self._tracks.amend(pairs, [k for k in lost if not any(k in p for p in pairs)])

    def _first_pose(self, theta, y, st: GaussianState) -> np.ndarray:
        """The frame's pose before screening: random starts for the first frame, else from the prediction."""
        if st.poses.shape[0] == 0:
            return initial_pose(self.model, theta, y, self.rng, ws=self._ws)[0]
        return self._pose_fit(theta, y, self._predict(st))

    def _screened_pose(self, theta, y, q, s2: float, present, n_present: int) -> _Screened:
        """The frame's pose with the markers beyond ``outlier_sd`` left out, worst first (at most three).

        Before the first marker is left out, the pose is fitted again from the last pose whose markers all
        fitted: the pose fit may have started in the wrong basin (a prediction carried through a glitch), and
        the frame may be whole after all. Stops early (``too_few``) when too few markers remain.
        ``present`` is updated in place.
        """
        rejected: list = []
        retried = False
        while True:
            x, Jq, Jt = self._linearise(theta, q)
            resid = np.sqrt(np.sum((y - x) ** 2, axis=-1))
            bad = self._screen(resid, s2) if len(rejected) < 3 else None  # a swapped pair needs two
            if bad is None:
                return _Screened(y, q, x, Jq, Jt, resid, present, n_present, rejected, False)
            if not (rejected or retried) and self._good is not None:
                retried = True
                q_alt = self._pose_fit(theta, y, self._good)
                x_alt = self._linearise(theta, q_alt)[0]
                if self._screen(np.sqrt(np.sum((y - x_alt) ** 2, axis=-1)), s2) is None:
                    q = q_alt
                    continue
            y = y.copy()
            y[bad] = np.nan
            present[bad] = False
            n_present -= 1
            rejected.append(self.model.marker_names[bad])
            if n_present < self._min_present:
                return _Screened(y, q, x, Jq, Jt, resid, present, n_present, rejected, True)
            q = self._pose_fit(theta, y, q)

    def _continuous(self, st: GaussianState, q) -> np.ndarray:
        """``q`` with its angles continuous with the last held pose (for the motion model)."""
        if not st.poses.shape[0]:
            return q
        last = st.poses[-1]
        return np.where(self._rot, last + (q - last + np.pi) % (2.0 * np.pi) - np.pi, q)

    def _pose_jumped(self, st: GaussianState, q, Jq2, s2: float) -> bool:
        """Whether the pose jumps beyond the motion model (:func:`pose_jump`; checked once poses are held).

        Records the frame's innovation (:meth:`_note_jump`) when it is checked.
        """
        if not (self._motion and st.poses.shape[0] == _HELD):
            return False
        gate = self._gate(st)
        jump = pose_jump(st, q, Jq2, self._weight, s2, self._allowance())
        self._note_jump(st, q)
        return jump > gate

    def _absorbed(self, st: GaussianState, sc: _Screened, theta, q, r, Jq2, Jt2) -> GaussianState:
        """The state after the frame's rows: absorbed and solved, then linearised again ``n_iter`` times
        at the filtered pose (iterated extended Kalman update) under a motion model."""
        model = self.model
        rr = float(r @ r)
        s2 = _sigma2(st.rss + rr, st.n_obs + r.size, st.n_used + 1, model, self.sigma,
                     self._sigma_fallback, self._sigma_floor)
        motion = self._motion
        new = solve_mean(absorb(st, r, Jq2, Jt2, q, theta, self._weight, r.size, rr), self._prior, s2,
                         pose=motion)
        if not motion:  # every pose free: the frame's own fit is its pose
            return new._replace(pose_mean=q)
        y, present = sc.y, sc.present
        last = np.inf
        for _ in range(self.n_iter):
            ql = new.pose_mean
            x2, Jq, Jt = self._linearise(theta, ql)
            r2 = (y[present] - x2[present]).reshape(-1)
            Jq2 = Jq[present].reshape(r2.size, -1)
            again = solve_mean(absorb(st, r2, Jq2, Jt[present].reshape(r2.size, -1), ql,
                                      theta, self._weight, r.size, rr), self._prior, s2)
            moved = float(np.sum((Jq2 @ (again.pose_mean - ql)) ** 2))
            if moved > last:  # each pass moves the pose further: they diverge, the last one is kept
                break
            new = again
            if moved <= RELINEARISE_TOL**2 * s2:
                break  # the filtered pose has settled: it moves the markers by less than a tenth of their noise
            last = moved
        return new

    def _relinearise(self, theta) -> None:
        """Every early frame linearised again at ``theta`` (:func:`relinearise`); with ``cutoff='auto'`` the
        motion model's cutoff is chosen first (:func:`live_cutoff`) from 50 frames on.

        With the grid beside it (a model with few parameters), ``theta`` is the grid's mean instead where the
        two disagree by more than :data:`_ASTRAY` of the grid's sds: the extended Kalman update
        linearises at its own mean, and a first guess in another basin keeps it there; the grid has
        weighed every point of the prior. The grid is left after the last early frame. A model with more
        parameters has no grid beside it: after the last early frame a batch fit of the early frames checks
        the basin instead (:meth:`_basin`, :func:`_basin_fit`)."""
        if self._shadow is not None:
            theta = self._shadow_theta(theta)
            if len(self._early) >= _RELINEARISE[-1]:
                self._shadow = None
        with one_blas_thread():
            self._relinearise_early(theta)

    def _relinearise_early(self, theta) -> None:
        """:meth:`_relinearise`'s work (with one BLAS thread)."""
        self._folded = None
        if self._auto and len(self._early) >= 50:
            self._set_cutoff(_for_all(live_cutoff(self.model, self._early, theta, self.rate, self._ws)))
        self._state = self._relinearised(self._early, theta)
        if len(self._early) >= _RELINEARISE[-1] and self.model.n_params > _SHADOW_PARAMS and _basin_affordable(
                self.model, len(self._early)):
            # the recursive form follows the basin of its first linearisations, made from a few frames: a batch
            # fit of the early frames searches the prior (the tennis arm's elbow centre once sat 20-140 batch sd
            # off, every frame fitting, health "ok")
            self._state, self._early = self._basin(self._early, self._state,
                                                   _basin_fit(self.model, self._early, self.rate,
                                                              _live_part(self._state).mean))
        if len(self._early) >= _RELINEARISE[-1] and self._motion:
            self._blocks, self._block, self._raw_open = True, list(self._early[-_LAG:]), theta_marginal(self._state)
            # the early frames' bias, at their smoothed poses, now: the estimate after them is the batch fit's
            y, q, used = (np.stack([f[k] for f in self._early]) for k in range(3))
            num = finish_steps(self._bias_steps(y, q, used, self._state.mean, self._cutoff_now))
            self._apply(_Refold(None, None, False), None, None, num)

    def _raw(self) -> tuple[np.ndarray, np.ndarray]:
        """The state's information about theta (:func:`theta_marginal`) without the corrections applied since
        the last full re-linearisation (:meth:`_apply`): what the frames gave as they were folded in."""
        Lam, eta = theta_marginal(self._state)
        return Lam - self._applied[0], eta - self._applied[1]

    def _close_block(self) -> None:
        """The open block has :data:`_BLOCK` frames: it closes, and the next one opens (called on the frame that
        fills it, after the frame is folded in).

        A frame arriving is linearised once, at its pose filtered from the frames before it; where the markers
        barely fix a pose, the smoothed pose ends elsewhere, and the remainder of that linearisation has one
        sign frame after frame: over an hour it biases case A at 15 mm by many of its sds. Each block is
        therefore folded in again at its poses smoothed with :data:`_LAG` frames on each side, once those
        after it have come (:meth:`_refold`), a step at a time (:meth:`work`). What the state's information
        about theta gained over the block (:meth:`_raw` at its two ends) is then replaced by the block's
        information at its smoothed poses (:meth:`_apply`): each frame ends linearised where the batch fit with
        this motion model linearises it, and the frame on hand is never folded again. The differences of the
        state's information at the blocks' ends add up to that of the whole stretch, so nothing is counted
        twice or left out; the motion model's link between the last poses of one block and the first of the
        next is left out of the blocks' own information (three frames of :data:`_BLOCK`)."""
        raw = self._raw()
        self._closed = _Refold(self._raw_open, raw)
        self._raw_open = raw

    def _refold(self) -> None:
        """The closed block's :data:`_LAG` frames after it have come: its work starts (one block at a time: any
        still pending is finished first)."""
        while self._pending is not None:
            self.work()
        p, self._closed = self._closed, None
        p.steps = self._refold_steps(self._block[:_BLOCK + 2 * _LAG], self._state.mean, self._cutoff_now,
                                     self._motion)
        self._pending = p
        self._block = self._block[_BLOCK:]  # the _LAG frames before the open block, and its first _LAG
        self._n_new = _LAG

    def _refold_steps(self, frames, theta, cutoff, motion: bool, after: int = _LAG):
        """The steps of :meth:`work` for one block: ``frames`` are its :data:`_LAG` frames before, its own and
        the ``after`` after. The poses are fitted again at ``theta`` and smoothed (as :func:`relinearise`
        does: where the smoothed poses misfit, with ``cutoff='auto'``, the free ones without the motion model);
        the block's information about theta at them (:func:`block_information`) and its second-order bias
        (:meth:`_bias_sum_of`) are returned: ``(Lambda, eta, sum S b)``."""
        model = self.model
        own = slice(_LAG, len(frames) - after)
        Y = np.stack([f[0] for f in frames])
        q = np.stack([f[1] for f in frames])
        used = np.array([f[2] for f in frames])
        rss_free = np.zeros(len(frames))
        if used.any():
            q[used], rss_free[used] = fit_pose(model, theta, Y[used], q[used], n_iter=10, ws=self._ws)
        yield
        R = None
        if motion and used.sum() >= 8:
            n_obs = int(np.isfinite(Y[used]).all(axis=-1).sum()) * model.dim
            s2 = _sigma2(float(rss_free.sum()), n_obs, int(used.sum()), model, self.sigma, self._sigma_fallback,
                         self._sigma_floor)
            qs, c = yield from fitting_smooth_steps(model, theta, Y, q, used, self.rate, cutoff,
                                                    float(rss_free.sum()), s2, self._ws, self._auto)
            if qs is not None:
                q, cutoff = qs, c
                R = self._penalty(Y[own], q[own], used[own], theta, cutoff)
            yield
        y, q, used = Y[own], q[own], used[own]
        Lam, eta = block_information(model, theta, y, q, used, R, self._ws)
        yield
        num = yield from self._bias_steps(y, q, used, theta, cutoff)
        return Lam, eta, num

    def _bias_steps(self, y, q, used, theta, cutoff):
        """Steps of :meth:`work` that sum the second-order bias of frames ``y``, ``q`` (:meth:`_bias_sum_of`), a
        piece at a time (:func:`_pieces`); the sum is returned."""
        num = np.zeros(self.model.n_params)
        for a in _pieces(self.model, len(q)):
            num = num + self._bias_sum_of(y[a], q[a], used[a], theta, cutoff)
            yield
        return num

    def _apply(self, p: _Refold, Lam, eta, num) -> None:
        """A block's work done (:meth:`_refold_steps`): what its frames gave the state as they came
        (``p``'s information at the block's two ends) replaced by ``(Lam, eta)``, the mean solved again, and
        its bias added. A block whose frames a full re-linearisation has folded in since
        (:meth:`_checked_done`), or the early frames (folded in at their smoothed poses from the start), add
        their bias only (``Lam`` and ``eta`` unused: None for the early frames)."""
        if p.correct:
            self._folded = None  # the frames folded in again change: a block whose frames a full
            # re-linearisation folded in since (:meth:`_checked_done`) changes only the bias
            dL = Lam - (p.end[0] - p.start[0])
            de = eta - (p.end[1] - p.start[1])
            new = add_theta_information(self._state, dL, de)
            if new is not None:  # None (not definite) cannot happen for a sum of information: left out if it does
                self._state = solve_mean(new, self._prior, self._current_sigma2(), pose=self._motion)
                self._applied = (self._applied[0] + dL, self._applied[1] + de)
        if np.isfinite(num).all():
            self._bias_sum = num if self._bias_sum is None else self._bias_sum + num
            self._bias_at = -_BIAS_EVERY  # solved again at the next estimate

    def _penalty(self, y, q, used, theta, cutoff):
        """The motion model's penalty over frames ``y``, ``q`` (:func:`smoothing_penalty`)."""
        model = self.model
        present = np.isfinite(y).all(axis=-1) & np.asarray(used, bool)[:, None]
        Jq = marker_jacobian(model, theta, q, self._ws)[1] * present[..., None, None]
        return smoothing_penalty(model, frame_gram(Jq.reshape(len(q), -1, model.n_pose)), self.rate, cutoff)

    def _bias_sum_of(self, y, q, used, theta, cutoff) -> np.ndarray:
        """The second-order bias of frames ``y``, ``q`` folded in at their smoothed poses: ``S b`` at unit noise
        (:func:`smoothed_bias_sums`; zero where it cannot be had).

        Folded in at its smoothed pose, each frame carries the bias of the batch ``marker`` fit with the
        same motion model, of order sigma^2: it does not shrink as the frames add up, and their sd does
        (case A at 15 mm: several sd after ten thousand frames). The batch fit takes its second-order bias
        off; so does the session (:meth:`_unbiased`). Each piece's expansion takes theta as known (the limit
        of many frames; the terms of order sigma^2 / T, which the batch fit keeps, are left out), so that a
        piece that alone leaves a parameter unidentified has a bias too."""
        y = np.where(np.asarray(used, bool)[:, None, None], y, np.nan)
        try:
            num, _ = smoothed_bias_sums(self.model, y, theta, q, 1.0, self._penalty(y, q, used, theta, cutoff),
                                        theta_known=True, max_frames=len(q), ws=self._ws)
        except np.linalg.LinAlgError:
            return np.zeros(self.model.n_params)
        return num if np.isfinite(num).all() else np.zeros(self.model.n_params)

    def _unbiased(self, st: GaussianState, s2: float) -> np.ndarray:
        """The mean of ``st`` less the second-order bias of the frames folded in at their smoothed poses
        (:meth:`_bias_sum_of`) at noise variance ``s2``, within the prior's bounds.

        The bias is ``s2 (sum S)^{-1} sum S b`` with the sum of information over every frame the state holds,
        the prior's included (at unit noise), not over the blocks alone: a block that leaves a parameter
        barely identified (a joint still in it) has a large bias along it, which only the frames after it
        outweigh; the frames not yet folded in again add their information but no bias (the open block and,
        until its work is done, the one before: the bias is then a little short of the batch fit's)."""
        if self._bias_sum is None:
            return st.mean
        if self._frame >= self._bias_at + _BIAS_EVERY:  # the information grows slowly: solved now and then
            Lam = _theta_information(st, self._prior, s2)[0] * s2  # unit noise
            self._bias, self._bias_at = np.linalg.solve(Lam, self._bias_sum), self._frame
        return np.minimum(np.maximum(st.mean - s2 * self._bias, self._prior[2]), self._prior[3])  # np.clip, quicker

    def _noise_dof(self, st) -> float:
        """Residual degrees of freedom behind the noise level (inf where it was stated)."""
        if self.sigma is not None:
            return math.inf
        return float(st.n_obs - self.model.n_pose * st.n_used - self.model.n_params)

    def _shadow_theta(self, theta):
        """``theta``, or the grid's mean where ``theta`` lies beyond :data:`_ASTRAY` of its sds from it."""
        st = self._shadow
        lw = self._grid._log_weights(st.rss, st.logdet, st.n_obs, st.n_used).ravel()
        if not np.isfinite(lw).any():
            return theta
        w = np.exp(lw - np.nanmax(lw))
        w = np.where(np.isfinite(w), w, 0.0)
        w /= w.sum()
        mean = w @ self._grid._points()[1]
        sd = np.sqrt(np.clip(np.diag(self._grid_cov(w, mean)), 0.0, None))
        return mean if np.any(np.abs(np.asarray(theta) - mean) > _ASTRAY * sd) else theta

    def _set_weight(self, cutoff) -> None:
        """The motion model's weight of each pose coordinate ``(Q,)`` for ``cutoff`` (Hz: one, one per
        coordinate, or None)."""
        self._weight = np.broadcast_to(np.asarray(motion_scale(cutoff, self.rate), float),
                                       (self.model.n_pose,)).copy()
        self._motion = bool(self._weight.max() > 0)

    def _set_cutoff(self, cutoff) -> None:
        """The motion model's cutoff from now on (``cutoff='auto'``)."""
        self._cutoff_now = cutoff
        self._set_weight(cutoff)
        if self._step is not None:
            self._step = _Step(self)

    def _not_used(self, st: GaussianState, y, s2: float, jumped: bool = False) -> None:
        """A frame whose data are not used: under the motion model its pose follows the prediction, for up to
        :data:`_BRIDGE` frames in a row; after a longer gap the held poses are marginalised
        (:func:`drop_poses`), and the next frame's pose is found afresh rather than trusted to a prediction
        that has run on without data."""
        self._gap += 1
        self._run = 0
        self._jumped = jumped
        if not (st.poses.shape[0] and self._motion):
            return
        q = self._predict(st)
        if self._gap > _BRIDGE:
            self._state = drop_poses(st)
        else:
            self._state = solve_mean(absorb(st, None, None, None, q, st.mean, self._weight, 0, 0.0), self._prior, s2)
        self._remember(y, q, False)

    def _predict(self, st: GaussianState) -> np.ndarray:
        """The next pose by constant velocity from the last two (where the pose fit starts)."""
        p = st.poses
        return p[-1] if p.shape[0] < 2 else 2.0 * p[-1] - p[-2]

    def _remember(self, y, q, used: bool) -> bool:
        """Keep an early frame for re-linearisation; True when it is time to re-linearise."""
        if self._kept is not None and len(self._early) >= _RELINEARISE[-1] and len(self._kept) < _DONE_KEEP:
            self._kept.append((y, q, used))
        if used and self._shadow is not None and not np.isnan(y).any():
            # frames with every marker only: with some missing, a grid point may fix no pose (log det -inf)
            st = self._grid.update(self._shadow, y)
            if np.isfinite(st.rss).all() and np.isfinite(st.logdet).all():
                self._shadow = st
        n = len(self._early)
        if n >= _RELINEARISE[-1]:
            if self._blocks:
                self._block.append((y, q, used))
                self._n_new += 1
                if self._n_new == _BLOCK:
                    self._close_block()
                elif self._n_new == _BLOCK + _LAG:
                    self._refold()
            if self._auto:  # after the early frames the cutoff follows the motion, every 200 frames
                self._recent.append((y, q, used))
                if len(self._recent) == _RELINEARISE[-1]:
                    # the frames' poses as fitted on arrival (the mean has settled by now): no pose fits here
                    self._set_cutoff(_for_all(live_cutoff(self.model, self._recent, self._state.mean, self.rate,
                                                          self._ws, refit=False)))
                    self._recent.clear()
            return False
        self._early.append((y, q, used))
        return n + 1 in _RELINEARISE

    def _gaussian_estimate(self, resid, problems, rejected, used: bool = False, y=None, q=None) -> LiveEstimate:
        """The estimate from the state; a frame ``used`` whole (``y (M, D)``, its pose ``q (Q,)``) has its
        residuals checked (:meth:`_misfit`); the frame's scale and the estimate's bounds are reported
        (:meth:`_notes`)."""
        st = self._state
        s2 = _sigma2(st.rss, st.n_obs, st.n_used, self.model, self.sigma, self._sigma_fallback,
                       self._sigma_floor)
        if used and resid is not None:
            problems = problems + self._misfit(resid, s2, st.n_obs - self.model.n_pose * st.n_used
                                               - self.model.n_params, y, q, st.mean)
        folded = self._folded_state(s2)
        on, lines = self._gaussian_bound(folded, s2)
        problems = problems + self._notes(lines)
        healthy = not problems
        return LiveEstimate(self._frame, self._frame / self.rate, _frozen(self._unbiased(folded, s2)),
                            _frozen(st.pose_mean),
                            math.sqrt(s2), healthy, "ok" if healthy else "; ".join(problems), rejected,
                            self.model, partial(theta_cov, folded, self._prior, s2), resid, self._ranges, on,
                            self._motion_seen(y if used else None, q, st.mean), self._targets,
                            self._noise_dof(st))

    def _folded_state(self, s2: float) -> GaussianState:
        """The state the estimate of theta is read from: under the motion model's blocks, the state with
        only the information of the frames folded in again at their smoothed poses (:meth:`_close_block`),
        its mean solved; else the state itself.

        A frame folded in on arrival is linearised at its pose filtered from the frames before it, which
        the noise moves; where the markers barely fix a pose that biases theta, and not as the smoothed
        pose does, whose bias the session takes off (:meth:`_unbiased`): case A at 15 mm, with blocks of 200
        frames, the filtered frames of the open and pending blocks (a quarter to a half of 1000 frames) held
        the estimate 0.9 of its sd low (coverage 0.80 over 100 sessions; ``benchmarks/live_long.py``). Their
        information waits until their block is folded in again (:meth:`finish` folds them in): the
        estimate is at most :data:`_BLOCK` + :data:`_LAG` frames, and its work, behind the stream. Made
        once after each block's work (and each re-linearisation), at the noise level of that time."""
        if not self._blocks:
            return self._state
        if self._folded is None:
            start = next((p.start for p in (self._pending, self._closed) if p is not None and p.correct),
                         self._raw_open)
            L, e = theta_marginal(self._state)
            new = add_theta_information(self._state, start[0] + self._applied[0] - L,
                                        start[1] + self._applied[1] - e)
            self._folded = self._state if new is None else solve_mean(new, self._prior, s2, pose=False)
        return self._folded

    def _motion_seen(self, y, q, theta) -> Callable[[], bool] | None:
        """Count a frame used whole (``y``, its pose ``q``; None: none) in the joints' motion, and return
        what says, when asked, whether every joint has stayed still so far (:meth:`_still_now`, at
        ``theta``); None once one has moved."""
        if self._moved:
            return None
        if y is not None and q is not None and self._joint_rot.size:
            a = np.asarray(q, float)[self._joint_rot]
            beyond = np.stack([a < self._extreme_at[0], a > self._extreme_at[1]])  # a new lowest or highest
            if np.isfinite(a).all() and beyond.any():  # each joint coordinate's extremes as fitted on arrival
                self._extreme_at = np.where(beyond, a, self._extreme_at)
                kept = (np.array(y, float), np.array(q, float))
                for side, k in zip(*np.nonzero(beyond), strict=True):
                    self._extreme[k][side] = kept
                self._extreme_version += 1
        return partial(self._still_now, np.array(theta, float),
                       tuple(e for pair in self._extreme for e in pair if e[0] is not None), self._extreme_version)

    def _still_now(self, theta, kept, version: int = -1) -> bool:
        """Whether every joint had stayed within :data:`~skelid.estimators.checks.misfit.STILL_JOINT_DEG` over the
        frames used up to an estimate (``theta``; ``kept``: the extreme frames then, see below).

        The poses fitted on arrival moved with the estimate (a still frame's pose and a length trade off, so
        identical frames drift apart as the estimate settles); the frames where each joint coordinate was
        lowest and highest on arrival are fitted again at ``theta`` and their range taken there. Once a joint
        has moved, later estimates say so without refitting. Noise large against the pose's determination
        can pass for motion (the status is then 'identified', as before this check). The answer for one set of
        extreme frames (``version``) is kept: they change ever more rarely, and a stream that stays still is
        refitted a few times, not at every frame.
        """
        if not self._joint_rot.size:
            return False
        if not kept:
            return True
        if self._still_memo[0] == version:
            return self._still_memo[1]
        y = np.stack([e[0] for e in kept])
        q = fit_pose(self.model, np.broadcast_to(theta, (len(kept), theta.size)), y, np.stack([e[1] for e in kept]),
                     ws=self._ws)[0][:, self._joint_rot]
        moved = bool(np.degrees(np.max(np.ptp(np.unwrap(q, axis=0), axis=0))) >= STILL_JOINT_DEG)
        self._moved = self._moved or moved
        self._still_memo = (version, not moved)
        return not moved

    def _gaussian_bound(self, st: GaussianState, s2: float) -> tuple[np.ndarray | None, list[str]]:
        """Which parameters' means are held on a prior bound ``(P,)`` (None: none), and the lines of those
        the unbounded solve puts beyond it by more than :data:`~skelid.live_health.BOUND_Z` sd."""
        lo, hi = self._ranges[0], self._ranges[1]
        on = (st.mean <= lo) | (st.mean >= hi)  # solve_mean clips: a mean held on a bound equals it
        if not on.any():
            return None, []
        Lam, eta = _theta_information(st, self._prior, s2)
        cov = np.linalg.inv(Lam)
        z = gaussian_bound_z(cov @ eta, np.sqrt(np.diag(cov)), lo, hi)
        return on, _bound_lines(self.model, np.where(on, z, -np.inf), np.where(st.mean <= lo, -1, 1))

    def _notes(self, bound_lines) -> list[str]:
        """What is reported whatever became of the frame: its scale off the model's, estimates on a bound."""
        return ([] if self._scale_line is None else [self._scale_line]) + bound_lines

    def _misfit(self, resid, s2: float, dof_noise: int, y=None, q=None, theta=None) -> list[str]:
        """What of a frame used whole and of the recent frames exceeds what the noise explains.

        ``resid (M,)`` is the frame's residual distances (its pose ``q`` fitted freely to the frame ``y``),
        ``s2`` the noise variance (stated, or estimated on ``dof_noise`` degrees of freedom), ``theta`` the
        parameters now (where the window's markers are left out in turn).
        The frame joins the misfit window (:class:`~skelid.live_health.MisfitWindow`); once the noise is
        known (stated, or :data:`_KNOWN_DOF` degrees of freedom) four checks:

        - the frame: its residual sum of squares against ``s2`` on its ``n D - Q`` degrees of freedom, beyond
          the ``1 - 1e-7`` quantile (:data:`_FRAME_P`; ``chi^2`` for a stated noise level, ``F`` against
          an estimated one): a frame that misfits as a whole, no one marker beyond the screen;
        - the window: the last 50 frames' residual variance against the stated noise level, or against that of
          the frames before them, beyond the ``1 - 1e-6`` quantile and :data:`~skelid.live_health.EFFECT_WINDOW`
          (4) times the noise variance (a misfit that began, a stated noise level too low);
        - each marker over the window: its mean squared residual distance beyond
          :data:`~skelid.live_health.EFFECT_MARKER` ``D s^2`` (4) and the quantile (a marker that does not
          follow the model while the rest do: placed elsewhere, loose), named only where leaving the markers
          out in turn tells it from the others (:func:`~skelid.live_health.alike_markers`), else the
          candidates listed;
        - a noise sd over :data:`_LOOSE` of the model's size (no marker system is that noisy: the stream's
          units or the model are wrong).

        An estimated noise level grows to cover a misfit of every marker alike; only a stated one can show
        that.
        """
        r2 = resid * resid
        seen = r2 == r2  # not NaN
        n = int(np.count_nonzero(seen))
        if n < self._M:
            r2 = np.where(seen, r2, 0.0)
        rss = float(r2.sum())
        stated = self.sigma is not None
        if not stated and dof_noise < _KNOWN_DOF:
            self._window.add(r2, seen, rss, n, y, q)
            return []
        units = self.model.units
        out = []
        dof = n * self._D - self.model.n_pose
        frame_cap = s2 * dof * ratio_limit(_FRAME_P, dof, None if stated else dof_noise) if dof > 0 else math.inf
        if rss > frame_cap:
            out.append(f"this frame's residuals (rms {math.sqrt(rss / (n * self._D)):.3g} {units}) "
                       f"exceed what the noise (sd {math.sqrt(s2):.3g}) explains: wrong model, units or labels?")
        # the window takes each frame, and each marker in it, at most at its own bound: a few frames already
        # reported (a swap the tracks missed and the model took in) would otherwise fill it for 50 frames
        self._window.add(np.minimum(r2, s2 * self._marker_cap), seen, min(rss, frame_cap), n, y, q)
        linearise = None if theta is None else partial(_window_linearise, self.model, self._ws, theta)
        mis = self._window.check(s2, None if stated else dof_noise, linearise)
        if mis is not None:
            out += self._window_lines(mis, s2, stated)
        size = self._size
        if s2 > (_LOOSE * size) ** 2:
            out.append(f"noise sd {math.sqrt(s2):.3g} {units} is over {_LOOSE:.0%} of the model's size "
                       f"({size:.3g} {units}): wrong units, wrong model or markers that do not follow it?")
        return out

    def _window_lines(self, mis, s2: float, stated: bool) -> list[str]:
        """The problem lines of a misfit window's finding (:class:`~skelid.live_health.Misfit`)."""
        units, names = self.model.units, self.model.marker_names
        out = []
        if mis.sd is not None:
            against = (f"stated noise sd {mis.noise_sd:.3g}: wrong model, units or noise level?" if stated else
                       f"{mis.noise_sd:.3g} of the frames before: the markers or the movement changed (a marker "
                       "slipped, a label changed?)")
            out.append(f"residual sd {mis.sd:.3g} {units} over the last {mis.n_frames} frames exceeds the {against}")
        if mis.alike.size:
            shown = ", ".join(f"{names[k]} {v:.3g}" for k, v in zip(mis.alike[:4], mis.alike_rms[:4], strict=True))
            more = f" and {mis.alike.size - 4} more" if mis.alike.size > 4 else ""
            out.append(f"markers that do not follow the model over the last {mis.n_frames} frames, but the residuals "
                       f"(beyond what the noise sd {math.sqrt(s2):.3g} allows) cannot say which: any one of {shown}"
                       f"{more} {units} (rms residual) taken out, the rest fit alike (placed elsewhere, loose, or "
                       "mislabelled?)")
        if mis.markers.size:
            shown = ", ".join(f"{names[k]} {v:.3g}" for k, v in zip(mis.markers[:3], mis.marker_rms[:3], strict=True))
            more = f" and {mis.markers.size - 3} more" if mis.markers.size > 3 else ""
            out.append(f"markers that do not follow the model over the last {mis.n_frames} frames (rms residual "
                       f"{shown}{more} {units}, beyond the {math.sqrt(EFFECT_MARKER * self._D * s2):.3g} that the "
                       f"noise sd {math.sqrt(s2):.3g} allows): placed elsewhere, loose, or mislabelled?")
        return out

    def _swapped_pair(self, theta, y, q, s2: float, candidates, st: GaussianState | None = None):
        """Two markers whose labels look swapped in frame ``y``: the names of the first pair among
        ``candidates`` (marker indices, worst first) with which, swapped back, every marker fits within
        ``outlier_sd``, the residual sum of squares is at most :data:`_DECISIVE` of the frame's as it came
        (and, given the state ``st``, the pose no longer jumps); None if no pair does."""
        starts = [a for a in (q, self._good) if a is not None]
        # the frame as it came, each start's best fit with every marker: a swap must fit far better than that
        # (two markers close together, as a bent elbow brings them, fit about as well either way round)
        rss0 = min(float(np.nansum((y - self._linearise(theta, self._pose_fit(theta, y, a))[0]) ** 2))
                   for a in starts) if starts else math.inf
        for i, j in itertools.combinations(candidates, 2):
            if not (np.isfinite(y[i]).all() and np.isfinite(y[j]).all()):
                continue
            ys = y.copy()
            ys[[i, j]] = y[[j, i]]
            for start in starts:
                qs = self._pose_fit(theta, ys, start)
                x, Jq, _ = self._linearise(theta, qs)
                d2 = np.sum((ys - x) ** 2, axis=-1)
                if self._screen(np.sqrt(d2), s2) is not None or np.nansum(d2) > _DECISIVE * rss0:
                    continue
                if st is not None:
                    m = np.isfinite(ys).all(axis=-1)
                    qc = self._continuous(st, qs)
                    jump = pose_jump(st, qc, Jq[m].reshape(-1, qs.size), self._weight, s2, self._allowance())
                    if jump > self._gate(st):
                        continue
                names = self.model.marker_names
                return names[i], names[j]
        return None

    def _push_grid(self, y) -> LiveEstimate:
        """One frame of the grid form: the grid filter's update, with the markers beyond ``outlier_sd`` noise
        sds of the most probable grid point left out (worst first, at most three, each time updating again
        from the state before the frame) once the noise level is known."""
        n_present = int((~np.isnan(y).any(axis=-1)).sum())
        problems = [] if n_present == self._M else [f"{self._M - n_present} marker(s) missing"]
        if n_present < self._min_present:
            problems.append("too few markers to fix the pose: frame not used")
            self._state = self._grid.update(self._state, y)
            return self._grid_estimate(None, problems)
        before = self._state
        s2 = self._grid_noise()
        limit = math.inf if s2 is None else self.outlier_sd * math.sqrt(self._D * s2)
        names, rejected = self.model.marker_names, []
        y0, first = y, None
        while True:
            st = self._grid.update(before, y)
            if n_present < self._M and not (np.isfinite(st.logdet).all() and np.isfinite(st.rss).all()):
                # the markers left fix no pose at some grid point (J^T J singular): the frame would poison every
                # later posterior (log det -inf everywhere, the posterior NaN), so it is not used
                self._tracks.amend(lost=[names.index(n) for n in rejected])
                problems.append((f"left out {', '.join(rejected)}; " if rejected else "")
                                + "the markers left do not fix the pose: frame not used")
                return self._grid_estimate(None, problems, tuple(rejected))
            lw = self._grid._log_weights(st.rss, st.logdet, st.n_obs, st.n_used).ravel()
            k = int(np.argmax(lw))
            resid = _grid_residuals(self.model, self._ws, self._grid._points()[1][k], st.pose[k], y)
            first = first or (self._grid._points()[1][k], st.pose[k], resid)
            if not np.fmax.reduce(resid) > limit or len(rejected) == 3:  # fmax: NaN (missing) never the largest
                break
            worst = int(np.nanargmax(resid))
            y = y.copy()
            y[worst] = np.nan
            rejected.append(names[worst])
            n_present -= 1
            if n_present < self._min_present:  # as in the Gaussian form: the last one cannot be told
                named = rejected[:-1]
                self._tracks.amend(lost=[names.index(n) for n in named])
                problems.append(_too_few_line(named, self.outlier_sd))
                return self._grid_estimate(None, problems, tuple(named))
        self._state = st
        if rejected:
            bad = [names.index(n) for n in rejected]
            theta, q, resid0 = first
            pair = self._swapped_pair(theta, y0, q, s2, _worst_first(resid0, bad))
            self._amend_tracks(pair, bad)
            problems.append(f"left out {', '.join(rejected)}: residual beyond {self.outlier_sd:g} noise sd "
                            "(swapped or wrong label?)")
            if pair:
                problems.insert(len(problems) - 1, _swap_line(pair))
        return self._grid_estimate(y, problems, tuple(rejected), resid=resid, lw=lw)

    def _grid_map(self, st) -> int:
        """Index of the most probable grid point of state ``st``."""
        return int(np.argmax(self._grid._log_weights(st.rss, st.logdet, st.n_obs, st.n_used)))

    def _grid_estimate(self, y, problems, rejected: tuple = (), resid=None, lw=None) -> LiveEstimate:
        """The grid form's estimate from its state (``lw``: its log weights, where already computed); frame
        ``y`` (None: not used) has the marker residuals ``resid (M,)`` at the most probable grid point, and,
        used whole, is checked against the noise (:meth:`_misfit`)."""
        model, st = self.model, self._state
        q = None
        if lw is None:
            lw = self._grid._log_weights(st.rss, st.logdet, st.n_obs, st.n_used).ravel()
        pts = self._grid._points()[1]
        w = np.exp(lw - lw.max())
        w /= w.sum()
        mean = w @ pts
        sigma = self._grid_sigma()
        k = int(np.argmax(lw))
        if st.pose is not None:
            q = st.pose[k]
            if y is not None:
                if resid is None:
                    resid = _grid_residuals(model, self._ws, pts[k], q, y)
                if np.isfinite(sigma) and not rejected:
                    problems = problems + self._misfit(resid, sigma * sigma, st.n_obs - model.n_pose * st.n_used
                                                       - model.n_params, y, q, pts[k])
        shape = self._grid_shape
        at = np.unravel_index(k, shape)
        on = None
        lines = []
        if any(i == 0 or i == n - 1 for i, n in zip(at, shape, strict=True)):  # the most probable point on an edge
            z, edge = grid_bound_z(lw.reshape(shape), at)
            on = edge != 0
            lines = _bound_lines(model, z, edge)
        problems = problems + self._notes(lines)
        healthy = not problems
        return LiveEstimate(self._frame, self._frame / self.rate, _frozen(mean), _frozen(q), sigma,
                            healthy, "ok" if healthy else "; ".join(problems), rejected, model,
                            partial(self._grid_cov, w, mean), resid, self._ranges, on,
                            self._motion_seen(y if not rejected else None, q, mean), self._targets,
                            self._noise_dof(st))

    def _grid_cov(self, w, mean) -> np.ndarray:
        """Covariance of the grid posterior with weights ``w (K,)``, plus the grid's quantisation variance
        (step^2 / 12), so that a posterior on one point still has an invertible covariance."""
        axes, pts = self._grid._points()
        d = pts - mean
        steps = np.array([np.diff(a).mean() if a.size > 1 else 0.0 for a in axes])
        return (d * w[:, None]).T @ d + np.diag(steps**2 / 12.0)

    # ------------------------------------------------------------------ the result
    def finish(self) -> LiveEstimate | None:
        """The estimate of every frame so far, as at the end of a stream (None before the first frame).

        Under the motion model the estimate holds the frames folded in again at their smoothed poses only
        (:meth:`_folded_state`): the last :data:`_BLOCK` to :data:`_BLOCK` + :data:`_LAG` frames wait for the
        frames after them. Here the block being folded in is finished, and the frames after it are folded in
        at their poses smoothed with the frames there are, their information and bias added to a copy of the
        state: the session goes on as before, and a later frame is folded in as it would have been.

        Returns
        -------
        LiveEstimate
            With the last estimate's health.
        """
        if self.estimate is None or self.method != "gaussian" or not self._blocks:
            return self.estimate
        while self._pending is not None:
            self.work()
        if len(self._block) <= _LAG:  # every frame is folded in again already
            return self.estimate
        start, frames = self._raw_open, self._block
        if self._closed is not None:
            if self._closed.correct:
                start = self._closed.start
            else:  # its frames are at their smoothed poses since the check of done: the open block's only
                frames = frames[_BLOCK:]
        with one_blas_thread():
            Lam, eta, num = finish_steps(self._refold_steps(frames, self._state.mean, self._cutoff_now,
                                                            self._motion, after=0))
        raw = self._raw()
        s2 = self._current_sigma2()
        new = add_theta_information(self._state, Lam - (raw[0] - start[0]), eta - (raw[1] - start[1]))
        if new is None or not np.isfinite(num).all():
            return self.estimate
        est = self._estimate_from(solve_mean(new, self._prior, s2, pose=False),
                                  num if self._bias_sum is None else self._bias_sum + num)
        problems = list(dict.fromkeys(h for h in (self.estimate.health, est.health) if h != "ok"))
        return dataclasses.replace(est, healthy=not problems, health="; ".join(problems) or "ok",
                                   rejected=self.estimate.rejected)

    def posterior(self) -> tuple[np.ndarray, np.ndarray]:
        """Current ``(mean (P,), cov (P, P))`` of theta (a Gaussian summary of the grid posterior)."""
        if self.method == "grid":
            st = self._state
            lw = self._grid._log_weights(st.rss, st.logdet, st.n_obs, st.n_used).ravel()
            w = np.exp(lw - lw.max())
            w /= w.sum()
            mean = w @ self._grid._points()[1]
            return mean, self._grid_cov(w, mean)
        s2 = self._current_sigma2()
        folded = self._folded_state(s2)
        return self._unbiased(folded, s2).copy(), theta_cov(folded, self._prior, s2)

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
        With the session's ``target_sd`` it is the requested parameter whose sd is the
        largest multiple of its target; once the estimate is ``done`` (every requested
        parameter identified at its target, :attr:`LiveEstimate.done`) the one piece of
        advice is "done" (``dof`` -1, no sweep).

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
        if self._targets is not None and self.estimate.done:
            return [_done_advice(model, self.estimate, self._targets)]
        worst = int(np.argmax(sd / (prior_sd if self._targets is None else self._targets)))
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


def build_kernels(model: Model, before: Callable[[], object] | None = None) -> bool:
    """Build the compiled kernels a :class:`Session` of ``model`` runs, once (numba's disk cache), and wait.

    A session keeps the path it starts on: one made while its kernels are not yet compiled runs numpy's
    for its whole life (an OpenSim leg about four times slower a frame), while they compile in the
    background for the next one. ``skelid live`` calls this first; call it before a session from Python
    on a fresh install. ``before`` is called once if anything has to be built (to say so).

    Returns
    -------
    bool
        Whether anything had to be built (False without numba or with ``SKELID_NUMBA=0``).
    """
    from skelid.estimators.fit import _lm_kernel
    from skelid.estimators.online import _live_kernel
    from skelid.model.kinematics import kinematics_plan

    if not _lm_kernel.AVAILABLE or _lm_kernel.MODE == "0":
        return False
    key = _lm_kernel.driver_key(kinematics_plan(model))
    if _lm_kernel._cached(key) and _live_kernel._cached():
        return False
    if before is not None:
        before()
    _lm_kernel.warm(key, wait=True)
    _live_kernel.warm(wait=True)
    return True


# --------------------------------------------------------------------------- the message a stream carries
def _json_number(x) -> float | None:
    """A float for JSON: None for NaN or infinity (JSON has neither)."""
    x = float(x)
    return x if math.isfinite(x) else None


def message(estimate: LiveEstimate, advice=(), stamp: float | None = None) -> dict:
    """The estimate as a ``skelid.live/1`` message: plain JSON values, the layout of docs/live-protocol.md.

    Parameters
    ----------
    estimate : LiveEstimate
    advice : sequence of Advice
        The movements to suggest, best first (:meth:`Session.advice`; the caller decides how often).
    stamp : float, optional
        The source's time stamp of the frame (an LSL time stamp, s), so that a receiver can measure the delay.

    Returns
    -------
    dict
        ``schema``, ``model``, ``units``, ``frame``, ``time``, ``stamp``, ``healthy``, ``health``,
        ``done`` (the stopping rule, :attr:`LiveEstimate.done`: null without targets), ``rejected``,
        ``sigma``, ``parameters`` (a list: ``name``, ``unit``, ``mean``, ``sd``, ``lower``,
        ``upper``, ``status``), ``joint_centres`` (a list: ``joint``, ``position`` as ``[x, y, z]``, z = 0
        for a planar model), ``advice`` (a list: ``text``, ``joint``, ``parameter``, ``sd_now``,
        ``sd_after``). A number that is not finite is ``None`` (JSON ``null``).
    """
    model = estimate._model
    params = [{"name": p.name, "unit": p.unit, "mean": _json_number(p.mean), "sd": _json_number(p.sd),
               "lower": _json_number(p.interval[0]), "upper": _json_number(p.interval[1]), "status": p.status}
              for p in estimate.parameters.values()]
    centres = []
    for joint, c in estimate.joint_centres.items():
        xyz = [_json_number(v) for v in c] + [0.0] * (3 - len(c))
        centres.append({"joint": joint, "position": xyz})
    return {"schema": SCHEMA, "model": model.name, "units": model.units, "frame": int(estimate.frame),
            "time": float(estimate.time), "stamp": None if stamp is None else _json_number(stamp),
            "healthy": bool(estimate.healthy), "health": estimate.health, "done": estimate.done,
            "rejected": list(estimate.rejected),
            "sigma": _json_number(estimate.sigma), "parameters": params, "joint_centres": centres,
            "advice": [{"text": a.text, "joint": a.joint, "parameter": a.parameter,
                        "sd_now": _json_number(a.sd_now), "sd_after": _json_number(a.sd_after)} for a in advice]}


def run(session: Session, frames, sinks=(), max_frames: int | None = None, advice_every: int | None = None,
        n_advice: int = 3, until_done: bool = False) -> LiveEstimate | None:
    """Run ``session`` over ``frames`` (any iterable, such as an LSL stream) and send each estimate to ``sinks``.

    Parameters
    ----------
    session : Session
    frames : iterable
        Frames as :meth:`Session.push` takes them. Where it has an attribute ``last_stamp`` (the
        source's time stamp of the frame it yielded last), each message carries it.
    sinks : sequence
        Objects with ``send(message: dict)`` (:mod:`skelid.io.stream`: LSL, UDP, a JSON Lines file).
    max_frames : int, optional
        Stop after this many frames.
    advice_every : int, optional
        Frames between two calls of :meth:`Session.advice` (each message carries the latest);
        default one second of frames. 0: no advice.
    n_advice : int
        Movements in each message, best first.
    until_done : bool
        Stop at the first estimate that is ``done`` (the session's ``target_sd``), whose message
        carries the "done" advice.

    Returns
    -------
    LiveEstimate or None
        The last estimate (None if no frame came).
    """
    every = max(1, round(session.rate)) if advice_every is None else int(advice_every)
    advice: list = []
    est = None
    for n, est in enumerate(session.feed(frames, max_frames=max_frames)):
        done = until_done and bool(est.done)
        if done or (every and n % every == 0):
            advice = session.advice()[:n_advice]
        if sinks:
            msg = message(est, advice, getattr(frames, "last_stamp", None))
            for sink in sinks:
                sink.send(msg)
        if done:
            break
    return est


class _FramePose:
    """One frame's pose fit at one ``theta``: :func:`~skelid.estimators.fit.pose.fit_pose` with ``n_iter=10``.

    On the compiled path the kernel is called directly with the session's own
    batch-of-one buffers (the same call and arguments as ``fit_pose`` makes, so
    the same numbers), without the general wrapper's broadcasting and
    re-layout of every argument per frame; otherwise ``fit_pose`` itself.
    """

    def __init__(self, model: Model, ws: Workspace):
        self.model, self.ws = model, ws
        self.tables = _kernel_tables(ws)
        if self.tables is not None:
            plan = ws.plan
            self.yT = np.empty((plan.n_markers, plan.dim, 1))
            self.wT = np.empty((plan.n_markers, 1))
            self.qT = np.empty((plan.n_pose, 1))
            self.gT = np.empty((geometry(model, model.theta_center).size, 1))
            self.no_tilts = _lm_kernel.no_tilts(1)

    def __call__(self, theta, y, q0, n_iter: int = 10) -> np.ndarray:
        """Pose ``(Q,)`` fitted to ``y (M, D)`` (NaN where missing) from ``q0 (Q,)``."""
        if self.tables is None:
            return fit_pose(self.model, theta, y, q0, n_iter=n_iter, ws=self.ws)[0]
        plan = self.ws.plan
        mask = np.isfinite(y).all(axis=-1)
        self.yT[..., 0] = np.where(mask[:, None], y, 0.0)
        self.wT[:, 0] = mask
        self.qT[:, 0] = q0
        self.gT[:, 0] = geometry(self.model, theta)
        tilt = tilt_tables(self.model, theta)
        tilts = self.no_tilts if tilt is None else _tilts_batch_last(tilt, ())
        _lm_kernel.lm_fit(self.gT, self.yT, self.wT, self.qT, int(n_iter), 1e-10, 1e-3, False, plan.dim,
                          plan.n_segments, plan.n_markers, tilts, *self.tables)
        return self.qT[:, 0].copy()


class _Linearise:
    """One frame's ``x (M, D)``, ``dx/dq (M, D, Q)`` and ``dx/dtheta (M, D, P)`` at ``(theta, q)``.

    :func:`~skelid.model.kinematics.marker_jacobian`, or its compiled form
    (:func:`skelid.estimators.online._live_kernel.linearise`, equal to rounding) where
    the session's pose fits take the compiled path, the model is one it covers
    and it is compiled already (decided once, so a session keeps one path).
    """

    def __init__(self, model: Model, ws: Workspace):
        self.model, self.ws = model, ws
        self.tables = _live_kernel.tables(ws) if ws.compiled and _live_kernel.ready() else None
        if self.tables is not None:
            self.gT = np.empty((geometry(model, model.theta_center).size, 1))
            self.qT = np.empty((model.n_pose, 1))

    def __call__(self, theta, q):
        if self.tables is None:
            return marker_jacobian(self.model, theta, q, self.ws)
        self.gT[:, 0] = geometry(self.model, theta)
        self.qT[:, 0] = q
        return _live_kernel.linearise(self.gT, self.qT, *self.tables)


class _Step:
    """The Gaussian form's whole frame in one compiled call (:func:`skelid.estimators.online._live_kernel.step`).

    The same pose fit, screening, update and mean as the general path of
    :meth:`Session._push_gaussian` (equal to rounding); a frame with a marker
    beyond the outlier limit, or whose pose jumps beyond the motion model, is
    handed back (None) to the general path, which leaves it out.
    """

    def __init__(self, session: Session):
        self.session = session
        model = session.model
        g_base, A = model.geometry_map
        mu0, L0, lo, hi = session._prior
        sigma = -1.0 if session.sigma is None else float(session.sigma)
        self.settings = (np.ascontiguousarray(session._weight, dtype=float), int(session.n_iter), sigma,
                         float(session._sigma_fallback),
                         float(session._sigma_floor))
        self.model_args = (np.ascontiguousarray(session._rot, dtype=np.bool_),
                           *(np.ascontiguousarray(a, dtype=float) for a in (mu0, L0, lo, hi, g_base, A)),
                           *session._linearise.tables)
        self.limit_scale = session.outlier_sd * math.sqrt(model.dim)

    def __call__(self, y, st: GaussianState, s2: float, n_present: int) -> LiveEstimate | None:
        ses = self.session
        known = ses._noise_known(st)
        limit = self.limit_scale * math.sqrt(s2) if known else math.inf
        weight, n_iter, sigma, fallback, floor = self.settings
        (status, root, rhs, mean, pose_mean, poses, hdiag, rss, n_obs, n_used, q,
         resid, jump) = _live_kernel.step(y, ses._predict(st), st.mean, np.ascontiguousarray(st.root), st.rhs,
                                          st.poses, st.hdiag, float(st.rss), int(st.n_obs), int(st.n_used), weight,
                                          n_iter, sigma, fallback, floor, limit, float(s2), ses._gate(st),
                                          ses._allowance(), *self.model_args)
        if status >= 0:
            return None  # the general path leaves out what does not fit (and records the jump itself)
        if jump >= 0.0:
            ses._note_jump(st, q)
        ses._good = q
        ses._state = GaussianState(root, rhs, mean, poses, pose_mean, hdiag, rss, n_obs, n_used)
        ses._gap = 0
        ses._run += 1
        if ses._remember(y, q, True):
            ses._relinearise(mean)
        problems = [] if n_present == ses._M else [f"{ses._M - n_present} marker(s) missing"]
        return ses._gaussian_estimate(resid, problems, (), used=True, y=y, q=q)


def _pieces(model: Model, T: int) -> list[slice]:
    """Frames ``0..T-1`` in pieces for :meth:`Session._bias_sum_of` (:data:`_BIAS_COST`; at least 25 frames each,
    as even as may be)."""
    size = max(25, _BIAS_COST // (model.n_params + model.n_pose) ** 2)
    edges = np.linspace(0, T, -(-T // size) + 1).astype(int)
    return [slice(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def _live_part(states) -> GaussianState:
    """The state after every frame, from :func:`relinearise`'s answer with or without ``split``."""
    return states if isinstance(states, GaussianState) else states[0]


def _for_all(cutoffs) -> np.ndarray:
    """The live choice from per-coordinate cutoffs: the highest, for every coordinate.

    The batch method keeps one cutoff per coordinate: it has seen the whole
    movement. A live session chooses from the frames so far, and the movement to
    come may be another joint's: a coordinate still in the last window gets the
    least cutoff, and its next sweep would be smoothed away. On the simulated
    calibration sessions of ``benchmarks/speed.py --only advice`` per-coordinate
    cutoffs took 434 frames on average against 230 with the highest for all (8
    sessions); on trials whose movement does not change they agree better with
    the batch estimate (see ``benchmarks/live_agreement.py``).
    """
    c = np.asarray(cutoffs, dtype=float)
    return np.full_like(c, c.max())


def _grid_residuals(model, ws, theta, q, y) -> np.ndarray:
    """Distance ``(M,)`` of each observed marker ``y (M, D)`` from the model at ``theta, q`` (NaN where missing)."""
    d = y - marker_positions(model, theta, q, ws)
    return np.sqrt((d * d).sum(axis=-1))


def _sweeps(model: Model, q_now, amplitudes_deg, n_frames):
    """Candidate sweeps ``[(dof, lo_deg, hi_deg)]`` and their poses ``[(n_frames, Q)]``."""
    from skelid.estimators.fit.pose import _rotation_ranges

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


@lru_cache(maxsize=256)
def _chi2_limit(dof: int, p_value: float = 1e-4) -> float:
    """The ``1 - p_value`` quantile of chi-square on ``dof`` degrees of freedom."""
    return float(chi2.isf(p_value, dof))


def _worst_first(resid, first, n: int = 4) -> list[int]:
    """Marker indices to try in a swap: ``first`` (the markers left out), then the largest residuals, at most
    ``n + len(first)``."""
    r = np.where(np.isfinite(resid), resid, -np.inf)
    rest = [int(k) for k in np.argsort(-r) if int(k) not in first and np.isfinite(r[k])]
    return list(first) + rest[:n]


def _swap_line(pair) -> str:
    return f"labels {pair[0]} and {pair[1]} look swapped (swapped back, every marker fits)"


def _too_few_line(named, outlier_sd: float) -> str:
    """The problem line of a frame whose screen ran out of markers: ``named`` were left out while enough
    remained to single them out; the marker that would have left too few cannot be told from the others
    (taking any one of them out leaves the rest fitting), so none is blamed for what remains."""
    if named:
        return (f"left out {', '.join(named)} (residual beyond {outlier_sd:g} sd); the rest still misfit and too "
                "few markers remain to tell which: frame not used")
    return (f"residuals beyond {outlier_sd:g} noise sd that no one marker can be blamed for (without any one "
            "of them too few markers remain to fix the pose): frame not used")


def _unit(model: Model, p) -> str:
    """The unit of parameter ``p``: degrees for a tilt, 1 for a scale factor, else the model's length unit."""
    return "deg" if p.kind == "axis_direction" else "1" if p.kind == "scale" else model.units


def _bound_lines(model: Model, z, edge) -> list[str]:
    """A line for each parameter pressed against its prior's bound: ``z (P,)`` sd beyond it
    (:func:`~skelid.live_health.gaussian_bound_z`, :func:`~skelid.live_health.grid_bound_z`) at least
    :data:`~skelid.live_health.BOUND_Z`, on the bound ``edge (P,)`` (-1 lower, 1 upper)."""
    out = []
    for k in np.flatnonzero(z >= BOUND_Z):
        p = model.parameters[k]
        side, bound = ("lower", p.prior.lower) if edge[k] < 0 else ("upper", p.prior.upper)
        far = "beyond it, further than the grid shows" if math.isinf(z[k]) else f"{z[k]:.3g} sd beyond it"
        out.append(f"{p.name} sits on its prior's {side} bound {bound:g} {_unit(model, p)} (the data put it {far}): "
                   "check the stream's units and the model")
    return out


#: how the scale finding names a stream unit
_UNIT_WORDS = {"mm": "millimetres", "cm": "centimetres", "m": "metres", "in": "inches"}


def _scale_words(scale, declared: str) -> str:
    """The finding of :meth:`~skelid.live_health.ScaleCheck.check` in words: how far off, and the likely unit."""
    lo, hi = (1.0 / scale.high, 1.0 / scale.low) if scale.high < 1.0 else (scale.low, scale.high)
    how = _times(lo) if hi == lo else f"{_times(lo)}-{_times(hi)}"
    how += " times closer together" if scale.high < 1.0 else " times farther apart"
    basis = "distances within its rigid segments" if scale.rigid else "their spread over the poses it allows"
    text = f"the markers lie {how} than the model puts them ({basis})"
    if scale.unit is None:
        return text + ": wrong units or wrong model?"
    f = scale.factor if scale.factor >= 1 else 1.0 / scale.factor
    fix = "convert it to mm, cm or m" if scale.unit == "in" else f"give units={scale.unit!r}"
    return (text + f": the stream looks to be in {_UNIT_WORDS[scale.unit]}, not {declared} (units off by a factor "
            f"{f:.4g}); {fix}")


def _times(v: float) -> str:
    """A factor in a few digits: 2.5, 14, 680."""
    return f"{v:.2g}" if v < 10 else f"{v:.0f}"


def _window_linearise(model: Model, ws: Workspace, theta, q):
    """Marker positions ``(T, M, D)`` and their pose Jacobian ``(T, M, D, Q)`` at ``theta (P,)`` and the poses
    ``q (T, Q)`` (the misfit window's frames, when its markers are left out in turn)."""
    x, Jq, _ = marker_jacobian(model, theta, q, ws)
    return x, Jq


def _coordinates(value, what: str) -> np.ndarray:
    """``value`` as a float array, or one line saying it is not real numbers (text, numbers written as text,
    complex numbers, anything numpy cannot make a float of)."""
    if isinstance(value, str | bytes):
        raise DataError(f"{what} is the text {value[:20]!r}, not coordinates",
                        "send numbers: (x, y, z) per marker")
    fix = "send real numbers: (x, y, z) per marker, NaN for a missing one"
    try:
        a = np.asarray(value)
    except (TypeError, ValueError):
        raise DataError(f"{what} is not numbers: {str(value)[:40]!r}", fix) from None
    if a.dtype.kind == "O":  # mixed or ragged: numbers written as text or complex numbers hide in here
        flat = a.ravel()
        if any(isinstance(v, str | bytes | complex | np.complexfloating) for v in flat):
            raise DataError(f"{what} is not real numbers: {str(value)[:40]!r}", fix)
    if a.dtype.kind in "USbc":
        kind = {"c": "complex numbers", "b": "true/false values"}.get(a.dtype.kind, "text")
        raise DataError(f"{what} holds {kind}, not coordinates: {str(value)[:40]!r}", fix)
    try:
        return a.astype(float, copy=False)
    except (TypeError, ValueError):
        raise DataError(f"{what} is not numbers: {str(value)[:40]!r}", fix) from None


def _missing(y) -> list[str]:
    """The frame's problem line for markers without a position (none when every marker is there)."""
    n = int((~np.isfinite(y).all(axis=-1)).sum())
    return [f"{n} marker(s) missing"] if n else []
