"""Write a skelid model (TOML text) from one reference frame of a recording.

The example models of real recordings are built the same way: one frame of the
data is the reference pose (every joint coordinate zero), every segment frame
is parallel to the laboratory frame in that pose, each segment's origin is the
nominal centre of the joint that carries it (from anatomical landmarks), and
each marker's position is where it was in that frame, relative to its
segment's origin. The unknown joint centres are then functional
(``joint_centre``) parameters around those nominal guesses.
"""

from __future__ import annotations

import numpy as np


def _fmt(v, digits: int) -> str:
    return "[" + ", ".join(f"{x:.{digits}f}" for x in np.asarray(v, float)) + "]"


def unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def uniform_parameter(name: str, kind: str, joint: str, lower: float, upper: float,
                      axes: str | None = None) -> dict:
    """One ``[[parameters]]`` entry with a uniform prior, as ``model_toml`` writes it.

    ``axes`` is the TOML text of the axes list (e.g. ``'["x", "y"]'``), or None for none.
    """
    entry = {"name": f'"{name}"', "kind": f'"{kind}"', "joint": f'"{joint}"'}
    if axes is not None:
        entry["axes"] = axes
    entry["prior"] = f'{{ type = "uniform", lower = {float(lower)}, upper = {float(upper)} }}'
    return entry


def leg_segments(side: str, hip, knee, ankle, knee_axis, ankle_axes, knee_range: list[float],
                 ankle_range: list[list[float]], markers: dict[str, list[str]]) -> list[dict]:
    """Thigh, shank and foot of one leg (``side`` "r" or "l") under the pelvis, as ``model_toml`` takes them.

    A spherical hip, a hinge knee about ``knee_axis`` and a universal ankle about
    ``ankle_axes``; ``hip``, ``knee``, ``ankle`` are the joint centres (3,) in the
    reference frame and ``markers`` maps "thigh", "shank", "foot" to marker names.
    """
    return [
        {"name": f"thigh_{side}", "parent": "pelvis", "joint": f"hip_{side}", "type": "spherical",
         "centre": hip, "markers": markers["thigh"]},
        {"name": f"shank_{side}", "parent": f"thigh_{side}", "joint": f"knee_{side}", "type": "hinge",
         "centre": knee, "axis": knee_axis, "range": knee_range, "markers": markers["shank"]},
        {"name": f"foot_{side}", "parent": f"shank_{side}", "joint": f"ankle_{side}", "type": "universal",
         "centre": ankle, "axes": ankle_axes, "range": ankle_range, "markers": markers["foot"]},
    ]


def functional_leg_parameters(side: str, half_width: float = 80.0, tilt: float = 30.0) -> list[dict]:
    """Functional hip (x, y, z), knee (x, y) and ankle (x, y) centres and the knee axis tilt of one leg.

    Uniform priors: centres within ``half_width`` of their nominal place (model units),
    the knee axis within ``tilt`` degrees of its nominal direction.
    """
    return [
        uniform_parameter(f"hip_{side}", "joint_centre", f"hip_{side}", -half_width, half_width, '["x", "y", "z"]'),
        uniform_parameter(f"knee_{side}", "joint_centre", f"knee_{side}", -half_width, half_width, '["x", "y"]'),
        uniform_parameter(f"knee_{side}_axis", "axis_direction", f"knee_{side}", -tilt, tilt, '["u", "v"]'),
        uniform_parameter(f"ankle_{side}", "joint_centre", f"ankle_{side}", -half_width, half_width, '["x", "y"]'),
    ]


def model_toml(name: str, units: str, description: str, comments: list[str], frame: dict,
               segments: list[dict], parameters: list[dict], labels: dict | None = None,
               digits: int = 1) -> str:
    """The TOML text of a model.

    Parameters
    ----------
    frame : dict
        Marker name -> position (D,) in the reference frame (laboratory axes).
    segments : list of dict
        Parents first. Keys: ``name``, ``parent`` ("ground" for the root),
        ``joint``, ``type``, ``centre`` (the joint centre in the reference frame),
        optional ``axis`` / ``axes`` (laboratory directions), ``range``,
        ``markers`` (names), ``root_position`` (for the root: the joint position
        written in the file, default the centre).
    parameters : list of dict
        Written as they are (TOML inline values must already be strings).
    labels : dict, optional
        Marker name -> its name in the data file, written as ``[aliases]``.
    """
    lines = [f"# {c}" if c else "#" for c in comments]
    lines += ["", "[model]", f'name = "{name}"', "dim = 3", f'units = "{units}"',
              f'description = "{description}"', ""]
    if labels:
        lines.append("[aliases]")
        lines += [f'{k} = "{v}"' for k, v in labels.items()]
        lines.append("")
    centre = {s["name"]: np.asarray(s["centre"], float) for s in segments}
    markers = []
    for s in segments:
        pos = s.get("root_position", s["centre"]) if s["parent"] == "ground" \
            else centre[s["name"]] - centre[s["parent"]]
        j = f'name = "{s["joint"]}", type = "{s["type"]}", position = {_fmt(pos, digits)}'
        if "axis" in s:
            j += f", axis = {_fmt(unit(s['axis']), 4)}"
        if "axes" in s:
            j += ", axes = [" + ", ".join(_fmt(unit(a), 4) for a in s["axes"]) + "]"
        if "range" in s:
            r = s["range"]
            j += ", range = " + (_fmt(r, 1) if np.ndim(r) == 1 else "[" + ", ".join(_fmt(x, 1) for x in r) + "]")
        lines += ["[[segments]]", f'name = "{s["name"]}"', f'parent = "{s["parent"]}"', f"joint = {{ {j} }}", ""]
        markers += [(m, s["name"], np.asarray(frame[m], float) - centre[s["name"]]) for m in s.get("markers", ())]
    for m, seg, pos in markers:
        lines += ["[[markers]]", f'name = "{m}"', f'segment = "{seg}"', f"position = {_fmt(pos, digits)}", ""]
    for p in parameters:
        lines.append("[[parameters]]")
        lines += [f"{k} = {v}" for k, v in p.items()]
        lines.append("")
    return "\n".join(lines).rstrip() + "\n"
