"""Other starting geometries: the fit finds the deepest minimum, and a second one that fits almost as well
is held inside the interval (skelid.estimators.marker: other_starts, motion_stage, modes_stage)."""

from pathlib import Path

import numpy as np

from skelid.estimators import marker as M
from tests.helpers import load_script

_ACCURACY = Path(__file__).resolve().parents[2] / "benchmarks" / "accuracy.py"


def _folded_trial(rep: int, sigma: float = 5.0):
    """The accuracy study's case-A trial with a drawn geometry, every joint near the folded pose."""
    acc = load_script(_ACCURACY, "accuracy_study")
    seed = [0, int(sigma), 0, (acc.NOISES + tuple(acc.POSTURES) + ("coupled",)).index("folded"), rep]
    return acc.singular_trial("case-a", 500, sigma, "folded", np.random.default_rng(seed))


def test_the_search_leaves_a_minimum_the_prior_centre_falls_into():
    # a drawn geometry (truth 271 mm) on which the fit from the prior's centre settles at 238 mm, 33 mm
    # (about 100 sd) away, with a sharp interval; the same fit started at the truth reaches a lower cost there
    trial = _folded_trial(38)
    truth = trial.theta[0]
    centre = M.MarkerEstimator(trial.model, n_starts=1, rng=0).fit(trial.data)
    assert abs(centre.theta_[0] - truth) > 20.0
    found = M.MarkerEstimator(trial.model, rng=0).fit(trial.data)
    sd = np.sqrt(found.cov_[0, 0])
    assert abs(found.theta_[0] - truth) < 3.0 * sd
    assert found.sigma_ < centre.sigma_  # the minimum found is the deeper one
    lo, hi = found.posterior_.credible_interval(0.95)[0]
    assert lo <= truth <= hi


def test_starts_spread_over_the_prior_box_and_are_the_same_for_every_fit():
    trial = _folded_trial(38)
    lo, hi = trial.model.parameters[0].prior.lower, trial.model.parameters[0].prior.upper
    a = M.search_starts(([lo], [hi]), 4)
    np.testing.assert_array_equal(a, M.search_starts(([lo], [hi]), 4))
    assert a.shape == (4, 1) and np.all((a > lo) & (a < hi))
    # one start in each quarter of the interval: a Latin hypercube's strata
    np.testing.assert_array_equal(np.sort(np.floor((a[:, 0] - lo) / (hi - lo) * 4)), [0, 1, 2, 3])


def _motion(minima):
    """A motion stage's value that only carries the settled minima (the stage reads nothing else)."""
    return M.Motion(None, None, tuple((np.array(t, float), c) for t, c in minima))


class _Fit:
    """The final fit, of which the stage reads only theta."""

    def __init__(self, theta):
        self.theta = np.array(theta, float)


def test_a_minimum_almost_as_likely_is_held_inside_the_interval():
    # estimate 250 (sd 2), another minimum at 210 whose cost is higher by 2 sigma^2 (likelihood ratio e^-1):
    # the interval about 250 reaches 210 and that minimum's own half-width beyond it
    sigma, cov = 3.0, np.array([[4.0]])
    mo = _motion([((250.0,), 1000.0), ((210.0,), 1000.0 + 2 * sigma**2)])
    modes = M.modes_stage(_model_with(1), mo, _Fit([250.0]), sigma, cov)
    sd = np.sqrt(cov[0, 0] + modes.cov[0, 0])
    np.testing.assert_allclose(M.Z95 * sd, 40.0 + M.Z95 * 2.0, rtol=1e-12)
    assert len(modes.kept) == 1 and abs(modes.kept[0]["ratio"] - np.exp(-1.0)) < 1e-12


def test_a_minimum_far_less_likely_or_within_the_interval_adds_nothing():
    sigma, cov = 3.0, np.array([[4.0]])
    unlikely = _motion([((250.0,), 1000.0), ((210.0,), 1000.0 + 2 * sigma**2 * 4.0)])  # ratio e^-4 < 0.05
    near = _motion([((250.0,), 1000.0), ((252.0,), 1000.0)])  # 1 sd away: the same mode
    for mo in (unlikely, near):
        modes = M.modes_stage(_model_with(1), mo, _Fit([250.0]), sigma, cov)
        assert not modes.kept and not np.any(modes.cov)


def test_the_race_minima_are_weighed_against_a_lower_minimum_found_after_the_race():
    # the race settled at 210 and 250 with equal costs, and a later stage moved the estimate to 250 at a
    # cost lower by 8 sigma^2: the race's minimum at 210 is e^-4 as likely as the estimate, not e^0
    sigma, cov = 3.0, np.array([[4.0]])
    mo = _motion([((250.0,), 1000.0), ((210.0,), 1000.0)])
    assert M.modes_stage(_model_with(1), mo, _Fit([250.0]), sigma, cov).kept
    modes = M.modes_stage(_model_with(1), mo, _Fit([250.0]), sigma, cov, own_cost=1000.0 - 8 * sigma**2)
    assert not modes.kept and not np.any(modes.cov)


def test_in_two_parameters_only_the_line_to_the_other_minimum_widens():
    sigma, cov = 1.0, np.diag([1.0, 1.0])
    mo = _motion([((0.0, 0.0), 10.0), ((10.0, 0.0), 10.5)])
    modes = M.modes_stage(_model_with(2), mo, _Fit([0.0, 0.0]), sigma, cov)
    assert modes.cov[1, 1] == 0.0 and modes.cov[0, 1] == 0.0
    np.testing.assert_allclose(M.Z95 * np.sqrt(1.0 + modes.cov[0, 0]), 10.0 + M.Z95, rtol=1e-12)


def _model_with(n_params: int):
    class _Model:
        pass

    m = _Model()
    m.n_params = n_params
    m.parameter_names = tuple(f"p{k}" for k in range(n_params))
    return m
