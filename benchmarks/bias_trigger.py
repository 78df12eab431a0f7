"""Is the second-order bias correction still accurate on long trials? (one trial per length)

    python benchmarks/bias_trigger.py --frames 1000 10000

Fits case A (sigma 15 mm, seed = number of frames, as speed.py's scaling rows) with
``bias_correction="box"`` (no bootstrap fallback, no jackknife) and prints the bias in sd
units next to one check of the expansion's accuracy: the change of the bias when it is
evaluated again at the corrected point ``theta - b`` (same poses). The fallback rule
``|b| > BIAS_RELIABLE sd`` grows like sqrt(frames) whatever that change is.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"
os.environ.setdefault("SKELID_NUMBA", "wait")

import argparse  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402

import numpy as np  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[1000, 10000])
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    from skelid.estimators.joint import smoothed_bias
    from skelid.estimators.marker import MarkerEstimator
    from skelid.simulate import builtin_model, simulate

    model = builtin_model("case-a")
    for F in args.frames:
        trial = simulate(model, sigma=15.0, n_frames=F, rng=np.random.default_rng(F))
        c0 = time.process_time()
        est = MarkerEstimator(model, bias_correction="box", jackknife=False).fit(trial.data)
        cpu = time.process_time() - c0
        f = est.fit_info_
        sd = float(np.sqrt(est.cov_plain_[0, 0]))
        b = float(est.bias_[0])
        c0 = time.process_time()
        b2 = float(smoothed_bias(model, est.y_, f.theta - est.bias_, f.pose, est.sigma_**2, f.penalty)[0])
        cpu_b = time.process_time() - c0
        print(f"{F} frames: fit {cpu:.1f} s CPU; bias {b:.4f} = {b / sd:.2f} sd (sd {sd:.4f}); at theta - b "
              f"{b2:.4f}: change {(b2 - b) / sd:+.3f} sd ({abs(b2 - b) / abs(b):.2%} of b); "
              f"that pass {cpu_b:.2f} s CPU; load {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
