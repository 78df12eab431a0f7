"""A fit's results as pandas, xarray and ArviZ objects.

Three views of one result, for users who work in those libraries:

* :func:`to_dataframe` -- one row per parameter, derived length and noise
  level of every method: estimate (posterior mean), MAP, sd, 95 % interval,
  Cramér-Rao bound, status.
* :func:`to_xarray` -- the per-frame arrays of one method with named dims:
  ``markers (frame, marker, axis)`` as measured, ``pose (frame, coordinate)``,
  ``residuals (frame, marker)``, with ``time = frame / rate``.
* :func:`to_inference_data` -- an :class:`arviz.InferenceData` whose
  ``posterior`` holds draws of every parameter and derived length, and whose
  ``observed_data`` holds the markers. Draws come from the sampler's weighted
  samples where the method has them (resampled to equal weights,
  systematically), otherwise from the Gaussian posterior
  ``theta ~ N(mean, Sigma)`` (``Sigma``: the method's covariance, or
  ``diag(sd^2)`` when only the sds are known). A derived length
  ``l_k = |o_k(theta)|`` is computed from each draw through the model's
  geometry, so its draws keep their correlation with the parameters; without
  the model it is drawn from ``N(mean_k, sd_k^2)``.

pandas, xarray and arviz are optional (``pip install 'skelid[data]'``) and are
imported only when a function that needs them is called.

A result is a fitted run (``FitRun``: one ``FitResult`` per method), one
``FitResult``, a result folder written by ``skelid fit --out``, or the
``result.json`` dict with its arrays.

Examples
--------
>>> import numpy as np
>>> result = {"units": "mm", "methods": {"marker": {
...     "L": {"map": 250.0, "mean": 250.0, "sd": 2.0, "ci95": [246.1, 253.9], "crlb_sd": 1.9}}}}
>>> df = to_dataframe(result)
>>> df[["method", "name", "estimate", "lower", "upper"]].to_dict("records")
[{'method': 'marker', 'name': 'L', 'estimate': 250.0, 'lower': 246.1, 'upper': 253.9}]
>>> idata = to_inference_data(result, n_draws=500, rng=np.random.default_rng(0))
>>> idata.posterior["L"].shape
(1, 500)
"""

from __future__ import annotations

import importlib
import math
import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from skelid.errors import SettingError, SkelidError

#: the columns of :func:`to_dataframe`, in order
COLUMNS = ("method", "name", "kind", "unit", "estimate", "map", "sd", "lower", "upper", "crlb_sd", "status")


