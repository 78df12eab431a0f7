"""The marker estimator on 3-D trees: several parameters, identifiability, gaps."""

import warnings

import numpy as np
import pytest

from skelid.errors import IdentifiabilityError, SkelidWarning
from skelid.estimators.marker import MarkerEstimator
from skelid.model import joint_positions, model_from_dict
from skelid.simulate import simulate
from tests.helpers import tree_3d, tree_3d_functional


def _fit(model, data, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkelidWarning)
        return MarkerEstimator(model, **kw).fit(data)


def test_noise_free_trial_recovers_every_parameter_and_derived_length():
    model = tree_3d_functional()
    truth = model.theta_nominal + np.array([6.0, -4.0, 3.0, 5.0, -6.0, 4.0, -3.0, 7.0, -5.0, 8.0])
    trial = simulate(model, theta=truth, n_frames=60, sigma=0.0, rng=np.random.default_rng(2))
    est = _fit(model, trial.data, bias_correction="none", cutoff=None)
    np.testing.assert_allclose(est.theta_, truth, atol=1e-6)
    centres = joint_positions(model, truth, trial.pose[0])
    hip, knee = model.segment_index["thigh"], model.segment_index["shank"]
    assert est.lengths_["hip-knee"]["value"] == pytest.approx(
        np.linalg.norm(centres[knee] - centres[hip]), abs=1e-6)
    res = est.result().diagnostics
    assert res["counting"]["pose_coordinates_per_frame"] == 12
    assert res["counting"]["surplus_per_frame"] == {"min": 18, "median": 18.0, "max": 18}
    assert set(res["joint_range_deg"]) == {"hip", "knee", "ankle"}


def _with_parameters(extra):
    d = tree_3d_functional().to_dict()
    d["parameters"] += extra
    return model_from_dict(d, "tree")


@pytest.mark.parametrize("extra, names", [
    # a hinge centre can slide along the hinge axis (z) without changing any marker
    ([{"name": "knee_z", "kind": "joint_centre", "joint": "knee", "axis": "z",
       "prior": {"type": "uniform", "lower": -20, "upper": 20}}], ["knee_z"]),
    # the weld's position and its only marker's position move that marker alike
    ([{"name": "weld_z", "kind": "joint_position", "joint": "weld", "axis": "z",
       "prior": {"type": "normal", "sd": 10}},
      {"name": "a1_z", "kind": "marker_position", "marker": "a1", "axis": "z",
       "prior": {"type": "normal", "sd": 10}}], ["weld_z", "a1_z"]),
])
def test_unidentifiable_combinations_are_named(extra, names):
    model = _with_parameters(extra)
    trial = simulate(model, n_frames=40, sigma=0.5, rng=np.random.default_rng(3))
    with pytest.raises(IdentifiabilityError) as info:
        _fit(model, trial.data)
    msg = str(info.value)
    assert "cannot identify" in msg and all(n in msg for n in names) and "\n" not in msg


def test_gaps_use_present_markers_and_skip_frames_that_cannot_fix_the_pose():
    model = tree_3d()
    trial = simulate(model, n_frames=80, sigma=1.0, rng=np.random.default_rng(5))
    y = trial.data.positions.copy()
    names = list(model.marker_names)
    y[5:15, names.index("p1")] = np.nan  # one pelvis marker gone: poses still fixed, frames used
    y[20:24, names.index("f1")] = np.nan  # foot down to one marker: the ankle's two angles ...
    y[20:24, names.index("f2")] = np.nan  # ... are not fixed: skipped although 24 coordinates remain
    y[30:33, :7] = np.nan  # only three markers left: fewer coordinates than pose coordinates
    est = _fit(model, trial.data.replace(positions=y), cutoff=None)  # skipping exact without a motion model
    assert est.frames_skipped_ == {"too_few_coordinates": 3, "pose_not_fixed": 4}
    skipped = np.r_[20:24, 30:33]
    assert not est.frames_used_[skipped].any() and est.frames_used_.sum() == 73
    assert any("7 of 80 frames" in w.message for w in est.warnings_)
    assert np.isnan(est.residuals_[5:15, names.index("p1")]).all()  # nothing filled in
    # skipping is exact: the same fit as without those frames
    keep = np.setdiff1d(np.arange(80), skipped)
    ref = _fit(model, trial.data.replace(positions=y[keep]), cutoff=None)
    np.testing.assert_allclose(est.theta_, ref.theta_, atol=1e-6)
    np.testing.assert_allclose(est.posterior_.sd, ref.posterior_.sd, rtol=1e-6)


def test_gaps_with_the_motion_model():
    model = tree_3d()
    trial = simulate(model, n_frames=80, sigma=1.0, rng=np.random.default_rng(5))
    y = trial.data.positions.copy()
    y[20:24, list(model.marker_names).index("f1")] = np.nan
    y[20:24, list(model.marker_names).index("f2")] = np.nan
    est = _fit(model, trial.data.replace(positions=y))
    assert not est.frames_used_[20:24].any() and est.frames_used_.sum() == 76
    assert np.all(np.abs(est.theta_ - trial.theta) < 5 * est.posterior_.sd + 1e-9)


def test_glitched_marker_positions_are_left_out_and_counted():
    model = tree_3d()
    trial = simulate(model, n_frames=80, sigma=1.0, rng=np.random.default_rng(6))
    y = trial.data.positions.copy()
    bad = [(10, 3), (11, 3), (40, 7), (60, 0)]
    for t, m in bad:
        y[t, m] += [150.0, -80.0, 60.0]  # a swapped or glitched label
    est = _fit(model, trial.data.replace(positions=y), cutoff=6.0)  # one motion model for both fits
    flagged = {(int(t), int(m)) for t, m in zip(*np.nonzero(est.outliers_), strict=True)}
    assert set(bad) <= flagged  # every glitch is caught
    # a glitch drags its frame's pose, so the screen may also leave out other markers of that frame,
    # never a marker of a clean frame
    assert {t for t, _ in flagged} == {t for t, _ in bad}
    clean = _fit(model, trial.data, cutoff=6.0)
    assert not clean.outliers_.any()
    np.testing.assert_allclose(est.theta_, clean.theta_, atol=0.5 * clean.posterior_.sd.max())
    assert est.result().diagnostics["outlying_marker_positions"] == len(flagged)
