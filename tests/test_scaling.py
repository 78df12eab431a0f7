"""Scaling an OpenSim model: noise-free data from a scaled model give back its scales and offsets."""

from __future__ import annotations

import json

import numpy as np
import pytest

from skelid.data import MarkerData
from skelid.errors import DataError
from skelid.io.osim import osim_parameters, read_osim
from skelid.model.kinematics import marker_positions
from skelid.scaling import PLACED_OFFSET_SD, fit_osim, join_trials, write_outputs

MODEL = """<?xml version="1.0" encoding="UTF-8" ?>
<OpenSimDocument Version="40000"><Model name="leg"><length_units>meters</length_units>
<BodySet><objects><Body name="pelvis"/><Body name="thigh"/><Body name="shank"/></objects></BodySet>
<JointSet><objects>
<FreeJoint name="root"><socket_parent_frame>/ground</socket_parent_frame>
<socket_child_frame>/bodyset/pelvis</socket_child_frame>
<coordinates><Coordinate name="rx"/><Coordinate name="ry"/><Coordinate name="rz"/>
<Coordinate name="tx"/><Coordinate name="ty"/><Coordinate name="tz"/></coordinates></FreeJoint>
<BallJoint name="hip"><socket_parent_frame>pelvis_offset</socket_parent_frame>
<socket_child_frame>/bodyset/thigh</socket_child_frame>
<coordinates><Coordinate name="h1"/><Coordinate name="h2"/><Coordinate name="h3"/></coordinates>
<frames><PhysicalOffsetFrame name="pelvis_offset"><socket_parent>/bodyset/pelvis</socket_parent>
<translation>0.05 -0.08 0.09</translation><orientation>0.1 0 0.2</orientation></PhysicalOffsetFrame></frames>
</BallJoint>
<CustomJoint name="knee"><socket_parent_frame>/bodyset/thigh</socket_parent_frame>
<socket_child_frame>/bodyset/shank</socket_child_frame>
<coordinates><Coordinate name="k"><range>-2 0.2</range></Coordinate></coordinates>
<SpatialTransform>
<TransformAxis name="rotation1"><coordinates>k</coordinates><axis>0 0 1</axis>
<LinearFunction name="function"><coefficients>1 0</coefficients></LinearFunction></TransformAxis>
<TransformAxis name="translation1"><coordinates>k</coordinates><axis>1 0 0</axis>
<SimmSpline name="function"><x>-2 -1 0 0.5</x><y>-0.004 0.003 -0.002 -0.005</y></SimmSpline></TransformAxis>
<TransformAxis name="translation2"><coordinates>k</coordinates><axis>0 1 0</axis>
<SimmSpline name="function"><x>-2 -1 0 0.5</x><y>-0.42 -0.41 -0.40 -0.398</y></SimmSpline></TransformAxis>
</SpatialTransform></CustomJoint>
</objects></JointSet>
<MarkerSet><objects>
{markers}
</objects></MarkerSet></Model></OpenSimDocument>"""

MARKERS = {"pelvis": [(0.1, 0.05, 0.1), (0.1, 0.05, -0.1), (-0.1, 0.06, 0.0), (0.0, 0.1, 0.05)],
           "thigh": [(0.03, -0.1, 0.05), (0.04, -0.25, 0.06), (-0.03, -0.2, 0.05), (0.0, -0.38, 0.05)],
           "shank": [(0.03, -0.1, 0.04), (0.04, -0.25, 0.05), (-0.03, -0.2, 0.05), (0.0, -0.38, 0.04)]}


def marker_xml(markers=MARKERS) -> str:
    """The MarkerSet entries of the leg model's markers."""
    return "\n".join(f'<Marker name="{b}{i}"><socket_parent_frame>/bodyset/{b}</socket_parent_frame>'
                     f'<location>{x} {y} {z}</location></Marker>'
                     for b, locs in markers.items() for i, (x, y, z) in enumerate(locs))


