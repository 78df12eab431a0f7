"""Result folders written before ``schema_version`` 1, read as a typed :class:`~skelid.result.FitRun`.

Until version 1, ``result.json`` held one dict per method in which parameter
estimates (``{"map", "mean", "sd", "ci95"}``) sat beside reserved keys
(``sigma``, ``lengths``, ``identifiability``, ``warnings``, ...), and
``arrays.npz`` named a method's arrays ``METHOD.KEY``. :func:`run_from_legacy`
turns such a dict into the typed result (for a program holding one in
memory); :func:`summary_dict` is its inverse. Result *folders* of that layout
are not read: :func:`skelid.io.results.read_run` refuses them in one line
naming the version (a damaged one cannot be told from an old one reliably,
so the fix is to fit again).

Plain-text warnings name their parameters in the text; a warning that
contains ``parameter NAME`` (as a whole token) is attached to ``NAME``. A
parameter whose method gave no status has ``extra["status_given"] = False``.

Examples
--------
>>> doc = {"units": "mm", "frames_total": 100, "methods": {"marker": {
...     "L": {"map": 250.0, "mean": 250.0, "sd": 2.0, "ci95": [246.1, 253.9]},
...     "sigma": {"value": 2.0, "ci95": [1.9, 2.1], "fixed": False},
...     "warnings": ["parameter L is poorly identified for this motion"]}}}
>>> run = run_from_legacy(doc)
>>> r = run.results["marker"]
>>> r.parameters["L"].interval, r.noise.sigma, r.warnings[0].parameters
((246.1, 253.9), 2.0, ('L',))
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import replace

import numpy as np

from skelid.errors import SkelidError
from skelid.result import FitResult, FitRun, FrameCounts, NoiseEstimate, ParameterEstimate, Warning

_STATUS = {"identified": "identified", "well identified": "identified", "ok": "identified",
           "poor": "poor", "poorly identified": "poor", "unidentified": "unidentified",
           "not identified": "unidentified", "prior": "prior", "placement": "placement"}
#: keys of a method's dict that are not parameters
_RESERVED = ("sigma", "lengths", "identifiability", "counting", "joint_range_deg", "warnings", "frames_used",
             "frames_dropped", "seconds")
_CODES = (
    (re.compile(r"not converg|before converging|failed to converge", re.I), "not-converged"),
    (re.compile(r"poorly identified", re.I), "poorly-identified"),
    (re.compile(r"soft-tissue", re.I), "soft-tissue-artefact"),
    (re.compile(r"bound of (its|their) prior", re.I), "on-bound"),
    (re.compile(r"skipped|dropped", re.I), "frames-skipped"),
    (re.compile(r"left out", re.I), "outliers"),
    (re.compile(r"missing in", re.I), "marker-gaps"),
    (re.compile(r"sampler", re.I), "sampler"),
)


def _float(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def _pair(v) -> tuple[float, float]:
    return (_float(v[0]), _float(v[1])) if isinstance(v, list | tuple) and len(v) == 2 else (math.nan, math.nan)


def _mentions(text: str, name: str) -> bool:
    return re.search(rf"(?<![\w.]){re.escape(name)}(?![\w])", text) is not None


def legacy_warning(text, names=()) -> Warning:
    """A plain-text warning as a :class:`Warning`: a code guessed from its words, the parameters it names."""
    if isinstance(text, Mapping):
        return Warning(str(text.get("code", "note")), str(text.get("message", "")),
                       tuple(text.get("parameters") or ()))
    text = str(text)
    code = next((c for rx, c in _CODES if rx.search(text)), "note")
    params = tuple(n for n in names if "parameter" in text.lower() and _mentions(text, n))
    return Warning(code, text, params)


def _own_arrays(method: str, arrays: Mapping) -> dict:
    """The arrays named ``METHOD.KEY``, keyed by ``KEY``."""
    pre = f"{method}."
    return {k[len(pre):]: np.asarray(v) for k, v in arrays.items() if k.startswith(pre)}


def _statuses(m: Mapping) -> dict:
    """Parameter name -> typed status from the method's ``identifiability`` rows (an unknown word is poor)."""
    return {str(r.get("parameter")): _STATUS.get(str(r.get("status", "")).lower(), "poor")
            for r in m.get("identifiability") or [] if isinstance(r, Mapping)}


