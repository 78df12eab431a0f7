"""Cross-trial consistency of the intervals on six real trials of one body (addbio-subject4).

The body's geometry is the same in every trial, so each trial's interval for a
length must agree with every other trial's at the nominal rate. For every
parameter and every pair of trials ``z = (a - b) / sqrt(sd_a^2 + sd_b^2)``;
with honest intervals about 95 % of the pairs have ``|z| <= 1.96`` and the sd
of ``z`` is about 1.

* ``before``: each trial fitted alone with today's defaults (one pooled noise
  level, the trial's own interval).
* ``after``: each trial's own estimate from the multi-trial fit (per-marker
  noise levels as weights) with the sd the estimator reports for comparing a
  trial with another (its own variance without the part every trial shares, the
  marker set's placement and the markers' disagreement, which cancels in a
  difference; plus the between-trial spread), by default:
  each parameter's between-trial sd ``tau`` integrated out under a half-normal
  prior scaled by a documented 10 mm skin-marker artefact (see
  :mod:`skelid.estimators.multitrial`). Because the posterior of ``tau`` comes
  from the same trials, ``leave_pair_out`` repeats the check with it computed
  from the four trials not in the pair: an out-of-sample version of the same
  claim.
* The same with ``tau^2`` estimated instead (DerSimonian-Laird, Paule-Mandel),
  with a normal or a ``t`` quantile of Satterthwaite's degrees of freedom: with
  four trials ``tau^2`` has about three degrees of freedom, so a difference
  standardised by it follows roughly ``t_3`` (sd 1.7) even when every interval
  is honest.
* The joint (all trials, one geometry) estimate of each length against
  AddBiomechanics' automatic scaling and an expert's manual scaling (hip-knee
  and knee-ankle distances of their .osim models in the default pose, from the
  ``opensim`` package). These are references, not truth; note that the model
  here puts the knee and ankle midway between the epicondyle and malleolus
  markers, while the OpenSim models put them at their joint frames.

The model is ``examples/subject4_lower_limb.toml`` (``examples/build_subject4.py``):
pelvis, hinge knees, universal ankles; unknowns are the four lengths.

Run from the repository root::

    nice -n 10 python benchmarks/real_calibration.py [--max-frames N] [--refit]

All frames by default. Trials longer than ``--max-frames`` are decimated (every
k-th frame), which widens their intervals but leaves the question the same; the
results then say ``reduced: true``. The per-trial fits are cached (pickled, in
``--cache``, keyed by the source code of the fit and the trial), so that the
statistics can be recomputed without refitting; ``--refit`` ignores the cache.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # multithreaded BLAS thrashes on a shared small machine

import argparse  # noqa: E402
import pickle  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from _common import provenance, results_dir, rewrite_markdown, source_key, write_results  # noqa: E402

from skelid.data import MarkerData  # noqa: E402
from skelid.estimators.checks.artefact import artefact_covariance  # noqa: E402
from skelid.estimators.marker import MarkerEstimator  # noqa: E402
from skelid.estimators.multitrial import (  # noqa: E402
    BETWEEN_TRIAL,
    PRIOR_ARTEFACT_RMS_MM,
    MultiTrialEstimator,
    mixture_half_width,
    pairwise_z,
    satterthwaite_dof,
    t_factor,
    tau_posterior,
)
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


def honest_band(sds: np.ndarray, observed: float, n_sim: int = 20_000, seed: int = 0) -> dict:
    """What the sd of z would be with honest intervals of these widths (a sampling check).

    Each trial's estimate is drawn ``N(mu, sd_kp^2)`` independently with the reported sds, and the
    sd of the pairwise z computed as for the data. The 60 pairs come from 6 trials, so they are
    far from independent: this gives the sd of z's own spread and the share of honest draws at or
    below the observed value.
    """
    rng = np.random.default_rng(seed)
    K = sds.shape[0]
    i, j = np.triu_indices(K, 1)
    x = rng.normal(size=(n_sim, *sds.shape)) * sds
    z = ((x[:, i] - x[:, j]) / np.sqrt(sds[i] ** 2 + sds[j] ** 2)).reshape(n_sim, -1)
    s = z.std(axis=1)
    frac = (np.abs(z) <= Z).mean(axis=1)
    return {"sd_z_quantiles": {q: float(np.quantile(s, float(q))) for q in ("0.05", "0.5", "0.95")},
            "fraction_quantiles": {q: float(np.quantile(frac, float(q))) for q in ("0.05", "0.5", "0.95")},
            "p_sd_z_at_most_observed": float(np.mean(s <= observed)), "n_sim": n_sim}


def trial_sd(var: np.ndarray, tau2: np.ndarray, n_trials: int, t: bool) -> np.ndarray:
    """Each trial's own sd with the between-trial variance, ``t``-scaled (Satterthwaite) or not."""
    total = var + tau2
    sd = np.sqrt(total)
    if not t:
        return sd
    return sd * t_factor(satterthwaite_dof(total, np.broadcast_to(tau2, var.shape), max(n_trials - 1, 1)))


