"""Many trials on a Dask cluster: one row per trial in a Parquet or CSV table.

Each row is read from the trial's typed result (:class:`~skelid.result.FitResult`),
with the values of :func:`skelid.io.frames.to_dataframe` per parameter.

``skelid batch MODEL 'DIR/*.trc' --out results.parquet`` fits every matching
file with one method on a ``dask.distributed`` cluster (a local one with one
single-threaded process per worker by default, or an existing one given by
its scheduler address) and writes one row per trial:

========================  ====================================================
column                    meaning
========================  ====================================================
``file``                  the trial's absolute path
``file_sha256``           hash of the trial file's content
``method``                the estimator
``settings``              JSON of the settings that shape the result (model, sigma, seed)
``skelid_version``        the version of skelid that fitted it
``n_frames``              frames in the file
``frames_used``           frames the method used
``<param>``               the estimate (posterior mean) of each parameter
``<param>_sd``            its posterior standard deviation
``<param>_ci_low/high``   its 95 % interval
``<param>_crlb_sd``       its Cramér-Rao bound, or null where the method computes none
``<param>_status``        ``identified``, ``placement``, ``poor``, ``unidentified``, ``prior`` or
                          ``on-bound``, or null where the method gives none
``sigma``                 marker noise (estimated, or as given)
``seconds``               time to read and fit the trial
``error``                 one line saying why the trial failed, or null
``warnings``              the method's warnings, joined by `` | ``, or null
``result_dir``            with ``--results DIR``: the trial's result folder, or null
``row_sha256``            checksum of the row's other values
========================  ====================================================

**Exactly once.** A row is keyed by ``(file_sha256, method, settings,
skelid_version)``: a re-run skips the trials whose key is in the table, and a
run with another method, seed, sigma or model adds rows beside the old ones
(a renamed or moved file with the same content is not fitted again). A table
whose columns are not those of the model (a foreign table), whose rows are
truncated, malformed or do not match their checksum (a corrupt or
hand-edited table), or which holds two rows with one key (duplicates) is
refused with one line before anything is fitted.

With ``--results DIR`` each fitted trial's whole result (the typed run, as
``skelid fit --out`` writes it, through :func:`skelid.io.results.write_run`) goes
into its own folder ``DIR/<file stem>-<hash of the row's key>``, which
``skelid report`` and :mod:`skelid.io.frames` read.

A trial that fails (an unreadable file, a missing marker, no solution) becomes
a row with its error and never stops the batch. The table is rewritten
atomically as trials finish, so an interrupted batch (Ctrl-C, ``SIGTERM``, or
the end of ``--max-time``) leaves a valid table, and a re-run fits only the
trials whose key is not in it yet (``retry_failed`` fits the failed ones
again). A batch whose trials together are estimated to take longer than the
limits (:func:`skelid.resources.batch_cost`) is refused before its cluster
starts. ``dask[distributed]`` and ``pyarrow`` come with the
``[dask]`` extra.
"""

from __future__ import annotations

import csv
import glob
import io
import math
import os
import sys
import time
import warnings
from pathlib import Path

from skelid import _stop
from skelid.errors import SkelidError, SkelidWarning

#: columns before and after the per-parameter ones
HEAD = ("file", "file_sha256", "method", "settings", "skelid_version", "n_frames", "frames_used")
TAIL = ("sigma", "seconds", "error", "warnings", "result_dir", "row_sha256")
#: the columns that identify a trial's fit
KEY = ("file_sha256", "method", "settings", "skelid_version")
STRING_COLUMNS = ("file", "file_sha256", "method", "settings", "skelid_version", "error", "warnings", "result_dir",
                  "row_sha256")
INT_COLUMNS = ("n_frames", "frames_used")
#: per-parameter columns ``<param><suffix>`` and the field of :func:`skelid.io.frames.estimate_fields` each holds
PARAM_FIELDS = {"": "estimate", "_sd": "sd", "_ci_low": "lower", "_ci_high": "upper", "_crlb_sd": "crlb_sd",
                "_status": "status"}
