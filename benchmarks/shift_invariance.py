"""How far a rigid shift of all markers moves the marker fit's numbers.

    python benchmarks/shift_invariance.py [--shifts 4]

Case A (40 frames, sigma 3 mm) and case B (80 frames, sigma 5 mm) are fitted with the
default MarkerEstimator, then again after adding a random shift (uniform in
``[-s, s]`` per coordinate) to every marker, for ``s`` from 1e2 to 1e7 mm. The largest
relative change of the estimate, its sd and sigma over the shifts is recorded for each
``s``. Both models have a free root, so the exact answer is no change at all. The fit works
about the data's centre (``skelid.estimators.base.fit_origin``), so what is left is the
shifted data's own rounding (the shifts are not whole millimetres), moved by the fit's
stopping rule: the same at every distance. It is what the tolerances of the shift
properties in ``tests/test_api_contract.py`` and ``tests/test_invariance.py`` and the
comment on ``skelid.data.MAX_FIT_COORDINATE_MM`` quote. Writes
``results/shift_invariance.json`` and ``.md``.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"
os.environ.setdefault("SKELID_NUMBA", "wait")

import argparse  # noqa: E402
import warnings  # noqa: E402

import numpy as np  # noqa: E402
from _common import results_dir, write_json  # noqa: E402

CASES = {"case-a": (40, 3.0, 0), "case-b": (80, 5.0, 1)}
SIZES = (1e2, 1e4, 1e5, 1e6, 1e7)


def values(model, data):
    from skelid.estimators.marker import MarkerEstimator

    r = MarkerEstimator(model, rng=0).fit(data).result()
    return (np.array([p.mean for p in r.parameters.values()]), np.array([p.sd for p in r.parameters.values()]),
            r.noise.sigma)


def run(n_shifts: int) -> list[dict]:
    from skelid.data import MAX_FIT_COORDINATE_MM
    from skelid.errors import SkelidWarning
    from skelid.estimators import base
    from skelid.simulate import builtin_model, simulate

    rows = []
    rng = np.random.default_rng(7)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkelidWarning)
        for case, (n_frames, sigma, seed) in CASES.items():
            model = builtin_model(case)
            data = simulate(model, n_frames=n_frames, sigma=sigma, rng=np.random.default_rng(seed)).data
            ref = values(model, data)
            for size in SIZES:
                worst = np.zeros(3)
                for _ in range(n_shifts):
                    shifted = data.replace(positions=data.positions + rng.uniform(-size, size, model.dim))
                    limit = base.check_range
                    base.check_range = lambda *a, **k: None  # measure beyond the range the fit accepts too
                    try:
                        v = values(model, shifted)
                    finally:
                        base.check_range = limit
                    worst = np.maximum(worst, [np.max(np.abs(v[0] / ref[0] - 1)), np.max(np.abs(v[1] / ref[1] - 1)),
                                               abs(v[2] / ref[2] - 1)])
                rows.append({"case": case, "shift_mm": size, "accepted": size <= MAX_FIT_COORDINATE_MM,
                             "estimate": float(worst[0]), "sd": float(worst[1]), "sigma": float(worst[2])})
                print(rows[-1], flush=True)
    return rows


def markdown(rows: list[dict]) -> str:
    out = ["# Rigid shift of all markers: largest relative change", "",
           "| case | shift up to (mm) | a fit accepts it | estimate | sd | sigma |", "|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['case']} | {r['shift_mm']:g} | {'yes' if r['accepted'] else 'no'} | {r['estimate']:.2g} | "
                   f"{r['sd']:.2g} | {r['sigma']:.2g} |")
    return "\n".join(out) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shifts", type=int, default=4, help="random shifts per size")
    args = ap.parse_args()
    rows = run(args.shifts)
    out = results_dir() / "shift_invariance"
    write_json(out.with_suffix(".json"), rows)
    out.with_suffix(".md").write_text(markdown(rows))


if __name__ == "__main__":
    main()