def leave_pair_out_z(est: np.ndarray, var: np.ndarray, method: str = "dl", t: bool = True,
                     unit_artefact: np.ndarray | None = None) -> np.ndarray:
    """Pairwise z with tau^2 of each pair estimated from the other trials only.

    ``method='prior'``: the half-normal prior on tau (scale from ``unit_artefact``, each trial's
    variance added by a unit artefact, over the other trials) and the posterior's trial intervals.
    """
    K = est.shape[0]
    i, j = np.triu_indices(K, 1)
    out = np.empty((len(i), est.shape[1]))
    for r, (a, b) in enumerate(zip(i, j, strict=True)):
        keep = np.setdiff1d(np.arange(K), [a, b])
        if method == "prior":
            scale = PRIOR_ARTEFACT_RMS_MM * np.sqrt(unit_artefact[keep].mean(axis=0))
            grid, weight, _, _ = tau_posterior(est[keep], var[keep], scale)
            sd = mixture_half_width(weight[:, None, :], 0.0, var[[a, b]][None] + grid[:, None, :] ** 2,
                                    np.zeros((2, est.shape[1]))) / Z
        else:
            tau2, _, _ = BETWEEN_TRIAL[method](est[keep], var[keep])
            sd = trial_sd(var[[a, b]], tau2, len(keep), t)
        out[r] = (est[a] - est[b]) / np.sqrt(sd[0] ** 2 + sd[1] ** 2)
    return out


def trial_status(multi, names) -> dict:
    """Each trial's own status of each parameter and whether it contributes to the joint estimate."""
    status = getattr(multi, "trial_status_", None)
    informs = getattr(multi, "trial_informs_", None)
    if status is None or informs is None:
        return {}
    return {t: {n: {"status": str(status[k, p]), "contributes": bool(informs[k, p])} for p, n in enumerate(names)}
            for k, t in enumerate(multi.trial_labels_)}


def fit_trial(model, data: MarkerData, mode: str, cache: Path | None, tag: str):
    """A fitted MarkerEstimator (cached), its wall and CPU seconds."""
    # the key leaves out the multi-trial combination: a single-trial fit does not run it
    key = source_key(MODEL, skip=("multitrial.py",))
    path = None if cache is None else cache / f"{tag}-{mode}-{key}.pkl"
    if path is not None and path.exists():
        with path.open("rb") as fh:
            return pickle.load(fh)
    t0, c0 = time.perf_counter(), time.process_time()
    est = MarkerEstimator(model, noise=mode).fit(data)
    out = (est, time.perf_counter() - t0, time.process_time() - c0)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("wb") as fh:
            pickle.dump(out, fh)
    return out


