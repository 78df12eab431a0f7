"""The marker-space estimator: joint fit, bias removed, CRLB, sigma, honest interval.

Model: marker ``m`` in frame ``t`` is seen at

.. math:: y_{tm} = f_m(\\theta, q_t) + \\varepsilon_{tm}, \\qquad \\varepsilon_{tm} \\sim N(0, \\sigma^2 I_D),

with geometry ``theta (P,)`` shared by all frames and a pose ``q_t (Q,)`` per frame; the
motion model penalises rough poses, so the estimate is

.. math:: (\\hat\\theta, \\hat q) = \\arg\\min \\sum_{t,m} \\lVert y_{tm} - f_m(\\theta, q_t) \\rVert^2
          + q^\\top R\\, q .

Steps (see :mod:`skelid.estimators.fit.joint` for the equations):

1. poses tracked at the prior centre, then joint least squares over ``theta``
   and every pose (Levenberg-Marquardt with the Schur complement);
2. noise level ``sigma^2 = RSS / (n_obs - Q T - P)`` with a chi-square interval,
   or the user's value;
3. second-order (Box) bias computed at the estimate and subtracted;
4. covariance ``sigma^2 S^{-1}`` (the Cramér-Rao bound at the estimate), or,
   when the residuals are serially correlated as soft-tissue artefact makes
   them, a Newey-West covariance that is at least as wide;
5. identifiability from the spectrum of the (prior-scaled) efficient information.

A normal prior on a parameter is combined with the data's Gaussian
approximation (precision-weighted); uniform priors only bound the search.

Example
-------
>>> import numpy as np
>>> from skelid.simulate import builtin_model, simulate
>>> model = builtin_model("case-a")
>>> trial = simulate(model, n_frames=80, sigma=5.0, rng=np.random.default_rng(0))
>>> r = MarkerEstimator(model, rng=0).fit(trial.data).result()
>>> abs(r.parameters["L2"].mean - 250.0) < 4 * r.parameters["L2"].sd + 1.0
True
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np
from scipy.stats import chi2

from skelid._linalg import one_blas_thread
from skelid._stop import interruptible
from skelid.data import MarkerData, unit_scale
from skelid.errors import ConvergenceError, DataError, IdentifiabilityError, ModelError, SettingError, SkelidError
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
    fit_origin,
    make_rng,
    marker_array,
    move_root,
    non_negative_or_none,
    one_of,
    positive_or_none,
)
from skelid.estimators.checks.artefact import artefact_covariance
from skelid.estimators.checks.misfit import (
    DEFAULT_PLACEMENT_SD_MM,
    PLACEMENT_SHARE,
    STILL_JOINT_DEG,
    model_misfit,
    placement_information,
    relaxed_estimate,
)
from skelid.estimators.checks.noise import marker_groups, per_marker_fit
from skelid.estimators.fit.joint import (
    JointFit,
    box_bias,
    choose_cutoffs,
    frame_scores,
    joint_fit,
    lag1_autocorrelation,
    newey_west,
    row_weights,
    smoothed_bias,
    smoothed_frame_scores,
    usable_frames,
    weighted_terms,
)
from skelid.estimators.fit.likelihood import crlb_sd, efficient_information, frame_terms, pose_fixed
from skelid.estimators.fit.pose import track_poses, workspace
from skelid.estimators.uncertainty.bootstrap import Draws, as_draws, draws_bias, linear_response
from skelid.estimators.uncertainty.jackknife import jackknife_stage
from skelid.estimators.uncertainty.posterior import GaussianPosterior
from skelid.estimators.uncertainty.singular import (
    N_DRAWS,
    POSE_SENSITIVE,
    PROFILE_CHECK,
    SECOND_ORDER_SPREAD,
    assigned_branch_start,
    branch_joints,
    branch_settled,
    expansion_consistent,
    fallback_covariance,
    indirect_bias,
    keeps_near_singular,
    mirrored_start,
    pose_check,
    profile_covariance,
    profile_sd_ratio,
    quadratic_term_draws,
    second_order_covariance,
)
from skelid.model.description import Model
from skelid.model.kinds import PARAMETER_TARGET
from skelid.model.kinematics import Workspace, joint_distances, marker_positions
from skelid.result import FitResult, NoiseEstimate, Warning

NUMERICAL_RESIDUAL = 1e-6  # residual rms, relative to the model's size, that is only rounding
STA_AUTOCORRELATION = 0.25  # mean lag-1 residual autocorrelation that flags soft-tissue artefact
MIN_AUTO_CUTOFF = 6.0  # Hz: the usual low-pass cutoff for marker data; raised for faster motion
MOTION_MIN_FRAMES = 3  # the motion model penalises second differences of the poses
STIFFER = 3.0  # the motion model's cutoff is divided by this for the graduated-smoothing start
STIFF_ITER = 10  # iterations of that start: it only has to reach the right pose branch
BIAS_RELIABLE = 1.5  # a second-order bias correction above this many sd is not trusted: bootstrap instead
CONVERGED_SD = 0.25  # an unconverged fit whose estimate still moves by more than this many sd fails
CONTINUE_ROUNDS = 2  # ... after this many continuations of n_iter iterations each
SCREEN_STEP_TOL = 1e-2  # the screening fit (no motion model) stops at steps below this many sd ...
SCREEN_TOL = 1e-5  # ... that lower its cost by less than this fraction
BOOT_STEP_TOL = 1e-2  # a bootstrap refit stops at steps below this many sd ...
# ... that lower its cost by less than this fraction. Case A, sigma 15 mm, 10^4 frames, 4 refits: these
# stop 0.01 sd (at most 0.03 sd) from the converged value in 8 iterations; 1e-3 / 1e-7 stopped 0.005 sd
# (at most 0.02) away in 13. The bootstrap's Monte Carlo error is 0.2 sd; at 10^3 frames both stop alike
BOOT_TOL = 1e-5
# refits of the parametric bootstrap: with the linear control variate the bias's Monte Carlo error is
# sd(s - l) / sqrt(3), about 0.2 sd on case A (sigma 15 mm, 10^3-10^4 frames); ten plain refits gave 0.3-0.4 sd
N_BOOT = 3
# the motion-model fit stops at steps below this many sd: its stopping point already moves by about 2e-5 sd
# when the Jacobians change at the rounding level, so a tighter rule only buys iterations
FIT_STEP_TOL = 1e-4
RACE_ITER = 10  # iterations each start of the motion-model fit gets before the better one is continued
N_STARTS = 9  # starting geometries under 'auto' where a joint has two pose branches: the centre and 8 more
SEARCH_MARGIN = 0.05  # those starts keep this share of each prior interval from either bound
SEARCH_DISTINCT = 0.01  # screening fits that end closer than this share of the prior's width are one
#: at most this many branch joints get the starts with every joint's side given (2^J motion-model fits)
MAX_ASSIGNED_JOINTS = 3
MODE_RATIO = 0.05  # another minimum whose likelihood is at least this share of the best's is held in the interval
MODE_SD = 2.0  # ... where it lies more than this many sd from the estimate
#: a parameter whose sd exceeds this fraction of its prior width is poorly identified (CRLB or final sd)
POOR_FRACTION = 0.25
Z95 = 1.959964  # two-sided 95 % normal quantile


def frame_counts(model: Model, y, used=None) -> dict:
    """Per-frame counting: independent coordinates against pose coordinates.

    A frame with ``m`` markers present gives ``m D`` coordinates and costs ``Q``
    pose coordinates; only the surplus ``m D - Q`` can inform ``theta``. Over
    the trial the surplus must exceed ``P``.

    Parameters
    ----------
    y : (T, M, D) float
        Markers, NaN where missing.
    used : (T,) bool, optional
        Frames that entered the fit.
    """
    n = np.isfinite(y).all(axis=-1).sum(axis=-1) * model.dim
    used = usable_frames(model, y) if used is None else np.asarray(used, bool)
    surplus = n - model.n_pose

    def stats(v):
        return {"min": int(v.min()), "median": float(np.median(v)), "max": int(v.max())} if v.size \
            else {"min": 0, "median": 0.0, "max": 0}

    return {
        "pose_coordinates_per_frame": model.n_pose,
        "marker_coordinates_per_frame": stats(n),
        "surplus_per_frame": stats(surplus),
        "frames_with_no_surplus": int((surplus <= 0).sum()),
        "frames_used": int(used.sum()),
        "surplus_total": int(surplus[used].sum()),
        "parameters": model.n_params,
    }


def joint_motion(model: Model, pose, used=None) -> dict:
    """Range of every joint rotation but the root's (degrees; central 95 % of the frames).

    One-axis joints: the angle about its circular mean (2.5 to 97.5 percentile);
    multi-axis joints of a 3-D model: the rotation angle from the mean rotation
    (:func:`skelid.estimators.checks.misfit.joint_ranges`), free of gimbal artefacts.

    Functional information about a joint (its centre, its axis) comes only
    from the joint moving; a range of a few degrees means little information.
    """
    from skelid.estimators.checks.misfit import joint_ranges

    return joint_ranges(model, pose, used)


def identifiability(model: Model, info: np.ndarray, sigma: float, rel_tol: float = 1e-9,
                    y=None, pose=None, used=None) -> dict:
    """Which parameters (and combinations) the data inform.

    Parameters are scaled by their prior width so that the spectrum is unit-free.
    A direction whose scaled information is below ``rel_tol`` times the largest
    is unidentifiable; a parameter whose bound exceeds a quarter of its prior
    width is poorly identified.

    Parameters
    ----------
    info : (P, P) float
        Efficient information for unit noise.
    sigma : float
        Noise standard deviation.
    y : (T, M, D) float, optional
        Markers, for the per-frame counting.
    pose : (T, Q) float, optional
        Fitted poses, for the joints' range of motion.
    used : (T,) bool, optional
        Frames that entered the fit.

    Returns
    -------
    dict with ``table`` (one row per parameter), ``null`` (unidentifiable
    combinations as ``{name: coefficient}``), and with ``y``/``pose`` given,
    ``counting`` (:func:`frame_counts`) and ``joint_range_deg`` (:func:`joint_motion`).
    """
    width = np.array([p.prior.upper - p.prior.lower for p in model.parameters])
    scaled = info * np.outer(width, width)
    w, V = np.linalg.eigh(scaled)
    top = max(w.max(), 1e-300)
    null = []
    for k in np.flatnonzero(w <= rel_tol * top):
        v = V[:, k]
        v = v / np.abs(v).max()
        null.append({n: round(float(c), 3) for n, c in zip(model.parameter_names, v, strict=True)
                     if abs(c) > 1e-3})
    sd = np.full(model.n_params, np.nan)
    if not null:
        try:
            sd = np.sqrt(np.clip(np.diag(np.linalg.inv(info)), 0, None)) * sigma
        except np.linalg.LinAlgError:
            pass
    in_null = np.zeros(model.n_params, bool)
    for comb in null:
        for n in comb:
            in_null[model.parameter_names.index(n)] = True
    table = []
    for k, p in enumerate(model.parameters):
        status = "unidentifiable" if in_null[k] else ("poor" if sd[k] > POOR_FRACTION * width[k] else "identified")
        table.append({"parameter": p.name, "crlb_sd": None if not np.isfinite(sd[k]) else float(sd[k]),
                      "status": status})
    out = {"table": table, "null": null,
           "condition": float(w.max() / max(w.min(), 1e-300)) if w.size else 1.0}
    if y is not None:
        out["counting"] = frame_counts(model, y, used)
    if pose is not None:
        out["joint_range_deg"] = joint_motion(model, pose, used)
    return out


def null_message(model: Model, null: list[dict]) -> str:
    """The unidentifiable combinations in words."""
    parts = []
    for comb in null:
        if len(comb) == 1:
            parts.append(f"{next(iter(comb))} (no information about it at all)")
        else:
            parts.append(" + ".join(f"{c:g}*{n}" for n, c in comb.items()))
    return "; ".join(parts)


# ============================================================================ stage values
class Start(NamedTuple):
    """What the fit starts from: markers, rate, starting geometry and poses, frames whose pose is fixed."""

    y: np.ndarray  # (T, M, D) markers, model order and units
    rate: float
    theta0: np.ndarray  # (P,)
    pose0: np.ndarray  # (T, Q)
    bounds: tuple  # ((P,), (P,)) prior bounds
    fixed: np.ndarray  # (T,) bool: the frame's markers fix every pose coordinate


class Screen(NamedTuple):
    """A first fit without motion model, and the glitched marker positions it left out."""

    y: np.ndarray  # (T, M, D) with outliers NaN
    fit: JointFit
    fixed: np.ndarray  # (T,) bool
    outliers: np.ndarray  # (T, M) bool
    others: tuple = ()  # other starting geometries and their tracked poses (:func:`other_starts`)


class Motion(NamedTuple):
    """The joint fit with the motion model (or the screening fit without one)."""

    fit: JointFit
    cutoff: float | np.ndarray | None  # Hz, per pose coordinate under 'auto'
    #: each settled fit of the race from other starting geometries: (theta (P,), penalised cost)
    minima: tuple = ()


class Modes(NamedTuple):
    """Other minima whose likelihood is close to the estimate's, and what holding them adds."""

    cov: np.ndarray  # (P, P) added to the covariance
    kept: tuple  # ({"theta": [...], "ratio": r}, ...) each minimum held, with its likelihood ratio


