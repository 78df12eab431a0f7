"""Text readers on small hand-written files: layouts, encodings and one-line errors."""

from __future__ import annotations

import numpy as np
import pytest

from skelid.errors import FormatError, SkelidWarning
from skelid.io import read_csv, read_markers, read_trc, read_tsv, sniff_format

TRC = (
    "PathFileType\t4\t(X/Y/Z)\tx.trc\n"
    "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n"
    "{rate}\t{rate}\t99\t2\t{units}\n"
    "Frame#\tTime\t{a}\t\t\tB\n"
    "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\n"
    "\n"
    "1\t0\t1\t2\t3\t4\t5\t6\n"
    "2\t0.01\t{value}\t2\t3\t\t\t\n"
)


def trc(tmp_path, name="x.trc", *, rate="100", units="mm", a="A", value="1.5", encoding="utf-8"):
    path = tmp_path / name
    path.write_bytes(TRC.format(rate=rate, units=units, a=a, value=value).encode(encoding))
    return path


# --------------------------------------------------------------------- TRC
def test_trc_small(tmp_path):
    d = read_trc(trc(tmp_path))
    assert d.names == ("A", "B") and d.rate == 100 and d.units == "mm" and d.n_frames == 2
    np.testing.assert_array_equal(d.positions[1], [[1.5, 2, 3], [np.nan] * 3])


@pytest.mark.parametrize("encoding", ["utf-8-sig", "utf-16", "cp1252"])
def test_trc_encodings(tmp_path, encoding):
    d = read_markers(trc(tmp_path, a="Épaule", encoding=encoding))
    assert d.names[0] == "Épaule"


@pytest.mark.parametrize(("kw", "message"), [
    (dict(rate="abc"), "DataRate on line 3 should be a number"),
    (dict(rate="-60"), "must be a sampling rate between"),
    (dict(rate="inf"), "should be a finite number"),
    (dict(units="inch"), "gives units 'inch'"),
    (dict(value="1.2.3"), r"line 8, data column 1: '1.2.3' is not a number"),
    (dict(value="1e13"), "coordinates larger than 1e\\+12 mm"),
])
def test_trc_errors_name_the_file_and_the_problem(tmp_path, kw, message):
    path = trc(tmp_path, **kw)
    with pytest.raises(FormatError, match=message) as info:
        read_trc(path)
    assert str(info.value).startswith(str(path)) and "\n" not in str(info.value)


def test_trc_extra_coordinates_and_missing_rows(tmp_path):
    path = tmp_path / "extra.trc"
    path.write_text(TRC.format(rate=100, units="mm", a="A", value="1") + "3\t0.02\t1\t2\t3\t4\t5\t6\t7\n")
    with pytest.raises(FormatError, match="line 9 has 7 coordinates for 2 markers"):
        read_trc(path)
    path.write_text("".join(TRC.format(rate=100, units="mm", a="A", value="1").splitlines(True)[:6]))
    with pytest.raises(FormatError, match="no data rows"):
        read_trc(path)


# -------------------------------------------------------------- Vicon CSV
VICON = (
    "Devices\n100\n,,Plate:Fx\nFrame,Sub Frame,Fx\n,,N\n1,0,3.5\n\n"
    "Trajectories\n100\n,,Sub:A,,,Sub:B,,\nFrame,Sub Frame,X,Y,Z,X,Y,Z\n,,mm,mm,mm,mm,mm,mm\n"
    "1,0,1,2,3,4,5,6\n2,0,1,2,3,,,\n\n"
    "Model Outputs\n100\n,,Sub:LHipAngles,,\n"
)


def test_vicon_csv_finds_the_trajectories_section(tmp_path):
    path = tmp_path / "nexus.csv"
    path.write_text(VICON)
    assert sniff_format(path) == "vicon-csv"
    d = read_csv(path)
    assert d.names == ("Sub:A", "Sub:B") and d.n_frames == 2 and d.units == "mm"
    assert d.present.tolist() == [[True, True], [True, False]]


def test_vicon_csv_without_trajectories(tmp_path):
    path = tmp_path / "nexus.csv"
    path.write_text(VICON.split("Trajectories")[0])
    with pytest.raises(FormatError, match="without a 'Trajectories' section"):
        read_csv(path)


# ------------------------------------------------------------ column CSV
def test_column_csv_rate_from_time_and_units_from_header(tmp_path):
    path = tmp_path / "p.txt"
    path.write_text("time,A_X [mm],A_Y [mm],B_X [mm],B_Y [mm]\n0,1,2,3,4\n0.004,1,2,,\n0.008,0,0,0,0\n")
    d = read_markers(path)
    assert (d.rate, d.units, d.dim, d.names) == (250.0, "mm", 2, ("A", "B"))
    assert d.present.tolist() == [[True, True], [True, False], [True, True]]  # 0,0 is a position here


def test_column_csv_guesses_units_and_warns_on_uneven_time(tmp_path):
    path = tmp_path / "p.csv"
    path.write_text("t,A_x,A_y,A_z,B_x,B_y,B_z\n0,0,0,0,0.3,0,0\n0.01,0,0,0,0.3,0,0\n0.03,0,0,0,0.3,0,0\n"
                    "0.04,0,0,0,0.3,0,0\n")
    with pytest.warns(SkelidWarning) as record:
        d = read_csv(path)
    messages = " ".join(str(w.message) for w in record)
    assert "not uniform" in messages and "units guessed as 'm'" in messages
    assert d.units == "m" and d.rate == 100.0


