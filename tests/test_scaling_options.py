"""Every option of ``skelid fit`` on an OpenSim model: it changes the result, or it is refused in one line.

One small fit (the three-body leg of ``test_scaling``, a static trial and a short movement) is run
once as the baseline; each case runs it again with one option changed and checks what the option
is for: the result differs in the way the option says, or the exit status is 2 with one line naming
the option and nothing written.
"""

from __future__ import annotations

import json

import pytest

from skelid.cli import cli, main
from skelid.io import write_trc
from tests.test_scaling import MODEL, _trials, marker_xml

TRUTH = {"pelvis": 1.0, "thigh": 1.1, "shank": 1.0}


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """The model, the trials, and the baseline fit's scaling table."""
    d = tmp_path_factory.mktemp("osim-options")
    (d / "leg.osim").write_text(MODEL.format(markers=marker_xml()))
    (d / "bare").mkdir()
    (d / "bare" / "leg.osim").write_text(MODEL.format(markers=""))
    (d / "markers").mkdir()
    (d / "markers" / "leg_markers.xml").write_text(
        f"<OpenSimDocument><MarkerSet><objects>{marker_xml()}</objects></MarkerSet></OpenSimDocument>")
    static, move = _trials(d / "leg.osim", TRUTH, frames=(6, 24))
    write_trc(d / "static.trc", static)
    write_trc(d / "move.trc", move)
    base = _run(d, [])
    assert base["rc"] == 0, base["err"]
    return d, base


def _run(d, extra, drop=(), model=None, out="out"):
    """``skelid fit MODEL static.trc move.trc --out DIR --json --quiet`` with ``extra``, less ``drop``."""
    import contextlib
    import io
    import shutil

    target = d / out
    shutil.rmtree(target, ignore_errors=True)
    argv = ["fit", str(model or d / "leg.osim"), str(d / "static.trc"), str(d / "move.trc"),
            "--out", str(target), "--json", "--quiet"]
    for opt in drop:
        i = argv.index(opt)
        del argv[i:i + (2 if opt == "--out" else 1)]
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        rc = main(argv + list(extra))
    text = stdout.getvalue()
    try:
        table = json.loads(text)
    except ValueError:
        table = None
    return {"rc": rc, "out": text, "err": stderr.getvalue(), "table": table, "dir": target}


def _numbers(table):
    """The fitted numbers of a scaling table (no timing, no paths)."""
    return {k: v for k, v in table.items() if k not in ("seconds", "written")}


def _refused(r, option):
    lines = r["err"].strip().splitlines()
    assert r["rc"] == 2 and len(lines) == 1 and option in lines[0], r["err"]
    assert not r["dir"].exists()


def _sd(table):
    """Each scale factor's sd, by (body, axis)."""
    return {(b, a): v["sd"] for b, e in table["scales"].items() for a, v in e.items()}


def check_method(d, base):
    # the paper method gets the fit: here its grid over three scale factors is refused by the memory check
    r = _run(d, ["--method", "paper", "--scale", "bodies"])
    _refused(r, "the paper fit")


def check_sigma(d, base):
    t = _run(d, ["--sigma", "0.5"])["table"]
    assert t["sigma_mm"]["value"] == 0.5 and t["sigma_mm"]["fixed"] and not base["table"]["sigma_mm"]["fixed"]
    # a noise level 50 times the fitted one: the scale the data determine (the thigh's) is far less sure; the
    # ones its markers' offsets leave to the prior (pelvis, shank) keep their prior-sized sd
    t_sd, b_sd = _sd(t), _sd(base["table"])
    assert max(t_sd[("thigh", a)] / b_sd[("thigh", a)] for a in "xyz") > 5
    assert all(t_sd[k] > 0.99 * b_sd[k] for k in b_sd)


def check_json(d, base):
    assert base["table"] is not None
    r = _run(d, [], drop=["--json", "--quiet"])
    assert r["rc"] == 0 and r["table"] is None and "scale pelvis" in r["out"]


def check_quiet(d, base):
    r = _run(d, [], drop=["--json"])
    assert r["rc"] == 0 and r["out"] == "" and "warning" not in r["err"]
    loud = _run(d, [], drop=["--quiet"])  # the same fit prints its warnings, one short line each
    assert base["table"]["warnings"] and "skelid: warning: " in loud["err"]
    assert all(len(line) <= 160 for line in loud["err"].splitlines())


