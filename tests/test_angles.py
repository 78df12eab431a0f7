"""Joint angles with uncertainty: exact on noise-free data, each part of the sd against its own check,
the files OpenSim reads, one line for every bad input, and agreement with OpenSim's IK on gait2354."""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest

from skelid import angles
from skelid.cli import main
from skelid.data import MarkerData
from skelid.errors import DataError, FormatError
from skelid.io import write_trc
from skelid.io.osim import osim_coordinates, osim_parameters, read_osim
from skelid.model.kinematics import marker_positions
from tests.test_scaling import MODEL, _trials, marker_xml

TRUTH = {"pelvis": 1.0, "thigh": 1.1, "shank": 1.0}


#: the leg with a locked coordinate (h3) and a foot that carries no marker (its ankle coordinate)
LOCKED_H3 = '<Coordinate name="h3"><locked>true</locked><default_value>0.1</default_value></Coordinate>'
LOCKED_FOOT = (MODEL.replace('<Coordinate name="h3"/>', LOCKED_H3)
               .replace('<Body name="shank"/>', '<Body name="shank"/><Body name="foot"/>')
               .replace("</objects></JointSet>",
                        '<PinJoint name="ankle"><socket_parent_frame>/bodyset/shank</socket_parent_frame>'
                        '<socket_child_frame>/bodyset/foot</socket_child_frame><coordinates>'
                        '<Coordinate name="a"><default_value>0.2</default_value></Coordinate></coordinates>'
                        '</PinJoint></objects></JointSet>'))


@pytest.fixture(scope="module")
def leg(tmp_path_factory):
    d = tmp_path_factory.mktemp("ik-leg")
    (d / "leg.osim").write_text(MODEL.format(markers=marker_xml()))
    static, move = _trials(d / "leg.osim", TRUTH, frames=(6, 24))
    write_trc(d / "static.trc", static)
    write_trc(d / "move.trc", move)
    return d


def _true_geometry(path, scales=TRUTH, cov_scale=0.0):
    """The leg's geometry at its true scales (offsets 0), with a covariance ``cov_scale`` times its prior's."""
    base, info = read_osim(path)
    model = osim_parameters(base, info, "bodies", "offsets")
    theta = model.theta_nominal.copy()
    for k, p in enumerate(model.parameters):
        if p.kind == "scale":
            theta[k] = scales[p.target]
    sd = np.array([p.prior.sd for p in model.parameters])
    sd = np.where([p.kind == "scale" for p in model.parameters], sd * theta, sd)  # log-normal: sd of the factor
    return angles.FittedGeometry(model, theta, np.diag((cov_scale * sd) ** 2), "joint", osim_coordinates(path),
                                 None, str(path))


def _poses(model, F=12, seed=0):
    rng = np.random.default_rng(seed)
    q = np.zeros((F, model.n_pose))
    q[:, 3:6] = [100.0, 900.0, 50.0]
    q[:, :3] = rng.uniform(-0.4, 0.4, (F, 3))
    q[:, 6:9] = rng.uniform(-0.5, 0.5, (F, 3))
    q[:, 9] = rng.uniform(-1.5, 0.0, F)
    return q


def test_noise_free_markers_give_back_every_coordinate_in_opensim_units(leg):
    geom = _true_geometry(leg / "leg.osim")
    q = _poses(geom.model)
    y = marker_positions(geom.model, geom.theta, q)
    a = angles.joint_angles(geom, MarkerData(y / 1000.0, geom.model.marker_names, 60.0, "m"), n_draws=0)
    assert a.names == ("rx", "ry", "rz", "tx", "ty", "tz", "h1", "h2", "h3", "k")
    expect = q.copy()
    expect[:, 3:6] /= 1000.0  # translations in metres, rotations in radians
    np.testing.assert_allclose(a.value, expect, atol=1e-7)
    assert a.fixed.all() and a.status == ("fitted",) * 10
    np.testing.assert_array_equal(a.sd_geometry, 0.0)  # a covariance of zero carries nothing
    assert np.all(a.sd_pose < 1e-6)  # the noise estimated from residuals of rounding


