"""How far a code change moves the marker fit's estimates, in standard deviations.

    python benchmarks/fit_drift.py --save before.json     # on the old code
    python benchmarks/fit_drift.py --compare before.json  # on the new code

Fits case A and case B (500 frames, sigma 15 mm, seed 0) and the lower limb
(examples/lower_limb.toml on the OpenSim walk) with the default MarkerEstimator and
records, per case, the final estimate, the profile estimate, the bias removed, the
interval's sd, the jackknife's sd and the CPU time. ``--compare`` prints the largest
change of each, divided by the reference sd of that parameter.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"
os.environ.setdefault("SKELID_NUMBA", "wait")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402

import numpy as np  # noqa: E402

FIELDS = ("theta", "theta_profile", "bias", "sd", "sd_jackknife")


def run_case(case: str) -> dict:
    from profile_fit import load_case

    from skelid.estimators.marker import MarkerEstimator

    model, data, label = load_case(case, 500)
    c0 = time.process_time()
    est = MarkerEstimator(model).fit(data)
    cpu = time.process_time() - c0
    jk = est.jackknife_.get("parameters", {})
    return {"label": label, "cpu_s": cpu, "bias_method": est.bias_method_,
            "theta": est.theta_.tolist(), "theta_profile": est.theta_profile_.tolist(), "bias": est.bias_.tolist(),
            "sd": np.sqrt(np.diag(est.cov_)).tolist(),
            "sd_jackknife": [jk.get(n, {}).get("sd", float("nan")) for n in model.parameter_names],
            "iterations": int(est.fit_info_.n_iter), "converged": bool(est.fit_info_.converged)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--save")
    ap.add_argument("--compare")
    ap.add_argument("--cases", nargs="+", default=["a", "b", "lower_limb"])
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    out = {c: run_case(c) for c in args.cases}
    out["loadavg"] = list(os.getloadavg())
    if args.save:
        from _common import write_json

        write_json(args.save, out)
    if args.compare:
        with open(args.compare) as fh:
            ref = json.load(fh)
        for c in args.cases:
            sd = np.asarray(ref[c]["sd"])
            row = [f"{c:>10}: CPU {ref[c]['cpu_s']:.2f} -> {out[c]['cpu_s']:.2f} s, bias method "
                   f"{ref[c]['bias_method']} -> {out[c]['bias_method']}"]
            for f in FIELDS:
                d = np.nanmax(np.abs(np.asarray(out[c][f]) - np.asarray(ref[c][f])) / sd)
                row.append(f"{f} {d:.1e} sd")
            print("; ".join(row))
    else:
        for c in args.cases:
            print(c, f"CPU {out[c]['cpu_s']:.2f} s", out[c]["bias_method"], np.round(out[c]["theta"][:4], 4))
    print("load average", ", ".join(f"{x:.1f}" for x in out["loadavg"]))


if __name__ == "__main__":
    main()
