"""Joint range as the rotation angle from the mean rotation (no gimbal artefacts)."""

import numpy as np
from scipy.spatial.transform import Rotation

from skelid.data import MarkerData
from skelid.estimators.checks.misfit import joint_ranges
from skelid.estimators.marker import MarkerEstimator
from skelid.model.description import model_from_dict
from skelid.model.kinematics import forward_kinematics, marker_positions


def _wrist_model():
    return model_from_dict({
        "model": {"name": "wrist", "dim": 3, "units": "mm"},
        "segments": [
            {"name": "forearm", "parent": "ground",
             "joint": {"name": "root", "type": "free", "position": [0.0, 0.0, 0.0]}},
            {"name": "hand", "parent": "forearm",
             "joint": {"name": "wrist", "type": "spherical", "position": [250.0, 0.0, 0.0]}},
        ],
        "markers": [
            {"name": "F1", "segment": "forearm", "position": [50.0, 30.0, 0.0]},
            {"name": "F2", "segment": "forearm", "position": [200.0, -25.0, 10.0]},
            {"name": "F3", "segment": "forearm", "position": [120.0, 5.0, 40.0]},
            {"name": "H1", "segment": "hand", "position": [40.0, 25.0, 0.0]},
            {"name": "H2", "segment": "hand", "position": [80.0, -20.0, 10.0]},
            {"name": "H3", "segment": "hand", "position": [60.0, 0.0, -30.0]},
        ],
        "parameters": [{"name": "wrist", "kind": "joint_centre", "joint": "wrist", "axes": ["x", "y", "z"],
                        "prior": {"type": "uniform", "lower": -40.0, "upper": 40.0}}],
    })


def _poses_near_gimbal_lock(model, n, wobble_deg, rng):
    """Root moving widely; wrist at 90 degrees about x (the z-x-y sequence's singular pose) plus a
    small random rotation, written as the model's z, x, y angles."""
    t = np.arange(n) / 100.0
    q = np.zeros((n, model.n_pose))
    dofs = model.dofs
    root_r = [k for k, d in enumerate(dofs) if d.segment == 0 and d.kind == "R"]
    root_t = [k for k, d in enumerate(dofs) if d.segment == 0 and d.kind == "T"]
    for j, k in enumerate(root_r):
        q[:, k] = 0.6 * np.sin(2 * np.pi * (0.3 + 0.1 * j) * t + j)
    for j, k in enumerate(root_t):
        q[:, k] = 80.0 * np.sin(2 * np.pi * 0.2 * t + j)
    wrist = [k for k, d in enumerate(dofs) if d.segment == 1 and d.kind == "R"]
    small = Rotation.from_rotvec(rng.normal(size=(n, 3)) * np.radians(wobble_deg) / np.sqrt(3))
    R = Rotation.from_euler("x", 90, degrees=True) * small
    q[:, wrist] = R.as_euler("ZXY")
    return q, R


def test_rotation_angle_range_has_no_gimbal_swing():
    model = _wrist_model()
    rng = np.random.default_rng(0)
    q, R = _poses_near_gimbal_lock(model, 400, 2.0, rng)
    kin = forward_kinematics(model, model.theta_center, q)  # the z, x, y angles reproduce R
    R_rel = np.swapaxes(kin.R_world_parent[:, 1], 1, 2) @ kin.R_world_seg[:, 1]
    assert np.allclose(R_rel, R.as_matrix(), atol=1e-9)
    wrist = [k for k, d in enumerate(model.dofs) if d.segment == 1 and d.kind == "R"]
    euler_span = np.degrees(np.ptp(np.unwrap(q[:, wrist], axis=0), axis=0)).max()
    assert euler_span > 90.0  # the Euler angles swing although the wrist barely moves
    (rng_deg,) = joint_ranges(model, q)["wrist"]
    # reference (rounded to 0.01 deg): twice the 95 % quantile of the angle from the mean rotation
    ref = 2 * np.degrees(np.quantile((R.mean().inv() * R).magnitude(), 0.95))
    assert abs(rng_deg - ref) < 0.006 and rng_deg < 12.0


def test_still_wrist_near_gimbal_lock_is_reported_as_barely_moving():
    model = _wrist_model()
    rng = np.random.default_rng(1)
    q, _ = _poses_near_gimbal_lock(model, 300, 1.0, rng)
    x = marker_positions(model, model.theta_center, q)
    # hand markers move by a few mm at most relative to the forearm
    y = x + rng.normal(0.0, 0.5, size=x.shape)
    est = MarkerEstimator(model, rng=np.random.default_rng(0), n_iter=30).fit(
        MarkerData(y, model.marker_names, 100.0, "mm"))
    (r,) = est.identifiability_["joint_range_deg"]["wrist"]
    assert r < 5.0
    assert any("moved less than" in w.message for w in est.warnings_)
