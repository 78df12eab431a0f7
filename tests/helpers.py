"""Models built in Python for tests, and the shared ways tests run skelid and its scripts."""

import importlib.util
import sys
from pathlib import Path

import numpy as np

from skelid.model import model_from_dict


def tree_3d():
    """A small 3-D tree with every joint type and every parameter kind."""
    return model_from_dict({
        "model": {"name": "tree3d", "dim": 3, "units": "mm"},
        "segments": [
            {"name": "pelvis", "parent": "ground", "joint": {"type": "free", "name": "root"}},
            {"name": "thigh", "parent": "pelvis",
             "joint": {"type": "spherical", "name": "hip", "position": [0, -80, -90]}},
            {"name": "shank", "parent": "thigh",
             "joint": {"type": "hinge", "name": "knee", "position": [0, -400, 0], "axis": [0, 0, 1]}},
            {"name": "foot", "parent": "shank",
             "joint": {"type": "universal", "name": "ankle", "position": [0, -380, 0],
                       "axes": [[0, 0, 1], [1, 0, 0]]}},
            {"name": "arm", "parent": "pelvis",
             "joint": {"type": "fixed", "name": "weld", "position": [0, 300, 0]}},
        ],
        "markers": [
            {"name": "p1", "segment": "pelvis", "position": [50, 0, 100]},
            {"name": "p2", "segment": "pelvis", "position": [50, 0, -100]},
            {"name": "p3", "segment": "pelvis", "position": [-80, 30, 0]},
            {"name": "t1", "segment": "thigh", "position": [40, -150, 20]},
            {"name": "t2", "segment": "thigh", "position": [-30, -250, 40]},
            {"name": "s1", "segment": "shank", "position": [30, -100, 25]},
            {"name": "s2", "segment": "shank", "position": [-20, -300, 30]},
            {"name": "f1", "segment": "foot", "position": [120, -40, 0]},
            {"name": "f2", "segment": "foot", "position": [-40, -50, 30]},
            {"name": "a1", "segment": "arm", "position": [10, 20, 30]},
        ],
        "parameters": [
            {"name": "thigh_length", "kind": "length", "joint": "knee",
             "prior": {"type": "uniform", "lower": 300, "upper": 500}},
            {"name": "hip_x", "kind": "joint_position", "joint": "hip", "axis": "x",
             "prior": {"type": "normal", "mean": 0, "sd": 20}},
            {"name": "s1_z", "kind": "marker_position", "marker": "s1", "axis": "z",
             "prior": {"type": "lognormal", "median": 25, "sd_log": 0.3}},
        ],
    })


