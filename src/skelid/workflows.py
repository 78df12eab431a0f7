"""End-to-end jobs the command line runs: fit a file, run the demo.

They return JSON-ready dicts; figures and files go through :mod:`skelid.plots`
and the atomic writers. No argument parsing here, no maths either.
"""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path

import numpy as np

from skelid.data import MarkerData
from skelid.errors import ModelError, SkelidWarning
from skelid.estimators.base import prepare
from skelid.io.atomic import atomic_write
from skelid.model.description import Model


def methods() -> dict:
    """Estimator classes by method name."""
    from skelid.estimators.marker import MarkerEstimator
    from skelid.estimators.paper import PaperFilter

    return {"paper": PaperFilter, "marker": MarkerEstimator}


DEFAULT_METHOD = "paper"


def make_estimator(name: str, model: Model, sigma: float | None = None,
                   rng: np.random.Generator | None = None):
    table = methods()
    if name not in table:
        raise ModelError(f"unknown method {name!r}", f"use one of: {', '.join(table)}")
    return table[name](model, sigma=sigma, rng=rng)


def fit_file(model: Model, data: MarkerData, method_names, sigma: float | None = None,
             seed: int = 0) -> tuple[dict, dict]:
    """Fit ``model`` to ``data`` with each method.

    Returns
    -------
    result : dict
        ``{"frames_total": F, "methods": {name: summary}}``.
    fitted : dict
        The fitted estimators by name (for figures).
    """
    y = prepare(model, data)
    out = {"model": model.name, "data": data.source, "units": model.units,
           "frames_total": int(y.shape[0]), "methods": {}}
    fitted = {}
    for name in method_names:
        est = make_estimator(name, model, sigma=sigma, rng=np.random.default_rng(seed))
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SkelidWarning)  # recorded in the result instead
            est.fit(y)
        res = est.result()
        res["seconds"] = round(time.perf_counter() - t0, 4)
        out["methods"][name] = res
        fitted[name] = est
    return out, fitted


def write_json(path, obj) -> Path:
    path = Path(path)
    with atomic_write(path) as fh:
        json.dump(obj, fh, indent=2, default=_json_default)
        fh.write("\n")
    return path


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


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
    if hasattr(main, "posterior_") and getattr(main.posterior_, "history", None) is not None \
            and hasattr(main.posterior_, "axes"):
        paths.append(plots.posterior_history(
            main.posterior_, out_dir / f"{prefix}posterior.png", truth=tv, units=model.units,
            title=f"{model.name}: posterior of {name} ({main.name} method)"))
    if hasattr(main, "map_path_"):
        extra = {f"most likely value ({k})": v.map_path_ for k, v in fitted.items()
                 if v is not main and hasattr(v, "map_path_")}
        paths.append(plots.map_path(
            main.map_path_, out_dir / f"{prefix}map_per_step.png", truth=tv,
            measured=getattr(main, "measured_", None), name=name, units=model.units,
            title=f"{model.name}: most likely {name} per step", extra=extra))
    return paths


def demo(out_dir, seed: int = 0, n_frames: int = 500, sigma: float = 15.0,
         method_names=None, progress: bool = True) -> dict:
    """Simulate cases A and B with the seed paper's settings, fit, draw, summarise."""
    from tqdm import tqdm

    from skelid.simulate import builtin_model, simulate

    method_names = list(method_names or methods())
    out_dir = Path(out_dir)
    summary = {}
    cases = ("case-a", "case-b")
    for k, case in enumerate(tqdm(cases, desc="demo", disable=not progress, unit="case")):
        model = builtin_model(case)
        trial = simulate(model, n_frames=n_frames, sigma=sigma,
                         rng=np.random.default_rng([seed, k]))
        res, fitted = fit_file(model, trial.data, method_names, seed=seed)
        key = case.replace("-", "_")
        figures(model, trial.data, fitted, out_dir, prefix=f"{key}_", truth=trial.truth)
        summary[key] = {"truth": trial.truth, "sigma_noise": sigma, "frames_total": res["frames_total"],
                        "methods": res["methods"]}
    write_json(out_dir / "summary.json", summary)
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
                    f"{case:<8} {mname:<8} {pname:<10} {v['mean']:>9.2f} {v['sd']:>7.2f} "
                    f"[{v['ci95'][0]:8.2f}, {v['ci95'][1]:8.2f}] "
                    f"{'' if t is None else f'{t:8.2f}':>8} {m.get('frames_used', ''):>6}"
                )
    head = (f"{'case':<8} {'method':<8} {'param':<10} {'mean':>9} {'sd':>7} {'95% interval':^22} "
            f"{'truth':>8} {'frames':>6}")
    return "\n".join([head, "-" * len(head), *rows])