def test_the_geometrys_draws_agree_with_its_first_order_effect(leg):
    geom = _true_geometry(leg / "leg.osim", cov_scale=0.02)
    q = _poses(geom.model, F=6)
    y = marker_positions(geom.model, geom.theta, q)
    a = angles.joint_angles(geom, MarkerData(y, geom.model.marker_names, 60.0, "mm"), n_draws=400,
                            rng=np.random.default_rng(1))
    ratio = a.sd_geometry / a.sd_geometry_linear
    # 400 draws: the sd is known to about 3.5 %; a wrong sign, unit or Jacobian is off by far more
    assert np.all((ratio > 0.85) & (ratio < 1.15)), ratio
    assert np.all(a.sd_geometry_linear > 0)
    share = a.geometry_share()
    assert np.all(share > 0.99)  # noise-free markers: the geometry is all of it


def test_the_pose_sd_matches_the_spread_of_refits_under_noise(leg):
    """The frame's own sd, sigma^2 (J^T J)^-1, against the spread of the pose over noisy copies of one frame."""
    from skelid.estimators.fit.pose import fit_pose

    geom = _true_geometry(leg / "leg.osim")
    q = _poses(geom.model, F=1, seed=3)
    x = marker_positions(geom.model, geom.theta, q)
    rng = np.random.default_rng(2)
    sigma = 2.0
    copies = x + rng.normal(0.0, sigma, (300,) + x.shape[1:])
    a = angles.joint_angles(geom, MarkerData(copies, geom.model.marker_names, 60.0, "mm"), n_draws=0)
    assert abs(a.sigma / sigma - 1) < 0.05
    qf, _ = fit_pose(geom.model, geom.theta, copies, np.repeat(q, 300, axis=0))
    spread = qf.std(axis=0)
    spread[3:6] /= 1000.0
    ratio = np.mean(a.sd_pose, axis=0) / spread
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio


def test_a_locked_coordinate_holds_its_default_and_one_no_marker_reaches_has_no_sd(tmp_path):
    path = tmp_path / "leg.osim"
    path.write_text(LOCKED_FOOT.format(markers=marker_xml()))
    coords = {c.name: c for c in osim_coordinates(path)}
    assert coords["h3"].locked and not coords["a"].locked and coords["a"].rotational and not coords["tx"].rotational
    base, info = read_osim(path)
    model = osim_parameters(base, info, "none", "none")
    geom = angles.FittedGeometry(model, np.zeros(0), np.zeros((0, 0)), "none", osim_coordinates(path), None, "x")
    q = np.zeros((4, model.n_pose))
    q[:, 3:6] = [0.0, 900.0, 0.0]
    q[:, 8] = [-0.1, -0.5, -1.0, -1.2]  # the knee (h3 is locked: no pose coordinate)
    y = marker_positions(model, np.zeros(0), q)
    y[2, :4] = np.nan  # the pelvis unseen in frame 2: its pose is not fixed
    a = angles.joint_angles(geom, MarkerData(y, model.marker_names, 60.0, "mm"), n_draws=5)
    c = a.names.index
    np.testing.assert_allclose(a.value[:, c("h3")], 0.1)
    np.testing.assert_array_equal(a.sd[:, c("h3")], 0.0)
    np.testing.assert_allclose(a.value[:, c("a")], 0.2)
    assert np.isnan(a.sd[:, c("a")]).all()
    assert a.status[c("h3")] == "locked" and a.status[c("a")] == "no markers"
    assert not a.fixed[2] and np.isnan(a.value[2, c("k")]) and np.isnan(a.sd[2, c("k")])
    np.testing.assert_allclose(a.value[[0, 1, 3], c("k")], q[[0, 1, 3], 8], atol=1e-7)
    text = angles.mot_text(a)
    assert "inDegrees=yes" in text and f"{np.degrees(0.1):.10g}" in text and "nan" in text