class Weights(NamedTuple):
    """Per-marker noise levels and the fit weighted by them (``noise='per_marker'``), or the fit as it is."""

    fit: JointFit
    weights: np.ndarray | None  # (M,) sigma^2 / sigma_m^2
    marker_sigma: np.ndarray | None  # (M,)
    marker_dof: np.ndarray | None  # (M,)


class Frames(NamedTuple):
    used: np.ndarray  # (T,) bool
    skipped: dict  # reason -> count


class Noise(NamedTuple):
    sigma: float
    interval: np.ndarray  # (2,)
    dof: float


class Residuals(NamedTuple):
    """Residual structure: distances, serial correlation, and the white noise level."""

    distance: np.ndarray  # (T, M), NaN in frames not used
    sta_score: float  # mean lag-1 autocorrelation of the residual coordinates
    flagged: bool  # correlated beyond STA_AUTOCORRELATION and above the rounding level
    sigma_white: float
    misfit: dict  # joint -> angle-driven residual pattern shared by its segment's markers (checks.model_misfit)


class Bias(NamedTuple):
    bias: np.ndarray  # (P,)
    method: str
    fallback: dict | None = None  # the second-order bias that was too large to trust, and the bootstrap's
    cov: np.ndarray | float = 0.0  # (P, P) added to the interval: the bootstrap's spread beyond sigma^2 S^-1


class Covariance(NamedTuple):
    info_inv: np.ndarray  # (P, P) S^{-1}
    plain: np.ndarray  # sigma^2 S^{-1}
    data: np.ndarray  # plain, or Newey-West widened, plus the artefact term
    artefact: np.ndarray  # (P, P)
    widened: bool
    crlb_sd: np.ndarray  # (P,) with every pose free
    crlb_motion_sd: np.ndarray  # (P,) with the motion model
    jackknife: dict  # leave-one-marker-out summary (jackknife.jackknife_stage)
    placement: dict  # where the information comes from, and the placement term added
    information: np.ndarray | None = None  # (P, P) efficient information of crlb_sd (several trials add it up)
    # (P, P) the part of ``data`` from the markers' disagreement (jackknife) and their placement: errors of
    # the marker set on the body, which every trial recorded with it shares
    shared: np.ndarray | None = None


class Estimate(NamedTuple):
    theta: np.ndarray  # (P,) bias-corrected, normal priors combined
    cov: np.ndarray  # (P, P)


class Misfit(NamedTuple):
    """Joints flagged as model misfit, their refits with a relaxed joint, and the widened estimate."""

    joints: dict  # joint -> remedy, the relaxed model's estimate and interval, parameters widened
    estimate: Estimate  # the estimate after widening (the input one when nothing is flagged)


class Summary(NamedTuple):
    """Diagnostics decided from the values: final identifiability rows, still joints, lengths."""

    table: list  # identifiability rows with the final sd and status
    still: list  # joints that barely moved
    lengths: dict  # derived joint-to-joint lengths


class MarkerFit(NamedTuple):
    """Every stage's value of one marker fit (see :meth:`MarkerEstimator.fit`)."""

    start: Start
    screen: Screen
    motion: Motion
    weights: Weights
    frames: Frames
    noise: Noise
    ident: dict
    pinned: np.ndarray  # (P,) bool: the profile estimate sits on a prior bound
    residuals: Residuals
    bias: Bias
    cov: Covariance
    estimate: Estimate
    summary: Summary
    pose_path: str = "numpy"  # "compiled" or "numpy": the path every pose fit took (see pose.workspace)
    misfit: Misfit | None = None  # model misfit: refits and widening (misfit_stage)
    beyond: np.ndarray | None = None  # (P,) the unbounded estimate where support_stage put it on a bound, else NaN
    origin: np.ndarray | None = None  # (D,) where the stages put the origin: their data and poses are less it
    modes: Modes | None = None  # other minima that fit almost as well (modes_stage)