PARAM_SUFFIXES = tuple(PARAM_FIELDS)
#: per-parameter columns that hold text
PARAM_STRING_SUFFIXES = ("_status",)
#: rewrite the table at most this often while trials finish (seconds)
WRITE_INTERVAL = 2.0
#: Seconds a batch waits with no Dask worker connected before it stops (the rows so far kept).
NO_WORKER_WAIT = 120.0
#: Seconds between two looks at the cluster while no trial finishes.
_POLL_S = 1.0
#: run in each worker process of the local cluster: Ctrl-C in a terminal reaches every process of the
#: command, and the batch itself stops the workers (a worker would print its own traceback)
WORKER_IGNORES_SIGINT = "import signal; signal.signal(signal.SIGINT, signal.SIG_IGN)"


def require_dask(parquet: bool = True) -> None:
    """A one-line error unless the ``[dask]`` extra is installed."""
    missing = []
    try:
        import distributed  # noqa: F401
    except ImportError:
        missing.append("dask[distributed]")
    if parquet:
        try:
            import pyarrow  # noqa: F401
        except ImportError:
            missing.append("pyarrow")
    if missing:
        raise SkelidError(f"skelid batch needs {' and '.join(missing)}, which are not installed",
                          "pip install 'skelid[dask]'")


def columns(model) -> list[str]:
    """The table's columns for ``model``, in order.

    Raises
    ------
    SkelidError
        Two parameters' columns would share a name (``a_sd`` beside ``a``'s sd).
    """
    cols = [*HEAD, *(f"{p}{s}" for p in model.parameter_names for s in PARAM_SUFFIXES), *TAIL]
    if len(set(cols)) != len(cols):
        twice = sorted({c for c in cols if cols.count(c) > 1})
        raise SkelidError(f"model {model.name!r} has parameter names that give the batch table the column "
                          f"{twice[0]!r} twice", "rename the parameter so that no name is another's plus "
                          f"{', '.join(s for s in PARAM_SUFFIXES if s)}")
    return cols


def string_columns(cols) -> set[str]:
    """The columns of ``cols`` that hold text (the others hold numbers)."""
    block = list(cols[len(HEAD):len(cols) - len(TAIL)])
    n = len(PARAM_SUFFIXES)
    text = {i for i, s in enumerate(PARAM_SUFFIXES) if s in PARAM_STRING_SUFFIXES}
    return set(STRING_COLUMNS) | {c for i, c in enumerate(block) if i % n in text}


def _one_line(text) -> str:
    return " ".join(str(text).split())


def file_sha256(path) -> str:
    """Hash of a file's content (read in blocks)."""
    import hashlib

    h = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    except OSError as exc:
        return f"unreadable: {exc.strerror or exc}"
    return h.hexdigest()


def settings_text(model, sigma: float | None, seed: int) -> str:
    """The settings that shape a result, as canonical JSON (the model by a hash of its description)."""
    import hashlib
    import json

    m = hashlib.sha256(json.dumps(model.to_dict(), sort_keys=True, default=str).encode()).hexdigest()[:16]
    return json.dumps({"model": m, "sigma": sigma, "seed": seed}, sort_keys=True)


def row_key(row) -> tuple:
    return tuple(row.get(c) for c in KEY)


def row_checksum(row, cols) -> str:
    import hashlib
    import json

    values = [row.get(c) for c in cols if c != "row_sha256"]
    return hashlib.sha256(json.dumps(values, default=repr).encode()).hexdigest()