def check_out(d, base):
    r = _run(d, [], drop=["--out"])
    assert r["rc"] == 0 and "written" not in r["table"] and "written" in base["table"]
    assert not r["dir"].exists()
    assert _numbers(r["table"]) == _numbers(base["table"])


def check_cutoff(d, base):
    t = _run(d, ["--cutoff", "0"])["table"]
    assert base["table"]["settings"]["cutoff"] == "auto" and t["settings"]["cutoff"] is None
    assert t["sigma_mm"]["per_trial"] != base["table"]["sigma_mm"]["per_trial"]


def check_artefact_rms(d, base):
    t = _run(d, ["--artefact-rms", "20"])["table"]
    assert t["settings"]["artefact_rms"] == 20.0
    assert all(t_sd > b_sd for t_sd, b_sd in zip(_sd(t).values(), _sd(base["table"]).values(), strict=True))


def check_noise(d, base):
    t = _run(d, ["--noise", "per-marker"])["table"]
    assert t["settings"]["noise"] == "per_marker" and len(t["sigma_mm"]["per_marker"]) == 12
    assert "per_marker" not in base["table"]["sigma_mm"]


def check_alternative(d, base):
    # another model of the leg (the knee's axis tilted 17 degrees, which no scale or offset can mimic; a hip
    # placed lower on the pelvis they can, and both models then fit alike): the spread of every scale factor
    alt = d / "leg_tilted_knee.osim"
    alt.write_text(MODEL.replace("<coordinates>k</coordinates><axis>0 0 1</axis>",
                                 "<coordinates>k</coordinates><axis>0.3 0 1</axis>").format(markers=marker_xml()))
    r = _run(d, ["--alternative", str(alt)])
    sens = r["table"]["model_sensitivity"]
    assert sens["models"] == ["leg.osim", "leg_tilted_knee.osim"] and base["table"]["model_sensitivity"] is None
    scales = {f"scale_{b}_{a}" for b in ("pelvis", "thigh", "shank") for a in "xyz"}
    lengths = {f"length {n}" for n in base["table"]["lengths_mm"]}
    assert lengths and set(sens["spread"]) == scales | lengths
    assert max(e["spread"] for e in sens["spread"].values()) > 1e-3
    # the trials were made with leg.osim: stacking gives it the weight, and the average is its fit
    avg = sens["average"]
    assert avg["weights"]["leg.osim"] > 0.9 and set(avg["quantities"]) == set(sens["spread"])
    for n, q in avg["quantities"].items():
        assert q["interval"][0] <= q["value"] <= q["interval"][1]
        assert q["value"] == pytest.approx(sens["estimates"]["leg.osim"][n]["value"], rel=1e-3)
    assert "average [95 % interval]" in (r["dir"] / "scaled_report.md").read_text()
    assert "alternative models" in (r["dir"] / "scaled_report.md").read_text()
    toml = d / "leg.toml"
    toml.write_text("")
    _refused(_run(d, ["--alternative", str(toml)]), "--alternative")


def check_seed(d, base):
    t = _run(d, ["--seed", "3"])["table"]
    assert _numbers(t) != _numbers(base["table"])
    assert _numbers(_run(d, ["--seed", "0"])["table"]) == _numbers(base["table"])  # 0 is the default


def check_scale(d, base):
    t = _run(d, ["--scale", "axes"])["table"]
    assert set(t["scales"]["thigh"]) == {"x", "y", "z"} == set(base["table"]["scales"]["thigh"])
    assert t["scales"] != base["table"]["scales"]  # the default's three factors are linked a priori
    one = _run(d, ["--scale", "bodies"])["table"]
    assert set(one["scales"]["thigh"]) == {"xyz"}


def check_markers(d, base):
    t = _run(d, ["--markers", "none"])["table"]
    assert t["marker_offsets_mm"] == {} and len(base["table"]["marker_offsets_mm"]) == 12


def check_marker_set(d, base):
    bare = d / "bare" / "leg.osim"
    assert _run(d, [], model=bare)["rc"] == 2  # no markers in the model, none beside it
    t = _run(d, ["--marker-set", str(d / "markers" / "leg_markers.xml")], model=bare)["table"]
    assert t["marker_set"].endswith("leg_markers.xml") and set(t["scales"]) == set(base["table"]["scales"])


