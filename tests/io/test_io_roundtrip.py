"""Writers and readers are inverse: write_trc/read_trc and write_csv/read_csv."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from skelid.data import MarkerData
from skelid.errors import DataError
from skelid.io import read_csv, read_markers, read_trc, write_csv, write_trc

NAME = st.from_regex(r"[A-Za-z][A-Za-z0-9_.:]{0,11}", fullmatch=True)


@st.composite
def marker_data(draw):
    F = draw(st.integers(1, 12))
    names = draw(st.lists(NAME, min_size=1, max_size=5, unique=True))
    D = draw(st.sampled_from([2, 3]))
    values = st.floats(-1e9, 1e9, allow_nan=False, allow_infinity=False)
    pos = draw(hnp.arrays(float, (F, len(names), D), elements=values))
    holes = draw(hnp.arrays(bool, (F, len(names), D)))
    pos[holes & (draw(st.booleans()))] = np.nan  # about half the cases have gaps
    rate = draw(st.floats(0.5, 20000.0, allow_nan=False) | st.sampled_from([50.0, 60.0, 100.0, 250.0]))
    units = draw(st.sampled_from(["mm", "cm", "m"]))
    return MarkerData(pos, tuple(names), rate, units)


def assert_same(a: MarkerData, b: MarkerData):
    assert a.names == b.names and a.rate == b.rate and a.units == b.units
    np.testing.assert_array_equal(a.positions, b.positions)  # NaN where NaN, bit-equal elsewhere


@settings(derandomize=True, max_examples=60, deadline=None, database=None)
@given(data=marker_data())
def test_csv_round_trip(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("csv") / "data.csv"
    write_csv(path, data)
    assert_same(read_csv(path), data)
    assert_same(read_markers(path), data)


@settings(derandomize=True, max_examples=60, deadline=None, database=None)
@given(data=marker_data())
def test_trc_round_trip(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("trc") / "data.trc"
    write_trc(path, data)
    back = read_trc(path)
    assert back.dim == 3
    if data.dim == 2:  # TRC is 3-D: planar data come back with Z = 0 where the marker is present
        z = back.positions[..., 2]
        np.testing.assert_array_equal(z[data.present], 0.0)
        assert np.isnan(z[~data.present]).all()
        back = back.replace(positions=back.positions[..., :2])
    assert_same(back, data)


@pytest.mark.parametrize(("writer", "name"), [
    (write_csv, "a,b"), (write_trc, "a\tb"),
    (write_csv, " padded"), (write_trc, "padded "),
    (write_csv, "line\nbreak"), (write_trc, "line\rbreak"),
])
def test_writers_refuse_names_the_format_cannot_hold(tmp_path, writer, name):
    data = MarkerData(np.zeros((1, 1, 3)), (name,), 100.0)
    with pytest.raises(DataError, match="cannot be written"):
        writer(tmp_path / "x.out", data)
    assert not list(tmp_path.iterdir())  # atomic: nothing left behind
