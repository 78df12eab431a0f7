"""End-to-end jobs the command line runs: fit a file, run the demo.

They return JSON-ready dicts; figures and files go through :mod:`skelid.plots`
and the atomic writers. No argument parsing here, no maths either: only the
checks that turn a user's mistake into a one-line :class:`~skelid.errors.SkelidError`
before it becomes a traceback, and the warnings a user should read.

An output folder (``fit --out DIR``, ``demo --out DIR``) is built in a hidden
temporary sibling and moved in when complete (:func:`skelid.io.atomic.atomic_dir`).
``fit`` writes into it:

``result.json`` and ``arrays.npz``
    The run (:class:`~skelid.result.FitRun`: one :class:`~skelid.result.FitResult` per
    method, with its posterior arrays) written by :func:`skelid.io.results.write_run`;
    the context holds the model, the data file, the data overview, the priors, the model
    description (for the report's view of the fitted body) and the provenance.
``*.png``
    The seed paper's figures (:func:`skelid.plots.fit_figures`).

The checks live in :mod:`skelid.checks`, the warning policy in :mod:`skelid.diagnostics`,
the estimators by name in :mod:`skelid.registry`, reading and writing in :mod:`skelid.io.results`.
"""

from __future__ import annotations

import math
import sys
import time
import warnings

import numpy as np

from skelid import checks, registry, resources
from skelid.checks import check_input_file, check_units, data_overview
from skelid.data import MarkerData, unit_scale
from skelid.diagnostics import collect_warnings, fit_warnings, lag1_autocorrelation, overview_warnings, unique_warnings
from skelid.errors import SkelidError, SkelidWarning
from skelid.estimators.base import prepare
from skelid.io.atomic import atomic_dir, check_output_dir
from skelid.io.results import posterior_arrays, write_json, write_run
from skelid.model.description import Model
from skelid.plots import fit_figures as figures
from skelid.provenance import model_parameters, provenance, run_context, versions
from skelid.result import FitResult, FitRun, Warning

__all__ = ["methods", "make_estimator", "check_options", "fit_options", "fit_file", "run_fit", "run_arrays", "table",
           "figures",
           "check_input_file", "check_units", "data_overview", "lag1_autocorrelation", "posterior_arrays",
           "versions", "write_json", "write_run", "run_context", "unique_warnings", "model_parameters", "provenance",
           "collect_warnings"]


def methods() -> dict:
    """Estimator classes by method name (see :mod:`skelid.registry`)."""
    return registry.estimators()


def check_options(model: Model, sigma: float | None = None, cutoff: float | None = None,
                  artefact_rms: float | None = None, placement_sd: float | None = None) -> None:
    """Refuse an unusable ``--sigma``, ``--cutoff``, ``--artefact-rms`` or ``--placement-sd`` for ``model``
    in one line."""
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
    if artefact_rms is not None and not (math.isfinite(artefact_rms) and artefact_rms >= 0):
        raise SkelidError(f"--artefact-rms must be a distance >= 0 {model.units}, got {artefact_rms}",
                          f"give the soft-tissue artefact's rms displacement in {model.units}, or 0 for none")
    if cutoff is not None and not (math.isfinite(cutoff) and cutoff >= 0):
        raise SkelidError(f"--cutoff must be a frequency >= 0 Hz, got {cutoff}",
                          "use 0 for no motion model, or e.g. --cutoff 6")
    if placement_sd is not None and not (math.isfinite(placement_sd) and placement_sd >= 0):
        raise SkelidError(f"--placement-sd must be a distance >= 0 {model.units}, got {placement_sd}",
                          f"give the sd of each marker's placement on its segment in {model.units}, e.g. "
                          f"{5 * unit_scale('mm', model.units):g}, or 0 for none")


