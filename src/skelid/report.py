"""One self-contained HTML report of a fit, answering first.

``write_report(result_dir)`` reads what ``skelid fit --out RESULT_DIR`` wrote
(``result.json`` and, if present, ``arrays.npz``, through
:func:`skelid.io.results.read_run`, which refuses a damaged, foreign or old
folder in one line before anything is drawn) and writes one HTML file that
opens from disk or travels by mail: figures are embedded as base64 PNGs and
the interactive view's library (plotly.js) is inlined, so nothing is fetched.
Sections:

1. Summary: each parameter's estimate, 95 % interval, Cramér–Rao bound and
   status, with the warnings that concern it beside it (a fit that did not
   converge or whose approximation broke is shown there, in red), the derived
   lengths and the marker noise; with model alternatives (``skelid fit
   --alternative``), each estimate's spread over the models in its row; the
   noise level of each marker where it was estimated (``--noise per-marker``);
   then every other warning.
2. The fitted body: an interactive view (:mod:`skelid.viewer`) of the fitted
   skeleton (segments, joint centres, model markers) against the measured
   markers over time, 3-D or planar, with a frame slider and a play button.
3. Data overview: file, format, frames, rate, units, and the gaps of the
   model's markers (the file's other markers in one line).
4. Marker trajectories of the model's markers, and when they are missing.
5. Posterior evolution: the marginal posterior after successive frames and the
   most likely value per step.
6. Final posterior: MAP, mean, sd, 95 % interval and Cramér–Rao bound of each
   parameter, the marker noise σ, and a figure of each marginal.
7. Residuals per marker over time (where soft-tissue artefact shows).
8. Identifiability: the Cramér–Rao bound and status of each parameter.
9. Warnings, all of them.
10. How the result was made: the exact command and the versions.

A section whose data a method does not provide says "not available for this
method" rather than disappearing. Names from the model or the data file are
shown as written (escaped in HTML, in figures and in the view; no mathtext).
matplotlib is imported only when a figure is drawn, with the Agg backend.
"""

from __future__ import annotations

import base64
import datetime
import html
import io
import math
import re
import sys
from collections.abc import Mapping
from functools import partial
from pathlib import Path

import numpy as np

from skelid.errors import SkelidError
from skelid.io.atomic import atomic_write, ensure_parent

NOT_AVAILABLE = "not available for this method"

SECTIONS = (
    ("summary", "Summary"),
    ("body", "The fitted body"),
    ("overview", "Data overview"),
    ("trajectories", "Marker trajectories"),
    ("evolution", "Posterior evolution"),
    ("posterior", "Final posterior"),
    ("residuals", "Residuals per marker"),
    ("identifiability", "Identifiability"),
    ("warnings", "Warnings"),
    ("provenance", "How this result was made"),
)

CSS = """
body { font-family: system-ui, -apple-system, 'Segoe UI', sans-serif; max-width: 1100px; margin: 2em auto;
       padding: 0 1em; color: #222; line-height: 1.45; }
h1 { font-size: 1.6em; } h2 { border-bottom: 2px solid #ccc; padding-bottom: .2em; margin-top: 2em; }
table { border-collapse: collapse; margin: .8em 0; font-size: .92em; }
th, td { border: 1px solid #ccc; padding: .25em .6em; text-align: right; }
th { background: #f0f0f0; } td.l, th.l { text-align: left; }
tr.gap td { background: #fff4e0; }
img { max-width: 100%; border: 1px solid #eee; margin: .5em 0; }
pre { background: #f6f6f6; padding: .6em; overflow-x: auto; white-space: pre-wrap; }
.na { color: #777; font-style: italic; }
.warn { color: #8a4b00; }
.severe { color: #b00000; font-weight: 600; }
td.w { text-align: left; font-size: .9em; max-width: 32em; }
td.w ul, ul.w { margin: 0; padding-left: 1.1em; }
tr.fit td { background: #fff0f0; }
.status-poor, .status-unidentified { color: #8a4b00; font-weight: 600; }
.status-prior, .status-placement { color: #777; }
.viewer { width: 100%; min-height: 620px; border: 1px solid #eee; }
nav ol { columns: 2; }
"""


# ----------------------------------------------------------------------------- helpers
def _e(x) -> str:
    return html.escape(str(x), quote=True)


def _fmt(x, digits: int = 4) -> str:
    if x is None:
        return "–"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int | np.integer):
        return str(int(x))
    try:
        v = float(x)
    except (TypeError, ValueError):
        return _e(x)
    if not math.isfinite(v):
        return "–"
    return f"{v:.{digits}g}"


def _interval(ci) -> str:
    if not isinstance(ci, list | tuple) or len(ci) != 2:
        return "–"
    return f"[{_fmt(ci[0])}, {_fmt(ci[1])}]"


def _table(head, rows, left=(0,), row_class=None, cell_class=None) -> str:
    th = "".join(f'<th class="{"l" if i in left else ""}">{_e(h)}</th>' for i, h in enumerate(head))
    cell_class = cell_class or {}
    body = []
    for r, row in enumerate(rows):
        cls = f' class="{row_class[r]}"' if row_class and row_class[r] else ""
        tds = "".join(f'<td class="{cell_class.get(i, "l" if i in left else "")}">{c}</td>'
                      for i, c in enumerate(row))
        body.append(f"<tr{cls}>{tds}</tr>")
    return f"<table><thead><tr>{th}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def _na(what: str = "") -> str:
    return f'<p class="na">{_e(what + ": " if what else "")}{NOT_AVAILABLE}.</p>'


def _img(png: bytes, alt: str) -> str:
    return f'<img alt="{_e(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode("ascii")}">'


# ----------------------------------------------------------------------------- figures
def _plt():
    from skelid.plots import _plt as get

    return get()


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    _plt().close(fig)
    return buf.getvalue()


def _ref_lines(ax, refs: dict, vertical: bool = True):
    styles = {"true value": dict(color="k", ls="--", lw=1.2),
              "nominal (model file)": dict(color="0.45", ls=":", lw=1.2)}
    for label, v in refs.items():
        if v is None or not math.isfinite(v):
            continue
        kw = styles.get(label, dict(color="k", ls="--", lw=1))
        (ax.axvline if vertical else ax.axhline)(v, label=f"{label} {v:.4g}", **kw)


