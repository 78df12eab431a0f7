"""The schema of the model file: every key, its type and its range, checked before a model is built.

A model file (docs/model-format.md) is parsed by ``tomllib`` into nested
tables; :func:`validate` walks that structure against :data:`SCHEMA` and
stops at the first problem with one line naming the key path
(``segments[2].joint.range``), what is wrong and the fix. The rules:

* every key is known: an unknown key (``postion``, ``unit``) is an error with
  the nearest known key as a suggestion (:func:`difflib.get_close_matches`);
* types are strict: an integer is an integer (``dim = 2.9`` and
  ``dim = true`` are refused), a number is an int or a float but never a bool
  or a string, a name is a string;
* numbers are finite and of a sane magnitude in the model's units (at most
  :data:`MAX_EXTENT_M` metres), ranges and prior bounds satisfy
  ``lower < upper``, a prior's spread is positive, and a prior interval is at
  most :data:`MAX_PRIOR_SCALE` times the size of the model.

Which keys a table takes can depend on one of its values (a joint's ``type``,
a parameter's ``kind``, a prior's ``type``). Adding a joint type or a
parameter kind is one line: its name in
:data:`skelid.model.kinds.JOINT_TYPES` or ``PARAMETER_KINDS``, and, if it
takes keys of its own, one entry in :data:`JOINT_KEYS` here or
:data:`skelid.model.kinds.PARAMETER_TARGET`. The key reference in docs/model-format.md is
generated from this schema by :func:`reference_markdown` (a test keeps the two
equal).

Examples
--------
>>> validate({"model": {"dim": 2.9}}, "arm.toml")
Traceback (most recent call last):
...
skelid.errors.ModelError: arm.toml: model.dim: must be an integer, got 2.9 (a float) (fix: write 2 or 3)
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from skelid.errors import ModelError
from skelid.model.kinds import JOINT_TYPES, MOTION_KINDS, PARAMETER_KINDS, PARAMETER_TARGET

#: largest coordinate or prior bound accepted, in metres (a motion-capture volume is far smaller)
MAX_EXTENT_M = 1000.0
#: a prior bound may be at most this many times the largest nominal coordinate of the model
MAX_PRIOR_SCALE = 1000.0
#: a joint range is in degrees, within +-this
MAX_ANGLE_DEG = 360.0
#: the marks around the generated key reference in docs/model-format.md
REFERENCE_BEGIN, REFERENCE_END = "<!-- schema-reference: begin -->", "<!-- schema-reference: end -->"
UNIT_IN_M = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}


# ----------------------------------------------------------------------------- context
@dataclass
class Context:
    """What checks of one value need to know about the whole file."""

    source: str
    dim: int = 3
    units: str = "mm"

    @property
    def max_extent(self) -> float:
        return MAX_EXTENT_M / UNIT_IN_M.get(self.units, 1e-3)

    def fail(self, path: str, problem: str, fix: str | None = None):
        where = f"{path}: " if path else ""
        raise ModelError(f"{self.source}: {where}{problem}", fix)


def _show(v) -> str:
    s = repr(v)
    return s if len(s) <= 60 else s[:57] + "..."


def _type_of(v) -> str:
    return {bool: "a boolean", int: "an integer", float: "a float", str: "a string", list: "a list",
            dict: "a table"}.get(type(v), type(v).__name__)


def is_number(v) -> bool:
    """An int or float (numpy scalars included), never a bool."""
    import numpy as np

    return isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool | np.bool_)


# ----------------------------------------------------------------------------- nodes
class Node:
    """One value of the schema. ``check`` raises :class:`ModelError` naming ``path``."""

    type_name = "value"

    def check(self, v, path: str, ctx: Context) -> None:  # pragma: no cover - abstract
        raise NotImplementedError


@dataclass
class Str(Node):
    choices: Callable[[Context], tuple[str, ...]] | tuple[str, ...] | None = None
    type_name: str = "string"

    def options(self, ctx):
        return self.choices(ctx) if callable(self.choices) else self.choices

    def check(self, v, path, ctx):
        opts = self.options(ctx)
        if not isinstance(v, str):
            hint = f"write one of {', '.join(map(repr, opts))}" if opts else f'write it in quotes: "{v}"'
            ctx.fail(path, f"must be a string, got {_show(v)} ({_type_of(v)})", hint)
        if not v.strip():
            ctx.fail(path, "must not be empty", "give a non-empty string")
        if opts and v not in opts:
            near = difflib.get_close_matches(v, opts, n=1)
            hint = f"did you mean {near[0]!r}? " if near else ""
            ctx.fail(path, f"unknown value {v!r}", f"{hint}use one of: {', '.join(opts)}")


@dataclass
class Int(Node):
    choices: tuple[int, ...] = ()
    type_name: str = "integer"

    def check(self, v, path, ctx):
        ok = " or ".join(map(str, self.choices))
        if isinstance(v, bool) or not isinstance(v, int):
            ctx.fail(path, f"must be an integer, got {_show(v)} ({_type_of(v)})", f"write {ok}")
        if self.choices and v not in self.choices:
            ctx.fail(path, f"must be {ok}, got {v}", f"write {ok}")


@dataclass
class Num(Node):
    """A finite number; ``positive`` for spreads and steps; ``length`` for the model's length unit."""

    positive: bool = False
    length: bool = True
    limit: float | None = None
    type_name: str = "number"

    def check(self, v, path, ctx):
        if not is_number(v):
            ctx.fail(path, f"must be a number, got {_show(v)} ({_type_of(v)})", "write a plain number like 12.5")
        if not math.isfinite(v):
            ctx.fail(path, f"must be finite, got {v}", "write a finite number")
        if self.positive and not v > 0:
            ctx.fail(path, f"must be positive, got {v}", "write a number greater than 0")
        limit = self.limit if self.limit is not None else ctx.max_extent if self.length else None
        if limit is not None and abs(v) > limit:
            ctx.fail(path, f"{v:g} is implausibly large (limit {limit:g}{' ' + ctx.units if self.length else ''})",
                     f"check the value and the model's units ({ctx.units})")