def custom_leg():
    """A 3-D leg of custom joints as OpenSim writes them: a root whose translations come after its rotations
    in the coordinate order but move first, a hip of three plain rotations, a knee that turns by its
    angle and slides by two splines of it (scaled by the thigh's length), an ankle turned by a cubic of
    its angle and set off by a constant translation, then a constant rotation, and toes welded on at an angle."""
    ident = {"type": "linear", "coefficients": [1.0, 0.0]}

    def motion(kind, axis, coordinate=None, function=ident):
        return {"kind": kind, "axis": axis, "function": function} | ({"coordinate": coordinate} if coordinate
                                                                     else {})

    c = 0.5 ** 0.5
    return model_from_dict({
        "model": {"name": "custom_leg", "dim": 3, "units": "mm"},
        "segments": [
            {"name": "pelvis", "parent": "ground",
             "joint": {"type": "custom", "name": "root", "coordinates": ["tilt", "list", "rot", "tx", "ty", "tz"],
                       "motions": [motion("translation", [1, 0, 0], "tx"), motion("translation", [0, 1, 0], "ty"),
                                   motion("translation", [0, 0, 1], "tz"), motion("rotation", [0, 0, 1], "tilt"),
                                   motion("rotation", [1, 0, 0], "list"), motion("rotation", [0, 1, 0], "rot")]}},
            {"name": "thigh", "parent": "pelvis",
             "joint": {"type": "custom", "name": "hip", "position": [-70, -66, 83],
                       "coordinates": ["flex", "add", "int"],
                       "motions": [motion("rotation", [0, 0, 1], "flex"), motion("rotation", [1, 0, 0], "add"),
                                   motion("rotation", [0, 1, 0], "int")]}},
            {"name": "shank", "parent": "thigh",
             "joint": {"type": "custom", "name": "knee", "position": [0, -400, 0], "coordinates": ["knee"],
                       "motions": [
                           motion("translation", [1, 0, 0], "knee", {"type": "spline", "end": "fmm",
                                  "x": [-2.09, -1.22, -0.52, -0.35, 0.0, 0.17],
                                  "y": [-3.2, 1.8, 4.1, 4.1, -0.8, -5.2]}),
                           motion("translation", [0, 1, 0], "knee", {"type": "spline",
                                  "x": [-2.09, -1.05, 0.0, 0.17], "y": [-422.0, -406.0, -396.0, -395.0]}),
                           motion("rotation", [0, 0, 1], "knee")]}},
            {"name": "foot", "parent": "shank",
             "joint": {"type": "custom", "name": "ankle", "position": [0, 0, 0], "coordinates": ["ankle"],
                       "orientation": [[c, -c, 0], [c, c, 0], [0, 0, 1]],
                       "motions": [motion("translation", [0, 1, 0], None,
                                          {"type": "constant", "coefficients": [-20.0]}),
                                   motion("rotation", [-0.105, -0.174, 0.979], "ankle",
                                          {"type": "polynomial", "coefficients": [0.05, 0.0, 0.9, 0.01]})]}},
            {"name": "toes", "parent": "foot",
             "joint": {"type": "custom", "name": "mtp", "position": [150, -20, 0], "coordinates": [], "motions": [],
                       "orientation": [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]}},
        ],
        "markers": [
            {"name": "p1", "segment": "pelvis", "position": [50, 0, 100]},
            {"name": "p2", "segment": "pelvis", "position": [50, 0, -100]},
            {"name": "p3", "segment": "pelvis", "position": [-80, 30, 0]},
            {"name": "t1", "segment": "thigh", "position": [40, -150, 20]},
            {"name": "t2", "segment": "thigh", "position": [-30, -250, 40]},
            {"name": "t3", "segment": "thigh", "position": [10, -350, -45]},
            {"name": "s1", "segment": "shank", "position": [30, -100, 25]},
            {"name": "s2", "segment": "shank", "position": [-20, -300, 30]},
            {"name": "s3", "segment": "shank", "position": [5, -200, -40]},
            {"name": "f1", "segment": "foot", "position": [120, -40, 0]},
            {"name": "f2", "segment": "foot", "position": [-40, -50, 30]},
            {"name": "f3", "segment": "foot", "position": [60, -60, -35]},
            {"name": "toe", "segment": "toes", "position": [40, -10, 15]},
        ],
        "parameters": [
            {"name": "scale_thigh", "kind": "scale", "segment": "thigh",
             "prior": {"type": "lognormal", "median": 1.0, "sd_log": 0.1}},
            {"name": "s3_z", "kind": "marker_position", "marker": "s3", "axis": "z",
             "prior": {"type": "normal", "mean": -40, "sd": 10}},
        ],
    })


def tree_3d_functional():
    """The 3-D test tree with vector, joint-centre and hinge-axis parameters."""
    d = tree_3d().to_dict()
    d["parameters"] = [
        {"name": "hip", "kind": "joint_centre", "joint": "hip", "axes": ["x", "y", "z"],
         "prior": {"type": "uniform", "lower": -40, "upper": 40}},
        {"name": "knee", "kind": "joint_centre", "joint": "knee", "axes": ["x", "y"],
         "prior": {"type": "normal", "sd": 15}},
        {"name": "knee_axis", "kind": "axis_direction", "joint": "knee", "axes": ["u", "v"],
         "prior": {"type": "uniform", "lower": -20, "upper": 20}},
        {"name": "f1", "kind": "marker_position", "marker": "f1", "axes": ["x", "z"],
         "prior": [{"type": "normal", "sd": 10}, {"type": "uniform", "lower": -30, "upper": 30}]},
        {"name": "arm_offset", "kind": "length", "joint": "weld",
         "prior": {"type": "uniform", "lower": 250, "upper": 350}},
    ]
    return model_from_dict(d, "tree3d_functional")