def check_overwrite(d, base):
    (d / "taken").mkdir(exist_ok=True)
    (d / "taken" / "old.txt").write_text("old")
    argv = ["fit", str(d / "leg.osim"), str(d / "static.trc"), str(d / "move.trc"), "--out", str(d / "taken"),
            "--quiet"]
    assert main(argv) == 2 and (d / "taken" / "old.txt").exists()
    assert main(argv + ["--overwrite"]) == 0
    assert not (d / "taken" / "old.txt").exists() and (d / "taken" / "scaled.osim").exists()


def check_placement_sd(d, base):
    _refused(_run(d, ["--placement-sd", "5"]), "--placement-sd")  # the offsets are fitted instead


def check_max_memory(d, base):
    _refused(_run(d, ["--max-memory", "1K"]), "--max-memory")


def check_max_time(d, base):
    _refused(_run(d, ["--max-time", "0.001s"]), "--max-time")


def check_ik(d, base):
    r = _run(d, ["--ik", "--ik-draws", "3"])
    assert sorted(p.name for p in (r["dir"] / "ik").iterdir()) == ["ik.json", "move.mot", "move_sd.mot",
                                                                  "static.mot", "static_sd.mot"]
    assert set(r["table"]["ik"]) == {"static", "move"} and "ik" not in base["table"]
    rest = {k: v for k, v in _numbers(r["table"]).items() if k != "ik"}
    assert rest == _numbers(base["table"])  # the fit is the same
    _refused(_run(d, ["--ik"], drop=["--out"]), "--out")


def check_ik_draws(d, base):
    t = _run(d, ["--ik", "--ik-draws", "0"])["table"]
    assert {s["draws"] for s in t["ik"].values()} == {0}
    _refused(_run(d, ["--ik-draws", "3"]), "--ik-draws")


def scale_setup(d, static="static.trc", model="leg.osim") -> str:
    """An OpenSim Scale setup for the leg: each body scaled, on all three axes, by its markers 0 and 1."""
    from skelid.io import read_markers

    t = read_markers(d / static).time
    meas = "".join(f'<Measurement name="{b}"><apply>true</apply><MarkerPairSet><objects><MarkerPair>'
                   f'<markers>{b}0 {b}1</markers></MarkerPair></objects></MarkerPairSet><BodyScaleSet><objects>'
                   f'<BodyScale name="{b}"><axes>X Y Z</axes></BodyScale></objects></BodyScaleSet></Measurement>'
                   for b in TRUTH)
    return (f'<?xml version="1.0" encoding="UTF-8" ?><OpenSimDocument Version="40000"><ScaleTool name="leg">'
            f'<mass>70</mass><GenericModelMaker><model_file>{model}</model_file></GenericModelMaker><ModelScaler>'
            f'<apply>true</apply><scaling_order>measurements</scaling_order><MeasurementSet><objects>{meas}'
            f'</objects></MeasurementSet><marker_file>{static}</marker_file><time_range>{t[0]} {t[-1]}</time_range>'
            '<preserve_mass_distribution>false</preserve_mass_distribution></ModelScaler>'
            '<MarkerPlacer><apply>false</apply></MarkerPlacer></ScaleTool></OpenSimDocument>')


