import numpy as np
import pytest

from skelid.data import MarkerData
from skelid.errors import DataError, FormatError
from skelid.io import read_markers, read_trc, write_trc


def test_trc_round_trip_with_gaps(tmp_path):
    rng = np.random.default_rng(0)
    pos = rng.normal(0, 300, size=(25, 4, 3))
    pos[3, 1] = np.nan
    d = MarkerData(pos, ("a", "b", "c", "d"), 120.0, "mm")
    write_trc(tmp_path / "x.trc", d)
    e = read_trc(tmp_path / "x.trc")
    assert e.names == d.names and e.rate == 120.0 and e.units == "mm"
    np.testing.assert_array_equal(e.positions, d.positions)


def test_planar_data_written_with_zero_z(tmp_path):
    d = MarkerData(np.ones((3, 2, 2)), ("a", "b"), 50.0, "m")
    write_trc(tmp_path / "p.trc", d)
    e = read_trc(tmp_path / "p.trc")
    assert e.dim == 3 and np.all(e.positions[..., 2] == 0) and e.units == "m"


def test_opensim_files(shared_data):
    walk = read_markers(shared_data / "opensim-subject01" / "subject01_walk1.trc")
    assert (walk.n_frames, walk.n_markers, walk.rate, walk.units) == (151, 41, 60.0, "mm")
    free = read_markers(shared_data / "opensim-subject01" / "walk_free_01.trc")
    assert free.n_frames == 73  # the header says 900
    blanks = read_markers(shared_data / "opensim-gaps" / "dataWithBlanksForMissingMarkers.trc")
    assert blanks.n_markers == 40 and 0.80 < np.isnan(blanks.positions[..., 0]).mean() < 0.82


def test_select_names_missing_markers():
    d = MarkerData(np.zeros((2, 2, 3)), ("Sub:A", "B"), 10.0)
    assert d.select(["A", "B"]).names == ("A", "B")
    with pytest.raises(DataError, match="marker\\(s\\) C required by the model"):
        d.select(["A", "C"])


def test_not_a_trc(tmp_path):
    p = tmp_path / "x.trc"
    p.write_text("hello\nworld\n")
    with pytest.raises(FormatError, match="PathFileType"):
        read_trc(p)


def _trc_with_times(path, times, sep="\t"):
    head = [f"PathFileType{sep}4{sep}(X/Y/Z){sep}x.trc",
            sep.join(["DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units"]),
            sep.join(["100", "100", str(len(times)), "1", "mm"]),
            sep.join(["Frame#", "Time", "A", "", ""]), sep.join(["", "", "X1", "Y1", "Z1"])]
    rows = [sep.join([str(k + 1), t, f"{k}.0", "1.0", "2.0"]) for k, t in enumerate(times)]
    path.write_text("\n".join(head + rows) + "\n")
    return path


@pytest.mark.parametrize("times, line, what", [
    (["0.00", "0.01", "0.01", "0.03"], 8, "does not increase"),      # a repeated row
    (["0.03", "0.02", "0.01", "0.00"], 7, "does not increase"),      # reversed
    (["0.00", "0.01", "0.02", "0.00", "0.01"], 9, "does not increase"),  # two takes pasted together
    (["0.00", "0.01", "x", "0.03"], 8, "is not a number"),
    (["0.00", "0.01", "nan", "0.03"], 8, "not a finite number"),
    (["0.00", "", "0.02", "0.03"], 7, "Time field is empty"),
])
def test_trc_time_column_is_checked(tmp_path, times, line, what):
    path = _trc_with_times(tmp_path / "t.trc", times)
    with pytest.raises(FormatError, match=f"line {line}: .*{what}"):
        read_trc(path)


def test_trc_without_times_or_with_increasing_times_reads(tmp_path):
    assert read_trc(_trc_with_times(tmp_path / "a.trc", ["", "", ""])).meta["time_step"] is None
    d = read_trc(_trc_with_times(tmp_path / "b.trc", ["0.00", "0.01", "0.02"]))
    assert d.n_frames == 3 and d.meta["time_step"] == pytest.approx(0.01)


def test_nul_character_in_utf16_text_is_refused(tmp_path):
    text = _trc_with_times(tmp_path / "a.trc", ["0.00", "0.01"]).read_text().replace("1.0", "1\x00.0", 1)
    (tmp_path / "u.trc").write_bytes(text.encode("utf-16"))
    with pytest.raises(FormatError, match="NUL character"):
        read_trc(tmp_path / "u.trc")


def test_nul_byte_in_a_utf8_cell_is_refused(tmp_path):
    text = _trc_with_times(tmp_path / "a.trc", ["0.00", "0.01"]).read_text().replace("1.0", "1\x00.0", 1)
    (tmp_path / "n.trc").write_bytes(text.encode("utf-8"))
    with pytest.raises(FormatError, match="binary content") as exc:
        read_trc(tmp_path / "n.trc")
    assert "\n" not in exc.value.one_line()
