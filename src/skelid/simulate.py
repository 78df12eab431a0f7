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
from skelid.errors import ModelError, SettingError, SkelidError
from skelid.estimators.fit.pose import _model_size, _rotation_ranges
from skelid.model.description import Model, load_model
from skelid.model.kinematics import marker_positions

BUILTIN_MODELS = {"case-a": "case_a.toml", "case-b": "case_b.toml"}


def builtin_model(name: str) -> Model:
    """One of the models that ship with skelid (``case-a``, ``case-b``)."""
    key = name.lower().replace("_", "-") if isinstance(name, str) else None
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
    """Smooth random poses ``(F, Q)`` (angles in radians).

    Raises
    ------
    SettingError
        ``n_frames < 1`` or not an integer, a rate outside :data:`skelid.data.RATE_RANGE`,
        an ``rng`` that is not a :class:`numpy.random.Generator`, in one line.
    ModelError
        ``model`` is not a :class:`~skelid.model.description.Model`.
    """
    _check_model(model, "simulate_motion")
    _check_n_frames(n_frames)
    rate = _check_rate(rate)
    _check_generator(rng)
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
    """Marker drift ``(F, M, D)`` that follows neighbouring joint angles and is slow in time.

    Parameters
    ----------
    pose : (F, Q) float
        Poses of ``model`` (angles in radians), e.g. from :func:`simulate_motion`.
    amplitude : float
        Norm of each marker's angle coefficients, model units (>= 0; 0 gives no drift).

    Raises
    ------
    SettingError
        A pose array that is not ``(F, Q)`` finite numbers, an amplitude that is negative or not
        finite, a rate outside :data:`skelid.data.RATE_RANGE`, an ``rng`` that is not a
        :class:`numpy.random.Generator`, in one line.
    ModelError
        ``model`` is not a :class:`~skelid.model.description.Model`.
    """
    _check_model(model, "soft_tissue_artefact")
    pose = _check_pose(model, pose)
    _check_level("amplitude", amplitude, model)
    rate = _check_rate(rate)
    _check_generator(rng)
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
    _check_model(model, "sta_rms")
    _check_level("amplitude", amplitude, model)
    return float(amplitude * np.sqrt(1.0 / (2.0 * model.dim) + 1.0 / 9.0))


def _is_number(v) -> bool:
    return isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool | np.bool_) \
        and bool(np.isfinite(v))


def _pair(v, name: str) -> tuple[float, float]:
    try:
        lo, hi = v
    except (TypeError, ValueError):
        raise SettingError(f"{name}={v!r} is not a pair of numbers", f"give {name} as (lower, upper)") from None
    if not (_is_number(lo) and _is_number(hi)):
        raise SettingError(f"{name}={v!r} is not a pair of finite numbers", f"give {name} as (lower, upper)")
    return float(lo), float(hi)


def _check_model(model, who: str) -> Model:
    from skelid.estimators.base import check_model

    return check_model(model, who)


def _check_n_frames(n_frames) -> int:
    if not (isinstance(n_frames, int | np.integer) and not isinstance(n_frames, bool) and n_frames >= 1):
        raise SettingError(f"n_frames={n_frames!r} is not a number of frames", "give an integer >= 1")
    return int(n_frames)


def _check_rate(rate) -> float:
    from skelid.data import check_rate

    try:
        return check_rate(rate, "simulate")
    except SkelidError as exc:
        raise SettingError(exc.problem, exc.fix) from None


def _check_level(name: str, v, model: Model) -> float:
    """A noise or artefact level: a finite number >= 0 in model units."""
    if not (_is_number(v) and v >= 0):
        raise SettingError(f"{name}={v!r} is not a noise level", f"give {name} as a finite number >= 0 "
                           f"in {model.units}")
    return float(v)


def _check_generator(rng) -> np.random.Generator:
    if not isinstance(rng, np.random.Generator):
        raise SettingError(f"rng={rng!r} is not a numpy.random.Generator",
                           "give rng=numpy.random.default_rng(seed)")
    return rng


