"""Checks that data can inform a model before any fit starts.

Each check is a small named function that raises a one-line
:class:`~skelid.errors.DataError` (or returns quietly); :func:`check_data`
runs them all. They look only at sizes and at the data's spread, never at a
fit:

* :func:`check_frames`: each method needs a minimum number of *usable* frames,
  frames whose present markers give more coordinates than the pose has
  (:data:`MIN_FRAMES`); a file of one or two rows, or all frames missing but
  one, is refused with the count;
* :func:`check_surplus`: the model's markers must give more coordinates per
  frame than it has pose coordinates, or no frame informs any parameter;
* :func:`check_motion`: data in which nothing moves (every coordinate constant
  over the usable frames, to rounding) carry no information about the joints
  and no noise to estimate: refused rather than fitted into a meaningless
  number.
"""

from __future__ import annotations

import numpy as np

from skelid.errors import DataError

#: usable frames each method needs at the least (the motion model of the marker methods needs a few)
MIN_FRAMES = {"paper": 1, "marker-grid": 1, "marker": 5, "marker-smc": 5}
DEFAULT_MIN_FRAMES = 5
#: a coordinate whose peak-to-peak range over the frames is below this fraction of the model's size is still
MOTION_RTOL = 1e-9


def usable_frames(model, y: np.ndarray) -> np.ndarray:
    """(F,) bool: frames whose present markers give more coordinates than the pose has."""
    present = np.isfinite(y).all(axis=-1)  # (F, M)
    return present.sum(axis=1) * model.dim > model.n_pose


def check_surplus(model, where: str = "the data") -> None:
    n_coord = len(model.markers) * model.dim
    if model.n_params and n_coord <= model.n_pose:
        raise DataError(
            f"model {model.name!r} has {len(model.markers)} markers ({n_coord} coordinates per frame) for "
            f"{model.n_pose} pose coordinates: no frame of {where} can inform its parameters",
            "add markers to the model (at least one coordinate more than the pose has)")


def check_frames(model, y: np.ndarray, method: str, where: str = "the data") -> None:
    need = MIN_FRAMES.get(method, DEFAULT_MIN_FRAMES)
    n = int(usable_frames(model, y).sum())
    if n < need:
        raise DataError(
            f"{where} has {n} frame(s) in which the model's markers fix the pose ({len(y)} frames in all); "
            f"the {method} method needs at least {need}",
            "use a longer trial, or check that the file holds the model's markers")


def check_motion(model, y: np.ndarray, where: str = "the data") -> None:
    ok = usable_frames(model, y)
    if ok.sum() < 2:
        return
    with np.errstate(invalid="ignore"):
        ptp = np.nanmax(y[ok], axis=0) - np.nanmin(y[ok], axis=0)  # (M, D)
    size = float(np.nanmax(np.abs(y[ok]))) if np.isfinite(y[ok]).any() else 0.0
    if not np.any(ptp > MOTION_RTOL * max(size, 1e-300)):
        raise DataError(
            f"nothing moves in {where}: every marker coordinate is the same in all {int(ok.sum())} usable frames, "
            "so the data hold no information about the joints and no noise to measure",
            "give a trial in which the joints move")


def check_data(model, y: np.ndarray, methods, where: str = "the data") -> None:
    """Run every check on ``y (F, M, D)`` (model markers, model units) for each method."""
    check_surplus(model, where)
    for m in methods:
        check_frames(model, y, m, where)
    check_motion(model, y, where)
