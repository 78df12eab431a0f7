"""The accuracy study's control-variate estimates of bias and RMSE (benchmarks/accuracy.py) against closed forms."""

from pathlib import Path

import numpy as np

from tests.helpers import load_script

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "accuracy.py"


def _accuracy():
    return load_script(_PATH, "accuracy_study")


def test_an_error_that_is_its_linear_term_plus_a_constant_gives_the_exact_bias_and_rmse():
    # err = l + c: bias c and rmse sqrt(crlb^2 + c^2) exactly, whatever the draws of l (the raw means are off)
    acc = _accuracy()
    lin = np.random.default_rng(0).normal(0.0, 2.0, size=40)
    trials = [{"crlb": 2.0, "linear": float(x),
               "final": {"est": 250.3 + float(x), "lo": 240.0, "hi": 260.0, "dropped": 0, "seconds": 0.1}}
              for x in lin]
    row = acc.summarise("case-a", 15.0, 250.0, "iid", trials, ["final"])[0]
    assert abs(row["bias"] - 0.3) > 0.05  # the plain mean carries the draws' luck
    np.testing.assert_allclose(row["bias_cv"], 0.3, atol=1e-12)
    np.testing.assert_allclose(row["rmse_cv"], np.sqrt(4.0 + 0.09), rtol=1e-12)
    assert row["bias_cv_se"] < 1e-12 and row["rmse_cv_se"] < 1e-12
    np.testing.assert_allclose(row["linear_mean"], lin.mean())


def test_the_controlled_mean_square_is_the_sample_one_with_the_variates_variance_swapped_for_the_known_one():
    # var(d) + 2 cov(l, d) = var(err) - var(l) for d = err - l: the known variance replaces the sample's
    acc = _accuracy()
    rng = np.random.default_rng(1)
    lin = rng.normal(0.0, 1.0, size=30)
    err = 0.8 * lin + rng.normal(0.5, 0.6, size=30)
    bias, _, rmse, se = acc.controlled(err, lin, 1.0)
    np.testing.assert_allclose(bias, err.mean() - lin.mean())
    np.testing.assert_allclose(rmse**2, err.var(ddof=1) + bias**2 + 1.0 - lin.var(ddof=1), rtol=1e-12)
    assert 0 < se < 1


def test_intervals_that_cover_exactly_when_the_linear_term_is_inside_the_bound_cover_095():
    # covered == (|l| <= 1.96 crlb): the controlled coverage is the variate's known mean, 0.95, with no error
    acc = _accuracy()
    lin = np.random.default_rng(3).normal(0.0, 1.5, size=60)
    covered = np.abs(lin) <= acc.Z95 * 1.5
    cov, se = acc.controlled_coverage(covered, lin, np.full(60, 1.5))
    assert abs(covered.mean() - 0.95) > 0.01  # the plain share carries the draws' luck
    np.testing.assert_allclose(cov, 0.95, atol=1e-12)
    assert se < 1e-12
