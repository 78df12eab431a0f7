"""The model description: segments, joints, markers and unknown parameters.

A model is a tree of rigid segments. Each segment has one joint that attaches
it to its parent (or to the ground for the root). A segment's frame has its
origin at that joint's centre; the joint's ``position`` is the centre written
in the parent's frame (in the world frame for the root). Markers sit at fixed
positions in their segment's frame.

A pose ``q`` stacks the coordinates of every joint, in segment order. Each joint
is a short chain of elementary motions applied in the parent frame at the joint
centre:

==========  ====  ====================================================
type        dim   elementary motions (in order)
==========  ====  ====================================================
free        2     translate x, translate y, rotate (about z)
free        3     translate x, y, z, then rotate about z, x, y
revolute    2     rotate (about z)
hinge       3     rotate about ``axis``
universal   3     rotate about ``axes[0]``, then about ``axes[1]``
spherical   3     rotate about z, x, y (body-fixed; singular at x = ±90°)
fixed       2, 3  none
==========  ====  ====================================================

The geometry vector ``g`` concatenates every joint's position in its parent's
frame, then every marker's position in its segment's frame. Unknown parameters
``theta (..., P)`` enter it linearly, ``g = g_base + theta @ A.T``:

* ``length``: the distance from a segment's origin to the joint ``joint``
  (the joint's position keeps its direction, its norm becomes ``theta``);
* ``joint_position``: one coordinate (``axis`` x, y or z) of a joint centre in
  its parent's frame;
* ``marker_position``: one coordinate of a marker in its segment's frame;
* ``joint_centre``: a shift ``delta`` (one coordinate, parent frame) of a
  joint centre *relative to both segments it joins*: the joint's position
  gains ``delta`` while the child's markers and the child's own joints lose it,
  so that in the reference pose (every joint coordinate zero) no marker moves.
  Only relative motion at the joint informs it (a functional joint centre).

* ``translation_gain``: the multiplier of one translation of a ``custom`` joint
  (``motion``: its index in the joint's motions), which moves the child by
  ``theta f(q)`` along its axis instead of ``f(q)`` (1 is the model as written;
  it replaces the parent's ``scale`` for that translation). With translations
  ``q, q^2, ...`` it lets a joint centre slide with the joint's angle by an
  unknown amount (:func:`skelid.model.variants.moving_centre`).

One kind enters nonlinearly and is handled by the kinematics:

* ``axis_direction``: a tilt (degrees) of a hinge axis away from its nominal
  direction ``e``. With ``u`` the parent-frame coordinate axis most
  perpendicular to ``e`` (made orthogonal to it) and ``v = e x u``, the tilts
  ``(alpha, beta)`` give the axis
  ``a = cos(alpha) cos(beta) e + sin(alpha) cos(beta) u + sin(beta) v``.

A parameter table with ``axes = [...]`` declares a vector: one scalar
parameter per listed axis, named ``<name>_<axis>``.

The model is frozen and hashable; algorithms take it first and never change it.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from skelid.errors import ModelError
from skelid.model.functions import CoordinateFunction
from skelid.model.kinds import JOINT_TYPES, MOTION_KINDS, PARAMETER_KINDS, PARAMETER_TARGET
from skelid.model.schema import check_built, validate

LINEAR_SETTING_KINDS = ("length", "joint_position", "marker_position")  # replace a coordinate
PRIOR_KINDS = ("uniform", "normal", "lognormal")
AXES = {"x": 0, "y": 1, "z": 2}
MOTION_KIND_OF = {v: k for k, v in MOTION_KINDS.items()}
TILT_AXES = {"u": 0, "v": 1}
UNITS = ("mm", "cm", "m")


def _unit(v, where: str) -> tuple[float, ...]:
    a = np.asarray(v, dtype=float)
    n = float(np.linalg.norm(a))
    if a.shape != (3,) or not np.isfinite(n) or n == 0:
        raise ModelError(f"{where}: an axis must be three finite numbers, not all zero, got {v!r}")
    if abs(n - 1.0) > 1e-12:  # leave unit vectors alone, so that a model written out reads back equal
        a = a / n
    return tuple(float(x) for x in a)


def tilt_basis(axis) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
    """``(e, u, v)``: a hinge's nominal unit axis and the two directions it tilts towards.

    ``u`` is the coordinate axis (x, then y, then z on ties) most perpendicular
    to ``e``, made orthogonal to it; ``v = e x u``.
    """
    e = np.asarray(axis, dtype=float)
    e = e / np.linalg.norm(e)
    c = int(np.argmin(np.abs(e)))
    u = np.eye(3)[c] - e[c] * e
    u = u / np.linalg.norm(u)
    v = np.cross(e, u)
    return tuple(map(float, e)), tuple(map(float, u)), tuple(map(float, v))


# ----------------------------------------------------------------------------- parts
@dataclass(frozen=True)
class Prior:
    """Prior of one scalar parameter.

    ``uniform(lower, upper)``, ``normal(mean, sd)`` or ``lognormal(median, sd_log)``.
    ``lower``/``upper`` always bound the search (grid) interval; for normal and
    log-normal priors they default to five standard deviations either side.

    ``group``/``correlation``: log-normal priors of equal ``sd_log`` that share a
    ``group`` name are jointly normal in their logs with this correlation (a body's
    three axis factors that lean towards one common factor; the OpenSim joint fit reads
    it, :func:`skelid.scaling._prior_terms`); each one's marginal is the prior above.
    """

    kind: str
    lower: float
    upper: float
    mean: float = math.nan
    sd: float = math.nan
    group: str = ""
    correlation: float = 0.0

    def log_pdf(self, x):
        """Log density (up to a constant) at ``x``; ``-inf`` outside the bounds."""
        x = np.asarray(x, dtype=float)
        inside = (x >= self.lower) & (x <= self.upper)
        if self.kind == "uniform":
            lp = np.zeros_like(x)
        elif self.kind == "normal":
            lp = -0.5 * ((x - self.mean) / self.sd) ** 2
        else:
            with np.errstate(divide="ignore", invalid="ignore"):
                lx = np.log(np.where(x > 0, x, np.nan))
            lp = -0.5 * ((lx - math.log(self.mean)) / self.sd) ** 2 - lx
        return np.where(inside, lp, -np.inf)

    @property
    def center(self) -> float:
        return 0.5 * (self.lower + self.upper) if self.kind == "uniform" else self.mean

    def to_dict(self) -> dict:
        d = {"type": self.kind, "lower": self.lower, "upper": self.upper}
        if self.kind == "normal":
            d.update(mean=self.mean, sd=self.sd)
        elif self.kind == "lognormal":
            d.update(median=self.mean, sd_log=self.sd)
        return d


@dataclass(frozen=True)
class Parameter:
    """One unknown scalar of the model geometry.

    Attributes
    ----------
    name : str
    kind : {'length', 'joint_position', 'marker_position', 'joint_centre', 'axis_direction'}
    target : str
        The joint (every kind but ``marker_position``) or marker it moves.
    axis : int or None
        Coordinate index (x, y, z) for the position kinds and ``joint_centre``;
        tilt index (u, v) for ``axis_direction``; the motion's index in its joint's
        ``motions`` for ``translation_gain``; None for ``length``.
    prior : Prior
    grid_step : float
        Spacing of the candidate grid used by grid filters.
    """

    name: str
    kind: str
    target: str
    axis: int | None
    prior: Prior
    grid_step: float

    @property
    def grid(self) -> np.ndarray:
        """(K,) float: candidate values ``lower, lower + step, ..., upper``."""
        from skelid.resources import MAX_GRID_POINTS

        n = (self.prior.upper - self.prior.lower) / self.grid_step
        if not n + 1 <= MAX_GRID_POINTS:
            raise ModelError(f"parameter {self.name!r}: a grid_step of {self.grid_step:g} makes {n + 1:.3g} grid "
                             "points", "use a coarser grid_step (or narrower prior bounds) in the model file")
        n = int(round(n)) + 1
        return np.linspace(self.prior.lower, self.prior.lower + (n - 1) * self.grid_step, n)


@dataclass(frozen=True)
class Motion:
    """One elementary motion of a ``custom`` joint: a rotation or translation by ``function(q)``.

    ``axis`` is a unit vector in the parent segment's frame (translations) or in
    the frame left by the joint's earlier rotations (rotations);
    ``coordinate`` indexes the joint's ``coordinates`` (-1: a constant function).

    A *carried* translation (kind ``"C"``) moves the child along ``axis`` (parent
    frame) by ``f * (axis . W v)``: the component along ``axis`` of the vector
    ``vector`` (parent frame) turned by ``W``, the product of the joint's rotations
    listed before it. Three of them along orthogonal axes with ``f`` the semi-axes
    and ``v`` the normal put the joint centre at ``diag(r) W v``, a point that
    slides over an ellipsoid as the joint turns (OpenSim's ``EllipsoidJoint``).
    Its function is a constant (the coordinates act through ``W``).
    """

    kind: str  # "R", "T" or "C"
    axis: tuple[float, ...]
    coordinate: int
    function: CoordinateFunction
    scale_weights: tuple[float, ...] = ()  # translation scales by w . s (default: the axis squared; 0: never)
    vector: tuple[float, ...] = ()  # carried translations: the vector v (parent frame)


@dataclass(frozen=True)
class Joint:
    """The joint that attaches a segment to its parent.

    A ``custom`` joint moves its child by ``motions``: every translation first
    (along axes of the parent's frame; a carried one by the component of a
    vector turned by the rotations listed before it), then the rotations in
    order, then the constant rotation ``orientation``; the coordinates it has
    are named by ``coordinates`` (see :mod:`skelid.model.functions`). With no
    motion at all it attaches its child rigidly (a weld).
    """

    name: str
    type: str
    position: tuple[float, ...]
    axes: tuple[tuple[float, ...], ...] = ()
    range: tuple[tuple[float, float], ...] = ()  # degrees, per rotation; used to simulate
    motions: tuple[Motion, ...] = ()
    coordinates: tuple[str, ...] = ()
    orientation: tuple[float, ...] = ()  # 9 numbers, row-major: rotation after the motions (custom)


@dataclass(frozen=True)
class Segment:
    """A rigid segment; ``parent`` is None for the root (attached to the ground)."""

    name: str
    parent: str | None
    joint: Joint


@dataclass(frozen=True)
class Marker:
    """A marker at ``position`` in ``segment``'s frame; ``label`` is its name in files."""

    name: str
    segment: str
    position: tuple[float, ...]
    label: str | None = None


@dataclass(frozen=True)
class Dof:
    """One pose coordinate of a joint (internal): an elementary motion, or a coupled coordinate."""

    segment: int
    kind: str  # "R" rotation or "T" translation
    axis: tuple[float, ...]  # in the frame the joint acts in (after earlier motions)
    coupled: bool = False  # drives several motions of a custom joint, or one through a function


# ----------------------------------------------------------------------------- model
@dataclass(frozen=True)
class Model:
    """A frozen articulated model.

    Build it with :func:`load_model` (TOML) or :func:`model_from_dict`; the
    constructor checks the tree and orders segments parents-first.
    """

    name: str
    dim: int
    units: str
    segments: tuple[Segment, ...]
    markers: tuple[Marker, ...]
    parameters: tuple[Parameter, ...] = ()
    description: str = field(default="", compare=False)

    def __post_init__(self):
        """Check the model with small named checkers (:data:`TREE_CHECKS`, then :data:`CONTENT_CHECKS`),
        ordering the segments parents first in between."""
        for check in TREE_CHECKS:
            check(self)
        object.__setattr__(self, "segments", _parents_first(self.segments))
        for check in CONTENT_CHECKS:
            check(self)

    # ------------------------------------------------------------ names & sizes
    @property
    def marker_names(self) -> tuple[str, ...]:
        return tuple(m.name for m in self.markers)

    @property
    def marker_labels(self) -> dict[str, str]:
        """Model marker name -> name in data files (where they differ)."""
        return {m.name: m.label for m in self.markers if m.label and m.label != m.name}

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)

    @property
    def n_params(self) -> int:
        return len(self.parameters)

    @property
    def segment_index(self) -> dict[str, int]:
        return {s.name: i for i, s in enumerate(self.segments)}

    @property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(s.joint.name for s in self.segments)

    def parameter(self, name: str) -> Parameter:
        for p in self.parameters:
            if p.name == name:
                return p
        raise ModelError(f"model {self.name!r} has no parameter {name!r}",
                         f"use one of: {', '.join(self.parameter_names) or '(none)'}")

    # --------------------------------------------------------------- compiled
    @cached_property
    def dofs(self) -> tuple[Dof, ...]:
        """Elementary motions of all joints, in pose order."""
        out = []
        for i, s in enumerate(self.segments):
            t = s.joint.type
            if self.dim == 2:
                if t == "free":
                    out += [Dof(i, "T", (1.0, 0.0)), Dof(i, "T", (0.0, 1.0)), Dof(i, "R", ())]
                elif t == "revolute":
                    out.append(Dof(i, "R", ()))
            else:
                ex, ey, ez = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
                if t == "free":
                    out += [Dof(i, "T", ex), Dof(i, "T", ey), Dof(i, "T", ez)]
                    out += [Dof(i, "R", ez), Dof(i, "R", ex), Dof(i, "R", ey)]
                elif t == "spherical":
                    out += [Dof(i, "R", ez), Dof(i, "R", ex), Dof(i, "R", ey)]
                elif t in ("hinge", "universal"):
                    out += [Dof(i, "R", a) for a in s.joint.axes]
                elif t == "custom":
                    out += _custom_dofs(i, s.joint)
        return tuple(out)

    @cached_property
    def coupled_translations(self) -> tuple[tuple[int, int, np.ndarray, float], ...]:
        """Translations of ``custom`` joints by a function that scales with the parent segment.

        ``(segment index, motion index, b (P,), base)``: the translation
        ``f(q)`` along its axis ``a`` is multiplied by ``base + theta @ b``, the
        parent's scale along ``a``: ``sum_i w_i s_i`` with ``s_i`` its per-axis
        factors (``s`` for one factor) and weights ``w`` the motion's
        ``scale_weights`` (an imported OpenSim joint: its axis in the joint's
        parent frame, as OpenSim scales a ``CustomJoint``) or ``a_i^2``.
        Translations that are a coordinate itself are not scaled, nor those
        whose weights are all zero. Carried translations are scaled like the
        others (an ellipsoid's semi-axes grow with its parent). A
        ``translation_gain`` parameter replaces that factor by its own value.
        """
        out = []
        for i, s in enumerate(self.segments):
            if s.joint.type != "custom" or s.parent is None:
                continue
            out += [(i, j, *self._translation_factor(s, j, m)) for j, m in enumerate(s.joint.motions)
                    if _scales_with_parent(m)]
        return tuple(out)

    def _translation_factor(self, s: Segment, j: int, m: Motion) -> tuple[np.ndarray, float]:
        """``(b (P,), base)`` of motion ``j`` of ``s``'s joint (see :attr:`coupled_translations`)."""
        b = np.zeros(self.n_params)
        gain = [k for k, p in enumerate(self.parameters)
                if p.kind == "translation_gain" and p.target == s.joint.name and p.axis == j]
        if gain:
            b[gain[0]] = 1.0
            return b, 0.0
        a2 = np.asarray(m.scale_weights or np.asarray(m.axis, float) ** 2, float)
        covered = np.zeros(3)
        for k, p in enumerate(self.parameters):
            if p.kind == "scale" and p.target == s.parent:
                axes = slice(None) if p.axis is None else p.axis
                b[k] += a2[axes].sum()
                covered[axes] = 1.0
        return b, float(a2 @ (1.0 - covered))

    @property
    def n_pose(self) -> int:
        """Number of pose coordinates per frame."""
        return len(self.dofs)

    @cached_property
    def parent_index(self) -> np.ndarray:
        """(S,) int: index of each segment's parent, -1 for the root."""
        idx = self.segment_index
        return np.array([-1 if s.parent is None else idx[s.parent] for s in self.segments])

    @cached_property
    def marker_segment(self) -> np.ndarray:
        """(M,) int: segment index of each marker."""
        idx = self.segment_index
        return np.array([idx[m.segment] for m in self.markers])

    @cached_property
    def ancestor(self) -> np.ndarray:
        """(S, S) bool: ``ancestor[a, b]`` is True if a is b or an ancestor of b."""
        S = len(self.segments)
        anc = np.eye(S, dtype=bool)
        for b in range(S):
            a = self.parent_index[b]
            while a >= 0:
                anc[a, b] = True
                a = self.parent_index[a]
        return anc

    @cached_property
    def dof_moves_marker(self) -> np.ndarray:
        """(Q, M) bool: pose coordinate k moves marker m."""
        seg = np.array([d.segment for d in self.dofs], dtype=int)
        return self.ancestor[seg][:, self.marker_segment]

    @cached_property
    def nominal_geometry(self) -> np.ndarray:
        """(G,) float: joint positions then marker positions, as written in the model."""
        return np.concatenate(
            [np.ravel([s.joint.position for s in self.segments]),
             np.ravel([m.position for m in self.markers]),
             np.ones(len(self.coupled_translations))]
        ).astype(float)

    @cached_property
    def geometry_map(self) -> tuple[np.ndarray, np.ndarray]:
        """``(g_base (G,), A (G, P))`` with ``g = g_base + theta @ A.T``.

        Columns of ``axis_direction`` parameters are zero: they act on the
        joint axes, not on the geometry vector (see :attr:`axis_tilts`).
        """
        D, S = self.dim, len(self.segments)
        g = self.nominal_geometry.copy()
        A = np.zeros((g.size, self.n_params))
        setting = np.zeros((g.size, self.n_params), dtype=bool)
        jidx = {s.joint.name: i for i, s in enumerate(self.segments)}
        midx = {m.name: i for i, m in enumerate(self.markers)}
        sidx = self.segment_index
        for k, p in enumerate(self.parameters):
            if p.kind == "length":
                sl = slice(jidx[p.target] * D, jidx[p.target] * D + D)
                u = g[sl] / np.linalg.norm(self.nominal_geometry[sl])
                g[sl] = 0.0
                A[sl, k] = u
                setting[sl, k] = u != 0
            elif p.kind in ("joint_position", "marker_position"):
                base = jidx[p.target] * D if p.kind == "joint_position" else (S + midx[p.target]) * D
                g[base + p.axis] = 0.0
                A[base + p.axis, k] = 1.0
                setting[base + p.axis, k] = True
            elif p.kind == "marker_offset":
                A[(S + midx[p.target]) * D + p.axis, k] += 1.0
            elif p.kind == "scale":
                s = sidx[p.target]
                rows = [(S + m) * D for m in np.flatnonzero(self.marker_segment == s)]
                rows += [c * D for c in np.flatnonzero(self.parent_index == s)]
                for r in rows:
                    for a in range(D) if p.axis is None else (p.axis,):
                        A[r + a, k] += self.nominal_geometry[r + a]
                        g[r + a] = 0.0
                        setting[r + a, k] = True
            elif p.kind == "joint_centre":
                s = jidx[p.target]
                A[s * D + p.axis, k] += 1.0
                for m in np.flatnonzero(self.marker_segment == s):
                    A[(S + m) * D + p.axis, k] -= 1.0
                for c in np.flatnonzero(self.parent_index == s):
                    A[c * D + p.axis, k] -= 1.0
        n0 = (S + len(self.markers)) * D
        for n, (_s, _m, b, base) in enumerate(self.coupled_translations):
            g[n0 + n] = base
            A[n0 + n] = b
        if np.any(setting.sum(axis=1) > 1):
            raise ModelError(
                f"model {self.name!r}: two parameters set the same coordinate",
                "give each geometric quantity at most one length/joint_position/marker_position/scale "
                "parameter",
            )
        return g, A

    @cached_property
    def axis_tilts(self) -> tuple[tuple[int, int, int, tuple, tuple, tuple], ...]:
        """Hinge axes with ``axis_direction`` parameters.

        One entry per such hinge: ``(dof index, parameter index of tilt u or -1,
        parameter index of tilt v or -1, e, u, v)`` with the unit vectors of the
        nominal axis and the two tilt directions (see the module docstring).
        """
        out = []
        dof_of = {self.segments[d.segment].joint.name: k for k, d in enumerate(self.dofs)
                  if d.kind == "R"}
        by_joint: dict[str, list[int]] = {}
        for k, p in enumerate(self.parameters):
            if p.kind == "axis_direction":
                by_joint.setdefault(p.target, [-1, -1])[p.axis] = k
        for joint, (ku, kv) in by_joint.items():
            k = dof_of[joint]
            e, u, v = tilt_basis(self.dofs[k].axis)
            out.append((k, ku, kv, e, u, v))
        return tuple(out)

    @cached_property
    def derived_lengths(self) -> tuple[tuple[str, int], ...]:
        """Distances between joint centres that depend on the parameters.

        ``(name, segment index)``: the distance from the segment's parent's
        origin to the segment's joint centre at the zero pose, named
        ``"<parent joint>-<joint>"``: ``|o_s(theta)|``, or, for a ``custom``
        joint whose centre slides with a coordinate by a translation that scales
        with the parent (an OpenSim knee), where that translation puts it at the
        zero pose. A joint whose only parameter is its own ``length`` is left
        out (that parameter is the distance).
        """
        D = self.dim
        _, A = self.geometry_map
        sliding = self.sliding_joint_parameters
        out = []
        for s, seg in enumerate(self.segments):
            if seg.parent is None:
                continue
            cols = np.flatnonzero(np.abs(A[s * D:(s + 1) * D]).sum(axis=0))
            if s in sliding:
                out.append((f"{self.segments[self.parent_index[s]].joint.name}-{seg.joint.name}", s))
                continue
            if cols.size == 0:
                continue
            if cols.size == 1 and self.parameters[cols[0]].kind == "length":
                continue
            parent_joint = self.segments[self.parent_index[s]].joint.name
            out.append((f"{parent_joint}-{seg.joint.name}", s))
        return tuple(out)

    @cached_property
    def sliding_joint_parameters(self) -> dict[int, np.ndarray]:
        """Segments whose joint centre slides with a coordinate by a translation that scales with a
        parameter: ``{segment index: the parameters (indices) that can move that centre at the zero pose}``
        (those of its offset from the parent, its translations' factors and any parameter of the joint)."""
        D = self.dim
        _, A = self.geometry_map
        out: dict[int, set] = {}
        for s, _m, b, _base in self.coupled_translations:
            if np.any(b):
                out.setdefault(s, set()).update(np.flatnonzero(b).tolist())
        for s, cols in out.items():
            name = self.segments[s].joint.name
            cols.update(np.flatnonzero(np.abs(A[s * D:(s + 1) * D]).sum(axis=0)).tolist())
            cols.update(k for k, p in enumerate(self.parameters) if p.target == name)
        return {s: np.array(sorted(c), dtype=int) for s, c in out.items()}

    @property
    def theta_nominal(self) -> np.ndarray:
        """(P,) float: the parameters' values implied by the model's nominal geometry.

        Zero for ``joint_centre`` shifts, ``marker_offset`` shifts and
        ``axis_direction`` tilts; one for ``scale`` factors.
        """
        g0 = self.nominal_geometry
        _, A = self.geometry_map
        out = np.zeros(self.n_params)
        for k, p in enumerate(self.parameters):
            col = A[:, k]
            if p.kind in ("scale", "translation_gain"):
                out[k] = 1.0
            elif p.kind == "length":
                out[k] = g0[col != 0] @ col[col != 0]
            elif p.kind in ("joint_position", "marker_position"):
                out[k] = g0[col != 0][0]
        return out

    @property
    def theta_center(self) -> np.ndarray:
        """(P,) float: centre of each parameter's prior."""
        return np.array([p.prior.center for p in self.parameters])

    def log_prior(self, theta) -> np.ndarray:
        """Log prior density of ``theta (..., P)`` -> ``(...)`` (independent parameters)."""
        theta = np.asarray(theta, dtype=float)
        out = np.zeros(theta.shape[:-1])
        for k, p in enumerate(self.parameters):
            out = out + p.prior.log_pdf(theta[..., k])
        return out

    # ---------------------------------------------------------------- export
    def to_dict(self) -> dict:
        """A dict that :func:`model_from_dict` turns back into an equal model."""
        head = {"name": self.name, "dim": self.dim, "units": self.units}
        if self.description:
            head["description"] = self.description
        return {"model": head,
                "segments": [{"name": s.name, "parent": s.parent or "ground", "joint": _joint_dict(s.joint)}
                             for s in self.segments],
                "markers": [{"name": m.name, "segment": m.segment, "position": list(m.position)}
                            | ({"label": m.label} if m.label else {}) for m in self.markers],
                "parameters": [_parameter_dict(p) for p in self.parameters]}

    def with_parameters(self, names) -> Model:
        """A copy of the model that keeps only the parameters ``names`` unknown."""
        keep = tuple(self.parameter(n) for n in names)
        return Model(self.name, self.dim, self.units, self.segments, self.markers, keep,
                     self.description)