@dataclass
class Vec(Node):
    """A list of ``n`` numbers (``n=None``: the model's dim)."""

    n: int | None = None
    item: Node = field(default_factory=Num)
    nonzero: bool = False

    @property
    def type_name(self):
        return f"list of {self.n or 'dim'} numbers"

    def check(self, v, path, ctx):
        n = self.n or ctx.dim
        if not isinstance(v, list | tuple):
            ctx.fail(path, f"must be a list of {n} numbers, got {_show(v)} ({_type_of(v)})",
                     f"write [{', '.join(['0.0'] * n)}]")
        if len(v) != n:
            ctx.fail(path, f"must have {n} numbers, got {len(v)}", f"write {n} numbers")
        for i, x in enumerate(v):
            self.item.check(x, f"{path}[{i}]", ctx)
        if self.nonzero and not any(v):
            ctx.fail(path, "must not be all zero", "give the direction, e.g. [0, 0, 1]")


@dataclass
class Range(Node):
    """``[lo, hi]`` with ``lo < hi``, each within ``limit`` (in the value's unit)."""

    item: Node
    unit: str = ""
    type_name: str = "[lower, upper]"

    def check(self, v, path, ctx):
        Vec(2, self.item).check(v, path, ctx)
        if not v[0] < v[1]:
            ctx.fail(path, f"lower {v[0]:g} must be below upper {v[1]:g}", f"write [{v[1]:g}, {v[0]:g}]")


