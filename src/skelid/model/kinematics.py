"""Forward kinematics of a segment tree and its analytic Jacobians.

For a model with segments ``s = 0..S-1`` (parents first), pose ``q`` and
geometry ``g = g_base + theta @ A.T`` (see :mod:`skelid.model.description`):

.. math::

    R_{ws} = R_{wp}\\,\\prod_k E_k(q_k), \\qquad
    p_{ws} = p_{wp} + R_{wp}\\, o_s + \\sum_{k\\,\\in\\,T(s)} R_{wp} e_k q_k,
    \\qquad x_m = p_{w s(m)} + R_{w s(m)}\\, r_m

where ``p`` is the segment's parent, ``o_s`` its joint's position in the
parent frame, ``E_k`` the elementary rotations of the joint and ``r_m`` the
marker's position in its segment. The Jacobians are

* rotation ``k`` about world axis ``w_k`` through ``c_k``: ``dx_m/dq_k = w_k x (x_m - c_k)``
  (in 2-D, ``w x v = (-v_y, v_x)``); translation: ``dx_m/dq_k = w_k``;
* joint offset ``o_s``: ``dx_m/do_s = R_wp`` for every marker below ``s``;
  marker offset: ``dx_m/dr_m = R_{w s(m)}``; and ``dx/dtheta = dx/dg · A``;
* a hinge axis ``a(alpha, beta)`` tilted by ``axis_direction`` parameters
  (angles in degrees): with ``R_b`` the frame the hinge acts in and ``q`` its
  angle, ``d R / d alpha = [w]_x R`` with the world vector
  ``w = sin(q) R_b a' + (1 - cos q) (R_b a) x (R_b a')``, ``a' = da/dalpha``
  (the left Jacobian of the exponential map, simplified because ``a' ⊥ a``),
  so ``dx_m/dalpha = w x (x_m - c)`` for every marker below the hinge.

Every function broadcasts over any leading batch axes shared by ``theta``
``(..., P)`` and ``pose (..., Q)``, typically ``(frames, hypotheses)``. The only
Python loop runs over the model's segments (the depth of the tree).

Planar models take a shorter path: every rotation is about ``z``, so a
segment's orientation is one angle, the sum of the rotation coordinates along
its chain, and ``R_{ws} = R(\\phi_s)`` needs one cosine and one sine per
segment instead of a product of matrices. What does not depend on the pose
(index tables, the parts of ``A`` that move joints and markers, which hinges
are tilted) is compiled once per model by :func:`kinematics_plan` and kept in
the model's :class:`Workspace`, never in the frozen model.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from skelid.model import _fk_kernel
from skelid.model.description import Model
from skelid.model.tilts import tilt_arrays, tilted_axes_from  # noqa: F401  (re-exported)


class Kinematics(NamedTuple):
    """Result of :func:`forward_kinematics` (all arrays share the batch shape ``...``)."""

    R_world_seg: np.ndarray  # (..., S, D, D)
    p_world_seg: np.ndarray  # (..., S, D) joint centre = segment origin
    R_world_parent: np.ndarray  # (..., S, D, D) frame the joint acts in
    dof_axis: np.ndarray  # (..., Q, D) world axis (3-D rotation or translation); 2-D rotation: 0
    dof_pivot: np.ndarray  # (..., Q, D) a point on the rotation axis
    markers: np.ndarray  # (..., M, D)
    g: np.ndarray  # (..., G)
    tilt_omega: np.ndarray  # (..., T, 2, D) world d(rotation)/d(tilt) of each tilted hinge, per degree
    dof_velocity: np.ndarray | None = None  # (..., Q, D) extra term of coupled coordinates' columns
    coupled_shift: np.ndarray | None = None  # (..., C, D) world f(q) a of each scaled coupled translation


class KinematicsPlan(NamedTuple):
    """What the kinematics of a model need that does not depend on ``theta`` or the pose."""

    dim: int
    n_segments: int
    n_markers: int
    n_pose: int
    n_params: int
    parent: tuple  # (S,) parent index, -1 for the root
    g_base: np.ndarray  # (G,)
    A: np.ndarray  # (G, P)
    dof_segment: np.ndarray  # (Q,) int
    dof_is_t: np.ndarray  # (Q,) bool
    dof_axis: np.ndarray  # (Q, D) nominal axis in the frame the joint acts in (2-D rotation: 0)
    dof_skew: np.ndarray  # (Q, 3, 3) cross-product matrix of a 3-D rotation axis
    dof_skew2: np.ndarray  # (Q, 3, 3) its square
    segment_dofs: tuple  # per segment, the indices of its pose coordinates
    segment_rot: tuple  # per segment, the indices of its rotation coordinates
    segment_trans: tuple  # per segment, the indices of its translation coordinates
    marker_segment: np.ndarray  # (M,) int
    moves: np.ndarray  # (Q, M) float: 1 where pose coordinate k moves marker m
    rot_dofs: np.ndarray  # (n_R,) int
    trans_dofs: np.ndarray  # (n_T,) int
    used_joints: np.ndarray  # segments whose joint position depends on theta
    A_joint: np.ndarray  # (n_used_joints, D, P)
    ancestor_markers: np.ndarray  # (n_used_joints, M) float: joint moves marker
    used_markers: np.ndarray  # markers whose position depends on theta
    A_marker: np.ndarray  # (n_used_markers, D, P)
    dof_tilt: np.ndarray  # (Q,) int: slot of the hinge in Model.axis_tilts, -1 if its axis is fixed
    n_tilts: int
    planar: bool  # 2-D, no tilted axis, every joint's translations before its rotation
    custom: tuple = ()  # per segment: None, or its custom joint's motions (see _custom_tables)
    orientation: tuple = ()  # per segment: None, or the constant (3, 3) rotation after its motions
    has_custom: bool = False
    n_coupled: int = 0  # scaled coupled translations (entries of g after the markers)
    coupled_segment: np.ndarray = np.zeros(0, dtype=int)  # (C,) segment of each
    coupled_moves: np.ndarray = np.zeros((0, 0))  # (C, M) float: the translation moves marker m


class Workspace:
    """What computing with one model needs besides the model: its tables and scratch.

    The :class:`~skelid.model.description.Model` is a frozen description that no
    algorithm writes to; like pinocchio's ``Data`` beside its ``Model``, a
    workspace holds everything derived from it for computing: the
    :class:`KinematicsPlan` (built once, here) and, for the pose fits, the
    compiled kernel's tables and which path (compiled or numpy) they take. An
    estimator creates one per fit and passes it to every function it calls
    (the ``ws`` argument); a function called without one builds what it needs
    for that call.

    Parameters
    ----------
    model : Model
    compiled : bool
        Whether the pose fits of this workspace use the compiled kernel (decided
        once, by whoever creates it; see :func:`skelid.estimators.fit.pose.workspace`).

    Examples
    --------
    >>> from skelid.simulate import builtin_model
    >>> model = builtin_model("case-a")
    >>> ws = Workspace(model)
    >>> marker_positions(model, model.theta_center, [0.0] * model.n_pose, ws=ws).shape
    (3, 2)
    """

    def __init__(self, model: Model, compiled: bool = False):
        self.model = model
        self.plan = _build_plan(model)
        self.compiled = bool(compiled)
        self.kernel_tables = None  # set by skelid.estimators.fit.pose on the compiled path
        self.fk_tables = None  # the compiled kinematics' tables (False: numpy path), decided on first use

    @property
    def path(self) -> str:
        """``"compiled"`` or ``"numpy"``: the path of this workspace's pose fits."""
        return "compiled" if self.compiled else "numpy"

    def __repr__(self) -> str:
        return f"Workspace({self.model.name!r}, path={self.path!r})"


