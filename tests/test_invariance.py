"""Where the data sit changes no number: the fits work about the data's own centre."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from skelid.errors import SkelidWarning
from skelid.estimators import MarkerEstimator, PaperFilter
from skelid.estimators.base import fit_origin, move_root
from skelid.model.kinematics import marker_positions
from skelid.simulate import builtin_model, simulate

CASE_A = builtin_model("case-a")


def _on_grid(data):
    """The data rounded to 1/1024 mm: a shift by whole millimetres is then exact in floating point."""
    return data.replace(positions=np.round(np.asarray(data.positions) * 1024.0) / 1024.0)


TRIAL = _on_grid(simulate(CASE_A, n_frames=40, sigma=3.0, rng=np.random.default_rng(3)).data)


def _fit(data):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkelidWarning)
        return MarkerEstimator(CASE_A, rng=0).fit(data)


@pytest.mark.parametrize("shift", [(1234.0, -987.0), (-65536.0, 31.0)])
def test_a_shift_by_whole_millimetres_changes_no_number_of_the_marker_fit(shift):
    base, moved = _fit(TRIAL), _fit(TRIAL.replace(positions=np.asarray(TRIAL.positions) + np.array(shift)))
    np.testing.assert_array_equal(moved.theta_, base.theta_)
    np.testing.assert_array_equal(moved.cov_, base.cov_)
    assert moved.sigma_ == base.sigma_
    np.testing.assert_array_equal(moved.origin_ - base.origin_, shift)
    # the poses come back in the data's frame: the root moved by the shift, nothing else
    np.testing.assert_allclose(moved.pose_, move_root(CASE_A, base.pose_, np.array(shift)), rtol=0, atol=1e-9)
    np.testing.assert_allclose(moved.y_, base.y_ + np.array(shift), rtol=0, atol=1e-9)


def test_the_origin_is_the_markers_mean_in_whole_units_and_ignores_missing_markers():
    y = np.asarray(TRIAL.positions).copy()
    y[3, 1] = np.nan
    present = np.isfinite(y).all(axis=-1)
    np.testing.assert_array_equal(fit_origin(CASE_A, y), np.round(y[present].mean(axis=0)))
    assert not fit_origin(CASE_A, np.full_like(y, np.nan)).any()


def test_moving_the_root_moves_every_marker_by_the_offset():
    pose = np.zeros((2, CASE_A.n_pose))
    offset = np.array([12.0, -7.0])
    moved = move_root(CASE_A, pose, offset)
    assert moved is not pose and not pose.any()
    theta = np.array([0.5 * (p.prior.lower + p.prior.upper) for p in CASE_A.parameters])

    np.testing.assert_allclose(marker_positions(CASE_A, theta, moved),
                               marker_positions(CASE_A, theta, pose) + offset, atol=1e-9)


def test_the_paper_filter_does_not_depend_on_where_the_frames_sit():
    base = PaperFilter(CASE_A).fit(TRIAL)
    moved = PaperFilter(CASE_A).fit(TRIAL.replace(positions=np.asarray(TRIAL.positions) + 5e5))
    np.testing.assert_allclose(moved.measured_, base.measured_, rtol=1e-9, equal_nan=True)


@pytest.mark.parametrize("units", ["m", "cm"])
def test_the_same_trial_in_other_units_gives_the_same_fit(units):
    """The data in metres or centimetres against a model in millimetres: converted on the way in, the
    estimate, its covariance and sigma equal those of the trial in millimetres. Not bit for bit as a shift by
    whole millimetres is: a tenth or a thousandth is not exact in binary, the tracked starting poses differ a
    little, and the motion model's penalty is built from them (5e-6 apart here), so the two costs differ: their
    optima are 2.6e-9 and 7.4e-9 of the estimate apart (5e-7 to 1.6e-6 of its sd); with one penalty, 8e-12."""
    base, other = _fit(TRIAL), _fit(TRIAL.to_units(units))
    np.testing.assert_allclose(other.theta_, base.theta_, rtol=2e-8)
    np.testing.assert_allclose(other.cov_, base.cov_, rtol=1e-6)
    assert other.sigma_ == pytest.approx(base.sigma_, rel=2e-8)
