"""Fuzzing the command line with broken and hostile input of four classes.

Hypothesis generates model files (valid ones and broken ones: deleted, renamed
and retyped keys, extreme numbers, swapped bounds, random text), data files
(truncated, junk lines, absurd rates and time steps, NaN cells, constant or
short trials, duplicate names, random bytes), result folders (a valid one with
its ``result.json`` or ``arrays.npz`` damaged) and command lines (every
subcommand with options drawn from valid and absurd values). Every case runs
``skelid`` in a worker process under an address-space limit
(``RLIMIT_AS``, :data:`MEMORY_MB`), in an empty folder, and must end in one of
two ways:

* exit 0 with a valid result (JSON that parses with finite estimates, a marker
  file that reads back, an HTML report), or
* exit 2 with exactly one line on stderr, ``skelid: error: ...``, and no new
  file anywhere in the folder;

never a traceback, never another exit status, never a hang (:data:`CASE_TIMEOUT`).
The seed is fixed (``derandomize=True``) and the number of cases bounded, so
the run is repeatable and takes about a minute; the cases tried per class are
printed at the end of the test session.
"""

from __future__ import annotations

import collections
import copy
import json
import math
import os
import selectors
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

tomli_w = pytest.importorskip("tomli_w", reason="tomli-w (the [test] extra) is not installed")

#: address-space limit of the worker process (numpy, scipy, numba and matplotlib need about 1.5 GB of it)
MEMORY_MB = 3000
#: seconds one case may take before it counts as a hang
CASE_TIMEOUT = 60
WORKER = Path(__file__).with_name("fuzz_worker.py")
#: cases tried per class, and their outcomes, for the summary at the end of the session
COUNTS: collections.Counter = collections.Counter()
OUTCOMES: collections.Counter = collections.Counter()


def fuzz_settings(n: int):
    # no shrinking: a failure is reported as found, so a failing run stays as short as a passing one
    return settings(max_examples=n, derandomize=True, database=None, deadline=None, print_blob=False,
                    suppress_health_check=list(HealthCheck), phases=[Phase.explicit, Phase.generate])


# --------------------------------------------------------------------------- the worker
class Worker:
    """One ``skelid`` process kept warm; restarted after a hang or a death."""

    def __init__(self):
        self.proc = None
        self.start()

    def start(self):
        env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1",
               "MPLBACKEND": "Agg", "SKELID_NUMBA": "0"}  # the numpy path: no kernel compile inside a case
        self.proc = subprocess.Popen([sys.executable, str(WORKER), str(MEMORY_MB)], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, env=env)

    def run(self, argv, cwd) -> dict:
        self.proc.stdin.write(json.dumps({"argv": [str(a) for a in argv], "cwd": str(cwd)}) + "\n")
        self.proc.stdin.flush()
        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        ready = sel.select(timeout=CASE_TIMEOUT)
        sel.close()
        line = self.proc.stdout.readline() if ready else ""
        if not line:
            status = "hang" if not ready else f"worker died ({self.proc.poll()})"
            self.stop()
            self.start()
            return {"code": status, "stdout": "", "stderr": ""}
        return json.loads(line)

    def stop(self):
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
        if self.proc is not None:
            self.proc.wait()


@pytest.fixture(scope="module")
def worker():
    w = Worker()
    yield w
    w.stop()


