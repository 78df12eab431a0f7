"""Posteriors over model parameters.

:class:`GridPosterior` is a discrete posterior on a Cartesian grid of 1-3
parameters, kept as normalised log weights. Bayes' rule for one frame is

.. math:: \\log w_k \\leftarrow \\log w_k + \\ell_t(\\theta_k) - \\log\\sum_j \\exp(\\log w_j + \\ell_t(\\theta_j))

so products of many small likelihoods never underflow. :class:`GaussianPosterior`
is a multivariate normal (a Laplace approximation around a batch estimate).
:class:`SamplePosterior` is a cloud of weighted draws ``(theta_i, W_i)`` (from a
sampler such as :mod:`skelid.estimators.uncertainty.smc`): expectations are weighted sums,
``E f(theta) ~ sum_i W_i f(theta_i)``, so it can hold any shape (skewed, bounded,
curved). All three offer ``map``, ``mean``, ``sd``, ``credible_interval(level)``,
``samples(n, rng)`` and ``summary()`` and are immutable: an update returns a new
object.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.special import logsumexp
from scipy.stats import norm


def _interval_from_cdf(x: np.ndarray, w: np.ndarray, level: float) -> tuple[float, float]:
    """Equal-tailed interval of a discrete distribution on sorted support ``x``.

    The grid value ``x_k`` stands for the cell ``[x_k - h/2, x_k + h/2]``; the
    cumulative distribution is interpolated linearly inside cells so that the
    interval does not snap to grid points.
    """
    a = (1.0 - level) / 2.0
    if x.size == 1:
        return float(x[0]), float(x[0])
    h = np.diff(x)
    edges = np.concatenate([[x[0] - h[0] / 2], x[:-1] + h / 2, [x[-1] + h[-1] / 2]])
    cdf = np.concatenate([[0.0], np.cumsum(w)])
    cdf /= cdf[-1]
    lo = np.interp(a, cdf, edges)
    hi = np.interp(1.0 - a, cdf, edges)
    return float(lo), float(hi)


@dataclass(frozen=True, eq=False)
class GridPosterior:
    """Posterior on the grid ``axes[0] x axes[1] x ...``.

    Parameters
    ----------
    names : tuple of str, length P
    axes : tuple of (K_p,) float arrays
        Candidate values of each parameter.
    log_weights : (K_0, ..., K_{P-1}) float
        Normalised log posterior mass of each grid point.
    n_updates : int
        Frames folded in so far.
    history : tuple of (int, ndarray)
        Snapshots ``(step, log_weights)`` taken at requested steps.
    """

    names: tuple[str, ...]
    axes: tuple[np.ndarray, ...]
    log_weights: np.ndarray
    n_updates: int = 0
    history: tuple = field(default=())

    @classmethod
    def from_log_prior(cls, names, axes, log_prior) -> GridPosterior:
        lw = np.asarray(log_prior, dtype=float)
        if not np.isfinite(lw).any():
            raise ValueError("the prior puts no mass on the grid")
        return cls(tuple(names), tuple(np.asarray(a, float) for a in axes), lw - logsumexp(lw))

    # ------------------------------------------------------------- updates
    def update(self, log_likelihood, snapshot: bool = False) -> GridPosterior:
        """Fold in one frame's log-likelihood (same shape as the grid)."""
        lw = self.log_weights + log_likelihood
        z = logsumexp(lw)
        if not np.isfinite(z):
            raise FloatingPointError("the likelihood is zero on every grid point")
        lw = lw - z
        hist = self.history + ((self.n_updates + 1, lw),) if snapshot else self.history
        return GridPosterior(self.names, self.axes, lw, self.n_updates + 1, hist)

    def with_snapshot(self, step: int) -> GridPosterior:
        return GridPosterior(self.names, self.axes, self.log_weights, self.n_updates,
                             self.history + ((step, self.log_weights),))

    # ------------------------------------------------------------- summaries
    @property
    def weights(self) -> np.ndarray:
        return np.exp(self.log_weights)

    def marginal(self, k: int = 0, log_weights=None) -> np.ndarray:
        """(K_k,) float: marginal posterior mass of parameter ``k``."""
        lw = self.log_weights if log_weights is None else log_weights
        other = tuple(i for i in range(lw.ndim) if i != k)
        return np.exp(logsumexp(lw, axis=other)) if other else np.exp(lw)

    @property
    def map(self) -> np.ndarray:
        """(P,) float: the grid point of highest posterior mass."""
        idx = np.unravel_index(np.argmax(self.log_weights), self.log_weights.shape)
        return np.array([a[i] for a, i in zip(self.axes, idx, strict=True)])

    @property
    def mean(self) -> np.ndarray:
        return np.array([self.marginal(k) @ a for k, a in enumerate(self.axes)])

    @property
    def sd(self) -> np.ndarray:
        m = self.mean
        return np.array(
            [np.sqrt(max(self.marginal(k) @ (a - m[k]) ** 2, 0.0)) for k, a in enumerate(self.axes)]
        )

    def credible_interval(self, level: float = 0.95) -> np.ndarray:
        """(P, 2) float: equal-tailed marginal intervals."""
        return np.array([_interval_from_cdf(a, self.marginal(k), level)
                         for k, a in enumerate(self.axes)])

    def samples(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, P) float: draws, jittered uniformly within each grid cell."""
        w = self.weights.ravel()
        idx = rng.choice(w.size, size=n, p=w / w.sum())
        sub = np.unravel_index(idx, self.log_weights.shape)
        out = np.empty((n, len(self.axes)))
        for k, a in enumerate(self.axes):
            h = a[1] - a[0] if a.size > 1 else 0.0
            out[:, k] = a[sub[k]] + rng.uniform(-h / 2, h / 2, size=n)
        return out

    @property
    def grid_points(self) -> np.ndarray:
        """(K_0 * ... * K_{P-1}, P) float: every grid point, C order."""
        mesh = np.meshgrid(*self.axes, indexing="ij")
        return np.stack([m.ravel() for m in mesh], axis=-1)

    def summary(self, level: float = 0.95) -> dict:
        ci = self.credible_interval(level)
        return {
            n: {"map": float(self.map[k]), "mean": float(self.mean[k]), "sd": float(self.sd[k]),
                "ci95": [float(ci[k, 0]), float(ci[k, 1])]}
            for k, n in enumerate(self.names)
        }


@dataclass(frozen=True, eq=False)
class GaussianPosterior:
    """Multivariate normal posterior ``N(mean, cov)`` over named parameters."""

    names: tuple[str, ...]
    mean: np.ndarray
    cov: np.ndarray
    history: tuple = field(default=())

    @property
    def map(self) -> np.ndarray:
        return self.mean

    @property
    def sd(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))

    def credible_interval(self, level: float = 0.95) -> np.ndarray:
        z = norm.ppf(0.5 + level / 2.0)
        return np.stack([self.mean - z * self.sd, self.mean + z * self.sd], axis=-1)

    def samples(self, n: int, rng: np.random.Generator) -> np.ndarray:
        return rng.multivariate_normal(self.mean, self.cov, size=n, method="eigh")

    def summary(self, level: float = 0.95) -> dict:
        ci = self.credible_interval(level)
        return {
            n: {"map": float(self.mean[k]), "mean": float(self.mean[k]), "sd": float(self.sd[k]),
                "ci95": [float(ci[k, 0]), float(ci[k, 1])]}
            for k, n in enumerate(self.names)
        }


def weighted_quantiles(x: np.ndarray, w: np.ndarray, q) -> np.ndarray:
    """Quantiles of the weighted sample ``x (N,)`` with weights ``w (N,)`` (summing to 1).

    The empirical distribution function is taken at the middle of each
    sample's mass, ``F(x_(i)) = sum_{j<i} w_(j) + w_(i) / 2`` over the sorted
    sample, and interpolated linearly between samples (clamped to the smallest
    and largest sample). With equal weights this is the usual ``(i - 1/2) / N``
    plotting position.

    Parameters
    ----------
    x : (N,) float
    w : (N,) float
    q : float or (K,) float
        Probabilities in [0, 1].

    Returns
    -------
    (K,) float (or a scalar for a scalar ``q``)
    """
    keep = w > 0
    order = np.argsort(x[keep], kind="stable")
    xs, ws = x[keep][order], w[keep][order]
    cdf = np.cumsum(ws) - 0.5 * ws
    cdf /= max(float(ws.sum()), 1e-300)
    return np.interp(q, cdf, xs)


@dataclass(frozen=True, eq=False)
class SamplePosterior:
    """Posterior held as weighted samples ``theta_i`` with normalised weights ``W_i``.

    Parameters
    ----------
    names : tuple of str, length P
    points : (N, P) float
        The samples.
    log_weights : (N,) float, optional
        Log weights (any constant); equal weights if not given. They are
        normalised on construction, ``sum_i exp(log_weights_i) = 1``.
    log_target : (N,) float, optional
        Unnormalised log posterior density at each sample; gives :attr:`map`.
    ess : float, optional
        Effective sample size, when the producer knows better than the
        weights (draws moved by MCMC are correlated); by default Kish's
        ``1 / sum_i W_i^2``.
    history : tuple
        Kept for the interface the other posteriors share (empty).

    Notes
    -----
    The arrays are copied and made read-only, so that the object is immutable.
    ``mean = sum_i W_i theta_i``; ``cov = sum_i W_i (theta_i - mean)(theta_i -
    mean)^T / (1 - sum_i W_i^2)`` (unbiased for independent draws);
    credible intervals are equal-tailed weighted quantiles
    (:func:`weighted_quantiles`) and so stay inside the support of the samples,
    e.g. inside a prior's bounds.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> post = SamplePosterior(("a",), rng.normal(2.0, 0.5, size=(4000, 1)))
    >>> round(float(post.mean[0]), 1), round(float(post.sd[0]), 1)
    (2.0, 0.5)
    """

    names: tuple[str, ...]
    points: np.ndarray
    log_weights: np.ndarray | None = None
    log_target: np.ndarray | None = None
    ess: float | None = None
    history: tuple = field(default=())

    def __post_init__(self):
        pts = np.array(self.points, dtype=float, ndmin=2)
        if pts.ndim != 2 or pts.shape[0] == 0:
            raise ValueError(f"points must be (N, P) with N > 0, got shape {np.shape(self.points)}")
        if pts.shape[1] != len(self.names):
            raise ValueError(f"{pts.shape[1]} columns of points for {len(self.names)} names")
        n = pts.shape[0]
        lw = np.zeros(n) if self.log_weights is None else np.array(self.log_weights, dtype=float)
        if lw.shape != (n,):
            raise ValueError(f"log_weights must be ({n},), got {lw.shape}")
        z = logsumexp(lw)
        if not np.isfinite(z):
            raise ValueError("the weights are all zero (or not finite)")
        lw = lw - z
        lt = None if self.log_target is None else np.array(self.log_target, dtype=float)
        if lt is not None and lt.shape != (n,):
            raise ValueError(f"log_target must be ({n},), got {lt.shape}")
        ess = float(1.0 / np.sum(np.exp(2.0 * lw))) if self.ess is None else float(self.ess)
        for a in (pts, lw, lt):
            if a is not None:
                a.flags.writeable = False
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "points", pts)
        object.__setattr__(self, "log_weights", lw)
        object.__setattr__(self, "log_target", lt)
        object.__setattr__(self, "ess", ess)

    @property
    def weights(self) -> np.ndarray:
        """(N,) float: normalised weights."""
        return np.exp(self.log_weights)

    @property
    def n_samples(self) -> int:
        return self.points.shape[0]

    @property
    def map(self) -> np.ndarray:
        """(P,) float: the sample with the highest ``log_target``.

        Without ``log_target``, the sample of highest density under a weighted
        Gaussian kernel density estimate (Scott's bandwidth, the samples'
        covariance) stands in; the density is evaluated at up to 512 of the
        samples (evenly spaced in their order), so the cost stays ``O(512 N)``.
        """
        if self.log_target is not None and np.isfinite(self.log_target).any():
            return self.points[int(np.argmax(np.where(np.isfinite(self.log_target),
                                                      self.log_target, -np.inf)))].copy()
        cand = np.unique(np.linspace(0, self.n_samples - 1, min(self.n_samples, 512)).astype(int))
        cand = cand[self.log_weights[cand] > -np.inf]
        if cand.size == 0:  # the evenly spaced ones carry no weight: take the heaviest
            cand = np.argsort(-self.log_weights)[:512]
        return self.points[cand[int(np.argmax(self._kde_log_density(self.points[cand])))]].copy()

    def _kde_log_density(self, at: np.ndarray, chunk: int = 256) -> np.ndarray:
        """(K,) float: log density (unnormalised) of the weighted Gaussian KDE at ``at (K, P)``."""
        x = self.points
        p = x.shape[1]
        h2 = (self.ess ** (-1.0 / (p + 4))) ** 2  # Scott's factor, squared
        c = np.atleast_2d(self.cov)
        L = np.linalg.cholesky(c * h2 + 1e-12 * max(float(np.abs(c).max()), 1e-300) * np.eye(p))
        z = np.linalg.solve(L, x.T).T
        za = np.linalg.solve(L, np.asarray(at, float).T).T
        out = np.empty(len(za))
        for a in range(0, len(za), chunk):
            d2 = np.sum((za[a:a + chunk, None, :] - z[None, :, :]) ** 2, axis=-1)
            out[a:a + chunk] = logsumexp(-0.5 * d2 + self.log_weights[None, :], axis=1)
        return out

    @property
    def mean(self) -> np.ndarray:
        """(P,) float: weighted mean."""
        return self.weights @ self.points

    @property
    def cov(self) -> np.ndarray:
        """(P, P) float: weighted covariance (unbiased for independent draws)."""
        w = self.weights
        d = self.points - self.mean
        c = (d * w[:, None]).T @ d
        return c / max(1.0 - float(w @ w), 1e-12)

    @property
    def sd(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))

    def credible_interval(self, level: float = 0.95) -> np.ndarray:
        """(P, 2) float: equal-tailed marginal intervals from weighted quantiles."""
        a = (1.0 - level) / 2.0
        w = self.weights
        return np.array([weighted_quantiles(self.points[:, k], w, [a, 1.0 - a])
                         for k in range(self.points.shape[1])])

    def samples(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, P) float: draws by multinomial resampling of the weighted samples."""
        idx = rng.choice(self.n_samples, size=n, p=self.weights)
        return self.points[idx].copy()

    def summary(self, level: float = 0.95) -> dict:
        ci = self.credible_interval(level)
        m, mean, sd = self.map, self.mean, self.sd
        return {
            n: {"map": float(m[k]), "mean": float(mean[k]), "sd": float(sd[k]),
                "ci95": [float(ci[k, 0]), float(ci[k, 1])]}
            for k, n in enumerate(self.names)
        }
