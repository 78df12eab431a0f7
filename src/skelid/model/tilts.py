"""Tilted hinge axes: the axis ``a(alpha, beta)`` of a hinge with ``axis_direction`` parameters.

With the hinge's nominal unit axis ``e`` and the two directions ``u``, ``v``
it tilts towards (:func:`skelid.model.description.tilt_basis`), tilts
``(alpha, beta)`` in degrees give

.. math:: a = \\cos\\alpha \\cos\\beta\\, e + \\sin\\alpha \\cos\\beta\\, u + \\sin\\beta\\, v .

Shared by the numpy kinematics (:mod:`skelid.model.kinematics`) and the
compiled one (:mod:`skelid.model._fk_kernel`), which import it and not each
other for it.
"""

from __future__ import annotations

import numpy as np


def tilt_arrays(model) -> tuple:
    """``(ku, kv, e, u, v)`` of the model's tilted hinges as arrays (see ``Model.axis_tilts``).

    ``ku``, ``kv`` are ``(T,)`` int parameter indices (-1: that tilt is fixed);
    ``e``, ``u``, ``v`` are ``(T, 3)`` float.
    """
    tilts = model.axis_tilts
    return tuple(np.array([t[i] for t in tilts]) for i in range(1, 6))


def tilted_axes_from(arrays: tuple, theta) -> tuple[np.ndarray, np.ndarray]:
    """The tilted axes ``(..., T, 3)`` and their derivatives per degree ``(..., T, 2, 3)``.

    Parameters
    ----------
    arrays : tuple
        :func:`tilt_arrays` of the model (at least one tilted hinge).
    theta : (..., P) float
    """
    ku, kv, e, u, v = arrays
    theta = np.asarray(theta, dtype=float)
    al = np.where(ku >= 0, np.radians(theta[..., np.maximum(ku, 0)]), 0.0)[..., None]
    be = np.where(kv >= 0, np.radians(theta[..., np.maximum(kv, 0)]), 0.0)[..., None]
    ca, sa, cb, sb = np.cos(al), np.sin(al), np.cos(be), np.sin(be)
    axis = ca * cb * e + sa * cb * u + sb * v
    d_al = cb * (-sa * e + ca * u)
    d_be = -sb * (ca * e + sa * u) + cb * v
    deg = np.pi / 180.0
    d_axis = np.stack([d_al * (ku >= 0)[:, None], d_be * (kv >= 0)[:, None]], -2) * deg
    return axis, d_axis