@pytest.fixture
def leg(tmp_path):
    p = tmp_path / "leg.osim"
    p.write_text(MODEL.format(markers=marker_xml()))
    return p


def _trials(path, scales, offsets=None, frames=(8, 40)):
    base, info = read_osim(path)
    model = osim_parameters(base, info, "bodies", "offsets")
    theta = model.theta_nominal.copy()
    for k, p in enumerate(model.parameters):
        if p.kind == "scale":
            theta[k] = scales[p.target]
        elif offsets and p.target in offsets:
            theta[k] = offsets[p.target][p.axis]
    t = np.arange(frames[1]) / 60.0
    q = np.zeros((frames[1], model.n_pose))
    q[:, 3:6] = [100.0, 900.0, 50.0]
    q[:, 3] += 400 * t
    q[:, 6] = 0.5 * np.sin(2 * np.pi * 1.1 * t)
    q[:, 7] = 0.3 * np.sin(2 * np.pi * 0.7 * t + 1)
    q[:, 8] = 0.3 * np.sin(2 * np.pi * 0.9 * t + 2)
    q[:, 9] = -0.9 + 0.8 * np.sin(2 * np.pi * 1.3 * t)
    q[:, 0] = 0.2 * np.sin(2 * np.pi * 0.5 * t)
    static = np.zeros((frames[0], model.n_pose))
    static[:, 3:6] = [0.0, 900.0, 0.0]
    rng = np.random.default_rng(0)
    mk = []
    for qq in (static, q):
        x = marker_positions(model, theta, qq) + rng.normal(0, 0.01, (len(qq), len(model.markers), 3))
        mk.append(MarkerData(x, model.marker_names, 60.0, "mm", "sim"))
    return mk


def test_noise_free_scales_are_recovered(leg, tmp_path):
    truth = {"pelvis": 1.08, "thigh": 1.12, "shank": 0.93}
    trials = _trials(leg, truth)
    fit = fit_osim(leg, trials, scale="bodies", markers="none")
    got = {p.target: fit.theta[k] for k, p in enumerate(fit.model.parameters)}
    for b, v in truth.items():
        assert got[b] == pytest.approx(v, abs=2e-4), b
    paths = write_outputs(fit, tmp_path / "out")
    table = json.loads(paths["json"].read_text())
    assert table["scales"]["thigh"]["xyz"]["ci95"][0] <= 1.12 <= table["scales"]["thigh"]["xyz"]["ci95"][1] + 1e-3
    again, _ = read_osim(paths["osim"])  # the written model carries the scales
    s_again, _ = read_osim(leg)
    f_again = again.segments[2].joint.motions[2].function.scale
    assert f_again == pytest.approx(1.12 * s_again.segments[2].joint.motions[2].function.scale, rel=1e-4)


def test_placed_offsets_recover_moved_markers_up_to_each_bodys_pose(leg):
    """Offsets of every marker of a body trade with the body's pose, so placement can only recover the
    markers' configuration on each body: the distances between them."""
    from skelid.model.kinematics import geometry

    truth = {"pelvis": 1.0, "thigh": 1.0, "shank": 1.0}
    moved = {"thigh1": (6.0, -4.0, 3.0), "shank3": (-5.0, 2.0, 4.0), "pelvis0": (0.0, 3.0, -2.0)}
    trials = _trials(leg, truth, moved)
    fit = fit_osim(leg, trials, scale="none", markers="offsets")
    model = fit.model
    S, M = len(model.segments), len(model.markers)
    placed = geometry(model, fit.theta)[S * 3:(S + M) * 3].reshape(M, 3)
    true = np.array(placed)
    for i, m in enumerate(model.markers):
        true[i] = np.asarray(m.position) + np.asarray(moved.get(m.name, (0.0, 0.0, 0.0)))
    moved_any = False
    def dist(r, idx):
        return np.linalg.norm(r[idx][:, None] - r[idx][None], axis=-1)

    nominal = np.array([m.position for m in model.markers])
    for b in MARKERS:
        idx = [i for i, m in enumerate(model.markers) if m.segment == b]
        np.testing.assert_allclose(dist(placed, idx), dist(true, idx), atol=0.05)
        moved_any |= np.abs(dist(placed, idx) - dist(nominal, idx)).max() > 1.0
    assert moved_any


