"""Warm-up of the compiled pose kernel: a tiny fit through the public path, run in a child process.

:func:`skelid.estimators.fit._lm_kernel.warm` starts a process that calls :func:`compile_here`, which
fits a two-segment model so that numba compiles (or loads from its disk cache) the driver the
real fits will use. It lives apart from the kernel because it goes through :mod:`.pose`, which
imports the kernel.
"""

from __future__ import annotations

import numpy as np

from skelid._numba import compile_lock
from skelid.estimators.fit._lm_kernel import _cached, compiled
from skelid.estimators.fit.pose import fit_pose_logdet
from skelid.model import model_from_dict


def compile_here(planar) -> None:
    """Compile the driver into the cache in this process, unless another process has (one at a time)."""
    with compile_lock("custom" if planar == "custom" else "planar" if planar else "spatial"):
        if not _cached(planar):
            fit_tiny_model(planar)


#: the custom driver's tiny model: a joint that turns by its coordinate and slides by a spline of it
_CUSTOM = {"type": "custom", "name": "j", "coordinates": ["c"],
           "motions": [{"kind": "translation", "axis": [1, 0, 0], "coordinate": "c",
                        "function": {"type": "spline", "x": [-1.0, 0.0, 1.0, 2.0], "y": [0.0, 0.1, 0.3, 0.2]}},
                       {"kind": "rotation", "axis": [0, 0, 1], "coordinate": "c",
                        "function": {"type": "linear", "coefficients": [1.0, 0.0]}}]}


def fit_tiny_model(planar) -> None:
    """Compile (or load) the driver in this process by fitting a tiny model through the public path."""
    custom = planar == "custom"
    planar = planar is True
    joint = {"type": "revolute", "name": "j"} if planar else {"type": "hinge", "name": "j", "axis": [0, 0, 1]}
    joint = _CUSTOM if custom else joint
    root = {"type": "free", "name": "root"}
    d = {"model": {"name": "warm", "dim": 2 if planar else 3, "units": "m"},
         "segments": [{"name": "a", "parent": "ground", "joint": root},
                      {"name": "b", "parent": "a", "joint": dict(joint, position=[1.0, 0.0] if planar
                                                                  else [1.0, 0.0, 0.0])}],
         "markers": [{"name": f"m{k}", "segment": "ab"[k // 3],
                      "position": ([0.1 * k, 0.2] if planar else [0.1 * k, 0.2, 0.05 * k])} for k in range(6)],
         "parameters": [{"name": "len", "kind": "length", "joint": "j",
                         "prior": {"type": "uniform", "lower": 0.5, "upper": 1.5}}]}
    model = model_from_dict(d, "warm")
    D = model.dim
    y = np.random.default_rng(0).normal(size=(2, len(model.markers), D))
    fit_pose_logdet(model, model.theta_center, y, np.zeros((2, model.n_pose)), n_iter=2)
    if not compiled("custom" if custom else planar):  # pragma: no cover - the model did not reach the kernel
        raise RuntimeError("the warm-up fit did not use the compiled kernel")
