"""Every marker file in ../shared/data is read as its README describes it."""

from __future__ import annotations

import numpy as np
import pytest

from skelid.data import MarkerData
from skelid.errors import FormatError, SkelidWarning
from skelid.io import read_c3d, read_csv, read_markers, read_trc, read_tsv, sniff_format

# path, reader, frames, markers (measured), rate, units, missing fraction (over measured markers)
MARKER_FILES = [
    ("opensim-subject01/subject01_static.trc", read_trc, 300, 49, 60, "mm", 0.0),
    ("opensim-subject01/subject01_walk1.trc", read_trc, 151, 41, 60, "mm", 0.0),
    ("opensim-subject01/walk_free_01.trc", read_trc, 73, 41, 60, "mm", 0.0),
    ("opensim-gaps/walking2.c3d", read_c3d, 1249, 38, 250, "mm", 0.4753),
    ("opensim-gaps/dataWithBlanksForMissingMarkers.trc", read_trc, 464, 40, 250, "mm", 0.8085),
    ("opensim-gaps/std_walking2_markers.trc", read_trc, 126, 44, 250, "mm", 0.5067),
    ("kineticstoolkit-tennis/kinematics_tennis_serve.c3d", read_c3d, 1092, 39, 50, "m", 0.0),
    ("kineticstoolkit-tennis/kinematics_tennis_serve_nan.c3d", read_c3d, 1092, 39, 50, "m", 0.0034),
    ("bmc-pendulum/3dPendulum.txt", read_csv, 300, 3, 100, "m", 0.0),
    ("pyomeca-upperlimb/markers_analogs.c3d", read_c3d, 580, 51, 100, "mm", 0.0103),
    ("pyomeca-upperlimb/markers.csv", read_csv, 580, 51, 100, "mm", 0.0103),
    ("pyomeca-upperlimb/markers.trc", read_trc, 93, 51, 100, "mm", 0.0),
    ("hand-fingers/recording.tsv", read_tsv, 6000, 21, 100, "mm", 0.0049),
    ("addbio-subject4/MarkerData/static1.trc", read_trc, 517, 55, 100, "m", 0.0),
    ("addbio-subject4/MarkerData/walking1.trc", read_trc, 131, 51, 100, "m", 0.0187),
    ("addbio-subject4/MarkerData/walking2.trc", read_trc, 132, 51, 100, "m", 0.0189),
    ("addbio-subject4/MarkerData/squats1.trc", read_trc, 1346, 51, 100, "m", 0.0),
    ("addbio-subject4/MarkerData/STS1.trc", read_trc, 1399, 51, 100, "m", 0.0),
    ("addbio-subject4/MarkerData/DJ1.trc", read_trc, 269, 51, 100, "m", 0.0003),
    # the C3D files also hold the lab software's computed points (bones, angles, moments): not markers
    ("ktk-gait-pig/static.c3d", read_c3d, 879, 42, 100, "m", 0.0236),
    ("ktk-gait-pig/gait.c3d", read_c3d, 474, 38, 100, "m", 0.0730),
]
pytestmark = pytest.mark.filterwarnings("ignore::skelid.errors.SkelidWarning")  # checked where expected
NOT_MARKER_FILES = ["LICENSE", "LICENSE.txt", "LICENSE.md", "NOTICE", "README.txt", ".xml", ".osim"]


@pytest.fixture(scope="module")
def read_all(data_dir):
    cache = {}

    def read(rel):
        if rel not in cache:
            cache[rel] = read_markers(data_dir / rel)
        return cache[rel]

    return read


@pytest.mark.parametrize(("rel", "reader", "frames", "markers", "rate", "units", "missing"), MARKER_FILES,
                         ids=[m[0].split("/")[-1] for m in MARKER_FILES])
def test_marker_file_matches_readme(read_all, data_dir, rel, reader, frames, markers, rate, units, missing):
    d = read_all(rel)
    assert isinstance(d, MarkerData)
    assert (d.n_frames, d.n_markers, d.dim) == (frames, markers, 3)
    assert d.rate == rate
    assert d.units == units
    assert 1 - d.present.mean() == pytest.approx(missing, abs=1e-4)
    assert d.source == str(data_dir / rel)
    direct = reader(data_dir / rel)
    np.testing.assert_array_equal(direct.positions, d.positions)
    assert direct.names == d.names


def test_every_file_in_the_data_folder_is_read_or_refused(data_dir):
    known = {m[0] for m in MARKER_FILES}
    seen = set()
    for path in sorted(p for p in data_dir.rglob("*") if p.is_file() and p.name != "README.md"):
        rel = path.relative_to(data_dir).as_posix()
        if rel in known:
            seen.add(rel)
            continue
        assert any(rel.endswith(s) for s in NOT_MARKER_FILES), f"unexpected file {rel}"
        assert sniff_format(path) is None
        with pytest.raises(FormatError) as info:
            read_markers(path)
        msg = str(info.value)
        assert "\n" not in msg and str(path) in msg
    assert seen == known


def test_trc_header_frame_counts_are_not_trusted(read_all):
    walk = read_all("opensim-subject01/walk_free_01.trc")
    assert walk.meta["header"]["NumFrames"] == "900" and walk.n_frames == 73
    upper = read_all("pyomeca-upperlimb/markers.trc")
    assert upper.meta["header"]["NumFrames"] == "652" and upper.n_frames == 93


def test_decimated_trc_keeps_its_data_rate_and_warns(data_dir):
    path = data_dir / "opensim-gaps" / "std_walking2_markers.trc"
    with pytest.warns(SkelidWarning, match="Time column advances 0.039936 s per row but DataRate says 250 Hz"):
        d = read_trc(path)
    assert d.rate == 250 and d.meta["time_step"] == pytest.approx(0.04, abs=1e-4)