def test_trials_join_with_a_gap_and_markers_are_united():
    a = MarkerData(np.ones((4, 2, 3)), ("m1", "m2"), 100.0, "m")
    b = MarkerData(np.ones((3, 2, 3)), ("m2", "m3"), 100.0, "mm")
    j = join_trials([a, b], gap=5)
    assert j.names == ("m1", "m2", "m3") and j.positions.shape == (12, 3, 3)
    assert np.all(j.positions[:4, 0] == 1000.0) and np.isnan(j.positions[4:9]).all()
    assert np.isnan(j.positions[9:, 0]).all() and j.meta["trial_frames"] == [(0, 4), (9, 12)]
    with pytest.raises(DataError):
        join_trials([a, MarkerData(np.ones((3, 2, 3)), ("m2", "m3"), 50.0, "mm")])


def test_no_model_marker_in_the_data_is_one_line(leg):
    other = MarkerData(np.ones((5, 2, 3)), ("X", "Y"), 60.0, "mm")
    with pytest.raises(DataError, match="none of the 12 markers"):
        fit_osim(leg, [other])


def test_cli_fit_osim_writes_the_scaled_model(leg, tmp_path, capsys):
    from skelid.cli import main
    from skelid.io import write_trc

    static, move = _trials(leg, {"pelvis": 1.0, "thigh": 1.1, "shank": 1.0})
    write_trc(tmp_path / "static.trc", static)
    write_trc(tmp_path / "move.trc", move)
    out = tmp_path / "fit"
    rc = main(["fit", str(leg), str(tmp_path / "static.trc"), str(tmp_path / "move.trc"), "--out", str(out),
               "--json", "--quiet"])
    assert rc == 0
    table = json.loads(capsys.readouterr().out)
    thigh = table["scales"]["thigh"]  # three factors (the default): the long axis's is exact, the others covered
    assert thigh["y"]["value"] == pytest.approx(1.1, abs=1e-3)
    assert all(thigh[a]["ci95"][0] < 1.1 < thigh[a]["ci95"][1] for a in "xz")
    assert {p.name for p in out.iterdir()} >= {"scaled.osim", "scaled_scale_set.xml", "scaled_scaling.json",
                                               "result.json", "arrays.npz"}
    from skelid.io.results import read_run

    run = read_run(out)
    assert run.context["scaling"]["scales"]["thigh"]["y"]["value"] == pytest.approx(1.1, abs=1e-3)
    assert run.results["marker"].parameters  # the scale and offset estimates, typed


