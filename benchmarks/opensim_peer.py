"""skelid's OpenSim scaling against its peers on the same recordings.

subject01 (``../shared/data/opensim-subject01``): OpenSim's ScaleTool run with
the setup file that ships with the data (``subject01_Setup_Scale.xml``,
gait2354 and its marker set, the static trial; run from a temporary copy of
the folder) against skelid fitting ``gait2354_simbody.osim`` to the static and
walking trials. Reported: scale factors side by side (skelid with its 95 %
intervals), OpenSim IK marker RMSE on the walk with each scaled model, and the
time of each.

subject4 (``../shared/data/addbio-subject4``): skelid on
``unscaled_generic.osim`` with the six trials against AddBiomechanics'
``optimized_scale_and_markers.osim`` and the expert's ``manually_scaled.osim``:
body scale factors (the peers' from their mesh scale factors over the generic
model's), key lengths (distances between joint centres at the reference pose),
OpenSim IK marker RMSE per trial with each model (every k-th frame, at most
40 per trial: OpenSim's IK of this model takes about 0.3 s a frame here), time.

skelid fits the trials with its multi-trial form (``--joined``: as one
recording with gaps; see :mod:`skelid.scaling`). Times are CPU seconds of this
process (``time.process_time``) and wall seconds, with the load average.
``--quick`` uses fewer frames and trials (marked as reduced in the results).

Run: ``nice -n 10 python benchmarks/opensim_peer.py [--quick]``
-> ``benchmarks/results/opensim_peer.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # one core, as the target says
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from skelid.data import MarkerData  # noqa: E402
from skelid.io import read_markers  # noqa: E402
from skelid.io.osim import read_osim  # noqa: E402
from skelid.model.kinematics import forward_kinematics  # noqa: E402
from skelid.scaling import fit_osim, opensim_ik, scaling_table, write_outputs  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
S01 = DATA / "opensim-subject01"
S04 = DATA / "addbio-subject4"
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import provenance, results_dir, write_json  # noqa: E402

OUT = results_dir()
JOINED = False  # --joined: trials as one recording with gaps, one marker fit
SCALE = None  # --scale: skelid's scale setting (None: fit_osim's default, the command line's)



def scale_entries(table: dict) -> list[tuple]:
    """``(label, body, axis, entry)`` of every scale factor of a scaling table: one per body, or per axis
    where the fit gave the body one factor per axis (``"femur_r x"``)."""
    return [(body if ax == "xyz" else f"{body} {ax}", body, ax, e)
            for body, axes in table["scales"].items() for ax, e in axes.items()]


def _axis(scales: dict, body: str, ax: str):
    """A peer's factors of ``body``: all three for one factor per body, the one of axis ``ax`` otherwise."""
    v = scales.get(body)
    return v if v is None or ax == "xyz" else [v["xyz".index(ax)]]


def _every(data: MarkerData, step: int) -> MarkerData:
    return MarkerData(data.positions[::step], data.names, data.rate / step, data.units, data.source, data.meta)


class Clock:
    """Wall and CPU seconds (``time.process_time``) of a block, with the load average at its end."""

    def __enter__(self):
        self.c0, self.w0 = time.process_time(), time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.cpu = round(time.process_time() - self.c0, 2)
        self.wall = round(time.perf_counter() - self.w0, 2)
        self.load = [round(v, 2) for v in os.getloadavg()]

    def dict(self) -> dict:
        return {"cpu_s": self.cpu, "wall_s": self.wall, "load_avg_1_5_15": self.load}


def run_scaletool(tmp: Path) -> dict:
    import opensim as osim

    osim.Logger.removeFileSink()  # OpenSim would write opensim.log beside every model it loads

    work = tmp / "subject01"
    shutil.copytree(S01, work)
    cwd = os.getcwd()
    os.chdir(work)
    try:
        with Clock() as clock:
            tool = osim.ScaleTool("subject01_Setup_Scale.xml")
            tool.run()
    finally:
        os.chdir(cwd)
    placer = tool.getMarkerPlacer()
    out_model = work / (placer.getOutputModelFileName() if placer.getApply()
                        else tool.getModelScaler().getOutputModelFileName())
    scale_file = work / tool.getModelScaler().getOutputScaleFileName()
    scales = {}
    ss = osim.ScaleSet(str(scale_file))
    for i in range(ss.getSize()):
        s = ss.get(i)
        v = s.getScaleFactors()
        scales[s.getSegmentName()] = [v.get(0), v.get(1), v.get(2)]
    return {"model": str(out_model), "scales": scales, "time": clock.dict()}