def fit_options(sigma: float | None = None, cutoff: float | None = None, artefact_rms: float | None = None,
                noise: str | None = "pooled") -> dict:
    """The ``skelid fit`` options given, as ``{option: setting value}``; options at their default are left out.

    ``--cutoff 0`` is no motion model (the setting None), ``--artefact-rms 0`` no artefact term (the
    default), ``--noise per-marker`` the setting ``'per_marker'``. :func:`skelid.registry.settings_from_options`
    turns them into an estimator's settings.

    Examples
    --------
    >>> fit_options(cutoff=0, artefact_rms=20.0, noise="per-marker")
    {'cutoff': None, 'artefact_rms': 20.0, 'noise': 'per_marker'}
    """
    out: dict = {}
    if sigma is not None:
        out["sigma"] = sigma
    if cutoff is not None:
        out["cutoff"] = cutoff or None
    if artefact_rms:
        out["artefact_rms"] = artefact_rms
    if noise not in (None, "pooled"):
        out["noise"] = str(noise).replace("-", "_")
    return out


def make_estimator(name: str, model: Model, sigma: float | None = None,
                   rng: np.random.Generator | None = None, cutoff: float | None = None,
                   artefact_rms: float | None = None, placement_sd: float | None = None):
    """Estimator ``name`` with the command-line options it declares; a bad option is one line."""
    registry.estimator_class(name)
    check_options(model, sigma, cutoff, artefact_rms, placement_sd)
    for option, value in (("artefact_rms", artefact_rms), ("placement_sd", placement_sd)):
        if value and option not in registry.cli_settings(name).values():
            flag = "--" + option.replace("_", "-")
            raise SkelidError(f"{flag} is not available with --method {name}: its posterior does not come "
                              f"from the joint fit the {option.split('_')[0]} term is computed from",
                              f"use --method marker or marker-smc with {flag}")
    options = {"sigma": sigma, "artefact_rms": artefact_rms or None, "cutoff": cutoff or None,
               "placement_sd": placement_sd}
    no_motion = {"cutoff": None} if cutoff == 0 and "cutoff" in registry.cli_settings(name) else {}
    return registry.make_estimator(name, model, options, rng=rng, **no_motion)


def check_cost(model: Model, method: str, n_frames: int, limits=None, about: bool = False):
    """Refuse a fit whose estimated memory or time exceeds ``limits`` (see :mod:`skelid.resources`).

    Returns the estimate (:class:`skelid.resources.Cost`).
    """
    resources.check_grid(model, method)
    frames = "" if n_frames <= 1 else f" of {'about ' if about else ''}{n_frames} frames"
    return resources.check(resources.fit_cost(model, method, n_frames), limits, f"the {method} fit{frames}")


# --------------------------------------------------------------------------- fitting
def _progress_bar(total: int, desc: str, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="frame", leave=False, file=sys.stderr,
                disable=not enabled or not sys.stderr.isatty(), mininterval=0.25)


def method_result(model: Model, est, seconds: float | None = None) -> FitResult:
    """The typed result of a fitted estimator as ``skelid fit`` writes it.

    The estimator's own :class:`~skelid.result.FitResult`, with the warnings of
    :func:`skelid.diagnostics.fit_warnings` added (each once), its posterior as
    arrays (:func:`skelid.io.results.posterior_arrays`) and the seconds it took.

    Raises
    ------
    FloatingPointError
        The method returned a non-finite estimate (a bug, said loudly rather than written).
    """
    r = est.result()
    for p in r.parameters.values():
        if not all(math.isfinite(x) for x in (p.map, p.mean, *p.interval)):
            raise FloatingPointError(f"the {r.method} method returned non-finite estimates for {p.name}: {p}")
    warns = unique_warnings([*r.warnings, *fit_warnings(model, r, est)])
    prov = dict(r.provenance) if seconds is None else {**r.provenance, "seconds": round(seconds, 4)}
    return r.replace(warnings=warns, arrays={**posterior_arrays(est), **r.arrays}, provenance=prov)


def fit_file(model: Model, data: MarkerData, method_names, sigma: float | None = None,
             seed: int = 0, progress: bool = False, cutoff: float | None = None,
             artefact_rms: float | None = None, placement_sd: float | None = None
             ) -> tuple[dict[str, FitResult], dict]:
    """Fit ``model`` to ``data`` with each method.

    Returns
    -------
    results : dict of str to FitResult
        By method name (see :func:`method_result`).
    fitted : dict
        The fitted estimators by name (for figures).
    """
    estimators = {name: make_estimator(name, model, sigma=sigma, rng=np.random.default_rng(seed),
                                       cutoff=cutoff, artefact_rms=artefact_rms, placement_sd=placement_sd)
                  for name in method_names}  # unknown methods fail before any work
    n_frames = data.n_frames
    results, fitted = {}, {}
    for name, est in estimators.items():
        t0 = time.perf_counter()
        bar = _progress_bar(n_frames, f"fit {name}", progress)
        with bar, warnings.catch_warnings():
            warnings.simplefilter("ignore", SkelidWarning)  # recorded in the result instead
            est.fit(data, progress=bar.update)
        results[name] = method_result(model, est, time.perf_counter() - t0)
        fitted[name] = est
    return results, fitted


