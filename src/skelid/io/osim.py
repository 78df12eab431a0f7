"""OpenSim models (.osim) in and out.

Reading
-------
:func:`read_osim` turns an OpenSim 4.x model (and the 3.x / 2.x layout with
``location_in_parent``) into a frozen :class:`~skelid.model.Model` in
millimetres. Each OpenSim body becomes a segment whose frame keeps the body's
orientation and has its origin at the joint centre (the origin of the joint's
child frame). With ``X_PF`` the joint's parent frame in the parent body,
``X_BM`` its child frame in the child body and ``X_FM(q)`` the joint's motion,

.. math::

    X_{G B} = X_{G P}\\, X_{P F}\\, X_{F M}(q)\\, X_{B M}^{-1},

the skelid joint position is ``p_PF - p_P^c`` (``p_P^c`` the parent's own
joint centre in the parent body), a marker's position is ``r_B - p_BM``, the
joint's axes are ``R_PF a`` and a constant rotation ``R_PF R_BM^T`` follows the
motions. ``PinJoint`` (rotation about z of F), ``SliderJoint``,
``UniversalJoint``, ``BallJoint``, ``GimbalJoint``, ``FreeJoint``,
``PlanarJoint``, ``WeldJoint`` (no motion: a rigid attachment) and
``CustomJoint`` become ``custom`` joints whose motions are functions of the
coordinates (``LinearFunction``, ``Constant``, ``PolynomialFunction``,
``SimmSpline``, ``NaturalCubicSpline``, ``MultiplierFunction``; see
:mod:`skelid.model.functions`). ``EllipsoidJoint`` and
``ScapulothoracicJoint`` add *carried* translations, whose amount follows the
joint's rotations (:func:`_ellipsoid`, :func:`_scapulothoracic`). A locked
coordinate becomes a constant at its default value. Bodies that carry no marker
and have no descendant that does are left out (``keep='markers'``). Files are
decoded in any encoding OpenSim reads (:mod:`skelid.io._xml`); the joint frames
of a file older than version 30505 are rounded as OpenSim rounds them.

A model or MarkerSet file of more than :data:`MAX_MARKERS` markers is refused
in one line before its markers are read.

Anything else that changes where a marker is (a coordinate coupled to another
joint's coordinate by a ``CoordinateCouplerConstraint``, an unknown joint or
function) is refused in one line naming the element, its type and why.

Parameters for identification come from :func:`osim_parameters`: a ``scale``
factor per body (or three per axis) that scales the body's joint frames,
markers and the coupled translations of joints whose parent it is, as
OpenSim's ScaleTool does, and ``marker_offset`` shifts of the markers (its
MarkerPlacer). :func:`write_scaled_osim` writes the result back into a copy
of the XML tree; :func:`write_scale_set` writes an OpenSim ScaleSet.
"""

from __future__ import annotations

import copy
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

from skelid.errors import FormatError, ModelError, SkelidError
from skelid.io._xml import first_tag, read_xml
from skelid.model.description import (
    Joint,
    Marker,
    Model,
    Motion,
    Parameter,
    Prior,
    Segment,
    _scales_with_parent,
)
from skelid.model.functions import CoordinateFunction

M_TO_MM = 1000.0
#: the most markers read from one model or MarkerSet file; more are refused before any is read. Marker
#: protocols have tens to a few hundred; the model's checks of unique names compare every marker
#: with every other, so the time grows with the square of the count (2000 markers: 0.1 s to read, 2 s
#: with an offset parameter per marker; 160000: minutes to read, hours with offsets)
MAX_MARKERS = 2000
UNIT_WORDS = {"meters": 1.0, "meter": 1.0, "m": 1.0}
JOINT_TAGS = ("CustomJoint", "PinJoint", "SliderJoint", "UniversalJoint", "BallJoint", "GimbalJoint",
              "FreeJoint", "PlanarJoint", "WeldJoint", "EllipsoidJoint", "ScapulothoracicJoint")
#: joints OpenSim has that skelid refuses, and why
REFUSED_JOINTS = {
    "ConstantCurvatureJoint": "its offset is a nonlinear function of its three Euler angles and a fixed length "
                              "(a segment bent along a circular arc), which skelid's joints (translations each a "
                              "function of one coordinate, or a fixed vector turned by the rotations) cannot "
                              "express",
}
FUNCTION_TAGS = ("LinearFunction", "Constant", "PolynomialFunction", "SimmSpline", "NaturalCubicSpline",
                 "MultiplierFunction")
# OpenSim 4 evaluates a NaturalCubicSpline with the end conditions of its SimmSpline (checked against the
# opensim package to 1e-12 mm on gait2354), so both read as "fmm" splines.
#: the first OpenSim document version whose joints hold their frames as offset frames
OFFSET_FRAME_VERSION = 30505
EX, EY, EZ = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)


# ----------------------------------------------------------------------------- small helpers
def _floats(text, n: int | None, where: str) -> tuple[float, ...]:
    try:
        v = tuple(float(x) for x in (text or "").split())
    except ValueError:
        raise FormatError(f"{where}: expected numbers, got {text!r}", "fix the value in the .osim file") from None
    if n is not None and len(v) != n:
        raise FormatError(f"{where}: expected {n} numbers, got {len(v)}", "fix the value in the .osim file")
    if not all(math.isfinite(x) for x in v):
        raise FormatError(f"{where}: numbers must be finite, got {text!r}", "fix the value in the .osim file")
    return v


def _rot_xyz(angles) -> np.ndarray:
    """Body-fixed x-y-z rotation ``Rx(a) Ry(b) Rz(c)`` (OpenSim's frame orientation)."""
    a, b, c = angles
    ca, sa, cb, sb, cc, sc = math.cos(a), math.sin(a), math.cos(b), math.sin(b), math.cos(c), math.sin(c)
    Rx = np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]])
    Ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
    Rz = np.array([[cc, -sc, 0], [sc, cc, 0], [0, 0, 1]])
    return Rx @ Ry @ Rz


def _child(el, tag):
    return el.find(tag) if el is not None else None


def _text(el, tag, default=None):
    c = el.find(tag)
    return default if c is None or c.text is None else c.text.strip()


@dataclass
class _Frame:
    """A frame fixed on a body: ``X_body_frame``."""

    body: str
    R: np.ndarray
    p: np.ndarray  # metres


class _MotionSpec(NamedTuple):
    """One motion of an OpenSim joint, in the joint's parent frame F (metres, radians)."""

    kind: str  # "R", "T" or "C" (a translation carried by the joint's earlier rotations)
    axis: tuple
    coordinate: int  # index in the joint's coordinates, -1: none
    function: CoordinateFunction
    vector: tuple | None = None  # "C": the vector the rotations turn (F frame)
    weights: tuple | None = None  # "C": the parent's scale factors it grows with (w . s)


@dataclass
class _JointSpec:
    name: str
    tag: str
    parent: _Frame
    child: _Frame
    coordinates: list  # (name, range (lo, hi), locked, default, motion_type)
    motions: list  # of _MotionSpec
    unscalable: str | None = None  # why OpenSim's scaling of the child cannot be followed, if it cannot


