"""Fuzzing the readers with mutated real files.

Each case takes a real file (or its first lines, to keep a case to a few
milliseconds), applies one to three mutations (truncation, flipped or inserted
bytes, dropped or repeated lines and columns, wrong header counts, huge
numbers, NaN and infinities), or replaces it by an empty file or binary
garbage, and asserts that the reader either returns a valid MarkerData or
raises FormatError/DataError: never another exception, never a hang (a 30 s
alarm), never a crash of the interpreter (C3D files are read in a child
process). Counts are printed at the end of the session as
``fuzz: <reader> tried N cases, M valid, K refused``.
"""

from __future__ import annotations

import re
import signal
import warnings
from contextlib import contextmanager

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from skelid.data import MarkerData
from skelid.errors import DataError, FormatError, SkelidWarning
from skelid.io import read_c3d, read_csv, read_markers, read_trc, read_tsv, write_csv

FUZZ = dict(derandomize=True, deadline=None, database=None,
            suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
TOKENS = ["1e308", "-1e400", "9" * 400, "nan", "NaN", "inf", "-inf", "", "0", "0.0", "1e13", "abc", "-0",
          "1,5", "\t", "  ", "1e-320", "١٢"]
HEADER_VALUES = ["0", "-1", "1", "2", "999999999", "abc", "", "1e9", "nan", "inf", "-60", "0.0001"]


# ------------------------------------------------------------ mutations
def _lines(raw: bytes) -> list[bytes]:
    return raw.split(b"\n")


def _at(seq, where: float) -> int:
    return min(int(where * len(seq)), max(len(seq) - 1, 0))


def apply(raw: bytes, op: tuple, sep: bytes) -> bytes:
    kind = op[0]
    if kind == "truncate":
        return raw[: int(op[1] * len(raw))]
    if kind == "flip":
        b = bytearray(raw)
        for where, value in op[1]:
            if b:
                b[_at(b, where)] = value
        return bytes(b)
    if kind == "insert":
        k = int(op[1] * len(raw))
        return raw[:k] + op[2] + raw[k:]
    if kind == "delete":
        k = int(op[1] * len(raw))
        return raw[:k] + raw[k + op[2]:]
    lines = _lines(raw)
    if kind == "drop_line" and lines:
        del lines[_at(lines, op[1])]
    elif kind == "dup_line" and lines:
        k = _at(lines, op[1])
        lines.insert(k, lines[k])
    elif kind in ("drop_column", "dup_column"):
        out = []
        for line in lines:
            f = line.split(sep)
            k = op[1] % len(f)
            if kind == "drop_column":
                del f[k]
            else:
                f.insert(k, f[k])
            out.append(sep.join(f))
        lines = out
    elif kind == "number" and lines:
        k = _at(lines, op[1])
        f = lines[k].split(sep)
        f[op[2] % len(f)] = op[3].encode()
        lines[k] = sep.join(f)
    elif kind == "header_value":
        text = b"\n".join(lines).decode("latin-1")
        return _set_header_value(text, op[1], op[2]).encode("latin-1")
    return b"\n".join(lines)


def _set_header_value(text: str, key: str, value: str) -> str:
    """Give header ``key`` a wrong ``value``, in whichever way the format writes its header."""
    lines = text.split("\n")
    for i, line in enumerate(lines[:12]):
        sep = "\t" if "\t" in line else ","
        f = line.split(sep)
        if key in (s.strip() for s in f):
            col = [s.strip() for s in f].index(key)
            if col == 0 and len(f) > 1:  # KEY<TAB>value (Qualisys)
                f[1] = value
                lines[i] = sep.join(f)
            elif i + 1 < len(lines):  # keys on one line, values on the next (TRC)
                g = lines[i + 1].split(sep)
                if col < len(g):
                    g[col] = value
                    lines[i + 1] = sep.join(g)
            return "\n".join(lines)
    return re.sub(rf"{re.escape(key)}=\S*", f"{key}={value}", text, count=1)


def ops(header_keys):
    where = st.floats(0, 1) | st.floats(0.3, 1)  # relative position; more often past the header
    return st.one_of(
        st.tuples(st.just("truncate"), where),
        st.tuples(st.just("flip"), st.lists(st.tuples(where, st.integers(0, 255)), min_size=1, max_size=8)),
        st.tuples(st.just("insert"), where, st.binary(min_size=1, max_size=16)),
        st.tuples(st.just("delete"), where, st.integers(1, 64)),
        st.tuples(st.just("drop_line"), where),
        st.tuples(st.just("dup_line"), where),
        st.tuples(st.just("drop_column"), st.integers(0, 300)),
        st.tuples(st.just("dup_column"), st.integers(0, 300)),
        st.tuples(st.just("number"), where, st.integers(0, 300), st.sampled_from(TOKENS)),
        st.tuples(st.just("header_value"), st.sampled_from(header_keys), st.sampled_from(HEADER_VALUES)),
    )


def cases(sources: list[bytes], header_keys, sep: bytes):
    """Mutated source files, empty files and binary garbage."""
    mutated = st.tuples(st.sampled_from(range(len(sources))), st.lists(ops(header_keys), min_size=1, max_size=3)).map(
        lambda t: _mutate(sources[t[0]], t[1], sep))
    return st.one_of(mutated, mutated, mutated, mutated, st.just(b""), st.binary(max_size=3000))


def _mutate(raw: bytes, operations, sep: bytes) -> bytes:
    for op in operations:
        raw = apply(raw, op, sep)
    return raw


# --------------------------------------------------------------- harness
class Hang(Exception):
    pass


@contextmanager
def deadline(seconds: float):
    def on_alarm(signum, frame):
        raise Hang(f"reader still running after {seconds} s")

    if not hasattr(signal, "setitimer"):  # no alarms on this platform: run unguarded
        yield
        return
    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def check(reader, path, counts, label):
    """Run ``reader(path)``: a valid MarkerData or FormatError/DataError, nothing else."""
    counts[label]["tried"] += 1
    try:
        with deadline(30.0), warnings.catch_warnings():
            warnings.simplefilter("ignore", SkelidWarning)
            d = reader(path)
    except (FormatError, DataError) as exc:
        counts[label]["refused"] += 1
        msg = str(exc)
        assert msg and "\n" not in msg, f"error message is not one line: {msg!r}"
        return
    assert isinstance(d, MarkerData)
    pos = d.positions
    assert pos.ndim == 3 and pos.shape[0] >= 1 and pos.shape[1] == len(d.names) >= 1 and pos.shape[2] in (2, 3)
    assert not np.isinf(pos).any()
    assert np.all(np.abs(pos[np.isfinite(pos)]) <= 1e12)
    assert np.isfinite(d.rate) and d.rate > 0 and d.units in ("mm", "cm", "m")
    counts[label]["valid"] += 1


def _head(path, n_lines: int) -> bytes:
    return b"\n".join(path.read_bytes().split(b"\n")[:n_lines])


@pytest.fixture(scope="module")
def sources(data_dir, tmp_path_factory):
    d = data_dir
    own = tmp_path_factory.mktemp("own") / "own.csv"
    rng = np.random.default_rng(0)
    pos = rng.normal(0, 300, size=(20, 3, 3))
    pos[3, 1] = np.nan
    write_csv(own, MarkerData(pos, ("A", "B", "S:C"), 120.0, "mm"))
    return {
        "trc": [(d / "opensim-subject01/walk_free_01.trc").read_bytes(),
                _head(d / "opensim-gaps/dataWithBlanksForMissingMarkers.trc", 40),
                _head(d / "pyomeca-upperlimb/markers.trc", 30)],
        "vicon": [_head(d / "pyomeca-upperlimb/markers.csv", 40)],
        "csv": [_head(d / "bmc-pendulum/3dPendulum.txt", 60), own.read_bytes()],
        "tsv": [_head(d / "hand-fingers/recording.tsv", 60)],
        "c3d": [(d / "kineticstoolkit-tennis/kinematics_tennis_serve.c3d").read_bytes()],
    }


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


# ----------------------------------------------------------------- tests
TRC_KEYS = ["DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units"]
TSV_KEYS = ["NO_OF_FRAMES", "NO_OF_MARKERS", "FREQUENCY", "DATA_INCLUDED", "MARKER_NAMES"]
CSV_KEYS = ["rate", "units"]


@settings(max_examples=300, **FUZZ)
@given(data=st.data())
def test_fuzz_trc(sources, work, fuzz_counts, data):
    raw = data.draw(cases(sources["trc"], TRC_KEYS, b"\t"))
    if data.draw(st.booleans()):  # the comma-separated flavour too
        raw = raw.replace(b"\t", b",")
    path = work / "case.trc"
    path.write_bytes(raw)
    check(read_trc, path, fuzz_counts, "read_trc")


@settings(max_examples=250, **FUZZ)
@given(data=st.data())
def test_fuzz_vicon_csv(sources, work, fuzz_counts, data):
    path = work / "case_vicon.csv"
    path.write_bytes(data.draw(cases(sources["vicon"], ["Trajectories"], b",")))
    check(read_csv, path, fuzz_counts, "read_csv (Vicon)")


@settings(max_examples=250, **FUZZ)
@given(data=st.data())
def test_fuzz_column_csv(sources, work, fuzz_counts, data):
    path = work / "case_columns.csv"
    path.write_bytes(data.draw(cases(sources["csv"], CSV_KEYS, b",")))
    check(read_csv, path, fuzz_counts, "read_csv (columns)")


@settings(max_examples=250, **FUZZ)
@given(data=st.data())
def test_fuzz_qualisys_tsv(sources, work, fuzz_counts, data):
    path = work / "case.tsv"
    path.write_bytes(data.draw(cases(sources["tsv"], TSV_KEYS, b"\t")))
    check(read_tsv, path, fuzz_counts, "read_tsv")


C3D_WORDS = st.tuples(st.sampled_from([0, 2, 4, 6, 8, 16, 18]), st.integers(0, 65535))


def _c3d_case(raw: bytes, kind: str, draw) -> bytes:
    """C3D mutations: header words, bytes in the header and parameter blocks, truncation, data bytes."""
    b = bytearray(raw)
    if kind == "header_word":  # wrong counts: points, analog, first/last frame, data start, ...
        offset, value = draw(C3D_WORDS)
        b[offset:offset + 2] = value.to_bytes(2, "little")
    elif kind == "parameters":
        for _ in range(draw(st.integers(1, 6))):
            b[draw(st.integers(0, 512 * 8 - 1))] = draw(st.integers(0, 255))
    elif kind == "data":
        for _ in range(draw(st.integers(1, 6))):
            b[draw(st.integers(512 * 8, len(b) - 1))] = draw(st.integers(0, 255))
    elif kind == "truncate":
        b = b[: draw(st.integers(0, len(b)))]
    elif kind == "key":
        b[1] = draw(st.integers(0, 255))
    return bytes(b)


@settings(max_examples=60, **FUZZ)
@given(data=st.data())
def test_fuzz_c3d(sources, work, fuzz_counts, data):
    kind = data.draw(st.sampled_from(["header_word", "parameters", "parameters", "data", "truncate", "key",
                                      "garbage", "empty"]))
    if kind == "garbage":
        raw = data.draw(st.binary(min_size=0, max_size=4096))
    elif kind == "empty":
        raw = b""
    else:
        raw = _c3d_case(sources["c3d"][0], kind, data.draw)
    path = work / "case.c3d"
    path.write_bytes(raw)
    check(read_c3d, path, fuzz_counts, "read_c3d")


EXTENSIONS = [".c3d", ".trc", ".csv", ".txt", ".tsv", ".xml", ".osim", ""]


@pytest.mark.parametrize("ext", [e for e in EXTENSIONS if e != ".c3d"])
def test_c3d_under_another_name_is_read_as_c3d(sources, work, ext):
    path = work / f"lying{ext}"
    path.write_bytes(sources["c3d"][0])
    assert read_markers(path).meta["format"] == "c3d"


@settings(max_examples=300, **FUZZ)
@given(data=st.data())
def test_fuzz_read_markers_with_any_extension(sources, work, fuzz_counts, data):
    fmt = data.draw(st.sampled_from(["trc", "vicon", "csv", "tsv"]))
    keys = {"trc": TRC_KEYS, "vicon": ["Trajectories"], "csv": CSV_KEYS, "tsv": TSV_KEYS}[fmt]
    sep = b"," if fmt in ("vicon", "csv") else b"\t"
    raw = data.draw(cases(sources[fmt], keys, sep))
    path = work / f"case{data.draw(st.sampled_from(EXTENSIONS))}"
    path.write_bytes(raw)
    check(read_markers, path, fuzz_counts, "read_markers")


def test_fuzz_counts_reported(fuzz_counts):
    """Runs last in this module: every fuzzed reader tried cases, and each case was counted once."""
    expected = {"read_trc", "read_csv (Vicon)", "read_csv (columns)", "read_tsv", "read_c3d", "read_markers"}
    if not fuzz_counts:
        pytest.skip("no fuzz test ran in this session")
    assert set(fuzz_counts) == expected
    for c in fuzz_counts.values():
        assert c["tried"] > 0 and c["tried"] == c["valid"] + c["refused"]
    assert sum(c["tried"] for c in fuzz_counts.values()) > 0
