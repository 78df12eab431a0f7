"""The marker-space estimator: joint fit, bias removed, CRLB, sigma, honest interval.

Steps (see :mod:`skelid.estimators.joint` for the equations):

1. poses tracked at the prior centre, then joint least squares over ``theta``
   and every pose (Levenberg-Marquardt with the Schur complement);
2. noise level ``sigma^2 = RSS / (n_obs - Q T - P)`` with a chi-square interval,
   or the user's value;
3. second-order (Box) bias computed at the estimate and subtracted;
4. covariance ``sigma^2 S^{-1}`` (the Cramér-Rao bound at the estimate), or,
   when the residuals are serially correlated as soft-tissue artefact makes
   them, a Newey-West covariance that is at least as wide;
5. identifiability from the spectrum of the (prior-scaled) efficient information.

A normal prior on a parameter is combined with the data's Gaussian
approximation (precision-weighted); uniform priors only bound the search.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from skelid.data import MarkerData
from skelid.errors import DataError, IdentifiabilityError
from skelid.estimators.artefact import artefact_covariance
from skelid.estimators.base import prepare, warn_once
from skelid.estimators.joint import (
    box_bias,
    choose_cutoffs,
    frame_scores,
    joint_fit,
    lag1_autocorrelation,
    newey_west,
    row_weights,
    smoothed_bias,
    smoothed_frame_scores,
    usable_frames,
    weighted_terms,
)
from skelid.estimators.likelihood import crlb_sd, efficient_information, frame_terms, pose_fixed
from skelid.estimators.noise import marker_groups, per_marker_fit
from skelid.estimators.pose import track_poses
from skelid.estimators.posterior import GaussianPosterior
from skelid.model.description import Model
from skelid.model.kinematics import joint_distances, marker_positions

NUMERICAL_RESIDUAL = 1e-6  # residual rms, relative to the model's size, that is only rounding
STA_AUTOCORRELATION = 0.25  # mean lag-1 residual autocorrelation that flags soft-tissue artefact
MIN_AUTO_CUTOFF = 6.0  # Hz: the usual low-pass cutoff for marker data; raised for faster motion
STILL_JOINT_DEG = 5.0  # a joint that moves less than this gives little functional information


def frame_counts(model: Model, y, used=None) -> dict:
    """Per-frame counting: independent coordinates against pose coordinates.

    A frame with ``m`` markers present gives ``m D`` coordinates and costs ``Q``
    pose coordinates; only the surplus ``m D - Q`` can inform ``theta``. Over
    the trial the surplus must exceed ``P``.

    Parameters
    ----------
    y : (T, M, D) float
        Markers, NaN where missing.
    used : (T,) bool, optional
        Frames that entered the fit.
    """
    n = np.isfinite(y).all(axis=-1).sum(axis=-1) * model.dim
    used = n > model.n_pose if used is None else np.asarray(used, bool)
    surplus = n - model.n_pose

    def stats(v):
        return {"min": int(v.min()), "median": float(np.median(v)), "max": int(v.max())} if v.size \
            else {"min": 0, "median": 0.0, "max": 0}

    return {
        "pose_coordinates_per_frame": model.n_pose,
        "marker_coordinates_per_frame": stats(n),
        "surplus_per_frame": stats(surplus),
        "frames_with_no_surplus": int((surplus <= 0).sum()),
        "frames_used": int(used.sum()),
        "surplus_total": int(surplus[used].sum()),
        "parameters": model.n_params,
    }


def joint_motion(model: Model, pose, used=None) -> dict:
    """Range of every joint rotation but the root's (degrees; central 95 % of the frames).

    One-axis joints: the angle about its circular mean (2.5 to 97.5 percentile);
    multi-axis joints of a 3-D model: the rotation angle from the mean rotation
    (:func:`skelid.estimators.checks.joint_ranges`), free of gimbal artefacts.

    Functional information about a joint (its centre, its axis) comes only
    from the joint moving; a range of a few degrees means little information.
    """
    from skelid.estimators.checks import joint_ranges

    return joint_ranges(model, pose, used)


def identifiability(model: Model, info: np.ndarray, sigma: float, rel_tol: float = 1e-9,
                    y=None, pose=None, used=None) -> dict:
    """Which parameters (and combinations) the data inform.

    Parameters are scaled by their prior width so that the spectrum is unit-free.
    A direction whose scaled information is below ``rel_tol`` times the largest
    is unidentifiable; a parameter whose bound exceeds a quarter of its prior
    width is poorly identified.

    Parameters
    ----------
    info : (P, P) float
        Efficient information for unit noise.
    sigma : float
        Noise standard deviation.
    y : (T, M, D) float, optional
        Markers, for the per-frame counting.
    pose : (T, Q) float, optional
        Fitted poses, for the joints' range of motion.
    used : (T,) bool, optional
        Frames that entered the fit.

    Returns
    -------
    dict with ``table`` (one row per parameter), ``null`` (unidentifiable
    combinations as ``{name: coefficient}``), and with ``y``/``pose`` given,
    ``counting`` (:func:`frame_counts`) and ``joint_range_deg`` (:func:`joint_motion`).
    """
    width = np.array([p.prior.upper - p.prior.lower for p in model.parameters])
    scaled = info * np.outer(width, width)
    w, V = np.linalg.eigh(scaled)
    top = max(w.max(), 1e-300)
    null = []
    for k in np.flatnonzero(w <= rel_tol * top):
        v = V[:, k]
        v = v / np.abs(v).max()
        null.append({n: round(float(c), 3) for n, c in zip(model.parameter_names, v, strict=True)
                     if abs(c) > 1e-3})
    sd = np.full(model.n_params, np.nan)
    if not null:
        try:
            sd = np.sqrt(np.clip(np.diag(np.linalg.inv(info)), 0, None)) * sigma
        except np.linalg.LinAlgError:
            pass
    in_null = np.zeros(model.n_params, bool)
    for comb in null:
        for n in comb:
            in_null[model.parameter_names.index(n)] = True
    table = []
    for k, p in enumerate(model.parameters):
        status = "unidentifiable" if in_null[k] else ("poor" if sd[k] > 0.25 * width[k] else "identified")
        table.append({"parameter": p.name, "crlb_sd": None if not np.isfinite(sd[k]) else float(sd[k]),
                      "status": status})
    out = {"table": table, "null": null,
           "condition": float(w.max() / max(w.min(), 1e-300)) if w.size else 1.0}
    if y is not None:
        out["counting"] = frame_counts(model, y, used)
    if pose is not None:
        out["joint_range_deg"] = joint_motion(model, pose, used)
    return out


def null_message(model: Model, null: list[dict]) -> str:
    """The unidentifiable combinations in words."""
    parts = []
    for comb in null:
        if len(comb) == 1:
            parts.append(f"{next(iter(comb))} (no information about it at all)")
        else:
            parts.append(" + ".join(f"{c:g}*{n}" for n, c in comb.items()))
    return "; ".join(parts)


class MarkerEstimator:
    """Bias-corrected joint estimate of the model's parameters from marker coordinates.

    Parameters
    ----------
    model : Model
    sigma : float, optional
        Marker noise standard deviation (model units); estimated if not given.
    bias_correction : bool
        Subtract the second-order bias (default True). False gives the plain
        profile (joint least-squares) estimate.
    robust : {'auto', 'always', 'never'}
        Use the Newey-West covariance when residuals look like soft-tissue
        artefact ('auto'), always, or never.
    rng : numpy.random.Generator, optional
        For the random starts of poses that rigid fits of the segments do not give.
    artefact_rms : float, optional
        Stated root-mean-square soft-tissue artefact of a marker coordinate (model
        units). The covariance it adds to the estimate (the part of the artefact that
        mimics a geometry change, see :mod:`skelid.estimators.artefact`) widens the
        interval. None: no artefact term.
    outlier_threshold : float or None
        Marker positions whose residual distance after a first fit exceeds this
        many robust standard deviations are left out and the fit repeated
        (None: keep every position).
    noise : {'pooled', 'per_marker'}
        One noise level for every marker, or each marker (or declared group) its
        own, estimated from its residuals and used as weights in the fit
        (see :mod:`skelid.estimators.noise`).
    marker_groups : dict of str to list of str, optional
        With ``noise='per_marker'``: markers that share one noise level.

    Attributes
    ----------
    posterior_ : GaussianPosterior
    theta_ : (P,) float
        Final (bias-corrected) estimate.
    theta_profile_ : (P,) float
        Joint least-squares estimate before correction.
    bias_ : (P,) float
        Estimated bias that was subtracted.
    crlb_sd_ : (P,) float
        Cramér-Rao bound (standard deviation) at the estimate.
    sigma_ : float
    sigma_ci_ : (2,) float
    pose_ : (T, Q) float
    residuals_ : (T, M) float
        Residual distance of each marker in each frame (NaN where missing and
        in frames skipped).
    outliers_ : (T, M) bool
        Marker positions left out as outliers (residual distance beyond
        ``outlier_threshold`` robust standard deviations after a first fit).
    frames_skipped_ : dict
        Frames left out because they have no more coordinates than pose
        coordinates, or because their markers do not fix every pose coordinate.
    frames_used_ : (T,) bool
    identifiability_ : dict
    sta_score_ : float
        Mean lag-1 autocorrelation of the residuals.
    cov_plain_ : (P, P) float
        ``sigma^2 S^{-1}``: the data's covariance for white noise.
    cov_data_ : (P, P) float
        The data's covariance used (``cov_plain_``, or the Newey-West one when
        ``widened_``), before any normal prior is combined with it.
    widened_ : bool
        Whether the Newey-West covariance was used.
    cov_ : (P, P) float
        Posterior covariance (``cov_data_`` combined with normal priors).
    y_ : (T, M, D) float
        The markers the final fit used (model order and units; outliers and
        skipped frames NaN).
    marker_sigma_ : (M,) float or None
        Each marker's noise level with ``noise='per_marker'`` (NaN without data).
    marker_weights_ : (M,) float or None
        The weights of the fit (``sigma_^2 / marker_sigma_^2`` up to rounding).
    warnings_ : list of str
    """

    name = "marker"
    #: a one-parameter fit that ends on a prior bound is an error (its normal posterior would
    #: straddle the bound); an estimator that can represent a posterior against a bound turns it off
    bound_is_error = True

    def __init__(self, model: Model, sigma: float | None = None, cutoff: float | str | None = "auto",
                 bias_correction: str = "auto", n_boot: int = 10, robust: str = "auto",
                 rng: np.random.Generator | None = None, n_iter: int = 100, rate: float | None = None,
                 outlier_threshold: float | None = 8.0, artefact_rms: float | None = None,
                 noise: str = "pooled", marker_groups: dict | None = None):
        self.model = model
        self.sigma = sigma
        self.cutoff = cutoff
        self.bias_correction = bias_correction
        self.n_boot = n_boot
        self.robust = robust
        self.rng = rng
        self.n_iter = n_iter
        self.rate = rate
        self.outlier_threshold = outlier_threshold
        self.artefact_rms = artefact_rms
        self.noise = noise
        self.marker_groups = marker_groups

    def fit(self, data: MarkerData | np.ndarray, theta0=None, pose0=None) -> MarkerEstimator:
        """Fit a whole trial; ``theta0``/``pose0`` optionally give the starting point."""
        model = self.model
        rate = data.rate if isinstance(data, MarkerData) else self.rate
        cutoff = self.cutoff if (self.cutoff and rate) else None
        if isinstance(cutoff, int | float) and cutoff >= rate / 2:
            cutoff = None  # no smoothing at or above the Nyquist frequency
        if model.n_params == 0:
            raise IdentifiabilityError(f"model {model.name!r} has no [[parameters]] to estimate",
                                       "add a [[parameters]] table")
        y = prepare(model, data) if isinstance(data, MarkerData) else np.asarray(data, float)
        self.warnings_ = []
        rng = self.rng if self.rng is not None else np.random.default_rng(0)
        theta0 = model.theta_center if theta0 is None else np.asarray(theta0, float)
        bounds = (np.array([p.prior.lower for p in model.parameters]),
                  np.array([p.prior.upper for p in model.parameters]))
        if pose0 is None:
            stride = max(1, int(rate // 25)) if rate else 1  # track at about 25 Hz, interpolate between
            pose0, _ = track_poses(model, theta0, y, rng, stride=stride)
        # a frame whose markers do not fix every pose coordinate is skipped (and counted)
        _, Jq0, _ = frame_terms(model, theta0, pose0, y)
        fixed = pose_fixed(Jq0)
        if not fixed.any():
            raise IdentifiabilityError(
                f"no frame's markers fix the pose of model {model.name!r}: "
                f"{_undetermined(model, Jq0, y)} cannot be seen from the markers",
                "add a marker on that segment or use a joint with fewer axes (hinge, universal)")
        # a first fit without motion model screens glitched markers (a smoother would spread a
        # glitch over its neighbours) and gives the per-frame poses that set the cutoffs
        fit = joint_fit(model, y, theta0, pose0, n_iter=self.n_iter, bounds=bounds, frames=fixed)
        self.outliers_ = np.zeros(y.shape[:2], dtype=bool)
        if self.outlier_threshold is not None:
            out = _outlying_markers(model, y, fit, self.outlier_threshold)
            if out.any():  # drop them (they become missing, not replaced) and fit again
                self.outliers_ = out
                y = np.where(out[..., None], np.nan, y)
                _, Jq0, _ = frame_terms(model, fit.theta, fit.pose, y)
                fixed = pose_fixed(Jq0)
                fit = joint_fit(model, y, fit.theta, fit.pose, n_iter=self.n_iter, bounds=bounds,
                                frames=fixed)
                warn_once(f"{int(out.sum())} marker positions in {int(out.any(axis=1).sum())} frames lie "
                          f"more than {self.outlier_threshold:g} robust standard deviations from the "
                          "fitted model (mislabelled or glitched markers?) and were left out", self.warnings_)
        if isinstance(cutoff, str):  # "auto": per-coordinate cutoffs from the motion, at least 6 Hz
            cutoff = np.maximum(choose_cutoffs(model, fit.pose, fit.frames_used, rate),
                                min(MIN_AUTO_CUTOFF, rate / 2))
        self.cutoff_ = cutoff
        if cutoff is not None:
            # the motion model makes pose branches stick: start from the tracked poses and from the
            # screening fit, and keep the lower penalised cost
            fits = [joint_fit(model, y, th, qq, n_iter=self.n_iter, bounds=bounds, frames=fixed,
                              rate=rate, cutoff=cutoff)
                    for th, qq in ((theta0, pose0), (fit.theta, fit.pose))]
            fit = min(fits, key=lambda f: f.rss + float(f.pose.ravel() @ (f.penalty @ f.pose.ravel())))
        fit, w = self._noise_levels(y, fit, bounds, fixed, rate, cutoff)
        used = fit.frames_used
        n_skip = int((~used).sum())
        self.frames_skipped_ = {"too_few_coordinates": int((~usable_frames(model, y)).sum()),
                                "pose_not_fixed": int((usable_frames(model, y) & ~fixed).sum())}
        if used.sum() == 0:
            raise DataError("no frame has enough markers to fix the pose",
                            "check that the file holds the model's markers")
        if n_skip:
            warn_once(f"{n_skip} of {len(y)} frames have too few markers to fix the pose "
                      "and were skipped", self.warnings_)
        Q, P = model.n_pose, model.n_params
        dof = fit.n_obs - fit.pose_dof - P
        if dof <= 0:
            raise IdentifiabilityError(
                f"{fit.n_obs} marker coordinates cannot inform {P} parameters and "
                f"{Q} pose coordinates per frame (each frame must give more coordinates than pose "
                "coordinates)", "add markers or remove parameters")
        if self.sigma is None:
            sigma2 = fit.rss / dof
            self.sigma_ci_ = np.sqrt(fit.rss / chi2.ppf([0.975, 0.025], dof))
        else:
            sigma2 = float(self.sigma) ** 2
            self.sigma_ci_ = np.array([self.sigma, self.sigma], float)
        self.sigma_ = float(np.sqrt(sigma2))
        ident = identifiability(model, fit.info, self.sigma_, y=y, pose=fit.pose, used=used)
        self.identifiability_ = ident
        if ident["null"]:
            raise IdentifiabilityError(
                f"the data cannot identify {null_message(model, ident['null'])} (no information "
                "about this for this motion and these markers)",
                "fix one of these parameters (remove it from [[parameters]]) or record more varied motion")
        width = bounds[1] - bounds[0]
        pinned = (fit.theta <= bounds[0] + 1e-6 * width) | (fit.theta >= bounds[1] - 1e-6 * width)
        if pinned.any() and model.n_params > 1:
            warn_once(f"parameter(s) {', '.join(np.array(model.parameter_names)[pinned])} ended on a "
                      "bound of their prior interval: the data do not pin them inside it", self.warnings_)
        elif pinned.any() and not self.bound_is_error:
            warn_once(f"parameter {model.parameter_names[0]} ended on a bound of its prior interval: the "
                      "data do not pin it inside it", self.warnings_)
        elif pinned.any():
            k = int(np.flatnonzero(pinned)[0])
            p = model.parameters[k]
            raise IdentifiabilityError(
                f"no solution inside the interval [{p.prior.lower:g}, {p.prior.upper:g}] of parameter "
                f"{p.name}: the best fit sits on the bound {fit.theta[k]:g} {model.units}",
                "widen the parameter's prior bounds or check the model's marker positions")
        for k, row in enumerate(ident["table"]):
            if row["status"] == "poor":
                warn_once(f"parameter {row['parameter']} is poorly identified for this motion "
                          f"(Cramér-Rao sd {row['crlb_sd']:.3g} {_unit(model, k)} is more than a quarter "
                          "of its prior range)", self.warnings_)
        info_inv = np.linalg.inv(fit.info)
        self.theta_profile_ = fit.theta
        # residual structure: soft-tissue artefact shows as slow, correlated residuals
        x = marker_positions(model, fit.theta, fit.pose)
        resid = y - x
        self.residuals_ = np.where(used[:, None], np.linalg.norm(resid, axis=-1), np.nan)
        self.sta_score_ = lag1_autocorrelation(resid, used)
        # residuals at the file's rounding level (noise-free data) are not soft-tissue artefact
        numerical = self.sigma_ <= NUMERICAL_RESIDUAL * float(np.abs(model.nominal_geometry).max())
        flagged = self.sta_score_ > STA_AUTOCORRELATION and not numerical
        # the noise that drives the second-order bias is the white part of the residuals:
        # with slow, correlated residuals (soft-tissue artefact, model misfit) it is
        # estimated from frame-to-frame differences, which a slow drift barely touches
        dr = np.diff(resid if w is None else resid * np.sqrt(w)[:, None], axis=0)[used[1:] & used[:-1]]
        self.sigma_white_ = float(np.sqrt(0.5 * np.nanmean(dr**2))) if dr.size else self.sigma_
        sigma2_bias = min(sigma2, self.sigma_white_**2) if flagged else sigma2
        method = self.bias_correction
        if method is True or method == "auto":
            method = "box"
        if method == "box" and fit.penalty is None:
            self.bias_ = box_bias(model, y[used], fit.theta, fit.pose[used], sigma2_bias, weights=w)
        elif method == "box":
            self.bias_ = smoothed_bias(model, np.where(used[:, None, None], y, np.nan), fit.theta,
                                       fit.pose, sigma2_bias, fit.penalty, weights=w)
        elif method == "bootstrap":
            self.bias_ = self._bootstrap_bias(y, fit, np.sqrt(sigma2), rate, cutoff, bounds, rng)
        elif method is False or method == "none":
            self.bias_ = np.zeros(P)
        else:
            raise ValueError("bias_correction must be 'auto', 'box', 'bootstrap' or 'none'")
        self.bias_method_ = method
        theta = fit.theta - self.bias_
        cov = sigma2 * info_inv
        self.crlb_motion_sd_ = np.sqrt(np.diag(cov))
        # the bound with every pose a free unknown (no motion model), at the estimate
        _, Jq_u, Jt_u = weighted_terms(model, fit.theta, fit.pose[used], y[used], row_weights(w, y[used]))
        self.crlb_sd_ = crlb_sd(efficient_information(Jq_u, Jt_u, self.sigma_))
        if flagged:
            warn_once(f"residuals are serially correlated (lag-1 autocorrelation "
                      f"{self.sta_score_:.2f}): they look like soft-tissue artefact, so the "
                      "interval was widened (Newey-West)", self.warnings_)
        self.cov_plain_ = cov
        self.widened_ = self.robust == "always" or (self.robust == "auto" and flagged)
        if self.widened_:
            if fit.penalty is None:
                scores = frame_scores(model, y[used], fit.theta, fit.pose[used], weights=w)
            else:
                scores = smoothed_frame_scores(model, np.where(used[:, None, None], y, np.nan),
                                               fit.theta, fit.pose, fit.penalty, weights=w)[used]
            lags = _bandwidth(self.sta_score_, len(scores))
            cov_nw = info_inv @ newey_west(scores, lags) @ info_inv
            cov = cov_nw if np.all(np.diag(cov_nw) >= np.diag(cov)) else np.maximum(cov, cov_nw)
        # the part of a soft-tissue artefact that mimics a geometry change leaves no residual: with its
        # size stated, its effect on the estimate is added (a random-effect model of the artefact)
        self.cov_artefact_ = np.zeros((P, P))
        if self.artefact_rms:
            self.cov_artefact_ = artefact_covariance(
                model, np.where(used[:, None, None], y, np.nan), fit.theta, fit.pose, fit.penalty,
                float(self.artefact_rms), used)
            cov = cov + self.cov_artefact_
        self.cov_data_ = cov
        theta, cov = _combine_normal_priors(model, theta, cov)
        self.cov_ = cov
        self.theta_ = theta
        self.pose_ = fit.pose
        self.y_ = np.where(used[:, None, None], y, np.nan)
        self.frames_used_ = used
        self.fit_info_ = fit
        self.posterior_ = GaussianPosterior(model.parameter_names, theta, cov)
        # the final interval (widened for correlated residuals) also decides "poor"
        sd_post = self.posterior_.sd
        for k, row in enumerate(ident["table"]):
            p = model.parameters[k]
            row["sd"] = float(sd_post[k])
            if row["status"] == "identified" and sd_post[k] > 0.25 * (p.prior.upper - p.prior.lower):
                row["status"] = "poor"
                warn_once(f"parameter {p.name} is poorly identified for this motion (sd "
                          f"{sd_post[k]:.3g} {_unit(model, k)} is more than a quarter of its prior range)",
                          self.warnings_)
        functional = {p.target for p in model.parameters if p.kind in ("joint_centre", "axis_direction")}
        still = [j for j, r in ident.get("joint_range_deg", {}).items()
                 if j in functional and max(r) < STILL_JOINT_DEG]
        if still:
            warn_once(f"joint(s) {', '.join(still)} moved less than {STILL_JOINT_DEG:g} degrees: their "
                      "centres and axes are informed only by tiny motions (a static trial cannot "
                      "locate a joint functionally)", self.warnings_)
        lengths, grad = joint_distances(model, theta)
        sd_len = np.sqrt(np.clip(np.einsum("kp,pq,kq->k", grad, cov, grad), 0.0, None))
        self.lengths_ = {name: {"value": float(v), "sd": float(e),
                                "ci95": [float(v - 1.959964 * e), float(v + 1.959964 * e)]}
                         for (name, _), v, e in zip(model.derived_lengths, lengths, sd_len, strict=True)}
        if not fit.converged:
            warn_once("the joint fit stopped before converging; the estimate may be off",
                      self.warnings_)
        for k, p in enumerate(model.parameters):
            if not p.prior.lower <= theta[k] <= p.prior.upper:
                warn_once(f"parameter {p.name} = {theta[k]:.4g} lies outside its prior bounds "
                          f"[{p.prior.lower:g}, {p.prior.upper:g}]", self.warnings_)
        return self

    def _noise_levels(self, y, fit, bounds, fixed, rate, cutoff):
        """Per-marker noise levels and the weighted fit (``noise='per_marker'``), or the fit as it is."""
        self.marker_sigma_ = self.marker_weights_ = self.marker_dof_ = None
        if self.noise == "pooled":
            return fit, None
        if self.noise != "per_marker":
            raise ValueError("noise must be 'pooled' or 'per_marker'")
        model = self.model

        def refit(weights, prev):
            return joint_fit(model, y, prev.theta, prev.pose, n_iter=self.n_iter, bounds=bounds,
                             frames=fixed, rate=rate, cutoff=cutoff, weights=weights)

        groups = marker_groups(model.marker_names, self.marker_groups)
        fit, w, sig, dof, _ = per_marker_fit(model, y, refit, fit, groups)
        self.marker_sigma_, self.marker_weights_, self.marker_dof_ = sig, w, dof
        return fit, w

    def _bootstrap_bias(self, y, fit, sigma, rate, cutoff, bounds, rng):
        """Parametric bootstrap: simulate from the fit, refit, mean shift of the estimate."""
        clean = marker_positions(self.model, fit.theta, fit.pose)
        miss = ~np.isfinite(y)
        shifts = []
        for _ in range(self.n_boot):
            ys = clean + rng.normal(0.0, sigma, size=clean.shape)
            ys[miss] = np.nan
            f = joint_fit(self.model, ys, fit.theta, fit.pose, n_iter=self.n_iter, bounds=bounds,
                          rate=rate, cutoff=cutoff)
            shifts.append(f.theta - fit.theta)
        return np.mean(shifts, axis=0)

    def result(self) -> dict:
        """JSON-ready summary."""
        out = {"frames_used": int(self.frames_used_.sum()),
               "frames_dropped": int((~self.frames_used_).sum()),
               "frames_skipped": dict(self.frames_skipped_),
               "outlying_marker_positions": int(self.outliers_.sum())}
        summ = self.posterior_.summary()
        for k, n in enumerate(self.model.parameter_names):
            summ[n]["crlb_sd"] = float(self.crlb_sd_[k])
            summ[n]["crlb_sd_motion_model"] = float(self.crlb_motion_sd_[k])
            summ[n]["bias_removed"] = float(self.bias_[k])
        out.update(summ)
        out["sigma"] = {"value": self.sigma_, "ci95": [float(v) for v in self.sigma_ci_],
                        "fixed": self.sigma is not None, "white": self.sigma_white_}
        if self.marker_sigma_ is not None:
            ok = np.isfinite(self.marker_sigma_)  # a marker without data has no level
            names = np.array(self.model.marker_names)[ok]
            out["sigma"]["per_marker"] = dict(zip(names.tolist(), self.marker_sigma_[ok].tolist(), strict=True))
            out["sigma"]["per_marker_dof"] = dict(zip(names.tolist(), self.marker_dof_[ok].tolist(), strict=True))
        if self.lengths_:
            out["lengths"] = self.lengths_
        out["cutoff_hz"] = None if self.cutoff_ is None else np.atleast_1d(self.cutoff_).tolist()
        out["identifiability"] = self.identifiability_["table"]
        out["counting"] = self.identifiability_.get("counting")
        out["joint_range_deg"] = self.identifiability_.get("joint_range_deg")
        out["residual_autocorrelation"] = self.sta_score_
        if self.artefact_rms:
            out["artefact"] = {"rms": float(self.artefact_rms),
                               "sd_added": [float(v) for v in np.sqrt(np.diag(self.cov_artefact_))]}
        out["warnings"] = list(self.warnings_)
        return out


def _outlying_markers(model: Model, y, fit, threshold: float, n_rounds: int = 4) -> np.ndarray:
    """(T, M) bool: marker positions whose leverage-corrected residual is an outlier.

    See :func:`skelid.estimators.screen.outlying_markers`.
    """
    from skelid.estimators.screen import outlying_markers

    return outlying_markers(model, y, fit.theta, fit.pose, fit.frames_used, threshold, n_rounds)


def _unit(model: Model, k: int) -> str:
    """Unit of parameter ``k``: degrees for axis tilts, the model's length unit otherwise."""
    return "deg" if model.parameters[k].kind == "axis_direction" else model.units