def load_trials(max_frames: int | None):
    datas, strides = [], []
    for t in TRIALS:
        d = read_markers(DATA / "MarkerData" / f"{t}.trc")
        d, k = decimate(d, max_frames) if max_frames else (d, 1)
        datas.append(d)
        strides.append(k)
    return datas, strides


def fits_only(max_frames: int | None, cache: Path, mode: str) -> None:
    """Fill the cache with one mode's per-trial fits (so that two processes can share the work)."""
    warnings.simplefilter("ignore")
    model = resolve_model(MODEL)
    datas, _ = load_trials(max_frames)
    for t, d in sorted(zip(TRIALS, datas, strict=True), key=lambda x: -x[1].n_frames):
        _, w, c = fit_trial(model, d, mode, cache, f"{t}-max{max_frames or 'all'}")
        print(f"{t} {mode}: {d.n_frames} frames, {w:.0f} s wall, {c:.0f} s CPU, load {os.getloadavg()[0]:.1f}",
              flush=True)


def run(max_frames: int | None, cache: Path | None) -> dict:
    warnings.simplefilter("ignore")
    load_start = os.getloadavg()
    cpu0, wall0 = time.process_time(), time.perf_counter()
    model = resolve_model(MODEL)
    names = list(model.parameter_names)
    datas, strides = load_trials(max_frames)
    tag = f"max{max_frames or 'all'}"
    before, after, timing = [], [], {}
    for t, d in zip(TRIALS, datas, strict=True):
        eb, wb, cb = fit_trial(model, d, "pooled", cache, f"{t}-{tag}")
        ea, wa, ca = fit_trial(model, d, "per_marker", cache, f"{t}-{tag}")
        before.append(eb)
        after.append(ea)
        timing[t] = {"before_wall_s": round(wb, 1), "before_cpu_s": round(cb, 1),
                     "after_wall_s": round(wa, 1), "after_cpu_s": round(ca, 1)}
        print(f"{t}: {d.n_frames} frames, fits {wb:.0f} + {wa:.0f} s wall, {cb:.0f} + {ca:.0f} s CPU", flush=True)
    theta_b = np.array([e.theta_ for e in before])
    sd_b = np.array([e.posterior_.sd for e in before])
    rates = [d.rate for d in datas]
    t0, c0 = time.perf_counter(), time.process_time()
    multi = MultiTrialEstimator(model, noise="per_marker", between_trial="dl").combine(after, rates, list(TRIALS))
    t_multi, c_multi = time.perf_counter() - t0, time.process_time() - c0
    multi_pm = MultiTrialEstimator(model, noise="per_marker", between_trial="pm").combine(after, rates, list(TRIALS))
    multi_prior = MultiTrialEstimator(model, noise="per_marker", between_trial="prior").combine(
        after, rates, list(TRIALS))
    unit_artefact = np.array([np.diag(artefact_covariance(model, e.y_, e.fit_info_.theta, e.fit_info_.pose,
                                                          e.fit_info_.penalty, 1.0, e.frames_used_))
                              for e in after])
    theta_a = multi.trial_theta_
    # each trial's own variance: the part every trial shares (the marker set's placement, the markers'
    # disagreement) cancels in a difference of two trials
    var_a = np.einsum("kpp->kp", multi.trial_cov_ - getattr(multi, "trial_shared_", 0.0))
    sd_within = np.sqrt(var_a)
    shared_a = np.einsum("kpp->kp", getattr(multi, "trial_shared_", np.zeros_like(multi.trial_cov_)))
    K = len(TRIALS)
    z = {
        "before": pairwise_z(theta_b, sd_b),
        "per_marker_weights_no_between_trial": pairwise_z(theta_a, sd_within),
        "after_normal": pairwise_z(theta_a, trial_sd(var_a, multi.tau2_, K, t=False)),
        "after": pairwise_z(theta_a, multi.trial_sd_),
        "after_pm": pairwise_z(theta_a, multi_pm.trial_sd_),
        "after_leave_pair_out_normal": leave_pair_out_z(theta_a, var_a, "dl", t=False),
        "after_leave_pair_out": leave_pair_out_z(theta_a, var_a, "dl", t=True),
        "after_leave_pair_out_pm_normal": leave_pair_out_z(theta_a, var_a, "pm", t=False),
        "after_leave_pair_out_pm": leave_pair_out_z(theta_a, var_a, "pm", t=True),
        "after_prior": pairwise_z(theta_a, multi_prior.trial_sd_),
        "after_leave_pair_out_prior": leave_pair_out_z(theta_a, var_a, "prior", unit_artefact=unit_artefact),
    }
    refs = {k: osim_lengths(DATA / "Models" / f) for k, f in REFERENCES.items()}

    def joint_table(m):
        out = {}
        for p, n in enumerate(names):
            mean, s = float(m.theta_[p]), float(m.posterior_.sd[p])
            out[n] = {"mean": mean, "sd": s, "ci95": [mean - Z * s, mean + Z * s],
                      "sd_within_trials": float(np.sqrt(m.cov_within_[p, p])),
                      "sd_between_trials": float(np.sqrt(m.tau2_[p])), "t_dof": float(m.dof_[p])}
            for k, ref in refs.items():
                out[n][f"{k}_mm"] = ref[n]
                out[n][f"{k}_minus_joint"] = ref[n] - mean
                out[n][f"{k}_inside"] = bool(abs(ref[n] - mean) <= Z * s)
        return out

    trials = {}
    for k, t in enumerate(TRIALS):
        trials[t] = {
            "frames": int(datas[k].n_frames), "stride": strides[k], "rate_hz": datas[k].rate,
            "before": {n: {"mean": float(theta_b[k, p]), "sd": float(sd_b[k, p])} for p, n in enumerate(names)},
            "after": {n: {"mean": float(theta_a[k, p]), "sd_within": float(sd_within[k, p]),
                          "sd_shared": float(np.sqrt(max(shared_a[k, p], 0.0))),
                          "sd": float(multi_prior.trial_sd_[k, p]), "sd_dl": float(multi.trial_sd_[k, p]),
                          "t_dof_dl": float(multi.trial_dof_[k, p])}
                      for p, n in enumerate(names)},
            # leave-one-marker-out of the per-marker-noise fit: leverage-corrected (CR2) sd, the
            # uncorrected jackknife's, and the marker whose deletion moves the estimate most
            "jackknife": {n: {key: v[key] for key in ("sd", "sd_uncorrected", "sd_white_noise", "sd_added",
                                                      "most_influential_marker", "shift") if key in v}
                          for n, v in after[k].jackknife_.get("parameters", {}).items()},
            "sigma_pooled": before[k].sigma_,
            "sigma_per_marker_median": float(np.nanmedian(after[k].marker_sigma_)),
            "sigma_per_marker_range": [float(np.nanmin(after[k].marker_sigma_)),
                                       float(np.nanmax(after[k].marker_sigma_))],
            "timing": timing[t],
        }
    summ = {k: z_summary(v) for k, v in z.items()}
    # pairs of trials of one activity (walking1, walking2): what repeat trials of one movement say
    act = [t.rstrip("0123456789").lower() for t in TRIALS]
    i, j = np.triu_indices(K, 1)
    same = np.array([act[a] == act[b] for a, b in zip(i, j, strict=True)])
    summ_same = {k: z_summary(v[same]) for k, v in z.items()} if same.any() else {}
    sb, sa, slpo = summ["before"], summ["after_prior"], summ["after_leave_pair_out_prior"]
    sdl, sdl_lpo = summ["after"], summ["after_leave_pair_out"]
    return {
        "benchmark": "real_calibration",
        "data": "../shared/data/addbio-subject4 (six trials of one subject)",
        "model": str(MODEL.relative_to(ROOT)),
        "parameters": names,
        "reduced": any(k > 1 for k in strides),
        "max_frames": max_frames,
        "frames_per_trial": {t: int(d.n_frames) for t, d in zip(TRIALS, datas, strict=True)},
        "fraction_consistent_before": sb["fraction_consistent"],
        "fraction_consistent": sa["fraction_consistent"],
        "fraction_consistent_leave_pair_out": slpo["fraction_consistent"],
        "sd_z_before": sb["sd_z"],
        "sd_z": sa["sd_z"],
        "sd_z_leave_pair_out": slpo["sd_z"],
        "fraction_consistent_dl": sdl["fraction_consistent"],
        "sd_z_dl": sdl["sd_z"],
        "fraction_consistent_leave_pair_out_dl": sdl_lpo["fraction_consistent"],
        "sd_z_leave_pair_out_dl": sdl_lpo["sd_z"],
        "z": summ,
        # the spread of the sd of z itself with honest intervals of the reported widths
        "honest_band": {"before": honest_band(sd_b, sb["sd_z"]),
                        "after": honest_band(multi_prior.trial_sd_, sa["sd_z"])},
        "z_by_parameter": {n: {k: z_summary(v[:, p]) for k, v in z.items()} for p, n in enumerate(names)},
        "z_within_activity": summ_same,
        "within_activity_pairs": [f"{TRIALS[a]}-{TRIALS[b]}" for a, b, s_ in zip(i, j, same, strict=True) if s_],
        "trial_status": trial_status(multi_prior, names),
        "tau_mm": {n: float(np.sqrt(multi.tau2_[p])) for p, n in enumerate(names)},
        "tau_mm_pm": {n: float(np.sqrt(multi_pm.tau2_[p])) for p, n in enumerate(names)},
        "tau_mm_prior": {n: float(np.sqrt(multi_prior.tau2_[p])) for p, n in enumerate(names)},
        "tau_prior_scale_mm": {n: float(multi_prior.tau_prior_scale_[p]) for p, n in enumerate(names)},
        "consistency_test": multi.consistency_,
        "joint": joint_table(multi),
        "joint_pm": joint_table(multi_pm),
        "joint_prior": joint_table(multi_prior),
        "trials": trials,
        "seconds": {"multi_trial_combination_wall": round(t_multi, 1), "multi_trial_combination_cpu": round(c_multi, 1),
                    "total_wall": round(time.perf_counter() - wall0, 1),
                    "total_cpu_this_run": round(time.process_time() - cpu0, 1),
                    "trial_fits_cpu": round(sum(v["before_cpu_s"] + v["after_cpu_s"] for v in timing.values()), 1)},
        "load_average": {"start": list(load_start), "end": list(os.getloadavg()), "cores": os.cpu_count()},
        "provenance": provenance(),
    }