# --------------------------------------------------------------------------- inputs
@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A valid model file, a valid 30-frame trial and a valid result folder."""
    from skelid.io import write_trc
    from skelid.simulate import builtin_model, simulate

    root = tmp_path_factory.mktemp("fuzz-base")
    model = builtin_model("case-a")
    trial = simulate(model, n_frames=30, sigma=5.0, rng=np.random.default_rng(0))
    write_trc(root / "data.trc", trial.data)
    (root / "model.toml").write_text(tomli_w.dumps(model.to_dict()))
    return {"root": root, "model": model.to_dict(), "trc": (root / "data.trc").read_text()}


@pytest.fixture(scope="module")
def result_dir(base, worker):
    res = worker.run(["fit", base["root"] / "model.toml", base["root"] / "data.trc", "--method", "paper",
                      "--method", "marker", "--out", "res", "--quiet"], base["root"])
    assert res["code"] == 0, res
    return base["root"] / "res"


_case = iter(range(10**9))


def new_case_dir(tmp_path_factory, cls: str) -> Path:
    d = tmp_path_factory.getbasetemp() / "fuzz" / f"{cls}-{next(_case)}"
    d.mkdir(parents=True)
    return d


def snapshot(folder: Path) -> dict:
    """Every path under ``folder`` (hidden ones included) with its size and modification time."""
    out = {}
    for p in folder.rglob("*"):
        try:
            st_ = p.lstat()
        except OSError:
            continue
        out[str(p.relative_to(folder))] = (st_.st_size, st_.st_mtime_ns, st_.st_mode)
    return out


def _finite_estimates(obj) -> bool:
    """Every ``mean``/``map``/``sd`` number in a JSON result is finite."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            if k in ("mean", "map", "sd") and isinstance(v, float) and not math.isfinite(v):
                return False
            if not _finite_estimates(v):
                return False
    elif isinstance(obj, list):
        return all(_finite_estimates(v) for v in obj)
    return True


def check_case(cls: str, res: dict, cwd: Path, before: dict, valid_result=None) -> None:
    """The property: exit 0 with a valid result, or exit 2, one stderr line and no new file."""
    COUNTS[cls] += 1
    OUTCOMES[(cls, res["code"])] += 1
    err = res["stderr"]
    assert "Traceback" not in err, f"{cls}: traceback\n{err[-3000:]}"
    assert res["code"] in (0, 2), f"{cls}: exit {res['code']}\n{err[-3000:]}"
    if res["code"] == 2:
        lines = err.splitlines()
        assert len(lines) == 1 and lines[0].startswith("skelid: error: "), f"{cls}: stderr {err[-3000:]!r}"
        assert snapshot(cwd) == before, f"{cls}: files changed on error: {sorted(set(snapshot(cwd)) ^ set(before))}"
    elif valid_result is not None:
        valid_result(res, cwd)


# --------------------------------------------------------------------------- values
FLOAT_TEXT = st.sampled_from(["1e300", "5e-324", "0", "-1", "nan", "inf", "-inf", "abc", "", "1e-300", "100",
                              "2.5", "1e308", "-0"])
WEIRD = st.one_of(
    st.integers(-10**30, 10**30), st.floats(allow_nan=True, allow_infinity=True), st.booleans(),
    st.text(max_size=6), st.sampled_from([1e308, -1e308, 5e-324, 2.9, 0.0, -1.0, "$\\foo$", "m", "hing", []]),
    st.lists(st.floats(-1e3, 1e3), max_size=4), st.dictionaries(st.sampled_from(["a", "type", "lower"]),
                                                                st.integers(-5, 5), max_size=2))


