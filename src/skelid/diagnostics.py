"""Which warnings a user reads about the data and a fit: the warning policy, in one place.

Thresholds (each written once):

* a model marker missing in more than ``GAP_WARN_FRACTION`` of the frames;
* a parameter is poorly identified when its sd exceeds ``POOR_FRACTION`` of its prior width
  (the estimators' own threshold, :data:`skelid.estimators.marker.POOR_FRACTION`);
* a marker's residuals whose lag-1 autocorrelation exceeds ``STA_AUTOCORR`` (and that are above the
  file's rounding level, :data:`skelid.estimators.marker.NUMERICAL_RESIDUAL`) look like soft-tissue
  artefact; per-frame measured values of a one-parameter method, above ``MEASURED_AUTOCORR``.

The lag-1 autocorrelation is :func:`skelid.estimators.fit.joint.lag1_autocorrelation` everywhere.
"""

from __future__ import annotations

import contextlib
import warnings

import numpy as np

from skelid.errors import SkelidWarning
from skelid.estimators.fit.joint import lag1_autocorrelation
from skelid.estimators.marker import NUMERICAL_RESIDUAL, POOR_FRACTION
from skelid.model.description import Model
from skelid.result import FitResult, Warning

#: a marker missing in more than this fraction of frames gets a warning
GAP_WARN_FRACTION = 0.10
#: lag-1 autocorrelation of a marker's residuals above which they look like soft-tissue artefact
STA_AUTOCORR = 0.7
#: the same for the per-frame measured values of a one-parameter method
MEASURED_AUTOCORR = 0.5
#: statuses of an identifiability row that need no warning
IDENTIFIED = ("ok", "identified", "well identified", "well-identified", "good")

__all__ = ["GAP_WARN_FRACTION", "POOR_FRACTION", "STA_AUTOCORR", "MEASURED_AUTOCORR", "overview_warnings",
           "fit_warnings", "prior_warnings", "status_warnings", "residual_warnings", "measured_warnings",
           "lag1_autocorrelation", "unique", "unique_warnings", "collect_warnings"]


def overview_warnings(overview: dict) -> list[str]:
    """A model marker missing in more than ``GAP_WARN_FRACTION`` of the frames."""
    F = overview["n_frames"]
    out = []
    for m in overview["markers"]:
        if m["used_by_model"] and m["frames_missing"] > GAP_WARN_FRACTION * F:
            out.append(f"marker {m['name']} is missing in {m['frames_missing']} of {F} frames "
                       f"({100 * m['frames_missing'] / F:.0f} %, {m['gaps']} gaps, longest "
                       f"{m['longest_gap']} frames)")
    return out


def fit_warnings(model: Model, result: FitResult, est) -> list[Warning]:
    """Warnings about a fit a user should read, each naming the parameters it concerns.

    Poorly identified parameters and parameters at a bound of their prior
    (:func:`prior_warnings`), a status other than identified
    (:func:`status_warnings`), residuals that look like soft-tissue artefact
    (:func:`residual_warnings`) and per-frame values that drift
    (:func:`measured_warnings`).
    """
    return [*prior_warnings(model, result), *status_warnings(result),
            *residual_warnings(model, result.method, est), *measured_warnings(model, result.method, est)]


def prior_warnings(model: Model, result: FitResult) -> list[Warning]:
    """A parameter whose sd exceeds ``POOR_FRACTION`` of its prior width, or whose MAP sits at a bound."""
    out, name = [], result.method
    for p in model.parameters:
        v = result.parameters.get(p.name)
        lo, hi = p.prior.lower, p.prior.upper
        width = hi - lo
        if v is None or not width > 0:
            continue
        ci = v.interval
        if v.sd > POOR_FRACTION * width:
            out.append(Warning("poorly-identified", f"parameter {p.name} is poorly identified by the {name} method: "
                               f"its sd {v.sd:.3g} {model.units} is more than a quarter of the prior interval "
                               f"(95 % interval [{ci[0]:.4g}, {ci[1]:.4g}] {model.units})", (p.name,)))
        elif min(v.map - lo, hi - v.map) <= max(p.grid_step, 0.005 * width):
            out.append(Warning("on-bound", f"parameter {p.name} ({name} method) is at a bound of its prior interval "
                               f"[{lo:g}, {hi:g}] {model.units}; the interval may be too narrow", (p.name,)))
    return out


