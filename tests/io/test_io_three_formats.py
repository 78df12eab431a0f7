"""The pyomeca upper-limb trial in three formats: C3D, Vicon CSV and TRC.

The C3D (``markers_analogs.c3d``) and the Nexus CSV (``markers.csv``) hold the
same 580 frames of the same 51 markers in the same order; the CSV is written
with six significant digits, so they agree to a relative 5e-6 and have the
same gaps.

The TRC (``markers.trc``) does not hold frames of that recording. Its header
names another trial (``DapOF6H1_1.trc``, 652 frames originally, 93 rows kept)
and its numbers confirm it: after the best rigid alignment of the 43 body
markers, no C3D frame comes closer than 13 mm RMS to any TRC frame (file
precision is 1e-4 mm), the box sits about 0.7 m away from where it is in the
C3D at the best-matching frame, and the TRC's ``STERr`` column is a copy of
``STER``. What the three files do share is the subject, the marker set (the
TRC writes ``boite:x`` as ``boite_x`` and drops the ``Daphnee:`` prefix, in
another order), the rate, the units and the rigid box: its eight markers keep
the same distances, to within 1.5 mm, in every file.
"""

from __future__ import annotations

import numpy as np
import pytest

from skelid.io import read_markers


@pytest.fixture(scope="module")
def trial(data_dir):
    folder = data_dir / "pyomeca-upperlimb"
    return {ext: read_markers(folder / f"markers{suffix}")
            for ext, suffix in (("c3d", "_analogs.c3d"), ("csv", ".csv"), ("trc", ".trc"))}


def trc_name(name: str) -> str:
    """The TRC's spelling of a C3D/CSV marker name."""
    return name.replace("boite:", "boite_").replace("Daphnee:", "")


def test_c3d_and_csv_agree_on_all_frames(trial):
    c3d, csv = trial["c3d"], trial["csv"]
    assert c3d.names == csv.names
    assert (c3d.n_frames, c3d.rate, c3d.units) == (csv.n_frames, csv.rate, csv.units) == (580, 100.0, "mm")
    assert np.array_equal(c3d.present, csv.present)
    assert (~c3d.present).sum() == 305
    np.testing.assert_allclose(csv.positions, c3d.positions, rtol=5.0001e-6, atol=0, equal_nan=True)


def test_trc_has_the_same_markers_rate_and_units(trial):
    c3d, trc = trial["c3d"], trial["trc"]
    assert sorted(trc_name(n) for n in c3d.names) == sorted(trc.names)
    assert trc.names != tuple(trc_name(n) for n in c3d.names)  # another order
    assert (trc.rate, trc.units) == (c3d.rate, c3d.units)


def _box_distances(d, names):
    idx = [d.names.index(n) for n in names]
    p = d.positions[:, idx]
    dist = np.linalg.norm(p[:, :, None] - p[:, None, :], axis=-1)
    return np.nanmedian(dist, axis=0)


def test_the_rigid_box_is_the_same_in_all_three(trial):
    box = [n for n in trial["c3d"].names if n.startswith("boite:")]
    assert len(box) == 8
    ref = _box_distances(trial["c3d"], box)
    np.testing.assert_allclose(_box_distances(trial["csv"], box), ref, atol=1e-2)
    np.testing.assert_allclose(_box_distances(trial["trc"], [trc_name(n) for n in box]), ref, atol=1.5)


def _rigid_rms(a: np.ndarray, b: np.ndarray) -> float:
    """RMS distance between point sets (N, 3) after the best rotation and translation of ``a`` onto ``b``."""
    ok = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
    a, b = a[ok] - a[ok].mean(axis=0), b[ok] - b[ok].mean(axis=0)
    u, s, vt = np.linalg.svd(a.T @ b)
    s[-1] *= np.sign(np.linalg.det(u @ vt))
    return float(np.sqrt(max((a ** 2).sum() + (b ** 2).sum() - 2 * s.sum(), 0.0) / len(a)))


def test_trc_frames_belong_to_another_recording(trial):
    c3d, trc = trial["c3d"], trial["trc"]
    body = [n for n in c3d.names if n.startswith("Daphnee:")]
    c = c3d.select(body).positions
    t = trc.select([trc_name(n) for n in body]).positions
    best = min(_rigid_rms(t[k], c[j]) for k in (0, 46, 92) for j in range(c3d.n_frames))
    assert best > 10.0  # mm; the same recording would match to 1e-4 mm
    assert np.array_equal(t[:, body.index("Daphnee:STER")], t[:, body.index("Daphnee:STERr")])
    assert not np.array_equal(c[:, body.index("Daphnee:STER")], c[:, body.index("Daphnee:STERr")])