def kinematics_plan(model: Model, ws: Workspace | None = None) -> KinematicsPlan:
    """The pose-independent tables of ``model``: the workspace's, or built for this call.

    Raises
    ------
    ValueError
        If ``ws`` belongs to another model.
    """
    if ws is None:
        return _build_plan(model)
    if ws.model is not model and ws.model != model:
        raise ValueError(f"the workspace belongs to model {ws.model.name!r}, not {model.name!r}")
    return ws.plan


def _build_plan(model: Model) -> KinematicsPlan:
    """The :class:`KinematicsPlan` of ``model``: index tables, then the geometry map's parts, then custom joints."""
    D, S, M = model.dim, len(model.segments), len(model.markers)
    g_base, A = model.geometry_map
    P = A.shape[1]
    dof_segment, is_t, axis, skew = _dof_tables(model)
    seg_dofs, seg_rot, seg_trans = _segment_dofs(dof_segment, is_t, S)
    ms = np.asarray(model.marker_segment, dtype=int)
    A_joint = A[: S * D].reshape(S, D, P)
    A_mark = A[S * D:(S + M) * D].reshape(M, D, P)
    used_j = np.flatnonzero(np.abs(A_joint).sum(axis=(1, 2)))
    used_m = np.flatnonzero(np.abs(A_mark).sum(axis=(1, 2)))
    custom, orient = _custom_tables(model, seg_dofs)
    ct_seg = np.array([c[0] for c in model.coupled_translations], dtype=int)
    return KinematicsPlan(
        D, S, M, len(dof_segment), P, tuple(int(i) for i in model.parent_index), g_base, A, dof_segment, is_t,
        axis, skew, skew @ skew, seg_dofs, seg_rot, seg_trans, ms,
        np.asarray(model.dof_moves_marker, dtype=float), np.flatnonzero(~is_t), np.flatnonzero(is_t),
        used_j, A_joint[used_j], model.ancestor[used_j][:, ms].astype(float), used_m, A_mark[used_m],
        _dof_tilts(model), len(model.axis_tilts), _is_planar(model, seg_trans, seg_rot, len(dof_segment)), custom,
        orient, any(c is not None for c in custom) or any(o is not None for o in orient), ct_seg.size, ct_seg,
        model.ancestor[ct_seg][:, ms].astype(float) if ct_seg.size else np.zeros((0, M)))


def _dof_tables(model: Model) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per pose coordinate: its segment ``(Q,)``, whether it translates ``(Q,)``, its nominal axis ``(Q, D)``
    (zero for a planar rotation) and the cross-product matrix of a 3-D rotation's axis ``(Q, 3, 3)``."""
    dofs, D = model.dofs, model.dim
    axis = np.zeros((len(dofs), D))
    skew = np.zeros((len(dofs), 3, 3))
    for k, d in enumerate(dofs):
        if d.kind == "T" or D == 3:
            axis[k] = d.axis
        if d.kind == "R" and D == 3:
            skew[k] = _skew(np.asarray(d.axis, float))
    return (np.array([d.segment for d in dofs], dtype=int), np.array([d.kind == "T" for d in dofs], dtype=bool),
            axis, skew)


