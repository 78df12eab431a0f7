"""Live health flags against simulated faults: how often each is seen, how soon, whether the culprit is named.

Each session is a simulated trial (100 Hz, i.i.d. noise ``sigma = 1 mm``) of
one of two models, its geometry drawn afresh per session:

* **case A** (the seed's planar chain, ``skelid.simulate.builtin_model("case-a")``;
  3 markers, 1 parameter, the grid form): ``L2 ~ N(250, 15)`` mm, held within
  210-290 mm;
* **3-D arm** (``examples/arm.toml``; 14 markers, 9 parameters, the Gaussian
  form with its default motion model): every coordinate of the shoulder, elbow
  and wrist centres ``~ N(0, 10)`` mm about the model's nominal place, held
  within 25 mm.

The session is :class:`skelid.live.Session` with its defaults (``method='auto'``,
the noise level estimated, ``cutoff='auto'``), fed the frames as arrays. A
session of seed ``s`` replays the same trial for every fault (common random
numbers); the fault's start ``k`` is drawn per session from frames 60-100 of
the 180 (after the noise level is known and the early re-linearisations after
10, 25 and 50 frames, across the one after 100). The faults, one per session:

=================  ==========================================================  ================
fault              what the stream does                                        detection window
=================  ==========================================================  ================
clean              nothing (the control)                                       -
swap               two labels (a random pair) exchanged on frames k..k+9        10 frames
dropout            one random marker NaN on frames k..k+19                      20 frames
frozen             frame k-1 sent again on frames k..k+29 (30 repeats)          10 frames
units m / units cm the whole stream in metres / centimetres, declared mm        50 frames
knocked marker     one random marker 30 mm off its place (random direction)    50 frames
                   from frame k to the end
=================  ==========================================================  ================

Per fault and model:

* **detected**: sessions with a not-ok health on some frame of
  ``[k, k + N)`` (``N`` the detection window above; the units faults start at
  frame 0); **frames to detection**: the first such frame less ``k``
  (median over the detected sessions);
* **named right**: of the detected sessions whose health text names a pair
  (``labels X and Y look swapped``, swaps) or a marker (``left out X``,
  ``markers that do not follow the model ... (rms residual X ...``, knocked
  marker) on a frame of the window, those whose first such name is the fault's
  pair or marker; a dropout's health counts the markers missing and names none;
  for the frozen stream and the units the cause is checked instead (the text
  says ``frozen stream`` / ``units``);
* **false alarms**: sessions with a not-ok health on any frame from 30 on
  (the warm-up: the first pose, the noise level on 30 degrees of freedom)
  outside the fault's frames and the 10 frames after them; for the clean
  control, any not-ok frame from 30 on; none can be counted for the units
  (every frame is faulty) or after a knocked marker (it stays knocked);
* **fault frames flagged**: the share of the fault's frames (within the
  window for the two faults without end) whose health is not ok, averaged
  over the sessions;
* **final error**: the largest ``|theta - theta_true| / sd`` over the
  parameters at the last frame (``sd`` the session's own), median and largest
  over the sessions: what the fault did to the estimate, the clean control's
  row the reference.

**The dropout's rule.** A marker missing is reported (``healthy`` is False
on that frame with ``N marker(s) missing``: by design a frame is healthy
only when it was used whole); the rest of the frame is still used where the
markers left fix the pose. The rule measured: on every dropout frame the
health reports the marker missing, and nothing else where the markers left
fix the pose (the arm: 13 of 14 markers), or ``too few markers`` / ``do not
fix the pose`` where they cannot (case A: 2 markers, 4 coordinates for 5 pose
coordinates). The share of sessions that follow it is reported beside the
table.

    nice -n 10 python benchmarks/live_health.py               # 100 sessions per fault and model
    nice -n 10 python benchmarks/live_health.py --quick       # 10 (a reduced run, marked so)

Results: ``benchmarks/results/live_health.{json,md}`` (through ``_common``: the
commit, date, CPU, cores, load and command line).
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import time

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core per session: BLAS threads only spin on a shared machine
# the compiled path throughout (waiting for it where numba's cache is cold), so that no flag depends on the cache
os.environ.setdefault("SKELID_NUMBA", "wait")
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402  (after the thread settings, which BLAS reads when it loads)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import provenance, results_dir, write_results  # noqa: E402

#: frames per session, rate (Hz), noise sd (mm)
FRAMES, RATE, SIGMA = 180, 100.0, 1.0
#: the fault starts on a frame drawn from this range (both ends included)
START = (60, 100)
#: frames at the start of every session that count as warm-up, not as false alarms
WARMUP = 30
#: frames after a fault's last one that may still be flagged (the tracks and the pose settling)
MARGIN = 10
#: the knocked marker's offset (mm)
KNOCK = 30.0
MODELS = ("case A", "3-D arm")
#: fault -> (frames it lasts, None: to the end; detection window N in frames)
FAULTS = {"clean": (0, None), "swap": (10, 10), "dropout": (20, 20), "frozen": (30, 10),
          "units m": (None, 50), "units cm": (None, 50), "knocked marker": (None, 50)}
UNIT_DIVISOR = {"units m": 1000.0, "units cm": 10.0}
#: the text that names the cause where no marker is named
CAUSE = {"frozen": "frozen stream", "units m": "units", "units cm": "units"}
_PAIR = re.compile(r"labels (\S+) and (\S+) look swapped")
_LEFT_OUT = re.compile(r"left out ([^:;(]+?)(?: \(|:|;|$)")
_NOT_FOLLOW = re.compile(r"do not follow the model over the last \d+ frames \(rms residual (\S+) ")


def _model(name: str):
    from skelid.model import load_model
    from skelid.simulate import builtin_model

    return builtin_model("case-a") if name == "case A" else load_model(ROOT / "examples" / "arm.toml")


def _geometry(name: str, model, rng) -> np.ndarray:
    """The session's true parameters ``(P,)``, drawn around the model's nominal ones."""
    if name == "case A":
        return np.clip(rng.normal(model.theta_nominal, 15.0), 210.0, 290.0)
    return model.theta_nominal + np.clip(rng.normal(0.0, 10.0, model.n_params), -25.0, 25.0)


def _faulty(fault: str, y, rng):
    """The frames ``(F, M, D)`` with ``fault`` applied, and where it is: ``(start, end, culprit)``
    (``end`` exclusive; ``culprit`` the pair or marker index, or None)."""
    F, M, D = y.shape
    y = y.copy()
    k = int(rng.integers(START[0], START[1] + 1))
    if fault == "clean":
        return y, (None, None, None)
    if fault == "swap":
        i, j = sorted(int(v) for v in rng.choice(M, 2, replace=False))
        y[k:k + 10, [i, j]] = y[k:k + 10, [j, i]]
        return y, (k, k + 10, (i, j))
    if fault == "dropout":
        m = int(rng.integers(M))
        y[k:k + 20, m] = np.nan
        return y, (k, k + 20, m)
    if fault == "frozen":
        y[k:k + 30] = y[k - 1]
        return y, (k, k + 30, None)
    if fault in UNIT_DIVISOR:
        return y / UNIT_DIVISOR[fault], (0, F, None)
    if fault == "knocked marker":
        m = int(rng.integers(M))
        u = rng.normal(size=D)
        y[k:, m] += KNOCK * u / np.linalg.norm(u)
        return y, (k, F, m)
    raise ValueError(fault)


def _named(text: str, names) -> tuple[tuple[str, ...] | None, str | None]:
    """The first pair and the first marker the health text names (None where it names none)."""
    pair = _PAIR.search(text)
    marker = _LEFT_OUT.search(text) or _NOT_FOLLOW.search(text)
    first = None
    if marker:
        first = marker.group(1).split(",")[0].strip()
        first = first if first in names else None
    return (tuple(sorted(pair.groups())) if pair else None), first


def one(task) -> dict:
    """One session: model ``name``, ``fault``, seed; what its health said, frame by frame, summed up."""
    name, fault, seed = task
    from skelid.live import Session
    from skelid.simulate import simulate

    model = _model(name)
    rng = np.random.default_rng([31, MODELS.index(name), seed])
    theta = _geometry(name, model, rng)
    trial = simulate(model, theta=theta, n_frames=FRAMES, rate=RATE, sigma=SIGMA, rng=rng)
    y, (start, end, culprit) = _faulty(fault, trial.data.positions,
                                       np.random.default_rng([32, MODELS.index(name), seed, list(FAULTS).index(fault)]))
    session = Session(model, labels=trial.data.names, units=model.units, rate=RATE, rng=np.random.default_rng(seed))
    healthy, texts = np.ones(FRAMES, dtype=bool), {}
    t0 = time.process_time()
    for t, frame in enumerate(y):
        est = session.push(frame)
        if not est.healthy:
            healthy[t] = False
            texts[t] = est.health
    sd = np.sqrt(np.clip(np.diag(est.cov), 0.0, None))
    out = {"model": name, "fault": fault, "seed": seed, "method": session.method, "start": start, "end": end,
           "error_sd": float(np.max(np.abs(est.theta - theta) / sd)), "cpu_s": time.process_time() - t0}
    names = model.marker_names
    out["culprit"] = (None if culprit is None else [names[i] for i in culprit] if isinstance(culprit, tuple)
                      else names[culprit])
    window = FAULTS[fault][1]
    quiet_from = WARMUP
    outside = np.zeros(FRAMES, dtype=bool)
    outside[quiet_from:] = True
    if start is not None:
        outside[start:end + MARGIN] = False
        hit = [t for t in range(start, min(start + window, FRAMES)) if not healthy[t]]
        out["detected_at"] = hit[0] - start if hit else None
        flagged_in = range(start, min(end, start + window) if FAULTS[fault][0] is None else end)
        out["fault_frames_flagged"] = float(np.mean([not healthy[t] for t in flagged_in]))
        out["named"] = out["named_right"] = None
        for t in hit:
            pair, marker = _named(texts[t], names)
            if fault == "swap" and pair:
                out["named"], out["named_right"] = list(pair), set(pair) == set(out["culprit"])
                break
            if fault == "knocked marker" and marker:
                out["named"], out["named_right"] = marker, marker == out["culprit"]
                break
            if fault in CAUSE:
                out["named"], out["named_right"] = texts[t][:120], CAUSE[fault] in texts[t]
                break
        if fault == "dropout":
            out["dropout_texts"] = sorted({_dropout_kind(texts.get(t, "ok")) for t in range(start, end)})
    alarms = np.flatnonzero(outside & ~healthy)
    out["false_alarms"] = int(alarms.size)
    out["first_false_alarm"] = int(alarms[0]) if alarms.size else None
    out["false_alarm_text"] = texts[int(alarms[0])] if alarms.size else None
    return out


def _dropout_kind(text: str) -> str:
    """What a dropout frame's health said, as one of a few kinds."""
    parts = [p.strip() for p in text.split(";")]
    rest = [p for p in parts if not re.fullmatch(r"\d+ marker\(s\) missing", p)]
    if len(rest) == len(parts):
        return "ok" if text == "ok" else "no missing marker reported: " + text
    if not rest:
        return "missing only"
    if all("too few markers" in p or "do not fix the pose" in p for p in rest):
        return "missing, too few markers"
    return "missing, and: " + "; ".join(rest)