# ----------------------------------------------------------------------------- functions
def _function(el, where: str) -> CoordinateFunction:
    """An OpenSim function element -> CoordinateFunction (values in OpenSim units)."""
    tag = el.tag
    name = f"{where} {tag}"
    if tag == "LinearFunction":
        c = _floats(_text(el, "coefficients"), 2, name)
        return CoordinateFunction("linear", c)
    if tag == "Constant":
        return CoordinateFunction("constant", _floats(_text(el, "value"), 1, name))
    if tag == "PolynomialFunction":
        return CoordinateFunction("polynomial", _floats(_text(el, "coefficients"), None, name))
    if tag in ("SimmSpline", "NaturalCubicSpline"):
        x, y = _floats(_text(el, "x"), None, name), _floats(_text(el, "y"), None, name)
        try:
            return CoordinateFunction("spline", (), x, y, "fmm")
        except ModelError as exc:
            raise FormatError(f"{name}: {exc.problem}", "fix the knots in the .osim file") from None
    if tag == "MultiplierFunction":
        inner = _function_in(el, "function", where) or _first_function(el, where)
        s = float(_text(el, "scale", "1"))
        f = inner
        return CoordinateFunction(f.kind, f.coefficients, f.x, f.y, f.end, f.scale * s)
    raise ModelError(f"{where}: unsupported function {tag}",
                     f"use one of {', '.join(FUNCTION_TAGS)} (or refit the joint with one)")


def _first_function(el, where):
    for c in el:
        if c.tag in FUNCTION_TAGS or c.tag.endswith("Function") or c.tag.endswith("Spline"):
            return _function(c, where)
    raise ModelError(f"{where}: no function found", "give the transform axis a function")


def _function_in(el, tag, where):
    f = el.find(tag)
    if f is None:
        return None
    for c in f:
        return _function(c, where)
    return None


# ----------------------------------------------------------------------------- joints
def _coordinates(el, jname):
    out = []
    for c in el.iter("Coordinate"):
        rng = _floats(_text(c, "range", "-3.14159 3.14159"), 2, f"coordinate {c.get('name')!r} range")
        locked = _text(c, "locked", "false").lower() == "true"
        default = float(_text(c, "default_value", "0") or 0)
        motion_type = _text(c, "motion_type", "")
        out.append((c.get("name"), rng, locked, default, motion_type))
    return out


def _standard_motions(tag: str, n_coords: int, jname: str):
    """Motions of the joints with a fixed structure, as (kind, axis, coordinate)."""
    table = {
        "PinJoint": [("R", EZ, 0)],
        "SliderJoint": [("T", EX, 0)],
        "UniversalJoint": [("R", EX, 0), ("R", EY, 1)],
        "BallJoint": [("R", EX, 0), ("R", EY, 1), ("R", EZ, 2)],
        "GimbalJoint": [("R", EX, 0), ("R", EY, 1), ("R", EZ, 2)],
        "FreeJoint": [("R", EX, 0), ("R", EY, 1), ("R", EZ, 2), ("T", EX, 3), ("T", EY, 4), ("T", EZ, 5)],
        "PlanarJoint": [("R", EZ, 0), ("T", EX, 1), ("T", EY, 2)],
        "WeldJoint": [],
    }
    motions = table[tag]
    need = max((c for *_, c in motions), default=-1) + 1
    if n_coords != need:
        raise ModelError(f"joint {jname!r} ({tag}) has {n_coords} coordinates, expected {need}",
                         "fix the joint's coordinate list")
    ident = CoordinateFunction("linear", (1.0, 0.0))
    return [_MotionSpec(k, a, c, ident) for k, a, c in motions]


def _spatial_transform(el, coords, jname) -> list[_MotionSpec]:
    """The motions of a ``CustomJoint``: one per ``TransformAxis`` that moves."""
    st = el.find("SpatialTransform")
    if st is None:
        raise ModelError(f"CustomJoint {jname!r} has no SpatialTransform", "add one or use another joint type")
    names = [c[0] for c in coords]
    motions = (_transform_axis(ta, names, f"joint {jname!r} {ta.get('name', '')}") for ta in st.iter("TransformAxis"))
    return [m for m in motions if m is not None]


def _transform_axis(ta, names: list, where: str) -> _MotionSpec | None:
    """One ``TransformAxis``: its motion, or None when it does not move (no function, or a zero constant)."""
    axis = _axis_of(ta, where)
    cnames = (_text(ta, "coordinates", "") or "").split()
    f = _axis_function(ta, where)
    if f is None:
        if cnames:
            raise ModelError(f"{where}: coordinate without a function", "give the transform axis a function")
        return None
    if len(cnames) > 1:
        raise ModelError(f"{where}: a function of {len(cnames)} coordinates is not supported",
                         "use one coordinate per transform axis")
    if cnames and cnames[0] not in names:
        raise ModelError(f"{where}: unknown coordinate {cnames[0]!r}", f"use one of {names}")
    ci = names.index(cnames[0]) if cnames and not f.is_constant else -1  # a constant follows no coordinate
    if ci < 0 and not f.is_constant:
        f = CoordinateFunction("constant", (float(f.value(np.zeros(1))[0]),))
    if f.is_constant and f.coefficients[0] * f.scale == 0.0:
        return None  # does not move
    kind = "R" if ta.get("name", "").startswith("rotation") else "T"
    return _MotionSpec(kind, axis, ci, f)


def _axis_of(ta, where: str) -> tuple[float, ...]:
    axis = np.asarray(_floats(_text(ta, "axis"), 3, f"{where} axis"))
    n = float(np.linalg.norm(axis))
    if n == 0:
        raise FormatError(f"{where}: zero axis", "give the transform axis a direction")
    return tuple(axis / n)


def _axis_function(ta, where: str) -> CoordinateFunction | None:
    """The function of a ``TransformAxis``: under ``<function>``, or (older files) a function element in it."""
    f = _function_in(ta, "function", where)
    if f is None:
        f = next((_function(c, where) for c in ta if c.tag in FUNCTION_TAGS or c.tag.endswith("Function")
                  or c.tag.endswith("Spline")), None)
    return f


def _ellipsoid(el, spec: _JointSpec) -> None:
    """OpenSim's ``EllipsoidJoint`` (Simbody's ``MobilizedBody::Ellipsoid``).

    ``X_FM = (R, diag(r) R e_z)`` with ``R = Rx(q0) Ry(q1) Rz(q2)`` (body-fixed)
    and ``r`` the semi-axes: the three rotations, then three carried
    translations along F's axes by ``r_i (e_i . R e_z)``, each growing with the
    parent's scale factor along its axis (OpenSim's ``EllipsoidJoint::extendScale``).
    """
    radii = _floats(_text(el, "radii_x_y_z"), 3, f"joint {spec.name!r} (EllipsoidJoint) radii_x_y_z")
    _need_coordinates(spec, 3)
    spec.motions = [_MotionSpec("R", e, i, _IDENTITY) for i, e in enumerate((EX, EY, EZ))]
    spec.motions += [_MotionSpec("C", e, -1, CoordinateFunction("constant", (r,)), EZ, e)
                     for e, r in zip((EX, EY, EZ), radii, strict=True)]


