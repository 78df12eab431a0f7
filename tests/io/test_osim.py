"""OpenSim model import: forward kinematics against the opensim package, Jacobians, bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from skelid.errors import FormatError, ModelError, SkelidError
from skelid.io.osim import osim_parameters, read_osim, scales_held
from skelid.model import model_from_dict
from skelid.model.functions import CoordinateFunction
from skelid.model.kinematics import forward_kinematics, marker_jacobian, marker_positions
from tests.helpers import load_script, opensim_marker_gap

ROOT = Path(__file__).resolve().parents[2]
SUBJECT01 = "opensim-subject01"
MODELS = [
    (f"{SUBJECT01}/gait2354_simbody.osim", f"{SUBJECT01}/gait2354_Scale_MarkerSet.xml"),
    (f"{SUBJECT01}/std_subject01_simbody.osim", None),
    ("addbio-subject4/Models/unscaled_generic.osim", None),
    ("addbio-subject4/Models/manually_scaled.osim", None),
    ("addbio-subject4/Models/optimized_scale_and_markers.osim", None),
]


def _pose_names(model):
    return [c for s in model.segments for c in s.joint.coordinates]


@pytest.mark.parametrize("path,marker_set", MODELS, ids=[m[0].rsplit("/", 1)[-1] for m in MODELS])
def test_markers_equal_opensim_at_random_poses(shared_data, path, marker_set):
    osim = pytest.importorskip("opensim", reason="the opensim package is not installed (pip install opensim)")
    osim.Logger.removeFileSink()  # no opensim.log beside the shared models
    ms = None if marker_set is None else str(shared_data / marker_set)
    model, _ = read_osim(shared_data / path, ms)
    om = osim.Model(str(shared_data / path))
    if ms is not None:
        mset = osim.MarkerSet(ms)
        for i in range(mset.getSize()):
            om.addMarker(mset.get(i).clone())
    assert len(_pose_names(model)) == model.n_pose
    worst = opensim_marker_gap(model, om, np.random.default_rng(0), 100)
    assert worst <= 1e-6, f"largest marker difference {worst:.2e} mm"


@pytest.mark.parametrize("key", ["gait2354", "rajagopal"])
def test_scales_per_axis_of_every_body_equal_opensims_own_scaling(shared_data, key):
    """OpenSim's ``Model.scale`` with a factor per axis for every body, talus and ulna (no markers) too, as the
    OpenSim-truth benchmark makes its subjects, against skelid's parameters at those factors (the joint fit's,
    with the bodies that hold a marked one's joint): the same markers at random poses. The Rajagopal knee's
    joint frames are turned against the femur's, so its coupled translations are scaled by OpenSim's own rule
    (their axis in the joint frame . the factors)."""
    pytest.importorskip("opensim", reason="the opensim package is not installed (pip install opensim)")
    truth_study = load_script(ROOT / "benchmarks" / "opensim_truth.py", "opensim_truth_for_tests")
    setup = truth_study.use_model(key)
    rng = np.random.default_rng(11)
    base, info = read_osim(setup.generic, setup.marker_set)
    model = osim_parameters(base, info, "axes", "none", holders=True)
    assert {"talus_r", "talus_l"} <= {p.target for p in model.parameters}
    factors = {b: rng.uniform(0.85, 1.15, 3) for b in truth_study.scaled_bodies("every")}
    om = truth_study.subject({"scales": factors, "offsets": dict.fromkeys(base.marker_names, np.zeros(3))})
    theta = np.array([factors[p.target][p.axis] for p in model.parameters])
    worst = opensim_marker_gap(model, om, rng, 100, theta=theta)
    assert worst <= 1e-6, f"largest marker difference {worst:.2e} mm"


@pytest.mark.parametrize("path", [MODELS[0][0], MODELS[2][0]])
def test_bodies_scaled_into_the_geometry_put_every_marker_where_their_factors_do(shared_data, path):
    """A model with some bodies' factors written into its geometry (their parameters gone) against the model
    with those factors as parameters: the same markers at random poses. The femurs carry the knees' coupled
    translations; the tali and ulnas hold a marked body's joint and carry no marker."""
    base, info = read_osim(shared_data / path)
    model = osim_parameters(base, info, "axes", "offsets", holders=True)
    rng = np.random.default_rng(3)
    theta = np.array([rng.uniform(0.85, 1.15) if p.kind == "scale" else rng.normal(0.0, 10.0)
                      for p in model.parameters])
    held = {b for b in ("femur_r", "femur_l", "talus_r", "talus_l", "ulna_r", "ulna_l")
            if b in {p.target for p in model.parameters}}
    assert {"femur_r", "talus_r"} <= held
    factors = {b: np.array([theta[k] for k, p in enumerate(model.parameters) if p.kind == "scale" and p.target == b])
               for b in held}
    fixed = scales_held(model, factors)
    assert not {p.target for p in fixed.parameters if p.kind == "scale"} & held
    kept = [model.parameter_names.index(n) for n in fixed.parameter_names]
    lo, hi = np.array([[-1.0, 1.0]] * model.n_pose).T
    q = rng.uniform(lo, hi, (100, model.n_pose))
    gap = np.abs(marker_positions(fixed, theta[kept], q) - marker_positions(model, theta, q)).max()
    assert gap <= 1e-9, f"largest marker difference {gap:.2e} mm"
    assert np.abs(marker_positions(scales_held(model, {}), theta, q) - marker_positions(model, theta, q)).max() == 0


