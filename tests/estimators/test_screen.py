"""Outlier screen: residuals standardised by each frame's own residual degrees of freedom."""

import numpy as np
import pytest
from scipy.stats import chi2

from skelid.estimators.checks.outliers import outlying_markers, robust_variance, standardised_residuals
from skelid.estimators.fit.joint import joint_fit
from skelid.simulate import builtin_model, simulate


def _fit(model, trial):
    return joint_fit(model, trial.data.positions, trial.theta, trial.pose, n_iter=50)


def test_standardised_residuals_are_chi_square_with_the_frames_dof():
    """z / sigma^2 follows chi2(dof) marker by marker; in case A a frame's residual has one degree of
    freedom (6 coordinates - 5 pose coordinates), so no marker's block has more than one direction."""
    model = builtin_model("case-a")
    sigma = 2.0
    trial = simulate(model, n_frames=400, sigma=sigma, rng=np.random.default_rng(3))
    fit = _fit(model, trial)
    z, dof = standardised_residuals(model, fit.theta, fit.pose, trial.data.positions)
    assert dof.max() == 1
    ok = dof > 0
    u = chi2.cdf(z[ok] / sigma**2, dof[ok])  # probability integral transform: uniform
    assert abs(u.mean() - 0.5) < 0.05
    assert abs(robust_variance(z, dof) / sigma**2 - 1.0) < 0.15


def test_robust_variance_of_a_chi_square_mixture_is_exact_on_medians():
    """Entries placed exactly at sigma^2 times their chi-square medians give sigma^2 back."""
    dof = np.array([[1, 2, 3], [1, 1, 2]])
    z = 7.0 * chi2.median(dof)
    assert np.isclose(robust_variance(z, dof), 7.0, rtol=1e-6)


def test_clean_case_a_trials_lose_no_position():
    """Pure Gaussian noise: nothing is dropped (the plain distance screen dropped 1-6 per trial)."""
    model = builtin_model("case-a")
    for seed in (0, 1, 2):
        trial = simulate(model, n_frames=300, sigma=15.0, rng=np.random.default_rng(seed))
        fit = _fit(model, trial)
        out = outlying_markers(model, trial.data.positions, fit.theta, fit.pose, fit.frames_used, 8.0)
        assert not out.any()


def test_glitches_in_case_a_are_found():
    model = builtin_model("case-a")
    trial = simulate(model, n_frames=300, sigma=5.0, rng=np.random.default_rng(4))
    y = trial.data.positions.copy()
    fit = _fit(model, trial)
    z, dof = standardised_residuals(model, fit.theta, fit.pose, y)
    # glitch positions where the marker can be checked well
    rng = np.random.default_rng(5)
    cand = np.argwhere(dof > 0)
    bad = cand[rng.choice(len(cand), 5, replace=False)]
    for t, m in bad:
        y[t, m] += 400.0 * np.array([0.6, -0.8])
    fit = joint_fit(model, y, trial.theta, trial.pose, n_iter=50)
    out = outlying_markers(model, y, fit.theta, fit.pose, fit.frames_used, 8.0)
    assert out.sum() >= 5
    assert all(out[t].any() for t, _ in bad)


def test_robust_variance_solves_the_same_equation_as_the_bisection():
    """Brent's root equals the 60-step bisection on the fraction below the chi-square medians."""
    from scipy.special import chdtr
    from scipy.stats import chi2

    rng = np.random.default_rng(3)
    dof = rng.integers(1, 7, size=400).astype(float)
    z = 4.0 * rng.chisquare(dof)
    z[:7] = np.nan
    ok = np.isfinite(z)
    zz, dd = z[ok], dof[ok]
    ratio = zz / chi2.median(dd)
    lo, hi = np.log(ratio.min()), np.log(ratio.max())
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.mean(chdtr(dd, zz / np.exp(mid))) > 0.5 else (lo, mid)
    assert robust_variance(z, dof) == pytest.approx(np.exp(0.5 * (lo + hi)), rel=1e-12)


def test_standardised_residuals_equal_the_dense_hat_matrix_formula():
    """Each marker's block of I - H from its own rows equals the block of the full (M D, M D) matrix."""
    from skelid.estimators.checks.outliers import V_MIN
    from skelid.estimators.fit.likelihood import frame_terms

    model = builtin_model("case-b")
    trial = simulate(model, sigma=5.0, n_frames=30, rng=np.random.default_rng(2))
    y = trial.data.positions.copy()
    y[3, 1] = np.nan
    z, dof = standardised_residuals(model, trial.theta, trial.pose, y)
    r, Jq, _ = frame_terms(model, trial.theta, trial.pose, y)
    T, M, D = y.shape
    H = Jq @ np.linalg.pinv(np.swapaxes(Jq, 1, 2) @ Jq, hermitian=True) @ np.swapaxes(Jq, 1, 2)
    for t in range(T):
        for m in range(M):
            if not np.isfinite(y[t, m]).all():
                assert np.isnan(z[t, m]) and dof[t, m] == 0
                continue
            sl = slice(m * D, (m + 1) * D)
            w, U = np.linalg.eigh(np.eye(D) - H[t, sl, sl])
            keep = w > V_MIN
            assert dof[t, m] == keep.sum()
            assert z[t, m] == pytest.approx(np.sum((U.T @ r[t, sl])[keep] ** 2 / w[keep]), rel=1e-9, abs=1e-12)