def _segment_dofs(dof_segment: np.ndarray, is_t: np.ndarray, S: int) -> tuple[tuple, tuple, tuple]:
    """Per segment, the indices of its pose coordinates, of its rotations and of its translations."""
    seg_dofs = tuple(tuple(int(k) for k in np.flatnonzero(dof_segment == i)) for i in range(S))
    return (seg_dofs, tuple(tuple(k for k in ks if not is_t[k]) for ks in seg_dofs),
            tuple(tuple(k for k in ks if is_t[k]) for ks in seg_dofs))


def _dof_tilts(model: Model) -> np.ndarray:
    """``(Q,)`` int: each pose coordinate's slot in :attr:`Model.axis_tilts`, -1 if its axis is fixed."""
    dof_tilt = np.full(model.n_pose, -1, dtype=int)
    for j, t in enumerate(model.axis_tilts):
        dof_tilt[t[0]] = j
    return dof_tilt


def _is_planar(model: Model, seg_trans: tuple, seg_rot: tuple, Q: int) -> bool:
    """2-D, no tilted axis, and every joint's translations before its rotation (the planar path's model)."""
    return model.dim == 2 and not model.axis_tilts and all(
        max(t, default=-1) < min(r, default=Q) for t, r in zip(seg_trans, seg_rot, strict=True))


def _custom_tables(model: Model, seg_dofs) -> tuple[tuple, tuple]:
    """Per segment: its custom joint's motions ``(is_translation, axis (3,), pose index or -1,
    function, slot in g's coupled factors or -1, K, K^2, carried)``, translations first; and its
    constant rotation. ``carried`` is None, or for a carried translation ``(v (3,), number of
    rotations before it)``."""
    slot = {(c[0], c[1]): n for n, c in enumerate(model.coupled_translations)}
    custom, orient = [], []
    for i, s in enumerate(model.segments):
        j = s.joint
        if j.type != "custom":
            custom.append(None)
            orient.append(None)
            continue
        rows = []
        for n, m in enumerate(j.motions):
            k = seg_dofs[i][m.coordinate] if m.coordinate >= 0 else -1
            a = np.asarray(m.axis, float)
            K = _skew(a)
            carried = None
            if m.kind == "C":
                carried = (np.asarray(m.vector, float), sum(1 for x in j.motions[:n] if x.kind == "R"))
            rows.append((m.kind != "R", a, k, m.function, slot.get((i, n), -1), K, K @ K, carried))
        rows.sort(key=lambda r: not r[0])  # translations first (stable: rotations keep their order)
        custom.append(tuple(rows))
        R = np.asarray(j.orientation, float).reshape(3, 3) if j.orientation else None
        orient.append(None if R is None or np.allclose(R, np.eye(3), atol=0, rtol=0) else R)
    return tuple(custom), tuple(orient)


def geometry(model: Model, theta) -> np.ndarray:
    """Geometry vector for parameter values.

    Parameters
    ----------
    theta : (..., P) float

    Returns
    -------
    g : (..., G) float
        Joint positions (S*D) then marker positions (M*D).
    """
    g_base, A = model.geometry_map
    theta = np.asarray(theta, dtype=float)
    if theta.shape[-1:] != (model.n_params,):
        raise ValueError(f"theta must end in {model.n_params} parameters, got shape {theta.shape}")
    return g_base + theta @ A.T


