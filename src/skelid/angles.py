"""Joint angles of a fitted OpenSim model, with the uncertainty of the geometry carried into them.

For a trial of ``F`` frames and the geometry ``theta`` (body scales and marker
offsets, :mod:`skelid.scaling`) each frame's pose is the least-squares fit of
the model's markers to the observed ones (what OpenSim's inverse kinematics
computes with every marker weight 1),

.. math:: \\hat q_t(\\theta) = \\arg\\min_q \\sum_{m} \\lVert y_{tm} - x_m(q, \\theta)\\rVert^2 .

Two sources of uncertainty reach an angle:

* **the geometry**: ``theta`` is known to its posterior, approximately
  ``N(theta_hat, Sigma_theta)`` (the Laplace covariance of the joint fit of
  scales and offsets, :attr:`skelid.scaling.JointOffsets.cov`). Draws
  ``theta_d ~ N(theta_hat, Sigma_theta)`` (clipped to the priors' support) are
  each fitted again, every frame of every draw in one batched pose fit started
  from ``hat q_t``; the spread of ``hat q_t(theta_d)`` over the draws is the
  geometry's variance ``v^geo_tc``. Its first-order form,
  ``G_t Sigma_theta G_t^T`` with ``G_t = -(J_q^T J_q)^{-1} J_q^T J_theta``,
  is computed beside it (``sd_geometry_linear``) as a check of the draws.
* **the markers of the frame**: with noise ``sigma`` per marker coordinate the
  pose fit's own covariance is ``sigma^2 (J_q^T J_q)^{-1}`` at the fit
  (``v^pose_tc``, its diagonal), ``sigma`` estimated from the trial's residuals
  on ``sum_t (3 M_t - Q)`` degrees of freedom.

The two are taken as independent (the geometry comes from the fit's frames, the
noise from this frame's markers; for a trial that was part of the fit they are
not exactly so, and that correlation is neglected), so

.. math:: \\mathrm{sd}_{tc} = \\sqrt{v^{geo}_{tc} + v^{pose}_{tc}}, \\qquad
          \\text{geometry share}_c = \\frac{\\sum_t v^{geo}_{tc}}{\\sum_t (v^{geo}_{tc} + v^{pose}_{tc})}.

The covariance is the one the fit reports (its intervals in ``scaled_scaling.json``): the joint
fit's Laplace covariance widened, parameter by parameter, where the fit's checks found model misfit
or serially correlated residuals. :meth:`FittedGeometry.laplace` gives the covariance before that
widening (``skelid ik --covariance laplace``), to see how much of an angle's sd the widening makes.

Every coordinate of the OpenSim model is reported (:func:`skelid.io.osim.osim_coordinates`):
a locked one at its default value with sd 0 (as OpenSim's IK holds it), one that no marker
reaches (a body without markers, left out of skelid's model) at its default value with
sd NaN (the data say nothing about it). A frame whose markers do not fix the pose
gets NaN for every coordinate. The pose fit is unconstrained: where a coordinate OpenSim clamps
lies outside its range, OpenSim's IK would hold it at the bound; those frames are counted
(``frames_outside_range``), not moved.

Files (:func:`write_ik`): ``<trial>.mot`` (OpenSim's motion format, rotational coordinates in
degrees, ``inDegrees=yes``, read by ``opensim.TimeSeriesTable``), ``<trial>_sd.mot`` (the total
sd, same units) and ``ik.json`` (per trial and coordinate: mean sd, pose and geometry parts,
geometry share, the draws and the noise level).

Examples
--------
Markers of a two-body chain seen without noise give back its pose: the slide in metres,
the rotation in radians (degrees in the ``.mot`` file).

>>> import numpy as np
>>> from skelid.model import model_from_dict
>>> from skelid.io.osim import OsimCoordinate
>>> m = model_from_dict({"model": {"name": "arm", "dim": 3, "units": "mm"},
...     "segments": [{"name": "a", "parent": "ground", "joint": {"type": "custom", "name": "root",
...                   "coordinates": ["tx"], "motions": [{"kind": "translation", "axis": [1, 0, 0], "coordinate": "tx",
...                                "function": {"type": "linear", "coefficients": [1, 0]}}]}},
...                  {"name": "b", "parent": "a", "joint": {"type": "custom", "name": "elbow",
...                   "position": [0, 0, 0], "coordinates": ["flex"],
...                   "motions": [{"kind": "rotation", "axis": [0, 0, 1], "coordinate": "flex",
...                                "function": {"type": "linear", "coefficients": [1, 0]}}]}}],
...     "markers": [{"name": "a1", "segment": "a", "position": [0, 10, 0]},
...                 {"name": "b1", "segment": "b", "position": [300, 0, 0]},
...                 {"name": "b2", "segment": "b", "position": [150, 20, 0]}]})
>>> coords = (OsimCoordinate("tx", "root", False, False, 0.0), OsimCoordinate("flex", "elbow", True, False, 0.0))
>>> geom = FittedGeometry(m, np.zeros(0), np.zeros((0, 0)), "none", coords, None, "arm.osim")
>>> from skelid.data import MarkerData
>>> from skelid.model.kinematics import marker_positions
>>> q = np.array([[5.0, 0.3], [6.0, 0.5], [7.0, 0.7]])
>>> y = marker_positions(m, np.zeros(0), q)
>>> out = joint_angles(geom, MarkerData(y, m.marker_names, 100.0, "mm"), n_draws=0)
>>> np.round(np.degrees(out.value[:, 1]), 6).tolist()
[17.188734, 28.64789, 40.107046]
>>> np.round(out.value[:, 0], 9).tolist()
[0.005, 0.006, 0.007]
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from skelid._linalg import frame_gram
from skelid._stop import interruptible
from skelid.data import MarkerData, unit_scale
from skelid.errors import DataError, FormatError, SettingError
from skelid.io.osim import OsimCoordinate
from skelid.model.description import Model

#: the file ``skelid fit MODEL.osim --out DIR`` writes for ``skelid ik``: ``<name>_geometry.json``
GEOMETRY_SUFFIX = "_geometry.json"
GEOMETRY_FORMAT = "skelid-osim-geometry"
GEOMETRY_VERSION = 1
#: draws of the geometry by default
N_DRAWS = 100
#: most pose fits (draws x frames) in one batch: bounds the memory of the Jacobians
BATCH_POSES = 4000
#: Levenberg-Marquardt iterations of a draw's pose fit (it starts at the MAP pose, a small step away) ...
DRAW_ITER = 15
#: ... taken this many at a time, after which the fits that have converged are set aside (:func:`_refit_draws`)
DRAW_ROUND = 3
#: ... converged: the residual sum of squares fell by at most this share of it over a round. The draws' spread is
#: what is wanted, known to 7 % at 100 draws: on subject01's walk (100 draws) every coordinate's geometry sd is
#: within 0.25 % of the fits run to a fall of 1e-10 all together, and `skelid ik` took 1.02 s CPU against 1.60
DRAW_TOL = 1e-4
MM_PER_M = 1000.0

_REFIT = "fit the model again with 'skelid fit MODEL.osim STATIC.trc TRIAL.trc --out DIR' (a current skelid)"


@dataclass(frozen=True)
class FittedGeometry:
    """What joint angles need from a fit: the model, its fitted parameters and their covariance.

    ``model`` carries the scale and offset parameters (millimetres); ``theta (P,)`` their
    values, ``cov (P, P)`` their posterior covariance; ``covariance`` says where it comes
    from (``"joint"``: the joint fit's Laplace covariance; ``"diagonal"``: each parameter's
    sd with the correlations unknown; ``"none"``: no parameters); ``coordinates`` every
    coordinate of the OpenSim model; ``sigma`` the fit's marker noise (mm), or None.
    """

    model: Model
    theta: np.ndarray
    cov: np.ndarray
    covariance: str
    coordinates: tuple[OsimCoordinate, ...]
    sigma: float | None
    source: str
    widening: np.ndarray | None = None  # (P,) how much the fit's checks widened each sd (None: not at all)
    places: str = "zero pose"  # where the marker offsets put the markers: "zero pose" or "mean over the trials"

    def laplace(self) -> FittedGeometry:
        """The geometry with the joint fit's Laplace covariance before its checks widened it."""
        if self.widening is None or not np.any(self.widening != 1.0):
            return self
        w = np.asarray(self.widening, float)
        return replace(self, cov=self.cov / np.outer(w, w), covariance=f"{self.covariance}, laplace",
                       widening=None)