def fit_trial(path: str, model, method: str = "marker", sigma: float | None = None, seed: int = 0,
              limits=None, ident: dict | None = None, results_dir=None, command=None,
              osim: str | None = None) -> dict:
    """Read and fit one trial; never raises for the trial's own problems.

    With ``results_dir``, the trial's run is written to its own folder there
    (:func:`result_folder`) through :func:`skelid.io.results.write_run`. With
    ``osim``, the ``.osim`` file ``model`` was read from (its marker set is a lab's
    whole protocol): a trial that lacks some of its markers is fitted with the
    model of the markers it has, as ``skelid fit`` does (:func:`skelid.loading.load_model`
    with ``marker_names``); a body left without markers has no estimate in its row.

    Returns
    -------
    dict
        One row (see the module docstring); ``error`` says what went wrong.
    """
    import numpy as np

    from skelid import resources
    from skelid.checks import check_data
    from skelid.estimators.base import prepare
    from skelid.io import read_markers
    from skelid.io.frames import estimate_fields
    from skelid.workflows import check_cost, check_input_file, check_units, make_estimator, method_result

    t0 = time.perf_counter()
    row = dict.fromkeys(columns(model))
    row.update({"file": str(path), "method": method, **(ident or {})})
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", SkelidWarning)
            est = make_estimator(method, model, sigma=sigma, rng=np.random.default_rng(seed))
            check_input_file(path)
            resources.check(resources.read_cost(path), limits, f"reading {path}")
            data = read_markers(path)
            model_t = model
            if osim is not None and not set(model.marker_names) <= set(data.names):
                from skelid.loading import load_model

                model_t = load_model(osim, marker_names=[n for n in model.marker_names if n in data.names])
                est = make_estimator(method, model_t, sigma=sigma, rng=np.random.default_rng(seed))
            check_units(model_t, data)
            row["n_frames"] = int(data.n_frames)
            check_data(model_t, prepare(model_t, data), [method], str(path))
            check_cost(model_t, method, data.n_frames, limits)
            est.fit(data)
            res = method_result(model_t, est)
        row.update(result_values(res, [n for n in model.parameter_names if n in res.parameters], estimate_fields))
        if results_dir is not None:
            row["result_dir"] = str(write_trial_run(results_dir, row, model_t, data, res, command))
        notes = list(dict.fromkeys([*(w.message for w in res.warnings),
                                    *(str(w.message) for w in caught if issubclass(w.category, SkelidWarning))]))
        row["warnings"] = " | ".join(_one_line(w) for w in notes) or None
    except SkelidError as exc:
        row["error"] = exc.one_line()
    except Exception as exc:  # a bug or a broken file: recorded, the batch goes on
        row["error"] = _one_line(f"internal error {type(exc).__name__}: {exc}")
    if row["error"] is not None:  # a failed trial has no estimate at all
        row.update({f"{name}{s}": None for name in model.parameter_names for s in PARAM_SUFFIXES})
    row["seconds"] = round(time.perf_counter() - t0, 4)
    return row


def result_folder(results_dir, row) -> Path:
    """``results_dir/<file stem>-<hash of the row's key>``: one folder per (content, method, settings, version)."""
    import hashlib
    import json

    key = hashlib.sha256(json.dumps(row_key(row)).encode()).hexdigest()[:12]
    return Path(results_dir) / f"{Path(str(row['file'])).stem}-{key}"


def write_trial_run(results_dir, row, model, data, res, command=None) -> Path:
    """Write one trial's run (``res`` and what ``skelid fit`` puts beside it) to its :func:`result_folder`."""
    from skelid.checks import data_overview
    from skelid.io.atomic import atomic_dir
    from skelid.io.results import write_run
    from skelid.provenance import run_context
    from skelid.result import FitRun
    from skelid.workflows import run_arrays

    target = result_folder(results_dir, row)
    run = FitRun({res.method: res}, run_context(model, data.source, data.n_frames, command,
                                                data_overview=data_overview(data, model)),
                 res.warnings, run_arrays(model, data))
    with atomic_dir(target, overwrite=True) as tmp:  # a folder left by an interrupted run is replaced whole
        write_run(tmp, run)
    return target


def result_values(res, names, estimate_fields) -> dict:
    """The row's values from a trial's :class:`~skelid.result.FitResult`: frames used, each
    parameter's fields (:data:`PARAM_FIELDS`), the noise level."""
    out = {"frames_used": None if res.frames is None else int(res.frames.used),
           "sigma": None if res.noise is None or not math.isfinite(res.noise.sigma) else float(res.noise.sigma)}
    for name in names:
        fields = estimate_fields(res.parameters[name])
        if not all(math.isfinite(fields[f]) for f in ("estimate", "sd", "lower", "upper")):
            raise FloatingPointError(f"non-finite estimate of {name}: {res.parameters[name]}")
        out.update({f"{name}{s}": fields[f] for s, f in PARAM_FIELDS.items()})
        out[f"{name}_crlb_sd"] = None if math.isnan(fields["crlb_sd"]) else fields["crlb_sd"]
    return out


# --------------------------------------------------------------------------- the table
def _fmt(out: Path) -> str:
    suffix = out.suffix.lower()
    if suffix == ".parquet":
        return "parquet"
    if suffix == ".csv":
        return "csv"
    raise SkelidError(f"--out {out}: unsupported table type {suffix or '(none)'!r}",
                      "end the file name with .parquet or .csv")


def _schema(cols):
    import pyarrow as pa

    kinds = {**{c: pa.string() for c in string_columns(cols)}, **{c: pa.int64() for c in INT_COLUMNS}}
    return pa.schema([(c, kinds.get(c, pa.float64())) for c in cols])