def test_welded_toes_with_markers_equal_opensim(shared_data, tmp_path):
    """gait2354 with its mtp joints replaced by WeldJoints and a marker on each toe."""
    osim = pytest.importorskip("opensim", reason="the opensim package is not installed (pip install opensim)")
    osim.Logger.removeFileSink()
    om = osim.Model(str(shared_data / MODELS[0][0]))
    mset = osim.MarkerSet(str(shared_data / MODELS[0][1]))
    for i in range(mset.getSize()):
        om.addMarker(mset.get(i).clone())
    om.initSystem()
    for side, z in (("r", 0.02), ("l", -0.02)):
        mtp = om.getJointSet().get(f"mtp_{side}")
        pf = osim.PhysicalOffsetFrame.safeDownCast(mtp.getParentFrame())
        cf = osim.PhysicalOffsetFrame.safeDownCast(mtp.getChildFrame())
        toes = om.getBodySet().get(f"toes_{side}")
        weld = osim.WeldJoint(f"mtp_{side}", om.getBodySet().get(f"calcn_{side}"), pf.get_translation(),
                              pf.get_orientation(), toes, cf.get_translation(), cf.get_orientation())
        om.updJointSet().remove(mtp)
        om.addJoint(weld)
        om.addMarker(osim.Marker(f"toe_{side}", toes, osim.Vec3(0.05, 0.01, z)))
    om.finalizeConnections()
    path = tmp_path / "welded_toes.osim"
    om.printToXML(str(path))
    model, _ = read_osim(path)
    assert {"toes_r", "toes_l"} <= {s.name for s in model.segments}
    assert {s.joint.name: s.joint.coordinates for s in model.segments}["mtp_r"] == ()
    worst = opensim_marker_gap(model, osim.Model(str(path)), np.random.default_rng(3), 100)
    assert worst <= 1e-6, f"largest marker difference {worst:.2e} mm"


@pytest.fixture
def gait_model(shared_data):
    model, info = read_osim(shared_data / MODELS[0][0], shared_data / MODELS[0][1])
    return osim_parameters(model, info, scale="axes", markers="offsets"), info


def test_jacobians_equal_finite_differences(gait_model):
    model, _ = gait_model
    rng = np.random.default_rng(1)
    theta = model.theta_nominal + rng.normal(0, 0.05, model.n_params)
    q = rng.uniform(-0.6, 0.3, model.n_pose)
    x, Jq, Jt = marker_jacobian(model, theta, q)
    h = 1e-6
    for k in range(model.n_pose):
        e = np.zeros(model.n_pose)
        e[k] = h
        fd = (marker_positions(model, theta, q + e) - marker_positions(model, theta, q - e)) / (2 * h)
        np.testing.assert_allclose(Jq[..., k], fd, atol=1e-5 * (1 + np.abs(fd).max()), err_msg=f"pose {k}")
    for k in range(model.n_params):
        e = np.zeros(model.n_params)
        e[k] = h
        fd = (marker_positions(model, theta + e, q) - marker_positions(model, theta - e, q)) / (2 * h)
        np.testing.assert_allclose(Jt[..., k], fd, atol=1e-5 * (1 + np.abs(fd).max()),
                                   err_msg=model.parameters[k].name)


