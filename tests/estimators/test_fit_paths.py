"""The marker fit gives the same numbers on the compiled and the numpy kinematics (fixed data, fixed seeds)."""

from pathlib import Path

import numpy as np
import pytest

from skelid.estimators.joint import joint_fit, smoothed_bias
from skelid.estimators.pose import track_poses
from skelid.model import _fk_kernel, load_model
from skelid.model.kinematics import Workspace

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
needs_kernel = pytest.mark.skipif(not _fk_kernel.AVAILABLE,
                                  reason="the compiled kinematics are turned off (SKELID_NUMBA=0)")


@needs_kernel
def test_lower_limb_fit_steps_and_bias_agree_on_both_kinematics_paths(shared_data, monkeypatch):
    from skelid.estimators.base import marker_array
    from skelid.io import read_markers

    model = load_model(EXAMPLES / "lower_limb.toml")
    y, rate = marker_array(model, read_markers(shared_data / "opensim-subject01" / "subject01_walk1.trc"), None)
    y = y[:40]
    q0, _ = track_poses(model, model.theta_center, y, np.random.default_rng(0), stride=4)

    def run():
        ws = Workspace(model)
        fit = joint_fit(model, y, model.theta_center, q0, n_iter=5, rate=rate, cutoff=6.0, ws=ws)
        return fit, ws

    fit, ws = run()
    assert ws.fk_tables is not False  # the compiled kinematics were used
    y_used = np.where(fit.frames_used[:, None, None], y, np.nan)
    sigma2 = float(fit.rss / fit.n_obs)
    bias = smoothed_bias(model, y_used, fit.theta, fit.pose, sigma2, fit.penalty)
    with monkeypatch.context() as mp:
        mp.setattr(_fk_kernel, "AVAILABLE", False)
        fit0, ws0 = run()
        bias0 = smoothed_bias(model, y_used, fit.theta, fit.pose, sigma2, fit.penalty)  # at the same point
    assert ws0.fk_tables is None  # the numpy path
    sd = np.sqrt(np.diag(np.linalg.inv(fit0.info)) * sigma2)
    assert fit.n_iter == fit0.n_iter == 5
    # five Levenberg-Marquardt steps from the same start: the same iterates up to rounding
    assert np.all(np.abs(fit.theta - fit0.theta) <= 1e-6 * sd)
    np.testing.assert_allclose(fit.info, fit0.info, rtol=1e-9, atol=1e-9 * np.abs(fit0.info).max())
    # the bias's finite differences of the Jacobians at one point
    assert np.all(np.abs(bias - bias0) <= 1e-7 * sd)
