"""Live Gaussian form against the batch ``marker`` estimate: with and without the motion model.

For each cell (a model and a noise level) and each simulated trial, the
estimate of a live :class:`skelid.live.Session` (Gaussian form) after the last
frame, every frame folded in (:meth:`~skelid.live.Session.finish`), is compared
with the batch :class:`~skelid.estimators.marker.MarkerEstimator` on the same
frames, as ``|live - batch| / sd_batch`` per parameter, for the session
without a motion model (``cutoff=None``) and with the batch method's motion
model (``cutoff=6``), for the default (``cutoff='auto'``: the cutoff
chosen from the frames as the batch method chooses it), and with the truth (``|live - true| / sd_live``). The
last cell plays the simulator's motion five times faster (up to 7.5 Hz).
Each trial is replayed twice: clean, and with glitches
(one marker missing for 10 frames, two labels swapped for 4 frames, 3 frames
with no marker at all); the glitched replay is compared with the clean one
(``|glitched - clean| / sd_live``) and its health flags are checked.

    nice -n 10 python benchmarks/live_agreement.py --reps 100 --jobs 2

Per cell and setting it reports the fraction of trials whose every parameter
lies within 1 and within 2 batch sd of the batch estimate, the live/batch sd
ratio, and the coverage of the truth by the live 95 % interval (per parameter).
``--cutoffs`` and ``--no-glitch`` run a subset (the default setting alone,
without the glitched replay, costs a third of the full run).

    nice -n 10 python benchmarks/live_agreement.py --reps 100 --jobs 2

Results: ``benchmarks/results/live_agreement.{json,md}`` (the run's
repetitions are written beside the figures; fewer than 100 is marked reduced).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core per trial: BLAS threads only spin on a shared machine
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402  (after the thread settings, which BLAS reads when it loads)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import results_dir, write_json  # noqa: E402

RESULTS = results_dir()
#: (model, noise sd in model units, frames, speed): ``speed`` times the simulator's motion (0.15-1.5 Hz), at 100 Hz
CELLS = {"case-a sigma 1 mm": ("case-a", 1.0, 300, 1), "case-a sigma 5 mm": ("case-a", 5.0, 300, 1),
         "tennis arm sigma 1 mm": ("tennis_arm", 0.001, 200, 1), "arm10 sigma 2 mm": ("arm10", 0.002, 200, 1),
         "tennis arm sigma 1 mm, 5x faster": ("tennis_arm", 0.001, 300, 5)}
CUTOFFS = {"none": None, "6 Hz": 6.0, "auto": "auto"}


def _model(name):
    from skelid.model import load_model
    from skelid.simulate import builtin_model

    if name.startswith("case"):
        return builtin_model(name)
    return load_model(ROOT / ("benchmarks" if name == "arm10" else "examples") / f"{name}.toml")


def _glitch(y, rng):
    """The frames with one marker missing for 10 frames, two labels swapped for 4 and 3 empty frames."""
    y = y.copy()
    F, M = y.shape[:2]
    a = int(rng.integers(F // 4, F // 2))
    y[a:a + 10, int(rng.integers(M))] = np.nan
    i, j = rng.choice(M, 2, replace=False)
    b = int(rng.integers(F // 2, 3 * F // 4))
    y[b:b + 4, [i, j]] = y[b:b + 4, [j, i]]
    c = int(rng.integers(3 * F // 4, F - 5))
    y[c:c + 3] = np.nan
    return y, (a, b, c)


def one(args):
    cell, seed, keys, glitch = args
    from skelid.errors import SkelidError
    from skelid.estimators.marker import MarkerEstimator
    from skelid.live import Session
    from skelid.simulate import simulate

    name, sigma, frames, speed = CELLS[cell]
    model = _model(name)
    rng = np.random.default_rng([11, seed])
    trial = simulate(model, n_frames=frames, sigma=sigma, rate=100.0 / speed, rng=rng)
    data = trial.data.replace(rate=100.0)  # the same poses, played ``speed`` times faster
    try:
        batch = MarkerEstimator(model, rng=np.random.default_rng(0)).fit(data)
    except SkelidError as exc:  # no batch interval to compare with (counted, not compared)
        return {"cell": cell, "seed": seed, "batch_failed": str(exc)}
    sd = np.sqrt(np.diag(batch.cov_))
    glitched, (a, b, c) = _glitch(data.positions, rng)
    out = {"cell": cell, "seed": seed}
    for key in keys:
        cutoff = CUTOFFS[key]
        ests = {}
        for kind, y in (("clean", data.positions), ("glitched", glitched))[:2 if glitch else 1]:
            s = Session(model, labels=data.names, units=data.units, rate=data.rate, method="gaussian", cutoff=cutoff,
                        rng=np.random.default_rng(0))
            flags = []
            for frame in y:
                est = s.push(frame)
                flags.append(est.healthy)
            ests[kind] = s.finish()  # every frame folded in, as the batch fit has them
            if kind == "glitched":
                bad = np.flatnonzero(~np.array(flags))
                expected = set(range(a, a + 10)) | set(range(b, b + 4)) | set(range(c, c + 3))
                out[f"{key} flags as expected"] = set(bad.tolist()) == expected
        live_sd = np.sqrt(np.diag(ests["clean"].cov))
        out[f"{key} vs batch"] = (np.abs(ests["clean"].theta - batch.theta_) / sd).tolist()
        out[f"{key} vs truth"] = (np.abs(ests["clean"].theta - trial.theta) / live_sd).tolist()
        lo, hi = np.array([ests["clean"].parameters[n].interval for n in model.parameter_names]).T
        out[f"{key} covers truth"] = ((lo <= trial.theta) & (trial.theta <= hi)).tolist()
        if glitch:
            out[f"{key} glitched vs clean"] = (np.abs(ests["glitched"].theta - ests["clean"].theta)
                                              / live_sd).tolist()
        out[f"{key} sd ratio"] = (live_sd / sd).tolist()
    return out


def summarise(rows) -> dict:
    res = {}
    for cell in CELLS:
        rs = [r for r in rows if r["cell"] == cell]
        failed = [r for r in rs if "batch_failed" in r]
        rs = [r for r in rs if "batch_failed" not in r]
        if not rs:
            continue
        c = res[cell] = {"trials": len(rs), "batch_failed": len(failed)}
        for key in CUTOFFS:
            if f"{key} vs batch" not in rs[0]:
                continue
            d = np.array([r[f"{key} vs batch"] for r in rs])
            t = np.array([r[f"{key} vs truth"] for r in rs])
            cov = np.array([r[f"{key} covers truth"] for r in rs])
            n = len(rs)
            c[key] = {"vs_truth_median": float(np.median(t)), "vs_truth_max": float(t.max()),
                      "vs_batch_median": float(np.median(d)), "vs_batch_p90": float(np.percentile(d, 90)),
                      "vs_batch_max": float(d.max()), "within_1sd_fraction": float((d.max(axis=1) < 1.0).mean()),
                      "within_2sd_fraction": float((d.max(axis=1) < 2.0).mean()),
                      "within_1sd_per_parameter": float((d < 1.0).mean()),
                      "coverage_95": float(cov.mean()),
                      "coverage_95_se": float(np.sqrt(cov.mean() * (1 - cov.mean()) / cov.size)),
                      "sd_ratio_median": float(np.median([r[f"{key} sd ratio"] for r in rs])),
                      "trials": n}
            if f"{key} glitched vs clean" in rs[0]:
                g = np.array([r[f"{key} glitched vs clean"] for r in rs])
                c[key].update({"glitched_vs_clean_max": float(g.max()), "glitched_vs_clean_median": float(np.median(g)),
                               "flags_as_expected": float(np.mean([r[f"{key} flags as expected"] for r in rs]))})
    return res


def write(res, reps, cpu_s, wall_s, load, command, tag: str = "") -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    reduced = reps < 100
    meta = {"reps": reps, "reduced": reduced, "cpu_s": cpu_s, "wall_s": wall_s, "loadavg_after": load,
            "date": time.strftime("%Y-%m-%d %H:%M"), "command": command}
    name = "live_agreement" + (f"_{tag}" if tag else "")
    write_json(RESULTS / f"{name}.json", {"meta": meta, "cells": res}, indent=2)
    lines = ["# Live session against the batch estimate", "",
             f"Written by `benchmarks/live_agreement.py` on {meta['date']}: {reps} simulated trials per cell"
             + (" (**reduced**: fewer than 100)" if reduced else "")
             + f"; {cpu_s:.0f} CPU s (this process and its workers), load average after {load[0]:.1f}. "
             f"Command: `{command}`.", "",
             "`|live - batch| / sd` per parameter (live: `Session.finish()` after the last frame; batch: "
             "`MarkerEstimator`, its sd); within 1 / 2 sd: trials whose "
             "every parameter is that close; live sd / batch sd: median over trials and parameters; coverage: "
             "fraction of parameters whose live 95 % interval holds the truth (binomial se beside it). Glitched: one "
             "marker missing for 10 frames, two labels swapped for 4, 3 empty frames, compared with the clean replay "
             "in the live sd; flags: the frames flagged unhealthy are exactly the glitched ones (- : not run). "
             "Trials whose batch fit gave no interval (a convergence error) are left out: "
             + (", ".join(f"{cell} {c['batch_failed']}" for cell, c in res.items() if c.get("batch_failed"))
                or "none") + ".", "",
             "| cell | motion model | median | 90 % | max | within 1 sd | within 2 sd | live sd / batch sd | "
             "coverage 95 % | vs truth (live sd) median / max | glitched max | flags right |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|"]
    for cell, c in res.items():
        for key in CUTOFFS:
            if key not in c:
                continue
            v = c[key]
            gl = (f"{v['glitched_vs_clean_max']:.2f} | {v['flags_as_expected']:.2f}" if "flags_as_expected" in v
                  else "- | -")
            lines.append(f"| {cell} | {key} | {v['vs_batch_median']:.2f} | {v['vs_batch_p90']:.2f} | "
                         f"{v['vs_batch_max']:.2f} | {v['within_1sd_fraction']:.2f} | {v['within_2sd_fraction']:.2f} | "
                         f"{v['sd_ratio_median']:.2f} | {v['coverage_95']:.3f} +- {v['coverage_95_se']:.3f} | "
                         f"{v['vs_truth_median']:.2f} / {v['vs_truth_max']:.2f} | {gl} |")
    (RESULTS / f"{name}.md").write_text("\n".join(lines) + "\n")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=100)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--cells", nargs="*", default=list(CELLS), choices=list(CELLS))
    ap.add_argument("--cutoffs", nargs="*", default=list(CUTOFFS), choices=list(CUTOFFS))
    ap.add_argument("--no-glitch", action="store_true", help="skip the glitched replay (a third of the cost)")
    ap.add_argument("--tag", default="", help="results go to live_agreement_TAG.{json,md} (default: no suffix)")
    a = ap.parse_args(argv)
    t0, c0 = time.perf_counter(), time.process_time()
    tasks = [(cell, s, a.cutoffs, not a.no_glitch) for cell in a.cells for s in range(a.reps)]
    with ProcessPoolExecutor(a.jobs) as pool:
        rows = list(pool.map(one, tasks))
    children = os.times()
    cpu = time.process_time() - c0 + children.children_user + children.children_system
    res = summarise(rows)
    command = "python benchmarks/live_agreement.py " + " ".join(argv if argv is not None else sys.argv[1:])
    write(res, a.reps, cpu, time.perf_counter() - t0, list(os.getloadavg()), command.strip(), a.tag)
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
