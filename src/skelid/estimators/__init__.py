"""Estimators of model parameters from marker data.

* :class:`PaperFilter` (``paper``): the seed method, per-frame Newton-Raphson and a grid Bayes filter.
* :class:`MarkerEstimator` (``marker``): joint fit of parameters and poses from the marker
  coordinates, motion model, second-order bias removed, Cramér-Rao bound, noise level.
* :class:`MarkerGridFilter` (``marker-grid``): online grid filter with the marker-space likelihood.
"""

from skelid.estimators.marker import MarkerEstimator
from skelid.estimators.online.grid import MarkerGridFilter
from skelid.estimators.paper import ConstraintSystem, PaperFilter
from skelid.estimators.uncertainty.posterior import GaussianPosterior, GridPosterior, SamplePosterior

__all__ = ["ConstraintSystem", "PaperFilter", "MarkerEstimator", "MarkerGridFilter", "GridPosterior",
           "GaussianPosterior", "SamplePosterior"]
