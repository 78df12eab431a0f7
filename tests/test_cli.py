import json
import struct
import subprocess
import sys

import numpy as np
import pytest

from skelid.cli import main
from skelid.data import MarkerData
from skelid.io import write_trc
from skelid.simulate import builtin_model, simulate
from tests.conftest import EXAMPLES

PNG = b"\x89PNG\r\n\x1a\n"


def _png_ok(path):
    data = path.read_bytes()
    assert data[:8] == PNG
    w, h = struct.unpack(">II", data[16:24])
    assert w > 100 and h > 100


def test_demo_writes_figures_and_documented_json(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--frames", "150", "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary) == {"case_a", "case_b"}
    for case in summary.values():
        assert case["truth"] == {"L2": 250.0}
        assert case["frames_total"] == 150 and case["model"] in ("case_a", "case_b")
        paper = case["results"]["paper"]
        assert 0 < paper["frames"]["used"] <= 150
        assert set(paper["parameters"]["L2"]) >= {"map", "mean", "sd", "interval", "crlb_sd", "status"}
        assert len(paper["parameters"]["L2"]["interval"]) == 2
    for case in ("case_a", "case_b"):
        for fig in ("trajectories", "posterior", "map_per_step"):
            _png_ok(out / f"{case}_{fig}.png")
    assert not list(out.glob("*.part"))


