"""End-to-end jobs the command line runs: fit a file, run the demo.

They return JSON-ready dicts; figures and files go through :mod:`skelid.plots`
and the atomic writers. No argument parsing here, no maths either: only the
checks that turn a user's mistake into a one-line :class:`~skelid.errors.SkelidError`
before it becomes a traceback, and the warnings a user should read.

An output folder (``fit --out DIR``, ``demo --out DIR``) is built in a hidden
temporary sibling and moved in when complete (:func:`skelid.io.atomic.atomic_dir`).
``fit`` writes into it:

``result.json``
    The summary (:func:`fit_file`) plus ``command``, ``cwd``, ``versions``,
    ``data_overview``, ``model_parameters``, ``model_description`` (the model as a
    dict, for the report's view of the fitted body) and ``warnings``.
``arrays.npz``
    What is not JSON-friendly (:func:`fit_arrays`): ``markers (F, M, D)`` in
    model units, ``marker_names``, ``rate``, ``units``, and per method ``NAME.*``
    entries: posterior grid axes, final marginals and their history, Gaussian
    mean and covariance, posterior samples and their weights, per-frame
    measured values, ``residuals (F, M)``, ``crlb_sd (P,)``, ``pose (F, Q)``.
``*.png``
    The seed paper's figures.
"""

from __future__ import annotations

import contextlib
import datetime
import inspect
import json
import math
import os
import platform
import sys
import time
import warnings
from importlib import metadata
from pathlib import Path

import numpy as np

from skelid import checks, resources
from skelid.data import MarkerData, unit_scale
from skelid.errors import DataError, FormatError, ModelError, SkelidError, SkelidWarning
from skelid.estimators.base import prepare
from skelid.estimators.marker import NUMERICAL_RESIDUAL
from skelid.io.atomic import atomic_dir, atomic_write, check_output_dir
from skelid.model.description import Model

#: a marker missing in more than this fraction of frames gets a warning
GAP_WARN_FRACTION = 0.10
#: a 95 % interval wider than this fraction of the prior interval gets a warning
POOR_FRACTION = 0.5
#: lag-1 autocorrelation of a marker's residuals above which they look like soft-tissue artefact
STA_AUTOCORR = 0.7
#: the same for the per-frame measured values of a one-parameter method
MEASURED_AUTOCORR = 0.5


def methods() -> dict:
    """Estimator classes by method name."""
    from skelid.estimators.grid import MarkerGridFilter
    from skelid.estimators.marker import MarkerEstimator
    from skelid.estimators.paper import PaperFilter
    from skelid.estimators.sampler import SamplerEstimator

    return {"marker": MarkerEstimator, "paper": PaperFilter, "marker-grid": MarkerGridFilter,
            "marker-smc": SamplerEstimator}


DEFAULT_METHOD = "marker"
DEMO_METHODS = ("paper", "marker")


def make_estimator(name: str, model: Model, sigma: float | None = None,
                   rng: np.random.Generator | None = None, cutoff: float | None = None,
                   artefact_rms: float | None = None):
    table = methods()
    if name not in table:
        raise ModelError(f"unknown method {name!r}", f"use one of: {', '.join(table)}")
    if sigma is not None:
        size = float(np.abs(model.nominal_geometry).max())
        if not (math.isfinite(sigma) and sigma > 0):
            raise SkelidError(f"--sigma must be a positive finite number of {model.units}, got {sigma}",
                              f"give the marker noise in {model.units}")
        if sigma < 1e-6 * size:
            raise SkelidError(f"--sigma {sigma:g} {model.units} is implausibly small for model {model.name!r} "
                              f"(size {size:g} {model.units})",
                              f"give the marker noise in {model.units}; markers are rarely better than "
                              f"{0.1 * unit_scale('mm', model.units):g} {model.units}")
    extra = {}
    if artefact_rms is not None:
        if not (math.isfinite(artefact_rms) and artefact_rms >= 0):
            raise SkelidError(f"--artefact-rms must be a distance >= 0 {model.units}, got {artefact_rms}",
                              f"give the soft-tissue artefact's rms displacement in {model.units}, or 0 for none")
        if name in ("marker", "marker-smc"):
            extra["artefact_rms"] = artefact_rms or None
        elif artefact_rms:
            raise SkelidError(f"--artefact-rms is not available with --method {name}: its posterior does not come "
                              "from the joint fit the artefact term is computed from",
                              "use --method marker or marker-smc with --artefact-rms")
    if cutoff is not None and name in ("marker", "marker-smc"):
        if not (math.isfinite(cutoff) and cutoff >= 0):
            raise SkelidError(f"--cutoff must be a frequency >= 0 Hz, got {cutoff}",
                              "use 0 for no motion model, or e.g. --cutoff 6")
        return table[name](model, sigma=sigma, rng=rng, cutoff=cutoff or None, **extra)
    return table[name](model, sigma=sigma, rng=rng, **extra)


