"""What every estimator shares: matching data to a model, and the fit/update shape.

An estimator is built with the model and its settings only
(``Estimator(model, sigma=15.0)``); ``fit(data)`` returns the estimator with
fitted attributes ending in ``_``; ``init_state()`` and ``update(state, frame)``
are the online form, and ``fit`` equals folding ``update`` over the frames.
"""

from __future__ import annotations

import warnings

import numpy as np

from skelid.data import MarkerData, unit_scale
from skelid.errors import DataError, SkelidWarning
from skelid.model.description import Model


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
    present = np.isfinite(y).all(axis=2)
    never = [n for n, p in zip(model.marker_names, present.any(axis=0), strict=True) if not p]
    if never:
        raise DataError(
            f"marker(s) {', '.join(never)} are missing in every frame of {data.source or 'the data'}",
            "remove them from the model or use a trial in which they were tracked",
        )
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


def warn_once(message: str, record: list | None = None) -> None:
    """Issue a :class:`SkelidWarning` and keep its text for the JSON result."""
    warnings.warn(message, SkelidWarning, stacklevel=3)
    if record is not None and message not in record:
        record.append(message)
