"""Synthetic trials, shared by tests, the demo and the benchmarks.

Motion: every pose coordinate follows a smooth random curve,

.. math:: u(t) = 0.7\\sin(2\\pi f_1 t + \\phi_1) + 0.3\\sin(2\\pi f_2 t + \\phi_2), \\qquad
          q(t) = c + a\\,u(t),

with frequencies drawn from 0.15-0.6 Hz and 0.6-1.5 Hz, so that a 5 s trial
sweeps each joint through its range a few times. A rotation with a range
``[lo, hi]`` (the joint's ``range`` in the model, degrees) has centre
``c = (lo + hi)/2`` and amplitude ``a = (hi - lo)/2``; root rotations swing
±25°, root translations ±20 % of the model's size. With ``hard_poses`` every
one-axis joint also passes through the straight position (0°) where markers on
either side of the joint line up with its centre; :func:`simulate_posture` keeps
every one-axis joint inside a given span instead (near the straight or the folded
pose, where the markers across the joint nearly line up and the per-frame pose is
ill-determined).

Noise: ``"iid"`` adds independent Gaussian noise of standard deviation
``sigma`` to every coordinate. ``"sta"`` adds soft-tissue artefact on top: each
marker drifts against its segment by an amount that depends on the angles of
the joints next to its segment and is correlated in time,

.. math:: \\delta_m(t) = \\sum_j b_{mj}\\,\\sin(q_j(t) + \\psi_{mj}) + s_m(t),

where ``b`` has norm ``sta_amplitude`` and ``s_m`` is a slow Gauss-Markov
process (time constant 0.5 s) of standard deviation ``sta_amplitude / 3``.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from skelid.data import MarkerData
from skelid.errors import ModelError
from skelid.estimators.fit.pose import _model_size, _rotation_ranges
from skelid.model.description import Model, load_model
from skelid.model.kinematics import marker_positions

BUILTIN_MODELS = {"case-a": "case_a.toml", "case-b": "case_b.toml"}


def builtin_model(name: str) -> Model:
    """One of the models that ship with skelid (``case-a``, ``case-b``)."""
    key = name.lower().replace("_", "-")
    if key not in BUILTIN_MODELS:
        raise ModelError(f"no built-in model {name!r}",
                         f"use one of: {', '.join(BUILTIN_MODELS)} or a .toml file")
    path = resources.files("skelid") / "models" / BUILTIN_MODELS[key]
    with resources.as_file(path) as p:
        return load_model(Path(p))


def resolve_model(name_or_path) -> Model:
    """A built-in model name, the path of a TOML model file, or an OpenSim ``.osim`` model.

    An ``.osim`` model comes with one scale factor per body that carries
    markers (:func:`skelid.io.osim.load_osim`; its MarkerSet found beside it
    when the model has none).
    """
    s = str(name_or_path)
    if s.lower().replace("_", "-") in BUILTIN_MODELS:
        return builtin_model(s)
    if s.lower().endswith(".osim"):
        from skelid.io.osim import load_osim

        return load_osim(s, scale="bodies", markers="none")
    return load_model(s)


@dataclass(frozen=True, eq=False)
class Trial:
    """A simulated trial: noisy data plus everything that produced it."""

    model: Model
    data: MarkerData
    theta: np.ndarray  # (P,) true parameters
    pose: np.ndarray  # (F, Q) true poses
    clean: np.ndarray  # (F, M, D) noise-free markers

    @property
    def truth(self) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.model.parameter_names, self.theta, strict=True)}


def simulate_motion(model: Model, n_frames: int, rate: float, rng: np.random.Generator,
                    hard_poses: bool = False) -> np.ndarray:
    """Smooth random poses ``(F, Q)`` (angles in radians)."""
    t = np.arange(n_frames) / rate
    ranges = _rotation_ranges(model)
    size = _model_size(model)
    q = np.empty((n_frames, model.n_pose))
    for k, d in enumerate(model.dofs):
        f1, f2 = rng.uniform(0.15, 0.6), rng.uniform(0.6, 1.5)
        p1, p2 = rng.uniform(0, 2 * np.pi, 2)
        u = 0.7 * np.sin(2 * np.pi * f1 * t + p1) + 0.3 * np.sin(2 * np.pi * f2 * t + p2)
        seg = model.segments[d.segment]
        if d.kind == "T":
            q[:, k] = 0.2 * size * u
        elif seg.joint.type == "free":
            q[:, k] = rng.uniform(-np.pi, np.pi) + np.radians(25.0) * u
        else:
            lo, hi = ranges[k]
            single = seg.joint.type in ("revolute", "hinge")
            if hard_poses and single:
                lo = min(lo, np.radians(-3.0))
                # sharpen the curve so it dwells near the straight position
                u = np.clip(1.3 * u, -1.0, 1.0)
            q[:, k] = 0.5 * (lo + hi) + 0.5 * (hi - lo) * u
    return q


def soft_tissue_artefact(model: Model, pose: np.ndarray, amplitude: float, rate: float,
                         rng: np.random.Generator) -> np.ndarray:
    """Marker drift ``(F, M, D)`` that follows neighbouring joint angles and is slow in time."""
    F, M, D = pose.shape[0], len(model.markers), model.dim
    if amplitude <= 0:
        return np.zeros((F, M, D))
    rot = np.array([d.kind == "R" and model.segments[d.segment].joint.type != "free"
                    for d in model.dofs])
    # joints next to each marker's segment: its own joint and its children's joints
    seg_of_dof = np.array([d.segment for d in model.dofs])
    parent = model.parent_index
    near = np.zeros((M, model.n_pose), dtype=bool)
    for m, s in enumerate(model.marker_segment):
        near[m] = rot & ((seg_of_dof == s) | (parent[seg_of_dof] == s))
    b = rng.normal(size=(M, model.n_pose, D)) * near[..., None]
    norm = np.linalg.norm(b.reshape(M, -1), axis=1)
    b *= (amplitude / np.where(norm > 0, norm, 1.0))[:, None, None]
    psi = rng.uniform(0, 2 * np.pi, size=(M, model.n_pose))
    angle_part = np.einsum("fmk,mkd->fmd", np.sin(pose[:, None, :] + psi[None]), b)
    # slow Gauss-Markov drift (AR(1), time constant 0.5 s)
    a = np.exp(-1.0 / (0.5 * rate))
    e = rng.normal(size=(F, M, D)) * (amplitude / 3.0) * np.sqrt(1 - a**2)
    s = np.empty((F, M, D))
    s[0] = rng.normal(size=(M, D)) * amplitude / 3.0
    for t in range(1, F):
        s[t] = a * s[t - 1] + e[t]
    return angle_part + s


def sta_rms(model: Model, amplitude: float) -> float:
    """Expected root-mean-square displacement of one marker coordinate under :func:`soft_tissue_artefact`.

    The angle part ``sum_j b_mj sin(q_j + psi_mj)`` has ``E ||b_m||^2 = amplitude^2`` spread over
    ``D`` coordinates and ``E sin^2 = 1/2``; the Gauss-Markov part has standard deviation
    ``amplitude / 3``: ``rms = amplitude * sqrt(1 / (2 D) + 1 / 9)``.
    """
    return float(amplitude * np.sqrt(1.0 / (2.0 * model.dim) + 1.0 / 9.0))


def simulate(model: Model, theta=None, n_frames: int = 500, rate: float = 100.0,
             sigma: float = 15.0, rng: np.random.Generator | None = None,
             hard_poses: bool = False, noise: str = "iid", sta_amplitude: float = 10.0) -> Trial:
    """Simulate a trial of ``model``.

    Parameters
    ----------
    model : Model
    theta : (P,) float, optional
        True parameters; defaults to the model's nominal geometry.
    n_frames : int
        Number of frames (500 in the seed method).
    rate : float
        Sampling rate in Hz.
    sigma : float
        Standard deviation of the i.i.d. Gaussian marker noise, model units (15 mm in the seed).
    rng : numpy.random.Generator
        Source of randomness (``default_rng(0)`` if not given).
    hard_poses : bool
        Make one-axis joints pass through the straight position.
    noise : {'iid', 'sta'}
        Independent Gaussian noise, or that plus soft-tissue artefact.
    sta_amplitude : float
        Soft-tissue artefact amplitude (model units) when ``noise='sta'``.

    Returns
    -------
    Trial
    """
    if noise not in ("iid", "sta"):
        raise ValueError(f"noise must be 'iid' or 'sta', got {noise!r}")
    rng = np.random.default_rng(0) if rng is None else rng
    theta = model.theta_nominal if theta is None else np.asarray(theta, dtype=float)
    pose = simulate_motion(model, n_frames, rate, rng, hard_poses)
    clean = marker_positions(model, theta, pose)
    noisy = clean + rng.normal(0.0, sigma, size=clean.shape)
    if noise == "sta":
        noisy = noisy + soft_tissue_artefact(model, pose, sta_amplitude, rate, rng)
    data = MarkerData(noisy, model.marker_names, rate, model.units, source="simulated")
    return Trial(model, data, theta, pose, clean)


def simulate_posture(model: Model, theta, n_frames: int, sigma: float, degrees: tuple[float, float],
                     rng: np.random.Generator, rate: float = 100.0) -> Trial:
    """A trial (i.i.d. noise) whose one-axis joints stay within ``degrees`` (e.g. near a singular pose).

    The motion is :func:`simulate_motion`'s, with each one-axis joint's curve rescaled
    to span ``degrees = (lo, hi)`` exactly.

    Returns
    -------
    Trial
    """
    theta = np.asarray(theta, dtype=float)
    pose = simulate_motion(model, n_frames, rate, rng)
    lo, hi = np.radians(degrees)
    for k, d in enumerate(model.dofs):
        if d.kind == "R" and model.segments[d.segment].joint.type in ("revolute", "hinge"):
            u = pose[:, k] - pose[:, k].min()
            pose[:, k] = lo + (hi - lo) * u / max(float(np.ptp(pose[:, k])), 1e-12)
    clean = marker_positions(model, theta, pose)
    noisy = clean + rng.normal(0.0, sigma, size=clean.shape)
    return Trial(model, MarkerData(noisy, model.marker_names, rate, model.units, source="simulated"),
                 theta, pose, clean)
