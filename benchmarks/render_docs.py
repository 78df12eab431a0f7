"""Write the figures the README and docs quote from the results files.

    python benchmarks/render_docs.py           # rewrite every generated block in README.md and docs/*.md
    python benchmarks/render_docs.py --check   # exit 1 (and show the difference) where a block is not what
                                               # the results give

A generated block is the text between ``<!-- results:NAME -->`` and ``<!-- /results:NAME -->``;
``RENDERERS`` maps each NAME to the function that makes it from the JSON in ``benchmarks/results``
(``benchmarks/experiments`` where a table has not been measured on the current code yet: the block
then says which tag of which file it shows). Each block ends with the file it came from and that
file's provenance. A figure the docs quote outside such a block is a figure nobody regenerates:
put it in a block. ``tests/test_docs_figures.py`` runs ``--check``.
"""

from __future__ import annotations

import argparse
import difflib
import json
import math
import re
import sys
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
EXPERIMENTS = ROOT / "benchmarks" / "experiments"
BLOCK = re.compile(r"(<!-- results:([\w-]+) -->\n)(.*?)(<!-- /results:\2 -->)", re.S)


def documents(root: Path = ROOT) -> list[Path]:
    """The files whose blocks are generated: README.md and docs/*.md."""
    return [root / "README.md", *sorted((root / "docs").glob("*.md"))]


def load(path: Path):
    return json.loads(path.read_text())


def rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def source(path: Path, doc=None, what: str = "") -> str:
    """The line that closes a block: the results file and its provenance."""
    doc = load(path) if doc is None else doc
    p = doc.get("provenance") if isinstance(doc, dict) else None
    legacy = (doc.get("date") or doc.get("meta", {}).get("date")) if isinstance(doc, dict) else None
    made = (f"commit {p['commit'][:10]}{' (uncommitted changes)' if p.get('dirty') else ''}, {p['date']}, "
            f"{p['cpu']} ({p['cores']} cores, load {p['load_average'][0]:.1f}), `{p['command']}`"
            if p and "command" in p else (f"written {legacy}, " if isinstance(legacy, str) else "written ")
            + "before results files recorded their provenance"
            + ("; `python benchmarks/run_all.py --full` remakes it" if path.parent == RESULTS else ""))
    runs = doc.get("section_runs") if isinstance(doc, dict) else None
    if isinstance(runs, dict) and len(runs) > 1:  # a file whose sections are run one at a time (speed.json)
        made = "its sections run separately: " + "; ".join(
            f"{name} " + (f"commit {r['commit'][:10]}, {r['date']}" if r.get("commit") else
                          f"{r.get('date', '?')}, before sections recorded their commit")
            for name, r in runs.items()) + "; `python benchmarks/speed.py --only SECTION` remakes one"
    return f"<sub>From [`{rel(path)}`](/{rel(path)}){what}: {made}.</sub>\n"


# ---------------------------------------------------------------- the demo


def demo() -> str:
    """The table ``skelid demo`` prints (seed 0), from benchmarks/results/demo.json."""
    path = RESULTS / "demo.json"
    doc = load(path)
    head = (f"{'case':<8} {'method':<8} {'param':<14} {'mean':>9} {'sd':>8} {'95% interval':^22} "
            f"{'truth':>8} {'frames':>6}")
    rows = [head, "-" * len(head)]
    for case in ("case_a", "case_b"):
        run = doc[case]
        for mname, r in run["results"].items():
            for pname, p in r["parameters"].items():
                t = run.get("truth", {}).get(pname)
                rows.append(f"{case:<8} {mname:<8} {pname:<14} {p['mean']:>9.5g} {p['sd']:>8.3g} "
                            f"[{p['interval'][0]:8.5g}, {p['interval'][1]:8.5g}] "
                            f"{'' if t is None else f'{t:8.5g}':>8} {r['frames']['used']:>6}")
    return "```text\n" + "\n".join(rows) + "\n```\n\n" + source(path, doc)


# ---------------------------------------------------------------- OpenSim


def opensim_scales() -> str:
    """subject01: skelid's scale factors with their intervals beside the ScaleTool's; IK RMSE; CPU time."""
    path = RESULTS / "opensim_peer.json"
    doc = load(path)
    s = doc["subject01"]
    lines = ["| body | skelid factor [95 % interval] | OpenSim ScaleTool |", "|---|---|---|"]
    bodies: dict = {}  # a body fitted per axis: its three factors in one row
    for row in s["scales"]:
        name, _, axis = row["body"].rpartition(" ")
        body, axis = (name, axis) if name and axis in ("x", "y", "z") else (row["body"], "")
        bodies.setdefault(body, []).append((axis, row))
    for body, rows in bodies.items():
        tool = sorted({v for _, row in rows for v in row["opensim"]})
        cells = "; ".join(f"{axis + ' ' if axis else ''}{row['skelid']:.3f} [{row['skelid_ci95'][0]:.3f}, "
                          f"{row['skelid_ci95'][1]:.3f}]" for axis, row in rows)
        lines.append(f"| {body} | {cells} | {', '.join(f'{v:.3f}' for v in tool)} |")
    ik, sec = s["ik_walk"], s["seconds"]
    lines += ["", f"OpenSim's inverse kinematics on the walk: marker RMSE {ik['skelid']['rmse_mm']:.1f} mm with "
              f"skelid's scaled model, {ik['opensim_scaletool']['rmse_mm']:.1f} mm with the ScaleTool's; skelid's "
              f"fit {sec['skelid_fit']['cpu_s']:.1f} s of CPU, the ScaleTool {sec['opensim_scaletool']['cpu_s']:.1f} s"
              + (" (a reduced run)" if doc.get("reduced") else "") + "."]
    return "\n".join(lines) + "\n\n" + source(path, doc)


def opensim_subject4() -> str:
    """subject4: key lengths (mm) of skelid's, AddBiomechanics' and the expert's models; IK RMSE per trial."""
    path = RESULTS / "opensim_peer.json"
    doc = load(path)
    s = doc["subject4"]
    kl = s["key_lengths_mm"]
    peers = [k for k in ("skelid", "addbiomechanics", "expert") if k in kl]
    lines = ["| length (mm) | " + " | ".join(peers) + " |", "|---" * (len(peers) + 1) + "|"]
    for name in kl["skelid"]:
        lines.append(f"| {name} | " + " | ".join(f"{kl[p][name]:.1f}" for p in peers) + " |")
    ik = s["ik"]
    trials = list(ik["skelid"])
    who = [k for k in ik]
    lines += ["", "| IK marker RMSE (mm) | " + " | ".join(trials) + " |", "|---" * (len(trials) + 1) + "|"]
    for w in who:
        lines.append(f"| {w} | " + " | ".join(f"{ik[w][t]['rmse_mm']:.1f}" if t in ik[w] else "—" for t in trials)
                     + " |")
    lines += ["", f"skelid's fit of the {len(s['fit_trials'])} trials: {s['seconds']['skelid_fit']['cpu_s']:.0f} s "
              "of CPU."]
    return "\n".join(lines) + "\n\n" + source(path, doc)


