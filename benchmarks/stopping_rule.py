"""The live stopping rule: frames to "done" when a user follows the advice, against a fixed routine, and
whether the truth lies inside the interval at the moment the session says "done".

Each simulated session draws its geometry from the model's prior (a right posterior then covers the
truth at the nominal rate) and a random starting pose inside the joints' ranges, and feeds a live
:class:`skelid.live.Session` with ``target_sd`` set (noise estimated, as a user would run it) one frame at a
time at 100 Hz, i.i.d. normal noise on every marker coordinate. Two ways to move, on the same truth, start
and noise level:

- ``guided``: after 20 still frames, the user does what :meth:`Session.advice` says first (a 1 s sweep of
  the named joint through the named range, reached from the current pose in 0.2 s), asks again, and so on;
- ``fixed``: every joint rotation in turn (the root's left out) sweeps once through the central 60 % of its
  range in 1 s (reached in 0.2 s), over and over: a fixed calibration routine.

Both stop at the first frame whose estimate is ``done`` (healthy, every parameter identified with its sd at
or below the target), or after ``--max-frames`` (counted as not done). Per cell and routine: sessions done,
median and 90th percentile of frames to done, coverage of the truth by the 95 % interval at "done" (every
parameter; sessions not done left out), rms z there, and the sd at done over the target.

    nice -n 10 python benchmarks/stopping_rule.py --reps 100 --jobs 2

Results: ``benchmarks/results/stopping_rule.{json,md}``.
"""

from __future__ import annotations

import argparse
import math
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
#: cell -> (model, noise sd in model units, target sd of every parameter in model units, live method)
CELLS = {"case-a sigma 5 mm, target 0.5 mm": ("case-a", 5.0, 0.5, "auto"),
         "case-a sigma 5 mm, target 0.5 mm, grid form": ("case-a", 5.0, 0.5, "grid"),
         "tennis arm sigma 1 mm, target 1 mm": ("tennis_arm", 0.001, 0.001, "auto")}
RATE = 100.0
SWEEP = 100  # frames of one sweep (1 s)
REACH = 20  # frames to reach a sweep's start (0.2 s)
STILL = 20  # still frames before the first advice
ROUTINES = ("guided", "fixed")


def _model(name):
    from skelid.model import load_model
    from skelid.simulate import builtin_model

    return builtin_model(name) if name.startswith("case") else load_model(ROOT / "examples" / f"{name}.toml")


def _eased(a, b, n):
    """``n`` poses from ``a`` to ``b`` (both ``(Q,)``), smooth at both ends."""
    s = 0.5 - 0.5 * np.cos(np.linspace(0.0, np.pi, n))
    return a[None] + s[:, None] * (b - a)[None]


def _sweep(q, k, centre, half):
    """Reach ``centre`` on coordinate ``k`` from ``q``, then one sine cycle of amplitude ``half``: ``(poses, end)``."""
    start = q.copy()
    start[k] = centre
    seq = np.repeat(start[None], SWEEP, axis=0)
    seq[:, k] = centre + half * np.sin(np.linspace(0.0, 2.0 * np.pi, SWEEP, endpoint=False))
    return np.concatenate([_eased(q, start, REACH), seq]), seq[-1].copy()


def _joint_rotations(model):
    return [k for k, d in enumerate(model.dofs) if d.kind == "R" and model.parent_index[d.segment] >= 0]


def _fixed_moves(model, ranges):
    """The fixed routine's sweeps, in order: ``[(k, centre, half)]`` (radians)."""
    return [(k, 0.5 * (ranges[k][0] + ranges[k][1]), 0.3 * (ranges[k][1] - ranges[k][0]))
            for k in _joint_rotations(model)]


def _session(model, truth, q0, sigma, target, method, routine, rng, max_frames):
    """Run one session; ``(frames, done, estimate)``."""
    from skelid.estimators.fit.pose import _rotation_ranges
    from skelid.live import Session
    from skelid.model.kinematics import marker_positions

    session = Session(model, labels=model.marker_names, units=model.units, rate=RATE, method=method,
                      target_sd=target, rng=np.random.default_rng(0))
    ranges = _rotation_ranges(model)
    fixed = _fixed_moves(model, ranges)
    q, est, n, step = q0.copy(), None, 0, 0
    plan = np.repeat(q0[None], STILL, axis=0)
    while n < max_frames:
        for pose in plan:
            y = marker_positions(model, truth, pose) + sigma * rng.standard_normal((len(model.markers), model.dim))
            est = session.push(y)
            n += 1
            if est.done or n >= max_frames:
                return n, bool(est.done), est
        q = plan[-1].copy()
        if routine == "guided":
            advice = session.advice()
            if not advice:
                plan = np.repeat(q[None], 10, axis=0)
                continue
            a = advice[0]
            lo, hi = math.radians(a.lower_deg), math.radians(a.upper_deg)
            plan, _ = _sweep(q, a.dof, 0.5 * (lo + hi), 0.5 * (hi - lo))
        else:
            k, centre, half = fixed[step % len(fixed)]
            step += 1
            plan, _ = _sweep(q, k, centre, half)
    return n, bool(est is not None and est.done), est