def _ik(model, trc, out) -> dict:
    with Clock() as clock:
        r = opensim_ik(model, trc, out)
    return r | clock.dict()


def _scale() -> dict:
    """``fit_osim``'s scale argument: the one ``--scale`` named, else none (its default)."""
    return {} if SCALE is None else {"scale": SCALE}


def subject01(tmp: Path, quick: bool) -> dict:
    static = read_markers(S01 / "subject01_static.trc")
    walk = read_markers(S01 / "subject01_walk1.trc")
    trials = [static, _every(walk, 2)] if quick else [static, walk]
    peer = run_scaletool(tmp)
    ik_os = _ik(peer["model"], S01 / "subject01_walk1.trc", tmp / "ik01_opensim")
    with Clock() as clock:  # as the command line does it: the marker set found beside the model
        fit = fit_osim(S01 / "gait2354_simbody.osim", trials, markers="offsets", joined=JOINED, **_scale())
    paths = write_outputs(fit, tmp / "skelid01")
    table = scaling_table(fit)
    rows = [{"body": label, "skelid": e["value"], "skelid_ci95": e["ci95"], "opensim": _axis(peer["scales"], body, ax)}
            for label, body, ax, e in scale_entries(table)]
    ik_sk = _ik(paths["osim"], S01 / "subject01_walk1.trc", tmp / "ik01_skelid")
    peer_cpu = peer["time"]["cpu_s"] + ik_os["cpu_s"]
    return {"frames_given": {"static": int(static.positions.shape[0]), "walk": int(trials[1].positions.shape[0])},
            "frames_used": fit.data.meta.get("trial_frames_used"),
            "marker_set": fit.marker_set,
            "scales": rows, "ik_walk": {"skelid": ik_sk, "opensim_scaletool": ik_os},
            "seconds": {"skelid_fit": clock.dict(), "opensim_scaletool": peer["time"],
                        "opensim_ik_walk": {k: ik_os[k] for k in ("cpu_s", "wall_s", "load_avg_1_5_15")},
                        "ratio_skelid_fit_cpu_to_scaletool_plus_ik_cpu": round(clock.cpu / max(peer_cpu, 1e-9), 2)},
            "skelid_sigma_mm": table["sigma_mm"], "markers_left_out": table["markers_left_out"],
            "warnings": table["warnings"]}


KEY_LENGTHS = [("pelvis width (hip-hip)", "femur_r", "femur_l"), ("thigh r (hip-knee)", "femur_r", "tibia_r"),
               ("thigh l (hip-knee)", "femur_l", "tibia_l"), ("shank r (knee-ankle)", "tibia_r", "talus_r"),
               ("shank l (knee-ankle)", "tibia_l", "talus_l"), ("upper arm r (shoulder-elbow)", "humerus_r", "ulna_r"),
               ("upper arm l (shoulder-elbow)", "humerus_l", "ulna_l")]


def key_lengths(path) -> dict:
    """Distances (mm) between joint centres at the reference pose (the bodies that carry markers)."""
    model, _ = read_osim(path)
    kin = forward_kinematics(model, np.zeros(0), np.zeros(model.n_pose))
    idx = {s.name: i for i, s in enumerate(model.segments)}
    return {name: float(np.linalg.norm(kin.p_world_seg[idx[a]] - kin.p_world_seg[idx[b]]))
            for name, a, b in KEY_LENGTHS if a in idx and b in idx}


def mesh_scales(path) -> dict:
    """Per body the ``scale_factors`` of its first attached mesh (the ScaleTool writes the body scale there)."""
    import xml.etree.ElementTree as ET

    out = {}
    for body in ET.parse(path).getroot().iter("Body"):
        sf = body.find(".//Mesh/scale_factors")
        if sf is not None and sf.text:
            out[body.get("name")] = [float(v) for v in sf.text.split()]
    return out


def peer_scales(path, generic) -> dict:
    """Body scale factors (x, y, z) of a scaled model: its mesh scale factors over the generic model's."""
    g = mesh_scales(generic)
    return {b: [v / w for v, w in zip(s, g[b], strict=True)] for b, s in mesh_scales(path).items() if b in g}


S04_TRIALS = ["static1", "walking1", "walking2", "squats1", "STS1", "DJ1"]
IK_FRAMES = 40  # OpenSim's IK of the full-body model takes about 0.3 s a frame here: every k-th frame, at most this


