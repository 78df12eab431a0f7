"""When is the motion-model fit's race between its two starts decided?

    python benchmarks/race_decision.py [--reps 4]

The marker fit's motion-model stage (``skelid.estimators.marker.motion_stage``) runs two
joint fits for ``RACE_ITER`` iterations each, one from the tracked poses and one from the
graduated-smoothing (stiffer) start, and continues the one with the lower penalised cost.
Stopping the losing start early would save up to ``RACE_ITER - k`` of its iterations; it is
safe only if the start that is behind after ``k`` iterations never wins at ``RACE_ITER``.

For fixed-seed trials of the accuracy study's cells (i.i.d. case A and B, and case A near the
folded and straight poses; the seeds of ``benchmarks/accuracy.py``) and the lower limb, this
records the difference of the two starts' penalised costs after ``k`` iterations (in units of
the screening fit's residual variance per coordinate) and counts, for each ``k`` and margin,
the trials where an early decision would pick another start than the full race.
Results: ``benchmarks/results/race_decision.json``.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"
os.environ.setdefault("SKELID_NUMBA", "wait")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import results_dir, write_json  # noqa: E402

RESULTS = results_dir()
KS = (1, 2, 3, 4, 5, 6, 8, 10)
MARGINS = (1.0, 10.0, 100.0, 1000.0)
CELLS = (("case-a", 5, "folded"), ("case-a", 15, "folded"), ("case-a", 5, "straight"), ("case-a", 15, "straight"),
         ("case-a", 5, "iid"), ("case-a", 15, "iid"), ("case-b", 5, "iid"), ("case-b", 15, "iid"))


def race_curves(model, data) -> list[float]:
    """Penalised cost of the tracked start less the stiff start's after each of ``KS`` iterations, / sigma^2."""
    import skelid.estimators.marker as mk
    from skelid.estimators.base import make_rng
    from skelid.estimators.fit.joint import joint_fit
    from skelid.estimators.fit.pose import workspace

    est = mk.MarkerEstimator(model)
    y, rate = mk.marker_array(model, data, est.rate)
    ws = workspace(model)
    st = mk.start_stage(model, y, rate, est, make_rng(est.rng), ws)
    sc = mk.screen_stage(model, st, est, ws)
    cutoff = est.cutoff  # the default, "auto": per-coordinate cutoffs, as motion_stage chooses them
    if isinstance(cutoff, str):
        cutoff = np.maximum(mk.choose_cutoffs(model, sc.fit.pose, sc.fit.frames_used, rate),
                            min(mk.MIN_AUTO_CUTOFF, rate / 2))
    cutoff = np.asarray(cutoff, float)
    stiff = joint_fit(model, sc.y, sc.fit.theta, sc.fit.pose, n_iter=mk.STIFF_ITER, bounds=st.bounds,
                      frames=sc.fixed, rate=rate, cutoff=cutoff / mk.STIFFER, ws=ws, summary=False)
    sigma2 = sc.fit.rss / max(sc.fit.n_obs, 1)
    costs = [[mk.penalised_cost(joint_fit(model, sc.y, th, qq, n_iter=k, bounds=st.bounds, frames=sc.fixed,
                                           rate=rate, cutoff=cutoff, ws=ws, summary=False)) for k in KS]
             for th, qq in ((st.theta0, st.pose0), (stiff.theta, stiff.pose))]
    return [(a - b) / sigma2 for a, b in zip(*costs, strict=True)]


def accuracy_trial(case, sigma, noise, rep, truth=250.0, n_frames=500):
    from accuracy import CASES, NOISES, POSTURES, singular_trial

    from skelid.simulate import builtin_model, simulate

    model = builtin_model(case)
    seed = [CASES.index(case), int(sigma), int(truth), (NOISES + tuple(POSTURES) + ("coupled",)).index(noise), rep]
    rng = np.random.default_rng(seed)
    if noise in POSTURES:
        return model, singular_trial(model, truth, n_frames, sigma, POSTURES[noise], rng).data
    return model, simulate(model, theta=[truth], n_frames=n_frames, sigma=sigma, noise=noise,
                           sta_amplitude=10.0, rng=rng).data


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reps", type=int, default=4)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    from profile_fit import load_case

    c0 = time.process_time()
    rows = []
    for case, sigma, noise in CELLS:
        for rep in range(args.reps):
            d = race_curves(*accuracy_trial(case, sigma, noise, rep))
            rows.append({"cell": f"{case} sigma {sigma} {noise}", "rep": rep, "dcost_by_k": d})
            print(rows[-1]["cell"], rep, " ".join(f"{x:.3g}" for x in d), flush=True)
    model, data, _ = load_case("lower_limb", 500)
    rows.append({"cell": "lower limb", "rep": 0, "dcost_by_k": race_curves(model, data)})
    print("lower limb", " ".join(f"{x:.3g}" for x in rows[-1]["dcost_by_k"]))
    table = {}
    for i, k in enumerate(KS[:-1]):
        for m in MARGINS:
            dec = [(r["dcost_by_k"][i] > 0, r["dcost_by_k"][-1] > 0) for r in rows if abs(r["dcost_by_k"][i]) > m]
            table[f"k={k} margin={m:g}"] = {"decided": len(dec), "wrong": sum(a != b for a, b in dec)}
            print(f"after {k} iterations, margin {m:g} sigma^2: decided {len(dec)} of {len(rows)}, "
                  f"other start than the full race in {table[f'k={k} margin={m:g}']['wrong']}")
    out = {"ks": KS, "race_iter": KS[-1], "rows": rows, "early_decision": table,
           "note": "dcost: penalised cost of the tracked-pose start less the stiff start's, / sigma^2 "
                   "(> 0: the stiff start is ahead)",
           "reps_per_cell": args.reps, "cpu_s": time.process_time() - c0, "loadavg": list(os.getloadavg()),
           "date": time.strftime("%Y-%m-%d %H:%M")}
    write_json(RESULTS / "race_decision.json", out)


if __name__ == "__main__":
    main()