def test_scaling_a_body_scales_its_markers_and_the_knee_translation(gait_model):
    model, _ = gait_model
    theta = model.theta_nominal.copy()
    names = model.parameter_names
    q = np.zeros(model.n_pose)
    x0 = marker_positions(model, theta, q)
    for a in "xyz":
        theta[names.index(f"scale_femur_r_{a}")] = 1.1
    kin0 = forward_kinematics(model, model.theta_nominal, q)
    kin1 = forward_kinematics(model, theta, q)
    s = {n: i for i, n in enumerate(s.name for s in model.segments)}
    hip, knee = s["femur_r"], s["tibia_r"]
    # the knee centre moves 10 % further from the hip (femur frame = its joint's frame at q = 0 here)
    np.testing.assert_allclose(kin1.p_world_seg[knee] - kin1.p_world_seg[hip],
                               1.1 * (kin0.p_world_seg[knee] - kin0.p_world_seg[hip]), atol=1e-9)
    x1 = marker_positions(model, theta, q)
    moved = np.abs(x1 - x0).max(axis=1) > 1e-9
    on = {m.segment for m, mv in zip(model.markers, moved, strict=True) if mv}
    assert on <= {"femur_r", "tibia_r", "talus_r", "calcn_r", "toes_r"} and "femur_r" in on


def test_model_round_trips_through_its_dict(gait_model):
    model, _ = gait_model
    back = model_from_dict(model.to_dict())
    rng = np.random.default_rng(2)
    theta = model.theta_nominal + rng.normal(0, 0.02, model.n_params)
    q = rng.uniform(-0.5, 0.5, (3, model.n_pose))
    np.testing.assert_allclose(marker_positions(back, theta, q), marker_positions(model, theta, q), atol=1e-9)


def test_splines():
    scipy = pytest.importorskip("scipy.interpolate")
    x = np.array([-2.0, -1.2, -0.5, 0.1, 0.9, 2.0])
    y = np.sin(x) + 0.1 * x**2
    q = np.linspace(-1.99, 1.99, 57)
    nat = CoordinateFunction("spline", (), tuple(x), tuple(y), "natural")
    ref = scipy.CubicSpline(x, y, bc_type="natural")
    v, d = nat.value_and_derivative(q)
    np.testing.assert_allclose(v, ref(q), atol=1e-12)
    np.testing.assert_allclose(d, ref(q, 1), atol=1e-12)
    cubic = CoordinateFunction("spline", (), tuple(x), tuple(x**3 - x), "fmm")  # reproduces a cubic
    v, d = cubic.value_and_derivative(q)
    np.testing.assert_allclose(v, q**3 - q, atol=1e-10)
    np.testing.assert_allclose(d, 3 * q**2 - 1, atol=1e-9)
    poly = CoordinateFunction("polynomial", (2.0, -1.0, 0.5))
    np.testing.assert_allclose(poly.value_and_derivative(q)[1], 4 * q - 1.0)


OSIM_HEAD = """<?xml version="1.0" encoding="UTF-8" ?>
<OpenSimDocument Version="40000"><Model name="m"><length_units>{units}</length_units>
<BodySet><objects><Body name="a"/><Body name="b"/></objects></BodySet>
<JointSet><objects>
<FreeJoint name="j0"><socket_parent_frame>/ground</socket_parent_frame>
<socket_child_frame>/bodyset/a</socket_child_frame>
<coordinates><Coordinate name="r1"/><Coordinate name="r2"/><Coordinate name="r3"/>
<Coordinate name="t1"/><Coordinate name="t2"/><Coordinate name="t3"/></coordinates></FreeJoint>
<{joint} name="j1"><socket_parent_frame>/bodyset/a</socket_parent_frame>
<socket_child_frame>/bodyset/b</socket_child_frame>
<coordinates><Coordinate name="k"/></coordinates></{joint}>
</objects></JointSet>
<MarkerSet><objects>
<Marker name="m1"><socket_parent_frame>/bodyset/{body}</socket_parent_frame><location>0 0.1 0</location></Marker>
<Marker name="m2"><socket_parent_frame>/bodyset/a</socket_parent_frame><location>0.1 0 0</location></Marker>
</objects></MarkerSet></Model></OpenSimDocument>"""


