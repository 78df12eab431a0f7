"""The marker jackknife's linearisation check on the squat and sit-to-stand trials of addbio-subject4.

Deleting the calcaneus marker leaves the shank length weakly identified; the one-step
replicate then extrapolates the cost's quadratic model far. This recomputes the jackknife
with the current code on the per-trial fits that ``benchmarks/real_calibration.py`` cached
(``--cache``; any cached fit of the trial and mode is taken, whatever code wrote it), and
reports per trial: which replicates were refitted, the cost ratio along them, the shift
of the most influential marker per parameter before (the cached fit's one-step summary)
and now, the jackknife sd, and the plain sd with the jackknife folded in.

Run from the repository root::

    nice -n 10 python benchmarks/jackknife_linearisation.py [--trials squats1 STS1] [--mode pooled]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import pickle  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from skelid.estimators.uncertainty.jackknife import fold, marker_jackknife  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def one_trial(path: Path) -> dict:
    est, _, _ = pickle.load(path.open("rb"))
    f, model = est.fit_, est.model
    fit, used, sigma, w = f.weights.fit, f.frames.used, f.noise.sigma, f.weights.weights
    y = np.where(used[:, None, None], f.screen.y, np.nan)
    c0, t0 = time.process_time(), time.perf_counter()
    jk = marker_jackknife(model, y, fit.theta, fit.pose, fit.penalty, sigma=sigma, weights=w)
    names = model.marker_names
    old = f.cov.jackknife.get("parameters", {})
    out = {"cache": path.name, "jackknife_cpu_s": time.process_time() - c0,
           "jackknife_wall_s": time.perf_counter() - t0, "load_average": os.getloadavg(),
           "not_one_step": {n: s for n, s in zip(names, jk.status, strict=True) if s not in ("one-step", "missing")},
           "cost_ratio_checked": {n: float(r) for n, r in zip(names, jk.ratio, strict=True) if np.isfinite(r)},
           "plain_sd": dict(zip(model.parameter_names, np.sqrt(np.diag(f.cov.plain)).tolist(), strict=True)),
           "reported_sd_before": dict(zip(model.parameter_names, est.posterior_.sd.tolist(), strict=True)),
           "parameters": {}}
    folded = np.sqrt(np.diag(fold(f.cov.plain, jk)[0])) if jk.available else np.full(model.n_params, np.nan)
    for k, p in enumerate(model.parameter_names):
        m = int(np.nanargmax(np.abs(jk.shifts[:, k]))) if np.isfinite(jk.shifts[:, k]).any() else None
        out["parameters"][p] = {
            "before_most_influential": [old.get(p, {}).get("most_influential_marker"), old.get(p, {}).get("shift")],
            "before_jackknife_sd": old.get(p, {}).get("sd"),
            "after_most_influential": None if m is None else [names[m], float(jk.shifts[m, k]), jk.status[m]],
            "after_jackknife_sd": float(np.sqrt(jk.cov[k, k])) if jk.available else None,
            "after_plain_plus_fold_sd": float(folded[k])}
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--cache", default="/tmp/skelid-real-calibration")
    ap.add_argument("--trials", nargs="+", default=["squats1", "STS1"])
    ap.add_argument("--mode", default="pooled", choices=["pooled", "per_marker"])
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "jackknife_linearisation.json"))
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    res = {}
    for t in args.trials:
        paths = sorted(Path(args.cache).glob(f"{t}-maxall-{args.mode}-*.pkl"))
        if not paths:
            print(f"{t}: no cached fit in {args.cache} (run benchmarks/real_calibration.py first)")
            continue
        res[t] = one_trial(paths[-1])
        print(t, json.dumps(res[t]["parameters"]), flush=True)
        Path(args.out).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
