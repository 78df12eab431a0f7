"""Cost of reading C3D files in a guarded child process instead of in-process.

Reads every C3D file in ../shared/data (or the files given on the command
line) ``--repeat`` times each way and writes the median times to
``benchmarks/results/c3d_isolation_overhead.txt``.

    python benchmarks/c3d_isolation_overhead.py [--repeat 7] [files...]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path

from skelid.io import read_c3d

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import provenance, results_dir  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="*", type=Path)
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    files = args.files or sorted((ROOT.parent / "shared" / "data").rglob("*.c3d"))
    lines = [f"# provenance: {json.dumps(provenance())}",
             f"# {platform.platform()}, {platform.python_version()}, median of {args.repeat} reads",
             f"{'file':45s} {'MB':>6s} {'in-process s':>13s} {'child s':>9s} {'overhead s':>11s}"]
    for path in files:
        times = {}
        for isolate in (False, True):
            read_c3d(path, isolate=isolate)  # warm the file cache and the imports
            runs = []
            for _ in range(args.repeat):
                t = time.perf_counter()
                read_c3d(path, isolate=isolate)
                runs.append(time.perf_counter() - t)
            times[isolate] = statistics.median(runs)
        lines.append(f"{path.name:45s} {path.stat().st_size / 1e6:6.2f} {times[False]:13.3f} {times[True]:9.3f} "
                     f"{times[True] - times[False]:11.3f}")
    out = results_dir() / "c3d_isolation_overhead.txt"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
