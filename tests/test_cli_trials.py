import json

import pytest

from skelid.cli import main
from tests.conftest import EXAMPLES


def test_several_trials_alternatives_and_per_marker_noise(tmp_path, capsys):
    paths = []
    for seed, frames in ((1, 60), (2, 50)):
        p = tmp_path / f"t{seed}.trc"
        assert main(["simulate", "case-b", "--sigma", "2", "--frames", str(frames), "--seed", str(seed),
                     "--out", str(p)]) == 0
        paths.append(str(p))
    # an alternative model: the same body under another name (its estimate equals the main one)
    alt = tmp_path / "alt.toml"
    alt.write_text((EXAMPLES / "case_b.toml").read_text().replace('name = "case_b"', 'name = "case_b_alt"'))
    capsys.readouterr()
    assert main(["fit", str(EXAMPLES / "case_b.toml"), *paths, "--cutoff", "0", "--noise", "per-marker",
                 "--alternative", str(alt), "--json", "--out", str(tmp_path / "fit")]) == 0
    res = json.loads(capsys.readouterr().out)
    from skelid.io.results import read_run

    run = read_run(tmp_path / "fit")  # the folder holds what was printed, through the one serializer
    assert run.results["marker"].diagnostics["model_sensitivity"]["models"] == ["case_b", "case_b_alt"]
    m = res["results"]["marker"]
    diag = m["diagnostics"]
    assert len(diag["trials"]) == 2 and [t["data"] for t in diag["trials"]] == paths
    assert diag["consistency"]["dof"] == 1 and 0.0 <= diag["consistency"]["p_value"] <= 1.0
    lo, hi = m["parameters"]["L2"]["interval"]
    assert lo < 250.0 < hi
    assert res["context"]["data"] == paths
    spread = diag["model_sensitivity"]["spread"]["L2"]
    assert set(spread["values"]) == {"case_b", "case_b_alt"} and spread["spread"] < 1e-6
    # the same model twice predicts every block equally: equal weights, and its own estimate as the average
    avg = diag["model_sensitivity"]["average"]
    assert avg["method"] == "stacking" and avg["weights"] == pytest.approx({"case_b": 0.5, "case_b_alt": 0.5})
    assert avg["quantities"]["L2"]["value"] == pytest.approx(diag["model_sensitivity"]["estimates"]["case_b"]["L2"]
                                                             ["value"])
    # another method with several trials is refused in one line
    assert main(["fit", str(EXAMPLES / "case_b.toml"), *paths, "--method", "paper"]) == 2
    # the text output shows each trial's own estimate and the consistency test
    capsys.readouterr()
    assert main(["fit", str(EXAMPLES / "case_b.toml"), *paths, "--cutoff", "0"]) == 0
    out = capsys.readouterr().out
    assert "each trial's own estimate" in out and "consistency of the trials" in out
    assert all(f"t{seed}.trc" in out for seed in (1, 2))


def test_trials_text_closed_form():
    from skelid.result import FitResult, ParameterEstimate
    from skelid.sensitivity import trials_text

    p = {"L": ParameterEstimate("L", "mm", 1.5, 1.5, 0.5, (0.5, 2.5))}
    diag = {
        "trials": [{"trial": "a.trc", "parameters": {"L": {"mean": 1.0, "sd": 0.1, "sd_with_between_trial": 0.2}}},
                   {"trial": "b.trc", "parameters": {"L": {"mean": 2.0, "sd": 0.1, "sd_with_between_trial": 0.2}}}],
        "consistency": {"statistic": 50.0, "dof": 1, "p_value": 1e-12},
        "heterogeneity": {"L": {"tau": 0.7}}}
    text = trials_text(FitResult("marker", p, diagnostics=diag))
    assert "a.trc" in text and "± 0.2" in text and "0.7" in text and "disagree" in text
    assert trials_text(FitResult("marker", p)) == ""


def test_the_models_average_weighs_a_misplaced_marker_model_out_and_shows_each_model(tmp_path, capsys):
    """Data of case B; the alternative holds marker D 10 mm off its place: it predicts every second of the
    trials worse, so the average is the right model's fit, with each model's estimate beside it."""
    p = tmp_path / "t.trc"
    assert main(["simulate", "case-b", "--sigma", "5", "--frames", "300", "--seed", "4", "--out", str(p)]) == 0
    wrong = tmp_path / "wrong.toml"
    text = (EXAMPLES / "case_b.toml").read_text()
    wrong.write_text(text.replace('name = "case_b"', 'name = "case_b_d"').replace("position = [180.0, -35.0]",
                                                                                   "position = [180.0, -25.0]"))
    assert wrong.read_text() != text.replace('name = "case_b"', 'name = "case_b_d"')
    capsys.readouterr()
    assert main(["fit", str(EXAMPLES / "case_b.toml"), str(p), "--alternative", str(wrong), "--json"]) == 0
    sens = json.loads(capsys.readouterr().out)["results"]["marker"]["diagnostics"]["model_sensitivity"]
    avg = sens["average"]
    assert avg["blocks"] >= 3 and avg["weights"]["case_b"] > 0.99
    right, off = (sens["estimates"][m]["L2"]["value"] for m in ("case_b", "case_b_d"))
    assert abs(off - right) > 1.0  # the misplaced marker moves the answer
    assert avg["quantities"]["L2"]["value"] == pytest.approx(right, abs=0.01 * abs(off - right))
    assert main(["fit", str(EXAMPLES / "case_b.toml"), str(p), "--alternative", str(wrong)]) == 0
    out = capsys.readouterr().out
    assert "the models' average (stacking weights" in out and "case_b_d" in out
    assert "too few to tell how the data divide" in out  # 3 s of frames: 3 blocks, under the 5 that can
