"""The typed result of a fit: one object every estimator returns and every reader takes.

A fit of a model with parameters ``theta (P,)`` to a trial gives, per parameter,
a point estimate, a standard deviation and a 95 % interval; per derived
quantity (joint-to-joint lengths) the same; the marker noise level ``sigma``;
the frame counts; diagnostics; and structured warnings::

    FitResult
    ├── method, settings, provenance
    ├── parameters : {name: ParameterEstimate}     (the model's parameters, nothing else)
    ├── derived    : {name: ParameterEstimate}     (lengths and other functions of theta)
    ├── noise      : NoiseEstimate                 (sigma, its interval, per-marker levels)
    ├── frames     : FrameCounts                   (total, used, dropped, skipped by reason)
    ├── diagnostics: {key: JSON value}             (identifiability, counting, residual structure, ...)
    ├── warnings   : (Warning(code, message, parameters), ...)
    └── arrays     : {key: ndarray}                (poses, residuals, samples, ... -> arrays.npz)

Parameter names live in their own mapping, so a parameter may be called
``sigma``, ``warnings`` or ``lengths`` without colliding with anything. New
outputs (per-marker noise, per-trial estimates, jackknife sd, sensitivity
spread) go into ``diagnostics``, ``noise.per_marker`` or
``ParameterEstimate.extra``, never as new top-level fields.

:mod:`skelid.io.results` writes and reads a result (``result.json`` with a
``schema_version`` plus ``arrays.npz``); the format is documented in
``docs/result-format.md``.

Examples
--------
>>> p = ParameterEstimate("sigma", "mm", map=250.0, mean=250.1, sd=2.0, interval=(246.2, 254.0))
>>> r = FitResult("marker", parameters={"sigma": p}, noise=NoiseEstimate(15.0))
>>> r.parameters["sigma"].mean, r.noise.sigma
(250.1, 15.0)
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from skelid.errors import SettingError  # a ValueError too

#: the statuses a parameter can have
STATUSES = ("identified", "placement", "poor", "unidentified", "prior", "on-bound")


@dataclass(frozen=True)
class ParameterEstimate:
    """What the data say about one parameter (or one derived quantity).

    Parameters
    ----------
    name : str
    unit : str
        ``"mm"`` (the model's length unit), ``"deg"``, ...
    map, mean, sd : float
        Most probable value, posterior mean and standard deviation (NaN if unknown).
    interval : (float, float)
        Central 95 % interval.
    crlb_sd : float or None
        Cramér-Rao bound on the standard deviation, where the estimator computes one.
    status : {'identified', 'placement', 'poor', 'unidentified', 'prior', 'on-bound'}
        ``placement``: the value follows from the markers' nominal placement on their segments
        rather than from motion (one still pose would give as much precision; a segment length
        between markers, a joint centre from a standing trial), so it is only as good as that
        placement. ``prior``: the data add nothing and the value is the prior's. ``on-bound``: the fit's
        optimum sits on (or beyond) a bound of the prior's support; the point reported is on
        the bound, never outside it (the unbounded value is in ``extra['beyond_bound']``).
    extra : mapping
        Estimator-specific numbers (``bias_removed``, ``crlb_sd_motion_model``, ``jackknife_sd``, ...),
        JSON values only.
    """

    name: str
    unit: str
    map: float
    mean: float
    sd: float
    interval: tuple[float, float]
    crlb_sd: float | None = None
    status: str = "identified"
    extra: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        if self.status not in STATUSES:
            raise SettingError(f"status must be one of {', '.join(STATUSES)}, got {self.status!r}")
        lo, hi = self.interval
        object.__setattr__(self, "interval", (float(lo), float(hi)))
        for f in ("map", "mean", "sd"):
            object.__setattr__(self, f, float(getattr(self, f)))
        if self.crlb_sd is not None:
            object.__setattr__(self, "crlb_sd", float(self.crlb_sd))
        object.__setattr__(self, "extra", dict(self.extra))

    @property
    def width(self) -> float:
        """Width of the 95 % interval."""
        return self.interval[1] - self.interval[0]


@dataclass(frozen=True)
class Warning:  # the name the result format uses (also exported as FitWarning)
    """A problem the user should read, with the parameters it concerns.

    Parameters
    ----------
    code : str
        Short slug (``not-converged``, ``poorly-identified``, ``soft-tissue-artefact``, ...),
        stable across versions so that a program can test for it.
    message : str
        One sentence for a person.
    parameters : tuple of str
        Names of the parameters the warning concerns (empty: the whole fit).
    """

    code: str
    message: str
    parameters: tuple[str, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "parameters", tuple(str(p) for p in self.parameters))

    def __str__(self) -> str:
        return self.message


#: the same class under a name that does not shadow Python's built-in ``Warning``
FitWarning = Warning


@dataclass(frozen=True)
class NoiseEstimate:
    """The marker noise level.

    Parameters
    ----------
    sigma : float
        Standard deviation of a marker coordinate (model units).
    interval : (float, float) or None
        Its 95 % interval (None when not estimated).
    fixed : bool
        Whether ``sigma`` was given by the user rather than estimated.
    per_marker : mapping of str to float
        Noise level of each marker, where the estimator has one.
    extra : mapping
        Other numbers (``white``: the level from frame-to-frame differences, ...).
    """

    sigma: float
    interval: tuple[float, float] | None = None
    fixed: bool = False
    per_marker: Mapping[str, float] = field(default_factory=dict)
    extra: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "sigma", float(self.sigma))
        if self.interval is not None:
            lo, hi = self.interval
            object.__setattr__(self, "interval", (float(lo), float(hi)))
        object.__setattr__(self, "per_marker", {str(k): float(v) for k, v in self.per_marker.items()})
        object.__setattr__(self, "extra", dict(self.extra))


@dataclass(frozen=True)
class FrameCounts:
    """How many frames entered the fit.

    Parameters
    ----------
    total : int
        Frames in the trial.
    used : int
        Frames that informed the estimate.
    skipped : mapping of str to int
        Frames left out, by reason (``too_few_coordinates``, ``pose_not_fixed``, ``no_solution``, ...).
    """

    total: int
    used: int
    skipped: Mapping[str, int] = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "total", int(self.total))
        object.__setattr__(self, "used", int(self.used))
        object.__setattr__(self, "skipped", {str(k): int(v) for k, v in self.skipped.items()})

    @property
    def dropped(self) -> int:
        """Frames that did not inform the estimate."""
        return self.total - self.used


@dataclass(frozen=True)
class JointMisfit:
    """A joint whose model cannot follow the data, and what was done about it.

    Read from ``diagnostics["model_misfit"]`` by :attr:`FitResult.misfit` (so it round-trips
    with the result file).

    Parameters
    ----------
    joint, segment : str
        The joint and its child segment.
    log10_p : float
        The misfit test's tail probability (:func:`skelid.estimators.checks.misfit.model_misfit`).
    rms : float
        Root-mean-square size of the angle-driven pattern the child's markers share (model units).
    remedy : str or None
        The relaxed joint to fit instead (``skelid.model.variants.moving_centre(model, 'knee')``).
    widened : tuple of str
        Parameters whose interval was widened to cover the relaxed model's fit.
    relaxed_mean, relaxed_sd : mapping of str to float
        The relaxed model's estimate of the model's parameters and their sd (empty when no
        relaxed model was fitted).
    """

    joint: str
    segment: str
    log10_p: float
    rms: float
    remedy: str | None = None
    widened: tuple[str, ...] = ()
    relaxed_mean: Mapping[str, float] = field(default_factory=dict)
    relaxed_sd: Mapping[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class FitResult:
    """Everything a fit produced, typed.

    Parameters
    ----------
    method : str
        Registered estimator name (``marker``, ``paper``, ...).
    parameters : mapping of str to ParameterEstimate
        One entry per model parameter, in model order.
    derived : mapping of str to ParameterEstimate
        Derived quantities (joint-to-joint lengths).
    noise : NoiseEstimate or None
    frames : FrameCounts or None
    diagnostics : mapping
        JSON values: identifiability, counting, residual structure, convergence, sampler record, ...
    warnings : tuple of Warning
    settings : mapping
        The estimator's settings (JSON values).
    provenance : mapping
        Versions, command, time (JSON values).
    arrays : mapping of str to ndarray
        Per-frame and per-sample arrays (poses, residuals, samples); written to ``arrays.npz``.
    """

    method: str
    parameters: Mapping[str, ParameterEstimate] = field(default_factory=dict)
    derived: Mapping[str, ParameterEstimate] = field(default_factory=dict)
    noise: NoiseEstimate | None = None
    frames: FrameCounts | None = None
    diagnostics: Mapping[str, Any] = field(default_factory=dict)
    warnings: tuple[Warning, ...] = ()
    settings: Mapping[str, Any] = field(default_factory=dict)
    provenance: Mapping[str, Any] = field(default_factory=dict)
    arrays: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        for name in ("parameters", "derived"):
            table = dict(getattr(self, name))
            for key, p in table.items():
                if not isinstance(p, ParameterEstimate) or p.name != key:
                    raise SettingError(f"{name}[{key!r}] must be a ParameterEstimate named {key!r}")
            object.__setattr__(self, name, table)
        object.__setattr__(self, "warnings", tuple(
            w if isinstance(w, Warning) else Warning("note", str(w)) for w in self.warnings))
        arrays = {}
        for k, v in self.arrays.items():
            a = np.array(v)  # own copy, read-only
            a.setflags(write=False)
            arrays[str(k)] = a
        object.__setattr__(self, "arrays", arrays)
        for name in ("diagnostics", "settings", "provenance"):
            object.__setattr__(self, name, dict(getattr(self, name)))

    # ---------------------------------------------------------------- views
    @property
    def names(self) -> tuple[str, ...]:
        """Parameter names, in model order."""
        return tuple(self.parameters)

    def values(self, field_name: str = "mean") -> np.ndarray:
        """``(P,)`` array of one field (``map``, ``mean``, ``sd``, ``crlb_sd``) over the parameters."""
        out = [getattr(p, field_name) for p in self.parameters.values()]
        return np.array([math.nan if v is None else v for v in out], float)

    @property
    def misfit(self) -> dict[str, JointMisfit]:
        """Joints flagged as model misfit (empty when none was, or the method does not test it)."""
        out = {}
        for j, v in (self.diagnostics.get("model_misfit") or {}).items():
            if not v.get("flagged"):
                continue
            rel = v.get("relaxed") or {}
            out[j] = JointMisfit(j, v["segment"], float(v["log10_p"]), float(v["rms"]), rel.get("remedy"),
                                 tuple(rel.get("widened", ())), dict(rel.get("theta") or {}),
                                 dict(rel.get("sd") or {}))
        return out

    def warnings_for(self, name: str) -> tuple[Warning, ...]:
        """The warnings that concern parameter ``name``."""
        return tuple(w for w in self.warnings if name in w.parameters)

    def replace(self, **changes) -> FitResult:
        """A copy with some fields changed (the result itself never changes)."""
        return replace(self, **changes)


@dataclass(frozen=True)
class FitRun:
    """One run of ``skelid fit``: the results of each method on one trial, and what they share.

    Parameters
    ----------
    results : mapping of str to FitResult
        By method name.
    context : mapping
        JSON values shared by the methods: ``model``, ``data``, ``units``, ``frames_total``,
        ``data_overview``, ``model_parameters``, ``provenance`` (command, versions), ``truth``, ...
    warnings : tuple of Warning
        Every warning of the run (reading the data, and each method's), each once.
    arrays : mapping of str to ndarray
        Arrays shared by the methods: ``markers (F, M, D)`` in model units, ``marker_names (M,)``, ...
    """

    results: Mapping[str, FitResult] = field(default_factory=dict)
    context: Mapping[str, Any] = field(default_factory=dict)
    warnings: tuple[Warning, ...] = ()
    arrays: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        results = dict(self.results)
        for k, r in results.items():
            if not isinstance(r, FitResult):
                raise SettingError(f"results[{k!r}] must be a FitResult")
        object.__setattr__(self, "results", results)
        object.__setattr__(self, "context", dict(self.context))
        object.__setattr__(self, "warnings", tuple(
            w if isinstance(w, Warning) else Warning("note", str(w)) for w in self.warnings))
        arrays = {}
        for k, v in self.arrays.items():
            a = np.array(v)
            a.setflags(write=False)
            arrays[str(k)] = a
        object.__setattr__(self, "arrays", arrays)