def _is_estimate(key, value) -> bool:
    """Whether one entry of a method's dict is a parameter estimate (not a reserved key)."""
    return key not in _RESERVED and isinstance(value, Mapping) and "map" in value and "ci95" in value


def _crlb_of(v: Mapping, i: int, crlb) -> float | None:
    """A parameter's Cramér-Rao sd: its own ``crlb_sd``, else entry ``i`` of the method's ``crlb_sd`` array."""
    c = v.get("crlb_sd")
    if c is None and crlb is not None and i < len(crlb):
        c = float(crlb[i])
    return None if c is None else _float(c)


def _parameters(m: Mapping, units: str, kinds: Mapping, status: Mapping, crlb) -> dict:
    """The method's parameter estimates, in the order of its dict.

    An axis direction is in degrees, a scale factor a ratio (unit ``1``), every other parameter in ``units``;
    a parameter held on its prior's bound (``on_bound``: ``lower`` or ``upper``) is ``on-bound``, with
    ``extra["bound"]`` naming which; one
    without an identifiability row is ``identified`` with ``extra["status_given"] = False``.
    """
    entries = [(k, v) for k, v in m.items() if _is_estimate(k, v)]
    params = {}
    for i, (name, v) in enumerate(entries):
        held = v.get("on_bound")
        given = name in status or held is not None
        params[name] = ParameterEstimate(
            name, {"axis_direction": "deg", "scale": "1"}.get(kinds.get(name), units), _float(v["map"]),
            _float(v.get("mean", v["map"])), _float(v.get("sd")), _pair(v["ci95"]),
            _crlb_of(v, i, crlb), "on-bound" if held else status.get(name, "identified"),
            {"bound": held} if held else {} if given else {"status_given": False})
    return params


def _derived(m: Mapping, units: str) -> dict:
    """The derived lengths (``lengths``: name -> ``{"value", "sd", "ci95"}``) as estimates."""
    return {k: ParameterEstimate(k, units, _float(v.get("value")), _float(v.get("value")), _float(v.get("sd")),
                                 _pair(v.get("ci95")), None, "identified", {"status_given": False})
            for k, v in (m.get("lengths") or {}).items() if isinstance(v, Mapping)}


def _noise(m: Mapping) -> NoiseEstimate | None:
    """The marker noise (``sigma``: ``{"value", "ci95", "fixed", ...}``), or None without a value."""
    sig = m.get("sigma")
    if not (isinstance(sig, Mapping) and "value" in sig):
        return None
    ci = sig.get("ci95")
    return NoiseEstimate(_float(sig["value"]), _pair(ci) if ci else None, bool(sig.get("fixed")),
                         extra={k: v for k, v in sig.items() if k not in ("value", "ci95", "fixed")})


def _frames(m: Mapping, frames_total) -> FrameCounts | None:
    """Frames of the run and those the method used (all of them where it does not say)."""
    if frames_total is None:
        return None
    used = m.get("frames_used", frames_total)
    return FrameCounts(int(frames_total), int(used if isinstance(used, int | float) else frames_total))


def _typed_array_names(own: dict) -> dict:
    """The method's arrays with the posterior's also under the names a typed result uses."""
    own = dict(own)
    if "posterior.points" in own:
        own["samples"] = own["posterior.points"]
        if "posterior.weights" in own:
            own["weights"] = own["posterior.weights"]
    if "posterior.cov" in own:
        own["cov"] = own["posterior.cov"]
    return own


