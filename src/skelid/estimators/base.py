"""What every estimator shares: the contract, its declared settings, and matching data to a model.

The contract (checked for every registered estimator by ``tests/estimators/test_contract.py``):

* ``Estimator(model, **settings)`` only stores the settings; each class declares them in
  ``settings`` (a tuple of :class:`Setting`), which the registry and the command line read;
* ``fit(data, *, progress=None)`` checks the settings (:class:`~skelid.errors.SettingError`
  naming the setting), fits, and returns the estimator; starting values are settings;
* fitted attributes end in ``_`` and share names across estimators: ``frames_used_ (F,) bool``,
  ``sigma_``, ``posterior_``, ``warnings_`` (tuple of :class:`~skelid.result.Warning`), ...;
  none exists before ``fit``;
* ``result()`` returns the typed :class:`~skelid.result.FitResult`
  (:class:`~skelid.errors.NotFittedError` before ``fit``);
* an online estimator also has ``init_state()`` and ``update(state, frame) -> state``, and
  ``fit`` folds ``update`` over the frames.

``data`` is a :class:`~skelid.data.MarkerData`, or an array ``(F, M, D)`` of the model's markers
in model order and units together with the ``rate`` setting (a rate is required, so that an
array never silently loses the motion model).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from skelid.data import MarkerData, check_positions, check_range, unit_scale
from skelid.errors import DataError, ModelError, NotFittedError, SettingError, SkelidWarning
from skelid.model.description import Model
from skelid.result import Warning


# ------------------------------------------------------------------------ settings
@dataclass(frozen=True)
class Setting:
    """One declared estimator setting.

    Parameters
    ----------
    name : str
        Keyword of ``__init__``.
    check : callable
        ``check(value) -> bool``: whether the value is usable.
    allowed : str
        The usable values in words, for the error message.
    cli : str, optional
        The ``skelid fit`` option that sets it (``"sigma"`` for ``--sigma``), if any.
    """

    name: str
    check: Callable[[Any], bool]
    allowed: str
    cli: str | None = None


#: integers a numeric setting takes lie in numpy's int64 range: a larger Python int becomes an object array
INT_RANGE = (-2**63, 2**63 - 1)
#: the largest count a setting takes (iterations, replicates, particles, moves): a larger one is a slip that
#: would overflow the compiled kernels or ask for arrays no memory holds
MAX_COUNT = 10**6


def _number(v) -> bool:
    if isinstance(v, bool) or not isinstance(v, int | float | np.integer | np.floating):
        return False
    if isinstance(v, int) and not INT_RANGE[0] <= v <= INT_RANGE[1]:
        return False
    return math.isfinite(v)


def positive(v) -> bool:
    return _number(v) and v > 0


def positive_or_none(v) -> bool:
    return v is None or positive(v)


def non_negative_or_none(v) -> bool:
    return v is None or (_number(v) and v >= 0)


def positive_int(v) -> bool:
    return isinstance(v, int | np.integer) and not isinstance(v, bool) and v > 0


def count(v) -> bool:
    """A positive integer up to :data:`MAX_COUNT` (iterations, replicates, particles, moves)."""
    return positive_int(v) and v <= MAX_COUNT


def counted(what: str, low: int = 1) -> str:
    """The usable values of a :func:`count` setting in words."""
    return f"a number of {what} from {low} to {MAX_COUNT}"


def one_of(*values) -> Callable[[Any], bool]:
    return lambda v: isinstance(v, str | bool | type(None)) and v in values


def seed_like(v) -> bool:
    """None, a non-negative integer seed, or a :class:`numpy.random.Generator`."""
    return v is None or isinstance(v, np.random.Generator) or (positive_int(v) or (_number(v) and v == 0
                                                                                  and isinstance(v, int)))


def array_or_none(v) -> bool:
    try:
        return v is None or np.isfinite(np.asarray(v, float)).all()
    except (TypeError, ValueError):
        return False


def steps(v) -> bool:
    try:
        return all(positive_int(s) for s in v)
    except TypeError:
        return False


RNG = Setting("rng", seed_like, "None, an integer seed >= 0 or a numpy.random.Generator")
RATE = Setting("rate", positive_or_none, "a positive sampling rate in Hz (needed when data is an array)")


def check_settings(est) -> None:
    """Raise :class:`~skelid.errors.SettingError` naming the first unusable setting of ``est``."""
    for s in type(est).settings:
        v = getattr(est, s.name)
        try:
            ok = bool(s.check(v))
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise SettingError(f"{type(est).__name__} setting {s.name}={v!r} is not usable",
                               f"give {s.allowed}")


def get_settings(est) -> dict:
    """The declared settings of ``est`` as ``{name: value}``."""
    return {s.name: getattr(est, s.name) for s in type(est).settings}


def make_rng(rng) -> np.random.Generator:
    """A generator from the ``rng`` setting: a seed gives a fresh one on every fit (fit twice, same answer)."""
    if isinstance(rng, np.random.Generator):
        return rng
    return np.random.default_rng(0 if rng is None else int(rng))


def check_model(model, who: str) -> Model:
    """``model`` if it is a :class:`~skelid.model.description.Model`, else a one-line :class:`ModelError`.

    Every estimator's ``__init__`` calls it: a model is not a setting, and a wrong one would
    otherwise surface as an ``AttributeError`` deep inside ``fit``.
    """
    if not isinstance(model, Model):
        raise ModelError(f"{who} needs a skelid Model as its first argument, got {type(model).__name__}",
                         "load one with skelid.load_model('model.toml') or "
                         "skelid.simulate.builtin_model('case-a')")
    return model


def check_fitted(est, attr: str = "frames_used_") -> None:
    """Raise :class:`~skelid.errors.NotFittedError` if ``est`` has not been fitted."""
    if not hasattr(est, attr):
        raise NotFittedError(f"this {type(est).__name__} has not been fitted yet",
                             "call fit(data) before asking for its result")


def setting_json(v):
    """A setting as a JSON value for :attr:`FitResult.settings`."""
    if isinstance(v, np.random.Generator):
        return "Generator"
    if isinstance(v, np.ndarray | list | tuple):
        return np.asarray(v, float).tolist() if np.asarray(v).dtype.kind in "biuf" else [str(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    return v if v is None or isinstance(v, bool | int | float | str) else repr(v)


def marker_array(model: Model, data, rate, method: str | None = None, motion: bool = True) -> tuple[np.ndarray, float]:
    """``(y (F, M, D), rate)`` from ``data``: a :class:`MarkerData`, or an array with the ``rate`` setting.

    With ``method`` (the estimator's name), the data are also checked as ``skelid fit`` checks
    them (:func:`skelid.checks.check_units`, :func:`skelid.checks.check_data`): marker distances
    of the model's size (not data in other units than they say), enough usable frames for the
    method, more marker coordinates than pose coordinates, something that moves (not with
    ``motion=False``: a trial among several, whose motion is checked with the others).

    Raises
    ------
    DataError
        See :func:`prepare` and :func:`skelid.checks.check_data`; an array of another shape than
        ``(F, M, D)`` for the model, or of anything but real numbers.
    SettingError
        An array without a ``rate``.
    """
    if isinstance(data, MarkerData):
        y, rate, where = prepare(model, data), data.rate, data.source or "the data"
    else:
        y, rate, where = _array_data(model, data, rate), float(rate), "the marker array"
    check_range(y, model.units, where)
    if method is not None:
        from skelid.checks import check_data, check_units  # the checks of skelid fit, the one place they live

        check_units(model, data if isinstance(data, MarkerData) else MarkerData(y, model.marker_names, rate,
                                                                                model.units, source=where))
        check_data(model, y, [method], where, motion=motion)
    return y, rate


def fit_origin(model: Model, y) -> np.ndarray:
    """``(D,) float``: the point a fit moves the origin to, so that its numbers do not depend on where the data sit.

    For a model whose root hangs from the ground by a free joint, a rigid shift of every marker is
    taken up exactly by the root's translation: the fit works on ``y - origin`` with ``origin`` the
    mean of the present marker coordinates rounded to whole model units (whole units, so that data
    shifted by whole units give the fit the same numbers, bit for bit), and :func:`move_root` puts
    the fitted poses back. Any other root is fixed in the laboratory: zeros (no move).

    Parameters
    ----------
    y : (F, M, D) float
        Markers, NaN where missing.
    """
    y = np.asarray(y, dtype=float)
    root = next(s for s in model.segments if s.parent is None)
    present = np.isfinite(y).all(axis=-1)
    if root.joint.type != "free" or not present.any():
        return np.zeros(y.shape[-1])
    return np.round(y[present].mean(axis=0))


def move_root(model: Model, pose, offset) -> np.ndarray:
    """``pose (..., Q)`` with the root's translation moved by ``offset (D,)``: every marker moves by ``offset``.

    The inverse of the move :func:`fit_origin` asks for is ``move_root(model, pose, origin)``; a
    zero offset returns ``pose`` unchanged (a copy).
    """
    pose = np.array(pose, dtype=float)
    offset = np.asarray(offset, dtype=float)
    if not offset.any():
        return pose
    root = next(i for i, s in enumerate(model.segments) if s.parent is None)
    k = [j for j, d in enumerate(model.dofs) if d.segment == root and d.kind == "T"]
    axes = np.array([model.dofs[j].axis for j in k])  # (D, D): a free root translates along the world's axes
    pose[..., k] += axes @ offset
    return pose


def _array_data(model: Model, data, rate) -> np.ndarray:
    if isinstance(data, str | bytes) or data is None or isinstance(data, dict):
        raise DataError(f"data must be MarkerData or an array (frames, markers, coordinates) of numbers, "
                        f"got {type(data).__name__}", "give a MarkerData (skelid.io.read_markers(path)) or an array")
    if rate is None:
        raise SettingError("marker data given as an array need the sampling rate (setting rate=None)",
                           "pass rate=HZ to the estimator, or give a MarkerData")
    y = check_positions(data, model.units, "the marker array")
    shape = (len(model.markers), model.dim)
    if y.ndim != 3 or y.shape[1:] != shape:
        raise DataError(f"marker array of shape {y.shape} does not fit model {model.name!r}",
                        f"give (frames, {shape[0]}, {shape[1]}): the model's markers in model order and units")
    if len(y) == 0:
        raise DataError("the marker array has no frames", "give at least one frame")
    _check_present(model, y, "the marker array")
    return y


def _check_present(model: Model, y: np.ndarray, source: str) -> None:
    """Every model marker present in some frame, and some frame with a marker."""
    present = np.isfinite(y).all(axis=2)
    never = [n for n, p in zip(model.marker_names, present.any(axis=0), strict=True) if not p]
    if never:
        raise DataError(
            f"marker(s) {', '.join(never)} are missing in every frame of {source}",
            "remove them from the model or use a trial in which they were tracked",
        )


def prepare(model: Model, data: MarkerData) -> np.ndarray:
    """Markers of ``model`` from ``data``, in model order and model units.

    Returns
    -------
    y : (F, M, D) float
        NaN where a marker is missing.

    Raises
    ------
    DataError
        A marker the model needs is not in the data, the data have no frames,
        or 3-D data with out-of-plane motion are given to a planar model.
    """
    if data.n_frames == 0:
        raise DataError(f"{data.source or 'the data'} has no frames", "check the file")
    sel = data.select(model.marker_names, model.marker_labels)
    y = sel.positions * unit_scale(data.units, model.units)
    _check_present(model, y, data.source or "the data")
    present = np.isfinite(y).all(axis=2)
    if model.dim == 2 and y.shape[2] == 3:
        z = y[..., 2][present]
        spread = float(np.max(np.abs(z - z.mean())))
        if spread > 1e-6 * max(float(np.abs(y[present][:, :2]).max()), 1.0):
            raise DataError(
                f"{data.source or 'the data'} moves out of the x-y plane "
                f"(z varies by {spread:.3g} {model.units}) but model {model.name!r} is planar",
                "use a 3-D model (dim = 3) or project the data onto the plane of motion first",
            )
        y = y[..., :2]
    elif model.dim == 3 and y.shape[2] == 2:
        raise DataError(f"{data.source or 'the data'} is planar but model {model.name!r} is 3-D",
                        "use a model with dim = 2")
    if not present.any(axis=1).any():
        raise DataError(f"{data.source or 'the data'} has no frame with any marker present")
    return y


def emit(found) -> tuple[Warning, ...]:
    """Issue each :class:`~skelid.result.Warning` once as a :class:`SkelidWarning`; the unique ones, in order."""
    out = []
    for w in found:
        if all(w.message != o.message for o in out):
            out.append(w)
            warnings.warn(w.message, SkelidWarning, stacklevel=3)
    return tuple(out)


def warn_once(message: str, record: list | None = None) -> None:
    """Issue a :class:`SkelidWarning` and keep its text for the JSON result."""
    warnings.warn(message, SkelidWarning, stacklevel=3)
    if record is not None and message not in record:
        record.append(message)


#: a point within this fraction of its prior's width from a bound sits on the bound
ON_BOUND_RTOL = 1e-6


def in_support(prior, points, interval, status: str) -> tuple[tuple[float, ...], tuple[float, float], str]:
    """Points (MAP, mean) and interval of one parameter held inside its prior's support ``[lower, upper]``.

    A point on or beyond a bound gets the status ``'on-bound'`` (unless the parameter is
    unidentified) and is put on the bound. The interval is always cut to the support: the
    prior gives no probability outside it, so neither does the posterior (a poorly identified
    length's normal interval would otherwise reach negative lengths).
    """
    lo, hi = float(prior.lower), float(prior.upper)
    tol = ON_BOUND_RTOL * (hi - lo)
    moved = any(not lo <= x <= hi for x in points)
    on = moved or any(x <= lo + tol or x >= hi - tol for x in points)
    if on and status != "unidentified":
        status = "on-bound"
    if moved:
        points = tuple(min(max(x, lo), hi) for x in points)
    interval = (min(max(interval[0], lo), hi), min(max(interval[1], lo), hi))
    return points, interval, status


def _beyond(posterior, k: int, point) -> dict:
    """``{'beyond_bound': {'map', 'mean'}}``: the unbounded values, where the point was put on a bound."""
    raw = (float(posterior.map[k]), float(posterior.mean[k]))
    return {} if raw == tuple(point) else {"beyond_bound": {"map": raw[0], "mean": raw[1]}}


def _status(s) -> str:
    return {"unidentifiable": "unidentified"}.get(str(s), str(s)) if s else "identified"


def parameter_unit(model: Model, k: int) -> str:
    """Unit of parameter ``k``: degrees for axis tilts, ``"1"`` for scale factors, the model's length unit otherwise."""
    kind = model.parameters[k].kind
    return "deg" if kind == "axis_direction" else "1" if kind == "scale" else model.units


def build_result(est, posterior, *, noise=None, skipped=None, crlb_sd=None, extra=None, status=None,
                 diagnostics=None, derived=None, arrays=None):
    """The :class:`~skelid.result.FitResult` of a fitted estimator from its posterior and extras.

    Parameters
    ----------
    posterior : GridPosterior, GaussianPosterior or SamplePosterior
        With ``map``, ``mean``, ``sd`` and ``credible_interval(0.95)``, named as the model's parameters.
    crlb_sd : (P,) float, optional
    extra : dict, optional
        ``{parameter: {key: value}}``.
    status : dict, optional
        ``{parameter: status}``; defaults to the rows of ``est.identifiability_`` if any.
    derived : dict, optional
        ``{name: {"value", "sd", "ci95"}}`` (joint-to-joint lengths).
    """
    from skelid.result import FitResult, FrameCounts, ParameterEstimate

    model = est.model
    ci = np.atleast_2d(posterior.credible_interval(0.95))
    if status is None:
        rows = getattr(est, "identifiability_", {}).get("table", [])
        status = {r["parameter"]: r["status"] for r in rows}
    params = {}
    for k, n in enumerate(model.parameter_names):
        crlb = None if crlb_sd is None or not np.isfinite(crlb_sd[k]) else float(crlb_sd[k])
        point, ext, st = in_support(model.parameters[k].prior, (float(posterior.map[k]), float(posterior.mean[k])),
                                    (float(ci[k, 0]), float(ci[k, 1])), _status(status.get(n)))
        params[n] = ParameterEstimate(n, parameter_unit(model, k), point[0], point[1], float(posterior.sd[k]),
                                      ext, crlb_sd=crlb, status=st,
                                      extra={**(extra or {}).get(n, {}), **_beyond(posterior, k, point)})
    der = {n: ParameterEstimate(n, model.units, v["value"], v["value"], v["sd"], tuple(v["ci95"]))
           for n, v in (derived or {}).items()}
    used = np.asarray(est.frames_used_, bool)
    arr = {k: np.asarray(v) for k, v in (arrays or {}).items() if v is not None}
    return FitResult(
        method=est.name, parameters=params, derived=der, noise=noise,
        frames=FrameCounts(len(used), int(used.sum()), skipped or {}),
        diagnostics=diagnostics or {}, warnings=tuple(est.warnings_),
        settings={k: setting_json(v) for k, v in get_settings(est).items() if k not in ("theta0", "pose0")},
        arrays=arr)