def _undetermined(model: Model, Jq, y) -> str:
    """Names of the pose coordinates that the markers of the best-observed frame do not fix."""
    t = int(np.argmax(np.isfinite(y).all(axis=-1).sum(axis=-1)))
    H = Jq[t].T @ Jq[t]
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    w, V = np.linalg.eigh(H / np.outer(d, d))
    weak = np.abs(V[:, 0]) > 0.3
    names = []
    for k in np.flatnonzero(weak):
        dof = model.dofs[k]
        joint = model.segments[dof.segment].joint
        j = sum(1 for i in range(k) if model.dofs[i].segment == dof.segment)
        names.append(f"{'rotation' if dof.kind == 'R' else 'translation'} {j + 1} of joint {joint.name!r}")
    return ", ".join(names) or "a combination of pose coordinates"


def _bandwidth(rho: float, n: int) -> int:
    """Newey-West lag window from the residual autocorrelation (Andrews' AR(1) rule)."""
    rho = float(np.clip(rho, 0.0, 0.98))
    alpha = 4 * rho**2 / (1 - rho) ** 4 if rho > 0 else 0.0
    L = int(np.ceil(1.1447 * (alpha * n) ** (1 / 3)))
    return int(np.clip(L, 1, max(n // 4, 1)))


def _combine_normal_priors(model: Model, theta, cov):
    prec = np.zeros(model.n_params)
    mean = np.zeros(model.n_params)
    for k, p in enumerate(model.parameters):
        if p.prior.kind == "normal":
            prec[k], mean[k] = 1.0 / p.prior.sd**2, p.prior.mean
    if not prec.any():
        return theta, cov
    A = np.linalg.inv(cov)
    post_cov = np.linalg.inv(A + np.diag(prec))
    return post_cov @ (A @ theta + prec * mean), post_cov