def _need(module: str):
    """Import an optional library, or say in one line how to get it."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise SkelidError(f"this conversion needs the {module} package, which is not installed",
                          "pip install 'skelid[data]' (pandas, xarray, arviz)") from None


# ----------------------------------------------------------------------------- one shape for every input
def as_run(result, arrays: Mapping | None = None):
    """The :class:`~skelid.result.FitRun` of any form a result comes in.

    Parameters
    ----------
    result : FitRun, FitResult, path of a result folder, or ``result.json`` dict
    arrays : mapping, optional
        The arrays of a ``result.json`` dict (``arrays.npz``'s content).

    A folder is read by :func:`skelid.io.results.read_run` (checked; an old or
    damaged one is refused in one line); a dict without ``schema_version`` is
    taken as the layout before version 1 (:func:`skelid.io.legacy.run_from_legacy`).
    """
    from skelid.io.legacy import run_from_legacy
    from skelid.io.results import read_run, run_from_dict
    from skelid.result import FitResult, FitRun

    if arrays is not None and not isinstance(arrays, Mapping):
        raise SettingError(f"arrays must be a mapping of name to array (arrays.npz's content), got "
                           f"{type(arrays).__name__}", "give dict(numpy.load('arrays.npz')) or leave it out")
    if isinstance(result, FitRun):
        return result
    if isinstance(result, FitResult):
        return FitRun({result.method: result})
    if isinstance(result, str | os.PathLike):
        return read_run(result)
    if isinstance(result, Mapping):
        if "schema_version" in result:
            return run_from_dict(result, arrays)
        return run_from_legacy(result, arrays)
    raise SkelidError(f"cannot convert a {type(result).__name__}",
                      "give a FitRun, a FitResult, a result folder or a result.json dict")


def _pick(run, method: str | None, prefer=()):
    """The result of ``method``; by default the first that has one of the arrays ``prefer``, else the first."""
    if not run.results:
        raise SkelidError("the result holds no method", "fit first: skelid fit MODEL DATA --out DIR")
    if method is not None and not isinstance(method, str):
        raise SettingError(f"method must be a method name (str) or None, got {type(method).__name__}",
                           f"use one of: {', '.join(run.results)}")
    if method is None:
        return next((r for r in run.results.values() if any(k in r.arrays for k in prefer)),
                    next(iter(run.results.values())))
    if method not in run.results:
        raise SkelidError(f"the result has no method {method!r}", f"use one of: {', '.join(run.results)}")
    return run.results[method]


def _model(run):
    desc = run.context.get("model_description") if isinstance(run.context, Mapping) else None
    if not isinstance(desc, Mapping):
        return None
    from skelid.model import model_from_dict

    try:
        return model_from_dict(dict(desc), str(run.context.get("model", "model")))
    except (SkelidError, KeyError, TypeError, ValueError):
        return None


# ----------------------------------------------------------------------------- pandas
def estimate_fields(p) -> dict:
    """One :class:`~skelid.result.ParameterEstimate` as the values of a table row.

    ``estimate`` (posterior mean), ``map``, ``sd``, ``lower``/``upper`` (95 % interval),
    ``crlb_sd`` (NaN where not computed) and ``status`` (None where the method gives
    none), in the order of :data:`COLUMNS`. :func:`to_dataframe` and the batch table
    (:mod:`skelid.batch`) both take their values from here.
    """
    return {"estimate": p.mean, "map": p.map, "sd": p.sd, "lower": p.interval[0], "upper": p.interval[1],
            "crlb_sd": math.nan if p.crlb_sd is None else p.crlb_sd,
            "status": p.status if p.extra.get("status_given", True) else None}


def to_dataframe(result, arrays: Mapping | None = None):
    """One row per parameter, derived quantity and noise level of every method.

    Parameters
    ----------
    result : FitRun, FitResult, result folder or ``result.json`` dict
    arrays : mapping, optional
        With a ``result.json`` dict: its arrays (for the Cramér-Rao bounds kept there).

    Returns
    -------
    pandas.DataFrame
        Columns :data:`COLUMNS`: ``kind`` is ``parameter``, ``derived`` or
        ``noise``; ``estimate`` the posterior mean; ``lower``/``upper`` the 95 %
        interval; ``crlb_sd`` NaN where not computed; ``status`` None where the
        method gives none.
    """
    pd = _need("pandas")
    run = as_run(result, arrays)
    rows = []
    for method, r in run.results.items():
        for kind, table in (("parameter", r.parameters), ("derived", r.derived)):
            for name, p in table.items():
                rows.append((method, name, kind, p.unit, *estimate_fields(p).values()))
        n = getattr(r, "noise", None)
        if n is not None:
            lo, hi = n.interval if n.interval is not None else (math.nan, math.nan)
            unit = next((p.unit for p in r.parameters.values()), run.context.get("units", ""))
            rows.append((method, "sigma", "noise", unit, n.sigma, n.sigma, math.nan, lo, hi, math.nan,
                         "prior" if n.fixed else None))
    df = pd.DataFrame(rows, columns=list(COLUMNS))
    for c in ("estimate", "map", "sd", "lower", "upper", "crlb_sd"):
        df[c] = df[c].astype(float)
    return df


# ----------------------------------------------------------------------------- xarray
def _coordinate_names(model) -> list[str]:
    """A name for each pose coordinate: ``joint.r`` / ``joint.t`` plus the axis (or its number in the joint)."""
    out, seen = [], {}
    for d in model.dofs:
        joint = model.segments[d.segment].joint.name
        axis = np.asarray(d.axis, float)
        tag = "r" if d.kind == "R" else "t"
        if axis.size and np.count_nonzero(axis) == 1 and abs(axis.max() - 1.0) < 1e-12:
            tag += "xyz"[int(np.argmax(axis))]
        key = f"{joint}.{tag}"
        seen[key] = seen.get(key, 0) + 1
        out.append(key if seen[key] == 1 else f"{key}{seen[key]}")
    return out


def to_xarray(result, method: str | None = None, arrays: Mapping | None = None):
    """The per-frame arrays of one method as an :class:`xarray.Dataset` with named dims.

    Parameters
    ----------
    result : FitRun, FitResult, result folder or ``result.json`` dict
    method : str, optional
        Which method (default: the first with poses or residuals, else the first).
    arrays : mapping, optional
        With a ``result.json`` dict: its arrays.

    Returns
    -------
    xarray.Dataset
        ``markers (frame, marker, axis)`` measured, in model units (where the
        result holds them), ``pose (frame, coordinate)`` (radians for rotations)
        and ``residuals (frame, marker)`` where the method has them; coordinates
        ``frame``, ``time`` (s), ``marker``, ``axis``, ``coordinate``; attributes
        ``method``, ``units``, ``rate_hz``.
    """
    xr = _need("xarray")
    run = as_run(result, arrays)
    r = _pick(run, method, prefer=("pose", "residuals"))
    shared = dict(run.arrays)
    model = _model(run)
    units = str(run.context.get("units") or shared.get("units", "") or "")
    rate = float(shared["rate"]) if "rate" in shared else float("nan")
    names = [str(n) for n in shared.get("marker_names", model.marker_names if model else [])]
    data, coords, names = _frame_variables(shared, dict(r.arrays), model, names)
    if not data:
        raise SkelidError(f"the {r.method} method's result holds no per-frame arrays",
                          "write the result with 'skelid fit ... --out DIR' (arrays.npz)")
    n_frames = next(iter(data.values()))[1].shape[0]
    frame = np.arange(n_frames)
    coords.update(frame=frame, time=("frame", frame / rate if math.isfinite(rate) and rate > 0 else
                                     np.full(n_frames, np.nan)))
    if "markers" in data or "residuals" in data:
        coords["marker"] = names
    if "markers" in data:
        coords["axis"] = list("xyz"[: data["markers"][1].shape[2]])
    return xr.Dataset(data, coords=coords, attrs={"method": r.method, "units": units, "rate_hz": rate})


def _frame_variables(shared: dict, own: dict, model, names: list) -> tuple[dict, dict, list]:
    """The dataset's variables (measured markers, poses, residuals), the coordinate names and the marker names.

    Marker names that do not match the arrays' marker count become ``m0, m1, ...``.
    """
    data, coords = {}, {}
    y = shared.get("markers")
    if y is not None:
        y = np.asarray(y, float)
        names = names if len(names) == y.shape[1] else [f"m{k}" for k in range(y.shape[1])]
        data["markers"] = (("frame", "marker", "axis"), y)
    pose = own.get("pose", own.get("poses"))
    if pose is not None:
        pose = np.asarray(pose, float)
        cn = _coordinate_names(model) if model is not None and model.n_pose == pose.shape[1] else \
            [f"q{k}" for k in range(pose.shape[1])]
        data["pose"] = (("frame", "coordinate"), pose)
        coords["coordinate"] = cn
    res = own.get("residuals")
    if res is not None and np.ndim(res) == 2:
        res = np.asarray(res, float)
        if len(names) != res.shape[1]:
            names = [f"m{k}" for k in range(res.shape[1])]
        data["residuals"] = (("frame", "marker"), res)
    return data, coords, names


# ----------------------------------------------------------------------------- arviz
def _systematic(weights: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``n`` equal-weight draws from weighted samples (systematic resampling)."""
    w = np.asarray(weights, float)
    c = np.cumsum(w / w.sum())
    c[-1] = 1.0
    return np.searchsorted(c, (rng.random() + np.arange(n)) / n)


def _draws(r, names: list[str], n_draws: int, rng: np.random.Generator) -> tuple[np.ndarray, str]:
    """``(n_draws, P)`` posterior draws of the parameters and how they were made."""
    own = dict(r.arrays)
    samples = own.get("samples")
    P = len(names)
    if samples is not None and np.ndim(samples) == 2 and np.shape(samples)[1] == P and len(samples):
        samples = np.asarray(samples, float)
        w = own.get("sample_weights", own.get("weights"))
        if w is not None and np.shape(w) == (len(samples),) and np.ptp(w) > 0:
            return samples[_systematic(w, n_draws, rng)], "the sampler's weighted samples, resampled systematically"
        if len(samples) >= n_draws:
            return samples[rng.choice(len(samples), n_draws, replace=False)], "the sampler's samples"
        return samples, "the sampler's samples"
    mean = np.array([r.parameters[n].mean for n in names])
    cov = own.get("cov", own.get("posterior.cov"))
    how = "the Gaussian posterior (mean and covariance)"
    if cov is None or np.shape(cov) != (P, P):
        cov = np.diag([r.parameters[n].sd ** 2 for n in names])
        how = "independent normals with each parameter's mean and sd (the result holds no covariance)"
    cov = np.asarray(cov, float)
    if not (np.isfinite(mean).all() and np.isfinite(cov).all()):
        raise SkelidError(f"the {r.method} method's posterior is not finite", "check the fit's warnings")
    return rng.multivariate_normal(mean, cov, size=n_draws, method="eigh"), how


def _derived_draws(r, model, names: list, theta, rng, post: dict) -> str:
    """Draws of the derived lengths into ``post``; how they were made.

    Through the model's geometry from each draw of the parameters where the result holds the model,
    else independent normals with each length's mean and sd.
    """
    if not r.derived:
        return ""
    lengths, how = None, ""
    if model is not None and tuple(model.parameter_names) == tuple(names):
        from skelid.model.kinematics import joint_distances

        keys = [k for k, _ in model.derived_lengths]
        if set(r.derived) <= set(keys):
            L, _ = joint_distances(model, theta)
            lengths = {k: L[:, keys.index(k)] for k in r.derived}
            how = "computed from each draw of the parameters through the model's geometry"
    if lengths is None:
        lengths = {k: rng.normal(p.mean, p.sd, size=theta.shape[0]) for k, p in r.derived.items()}
        how = "independent normals with each length's mean and sd (no model in the result)"
    for k, v in lengths.items():
        if k in post:
            raise SkelidError(f"derived length {k!r} has the name of a parameter", "rename the parameter or the joint")
        post[k] = np.asarray(v)[None, :]
    return how


def to_inference_data(result, method: str | None = None, n_draws: int = 1000,
                      rng: np.random.Generator | None = None, arrays: Mapping | None = None):
    """Posterior draws of every parameter and derived length, and the observed markers, for ArviZ.

    Parameters
    ----------
    result : FitRun, FitResult, result folder or ``result.json`` dict
    method : str, optional
        Which method (default: the first).
    n_draws : int
        Draws to make (from a Gaussian posterior; a sampler's samples are
        resampled to this many).
    rng : numpy.random.Generator, optional
        Source of the draws (default ``numpy.random.default_rng(0)``, so that
        two calls agree).
    arrays : mapping, optional
        With a ``result.json`` dict: its arrays.

    Returns
    -------
    arviz.InferenceData
        ``posterior``: one variable per parameter and derived length, dims
        ``(chain, draw)`` with one chain; its attributes say where the draws
        came from. ``observed_data``: ``markers (frame, marker, axis)`` where
        the result holds them.
    """
    az = _need("arviz")
    if not (isinstance(n_draws, int | np.integer) and not isinstance(n_draws, bool) and n_draws >= 1):
        raise SettingError(f"n_draws must be an integer of at least 1, got {n_draws!r}", "e.g. n_draws=1000")
    if rng is not None and not isinstance(rng, np.random.Generator):
        raise SettingError(f"rng must be a numpy.random.Generator or None, got {type(rng).__name__}",
                           "give rng=numpy.random.default_rng(seed)")
    rng = np.random.default_rng(0) if rng is None else rng
    run = as_run(result, arrays)
    r = _pick(run, method)
    names = list(r.parameters)
    theta, how = _draws(r, names, int(n_draws), rng) if names else (np.zeros((int(n_draws), 0)), "")
    post: dict[str, Any] = {n: theta[None, :, k] for k, n in enumerate(names)}
    derived_how = _derived_draws(r, _model(run), names, theta, rng, post)
    attrs = {"method": r.method, "draws_from": how, "derived_from": derived_how,
             "units": str(run.context.get("units", ""))}
    groups = {"posterior": post, "posterior_attrs": attrs}
    y = dict(run.arrays).get("markers")
    if y is not None:
        y = np.asarray(y, float)
        mnames = [str(n) for n in dict(run.arrays).get("marker_names", [])]
        groups["observed_data"] = {"markers": y}
        groups["dims"] = {"markers": ["frame", "marker", "axis"]}
        groups["coords"] = {"frame": np.arange(y.shape[0]), "axis": list("xyz"[: y.shape[2]]),
                            "marker": mnames if len(mnames) == y.shape[1] else list(range(y.shape[1]))}
    return az.from_dict(**groups)