def _write(tmp_path, units="meters", joint="PinJoint", body="b", text=None):
    p = tmp_path / "m.osim"
    p.write_text(text if text is not None else OSIM_HEAD.format(units=units, joint=joint, body=body))
    return p


def test_a_small_model_reads(tmp_path):
    model, _ = read_osim(_write(tmp_path))
    assert [s.name for s in model.segments] == ["a", "b"]
    assert model.n_pose == 7
    np.testing.assert_allclose(marker_positions(model, np.zeros(0), np.zeros(7))[0], [0, 100, 0])


@pytest.mark.parametrize("kw,err,words", [
    ({"text": "<OpenSimDocument><Model"}, FormatError, "malformed XML"),
    ({"joint": "ConstantCurvatureJoint"}, ModelError, "ConstantCurvatureJoint"),
    ({"body": "nowhere"}, ModelError, "nowhere"),
    ({"units": "millimeters"}, ModelError, "length_units"),
])
def test_bad_osim_is_one_line(tmp_path, kw, err, words):
    with pytest.raises(err) as exc:
        read_osim(_write(tmp_path, **kw))
    line = exc.value.one_line()
    assert words in line and "fix:" in line and "\n" not in line
    assert isinstance(exc.value, SkelidError)


# A 2.x / 3.x file (gait2354 is version 20302) keeps its joint frames as location_in_parent etc., which
# OpenSim (and so skelid) reads with six significant digits: read back, the scaled frames move by up to
# 5e-7 of their size (5e-5 mm at 100 mm). A 4.x file is read back as written.
@pytest.mark.parametrize("path,marker_set,read_back_mm", [(*MODELS[0], 1e-3), (*MODELS[2], 1e-6)],
                         ids=["gait2354", "addbio-generic"])
def test_written_scaled_model_equals_skelid_in_opensim(shared_data, tmp_path, path, marker_set, read_back_mm):
    """Scales and offsets written back: OpenSim's markers on the written .osim equal skelid's."""
    osim = pytest.importorskip("opensim", reason="the opensim package is not installed (pip install opensim)")
    osim.Logger.removeFileSink()  # no opensim.log beside the shared models
    from skelid.io.osim import write_scale_set, write_scaled_osim

    ms = None if marker_set is None else shared_data / marker_set
    base, info = read_osim(shared_data / path, ms)
    model = osim_parameters(base, info, scale="axes", markers="offsets")
    rng = np.random.default_rng(4)
    theta = model.theta_nominal.copy()
    for k, p in enumerate(model.parameters):
        theta[k] = rng.uniform(0.85, 1.2) if p.kind == "scale" else rng.normal(0, 8.0)
    out = tmp_path / "scaled.osim"
    write_scaled_osim(shared_data / path, out, model, info, theta, ms)
    write_scale_set(tmp_path / "scales.xml", model, theta)
    assert osim.ScaleSet(str(tmp_path / "scales.xml")).getSize() == len({p.target for p in model.parameters
                                                                          if p.kind == "scale"})
    om = osim.Model(str(out))
    state = om.initSystem()
    coords = om.getCoordinateSet()
    names = _pose_names(model)
    worst = 0.0
    for _ in range(10):
        q = np.zeros(model.n_pose)
        for k, n in enumerate(names):
            c = coords.get(n)
            v = rng.uniform(max(c.getRangeMin(), -np.pi), min(c.getRangeMax(), np.pi))
            c.setValue(state, v, False)
            q[k] = v * (1000.0 if c.getMotionType() == 2 else 1.0)
        om.realizePosition(state)
        x = marker_positions(model, theta, q)
        ref = np.array([[om.getMarkerSet().get(m.name).getLocationInGround(state).get(i) for i in range(3)]
                        for m in model.markers]) * 1000.0
        worst = max(worst, float(np.abs(x - ref).max()))
    assert worst <= 0.01, f"largest marker difference {worst:.2e} mm"
    # and read back by skelid itself, the unscaled geometry of the written file is the scaled one
    again, _ = read_osim(out)
    q = np.zeros(model.n_pose)
    np.testing.assert_allclose(marker_positions(again, np.zeros(0), q), marker_positions(model, theta, q),
                               atol=read_back_mm)


