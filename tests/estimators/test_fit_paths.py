"""The marker fit gives the same numbers on the compiled and the numpy kinematics (fixed data, fixed seeds)."""

from pathlib import Path

import numpy as np
import pytest

from skelid.estimators.fit.joint import joint_fit, smoothed_bias
from skelid.estimators.fit.pose import track_poses
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
    y = y[:30]
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


@needs_kernel
@pytest.mark.parametrize("T, Q", [(200, 4), (40, 18), (30, 1)])
def test_compiled_selected_inversion_equals_the_numpy_sweep(T, Q):
    import scipy.sparse as sp
    from scipy.linalg import cholesky_banded

    from skelid.estimators.fit.joint import _banded_system, _dense_from_banded, _selected_inverse_by_blocks

    rng = np.random.default_rng(T + Q)
    A = rng.normal(size=(T, Q, Q))
    H = A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(Q)
    D3 = sp.diags([-1.0, 3.0, -3.0, 1.0], [0, 1, 2, 3], shape=(T - 3, T))
    ab = _banded_system(H, sp.kron(D3.T @ D3, sp.diags(rng.random(Q) + 0.5)).tocsc())
    u, n = ab.shape[0] - 1, ab.shape[1]
    cb = cholesky_banded(ab, lower=False)
    Ub = np.zeros((n + u, u + 1))
    for d in range(u + 1):
        Ub[:n - d, d] = cb[u - d, d:]
    compiled = _fk_kernel.band_inverse_blocks(Ub, Q, T)
    plain = _selected_inverse_by_blocks(Ub, Q, T)
    np.testing.assert_allclose(compiled, plain, rtol=0, atol=1e-13 * np.abs(plain).max())
    dense = np.linalg.inv(_dense_from_banded(ab))  # and both are the diagonal blocks of the inverse
    idx = np.arange(T)[:, None] * Q + np.arange(Q)
    np.testing.assert_allclose(compiled, dense[idx[:, :, None], idx[:, None, :]], rtol=1e-9,
                               atol=1e-9 * np.abs(plain).max())