def _result(method: str, m: Mapping, units: str, frames_total, arrays: Mapping, kinds: Mapping) -> FitResult:
    """One method's dict of the old layout (and its ``METHOD.KEY`` arrays) as a :class:`FitResult`."""
    own = _own_arrays(method, arrays)
    params = _parameters(m, units, kinds, _statuses(m), own.get("crlb_sd"))
    derived = _derived(m, units)
    noise = _noise(m)
    frames = _frames(m, frames_total)
    diagnostics = {k: m[k] for k in ("identifiability", "counting", "joint_range_deg") if m.get(k) is not None}
    provenance = {"seconds": m["seconds"]} if "seconds" in m else {}
    return FitResult(method, params, derived, noise, frames, diagnostics,
                     tuple(legacy_warning(w, list(params)) for w in m.get("warnings") or ()),
                     provenance=provenance, arrays=_typed_array_names(own))


def run_from_legacy(doc: Mapping, arrays: Mapping | None = None) -> FitRun:
    """A ``result.json`` dict without ``schema_version`` (and its arrays) as a :class:`FitRun`.

    Raises
    ------
    SkelidError
        ``doc`` has no ``methods`` table.
    """
    arrays = dict(arrays or {})
    if not isinstance(doc.get("methods"), Mapping):
        raise SkelidError("this is not a skelid fit result (no 'methods' table)",
                          "give a folder written by 'skelid fit --out DIR'")
    units = str(doc.get("units") or arrays.get("units", ""))
    kinds = {k: v.get("kind") for k, v in (doc.get("model_parameters") or {}).items() if isinstance(v, Mapping)}
    results = {k: _result(k, m, units, doc.get("frames_total"), arrays, kinds) for k, m in doc["methods"].items()}
    names = [n for r in results.values() for n in r.parameters]
    context = {k: v for k, v in doc.items() if k not in ("methods", "warnings")}
    prov = {k: context.pop(k) for k in ("command", "cwd", "created", "versions") if k in context}
    if prov:
        context["provenance"] = prov
    return FitRun(results, context, tuple(legacy_warning(w, names) for w in doc.get("warnings") or ()),
                  {k: v for k, v in arrays.items() if "." not in k})


def run_from_scaling(fit_, table: dict, command=None) -> FitRun:
    """The run ``skelid fit MODEL.osim`` writes as ``result.json``: the scale and offset estimates
    (converted from the scaling fit's flat dict), the scaling table in the context."""
    from skelid.provenance import model_parameters, provenance

    doc = {"units": fit_.model.units, "frames_total": int(fit_.data.positions.shape[0]),
           "methods": {"marker": fit_.result}, "model_parameters": model_parameters(fit_.model)}
    run = run_from_legacy(doc, scaling_arrays(fit_))
    # several trials: each trial's estimate, the between-trial spread and the consistency test, typed as the
    # several-trial fit of a .toml model keeps them
    diag = {k: fit_.result[k] for k in ("trials", "consistency", "heterogeneity", "between_trial")
            if fit_.result.get(k) is not None}
    if diag:
        r = run.results["marker"]
        run = replace(run, results={**run.results, "marker": r.replace(diagnostics={**r.diagnostics, **diag})})
    context = {"model": fit_.model.name, "data": str(fit_.data.source), "units": fit_.model.units,
               "frames_total": int(fit_.data.positions.shape[0]), "scaling": table,
               "model_parameters": doc["model_parameters"], "model_description": fit_.model.to_dict(),
               "provenance": provenance(command)}
    return FitRun(run.results, context, tuple(fit_.warnings), run.arrays)


#: posterior draws of the geometry an OpenSim fit's ``arrays.npz`` keeps (from its Laplace posterior)
SCALING_DRAWS = 400


