"""Profile of one MarkerEstimator fit on a case-A trial (cProfile on the CPU clock).

    python benchmarks/profile_fit.py                 # 500 frames, the top 30 lines by cumulative time
    python benchmarks/profile_fit.py --frames 1000 --top 50

One BLAS thread; a warm-up fit first (numba loaded, the compiled kernel waited
for); then the median CPU and wall time of three fits, the load average, the
joint fits' iteration counts, and the profile of one more fit. The profiler's
clock is ``time.process_time``, so time spent waiting for a core on a shared
machine does not count.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"
os.environ.setdefault("SKELID_NUMBA", "wait")

import argparse  # noqa: E402
import cProfile  # noqa: E402
import pstats  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402

import numpy as np  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=500)
    ap.add_argument("--top", type=int, default=30)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    from skelid.estimators import joint, marker
    from skelid.simulate import builtin_model, simulate

    model = builtin_model("case-a")
    trial = simulate(model, sigma=15.0, n_frames=args.frames, rng=np.random.default_rng(0))
    marker.MarkerEstimator(model).fit(trial.data)  # warm up
    wall, cpu = [], []
    for _ in range(3):
        t0, c0 = time.perf_counter(), time.process_time()
        est = marker.MarkerEstimator(model).fit(trial.data)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    print(f"case A, {args.frames} frames: CPU {statistics.median(cpu):.3f} s, wall {statistics.median(wall):.3f} s "
          f"(median of 3), load average {', '.join(f'{x:.1f}' for x in os.getloadavg())}, "
          f"pose path {est.result().diagnostics['pose_path']}")
    print(f"estimate {est.theta_[0]:.6f}, sd {np.sqrt(est.cov_[0, 0]):.6f}")
    calls = []
    original = marker.joint_fit

    def counted(*a, **k):
        f = original(*a, **k)
        calls.append((f.n_iter, f.converged))
        return f

    marker.joint_fit = counted
    try:
        prof = cProfile.Profile(time.process_time)
        prof.enable()
        marker.MarkerEstimator(model).fit(trial.data)
        prof.disable()
    finally:
        marker.joint_fit = original
    print("joint fits (iterations, converged):", calls, "step tolerance", joint.STEP_TOL)
    pstats.Stats(prof).sort_stats("cumulative").print_stats(args.top)


if __name__ == "__main__":
    main()
