"""Where the error beyond the Cramér-Rao bound comes from: an i.i.d. cell of the accuracy study, trial by trial.

    python benchmarks/bias_budget.py --case case-a --sigma 15 --truth 250 --reps 100 --jobs 2

Each trial of the accuracy study's cell (the same seeds as ``benchmarks/accuracy.py``) is fitted with
the default estimator, and its error is split as

.. math:: \\hat\\theta - \\theta = l + d, \\qquad l = S^{-1} \\textstyle\\sum_t K_t^\\top e_t,

``l`` the exact first-order term in the trial's own noise ``e`` at the truth (every pose free; mean
exactly zero, variance exactly crlb^2), ``d`` the rest: bias, the spread of the higher-order terms, and
their correlation with ``l``. Then

.. math:: \\mathrm{MSE} = \\mathrm{crlb}^2 + \\mathrm{Var}(d) + 2\\,\\mathrm{Cov}(l, d) + \\bar d^{\\,2}

with every term but the first from the trials (their Monte Carlo error is far below that of the plain
mean square, whose main part, ``l``, is known). The same split is made for the profile estimate
(no correction), for it less the second-order bias at the estimate (what the expansion path
subtracts), less the second-order bias at the truth (true geometry and poses: an oracle correction
that carries no noise of its own), and for the estimator as run (expansion or bootstrap). A
correction that only removes a mean cannot take away ``Var(d)`` or ``Cov(l, d)``: if the oracle's
RMSE misses the target, the bias stage cannot meet it. The noise-free refit with the fit's own
motion model gives the motion model's (regularisation) bias. ``top 3``: the share of
``MSE - crlb^2`` that the three trials with the largest ``|d|`` carry (a heavy tail, not a shift).

Results: ``benchmarks/results/bias_budget.json`` (per cell) and ``.md``.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
CASES = ("case-a", "case-b")


def one_trial(args) -> dict:
    """One trial of the accuracy study's i.i.d. cell: the error's parts (first parameter)."""
    case, sigma, truth, rep = args
    warnings.simplefilter("ignore")
    from skelid.estimators.fit.joint import joint_fit, smoothed_bias
    from skelid.estimators.fit.likelihood import crlb_sd, efficient_information, frame_terms
    from skelid.estimators.marker import MarkerEstimator
    from skelid.estimators.uncertainty.bootstrap import linear_response
    from skelid.simulate import builtin_model, simulate

    model = builtin_model(case)
    seed = [CASES.index(case), int(sigma), int(truth), 0, rep]  # accuracy.py's seeds for noise 'iid'
    trial = simulate(model, theta=[truth], n_frames=500, sigma=sigma, noise="iid", sta_amplitude=10.0,
                     rng=np.random.default_rng(seed))
    _, Jq, Jt = frame_terms(model, trial.theta, trial.pose, trial.clean)
    crlb = float(crlb_sd(efficient_information(Jq, Jt, sigma))[0])
    noise = (trial.data.positions - trial.clean)[None]
    lin = float(linear_response(model, trial.clean, trial.theta, trial.pose, noise).theta[0, 0])
    c0 = time.process_time()
    est = MarkerEstimator(model, rng=rep).fit(trial.data)
    cpu = time.process_time() - c0
    f = est.fit_info_
    b_hat = est.bias_ if est.bias_method_ == "box" else np.asarray(est.bias_fallback_["box"])
    b_true = smoothed_bias(model, trial.clean, trial.theta, trial.pose, sigma**2, f.penalty)
    clean = joint_fit(model, trial.clean, trial.theta, trial.pose, n_iter=100, penalty=f.penalty, summary=False)
    return {"rep": rep, "crlb": crlb, "linear": lin, "profile": float(f.theta[0] - truth),
            "final": float(est.theta_[0] - truth), "b_estimate": float(b_hat[0]), "b_truth": float(b_true[0]),
            "regularisation": float(clean.theta[0] - truth), "method": est.bias_method_,
            "covered": bool(abs(est.theta_[0] - truth) <= 1.959964 * est.posterior_.sd[0]), "cpu_s": cpu}


def budget(err, lin, var_lin: float) -> dict:
    """``MSE = var_lin + Var(d) + 2 Cov(l, d) + mean(d)^2`` for ``d = err - lin`` (sample moments)."""
    err, lin = np.asarray(err, float), np.asarray(lin, float)
    d = err - lin
    c = np.cov(lin, d)
    mse = var_lin + c[1, 1] + 2.0 * c[0, 1] + d.mean() ** 2
    excess = np.maximum(mse - var_lin, 1e-300)
    n = len(d)
    top = np.argsort(-np.abs(d - d.mean()))[:3]
    keep = np.ones(n, bool)
    keep[top] = False
    ck = np.cov(lin[keep], d[keep])
    mse_k = var_lin + ck[1, 1] + 2.0 * ck[0, 1] + d[keep].mean() ** 2
    return {"bias": float(d.mean()), "bias_se": float(d.std(ddof=1) / np.sqrt(n)), "var_d": float(c[1, 1]),
            "two_cov": float(2.0 * c[0, 1]), "slope": float(c[0, 1] / var_lin), "rmse": float(np.sqrt(mse)),
            "rmse_without_top3": float(np.sqrt(mse_k)), "top3_share": float(1.0 - (mse_k - var_lin) / excess)}


def summarise(case, sigma, truth, trials) -> dict:
    k = {n: np.array([t[n] for t in trials]) for n in trials[0] if n not in ("method", "covered")}
    var_lin = float(np.mean(k["crlb"] ** 2))
    crlb = float(np.sqrt(var_lin))
    rows = {"none": k["profile"], "second order at the estimate": k["profile"] - k["b_estimate"],
            "second order at the truth (oracle)": k["profile"] - k["b_truth"], "as run": k["final"]}
    methods = [t["method"] for t in trials]
    return {"case": case, "sigma": sigma, "truth": truth, "reps": len(trials), "crlb": crlb,
            "linear_mean": float(k["linear"].mean()), "regularisation": float(k["regularisation"].mean()),
            "coverage95": float(np.mean([t["covered"] for t in trials])),
            "bias_methods": {m: methods.count(m) for m in sorted(set(methods))},
            "cpu_s_per_fit": float(k["cpu_s"].mean()),
            "corrections": {name: budget(err, k["linear"], var_lin) for name, err in rows.items()},
            "trials": trials}


def write(cells: dict) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "bias_budget.json").write_text(json.dumps(cells, indent=1))
    with open(RESULTS / "bias_budget.md", "w") as fh:
        fh.write("# Error budget of the i.i.d. cells\n\nGenerated by `python benchmarks/bias_budget.py` (see its "
                 "docstring). Per trial, error = l + d with l the exact first-order term in the trial's noise "
                 "(variance crlb^2); MSE = crlb^2 + Var(d) + 2 Cov(l, d) + bias^2, all in crlb units. `slope`: "
                 "Cov(l, d) / crlb^2, the extra response to the noise beyond first order. `top 3`: the share of "
                 "the excess MSE the three trials with the largest |d| carry, and the RMSE without them. "
                 "`regularisation`: mean error of the noise-free refit with the fit's own motion model. "
                 "Targets: |bias| <= 0.2, rmse <= 1.1.\n\n| case | sigma | truth | reps | correction | bias (se) | "
                 "Var(d) | 2 Cov(l, d) | slope | rmse | top 3 share | rmse without top 3 |\n|" + "---|" * 12 + "\n")
        for c in cells.values():
            s = c["crlb"]
            for name, b in c["corrections"].items():
                fh.write(f"| {c['case']} | {c['sigma']:g} | {c['truth']:g} | {c['reps']} | {name} | "
                         f"{b['bias'] / s:.3f} ({b['bias_se'] / s:.3f}) | {b['var_d'] / s**2:.3f} | "
                         f"{b['two_cov'] / s**2:.3f} | {b['slope']:.3f} | {b['rmse'] / s:.3f} | "
                         f"{b['top3_share']:.2f} | {b['rmse_without_top3'] / s:.3f} |\n")
        fh.write("\n| case | sigma | truth | reps | crlb (mm) | mean l (crlb) | regularisation (crlb) | coverage95 | "
                 "bias methods | CPU s/fit |\n|" + "---|" * 10 + "\n")
        for c in cells.values():
            fh.write(f"| {c['case']} | {c['sigma']:g} | {c['truth']:g} | {c['reps']} | {c['crlb']:.3f} | "
                     f"{c['linear_mean'] / c['crlb']:.3f} | {c['regularisation'] / c['crlb']:.4f} | "
                     f"{c['coverage95']:.2f} | {c['bias_methods']} | {c['cpu_s_per_fit']:.2f} |\n")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="case-a", choices=CASES)
    ap.add_argument("--sigma", type=float, default=15.0)
    ap.add_argument("--truth", type=float, default=250.0)
    ap.add_argument("--reps", type=int, default=100)
    ap.add_argument("--jobs", type=int, default=2)
    a = ap.parse_args()
    tasks = [(a.case, a.sigma, a.truth, r) for r in range(a.reps)]
    if a.jobs > 1:
        with ProcessPoolExecutor(a.jobs) as pool:
            trials = list(pool.map(one_trial, tasks))
    else:
        trials = [one_trial(t) for t in tasks]
    path = RESULTS / "bias_budget.json"
    cells = json.loads(path.read_text()) if path.exists() else {}
    cells[f"{a.case} {a.sigma:g} {a.truth:g}"] = summarise(a.case, a.sigma, a.truth, trials)
    write(cells)
    print((RESULTS / "bias_budget.md").read_text())


if __name__ == "__main__":
    main()