# ----------------------------------------------------------------------------- export
def _joint_dict(j: Joint) -> dict:
    """A joint as its model-file table."""
    out = {"name": j.name, "type": j.type, "position": list(j.position)}
    if j.type == "hinge":
        out["axis"] = list(j.axes[0])
    elif j.type == "universal":
        out["axes"] = [list(a) for a in j.axes]
    elif j.type == "custom":
        out["coordinates"] = list(j.coordinates)
        out["motions"] = [_motion_dict(m, j.coordinates) for m in j.motions]
        if j.orientation:
            out["orientation"] = [list(j.orientation[r * 3:r * 3 + 3]) for r in range(3)]
    if j.range:
        out["range"] = [list(r) for r in j.range]
    return out


def _motion_dict(m: Motion, coordinates: tuple[str, ...]) -> dict:
    return ({"kind": MOTION_KINDS[m.kind], "axis": list(m.axis)}
            | ({"coordinate": coordinates[m.coordinate]} if m.coordinate >= 0 else {})
            | {"function": m.function.to_dict()}
            | ({"scale_weights": list(m.scale_weights)} if m.scale_weights else {})
            | ({"vector": list(m.vector)} if m.vector else {}))


def _parameter_dict(p: Parameter) -> dict:
    """A scalar parameter as its model-file table."""
    e = {"name": p.name, "kind": p.kind, PARAMETER_TARGET.get(p.kind, "joint"): p.target}
    if p.kind == "translation_gain":
        e["motion"] = p.axis
    elif p.axis is not None:
        e["axis"] = ("uv" if p.kind == "axis_direction" else "xyz")[p.axis]
    e["prior"] = p.prior.to_dict()
    e["grid_step"] = p.grid_step
    return e