def _ik_trials(tmp: Path) -> dict:
    """Each subject4 trial thinned to at most IK_FRAMES frames (every k-th), written as TRC for OpenSim."""
    from skelid.io import write_trc
    from skelid.scaling import thin_trial

    out = {}
    for n in S04_TRIALS:
        d = read_markers(S04 / "MarkerData" / f"{n}.trc")
        out[n] = tmp / f"ik_{n}.trc"
        write_trc(out[n], thin_trial(d, IK_FRAMES))
    return out


def _s04_models() -> dict:
    return {"addbiomechanics": S04 / "Models" / "optimized_scale_and_markers.osim",
            "expert": S04 / "Models" / "manually_scaled.osim",
            "generic": S04 / "Models" / "unscaled_generic.osim"}


def subject4_peers(tmp: Path) -> dict:
    """Without a skelid fit: the peers' key lengths and IK RMSE on every trial."""
    models = _s04_models()
    lengths = {k: key_lengths(v) for k, v in models.items()}
    files = _ik_trials(tmp)
    ik = {m: {n: _ik(models[m], files[n], tmp / f"ik04_{m}_{n}") for n in S04_TRIALS}
          for m in ("addbiomechanics", "expert")}
    return {"skelid_fit": "not run (--subject4 peers)", "key_lengths_mm": lengths, "ik": ik}


def subject4(tmp: Path, quick: bool) -> dict:
    fit_names = ["static1", "walking1"] if quick else S04_TRIALS
    trials = {n: read_markers(S04 / "MarkerData" / f"{n}.trc") for n in S04_TRIALS}
    use = [trials[n] for n in fit_names]
    with Clock() as clock:
        fit = fit_osim(S04 / "Models" / "unscaled_generic.osim", use, markers="offsets", **_scale(),
                       joined=JOINED)
    print(json.dumps({"subject4_skelid_fit": clock.dict()}), flush=True)
    paths = write_outputs(fit, tmp / "skelid04")
    table = scaling_table(fit)
    models = {"skelid": paths["osim"]} | _s04_models()
    lengths = {k: key_lengths(v) for k, v in models.items()}
    scales = {m: peer_scales(models[m], models["generic"]) for m in ("addbiomechanics", "expert")}
    files = _ik_trials(tmp)
    ik = {m: {n: _ik(models[m], files[n], tmp / f"ik04_{m}_{n}") for n in S04_TRIALS}
          for m in ("skelid", "addbiomechanics", "expert")}
    return {"fit_trials": fit_names, "frames_given": {n: int(trials[n].positions.shape[0]) for n in fit_names},
            "frames_used": fit.data.meta.get("trial_frames_used"),
            "scales": {label: {"skelid": e["value"], "skelid_ci95": e["ci95"],
                               "addbiomechanics": _axis(scales["addbiomechanics"], b, ax),
                               "expert": _axis(scales["expert"], b, ax)}
                       for label, b, ax, e in scale_entries(table)},
            "key_lengths_mm": lengths, "ik": ik,
            "seconds": {"skelid_fit": clock.dict()},
            "skelid_sigma_mm": table["sigma_mm"], "markers_left_out": table["markers_left_out"],
            "warnings": table["warnings"]}


def markdown(res: dict) -> str:
    s1, s4 = res["subject01"], res["subject4"]
    head = ["# OpenSim peers: ScaleTool and AddBiomechanics against skelid", "",
            f"{'REDUCED run (--quick). ' if res['reduced'] else ''}Machine: shared, 2 cores under load; every time "
            "is given as CPU seconds of this one process (time.process_time) and wall seconds, with the load "
            "average (1, 5, 15 min) when the step ended. skelid's fit time excludes Python's import of the "
            f"package ({res['import_cpu_s']} s CPU); freed memory is kept for reuse, as the skelid program "
            f"keeps it. Peak memory of the whole benchmark process (OpenSim "
            f"included): {res['peak_memory_mb']:.0f} MB.", ""]
    body4 = _markdown4_peers(s4) if "skelid_fit" in s4 else _markdown4(s4)
    return "\n".join(head) + "\n" + _markdown01(res, s1) + body4


def _t(d: dict) -> str:
    return f"{d['cpu_s']} s CPU, {d['wall_s']} s wall (load {d['load_avg_1_5_15'][0]})"


