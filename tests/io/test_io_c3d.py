"""C3D reader: header validation, the guarded child process, missing points, units, computed points."""

from __future__ import annotations

import time
import warnings

import numpy as np
import pytest

import skelid.io.c3d as c3d_module
from skelid.errors import FormatError, SkelidWarning
from skelid.io import bone_points, check_c3d_header, read_c3d

ezc3d = pytest.importorskip("ezc3d")


def write_c3d(path, points, labels, *, units=("mm",), rate=100.0, residuals=None, groups=None):
    """A small C3D file written by ezc3d; ``points (F, N, 3)``."""
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [rate]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(labels)
    c["parameters"]["POINT"]["UNITS"]["value"] = list(units)
    F, N, _ = points.shape
    data = np.ones((4, N, F))
    data[:3] = np.transpose(points, (2, 1, 0))
    c["data"]["points"] = data
    if residuals is not None:
        c["data"]["meta_points"] = {"residuals": np.asarray(residuals, float).T[None],
                                    "camera_masks": np.zeros((7, N, F), bool)}
    for name, values in (groups or {}).items():
        c.add_parameter("POINT", name, list(values))
    c.write(str(path))
    return path


@pytest.fixture
def small(tmp_path):
    rng = np.random.default_rng(1)
    pts = rng.normal(500.0, 200.0, size=(6, 3, 3))
    return write_c3d(tmp_path / "small.c3d", pts, ["A", "B", "C"]), pts


def test_reads_points_rate_units(small):
    path, pts = small
    d = read_c3d(path)
    assert d.names == ("A", "B", "C") and d.rate == 100.0 and d.units == "mm"
    np.testing.assert_allclose(d.positions, pts, rtol=1e-6)  # C3D stores float32
    assert d.meta["computed_points"] == [] and d.meta["header"]["consistent"]


def test_in_process_read_equals_isolated_read(data_dir):
    path = data_dir / "opensim-gaps" / "walking2.c3d"
    a, b = read_c3d(path), read_c3d(path, isolate=False)
    np.testing.assert_array_equal(a.positions, b.positions)
    assert a.names == b.names and a.meta["computed_points"] == b.meta["computed_points"]


def test_negative_residual_and_exact_zero_are_missing(tmp_path):
    pts = np.full((5, 2, 3), 7.0)
    pts[3, 1] = 0.0
    residuals = np.zeros((5, 2))
    residuals[1, 0] = -1.0
    d = read_c3d(write_c3d(tmp_path / "gaps.c3d", pts, ["A", "B"], residuals=residuals))
    expected = np.ones((5, 2), bool)
    expected[1, 0] = expected[3, 1] = False
    np.testing.assert_array_equal(d.present, expected)


def test_missing_units_are_guessed_with_a_warning(tmp_path):
    rng = np.random.default_rng(2)
    metres = rng.normal(0.0, 0.4, size=(10, 6, 3)) + [1.0, 2.0, 0.9]
    path = write_c3d(tmp_path / "m.c3d", metres, list("ABCDEF"), units=())
    with pytest.warns(SkelidWarning, match="units guessed as 'm'"):
        d = read_c3d(path)
    assert d.units == "m" and d.meta["units_guessed"]
    path = write_c3d(tmp_path / "mm.c3d", metres * 1000, list("ABCDEF"), units=())
    with pytest.warns(SkelidWarning, match="units guessed as 'mm'"):
        assert read_c3d(path).units == "mm"


def test_unsupported_units_are_refused(tmp_path):
    path = write_c3d(tmp_path / "in.c3d", np.ones((3, 1, 3)), ["A"], units=("in",))
    with pytest.raises(FormatError, match="POINT:UNITS is 'in'"):
        read_c3d(path)


def test_computed_points_from_groups_and_names(tmp_path):
    pts = np.arange(4 * 5 * 3, dtype=float).reshape(4, 5, 3) + 1
    labels = ["S:LASI", "S:LHipAngles", "S:LHJC", "Custom", "RASI"]
    path = write_c3d(tmp_path / "pig.c3d", pts, labels, groups={"ANGLES": ["S:LHipAngles"], "SCALARS": ["Custom"]})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        d = read_c3d(path)
    assert d.names == ("S:LASI", "RASI")
    assert d.meta["computed_points"] == ["S:LHipAngles", "S:LHJC", "Custom"]
    np.testing.assert_allclose(d.meta["computed"]["S:LHJC"], pts[:, 2])


