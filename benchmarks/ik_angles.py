"""Joint angles with uncertainty (:mod:`skelid.angles`) against OpenSim's inverse kinematics, and their coverage.

Part 1, real data: gait2354 (``../shared/data/opensim-subject01/gait2354_simbody.osim`` with
``gait2354_Scale_MarkerSet.xml``) fitted to ``subject01_static.trc`` + ``subject01_walk1.trc``
(:func:`skelid.scaling.fit_osim`, the command line's defaults), the scaled model written
(:func:`skelid.scaling.write_outputs`), then the walk's angles with skelid
(:func:`skelid.angles.joint_angles`, ``--draws`` draws of the geometry) and with OpenSim's
``InverseKinematicsTool`` on the same scaled ``.osim`` with the same markers, every weight 1
(:func:`skelid.scaling.opensim_ik`). Per coordinate: the rms difference over the frames
(degrees, or mm for translations), skelid's mean sd and the share of its variance from the
geometry.

Part 2, synthetic truth (``--coverage-reps N``, 0 to skip): the three-body leg of the tests
(a free pelvis, a ball hip, a knee with a coupled translation; 12 markers, none fixed). Each
repetition draws the body scales uniform in [0.9, 1.1] and every marker's offset from the fit's
prior (normal, 10 mm per axis), generates a static trial (6 frames) and a movement (48 frames, 60 Hz)
from the model with i.i.d. noise of sd ``--noise`` mm, fits both, runs :func:`joint_angles` on the
movement and counts how often the 95 % interval (``value ± 1.96 sd``) holds the true coordinate,
per coordinate, over frames and repetitions (frames of one repetition share its geometry error, so
the repetitions are the unit of replication).

Run: ``nice -n 10 python benchmarks/ik_angles.py [--draws 100] [--coverage-reps 100] [--quick]``
-> ``benchmarks/results/ik_angles.{json,md}``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import provenance, results_dir, write_results  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "opensim-subject01"
GENERIC = DATA / "gait2354_simbody.osim"
MARKER_SET = DATA / "gait2354_Scale_MarkerSet.xml"
STATIC = DATA / "subject01_static.trc"
WALK = DATA / "subject01_walk1.trc"

LEG = """<?xml version="1.0" encoding="UTF-8" ?>
<OpenSimDocument Version="40000"><Model name="leg"><length_units>meters</length_units>
<BodySet><objects><Body name="pelvis"/><Body name="thigh"/><Body name="shank"/></objects></BodySet>
<JointSet><objects>
<FreeJoint name="root"><socket_parent_frame>/ground</socket_parent_frame>
<socket_child_frame>/bodyset/pelvis</socket_child_frame>
<coordinates><Coordinate name="rx"/><Coordinate name="ry"/><Coordinate name="rz"/>
<Coordinate name="tx"/><Coordinate name="ty"/><Coordinate name="tz"/></coordinates></FreeJoint>
<BallJoint name="hip"><socket_parent_frame>pelvis_offset</socket_parent_frame>
<socket_child_frame>/bodyset/thigh</socket_child_frame>
<coordinates><Coordinate name="h1"/><Coordinate name="h2"/><Coordinate name="h3"/></coordinates>
<frames><PhysicalOffsetFrame name="pelvis_offset"><socket_parent>/bodyset/pelvis</socket_parent>
<translation>0.05 -0.08 0.09</translation><orientation>0.1 0 0.2</orientation></PhysicalOffsetFrame></frames>
</BallJoint>
<CustomJoint name="knee"><socket_parent_frame>/bodyset/thigh</socket_parent_frame>
<socket_child_frame>/bodyset/shank</socket_child_frame>
<coordinates><Coordinate name="k"><range>-2 0.2</range></Coordinate></coordinates>
<SpatialTransform>
<TransformAxis name="rotation1"><coordinates>k</coordinates><axis>0 0 1</axis>
<LinearFunction name="function"><coefficients>1 0</coefficients></LinearFunction></TransformAxis>
<TransformAxis name="translation1"><coordinates>k</coordinates><axis>1 0 0</axis>
<SimmSpline name="function"><x>-2 -1 0 0.5</x><y>-0.004 0.003 -0.002 -0.005</y></SimmSpline></TransformAxis>
<TransformAxis name="translation2"><coordinates>k</coordinates><axis>0 1 0</axis>
<SimmSpline name="function"><x>-2 -1 0 0.5</x><y>-0.42 -0.41 -0.40 -0.398</y></SimmSpline></TransformAxis>
</SpatialTransform></CustomJoint>
</objects></JointSet>
<MarkerSet><objects>
{markers}
</objects></MarkerSet></Model></OpenSimDocument>"""
LEG_MARKERS = {"pelvis": [(0.1, 0.05, 0.1), (0.1, 0.05, -0.1), (-0.1, 0.06, 0.0), (0.0, 0.1, 0.05)],
               "thigh": [(0.03, -0.1, 0.05), (0.04, -0.25, 0.06), (-0.03, -0.2, 0.05), (0.0, -0.38, 0.05)],
               "shank": [(0.03, -0.1, 0.04), (0.04, -0.25, 0.05), (-0.03, -0.2, 0.05), (0.0, -0.38, 0.04)]}


# ----------------------------------------------------------------------------- part 1: OpenSim IK
def opensim_comparison(draws: int, seed: int, frames: int | None) -> dict:
    """skelid's angles of the walk against OpenSim IK's on the scaled model skelid wrote."""
    import opensim as osim

    from skelid.angles import fitted_geometry, joint_angles
    from skelid.data import MarkerData
    from skelid.io import read_markers, write_trc
    from skelid.scaling import fit_osim, opensim_ik, write_outputs

    static, walk = read_markers(STATIC), read_markers(WALK)
    tmp = Path(tempfile.mkdtemp(prefix="skelid-ik-angles-"))
    walk_path = WALK
    if frames is not None and frames < walk.positions.shape[0]:
        walk = MarkerData(walk.positions[:frames], walk.names, walk.rate, walk.units, str(WALK), walk.meta)
        walk_path = tmp / "walk.trc"
        write_trc(walk_path, walk)
        walk = read_markers(walk_path)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = fit_osim(GENERIC, [static, walk], marker_set=MARKER_SET, seed=seed)
    t_fit = time.perf_counter() - t0
    paths = write_outputs(fit, tmp / "fit")
    geom = fitted_geometry(fit)
    t0 = time.perf_counter()
    ang = joint_angles(geom, walk, draws, np.random.default_rng(seed))
    t_ik = time.perf_counter() - t0
    lap = joint_angles(geom.laplace(), walk, draws, np.random.default_rng(seed))
    ref = opensim_ik(paths["osim"], walk_path, tmp / "osim", markers=geom.model.marker_names)
    table = osim.TimeSeriesTable(str(tmp / "osim" / "ik.mot"))
    in_deg = table.getTableMetaDataAsString("inDegrees").strip().lower() == "yes"
    labels = list(table.getColumnLabels())
    om = osim.Model(str(paths["osim"]))
    om.initSystem()
    cs = om.getCoordinateSet()
    rotational = {cs.get(i).getName(): cs.get(i).getMotionType() == 1 for i in range(cs.getSize())}
    rows = {}
    ranges = {c.name: c for c in geom.coordinates}
    for c, name in enumerate(ang.names):
        ours = ang.value[:, c]
        theirs = np.asarray(table.getDependentColumn(name).to_numpy()) if name in labels else None
        rot = bool(ang.rotational[c])
        unit = 180.0 / np.pi if rot else 1000.0
        row = {"unit": "deg" if rot else "mm", "status": ang.status[c],
               "opensim_says_rotational": rotational.get(name),
               "mean_sd": _mean(ang.sd[:, c]) * unit, "rms_sd_pose": _rms(ang.sd_pose[:, c]) * unit,
               "rms_sd_geometry": _rms(ang.sd_geometry[:, c]) * unit,
               "rms_sd_geometry_linear": _rms(ang.sd_geometry_linear[:, c]) * unit,
               "geometry_share": float(ang.geometry_share()[c]),
               "laplace_mean_sd": _mean(lap.sd[:, c]) * unit,
               "laplace_geometry_share": float(lap.geometry_share()[c]),
               "frames_outside_range": int(ang.outside_range[c])}
        if theirs is not None and theirs.shape == ours.shape:
            theirs_si = np.radians(theirs) if (rot and in_deg) else theirs
            d = ours - theirs_si
            if rot:
                d = (d + np.pi) % (2 * np.pi) - np.pi
            ok = np.isfinite(d)
            row["rms_difference_all_frames"] = float(np.sqrt(np.mean(d[ok] ** 2)) * unit) if ok.any() else None
            # both well posed: OpenSim's value not held at a bound of a clamped coordinate
            co = ranges[name]
            held = np.zeros_like(ok)
            if co.clamped:
                tol = 1e-6
                held = (theirs_si <= co.range[0] + tol) | (theirs_si >= co.range[1] - tol)
            ok &= ~held
            row["frames_at_opensim_bound"] = int(held.sum())
            row["rms_difference"] = float(np.sqrt(np.mean(d[ok] ** 2)) * unit) if ok.any() else None
            row["max_difference"] = float(np.max(np.abs(d[ok])) * unit) if ok.any() else None
        rows[name] = row
    cost_ours, cost_theirs = _costs(geom, walk, ang, table)
    gap = _model_gap(geom, paths["osim"], ang, table)
    tight = _opensim_ik_tight(paths["osim"], walk_path, tmp / "osim_tight", geom.model.marker_names)
    tight_rms = {}
    for c, name in enumerate(ang.names):
        if ang.status[c] != "fitted" or name not in labels:
            continue
        rot = bool(ang.rotational[c])
        v = np.asarray(tight.getDependentColumn(name).to_numpy())
        v = np.radians(v) if (rot and in_deg) else v
        d = ang.value[:, c] - v
        d = (d + np.pi) % (2 * np.pi) - np.pi if rot else d
        tight_rms[name] = float(np.sqrt(np.nanmean(d**2)) * (180.0 / np.pi if rot else 1000.0))
    return {"frames": int(ang.time.size), "frames_fixed": int(ang.fixed.sum()), "draws": draws,
            "markers": len(geom.model.markers), "covariance": geom.covariance, "sigma_mm": ang.sigma,
            "seconds_fit": round(t_fit, 1), "seconds_ik": round(t_ik, 1), "opensim_ik": ref,
            "coordinate_order_matches_opensim": labels == list(ang.names),
            "motion_types_match_opensim": all(rotational.get(n) == bool(r) for n, r in
                                              zip(ang.names, ang.rotational, strict=True)),
            "model_gap_mm": gap,
            "rms_difference_to_opensim_accuracy_1e-8": tight_rms,
            "frames_skelid_cost_not_above_opensim": float(np.mean(cost_ours <= cost_theirs * (1 + 1e-9))),
            "median_relative_cost_excess_of_opensim": float(np.median((cost_theirs - cost_ours) / cost_ours)),
            "widening_range": [float(np.min(geom.widening)), float(np.max(geom.widening))]
            if geom.widening is not None else None,
            "coordinates": rows}


def _opensim_ik_tight(osim_path, trc_path, out_dir, markers, accuracy=1e-8):
    """OpenSim's InverseKinematicsTool as :func:`skelid.scaling.opensim_ik` runs it, at a tighter accuracy."""
    import opensim as osim

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    model = osim.Model(str(osim_path))
    model.initSystem()
    tool = osim.InverseKinematicsTool()
    tool.setModel(model)
    tool.setMarkerDataFileName(str(trc_path))
    tasks = tool.getIKTaskSet()
    for n in markers:
        t = osim.IKMarkerTask()
        t.setName(n)
        t.setApply(True)
        t.setWeight(1.0)
        tasks.cloneAndAppend(t)
    tvec = np.asarray(osim.TimeSeriesTableVec3(str(trc_path)).getIndependentColumn())
    tool.setStartTime(float(tvec[0]))
    tool.setEndTime(float(tvec[-1]))
    tool.set_accuracy(accuracy)
    tool.setResultsDir(str(out_dir))
    tool.setOutputMotionFileName(str(out_dir / "ik.mot"))
    tool.run()
    return osim.TimeSeriesTable(str(out_dir / "ik.mot"))


