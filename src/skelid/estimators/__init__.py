"""Estimators of model parameters from marker data."""

from skelid.estimators.paper import ConstraintSystem, PaperFilter
from skelid.estimators.posterior import GaussianPosterior, GridPosterior

__all__ = ["ConstraintSystem", "PaperFilter", "GridPosterior", "GaussianPosterior"]
