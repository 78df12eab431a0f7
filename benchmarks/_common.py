"""Provenance and result files shared by the real-data benchmarks.

Each benchmark writes ``<out>.json`` (the numbers) and ``<out>.md`` (their report,
made from the JSON by the benchmark's ``markdown`` function), records the commit
it ran at, and caches per-trial fits under a key that changes whenever the code
a fit runs or the model file changes.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def git_commit() -> str:
    """The checkout's HEAD commit (``SKELID_BENCH_COMMIT`` for a copy exported from one), or "unknown"."""
    import os

    if os.environ.get("SKELID_BENCH_COMMIT"):
        return os.environ["SKELID_BENCH_COMMIT"]
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def source_key(model: Path, skip: tuple[str, ...] = ()) -> str:
    """Hash (16 hex digits) of the code a fit runs and of its model file.

    The code is every module of ``skelid.estimators`` and ``skelid.model``, less the
    file names in ``skip``.
    """
    import skelid

    h = hashlib.sha256()
    src = Path(skelid.__file__).resolve().parent
    for f in sorted([*(src / "estimators").rglob("*.py"), *(src / "model").rglob("*.py")]):
        if f.name not in skip:
            h.update(f.read_bytes())
    h.update(Path(model).read_bytes())
    return h.hexdigest()[:16]


def write_results(out: Path, res: dict, markdown: Callable[[dict], str]) -> None:
    """Write ``out.json`` and ``out.md`` and print the report."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(res, indent=2) + "\n")
    text = markdown(res)
    out.with_suffix(".md").write_text(text)
    print(text)


def rewrite_markdown(out: Path, markdown: Callable[[dict], str]) -> None:
    """Rewrite ``out.md`` from the ``out.json`` a previous run wrote."""
    out = Path(out)
    out.with_suffix(".md").write_text(markdown(json.loads(out.with_suffix(".json").read_text())))


def provenance(argv=None) -> dict:
    """Commit, date (UTC), CPU model, core count, load average and command line of a run."""
    import datetime
    import os
    import platform
    import sys

    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"commit": git_commit(), "date_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "cpu_model": cpu, "cores": os.cpu_count(), "load_average_1_5_15": [round(v, 2) for v in os.getloadavg()],
            "command": " ".join(["python", *(sys.argv if argv is None else ["benchmarks/...", *argv])])}