# ----------------------------------------------------------------------------- model checks
# Each checker takes the model and raises ModelError naming what is wrong and the fix (the manner of
# pinocchio's check-model: one small named check per rule, run in order by Model.__post_init__).
def _check_header(model: Model) -> None:
    """dim is 2 or 3, units known, at least one segment."""
    if model.dim not in (2, 3):
        raise ModelError(f"model {model.name!r}: dim must be 2 or 3, got {model.dim}")
    if model.units not in UNITS:
        raise ModelError(f"model {model.name!r}: unknown units {model.units!r}", f"use one of {UNITS}")
    if not model.segments:
        raise ModelError(f"model {model.name!r} has no segments", "add a [[segments]] table")


def _check_unique_names(model: Model) -> None:
    """No segment name and no joint name is used twice."""
    for what, names in (("segment", [s.name for s in model.segments]),
                        ("joint", [s.joint.name for s in model.segments])):
        for n in names:
            if names.count(n) > 1:
                raise ModelError(f"{what} name {n!r} is used twice", f"give each {what} a unique name")


def _check_one_root(model: Model) -> None:
    roots = [s for s in model.segments if s.parent is None]
    if len(roots) != 1:
        raise ModelError(f"model {model.name!r} has {len(roots)} root segments (parent = 'ground')",
                         "exactly one segment must hang from the ground")