def _markdown01(res: dict, s1: dict) -> str:
    sec = s1["seconds"]
    lines = ["## subject01: gait2354, static + walk", "",
             f"skelid: {res.get('trials', 'multi-trial')} fit of `gait2354_simbody.osim` as the command line runs "
             f"it, with the marker set it found beside the model (`{Path(s1['marker_set']).name}`), "
             f"frames used per trial {s1['frames_used']} (of {s1['frames_given']['static']} static and "
             f"{s1['frames_given']['walk']} walk frames), one scale per body; then every free marker placed on "
             "the static trial. OpenSim: ScaleTool with the setup file that ships with the data.", "",
             "| body | skelid scale [95 % interval] | OpenSim ScaleTool (x, y, z) |", "|---|---|---|"]
    for r in s1["scales"]:
        os_ = ", ".join(f"{v:.4f}" for v in r["opensim"]) if r["opensim"] else "-"
        lo, hi = r["skelid_ci95"]
        lines.append(f"| {r['body']} | {r['skelid']:.4f} [{lo:.4f}, {hi:.4f}] | {os_} |")
    ik = s1["ik_walk"]
    lines += ["", "| model | OpenSim IK marker RMSE on the walk (mm) | max (mm) | time |", "|---|---|---|---|",
              f"| skelid-scaled | {ik['skelid']['rmse_mm']:.1f} | {ik['skelid']['max_mm']:.1f} | "
              f"skelid fit {_t(sec['skelid_fit'])} |",
              f"| ScaleTool-scaled | {ik['opensim_scaletool']['rmse_mm']:.1f} | "
              f"{ik['opensim_scaletool']['max_mm']:.1f} | ScaleTool {_t(sec['opensim_scaletool'])} + "
              f"IK {_t(sec['opensim_ik_walk'])} |", "",
              f"skelid's fit takes {sec['ratio_skelid_fit_cpu_to_scaletool_plus_ik_cpu']} times the CPU time of "
              "OpenSim's ScaleTool plus its IK on the walk (skelid fits the walk too and gives intervals; "
              "ScaleTool uses the static trial only).", ""]
    return "\n".join(lines) + "\n"


def _markdown4_peers(s4: dict) -> str:
    lines = ["## subject4: generic full-body model, AddBiomechanics and expert scalings", "",
             f"skelid's fit of subject4: {s4['skelid_fit']}.", "",
             "| length (mm) | generic | AddBiomechanics | expert |", "|---|---|---|---|"]
    L = s4["key_lengths_mm"]
    for name in L["generic"]:
        v = [L[m].get(name, float("nan")) for m in ("generic", "addbiomechanics", "expert")]
        lines.append(f"| {name} | " + " | ".join(f"{x:.1f}" for x in v) + " |")
    lines += ["", "| trial | AddBiomechanics IK RMSE (mm) | expert |", "|---|---|---|"]
    for n in s4["ik"]["addbiomechanics"]:
        a, e = s4["ik"]["addbiomechanics"][n]["rmse_mm"], s4["ik"]["expert"][n]["rmse_mm"]
        lines.append(f"| {n} | {a:.1f} | {e:.1f} |")
    return "\n".join(lines) + "\n"


