"""Is the second-order bias correction still accurate on long trials, where it is many sd?

    python benchmarks/bias_trigger.py --frames 1000 10000 --reps 100 --jobs 2

Fits case A (sigma 15 mm, L2 = 250 mm, i.i.d. noise) with the default estimator and records,
per trial: the second-order correction ``b`` in sd units, its change when evaluated again at
the corrected point (geometry ``theta - b``, poses deconvolved), which bias method the estimator used, the
error and the 95 % interval. The profile bias of a fit with incidental poses does not shrink
with the number of frames while the sd does, so ``|b| / sd`` grows like ``sqrt(frames)``
(about 1 sd at 10^3 frames, 4 sd at 10^4), so the rule "a correction above 1.5 sd goes to the
parametric bootstrap" sends every long trial there. The study says whether the expansion would
have been accurate where it stays put when re-evaluated
(:func:`skelid.estimators.uncertainty.singular.expansion_consistent`): mean error (bias) against the sd,
coverage, for the estimator as it is run.

Results go to ``benchmarks/results/bias_trigger.json`` and ``.md`` (keyed by frames; a re-run
replaces the lengths it ran). ``--reps`` below 100 is a reduced run and is marked so.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"
os.environ.setdefault("SKELID_NUMBA", "wait")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import results_dir, rows_of, write_json  # noqa: E402

RESULTS = results_dir()
Z95 = 1.959964
TRUTH = 250.0


def one_trial(frames: int, rep: int) -> dict:
    """Fit one simulated trial with the default estimator; the bias check's numbers and the error."""
    from skelid.estimators.fit.joint import smoothed_bias
    from skelid.estimators.marker import MarkerEstimator
    from skelid.estimators.uncertainty.singular import deconvolve_poses
    from skelid.simulate import builtin_model, simulate

    model = builtin_model("case-a")
    trial = simulate(model, theta=[TRUTH], sigma=15.0, n_frames=frames, rng=np.random.default_rng([7, frames, rep]))
    c0 = time.process_time()
    est = MarkerEstimator(model, jackknife=False).fit(trial.data)
    cpu = time.process_time() - c0
    f = est.fit_info_
    sd_plain = float(np.sqrt(est.cov_plain_[0, 0]))
    b = est.bias_ if est.bias_method_ == "box" else np.asarray(est.bias_fallback_["box"])
    var = []
    smoothed_bias(model, est.y_, f.theta, f.pose, est.sigma_**2, f.penalty, weights=est.marker_weights_, pose_var=var)
    q_tilde = deconvolve_poses(f.pose, var[0], est.frames_used_)
    b2 = smoothed_bias(model, est.y_, f.theta - b, q_tilde, est.sigma_**2, f.penalty, weights=est.marker_weights_)
    sd = float(est.posterior_.sd[0])
    err = float(est.theta_[0] - TRUTH)
    return {"frames": frames, "rep": rep, "err": err, "sd": sd, "z": err / sd, "covered": bool(abs(err) <= Z95 * sd),
            "profile_err": float(est.theta_profile_[0] - TRUTH), "b_over_sd": float(b[0]) / sd_plain,
            "change_over_sd": float(b2[0] - b[0]) / sd_plain, "method": est.bias_method_, "cpu_s": cpu,
            "n_boot": est.n_boot}


def summarise(trials: list[dict]) -> dict:
    err = np.array([t["err"] for t in trials])
    sd = np.array([t["sd"] for t in trials])
    n = len(trials)
    cov = float(np.mean([t["covered"] for t in trials]))
    return {"frames": trials[0]["frames"], "reps": n, "reduced": n < 100, "bias": float(err.mean()),
            "bias_se": float(err.std(ddof=1) / np.sqrt(n)) if n > 1 else float("nan"),
            "spread": float(err.std(ddof=1)) if n > 1 else float("nan"), "mean_sd": float(sd.mean()),
            "bias_over_sd": float(err.mean() / sd.mean()), "coverage95": cov,
            "coverage_se": float(np.sqrt(cov * (1 - cov) / n)),
            "profile_bias": float(np.mean([t["profile_err"] for t in trials])),
            "b_over_sd": float(np.mean([t["b_over_sd"] for t in trials])),
            "max_abs_change_over_sd": float(np.max(np.abs([t["change_over_sd"] for t in trials]))),
            "bootstrap_fallbacks": int(sum(t["method"] != "box" for t in trials)),
            "old_rule_fires": int(sum(abs(t["b_over_sd"]) > 1.5 for t in trials)),
            "cpu_s_per_fit": float(np.mean([t["cpu_s"] for t in trials])), "load": list(os.getloadavg()),
            "n_boot": trials[0].get("n_boot")}


