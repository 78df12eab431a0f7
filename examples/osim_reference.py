"""Reference geometry of OpenSim's subject01 model (``std_subject01_simbody.osim``).

Reads, with ``xml.etree`` only, what the lower-limb example needs from the
scaled Gait2354 model of the OpenSim scaling test: joint locations in their
parent bodies, joint axes, the knee's translation (a spline of the knee angle
times a scale factor) and the markers' locations in their bodies. Lengths are
returned in millimetres.

The knee of Gait2354 is not a pin: the tibia's origin moves along splines of
the knee angle, so the hip-knee distance depends on the angle; this module
evaluates the splines with a natural cubic spline through the knots.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline


def _vec(text) -> np.ndarray:
    return np.array([float(v) for v in text.split()])


class OsimModel:
    """The parts of an OpenSim 3.x model file the examples use (mm)."""

    def __init__(self, path):
        self.path = Path(path)
        root = ET.parse(self.path).getroot()
        self.joints = {}
        for body in root.iter("Body"):
            for j in body.iter("CustomJoint"):
                axes = {}
                for ta in j.iter("TransformAxis"):
                    axes[ta.get("name")] = (_vec(ta.find("axis").text), ta)
                self.joints[j.get("name")] = {
                    "parent": j.find("parent_body").text.strip(),
                    "child": body.get("name"),
                    "location": 1000.0 * _vec(j.find("location_in_parent").text),
                    "axes": axes,
                }
        self.markers = {}
        for m in root.iter("Marker"):
            self.markers[m.get("name")] = (m.find("body").text.strip(), 1000.0 * _vec(m.find("location").text))

    def rotation_axis(self, joint: str) -> np.ndarray:
        """Unit axis (parent frame) of the joint's first rotation driven by a coordinate."""
        for name in ("rotation1", "rotation2", "rotation3"):
            a, ta = self.joints[joint]["axes"][name]
            coords = ta.find("coordinates").text
            if coords and coords.strip():
                return a / np.linalg.norm(a)
        raise ValueError(f"joint {joint} has no driven rotation")

    def translation(self, joint: str, angle: float = 0.0) -> np.ndarray:
        """Offset (mm) of the child's origin in the parent at a coordinate value (rad)."""
        out = self.joints[joint]["location"].copy()
        for name in ("translation1", "translation2", "translation3"):
            axis, ta = self.joints[joint]["axes"][name]
            fn = ta.find("function")
            mult = fn.find("MultiplierFunction")
            scale = 1.0
            if mult is not None:
                scale = float(mult.find("scale").text)
                fn = mult.find("function")
            spline = fn.find("SimmSpline")
            if spline is not None:
                x, y = _vec(spline.find("x").text), _vec(spline.find("y").text)
                val = float(CubicSpline(x, y, bc_type="natural")(angle))
            else:
                const = fn.find("Constant")
                val = float(const.find("value").text) if const is not None else 0.0
            out += 1000.0 * scale * val * axis
        return out

    def thigh_length(self, side: str, knee_angle: float = 0.0) -> float:
        """Hip-knee distance (mm): the femur's hip at its origin, the tibia's origin at the knee."""
        return float(np.linalg.norm(self.translation(f"knee_{side}", knee_angle)))

    def shank_length(self, side: str) -> float:
        """Knee-ankle distance (mm): the ankle's location in the tibia."""
        return float(np.linalg.norm(self.joints[f"ankle_{side}"]["location"]))

    def body_markers(self, body: str) -> dict[str, np.ndarray]:
        return {n: loc for n, (b, loc) in self.markers.items() if b == body}
