"""Profile of one MarkerEstimator fit on a case-A trial (cProfile on the CPU clock).

    python benchmarks/profile_fit.py                 # 500 frames, the top 30 lines by cumulative time
    python benchmarks/profile_fit.py --frames 1000 --top 50
    python benchmarks/profile_fit.py --case lower_limb   # examples/lower_limb.toml on the OpenSim walk
    python benchmarks/profile_fit.py --case b            # case B (sigma 15 mm)

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
    ap.add_argument("--case", choices=("a", "b", "lower_limb"), default="a")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    from skelid.estimators import marker
    from skelid.estimators.fit import joint

    model, data, label = load_case(args.case, args.frames)
    marker.MarkerEstimator(model).fit(data)  # warm up
    wall, cpu = [], []
    for _ in range(args.repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        est = marker.MarkerEstimator(model).fit(data)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    print(f"{label}: CPU {statistics.median(cpu):.3f} s, wall {statistics.median(wall):.3f} s "
          f"(median of {len(cpu)}), load average {', '.join(f'{x:.1f}' for x in os.getloadavg())}, "
          f"pose path {est.result().diagnostics['pose_path']}")
    sd = np.sqrt(np.diag(est.cov_))
    print("estimate", " ".join(f"{v:.6f}" for v in est.theta_[:6]), "sd", " ".join(f"{v:.6f}" for v in sd[:6]),
          f"bias method {est.bias_method_}")
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
        marker.MarkerEstimator(model).fit(data)
        prof.disable()
    finally:
        marker.joint_fit = original
    print("joint fits (iterations, converged):", calls, "step tolerance (sd): screening", marker.SCREEN_STEP_TOL,
          "motion-model fit", marker.FIT_STEP_TOL, "default", joint.STEP_TOL)
    pstats.Stats(prof).sort_stats("cumulative").print_stats(args.top)


def load_case(case: str, n_frames: int):
    """(model, data, label) of a profiled case: case A or B (sigma 15 mm, seed 0) or the lower limb."""
    from pathlib import Path

    if case == "lower_limb":
        from skelid.io import read_markers
        from skelid.model import load_model

        root = Path(__file__).resolve().parents[1]
        data = read_markers(root.parent / "shared" / "data" / "opensim-subject01" / "subject01_walk1.trc")
        return load_model(root / "examples" / "lower_limb.toml"), data, f"lower limb, {data.n_frames} frames"
    from skelid.simulate import builtin_model, simulate

    model = builtin_model(f"case-{case}")
    trial = simulate(model, sigma=15.0, n_frames=n_frames, rng=np.random.default_rng(0))
    return model, trial.data, f"case {case.upper()}, {n_frames} frames"


if __name__ == "__main__":
    main()