@pytest.mark.parametrize(("text", "message"), [
    ("A_x,A_y\n1,2\n", "no sampling rate"),
    ("t,A_x,A_y\n0,1,2\n0,1,2\n", "line 3: time 0 does not increase"),
    ("t,A_x,A_y\n-1e308,1,2\n1e308,1,2\n", "time values too large"),
    ("t,A_x,A_y\n1e308,1,2\n-1e308,1,2\n", "does not increase"),
    ("t,A_x,A_y\n0,1e300,2\n1,1,2\n", "coordinates larger than 1e\\+12"),
    ("t,A_x (mm),A_y (m)\n0,1,2\n1,1,2\n", r"mixes units \['m', 'mm'\]"),
    ("t,A_x,B_y\n0,1,2\n1,1,2\n", "marker 'A' has columns X"),
    ("t,A_x,A_y,speed\n0,1,2,3\n", "'speed' is neither a time, a frame nor a coordinate"),
    ("t,t,A_x,A_y\n0,0,1,2\n", "a second 't' column"),
    ("t,A_x,A_y\n0,1,2,3\n", "line 2 has 4 fields but the header names 3 columns"),
    ("# a note\n\n", "no header line"),
    ("", "the file is empty"),
    ("Some prose,\nmore prose\n", "not a marker table"),
])
def test_column_csv_errors(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(FormatError, match=message) as info:
        read_csv(path)
    assert "\n" not in str(info.value)


# ---------------------------------------------------------------- Qualisys
QTM_OLD = (
    "NO_OF_FRAMES\t99\nNO_OF_MARKERS\t2\nFREQUENCY\t200\nDATA_INCLUDED\t3D\nMARKER_NAMES\tA\tB\n"
    "1.0\t2.0\t3.0\t0.000\t0.000\t0.000\n4\t5\t6\t7\t8\t9\n"
)


def test_qualisys_without_frame_line_and_zero_as_missing(tmp_path):
    path = tmp_path / "old.tsv"
    path.write_text(QTM_OLD)
    assert sniff_format(path) == "qualisys-tsv"
    d = read_tsv(path)
    assert (d.names, d.rate, d.units, d.n_frames) == (("A", "B"), 200.0, "mm", 2)
    assert d.present.tolist() == [[True, False], [True, True]]


def test_qualisys_6d_is_refused(tmp_path):
    path = tmp_path / "6d.tsv"
    path.write_text(QTM_OLD.replace("\t3D", "\t6D"))
    with pytest.raises(FormatError, match="only 3D marker data"):
        read_tsv(path)


def test_plain_tsv_is_read_as_columns(tmp_path):
    path = tmp_path / "plain.tsv"
    path.write_text("# rate=50 units=cm\nframe\tA_x\tA_y\tA_z\n1\t1\t2\t3\n")
    d = read_markers(path)
    assert (d.rate, d.units, d.names) == (50.0, "cm", ("A",))


# ------------------------------------------------ the time column, one check for every text reader
def _rows_with_times(fmt, times):
    """A file of format ``fmt`` with one marker and one row per time (data rows start on line 7 in each)."""
    if fmt == "trc":
        head = ("PathFileType\t4\t(X/Y/Z)\tx.trc\nDataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n"
                "100\t100\t9\t1\tmm\nFrame#\tTime\tA\t\t\n\t\tX1\tY1\tZ1\n\n")
        rows = "".join(f"{k + 1}\t{t}\t{k}.0\t1.0\t2.0\n" for k, t in enumerate(times))
    elif fmt == "csv":  # the comment gives the rate: the time column is checked all the same
        head = "# units=mm rate=100\n# a note\n# another\n# and one more\n# the header is next\ntime,A_x,A_y,A_z\n"
        rows = "".join(f"{t},{k}.0,1.0,2.0\n" for k, t in enumerate(times))
    else:
        head = ("NO_OF_FRAMES\t9\nNO_OF_MARKERS\t1\nFREQUENCY\t100\nDATA_INCLUDED\t3D\nMARKER_NAMES\tA\n"
                "Frame\tTime\tA X\tA Y\tA Z\n")
        rows = "".join(f"{k + 1}\t{t}\t{k}.0\t1.0\t2.0\n" for k, t in enumerate(times))
    return head + rows


@pytest.mark.parametrize("fmt", ["trc", "csv", "tsv"])
@pytest.mark.parametrize("times, message", [
    (["0.00", "0.01", "0.01", "0.03"], r"line 9: time 0.01 does not increase \(line 8 has 0.01\)"),  # repeated
    (["0.03", "0.02", "0.01"], r"line 8: time 0.02 does not increase \(line 7 has 0.03\)"),  # reversed
    (["0.00", "0.01", "0.02", "0.00", "0.01"], r"line 10: time 0 does not increase \(line 9 has 0.02\)"),  # pasted
    (["0.00", "0.01", "x"], "line 9: time 'x' is not a number"),
    (["0.00", "inf", "0.02"], "line 8: time 'inf' is not a finite number"),
    (["0.00", "", "0.02"], "line 8: the [Tt]ime field is empty while other rows have one"),
])
def test_every_text_reader_refuses_a_time_column_out_of_order(tmp_path, fmt, times, message):
    path = tmp_path / f"t.{fmt}"
    path.write_text(_rows_with_times(fmt, times))
    with pytest.raises(FormatError, match=message) as info:
        read_markers(path)
    assert "\n" not in str(info.value) and "(fix: " in str(info.value)


@pytest.mark.parametrize("fmt", ["trc", "csv", "tsv"])
def test_an_increasing_time_column_reads_in_every_text_reader(tmp_path, fmt):
    path = tmp_path / f"t.{fmt}"
    path.write_text(_rows_with_times(fmt, ["0.00", "0.01", "0.02"]))
    d = read_markers(path)
    assert (d.n_frames, d.rate) == (3, 100.0)
    np.testing.assert_array_equal(d.positions[:, 0, 0], [0.0, 1.0, 2.0])