def test_bone_points_gathers_complete_segments(tmp_path):
    labels = ["S:LASI", "S:LFEO", "S:LFEA", "S:LFEL", "S:LFEP", "S:RTIO", "S:RTIP", "S:LHipAngles"]
    pts = np.arange(3 * len(labels) * 3, dtype=float).reshape(3, len(labels), 3) + 1
    d = read_c3d(write_c3d(tmp_path / "bones.c3d", pts, labels))
    bones = bone_points(d)
    assert list(bones) == ["LFE"]  # the right tibia lacks two of its four points
    for k, part in enumerate(("origin", "anterior", "lateral", "proximal")):
        np.testing.assert_allclose(bones["LFE"][part], pts[:, 1 + k])
    assert d.names == ("S:LASI",)


@pytest.mark.parametrize("name", ["LHJC", "R_KJC", "LHipJointCentre", "LKneeMoment", "RAnklePower",
                                  "CentreOfMass", "PELO", "LFEA", "RTIP", "HEDO", "LNormalisedGRF"])
def test_computed_name_pattern(name):
    assert c3d_module.COMPUTED_NAME.search(name)


@pytest.mark.parametrize("name", ["LASI", "RKNE", "LTIB", "LTOE", "RHEE", "C7", "CLAV", "LFHD", "T10", "RPSI"])
def test_marker_names_are_not_computed(name):
    assert not c3d_module.COMPUTED_NAME.search(name)


# ------------------------------------------------------------------ header
def _never_spawn(monkeypatch):
    def fail(*args, **kwargs):
        raise AssertionError("the child process should not be started for this file")

    monkeypatch.setattr(c3d_module, "_extract_in_child", fail)


def test_header_of_real_files_is_consistent(data_dir):
    for path in sorted(data_dir.rglob("*.c3d")):
        h = check_c3d_header(path)
        assert h["consistent"] and h["processor"] == "Intel" and h["n_points"] > 0


@pytest.mark.parametrize(("edit", "message"), [
    (lambda b: b[:100], "at least one 512-byte header block"),
    (lambda b: b[:1] + b"\x51" + b[2:], "not the C3D key 0x50"),
    (lambda b: b"\x00" + b[1:], "parameter section pointer"),
    (lambda b: b"\x01" + b[1:], "parameter section pointer"),
    (lambda b: b[:515] + b"\x07" + b[516:], "unknown processor type"),
    (lambda b: b[: 512 * 3], "runs past the end"),
    (lambda b: b[: len(b) // 2], "truncated"),
    (lambda b: b[:-1], "truncated"),
])
def test_header_refusals_are_immediate(monkeypatch, tmp_path, data_dir, edit, message):
    raw = (data_dir / "kineticstoolkit-tennis" / "kinematics_tennis_serve.c3d").read_bytes()
    path = tmp_path / "bad.c3d"
    path.write_bytes(edit(raw))
    _never_spawn(monkeypatch)
    with pytest.raises(FormatError, match=message) as info:
        read_c3d(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


# ------------------------------------------------------------- child guard
@pytest.mark.parametrize(("source", "message"), [
    ("import os; os.abort()", r"ezc3d crashed \(SIGABRT\)"),
    ("import ctypes; ctypes.string_at(0)", r"ezc3d crashed \(SIGSEGV\)"),
    ("import sys; sys.stderr.write('RuntimeError: boom\\n'); sys.exit(3)", "ezc3d cannot read the file .*boom"),
    ("pass", "returned no data"),
])
def test_a_crash_in_the_child_is_a_format_error(monkeypatch, small, source, message):
    monkeypatch.setattr(c3d_module, "_CHILD_SOURCE", source)
    with pytest.raises(FormatError, match=message) as info:
        read_c3d(small[0])
    assert str(small[0]) in str(info.value)


def test_without_a_child_process_the_read_falls_back_with_a_warning(monkeypatch, small):
    monkeypatch.setattr(c3d_module.sys, "executable", str(small[0].parent / "no-such-python"))
    with pytest.warns(SkelidWarning, match="unguarded"):
        d = read_c3d(small[0])
    assert d.names == ("A", "B", "C")


def test_a_hang_in_the_child_is_a_format_error(monkeypatch, small):
    monkeypatch.setattr(c3d_module, "_CHILD_SOURCE", "import time; time.sleep(60)")
    t = time.perf_counter()
    with pytest.raises(FormatError, match="took more than 1 s"):
        read_c3d(small[0], timeout=1.0)
    assert time.perf_counter() - t < 10


def test_runaway_allocation_is_stopped(tmp_path, data_dir):
    """One corrupt length byte in the parameters makes ezc3d ask for gigabytes."""
    raw = bytearray((data_dir / "kineticstoolkit-tennis" / "kinematics_tennis_serve.c3d").read_bytes())
    at = raw.index(b"\x15Force Structures Used")
    raw[at] = 246
    path = tmp_path / "runaway.c3d"
    path.write_bytes(bytes(raw))
    t = time.perf_counter()
    with pytest.raises(FormatError, match="ran out of memory|cannot read|crashed"):
        read_c3d(path)
    assert time.perf_counter() - t < 15

