"""Soft-tissue artefact as a random effect of stated size: how much it can move the estimate.

A skin marker slides against the bone by an amount that follows the angles of
the joints next to its segment. Part of that slide looks exactly like a change
of geometry, so no residual can reveal it, and residual-based intervals
(Newey-West included) claim a precision the data do not have. Following the
modal description of soft-tissue artefact (marker displacement as a smooth
function of the adjacent joint angles), each marker coordinate gets

.. math:: \\delta_{m}(t) = \\sum_k c_{mk}\\, \\phi_{mk}(t), \\qquad c_{mk} \\sim N(0, a^2 / K_m),

with ``K_m`` basis functions ``phi`` per coordinate of marker ``m``: a constant,
and the first and second powers of each adjacent joint angle (centred, scaled to
unit root-mean-square over the trial), so that ``a`` is the root-mean-square
displacement of a marker coordinate, which the user states (skin markers on the
thigh: 10-30 mm; on the forearm or hand: a few mm). Linearising the fit, a
marker perturbation ``delta`` moves the estimate by
``sum_t S^{-1} (K_t - J_t G_t)^T delta_t`` (the influence rows of the
motion-model fit, see :func:`skelid.estimators.fit.joint.smoothed_frame_scores`), so
the artefact adds

.. math:: \\Sigma_{art} = g\\, \\mathrm{diag}(a^2/K_m)\\, g^\\top, \\qquad
          g = S^{-1} \\textstyle\\sum_t (K_t - J_t G_t)^\\top B_t,

to the covariance of the estimate (``B_t``: the basis at frame ``t``). This is a
statement about what the data cannot tell apart, not an estimate from them.
"""

from __future__ import annotations

import numpy as np

from skelid._linalg import summed_gram
from skelid.estimators.fit.likelihood import frame_terms
from skelid.model.description import Model


def artefact_basis(model: Model, pose, used) -> tuple[np.ndarray, np.ndarray]:
    """Basis of marker displacements driven by adjacent joint angles.

    For marker ``m`` on segment ``s``, the adjacent angles are the rotational
    coordinates of the joint of ``s`` and of its children's joints (a free
    root's coordinates are not joint angles and are left out). Each marker
    coordinate gets a constant, and ``u`` and ``u^2 - mean`` for every adjacent
    angle ``u`` (centred and scaled over the frames used).

    Returns
    -------
    funcs : (T, K) float
        Each basis function over the frames.
    owner : (K,) int
        The marker coordinate (``m * D + d``) each one moves; the displacement of
        basis function ``k`` is ``funcs[:, k]`` on that coordinate and 0 elsewhere.
    """
    D = model.dim
    seg_of_dof = np.array([d.segment for d in model.dofs])
    rot = np.array([d.kind == "R" and model.segments[d.segment].joint.type != "free" for d in model.dofs])
    u = pose[:, rot] - pose[used][:, rot].mean(axis=0)
    u = u / np.maximum(np.sqrt(np.mean(u[used] ** 2, axis=0)), 1e-12)
    u2 = u**2 - np.mean(u[used] ** 2, axis=0)
    u2 = u2 / np.maximum(np.sqrt(np.mean(u2[used] ** 2, axis=0)), 1e-12)
    table = np.concatenate([np.ones((len(pose), 1)), u, u2], axis=1)  # constant, angles, squares
    dof_col = np.full(len(rot), -1)
    dof_col[rot] = np.arange(rot.sum())
    seg_s = model.marker_segment[:, None]
    near = rot & ((seg_of_dof == seg_s) | (model.parent_index[seg_of_dof] == seg_s))  # (M, Q)
    cols, owner = [], []
    for m in range(len(model.markers)):  # which functions each marker gets: model structure only
        k = dof_col[near[m]]
        per_marker = np.concatenate([[0], 1 + k, 1 + rot.sum() + k])
        cols += [per_marker] * D
        owner += [np.full(per_marker.size, m * D + d) for d in range(D)]
    return table[:, np.concatenate(cols)], np.concatenate(owner)


def artefact_influence(model: Model, y, theta, pose, R, used):
    """How each artefact basis function moves the estimate, to first order.

    Returns
    -------
    g : (P, K) float
        Change of ``theta`` per unit coefficient of each basis function.
    owner : (K,) int
        The marker coordinate (``m * D + d``) each basis function moves.
    """
    from skelid.estimators.fit.joint import influence_rows

    _, Jq, Jt = frame_terms(model, theta, pose, y)
    A, _ = influence_rows(Jq, Jt, R)  # (T, m, P); rows of missing markers are zero
    return _influence_of_basis(model, A, summed_gram(Jt, A), pose, used)


def _influence_of_basis(model: Model, A, S, pose, used, sw=None):
    """:func:`artefact_influence` from a fit's influence rows ``A (T, M*D, P)`` and information ``S``;
    ``sw (T, M*D)``: the rows' weights (square roots), None for none. Returns ``g (P, K)``, ``owner (K,)``."""
    funcs, owner = artefact_basis(model, pose, used)
    if sw is not None:
        funcs = funcs * sw[:, owner]
    g = np.empty((A.shape[-1], len(owner)))
    for j in np.unique(owner):  # one marker coordinate at a time: no (T, K, P) copy of the rows
        k = np.flatnonzero(owner == j)
        g[:, k] = A[:, j, :].T @ funcs[:, k]
    return np.linalg.pinv(S) @ g, owner


def marker_artefact_terms(model: Model, A, S, pose, used, sw=None) -> np.ndarray:
    """Each marker's share of :func:`artefact_covariance` at a unit root-mean-square: ``(M, P, P)``.

    The artefact's coefficients are independent between markers, so the covariance it adds is the sum
    of these terms times ``rms^2``; the marker jackknife, which sees the markers one at a time, compares
    its spread with the terms of the markers it could leave out
    (:func:`skelid.estimators.uncertainty.jackknife.fold`). ``A``, ``S``, ``sw``: as
    :func:`_influence_of_basis`.
    """
    g, owner = _influence_of_basis(model, A, S, pose, used, sw)
    g = g * np.sqrt(1.0 / np.bincount(owner)[owner])  # the coordinate's unit rms shared by its functions
    marker = owner // model.dim
    out = np.zeros((len(model.markers), g.shape[0], g.shape[0]))
    for m in np.unique(marker):
        gm = g[:, marker == m]
        out[m] = gm @ gm.T
    return out


def artefact_covariance(model: Model, y, theta, pose, R, rms: float, used) -> np.ndarray:
    """Covariance ``(P, P)`` that a soft-tissue artefact of root-mean-square ``rms`` adds to ``theta``.

    Parameters
    ----------
    y : (T, M, D) float
        Markers, NaN where missing or not used (only the pattern is used).
    theta : (P,) float
    pose : (T, Q) float
        The fit's poses.
    R : sparse (T*Q, T*Q) or None
        The fit's motion-model penalty (None: poses free per frame).
    rms : float
        Root-mean-square artefact displacement of a marker coordinate (model units).
    used : (T,) bool
        Frames in the fit.
    """
    g, owner = artefact_influence(model, y, theta, pose, R, used)
    var = rms**2 / np.bincount(owner)[owner]  # the coordinate's rms shared by its basis functions
    return (g * var) @ g.T