@dataclass
class ListOf(Node):
    item: Node
    n: int | None = None
    min_len: int = 0
    type_name: str = "list"

    def check(self, v, path, ctx):
        if not isinstance(v, list | tuple):
            ctx.fail(path, f"must be a list, got {_show(v)} ({_type_of(v)})", "write [ ... ]")
        if self.n is not None and len(v) != self.n:
            ctx.fail(path, f"must have {self.n} entries, got {len(v)}", f"write {self.n}")
        if len(v) < self.min_len:
            ctx.fail(path, f"needs at least {self.min_len} entries, got {len(v)}", "add entries")
        for i, x in enumerate(v):
            self.item.check(x, f"{path}[{i}]", ctx)


@dataclass
class OneOrList(Node):
    """One value, or a list of them (``range = [lo, hi]`` or ``[[lo, hi], ...]``)."""

    item: Node
    is_list: Callable[[object], bool]
    type_name: str = "one or a list"

    def check(self, v, path, ctx):
        if self.is_list(v):
            ListOf(self.item, min_len=1).check(v, path, ctx)
        else:
            self.item.check(v, path, ctx)


@dataclass
class MapOf(Node):
    """A table of free keys, every value checked by ``item`` (``[aliases]``)."""

    item: Node
    type_name: str = "table"

    def check(self, v, path, ctx):
        if not isinstance(v, Mapping):
            ctx.fail(path, f"must be a table, got {_show(v)} ({_type_of(v)})", "write [aliases] then NAME = \"LABEL\"")
        for k, x in v.items():
            self.item.check(x, f"{path}.{k}", ctx)


@dataclass
class Key:
    """One key of a table: its node, whether it is required, its default and what it means."""

    node: Node
    doc: str
    required: bool = False
    default: str = ""


@dataclass
class Table(Node):
    """A table with known keys; ``variant`` picks extra keys by the value of one key."""

    keys: dict[str, Key]
    variant: tuple[str, Callable[[object], Mapping[str, Key]]] | None = None
    variant_default: str | None = None
    example: str = ""
    type_name: str = "table"

    def allowed(self, v: Mapping) -> dict[str, Key]:
        keys = dict(self.keys)
        if self.variant is not None:
            keys.update(self.variant[1](v.get(self.variant[0], self.variant_default)))
        return keys

    def check(self, v, path, ctx):
        if not isinstance(v, Mapping):
            ctx.fail(path, f"must be a table, got {_show(v)} ({_type_of(v)})",
                     f"write {self.example}" if self.example else "see docs/model-format.md")
        # the discriminating key first, so that the keys it allows are known
        if self.variant is not None:
            vk = self.variant[0]
            if vk in v:
                self.keys[vk].node.check(v[vk], _join(path, vk), ctx)
            elif self.keys[vk].required:
                ctx.fail(_join(path, vk), "missing key", f"add {vk} = ... (see docs/model-format.md)")
        keys = self.allowed(v)
        every = set(self.keys)
        if self.variant is not None:
            every |= {k for opt in _variant_values(self, ctx) for k in self.variant[1](opt)}
        for k in v:
            if k not in keys:
                if k in every:
                    what = v.get(self.variant[0], self.variant_default) if self.variant else None
                    ctx.fail(_join(path, k), f"key not used with {self.variant[0]} = {what!r}",
                             f"remove it; keys allowed here: {', '.join(keys)}")
                near = difflib.get_close_matches(str(k), list(keys), n=1, cutoff=0.6)
                hint = f"did you mean {near[0]!r}? " if near else ""
                ctx.fail(_join(path, k), "unknown key",
                         f"{hint}keys allowed here: {', '.join(keys)} (see docs/model-format.md)")
        for k, key in keys.items():
            if k not in v:
                if key.required:
                    ctx.fail(_join(path, k), "missing key", f"add {k} = ... (see docs/model-format.md)")
                continue
            key.node.check(v[k], _join(path, k), ctx)


def _join(path: str, key) -> str:
    return f"{path}.{key}" if path else str(key)


def _variant_values(table: Table, ctx: Context) -> tuple:
    node = table.keys[table.variant[0]].node
    return node.options(ctx) if isinstance(node, Str) else ()


