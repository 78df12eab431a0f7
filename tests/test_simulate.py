"""Synthetic trials: the posture-limited motion near singular poses."""

import numpy as np

from skelid.model.kinematics import marker_positions
from skelid.simulate import builtin_model, simulate_posture


def test_a_posture_trial_keeps_every_one_axis_joint_in_its_span():
    model = builtin_model("case-a")
    trial = simulate_posture(model, [240.0], 60, 0.0, (150.0, 172.0), np.random.default_rng(0))
    hinge = [k for k, d in enumerate(model.dofs)
             if d.kind == "R" and model.segments[d.segment].joint.type in ("revolute", "hinge")]
    assert len(hinge) == 2
    deg = np.degrees(trial.pose[:, hinge])
    np.testing.assert_allclose(deg.min(axis=0), 150.0, atol=1e-9)
    np.testing.assert_allclose(deg.max(axis=0), 172.0, atol=1e-9)
    # noise-free: the markers are the model's at the true geometry and poses
    np.testing.assert_allclose(trial.data.positions, marker_positions(model, np.array([240.0]), trial.pose))
    assert trial.data.rate == 100.0 and trial.theta.tolist() == [240.0]