def _markdown4(s4: dict) -> str:
    fr = ", ".join(f"{n} {u}/{s4['frames_given'][n]}" for n, u in zip(s4["fit_trials"], s4["frames_used"],
                                                                       strict=True))
    lines = ["## subject4: generic full-body model, AddBiomechanics and expert scalings", "",
             f"skelid fitted `unscaled_generic.osim` to {', '.join(s4['fit_trials'])} at once (frames used/given: "
             f"{fr}) in {_t(s4['seconds']['skelid_fit'])}. AddBiomechanics' model comes from all trials at once "
             "(its README reports per-trial marker RMSE of 9.5-16 mm); the expert's is a hand scaling. Neither is "
             "truth.", "",
             "| body | skelid scale [95 % interval] | AddBiomechanics (x, y, z) | expert (x, y, z) |",
             "|---|---|---|---|"]
    for b, e in s4["scales"].items():
        def xyz(v):
            return "-" if v is None else ", ".join(f"{x:.3f}" for x in v)
        lo, hi = e["skelid_ci95"]
        lines.append(f"| {b} | {e['skelid']:.3f} [{lo:.3f}, {hi:.3f}] | {xyz(e['addbiomechanics'])} | "
                     f"{xyz(e['expert'])} |")
    lines += ["", "| length between joint centres (mm) | generic | skelid | AddBiomechanics | expert |",
              "|---|---|---|---|---|"]
    L = s4["key_lengths_mm"]
    for name in L["generic"]:
        v = [L[m].get(name, float("nan")) for m in ("generic", "skelid", "addbiomechanics", "expert")]
        lines.append(f"| {name} | " + " | ".join(f"{x:.1f}" for x in v) + " |")
    ik = s4["ik"]
    dyn = [n for n in ik["skelid"] if n != "static1"]
    worse = [ik["skelid"][n]["rmse_mm"] - min(ik[m][n]["rmse_mm"] for m in ("addbiomechanics", "expert"))
             for n in dyn]
    lines += ["", f"On the movement trials skelid's model tracks {min(worse):.1f} to {max(worse):.1f} mm worse "
              "(IK RMSE) than the better peer: skelid places each free marker on the static trial only, "
              "AddBiomechanics moves the markers to fit every trial at once. skelid's intervals are statistical "
              "intervals of one scale per body given the model's marker set; neither peer is truth and they "
              "disagree with each other (pelvis, tibia) by more than those intervals' width, so a peer's factor "
              "outside them is a different answer, not a measured failure of coverage."]
    lines += ["", f"OpenSim IK on every k-th frame of each trial (at most {IK_FRAMES}; the same frames for every "
              "model), every model marker in the file, weight 1:", "",
              "| trial | frames | skelid IK RMSE (mm) | AddBiomechanics | expert | IK time, skelid model |",
              "|---|---|---|---|---|---|"]
    for n in s4["ik"]["skelid"]:
        r = s4["ik"]
        lines.append(f"| {n} | {r['skelid'][n]['frames']} | " + " | ".join(
            f"{r[m][n]['rmse_mm']:.1f}" for m in ("skelid", "addbiomechanics", "expert"))
            + f" | {r['skelid'][n]['wall_s']} s wall |")
    kinds = {}
    for w in s4["warnings"]:  # one line per kind; every message is in the JSON
        key = w.split(":")[0].split(" (")[0]
        key = "model misfit at a joint" if key.startswith("model misfit") else key
        kinds[key] = kinds.get(key, 0) + 1
    lines += ["", "Markers left out of skelid's fit (not in every trial): " + ", ".join(s4["markers_left_out"]), "",
              f"skelid's {len(s4['warnings'])} warnings over the trials, by kind (all in opensim_peer.json):", ""]
    lines += [f"- {k} ({n}x)" if n > 1 else f"- {k}" for k, n in kinds.items()]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames and trials (results marked reduced)")
    ap.add_argument("--joined", action="store_true", help="fit the trials as one recording with gaps")
    ap.add_argument("--subject4", choices=("full", "peers"), default="full",
                    help="peers: no skelid fit of subject4, only the peers' lengths and IK")
    ap.add_argument("--scale", choices=("linked", "bodies", "axes"), default=None,
                    help="skelid's scale setting (default: the command line's)")
    args = ap.parse_args(argv)
    global JOINED, SCALE
    JOINED, SCALE = args.joined, args.scale
    import opensim as osim

    osim.Logger.setLevelString("Warn")  # no line per IK frame
    c0 = time.process_time()
    import skelid.estimators.multitrial  # noqa: F401  (imports outside the timed fit)
    import skelid.workflows  # noqa: F401
    from skelid.resources import keep_freed_memory

    keep_freed_memory()  # as the skelid program does

    # the commit and load the run starts from (a run of many minutes must not name a later commit)
    res = {"provenance": provenance(None if argv is None else ["benchmarks/opensim_peer.py", *argv]),
           "reduced": bool(args.quick), "trials": "joined" if args.joined else "multi-trial",
           "scale": SCALE or "default",
           "import_cpu_s": round(time.process_time() - c0, 2)}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        res["subject01"] = subject01(tmp, args.quick)
        print(json.dumps(res["subject01"]["seconds"]), flush=True)
        res["subject4"] = subject4(tmp, args.quick) if args.subject4 == "full" else subject4_peers(tmp)
    res["peak_memory_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    for log in DATA.rglob("opensim.log"):  # OpenSim's log must not stay beside the shared data
        log.unlink()
    OUT.mkdir(parents=True, exist_ok=True)
    write_json(OUT / "opensim_peer.json", res)
    (OUT / "opensim_peer.md").write_text(markdown(res))
    print(markdown(res))


if __name__ == "__main__":
    main()