# ----------------------------------------------------------------------------- the model format
#: keys a joint takes beyond name, type, position and range, by joint type
JOINT_KEYS: dict[str, dict[str, Key]] = {
    "hinge": {"axis": Key(Vec(3, Num(length=False), nonzero=True), "rotation axis in the parent frame",
                          default="[0, 0, 1]")},
    "universal": {"axes": Key(ListOf(Vec(3, Num(length=False), nonzero=True), n=2),
                              "the two rotation axes, the second moved by the first", required=True)},
}

_COEFFS = Key(ListOf(Num(length=False), min_len=1), "coefficients (linear: slope, intercept; polynomial: "
             "highest power first; constant: the value)", required=True)
#: keys of each coordinate function type (custom joints)
FUNCTION_KEYS: dict[str, dict[str, Key]] = {
    "constant": {"coefficients": _COEFFS},
    "linear": {"coefficients": _COEFFS},
    "polynomial": {"coefficients": _COEFFS},
    "spline": {"x": Key(ListOf(Num(length=False), min_len=2), "knots (coordinate values)", required=True),
               "y": Key(ListOf(Num(length=False), min_len=2), "values at the knots", required=True),
               "end": Key(Str(("natural", "fmm")), "end condition", default='"natural"')},
}

FUNCTION = Table({"type": Key(Str(lambda ctx: tuple(FUNCTION_KEYS)), "function type", required=True),
                  "scale": Key(Num(length=False), "multiplies the function", default="1")},
                 variant=("type", lambda t: FUNCTION_KEYS.get(t, {})),
                 example="{type = 'linear', coefficients = [1.0, 0.0]}")

MOTION = Table({
    "kind": Key(Str(tuple(MOTION_KINDS.values())), "rotation, translation, or a translation carried "
                "by the earlier rotations (along axis by f * (axis . W vector))", required=True),
    "axis": Key(Vec(3, Num(length=False), nonzero=True), "axis (parent frame for translations, the frame "
                "left by earlier rotations for rotations)", required=True),
    "coordinate": Key(Str(), "the joint coordinate it follows", default="none: a constant function"),
    "function": Key(FUNCTION, "the amount as a function of the coordinate", required=True),
    "scale_weights": Key(Vec(3, Num(length=False)), "a translation scales by w . (parent's scale factors); "
                         "all zero: never", default="the axis squared"),
    "vector": Key(Vec(3, Num(length=False)), "the vector a carried translation turns with the joint "
                  "(parent frame)", default="none (required with kind = carried)"),
}, example="{kind = 'rotation', axis = [0, 0, 1], coordinate = 'knee', function = {...}}")

JOINT_KEYS["custom"] = {
    "coordinates": Key(ListOf(Str()), "names of the joint's coordinates (pose order)", required=True),
    "motions": Key(ListOf(MOTION), "translations (applied first) and rotations, in order", required=True),
    "orientation": Key(ListOf(Vec(3, Num(length=False)), n=3), "constant rotation matrix after the motions",
                       default="the identity"),
}


#: axis names a parameter kind takes (default: x, y, z); None: no axis
PARAMETER_AXES: dict[str, tuple[str, ...] | None] = {"length": None, "axis_direction": ("u", "v"),
                                                     "translation_gain": None}

_BOUNDS = {"lower": Key(Num(), "lower bound of the search interval"),
           "upper": Key(Num(), "upper bound of the search interval")}

#: keys of each prior type
PRIOR_KEYS: dict[str, dict[str, Key]] = {
    "uniform": {"lower": Key(Num(), "lower bound", required=True),
                "upper": Key(Num(), "upper bound", required=True)},
    "normal": {"mean": Key(Num(), "mean", default="the nominal value"),
               "sd": Key(Num(positive=True), "standard deviation", required=True), **_BOUNDS},
    "lognormal": {"median": Key(Num(positive=True), "median", default="the nominal value"),
                  "sd_log": Key(Num(positive=True, length=False, limit=5.0),
                                "standard deviation of the logarithm", required=True), **_BOUNDS},
}