def _scapulothoracic(el, spec: _JointSpec) -> None:
    """OpenSim's ``ScapulothoracicJoint``: an ellipsoid joint, then a pin (winging), then a weld.

    OpenSim builds it (``ScapulothoracicJoint::extendAddToSystem``) from the
    parent frame turned by ``Z = Rz(pi/2)``, an ellipsoid mobilizer with the
    thoracic radii ``(r_y, r_x, r_z)`` whose child frame is ``Z`` in an
    intermediate body, and a pin about the unit vector
    ``d = (-sin w, cos w, 0)`` through ``o = (o_x, o_y, 0)`` of that body
    (``w`` the winging direction, ``o`` the winging axis origin), the
    joint's child frame fixed to the pin's body. With ``R`` the ellipsoid's
    body-fixed x-y-z rotation, the point ``o`` (fixed in the child frame) is at
    ``diag(r_y, r_x, r_z) R e_z + R Z^T o`` in the turned parent frame and the
    child turns by ``R Rot(Z^T d, q3) Z^T``. skelid's segment origin is that
    point: rotations about x, y, z, carried translations for both terms (the
    radii grow with the parent's scale factors, ``o`` does not), then the
    winging about ``Z^T d = (cos w, sin w, 0)``.
    """
    where = f"joint {spec.name!r} (ScapulothoracicJoint)"
    rx, ry, rz = _floats(_text(el, "thoracic_ellipsoid_radii_x_y_z"), 3, f"{where} thoracic_ellipsoid_radii_x_y_z")
    ox, oy = _floats(_text(el, "scapula_winging_axis_origin", "0 0"), 2, f"{where} scapula_winging_axis_origin")
    w = _floats(_text(el, "scapula_winging_axis_direction", "0"), 1, f"{where} scapula_winging_axis_direction")[0]
    _need_coordinates(spec, 4)
    spec.parent = _Frame(spec.parent.body, spec.parent.R @ _RZ90, spec.parent.p)
    o_child = np.array([ox, oy, 0.0])
    spec.child = _Frame(spec.child.body, spec.child.R @ _RZ90, spec.child.p + spec.child.R @ o_child)
    motions = [_MotionSpec("R", e, i, _IDENTITY) for i, e in enumerate((EX, EY, EZ))]
    motions += [_MotionSpec("C", e, -1, CoordinateFunction("constant", (r,)), EZ, weights)
                for e, r, weights in ((EX, ry, EY), (EY, rx, EX), (EZ, rz, EZ))]
    offset = _RZ90.T @ o_child
    size = float(np.linalg.norm(offset))
    if size > 0:
        motions += [_MotionSpec("C", e, -1, CoordinateFunction("constant", (size,)), tuple(offset / size),
                                (0.0, 0.0, 0.0)) for e in (EX, EY, EZ)]
        spec.unscalable = ("OpenSim scales its ScapulothoracicJoint's winging axis origin with this body's "
                           "factors in the joint's frame, which skelid does not follow")
    motions.append(_MotionSpec("R", (math.cos(w), math.sin(w), 0.0), 3, _IDENTITY))
    spec.motions = motions


def _need_coordinates(spec: _JointSpec, n: int) -> None:
    if len(spec.coordinates) != n:
        raise ModelError(f"joint {spec.name!r} ({spec.tag}) has {len(spec.coordinates)} coordinates, expected {n}",
                         "fix the joint's coordinate list")


_IDENTITY = CoordinateFunction("linear", (1.0, 0.0))
_RZ90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # Rz(pi/2)
#: joints whose child slides over an ellipsoid: tag -> the reader of their motions
SURFACE_JOINTS = {"EllipsoidJoint": _ellipsoid, "ScapulothoracicJoint": _scapulothoracic}