def _model_gap(geom, osim_path, ang, table) -> float:
    """Largest distance (mm) between OpenSim's markers and skelid's at OpenSim's IK coordinates, every frame."""
    import opensim as osim

    from skelid.angles import coordinate_map
    from skelid.model.kinematics import marker_positions

    om = osim.Model(str(osim_path))
    state = om.initSystem()
    cs, ms = om.getCoordinateSet(), om.getMarkerSet()
    index, factor = coordinate_map(geom.model, geom.coordinates)
    in_deg = table.getTableMetaDataAsString("inDegrees").strip().lower() == "yes"
    cols = {n: np.asarray(table.getDependentColumn(n).to_numpy()) for n in ang.names}
    worst = 0.0
    for t in range(ang.time.size):
        q = np.zeros(geom.model.n_pose)
        for c, n in enumerate(ang.names):
            v = cols[n][t]
            v = np.radians(v) if (ang.rotational[c] and in_deg) else v
            cs.get(n).setValue(state, float(v), False)
            if index[c] >= 0:
                q[index[c]] = v / factor[c]
        om.realizePosition(state)
        x = marker_positions(geom.model, geom.theta, q)
        ref = np.array([[ms.get(m.name).getLocationInGround(state).get(i) for i in range(3)]
                        for m in geom.model.markers]) * 1000.0
        worst = max(worst, float(np.abs(x - ref).max()))
    return worst