def test_simulate_then_fit_json(tmp_path, capsys):
    trc = tmp_path / "a.trc"
    assert main(["simulate", "case-a", "--sigma", "5", "--frames", "120", "--seed", "1",
                 "--out", str(trc)]) == 0
    assert "true L2 = 250 mm" in capsys.readouterr().out
    assert main(["fit", str(EXAMPLES / "case_a.toml"), str(trc), "--method", "paper", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["context"]["frames_total"] == 120
    lo, hi = res["results"]["paper"]["parameters"]["L2"]["interval"]
    assert 200 <= lo < hi <= 300
    csv = tmp_path / "a.csv"
    assert main(["simulate", "case-b", "--frames", "20", "--out", str(csv)]) == 0
    assert csv.read_text().splitlines()[1].startswith("frame,time,A_x,A_y,B_x")


def test_fit_help_shows_a_working_example(capsys):
    with pytest.raises(SystemExit):
        from skelid.cli import cli

        cli.main(["fit", "--help"], prog_name="skelid")
    assert "skelid fit examples/case_a.toml" in capsys.readouterr().out


def _run(args, tmp_path):
    """Run the installed CLI in a subprocess: exit code and stderr."""
    p = subprocess.run([sys.executable, "-m", "skelid.cli", *args], capture_output=True, text=True,
                       cwd=tmp_path, timeout=120)
    return p.returncode, p.stderr


def _bad_inputs(tmp_path):
    model = builtin_model("case-a")
    trial = simulate(model, sigma=5.0, n_frames=30)
    good = tmp_path / "good.trc"
    write_trc(good, trial.data)
    bad_model = tmp_path / "bad_joint.toml"
    bad_model.write_text((EXAMPLES / "case_a.toml").read_text().replace('type = "revolute"', 'type = "ball"', 1))
    missing = tmp_path / "missing.trc"
    write_trc(missing, MarkerData(trial.data.positions[:, :2], ("A", "B"), 100.0))
    allnan = tmp_path / "nan.trc"
    write_trc(allnan, trial.data.replace(positions=np.full_like(trial.data.positions, np.nan)))
    interval = tmp_path / "interval.toml"
    interval.write_text((EXAMPLES / "case_a.toml").read_text().replace("lower = 200.0, upper = 300.0",
                                                                       "lower = 400.0, upper = 450.0"))
    clean = tmp_path / "clean.trc"
    write_trc(clean, simulate(model, sigma=0.0, n_frames=30).data)
    garbage = tmp_path / "garbage.trc"
    garbage.write_bytes(bytes(range(256)) * 4)
    notoml = tmp_path / "broken.toml"
    notoml.write_text("[model\n")
    return {
        "unknown joint type": ([str(bad_model), str(good)], "segments[1].joint.type: unknown value 'ball'"),
        "marker missing from file": ([str(EXAMPLES / "case_a.toml"), str(missing)], "marker(s) C"),
        "all rows NaN": ([str(EXAMPLES / "case_a.toml"), str(allnan)], "missing in every frame"),
        "no solution in interval": ([str(interval), str(clean)], "no solution inside the interval"),
        "binary garbage": ([str(EXAMPLES / "case_a.toml"), str(garbage)], "binary content"),
        "broken toml": ([str(notoml), str(good)], "not valid TOML"),
        "no such data file": ([str(EXAMPLES / "case_a.toml"), "nope.trc"], "does not exist"),
        "unsupported extension": ([str(EXAMPLES / "case_a.toml"), str(bad_model)], "unsupported file type"),
    }


def test_bad_inputs_give_one_line_and_exit_2(tmp_path):
    out = tmp_path / "out"
    for label, (args, needle) in _bad_inputs(tmp_path).items():
        code, err = _run(["fit", *args, "--out", str(out)], tmp_path)
        assert code == 2, (label, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1, (label, err)
        assert "Traceback" not in err and needle in lines[0], (label, err)
        assert not out.exists(), label  # nothing half-written


def test_nan_rows_warn_once_and_still_fit(tmp_path):
    trial = simulate(builtin_model("case-a"), sigma=3.0, n_frames=60)
    y = np.array(trial.data.positions)
    y[10:14] = np.nan
    p = tmp_path / "gappy.trc"
    write_trc(p, trial.data.replace(positions=y))
    code, err = _run(["fit", str(EXAMPLES / "case_a.toml"), str(p)], tmp_path)
    assert code == 0
    assert err.count("4 of 60 frames have too few markers to fix the pose") == 1
    code, err = _run(["fit", str(EXAMPLES / "case_a.toml"), str(p), "--quiet"], tmp_path)
    assert code == 0 and "warning" not in err and not err.strip()


def test_a_long_warning_takes_one_short_line_and_says_where_the_rest_is(tmp_path, capsys):
    from skelid.cli import WARNING_WIDTH, _echo_warnings, short_warning

    long = ("the residuals follow the pose: a soft-tissue artefact of about 7.7 mm rms per marker coordinate "
            "(F test p = 1.0e-255); the part of it that looks like a change of the geometry is in the intervals "
            "(the largest effect: scale_femur_r_y, 3.1 times the sd the residuals alone give)")
    _echo_warnings([long, "short one", long], full_in=tmp_path / "out")
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 3 and all(len(x) <= WARNING_WIDTH for x in lines)
    assert lines[0].endswith("...") and "soft-tissue artefact of about 7.7 mm" in lines[0]
    assert lines[1] == "skelid: warning: short one"
    assert str(tmp_path / "out" / "result.json") in lines[2]
    assert short_warning("a\n  b") == "a b" and short_warning("x" * 400).endswith("...")
    _echo_warnings([long], quiet=True)
    assert not capsys.readouterr().err


def test_cutoff_option_sets_the_motion_model(tmp_path, capsys):
    trc = tmp_path / "b.trc"
    assert main(["simulate", "case-b", "--sigma", "2", "--frames", "80", "--out", str(trc)]) == 0
    capsys.readouterr()
    for cutoff in ("0", "4"):
        assert main(["fit", str(EXAMPLES / "case_b.toml"), str(trc), "--cutoff", cutoff, "--json"]) == 0
        res = json.loads(capsys.readouterr().out)
        lo, hi = res["results"]["marker"]["parameters"]["L2"]["interval"]
        assert lo < 250.0 < hi
    assert main(["fit", str(EXAMPLES / "case_b.toml"), str(trc), "--cutoff", "-1"]) == 2


def test_artefact_option_widens_the_interval(tmp_path, capsys):
    trc = tmp_path / "b.trc"
    assert main(["simulate", "case-b", "--sigma", "2", "--frames", "80", "--out", str(trc)]) == 0
    capsys.readouterr()
    widths = []
    for rms in ("0", "5"):
        assert main(["fit", str(EXAMPLES / "case_b.toml"), str(trc), "--artefact-rms", rms, "--json"]) == 0
        res = json.loads(capsys.readouterr().out)["results"]["marker"]
        lo, hi = res["parameters"]["L2"]["interval"]
        widths.append(hi - lo)
        assert ("artefact" in res["diagnostics"]) == (rms != "0")
    assert widths[1] > 1.5 * widths[0]
    assert res["diagnostics"]["artefact"]["rms"] == 5.0 and res["diagnostics"]["artefact"]["sd_added"][0] > 0
    for bad in ("-1", "nan"):
        assert main(["fit", str(EXAMPLES / "case_b.toml"), str(trc), "--artefact-rms", bad]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "--artefact-rms" in err


def test_placement_option_widens_the_interval_of_one_trial_and_of_several(tmp_path, capsys):
    trcs = [tmp_path / "a.trc", tmp_path / "b.trc"]
    for k, trc in enumerate(trcs):
        assert main(["simulate", "case-b", "--sigma", "2", "--frames", "80", "--seed", str(k), "--out",
                     str(trc)]) == 0
    capsys.readouterr()
    for files in ([trcs[0]], trcs):
        widths = []
        for sd in (None, "0", "5"):
            argv = ["fit", str(EXAMPLES / "case_b.toml"), *map(str, files), "--json"]
            assert main(argv + ([] if sd is None else ["--placement-sd", sd])) == 0
            lo, hi = json.loads(capsys.readouterr().out)["results"]["marker"]["parameters"]["L2"]["interval"]
            widths.append(hi - lo)
        assert widths[1] == pytest.approx(widths[0])  # moving trials: none by default, as 0
        assert widths[2] > 2.0 * widths[0]
    for bad in ("-1", "nan"):
        assert main(["fit", str(EXAMPLES / "case_b.toml"), str(trcs[0]), "--placement-sd", bad]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "--placement-sd" in err
    assert main(["fit", str(EXAMPLES / "case_b.toml"), str(trcs[0]), "--placement-sd", "5", "--method", "paper"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--placement-sd" in err


def test_artefact_option_works_with_the_sampler_and_is_refused_where_it_cannot_act(tmp_path, capsys):
    trc = tmp_path / "b.trc"
    assert main(["simulate", "case-b", "--sigma", "2", "--frames", "80", "--out", str(trc)]) == 0
    capsys.readouterr()
    widths = []
    for rms in ("0", "5"):
        assert main(["fit", str(EXAMPLES / "case_b.toml"), str(trc), "--artefact-rms", rms, "--json",
                     "--method", "marker-smc"]) == 0
        res = json.loads(capsys.readouterr().out)["results"]["marker-smc"]
        lo, hi = res["parameters"]["L2"]["interval"]
        widths.append(hi - lo)
    assert widths[1] > 1.5 * widths[0]
    assert main(["fit", str(EXAMPLES / "case_b.toml"), str(trc), "--artefact-rms", "5", "--method", "paper"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--artefact-rms" in err
