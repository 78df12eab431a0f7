"""Writing and reading fit results: ``result.json`` (with a ``schema_version``) plus ``arrays.npz``.

The one serializer of :class:`~skelid.result.FitResult` and :class:`~skelid.result.FitRun`;
``skelid fit``, ``batch`` and ``report`` all go through it. The format is documented in
``docs/result-format.md``.

Reading never trusts the files: a hand-edited or damaged ``result.json`` or
``arrays.npz`` (wrong types, missing keys, deep nesting, huge numbers, arrays of the
wrong shape or that do not fit one another, such as a marginal without its grid or
samples with a column too many, a newer or unknown ``schema_version``) is refused with one
:class:`~skelid.errors.FormatError` line naming the file, the key path and the
problem, before anything uses it. Sizes are bounded before reading.

JSON has no NaN: a non-finite number is written as ``null`` and a ``null`` float
reads back as NaN (``crlb_sd``: as None).

Examples
--------
>>> import tempfile, pathlib
>>> from skelid.result import FitResult, FitRun, NoiseEstimate, ParameterEstimate
>>> p = ParameterEstimate("L2", "mm", 250.0, 250.0, 2.0, (246.1, 253.9))
>>> run = FitRun({"marker": FitResult("marker", {"L2": p}, noise=NoiseEstimate(15.0))})
>>> d = pathlib.Path(tempfile.mkdtemp())
>>> _ = write_run(d, run)
>>> read_run(d).results["marker"].parameters["L2"].sd
2.0
"""

from __future__ import annotations

import json
import math
import re
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from skelid.errors import FormatError
from skelid.io._common import as_path
from skelid.io.atomic import atomic_write
from skelid.result import (
    STATUSES,
    FitResult,
    FitRun,
    FrameCounts,
    NoiseEstimate,
    ParameterEstimate,
    Warning,
)

#: the version this skelid writes; it reads this one only
SCHEMA_VERSION = 1
#: ``format`` field of ``result.json``
FORMAT = "skelid-result"
RESULT_JSON = "result.json"
ARRAYS_NPZ = "arrays.npz"

#: refuse a ``result.json`` larger than this before reading it
MAX_JSON_BYTES = 64 * 2**20
#: refuse an ``arrays.npz`` whose arrays hold more than this, uncompressed, before reading them
MAX_ARRAY_BYTES = 4 * 2**30
#: deepest nesting of JSON objects and lists accepted
MAX_DEPTH = 32
#: longest string accepted anywhere in ``result.json``
MAX_STRING = 100_000
#: most dimensions of one array
MAX_NDIM = 5
#: integers beyond this are not counts or settings but damage
MAX_INT = 2**53

_FIX = "write the folder again with 'skelid fit ... --out DIR'"


# ============================================================================ write
def _clean(v: Any, path: str = "$") -> Any:
    """``v`` as plain JSON values: numpy scalars and arrays converted, non-finite floats as None."""
    if isinstance(v, bool | None | str):
        return v
    if isinstance(v, int | np.integer):
        return int(v)
    if isinstance(v, float | np.floating):
        return float(v) if math.isfinite(v) else None
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, np.ndarray):
        return _clean(v.tolist(), path)
    if isinstance(v, Path):
        return str(v)
    if isinstance(v, Mapping):
        return {str(k): _clean(x, f"{path}.{k}") for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_clean(x, f"{path}[{i}]") for i, x in enumerate(v)]
    raise TypeError(f"{path}: {type(v).__name__} is not a JSON value")


def _estimate_to_dict(p: ParameterEstimate) -> dict:
    return {"unit": p.unit, "map": p.map, "mean": p.mean, "sd": p.sd, "interval": list(p.interval),
            "crlb_sd": p.crlb_sd, "status": p.status, "extra": dict(p.extra)}


def _warning_to_dict(w: Warning) -> dict:
    return {"code": w.code, "message": w.message, "parameters": list(w.parameters)}


def result_to_dict(r: FitResult) -> dict:
    """JSON-ready dict of a result; ``arrays`` appear as ``{key: {"shape", "dtype"}}``."""
    noise = None if r.noise is None else {
        "sigma": r.noise.sigma, "interval": None if r.noise.interval is None else list(r.noise.interval),
        "fixed": r.noise.fixed, "per_marker": dict(r.noise.per_marker), "extra": dict(r.noise.extra)}
    frames = None if r.frames is None else {
        "total": r.frames.total, "used": r.frames.used, "skipped": dict(r.frames.skipped)}
    return _clean({
        "method": r.method,
        "parameters": {k: _estimate_to_dict(p) for k, p in r.parameters.items()},
        "derived": {k: _estimate_to_dict(p) for k, p in r.derived.items()},
        "noise": noise,
        "frames": frames,
        "diagnostics": dict(r.diagnostics),
        "warnings": [_warning_to_dict(w) for w in r.warnings],
        "settings": dict(r.settings),
        "provenance": dict(r.provenance),
        "arrays": {k: {"shape": list(a.shape), "dtype": a.dtype.str} for k, a in r.arrays.items()},
    })