def _zoom(ax, axis, weights, extra=()):
    """Limit the x axis to where the posterior mass is (and the reference values)."""
    los, his = [], []
    for w in weights:
        w = np.asarray(w, float)
        if not np.isfinite(w).all() or w.sum() <= 0:
            continue
        c = np.cumsum(w) / w.sum()
        los.append(axis[min(np.searchsorted(c, 0.0005), axis.size - 1)])
        his.append(axis[min(np.searchsorted(c, 0.9995), axis.size - 1)])
    if not los:
        return
    vals = [v for v in extra if v is not None and math.isfinite(v)]
    lo, hi = min(los + vals), max(his + vals)
    pad = max(0.25 * (hi - lo), 2 * float(axis[1] - axis[0]) if axis.size > 1 else 1.0)
    ax.set_xlim(max(lo - pad, float(axis[0])), min(hi + pad, float(axis[-1])))


def fig_trajectories(markers, names, rate, units) -> bytes:
    plt = _plt()
    F, M, D = markers.shape
    t = np.arange(F) / rate
    fig, axes = plt.subplots(D, 1, figsize=(9, 2.3 * D + 0.8), sharex=True, squeeze=False)
    for k, ax in enumerate(axes[:, 0]):
        for m in range(M):
            ax.plot(t, markers[:, m, k], lw=0.9, label=names[m])
        ax.set_ylabel(f"{'xyz'[k]} [{units}]")
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=7, ncol=min(M, 6), loc="upper left", bbox_to_anchor=(0, 1.35))
    fig.suptitle("Marker trajectories (model markers, model units; gaps are missing frames)", y=1.02)
    return _png(fig)


def fig_missing(markers, names, rate) -> bytes:
    plt = _plt()
    F, M, _ = markers.shape
    missing = ~np.isfinite(markers).all(axis=2)
    fig, ax = plt.subplots(figsize=(9, 0.35 * M + 1.2))
    for m in range(M):
        x = np.concatenate([[False], missing[:, m], [False]]).astype(int)
        starts = np.flatnonzero(np.diff(x) == 1)
        stops = np.flatnonzero(np.diff(x) == -1)
        ax.broken_barh([(s / rate, (e - s) / rate) for s, e in zip(starts, stops, strict=True)],
                       (m - 0.4, 0.8), color="tab:red")
    ax.set_yticks(range(M), names)
    ax.set_ylim(-0.6, M - 0.4)
    ax.set_xlim(0, F / rate)
    ax.set_xlabel("time [s]")
    ax.set_title("Missing markers (red: frames where the marker is missing)")
    ax.grid(axis="x", alpha=0.3)
    return _png(fig)