def _paths(obj, prefix=()):
    """Key paths (tuples) of every value in a nested dict/list."""
    out = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.append((*prefix, k))
            out += _paths(v, (*prefix, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out.append((*prefix, i))
            out += _paths(v, (*prefix, i))
    return out


def _get_parent(obj, path):
    for k in path[:-1]:
        obj = obj[k]
    return obj


@st.composite
def mutated(draw, base, max_mutations: int = 3):
    """A deep copy of ``base`` with up to ``max_mutations`` keys deleted, renamed, retyped or swapped."""
    d = copy.deepcopy(base)
    for _ in range(draw(st.integers(0, max_mutations))):
        paths = _paths(d)
        if not paths:
            break
        path = draw(st.sampled_from(paths))
        parent, key = _get_parent(d, path), path[-1]
        op = draw(st.sampled_from(["delete", "rename", "retype", "retype", "swap", "nest"]))
        if op == "delete":
            del parent[key]
        elif op == "rename" and isinstance(parent, dict):
            parent[draw(st.sampled_from([key[:-1] or "x", key + "s", key.replace("o", "", 1), "unit", "postion"]))] \
                = parent.pop(key)
        elif op == "swap" and isinstance(parent[key], list) and len(parent[key]) >= 2:
            parent[key] = parent[key][::-1]
        elif op == "nest":
            v = parent[key]
            for _ in range(draw(st.integers(1, 50))):
                v = [v]
            parent[key] = v
        else:
            parent[key] = draw(WEIRD)
    return d


# --------------------------------------------------------------------------- class 1: model files
@st.composite
def model_files(draw, base_model):
    kind = draw(st.sampled_from(["valid", "mutated", "mutated", "mutated", "raw"]))
    if kind == "valid":
        return tomli_w.dumps(base_model).encode()
    if kind == "raw":
        return draw(st.one_of(st.binary(max_size=200), st.text(max_size=200).map(str.encode),
                              st.just(b"[model]\ndim = 2\n[[segments]]\nname = 1\n")))
    d = draw(mutated(base_model))
    try:
        return tomli_w.dumps(d).encode()
    except (TypeError, ValueError):  # not representable in TOML: write what a person might have typed
        return repr(d).encode()


def _valid_fit_json(res, cwd):
    out = json.loads(res["stdout"])
    assert _finite_estimates(out), res["stdout"][-2000:]


@fuzz_settings(20)
@given(data=st.data())
def test_fuzz_model_files(worker, base, tmp_path_factory, data):
    text = data.draw(model_files(base["model"]))
    cwd = new_case_dir(tmp_path_factory, "model")
    (cwd / "model.toml").write_bytes(text)
    (cwd / "data.trc").write_text(base["trc"])
    before = snapshot(cwd)
    res = worker.run(["fit", "model.toml", "data.trc", "--method", "paper", "--json"], cwd)
    check_case("model files", res, cwd, before, _valid_fit_json)


# --------------------------------------------------------------------------- class 2: data files
@st.composite
def data_files(draw, trc: str):
    lines = trc.splitlines()
    head, body = lines[:6], lines[6:]
    for _ in range(draw(st.integers(1, 3))):
        op = draw(st.sampled_from(["truncate", "junk", "rate", "numframes", "cell", "constant", "rows", "nan",
                                   "time", "names", "binary", "columns"]))
        if op == "truncate":
            text = "\n".join(head + body)
            text = text[: draw(st.integers(0, len(text)))]
            lines = text.split("\n")
            head, body = lines[:6], lines[6:]
        elif op == "junk" and head + body:
            k = draw(st.integers(0, len(head) + len(body) - 1))
            junk = draw(st.text(max_size=30))
            if k < len(head):
                head[k] = junk
            else:
                body[k - len(head)] = junk
        elif op in ("rate", "numframes") and len(head) > 2:
            f = head[2].split("\t")
            for i in ((0, 1, 5) if op == "rate" else (2, 7)):
                if i < len(f):
                    f[i] = draw(FLOAT_TEXT) if op == "rate" else str(draw(st.integers(-5, 10**12)))
            head[2] = "\t".join(f)
        elif op == "cell" and body:
            k = draw(st.integers(0, len(body) - 1))
            c = body[k].split("\t")
            c[draw(st.integers(0, len(c) - 1))] = draw(FLOAT_TEXT)
            body[k] = "\t".join(c)
        elif op == "constant" and body:
            first = body[0].split("\t")
            body = ["\t".join(r.split("\t")[:2] + first[2:]) for r in body]
        elif op == "rows":
            body = body[: draw(st.integers(0, 6))]
        elif op == "nan" and body:
            keep = draw(st.integers(0, len(body) - 1))
            body = [r if i == keep else "\t".join(r.split("\t")[:2] + [""] * (len(r.split("\t")) - 2))
                    for i, r in enumerate(body)]
        elif op == "time" and body:
            step = draw(st.sampled_from([1e-300, 0.0, -0.01, 1e300, 5e-324]))
            body = ["\t".join([r.split("\t")[0], repr(i * step), *r.split("\t")[2:]]) for i, r in enumerate(body)]
        elif op == "names" and len(head) > 3:
            head[3] = head[3].replace("B", draw(st.sampled_from(["A", "$\\foo$", "", "B\tB"])))
        elif op == "binary":
            return draw(st.binary(max_size=300))
        elif op == "columns" and body:
            body = ["\t".join(r.split("\t")[: draw(st.integers(0, 6))]) for r in body]
    return ("\n".join(head + body) + "\n").encode()


@fuzz_settings(20)
@given(data=st.data())
def test_fuzz_data_files(worker, base, tmp_path_factory, data):
    blob = data.draw(data_files(base["trc"]))
    method = data.draw(st.sampled_from(["paper", "paper", "marker"]))
    cwd = new_case_dir(tmp_path_factory, "data")
    (cwd / "trial.trc").write_bytes(blob)
    before = snapshot(cwd)
    res = worker.run(["fit", "case-a", "trial.trc", "--method", method, "--json"], cwd)
    check_case("data files", res, cwd, before, _valid_fit_json)


# --------------------------------------------------------------------------- class 3: result folders
@fuzz_settings(15)
@given(data=st.data())
def test_fuzz_result_files(worker, result_dir, tmp_path_factory, data):
    import shutil

    cwd = new_case_dir(tmp_path_factory, "result")
    res_dir = cwd / "res"
    shutil.copytree(result_dir, res_dir)
    target = data.draw(st.sampled_from(["json", "json", "npz"]))
    if target == "json":
        doc = json.loads((res_dir / "result.json").read_text())
        kind = data.draw(st.sampled_from(["mutated", "mutated", "text", "huge"]))
        if kind == "mutated":
            text = json.dumps(data.draw(mutated(doc, 4)), default=str)
        elif kind == "huge":
            text = json.dumps(doc).replace("{", '{"n": ' + "9" * data.draw(st.integers(1, 5000)) + ",", 1)
        else:
            text = data.draw(st.text(max_size=100))
        (res_dir / "result.json").write_text(text)
    else:
        blob = (res_dir / "arrays.npz").read_bytes()
        kind = data.draw(st.sampled_from(["truncate", "junk", "flat"]))
        if kind == "truncate":
            blob = blob[: data.draw(st.integers(0, len(blob)))]
        elif kind == "junk":
            blob = data.draw(st.binary(max_size=200))
        (res_dir / "arrays.npz").write_bytes(blob)
        if kind == "flat":
            with np.load(result_dir / "arrays.npz") as z:
                arrays = {k: np.ravel(z[k]) for k in z.files}
            np.savez(res_dir / "arrays.npz", **arrays)
    before = snapshot(cwd)

    def valid_report(res, cwd):
        html = (cwd / "report.html").read_text(errors="replace")
        assert html.lstrip().lower().startswith(("<!doctype", "<html")), html[:200]

    res = worker.run(["report", "res", "--out", "report.html", "--quiet"], cwd)
    check_case("result files", res, cwd, before, valid_report)


# --------------------------------------------------------------------------- class 4: command lines
def _opt(name, values):
    return st.one_of(st.just([]), values.map(lambda v: [name, v]))


@st.composite
def command_lines(draw):
    cmd = draw(st.sampled_from(["fit", "fit", "fit", "simulate", "simulate", "report", "batch", "demo", "bogus",
                                "--version", "--help"]))
    out_names = st.sampled_from(["out", "out.trc", "out.csv", "out.txt", "exists.txt", "folder", "dangling",
                                 "fifo", "/dev/null", "", "a/b/c"])
    if cmd == "fit":
        argv = ["fit", draw(st.sampled_from(["model.toml", "case-a", "case-b", "missing.toml", "folder", "fifo",
                                             "data.trc"])),
                draw(st.sampled_from(["data.trc", "data.trc", "missing.trc", "folder", "fifo", "model.toml",
                                      "/dev/null"]))]
        method = draw(st.sampled_from(["paper", "marker", "marker-grid", "bogus", "marker-smc", None]))
        if method is not None:
            argv += ["--method", method]
        if method == "marker-smc":
            argv += ["--max-time", "1ms"]  # refused by its cost estimate: a real run is too slow here
        argv += draw(_opt("--sigma", FLOAT_TEXT)) + draw(_opt("--cutoff", FLOAT_TEXT))
        argv += draw(_opt("--artefact-rms", FLOAT_TEXT)) + draw(_opt("--out", out_names))
        argv += draw(_opt("--seed", st.sampled_from(["0", "-1", str(2**70), "x"])))
        argv += draw(_opt("--max-memory", st.sampled_from(["1K", "8G", "abc", "0", "-1G"])))
        argv += draw(st.sampled_from([[], ["--json"], ["--quiet"], ["--overwrite"]]))
    elif cmd == "simulate":
        argv = ["simulate", draw(st.sampled_from(["case-a", "case-b", "model.toml", "missing", "folder"]))]
        argv += draw(_opt("--frames", st.sampled_from(["0", "1", "5", "50", "-3", str(10**9), str(10**15), "x"])))
        argv += draw(_opt("--rate", FLOAT_TEXT)) + draw(_opt("--sigma", FLOAT_TEXT))
        argv += draw(_opt("--noise", st.sampled_from(["iid", "sta", "x"])))
        argv += draw(st.one_of(st.just([]), out_names.map(lambda v: ["--out", v])))
        if "--frames" not in argv:
            argv += ["--frames", "40"]
    elif cmd == "report":
        argv = ["report", draw(st.sampled_from(["missing", "folder", "exists.txt", "fifo", "empty"]))]
        argv += draw(_opt("--out", out_names))
    elif cmd == "batch":
        argv = ["batch", draw(st.sampled_from(["case-a", "missing.toml"])),
                draw(st.sampled_from(["nomatch*.trc", "folder", "empty"])),
                "--out", draw(st.sampled_from(["r.csv", "r.parquet", "r.xlsx", "exists.txt", "dangling"]))]
        argv += draw(_opt("--method", st.sampled_from(["paper", "bogus"])))
    elif cmd == "demo":  # a valid demo is too long for the harness: every one here has a bad argument
        argv = ["demo", *draw(st.sampled_from([["--frames", "5"], ["--sigma", "-1"], ["--out", "exists.txt"],
                                                ["--out", "dangling"], ["--seed", "-1"], ["--max-memory", "1K"],
                                                ["--frames", "x"]]))]
    else:
        argv = [cmd]
    return argv


def _make_fixtures(cwd: Path, base: dict) -> None:
    (cwd / "model.toml").write_text(tomli_w.dumps(base["model"]))
    (cwd / "data.trc").write_text(base["trc"])
    (cwd / "folder").mkdir()
    (cwd / "folder" / "keep.txt").write_text("keep")
    (cwd / "empty").mkdir()
    (cwd / "exists.txt").write_text("keep")
    (cwd / "dangling").symlink_to(cwd / "nowhere")
    os.mkfifo(cwd / "fifo")


@fuzz_settings(30)
@given(argv=command_lines())
def test_fuzz_command_lines(worker, base, tmp_path_factory, argv):
    cwd = new_case_dir(tmp_path_factory, "argv")
    _make_fixtures(cwd, base)
    before = snapshot(cwd)

    def valid(res, cwd):
        if argv[0] == "simulate":
            from skelid.io import read_markers

            out = argv[argv.index("--out") + 1]
            assert read_markers(cwd / out).n_frames >= 1
        elif argv[0] == "fit" and "--json" in argv:
            _valid_fit_json(res, cwd)
        elif argv[0] in ("--version", "--help"):
            assert res["stdout"].strip()

    res = worker.run(argv, cwd)
    check_case("command lines", res, cwd, before, valid)


def test_fuzz_counts_are_reported():
    """Runs last in this module: every class was tried (the counts are printed at the end of the session)."""
    if not COUNTS:
        pytest.skip("the fuzz classes were not run (deselected)")
    assert {"model files", "data files", "result files", "command lines"} <= set(COUNTS), COUNTS
    assert min(COUNTS.values()) >= 10, COUNTS


def summary_lines() -> list[str]:
    """One line per class: cases tried and their exit statuses."""
    out = []
    for cls, n in sorted(COUNTS.items()):
        codes = ", ".join(f"exit {c}: {k}" for (c2, c), k in sorted(OUTCOMES.items(), key=str) if c2 == cls)
        out.append(f"{cls}: {n} cases ({codes})")
    return out