def _cli(argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(argv)
    return rc, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def fitted(leg):
    """``skelid fit leg.osim static.trc move.trc --out fit --ik --ik-draws 8``."""
    rc, _, err = _cli(["fit", str(leg / "leg.osim"), str(leg / "static.trc"), str(leg / "move.trc"),
                       "--out", str(leg / "fit"), "--quiet", "--ik", "--ik-draws", "8"])
    assert rc == 0, err
    return leg / "fit"


def test_fit_ik_writes_angles_sd_and_summary_that_opensim_reads(fitted):
    ik = fitted / "ik"
    assert sorted(p.name for p in ik.iterdir()) == ["ik.json", "move.mot", "move_sd.mot", "static.mot",
                                                   "static_sd.mot"]
    doc = json.loads((ik / "ik.json").read_text())["trials"]["move"]
    assert doc["frames"] == 24 and doc["draws"] == 8 and doc["covariance"] == "joint"
    k = doc["coordinates"]["k"]
    assert k["unit"] == "deg" and k["mean_sd"] > 0 and 0 <= k["geometry_share"] <= 1
    osim = pytest.importorskip("opensim", reason="the opensim package is not installed (pip install opensim)")
    osim.Logger.removeFileSink()
    t = osim.TimeSeriesTable(str(ik / "move.mot"))
    sd = osim.TimeSeriesTable(str(ik / "move_sd.mot"))
    assert t.getTableMetaDataAsString("inDegrees") == "yes" and t.getNumRows() == 24
    assert list(t.getColumnLabels()) == list(sd.getColumnLabels()) == ["rx", "ry", "rz", "tx", "ty", "tz",
                                                                      "h1", "h2", "h3", "k"]
    knee = np.asarray(t.getDependentColumn("k").to_numpy())
    assert -90 < knee.min() < knee.max() < 0  # degrees: the simulated knee swings in [-1.7, -0.1] rad
    assert np.all(np.asarray(sd.getDependentColumn("k").to_numpy()) > 0)


def test_ik_on_a_result_folder_gives_the_same_angles_as_fit_ik(fitted, tmp_path):
    rc, out, err = _cli(["ik", str(fitted), str(fitted.parent / "move.trc"), "--draws", "8", "--out",
                         str(tmp_path / "again"), "--json"])
    assert rc == 0, err
    doc = json.loads(out)["move"]
    assert doc["draws"] == 8
    a = np.loadtxt(tmp_path / "again" / "move.mot", skiprows=11)
    b = np.loadtxt(fitted / "ik" / "move.mot", skiprows=11)
    np.testing.assert_allclose(a, b, atol=1e-6)  # same geometry, same seed: equal to the pose fit's tolerance
    sa = np.loadtxt(tmp_path / "again" / "move_sd.mot", skiprows=11)
    sb = np.loadtxt(fitted / "ik" / "move_sd.mot", skiprows=11)
    np.testing.assert_allclose(sa, sb, rtol=1e-4)


@pytest.mark.parametrize("case", ["missing", "toml", "old", "damaged", "no-markers", "twice"])
def test_bad_input_to_ik_is_one_line_and_writes_nothing(fitted, tmp_path, case):
    import shutil

    move = fitted.parent / "move.trc"
    target = tmp_path / "fit"
    trial = [str(move)]
    if case == "missing":
        target = tmp_path / "nowhere"
        words = "does not exist"
    elif case == "toml":
        target.mkdir()
        (target / "result.json").write_text("{}")
        words = ".toml model"
    elif case == "old":
        shutil.copytree(fitted, target)
        (target / "scaled_geometry.json").unlink()
        words = "before skelid kept its geometry"
    elif case == "damaged":
        shutil.copytree(fitted, target)
        doc = json.loads((target / "scaled_geometry.json").read_text())
        doc["cov"] = doc["cov"][:-1]
        (target / "scaled_geometry.json").write_text(json.dumps(doc))
        words = "malformed"
    elif case == "no-markers":
        shutil.copytree(fitted, target)
        other = MarkerData(np.zeros((3, 1, 3)), ("X",), 60.0, "mm")
        write_trc(tmp_path / "other.trc", other)
        trial = [str(tmp_path / "other.trc")]
        words = "none of the model's"
    else:
        shutil.copytree(fitted, target)
        (tmp_path / "b").mkdir()
        shutil.copy(move, tmp_path / "b" / "move.trc")
        trial = [str(move), str(tmp_path / "b" / "move.trc")]
        words = "two trials are named"
    out = tmp_path / "angles"
    rc, _, err = _cli(["ik", str(target), *trial, "--out", str(out), "--draws", "2"])
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and words in lines[0] and "fix:" in lines[0], err
    assert not out.exists()


def test_ik_options_on_a_toml_fit_or_without_out_are_refused(leg, tmp_path):
    rc, _, err = _cli(["fit", "case-a", str(leg / "move.trc"), "--ik"])
    assert rc == 2 and "--ik" in err and len(err.strip().splitlines()) == 1
    rc, _, err = _cli(["fit", str(leg / "leg.osim"), str(leg / "move.trc"), "--ik"])
    assert rc == 2 and "--out" in err
    rc, _, err = _cli(["fit", str(leg / "leg.osim"), str(leg / "move.trc"), "--ik-draws", "3", "--out",
                       str(tmp_path / "x")])
    assert rc == 2 and "--ik-draws" in err and not (tmp_path / "x").exists()


def test_read_geometry_round_trips(fitted):
    g = angles.read_geometry(fitted)
    assert g.covariance == "joint" and g.theta.shape == (g.model.n_params,) and g.cov.shape == (g.theta.size,) * 2
    assert np.allclose(g.cov, g.cov.T) and np.all(np.diag(g.cov) > 0)
    with pytest.raises(DataError):
        angles.find_geometry(fitted / "ik")
    assert issubclass(FormatError, Exception)


@pytest.mark.opensim
def test_angles_agree_with_opensim_ik_on_a_gait2354_clip(shared_data, tmp_path):
    """The generic gait2354 model, 12 frames of the walk: every coordinate within 0.5 deg (1 mm) rms of OpenSim's."""
    osim = pytest.importorskip("opensim", reason="the opensim package is not installed (pip install opensim)")
    from skelid.io import read_markers
    from skelid.io.osim import keep_markers, write_scaled_osim
    from skelid.scaling import opensim_ik

    d = shared_data / "opensim-subject01"
    src, mset = d / "gait2354_simbody.osim", d / "gait2354_Scale_MarkerSet.xml"
    walk = read_markers(d / "subject01_walk1.trc")
    clip = MarkerData(walk.positions[40:52], walk.names, walk.rate, walk.units, "clip", walk.meta)
    write_trc(tmp_path / "clip.trc", clip)
    clip = read_markers(tmp_path / "clip.trc")
    full, info = read_osim(src, mset)
    model = osim_parameters(keep_markers(full, [n for n in full.marker_names if n in clip.names]), info, "none",
                            "none")
    write_scaled_osim(src, tmp_path / "model.osim", model, info, np.zeros(0), mset)
    geom = angles.FittedGeometry(model, np.zeros(0), np.zeros((0, 0)), "none", osim_coordinates(src), None, str(src))
    a = angles.joint_angles(geom, clip, n_draws=0)
    opensim_ik(tmp_path / "model.osim", tmp_path / "clip.trc", tmp_path / "ik", markers=model.marker_names)
    ref = osim.TimeSeriesTable(str(tmp_path / "ik" / "ik.mot"))
    assert list(ref.getColumnLabels()) == list(a.names)
    np.testing.assert_allclose(np.asarray(ref.getIndependentColumn()), a.time, atol=1e-6)
    ours = np.loadtxt(io.StringIO(angles.mot_text(a)), skiprows=11)[:, 1:]
    for c, name in enumerate(a.names):
        theirs = np.asarray(ref.getDependentColumn(name).to_numpy())
        rms = np.sqrt(np.mean((ours[:, c] - theirs) ** 2))
        assert rms <= (0.5 if a.rotational[c] else 0.001), (name, rms)


def test_the_laplace_covariance_is_the_fits_before_its_checks_widened_it(fitted):
    from dataclasses import replace

    table = json.loads((fitted / "scaled_scaling.json").read_text())
    g = angles.read_geometry(fitted)
    assert g.widening is not None and np.all(g.widening >= 1.0)
    w = np.asarray(g.widening, float)
    sd_rep, sd_lap = np.sqrt(np.diag(g.cov)), np.sqrt(np.diag(g.laplace().cov))
    n = 0
    for k, p in enumerate(g.model.parameters):
        if p.kind != "scale":
            continue
        e = table["scales"][p.target]["xyz" if p.axis is None else "xyz"[p.axis]]
        assert sd_rep[k] == pytest.approx(e["sd"], rel=1e-9)
        if w[k] == 1.0:  # not widened: the Laplace sd is the one reported, the bound unless an artefact adds
            assert sd_lap[k] == pytest.approx(sd_rep[k], rel=1e-12) and e["crlb_sd"] <= e["sd"] * (1 + 1e-9)
        else:  # widened: the reported variance is the widened bound plus what an artefact or placement adds
            assert e["crlb_sd"] * w[k] <= e["sd"] * (1 + 1e-9) and sd_lap[k] >= e["crlb_sd"] * (1 - 1e-9)
            assert sd_lap[k] == pytest.approx(sd_rep[k] / w[k], rel=1e-12)
        n += 1
    assert n == 9  # three factors per body (the default)
    # widened by the checks: laplace() takes the widening back out
    more = np.linspace(1.5, 3.0, w.size)
    wide = replace(g, cov=g.cov * np.outer(more, more), widening=more)
    lap = wide.laplace()
    np.testing.assert_allclose(lap.cov, g.cov, rtol=1e-12, atol=0)
    assert "laplace" in lap.covariance and lap.widening is None
    rc, out, err = _cli(["ik", str(fitted), str(fitted.parent / "move.trc"), "--draws", "4", "--covariance",
                         "laplace", "--out", str(fitted.parent / "laplace"), "--json"])
    assert rc == 0, err
    # the command line's laplace covariance: the fit's own where its checks widened nothing
    assert ("laplace" in json.loads(out)["move"]["covariance"]) == bool(np.any(w != 1.0))


def test_the_batches_of_draws_and_frames_do_not_change_the_answer(leg):
    geom = _true_geometry(leg / "leg.osim", cov_scale=0.05)
    q = _poses(geom.model, F=9)
    y = marker_positions(geom.model, geom.theta, q) + np.random.default_rng(4).normal(0, 0.5, (9, 12, 3))
    data = MarkerData(y, geom.model.marker_names, 60.0, "mm")
    big = angles.joint_angles(geom, data, n_draws=6, rng=np.random.default_rng(5))
    small = angles.joint_angles(geom, data, n_draws=6, rng=np.random.default_rng(5), batch=4)  # 2 frames a block
    np.testing.assert_allclose(small.value, big.value, atol=1e-12)
    np.testing.assert_allclose(small.sd, big.sd, rtol=1e-6)
    np.testing.assert_allclose(small.sd_geometry_linear, big.sd_geometry_linear, rtol=1e-9)


def test_draws_set_aside_once_converged_give_the_spread_of_fits_run_to_the_end(leg, monkeypatch):
    """Each draw's pose fit stops, a few iterations at a time, once its cost falls by at most DRAW_TOL over a
    round, instead of running with the whole batch until the slowest converges: the geometry's sd is that of
    fits run to a fall of 1e-10 all together, to well within the draws' own Monte-Carlo error."""
    geom = _true_geometry(leg / "leg.osim", cov_scale=0.05)
    q = _poses(geom.model, F=9)
    y = marker_positions(geom.model, geom.theta, q) + np.random.default_rng(4).normal(0, 0.5, (9, 12, 3))
    data = MarkerData(y, geom.model.marker_names, 60.0, "mm")
    rounds = angles.joint_angles(geom, data, n_draws=50, rng=np.random.default_rng(5))

    def at_once(model, theta, y, q0, ws, fit):
        return fit(model, theta, y, q0, n_iter=angles.DRAW_ITER, ws=ws)[0]

    monkeypatch.setattr(angles, "_refit_draws", at_once)
    whole = angles.joint_angles(geom, data, n_draws=50, rng=np.random.default_rng(5))
    np.testing.assert_allclose(rounds.value, whole.value, atol=1e-12)  # the MAP poses are not drawn
    ok = np.isfinite(whole.sd_geometry)
    np.testing.assert_allclose(rounds.sd_geometry[ok], whole.sd_geometry[ok], rtol=5e-3)
