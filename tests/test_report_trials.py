"""The per-trial section of the report: each trial's estimate and the consistency test, robust to bad input."""

from skelid.report import per_trial_html
from skelid.result import FitResult, ParameterEstimate

P = {"L": ParameterEstimate("L", "mm", 1.5, 1.5, 0.5, (0.5, 2.5))}


def _result(diagnostics):
    return FitResult("marker-multi", P, diagnostics=diagnostics)


def test_trials_and_consistency_are_shown():
    d = {"trials": [{"trial": "walk<1>.trc", "frames_used": 10, "sigma": 1.0,
                     "parameters": {"L": {"mean": 1.0, "sd": 0.1, "sd_with_between_trial": 0.25}}},
                    {"trial": "squat.trc", "frames_used": 12, "sigma": 1.2,
                     "parameters": {"L": {"mean": 2.0, "sd": 0.1, "sd_with_between_trial": 0.25}}}],
         "consistency": {"statistic": 50.0, "dof": 1, "p_value": 1e-12},
         "heterogeneity": {"L": {"tau": 0.7}}}
    html = per_trial_html(_result(d), "mm")
    assert "walk&lt;1&gt;.trc" in html and "squat.trc" in html  # names escaped
    assert "1 ± 0.25" in html and "2 ± 0.25" in html and "0.7" in html
    assert "χ² = 50 on 1 degrees of freedom" in html and "disagree" in html


def test_single_trial_and_malformed_diagnostics_give_no_section_or_no_traceback():
    assert per_trial_html(_result({}), "mm") == ""
    assert per_trial_html(_result({"trials": "x"}), "mm") == ""
    assert per_trial_html(_result({"trials": [1, 2]}), "mm") == ""
    html = per_trial_html(_result({"trials": [{"parameters": {"L": {"mean": "a"}}}, {"parameters": 3}],
                                   "consistency": {"statistic": None}, "heterogeneity": {"L": 5}}), "mm")
    assert "Each trial" in html and "χ²" not in html