def _truth_values(rows: dict, prefix: str, key: str) -> list:
    """``key`` of every row of an OpenSim-truth cell whose quantity starts with ``prefix`` (where given)."""
    return [r[key] for q, r in rows.items() if q.startswith(prefix) and r.get(key) is not None]


def _median_text(v) -> str:
    return f"{sorted(v)[len(v) // 2]:.2f}" if v else "—"


def _share_text(cell: dict, key: str) -> str:
    v = cell.get(key)
    return "—" if v is None else f"{v:.0%}"


def _pooled_text(cell: dict, kind: str, cls: str = "data-determined") -> str:
    """A cell's coverage and rms z pooled over its parameters of ``kind`` that the data determine."""
    v = (cell.get("classes") or {}).get(f"{kind}, {cls}")
    return "—" if not v else f"{v['coverage95']:.2f} (rms z {v['rms_z']:.2f})"


def _points_text(cell: dict, kind: str) -> str:
    """A cell's body-frame points of ``kind`` pooled: coverage per axis / of the 3-D region."""
    v = (cell.get("points") or {}).get(kind)
    return "—" if not v else f"{v['coverage95_axes']:.2f} / {v['region_coverage95']:.2f}"


JOINTS_KIND, MARKERS_KIND = "joint centres (parent body frame)", "markers (own body frame)"


def _truth_cells() -> tuple[dict, str]:
    """The OpenSim-truth cells of the main table, of the default fit's file and of the 100-draw runs (each
    later file's cells taking precedence), and the source lines of each."""
    cells, sources = {}, []
    for name in ("opensim_truth.json", "opensim_truth_default.json", "opensim_truth_iid100.json",
                 "opensim_truth_sta100.json", "opensim_truth_sta1walk100.json", "opensim_truth_angles100.json",
                 "opensim_truth_pm100.json", "opensim_truth_stalab100.json", "opensim_truth_bodies100.json"):
        path = RESULTS / name
        if path.exists():
            doc = load(path)
            # each cell beside the peer (ScaleTool) of its own draws, from its own file
            cells.update({k: dict(c, peers=doc["cells"]) for k, c in doc["cells"].items()})
            sources.append(source(path, doc))
    return cells, "\n".join(sources)


def _peer_rmse(cells: dict, key: str) -> list:
    """ScaleTool's length RMSE on the draws of cell ``key`` (the same file's peer cell), per length."""
    truth, _, design, noise = key.split("/")
    peers = cells[key].get("peers", cells)
    return _truth_values(peers.get(f"{truth}/scaletool/{design}/{noise}", {}).get("rows", {}), "length", "rmse")


