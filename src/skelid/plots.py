"""Figures. matplotlib is imported only when a figure is drawn (Agg backend).

Every function writes one PNG atomically and returns its path. Names from
model and data files are drawn as written: mathtext is off while a figure is
built (a marker called ``$\\foo$`` is not TeX).
"""

from __future__ import annotations

import functools
import io
from pathlib import Path

import numpy as np

from skelid.io.atomic import atomic_write


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    # names come from users' files: draw "$\\foo$" as those characters, never as mathtext
    plt.rcParams["text.parse_math"] = False

    return plt


def literal_text(func):
    """Build the figure with mathtext off, so that names are shown as written."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with _plt().rc_context({"text.parse_math": False}):
            return func(*args, **kwargs)

    return wrapper


def _save(fig, path) -> Path:
    path = Path(path)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120, bbox_inches="tight")
    _plt().close(fig)
    with atomic_write(path, "wb") as fh:
        fh.write(buf.getvalue())
    return path


@literal_text
def trajectories(data, path, title: str = "Marker trajectories") -> Path:
    """Marker paths in the x-y plane (2-D data) or coordinates against time (3-D)."""
    plt = _plt()
    pos = data.positions
    if data.dim == 2:
        fig, ax = plt.subplots(figsize=(6, 5))
        for m, name in enumerate(data.names):
            ax.plot(pos[:, m, 0], pos[:, m, 1], ".", ms=2, label=name)
        ax.set_xlabel(f"x [{data.units}]")
        ax.set_ylabel(f"y [{data.units}]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.legend(title="marker", markerscale=5, fontsize=8)
    else:
        fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
        t = data.time
        for k, ax in enumerate(axes):
            for m, name in enumerate(data.names[:12]):
                ax.plot(t, pos[:, m, k], lw=0.8, label=name)
            ax.set_ylabel(f"{'xyz'[k]} [{data.units}]")
        axes[-1].set_xlabel("time [s]")
        axes[0].legend(fontsize=6, ncol=4)
    fig.suptitle(title)
    return _save(fig, path)


@literal_text
def posterior_history(posterior, path, truth: float | None = None, units: str = "mm",
                      title: str = "Posterior", gaussians: dict | None = None) -> Path:
    """The marginal posterior of the first parameter at each stored step."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    x = posterior.axes[0]
    h = x[1] - x[0] if x.size > 1 else 1.0
    snaps = list(posterior.history) or [(posterior.n_updates, posterior.log_weights)]
    for step, lw in snaps:
        ax.plot(x, posterior.marginal(0, lw) / h, label=f"after {step} steps")
    for label, (mu, sd) in (gaussians or {}).items():
        xx = np.linspace(x[0], x[-1], 2000)
        ax.plot(xx, np.exp(-0.5 * ((xx - mu) / sd) ** 2) / (sd * np.sqrt(2 * np.pi)), "k-", lw=1.2,
                label=label)
    if truth is not None:
        ax.axvline(truth, color="k", ls="--", lw=1, label=f"true value {truth:g} {units}")
    ax.set_xlabel(f"{posterior.names[0]} [{units}]")
    ax.set_ylabel(f"posterior density [1/{units}]")
    mass = np.max([posterior.marginal(0, lw) for _, lw in snaps], axis=0)
    shown = x[mass > 1e-4 * mass.max()]
    lo, hi = shown.min(), shown.max()
    for mu, sd in (gaussians or {}).values():
        lo, hi = min(lo, mu - 4 * sd), max(hi, mu + 4 * sd)
    if truth is not None:
        lo, hi = min(lo, truth), max(hi, truth)
    pad = 0.15 * max(hi - lo, h)
    ax.set_xlim(max(x[0], lo - pad), min(x[-1], hi + pad))
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(title)
    return _save(fig, path)


@literal_text
def map_path(steps_map, path, truth: float | None = None, measured=None, name: str = "L2",
             units: str = "mm", title: str = "Most likely value per step", extra: dict | None = None) -> Path:
    """Most likely value after each step, the per-frame measurements and the truth."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    steps = np.arange(1, len(steps_map) + 1)
    if measured is not None:
        ax.plot(steps, measured, ".", ms=2, color="0.7", label="per-frame measured value")
    ax.plot(steps, steps_map, lw=1.5, label="most likely value (paper)")
    for label, series in (extra or {}).items():
        ax.plot(np.arange(1, len(series) + 1), series, lw=1.5, label=label)
    if truth is not None:
        ax.axhline(truth, color="k", ls="--", lw=1, label=f"true value {truth:g} {units}")
    ax.set_xlabel("step (frame)")
    ax.set_ylabel(f"{name} [{units}]")
    finite = np.asarray(steps_map)[np.isfinite(steps_map)]
    if finite.size:
        lo, hi = np.percentile(finite, [0, 100])
        pad = max(hi - lo, 1.0)
        if truth is not None:
            lo, hi = min(lo, truth), max(hi, truth)
        ax.set_ylim(lo - pad, hi + pad)
    ax.legend(fontsize=8)
    ax.set_title(title)
    return _save(fig, path)


def fit_figures(model, data, fitted: dict, out_dir, prefix: str = "",
            truth: dict | None = None) -> list[Path]:
    """The seed paper's figures for a fit: trajectories, posterior history, MAP per step."""
    out_dir = Path(out_dir)
    name = model.parameter_names[0] if model.n_params else ""
    tv = (truth or {}).get(name)
    paths = [trajectories(data, out_dir / f"{prefix}trajectories.png",
                                title=f"{model.name}: marker trajectories")]
    main = fitted.get("paper") or next(iter(fitted.values()))
    gauss = {f"final posterior ({k} method)": (v.posterior_.mean[0], v.posterior_.sd[0])
             for k, v in fitted.items() if v is not main and not hasattr(v.posterior_, "axes")}
    if hasattr(main, "posterior_") and hasattr(main.posterior_, "axes"):
        paths.append(posterior_history(
            main.posterior_, out_dir / f"{prefix}posterior.png", truth=tv, units=model.units,
            title=f"{model.name}: posterior of {name} ({main.name} method)", gaussians=gauss))
    if hasattr(main, "map_path_"):
        extra = {f"most likely value ({k})": v.map_path_ for k, v in fitted.items()
                 if v is not main and hasattr(v, "map_path_")}
        paths.append(map_path(
            main.map_path_, out_dir / f"{prefix}map_per_step.png", truth=tv,
            measured=getattr(main, "measured_", None), name=name, units=model.units,
            title=f"{model.name}: most likely {name} per step", extra=extra))
    return paths