def _check_pose(model: Model, pose) -> np.ndarray:
    try:
        q = np.asarray(pose)
    except (TypeError, ValueError):
        q = None
    if q is None or q.dtype.kind not in "iuf" or q.ndim != 2 or q.shape[1] != model.n_pose \
            or not np.isfinite(q).all():
        shape = "" if q is None else f" of shape {q.shape}"
        raise SettingError(f"pose{shape} is not (frames, {model.n_pose}) real, finite numbers for model {model.name!r}",
                           "give the poses simulate_motion(model, ...) returns")
    return q.astype(float)


def check_simulation(model, theta, n_frames, rate, sigma, rng, noise: str = "iid", sta_amplitude: float = 0.0,
                     hard_poses: bool = False, nominal: bool = True) -> tuple[np.ndarray, np.random.Generator]:
    """The checks of :func:`simulate`'s arguments: ``(theta (P,), rng)``, or a one-line :class:`SettingError`
    (:class:`ModelError` for something that is not a model)."""
    _check_model(model, "simulate")
    _check_n_frames(n_frames)
    _check_rate(rate)
    for name, v in (("sigma", sigma), ("sta_amplitude", sta_amplitude)):
        _check_level(name, v, model)
    if not isinstance(noise, str) or noise not in ("iid", "sta"):
        raise SettingError(f"noise={noise!r} is not a noise model", "give noise='iid' or noise='sta'")
    if not isinstance(hard_poses, bool | np.bool_):
        raise SettingError(f"hard_poses={hard_poses!r} is not True or False", "give hard_poses=True or False")
    rng = np.random.default_rng(0) if rng is None else _check_generator(rng)
    if theta is None and nominal:
        return model.theta_nominal, rng
    if theta is None:
        raise SettingError("theta=None: the true parameters are needed here",
                           f"give {model.n_params} values, one per parameter {list(model.parameter_names)} "
                           "(e.g. model.theta_nominal)")
    try:
        th = np.array(theta, dtype=float)
    except (TypeError, ValueError):
        raise SettingError(f"theta={theta!r} is not an array of numbers",
                           f"give {model.n_params} values, one per parameter {list(model.parameter_names)}") from None
    if th.shape != (model.n_params,) or not np.isfinite(th).all():
        raise SettingError(f"theta of shape {th.shape} does not fit model {model.name!r} "
                           f"({model.n_params} parameters), or is not finite",
                           f"give {model.n_params} finite values, one per parameter {list(model.parameter_names)}")
    return th, rng


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

    Raises
    ------
    SettingError
        An argument out of its range (``n_frames < 1``, ``sigma < 0``, a rate outside
        :data:`skelid.data.RATE_RANGE`, a ``theta`` of the wrong length, ...), in one line.
    ModelError
        ``model`` is not a :class:`~skelid.model.description.Model`.
    """
    theta, rng = check_simulation(model, theta, n_frames, rate, sigma, rng, noise=noise, sta_amplitude=sta_amplitude,
                                  hard_poses=hard_poses)
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

    Raises
    ------
    SettingError
        An argument out of its range (``n_frames < 1``, ``sigma < 0``, a rate outside
        :data:`skelid.data.RATE_RANGE`, a ``theta`` of the wrong length, ...), in one line.
    ModelError
        ``model`` is not a :class:`~skelid.model.description.Model`.
    """
    theta, rng = check_simulation(model, theta, n_frames, rate, sigma, rng, nominal=False)
    lo_deg, hi_deg = _pair(degrees, "degrees")
    if not lo_deg < hi_deg:
        raise SettingError(f"simulate_posture degrees=({lo_deg:g}, {hi_deg:g}) is not an interval",
                           "give (lower, upper) in degrees with lower < upper")
    degrees = (lo_deg, hi_deg)
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