def run_to_dict(run: FitRun) -> dict:
    """The whole ``result.json`` document of a run."""
    return {
        "schema_version": SCHEMA_VERSION,
        "format": FORMAT,
        "context": _clean(dict(run.context)),
        "warnings": [_warning_to_dict(w) for w in run.warnings],
        "arrays": {k: {"shape": list(a.shape), "dtype": a.dtype.str} for k, a in run.arrays.items()},
        "results": {k: result_to_dict(r) for k, r in run.results.items()},
    }


def run_arrays(run: FitRun) -> dict[str, np.ndarray]:
    """The ``arrays.npz`` members of a run: ``run/KEY`` and ``METHOD/KEY``."""
    out = {f"run/{k}": a for k, a in run.arrays.items()}
    for m, r in run.results.items():
        out.update({f"{m}/{k}": a for k, a in r.arrays.items()})
    return out


def dumps(doc: Mapping) -> str:
    """Standard JSON text (no NaN tokens), as the files hold it."""
    return json.dumps(_clean(doc), indent=2, allow_nan=False) + "\n"


def write_run(out_dir, run: FitRun) -> Path:
    """Write ``result.json`` and ``arrays.npz`` of ``run`` into ``out_dir`` (each atomically).

    The JSON is written last: its presence says the folder is complete.

    Returns
    -------
    Path
        The ``result.json`` written.
    """
    out_dir = Path(out_dir)
    for a in run_arrays(run).values():
        if a.dtype.kind not in "biufU":
            raise TypeError(f"array of dtype {a.dtype} cannot be written without pickling")
    with atomic_write(out_dir / ARRAYS_NPZ, "wb", encoding=None) as fh:
        np.savez_compressed(fh, **run_arrays(run))
    with atomic_write(out_dir / RESULT_JSON) as fh:
        fh.write(dumps(run_to_dict(run)))
    return out_dir / RESULT_JSON


# ============================================================================= read
class _Bad(Exception):
    """A problem inside the document, with its key path."""

    def __init__(self, where: str, problem: str):
        super().__init__(f"{where}: {problem}" if where else problem)


def _type_name(v) -> str:
    return {dict: "an object", list: "a list", str: "a string", bool: "true/false", type(None): "null",
            int: "an integer", float: "a number"}.get(type(v), type(v).__name__)


def _obj(v, where: str, keys: dict[str, bool] | None = None) -> dict:
    """``v`` must be an object; with ``keys`` ({key: required}), no other key and no missing one."""
    if not isinstance(v, dict):
        raise _Bad(where, f"expected an object, got {_type_name(v)}")
    if keys is not None:
        unknown = sorted(set(v) - set(keys))
        if unknown:
            raise _Bad(where, f"unknown key {unknown[0]!r} (expected {', '.join(keys)})")
        missing = [k for k, req in keys.items() if req and k not in v]
        if missing:
            raise _Bad(where, f"missing key {missing[0]!r}")
    return v


def _str(v, where: str) -> str:
    if not isinstance(v, str):
        raise _Bad(where, f"expected a string, got {_type_name(v)}")
    return v


def _int(v, where: str, low: int = 0) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise _Bad(where, f"expected an integer, got {_type_name(v)}")
    if not low <= v <= MAX_INT:
        raise _Bad(where, f"integer {v} out of range [{low}, 2**53]")
    return v


def _float(v, where: str, none_ok: bool = False) -> float | None:
    """A JSON number, or null (NaN; None where ``none_ok``)."""
    if v is None:
        return None if none_ok else math.nan
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise _Bad(where, f"expected a number, got {_type_name(v)}")
    if isinstance(v, int) and abs(v) > MAX_INT:
        raise _Bad(where, f"number {v} out of range")
    return float(v)


def _bool(v, where: str) -> bool:
    if not isinstance(v, bool):
        raise _Bad(where, f"expected true or false, got {_type_name(v)}")
    return v


def _pair(v, where: str) -> tuple[float, float]:
    if not isinstance(v, list) or len(v) != 2:
        raise _Bad(where, f"expected a list of two numbers, got {_type_name(v)}")
    return _float(v[0], f"{where}[0]"), _float(v[1], f"{where}[1]")