def fitted_geometry(fit) -> FittedGeometry:
    """The geometry of a :class:`~skelid.scaling.ScalingFit` with its covariance.

    The joint fit's covariance where the fit has one (``fit.joint``); otherwise each
    parameter's sd from the result, without correlations (``covariance="diagonal"``).
    Where the fit estimated a slide of the markers on their bodies, each marker sits where the
    slide puts it on average over the trials (``artefact.mean_place_mm``, the place the written
    ``.osim`` gives it; the offsets' priors move with them), not at its zero-pose place: on
    subject01's walk the markers' rms residual is then 13 mm, against 27 mm at the zero-pose
    places, and the knee and hip angles move by 3-5 degrees. The covariance stays the offsets':
    a mean place is known better than the zero-pose place it is carried from, so the geometry's
    part of an angle's sd errs wide there.
    """
    from skelid.io.osim import mean_places, offsets_moved, osim_coordinates

    model, theta = fit.model, np.asarray(fit.theta, float)
    places = mean_places(fit)
    if places:
        model, theta = offsets_moved(model, theta, places)
    widening = None
    if fit.joint is not None and np.shape(fit.joint.cov) == (model.n_params, model.n_params):
        cov, kind = np.asarray(fit.joint.cov, float), "joint"
        widening = np.array([float((fit.result.get(p.name) or {}).get("widened_by_checks") or 1.0)
                             for p in model.parameters])
    elif model.n_params:
        sd = np.array([float((fit.result.get(p.name) or {}).get("sd", np.nan)) for p in model.parameters])
        sd = np.where(np.isfinite(sd), sd, 0.0)
        cov, kind = np.diag(sd**2), "diagonal"
    else:
        cov, kind = np.zeros((0, 0)), "none"
    sig = fit.result.get("sigma")
    sigma = sig.get("value") if isinstance(sig, dict) else sig
    sigma = float(sigma) if isinstance(sigma, int | float) and np.isfinite(sigma) else None
    return FittedGeometry(model, theta, 0.5 * (cov + cov.T), kind, osim_coordinates(fit.source), sigma,
                          str(fit.source), widening, "mean over the trials" if places else "zero pose")


