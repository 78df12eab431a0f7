"""The models' average: stacking weights against brute force, the mixture against its closed forms, and
the blocks of frames it weighs."""

import itertools

import numpy as np
import pytest
from scipy.stats import norm

from skelid.errors import DataError
from skelid.estimators.uncertainty.stacking import mixture_summary, stacking_weights
from skelid.sensitivity import average_of, block_log_density, frame_log_density


def _score(lp, w):
    m = lp.max(axis=1, keepdims=True)
    return float(np.sum(np.log(np.exp(lp - m) @ w) + m[:, 0]))


@pytest.mark.parametrize("seed", range(4))
def test_stacking_weights_maximise_the_log_score_as_a_grid_search_does(seed):
    rng = np.random.default_rng(seed)
    lp = rng.normal(0.0, 2.0, (40, 3)) + np.array([0.0, 0.3, -0.2])
    w = stacking_weights(lp)
    assert w.shape == (3,) and np.all(w >= 0) and abs(w.sum() - 1) < 1e-12
    step = 0.005
    grid = [np.array([a, b, 1 - a - b]) for a, b in itertools.product(np.arange(0, 1 + step / 2, step), repeat=2)
            if a + b <= 1 + 1e-12]
    best = max(grid, key=lambda g: _score(lp, np.clip(g, 0, None)))
    assert _score(lp, w) >= _score(lp, np.clip(best, 0, None)) - 1e-9
    assert np.max(np.abs(w - best)) < 0.02


def test_a_model_that_predicts_every_unit_better_takes_all_the_weight_and_equal_models_share_it():
    assert stacking_weights([[0.0, -0.5, -3.0]] * 7)[0] == pytest.approx(1.0, abs=1e-8)
    assert stacking_weights(np.zeros((5, 4))) == pytest.approx(np.full(4, 0.25))
    # each model best on its own units, decisively: the share of units each predicts best
    lp = np.where(np.arange(10)[:, None] < 3, [0.0, -200.0], [-200.0, 0.0])
    assert stacking_weights(lp) == pytest.approx([0.3, 0.7], abs=1e-8)
    # a unit one model cannot predict at all (density 0) is no error
    assert stacking_weights([[0.0, -np.inf], [-1.0, 0.0]]).sum() == pytest.approx(1.0)


@pytest.mark.parametrize("bad", [np.zeros((0, 2)), np.zeros(3), [[np.nan, np.nan], [0.0, 0.0]],
                                 [[0.0, np.nan], [0.0, np.nan]]])
def test_units_or_models_without_a_density_are_refused(bad):
    with pytest.raises(ValueError):
        stacking_weights(bad)


def test_one_model_gives_its_own_normal_interval_and_in_log_space_its_log_normal_one():
    r = mixture_summary([2.0], [0.5], [1.0])
    assert r["value"] == 2.0 and r["sd"] == pytest.approx(0.5)
    assert r["interval"] == pytest.approx([2.0 - 1.959964 * 0.5, 2.0 + 1.959964 * 0.5], abs=1e-6)
    r = mixture_summary([np.log(1.1)], [0.05], [1.0], log=True)
    assert r["value"] == pytest.approx(1.1)
    assert r["interval"] == pytest.approx(list(1.1 * np.exp([-1.959964 * 0.05, 1.959964 * 0.05])), rel=1e-6)


def test_the_mixture_interval_holds_its_probability():
    mu, sd, w = np.array([0.0, 4.0, 5.0]), np.array([1.0, 0.5, 2.0]), np.array([0.2, 0.5, 0.3])
    r = mixture_summary(mu, sd, w, level=0.9)
    cdf = [float(w @ norm.cdf((x - mu) / sd)) for x in r["interval"]]
    assert cdf == pytest.approx([0.05, 0.95], abs=1e-10)
    assert r["value"] == pytest.approx(w @ mu)
    assert r["sd"] ** 2 == pytest.approx(w @ (sd**2 + (mu - w @ mu) ** 2))
    # a model of weight 0 changes nothing; a model with no spread is a point mass
    assert mixture_summary([*mu, 100.0], [*sd, 1.0], [*w, 0.0], level=0.9)["interval"] == r["interval"]
    lo, hi = mixture_summary([0.0, 10.0], [0.0, 0.0], [0.5, 0.5])["interval"]
    assert (lo, hi) == (0.0, 10.0)


def test_a_frame_density_is_the_gaussian_density_of_its_residuals_less_its_pose_coordinates():
    r = np.array([[1.0, np.nan, 2.0], [np.nan, np.nan, np.nan]])
    sig = np.array([2.0, 1.0, 0.5])
    lp = frame_log_density(r, sig, dim=3, n_pose=4)
    # a 3-D isotropic normal at distance d: 3 log-densities of N(0, s) whose squares sum to d^2
    want = sum(3 * norm.logpdf(0, scale=s) - d**2 / (2 * s**2) for d, s in ((1.0, 2.0), (2.0, 0.5))) - 4
    assert lp[0] == pytest.approx(want) and np.isnan(lp[1])


def test_blocks_hold_the_frames_every_model_fitted_and_pay_a_share_of_the_geometry():
    a = np.arange(25, dtype=float)
    b = a + 1.0
    b[3] = np.nan  # a frame the second model did not fit leaves the first's too
    lp = block_log_density([[a], [b]], rates=[10.0], n_params=[2, 6])  # blocks of 10 frames: 3 of them
    keep = np.ones(25, bool)
    keep[3] = False
    want = np.array([[a[keep & (a // 10 == k)].sum(), (a + 1)[keep & (a // 10 == k)].sum()] for k in range(3)])
    assert lp == pytest.approx(want - np.array([2, 6]) / 3)
    with pytest.raises(DataError):
        block_log_density([[np.full(4, np.nan)], [a[:4]]], rates=[10.0], n_params=[1, 1])
    with pytest.raises(DataError, match="different frames of trial 1"):  # every frame against every k-th
        block_log_density([[a], [a[::4]]], rates=[10.0], n_params=[1, 1])


def test_the_average_of_two_models_that_split_the_data_covers_both():
    est = {"one": {"L": {"value": 100.0, "sd": 1.0}, "only_one": {"value": 1.0, "sd": 0.1}},
           "two": {"L": {"value": 110.0, "sd": 1.0}}}
    lp = np.where(np.arange(20)[:, None] < 10, [0.0, -50.0], [-50.0, 0.0])
    avg = average_of(lp, est)
    assert avg["weights"] == pytest.approx({"one": 0.5, "two": 0.5}) and avg["blocks"] == 20
    q = avg["quantities"]["L"]
    assert q["value"] == pytest.approx(105.0) and q["interval"][0] < 100.0 and q["interval"][1] > 110.0
    assert avg["quantities"]["only_one"]["models"] == ["one"]  # a quantity of one model is that model's
    assert avg["quantities"]["only_one"]["value"] == pytest.approx(1.0)


def test_a_quantity_only_models_without_weight_have_is_left_out_of_the_average():
    est = {"one": {"L": {"value": 100.0, "sd": 1.0}}, "two": {"L": {"value": 101.0, "sd": 1.0}}}
    est["one"]["only_one"] = {"value": 1.0, "sd": 0.1}
    avg = average_of([[-500.0, 0.0]] * 3, est)  # the second model predicts every block better
    assert avg["weights"]["one"] == pytest.approx(0.0, abs=1e-12)
    assert "only_one" not in avg["quantities"] and avg["quantities"]["L"]["value"] == pytest.approx(101.0)