# --------------------------------------------------------------------------- checks
def check_input_file(path, what: str = "data file") -> Path:
    """An existing, readable, non-empty regular file, or a one-line error naming it."""
    from skelid.io._common import check_regular_file

    path = Path(path)
    cls = ModelError if what.startswith("model") else FormatError
    check_regular_file(path, what, cls)
    try:
        with open(path, "rb") as fh:
            head = fh.read(1)
    except OSError as exc:
        raise cls(f"cannot read {what} {path}: {exc.strerror or exc}",
                  "check the file's permissions") from None
    if not head:
        raise cls(f"{what} {path} is empty", "check that the file was written completely")
    return path


def check_cost(model: Model, method: str, n_frames: int, limits=None, about: bool = False):
    """Refuse a fit whose estimated memory or time exceeds ``limits`` (see :mod:`skelid.resources`).

    Returns the estimate (:class:`skelid.resources.Cost`).
    """
    resources.check_grid(model, method)
    frames = "" if n_frames <= 1 else f" of {'about ' if about else ''}{n_frames} frames"
    return resources.check(resources.fit_cost(model, method, n_frames), limits, f"the {method} fit{frames}")


def _model_names_in_file(model: Model, data: MarkerData) -> dict[str, str]:
    """Model marker name -> name in the file, for the markers that are there."""
    labels = model.marker_labels
    names = set(data.names)
    bare: dict[str, list[str]] = {}
    for n in data.names:
        bare.setdefault(n.rsplit(":", 1)[-1], []).append(n)
    out = {}
    for m in model.marker_names:
        w = labels.get(m, m)
        if w in names:
            out[m] = w
        elif len(bare.get(w, [])) == 1:
            out[m] = bare[w][0]
    return out


def _path_bounds(model: Model) -> tuple[np.ndarray, np.ndarray]:
    """``(rigid (M, M), upper (M, M))``: exact distances between markers on one segment
    (NaN across segments), and upper bounds through the joint centres for any pair."""
    seg = {s.name: i for i, s in enumerate(model.segments)}
    parent = model.parent_index
    jlen = np.array([np.linalg.norm(s.joint.position) for s in model.segments])
    jlen[parent < 0] = 0.0

    def chain(s):
        out = [s]
        while parent[out[-1]] >= 0:
            out.append(int(parent[out[-1]]))
        return out

    M = len(model.markers)
    pos = [np.asarray(m.position, float) for m in model.markers]
    si = [seg[m.segment] for m in model.markers]
    rigid = np.full((M, M), np.nan)
    upper = np.zeros((M, M))
    for a in range(M):
        ca = chain(si[a])
        for b in range(M):
            if si[a] == si[b]:
                rigid[a, b] = upper[a, b] = np.linalg.norm(pos[a] - pos[b])
                continue
            cb = chain(si[b])
            common = next(s for s in ca if s in cb)
            path = ca[:ca.index(common)] + cb[:cb.index(common)]
            upper[a, b] = np.linalg.norm(pos[a]) + np.linalg.norm(pos[b]) + jlen[path].sum()
    return rigid, upper