def _costs(geom, walk, ang, table):
    """Each frame's sum of squared marker residuals (mm^2) at skelid's coordinates and at OpenSim's."""
    from skelid.angles import _markers_mm, coordinate_map
    from skelid.model.kinematics import marker_positions

    index, factor = coordinate_map(geom.model, geom.coordinates)
    y = _markers_mm(geom.model, walk)
    ours = np.zeros((y.shape[0], geom.model.n_pose))
    theirs = np.zeros_like(ours)
    in_deg = table.getTableMetaDataAsString("inDegrees").strip().lower() == "yes"
    for c, name in enumerate(ang.names):
        k = index[c]
        if k < 0:
            continue
        v = np.asarray(table.getDependentColumn(name).to_numpy())
        v = np.radians(v) if (ang.rotational[c] and in_deg) else v
        ours[:, k] = ang.value[:, c] / factor[c]
        theirs[:, k] = v / factor[c]

    def cost(q):
        return np.nansum((marker_positions(geom.model, geom.theta, q) - y) ** 2, axis=(1, 2))
    return cost(ours), cost(theirs)


def _mean(x) -> float:
    x = np.asarray(x, float)
    return float(np.mean(x[np.isfinite(x)])) if np.isfinite(x).any() else float("nan")


def _rms(x) -> float:
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x[np.isfinite(x)] ** 2))) if np.isfinite(x).any() else float("nan")


