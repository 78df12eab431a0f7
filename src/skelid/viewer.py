"""An interactive view of the fitted body, for the HTML report.

For a fitted geometry ``theta`` and the poses ``q_t`` of the trial's frames,
forward kinematics (:func:`skelid.model.kinematics.forward_kinematics`) gives
in every frame ``t``

.. math::

    c_{ts} = p_{w s}(q_t, \\theta) \\quad \\text{(joint centre of segment } s),
    \\qquad \\hat x_{tm} = x_m(q_t, \\theta) \\quad \\text{(model marker } m),

which the view draws against the measured markers ``y_{tm}``: the segments as
lines from each parent's joint centre to its child's, the joint centres, the
model markers, thin lines from each segment's joint centre to its markers, and
the residual ``y_{tm} - \\hat x_{tm}`` as a red line. A slider picks the frame
and a button plays the trial. 3-D models get a rotatable 3-D scene, planar
models a 2-D plot with equal axes.

The page uses plotly.js, inlined from the ``plotly`` package's offline bundle
(:func:`plotly_script`), so the report stays one file that works offline. Long
trials are decimated: at most ``max_frames`` frames are shown, every ``k``-th
frame with ``k = ceil(F / max_frames)``, and the page says so. Coordinates are
rounded to a ten-thousandth of the body's size (0.1 mm for a 1 m body).

Every name (marker, segment, method) enters the page as text: JSON with ``<``,
``>`` and ``&`` escaped, plotly's pseudo-HTML escaped, and LaTeX typesetting
off, so ``$\\alpha$`` or ``<script>`` are shown as written.

Examples
--------
>>> import numpy as np
>>> from skelid.simulate import builtin_model
>>> model = builtin_model("case-a")
>>> pose = np.zeros((10, model.n_pose))
>>> spec = figure_spec(model, model.theta_nominal, pose, measured=None)
>>> spec["meta"]["frames_shown"], spec["meta"]["dim"]
(10, 2)
"""

from __future__ import annotations

import html
import json
import math

import numpy as np

from skelid.model.description import Model
from skelid.model.kinematics import forward_kinematics

#: at most this many frames are put in the page (longer trials are decimated)
MAX_FRAMES = 250

#: the order of the traces in the figure and in every animation frame
TRACES = ("measured markers", "model markers", "residual", "segments", "joint centres", "marker offsets")


def decimation(n_frames: int, max_frames: int = MAX_FRAMES) -> tuple[np.ndarray, int]:
    """Indices of the frames to show and the stride ``k``: every ``k``-th frame, at most ``max_frames``."""
    stride = max(1, math.ceil(n_frames / max(int(max_frames), 1)))
    return np.arange(0, n_frames, stride), stride


def body_positions(model: Model, theta, poses) -> tuple[np.ndarray, np.ndarray]:
    """Joint centres ``(K, S, D)`` and model markers ``(K, M, D)`` of ``poses (K, Q)`` at ``theta (P,)``.

    A frame whose pose is not finite (the fit skipped it) gives NaN.
    """
    poses = np.asarray(poses, float)
    ok = np.isfinite(poses).all(axis=-1)
    kin = forward_kinematics(model, np.asarray(theta, float), np.where(ok[:, None], poses, 0.0))
    joints = np.where(ok[:, None, None], kin.p_world_seg, np.nan)
    markers = np.where(ok[:, None, None], kin.markers, np.nan)
    return joints, markers


def _text(s) -> str:
    """A name as plotly shows it literally (its pseudo-HTML escaped)."""
    return html.escape(str(s), quote=False)


