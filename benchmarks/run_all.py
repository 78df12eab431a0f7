"""Regenerate every committed results file on the current commit, one benchmark after another.

    python benchmarks/run_all.py --full            # the committed tables, into benchmarks/results (hours)
    python benchmarks/run_all.py --quick           # reduced repetitions, into a scratch folder (minutes)
    python benchmarks/run_all.py --quick --only demo outlier_screen race_decision
    python benchmarks/run_all.py --list            # the table below, and what each entry writes

``--full`` is what the committed tables are made with; ``--quick`` is for a change's author: the
same scripts with fewer repetitions, written to ``--out`` (default: a new folder under /tmp) through
``SKELID_BENCH_RESULTS``, so nothing under ``benchmarks/results`` changes. Each benchmark runs as a
subprocess with its own arguments (``BENCHMARKS``: one line per benchmark; ``{results}`` in an
argument is the folder results go to, ``{scratch}`` a temporary folder); a failure stops the run.
``--full`` first removes the files it is about to regenerate (those no entry left out also writes), so
that no benchmark merges rows of an earlier commit into them.
Every JSON file a benchmark writes carries its provenance (``_common.provenance``: commit, date, CPU,
cores, load average, command line). After a ``--full`` run, ``python benchmarks/render_docs.py``
writes the new figures into README.md and docs/.

Entries whose script is missing, or whose data (``../shared/data``) is absent, are skipped and said so.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ENV_RESULTS, ROOT, with_provenance  # noqa: E402

DATA = ROOT.parent / "shared" / "data"


@dataclass(frozen=True)
class Bench:
    """One benchmark run: ``script`` (under benchmarks/, or ``skelid`` for the CLI) with its arguments."""

    name: str
    script: str
    full: tuple[str, ...]
    quick: tuple[str, ...]
    writes: tuple[str, ...]  # files under the results folder
    needs_data: bool = False  # reads ../shared/data
    stdout_json: str | None = None  # the command prints JSON: write it (with provenance) to this file
    env: tuple[tuple[str, str], ...] = ()  # environment variables the command runs with


B = Bench

#: the OpenSim-truth cells of the committed table (README and docs/opensim.md quote them)
#: the default fit (three linked factors per body) beside one factor per body, on both kinds of truth
OPENSIM_DEFAULT_CELLS = ("axes/linked/static+walk/5", "bodies/linked/static+walk/5", "axes/bodies/static+walk/5",
                         "bodies/bodies/static+walk/5")
#: the exact structure (one factor per axis) for reference, then the default fit (linked) in the other designs
#: and noise kinds; the default beside one factor per body on i.i.d. noise is OPENSIM_DEFAULT_CELLS
OPENSIM_TRUTH_CELLS = ("axes/axes/static+walk/5", "axes/linked/walk/5", "axes/linked/static+walk/pm",
                       "axes/linked+pm/static+walk/pm", "axes/linked/static+walk/sta", "axes/linked/walk/sta",
                       "axes/linked/walk+walk2/sta", "axes/linked/walk+walk2/stalab")
#: the i.i.d. and per-marker cells of OPENSIM_TRUTH_CELLS again at 100 draws (the exact structure and the default);
#: opensim_truth_sta100 and opensim_truth_sta1walk100 do the same for the skin-artefact cells; opensim_truth_angles100
#: the default i.i.d. cells with the joint angles of their walk scored; opensim_truth_pm100 `--noise per-marker`;
#: opensim_truth_stalab100 the slide in the laboratory's frame; opensim_truth_bodies100 the other
#: OPENSIM_DEFAULT_CELLS
#: the full-body model of the six-trial subject, scaled per axis (only its marked bodies, or every body as
#: OpenSim's setups do), walks only and with a static trial
RAJAGOPAL_CELLS = ("axes/linked/walk/5", "every/linked/walk/5", "every/linked/static+walk/5")
OPENSIM_100_CELLS = ("axes/axes/static+walk/5", "axes/linked/static+walk/pm")


def truth100(name: str, cells: tuple, extra: tuple = ()) -> Bench:
    """An OpenSim-truth run of ``cells`` at 100 draws into ``{results}/NAME``; reduced: one draw of the first cell."""
    out = ("--out", f"{{results}}/{name}")
    return B(name, "opensim_truth.py", ("--reps", "100", "--jobs", "2", *extra, "--cells", *cells, *out),
             ("--reps", "1", "--no-peer", *extra, "--cells", cells[0], *out), (f"{name}.json", f"{name}.md"),
             needs_data=True)


#: one line per benchmark; dependent entries after what they read (jackknife_linearisation reads
#: real_calibration's cached fits). The demo waits for the compiled kernel: the seed method's frame
#: count can differ by a frame or two between the compiled and the numpy path, and a fresh install's
#: first run takes the numpy path while the kernel compiles.
BENCHMARKS: tuple[Bench, ...] = (
    B("demo", "skelid", ("demo", "--json", "--seed", "0", "--quiet", "--overwrite", "--out", "{scratch}/demo"),
      ("demo", "--json", "--seed", "0", "--quiet", "--overwrite", "--out", "{scratch}/demo"),
      ("demo.json",), stdout_json="demo.json", env=(("SKELID_NUMBA", "wait"),)),
    B("accuracy", "accuracy.py", ("--reps", "100", "--jobs", "2"),
      ("--reps", "3", "--jobs", "2", "--cases", "case-a", "--sigmas", "15", "--truths", "250"),
      ("accuracy.json", "accuracy.md")),
    B("accuracy_artefact", "accuracy.py", ("--reps", "100", "--jobs", "2", "--noises", "sta", "--methods",
                                           "final-artefact"),
      ("--reps", "2", "--jobs", "2", "--cases", "case-a", "--sigmas", "15", "--truths", "250", "--noises", "sta",
       "--methods", "final-artefact"), ("accuracy.json", "accuracy.md")),
    B("accuracy_singular", "accuracy.py", ("--reps", "100", "--jobs", "2", "--cases", "case-a", "case-b",
                                           "--noises", "straight", "folded", "--methods", "final"),
      ("--reps", "2", "--jobs", "2", "--cases", "case-a", "--sigmas", "15", "--noises", "folded",
       "--methods", "final"),
      ("accuracy.json", "accuracy.md")),
    B("accuracy_frames", "accuracy.py", ("--frames-study", "--reps", "20", "--jobs", "2"),
      ("--frames-study", "--reps", "1", "--jobs", "2"), ("rmse_vs_frames.json", "rmse_vs_frames.png")),
    B("bias_budget_250", "bias_budget.py", ("--truth", "250", "--reps", "100", "--jobs", "2"),
      ("--truth", "250", "--reps", "3", "--jobs", "2"), ("bias_budget.json", "bias_budget.md")),
    B("bias_budget_210", "bias_budget.py", ("--truth", "210", "--reps", "100", "--jobs", "2"),
      ("--truth", "210", "--reps", "3", "--jobs", "2"), ("bias_budget.json", "bias_budget.md")),
    B("bias_trigger", "bias_trigger.py", ("--frames", "1000", "10000", "--reps", "100", "--jobs", "2"),
      ("--frames", "1000", "--reps", "2"), ("bias_trigger.json", "bias_trigger.md")),
    B("outlier_screen", "outlier_screen.py", ("--reps", "100", "--jobs", "2"), ("--reps", "4", "--jobs", "2"),
      ("outlier_screen.json", "outlier_screen.md")),
    B("model_average", "model_average.py", ("--reps", "100", "--jobs", "2"),
      ("--reps", "2", "--jobs", "2", "--sigmas", "15"), ("model_average.json", "model_average.md")),
    B("race_decision", "race_decision.py", ("--reps", "4"), ("--reps", "1"), ("race_decision.json",)),
    B("model_mismatch", "model_mismatch.py", ("--reps", "100", "--jobs", "2", "--replace"),
      ("--reps", "2", "--null-reps", "4", "--sigmas", "5", "--jobs", "2", "--replace"),
      ("model_mismatch.json", "model_mismatch.md")),
    B("soft_tissue", "soft_tissue.py", ("--reps", "100", "--jobs", "2", "--out", "{results}/soft_tissue"),
      ("--reps", "3", "--jobs", "2", "--out", "{results}/soft_tissue"), ("soft_tissue.json", "soft_tissue.md")),
    B("soft_tissue_arm", "soft_tissue.py", ("--case", "examples/arm.toml", "--trials", "1", "--reps", "100",
                                            "--jobs", "2", "--out", "{results}/soft_tissue_arm"),
      ("--case", "examples/arm.toml", "--trials", "1", "--reps", "2", "--jobs", "2",
       "--out", "{results}/soft_tissue_arm"), ("soft_tissue_arm.json", "soft_tissue_arm.md")),
    B("soft_tissue_leg", "soft_tissue.py", ("--case", "examples/lower_limb.toml", "--trials", "2", "--reps", "100",
                                            "--jobs", "2", "--placement-sd", "5", "--out", "{results}/soft_tissue_leg"),
      ("--case", "examples/lower_limb.toml", "--trials", "2", "--reps", "2", "--jobs", "2", "--placement-sd", "5",
       "--out", "{results}/soft_tissue_leg"), ("soft_tissue_leg.json", "soft_tissue_leg.md")),
    B("shift_invariance", "shift_invariance.py", (), ("--shifts", "1"),
      ("shift_invariance.json", "shift_invariance.md")),
    B("live_agreement", "live_agreement.py", ("--reps", "100", "--jobs", "2"),
      ("--reps", "2", "--jobs", "2", "--no-glitch", "--cutoffs", "auto"), ("live_agreement.json", "live_agreement.md")),
    B("live_agreement_arms", "live_agreement.py",
      ("--reps", "100", "--jobs", "2", "--cutoffs", "auto", "none", "--no-glitch", "--tag", "arms", "--cells",
       "tennis arm sigma 1 mm", "arm10 sigma 2 mm", "tennis arm sigma 1 mm, 5x faster"),
      ("--reps", "2", "--jobs", "2", "--cutoffs", "auto", "--no-glitch", "--tag", "arms", "--cells",
       "arm10 sigma 2 mm"), ("live_agreement_arms.json", "live_agreement_arms.md")),
    B("live_agreement_case_a", "live_agreement.py",
      ("--reps", "100", "--jobs", "2", "--cutoffs", "auto", "none", "--no-glitch", "--tag", "case_a", "--cells",
       "case-a sigma 1 mm", "case-a sigma 5 mm"),
      ("--reps", "2", "--jobs", "2", "--cutoffs", "auto", "--no-glitch", "--tag", "case_a", "--cells",
       "case-a sigma 5 mm"), ("live_agreement_case_a.json", "live_agreement_case_a.md")),
    B("live_health", "live_health.py", (), ("--quick",), ("live_health.json", "live_health.md")),
    B("soak", "soak.py", (), ("--minutes", "2"), ("soak.json", "soak.md")),
    B("live_lsl", "live_lsl.py", (), ("--frames", "400", "--skip", "100"), ("live_lsl.json", "live_lsl.md")),
    B("live_long", "live_long.py", ("--reps", "100", "--jobs", "2"),
      ("--reps", "2", "--jobs", "2", "--checkpoints", "500", "1000"), ("live_long.json", "live_long.md")),
    B("stopping_rule", "stopping_rule.py", ("--reps", "100", "--jobs", "2"), ("--reps", "2", "--jobs", "2"),
      ("stopping_rule.json", "stopping_rule.md")),
    B("batch_faults", "batch_faults.py", (), ("--trials", "20", "--start-trials", "4", "--race-seconds", "1"),
      ("batch_faults.json", "batch_faults.md")),
    B("sampler", "sampler.py", (), (), ("sampler.md",)),
    B("speed", "speed.py", (), ("--only", "online", "fit", "--repeats", "1", "--online-frames", "300"),
      ("speed.json", "speed.md")),
    B("c3d_isolation_overhead", "c3d_isolation_overhead.py", (), ("--repeat", "1"), ("c3d_isolation_overhead.txt",),
      needs_data=True),
    B("real_data", "real_data.py", (), (), ("real_data.json", "real_data.md"), needs_data=True),
    B("real_calibration", "real_calibration.py", ("--out", "{results}/real_calibration"),
      ("--max-frames", "300", "--out", "{results}/real_calibration", "--cache", "{scratch}/real-calibration"),
      ("real_calibration.json", "real_calibration.md"), needs_data=True),
    B("jackknife_linearisation", "jackknife_linearisation.py", ("--out", "{results}/jackknife_linearisation.json"),
      ("--out", "{results}/jackknife_linearisation.json", "--cache", "{scratch}/real-calibration"),
      ("jackknife_linearisation.json",), needs_data=True),
    B("pig_compare", "pig_compare.py", ("--out", "{results}/pig_compare"),
      ("--out", "{results}/pig_compare", "--cache", "{scratch}/pig-compare"), ("pig_compare.json", "pig_compare.md"),
      needs_data=True),
    B("opensim_peer", "opensim_peer.py", (), ("--quick",), ("opensim_peer.json", "opensim_peer.md"), needs_data=True),
    B("report_figure", "report_figure.py", (), ("--figure", "{results}/opensim_report.png"), ("opensim_report.json",),
      needs_data=True),
    B("opensim_truth", "opensim_truth.py",
      ("--reps", "24", "--jobs", "2", "--cells", *OPENSIM_TRUTH_CELLS), ("--quick",),
      ("opensim_truth.json", "opensim_truth.md"), needs_data=True),
    B("opensim_truth_default", "opensim_truth.py",
      ("--reps", "24", "--jobs", "2", "--cells", *OPENSIM_DEFAULT_CELLS, "--out", "{results}/opensim_truth_default"),
      ("--reps", "1", "--no-peer", "--cells", "axes/linked/static+walk/5", "--out",
       "{results}/opensim_truth_default"),
      ("opensim_truth_default.json", "opensim_truth_default.md"), needs_data=True),
    truth100("opensim_truth_iid100", OPENSIM_100_CELLS),
    B("opensim_truth_sta100", "opensim_truth.py",
      ("--reps", "100", "--jobs", "2", "--cells", "axes/linked/walk+walk2/sta", "--out",
       "{results}/opensim_truth_sta100"),
      ("--reps", "1", "--no-peer", "--cells", "axes/linked/walk/sta", "--out", "{results}/opensim_truth_sta100"),
      ("opensim_truth_sta100.json", "opensim_truth_sta100.md"), needs_data=True),
    truth100("opensim_truth_sta1walk100", ("axes/linked/static+walk/sta", "axes/linked/walk/sta")),
    truth100("opensim_truth_angles100", ("axes/linked/static+walk/5", "axes/linked/walk/5"), ("--angles", "0")),
    truth100("opensim_truth_pm100", ("axes/linked+pm/static+walk/pm",)),
    truth100("opensim_truth_stalab100", ("axes/linked/walk+walk2/stalab",)),
    truth100("opensim_truth_bodies100", OPENSIM_DEFAULT_CELLS[1:]),
    B("opensim_truth_prior", "opensim_truth.py",
      ("--reps", "100", "--jobs", "2", "--no-peer", "--cells", "prior/axes/static+walk/5", "prior/axes/walk/5",
       "--out", "{results}/opensim_truth_prior"),
      ("--reps", "2", "--no-peer", "--cells", "prior/axes/walk/5", "--out", "{results}/opensim_truth_prior"),
      ("opensim_truth_prior.json", "opensim_truth_prior.md"), needs_data=True),
    B("opensim_truth_exact", "opensim_truth.py",
      ("--reps", "4", "--jobs", "2", "--cells", "axes/axes/static+walk/0", "axes/linked/static+walk/0",
       "axes/bodies/static+walk/0",
       "axes/axes/walk/0", "--out", "{results}/opensim_truth_exact"),
      ("--reps", "1", "--no-peer", "--cells", "axes/axes/walk/0", "--out", "{results}/opensim_truth_exact"),
      ("opensim_truth_exact.json", "opensim_truth_exact.md"), needs_data=True),
    B("opensim_truth_rajagopal", "opensim_truth.py",
      ("--model", "rajagopal", "--reps", "100", "--jobs", "2", "--no-peer", "--cells", *RAJAGOPAL_CELLS,
       "--out", "{results}/opensim_truth_rajagopal"),
      ("--model", "rajagopal", "--reps", "1", "--no-peer", "--cells", RAJAGOPAL_CELLS[0], "--out",
       "{results}/opensim_truth_rajagopal"),
      ("opensim_truth_rajagopal.json", "opensim_truth_rajagopal.md"), needs_data=True),
    B("ik_angles", "ik_angles.py", (), ("--quick",), ("ik_angles.json", "ik_angles.md"), needs_data=True),
)


def command(b: Bench, mode: str, results: Path, scratch: Path) -> list[str]:
    """The command line of ``b`` in ``mode`` ("full" or "quick"), placeholders filled in."""
    # the results folder as the recorded command line can be rerun from the checkout's root (its working folder)
    shown = results.relative_to(ROOT) if results.is_absolute() and results.is_relative_to(ROOT) else results
    args = [a.format(results=shown, scratch=scratch) for a in (b.full if mode == "full" else b.quick)]
    if b.script == "skelid":
        return [sys.executable, "-m", "skelid.cli", *args]
    return [sys.executable, str(Path("benchmarks") / b.script), *args]


def skip_reason(b: Bench) -> str | None:
    if b.script != "skelid" and not (ROOT / "benchmarks" / b.script).exists():
        return f"benchmarks/{b.script} is not in this checkout"
    if b.needs_data and not DATA.is_dir():
        return f"{DATA} is absent"
    return None


def stale_files(chosen: list[Bench]) -> list[str]:
    """The files that only ``chosen`` entries write (a file another entry also writes is kept)."""
    runnable = [b for b in chosen if not skip_reason(b)]
    others = {w for b in BENCHMARKS if b not in runnable for w in b.writes}
    return sorted({w for b in runnable for w in b.writes} - others)


def run_one(b: Bench, mode: str, results: Path, scratch: Path, env: dict) -> dict:
    cmd = command(b, mode, results, scratch)
    shown = " ".join([*(f"{k}={shlex.quote(v)}" for k, v in b.env),
                      shlex.join(["skelid", *cmd[3:]] if b.script == "skelid" else ["python", *cmd[1:]])])
    print(f"[run_all] {b.name}: {shown}", flush=True)
    t0, c0 = time.perf_counter(), os.times()
    out = subprocess.run(cmd, cwd=ROOT, env=dict(env, **dict(b.env)),
                         stdout=subprocess.PIPE if b.stdout_json else None, text=True)
    c1 = os.times()
    if out.returncode == 0 and b.stdout_json:
        doc = with_provenance(json.loads(out.stdout))
        doc["provenance"]["command"] = shown
        (results / b.stdout_json).write_text(json.dumps(doc, indent=1) + "\n")
    return {"name": b.name, "rc": out.returncode, "wall_s": time.perf_counter() - t0,
            "cpu_s": (c1.children_user + c1.children_system) - (c0.children_user + c0.children_system),
            "writes": [str(results / w) for w in b.writes]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = ap.add_mutually_exclusive_group(required=True)
    mode.add_argument("--full", action="store_true", help="the committed tables, into benchmarks/results")
    mode.add_argument("--quick", action="store_true", help="reduced repetitions, into a scratch folder")
    mode.add_argument("--list", action="store_true", help="print the table of benchmarks and stop")
    ap.add_argument("--only", nargs="+", metavar="NAME", help="run only these entries (in the table's order)")
    ap.add_argument("--skip", nargs="+", metavar="NAME", default=[], help="leave these entries out")
    ap.add_argument("--out", type=Path, help="--quick: the folder results go to (default: a new one under /tmp)")
    a = ap.parse_args(argv)
    names = {b.name for b in BENCHMARKS}
    for n in [*(a.only or []), *a.skip]:
        if n not in names:
            ap.error(f"no benchmark {n!r}; the table has: {', '.join(b.name for b in BENCHMARKS)}")
    chosen = [b for b in BENCHMARKS if (a.only is None or b.name in a.only) and b.name not in a.skip]
    if a.list:
        for b in BENCHMARKS:
            print(f"{b.name:24s} {b.script:28s} -> {', '.join(b.writes)}"
                  + (f"  (skipped: {skip_reason(b)})" if skip_reason(b) else ""))
        return 0
    mode = "full" if a.full else "quick"
    scratch = Path(tempfile.mkdtemp(prefix="skelid-run-all-"))
    if mode == "full":
        if a.out:
            ap.error("--out is for --quick; --full writes benchmarks/results")
        results = ROOT / "benchmarks" / "results"
    else:
        results = (a.out or scratch / "results").resolve()
    results.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, **{ENV_RESULTS: str(results)}) if mode == "quick" else \
        {k: v for k, v in os.environ.items() if k != ENV_RESULTS}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT / "src"), *filter(None, [env.get("PYTHONPATH")])])
    print(f"[run_all] --{mode}: {len(chosen)} benchmarks into {results}", flush=True)
    if mode == "full":  # merging benchmarks would keep rows of another commit: start their files afresh
        for name in stale_files(chosen):
            (results / name).unlink(missing_ok=True)
    done, t_all = [], time.perf_counter()
    for b in chosen:
        why = skip_reason(b)
        if why:
            print(f"[run_all] {b.name}: skipped ({why})", flush=True)
            done.append({"name": b.name, "rc": None, "wall_s": 0.0, "cpu_s": 0.0, "writes": [], "skipped": why})
            continue
        r = run_one(b, mode, results, scratch, env)
        done.append(r)
        if r["rc"] != 0:
            print(f"[run_all] {b.name} failed (exit {r['rc']}); stopping", flush=True)
            break
    print(f"\n[run_all] summary (--{mode}, results in {results}):")
    for r in done:
        state = "skipped: " + r["skipped"] if r.get("skipped") else ("ok" if r["rc"] == 0 else f"FAILED ({r['rc']})")
        print(f"  {r['name']:24s} {state:10s} {r['wall_s']:8.1f} s wall {r['cpu_s']:8.1f} s CPU  "
              + ", ".join(Path(w).name for w in r["writes"] if Path(w).exists()))
    failed = [r for r in done if r["rc"] not in (0, None)]
    print(f"[run_all] {len(done) - len(failed)} of {len(chosen)} done in {time.perf_counter() - t_all:.0f} s"
          + ("" if not failed else f"; {failed[0]['name']} failed"))
    if mode == "quick":
        print(f"[run_all] reduced run: nothing under benchmarks/results changed; files in {results}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