def fig_history(axis, snaps, steps, final, name, units, refs, method) -> bytes:
    plt = _plt()
    h = float(axis[1] - axis[0]) if axis.size > 1 else 1.0
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    for s, w in zip(steps, snaps, strict=True):
        ax.plot(axis, w / h, lw=1.2, label=f"after {int(s)} frames")
    if final is not None:
        ax.plot(axis, final / h, lw=2, color="k", alpha=0.7, label="final")
    _ref_lines(ax, refs)
    _zoom(ax, axis, [*snaps, *([] if final is None else [final])], refs.values())
    ax.set_xlabel(f"{name} [{units}]")
    ax.set_ylabel(f"posterior density [1/{units}]")
    ax.set_title(f"Posterior of {name} as frames accumulate ({method} method)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return _png(fig)


def fig_gaussian_history(steps, means, sds, name, units, refs, method) -> bytes:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    ax.plot(steps, means, lw=1.5, label="posterior mean")
    ax.fill_between(steps, means - 1.96 * sds, means + 1.96 * sds, alpha=0.25, label="95 % interval")
    _ref_lines(ax, refs, vertical=False)
    ax.set_xlabel("frames used")
    ax.set_ylabel(f"{name} [{units}]")
    ax.set_title(f"Posterior of {name} as frames accumulate ({method} method)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return _png(fig)


def fig_map_path(map_path, measured, name, units, refs, method) -> bytes:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    steps = np.arange(1, len(map_path) + 1)
    map_path = np.asarray(map_path, float)
    if measured is not None and np.isfinite(measured).any():
        first = int(np.argmax(np.isfinite(measured)))  # before it the "most likely value" is only the prior's
        map_path = np.where(steps > first, map_path, np.nan)
    if measured is not None:
        ax.plot(steps, measured, ".", ms=2.5, color="0.6", label="per-frame measured value")
    ax.plot(steps, map_path, lw=1.5, label="most likely value so far")
    _ref_lines(ax, refs, vertical=False)
    finite = np.asarray(map_path)[np.isfinite(map_path)]
    if finite.size:
        lo, hi = float(finite.min()), float(finite.max())
        vals = [v for v in refs.values() if v is not None and math.isfinite(v)]
        lo, hi = min([lo, *vals]), max([hi, *vals])
        pad = max(hi - lo, 1e-9 + 0.02 * max(abs(hi), 1.0))
        ax.set_ylim(lo - pad, hi + pad)
    ax.set_xlabel("frame")
    ax.set_ylabel(f"{name} [{units}]")
    ax.set_title(f"Most likely {name} after each frame ({method} method)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return _png(fig)


def fig_final(panels, units, method) -> bytes:
    """One panel per parameter: the final marginal, its 95 % interval, the Cramér–Rao bound."""
    from matplotlib.ticker import MaxNLocator
    from scipy.stats import norm

    plt = _plt()
    n = len(panels)
    ncol = min(n, 3)
    nrow = math.ceil(n / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.3 * nrow), squeeze=False)
    for ax in axes.ravel()[n:]:
        ax.set_visible(False)
    for ax, p in zip(axes.ravel(), panels, strict=False):
        mean, sd, ci = p["mean"], p["sd"], p["ci95"]
        if p.get("axis") is not None:
            x, w = p["axis"], p["marginal"]
            h = float(x[1] - x[0]) if x.size > 1 else 1.0
            ax.plot(x, w / h, lw=1.5, label="posterior")
            _zoom(ax, x, [w], [*p["refs"].values(), *(ci or [])])
        else:
            s = sd if sd and sd > 0 else 1.0
            x = np.linspace(mean - 4.5 * s, mean + 4.5 * s, 301)
            ax.plot(x, norm.pdf(x, mean, s), lw=1.5, label=p.get("kind_label", "posterior (normal)"))
        if ci and all(c is not None and math.isfinite(c) for c in ci):
            ax.axvspan(ci[0], ci[1], alpha=0.15, color="tab:blue", label="95 % interval")
        crlb = p.get("crlb_sd")
        if crlb is not None and math.isfinite(crlb) and crlb > 0:
            xc = np.linspace(mean - 4.5 * crlb, mean + 4.5 * crlb, 301)
            ax.plot(xc, norm.pdf(xc, mean, crlb), "--", color="tab:orange", lw=1.2,
                    label=f"Cramér–Rao bound (sd {crlb:.3g})")
        _ref_lines(ax, p["refs"])
        ax.set_xlabel(f"{p['name']} [{units}]")
        ax.set_ylabel(f"density [1/{units}]")
        ax.xaxis.set_major_locator(MaxNLocator(5))
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    fig.suptitle(f"Final posterior of each parameter ({method} method)")
    fig.tight_layout()
    return _png(fig)


def fig_residuals(residuals, names, rate, units, sigma, method) -> bytes:
    plt = _plt()
    F, M = residuals.shape
    t = np.arange(F) / rate
    fig, ax = plt.subplots(figsize=(9, 4.5))
    for m in range(M):
        ax.plot(t, residuals[:, m], lw=0.8, label=names[m] if m < len(names) else f"marker {m}")
    if sigma is not None and math.isfinite(sigma):
        ax.axhline(sigma, color="k", ls="--", lw=1, label=f"noise σ = {sigma:.3g} {units}")
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"residual distance [{units}]")
    ax.set_title(f"Residual of each marker over time ({method} method); slow drifts suggest soft-tissue artefact")
    ax.legend(fontsize=7, ncol=min(M + 1, 5))
    ax.grid(alpha=0.3)
    return _png(fig)


# ----------------------------------------------------------------------------- sections
class _Builder:
    """Collects HTML parts and figure jobs; figures are drawn later, under one progress bar."""

    def __init__(self):
        self.parts: list = []
        self.uses_plotly = False

    def add(self, text: str):
        self.parts.append(text)

    def figure(self, job, alt: str):
        self.parts.append((job, alt))

    def n_figures(self) -> int:
        return sum(isinstance(p, tuple) for p in self.parts)

    def render(self, progress: bool) -> str:
        from tqdm import tqdm

        bar = tqdm(total=self.n_figures(), desc="report", unit="figure", leave=False, file=sys.stderr,
                   disable=not progress or not sys.stderr.isatty())
        out = []
        # names from files are text, not mathtext: '$\\alpha$' is drawn as written
        with bar, _plt().rc_context({"text.parse_math": False}):
            for p in self.parts:
                if isinstance(p, tuple):
                    job, alt = p
                    out.append(_img(job(), alt))
                    bar.update(1)
                else:
                    out.append(p)
        return "\n".join(out)


def _refs(ctx: Mapping, pname: str) -> dict:
    refs = {}
    truth = ctx.get("truth") or {}
    if isinstance(truth, Mapping) and pname in truth:
        refs["true value"] = float(truth[pname])
    mp = (ctx.get("model_parameters") or {}).get(pname) or {}
    if mp.get("nominal") is not None and "true value" not in refs:
        refs["nominal (model file)"] = float(mp["nominal"])
    return refs


def _overview(b: _Builder, run):
    ctx = run.context
    ov = ctx.get("data_overview")
    if not isinstance(ov, Mapping):
        b.add(_na("data overview (result.json has no data_overview)"))
        return
    rows = [("data file", _e(ov.get("source", ctx.get("data", "")))),
            ("format", _e(ov.get("format", "–"))),
            ("frames", _fmt(ov.get("n_frames"))),
            ("markers in the file", _fmt(ov.get("n_markers"))),
            ("sampling rate", f"{_fmt(ov.get('rate_hz'))} Hz"),
            ("duration", f"{_fmt(ov.get('duration_s'))} s"),
            ("units in the file", _e(ov.get("units", "–"))),
            ("model", _e(ctx.get("model", "–"))),
            ("model units (results are in these)", _e(ctx.get("units", "–")))]
    b.add(_table(["", ""], rows, left=(0, 1)))
    used = ov.get("model_markers") or {}
    if used:
        b.add("<p>Model markers and their names in the file: "
              + ", ".join(f"{_e(k)} → {_e(v)}" for k, v in used.items()) + ".</p>")
    markers = ov.get("markers") or []
    if markers:
        mine = [m for m in markers if m.get("used_by_model")]
        others = [m for m in markers if not m.get("used_by_model")]
        rows = [(_e(m["name"]), _fmt(m.get("frames_missing")), _fmt(m.get("gaps")), _fmt(m.get("longest_gap")))
                for m in mine]
        cls = ["gap" if m.get("frames_missing") else "" for m in mine]
        if others:
            gappy = sum(1 for m in others if m.get("frames_missing"))
            names = ", ".join(_e(m["name"]) for m in others)
            rows.append((f"<details><summary>{len(others)} other markers in the file, not used by the model "
                         f"({gappy} with gaps)</summary>{names}</details>", "–", "–", "–"))
            cls.append("")
        b.add("<h3>Gaps of the model's markers</h3>")
        b.add(_table(["marker", "frames missing", "gaps", "longest gap [frames]"], rows, row_class=cls))


def _trajectories(b: _Builder, arrays: Mapping):
    if "markers" not in arrays:
        b.add(_na("marker trajectories (no arrays.npz)"))
        return
    y = np.asarray(arrays["markers"], float)
    names = [str(n) for n in arrays.get("marker_names", [f"m{i}" for i in range(y.shape[1])])]
    rate = float(arrays.get("rate", 1.0))
    units = str(arrays.get("units", ""))
    b.figure(partial(fig_trajectories, y, names, rate, units), "marker trajectories")
    if not np.isfinite(y).all():
        b.figure(partial(fig_missing, y, names, rate), "missing markers over time")
    else:
        b.add("<p>No marker of the model is missing in any frame.</p>")


def _evolution(b: _Builder, run, units: str):
    for method, r in run.results.items():
        b.add(f"<h3>Method: {_e(method)}</h3>")
        a = r.arrays
        names = [str(n) for n in a.get("posterior.names", list(r.parameters))]
        shown = False
        steps = a.get("posterior.history_steps")
        if str(a.get("posterior.kind", "")) == "grid" and steps is not None and len(steps):
            for k, name in enumerate(names):
                if f"posterior.history.{k}" not in a:
                    continue
                axis, hist = a[f"posterior.axis.{k}"], a[f"posterior.history.{k}"]
                final = a.get(f"posterior.marginal.{k}")
                refs = _refs(run.context, name)
                b.figure(partial(fig_history, axis, hist, steps, final, name, units, refs, method),
                         f"posterior of {name} as frames accumulate")
                shown = True
        elif "posterior.history_mean" in a and steps is not None and len(steps):
            means, covs = a["posterior.history_mean"], a["posterior.history_cov"]
            for k, name in enumerate(names):
                sds = np.sqrt(np.clip(covs[:, k, k], 0, None))
                refs = _refs(run.context, name)
                b.figure(partial(fig_gaussian_history, steps, means[:, k], sds, name, units, refs, method),
                         f"posterior of {name} as frames accumulate")
                shown = True
        if "map_path" in a and names:
            refs = _refs(run.context, names[0])
            b.figure(partial(fig_map_path, a["map_path"], a.get("measured"), names[0], units, refs, method),
                     f"most likely {names[0]} per frame")
            shown = True
        if not shown:
            b.add(_na("posterior evolution"))


def _histogram(x, w=None) -> dict:
    """Weighted histogram of posterior samples as a marginal on equal cells (``axis``, ``marginal``)."""
    x = np.asarray(x, float)
    w = np.full(x.size, 1.0 / max(x.size, 1)) if w is None else np.asarray(w, float)
    n = int(np.clip(np.sqrt(x.size), 10, 60))
    lo, hi = float(x.min()), float(x.max())
    if not hi > lo:
        hi = lo + max(abs(lo), 1.0) * 1e-6
    mass, edges = np.histogram(x, bins=n, range=(lo, hi), weights=w)
    return {"axis": 0.5 * (edges[:-1] + edges[1:]), "marginal": mass / max(mass.sum(), 1e-300)}


def _noise_line(r, units: str) -> str:
    n = r.noise
    if n is None:
        return _na("marker noise σ")
    how = "fixed, not estimated" if n.fixed else "estimated"
    ci = f", 95 % interval {_interval(n.interval)} {_e(units)}" if n.interval is not None else ""
    return f"<p>Marker noise σ = {_fmt(n.sigma)} {_e(units)} ({how}){ci}.</p>"


def _num(x) -> float | None:
    """A finite number from an untrusted JSON value, else None."""
    if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x):
        return None
    return float(x)


