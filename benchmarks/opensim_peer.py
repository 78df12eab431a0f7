"""skelid's OpenSim scaling against its peers on the same recordings.

subject01 (``../shared/data/opensim-subject01``): OpenSim's ScaleTool run with
the setup file that ships with the data (``subject01_Setup_Scale.xml``,
gait2354 and its marker set, the static trial; run from a temporary copy of
the folder) against skelid fitting ``gait2354_simbody.osim`` to the static and
walking trials. Reported: scale factors side by side (skelid with its 95 %
intervals), OpenSim IK marker RMSE on the walk with each scaled model, and the
wall time of each.

subject4 (``../shared/data/addbio-subject4``): skelid on
``unscaled_generic.osim`` against AddBiomechanics' ``optimized_scale_and_markers.osim``
and the expert's ``manually_scaled.osim``: key lengths (distances between joint
centres at the reference pose), IK marker RMSE per trial with each model, time.

Trials are joined into one recording with gaps of missing frames (shared
geometry, separate poses; see :mod:`skelid.scaling`). ``--quick`` uses fewer
frames (marked as reduced in the results).

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

import numpy as np

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
OUT = ROOT / "benchmarks" / "results"
JOINED = False  # --joined: trials as one recording with gaps, one marker fit


def _every(data: MarkerData, step: int) -> MarkerData:
    return MarkerData(data.positions[::step], data.names, data.rate / step, data.units, data.source, data.meta)


def _cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def run_scaletool(tmp: Path) -> dict:
    import opensim as osim

    osim.Logger.removeFileSink()  # OpenSim would write opensim.log beside every model it loads

    work = tmp / "subject01"
    shutil.copytree(S01, work)
    cwd = os.getcwd()
    os.chdir(work)
    try:
        t0 = time.perf_counter()
        tool = osim.ScaleTool("subject01_Setup_Scale.xml")
        tool.run()
        seconds = time.perf_counter() - t0
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
    return {"model": str(out_model), "scales": scales, "seconds": round(seconds, 3)}


def subject01(tmp: Path, quick: bool) -> dict:
    static = read_markers(S01 / "subject01_static.trc")
    walk = read_markers(S01 / "subject01_walk1.trc")
    trials = [static, _every(walk, 2)] if quick else [static, walk]
    peer = run_scaletool(tmp)
    c0, t0 = _cpu(), time.perf_counter()
    fit = fit_osim(S01 / "gait2354_simbody.osim", trials, S01 / "gait2354_Scale_MarkerSet.xml",
                   scale="bodies", markers="offsets", joined=JOINED)
    wall, cpu = time.perf_counter() - t0, _cpu() - c0
    paths = write_outputs(fit, tmp / "skelid01")
    table = scaling_table(fit)
    rows = []
    for body, e in table["scales"].items():
        rows.append({"body": body, "skelid": e["xyz"]["value"], "skelid_ci95": e["xyz"]["ci95"],
                     "opensim": peer["scales"].get(body)})
    ik_sk = opensim_ik(paths["osim"], S01 / "subject01_walk1.trc", tmp / "ik01_skelid")
    ik_os = opensim_ik(peer["model"], S01 / "subject01_walk1.trc", tmp / "ik01_opensim")
    return {"frames": {"static": min(30, int(static.positions.shape[0])),
                       "walk": int(trials[1].positions.shape[0])},
            "scales": rows, "ik_walk": {"skelid": ik_sk, "opensim_scaletool": ik_os},
            "seconds": {"skelid_fit_wall": round(wall, 2), "skelid_fit_cpu": round(cpu, 2),
                        "opensim_scaletool_wall": peer["seconds"],
                        "opensim_ik_walk_wall": ik_os["seconds"]},
            "skelid_sigma_mm": table["sigma_mm"], "markers_left_out": table["markers_left_out"]}


KEY_LENGTHS = [("pelvis width (hip-hip)", "femur_r", "femur_l"), ("thigh r (hip-knee)", "femur_r", "tibia_r"),
               ("thigh l (hip-knee)", "femur_l", "tibia_l"), ("shank r (knee-ankle)", "tibia_r", "talus_r"),
               ("shank l (knee-ankle)", "tibia_l", "talus_l")]


def key_lengths(path, theta=None, model=None) -> dict:
    if model is None:
        model, _ = read_osim(path)
    th = np.zeros(model.n_params) if theta is None else theta
    kin = forward_kinematics(model, th if theta is not None else model.theta_nominal, np.zeros(model.n_pose))
    idx = {s.name: i for i, s in enumerate(model.segments)}
    out = {}
    for name, a, b in KEY_LENGTHS:
        if a in idx and b in idx:
            out[name] = float(np.linalg.norm(kin.p_world_seg[idx[a]] - kin.p_world_seg[idx[b]]))
    return out


def subject4_peers(tmp: Path) -> dict:
    """Without a skelid fit: the peers' key lengths and IK RMSE on the walks."""
    models = {"addbiomechanics": S04 / "Models" / "optimized_scale_and_markers.osim",
              "expert": S04 / "Models" / "manually_scaled.osim",
              "generic": S04 / "Models" / "unscaled_generic.osim"}
    lengths = {k: key_lengths(v) for k, v in models.items()}
    ik = {m: {n: opensim_ik(models[m], S04 / "MarkerData" / f"{n}.trc", tmp / f"ik04_{m}_{n}")
              for n in ("walking1",)} for m in ("addbiomechanics", "expert")}
    return {"skelid_fit": "not run (--subject4 peers)", "key_lengths_mm": lengths, "ik": ik}


