"""Scale an OpenSim model to a subject: fit body scales and marker offsets, write them back.

The geometry of an imported OpenSim model (see :mod:`skelid.io.osim`) is
``g(theta) = g_base + theta @ A.T`` with one ``scale`` factor ``s_b`` per body
(or ``s_b = (s_x, s_y, s_z)``) multiplying the body's joint frames, markers
and the coupled translations of the joints it is the parent of, and a
``marker_offset`` ``delta_m`` added to each free marker:

.. math:: r_m = S_{b(m)}\\, r_m^0 + \\delta_m, \\qquad
          \\log s_b \\sim N(0, 0.15^2), \\quad \\delta_m \\sim N(0, (10\\,\\mathrm{mm})^2 I).

The fit goes in three steps:

1. the scale factors from skelid's ``marker`` method (poses and geometry by
   joint least squares) with the markers at their nominal places; with several
   trials, from its multi-trial form (:mod:`skelid.estimators.multitrial`);
2. the offsets placed as OpenSim's MarkerPlacer places them: each free marker
   moves to where the first trial saw it in the fitted poses
   (:func:`place_markers`);
3. scales and offsets fitted together on every frame of every trial, as the
   MAP under their priors with every pose profiled out
   (:func:`fit_scales_and_offsets`); its Laplace covariance is the interval, so
   the offsets' uncertainty is carried into the scales. Offsets of all the
   markers of a body trade with the body's pose (and a leaf body's scale with
   its markers' offsets): there the prior decides, the posterior says so, and a
   warning names the scales the data leave to it. The ``marker`` method is then
   run once more with every marker where step 3 put it; its checks (model
   misfit, serially correlated residuals, markers that disagree) give the
   warnings, and where they widen its interval the joint interval is widened by
   each trial's information in it deflated by that trial's ratio (:func:`check_ratios`,
   :func:`deflated_widening`; the markers' placement term excepted, which the offsets already
   carry), never beyond the prior's sd, and not where a soft-tissue slide is estimated with the
   geometry and its steps settled (the misfit those checks widen for is then the slide, whose
   covariance the joint interval already holds); with several trials, the spread of the markers' placement
   from trial to trial is added (:mod:`skelid.estimators.checks.trial_placement`). With one factor per body
   (``scale='bodies'``), a score test per body against one factor per axis
   (:func:`one_factor_test`, Bonferroni over the bodies at 1 %) picks one factor
   per axis for the bodies where the data contradict one and determine three
   within the prior's range (:func:`_per_axis_where_contradicted`), and the
   joint fit is run again with them; the others are named.

Steps 1 and 2 only give the start (and, with ``joint=False``, the answer: the
scales with the markers at their nominal places and the offsets placed after,
their uncertainty not carried into the scales).
Several trials of one subject are read as one recording (:func:`join_trials`: the union of their
markers, a gap of missing frames between trials) and fitted as separate
trials with one geometry.

:func:`write_outputs` writes the scaled ``.osim`` (every other element of the
source kept), an OpenSim ScaleSet, and ``scaling.json`` with each factor and
marker offset and its 95 % interval, its Cramér-Rao bound, the noise level with
its interval, the estimator's settings and, with several trials,
:func:`trials_table`: each trial's own scale factors, the between-trial sd and
the trials' consistency test (also in the report and in ``result.json``). :func:`opensim_ik` runs OpenSim's own
InverseKinematicsTool on a model and a trial and returns its marker RMSE.
"""

from __future__ import annotations

import json
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from skelid._linalg import frame_gram, one_blas_thread
from skelid._stop import interruptible
from skelid.data import MarkerData, unit_scale
from skelid.errors import DataError, SettingError, SkelidWarning
from skelid.estimators.checks.pose_artefact import pose_artefact
from skelid.estimators.checks.trial_placement import trial_placement
from skelid.io.osim import (
    OsimInfo,
    body_scales,
    keep_markers,
    marker_locations,
    mean_places,
    osim_parameters,
    read_osim,
    scales_held,
    widened_offset_priors,
    write_scale_set,
    write_scaled_osim,
)
from skelid.model.description import Model

GAP_FRAMES = 10  # missing frames between joined trials


def join_trials(trials, gap: int = GAP_FRAMES, units: str = "mm") -> MarkerData:
    """Trials of one subject as one recording: the union of their markers, NaN in the gaps.

    Parameters
    ----------
    trials : sequence of MarkerData
        Same sampling rate.
    gap : int
        Frames with every marker missing between two trials.

    Returns
    -------
    MarkerData
        In ``units``; ``meta['trial_frames']`` lists each trial's frame slice ``(start, stop)``.
    """
    trials = list(trials)
    if not trials:
        raise DataError("no trial given", "give at least one marker file")
    rates = {float(t.rate) for t in trials}
    if len(rates) > 1:
        raise DataError(f"the trials have different sampling rates {sorted(rates)} Hz",
                        "resample them to one rate before fitting them together")
    names = []
    for t in trials:
        names += [n for n in t.names if n not in names]
    blocks, slices, start = [], [], 0
    for i, t in enumerate(trials):
        f = unit_scale(t.units, units)
        block = np.full((t.positions.shape[0], len(names), 3), np.nan)
        idx = [names.index(n) for n in t.names]
        block[:, idx] = t.positions * f
        blocks.append(block)
        slices.append((start, start + len(block)))
        start += len(block)
        if i < len(trials) - 1:
            blocks.append(np.full((gap, len(names), 3), np.nan))
            start += gap
    return MarkerData(np.concatenate(blocks), tuple(names), float(trials[0].rate), units,
                      " + ".join(t.source for t in trials), {"trial_frames": slices})


@dataclass
class ScalingFit:
    """An imported model fitted to a subject's trials."""

    model: Model
    info: OsimInfo
    source: str
    marker_set: str | None
    data: MarkerData
    estimator: object
    result: dict
    seconds: float
    dropped_markers: tuple = ()
    warnings: list = field(default_factory=list)
    theta: np.ndarray = field(default_factory=lambda: np.zeros(0))
    joint: JointOffsets | None = None  # scales and offsets fitted together (``joint=True``)
    trials: tuple = ()  # every trial as given, the model's markers in its order (the joint fit's frames)


STATIC_FRAMES = 20
MOVEMENT_FRAMES = 80
#: the first of several trials is a static one where its markers move less than this about the
#: markers' centre (mm rms per coordinate, the 90th percentile over the markers): standing trials of
#: the shared recordings move less than 10 mm, their walks, squats, sit-to-stands and jumps more than 80 mm
STILL_MM = 30.0