def run_arrays(model: Model, data: MarkerData) -> dict[str, np.ndarray]:
    """The arrays every method of a run shares: the model's markers ``(F, M, D)`` in model units,
    their names, the rate and the units."""
    return {"markers": np.asarray(prepare(model, data), float),
            "marker_names": np.array(model.marker_names, dtype=str),
            "rate": np.array(float(data.rate)), "units": np.array(model.units)}


def run_fit(model_path, data_path, method_names=(), sigma: float | None = None, seed: int = 0,
            out_dir=None, command=None, progress: bool = False, cutoff: float | None = None,
            artefact_rms: float | None = None, limits=None, overwrite: bool = False,
            placement_sd: float | None = None) -> FitRun:
    """Everything ``skelid fit`` does: check, read, fit, warn, write ``out_dir``.

    An existing ``out_dir`` is refused unless ``overwrite``, which replaces it whole.

    ``limits`` (:class:`skelid.resources.Limits`, default from the environment)
    bounds the memory and time the fit is estimated to need: beyond them it is
    refused before reading or fitting.

    Returns
    -------
    FitRun
        One result per method; the run's warnings (reading the data, its gaps, every
        method's), each once. ``out_dir`` receives it through :func:`skelid.io.results.write_run`.
    """
    from skelid.io import read_markers
    from skelid.simulate import BUILTIN_MODELS, resolve_model

    if out_dir is not None:
        check_output_dir(out_dir, overwrite)
    if str(model_path).lower().replace("_", "-") not in BUILTIN_MODELS:
        check_input_file(model_path, "model file")
    model = resolve_model(model_path)
    check_input_file(data_path, "data file")
    names = list(method_names) or [registry.DEFAULT_METHOD]
    for n in names:
        # an unknown method or a bad setting fails before reading
        make_estimator(n, model, sigma, cutoff=cutoff, artefact_rms=artefact_rms, placement_sd=placement_sd)
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
    results, fitted = fit_file(model, data, names, sigma=sigma, seed=seed, progress=progress,
                               cutoff=cutoff, artefact_rms=artefact_rms, placement_sd=placement_sd)
    warns = [*(Warning("reading", w) for w in read_warnings),
             *(Warning("marker-gaps", w) for w in overview_warnings(overview)),
             *(w for r in results.values() for w in r.warnings)]
    run = FitRun(results, run_context(model, data.source, data.n_frames, command, data_overview=overview),
                 unique_warnings(warns), run_arrays(model, data))
    if out_dir is not None:
        with atomic_dir(out_dir, protect=[model_path, data_path], overwrite=overwrite) as tmp:
            figures(model, data, fitted, tmp)
            write_run(tmp, run)
    return run


def table(runs) -> str:
    """A short text table of a fit (a :class:`FitRun`) or of the demo (``{case: FitRun}``)."""
    rows = []
    cases = {"fit": runs} if isinstance(runs, FitRun) else runs
    for case, run in cases.items():
        truth = run.context.get("truth") or {}
        for mname, r in run.results.items():
            used = "" if r.frames is None else r.frames.used
            for pname, p in r.parameters.items():
                t = truth.get(pname)
                rows.append(
                    f"{case:<8} {mname:<8} {pname:<14} {p.mean:>9.5g} {p.sd:>8.3g} "
                    f"[{p.interval[0]:8.5g}, {p.interval[1]:8.5g}] "
                    f"{'' if t is None else f'{t:8.5g}':>8} {used:>6}"
                )
    head = (f"{'case':<8} {'method':<8} {'param':<14} {'mean':>9} {'sd':>8} {'95% interval':^22} "
            f"{'truth':>8} {'frames':>6}")
    return "\n".join([head, "-" * len(head), *rows])