def _json_value(v, where: str, depth: int = 0) -> Any:
    """Any JSON value, bounded in depth, string length and integer size."""
    if depth > MAX_DEPTH:
        raise _Bad(where, f"nested deeper than {MAX_DEPTH} levels")
    if isinstance(v, dict):
        return {k: _json_value(x, f"{where}.{k}", depth + 1) for k, x in v.items()}
    if isinstance(v, list):
        return [_json_value(x, f"{where}[{i}]", depth + 1) for i, x in enumerate(v)]
    if isinstance(v, str) and len(v) > MAX_STRING:
        raise _Bad(where, f"string of {len(v)} characters (at most {MAX_STRING})")
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) > MAX_INT:
        raise _Bad(where, f"integer {v} out of range")
    if isinstance(v, float) and not math.isfinite(v):
        raise _Bad(where, "NaN or infinity (write null)")
    return v


def _json_object(v, where: str) -> dict:
    return _json_value(_obj(v, where), where)


def _estimate(name: str, v, where: str) -> ParameterEstimate:
    d = _obj(v, where, {"unit": True, "map": True, "mean": True, "sd": True, "interval": True,
                        "crlb_sd": False, "status": True, "extra": False})
    status = _str(d["status"], f"{where}.status")
    if status not in STATUSES:
        raise _Bad(f"{where}.status", f"{status!r} is not one of {', '.join(STATUSES)}")
    return ParameterEstimate(
        name=name, unit=_str(d["unit"], f"{where}.unit"), map=_float(d["map"], f"{where}.map"),
        mean=_float(d["mean"], f"{where}.mean"), sd=_float(d["sd"], f"{where}.sd"),
        interval=_pair(d["interval"], f"{where}.interval"),
        crlb_sd=_float(d.get("crlb_sd"), f"{where}.crlb_sd", none_ok=True), status=status,
        extra=_json_object(d.get("extra", {}), f"{where}.extra"))


def _warnings(v, where: str) -> tuple[Warning, ...]:
    if not isinstance(v, list):
        raise _Bad(where, f"expected a list of warnings, got {_type_name(v)}")
    out = []
    for i, w in enumerate(v):
        wh = f"{where}[{i}]"
        d = _obj(w, wh, {"code": True, "message": True, "parameters": False})
        params = d.get("parameters", [])
        if not isinstance(params, list):
            raise _Bad(f"{wh}.parameters", f"expected a list of names, got {_type_name(params)}")
        out.append(Warning(_str(d["code"], f"{wh}.code"), _str(d["message"], f"{wh}.message"),
                           tuple(_str(p, f"{wh}.parameters[{j}]") for j, p in enumerate(params))))
    return tuple(out)


def _array_specs(v, where: str) -> dict[str, tuple[tuple[int, ...], str]]:
    out = {}
    for k, spec in _obj(v, where).items():
        wh = f"{where}.{k}"
        d = _obj(spec, wh, {"shape": True, "dtype": True})
        if not isinstance(d["shape"], list) or len(d["shape"]) > MAX_NDIM:
            raise _Bad(f"{wh}.shape", f"expected a list of at most {MAX_NDIM} sizes")
        shape = tuple(_int(n, f"{wh}.shape[{i}]") for i, n in enumerate(d["shape"]))
        out[k] = (shape, _str(d["dtype"], f"{wh}.dtype"))
    return out


def _take_arrays(specs: dict, arrays: Mapping[str, np.ndarray], prefix: str, where: str) -> dict:
    out = {}
    for k, (shape, _) in specs.items():
        key = f"{prefix}{k}"
        if key not in arrays:
            raise _Bad(f"{where}.{k}", f"{ARRAYS_NPZ} has no array {key!r}")
        a = arrays[key]
        if a.shape != shape:
            raise _Bad(f"{where}.{k}", f"{ARRAYS_NPZ}[{key!r}] has shape {a.shape}, result.json says {shape}")
        out[k] = a
    return out


def result_from_dict(d, arrays: Mapping[str, np.ndarray] | None = None, where: str = "",
                     prefix: str = "") -> FitResult:
    """A :class:`FitResult` from :func:`result_to_dict`'s output, every field checked.

    ``arrays`` supplies the arrays the document declares (under ``prefix + key``);
    None leaves the result without arrays.

    Raises
    ------
    FormatError
        A field has the wrong type, a key is missing or unknown, a declared array is
        absent or of another shape.
    """
    try:
        return _result(d, arrays, where or "$", prefix)
    except _Bad as exc:
        raise FormatError(f"not a valid skelid result: {exc}") from None