def marker_motion(data: MarkerData) -> float:
    """How far a trial's markers move (mm): the 90th percentile over the markers of each one's rms
    displacement per coordinate about its mean place, measured from the markers' centre in each frame
    (a subject who walks or sways as a whole still stands). NaN where no marker is seen twice."""
    p = data.positions * unit_scale(data.units, "mm")
    with warnings.catch_warnings(), np.errstate(invalid="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)  # markers never seen
        c = p - np.nanmean(p, axis=1, keepdims=True)
        rms = np.sqrt(np.nanmean((c - np.nanmean(c, axis=0, keepdims=True)) ** 2, axis=(0, 2)))
    seen = (np.isfinite(p).all(axis=-1).sum(axis=0) > 1) & np.isfinite(rms)
    return float(np.percentile(rms[seen], 90)) if seen.any() else float("nan")


def thin_trial(data: MarkerData, max_frames: int | None, uniform: bool = True) -> MarkerData:
    """A trial cut to at most ``max_frames`` frames.

    Parameters
    ----------
    max_frames : int or None
        None: the trial as it is.
    uniform : bool
        True: every ``k``-th frame with ``k = ceil(F / max_frames)`` and the
        rate divided by ``k`` (the motion model needs equal steps); False:
        ``max_frames`` evenly spaced frames at the original rate.
    """
    F = data.positions.shape[0]
    if max_frames is None or F <= max_frames:
        return data
    if uniform:
        k = -(-F // int(max_frames))
        return MarkerData(data.positions[::k], data.names, data.rate / k, data.units, data.source, data.meta)
    idx = np.unique(np.linspace(0, F - 1, int(max_frames)).round().astype(int))
    return MarkerData(data.positions[idx], data.names, data.rate, data.units, data.source, data.meta)


@interruptible
def fit_osim(osim_path, trials, marker_set=None, scale: str = "linked", markers: str = "offsets",
             method: str = "marker", seed: int = 0, sigma: float | None = None,
             static_frames: int | None = STATIC_FRAMES, movement_frames: int | None = MOVEMENT_FRAMES,
             joined: bool = False, joint: bool = True, cutoff: float | None = None,
             artefact_rms: float | None = None, noise: str = "pooled", limits=None) -> ScalingFit:
    """Fit body scales and marker offsets of an OpenSim model to marker trials.

    Parameters
    ----------
    osim_path : path
    trials : sequence of MarkerData or paths
        A static trial first, then movement trials of one subject (paths are read with
        :func:`skelid.io.read_markers`).
    marker_set : path, optional
        A MarkerSet file for models without markers (default: the one
        :func:`skelid.io.osim.find_marker_set` finds next to the model).
    scale : {'linked', 'bodies', 'axes', 'none'}
        See :func:`skelid.io.osim.osim_parameters`. The default, three factors per body whose logs
        are correlated a priori, is the one whose intervals cover where the truth is scaled per axis
        (one factor per body holds every joint centre on the ray of its generic place, and the
        data, whose markers may move, cannot say it is off: ``benchmarks/opensim_truth.py``).
    markers : {'offsets', 'none'}
        Place the free markers on the first trial after the scale fit (see :func:`place_markers`).
    static_frames : int or None
        The first trial, when movement trials follow it, its markers stand still
        (:func:`marker_motion` below :data:`STILL_MM`) and it has more frames,
        contributes every ``k``-th frame, at most this many, to steps 1 and 2 (a
        static trial repeats one pose). A lone trial, or a first one that moves, is
        a movement trial. None: all.
        The joint fit of scales and offsets uses every frame.
    movement_frames : int or None
        Each movement trial, when it has more frames, contributes every ``k``-th
        frame, at most this many, to steps 1 and 2 (:func:`thin_trial`; the residuals of
        neighbouring frames at motion-capture rates are strongly correlated,
        so thinning costs little information and the serial-correlation
        correction of the interval still applies). None: all.
    joined : bool
        Fit the trials as one recording with gaps (one marker fit, :func:`join_trials`)
        instead of the multi-trial fit (each trial alone, then together).
    joint : bool
        With ``markers='offsets'``: after the scale fit and the placement, fit the
        scales and every offset together on every frame of every trial
        (:func:`fit_scales_and_offsets`); the answer and its intervals are that
        fit's. False: the scales with the markers at their nominal places, the
        offsets placed afterwards and their uncertainty not carried into the scales.
    cutoff, artefact_rms, noise
        The ``skelid fit`` options of the same names, passed to the estimator as for a
        ``.toml`` model (:func:`fit_settings`); one the method does not declare is refused.
    limits : skelid.resources.Limits, optional
        Memory and time the fit may be estimated to need (default from the environment).

    Returns
    -------
    ScalingFit
    """
    trials = checked_trials(trials)
    if markers not in ("offsets", "none"):
        raise SettingError(f"markers={markers!r} is not a marker mode", "use 'offsets' or 'none'")
    full, info = read_osim(osim_path, marker_set)
    given = trials
    trials, multi, data, first_trial = _prepared_trials(trials, method, static_frames, movement_frames, joined)
    present = _present_markers(full, trials, data, multi, osim_path)
    original = keep_markers(full, present)
    dropped = tuple(n for n in full.marker_names if n not in present)
    settings = fit_settings(original, method, multi, sigma, cutoff, artefact_rms, noise)
    _check_cost(osim_parameters(original, info, scale, "none", present), method, trials, limits)
    t0 = time.perf_counter()
    notes, moved, joint_fit = [], {}, None
    with warnings.catch_warnings(), one_blas_thread():
        warnings.simplefilter("ignore", SkelidWarning)  # recorded in the result instead
        if markers == "offsets" and scale != "none":
            moved, note = place_free_markers_first(full, info, scale, trials[0], sigma, seed, settings)
            notes += [note] if note else []
        model = osim_parameters(_with_marker_positions(original, moved), info, scale, "none", present)
        parts = [_select(t, model.marker_names) for t in trials]
        starts = _starts_joint_fit(markers == "offsets" and joint, scale, method, present)
        est, res, theta, poses = _fit_scales(model, parts, data, multi, method, sigma, seed,
                                             dict(settings, **START_ONLY) if starts else settings)
    if markers == "offsets":
        model, theta = _placed_offsets(model, theta, poses[0], parts[0], original, info, scale, present, moved, res)
        if joint and scale != "none" and any(p.kind == "marker_offset" for p in model.parameters):
            stage = _ScaleStage(original, info, present, trials, data, multi, method, sigma, seed, settings)
            model, theta, est, res, joint_fit = _joint_stage(stage, model, theta, given, scale, res)
    warns = _fit_warnings(osim_path, info, notes, res, dropped, multi)
    res = {**res, "first_trial": first_trial}
    frames = [int(t.positions.shape[0]) for t in trials]
    source = " + ".join(t.source or f"trial {k + 1}" for k, t in enumerate(trials))
    shown = MarkerData(np.concatenate([p.positions for p in parts]), model.marker_names, parts[0].rate,
                       parts[0].units, source, {"trial_frames_used": frames})
    return ScalingFit(model, info, str(osim_path), info.marker_set, shown, est, res, time.perf_counter() - t0,
                      dropped, warns, theta, joint_fit, tuple(_select(t, model.marker_names) for t in given))


#: the scale fit's settings where it only starts the joint fit: its estimate without the second-order bias
#: correction and the marker jackknife, which only the interval needs (subject01: 12.6 to 11.0 s CPU, the
#: answer unchanged to 1e-5 sd: the joint fit converges to its own optimum)
START_ONLY = {"bias_correction": "none", "jackknife": False}


def _starts_joint_fit(joint: bool, scale: str, method: str, present) -> bool:
    """Whether the scale fit only starts the joint fit of scales and offsets (``joint``: offsets asked for and
    fitted jointly; some marker present): its checks are then rerun on the joint fit's markers, and its own
    interval stages (:data:`START_ONLY`) are skipped."""
    return joint and scale != "none" and method in ("marker", "marker-multi") and bool(present)


def checked_trials(trials) -> list[MarkerData]:
    """The trials of a fit as :class:`~skelid.data.MarkerData`: marker files are read, anything else refused.

    Raises
    ------
    SettingError
        Where ``trials`` is not a sequence of :class:`~skelid.data.MarkerData` or paths, or is empty.
    """
    from skelid.io import read_markers

    if isinstance(trials, (str, Path, MarkerData)):
        trials = [trials]
    try:
        trials = list(trials)
    except TypeError:
        raise SettingError(f"trials must be a list of marker files or MarkerData, not {type(trials).__name__}",
                           "give a list such as [read_markers('static.trc'), read_markers('walk.trc')]") from None
    if not trials:
        raise DataError("no trial given", "give at least one marker file")
    out = []
    for k, t in enumerate(trials):
        if isinstance(t, (str, Path)):
            t = read_markers(t)
        elif not isinstance(t, MarkerData):
            raise SettingError(f"trial {k + 1} is a {type(t).__name__}, not a marker file or MarkerData",
                               "give paths of marker files or what skelid.io.read_markers returns")
        out.append(t)
    return out


def _prepared_trials(trials, method, static_frames, movement_frames, joined):
    """The trials thinned for steps 1 and 2, whether they are fitted as several trials, the joined recording
    and the result's ``first_trial`` entry (whether it was taken as a static trial, and why).

    The first trial is a static one only when movement trials follow it and its markers stand still
    (:func:`marker_motion` below :data:`STILL_MM`); a lone trial is a movement trial, and so is a
    first trial that moves.
    """
    motion = marker_motion(trials[0])
    static = len(trials) > 1 and motion < STILL_MM
    first = static_frames if static else movement_frames
    trials = [thin_trial(trials[0], first)] + [thin_trial(t, None if joined else movement_frames) for t in trials[1:]]
    multi = len(trials) > 1 and method == "marker" and not joined
    entry = {"static": bool(static), "marker_motion_mm": round(motion, 2) if np.isfinite(motion) else None,
             "still_below_mm": STILL_MM}
    return trials, multi, (join_trials(trials) if not multi else None), entry


def _present_markers(full: Model, trials, data, multi: bool, osim_path) -> list[str]:
    """The model's markers the data hold: in every trial for the several-trial fit, in any for a joined one."""
    def seen_in(t, n):
        return n in t.names and np.isfinite(t.positions[:, t.names.index(n)]).all(axis=-1).any()
    present = [n for n in full.marker_names
               if (all(seen_in(t, n) for t in trials) if multi else seen_in(data, n))]
    if not present:
        names = trials[0].names
        raise DataError(f"none of the {len(full.markers)} markers of {osim_path} is in the data "
                        f"(model: {', '.join(full.marker_names[:4])} ...; data: {', '.join(names[:4])} ...)",
                        "rename the markers in the model's MarkerSet or in the data so that they match")
    return present


#: the prior sd (mm) of the offset of a marker the first placement moved: about its generic place, which is a
#: placeholder (a cluster held at one point) and says little of where the marker sits on this subject
PLACED_OFFSET_SD = 50.0


def _placed_offsets(model, theta, pose, static, original, info, scale, present, moved, res):
    """Step 2: the free markers placed on the first trial; the model with offsets and its ``theta``.

    Each offset's entry is written into ``res``. A free marker that the first placement moved
    (:func:`place_free_markers_first`: a marker set's ``fixed=false`` markers, clusters whose
    place in the generic model is a placeholder) starts from that placement, and its offset's
    prior is :data:`PLACED_OFFSET_SD` wide about its generic place: that place says little of
    where it sits on this subject (a prior of 10 mm around it held thigh clusters placed
    50-100 mm away at the prior's bound: Subject4, noise 32 mm). Centred on the placement
    instead, the trial informed the prior and the likelihood both: on OpenSim-generated
    walks of the Rajagopal model a femur's x and z scales, which only the clusters' placement
    held, came out 0.3-0.6 off with an sd of 0.04.
    """
    offsets, sd, n_eff = place_markers(model, theta, pose, static.positions, (0, static.positions.shape[0]),
                                       [m.name not in info.fixed_markers for m in model.markers])
    centre = {}
    if moved:  # offsets from the model's own marker places: the first placement, scaled, plus the last
        s_body = body_scales(model, theta)
        for i, m in enumerate(model.markers):
            if m.name in moved:
                r0 = np.asarray(original.markers[original.marker_names.index(m.name)].position)
                centre[m.name] = s_body.get(m.segment, np.ones(3)) * (np.asarray(m.position) - r0)
                offsets[i] += centre[m.name]
    start = dict(zip([p.name for p in model.parameters], theta, strict=True))
    model = widened_offset_priors(osim_parameters(original, info, scale, "offsets", present, holders=True),
                                  centre, PLACED_OFFSET_SD)
    theta = np.array([start.get(p.name, 1.0 if p.kind == "scale" else 0.0) for p in model.parameters])
    for k, p in enumerate(model.parameters):
        if p.kind == "marker_offset":
            i = model.marker_names.index(p.target)
            theta[k] = offsets[i, p.axis]
            half = 1.959964 * sd[i, p.axis]
            res[p.name] = {"map": float(offsets[i, p.axis]), "mean": float(offsets[i, p.axis]),
                           "sd": float(sd[i, p.axis]), "ci95": [float(offsets[i, p.axis] - half),
                                                               float(offsets[i, p.axis] + half)],
                           "n_eff": float(n_eff[i]), "method": "placed on the static trial"}
    return model, theta


@dataclass(frozen=True)
class _ScaleStage:
    """What the scale fit of step 1 was given, for its rerun in step 3."""

    original: Model
    info: object
    present: list
    trials: list
    data: MarkerData | None
    multi: bool
    method: str
    sigma: float | None
    seed: int
    settings: dict


def _joint_stage(st: _ScaleStage, model, theta, given, scale, res):
    """Step 3: scales and offsets fitted together, widened by the scale fit's checks.

    Returns ``(model, theta, estimator, result dict, JointOffsets)``; the model gains one factor
    per axis for the bodies where the score test contradicts one (``scale='bodies'``).
    """
    with warnings.catch_warnings(), one_blas_thread():
        warnings.simplefilter("ignore", SkelidWarning)
        ys = [_select(t, model.marker_names).positions for t in given]
        weights = _marker_weights(model, res) if st.settings.get("noise") == "per_marker" else None
        jo = _joint_refinement(model, theta, [_select(t, model.marker_names) for t in given], st.sigma, st.seed,
                               weights)
        tests, axes_notes = {}, []
        if scale == "bodies":
            model, jo, tests, axes_notes = _per_axis_where_contradicted(st, model, jo, ys, weights)
        # the checks (misfit, serial correlation, marker jackknife) of the scale fit with every marker
        # where the joint fit put it: they widen the joint interval, never narrow it
        m3 = _checks_model(model, jo.theta, st.original)
        est, res3, _, _ = _fit_scales(m3, [_select(t, m3.marker_names) for t in st.trials], st.data, st.multi,
                                      st.method, st.sigma, st.seed, st.settings, checks_only=True)
        res3 = _without_carried_warnings(res3, est)
        # the soft-tissue artefact the residuals show: the part of it that mimics the geometry is added
        # (its slopes are estimated with the geometry where it is present: the slide from the model's zero pose)
        art = pose_artefact(model, jo.theta, ys, jo.poses, jo.sigma, jo.cov, weights,
                            reference=np.zeros(jo.poses[0].shape[1]))
        # markers that sit elsewhere on the body in each trial (the slide's mean follows the trial's mean pose)
        offsets = np.array([p.kind == "marker_offset" for p in model.parameters])
        placed = trial_placement(jo.info_trials, jo.score_trials, jo.cov, offsets)
    bound = np.sqrt(np.clip(np.diag(jo.cov), 0.0, None))
    widen = np.ones(model.n_params)
    before = jo  # the fit the checks' ratios deflate, before the slide moves it
    # never wider than the prior: the data cannot leave a parameter less known than before them (a static
    # trial's checks' ratio, 70 on subject01 and 10^6 on an exactly fitted one, asked for far more)
    # the interval with each marker's own noise level (the sandwich), widened by the checks and by the
    # fit's errors on data simulated from its own answer (whichever asks for more)
    held = _on_bounds(model, jo.theta)  # the fit's own optimum, before the correction moves it off a bound
    jo, checked, base, slide, art, steps, settled = _with_slide(model, jo, art, ys, weights)
    if slide is not None:
        bound = _sd(slide.cov)
    if not settled:  # settled, the slide the scale fit's checks widen for is in the slide's covariance already
        ratios = _on_scales(model, m3, check_ratios(est, m3))
        widen[:ratios.shape[1]] = deflated_widening(before, _prior_terms(model, before.theta)[1], ratios)
    bias, boot, boot_entry, bias_var = bootstrap_check(model, checked, ys, base if slide is None else checked.cov,
                                                       st.sigma if slide is None else None, weights, st.seed)
    base = base + np.diag(bias_var)  # the correction's own noise
    jo = _corrected(model, jo, bias, ys, weights)
    psd = prior_sd(_prior_terms(model, jo.theta)[1])
    widen = np.maximum(np.minimum(np.maximum(widen, boot), psd / np.maximum(bound, 1e-300)), 1.0)
    jo = replace(jo, cov=base * np.outer(widen, widen) + (art.cov if slide is None else 0.0) + placed.cov)
    out = _joint_result(model, jo, res3, widen, bound, st.sigma, weights, held)
    ratio = _artefact_ratio(art, bound) if slide is None else np.abs(slide.shift) / _sd(slide.cov)
    out["artefact"] = _artefact_entry(art, ratio, slide, model, (steps, settled))
    if out["artefact"]["warn"]:
        out["warnings"] = list(out.get("warnings", [])) + [_artefact_warning(model, art, ratio, slide,
                                                                             out["artefact"])]
    out["bootstrap"] = boot_entry
    out["trial_placement"] = _placement_entry(placed, bound)
    if out["trial_placement"]["warn"]:
        out["warnings"] = list(out.get("warnings", [])) + [_placement_warning(model, placed, bound, len(given))]
    if tests:
        out["one_factor_test"] = tests
    if axes_notes:
        out["warnings"] = list(out.get("warnings", [])) + axes_notes
    return model, jo.theta, est, out, jo


def _corrected(model: Model, jo: JointOffsets, bias, ys, weights) -> JointOffsets:
    """``jo`` with the bias taken off ``theta`` (within the prior's bounds) and every pose fitted again
    there, so that the poses, residuals and noise levels that the result, the written trials and the
    model average use are those of the reported geometry."""
    from skelid.estimators.fit.pose import workspace

    lo, hi = _prior_bounds(model)
    theta = np.clip(jo.theta - bias, lo, hi)
    ws = workspace(model)
    poses = [_trial_cost(model, theta, y, q, ws, weights, POSE_ITER)[0] for y, q in zip(ys, jo.poses, strict=True)]
    return replace(jo, theta=theta, poses=poses)


#: the artefact's term is named in a warning where it widens some sd by at least this share of the bound
#: (an estimate it could move by half an sd, as for the misfit test)
ARTEFACT_EFFECT = 0.5


def _prior_bounds(model: Model) -> tuple[np.ndarray, np.ndarray]:
    """``(lower, upper)``: each parameter's prior bounds."""
    return (np.array([p.prior.lower for p in model.parameters]), np.array([p.prior.upper for p in model.parameters]))


def _sd(cov) -> np.ndarray:
    return np.maximum(np.sqrt(np.clip(np.diag(cov), 0.0, None)), 1e-300)


def _slide_fit(model: Model, jo, art):
    """The joint fit with the artefact's slopes estimated beside the geometry (None where none is present, or
    where the slopes cannot be told from the geometry: :func:`~skelid.estimators.checks.pose_artefact.joint_slide`
    raises)."""
    from skelid.estimators.checks.pose_artefact import joint_slide

    if art.slide is None or not jo.info_trials:
        return None
    s2 = np.asarray(jo.sigma, float) ** 2  # each trial's information and score back to unit noise
    info = sum(s * info_k for s, info_k in zip(s2, jo.info_trials, strict=True))
    score = sum(s * g for s, g in zip(s2, jo.score_trials, strict=True))
    grad, curv = _prior_terms(model, jo.theta)
    try:
        return joint_slide(art.slide, info, score, grad, curv, float(np.sum(jo.dof)))
    except np.linalg.LinAlgError:  # the slopes cannot be told from the geometry: the artefact's term instead
        return None


#: Gauss-Newton steps of the geometry with the slide's slopes (:func:`_slide_converged`) at most, and the
#: step (in sd) below which they stop
SLIDE_STEPS = 12
SLIDE_STEP_SD = 0.05
#: ... and a step is taken only if at most this share of the one before (the steps settle geometrically, not
#: always fast at first: 11.6, 9.4, 1.6, 0.27 sd on an OpenSim-generated walk, whose second step 0.7 refused)
SLIDE_CONTRACTION = 0.9


def _slide_converged(model: Model, jo, art, ys, weights):
    """:func:`_slide_fit` iterated towards the joint optimum of the geometry, the slopes and the poses.

    Each step fits the poses to the markers less the slide the last step estimated, then takes the
    joint estimate's step from there. A single step from the fit that ignores the slide leaves the
    poses to absorb the slide's rigid part (on OpenSim-generated walks the second step still moved
    the geometry by 4-8 sd). The slide's sizes are those of the first step until the steps fall
    below :data:`SLIDE_STEP_SD`, then estimated once more where the fit has arrived. The poses are
    fitted with the slide held where the last step put it, which converges only where the slide
    turns with the pose much less than the markers do: a step not at most :data:`SLIDE_CONTRACTION`
    of the one before is not taken, and the fit stays where it was (on subject01's walk, whose
    slopes come out near 100 mm per radian, the steps stay at 7-19 sd and the slide grows without end).

    Returns ``(SlideFit, artefact, steps, settled)``: the fit's ``shift`` is from ``jo.theta``, its
    covariance that of the last linearisation; ``artefact`` is ``art`` with that step's slide terms
    (the directions its slopes are in); ``settled`` whether the steps fell below :data:`SLIDE_STEP_SD`.
    """
    from skelid.estimators.checks.pose_artefact import joint_slide, slide_displacement
    from skelid.estimators.fit.joint import row_weights
    from skelid.estimators.fit.pose import workspace

    slide = _slide_fit(model, jo, art)
    if slide is None:
        return None, art, 0, False
    lo, hi = _prior_bounds(model)
    theta, poses, sl, ws = np.clip(jo.theta + slide.shift, lo, hi), jo.poses, art.slide, workspace(model)
    sizes, phase, steps = slide.sizes, 0, 1
    last = float(np.max(np.abs(slide.shift) / _sd(slide.cov)))
    while steps < SLIDE_STEPS:
        moved = slide_displacement(model, theta, poses, sl, slide.slopes)
        info, score, new_poses = 0.0, 0.0, []
        for y, q, d in zip(ys, poses, moved, strict=True):
            q, r, Jq, Jt = _posed_terms(model, theta, y - d, q, ws, weights)
            sw = row_weights(weights, y)
            seen = np.repeat(np.isfinite(y).all(axis=-1), 3, axis=1)  # the slide back on the residuals seen
            terms = _summed_terms(model.dim, q, r + d.reshape(len(d), -1) * seen * (1.0 if sw is None else sw), Jq, Jt)
            info, score = info + terms[1], score + terms[2]
            new_poses.append(q)
        a = pose_artefact(model, theta, ys, new_poses, jo.sigma, jo.cov, weights, reference=np.zeros(q.shape[1]),
                          tested=False)
        if a.slide is None:
            break
        grad, curv = _prior_terms(model, theta)
        try:
            nxt = joint_slide(a.slide, info, score, grad, curv, float(np.sum(jo.dof)), None if phase == 1 else sizes,
                              start=sizes)
        except np.linalg.LinAlgError:  # the slopes no longer told from the geometry: the last step stands
            break
        size = float(np.max(np.abs(nxt.shift) / _sd(nxt.cov)))
        if size > SLIDE_CONTRACTION * last and size >= SLIDE_STEP_SD:  # not settling: stay, with this point's cov
            return replace(nxt, shift=theta - jo.theta, slopes=slide.slopes), replace(art, slide=sl), steps, False
        steps += 1
        theta, poses, sl, slide, last = np.clip(theta + nxt.shift, lo, hi), new_poses, a.slide, nxt, size
        if phase == 1:  # the sizes estimated where the fit has arrived: kept from here
            sizes, phase = slide.sizes, 2
        if size < SLIDE_STEP_SD:
            if phase == 2:
                return replace(slide, shift=theta - jo.theta), replace(art, slide=sl), steps, True
            phase, last = 1, np.inf
    return replace(slide, shift=theta - jo.theta), replace(art, slide=sl), steps, False


def _with_slide(model: Model, jo, art, ys, weights) -> tuple:
    """The joint fit moved to the slide's estimate (:func:`_slide_converged`), where there is one.

    Returns ``(jo, checked, base, slide, artefact, steps, settled)``: ``jo`` at the slide's geometry with
    its poses there; ``base`` the interval before any widening (the slide's covariance, else the fit's
    with each marker's own noise level); ``checked`` what data simulated from the fit
    (:func:`bootstrap_check`) start from: with a slide, ``jo`` with the white noise level the slide
    leaves for every trial and marker and the information and Laplace covariance at that level there,
    so that the simulated data carry the noise that is left, not the slide taken for noise (a pelvis
    scale's "bias" at the slide-blind fit's marker levels reached 6 sd on an OpenSim-generated walk,
    and moved it 7 sd from the truth; with the information of the fit before the slide, 157 sd).
    """
    slide, art, steps, settled = _slide_converged(model, jo, art, ys, weights)
    if slide is None:
        return jo, jo, (jo.cov if jo.cov_noise is None else jo.cov_noise), None, art, steps, settled
    from skelid.estimators.fit.pose import workspace

    lo, hi = _prior_bounds(model)
    theta, ws = np.clip(jo.theta + slide.shift, lo, hi), workspace(model)
    there = [_trial_terms(model, theta, y, q, ws, weights, POSE_ITER) for y, q in zip(ys, jo.poses, strict=True)]
    jo = replace(jo, theta=theta, poses=[t[0] for t in there])
    white = slide.sigma_white  # the information where the fit has arrived (the simulated fits' steps start there)
    info = tuple(t[1] / white**2 for t in there)
    checked = replace(jo, cov=_posterior(model, sum(info), _prior_terms(model, theta)[1])[1], info_trials=info,
                      sigma=np.full(len(ys), white),
                      marker_sd=None if jo.marker_sd is None else np.full_like(jo.marker_sd, white))
    return jo, checked, slide.cov, slide, art, steps, settled


def _artefact_ratio(art, bound) -> np.ndarray:
    """Per parameter, the sd the artefact's term adds over the sd the residuals alone give."""
    return _sd(art.cov) / np.maximum(bound, 1e-300)


def _artefact_entry(art, ratio, slide=None, model: Model | None = None, steps=(0, False)) -> dict:
    """The result's ``artefact`` entry: what the residuals show of a pose-dependent artefact.

    With ``slide`` (its slopes estimated with the geometry) the sizes are the joint fit's,
    ``largest_sd_ratio`` is the largest step it took, in the step's sd, ``mean_place_mm``
    where each of the ``model``'s markers sits on average over the trials from its offset's place
    (the slide at the trials' mean pose, body frame: the place the written model takes), and
    ``by_body`` each body's shared slope sd and the rms its markers slide by over the trials'
    poses; else the sd the artefact's term adds over the residuals' own.
    """
    entry = {"present": bool(art.present), "p_value": float(art.p_value),
             "rms": float(art.rms if slide is None else slide.rms),
             "slope_sd_shared": float(art.tau_shared if slide is None else slide.tau_shared),
             "slope_sd_own": float(art.tau_own if slide is None else slide.tau_own),
             "sigma_white": list(art.sigma_white) if slide is None else [slide.sigma_white] * len(art.sigma_white),
             "largest_sd_ratio": float(ratio.max(initial=0.0)),
             "estimated_with_geometry": slide is not None,
             "warn": bool(art.present and ratio.max(initial=0.0) >= ARTEFACT_EFFECT),
             "method": "residuals against a marker slide linear in the joint angles (skelid.estimators.checks."
                       "pose_artefact)"}
    if slide is not None:
        entry["method"] += "; its slopes estimated with the geometry (joint_slide), iterated to the optimum"
        entry["steps"], entry["settled"] = int(steps[0]), bool(steps[1])
        mean = np.einsum("mac,c->ma", slide.slopes, art.slide.mean_dr)
        entry["mean_place_mm"] = {n: [float(v) for v in mean[i]] for i, n in enumerate(model.marker_names)}
        entry["by_body"] = {
            model.segments[model.marker_segment[idx[0]]].name: {
                "slope_sd_shared": float(t), "rms": float(np.sqrt((t**2 + slide.tau_own**2) * art.slide.pose_spread))}
            for idx, t in zip(art.slide.bodies, slide.tau_bodies, strict=True)}
    return entry


def _artefact_warning(model: Model, art, ratio, slide=None, entry=None) -> str:
    """One line naming the artefact the residuals show and what it does to the intervals."""
    k = int(np.argmax(ratio))
    if slide is not None:
        held = "" if (entry or {}).get("settled", True) else (
            f"; its estimate did not settle and was kept after {entry['steps']} step(s): the slide turns with the "
            "pose nearly as much as the markers do, more than a linear slide holds")
        return (f"the residuals follow the pose: a soft-tissue artefact of about {slide.rms:.2g} {model.units} rms "
                f"per marker coordinate (F test p = {art.p_value:.1e}), its slopes estimated with the geometry "
                f"and integrated out of the intervals; it moved {model.parameter_names[k]} by {ratio[k]:.1f} sd "
                f"(white noise left: {slide.sigma_white:.2g} {model.units}){held}")
    return (f"the residuals follow the pose: a soft-tissue artefact of about {art.rms:.2g} {model.units} rms per "
            f"marker coordinate (F test p = {art.p_value:.1e}); the part of it that looks like a change of the "
            f"geometry is in the intervals (the largest effect: {model.parameter_names[k]}, "
            f"{ratio[k]:.1f} times the sd the residuals alone give)")


def _placement_entry(placed, bound) -> dict:
    """The result's ``trial_placement`` entry: how far the trials' marker placements differ."""
    ratio = _artefact_ratio(placed, bound)
    return {"present": bool(placed.present), "p_value": float(placed.p_value), "sd_between_trials": float(placed.tau),
            "largest_sd_ratio": float(ratio.max(initial=0.0)),
            "warn": bool(placed.present and ratio.max(initial=0.0) >= ARTEFACT_EFFECT),
            "method": "a random effect on each trial's marker offsets, sized from the trials' scores "
                      "(skelid.estimators.checks.trial_placement)"}


def _placement_warning(model: Model, placed, bound, n_trials: int) -> str:
    """One line naming the placement spread between the trials and what it does to the intervals."""
    ratio = _artefact_ratio(placed, bound)
    k = int(np.argmax(ratio))
    return (f"the {n_trials} trials see the markers at different places on the body: about {placed.tau:.2g} "
            f"{model.units} per offset coordinate from trial to trial (test p = {placed.p_value:.1e}), as skin "
            f"that slides with each trial's mean pose does; that spread is in the intervals (the largest effect: "
            f"{model.parameter_names[k]}, {ratio[k]:.1f} times the sd the residuals alone give)")


def _per_axis_where_contradicted(st: _ScaleStage, model, jo, ys, weights):
    """Where the data contradict one factor per body (:func:`one_factor_test`), one factor per axis, refitted.

    A contradicted body is fitted per axis only where its three factors are identified
    (:data:`AXES_IDENTIFIED`) and both the one-step estimate and the refit keep each within its
    prior's central 99 % (:data:`AXES_PLAUSIBLE_SD`): a factor beyond it is a misfit that the
    extra freedom absorbs (marker places, joint centres, soft tissue), not the body's
    proportions (on real walks fitted per axis: a pelvis height of 0.59, a tibia width at the
    bound 2.1, and OpenSim's IK 60 mm off the markers). Another contradicted body keeps its one
    factor and is named.

    Returns ``(model, JointOffsets, tests, notes)``.
    """
    from skelid.estimators.checks.pose_artefact import pose_artefact

    per_axis = osim_parameters(st.original, st.info, "axes", "offsets", st.present, holders=True)
    th = _map_theta(jo.theta, model, per_axis)
    art = pose_artefact(per_axis, th, ys, jo.poses, jo.sigma, np.eye(per_axis.n_params), weights)
    tests = one_factor_test(model, per_axis, jo, ys, weights, art.score_cov if art.present else None)
    flagged = [b for b, t in tests.items() if t["p"] < AXES_TEST_LEVEL / len(tests)]
    one_step = _mixed_scales(model, per_axis, flagged)
    th1 = _map_theta(jo.theta, model, one_step)
    for k, p in enumerate(one_step.parameters):
        if p.kind == "scale" and p.target in flagged and p.axis is not None:
            th1[k] += tests[p.target]["step"][p.axis]
    wild = _implausible_bodies(one_step, th1, flagged)
    switch = [b for b in flagged if tests[b]["identified"] and b not in wild]
    if switch:
        model, jo, switch = _refit_per_axis(st, model, per_axis, jo, ys, weights, switch)
    for b, t in tests.items():
        t["fitted_per_axis"] = b in switch
    return model, jo, tests, _axes_notes(tests, switch, [b for b in flagged if b not in switch])


def _refit_per_axis(st: _ScaleStage, model, per_axis, jo, ys, weights, switch):
    """The joint fit with ``switch``'s bodies per axis, less those whose refit leaves the prior's 99 %.

    Returns ``(model, JointOffsets, bodies fitted per axis)``.
    """
    def refit(bodies):
        new = _mixed_scales(model, per_axis, bodies)
        return new, fit_scales_and_offsets(new, ys, _map_theta(jo.theta, model, new), jo.poses, st.sigma,
                                           weights=weights)

    new, fit = refit(switch)
    wild = _implausible_bodies(new, fit.theta, switch)
    if wild:  # once more without them, and that refit stands
        switch = [b for b in switch if b not in wild]
        if not switch:
            return model, jo, []
        new, fit = refit(switch)
    return new, fit, switch


def _axes_notes(tests: dict, switch, kept) -> list[str]:
    """The warnings of the one-factor test: the bodies fitted per axis, and those contradicted but kept."""
    notes = []
    if switch:
        notes.append(f"one scale factor for {', '.join(switch)} is contradicted by the data (score test against "
                     "one factor per axis, p = " + ", ".join(f"{tests[b]['p']:.1e}" for b in switch)
                     + "): fitted with one factor per axis")
    if kept:
        notes.append(f"one scale factor for {', '.join(kept)} is contradicted by the data (p = "
                     + ", ".join(f"{tests[b]['p']:.1e}" for b in kept) + "), but per axis these trials would not "
                     "determine its factors or would put one outside the prior's 99 %: more likely a misfit of the "
                     "model (marker places, joint centres, soft tissue) than of its proportions; one factor kept")
    return notes


#: a factor fitted per axis is plausible within this many prior sd of the prior's median (its central 99 %)
AXES_PLAUSIBLE_SD = 2.576


def _implausible_bodies(model: Model, theta, bodies) -> list[str]:
    """Of ``bodies``, those with a scale factor beyond :data:`AXES_PLAUSIBLE_SD` prior sd of its median."""
    out = []
    for k, p in enumerate(model.parameters):
        if p.kind == "scale" and p.target in bodies and p.prior.kind == "lognormal":
            z = abs(np.log(max(float(theta[k]), 1e-12)) - np.log(p.prior.mean)) / p.prior.sd
            if z > AXES_PLAUSIBLE_SD and p.target not in out:
                out.append(p.target)
    return out


def _fit_warnings(osim_path, info, notes, res, dropped, multi) -> list[str]:
    """Every warning of an .osim fit, once each: the marker set, the placement, the fit, the markers left out."""
    warns = []
    if info.marker_set_found_by:
        warns.append(f"{Path(osim_path).name} has no markers: {info.marker_set_found_by}")
    warns += notes + list(res.get("warnings", []))
    if dropped:
        warns.append(f"{len(dropped)} model markers are not in the data"
                     + (" (of every trial)" if multi else "") + f" and were left out: {', '.join(dropped)}")
    return list(dict.fromkeys(warns))


def fit_settings(model: Model, method: str, multi: bool, sigma: float | None = None, cutoff: float | None = None,
                 artefact_rms: float | None = None, noise: str = "pooled") -> dict:
    """The scale fit's estimator settings from the ``skelid fit`` options, built as for a ``.toml`` model.

    The options are checked (:func:`skelid.workflows.check_options`) and mapped onto the
    settings the estimator declares (:func:`skelid.registry.settings_from_options`): the
    several-trial :class:`~skelid.estimators.multitrial.MultiTrialEstimator` with ``multi``,
    else the class of ``method``.

    Raises
    ------
    SkelidError
        An unusable value, or an option the method does not use (one line naming it).
    """
    from skelid import registry, workflows
    from skelid.estimators.multitrial import MultiTrialEstimator

    workflows.check_options(model, sigma, cutoff, artefact_rms)
    cls = MultiTrialEstimator if multi else registry.estimator_class(method)
    return registry.settings_from_options(cls, workflows.fit_options(sigma, cutoff, artefact_rms, noise), method)


def _check_cost(model: Model, method: str, trials, limits) -> None:
    """Refuse a fit estimated to need more memory or time than ``limits`` (before any fitting)."""
    from skelid import workflows

    workflows.check_cost(model, method, sum(int(t.positions.shape[0]) for t in trials), limits)


def with_alternatives(fit: ScalingFit, alternatives, trials, **options) -> ScalingFit:
    """``fit`` with the spread and the average of its scale factors and lengths over alternative OpenSim
    models of the same body.

    The trials are refitted under each alternative ``.osim`` model (another joint model, another
    generic model) with the same ``options`` (the keywords of :func:`fit_osim`), and every scale
    factor and length that at least two models share (by name) gets its spread
    (:func:`skelid.sensitivity.model_spread`), in ``fit.result["model_sensitivity"]``. Under
    ``"average"``, the models' average (:func:`skelid.sensitivity.average_of`): each model weighted by
    stacking over one-second blocks of the trials' frames, its log density there that of the joint fit's
    residuals over the markers every model has; a scale factor's mixture taken in log space.

    Raises
    ------
    DataError
        An alternative that is not an ``.osim`` model, or two models of one file name.
    """
    from skelid.sensitivity import average_of, block_log_density, model_spread

    def scales(f):
        """Each scale factor (relative to its model's own generic geometry) and each joint-to-joint length
        (mm, the same quantity whatever the model's generic geometry)."""
        out = {p.name: {"value": float(f.result[p.name]["map"]), "sd": float(f.result[p.name]["sd"])}
               for p in f.model.parameters if p.kind == "scale"}
        return out | {f"length {n}": {"value": float(e["value"]), "sd": float(e["sd"])}
                      for n, e in (f.result.get("lengths") or {}).items()}

    done = {Path(fit.source).name: fit}
    for path in alternatives:
        name = Path(path).name
        if not name.lower().endswith(".osim"):
            raise DataError(f"--alternative {path}: an OpenSim model's alternative must be an .osim model",
                            "give another .osim model of the same body")
        if name in done:
            raise DataError(f"model alternatives need distinct file names; {name} is given twice",
                            "rename one of the model files")
        done[name] = fit_osim(path, trials, **options)
    fits = {name: scales(f) for name, f in done.items()}
    shared = [n for n in fit.model.marker_names if all(n in f.model.marker_names for f in done.values())]
    if not shared:
        raise DataError(f"the model alternatives share no marker with {Path(fit.source).name}, so their fits "
                        "cannot be weighed", "give alternatives of the same body with the same markers")
    frames = [_fit_frames(f, shared) for f in done.values()]
    lp = block_log_density([f for f, _ in frames], frames[0][1], [f.model.n_params for f in done.values()])
    sens = {"models": list(fits), "estimates": fits, "spread": model_spread(fits),
            "average": average_of(lp, fits, log=[q for f in fits.values() for q in f if q.startswith("scale")])}
    return replace(fit, result={**fit.result, "model_sensitivity": sens})


def _fit_frames(fit: ScalingFit, names) -> tuple[list[np.ndarray], list[float]]:
    """:func:`skelid.sensitivity.frame_log_density` of every trial of an OpenSim fit over the markers
    ``names``, and the rate of those frames: the joint fit's residuals at every frame at each trial's
    noise level; where the scales and offsets were not fitted together, the scale fit's on the frames
    it used (every k-th)."""
    from skelid.model.kinematics import forward_kinematics
    from skelid.sensitivity import frame_log_density

    model = fit.model
    idx = [model.marker_names.index(n) for n in names]
    out, rates = [], []
    if fit.joint is None:
        for e, t in zip(getattr(fit.estimator, "trials_", None) or [fit.estimator], fit.trials, strict=True):
            r = np.asarray(e.residuals_)
            out.append(np.where(e.frames_used_, frame_log_density(r[:, idx], float(e.sigma_), model.dim,
                                                                  model.n_pose), np.nan))
            rates.append(float(t.rate) * r.shape[0] / max(1, t.positions.shape[0]))
        return out, rates
    for k, t in enumerate(fit.trials):
        x = forward_kinematics(model, fit.joint.theta, fit.joint.poses[k]).markers[:, idx]
        y = t.positions[:, [t.names.index(n) for n in names]] * unit_scale(t.units, model.units)
        out.append(frame_log_density(np.linalg.norm(y - x, axis=-1), float(fit.joint.sigma[k]), model.dim,
                                     model.n_pose))
        rates.append(float(t.rate))
    return out, rates


def place_free_markers_first(full: Model, info: OsimInfo, scale: str, static: MarkerData, sigma=None,
                             seed: int = 0, settings: dict | None = None) -> tuple[dict, str | None]:
    """Free markers placed on the static trial after a scale fit to its fixed (anatomical) markers.

    OpenSim marks a marker ``fixed`` when its place on the body is known (a
    bony landmark) and leaves the others (clusters on the thigh or shank) to
    be placed on the subject; a generic model may hold them at one
    placeholder point. Fitted at their nominal places they would drive the
    scales. So first the static trial is fitted with the fixed markers only
    (OpenSim's order: scale on the landmarks, then place the others), and each
    free marker on a body that pass reaches is moved to where the static
    trial saw it: ``r_m^0 = S_b^{-1} mean_t R_t^T (y_mt - p_t)``. The fit of
    all trials then starts from those places.

    The first pass is a :class:`~skelid.estimators.marker.MarkerEstimator` with those of
    ``settings`` (:func:`fit_settings`) that it declares.

    Returns
    -------
    moved : dict
        Marker name -> new nominal position (segment frame, mm); empty when
        the model has no fixed markers or no free ones, or the static trial
        does not fix the poses with its fixed markers alone.
    note : str or None
        What was done, for the warnings.
    """
    from skelid.errors import SkelidError
    from skelid.estimators.marker import MarkerEstimator
    from skelid.model.kinematics import forward_kinematics

    def seen(n):
        return n in static.names and np.isfinite(static.positions[:, static.names.index(n)]).all(axis=-1).any()

    fixed = [m.name for m in full.markers if m.name in info.fixed_markers and seen(m.name)]
    free = [m.name for m in full.markers if m.name not in info.fixed_markers and seen(m.name)]
    if not fixed or not free:
        return {}, None
    m1 = osim_parameters(keep_markers(full, fixed), info, scale, "none", fixed)
    if not m1.n_params:
        return {}, None
    try:
        with warnings.catch_warnings():  # a first pass: its warnings are not the answer's
            warnings.simplefilter("ignore", SkelidWarning)
            own = {s.name for s in MarkerEstimator.settings}
            kw = {k: v for k, v in ({"sigma": sigma} if settings is None else settings).items() if k in own}
            est = MarkerEstimator(m1, **{**kw, "rng": np.random.default_rng(seed)}).fit(
                _select(static, m1.marker_names))
    except SkelidError as exc:
        return {}, ("free markers placed after the scale fit only: a fit of the static trial's fixed markers "
                    f"failed ({exc.problem})")
    kin = forward_kinematics(m1, est.theta_, est.pose_)
    seg = {s.name: i for i, s in enumerate(m1.segments)}
    scales = body_scales(m1, est.theta_)
    y = _select(static, free).positions
    moved = {}
    for j, n in enumerate(free):
        b = full.markers[full.marker_names.index(n)].segment
        if b not in seg:
            continue
        i = seg[b]
        r = np.einsum("tji,tj->ti", kin.R_world_seg[:, i], y[:, j] - kin.p_world_seg[:, i])
        ok = np.isfinite(r).all(axis=-1) & np.asarray(est.frames_used_, bool)
        if ok.any():
            moved[n] = tuple(float(v) for v in r[ok].mean(axis=0) / scales.get(b, np.ones(3)))
    return moved, (f"{len(moved)} free markers were placed on the static trial after a scale fit to its "
                   f"{len(fixed)} fixed markers, before the fit of every trial")


def _with_marker_positions(model: Model, moved: dict) -> Model:
    """``model`` with the markers in ``moved`` at their new positions."""
    if not moved:
        return model
    mk = tuple(replace(m, position=moved[m.name]) if m.name in moved else m for m in model.markers)
    return Model(model.name, model.dim, model.units, model.segments, mk)


def _select(t: MarkerData, names) -> MarkerData:
    """``t`` with the columns ``names`` in that order, in millimetres."""
    f = unit_scale(t.units, "mm")
    return MarkerData(t.positions[:, [t.names.index(n) for n in names]] * f, tuple(names), t.rate, "mm",
                      t.source, t.meta)


def _as_dict(r) -> dict:
    from skelid.io.legacy import summary_dict

    return dict(r) if isinstance(r, dict) else summary_dict(r)


#: a scale fit that does not converge is tried once more with this many times the iterations (the scale fit
#: with the markers at their nominal places is misspecified by their offsets and may creep along a flat
#: direction: on exact OpenSim data, 1 walk in 4 still moved 0.3 sd after 100 further iterations)
RETRY_ITER_FACTOR = 4


def _fit_scales(model, parts, data, multi, method, sigma, seed, settings: dict | None = None,
                checks_only: bool = False):
    """The scale fit: ``(estimator, result dict, theta, [pose (F_k, Q) of each trial])``.

    ``settings``: the estimator's settings (:func:`fit_settings`; default: ``sigma`` only). The
    scale fit only starts the joint fit of scales and offsets (or, ``checks_only``, gives its
    checks), so a fit that does not converge is not fatal: it is tried once more with
    :data:`RETRY_ITER_FACTOR` times the iterations, and its estimate then kept as it stands with
    the ``not-converged`` warning (``checks_only``: kept at once). Only the marker methods.
    """
    from skelid.errors import ConvergenceError

    settings = dict(settings or {"sigma": sigma})
    marker = method in ("marker", "marker-multi")
    if marker and checks_only:
        # the checks' ratios compare the data sd with the plain one; the bias and spread of the estimate that is
        # reported are the joint fit's own (:func:`bootstrap_check`), not this fit's second-order correction
        settings |= {"on_nonconvergence": "warn", "bias_correction": "none"}
    try:
        return _fit_scales_once(model, parts, data, multi, method, sigma, seed, settings)
    except ConvergenceError:
        if not marker:
            raise
        from skelid.estimators.marker import MarkerEstimator

        more = dict(settings, on_nonconvergence="warn")
        more["n_iter"] = RETRY_ITER_FACTOR * int(more.get("n_iter") or MarkerEstimator(model).n_iter)
        return _fit_scales_once(model, parts, data, multi, method, sigma, seed, more)


def _fit_scales_once(model, parts, data, multi, method, sigma, seed, settings: dict | None = None):
    """:func:`_fit_scales` without the retry."""
    rng = np.random.default_rng(seed)
    settings = {"sigma": sigma} if settings is None else dict(settings)
    if not model.n_params:  # nothing to scale: poses of the nominal model on the static trial only
        from skelid.estimators.fit.pose import track_poses

        theta = np.zeros(0)
        return None, {"warnings": []}, theta, [track_poses(model, theta, parts[0].positions, rng)[0]]
    if multi:
        from skelid.estimators.multitrial import MultiTrialEstimator

        est = MultiTrialEstimator(model, **{**settings, "rng": rng}).fit(parts)
        edges = np.cumsum([0] + [len(p.positions) for p in parts])
        poses = [est.pose_[a:b] for a, b in zip(edges[:-1], edges[1:], strict=True)]
        return est, _as_dict(est.result()), np.asarray(est.theta_, float), poses
    from skelid.registry import make_estimator

    sub = _select(data, model.marker_names)
    est = make_estimator(method, model, None, **{**settings, "rng": rng})
    est.fit(sub)
    poses = [est.pose_[a:b] for a, b in data.meta["trial_frames"]]
    return est, _as_dict(est.result()), np.asarray(est.theta_, float), poses


#: relative change of the residual sum of squares, and largest step in prior sd, that end the joint refinement
JOINT_TOL = 1e-12
JOINT_STEP_SD = 1e-7
JOINT_ITER = 60
#: Levenberg-Marquardt iterations of each pose fit inside the joint fit (warm-started from the last
#: iterate's poses, which a small step of the geometry moves little); the last evaluation fits every
#: pose to convergence (:data:`POSE_ITER`). On subject01 (static + walk): converged in 36 iterations,
#: 46 s CPU, against 30 full pose fits per iteration that stopped unconverged at 30 iterations, 71 s
JOINT_POSE_ITER = 4
#: a pose fit's iterations where it must converge
POSE_ITER = 30
#: Newton decrement (squared length of the step in posterior sd) below which the joint fit is at its optimum
JOINT_DECREMENT = 1e-3
#: halvings of a joint-fit step tried before the full step is taken anyway (the noise levels re-estimated after it)
JOINT_HALVINGS = 8
#: noise-free data: the noise level is rounding, not zero; its floor, relative to the model's size, is the
#: marker estimator's (:data:`skelid.estimators.marker.NUMERICAL_RESIDUAL`: 1e-3 mm on a 1 m body). With a
#: floor of 1e-6 mm the weights of the data (1e12) left the joint fit of an exact gait2354 walk unconverged
#: after 100 iterations (72 s); with this one it converged in 10 (19 s), to the same scales.
SIGMA_FLOOR = 1e-6


@dataclass(frozen=True)
class JointOffsets:
    """Scales and marker offsets fitted together (:func:`fit_scales_and_offsets`)."""

    theta: np.ndarray  # (P,) MAP of every parameter of the model
    cov: np.ndarray  # (P, P) Laplace covariance: (S / sigma^2 + prior precision)^-1
    poses: list  # [(F_k, Q)] per trial
    sigma: np.ndarray  # (K,) noise sd per trial (mm)
    dof: np.ndarray  # (K,) residual degrees of freedom per trial
    edf: float  # effective number of parameters the data determine
    n_iter: int
    converged: bool
    prior_only: tuple = ()  # scale parameters the data leave to the prior
    info_trials: tuple = ()  # [(P, P)] each trial's information S_k / sigma_k^2 (their sum is the data's)
    score_trials: tuple = ()  # [(P,)] each trial's score K^T r / sigma_k^2 at theta
    cov_noise: np.ndarray | None = None  # (P, P) the sandwich with each marker's own noise level (or None: cov)
    marker_sd: np.ndarray | None = None  # (K, M) each marker's noise sd in each trial (mm, weighted units)


def _prior_terms(model: Model, theta) -> tuple[np.ndarray, np.ndarray]:
    """Gradient and (Gauss-Newton) curvature of the negative log prior: ``(P,)``, and ``(P,)`` or ``(P, P)``.

    Normal priors: ``(theta - mu)^2 / (2 sd^2)``; log-normal ones: ``(log theta - log m)^2 / (2 sd^2)``
    (the MAP in log space); uniform ones: nothing. Log-normal priors that share a group
    (:class:`skelid.model.description.Prior`) are jointly normal in their logs ``u``:
    ``(u - log m)^T Sigma^-1 (u - log m) / 2`` with ``Sigma = sd^2 ((1 - rho) I + rho 1 1^T)``; the
    curvature is then the matrix ``D Sigma^-1 D``, ``D = diag(1 / theta)`` on the group's block
    (a model without groups keeps the vector of the diagonal).
    """
    g = np.zeros(model.n_params)
    h = np.zeros(model.n_params)
    for k, p in enumerate(model.parameters):
        if p.prior.kind == "normal":
            g[k] = (theta[k] - p.prior.mean) / p.prior.sd**2
            h[k] = 1.0 / p.prior.sd**2
        elif p.prior.kind == "lognormal":
            t = max(float(theta[k]), 1e-12)
            g[k] = (np.log(t) - np.log(p.prior.mean)) / (p.prior.sd**2 * t)
            h[k] = 1.0 / (p.prior.sd * t) ** 2
    groups = _prior_groups(model)
    if not groups:
        return g, h
    H = np.diag(h)
    for idx, u, inv in _group_terms(model, theta, groups):
        t = np.maximum(np.asarray(theta, float)[idx], 1e-12)
        g[idx] = (inv @ u) / t
        H[np.ix_(idx, idx)] = inv / np.outer(t, t)
    return g, H


def _prior_groups(model: Model) -> list[np.ndarray]:
    """The index sets of the parameters whose log-normal priors share a group (two or more each)."""
    by: dict = {}
    for k, p in enumerate(model.parameters):
        if p.prior.kind == "lognormal" and p.prior.group:
            by.setdefault(p.prior.group, []).append(k)
    return [np.array(v) for v in by.values() if len(v) > 1]


def _group_terms(model: Model, theta, groups):
    """Per group: its indices, the logs' departures from the medians ``u`` and ``Sigma^-1``."""
    for idx in groups:
        pr = [model.parameters[k].prior for k in idx]
        sd, rho = pr[0].sd, pr[0].correlation
        n = idx.size
        sigma = sd**2 * ((1.0 - rho) * np.eye(n) + rho * np.ones((n, n)))
        u = np.log(np.maximum(np.asarray(theta, float)[idx], 1e-12)) - np.log([q.mean for q in pr])
        yield idx, u, np.linalg.inv(sigma)


def _prior_cost(model: Model, theta) -> float:
    """The negative log prior whose gradient and curvature :func:`_prior_terms` gives (constants dropped)."""
    groups = _prior_groups(model)
    grouped = set(np.concatenate(groups).tolist()) if groups else set()
    c = 0.0
    for k, p in enumerate(model.parameters):
        if p.prior.kind == "normal":
            c += 0.5 * ((theta[k] - p.prior.mean) / p.prior.sd) ** 2
        elif p.prior.kind == "lognormal" and k not in grouped:
            c += 0.5 * ((np.log(max(float(theta[k]), 1e-12)) - np.log(p.prior.mean)) / p.prior.sd) ** 2
    for _, u, inv in _group_terms(model, theta, groups):
        c += 0.5 * float(u @ inv @ u)
    return c


def prior_matrix(prior_precision) -> np.ndarray:
    """A prior precision as a ``(P, P)`` matrix (the diagonal of a vector)."""
    h = np.asarray(prior_precision, float)
    return np.diag(h) if h.ndim == 1 else h


def prior_sd(prior_precision) -> np.ndarray:
    """Each parameter's marginal prior sd from a prior precision (vector or matrix)."""
    h = np.asarray(prior_precision, float)
    if h.ndim == 1:
        return 1.0 / np.sqrt(np.maximum(h, 1e-300))
    sd = 1.0 / np.sqrt(np.maximum(np.diag(h), 1e-300))
    coupled = np.flatnonzero(np.abs(h - np.diag(np.diag(h))).sum(axis=1) > 0)  # the groups' blocks
    if coupled.size:
        sd[coupled] = np.sqrt(np.clip(np.diag(np.linalg.inv(h[np.ix_(coupled, coupled)])), 0.0, None))
    return sd


def fit_scales_and_offsets(model: Model, ys, theta0, poses0, sigma: float | None = None,
                           n_iter: int = JOINT_ITER, weights=None) -> JointOffsets:
    """MAP of the body scales and marker offsets together under their priors, every pose profiled out.

    Model: trial ``k``, frame ``t``, marker ``m``:
    ``y_ktm = x_m(theta, q_kt) + e``, ``e ~ N(0, sigma_k^2 I)``, with ``theta`` the
    scales and offsets and the priors of :func:`skelid.io.osim.osim_parameters`
    (offsets ``N(0, 10^2)`` mm, scales log-normal). The offsets of all the
    markers of a body trade with the body's pose (and a leaf body's scale with
    its markers' offsets), so the data alone leave directions undetermined; the
    prior fixes them, and the posterior says how well each is known. Each
    iteration fits every pose for the current ``theta``
    (:func:`skelid.estimators.pose.fit_pose`), then takes the Gauss-Newton step
    of the penalised cost with the poses eliminated (Schur complement):

    .. math:: (S/\\sigma^2 + \\Lambda)\\,\\Delta = \\sum_t K_{\\perp t}^\\top r_t / \\sigma^2 - \\nabla(-\\log p),
              \\qquad S = \\sum_t K_{\\perp t}^\\top K_{\\perp t}

    (``K_perp`` from :func:`skelid.estimators.likelihood.projected_theta_jacobian`,
    each trial with its own ``sigma_k``), halved until the penalised cost falls,
    with the parameters that press against their prior's bounds held there
    (:func:`_bounded_step`). The noise of each trial is re-estimated
    at every iteration, ``sigma_k^2 = RSS_k / (n_k - Q T_k - edf n_k / n)``,
    ``edf = tr((S/sigma^2) (S/sigma^2 + Lambda)^{-1})``. The covariance is the
    Laplace approximation of the joint posterior, ``(S/sigma^2 + Lambda)^{-1}``
    at the MAP.

    Parameters
    ----------
    model : Model
        With ``scale`` and ``marker_offset`` parameters.
    ys : sequence of (F_k, M, 3) float
        Markers of each trial (mm, the model's marker order, NaN where missing).
    theta0 : (P,) float
    poses0 : sequence of (F_k, Q) float
        Starting poses.
    sigma : float, optional
        Known noise sd (mm) of every trial; estimated per trial if not given.
    weights : (M,) float, optional
        Relative weights ``1 / rho_m^2`` of the markers (per-marker noise ``sigma_k rho_m``): the
        rows of marker ``m`` are scaled by ``1 / rho_m`` and the poses are the weighted fits.

    Returns
    -------
    JointOffsets
    """
    from skelid.estimators.fit.joint import weighted_terms
    from skelid.estimators.fit.pose import workspace

    ws = workspace(model)
    lo, hi = _prior_bounds(model)
    theta = np.clip(np.asarray(theta0, float), lo, hi)
    poses = [np.asarray(q, float).copy() for q in poses0]
    ys = [np.asarray(y, float) for y in ys]
    K = len(ys)
    n_obs = np.array([np.isfinite(y).all(axis=-1).sum() * 3 for y in ys], float)
    n_pose = np.array([model.n_pose * np.isfinite(y).all(axis=-1).any(axis=-1).sum() for y in ys], float)
    sig = np.full(K, np.nan if sigma is None else float(sigma))
    floor = SIGMA_FLOOR * float(np.abs(model.nominal_geometry).max())
    dof = np.maximum(n_obs - n_pose - model.n_params, 1.0)

    def terms(th, qs, cost_only=False):  # each trial's poses at ``th``, its information, score, RSS
        one = _trial_cost if cost_only else _trial_terms
        return [one(model, th, y, q, ws, weights, JOINT_POSE_ITER) for y, q in zip(ys, qs, strict=True)]

    def complete(th, tt):  # the information and score of trials evaluated for their cost only
        return [t if t[1] is not None else _summed_terms(model.dim, t[0], *weighted_terms(model, th, t[0], y, None, ws))
                for y, t in zip(ys, tt, strict=True)]

    def penalised(th, tt, w):  # the penalised cost at noise weights ``w``
        return 0.5 * float(w @ np.array([t[3] for t in tt])) + _prior_cost(model, th)

    theta, now, dof, n_done, converged = _iterate(model, (terms, complete), penalised, theta, terms(theta, poses),
                                                  dof, None if sigma is None else sig, (n_obs, n_pose, floor), n_iter)
    # the covariance at the final theta, every pose fitted to convergence; with the noise estimated,
    # each marker's own level too (a sandwich): the fit weighs every marker alike, and where their levels
    # differ its Laplace interval is wrong (1-10 mm per marker on OpenSim-generated walks: 0.5-0.8 of
    # the actual spread)
    final = [_trial_terms(model, theta, y, t[0], ws, weights, POSE_ITER, floor if sigma is None else None)
             for y, t in zip(ys, now, strict=True)]
    rss = np.array([t[3] for t in final])
    if sigma is None:
        sig = np.sqrt(np.maximum(rss / dof, floor**2))
    _, hp = _prior_terms(model, theta)
    info = tuple(t[1] / s_k**2 for t, s_k in zip(final, sig, strict=True))
    scores = tuple(t[2] / s_k**2 for t, s_k in zip(final, sig, strict=True))
    _, cov, edf, prior_only = _posterior(model, sum(info), hp)
    cov_noise, marker_sd = None, None
    if sigma is None:
        J = sum(t[4] / s_k**4 for t, s_k in zip(final, sig, strict=True))
        cov_noise = cov @ (J + prior_matrix(hp)) @ cov
        cov_noise = 0.5 * (cov_noise + cov_noise.T)
        marker_sd = np.sqrt(np.array([t[5] for t in final]))
    return JointOffsets(theta, cov, [t[0] for t in final], sig, dof, edf, n_done, converged, prior_only, info,
                        scores, cov_noise, marker_sd)


def _iterate(model: Model, terms, penalised, theta, now, dof, sig, counts, n_iter: int):
    """The joint fit's Gauss-Newton iterations: ``(theta, terms, dof, iterations, converged)``.

    ``terms = (evaluate, complete)``: ``evaluate(theta, poses)`` gives each trial's ``(poses, S,
    K^T r, RSS)``, ``evaluate(theta, poses, cost_only=True)`` the poses and RSS only (None for the
    sums), which ``complete(theta, terms)`` fills in; ``penalised(theta, terms, w)`` the penalised
    cost at noise weights ``w``; ``sig`` the known noise sd per trial or None (estimated each
    iteration), ``counts`` ``(n_obs, n_pose, floor)``. The steps tried while backtracking are
    evaluated for their cost only (the poses and RSS; most are turned down), the one taken
    is completed.
    """
    evaluate, complete = terms
    lo, hi = _prior_bounds(model)
    sd0 = np.array([p.prior.sd for p in model.parameters])
    tiny = JOINT_STEP_SD * np.where(np.isfinite(sd0), sd0, 1.0)
    n_obs, n_pose, floor = counts
    for it in range(1, n_iter + 1):
        rss = np.array([t[3] for t in now])
        s = np.sqrt(np.maximum(rss / dof, floor**2)) if sig is None else sig
        w = 1.0 / s**2
        gp, hp = _prior_terms(model, theta)
        info = sum(wk * t[1] for wk, t in zip(w, now, strict=True))
        _, _, edf, _ = _posterior(model, info, hp)
        score = sum(wk * t[2] for wk, t in zip(w, now, strict=True)) - gp
        step = _bounded_step(info, hp, score, theta, lo, hi)
        if float(score @ step) <= JOINT_DECREMENT:  # within 0.03 sd of the optimum
            return theta, now, dof, it, True
        dof = np.maximum(n_obs - n_pose - edf * n_obs / n_obs.sum(), 1.0)
        cost = penalised(theta, now, w)
        poses = [t[0] for t in now]
        theta, now, step, new_cost = _backtrack(theta, step, lo, hi, cost,
                                                lambda th, q=poses: evaluate(th, q, cost_only=True),
                                                lambda th, tt, w=w: penalised(th, tt, w))
        now = complete(theta, now)
        if np.all(np.abs(step) <= tiny) or 0.0 <= cost - new_cost <= JOINT_TOL * max(abs(cost), 1e-300):
            return theta, now, dof, it, True
    return theta, now, dof, n_iter, False


#: data sets simulated from the joint fit's own answer (:func:`bootstrap_check`)
BOOTSTRAP_SETS = 12
#: Gauss-Newton steps of each simulated frame's pose from the fitted one (the noise moves it little)
BOOTSTRAP_POSE_ITER = 8
#: a class of parameters is widened together only where its steps spread at least this much wider
#: than the interval says (the same effect size as the misfit test's half sd, in quadrature)
BOOTSTRAP_POOLED_EFFECT = 1.1


def bootstrap_check(model: Model, jo: JointOffsets, ys, cov, sigma=None, weights=None,
                    seed: int = 0) -> tuple[np.ndarray, np.ndarray, dict, np.ndarray]:
    """The joint fit's bias and the widening its errors ask for, from data simulated from its answer.

    :data:`BOOTSTRAP_SETS` data sets: every trial's markers where the MAP ``theta`` and poses
    put them, plus independent noise with each marker's fitted level (``jo.marker_sd``; the
    known ``sigma`` where given), missing where the data are. On each, every frame's pose is
    fitted afresh (from the fitted one) and one Gauss-Newton step of ``theta`` is taken from
    the MAP with the fit's information, ``d_b = (S/sigma^2 + Lambda)^-1 g_b`` (``g_b`` the
    data's score with those poses; the prior's pull is the posterior's own). A linear fit would
    give ``E[d_b] = 0`` and ``Cov(d_b) = cov``; the poses, fitted frame by frame from noisy
    markers, are not linear in the noise, and ``mean(d_b - l_b)`` estimates the fit's bias,
    which is taken off the estimate: ``l_b`` is the step a linear fit takes on the same noise
    (the poses and Jacobians held at the fitted ones), whose expectation is exactly zero, so
    the difference keeps the nonlinear part only (a control variate). The plain ``mean(d_b)``
    carried the noise of the linear part: over ten seeds of one full-body fit a right femur's
    length factor's "bias" ranged from -0.64 to +0.41 sd, and every fit of one model and
    motion draws the same seed, so one seed's error recurred in every draw (+1.7 mm in the
    right thigh, +0.4 mm with the control variate, 24 draws). With per-marker noise of 1-10 mm
    and one noise level fitted, the correction lowered the rms error of the four leg lengths
    of OpenSim-generated gait2354 walks from 3.4-4.6 mm uncorrected to 2.8-3.8 mm (40 paired
    draws).

    Each sd is widened by the steps' variance over what a linear fit gives them (``var``: ``cov``
    less the prior's part, ``C Lambda C``), measured against the same control variate:
    ``1 + (s^2(d) - s^2(l)) / var``, where ``s^2(l)`` estimates ``var`` on the same noise, so
    the ratio carries the nonlinear part's variance without the chi-square(B-1) noise of a
    plain ``s^2(d) / var``. Over ten seeds of one gait2354 fit with per-marker noise the plain
    ratio of a parameter scattered with an sd of 0.41 (median over parameters), this one with
    0.15; a test of the plain ratio at its upper 10 % point widened 7 to 33 of 115 parameters
    by the seed alone, and the seed every fit of one model and motion shares decided which.
    Where the plain ratio pooled over the scales (or the offsets) that the data determine
    exceeds its own 10 % point and :data:`BOOTSTRAP_POOLED_EFFECT` squared (the linear part
    itself spreading wider than the interval says), all of them are widened by it. The
    correction's own noise, the variance of ``mean(d_b - l_b)``, is returned for the caller to
    add to each parameter's variance.

    Returns
    -------
    bias : (P,) float
        To subtract from ``theta``.
    widen : (P,) float
        At least 1.
    entry : dict
        The result's ``bootstrap`` entry.
    bias_var : (P,) float
        The variance of ``bias`` from the simulation.
    """
    from scipy.stats import chi2

    _, hp = _prior_terms(model, jo.theta)
    B = BOOTSTRAP_SETS
    steps, linear = _simulated_steps(model, jo, ys, hp, sigma, weights, np.random.default_rng(seed))
    # the steps' variance under a linear fit: the data's part of the interval, without the prior's
    var = np.clip(np.diag(cov) - np.einsum("ip,pq,iq->i", jo.cov, prior_matrix(hp), jo.cov), 1e-300, None)
    bias = (steps - linear).mean(axis=0)
    bias_var = (steps - linear).var(axis=0, ddof=1) / B
    ratio = steps.var(axis=0, ddof=1) / var
    # the same ratio with the linear part's sampling noise taken out: its variance's expectation is var
    excess = 1.0 + (steps.var(axis=0, ddof=1) - linear.var(axis=0, ddof=1)) / var
    widen = np.sqrt(np.maximum(excess, 1.0))
    determined = np.sqrt(np.clip(np.diag(jo.cov), 0.0, None)) <= AXES_IDENTIFIED * prior_sd(hp)
    kinds = np.array([p.kind for p in model.parameters])
    pooled = {}
    for kind in np.unique(kinds):
        g = (kinds == kind) & determined
        if g.any():
            df = (B - 1) * int(g.sum())
            pooled[str(kind)] = float(np.mean(ratio[g]))
            if pooled[str(kind)] > max(chi2.ppf(0.9, df) / df, BOOTSTRAP_POOLED_EFFECT**2):
                widen[g] = np.maximum(widen[g], np.sqrt(pooled[str(kind)]))
    z = bias / np.sqrt(var)
    k = int(np.argmax(np.abs(z))) if z.size else 0
    w = int(np.argmax(widen)) if z.size else 0
    entry = {"sets": B, "correction_sd_share": float(np.sqrt(np.max(bias_var / var))) if z.size else 0.0,
             "largest_bias_sd": float(z[k]) if z.size else 0.0,
             "largest_bias_parameter": model.parameter_names[k] if z.size else None,
             "pooled_sd_ratio": {kk: float(np.sqrt(v)) for kk, v in pooled.items()},
             "largest_widening": float(widen[w]) if z.size else 1.0,
             "largest_widening_parameter": model.parameter_names[w] if z.size else None,
             "widened_over_5_percent": [n for n, f in zip(model.parameter_names, widen, strict=True) if f > 1.05],
             "method": "data simulated from the fit with each marker's noise level; one Gauss-Newton step "
                       "from the fit on each, and the step a linear fit takes on the same noise (a control "
                       "variate): the mean of their difference is the bias taken off; the variance the steps "
                       "add to the linear fit's widens the sd"}
    return bias, widen, entry, bias_var


def _simulated_steps(model: Model, jo: JointOffsets, ys, hp, sigma, weights, rng) -> tuple[np.ndarray, np.ndarray]:
    """:func:`bootstrap_check`'s steps on each simulated data set: ``(steps, linear)``, each ``(B, P)``.

    ``steps``: one Gauss-Newton step from the MAP, every pose fitted afresh from the fitted one;
    ``linear``: the step a linear fit takes on the same noise (the poses held at the fitted ones,
    the Jacobians there), whose expectation is exactly zero. The noise is drawn data set by data
    set, trial by trial (the stream of a given seed does not depend on how the steps are
    summed), and held for all sets (``B`` times the markers), so that each trial's Jacobians at
    the fitted poses are built once.
    """
    from skelid.estimators.fit.joint import row_weights, weighted_terms
    from skelid.estimators.fit.likelihood import projected_score
    from skelid.estimators.fit.pose import workspace
    from skelid.model.kinematics import marker_positions

    ws = workspace(model)
    solve = _posterior_solver(sum(jo.info_trials), hp)[0]
    fitted = []  # each trial's fitted markers and each marker's noise sd, the same for every data set
    for k, (y, q) in enumerate(zip(ys, jo.poses, strict=True)):
        if jo.marker_sd is not None:
            sd = jo.marker_sd[k] / (1.0 if weights is None else np.sqrt(np.maximum(weights, 1e-300)))
        else:
            sd = np.full(y.shape[1], float(sigma if sigma is not None else jo.sigma[k]))
        fitted.append((marker_positions(model, jo.theta, q), sd[None, :, None]))
    noise = [[rng.normal(size=x.shape) * sd for x, sd in fitted] for _ in range(BOOTSTRAP_SETS)]
    score = np.zeros((BOOTSTRAP_SETS, model.n_params))  # the data's part: the prior's pull is the posterior's
    linear = np.zeros((BOOTSTRAP_SETS, model.n_params))
    for k, (y, q) in enumerate(zip(ys, jo.poses, strict=True)):
        x, seen = fitted[k][0], np.isfinite(y)
        sw = row_weights(weights, y)
        _, Jq, Jt = weighted_terms(model, jo.theta, q, y, sw, ws)
        for b in range(BOOTSTRAP_SETS):
            e = np.where(seen, noise[b][k], 0.0)
            _, r, Jq_b, Jt_b = _posed_terms(model, jo.theta, np.where(seen, x + e, np.nan), q, ws, weights,
                                            BOOTSTRAP_POSE_ITER)
            score[b] += projected_score(Jq_b, Jt_b, r) / jo.sigma[k] ** 2
            lin = e.reshape(e.shape[0], -1)
            linear[b] += projected_score(Jq, Jt, lin if sw is None else lin * sw) / jo.sigma[k] ** 2
    return np.array([solve(g) for g in score]), np.array([solve(g) for g in linear])


def _trial_terms(model: Model, theta, y, q, ws, weights, pose_iter, floor=None) -> tuple:
    """One trial's poses at ``theta`` and the sums the joint fit needs.

    Returns ``(poses, S, K^T r, RSS)`` with ``S = sum_t K_perp^T K_perp``; with a noise ``floor``
    (mm) also ``sum_t K_perp^T diag(s^2) K_perp`` with each marker's noise variance
    ``s_m^2`` (:func:`marker_noise_variances`, at least ``floor^2``) and those variances ``(M,)``.
    """
    return _summed_terms(model.dim, *_posed_terms(model, theta, y, q, ws, weights, pose_iter), y=y, floor=floor)


def _summed_terms(dim: int, q, r, Jq, Jt, y=None, floor=None) -> tuple:
    """:func:`_trial_terms` from the fitted poses, their residuals and both Jacobians (``dim`` rows per marker)."""
    from skelid.estimators.fit.likelihood import projected_sums

    if floor is None:
        return (q, *projected_sums(Jq, Jt, r, dim), float(np.sum(r**2)))
    var = np.maximum(marker_noise_variances(Jq, r, np.isfinite(y).all(axis=-1)), floor**2)
    S, Kr, Sw = projected_sums(Jq, Jt, r, dim, np.repeat(var, dim))
    return q, S, Kr, float(np.sum(r**2)), Sw, var


def _trial_cost(model: Model, theta, y, q, ws, weights, pose_iter) -> tuple:
    """:func:`_trial_terms` without the sums where they are not needed: ``(poses, None, None, RSS)``.

    The backtracking of the joint fit asks only whether a step lowers the cost; the Jacobians
    of ``theta`` and their projection cost more than the poses. With marker weights the weighted
    pose steps need the pose Jacobian, and everything is computed.
    """
    from skelid.estimators.fit.joint import _residuals
    from skelid.estimators.fit.pose import fit_pose

    if weights is not None:
        return _trial_terms(model, theta, y, q, ws, weights, pose_iter)
    q = fit_pose(model, theta, y, q, n_iter=pose_iter, ws=ws)[0]
    return q, None, None, float(np.sum(_residuals(model, theta, q, y, None, ws) ** 2))


def _backtrack(theta, step, lo, hi, cost, terms, penalised):
    """The joint fit's step, halved until the penalised cost falls: ``(theta, terms, step, cost)``.

    The full Gauss-Newton step overshoots where poses, offsets and scales trade (a body's few
    markers, each offset free). Where no shorter step lowers the cost at these noise levels
    either, the full one is taken and the noise levels follow it (a trial that fits exactly, a
    static one whose markers were placed on it, weighs a million times the others; at its weights
    every step away from it costs, and only the full step, with the levels re-estimated after it,
    leads on to the optimum).
    """
    full = None
    for _ in range(JOINT_HALVINGS):
        trial = np.clip(theta + step, lo, hi)
        new = terms(trial)
        new_cost = penalised(trial, new)
        full = full or (trial, new, step, new_cost)
        if new_cost <= cost + JOINT_TOL * abs(cost):
            return trial, new, step, new_cost
        step = 0.5 * step
    return full


#: frames per block of the pose projection in :func:`marker_noise_variances` (bounded memory)
LEVERAGE_BLOCK = 128


def marker_noise_variances(J_pose, r, observed) -> np.ndarray:
    """Each marker's noise variance from the residuals left after every frame's pose fit: ``(M,)``.

    With ``E_t = I - J_t (J_t^T J_t)^{-1} J_t^T`` the projection off frame ``t``'s pose and
    independent noise of variance ``s_m^2`` on the rows of marker ``m``, the residuals have
    ``E[r_ti^2] = sum_j E_t,ij^2 s_{m(j)}^2``. Summed over the frames and each marker's rows this
    is the linear system ``A s^2 = b``, ``A_mn = sum_t sum_{i in m, j in n} E_t,ij^2``,
    ``b_m = sum_t sum_{i in m} r_ti^2``, solved for ``s^2 >= 0`` (non-negative least squares).
    The pose takes more of the residual of a marker on a body with few markers; dividing each
    marker's mean square by one common share would call those markers quieter than they are.

    Parameters
    ----------
    J_pose : (T, M*D, Q) float
        Pose Jacobians (rows of missing markers zero).
    r : (T, M*D) float
        Residuals at the fitted poses (missing: 0).
    observed : (T, M) bool

    Returns
    -------
    (M,) float
        ``s_m^2``; 0 for a marker never observed.
    """
    from scipy.optimize import nnls

    T, MD, Q = J_pose.shape
    M = observed.shape[1]
    D = MD // M
    rows = np.repeat(observed, D, axis=1).astype(float)
    A = np.zeros((M, M))
    for a in range(0, T, LEVERAGE_BLOCK):
        Jb, wb = J_pose[a:a + LEVERAGE_BLOCK], rows[a:a + LEVERAGE_BLOCK]
        H = frame_gram(Jb)
        ridge = 1e-12 * np.maximum(np.einsum("tqq->t", H) / max(Q, 1), 1e-300)
        G = np.linalg.solve(H + ridge[:, None, None] * np.eye(Q), np.swapaxes(Jb, 1, 2))
        E = (wb[:, :, None] * wb[:, None, :]) * (np.eye(MD) - Jb @ G)
        A += (E**2).reshape(-1, M, D, M, D).sum(axis=(0, 2, 4))
    b = (r**2).reshape(T, M, D).sum(axis=(0, 2))
    seen = np.diag(A) > 0
    out = np.zeros(M)
    if seen.any():
        out[seen] = nnls(A[np.ix_(seen, seen)], b[seen])[0]
    return out


#: Gauss-Newton steps of the weighted pose fit that follows the plain one (:func:`_posed_terms`)
WEIGHTED_POSE_STEPS = 4


def _posed_terms(model: Model, theta, y, q, ws, weights=None, pose_iter: int = POSE_ITER):
    """Each frame's pose for ``theta``, then its residuals and Jacobians (rows weighted with ``weights``).

    The plain least-squares pose (:func:`skelid.estimators.fit.pose.fit_pose`) first; with
    ``weights``, a few Gauss-Newton steps of the weighted pose fit from there (the weights move the
    pose little: the plain pose is close).

    Returns
    -------
    q : (T, Q) float
    r : (T, M*3) float
    J_pose : (T, M*3, Q) float
    J_theta : (T, M*3, P) float
    """
    from skelid.estimators.fit.joint import row_weights, weighted_terms
    from skelid.estimators.fit.pose import fit_pose

    q = fit_pose(model, theta, y, q, n_iter=pose_iter, ws=ws)[0]
    sw = row_weights(weights, y)
    r, Jq, Jt = weighted_terms(model, theta, q, y, sw, ws)
    if sw is None:
        return q, r, Jq, Jt
    Q = Jq.shape[-1]
    for _ in range(WEIGHTED_POSE_STEPS):
        H = frame_gram(Jq)
        ridge = 1e-9 * np.maximum(np.einsum("tqq->t", H) / max(Q, 1), 1e-300)
        dq = np.linalg.solve(H + ridge[:, None, None] * np.eye(Q), np.einsum("tkq,tk->tq", Jq, r)[..., None])[..., 0]
        q = q + dq
        r, Jq, Jt = weighted_terms(model, theta, q, y, sw, ws)
    return q, r, Jq, Jt


def _bounded_step(info, prior_precision, score, theta, lo, hi) -> np.ndarray:
    """The Gauss-Newton step of the penalised cost with the parameters held at a bound they press against.

    A parameter on its bound whose step would leave the box is held there and the step of the
    others solved without it (a projected Newton step, Bertsekas' active set): clipping the full
    step instead moves the others as if the held one had moved with them, and the fit stalls
    (on subject01 four marker offsets on their 50 mm bound left the joint fit 15 sd from its
    optimum after 90 iterations).
    """
    P = theta.size
    held = np.zeros(P, bool)
    step = np.zeros(P)
    for _ in range(P + 1):
        free = ~held
        sub = np.ix_(free, free)
        pp = prior_precision[free] if np.ndim(prior_precision) == 1 else prior_precision[sub]
        solve = _posterior_solver(info[sub], pp)[0]
        step[:] = 0.0
        step[free] = solve(score[free])
        press = free & (((theta <= lo) & (step < 0)) | ((theta >= hi) & (step > 0)))
        if not press.any():
            return step
        held |= press
    return step


def _posterior(model: Model, info, prior_precision, rel_tol: float = 1e-10):
    """The Gaussian posterior of data information ``info`` and a diagonal prior precision.

    In coordinates scaled by the prior sd the prior precision is the identity, so with
    ``M = V diag(w) V^T`` the posterior covariance is ``V diag(1 / (w + 1)) V^T``, computed in that basis
    (a reconstruction of ``M`` would carry rounding of ``eps * max(w)`` into every direction: with a
    tiny noise level, more than the prior). Directions whose ``w`` is below ``rel_tol`` times the largest
    carry rounding only (exactly none in exact arithmetic) and get ``w = 0``.

    Returns
    -------
    solve : callable
        ``b (P,) -> cov @ b``.
    cov : (P, P) float
    edf : float
        ``tr(cov @ info)``, the number of parameters the data determine.
    prior_only : tuple of str
        Scale parameters with a share above 1 % in the null directions (the data leave them to the prior).
    """
    solve, cov, edf, share = _posterior_solver(info, prior_precision, rel_tol)
    names = tuple(p.name for k, p in enumerate(model.parameters) if p.kind == "scale" and share[k] > 0.01)
    return solve, cov, edf, names


def _posterior_solver(info, prior_precision, rel_tol: float = 1e-10):
    """:func:`_posterior` without the model: ``(solve, cov, edf, share of each parameter in the null directions)``.

    A prior precision given as a matrix ``Lambda`` (correlated priors) is whitened by its Cholesky factor
    ``Lambda = L L^T`` instead of the prior sd; the share of parameter ``i`` is then the part of its prior
    variance that lies in the null directions.
    """
    if np.ndim(prior_precision) == 2:
        return _posterior_solver_full(info, np.asarray(prior_precision, float), rel_tol)
    d = 1.0 / np.sqrt(np.maximum(prior_precision, 1e-300))
    w, V, null, inv = _whitened_eigen(info * np.outer(d, d), rel_tol)
    cov = (V * inv) @ V.T * np.outer(d, d)

    def solve(b):
        return d * (V @ (inv * (V.T @ (d * b))))
    return solve, 0.5 * (cov + cov.T), float(np.sum(w * inv)), (V[:, null] ** 2).sum(axis=1)


def _whitened_eigen(M, rel_tol: float):
    """The data information in prior-whitened coordinates, ``M = V diag(w) V^T``: ``(w, V, null, 1 / (w + 1))``,
    ``w`` set to 0 in the directions below ``rel_tol`` times the largest (rounding only)."""
    w, V = np.linalg.eigh(0.5 * (M + M.T))
    null = w <= rel_tol * max(w.max(initial=0.0), 1e-300)
    w = np.where(null, 0.0, w)
    return w, V, null, 1.0 / (w + 1.0)


def _posterior_solver_full(info, prior_precision, rel_tol: float = 1e-10):
    """:func:`_posterior_solver` for a prior precision matrix."""
    from scipy.linalg import solve_triangular

    P = prior_precision.shape[0]
    L = np.linalg.cholesky(0.5 * (prior_precision + prior_precision.T))
    Li = solve_triangular(L, np.eye(P), lower=True)  # whitened coordinates z = L^T theta
    w, V, null, inv = _whitened_eigen(Li @ info @ Li.T, rel_tol)
    W = Li.T @ V  # the posterior's directions in the parameters
    cov = (W * inv) @ W.T

    def solve(b):
        return W @ (inv * (W.T @ b))
    prior_var = np.einsum("ij,ij->i", W, W)  # W W^T = Lambda^-1
    share = (W[:, null] ** 2).sum(axis=1) / np.maximum(prior_var, 1e-300)
    return solve, 0.5 * (cov + cov.T), float(np.sum(w * inv)), share


def _joint_refinement(model: Model, theta, trials, sigma, seed, weights=None) -> JointOffsets:
    """:func:`fit_scales_and_offsets` on every frame of ``trials``, poses tracked at ``theta`` first."""
    from skelid.estimators.fit.pose import track_poses

    rng = np.random.default_rng(seed)
    ys = [t.positions for t in trials]
    poses = [track_poses(model, theta, y, rng)[0] for y in ys]
    return fit_scales_and_offsets(model, ys, theta, poses, sigma, weights=weights)


def _noise_interval(sigma: float, dof: float, scale_fit_sigma: dict | None) -> list:
    """95 % interval of the joint fit's noise level ``sigma`` on ``dof`` residual degrees of freedom.

    The scale fit on the same frames gives the noise level's relative uncertainty with its
    corrections (serially correlated residuals: fewer effective degrees of freedom); its interval,
    relative to its own value, is carried over. Without one, the chi-square interval
    ``sigma sqrt(dof / chi2_{0.975, 0.025}(dof))``.
    """
    from scipy.stats import chi2

    ci = (scale_fit_sigma or {}).get("ci95")
    value = (scale_fit_sigma or {}).get("value")
    if ci is not None and value and np.all(np.isfinite(ci)) and ci[0] < value < ci[1]:
        return [float(sigma * ci[0] / value), float(sigma * ci[1] / value)]
    dof = max(dof, 1.0)
    return [float(sigma * np.sqrt(dof / chi2.ppf(0.975, dof))), float(sigma * np.sqrt(dof / chi2.ppf(0.025, dof)))]


def _marker_weights(model: Model, res: dict) -> np.ndarray | None:
    """Relative weights ``1 / sigma_m^2`` (geometric mean 1) from a fit's per-marker noise, or None.

    A marker the fit gave no noise level gets the median weight.
    """
    per = ((res.get("sigma") or {}).get("per_marker")) or {}
    s = np.array([per.get(m, np.nan) for m in model.marker_names], float)
    ok = np.isfinite(s) & (s > 0)
    if not ok.any():
        return None
    s = np.where(ok, s, np.median(s[ok]))
    w = 1.0 / s**2
    return w / np.exp(np.mean(np.log(w)))


def _placed_positions(model: Model, theta) -> dict:
    """Each marker's nominal position (segment frame, mm) that puts it at ``S r + delta`` unscaled."""
    scales = body_scales(model, theta)
    delta = np.zeros((len(model.markers), 3))
    for k, p in enumerate(model.parameters):
        if p.kind == "marker_offset":
            delta[model.marker_names.index(p.target), p.axis] = theta[k]
    return {m.name: tuple(float(v) for v in np.asarray(m.position) + delta[i] / scales.get(m.segment, np.ones(3)))
            for i, m in enumerate(model.markers)}


#: warnings of the scale fit behind the joint fit's checks about terms the joint fit carries itself, and about
#: that fit's own estimate (a bound, the prior, its identification), which the joint fit does not report: it
#: marks its own parameters on a bound and names those the data leave to the prior (:func:`_joint_result`)
CARRIED_WARNINGS = ("placement-informed", "trials-disagree", "on-bound", "outside-prior", "poorly-identified")


def _without_carried_warnings(res: dict, est) -> dict:
    """``res`` without the scale fit's warnings about what the joint fit models itself.

    ``placement-informed``: a trial's scales follow the markers' nominal placement; in the joint
    fit the placement is a parameter (the offsets, with their prior), so its uncertainty is
    already in the joint interval and the scale fit's placement term is not carried over
    (:func:`check_ratios`). ``trials-disagree``: the several-trial scale fit, which holds every
    marker where the joint fit put it, finds the trials' scales apart beyond its within-trial
    intervals; those leave out the offsets' uncertainty (on one exactly modelled body with
    i.i.d. noise it rejected at 1 % in 3 fits of 12), and the joint fit's own test of the
    trials' placement (:mod:`skelid.estimators.checks.trial_placement`) takes its place. Both
    warnings say their term was added, which would be wrong. ``on-bound``, ``outside-prior`` and
    ``poorly-identified`` are about that fit's own estimate, which is not the answer: with every marker
    held where the joint fit put it, a factor the joint fit leaves to its prior (a humerus' width on a
    walk) is pinned by markers that were themselves placed, and ran to a bound on exact data.
    """
    drop = {w.message for w in getattr(est, "warnings_", ()) if w.code in CARRIED_WARNINGS}
    return dict(res, warnings=[w for w in res.get("warnings", []) if w not in drop]) if drop else res


def _placement_variance(e) -> np.ndarray:
    """Per parameter, the variance the marker estimator's placement term added (zero if none)."""
    pars = ((getattr(e, "placement_", None) or {}).get("parameters")) or {}
    return np.array([float((pars.get(n) or {}).get("sd_added") or 0.0) ** 2 for n in e.model.parameter_names])


def check_ratios(est, model: Model) -> np.ndarray:
    """Per trial and scale parameter, how much the scale fit's checks widened its sd: ``(K, P)``, at least 1.

    The ratio of the marker estimator's data sd (``cov_data_``) to its plain one
    (``cov_plain_``, ``sigma^2 S^{-1}``) for each trial's own fit: the plain interval
    widened where its checks ask for it (model misfit, serially correlated residuals,
    markers that disagree). The term for the markers' nominal placement (a static trial's
    ``placement_sd``) is left out: the joint fit has the markers' offsets as parameters, so
    it is already in the joint interval (carried again, it gave a static trial plus a walk
    4 times the sd of the scales the walk determines). One row for a fit of one recording.
    """
    rows = []
    for e in getattr(est, "trials_", [est]):
        plain = np.diag(np.asarray(e.cov_plain_, float))
        var = np.maximum(np.diag(np.asarray(e.cov_data_, float)) - _placement_variance(e), plain)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.sqrt(var / plain)
        rows.append(np.maximum(np.where(np.isfinite(r), r, 1.0)[:model.n_params], 1.0))
    return np.array(rows)


def deflated_widening(jo: JointOffsets, prior_precision, ratios) -> np.ndarray:
    """Per scale parameter ``i``, the joint sd with each trial's information deflated by its checks, over the bound.

    For parameter ``i``, trial ``k``'s information ``I_k`` in the joint fit is divided by
    ``r_ki^2`` (``ratios``, :func:`check_ratios`) and the posterior variance of ``i``
    recomputed: ``[(sum_k I_k / r_ki^2 + Lambda)^-1]_ii``. Each trial counts with the weight
    it has in the joint fit: a static trial whose scale fit holds the markers where the joint
    fit put them has a plain sd far below its share of the joint fit, and its precision no
    longer drowns the widening a walk's checks ask for (static trial plus walk with a 5-15 mm
    soft-tissue artefact on OpenSim-generated subjects: hip-knee coverage 0.50-0.67 with the
    precision-weighted ratio, 0.50-0.75 so; the artefact's size did the rest). A scalar
    per trial and parameter can only widen (the deflated information is below the full one
    in the Loewner order), and never beyond the prior. One row of ``ratios`` for every trial
    of a fit of one recording.
    """
    K, P3 = len(jo.info_trials), ratios.shape[1]
    if K == 0 or not np.any(ratios > 1.0):
        return np.ones(P3)
    r = np.broadcast_to(ratios, (K, P3)) if ratios.shape[0] != K else ratios
    bound2 = np.clip(np.diag(jo.cov), 1e-300, None)
    out = np.ones(P3)
    for i in range(P3):
        if np.all(r[:, i] <= 1.0):
            continue
        info = sum(I / r[k, i] ** 2 for k, I in enumerate(jo.info_trials))
        _, cov, _, _ = _posterior_solver(info, prior_precision)
        out[i] = max(1.0, float(np.sqrt(cov[i, i] / bound2[i])))
    return out


def _joint_result(model: Model, jo: JointOffsets, res: dict, widen, bound, sigma=None, weights=None,
                  held: dict | None = None) -> dict:
    """The result dict with every parameter, the noise and the lengths from the joint fit.

    ``res``: the result of the scale fit with every marker where the joint fit put it (its
    several-trial diagnostics are kept; its ``sd_within_trials`` and ``sd_between_trials`` are
    carried to the scale factors). ``bound``: the sd of the Laplace posterior before any widening,
    ``sqrt(diag (S / sigma^2 + Lambda)^-1)``, the Bayesian (van Trees) information bound of the
    priors and the data at the fitted noise level, given as ``crlb_sd``. ``weights``: the per-marker
    relative weights the joint fit used (``noise='per_marker'``). ``held``: the parameters the fit held on
    a bound (:func:`_on_bounds`; default: those on one at ``jo.theta``), marked ``on_bound`` and named in a warning.
    """
    from skelid.model.kinematics import joint_distances

    out = {k: v for k, v in res.items() if k not in model.parameter_names}
    sd = np.sqrt(np.clip(np.diag(jo.cov), 0.0, None))
    for k, p in enumerate(model.parameters):
        v, half = float(jo.theta[k]), 1.959964 * float(sd[k])
        # a scale factor's interval in log space, where its prior is normal: never below zero
        ci = ([v * np.exp(-half / v), v * np.exp(half / v)] if p.kind == "scale" and v > 0 else [v - half, v + half])
        ci = [max(ci[0], p.prior.lower), min(ci[1], p.prior.upper)]  # the posterior has no mass beyond the bounds
        out[p.name] = {"map": v, "mean": v, "sd": float(sd[k]), "ci95": [float(c) for c in ci],
                       "crlb_sd": float(bound[k]), "widened_by_checks": float(widen[k]),
                       "method": "scales and offsets fitted together (Laplace interval)"}
        own = res.get(p.name) or {}
        out[p.name].update({key: float(own[key]) for key in ("sd_within_trials", "sd_between_trials")
                            if own.get(key) is not None})
    _mark_bounds(out, model, jo.theta, _on_bounds(model, jo.theta) if held is None else held)
    if jo.prior_only:
        out["warnings"] = list(out.get("warnings", [])) + [
            f"the data do not determine {', '.join(jo.prior_only)}: each interval is its prior's (the body carries "
            "no marker, or its scale trades with its markers' offsets, whose places on the body are known only to "
            "their prior); a trial that moves the body's joints through a wider range narrows it"]
    if model.derived_lengths:
        L, grad = joint_distances(model, jo.theta)
        lsd = np.sqrt(np.clip(np.einsum("kp,pq,kq->k", grad, jo.cov, grad), 0.0, None))
        out["lengths"] = {name: {"value": float(v), "sd": float(e), "ci95": [float(v - 1.959964 * e),
                                                                              float(v + 1.959964 * e)]}
                          for (name, _), v, e in zip(model.derived_lengths, L, lsd, strict=True)}
    n = np.maximum(jo.dof, 1.0)
    pooled = float(np.sqrt(np.sum(n * jo.sigma**2) / n.sum()))
    out["sigma"] = {"value": float(sigma) if sigma is not None else pooled, "fixed": sigma is not None,
                    "per_trial": [float(v) for v in jo.sigma], "method": "joint fit of scales and offsets"}
    if sigma is None:
        out["sigma"]["ci95"] = _noise_interval(pooled, float(n.sum()), res.get("sigma"))
    if weights is not None:  # each marker's sd: the fitted level times its relative sd
        rel = 1.0 / np.sqrt(weights)
        out["sigma"]["per_marker"] = {m: float(pooled * v) for m, v in zip(model.marker_names, rel, strict=True)}
    out["joint_fit"] = {"iterations": jo.n_iter, "converged": jo.converged, "edf": jo.edf}
    if not jo.converged:
        out["warnings"] = list(out.get("warnings", [])) + [
            f"the joint fit of scales and marker offsets did not converge in {jo.n_iter} iterations"]
    return out


#: a parameter within this share of its prior's sd of a bound is on it
ON_BOUND_SD = 1e-6


def _on_bounds(model: Model, theta) -> dict[str, str]:
    """The parameters whose fitted value sits on their prior's bound: name -> 'lower' or 'upper'."""
    out = {}
    for p, v in zip(model.parameters, np.asarray(theta, float), strict=True):
        tol = ON_BOUND_SD * (p.prior.sd if np.isfinite(p.prior.sd) else p.prior.upper - p.prior.lower)
        if v <= p.prior.lower + tol:
            out[p.name] = "lower"
        elif v >= p.prior.upper - tol:
            out[p.name] = "upper"
    return out


def _mark_bounds(out: dict, model: Model, theta, held: dict[str, str]) -> None:
    """Each parameter held on a bound marked ``on_bound`` in the result ``out``, and one warning naming them."""
    for name, side in held.items():
        out[name]["on_bound"] = side
    if held:
        out["warnings"] = list(out.get("warnings", [])) + [_bounds_warning(model, theta, held)]


def _bounds_warning(model: Model, theta, held: dict[str, str]) -> str:
    """One line naming the parameters held on a bound and, per body, the scale factors they trade with."""
    by_name = {p.name: p for p in model.parameters}
    segment = {m.name: m.segment for m in model.markers}
    bodies = []
    for name in held:
        p = by_name[name]
        body = segment.get(p.target) if p.kind == "marker_offset" else p.target
        if body not in bodies:
            bodies.append(body)
    scales = [f"{p.name} {v:.3g}" for p, v in zip(model.parameters, theta, strict=True)
              if p.kind == "scale" and p.target in bodies]
    shown = ", ".join(f"{n} ({held[n]})" for n in list(held)[:8]) + (f" and {len(held) - 8} more" if len(held) > 8
                                                                     else "")
    return (f"the joint fit holds {shown} on their prior's bound: the data pull them farther than the model lets "
            f"them go, and the estimates of {', '.join(bodies)} beside them"
            + (f" ({', '.join(scales)})" if scales else "") + " are answers to a constrained fit, their intervals "
            "conditional on that bound; check those markers' labels and places in the static trial, or hold the "
            "body's proportions with --scale bodies")


#: family-wise level of the score test of one scale factor per body against one per axis (split over the bodies)
AXES_TEST_LEVEL = 0.01
#: a body's three factors are identified where each one's sd, artefact included, is at most this share of
#: its prior's sd (the data carry at least three quarters of the information): only then is the body
#: fitted per axis; on real walks a femur's x and z factors are not, and fitted per axis they ran to
#: the prior's bounds (0.47, 2.1) and left OpenSim's IK 60 mm off the markers
AXES_IDENTIFIED = 0.5


def one_factor_test(model: Model, per_axis: Model, jo: JointOffsets, ys, weights=None, score_cov=None) -> dict:
    """Per body, the score test of one scale factor against one per axis at the joint fit, and the axes' sd.

    For body ``b``: the model ``M_b`` with ``b``'s three factors and one factor for every other
    body; from the one-factor fit, its Gauss-Newton step ``u = A^{-1} g`` (``g`` the score with
    the poses profiled out and the priors' gradient included, ``A`` the posterior precision).
    The differences ``d = L u_b`` of ``b``'s three factors test the one-factor model,
    ``T_b = d^T Var(d)^{-1} d ~ chi^2_2``, with ``Var(u) = A^{-1} + A^{-1} C A^{-1}``: the
    posterior covariance (the prior counted as information: in the directions the data leave to
    it, the step is the prior's, and a data-only variance there, ``A^{-1} S A^{-1}``, is nearly
    zero: T of 400-2000 on exact data) plus the part ``C`` that a pose-dependent artefact adds
    to the score (:func:`skelid.estimators.checks.pose_artefact.pose_artefact`, in the per-axis
    parameters): an artefact that the residuals show is not taken for a geometry one factor
    cannot hold. ``b``'s three factors have the one factor's prior spread over them
    (:func:`_spread_prior`). The step, not the score alone: the other parameters'
    scores vanish only at the exact optimum, and a quadratic form of ``b``'s score alone
    counts whatever is left of them (on subject01 a fit 15 sd short of its optimum gave
    ``T`` of 10^5-10^6 for every body).

    Returns
    -------
    dict
        Body -> ``{"stat": T_b, "p": p-value, "step": [u_b, the one-step change of each axis],
        "sd": [sd of each axis in M_b, artefact included], "prior_sd": [...],
        "axis_identified": [sd at most AXES_IDENTIFIED of the prior's], "identified": all three}``.
    """
    from scipy.stats import chi2

    from skelid.estimators.fit.joint import row_weights, weighted_terms
    from skelid.estimators.fit.likelihood import projected_sums
    from skelid.estimators.fit.pose import workspace

    ws = workspace(per_axis)
    th = _map_theta(jo.theta, model, per_axis)
    S, g = 0.0, 0.0
    for y, q, sig in zip(ys, jo.poses, jo.sigma, strict=True):
        r, Jq, Jt = weighted_terms(per_axis, th, q, y, row_weights(weights, y), ws)
        r = np.where(np.isfinite(r), r, 0.0)
        Sk, gk = projected_sums(Jq, Jt, r, per_axis.dim)
        S = S + Sk / sig**2
        g = g + gk / sig**2
    C = np.zeros_like(S) if score_cov is None else np.asarray(score_cov, float)
    L = np.array([[1.0, -1.0, 0.0], [0.0, 1.0, -1.0]])
    out = {}
    for b in dict.fromkeys(p.target for p in per_axis.parameters if p.kind == "scale"):
        mb = _spread_prior(_mixed_scales(model, per_axis, [b]), b)
        E = _embedding(per_axis, mb)
        thb = _map_theta(jo.theta, model, mb)
        gp, hp = _prior_terms(mb, thb)
        solve, cov, _, _ = _posterior_solver(E.T @ S @ E, hp)
        u = solve(E.T @ g - gp)
        V = cov + cov @ (E.T @ C @ E) @ cov
        k = [i for i, p in enumerate(mb.parameters) if p.kind == "scale" and p.target == b]
        d = L @ u[k]
        t = float(d @ np.linalg.lstsq(L @ V[np.ix_(k, k)] @ L.T, d, rcond=1e-12)[0])
        # identified: judged under the per-axis model's own priors (the sd each axis would have fitted per axis)
        plain = _mixed_scales(model, per_axis, [b])
        _, hq = _prior_terms(plain, thb)
        cq = _posterior_solver(E.T @ S @ E, hq)[1]
        sd = np.sqrt(np.clip(np.diag(cq + cq @ (E.T @ C @ E) @ cq)[k], 0.0, None))
        prior_sd = 1.0 / np.sqrt(hq[k])
        out[b] = {"stat": t, "p": float(chi2.sf(t, 2)), "step": [float(v) for v in u[k]],
                  "sd": [float(v) for v in sd], "prior_sd": [float(v) for v in prior_sd],
                  "axis_identified": [bool(v) for v in sd <= AXES_IDENTIFIED * prior_sd],
                  "identified": bool(np.all(sd <= AXES_IDENTIFIED * prior_sd))}
    return out


def _spread_prior(model: Model, body: str) -> Model:
    """``model`` with the prior sd of ``body``'s three factors ``sqrt(3)`` times the one factor's.

    At a common value the three then have the one factor's prior gradient and curvature summed
    over them: the test's step has no part that only the two priors' difference makes (with
    three priors of the one factor's width, a body the data leave to its prior was "contradicted"
    at p = 0 on exact data).
    """
    params = tuple(replace(p, prior=replace(p.prior, sd=p.prior.sd * np.sqrt(3.0)))
                   if p.kind == "scale" and p.target == body and p.axis is not None else p
                   for p in model.parameters)
    return replace(model, parameters=params)


def _embedding(full: Model, sub: Model) -> np.ndarray:
    """``(P_full, P_sub)``: ``full``'s parameters as a linear function of ``sub``'s (a body's axes from one factor)."""
    col = {p.name: j for j, p in enumerate(sub.parameters)}
    one = {p.target: j for j, p in enumerate(sub.parameters) if p.kind == "scale" and p.axis is None}
    E = np.zeros((full.n_params, sub.n_params))
    for i, p in enumerate(full.parameters):
        if p.name in col:
            E[i, col[p.name]] = 1.0
        elif p.kind == "scale" and p.target in one:
            E[i, one[p.target]] = 1.0
    return E


def _map_theta(theta, src: Model, dst: Model) -> np.ndarray:
    """Values of ``dst``'s parameters from ``src``'s: by name, a body's axes from its one factor."""
    idx = {p.name: k for k, p in enumerate(src.parameters)}
    one = {p.target: theta[k] for k, p in enumerate(src.parameters) if p.kind == "scale" and p.axis is None}
    axis = {(p.target, p.axis): theta[k] for k, p in enumerate(src.parameters) if p.kind == "scale"
            and p.axis is not None}
    out = np.zeros(dst.n_params)
    for k, p in enumerate(dst.parameters):
        if p.name in idx:
            out[k] = theta[idx[p.name]]
        elif p.kind == "scale" and p.axis is not None:
            out[k] = one.get(p.target, 1.0)
        elif p.kind == "scale":
            out[k] = float(np.mean([v for (b, _), v in axis.items() if b == p.target] or [1.0]))
    return out


def _mixed_scales(model: Model, per_axis: Model, bodies) -> Model:
    """``model`` with the one-factor scales of ``bodies`` replaced by ``per_axis``'s three."""
    bodies = set(bodies)
    scales = []
    for p in model.parameters:
        if p.kind != "scale":
            continue
        if p.target in bodies:
            scales += [q for q in per_axis.parameters if q.kind == "scale" and q.target == p.target]
        else:
            scales.append(p)
    rest = tuple(p for p in model.parameters if p.kind != "scale")
    return Model(model.name, model.dim, model.units, model.segments, model.markers, tuple(scales) + rest,
                 model.description)


def _checks_model(model: Model, theta, original: Model) -> Model:
    """The scale fit's model for the checks of the joint fit at ``theta``: every marker where the joint fit put
    it, the scale factors of the bodies that carry one, and the bodies that only hold another's joint held at
    their fitted size (:func:`skelid.io.osim.scales_held`).

    A body that only holds another's joint is known to the data through where that body sits, often not at
    all: a fit without the scales' priors cannot have it. Left at its generic size instead, the checks
    tested a model the joint fit had not fitted: on OpenSim-generated walks of a per-axis scaled subject, a
    talus at its generic size showed as misfit at the subtalar joint, and the marker jackknife widened
    every length by up to 1.6 (its largest eigenvalue 50 against a 95 % point of 10 under white noise).
    """
    placed = _with_marker_positions(original, _placed_positions(model, theta))
    marked = {m.segment for m in placed.markers}
    scaled = Model(placed.name, placed.dim, placed.units, placed.segments, placed.markers,
                   tuple(p for p in model.parameters if p.kind == "scale"), model.description)
    return scales_held(scaled, {b: v for b, v in body_scales(model, theta).items() if b not in marked})


def _on_scales(model: Model, sub: Model, ratios) -> np.ndarray:
    """``ratios (K, P_sub)`` of ``sub``'s scale parameters spread over every scale parameter of ``model`` (its
    first ones), 1 for those ``sub`` lacks."""
    names = [p.name for p in model.parameters if p.kind == "scale"]
    out = np.ones((ratios.shape[0], len(names)))
    for j, p in enumerate(sub.parameters):
        out[:, names.index(p.name)] = ratios[:, j]
    return out


def place_markers(model: Model, theta, pose, y, frames, movable) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Marker offsets that put each marker where the static trial saw it (OpenSim's MarkerPlacer).

    With the fitted geometry and poses, a marker's offset is the mean over the
    static frames of its residual in its segment's frame,
    ``delta_m = mean_t R_t^T (y_mt - x_mt)``; its standard error is the frame
    scatter over ``sqrt(n_eff)`` with ``n_eff = n (1 - rho) / (1 + rho)`` from
    the lag-1 autocorrelation ``rho`` of the residuals (a static trial's
    residuals are strongly correlated in time).

    Parameters
    ----------
    pose : (F, Q) float
    y : (F, M, 3) float
    frames : (start, stop)
        The static trial's frames.
    movable : (M,) bool
        Markers that may move (not ``fixed`` in the model); the others get 0.

    Returns
    -------
    offsets, sd : (M, 3) float
        In the segment frame, model units.
    n_eff : (M,) float
    """
    from skelid.model.kinematics import forward_kinematics

    sl = slice(*frames)
    kin = forward_kinematics(model, theta, pose[sl])
    R = kin.R_world_seg[:, model.marker_segment]  # (T, M, 3, 3)
    r = np.einsum("tmji,tmj->tmi", R, y[sl] - kin.markers)  # residual in the segment frame
    ok = np.isfinite(r).all(axis=-1)
    n = ok.sum(axis=0).astype(float)
    r0 = np.where(ok[..., None], r, 0.0)
    mean = r0.sum(axis=0) / np.maximum(n, 1)[:, None]
    dev = np.where(ok[..., None], r - mean, 0.0)
    var = (dev**2).sum(axis=0) / np.maximum(n - 1, 1)[:, None]
    num = (dev[1:] * dev[:-1]).sum(axis=(0, 2))
    den = (dev**2).sum(axis=(0, 2))
    rho = np.clip(np.where(den > 0, num / np.maximum(den, 1e-300), 0.0), 0.0, 0.99)
    n_eff = np.maximum(n * (1 - rho) / (1 + rho), 1.0)
    sd = np.sqrt(var / n_eff[:, None])
    movable = np.asarray(movable, bool) & (n > 0)
    return np.where(movable[:, None], mean, 0.0), np.where(movable[:, None], sd, 0.0), n_eff


def scaling_table(fit: ScalingFit) -> dict:
    """Scale factors and marker offsets with their intervals (the sidecar JSON's content)."""
    res = fit.result
    scales: dict = {}
    offsets: dict = {}
    for p in fit.model.parameters:
        e = res[p.name]
        entry = {"value": float(e["map"]), "sd": float(e.get("sd", np.nan)),
                 "ci95": [float(v) for v in e.get("ci95", (np.nan, np.nan))]}
        entry.update({k: float(e[k]) for k in ("crlb_sd", "sd_within_trials", "sd_between_trials")
                      if e.get(k) is not None})
        if p.kind == "scale":
            key = "xyz" if p.axis is None else "xyz"[p.axis]
            scales.setdefault(p.target, {})[key] = entry
        elif p.kind == "marker_offset":
            offsets.setdefault(p.target, {})["xyz"[p.axis]] = entry
    locs = marker_locations(fit.model, fit.info, fit.theta, mean_places(fit))
    return {
        "source_model": fit.source,
        "marker_set": fit.marker_set,
        "data": fit.data.source,
        "units": {"scale": "1", "marker_offset": "mm", "marker_location": "m"},
        "scales": scales,
        "marker_offsets_mm": offsets,
        "marker_locations_m": {n: [float(v) for v in x] for n, x in locs.items()},
        "body_scale_factors": {b: [float(v) for v in s] for b, s in body_scales(fit.model, fit.theta).items()},
        "sigma_mm": res.get("sigma"),
        "lengths_mm": res.get("lengths"),
        "fixed_markers": sorted(set(fit.info.fixed_markers) & set(fit.model.marker_names)),
        "trial_names": [Path(str(t.source)).name if t.source else f"trial {k + 1}"
                        for k, t in enumerate(fit.trials)],
        "trials": trials_table(fit),
        "model_sensitivity": res.get("model_sensitivity"),
        "settings": _settings_json(fit.estimator),
        "frames_used": res.get("frames_used"),
        "first_trial": res.get("first_trial"),
        "seconds": round(fit.seconds, 3),
        "markers_left_out": list(fit.dropped_markers),
        "warnings": list(fit.warnings),
    }


def _scale_key(p) -> tuple[str, str]:
    """``(body, axis)`` of a scale parameter as the scaling table names them."""
    return p.target, "xyz" if p.axis is None else "xyz"[p.axis]


def trials_table(fit: ScalingFit) -> dict | None:
    """Several trials: each trial's own scale factors, the between-trial sd and the consistency test.

    From the several-trial fit's diagnostics (:meth:`~skelid.estimators.multitrial.MultiTrialEstimator.result`);
    None for a fit of one trial (or of trials joined into one recording).

    Returns
    -------
    dict
        ``n_trials``; ``per_trial``: ``[{trial, frames, frames_used, sigma_mm, scales: {body: {axis:
        {value, sd, sd_with_between_trial, ci95}}}}]``; ``between_trial_sd``: ``{body: {axis: tau}}``;
        ``heterogeneity``: Cochran's ``q``, ``i2``, ``dof`` by body and axis; ``consistency``:
        ``{statistic, dof, p_value, tested, verdict}`` (``p_value`` None, "not tested", below one degree
        of freedom); ``between_trial``: how the spread entered the intervals.
    """
    res = fit.result
    rows = res.get("trials")
    if not isinstance(rows, list) or not rows:
        return None
    scales = [p for p in fit.model.parameters if p.kind == "scale"]
    per = []
    for r in rows:
        own: dict = {}
        for p in scales:
            e = (r.get("parameters") or {}).get(p.name)
            if e is not None:
                b, ax = _scale_key(p)
                own.setdefault(b, {})[ax] = {"value": e["mean"], "sd": e["sd"],
                                             "sd_with_between_trial": e["sd_with_between_trial"],
                                             "ci95": list(e["interval"])}
        per.append({"trial": r.get("trial"), "frames": r.get("frames"), "frames_used": r.get("frames_used"),
                    "sigma_mm": r.get("sigma"), "scales": own})
    het = res.get("heterogeneity") or {}
    between: dict = {}
    spread: dict = {}
    for p in scales:
        if p.name in het:
            b, ax = _scale_key(p)
            between.setdefault(b, {})[ax] = het[p.name]["tau"]
            spread.setdefault(b, {})[ax] = {k: het[p.name][k] for k in ("q", "i2", "dof") if k in het[p.name]}
    cons = dict(res.get("consistency") or {})
    if cons:
        if cons.get("p_value") is None:
            cons["verdict"] = "not tested (fewer than one degree of freedom)"
        else:
            # the trials' scales with every marker held where the joint fit put it: their within-trial
            # intervals leave out the offsets' uncertainty, so this is a diagnostic, not the interval's term
            cons["verdict"] = ("the trials' scales agree" if cons["p_value"] >= 0.01 else
                               "the trials' scales differ beyond their within-trial intervals (markers held "
                               "where the joint fit put them)")
    placement = res.get("trial_placement")
    if placement:
        placement = dict(placement, verdict=(
            "the trials see the markers at different places on the body; the spread is in the intervals"
            if placement.get("present") else "one marker placement fits every trial"))
    return {"n_trials": len(rows), "per_trial": per, "between_trial_sd": between, "heterogeneity": spread,
            "consistency": cons, "between_trial": res.get("between_trial"), "placement": placement}


def _settings_json(est) -> dict:
    """The scale fit's estimator and its declared settings, as JSON values (empty without a fit)."""
    from skelid.estimators.base import get_settings, setting_json

    if est is None:
        return {}
    return {"method": est.name, **{k: setting_json(v) for k, v in get_settings(est).items()
                                   if k not in ("theta0", "pose0", "rng")}}


def write_outputs(fit: ScalingFit, out_dir, name: str = "scaled", table: dict | None = None) -> dict[str, Path]:
    """Write ``<name>.osim``, ``<name>_scale_set.xml``, ``<name>_scaling.json``, ``<name>_report.md`` and
    ``<name>_geometry.json`` (the fitted model and its covariance, for :mod:`skelid.angles`).

    ``table``: the fit's :func:`scaling_table` with what was added to it (ScaleTool's factors); default the
    fit's own."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"osim": out_dir / f"{name}.osim", "scale_set": out_dir / f"{name}_scale_set.xml",
             "json": out_dir / f"{name}_scaling.json", "report": out_dir / f"{name}_report.md"}
    write_scaled_osim(fit.source, paths["osim"], fit.model, fit.info, fit.theta, fit.marker_set,
                      moved=mean_places(fit))
    write_scale_set(paths["scale_set"], fit.model, fit.theta)
    table = scaling_table(fit) if table is None else table
    paths["json"].write_text(json.dumps(_finite_or_none(table), indent=1, allow_nan=False) + "\n")
    paths["report"].write_text(report_markdown(fit, table, {k: v.name for k, v in paths.items()}))
    from skelid.angles import fitted_geometry, write_geometry  # what 'skelid ik' needs from the fit

    paths["geometry"] = write_geometry(fitted_geometry(fit), out_dir, name)
    return paths


def report_markdown(fit: ScalingFit, table: dict | None = None, files: dict | None = None) -> str:
    """A short human-readable report of a scaling fit (Markdown).

    The trials and frames used, each body's scale factor with its 95 %
    interval, the fitted distances between joint centres, the placed marker
    offsets, the markers left out, the warnings, and how to check the scaled
    model in OpenSim.
    """
    table = scaling_table(fit) if table is None else table
    lines = _head_markdown(fit, table) + _trials_markdown(table.get("trials"))
    for section in (_scales_markdown, _lengths_markdown, _offsets_markdown, _slide_markdown, _sensitivity_markdown,
                    _tail_markdown):
        lines += section(fit, table, files)
    return "\n".join(lines)


def _head_markdown(fit: ScalingFit, table: dict) -> list[str]:
    """The title, the model and data, the frames used and the noise of each trial, the noise level."""
    res = fit.result
    lines = [f"# Scaling of {Path(fit.source).name}", "",
             f"Model: `{fit.source}`" + (f" with the markers of `{fit.marker_set}`" if fit.marker_set else ""),
             f"Data: {fit.data.source}", ""]
    frames = fit.data.meta.get("trial_frames_used", [])
    sig = (res.get("sigma") or {}).get("per_trial") if isinstance(res.get("sigma"), dict) else None
    if frames:
        first = res.get("first_trial") or {}
        lines += ["| trial | taken as | frames used | marker noise sd (mm) |", "|---|---|---|---|"]
        for k, (src, n) in enumerate(zip(fit.data.source.split(" + "), frames, strict=False)):
            s = f"{sig[k]:.1f}" if sig and k < len(sig) and sig[k] is not None else "-"
            role = "static" if k == 0 and first.get("static") else "movement"
            if k == 0 and first.get("marker_motion_mm") is not None:  # why: how far its markers move
                role += f" (markers move {first['marker_motion_mm']:.3g} mm)"
            lines.append(f"| {Path(src).name} | {role} | {n} | {s} |")
        lines.append("")
    noise = table.get("sigma_mm") or {}
    if isinstance(noise, dict) and noise.get("value") is not None:
        ci = noise.get("ci95")
        lines += [f"Marker noise sd: {noise['value']:.3g} mm" + (f" [{ci[0]:.3g}, {ci[1]:.3g}]" if ci else
                                                                 " (given, not estimated)"), ""]
    return lines


def _scales_markdown(fit: ScalingFit, table: dict, files) -> list[str]:
    if not table["scales"]:
        return []
    peer = table.get("scaletool")
    beside = {(r["body"], r["axis"]): r for r in (peer or {}).get("compared", [])}
    lines = ["## Body scale factors", ""]
    if peer:
        lines += [f"OpenSim's ScaleTool on `{Path(peer['setup']).name}` (static trial "
                  f"`{Path(peer['static_trial']).name}`): {peer['inside']} of its {peer['n_compared']} factors "
                  "inside skelid's 95 % interval.", ""]
    lines += ["| body | axis | scale | 95 % interval |" + (" ScaleTool |" if peer else ""),
              "|---|---|---|---|" + ("---|" if peer else "")]
    for body, axes in table["scales"].items():
        for ax, e in axes.items():
            lo, hi = e["ci95"]
            r = beside.get((body, ax))
            st = "" if not peer else (" - |" if r is None else
                                      f" {r['scaletool']:.4f}{'' if r['inside'] else ' (outside)'} |")
            lines.append(f"| {body} | {ax} | {e['value']:.4f} | [{lo:.4f}, {hi:.4f}] |{st}")
    return lines + [""]


def _lengths_markdown(fit: ScalingFit, table: dict, files) -> list[str]:
    lengths = fit.result.get("lengths") or {}
    if not lengths:
        return []
    lines = ["## Distances between joint centres (mm)", "", "| between | value | 95 % interval |", "|---|---|---|"]
    for n, e in lengths.items():
        lo, hi = e.get("ci95", (np.nan, np.nan))
        lines.append(f"| {n} | {e['value']:.1f} | [{lo:.1f}, {hi:.1f}] |")
    return lines + [""]


def _offsets_markdown(fit: ScalingFit, table: dict, files) -> list[str]:
    if not table["marker_offsets_mm"]:
        return []
    lines = ["## Marker offsets (mm, in the body frame)", "", "| marker | x | y | z | largest sd |",
             "|---|---|---|---|---|"]
    for m, e in table["marker_offsets_mm"].items():
        v = [e[a]["value"] if a in e else 0.0 for a in "xyz"]
        sd = max(e[a]["sd"] for a in e)
        lines.append(f"| {m} | {v[0]:.1f} | {v[1]:.1f} | {v[2]:.1f} | {sd:.1f} |")
    return lines + [""]


def _slide_markdown(fit: ScalingFit, table: dict, files) -> list[str]:
    """Each body's soft-tissue slide, where it was estimated with the geometry (largest first)."""
    by_body = (fit.result.get("artefact") or {}).get("by_body")
    if not by_body:
        return []
    lines = ["## Soft-tissue slide of each body's markers", "",
             "| body | shared slope sd (mm per radian) | rms over the trials' poses (mm) |", "|---|---|---|"]
    for b, e in sorted(by_body.items(), key=lambda kv: -kv[1]["rms"]):
        lines.append(f"| {b} | {e['slope_sd_shared']:.1f} | {e['rms']:.1f} |")
    return lines + [""]


def _sensitivity_markdown(fit: ScalingFit, table: dict, files) -> list[str]:
    sens = table.get("model_sensitivity")
    if not (sens and sens["spread"]):
        return []
    avg = sens.get("average") or {}
    q = avg.get("quantities") or {}
    lines = ["## Scale factors and lengths under alternative models", "",
             "A scale factor is relative to its own model's generic geometry; a length (joint centre to joint "
             "centre, mm) is the same quantity under every model.", ""]
    if avg:
        lines += [f"The models' average weighs each model by stacking over {avg['blocks']} blocks of "
                  f"{avg['unit']} (" + ", ".join(f"{m} {w:.2f}" for m, w in avg["weights"].items())
                  + "): the share of the data each predicts best; its interval is the weighted mixture of "
                  "the models' own, so it holds the choice of model where the data cannot settle it.", ""]
    lines += ["| quantity | average [95 % interval] | " + " | ".join(sens["models"]) + " | spread |",
              "|---|---|" + "---|" * (len(sens["models"]) + 1)]
    for n, e in sens["spread"].items():
        cells = [f"{e['values'][m]:.4f}" if m in e["values"] else "-" for m in sens["models"]]
        a = q.get(n)
        mean = f"{a['value']:.4f} [{a['interval'][0]:.4f}, {a['interval'][1]:.4f}]" if a else "-"
        lines.append(f"| {n} | {mean} | " + " | ".join(cells) + f" | {e['spread']:.4f} |")
    return lines + [""]


def _tail_markdown(fit: ScalingFit, table: dict, files) -> list[str]:
    """The markers left out, the warnings, the files written."""
    lines = []
    if table["markers_left_out"]:
        lines += ["Markers of the model left out (not in every trial): " + ", ".join(table["markers_left_out"]), ""]
    if table["warnings"]:
        lines += ["## Warnings", ""] + [f"- {w}" for w in table["warnings"]] + [""]
    if files:
        lines += ["## Files", "", f"- `{files['osim']}`: the scaled model (load it in OpenSim and run "
                  "inverse kinematics with it);", f"- `{files['scale_set']}`: the scale factors as an OpenSim "
                  "ScaleSet;", f"- `{files['json']}`: every factor and offset with its sd and 95 % interval.", ""]
    return lines


def _trials_markdown(trials: dict | None) -> list[str]:
    """The report's section on several trials: each trial's scale factors, the spread, the consistency test."""
    if not trials:
        return []
    per = trials["per_trial"]
    names = [Path(str(r["trial"])).name for r in per]
    lines = ["## Each trial's own scale factors", "",
             "Each trial fitted alone (sd with the between-trial spread); the joint estimate below combines them.",
             "", "| body | axis | " + " | ".join(names) + " | between-trial sd |",
             "|---|---|" + "---|" * (len(names) + 1)]
    for body, axes in trials["between_trial_sd"].items():
        for ax, tau in axes.items():
            cells = []
            for r in per:
                e = r["scales"].get(body, {}).get(ax)
                cells.append("-" if e is None else f"{e['value']:.4f} ± {e['sd_with_between_trial']:.4f}")
            lines.append(f"| {body} | {ax} | " + " | ".join(cells) + f" | {tau:.4f} |")
    c = trials.get("consistency") or {}
    if c:
        if c.get("p_value") is None:
            lines += ["", "Consistency of the trials with the joint estimate: not tested (fewer than one degree "
                      "of freedom)."]
        else:
            lines += ["", f"Consistency of the trials with the joint estimate: chi-square {c['statistic']:.1f} on "
                      f"{c['dof']} degrees of freedom, p = {c['p_value']:.2g} ({c['verdict']})."]
    pl = trials.get("placement") or {}
    if pl:
        lines += ["", f"Marker placement from trial to trial (joint fit): about {pl['sd_between_trials']:.2g} mm per "
                  f"offset coordinate, p = {pl['p_value']:.2g} ({pl['verdict']})."]
    return lines + [""]


def _finite_or_none(obj):
    """``obj`` with every non-finite float replaced by None (JSON has no NaN)."""
    if isinstance(obj, dict):
        return {k: _finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite_or_none(v) for v in obj]
    if isinstance(obj, float | np.floating):
        return float(obj) if np.isfinite(obj) else None
    return obj


def opensim_ik(osim_path, trc_path, out_dir, markers=None) -> dict:
    """Run OpenSim's InverseKinematicsTool; marker RMSE (mm) over the frames and markers it used.

    Parameters
    ----------
    markers : iterable of str, optional
        Markers to track (weight 1 each); default: every model marker in the file.

    Returns
    -------
    dict
        ``rmse_mm`` (root mean square over frames of the per-frame marker RMS
        error OpenSim reports), ``max_mm``, ``frames``, ``seconds``.
    """
    import opensim as osim

    osim.Logger.removeFileSink()  # OpenSim would write opensim.log beside every model it loads

    from skelid.io import read_markers

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    data = read_markers(trc_path)
    model = osim.Model(str(osim_path))
    model.initSystem()
    names = [model.getMarkerSet().get(i).getName() for i in range(model.getMarkerSet().getSize())]
    use = [n for n in names if n in data.names and (markers is None or n in set(markers))]
    tool = osim.InverseKinematicsTool()
    tool.setModel(model)
    tool.setMarkerDataFileName(str(trc_path))
    tasks = tool.getIKTaskSet()
    for n in use:
        t = osim.IKMarkerTask()
        t.setName(n)
        t.setApply(True)
        t.setWeight(1.0)
        tasks.cloneAndAppend(t)
    tvec = np.asarray(osim.TimeSeriesTableVec3(str(trc_path)).getIndependentColumn())
    tool.setStartTime(float(tvec[0]))
    tool.setEndTime(float(tvec[-1]))
    tool.setResultsDir(str(out_dir))
    tool.set_report_errors(True)
    tool.setOutputMotionFileName(str(out_dir / "ik.mot"))
    t0 = time.perf_counter()
    tool.run()
    seconds = time.perf_counter() - t0
    err = osim.TimeSeriesTable(str(out_dir / "_ik_marker_errors.sto"))
    rms = np.asarray(err.getDependentColumn("marker_error_RMS").to_numpy())
    mx = np.asarray(err.getDependentColumn("marker_error_max").to_numpy())
    return {"rmse_mm": float(np.sqrt(np.mean(rms**2)) * 1000.0), "max_mm": float(mx.max() * 1000.0),
            "frames": int(rms.size), "markers": len(use), "seconds": round(seconds, 3)}
