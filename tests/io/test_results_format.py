"""The typed result and its one serializer: round trips, reserved-looking names, refusals."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from skelid.errors import FormatError, SkelidError
from skelid.io import results as rio
from skelid.result import FitResult, FitRun, FrameCounts, NoiseEstimate, ParameterEstimate, Warning


def _estimate(name, v=250.0, **kw):
    return ParameterEstimate(name, "mm", map=v, mean=v + 0.1, sd=2.0, interval=(v - 3.9, v + 4.1), **kw)


def _result(names=("L2",), method="marker") -> FitResult:
    params = {n: _estimate(n, 100.0 + k, crlb_sd=1.5 if k else None, extra={"bias_removed": 0.25})
              for k, n in enumerate(names)}
    return FitResult(
        method=method, parameters=params, derived={"thigh": _estimate("thigh", 400.0)},
        noise=NoiseEstimate(15.0, (14.0, 16.2), per_marker={"KNE": 14.0}, extra={"white": 14.8}),
        frames=FrameCounts(500, 480, {"too_few_coordinates": 20}),
        diagnostics={"identifiability": [{"parameter": names[0], "status": "identified"}],
                     "residual_autocorrelation": float("nan"), "nested": {"a": [1, 2, {"b": None}]}},
        warnings=(Warning("poorly-identified", f"parameter {names[0]} is poorly identified", (names[0],)),
                  Warning("not-converged", "the fit did not converge")),
        settings={"sigma": None, "cutoff": "auto", "n_iter": 100},
        provenance={"skelid": "1.0"},
        arrays={"residuals": np.arange(12.0).reshape(4, 3), "pose": np.ones((4, 2))})


def _run(result: FitResult) -> FitRun:
    return FitRun({result.method: result}, context={"model": "case-a", "frames_total": 500},
                  warnings=result.warnings, arrays={"markers": np.zeros((4, 3, 2)),
                                                    "marker_names": np.array(["A", "B", "C"])})


def _same(a: FitResult, b: FitResult) -> None:
    assert a.method == b.method and a.names == b.names
    for k in a.parameters:
        pa, pb = a.parameters[k], b.parameters[k]
        assert (pa.map, pa.mean, pa.sd, pa.interval, pa.crlb_sd, pa.status, pa.extra) == \
               (pb.map, pb.mean, pb.sd, pb.interval, pb.crlb_sd, pb.status, pb.extra)
    assert a.derived == b.derived and a.noise == b.noise and a.frames == b.frames
    assert a.warnings == b.warnings and a.settings == b.settings and a.provenance == b.provenance
    assert set(a.arrays) == set(b.arrays)
    for k in a.arrays:
        np.testing.assert_array_equal(a.arrays[k], b.arrays[k])


@pytest.mark.parametrize("names", [("L2",), ("sigma", "warnings", "lengths"), ("frames", "noise", "method"),
                                   ("parameters", "schema_version", "arrays")])
def test_round_trip_through_files(tmp_path, names):
    r = _result(names)
    rio.write_run(tmp_path, _run(r))
    back = rio.read_run(tmp_path)
    _same(r, back.results["marker"])
    assert back.results["marker"].names == names  # no name swallowed by a reserved key
    assert back.context == {"model": "case-a", "frames_total": 500}
    np.testing.assert_array_equal(back.arrays["marker_names"], ["A", "B", "C"])
    # NaN is written as null (standard JSON) and reads back as NaN
    text = (tmp_path / "result.json").read_text()
    assert "NaN" not in text
    assert math.isnan(back.results["marker"].diagnostics["residual_autocorrelation"] or math.nan)


def test_to_dict_from_dict_round_trip():
    r = _result(("sigma", "lengths"))
    back = rio.result_from_dict(json.loads(json.dumps(rio.result_to_dict(r))), r.arrays)
    _same(r, back)


def test_result_is_immutable():
    r = _result()
    with pytest.raises(AttributeError):
        r.method = "paper"
    with pytest.raises(ValueError):
        r.arrays["pose"][0, 0] = 5.0
    assert r.warnings_for("L2")[0].code == "poorly-identified"
    np.testing.assert_allclose(r.values("mean"), [100.1])


def test_parameter_key_must_match_its_name():
    with pytest.raises(ValueError, match="named"):
        FitResult("marker", parameters={"a": _estimate("b")})
    with pytest.raises(ValueError, match="status"):
        _estimate("a", status="fine")


def _write_doc(tmp_path, doc):
    rio.write_run(tmp_path, _run(_result()))
    (tmp_path / "result.json").write_text(json.dumps(doc) if not isinstance(doc, str) else doc)


def _doc(tmp_path):
    rio.write_run(tmp_path, _run(_result()))
    return json.loads((tmp_path / "result.json").read_text())


def _edit(doc, path, value):
    d = doc
    for k in path[:-1]:
        d = d[k]
    if value is KeyError:
        del d[path[-1]]
    else:
        d[path[-1]] = value
    return doc


@pytest.mark.parametrize("path, value, needle", [
    (("schema_version",), 2, "newer"),
    (("schema_version",), 0, "unknown version 0"),
    (("schema_version",), "1", "expected an integer"),
    (("schema_version",), KeyError, "schema_version"),
    (("format",), "other", "format"),
    (("results",), KeyError, "missing key 'results'"),
    (("results",), [], "expected an object"),
    (("results", "marker", "parameters", "L2", "map"), "abc", "results.marker.parameters.L2.map"),
    (("results", "marker", "parameters", "L2", "interval"), [1.0], "interval"),
    (("results", "marker", "parameters", "L2", "status"), "fine", "status"),
    (("results", "marker", "parameters", "L2", "sd"), True, "expected a number"),
    (("results", "marker", "parameters", "L2", "postion"), 1.0, "unknown key 'postion'"),
    (("results", "marker", "warnings"), "abc", "expected a list of warnings"),
    (("results", "marker", "warnings", 0), "abc", "warnings[0]"),
    (("results", "marker", "frames", "used"), 10**30, "out of range"),
    (("results", "marker", "frames", "used"), 501, "used of 500"),
    (("results", "marker", "method"), "paper", "under the key"),
    (("results", "marker", "arrays", "pose", "shape"), [5, 2], "shape"),
    (("results", "marker", "arrays", "missing"), {"shape": [1], "dtype": "<f8"}, "no array"),
    (("results", "marker", "noise", "per_marker"), [1, 2], "expected an object"),
    (("warnings",), {"a": 1}, "expected a list"),
])
def test_damaged_json_is_one_line(tmp_path, path, value, needle):
    doc = _edit(_doc(tmp_path), path, value)
    (tmp_path / "result.json").write_text(json.dumps(doc))
    with pytest.raises(FormatError) as err:
        rio.read_run(tmp_path)
    msg = err.value.one_line()
    assert needle in msg and "\n" not in msg and str(tmp_path) in msg


def test_legacy_result_names_its_version(tmp_path):
    (tmp_path / "result.json").write_text(json.dumps({"methods": {"marker": {}}}))
    with pytest.raises(FormatError, match="before result schema version 1"):
        rio.read_run(tmp_path)


@pytest.mark.parametrize("text, needle", [
    ("[" * 100_000, "cannot be read"),
    ("[" * 40 + "]" * 40, "expected an object"),
    ('{"schema_version": 1, "format": "skelid-result", "results": {}, "context": {"a": ' + "[" * 40 + "]" * 40 + "}}",
     "nested deeper"),
    ('{"a": 1, "a": 2}', "twice"),
    ('{"schema_version": NaN}', "NaN is not JSON"),
    ('{"schema_version": 1' + "0" * 5000 + "}", "cannot be read"),
    ("\xff\xfe", "UTF-8"),
    ("{not json", "not valid JSON"),
    ("", "not valid JSON"),
])
def test_hostile_json_is_one_line(tmp_path, text, needle):
    _write_doc(tmp_path, "")
    (tmp_path / "result.json").write_bytes(text.encode("latin-1") if text == "\xff\xfe" else text.encode())
    with pytest.raises(FormatError) as err:
        rio.read_run(tmp_path)
    assert needle in err.value.one_line()


@pytest.mark.parametrize("content, needle", [
    (b"", "damaged"),
    (b"PK\x03\x04garbage", "damaged"),
    (b"not a zip at all", "damaged"),
])
def test_damaged_npz_is_one_line(tmp_path, content, needle):
    rio.write_run(tmp_path, _run(_result()))
    (tmp_path / "arrays.npz").write_bytes(content)
    with pytest.raises(FormatError, match=needle):
        rio.read_run(tmp_path)


def test_npz_with_objects_or_wrong_shape_is_refused(tmp_path):
    rio.write_run(tmp_path, _run(_result()))
    np.savez(tmp_path / "arrays.npz", **{"marker/residuals": np.zeros(3), "marker/pose": np.ones((4, 2)),
                                         "run/markers": np.zeros((4, 3, 2)), "run/marker_names": np.array(["A"])})
    with pytest.raises(FormatError, match="shape"):
        rio.read_run(tmp_path)
    np.savez(tmp_path / "arrays.npz", x=np.array([{"a": 1}], dtype=object))
    with pytest.raises(FormatError):
        rio.read_run(tmp_path)


def test_npz_size_is_checked_before_reading(tmp_path, monkeypatch):
    rio.write_run(tmp_path, _run(_result()))
    monkeypatch.setattr(rio, "MAX_ARRAY_BYTES", 10)
    with pytest.raises(FormatError, match="unpacks to"):
        rio.read_run(tmp_path)


def test_missing_folder_and_file(tmp_path):
    with pytest.raises(SkelidError, match="does not exist"):
        rio.read_run(tmp_path / "nope")
    with pytest.raises(SkelidError, match="no result.json"):
        rio.read_run(tmp_path)


def test_folder_without_npz_reads_without_arrays(tmp_path):
    rio.write_run(tmp_path, _run(_result()))
    (tmp_path / "arrays.npz").unlink()
    assert rio.read_run(tmp_path).results["marker"].arrays == {}
