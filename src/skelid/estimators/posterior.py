"""Posteriors over model parameters.

:class:`GridPosterior` is a discrete posterior on a Cartesian grid of 1-3
parameters, kept as normalised log weights. Bayes' rule for one frame is

.. math:: \\log w_k \\leftarrow \\log w_k + \\ell_t(\\theta_k) - \\log\\sum_j \\exp(\\log w_j + \\ell_t(\\theta_j))

so products of many small likelihoods never underflow. :class:`GaussianPosterior`
is a multivariate normal (a Laplace approximation around a batch estimate). Both
offer ``map``, ``mean``, ``sd``, ``credible_interval(level)`` and ``samples(n, rng)``
and are immutable: an update returns a new object.
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