def read_table(out: Path, cols) -> list[dict]:
    """Rows already in ``out`` (none if it does not exist), each checked.

    Raises
    ------
    SkelidError
        One line: the table cannot be read, its columns are not ``cols`` (a
        foreign table), a row is truncated, malformed or does not match its
        checksum, or two rows share one key.
    """
    from skelid.io.atomic import check_target

    if check_target(out) is None:
        return []
    fmt = _fmt(out)
    fix = "remove it, or choose another --out file"
    try:
        if fmt == "parquet":
            import pyarrow.parquet as pq

            with open(out, "rb") as fh:  # one open file: a rewrite that lands meanwhile cannot mix two tables
                table = pq.read_table(fh)
            names, rows = table.column_names, table.to_pylist()
        else:
            with open(out, newline="", encoding="utf-8") as fh:
                reader = csv.DictReader(fh)
                names = list(reader.fieldnames or [])
                _check_columns(out, names, cols)
                rows, text = [], string_columns(cols)
                for r in reader:
                    if None in r or None in r.values():
                        raise SkelidError(f"table {out} is truncated or corrupt: line {reader.line_num} has "
                                          f"{len(r) - (None in r) - sum(v is None for v in r.values())} fields "
                                          f"for {len(names)} columns", fix)
                    rows.append({k: _from_csv(k, v, out, reader.line_num, k in text) for k, v in r.items()})
    except SkelidError:
        raise
    except Exception as exc:
        raise SkelidError(f"cannot read the existing table {out}: {_one_line(exc)}", fix) from None
    _check_columns(out, names, cols)
    seen = {}
    for i, r in enumerate(rows):
        if r.get("row_sha256") != row_checksum(r, cols):
            raise SkelidError(f"row {i + 1} of table {out} ({r.get('file')}) does not match its checksum: the "
                              "table is truncated, corrupt or was edited", fix)
        k = row_key(r)
        if k in seen:
            raise SkelidError(f"table {out} has duplicate rows {seen[k] + 1} and {i + 1} for one trial "
                              f"({r.get('file')}, {r.get('method')}, the same settings)",
                              "remove one of them, or choose another --out file")
        seen[k] = i
    return rows


def _check_columns(out, names, cols) -> None:
    if list(names) != list(cols):
        raise SkelidError(f"{out} has columns {', '.join(names[:8])}{', ...' if len(names) > 8 else ''}, not "
                          "those of a skelid batch table of this model", "choose another --out file for this model")


def _from_csv(col: str, text: str, out, line: int, is_text: bool):
    if text == "":
        return None
    if is_text:
        return text
    try:
        return int(text) if col in INT_COLUMNS else float(text)
    except ValueError:
        raise SkelidError(f"table {out} is corrupt: line {line} has {text[:40]!r} in column {col}",
                          "remove it, or choose another --out file") from None


def write_table(out: Path, rows: list[dict], cols) -> None:
    """Write ``rows`` to ``out`` atomically (a reader sees the old or the new table, never half)."""
    from skelid.io.atomic import atomic_write

    rows = sorted(({**r, "row_sha256": row_checksum(r, cols)} for r in rows),
                  key=lambda r: (r["file"], r["method"], r.get("settings") or "", r.get("skelid_version") or ""))
    if _fmt(out) == "parquet":
        import pyarrow as pa
        import pyarrow.parquet as pq

        table = pa.Table.from_pylist([{c: r.get(c) for c in cols} for r in rows], schema=_schema(cols))
        with atomic_write(out, "wb") as fh:
            pq.write_table(table, fh)
        return
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for r in rows:
        w.writerow(["" if r.get(c) is None else r.get(c) for c in cols])
    with atomic_write(out, newline="") as fh:
        fh.write(buf.getvalue())


# --------------------------------------------------------------------------- the run
def find_trials(pattern: str) -> list[str]:
    """Absolute paths of the files matching ``pattern`` (a glob, a folder, or a file), sorted."""
    p = Path(pattern)
    if p.is_dir():
        hits = [str(q) for q in p.iterdir() if q.is_file()]
    else:
        hits = [h for h in glob.glob(pattern, recursive=True) if Path(h).is_file()]
    if not hits:
        raise SkelidError(f"no file matches {pattern!r}", "check the pattern; quote it so that the shell "
                          "does not expand it, e.g. 'trials/*.trc'")
    return sorted({str(Path(h).resolve()) for h in hits})


