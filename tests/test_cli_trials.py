import json

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
    # another method with several trials is refused in one line
    assert main(["fit", str(EXAMPLES / "case_b.toml"), *paths, "--method", "paper"]) == 2