@pytest.mark.parametrize("text,words", [
    ("<OpenSimDocument><Model", "malformed XML"),
    (MODEL.replace("BallJoint", "ConstantCurvatureJoint").format(markers=""), "ConstantCurvatureJoint"),
    (MODEL.format(markers='<Marker name="x"><socket_parent_frame>/bodyset/arm</socket_parent_frame>'
                          '<location>0 0 0</location></Marker>'), "arm"),
])
def test_cli_bad_osim_exits_2_with_one_line(tmp_path, capsys, text, words):
    from skelid.cli import main

    bad = tmp_path / "bad.osim"
    bad.write_text(text)
    trc = tmp_path / "t.trc"
    from skelid.io import write_trc

    write_trc(trc, MarkerData(np.ones((3, 1, 3)), ("x",), 60.0, "mm"))
    for argv in (["fit", str(bad), str(trc), "--out", str(tmp_path / "o")],
                 ["model", "import", str(bad), "--out", str(tmp_path / "m.toml")]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert words in err and len(err.splitlines()) == 1
        assert not (tmp_path / "o").exists() and not (tmp_path / "m.toml").exists()


def test_cli_model_import_writes_a_model_that_loads(leg, tmp_path):
    from skelid.cli import main
    from skelid.model import load_model

    out = tmp_path / "leg.toml"
    assert main(["model", "import", str(leg), "--out", str(out), "--scale", "bodies"]) == 0
    model = load_model(out)
    base, _ = read_osim(leg)
    q = np.linspace(-0.5, 0.3, base.n_pose)
    np.testing.assert_allclose(marker_positions(model, model.theta_nominal, q),
                               marker_positions(base, np.zeros(0), q), atol=1e-9)


def test_marker_set_is_found_beside_the_model(shared_data):
    from skelid.io.osim import find_marker_set

    path = shared_data / "opensim-subject01" / "gait2354_simbody.osim"
    ms, how = find_marker_set(path)
    assert ms.name == "gait2354_Scale_MarkerSet.xml" and "subject01_Setup_Scale.xml" in how
    model, info = read_osim(path)
    assert len(model.markers) == 39 and info.marker_set == str(ms)


def test_a_lone_marker_set_file_is_taken_two_are_refused_in_one_line(tmp_path):
    from skelid.errors import ModelError

    text = "\n".join(f'<Marker name="{b}{i}"><socket_parent_frame>/bodyset/{b}</socket_parent_frame>'
                     f'<location>{x} {y} {z}</location></Marker>'
                     for b, locs in MARKERS.items() for i, (x, y, z) in enumerate(locs))
    (tmp_path / "leg.osim").write_text(MODEL.format(markers=""))
    (tmp_path / "notes.xml").write_text("<OpenSimDocument><IKTaskSet/></OpenSimDocument>")
    (tmp_path / "broken.xml").write_text("<OpenSimDocument><MarkerSet")
    with pytest.raises(ModelError, match="--marker-set"):
        read_osim(tmp_path / "leg.osim")
    (tmp_path / "leg_markers.xml").write_text(f"<OpenSimDocument><MarkerSet><objects>{text}</objects>"
                                              "</MarkerSet></OpenSimDocument>")
    model, info = read_osim(tmp_path / "leg.osim")
    assert len(model.markers) == 12 and info.marker_set.endswith("leg_markers.xml")
    (tmp_path / "other.xml").write_text((tmp_path / "leg_markers.xml").read_text())
    with pytest.raises(ModelError) as exc:
        read_osim(tmp_path / "leg.osim")
    line = str(exc.value)
    assert "leg_markers.xml" in line and "other.xml" in line and "--marker-set" in line and "\n" not in line


def test_the_first_example_runs_as_written_on_a_few_frames(shared_data, tmp_path, capsys):
    """``skelid fit gait2354_simbody.osim static.trc walk.trc --out DIR`` (no marker set named): a scaled
    model OpenSim loads and runs inverse kinematics with, a ScaleSet and a report."""
    osim = pytest.importorskip("opensim", reason="the opensim package is not installed (pip install opensim)")
    osim.Logger.removeFileSink()
    from skelid.cli import main
    from skelid.io import read_markers, write_trc
    from skelid.scaling import opensim_ik

    s01 = shared_data / "opensim-subject01"
    static, walk = read_markers(s01 / "subject01_static.trc"), read_markers(s01 / "subject01_walk1.trc")
    write_trc(tmp_path / "static.trc", MarkerData(static.positions[:4], static.names, static.rate, static.units))
    write_trc(tmp_path / "walk.trc", MarkerData(walk.positions[:24:2], walk.names, walk.rate / 2, walk.units))
    out = tmp_path / "fit"
    assert main(["fit", str(s01 / "gait2354_simbody.osim"), str(tmp_path / "static.trc"),
                 str(tmp_path / "walk.trc"), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "gait2354_Scale_MarkerSet.xml" in err
    assert {"scaled.osim", "scaled_scale_set.xml", "scaled_report.md"} <= {p.name for p in out.iterdir()}
    assert osim.ScaleSet(str(out / "scaled_scale_set.xml")).getSize() == 10  # 8 marked bodies and the tali
    assert "femur_r" in (out / "scaled_report.md").read_text()
    ik = opensim_ik(out / "scaled.osim", tmp_path / "walk.trc", tmp_path / "ik")
    assert ik["frames"] == 12 and ik["markers"] == 31 and ik["rmse_mm"] < 60.0
    assert not list(s01.glob("*.log"))


#: the leg's markers marked ``fixed`` (landmarks) in :func:`_write_fixed`
FIXED = {"pelvis0", "pelvis1", "pelvis2", "pelvis3", "thigh0", "thigh3", "shank0", "shank3"}


def _write_fixed(path, places=None):
    """The leg model with the markers of :data:`FIXED` marked fixed, each marker at ``places`` (name -> (3,) m)
    or its own place."""
    places = places or {}
    path.write_text(MODEL.format(markers="\n".join(
        f'<Marker name="{b}{i}"><socket_parent_frame>/bodyset/{b}</socket_parent_frame>'
        f'<location>{" ".join(map(str, places.get(f"{b}{i}", loc)))}</location>'
        f'<fixed>{str(f"{b}{i}" in FIXED).lower()}</fixed></Marker>'
        for b, locs in MARKERS.items() for i, loc in enumerate(locs))))
    return path


def test_free_markers_at_a_placeholder_are_placed_before_they_can_drive_the_scales(tmp_path):
    """Cluster markers a generic model holds at one placeholder point: the static trial's fixed markers scale
    the bodies first, and the free markers go where the static trial saw them."""
    from skelid.scaling import place_free_markers_first

    placeholder = {"thigh": (0.0, -0.2, 0.05), "shank": (0.0, -0.2, 0.05)}
    at_placeholder = {f"{b}{i}": placeholder[b] for b in placeholder for i in range(4) if f"{b}{i}" not in FIXED}
    truth = {"pelvis": 1.05, "thigh": 1.1, "shank": 0.95}
    static, _ = _trials(_write_fixed(tmp_path / "true.osim"), truth, frames=(6, 2))
    generic = _write_fixed(tmp_path / "generic.osim", places=at_placeholder)
    full, info = read_osim(generic)
    assert info.fixed_markers == FIXED
    moved, note = place_free_markers_first(full, info, "bodies", static)
    assert set(moved) == {"thigh1", "thigh2", "shank1", "shank2"} and "8 fixed markers" in note
    true_model, _ = read_osim(tmp_path / "true.osim")
    for name, r in moved.items():  # the true place (mm, from the body's joint centre) up to the noise
        expected = true_model.markers[true_model.marker_names.index(name)].position
        np.testing.assert_allclose(r, expected, atol=0.5, err_msg=name)


def test_a_fixed_marker_off_its_landmark_is_fitted_not_taken_as_exact(tmp_path):
    """OpenSim's ``fixed`` flag (a palpated landmark its MarkerPlacer leaves alone) is no proof of the place: a
    landmark marker 9 mm off the generic model's landmark gets its offset fitted, and the noise stays the noise."""
    fixed = FIXED
    truth = {"pelvis": 1.0, "thigh": 1.0, "shank": 1.0}
    thigh3 = np.add(MARKERS["thigh"][3], (0.006, -0.004, 0.005))
    trials = _trials(_write_fixed(tmp_path / "true.osim", places={"thigh3": thigh3}), truth)
    generic = _write_fixed(tmp_path / "generic.osim")
    base, info = read_osim(generic)
    assert info.fixed_markers == fixed
    assert {p.target for p in osim_parameters(base, info, "bodies", "offsets").parameters
            if p.kind == "marker_offset"} == set(base.marker_names)
    fit = fit_osim(generic, trials, scale="bodies", markers="offsets")
    assert fit.result["sigma"]["value"] < 0.05  # simulated at 0.01 mm; held at its landmark, about 1 mm
    got = [fit.result[f"offset_thigh3_{a}"]["mean"] for a in "xyz"]
    np.testing.assert_allclose(got, (0.006e3, -0.004e3, 0.005e3), atol=0.3)
    # the free markers, placed on the static trial first, have a wide prior about their generic place
    sd = {p.target: p.prior.sd for p in fit.model.parameters if p.kind == "marker_offset"}
    assert {m for m, v in sd.items() if v == PLACED_OFFSET_SD} == set(base.marker_names) - fixed
    assert all(sd[m] == 10.0 for m in fixed)


def test_an_unmarked_body_that_holds_a_marked_ones_joint_is_scaled_in_the_joint_fit(shared_data):
    """gait2354's talus carries no marker but holds the foot's joint 65 mm from its own: the joint fit (under
    the scales' priors) scales it; a fit without priors, where the data alone cannot, does not."""
    from skelid.io.osim import scaled_bodies

    s01 = shared_data / "opensim-subject01"
    base, info = read_osim(s01 / "gait2354_simbody.osim", s01 / "gait2354_Scale_MarkerSet.xml")
    assert set(scaled_bodies(base, base.marker_names)) - {m.segment for m in base.markers} == {"talus_r", "talus_l"}
    joint = {p.target for p in osim_parameters(base, info, "linked", "offsets", holders=True).parameters
             if p.kind == "scale"}
    plain = {p.target for p in osim_parameters(base, info, "linked", "offsets").parameters if p.kind == "scale"}
    assert joint - plain == {"talus_r", "talus_l"}


def test_batch_and_other_commands_read_an_osim_model_with_body_scales(shared_data):
    from skelid.simulate import resolve_model

    model = resolve_model(shared_data / "opensim-subject01" / "gait2354_simbody.osim")
    assert {p.kind for p in model.parameters} == {"scale"} and len(model.parameters) == 8
    assert len(model.markers) == 39  # the MarkerSet found beside the model


def test_scales_and_offsets_fitted_together_recover_the_identified_scales(leg):
    """Near noise-free data with moved markers: the joint fit recovers the scale the data determine (the
    thigh's, between the functional hip and knee centres); the shank's (a leaf) and the pelvis' (one hip
    only: a shift of all its markers mimics it) are left to the offsets' prior, and said so."""
    truth = {"pelvis": 1.06, "thigh": 1.1, "shank": 0.95}
    moved = {"thigh1": (6.0, -4.0, 3.0), "shank3": (-5.0, 2.0, 4.0), "pelvis0": (0.0, 3.0, -2.0),
             "thigh3": (-3.0, 0.0, 8.0)}
    trials = _trials(leg, truth, moved)
    fit = fit_osim(leg, trials[1:], scale="bodies", markers="offsets")
    assert fit.joint is not None and fit.joint.converged
    got = {p.target: fit.theta[k] for k, p in enumerate(fit.model.parameters) if p.kind == "scale"}
    assert got["thigh"] == pytest.approx(truth["thigh"], abs=1e-4)
    assert any("do not determine scale_pelvis, scale_shank" in w for w in fit.warnings)
    assert fit.result["scale_shank"]["sd"] > 0.01  # the prior's width, not rounding


def test_a_lone_trial_is_not_thinned_as_a_static_one(leg):
    trials = _trials(leg, {"pelvis": 1.0, "thigh": 1.0, "shank": 1.0}, frames=(8, 40))
    fit = fit_osim(leg, trials[1:], scale="bodies", markers="none")
    assert fit.data.meta["trial_frames_used"] == [40]


def test_a_first_trial_that_moves_is_a_movement_trial_and_a_standing_one_a_static_one(leg, tmp_path):
    """Two walks: the first is not thinned to a static trial's frames, and the result says why; a
    standing first trial is, with its small motion beside the threshold."""
    from skelid.scaling import MOVEMENT_FRAMES, STATIC_FRAMES, STILL_MM, marker_motion

    static, move = _trials(leg, {"pelvis": 1.0, "thigh": 1.0, "shank": 1.0}, frames=(60, 160))
    assert marker_motion(static) < 0.1 < STILL_MM < marker_motion(move)
    assert np.isnan(marker_motion(MarkerData(static.positions[:1], static.names, 60.0, "mm", "one frame")))
    first, second = (MarkerData(move.positions[s], move.names, 60.0, "mm", "sim") for s in (slice(0, 120),
                                                                                              slice(120, None)))
    fit = fit_osim(leg, [first, second], scale="bodies", markers="none")
    assert fit.data.meta["trial_frames_used"] == [60, 40] and 60 > STATIC_FRAMES and 60 <= MOVEMENT_FRAMES
    assert fit.result["first_trial"]["static"] is False
    assert fit.result["first_trial"]["marker_motion_mm"] > STILL_MM
    paths = write_outputs(fit, tmp_path / "out")
    assert json.loads(paths["json"].read_text())["first_trial"]["static"] is False
    assert "| sim | movement (markers move " in paths["report"].read_text()
    fit = fit_osim(leg, [static, second], scale="bodies", markers="none")
    assert fit.data.meta["trial_frames_used"] == [STATIC_FRAMES, 40]
    assert fit.result["first_trial"] == {"static": True, "marker_motion_mm": pytest.approx(0.01, abs=0.01),
                                         "still_below_mm": STILL_MM}


@pytest.mark.parametrize("name, still", [
    ("opensim-subject01/subject01_static.trc", True), ("addbio-subject4/MarkerData/static1.trc", True),
    ("ktk-gait-pig/static.c3d", True), ("opensim-subject01/subject01_walk1.trc", False),
    ("addbio-subject4/MarkerData/squats1.trc", False), ("addbio-subject4/MarkerData/STS1.trc", False),
    ("addbio-subject4/MarkerData/DJ1.trc", False), ("opensim-gaps/walking2.c3d", False)])
def test_the_shared_standing_trials_stand_still_and_their_movements_move(shared_data, name, still):
    """What the threshold between a static and a movement trial stands on: less than 10 mm against more than 80."""
    from skelid.io import read_markers
    from skelid.scaling import STILL_MM, marker_motion

    motion = marker_motion(read_markers(shared_data / name))
    assert (motion < 10.0 < STILL_MM) if still else (motion > 80.0 > STILL_MM)


def test_an_offset_the_data_pull_past_its_bound_is_held_there_and_named(leg):
    """A marker 90 mm from its model place along one axis (the offsets' bound is 50 mm): the joint fit
    holds that offset on its bound, marks it so in the result and names it and its body's scale in one
    warning; a fit of markers within their bounds says nothing of bounds."""
    from skelid.scaling import _on_bounds

    truth = {"pelvis": 1.0, "thigh": 1.05, "shank": 1.0}
    far = _trials(leg, truth, {"thigh1": (90.0, 0.0, 0.0)})
    fit = fit_osim(leg, far[1:], scale="bodies", markers="offsets")
    assert fit.result["offset_thigh1_x"].get("on_bound") == "upper"
    assert fit.result["offset_thigh1_x"]["ci95"][1] <= 50.0  # nothing beyond the bound, the interval included
    from skelid.io.legacy import run_from_scaling
    from skelid.scaling import scaling_table

    run = run_from_scaling(fit, scaling_table(fit))
    held = run.results["marker"].parameters["offset_thigh1_x"]
    assert held.status == "on-bound" and held.extra["bound"] == "upper"
    assert run.results["marker"].parameters["offset_thigh1_y"].status == "identified"
    said = [w for w in fit.warnings if "on their prior's bound" in w]
    assert len(said) == 1 and "offset_thigh1_x (upper)" in said[0] and "scale_thigh" in said[0]
    near = _trials(leg, truth, {"thigh1": (9.0, 0.0, 0.0)})
    fit = fit_osim(leg, near[1:], scale="bodies", markers="offsets")
    assert not _on_bounds(fit.model, fit.theta)
    assert not any("prior's bound" in w for w in fit.warnings)