def _client(workers: int | None, scheduler: str | None):
    import logging

    from distributed import Client, LocalCluster

    for name in ("distributed", "distributed.worker", "distributed.nanny", "distributed.scheduler"):
        logging.getLogger(name).setLevel(logging.ERROR)
    if scheduler:
        try:
            return Client(scheduler, timeout="10s"), None
        except (OSError, TimeoutError) as exc:
            raise SkelidError(f"cannot reach the Dask scheduler at {scheduler}: {_one_line(exc)}",
                              "check the address (e.g. tcp://host:8786) and that the scheduler runs") from None
    n = workers or max(1, os.cpu_count() or 1)
    try:
        with warnings.catch_warnings():
            # the scheduler's health endpoint takes another port when 8787 is taken (another cluster running):
            # nothing to tell the user, and it would break the one-line report of a stop
            warnings.filterwarnings("ignore", message=r"Port \d+ is already in use", category=UserWarning)
            # the workers' own logs silenced up to CRITICAL: a fit's failure comes back as its row's error, and
            # at shutdown a worker whose heartbeat races the scheduler's close logs an ERROR with a traceback
            # that no one can act on (it broke --quiet's silence now and then)
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                                   silence_logs=logging.CRITICAL, preload=[WORKER_IGNORES_SIGINT])
    except (RuntimeError, OSError, TimeoutError) as exc:  # a worker that died or could not start meanwhile
        raise SkelidError(f"the local Dask cluster of {n} worker(s) did not start: {_one_line(exc)}",
                          "run the command again (trials already in the table are skipped); if it keeps "
                          "failing, give fewer --workers or free some memory") from None
    return Client(cluster), cluster


def run_batch(model_path, pattern: str, out, method: str = "marker", sigma: float | None = None,
              seed: int = 0, workers: int | None = None, scheduler: str | None = None,
              retry_failed: bool = False, progress: bool = False, limits=None, results_dir=None,
              command=None) -> dict:
    """Fit every trial matching ``pattern`` and add their rows to the table ``out``.

    Parameters
    ----------
    model_path : str
        A model TOML file or a built-in model name.
    pattern : str
        Glob of the trial files (or a folder).
    out : path-like
        ``.parquet`` or ``.csv`` table; rows already there are kept and their
        trials skipped.
    workers : int, optional
        Worker processes of the local cluster (default: one per CPU).
    scheduler : str, optional
        Address of an existing Dask scheduler to use instead.
    retry_failed : bool
        Fit again the trials whose rows hold an error.
    results_dir : path-like, optional
        Folder for each fitted trial's result folder (see :func:`result_folder`).
    command : list of str, optional
        The command line, recorded in each result's provenance.

    Returns
    -------
    dict
        ``{"out", "trials", "fitted", "failed", "skipped", "seconds"}``.
    """
    from skelid import __version__

    out = Path(out)
    model, results_dir = _checked_batch(model_path, out, method, sigma, limits, results_dir)

    cols = columns(model)
    files = find_trials(pattern)
    rows = {row_key(r): r for r in read_table(out, cols)}
    settings = settings_text(model, sigma, seed)
    ident = {f: {"file_sha256": file_sha256(f), "method": method, "settings": settings,
                 "skelid_version": __version__} for f in files}
    key_of = {f: row_key(ident[f]) for f in files}
    todo = [f for f in files
            if key_of[f] not in rows or (retry_failed and rows[key_of[f]].get("error") is not None)]
    summary = {"out": str(out), "trials": len(files), "fitted": 0, "failed": 0,
               "skipped": len(files) - len(todo), "seconds": 0.0}
    if not todo:
        return summary
    if scheduler is None:  # refused before a cluster is started
        _check_batch_cost(model, method, todo, limits, workers or max(1, os.cpu_count() or 1))
    t0 = time.perf_counter()
    osim = str(Path(model_path).absolute()) if str(model_path).lower().endswith(".osim") else None
    client = cluster = None
    try:
        with _stop.deferred():  # a stop while the cluster starts takes effect once it can be closed
            client, cluster = _client(workers, scheduler)
        if scheduler is not None:
            _check_batch_cost(model, method, todo, limits, sum(client.nthreads().values()))
        futures = [client.submit(fit_trial, f, model, method, sigma, seed, limits, ident[f], results_dir, command,
                                 osim, key=f"skelid-fit-{i}-{f}", pure=False) for i, f in enumerate(todo)]
        _collect(client, futures, {fut.key: f for fut, f in zip(futures, todo, strict=True)}, ident, rows, cols,
                 out, summary, progress)
    finally:
        with _stop.deferred():  # closed whole, even when a second signal comes
            if client is not None:
                client.close()
            if cluster is not None:
                cluster.close()
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    return summary


