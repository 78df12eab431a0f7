"""The models' average (``skelid fit --alternative``) against one model's interval, on simulated truth.

Case B of the seed method (planar arm, forearm length L2, four markers), 1000 frames at 100 Hz,
i.i.d. noise. Per repetition the truth is drawn: L2 uniform in [220, 280] mm and marker D's
place across the forearm uniform in [-40, -30] mm. Two models are fitted to the same trial,
differing only in where they put marker D (its place is not estimated, as a model built from a
reference pose fixes it), and averaged by stacking (:mod:`skelid.estimators.uncertainty.stacking`):

* ``right+wrong``: the main model has D 5-10 mm off the truth (either side), the alternative
  has it right; a user who picked the wrong main model gets the average instead of its interval.
* ``between``: the truth lies between the two models' places for D (each 3-7 mm off it).
* ``same``: both models right (the same model twice): the average must be the model's own.

Scored per cell: coverage of the true L2 by the main model's 95 % interval, by the
alternative's and by the average's; their mean width; the right model's mean weight; RMSE
beside the Cramér-Rao bound of the right model (its ``crlb_sd``, averaged).

    python benchmarks/model_average.py --reps 100 --jobs 2
"""

from __future__ import annotations

import argparse
import sys
import time
import tomllib
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, provenance, results_dir, write_results  # noqa: E402

RESULTS = results_dir()
CELLS = ("right+wrong", "between", "same")
FRAMES, RATE = 1000, 100.0


def _model(name: str, d_y: float):
    """Case B with marker D at ``(180, d_y)`` on the forearm."""
    from skelid.model.description import model_from_dict

    doc = tomllib.loads((ROOT / "examples" / "case_b.toml").read_text())
    doc["model"]["name"] = name
    for m in doc["markers"]:
        if m["name"] == "D":
            m["position"] = [180.0, float(d_y)]
    return model_from_dict(doc, name)


def one(args) -> dict:
    cell, seed, sigma = args
    from skelid.sensitivity import sensitivity
    from skelid.simulate import simulate

    rng = np.random.default_rng([11, CELLS.index(cell), seed])
    L2, d_true = rng.uniform(220.0, 280.0), rng.uniform(-40.0, -30.0)
    if cell == "right+wrong":
        places = {"main": d_true + rng.choice([-1, 1]) * rng.uniform(5.0, 10.0), "alt": d_true}
    elif cell == "between":
        places = {"main": d_true - rng.uniform(3.0, 7.0), "alt": d_true + rng.uniform(3.0, 7.0)}
    else:
        places = {"main": d_true, "alt": d_true}
    truth_model = _model("truth", d_true)
    theta = np.array([L2])
    trial = simulate(truth_model, theta, n_frames=FRAMES, rate=RATE, sigma=sigma, rng=rng)
    models = [_model(n, y) for n, y in places.items()]
    t0 = time.process_time()
    sens = sensitivity(models, [trial.data], rng=np.random.default_rng(seed))
    cpu = time.process_time() - t0
    avg = sens["average"]
    row = {"cell": cell, "seed": seed, "sigma": sigma, "truth": L2, "weights": avg["weights"],
           "blocks": avg["blocks"], "cpu_s": cpu}
    for n in ("main", "alt"):
        e = sens["estimates"][n]["L2"]
        row[n] = {"value": e["value"], "sd": e["sd"], "interval": [e["value"] - 1.959964 * e["sd"],
                                                                     e["value"] + 1.959964 * e["sd"]]}
    q = avg["quantities"]["L2"]
    row["average"] = {"value": q["value"], "sd": q["sd"], "interval": q["interval"]}
    return row


def summarise(rows: list[dict]) -> list[dict]:
    out = []
    for cell in CELLS:
        for sigma in sorted({r["sigma"] for r in rows}):
            rs = [r for r in rows if r["cell"] == cell and r["sigma"] == sigma]
            if not rs:
                continue
            right = "alt" if cell != "between" else None
            s = {"cell": cell, "sigma": sigma, "reps": len(rs),
                 "mean_blocks": float(np.mean([r["blocks"] for r in rs]))}
            for k in ("main", "alt", "average"):
                err = np.array([r[k]["value"] - r["truth"] for r in rs])
                cov = np.mean([r[k]["interval"][0] <= r["truth"] <= r[k]["interval"][1] for r in rs])
                s[k] = {"coverage": float(cov), "rmse": float(np.sqrt(np.mean(err**2))),
                        "mean_width": float(np.mean([np.diff(r[k]["interval"])[0] for r in rs])),
                        "mean_sd": float(np.mean([r[k]["sd"] for r in rs]))}
            s["weight_alt"] = float(np.mean([r["weights"]["alt"] for r in rs]))
            s["right_model"] = right
            s["cpu_s_per_rep"] = float(np.mean([r["cpu_s"] for r in rs]))
            out.append(s)
    return out


def markdown(res: dict) -> str:
    p = res["provenance"]
    lines = ["# The models' average against one model's interval (case B, marker D placed two ways)", "",
             f"Commit `{p['commit'][:10]}`, {p['date']}, {p['cpu']}, {p['cores']} cores; "
             f"`{p['command']}`.", "",
             "Per repetition: L2 ~ U[220, 280] mm, marker D's true place across the forearm ~ U[-40, -30] mm, "
             f"{FRAMES} frames at {RATE:g} Hz, i.i.d. noise. Two models differ only in D's place. "
             "`right+wrong`: main 5-10 mm off, alternative right; `between`: the truth between them (3-7 mm "
             "each); `same`: both right. Coverage of the true L2 by each 95 % interval; `weight alt`: the "
             "alternative's mean stacking weight.", "",
             "| cell | sigma (mm) | reps | blocks | coverage: main / alternative / average | mean width (mm): "
             "main / alternative / average | RMSE (mm): main / alternative / average | weight alt |",
             "|---|---|---|---|---|---|---|---|"]
    for s in res["summary"]:
        f = "{:.2f} / {:.2f} / {:.2f}".format(*(s[k]["coverage"] for k in ("main", "alt", "average")))
        w = "{:.1f} / {:.1f} / {:.1f}".format(*(s[k]["mean_width"] for k in ("main", "alt", "average")))
        e = "{:.2f} / {:.2f} / {:.2f}".format(*(s[k]["rmse"] for k in ("main", "alt", "average")))
        lines.append(f"| {s['cell']} | {s['sigma']:g} | {s['reps']} | {s['mean_blocks']:.0f} | {f} | {w} | {e} | "
                     f"{s['weight_alt']:.2f} |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=100)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--sigmas", type=float, nargs="+", default=[5.0, 15.0])
    ap.add_argument("--cells", nargs="+", default=list(CELLS), choices=CELLS)
    ap.add_argument("--out", type=Path, default=RESULTS / "model_average")
    args = ap.parse_args()
    tasks = [(c, s, sg) for c in args.cells for sg in args.sigmas for s in range(args.reps)]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(args.jobs) as ex:
        rows = list(ex.map(one, tasks, chunksize=4))
    res = {"provenance": provenance(), "wall_s": time.perf_counter() - t0, "summary": summarise(rows), "rows": rows}
    write_results(args.out, res, markdown)
    print(markdown(res))


if __name__ == "__main__":
    main()