# ----------------------------------------------------------------------------- the XML walk
class _Reader:
    def __init__(self, root, source: str):
        self.source = source
        try:
            self.version = int(root.get("Version", "0")) if root.tag == "OpenSimDocument" else 0
        except ValueError:
            raise FormatError(f"{source}: OpenSimDocument Version {root.get('Version')!r} is not a number",
                              "fix the Version attribute") from None
        self.model_el = root.find("Model") if root.tag != "Model" else root
        if self.model_el is None:
            raise FormatError(f"{source}: no <Model> element", "is this an OpenSim .osim file?")
        units = (_text(self.model_el, "length_units", "meters") or "meters").lower()
        if units not in UNIT_WORDS:
            raise ModelError(f"{source}: <length_units> is {units!r}",
                             "skelid reads OpenSim models in meters; convert the model to meters")
        self.frames: dict[str, _Frame] = {}
        self.joints: list[_JointSpec] = []
        self.bodies: list[str] = []
        self.markers: list[tuple[str, str, np.ndarray, bool]] = []  # name, body, location in body (m), fixed

    # frames --------------------------------------------------------------
    def frame(self, ref: str, owner: dict, where: str) -> _Frame:
        ref = ref.strip()
        key = ref.rsplit("/", 1)[-1] if ref.startswith("/bodyset/") or ref in ("/ground", "ground") else ref
        if ref in ("/ground", "ground", "../ground"):
            return _Frame("ground", np.eye(3), np.zeros(3))
        if key in owner:
            return owner[key]
        name = ref.rstrip("/").rsplit("/", 1)[-1]
        if name in owner:
            return owner[name]
        if name in self.frames:
            return self.frames[name]
        if name in self.bodies or name == "ground":
            return _Frame(name, np.eye(3), np.zeros(3))
        raise ModelError(f"{where}: unknown frame {ref!r}", "point the socket at a body or an offset frame")

    def offset_frames(self, el, where) -> dict:
        out = {}
        fr = el.find("frames")
        if fr is None:
            return out
        pending = list(fr.iter("PhysicalOffsetFrame"))
        for _ in range(len(pending) + 1):
            rest = []
            for f in pending:
                try:
                    base = self.frame(_text(f, "socket_parent", ""), out, f"{where} frame {f.get('name')!r}")
                except ModelError:
                    rest.append(f)
                    continue
                R = _rot_xyz(_floats(_text(f, "orientation", "0 0 0"), 3, f"{where} orientation"))
                p = np.asarray(_floats(_text(f, "translation", "0 0 0"), 3, f"{where} translation"))
                out[f.get("name")] = _Frame(base.body, base.R @ R, base.p + base.R @ p)
            if not rest:
                break
            pending = rest
        if pending and rest:
            raise ModelError(f"{where}: offset frame {rest[0].get('name')!r} has an unknown parent",
                             "fix its socket_parent")
        return out

    # 4.x -------------------------------------------------------------------
    def read(self):
        m = self.model_el
        bodyset = m.find("BodySet")
        if bodyset is None:
            raise FormatError(f"{self.source}: no <BodySet>", "is this an OpenSim model?")
        body_els = list(bodyset.iter("Body"))
        self.bodies = [b.get("name") for b in body_els if b.get("name") != "ground"]
        old_layout = any(b.find("Joint") is not None for b in body_els)
        if old_layout:
            self._read_old(body_els)
        else:
            self._read_new(m)
        self._read_markers(m.find("MarkerSet"))
        self.couplers = []
        cs = m.find("ConstraintSet")
        if cs is not None:
            for c in cs.iter("CoordinateCouplerConstraint"):
                enforced = (_text(c, "isEnforced", "true") or "true").lower() == "true" and \
                    (_text(c, "isDisabled", "false") or "false").lower() != "true"
                if enforced:
                    self.couplers.append((c.get("name"), _text(c, "dependent_coordinate_name", ""),
                                          (_text(c, "independent_coordinate_names", "") or "").split()))

    def _read_new(self, m):
        for fs in (m.findall("FrameSet") or []):
            self.frames.update(self.offset_frames(fs.find("objects") or fs, "FrameSet"))
        jointset = m.find("JointSet")
        if jointset is None:
            raise FormatError(f"{self.source}: no <JointSet>", "is this an OpenSim 4 model?")
        objects = jointset.find("objects")
        for el in (objects if objects is not None else []):
            self._joint(el, el.get("name"))

    def _joint(self, el, jname, parent=None, child=None):
        tag = el.tag
        if tag not in JOINT_TAGS:
            why = REFUSED_JOINTS.get(tag, "skelid does not know this joint type")
            raise ModelError(f"{self.source}: joint {jname!r} ({tag}): {why}",
                             f"replace it with one of {', '.join(JOINT_TAGS)} (a CustomJoint can approximate it), "
                             "or remove the markers of the bodies it moves")
        coords = _coordinates(el, jname)
        if parent is None:
            own = self.offset_frames(el, f"joint {jname!r}")
            parent = self.frame(_text(el, "socket_parent_frame", ""), own, f"joint {jname!r} parent")
            child = self.frame(_text(el, "socket_child_frame", ""), own, f"joint {jname!r} child")
        if child.body == "ground":
            raise ModelError(f"joint {jname!r} has the ground as its child",
                             "reverse the joint so that the ground is its parent")
        if (_text(el, "reverse", "false") or "false").lower() == "true":
            raise ModelError(f"joint {jname!r} is reversed", "write it with the parent body as its parent")
        spec = _JointSpec(jname, tag, parent, child, coords, [])
        if tag == "CustomJoint":
            spec.motions = _spatial_transform(el, coords, jname)
        elif tag in SURFACE_JOINTS:
            SURFACE_JOINTS[tag](el, spec)
        else:
            spec.motions = _standard_motions(tag, len(coords), jname)
        self.joints.append(spec)

    # 3.x / 2.x -------------------------------------------------------------
    def _read_old(self, body_els):
        for b in body_els:
            jwrap = b.find("Joint")
            if jwrap is None or len(jwrap) == 0:
                continue
            el = jwrap[0]
            jname = el.get("name")
            pname = _text(el, "parent_body", "")
            vec = self._old_vector
            R_pf = _rot_xyz(vec(el, "orientation_in_parent", jname))
            p_pf = np.asarray(vec(el, "location_in_parent", jname))
            R_bm = _rot_xyz(vec(el, "orientation", jname))
            p_bm = np.asarray(vec(el, "location", jname))
            parent = _Frame(pname, R_pf, p_pf)
            child = _Frame(b.get("name"), R_bm, p_bm)
            self._joint(el, jname, parent, child)

    def _old_vector(self, el, tag: str, jname: str) -> tuple[float, ...]:
        """A joint frame's numbers in a 3.x / 2.x file, as OpenSim reads them.

        OpenSim upgrades a file older than version 30505 by writing these four
        vectors into offset frames with six significant digits (C++'s default
        stream precision), and computes with the rounded values; so does skelid.
        """
        v = _floats(_text(el, tag, "0 0 0"), 3, f"joint {jname!r} {tag}")
        if self.version < OFFSET_FRAME_VERSION:
            v = tuple(float(f"{x:.6g}") for x in v)
        return v

    # markers ---------------------------------------------------------------
    def _read_markers(self, ms, source: str | None = None):
        if ms is None:
            return
        n = sum(1 for _ in ms.iter("Marker"))
        if n > MAX_MARKERS:  # refused before any is read (see MAX_MARKERS)
            raise ModelError(f"{source or self.source} has {n} markers, more than the {MAX_MARKERS} skelid "
                             "reads from one model",
                             "keep the markers of your protocol (a MarkerSet file of them, given with "
                             "--marker-set FILE)")
        for mk in ms.iter("Marker"):
            name = mk.get("name")
            ref = _text(mk, "socket_parent_frame") or _text(mk, "body")
            if not ref:
                raise ModelError(f"marker {name!r} names no body", "give it a socket_parent_frame or body")
            try:
                fr = self.frame(ref, {}, f"marker {name!r}")
            except ModelError:
                raise ModelError(f"marker {name!r} is on {ref!r}, which is not a body of the model",
                                 "put it on one of: " + ", ".join(self.bodies)) from None
            loc = np.asarray(_floats(_text(mk, "location", "0 0 0"), 3, f"marker {name!r} location"))
            fixed = (_text(mk, "fixed", "false") or "false").lower() == "true"
            self.markers.append((name, fr.body, fr.p + fr.R @ loc, fixed))


def _parse(path) -> ET.ElementTree:
    return read_xml(path, "model file")


# ----------------------------------------------------------------------------- to a skelid model
@dataclass(frozen=True)
class OsimInfo:
    """What the write-back needs besides the model: per segment its joint's child frame in the body (m)."""

    source: str
    child_offset: dict  # body -> (R_BM (3,3), p_BM (3,)) in metres
    joint_of: dict  # body -> joint name
    fixed_markers: frozenset
    marker_set: str | None = None  # the MarkerSet file read (given, or found next to the model)
    marker_set_found_by: str | None = None  # how it was found when not given
    unscalable: dict = field(default_factory=dict)  # body -> why skelid cannot scale it as OpenSim does


def read_osim(path, marker_set=None, keep: str = "markers", name: str | None = None) -> tuple[Model, OsimInfo]:
    """Read an OpenSim model into a skelid :class:`Model` (millimetres).

    Parameters
    ----------
    path : str or Path
        The .osim file.
    marker_set : str or Path, optional
        An OpenSim MarkerSet XML file whose markers replace the model's (the
        gait2354 model, for instance, ships its markers separately). Not given
        for a model without markers: the one :func:`find_marker_set` finds next
        to the model, if any (``info.marker_set`` names the file read).
    keep : {'markers', 'all'}
        Keep only the bodies that carry markers or lead to one (default), or all.

    Returns
    -------
    model : Model
        No parameters; see :func:`osim_parameters`.
    info : OsimInfo

    Raises
    ------
    FormatError, ModelError
        One line naming the element and the fix.
    """
    tree = _parse(path)
    rd = _Reader(tree.getroot(), str(path))
    rd.read()
    found_by = None
    if marker_set is None and not rd.markers:
        marker_set, found_by = find_marker_set(path)
    if marker_set is not None:
        ms_root = _parse(marker_set).getroot()
        ms = ms_root if ms_root.tag == "MarkerSet" else ms_root.find("MarkerSet")
        if ms is None:
            raise FormatError(f"{marker_set}: no <MarkerSet> element", "give an OpenSim MarkerSet file")
        rd.markers = []
        rd._read_markers(ms, str(marker_set))
    if not rd.markers:
        raise ModelError(f"{path} has no markers" + (f" and {found_by}" if marker_set is None and found_by else ""),
                         "give the model's MarkerSet file with --marker-set FILE (or add a MarkerSet to the model)")
    model, info = _to_model(rd, keep, name or rd.model_el.get("name") or Path(path).stem)
    return model, replace(info, marker_set=None if marker_set is None else str(marker_set),
                          marker_set_found_by=found_by)


class OsimCoordinate(NamedTuple):
    """One coordinate of an OpenSim model, as OpenSim lists it (joint order, then the joint's order)."""

    name: str
    joint: str
    rotational: bool  # it turns a rotation axis of its joint (OpenSim writes it in degrees)
    locked: bool
    default: float  # OpenSim units: radians or metres
    range: tuple = (-math.inf, math.inf)  # OpenSim units
    clamped: bool = False  # OpenSim keeps it inside its range (its inverse kinematics, too)


