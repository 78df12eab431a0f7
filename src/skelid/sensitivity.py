"""Several trials and model alternatives: what ``skelid fit MODEL a.trc b.trc ...`` runs.

* Several files: one geometry for all of them
  (:class:`~skelid.estimators.multitrial.MultiTrialEstimator`), each trial's own
  estimate beside the joint one, their chi-square consistency, the between-trial
  variance in the interval.
* Model alternatives (``--alternative OTHER.toml``: another joint type, another
  marker subset, another nominal geometry): the same data are fitted under each,
  and the spread of every quantity the models share is reported beside the
  interval. The spread is the range of the estimates over the models (the main
  one included); it measures how much the answer depends on modelling choices
  the data cannot settle, which no interval from one model contains.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from skelid.data import MarkerData
from skelid.errors import DataError
from skelid.io.results import write_run
from skelid.model.description import Model
from skelid.result import FitResult, FitRun


def trials_text(result: FitResult) -> str:
    """Each trial's own estimate and the consistency test, as text (empty for a one-trial result).

    Parameters
    ----------
    result : FitResult
        A several-trial result: ``diagnostics`` holds ``trials``, ``consistency`` and
        ``heterogeneity`` (:meth:`~skelid.estimators.multitrial.MultiTrialEstimator.result`).
    """
    d = result.diagnostics
    rows, cons = d.get("trials"), d.get("consistency")
    if not rows or not cons:
        return ""
    names = list(result.parameters)
    label = [str(r.get("data") or r.get("trial", "")) for r in rows]
    width = max(len(x) for x in [*label, "between-trial sd"]) + 2
    head = f"{'trial':<{width}}" + "".join(f"{n:>24}" for n in names)
    lines = ["", "each trial's own estimate (sd with the between-trial spread):", head, "-" * len(head)]
    for lab, r in zip(label, rows, strict=True):
        cells = "".join(f"{r['parameters'][n]['mean']:>14.5g} ± {r['parameters'][n]['sd_with_between_trial']:<7.3g}"
                        for n in names)
        lines.append(f"{lab:<{width}}" + cells)
    het = d.get("heterogeneity") or {}
    if het:
        lines.append(f"{'between-trial sd':<{width}}" + "".join(
            f"{het[n]['tau']:>24.3g}" for n in names if n in het))
    trend = d.get("motion_trend") or {}
    if trend:
        lines.append(f"{'per degree of its joint':<{width}}" + "".join(_trend_cell(trend.get(n)) for n in names))
        lines.append("(each trial's estimate against the range through which it moves the parameter's joint: "
                     "slope and p value of the random-effects meta-regression)")
    if cons.get("p_value") is None:
        lines.append("consistency of the trials with the joint estimate: not tested (fewer than one degree of "
                     "freedom)")
        return "\n".join(lines)
    verdict = "the trials agree" if cons["p_value"] >= 0.01 else "the trials disagree beyond their own intervals"
    lines.append(f"consistency of the trials with the joint estimate: chi-square {cons['statistic']:.1f} on "
                 f"{cons['dof']} degrees of freedom, p = {cons['p_value']:.2g} ({verdict})")
    return "\n".join(lines)


def _trend_cell(r) -> str:
    """One parameter's trend with its joint's range, for :func:`trials_text`."""
    if not r:
        return f"{'-':>24}"
    return f"{r['slope']:+.3g} (p {r['p_value']:.2g})".rjust(24)


def fit_trials(model: Model, datas: Sequence[MarkerData], **settings):
    """One fitted estimator for ``datas``: the single-trial one for one file, else the multi-trial one."""
    from skelid.estimators.marker import MarkerEstimator
    from skelid.estimators.multitrial import MultiTrialEstimator

    if len(datas) == 1:
        return MarkerEstimator(model, **settings).fit(datas[0])
    return MultiTrialEstimator(model, **settings).fit(datas)


def quantities(model: Model, est) -> dict[str, dict[str, float]]:
    """Parameters and derived lengths of a fitted estimator: ``{name: {"value", "sd"}}``."""
    sd = est.posterior_.sd
    out = {n: {"value": float(est.theta_[k]), "sd": float(sd[k])} for k, n in enumerate(model.parameter_names)}
    for n, v in (getattr(est, "lengths_", None) or {}).items():
        out.setdefault(n, {"value": float(v["value"]), "sd": float(v["sd"])})
    return out


def model_spread(estimates: Mapping[str, Mapping[str, Mapping[str, float]]]) -> dict:
    """Spread of each quantity over model alternatives.

    Parameters
    ----------
    estimates : {model name: {quantity: {"value", "sd"}}}
        The first model is the main one.

    Returns
    -------
    dict : ``{quantity: {"values": {model: value}, "spread": max - min, "sd_over_models": sd,
    "largest_sd": the widest of the models' own sds}}`` for every quantity that at
    least two models share.
    """
    names: dict[str, dict[str, float]] = {}
    sds: dict[str, list[float]] = {}
    for mname, q in estimates.items():
        for n, v in q.items():
            names.setdefault(n, {})[mname] = v["value"]
            sds.setdefault(n, []).append(v["sd"])
    out = {}
    for n, vals in names.items():
        if len(vals) < 2:
            continue
        x = np.array(list(vals.values()))
        out[n] = {"values": dict(vals), "spread": float(x.max() - x.min()),
                  "sd_over_models": float(x.std(ddof=1)), "largest_sd": float(max(sds[n]))}
    return out


#: a held-out unit of the stacking weights: this long a stretch of a trial's frames (residuals of
#: neighbouring frames are correlated; a second of movement is roughly one independent piece of it)
BLOCK_SECONDS = 1.0
#: below this many blocks the weights rest on too few independent stretches of data to split models: said so
FEW_BLOCKS = 5


def frame_log_density(residuals, sigma, dim: int, n_pose: int) -> np.ndarray:
    """Each frame's log density under a fitted model: ``(T,)``, NaN where no marker is seen.

    The Gaussian density of the frame's residual distances ``residuals (T, M)`` (NaN: missing) at
    the noise levels ``sigma`` (a scalar or one per marker) in ``dim`` coordinates, less the
    ``n_pose`` pose coordinates fitted to the frame: the in-sample optimism of the log density
    (Akaike's correction), so that a model with more joint freedom does not win by fitting each
    frame's noise.
    """
    r = np.asarray(residuals, dtype=float)
    sig = np.broadcast_to(np.asarray(sigma, dtype=float), r.shape[1:])
    seen = np.isfinite(r)
    term = -0.5 * dim * np.log(2 * np.pi * sig**2) - 0.5 * (np.where(seen, r, 0.0) / sig) ** 2
    return np.where(seen.any(axis=1), np.where(seen, term, 0.0).sum(axis=1) - n_pose, np.nan)


def block_log_density(frames, rates, n_params) -> np.ndarray:
    """Each model's log predictive density of each block of frames: the units that stacking weighs.

    A block is :data:`BLOCK_SECONDS` of one trial's frames that every model fitted; it also pays
    its share of each model's geometry parameters (the optimism of the geometry's fit).

    Parameters
    ----------
    frames : [K][n_trials] of (T_t,) float
        :func:`frame_log_density` of each trial under each model (NaN: a frame the model did not
        fit).
    rates : (n_trials,) float
        Each trial's frame rate (Hz) in those arrays; not finite: blocks of 100 frames.
    n_params : (K,) int
        Each model's number of geometry parameters.

    Returns
    -------
    (n_blocks, K) float

    Raises
    ------
    DataError
        No frame is fitted by every model, or the models were fitted to different frames of a trial.
    """
    out = []
    for t, rate in enumerate(rates):
        each = [np.asarray(f[t], dtype=float) for f in frames]
        if len({a.shape for a in each}) > 1:
            raise DataError(f"the model alternatives were fitted to different frames of trial {t + 1} "
                            f"({', '.join(str(a.size) for a in each)}), so their fits cannot be weighed",
                            "fit every alternative the same way (the same marker placement: --markers)")
        lp = np.stack(each, axis=1)  # (T, K)
        used = np.isfinite(lp).all(axis=1)
        size = max(1, int(round(float(rate) * BLOCK_SECONDS))) if np.isfinite(rate) and rate > 0 else 100
        block = np.arange(lp.shape[0]) // size
        out.extend(lp[used & (block == b)].sum(axis=0) for b in np.unique(block[used]))
    if not out:
        raise DataError("the model alternatives share no fitted frame, so their fits cannot be weighed",
                        "fit trials whose frames every model can follow")
    lp = np.array(out)
    return lp - np.asarray(n_params, dtype=float) / lp.shape[0]


def estimator_frames(model: Model, est) -> list[np.ndarray]:
    """:func:`frame_log_density` of every trial of a fitted marker estimator (each trial's own fit
    for a several-trial one), at its noise level (each marker's own with ``noise='per_marker'``)."""
    out = []
    for e in list(getattr(est, "trials_", None) or [est]):
        ms = getattr(e, "marker_sigma_", None)
        sig = np.full(np.shape(e.residuals_)[1], float(e.sigma_))
        if ms is not None:
            sig = np.where(np.isfinite(ms) & (np.asarray(ms) > 0), ms, sig)
        lp = frame_log_density(e.residuals_, sig, model.dim, model.n_pose)
        out.append(np.where(np.asarray(e.frames_used_, bool), lp, np.nan))
    return out


def model_average(models: Sequence[Model], ests: Sequence, datas: Sequence[MarkerData],
                  estimates: Mapping[str, Mapping[str, Mapping[str, float]]]) -> dict:
    """The models' average: stacking weights over blocks of frames and each quantity's mixture.

    Parameters
    ----------
    models, ests, datas
        The models, their fitted estimators (:func:`fit_trials`) and the trials they were fitted to.
    estimates : {model name: {quantity: {"value", "sd"}}}
        :func:`quantities` of each fit.

    Returns
    -------
    dict : ``{"method": "stacking", "unit": ..., "blocks": n, "weights": {model: w},
    "quantities": {quantity: {"value", "sd", "interval", "models"}}}``: every quantity of the
    first (main) model, averaged over the models that have it (their weights renormalised).
    """
    lp = block_log_density([estimator_frames(m, e) for m, e in zip(models, ests, strict=True)],
                           [d.rate for d in datas], [m.n_params for m in models])
    return average_of(lp, estimates)


def average_of(log_density, estimates: Mapping[str, Mapping[str, Mapping[str, float]]],
               log: Sequence[str] = ()) -> dict:
    """:func:`model_average` from the blocks' log densities ``(n_blocks, K)`` of the models of
    ``estimates`` (in its order); the quantities in ``log`` are mixed in log space (ratios)."""
    from skelid.estimators.uncertainty.stacking import mixture_summary, stacking_weights

    lp = np.asarray(log_density, dtype=float)
    w = dict(zip(list(estimates), map(float, stacking_weights(lp)), strict=True))
    first = next(iter(estimates))
    out = {}
    for q in estimates[first]:
        have = [n for n in estimates if q in estimates[n] and w[n] > 0]
        if not have:  # only models the data give no weight have it
            continue
        mu = np.array([estimates[n][q]["value"] for n in have])
        sd = np.array([estimates[n][q]["sd"] for n in have])
        if q in log:  # a ratio: its interval is log-normal, the sd of its log by the delta method
            mu, sd = np.log(np.where(mu > 0, mu, np.nan)), sd / mu
        if not (np.isfinite(mu).all() and np.isfinite(sd).all()):
            continue
        out[q] = {**mixture_summary(mu, sd, [w[n] for n in have], log=q in log), "models": have}
    return {"method": "stacking", "unit": f"{BLOCK_SECONDS:g} s of a trial's frames", "blocks": int(lp.shape[0]),
            "weights": w, "quantities": out}


def average_text(result: FitResult) -> str:
    """The models' average of ``skelid fit --alternative`` as text (empty without alternatives)."""
    avg = (result.diagnostics.get("model_sensitivity") or {}).get("average")
    if not avg or not avg.get("quantities"):
        return ""
    weights = ", ".join(f"{k} {v:.2f}" for k, v in avg["weights"].items())
    est = result.diagnostics["model_sensitivity"]["estimates"]
    models = list(avg["weights"])
    width = max(len(q) for q in [*avg["quantities"], "quantity"]) + 2
    head = (f"{'quantity':<{width}}{'average':>12}  {'95 % interval':<24}{'sd':>10}"
            + "".join(f"{m[:14]:>16}" for m in models))
    few = (f"; only {avg['blocks']} of them, too few to tell how the data divide between the models, so the "
           "weights go to the model that fits them best" if avg["blocks"] < FEW_BLOCKS else "")
    lines = ["", f"the models' average (stacking weights over {avg['blocks']} blocks of "
             f"{avg['unit']}{few}: {weights}):", head, "-" * len(head)]
    for q, r in avg["quantities"].items():
        lo, hi = r["interval"]
        each = "".join(f"{est[m][q]['value']:>16.5g}" if q in est.get(m, {}) else f"{'-':>16}" for m in models)
        lines.append(f"{q:<{width}}{r['value']:>12.5g}  {f'[{lo:.5g}, {hi:.5g}]':<24}{r['sd']:>10.3g}" + each)
    return "\n".join(lines)


def sensitivity(models: Sequence[Model], datas: Sequence[MarkerData], **settings) -> dict:
    """Fit every model alternative to the same data and report the spread (see :func:`model_spread`).

    Raises
    ------
    DataError
        Two alternatives have the same name (their results could not be told apart).
    """
    seen = [m.name for m in models]
    if len(set(seen)) != len(seen):
        raise DataError(f"model alternatives need distinct names, got {', '.join(seen)}",
                        "give each model file its own [model] name")
    return _sensitivity_record(models, [fit_trials(m, datas, **settings) for m in models], datas)


def _sensitivity_record(models: Sequence[Model], ests: Sequence, datas: Sequence[MarkerData]) -> dict:
    """The ``model_sensitivity`` record of fitted estimators: each model's quantities, their spread and average."""
    fits = {m.name: quantities(m, e) for m, e in zip(models, ests, strict=True)}
    return {"models": list(fits), "estimates": fits, "spread": model_spread(fits),
            "average": model_average(models, ests, datas, fits)}


def run_fit_trials(model_path, data_paths, method_names=(), sigma: float | None = None, seed: int = 0,
                   out_dir=None, command=None, cutoff: float | None = None,
                   artefact_rms: float | None = None, noise: str = "pooled", alternatives=(),
                   overwrite: bool = False, placement_sd: float | None = None) -> FitRun:
    """``skelid fit`` with several trials, per-marker noise or model alternatives (marker method only).

    Returns
    -------
    FitRun
        The ``marker`` result (with several trials, each trial's estimate and the
        consistency test under ``diagnostics``; with alternatives,
        ``diagnostics["model_sensitivity"]``: :func:`sensitivity` without the main fit
        repeated), written to ``out_dir`` through :func:`skelid.io.results.write_run`.
    """
    from skelid import workflows
    from skelid.checks import check_distinct_files
    from skelid.errors import SkelidError
    from skelid.io import read_markers
    from skelid.io.atomic import atomic_dir, check_output_dir
    from skelid.simulate import BUILTIN_MODELS, resolve_model

    names = list(method_names) or ["marker"]
    if names != ["marker"]:
        raise SkelidError(f"several trials, --noise and --alternative work with the marker method only, "
                          f"not {', '.join(names)}", "use --method marker or fit one file")
    if out_dir is not None:
        check_output_dir(out_dir, overwrite=overwrite)

    def load_model(path):
        if str(path).lower().replace("_", "-") not in BUILTIN_MODELS:
            workflows.check_input_file(path, "model file")
        return resolve_model(path)

    model = load_model(model_path)
    others = [load_model(p) for p in alternatives]
    check_alternatives(model, others)
    for p in data_paths:
        workflows.check_input_file(p, "data file")
    check_distinct_files(data_paths)
    # bad settings fail before any reading
    workflows.make_estimator("marker", model, sigma, cutoff=cutoff, artefact_rms=artefact_rms,
                             placement_sd=placement_sd)
    settings = {"sigma": sigma, "rng": np.random.default_rng(seed), "noise": noise,
                "artefact_rms": artefact_rms or None, "placement_sd": placement_sd}
    if cutoff is not None:
        settings["cutoff"] = cutoff or None
    with workflows.collect_warnings() as read_warnings:
        datas = [read_markers(p) for p in data_paths]
        for d in datas:
            workflows.check_units(model, d)
    with workflows.collect_warnings():
        est = fit_trials(model, datas, **settings)
    result = trials_result(model, est, data_paths, sum(d.n_frames for d in datas))
    if others:
        with workflows.collect_warnings():
            ests = [est]
            for m in others:
                # the same random stream as the main fit, so that the spread holds no Monte-Carlo noise
                ests.append(fit_trials(m, datas, **{**settings, "rng": np.random.default_rng(seed)}))
        sens = _sensitivity_record([model, *others], ests, datas)
        result = result.replace(diagnostics={**result.diagnostics, "model_sensitivity": sens})
    data = str(data_paths[0]) if len(datas) == 1 else [str(p) for p in data_paths]
    arrays = workflows.run_arrays(model, datas[0]) if len(datas) == 1 else {}
    run = FitRun({"marker": result},
                 workflows.run_context(model, data, sum(d.n_frames for d in datas), command),
                 workflows.unique_warnings([*read_warnings, *result.warnings]), arrays)
    if out_dir is not None:
        with atomic_dir(out_dir, protect=[model_path, *data_paths, *alternatives], overwrite=overwrite) as tmp:
            write_run(tmp, run)
    return run


def check_alternatives(model: Model, others) -> None:
    """Alternatives of one body: distinct names and the main model's markers (one line otherwise).

    Models fitted to different markers see different data: their estimates and fits cannot be
    set side by side as views of one recording.
    """
    seen = {model.name}
    for m in others:
        if m.name in seen:
            raise DataError(f"model alternatives need distinct names; {m.name!r} is used twice",
                            "give each model file its own [model] name")
        seen.add(m.name)
        missing = [n for n in model.marker_names if n not in m.marker_names]
        extra = [n for n in m.marker_names if n not in model.marker_names]
        if missing or extra:
            what = "; ".join(x for x in (f"lacks {', '.join(missing)}" if missing else "",
                                         f"adds {', '.join(extra)}" if extra else "") if x)
            raise DataError(f"alternative model {m.name!r} uses other markers than {model.name!r} ({what}), so the "
                            "two would be fitted to different data", "give every alternative model the main "
                            "model's markers (the same names; their positions on the segments may differ)")


def trials_result(model: Model, est, data_paths, frames_total: int) -> FitResult:
    """The typed result of :func:`fit_trials`, each trial's row naming its file.

    A multi-trial estimator that still returns the flat dict of the layout before
    result schema version 1 is converted (:func:`skelid.io.legacy.run_from_legacy`),
    its trials, consistency test and heterogeneity kept under ``diagnostics``.
    """
    from skelid import workflows

    res = est.result()
    if not isinstance(res, FitResult):
        from skelid.io.legacy import run_from_legacy

        doc = {"units": model.units, "frames_total": int(frames_total), "methods": {"marker": res}}
        conv = run_from_legacy(doc).results["marker"]
        diag = {k: res[k] for k in ("trials", "consistency", "heterogeneity") if k in res}
        res = conv.replace(diagnostics={**conv.diagnostics, **diag})
    else:
        res = workflows.method_result(model, est)
    # one method key per run: the several-trial fit is the marker method given several files
    res = res.replace(method="marker")
    trials = res.diagnostics.get("trials")
    if isinstance(trials, list) and len(trials) == len(data_paths) > 1:
        rows = [{**row, "data": str(p)} for row, p in zip(trials, data_paths, strict=True)]
        res = res.replace(diagnostics={**res.diagnostics, "trials": rows})
    return res.replace(arrays={**workflows.posterior_arrays(est), **res.arrays})