def _skew(a: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``(..., 3, 3)`` of vectors ``(..., 3)``."""
    a = np.asarray(a, dtype=float)
    K = np.zeros(a.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -a[..., 2], a[..., 1]
    K[..., 1, 0], K[..., 1, 2] = a[..., 2], -a[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -a[..., 1], a[..., 0]
    return K


def _rotation(dim: int, axis, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., D, D)`` by ``angle (...)`` about ``axis`` (3-D) or z (2-D).

    ``axis`` is a unit vector ``(3,)`` or a batch of them ``(..., 3)``.
    """
    c, s = np.cos(angle), np.sin(angle)
    if dim == 2:
        return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    K = _skew(np.asarray(axis, dtype=float))
    return np.eye(3) + s[..., None, None] * K + (1.0 - c)[..., None, None] * (K @ K)


def tilted_axes(model: Model, theta) -> tuple[np.ndarray, np.ndarray]:
    """Axes of the hinges that have ``axis_direction`` parameters.

    Parameters
    ----------
    theta : (..., P) float

    Returns
    -------
    axis : (..., T, 3) float
        Unit axis of each tilted hinge (in the frame it acts in), in the order
        of :attr:`Model.axis_tilts`.
    d_axis : (..., T, 2, 3) float
        Its derivatives with respect to the two tilts, per degree.
    """
    theta = np.asarray(theta, dtype=float)
    tilts = model.axis_tilts
    if not tilts:
        batch = theta.shape[:-1]
        return np.zeros(batch + (0, 3)), np.zeros(batch + (0, 2, 3))
    return tilted_axes_from(tilt_arrays(model), theta)


def _axis_cross(w: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``w x v`` for ``w (..., 1, 3)`` and ``v (..., M, 3)`` (what ``np.cross`` computes, with less overhead)."""
    out = np.empty(np.broadcast_shapes(w.shape, v.shape))
    w0, w1, w2 = w[..., 0], w[..., 1], w[..., 2]
    v0, v1, v2 = v[..., 0], v[..., 1], v[..., 2]
    out[..., 0] = w1 * v2 - w2 * v1
    out[..., 1] = w2 * v0 - w0 * v2
    out[..., 2] = w0 * v1 - w1 * v0
    return out


def _rotation_2d(c: np.ndarray, s: np.ndarray) -> np.ndarray:
    """``(..., 2, 2)`` rotation matrices from cosines and sines ``(...)``."""
    R = np.empty(c.shape + (2, 2))
    R[..., 0, 0] = c
    R[..., 0, 1] = -s
    R[..., 1, 0] = s
    R[..., 1, 1] = c
    return R


class TiltTables(NamedTuple):
    """The tilted hinge axes of a batch of ``theta`` (see :func:`tilt_tables`)."""

    axis: np.ndarray  # (..., T, 3) unit axis in the frame the hinge acts in
    d_axis: np.ndarray  # (..., T, 2, 3) its derivatives per degree of tilt
    skew: np.ndarray  # (..., T, 3, 3) cross-product matrix of the axis
    skew2: np.ndarray  # (..., T, 3, 3) its square


def tilt_tables(model: Model, theta) -> TiltTables | None:
    """Axes of the tilted hinges for ``theta (..., P)`` and their cross-product matrices.

    ``None`` when the model has no ``axis_direction`` parameter.
    """
    if not model.axis_tilts:
        return None
    axis, d_axis = tilted_axes(model, theta)
    K = _skew(axis)
    return TiltTables(axis, d_axis, K, K @ K)


def forward_kinematics(model: Model, theta, pose, ws: Workspace | None = None) -> Kinematics:
    """Segment frames, joint axes and marker positions.

    Parameters
    ----------
    model : Model
    theta : (..., P) float
        Parameter values.
    pose : (..., Q) float
        Pose coordinates (see the model's joint table); angles in radians.
    ws : Workspace, optional
        The model's workspace (its tables are built for this call without one).

    Returns
    -------
    Kinematics
        The orientation arrays of a planar model are read-only views (shared
        across batch axes that only ``theta`` spans).
    """
    plan = kinematics_plan(model, ws)
    g = geometry(model, theta)
    pose = np.asarray(pose, dtype=float)
    if pose.shape[-1:] != (plan.n_pose,):
        raise ValueError(f"pose must end in {plan.n_pose} coordinates, got shape {pose.shape}")
    if plan.planar:
        return _forward_planar(plan, g, pose)
    return _forward_general(plan, g, pose, tilt_tables(model, theta))


def _forward_planar(plan: KinematicsPlan, g: np.ndarray, pose: np.ndarray, markers_only: bool = False):
    """:func:`forward_kinematics` for a planar model: one angle per segment.

    ``markers_only``: return only the marker positions ``(..., M, 2)`` (what a residual needs).
    """
    S, M = plan.n_segments, plan.n_markers
    batch = np.broadcast_shapes(g.shape[:-1], pose.shape[:-1])
    gb = g.shape[:-1]
    offsets = g[..., : S * 2].reshape(gb + (S, 2))
    r_marker = g[..., S * 2:].reshape(gb + (M, 2))
    # segment angles along the tree; column S stays 0 and serves as the root's parent
    phi = np.zeros(pose.shape[:-1] + (S + 1,))
    u = np.empty(batch + (S, 2))  # joint offset plus translations, in the parent's frame
    u[...] = offsets
    for i in range(S):
        a = phi[..., plan.parent[i]]
        for k in plan.segment_rot[i]:
            a = a + pose[..., k]
        phi[..., i] = a
        for k in plan.segment_trans[i]:
            u[..., i, :] += plan.dof_axis[k] * pose[..., k, None]
    c, s = np.cos(phi), np.sin(phi)
    par = np.asarray(plan.parent)
    cp, sp = c[..., par], s[..., par]
    v = np.empty(batch + (S, 2))
    v[..., 0] = cp * u[..., 0] - sp * u[..., 1]
    v[..., 1] = sp * u[..., 0] + cp * u[..., 1]
    p = np.zeros(batch + (S + 1, 2))
    for i in range(S):
        p[..., i, :] = p[..., plan.parent[i], :] + v[..., i, :]
    p = p[..., :S, :]
    ms = plan.marker_segment
    cm, sm = c[..., ms], s[..., ms]
    x = np.empty(batch + (M, 2))
    x[..., 0] = p[..., ms, 0] + (cm * r_marker[..., 0] - sm * r_marker[..., 1])
    x[..., 1] = p[..., ms, 1] + (sm * r_marker[..., 0] + cm * r_marker[..., 1])
    if markers_only:
        return x
    Q = plan.n_pose
    axis = np.zeros(batch + (Q, 2))
    pivot = np.zeros(batch + (Q, 2))
    seg = plan.dof_segment
    cp, sp = np.broadcast_to(cp, batch + (S,)), np.broadcast_to(sp, batch + (S,))
    if plan.trans_dofs.size:
        t = plan.trans_dofs
        at = plan.dof_axis[t]
        ct, st = cp[..., seg[t]], sp[..., seg[t]]
        axis[..., t, 0] = ct * at[:, 0] - st * at[:, 1]
        axis[..., t, 1] = st * at[:, 0] + ct * at[:, 1]
    if plan.rot_dofs.size:
        pivot[..., plan.rot_dofs, :] = p[..., seg[plan.rot_dofs], :]
    # orientations depend on the pose only: shared (read-only) across the other batch axes
    R = np.broadcast_to(_rotation_2d(c[..., :S], s[..., :S]), batch + (S, 2, 2))
    Rpar = np.broadcast_to(_rotation_2d(cp, sp), batch + (S, 2, 2))
    return Kinematics(R, p, Rpar, axis, pivot, x, np.broadcast_to(g, batch + g.shape[-1:]),
                      np.zeros(batch + (0, 2, 2)))


def _forward_general(plan: KinematicsPlan, g: np.ndarray, pose: np.ndarray, tilt: TiltTables | None = None,
                     want_omega: bool = True) -> Kinematics:
    """:func:`forward_kinematics` for any model: products of elementary rotations.

    ``tilt`` (from :func:`tilt_tables`, batch axes broadcasting with ``g``) is
    required when the model has tilted hinges; ``want_omega=False`` leaves
    ``tilt_omega`` zero (a pose fit does not need it).
    """
    D, S, M, Q = plan.dim, plan.n_segments, plan.n_markers, plan.n_pose
    if plan.n_tilts and tilt is None:
        raise ValueError("a model with tilted hinge axes needs its tilt tables")
    batch = np.broadcast_shapes(g.shape[:-1], pose.shape[:-1])
    if plan.n_tilts:
        batch = np.broadcast_shapes(batch, tilt.axis.shape[:-2])
    gb = g.shape[:-1]
    offsets = g[..., : S * D].reshape(gb + (S, D))
    r_marker = g[..., S * D:(S + M) * D].reshape(gb + (M, D))
    factors = g[..., (S + M) * D:]
    eye = np.eye(D)
    velocity = np.zeros(batch + (Q, D)) if plan.has_custom else None
    shift = np.zeros(batch + (plan.n_coupled, D)) if plan.has_custom else None
    R = np.empty(batch + (S, D, D))
    p = np.empty(batch + (S, D))
    Rpar = np.empty(batch + (S, D, D))
    axis = np.zeros(batch + (Q, D))
    pivot = np.zeros(batch + (Q, D))
    omega = np.zeros(batch + (plan.n_tilts, 2, D))
    for i in range(S):
        par = plan.parent[i]
        Rp = eye if par < 0 else R[..., par, :, :]
        pp = 0.0 if par < 0 else p[..., par, :]
        Ri = Rp
        pi = pp + np.matmul(Rp, offsets[..., i, :, None])[..., 0]
        if plan.has_custom and plan.custom[i] is not None:
            Ri, pi = _custom_joint(plan.custom[i], Rp, pi, pose, factors, axis, pivot, velocity, shift)
            if plan.orientation[i] is not None:
                Ri = Ri @ plan.orientation[i]
            R[..., i, :, :] = Ri
            p[..., i, :] = pi
            Rpar[..., i, :, :] = Rp
            continue
        for k in plan.segment_dofs[i]:
            qk = pose[..., k]
            j = plan.dof_tilt[k]
            if plan.dof_is_t[k]:
                w = Ri @ plan.dof_axis[k]
                axis[..., k, :] = w
                pi = pi + w * qk[..., None]
            elif j >= 0:  # a hinge whose axis depends on theta
                w = np.matmul(Ri, tilt.axis[..., j, :, None])[..., 0]
                axis[..., k, :] = w
                pivot[..., k, :] = pi
                if want_omega:
                    dw = np.matmul(Ri[..., None, :, :], tilt.d_axis[..., j, :, :, None])[..., 0]
                    omega[..., j, :, :] = np.sin(qk)[..., None, None] * dw \
                        + (1.0 - np.cos(qk))[..., None, None] * _axis_cross(w[..., None, :], dw)
                Ri = Ri @ (eye + np.sin(qk)[..., None, None] * tilt.skew[..., j, :, :]
                           + (1.0 - np.cos(qk))[..., None, None] * tilt.skew2[..., j, :, :])
            else:
                if D == 3:
                    axis[..., k, :] = Ri @ plan.dof_axis[k]
                pivot[..., k, :] = pi
                if D == 2:
                    Ri = Ri @ _rotation(2, None, qk)
                else:
                    Ri = Ri @ (eye + np.sin(qk)[..., None, None] * plan.dof_skew[k]
                               + (1.0 - np.cos(qk))[..., None, None] * plan.dof_skew2[k])
        R[..., i, :, :] = Ri
        p[..., i, :] = pi
        Rpar[..., i, :, :] = Rp
    ms = plan.marker_segment
    x = p[..., ms, :] + np.matmul(R[..., ms, :, :], r_marker[..., None])[..., 0]
    return Kinematics(R, p, Rpar, axis, pivot, x, np.broadcast_to(g, batch + g.shape[-1:]), omega,
                      velocity, shift)


def _custom_joint(rows, Rp, p0, pose, factors, axis, pivot, velocity, shift):
    """Frame of a custom joint's child and its coordinates' Jacobian columns (written in place).

    Translations along ``Rp a`` by ``c f(q)`` (``c`` the parent's scale along
    ``a`` for a scaled coupled translation, else 1), then rotations by
    ``f(q)`` about axes carried by the earlier rotations. The column of a
    coordinate is ``omega x (x - pivot) + v`` with ``omega = sum f'(q) w`` over
    its rotations (world axes ``w``), ``v = sum c f'(q) Rp a`` over its
    translations and the pivot at the joint centre after the translations.
    A carried translation by ``c f (w . u)``, ``u = R_n v`` the vector turned by
    the first ``n`` rotations (world frame ``R_n``), adds
    ``c f w (w . (f'_j(q) w_j x u))`` to the column of each of those rotations ``j``.
    """
    Ri, frames, spins = _custom_rotations(rows, Rp, pose, axis)
    pi = p0
    for is_t, a, k, fun, slot, _K, _K2, carried in rows:
        if not is_t:
            continue
        w = Rp @ a
        if carried is not None:
            pi = pi + _carried_translation(w, fun, slot, carried, frames, spins, factors, velocity, shift)
            continue
        if fun.is_identity:  # a translational coordinate
            axis[..., k, :] = w
            pi = pi + w * pose[..., k, None]
            continue
        val, der = fun.value_and_derivative(pose[..., k] if k >= 0 else np.zeros(pose.shape[:-1]))
        c = factors[..., slot] if slot >= 0 else 1.0
        if slot >= 0:
            shift[..., slot, :] = w * val[..., None]
        pi = pi + w * (c * val)[..., None]
        if k >= 0:
            velocity[..., k, :] += w * (c * der)[..., None]
    for is_t, _a, k, fun, _slot, _K, _K2, _c in rows:
        if k >= 0 and not (is_t and fun.is_identity):
            pivot[..., k, :] = pi
    return Ri, pi


def _custom_rotations(rows, Rp, pose, axis):
    """The rotations of a custom joint: the child's frame, the frame after each rotation, and
    ``(pose index, world axis, derivative of the angle)`` of each (axes written into ``axis``)."""
    Ri = Rp
    frames, spins = [Rp], []
    for is_t, a, k, fun, _slot, K, K2, _c in rows:
        if is_t:
            continue
        w = Ri @ a
        if fun.is_identity:
            val, der = pose[..., k], None
            axis[..., k, :] = w
        else:
            val, der = fun.value_and_derivative(pose[..., k] if k >= 0 else np.zeros(pose.shape[:-1]))
            if k >= 0:
                axis[..., k, :] += w * der[..., None]
        spins.append((k, w, der))
        Ri = Ri @ (np.sin(val)[..., None, None] * K + (1.0 - np.cos(val))[..., None, None] * K2 + _EYE3)
        frames.append(Ri)
    return Ri, frames, spins


def _carried_translation(w, fun, slot, carried, frames, spins, factors, velocity, shift):
    """World shift ``c f (w . u) w`` of a carried translation (see :func:`_custom_joint`); its
    columns are added to ``velocity`` and its factor's derivative written into ``shift``."""
    v, n = carried
    u = frames[n] @ v
    f = float(fun.value(np.zeros(1))[0])
    c = factors[..., slot, None] if slot >= 0 else 1.0
    along = np.sum(w * u, axis=-1)[..., None]
    if slot >= 0:
        shift[..., slot, :] = w * (f * along)
    for k, wj, der in spins[:n]:
        if k < 0:
            continue
        d = np.sum(w * np.cross(wj, u), axis=-1)[..., None]
        if der is not None:
            d = d * der[..., None]
        velocity[..., k, :] += w * (c * f * d)
    return w * (c * f * along)


_EYE3 = np.eye(3)


def joint_distances(model: Model, theta) -> tuple[np.ndarray, np.ndarray]:
    """The model's derived lengths and their gradients.

    Parameters
    ----------
    theta : (..., P) float

    Returns
    -------
    lengths : (..., K) float
        ``|o_s(theta)|`` for each entry of :attr:`Model.derived_lengths` (at the zero pose, through the
        forward kinematics, for a joint centre that slides with a coordinate).
    grad : (..., K, P) float
        ``d lengths / d theta``.
    """
    D = model.dim
    g_base, A = model.geometry_map
    segs = [s for _, s in model.derived_lengths]
    theta = np.asarray(theta, dtype=float)
    if not segs:
        return np.zeros(theta.shape[:-1] + (0,)), np.zeros(theta.shape[:-1] + (0, model.n_params))
    rows = np.array([[s * D + d for d in range(D)] for s in segs])  # (K, D)
    o = g_base[rows] + np.einsum("kdp,...p->...kd", A[rows], theta)
    n = np.linalg.norm(o, axis=-1)
    grad = np.einsum("...kd,kdp->...kp", o / np.maximum(n, 1e-300)[..., None], A[rows])
    for k, s in enumerate(segs):
        cols = model.sliding_joint_parameters.get(s)
        if cols is not None:
            n[..., k], grad[..., k, :] = _sliding_distance(model, theta, s, cols)
    return n, grad


#: relative step of the central differences of :func:`_sliding_distance` (of each parameter's prior sd, or 1)
SLIDING_STEP = 1e-6


def _sliding_distance(model: Model, theta, s: int, cols) -> tuple[np.ndarray, np.ndarray]:
    """Distance ``(...)`` from segment ``s``'s parent's origin to its joint centre at the zero pose, whose
    translations follow functions of the coordinates, and its gradient ``(..., P)`` (central differences in
    the parameters ``cols`` that can move it; the rest leave it)."""
    P = model.n_params
    sd = np.array([p.prior.sd for p in model.parameters], float)
    h = SLIDING_STEP * np.where(np.isfinite(sd) & (sd > 0), sd, 1.0)[cols]
    steps = np.zeros((1 + 2 * len(cols), P))
    steps[1 + np.arange(len(cols)), cols] = h
    steps[1 + len(cols) + np.arange(len(cols)), cols] = -h
    th = theta[..., None, :] + steps  # (..., 1 + 2c, P)
    p = forward_kinematics(model, th, np.zeros(th.shape[:-1] + (model.n_pose,))).p_world_seg
    d = np.linalg.norm(p[..., s, :] - p[..., model.parent_index[s], :], axis=-1)  # (..., 1 + 2c)
    grad = np.zeros(theta.shape[:-1] + (P,))
    grad[..., cols] = (d[..., 1:1 + len(cols)] - d[..., 1 + len(cols):]) / (2.0 * h)
    return d[..., 0], grad


def marker_positions(model: Model, theta, pose, ws: Workspace | None = None) -> np.ndarray:
    """Marker positions ``(..., M, D)`` for ``theta (..., P)`` and ``pose (..., Q)``."""
    plan = kinematics_plan(model, ws)
    pose = np.asarray(pose, dtype=float)
    if pose.shape[-1:] != (plan.n_pose,):
        raise ValueError(f"pose must end in {plan.n_pose} coordinates, got shape {pose.shape}")
    g = geometry(model, theta)
    tables = _fk_tables(model, plan, ws)
    if tables is not None:
        return _fk_kernel.kinematics(model, plan, *tables, g, pose, theta, want_jac=False)[0]
    if plan.planar:  # the markers alone: no joint axes or orientations
        return _forward_planar(plan, g, pose, markers_only=True)
    return _forward_general(plan, g, pose, tilt_tables(model, theta), want_omega=False).markers


def joint_positions(model: Model, theta, pose, ws: Workspace | None = None) -> np.ndarray:
    """World positions ``(..., S, D)`` of every segment's joint centre."""
    return forward_kinematics(model, theta, pose, ws).p_world_seg


def pose_jacobian(model: Model, kin: Kinematics, ws: Workspace | None = None) -> np.ndarray:
    """``dx/dq`` as ``(..., M, D, Q)`` from a :class:`Kinematics`."""
    return pose_jacobian_from_plan(kinematics_plan(model, ws), kin)


def pose_jacobian_from_plan(plan, kin: Kinematics, mask=None) -> np.ndarray:
    """:func:`pose_jacobian` from the model's :func:`kinematics_plan`.

    ``mask`` ``(..., M)``, optional: the rows of markers where it is 0 (missing) are zeroed.
    """
    x = kin.markers  # (..., M, D)
    axis, pivot = kin.dof_axis, kin.dof_pivot  # (..., Q, D)
    batch = np.broadcast_shapes(x.shape[:-2], pivot.shape[:-2])
    M, D, Q = plan.n_markers, plan.dim, plan.n_pose
    # written straight into the (..., M, D, Q) layout: one pass per component, no transposed copy
    cols = np.empty(batch + (M, D, Q))
    rel = [x[..., :, None, d] - pivot[..., None, :, d] for d in range(D)]  # each (..., M, Q)
    if D == 2:
        cols[..., 0, :] = -rel[1]
        cols[..., 1, :] = rel[0]
    else:
        a = [axis[..., None, :, d] for d in range(3)]
        cols[..., 0, :] = a[1] * rel[2] - a[2] * rel[1]
        cols[..., 1, :] = a[2] * rel[0] - a[0] * rel[2]
        cols[..., 2, :] = a[0] * rel[1] - a[1] * rel[0]
    if plan.trans_dofs.size:
        t = plan.trans_dofs
        cols[..., t] = np.swapaxes(axis[..., t, :], -1, -2)[..., None, :, :]
    if kin.dof_velocity is not None:
        cols += np.swapaxes(kin.dof_velocity, -1, -2)[..., None, :, :]
    moves = plan.moves.T if mask is None else plan.moves.T * mask[..., :, None]  # (..., M, Q)
    cols *= moves[..., :, None, :]
    return cols


def pose_gradient(model: Model, kin: Kinematics, r) -> np.ndarray:
    """``J_pose^T r`` as ``(..., Q)`` without forming the Jacobian.

    With ``w_{km}`` = 1 if pose coordinate ``k`` moves marker ``m``, a
    rotation about the world axis ``a_k`` through ``p_k`` has column
    ``a_k x (x_m - p_k)``, so by the triple product

    .. math:: g_k = a_k \\cdot \\Big(\\sum_m w_{km}\\, x_m \\times r_m
              - p_k \\times \\sum_m w_{km}\\, r_m\\Big)

    (the z component of the planar cross products in 2-D), and a translation
    along ``a_k`` has ``g_k = a_k . sum_m w_km r_m``. The cost is
    ``O(Q M)`` per frame with no ``(Q, M, D)`` array.

    Parameters
    ----------
    kin : Kinematics
        Only ``dof_axis``, ``dof_pivot`` and ``markers`` are read.
    r : (..., M, D) float
        Residuals (zero where a marker is missing).

    Returns
    -------
    (..., Q) float
    """
    W = model.dof_moves_marker.astype(float)  # (Q, M)
    x = kin.markers
    r = np.asarray(r, float)
    s = np.einsum("km,...md->...kd", W, r)  # sum_m w r_m
    axis, pivot = kin.dof_axis, kin.dof_pivot
    if model.dim == 3:
        rot = np.einsum("km,...md->...kd", W, np.cross(x, r)) - np.cross(pivot, s)
        g_rot = np.einsum("...kd,...kd->...k", axis, rot)
    else:
        c = x[..., 0] * r[..., 1] - x[..., 1] * r[..., 0]
        g_rot = np.einsum("km,...m->...k", W, c) - (pivot[..., 0] * s[..., 1] - pivot[..., 1] * s[..., 0])
    g_trans = np.einsum("...kd,...kd->...k", axis, s)
    is_t = np.array([d.kind == "T" for d in model.dofs], dtype=bool)
    if kin.dof_velocity is not None:
        g_rot = g_rot + np.einsum("...kd,...kd->...k", kin.dof_velocity, s)
    return np.where(is_t, g_trans, g_rot)


def theta_jacobian(model: Model, kin: Kinematics, ws: Workspace | None = None) -> np.ndarray:
    """``dx/dtheta`` as ``(..., M, D, P)`` from a :class:`Kinematics`."""
    plan = kinematics_plan(model, ws)
    M, D, P = plan.n_markers, plan.dim, plan.n_params
    batch = kin.markers.shape[:-2]
    used_j = plan.used_joints
    if used_j.size:  # sum over the joints above each marker: one matrix product
        RA = np.matmul(kin.R_world_parent[..., used_j, :, :], plan.A_joint)  # (..., s, D, P)
        RA = np.broadcast_to(RA, batch + RA.shape[-3:]).reshape(batch + (used_j.size, D * P))
        J = np.matmul(plan.ancestor_markers.T, RA).reshape(batch + (M, D, P))
    else:
        J = np.zeros(batch + (M, D, P))
    used_m = plan.used_markers
    if used_m.size:
        J[..., used_m, :, :] += np.matmul(kin.R_world_seg[..., plan.marker_segment[used_m], :, :], plan.A_marker)
    if plan.n_coupled:
        # d x / d c = f(q) Rp a for the markers the translation moves; c = base + theta @ b
        _, A = model.geometry_map
        B = A[(plan.n_segments + plan.n_markers) * plan.dim:]  # (C, P)
        J += np.einsum("...cd,cm,cp->...mdp", kin.coupled_shift, plan.coupled_moves, B)
    for j, (k, ku, kv, *_) in enumerate(model.axis_tilts):
        moved = plan.moves[k][:, None]
        rel = kin.markers - kin.dof_pivot[..., k, None, :]
        for c, kp in enumerate((ku, kv)):
            if kp >= 0:
                J[..., kp] += _axis_cross(kin.tilt_omega[..., j, c, None, :], rel) * moved
    return J


def marker_jacobian(model: Model, theta, pose, ws: Workspace | None = None):
    """Marker positions and both Jacobians.

    Parameters
    ----------
    theta : (..., P) float
    pose : (..., Q) float
    ws : Workspace, optional

    Returns
    -------
    x : (..., M, D) float
        Marker positions.
    J_pose : (..., M, D, Q) float
        ``dx/dpose``.
    J_theta : (..., M, D, P) float
        ``dx/dtheta``.
    """
    if ws is None:
        ws = Workspace(model)
    tables = _fk_tables(model, ws.plan, ws)
    if tables is not None:
        return _fk_kernel.kinematics(model, ws.plan, *tables, geometry(model, theta), _kernel_pose(ws, pose), theta)
    kin = forward_kinematics(model, theta, pose, ws)
    return kin.markers, pose_jacobian(model, kin, ws), theta_jacobian(model, kin, ws)


def _kernel_pose(ws: Workspace, pose) -> np.ndarray:
    """``pose`` as a float array, checked against the plan's pose coordinates (the compiled path's input)."""
    pose = np.asarray(pose, dtype=float)
    if pose.shape[-1:] != (ws.plan.n_pose,):
        raise ValueError(f"pose must end in {ws.plan.n_pose} coordinates, got shape {pose.shape}")
    return pose


def stacked_jacobian(model: Model, theta, pose, ws: Workspace | None = None) -> np.ndarray:
    """Both Jacobians side by side, ``[dx/dtheta, dx/dq]``: ``(..., M, D, P + Q)``.

    What :func:`marker_jacobian` gives, concatenated (the compiled path writes them
    into one array).
    """
    if ws is None:
        ws = Workspace(model)
    tables = _fk_tables(model, ws.plan, ws)
    if tables is not None:
        return _fk_kernel.kinematics(model, ws.plan, *tables, geometry(model, theta), _kernel_pose(ws, pose), theta,
                                     stacked=True)[1]
    _, Jq, Jt = marker_jacobian(model, theta, pose, ws)
    return np.concatenate([Jt, Jq], axis=-1)


def _fk_tables(model: Model, plan: KinematicsPlan, ws: Workspace | None):
    """The compiled kinematics' tables and tilted-hinge tables for this call, or None for the numpy path.

    A planar model, or a spatial one without custom joints, takes the compiled path
    when numba can run it now (:func:`skelid.model._fk_kernel.ready`); a workspace
    decides once, on its first call, so that one fit never switches path halfway.
    """
    if not _fk_kernel.AVAILABLE:
        return None
    if ws is not None and ws.fk_tables is not None:
        return ws.fk_tables or None
    tables = _fk_kernel.plan_tables(plan) if _fk_kernel.ready(bool(plan.planar)) else None
    if tables is not None:
        tables = (tables, _fk_kernel.tilt_tables(model))
    if ws is not None:
        ws.fk_tables = tables if tables is not None else False
    return tables