def per_trial_html(r, units: str) -> str:
    """Each trial's own estimate beside the joint one and the trials' consistency test (several-trial fits).

    Reads ``diagnostics['trials']``, ``['consistency']`` and ``['heterogeneity']`` of a
    :class:`~skelid.result.FitResult`; anything missing or of the wrong type is left out,
    and a result without trials gives ``""``.
    """
    d = r.diagnostics
    rows = d.get("trials")
    if not isinstance(rows, list) or not rows or not all(isinstance(t, Mapping) for t in rows):
        return ""
    names = list(r.parameters)
    out = ["<h4>Each trial's own estimate</h4>",
           f"<p>Mean ± sd [{_e(units)}]; the sd includes the between-trial spread (integrated out under "
           "the stated prior on it, or estimated with a t factor for few trials). The joint estimate is the "
           "table above.</p>"]
    body = []
    for t in rows:
        ps = t.get("parameters") if isinstance(t.get("parameters"), Mapping) else {}
        cells = []
        for n in names:
            p = ps.get(n) if isinstance(ps.get(n), Mapping) else {}
            m, sd = _num(p.get("mean")), _num(p.get("sd_with_between_trial", p.get("sd")))
            cells.append("–" if m is None else f"{_fmt(m)} ± {_fmt(sd)}")
        body.append((_e(t.get("trial", t.get("data", "–"))), _fmt(_num(t.get("frames_used"))),
                     _fmt(_num(t.get("sigma"))), *cells))
    het = d.get("heterogeneity") if isinstance(d.get("heterogeneity"), Mapping) else {}
    if het:
        body.append(("<em>between-trial sd</em>", "", "", *[
            _fmt(_num(het[n].get("tau"))) if isinstance(het.get(n), Mapping) else "–" for n in names]))
    out.append(_table(["trial", "frames used", f"σ [{units}]", *names], body))
    c = d.get("consistency")
    if isinstance(c, Mapping) and _num(c.get("statistic")) is not None and _num(c.get("p_value")) is not None:
        p = _num(c["p_value"])
        verdict = ("the trials agree within their own intervals" if p >= 0.01 else
                   "the trials disagree beyond their own intervals; the between-trial spread is in the "
                   "joint interval")
        out.append(f"<p>Consistency of the trials with the joint estimate: χ² = {_fmt(_num(c['statistic']))} on "
                   f"{_fmt(_num(c.get('dof')))} degrees of freedom, p = {_fmt(p, 2)} ({verdict}).</p>")
    elif isinstance(c, Mapping):
        out.append("<p>Consistency of the trials with the joint estimate: not tested (fewer than one degree of "
                   "freedom: one trial informs the parameters).</p>")
    return "\n".join(out)


def _final(b: _Builder, run, units: str):
    ctx = run.context
    for method, r in run.results.items():
        b.add(f"<h3>Method: {_e(method)}</h3>")
        if not r.parameters:
            b.add(_na("parameter estimates"))
            continue
        rows = [_final_row(ctx, name, p) for name, p in r.parameters.items()]
        panels = [_final_panel(ctx, r.arrays, name, p) for name, p in r.parameters.items()]
        ref_head = "true value" if ctx.get("truth") else "nominal (model file)"
        b.add(_table(["parameter", f"MAP [{units}]", f"mean [{units}]", f"sd [{units}]", "95 % interval",
                      f"Cramér–Rao sd [{units}]", "prior interval", ref_head], rows))
        b.add(_noise_line(r, units))
        b.add(per_trial_html(r, units))
        if r.frames is not None:
            dropped = f", {_fmt(r.frames.dropped)} dropped" if r.frames.dropped else ""
            b.add(f"<p>Frames used: {_fmt(r.frames.used)} of {_fmt(r.frames.total)}{dropped}.</p>")
        if "seconds" in r.provenance:
            b.add(f"<p>The fit took {_fmt(r.provenance['seconds'], 3)} s.</p>")
        if len(panels) > MAX_PANELS:  # one image no taller than about 2000 px; the table lists every one
            b.add(f"<p>The figure shows the first {MAX_PANELS} of the {len(panels)} parameters.</p>")
        b.figure(partial(fig_final, panels[:MAX_PANELS], units, method),
                 f"final posterior of each parameter ({method})")


def _final_row(ctx: dict, name: str, p) -> tuple:
    """One parameter's row of the final table: estimates, interval, bound, prior interval, reference."""
    mp = (ctx.get("model_parameters") or {}).get(name) or {}
    prior = mp.get("prior") or {}
    ref = (ctx.get("truth") or {}).get(name, mp.get("nominal"))
    return (_e(name), _fmt(p.map), _fmt(p.mean), _fmt(p.sd), _interval(p.interval),
            _fmt(p.crlb_sd) if p.crlb_sd is not None else f'<span class="na">{NOT_AVAILABLE}</span>',
            _interval([prior.get("lower"), prior.get("upper")]) if prior else "–", _fmt(ref))


