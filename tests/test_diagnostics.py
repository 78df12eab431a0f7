"""The warning policy: each warning names the parameters it concerns, decided from the values."""

from types import SimpleNamespace

import numpy as np

from skelid.diagnostics import fit_warnings, prior_warnings, slow_markers, status_warnings
from skelid.result import FitResult, ParameterEstimate
from skelid.simulate import builtin_model


def _result(mean=250.0, sd=2.0, rows=()):
    p = ParameterEstimate("L2", "mm", mean, mean, sd, (mean - 2 * sd, mean + 2 * sd))
    return FitResult("marker", {"L2": p}, diagnostics={"identifiability": list(rows)})


def test_poorly_identified_and_on_bound_name_their_parameter():
    model = builtin_model("case-a")  # L2 in [200, 300] mm
    assert prior_warnings(model, _result()) == []
    (poor,) = prior_warnings(model, _result(sd=30.0))  # more than a quarter of the prior's width
    assert poor.code == "poorly-identified" and poor.parameters == ("L2",) and "sd 30" in poor.message
    (bound,) = prior_warnings(model, _result(mean=299.9))
    assert bound.code == "on-bound" and bound.parameters == ("L2",)


def test_a_status_other_than_identified_is_a_warning_about_that_parameter():
    rows = [{"parameter": "L2", "status": "unidentified"}, {"parameter": "L2", "status": "identified"}]
    (w,) = status_warnings(_result(rows=rows))
    assert w.parameters == ("L2",) and "unidentified (marker method)" in w.message


def test_drifting_residuals_look_like_soft_tissue_artefact():
    model = builtin_model("case-a")
    rng = np.random.default_rng(0)
    r = rng.normal(0.0, 1.0, (400, 3))
    r[:, 1] = 5.0 * np.sin(np.arange(400) / 40.0)  # marker B drifts slowly
    r[:50, 2] = np.nan
    est = SimpleNamespace(residuals_=r)
    assert [m for m, _, _ in slow_markers(model, est)] == ["B"]
    (w,) = [w for w in fit_warnings(model, _result(), est) if w.code == "soft-tissue-artefact"]
    assert "marker B" in w.message and w.parameters == ()
    # a segment already reported as model misfit is not reported again
    est.misfit_ = {"forearm": {"segment": "forearm", "flagged": True}}
    assert slow_markers(model, est) == []