def geometry_document(geom: FittedGeometry) -> dict:
    """The JSON document of ``geom`` (:func:`read_geometry` reads it back)."""
    return {"format": GEOMETRY_FORMAT, "version": GEOMETRY_VERSION, "source_model": geom.source,
            "model": geom.model.to_dict(), "parameters": list(geom.model.parameter_names),
            "theta": [float(v) for v in geom.theta], "cov": [[float(v) for v in row] for row in geom.cov],
            "covariance": geom.covariance, "sigma_mm": geom.sigma, "marker_places": geom.places,
            "widening": [1.0] * geom.model.n_params if geom.widening is None else [float(v) for v in geom.widening],
            "coordinates": [c._asdict() for c in geom.coordinates]}


def write_geometry(geom: FittedGeometry, out_dir, name: str = "scaled") -> Path:
    """Write ``<name>_geometry.json`` into ``out_dir`` (atomically)."""
    from skelid.io.results import write_json

    return write_json(Path(out_dir) / f"{name}{GEOMETRY_SUFFIX}", geometry_document(geom))


def find_geometry(result_dir) -> Path:
    """The geometry file of an OpenSim fit's result folder; one line naming what is wrong otherwise."""
    d = Path(result_dir)
    if not d.is_dir():
        raise DataError(f"result folder {d} does not exist" if not d.exists() else f"{d} is not a folder",
                        "give the folder 'skelid fit MODEL.osim ... --out DIR' wrote")
    found = sorted(d.glob(f"*{GEOMETRY_SUFFIX}"))
    if len(found) == 1:
        return found[0]
    if len(found) > 1:
        raise DataError(f"{d} holds {len(found)} geometry files ({', '.join(f.name for f in found)})",
                        "keep one fit per result folder")
    if any(d.glob("*_scaling.json")):
        raise DataError(f"{d} holds an OpenSim fit written before skelid kept its geometry for joint angles",
                        _REFIT)
    if (d / "result.json").is_file():
        raise DataError(f"{d} holds the fit of a .toml model; joint angles are computed for OpenSim models",
                        "fit an .osim model with 'skelid fit MODEL.osim STATIC.trc TRIAL.trc --out DIR'")
    raise DataError(f"{d} is not a result folder of skelid (no {GEOMETRY_SUFFIX.lstrip('_')} file)",
                    "give the folder 'skelid fit MODEL.osim ... --out DIR' wrote")


def _bound(v) -> float:
    """A range bound as JSON holds it (None: unbounded, JSON has no infinity)."""
    return float(v) if v is not None else float("nan")


