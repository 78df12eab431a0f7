"""Cross-trial consistency of the intervals on six real trials of one body (addbio-subject4).

The body's geometry is the same in every trial, so each trial's interval for a
length must agree with every other trial's at the nominal rate. For every
parameter and every pair of trials ``z = (a - b) / sqrt(sd_a^2 + sd_b^2)``;
with honest intervals about 95 % of the pairs have ``|z| <= 1.96`` and the sd
of ``z`` is about 1.

* ``before``: each trial fitted alone with today's defaults (one pooled noise
  level, the trial's own interval).
* ``after``: each trial's own estimate from the multi-trial fit (per-marker
  noise levels as weights) with an interval that includes the between-trial
  variance (DerSimonian-Laird ``tau^2`` per parameter, estimated from these six
  trials). Because ``tau^2`` comes from the same trials, ``leave_pair_out``
  repeats the check with ``tau^2`` estimated from the four trials not in the
  pair: an out-of-sample version of the same claim.
* The joint (all trials, one geometry) estimate of each length against
  AddBiomechanics' automatic scaling and an expert's manual scaling (hip-knee
  and knee-ankle distances of their .osim models in the default pose, from the
  ``opensim`` package). These are references, not truth; note that the model
  here puts the knee and ankle midway between the epicondyle and malleolus
  markers, while the OpenSim models put them at their joint frames.

The model is ``examples/subject4_lower_limb.toml`` (``examples/build_subject4.py``):
pelvis, hinge knees, universal ankles; unknowns are the four lengths.

Run from the repository root::

    nice -n 10 python benchmarks/real_calibration.py [--max-frames 150]

Trials longer than ``--max-frames`` are decimated (every k-th frame), which
widens their intervals but leaves the question the same; the results then say
``reduced: true``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # multithreaded BLAS thrashes on a shared small machine

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from skelid.data import MarkerData  # noqa: E402
from skelid.estimators.marker import MarkerEstimator  # noqa: E402
from skelid.estimators.multitrial import MultiTrialEstimator, dersimonian_laird, pairwise_z  # noqa: E402
from skelid.io import read_markers  # noqa: E402
from skelid.simulate import resolve_model  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT.parent / "shared" / "data" / "addbio-subject4"
TRIALS = ("static1", "walking1", "walking2", "squats1", "STS1", "DJ1")
MODEL = ROOT / "examples" / "subject4_lower_limb.toml"
REFERENCES = {"addbiomechanics": "optimized_scale_and_markers.osim", "expert": "manually_scaled.osim",
              "generic": "unscaled_generic.osim"}
Z = 1.959963984540054


def decimate(data: MarkerData, max_frames: int) -> tuple[MarkerData, int]:
    k = max(1, int(np.ceil(data.n_frames / max_frames)))
    if k == 1:
        return data, 1
    return MarkerData(data.positions[::k], data.names, data.rate / k, data.units, source=data.source), k


def osim_lengths(path: Path) -> dict[str, float]:
    """Hip-knee and knee-ankle distances (mm) of an OpenSim model in its default pose."""
    import opensim as osim

    osim.Logger.removeFileSink()  # OpenSim would write opensim.log beside every model it loads

    osim.Logger.setLevelString("off")
    m = osim.Model(str(path))
    s = m.initSystem()
    js = m.getJointSet()

    def centre(joint):
        p = js.get(joint).getChildFrame().getPositionInGround(s)
        return 1000.0 * np.array([p.get(0), p.get(1), p.get(2)])

    out = {}
    for side in ("r", "l"):
        hip, knee, ankle = centre(f"hip_{side}"), centre(f"walker_knee_{side}"), centre(f"ankle_{side}")
        out[f"thigh_{side}"] = float(np.linalg.norm(knee - hip))
        out[f"shank_{side}"] = float(np.linalg.norm(ankle - knee))
    return out


def z_summary(z: np.ndarray) -> dict:
    z = z[np.isfinite(z)]
    return {"fraction_consistent": float(np.mean(np.abs(z) <= Z)), "sd_z": float(np.std(z)),
            "rms_z": float(np.sqrt(np.mean(z**2))), "n_pairs": int(z.size)}


def leave_pair_out_z(est: np.ndarray, var: np.ndarray) -> np.ndarray:
    """Pairwise z with tau^2 of each pair estimated from the other trials only."""
    K = est.shape[0]
    i, j = np.triu_indices(K, 1)
    out = np.empty((len(i), est.shape[1]))
    for r, (a, b) in enumerate(zip(i, j, strict=True)):
        keep = np.setdiff1d(np.arange(K), [a, b])
        tau2, _, _ = dersimonian_laird(est[keep], var[keep])
        out[r] = (est[a] - est[b]) / np.sqrt(var[a] + var[b] + 2 * tau2)
    return out


def git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def run(max_frames: int) -> dict:
    warnings.simplefilter("ignore")
    model = resolve_model(MODEL)
    names = list(model.parameter_names)
    datas, strides = [], []
    for t in TRIALS:
        d, k = decimate(read_markers(DATA / "MarkerData" / f"{t}.trc"), max_frames)
        datas.append(d)
        strides.append(k)
    t0 = time.perf_counter()
    before = [MarkerEstimator(model).fit(d) for d in datas]
    t_before = time.perf_counter() - t0
    theta_b = np.array([e.theta_ for e in before])
    sd_b = np.array([e.posterior_.sd for e in before])
    t0 = time.perf_counter()
    multi = MultiTrialEstimator(model, noise="per_marker").fit(datas)
    t_multi = time.perf_counter() - t0
    theta_a = multi.trial_theta_
    var_a = np.einsum("kpp->kp", multi.trial_cov_)
    sd_within = np.sqrt(var_a)
    sd_a = np.sqrt(var_a + multi.tau2_)
    z_before = pairwise_z(theta_b, sd_b)
    z_weighted = pairwise_z(theta_a, sd_within)
    z_after = pairwise_z(theta_a, sd_a)
    z_lpo = leave_pair_out_z(theta_a, var_a)
    refs = {k: osim_lengths(DATA / "Models" / f) for k, f in REFERENCES.items()}
    joint = {}
    for p, n in enumerate(names):
        m, s = float(multi.theta_[p]), float(multi.posterior_.sd[p])
        joint[n] = {"mean": m, "sd": s, "ci95": [m - Z * s, m + Z * s],
                    "sd_within_trials": float(np.sqrt(multi.cov_within_[p, p])),
                    "sd_between_trials": float(np.sqrt(multi.tau2_[p]))}
        for k, ref in refs.items():
            joint[n][f"{k}_mm"] = ref[n]
            joint[n][f"{k}_minus_joint"] = ref[n] - m
            joint[n][f"{k}_inside"] = bool(abs(ref[n] - m) <= Z * s)
    trials = {}
    for k, t in enumerate(TRIALS):
        trials[t] = {
            "frames": int(datas[k].n_frames), "stride": strides[k], "rate_hz": datas[k].rate,
            "before": {n: {"mean": float(theta_b[k, p]), "sd": float(sd_b[k, p])} for p, n in enumerate(names)},
            "after": {n: {"mean": float(theta_a[k, p]), "sd_within": float(sd_within[k, p]),
                          "sd": float(sd_a[k, p])} for p, n in enumerate(names)},
            "sigma_pooled": before[k].sigma_,
            "sigma_per_marker_median": float(np.nanmedian(multi.trials_[k].marker_sigma_)),
            "sigma_per_marker_range": [float(np.nanmin(multi.trials_[k].marker_sigma_)),
                                       float(np.nanmax(multi.trials_[k].marker_sigma_))],
        }
    sb, sa = z_summary(z_before), z_summary(z_after)
    return {
        "benchmark": "real_calibration",
        "data": "../shared/data/addbio-subject4 (six trials of one subject)",
        "model": str(MODEL.relative_to(ROOT)),
        "parameters": names,
        "reduced": any(k > 1 for k in strides),
        "max_frames": max_frames,
        "fraction_consistent_before": sb["fraction_consistent"],
        "fraction_consistent": sa["fraction_consistent"],
        "sd_z_before": sb["sd_z"],
        "sd_z": sa["sd_z"],
        "z": {"before": sb, "per_marker_weights_no_between_trial": z_summary(z_weighted), "after": sa,
              "after_leave_pair_out": z_summary(z_lpo)},
        "z_by_parameter": {n: {"before": z_summary(z_before[:, p]), "after": z_summary(z_after[:, p]),
                               "after_leave_pair_out": z_summary(z_lpo[:, p])} for p, n in enumerate(names)},
        "tau_mm": {n: float(np.sqrt(multi.tau2_[p])) for p, n in enumerate(names)},
        "consistency_test": multi.consistency_,
        "joint": joint,
        "trials": trials,
        "seconds": {"before": round(t_before, 1), "multi_trial": round(t_multi, 1)},
        "provenance": {"commit": git_commit(), "python": platform.python_version(),
                       "machine": platform.machine(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())},
    }


def markdown(res: dict) -> str:
    names = res["parameters"]
    L = ["# Cross-trial consistency on addbio-subject4", ""]
    if res["reduced"]:
        L += [f"**Reduced run**: trials decimated to at most {res['max_frames']} frames (every k-th frame; "
              "strides below). Per-trial intervals are wider than on the full trials.", ""]
    L += [f"Model `{res['model']}` (hinge knees; unknowns: {', '.join(names)}). "
          f"Pairs of trials x parameters: {res['z']['before']['n_pairs']}.", "",
          "| intervals | fraction of pairs with abs(z) <= 1.96 | sd of z | rms z |", "|---|---|---|---|"]
    labels = {"before": "before: each trial alone, pooled noise",
              "per_marker_weights_no_between_trial": "per-marker noise, no between-trial term",
              "after": "after: per-marker noise + between-trial tau^2 (in-sample)",
              "after_leave_pair_out": "after, tau^2 from the other four trials (leave pair out)"}
    for k, lab in labels.items():
        s = res["z"][k]
        L.append(f"| {lab} | {s['fraction_consistent']:.2f} | {s['sd_z']:.2f} | {s['rms_z']:.2f} |")
    L += ["", "Targets: fraction >= 0.90, sd of z 0.8-1.3.", "",
          "## By parameter", "", "| parameter | tau (mm) | before: fraction, sd z | after: fraction, sd z | "
          "leave pair out: fraction, sd z |", "|---|---|---|---|---|"]
    for n in names:
        b, a, lpo = (res["z_by_parameter"][n][k] for k in ("before", "after", "after_leave_pair_out"))
        L.append(f"| {n} | {res['tau_mm'][n]:.2f} | {b['fraction_consistent']:.2f}, {b['sd_z']:.2f} | "
                 f"{a['fraction_consistent']:.2f}, {a['sd_z']:.2f} | {lpo['fraction_consistent']:.2f}, "
                 f"{lpo['sd_z']:.2f} |")
    c = res["consistency_test"]
    L += ["", f"Chi-square consistency of the per-trial estimates against the joint one: "
          f"{c['statistic']:.1f} on {c['dof']} degrees of freedom, p = {c['p_value']:.2g}.", "",
          "## Per trial (mm): before (pooled noise) mean ± sd; after mean ± sd with tau", "",
          "| trial | frames (stride) | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    for t, row in res["trials"].items():
        cells = [f"{row['before'][n]['mean']:.1f} ± {row['before'][n]['sd']:.2f}; "
                 f"{row['after'][n]['mean']:.1f} ± {row['after'][n]['sd']:.2f}" for n in names]
        L.append(f"| {t} | {row['frames']} ({row['stride']}) | " + " | ".join(cells) + " |")
    L += ["", "## Joint estimate (all six trials, one geometry) against the OpenSim scalings (mm)", "",
          "| parameter | joint mean [95 % interval] | within / between sd | AddBiomechanics | expert | generic |",
          "|---|---|---|---|---|---|"]
    for n in names:
        j = res["joint"][n]

        def ref(k, j=j):
            return f"{j[k + '_mm']:.1f} ({j[k + '_minus_joint']:+.1f}{', inside' if j[k + '_inside'] else ''})"

        L.append(f"| {n} | {j['mean']:.1f} [{j['ci95'][0]:.1f}, {j['ci95'][1]:.1f}] | "
                 f"{j['sd_within_trials']:.2f} / {j['sd_between_trials']:.2f} | {ref('addbiomechanics')} | "
                 f"{ref('expert')} | {ref('generic')} |")
    L += ["", "The OpenSim lengths run between their joint frames (hip centre to the knee frame, knee frame "
          "to the talus frame); this model's knee and ankle lie midway between the epicondyle and malleolus "
          "markers, so a few millimetres of difference are a matter of definition.", "",
          f"Time: before {res['seconds']['before']} s, multi-trial {res['seconds']['multi_trial']} s. "
          f"Commit {res['provenance']['commit'][:10]}, {res['provenance']['date']}.", ""]
    return "\n".join(L)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-frames", type=int, default=150)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "real_calibration"))
    args = ap.parse_args(argv)
    res = run(args.max_frames)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(res, indent=2) + "\n")
    out.with_suffix(".md").write_text(markdown(res))
    print(markdown(res))


if __name__ == "__main__":
    main()