def _result(d, arrays, where: str, prefix: str) -> FitResult:
    d = _obj(d, where, {"method": True, "parameters": True, "derived": False, "noise": False,
                        "frames": False, "diagnostics": False, "warnings": False, "settings": False,
                        "provenance": False, "arrays": False})
    params = {k: _estimate(k, v, f"{where}.parameters.{k}")
              for k, v in _obj(d["parameters"], f"{where}.parameters").items()}
    derived = {k: _estimate(k, v, f"{where}.derived.{k}")
               for k, v in _obj(d.get("derived", {}), f"{where}.derived").items()}
    noise = None
    if d.get("noise") is not None:
        wn = f"{where}.noise"
        n = _obj(d["noise"], wn, {"sigma": True, "interval": False, "fixed": False, "per_marker": False,
                                  "extra": False})
        per = {k: _float(v, f"{wn}.per_marker.{k}")
               for k, v in _obj(n.get("per_marker", {}), f"{wn}.per_marker").items()}
        noise = NoiseEstimate(_float(n["sigma"], f"{wn}.sigma"),
                              None if n.get("interval") is None else _pair(n["interval"], f"{wn}.interval"),
                              _bool(n.get("fixed", False), f"{wn}.fixed"), per,
                              _json_object(n.get("extra", {}), f"{wn}.extra"))
    frames = None
    if d.get("frames") is not None:
        wf = f"{where}.frames"
        f = _obj(d["frames"], wf, {"total": True, "used": True, "skipped": False})
        total, used = _int(f["total"], f"{wf}.total"), _int(f["used"], f"{wf}.used")
        if used > total:
            raise _Bad(f"{wf}.used", f"{used} frames used of {total}")
        skipped = {k: _int(v, f"{wf}.skipped.{k}")
                   for k, v in _obj(f.get("skipped", {}), f"{wf}.skipped").items()}
        frames = FrameCounts(total, used, skipped)
    diagnostics = _json_object(d.get("diagnostics", {}), f"{where}.diagnostics")
    _check(diagnostics, DIAGNOSTIC_KEYS, f"{where}.diagnostics")
    specs = _array_specs(d.get("arrays", {}), f"{where}.arrays")
    arr = {} if arrays is None else _take_arrays(specs, arrays, prefix, f"{where}.arrays")
    _check_result_arrays(arr, f"{where}.arrays", prefix, len(params))
    return FitResult(
        method=_str(d["method"], f"{where}.method"), parameters=params, derived=derived, noise=noise,
        frames=frames, diagnostics=diagnostics,
        warnings=_warnings(d.get("warnings", []), f"{where}.warnings"),
        settings=_json_object(d.get("settings", {}), f"{where}.settings"),
        provenance=_json_object(d.get("provenance", {}), f"{where}.provenance"), arrays=arr)


def run_from_dict(doc, arrays: Mapping[str, np.ndarray] | None = None) -> FitRun:
    """A :class:`FitRun` from a parsed ``result.json`` (and the arrays of ``arrays.npz``).

    Raises
    ------
    FormatError
        Unknown or newer ``schema_version``, or any field not as documented.
    """
    try:
        return _run(doc, arrays)
    except _Bad as exc:
        raise FormatError(f"not a valid skelid result: {exc}", _FIX) from None


def _check_version(doc) -> None:
    if not isinstance(doc, dict):
        raise _Bad("$", f"expected an object, got {_type_name(doc)}")
    if "schema_version" not in doc:
        if "methods" in doc:
            raise _Bad("$", "written by skelid before result schema version 1 (no schema_version)")
        raise _Bad("$", "missing key 'schema_version'")
    v = doc["schema_version"]
    if isinstance(v, bool) or not isinstance(v, int):
        raise _Bad("$.schema_version", f"expected an integer, got {_type_name(v)}")
    if v > SCHEMA_VERSION:
        raise _Bad("$.schema_version", f"version {v} is newer than this skelid reads ({SCHEMA_VERSION}); "
                   "upgrade skelid")
    if v != SCHEMA_VERSION:
        raise _Bad("$.schema_version", f"unknown version {v} (this skelid reads {SCHEMA_VERSION})")


def _run(doc, arrays) -> FitRun:
    _check_version(doc)
    doc = _obj(doc, "$", {"schema_version": True, "format": True, "context": False, "warnings": False,
                          "arrays": False, "results": True})
    if doc["format"] != FORMAT:
        raise _Bad("$.format", f"expected {FORMAT!r}, got {doc['format']!r}")
    results = {k: _result(v, arrays, f"$.results.{k}", f"{k}/")
               for k, v in _obj(doc["results"], "$.results").items()}
    for k, r in results.items():
        if r.method != k:
            raise _Bad(f"$.results.{k}.method", f"{r.method!r} under the key {k!r}")
    specs = _array_specs(doc.get("arrays", {}), "$.arrays")
    arr = {} if arrays is None else _take_arrays(specs, arrays, "run/", "$.arrays")
    _check_run_arrays(arr)
    context = _json_object(doc.get("context", {}), "$.context")
    _check(context, CONTEXT_KEYS, "$.context")
    return FitRun(results, context, _warnings(doc.get("warnings", []), "$.warnings"), arr)