def read_geometry(result_dir) -> FittedGeometry:
    """The :class:`FittedGeometry` in an OpenSim fit's result folder, every part checked.

    Raises
    ------
    DataError
        The folder is not an OpenSim fit's (or is one from before the geometry was kept).
    FormatError
        The geometry file is damaged (names the key).
    """
    from skelid.errors import SkelidError
    from skelid.io.results import load_json

    path = find_geometry(result_dir)
    doc = load_json(path)

    def bad(what):
        return FormatError(f"{path}: {what}", _REFIT)

    if not isinstance(doc, dict) or doc.get("format") != GEOMETRY_FORMAT:
        raise bad(f"not a skelid geometry file (format should be {GEOMETRY_FORMAT!r})")
    if doc.get("version") != GEOMETRY_VERSION:
        raise bad(f"version {doc.get('version')!r}; this skelid reads version {GEOMETRY_VERSION}")
    try:
        model, theta, cov, coords, widening, kind, sigma = _geometry_entries(doc, str(path))
    except SkelidError as exc:
        raise bad(f"its model does not load ({exc.problem})") from None
    except (KeyError, TypeError, ValueError) as exc:
        raise bad(f"missing or malformed entry ({type(exc).__name__}: {str(exc)[:80]})") from None
    problem = _geometry_problem(doc, model, theta, cov, coords, widening)
    if problem:
        raise bad(problem)
    return FittedGeometry(model, theta, cov, kind, coords, sigma, str(doc.get("source_model", "")), widening,
                          str(doc.get("marker_places", "zero pose")))


def _geometry_entries(doc: dict, source: str) -> tuple:
    """The geometry file's entries as read: ``(model, theta, cov, coordinates, widening, kind, sigma)``.

    Raises KeyError, TypeError or ValueError where an entry is missing or malformed, and the
    model's own error where it does not load.
    """
    from skelid.model import model_from_dict

    model = model_from_dict(doc["model"], source)
    theta = np.asarray(doc["theta"], float)
    cov = np.asarray(doc["cov"], float).reshape(theta.size, theta.size) if theta.size else np.zeros((0, 0))
    coords = tuple(OsimCoordinate(str(c["name"]), str(c["joint"]), bool(c["rotational"]), bool(c["locked"]),
                                  float(c["default"]), tuple(_bound(v) for v in c["range"]), bool(c["clamped"]))
                   for c in doc["coordinates"])
    if any(len(c.range) != 2 for c in coords):
        raise ValueError("a coordinate's range is not two numbers")
    sigma = doc.get("sigma_mm")
    return (model, theta, cov, coords, np.asarray(doc["widening"], float), str(doc["covariance"]),
            None if sigma is None else float(sigma))


def _geometry_problem(doc: dict, model, theta, cov, coords, widening) -> str | None:
    """What is inconsistent in a geometry file's entries (one line), or None."""
    if tuple(doc.get("parameters", ())) != model.parameter_names or theta.size != model.n_params \
            or widening.shape != theta.shape or not np.all(np.isfinite(widening) & (widening > 0)):
        return "its parameters do not match its model"
    if not (np.isfinite(theta).all() and np.isfinite(cov).all()) or (cov.size and np.linalg.eigvalsh(
            0.5 * (cov + cov.T)).min() < -1e-9 * max(float(np.abs(cov).max()), 1e-300)):
        return "its parameters or covariance are not finite, or the covariance is not positive semi-definite"
    known = {c.name for c in coords}
    missing = [n for s in model.segments for n in s.joint.coordinates if n not in known]
    if missing:
        return f"coordinates {', '.join(missing[:3])} of its model are not in its coordinate list"
    return None


