"""Custom (coupled) joints as flat tables for the compiled kernels.

A custom joint (:mod:`skelid.model.functions`) is a list of motions, each a translation or a
rotation by a coordinate or by a function of it. The compiled kernels (the pose fit's and the
kinematics') read them from the arrays :func:`custom_arrays` makes of a
:class:`~skelid.model.kinematics.KinematicsPlan`, and evaluate the functions with
:func:`function_value`.
"""

from __future__ import annotations

import numpy as np

from skelid._numba import AVAILABLE, numba


def _function_tables(funs) -> tuple:
    """Flat tables of coordinate functions: ``(kind, scale, start, values, piece start, base, coef)``.

    Kind 0: a spline, its knots in ``values[start[f]:start[f + 1]]`` and its pieces (one more
    than the knots: the end tangents included; see ``CoordinateFunction._pieces``) at rows
    ``piece_start[f]...`` of ``base`` and ``coef (n, 4)`` (power form ``c0 + c1 b + c2 b^2 + c3 b^3``,
    ``b = q - base``). Kind 1: a polynomial, its coefficients (highest power first) in ``values``
    (a constant and a linear function are polynomials).
    """
    kind, scale, start, values, pstart, base, coef = [], [], [0], [], [0], [], []
    for f in funs:
        scale.append(f.scale)
        if f.kind == "spline":
            x, b, c = f._pieces
            kind.append(0)
            values += list(x)
            base += list(b)
            coef += [list(r) for r in np.asarray(c).T]
        else:
            kind.append(1)
            values += list(f.coefficients)
        start.append(len(values))
        pstart.append(len(base))
    return (np.array(kind, np.int64), np.array(scale, float), np.array(start, np.int64), np.array(values, float),
            np.array(pstart, np.int64), np.array(base, float), np.array(coef, float).reshape(-1, 4))


def custom_arrays(plan) -> tuple | None:
    """The tables of a model's custom joints for the compiled kernel, or None where it cannot follow them.

    Per motion row (segment ``i``'s rows ``start[i]:start[i + 1]``, translations first, as
    :func:`skelid.model.kinematics._forward_general` applies them): whether it translates, its
    axis, its pose coordinate (-1: none), its function (-1: the coordinate itself, else a row of
    :func:`_function_tables`), its scale factor's slot in ``g`` (-1: none) and the cross-product
    matrix of its axis and its square; per segment the constant rotation after the motions; per
    pose coordinate whether its column has a velocity term (a function's derivative). Carried
    translations and tilted hinges are left to the numpy path (None).
    """
    S, Q = plan.n_segments, plan.n_pose
    if plan.dim != 3 or plan.n_tilts:
        return None
    is_t, axis, coord, fun, slot, skew, skew2, funs = [], [], [], [], [], [], [], []
    start = [0]
    orient = np.zeros((S, 3, 3))
    has_orient = np.zeros(S, np.bool_)
    has_vel = np.zeros(Q, np.bool_)
    for i in range(S):
        for t, a, k, f, sl, K, K2, carried in plan.custom[i] or ():
            if carried is not None:
                return None
            plain = k >= 0 and f.is_identity
            is_t.append(bool(t))
            axis.append(np.asarray(a, float))
            coord.append(k)
            fun.append(-1 if plain else len(funs))
            funs += [] if plain else [f]
            slot.append(sl)
            skew.append(K)
            skew2.append(K2)
            if k >= 0 and not plain:
                has_vel[k] = has_vel[k] or bool(t)
        start.append(len(is_t))
        if plan.orientation[i] is not None:
            orient[i] = plan.orientation[i]
            has_orient[i] = True
    n = len(is_t)
    rows = (np.array(start, np.int64), np.array(is_t, np.bool_).reshape(n), np.array(axis, float).reshape(n, 3),
            np.array(coord, np.int64).reshape(n), np.array(fun, np.int64).reshape(n),
            np.array(slot, np.int64).reshape(n), np.array(skew, float).reshape(n, 3, 3),
            np.array(skew2, float).reshape(n, 3, 3), orient, has_orient, has_vel)
    return rows + _function_tables(funs) + ((S + plan.n_markers) * 3,)


def no_custom(S: int, Q: int) -> tuple:
    """The custom-joint tables of a model without custom joints (the drivers' common argument)."""
    i, f = np.int64, float
    return (np.zeros(S + 1, i), np.zeros(0, np.bool_), np.zeros((0, 3)), np.zeros(0, i), np.zeros(0, i),
            np.zeros(0, i), np.zeros((0, 3, 3)), np.zeros((0, 3, 3)), np.zeros((S, 3, 3)), np.zeros(S, np.bool_),
            np.zeros(Q, np.bool_), np.zeros(0, i), np.zeros(0, f), np.zeros(1, i), np.zeros(0, f), np.zeros(1, i),
            np.zeros(0, f), np.zeros((0, 4)), 0)


if AVAILABLE:  # pragma: no branch
    _jit = numba.njit(cache=True, nogil=True, error_model="numpy")

    @_jit
    def function_value(f, v, kind, scale, start, values, pstart, base, coef):
        """``(f(v), f'(v))`` of function ``f`` of :func:`_function_tables` (compiled)."""
        if kind[f] == 1:  # a polynomial, highest power first (Horner)
            val, der = 0.0, 0.0
            for j in range(start[f], start[f + 1]):
                der = der * v + val
                val = val * v + values[j]
            return scale[f] * val, scale[f] * der
        n = pstart[f]  # the piece: one past the last knot at or below v (its left tangent below the first)
        for j in range(start[f], start[f + 1]):
            if values[j] <= v:
                n += 1
            else:
                break
        h = v - base[n]
        c1, c2, c3 = coef[n, 1], coef[n, 2], coef[n, 3]
        return (scale[f] * (coef[n, 0] + h * (c1 + h * (c2 + h * c3))),
                scale[f] * (c1 + h * (2.0 * c2 + 3.0 * h * c3)))
