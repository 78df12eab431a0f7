"""Several trials of an OpenSim model: each trial's scales, the between-trial sd, the consistency test,
the Cramér-Rao bound and the noise interval, in scaled_scaling.json, the report and result.json."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from skelid.data import MarkerData
from skelid.estimators.multitrial import consistency_test
from skelid.scaling import _trials_markdown, fit_osim, write_outputs
from tests.test_scaling import MARKERS, MODEL, _trials, marker_xml


@pytest.fixture(scope="module")
def leg_trials(tmp_path_factory):
    """The leg model, a static trial and two movement trials."""
    d = tmp_path_factory.mktemp("osim-trials")
    (d / "leg.osim").write_text(MODEL.format(markers=marker_xml()))
    static, move = _trials(d / "leg.osim", {"pelvis": 1.02, "thigh": 1.1, "shank": 0.97}, frames=(6, 48))
    trials = [MarkerData(static.positions, static.names, 60.0, "mm", "static.trc"),
              MarkerData(move.positions[:24], move.names, 60.0, "mm", "walk1.trc"),
              MarkerData(move.positions[24:], move.names, 60.0, "mm", "walk2.trc")]
    return d, trials


def _finite(x) -> bool:
    return x is not None and math.isfinite(x)


def test_three_trials_give_each_trials_scales_the_spread_the_test_the_bound_and_the_noise_interval(leg_trials):
    d, trials = leg_trials
    fit = fit_osim(d / "leg.osim", trials)
    paths = write_outputs(fit, d / "out")
    table = json.loads(paths["json"].read_text())
    tr = table["trials"]
    assert tr["n_trials"] == 3 and [r["trial"] for r in tr["per_trial"]] == ["static.trc", "walk1.trc", "walk2.trc"]
    for r in tr["per_trial"]:
        assert set(r["scales"]) == set(MARKERS) and r["frames_used"] > 0 and _finite(r["sigma_mm"])
        for axes in r["scales"].values():
            for e in axes.values():
                assert all(_finite(e[k]) for k in ("value", "sd", "sd_with_between_trial"))
                assert e["ci95"][0] < e["value"] < e["ci95"][1]
    assert all(_finite(s) and s >= 0 for v in tr["between_trial_sd"].values() for s in v.values())
    c = tr["consistency"]
    assert c["tested"] and c["dof"] == (3 - 1) * 9 and 0.0 <= c["p_value"] <= 1.0 and _finite(c["statistic"])
    for body, axes in table["scales"].items():
        for e in axes.values():
            # the bound at one noise level per trial; the sd is the sandwich of each marker's own level,
            # which may fall below it by that level's estimation noise (a few per cent with 12 markers)
            assert _finite(e["crlb_sd"]) and 0 < e["crlb_sd"] <= 1.05 * e["sd"], body
            assert _finite(e["sd_between_trials"]) and _finite(e["sd_within_trials"])
    noise = table["sigma_mm"]
    lo, hi = noise["ci95"]
    assert lo < noise["value"] < hi and hi - lo > 1e-6 * noise["value"]
    pl = tr["placement"]  # the joint fit's own test of one marker placement for every trial
    assert 0.0 <= pl["p_value"] <= 1.0 and pl["sd_between_trials"] >= 0 and pl["verdict"]
    report = paths["report"].read_text()
    assert "Each trial's own scale factors" in report and "walk2.trc" in report
    assert f"on {c['dof']} degrees of freedom" in report and "Marker placement from trial to trial" in report


def test_the_consistency_test_counts_the_scale_factors_of_every_axis_not_the_offsets(leg_trials):
    d, trials = leg_trials
    fit = fit_osim(d / "leg.osim", trials[:2], scale="axes", markers="offsets")
    c = fit.result["consistency"]
    n_scales = sum(p.kind == "scale" for p in fit.model.parameters)
    assert n_scales == 9 and len(fit.model.parameters) > n_scales  # offsets placed beside the scales
    assert c["dof"] == (2 - 1) * 9 and c["tested"]


def test_the_cli_writes_the_trials_into_result_json(leg_trials, tmp_path):
    from skelid.cli import main
    from skelid.io import write_trc
    from skelid.io.results import read_run

    d, trials = leg_trials
    files = []
    for t in trials[:2]:
        write_trc(tmp_path / t.source, t)
        files.append(str(tmp_path / t.source))
    assert main(["fit", str(d / "leg.osim"), *files, "--out", str(tmp_path / "fit"), "--quiet"]) == 0
    r = read_run(tmp_path / "fit").results["marker"]
    names = {f"scale_{b}_{a}" for b in MARKERS for a in "xyz"}  # three factors per body (the default)
    assert len(r.diagnostics["trials"]) == 2 and r.diagnostics["consistency"]["dof"] == 9
    assert set(r.diagnostics["heterogeneity"]) == names
    assert all(_finite(r.parameters[n].crlb_sd) for n in names)
    assert r.noise.interval is not None and r.noise.interval[0] < r.noise.sigma < r.noise.interval[1]


def test_a_given_noise_level_has_no_interval_rather_than_a_point(leg_trials):
    d, trials = leg_trials
    fit = fit_osim(d / "leg.osim", trials[:2], sigma=0.01, markers="none")
    table = json.loads(write_outputs(fit, d / "given")["json"].read_text())
    assert table["sigma_mm"]["fixed"] and table["sigma_mm"]["value"] == 0.01 and "ci95" not in table["sigma_mm"]


def test_below_one_degree_of_freedom_nothing_is_tested():
    one = consistency_test(np.array([[1.0, 2.0]]), np.array([np.eye(2)]), np.array([0.0, 0.0]))
    assert not one["tested"] and one["p_value"] is None and one["dof"] == 0
    # two trials that each inform one direction only, the same one: 1 + 1 observations of 2 parameters
    flat = np.array([[[1.0, 0.0], [0.0, 0.0]], [[1.0, 0.0], [0.0, 0.0]]])
    none = consistency_test(np.array([[1.0, 0.0], [3.0, 0.0]]), flat, np.array([2.0, 0.0]))
    assert not none["tested"] and none["p_value"] is None
    # one trial of full rank and one of rank 1: 2 + 1 - 2 = 1 degree of freedom
    mixed = consistency_test(np.array([[1.0, 0.0], [3.0, 5.0]]), np.array([np.eye(2), flat[0]]), np.array([2.0, 0.0]))
    assert mixed["tested"] and mixed["dof"] == 1 and mixed["statistic"] == pytest.approx(1.0 + 1.0)
    lines = "\n".join(_trials_markdown({"per_trial": [{"trial": "a.trc", "scales": {}}], "between_trial_sd": {},
                                        "consistency": {**one, "verdict": "not tested"}}))
    assert "not tested (fewer than one degree of freedom)" in lines


def test_a_still_static_trial_beside_a_moving_one_is_fitted_and_trials_of_which_none_moves_are_refused(leg_trials):
    """A noise-free static trial repeats one frame exactly (synthetic truth does): beside a walk it is fitted, alone
    or beside other still trials it is refused in one line."""
    from skelid.errors import DataError

    d, trials = leg_trials
    static = trials[0]
    still = replace(static, positions=np.repeat(static.positions[:1], len(static.positions), axis=0))
    fit = fit_osim(d / "leg.osim", [still, trials[1]])
    assert all(np.isfinite(fit.result[p.name]["sd"]) for p in fit.model.parameters if p.kind == "scale")
    with pytest.raises(DataError, match="nothing moves"):
        fit_osim(d / "leg.osim", [still, replace(still, source="still2.trc")])


def test_a_scale_fit_that_does_not_converge_is_tried_once_more_with_more_iterations(leg_trials, monkeypatch):
    import skelid.scaling as sc
    from skelid.errors import ConvergenceError

    d, trials = leg_trials
    calls, real = [], sc._fit_scales_once

    def once(model, parts, data, multi, method, sigma, seed, settings=None):
        calls.append(dict(settings or {}))
        if len(calls) == 1:
            raise ConvergenceError("the joint fit did not converge", "raise n_iter")
        return real(model, parts, data, multi, method, sigma, seed, settings)

    monkeypatch.setattr(sc, "_fit_scales_once", once)
    fit = fit_osim(d / "leg.osim", trials[:2], markers="none")
    assert calls[1]["n_iter"] == sc.RETRY_ITER_FACTOR * 100 and np.isfinite(fit.result["scale_thigh_y"]["sd"])
    assert "on_nonconvergence" not in calls[0] and calls[1]["on_nonconvergence"] == "warn"


def test_the_check_fit_of_an_osim_fit_keeps_an_unconverged_estimate(leg_trials, monkeypatch):
    import skelid.scaling as sc

    d, trials = leg_trials
    calls, real = [], sc._fit_scales_once

    def once(model, parts, data, multi, method, sigma, seed, settings=None):
        calls.append(dict(settings or {}))
        return real(model, parts, data, multi, method, sigma, seed, settings)

    monkeypatch.setattr(sc, "_fit_scales_once", once)
    fit_osim(d / "leg.osim", trials[:2])
    assert [c.get("on_nonconvergence") for c in calls] == [None, "warn"]
