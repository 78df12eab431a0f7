"""Long live sessions: does the live interval still hold the truth as the frames add up?

A live :class:`skelid.live.Session` (its defaults: the Gaussian form with the motion model, the noise
estimated) is fed a simulated trial one frame at a time at 100 Hz; at each checkpoint (5 s to 100 s of
frames by default) its estimate and 95 % interval are compared with the truth. Each session draws its
geometry from the model's prior (a right posterior then covers the truth at the nominal rate, whatever the
geometry) and its own motion and noise (:func:`skelid.simulate.simulate`).

The sd of a session shrinks as one over the root of its frames; a bias that does not (each frame linearised
where its pose is poorly known, the second-order bias of the joint fit) shows as coverage that falls with
the frames. Per cell and checkpoint: coverage of every parameter's interval (with its binomial se), mean z
and rms z (``z = (estimate - truth) / sd``; 0 and 1 when right).

    nice -n 10 python benchmarks/live_long.py --reps 100 --jobs 2

Results: ``benchmarks/results/live_long.{json,md}``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core per session
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import provenance, results_dir, write_results  # noqa: E402

RESULTS = results_dir()
RATE = 100.0
#: cell -> (model, marker noise sd in model units)
CELLS = {"case-a sigma 5 mm": ("case-a", 5.0),
         "case-a sigma 15 mm": ("case-a", 15.0),
         "arm10 sigma 2 mm": ("arm10", 0.002),
         "tennis arm sigma 1 mm": ("tennis_arm", 0.001)}
CHECKPOINTS = (500, 1000, 2000, 5000, 10000)


def _model(name):
    from skelid.model import load_model
    from skelid.simulate import builtin_model

    if name.startswith("case"):
        return builtin_model(name)
    return load_model(ROOT / ("benchmarks" if name == "arm10" else "examples") / f"{name}.toml")


def one(args):
    """One session: z and coverage of every parameter at each checkpoint."""
    from skelid.estimators.sampler import sample_prior
    from skelid.live import Session, build_kernels
    from skelid.simulate import simulate

    cell, seed, checkpoints = args
    name, sigma = CELLS[cell]
    model = _model(name)
    build_kernels(model)
    rng = np.random.default_rng([31, seed])
    truth = sample_prior(model, 1, rng)[0]
    n = max(checkpoints)
    trial = simulate(model, theta=truth, n_frames=n, rate=RATE, sigma=sigma, rng=rng)
    session = Session(model, labels=trial.data.names, units=trial.data.units, rate=RATE)
    out = {"cell": cell, "seed": seed, "truth": truth.tolist(), "at": {}}
    slowest, slowest_work = 0.0, 0.0
    for t, frame in enumerate(np.asarray(trial.data.positions)):
        t0 = time.perf_counter()
        est = session.push(frame, defer=True)
        t1 = time.perf_counter()
        session.work()  # the step of work after the estimate, as Session.feed does
        slowest, slowest_work = max(slowest, t1 - t0), max(slowest_work, time.perf_counter() - t1)
        if t + 1 in checkpoints:
            ps = list(est.parameters.values())
            lo = np.array([p.interval[0] for p in ps])
            hi = np.array([p.interval[1] for p in ps])
            sd = np.array([p.sd for p in ps])
            out["at"][str(t + 1)] = {"z": ((est.theta - truth) / sd).tolist(),
                                     "covers": ((lo <= truth) & (truth <= hi)).tolist(),
                                     "healthy": bool(est.healthy)}
    out["slowest_push_ms"] = 1e3 * slowest
    out["slowest_work_ms"] = 1e3 * slowest_work
    return out


def summarise(rows, checkpoints) -> dict:
    out = {}
    for cell in dict.fromkeys(r["cell"] for r in rows):
        rs = [r for r in rows if r["cell"] == cell]
        res = {"sessions": len(rs), "slowest_push_ms_median": float(np.median([r["slowest_push_ms"] for r in rs])),
               "slowest_work_ms_median": float(np.median([r["slowest_work_ms"] for r in rs]))}
        for c in checkpoints:
            z = np.array([v for r in rs for v in r["at"][str(c)]["z"]], float)
            cov = np.array([v for r in rs for v in r["at"][str(c)]["covers"]], float)
            res[str(c)] = {"coverage": float(cov.mean()), "coverage_se": float(np.sqrt(cov.mean() * (1 - cov.mean())
                                                                                        / cov.size)),
                           "pairs": int(cov.size), "mean_z": float(z.mean()), "rms_z": float(np.sqrt(np.mean(z**2))),
                           "healthy": float(np.mean([r["at"][str(c)]["healthy"] for r in rs]))}
        out[cell] = res
    return out


def markdown(res: dict) -> str:
    p = res["provenance"]
    cps = res["checkpoints"]
    lines = ["# Long live sessions: coverage as the frames add up", "",
             f"{res['reps']} sessions per cell (geometry drawn from the prior per session, its own motion and "
             f"noise), each fed {max(cps)} frames at 100 Hz to a `Session` with its defaults. Commit "
             f"`{p['commit']}`, {p['date']}, `{p['command']}`; {res['wall_s']:.0f} s wall.", "",
             "Coverage: the 95 % interval holds the truth (every parameter of every session; 0.95 is right, "
             "binomial se beside it); z = (estimate - truth) / sd: mean 0 and rms 1 when right.", "",
             "| cell | frames | coverage | mean z | rms z | healthy |", "|---|---|---|---|---|---|"]
    for cell, r in res["cells"].items():
        for c in cps:
            g = r[str(c)]
            lines.append(f"| {cell} | {c} | {g['coverage']:.3f} ± {g['coverage_se']:.3f} ({g['pairs']}) | "
                         f"{g['mean_z']:+.2f} | {g['rms_z']:.2f} | {g['healthy']:.2f} |")
    cells = res["cells"].items()
    lines += ["", "Slowest push of a session (`push(frame, defer=True)`, the estimate's latency; median over "
              "sessions, ms): " + ", ".join(f"{cell} {r['slowest_push_ms_median']:.0f}" for cell, r in cells)
              + ". Slowest step of work after a push (`Session.work`; median over sessions, ms): "
              + ", ".join(f"{cell} {r['slowest_work_ms_median']:.1f}" for cell, r in cells) + "."]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reps", type=int, default=100)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--checkpoints", type=int, nargs="*", default=list(CHECKPOINTS))
    ap.add_argument("--cells", nargs="*", default=list(CELLS))
    ap.add_argument("--out", default=str(RESULTS / "live_long"))
    a = ap.parse_args(argv)
    t0 = time.time()
    cps = tuple(sorted(a.checkpoints))
    tasks = [(c, s, cps) for c in a.cells for s in range(a.reps)]
    with ProcessPoolExecutor(a.jobs) as ex:
        rows = list(ex.map(one, tasks, chunksize=1))
    res = {"reps": a.reps, "checkpoints": list(cps), "wall_s": time.time() - t0,
           "cells": summarise(rows, cps), "rows": rows, "provenance": provenance(argv)}
    write_results(Path(a.out), res, markdown)


if __name__ == "__main__":
    main()