def _no_duplicates(pairs):
    d = {}
    for k, v in pairs:
        if k in d:
            raise _Bad("", f"key {k!r} appears twice in one object")
        d[k] = v
    return d


def _no_constant(token: str):
    raise _Bad("", f"{token} is not JSON (write null)")


def load_json(path) -> Any:
    """Parse ``path`` as JSON with the size, nesting and number bounds; one FormatError line otherwise."""
    path = as_path(path, "result file")
    try:
        size = path.stat().st_size
        if not path.is_file():
            raise FormatError(f"{path} is not a regular file", _FIX)
        if size > MAX_JSON_BYTES:
            raise FormatError(f"{path} is {size / 2**20:.0f} MiB, more than a result file holds "
                              f"({MAX_JSON_BYTES // 2**20} MiB)", _FIX)
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise FormatError(f"{path} is not UTF-8 text", _FIX) from None
    except OSError as exc:
        raise FormatError(f"cannot read {path}: {exc.strerror or exc}", "check the path and permissions") from None
    try:
        return json.loads(text, object_pairs_hook=_no_duplicates, parse_constant=_no_constant)
    except json.JSONDecodeError as exc:
        raise FormatError(f"{path} is not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})",
                          _FIX) from None
    except _Bad as exc:
        raise FormatError(f"{path}: {exc}", _FIX) from None
    except (RecursionError, ValueError) as exc:  # nesting beyond the parser's stack, an integer too long
        raise FormatError(f"{path} cannot be read as a result ({str(exc).splitlines()[0][:80]})", _FIX) from None