def _joint_types(ctx: Context) -> tuple[str, ...]:
    return JOINT_TYPES.get(ctx.dim, ())


def _angle_pair_list(v) -> bool:
    return isinstance(v, list | tuple) and bool(v) and isinstance(v[0], list | tuple)


JOINT = Table({
    "name": Key(Str(), "joint name, used by parameters", default="the segment's name"),
    "type": Key(Str(_joint_types), "joint type (see Joints)", required=True),
    "position": Key(Vec(), "joint centre in the parent frame (world frame for the root)",
                    default="the origin"),
    "range": Key(OneOrList(Range(Num(length=False, limit=MAX_ANGLE_DEG), "deg"), _angle_pair_list),
                 "degrees, [lo, hi] per rotation (a list of pairs for several); for simulation and starts"),
}, variant=("type", lambda t: JOINT_KEYS.get(t, {})),
    example="{type = 'revolute', position = [...]}")

SEGMENT = Table({
    "name": Key(Str(), "segment name", required=True),
    "parent": Key(Str(), "parent segment, or ground for the root", default='"ground"'),
    "joint": Key(JOINT, "the joint attaching it to its parent", required=True),
}, example="[[segments]] tables")

MARKER = Table({
    "name": Key(Str(), "marker name", required=True),
    "segment": Key(Str(), "segment the marker is fixed on", required=True),
    "position": Key(Vec(), "position in the segment's frame", default="the origin"),
    "label": Key(Str(), "name in data files", default="the name"),
}, example="[[markers]] tables")

PRIOR = Table({"type": Key(Str(lambda ctx: tuple(PRIOR_KEYS)), "prior type", default='"uniform"')},
              variant=("type", lambda t: PRIOR_KEYS.get(t, {})), variant_default="uniform",
              example="{type = 'uniform', lower = .., upper = ..}")


def _target_keys(kind) -> dict[str, Key]:
    tk = PARAMETER_TARGET.get(kind, "joint")
    keys = {tk: Key(Str(), f"the {tk} the parameter moves", required=True)}
    names = PARAMETER_AXES.get(kind, ("x", "y", "z"))
    if names is not None:
        keys["axis"] = Key(Str(names), "coordinate or tilt axis")
        keys["axes"] = Key(ListOf(Str(names), min_len=1), "several axes: one parameter each, named NAME_AXIS")
    if kind == "translation_gain":
        keys["motion"] = Key(Int(), "index (from 0) of the translation in the joint's motions", required=True)
    return keys


def _prior_is_list(v) -> bool:
    return isinstance(v, list | tuple)


PARAMETER = Table({
    "name": Key(Str(), "parameter name", default="p<number>"),
    "kind": Key(Str(lambda ctx: PARAMETER_KINDS), "parameter kind (see Parameters)", required=True),
    "prior": Key(OneOrList(PRIOR, _prior_is_list), "a prior table, or one per axis", required=True),
    "grid_step": Key(Num(positive=True), "spacing of grid filters' candidate values",
                     default="1/200 of the prior interval"),
}, variant=("kind", _target_keys), example="[[parameters]] tables")

MODEL = Table({
    "name": Key(Str(), "model name", default="the file name"),
    "dim": Key(Int((2, 3)), "2 (planar) or 3", default="3"),
    "units": Key(Str(lambda ctx: tuple(UNIT_IN_M)), "length unit of every number", default='"mm"'),
    "description": Key(Str(), "free text"),
}, example="[model] with name, dim, units")

SCHEMA = Table({
    "model": Key(MODEL, "the model's name, dimension and units"),
    "segments": Key(ListOf(SEGMENT, min_len=1), "rigid segments and their joints", required=True),
    "markers": Key(ListOf(MARKER, min_len=1), "markers fixed on segments", required=True),
    "parameters": Key(ListOf(PARAMETER), "unknown scalars and their priors"),
    "aliases": Key(MapOf(Str()), "model marker name -> name in data files"),
})


