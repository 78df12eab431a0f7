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
