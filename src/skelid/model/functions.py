"""Functions of one coordinate that drive the motions of a coupled joint.

A coupled joint (type ``custom``) moves its child by elementary motions whose
amounts are functions ``f(q)`` of the joint's coordinates, the way OpenSim's
``CustomJoint`` does through its ``SpatialTransform``. The knee of the gait
models, for instance, rotates by ``q`` about z and translates by two splines
of the same ``q``, so its centre slides with flexion.

Each function returns its value and its derivative, both analytic:

* ``constant``: ``f(q) = c`` (a motion that does not move);
* ``linear``: ``f(q) = a q + b`` (``coefficients = (a, b)``);
* ``polynomial``: ``f(q) = sum_k c_k q^(n-k)`` (``coefficients`` highest power
  first, as OpenSim's ``PolynomialFunction`` writes them);
* ``spline``: a cubic spline through knots ``(x_i, y_i)`` with second
  derivatives ``M_i`` solving the continuity equations

  .. math:: h_{i-1} M_{i-1} + 2 (h_{i-1} + h_i) M_i + h_i M_{i+1}
            = 6 (\\Delta_i - \\Delta_{i-1}),
            \\quad \\Delta_i = (y_{i+1} - y_i) / h_i

  and one of two end conditions: ``natural`` (``M_0 = M_{n-1} = 0``, OpenSim's
  ``NaturalCubicSpline``) or ``fmm`` (the third derivative at each end equals
  that of the cubic through the four nearest knots, the Forsythe-Malcolm-Moler
  condition of OpenSim's ``SimmSpline``; three knots give a parabola, two a
  line). Outside the knots a spline continues along its end tangent.

A ``scale`` multiplies any of them (OpenSim's ``MultiplierFunction``).

Examples
--------
>>> f = CoordinateFunction("spline", x=(0.0, 1.0, 2.0, 3.0), y=(0.0, 1.0, 8.0, 27.0), end="fmm")
>>> [round(float(v), 12) for v in f.value([0.5, 2.5])]  # a cubic is reproduced exactly
[0.125, 15.625]
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from skelid.errors import ModelError

FUNCTION_KINDS = ("constant", "linear", "polynomial", "spline")
SPLINE_ENDS = ("natural", "fmm")


@dataclass(frozen=True)
class CoordinateFunction:
    """A function of one coordinate with its analytic derivative (see the module docstring).

    Attributes
    ----------
    kind : {'constant', 'linear', 'polynomial', 'spline'}
    coefficients : tuple of float
        ``(c,)`` for a constant, ``(a, b)`` for a linear function, highest power
        first for a polynomial; empty for a spline.
    x, y : tuple of float
        Spline knots (strictly increasing ``x``).
    end : {'natural', 'fmm'}
        Spline end condition.
    scale : float
        Multiplies the function.
    """

    kind: str
    coefficients: tuple[float, ...] = ()
    x: tuple[float, ...] = ()
    y: tuple[float, ...] = ()
    end: str = "natural"
    scale: float = 1.0

    def __post_init__(self):
        if self.kind not in FUNCTION_KINDS:
            raise ModelError(f"unknown coordinate function {self.kind!r}",
                             f"use one of: {', '.join(FUNCTION_KINDS)}")
        need = {"constant": 1, "linear": 2}
        if self.kind in need and len(self.coefficients) != need[self.kind]:
            raise ModelError(f"a {self.kind} function needs {need[self.kind]} coefficient(s), "
                             f"got {len(self.coefficients)}")
        if self.kind == "polynomial" and not self.coefficients:
            raise ModelError("a polynomial function needs at least one coefficient")
        if self.kind == "spline":
            if self.end not in SPLINE_ENDS:
                raise ModelError(f"unknown spline end condition {self.end!r}",
                                 f"use one of: {', '.join(SPLINE_ENDS)}")
            x = np.asarray(self.x, float)
            if x.size < 2 or x.size != len(self.y) or np.any(np.diff(x) <= 0) \
                    or not np.all(np.isfinite(self.y)) or not np.all(np.isfinite(x)):
                raise ModelError(
                    f"a spline needs at least two knots with strictly increasing, finite x and as many y "
                    f"(got {len(self.x)} x and {len(self.y)} y)")

    @cached_property
    def is_identity(self) -> bool:
        """True for ``f(q) = q`` (the motion is the coordinate itself)."""
        return self.kind == "linear" and self.scale * self.coefficients[0] == 1.0 and self.coefficients[1] == 0.0

    @cached_property
    def is_constant(self) -> bool:
        return self.kind == "constant"

    @cached_property
    def _second(self) -> np.ndarray:
        """Second derivatives ``M_i`` of the spline at its knots."""
        x, y = np.asarray(self.x, float), np.asarray(self.y, float)
        n = x.size
        if n == 2:
            return np.zeros(2)
        h = np.diff(x)
        delta = np.diff(y) / h
        A = np.zeros((n, n))
        b = np.zeros(n)
        for i in range(1, n - 1):
            A[i, i - 1:i + 2] = h[i - 1], 2 * (h[i - 1] + h[i]), h[i]
            b[i] = 6 * (delta[i] - delta[i - 1])
        if self.end == "natural":
            A[0, 0] = A[-1, -1] = 1.0
        else:  # third derivative of the end interval = that of the cubic through the 4 end knots
            def third(xs, ys):  # 6 x third divided difference (0 for fewer than 4 knots)
                if len(xs) < 4:
                    return 0.0
                d = list(ys)
                for k in range(1, 4):
                    d = [(d[i + 1] - d[i]) / (xs[i + k] - xs[i]) for i in range(len(d) - 1)]
                return 6.0 * d[0]
            A[0, 0], A[0, 1], b[0] = -1.0 / h[0], 1.0 / h[0], third(x[:4], y[:4])
            A[-1, -2], A[-1, -1], b[-1] = -1.0 / h[-1], 1.0 / h[-1], third(x[-4:], y[-4:])
        return np.linalg.solve(A, b)

    def value_and_derivative(self, q) -> tuple[np.ndarray, np.ndarray]:
        """``(f(q), f'(q))``, each shaped like ``q``."""
        q = np.asarray(q, dtype=float)
        c = self.coefficients
        if self.kind == "constant":
            v, d = np.full(q.shape, c[0]), np.zeros(q.shape)
        elif self.kind == "linear":
            v, d = c[0] * q + c[1], np.full(q.shape, c[0])
        elif self.kind == "polynomial":
            p = np.asarray(c, float)
            v, d = np.polyval(p, q), np.polyval(np.polyder(p), q) if p.size > 1 else np.zeros(q.shape)
        else:
            v, d = self._spline(q)
        return self.scale * v, self.scale * d

    def value(self, q) -> np.ndarray:
        return self.value_and_derivative(q)[0]

    @cached_property
    def _pieces(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Knots, bases and power-form coefficients of the pieces, the end tangents included.

        Row 0 is the line left of the first knot, rows ``1 .. n-1`` the cubic
        on each interval, row ``n`` the line right of the last knot; piece
        ``i`` is ``c0 + c1 b + c2 b^2 + c3 b^3`` with ``b = q - base_i``.
        """
        x, y = np.asarray(self.x, float), np.asarray(self.y, float)
        M = self._second
        h = np.diff(x)
        c1 = np.diff(y) / h - h * (2 * M[:-1] + M[1:]) / 6
        c2 = M[:-1] / 2
        c3 = np.diff(M) / (6 * h)
        s1 = np.diff(y)[-1] / h[-1] + h[-1] * (M[-2] + 2 * M[-1]) / 6  # slope at the last knot
        coef = np.zeros((x.size + 1, 4))
        coef[0, :2] = y[0], c1[0]
        coef[1:-1] = np.stack([y[:-1], c1, c2, c3], axis=-1)
        coef[-1, :2] = y[-1], s1
        base = np.concatenate([[x[0]], x[:-1], [x[-1]]])
        return x, base, np.ascontiguousarray(coef.T)  # (4, n + 1)

    def _spline(self, q):
        x, base, coef = self._pieces
        i = np.searchsorted(x, q, side="right")
        b = q - base[i]
        c0, c1, c2, c3 = coef[:, i]
        v = c0 + b * (c1 + b * (c2 + b * c3))
        d = c1 + b * (2.0 * c2 + 3.0 * b * c3)
        return v, d

    def to_dict(self) -> dict:
        d: dict = {"type": self.kind}
        if self.kind == "spline":
            d.update(x=list(self.x), y=list(self.y), end=self.end)
        else:
            d["coefficients"] = list(self.coefficients)
        if self.scale != 1.0:
            d["scale"] = self.scale
        return d

    @classmethod
    def from_dict(cls, d, where: str) -> CoordinateFunction:
        if not isinstance(d, dict) or "type" not in d:
            raise ModelError(f"{where}: a function must be a table with a type",
                             f"use type = one of {', '.join(FUNCTION_KINDS)}")
        try:
            return cls(str(d["type"]), tuple(float(v) for v in d.get("coefficients", ())),
                       tuple(float(v) for v in d.get("x", ())), tuple(float(v) for v in d.get("y", ())),
                       str(d.get("end", "natural")), float(d.get("scale", 1.0)))
        except ModelError as exc:
            raise ModelError(f"{where}: {exc.problem}", exc.fix) from None
        except (TypeError, ValueError):
            raise ModelError(f"{where}: function values must be numbers, got {d!r}") from None