def check_scaletool(d, base):
    pytest.importorskip("opensim")
    setup = d / "leg_Setup_Scale.xml"
    # OpenSim loads only bodies with a mass and a knee whose three rotation axes are independent; neither
    # changes the geometry skelid fits
    massive = MODEL.format(markers=marker_xml()).replace(
        '<TransformAxis name="translation1">', '<TransformAxis name="rotation2"><axis>1 0 0</axis></TransformAxis>'
        '<TransformAxis name="rotation3"><axis>0 1 0</axis></TransformAxis><TransformAxis name="translation1">')
    for b in TRUTH:
        massive = massive.replace(f'<Body name="{b}"/>', f'<Body name="{b}"><mass>5</mass><mass_center>0 0 0'
                                  '</mass_center><inertia>0.1 0.1 0.1 0 0 0</inertia></Body>')
    (d / "leg_mass.osim").write_text(massive)
    setup.write_text(scale_setup(d, model="leg_mass.osim"))
    before = sorted(p.name for p in d.iterdir())
    r = _run(d, ["--scaletool", str(setup)])
    assert r["rc"] == 0, r["err"]
    peer = r["table"]["scaletool"]
    # its marker pairs on noise-free markers: every factor is the true one, on all three axes
    for body, v in TRUTH.items():
        assert peer["scales"][body] == pytest.approx([v] * 3, abs=2e-3)
    assert peer["n_compared"] == sum(len(a) for a in base["table"]["scales"].values())
    thigh = [row for row in peer["compared"] if row["body"] == "thigh"]
    assert all(row["inside"] for row in thigh) and peer["inside"] >= len(thigh)
    same = {k: v for k, v in r["table"].items() if k not in ("scaletool", "warnings")}
    assert _numbers(same) == _numbers({k: v for k, v in base["table"].items() if k != "warnings"})
    assert r["table"]["warnings"][:-1] == base["table"]["warnings"]
    assert json.loads((r["dir"] / "scaled_scaling.json").read_text())["scaletool"]["n_compared"] == \
        peer["n_compared"]
    assert "ScaleTool |" in (r["dir"] / "scaled_report.md").read_text()
    assert main(["report", str(r["dir"]), "--quiet"]) == 0
    html = next(r["dir"].glob("*.html")).read_text()
    assert "OpenSim ScaleTool" in html and f"{peer['inside']} of {peer['n_compared']} of its factors" in html
    assert set(p.name for p in d.iterdir()) - set(before) <= {r["dir"].name}  # nothing beside the setup
    # the setup scales another file than the model fitted: said once
    assert sum("the ScaleTool setup scales leg_mass.osim" in w for w in r["table"]["warnings"]) == 1
    _refused(_run(d, ["--scaletool", str(d / "none.xml")]), "none.xml")


CASES = {"--method": check_method, "--sigma": check_sigma, "--json": check_json, "--quiet": check_quiet,
         "--out": check_out, "--cutoff": check_cutoff, "--artefact-rms": check_artefact_rms,
         "--placement-sd": check_placement_sd,
         "--noise": check_noise, "--alternative": check_alternative, "--seed": check_seed, "--scale": check_scale,
         "--markers": check_markers, "--marker-set": check_marker_set, "--overwrite": check_overwrite,
         "--max-memory": check_max_memory, "--max-time": check_max_time, "--ik": check_ik,
         "--ik-draws": check_ik_draws, "--scaletool": check_scaletool}


def test_every_fit_option_has_a_case():
    options = {o for p in cli.commands["fit"].params for o in p.opts if o.startswith("--")}
    assert options - {"--help"} == set(CASES)


@pytest.mark.parametrize("option", list(CASES))
def test_an_osim_fit_honours_or_refuses_the_option(case, option):
    d, base = case
    CASES[option](d, base)


@pytest.mark.parametrize("setup, says", [
    ("not xml <", "malformed XML"),
    ('<OpenSimDocument Version="40000"><IKTool/></OpenSimDocument>', "holds no <ScaleTool>"),
    ("missing-static", "does not exist"),
    ("scaler-off", "ModelScaler off"),
])
def test_a_scale_setup_scaletool_cannot_run_is_refused_in_one_line(case, setup, says):
    pytest.importorskip("opensim")
    d, _ = case
    path = d / "bad_Setup_Scale.xml"
    if setup == "missing-static":
        setup = scale_setup(d).replace("<marker_file>static.trc", "<marker_file>nowhere.trc")
    elif setup == "scaler-off":
        setup = scale_setup(d).replace("<ModelScaler><apply>true", "<ModelScaler><apply>false")
    path.write_text(setup)
    try:
        r = _run(d, ["--scaletool", str(path)])
        _refused(r, path.name)
        assert says in r["err"]
    finally:
        path.unlink()


def test_scaletool_without_opensim_or_for_a_toml_model_is_refused(case, monkeypatch, tmp_path):
    import sys

    from skelid.errors import SettingError
    from skelid.scaletool import run_scaletool

    d, _ = case
    path = d / "leg_Setup_Scale.xml"
    path.write_text(scale_setup(d))
    monkeypatch.setitem(sys.modules, "opensim", None)  # as where the package is not installed
    with pytest.raises(SettingError, match="opensim package is not installed"):
        run_scaletool(path)
    _refused(_run(d, ["--scaletool", str(path)]), "opensim")
    monkeypatch.undo()
    toml = _run(d, ["--scaletool", str(path)], model="case-a")
    _refused(toml, "--scaletool")
