"""Which warnings a user reads about the data and a fit: the warning policy, in one place.

Thresholds (each written once):

* a model marker missing in more than ``GAP_WARN_FRACTION`` of the frames;
* a parameter is poorly identified when its sd exceeds ``POOR_FRACTION`` of its prior width
  (the estimators' own threshold, :data:`skelid.estimators.marker.POOR_FRACTION`);
* a marker's residuals whose lag-1 autocorrelation exceeds ``STA_AUTOCORR`` (and that are above the
  file's rounding level, :data:`skelid.estimators.marker.NUMERICAL_RESIDUAL`) look like soft-tissue
  artefact; per-frame measured values of a one-parameter method, above ``MEASURED_AUTOCORR``.

The lag-1 autocorrelation is :func:`skelid.estimators.joint.lag1_autocorrelation` everywhere.
"""

from __future__ import annotations

import contextlib
import warnings

import numpy as np

from skelid.errors import SkelidWarning
from skelid.estimators.joint import lag1_autocorrelation
from skelid.estimators.marker import NUMERICAL_RESIDUAL, POOR_FRACTION
from skelid.model.description import Model

#: a marker missing in more than this fraction of frames gets a warning
GAP_WARN_FRACTION = 0.10
#: lag-1 autocorrelation of a marker's residuals above which they look like soft-tissue artefact
STA_AUTOCORR = 0.7
#: the same for the per-frame measured values of a one-parameter method
MEASURED_AUTOCORR = 0.5

__all__ = ["GAP_WARN_FRACTION", "POOR_FRACTION", "STA_AUTOCORR", "MEASURED_AUTOCORR", "overview_warnings",
           "fit_warnings", "lag1_autocorrelation", "unique", "collect_warnings"]


def overview_warnings(overview: dict) -> list[str]:
    F = overview["n_frames"]
    out = []
    for m in overview["markers"]:
        if m["used_by_model"] and m["frames_missing"] > GAP_WARN_FRACTION * F:
            out.append(f"marker {m['name']} is missing in {m['frames_missing']} of {F} frames "
                       f"({100 * m['frames_missing'] / F:.0f} %, {m['gaps']} gaps, longest "
                       f"{m['longest_gap']} frames)")
    return out


def fit_warnings(model: Model, name: str, res: dict, est) -> list[str]:
    """Warnings about a fit a user should read: poorly identified parameters,
    parameters stuck at a bound of their prior, residuals that look like
    soft-tissue artefact."""
    out = []
    for p in model.parameters:
        v = res.get(p.name)
        if not isinstance(v, dict) or "ci95" not in v:
            continue
        lo, hi = p.prior.lower, p.prior.upper
        width = hi - lo
        ci = v["ci95"]
        if width > 0 and v["sd"] > POOR_FRACTION * width:
            out.append(f"parameter {p.name} is poorly identified by the {name} method: its sd {v['sd']:.3g} "
                       f"{model.units} is more than a quarter of the prior interval (95 % interval "
                       f"[{ci[0]:.4g}, {ci[1]:.4g}] {model.units})")
        elif width > 0 and min(v["map"] - lo, hi - v["map"]) <= max(p.grid_step, 0.005 * width):
            out.append(f"parameter {p.name} ({name} method) is at a bound of its prior interval "
                       f"[{lo:g}, {hi:g}] {model.units}; the interval may be too narrow")
    for row in res.get("identifiability", []) or []:
        status = str(row.get("status", ""))
        if status and status.lower() not in ("ok", "identified", "well identified", "well-identified", "good"):
            out.append(f"parameter {row.get('parameter')} is {status} ({name} method)")
    r = getattr(est, "residuals_", None)
    if r is not None and np.ndim(r) == 2:
        r = np.asarray(r, float)
        # residuals at the level of the file's rounding (noise-free data) say nothing about tissue
        floor = NUMERICAL_RESIDUAL * float(np.abs(model.nominal_geometry).max())
        misfit = {v["segment"] for v in (getattr(est, "misfit_", None) or {}).values() if v["flagged"]}
        slow, one = [], ""
        for m, mname in enumerate(model.marker_names[: r.shape[1]]):
            if model.markers[m].segment in misfit:
                continue  # already reported as model misfit
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # a marker never present
                rho = lag1_autocorrelation(r[:, m])
            rms = float(np.sqrt(np.nanmean(r[:, m] ** 2))) if np.isfinite(r[:, m]).any() else 0.0
            if rho > STA_AUTOCORR and rms > floor:
                slow.append(f"{mname} (rms {rms:.3g}, lag-1 {rho:.2f})")
                one = (f"residuals of marker {mname} ({name} method, rms {rms:.3g} {model.units}) are "
                       f"correlated in time (lag-1 autocorrelation {rho:.2f}): this looks like "
                       "soft-tissue artefact, not measurement noise")
        if len(slow) == 1:
            out.append(one)
        elif slow:  # one line for all of them
            out.append(f"residuals of {len(slow)} markers ({name} method) are correlated in time: "
                       f"{', '.join(slow)} {model.units}; this looks like soft-tissue artefact, not measurement "
                       "noise")
    measured = getattr(est, "measured_", None)
    if measured is not None and model.n_params == 1:
        rho = lag1_autocorrelation(measured)
        if rho > MEASURED_AUTOCORR:
            out.append(f"the per-frame values of {model.parameter_names[0]} ({name} method) drift slowly "
                       f"(lag-1 autocorrelation {rho:.2f}) instead of scattering independently: this looks "
                       "like soft-tissue artefact, and the 95 % interval, which treats frames as independent, "
                       "is too narrow")
    return out


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
