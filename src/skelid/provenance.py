"""How a result was made: command, working folder, time, versions, and the model's priors."""

from __future__ import annotations

import datetime
import os
import platform
import sys
from importlib import metadata

from skelid.model.description import Model


def versions() -> dict:
    """Versions of Python, skelid and the libraries that shape a result."""
    out = {"python": platform.python_version(), "platform": platform.platform()}
    for pkg in ("skelid", "numpy", "scipy", "ezc3d", "matplotlib", "click", "tqdm"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def provenance(command=None) -> dict:
    return {
        "command": list(command) if command is not None else ["skelid", *sys.argv[1:]],
        "cwd": os.getcwd(),
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "versions": versions(),
    }


def model_parameters(model: Model) -> dict:
    """Prior interval and nominal value of each parameter (for reports)."""
    return {p.name: {"kind": p.kind, "target": p.target, "prior": p.prior.to_dict(),
                     "nominal": float(v), "units": model.units}
            for p, v in zip(model.parameters, model.theta_nominal, strict=True)}


def run_context(model: Model, data_source, frames_total: int, command=None, **more) -> dict:
    """The context of a run: model, data, units, frames, priors, model description, provenance."""
    return {"model": model.name, "data": data_source, "units": model.units, "frames_total": int(frames_total),
            **more, "model_parameters": model_parameters(model), "model_description": model.to_dict(),
            "provenance": provenance(command)}
