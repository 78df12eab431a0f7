"""Whether a parameter's per-trial estimates change with how far each trial moves a joint.

A segment length is the same in a walk and a squat. Where the trials' own estimates of it grow with
the range through which each trial moves the joint at its end (a thigh that lengthens with the
activity's knee flexion), the model does not follow that joint: a centre that rolls or slides with
flexion, skin that slides with it. The answer then depends on the activity recorded, and the
trials' scatter is not the random effect the several-trial interval assumes.

The test is a random-effects meta-regression of the estimates ``y_k`` (within-trial variances
``v_k``) on the moderator ``x_k``, the joint's range in trial ``k``:

    y_k = a + b x_k + u_k + e_k,   u_k ~ N(0, tau^2),   e_k ~ N(0, v_k),

with ``tau^2`` by the method of moments on the weighted residuals (DerSimonian and Laird's
estimator for meta-regression) and the slope's standard error by Knapp and Hartung's adjustment,
``b / se`` referred to Student's t on ``K - 2`` degrees of freedom: the test of a moderator that
holds its size with few studies (Knapp and Hartung, Statistics in Medicine 2003).
"""

from __future__ import annotations

import numpy as np
from scipy.stats import t as student_t

#: fewest trials for the test (two degrees of freedom for its t)
MIN_TRIALS = 4


def motion_trend(estimates, variances, moderator) -> dict | None:
    """Random-effects meta-regression of per-trial estimates on a moderator, with Knapp-Hartung's test.

    Parameters
    ----------
    estimates, variances, moderator : (K,) float
        Each trial's estimate, its within-trial variance and its moderator (a joint's range).

    Returns
    -------
    dict or None
        ``slope``, ``se``, ``t``, ``dof``, ``p_value`` (two-sided), ``tau`` (the between-trial sd the
        trend leaves), ``change`` (the slope times the moderator's span over the trials); None with
        fewer than :data:`MIN_TRIALS` trials, a moderator that does not vary, or a variance that is
        not positive and finite.

    >>> x = np.array([0.0, 30.0, 60.0, 90.0, 120.0])
    >>> r = motion_trend(400.0 + 0.1 * x + np.array([0.3, -0.2, 0.1, -0.4, 0.2]), np.full(5, 0.25), x)
    >>> round(r["slope"], 2), r["p_value"] < 0.001, r["dof"]
    (0.1, True, 3)
    """
    y, v, x = (np.asarray(a, dtype=float) for a in (estimates, variances, moderator))
    K = y.size
    if K < MIN_TRIALS or not (np.isfinite(y).all() and np.isfinite(x).all() and np.isfinite(v).all()):
        return None
    if (v <= 0).any() or np.ptp(x) <= 1e-12 * max(1.0, float(np.abs(x).max())):
        return None
    X = np.column_stack([np.ones(K), x - x.mean()])
    w = 1.0 / v
    XtW = X.T * w
    P = np.linalg.inv(XtW @ X)
    resid = y - X @ (P @ (XtW @ y))
    q = float(w @ resid**2)
    # the method of moments: E[Q] = (K - 2) + tau^2 trace(W - W X (X^T W X)^-1 X^T W)
    trace = float(w.sum() - np.trace(P @ (XtW * w) @ X))
    tau2 = max(0.0, (q - (K - 2)) / trace) if trace > 0 else 0.0
    ws = 1.0 / (v + tau2)
    XtWs = X.T * ws
    Ps = np.linalg.inv(XtWs @ X)
    beta = Ps @ (XtWs @ y)
    rs = y - X @ beta
    scale = max(float(ws @ rs**2) / (K - 2), 1e-300)  # Knapp-Hartung's factor
    se = float(np.sqrt(scale * Ps[1, 1]))
    t = float(beta[1] / se) if se > 0 else float(np.copysign(np.inf, beta[1]))
    dof = K - 2
    return {"slope": float(beta[1]), "se": se, "t": t, "dof": dof,
            "p_value": float(2.0 * student_t.sf(abs(t), dof)), "tau": float(np.sqrt(tau2)),
            "change": float(beta[1] * np.ptp(x))}