def status_warnings(result: FitResult) -> list[Warning]:
    """A row of the identifiability table whose status is not 'identified'."""
    out = []
    for row in result.diagnostics.get("identifiability") or []:
        status, pname = str(row.get("status", "")), str(row.get("parameter"))
        if status and status.lower() not in IDENTIFIED:
            out.append(Warning("poorly-identified", f"parameter {pname} is {status} ({result.method} method)",
                               (pname,)))
    return out


def residual_warnings(model: Model, name: str, est) -> list[Warning]:
    """Markers whose residuals drift slowly (lag-1 autocorrelation above ``STA_AUTOCORR``): one warning."""
    slow = slow_markers(model, est)
    if len(slow) == 1:
        mname, rms, rho = slow[0]
        return [Warning("soft-tissue-artefact", f"residuals of marker {mname} ({name} method, rms {rms:.3g} "
                        f"{model.units}) are correlated in time (lag-1 autocorrelation {rho:.2f}): this looks "
                        "like soft-tissue artefact, not measurement noise")]
    if slow:  # one line for all of them
        listed = ", ".join(f"{m} (rms {rms:.3g}, lag-1 {rho:.2f})" for m, rms, rho in slow)
        return [Warning("soft-tissue-artefact", f"residuals of {len(slow)} markers ({name} method) are correlated "
                        f"in time: {listed} {model.units}; this looks like soft-tissue artefact, not measurement "
                        "noise")]
    return []


def slow_markers(model: Model, est) -> list[tuple[str, float, float]]:
    """``(marker, rms, lag-1 autocorrelation)`` of each marker whose residuals (``est.residuals_ (F, M)``)
    drift: autocorrelation above ``STA_AUTOCORR`` and rms above the file's rounding level. Markers
    on a segment already flagged as model misfit (``est.misfit_``) are left out."""
    r = getattr(est, "residuals_", None)
    if r is None or np.ndim(r) != 2:
        return []
    r = np.asarray(r, float)[:, : len(model.markers)]
    # residuals at the level of the file's rounding (noise-free data) say nothing about tissue
    floor = NUMERICAL_RESIDUAL * float(np.abs(model.nominal_geometry).max())
    misfit = {v["segment"] for v in (getattr(est, "misfit_", None) or {}).values() if v["flagged"]}
    rms, rho = residual_scores(r)
    return [(model.marker_names[m], float(rms[m]), float(rho[m])) for m in range(r.shape[1])
            if rho[m] > STA_AUTOCORR and rms[m] > floor and model.markers[m].segment not in misfit]


def residual_scores(r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Root-mean-square ``(M,)`` (0 for a marker never present) and lag-1 autocorrelation ``(M,)``
    of each column of the residuals ``r (F, M)``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a marker never present
        rms = np.sqrt(np.nanmean(r ** 2, axis=0))
        rho = np.array([lag1_autocorrelation(r[:, m]) for m in range(r.shape[1])], float)
    return np.where(np.isfinite(rms), rms, 0.0), rho


def measured_warnings(model: Model, name: str, est) -> list[Warning]:
    """Per-frame values of a one-parameter method that drift (lag-1 autocorrelation above ``MEASURED_AUTOCORR``)."""
    measured = getattr(est, "measured_", None)
    if measured is None or model.n_params != 1:
        return []
    rho = lag1_autocorrelation(measured)
    if not rho > MEASURED_AUTOCORR:
        return []
    pname = model.parameter_names[0]
    return [Warning("soft-tissue-artefact", f"the per-frame values of {pname} ({name} method) drift slowly "
                    f"(lag-1 autocorrelation {rho:.2f}) instead of scattering independently: this looks like "
                    "soft-tissue artefact, and the 95 % interval, which treats frames as independent, is too "
                    "narrow", (pname,))]


def unique_warnings(items) -> tuple[Warning, ...]:
    """Warnings (or plain messages) each once by message, in order."""
    out = {}
    for w in items:
        w = w if isinstance(w, Warning) else Warning("note", str(w))
        out.setdefault(w.message, w)
    return tuple(out.values())


def unique(seq) -> list:
    out = []
    for s in seq:
        if s not in out:
            out.append(s)
    return out


@contextlib.contextmanager
def collect_warnings():
    """Record :class:`SkelidWarning` messages instead of printing them; other warnings pass."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", SkelidWarning)
        box: list[str] = []
        yield box
    for w in caught:
        if issubclass(w.category, SkelidWarning):
            box.append(str(w.message))
        else:  # pragma: no cover - not ours: show it as usual
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