def summarise(rows) -> dict:
    """Per model and fault: sessions, detected, frames to detection, named right, false alarms, flags, error."""
    out = {}
    for fault in FAULTS:
        for name in MODELS:
            rs = [r for r in rows if r["model"] == name and r["fault"] == fault]
            if not rs:
                continue
            n = len(rs)
            c = {"model": name, "fault": fault, "method": rs[0]["method"], "sessions": n,
                 "detection_window": FAULTS[fault][1]}
            if fault != "clean":
                det = [r["detected_at"] for r in rs if r["detected_at"] is not None]
                named = [r for r in rs if r["named"] is not None]
                c.update(detected=len(det), median_frames_to_detection=float(np.median(det)) if det else None,
                         named=len(named), named_right=sum(bool(r["named_right"]) for r in named),
                         fault_frames_flagged=float(np.mean([r["fault_frames_flagged"] for r in rs])))
            countable = fault == "clean" or FAULTS[fault][0] is not None or fault == "knocked marker"
            c["false_alarms"] = sum(bool(r["false_alarms"]) for r in rs) if countable else None
            c["false_alarm_texts"] = sorted({r["false_alarm_text"] for r in rs if r["false_alarm_text"]})[:5]
            c["false_alarm_sessions"] = [r["seed"] for r in rs if r["false_alarms"]]
            if fault == "dropout":
                kinds = [tuple(r["dropout_texts"]) for r in rs]
                expected = ("missing, too few markers",) if name == "case A" else ("missing only",)
                c["dropout_as_rule"] = sum(k == expected for k in kinds)
                c["dropout_kinds"] = sorted({"/".join(k) for k in kinds})
            err = [r["error_sd"] for r in rs]
            c["final_error_median"], c["final_error_max"] = float(np.median(err)), float(np.max(err))
            c["cpu_s"] = float(sum(r["cpu_s"] for r in rs))
            out[f"{fault} / {name}"] = c
    return out