# ----------------------------------------------------------------------------- the angles
@dataclass(frozen=True)
class JointAngles:
    """Every OpenSim coordinate of a trial, frame by frame, with its uncertainty.

    Arrays are ``(F, C)`` over frames and the coordinates ``names``, in OpenSim units
    (radians for ``rotational`` coordinates, metres for the others); NaN in a frame whose
    pose the markers do not fix. ``sd`` is the total, ``sd_pose`` the part of the frame's
    marker noise, ``sd_geometry`` that of the geometry (from ``n_draws`` draws; the first-order
    form without draws), ``sd_geometry_linear`` the first-order form always.
    """

    names: tuple[str, ...]
    rotational: np.ndarray  # (C,) bool
    time: np.ndarray  # (F,)
    value: np.ndarray
    sd: np.ndarray
    sd_pose: np.ndarray
    sd_geometry: np.ndarray
    sd_geometry_linear: np.ndarray
    fixed: np.ndarray  # (F,) bool: the markers fix the pose
    status: tuple[str, ...]  # per coordinate: "fitted", "locked" or "no markers"
    sigma: float  # marker noise of the trial (mm) used for sd_pose
    n_draws: int
    covariance: str
    outside_range: np.ndarray  # (C,) int: frames where a clamped coordinate lies outside its range
    source: str = ""

    def geometry_share(self) -> np.ndarray:
        """(C,) share of each coordinate's angle variance (summed over the frames) from the geometry."""
        g = np.nansum(self.sd_geometry**2, axis=0)
        t = np.nansum(self.sd**2, axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(t > 0, g / t, np.nan)

    def summary(self) -> dict:
        """Per coordinate: mean value and mean sd (OpenSim's .mot units), pose and geometry sd, share."""
        deg = np.where(self.rotational, 180.0 / np.pi, 1.0)
        share = self.geometry_share()
        coords = {}
        for c, n in enumerate(self.names):
            f = deg[c]
            coords[n] = {"unit": "deg" if self.rotational[c] else "m", "status": self.status[c],
                         "mean": _nanmean(self.value[:, c]) * f, "mean_sd": _nanmean(self.sd[:, c]) * f,
                         "rms_sd_pose": _nanrms(self.sd_pose[:, c]) * f,
                         "rms_sd_geometry": _nanrms(self.sd_geometry[:, c]) * f,
                         "rms_sd_geometry_linear": _nanrms(self.sd_geometry_linear[:, c]) * f,
                         "geometry_share": float(share[c]),
                         "frames_outside_range": int(self.outside_range[c])}
        return {"trial": self.source, "frames": int(self.time.size), "frames_fixed": int(self.fixed.sum()),
                "sigma_mm": self.sigma, "draws": self.n_draws, "covariance": self.covariance,
                "coordinates": coords}


def _nanmean(x) -> float:
    x = np.asarray(x, float)
    return float(np.mean(x[np.isfinite(x)])) if np.isfinite(x).any() else float("nan")


def _nanrms(x) -> float:
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x[np.isfinite(x)] ** 2))) if np.isfinite(x).any() else float("nan")


def coordinate_map(model: Model, coordinates) -> tuple[np.ndarray, np.ndarray]:
    """Where each OpenSim coordinate sits in skelid's pose vector, and the factor to OpenSim units.

    skelid's pose has one entry per coordinate of every joint, segments in order; a
    translational coordinate that is itself a translation is in millimetres there, every
    other coordinate in OpenSim's units (radians, or the argument of its functions).

    Returns
    -------
    index : (C,) int
        Pose index, -1 for a coordinate the model does not have (locked, or no marker reaches it).
    factor : (C,) float
        Multiplies the pose value to give OpenSim's (1e-3 for millimetres, else 1).
    """
    where, k = {}, 0
    for s in model.segments:
        for ci, name in enumerate(s.joint.coordinates):
            mm = any(m.kind == "T" and m.coordinate == ci and m.function.is_identity for m in s.joint.motions)
            where[name] = (k, 1.0 / MM_PER_M if mm else 1.0)
            k += 1
    if k != model.n_pose:
        raise DataError(f"model {model.name!r}: its pose has {model.n_pose} coordinates, its joints name {k}",
                        _REFIT)
    index = np.array([where.get(c.name, (-1, 1.0))[0] for c in coordinates], int)
    factor = np.array([where.get(c.name, (-1, 1.0))[1] for c in coordinates], float)
    return index, factor


def _markers_mm(model: Model, data: MarkerData) -> np.ndarray:
    """``data``'s markers in the model's order, in mm, NaN for a marker the trial lacks: ``(F, M, 3)``."""
    present = [n for n in model.marker_names if n in data.names]
    if not present:
        raise DataError(f"{data.source or 'the trial'}: none of the model's {len(model.markers)} markers "
                        f"({', '.join(model.marker_names[:4])} ...) is in it",
                        "give a trial recorded with the marker set of the fit")
    f = unit_scale(data.units, "mm")
    y = np.full((data.positions.shape[0], len(model.markers), 3), np.nan)
    for i, n in enumerate(model.marker_names):
        if n in data.names:
            y[:, i] = data.positions[:, data.names.index(n)] * f
    return y


