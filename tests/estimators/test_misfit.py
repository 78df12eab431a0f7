"""Model misfit (a knee centre that moves with flexion, fitted as a fixed hinge) against soft tissue."""

import numpy as np

from skelid.data import MarkerData
from skelid.estimators.checks import model_misfit
from skelid.estimators.joint import joint_fit
from skelid.estimators.marker import MarkerEstimator
from skelid.model.description import model_from_dict
from skelid.model.kinematics import marker_positions


def _knee_model():
    return model_from_dict({
        "model": {"name": "knee", "dim": 3, "units": "mm"},
        "segments": [
            {"name": "thigh", "parent": "ground",
             "joint": {"name": "hip", "type": "free", "position": [0.0, 0.0, 0.0]}},
            {"name": "shank", "parent": "thigh",
             "joint": {"name": "knee", "type": "hinge", "axis": [0.0, 0.0, 1.0], "position": [0.0, -400.0, 0.0],
                       "range": [0.0, 100.0]}},
        ],
        "markers": [
            {"name": "T1", "segment": "thigh", "position": [60.0, -100.0, 20.0]},
            {"name": "T2", "segment": "thigh", "position": [-40.0, -250.0, 50.0]},
            {"name": "T3", "segment": "thigh", "position": [50.0, -350.0, -40.0]},
            {"name": "S1", "segment": "shank", "position": [50.0, -80.0, 40.0]},
            {"name": "S2", "segment": "shank", "position": [-30.0, -200.0, 50.0]},
            {"name": "S3", "segment": "shank", "position": [40.0, -330.0, -40.0]},
        ],
        "parameters": [{"name": "knee", "kind": "joint_centre", "joint": "knee", "axes": ["x", "y"],
                        "prior": {"type": "uniform", "lower": -40.0, "upper": 40.0}}],
    })


def _trial(seed, sigma, moving_centre=0.0, tissue=0.0, n=300):
    """Knee flexing 0-100 degrees; the true centre moves by ``moving_centre`` mm over the range (as a
    function of flexion), and/or each shank marker slides its own way with flexion (``tissue`` mm)."""
    model = _knee_model()
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 100.0
    q = np.zeros((n, model.n_pose))
    for k, d in enumerate(model.dofs):
        if d.segment == 1:
            q[:, k] = np.radians(50.0) - np.radians(50.0) * np.cos(2 * np.pi * 0.7 * t)
        else:
            q[:, k] = (0.3 if d.kind == "R" else 60.0) * np.sin(2 * np.pi * rng.uniform(0.2, 0.6) * t + k)
    flex = q[:, [k for k, d in enumerate(model.dofs) if d.segment == 1][0]]
    theta = np.zeros((n, 2))
    theta[:, 0] = moving_centre * (1.0 - np.cos(flex))
    theta[:, 1] = 0.5 * moving_centre * np.sin(flex)
    y = marker_positions(model, theta, q)
    if tissue:
        d = rng.normal(size=(3, 3))
        d *= tissue / np.linalg.norm(d, axis=1, keepdims=True)
        phase = rng.uniform(0, 2 * np.pi, 3)
        y[:, 3:] += np.sin(flex[:, None, None] * 1.5 + phase[None, :, None]) * d[None]
    return model, y + rng.normal(0.0, sigma, size=y.shape) if sigma else y, q


def test_a_moving_knee_centre_is_flagged_as_misfit_with_and_without_noise():
    for sigma in (0.0, 1.0):
        model, y, q = _trial(0, sigma, moving_centre=10.0)
        fit = joint_fit(model, y, model.theta_center, q, n_iter=50)
        res = model_misfit(model, y, fit.theta, fit.pose, fit.frames_used, max(sigma, 1e-3))
        assert res["knee"]["flagged"], res


def test_soft_tissue_that_moves_each_marker_its_own_way_is_not_misfit():
    model, y, q = _trial(1, 1.0, tissue=8.0)
    fit = joint_fit(model, y, model.theta_center, q, n_iter=50)
    res = model_misfit(model, y, fit.theta, fit.pose, fit.frames_used, 1.0)
    assert not res["knee"]["flagged"], res


def test_noise_free_misfit_keeps_its_markers_and_says_misfit_once():
    model, y, _ = _trial(2, 0.0, moving_centre=10.0)
    est = MarkerEstimator(model, rng=np.random.default_rng(0)).fit(MarkerData(y, model.marker_names, 100.0, "mm"))
    assert not est.outliers_.any()
    assert sum("model misfit at joint knee" in w.message for w in est.warnings_) == 1
    assert not any("look like soft-tissue artefact" in w.message for w in est.warnings_)