def _check_segments(model: Model) -> None:
    """Every segment's parent exists and its joint fits the model (type, position)."""
    seg_names = [s.name for s in model.segments]
    for s in model.segments:
        if s.parent is not None and s.parent not in seg_names:
            raise ModelError(f"segment {s.name!r} has parent {s.parent!r}, which is not a segment",
                             f"use one of: ground, {', '.join(seg_names)}")
        _check_joint(model, s)


def _check_joint(model: Model, s: Segment) -> None:
    j = s.joint
    if j.type not in JOINT_TYPES[model.dim]:
        raise ModelError(f"joint {j.name!r} has unknown type {j.type!r} for a {model.dim}-D model",
                         f"use one of: {', '.join(JOINT_TYPES[model.dim])}")
    if j.type == "free" and s.parent is not None:
        raise ModelError(f"joint {j.name!r}: only the root segment may have a free joint",
                         "use revolute (2-D) or hinge/universal/spherical (3-D)")
    if j.type == "custom":
        _check_custom(j)
    if len(j.position) != model.dim:
        raise ModelError(f"joint {j.name!r}: position needs {model.dim} coordinates, got {len(j.position)}")


def _parents_first(segments: tuple[Segment, ...]) -> tuple[Segment, ...]:
    """The segments ordered parents first (a cycle is refused)."""
    ordered, placed = [], set()
    pending = list(segments)
    while pending:
        ready = [s for s in pending if s.parent is None or s.parent in placed]
        if not ready:
            raise ModelError(f"segments {', '.join(s.name for s in pending)} form a cycle",
                             "the segments must form a tree")
        for s in ready:
            ordered.append(s)
            placed.add(s.name)
            pending.remove(s)
    return tuple(ordered)


