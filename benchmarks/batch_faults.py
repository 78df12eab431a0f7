"""What a killed Dask worker and a full disk do to ``skelid batch``.

    nice python benchmarks/batch_faults.py [--trials 200] [--workers 2] [--timeout 240] [--kills 1]

The trials are small simulated ones (case A, 60 frames, sigma 3 mm, one TRC file each,
seeds 0, 1, ...), fitted with the default method by ``skelid batch case-a 'DIR/*.trc'
--out TABLE.parquet --results RUNS --workers 2 --quiet --json`` in a subprocess. Three faults:

* **A worker killed mid-run.** Once the table holds some rows (``--kill-after``, default a
  fifth of the trials), one Dask worker process (a child of the batch whose command line
  is multiprocessing's ``spawn_main``) gets ``SIGKILL``. The batch is left to finish; if it
  exits with an error, or runs past ``--timeout``, it gets ``SIGTERM`` (``SIGKILL`` 30 s
  later if it is still there) and the same command is started again ("client restarted"),
  until one run exits 0 having every trial fitted, failed or skipped. If rows hold an
  error then, the command is run once more with ``--retry-failed``. Checked: every
  trial's row is in the table exactly once (and the table passes skelid's own checks on
  reading it: the columns, each row's checksum, no two rows with one key); the rows with
  an error, with what they say; no hidden ``.NAME.*.part`` entry left beside the table or
  among the result folders; each fitted row's result folder complete and no folder that
  no row names; whether the killed worker was replaced; the table readable at every poll
  (every 0.2 s) while the batch ran: its bytes read through one open file and checked as
  ``skelid.batch.read_table`` checks a table (what the writer left at that moment), and,
  counted apart, ``skelid.batch.read_table`` on the path itself, as another program
  reading the table meanwhile would.
* **Disk full.** The batch runs under a file-size limit (``RLIMIT_FSIZE``, with ``SIGXFSZ``
  ignored, so that a write past it fails with ``EFBIG`` as one on a full disk fails with
  ``ENOSPC``; no root needed) set to the size of the table with half the trials' rows
  (measured beforehand on copies of one fitted row), above each trial's result files:
  the table's rewrite fails partway through the batch. Recorded: the exit status, what
  it printed on stderr (one line? a traceback?), that the table left behind is readable
  and passes the checks, its rows complete (every column of a fitted row filled), no
  ``.part`` entry left; then the same command without the limit: its exit status and
  summary, and whether it fitted exactly the trials that were missing from the table.
* **A worker killed while the cluster starts** (``--start-trials``, default 10 trials;
  0 leaves it out): ``SIGKILL`` to a worker process 0.3 s after it appears, before the
  first row; recorded: what the run prints (one line? a traceback?) and its exit status,
  then whether the same command run again completes.

Then **reading the table while it is rewritten**: a thread rewrites a table with
``skelid.batch.write_table`` (the killed-worker batch's rows, a growing prefix each time)
again and again while the main thread reads it for ``--race-seconds`` (default 4 s) per
way of reading: by its path (``skelid.batch.read_table``) and through one open file.

``--kills N`` kills a worker N times during the first fault (at least ``--kill-gap`` s
apart, each once the run has added rows, so never while its cluster starts): a harsher
variant, not the default.

A file-size limit is per file, not a quota: it stops only the writes that make one file
larger than the limit, here the table's; a real full disk would stop the result folders'
writes too (each then becomes that trial's error row, which ``--retry-failed`` fits
again).

Prints the figures and writes ``results/batch_faults.json`` and ``.md`` (through
``_common``: the commit, date, CPU, cores, load and command line). About two to three
minutes on two cores.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import collections  # noqa: E402
import json  # noqa: E402
import re  # noqa: E402
import resource  # noqa: E402
import shutil  # noqa: E402
import signal  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import provenance, results_dir, write_results  # noqa: E402

MODEL = "case-a"
FRAMES, SIGMA = 60, 3.0
#: seconds between two looks at the table while a batch runs
POLL_S = 0.2
#: hidden partial entries an atomic writer leaves when it is killed (``.NAME.<...>.part``)
PART = re.compile(r"^\..+\.part$")
#: runs of one command before giving up (the first, and the restarts after a failure or a hang)
MAX_ATTEMPTS = 4


# --------------------------------------------------------------------------- trials and the command
def make_trials(folder: Path, n: int, frames: int = FRAMES, sigma: float = SIGMA) -> list[str]:
    """``n`` simulated case-A trials ``folder/tNNNN.trc`` (seeds 0..n-1); their absolute paths."""
    import numpy as np

    from skelid.io import write_trc
    from skelid.simulate import builtin_model, simulate

    folder.mkdir(parents=True, exist_ok=True)
    model = builtin_model(MODEL)
    paths = []
    for k in range(n):
        p = folder / f"t{k:04d}.trc"
        write_trc(p, simulate(model, n_frames=frames, sigma=sigma, rng=np.random.default_rng(k)).data)
        paths.append(str(p.resolve()))
    return paths


def skelid_program() -> list[str]:
    """The ``skelid`` program of this Python (its script beside the interpreter, else ``python -c``)."""
    script = Path(sys.executable).with_name("skelid")
    if script.is_file():
        return [sys.executable, str(script)]
    return [sys.executable, "-c", "import sys; from skelid.cli import main; sys.exit(main())"]


def batch_command(trials: Path, out: Path, runs: Path | None, workers: int, *extra: str) -> list[str]:
    cmd = [*skelid_program(), "batch", MODEL, str(trials / "*.trc"), "--out", str(out), "--workers", str(workers),
           "--quiet", "--json", *extra]
    return cmd + (["--results", str(runs)] if runs is not None else [])


def shown(cmd: list[str], work: Path) -> str:
    """``cmd`` as the report shows it: ``skelid ...``, the work folder as ``WORK``."""
    return " ".join(["skelid", *cmd[len(skelid_program()):]]).replace(str(work), "WORK")


def columns() -> list[str]:
    from skelid.batch import columns as cols
    from skelid.simulate import builtin_model

    return cols(builtin_model(MODEL))


# --------------------------------------------------------------------------- looking at a running batch
def dask_workers(pid: int) -> list[int]:
    """The Dask worker processes of batch ``pid``: its children started by multiprocessing's ``spawn_main``
    (the others are its resource tracker and, while a kernel compiles, the compiling process)."""
    try:
        import psutil
    except ImportError:
        psutil = None
    found = []
    if psutil is not None:
        try:
            kids = psutil.Process(pid).children(recursive=False)
        except psutil.Error:
            return []
        for c in kids:
            try:
                if "spawn_main" in " ".join(c.cmdline()):
                    found.append(c.pid)
            except psutil.Error:
                pass
        return sorted(found)
    kids = set()
    for f in Path(f"/proc/{pid}/task").glob("*/children"):
        try:
            kids |= {int(x) for x in f.read_text().split()}
        except OSError:
            pass
    if not kids and shutil.which("pgrep"):
        got = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True)
        kids = {int(x) for x in got.stdout.split()}
    for c in kids:
        try:
            if b"spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes():
                found.append(c)
        except OSError:
            pass
    return sorted(found)


def table_rows(out: Path) -> tuple[list[dict] | None, str | None]:
    """The table's rows as ``skelid batch`` reads them (its checks included), or ``(None, why not)``."""
    from skelid.batch import read_table
    from skelid.errors import SkelidError

    try:
        return read_table(out, columns()), None
    except SkelidError as exc:
        return None, exc.one_line()


