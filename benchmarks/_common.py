"""Provenance and result files shared by the benchmarks.

Each benchmark writes ``<out>.json`` (the numbers) and ``<out>.md`` (their report,
made from the JSON by the benchmark's ``markdown`` function). Every JSON file carries
a ``provenance`` entry (:func:`provenance`: commit, date, CPU, cores, load average,
command line). Results go to :func:`results_dir` (``benchmarks/results``, or the folder
in ``SKELID_BENCH_RESULTS``: ``benchmarks/run_all.py --quick`` points it at a scratch
folder); runs tagged as experiments go to :func:`experiments_dir`. Real-data benchmarks
cache per-trial fits under a key that changes whenever the code a fit runs or the
model file changes.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import os
import platform
import shlex
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
#: environment variable naming the folder results are written to instead of benchmarks/results
ENV_RESULTS = "SKELID_BENCH_RESULTS"


def results_dir() -> Path:
    """Where a benchmark writes its results: ``$SKELID_BENCH_RESULTS`` if set, else ``benchmarks/results``."""
    return Path(os.environ.get(ENV_RESULTS) or ROOT / "benchmarks" / "results")


def experiments_dir() -> Path:
    """Where tagged experiments and ablations go: ``experiments/`` beside :func:`results_dir`'s default, or a
    subfolder ``experiments`` of ``$SKELID_BENCH_RESULTS`` when that is set."""
    env = os.environ.get(ENV_RESULTS)
    return Path(env) / "experiments" if env else ROOT / "benchmarks" / "experiments"


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), or what :mod:`platform` says elsewhere."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def provenance(argv: list[str] | None = None) -> dict:
    """What made a results file: commit, date (UTC), CPU model, core count, load average, command line.

    ``dirty`` is true when the checkout had uncommitted changes to tracked files other than the
    results and experiments themselves (which a run rewrites). ``argv`` defaults to this process's
    command line.
    """
    argv = sys.argv if argv is None else argv
    try:
        dirty = bool(subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".",
                                     ":!benchmarks/results", ":!benchmarks/experiments"], cwd=ROOT,
                                    capture_output=True, text=True, check=True).stdout.strip())
    except (OSError, subprocess.CalledProcessError):
        dirty = None
    return {"commit": git_commit(), "dirty": dirty,
            "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "cpu": cpu_model(), "cores": os.cpu_count(),
            "load_average": [round(v, 2) for v in os.getloadavg()],
            "python": platform.python_version(),
            "command": shlex.join(["python", *argv])}


def with_provenance(res):
    """``res`` with a ``provenance`` entry (a list of rows becomes ``{"provenance": ..., "rows": [...]}``).

    A ``provenance`` that ``res`` already holds is kept: a run that writes its results after every
    step took it when it started, and the checkout may have moved on since.
    """
    if isinstance(res, list):
        return {"provenance": provenance(), "rows": res}
    return {"provenance": res.get("provenance") or provenance(), **{k: v for k, v in res.items() if k != "provenance"}}


def write_json(path: Path, res, **dump) -> None:
    """Write ``res`` with its :func:`provenance` to ``path`` (folders made as needed)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(with_provenance(res), **({"indent": 1} | dump)) + "\n")


def rows_of(obj) -> list:
    """The rows of a results file that holds a list, with or without its provenance wrapper."""
    return obj["rows"] if isinstance(obj, dict) else obj


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


def write_results(out: Path, res: dict, markdown: Callable[[dict], str], quiet: bool = False) -> None:
    """Write ``out.json`` and ``out.md`` and print the report (not when ``quiet``)."""
    out = Path(out)
    write_json(out.with_suffix(".json"), res, indent=2)
    text = markdown(res)
    out.with_suffix(".md").write_text(text)
    if not quiet:
        print(text)


def rewrite_markdown(out: Path, markdown: Callable[[dict], str]) -> None:
    """Rewrite ``out.md`` from the ``out.json`` a previous run wrote."""
    out = Path(out)
    out.with_suffix(".md").write_text(markdown(json.loads(out.with_suffix(".json").read_text())))