def _final_panel(ctx: dict, a, name: str, p) -> dict:
    """One parameter's panel of the final figure: its grid marginal, samples' histogram or normal curve."""
    post_names = [str(n) for n in a.get("posterior.names", [])]
    panel = {"name": name, "mean": p.mean if math.isfinite(p.mean) else p.map,
             "sd": p.sd if math.isfinite(p.sd) else 0.0, "ci95": list(p.interval),
             "crlb_sd": p.crlb_sd, "refs": _refs(ctx, name)}
    k = post_names.index(name) if name in post_names else None
    if k is not None and f"posterior.axis.{k}" in a:
        panel.update(axis=a[f"posterior.axis.{k}"], marginal=a[f"posterior.marginal.{k}"])
    elif k is not None and "samples" in a:
        panel.update(_histogram(a["samples"][:, k], a.get("sample_weights")))
    elif k is not None and "posterior.cov" in a:
        panel.update(mean=float(a["posterior.mean"][k]), sd=float(np.sqrt(max(a["posterior.cov"][k, k], 0))),
                     kind_label="posterior (Gaussian)")
    else:
        panel["kind_label"] = "normal with the posterior mean and sd"
    return panel


def _residuals(b: _Builder, run, units: str):
    from skelid.workflows import lag1_autocorrelation

    names = [str(n) for n in run.arrays.get("marker_names", [])]
    rate = float(run.arrays.get("rate", 1.0))
    for method, r in run.results.items():
        b.add(f"<h3>Method: {_e(method)}</h3>")
        res = r.arrays.get("residuals")
        if res is None or np.ndim(res) != 2:
            b.add(_na("per-marker residuals"))
            continue
        res = np.asarray(res, float)
        sigma = None if r.noise is None else r.noise.sigma
        b.figure(partial(fig_residuals, res, names, rate, units, sigma, method),
                 f"residuals per marker ({method})")
        rows = []
        with np.errstate(invalid="ignore"):
            for k in range(res.shape[1]):
                col = res[:, k]
                fin = col[np.isfinite(col)]
                rows.append((_e(names[k] if k < len(names) else f"marker {k}"),
                             _fmt(np.sqrt(np.mean(fin ** 2)) if fin.size else None),
                             _fmt(fin.max() if fin.size else None), _fmt(lag1_autocorrelation(col), 2)))
        b.add(_table(["marker", f"rms [{units}]", f"max [{units}]", "lag-1 autocorrelation"], rows))
        b.add("<p>Measurement noise gives residuals that change from frame to frame (autocorrelation near 0); "
              "soft-tissue artefact gives slow drifts (autocorrelation near 1) that follow the motion.</p>")


def _identifiability(b: _Builder, run, units: str):
    for method, r in run.results.items():
        b.add(f"<h3>Method: {_e(method)}</h3>")
        rows = r.diagnostics.get("identifiability")
        if not isinstance(rows, list) or not rows:
            b.add(_na("identifiability table"))
            continue
        b.add(_table(["parameter", f"Cramér–Rao sd [{units}]", "status"],
                     [(_e(row.get("parameter", "")), _fmt(row.get("crlb_sd")), _e(row.get("status", "")))
                      for row in rows if isinstance(row, Mapping)], left=(0, 2)))


def _all_warnings(run, notes) -> list[dict]:
    out, seen = [], set()
    for w in [*run.warnings, *(w for r in run.results.values() for w in r.warnings)]:
        if w.message not in seen:
            seen.add(w.message)
            out.append({"message": w.message, "severe": _is_severe(w.code, w.message)})
    return out + [{"message": n, "severe": False} for n in notes if n not in seen]


def _warnings(b: _Builder, run, notes: list[str]):
    items = _all_warnings(run, notes)
    if items:
        b.add(_warning_list(items, show=len(items)))
    else:
        b.add("<p>No warnings.</p>")


def _provenance(b: _Builder, run):
    from skelid.workflows import versions

    prov = run.context.get("provenance") or {}
    cmd = prov.get("command")
    if cmd:
        import shlex

        text = shlex.join(str(c) for c in cmd) if isinstance(cmd, list) else str(cmd)
        b.add(f"<p>Command (run in <code>{_e(prov.get('cwd', '?'))}</code>"
              f"{', on ' + _e(prov['created']) if prov.get('created') else ''}):</p><pre>{_e(text)}</pre>")
    else:
        b.add(_na("the command (result.json does not record it)"))
    vers = prov.get("versions")
    if isinstance(vers, Mapping) and vers:
        b.add(_table(["package", "version"], [(_e(k), _e(v)) for k, v in vers.items()], left=(0, 1)))
    else:
        b.add(_na("versions (result.json does not record them)"))
    now = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    b.add(f"<p>This report was written on {_e(now)} by skelid {_e(versions()['skelid'])}.</p>")


# ----------------------------------------------------------------------------- summary
#: warning codes that say the numbers themselves may be wrong (shown in red)
SEVERE_CODES = frozenset({"not-converged", "approximation-broken", "broken-approximation", "unreliable-fit",
                          "sampler-not-mixed", "sampler-stage-limit", "fallback"})
_SEVERE_TEXT = re.compile(r"not converg|before converging|failed to converge|approximation (is )?broke|"
                          r"not have mixed|jumped to the posterior|unreliable", re.I)


def _is_severe(code: str, message: str) -> bool:
    return code in SEVERE_CODES or bool(_SEVERE_TEXT.search(message))


def _method_warnings(run, method: str) -> list[dict]:
    """This method's warnings and the run's that concern it (or no method), as ``{message, parameters, severe}``."""
    r = run.results[method]
    others = [k for k in run.results if k != method]
    items = list(r.warnings)
    theirs = {w.message for o in others for w in run.results[o].warnings}
    for w in run.warnings:  # run-level: this method's, or no method's
        if w.message in theirs and w.message not in {x.message for x in r.warnings}:
            continue
        if f"{method} method" in w.message or not any(f"{o} method" in w.message for o in others):
            items.append(w)
    out, seen = [], set()
    for w in items:
        if w.message in seen:
            continue
        seen.add(w.message)
        out.append({"message": w.message, "parameters": [p for p in w.parameters if p in r.parameters],
                    "severe": _is_severe(w.code, w.message)})
    return out


def _warning_list(items: list[dict], cls: str = "w", show: int = 6) -> str:
    """Warnings as a list, severe ones first and in red; beyond ``show`` of them the rest fold away."""
    items = sorted(items, key=lambda w: not w["severe"])

    def li(ws):
        return "".join(f'<li class="{"severe" if w["severe"] else "warn"}">{_e(w["message"])}</li>' for w in ws)

    if not items:
        return ""
    if len(items) <= show:
        return f'<ul class="{cls}">{li(items)}</ul>'
    return (f'<ul class="{cls}">{li(items[:show - 1])}</ul><details><summary>{len(items) - show + 1} more '
            f'warnings</summary><ul class="{cls}">{li(items[show - 1:])}</ul></details>')


def _status_cell(p) -> str:
    if not p.extra.get("status_given", True):
        return "–"
    return f'<span class="status-{_e(p.status)}">{_e(p.status)}</span>'