def _check_markers(model: Model) -> None:
    """Marker names unique, each on a segment of the model with a position of the model's dim; at least one."""
    seg_names = [s.name for s in model.segments]
    mnames = [m.name for m in model.markers]
    for m in model.markers:
        if mnames.count(m.name) > 1:
            raise ModelError(f"marker name {m.name!r} is used twice")
        if m.segment not in seg_names:
            raise ModelError(f"marker {m.name!r} is on segment {m.segment!r}, which is not in the model",
                             f"use one of: {', '.join(seg_names)}")
        if len(m.position) != model.dim:
            raise ModelError(f"marker {m.name!r}: position needs {model.dim} coordinates, got {len(m.position)}")
    if not model.markers:
        raise ModelError(f"model {model.name!r} has no markers", "add [[markers]] tables")


def _check_parameters(model: Model) -> None:
    """Each parameter: a unique name, an existing target, and the rules of its kind."""
    pnames = [p.name for p in model.parameters]
    for p in model.parameters:
        if pnames.count(p.name) > 1:
            raise ModelError(f"parameter name {p.name!r} is used twice")
        _check_target(model, p)
        if p.kind in ("joint_position", "marker_position", "joint_centre", "scale", "marker_offset") \
                and p.axis is not None and p.axis >= model.dim:
            raise ModelError(f"parameter {p.name!r}: axis 'z' does not exist in a 2-D model")
        kind_check = PARAMETER_CHECKS.get(p.kind)
        if kind_check is not None:
            kind_check(model, p, next((s for s in model.segments if s.joint.name == p.target), None))


def _check_target(model: Model, p: Parameter) -> None:
    on_marker = p.kind in ("marker_position", "marker_offset")
    targets = [m.name for m in model.markers] if on_marker else [s.name for s in model.segments] \
        if p.kind == "scale" else [s.joint.name for s in model.segments]
    if p.target not in targets:
        what = "marker" if on_marker else "segment" if p.kind == "scale" else "joint"
        raise ModelError(f"parameter {p.name!r} refers to {what} {p.target!r}, which is not in the model",
                         f"use one of: {', '.join(targets)}")