def osim_coordinates(path) -> tuple[OsimCoordinate, ...]:
    """Every coordinate of the model in ``path``, in the order OpenSim's coordinate set has them.

    A coordinate is rotational when it drives a rotation of its joint (as OpenSim decides a
    coordinate's motion type), translational otherwise.

    Raises
    ------
    FormatError, ModelError
        As :func:`read_osim`.
    """
    root = _parse(path).getroot()
    rd = _Reader(root, str(path))
    rd.read()
    clamped = {c.get("name"): (_text(c, "clamped", "false") or "false").lower() == "true"
               for c in root.iter("Coordinate")}
    out = []
    for j in rd.joints:
        for ci, (cname, rng, locked, default, _mt) in enumerate(j.coordinates):
            rot = any(m.kind == "R" and m.coordinate == ci for m in j.motions)
            out.append(OsimCoordinate(cname, j.name, rot, locked, float(default), tuple(float(v) for v in rng),
                                      clamped.get(cname, False)))
    return tuple(out)


def _document_kind(path: Path) -> str | None:
    """The tag of an OpenSim XML document's top object (``ScaleTool``, ``MarkerSet``, ``Model`` ...), cheaply."""
    return first_tag(path)


def find_marker_set(path) -> tuple[Path | None, str | None]:
    """The MarkerSet file that goes with a model without markers, found next to the model.

    Looked for among the ``*.xml`` files in the model's folder, in this order:

    1. the ``marker_set_file`` of an OpenSim ScaleTool setup whose
       ``GenericModelMaker`` names this model as its ``model_file`` (how
       OpenSim's own example folders pair a model with its markers);
    2. the only file whose document is a ``<MarkerSet>``.

    Parameters
    ----------
    path : str or Path
        The .osim file.

    Returns
    -------
    marker_set : Path or None
        None when neither rule gives exactly one file.
    how : str or None
        How it was found (for the user), or why none was taken.
    """
    path = Path(path)
    folder = path.resolve().parent
    setups, sets = [], []
    for f in sorted(folder.glob("*.xml")):
        if not f.is_file() or f.stat().st_size > 5_000_000:
            continue
        kind = _document_kind(f)
        if kind == "MarkerSet":
            sets.append(f)
        elif kind == "ScaleTool":
            setups.append(f)
    for f in setups:
        try:
            gm = read_xml(f).getroot().find(".//GenericModelMaker")
        except SkelidError:
            continue
        model_file = (_text(gm, "model_file", "") or "").strip() if gm is not None else ""
        ms_file = (_text(gm, "marker_set_file", "") or "").strip() if gm is not None else ""
        if not model_file or not ms_file or ms_file == "Unassigned":
            continue
        if (f.parent / model_file).resolve() == path.resolve() and (f.parent / ms_file).is_file():
            return f.parent / ms_file, (f"its markers come from {ms_file}, which the ScaleTool setup {f.name} "
                                        "beside it pairs with it")
    if len(sets) == 1:
        return sets[0], f"its markers come from {sets[0].name}, the only MarkerSet file beside it"
    if sets:
        return None, f"{len(sets)} MarkerSet files lie beside it ({', '.join(s.name for s in sets)})"
    return None, None


def _to_model(rd: _Reader, keep: str, name: str) -> tuple[Model, OsimInfo]:
    """The skelid model of what ``rd`` read: the tree, the bodies kept, their joints and markers."""
    by_child = _joints_by_child(rd)
    _check_marker_bodies(rd, by_child)
    kept = _kept_bodies(rd, by_child, keep)
    _check_couplers(rd, kept)
    order = [b for b in rd.bodies if b in kept]
    child_offset = {b: (by_child[b].child.R, by_child[b].child.p) for b in order}
    segments = [_segment(b, by_child[b], child_offset) for b in order]
    markers = [Marker(mname, body, tuple(float(v) for v in (loc - child_offset[body][1]) * M_TO_MM))
               for mname, body, loc, _fixed in rd.markers if body in kept]
    info = OsimInfo(rd.source, child_offset, {b: by_child[b].name for b in order},
                    frozenset(m[0] for m in rd.markers if m[3]),
                    unscalable={b: by_child[b].unscalable for b in order if by_child[b].unscalable})
    return Model(name, 3, "mm", tuple(segments), tuple(markers)), info


def _joints_by_child(rd: _Reader) -> dict:
    """Body -> the joint that attaches it (a body attached twice closes a loop: refused)."""
    by_child = {}
    for j in rd.joints:
        if j.child.body in by_child:
            raise ModelError(f"body {j.child.body!r} is the child of two joints "
                             f"({by_child[j.child.body].name!r}, {j.name!r})",
                             "skelid reads tree-shaped models; remove the loop-closing joint")
        by_child[j.child.body] = j
    return by_child


def _check_marker_bodies(rd: _Reader, by_child: dict) -> None:
    for b in {m[1] for m in rd.markers}:
        if b == "ground":
            raise ModelError("a marker is fixed to the ground", "remove it: it carries no information")
        if b not in by_child:
            raise ModelError(f"body {b!r} carries markers but no joint attaches it",
                             "attach it to the model with a joint")


def _kept_bodies(rd: _Reader, by_child: dict, keep: str) -> set:
    """The bodies that carry markers and those between them and the ground (all with ``keep='all'``)."""
    parent_of = {b: j.parent.body for b, j in by_child.items()}
    kept = set()
    for b in ({m[1] for m in rd.markers} if keep == "markers" else set(by_child)):
        while b != "ground" and b not in kept:
            kept.add(b)
            if b not in parent_of:
                raise ModelError(f"body {b!r} is not attached to the ground through joints",
                                 "attach it with a joint")
            b = parent_of[b]
    return kept


def _check_couplers(rd: _Reader, kept: set) -> None:
    """Refuse a coordinate coupled across joints when it moves a kept body."""
    owner = {c[0]: j for j in rd.joints for c in j.coordinates}
    for cname, dep, indep in rd.couplers:
        j = owner.get(dep)
        if j is not None and j.child.body in kept:
            raise ModelError(f"CoordinateCouplerConstraint {cname!r} makes coordinate {dep!r} of joint {j.name!r} "
                             f"({j.tag}) a function of {', '.join(map(repr, indep)) or 'nothing'}, and skelid's "
                             "joints follow only their own coordinates",
                             f"remove the markers of body {j.child.body!r} and of the bodies below it, or write the "
                             "coupling into the joint (a CustomJoint whose axes are functions of its own coordinate)")


def _segment(body: str, j: _JointSpec, child_offset: dict) -> Segment:
    """The segment of ``body`` and its joint (position, motions, coordinates, constant rotation), in mm."""
    par = j.parent.body
    base = np.zeros(3) if par == "ground" else child_offset[par][1]
    position = (j.parent.p - base) * M_TO_MM
    R_pf = j.parent.R
    cmap, coords = _moving_coordinates(j)
    motions = []
    for spec in j.motions:
        motion, offset = _motion(spec, j, R_pf, cmap)
        position = position + offset
        if motion is not None:
            motions.append(motion)
    ranges = [tuple(float(np.degrees(v)) for v in rng) for ci, (_n, rng, *_r) in enumerate(j.coordinates)
              if ci in cmap and any(m.kind == "R" and m.coordinate == cmap[ci] for m in motions)]
    C = R_pf @ j.child.R.T
    orient = () if np.allclose(C, np.eye(3), atol=1e-15, rtol=0) else tuple(float(v) for v in C.ravel())
    joint = Joint(j.name, "custom", tuple(float(v) for v in position), (), tuple(ranges), tuple(motions),
                  tuple(coords), orient)
    return Segment(body, None if par == "ground" else par, joint)