CREDITS = "<!-- after Delp S.L., “Müller” – 1990 -->\n<credits>Zajac F.E., Müller</credits>\n"


@pytest.mark.parametrize("declaration,codec", [
    ('<?xml version="1.0" encoding="UTF-8" ?>', "cp1252"),  # claims UTF-8, holds Windows-1252 bytes
    ("", "cp1252"),  # no declaration
    ('<?xml version="1.0" encoding="UTF-8" ?>', "latin-1"),
    ('<?xml version="1.0" encoding="windows-1252"?>', "cp1252"),
    ("<?xml version='1.0' encoding='ISO-8859-1'?>", "latin-1"),
    ('<?xml version="1.0" encoding="UTF-16"?>', "utf-16"),
    ('<?xml version="1.0" encoding="UTF-8" ?>', "utf-8"),
], ids=["utf8-claimed-cp1252", "undeclared-cp1252", "utf8-claimed-latin1", "cp1252", "latin1", "utf16", "utf8"])
def test_osim_in_every_encoding_reads(tmp_path, declaration, codec):
    plain = OSIM_HEAD.format(units="meters", joint="PinJoint", body="b")
    text = plain.split("\n", 1)[1].replace('<Model name="m">', '<Model name="m">' + CREDITS, 1)
    credits = CREDITS if codec != "latin-1" else CREDITS.replace("“", '"').replace("”", '"').replace("–", "-")
    text = text.replace(CREDITS, credits)
    path = tmp_path / "enc.osim"
    path.write_bytes(((declaration + "\n") if declaration else "").encode(codec) + text.encode(codec)
                     if codec != "utf-16" else (declaration + "\n" + text).encode("utf-16"))
    if codec in ("cp1252", "latin-1") and "UTF-8" in declaration:
        with pytest.raises(UnicodeDecodeError):
            path.read_bytes().decode("utf-8")  # the case this test is about: not valid UTF-8
    model, _ = read_osim(path)
    ref, _ = read_osim(_write(tmp_path))
    assert model == ref


def test_decoding_keeps_utf8_and_reads_stray_bytes_as_cp1252():
    from skelid.io._xml import decode_xml

    data = '<a>Müller '.encode() + b"\x93q\x94 \x81" + b"</a>"
    assert decode_xml(data) == "<a>Müller “q” \x81</a>"
    with pytest.raises(FormatError) as exc:
        decode_xml(b'<?xml version="1.0" encoding="klingon-8"?><a/>', "x.osim")
    assert "klingon-8" in exc.value.one_line() and "fix:" in exc.value.one_line()


def test_a_model_of_more_markers_than_skelid_reads_is_refused_before_reading_them(tmp_path):
    """2000 markers read; one more is refused in one line naming the count, before any marker is parsed
    (a model of 160 000 markers costs its XML's parse, about a second)."""
    from skelid.io.osim import MAX_MARKERS

    def model_with(n):
        many = "".join(f'<Marker name="x{k}"><socket_parent_frame>/bodyset/a</socket_parent_frame>'
                       f'<location>0 0 {k * 1e-5}</location></Marker>' for k in range(n))
        return _write(tmp_path, text=OSIM_HEAD.format(units="meters", joint="PinJoint", body="b").replace(
            "</objects></MarkerSet>", many + "</objects></MarkerSet>"))

    model, _ = read_osim(model_with(MAX_MARKERS - 2))
    assert len(model.marker_names) == MAX_MARKERS
    with pytest.raises(ModelError, match=f"has {MAX_MARKERS + 1} markers, more than the {MAX_MARKERS}") as exc:
        read_osim(model_with(MAX_MARKERS - 1))
    assert "\n" not in exc.value.one_line()
    with pytest.raises(ModelError, match="has 160002 markers"):
        read_osim(model_with(160_000))