def run_cli(args, cwd=None, memory_mb: int | None = 3000, timeout: float = 120, env=None):
    """Run ``skelid ARGS`` in a fresh Python process under an address-space limit.

    Returns the ``subprocess.CompletedProcess`` (text mode). ``memory_mb`` caps
    the child's virtual memory (``RLIMIT_AS``), so a job that would allocate
    without bound fails fast instead of taking the machine down.
    """
    import os
    import resource
    import subprocess

    def limit():  # pragma: no cover - runs in the child
        if memory_mb is not None:
            n = memory_mb * 2**20
            resource.setrlimit(resource.RLIMIT_AS, (n, n))

    code = "import sys; from skelid.cli import main; sys.exit(main(sys.argv[1:]))"
    full_env = {**os.environ, "NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
                **(env or {})}
    return subprocess.run([sys.executable, "-c", code, *map(str, args)], cwd=cwd, capture_output=True,
                          text=True, timeout=timeout, preexec_fn=limit, env=full_env, stdin=subprocess.DEVNULL)


def opensim_marker_gap(model, osim_model, rng, n_poses: int = 100, limit: float = 3.141592653589793,
                       theta=None) -> float:
    """Largest distance (mm) between skelid's and OpenSim's markers over random poses.

    ``model`` is the skelid import of ``osim_model`` (an ``opensim.Model`` whose
    system is not yet built). Each pose draws every coordinate of ``model``
    uniformly in its OpenSim range (clipped to +-``limit`` rad, +-0.1 m for a
    translation), sets it in the state without enforcing constraints, assembles
    the model when it has constraints and reads the coordinates back, so both
    sides use the values OpenSim's markers are computed at. ``theta``: the
    parameters of ``model`` (none by default).
    """
    import numpy as np

    from skelid.model.kinematics import marker_positions

    state = osim_model.initSystem()
    coords = osim_model.getCoordinateSet()
    names = [c for s in model.segments for c in s.joint.coordinates]
    translational = [coords.get(n).getMotionType() == 2 for n in names]
    markers = osim_model.getMarkerSet()
    worst = 0.0
    for _ in range(n_poses):
        for n, is_t in zip(names, translational, strict=True):
            c = coords.get(n)
            lim = 0.1 if is_t else limit
            c.setValue(state, rng.uniform(max(c.getRangeMin(), -lim), min(c.getRangeMax(), lim)), False)
        if osim_model.getConstraintSet().getSize():
            osim_model.assemble(state)
        osim_model.realizePosition(state)
        q = np.array([coords.get(n).getValue(state) * (1000.0 if is_t else 1.0)
                      for n, is_t in zip(names, translational, strict=True)])
        x = marker_positions(model, np.zeros(0) if theta is None else np.asarray(theta, float), q)
        ref = np.array([[markers.get(m.name).getLocationInGround(state).get(i) for i in range(3)]
                        for m in model.markers]) * 1000.0
        worst = max(worst, float(np.abs(x - ref).max()))
    return worst


def leg_walk_poses(n_frames: int, n_pose: int, rate: float = 60.0) -> np.ndarray:
    """``(F, Q)`` poses of the test leg's walk: pelvis at (100, 900, 50) mm, each joint swinging at its own rate."""
    t = np.arange(n_frames) / rate
    q = np.zeros((n_frames, n_pose))
    q[:, 3:6] = [100.0, 900.0, 50.0]
    q[:, 6] = 0.5 * np.sin(2 * np.pi * 1.1 * t)
    q[:, 7] = 0.3 * np.sin(2 * np.pi * 0.7 * t + 1)
    q[:, 8] = 0.3 * np.sin(2 * np.pi * 0.9 * t + 2)
    q[:, 9] = -0.9 + 0.8 * np.sin(2 * np.pi * 1.3 * t)
    q[:, 0] = 0.2 * np.sin(2 * np.pi * 0.5 * t)
    return q


def load_script(path, name: str | None = None):
    """A script of the repository (a benchmark, an example) imported as a module, without running its main."""
    path = Path(path)
    spec = importlib.util.spec_from_file_location(name or path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # a dataclass of the script looks its module up there
    spec.loader.exec_module(mod)
    return mod
