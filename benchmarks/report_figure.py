"""The README's OpenSim example, run as written, and the first screen of its report.

``skelid fit gait2354_simbody.osim subject01_static.trc subject01_walk1.trc --scaletool
subject01_Setup_Scale.xml``, then ``skelid report``, then headless Chromium captures the top of the
report (the scale factors with their intervals beside OpenSim's ScaleTool) as
``docs/figures/opensim_report.png``; ``benchmarks/results/opensim_report.json`` names the commit and
command that made it, and what the screen shows.

Usage: ``python benchmarks/report_figure.py`` (needs ``../shared/data``, the ``opensim`` package and
a ``chromium`` on the PATH).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import provenance, results_dir, write_json  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "opensim-subject01"
FIGURE = ROOT / "docs" / "figures" / "opensim_report.png"
#: the browser window: wide enough for the scale table, tall enough for the first screen's answers
WINDOW = (1280, 1400)
BROWSERS = ("chromium", "chromium-browser", "google-chrome")


def _skelid(argv) -> float:
    """``skelid ARGV`` in this process, quietly; its wall seconds (it must succeed)."""
    from skelid.cli import main

    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        rc = main([str(a) for a in argv])
    if rc:
        raise SystemExit(f"skelid {' '.join(map(str, argv))} failed with exit status {rc}")
    return time.perf_counter() - t0


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--figure", type=Path, default=FIGURE)
    ap.add_argument("--results", type=Path, default=results_dir())
    args = ap.parse_args(argv)
    browser = next((b for b in map(shutil.which, BROWSERS) if b), None)
    if browser is None:
        raise SystemExit("no chromium on the PATH: the report's screen cannot be captured")
    prov = provenance(None if argv is None else ["benchmarks/report_figure.py", *argv])
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "subject01"
        fit_s = _skelid(["fit", DATA / "gait2354_simbody.osim", DATA / "subject01_static.trc",
                         DATA / "subject01_walk1.trc", "--scaletool", DATA / "subject01_Setup_Scale.xml",
                         "--out", out, "--quiet"])
        report_s = _skelid(["report", out, "--quiet"])
        html = out / "report.html"
        args.figure.parent.mkdir(parents=True, exist_ok=True)
        shot = subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                               f"--window-size={WINDOW[0]},{WINDOW[1]}", f"--screenshot={args.figure}",
                               html.as_uri()], capture_output=True, text=True, timeout=300)
        if shot.returncode or not args.figure.exists():
            raise SystemExit(f"{browser} could not capture the report: {shot.stderr.strip()[-300:]}")
        table = json.loads((out / "scaled_scaling.json").read_text())
    peer = table["scaletool"]
    res = {"provenance": prov, "figure": str(args.figure.relative_to(ROOT)), "window_px": list(WINDOW),
           "fit_wall_s": round(fit_s, 1), "report_wall_s": round(report_s, 1),
           "scaletool_inside": peer["inside"], "scaletool_compared": peer["n_compared"],
           "outside": [f"{r['body']} {r['axis']}" for r in peer["compared"] if not r["inside"]],
           "lengths_mm": {k: round(v["value"], 1) for k, v in (table.get("lengths_mm") or {}).items()}}
    write_json(args.results / "opensim_report.json", res, indent=2)
    print(json.dumps({k: v for k, v in res.items() if k != "provenance"}, indent=1))


if __name__ == "__main__":
    main()
