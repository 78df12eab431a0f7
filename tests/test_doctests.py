"""The runnable examples at the top of the estimator modules and of the result API (run as doctests)."""

import doctest
import importlib
import warnings

import pytest

from skelid.errors import SkelidWarning

MODULES = ["skelid.result", "skelid.io.results", "skelid.registry", "skelid.estimators.paper",
           "skelid.estimators.online.grid", "skelid.estimators.marker", "skelid.estimators.sampler", "skelid.live",
           "skelid.live_health", "skelid.angles", "skelid.estimators.uncertainty.stacking",
           "skelid.estimators.checks.trial_motion"]


@pytest.mark.parametrize("name", MODULES)
def test_module_examples_run(name):
    module = importlib.import_module(name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkelidWarning)
        result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0, f"{name} has no example"
    assert result.failed == 0
