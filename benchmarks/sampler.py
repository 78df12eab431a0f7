"""The marker-smc sampler: its cost, and how it compares with the normal posterior and with quadrature.

Writes ``benchmarks/results/sampler.md``. One core (thread variables set before
numpy is imported); the machine may be shared, so the load average is
recorded and times are wall-clock of one run each.

    python benchmarks/sampler.py          # about 3 minutes on one core

Cases
-----
case A, 500 frames, 15 mm      near-normal posterior: sampler against the marker estimator
case A at a bound              40 frames, 15 mm, forearm 295 mm of a [200, 300] prior: the fit ends
                               on the bound; sampler against quadrature of its own likelihood
finger, 500 frames, 2 mm       three coordinates of a functional joint centre (examples/finger.toml)
pendulum, 300 frames, 5 mm     three parameters (examples/pendulum.toml)
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
           "VECLIB_MAXIMUM_THREADS"):
    os.environ[_v] = "1"

import datetime  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.special import logsumexp  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from skelid.errors import SkelidWarning  # noqa: E402
from skelid.estimators.sampler import ProfileLikelihood, SamplerEstimator  # noqa: E402
from skelid.model import load_model  # noqa: E402
from skelid.simulate import builtin_model, simulate  # noqa: E402

sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import provenance, results_dir  # noqa: E402

OUT = results_dir() / "sampler.md"


def run(model, data, seed=0):
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkelidWarning)
        est = SamplerEstimator(model, rng=np.random.default_rng(seed)).fit(data)
    return est, time.perf_counter() - t0


def quadrature(est, grid):
    """Mean, sd, 95 % interval of the estimator's own likelihood on a grid (one parameter)."""
    fit = est.fit_info_
    like = ProfileLikelihood(est.model, est.y_, fit.theta, fit.pose, fit.penalty, est.sigma_**2, est.bias_,
                             tau=est.likelihood_tau_, scale=np.sqrt(np.diag(est.cov_data_)))
    ll = np.empty(grid.size)
    carry = {}
    for i in np.argsort(np.abs(grid - (fit.theta[0] - est.bias_[0]))):
        j = min(carry, key=lambda k: abs(k - i)) if carry else None
        l_i, carry[i] = like.refine(grid[i][None, None], like.initial_carry(1) if j is None else carry[j])
        ll[i] = l_i[0]
    w = np.exp(ll - logsumexp(ll))
    mean = w @ grid
    return mean, float(np.sqrt(w @ (grid - mean) ** 2)), np.interp([0.025, 0.975], np.cumsum(w) - w / 2, grid)


def row(name, est, seconds):
    g, s = est.gaussian_posterior_, est.posterior_
    smp = est.result().diagnostics["sampler"]
    d_mean = np.max(np.abs(s.mean - g.mean) / g.sd)
    sd_ratio = s.sd / g.sd
    return (f"| {name} | {est.model.n_params} | {int(est.frames_used_.sum())} | {seconds:.1f} | "
            f"{smp['seconds']:.1f} | {smp['stages']} | {smp['likelihood_evaluations']} | {smp['ess']:.0f} | "
            f"{smp['acceptance']:.2f} | {d_mean:.2f} | {sd_ratio.min():.2f}-{sd_ratio.max():.2f} |")


def main():
    load = os.getloadavg()[0]
    lines = ["# marker-smc sampler", "",
             f"Written by `benchmarks/sampler.py` on {datetime.datetime.now():%Y-%m-%d %H:%M}; one core; "
             f"load average {load:.2f} before on {os.cpu_count()} CPUs (shared machine: wall times of one run).",
             "", "200 particles, 3 moves per stage. 'd mean' is the largest difference of the posterior means "
             "in standard deviations of the normal posterior of the marker estimator; 'sd ratio' the range of "
             "the sampler's sd over the normal one.", "",
             "| case | P | frames | total s | sampler s | stages | evaluations | ESS | acceptance | d mean | "
             "sd ratio |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    a = builtin_model("case-a")
    trial = simulate(a, theta=[250.0], n_frames=500, sigma=15.0, rng=np.random.default_rng(1))
    lines.append(row("case A, 500 frames, 15 mm", *run(a, trial.data)))
    finger = load_model(ROOT / "examples" / "finger.toml")
    trial = simulate(finger, n_frames=500, sigma=2.0, rng=np.random.default_rng(1))
    lines.append(row("finger, 500 frames, 2 mm", *run(finger, trial.data)))
    pend = load_model(ROOT / "examples" / "pendulum.toml")
    trial = simulate(pend, n_frames=300, sigma=0.005, rng=np.random.default_rng(1))
    lines.append(row("pendulum, 300 frames, 5 mm", *run(pend, trial.data)))
    bound = simulate(a, theta=[295.0], n_frames=40, sigma=15.0, rng=np.random.default_rng(3))
    est, sec = run(a, bound.data)
    lines.append(row("case A at a bound, 40 frames", est, sec))
    q_mean, q_sd, q_ci = quadrature(est, np.linspace(200.0, 300.0, 401))
    s, g = est.posterior_, est.gaussian_posterior_
    ci, gci = s.credible_interval(0.95)[0], g.credible_interval(0.95)[0]
    lines += ["", "Case A at a bound (truth 295 mm, prior [200, 300] mm): the joint fit ends on the bound.", "",
              "| | mean | sd | 95 % interval |", "|---|---:|---:|---|",
              f"| quadrature of the sampled likelihood | {q_mean:.2f} | {q_sd:.2f} | [{q_ci[0]:.2f}, {q_ci[1]:.2f}] |",
              f"| marker-smc | {s.mean[0]:.2f} | {s.sd[0]:.2f} | [{ci[0]:.2f}, {ci[1]:.2f}] |",
              f"| marker (normal) | {g.mean[0]:.2f} | {g.sd[0]:.2f} | [{gci[0]:.2f}, {gci[1]:.2f}] |", ""]
    p = provenance()
    lines.insert(1, f"\nProvenance: commit {p['commit']}, {p['date']}, {p['cpu']} ({p['cores']} cores), "
                    f"load {p['load_average']}, `{p['command']}`.")
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
