"""The demo: simulate the seed method's cases A and B, fit them, draw the figures, summarise."""

from __future__ import annotations

import math
import sys

import numpy as np

from skelid.errors import SkelidError
from skelid.io.atomic import atomic_dir, check_output_dir
from skelid.io.results import result_to_dict, write_json
from skelid.plots import fit_figures as figures
from skelid.result import FitRun
from skelid.workflows import check_cost, fit_file

DEMO_METHODS = ("paper", "marker")


def demo(out_dir, seed: int = 0, n_frames: int = 500, sigma: float = 15.0,
         method_names=None, progress: bool = True, limits=None, overwrite: bool = False) -> dict:
    """Simulate cases A and B with the seed paper's settings, fit, draw, summarise.

    Nothing appears in ``out_dir`` until every figure and ``summary.json`` are complete.

    Returns
    -------
    dict of str to FitRun
        ``{"case_a": run, "case_b": run}``; each context holds the ``truth``.
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
    runs, drawn = {}, []
    cases = ("case-a", "case-b")
    bar = tqdm(total=len(cases) + 1, desc="demo", unit="step", file=sys.stderr,
               disable=not progress or not sys.stderr.isatty())
    for k, case in enumerate(cases):
        bar.set_postfix_str(case)
        model = builtin_model(case)
        trial = simulate(model, n_frames=n_frames, sigma=sigma,
                         rng=np.random.default_rng([seed, k]))
        results, fitted = fit_file(model, trial.data, method_names, seed=seed, progress=progress)
        key = case.replace("-", "_")
        drawn.append((model, trial, fitted, key))
        runs[key] = FitRun(results, {"model": model.name, "units": model.units,
                                     "frames_total": trial.data.n_frames, "truth": trial.truth,
                                     "sigma_noise": sigma})
        bar.update(1)
    bar.set_postfix_str("figures")
    with bar, atomic_dir(out_dir, overwrite=overwrite) as tmp:
        for model, trial, fitted, key in drawn:
            figures(model, trial.data, fitted, tmp, prefix=f"{key}_", truth=trial.truth)
        write_json(tmp / "summary.json", summary_document(runs))
        bar.update(1)
    return runs


def summary_document(runs) -> dict:
    """``summary.json`` of the demo: per case, the run's context and each method's result
    (as in ``result.json``, without arrays; see ``docs/result-format.md``)."""
    return {case: {**run.context, "results": {m: result_to_dict(r.replace(arrays={}))
                                              for m, r in run.results.items()}}
            for case, run in runs.items()}