def _check_batch_cost(model, method: str, paths, limits, n_workers: int) -> None:
    """Refuse a batch whose trials together are estimated to exceed ``limits`` (:func:`skelid.resources.batch_cost`)."""
    from skelid import resources

    resources.check(resources.batch_cost(model, method, paths, n_workers), limits,
                    f"skelid batch of {len(paths)} trials")


def _checked_batch(model_path, out: Path, method: str, sigma, limits, results_dir):
    """A batch's model and settings checked before any work: ``(model, absolute results folder or None)``."""
    from skelid.simulate import BUILTIN_MODELS, resolve_model
    from skelid.workflows import check_cost, check_input_file, make_estimator

    if results_dir is not None:  # a file, link or device there is refused before any work
        from skelid.io.atomic import check_target

        check_target(Path(results_dir), folder=True)
        results_dir = Path(results_dir).absolute()
    require_dask(_fmt(out) == "parquet")
    if str(model_path).lower().replace("_", "-") not in BUILTIN_MODELS:
        check_input_file(model_path, "model file")
    model = resolve_model(model_path)
    make_estimator(method, model, sigma)  # an unknown method or a bad sigma fails before any work
    check_cost(model, method, 1, limits)  # a grid too large for any trial
    return model, results_dir


def _finished(client, futures):
    """The futures in the order they finish; a :class:`SkelidError` once no worker has been connected for
    :data:`NO_WORKER_WAIT` s (all of them died, or a scheduler's workers went away), instead of waiting forever."""
    from distributed import wait

    pending, alone = list(futures), None
    while pending:
        try:
            done, left = wait(pending, timeout=_POLL_S, return_when="FIRST_COMPLETED")
        except TimeoutError:
            done, left = (), pending
        if done:
            alone = None
            yield from done
            pending = list(left)
            continue
        if client.nthreads():
            alone = None
        elif alone is None:
            alone = time.monotonic()
        elif time.monotonic() - alone > NO_WORKER_WAIT:
            raise SkelidError(f"no Dask worker has been connected for {NO_WORKER_WAIT:g} s; {len(pending)} "
                              f"trial(s) not fitted (the rows so far are in the table)",
                              "start workers (or leave out --scheduler for a local cluster), then run the "
                              "same command again: the trials already in the table are skipped")


def _collect(client, futures, path_of: dict, ident: dict, rows: dict, cols, out: Path, summary: dict,
             progress: bool):
    """Each finished trial's row into ``rows`` and the table, written every :data:`WRITE_INTERVAL` s.

    A worker that died or a task that could not run gives its trial an error row. Interrupted,
    or left with no worker, what finished is written, so that a re-run resumes from there.
    """
    from tqdm import tqdm

    bar = tqdm(total=len(futures), desc="batch", unit="trial", file=sys.stderr, mininterval=0.25,
               disable=not progress or not sys.stderr.isatty())
    last, unsaved = time.monotonic(), False
    try:
        with bar:
            for fut in _finished(client, futures):
                try:
                    row = fut.result()
                except Exception as exc:  # the worker died or the task could not run
                    row = dict.fromkeys(cols)
                    row.update({"file": path_of[fut.key], **ident[path_of[fut.key]],
                                "error": _one_line(f"worker failed on this trial: {type(exc).__name__}: {exc}")})
                rows[row_key(row)] = row
                unsaved = True
                _stop.check()  # a stop that a library dropped on its way: the rows so far are kept
                summary["failed" if row["error"] is not None else "fitted"] += 1
                bar.update(1)
                if time.monotonic() - last > WRITE_INTERVAL:
                    write_table(out, list(rows.values()), cols)
                    unsaved, last = False, time.monotonic()
        write_table(out, list(rows.values()), cols)
        unsaved = False
    finally:
        if unsaved:  # interrupted: keep what finished, so that a re-run resumes from there
            with _stop.cleanup():
                write_table(out, list(rows.values()), cols)