#: panels of the final-posterior figure (six rows of three: an image about 2000 px tall)
MAX_PANELS = 18
#: rows of a long table shown before the rest folds away
TABLE_ROWS = 16


def _folded_table(head, rows, what: str, left=(0,)) -> str:
    """A table whose rows beyond :data:`TABLE_ROWS` fold away under a summary line."""
    if len(rows) <= TABLE_ROWS:
        return _table(head, rows, left=left)
    return (_table(head, rows[:TABLE_ROWS], left=left) + f"<details><summary>{len(rows) - TABLE_ROWS} more "
            f"{_e(what)}</summary>{_table(head, rows[TABLE_ROWS:], left=left)}</details>")


def _opensim(b: _Builder, run, units: str):
    """An OpenSim scaling, answered first: each body's scale factors (ratios) with their intervals, the
    lengths between joint centres, each marker's residual (landmarks apart from placed markers), each
    warning once in a line with its detail folded."""
    from skelid.errors import headline

    sc = run.context.get("scaling") or {}
    trials = sc.get("trial_names") or [str(run.context.get("data", ""))]
    b.add(f"<p><b>{_e(Path(str(sc.get('source_model', ''))).name)}</b> scaled to {len(trials)} trial(s): "
          f"{_e(', '.join(trials))}. The scaled model, its ScaleSet and the scaling table are beside this "
          "report.</p>")
    peer = sc.get("scaletool") if isinstance(sc.get("scaletool"), dict) else None
    rows = _scale_rows(sc.get("scales") or {}, peer)
    b.add("<h3>Scale factors (ratios to the generic model)</h3>")
    if peer is not None:
        b.add(_scaletool_line(peer))
    head = ["body", "axis", "factor", "95 % interval"] + (["OpenSim ScaleTool"] if peer is not None else [])
    b.add(_folded_table(head + ["Cramér–Rao sd"], rows, "scale factors") if rows else _na("scale factors"))
    lengths = sc.get("lengths_mm") or {}
    if lengths:
        b.add(f"<h3>Lengths between joint centres [{_e(units)}]</h3>")
        b.add(_folded_table(["segment", "length", "95 % interval"],
                            [(_e(k), _fmt(v.get("value"), 5), _interval(v.get("ci95"))) for k, v in lengths.items()],
                            "lengths"))
    b.add(_marker_residuals(run, set(sc.get("fixed_markers") or []), units))
    warns = list(dict.fromkeys(str(w) for w in (sc.get("warnings") or [])))
    if warns:
        b.add(f"<h3>Warnings ({len(warns)})</h3><ul class=\"w\">" + "".join(
            f"<li>{_e(headline(w, 160))}" + (f"<details><summary>detail</summary>{_e(w)}</details>"
                                              if headline(w, 160) != " ".join(w.split()) else "") + "</li>"
            for w in warns) + "</ul>")


def _scale_rows(scales: Mapping, peer: dict | None) -> list[tuple]:
    """One row per body and axis: the factor, its interval, ScaleTool's factor where it ran, the CRLB."""
    beside = {(r.get("body"), r.get("axis")): r for r in (peer or {}).get("compared") or [] if isinstance(r, dict)}
    rows = []
    for body, axes in scales.items():
        for ax, e in axes.items():
            r = beside.get((body, ax))
            st = [] if peer is None else ["–" if r is None else
                                          _fmt(r.get("scaletool")) + ("" if r.get("inside") else " (outside)")]
            rows.append((_e(body), "one factor" if ax == "xyz" else ax, _fmt(e.get("value")),
                         _interval(e.get("ci95")), *st, _fmt(e.get("crlb_sd"))))
    return rows


def _scaletool_line(peer: dict) -> str:
    """Which ScaleTool run stands beside the factors, and how many of its factors skelid's intervals hold."""
    rng = peer.get("time_range") or []
    when = f" at {_fmt(rng[0], 3)}–{_fmt(rng[1], 3)} s" if len(rng) == 2 else ""
    return (f"<p>OpenSim's ScaleTool {_e(peer.get('opensim_version', ''))} on the setup "
            f"<code>{_e(Path(str(peer.get('setup', ''))).name)}</code> (static trial "
            f"<code>{_e(Path(str(peer.get('static_trial', ''))).name)}</code>{when}; measurements: "
            f"{_e(', '.join(map(str, peer.get('measurements') or [])) or 'none')}): "
            f"{_e(peer.get('inside', 0))} of {_e(peer.get('n_compared', 0))} of its factors lie inside skelid's "
            "95 % interval. A factor outside is one the markers contradict (or one its measurements set for "
            "another body).</p>")


def _marker_residuals(run, fixed: set, units: str) -> str:
    """Each marker's rms and largest distance from the fitted model, the landmarks (fixed) apart from the
    markers placed on the subject, largest first."""
    r = next(iter(run.results.values()), None)
    res = None if r is None else r.arrays.get("residuals")
    names = [str(n) for n in run.arrays.get("marker_names", [])]
    if res is None or np.ndim(res) != 2 or np.shape(res)[1] != len(names):
        return _na("per-marker residuals (no arrays.npz)")
    res = np.asarray(res, float)
    with np.errstate(invalid="ignore"):
        rms = np.sqrt(np.nanmean(res**2, axis=0))
        big = np.nanmax(np.where(np.isfinite(res), res, -np.inf), axis=0)
    out = [f"<h3>Residuals per marker [{_e(units)}]</h3>"]
    for label, keep in (("landmarks (fixed in the marker set)", lambda n: n in fixed),
                        ("markers placed on the subject", lambda n: n not in fixed)):
        idx = sorted((k for k, n in enumerate(names) if keep(n)), key=lambda k: -rms[k] if np.isfinite(rms[k]) else 0)
        if idx:
            out.append(f"<p>{_e(label)}: {len(idx)}</p>" + _folded_table(
                ["marker", "rms", "largest"], [(_e(names[k]), _fmt(rms[k], 2), _fmt(big[k], 2)) for k in idx],
                "markers"))
    return "".join(out)


def _summary(b: _Builder, run, units: str, notes: list[str]):
    """The answer: every estimate with its interval, bound, status and warnings (and, with model
    alternatives, its spread over the models); the noise of each marker; then the other warnings."""
    for method, r in run.results.items():
        b.add(f"<h3>Method: {_e(method)}</h3>")
        warns = _method_warnings(run, method)
        spread = _model_spread(r)
        rows, cls = _summary_rows(r, warns, units, spread)
        if not rows:
            b.add(_na("parameter estimates"))
            continue
        head = ["parameter", f"estimate [{units}]", "95 % interval", f"Cramér–Rao sd [{units}]", "status",
                *([f"spread over models [{units}]"] if spread else []), "warnings"]
        last = len(head) - 1
        b.add(_table(head, rows, left=(0, last), row_class=cls, cell_class={last: "w"}))
        if spread:
            b.add(_spread_note(r.diagnostics["model_sensitivity"]))
        if r.noise is not None and r.noise.per_marker:
            b.add(_per_marker_noise(r.noise, units))
        rest = [w for w in warns if not w["parameters"] and not w["severe"]]
        if rest:
            b.add(f"<p>Other warnings about this fit:</p>{_warning_list(rest)}")
    if notes:
        b.add(_warning_list([{"message": n, "severe": False} for n in notes]))