def _check_length(model: Model, p: Parameter, seg: Segment) -> None:
    if np.linalg.norm(seg.joint.position) == 0:
        raise ModelError(f"parameter {p.name!r}: joint {p.target!r} sits at its parent's origin, "
                         "so its length has no direction", "give the joint a nominal position along the segment")


def _check_joint_centre(model: Model, p: Parameter, seg: Segment) -> None:
    if seg.parent is None:
        raise ModelError(f"parameter {p.name!r}: joint {p.target!r} attaches the root to the ground, "
                         "so no relative motion defines its centre",
                         "put joint_centre parameters on joints between two segments")
    children = {c.joint.name for c in model.segments if c.parent == seg.name}
    clash = [q.name for q in model.parameters
             if q.kind == "length" and (q.target == p.target or q.target in children)]
    if clash:
        raise ModelError(f"parameter {p.name!r}: the joint centre {p.target!r} is an end of length "
                         f"parameter {clash[0]!r}, whose meaning would then be unclear",
                         "drop the length parameter: the distance between joint centres is "
                         "reported as a derived length")


def _check_axis_direction(model: Model, p: Parameter, seg: Segment) -> None:
    if seg.joint.type != "hinge":
        raise ModelError(f"parameter {p.name!r}: axis_direction needs a hinge joint, "
                         f"{p.target!r} is {seg.joint.type}", "point it at a hinge joint")


def _check_one_per_slot(model: Model) -> None:
    """At most one translation_gain per translation and one axis_direction per tilt of a joint."""
    gains = [(p.target, p.axis) for p in model.parameters if p.kind == "translation_gain"]
    for g in gains:
        if gains.count(g) > 1:
            raise ModelError(f"joint {g[0]!r} has two translation_gain parameters for motion {g[1]}",
                             "give each translation at most one gain")
    tilts = [(p.target, p.axis) for p in model.parameters if p.kind == "axis_direction"]
    for t in tilts:
        if tilts.count(t) > 1:
            raise ModelError(f"joint {t[0]!r} has two axis_direction parameters for tilt "
                             f"{'uv'[t[1]]!r}", "give each tilt at most one parameter")


#: checks of the tree, before the segments are ordered parents first
TREE_CHECKS = (_check_header, _check_unique_names, _check_one_root, _check_segments)
#: checks of what hangs on the tree
CONTENT_CHECKS = (_check_markers, _check_parameters, _check_one_per_slot)
#: the rules of one parameter kind: (model, parameter, the segment of its target joint or None)
PARAMETER_CHECKS = {
    "length": _check_length,
    "joint_centre": _check_joint_centre,
    "axis_direction": _check_axis_direction,
    "translation_gain": lambda model, p, seg: _check_gain(p, seg.joint),
}


# ----------------------------------------------------------------------------- custom joints
def _scales_with_parent(m: Motion) -> bool:
    """A translation by a function of a coordinate, or a carried one, unless its scale weights are all zero."""
    if m.kind == "R" or (m.kind == "T" and (m.function.is_identity or m.function.is_constant)):
        return False
    return not (m.scale_weights and not any(m.scale_weights))


def _check_custom(j: Joint) -> None:
    """A custom joint's motions and coordinates agree; no motion at all is a rigid attachment (a weld)."""
    for m in j.motions:
        if m.kind not in ("R", "T", "C") or len(m.axis) != 3:
            raise ModelError(f"joint {j.name!r}: a motion needs kind rotation/translation/carried and a 3-D axis")
        if (m.kind == "C") != (len(m.vector) == 3):
            raise ModelError(f"joint {j.name!r}: a carried translation, and only one, needs a 3-D vector",
                             "give a carried motion vector = [x, y, z] and no other motion a vector")
        if m.kind == "C" and (m.coordinate >= 0 or not m.function.is_constant):
            raise ModelError(f"joint {j.name!r}: a carried translation follows the joint's rotations, not a "
                             "coordinate", "give it no coordinate and a constant function")
        if not -1 <= m.coordinate < len(j.coordinates):
            raise ModelError(f"joint {j.name!r}: a motion refers to coordinate {m.coordinate}, "
                             f"the joint has {len(j.coordinates)}")
        if m.coordinate < 0 and not m.function.is_constant:
            raise ModelError(f"joint {j.name!r}: a motion without a coordinate must have a constant function")
    used = {m.coordinate for m in j.motions}
    for c, name in enumerate(j.coordinates):
        if c not in used:
            raise ModelError(f"joint {j.name!r}: coordinate {name!r} drives no motion",
                             "remove it or give a motion its name")
    if j.orientation and len(j.orientation) != 9:
        raise ModelError(f"joint {j.name!r}: orientation must be a 3 x 3 rotation matrix")


def _custom_dofs(i: int, j: Joint) -> list[Dof]:
    """One pose coordinate per coordinate of a custom joint, in the joint's order."""
    out = []
    carried = any(m.kind == "C" for m in j.motions)  # the rotations also move the joint centre
    for c in range(len(j.coordinates)):
        ms = [m for m in j.motions if m.coordinate == c]
        plain = len(ms) == 1 and ms[0].function.is_identity and not (carried and ms[0].kind == "R")
        rot = [m for m in ms if m.kind == "R"]
        if plain:
            out.append(Dof(i, ms[0].kind, ms[0].axis))
        else:
            out.append(Dof(i, "R", (rot or ms)[0].axis, coupled=True))
    return out


def _custom_from_dict(j: dict, where: str):
    coords = j.get("coordinates", [])
    if not isinstance(coords, list) or not all(isinstance(c, str) for c in coords):
        raise ModelError(f"{where}: a custom joint needs coordinates = ['name', ...]")
    motions = []
    for n, m in enumerate(j.get("motions", [])):
        mw = f"{where} motion {n + 1}"
        if not isinstance(m, dict) or m.get("kind") not in MOTION_KIND_OF:
            raise ModelError(f"{mw}: needs kind = 'rotation', 'translation' or 'carried'")
        c = m.get("coordinate", "")
        if c and c not in coords:
            raise ModelError(f"{mw}: coordinate {c!r} is not one of the joint's coordinates {coords}")
        sw, vec = m.get("scale_weights", ()), m.get("vector", ())
        motions.append(Motion(MOTION_KIND_OF[m["kind"]], _unit(m.get("axis"), f"{mw} axis"),
                              coords.index(c) if c else -1,
                              CoordinateFunction.from_dict(m.get("function"), f"{mw} function"),
                              _num_list(sw, 3, f"{mw} scale_weights") if sw else (),
                              _num_list(vec, 3, f"{mw} vector") if vec else ()))
    orient = ()
    if "orientation" in j:
        R = np.asarray(j["orientation"], dtype=float)
        if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-9) or np.linalg.det(R) < 0:
            raise ModelError(f"{where}: orientation must be a 3 x 3 rotation matrix")
        orient = tuple(float(v) for v in R.ravel())
    return tuple(motions), tuple(str(c) for c in coords), orient


