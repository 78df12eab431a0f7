"""Checks on a fit that say how far its numbers can be trusted.

**Joint range as a rotation angle.** A joint with two or three rotation axes
(universal, spherical) is described by its relative rotation
``R_t = R_{world,parent}^T R_{world,seg}`` at each frame. Its mean ``R_bar``
(the chordal L2 mean, :meth:`scipy.spatial.transform.Rotation.mean`) is the
joint's typical posture, and the joint's excursion at frame ``t`` is the
rotation angle

.. math:: \\alpha_t = \\lVert \\log(\\bar R^\\top R_t) \\rVert ,

which, unlike Euler angles, does not swing through 180 degrees near gimbal lock.
The reported range is ``2 * quantile_{0.95}(alpha)``: the opening of the cone
(about the mean posture) holding 95 % of the frames, which for a one-axis joint
swinging symmetrically equals its range of motion. One-axis joints (and every
joint of a planar model) keep the central 95 % range of their angle about its
circular mean.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from skelid.model.description import Model
from skelid.model.kinematics import forward_kinematics

#: the range of a multi-axis joint is twice this quantile of its rotation angle from the mean
RANGE_QUANTILE = 0.95


def joint_ranges(model: Model, pose, used=None, theta=None) -> dict[str, list[float]]:
    """Range of every joint rotation but the root's, in degrees.

    Parameters
    ----------
    pose : (T, Q) float
    used : (T,) bool, optional
        Frames to include.
    theta : (P,) float, optional
        Parameters (they matter only for tilted hinge axes); default the prior centres.

    Returns
    -------
    dict
        joint name -> ``[range]`` for a multi-axis joint of a 3-D model (rotation angle,
        see the module notes), or one range per rotation coordinate otherwise.
    """
    pose = np.asarray(pose, float)
    if used is not None:
        pose = pose[np.asarray(used, bool)]
    out: dict[str, list[float]] = {}
    if len(pose) == 0:
        return out
    kin = None
    for s, seg in enumerate(model.segments):
        if seg.parent is None:
            continue
        ks = [k for k, d in enumerate(model.dofs) if d.segment == s and d.kind == "R"]
        if not ks:
            continue
        if model.dim == 3 and len(ks) > 1:
            if kin is None:
                th = model.theta_center if theta is None else np.asarray(theta, float)
                kin = forward_kinematics(model, th, pose)
            R_rel = np.swapaxes(kin.R_world_parent[:, s], -1, -2) @ kin.R_world_seg[:, s]
            rot = Rotation.from_matrix(R_rel)
            alpha = (rot.mean().inv() * rot).magnitude()
            out[seg.joint.name] = [round(float(np.degrees(2.0 * np.quantile(alpha, RANGE_QUANTILE))), 2)]
            continue
        z = np.exp(1j * pose[:, ks])
        ang = np.angle(z * np.conj(z.mean(axis=0)))  # about the circular mean, in (-pi, pi]
        lo, hi = np.percentile(ang, [2.5, 97.5], axis=0)
        out[seg.joint.name] = [round(float(v), 2) for v in np.degrees(hi - lo)]
    return out