# ----------------------------------------------------------------------------- part 2: coverage
def _leg_trials(path, rng, noise_mm):
    """A static trial and a movement of the leg at drawn scales and offsets; their true poses (F, Q)."""
    from skelid.data import MarkerData
    from skelid.io.osim import osim_parameters, read_osim
    from skelid.model.kinematics import marker_positions

    base, info = read_osim(path)
    model = osim_parameters(base, info, "bodies", "offsets")
    theta = model.theta_nominal.copy()
    for k, p in enumerate(model.parameters):
        theta[k] = rng.uniform(0.9, 1.1) if p.kind == "scale" else rng.normal(0.0, p.prior.sd)
    t = np.arange(48) / 60.0
    q = np.zeros((48, model.n_pose))
    ph = rng.uniform(0, 2 * np.pi, 6)
    q[:, 3:6] = [100.0, 900.0, 50.0]
    q[:, 3] += 400 * t
    q[:, 0] = 0.2 * np.sin(2 * np.pi * 0.5 * t + ph[0])
    q[:, 6] = 0.5 * np.sin(2 * np.pi * 1.1 * t + ph[1])
    q[:, 7] = 0.3 * np.sin(2 * np.pi * 0.7 * t + ph[2])
    q[:, 8] = 0.3 * np.sin(2 * np.pi * 0.9 * t + ph[3])
    q[:, 9] = -0.9 + 0.8 * np.sin(2 * np.pi * 1.3 * t + ph[4])
    static = np.zeros((6, model.n_pose))
    static[:, 3:6] = [0.0, 900.0, 0.0]
    out = []
    for qq in (static, q):
        x = marker_positions(model, theta, qq) + rng.normal(0, noise_mm, (len(qq), len(model.markers), 3))
        out.append(MarkerData(x, model.marker_names, 60.0, "mm", "sim"))
    return out, q