def snapshot_rows(out: Path) -> tuple[list[dict] | None, str | None]:
    """:func:`table_rows` of the table's bytes read through one open file (copied to a private file first): what
    the writer left at one moment, whatever a rename does meanwhile."""
    with open(out, "rb") as fh:
        data = fh.read()
    with tempfile.TemporaryDirectory(prefix="skelid-snapshot-") as tmp:
        copy = Path(tmp) / out.name
        copy.write_bytes(data)
        rows, why = table_rows(copy)
    return rows, None if why is None else why.replace(str(copy), str(out))


def part_entries(*folders: Path) -> list[str]:
    """Hidden partial entries (``.NAME.*.part``) in ``folders``."""
    return sorted(str(p) for f in folders if f.is_dir() for p in f.iterdir() if PART.match(p.name))


class Attempt:
    """One run of the command, watched: the table read every :data:`POLL_S` s while it runs."""

    def __init__(self, cmd: list[str], out: Path, timeout: float, preexec=None, hook=None):
        self.cmd, self.out, self.timeout, self.preexec, self.hook = cmd, out, timeout, preexec, hook
        self.polls = self.unreadable = self.path_unreadable = 0
        self.unreadable_texts: list[str] = []
        self.path_texts: list[str] = []
        self.rows_seen = 0
        self.hung = self.terminated = self.killed = False

    def run(self) -> dict:
        t0 = time.monotonic()
        proc = subprocess.Popen(self.cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                preexec_fn=self.preexec)
        streams = {"stdout": [], "stderr": []}
        readers = [threading.Thread(target=lambda k=k, s=s: streams[k].append(s.read()), daemon=True)
                   for k, s in (("stdout", proc.stdout), ("stderr", proc.stderr))]
        for r in readers:
            r.start()
        self.proc = proc
        while proc.poll() is None:
            if time.monotonic() - t0 > self.timeout and not self.hung:
                self.hung = self.terminated = True
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(30)
                except subprocess.TimeoutExpired:
                    self.killed = True
                    left = dask_workers(proc.pid)
                    proc.kill()
                    for w in left:  # its workers would outlive it
                        _kill(w)
                break
            self.look(time.monotonic() - t0)
            time.sleep(POLL_S)
        proc.wait()
        for r in readers:
            r.join(10)
        self.look(time.monotonic() - t0)  # once more: the table it left
        stdout, stderr = "".join(streams["stdout"]), "".join(streams["stderr"])
        try:
            summary = json.loads(stdout) if stdout.strip() else None
        except json.JSONDecodeError:
            summary = None
        return {"exit": proc.returncode, "seconds": round(time.monotonic() - t0, 2), "summary": summary,
                "stderr": stderr.strip().splitlines(), "hung": self.hung, "terminated": self.terminated,
                "killed_after_sigterm": self.killed, "table_polls": self.polls, "table_unreadable": self.unreadable,
                "unreadable_texts": self.unreadable_texts[:3], "path_unreadable": self.path_unreadable,
                "path_texts": self.path_texts[:3]}

    def look(self, t: float) -> None:
        if not self.out.exists():
            if self.hook is not None:
                self.hook(self, t, [])
            return
        try:
            rows, why = snapshot_rows(self.out)
        except FileNotFoundError:
            return
        self.polls += 1
        if (by_path := table_rows(self.out))[0] is None:  # skelid.batch.read_table on the path, as a reader would
            self.path_unreadable += 1
            self.path_texts.append(by_path[1])
        if rows is None:
            self.unreadable += 1
            self.unreadable_texts.append(why)
            return
        self.rows_seen = len(rows)
        if self.hook is not None:
            self.hook(self, t, rows)