# ----------------------------------------------------------------------------- loading
def _num_list(v, n: int | None, where: str) -> tuple[float, ...]:
    try:
        out = tuple(float(x) for x in v)
    except (TypeError, ValueError):
        raise ModelError(f"{where}: expected a list of numbers, got {v!r}") from None
    if n is not None and len(out) != n:
        raise ModelError(f"{where}: expected {n} numbers, got {len(out)}")
    if not all(math.isfinite(x) for x in out):
        raise ModelError(f"{where}: numbers must be finite, got {v!r}")
    return out


def _prior(d, where: str, nominal: float = math.nan) -> Prior:
    if not isinstance(d, dict):
        raise ModelError(f"{where}: prior must be a table like {{type = 'uniform', lower = .., upper = ..}}")
    kind = d.get("type", "uniform")
    if kind not in PRIOR_KINDS:
        raise ModelError(f"{where}: unknown prior type {kind!r}", f"use one of: {', '.join(PRIOR_KINDS)}")
    try:
        if kind == "uniform":
            lo, hi = float(d["lower"]), float(d["upper"])
            mean = sd = math.nan
        elif kind == "normal":
            mean, sd = float(d.get("mean", nominal)), float(d["sd"])
            if not math.isfinite(mean):
                raise KeyError("mean")
            lo, hi = float(d.get("lower", mean - 5 * sd)), float(d.get("upper", mean + 5 * sd))
        else:
            mean, sd = float(d.get("median", nominal)), float(d["sd_log"])
            if not math.isfinite(mean):
                raise KeyError("median")
            lo = float(d.get("lower", mean * math.exp(-5 * sd)))
            hi = float(d.get("upper", mean * math.exp(5 * sd)))
    except KeyError as exc:
        raise ModelError(f"{where}: a {kind} prior needs {exc.args[0]!r}") from None
    except (TypeError, ValueError):
        raise ModelError(f"{where}: prior values must be numbers, got {d!r}") from None
    if kind != "uniform" and not sd > 0:
        raise ModelError(f"{where}: prior sd must be positive, got {sd}")
    if kind == "lognormal" and not mean > 0:
        raise ModelError(f"{where}: a log-normal prior needs a positive median, got {mean}")
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ModelError(f"{where}: prior bounds must satisfy lower < upper, got [{lo}, {hi}]")
    return Prior(kind, lo, hi, mean, sd)


def _check_gain(p: Parameter, j: Joint) -> None:
    """A ``translation_gain`` must point at a translation of a custom joint by a non-trivial function."""
    if j.type != "custom":
        raise ModelError(f"parameter {p.name!r}: translation_gain needs a custom joint, {j.name!r} is {j.type}",
                         "point it at a custom joint")
    if p.axis is None or p.axis >= len(j.motions):
        raise ModelError(f"parameter {p.name!r}: joint {j.name!r} has no motion {p.axis}",
                         f"use motion = 0 .. {len(j.motions) - 1}")
    m = j.motions[p.axis]
    if m.kind != "T" or m.function.is_identity or m.function.is_constant:
        raise ModelError(f"parameter {p.name!r}: motion {p.axis} of joint {j.name!r} is not a translation by a "
                         "function of a coordinate", "point it at such a translation")


def _nominal(kind: str, target: str, axis, segments, markers) -> float:
    """Nominal value of a scalar parameter from the parsed geometry (NaN if the target is unknown)."""
    if kind in ("joint_centre", "axis_direction", "marker_offset"):
        return 0.0
    if kind in ("scale", "translation_gain"):
        return 1.0
    if kind == "marker_position":
        pos = next((m.position for m in markers if m.name == target), None)
    else:
        pos = next((s.joint.position for s in segments if s.joint.name == target), None)
    if pos is None:
        return math.nan
    if kind == "length":
        return float(np.linalg.norm(pos))
    return float(pos[axis]) if axis < len(pos) else math.nan


def _parameters(p, i: int, source: str, segments, markers) -> list[Parameter]:
    """One ``[[parameters]]`` table -> its scalar parameters (several with ``axes = [...]``)."""
    if not isinstance(p, dict):
        raise ModelError(f"{source}: parameter number {i + 1} must be a table")
    name = str(p.get("name", f"p{i}"))
    where = f"{source}: parameter {name!r}"
    kind = p.get("kind")
    if kind not in PARAMETER_KINDS:
        raise ModelError(f"{where}: unknown kind {kind!r}", f"use one of: {', '.join(PARAMETER_KINDS)}")
    target_key = PARAMETER_TARGET.get(kind, "joint")
    target = p.get(target_key)
    if target is None:
        raise ModelError(f"{where}: needs {target_key} = '...'")
    comps = _parameter_components(p, kind, name, where)
    priors = _parameter_priors(p, len(comps), where)
    return [_scalar_parameter(f"{source}: parameter {pname!r}", pname, kind, str(target), axis, prior_d,
                              p.get("grid_step"), segments, markers)
            for (pname, axis), prior_d in zip(comps, priors, strict=True)]


def _parameter_components(p: dict, kind: str, name: str, where: str) -> list[tuple[str, int | None]]:
    """``(name, axis)`` of each scalar a parameter table declares."""
    if kind == "translation_gain":
        motion = p.get("motion")
        if isinstance(motion, bool) or not isinstance(motion, int) or motion < 0:
            raise ModelError(f"{where}: needs motion = N, the index (from 0) of a translation in the joint's "
                             f"motions, got {motion!r}")
        return [(name, motion)]
    if kind == "length" or (kind == "scale" and "axis" not in p and "axes" not in p):
        if "axis" in p or "axes" in p:
            raise ModelError(f"{where}: a length has no axis", "remove axis/axes")
        return [(name, None)]
    return _axis_components(p, kind, name, where)