def load_npz(path) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` file, bounded in size and kind; one FormatError line otherwise."""
    path = as_path(path, "result file")
    try:
        if not path.is_file():
            raise FormatError(f"{path} is not a regular file", _FIX)
        with zipfile.ZipFile(path) as zf:
            infos = zf.infolist()
        total = sum(i.file_size for i in infos)
        if total > MAX_ARRAY_BYTES:
            raise FormatError(f"{path} unpacks to {total / 2**30:.1f} GiB, more than a result holds "
                              f"({MAX_ARRAY_BYTES / 2**30:.0f} GiB)", _FIX)
        out = {}
        with np.load(path, allow_pickle=False) as z:
            for k in z.files:
                a = z[k]
                if a.dtype.kind not in "biufU" or a.ndim > MAX_NDIM:
                    raise FormatError(f"{path}: array {k!r} of dtype {a.dtype} and {a.ndim} dimensions is "
                                      "not one skelid writes", _FIX)
                out[k] = a
        return out
    except FormatError:
        raise
    except OSError as exc:
        raise FormatError(f"cannot read {path}: {exc.strerror or exc}", "check the path and permissions") from None
    except (zipfile.BadZipFile, ValueError, EOFError, KeyError, RuntimeError, NotImplementedError) as exc:
        raise FormatError(f"{path} is damaged ({str(exc).splitlines()[0][:80] if str(exc) else 'unreadable'})",
                          _FIX) from None


def read_run(result_dir) -> FitRun:
    """Read and validate the run a folder holds (``result.json`` and, if present, ``arrays.npz``).

    A folder without ``arrays.npz`` reads with every array left out.

    Raises
    ------
    FormatError
        The folder, ``result.json`` or ``arrays.npz`` is missing, damaged, of an unknown or
        newer version, or not as documented; one line naming the file and the key path.
    """
    d = as_path(result_dir, "result folder")
    if not d.is_dir():
        raise FormatError(f"result folder {d} does not exist" if not d.exists()
                          else f"{d} is not a result folder", "give the folder 'skelid fit --out DIR' wrote")
    js = d / RESULT_JSON
    if not js.exists():
        raise FormatError(f"{d} has no {RESULT_JSON}", "give the folder 'skelid fit --out DIR' wrote")
    doc = load_json(js)
    npz = d / ARRAYS_NPZ
    arrays = load_npz(npz) if npz.exists() else None
    try:
        return _run(doc, arrays)
    except _Bad as exc:
        raise FormatError(f"{js}: {exc}", _FIX) from None


# ============================================================ the keys readers rely on
# ``context`` and ``diagnostics`` are open objects (any JSON value under a new key), but the
# keys below are read by the report and the conversions, so their shapes are checked too.
# A spec is a type (str, int, float, bool), ``_Opt(spec)`` (null allowed), ``[spec]`` (a list),
# ``_MapOf(spec)`` (an object with any keys) or a dict (an object with these optional keys; a key
# whose spec is ``_Need((spec,))`` must be there).
class _Opt(tuple):
    pass


class _MapOf(tuple):
    pass


class _Need(tuple):
    """A key of an object spec that must be there (the report and the conversions index it)."""


_NUMBER = _Opt((float,))
_MARKER_ROW = {"name": _Need((str,)), "used_by_model": bool, "frames_missing": int, "gaps": int, "longest_gap": int}
_PRIOR = _MapOf((_Opt((float, str)),))
CONTEXT_KEYS = {
    "model": str, "units": str, "frames_total": int,
    "data": _Opt((str, [str])),
    "data_overview": {"source": _Opt((str,)), "format": str, "n_frames": int, "n_markers": int, "dim": int,
                      "rate_hz": _NUMBER, "units": str, "duration_s": _NUMBER, "model_markers": _MapOf((str,)),
                      "markers": [_MARKER_ROW]},
    "model_parameters": _MapOf(({"kind": str, "target": _Opt((str,)), "prior": _PRIOR, "nominal": _NUMBER,
                                 "units": str},)),
    "model_description": _MapOf((_Opt((object,)),)),
    "provenance": {"command": [str], "cwd": str, "created": str, "versions": _MapOf((str,))},
    "truth": _MapOf((_NUMBER,)),
}
#: the model-sensitivity record of ``skelid fit --alternative`` (see :mod:`skelid.sensitivity`)
SENSITIVITY = {"models": [str], "estimates": _MapOf((_MapOf(({"value": _NUMBER, "sd": _NUMBER},)),)),
               "spread": _MapOf(({"values": _MapOf((_NUMBER,)), "spread": _NUMBER, "sd_over_models": _NUMBER,
                                  "largest_sd": _NUMBER},)),
               "average": {"method": str, "unit": str, "blocks": int, "weights": _MapOf((_NUMBER,)),
                           "quantities": _MapOf(({"value": _NUMBER, "sd": _NUMBER, "interval": [_NUMBER],
                                                  "models": [str]},))}}
DIAGNOSTIC_KEYS = {
    "identifiability": [{"parameter": str, "status": str, "crlb_sd": _NUMBER}],
    "model_sensitivity": SENSITIVITY,
}
#: the run's arrays: (dtype kinds, dimensions)
RUN_ARRAYS = {"markers": ("f", 3), "marker_names": ("U", 1), "rate": ("fiu", 0), "units": ("U", 0)}


def _check(v, spec, where: str) -> None:
    """``v`` has the shape ``spec`` describes (see above); raises _Bad naming the key path otherwise."""
    if isinstance(spec, _Opt):
        _check_opt(v, spec, where)
    elif isinstance(spec, _MapOf):
        for k, x in _obj(v, where).items():
            _check(x, spec[0], f"{where}.{k}")
    elif isinstance(spec, _Need):
        _check(v, spec[0], where)
    elif isinstance(spec, dict):
        d = _obj(v, where)
        missing = [k for k, s in spec.items() if isinstance(s, _Need) and k not in d]
        if missing:
            raise _Bad(where, f"has no key {missing[0]!r}")
        for k in spec.keys() & d.keys():
            _check(d[k], spec[k], f"{where}.{k}")
    elif isinstance(spec, list):
        if not isinstance(v, list):
            raise _Bad(where, f"expected a list, got {_type_name(v)}")
        for i, x in enumerate(v):
            _check(x, spec[0], f"{where}[{i}]")
    elif spec in _SCALARS:
        _SCALARS[spec](v, where)


def _check_opt(v, spec: _Opt, where: str) -> None:
    """``v`` is null or has one of the shapes in ``spec`` (the first one's complaint otherwise)."""
    if v is None:
        return
    errors = []
    for s in spec:
        try:
            return _check(v, s, where)
        except _Bad as exc:
            errors.append(exc)
    raise errors[0]


_SCALARS = {float: _float, int: _int, str: _str, bool: _bool}


def _check_run_arrays(arrays: Mapping[str, np.ndarray]) -> None:
    for k, (kinds, ndim) in RUN_ARRAYS.items():
        a = arrays.get(k)
        if a is not None and (a.dtype.kind not in kinds or a.ndim != ndim):
            raise _Bad(f"$.arrays.{k}", f"{ARRAYS_NPZ}[run/{k}] is a {a.ndim}-d array of dtype {a.dtype}, "
                       f"not the {ndim}-d array skelid writes")
    rate = arrays.get("rate")
    if rate is not None:
        from skelid.data import RATE_RANGE

        r = float(rate)
        if not RATE_RANGE[0] <= r <= RATE_RANGE[1]:  # NaN fails too
            raise _Bad("$.arrays.rate", f"{ARRAYS_NPZ}[run/rate] is {r:g} Hz, not a sampling rate between "
                       f"{RATE_RANGE[0]:g} and {RATE_RANGE[1]:g} Hz")
    y, names = arrays.get("markers"), arrays.get("marker_names")
    if y is not None and names is not None and y.shape[1] != names.shape[0]:
        raise _Bad("$.arrays.markers", f"{y.shape[1]} markers but {names.shape[0]} marker names")


#: the arrays of one method's result that the report reads: (dtype kinds, dimensions). ``posterior.axis``,
#: ``posterior.marginal`` and ``posterior.history`` stand for ``posterior.axis.K`` ... of each parameter K
RESULT_ARRAYS = {
    "posterior.kind": ("U", 0), "posterior.names": ("U", 1),
    "posterior.mean": ("fiu", 1), "posterior.cov": ("fiu", 2),
    "posterior.history_steps": ("fiu", 1), "posterior.history_mean": ("fiu", 2), "posterior.history_cov": ("fiu", 3),
    "posterior.axis": ("fiu", 1), "posterior.marginal": ("fiu", 1), "posterior.history": ("fiu", 2),
    "samples": ("fiu", 2), "sample_weights": ("fiu", 1),
    "residuals": ("fiu", 2), "pose": ("fiu", 2), "measured": ("fiu", 1), "map_path": ("fiu", 1),
}
_GRID_KEY = re.compile(r"^posterior\.(axis|marginal|history)\.(\d+)$")


def _check_result_arrays(a: Mapping[str, np.ndarray], where: str, prefix: str, n_params: int) -> None:
    """The arrays of one method's result hang together as the estimators write them (see
    :func:`posterior_arrays`), so that the report can index one by another; raises _Bad naming
    the first that does not (an array another one needs, or one of another shape or dtype)."""
    for k, x in a.items():
        spec = RESULT_ARRAYS.get(_GRID_KEY.sub(r"posterior.\1", k))
        if spec is not None and (x.dtype.kind not in spec[0] or x.ndim != spec[1]):
            what = "strings" if spec[0] == "U" else "numbers"
            raise _Bad(f"{where}.{k}", f"{ARRAYS_NPZ}[{prefix}{k}] is a {x.ndim}-d array of dtype {x.dtype}, "
                       f"not the {spec[1]}-d array of {what} skelid writes")
    check = _ArrayCheck(a, where, prefix)
    check.posterior(n_params)
    check.samples()
    check.paths()


class _ArrayCheck:
    """The checks of :func:`_check_result_arrays` that relate one array to another."""

    def __init__(self, a: Mapping[str, np.ndarray], where: str, prefix: str):
        self.a, self.where, self.prefix = a, where, prefix

    def bad(self, k: str, problem: str) -> _Bad:
        return _Bad(f"{self.where}.{k}", f"{ARRAYS_NPZ}[{self.prefix}{k}] {problem}")

    def need(self, k: str, other: str) -> None:
        """``other`` is there where ``k`` is."""
        if k in self.a and other not in self.a:
            raise self.bad(k, f"is there but {self.prefix}{other} is not")

    def shape(self, k: str, shape: tuple[int, ...], what: str) -> None:
        if k in self.a and self.a[k].shape != shape:
            raise self.bad(k, f"has shape {self.a[k].shape}, not {shape} ({what})")

    def finite(self, k: str, low: float = -math.inf) -> None:
        x = self.a.get(k)
        if x is not None and not (np.isfinite(x).all() and (x >= low).all()):
            raise self.bad(k, "holds values that are not finite numbers" + (f" >= {low:g}" if low > -math.inf else ""))

    def posterior(self, n_params: int) -> None:
        """Mean and covariance sized by ``posterior.names``, and the grids and histories.

        The report indexes the mean, covariance and samples by ``posterior.names`` (without it
        they are not drawn, as in an OpenSim fit's result), and the histories by those names or
        else by the result's ``n_params`` parameters.
        """
        a = self.a
        names = a.get("posterior.names")
        P = n_params if names is None else len(names)
        if names is not None:
            per = f"one per parameter in {self.prefix}posterior.names"
            self.need("posterior.mean", "posterior.cov")
            self.need("posterior.cov", "posterior.mean")
            self.shape("posterior.mean", (P,), per)
            self.shape("posterior.cov", (P, P), per)
        steps = a.get("posterior.history_steps")
        for k in ("posterior.history_mean", "posterior.history_cov"):
            self.need(k, "posterior.history_steps")
            self.need(k, "posterior.history_mean" if k.endswith("cov") else "posterior.history_cov")
        if steps is not None:
            S = len(steps)
            self.shape("posterior.history_mean", (S, P), "one row per history step and parameter")
            self.shape("posterior.history_cov", (S, P, P), "one matrix per history step")
        for k in sorted({int(m.group(2)) for m in map(_GRID_KEY.match, a) if m}):
            self.grid(k, steps)

    def grid(self, k: int, steps) -> None:
        """Parameter ``k``'s grid: an axis of finite numbers, its marginal, its history."""
        axis, marginal, history = f"posterior.axis.{k}", f"posterior.marginal.{k}", f"posterior.history.{k}"
        self.need(marginal, axis)
        self.need(axis, marginal)
        self.need(history, axis)
        self.need(history, "posterior.history_steps")
        n = len(self.a[axis])
        if n == 0:
            raise self.bad(axis, "is empty (a grid has at least one point)")
        self.finite(axis)
        self.shape(marginal, (n,), f"one value per point of {self.prefix}{axis}")
        if steps is not None:
            self.shape(history, (len(steps), n), "one marginal per history step")

    def samples(self) -> None:
        """Posterior samples ``(N, P)`` of finite numbers and their N weights."""
        x = self.a.get("samples")
        self.need("sample_weights", "samples")
        if x is None:
            return
        if "posterior.names" in self.a:
            self.shape("samples", (len(x), len(self.a["posterior.names"])),
                       f"one column per parameter in {self.prefix}posterior.names")
        if len(x) == 0:
            raise self.bad("samples", "is empty")
        self.finite("samples")
        self.shape("sample_weights", (len(x),), f"one weight per row of {self.prefix}samples")
        self.finite("sample_weights", 0.0)
        if "sample_weights" in self.a and not self.a["sample_weights"].sum() > 0:
            raise self.bad("sample_weights", "sums to 0")

    def paths(self) -> None:
        """Per-frame arrays: residuals of at least one frame; the measured values beside the MAP path."""
        if "residuals" in self.a and len(self.a["residuals"]) == 0:
            raise self.bad("residuals", "has no frames")
        if "measured" in self.a and "map_path" in self.a:
            self.shape("measured", self.a["map_path"].shape, f"one value per frame of {self.prefix}map_path")


# ============================================================ arrays of a fitted estimator
def posterior_arrays(est) -> dict[str, np.ndarray]:
    """The posterior of a fitted estimator as arrays (``posterior.*``), for the report's figures.

    ``posterior.kind`` says which form: ``grid`` (``axis.K``, ``marginal.K`` and
    ``history.K`` per parameter K with ``history_steps``), ``gaussian`` (``mean``,
    ``cov`` and, where the estimator keeps one, its history ``history_mean``,
    ``history_cov``, ``history_steps``) or ``samples`` (``mean``, ``cov``; the
    samples themselves are the result's ``samples`` and ``sample_weights``).
    ``posterior.names`` lists the parameters. An estimator without ``posterior_`` gives none.
    """
    post = getattr(est, "posterior_", None)
    if post is None:
        return {}
    history = tuple(getattr(post, "history", ()) or ())
    if hasattr(post, "axes") and hasattr(post, "marginal"):
        out = _grid_arrays(post, history)
    elif hasattr(post, "points") and hasattr(post, "weights"):
        out = {"kind": np.array("samples"), "mean": np.asarray(post.mean, float),
               "cov": np.atleast_2d(np.asarray(post.cov, float))}
    elif hasattr(post, "cov"):
        out = _gaussian_arrays(post, history)
    else:
        out = {}
    out["names"] = np.array(tuple(getattr(post, "names", ())), dtype=str)
    return {f"posterior.{k}": v for k, v in out.items()}


def _grid_arrays(post, history) -> dict[str, np.ndarray]:
    steps = [int(h[0]) for h in history]
    out = {"kind": np.array("grid"), "history_steps": np.array(steps, dtype=int)}
    for k, ax in enumerate(post.axes):
        out[f"axis.{k}"] = np.asarray(ax, float)
        out[f"marginal.{k}"] = np.asarray(post.marginal(k), float)
        if steps:
            out[f"history.{k}"] = np.stack([post.marginal(k, h[1]) for h in history])
    return out


def _gaussian_arrays(post, history) -> dict[str, np.ndarray]:
    out = {"kind": np.array("gaussian"), "mean": np.asarray(post.mean, float), "cov": np.asarray(post.cov, float)}
    hist = [h for h in history if len(h) == 3]
    if hist:
        out["history_steps"] = np.array([int(h[0]) for h in hist])
        out["history_mean"] = np.stack([np.asarray(h[1], float) for h in hist])
        out["history_cov"] = np.stack([np.asarray(h[2], float) for h in hist])
    return out


def write_json(path, obj) -> Path:
    """Write ``obj`` as standard JSON (non-finite numbers as null) atomically."""
    path = Path(path)
    with atomic_write(path) as fh:
        fh.write(dumps(obj))
    return path