def _share(k, n) -> str:
    return f"{k}/{n} ({k / n:.0%})" if n else "-"


def markdown(res: dict) -> str:
    p = res["provenance"]
    n = res["sessions"]
    lines = ["# Live health flags on simulated faults", "",
             f"Commit `{p['commit'][:10]}`{' (uncommitted changes)' if p.get('dirty') else ''}, {p['date']}, "
             f"{p['cpu']}, {p['cores']} cores, load {p['load_average']} at the start; `{p['command']}`; "
             f"{n} sessions per fault and model" + (" (**reduced**: fewer than 100)" if res["reduced"] else "")
             + f", {res['wall_s']:.0f} s wall, {res['cpu_s']:.0f} CPU s in the sessions.", "",
             f"{FRAMES} frames per session at {RATE:g} Hz, noise sd {SIGMA:g} mm, geometry drawn per session; the "
             f"fault starts on a frame drawn from {START[0]}-{START[1]}. Detected: health not ok within the window's "
             "frames of the fault's start; named right: of the sessions whose health named a pair (swap) or a marker "
             "(knocked marker), those that named the right one (the frozen stream and the units: the text names the "
             f"cause); false alarms: sessions with a not-ok frame from frame {WARMUP} on outside the fault and the "
             f"{MARGIN} frames after it; fault frames flagged: mean share of the fault's frames (within the window "
             "for a fault without end) not ok; final error: median (max) over sessions of the largest "
             "|theta - truth| / sd at the last frame (the session's own sd; the clean row is the reference). "
             "`benchmarks/live_health.py` states the rules.", "",
             "| fault | model | sessions | detected (window) | median frames to detection | named right | false alarms "
             "| fault frames flagged | final error, median (max) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for c in res["cells"].values():
        lines.append(_row(c))
    drop = [c for c in res["cells"].values() if c["fault"] == "dropout"]
    if drop:
        lines += ["", "Dropouts (a marker missing is reported by design; the rule: the health says the marker is "
                  "missing and nothing else where the markers left fix the pose, `too few markers` where they do not): "
                  + "; ".join(f"{c['model']}: {_share(c['dropout_as_rule'], c['sessions'])} follow it "
                              f"(seen: {', '.join(c['dropout_kinds'])})" for c in drop) + "."]
    texts = [(c, t) for c in res["cells"].values() for t in c["false_alarm_texts"]]
    if texts:
        lines += ["", "First false-alarm texts (up to five per cell):", ""]
        lines += [f"- {c['fault']} / {c['model']}: {t}" for c, t in texts]
    return "\n".join(lines) + "\n"


def _row(c: dict) -> str:
    """One line of the table (docs/live.md renders the same columns)."""
    n = c["sessions"]
    if c["fault"] == "clean":
        cells = ["-", "-", "-"]
        flagged = "-"
    else:
        cells = [f"{_share(c['detected'], n)} ({c['detection_window']})",
                 "-" if c["median_frames_to_detection"] is None else f"{c['median_frames_to_detection']:g}",
                 f"{c['named_right']}/{c['named']}" if c["named"] else ("not named" if c["fault"] == "dropout"
                                                                         else "none named")]
        flagged = f"{c['fault_frames_flagged']:.0%}"
    fa = "-" if c["false_alarms"] is None else _share(c["false_alarms"], n)
    error = f"{c['final_error_median']:.2f} ({c['final_error_max']:.3g})"
    return f"| {c['fault']} | {c['model']} | {n} | " + " | ".join(cells) + f" | {fa} | {flagged} | {error} |"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=100, help="sessions per fault and model (default 100)")
    ap.add_argument("--quick", action="store_true", help="10 sessions per fault and model (a reduced run)")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    ap.add_argument("--models", nargs="+", default=list(MODELS), choices=list(MODELS))
    ap.add_argument("--faults", nargs="+", default=list(FAULTS), choices=list(FAULTS))
    ap.add_argument("--out", type=Path, default=None, help="results file stem (default results/live_health)")
    a = ap.parse_args(argv)
    n = 10 if a.quick else a.sessions
    prov = provenance()
    t0 = time.perf_counter()
    tasks = [(m, f, s) for m in reversed(a.models) for f in a.faults for s in range(n)]  # the slower model first
    with ProcessPoolExecutor(a.jobs) as pool:
        rows = list(pool.map(one, tasks, chunksize=4))
    wall = time.perf_counter() - t0
    res = {"provenance": prov, "sessions": n, "reduced": n < 100, "frames": FRAMES, "rate": RATE, "sigma": SIGMA,
           "start": list(START), "warmup": WARMUP, "margin": MARGIN, "knock_mm": KNOCK,
           "wall_s": wall, "cpu_s": float(sum(r["cpu_s"] for r in rows)), "cells": summarise(rows),
           "sessions_rows": rows}
    write_results(a.out or results_dir() / "live_health", res, markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