def _axis_components(p: dict, kind: str, name: str, where: str) -> list[tuple[str, int]]:
    """The scalars of ``axis = ...`` (one) or ``axes = [...]`` (one per axis, named ``<name>_<axis>``)."""
    names = AXES if kind != "axis_direction" else TILT_AXES
    hint = "'x', 'y' or 'z'" if kind != "axis_direction" else "'u' or 'v'"
    if "axes" in p:
        if "axis" in p:
            raise ModelError(f"{where}: give either axis or axes, not both")
        axes = p["axes"]
        if not isinstance(axes, list) or not axes or any(a not in names for a in axes) \
                or len(set(axes)) != len(axes):
            raise ModelError(f"{where}: axes must be a list of distinct {hint}, got {axes!r}")
        return [(f"{name}_{a}", names[a]) for a in axes]
    ax = p.get("axis")
    if ax not in names:
        raise ModelError(f"{where}: needs axis = {hint} (or axes = [...] for several)")
    return [(name, names[ax])]


def _parameter_priors(p: dict, n: int, where: str) -> list:
    """One prior table per scalar: the table's list of them, or its one table repeated."""
    priors = p.get("prior", {})
    if not isinstance(priors, list):
        return [priors] * n
    if len(priors) != n:
        raise ModelError(f"{where}: {len(priors)} priors for {n} axes", "give one prior table, or one per axis")
    return priors


def _scalar_parameter(where: str, name: str, kind: str, target: str, axis, prior_d, step, segments,
                      markers) -> Parameter:
    """One scalar parameter: its prior (centred on the nominal value where implicit) and grid step."""
    prior = _prior(prior_d, where, _nominal(kind, target, axis, segments, markers))
    step = step if step is not None else (prior.upper - prior.lower) / 200
    try:
        step = float(step)
    except (TypeError, ValueError):
        raise ModelError(f"{where}: grid_step must be a number") from None
    if not step > 0:
        raise ModelError(f"{where}: grid_step must be positive, got {step}")
    return Parameter(name, kind, target, axis, prior, step)


def model_from_dict(d: dict, source: str = "model") -> Model:
    """Build a :class:`Model` from the parsed TOML structure (see docs/model-format.md)."""
    validate(d, source)  # keys, types and ranges, with key paths; what follows builds the model
    head = d.get("model", {})
    try:
        dim = int(head.get("dim", 3))
    except (TypeError, ValueError):
        raise ModelError(f"{source}: [model] dim must be 2 or 3") from None
    segments = [_segment_from_dict(s, i, dim, source) for i, s in enumerate(d.get("segments", []))]
    aliases = d.get("aliases", {}) or {}
    markers = [_marker_from_dict(m, i, dim, source, aliases) for i, m in enumerate(d.get("markers", []))]
    params = [q for i, p in enumerate(d.get("parameters", [])) for q in _parameters(p, i, source, segments, markers)]
    model = Model(str(head.get("name", Path(source).stem)), dim, str(head.get("units", "mm")), tuple(segments),
                  tuple(markers), tuple(params), str(head.get("description", "")))
    check_built(model, d, source)
    return model


def _segment_from_dict(s: dict, i: int, dim: int, source: str) -> Segment:
    """One ``[[segments]]`` table -> its segment and joint."""
    where = f"{source}: segment {s.get('name', i + 1)!r}"
    if "name" not in s:
        raise ModelError(f"{source}: segment number {i + 1} has no name")
    j = s.get("joint", {})
    if not isinstance(j, dict) or "type" not in j:
        raise ModelError(f"{where}: needs a joint table with a type",
                         "write joint = {type = 'revolute', position = [...]}")
    jtype = str(j["type"])
    if jtype not in JOINT_TYPES.get(dim, ()):
        raise ModelError(f"{where}: unknown joint type {jtype!r} for a {dim}-D model",
                         f"use one of: {', '.join(JOINT_TYPES.get(dim, ()))}")
    pos = _num_list(j.get("position", [0.0] * dim), dim, f"{where} joint position")
    rng = j.get("range", ())
    if rng and not isinstance(rng[0], list):
        rng = [rng]
    rng = tuple(_num_list(r, 2, f"{where} joint range") for r in rng)
    motions, coords, orient = _custom_from_dict(j, where) if jtype == "custom" else ((), (), ())
    parent = s.get("parent", "ground")
    return Segment(str(s["name"]), None if parent in (None, "ground") else str(parent),
                   Joint(str(j.get("name", s["name"])), jtype, pos, _joint_axes(j, jtype, where), rng, motions,
                         coords, orient))


def _joint_axes(j: dict, jtype: str, where: str) -> tuple:
    """A hinge's axis or a universal joint's two axes (unit vectors); none for the other types."""
    if jtype == "hinge":
        return (_unit(j.get("axis", (0, 0, 1)), f"{where} joint axis"),)
    if jtype == "universal":
        ax = j.get("axes")
        if not isinstance(ax, list) or len(ax) != 2:
            raise ModelError(f"{where}: a universal joint needs axes = [[..], [..]]")
        return tuple(_unit(a, f"{where} joint axes") for a in ax)
    return ()


def _marker_from_dict(m: dict, i: int, dim: int, source: str, aliases: dict) -> Marker:
    if "name" not in m or "segment" not in m:
        raise ModelError(f"{source}: marker number {i + 1} needs a name and a segment")
    pos = _num_list(m.get("position", [0.0] * dim), dim, f"{source}: marker {m['name']!r} position")
    return Marker(str(m["name"]), str(m["segment"]), pos, m.get("label", aliases.get(m["name"])))


def load_model(path) -> Model:
    """Read a model description from a TOML file.

    Raises
    ------
    ModelError
        With the file name, the problem and the fix, for any invalid content.
    """
    from skelid.io._common import check_regular_file

    path = check_regular_file(path, "model file", ModelError)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ModelError(f"model file {path} does not exist", "check the path") from None
    except UnicodeDecodeError:
        raise ModelError(f"model file {path} is not text",
                         "a model file is a UTF-8 TOML text file; see docs/model-format.md") from None
    except OSError as exc:
        raise ModelError(f"cannot read model file {path}: {exc.strerror or exc}",
                         "check the path and the file's permissions") from None
    try:
        d = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ModelError(f"{path}: not valid TOML ({exc})", "see docs/model-format.md") from None
    try:
        return model_from_dict(d, str(path))
    except ModelError:
        raise
    except (TypeError, ValueError, AttributeError, KeyError) as exc:
        raise ModelError(f"{path}: malformed model description ({exc})",
                         "see docs/model-format.md") from None
