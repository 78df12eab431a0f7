"""Scale an OpenSim model to a subject: fit body scales and marker offsets, write them back.

The geometry of an imported OpenSim model (see :mod:`skelid.io.osim`) is
``g(theta) = g_base + theta @ A.T`` with one ``scale`` factor ``s_b`` per body
(or ``s_b = (s_x, s_y, s_z)``) multiplying the body's joint frames, markers
and the coupled translations of the joints it is the parent of, and a
``marker_offset`` ``delta_m`` added to each free marker:

.. math:: r_m = S_{b(m)}\\, r_m^0 + \\delta_m, \\qquad
          \\log s_b \\sim N(0, 0.15^2), \\quad \\delta_m \\sim N(0, (10\\,\\mathrm{mm})^2 I).

The scale factors come from skelid's ``marker`` method (poses and geometry by
joint least squares, intervals from the Laplace approximation) with the
markers at their nominal places; with several trials, from its multi-trial
form (each trial fitted alone, then all at once with one geometry, the
between-trial spread added to the interval; see
:mod:`skelid.estimators.multitrial`). The offsets are then placed as OpenSim's
MarkerPlacer places them: each free marker moves to where the first (static)
trial saw it in the fitted poses, with a standard error from the frame
scatter (:func:`place_markers`). They are not fitted jointly with the scales:
the joint fit has no prior penalty, and offsets of every marker of a body
trade with the body's pose, so the data alone cannot identify them.
Several trials of one subject are read as one recording (:func:`join_trials`: the union of their
markers, a gap of missing frames between trials) and fitted as separate
trials with one geometry.

:func:`write_outputs` writes the scaled ``.osim`` (every other element of the
source kept), an OpenSim ScaleSet, and ``scaling.json`` with each factor and
marker offset and its 95 % interval. :func:`opensim_ik` runs OpenSim's own
InverseKinematicsTool on a model and a trial and returns its marker RMSE.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from skelid.data import MarkerData, unit_scale
from skelid.errors import DataError
from skelid.io.osim import (
    OsimInfo,
    body_scales,
    keep_markers,
    marker_locations,
    osim_parameters,
    read_osim,
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


STATIC_FRAMES = 30


def fit_osim(osim_path, trials, marker_set=None, scale: str = "bodies", markers: str = "offsets",
             method: str = "marker", seed: int = 0, sigma: float | None = None,
             static_frames: int | None = STATIC_FRAMES, joined: bool = False) -> ScalingFit:
    """Fit body scales and marker offsets of an OpenSim model to marker trials.

    Parameters
    ----------
    osim_path : path
    trials : sequence of MarkerData
        A static trial and movement trials of one subject (joined by :func:`join_trials`).
    marker_set : path, optional
        A MarkerSet file for models without markers.
    scale : {'bodies', 'axes', 'none'}
        See :func:`skelid.io.osim.osim_parameters`.
    markers : {'offsets', 'none'}
        Place the free markers on the first trial after the scale fit (see :func:`place_markers`).
    static_frames : int or None
        The first trial, when it has more frames, contributes this many evenly
        spaced ones (a static trial repeats one pose: more frames add time, not
        information, since its residuals are serially correlated). None: all.
    joined : bool
        Fit the trials as one recording with gaps (one marker fit) instead of
        the multi-trial fit (each trial alone, then together).

    Returns
    -------
    ScalingFit
    """
    from skelid.io.results import summary_dict
    from skelid.workflows import make_estimator

    trials = list(trials)
    if static_frames is not None and trials and trials[0].positions.shape[0] > static_frames:
        t = trials[0]
        idx = np.unique(np.linspace(0, t.positions.shape[0] - 1, static_frames).round().astype(int))
        trials[0] = MarkerData(t.positions[idx], t.names, t.rate, t.units, t.source, t.meta)
    data = join_trials(trials)
    full, info = read_osim(osim_path, marker_set)
    multi = len(trials) > 1 and method == "marker" and not joined
    # the multi-trial fit needs every marker in every trial; a joined recording, in any
    spans = data.meta["trial_frames"] if multi else [(0, data.positions.shape[0])]
    present = [n for n in full.marker_names if n in data.names
               and all(np.isfinite(data.positions[a:b, data.names.index(n)]).all(axis=-1).any() for a, b in spans)]
    if not present:
        raise DataError(f"none of the {len(full.markers)} markers of {osim_path} is in the data "
                        f"(model: {', '.join(full.marker_names[:4])} ...; data: {', '.join(data.names[:4])} ...)",
                        "rename the markers in the model's MarkerSet or in the data so that they match")
    base, info = read_osim(osim_path, marker_set)
    base = keep_markers(base, present)
    model = osim_parameters(base, info, scale, "none", present)
    dropped = tuple(n for n in full.marker_names if n not in present)
    sub = MarkerData(data.positions[:, [data.names.index(n) for n in model.marker_names]],
                     model.marker_names, data.rate, data.units, data.source, data.meta)
    t0 = time.perf_counter()
    if model.n_params and multi:
        from skelid.estimators.multitrial import MultiTrialEstimator

        parts = [MarkerData(sub.positions[a:b], sub.names, sub.rate, sub.units, t.source)
                 for (a, b), t in zip(data.meta["trial_frames"], trials, strict=True)]
        est = MultiTrialEstimator(model, sigma=sigma, rng=np.random.default_rng(seed)).fit(parts)
        res, theta = summary_dict(est.result()), np.asarray(est.theta_, float)
        edges = np.cumsum([0] + [len(p.positions) for p in parts])
        pose = np.full((sub.positions.shape[0], model.n_pose), np.nan)
        for (a, b), e0, e1 in zip(data.meta["trial_frames"], edges[:-1], edges[1:], strict=True):
            pose[a:b] = est.pose_[e0:e1]
    elif model.n_params:
        est = make_estimator(method, model, sigma, rng=np.random.default_rng(seed))
        est.fit(sub)
        res, theta, pose = summary_dict(est.result()), np.asarray(est.theta_, float), est.pose_
    else:  # nothing to scale: poses of the nominal model only
        from skelid.estimators.pose import track_poses

        est, res, theta = None, {"warnings": []}, np.zeros(0)
        static = slice(*data.meta["trial_frames"][0])
        pose = np.zeros((sub.positions.shape[0], model.n_pose))
        pose[static] = track_poses(model, theta, sub.positions[static], np.random.default_rng(seed))[0]
    if markers == "offsets":
        static = data.meta["trial_frames"][0]
        offsets, sd, n_eff = place_markers(model, theta, pose, sub.positions, static,
                                           [m.name not in info.fixed_markers for m in model.markers])
        model = osim_parameters(base, info, scale, "offsets", present)
        theta = np.concatenate([theta, np.zeros(model.n_params - theta.size)])
        for k, p in enumerate(model.parameters):
            if p.kind == "marker_offset":
                i = model.marker_names.index(p.target)
                theta[k] = offsets[i, p.axis]
                half = 1.959964 * sd[i, p.axis]
                res[p.name] = {"map": float(offsets[i, p.axis]), "mean": float(offsets[i, p.axis]),
                               "sd": float(sd[i, p.axis]), "ci95": [float(offsets[i, p.axis] - half),
                                                                   float(offsets[i, p.axis] + half)],
                               "n_eff": float(n_eff[i]), "method": "placed on the static trial"}
    seconds = time.perf_counter() - t0
    warns = list(res.get("warnings", []))
    if dropped:
        warns.append(f"{len(dropped)} model markers are not in the data"
                     + (" (of every trial)" if multi else "") + f" and were left out: {', '.join(dropped)}")
    return ScalingFit(model, info, str(osim_path), None if marker_set is None else str(marker_set),
                      sub, est, res, seconds, dropped, warns, theta)


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
        if p.kind == "scale":
            key = "xyz" if p.axis is None else "xyz"[p.axis]
            scales.setdefault(p.target, {})[key] = entry
        elif p.kind == "marker_offset":
            offsets.setdefault(p.target, {})["xyz"[p.axis]] = entry
    locs = marker_locations(fit.model, fit.info, fit.theta)
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
        "frames_used": res.get("frames_used"),
        "seconds": round(fit.seconds, 3),
        "markers_left_out": list(fit.dropped_markers),
        "warnings": list(fit.warnings),
    }


def write_outputs(fit: ScalingFit, out_dir, name: str = "scaled") -> dict[str, Path]:
    """Write ``<name>.osim``, ``<name>_scale_set.xml`` and ``<name>_scaling.json`` into ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"osim": out_dir / f"{name}.osim", "scale_set": out_dir / f"{name}_scale_set.xml",
             "json": out_dir / f"{name}_scaling.json"}
    write_scaled_osim(fit.source, paths["osim"], fit.model, fit.info, fit.theta, fit.marker_set)
    write_scale_set(paths["scale_set"], fit.model, fit.theta)
    paths["json"].write_text(json.dumps(_finite_or_none(scaling_table(fit)), indent=1, allow_nan=False) + "\n")
    return paths


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