def subject4(tmp: Path, quick: bool) -> dict:
    names = ["static1", "walking1", "walking2", "squats1", "STS1", "DJ1"]
    fit_names = ["static1", "walking1"] if quick else ["static1", "walking1", "walking2"]
    trials = {n: read_markers(S04 / "MarkerData" / f"{n}.trc") for n in names}
    use = [trials[n] for n in fit_names]
    c0, t0 = _cpu(), time.perf_counter()
    fit = fit_osim(S04 / "Models" / "unscaled_generic.osim", use, scale="bodies", markers="offsets", joined=JOINED)
    wall, cpu = time.perf_counter() - t0, _cpu() - c0
    paths = write_outputs(fit, tmp / "skelid04")
    table = scaling_table(fit)
    models = {"skelid": paths["osim"], "addbiomechanics": S04 / "Models" / "optimized_scale_and_markers.osim",
              "expert": S04 / "Models" / "manually_scaled.osim",
              "generic": S04 / "Models" / "unscaled_generic.osim"}
    lengths = {k: key_lengths(v) for k, v in models.items()}
    ik = {}
    ik_trials = ["static1", "walking1", "walking2", "DJ1"]  # STS1, squats1 (1400 frames each): too long here
    for m in ("skelid", "addbiomechanics", "expert"):
        ik[m] = {n: opensim_ik(models[m], S04 / "MarkerData" / f"{n}.trc", tmp / f"ik04_{m}_{n}") for n in ik_trials}
    return {"fit_trials": fit_names, "static_frames": 30,
            "scales_skelid": {b: {"value": e["xyz"]["value"], "ci95": e["xyz"]["ci95"]}
                              for b, e in table["scales"].items()},
            "key_lengths_mm": lengths, "ik": ik,
            "seconds": {"skelid_fit_wall": round(wall, 2), "skelid_fit_cpu": round(cpu, 2)},
            "skelid_sigma_mm": table["sigma_mm"], "markers_left_out": table["markers_left_out"]}


def markdown(res: dict) -> str:
    s1, s4 = res["subject01"], res["subject4"]
    if "skelid_fit" in s4:
        return _markdown01(res, s1) + _markdown4_peers(s4)
    return _markdown01(res, s1) + _markdown4(s4)