def _lines(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Segments ``a[k] -> b[k]`` as one polyline with NaN breaks: ``(..., 3 N, D)``."""
    gap = np.full(a.shape, np.nan)
    return np.stack([a, b, gap], axis=-2).reshape(*a.shape[:-2], 3 * a.shape[-2], a.shape[-1])


def _round(a: np.ndarray, decimals: int) -> list:
    """Rounded values as a JSON list, NaN as null."""
    a = np.round(np.asarray(a, float), decimals)
    return [None if not math.isfinite(v) else (int(v) if decimals <= 0 else float(v)) for v in a.ravel()]


def _up_axis(joints: np.ndarray) -> int:
    """The coordinate axis from the leaf joint centres to the root's (pelvis above feet), signed +1-based."""
    c = np.nanmean(joints, axis=0)
    if not np.isfinite(c).all() or c.shape[0] < 2:
        return 3
    v = c[0] - np.nanmean(c[1:], axis=0)
    k = int(np.argmax(np.abs(v)))
    return (k + 1) * (1 if v[k] >= 0 else -1)


def figure_spec(model: Model, theta, poses, measured=None, frame_index=None, rate: float = 1.0,
                units: str | None = None, title: str = "", max_frames: int = MAX_FRAMES) -> dict:
    """The plotly figure (data, layout, frames) of the fitted body over the trial.

    Parameters
    ----------
    model : Model
    theta : (P,) float
        Fitted parameters.
    poses : (F, Q) float
        Fitted pose of every frame (NaN rows for frames without one).
    measured : (F, M, D) float, optional
        The model's markers as measured (model units), NaN where missing.
    frame_index : (F,) int, optional
        Frame numbers of ``poses`` in the trial (default ``0..F-1``).
    rate : float
        Sampling rate (Hz), for the time shown on the slider.
    units : str, optional
        Length unit (default the model's).
    title : str
    max_frames : int
        Decimate to at most this many frames (see :func:`decimation`).

    Returns
    -------
    dict
        ``data``, ``layout``, ``frames`` (plotly's figure keys) and ``meta``
        (``dim``, ``frames_total``, ``frames_shown``, ``stride``).
    """
    units = units or model.units
    poses = np.asarray(poses, float)
    F, D = poses.shape[0], model.dim
    frame_index = np.arange(F) if frame_index is None else np.asarray(frame_index, int)
    keep, stride = decimation(F, max_frames)
    joints, fitted = body_positions(model, theta, poses[keep])
    y = np.full(fitted.shape, np.nan) if measured is None else np.asarray(measured, float)[keep]
    K, S, M = len(keep), joints.shape[1], fitted.shape[1]

    parent = model.parent_index
    child = np.flatnonzero(parent >= 0)
    seg_lines = _lines(joints[:, parent[child]], joints[:, child])  # (K, 3 C, D)
    offsets = _lines(joints[:, model.marker_segment], fitted)  # (K, 3 M, D)
    resid = _lines(fitted, y)

    ranges, decimals = _ranges(D, joints, fitted, y)
    styles = _styles(D, [_text(n) for n in model.marker_names], [_text(s.joint.name) for s in model.segments])
    kind = "scatter3d" if D == 3 else "scatter"
    axes = "xyz"[:D]

    def traces(k: int, with_style: bool) -> list[dict]:
        out = []
        for j, pts in enumerate((y[k], fitted[k], resid[k], seg_lines[k], joints[k], offsets[k])):
            t = {a: _round(pts[:, i], decimals) for i, a in enumerate(axes)}
            if with_style:
                t = {"type": kind, "name": TRACES[j], **styles[j], **t}
            out.append(t)
        return out

    data = traces(0, True)
    names = [str(int(frame_index[keep[k]])) for k in range(K)]
    frames = [{"name": names[k], "data": traces(k, False), "traces": list(range(len(TRACES)))}
              for k in range(K)]
    slider, play = _animation_controls(names, F, stride, rate)
    layout = {"title": {"text": _text(title)}, "height": 620, "margin": {"l": 10, "r": 10, "t": 40, "b": 10},
              "legend": {"x": 0, "y": 1}, "sliders": [slider], "updatemenus": [play],
              "uirevision": "keep"}
    _set_axes(layout, D, joints, ranges, units)
    meta = {"dim": D, "frames_total": F, "frames_shown": K, "stride": stride,
            "n_segments": S, "n_markers": M}
    return {"data": data, "layout": layout, "frames": frames, "meta": meta}


def _ranges(D: int, joints, fitted, y) -> tuple[list, int]:
    """The axis ranges around everything shown (5 % padding) and the decimals worth sending."""
    every = np.concatenate([joints.reshape(-1, D), fitted.reshape(-1, D), y.reshape(-1, D)])
    every = every[np.isfinite(every).all(axis=1)]
    lo, hi = (every.min(axis=0), every.max(axis=0)) if every.size else (np.zeros(D), np.ones(D))
    size = float(np.max(hi - lo)) or 1.0
    decimals = int(max(0, 4 - math.floor(math.log10(size))))
    pad = 0.05 * size
    return [[float(lo[k] - pad), float(hi[k] + pad)] for k in range(D)], decimals


def _styles(D: int, mnames: list, jnames: list) -> list[dict]:
    """The style of each trace of :data:`TRACES`, in order."""
    return [
        dict(mode="markers", marker=dict(size=5 if D == 3 else 8, color="#1f77b4"), text=mnames,
             hovertemplate="%{text} (measured)<extra></extra>"),
        dict(mode="markers", marker=dict(size=4 if D == 3 else 7, color="#ff7f0e", symbol="x" if D == 2 else "cross"),
             text=mnames, hovertemplate="%{text} (model)<extra></extra>"),
        dict(mode="lines", line=dict(color="#d62728", width=2), hoverinfo="skip"),
        dict(mode="lines", line=dict(color="#333333", width=7 if D == 3 else 4), hoverinfo="skip"),
        dict(mode="markers", marker=dict(size=6 if D == 3 else 9, color="#2ca02c",
                                         symbol="diamond"), text=jnames,
             hovertemplate="%{text} (joint centre)<extra></extra>"),
        dict(mode="lines", line=dict(color="#aaaaaa", width=2 if D == 3 else 1), hoverinfo="skip"),
    ]


def _animation_controls(names: list, F: int, stride: int, rate: float) -> tuple[dict, dict]:
    """The frame slider and the play/pause buttons."""
    anim = {"mode": "immediate", "frame": {"duration": 0, "redraw": True}, "transition": {"duration": 0}}
    steps = [{"method": "animate", "label": n, "args": [[n], anim]} for n in names]
    slider = {"active": 0, "steps": steps, "x": 0.08, "len": 0.92, "y": 0, "pad": {"t": 30},
              "currentvalue": {"prefix": "frame ", "suffix": f" (every {stride}-th frame of {F}, {rate:g} Hz)"
                               if stride > 1 else f" of {F} ({rate:g} Hz)"}}
    play = {"type": "buttons", "showactive": False, "x": 0.0, "y": 0, "xanchor": "left", "yanchor": "top",
            "pad": {"t": 40},
            "buttons": [{"label": "▶ play", "method": "animate",
                         "args": [None, {"mode": "immediate", "fromcurrent": True,
                                         "frame": {"duration": max(int(1000 * stride / rate), 40) if rate > 0
                                                   else 50, "redraw": True},
                                         "transition": {"duration": 0}}]},
                        {"label": "❚❚ pause", "method": "animate",
                         "args": [[None], {"mode": "immediate", "frame": {"duration": 0, "redraw": False}}]}]}
    return slider, play


def _set_axes(layout: dict, D: int, joints, ranges: list, units: str) -> None:
    """The 3-D scene (camera up along the body's long axis) or the 2-D axes, equal scale, into ``layout``."""
    axes = "xyz"[:D]
    if D == 3:
        up = _up_axis(joints)
        upv = {a: 0 for a in "xyz"}
        upv["xyz"[abs(up) - 1]] = 1 if up > 0 else -1
        layout["scene"] = {"aspectmode": "data", "camera": {"up": upv},
                           **{f"{a}axis": {"range": ranges[i], "title": {"text": f"{a} [{_text(units)}]"},
                                           "autorange": False}
                              for i, a in enumerate(axes)}}
        return
    slider, play = layout["sliders"][0], layout["updatemenus"][0]
    layout["xaxis"] = {"range": ranges[0], "title": {"text": f"x [{_text(units)}]"}, "autorange": False}
    layout["yaxis"] = {"range": ranges[1], "title": {"text": f"y [{_text(units)}]"}, "autorange": False,
                       "scaleanchor": "x", "scaleratio": 1}
    layout["margin"].update(b=60, l=70)
    slider.update(pad={"t": 70}, x=0.13, len=0.87)  # clear of the play button beside the y axis
    play["pad"] = {"t": 80}
    layout["legend"] = {"x": 1.02, "y": 1}


def _js(obj) -> str:
    """JSON that is safe inside a ``<script>`` element (no ``</script>``, no ``<!--``)."""
    return (json.dumps(obj, allow_nan=False, separators=(",", ":"), ensure_ascii=False)
            .replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")
            .replace("\u2028", "\\u2028").replace("\u2029", "\\u2029"))


def plotly_script() -> str:
    """plotly.js, from the ``plotly`` package's offline bundle, as one inline ``<script>`` element."""
    try:
        from plotly.offline import get_plotlyjs
    except ImportError:  # pragma: no cover - plotly is a dependency
        from skelid.errors import SkelidError

        raise SkelidError("the report's 3-D view needs the plotly package", "pip install plotly") from None
    return f'<script type="text/javascript">{get_plotlyjs()}</script>'


def viewer_html(spec: dict, div_id: str = "skeleton-view") -> str:
    """The ``<div>`` and inline ``<script>`` that draw ``spec`` (needs :func:`plotly_script` earlier in the page).

    The div's ``data-frame`` attribute holds the frame shown, and ``data-ready``
    becomes ``1`` once the plot is drawn.
    """
    meta = spec["meta"]
    fig = {k: spec[k] for k in ("data", "layout")}
    config = {"responsive": True, "displaylogo": False, "typesetMath": False}
    return (
        f'<div id="{html.escape(div_id)}" class="viewer" data-frame="{html.escape(spec["frames"][0]["name"])}" '
        f'data-frames-shown="{meta["frames_shown"]}" data-stride="{meta["stride"]}" data-ready="0"></div>\n'
        "<script>\n(function () {\n"
        f'  var gd = document.getElementById("{html.escape(div_id)}");\n'
        f"  var fig = {_js(fig)};\n  var frames = {_js(spec['frames'])};\n"
        f"  Plotly.newPlot(gd, fig.data, fig.layout, {_js(config)}).then(function () {{\n"
        "    gd.on('plotly_animatingframe', function (e) { gd.dataset.frame = e.name; });\n"
        "    gd.on('plotly_sliderchange', function (e) { gd.dataset.frame = e.step.label; });\n"
        "    return Plotly.addFrames(gd, frames);\n"
        "  }).then(function () { gd.dataset.ready = '1'; });\n"
        "})();\n</script>"
    )