def opensim_truth() -> str:
    """Coverage on models whose true scales are known (benchmarks/opensim_truth.py), once it has run."""
    path = RESULTS / "opensim_truth.json"
    if not path.exists():
        return ("*Not measured yet.* `benchmarks/opensim_truth.py` (markers simulated on OpenSim models of known "
                "scale) writes `benchmarks/results/opensim_truth.json`; `python benchmarks/run_all.py --full` then "
                "`python benchmarks/render_docs.py` put its coverage here.\n")
    cells, sources = _truth_cells()
    lines = ["| cell (truth/fit/design/noise) | draws | coverage 95 %: scales, median (min) | lengths | offsets "
             "| pooled, data-determined: scales | offsets | joint centres in body frames: per axis / region "
             "| markers: per axis / region | RMSE/sd, scales (median) | length RMSE (mm): skelid "
             "| ScaleTool | artefact found / named | CPU s per fit |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for key, c in cells.items():
        truth, fit, design, noise = key.split("/")
        if fit == "scaletool" or not c["rows"]:
            continue
        rows = c["rows"]
        sc, ln, of = (_truth_values(rows, p, "coverage95") for p in ("scale", "length", "offset"))
        rs = _truth_values(rows, "scale", "rmse_over_sd")
        lr = _truth_values(rows, "length", "rmse")
        pr = _peer_rmse(cells, key)
        med = _median_text
        lines.append(f"| {key} | {c['n']}" + (f" ({c['failed']} failed)" if c["failed"] else "")
                     + f" | {med(sc)} ({min(sc):.2f}) | {med(ln)} | {med(of)} | {_pooled_text(c, 'scales')} | "
                     f"{_pooled_text(c, 'offsets')} | {_points_text(c, JOINTS_KIND)} | "
                     f"{_points_text(c, MARKERS_KIND)} | {med(rs)} | "
                     f"{sum(lr) / len(lr):.1f} | " + (f"{sum(pr) / len(pr):.1f}" if pr else "—")
                     + f" | {_share_text(c, 'share_artefact_term')} / {_share_text(c, 'share_artefact_named')}"
                     + f" | {c['cpu_s_per_fit']:.0f} |")
    note = ("Geometry drawn per draw; each cell from the last of the files below that holds it (the 100-draw runs "
            "after the 24-draw ones). "
            "Lengths: hip-knee and knee-ankle per side; RMSE averaged over the four. Body frames: every joint "
            "centre in its parent body's frame and every marker in its own, at the zero pose, pooled over them "
            "and the draws: the coverage of each coordinate's interval, and of the 3-D 95 % region (chi-square, "
            "3 degrees of freedom); '—' where the results predate them. Per quantity: the Markdown file beside "
            "each cell's JSON file below.")
    out = "\n".join(lines) + "\n\n" + note + "\n\n" + _angles_table(cells) + sources
    exact, prior = RESULTS / "opensim_truth_exact.json", RESULTS / "opensim_truth_prior.json"
    raj = RESULTS / "opensim_truth_rajagopal.json"
    out += ("\n" + opensim_truth_rajagopal(raj) if raj.exists() else "")
    out += ("\n" + opensim_truth_prior(prior) if prior.exists() else "")
    return out + ("\n" + opensim_truth_exact(exact) if exact.exists() else "")


RAJAGOPAL = "the full-body Rajagopal-type model of `addbio-subject4`"


def _rajagopal_cells(doc: dict) -> list:
    """The fitted cells of the Rajagopal run: ``(key, cell, length coverages, mean length RMSE)``."""
    out = []
    for key, c in doc["cells"].items():
        if key.split("/")[1] == "scaletool" or not c["rows"]:
            continue
        ln = _truth_values(c["rows"], "length", "coverage95")
        lr = _truth_values(c["rows"], "length", "rmse")
        out.append((key, c, ln, sum(lr) / len(lr)))
    return out


def opensim_truth_rajagopal(path: Path) -> str:
    """The same study on the Rajagopal model: landmark (fixed) markers, placeholder clusters, unmarked bodies."""
    doc = load(path)
    lines = [f"| {RAJAGOPAL}: cell | draws | mean σ (mm) | lengths: coverage (min-max), RMSE (mm) "
             "| pooled, data-determined: scales | prior-dominated | offsets "
             "| joint centres in body frames: per axis / region | markers: per axis / region | CPU s per fit |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for key, c, ln, lr in _rajagopal_cells(doc):
        lines.append(f"| {key} | {c['n']}" + (f" ({c['failed']} failed)" if c["failed"] else "")
                     + f" | {c.get('sigma_mean') or float('nan'):.2f} | {min(ln):.2f}-{max(ln):.2f}, {lr:.1f} | "
                     f"{_pooled_text(c, 'scales')} | {_pooled_text(c, 'scales', 'prior-dominated')} | "
                     f"{_pooled_text(c, 'offsets')} | {_points_text(c, JOINTS_KIND)} | "
                     f"{_points_text(c, MARKERS_KIND)} | {c['cpu_s_per_fit']:.0f} |")
    return ("\n".join(lines) + "\n\nThe model of `Models/unscaled_generic.osim`: 49 markers, 31 of them `fixed` "
            "landmarks, the thigh and shank clusters held at one placeholder point per body; motion from its walks "
            "(OpenSim IK on the expert's scaled model), 100 Hz. Truth `axes`: the bodies with markers scaled per "
            "axis; `every`: every body (talus, toes, patella, ulna, hand too), as OpenSim's scale setups do. Every "
            "marker, landmarks included, moved 1-20 mm. Lengths: hip-knee, knee-ankle and shoulder-elbow per side. "
            "No ScaleTool peer: the model comes without a measurement setup. Per quantity: "
            "[`benchmarks/results/opensim_truth_rajagopal.md`](/benchmarks/results/opensim_truth_rajagopal.md)."
            "\n\n" + source(path, doc))


def opensim_truth_prior(path: Path) -> str:
    """Truth drawn from the fit's own priors: coverage pooled over every scale and offset, by who decides them."""
    doc = load(path)
    lines = ["| truth from the fit's priors: cell | draws | scales: data-determined | prior-dominated "
             "| offsets: data-determined | prior-dominated | lengths: coverage (min-max) |",
             "|---|---|---|---|---|---|---|"]
    for key, c in doc["cells"].items():
        if key.split("/")[1] == "scaletool" or not c["rows"]:
            continue
        ln = _truth_values(c["rows"], "length", "coverage95")
        lines.append(f"| {key} | {c['n']} | {_pooled_text(c, 'scales')} | "
                     f"{_pooled_text(c, 'scales', 'prior-dominated')} | {_pooled_text(c, 'offsets')} | "
                     f"{_pooled_text(c, 'offsets', 'prior-dominated')} | "
                     f"{min(ln):.2f}-{max(ln):.2f} |")
    return ("\n".join(lines) + "\n\nFactors (log-normal, sd 0.15 per axis) and offsets (normal, 10 mm) drawn from "
            "the priors the fit uses: a right posterior covers 95 % of every quantity here, also of those the data "
            "leave to the prior (the uniform truths above are narrower than the priors, so there an interval the "
            "prior decides covers more often). Data-determined: the fit's bound at most half the prior's sd; rms z: "
            "root mean square of error / reported sd. Per quantity: "
            "[`benchmarks/results/opensim_truth_prior.md`](/benchmarks/results/opensim_truth_prior.md).\n\n"
            + source(path, doc))


#: the README's lines: what each sums up, and its cells (several: one line, the coverage of each named)
SUMMARY_CELLS = (("the exact model (one factor per axis), static + walk, i.i.d. 5 mm",
                  (("", "axes/axes/static+walk/5"),)),
                 ("the default (three linked factors per body), static + walk, i.i.d. 5 mm",
                  (("per-axis truth", "axes/linked/static+walk/5"), ("one factor per body in truth",
                                                                      "bodies/linked/static+walk/5"))),
                 ("one factor per body (`--scale bodies`) on per-axis truth, static + walk, i.i.d. 5 mm",
                  (("", "axes/bodies/static+walk/5"),)),
                 ("the default, per-marker noise 1-10 mm, static + walk",
                  (("pooled noise", "axes/linked/static+walk/pm"),
                   ("`--noise per-marker`", "axes/linked+pm/static+walk/pm"))),
                 ("the default, soft-tissue artefact 5-15 mm rms, linear in the joint angles in each body's frame",
                  (("static + walk", "axes/linked/static+walk/sta"), ("one walk", "axes/linked/walk/sta"),
                   ("two walks", "axes/linked/walk+walk2/sta"),
                   ("two walks, the slide in the laboratory's frame (a form skelid does not model)",
                    "axes/linked/walk+walk2/stalab"))))


def _angles_table(cells: dict) -> str:
    """Per coordinate, the coverage of the walk's joint angles (``skelid ik``) in the cells that scored them."""
    scored = {k: c["angles"] for k, c in cells.items() if c.get("angles")}
    if not scored:
        return ""
    keys = list(scored)
    names = list(next(iter(scored.values())))
    lines = ["| joint angle of the walk (`skelid ik`, first order) | unit | "
             + " | ".join(f"{k}: coverage 95 % (rms z)" for k in keys) + " | geometry's share of the variance |",
             "|---|---|" + "---|" * len(keys) + "---|"]
    for n in names:
        cols = [f"{scored[k][n]['coverage95']:.2f} ({scored[k][n]['rms_z']:.2f})" if n in scored[k] else "—"
                for k in keys]
        lines.append(f"| {n} | {scored[keys[0]][n]['unit']} | " + " | ".join(cols)
                     + f" | {scored[keys[0]][n]['geometry_share']:.2f} |")
    return ("\n".join(lines) + "\n\nEach walk frame's angle against the coordinate that made its markers, its "
            "95 % interval from the pose's own noise and the fit's geometry posterior (the first-order effect, "
            "checked against draws in the table of the section on joint angles below); coverage averaged over "
            "the frames and the draws; the geometry's share from the first cell.\n\n")


def _angles_text(c: dict) -> str:
    """The walk's joint angles (``skelid ik``) against the true coordinates, where the cell scored them."""
    a = c.get("angles") or {}
    if not a:
        return ""
    cov = sorted(v["coverage95"] for v in a.values())
    return (f"; the walk's {len(cov)} joint angles (`skelid ik`) cover {cov[0]:.2f}-{cov[-1]:.2f} per coordinate "
            f"(median {cov[len(cov) // 2]:.2f})")


def opensim_truth_summary() -> str:
    """The README's lines: per summed-up design, the lengths' coverage and RMSE beside the ScaleTool's."""
    path = RESULTS / "opensim_truth.json"
    if not path.exists():
        return opensim_truth()
    cells, sources = _truth_cells()
    lines = []
    for what, parts in SUMMARY_CELLS:
        shown = []
        for label, key in parts:
            c = cells.get(key)
            if not c or not c["rows"]:
                continue
            ln = _truth_values(c["rows"], "length", "coverage95")
            lr = _truth_values(c["rows"], "length", "rmse")
            pr = _peer_rmse(cells, key)
            jc = (c.get("points") or {}).get(JOINTS_KIND)
            shown.append((f"{label}: " if label else "") + f"cover {min(ln):.2f}-{max(ln):.2f}, RMSE "
                         f"{sum(lr) / len(lr):.1f} mm" + (f" (ScaleTool {sum(pr) / len(pr):.1f} mm)" if pr else "")
                         + (f"; joint centres in their parent body cover {jc['coverage95_axes']:.2f} per axis, "
                            f"{jc['region_coverage95']:.2f} as 3-D regions" if jc else "")
                         + _angles_text(c) + f", {c['n']} draws")
        if shown:
            lines.append(f"- {what}, hip-knee and knee-ankle intervals: " + "; ".join(shown))
    prior, raj = RESULTS / "opensim_truth_prior.json", RESULTS / "opensim_truth_rajagopal.json"
    tail = ""
    if raj.exists():
        rd = load(raj)
        shown = [f"{key.split('/')[0]} truth, {key.split('/')[2].replace('+', ' + ')}: lengths cover "
                 f"{min(ln):.2f}-{max(ln):.2f}, RMSE {lr:.1f} mm; joint centres "
                 f"{_points_text(c, JOINTS_KIND)}, markers {_points_text(c, MARKERS_KIND)} (per axis / region), "
                 f"{c['n']} draws" for key, c, ln, lr in _rajagopal_cells(rd)]
        lines.append(f"- {RAJAGOPAL} (landmark and cluster markers, the talus and ulna unmarked), the default, "
                     "i.i.d. 5 mm: " + "; ".join(shown))
        tail += "\n" + source(raj, rd)
    if prior.exists():
        pd = load(prior)
        cls = [v for c in pd["cells"].values() for k, v in (c.get("classes") or {}).items()]
        n = min((c["n"] for c in pd["cells"].values()), default=0)
        if cls:
            lines.append(f"- truth drawn from the fit's own priors (i.i.d. 5 mm, static + walk and one walk): every "
                         f"scale and offset, those the prior decides included, pooled by kind: cover "
                         f"{min(v['coverage95'] for v in cls):.2f}-{max(v['coverage95'] for v in cls):.2f}, rms z "
                         f"{min(v['rms_z'] for v in cls):.2f}-{max(v['rms_z'] for v in cls):.2f}, {n} draws")
            tail += "\n" + source(prior, pd)
    # the files' lines one under the other in one paragraph: the README stays a few screens long
    files = "<br>".join(line.strip() for line in (sources + tail).splitlines() if line.strip())
    return ("\n".join(lines) + "\n\nEvery cell, scale and offset: "
            "[docs/opensim.md](docs/opensim.md#coverage-on-opensim-truth).\n\n" + files + "\n")


def opensim_truth_exact(path: Path) -> str:
    """Noise-free cells: the noise level found, the largest errors, the warnings given."""
    doc = load(path)
    lines = ["| noise-free cell | draws | mean σ (mm) | largest error: scale | length (mm) | warned of misfit "
             "| of artefact |",
             "|---|---|---|---|---|---|---|"]
    for key, c in doc["cells"].items():
        if key.split("/")[1] == "scaletool" or not c["rows"]:
            continue
        fits = [d["fits"][key] for d in doc["draws"] if key in d["fits"] and "error" not in d["fits"][key]]
        misfit = sum(any("model misfit" in w or "disagree beyond their noise" in w for w in f["warnings"])
                     for f in fits)  # the misfit test's warning, or the marker jackknife's
        artefact = sum(any("soft-tissue artefact of about" in w for w in f["warnings"]) for f in fits)
        worst = {k: max((abs(f["q"][q]["est"] - f["truth"][q]) for f in fits for q in f["truth"]
                         if q.startswith(k) and q in f["q"]), default=float("nan")) for k in ("scale", "length")}
        lines.append(f"| {key} | {c['n']} | {c.get('sigma_mean') or float('nan'):.2g} | {worst['scale']:.2g} | "
                     f"{worst['length']:.2g} | {misfit} of {len(fits)} | {artefact} of {len(fits)} |")
    return ("\n".join(lines) + "\n\nScales the data leave to the prior (the warning names them: every marker of "
            "the body free to move) keep the prior's interval and miss the truth by up to the largest error above; "
            "per quantity: [`benchmarks/results/opensim_truth_exact.md`](/benchmarks/results/opensim_truth_exact.md)."
            "\n\n" + source(path, doc))


def ik_angles() -> str:
    """Joint angles against OpenSim's IK on subject01's walk, their sd and geometry share; the coverage check."""
    path = RESULTS / "ik_angles.json"
    if not path.exists():
        return ("*Not measured yet.* `python benchmarks/ik_angles.py` writes `benchmarks/results/ik_angles.json`; "
                "`python benchmarks/render_docs.py` then puts its table here.\n")
    doc = load(path)
    o = doc.get("opensim")
    lines = []

    def f(v, fmt=".2f"):
        return "—" if v is None else format(v, fmt)
    if o:
        lines += [f"subject01 walk, {o['frames']} frames, {o['markers']} markers, {o['draws']} draws of the geometry; "
                  f"skelid's marker cost at or below OpenSim's on {o['frames_skelid_cost_not_above_opensim']:.0%} of "
                  "the frames" + (f", the two models' markers {o['model_gap_mm']:.1e} mm apart at OpenSim's "
                                  "coordinates" if o.get("model_gap_mm") is not None else "")
                  + ". Rotations in degrees, translations in mm; the difference over the frames where "
                  "OpenSim does not hold the coordinate at a bound of its range (frames held in brackets)"
                  + ("; and over every frame to OpenSim's IK run at accuracy 1e-8 instead of its default 1e-5"
                     if o.get("rms_difference_to_opensim_accuracy_1e-8") else "") + ".", "",
                  "| coordinate | rms difference to OpenSim IK | at accuracy 1e-8 | mean sd | geometry share | "
                  "mean sd, Laplace covariance | geometry share, Laplace |", "|---|---|---|---|---|---|---|"]
        tight = o.get("rms_difference_to_opensim_accuracy_1e-8") or {}
        for n, r in o["coordinates"].items():
            if r["status"] != "fitted":
                continue
            held = f" ({r['frames_at_opensim_bound']})" if r.get("frames_at_opensim_bound") else ""
            lines.append(f"| {n} | {f(r.get('rms_difference'))}{held} | {f(tight.get(n))} | {f(r['mean_sd'], '.1f')} | "
                         f"{f(r['geometry_share'])} | {f(r['laplace_mean_sd'], '.1f')} | "
                         f"{f(r['laplace_geometry_share'])} |")
    c = doc.get("coverage")
    if c and c.get("coordinates"):
        lap = c.get("laplace_mean_coverage_95")
        lines += ["", f"Coverage of the true coordinates by the 95 % intervals on the synthetic leg "
                  f"({c['reps_done']} of {c['reps']} repetitions, noise {c['noise_mm']:g} mm): mean "
                  f"{c['mean_coverage_95']:.3f} with the reported covariance (per coordinate " + ", ".join(
                      f"{n} {r['coverage_95']:.2f}" for n, r in c["coordinates"].items()) + ")"
                  + (f", {lap:.3f} with the Laplace covariance (per coordinate " + ", ".join(
                      f"{n} {r['coverage_95']:.2f}" for n, r in c["laplace_coordinates"].items()) + ")"
                     if lap is not None else "") + "."]
    return "\n".join(lines) + "\n\n" + source(path, doc)


# ---------------------------------------------------------------- accuracy


def accuracy_rows(keep: Callable[[dict], bool], fallback: str) -> tuple[list[dict], Path, dict, str]:
    """Rows ``keep`` selects from the current table; if it has none, those of tag ``fallback`` from the
    experiments, with a note saying so."""
    path = RESULTS / "accuracy.json"
    if path.exists():
        doc = load(path)
        rows = [r for r in (doc["rows"] if isinstance(doc, dict) else doc) if keep(r)]
        if rows:
            return rows, path, doc, ""
    path = EXPERIMENTS / "accuracy.json"
    doc = load(path)
    rows = [r for r in (doc["rows"] if isinstance(doc, dict) else doc) if r.get("tag") == fallback and keep(r)]
    return rows, path, doc, f", tag `{fallback}` (an earlier version of the code: not yet measured on this commit)"


def _fmt_entry(r: dict | None) -> str:
    if r is None:
        return "—"
    if not r["reps"] or not math.isfinite(r["bias"]):
        return "— (every fit on the bound)" if r.get("failed") else "—"
    refused = f" ({r['failed']} refused)" if r.get("failed") else ""
    return f"{r['bias']:+.2f} ± {r['bias_se']:.2f} / {r['rmse_over_crlb']:.2f} / {r['coverage95']:.2f}{refused}"


CELL_ORDER = [(n, c, s, t) for n in ("iid", "sta") for c in ("case-a", "case-b") for s in (5.0, 15.0)
              for t in (210.0, 250.0, 290.0)]
NOISE_NAME = {"iid": "i.i.d.", "sta": "soft tissue"}


def _cells(rows):
    by = {}
    for r in rows:
        by.setdefault((r["noise"], r["case"], r["sigma"], r["truth"]), {})[r["method"]] = r
    return by


def accuracy_main() -> str:
    """Bias ± se / RMSE ÷ CRLB / coverage of every method on every i.i.d. and soft-tissue cell."""
    rows, path, doc, note = accuracy_rows(lambda r: r["noise"] in ("iid", "sta") and r["method"] in
                                          ("final", "paper", "laplace", "profile"), "previous")
    by = _cells(rows)
    lines = ["| case | σ | L2 | noise | CRLB | marker (default) | paper (seed) | Laplace grid | "
             "joint fit, free poses |", "|---|---|---|---|---|---|---|---|---|"]
    for key in CELL_ORDER:
        if key not in by:
            continue
        m = by[key]
        crlb = next(iter(m.values()))["crlb"]
        lines.append(f"| {key[1][-1].upper()} | {key[2]:g} | {key[3]:g} | {NOISE_NAME[key[0]]} | {crlb:.2f} | "
                     + " | ".join(_fmt_entry(m.get(k)) for k in ("final", "paper", "laplace", "profile")) + " |")
    return "\n".join(lines) + "\n\n" + source(path, doc, note)


def accuracy_artefact() -> str:
    """Soft-tissue cells: coverage of the default interval and with the artefact's size stated."""
    rows, path, doc, note = accuracy_rows(lambda r: r["noise"] == "sta" and r["method"] in
                                          ("final", "final-artefact"), "previous")
    by = _cells(rows)
    lines = ["| case | σ | L2 | coverage, default | coverage, artefact stated | RMSE ÷ CRLB |",
             "|---|---|---|---|---|---|"]
    for key in CELL_ORDER:
        m = by.get(key)
        if not m or "final" not in m:
            continue
        art = m.get("final-artefact")
        lines.append(f"| {key[1][-1].upper()} | {key[2]:g} | {key[3]:g} | {m['final']['coverage95']:.2f} | "
                     f"{'—' if art is None else format(art['coverage95'], '.2f')} | "
                     f"{m['final']['rmse_over_crlb']:.1f} |")
    return "\n".join(lines) + "\n\n" + source(path, doc, note)


def accuracy_control() -> str:
    """The i.i.d. cells with the linear control variate: bias and RMSE in units of the bound, coverage."""
    rows, path, doc, note = accuracy_rows(lambda r: r["method"] == "final" and "bias_cv" in r and r["noise"] == "iid",
                                          "control")
    lines = ["| case | σ | L2 | trials | bias ÷ CRLB (se) | RMSE ÷ CRLB (se) | coverage |",
             "|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: (r["case"], r["sigma"], r["truth"])):
        c = r["crlb"]
        lines.append(f"| {r['case'][-1].upper()} | {r['sigma']:g} | {r['truth']:g} | {r['reps']} | "
                     f"{r['bias_cv'] / c:.2f} ({r['bias_cv_se'] / c:.2f}) | {r['rmse_cv_over_crlb']:.2f} "
                     f"({r['rmse_cv_se'] / c:.2f}) | {r['coverage95']:.2f} |")
    return "\n".join(lines) + "\n\n" + source(path, doc, note)


def accuracy_singular() -> str:
    """Case A near the straight and folded poses: coverage, bias and RMSE of the default estimator."""
    rows, path, doc, note = accuracy_rows(lambda r: r["noise"] in ("straight", "folded") and r["method"] == "final",
                                          "folded6")
    lines = ["| pose | case | σ | L2 | trials | coverage | abs(z) > 3 | bias ÷ CRLB | RMSE ÷ CRLB |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: (r["noise"], r["case"], r["sigma"], r["truth"])):
        lines.append(f"| {r['noise']} | {r['case'][-1].upper()} | {r['sigma']:g} | "
                     f"{'drawn' if r['truth'] == 0 else format(r['truth'], 'g')} | {r['reps']} | "
                     f"{r['coverage95']:.2f} | {r.get('z_gt3', float('nan')):.2f} | "
                     f"{r['bias'] / r['crlb']:.2f} | {r['rmse_over_crlb']:.2f} |")
    return "\n".join(lines) + "\n\n" + source(path, doc, note)


def accuracy_frames() -> str:
    """RMSE against the number of frames (case A, σ 15): each method beside the bound."""
    path = RESULTS / "rmse_vs_frames.json"
    doc = load(path)
    names = {"final": "marker", "paper": "paper (seed)", "profile": "joint fit, free poses", "crlb": "CRLB"}
    lines = ["| frames | " + " | ".join(str(f) for f in doc["frames"]) + " |", "|---" * (len(doc["frames"]) + 1) + "|"]
    for k, label in names.items():
        lines.append(f"| {label} (mm) | " + " | ".join(f"{v:.2f}" for v in doc[k]) + " |")
    return "\n".join(lines) + "\n\n" + source(path, doc)


# ---------------------------------------------------------------- honest intervals on real recordings


def real_calibration() -> str:
    """Six trials of one body: the share of trial pairs whose estimates agree within 1.96 combined sd."""
    path = RESULTS / "real_calibration.json"
    d = load(path)
    lines = ["| intervals | pairs within 1.96 combined sd | sd of z (about 1 when honest) |", "|---|---|---|",
             f"| each trial alone, today's defaults | {d['fraction_consistent_before']:.2f} | {d['sd_z_before']:.2f} |",
             f"| multi-trial fit, between-trial prior (the default) | {d['fraction_consistent']:.2f} | "
             f"{d['sd_z']:.2f} |",
             f"| the same, prior from the other trials (leave the pair out) | "
             f"{d['fraction_consistent_leave_pair_out']:.2f} | {d['sd_z_leave_pair_out']:.2f} |",
             f"| between-trial variance estimated (DerSimonian-Laird) | {d['fraction_consistent_dl']:.2f} | "
             f"{d['sd_z_dl']:.2f} |"]
    return "\n".join(lines) + "\n\n" + source(path, d)


def soft_tissue() -> str:
    """Simulated soft-tissue artefact, size not stated: coverage and median width from 1 to 4 trials."""
    path = RESULTS / "soft_tissue.json"
    d = load(path)
    cells = d["cells"]
    rows = [("one trial", "single/default")] + [(f"{k} trials, between-trial prior", f"multi-prior/{k}")
                                                 for k in (2, 3, 4)]
    rows += [(f"{k} trials, between-trial variance estimated", f"multi/{k}") for k in (2, 3, 4)]
    lines = ["| fit | coverage 95 % | median width | refused |", "|---|---|---|---|"]
    for label, key in rows:
        if key in cells:
            c = next(iter(cells[key].values()))
            lines.append(f"| {label} | {c['coverage95']:.2f} | {c['median_width']:.1f} | {c['refused']} |")
    head = (f"{d['case']}, σ {d['sigma']:g}, artefact amplitude {d['amplitude']:g}, {d['frames']} frames per "
            f"trial, {d['reps']} subjects" + (" (a reduced run)" if d.get("reduced") else "") + ":\n\n")
    return head + "\n".join(lines) + "\n\n" + source(path, d)


def soft_tissue_arm() -> str:
    """A 3-D arm with skin artefact, size not stated: each centre's per-axis and region coverage, and width."""
    path = RESULTS / "soft_tissue_arm.json"
    d = load(path)
    cells, regions = d["cells"], d.get("regions", {})
    rows = [("one trial", "single/default"), ("one trial, placement sd stated", "single/placement-stated")]
    rows += [(f"{k} trials, between-trial prior", f"multi-prior/{k}") for k in range(2, d["trials"] + 1)]
    lines = ["| fit | centre | coverage per axis (x, y, z) | coverage as a 3-D region | median half-width ÷ RMSE |",
             "|---|---|---|---|---|"]
    for label, key in rows:
        for centre, r in regions.get(key, {}).items():
            axes = [cells[key][f"{centre}_{a}"] for a in "xyz"]
            cover = ", ".join(f"{c['coverage95']:.2f}" for c in axes)
            ratio = [c["median_width"] / 2.0 / c["rmse"] for c in axes]
            width = f"{min(ratio):.1f}–{max(ratio):.1f}"
            lines.append(f"| {label} | {centre} | {cover} | {r['coverage95']:.2f} | {width} |")
    head = (f"`{d['case']}`, σ {d['sigma']:g}, artefact amplitude {d['amplitude']:g}, {d['frames']} frames per "
            f"trial, {d['reps']} subjects, markers misplaced by {d.get('placement_sd', 0):g} mm sd"
            + (" (a reduced run)" if d.get("reduced") else "") + ":\n\n")
    return head + "\n".join(lines) + "\n\n" + source(path, d)


def model_mismatch() -> str:
    """A coupled knee fitted with a hinge: how often the misfit check flags it, and coverage before and after."""
    path = RESULTS / "model_mismatch.json"
    d = load(path)
    lines = ["| source | σ | trials | flagged | hinge's own coverage | coverage after (x, y) |",
             "|---|---|---|---|---|---|"]
    def cov(r, key):
        return " / ".join(f"{v:.2f}" for v in r[key]["coverage"]) if key in r else "—"

    for r in d["rows"]:
        if r["source"] != "null":  # the test's null distribution, not a model
            lines.append(f"| {r['source']} | {r['sigma']:g} | {r['reps']} | {r['flag_rate']:.2f} | {cov(r, 'hinge')} | "
                         f"{cov(r, 'after')} |")
    return "\n".join(lines) + "\n\n" + source(path, d)


def model_average() -> str:
    """The models' average beside each model's own interval (case B, marker D placed two ways)."""
    path = RESULTS / "model_average.json"
    d = load(path)
    lines = ["| cell | σ (mm) | repetitions | coverage 95 %: main / alternative / average | mean width (mm) | "
             "RMSE (mm) | alternative's weight |", "|---|---|---|---|---|---|---|"]
    for s in d["summary"]:
        three = ("main", "alt", "average")
        lines.append(f"| {s['cell']} | {s['sigma']:g} | {s['reps']} | "
                     + " / ".join(f"{s[k]['coverage']:.2f}" for k in three) + " | "
                     + " / ".join(f"{s[k]['mean_width']:.1f}" for k in three) + " | "
                     + " / ".join(f"{s[k]['rmse']:.2f}" for k in three) + f" | {s['weight_alt']:.2f} |")
    return "\n".join(lines) + "\n\n" + source(path, d)


def screens() -> str:
    """The outlier screen's false alarms and the second-order correction on long trials."""
    o_path, b_path = RESULTS / "outlier_screen.json", RESULTS / "bias_trigger.json"
    o, b = load(o_path), load(b_path)
    rows = b["rows"] if isinstance(b, dict) else b
    lines = [f"- Outlier screen on Gaussian data ({o['case']}, σ {o['sigma']:g}, {o['frames']} frames): "
             f"{o['trials_without_drop']} of {o['reps']} trials without a drop (the plain rule it replaced: "
             f"{o['trials_without_drop_plain_rule']}).",
             *(f"- Second-order correction on {r['frames']} frames ({r['reps']} trials"
               f"{', reduced' if r.get('reduced') else ''}): coverage {r['coverage95']:.2f}, bias "
               f"{r['bias_over_sd']:.2f} sd, {r['bootstrap_fallbacks']} sent to the bootstrap." for r in rows)]
    return "\n".join(lines) + "\n\n" + source(o_path, o) + "\n" + source(b_path, b)


# ---------------------------------------------------------------- speed and live


def speed() -> str:
    """Batch fit times and the online update, from benchmarks/results/speed.json."""
    path = RESULTS / "speed.json"
    d = load(path)
    lines = ["| measurement (one core) | time |", "|---|---|",
             f"| case A, 500 frames, `marker` fit with its posterior | {d['fit_case_a_cpu_s']:.2f} s CPU |",
             f"| scipy `least_squares` on the same joint problem | {d['least_squares_cpu_s']:.2f} s CPU "
             f"(RMSE {d['least_squares_rmse']:.1f} mm against skelid's {d['skelid_rmse']:.1f} mm) |",
             f"| 3-D lower limb on the OpenSim walk | {d['lower_limb_fit_cpu_s']:.2f} s CPU |",
             f"| 10⁴ frames against 10³ (`marker`) | {d['marker_scaling_ratio_1e4_over_1e3']:.1f} × |",
             f"| online grid filter, one frame (case A, 256 hypotheses) | {d['online_update_ms_median']:.2f} ms "
             f"median, {d['online_update_ms_p99']:.2f} ms 99th percentile (numpy path: "
             f"{d['online_numpy_update_ms_median']:.1f} ms) |"]
    return "\n".join(lines) + "\n\n" + source(path, d)


def live_speed() -> str:
    """``Session.push`` latencies from benchmarks/results/speed.json."""
    path = RESULTS / "speed.json"
    d = load(path)
    rows = [("case A, Gaussian form", "live_case_a_gaussian_ms"), ("case A, grid form", "live_case_a_grid_ms"),
            ("3-D arm, 10 markers, 6 parameters (the defaults)", "live_arm3d_ms"),
            ("3-D arm, 6 Hz motion model", "live_arm3d_motion_ms"),
            ("3-D arm, no motion model", "live_arm3d_free_ms"),
            ("gait2354 body scales (8), subject01's walk", "live_osim_scales_ms"),
            ("gait2354 body scales and marker offsets, subject01's walk", "live_osim_offsets_ms")]

    def work(r):
        if "work_max" not in r:
            return "— | —"
        return f"{r['work_max']:.1f} ms | {r['with_work_p99']:.2f} ms" if r["work_p99"] > 0.05 else "none | same"

    lines = ["| session | median | 99th percentile | work between frames: largest step | both (a plain `push`): "
             "99th percentile |", "|---|---|---|---|---|"]
    lines += [f"| {label} | {d[k]['p50']:.2f} ms | {d[k]['p99']:.2f} ms | {work(d[k])} |" for label, k in rows
              if k in d]
    return "\n".join(lines) + "\n\n" + source(path, d)


def live_health() -> str:
    """The live health flags on simulated faults (benchmarks/live_health.py): detection, delay, naming, false alarms."""
    path = RESULTS / "live_health.json"
    if not path.exists():
        return ("*Not measured yet.* `python benchmarks/live_health.py` writes `benchmarks/results/live_health.json`; "
                "`python benchmarks/render_docs.py` then puts its table here.\n")
    d = load(path)

    def share(k, n):
        return f"{k}/{n}"

    lines = ["| fault | model | sessions | detected (within N frames) | median frames to detection | named right "
             "| false alarms | final error, median (max) |", "|---|---|---|---|---|---|---|---|"]
    for c in d["cells"].values():
        n = c["sessions"]
        if c["fault"] == "clean":
            found = ["—", "—", "—"]
        else:
            med = c["median_frames_to_detection"]
            named = (f"{c['named_right']}/{c['named']}" if c["named"] else
                     "not named" if c["fault"] == "dropout" else "none named")
            found = [f"{share(c['detected'], n)} (N {c['detection_window']})", "—" if med is None else f"{med:g}",
                     named]
        fa = "—" if c["false_alarms"] is None else share(c["false_alarms"], n)
        lines.append(f"| {c['fault']} | {c['model']} ({c['method']}) | {n} | " + " | ".join(found)
                     + f" | {fa} | {c['final_error_median']:.2f} ({c['final_error_max']:.3g}) |")
    drop = "; ".join(f"{c['model']} {share(c['dropout_as_rule'], c['sessions'])}" for c in d["cells"].values()
                     if c["fault"] == "dropout")
    alarms = {}  # per model: the trials (seeds) with a false alarm in any cell, and those of the clean control
    for c in d["cells"].values():
        seen, clean = alarms.setdefault(c["model"], (set(), set()))
        seen.update(c["false_alarm_sessions"])
        if c["fault"] == "clean":
            clean.update(c["false_alarm_sessions"])
    same = "; ".join(f"{m}: {len(seen)} trials, {len(seen & clean)} of them with one in the clean replay too"
                     for m, (seen, clean) in alarms.items() if seen)
    note = (f"{d['frames']} frames per session at {d['rate']:g} Hz, noise sd {d['sigma']:g} mm, the geometry drawn "
            f"per session, the fault from a frame drawn in {d['start'][0]}-{d['start'][1]} (the units: the whole "
            "stream). Named right: of the sessions whose health named a pair (swap) or a marker (knocked marker), "
            "those that named the right one; for the frozen stream and the units, whether the text names the cause. "
            f"False alarms: sessions with a not-ok frame from frame {d['warmup']} on outside the fault and the "
            f"{d['margin']} frames after it (every fault replays the same trials, so that one trial can count in "
            f"several rows; {same or 'none'}). Final error: the largest |estimate − truth| / sd over the parameters at "
            "the last frame (the clean row is the reference). A missing marker is reported by design; on every "
            "dropout frame the health said the marker is missing and nothing else where the markers left fix the "
            f"pose, `too few markers` where they do not (case A) in: {drop}. The rules: `benchmarks/live_health.py`; "
            "the report with the texts of the false alarms: "
            "[`benchmarks/results/live_health.md`](/benchmarks/results/live_health.md).")
    return "\n".join(lines) + "\n\n" + note + "\n\n" + source(path, d)


def live_stopping() -> str:
    """The stopping rule's study (benchmarks/stopping_rule.py): frames to done and coverage at done."""
    path = RESULTS / "stopping_rule.json"
    if not path.exists():
        return ("*Not measured yet.* `python benchmarks/stopping_rule.py` writes "
                "`benchmarks/results/stopping_rule.json`.\n")
    d = load(path)

    def num(v, f="{:.0f}"):
        return "-" if v is None else f.format(v)

    lines = ["| cell | routine | done | frames to done, median (90 %) | coverage at done | rms z at done |",
             "|---|---|---|---|---|---|"]
    for cell, r in d["cells"].items():
        for routine in ("guided", "fixed"):
            g = r[routine]
            lines.append(f"| {cell} | {routine} | {g['done']}/{r['sessions']} | {num(g['frames_median'])} "
                         f"({num(g['frames_p90'])}) | {num(g['coverage_at_done'], '{:.3f}')} | "
                         f"{num(g['rms_z_at_done'], '{:.2f}')} |")
    note = (f"{d['reps']} sessions per cell, geometry drawn from the prior, at most {d['max_frames']} frames (100 Hz). "
            "`guided`: the user does what `advice()` says first, then asks again; `fixed`: each joint rotation in "
            "turn through the central 60 % of its range, 1 s each, over and over. Coverage: the 95 % intervals "
            "of every parameter at the frame that says done (0.95 is right); sessions not done are left out. "
            "[`benchmarks/results/stopping_rule.md`](/benchmarks/results/stopping_rule.md)")
    return "\n".join(lines) + "\n\n" + note + "\n\n" + source(path, d)


def live_long() -> str:
    """Long live sessions (benchmarks/live_long.py): coverage as the frames add up."""
    path = RESULTS / "live_long.json"
    if not path.exists():
        return "*Not measured yet.* `python benchmarks/live_long.py` writes `benchmarks/results/live_long.json`.\n"
    d = load(path)
    cps = d["checkpoints"]
    lines = ["| cell | " + " | ".join(f"{c} frames" for c in cps) + " |", "|---|" + "---|" * len(cps)]
    for cell, r in d["cells"].items():
        lines.append(f"| {cell} | " + " | ".join(f"{r[str(c)]['coverage']:.2f} ({r[str(c)]['mean_z']:+.2f}, "
                                                 f"{r[str(c)]['rms_z']:.2f})" for c in cps) + " |")
    note = (f"Coverage of every parameter's 95 % interval (mean z, rms z); {d['reps']} sessions per cell, geometry "
            "drawn from the prior, the session's defaults, 100 Hz. "
            "[`benchmarks/results/live_long.md`](/benchmarks/results/live_long.md)")
    return "\n".join(lines) + "\n\n" + note + "\n\n" + source(path, d)


def live_iterated() -> str:
    """One pass at the filtered pose beside ``n_iter=4`` (experiments of the code whose estimate held every frame
    as it came), and the default now: live_long's cells."""
    exp = ROOT / "benchmarks" / "experiments"
    base, before, it = RESULTS / "live_long.json", exp / "live_long_unfolded.json", exp / "live_long_iterated.json"
    a, u, b = load(base), load(before), load(it)
    cps = a["checkpoints"]
    lines = ["| cell | estimate | " + " | ".join(f"{c} frames" for c in cps) + " |", "|---|---|" + "---|" * len(cps)]
    for cell in ("case-a sigma 15 mm", "tennis arm sigma 1 mm"):
        for label, d in (("every frame as it came, 1 pass", u), ("every frame as it came, up to 4 passes", b),
                         ("frames folded in again (now)", a)):
            r = d["cells"][cell]
            lines.append(f"| {cell} | {label} | " + " | ".join(
                f"{r[str(c)]['coverage']:.2f} ({r[str(c)]['mean_z']:+.2f}, {r[str(c)]['rms_z']:.2f})" for c in cps)
                + " |")
    stop_path = exp / "stopping_rule_iterated.json"
    stop = load(stop_path)
    worst = max(max(abs(z) for z in r["fixed"]["z"]) for r in stop["rows"] if "tennis" in r["cell"] and r["fixed"])
    note = (f"Coverage (mean z, rms z), {a['reps']} sessions per cell. With up to 4 passes, the stopping study's "
            f"tennis-arm fixed routine ended one session {worst:.0f} sd off.")
    return ("\n".join(lines) + "\n\n" + note + "\n\n" + source(base, a) + source(before, u)
            + source(it, b) + source(stop_path, stop))


RENDERERS: dict[str, Callable[[], str]] = {
    "demo": demo,
    "opensim-scales": opensim_scales,
    "opensim-subject4": opensim_subject4,
    "opensim-truth": opensim_truth,
    "opensim-truth-summary": opensim_truth_summary,
    "ik-angles": ik_angles,
    "accuracy-main": accuracy_main,
    "accuracy-artefact": accuracy_artefact,
    "accuracy-control": accuracy_control,
    "accuracy-singular": accuracy_singular,
    "accuracy-frames": accuracy_frames,
    "real-calibration": real_calibration,
    "soft-tissue": soft_tissue,
    "soft-tissue-arm": soft_tissue_arm,
    "model-mismatch": model_mismatch,
    "model-average": model_average,
    "screens": screens,
    "speed": speed,
    "live-speed": live_speed,
    "live-health": live_health,
    "live-stopping": live_stopping,
    "live-long": live_long,
    "live-iterated": live_iterated,
}


def render(text: str, renderers: dict[str, Callable[[], str]] = RENDERERS) -> str:
    """``text`` with every block replaced by what its renderer gives; an unknown block name raises KeyError."""
    def one(m):
        return m.group(1) + renderers[m.group(2)]() + m.group(4)

    return BLOCK.sub(one, text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="change nothing; exit 1 where a block differs")
    a = ap.parse_args(argv)
    stale = []
    for path in documents():
        old = path.read_text()
        new = render(old)
        if new == old:
            continue
        stale.append(path)
        if a.check:
            sys.stdout.writelines(difflib.unified_diff(old.splitlines(True), new.splitlines(True),
                                                       f"{rel(path)} (as committed)", f"{rel(path)} (from results)"))
        else:
            path.write_text(new)
            print(f"rewrote {rel(path)}")
    if a.check and stale:
        print(f"\n{len(stale)} file(s) quote figures that differ from benchmarks/results: "
              "run python benchmarks/render_docs.py", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