def _markdown4_peers(s4: dict) -> str:
    lines = ["## subject4: LaiArnold generic model, AddBiomechanics and expert scalings", "",
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


def _markdown01(res: dict, s1: dict) -> str:
    lines = ["# OpenSim peers: ScaleTool and AddBiomechanics against skelid", "",
             f"{'REDUCED run (--quick). ' if res['reduced'] else ''}Machine: shared, 2 cores under load; "
             "times are wall clock and CPU seconds of one process.", "",
             "## subject01: gait2354, static + walk", "",
             f"skelid: {res.get('trials', 'joined')} fit ({s1['frames']['static']} static + "
             f"{s1['frames']['walk']} walk frames), one scale per body with markers, then offsets of every free "
             "marker placed on the static trial.", "",
             "| body | skelid scale [95 % interval] | OpenSim ScaleTool (x, y, z) |", "|---|---|---|"]
    for r in s1["scales"]:
        os_ = ", ".join(f"{v:.4f}" for v in r["opensim"]) if r["opensim"] else "-"
        lo, hi = r["skelid_ci95"]
        lines.append(f"| {r['body']} | {r['skelid']:.4f} [{lo:.4f}, {hi:.4f}] | {os_} |")
    ik = s1["ik_walk"]
    sec = s1["seconds"]
    lines += ["", "| | OpenSim IK marker RMSE on the walk (mm) | max (mm) | time (s) |", "|---|---|---|---|",
              f"| skelid-scaled model | {ik['skelid']['rmse_mm']:.1f} | {ik['skelid']['max_mm']:.1f} | "
              f"fit {sec['skelid_fit_wall']} wall, {sec['skelid_fit_cpu']} CPU |",
              f"| ScaleTool-scaled model | {ik['opensim_scaletool']['rmse_mm']:.1f} | "
              f"{ik['opensim_scaletool']['max_mm']:.1f} | ScaleTool {sec['opensim_scaletool_wall']} + "
              f"IK {sec['opensim_ik_walk_wall']} |", ""]
    return "\n".join(lines) + "\n"


def _markdown4(s4: dict) -> str:
    lines = ["## subject4: LaiArnold generic model, AddBiomechanics and expert scalings", "",
             f"skelid fitted to {', '.join(s4['fit_trials'])} (static trial: {s4['static_frames']} frames), "
             f"{s4['seconds']['skelid_fit_wall']} s wall, {s4['seconds']['skelid_fit_cpu']} s CPU.", "",
             "| length (mm) | generic | skelid | AddBiomechanics | expert |", "|---|---|---|---|---|"]
    L = s4["key_lengths_mm"]
    for name in L["generic"]:
        v = [L[m].get(name, float("nan")) for m in ("generic", "skelid", "addbiomechanics", "expert")]
        lines.append(f"| {name} | " + " | ".join(f"{x:.1f}" for x in v) + " |")
    lines += ["", "| trial | skelid IK RMSE (mm) | AddBiomechanics | expert |", "|---|---|---|---|"]
    for n in s4["ik"]["skelid"]:
        lines.append(f"| {n} | " + " | ".join(f"{s4['ik'][m][n]['rmse_mm']:.1f}"
                                               for m in ("skelid", "addbiomechanics", "expert")) + " |")
    lines += ["", "skelid scales (subject4): " + ", ".join(
        f"{b} {e['value']:.3f} [{e['ci95'][0]:.3f}, {e['ci95'][1]:.3f}]" for b, e in s4["scales_skelid"].items())]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames (results marked reduced)")
    ap.add_argument("--joined", action="store_true", help="fit the trials as one recording with gaps")
    ap.add_argument("--subject4", choices=("full", "peers"), default="full",
                    help="peers: no skelid fit of subject4, only the peers' lengths and IK on a walk")
    args = ap.parse_args(argv)
    global JOINED
    JOINED = args.joined
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    res = {"reduced": bool(args.quick), "trials": "joined" if args.joined else "multi-trial"}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        res["subject01"] = subject01(tmp, args.quick)
        print(json.dumps(res["subject01"]["seconds"]), flush=True)
        res["subject4"] = subject4(tmp, args.quick) if args.subject4 == "full" else subject4_peers(tmp)
    res["peak_memory_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "opensim_peer.json").write_text(json.dumps(res, indent=1) + "\n")
    (OUT / "opensim_peer.md").write_text(markdown(res))
    print(markdown(res))


if __name__ == "__main__":
    main()