# ----------------------------------------------------------------------------- checks
def validate(d, source: str = "model") -> None:
    """Check a parsed model file against :data:`SCHEMA` and the rules of the module docstring.

    Raises
    ------
    ModelError
        The first problem, as one line naming ``source`` and the key path.
    """
    ctx = Context(source)
    if not isinstance(d, Mapping):
        ctx.fail("", f"is not a table of keys, got {_type_of(d)}", "see docs/model-format.md")
    head = d.get("model", {})
    if isinstance(head, Mapping):
        # dim and units first: the other checks depend on them
        if "dim" in head:
            MODEL.keys["dim"].node.check(head["dim"], "model.dim", ctx)
            ctx.dim = head["dim"]
        if "units" in head:
            MODEL.keys["units"].node.check(head["units"], "model.units", ctx)
            ctx.units = head["units"]
    SCHEMA.check(d, "", ctx)
    _check_priors(d, ctx)


def _model_size(d: Mapping) -> float:
    xs = [abs(x) for s in d.get("segments", []) for x in s["joint"].get("position", ())]
    xs += [abs(x) for m in d.get("markers", []) for x in m.get("position", ())]
    return max(xs, default=0.0)


def _check_priors(d: Mapping, ctx: Context) -> None:
    """Bounds derived from each prior: finite, ``lower < upper``, of the model's size."""
    size = _model_size(d)
    limit = min(ctx.max_extent, MAX_PRIOR_SCALE * size) if size > 0 else ctx.max_extent
    for i, p in enumerate(d.get("parameters", [])):
        priors = p.get("prior", {})
        many = isinstance(priors, list | tuple)
        for j, pr in enumerate(priors if many else [priors]):
            path = f"parameters[{i}].prior" + (f"[{j}]" if many else "")
            lo, hi, exact = prior_bounds(pr, size)
            if not (math.isfinite(lo) and math.isfinite(hi)):
                ctx.fail(path, "gives an unbounded search interval", "set lower and upper, or a smaller spread")
            if exact and not lo < hi:
                ctx.fail(path, f"lower {lo:g} must be below upper {hi:g}", "swap or correct the bounds")
            if max(abs(lo), abs(hi)) > limit:
                ctx.fail(path, f"interval [{lo:g}, {hi:g}] {ctx.units} is implausibly wide for a model of size "
                         f"{size:g} {ctx.units} (limit {limit:g})", "give bounds of the size of the model")
            step = p.get("grid_step")
            if exact and step is not None and step > hi - lo:
                ctx.fail(f"parameters[{i}].grid_step", f"{step:g} is wider than the prior interval "
                         f"[{lo:g}, {hi:g}]", "give a step smaller than the interval")


def prior_bounds(pr: Mapping, size: float = 0.0) -> tuple[float, float, bool]:
    """``(lower, upper, exact)``: the search interval a prior table gives.

    Where the centre is implicit (the nominal value, at most ``size`` away from
    0), the interval is an estimate centred on 0 (normal) or ``size``
    (log-normal), and ``exact`` is False.
    """
    kind = pr.get("type", "uniform")
    if kind == "uniform":
        return float(pr["lower"]), float(pr["upper"]), True
    centre_key = "mean" if kind == "normal" else "median"
    exact = centre_key in pr or ("lower" in pr and "upper" in pr)
    if kind == "normal":
        mean, sd = pr.get("mean", 0.0), pr["sd"]
        lo, hi = mean - 5 * sd, mean + 5 * sd
    else:
        med, s = pr.get("median", size or 1.0), min(5 * pr["sd_log"], 700.0)
        lo, hi = med * math.exp(-s), med * math.exp(s)
    return float(pr.get("lower", lo)), float(pr.get("upper", hi)), exact


# ----------------------------------------------------------------------------- reference
def _rows(table: Table, path: str, ctx: Context, out: list, note: str = "") -> None:
    for k, key in table.keys.items():
        _row(k, key, path, ctx, out, note)
    if table.variant is not None:
        for opt in _variant_values(table, Context("", 3)) or ():
            for k, key in table.variant[1](opt).items():
                _row(k, key, path, ctx, out, f"{table.variant[0]} = {opt}")