def coverage(reps: int, draws: int, noise_mm: float, seed: int) -> dict:
    """Coverage of the true coordinates by the 95 % intervals on the synthetic leg, per coordinate."""
    from skelid.angles import coordinate_map, fitted_geometry, joint_angles
    from skelid.scaling import fit_osim

    tmp = Path(tempfile.mkdtemp(prefix="skelid-ik-coverage-"))
    text = "\n".join(f'<Marker name="{b}{i}"><socket_parent_frame>/bodyset/{b}</socket_parent_frame>'
                     f'<location>{x} {y} {z}</location></Marker>'
                     for b, locs in LEG_MARKERS.items() for i, (x, y, z) in enumerate(locs))
    path = tmp / "leg.osim"
    path.write_text(LEG.format(markers=text))
    kinds = ("reported", "laplace")
    hits, z2, n, failures, names = {}, {}, 0, [], None
    t0 = time.perf_counter()
    for r in range(reps):
        rng = np.random.default_rng([seed, r])
        (static, move), q_true = _leg_trials(path, rng, noise_mm)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                fit = fit_osim(path, [static, move], seed=r)
            geom = fitted_geometry(fit)
            out = {"reported": joint_angles(geom, move, draws, np.random.default_rng([seed, r, 1])),
                   "laplace": joint_angles(geom.laplace(), move, draws, np.random.default_rng([seed, r, 1]))}
        except Exception as exc:  # a failed repetition is counted, never hidden
            failures.append(f"{r}: {type(exc).__name__}: {exc}")
            continue
        index, factor = coordinate_map(geom.model, geom.coordinates)
        truth = q_true[:, index] * factor
        for kind, a in out.items():
            d = a.value - truth
            d = np.where(a.rotational, (d + np.pi) % (2 * np.pi) - np.pi, d)
            inside = (np.abs(d) <= 1.959964 * a.sd) & np.isfinite(a.sd)
            names = a.names
            hits[kind] = hits.get(kind, 0.0) + inside.mean(axis=0)
            z2[kind] = z2.get(kind, 0.0) + np.nanmean((d / a.sd) ** 2, axis=0)
        n += 1
    res = {"reps": reps, "reps_done": n, "draws": draws, "noise_mm": noise_mm, "frames": 48,
           "seconds": round(time.perf_counter() - t0, 1), "failures": failures}
    for kind in kinds:
        rows = {}
        if n:
            for c, name in enumerate(names):
                rows[name] = {"coverage_95": float(hits[kind][c] / n), "rms_z": float(np.sqrt(z2[kind][c] / n))}
        key = "coordinates" if kind == "reported" else "laplace_coordinates"
        res[key] = rows
        res["mean_coverage_95" if kind == "reported" else "laplace_mean_coverage_95"] = (
            float(np.mean([v["coverage_95"] for v in rows.values()])) if rows else None)
    return res


