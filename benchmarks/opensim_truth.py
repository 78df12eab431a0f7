"""skelid's OpenSim scaling on data whose truth OpenSim itself generated.

Each draw builds a subject with the ``opensim`` package from a generic model
(``--model``): gait2354 (``../shared/data/opensim-subject01/gait2354_simbody.osim``
with ``gait2354_Scale_MarkerSet.xml``, subject01's walks), or ``rajagopal``, the
full-body Rajagopal-type model of ``addbio-subject4`` (``Models/unscaled_generic.osim``,
49 markers, 31 of them ``fixed`` landmarks, thigh and shank clusters held at one
placeholder point; its walks, 100 Hz, IK on the expert's scaled model because IK
on the unscaled one tracks them at 84 mm):

1. scale factors drawn per draw, uniform in [0.85, 1.15], left and right drawn
   independently, for the bodies that carry markers (gait2354: pelvis, torso,
   femur, tibia, calcaneus per side; talus and toes carry none and stay at 1):
   ``truth=bodies`` one factor per body, ``truth=axes`` one per body axis,
   ``truth=every`` one per axis for every body of the model (talus, toes,
   patella, ulna, hand too, as OpenSim's scale setups scale them);
   applied with OpenSim's own ``Model.scale(state, ScaleSet, ...)``;
2. every marker (``fixed`` ones too) moved by a known offset in its body frame, a random direction
   of length uniform in [1, 20] mm; ``truth=prior`` instead draws both from
   the fit's own priors (per axis, the factor log-normal with sd 0.15, each
   offset coordinate normal with sd 10 mm): there a right posterior covers
   95 % of every quantity, those the data leave to the prior included, while
   the uniform truths are narrower than the priors and a prior-dominated
   interval covers them more often;
3. the motion: OpenSim's InverseKinematicsTool solution of ``subject01_walk1.trc``
   on the generic model (151 frames, 60 Hz; rajagopal: ``walking1.trc``, 131 frames),
   and a standing pose (its IK of a second of the static trial, averaged) held for
   1 s; computed once and cached under the system's temporary folder
   (``skelid-opensim-truth``), never committed;
4. markers from OpenSim's kinematics of the scaled model at those coordinates
   (``Marker.getLocationInGround``), plus noise of one of three kinds, named
   by the cell's last field: a number (``0``, ``2``, ``5``, ``10``): i.i.d.
   normal noise of that sd (mm) per coordinate; ``pm``: i.i.d. per marker,
   each marker's sd drawn uniform in [1, 10] mm; ``sta``: simulated
   soft-tissue artefact, never told to the estimator: each marker moves on
   its body, in the body's frame, by ``W_m (q(t) - q_static)`` (the
   rotational coordinates, rad; the segment-embedded, joint-angle-driven
   model of the artefact literature), ``W_m = W_b + W'_m / 2`` with ``W_b``
   shared by the markers of body ``b`` and ``W'_m`` its own (normal draws),
   scaled so that the body's markers move by an rms (over the walk, per
   coordinate) drawn uniform in [5, 15] mm per body; zero at the standing
   pose; plus 1 mm i.i.d. noise. ``stalab``: the same draws added in the
   laboratory's frame instead (a slide that does not turn with its body:
   a form skelid's slide, which lives in the body's frame, does not hold;
   the check of what such a misfit costs). A marker that slides has no
   one place on its body: the truth of its offset and of its place in its
   body is where the artefact puts it at the model's zero pose, the pose in
   which skelid defines the offsets (the standing pose is not in every design,
   and between the two poses the artefact moves a marker by about its rms).

Designs: ``static+walk`` (the static trial first, as the command line takes
it), ``walk`` (one dynamic trial alone) and ``walk+walk2`` (two dynamic trials:
the walk and the IK of ``walk_free_01.trc``, 73 frames, another walk of the
same subject, as two trials of one fit; rajagopal: ``walking2.trc``). skelid fits the generic model with
:func:`skelid.scaling.fit_osim` with ``scale="linked"`` (the default, the
user's case: three factors per body, their logs correlated a priori), with
``scale="bodies"`` (one factor per body), and, where the truth is per axis,
with ``scale="axes"`` (the exact structure). Reported per cell for every scale factor, segment length
(hip-knee, knee-ankle per side, rajagopal also shoulder-elbow, at the zero pose, joint centre to
joint centre: the origins of the joints' child frames, which in the Rajagopal knee and ankle are not
the bodies' origins),
marker offset, and every joint centre in its parent body's frame and marker in its
own body's frame (the same quantities whatever the fit's parametrisation): bias,
bias/CRLB (skelid's Cramér-Rao sd where it reports one, else its sd), RMSE/mean
reported sd, RMSE/CRLB, coverage of the 95 % interval, mean reported sd / actual
sd, draws, failures. A one-factor fit of a per-axis truth is compared with the
mean of the three true factors; that is no quantity such a fit estimates, and the
body-frame rows are the ones that compare its answer with the truth.

Peer in the same draw: OpenSim's ScaleTool (measurement-based scaling with the
marker pairs of ``subject01_Setup_Scale.xml``, then its MarkerPlacer) on the
same static trial (``static+walk`` design only, gait2354 only: no measurement
setup comes with the Rajagopal model); its scale and length errors beside skelid's.

Run: ``nice -n 10 python benchmarks/opensim_truth.py [--quick] [--reps N] [--cells ...] [--jobs J]
[--out PATH]`` -> ``benchmarks/results/opensim_truth.{json,md}``. A cell is
``truth/fit/design/noise``, e.g. ``axes/axes/walk/5``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import provenance, write_results  # noqa: E402

SHARED = ROOT.parent / "shared" / "data"
OUT = ROOT / "benchmarks" / "results" / "opensim_truth"
CACHE = Path(tempfile.gettempdir()) / "skelid-opensim-truth"
STATIC_SECONDS = 1.0
SCALE_RANGE = (0.85, 1.15)
OFFSET_RANGE_MM = (1.0, 20.0)


@dataclass(frozen=True)
class Setup:
    """A generic model, its trials and what is scored: one per ``--model``."""

    key: str
    title: str
    generic: Path
    #: a separate MarkerSet file, or None where the model holds its markers
    marker_set: Path | None
    #: trials: (file, time range or None): the walk, another walk, the standing trial (its mean pose held)
    walk: tuple
    walk2: tuple
    static: tuple
    rate: float
    #: (name, parent body, child body): distances between joint centres at the zero pose
    lengths: dict
    #: ScaleTool's setup and the files it names (copied beside it), or None: no peer for this model
    scaletool: tuple | None = None
    #: the model whose IK of the trials gives the motions (default the generic one); a scaled one where the
    #: generic model is too far from the subject for IK to track the walk
    ik_model: Path | None = None


SETUPS = {
    "gait2354": Setup(
        "gait2354", "gait2354 (subject01's walks)", SHARED / "opensim-subject01" / "gait2354_simbody.osim",
        SHARED / "opensim-subject01" / "gait2354_Scale_MarkerSet.xml",
        (SHARED / "opensim-subject01" / "subject01_walk1.trc", None),
        (SHARED / "opensim-subject01" / "walk_free_01.trc", None),
        (SHARED / "opensim-subject01" / "subject01_static.trc", (1.0, 2.0)), 60.0,
        {"thigh_r (hip-knee)": ("femur_r", "tibia_r"), "thigh_l (hip-knee)": ("femur_l", "tibia_l"),
         "shank_r (knee-ankle)": ("tibia_r", "talus_r"), "shank_l (knee-ankle)": ("tibia_l", "talus_l")},
        ("subject01_Setup_Scale.xml", ("gait2354_simbody.osim", "gait2354_Scale_MarkerSet.xml"))),
    "rajagopal": Setup(
        "rajagopal", "the full-body Rajagopal-type model of addbio-subject4 (its walks)",
        SHARED / "addbio-subject4" / "Models" / "unscaled_generic.osim", None,
        (SHARED / "addbio-subject4" / "MarkerData" / "walking1.trc", None),
        (SHARED / "addbio-subject4" / "MarkerData" / "walking2.trc", None),
        (SHARED / "addbio-subject4" / "MarkerData" / "static1.trc", (0.5, 1.5)), 100.0,
        {"thigh_r (hip-knee)": ("femur_r", "tibia_r"), "thigh_l (hip-knee)": ("femur_l", "tibia_l"),
         "shank_r (knee-ankle)": ("tibia_r", "talus_r"), "shank_l (knee-ankle)": ("tibia_l", "talus_l"),
         "upper arm_r (shoulder-elbow)": ("humerus_r", "ulna_r"),
         "upper arm_l (shoulder-elbow)": ("humerus_l", "ulna_l")},
        ik_model=SHARED / "addbio-subject4" / "Models" / "manually_scaled.osim"),
}
#: the model of this run (:func:`use_model`); gait2354 unless ``--model`` says otherwise
SETUP = SETUPS["gait2354"]


def use_model(key: str) -> Setup:
    global SETUP
    SETUP = SETUPS[key]
    return SETUP


NOISES = (0.0, 2.0, 5.0, 10.0)
# truth, fit, design
CONFIGS = (("bodies", "bodies"), ("axes", "bodies"), ("axes", "axes"), ("axes", "linked"), ("bodies", "linked"))
DESIGNS = ("static+walk", "walk", "walk+walk2")
Z95 = 1.959964
#: a parameter is data-determined in a draw where its bound is at most this share of its prior's sd
IDENTIFIED_SHARE = 0.5


def _osim():
    import opensim as osim

    osim.Logger.setLevelString("Error")
    osim.Logger.removeFileSink()  # OpenSim would write opensim.log beside every model it loads
    return osim


def generic_model():
    osim = _osim()
    model = osim.Model(str(SETUP.generic))
    if SETUP.marker_set is not None:
        model.updateMarkerSet(osim.MarkerSet(str(SETUP.marker_set)))
    model.initSystem()
    return model


def scaled_bodies(truth: str) -> tuple[str, ...]:
    """The bodies a truth scales: those carrying markers (the bodies skelid scales), or with ``truth='every'``
    every body of the model (talus, toes, patella, forearm and hand bones as well, as OpenSim's scale setups do)."""
    model = generic_model()
    ms, bs = model.getMarkerSet(), model.getBodySet()
    marked = {ms.get(i).getParentFrame().findBaseFrame().getName() for i in range(ms.getSize())}
    return tuple(bs.get(i).getName() for i in range(bs.getSize())
                 if truth == "every" or bs.get(i).getName() in marked)


def _ik(trc: Path, name: str, t_range=None) -> tuple[list[str], np.ndarray]:
    """OpenSim IK of ``trc`` on the generic model: coordinate names and values (F, C) in rad / m (cached)."""
    cache = CACHE / f"{SETUP.key}_{name}.npz"
    if cache.exists():
        z = np.load(cache, allow_pickle=False)
        return [str(n) for n in z["names"]], z["q"]
    osim = _osim()
    CACHE.mkdir(parents=True, exist_ok=True)
    model = generic_model() if SETUP.ik_model is None else osim.Model(str(SETUP.ik_model))
    model.initSystem()
    tool = osim.InverseKinematicsTool()
    tool.setModel(model)
    tool.setMarkerDataFileName(str(trc))
    tasks = tool.getIKTaskSet()
    in_trial = set(osim.TimeSeriesTableVec3(str(trc)).getColumnLabels())
    for i in range(model.getMarkerSet().getSize()):
        if model.getMarkerSet().get(i).getName() not in in_trial:
            continue
        t = osim.IKMarkerTask()
        t.setName(model.getMarkerSet().get(i).getName())
        t.setApply(True)
        t.setWeight(1.0)
        tasks.cloneAndAppend(t)
    tvec = np.asarray(osim.TimeSeriesTableVec3(str(trc)).getIndependentColumn())
    lo, hi = (tvec[0], tvec[-1]) if t_range is None else t_range
    tool.setStartTime(float(lo))
    tool.setEndTime(float(hi))
    tool.setResultsDir(str(CACHE))
    tool.setOutputMotionFileName(str(CACHE / f"{SETUP.key}_{name}.mot"))
    tool.run()
    table = osim.TimeSeriesTable(str(CACHE / f"{SETUP.key}_{name}.mot"))
    cs = model.getCoordinateSet()
    names, cols = [], []
    for i in range(cs.getSize()):
        c = cs.get(i)
        v = np.asarray(table.getDependentColumn(c.getName()).to_numpy(), float)
        if c.getMotionType() == 1:  # rotational, written in degrees
            v = np.deg2rad(v)
        names.append(c.getName())
        cols.append(v)
    q = np.stack(cols, axis=1)
    np.savez(cache, names=np.array(names), q=q)
    return names, q


def motions() -> dict:
    """The coordinates of the walks (F, C) and of the standing pose held (T, C)."""
    names, walk = _ik(SETUP.walk[0], "walk", SETUP.walk[1])
    _, walk2 = _ik(SETUP.walk2[0], "walk2", SETUP.walk2[1])
    _, stand = _ik(SETUP.static[0], "static", SETUP.static[1])
    hold = np.repeat(stand.mean(axis=0, keepdims=True), int(SETUP.rate * STATIC_SECONDS), axis=0)
    return {"names": names, "walk": walk, "walk2": walk2, "static": hold}


STA_RMS_MM = (5.0, 15.0)
#: the artefact's kinds: in each body's frame, in the laboratory's
STA = ("sta", "stalab")
STA_NOISE_MM = 1.0
PER_MARKER_SD_MM = (1.0, 10.0)


def noise_token(n) -> str:
    """A cell's noise field as written in its key: a number as ``%g``, else the kind's name."""
    try:
        return f"{float(n):g}"
    except ValueError:
        if n not in ("pm", *STA):
            raise SystemExit(f"unknown noise {n!r}: a number (mm), 'pm', 'sta' or 'stalab'") from None
        return n


def add_noise(rng, token: str, model, coord_names, trials: dict, static_q) -> tuple[dict, np.ndarray | None]:
    """``trials``: name -> (positions (F, M, 3) mm, coordinates (F, C)); the noisy positions by name, and
    for an artefact where it puts each marker at the model's zero pose ((M, 3) mm, ground frame)."""
    ms = model.getMarkerSet()
    M = ms.getSize()
    if token == "pm":
        sd = rng.uniform(*PER_MARKER_SD_MM, M)[None, :, None]
        return {k: y + rng.normal(size=y.shape) * sd for k, (y, _) in trials.items()}, None
    if token not in STA:
        return {k: y + rng.normal(0.0, float(token), y.shape) for k, (y, _) in trials.items()}, None
    cs = model.getCoordinateSet()
    rot = np.array([cs.get(n).getMotionType() == 1 for n in coord_names])
    bodies = [ms.get(i).getParentFrameName().split("/")[-1] for i in range(M)]
    shared = {b: rng.normal(size=(3, rot.sum())) for b in sorted(set(bodies))}
    W = np.stack([shared[b] + 0.5 * rng.normal(size=(3, rot.sum())) for b in bodies])  # (M, 3, C)
    ref = static_q[0, rot]

    def artefact(q):  # (T, M, 3) ground frame: turned with each marker's body for ``sta``
        d = np.einsum("mjc,tc->tmj", W, q[:, rot] - ref)
        return d if token == "stalab" else np.einsum("tmij,tmj->tmi", marker_rotations(model, coord_names, q), d)
    walk = np.einsum("mjc,tc->tmj", W, trials["walk"][1][:, rot] - ref)  # a rotation keeps the rms
    for b in sorted(set(bodies)):  # each body's markers move by their drawn rms over the walk
        idx = [i for i, x in enumerate(bodies) if x == b]
        rms = float(np.sqrt(np.mean(walk[:, idx] ** 2)))
        if rms > 0:
            W[idx] *= rng.uniform(*STA_RMS_MM) / rms
    noisy = {k: y + artefact(q) + rng.normal(0.0, STA_NOISE_MM, y.shape) for k, (y, q) in trials.items()}
    return noisy, artefact(np.zeros((1, len(coord_names))))[0]


def marker_rotations(model, coord_names, q) -> np.ndarray:
    """``(F, M, 3, 3)``: the rotation of each marker's body in the ground frame at the coordinates ``q``."""
    state = model.initSystem()
    cs = model.getCoordinateSet()
    coords = [cs.get(n) for n in coord_names]
    ms = model.getMarkerSet()
    frames = [ms.get(i).getParentFrame() for i in range(ms.getSize())]
    out = np.empty((len(q), len(frames), 3, 3))
    for t, row in enumerate(q):
        for c, v in zip(coords, row, strict=True):
            c.setValue(state, float(v), False)
        model.realizePosition(state)
        for j, f in enumerate(frames):
            R = f.getTransformInGround(state).R()
            out[t, j] = [[R.get(i, k) for k in range(3)] for i in range(3)]
    return out


def fit_priors() -> tuple[float, float]:
    """skelid's default priors for an OpenSim fit: the sd of a scale factor's log, an offset's sd (mm)."""
    import inspect

    from skelid.io.osim import osim_parameters

    par = inspect.signature(osim_parameters).parameters
    return float(par["scale_sd_log"].default), float(par["offset_sd"].default)


def draw_truth(rng, truth: str, marker_names) -> dict:
    """Per body three scale factors and per marker an offset (mm, body frame).

    ``bodies``/``axes``: uniform factors (:data:`SCALE_RANGE`), offsets of uniform length
    (:data:`OFFSET_RANGE_MM`); ``prior``: per-axis factors and offsets drawn from the priors the
    fit uses (:func:`fit_priors`), where a right posterior covers 95 % of every quantity, also of
    those the data leave to the prior.
    """
    if truth == "prior":
        sd_log, sd_off = fit_priors()
        scales = {b: np.exp(rng.normal(0.0, sd_log, 3)) for b in scaled_bodies(truth)}
        d = rng.normal(0.0, sd_off, (len(marker_names), 3))
        return {"scales": scales, "offsets": dict(zip(marker_names, d, strict=True))}
    scales = {}
    for b in scaled_bodies(truth):
        s = rng.uniform(*SCALE_RANGE, 1 if truth == "bodies" else 3)
        scales[b] = np.broadcast_to(s, 3).astype(float).copy()
    d = rng.normal(size=(len(marker_names), 3))
    d *= (rng.uniform(*OFFSET_RANGE_MM, len(marker_names)) / np.linalg.norm(d, axis=1))[:, None]
    return {"scales": scales, "offsets": dict(zip(marker_names, d, strict=True))}


def subject(truth: dict):
    """The generic model scaled by OpenSim with ``truth``'s factors and its markers moved."""
    osim = _osim()
    model = generic_model()
    state = model.initSystem()
    ss = osim.ScaleSet()
    for b, s in truth["scales"].items():
        sc = osim.Scale()
        sc.setSegmentName(b)
        sc.setScaleFactors(osim.Vec3(*map(float, s)))
        sc.setApply(True)
        ss.cloneAndAppend(sc)
    model.scale(state, ss, False, -1.0)
    for i in range(model.getMarkerSet().getSize()):
        m = model.getMarkerSet().get(i)
        loc = m.get_location()
        d = truth["offsets"][m.getName()] / 1000.0
        m.set_location(osim.Vec3(loc.get(0) + d[0], loc.get(1) + d[1], loc.get(2) + d[2]))
    model.finalizeConnections()
    model.initSystem()
    return model


def marker_trajectories(model, coord_names, q) -> tuple[list[str], np.ndarray]:
    """OpenSim's marker positions (F, M, 3) in mm at the coordinates ``q (F, C)``."""
    state = model.initSystem()
    cs = model.getCoordinateSet()
    coords = [cs.get(n) for n in coord_names]
    ms = model.getMarkerSet()
    names = [ms.get(i).getName() for i in range(ms.getSize())]
    out = np.empty((len(q), len(names), 3))
    for t, row in enumerate(q):
        for c, v in zip(coords, row, strict=True):
            c.setValue(state, float(v), False)
        model.realizePosition(state)
        for j in range(len(names)):
            p = ms.get(j).getLocationInGround(state)
            out[t, j] = (p.get(0), p.get(1), p.get(2))
    return names, out * 1000.0


def joint_centres(model, state) -> dict:
    """Body name -> the ground position (m) of its joint's centre: the origin of the joint's child frame.

    Where a joint's child frame sits away from its body's origin (the Rajagopal knee and ankle), the
    body's origin is not the joint centre; skelid's segments have their origin at the joint centre.
    """
    js = model.getJointSet()
    out = {}
    for i in range(js.getSize()):
        f = js.get(i).getChildFrame()
        v = f.getPositionInGround(state)
        out[f.findBaseFrame().getName()] = np.array([v.get(0), v.get(1), v.get(2)])
    return out


def opensim_lengths(model, coord_names) -> dict:
    """Distances (mm) between the joint centres of ``SETUP.lengths`` at the zero pose."""
    state = model.initSystem()
    cs = model.getCoordinateSet()
    for n in coord_names:
        cs.get(n).setValue(state, 0.0, False)
    model.realizePosition(state)
    c = joint_centres(model, state)
    return {k: float(np.linalg.norm(c[a] - c[b]) * 1000.0) for k, (a, b) in SETUP.lengths.items()}


def opensim_points(model, moved=None) -> dict:
    """Each joint centre in its parent body's frame (from the parent's own joint centre) and each marker in its
    own body's frame (from the body's joint centre), in mm at the zero pose.

    Quantities that mean the same whatever a fit's parametrisation (one factor per body or one per
    axis, offsets measured from differently scaled nominal places): where the body's joints and
    markers are. ``moved``: (M, 3) mm added to the markers in the ground frame (the artefact there).
    """
    state = model.initSystem()
    cs = model.getCoordinateSet()
    for i in range(cs.getSize()):
        cs.get(i).setValue(state, 0.0, False)
    model.realizePosition(state)

    centre = joint_centres(model, state)

    def frame(b):
        R = b.getTransformInGround(state).R()
        return np.array([[R.get(i, j) for j in range(3)] for i in range(3)]), centre[b.getName()]
    out = {}
    js = model.getJointSet()
    for i in range(js.getSize()):
        par, ch = js.get(i).getParentFrame().findBaseFrame(), js.get(i).getChildFrame().findBaseFrame()
        if par.getName() == "ground":
            continue
        (Rp, pp), (_, pc) = frame(par), frame(ch)
        out[f"joint {ch.getName()} in {par.getName()}"] = Rp.T @ (pc - pp) * 1000.0
    ms = model.getMarkerSet()
    for i in range(ms.getSize()):
        m = ms.get(i)
        R, p = frame(m.getParentFrame().findBaseFrame())
        x = np.array([m.getLocationInGround(state).get(k) for k in range(3)])
        x = x if moved is None else x + moved[i] / 1000.0
        out[f"marker {m.getName()}"] = R.T @ (x - p) * 1000.0
    return out


# ----------------------------------------------------------------------------- skelid
def skelid_lengths(fit) -> tuple[dict, dict]:
    """Lengths (mm) at the zero pose from a fit and their sd (delta method over the scale covariance)."""
    from skelid.model.kinematics import forward_kinematics

    model, theta = fit.model, np.asarray(fit.theta, float)
    idx = {s.name: i for i, s in enumerate(model.segments)}
    zero = np.zeros(model.n_pose)

    def lengths(th):
        kin = forward_kinematics(model, th, zero)
        return np.array([np.linalg.norm(kin.p_world_seg[idx[a]] - kin.p_world_seg[idx[b]])
                         for a, b in SETUP.lengths.values()])
    ks = [k for k, p in enumerate(model.parameters) if p.kind == "scale"]
    L0 = lengths(theta)
    G = np.zeros((len(SETUP.lengths), len(ks)))
    for j, k in enumerate(ks):
        th = theta.copy()
        th[k] += 1e-6
        G[:, j] = (lengths(th) - L0) / 1e-6
    cov = scale_covariance(fit, ks)
    sd = np.sqrt(np.clip(np.einsum("lp,pq,lq->l", G, cov, G), 0, None))
    names = list(SETUP.lengths)
    return dict(zip(names, L0, strict=True)), dict(zip(names, sd, strict=True))


def skelid_points(model, theta) -> dict:
    """:func:`opensim_points` of a skelid model at ``theta``: (3,) arrays in the model's units (mm)."""
    from skelid.model.kinematics import forward_kinematics

    kin = forward_kinematics(model, np.asarray(theta, float), np.zeros(model.n_pose))
    R, p = kin.R_world_seg, kin.p_world_seg
    out = {}
    for i, s in enumerate(model.segments):
        j = model.parent_index[i]
        if j >= 0:
            out[f"joint {s.name} in {model.segments[j].name}"] = R[j].T @ (p[i] - p[j])
    for k, m in enumerate(model.marker_names):
        i = model.marker_segment[k]
        out[f"marker {m}"] = R[i].T @ (kin.markers[k] - p[i])
    return out


def skelid_point_estimates(fit) -> dict:
    """Every :func:`skelid_points` quantity with its 3 x 3 covariance (delta method over the fit's covariance)."""
    model, theta = fit.model, np.asarray(fit.theta, float)
    cov = np.asarray(fit.joint.cov if getattr(fit, "joint", None) is not None else
                     np.diag([fit.result[p.name]["sd"] ** 2 for p in model.parameters]), float)
    x0 = skelid_points(model, theta)
    keys = list(x0)
    G = np.zeros((len(keys), 3, theta.size))
    for k in range(theta.size):  # the points are linear in theta (the geometry map): one-sided steps are exact
        th = theta.copy()
        th[k] += 1e-3
        x1 = skelid_points(model, th)
        G[:, :, k] = [(x1[q] - x0[q]) / 1e-3 for q in keys]
    C = np.einsum("qip,pr,qjr->qij", G, cov, G)
    return {q: {"est": x0[q], "cov": C[n]} for n, q in enumerate(keys)}


def scale_covariance(fit, ks) -> np.ndarray:
    """The covariance of the scale parameters ``ks`` as the fit reports it (its sd on the diagonal)."""
    if getattr(fit, "joint", None) is not None:  # scales and offsets fitted together
        return np.asarray(fit.joint.cov, float)[np.ix_(ks, ks)]
    est = fit.estimator
    cov = getattr(est, "cov_", None)
    names = [fit.model.parameters[k].name for k in ks]
    if cov is not None and hasattr(est, "model") and [p.name for p in est.model.parameters][:len(ks)] == names:
        return np.asarray(cov, float)[:len(ks), :len(ks)]
    if cov is not None and hasattr(est, "model"):
        en = [p.name for p in est.model.parameters]
        i = [en.index(n) for n in names]
        return np.asarray(cov, float)[np.ix_(i, i)]
    sd = np.array([fit.result[n]["sd"] for n in names])
    return np.diag(sd**2)


def skelid_fit(trials, fit: str, angles=None) -> dict:
    """``fit``: the scale mode, with ``+pm`` for per-marker noise (``noise='per_marker'``); ``angles``:
    ``(draws, coordinate names, {trial: true coordinates (F, C)})`` to score skelid's joint angles, or None."""
    from skelid.data import MarkerData
    from skelid.scaling import _prior_terms, fit_osim, prior_sd

    scale, _, extra = fit.partition("+")
    noise = "per_marker" if extra == "pm" else "pooled"

    data = [MarkerData(y, tuple(names), SETUP.rate, "mm", src) for src, names, y in trials]
    t0 = time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = fit_osim(SETUP.generic, data, marker_set=SETUP.marker_set, scale=scale, markers="offsets", noise=noise)
    cpu = time.process_time() - t0
    est = fit.estimator
    crlb = getattr(est, "crlb_sd_", None)
    if crlb is None and hasattr(est, "trials_"):  # several trials: each trial's bound, combined
        crlb = np.sum([np.asarray(e.crlb_sd_, float) ** -2.0 for e in est.trials_], axis=0) ** -0.5
    out = {"cpu_s": cpu, "sigma": fit.result.get("sigma"), "warnings": list(fit.warnings), "q": {},
           "joint_fit": fit.result.get("joint_fit"), "artefact": fit.result.get("artefact")}
    en = [p.name for p in est.model.parameters] if hasattr(est, "model") else []
    psd = prior_sd(_prior_terms(fit.model, fit.theta)[1])
    for k, p in enumerate(fit.model.parameters):
        e = fit.result[p.name]
        if e.get("crlb_sd") is not None:  # the joint fit's bound (its Laplace sd before any widening)
            cr = float(e["crlb_sd"])
        else:
            cr = float(crlb[en.index(p.name)]) if crlb is not None and p.name in en else float("nan")
        if p.kind == "scale":
            key = f"scale {p.target}" + ("" if p.axis is None else f" {'xyz'[p.axis]}")
        else:
            key = f"offset {p.target} {'xyz'[p.axis]}"
        # data-determined: the bound at most IDENTIFIED_SHARE of the prior's sd (the data, not the prior, decide)
        out["q"][key] = {"est": float(fit.theta[k]), "sd": float(e["sd"]), "crlb": cr,
                         "identified": bool(np.isfinite(cr) and cr <= IDENTIFIED_SHARE * psd[k])}
    L, sd = skelid_lengths(fit)
    for n in L:
        out["q"][f"length {n}"] = {"est": L[n], "sd": sd[n], "crlb": float("nan")}
    out["points"] = skelid_point_estimates(fit)
    if angles is not None:
        out["angles"] = angle_scores(fit, trials, *angles)
    return out


def angle_scores(fit, trials, n_draws: int, coord_names, true_q: dict) -> dict:
    """skelid's joint angles (``skelid ik``: the fit's geometry posterior carried into every coordinate,
    ``n_draws`` draws or its first-order effect at 0) of each movement trial against the coordinates that
    made its markers: per coordinate, the share of frames whose 95 % interval holds the truth, rms z, RMSE
    (deg or mm) and the share of the variance that comes from the geometry, averaged over the trials."""
    from skelid.angles import fitted_geometry, joint_angles
    from skelid.data import MarkerData

    geom = fitted_geometry(fit)
    per: dict = {}
    units: dict = {}
    for src, names, y in trials:
        if src not in true_q:
            continue
        ja = joint_angles(geom, MarkerData(y, tuple(names), SETUP.rate, "mm", src), n_draws, np.random.default_rng(0))
        for c, name in enumerate(ja.names):
            if ja.status[c] != "fitted" or name not in coord_names:
                continue
            err = ja.value[:, c] - true_q[src][:, coord_names.index(name)]
            unit = 180.0 / np.pi if ja.rotational[c] else 1000.0
            if ja.rotational[c]:
                err = (err + np.pi) % (2.0 * np.pi) - np.pi
            sd = ja.sd[:, c]
            ok = np.isfinite(err) & np.isfinite(sd) & (sd > 0)
            if not ok.any():
                continue
            z = err[ok] / sd[ok]
            units[name] = "deg" if ja.rotational[c] else "mm"
            e = per.setdefault(name, {"cover": [], "rms_z": [], "rmse": [], "mean_sd": [], "geometry_share": []})
            e["cover"].append(float(np.mean(np.abs(z) <= Z95)))
            e["rms_z"].append(float(np.sqrt(np.mean(z**2))))
            e["rmse"].append(float(np.sqrt(np.mean(err[ok] ** 2)) * unit))
            e["mean_sd"].append(float(np.mean(sd[ok]) * unit))
            e["geometry_share"].append(float(np.mean(ja.sd_geometry[ok, c] ** 2) / np.mean(sd[ok] ** 2)))
    return {n: {k: float(np.mean(v)) for k, v in e.items()} | {"unit": units[n]} for n, e in per.items()}


def true_values(truth: dict, lengths: dict, fit_scale: str) -> dict:
    q = {}
    for b, s in truth["scales"].items():  # a one-factor fit may give a body one factor per axis (score test)
        for i, a in enumerate("xyz"):
            q[f"scale {b} {a}"] = float(s[i])
        if fit_scale != "axes":
            q[f"scale {b}"] = float(np.mean(s))
    for m, d in truth["offsets"].items():
        for i, a in enumerate("xyz"):
            q[f"offset {m} {a}"] = float(d[i])
    for n, v in lengths.items():
        q[f"length {n}"] = v
    return q


# ----------------------------------------------------------------------------- OpenSim's ScaleTool
def scaletool(names, static: np.ndarray, work: Path, coord_names) -> dict:
    """ScaleTool (measurements, then MarkerPlacer) on the static trial: its scales and lengths."""
    osim = _osim()
    from skelid.data import MarkerData
    from skelid.io import write_trc

    work.mkdir(parents=True, exist_ok=True)
    setup, files = SETUP.scaletool
    for f in (setup, *files):
        if not (work / f).exists():
            shutil.copy(SETUP.generic.parent / f, work / f)
    write_trc(work / "static.trc", MarkerData(static, tuple(names), SETUP.rate, "mm", "static"))
    cwd = os.getcwd()
    os.chdir(work)
    t0 = time.process_time()
    try:
        tool = osim.ScaleTool(setup)
        t_end = (static.shape[0] - 1) / SETUP.rate
        times = osim.ArrayDouble()
        times.append(0.0)
        times.append(t_end)
        ms = tool.getModelScaler()
        ms.setMarkerFileName("static.trc")
        ms.setTimeRange(times)
        order = osim.ArrayStr()
        order.append("measurements")
        ms.setScalingOrder(order)  # the setup's manual scales for femur and tibia are not the subject's
        ms.setOutputModelFileName("scaled_only.osim")
        ms.setOutputScaleFileName("scale_set.xml")
        mp = tool.getMarkerPlacer()
        mp.setStaticPoseFileName("static.trc")
        mp.setTimeRange(times)
        mp.setOutputModelFileName("placed.osim")
        mp.setOutputMotionFileName("placed.mot")
        tool.run()
        cpu = time.process_time() - t0
        ss = osim.ScaleSet("scale_set.xml")
        scales = {}
        for i in range(ss.getSize()):
            s = ss.get(i)
            v = s.getScaleFactors()
            scales[s.getSegmentName()] = [v.get(0), v.get(1), v.get(2)]
        model = osim.Model("placed.osim")
        lengths = opensim_lengths(model, coord_names)
        ms_ = model.getMarkerSet()
        locs = {ms_.get(i).getName(): np.array([ms_.get(i).get_location().get(k) for k in range(3)]) * 1000.0
                for i in range(ms_.getSize())}
    finally:
        os.chdir(cwd)
    return {"scales": scales, "lengths": lengths, "locations_mm": locs, "cpu_s": cpu}


# ----------------------------------------------------------------------------- one draw
def run_draw(args) -> dict:
    model_key, truth_kind, noise, seed, designs, fits, peer, work, n_angle_draws = args
    use_model(model_key)
    peer = peer and SETUP.scaletool is not None
    mo = motions()
    rng = np.random.default_rng(seed)
    generic = generic_model()
    mnames = [generic.getMarkerSet().get(i).getName() for i in range(generic.getMarkerSet().getSize())]
    truth = draw_truth(rng, truth_kind, mnames)
    model = subject(truth)
    names, walk = marker_trajectories(model, mo["names"], mo["walk"])
    _, static1 = marker_trajectories(model, mo["names"], mo["static"][:1])
    static = np.repeat(static1, len(mo["static"]), axis=0)
    clean = {"walk": (walk, mo["walk"]), "static": (static, mo["static"])}
    if any(d == "walk+walk2" for d in designs):
        clean["walk2"] = (marker_trajectories(model, mo["names"], mo["walk2"])[1], mo["walk2"])
    lengths = opensim_lengths(model, mo["names"])
    noisy, moved = add_noise(rng, noise, model, mo["names"], clean, mo["static"])
    points = opensim_points(model, moved)
    if moved is not None:  # a sliding marker's place on its body is where the artefact puts it at the zero pose
        nominal = opensim_points(model)
        truth = {**truth, "offsets": {m: d + points[f"marker {m}"] - nominal[f"marker {m}"]
                                      for m, d in truth["offsets"].items()}}
    walk, static = noisy["walk"], noisy["static"]
    out = {"seed": seed, "truth_kind": truth_kind, "noise": noise, "fits": {}}
    for design in designs:
        trials = {"static+walk": [("static", names, static), ("walk", names, walk)],
                  "walk": [("walk", names, walk)],
                  "walk+walk2": [("walk", names, walk), ("walk2", names, noisy.get("walk2"))]}[design]
        for fs in fits:
            key = f"{truth_kind}/{fs}/{design}/{noise}"
            tv = true_values(truth, lengths, fs.partition("+")[0])
            try:
                r = skelid_fit(trials, fs, None if n_angle_draws is None else
                               (n_angle_draws, mo["names"], {"walk": mo["walk"], "walk2": mo["walk2"]}))
            except Exception as exc:  # a failed fit is counted in its cell, with its message
                out["fits"][key] = {"error": f"{type(exc).__name__}: {exc}"[:300]}
                continue
            r["truth"] = {k: tv[k] for k in r["q"] if k in tv}
            r["truth_points"] = {k: points[k] for k in r["points"] if k in points}
            out["fits"][key] = r
    if peer and "static+walk" in designs:
        try:
            p = scaletool(names, static, Path(work) / f"st_{os.getpid()}", mo["names"])
            err = {}
            for b in truth["scales"]:
                if b in p["scales"]:
                    err[f"scale {b}"] = [float(v - t) for v, t in zip(p["scales"][b], truth["scales"][b],
                                                                       strict=True)]
            for n, v in p["lengths"].items():
                err[f"length {n}"] = float(v - lengths[n])
            out["scaletool"] = {"error": err, "cpu_s": p["cpu_s"]}
        except Exception as exc:
            out["scaletool"] = {"failed": f"{type(exc).__name__}: {exc}"[:300]}
    return out


# ----------------------------------------------------------------------------- summary
#: the words of skelid's warning that names a soft-tissue artefact the residuals show
ARTEFACT_WARNING = "soft-tissue artefact of about"


def summarise(draws: list[dict]) -> dict:
    cells: dict = {}
    for d in draws:
        for key, r in d["fits"].items():
            c = cells.setdefault(key, {"n": 0, "failed": 0, "errors": [], "rows": {}, "cpu": [], "sigma": [],
                                       "warned": 0, "artefact": 0, "art_term": 0})
            if "error" in r:
                c["failed"] += 1
                c["errors"].append(r["error"])
                continue
            c["n"] += 1
            c["cpu"].append(r["cpu_s"])
            s = r.get("sigma")
            c["sigma"].append(s.get("value") if isinstance(s, dict) else s)
            c["warned"] += bool(r["warnings"])
            c["artefact"] += any(ARTEFACT_WARNING in w for w in r["warnings"])
            c["art_term"] += bool((r.get("artefact") or {}).get("present"))
            for q, e in r["q"].items():
                if q in r["truth"]:
                    row = c["rows"].setdefault(q, {"err": [], "sd": [], "crlb": []})
                    row["err"].append(e["est"] - r["truth"][q])
                    row["sd"].append(e["sd"])
                    row["crlb"].append(e["crlb"])
                    if "identified" in e and e["sd"] > 0:  # pooled by kind and by who decides it
                        kind = "scales" if q.startswith("scale") else "offsets"
                        cls = "data-determined" if e["identified"] else "prior-dominated"
                        c.setdefault("classes", {}).setdefault(f"{kind}, {cls}", []).append(
                            (e["est"] - r["truth"][q]) / e["sd"])
            _score_points(c, r)
            for name, a in (r.get("angles") or {}).items():
                c.setdefault("angles", {}).setdefault(name, []).append(a)
        if "scaletool" in d and "error" in d["scaletool"]:
            key = f"{d['truth_kind']}/scaletool/static+walk/{d['noise']}"
            c = cells.setdefault(key, {"n": 0, "failed": 0, "errors": [], "rows": {}, "cpu": []})
            c["n"] += 1
            c["cpu"].append(d["scaletool"]["cpu_s"])
            for q, e in d["scaletool"]["error"].items():
                if isinstance(e, list):
                    for i, a in enumerate("xyz"):
                        c["rows"].setdefault(f"{q} {a}", {"err": []})["err"].append(e[i])
                else:
                    c["rows"].setdefault(q, {"err": []})["err"].append(e)
    out = {}
    for key, c in sorted(cells.items()):
        rows = {}
        for q, v in c["rows"].items():
            err = np.asarray(v["err"], float)
            row = {"n": int(err.size), "bias": float(err.mean()), "rmse": float(np.sqrt(np.mean(err**2))),
                   "actual_sd": float(err.std(ddof=1)) if err.size > 1 else float("nan")}
            if "sd" in v:
                sd = np.asarray(v["sd"], float)
                cr = np.asarray(v["crlb"], float)
                ref = np.where(np.isfinite(cr), cr, sd)
                row |= {"mean_sd": float(sd.mean()), "mean_crlb": float(np.nanmean(ref)),
                        "crlb_is_sd": bool(~np.isfinite(cr).any()),
                        "bias_over_crlb": float(err.mean() / np.nanmean(ref)),
                        "rmse_over_sd": float(np.sqrt(np.mean(err**2)) / sd.mean()),
                        "rmse_over_crlb": float(np.sqrt(np.mean(err**2)) / np.nanmean(ref)),
                        "coverage95": float(np.mean(np.abs(err) <= Z95 * sd)),
                        "sd_ratio": float(sd.mean() / err.std(ddof=1)) if err.size > 1 else float("nan")}
            rows[q] = row
        out[key] = {"n": c["n"], "failed": c["failed"], "errors": sorted(set(c["errors"]))[:5], "rows": rows,
                    "cpu_s_per_fit": float(np.mean(c["cpu"])) if c["cpu"] else float("nan")}
        out[key]["classes"] = {k: {"n": len(z), "coverage95": float(np.mean(np.abs(z) <= Z95)),
                                   "rms_z": float(np.sqrt(np.mean(np.square(z))))}
                               for k, z in sorted(c.get("classes", {}).items())}
        out[key] |= _points_summary(c)
        if c.get("angles"):
            out[key]["angles"] = {n: {"draws": len(v), "unit": v[0]["unit"],
                                      "coverage95": float(np.mean([a["cover"] for a in v])),
                                      "rms_z": float(np.sqrt(np.mean([a["rms_z"] ** 2 for a in v]))),
                                      "rmse": float(np.sqrt(np.mean([a["rmse"] ** 2 for a in v]))),
                                      "mean_sd": float(np.mean([a["mean_sd"] for a in v])),
                                      "geometry_share": float(np.mean([a["geometry_share"] for a in v]))}
                                  for n, v in c["angles"].items()}
        if "sigma" in c:
            sig = [s for s in c["sigma"] if s is not None]
            out[key] |= {"sigma_mean": float(np.mean(sig)) if sig else None,
                         "share_warned": c["warned"] / max(c["n"], 1),
                         "share_artefact_named": c["artefact"] / max(c["n"], 1),
                         "share_artefact_term": c["art_term"] / max(c["n"], 1)}
    return out


#: chi^2_3 95 % point: a 3-D point's region (its 95 % ellipsoid) covers the truth where d^2 is at most this
CHI2_3_95 = 7.814728
#: an error this small (mm) counts as none: a coordinate no parameter moves is exact in the fit and the truth
EXACT_MM = 1e-6


def _point_scores(err, cov) -> tuple[np.ndarray, float]:
    """Per axis ``|error| / sd`` (0 where both are nil, inf where the sd is nil and the error is not) and the
    squared Mahalanobis distance (inf where the error leaves the covariance's range)."""
    err, cov = np.asarray(err, float), np.asarray(cov, float)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    z = np.where(np.abs(err) <= EXACT_MM, 0.0, np.abs(err) / np.maximum(sd, 1e-300))
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    e = V.T @ err
    live = w > 1e-12 * max(float(w.max()), 1e-300)
    if np.any(np.abs(e[~live]) > EXACT_MM):
        return z, float("inf")
    return z, float(np.sum(e[live] ** 2 / w[live]))


def _score_points(c: dict, r: dict) -> None:
    """Add a fit's joint centres and markers (body frames) to its cell's tallies."""
    truth = r.get("truth_points") or {}
    for q, e in (r.get("points") or {}).items():
        if q not in truth:
            continue
        err = np.asarray(e["est"], float) - np.asarray(truth[q], float)
        if np.trace(np.asarray(e["cov"], float)) <= EXACT_MM**2 and np.all(np.abs(err) <= EXACT_MM):
            continue  # no parameter moves it (a joint of a body the fit does not scale): nothing estimated
        z, d2 = _point_scores(err, e["cov"])
        kind = "joint centres (parent body frame)" if q.startswith("joint") else "markers (own body frame)"
        t = c.setdefault("points", {}).setdefault(kind, {"z": [], "d2": [], "err": []})
        t["z"] += list(z)
        t["d2"].append(d2)
        t["err"] += list(err)
        if q.startswith("joint"):
            j = c.setdefault("joints", {}).setdefault(q[len("joint "):], {"err": [], "sd": [], "z": [], "d2": []})
            j["err"].append(float(np.linalg.norm(err)))
            j["sd"].append(float(np.sqrt(max(np.trace(np.asarray(e["cov"], float)), 0.0) / 3.0)))
            j["z"] += list(z)
            j["d2"].append(d2)


def _points_summary(c: dict) -> dict:
    """Per kind and per joint: coverage per axis and of the 3-D region, rms z, RMSE."""
    def cover(t):
        z, d2 = np.asarray(t["z"], float), np.asarray(t["d2"], float)
        finite = z[np.isfinite(z)]
        return {"coverage95_axes": float(np.mean(z <= Z95)), "rms_z": float(np.sqrt(np.mean(np.square(finite)))),
                "share_nil_sd": float(np.mean(~np.isfinite(z))),
                "region_coverage95": float(np.mean(d2 <= CHI2_3_95)), "median_d2_over_3": float(np.median(d2) / 3.0)}
    out = {}
    if c.get("points"):
        out["points"] = {k: {"n": len(t["d2"]), "rmse_mm": float(np.sqrt(np.mean(np.square(t["err"]))))} | cover(t)
                         for k, t in sorted(c["points"].items())}
    if c.get("joints"):
        out["joints"] = {k: {"n": len(t["d2"]), "rmse_3d_mm": float(np.sqrt(np.mean(np.square(t["err"])))),
                             "mean_sd_mm": float(np.mean(t["sd"]))} | cover(t) for k, t in sorted(c["joints"].items())}
    return out


def markdown(res: dict) -> str:
    p = res["provenance"]
    setup = SETUPS[res.get("model", "gait2354")]
    lines = ["# OpenSim-generated truth: skelid's OpenSim scaling against known geometry", "",
             f"Model: {setup.title}, `{setup.generic.relative_to(SHARED.parent.parent)}`.", "",
             f"{'REDUCED run (--quick). ' if res['quick'] else ''}{res['draws_done']} of {res['draws_planned']} "
             f"planned draws done ({res['reps']} planned per cell; each cell's own count is in its heading; "
             f"geometry drawn per draw). Commit `{p['commit'][:10]}`, {p['date']}, {p['cpu']}, "
             f"{p['cores']} cores, load "
             f"{p['load_average']} at the start; `{p['command']}`; {res['wall_s']:.0f} s wall.", "",
             "Cell = truth / fit / design / noise (a number: i.i.d. sd in mm; `pm`: per-marker sd 1-10 mm; "
             "`sta`: soft-tissue artefact 5-15 mm rms per body plus 1 mm, never told to the estimator, linear in "
             "the joint angles in each body's frame; `stalab`: the same in the laboratory's frame, a form "
             "skelid's slide does not hold; a sliding marker's true offset and place are where the artefact "
             "puts it at the zero pose)."
             " Truth `bodies`: one factor per body; `axes`: one per "
             "axis (both uniform in [0.85, 1.15], offsets 1-20 mm long, for the bodies that carry markers); `every`: "
             "one per axis for every body, those without markers (talus, toes, patella, forearm, hand) "
             "included, as OpenSim's scale setups scale them; `prior`: per axis, factors and offsets "
             "drawn from the fit's own priors (log-normal sd 0.15, normal 10 mm), where a right posterior "
             "covers 95 % of every quantity, also of those the data leave to the prior. Fit on the generic "
             "model: `linked`, `fit_osim(scale='linked')` (the default), three factors per body whose logs are "
             "correlated 0.8 a priori; `bodies`: one factor per body; `axes`: three independent ones, the "
             "exact structure; "
             "`axes+pm`: the same as `axes` with `noise='per_marker'`. Marker offsets are pooled over "
             "every marker and axis (per-offset rows in the JSON). Body-frame rows: each joint centre in its parent "
             "body's frame and each marker in its own body's frame at the zero pose (mm), the same quantities "
             "whatever the fit's parametrisation (a one-factor fit's offsets and factor are not the per-axis "
             "truth's); their sd by the delta method over the fit's covariance; region coverage: the 95 % "
             "ellipsoid (chi2_3) covers the truth (a coordinate the fit holds exact, with a nil sd, and the truth "
             "elsewhere is a miss). \"Artefact term added\": the fit found a "
             "pose-dependent artefact in its residuals (F test) and added its effect to the intervals; "
             "\"named\": it also warned. Pooled rows: every (parameter, draw) pair, data-determined where the "
             f"fit's bound is at most {IDENTIFIED_SHARE} of the prior's sd, else prior-dominated; rms z is the root "
             "mean square of error / reported sd (1 where the sd is right, below 1 where it is wide). "
             "ScaleTool rows: OpenSim's measurement-based scaling on the same static "
             "trial (error of each "
             "axis' factor against the truth's).", ""]
    for key, c in res["cells"].items():
        head = f"## {key}: {c['n']} draws, {c['failed']} failed, {_f(c['cpu_s_per_fit'], 1)} s CPU per fit"
        if c.get("sigma_mean") is not None:
            head += f", mean sigma {c['sigma_mean']:.3f} mm, warned in {c['share_warned']:.0%}"
            if c.get("share_artefact_named") is not None:
                head += f", artefact named in {c['share_artefact_named']:.0%}"
            if c.get("share_artefact_term") is not None:
                head += f", artefact term added in {c['share_artefact_term']:.0%}"
        lines += [head, ""]
        if c["errors"]:
            lines += [f"Failures: {'; '.join(c['errors'])}", ""]
        if not c["rows"]:
            continue
        st = "sd" not in next(iter(c["rows"].values()), {}) and "mean_sd" not in next(iter(c["rows"].values()))
        if st:
            lines += ["| quantity | bias | RMSE |", "|---|---|---|"]
            for q, r in c["rows"].items():
                lines.append(f"| {q} | {_f(r['bias'], 4)} | {_f(r['rmse'], 4)} |")
            lines.append("")
            continue
        lines += ["| quantity | bias | bias/CRLB | RMSE | RMSE/CRLB | RMSE/mean sd | coverage 95 % "
                  "| mean sd / actual sd |", "|---|---|---|---|---|---|---|---|"]
        pooled: dict = {}
        for q, r in c["rows"].items():
            if q.startswith("offset"):
                for k in ("bias_over_crlb", "rmse_over_crlb", "rmse_over_sd", "coverage95", "sd_ratio", "rmse",
                          "bias"):
                    pooled.setdefault(k, []).append(r[k])
                continue
            lines.append(f"| {q} | {_f(r['bias'], 4)} | {_f(r['bias_over_crlb'])} | {_f(r['rmse'], 4)} | "
                         f"{_f(r['rmse_over_crlb'])} | {_f(r['rmse_over_sd'])} | {_f(r['coverage95'])} | "
                         f"{_f(r['sd_ratio'])} |")
        if pooled:
            m = {k: _nanmean(v) for k, v in pooled.items()}
            lo = _nanmin(pooled["coverage95"])
            lines.append(f"| offsets, mean over {len(pooled['bias'])} (mm) | {_f(m['bias'], 3)} | "
                         f"{_f(m['bias_over_crlb'])} | {_f(m['rmse'], 3)} | {_f(m['rmse_over_crlb'])} | "
                         f"{_f(m['rmse_over_sd'])} | {_f(m['coverage95'])} (min {_f(lo)}) | {_f(m['sd_ratio'])} |")
        lines.append("")
        lines += _points_markdown(c) + _angles_markdown(c)
        if c.get("classes"):
            lines += ["| pooled over parameters and draws | n | coverage 95 % | rms z (1 = right) |",
                      "|---|---|---|---|"]
            lines += [f"| {k} | {v['n']} | {_f(v['coverage95'])} | {_f(v['rms_z'])} |" for k, v in c["classes"].items()]
            lines.append("")
    return "\n".join(lines) + "\n"


def _angles_markdown(c: dict) -> list[str]:
    """Joint angles of the walks against the coordinates that made them (``--angles``)."""
    a = c.get("angles")
    if not a:
        return []
    lines = ["| joint angle (walk frames, `skelid ik`) | unit | coverage 95 % | rms z | RMSE | mean sd "
             "| geometry's share of the variance |", "|---|---|---|---|---|---|---|"]
    lines += [f"| {n} | {v['unit']} | {_f(v['coverage95'])} | {_f(v['rms_z'])} | {_f(v['rmse'])} | "
              f"{_f(v['mean_sd'])} | {_f(v['geometry_share'])} |" for n, v in a.items()]
    cov = [v["coverage95"] for v in a.values()]
    return lines + [f"| all {len(cov)} coordinates | | {_f(min(cov))}-{_f(max(cov))} | | | | |", ""]


def _points_markdown(c: dict) -> list[str]:
    """The body-frame tables: joint centres one by one, then joint centres and markers pooled."""
    lines = []
    if c.get("joints"):
        lines += ["| joint centre in its parent body | RMSE 3-D (mm) | mean sd per axis (mm) | coverage per axis "
                  "| region coverage (chi2_3) | median d2/3 |", "|---|---|---|---|---|---|"]
        lines += [f"| {k} | {_f(v['rmse_3d_mm'], 1)} | {_f(v['mean_sd_mm'], 1)} | {_f(v['coverage95_axes'])} | "
                  f"{_f(v['region_coverage95'])} | {_f(v['median_d2_over_3'])} |" for k, v in c["joints"].items()]
        lines.append("")
    if c.get("points"):
        lines += ["| pooled over points and draws | points | RMSE per axis (mm) | coverage per axis | rms z | "
                  "region coverage (chi2_3) |", "|---|---|---|---|---|---|"]
        lines += [f"| {k} | {v['n']} | {_f(v['rmse_mm'], 1)} | {_f(v['coverage95_axes'])} | {_f(v['rms_z'])} | "
                  f"{_f(v['region_coverage95'])} |" for k, v in c["points"].items()]
        lines.append("")
    return lines


def _f(v, digits: int = 2) -> str:
    """A number for the table; '-' where it is undefined (one draw, a zero sd)."""
    if v is None or not np.isfinite(v):
        return "-"
    return f"{v:.{digits}f}"


def _nanmean(v) -> float:
    a = np.array([np.nan if x is None else x for x in v], float)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else float("nan")


def _nanmin(v) -> float:
    a = np.array([np.nan if x is None else x for x in v], float)
    a = a[np.isfinite(a)]
    return float(a.min()) if a.size else float("nan")


def parse_cells(cells) -> list[tuple]:
    out = []
    for c in cells:
        t, f, d, n = c.split("/")
        if d not in DESIGNS:
            raise SystemExit(f"unknown design {d!r}: one of {', '.join(DESIGNS)}")
        out.append((t, f, d, noise_token(n)))
    return out


def default_cells(quick: bool) -> list[tuple]:
    noises = ("0", "5") if quick else tuple(noise_token(n) for n in NOISES) + ("pm", *STA)
    designs = DESIGNS[:2] if quick else DESIGNS
    return [(t, f, d, n) for t, f in CONFIGS for d in designs for n in noises]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--cells", nargs="*", help="truth/fit/design/noise, e.g. axes/axes/walk/5")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="3 draws, noise 0 and 5 mm only")
    ap.add_argument("--no-peer", action="store_true", help="skip OpenSim's ScaleTool")
    ap.add_argument("--model", choices=sorted(SETUPS), default="gait2354",
                    help="the generic model and its trials (default gait2354; rajagopal: addbio-subject4's "
                         "full-body model)")
    ap.add_argument("--out", type=Path, default=None,
                    help="results path without suffix (default benchmarks/results/opensim_truth, with _MODEL for "
                         "a model other than gait2354)")
    ap.add_argument("--seed", type=int, default=20261202)
    ap.add_argument("--angles", type=int, default=None, metavar="DRAWS",
                    help="also score skelid's joint angles of each walk against the true coordinates, with this "
                         "many draws of the geometry (0: its first-order effect)")
    ap.add_argument("--rescore", action="store_true",
                    help="recompute the true values of the results at --out from each draw's seed; no fit is run")
    args = ap.parse_args(argv)
    use_model(args.model)
    if args.out is None:
        args.out = OUT if args.model == "gait2354" else OUT.with_name(f"{OUT.name}_{args.model}")
    if args.rescore:
        rescore(args.out)
        return
    reps = 3 if args.quick and args.reps == 20 else args.reps
    cells = parse_cells(args.cells) if args.cells else default_cells(args.quick)
    prov = provenance(None if argv is None else ["benchmarks/opensim_truth.py", *argv])
    motions()  # the IK once, before any worker needs it
    # one draw generates the data of every cell sharing its truth and noise
    groups: dict = {}
    for t, f, d, n in cells:
        g = groups.setdefault((t, n), {"designs": [], "fits": []})
        g["designs"] += [d] if d not in g["designs"] else []
        g["fits"] += [f] if f not in g["fits"] else []
    w0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as work:
        tasks = []  # rep by rep, so that every cell has about as many draws whenever the run stops
        for r in range(reps):
            for gi, ((t, n), g) in enumerate(sorted(groups.items())):
                seed = args.seed + 1000 * r + gi
                tasks.append((args.model, t, n, seed, tuple(g["designs"]), tuple(g["fits"]), not args.no_peer,
                              work, args.angles))
        keep = {f"{t}/{f}/{d}/{n}" for t, f, d, n in cells}
        draws = []

        def record(draw, k):  # the results so far are written after every draw
            draw["fits"] = {key: v for key, v in draw["fits"].items() if key in keep}
            draws.append(draw)
            print(f"draw {k + 1}/{len(tasks)} {draw['truth_kind']} noise {draw['noise']}: "
                  f"{time.perf_counter() - w0:.0f} s", flush=True)
            res = {"provenance": prov, "model": args.model, "quick": bool(args.quick), "reps": reps,
                   "draws_done": len(draws),
                   "draws_planned": len(tasks), "wall_s": time.perf_counter() - w0, "cells": summarise(draws),
                   "draws": draws}
            write_results(args.out, _finite(res), markdown, quiet=k + 1 < len(tasks))
        if args.jobs > 1:
            with ProcessPoolExecutor(args.jobs) as pool:
                for k, draw in enumerate(pool.map(run_draw, tasks)):
                    record(draw, k)
        else:
            for k, task in enumerate(tasks):
                record(run_draw(task), k)


def rescore(path: Path) -> None:
    """Rewrite a results file's true values from each draw's seed (the truth is drawn from it), then its tables.

    For results written before a quantity was scored: the fits are not rerun; each fit's
    ``truth`` is recomputed by :func:`draw_truth` and :func:`true_values` (the lengths, which
    OpenSim's kinematics gave, and under the artefact the offsets, which its draw moved, are kept).
    """
    import json

    res = json.loads(path.with_suffix(".json").read_text())
    use_model(res.get("model", "gait2354"))
    g = generic_model()
    mnames = [g.getMarkerSet().get(i).getName() for i in range(g.getMarkerSet().getSize())]
    for d in res["draws"]:
        truth = draw_truth(np.random.default_rng(d["seed"]), d["truth_kind"], mnames)
        for key, r in d["fits"].items():
            if "error" in r:
                continue
            lengths = {q[len("length "):]: v for q, v in r["truth"].items() if q.startswith("length ")}
            tv = true_values(truth, lengths, key.split("/")[1].partition("+")[0])
            if d["noise"] in STA:  # a sliding marker's offset depends on the artefact's draw: kept as recorded
                tv.update({k: v for k, v in r["truth"].items() if k.startswith("offset ")})
            r["truth"] = {k: tv[k] for k in r["q"] if k in tv}
    res["cells"] = summarise(res["draws"])
    res["rescored"] = "true values recomputed from each draw's seed by --rescore"
    write_results(path, _finite(res), markdown, quiet=True)


def _finite(obj):
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _finite(obj.tolist())
    if isinstance(obj, float | np.floating):
        return float(obj) if np.isfinite(obj) else None
    if isinstance(obj, np.integer | np.bool_):
        return obj.item()
    return obj


if __name__ == "__main__":
    main()