def scaling_arrays(fit_, n_draws: int = SCALING_DRAWS, seed: int = 0) -> dict:
    """What an OpenSim fit's ``arrays.npz`` holds: every trial's markers, poses and residuals, and draws.

    Shared: ``markers`` (frames of every trial one after another, the model's markers, model
    units), ``marker_names``, ``rate`` (the first trial's), ``trial`` (each frame's trial, from
    0). The method's (``marker``): ``pose`` (the joint fit's poses), ``residuals`` (each marker's
    distance from the fitted model, NaN where missing), ``posterior.cov`` and ``n_draws`` equal-
    weight draws ``posterior.points`` of the parameters from the joint fit's posterior (its
    Laplace approximation with the checks' widening and the artefact's term). Empty without a
    joint fit (``joint=False`` or no marker offsets).
    """
    from skelid.model.kinematics import marker_positions

    jo = getattr(fit_, "joint", None)
    trials = getattr(fit_, "trials", ())
    if jo is None or not trials or len(trials) != len(jo.poses):
        return {}
    y = np.concatenate([np.asarray(t.positions, float) for t in trials])
    q = np.concatenate([np.asarray(p, float) for p in jo.poses])
    x = marker_positions(fit_.model, fit_.theta, q)
    res = np.linalg.norm(y - x, axis=-1)
    w, V = np.linalg.eigh(0.5 * (jo.cov + jo.cov.T))
    z = np.random.default_rng(seed).standard_normal((n_draws, w.size))
    draws = np.asarray(fit_.theta, float) + (z * np.sqrt(np.clip(w, 0.0, None))) @ V.T
    return {"markers": y, "marker_names": np.array(fit_.model.marker_names), "rate": np.float64(trials[0].rate),
            "trial": np.repeat(np.arange(len(trials)), [len(t.positions) for t in trials]),
            "marker.pose": q, "marker.residuals": res, "marker.posterior.cov": np.asarray(jo.cov, float),
            "marker.posterior.points": draws, "marker.posterior.weights": np.full(n_draws, 1.0 / n_draws)}


def summary_dict(r: FitResult) -> dict:
    """A :class:`FitResult` as one method's flat dict of the layout before schema version 1.

    ``frames_used``, ``frames_dropped``, ``frames_skipped``; one entry per parameter
    (``map``, ``mean``, ``sd``, ``ci95``, ``crlb_sd`` and the estimator's extras);
    ``sigma``; ``lengths``; every diagnostic under its own key; ``warnings`` (messages).
    In this flat shape a parameter named like a reserved key shadows it, which is why
    result files hold the typed form (:func:`skelid.io.results.write_run`); the OpenSim
    scaling table is still built from this shape.
    """
    out: dict = {}
    if r.frames is not None:
        out.update(frames_used=r.frames.used, frames_dropped=r.frames.dropped, frames_skipped=dict(r.frames.skipped))
    out.update({k: v for k, v in r.diagnostics.items() if k != "identifiability"})
    for k, p in r.parameters.items():
        entry = {"map": p.map, "mean": p.mean, "sd": p.sd, "ci95": list(p.interval)}
        if p.crlb_sd is not None:
            entry["crlb_sd"] = p.crlb_sd
        out[k] = {**entry, **p.extra}
    if r.noise is not None:
        out["sigma"] = _noise_dict(r.noise)
    if r.derived:
        out["lengths"] = {k: {"value": p.mean, "sd": p.sd, "ci95": list(p.interval)} for k, p in r.derived.items()}
    if "identifiability" in r.diagnostics:
        out["identifiability"] = r.diagnostics["identifiability"]
    out["warnings"] = [w.message for w in r.warnings]
    return out


def _noise_dict(n: NoiseEstimate) -> dict:
    sig = {"value": n.sigma, "fixed": n.fixed}
    if n.interval is not None:  # a noise level given, not estimated, has none
        sig["ci95"] = list(n.interval)
    sig.update(n.extra)
    if n.per_marker:
        sig["per_marker"] = dict(n.per_marker)
    return sig