def _kill(pid: int) -> None:
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def done(run: dict, n: int) -> bool:
    """The run exited 0 and its summary counts every trial (fitted, failed or already in the table)."""
    s = run["summary"]
    return run["exit"] == 0 and s is not None and s["fitted"] + s["failed"] + s["skipped"] == n == s["trials"]


# --------------------------------------------------------------------------- what a table holds
def check_table(out: Path, runs: Path | None, trials: list[str]) -> dict:
    """The final table against the trials: each once, errors, partial entries, result folders."""
    rows, why = table_rows(out)
    res = {"readable": rows is not None, "why_not": why}
    if rows is None:
        return res
    count = collections.Counter(r["file"] for r in rows)
    fitted = [r for r in rows if r["error"] is None]
    incomplete = [r["file"] for r in fitted if any(r[c] is None for c in complete_columns())]
    missing = sorted(set(trials) - set(count))
    res.update({"rows": len(rows), "trials": len(trials), "n_missing": len(missing),
                "missing": [Path(f).name for f in missing[:5]],
                "twice": sorted(f for f, c in count.items() if c > 1), "foreign": sorted(set(count) - set(trials)),
                "exactly_once": sorted(count) == sorted(trials) and all(c == 1 for c in count.values()),
                "errors": [{"file": Path(r["file"]).name, "error": r["error"]} for r in rows if r["error"]],
                "incomplete_rows": incomplete,
                "part_entries": part_entries(out.parent, *([runs] if runs is not None else []))})
    if runs is not None:
        from skelid.io.atomic import INDEX_FILES

        named = {Path(r["result_dir"]).name for r in fitted if r["result_dir"]}
        folders = {p.name for p in runs.iterdir() if p.is_dir() and not PART.match(p.name)} if runs.is_dir() else set()
        bad = [n for n in sorted(named) if not (runs / n / "arrays.npz").is_file()
               or not any((runs / n / f).is_file() for f in INDEX_FILES)]
        res.update({"result_folders": len(folders), "rows_without_folder": sum(not r["result_dir"] for r in fitted),
                    "folders_incomplete": bad, "folders_missing": sorted(named - folders),
                    "folders_unnamed": sorted(folders - named)})
    return res