# ----------------------------------------------------------------------------- report
def markdown(res: dict) -> str:
    p = res["provenance"]
    lines = ["# Joint angles with uncertainty against OpenSim IK", "",
             f"Commit {p['commit']}, {p['date']}, {p['cpu']} ({p['cores']} cores); `{p['command']}`", ""]
    o = res.get("opensim")
    if o:
        ik = o["opensim_ik"]
        lines += [f"subject01 walk, {o['frames']} frames ({o['frames_fixed']} with the pose fixed), {o['markers']} "
                  f"markers, {o['draws']} draws of the geometry ({o['covariance']} covariance); marker noise "
                  f"{o['sigma_mm']:.2f} mm; OpenSim IK marker rms {ik['rmse_mm']:.2f} mm. Fit {o['seconds_fit']} s, "
                  f"skelid ik {o['seconds_ik']} s, OpenSim IK {ik['seconds']} s. Coordinate order as OpenSim's: "
                  f"{o['coordinate_order_matches_opensim']}; motion types as OpenSim's: "
                  f"{o['motion_types_match_opensim']}.", "",
                  f"skelid's marker cost is at or below OpenSim's on {o['frames_skelid_cost_not_above_opensim']:.0%} "
                  f"of the frames (OpenSim's median excess {o['median_relative_cost_excess_of_opensim']:.1e}); "
                  f"the two models' markers agree to {o['model_gap_mm']:.1e} mm at OpenSim's coordinates; OpenSim "
                  "IK at accuracy 1e-8 instead of 1e-5 differs from skelid by (deg / mm) " + ", ".join(
                      f"{n} {v:.2f}" for n, v in o["rms_difference_to_opensim_accuracy_1e-8"].items()) + ". "
                  "Differences over the frames where OpenSim does not hold the coordinate at a bound of its range "
                  "(frames held in brackets). " + (
                      f"The fit's checks widened its parameters' sd by {o['widening_range'][0]:.1f} to "
                      f"{o['widening_range'][1]:.1f}; " if o.get("widening_range") else "")
                  + "the last two columns use the Laplace covariance before that widening.", "",
                  "| coordinate | unit | rms diff to OpenSim | max diff | mean sd | sd pose | sd geometry "
                  "(draws / first order) | geometry share | mean sd, Laplace | geometry share, Laplace |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for n, r in o["coordinates"].items():
            def f(v, fmt=".3f"):
                return "-" if v is None or not np.isfinite(v) else format(v, fmt)
            held = f" ({r['frames_at_opensim_bound']})" if r.get("frames_at_opensim_bound") else ""
            lines.append(f"| {n} | {r['unit']} | {f(r.get('rms_difference'))}{held} | {f(r.get('max_difference'))} | "
                         f"{f(r['mean_sd'])} | {f(r['rms_sd_pose'])} | {f(r['rms_sd_geometry'])} / "
                         f"{f(r['rms_sd_geometry_linear'])} | {f(r['geometry_share'], '.2f')} | "
                         f"{f(r['laplace_mean_sd'])} | {f(r['laplace_geometry_share'], '.2f')} |")
        lines.append("")
    c = res.get("coverage")
    if c and c["coordinates"]:
        lines += [f"Coverage on the synthetic leg: {c['reps_done']} of {c['reps']} repetitions, {c['draws']} draws, "
                  f"noise {c['noise_mm']} mm, {c['frames']} frames each ({c['seconds']} s); mean coverage of the "
                  f"95 % intervals {c['mean_coverage_95']:.3f} with the reported covariance, "
                  f"{c['laplace_mean_coverage_95']:.3f} with the Laplace covariance.", "",
                  "| coordinate | coverage 95 % | rms z | coverage 95 %, Laplace | rms z, Laplace |",
                  "|---|---|---|---|---|"]
        for n, r in c["coordinates"].items():
            lp = c["laplace_coordinates"][n]
            lines.append(f"| {n} | {r['coverage_95']:.3f} | {r['rms_z']:.2f} | {lp['coverage_95']:.3f} | "
                         f"{lp['rms_z']:.2f} |")
        if c["failures"]:
            lines += ["", "Failed repetitions: " + "; ".join(c["failures"])]
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=100)
    ap.add_argument("--frames", type=int, default=None, help="first frames of the walk only (default: all)")
    ap.add_argument("--coverage-reps", type=int, default=100)
    ap.add_argument("--coverage-draws", type=int, default=50)
    ap.add_argument("--noise", type=float, default=2.0, help="marker noise of the synthetic trials (mm)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="40 frames, 20 draws, 5 coverage repetitions")
    ap.add_argument("--skip-opensim", action="store_true")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.quick:
        args.frames, args.draws, args.coverage_reps, args.coverage_draws = 40, 20, 5, 20
    out = args.out or results_dir() / "ik_angles"
    res = {"provenance": provenance(None if argv is None else ["benchmarks/ik_angles.py", *argv]),
           "quick": bool(args.quick)}
    if not args.skip_opensim:
        res["opensim"] = opensim_comparison(args.draws, args.seed, args.frames)
    if args.coverage_reps > 0:
        res["coverage"] = coverage(args.coverage_reps, args.coverage_draws, args.noise, args.seed)
    write_results(out, _finite(res), markdown)


def _finite(obj):
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    if isinstance(obj, float | np.floating):
        return float(obj) if np.isfinite(obj) else None
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


if __name__ == "__main__":
    main()