def check_units(model: Model, data: MarkerData) -> None:
    """Compare marker distances in the data with the model's, to catch wrong units.

    Distances between markers on one segment must match the model's; any
    distance must stay below the model's bound through the joint centres.

    Raises
    ------
    DataError
        The data are ~3x or more larger (or smaller) than the model says.
    """
    names = _model_names_in_file(model, data)
    if len(names) < 2:
        return
    idx = {n: data.names.index(f) for n, f in names.items()}
    mi = [i for i, m in enumerate(model.marker_names) if m in idx]
    y = data.positions[:, [idx[model.marker_names[i]] for i in mi]] * unit_scale(data.units, model.units)
    with warnings.catch_warnings(), np.errstate(invalid="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        d = np.nanmedian(np.linalg.norm(y[:, :, None] - y[:, None, :], axis=-1), axis=0)
    rigid, upper = _path_bounds(model)
    rigid, upper = rigid[np.ix_(mi, mi)], upper[np.ix_(mi, mi)]
    iu = np.triu_indices(len(mi), 1)
    d, rigid, upper = d[iu], rigid[iu], upper[iu]
    ok = np.isfinite(d)
    r_rigid = d[ok & (rigid > 0)] / rigid[ok & (rigid > 0)]
    r_upper = d[ok & (upper > 0)] / upper[ok & (upper > 0)]
    factor = None
    if r_rigid.size:
        s = float(np.median(r_rigid))
        if s > 3 or s < 1 / 3:
            factor = s
    elif r_upper.size:
        s = float(np.median(r_upper))
        if s > 3 or float(np.max(r_upper)) < 1 / 30:
            factor = s
    if factor is not None:
        where = data.source or "the data"
        raise DataError(
            f"marker distances in {where} are about {factor:.3g} times those of model {model.name!r} "
            f"(file units: {data.units}, model units: {model.units}); the units of one of them are wrong",
            "check the units field of the data file and the units of the model; mm, cm and m are "
            "converted automatically",
        )


def _gap_runs(missing: np.ndarray) -> tuple[int, int]:
    """Number of runs of True in ``missing (F,)`` and the longest run."""
    if not missing.any():
        return 0, 0
    m = np.concatenate([[False], missing, [False]]).astype(int)
    starts = np.flatnonzero(np.diff(m) == 1)
    stops = np.flatnonzero(np.diff(m) == -1)
    return int(len(starts)), int((stops - starts).max())


def data_overview(data: MarkerData, model: Model | None = None) -> dict:
    """What the file holds: size, rate, units, and the gaps of every marker.

    Returns
    -------
    dict
        ``source, format, n_frames, n_markers, dim, rate_hz, units, duration_s,
        model_markers {model name: file name}, markers [{name, used_by_model,
        frames_missing, gaps, longest_gap}]``.
    """
    used = _model_names_in_file(model, data) if model is not None else {}
    in_model = {f: m for m, f in used.items()}
    present = data.present
    markers = []
    for k, n in enumerate(data.names):
        runs, longest = _gap_runs(~present[:, k])
        markers.append({"name": n, "used_by_model": n in in_model,
                        "frames_missing": int((~present[:, k]).sum()), "gaps": runs,
                        "longest_gap": longest})
    return {
        "source": data.source, "format": data.meta.get("format", Path(data.source).suffix.lstrip(".")),
        "n_frames": data.n_frames, "n_markers": data.n_markers, "dim": data.dim,
        "rate_hz": data.rate, "units": data.units,
        "duration_s": round(data.n_frames / data.rate, 6), "model_markers": used,
        "markers": markers,
    }


def overview_warnings(overview: dict) -> list[str]:
    F = overview["n_frames"]
    out = []
    for m in overview["markers"]:
        if m["used_by_model"] and m["frames_missing"] > GAP_WARN_FRACTION * F:
            out.append(f"marker {m['name']} is missing in {m['frames_missing']} of {F} frames "
                       f"({100 * m['frames_missing'] / F:.0f} %, {m['gaps']} gaps, longest "
                       f"{m['longest_gap']} frames)")
    return out


def fit_warnings(model: Model, name: str, res: dict, est) -> list[str]:
    """Warnings about a fit a user should read: poorly identified parameters,
    parameters stuck at a bound of their prior, residuals that look like
    soft-tissue artefact."""
    out = []
    for p in model.parameters:
        v = res.get(p.name)
        if not isinstance(v, dict) or "ci95" not in v:
            continue
        lo, hi = p.prior.lower, p.prior.upper
        width = hi - lo
        ci = v["ci95"]
        if width > 0 and ci[1] - ci[0] > POOR_FRACTION * width:
            out.append(f"parameter {p.name} is poorly identified by the {name} method: its 95 % interval "
                       f"[{ci[0]:.4g}, {ci[1]:.4g}] {model.units} covers {100 * (ci[1] - ci[0]) / width:.0f} % "
                       f"of the prior interval")
        elif width > 0 and min(v["map"] - lo, hi - v["map"]) <= max(p.grid_step, 0.005 * width):
            out.append(f"parameter {p.name} ({name} method) is at a bound of its prior interval "
                       f"[{lo:g}, {hi:g}] {model.units}; the interval may be too narrow")
    for row in res.get("identifiability", []) or []:
        status = str(row.get("status", ""))
        if status and status.lower() not in ("ok", "identified", "well identified", "well-identified", "good"):
            out.append(f"parameter {row.get('parameter')} is {status} ({name} method)")
    r = getattr(est, "residuals_", None)
    if r is not None and np.ndim(r) == 2:
        r = np.asarray(r, float)
        # residuals at the level of the file's rounding (noise-free data) say nothing about tissue
        floor = NUMERICAL_RESIDUAL * float(np.abs(model.nominal_geometry).max())
        misfit = {v["segment"] for v in (getattr(est, "misfit_", None) or {}).values() if v["flagged"]}
        on_misfit = {model.markers[m].segment for m in range(len(model.markers))} & misfit
        slow = []
        for m, mname in enumerate(model.marker_names[: r.shape[1]]):
            if model.markers[m].segment in on_misfit:
                continue  # already reported as model misfit
            rho = lag1_autocorrelation(r[:, m])
            rms = float(np.sqrt(np.nanmean(r[:, m] ** 2))) if np.isfinite(r[:, m]).any() else 0.0
            if rho > STA_AUTOCORR and rms > floor:
                slow.append(f"{mname} (rms {rms:.3g}, lag-1 {rho:.2f})")
                one = (f"residuals of marker {mname} ({name} method, rms {rms:.3g} {model.units}) are "
                       f"correlated in time (lag-1 autocorrelation {rho:.2f}): this looks like "
                       "soft-tissue artefact, not measurement noise")
        if len(slow) == 1:
            out.append(one)
        elif slow:  # one line for all of them
            out.append(f"residuals of {len(slow)} marker(s) ({name} method) are correlated in time: "
                       f"{', '.join(slow)} {model.units}; this looks like soft-tissue artefact, not measurement "
                       "noise")
    measured = getattr(est, "measured_", None)
    if measured is not None and model.n_params == 1:
        rho = lag1_autocorrelation(measured)
        if rho > MEASURED_AUTOCORR:
            out.append(f"the per-frame values of {model.parameter_names[0]} ({name} method) drift slowly "
                       f"(lag-1 autocorrelation {rho:.2f}) instead of scattering independently: this looks "
                       "like soft-tissue artefact, and the 95 % interval, which treats frames as independent, "
                       "is too narrow")
    return out


def lag1_autocorrelation(x, min_pairs: int = 20) -> float:
    """Correlation of ``x[t]`` with ``x[t+1]`` over consecutive finite pairs (NaN if fewer than ``min_pairs``).

    Measurement noise gives values near 0; slow drifts (soft-tissue artefact) give values near 1.
    """
    x = np.asarray(x, float)
    fin = np.isfinite(x)
    if fin.sum() < 2:
        return float("nan")
    x = x - x[fin].mean()
    a, b = x[:-1], x[1:]
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < min_pairs:
        return float("nan")
    den = math.sqrt(float(a[ok] @ a[ok]) * float(b[ok] @ b[ok]))
    return float(a[ok] @ b[ok]) / den if den > 0 else float("nan")


def _unique(seq) -> list:
    out = []
    for s in seq:
        if s not in out:
            out.append(s)
    return out


@contextlib.contextmanager
def collect_warnings():
    """Record :class:`SkelidWarning` messages instead of printing them; other warnings pass."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", SkelidWarning)
        box: list[str] = []
        yield box
    for w in caught:
        if issubclass(w.category, SkelidWarning):
            box.append(str(w.message))
        else:  # pragma: no cover - not ours: show it as usual
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)


# --------------------------------------------------------------------------- provenance
def versions() -> dict:
    """Versions of Python, skelid and the libraries that shape a result."""
    out = {"python": platform.python_version(), "platform": platform.platform()}
    for pkg in ("skelid", "numpy", "scipy", "ezc3d", "matplotlib", "click", "tqdm"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def provenance(command=None) -> dict:
    return {
        "command": list(command) if command is not None else ["skelid", *sys.argv[1:]],
        "cwd": os.getcwd(),
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "versions": versions(),
    }


def model_parameters(model: Model) -> dict:
    """Prior interval and nominal value of each parameter (for reports)."""
    return {p.name: {"kind": p.kind, "target": p.target, "prior": p.prior.to_dict(),
                     "nominal": float(v), "units": model.units}
            for p, v in zip(model.parameters, model.theta_nominal, strict=True)}


# --------------------------------------------------------------------------- fitting
def _progress_bar(total: int, desc: str, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="frame", leave=False, file=sys.stderr,
                disable=not enabled or not sys.stderr.isatty(), mininterval=0.25)


def fit_file(model: Model, data: MarkerData, method_names, sigma: float | None = None,
             seed: int = 0, progress: bool = False, cutoff: float | None = None,
             artefact_rms: float | None = None) -> tuple[dict, dict]:
    """Fit ``model`` to ``data`` with each method.

    Returns
    -------
    result : dict
        ``{"frames_total": F, "methods": {name: summary}}``.
    fitted : dict
        The fitted estimators by name (for figures).
    """
    estimators = {name: make_estimator(name, model, sigma=sigma, rng=np.random.default_rng(seed),
                                       cutoff=cutoff, artefact_rms=artefact_rms)
                  for name in method_names}  # unknown methods fail before any work
    y = prepare(model, data)
    out = {"model": model.name, "data": data.source, "units": model.units,
           "frames_total": int(y.shape[0]), "methods": {}}
    fitted = {}
    for name, est in estimators.items():
        t0 = time.perf_counter()
        kw = {}
        bar = _progress_bar(len(y), f"fit {name}", progress)
        if "progress" in inspect.signature(est.fit).parameters:
            kw["progress"] = bar.update
        with bar, warnings.catch_warnings():
            warnings.simplefilter("ignore", SkelidWarning)  # recorded in the result instead
            est.fit(data, **kw)
        res = est.result()
        _check_finite(name, res)
        res["seconds"] = round(time.perf_counter() - t0, 4)
        out["methods"][name] = res
        fitted[name] = est
    return out, fitted


def _check_finite(method: str, res: dict) -> None:
    """A method that returns NaN estimates has a bug; say so loudly rather than write NaN."""
    for pname, v in res.items():
        if isinstance(v, dict) and "map" in v:
            vals = [v["map"], v.get("mean", 0.0), *v.get("ci95", ())]
            if not all(isinstance(x, int | float) and math.isfinite(x) for x in vals):
                raise FloatingPointError(f"the {method} method returned non-finite estimates for {pname}: {v}")


def fit_arrays(model: Model, y: np.ndarray, rate: float, fitted: dict) -> dict[str, np.ndarray]:
    """The arrays a report needs that JSON holds badly (see the module docstring)."""
    out = {"markers": np.asarray(y, float), "marker_names": np.array(model.marker_names, dtype=str),
           "rate": np.array(float(rate)), "units": np.array(model.units)}
    for name, est in fitted.items():
        out.update({f"{name}.{k}": v for k, v in estimator_arrays(est).items()})
    return out


def estimator_arrays(est) -> dict[str, np.ndarray]:
    """Posterior grid, history, Gaussian moments, residuals and bounds of a fitted estimator.

    Works on any estimator by the attributes it has: ``posterior_`` (a grid
    posterior with ``axes``, ``history``, ``marginal(k, lw)``; weighted samples
    with ``points``, ``weights``, whose mean and covariance are stored too; or a
    Gaussian with ``mean``, ``cov``), ``residuals_ (F, M)``, ``crlb_sd_ (P,)``,
    ``measured_ (F,)``, ``map_path_ (F,)``, ``pose_ (F, Q)`` (stored as ``pose``).
    """
    out: dict[str, np.ndarray] = {}
    post = getattr(est, "posterior_", None)
    if post is not None:
        out["posterior.names"] = np.array(tuple(getattr(post, "names", ())), dtype=str)
        history = tuple(getattr(post, "history", ()) or ())
        if hasattr(post, "axes") and hasattr(post, "marginal"):
            out["posterior.kind"] = np.array("grid")
            steps = [int(h[0]) for h in history]
            out["posterior.history_steps"] = np.array(steps, dtype=int)
            for k, ax in enumerate(post.axes):
                out[f"posterior.axis.{k}"] = np.asarray(ax, float)
                out[f"posterior.marginal.{k}"] = np.asarray(post.marginal(k), float)
                if steps:
                    out[f"posterior.history.{k}"] = np.stack([post.marginal(k, h[1]) for h in history])
        elif hasattr(post, "points") and hasattr(post, "weights"):
            out["posterior.kind"] = np.array("samples")
            out["posterior.points"] = np.asarray(post.points, float)
            out["posterior.weights"] = np.asarray(post.weights, float)
            out["posterior.mean"] = np.asarray(post.mean, float)
            out["posterior.cov"] = np.atleast_2d(np.asarray(post.cov, float))
        elif hasattr(post, "cov"):
            out["posterior.kind"] = np.array("gaussian")
            out["posterior.mean"] = np.asarray(post.mean, float)
            out["posterior.cov"] = np.asarray(post.cov, float)
            hist = [h for h in history if len(h) == 3]
            if hist:
                out["posterior.history_steps"] = np.array([int(h[0]) for h in hist])
                out["posterior.history_mean"] = np.stack([np.asarray(h[1], float) for h in hist])
                out["posterior.history_cov"] = np.stack([np.asarray(h[2], float) for h in hist])
    for attr in ("residuals_", "crlb_sd_", "measured_", "map_path_", "pose_"):
        v = getattr(est, attr, None)
        if v is not None:
            out[attr.rstrip("_")] = np.asarray(v, float)
    return out


def write_json(path, obj) -> Path:
    path = Path(path)
    text = json.dumps(obj, indent=2, default=_json_default, allow_nan=True)
    with atomic_write(path) as fh:
        fh.write(text + "\n")
    return path


def write_npz(path, arrays: dict) -> Path:
    path = Path(path)
    with atomic_write(path, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    return path


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def run_fit(model_path, data_path, method_names=(), sigma: float | None = None, seed: int = 0,
            out_dir=None, command=None, progress: bool = False, cutoff: float | None = None,
            artefact_rms: float | None = None, limits=None, overwrite: bool = False) -> dict:
    """Everything ``skelid fit`` does: check, read, fit, warn, write ``out_dir``.

    An existing ``out_dir`` is refused unless ``overwrite``, which replaces it whole.

    ``limits`` (:class:`skelid.resources.Limits`, default from the environment)
    bounds the memory and time the fit is estimated to need: beyond them it is
    refused before reading or fitting.

    Returns
    -------
    dict
        The result, with ``warnings`` (each message once) and provenance.
    """
    from skelid.io import read_markers
    from skelid.simulate import BUILTIN_MODELS, resolve_model

    if out_dir is not None:
        check_output_dir(out_dir, overwrite)
    if str(model_path).lower().replace("_", "-") not in BUILTIN_MODELS:
        check_input_file(model_path, "model file")
    model = resolve_model(model_path)
    check_input_file(data_path, "data file")
    names = list(method_names) or [DEFAULT_METHOD]
    for n in names:
        # an unknown method or a bad setting fails before reading
        make_estimator(n, model, sigma, cutoff=cutoff, artefact_rms=artefact_rms)
        check_cost(model, n, 1, limits)  # a grid too large for any data
    resources.check(resources.read_cost(data_path), limits, f"reading {data_path}")
    n_guess = resources.estimate_frames(data_path)
    if n_guess is not None:  # a file too long to fit is refused before it is parsed
        for n in names:
            check_cost(model, n, n_guess, limits, about=True)
    with collect_warnings() as read_warnings:
        data = read_markers(data_path)
        check_units(model, data)
    checks.check_data(model, prepare(model, data), names, data.source or str(data_path))
    cost = [check_cost(model, n, data.n_frames, limits) for n in names]
    if progress and sys.stderr.isatty() and sum(c.seconds for c in cost) > 30:
        sys.stderr.write(f"skelid: this fit may take about {resources.format_seconds(sum(c.seconds for c in cost))} "
                         f"and {resources.format_size(max(c.memory for c in cost))} of memory\n")
    overview = data_overview(data, model)
    result, fitted = fit_file(model, data, names, sigma=sigma, seed=seed, progress=progress,
                              cutoff=cutoff, artefact_rms=artefact_rms)
    extra = []
    for name, est in fitted.items():
        extra += fit_warnings(model, name, result["methods"][name], est)
    method_w = [w for m in result["methods"].values() for w in m.get("warnings", [])]
    result["warnings"] = _unique(read_warnings + overview_warnings(overview) + method_w + extra)
    result.update(provenance(command))
    result["data_overview"] = overview
    result["model_parameters"] = model_parameters(model)
    result["model_description"] = model.to_dict()
    if out_dir is not None:
        y = prepare(model, data)
        with atomic_dir(out_dir, protect=[model_path, data_path], overwrite=overwrite) as tmp:
            figures(model, data, fitted, tmp)
            write_npz(tmp / "arrays.npz", fit_arrays(model, y, data.rate, fitted))
            write_json(tmp / "result.json", result)
    return result


def figures(model: Model, data: MarkerData, fitted: dict, out_dir, prefix: str = "",
            truth: dict | None = None) -> list[Path]:
    """The seed paper's figures for a fit: trajectories, posterior history, MAP per step."""
    from skelid import plots

    out_dir = Path(out_dir)
    name = model.parameter_names[0] if model.n_params else ""
    tv = (truth or {}).get(name)
    paths = [plots.trajectories(data, out_dir / f"{prefix}trajectories.png",
                                title=f"{model.name}: marker trajectories")]
    main = fitted.get("paper") or next(iter(fitted.values()))
    gauss = {f"final posterior ({k} method)": (v.posterior_.mean[0], v.posterior_.sd[0])
             for k, v in fitted.items() if v is not main and not hasattr(v.posterior_, "axes")}
    if hasattr(main, "posterior_") and hasattr(main.posterior_, "axes"):
        paths.append(plots.posterior_history(
            main.posterior_, out_dir / f"{prefix}posterior.png", truth=tv, units=model.units,
            title=f"{model.name}: posterior of {name} ({main.name} method)", gaussians=gauss))
    if hasattr(main, "map_path_"):
        extra = {f"most likely value ({k})": v.map_path_ for k, v in fitted.items()
                 if v is not main and hasattr(v, "map_path_")}
        paths.append(plots.map_path(
            main.map_path_, out_dir / f"{prefix}map_per_step.png", truth=tv,
            measured=getattr(main, "measured_", None), name=name, units=model.units,
            title=f"{model.name}: most likely {name} per step", extra=extra))
    return paths


def demo(out_dir, seed: int = 0, n_frames: int = 500, sigma: float = 15.0,
         method_names=None, progress: bool = True, limits=None, overwrite: bool = False) -> dict:
    """Simulate cases A and B with the seed paper's settings, fit, draw, summarise.

    Nothing appears in ``out_dir`` until every figure and ``summary.json`` are complete.
    """
    from tqdm import tqdm

    from skelid.simulate import builtin_model, simulate

    if not (math.isfinite(sigma) and sigma >= 0):
        raise SkelidError(f"--sigma must be a finite number >= 0 (mm), got {sigma}", "e.g. --sigma 15")
    method_names = list(method_names or DEMO_METHODS)
    check_output_dir(out_dir, overwrite)
    for case in ("case-a", "case-b"):
        for n in method_names:
            check_cost(builtin_model(case), n, n_frames, limits)
    summary, drawn = {}, []
    cases = ("case-a", "case-b")
    bar = tqdm(total=len(cases) + 1, desc="demo", unit="step", file=sys.stderr,
               disable=not progress or not sys.stderr.isatty())
    for k, case in enumerate(cases):
        bar.set_postfix_str(case)
        model = builtin_model(case)
        trial = simulate(model, n_frames=n_frames, sigma=sigma,
                         rng=np.random.default_rng([seed, k]))
        res, fitted = fit_file(model, trial.data, method_names, seed=seed, progress=progress)
        key = case.replace("-", "_")
        drawn.append((model, trial, fitted, key))
        summary[key] = {"truth": trial.truth, "sigma_noise": sigma, "frames_total": res["frames_total"],
                        "methods": res["methods"]}
        bar.update(1)
    bar.set_postfix_str("figures")
    with bar, atomic_dir(out_dir, overwrite=overwrite) as tmp:
        for model, trial, fitted, key in drawn:
            figures(model, trial.data, fitted, tmp, prefix=f"{key}_", truth=trial.truth)
        write_json(tmp / "summary.json", summary)
        bar.update(1)
    return summary


def table(summary: dict) -> str:
    """A short text table of a demo or fit summary."""
    rows = []
    cases = summary if "methods" not in summary else {"fit": summary}
    for case, res in cases.items():
        truth = res.get("truth", {})
        for mname, m in res["methods"].items():
            for pname, v in m.items():
                if not isinstance(v, dict) or "map" not in v:
                    continue
                t = truth.get(pname)
                rows.append(
                    f"{case:<8} {mname:<8} {pname:<14} {v['mean']:>9.5g} {v['sd']:>8.3g} "
                    f"[{v['ci95'][0]:8.5g}, {v['ci95'][1]:8.5g}] "
                    f"{'' if t is None else f'{t:8.5g}':>8} {m.get('frames_used', ''):>6}"
                )
    head = (f"{'case':<8} {'method':<8} {'param':<14} {'mean':>9} {'sd':>8} {'95% interval':^22} "
            f"{'truth':>8} {'frames':>6}")
    return "\n".join([head, "-" * len(head), *rows])