def complete_columns() -> list[str]:
    """Columns every fitted row fills (the crlb and status columns, the warnings may be null)."""
    from skelid.batch import HEAD, INT_COLUMNS

    cols = columns()
    params = [c for c in cols[len(HEAD):] if c.endswith("_sd") and not c.endswith("_crlb_sd")]
    names = [c[:-3] for c in params]
    return [*HEAD, *INT_COLUMNS, *(f"{n}{s}" for n in names for s in ("", "_sd", "_ci_low", "_ci_high")),
            "sigma", "seconds", "row_sha256"]


def table_ok(check: dict) -> bool:
    return (check["readable"] and check["exactly_once"] and not check["errors"] and not check["incomplete_rows"]
            and not check["part_entries"] and not check.get("folders_incomplete")
            and not check.get("folders_missing") and not check.get("folders_unnamed"))


# --------------------------------------------------------------------------- fault 1: a worker killed
def killed_worker(trials_dir: Path, trials: list[str], work: Path, workers: int = 2, kill_after: int | None = None,
                  timeout: float = 240.0, results: bool = True, kills: int = 1, kill_gap: float = 2.0) -> dict:
    """Run the batch, SIGKILL one Dask worker once ``kill_after`` rows are in the table (``kills`` times, at
    least ``kill_gap`` s apart, each while the batch is fitting: never while its cluster starts), restart the
    command (SIGTERM first) while it fails or hangs; return what happened and :func:`check_table` of the end."""
    n = len(trials)
    kill_after = max(1, n // 5) if kill_after is None else kill_after
    out, runs = work / "killed.parquet", (work / "killed-runs" if results else None)
    cmd = batch_command(trials_dir, out, runs, workers)
    sent: list[dict] = []
    attempts: list[dict] = []
    start_rows = {"n": 0}

    def hook(att: Attempt, t: float, rows: list[dict]) -> None:
        ws = dask_workers(att.proc.pid) if att.proc.poll() is None else []
        for k in sent:
            if "replaced_after_s" not in k and len(ws) == workers and k["worker_pid"] not in ws:
                k["replaced_after_s"] = round(time.monotonic() - k["t"], 2)
        fitting = len(rows) > start_rows["n"]  # this run has added rows: its cluster is up
        if (len(sent) < kills and fitting and kill_after <= len(rows) < n and len(ws) == workers
                and (not sent or time.monotonic() - sent[-1]["t"] >= kill_gap)):
            victim = ws[0]
            _kill(victim)
            sent.append({"at_s": round(t, 2), "rows_in_table": len(rows), "worker_pid": victim, "workers_before": ws,
                         "attempt": len(attempts) + 1, "t": time.monotonic()})

    while len(attempts) < MAX_ATTEMPTS:
        rows, _ = table_rows(out)
        start_rows["n"] = len(rows or [])
        run = Attempt(cmd, out, timeout, hook=hook).run()
        attempts.append(run)
        print(f"killed worker, run {len(attempts)}: exit {run['exit']}, {run['seconds']} s, "
              f"summary {run['summary']}, hung {run['hung']}, stderr {run['stderr'][-3:]}", flush=True)
        if done(run, n):
            break
    for k in sent:
        k.pop("t")
    final = check_table(out, runs, trials)
    retry = None
    if final.get("errors"):  # what --retry-failed makes of the rows the kill left with an error
        retry = Attempt([*cmd, "--retry-failed"], out, timeout).run()
        retry["check"] = check_table(out, runs, trials)
    return {"trials": n, "workers": workers, "kill_after_rows": kill_after, "timeout_s": timeout,
            "command": shown(cmd, work), "kills": sent, "attempts": attempts,
            "client_restarts": len(attempts) - 1, "completed": done(attempts[-1], n),
            "table_polls": sum(a["table_polls"] for a in attempts),
            "table_unreadable": sum(a["table_unreadable"] for a in attempts),
            "table_unreadable_by_path": sum(a["path_unreadable"] for a in attempts),
            "final": final, "retry_failed": retry,
            "ok": len(sent) == kills and done(attempts[-1], n) and table_ok(final)
            and sum(a["table_unreadable"] for a in attempts) == 0}


def killed_at_start(trials_dir: Path, trials: list[str], work: Path, workers: int = 2, timeout: float = 120.0,
                    delay: float = 0.3) -> dict:
    """SIGKILL a Dask worker ``delay`` s after it appears, while the batch's cluster is still starting (before any
    row); then run the same command again. What the first run prints, and whether the second completes."""
    n = len(trials)
    out = work / "start.parquet"
    cmd = batch_command(trials_dir, out, None, workers)
    sent: dict = {}

    def hook(att: Attempt, t: float, rows: list[dict]) -> None:
        if sent.get("done") or att.proc.poll() is not None:
            return
        ws = dask_workers(att.proc.pid)
        if ws and "seen" not in sent:
            sent["seen"] = time.monotonic()
        if ws and not rows and time.monotonic() - sent["seen"] >= delay:
            _kill(ws[0])
            sent.update({"done": True, "at_s": round(t, 2), "worker_pid": ws[0], "workers_seen": ws})

    first = Attempt(cmd, out, timeout, hook=hook).run()
    print(f"killed at start: exit {first['exit']}, {first['seconds']} s, stderr {first['stderr'][-2:]}", flush=True)
    again = Attempt(cmd, out, timeout).run()
    err = first["stderr"]
    sent.pop("seen", None)
    return {"trials": n, "workers": workers, "command": shown(cmd, work), "kill": sent,
            "first": {**first, "stderr": err[-6:], "stderr_lines": len(err)},
            "one_line": len(err) <= 1, "traceback": any("Traceback" in line for line in err),
            "message": err[-1] if err else None, "rerun": again, "completed": done(again, n),
            "final": check_table(out, None, trials)}


# --------------------------------------------------------------------------- reading while the batch writes
def reader_race(rows: list[dict], work: Path, seconds: float = 4.0) -> dict:
    """Rewrite a table again and again (``skelid.batch.write_table``, as the batch does, a growing prefix of
    ``rows`` each time) in a thread while this one reads it, for ``seconds`` per way of reading: by its path
    (``skelid.batch.read_table``) and through one open file (:func:`snapshot_rows`). Reads and failures."""
    from skelid.batch import write_table

    out = work / "race" / "table.parquet"
    out.parent.mkdir(parents=True, exist_ok=True)
    cols = columns()
    res = {}
    for way, read in (("by path", table_rows), ("one open file", snapshot_rows)):
        write_table(out, rows[:10], cols)
        stop = threading.Event()
        writes = [0]

        def writer(stop=stop, writes=writes):
            k = 10
            while not stop.is_set():
                k = 10 if k >= len(rows) else k + 7
                write_table(out, rows[:k], cols)
                writes[0] += 1

        th = threading.Thread(target=writer, daemon=True)
        th.start()
        reads = failed = 0
        texts: list[str] = []
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            got, why = read(out)
            reads += 1
            if got is None:
                failed += 1
                if len(texts) < 3:
                    texts.append(why)
        stop.set()
        th.join()
        res[way] = {"reads": reads, "failed": failed, "writes": writes[0], "texts": texts}
        print(f"reading while rewritten, {way}: {failed} of {reads} reads failed ({writes[0]} rewrites)", flush=True)
    return res


# --------------------------------------------------------------------------- fault 2: disk full
def size_probe(trial: str, n_rows: int, work: Path) -> dict:
    """Bytes of the table with ``n_rows`` rows (copies of one fitted row with their values spread) and of
    the largest file of a trial's result folder."""
    import numpy as np

    from skelid import __version__
    from skelid.batch import HEAD, STRING_COLUMNS, TAIL, fit_trial, row_key, settings_text, write_table
    from skelid.simulate import builtin_model

    model = builtin_model(MODEL)
    ident = {"file_sha256": "0" * 64, "method": "marker", "settings": settings_text(model, None, 0),
             "skelid_version": __version__}
    probe = work / "probe"
    row = fit_trial(trial, model, ident=ident, results_dir=probe / "runs")
    rng = np.random.default_rng(0)
    rows = []
    for i in range(n_rows):
        r = dict(row, file=str(Path(trial).with_name(f"t{i:04d}.trc")), file_sha256=f"{rng.integers(2**62):064x}")
        for c in columns()[len(HEAD):-len(TAIL)] + ["sigma", "seconds"]:
            if c not in STRING_COLUMNS and isinstance(r.get(c), float):
                r[c] *= 1 + 1e-3 * rng.normal()
        rows.append(r)
    assert len({row_key(r) for r in rows}) == n_rows
    write_table(probe / "t.parquet", rows, columns())
    files = [p.stat().st_size for p in Path(row["result_dir"]).iterdir()]
    return {"table_bytes": (probe / "t.parquet").stat().st_size, "result_file_bytes": max(files)}


def limited(limit: int):
    """``preexec_fn``: files no larger than ``limit`` bytes, a write past it failing with EFBIG."""
    def preexec():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return preexec


def disk_full(trials_dir: Path, trials: list[str], work: Path, workers: int = 2, limit: int | None = None,
              timeout: float = 240.0, results: bool = True) -> dict:
    """Run the batch under a file-size limit (the table's size at half the trials by default), then without."""
    n = len(trials)
    probe = size_probe(trials[0], n // 2, work)
    limit = probe["table_bytes"] if limit is None else limit
    out, runs = work / "full.parquet", (work / "full-runs" if results else None)
    cmd = batch_command(trials_dir, out, runs, workers)
    first = Attempt(cmd, out, timeout, preexec=limited(limit)).run()
    print(f"disk full: exit {first['exit']}, {first['seconds']} s, stderr {first['stderr']}", flush=True)
    after = check_table(out, runs, trials)
    left = after.get("rows", 0)
    try:
        out_bytes = out.stat().st_size
    except OSError:
        out_bytes = None
    again = Attempt(cmd, out, timeout).run()
    print(f"disk full, re-run without the limit: exit {again['exit']}, {again['seconds']} s, "
          f"summary {again['summary']}", flush=True)
    final = check_table(out, runs, trials)
    s = again["summary"] or {}
    err = first["stderr"]
    return {"trials": n, "workers": workers, "limit_bytes": limit, "probe": probe, "results_folders": results,
            "command": shown(cmd, work), "limited": first,
            "one_line": len(err) == 1, "traceback": any("Traceback" in line for line in err),
            "message": err[-1] if err else None,
            "table_after": {"bytes": out_bytes, **{k: v for k, v in after.items() if k != "errors"},
                            "errors": after.get("errors", [])},
            "rows_left": left, "rerun": again,
            "fitted_only_missing": bool(s) and s.get("skipped") == left and s.get("fitted", 0) + s.get("failed", 0)
            == n - left,
            "final": final,
            "ok": (first["exit"] not in (0, None) and len(err) == 1 and after.get("readable", False)
                   and not after.get("twice") and not after.get("errors") and not after.get("incomplete_rows")
                   and not after.get("part_entries") and done(again, n) and table_ok(final))}


# --------------------------------------------------------------------------- report
def _yn(v) -> str:
    return "yes" if v else "**no**"


def markdown(res: dict) -> str:
    p = res["provenance"]
    k, d, st = res["killed_worker"], res["disk_full"], res.get("killed_at_start")
    lines = ["# skelid batch under faults: a killed worker, a full disk", "",
             f"Commit `{p['commit'][:10]}`{' (uncommitted changes)' if p.get('dirty') else ''}, {p['date']}, "
             f"{p['cpu']}, {p['cores']} cores, load {p['load_average']} at the start; `{p['command']}`; "
             f"{res['wall_s']:.0f} s wall. {k['trials']} simulated trials (case A, {FRAMES} frames, sigma "
             f"{SIGMA:g} mm), `skelid batch` with {k['workers']} workers in a subprocess. "
             "`benchmarks/batch_faults.py` states the rules.", "",
             "## A worker killed mid-run", "",
             f"`{k['command']}`", "",
             "| | |", "|---|---|"]
    for i, kill in enumerate(k["kills"], 1):
        seen = f"after {kill['replaced_after_s']} s" if "replaced_after_s" in kill else "**not seen**"
        lines.append(f"| SIGKILL {i} to a worker process | pid {kill['worker_pid']} at {kill['at_s']} s of run "
                     f"{kill['attempt']}, {kill['rows_in_table']} rows in the table; replaced {seen} |")
    if not k["kills"]:
        lines.append("| SIGKILL to a worker process | **not sent** (the batch ended first) |")
    for i, a in enumerate(k["attempts"], 1):
        err = f"; stderr: {_code(a['stderr'][-1])}" if a["stderr"] else ""
        lines.append(f"| run {i} | exit {a['exit']}, {a['seconds']} s{', hung: SIGTERM' if a['hung'] else ''}; "
                     f"summary {_summary(a['summary'])}{err} |")
    lines += [f"| client restarts | {k['client_restarts']} |",
              f"| completed | {_yn(k['completed'])} |",
              f"| table readable at every poll (its bytes through one open file) | {_yn(k['table_unreadable'] == 0)} "
              f"({k['table_polls']} polls, {k['table_unreadable']} unreadable) |",
              f"| the same polls by path (`skelid.batch.read_table`) | {k['table_unreadable_by_path']} unreadable"
              + _texts([t for a in k["attempts"] for t in a["path_texts"]]) + " |"]
    lines += _check_lines(k["final"])
    if k["retry_failed"] is not None:
        r = k["retry_failed"]
        lines.append(f"| `--retry-failed` | exit {r['exit']}, summary {_summary(r['summary'])}; errors left "
                     f"{len(r['check'].get('errors', []))} |")
    lines += [f"| **all properties hold** | {_yn(k['ok'])} |", "",
              "## Disk full (a file-size limit)", "",
              f"`{d['command']}` under `RLIMIT_FSIZE` = {d['limit_bytes']} bytes (the table with "
              f"{d['trials'] // 2} rows, estimated: {d['probe']['table_bytes']} bytes; a trial's largest result "
              f"file: {d['probe']['result_file_bytes']} bytes), then again without the limit.", "",
              "| | |", "|---|---|"]
    a, t = d["limited"], d["table_after"]
    lines += [f"| exit status under the limit | {a['exit']} ({a['seconds']} s) |",
              f"| stderr | {len(a['stderr'])} line(s){', a traceback' if d['traceback'] else ', no traceback'}: "
              f"{_code(d['message']) if d['message'] else '(nothing)'} |",
              f"| table left | readable {_yn(t.get('readable'))}, {t.get('rows', 0)} rows ({t['bytes']} bytes), "
              f"rows complete {_yn(not t.get('incomplete_rows'))}, duplicates {len(t.get('twice', []))}, error rows "
              f"{len(t.get('errors', []))}, `.part` entries {len(t.get('part_entries', []))} |",
              f"| table readable at every poll (one open file) | {_yn(a['table_unreadable'] == 0)} ({a['table_polls']} "
              f"polls; by path: {a['path_unreadable']} unreadable) |",
              f"| re-run without the limit | exit {d['rerun']['exit']}, {d['rerun']['seconds']} s, summary "
              f"{_summary(d['rerun']['summary'])} |",
              f"| fitted only the missing trials | {_yn(d['fitted_only_missing'])} ({d['trials'] - d['rows_left']} "
              "missing) |"]
    lines += _check_lines(d["final"])
    lines += [f"| **all properties hold** | {_yn(d['ok'])} |", ""]
    race = res.get("reader_race")
    if race is not None:
        lines += ["## Reading the table while it is rewritten", "",
                  "`skelid.batch.write_table` rewrites a table (10 to all the rows of the killed-worker batch, "
                  "growing) again and again in a thread while another reads it, a few seconds per way of reading.",
                  "", "| way of reading | reads | failed | rewrites meanwhile | first failure |",
                  "|---|---|---|---|---|"]
        for way, r in race.items():
            lines.append(f"| {way} | {r['reads']} | {r['failed']} | {r['writes']} | "
                         f"{_code(r['texts'][0]) if r['texts'] else '-'} |")
        lines.append("")
    if st is not None:
        f = st["first"]
        kill = st["kill"]
        lines += ["## A worker killed while the cluster starts", "",
                  f"`{st['command']}` ({st['trials']} trials): SIGKILL to a worker process "
                  + (f"at {kill['at_s']} s, before any row" if kill.get("done") else "**not sent**")
                  + ", then the same command again.", "", "| | |", "|---|---|",
                  f"| first run | exit {f['exit']}, {f['seconds']} s; stderr {f['stderr_lines']} line(s)"
                  f"{', a traceback' if st['traceback'] else ''}; last: "
                  f"{_code(st['message']) if st['message'] else '(nothing)'} |",
                  f"| one line, no traceback | {_yn(st['one_line'] and not st['traceback'])} |",
                  f"| second run | exit {st['rerun']['exit']}, summary {_summary(st['rerun']['summary'])}; completed "
                  f"{_yn(st['completed'])} |"]
        lines += _check_lines(st["final"]) + [""]
    return "\n".join(lines) + "\n"


def _check_lines(c: dict) -> list[str]:
    if not c.get("readable"):
        return [f"| final table | **unreadable**: {c.get('why_not')} |"]
    out = [f"| final table: every trial exactly once | {_yn(c['exactly_once'])} ({c['rows']} rows for "
           f"{c['trials']} trials; missing {c['n_missing']}, twice {len(c['twice'])}) |",
           f"| rows with an error | {len(c['errors'])}"
           + (": " + "; ".join(f"{e['file']}: {_code(e['error'])}" for e in c["errors"][:5]) if c["errors"] else "")
           + " |",
           f"| fitted rows complete | {_yn(not c['incomplete_rows'])} |",
           f"| `.part` entries left | {len(c['part_entries'])}"
           + (": " + ", ".join(Path(x).name for x in c["part_entries"][:5]) if c["part_entries"] else "") + " |"]
    if "result_folders" in c:
        out.append(f"| result folders | {c['result_folders']}; incomplete {len(c['folders_incomplete'])}, named by a "
                   f"row but absent {len(c['folders_missing'])}, named by no row {len(c['folders_unnamed'])} |")
    return out


def _texts(texts: list[str]) -> str:
    return f": {_code(texts[0])}" if texts else ""


def _summary(s) -> str:
    if not s:
        return "(none)"
    return f"{s['fitted']} fitted, {s['failed']} failed, {s['skipped']} skipped"


def _code(text: str) -> str:
    return "`" + str(text).replace("`", "'").replace("|", "\\|") + "`"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=200, help="simulated trials per batch")
    ap.add_argument("--workers", type=int, default=2, help="Dask worker processes")
    ap.add_argument("--kill-after", type=int, default=None, help="rows in the table before the kill "
                    "(default: a fifth of the trials)")
    ap.add_argument("--kills", type=int, default=1, help="workers killed one after another during the batch")
    ap.add_argument("--kill-gap", type=float, default=2.0, help="seconds at least between two kills")
    ap.add_argument("--timeout", type=float, default=240.0, help="seconds before a run counts as hung")
    ap.add_argument("--start-trials", type=int, default=10, help="trials of the batch whose worker is killed "
                    "while its cluster starts (0: not run)")
    ap.add_argument("--race-seconds", type=float, default=4.0, help="seconds per way of reading the table while "
                    "it is rewritten")
    ap.add_argument("--keep", default=None, help="work in this folder and keep it (default: a temporary one)")
    ap.add_argument("--out", default=None, help="results file stem (default: results/batch_faults)")
    args = ap.parse_args()
    t0 = time.monotonic()
    prov = provenance()  # the command and the load at the start
    work = Path(args.keep or tempfile.mkdtemp(prefix="skelid-batch-faults-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        trials_dir = work / "trials"
        trials = make_trials(trials_dir, args.trials)
        res = {"model": MODEL, "frames": FRAMES, "sigma_mm": SIGMA,
               "killed_worker": killed_worker(trials_dir, trials, work, args.workers, args.kill_after, args.timeout,
                                              kills=args.kills, kill_gap=args.kill_gap),
               "disk_full": disk_full(trials_dir, trials, work, args.workers, timeout=args.timeout)}
        rows, _ = table_rows(work / "killed.parquet")
        if rows:
            res["reader_race"] = reader_race(rows, work, args.race_seconds)
        if args.start_trials:
            res["killed_at_start"] = killed_at_start(work / "start-trials",
                                                     make_trials(work / "start-trials", args.start_trials), work,
                                                     args.workers)
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    res = json.loads(json.dumps(res).replace(str(work), "WORK"))  # the temporary folder's name says nothing
    res = {"provenance": prov, **res, "wall_s": round(time.monotonic() - t0, 1)}
    write_results(Path(args.out) if args.out else results_dir() / "batch_faults", res, markdown)


if __name__ == "__main__":
    main()