def _moving_coordinates(j: _JointSpec) -> tuple[dict, list]:
    """The joint's unlocked coordinates that drive a motion: OpenSim index -> skelid index, and their names."""
    cmap, coords = {}, []
    for ci, (cname, _rng, locked, _default, _mt) in enumerate(j.coordinates):
        if not locked and any(m.coordinate == ci for m in j.motions):
            cmap[ci] = len(coords)
            coords.append(cname)
    return cmap, coords


def _motion(spec: _MotionSpec, j: _JointSpec, R_pf: np.ndarray, cmap: dict) -> tuple[Motion | None, np.ndarray]:
    """One motion of an OpenSim joint in the parent body's frame (mm), or None and the fixed offset it is.

    A locked coordinate's motion becomes a constant at its default value; a
    constant translation is a shift of the joint's position (returned).
    """
    f, ci = spec.function, spec.coordinate
    if ci >= 0 and j.coordinates[ci][2]:  # locked
        f = CoordinateFunction("constant", (float(f.value(np.array([j.coordinates[ci][3]]))[0]),))
        ci = -1
    a = tuple(float(v) for v in R_pf @ np.asarray(spec.axis))
    none = np.zeros(3)
    if spec.kind == "R":
        return Motion("R", a, cmap.get(ci, -1), f), none
    if spec.kind == "C":
        return Motion("C", a, -1, _scaled(f, M_TO_MM), tuple(float(v) for v in spec.weights),
                      tuple(float(v) for v in R_pf @ np.asarray(spec.vector))), none
    if not (ci >= 0 and f.is_identity):  # a translational coordinate stays in mm through the pose
        f = _scaled(f, M_TO_MM)
    if f.is_constant:  # a fixed offset: part of the joint position
        return None, np.asarray(a) * f.coefficients[0] * f.scale
    return Motion("T", a, cmap.get(ci, -1), f, tuple(float(v) for v in spec.axis)), none


def _scaled(f: CoordinateFunction, factor: float) -> CoordinateFunction:
    return CoordinateFunction(f.kind, f.coefficients, f.x, f.y, f.end, f.scale * factor)


# ----------------------------------------------------------------------------- parameters
def osim_parameters(model: Model, info: OsimInfo, scale: str = "bodies", markers: str = "offsets",
                    marker_names=None, scale_sd_log: float = 0.15, offset_sd: float = 10.0,
                    holders: bool = False) -> Model:
    """The model with identification parameters for an imported OpenSim model.

    Parameters
    ----------
    scale : {'bodies', 'axes', 'linked', 'none'}
        One log-normal scale factor per body that carries markers (with
        ``holders``, also per body that holds the joint of one: :func:`scaled_bodies`;
        median 1, ``scale_sd_log``), three per axis, three per axis whose logs are correlated
        (:data:`AXIS_CORRELATION`: a body's proportions lean towards one common
        factor without being held to it), or none.
    markers : {'offsets', 'none'}
        A normal ``marker_offset`` (mean 0, ``offset_sd`` mm) per axis of every
        marker, or none. A marker OpenSim marks ``fixed`` (a palpated bony
        landmark, which its MarkerPlacer does not move) gets one too: a
        landmark is found on the skin to within millimetres to centimetres, and
        a generic model's landmark sits where this subject's does only as far as
        the body scales linearly; held exact, such markers' placement errors
        went into the scales with intervals that did not hold them.
    marker_names : iterable of str, optional
        Markers present in the data: only those get offsets, and only the
        markers among them count as carrying a body. Default: all.
    holders : bool
        Scale the unmarked bodies that hold a marked one's joint too. Their
        factors are known to the data only through where the bodies below them
        sit, often not at all: only a fit under the scales' priors (the joint
        fit of scales and offsets) can have them.

    Returns
    -------
    Model
    """
    if scale not in SCALE_MODES:
        raise ModelError(f"unknown scale setting {scale!r}", "use bodies, axes, linked or none")
    if markers not in ("offsets", "none"):
        raise ModelError(f"unknown marker setting {markers!r}", "use offsets or none")
    present = set(model.marker_names if marker_names is None else marker_names)
    bodies = (scaled_bodies(model, present) if holders else
              [b.name for b in model.segments if any(m.segment == b.name and m.name in present for m in model.markers)])
    params = _scale_parameters(bodies, scale, info, scale_sd_log)
    if markers == "offsets":
        oprior = Prior("normal", -5 * offset_sd, 5 * offset_sd, 0.0, offset_sd)
        for m in model.markers:
            if m.name in present:
                params += [Parameter(f"offset_{m.name}_{a}", "marker_offset", m.name, i, oprior, offset_sd / 20)
                           for i, a in enumerate("xyz")]
    return Model(model.name, model.dim, model.units, model.segments, model.markers, tuple(params),
                 model.description)


def scaled_bodies(model: Model, present) -> list[str]:
    """The bodies that get scale factors: those that carry a marker of ``present``, and those that carry
    none but hold the joint of a body below them that does, away from their own joint centre.

    A body between two marked ones (the talus between the shank and the foot, the ulna between the
    upper arm and the radius) places everything below it by its size: held at the generic size, its
    true scale would go into the foot's scales and markers with intervals that do not hold it.
    """
    marked = {m.segment for m in model.markers if m.name in present}
    below = set(marked)  # bodies with a marked body at or below them
    for s in reversed(model.segments):  # children come after their parents
        if s.name in below and s.parent is not None:
            below.add(s.parent)
    holds = {s.parent for s in model.segments
             if s.parent is not None and s.name in below and np.linalg.norm(s.joint.position) > 1e-9}
    return [s.name for s in model.segments if s.name in marked or (s.name in below and s.name in holds)]


def _scale_parameters(bodies, scale: str, info: OsimInfo, sd_log: float) -> list[Parameter]:
    """One log-normal factor per body (``scale='bodies'``), three (``'axes'``, ``'linked'``) or none."""
    if scale == "none":
        return []
    lo, hi = math.exp(-5 * sd_log), math.exp(5 * sd_log)
    prior = Prior("lognormal", lo, hi, 1.0, sd_log)
    params = []
    for s in bodies:
        if s in info.unscalable:
            raise ModelError(f"body {s!r} cannot get a scale factor: {info.unscalable[s]}",
                             "fit without scale factors (--scale none) or put the winging axis through the "
                             "joint centre (scapula_winging_axis_origin 0 0)")
        if scale == "bodies":
            params.append(Parameter(f"scale_{s}", "scale", s, None, prior, (hi - lo) / 200))
        else:
            pa = prior if scale == "axes" else replace(prior, group=f"scale_{s}", correlation=AXIS_CORRELATION)
            params += [Parameter(f"scale_{s}_{a}", "scale", s, i, pa, (hi - lo) / 200) for i, a in enumerate("xyz")]
    return params