def one(args):
    from skelid.estimators.sampler import sample_prior
    from skelid.simulate import simulate_motion

    cell, seed, max_frames = args
    name, sigma, target, method = CELLS[cell]
    model = _model(name)
    rng = np.random.default_rng([23, seed])
    truth = sample_prior(model, 1, rng)[0]
    q0 = simulate_motion(model, 1, RATE, rng)[0]
    out = {"cell": cell, "seed": seed, "truth": truth.tolist()}
    for routine in ROUTINES:
        n, done, est = _session(model, truth, q0, sigma, target, method, routine,
                                np.random.default_rng([29, seed]), max_frames)
        ps = list(est.parameters.values())
        lo = np.array([p.interval[0] for p in ps])
        hi = np.array([p.interval[1] for p in ps])
        sd = np.array([p.sd for p in ps])
        out[routine] = {"frames": n, "done": done, "covers": ((lo <= truth) & (truth <= hi)).tolist(),
                        "z": ((est.theta - truth) / sd).tolist(), "sd_over_target": (sd / target).tolist(),
                        "health": est.health}
    return out


def summarise(rows) -> dict:
    out = {}
    for cell in CELLS:
        rs = [r for r in rows if r["cell"] == cell]
        res = {"sessions": len(rs)}
        for routine in ROUTINES:
            done = [r[routine] for r in rs if r[routine]["done"]]
            frames = np.array([d["frames"] for d in done], float)
            cov = np.array([c for d in done for c in d["covers"]], float)
            z = np.array([v for d in done for v in d["z"]], float)
            res[routine] = {
                "done": len(done),
                "frames_median": float(np.median(frames)) if frames.size else None,
                "frames_p90": float(np.percentile(frames, 90)) if frames.size else None,
                "coverage_at_done": float(cov.mean()) if cov.size else None,
                "coverage_pairs": int(cov.size),
                "rms_z_at_done": float(np.sqrt(np.mean(z**2))) if z.size else None,
                "sd_over_target_max": float(max(max(d["sd_over_target"]) for d in done)) if done else None}
        pairs = [(r["guided"]["frames"], r["fixed"]["frames"]) for r in rs
                 if r["guided"]["done"] and r["fixed"]["done"]]
        res["guided_over_fixed_frames_median"] = float(np.median([a / b for a, b in pairs])) if pairs else None
        res["guided_faster_fraction"] = float(np.mean([a < b for a, b in pairs])) if pairs else None
        out[cell] = res
    return out


def markdown(res: dict) -> str:
    p = res["provenance"]
    lines = ["# Live stopping rule: frames to \"done\" and coverage at \"done\"", "",
             f"{res['reps']} sessions per cell (geometry drawn from the prior per session, a random start pose), "
             f"at most {res['max_frames']} frames each (100 Hz). Commit `{p['commit']}`, {p['date']}, "
             f"`{p['command']}`; {res['wall_s']:.0f} s wall.", "",
             "`guided`: the user does what `Session.advice()` says first, then asks again; `fixed`: every joint "
             "rotation in turn through the central 60 % of its range, 1 s each, over and over. Coverage: the "
             "95 % interval at the frame that says done holds the truth (every parameter of the sessions done; "
             "0.95 is right). Guided / fixed: the median over sessions of the ratio of their frames to done.", "",
             "| cell | routine | done | frames to done, median | 90th percentile | coverage at done | rms z | "
             "largest sd / target |", "|---|---|---|---|---|---|---|---|"]
    for cell, r in res["cells"].items():
        for routine in ROUTINES:
            g = r[routine]
            fmt = lambda v, f="{:.0f}": "-" if v is None else f.format(v)  # noqa: E731
            lines.append(f"| {cell} | {routine} | {g['done']} of {r['sessions']} | {fmt(g['frames_median'])} | "
                         f"{fmt(g['frames_p90'])} | {fmt(g['coverage_at_done'], '{:.3f}')} "
                         f"({g['coverage_pairs']}) | {fmt(g['rms_z_at_done'], '{:.2f}')} | "
                         f"{fmt(g['sd_over_target_max'], '{:.3f}')} |")
    lines += ["", "| cell | guided / fixed frames (median) | guided sooner |", "|---|---|---|"]
    for cell, r in res["cells"].items():
        a, b = r["guided_over_fixed_frames_median"], r["guided_faster_fraction"]
        lines.append(f"| {cell} | {'-' if a is None else f'{a:.2f}'} | {'-' if b is None else f'{b:.2f}'} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reps", type=int, default=100)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--max-frames", type=int, default=4000)
    ap.add_argument("--cells", nargs="*", default=list(CELLS))
    ap.add_argument("--out", default=str(RESULTS / "stopping_rule"))
    a = ap.parse_args(argv)
    t0 = time.time()
    tasks = [(c, s, a.max_frames) for c in a.cells for s in range(a.reps)]
    with ProcessPoolExecutor(a.jobs) as ex:
        rows = list(ex.map(one, tasks, chunksize=1))
    res = {"reps": a.reps, "max_frames": a.max_frames, "wall_s": time.time() - t0,
           "cells": summarise(rows), "rows": rows, "provenance": provenance(argv)}
    write_results(Path(a.out), res, markdown)


if __name__ == "__main__":
    main()