def _summary_rows(r, warns: list[dict], units: str, spread: dict | None) -> tuple[list, list]:
    """Rows of the summary table (and their classes): the whole fit's severe warnings, then each
    parameter, derived length and the noise level; with ``spread``, its column before the warnings."""
    rows, cls = [], []

    def add(cells, key, row_class=""):
        *main, warn = cells
        extra = [] if spread is None else ["–" if key is None else _spread_cell(spread.get(key))]
        rows.append((*main, *extra, warn))
        cls.append(row_class)

    fit_wide = [w for w in warns if not w["parameters"] and w["severe"]]
    if fit_wide:
        add(["<b>the whole fit</b>", "", "", "", "", _warning_list(fit_wide)], None, "fit")
    for name, p in r.parameters.items():
        mine = [w for w in warns if name in w["parameters"]]
        add([_e(name), *_estimate_cells(p, units), _warning_list(mine)], name)
    for name, p in r.derived.items():
        add([f"{_e(name)} <small>(derived length)</small>", *_estimate_cells(p, units), ""], name)
    if r.noise is not None:
        add(["marker noise σ" + (" <small>(fixed)</small>" if r.noise.fixed else ""), _fmt(r.noise.sigma),
             _interval(r.noise.interval), "–", "–", ""], None)
    return rows, cls


def _estimate_cells(p, units: str) -> list[str]:
    """Estimate (with its unit where it is not the model's), interval, Cramér–Rao sd and status."""
    unit = "" if p.unit == units else f" {_e(p.unit)}"
    return [_fmt(p.mean if math.isfinite(p.mean) else p.map) + unit, _interval(p.interval),
            _fmt(p.crlb_sd) if p.crlb_sd is not None else '<span class="na">–</span>', _status_cell(p)]


def _model_spread(r) -> dict | None:
    """``{quantity: spread record}`` of ``skelid fit --alternative`` (see :mod:`skelid.sensitivity`), or None."""
    sens = r.diagnostics.get("model_sensitivity")
    spread = sens.get("spread") if isinstance(sens, Mapping) else None
    if not (isinstance(spread, Mapping) and spread):
        return None
    avg = (sens.get("average") or {}).get("quantities") or {}
    return {k: {**v, "average": avg.get(k)} if isinstance(v, Mapping) else v for k, v in spread.items()}


def _spread_cell(rec) -> str:
    """The range of one quantity's estimates over the models, with each model's value on hover;
    in colour where it is wider than the widest of the models' own sds."""
    if not isinstance(rec, Mapping):
        return '<span class="na">–</span>'
    values = ", ".join(f"{k}: {_fmt(v)}" for k, v in (rec.get("values") or {}).items())
    wide = _finite(rec.get("spread")) > _finite(rec.get("largest_sd"), math.inf)
    cell = f'<span class="{"warn" if wide else ""}" title="{_e(values)}">{_fmt(rec.get("spread"))}</span>'
    avg = rec.get("average")
    if isinstance(avg, Mapping) and isinstance(avg.get("interval"), list | tuple):
        cell += f"<br><small>average {_fmt(avg.get('value'))} {_interval(avg['interval'])}</small>"
    return cell


def _finite(x, default: float = math.nan) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return default
    return v if math.isfinite(v) else default


def _spread_note(sens: Mapping) -> str:
    models = ", ".join(_e(m) for m in sens.get("models") or [])
    avg = sens.get("average") if isinstance(sens.get("average"), Mapping) else {}
    weights = ", ".join(f"{_e(m)} {_finite(w):.2f}" for m, w in (avg.get("weights") or {}).items())
    average = (f" Under it, the models' average: each model weighted by stacking over {avg.get('blocks')} blocks "
               f"of {_e(str(avg.get('unit')))} ({weights}), the share of the data it predicts best, and the "
               "interval the mixture of the models' own, which holds the choice of model where the data cannot "
               "settle it." if weights else "")
    return (f"<p>Model sensitivity: the data were fitted again under each model ({models}); the spread is the "
            "range of an estimate over them (hover for each model's value). It measures how much the answer "
            "depends on modelling choices the data cannot settle, which no interval from one model contains; "
            'a spread <span class="warn">in colour</span> exceeds the largest of the models\' own sds.'
            f"{average}</p>")


def _per_marker_noise(noise, units: str, show: int = 12) -> str:
    """The noise level of each marker, highest first (the rest folded away beyond ``show``)."""
    items = sorted(noise.per_marker.items(), key=lambda kv: -_finite(kv[1], -math.inf))
    pooled = noise.sigma

    def cell(k, v):
        high = math.isfinite(pooled) and _finite(v) > 1.5 * pooled
        return f'<span class="{"warn" if high else ""}">{_e(k)} {_fmt(v, 3)}</span>'

    text = ", ".join(cell(k, v) for k, v in items[:show])
    if len(items) > show:
        text += (f"<details><summary>{len(items) - show} more markers</summary>"
                 + ", ".join(cell(k, v) for k, v in items[show:]) + "</details>")
    return (f"<p>Marker noise per marker (σ in {_e(units)}, highest first; in colour: more than 1.5 times the "
            f"pooled σ {_fmt(pooled)}): {text}</p>")


# ----------------------------------------------------------------------------- the fitted body
def _model_of(ctx: Mapping):
    """The fitted model from the result's context (``model_description``), or None."""
    desc = ctx.get("model_description")
    if not isinstance(desc, Mapping):
        return None
    from skelid.model import model_from_dict

    try:
        return model_from_dict(dict(desc), str(ctx.get("model", "model")))
    except (SkelidError, KeyError, TypeError, ValueError):
        return None