#: the scale settings of :func:`osim_parameters`
SCALE_MODES = ("bodies", "axes", "linked", "none")
#: ``scale='linked'``: the correlation of the logs of a body's three axis factors. With the factors'
#: log-sd of 0.15, each axis departs from the body's common factor by a log-sd of
#: ``0.15 sqrt((1 - rho) 2/3)``, about 0.055 (5.5 %), and two axes differ by ``0.15 sqrt(2 (1 - rho))``, about 0.095:
#: a body's proportions held near one factor where the data say nothing of them, free where they do.
#: Of the order of real bodies: AddBiomechanics' per-axis scales of ``addbio-subject4`` (its
#: ``optimized_scale_and_markers.osim`` over ``unscaled_generic.osim``) depart from their body's mean
#: log by 0.044 rms, this prior's by 0.055
AXIS_CORRELATION = 0.8


def keep_markers(model: Model, names) -> Model:
    """The model with only the markers ``names`` and the bodies they need (no parameters)."""
    names = set(names)
    mk = tuple(m for m in model.markers if m.name in names)
    if not mk:
        raise ModelError(f"none of the markers of model {model.name!r} is in the data",
                         "check the marker names in the data file against the model's")
    idx = {s.name: s for s in model.segments}
    need = set()
    for m in mk:
        b = m.segment
        while b is not None and b not in need:
            need.add(b)
            b = idx[b].parent
    return Model(model.name, 3, model.units, tuple(s for s in model.segments if s.name in need), mk)


def load_osim(path, marker_set=None, scale: str = "bodies", markers: str = "offsets",
              marker_names=None) -> Model:
    """:func:`read_osim`, only the markers in ``marker_names`` if given, then :func:`osim_parameters`."""
    model, info = read_osim(path, marker_set)
    if marker_names is not None:
        model = keep_markers(model, marker_names)
    return osim_parameters(model, info, scale, markers, marker_names)


# ----------------------------------------------------------------------------- writing back
def body_scales(model: Model, theta) -> dict[str, np.ndarray]:
    """Per body its three scale factors from ``theta (P,)`` (1 where it has no scale parameter)."""
    out = {}
    for k, p in enumerate(model.parameters):
        if p.kind == "scale":
            s = out.setdefault(p.target, np.ones(3))
            if p.axis is None:
                s[:] = theta[k]
            else:
                s[p.axis] = theta[k]
    return out


def scales_held(model: Model, scales: dict) -> Model:
    """``model`` with the bodies of ``scales`` (name -> three factors) scaled into its geometry, their scale
    parameters gone: the same marker positions at every pose as ``model`` at those factors.

    A body's factors scale its markers, the joint places of the bodies it carries and the translations of
    their custom joints that scale with it (by ``w . s`` over ``w . 1``, ``w`` the motion's scale weights,
    :attr:`skelid.model.description.Model.coupled_translations`).
    """
    s = {b: np.broadcast_to(np.asarray(v, float), (3,)) for b, v in scales.items()}
    if not s:
        return model

    def motion(m: Motion, f: np.ndarray) -> Motion:  # the weights as Model._translation_factor takes them
        if not _scales_with_parent(m):
            return m
        w = np.asarray(m.scale_weights or np.asarray(m.axis, float) ** 2, float)
        return replace(m, function=_scaled(m.function, float(w @ f / w.sum())))

    segments = []
    for seg in model.segments:
        f = s.get(seg.parent)
        if f is not None:
            j = seg.joint
            seg = replace(seg, joint=replace(j, position=tuple(float(v) for v in np.asarray(j.position) * f),
                                             motions=tuple(motion(m, f) for m in j.motions)))
        segments.append(seg)
    markers = tuple(replace(m, position=tuple(float(v) for v in np.asarray(m.position) * s[m.segment]))
                    if m.segment in s else m for m in model.markers)
    params = tuple(p for p in model.parameters if not (p.kind == "scale" and p.target in s))
    return Model(model.name, model.dim, model.units, tuple(segments), markers, params, model.description)


def marker_locations(model: Model, info: OsimInfo, theta, moved=None) -> dict[str, np.ndarray]:
    """Each marker's location in its body frame (metres) after scaling and offsets (and ``moved``: a
    marker's further displacement in its body frame, mm, by name)."""
    from skelid.model.kinematics import geometry

    g = geometry(model, np.asarray(theta, float))
    S, M = len(model.segments), len(model.markers)
    r = g[S * 3:(S + M) * 3].reshape(M, 3) / M_TO_MM
    scales = body_scales(model, theta)
    out = {}
    for i, m in enumerate(model.markers):
        p_bm = info.child_offset[m.segment][1] * scales.get(m.segment, np.ones(3))
        out[m.name] = p_bm + r[i] + np.asarray((moved or {}).get(m.name, np.zeros(3)), float) / M_TO_MM
    return out


def widened_offset_priors(model: Model, names, sd: float) -> Model:
    """``model`` with the offset priors of the markers ``names`` widened to ``sd`` (mm) about the same centre."""
    names = set(names)
    params = []
    for p in model.parameters:
        if p.kind == "marker_offset" and p.target in names:
            pr = p.prior
            p = replace(p, prior=replace(pr, lower=pr.mean - 5.0 * sd, upper=pr.mean + 5.0 * sd, sd=sd))
        params.append(p)
    return replace(model, parameters=tuple(params))


def centred_offset_priors(model: Model, centre: dict) -> Model:
    """``model`` with the offset priors of the markers in ``centre`` (name -> (3,) mm) centred there."""
    if not centre:
        return model
    params = []
    for p in model.parameters:
        if p.kind == "marker_offset" and p.target in centre:
            c, pr = float(centre[p.target][p.axis]), p.prior
            p = replace(p, prior=replace(pr, lower=pr.lower + c, upper=pr.upper + c, mean=pr.mean + c))
        params.append(p)
    return replace(model, parameters=tuple(params))


def mean_places(fit) -> dict | None:
    """Where the slide puts each marker on average over the trials (mm, body frame), from its offset's place.

    The offsets are the markers' places at the model's zero pose; a marker that slides sits elsewhere
    while the subject moves, and inverse kinematics holds it at one place: the written model puts it
    at its mean place over the trials. None where no slide was estimated. ``fit``: a
    :class:`skelid.scaling.ScalingFit` (or anything with its ``result``).
    """
    return (fit.result.get("artefact") or {}).get("mean_place_mm")


def offsets_moved(model: Model, theta, moved: dict) -> tuple[Model, np.ndarray]:
    """``(model, theta)`` with each marker of ``moved`` (name -> (3,) mm, body frame) moved by that much.

    Its offsets take the move and their priors move with them (:func:`centred_offset_priors`); an axis
    without an offset moves the marker's nominal place (unscaled, as the scales apply to it).
    """
    theta = np.array(theta, float)
    done = set()
    for k, p in enumerate(model.parameters):
        if p.kind == "marker_offset" and p.target in moved:
            theta[k] += float(moved[p.target][p.axis])
            done.add((p.target, p.axis))
    model = centred_offset_priors(model, {m: np.asarray(v, float) for m, v in moved.items()
                                     if any((m, a) in done for a in range(3))})
    scales = body_scales(model, theta)
    markers = []
    for m in model.markers:
        rest = np.array([0.0 if (m.name, a) in done else float(moved.get(m.name, (0.0,) * 3)[a]) for a in range(3)])
        if np.any(rest):
            m = replace(m, position=tuple(np.asarray(m.position, float) + rest / scales.get(m.segment, np.ones(3))))
        markers.append(m)
    return replace(model, markers=tuple(markers)), theta