def _row(k, key: Key, path, ctx, out, note):
    p = _join(path, k)
    node = key.node
    sub = node.item if isinstance(node, ListOf | OneOrList) and isinstance(node.item, Table) else node
    if isinstance(sub, Table):
        kind = "table" if sub is node else "table, or a list of them" if isinstance(node, OneOrList) \
            else "list of tables"
        out.append([p, kind, key.required, key.default, key.doc, note])
        _rows(sub, p + ("[]" if sub is not node else ""), ctx, out)
        return
    row = [p, _describe(node, ctx), key.required, key.default, key.doc, note]
    same = next((r for r in out if r[:5] == row[:5]), None)
    if same is None:
        out.append(row)
    elif note and same[5]:  # the same key for several values of the variant: one row naming them
        same[5] += ", " + note.split(" = ")[1]


def _describe(node: Node, ctx: Context) -> str:
    if isinstance(node, Str) and node.choices is not None:
        opts = node.options(ctx) if not callable(node.choices) else (
            tuple(dict.fromkeys(JOINT_TYPES[2] + JOINT_TYPES[3]))
            if node.choices is _joint_types else node.options(ctx))
        return "one of " + ", ".join(f"`{o}`" for o in opts)
    if isinstance(node, Int) and node.choices:
        return "integer: " + " or ".join(map(str, node.choices))
    if isinstance(node, Num):
        return "positive number" if node.positive else "number"
    if isinstance(node, Range):
        return "[lower, upper], lower < upper"
    if isinstance(node, OneOrList):
        return f"{_describe(node.item, ctx)}, or a list of them"
    if isinstance(node, ListOf):
        n = f"{node.n} " if node.n else ""
        return f"list of {n}({_describe(node.item, ctx)})"
    if isinstance(node, MapOf):
        return "table of strings"
    if isinstance(node, Vec):
        return f"list of {node.n or 'dim'} numbers"
    return node.type_name


def reference_rows() -> list[tuple]:
    """``(key path, type, required, default, meaning, when)`` for every key of the schema."""
    out: list = []
    _rows(SCHEMA, "", Context(""), out)
    return [tuple(r) for r in out]


def reference_markdown() -> str:
    """The key reference table of docs/model-format.md, generated from the schema."""
    lines = ["| key | type | required | default | meaning |", "|---|---|---|---|---|"]
    for path, typ, req, default, doc, note in reference_rows():
        when = f" (with {note})" if note else ""
        lines.append(f"| `{path}` | {typ} | {'yes' if req else ''} | {default} | {doc}{when} |")
    return "\n".join(lines)


def documented_keys(markdown: str) -> set[str]:
    """Key paths of the reference table in a markdown text (between its begin and end marks)."""
    out = set()
    block = markdown.split(REFERENCE_BEGIN, 1)[-1].split(REFERENCE_END, 1)[0]
    for line in block.splitlines():
        if line.startswith("| `"):
            out.add(line.split("`")[1])
    return out


def check_built(model, d: Mapping, source: str = "model") -> None:
    """Checks that need the built model: a joint's ``range`` has at most one pair per rotation."""
    ctx = Context(source, model.dim, model.units)
    rotations: dict[str, int] = {}
    for dof in model.dofs:
        if dof.kind == "R":
            name = model.segments[dof.segment].name
            rotations[name] = rotations.get(name, 0) + 1
    for i, s in enumerate(d.get("segments", [])):
        seg = next(x for x in model.segments if x.name == s["name"])
        n = rotations.get(seg.name, 0)
        if len(seg.joint.range) > n:
            ctx.fail(f"segments[{i}].joint.range", f"has {len(seg.joint.range)} [lo, hi] pair(s) for a "
                     f"{seg.joint.type} joint with {n} rotation(s)", f"give at most {n} pair(s)")