def markdown(res: dict) -> str:
    names = res["parameters"]
    L = ["# Cross-trial consistency on addbio-subject4", ""]
    if res["reduced"]:
        L += [f"**Reduced run**: trials decimated to at most {res['max_frames']} frames (every k-th frame; "
              "strides below). Per-trial intervals are wider than on the full trials.", ""]
    else:
        L += ["Full run: every frame of every trial (" + ", ".join(
            f"{t} {n}" for t, n in res["frames_per_trial"].items()) + ").", ""]
    L += [f"Model `{res['model']}` (hinge knees; unknowns: {', '.join(names)}). "
          f"Pairs of trials x parameters: {res['z']['before']['n_pairs']}. "
          "z = difference of two trials' estimates / sqrt(sd_a^2 + sd_b^2), sd = the interval's half-width / 1.96.",
          "", "| intervals | fraction of pairs with abs(z) <= 1.96 | sd of z | rms z |", "|---|---|---|---|"]
    labels = {"before": "before: each trial alone, today's single-trial defaults (pooled noise, marker jackknife, "
                        "placement sd for static-informed parameters)",
              "per_marker_weights_no_between_trial": "per-marker noise, each trial's own variance (without the part "
                                                     "all trials share), no between-trial term",
              "after_normal": "per-marker noise + DL tau^2 (in-sample), normal quantile",
              "after": "per-marker noise + DL tau^2 (in-sample), t quantile (Satterthwaite)",
              "after_pm": "after with Paule-Mandel tau^2 (in-sample), t quantile",
              "after_leave_pair_out_normal": "DL tau^2 from the other four trials, normal quantile",
              "after_leave_pair_out": "DL tau^2 from the other four trials, t quantile (out of sample)",
              "after_leave_pair_out_pm_normal": "PM tau^2 from the other four trials, normal quantile",
              "after_leave_pair_out_pm": "PM tau^2 from the other four trials, t quantile",
              "after_prior": "**after** (reported, the default): half-normal prior on tau, in-sample posterior",
              "after_leave_pair_out_prior": "**half-normal prior on tau, posterior from the other four trials** "
                                            "(out of sample)"}
    for k, lab in labels.items():
        if k not in res["z"]:
            continue
        s = res["z"][k]
        L.append(f"| {lab} | {s['fraction_consistent']:.2f} | {s['sd_z']:.2f} | {s['rms_z']:.2f} |")
    if res.get("z_within_activity"):
        w = res["z_within_activity"]
        L += ["", "Within one activity (" + ", ".join(res["within_activity_pairs"]) + "; "
              f"{w['before']['n_pairs']} pair x parameter values): rms z before "
              f"{w['before']['rms_z']:.2f}, per-marker noise without a between-trial term "
              f"{w['per_marker_weights_no_between_trial']['rms_z']:.2f}, after (reported) "
              f"{w['after_prior']['rms_z']:.2f}; fraction within 1.96: {w['before']['fraction_consistent']:.2f}, "
              f"{w['per_marker_weights_no_between_trial']['fraction_consistent']:.2f}, "
              f"{w['after_prior']['fraction_consistent']:.2f}."]
    if res.get("trial_status"):
        off = [f"{t} ({', '.join(n for n, v in row.items() if not v['contributes'])})"
               for t, row in res["trial_status"].items() if not all(v["contributes"] for v in row.values())]
        L += ["", "Trials that leave a parameter unidentified by motion (status 'placement', 'poor', ...) and "
              "contribute nothing to it in the joint estimate: " + ("; ".join(off) if off else "none") + "."]
    L += ["", "Targets: fraction >= 0.90, sd of z 0.8-1.3.", ""]
    if "honest_band" in res:
        hb = res["honest_band"]

        def band(k):
            q = hb[k]["sd_z_quantiles"]
            return (f"{q['0.05']:.2f}-{q['0.95']:.2f} (median {q['0.5']:.2f}); an sd of z at or below the "
                    f"observed {res['z'][dict(before='before', after='after_prior')[k]]['sd_z']:.2f} in "
                    f"{hb[k]['p_sd_z_at_most_observed']:.2f} of them")

        L += ["How far the sd of z can stray with honest intervals: the 60 pairs come from 6 trials and "
              "are far from independent. Drawing each trial's estimates from normal laws with the reported "
              "sds (20 000 draws) gives a 90 % range for the sd of z of " + band("after") + " (after); "
              + band("before") + " (before).", ""]
    L += [
          "Why a t quantile: the between-trial variance of a pair left out is estimated from four trials, "
          "about three degrees of freedom; when it dominates a trial's variance, the difference standardised "
          "by it follows roughly Student t_3 (sd sqrt(3) = 1.73) rather than a normal law, even with honest "
          "intervals (the cause of the sd of z of 1.67 in an earlier reduced run, at 40 frames per trial, "
          "where tau reached 9 mm against within-trial sds of 1-3 mm). The estimator's intervals use a t "
          "quantile with Satterthwaite's effective degrees of freedom (normal when tau^2 = 0, t_{K-1} when "
          "tau^2 dominates): a general rule of random-effects meta-analysis, not tuned to this subject. "
          f"In this run the largest tau is {max(res['tau_mm'].values()):.2f} mm against within-trial sds of "
          f"{min(min(r['after'][n]['sd_within'] for n in names) for r in res['trials'].values()):.1f}-"
          f"{max(max(r['after'][n]['sd_within'] for n in names) for r in res['trials'].values()):.0f} mm, "
          "so the t and normal rows nearly coincide. The in-sample rows reuse the trials that estimated "
          "tau^2 and are optimistic; the leave-pair-out rows are the out-of-sample check.", ""]
    if "tau_prior_scale_mm" in res:
        sc, tp = res["tau_prior_scale_mm"], res["tau_mm_prior"]
        L += ["Half-normal prior on tau (`between_trial='prior'`, the estimator's default): its scale is "
              "the sd that a 10 mm root-mean-square skin-marker artefact would add to one trial's estimate, "
              f"here {min(sc.values()):.1f}-{max(sc.values()):.1f} mm; the posterior mean of tau is "
              f"{min(tp.values()):.1f}-{max(tp.values()):.1f} mm (DL: {min(res['tau_mm'].values()):.1f}-"
              f"{max(res['tau_mm'].values()):.1f} mm). Where DL's tau is 0 the posterior keeps some spread, so "
              "these intervals are a little wider than DL's.", ""]
    L += ["## By parameter", "", "| parameter | tau DL / PM / prior posterior (mm) | before: fraction, sd z | "
          "after: fraction, sd z | "
          "leave pair out (prior): fraction, sd z |", "|---|---|---|---|---|"]
    for n in names:
        b, a, lpo = (res["z_by_parameter"][n][k] for k in ("before", "after_prior", "after_leave_pair_out_prior"))
        L.append(f"| {n} | {res['tau_mm'][n]:.2f} / {res['tau_mm_pm'][n]:.2f} / {res['tau_mm_prior'][n]:.2f} | "
                 f"{b['fraction_consistent']:.2f}, {b['sd_z']:.2f} | "
                 f"{a['fraction_consistent']:.2f}, {a['sd_z']:.2f} | {lpo['fraction_consistent']:.2f}, "
                 f"{lpo['sd_z']:.2f} |")
    c = res["consistency_test"]
    verdict = (f"{c['statistic']:.1f} on {c['dof']} degrees of freedom, p = {c['p_value']:.2g}"
               if c.get("p_value") is not None else "not tested (fewer than one degree of freedom)")
    L += ["", f"Chi-square consistency of the per-trial estimates against the joint one: {verdict}.", "",
          "## Per trial (mm): before (pooled noise) mean ± sd; after mean ± sd (the between-trial prior's "
          "posterior included)", "",
          "| trial | frames (stride) | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    for t, row in res["trials"].items():
        cells = [f"{row['before'][n]['mean']:.1f} ± {row['before'][n]['sd']:.2f}; "
                 f"{row['after'][n]['mean']:.1f} ± {row['after'][n]['sd']:.2f}" for n in names]
        L.append(f"| {t} | {row['frames']} ({row['stride']}) | " + " | ".join(cells) + " |")
    if any(row.get("jackknife") for row in res["trials"].values()):
        L += ["", "## Leave-one-marker-out per trial (per-marker noise fits; mm)", "",
              "Each cell: the leverage-corrected (CR2) jackknife sd / the uncorrected jackknife's sd; the "
              "marker whose deletion moves the estimate most, and by how much. A marker that alone carries "
              "most of the information about a length (a heel marker fixing the ankle in a squat) has a "
              "large uncorrected replicate that mostly measures the fit without it; CR2 scales it by the "
              "square root of the information that deletion keeps.", "",
              "| trial | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
        for t, row in res["trials"].items():
            jk = row.get("jackknife") or {}
            cells = [(f"{jk[n]['sd']:.2f} / {jk[n].get('sd_uncorrected', float('nan')):.2f}; "
                      f"{jk[n]['most_influential_marker']} {jk[n]['shift']:+.1f}") if n in jk else "n/a"
                     for n in names]
            L.append(f"| {t} | " + " | ".join(cells) + " |")
    for key, title in (("joint_prior", "half-normal prior on tau, the default"), ("joint", "DerSimonian-Laird tau^2"),
                       ("joint_pm", "Paule-Mandel tau^2")):
        if key not in res:
            continue
        L += ["", f"## Joint estimate (all six trials, one geometry; {title}) against the OpenSim scalings (mm)", "",
              "| parameter | joint mean [95 % interval] | within / between sd | t dof | AddBiomechanics | expert "
              "| generic |", "|---|---|---|---|---|---|---|"]
        for n in names:
            j = res[key][n]

            def ref(k, j=j):
                return f"{j[k + '_mm']:.1f} ({j[k + '_minus_joint']:+.1f}{', inside' if j[k + '_inside'] else ''})"

            L.append(f"| {n} | {j['mean']:.1f} [{j['ci95'][0]:.1f}, {j['ci95'][1]:.1f}] | "
                     f"{j['sd_within_trials']:.2f} / {j['sd_between_trials']:.2f} | {j['t_dof']:.1f} | "
                     f"{ref('addbiomechanics')} | {ref('expert')} | {ref('generic')} |")
    sec, la = res["seconds"], res["load_average"]
    L += ["", "The OpenSim lengths run between their joint frames (hip centre to the knee frame, knee frame "
          "to the talus frame); this model's knee and ankle lie midway between the epicondyle and malleolus "
          "markers, so a few millimetres of difference are a matter of definition.", "",
          "## Time", "", "| trial | frames | before: wall / CPU s | after: wall / CPU s |", "|---|---|---|---|"]
    for t, row in res["trials"].items():
        tm = row["timing"]
        L.append(f"| {t} | {row['frames']} | {tm['before_wall_s']} / {tm['before_cpu_s']} | "
                 f"{tm['after_wall_s']} / {tm['after_cpu_s']} |")
    L += ["", f"Trial fits {sec['trial_fits_cpu']} CPU s in all (cached fits keep the CPU seconds of the run "
          f"that made them); multi-trial combination {sec['multi_trial_combination_wall']} s wall, "
          f"{sec['multi_trial_combination_cpu']} s CPU; this run {sec['total_wall']} s wall, "
          f"{sec['total_cpu_this_run']} s CPU. Load average at start {la['start'][0]:.2f}, at end "
          f"{la['end'][0]:.2f} on {la['cores']} cores (shared machine).",
          f"Commit {res['provenance']['commit'][:10]}, {res['provenance']['date']}.", ""]
    return "\n".join(L)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-frames", type=int, default=None, help="decimate longer trials (default: all frames)")
    ap.add_argument("--out", default=str(results_dir() / "real_calibration"))
    ap.add_argument("--cache", default="/tmp/skelid-real-calibration", help="folder for the per-trial fits")
    ap.add_argument("--refit", action="store_true", help="ignore cached per-trial fits")
    ap.add_argument("--markdown-only", action="store_true", help="rewrite the .md from the .json and stop")
    ap.add_argument("--fits-only", choices=["pooled", "per_marker"], default=None,
                    help="only fill the cache with this mode's per-trial fits, then stop")
    args = ap.parse_args(argv)
    cache = Path(args.cache)
    if args.refit and cache.exists():
        for f in cache.glob("*.pkl"):
            f.unlink()
    if args.markdown_only:
        out = Path(args.out)
        rewrite_markdown(out, markdown)
        return
    if args.fits_only:
        fits_only(args.max_frames, cache, args.fits_only)
        return
    res = run(args.max_frames, cache)
    out = Path(args.out)
    write_results(out, res, markdown)


if __name__ == "__main__":
    main()