def _fmt(v) -> str:
    return " ".join(repr(float(x)) for x in v)


def _scale_function_el(fel_parent, factor: float):
    """Multiply the function under ``fel_parent`` by ``factor`` (wrap it, or scale a MultiplierFunction)."""
    for c in list(fel_parent):
        if c.tag == "MultiplierFunction":
            sc = c.find("scale")
            sc.text = repr(float(sc.text) * factor)
            return
        if c.tag == "Constant":
            v = c.find("value")
            v.text = repr(float(v.text) * factor)
            return
        if c.tag in FUNCTION_TAGS:
            idx = list(fel_parent).index(c)
            fel_parent.remove(c)
            mf = ET.Element("MultiplierFunction", {"name": c.get("name", "function")})
            c2 = copy.deepcopy(c)
            c2.set("name", "")
            inner = ET.SubElement(mf, "function")
            inner.append(c2)
            ET.SubElement(mf, "scale").text = repr(float(factor))
            fel_parent.insert(idx, mf)
            return


def write_scaled_osim(src, out, model: Model, info: OsimInfo, theta, marker_set=None, name=None,
                      moved=None) -> None:
    """Write ``src`` scaled by the fitted ``theta`` to ``out``, every other element untouched.

    Joint frames on a body are scaled by its factors, coupled translations of
    a ``CustomJoint`` by its parent's factor along the axis, the ellipsoid of an
    ``EllipsoidJoint`` or ``ScapulothoracicJoint`` by its parent's factors,
    markers moved to their fitted locations (scale and offset). Markers read
    from a separate ``marker_set`` file are added to the model's MarkerSet; ``moved`` as for
    :func:`marker_locations`.
    """
    tree = _parse(src)
    m_el = tree.getroot().find("Model")
    if name:
        m_el.set("name", name)
    scales = body_scales(model, theta)
    joints = _scale_joint_frames(m_el, scales)
    for el, parent, child in joints:
        _scale_joint_motion(el, scales.get(parent), scales.get(child))
    ms = _merged_marker_set(m_el, marker_set)
    if ms is not None:
        _place_markers(ms, marker_locations(model, info, theta, moved), scales)
    tree.write(out, encoding="UTF-8", xml_declaration=True)


def _scale_vector(el, tag: str, factors) -> None:
    """Multiply the three numbers of ``el``'s ``tag`` element by ``factors`` (nothing if either is absent)."""
    e = el.find(tag)
    if e is not None and factors is not None:
        e.text = _fmt(np.asarray(_floats(e.text, 3, tag)) * factors)


def _scale_joint_frames(m_el, scales: dict) -> list:
    """Scale every joint's frames by their bodies' factors; ``(joint element, parent body, child body)`` each."""
    bodyset = m_el.find("BodySet")
    joints = []
    if any(b.find("Joint") is not None for b in bodyset.iter("Body")):  # 2.x / 3.x: joints inside bodies
        for b in bodyset.iter("Body"):
            jw = b.find("Joint")
            if jw is not None and len(jw):
                el = jw[0]
                parent = _text(el, "parent_body", "")
                _scale_vector(el, "location_in_parent", scales.get(parent))
                _scale_vector(el, "location", scales.get(b.get("name")))
                joints.append((el, parent, b.get("name")))
        return joints
    for el in (m_el.find("JointSet").find("objects") or []):
        fr = el.find("frames")
        offsets = {f.get("name"): _last(_text(f, "socket_parent", "")) for f in
                   (fr.iter("PhysicalOffsetFrame") if fr is not None else [])}
        for f in (fr.iter("PhysicalOffsetFrame") if fr is not None else []):
            _scale_vector(f, "translation", scales.get(offsets[f.get("name")]))
        parent, child = (_last(_text(el, tag, "")) for tag in ("socket_parent_frame", "socket_child_frame"))
        joints.append((el, offsets.get(parent, parent), offsets.get(child, child)))
    return joints


def _last(ref: str | None) -> str:
    return (ref or "").rsplit("/", 1)[-1]


def _scale_joint_motion(el, parent_scale, child_scale) -> None:
    """Scale what a joint's motion holds, as OpenSim's ``extendScale`` of its type does."""
    if el.tag == "EllipsoidJoint":
        _scale_vector(el, "radii_x_y_z", parent_scale)
    elif el.tag == "ScapulothoracicJoint":
        _scale_vector(el, "thoracic_ellipsoid_radii_x_y_z", parent_scale)
        o = el.find("scapula_winging_axis_origin")
        if o is not None and parent_scale is not None and child_scale is not None:
            o.text = _fmt(np.asarray(_floats(o.text, 2, "scapula_winging_axis_origin")) * child_scale[:2])
    elif el.tag == "CustomJoint" and parent_scale is not None:
        for ta in el.iter("TransformAxis"):
            if not ta.get("name", "").startswith("translation"):
                continue
            a = np.asarray(_floats(_text(ta, "axis"), 3, "axis"))
            factor = float(a / np.linalg.norm(a) @ parent_scale)  # OpenSim: the axis (parent frame) . factors
            holder = ta.find("function")
            _scale_function_el(ta if holder is None else holder, factor)


def _merged_marker_set(m_el, marker_set):
    """The model's MarkerSet element, with the markers of a separate ``marker_set`` file added."""
    ms = m_el.find("MarkerSet")
    if marker_set is None:
        return ms
    extra = _parse(marker_set).getroot()
    extra = extra if extra.tag == "MarkerSet" else extra.find("MarkerSet")
    if ms is None:
        ms = ET.SubElement(m_el, "MarkerSet", {"name": "markerset"})
    objs = ms.find("objects")
    if objs is None:
        objs = ET.SubElement(ms, "objects")
    for mk in extra.iter("Marker"):
        objs.append(copy.deepcopy(mk))
    return ms


def _place_markers(ms, locations: dict, scales: dict) -> None:
    """Fitted markers at their fitted locations; the others scaled with their body."""
    for mk in ms.iter("Marker"):
        n = mk.get("name")
        body = _last(_text(mk, "socket_parent_frame") or _text(mk, "body") or "")
        loc = mk.find("location")
        if n in locations:
            loc.text = _fmt(locations[n])
        elif body in scales and loc is not None:
            loc.text = _fmt(np.asarray(_floats(loc.text, 3, "location")) * scales[body])


def write_scale_set(out, model: Model, theta, name: str = "scaleset") -> None:
    """An OpenSim ScaleSet XML with one Scale per body that has scale parameters."""
    root = ET.Element("OpenSimDocument", {"Version": "40000"})
    ss = ET.SubElement(root, "ScaleSet", {"name": name})
    objs = ET.SubElement(ss, "objects")
    for body, s in body_scales(model, theta).items():
        e = ET.SubElement(objs, "Scale", {"name": ""})
        ET.SubElement(e, "scales").text = _fmt(s)
        ET.SubElement(e, "segment").text = body
        ET.SubElement(e, "apply").text = "true"
    ET.indent(root)
    ET.ElementTree(root).write(out, encoding="UTF-8", xml_declaration=True)