def test_blank_fields_are_missing_markers(read_all):
    d = read_all("opensim-gaps/dataWithBlanksForMissingMarkers.trc")
    assert (~d.present).any(axis=0).all()  # every marker has gaps
    assert np.isnan(d.positions[~d.present]).all()


def test_tennis_nan_differs_from_tennis_only_by_rsho_gaps(read_all):
    full = read_all("kineticstoolkit-tennis/kinematics_tennis_serve.c3d")
    gaps = read_all("kineticstoolkit-tennis/kinematics_tennis_serve_nan.c3d")
    assert full.names == gaps.names
    i = gaps.names.index("Derrick:RSHO")
    missing = np.flatnonzero(~gaps.present[:, i])
    assert len(missing) == 145 and missing.min() == 134 and missing.max() == 927
    assert full.present.all()
    others = np.ones(gaps.n_markers, bool)
    others[i] = False
    assert np.array_equal(gaps.positions[:, others], full.positions[:, others])  # bit-identical
    kept = gaps.present[:, i]
    assert np.array_equal(gaps.positions[kept, i], full.positions[kept, i])


def test_walking2_joint_centres_are_kept_apart(read_all):
    d = read_all("opensim-gaps/walking2.c3d")
    jc = ["LAJC", "LHJC", "LKJC", "RAJC", "RHJC", "RKJC"]
    assert d.meta["computed_points"] == jc
    assert not set(jc) & set(d.names)
    assert d.n_markers + len(jc) == 44
    for name in jc:
        assert d.meta["computed"][name].shape == (1249, 3)
    everything = np.concatenate([d.positions, np.stack([d.meta["computed"][n] for n in jc], axis=1)], axis=1)
    assert 1 - np.isfinite(everything).all(axis=2).mean() == pytest.approx(0.5016, abs=1e-4)
    # modelled, not measured: the two hip centres sit in one rigid pelvis
    width = np.linalg.norm(d.meta["computed"]["LHJC"] - d.meta["computed"]["RHJC"], axis=1)
    width = width[np.isfinite(width)]
    assert width.size > 400 and np.ptp(width) < 1e-3


def test_pendulum_rod_length_is_half_a_metre(read_all):
    d = read_all("bmc-pendulum/3dPendulum.txt")
    assert d.names == ("m1", "m2", "m3")
    rod = np.linalg.norm(d.positions[:, 0] - d.positions[:, 1], axis=1)
    np.testing.assert_allclose(rod, 0.5, atol=1e-12)
    assert np.all(d.positions[:, 0] == 0.0) and d.present.all()  # the pivot at the origin is not "missing"


def test_qualisys_gaps(read_all):
    d = read_all("hand-fingers/recording.tsv")
    gaps = dict(zip(d.names, (~d.present).sum(axis=0), strict=True))
    assert (gaps["thumb_tip"], gaps["middle_tip"], gaps["ring_tip"]) == (493, 78, 42)
    assert sum(v > 0 for v in gaps.values()) == 3


def test_vicon_csv_keeps_subject_prefixes(read_all):
    d = read_all("pyomeca-upperlimb/markers.csv")
    assert d.names[0] == "boite:gauche_ext" and "Daphnee:ASISr" in d.names
    assert d.select(["ASISr"]).n_markers == 1


def test_plug_in_gait_bones_are_the_joint_centres(read_all):
    """What the Plug-in-Gait comparison relies on, checked on the file itself.

    The femur's origin is the knee centre (a fixed distance from the lateral knee
    marker), its proximal point the hip centre (the two hips a fixed distance
    apart, the pelvis origin midway), the tibia's origin the ankle centre (a fixed
    distance from the lateral malleolus marker), and the knee centre lies on the
    tibia's proximal axis; the tibia's own proximal point is not the knee centre.
    """
    from skelid.io import bone_points

    d = read_all("ktk-gait-pig/gait.c3d")
    assert "LNormalisedGRF" not in d.names  # a computed point, not a marker
    bones = bone_points(d)
    assert {"PEL", "LFE", "RFE", "LTI", "RTI", "LFO", "RFO"} <= set(bones)
    pos = {n: d.positions[:, i] for i, n in enumerate(d.names)}

    def spread(a, b):
        r = np.linalg.norm(a - b, axis=1)
        r = r[np.isfinite(r)]
        return float(np.ptp(r)), float(np.mean(r))

    for s in "LR":
        fe, ti = bones[f"{s}FE"], bones[f"{s}TI"]
        assert spread(pos[f"{s}KNE"], fe["origin"])[0] < 1e-4  # m
        assert spread(pos[f"{s}ANK"], ti["origin"])[0] < 1e-4
        axis = ti["proximal"] - ti["origin"]
        to_knee = fe["origin"] - ti["origin"]
        cos = np.sum(axis * to_knee, axis=1) / np.linalg.norm(axis, axis=1) / np.linalg.norm(to_knee, axis=1)
        assert np.all(cos > 1 - 1e-9)
        assert spread(fe["origin"], ti["proximal"])[1] > 0.01  # 18 mm: the tibia bone stops short of the knee
    ptp, width = spread(bones["LFE"]["proximal"], bones["RFE"]["proximal"])
    assert ptp < 1e-4 and 0.1 < width < 0.2
    mid = 0.5 * (bones["LFE"]["proximal"] + bones["RFE"]["proximal"])
    assert np.nanmax(np.linalg.norm(mid - bones["PEL"]["origin"], axis=1)) < 1e-4
