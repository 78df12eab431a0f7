"""Monte Carlo accuracy study: bias, spread, RMSE against the Cramér-Rao bound, coverage.

Cells: cases A and B x sigma in {5, 15} mm x true L2 near each end and in the
middle of the prior interval x i.i.d. and soft-tissue-artefact noise; 500
frames. Methods:

* ``paper``   the seed method (per-frame Newton-Raphson + grid Bayes filter);
* ``profile`` joint least squares over L2 and every pose, no motion model, no correction;
* ``laplace`` grid filter with the Laplace-marginal likelihood (poses integrated out);
* ``final``   the default ``marker`` estimator (motion model, noise level estimated);
* cells ``straight`` and ``folded`` (``--noises straight folded``): i.i.d. noise with
  every revolute joint kept near the poses where the markers across a joint line up
  (the second-order bias expansion is least accurate there), on a geometry drawn for
  each trial (:func:`drawn_model`: the upper arm's length, every marker's place, the
  true L2 in 210-290 mm, each joint's own range of motion near 0 or 180 degrees;
  ``POSTURE_DRAWS``), so that no rule can be fitted to one geometry (``--truths`` is
  ignored; the rows' ``truth`` is 0);
* cell ``coupled`` (``--noises coupled``): a thigh and shank whose knee is a coupled
  (``custom``) joint whose centre slides with flexion (by ``MOVING_CENTRE`` (q^2/2, q/2) mm,
  q the flexion in radians, 0-90 degrees), fitted with a hinge whose centre (x, y) is
  unknown; the truth is the centre at zero flexion, rows ``final:1`` give the second
  coordinate; the rows count how often the model-misfit warning fired;
* ``final-artefact`` the same with the soft-tissue artefact's size stated
  (``artefact_rms``: the simulator's expected rms displacement of a marker
  coordinate, :func:`skelid.simulate.sta_rms`); soft-tissue cells only;
* ``final-4hz`` the default estimator with its motion model's cutoff fixed at 4 Hz (``auto`` chooses
  at least 6 Hz): how much of the error beyond the bound the pose noise that the motion model lets
  through causes (the simulated motion has no content above 1.5 Hz);
* ``final-nofloor`` the default estimator with ``auto``'s per-coordinate cutoffs (twice the
  cross-validated one) not raised to its 6 Hz floor (``MIN_AUTO_CUTOFF``; 2-4 Hz on these cells).

``crlb`` is the Cramér-Rao bound with every pose unknown, at the true poses and
the true sigma. Each run's rows carry a ``tag``: the default, ``current``, is the
current code's table and is written cell by cell to ``benchmarks/results/accuracy.json``
and ``accuracy.md``; any other tag (``--tag before`` for a run of the code before a
change, a variant of a method) is an experiment and goes to
``benchmarks/experiments/accuracy.json`` and ``.md``, where the earlier tags are kept. A
re-run skips the cells of its tag already there (``--fresh`` starts over). Each cell
records the commit, the CPU seconds of all its processes, its wall time and the load
average when it ended; the file its provenance (:func:`_common.provenance`). ``--jobs 2``
fits in this process and one worker.

    python benchmarks/accuracy.py --reps 100 --jobs 2
    python benchmarks/accuracy.py --noises folded straight --methods final --reps 20
    python benchmarks/accuracy.py --cases case-a --sigmas 1 5 --noises coupled --methods final --reps 20
    python benchmarks/accuracy.py --frames-study --reps 20
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import experiments_dir, git_commit, results_dir, rows_of, with_provenance, write_json  # noqa: E402

#: the tag of the default run: the current code's table, written to ``benchmarks/results``; any other tag is an
#: experiment or ablation and goes to ``benchmarks/experiments`` (the record of every earlier tag is kept there)
DEFAULT_TAG = "current"
CASES = ("case-a", "case-b")
SIGMAS = (5.0, 15.0)
TRUTHS = (210.0, 250.0, 290.0)
NOISES = ("iid", "sta")
#: where the drawn geometry's joints move: each revolute joint's own range, centred at a draw from
#: ``centre`` with a half-width drawn from ``half`` (degrees); straight = 0, folded = 180
POSTURE_DRAWS = {"straight": {"centre": (0.0, 20.0), "half": (5.0, 12.5)},
                 "folded": {"centre": (146.0, 166.0), "half": (5.0, 12.0)}}
#: the drawn L2's range (mm), inside the prior's 200-300 mm
DRAWN_L2 = (210.0, 290.0)
#: i.i.d. noise with every revolute joint kept near a singular pose (markers across it nearly in line)
POSTURES = tuple(POSTURE_DRAWS)

METHODS = ("paper", "profile", "laplace", "final")
Z95 = 1.959964
CHUNK = 20  # trials between two writes of a cell's rows
EXTRA_METHODS = ("final-artefact", "final-4hz", "final-nofloor")


def one_trial(args):
    """Fit every method to one simulated trial; returns estimates, intervals, bound."""
    case, sigma, truth, noise, rep, n_frames, methods = args
    cpu0 = time.process_time()
    warnings.simplefilter("ignore")
    from threadpoolctl import threadpool_limits

    threadpool_limits(1, user_api="blas")  # a fit's small factorisations only slow down with more threads
    from skelid.errors import SkelidError
    from skelid.estimators.fit.likelihood import crlb_sd, efficient_information, frame_terms
    from skelid.estimators.marker import MarkerEstimator
    from skelid.estimators.online.grid import MarkerGridFilter
    from skelid.estimators.paper import PaperFilter
    from skelid.simulate import builtin_model, simulate, sta_rms

    model = knee_model(coupled=False) if noise == "coupled" else builtin_model(case)
    seed = [CASES.index(case), int(sigma), int(truth), (NOISES + tuple(POSTURES) + ("coupled",)).index(noise), rep]
    if noise == "coupled":
        trial = coupled_knee_trial(model, n_frames, sigma, np.random.default_rng(seed))
    elif noise in POSTURES:
        trial = singular_trial(case, n_frames, sigma, noise, np.random.default_rng(seed))
        model = trial.model
    else:
        trial = simulate(model, theta=[truth], n_frames=n_frames, sigma=sigma, noise=noise,
                         sta_amplitude=10.0, rng=np.random.default_rng(seed))
    _, Jq, Jt = frame_terms(model, trial.theta, trial.pose, trial.clean)
    bounds = crlb_sd(efficient_information(Jq, Jt, sigma))
    bound = float(bounds[0])
    out = {"crlb": bound, "crlb_all": bounds.tolist(), "truth_all": [float(v) for v in trial.theta]}
    if noise == "iid" or noise in POSTURES:  # Gaussian noise: the exact linear term is a control variate
        out["linear_all"] = linear_term(model, trial).tolist()
        out["linear"] = out["linear_all"][0]
    centre = float(model.theta_center[0])
    for name in methods:
        t0 = time.perf_counter()
        try:
            if name == "paper":
                est = PaperFilter(model).fit(trial.data)
                post, dropped = est.posterior_, int((~est.frames_used_).sum())
            elif name == "profile":
                est = MarkerEstimator(model, cutoff=None, bias_correction="none", robust="never")
                est.fit(trial.data)
                post, dropped = est.posterior_, int((~est.frames_used_).sum())
                centre = float(est.theta_[0])
            elif name == "laplace":
                half = 8 * max(bound, 0.5)
                axes = (np.linspace(centre - half, centre + half, 41),) if "profile" in out \
                    and "est" in out["profile"] else None  # no profile estimate: the whole prior grid
                est = MarkerGridFilter(model, axes=axes, likelihood="laplace").fit(trial.data)
                post, dropped = est.posterior_, int((~est.frames_used_).sum())
            elif name == "final-4hz":
                est = MarkerEstimator(model, cutoff=4.0).fit(trial.data)
                post, dropped = est.posterior_, int((~est.frames_used_).sum())
            elif name == "final-nofloor":
                import skelid.estimators.marker as marker_module

                floor, marker_module.MIN_AUTO_CUTOFF = marker_module.MIN_AUTO_CUTOFF, 0.0
                try:
                    est = MarkerEstimator(model).fit(trial.data)
                finally:
                    marker_module.MIN_AUTO_CUTOFF = floor
                post, dropped = est.posterior_, int((~est.frames_used_).sum())
            elif name == "final-artefact":
                rms = sta_rms(model, 10.0) if noise == "sta" else 0.0
                est = MarkerEstimator(model, artefact_rms=rms or None).fit(trial.data)
                post, dropped = est.posterior_, int((~est.frames_used_).sum())
            else:
                est = MarkerEstimator(model).fit(trial.data)
                post, dropped = est.posterior_, int((~est.frames_used_).sum())
            ci = post.credible_interval(0.95)
            out[name] = {"est": float(post.mean[0]), "lo": float(ci[0, 0]), "hi": float(ci[0, 1]),
                         "dropped": dropped, "seconds": time.perf_counter() - t0,
                         "est_all": post.mean.tolist(), "lo_all": ci[:, 0].tolist(), "hi_all": ci[:, 1].tolist()}
            if isinstance(est, MarkerEstimator):
                out[name].update(profile=float(est.theta_profile_[0]), bias=float(est.bias_[0]),
                                 bias_method=est.bias_method_, flags=sorted({w.code for w in est.warnings_}))
        except SkelidError as exc:
            out[name] = {"error": exc.one_line(), "dropped": n_frames}
    out["cpu"] = time.process_time() - cpu0
    return out


def linear_term(model, trial) -> np.ndarray:
    """The estimate's error to first order in this trial's noise, at the truth: ``(P,)``.

    ``l = S^{-1} sum_t K_t^T e_t`` (every pose free; :func:`skelid.estimators.uncertainty.bootstrap.linear_response`
    without a motion model) for the noise ``e = y - f(theta, q)`` the simulator drew. It is linear in
    Gaussian noise, so its mean is exactly zero and its variance exactly the bound, ``crlb^2``: a
    control variate for the Monte Carlo means. The estimator's error ``err`` is ``l`` plus a rest
    (bias, higher-order terms) that varies far less, so ``mean(err - l)`` estimates the bias with a
    Monte Carlo error several times below ``sd(err) / sqrt(n)``, and the mean squared error likewise
    (:func:`controlled`; ``summarise``: ``bias_cv``, ``rmse_cv``).
    """
    from skelid.estimators.uncertainty.bootstrap import linear_response

    noise = trial.data.positions - trial.clean
    return linear_response(model, trial.clean, trial.theta, trial.pose, noise[None]).theta[0]


#: how far the coupled knee's centre slides: (x, y) = MOVING_CENTRE * (q^2 / 2, q / 2), q the flexion (rad)
MOVING_CENTRE = 10.0


def knee_model(coupled: bool):
    """Thigh (free) and shank; the knee a hinge whose centre (x, y) is unknown, or a coupled joint
    (``custom``, as an OpenSim knee) whose centre slides with flexion and has no unknowns."""
    from skelid.model.description import model_from_dict

    mc = MOVING_CENTRE
    hinge = {"name": "knee", "type": "hinge", "axis": [0.0, 0.0, 1.0], "position": [0.0, -400.0, 0.0],
             "range": [0.0, 100.0]}
    poly = {"type": "polynomial"}
    custom = {"name": "knee", "type": "custom", "position": [0.0, -400.0, 0.0], "coordinates": ["flex"],
              "motions": [
                  {"kind": "translation", "axis": [1, 0, 0], "coordinate": "flex",
                   "function": dict(poly, coefficients=[mc / 2, 0.0, 0.0])},
                  {"kind": "translation", "axis": [0, 1, 0], "coordinate": "flex",
                   "function": dict(poly, coefficients=[mc / 2, 0.0])},
                  {"kind": "rotation", "axis": [0, 0, 1], "coordinate": "flex",
                   "function": {"type": "linear", "coefficients": [1.0, 0.0]}}]}
    spec = {"model": {"name": "knee", "dim": 3, "units": "mm"},
            "segments": [{"name": "thigh", "parent": "ground",
                          "joint": {"name": "hip", "type": "free", "position": [0.0, 0.0, 0.0]}},
                         {"name": "shank", "parent": "thigh", "joint": custom if coupled else hinge}],
            "markers": [{"name": n, "segment": seg, "position": p} for n, seg, p in (
                ("T1", "thigh", [60.0, -100.0, 20.0]), ("T2", "thigh", [-40.0, -250.0, 50.0]),
                ("T3", "thigh", [50.0, -350.0, -40.0]), ("S1", "shank", [50.0, -80.0, 40.0]),
                ("S2", "shank", [-30.0, -200.0, 50.0]), ("S3", "shank", [40.0, -330.0, -40.0]))]}
    if not coupled:
        spec["parameters"] = [{"name": "knee", "kind": "joint_centre", "joint": "knee", "axes": ["x", "y"],
                               "prior": {"type": "uniform", "lower": -40.0, "upper": 40.0}}]
    return model_from_dict(spec)


def coupled_knee_trial(model, n_frames, sigma, rng):
    """Markers of the coupled knee (flexion 0-90 degrees), to be fitted with the hinge ``model``.

    The truth for the hinge's centre is the coupled knee's centre at zero flexion, (0, 0). The misfit
    test's power and false alarms under noise, the source's own knee and the moving-centre refit are
    studied at 100 trials per cell in ``benchmarks/model_mismatch.py``."""
    from skelid.data import MarkerData
    from skelid.model.kinematics import marker_positions
    from skelid.simulate import Trial, simulate_motion

    pose = simulate_motion(model, n_frames, 100.0, rng)
    k = [i for i, d in enumerate(model.dofs) if d.segment == 1][0]
    u = (pose[:, k] - pose[:, k].min()) / max(float(np.ptp(pose[:, k])), 1e-12)
    pose[:, k] = np.radians(90.0) * u
    clean = marker_positions(knee_model(coupled=True), np.zeros(0), pose)
    noisy = clean + rng.normal(0.0, sigma, size=clean.shape)
    return Trial(model, MarkerData(noisy, model.marker_names, 100.0, model.units, source="simulated"),
                 np.zeros(model.n_params), pose, clean)


def drawn_model(case: str, rng):
    """Case A or B with its geometry drawn: the upper arm's length, and every marker's place.

    Upper arm 250-350 mm; each marker at 30-70 % of its element's length (the hand's at 50-110 mm) and
    10-40 mm off its long axis, on opposite sides across each joint as in the built-in models (so that
    the markers across a joint line up near its singular poses), the whole arm mirrored at random. The
    forearm's nominal length stays at the built-in model's (the truth is drawn apart: ``DRAWN_L2``)."""
    import tomllib
    from importlib import resources

    from skelid.model.description import model_from_dict
    from skelid.simulate import BUILTIN_MODELS

    spec = tomllib.loads((resources.files("skelid") / "models" / BUILTIN_MODELS[case]).read_text())
    upper = rng.uniform(250.0, 350.0)
    spec["segments"][1]["joint"]["position"] = [upper, 0.0]
    along = {"upper_arm": upper, "forearm": 250.0, "hand": 160.0}
    side = rng.choice([-1.0, 1.0])
    for m in spec["markers"]:
        sign = side * np.sign(m["position"][1])  # the built-in model's side, mirrored as a whole
        m["position"] = [rng.uniform(0.3, 0.7) * along[m["segment"]], sign * rng.uniform(10.0, 40.0)]
    return model_from_dict(spec, f"{case} (drawn geometry)")


def singular_trial(case, n_frames, sigma, posture, rng):
    """A trial of a drawn geometry (:func:`drawn_model`, ``DRAWN_L2``) whose revolute joints each move
    through their own drawn range near the straight or folded pose (``POSTURE_DRAWS``)."""
    from skelid.data import MarkerData
    from skelid.model.kinematics import marker_positions
    from skelid.simulate import Trial, simulate_motion

    model = drawn_model(case, rng)
    theta = np.array([rng.uniform(*DRAWN_L2)])
    pose = simulate_motion(model, n_frames, 100.0, rng)
    draw = POSTURE_DRAWS[posture]
    for k, d in enumerate(model.dofs):
        if d.kind == "R" and model.segments[d.segment].joint.type in ("revolute", "hinge"):
            centre, half = rng.uniform(*draw["centre"]), rng.uniform(*draw["half"])
            u = (pose[:, k] - pose[:, k].min()) / max(float(np.ptp(pose[:, k])), 1e-12)
            pose[:, k] = np.radians(centre + half * (2.0 * u - 1.0))
    clean = marker_positions(model, theta, pose)
    noisy = clean + rng.normal(0.0, sigma, size=clean.shape)
    return Trial(model, MarkerData(noisy, model.marker_names, 100.0, model.units, source="simulated"),
                 theta, pose, clean)


def controlled(err, lin, var_lin: float):
    """Bias and RMSE of errors ``err (n,)`` with the control variate ``lin (n,)`` of known variance.

    ``lin`` has mean zero and variance ``var_lin`` exactly (:func:`linear_term`); with ``d = err - lin``,
    bias ``= mean(d)`` and ``mse = var_lin + var(d) + 2 cov(lin, d) + mean(d)^2`` (sample moments): where
    ``err`` is ``lin`` plus a constant, both are exact whatever the draws. The RMSE's standard error is the
    jackknife's over the trials.

    Returns
    -------
    bias, bias_se, rmse, rmse_se : float
    """
    err, lin = np.asarray(err, float), np.asarray(lin, float)
    n = len(err)

    def rmse(e, x):
        d = e - x
        c = np.cov(x, d)
        return float(np.sqrt(max(var_lin + c[1, 1] + 2.0 * c[0, 1] + d.mean() ** 2, 0.0)))

    d = err - lin
    keep = ~np.eye(n, dtype=bool)
    jack = np.array([rmse(err[k], lin[k]) for k in keep])
    return (float(d.mean()), float(d.std(ddof=1) / np.sqrt(n)), rmse(err, lin),
            float(np.sqrt((n - 1) / n * np.sum((jack - jack.mean()) ** 2))))


def controlled_coverage(covered, lin, crlb):
    """Coverage of intervals ``covered (n,) bool`` with the control variate ``|l| <= Z95 crlb``.

    For Gaussian noise ``l ~ N(0, crlb^2)`` exactly, so the variate's mean is exactly 0.95; the
    coverage less ``beta`` times the variate's excess (``beta`` from the regression of one indicator
    on the other) has the same mean and less Monte Carlo error where the intervals follow ``l``.

    Returns
    -------
    coverage, se : float
    """
    c = np.asarray(covered, float)
    v = (np.abs(np.asarray(lin, float)) <= Z95 * np.asarray(crlb, float)).astype(float)
    var_v = v.var(ddof=1)
    beta = float(np.cov(c, v)[0, 1] / var_v) if var_v > 0 else 0.0
    adj = c - beta * (v - 0.95)
    return float(adj.mean()), float(adj.std(ddof=1) / np.sqrt(len(adj)))


def summarise(case, sigma, truth, noise, trials, methods, split=True):
    """One row per method (the first parameter); for a model with several, also ``method:k`` rows."""
    rows = []
    n_par = max((len(t[m].get("est_all", [0])) for t in trials for m in methods if "est" in t[m]), default=1)
    n_par = n_par if split else 1
    for k in range(1, n_par):
        alias = [dict(t, **{f"{m}:{k}": dict({c: v for c, v in t[m].items() if c not in ("profile", "bias")},
                                             est=t[m]["est_all"][k], lo=t[m]["lo_all"][k], hi=t[m]["hi_all"][k])
                            if "est" in t[m] else t[m] for m in methods})
                 for t in trials]
        rows += summarise(case, sigma, truth, noise, [dict(a, crlb=a.get("crlb_all", [a["crlb"]] * n_par)[k],
                                                          truth_all=[a.get("truth_all", [truth] * n_par)[k]],
                                                          **({"linear": a["linear_all"][k]} if "linear_all" in a
                                                             else {}))
                                                     for a in alias], [f"{m}:{k}" for m in methods], False)
    bound = float(np.sqrt(np.mean([t["crlb"] ** 2 for t in trials])))
    for name in methods:
        ok = [t[name] for t in trials if "est" in t[name]]
        # the truth a cell's label names, or the one drawn for each trial (drawn geometry: label 0)
        true = np.array([t.get("truth_all", [truth])[0] if truth == 0.0 else truth for t in trials
                         if "est" in t[name]])
        err = np.array([o["est"] for o in ok]) - true
        n = len(err)
        cover = np.mean([o["lo"] <= v <= o["hi"] for o, v in zip(ok, true, strict=True)]) if n else float("nan")
        rmse = float(np.sqrt(np.mean(err**2))) if n else float("nan")
        half = np.array([(o["hi"] - o["lo"]) / 2 for o in ok])
        row = {
            "case": case, "sigma": sigma, "truth": truth, "noise": noise, "method": name,
            "reps": n, "failed": len(trials) - n,
            "bias": float(err.mean()) if n else float("nan"),
            "bias_se": float(err.std(ddof=1) / np.sqrt(n)) if n > 1 else float("nan"),
            "sd": float(err.std(ddof=1)) if n > 1 else float("nan"),
            "rmse": rmse, "crlb": bound, "rmse_over_crlb": rmse / bound,
            "coverage95": float(cover),
            "z_gt3": float(np.mean(np.abs(err) > 3 * half / Z95)) if n else float("nan"),
            "frames_dropped": float(np.mean([t[name]["dropped"] for t in trials])),
            "seconds_per_fit": float(np.mean([o["seconds"] for o in ok])) if n else float("nan"),
        }
        lin = [t["linear"] for t in trials if "est" in t[name] and "linear" in t]
        if n > 2 and len(lin) == n:  # control variate (see linear_term): the same means, less Monte Carlo error
            c2 = np.mean([t["crlb"] ** 2 for t in trials if "est" in t[name]])
            b, b_se, rmse_cv, rmse_se = controlled(err, np.array(lin), c2)
            row.update(bias_cv=b, bias_cv_se=b_se, rmse_cv=rmse_cv, rmse_cv_over_crlb=rmse_cv / bound,
                       rmse_cv_se=rmse_se, linear_mean=float(np.mean(lin)))
            row["coverage95_cv"], row["coverage95_cv_se"] = controlled_coverage(
                [o["lo"] <= v <= o["hi"] for o, v in zip(ok, true, strict=True)], lin,
                [t["crlb"] for t in trials if "est" in t[name]])
        if n and "bias_method" in ok[0]:
            if "profile" in ok[0]:  # first parameter only
                row["profile_bias"] = float(np.mean([o["profile"] for o in ok] - true))
                row["bias_removed"] = float(np.mean([o["bias"] for o in ok]))
            methods_used = [o["bias_method"] for o in ok]
            row["bias_methods"] = {m: methods_used.count(m) for m in sorted(set(methods_used))}
            flags = [f for o in ok for f in o["flags"]]
            row["warnings"] = {f: flags.count(f) for f in sorted(set(flags))}
        rows.append(row)
    return rows


def folder_for(tag: str) -> Path:
    """``benchmarks/results`` for the default tag, ``benchmarks/experiments`` for any other."""
    return results_dir() if tag == DEFAULT_TAG else experiments_dir()


def write(rows, folder: Path, prov: dict | None = None):
    """Merge ``rows`` into ``folder``/accuracy.json (cells other runs wrote meanwhile are kept) and rewrite
    accuracy.md there; ``prov``: the provenance to keep (a rewrite of the tables, ``--report``), else this run's.

    Runs of different cells may write at once: the read-merge-write holds an exclusive lock."""
    import fcntl

    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / ".accuracy.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        _write(rows, folder, prov)


#: later versions compared with tag ``deconvolved``, and what changed
LATER = {"selfconsistent": "a correction above 1.5 sd is evaluated again at the corrected geometry and the "
                           "deconvolved poses, and sent to the bootstrap only when it moves there by more than the "
                           "bootstrap's Monte Carlo error, sd / sqrt(10). Evaluated at the corrected geometry "
                           "only (fitted poses), the same rule kept the expansion in 9 near-straight sigma-15 trials "
                           "(fallback 90 of 100: coverage 0.91, bias 0.68 crlb) and 2 near-folded ones (47: 0.90, "
                           "-0.05 crlb): the poses' share of the change is what flags them",
         "stiffer": "that rule (evaluated at the corrected geometry only), and the graduated-smoothing start "
                    "9 times stiffer than the motion model (was 3; not kept: no gain in coverage on the one "
                    "cell it was run on)",
         "branch": "the branch check (frames on the mirrored branch of a joint that two marker distances fix "
                   "are mirrored and the motion-model fit repeated, kept at a lower penalised cost; "
                   ":func:`skelid.estimators.uncertainty.singular.mirrored_start`); "
                   "the near-straight sigma-5 row of this tag "
                   "is an interrupted run (20 trials)",
         "spread": "the branch check and, where the second-order correction exceeds 0.5 sd on the expansion's "
                   "path, the covariance of the second-order term (64 Gaussian draws, "
                   ":func:`skelid.estimators.uncertainty.singular.quadratic_term_draws`) "
                   "added to the interval (not kept: near the "
                   "straight pose at sigma 15 mm the check mirrored 12-46 % of a trial's frames and kept minima "
                   "tens of mm from the truth, rmse 6.4 crlb)",
         "stretch": "as `spread`, the branch check limited to a joint whose minority side holds at most 10 % of "
                    "the frames (a stretch on the wrong branch, not a motion that straddles the singular pose)",
         "folded6": "the branch check mirrors every joint's minority side at once (frames compared with those "
                    "near the same singular pose) and keeps the refit at a lower penalised cost only when it "
                    "settles every frame on one branch (was: one joint at a time, at most 10 % of the frames); "
                    "where a kept bias correction exceeds 0.25 sd, the sd is evaluated at the interval's ends along "
                    "the parameter's profile and the variance raised to the larger end's "
                    "(:func:`skelid.estimators.uncertainty.singular.profile_sd_ratio`)",
         "folded6b": "as `folded6`, and when the refit of every joint at once is not kept, the earlier rule is "
                     "tried (one joint at a time whose minority side holds at most 10 % of the frames, kept at a "
                     "lower penalised cost; tried, not kept)"}
#: the tag each later tag is compared with (default ``deconvolved``)
BEFORE = {"folded6": "stretch", "folded6b": "stretch"}


def _write_cv(fh, rows):
    """The cells whose trials carry the linear control variate: raw and controlled bias and RMSE."""
    cv = [r for r in rows if "bias_cv" in r and ":" not in r["method"]]
    if not cv:
        return
    fh.write("## Bias and RMSE with the linear control variate\n\n"
             "Each trial's error less its exact first-order term in the simulated noise, ``l`` (mean exactly "
             "zero, variance exactly crlb^2; `benchmarks/accuracy.py::linear_term`): `bias cv` = mean(err - l), "
             "`rmse cv` = sqrt(crlb^2 + var(err - l) + 2 cov(l, err - l) + bias cv^2), "
             "the same quantities as `bias` and `rmse` with a smaller Monte Carlo error (`se`, in crlb). "
             "`coverage cv`: the coverage with the indicator |l| <= 1.96 crlb (mean exactly 0.95) as its "
             "control variate (rows written before it was added have none). "
             "`mean l`: the trials' own mean of ``l`` (crlb), the share "
             "of the raw bias that is luck of the draw. Targets: |bias| <= 0.2 crlb, rmse <= 1.1 crlb, coverage "
             "0.93-0.97.\n\n| tag | case | sigma | truth | noise | method | reps | bias (se) | mean l | bias cv (se) | "
             "rmse | rmse cv (se) | coverage95 (se) | coverage cv (se) |\n|" + "---|" * 14 + "\n")
    for r in cv:
        c, n, p = r["crlb"], max(r["reps"], 1), r["coverage95"]
        fh.write(f"| {r.get('tag')} | {r['case']} | {r['sigma']:g} | {r['truth']:g} | {r['noise']} | {r['method']} | "
                 f"{r['reps']} | {r['bias'] / c:.2f} ({r['bias_se'] / c:.2f}) | {r['linear_mean'] / c:.2f} | "
                 f"{r['bias_cv'] / c:.2f} ({r['bias_cv_se'] / c:.2f}) | {r['rmse_over_crlb']:.2f} | "
                 f"{r['rmse_cv_over_crlb']:.2f} ({r['rmse_cv_se'] / c:.2f}) | "
                 f"{p:.2f} ({np.sqrt(p * (1 - p) / n):.2f}) | "
                 + (f"{r['coverage95_cv']:.2f} ({r['coverage95_cv_se']:.2f}) |\n" if "coverage95_cv" in r
                    else "|\n"))
    fh.write("\n")


def _write_later(fh, rows):
    """Each cell of the tags in ``LATER`` beside the same cell of tag ``deconvolved``."""
    for tag, what in LATER.items():
        before = BEFORE.get(tag, "deconvolved")
        cells = {}
        for r in rows:
            if r.get("tag") in (before, tag) and r["method"] == "final":
                cells.setdefault((r["case"], r["sigma"], r["truth"], r["noise"], r["method"]), {})[r["tag"]] = r
        cells = {k: v for k, v in cells.items() if len(v) == 2}
        if not cells:
            continue
        was = ("tag `deconvolved` (a correction above 1.5 sd is sent to the bootstrap)" if before == "deconvolved"
               else f"tag `{before}`")
        fh.write(f"## Before and after: tag `{tag}`\n\nBefore: {was}; after: {what}. `cov se`: Monte Carlo "
                 "standard error of the coverage after, sqrt(p (1 - p) / n). Targets: coverage 0.93-0.97, "
                 "|bias| <= 0.2 crlb, rmse <= 1.1 crlb."
                 "\n\n" + PAIR_HEAD.split("\n")[0] + " cov se | fallback | CPU s/trial |\n|" + "---|" * 13 + "\n")
        for k, v in sorted(cells.items(), key=lambda kv: (kv[0][3] == "iid", kv[0])):
            b, a = v[before], v[tag]
            fb = [sum(n for m, n in r.get("bias_methods", {}).items() if m not in ("box", "none")) for r in (b, a)]
            cpu = [r.get("cpu_seconds", float("nan")) / max(r["reps"] + r.get("failed", 0), 1) for r in (b, a)]
            p, n = a["coverage95"], max(a["reps"], 1)
            fh.write(_pair_row(k, b, a)[:-1] + f" {np.sqrt(p * (1 - p) / n):.3f} | {fb[0]} -> {fb[1]} | "
                     f"{cpu[0]:.2f} -> {cpu[1]:.2f} |\n")
        fh.write("\n")


def _write(rows, folder: Path, prov: dict | None = None):
    order = {m: k for k, m in enumerate(METHODS + EXTRA_METHODS)}
    tags = {"previous": 0, "before": 1, "after": 2, "after100": 3, "main-general": 4, "deconvolved": 5,
            "selfconsistent": 6, "stiffer": 7, "branch": 8, "spread": 9, "stretch": 10, "control": 11,
            "folded6": 12, "folded6b": 13}
    rows = sorted(rows, key=lambda r: (tags.get(r.get("tag"), 9), r["case"], r["noise"], r["sigma"], r["truth"],
                                       order.get(r["method"], 99)))
    from skelid.io.atomic import atomic_write

    path = folder / "accuracy.json"
    if path.exists():  # another run may have written cells meanwhile: keep them
        key = lambda r: (r.get("tag", "previous"), r["case"], r["sigma"], r["truth"], r["noise"], r["method"])  # noqa: E731
        mine = {key(r) for r in rows}
        rows = rows + [r for r in rows_of(json.loads(path.read_text())) if key(r) not in mine]
        rows = sorted(rows, key=lambda r: (tags.get(r.get("tag"), 9), r["case"], r["noise"], r["sigma"],
                                           r["truth"], order.get(r["method"], 99)))
    with atomic_write(path) as fh:  # experiments: many runs, each row naming its own commit and tag
        json.dump(rows if folder == experiments_dir() else
                  with_provenance({"provenance": prov, "rows": rows} if prov else rows), fh, indent=1)
    head = ("| case | sigma | truth | noise | method | reps | bias | bias_se | sd | rmse | crlb | "
            "rmse/crlb | coverage95 | abs(z)>3 | profile bias | removed | fallback | s/fit |")
    with atomic_write(folder / "accuracy.md") as fh:
        fh.write("# Accuracy study\n\nGenerated by `python benchmarks/accuracy.py`; lengths in mm. "
                 + ("This file holds the current code's table (tag `current`); experiments and ablations are in "
                    "`benchmarks/experiments/accuracy.md`. " if folder != experiments_dir() else
                    "Experiments and ablations: each tag is a version of the code or a variant of a method; "
                    "the current code's table is `benchmarks/results/accuracy.md`. ")
                 + "Each row's `commit` in the JSON says which code ran it. "
                 "`crlb`: Cramér-Rao bound with every pose unknown, at the true poses. `profile bias`: mean "
                 "error of the joint least-squares estimate before correction; `removed`: mean correction "
                 "subtracted; `fallback`: trials whose correction came from a check's fallback rather than "
                 "the second-order expansion. "
                 + ("" if folder != experiments_dir() else "Tags: `previous` = results of an earlier version kept for "
                 "reference, `before` = the code before the graduated-smoothing start, `after` = the code after it, "
                 "`after100` = the same code at 100 trials on the near-singular cells, `deconvolved` = the check "
                 "of the local approximation and its bootstrap fallback at the deconvolved poses "
                 "(:mod:`skelid.estimators.uncertainty.singular`), `main-general` = the code before that check "
                 "on the cells "
                 "used to see whether it holds elsewhere (another length, case B), `selfconsistent` = a large "
                 "second-order correction evaluated again at the corrected geometry and deconvolved poses and "
                 "trusted when it stays put (instead of sent to the bootstrap whenever it exceeds 1.5 sd), "
                 "`stiffer` = that rule and a graduated-smoothing start 9 times stiffer than the motion model "
                 "(was 3; tried, not kept), `branch` = the check of a joint's mirrored pose branch, `spread` = "
                 "that check and the second-order term's spread in the interval, `stretch` = both, the check "
                 "limited to short stretches, `control` = the code as of `stretch` and later merges, each "
                 "Gaussian-noise trial with its linear control variate (see the section on it), "
                 "`folded6` = every joint's stretches mirrored at once and kept when the "
                 "refit settles on one branch, and the sd taken at the interval's ends along the profile where "
                 "that is larger, `folded6b` = `folded6` and, when its refit is not kept, the earlier one-joint rule "
                 "(tried, not kept: one refit kept in 100 trials, no figure moved beyond noise, one more refit "
                 "on the speed trial), `drawn-before` = the near-singular cells on a geometry drawn for each trial "
                 "(as every later run of them), fitted by the code before the fit searched other starting "
                 "geometries; `before-search` and `search-iid` = case A's i.i.d. cells fitted by the code before "
                 "and after that search. ")
                 + "A row with fewer trials than its cell asks for is a reduced run (a busy shared machine): "
                 "see its `reps`.\n\n")
        pairs = {}
        for r in rows:
            if r.get("tag") in ("before", "after"):
                pairs.setdefault((r["case"], r["sigma"], r["truth"], r["noise"], r["method"]), {})[r["tag"]] = r
        pairs = {k: v for k, v in pairs.items() if len(v) == 2}
        if pairs:
            fh.write("## Before and after (the graduated-smoothing start)\n\n" + PAIR_HEAD)
            for k, v in pairs.items():
                fh.write(_pair_row(k, v["before"], v["after"]))
            fh.write("\n")
        fix = {}
        for r in rows:  # each cell of this version beside the same cell of the version before, at 100 trials
            key = (r["case"], r["sigma"], r["truth"], r["noise"], r["method"])
            if r.get("tag") in ("after", "after100", "main-general", "deconvolved"):
                fix.setdefault(key, {})[r["tag"]] = r
        fix = {k: v for k, v in fix.items() if "deconvolved" in v and ({"after100", "main-general", "after"} & set(v))}
        if fix:
            fh.write("## Before and after the check of the local approximation (pose deconvolution and "
                     "bootstrap fallback)\n\nBefore: tag `after100` (near-singular cells) or `after` (i.i.d. "
                     "cells); after: tag `deconvolved`. `fallback` = trials (of those in the cell) whose check "
                     "failed, so that the bootstrap at the deconvolved poses stood in; CPU s/trial: CPU seconds of the "
                     "cell's processes per trial (every method the run fitted; threads and load differ between runs)."
                     "\n\n" + PAIR_HEAD.split("\n")[0] + " fallback | CPU s/trial |\n|" + "---|" * 12 + "\n")
            for k, v in sorted(fix.items(), key=lambda kv: (kv[0][3] == "iid", kv[0])):
                b = v.get("after100", v.get("main-general", v.get("after")))
                a = v["deconvolved"]
                fb = [sum(n for m, n in r.get("bias_methods", {}).items() if m not in ("box", "none")) for r in (b, a)]
                cpu = [r.get("cpu_seconds", float("nan")) / max(r["reps"] + r.get("failed", 0), 1) for r in (b, a)]
                fh.write(_pair_row(k, b, a)[:-1] + f" {fb[0]} -> {fb[1]} | {cpu[0]:.2f} -> {cpu[1]:.2f} |\n")
            fh.write("\n")
        _write_later(fh, rows)
        _write_cv(fh, rows)
        for tag in sorted({r.get("tag", "previous") for r in rows}, key=lambda t: tags.get(t, 9)):
            fh.write(f"## {tag}\n\n{head}\n" + "|" + "---|" * 18 + "\n")
            for r in rows:
                if r.get("tag", "previous") != tag:
                    continue
                fb = sum(v for k, v in r.get("bias_methods", {}).items() if k not in ("box", "none"))
                fh.write(
                    f"| {r['case']} | {r['sigma']:g} | {r['truth']:g} | {r['noise']} | {r['method']} | "
                    f"{r['reps']} | {r['bias']:.2f} | {r['bias_se']:.2f} | {r['sd']:.2f} | {r['rmse']:.2f} | "
                    f"{r['crlb']:.2f} | {r['rmse_over_crlb']:.2f} | {r['coverage95']:.2f} | "
                    f"{r.get('z_gt3', float('nan')):.2f} | {r.get('profile_bias', float('nan')):.2f} | "
                    f"{r.get('bias_removed', float('nan')):.2f} | {fb if 'bias_methods' in r else ''} | "
                    f"{r['seconds_per_fit']:.2f} |\n")
            fh.write("\n")
        runs = [r for r in rows if "cpu_seconds" in r]
        if runs:
            fh.write("## Cost of each cell (this machine, shared)\n\n| tag | case | sigma | truth | noise | "
                     "reps | CPU s (all processes) | wall s | load average (1, 5, 15 min) |\n|" + "---|" * 9 + "\n")
            seen = set()
            for r in runs:
                key = (r.get("tag"), r["case"], r["sigma"], r["truth"], r["noise"])
                if key in seen:
                    continue
                seen.add(key)
                fh.write(f"| {key[0]} | {r['case']} | {r['sigma']:g} | {r['truth']:g} | {r['noise']} | {r['reps']} | "
                         f"{r['cpu_seconds']:.0f} | {r['wall_seconds']:.0f} | "
                         f"{', '.join(f'{v:.2f}' for v in r['load_average'])} |\n")


PAIR_HEAD = ("| case | sigma | truth | noise | method | reps | coverage95 | bias / crlb | rmse / crlb | abs(z)>3 |\n|"
             + "---|" * 10 + "\n")


def _pair_row(key, b, a) -> str:
    case, sigma, truth, noise, method = key
    return (f"| {case} | {sigma:g} | {truth:g} | {noise} | {method} | {b['reps']} / {a['reps']} | "
            f"{b['coverage95']:.2f} -> {a['coverage95']:.2f} | {b['bias'] / b['crlb']:.2f} -> "
            f"{a['bias'] / a['crlb']:.2f} | {b['rmse_over_crlb']:.2f} -> {a['rmse_over_crlb']:.2f} | "
            f"{b.get('z_gt3', float('nan')):.2f} -> {a.get('z_gt3', float('nan')):.2f} |\n")


def run_tasks(tasks, jobs):
    """Run ``one_trial`` over ``tasks``: in this process and ``jobs - 1`` worker processes."""
    if jobs <= 1:
        return [one_trial(t) for t in tasks]
    out = [None] * len(tasks)
    with ProcessPoolExecutor(jobs - 1) as pool:
        mine = list(range(0, len(tasks), jobs))
        futures = {i: pool.submit(one_trial, tasks[i]) for i in range(len(tasks)) if i % jobs}
        for i in mine:
            out[i] = one_trial(tasks[i])
        for i, f in futures.items():
            out[i] = f.result()
    return out


def frames_study(reps, jobs, frames=(100, 300, 1000, 3000, 5000)):
    """RMSE against the number of frames (case A, sigma 15, i.i.d.), with the bound."""
    tasks = [("case-a", 15.0, 250.0, "iid", r, F, ("paper", "profile", "final"))
             for F in frames for r in range(reps)]
    res = run_tasks(tasks, jobs)
    table = {}
    for (_, _, _, _, _, F, _), r in zip(tasks, res, strict=True):
        table.setdefault(F, []).append(r)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    out = {}
    for name in ("paper", "profile", "final"):
        rm = [np.sqrt(np.mean([(t[name]["est"] - 250.0) ** 2 for t in table[F] if "est" in t[name]]))
              for F in frames]
        out[name] = rm
        ax.loglog(frames, rm, "o-", label=name)
    bound = [np.sqrt(np.mean([t["crlb"] ** 2 for t in table[F]])) for F in frames]
    out["crlb"] = bound
    ax.loglog(frames, bound, "k--", label="Cramér-Rao bound (poses free)")
    ax.set_xlabel("frames")
    ax.set_ylabel("RMSE of L2 [mm]")
    ax.set_title(f"case A, sigma 15 mm, {reps} trials per point: a plateau is bias")
    ax.legend()
    results_dir().mkdir(parents=True, exist_ok=True)
    fig.savefig(results_dir() / "rmse_vs_frames.png", dpi=120, bbox_inches="tight")
    write_json(results_dir() / "rmse_vs_frames.json", {"frames": list(frames), "reps": reps, **out})
    print(json.dumps({"frames": list(frames), **out}, indent=1))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=100)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--frames", type=int, default=500)
    ap.add_argument("--cases", nargs="*", default=list(CASES))
    ap.add_argument("--sigmas", nargs="*", type=float, default=list(SIGMAS))
    ap.add_argument("--noises", nargs="*", default=list(NOISES), choices=NOISES + tuple(POSTURES) + ("coupled",),
                    help="'straight' and 'folded': i.i.d. noise near a singular pose, geometry drawn per trial; "
                    "'coupled': markers of a knee whose centre slides with flexion, fitted with a hinge (for "
                    "these three the truths are ignored)")
    ap.add_argument("--truths", nargs="*", type=float, default=list(TRUTHS))
    ap.add_argument("--methods", nargs="*", default=list(METHODS), choices=METHODS + EXTRA_METHODS)
    ap.add_argument("--fresh", action="store_true", help="ignore results already written")
    ap.add_argument("--tag", default=DEFAULT_TAG,
                    help=f"label of this run's rows: '{DEFAULT_TAG}' (the default) writes benchmarks/results, any "
                    "other (an experiment, e.g. 'before' a change) benchmarks/experiments")
    ap.add_argument("--frames-study", action="store_true")
    ap.add_argument("--report", action="store_true", help="rewrite accuracy.md from accuracy.json and stop")
    a = ap.parse_args()
    if a.report:
        for folder in (results_dir(), experiments_dir()):
            if (folder / "accuracy.json").exists():  # the tables rewritten, the file's provenance kept
                doc = json.loads((folder / "accuracy.json").read_text())
                write(rows_of(doc), folder, doc.get("provenance") if isinstance(doc, dict) else None)
        return
    if a.frames_study:
        frames_study(a.reps, a.jobs)
        return
    folder = folder_for(a.tag)
    path = folder / "accuracy.json"
    rows = [] if a.fresh or not path.exists() else rows_of(json.loads(path.read_text()))
    for r in rows:
        r.setdefault("tag", "previous")
    done = {(r["tag"], r["case"], r["sigma"], r["truth"], r["noise"], r["method"]) for r in rows}
    commit = git_commit()
    produced = []  # the cells this run finished: only these are written over what the file holds then
    for case in a.cases:
        for sigma in a.sigmas:
            for noise in a.noises:
                for truth in ([0.0] if noise == "coupled" or noise in POSTURES else a.truths):
                    todo = tuple(m for m in a.methods if (a.tag, case, sigma, truth, noise, m) not in done)
                    if not todo:
                        continue
                    t0 = time.time()
                    tasks = [(case, sigma, truth, noise, r, a.frames, todo) for r in range(a.reps)]
                    trials = []
                    for start in range(0, len(tasks), CHUNK):  # a cell's rows are rewritten as trials come in
                        trials += run_tasks(tasks[start:start + CHUNK], a.jobs)
                        cost = {"cpu_seconds": float(sum(t["cpu"] for t in trials)),
                                "wall_seconds": time.time() - t0, "jobs": a.jobs, "tag": a.tag, "commit": commit,
                                "load_average": [round(v, 2) for v in os.getloadavg()]}
                        cell = [dict(r, **cost) for r in summarise(case, sigma, truth, noise, trials, todo)]
                        write(produced + cell, folder)
                    produced += cell
                    for r in cell:
                        print(f"{case} s={sigma:g} L2={truth:g} {noise:<3} {r['method']:<8} "
                              f"bias {r['bias']:7.2f}±{r['bias_se']:.2f} sd {r['sd']:6.2f} "
                              f"rmse {r['rmse']:6.2f} crlb {r['crlb']:5.2f} ratio {r['rmse_over_crlb']:5.2f} "
                              f"cover {r['coverage95']:.2f} |z|>3 {r['z_gt3']:.2f} "
                              f"profile {r.get('profile_bias', float('nan')):.2f} "
                              f"removed {r.get('bias_removed', float('nan')):.2f} {r.get('bias_methods', '')} "
                              f"{r.get('warnings', '')}", flush=True)
                    print(f"  cell took {cost['wall_seconds']:.0f} s wall, {cost['cpu_seconds']:.0f} s CPU, "
                          f"load {cost['load_average']}", flush=True)


if __name__ == "__main__":
    main()