def write(rows: list[dict]) -> None:
    path = RESULTS / "bias_trigger.json"
    old = rows_of(json.loads(path.read_text())) if path.exists() else []
    keep = [r for r in old if isinstance(r, dict) and r.get("frames") not in {r2["frames"] for r2 in rows}]
    rows = sorted(keep + rows, key=lambda r: r["frames"])
    write_json(path, rows)
    lines = ["# Second-order bias correction on long trials", "",
             "Generated by `python benchmarks/bias_trigger.py`; case A, sigma 15 mm, L2 = 250 mm, i.i.d. noise, the "
             "default estimator (a correction above 1.5 sd goes to the parametric bootstrap at the deconvolved poses: "
             "`n_boot` refits, each with its linear control variate). `b / sd`: mean second-order correction "
             "against the sd; `max change`: largest change of it at the corrected geometry and poses (sd); "
             "`old rule`: trials the rule 'above 1.5 "
             "sd' would have sent to the bootstrap; `fallback`: trials the estimator sent there. A row with reps "
             "< 100 is a reduced run (CPU on a shared machine).", "",
             "| frames | reps | bias (mm) | bias se | bias / sd | spread / mean sd | coverage95 | cov se | b / sd | "
             "max change / sd | old rule | fallback | n_boot | CPU s/fit | load |", "|" + "---|" * 15]
    for r in rows:
        lines.append(f"| {r['frames']} | {r['reps']}{' (reduced)' if r['reduced'] else ''} | {r['bias']:.3f} | "
                     f"{r['bias_se']:.3f} | {r['bias_over_sd']:.2f} | {r['spread'] / r['mean_sd']:.2f} | "
                     f"{r['coverage95']:.2f} | {r['coverage_se']:.3f} | {r['b_over_sd']:.2f} | "
                     f"{r['max_abs_change_over_sd']:.4f} | {r['old_rule_fires']} | {r['bootstrap_fallbacks']} | "
                     f"{r.get('n_boot') or '10 (plain)'} | "
                     f"{r['cpu_s_per_fit']:.1f} | {r['load'][0]:.1f} |")
    (RESULTS / "bias_trigger.md").write_text("\n".join(lines) + "\n")


def _worker_init():
    warnings.simplefilter("ignore")
    from threadpoolctl import threadpool_limits

    threadpool_limits(1, user_api="blas")


def _trial(args):
    return one_trial(*args)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--jobs", type=int, default=1, help="Worker processes (one BLAS thread each).")
    args = ap.parse_args(argv)
    _worker_init()
    rows = []
    pool = None
    if args.jobs > 1:
        import multiprocessing

        pool = multiprocessing.get_context("spawn").Pool(args.jobs, initializer=_worker_init)
    try:
        for F in args.frames:
            trials = []
            work = [(F, rep) for rep in range(args.reps)]
            results = pool.imap(_trial, work) if pool is not None else map(_trial, work)
            for rep, t in enumerate(results):
                trials.append(t)
                print(f"{F} frames, trial {rep}: err {t['err']:+.3f} sd {t['sd']:.3f} b {t['b_over_sd']:.2f} sd, "
                      f"change {t['change_over_sd']:+.4f} sd, {t['method']}, {t['cpu_s']:.1f} s CPU", flush=True)
                if len(trials) % 10 == 0 and len(trials) < args.reps:  # a partial row, marked reduced
                    write(rows + [summarise(trials)])
            rows.append(summarise(trials))
            write(rows)
    finally:
        if pool is not None:
            pool.close()
            pool.join()
    print(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