def draw_geometry(geom: FittedGeometry, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` draws of ``theta`` from ``N(theta_hat, cov)``, clipped to the priors' support: ``(n, P)``."""
    model = geom.model
    w, V = np.linalg.eigh(geom.cov)
    L = V * np.sqrt(np.clip(w, 0.0, None))
    z = rng.standard_normal((n, model.n_params))
    lo = np.array([p.prior.lower for p in model.parameters])
    hi = np.array([p.prior.upper for p in model.parameters])
    return np.clip(geom.theta + z @ L.T, lo, hi)


def _wrap(dq, rot):
    return np.where(rot, (dq + np.pi) % (2.0 * np.pi) - np.pi, dq)


@interruptible
def joint_angles(geom: FittedGeometry, data: MarkerData, n_draws: int = N_DRAWS,
                 rng: np.random.Generator | None = None, batch: int = BATCH_POSES) -> JointAngles:
    """Every OpenSim coordinate of ``data``'s frames on the fitted geometry, with sd and geometry share.

    Parameters
    ----------
    geom : FittedGeometry
    data : MarkerData
        A trial with (some of) the fit's markers; any units.
    n_draws : int
        Draws of the geometry (0: its first-order effect only).
    rng : numpy.random.Generator
        For the draws and the pose tracker's random starts.
    batch : int
        Most pose fits (draws x frames) at once.

    Returns
    -------
    JointAngles
    """
    from skelid.estimators.fit.likelihood import pose_fixed
    from skelid.estimators.fit.pose import fit_pose, pose_determined, track_poses, workspace

    if (isinstance(n_draws, bool) or not isinstance(n_draws, numbers.Real) or not math.isfinite(n_draws)
            or n_draws < 0 or int(n_draws) != n_draws):
        raise SettingError(f"draws must be a whole number, at least 0; got {n_draws!r}", "give --draws 100")
    rng = np.random.default_rng(0) if rng is None else rng
    model, theta = geom.model, geom.theta
    y = _markers_mm(model, data)
    F, Q = y.shape[0], model.n_pose
    ws = workspace(model)
    rot_pose = np.array([d.kind == "R" for d in model.dofs])
    q, rss = track_poses(model, theta, y, rng, ws=ws)
    fixed = pose_determined(model, y) & np.isfinite(rss)
    Hinv_diag, var_lin = np.zeros((F, Q)), np.zeros((F, Q))
    step = max(1, int(batch) // 8)
    for a in range(0, F, step):  # in blocks of frames: the parameter Jacobian is (frames, 3M, P)
        sl = slice(a, a + step)
        Jq, Jt = _jacobians(model, theta, q[sl], y[sl], ws)
        fixed[sl] &= pose_fixed(Jq)
        H = frame_gram(Jq)
        H[~fixed[sl]] = np.eye(Q)
        Hinv = np.linalg.inv(H)
        Hinv_diag[sl] = np.einsum("tqq->tq", Hinv)
        if model.n_params:
            # first order: dq/dtheta = -(Jq^T Jq)^-1 Jq^T J_theta
            # as matrix products (BLAS): einsum's own loops took 70 % of a 150-frame gait2354 trial's time
            G = -(Hinv @ (np.swapaxes(Jq, -1, -2) @ Jt))
            var_lin[sl] = np.sum((G @ geom.cov) * G, axis=-1)
    n_obs = np.isfinite(y).all(axis=-1).sum(axis=-1) * 3
    dof = float(np.sum(n_obs[fixed] - Q))
    if dof >= 1:
        sigma = float(np.sqrt(np.sum(rss[fixed]) / dof))
    elif geom.sigma is not None:
        sigma = float(geom.sigma)
    else:
        raise DataError(f"{data.source or 'the trial'}: its markers do not fix any frame's pose with residual "
                        "degrees of freedom to spare, so the noise of the angles cannot be estimated",
                        "give a trial with more of the fit's markers")
    var_pose = sigma**2 * Hinv_diag
    if n_draws and model.n_params:
        draws = draw_geometry(geom, int(n_draws), rng)
        var_geo = _draw_variance(model, draws, y, q, fixed, rot_pose, ws, batch, fit_pose)
    else:
        var_geo = var_lin
    return _to_coordinates(geom, data, q, var_pose, var_geo, var_lin, fixed, sigma, int(n_draws) if
                           model.n_params else 0)


def _jacobians(model, theta, q, y, ws):
    """Pose and parameter Jacobians of every frame, rows of missing markers zero: ``(F, 3M, Q)``, ``(F, 3M, P)``."""
    from skelid.model.kinematics import marker_jacobian

    _, Jq, Jt = marker_jacobian(model, theta, q, ws)
    w = np.isfinite(y).all(axis=-1)[..., None, None]
    F = y.shape[0]
    return (np.where(w, Jq, 0.0).reshape(F, -1, model.n_pose),
            np.where(w, Jt, 0.0).reshape(F, -1, model.n_params) if model.n_params else None)


def _draw_variance(model, draws, y, q, fixed, rot, ws, batch, fit_pose) -> np.ndarray:
    """(F, Q) variance over the draws of each frame's refitted pose (every draw x frame batched)."""
    D, F, Q = draws.shape[0], y.shape[0], q.shape[1]
    total, square = np.zeros((F, Q)), np.zeros((F, Q))  # of the deviations from the MAP pose, over the draws
    idx = np.flatnonzero(fixed)
    if idx.size == 0:
        return total
    per_draws = max(1, int(batch) // idx.size)  # draws per batch (all frames), or frames per batch (one draw)
    per_frames = min(idx.size, int(batch))
    for a in range(0, D, per_draws):
        th = draws[a:a + per_draws, None, :]
        for b in range(0, idx.size, per_frames):
            f = idx[b:b + per_frames]
            qd = _refit_draws(model, th, y[None, f], np.broadcast_to(q[f], (th.shape[0], f.size, Q)), ws, fit_pose)
            dq = _wrap(qd - q[f], rot)
            total[f] += dq.sum(axis=0)
            square[f] += (dq**2).sum(axis=0)
    if D == 1:
        return square
    return np.maximum(square - total**2 / D, 0.0) / (D - 1)


def _refit_draws(model, theta, y, q0, ws, fit_pose) -> np.ndarray:
    """Each draw's pose fitted from ``q0`` (``(D, F, Q)``; ``theta (D, 1, P)``, ``y (1, F, M, 3)``).

    A batch of pose fits runs until its slowest member has converged, so one draw that needs all
    :data:`DRAW_ITER` iterations holds back every other. The fits run :data:`DRAW_ROUND` iterations at a time,
    and after each round those whose residual sum of squares fell by at most :data:`DRAW_TOL` of it over the
    round are set aside.
    """
    from skelid.model.kinematics import marker_positions

    shape = q0.shape[:-1]
    th = np.broadcast_to(theta, shape + theta.shape[-1:])
    yy = np.broadcast_to(y, shape + y.shape[-2:])
    q = np.array(q0, dtype=float)
    cost = np.nansum((yy - marker_positions(model, th, q, ws)) ** 2, axis=(-1, -2))
    active = np.ones(shape, bool)
    done = 0
    while done < DRAW_ITER and active.any():
        idx = np.nonzero(active)
        q[idx], new = fit_pose(model, th[idx], yy[idx], q[idx], n_iter=min(DRAW_ROUND, DRAW_ITER - done), ws=ws)
        done += DRAW_ROUND
        active[idx] = cost[idx] - new > DRAW_TOL * new
        cost[idx] = new
    return q


def _to_coordinates(geom, data, q, var_pose, var_geo, var_lin, fixed, sigma, n_draws) -> JointAngles:
    """The pose's values and variances as every OpenSim coordinate in OpenSim units."""
    coords = geom.coordinates
    index, factor = coordinate_map(geom.model, coords)
    F, C = q.shape[0], len(coords)
    value = np.full((F, C), np.nan)
    vp, vg, vl = (np.full((F, C), np.nan) for _ in range(3))
    status = []
    for c, co in enumerate(coords):
        k = index[c]
        if k >= 0:
            value[:, c] = q[:, k] * factor[c]
            vp[:, c] = var_pose[:, k] * factor[c] ** 2
            vg[:, c] = var_geo[:, k] * factor[c] ** 2
            vl[:, c] = var_lin[:, k] * factor[c] ** 2
            status.append("fitted")
        else:  # OpenSim's IK holds such a coordinate at its default value
            value[:, c] = co.default
            zero = 0.0 if co.locked else np.nan
            vp[:, c], vg[:, c], vl[:, c] = zero, zero, zero
            status.append("locked" if co.locked else "no markers")
    fitted = index >= 0
    for a in (value, vp, vg, vl):
        a[np.ix_(~fixed, fitted)] = np.nan
    # a rotational coordinate's value on the branch nearest zero, then continuous in time
    rot = np.array([c.rotational for c in coords])
    wrap = rot & fitted
    value[:, wrap] = _wrap(value[:, wrap], True)
    ok = fixed
    if ok.any():
        value[np.ix_(ok, wrap)] = np.unwrap(value[np.ix_(ok, wrap)], axis=0)
    lo = np.array([c.range[0] for c in coords], float)
    hi = np.array([c.range[1] for c in coords], float)
    clamped = np.array([c.clamped and s == "fitted" for c, s in zip(coords, status, strict=True)])
    with np.errstate(invalid="ignore"):
        outside = (((value < lo - 1e-9) | (value > hi + 1e-9)) & clamped).sum(axis=0)
    time = _times(data)
    return JointAngles(tuple(c.name for c in coords), rot, time, value, np.sqrt(vp + vg), np.sqrt(vp), np.sqrt(vg),
                       np.sqrt(vl), fixed, tuple(status), sigma, n_draws, geom.covariance, outside,
                       str(data.source or ""))


def _times(data: MarkerData) -> np.ndarray:
    """Each frame's time: from the file's Time column where it has one (its start and mean step), else
    ``frame / rate``."""
    meta = data.meta if isinstance(data.meta, dict) else {}
    start, step = meta.get("time_start"), meta.get("time_step")
    start = float(start) if isinstance(start, int | float) and np.isfinite(start) else 0.0
    step = float(step) if isinstance(step, int | float) and np.isfinite(step) and step > 0 else 1.0 / data.rate
    return start + step * np.arange(data.positions.shape[0])


# ----------------------------------------------------------------------------- files
def mot_text(angles: JointAngles, which: str = "value", name: str | None = None) -> str:
    """An OpenSim ``.mot`` file of ``angles.value`` (``which='value'``) or ``angles.sd`` (``'sd'``).

    Rotational coordinates in degrees (``inDegrees=yes``), the others in metres, as OpenSim's
    inverse kinematics writes them; ``nan`` where a value is not known.
    """
    arr = {"value": angles.value, "sd": angles.sd}[which]
    deg = np.where(angles.rotational, 180.0 / np.pi, 1.0)
    out = arr * deg
    F, C = out.shape
    title = name or ("Coordinates" if which == "value" else "Coordinates_sd")
    head = [title, "version=1", f"nRows={F}", f"nColumns={C + 1}", "inDegrees=yes", "",
            "Units are S.I. units (second, meters, Newtons, ...)",
            "If the header above contains a line with 'inDegrees', this indicates whether rotational values "
            "are in degrees (yes) or radians (no).",
            "" if which == "value" else "Each value is the standard deviation of the coordinate (skelid ik).",
            "endheader", "\t".join(["time", *angles.names])]
    rows = ["\t".join([f"{angles.time[t]:.8f}"] + [_num(v) for v in out[t]]) for t in range(F)]
    return "\n".join(head + rows) + "\n"


def _num(v: float) -> str:
    return "nan" if not np.isfinite(v) else f"{v:.10g}"


def trial_stem(path) -> str:
    """The file stem of a trial (``walk1`` for ``data/walk1.trc``)."""
    return Path(str(path)).stem


def write_ik(out_dir, results: dict) -> dict[str, Path]:
    """Write ``<stem>.mot`` and ``<stem>_sd.mot`` per trial and ``ik.json`` into ``out_dir``.

    Parameters
    ----------
    results : dict
        Trial stem -> :class:`JointAngles`.
    """
    from skelid.io.atomic import atomic_write
    from skelid.io.results import write_json

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {}
    for stem, a in results.items():
        for which, suffix in (("value", ""), ("sd", "_sd")):
            p = out_dir / f"{stem}{suffix}.mot"
            with atomic_write(p) as fh:
                fh.write(mot_text(a, which, f"{stem}{suffix}"))
            paths[f"{stem}{suffix}"] = p
    doc = {"format": "skelid-ik", "trials": {stem: a.summary() for stem, a in results.items()}}
    paths["json"] = write_json(out_dir / "ik.json", doc)
    return paths


def check_trial_names(paths) -> list[str]:
    """Each trial's file stem; two trials of one stem are refused (their files would collide)."""
    stems = [trial_stem(p) for p in paths]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        raise DataError(f"two trials are named {dup[0]!r}; their angle files would have one name",
                        "rename one of the trial files")
    return stems


def ik_document(results: dict) -> dict:
    """What ``skelid ik --json`` prints: each trial's summary (:meth:`JointAngles.summary`)."""
    return {stem: a.summary() for stem, a in results.items()}


def run_ik(geom: FittedGeometry, trials: dict, n_draws: int = N_DRAWS, seed: int = 0) -> dict:
    """:func:`joint_angles` of each trial (stem -> MarkerData), each with a generator seeded by ``seed`` and its
    stem (a trial gets the same draws whichever trials come with it)."""
    import zlib

    return {stem: joint_angles(geom, data, n_draws, np.random.default_rng([seed, zlib.crc32(stem.encode())]))
            for stem, data in trials.items()}
