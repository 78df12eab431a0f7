"""The estimators by method name, and building one from command-line options.

Each estimator class declares its settings (``settings``: a tuple of
:class:`~skelid.estimators.base.Setting`); a setting with a ``cli`` name is set by
that ``skelid fit`` option. Building an estimator passes exactly the options its class
declares: no signature inspection, no special cases by name.

Examples
--------
>>> from skelid.simulate import builtin_model
>>> est = make_estimator("marker", builtin_model("case-a"), {"sigma": 15.0, "cutoff": 6.0})
>>> est.sigma, est.cutoff
(15.0, 6.0)
>>> names()
('marker', 'paper', 'marker-grid', 'marker-smc')
"""

from __future__ import annotations

from collections.abc import Mapping

from skelid.errors import ModelError
from skelid.model.description import Model

DEFAULT_METHOD = "marker"


def estimators() -> dict[str, type]:
    """Estimator classes by method name (the class's ``name``)."""
    from skelid.estimators.marker import MarkerEstimator
    from skelid.estimators.online.grid import MarkerGridFilter
    from skelid.estimators.paper import PaperFilter
    from skelid.estimators.sampler import SamplerEstimator

    return {cls.name: cls for cls in (MarkerEstimator, PaperFilter, MarkerGridFilter, SamplerEstimator)}


def names() -> tuple[str, ...]:
    return tuple(estimators())


def estimator_class(name: str) -> type:
    table = estimators()
    if name not in table:
        raise ModelError(f"unknown method {name!r}", f"use one of: {', '.join(table)}")
    return table[name]


def cli_settings(name: str) -> dict[str, str]:
    """``{option: setting}`` of the command-line options method ``name`` takes."""
    return {s.cli: s.name for s in estimator_class(name).settings if s.cli}


def settings_from_options(cls: type, options: Mapping, method: str) -> dict:
    """The settings of estimator class ``cls`` that the given ``skelid fit`` options set.

    Parameters
    ----------
    cls : type
        An estimator class with declared ``settings`` (a registered one, or the several-trial
        :class:`~skelid.estimators.multitrial.MultiTrialEstimator`).
    options : mapping
        ``{option: setting value}`` of the options given (every key counts as given; ``cutoff``
        None is "no motion model").
    method : str
        The method name, for the message.

    Returns
    -------
    dict
        ``{setting: value}``.

    Raises
    ------
    SettingError
        An option given that ``cls`` does not declare (it would be ignored): one line naming it.

    Examples
    --------
    >>> from skelid.estimators.marker import MarkerEstimator
    >>> settings_from_options(MarkerEstimator, {"cutoff": None, "noise": "per_marker"}, "marker")
    {'cutoff': None, 'noise': 'per_marker'}
    """
    from skelid.errors import SettingError

    declared = {s.cli: s.name for s in cls.settings if s.cli}
    for opt in options:
        if opt not in declared:
            takes = [n for n, c in estimators().items() if opt in {s.cli for s in c.settings}]
            raise SettingError(f"--{opt.replace('_', '-')} has no effect with --method {method}: the method does "
                               "not use it", f"leave --{opt.replace('_', '-')} out"
                               + (f", or use --method {' or '.join(takes)}" if takes else ""))
    return {declared[opt]: v for opt, v in options.items()}


def make_estimator(name: str, model: Model, options: Mapping | None = None, **settings):
    """Estimator ``name`` for ``model``, with the command-line ``options`` it declares and ``settings``.

    An option the method does not declare, or that is None, is left out (the
    method's default applies); the settings are checked at once, so a bad value
    fails before any data are read.

    Raises
    ------
    ModelError
        Unknown method.
    SettingError
        A setting the estimator cannot use.
    """
    from skelid.estimators.base import check_settings

    cls = estimator_class(name)
    kw = {setting: options[opt] for opt, setting in cli_settings(name).items()
          if options and options.get(opt) is not None}
    est = cls(model, **kw, **settings)
    check_settings(est)
    return est