def _body(b: _Builder, run, units: str):
    """The interactive view of the fitted body over the trial (the first method with poses, else the first)."""
    from skelid import viewer

    model = _model_of(run.context)
    if model is None:
        b.add(_na("the view of the fitted body (the result holds no model description; "
                  "rerun skelid fit to get it)"))
        return
    if "markers" not in run.arrays:
        b.add(_na("the view of the fitted body (no arrays.npz)"))
        return
    method = next((k for k, r in run.results.items() if r.parameters and "pose" in r.arrays),
                  next((k for k, r in run.results.items() if r.parameters), None))
    if method is None:
        b.add(_na("the view of the fitted body (no estimates)"))
        return
    r = run.results[method]
    theta = np.array([r.parameters[n].mean if n in r.parameters else float(v)
                      for n, v in zip(model.parameter_names, model.theta_nominal, strict=True)])
    y = np.asarray(run.arrays["markers"], float)
    if y.ndim != 3 or y.shape[1:] != (len(model.markers), model.dim) or not len(y):
        from skelid.errors import FormatError

        raise FormatError(f"arrays.npz: the markers array has shape {y.shape}, not (frames, "
                          f"{len(model.markers)}, {model.dim}) as model {model.name!r} needs",
                          "fit again with 'skelid fit --out' to rewrite the result folder")
    pose = r.arrays.get("pose", r.arrays.get("poses"))
    keep, _ = viewer.decimation(len(y))
    if pose is not None and np.shape(pose) == (len(y), model.n_pose):
        pose = np.array(pose, float)
        res = r.arrays.get("residuals")
        if res is not None and np.shape(res)[0] == len(y):  # frames the fit skipped have no pose
            pose[~np.isfinite(np.asarray(res, float)).any(axis=1)] = np.nan
        how = f"the poses the {_e(method)} method estimated"
    else:
        from skelid.estimators.fit.pose import pose_determined, track_poses

        q, _ = track_poses(model, theta, y[keep], np.random.default_rng(0))
        q[~pose_determined(model, y[keep])] = np.nan
        pose = np.full((len(y), model.n_pose), np.nan)
        pose[keep] = q
        how = (f"poses fitted to the shown frames at the {_e(method)} method's estimate "
               "(the method estimates no poses)")
    rate = float(run.arrays.get("rate", 1.0))
    spec = viewer.figure_spec(model, theta, pose, y, rate=rate, units=units,
                              title=f"{model.name}: fitted body ({method} method) and measured markers")
    meta = spec["meta"]
    shown = (f"all {meta['frames_total']} frames" if meta["stride"] == 1 else
             f"every {meta['stride']}-th frame of {meta['frames_total']} ({meta['frames_shown']} frames)")
    b.add(f"<p>The {_e(method)} method's estimate of the geometry in {how}: segments (dark lines between joint "
          f"centres), joint centres (green), model markers (orange) and the measured markers (blue), the "
          f"residual between them in red. Drag to rotate, scroll to zoom; the slider picks the frame "
          f"({shown}; at most {viewer.MAX_FRAMES} frames are put in the page).</p>")
    b.add(viewer.viewer_html(spec))
    b.uses_plotly = True


def load_run(result_dir):
    """``(run, notes)``: the :class:`~skelid.result.FitRun` a result folder holds and what it lacks.

    Read by :func:`skelid.io.results.read_run`, which checks everything first: a
    damaged, foreign or old folder is refused in one line (:class:`~skelid.errors.FormatError`).
    """
    from skelid.io.results import read_run

    d = Path(result_dir)
    if d.is_dir() and not (d / "result.json").exists() and (d / "summary.json").exists():
        raise SkelidError(f"{d} holds demo output, which has no single fit",
                          "run 'skelid fit MODEL DATA --out DIR' and give DIR")
    run = read_run(d)
    notes = [] if (d / "arrays.npz").is_file() else [
        f"{d} has no arrays.npz: the report has no trajectory, posterior-evolution or "
        "residual figures (rerun skelid fit with --out to get them)"]
    return run, notes


def build_html(result, arrays=None, notes=(), progress: bool = False) -> str:
    """The report as one HTML string (figures and the view's library embedded).

    Parameters
    ----------
    result : FitRun, FitResult or ``result.json`` dict
    arrays : mapping, optional
        The arrays of a ``result.json`` dict.
    """
    from skelid.io.frames import as_run

    run = as_run(result, arrays)
    ctx = run.context
    units = str(ctx.get("units") or run.arrays.get("units", "") or
                next((p.unit for r in run.results.values() for p in r.parameters.values()), ""))
    b = _Builder()
    data = " + ".join(Path(d.strip()).name for d in str(ctx.get("data", "")).split(" + ") if d.strip())
    title = f"skelid report: {ctx.get('model', 'model')} on {data or 'data'}"
    head = (f'<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n<title>{_e(title)}</title>\n'
            f"<style>{CSS}</style>\n")
    b.add("</head>\n<body>\n" f"<h1>{_e(title)}</h1>")
    methods = ", ".join(run.results) or "none"
    b.add(f"<p>Methods: {_e(methods)}. All lengths are in {_e(units)}.</p>")
    shown = ((("opensim", "The scaled OpenSim model"),) if ctx.get("scaling") else ()) + SECTIONS
    b.add("<nav><ol>" + "".join(f'<li><a href="#{k}">{_e(t)}</a></li>' for k, t in shown) + "</ol></nav>")
    sections = {"opensim": lambda: _opensim(b, run, units),
                "summary": lambda: _summary(b, run, units, list(notes)), "body": lambda: _body(b, run, units),
                "overview": lambda: _overview(b, run), "trajectories": lambda: _trajectories(b, run.arrays),
                "evolution": lambda: _evolution(b, run, units), "posterior": lambda: _final(b, run, units),
                "residuals": lambda: _residuals(b, run, units),
                "identifiability": lambda: _identifiability(b, run, units),
                "warnings": lambda: _warnings(b, run, list(notes)), "provenance": lambda: _provenance(b, run)}
    for key, heading in shown:
        b.add(f'<h2 id="{key}">{_e(heading)}</h2>')
        sections[key]()
    b.add("</body>\n</html>")
    body = b.render(progress)
    if b.uses_plotly:
        from skelid.viewer import plotly_script

        head += plotly_script() + "\n"
    return head + body + "\n"


def write_report(result_dir, out=None, progress: bool = False) -> tuple[Path, list[str]]:
    """Write the HTML report of ``result_dir`` to ``out`` (default ``result_dir/report.html``).

    Returns
    -------
    path : Path
    notes : list of str
        What the report could not include, for the user to read.
    """
    run, notes = load_run(result_dir)
    out = Path(out) if out is not None else Path(result_dir) / "report.html"
    inputs = {(Path(result_dir) / n).resolve() for n in ("result.json", "arrays.npz")}
    if out.resolve() in inputs:
        raise SkelidError(f"--out {out} would overwrite the input {out.name}", "choose another file name")
    if out.is_dir():
        raise SkelidError(f"--out {out} is a folder", "give the name of the HTML file to write, e.g. report.html")
    ensure_parent(out)
    text = build_html(run, None, notes, progress)
    with atomic_write(out, newline="\n") as fh:
        fh.write(text)
    return out, notes
