"""Monte Carlo accuracy study: bias, spread, RMSE against the Cramér-Rao bound, coverage.

Cells: cases A and B x sigma in {5, 15} mm x true L2 near each end and in the
middle of the prior interval x i.i.d. and soft-tissue-artefact noise; 500
frames. Methods:

* ``paper``   the seed method (per-frame Newton-Raphson + grid Bayes filter);
* ``profile`` joint least squares over L2 and every pose, no motion model, no correction;
* ``laplace`` grid filter with the Laplace-marginal likelihood (poses integrated out);
* ``final``   the default ``marker`` estimator (motion model, noise level estimated);
* cells ``straight`` and ``folded`` (``--noises straight folded``): i.i.d. noise with
  every revolute joint kept within 0-25 or 150-172 degrees, near the poses where
  the markers across a joint line up (the second-order bias expansion is least
  accurate there);
* ``final-artefact`` the same with the soft-tissue artefact's size stated
  (``artefact_rms``: the simulator's expected rms displacement of a marker
  coordinate, :func:`skelid.simulate.sta_rms`); soft-tissue cells only.

``crlb`` is the Cramér-Rao bound with every pose unknown, at the true poses and
the true sigma. Results are written cell by cell to
``benchmarks/results/accuracy.json`` and ``accuracy.md``; a re-run skips the
cells already there (``--fresh`` starts over).

    python benchmarks/accuracy.py --reps 100 --jobs 2
    python benchmarks/accuracy.py --frames-study --reps 20
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
CASES = ("case-a", "case-b")
SIGMAS = (5.0, 15.0)
TRUTHS = (210.0, 250.0, 290.0)
NOISES = ("iid", "sta")
#: i.i.d. noise with every revolute joint kept near a singular pose (markers across it nearly in line)
POSTURES = {"straight": (0.0, 25.0), "folded": (150.0, 172.0)}  # degrees
METHODS = ("paper", "profile", "laplace", "final")
EXTRA_METHODS = ("final-artefact",)


def one_trial(args):
    """Fit every method to one simulated trial; returns estimates, intervals, bound."""
    case, sigma, truth, noise, rep, n_frames, methods = args
    warnings.simplefilter("ignore")
    from skelid.errors import SkelidError
    from skelid.estimators.grid import MarkerGridFilter
    from skelid.estimators.likelihood import crlb_sd, efficient_information, frame_terms
    from skelid.estimators.marker import MarkerEstimator
    from skelid.estimators.paper import PaperFilter
    from skelid.simulate import builtin_model, simulate, sta_rms

    model = builtin_model(case)
    seed = [CASES.index(case), int(sigma), int(truth), (NOISES + tuple(POSTURES)).index(noise), rep]
    if noise in POSTURES:
        trial = singular_trial(model, truth, n_frames, sigma, POSTURES[noise], np.random.default_rng(seed))
    else:
        trial = simulate(model, theta=[truth], n_frames=n_frames, sigma=sigma, noise=noise,
                         sta_amplitude=10.0, rng=np.random.default_rng(seed))
    _, Jq, Jt = frame_terms(model, trial.theta, trial.pose, trial.clean)
    bound = float(crlb_sd(efficient_information(Jq, Jt, sigma))[0])
    out = {"crlb": bound}
    centre = float(model.theta_center[0])
    for name in methods:
        t0 = time.perf_counter()
        try:
            if name == "paper":
                est = PaperFilter(model).fit(trial.data)
                post, dropped = est.posterior_, int((~est.frames_used_).sum())
            elif name == "profile":
                est = MarkerEstimator(model, cutoff=None, bias_correction="none", robust="never")
                est.fit(trial.data)
                post, dropped = est.posterior_, int((~est.frames_used_).sum())
                centre = float(est.theta_[0])
            elif name == "laplace":
                half = 8 * max(bound, 0.5)
                axes = (np.linspace(centre - half, centre + half, 41),) if "profile" in out \
                    and "est" in out["profile"] else None  # no profile estimate: the whole prior grid
                est = MarkerGridFilter(model, axes=axes, likelihood="laplace").fit(trial.data)
                post, dropped = est.posterior_, int((~est.frames_used_).sum())
            elif name == "final-artefact":
                rms = sta_rms(model, 10.0) if noise == "sta" else 0.0
                est = MarkerEstimator(model, artefact_rms=rms or None).fit(trial.data)
                post, dropped = est.posterior_, int((~est.frames_used_).sum())
            else:
                est = MarkerEstimator(model).fit(trial.data)
                post, dropped = est.posterior_, int((~est.frames_used_).sum())
            lo, hi = post.credible_interval(0.95)[0]
            out[name] = {"est": float(post.mean[0]), "lo": float(lo), "hi": float(hi),
                         "dropped": dropped, "seconds": time.perf_counter() - t0}
        except SkelidError as exc:
            out[name] = {"error": exc.one_line(), "dropped": n_frames}
    return out


def singular_trial(model, truth, n_frames, sigma, degrees, rng):
    """A trial whose revolute joints stay within ``degrees`` (near the straight or folded pose)."""
    from skelid.data import MarkerData
    from skelid.model.kinematics import marker_positions
    from skelid.simulate import Trial, simulate_motion

    pose = simulate_motion(model, n_frames, 100.0, rng)
    lo, hi = np.radians(degrees)
    for k, d in enumerate(model.dofs):
        if d.kind == "R" and model.segments[d.segment].joint.type in ("revolute", "hinge"):
            u = pose[:, k] - pose[:, k].min()
            pose[:, k] = lo + (hi - lo) * u / max(float(np.ptp(pose[:, k])), 1e-12)
    theta = np.array([truth], float)
    clean = marker_positions(model, theta, pose)
    noisy = clean + rng.normal(0.0, sigma, size=clean.shape)
    return Trial(model, MarkerData(noisy, model.marker_names, 100.0, model.units, source="simulated"),
                 theta, pose, clean)


def summarise(case, sigma, truth, noise, trials, methods):
    rows = []
    bound = float(np.sqrt(np.mean([t["crlb"] ** 2 for t in trials])))
    for name in methods:
        ok = [t[name] for t in trials if "est" in t[name]]
        err = np.array([o["est"] for o in ok]) - truth
        n = len(err)
        cover = np.mean([o["lo"] <= truth <= o["hi"] for o in ok]) if n else float("nan")
        rmse = float(np.sqrt(np.mean(err**2))) if n else float("nan")
        rows.append({
            "case": case, "sigma": sigma, "truth": truth, "noise": noise, "method": name,
            "reps": n, "failed": len(trials) - n,
            "bias": float(err.mean()) if n else float("nan"),
            "bias_se": float(err.std(ddof=1) / np.sqrt(n)) if n > 1 else float("nan"),
            "sd": float(err.std(ddof=1)) if n > 1 else float("nan"),
            "rmse": rmse, "crlb": bound, "rmse_over_crlb": rmse / bound,
            "coverage95": float(cover),
            "frames_dropped": float(np.mean([t[name]["dropped"] for t in trials])),
            "seconds_per_fit": float(np.mean([o["seconds"] for o in ok])) if n else float("nan"),
        })
    return rows


def write(rows):
    order = {m: k for k, m in enumerate(METHODS + EXTRA_METHODS)}
    rows = sorted(rows, key=lambda r: (r["case"], r["noise"], r["sigma"], r["truth"], order.get(r["method"], 99)))
    RESULTS.mkdir(parents=True, exist_ok=True)
    from skelid.io.atomic import atomic_write

    with atomic_write(RESULTS / "accuracy.json") as fh:
        json.dump(rows, fh, indent=1)
    head = ("| case | sigma | truth | noise | method | reps | bias | bias_se | sd | rmse | crlb | "
            "rmse/crlb | coverage95 | frames dropped | s/fit |")
    lines = [head, "|" + "---|" * 15]
    for r in rows:
        lines.append(
            f"| {r['case']} | {r['sigma']:g} | {r['truth']:g} | {r['noise']} | {r['method']} | {r['reps']} | "
            f"{r['bias']:.2f} | {r['bias_se']:.2f} | {r['sd']:.2f} | {r['rmse']:.2f} | {r['crlb']:.2f} | "
            f"{r['rmse_over_crlb']:.2f} | {r['coverage95']:.2f} | {r['frames_dropped']:.0f} | "
            f"{r['seconds_per_fit']:.2f} |")
    with atomic_write(RESULTS / "accuracy.md") as fh:
        fh.write("# Accuracy study\n\nGenerated by `python benchmarks/accuracy.py`; lengths in mm. "
                 "`crlb`: Cramér-Rao bound with every pose unknown, at the true poses.\n\n")
        fh.write("\n".join(lines) + "\n")


def frames_study(reps, jobs, frames=(100, 300, 1000, 3000, 5000)):
    """RMSE against the number of frames (case A, sigma 15, i.i.d.), with the bound."""
    tasks = [("case-a", 15.0, 250.0, "iid", r, F, ("paper", "profile", "final"))
             for F in frames for r in range(reps)]
    with ProcessPoolExecutor(jobs) as pool:
        res = list(pool.map(one_trial, tasks))
    table = {}
    for (_, _, _, _, _, F, _), r in zip(tasks, res, strict=True):
        table.setdefault(F, []).append(r)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    out = {}
    for name in ("paper", "profile", "final"):
        rm = [np.sqrt(np.mean([(t[name]["est"] - 250.0) ** 2 for t in table[F] if "est" in t[name]]))
              for F in frames]
        out[name] = rm
        ax.loglog(frames, rm, "o-", label=name)
    bound = [np.sqrt(np.mean([t["crlb"] ** 2 for t in table[F]])) for F in frames]
    out["crlb"] = bound
    ax.loglog(frames, bound, "k--", label="Cramér-Rao bound (poses free)")
    ax.set_xlabel("frames")
    ax.set_ylabel("RMSE of L2 [mm]")
    ax.set_title(f"case A, sigma 15 mm, {reps} trials per point: a plateau is bias")
    ax.legend()
    RESULTS.mkdir(parents=True, exist_ok=True)
    fig.savefig(RESULTS / "rmse_vs_frames.png", dpi=120, bbox_inches="tight")
    (RESULTS / "rmse_vs_frames.json").write_text(json.dumps({"frames": list(frames), **out}, indent=1))
    print(json.dumps({"frames": list(frames), **out}, indent=1))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=100)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--frames", type=int, default=500)
    ap.add_argument("--cases", nargs="*", default=list(CASES))
    ap.add_argument("--sigmas", nargs="*", type=float, default=list(SIGMAS))
    ap.add_argument("--noises", nargs="*", default=list(NOISES), choices=NOISES + tuple(POSTURES),
                    help="'straight' and 'folded': i.i.d. noise near a singular pose")
    ap.add_argument("--truths", nargs="*", type=float, default=list(TRUTHS))
    ap.add_argument("--methods", nargs="*", default=list(METHODS), choices=METHODS + EXTRA_METHODS)
    ap.add_argument("--fresh", action="store_true", help="ignore results already written")
    ap.add_argument("--frames-study", action="store_true")
    a = ap.parse_args()
    if a.frames_study:
        frames_study(a.reps, a.jobs)
        return
    path = RESULTS / "accuracy.json"
    rows = [] if a.fresh or not path.exists() else json.loads(path.read_text())
    done = {(r["case"], r["sigma"], r["truth"], r["noise"], r["method"]) for r in rows}
    for case in a.cases:
        for sigma in a.sigmas:
            for noise in a.noises:
                for truth in a.truths:
                    todo = tuple(m for m in a.methods if (case, sigma, truth, noise, m) not in done)
                    if not todo:
                        continue
                    t0 = time.time()
                    tasks = [(case, sigma, truth, noise, r, a.frames, todo) for r in range(a.reps)]
                    with ProcessPoolExecutor(a.jobs) as pool:
                        trials = list(pool.map(one_trial, tasks))
                    cell = summarise(case, sigma, truth, noise, trials, todo)
                    rows.extend(cell)
                    write(rows)
                    for r in cell:
                        print(f"{case} s={sigma:g} L2={truth:g} {noise:<3} {r['method']:<8} "
                              f"bias {r['bias']:7.2f}±{r['bias_se']:.2f} sd {r['sd']:6.2f} "
                              f"rmse {r['rmse']:6.2f} crlb {r['crlb']:5.2f} ratio {r['rmse_over_crlb']:5.2f} "
                              f"cover {r['coverage95']:.2f} dropped {r['frames_dropped']:.0f}", flush=True)
                    print(f"  cell took {time.time() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