# ================================================================================ stages
def start_stage(model: Model, y, rate, s: MarkerEstimator, rng, ws: Workspace | None = None,
                origin=None) -> Start:
    """Starting geometry and poses; which frames' markers fix the pose.

    ``y`` is the data less ``origin (D,)`` (:func:`~skelid.estimators.base.fit_origin`; None: not
    moved); the ``pose0`` setting, in the data's frame, is moved with them.
    """
    if model.n_params == 0:
        raise IdentifiabilityError(f"model {model.name!r} has no [[parameters]] to estimate",
                                   "add a [[parameters]] table")
    theta0 = model.theta_center if s.theta0 is None else np.asarray(s.theta0, float)
    if theta0.shape != (model.n_params,):
        raise SettingError(f"{type(s).__name__} setting theta0 of shape {theta0.shape} does not fit model "
                           f"{model.name!r}", f"give {model.n_params} starting values, one per parameter "
                           f"{list(model.parameter_names)}, or None")
    bounds = (np.array([p.prior.lower for p in model.parameters]),
              np.array([p.prior.upper for p in model.parameters]))
    pose0 = s.pose0
    if pose0 is not None and np.shape(pose0) != (len(y), model.n_pose):
        raise SettingError(f"{type(s).__name__} setting pose0 of shape {np.shape(pose0)} does not fit these data "
                           f"({len(y)} frames) and model {model.name!r} ({model.n_pose} pose coordinates)",
                           f"give ({len(y)}, {model.n_pose}) starting poses, or None")
    if pose0 is not None and origin is not None:
        pose0 = move_root(model, pose0, -np.asarray(origin, float))
    if pose0 is None:
        stride = max(1, int(rate // 25))  # track at about 25 Hz, interpolate between
        pose0, _ = track_poses(model, theta0, y, rng, stride=stride, ws=ws)
    pose0 = np.asarray(pose0, float)
    _, Jq0, _ = frame_terms(model, theta0, pose0, y, ws)
    fixed = pose_fixed(Jq0)
    if not fixed.any():
        raise IdentifiabilityError(
            f"no frame's markers fix the pose of model {model.name!r}: "
            f"{_undetermined(model, Jq0, y)} cannot be seen from the markers",
            "add a marker on that segment or use a joint with fewer axes (hinge, universal)")
    return Start(y, float(rate), theta0, pose0, bounds, fixed)


def search_starts(bounds, n: int) -> np.ndarray:
    """``n`` starting geometries spread over the prior's ``bounds`` (``(lower (P,), upper (P,))``), ``(n, P)``.

    A Latin hypercube with each stratum's centre (deterministic: the same starts for every fit of the
    model), over the central ``1 - 2 SEARCH_MARGIN`` of each parameter's interval.
    """
    from scipy.stats import qmc

    lo, hi = (np.asarray(b, float) for b in bounds)
    u = qmc.LatinHypercube(d=len(lo), scramble=False, seed=0).random(n)
    return lo + (hi - lo) * (SEARCH_MARGIN + (1.0 - 2.0 * SEARCH_MARGIN) * u)


def other_starts(model: Model, st: Start, s: MarkerEstimator, y, fixed, first: JointFit,
                 ws: Workspace | None = None) -> tuple[tuple[np.ndarray, np.ndarray, JointFit], ...]:
    """Screening fits from other starting geometries, for the motion-model fit to race against the first.

    The joint fit is a local descent, and on some geometries (markers across a joint nearly in line
    over a whole trial: each pose has two branches there) its cost has more than one minimum; from the
    prior's centre it can settle tens of sd from the truth with an interval that looks sharp. With
    neither ``theta0`` nor ``pose0`` given, ``n - 1`` geometries spread over the prior's bounds
    (:func:`search_starts`; ``n = n_starts``, under ``'auto'`` ``N_STARTS`` where some joint's pose has
    two branches, :func:`skelid.estimators.uncertainty.singular.branch_joints`, else 1) each get poses
    tracked for them (from a generator of their own, so the fit's random numbers are unchanged) and a
    screening fit. Where that fit ends elsewhere than
    ``first`` and the others (by more than ``SEARCH_DISTINCT`` of the prior's width in some parameter),
    the start (geometry and tracked poses, which keep to one branch) and its screening fit are returned.
    Without the motion model a wrong branch in each frame can fit the markers better than the right
    geometry does, so the screening fits' residuals do not decide: the motion-model fit's penalised
    cost does, from the start and from the screening fit as the first start's (:func:`motion_stage`).
    """
    n = (N_STARTS if branch_joints(model) else 1) if s.n_starts == "auto" else s.n_starts
    if n <= 1 or s.theta0 is not None or s.pose0 is not None:
        return ()
    width = np.maximum(st.bounds[1] - st.bounds[0], 1e-300)
    stride = max(1, int(st.rate // 25))
    found, out = [first.theta], []
    for k, theta in enumerate(search_starts(st.bounds, n - 1)):
        try:
            pose, _ = track_poses(model, theta, y, np.random.default_rng(k), stride=stride, ws=ws)
            fit = joint_fit(model, y, theta, pose, n_iter=s.n_iter, bounds=st.bounds, frames=fixed,
                            tol=SCREEN_TOL, step_tol=SCREEN_STEP_TOL, ws=ws, summary=False)
        except SkelidError:  # a start the markers cannot be tracked from
            continue
        if all(np.any(np.abs(fit.theta - t) > SEARCH_DISTINCT * width) for t in found):
            found.append(fit.theta)
            out.append((theta, pose, fit))
    return tuple(out)


def screen_stage(model: Model, st: Start, s: MarkerEstimator, ws: Workspace | None = None) -> Screen:
    """Fit without motion model (a smoother would spread a glitch over its neighbours); leave out glitches."""
    y, fixed = st.y, st.fixed
    fit = joint_fit(model, y, st.theta0, st.pose0, n_iter=s.n_iter, bounds=st.bounds, frames=fixed,
                    tol=SCREEN_TOL, step_tol=SCREEN_STEP_TOL, ws=ws)
    out = np.zeros(y.shape[:2], dtype=bool)
    if s.outlier_threshold is not None:
        found = _outlying_markers(model, y, fit, s.outlier_threshold, ws=ws)
        if found.any():  # drop them (they become missing, not replaced) and fit again
            out = found
            y = np.where(out[..., None], np.nan, y)
            _, Jq0, _ = frame_terms(model, fit.theta, fit.pose, y, ws)
            fixed = pose_fixed(Jq0)
            fit = joint_fit(model, y, fit.theta, fit.pose, n_iter=s.n_iter, bounds=st.bounds, frames=fixed,
                            tol=SCREEN_TOL, step_tol=SCREEN_STEP_TOL, ws=ws)
    return Screen(y, fit, fixed, out, other_starts(model, st, s, y, fixed, fit, ws))


def motion_stage(model: Model, st: Start, sc: Screen, s: MarkerEstimator, ws: Workspace | None = None) -> Motion:
    """The joint fit with the motion model, from the tracked poses and from the screening fit (and from
    other starting geometries, :func:`_race`): the one with the lowest penalised cost."""
    rate = st.rate
    cutoff = s.cutoff or None  # 0: no motion model
    if isinstance(cutoff, int | float) and cutoff >= rate / 2:
        cutoff = None  # no smoothing at or above the Nyquist frequency
    if isinstance(cutoff, str):  # "auto": per-coordinate cutoffs from the motion, at least 6 Hz
        cutoff = np.maximum(choose_cutoffs(model, sc.fit.pose, sc.fit.frames_used, rate),
                            min(MIN_AUTO_CUTOFF, rate / 2))
    if cutoff is None:  # the screening fit is the fit: the start whose fit has the smallest residuals
        fits = [joint_fit(model, sc.y, f.theta, f.pose, n_iter=s.n_iter, bounds=st.bounds, frames=sc.fixed,
                          tol=SCREEN_TOL, step_tol=SCREEN_STEP_TOL, ws=ws) for _, _, f in sc.others]
        return Motion(min(fits, key=lambda f: f.rss) if fits and min(f.rss for f in fits) < sc.fit.rss
                      else sc.fit, None)
    if len(sc.y) < MOTION_MIN_FRAMES:
        raise DataError(f"{len(sc.y)} frame(s): the motion model (cutoff) smooths second differences of the poses "
                        f"and needs at least {MOTION_MIN_FRAMES} frames", "give a longer trial, or cutoff=None")
    fits = _race(model, st, sc, s, cutoff, ws)
    best = min(fits, key=penalised_cost)
    minima = tuple((f.theta, penalised_cost(f)) for f in fits if f.converged) if sc.others else ()
    more = s.n_iter - RACE_ITER if not best.converged else 0  # 0: only the information at the estimate
    fit = joint_fit(model, sc.y, best.theta, best.pose, n_iter=max(more, 0), bounds=st.bounds, frames=sc.fixed,
                    penalty=best.penalty, step_tol=FIT_STEP_TOL, ws=ws)
    if not more:
        fit = fit._replace(converged=best.converged, n_iter=best.n_iter)
    return Motion(fit, cutoff, minima)


def modes_stage(model: Model, mo: Motion, fit: JointFit, sigma: float, cov, own_cost: float = np.inf) -> Modes:
    """Other minima of the penalised cost that fit almost as well, held inside the interval.

    The race of :func:`motion_stage` settles each start in a minimum. Where one lies more than
    ``MODE_SD`` sd (of ``cov``) from the estimate in some parameter and its likelihood ratio to the best,
    ``exp(-(C_k - C_min) / (2 sigma^2))``, is at least ``MODE_RATIO``, the data do not rule that geometry
    out: a Gaussian interval about the estimate cannot hold two modes, so the variance along the line
    to that minimum is raised until the interval reaches beyond it by its own half-width (the
    estimate's sd along that line standing in for the other minimum's). ``own_cost``: the estimate's
    own penalised cost where it is comparable (the same cost, unweighted): a later stage (the branch
    check) can find a lower minimum than every start of the race, and the ratios are then to it.
    """
    extra = np.zeros((model.n_params, model.n_params))
    if not mo.minima:
        return Modes(extra, ())
    lowest = min(min(c for _, c in mo.minima), own_cost)
    sd = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    kept = []
    for theta, c in mo.minima:
        d = np.asarray(theta, float) - fit.theta
        ratio = float(np.exp(-(c - lowest) / (2.0 * sigma**2)))
        if ratio < MODE_RATIO or not np.any(np.abs(d) > MODE_SD * sd):
            continue
        u = d / np.linalg.norm(d)
        s_u = float(np.sqrt(max(u @ cov @ u, 0.0)))
        need = (np.linalg.norm(d) + Z95 * s_u) / Z95
        extra = extra + (need**2 - s_u**2) * np.outer(u, u)
        kept.append({"theta": [float(v) for v in theta], "ratio": ratio})
    return Modes(extra, tuple(kept))


def _race(model: Model, st: Start, sc: Screen, s: MarkerEstimator, cutoff, ws: Workspace | None) -> list:
    """The motion-model fits from every start, each far enough along to compare their penalised costs.

    The motion model makes pose branches stick: the starts race for RACE_ITER iterations, and the one
    with the lowest penalised cost is continued (with its own penalty, so the cost it minimises stays).
    Near a singular pose the per-frame fits jump between branches, so the second start is a fit whose
    motion model is STIFFER times stiffer (graduated smoothing): it carries one smooth trajectory through.
    The other starting geometries (:func:`other_starts`) race too, from their tracked poses and from
    their screening fits' graduated start, each run to the end (another basin is only known once its
    fit has settled), and then the first two are also settled, so that every cost compared is a minimum's.
    """
    rate = st.rate

    def stiff(f):
        return joint_fit(model, sc.y, f.theta, f.pose, n_iter=min(s.n_iter, STIFF_ITER), bounds=st.bounds,
                         frames=sc.fixed, rate=rate, cutoff=np.asarray(cutoff, float) / STIFFER, ws=ws, summary=False)

    first = stiff(sc.fit)
    fits = [joint_fit(model, sc.y, th, qq, n_iter=min(RACE_ITER, s.n_iter), bounds=st.bounds, frames=sc.fixed,
                      rate=rate, cutoff=cutoff, ws=ws, summary=False)
            for th, qq in ((st.theta0, st.pose0), (first.theta, first.pose))]
    for th, qq, screened in sc.others:
        g = stiff(screened)
        fits += [joint_fit(model, sc.y, a, b, n_iter=s.n_iter, bounds=st.bounds, frames=sc.fixed, rate=rate,
                           cutoff=cutoff, ws=ws, summary=False, step_tol=FIT_STEP_TOL)
                 for a, b in ((th, qq), (g.theta, g.pose))]
    if sc.others:
        fits[:2] = [f if f.converged else joint_fit(model, sc.y, f.theta, f.pose, n_iter=max(s.n_iter - RACE_ITER, 0),
                                                    bounds=st.bounds, frames=sc.fixed, penalty=f.penalty, ws=ws,
                                                    summary=False, step_tol=FIT_STEP_TOL) for f in fits[:2]]
    return fits


def penalised_cost(f: JointFit) -> float:
    """A joint fit's cost with its motion-model penalty (without one: its residual sum of squares)."""
    if f.penalty is None:
        return float(f.rss)
    return f.rss + float(f.pose.ravel() @ (f.penalty @ f.pose.ravel()))


def weights_stage(model: Model, st: Start, sc: Screen, mo: Motion, s: MarkerEstimator,
                  ws: Workspace | None = None) -> Weights:
    """Per-marker noise levels and the weighted refit (see :mod:`skelid.estimators.checks.noise`)."""
    if s.noise == "pooled":
        return Weights(mo.fit, None, None, None)

    def refit(weights, prev):
        return joint_fit(model, sc.y, prev.theta, prev.pose, n_iter=s.n_iter, bounds=st.bounds, frames=sc.fixed,
                         rate=st.rate, cutoff=mo.cutoff, weights=weights, ws=ws)

    groups = marker_groups(model.marker_names, s.marker_groups)
    fit, w, sig, dof, _ = per_marker_fit(model, sc.y, refit, mo.fit, groups)
    return Weights(fit, w, sig, dof)


def frames_stage(model: Model, sc: Screen, fit: JointFit) -> Frames:
    usable = usable_frames(model, sc.y)
    used = fit.frames_used
    if used.sum() == 0:
        raise DataError("no frame has enough markers to fix the pose",
                        "check that the file holds the model's markers")
    return Frames(used, {"too_few_coordinates": int((~usable).sum()),
                         "pose_not_fixed": int((usable & ~sc.fixed).sum())})


def noise_stage(model: Model, fit: JointFit, sigma: float | None) -> Noise:
    """``sigma^2 = RSS / (n_obs - pose dof - P)`` with a chi-square interval, or the user's value."""
    dof = fit.n_obs - fit.pose_dof - model.n_params
    if dof <= 0:
        raise IdentifiabilityError(
            f"{fit.n_obs} marker coordinates cannot inform {model.n_params} parameters and "
            f"{model.n_pose} pose coordinates per frame (each frame must give more coordinates than pose "
            "coordinates)", "add markers or remove parameters")
    if sigma is not None:
        return Noise(float(sigma), np.array([sigma, sigma], float), dof)
    return Noise(float(np.sqrt(fit.rss / dof)), np.sqrt(fit.rss / chi2.ppf([0.975, 0.025], dof)), dof)


def identify_stage(model: Model, st: Start, sc: Screen, fr: Frames, fit: JointFit, noise: Noise,
                   on_bound: str, motion_pose=None) -> tuple[dict, np.ndarray]:
    """Identifiability table, and the parameters whose profile estimate sits on a prior bound.

    With ``motion_pose`` (the unweighted fit's poses, given for a per-marker weighted fit) each
    joint's range of motion is the smaller of the two fits': weights that let the poses follow a
    few markers closely never widen a range (nor change which joints count as still).
    """
    ident = identifiability(model, fit.info, noise.sigma, y=sc.y, pose=fit.pose, used=fr.used)
    if motion_pose is not None and "joint_range_deg" in ident:
        plain = joint_motion(model, motion_pose, fr.used)
        ident["joint_range_deg"] = {j: [min(a, b) for a, b in zip(r, plain.get(j, r), strict=True)]
                                    for j, r in ident["joint_range_deg"].items()}
    if ident["null"]:
        raise IdentifiabilityError(
            f"the data cannot identify {null_message(model, ident['null'])} (no information "
            "about this for this motion and these markers)",
            "fix one of these parameters (remove it from [[parameters]]) or record more varied motion")
    lo, hi = st.bounds
    width = hi - lo
    pinned = (fit.theta <= lo + 1e-6 * width) | (fit.theta >= hi - 1e-6 * width)
    if pinned.any() and model.n_params == 1 and on_bound == "error":
        p = model.parameters[0]
        raise IdentifiabilityError(
            f"no solution inside the interval [{p.prior.lower:g}, {p.prior.upper:g}] of parameter "
            f"{p.name}: the best fit sits on the bound {fit.theta[0]:g} {model.units}",
            "widen the parameter's prior bounds or check the model's marker positions")
    return ident, pinned


def residual_stage(model: Model, y, fit: JointFit, used, sigma: float, w=None) -> Residuals:
    """Soft-tissue artefact shows as slow, correlated residuals; its white part drives the bias."""
    resid = y - marker_positions(model, fit.theta, fit.pose)
    score = lag1_autocorrelation(resid, used)
    # residuals at the file's rounding level (noise-free data) are not soft-tissue artefact
    numerical = sigma <= NUMERICAL_RESIDUAL * float(np.abs(model.nominal_geometry).max())
    # with slow, correlated residuals the white noise comes from frame-to-frame differences,
    # which a slow drift barely touches
    dr = np.diff(resid if w is None else resid * np.sqrt(w)[:, None], axis=0)[used[1:] & used[:-1]]
    white = float(np.sqrt(0.5 * np.nanmean(dr**2))) if dr.size else sigma
    misfit = model_misfit(model, y, fit.theta, fit.pose, used)
    return Residuals(np.where(used[:, None], np.linalg.norm(resid, axis=-1), np.nan), score,
                     bool(score > STA_AUTOCORRELATION and not numerical), white, misfit)


def bias_stage(est: MarkerEstimator, st: Start, sc: Screen, mo: Motion, wt: Weights, used, noise: Noise,
               res: Residuals, rng) -> Bias:
    """Second-order (Box) bias at the estimate, or a parametric bootstrap, or none.

    Under ``'auto'`` the second-order correction is checked (:mod:`skelid.estimators.uncertainty.singular`):
    when the information about ``theta`` depends on where the poses lie within their own error
    (near a singular pose), or a correction exceeds ``BIAS_RELIABLE`` sd (what the expansion
    leaves, a fixed share of the correction, is then no longer small against the sd), a parametric
    bootstrap at the deconvolved poses stands in for it, and its spread, Monte Carlo error and
    disagreement with the second-order bias there widen the interval. A kept correction above
    ``SECOND_ORDER_SPREAD`` sd brings the covariance of the second-order term into the interval
    (:func:`skelid.estimators.uncertainty.singular.quadratic_term_draws`).
    """
    model, fit, w = est.model, wt.fit, wt.weights
    sigma2 = noise.sigma**2
    sigma2_bias = min(sigma2, res.sigma_white**2) if res.flagged else sigma2
    method = "box" if est.bias_correction in (True, "auto") else est.bias_correction
    method = "none" if method is False else method
    y = sc.y
    y_used = np.where(used[:, None, None], y, np.nan)

    def second_order(q, pose_var=None, theta=None):
        theta = fit.theta if theta is None else theta
        if fit.penalty is None:
            var = [] if pose_var is not None else None
            b = box_bias(model, y[used], theta, q[used], sigma2_bias, weights=w, pose_var=var)
            if var is not None:  # frames not used: no information, the mean variance
                full = np.empty(q.shape)
                full[used] = var[0]
                full[~used] = var[0].mean(axis=0)
                pose_var.append(full)
            return b
        return smoothed_bias(model, y_used, theta, q, sigma2_bias, fit.penalty, weights=w, pose_var=pose_var)

    if method == "box":
        checked = est.bias_correction in ("auto", True)
        pose_var = [] if checked else None
        b = second_order(fit.pose, pose_var)
        if not checked:
            return Bias(b, method)
        sd = noise.sigma * np.sqrt(np.clip(np.diag(np.linalg.inv(fit.info)), 0, None))
        check = pose_check(model, y, fit.theta, fit.pose, pose_var[0], used, row_weights(w, y))
        large = np.abs(b) > BIAS_RELIABLE * sd
        # evaluated again at the corrected point: geometry less its bias, poses freed of their scatter
        b_next = second_order(check.q_tilde, theta=fit.theta - b) if np.any(large) and not check.sensitive else b
        # the size decides, not whether the correction stays put there: on long trials (case A,
        # sigma 15 mm, 10^4 frames) it stays put and still leaves 0.7 sd of bias (bootstrap: 0.1 sd)
        if check.sensitive or np.any(large):
            # the local expansion is unreliable here (near a singular pose): the bias of this fit is
            # measured by simulation at the deconvolved poses instead
            b_tilde = second_order(check.q_tilde)
            seed = int(rng.integers(2**63))  # every step of the fixed point draws the same noise

            def refit(th, qq):
                return as_draws(est._bootstrap_bias(y, fit._replace(theta=th, pose=qq), noise.sigma, st.rate,
                                                    mo.cutoff, st.bounds, np.random.default_rng(seed)))

            boot, shifts = indirect_bias(refit, fit.theta, check.q_tilde)
            extra = fallback_covariance(shifts, sigma2 * np.linalg.inv(fit.info), boot - b_tilde)
            k = int(np.argmax(np.maximum(np.abs(check.info_change) / POSE_SENSITIVE,
                                         np.abs(b_next - b) * np.sqrt(est.n_boot) / np.maximum(sd, 1e-300))))
            reason = "pose" if check.sensitive else "large"
            return Bias(boot, "bootstrap", {
                "reason": reason, "box": b.tolist(), "box_deconvolved": b_tilde.tolist(),
                "box_corrected": b_next.tolist(),
                "consistent": expansion_consistent(b, b_next, sd, est.n_boot).tolist(),
                "bootstrap": boot.tolist(), "n_boot": est.n_boot, "parameter": model.parameter_names[k],
                "sd": float(sd[k]), "info_change": check.info_change.tolist(),
                "pose_sd": check.pose_sd.tolist(),
                "sd_bootstrap": np.sqrt(np.diag(extra + sigma2 * np.linalg.inv(fit.info))).tolist()}, extra)
        if np.any(np.abs(b) > SECOND_ORDER_SPREAD * sd):
            # the second-order term's spread (zero mean beside the first-order one): not small here
            if fit.penalty is None:
                draws = quadratic_term_draws(model, y[used], fit.theta, fit.pose[used], sigma2_bias, None, w,
                                             N_DRAWS, rng.spawn(1)[0])
            else:
                draws = quadratic_term_draws(model, y_used, fit.theta, fit.pose, sigma2_bias, fit.penalty, w,
                                             N_DRAWS, rng.spawn(1)[0])
            return Bias(b, method, None, second_order_covariance(draws))
        return Bias(b, method)
    if method == "bootstrap":
        boot, extra = bootstrap_bias(est, y, fit, noise, st, mo, rng)
        return Bias(boot, method, None, extra)
    return Bias(np.zeros(model.n_params), method)


def profile_stage(est: MarkerEstimator, sc: Screen, wt: Weights, used, noise: Noise, bias: Bias) -> Bias:
    """The sd at the ends of the interval where it is larger than at the estimate (near a singular pose).

    Where a bias correction above ``PROFILE_CHECK`` sd was found (the log-likelihood's third
    derivatives are not small), the information is evaluated along each parameter's profile at
    the interval's ends (:func:`skelid.estimators.uncertainty.singular.profile_sd_ratio`) and the variance
    raised to the larger end's; elsewhere nothing is computed.
    """
    model, fit, w = est.model, wt.fit, wt.weights
    if fit.info is None or not np.any(bias.bias):
        return bias
    plain = noise.sigma**2 * np.linalg.inv(fit.info)
    if not np.any(np.abs(bias.bias) > PROFILE_CHECK * np.sqrt(np.clip(np.diag(plain), 0, None))):
        return bias
    y = sc.y
    if fit.penalty is None:
        ratio = profile_sd_ratio(model, y[used], fit.theta, fit.pose[used], noise.sigma, None, w)
    else:
        ratio = profile_sd_ratio(model, np.where(used[:, None, None], y, np.nan), fit.theta, fit.pose,
                                 noise.sigma, fit.penalty, w)
    return bias._replace(cov=bias.cov + profile_covariance(ratio, plain))


def bootstrap_bias(est: MarkerEstimator, y, fit: JointFit, noise: Noise, st: Start, mo: Motion, rng):
    """Parametric bootstrap of the bias, and the covariance it adds to ``sigma^2 S^{-1}``.

    ``B = n_boot`` data sets are simulated from the fit and refitted; the bias is the mean
    shift less its linear part, ``b* = mean(s_b - l_b)`` (:mod:`skelid.estimators.uncertainty.bootstrap`).
    Where the local approximation fails, the refits also spread more than ``sigma^2 S^{-1}``
    says: the covariance added is the excess of their covariance ``C* = Var(l) + Cov(s) - Cov(l)``
    over it (eigenvalues clipped at zero), plus ``Cov(s - l)/B``, the Monte Carlo variance of ``b*``.

    Returns
    -------
    bias : (P,) float
    extra : (P, P) float
    """
    draws = est._bootstrap_bias(y, fit, noise.sigma, st.rate, mo.cutoff, st.bounds, rng)
    return draws_bias(as_draws(draws)), fallback_covariance(draws, noise.sigma**2 * np.linalg.inv(fit.info),
                                                         np.zeros(len(fit.theta)))


def covariance_stage(est: MarkerEstimator, sc: Screen, wt: Weights, used, noise: Noise,
                     res: Residuals, ident: dict | None = None, rng=None) -> Covariance:
    """``sigma^2 S^{-1}``; Newey-West when the residuals are correlated; the stated artefact's term."""
    model, y, fit, w = est.model, sc.y, wt.fit, wt.weights
    info_inv = np.linalg.inv(fit.info)
    plain = noise.sigma**2 * info_inv
    # the bound with every pose a free unknown (no motion model), at the estimate
    _, Jq_u, Jt_u = weighted_terms(model, fit.theta, fit.pose[used], y[used], row_weights(w, y[used]))
    info_eff = efficient_information(Jq_u, Jt_u, noise.sigma)
    crlb = crlb_sd(info_eff)
    widened = est.robust == "always" or (est.robust == "auto" and res.flagged)
    cov = plain
    y_used = np.where(used[:, None, None], y, np.nan)
    if widened:
        if fit.penalty is None:
            scores = frame_scores(model, y[used], fit.theta, fit.pose[used], weights=w)
        else:
            scores = smoothed_frame_scores(model, y_used, fit.theta, fit.pose, fit.penalty, weights=w)[used]
        cov_nw = info_inv @ newey_west(scores, _bandwidth(res.sta_score, len(scores))) @ info_inv
        cov = cov_nw if np.all(np.diag(cov_nw) >= np.diag(cov)) else np.maximum(cov, cov_nw)
    # the part of a soft-tissue artefact that mimics a geometry change leaves no residual: with its
    # size stated, its effect on the estimate is added (a random-effect model of the artefact)
    artefact = np.zeros((model.n_params, model.n_params))
    if est.artefact_rms:
        artefact = artefact_covariance(model, y_used, fit.theta, fit.pose, fit.penalty,
                                       float(est.artefact_rms), used)
        cov = cov + artefact
    # one marker's artefact that moves the estimate shows when that marker is left out
    jack = {"available": False, "folded": False}
    own = cov
    if est.jackknife:
        # the markers' disagreement is tested against white noise no smaller than rounding (noise-free data:
        # their disagreement is the last digits of two kinematics, not an artefact)
        rounding = NUMERICAL_RESIDUAL * float(np.abs(model.nominal_geometry).max())
        cov, jack, _ = jackknife_stage(model, y_used, fit, max(noise.sigma, rounding), cov,
                                       fold_in=not est.artefact_rms, rng=rng, weights=w)
    cov, place = placement_stage(est, y_used, fit, used, w, ident or {}, cov)
    return Covariance(info_inv, plain, cov, artefact, widened, crlb, np.sqrt(np.diag(plain)), jack, place, info_eff,
                      cov - own)


def converge_stage(model: Model, st: Start, sc: Screen, mo: Motion, wt: Weights, s: MarkerEstimator,
                   ws: Workspace | None = None) -> Weights:
    """A fit that stopped early is continued (up to ``CONTINUE_ROUNDS`` times ``n_iter`` more
    iterations); if its estimate still moves by more than ``CONVERGED_SD`` of its sd in the last
    round, no interval is reported (one line), or, with ``on_nonconvergence='warn'``, the estimate
    is kept and flagged (the ``not-converged`` warning): for a caller that only starts from it."""
    fit = wt.fit
    for _ in range(CONTINUE_ROUNDS):
        if fit.converged:
            break
        more = joint_fit(model, sc.y, fit.theta, fit.pose, n_iter=s.n_iter, bounds=st.bounds, frames=sc.fixed,
                         penalty=fit.penalty, weights=wt.weights, ws=ws)
        dof = max(more.n_obs - more.pose_dof - model.n_params, 1.0)
        # exact data: the noise level is rounding (NUMERICAL_RESIDUAL of the model's size), not the residuals'
        sigma2 = max(more.rss / dof, (NUMERICAL_RESIDUAL * float(np.abs(model.nominal_geometry).max())) ** 2)
        try:
            sd = np.sqrt(np.clip(np.diag(np.linalg.inv(more.info)), 0, None) * sigma2)
        except np.linalg.LinAlgError:
            return wt._replace(fit=more)
        step = np.abs(more.theta - fit.theta)
        fit = more
        if not np.any(step > CONVERGED_SD * np.maximum(sd, 1e-300)):
            return wt._replace(fit=more)
    if fit.converged or s.on_nonconvergence == "warn":  # "warn": the estimate as it stands, flagged
        return wt._replace(fit=fit)
    k = int(np.argmax(step / np.maximum(sd, 1e-300)))
    raise ConvergenceError(
        f"the joint fit did not converge: {model.parameter_names[k]} still moved by {step[k]:.3g} "
        f"({step[k] / max(sd[k], 1e-300):.1f} sd) in {s.n_iter} further iterations, so no interval "
        "can be given", "raise n_iter, or check the model's starting geometry and the data")


def branch_stage(model: Model, st: Start, sc: Screen, wt: Weights, s: MarkerEstimator,
                 ws: Workspace | None = None) -> Weights:
    """Frames on a joint's mirrored branch (:func:`skelid.estimators.uncertainty.singular.branch_joints`) refitted.

    For the joints whose centre two marker distances fix, the frames on the side of each one's
    singular pose that fewer frames take are mirrored, every joint at once, and the motion-model
    fit is repeated from there (:func:`skelid.estimators.uncertainty.singular.mirrored_start`); the refit is
    kept when it converged to a lower penalised cost (the first fit sat in a local minimum) and
    keeps to one branch at every such joint (:func:`skelid.estimators.uncertainty.singular.branch_settled`).
    A model without such joints, or a fit with every frame on one branch, costs nothing.
    """
    fit = wt.fit
    joints = branch_joints(model)
    if fit.penalty is None or not joints:
        return wt
    starts = [mirrored_start(model, fit.theta, fit.pose, sc.y, joints, fit.frames_used, ws)]
    # the joints that stay near one singular pose throughout, each put on either branch in every frame
    near = [j for j in joints if keeps_near_singular(model, fit.theta, fit.pose, j, fit.frames_used, ws)]
    if len(near) <= MAX_ASSIGNED_JOINTS:  # 2^J starts
        starts += [assigned_branch_start(model, fit.theta, fit.pose, sc.y, near, signs, fit.frames_used, ws)
                   for signs in itertools.product((1.0, -1.0), repeat=len(near))]
    best = fit
    sigma = float(np.sqrt(fit.rss / max(fit.n_obs - fit.pose_dof - model.n_params, 1.0)))
    for start in starts:
        if start is None:
            continue
        new = joint_fit(model, sc.y, fit.theta, start, n_iter=s.n_iter, bounds=st.bounds, frames=sc.fixed,
                        penalty=fit.penalty, weights=wt.weights, step_tol=FIT_STEP_TOL, ws=ws)
        if (new.converged and penalised_cost(new) < penalised_cost(best) * (1.0 - 1e-9)
                and branch_settled(model, new.theta, new.pose, joints, new.frames_used, ws, (fit.theta, fit.pose),
                                   sigma)):
            best = new
    return wt if best is fit else wt._replace(fit=best)


def placement_stage(est: MarkerEstimator, y_used, fit: JointFit, used, w, ident: dict, cov):
    """Flag parameters informed by the nominal marker placement; add its uncertainty to ``cov``.

    See :func:`skelid.estimators.checks.misfit.placement_information`. The placement's standard
    deviation is ``placement_sd`` when stated, and its effect on every parameter is added (a
    functional joint centre moves with a misplaced marker as well: the fit cannot tell the
    misplacement from the centre); otherwise ``DEFAULT_PLACEMENT_SD_MM`` for a trial whose joints
    all moved less than ``STILL_JOINT_DEG`` (a static trial) where a parameter is informed by the
    placement, and none for a trial with motion (the flag is then reported without a warning).
    """
    model = est.model
    place = placement_information(model, y_used, fit.theta, fit.pose, used, fit.penalty, w)
    share = place["share_still"]
    flagged = share > PLACEMENT_SHARE
    ranges = [max(r) for r in ident.get("joint_range_deg", {}).values()]
    static = bool(ranges) and max(ranges) < STILL_JOINT_DEG
    if est.placement_sd is not None:
        sd = float(est.placement_sd)
    else:
        sd = DEFAULT_PLACEMENT_SD_MM * unit_scale("mm", model.units) if static else 0.0
    stated = est.placement_sd is not None
    added = sd**2 * place["cov_per_unit"] if (flagged.any() or stated) else np.zeros_like(cov)
    out = {"placement_sd": sd, "static": static, "min_share": float(share[flagged].min()) if flagged.any() else 0.0,
           "parameters": {n: {"share_from_still_pose": round(float(share[k]), 3),
                              "informed_by_placement": bool(flagged[k]),
                              "sd_added": float(np.sqrt(max(added[k, k], 0.0)))}
                          for k, n in enumerate(model.parameter_names)}}
    return cov + added, out


def misfit_stage(est: MarkerEstimator, st: Start, sc: Screen, wt: Weights, res: Residuals,
                 estimate: Estimate) -> Misfit:
    """Refit each joint flagged as model misfit with a relaxed joint; widen the intervals to cover it.

    A flagged hinge of a 3-D model is refitted as its moving-centre variant
    (:func:`skelid.model.variants.moving_centre`: the centre's path cubic in the angle, each
    gain with a normal prior of sd 10 mm per radian^k about the hinge), from the fit's own
    geometry and poses, with the same motion model and weights. The refit's estimate and sd
    combine its data with those priors (:func:`skelid.estimators.checks.misfit.relaxed_estimate`).
    Each parameter's 95 % interval becomes the hull of its own interval and the refit's
    (``theta_v +- 1.96 sd_v``); the estimate is the hull's midpoint and the covariance is
    rescaled to the hull's half-width, keeping the correlations. See
    ``benchmarks/results/model_mismatch.md`` for the coverage and width of this rule. Other
    joint types have no built-in relaxation: the warning names the remedy and the interval is
    left as it is. Nothing is refitted when no joint is flagged.
    """
    from skelid.model.variants import moving_centre

    model = est.model
    flagged = [j for j, v in res.misfit.items() if v["flagged"]]
    if not flagged:
        return Misfit({}, estimate)
    theta, cov = estimate
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    lo, hi = theta - Z95 * sd, theta + Z95 * sd
    fit, P = wt.fit, model.n_params
    joints = {}
    for j in flagged:
        seg = next(s for s in model.segments if s.joint.name == j)
        if model.dim != 3 or seg.joint.type != "hinge":
            joints[j] = {"remedy": "a coupled joint (a custom joint whose translations follow its angles)",
                         "variant": None}
            continue
        try:
            variant = moving_centre(model, j)
        except ModelError as e:  # e.g. a hinge whose axis is fitted: no variant to refit with
            joints[j] = {"remedy": f"{e.fix}, then skelid.model.variants.moving_centre(model, {j!r})",
                         "variant": None, "why": e.problem}
            continue
        extra = variant.n_params - P
        bounds = (np.concatenate([st.bounds[0], [p.prior.lower for p in variant.parameters[P:]]]),
                  np.concatenate([st.bounds[1], [p.prior.upper for p in variant.parameters[P:]]]))
        f = joint_fit(variant, sc.y, np.concatenate([fit.theta, np.zeros(extra)]), fit.pose, n_iter=est.n_iter,
                      bounds=bounds, frames=sc.fixed, penalty=fit.penalty, weights=wt.weights)
        th_v, sd_v = relaxed_estimate(variant, f, P)
        lo, hi = np.minimum(lo, th_v - Z95 * sd_v), np.maximum(hi, th_v + Z95 * sd_v)
        joints[j] = {"remedy": f"skelid.model.variants.moving_centre(model, {j!r})", "variant": variant.name,
                     "theta": dict(zip(model.parameter_names, th_v.tolist(), strict=True)),
                     "sd": dict(zip(model.parameter_names, sd_v.tolist(), strict=True)),
                     "gains": dict(zip(variant.parameter_names[P:], f.theta[P:].tolist(), strict=True)),
                     "converged": bool(f.converged)}
    new_sd = (hi - lo) / (2 * Z95)
    widened = new_sd > sd * (1 + 1e-6)
    names = [n for n, w in zip(model.parameter_names, widened, strict=True) if w]
    for v in joints.values():
        v["widened"] = names
        v["sd_before"] = dict(zip(model.parameter_names, sd.tolist(), strict=True))
    if not names:  # no refit, or each refit inside the intervals: the estimate stands as it is
        return Misfit(joints, estimate)
    scale = np.where(sd > 0, new_sd / np.maximum(sd, 1e-300), 1.0)
    return Misfit(joints, Estimate((lo + hi) / 2, cov * np.outer(scale, scale)))


def summary_stage(model: Model, ident: dict, est: Estimate, placement: dict | None = None) -> Summary:
    """The final identifiability rows, still joints, lengths.

    The final interval also decides 'poor'. A parameter informed by the markers' nominal
    placement rather than by motion (:func:`placement_stage`) in a trial whose joints all stood
    still, or whose own joint stood still, has the status 'placement': its value is the one
    the placement implies, not one the motion found.
    """
    sd = np.sqrt(np.clip(np.diag(est.cov), 0.0, None))
    pl = placement or {}
    ranges = ident.get("joint_range_deg", {})
    still_joints = {j for j, r in ranges.items() if max(r) < STILL_JOINT_DEG}
    table = []
    for k, row in enumerate(ident["table"]):
        p = model.parameters[k]
        row = dict(row, sd=float(sd[k]))
        if row["status"] == "identified" and sd[k] > POOR_FRACTION * (p.prior.upper - p.prior.lower):
            row["status"] = "poor"
        still = pl.get("static") or (PARAMETER_TARGET.get(p.kind, "joint") == "joint" and p.target in still_joints)
        placed = pl.get("parameters", {}).get(p.name, {}).get("informed_by_placement", False)
        if row["status"] == "identified" and still and placed:
            row["status"] = "placement"
        table.append(row)
    functional = {p.target for p in model.parameters if p.kind in ("joint_centre", "axis_direction")}
    still = [j for j, r in ranges.items() if j in functional and max(r) < STILL_JOINT_DEG]
    return Summary(table, still, derived_lengths(model, est.theta, est.cov))


def derived_lengths(model: Model, theta, cov) -> dict:
    """Joint-to-joint lengths with their sd (delta method) and 95 % interval."""
    lengths, grad = joint_distances(model, theta)
    sd = np.sqrt(np.clip(np.einsum("kp,pq,kq->k", grad, cov, grad), 0.0, None))
    return {name: {"value": float(v), "sd": float(e), "ci95": [float(v - Z95 * e), float(v + Z95 * e)]}
            for (name, _), v, e in zip(model.derived_lengths, lengths, sd, strict=True)}


def marker_warnings(model: Model, s: MarkerEstimator, f: MarkerFit) -> list[Warning]:
    """The warnings a marker fit deserves, decided from its values (one small check per concern)."""
    checks = (_data_warnings, _bound_warnings, _identification_warnings, _residual_warnings, _bias_warnings,
              _jackknife_warnings, _placement_warnings, _motion_warnings, _mode_warnings)
    return [w for check in checks for w in check(model, s, f)]


def _mode_warnings(model: Model, s: MarkerEstimator, f: MarkerFit) -> list[Warning]:
    """Another minimum of the cost fits almost as well: the interval holds it."""
    if f.modes is None or not f.modes.kept:
        return []
    m = max(f.modes.kept, key=lambda k: k["ratio"])
    at = ", ".join(f"{n} = {v:.4g}" for n, v in zip(model.parameter_names, m["theta"], strict=True))
    return [Warning("other-minimum", f"another geometry fits the markers almost as well ({at}; likelihood ratio "
                    f"{m['ratio']:.2g}, {len(f.modes.kept)} such minimum(s)): the data allow both, so the interval "
                    "was widened to hold it; more frames or a marker that breaks the symmetry would decide")]


def _data_warnings(model: Model, s: MarkerEstimator, f: MarkerFit) -> list[Warning]:
    """Marker positions left out as outliers; frames skipped."""
    out = []
    out_ = f.screen.outliers
    if out_.any():
        out.append(Warning("outliers", f"{int(out_.sum())} marker positions in {int(out_.any(axis=1).sum())} "
                           f"frames lie more than {s.outlier_threshold:g} robust standard deviations from the "
                           "fitted model (mislabelled or glitched markers?) and were left out"))
    n_rep = repeated_frames(f.start.y)
    if n_rep:
        out.append(Warning("repeated-frames", f"{n_rep} of {len(f.start.y)} frames repeat the frame before them "
                           "exactly (a frozen capture, or a file padded with copies?): each is counted as new "
                           "information, so the interval is too narrow by up to the square root of the share "
                           "of distinct frames; remove the copies"))
    n_skip = int((~f.frames.used).sum())
    if n_skip:
        out.append(Warning("frames-skipped", f"{n_skip} of {len(f.frames.used)} frames have too few markers "
                           "to fix the pose and were skipped"))
    return out


def repeated_frames(y) -> int:
    """Frames ``y (T, M, D)`` identical to the one before them in every coordinate (NaN where NaN), with a
    marker present: real noise never repeats a frame exactly, a frozen capture or a padded file does."""
    y = np.asarray(y, float)
    if len(y) < 2:
        return 0
    a, b = y[1:], y[:-1]
    same = ((a == b) | (np.isnan(a) & np.isnan(b))).all(axis=(1, 2))
    return int((same & np.isfinite(a).all(axis=2).any(axis=1)).sum())


def _bound_warnings(model: Model, s: MarkerEstimator, f: MarkerFit) -> list[Warning]:
    """Parameters pinned on a bound of their prior, or lying outside it."""
    out = []
    if f.pinned.any():
        pinned = tuple(np.array(model.parameter_names)[f.pinned])
        out.append(Warning("on-bound", f"parameter(s) {', '.join(pinned)} ended on a bound of their prior "
                           "interval: the data do not pin them inside it", pinned) if model.n_params > 1 else
                   Warning("on-bound", f"parameter {pinned[0]} ended on a bound of its prior interval: the "
                           "data do not pin it inside it", pinned))
    beyond = f.beyond if f.beyond is not None else np.full(model.n_params, np.nan)
    for k, p in enumerate(model.parameters):
        if np.isfinite(beyond[k]):
            out.append(Warning("outside-prior", f"the estimate of parameter {p.name} ({beyond[k]:.4g} after the "
                               "corrections) lies beyond its prior bounds "
                               f"[{p.prior.lower:g}, {p.prior.upper:g}]; it is reported on the bound "
                               f"{f.estimate.theta[k]:g}: the data do not place it inside its prior", (p.name,)))
    return out


def _identification_warnings(model: Model, s: MarkerEstimator, f: MarkerFit) -> list[Warning]:
    """Parameters poorly identified by the Cramér-Rao bound, or only once the interval is final."""
    out = []
    for k, row in enumerate(f.ident["table"]):
        if row["status"] == "poor":
            out.append(Warning("poorly-identified", f"parameter {row['parameter']} is poorly identified for "
                               f"this motion (Cramér-Rao sd {row['crlb_sd']:.3g} {_unit(model, k)} is more than "
                               "a quarter of its prior range)", (row["parameter"],)))
    for k, (before, after) in enumerate(zip(f.ident["table"], f.summary.table, strict=True)):
        if before["status"] == "identified" and after["status"] == "poor":
            out.append(Warning("poorly-identified", f"parameter {after['parameter']} is poorly identified for "
                               f"this motion (sd {after['sd']:.3g} {_unit(model, k)} is more than a quarter of "
                               "its prior range)", (after["parameter"],)))
    return out


def _residual_warnings(model: Model, s: MarkerEstimator, f: MarkerFit) -> list[Warning]:
    """Model misfit at a joint; serially correlated residuals and whether the interval was widened."""
    misfit = [j for j, v in f.residuals.misfit.items() if v["flagged"]]
    out = []
    for j in misfit:
        v = f.residuals.misfit[j]
        p_txt = f"p = {10 ** v['log10_p']:.1g}" if v["log10_p"] > -300 else "p < 1e-300"
        relaxed = f.misfit.joints.get(j) if f.misfit is not None else None
        if f.misfit is None:  # no refit was asked for
            then = ""
        elif relaxed and relaxed["variant"]:
            then = (f"; refitted with a moving centre ({relaxed['remedy']}), the intervals of "
                    f"{', '.join(relaxed['widened'])} were widened to cover both fits"
                    if relaxed["widened"] else
                    f"; a refit with a moving centre ({relaxed['remedy']}) lies inside the intervals")
        elif relaxed and relaxed.get("why"):
            then = f"; not refitted ({relaxed['why']}), so the interval was not widened: {relaxed['remedy']}"
        else:
            then = "; no built-in relaxation of this joint type, so the interval was not widened"
        out.append(Warning("model-misfit", f"model misfit at joint {j}: the markers of {v['segment']} move together "
                           f"with the joint angle (rms {v['rms']:.3g} {model.units}, {p_txt}; it moves the estimate "
                           f"by {v['effect']:.2g} sd), which "
                           "the joint model cannot follow: a joint centre that moves with the angle, or soft-tissue "
                           "artefact that carries the segment's markers together (its dominant mode; markers on "
                           "skin cannot tell the two apart); fit the joint's coupled motion or a moving centre "
                           f"(skelid.model.variants.moving_centre) to remove the bias it leaves{then}",
                           tuple(relaxed["widened"]) if relaxed and relaxed["variant"] else ()))
    if f.residuals.flagged:
        then = ("so the interval was widened (Newey-West)" if f.cov.widened else
                "but the interval was not widened (robust='never')")
        what = "model misfit (above)" if misfit else "soft-tissue artefact"
        out.append(Warning("model-misfit" if misfit else "soft-tissue-artefact",
                           f"residuals are serially correlated (lag-1 autocorrelation "
                           f"{f.residuals.sta_score:.2f}): they look like {what}, {then}"))
    return out


def _bias_warnings(model: Model, s: MarkerEstimator, f: MarkerFit) -> list[Warning]:
    """The second-order bias correction failed its check (bootstrap fallback), and why."""
    fb = f.bias.fallback
    if not fb:
        return []
    k = model.parameter_names.index(fb["parameter"])
    if fb.get("reason") == "pose":
        why = (f"the poses are poorly identified (near a singular pose: the information about "
               f"{fb['parameter']} changes by {100 * abs(fb['info_change'][k]):.0f} % when the fitted poses are "
               "freed of their estimated scatter), so the local approximation is unreliable")
    else:
        why = (f"the second-order bias correction of {fb['parameter']} ({fb['box'][k]:.3g}, sd {fb['sd']:.3g}; "
               f"{fb['box_corrected'][k]:.3g} when evaluated at the corrected geometry and poses) is more than "
               f"{BIAS_RELIABLE:g} sd, so what the expansion leaves is no longer small against the sd")
    return [Warning("bias-fallback", f"{why}; the bias was measured by parametric bootstrap ({fb['n_boot']} "
                    f"refits at the deconvolved poses: {fb['bootstrap'][k]:.3g} against {fb['box'][k]:.3g} from "
                    f"the second-order expansion) instead, and the interval uses the refits' spread and the "
                    f"bias estimates' disagreement (sd {fb['sd_bootstrap'][k]:.3g})", (fb["parameter"],))]


def _jackknife_warnings(model: Model, s: MarkerEstimator, f: MarkerFit) -> list[Warning]:
    """Markers that disagree beyond their noise (the interval widened by the marker jackknife)."""
    jk = f.cov.jackknife
    out = []
    if jk.get("markers_refit_failed"):
        out.append(Warning("marker-jackknife", "leave-one-marker-out: without marker(s) "
                           f"{', '.join(jk['markers_refit_failed'])} the refit found no estimate (it did not "
                           "converge or ended on a prior bound); they have no replicate"))
    if not jk.get("warn"):  # not widened, or by too little to move an estimate by half its sd
        return out
    k = max(jk["parameters"], key=lambda n: jk["parameters"][n]["sd_added"])
    v = jk["parameters"][k]
    return out + [Warning("marker-jackknife", f"the markers disagree beyond their noise (leave-one-marker-out): "
                          f"without marker {v['most_influential_marker']} the estimate of {k} moves by "
                          f"{v['shift']:.3g}; the interval was widened by the marker jackknife"
                          + (f" (as by a skin artefact of {jk['artefact_rms']:.3g} {model.units} rms on every marker)"
                             if jk.get("artefact_rms") else ""), (k,))]


def _placement_warnings(model: Model, s: MarkerEstimator, f: MarkerFit) -> list[Warning]:
    """Parameters informed by the markers' nominal placement rather than by motion."""
    pl = f.cov.placement
    flagged_p = tuple(n for n, v in pl["parameters"].items() if v["informed_by_placement"])
    if not flagged_p or not (pl["static"] or pl["placement_sd"] > 0):  # with motion the flag stays in the result
        return []
    tail = (f"; a marker placement uncertainty of {pl['placement_sd']:.3g} {model.units} per coordinate was "
            "added to the interval" if pl["placement_sd"] > 0 else
            "; state the markers' placement uncertainty (placement_sd) to carry it into the interval")
    return [Warning("placement-informed", f"parameter(s) {', '.join(flagged_p)} are informed by the "
                    "markers' nominal placement on their segments, not by motion (one still pose gives "
                    f"{100 * pl['min_share']:.0f} % or more of their precision): their value follows "
                    f"from the model's marker positions{tail}", flagged_p)]


def _motion_warnings(model: Model, s: MarkerEstimator, f: MarkerFit) -> list[Warning]:
    """Joints that hardly moved; a joint fit that did not converge."""
    out = []
    if f.summary.still:
        out.append(Warning("still-joint", f"joint(s) {', '.join(f.summary.still)} moved less than "
                           f"{STILL_JOINT_DEG:g} degrees: their centres and axes are informed only by tiny "
                           "motions (a static trial cannot locate a joint functionally)"))
    if not f.weights.fit.converged:
        out.append(Warning("not-converged", "the joint fit stopped before converging; the estimate may be off"))
    return out


def joint_stages(est: MarkerEstimator, y, rate: float, rng, ws: Workspace | None = None):
    """The stages up to the joint fit with the motion model: ``(origin, start, screen, motion)``, the data
    moved by ``origin`` (:func:`~skelid.estimators.base.fit_origin`: the stages see the same numbers wherever
    the data sit)."""
    model = est.model
    origin = fit_origin(model, y)
    st = start_stage(model, np.asarray(y, float) - origin, rate, est, rng, ws, origin)
    sc = screen_stage(model, st, est, ws)
    return origin, st, sc, motion_stage(model, st, sc, est, ws)


def run_marker_fit(est: MarkerEstimator, y, rate: float, rng, on_bound: str = "error",
                   misfit_refit: bool = True) -> MarkerFit:
    """The stages of a marker fit, each returning a small immutable value.

    screen -> joint fit -> per-marker weights -> noise -> identifiability -> residuals -> bias -> covariance -> priors
    -> misfit refit -> summary. A new stage is one function here and one field of :class:`MarkerFit`.
    ``misfit_refit=False`` skips the refit of joints flagged as misfit (a caller that builds its
    own interval from these stages: the sampler).
    """
    model = est.model
    ws = workspace(model)  # one path (compiled or numpy) for every pose fit of this fit
    origin, st, sc, mo = joint_stages(est, y, rate, rng, ws)
    wt = weights_stage(model, st, sc, mo, est, ws)
    wt = converge_stage(model, st, sc, mo, wt, est, ws)
    wt = branch_stage(model, st, sc, wt, est, ws)
    fit = wt.fit
    fr = frames_stage(model, sc, fit)
    noise = noise_stage(model, fit, est.sigma)
    ident, pinned = identify_stage(model, st, sc, fr, fit, noise, on_bound,
                                   None if wt.weights is None else mo.fit.pose)
    res = residual_stage(model, sc.y, fit, fr.used, noise.sigma, wt.weights)
    bias = bias_stage(est, st, sc, mo, wt, fr.used, noise, res, rng)
    bias = profile_stage(est, sc, wt, fr.used, noise, bias)
    cov = covariance_stage(est, sc, wt, fr.used, noise, res, ident, rng)
    modes = modes_stage(model, mo, fit, noise.sigma, cov.data + bias.cov,
                        penalised_cost(fit) if wt.weights is None else np.inf)
    estimate = Estimate(*_combine_normal_priors(model, fit.theta - bias.bias, cov.data + bias.cov + modes.cov))
    mis = misfit_stage(est, st, sc, wt, res, estimate) if misfit_refit else None
    estimate = mis.estimate if mis is not None else estimate
    estimate, beyond = support_stage(st, estimate)
    return MarkerFit(st, sc, mo, wt, fr, noise, ident, pinned | np.isfinite(beyond), res, bias, cov, estimate,
                     summary_stage(model, ident, estimate, cov.placement), ws.path, mis, beyond, origin, modes)


def support_stage(st: Start, estimate: Estimate) -> tuple[Estimate, np.ndarray]:
    """The estimate held inside its prior's support: a value the bias correction, a normal prior or the
    misfit widening moved beyond a bound is put on that bound (no estimate leaves its prior's support).

    Returns the estimate and ``beyond (P,)``: the unbounded value where it was moved, NaN elsewhere.
    """
    lo, hi = st.bounds
    theta = np.clip(estimate.theta, lo, hi)
    beyond = np.where(theta != estimate.theta, estimate.theta, np.nan)
    return estimate._replace(theta=theta), beyond


# ============================================================================== estimator
class MarkerEstimator:
    """Bias-corrected joint estimate of the model's parameters from marker coordinates.

    Parameters
    ----------
    model : Model
    sigma : float, optional
        Marker noise standard deviation (model units); estimated if not given.
    cutoff : float, 'auto' or None
        Motion-model cutoff (Hz); 'auto' chooses one per pose coordinate; None: no motion model.
    bias_correction : {'auto', 'box', 'bootstrap', 'none'}
        Subtract the second-order bias (default); 'none' gives the plain profile
        (joint least-squares) estimate.
    n_boot : int
        Refits of the parametric bootstrap (the 'bootstrap' bias, and the fallback of 'auto'), each
        with its linear control variate (:mod:`skelid.estimators.uncertainty.bootstrap`); default ``N_BOOT``.
    robust : {'auto', 'always', 'never'}
        Use the Newey-West covariance when residuals look like soft-tissue
        artefact ('auto'), always, or never.
    rng : int, numpy.random.Generator or None
        Seed (a fresh generator on every fit) or generator for the random starts of poses that rigid
        fits of the segments do not give.
    n_iter : int
        Joint-fit iterations at most.
    rate : float, optional
        Sampling rate (Hz) of data given as an array; required then.
    outlier_threshold : float or None
        Marker positions whose residual distance after a first fit exceeds this
        many robust standard deviations are left out and the fit repeated
        (None: keep every position).
    artefact_rms : float, optional
        Stated root-mean-square soft-tissue artefact of a marker coordinate (model
        units). The covariance it adds to the estimate (the part of the artefact that
        mimics a geometry change, see :mod:`skelid.estimators.checks.artefact`) widens the
        interval. None: no artefact term.
    noise : {'pooled', 'per_marker'}
        One noise level for every marker, or each marker (or declared group) its
        own, estimated from its residuals and used as weights in the fit
        (see :mod:`skelid.estimators.checks.noise`).
    marker_groups : dict of str to list of str, optional
        With ``noise='per_marker'``: markers that share one noise level.
    jackknife : bool
        Leave each marker out (one-step refits, :mod:`skelid.estimators.uncertainty.jackknife`) and
        add the markers' disagreement beyond white noise to the covariance (only
        reported when ``artefact_rms`` is stated).
    placement_sd : float, optional
        Standard deviation (model units, per coordinate) of each marker's placement on its
        segment; its effect on every parameter (to first order: what a misplaced marker does to
        the estimate, :func:`skelid.estimators.checks.misfit.placement_information`) is added to
        the interval, and it is shared by every trial recorded with these markers. None: 5 mm for a
        static trial, none otherwise.
    theta0 : (P,) float, optional
        Starting geometry (default: the prior centre, and more spread over the prior's bounds, see
        ``n_starts``).
    pose0 : (T, Q) float, optional
        Starting poses (default: tracked at the starting geometry).
    n_starts : int or 'auto'
        Starting geometries tried when neither ``theta0`` nor ``pose0`` is given: the prior centre
        and ``n_starts - 1`` more spread over the prior's bounds; the motion-model fit from each
        races, and the lowest penalised cost wins; another minimum that fits almost as well widens
        the interval (:func:`other_starts`, :func:`modes_stage`). 1: the prior centre only.
        'auto' (default): ``N_STARTS`` where some joint's pose has two mirror-image branches (a
        one-axis joint between two segments with one marker each, whose cost has several minima
        near its straight and folded poses), else 1.
    on_nonconvergence : {'error', 'warn'}
        A joint fit that still moves after its continuations raises
        :class:`~skelid.errors.ConvergenceError` (no interval), or, with ``'warn'``, keeps its
        estimate with the ``not-converged`` warning (for a fit that only starts or checks
        another, as the scale fit of an OpenSim model does).

    Attributes
    ----------
    posterior_ : GaussianPosterior
    theta_ : (P,) float
        Final (bias-corrected) estimate.
    theta_profile_ : (P,) float
        Joint least-squares estimate before correction.
    bias_ : (P,) float
        Estimated bias that was subtracted.
    crlb_sd_ : (P,) float
        Cramér-Rao bound (standard deviation) at the estimate.
    crlb_information_ : (P, P) float
        The efficient information it inverts (every pose free).
    sigma_ : float
    sigma_ci_ : (2,) float
    pose_ : (T, Q) float
    residuals_ : (T, M) float
        Residual distance of each marker in each frame (NaN where missing and
        in frames skipped).
    outliers_ : (T, M) bool
        Marker positions left out as outliers.
    frames_skipped_ : dict
        Frames left out because they have no more coordinates than pose
        coordinates, or because their markers do not fix every pose coordinate.
    frames_used_ : (T,) bool
    identifiability_ : dict
    sta_score_ : float
        Mean lag-1 autocorrelation of the residuals.
    cov_plain_ : (P, P) float
        ``sigma^2 S^{-1}``: the data's covariance for white noise.
    cov_data_ : (P, P) float
        The data's covariance used (``cov_plain_``, or the Newey-West one when
        ``widened_``), before any normal prior is combined with it.
    cov_shared_ : (P, P) float
        The part of ``cov_data_`` that the marker jackknife and the placement uncertainty added:
        errors of the markers' placement on the body, which another trial recorded with the same
        markers shares (several trials combine it once, not as independent noise).
    widened_ : bool
        Whether the Newey-West covariance was used.
    cov_ : (P, P) float
        Posterior covariance (``cov_data_`` combined with normal priors).
    y_ : (T, M, D) float
        The markers the final fit used (model order and units; outliers and
        skipped frames NaN).
    marker_sigma_ : (M,) float or None
        Each marker's noise level with ``noise='per_marker'`` (NaN without data).
    marker_weights_ : (M,) float or None
        The weights of the fit (``sigma_^2 / marker_sigma_^2`` up to rounding).
    fit_ : MarkerFit
        Every stage's value. The stages work on the data less ``origin_``; ``pose_``, ``y_`` and
        ``fit_info_`` are in the data's frame.
    origin_ : (D,) float
        Where the stages put the origin (:func:`~skelid.estimators.base.fit_origin`: the markers'
        mean in whole model units for a free root, else zeros), so that a rigid shift of all markers
        leaves every number of the fit where it was.
    warnings_ : tuple of Warning
    """

    name = "marker"
    settings = (
        Setting("sigma", positive_or_none, "a positive noise level in model units, or None to estimate it",
                cli="sigma"),
        Setting("cutoff", lambda v: v == "auto" or non_negative_or_none(v),
                "'auto', a cutoff >= 0 Hz, or None for no motion model", cli="cutoff"),
        Setting("bias_correction", one_of("auto", "box", "bootstrap", "none", True, False),
                "'auto', 'box', 'bootstrap' or 'none'"),
        Setting("n_boot", count, counted("bootstrap replicates")),
        Setting("robust", one_of("auto", "always", "never"), "'auto', 'always' or 'never'"),
        RNG,
        Setting("n_iter", count, counted("iterations")),
        RATE,
        Setting("outlier_threshold", positive_or_none, "a positive number of robust sd, or None"),
        Setting("artefact_rms", non_negative_or_none, "a distance >= 0 in model units, or None",
                cli="artefact_rms"),
        Setting("noise", one_of("pooled", "per_marker"), "'pooled' or 'per_marker'", cli="noise"),
        Setting("marker_groups", lambda v: v is None or isinstance(v, dict), "None or {group: [marker names]}"),
        Setting("jackknife", lambda v: isinstance(v, bool), "True or False"),
        Setting("placement_sd", non_negative_or_none, "a distance >= 0 in model units, or None",
                cli="placement_sd"),
        Setting("theta0", array_or_none, "None or finite starting values, one per parameter"),
        Setting("pose0", array_or_none, "None or finite starting poses (frames, pose coordinates)"),
        Setting("n_starts", lambda v: (isinstance(v, str) and v == "auto") or count(v),
                "'auto' or " + counted("starting geometries")),
        Setting("on_nonconvergence", one_of("error", "warn"), "'error' or 'warn'"),
    )

    def __init__(self, model: Model, sigma: float | None = None, cutoff: float | str | None = "auto",
                 bias_correction: str = "auto", n_boot: int = N_BOOT, robust: str = "auto",
                 rng: np.random.Generator | int | None = None, n_iter: int = 100, rate: float | None = None,
                 outlier_threshold: float | None = 8.0, artefact_rms: float | None = None,
                 noise: str = "pooled", marker_groups: dict | None = None, theta0=None, pose0=None,
                 jackknife: bool = True, placement_sd: float | None = None, on_nonconvergence: str = "error",
                 n_starts: int | str = "auto"):
        self.model = check_model(model, type(self).__name__)
        self.sigma = sigma
        self.cutoff = cutoff
        self.bias_correction = bias_correction
        self.n_boot = n_boot
        self.robust = robust
        self.rng = rng
        self.n_iter = n_iter
        self.rate = rate
        self.outlier_threshold = outlier_threshold
        self.artefact_rms = artefact_rms
        self.noise = noise
        self.marker_groups = marker_groups
        self.jackknife = jackknife
        self.placement_sd = placement_sd
        self.theta0 = theta0
        self.pose0 = pose0
        self.on_nonconvergence = on_nonconvergence
        self.n_starts = n_starts

    @interruptible
    def fit(self, data: MarkerData | np.ndarray, *, progress=None) -> MarkerEstimator:
        """Fit a whole trial: the stages of :func:`run_marker_fit`, then the warnings from their values."""
        check_settings(self)
        y, rate = marker_array(self.model, data, self.rate, self.name)
        with one_blas_thread():
            f = run_marker_fit(self, y, rate, make_rng(self.rng))
        self._publish(f, emit(marker_warnings(self.model, self, f)))
        if progress is not None:
            progress(len(y))
        return self

    def _publish(self, f: MarkerFit, found) -> None:
        """Set the fitted attributes from the stages' values."""
        fit, used = f.weights.fit, f.frames.used
        origin = np.zeros(self.model.dim) if f.origin is None else f.origin
        fit = fit._replace(pose=move_root(self.model, fit.pose, origin))  # the poses in the data's frame
        self.fit_ = f
        self.origin_ = origin
        self.fit_info_ = fit
        self.cutoff_ = f.motion.cutoff
        self.outliers_ = f.screen.outliers
        self.frames_skipped_ = f.frames.skipped
        self.frames_used_ = used
        self.sigma_ = f.noise.sigma
        self.sigma_ci_ = f.noise.interval
        self.sigma_white_ = f.residuals.sigma_white
        self.identifiability_ = dict(f.ident, table=f.summary.table)
        self.theta_profile_ = fit.theta
        self.residuals_ = f.residuals.distance
        self.sta_score_ = f.residuals.sta_score
        self.bias_ = f.bias.bias
        self.bias_method_ = f.bias.method
        self.crlb_motion_sd_ = f.cov.crlb_motion_sd
        self.crlb_sd_ = f.cov.crlb_sd
        self.crlb_information_ = f.cov.information
        self.cov_plain_ = f.cov.plain
        self.widened_ = f.cov.widened
        self.cov_artefact_ = f.cov.artefact
        self.jackknife_ = f.cov.jackknife
        self.placement_ = f.cov.placement
        self.misfit_ = {j: dict(v, relaxed=f.misfit.joints.get(j)) if f.misfit is not None else dict(v)
                        for j, v in f.residuals.misfit.items()}
        self.bias_fallback_ = f.bias.fallback
        self.cov_data_ = f.cov.data + f.bias.cov  # with the bootstrap's spread when it stood in
        self.cov_shared_ = f.cov.shared
        self.theta_, self.cov_ = f.estimate
        self.pose_ = fit.pose
        self.y_ = np.where(used[:, None, None], f.screen.y + origin, np.nan)
        self.posterior_ = GaussianPosterior(self.model.parameter_names, self.theta_, self.cov_)
        self.lengths_ = f.summary.lengths
        self.marker_weights_, self.marker_sigma_, self.marker_dof_ = f.weights[1:]
        self.warnings_ = tuple(found)

    def _bootstrap_bias(self, y, fit, sigma, rate, cutoff, bounds, rng) -> Draws:
        """Parametric bootstrap: simulate from the fit, refit; the shifts and their linear parts.

        The noise of all ``n_boot`` data sets is drawn first, and the joint fit's first
        Gauss-Newton step for each (:func:`~skelid.estimators.uncertainty.bootstrap.linear_response`) is the
        control variate of its refit (:mod:`skelid.estimators.uncertainty.bootstrap`). Every refit starts at
        the simulated point (a start at refit 1's solution moved by the difference of the linear
        steps took more iterations, not fewer: the poses' own nonlinear parts differ from refit to
        refit), minimises the same cost (one motion-model penalty) and stops at steps below
        ``BOOT_STEP_TOL`` of the sd: the bias's Monte Carlo error, ``sd(s - l) / sqrt(n_boot)``
        (about 0.3 sd over ``sqrt(n_boot)`` on case A), is far above that.
        """
        ws = Workspace(self.model)  # kinematics only: no pose fit here
        clean = marker_positions(self.model, fit.theta, fit.pose, ws)
        miss = ~np.isfinite(y)
        noise = rng.normal(0.0, sigma, size=(self.n_boot,) + clean.shape)
        pattern = np.where(miss, np.nan, clean)
        try:
            lin = linear_response(self.model, pattern, fit.theta, fit.pose, noise, rate, cutoff, ws)
        except np.linalg.LinAlgError:  # no linear step: the plain bootstrap
            lin = None
        shifts = []
        for b in range(self.n_boot):
            ys = clean + noise[b]
            ys[miss] = np.nan
            # from the simulated point; with the linear step's penalty (the one the refit would build there)
            q0, penalty = (fit.pose, None) if lin is None else (lin.q_start, lin.penalty)
            f = joint_fit(self.model, ys, fit.theta, q0, n_iter=self.n_iter, bounds=bounds, rate=rate, cutoff=cutoff,
                          penalty=penalty, step_tol=BOOT_STEP_TOL, tol=BOOT_TOL, ws=ws, summary=False)
            shifts.append(f.theta - fit.theta)
        shifts = np.array(shifts)
        if lin is None:
            return as_draws(shifts)
        return Draws(shifts, lin.theta, sigma**2 * lin.cov_unit)

    def result(self) -> FitResult:
        """The typed result (:class:`~skelid.result.FitResult`)."""
        check_fitted(self)
        model = self.model
        jk = self.jackknife_.get("parameters", {})
        extra = {n: {"bias_removed": float(self.bias_[k]), "crlb_sd_motion_model": float(self.crlb_motion_sd_[k]),
                     "jackknife_sd": jk.get(n, {}).get("sd"),
                     "informed_by_placement": self.placement_["parameters"][n]["informed_by_placement"]}
                 for k, n in enumerate(model.parameter_names)}
        diagnostics = {
            "identifiability": self.identifiability_["table"], "null": self.identifiability_["null"],
            "condition": self.identifiability_["condition"],
            "counting": self.identifiability_.get("counting"),
            "joint_range_deg": self.identifiability_.get("joint_range_deg"),
            "residual_autocorrelation": self.sta_score_, "widened": bool(self.widened_),
            "cutoff_hz": None if self.cutoff_ is None else np.atleast_1d(self.cutoff_).tolist(),
            "outlying_marker_positions": int(self.outliers_.sum()),
            "converged": bool(self.fit_info_.converged), "iterations": int(self.fit_info_.n_iter),
            "pose_path": self.fit_.pose_path,
            "bias_method": self.bias_method_, "bias_fallback": self.bias_fallback_,
            "marker_jackknife": self.jackknife_, "placement": self.placement_, "model_misfit": self.misfit_}
        if self.artefact_rms:
            diagnostics["artefact"] = {"rms": float(self.artefact_rms),
                                       "sd_added": np.sqrt(np.diag(self.cov_artefact_)).tolist()}
        per, extra_noise = {}, {"white": self.sigma_white_}
        if self.marker_sigma_ is not None:
            ok = np.isfinite(self.marker_sigma_)  # a marker without data has no level
            names = np.array(model.marker_names)[ok].tolist()
            per = dict(zip(names, self.marker_sigma_[ok].tolist(), strict=True))
            extra_noise["per_marker_dof"] = dict(zip(names, self.marker_dof_[ok].tolist(), strict=True))
        noise = NoiseEstimate(self.sigma_, None if self.sigma is not None else tuple(self.sigma_ci_),
                              fixed=self.sigma is not None, per_marker=per, extra=extra_noise)
        return build_result(self, self.posterior_, crlb_sd=self.crlb_sd_, extra=extra, noise=noise,
                            skipped=self.frames_skipped_, diagnostics=diagnostics, derived=self.lengths_,
                            arrays={"residuals": self.residuals_, "pose": self.pose_,
                                    "outliers": self.outliers_})


def _outlying_markers(model: Model, y, fit, threshold: float, n_rounds: int = 4, ws=None) -> np.ndarray:
    """(T, M) bool: marker positions whose leverage-corrected residual is an outlier.

    See :func:`skelid.estimators.checks.outliers.outlying_markers`.
    """
    from skelid.estimators.checks.outliers import outlying_markers

    return outlying_markers(model, y, fit.theta, fit.pose, fit.frames_used, threshold, n_rounds, ws)


def _unit(model: Model, k: int) -> str:
    """Unit of parameter ``k``: degrees for axis tilts, the model's length unit otherwise."""
    return "deg" if model.parameters[k].kind == "axis_direction" else model.units


def _undetermined(model: Model, Jq, y) -> str:
    """Names of the pose coordinates that the markers of the best-observed frame do not fix."""
    t = int(np.argmax(np.isfinite(y).all(axis=-1).sum(axis=-1)))
    H = Jq[t].T @ Jq[t]
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    w, V = np.linalg.eigh(H / np.outer(d, d))
    weak = np.abs(V[:, 0]) > 0.3
    names = []
    for k in np.flatnonzero(weak):
        dof = model.dofs[k]
        joint = model.segments[dof.segment].joint
        j = sum(1 for i in range(k) if model.dofs[i].segment == dof.segment)
        names.append(f"{'rotation' if dof.kind == 'R' else 'translation'} {j + 1} of joint {joint.name!r}")
    return ", ".join(names) or "a combination of pose coordinates"


def _bandwidth(rho: float, n: int) -> int:
    """Newey-West lag window from the residual autocorrelation (Andrews' AR(1) rule)."""
    rho = float(np.clip(rho, 0.0, 0.98))
    alpha = 4 * rho**2 / (1 - rho) ** 4 if rho > 0 else 0.0
    L = int(np.ceil(1.1447 * (alpha * n) ** (1 / 3)))
    return int(np.clip(L, 1, max(n // 4, 1)))


def _combine_normal_priors(model: Model, theta, cov):
    prec = np.zeros(model.n_params)
    mean = np.zeros(model.n_params)
    for k, p in enumerate(model.parameters):
        if p.prior.kind == "normal":
            prec[k], mean[k] = 1.0 / p.prior.sd**2, p.prior.mean
    if not prec.any():
        return theta, cov
    A = np.linalg.inv(cov)
    post_cov = np.linalg.inv(A + np.diag(prec))
    return post_cov @ (A @ theta + prec * mean), post_cov
